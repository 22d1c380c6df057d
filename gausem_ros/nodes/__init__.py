"""GauSem's ROS 2 nodes (docs/DESIGN.md §4). Each module holds one node class and its ``main(args=None)`` entry point.

- ``segmentation``: rgb/image -> semantic/labels (mono16) + semantic/color (rgb8), with a segmenter that works on the
  image alone (``semantics.segmenter: ade20k`` or ``dinov2``). With ``labels`` the class ids come with the data: the
  player (or another robot stack) publishes semantic/labels and this node is not run.
- ``tracking_mapping``: owns the SLAM system and the map; odometry, path, TF, map, grid, keyframe and submap records
  (and with ``loop_closure: nodes`` place signatures), services gausem/save_map, gausem/load_map, gausem/finish and
  gausem/reset. Its parts (one output each) are in the ``tracking`` subpackage.
- ``loop_detection``: place signatures -> ranked loop candidates (paper Algorithm 1, the core's LoopDetector).
- ``pose_graph``: keyframe and submap records + loop constraints -> corrected keyframe and anchor poses (GTSAM).
"""
NODE_MODULES = ("segmentation", "tracking_mapping", "loop_detection", "pose_graph")
