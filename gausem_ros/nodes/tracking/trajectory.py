"""The tracked camera's outputs: ``gausem/odometry``, ``gausem/path`` and TF.

``gausem/odometry``: nav_msgs/Odometry of the camera frame (``camera_frame``, else the rgb image's frame_id) in
``map_frame``, stamped like the rgb image; a degraded frame's pose covariance has ``DEGRADED_VARIANCE`` on its
diagonal (zero, i.e. unknown, when ok). ``gausem/path`` (latched): re-published after every frame with its pose
appended, rebuilt from the trajectory after a correction; frames judged lost are in neither. TF by REP-105
(:mod:`gausem_ros.frames`; needs tf2_ros or tf2_msgs, which the pip set-up builds): ``map_frame -> odom_frame`` (the
map's corrections) and ``odom_frame ->`` camera (the motion as tracked, never jumping), or with ``base_frame`` set
``odom_frame -> base_frame`` and on /tf_static ``base_frame ->`` camera (``camera_extrinsic``: x y z qx qy qz qw of the
camera in the base frame), stamped like the frame and composing to its odometry; a correction between frames (a
pose-graph answer, the global refinement) reaches TF with the next frame, as tf2 ignores a second transform at a
stamp it holds. Published poses are projected onto SE(3) in float64.
"""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from nav_msgs.msg import Odometry, Path

import msg_adapters as ma
from gausem_core.geometry import rigid_float64
from gausem_core.slam.events import FrameEvents
from gausem_core.slam.system import FrameResult, GauSemSLAM

from ...frames import Rep105Frames, inverse
from ...qos import EVENT_QOS, LATCHED_QOS
from ...tf import make_transform_broadcaster

DEGRADED_VARIANCE = 1.0  # m^2 and rad^2 on the odometry's pose covariance diagonal for a degraded frame


def path_poses(slam: GauSemSLAM) -> list[tuple[float, np.ndarray]]:
    """(stamp, map-from-camera float64) of the frames a path rebuilt from ``slam``'s trajectory holds: not the lost
    ones, nor one whose pose is not finite."""
    poses = ((t, rigid_float64(p).numpy()) for t, p in slam.trajectory(False))
    return [(t, m) for t, m in poses if np.isfinite(m).all()]


class TrajectoryPublisher:
    """Odometry, path and TF of one map's frames (:meth:`reset` with each new map); ``tf_static``: the node's
    /tf_static broadcaster."""

    def __init__(self, node, params: SimpleNamespace, tf_static):
        self._params = params
        self._frames = Rep105Frames(params.map_frame, params.odom_frame, params.base_frame, params.camera_extrinsic)
        self._odometry_pub = node.create_publisher(Odometry, "gausem/odometry", EVENT_QOS)
        self._path_pub = node.create_publisher(Path, "gausem/path", LATCHED_QOS)
        self._tf = make_transform_broadcaster(node)
        self._tf_static = tf_static
        self._static_camera_frame = ""  # the camera frame the static base_frame -> camera was sent for
        self._camera_frame = params.camera_frame or "camera"

    def reset(self, slam: GauSemSLAM) -> None:
        self._slam = slam
        self._path: Path | None = None  # the published path (None: rebuild it from the trajectory)
        self._tf_last: int | None = None  # the last frame (id in this map) whose transforms were sent

    def publish_odometry(self, pose: np.ndarray, stamp: float, image_frame: str, degraded: bool) -> None:
        """A tracked frame's pose (map-from-camera, float64) in the frame of its rgb image (``image_frame``)."""
        self._camera_frame = self._params.camera_frame or image_frame or "camera"
        odometry = ma.matrix_to_odometry(pose, ma.make_header(stamp, self._params.map_frame), self._camera_frame)
        if degraded:
            odometry.pose.covariance = (DEGRADED_VARIANCE * np.eye(6)).ravel().tolist()
        self._odometry_pub.publish(odometry)

    def publish_motion(self, result: FrameResult, pose: np.ndarray, stamp: float) -> None:
        """After its odometry: the frame's transforms, then the path with its pose (rebuilt when the frame's loop
        closure moved the map)."""
        self._send_transforms(result, pose, stamp)
        self.note_events(result.events)
        self.publish_path((stamp, pose))

    def note_events(self, events: FrameEvents) -> None:
        """A frame's events: when its loop closure moved the map, the next path published is rebuilt."""
        if events.loop is not None and events.loop.correction:
            self.path_corrected()

    def path_corrected(self) -> None:
        """The map moved: the next path published is rebuilt from the trajectory."""
        self._path = None

    def publish_path(self, new: tuple[float, np.ndarray] | None = None) -> None:
        """The path with the ``new`` (stamp, pose) appended (one pose converted a frame); rebuilt from the whole
        trajectory after a correction. Frames judged lost are in neither (nor in save_map's trajectory), as they
        publish no odometry."""
        map_frame = self._params.map_frame
        if self._path is None:
            self._path = ma.poses_to_path(path_poses(self._slam), map_frame)
        elif new is not None:
            entry = ma.matrix_to_pose_stamped(new[1], ma.make_header(new[0], map_frame))
            self._path.poses.append(entry)
            self._path.header = entry.header
        self._path_pub.publish(self._path)

    def _send_transforms(self, result: FrameResult, pose: np.ndarray, stamp: float) -> None:
        """``map -> odom -> camera`` (or ``-> base``), with the motion since the last frame sent from both frames'
        map poses as they are now (none for a relocalised frame); the static ``base -> camera`` once per camera
        frame name."""
        motion = None
        if self._tf_last is not None and result.relocalisation is None:
            with self._slam.lock:  # both poses after the same corrections (the mapping worker corrects in parallel)
                last, current = (rigid_float64(self._slam.frames[i].cam_to_world).numpy()
                                 for i in (self._tf_last, result.frame_id))
            motion = inverse(last) @ current
        self._tf_last = result.frame_id
        self._tf.sendTransform(self._frames.transforms(stamp, self._camera_frame, pose, motion))
        if self._tf_static is not None and self._static_camera_frame != self._camera_frame:
            self._static_camera_frame = self._camera_frame
            self._tf_static.sendTransform(self._frames.static_transforms(stamp, self._camera_frame))
