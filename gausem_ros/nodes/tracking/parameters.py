"""tracking_mapping's own parameters (docs/ROS.md has the table) and the checks that fail the node at start."""
from __future__ import annotations

from types import SimpleNamespace

from gausem_core.config import SlamConfig
from gausem_core.runtime import smallest_image_side

NODE_DEFAULTS = {
    "classes": "synthetic",      # class table of the labels: synthetic, nyu40, scannet20 or a class-table file
    "use_labels": True,          # False: no semantic/labels input (e.g. TUM), every pixel is one class
    "map_frame": "map",
    "odom_frame": "odom",
    "base_frame": "",            # "" = none: TF odom -> camera; else odom -> base_frame and static base_frame -> camera
    "camera_extrinsic": [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0],  # with base_frame: the camera in it, x y z qx qy qz qw
    "camera_frame": "",          # "" = the rgb image's header frame_id
    "input_qos": "reliable",     # or "sensor_data" for a live camera driver
    "sync_queue_size": 10,
    "sync_slop": 0.02,           # seconds
    "sync_wait": 5.0,            # seconds an rgb/depth/labels message waits for its partners before it is dropped as
    # unmatched (0: until a later frame matches; a lock-step replay sends none, so its player would wait its timeout)
    "map_publish_period": 2.0,   # seconds
    "map_voxel_size": 0.05,      # metres: gausem/map holds one Gaussian per voxel of each submap (0: every Gaussian)
    "grid_frame": "floor",       # the grid's frame: level, on the estimated floor, map -> grid_frame on /tf_static
    # (re-sent when the floor estimate moves); "": the map frame, the grid's origin then tilted in it
    "grid_publish_period": 5.0,  # seconds between occupancy grids at most (one after new keyframes or a map
    # correction; 0: no grid)
    "min_valid_depth": 0.05,     # fraction of pixels with a valid depth below which a frame is dropped
    "min_image_size": 16,        # pixels: frames with a smaller side are dropped (bad_size); >= the pyramids' need
    "max_image_pixels": 1280 * 720,  # larger frames are downscaled to at most this many pixels (aspect kept)
    "output_dir": "gausem_output",
    "loop_closure": "core",      # or "nodes": see gausem_ros.nodes.tracking.loop_link
    "loop_answer_timeout": 5.0,  # seconds; nodes: the longest wait for loop_detection's and pose_graph's answers
    "save_on_exit": False,       # write map.ply, trajectory.txt and session/ to output_dir when the node shuts down
    "map_path": "",              # a session folder: the map resumes from it when it holds a session, else starts there;
    # checkpoints go there (and gausem/load_map reads it)
    "checkpoint_keyframes": 5,   # with map_path: checkpoint the session every this many new keyframes (0: never) ...
    "checkpoint_period": 60.0,   # ... or this many seconds after the last checkpoint, at the next frame (0: never)
    "viewer": "off",             # or record, web, native: a live 3D view (gausem_ros.nodes.tracking.viewer)
    "viewer_path": "",           # the recording ("" = output_dir/gausem.rrd)
    "viewer_colors": "rgb",      # the map's points coloured by rgb or class
    "viewer_map_every": 10,      # frames between the map's updates in the view
    "viewer_port": 9090,         # viewer web: the web page's port
}
LOOP_CLOSURE_MODES = ("core", "nodes")
LIVE_DEFAULTS = {"worker.mode": "async"}  # a live node maps on the mapping worker, beside its tracker
LOCKSTEP_DEFAULTS = {"worker.mode": "sync"}  # a lock-step replay maps each keyframe before answering: gausem run's


def check_parameters(cfg: SlamConfig, p: SimpleNamespace) -> None:
    """ValueError naming the parameter to change when the node's parameters cannot work (together)."""
    if p.loop_closure not in LOOP_CLOSURE_MODES:
        raise ValueError(f"tracking_mapping: loop_closure must be one of {', '.join(LOOP_CLOSURE_MODES)}, got "
                         f"{p.loop_closure!r}")
    least = smallest_image_side(cfg)
    if p.min_image_size < least:
        raise ValueError(f"tracking_mapping: min_image_size {p.min_image_size} is below {least} pixels, the smallest "
                         "side the image pyramids (tracking.gauss_newton.pyramid_levels, "
                         "loop.registration.pyramid_levels and downsample) can take; raise min_image_size")
    if p.max_image_pixels < p.min_image_size ** 2:
        raise ValueError(f"tracking_mapping: max_image_pixels {p.max_image_pixels} is below min_image_size^2 = "
                         f"{p.min_image_size ** 2}; raise max_image_pixels")
    if p.grid_frame and p.grid_frame in (p.map_frame, p.odom_frame, p.base_frame):
        raise ValueError(f"tracking_mapping: grid_frame {p.grid_frame!r} must differ from map_frame, odom_frame "
                         "and base_frame (\"\" puts the grid in map_frame)")
    if p.sync_wait < 0:
        raise ValueError(f"tracking_mapping: sync_wait must be >= 0 (0: off), got {p.sync_wait}")
    if p.map_voxel_size < 0:
        raise ValueError(f"tracking_mapping: map_voxel_size must be >= 0 (0: every Gaussian), got {p.map_voxel_size}")
    if p.grid_publish_period < 0:
        raise ValueError(f"tracking_mapping: grid_publish_period must be >= 0 (0: no grid), got "
                         f"{p.grid_publish_period}")
