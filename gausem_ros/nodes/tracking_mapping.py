"""The tracking-and-mapping node: owns :class:`GauSemSLAM` (and so the Gaussian map).

Subscribes (relative names, remappable): ``rgb/image`` (rgb8/bgr8/rgba8/bgra8), ``depth/image`` (16UC1 mm or 32FC1 m),
``rgb/camera_info`` (a lens distortion it states is undone: ``gausem_core.data.undistortion``), ``semantic/labels``
(mono8/mono16 class ids; not with ``use_labels: false``), approximately synchronised; with ``loop_closure: nodes``,
``gausem/loop_candidates`` and ``gausem/pose_graph`` (records, ``msg_adapters.records``).
Publishes: ``gausem/odometry`` (nav_msgs/Odometry of the camera frame in ``map_frame``, stamped like the rgb image),
``gausem/path`` (latched, re-published after every frame with its pose appended; rebuilt from the trajectory after a
loop correction), TF by REP-105 (:mod:`gausem_ros.frames`; needs tf2_ros or tf2_msgs, which the pip set-up builds):
``map_frame`` -> ``odom_frame`` (the map's corrections) and ``odom_frame`` -> camera frame (the motion as tracked, never
jumping), or with ``base_frame`` set ``odom_frame`` -> ``base_frame`` and on /tf_static ``base_frame`` -> camera frame
(``camera_extrinsic``: x y z qx qy qz qw of the camera in the base frame), stamped like the frame and composing to its
odometry; a correction between frames (a pose-graph answer, the global refinement) reaches TF with the next frame, as
tf2 ignores a second transform at a stamp it holds,
``gausem/map`` (PointCloud2 of the Gaussians, latched, at most once per ``map_publish_period`` s), ``gausem/grid``
(nav_msgs/OccupancyGrid, latched, rebuilt after new keyframes and map corrections at most once per
``grid_publish_period`` s: ``gausem_core.maps``, parameters ``grid.*``; in ``grid_frame``, level on the estimated floor,
``map_frame -> grid_frame`` on /tf_static), ``gausem/keyframes``
(KeyframeRecord, pose in its submap frame), ``gausem/submaps`` (SubmapEvent), with ``loop_closure: nodes``
``gausem/place_signatures`` (PlaceSignatureRecord of each loop keyframe), ``gausem/loop_constraints``
(LoopConstraintRecord, every accepted loop) and ``gausem/diagnostics`` (dropped inputs by reason, frames processed,
the stamp of
the last frame handled). ``seconds``: the processing time so far, for fps.
Tracking health (``gausem_core.slam.health``): the last frame's ``tracking.status`` (ok / degraded / lost) and signals
(``tracking.inlier_fraction``, ...) are in the diagnostics values, and raise the level (WARN degraded, ERROR lost).
The odometry of a degraded frame has pose covariance ``DEGRADED_VARIANCE`` on its diagonal (zero, i.e. unknown, when
ok); a lost frame is not mapped, publishes no odometry and is dropped as ``tracking_lost``; the next frames are
relocalised against the map (dropped as ``relocalisation_failed`` until one is placed).
Services (std_srvs/Trigger): ``gausem/save_map`` writes ``map.ply``, ``trajectory.txt`` (TUM) and the whole SLAM
state (``session/``, :mod:`gausem_core.slam.persistence`) to ``output_dir``; ``gausem/load_map`` replaces the map by
the session in ``map_path`` (default: ``output_dir/session``); ``gausem/finish`` ends the sequence with the global
refinement (as the offline pipeline does after the last frame); ``gausem/reset`` starts a new map.

Resuming: with ``map_path`` set, the node starts from the session saved there, or, when the folder holds none yet,
starts a new map there; either way it checkpoints the session into it (crash-safe, ``slam.checkpoint``) every
``checkpoint_keyframes`` new keyframes or ``checkpoint_period`` seconds, so a tracker killed and respawned
(``gausem-launch --respawn``) goes on with the map of its last checkpoint, in the same ``map`` frame. The diagnostics
add ``checkpoint.written``, ``checkpoint.frames`` and ``checkpoint.seconds_last`` (what writing it cost). A loaded map is re-published (submaps, keyframes, path, map), so pose_graph rebuilds its graph; with
``loop_closure: nodes`` its loop database goes to loop_detection too (the stored place signatures, flagged loaded, the
first flagged new_map, one at a time in step with loop_detection's answers, before the next frame), so loops close
into the loaded map as with ``core``. The next frames are relocalised against it (the robot is not where the last
saved frame was): until one is placed, frames are dropped as ``relocalisation_failed`` and nothing is published for
them.

Mapping beside tracking: the node's core maps on its mapping worker (``worker.mode: async``, this node's default;
``gausem-ros --lockstep`` and ``gausem-launch --play '... --lockstep'`` make it ``sync``, as ``gausem run``): a frame's
odometry is published once it is tracked, while keyframes, submaps and loops are mapped on the worker; their events
(keyframes, submaps, loop constraints) are published when the worker finishes them, with a later frame. The
diagnostics add ``worker.mode``, ``worker.queue_depth`` (keyframes waiting), ``worker.lag_frames`` (frames tracked
while the last keyframe was being mapped), ``worker.keyframes_superseded`` and ``worker.map_age_frames`` (frames
between the last frame and the newest keyframe of the map it was tracked against). ``worker.tracker_threads`` and
``worker.threads`` split the CPU cores between the two (default: half each).

Live input: the image subscriptions run in their own callback group, so with a multi-threaded executor (as every
GauSem entry point uses) inputs keep arriving while a frame is processed; frames are processed one at a time, the
newest synchronised one first (``NewestFrameQueue``), so a tracker that falls behind skips frames instead of building
a backlog. Every rgb image received is accounted for: processed (a pose published), pending, or dropped and counted
by reason on gausem/diagnostics (``dropped.<reason>``) with a warning: ``superseded`` (a newer frame arrived while
busy), ``lost_in_transport`` (never received: a gap in the publisher's sequence numbers, e.g. the subscription queue
overflowed), ``unmatched`` (no depth/labels within ``sync_slop``, or none yet ``sync_wait`` s after it arrived; the
warning gives the offset seen), ``no_depth`` /
``no_labels`` (that input never arrived: with ``use_labels`` true and no labels, the warning names the parameter;
once it has been silent ``sync_wait`` s, frames are dropped at once instead of each waiting ``sync_wait``),
``stale_stamp`` / ``duplicate_stamp`` (stamps going backwards or repeated), bad input (wrong encodings, data
shorter than the declared size, a side below ``min_image_size``, size mismatches, too little valid depth, no
camera_info yet, labels outside the class table), ``camera_changed`` (a camera that is neither the map's nor a
scaling of it: a frame of a scaled camera is resized to the map's, with a log line), ``tracking_diverged`` (a pose estimate that is not finite: nothing
is published for it) and ``processing_error`` (any input whose handling raises; the node goes on). The core hears
of the frames dropped before it (superseded, lost in transport, unmatched, bad input) with the next frame it gets,
as skipped ones (``GauSemSLAM.process``): its motion model, ``tracking.feature_start`` and
``mapping.coverage_keyframes`` then treat that frame as following a gap, even where a steadily slow node's stamps
cannot show one. Frames of more
than ``max_image_pixels`` pixels are downscaled (aspect kept, intrinsics scaled). ``frames_in``, ``frames_processed``,
``frames_pending`` and the latency from a synchronised frame's arrival to its pose's publication (``latency_ms.median``
/ ``.p95`` over the last 100 frames) are published with the counts; :meth:`TrackingMappingNode.summary` gives them
for the whole run. Published poses are projected onto SE(3) in float64.
Loop closure (with ``loop.enabled``), parameter ``loop_closure``:

- ``core`` (default): the node's core closes loops itself (detection, registration, pose graphs: the one
  implementation, :class:`~gausem_core.slam.loop_closure.LoopClosure`), exactly as ``gausem run`` does, so a
  lock-step replay gives the offline run's loops and trajectory; the accepted loops are published on
  ``gausem/loop_constraints`` for observers, and loop_detection and pose_graph need not run.
- ``nodes`` (distributed, docs/DESIGN.md §4): the same core code in three nodes. This node's core describes each loop
  keyframe (:meth:`~gausem_core.slam.loop_closure.LoopClosure.describe`) and publishes that place signature on
  ``gausem/place_signatures``; loop_detection runs the core's detector on it and answers with the ranked candidates
  (``gausem/loop_candidates``); this node's core confirms one (the bag of words: geometric verification in order,
  which needs both keyframes' images, held here) and registers it (keyframe alignment or SGR: it holds the Gaussians,
  ``GauSemSLAM.register_loop``), and publishes an accepted loop on ``gausem/loop_constraints`` (after re-publishing
  every keyframe with its current pose and anchor, which bundle adjustment and corrections changed since, as the
  core's :meth:`~gausem_core.slam.loop_closure.LoopClosure.correct` takes them); pose_graph optimises (the core's
  :class:`~gausem_core.slam.loop_graphs.LoopGraphs`) and answers on ``gausem/pose_graph``, applied here
  (``GauSemSLAM.apply_pose_graph``). The next frame waits for those answers (``loop_answer_timeout`` s at most, and
  only while loop_detection and pose_graph subscribe; 0: no wait, answers are applied when they arrive), as
  ``gausem run`` applies them within the keyframe's call: a lock-step replay gives the same loops, but for the check
  of the last loop keyframes at the end of a run (``loop.check_at_end``, off by default), which only ``core`` makes.

A live 3D view (``gausem_core.viewer``, needs rerun-sdk): ``viewer`` ``record`` logs every processed frame, the
trajectory, the loops and the map to a Rerun recording (``viewer_path``, default ``output_dir/gausem.rrd``), ``web``
also serves it to a browser on ``viewer_port`` (the URL is logged), ``native`` opens the desktop viewer; ``off`` (the
default) imports nothing. ``viewer_colors``: the map's points by ``rgb`` or ``class``; ``viewer_map_every``: the map
every this many frames.
"""
from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import torch
from diagnostic_msgs.msg import DiagnosticStatus
from nav_msgs.msg import OccupancyGrid, Odometry, Path as PathMsg
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_srvs.srv import Trigger

import msg_adapters as ma
from gausem_core.config import SlamConfig
from gausem_core.data.frame import Frame, resize_frame
from gausem_core.data.undistortion import Undistortion
from gausem_core.geometry import PinholeCamera, rigid_float64
from gausem_core.io.ply import write_gaussian_ply
from gausem_core.io.trajectory import Trajectory, write_tum_trajectory
from gausem_core.maps.slam_grid import KeyframeRays, floor_class_id, slam_grid
from gausem_core.runtime import resolve_device, smallest_image_side
from gausem_core.semantics.source import UNLABELLED_PALETTE
from gausem_core.slam.events import FrameEvents, KeyframeState, SubmapChange
from gausem_core.slam.health import TrackingHealth
from gausem_core.slam.loop import PlaceSignature
from gausem_core.slam.checkpoint import Checkpointer
from gausem_core.slam.observation import Observation
from gausem_core.slam.persistence import SESSION_FILE
from gausem_core.slam.system import GauSemSLAM

from ..frames import Rep105Frames, inverse
from ..qos import EVENT_QOS, INPUT_QOS_HINT, LATCHED_QOS, input_qos, subscribe_camera
from ..sync import make_synchronizer
from ..tf import make_transform_broadcaster
from .common import (LAST_FRAME_KEY, DropReport, FrameRejected, NewestFrameQueue, class_table,
                     declare_parameters, declare_slam_config, run_node, survives_errors)
from .loop_answers import LoopAnswers

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
    "grid_frame": "floor",       # the grid's frame: level, on the estimated floor, map -> grid_frame on /tf_static
    # (re-sent when the floor estimate moves); "": the map frame, the grid's origin then tilted in it
    "grid_publish_period": 5.0,  # seconds between occupancy grids at most (one after new keyframes or a map
    # correction; 0: no grid)
    "min_valid_depth": 0.05,     # fraction of pixels with a valid depth below which a frame is dropped
    "min_image_size": 16,        # pixels: frames with a smaller side are dropped (bad_size); >= the pyramids' need
    "max_image_pixels": 1280 * 720,  # larger frames are downscaled to at most this many pixels (aspect kept)
    "output_dir": "gausem_output",
    "loop_closure": "core",      # or "nodes": see the module docstring
    "loop_answer_timeout": 5.0,  # seconds; nodes: the longest wait for loop_detection's and pose_graph's answers
    "save_on_exit": False,       # write map.ply, trajectory.txt and session/ to output_dir when the node shuts down
    "map_path": "",              # a session folder: the map resumes from it when it holds a session, else starts there;
    # checkpoints go there (and gausem/load_map reads it)
    "checkpoint_keyframes": 5,   # with map_path: checkpoint the session every this many new keyframes (0: never) ...
    "checkpoint_period": 60.0,   # ... or this many seconds after the last checkpoint, at the next frame (0: never)
    "viewer": "off",             # or record, web, native: a live 3D view (see the module docstring)
    "viewer_path": "",           # the recording ("" = output_dir/gausem.rrd)
    "viewer_colors": "rgb",      # the map's points coloured by rgb or class
    "viewer_map_every": 10,      # frames between the map's updates in the view
    "viewer_port": 9090,         # viewer web: the web page's port
}
LOOP_CLOSURE_MODES = ("core", "nodes")
SYNC_REASONS = {"backwards": "stale_stamp", "duplicate": "duplicate_stamp", "unmatched": "unmatched",
                "lost_in_transport": "lost_in_transport"}
NO_LABELS_FIX = ("use_labels is true but no semantic/labels arrived: a bag that records labels under another name "
                 "replays them with --topic labels=TOPIC (gausem-player, gausem-ros); for data without labels set "
                 "-p use_labels:=false, or run the segmentation node (-p semantics.segmenter:=ade20k "
                 "-p classes:=nyu40)")


def _check_size_limits(cfg: SlamConfig, min_image_size: int, max_image_pixels: int) -> None:
    """ValueError naming the parameter to change when the size limits cannot work together."""
    least = smallest_image_side(cfg)
    if min_image_size < least:
        raise ValueError(f"tracking_mapping: min_image_size {min_image_size} is below {least} pixels, the smallest "
                         "side the image pyramids (tracking.gauss_newton.pyramid_levels, "
                         "loop.registration.pyramid_levels and downsample) can take; raise min_image_size")
    if max_image_pixels < min_image_size ** 2:
        raise ValueError(f"tracking_mapping: max_image_pixels {max_image_pixels} is below min_image_size^2 = "
                         f"{min_image_size ** 2}; raise max_image_pixels")


CAMERA_TOLERANCE_PX = 0.5  # intrinsics (scaled to the map's image size) that differ by more are another camera
DEGRADED_VARIANCE = 1.0  # m^2 and rad^2 on the odometry's pose covariance diagonal for a degraded frame
_HEALTH_LEVELS = {"ok": (DiagnosticStatus.OK, ""), "degraded": (DiagnosticStatus.WARN, "tracking degraded"),
                  "lost": (DiagnosticStatus.ERROR, "tracking lost")}


LIVE_DEFAULTS = {"worker.mode": "async"}  # a live node maps on the mapping worker, beside its tracker
LOCKSTEP_DEFAULTS = {"worker.mode": "sync"}  # a lock-step replay maps each keyframe before answering: gausem run's


class TrackingMappingNode(Node):
    """``slam_defaults``: SLAM parameter defaults of this node (default :data:`LIVE_DEFAULTS`; the parameters given
    still win)."""

    def __init__(self, slam_defaults: dict | None = None, **kwargs):
        super().__init__("tracking_mapping", **kwargs)
        self.cfg = declare_slam_config(self, LIVE_DEFAULTS if slam_defaults is None else slam_defaults)
        self.params = p = declare_parameters(self, NODE_DEFAULTS)
        if p.loop_closure not in LOOP_CLOSURE_MODES:
            raise ValueError(f"tracking_mapping: loop_closure must be one of {', '.join(LOOP_CLOSURE_MODES)}, got "
                             f"{p.loop_closure!r}")
        _check_size_limits(self.cfg, p.min_image_size, p.max_image_pixels)
        self.tf_frames = Rep105Frames(p.map_frame, p.odom_frame, p.base_frame, p.camera_extrinsic)
        if p.grid_frame and p.grid_frame in (p.map_frame, p.odom_frame, p.base_frame):
            raise ValueError(f"tracking_mapping: grid_frame {p.grid_frame!r} must differ from map_frame, odom_frame "
                             "and base_frame (\"\" puts the grid in map_frame)")
        self._static_camera_frame = ""  # the camera frame the static base_frame -> camera was sent for
        table = class_table(p.classes) if p.use_labels else None
        self.palette = table.palette if table is not None else UNLABELLED_PALETTE
        self._floor_class = floor_class_id(table.names if table is not None else None, self.cfg.grid.floor_class)
        self.device = resolve_device(self.cfg.device)
        self.drops = DropReport(self, status=self._status, level=lambda: _HEALTH_LEVELS[self.health.status])
        self._handled_ns = -1  # stamp of the last synchronised frame handled (processed or dropped)
        self.loop_candidates: list[ma.LoopCandidateRecord] = []
        self.pose_graph_updates: list[ma.PoseGraphUpdate] = []
        # the latest valid rgb/camera_info: (the pinhole camera the frames are given in, the Undistortion that takes
        # them there or None), replaced whole so that a frame never pairs one camera_info's camera with another's
        self._camera: tuple[PinholeCamera, Undistortion | None] | None = None
        self.lens_distortion: tuple[float, ...] = ()  # its D (empty: none stated)
        self.latencies: list[float] = []  # seconds from a frame's arrival to its pose's publication
        self._in_progress = False  # a frame is being processed
        self._loop_answers = LoopAnswers(
            p.loop_answer_timeout, lambda: self._signature_pub.get_subscription_count() > 0,
            lambda: self._constraint_pub.get_subscription_count() > 0,
            lambda what: self.get_logger().warning(f"no {what} answer within loop_answer_timeout = "
                                                   f"{p.loop_answer_timeout} s; going on with the next frame"))
        self.checkpoints = Checkpointer(p.map_path, p.checkpoint_keyframes, p.checkpoint_period) if p.map_path \
            else None
        if self.device.type == "cuda":  # the inputs are subscribed once the renderer is ready
            self.get_logger().info("preparing the renderer on cuda (gsplat compiles its kernels on a machine's first "
                                   "run: one to two minutes)")
        self.frames_processed = 0  # the input accounting's (kept across load_map, cleared by gausem/reset)
        self._reset_state()
        self._viewer = self._open_viewer()

        inputs = [("rgb", Image, "rgb/image"), ("depth", Image, "depth/image")] + (
            [("labels", Image, "semantic/labels")] if p.use_labels else [])
        qos = input_qos(p.input_qos)
        input_group = MutuallyExclusiveCallbackGroup()  # inputs arrive while a frame is processed
        self._inputs = make_synchronizer(self, inputs, self._on_frame, qos, queue_size=p.sync_queue_size,
                                         slop=p.sync_slop, on_drop=self._on_sync_drop, callback_group=input_group)
        self._queue = NewestFrameQueue(self, self._process, lambda _: self.drops.drop(
            "superseded", "a newer synchronised frame arrived before this one was processed"),
            ready=self._loop_settled)  # superseded and skipped frames reach the core through _process's count
        subscribe_camera(self, CameraInfo, "rgb/camera_info", self._on_camera_info, qos, input_group, INPUT_QOS_HINT)
        if p.sync_wait < 0:
            raise ValueError(f"tracking_mapping: sync_wait must be >= 0 (0: off), got {p.sync_wait}")
        if p.sync_wait:
            self.create_timer(min(p.sync_wait / 2, 0.5), lambda: self._inputs.synchronizer.flush(p.sync_wait),
                              callback_group=input_group)
        if self.loop_nodes:
            self._signature_pub = self.create_publisher(PointCloud2, "gausem/place_signatures", EVENT_QOS)
            self.create_subscription(PointCloud2, "gausem/loop_candidates", self._on_loop_candidates, EVENT_QOS)
            self.create_subscription(PointCloud2, "gausem/pose_graph", self._on_pose_graph, EVENT_QOS)
            self._answer_timer = self.create_timer(0.05, self._await_loop_answers)
            self._answer_timer.cancel()  # runs while an answer is awaited
        self._constraint_pub = self.create_publisher(PointCloud2, "gausem/loop_constraints", EVENT_QOS)
        self._odometry_pub = self.create_publisher(Odometry, "gausem/odometry", EVENT_QOS)
        self._path_pub = self.create_publisher(PathMsg, "gausem/path", LATCHED_QOS)
        self._map_pub = self.create_publisher(PointCloud2, "gausem/map", LATCHED_QOS)
        self._grid_pub = self.create_publisher(OccupancyGrid, "gausem/grid", LATCHED_QOS)
        self._keyframe_pub = self.create_publisher(PointCloud2, "gausem/keyframes", EVENT_QOS)
        self._submap_pub = self.create_publisher(PointCloud2, "gausem/submaps", EVENT_QOS)
        self._tf = make_transform_broadcaster(self)
        self._tf_static = make_transform_broadcaster(self, static=True) if p.base_frame or p.grid_frame else None
        self.create_timer(p.map_publish_period, self._publish_map)
        if p.grid_publish_period < 0:
            raise ValueError(f"tracking_mapping: grid_publish_period must be >= 0 (0: no grid), got "
                             f"{p.grid_publish_period}")
        if p.grid_publish_period:
            self.create_timer(p.grid_publish_period, self._publish_grid)
        self.create_service(Trigger, "gausem/save_map", self._on_save_map)
        self.create_service(Trigger, "gausem/reset", self._on_reset)
        self.create_service(Trigger, "gausem/load_map", self._on_load_map)
        self.create_service(Trigger, "gausem/finish", self._on_finish)
        if p.map_path and (Path(p.map_path) / SESSION_FILE).exists():
            try:
                self.load_map(p.map_path)
            except (OSError, ValueError) as err:  # a truncated or foreign session: say which parameter names it
                raise ValueError(f"tracking_mapping: cannot load map_path {p.map_path!r}: {err}") from err
        elif p.map_path:
            self.get_logger().info(f"no session in map_path {p.map_path} yet: a new map, checkpointed there")

    def _open_viewer(self):
        """The ``viewer`` parameter's :class:`~gausem_core.viewer.Viewer`; None when off (nothing imported)."""
        p = self.params
        if p.viewer == "off":
            return None
        from gausem_core.viewer import RECORDING, Viewer

        try:
            viewer = Viewer(p.viewer_path or Path(p.output_dir) / RECORDING, self.palette,
                            class_table(p.classes).names if p.use_labels else None, p.viewer, p.viewer_colors,
                            p.viewer_map_every, web_port=p.viewer_port)
        except (ImportError, ValueError) as err:
            raise ValueError(f"tracking_mapping: viewer {p.viewer!r}: {err}") from err
        self.get_logger().info(f"viewer: recording to {viewer.path}" + (f", web viewer at {viewer.url}"
                                                                          if viewer.url else ""))
        return viewer

    @property
    def loop_nodes(self) -> bool:
        """Whether loops come from the loop_detection and pose_graph nodes (``loop_closure: nodes``)."""
        return self.cfg.loop.enabled and self.params.loop_closure == "nodes"

    def _reset_state(self, slam: GauSemSLAM | None = None) -> None:
        """A new map (or ``slam``, a loaded one) with the node's per-map state cleared."""
        torch.manual_seed(self.cfg.seed)
        self.slam = slam or GauSemSLAM(self.cfg, self.device, num_classes=len(self.palette),
                                       detect_loops=not self.loop_nodes)
        self._busy: tuple[float, float] | None = None  # perf_counter at the first processed frame's start, last end
        self._last_stamp = -math.inf
        self._camera_frame = self.params.camera_frame or "camera"
        self._map_dirty = False
        self._grid_dirty = False  # keyframes or corrections since the last grid
        self._rays = KeyframeRays(self.cfg.grid.pixel_stride)  # the map's keyframe rays, for its grids
        self._grid_floor: str | None = None  # where the last grid's floor came from (logged when it changes)
        self._grid_floor_pose: np.ndarray | None = None  # map-from-floor last sent on /tf_static (grid_frame)
        self._path: PathMsg | None = None  # the published path (None: rebuild it from the trajectory)
        self._tf_last: int | None = None  # the last frame (id in this map) whose transforms were sent
        self.map_age = 0  # frames between the last frame and the newest keyframe of the map it was tracked against
        self._loop_answers.clear()
        self._new_map = True  # the next place signature is the map's first (loop_detection starts over)
        self._loaded_places: list[tuple[PlaceSignature, float]] = []  # a loaded map's, still to go to loop_detection
        self.health = TrackingHealth("ok")  # the last frame's
        self.health_log: list[tuple[int, float, TrackingHealth]] = []  # (frame, stamp, health) of every frame given
        # to the core, dropped ones included (the report's tracking_status.csv)
        self._rescaled_sizes: set[tuple[int, int]] = set()  # frame sizes said to be resized to the map's camera
        if self.checkpoints is not None:
            self.checkpoints.start(self.slam)  # a new or loaded map: nothing in it is new yet

    # --- inputs -------------------------------------------------------------------------------------------------
    @survives_errors(frame=False)
    def _on_camera_info(self, msg: CameraInfo) -> None:
        """The camera, and for one whose camera_info states a lens distortion (non-zero D, OpenCV's plumb_bob or
        rational_polynomial coefficients) the undistortion every frame then goes through (said once per calibration);
        the frames are then a pinhole camera's whose every pixel the lens covers."""
        try:
            camera = ma.camera_info_to_camera(msg)
            distortion = tuple(float(d) for d in msg.d) if any(msg.d) else ()
            if distortion and len(distortion) not in (4, 5, 8):
                raise ValueError(f"CameraInfo distortion {msg.distortion_model!r} has {len(distortion)} coefficients; "
                                 "GauSem undoes OpenCV's 4, 5 or 8 (plumb_bob, rational_polynomial)")
        except ValueError as err:
            self.drops.drop("bad_camera_info", str(err), frame=False)
            return
        if self._camera is not None and (self._camera[0], self.lens_distortion) == (camera, distortion):
            return
        undistortion = Undistortion(camera, distortion) if distortion else None
        if undistortion is not None:
            c = undistortion.camera
            self.get_logger().info(f"rgb/camera_info states lens distortion {msg.distortion_model} {list(distortion)}: "
                                   f"frames are undistorted into the pinhole fx {c.fx:.1f} fy {c.fy:.1f} "
                                   f"cx {c.cx - 0.5:.1f} cy {c.cy - 0.5:.1f}")
        self._camera, self.lens_distortion = (camera, undistortion), distortion

    @property
    def camera(self) -> PinholeCamera | None:
        """The pinhole camera the frames are processed in (after any undistortion); None before a camera_info."""
        return None if self._camera is None else (self._camera[1].camera if self._camera[1] else self._camera[0])

    def _on_frame(self, *msgs: Image) -> None:
        self._queue.put(msgs, ma.header_seconds(msgs[0].header))

    def _on_sync_drop(self, index: int, reason: str, detail: str, stamp: float | None) -> None:
        """The synchroniser dropped a message: an rgb image is a lost frame (counted by reason; the diagnostics name
        it as handled, which answers a lock-step player); depth and label messages without a frame are only counted
        (``sync.<input>.<reason>`` in the diagnostics)."""
        if index:
            return
        if stamp is not None:
            self._handled_ns = max(self._handled_ns, ma.seconds_to_ns(stamp))
        sync = self._inputs.synchronizer
        silent = [name for name, received in zip(sync.names, sync.received) if not received]
        if reason == "unmatched" and silent:
            reason = f"no_{silent[0]}"
            detail += f"; {NO_LABELS_FIX}" if silent[0] == "labels" else ""
        if reason == "lost_in_transport":  # unstamped, but after the last rgb received, so after any pending frame
            stamp = math.inf
        self._skip(SYNC_REASONS.get(reason, reason), detail, stamp)

    def _skip(self, reason: str, detail: str, stamp: float | None = None) -> None:
        """A frame (stamped ``stamp`` where known) dropped before it reached the core: counted by reason, and passed
        on to the core with the next frame after it as a skipped one (its motion model then knows that the camera
        moved on for longer)."""
        self._queue.skip(stamp=stamp)
        self.drops.drop(reason, detail)

    def _observation(self, rgb_msg: Image, depth_msg: Image, labels_msg: Image | None = None) -> Observation:
        """Validated observation of one synchronised frame (downscaled to ``max_image_pixels``), or FrameRejected
        saying why not."""
        stamp = ma.header_seconds(rgb_msg.header)
        if stamp <= self._last_stamp:
            raise FrameRejected("stale_stamp", f"frame stamped {stamp:.6f} s is not after the last processed "
                                               f"frame ({self._last_stamp:.6f} s)")
        if self._camera is None:
            raise FrameRejected("no_camera_info", "no valid rgb/camera_info received yet; waiting for it")
        camera, undistortion = self._camera
        self._check_min_size(rgb_msg, depth_msg, labels_msg)
        rgb, depth, labels = self._decode(rgb_msg, depth_msg, labels_msg)
        sizes = {"rgb": rgb.shape[:2], "depth": depth.shape, "labels": labels.shape,
                 "camera_info": (camera.height, camera.width)}
        if len(set(sizes.values())) > 1:
            raise FrameRejected("size_mismatch", "image sizes differ (height, width): "
                                + ", ".join(f"{k} {v}" for k, v in sizes.items()))
        if labels.size and (labels.min() < 0 or labels.max() >= len(self.palette)):
            raise FrameRejected("bad_labels", f"labels span [{labels.min()}, {labels.max()}], outside the class "
                                              f"table's ids 0..{len(self.palette) - 1} (parameter classes)")
        if undistortion is not None:
            rgb, depth, labels, camera = (undistortion.color(rgb), undistortion.nearest(depth),
                                          undistortion.labels(labels), undistortion.camera)
        valid = float((depth > 0).mean()) if depth.size else 0.0
        if valid < self.params.min_valid_depth:
            raise FrameRejected("invalid_depth", f"only {100 * valid:.1f} % of the depth pixels are valid (finite, "
                                                 f"> 0); at least {100 * self.params.min_valid_depth:.1f} % needed")
        frame = self._in_map_camera(self._limit_pixels(Frame(0, stamp, rgb, depth, labels, camera)))
        return Observation.from_arrays(frame.rgb, frame.depth, frame.labels, frame.camera, self.palette, stamp,
                                       self.device)

    def _check_min_size(self, *msgs: Image | None) -> None:
        """FrameRejected (bad_size) for an image with a side below ``min_image_size``, before any decoding."""
        least = self.params.min_image_size
        for name, msg in zip(("rgb", "depth", "labels"), msgs):
            if msg is not None and min(msg.width, msg.height) < least:
                raise FrameRejected("bad_size", f"{name} image is {msg.width}x{msg.height}: sides below "
                                                f"{least} pixels are dropped (parameter min_image_size)")

    def _decode(self, rgb_msg: Image, depth_msg: Image, labels_msg: Image | None):
        """RGB, depth (metres) and labels (zeros without a labels input) arrays, or FrameRejected (bad_encoding;
        bad_image when the data does not hold the declared size)."""
        try:
            rgb = ma.image_to_rgb(rgb_msg)
            depth = ma.image_to_depth(depth_msg)
            labels = (ma.image_to_labels(labels_msg) if labels_msg is not None
                      else np.zeros(depth.shape, np.int64))
        except ma.ImageEncodingError as err:
            raise FrameRejected("bad_encoding", str(err)) from err
        except ValueError as err:  # data length / step inconsistent with the declared size
            raise FrameRejected("bad_image", str(err)) from err
        return rgb, depth, labels

    def _limit_pixels(self, frame: Frame) -> Frame:
        """The frame downscaled, aspect kept, to at most ``max_image_pixels`` pixels (rgb area-averaged, depth and
        labels nearest, intrinsics scaled: ``resize_frame``); FrameRejected (bad_size) if a side would fall below
        ``min_image_size``."""
        w, h = frame.size
        limit = self.params.max_image_pixels
        if w * h <= limit:
            return frame
        scale = math.sqrt(limit / (w * h))
        size = int(w * scale), int(h * scale)
        if min(size) < self.params.min_image_size:
            raise FrameRejected("bad_size", f"a {w}x{h} image downscaled to max_image_pixels = {limit} would be "
                                            f"{size[0]}x{size[1]}, a side below min_image_size; raise "
                                            "max_image_pixels or lower min_image_size")
        return resize_frame(frame, *size)

    def _in_map_camera(self, frame: Frame) -> Frame:
        """The frame in the camera of the map (its first keyframe's): one whose camera is a scaling of it is resized
        to it (said once per size); another camera is rejected (camera_changed: a map has one camera model)."""
        if not self.slam.submaps:
            return frame
        ours = self.slam.submaps[0].keyframes[0].obs.camera
        theirs = frame.camera.scaled(ours.width, ours.height)
        if max(abs(a - b) for a, b in zip((theirs.fx, theirs.fy, theirs.cx, theirs.cy),
                                          (ours.fx, ours.fy, ours.cx, ours.cy))) > CAMERA_TOLERANCE_PX:
            raise FrameRejected("camera_changed", f"the frame's camera {frame.camera} is not the map's {ours} nor a "
                                                  "scaling of it; gausem/reset starts a map in the new camera")
        if frame.size != (ours.width, ours.height) and frame.size not in self._rescaled_sizes:
            self._rescaled_sizes.add(frame.size)
            self.get_logger().info(f"frames of {frame.size[0]}x{frame.size[1]} are resized to the map's "
                                   f"{ours.width}x{ours.height} (their camera is a scaling of its camera)")
        return resize_frame(frame, ours.width, ours.height)

    # --- processing ---------------------------------------------------------------------------------------------
    @property
    def seconds(self) -> float:
        """Wall time from the start of the first processed frame (message conversion included) to the end of the
        last one: the ROS counterpart of the offline pipeline's loop time (0 before any frame)."""
        return self._busy[1] - self._busy[0] if self._busy else 0.0

    @survives_errors
    def _process(self, msgs: tuple[Image, ...], arrived: float, skipped: int) -> None:
        """One synchronised frame; ``skipped``: the frames dropped since the last one the queue handed over."""
        start = time.perf_counter()
        self._handled_ns = ma.time_to_ns(msgs[0].header.stamp)
        self._in_progress = True  # until the frame is counted as processed or dropped
        try:
            obs = self._observation(*msgs)
        except Exception as err:
            self._in_progress = False
            self._queue.skip(skipped)  # passed on with the next frame, as is this one when it is rejected
            if not isinstance(err, FrameRejected):
                raise  # counted as a processing_error drop
            self._skip(err.reason, str(err))
            return
        try:
            self._track_and_publish(obs, msgs[0].header.frame_id, arrived, skipped)
        except Exception:
            self._in_progress = False  # counted as a processing_error drop
            raise
        self._busy = (self._busy[0] if self._busy else start, time.perf_counter())
        self._checkpoint()

    def _checkpoint(self) -> None:
        """Write the session to ``map_path`` when a checkpoint is due; a failure is logged, the node goes on."""
        if self.checkpoints is None or not self.checkpoints.due(self.slam):
            return
        try:
            seconds = self.checkpoints.write(self.slam)
        except OSError as err:
            self.checkpoints.start(self.slam)  # tried again at the next interval, not at every frame
            self.get_logger().error(f"checkpoint: could not write to {self.params.map_path}: {err}")
        else:
            self.get_logger().debug(f"checkpoint of {len(self.slam.frames)} frames in {seconds:.2f} s")

    def _track_and_publish(self, obs: Observation, image_frame: str, arrived: float, skipped: int) -> None:
        result = self.slam.process(obs, skipped)
        if self._viewer is not None:
            self._viewer.frame(obs, result, self.slam)
        self._last_stamp = obs.timestamp
        self.map_age = result.map_age
        self._publish_mapped(result.mapped)
        self.health = result.health
        self.health_log.append((result.frame_id, obs.timestamp, result.health))
        if result.relocalisation is not None:
            if not self._relocalised(result.relocalisation, obs.timestamp):
                return
        if result.health.status == "lost":
            self._in_progress = False
            self.drops.drop("tracking_lost", f"frame stamped {obs.timestamp:.6f} s: tracking lost "
                                             f"({', '.join(result.health.reasons)}); not mapped, nothing published, "
                                             "the next frames are relocalised")
            return
        pose = rigid_float64(result.cam_to_world).numpy()
        if not np.isfinite(pose).all():
            self._in_progress = False
            self.drops.drop("tracking_diverged", f"frame stamped {obs.timestamp:.6f} s: the estimated pose is not "
                                                 "finite; nothing is published for it (reset with gausem/reset)")
            return
        self._camera_frame = self.params.camera_frame or image_frame or "camera"
        header = ma.make_header(obs.timestamp, self.params.map_frame)
        odometry = ma.matrix_to_odometry(pose, header, self._camera_frame)
        if result.health.status == "degraded":
            odometry.pose.covariance = (DEGRADED_VARIANCE * np.eye(6)).ravel().tolist()
        self._odometry_pub.publish(odometry)
        self.frames_processed += 1
        self._in_progress = False
        self.latencies.append(time.monotonic() - arrived)
        self._send_transforms(result, pose, obs.timestamp)
        if self._corrected(result.events):
            self._path = None  # rebuilt from the corrected trajectory
        self._publish_path((obs.timestamp, pose))
        self._publish_events(result.events, header)
        self._map_dirty = True
        self.drops.publish()

    def _send_transforms(self, result, pose: np.ndarray, stamp: float) -> None:
        """A published frame's ``map -> odom -> camera`` (or ``-> base``), with the motion since the last frame sent
        from both frames' map poses as they are now (none for a relocalised frame); the static ``base -> camera``
        once per camera frame name."""
        motion = None
        if self._tf_last is not None and result.relocalisation is None:
            with self.slam.lock:  # both poses after the same corrections (the mapping worker corrects in parallel)
                last, current = (rigid_float64(self.slam.frames[i].cam_to_world).numpy()
                                 for i in (self._tf_last, result.frame_id))
            motion = inverse(last) @ current
        self._tf_last = result.frame_id
        self._tf.sendTransform(self.tf_frames.transforms(stamp, self._camera_frame, pose, motion))
        if self._tf_static is not None and self._static_camera_frame != self._camera_frame:
            self._static_camera_frame = self._camera_frame
            self._tf_static.sendTransform(self.tf_frames.static_transforms(stamp, self._camera_frame))

    def _relocalised(self, reloc, stamp: float) -> bool:
        """Report a relocalisation against a loaded map; whether it placed the frame."""
        if not reloc.accepted:
            self._in_progress = False
            self.drops.drop("relocalisation_failed", f"frame stamped {stamp:.6f} s could not be placed against the "
                                                     f"map (inlier fraction {reloc.inlier_fraction:.2f}); the "
                                                     "next frame tries again")
            return False
        self.get_logger().info(f"relocalised against the map (submap {reloc.submap_id}, inlier fraction "
                               f"{reloc.inlier_fraction:.2f}); tracking goes on")
        return True

    def _status(self) -> dict:
        """Diagnostics besides the drop counts: frames in, processed and pending, the last frame's tracking health,
        the latency over the last 100 frames, the last handled frame (lock-step players take it as the answer for a
        frame that produced no odometry), the depth and label messages the synchroniser dropped and the estimated
        vignetting (brightness in the image corners relative to the centre, ``slam.back_end.vignetting``) and whether the
        frames are undistorted (``camera.undistorted``: the camera_info states a lens distortion)."""
        sync = self._inputs.synchronizer
        return {"frames_in": sync.received[0] + sync.lost[0], "frames_processed": self.frames_processed,
                "frames_pending": self._frames_pending(), LAST_FRAME_KEY: self._handled_ns,
                "tracking.status": self.health.status,
                **{f"tracking.{name}": value for name, value in self.health.signals().items()},
                "camera.vignetting_corner_gain": math.exp(self.slam.back_end.vignetting.a),
                "camera.undistorted": bool(self.lens_distortion), **self._worker_status(), **self._checkpoint_status(),
                **latency_stats(self.latencies[-100:]),
                **{f"sync.{name}.{reason}": n for (name, reason), n in sorted(sync.dropped.items())
                   if name != sync.names[0]}}

    def _worker_status(self) -> dict:
        """The mapping worker's state: mode, keyframes waiting, the last mapped keyframe's lag (tracker frames between
        its arrival and its mapping), keyframes superseded in the queue, and the last frame's map age."""
        worker = self.slam.back_end.worker
        status = {"worker.mode": self.cfg.worker.mode, "worker.map_age_frames": self.map_age}
        if worker is not None:
            lags = worker.stats.lag_frames
            status.update({"worker.queue_depth": worker.depth, "worker.lag_frames": lags[-1] if lags else 0,
                           "worker.keyframes_superseded": worker.stats.superseded})
        return status

    def _checkpoint_status(self) -> dict:
        """Checkpoints written, frames in the last one and what writing it cost."""
        if self.checkpoints is None:
            return {}
        stats = self.checkpoints.stats
        return {"checkpoint.written": stats.written, "checkpoint.frames": stats.frames,
                "checkpoint.seconds_last": stats.seconds_last}

    def summary(self) -> dict:
        """The whole run's input accounting: frames in = processed + dropped (by reason) + pending; latency."""
        sync = self._inputs.synchronizer
        return {"frames_in": sync.received[0] + sync.lost[0], "frames_processed": self.frames_processed,
                "dropped": dict(sorted(self.drops.counts.items())),
                "frames_pending": self._frames_pending(), **latency_stats(self.latencies)}

    def _frames_pending(self) -> int:
        """Frames received and not yet processed or dropped: unmatched in the synchroniser, queued, in progress."""
        return self._inputs.synchronizer.pending(0) + self._queue.pending + self._in_progress

    def _publish_path(self, new: tuple[float, np.ndarray] | None = None) -> None:
        """The path with the ``new`` pose appended (one pose converted a frame); rebuilt from the whole trajectory
        after a correction (:attr:`_path` None). Frames judged lost are in neither (nor in save_map's trajectory), as
        they publish no odometry."""
        if self._path is None:
            self._path = ma.poses_to_path([(t, m) for t, m in ((t, rigid_float64(p).numpy())
                                                               for t, p in self.slam.trajectory(False))
                                           if np.isfinite(m).all()], self.params.map_frame)
        elif new is not None:
            entry = ma.matrix_to_pose_stamped(new[1], ma.make_header(new[0], self.params.map_frame))
            self._path.poses.append(entry)
            self._path.header = entry.header
        self._path_pub.publish(self._path)

    @staticmethod
    def _corrected(events: FrameEvents) -> bool:
        """Whether a keyframe's loop closure moved the map (the path is then rebuilt)."""
        return events.loop is not None and bool(events.loop.correction)

    def _publish_mapped(self, mapped: tuple[FrameEvents, ...]) -> None:
        """The events of keyframes the mapping worker finished (async), stamped like their keyframes."""
        for events in mapped:
            if self._corrected(events):
                self._path = None
            stamp = events.keyframe.timestamp if events.keyframe is not None else max(self._last_stamp, 0.0)
            self._publish_events(events, ma.make_header(stamp, self.params.map_frame))

    def _publish_events(self, events: FrameEvents, header) -> None:
        """A frame's events: submaps closed and opened, its keyframe, a loop keyframe's place signature
        (``loop_closure: nodes``: loop_detection's answer is then awaited), the loop the core closed (``loop_closure:
        core``; published for observers)."""
        self._publish_submaps(events.submaps, header)
        if events.keyframe is not None:
            self._publish_keyframes([events.keyframe], header)
            self._grid_dirty = True
        if events.place is not None:
            self._publish_place(events.place, events.keyframe.timestamp)
        if events.loop is not None and events.loop.constraint is not None:
            self._constraint_pub.publish(ma.records_to_pointcloud2(
                [ma.loop_constraint_to_record(events.loop.constraint)], header))

    def _publish_place(self, place: PlaceSignature, stamp: float, loaded: bool = False) -> None:
        """Send a place signature (stamped like its keyframe) to loop_detection; its answer is awaited."""
        self._loop_answers.expect_candidates(stamp)
        self._answer_timer.reset()
        record = ma.place_signature_to_record(place, stamp, loaded=loaded, new_map=self._new_map)
        self._new_map = False
        self._signature_pub.publish(ma.records_to_pointcloud2([record], ma.make_header(stamp, self.params.map_frame)))

    def _send_loaded_places(self) -> None:
        """Send a loaded map's signatures to loop_detection, each once the last one was answered (or given up)."""
        while self._loaded_places and self._loop_answers.settled():
            self._publish_place(*self._loaded_places.pop(0), loaded=True)

    def _loop_settled(self) -> bool:
        """Whether the next frame may be processed: loop_detection holds the loaded map and no loop answer is
        awaited."""
        return not self._loaded_places and self._loop_answers.settled()

    def _publish_submaps(self, changes: list[SubmapChange], header) -> None:
        events = [ma.SubmapEvent(c.submap_id, c.first_keyframe, c.anchor.numpy(),
                                 ma.SubmapEventKind.CREATED if c.opened else ma.SubmapEventKind.CLOSED)
                  for c in changes]
        if events:
            self._submap_pub.publish(ma.records_to_pointcloud2(events, header))

    def _publish_keyframes(self, keyframes: list[KeyframeState], header) -> None:
        """KeyframeRecords with the keyframes' current poses."""
        records = [ma.KeyframeRecord(k.frame_id, k.timestamp, k.submap_id, k.pose.numpy(), k.anchor.numpy())
                   for k in keyframes]
        if records:
            self._keyframe_pub.publish(ma.records_to_pointcloud2(records, header))

    def _publish_map(self) -> None:
        if not self._map_dirty:
            return
        self._map_dirty = False
        stamp = max(self._last_stamp, 0.0)
        self._map_pub.publish(ma.cloud_to_pointcloud2(self.slam.global_cloud(),
                                                      ma.make_header(stamp, self.params.map_frame), self.palette))

    def _publish_grid(self) -> None:
        """The occupancy grid, when keyframes or a correction changed the map since the last one (none while the map
        shows no floor: said once)."""
        if not self._grid_dirty:
            return
        self._grid_dirty = False
        try:
            grid = slam_grid(self.slam, self.cfg.grid, self.palette, self._floor_class, self._rays)
        except ValueError as err:
            self.get_logger().warning(f"no occupancy grid yet: {err}", once=True)
            return
        if grid.floor.source != self._grid_floor:
            self._grid_floor = grid.floor.source
            where = "the floor class" if grid.floor.source == "class" else "the lowest level plane"
            self.get_logger().info(f"occupancy grid: the floor from {where} ({grid.floor.inliers} Gaussians)")
        stamp, frame = max(self._last_stamp, 0.0), self.params.grid_frame
        if frame and (self._grid_floor_pose is None or not np.array_equal(self._grid_floor_pose, grid.floor.pose)):
            self._grid_floor_pose = grid.floor.pose
            self._tf_static.sendTransform(ma.matrix_to_transform(
                grid.floor.pose, ma.make_header(stamp, self.params.map_frame), frame))
        header = ma.make_header(stamp, frame or self.params.map_frame)
        self._grid_pub.publish(ma.grid_to_occupancy_grid(grid, header, floor_frame=bool(frame)))

    # --- loop closure events ------------------------------------------------------------------------------------
    @survives_errors(frame=False)
    def _on_loop_candidates(self, msg: PointCloud2) -> None:
        """One query keyframe's ranked candidates (possibly none): the loop closure confirms one (verification with
        the bag of words) and registers it; an accepted loop goes out to pose_graph, whose answer is then awaited."""
        try:
            self._close_loop(msg)
        finally:
            self._loop_answers.candidates_arrived(ma.header_seconds(msg.header))
            self._send_loaded_places()
            self._queue.wake()

    def _close_loop(self, msg: PointCloud2) -> None:
        try:
            candidates = ma.pointcloud2_to_records(msg, ma.LoopCandidateRecord)
            outcome = self.slam.register_loop([ma.record_to_loop_candidate(c) for c in candidates])
        except ValueError as err:  # unknown keyframes (e.g. from before a reset), inconsistent records
            self.drops.drop("bad_loop_candidates", str(err), frame=False)
            return
        self.loop_candidates += candidates  # handled
        if outcome is None:
            return
        constraint, record = outcome.constraint, outcome.record
        self.get_logger().info(f"loop candidate {record.query_frame}->{record.match_frame} (submaps "
                               f"{record.query_submap}, {record.match_submap}, {len(candidates)} ranked): "
                               f"{'accepted' if constraint else 'rejected'}, fitness {record.fitness:.3f}, "
                               f"{record.seconds:.2f} s")
        if constraint is None:
            return
        header = ma.make_header(max(self._last_stamp, 0.0), self.params.map_frame)
        self._publish_keyframes(self.slam.keyframe_states(), header)  # the poses and anchors as they are now
        self._loop_answers.expect_pose_graph()
        self._answer_timer.reset()
        self._constraint_pub.publish(ma.records_to_pointcloud2([ma.loop_constraint_to_record(constraint)], header))

    def _await_loop_answers(self) -> None:
        """While loop answers are awaited: once they are given up (timeout, helper gone), send the next loaded
        signature, if any, or wake the waiting frame."""
        self._send_loaded_places()
        if self._loop_settled():
            self._answer_timer.cancel()
            self._queue.wake()

    @survives_errors(frame=False)
    def _on_pose_graph(self, msg: PointCloud2) -> None:
        try:
            self._apply_pose_graph(msg)
        finally:
            self._loop_answers.pose_graph_arrived()
            self._queue.wake()

    def _apply_pose_graph(self, msg: PointCloud2) -> None:
        try:
            update = ma.pointcloud2_to_pose_graph_update(msg)
        except ValueError as err:
            self.drops.drop("bad_pose_graph", str(err), frame=False)
            return
        correction = self.slam.apply_pose_graph(ma.pose_graph_update_to_core(update))
        self.get_logger().info(f"pose graph update of {len(update.nodes)} poses: moved {correction.anchors} submaps "
                               f"and {correction.keyframes} keyframes (in {len(correction.submaps)} submaps)")
        if correction:
            self._path = None
            self._publish_path()
            self._map_dirty = self._grid_dirty = True
        self.pose_graph_updates.append(update)  # applied

    def finish(self) -> None:
        """End of the sequence: the core's end of a run (``loop_closure: core``: the loop keyframes whose check never
        came are checked, ``loop.check_at_end``; then the global refinement, ``refinement.enabled``), counted in
        ``seconds``; a loop closed then is published, the keyframes, corrected path and map are re-published."""
        start = time.perf_counter()
        loop = self.slam.finish()
        if self._busy:
            self._busy = (self._busy[0], self._busy[1] + time.perf_counter() - start)
        self._publish_mapped(self.slam.take_mapped())  # async: the keyframes mapped after the last frame
        header = ma.make_header(max(self._last_stamp, 0.0), self.params.map_frame)
        if loop is not None and loop.constraint is not None:
            self._constraint_pub.publish(ma.records_to_pointcloud2([ma.loop_constraint_to_record(loop.constraint)],
                                                                   header))
        if self.slam.submaps:
            self._publish_keyframes(self.slam.keyframe_states(), header)  # as loop closure and refinement left them
        self._path = None
        self._publish_path()
        self._map_dirty = True
        self._publish_map()  # now: a caller that finishes may stop spinning (the map timer) right after
        if self.params.grid_publish_period:
            self._grid_dirty = True
            self._publish_grid()
        if self._viewer is not None:
            self._viewer.finish(self.slam)

    # --- services -----------------------------------------------------------------------------------------------
    def save_map(self, folder: str | Path) -> tuple[Path, Path]:
        """Write the map (3DGS-style PLY with class ids), the trajectory (TUM) and the session (``session/``, what
        ``map_path`` loads) to ``folder``."""
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        self.slam.save(folder / "session")
        cloud = self.slam.global_cloud()
        ply, trajectory = folder / "map.ply", folder / "trajectory.txt"
        write_gaussian_ply(ply, cloud, cloud.class_ids(self.palette.to(cloud.means.device)))
        poses = self.slam.trajectory(include_lost=False)  # as published: a lost frame has no odometry
        write_tum_trajectory(trajectory, Trajectory([t for t, _ in poses],
                                                    np.array([rigid_float64(p).numpy() for _, p in poses]
                                                            ).reshape(-1, 4, 4)))
        return ply, trajectory

    def _on_save_map(self, request, response):
        del request
        try:
            ply, trajectory = self.save_map(self.params.output_dir)
        except OSError as err:
            response.success, response.message = False, f"could not write to {self.params.output_dir}: {err}"
        else:
            response.success, response.message = True, f"wrote {ply} and {trajectory}"
        return response

    def load_map(self, folder: str | Path) -> None:
        """Replace the map by a saved session (raises OSError / ValueError when it cannot be read), re-publish it and
        relocalise the next frames against it."""
        slam = GauSemSLAM.load(folder, self.device, cfg=self.cfg)
        slam.back_end.detect_loops = not self.loop_nodes
        self.slam.close()
        self._reset_state(slam)
        header = ma.make_header(max((t for t, _ in slam.trajectory()), default=0.0), self.params.map_frame)
        self._publish_submaps(slam.submap_states(), header)
        keyframes = slam.keyframe_states()
        self._publish_keyframes(keyframes, header)
        if self.loop_nodes:
            stamps = {k.frame_id: k.timestamp for k in keyframes}
            self._loaded_places = [(p, stamps[p.keyframe_id]) for p in slam.loop_closure.stored_places()]
            self._send_loaded_places()
        self._publish_path()
        self._map_dirty = self._grid_dirty = True
        self.get_logger().info(f"loaded the map in {folder}: {len(slam.submaps)} submaps, {len(slam.trajectory())} "
                               "frames; "
                               "the next frames are relocalised against it")

    def _on_load_map(self, request, response):
        del request
        folder = self.get_parameter("map_path").value or str(Path(self.params.output_dir) / "session")
        try:
            self.load_map(folder)
        except (OSError, ValueError) as err:  # missing, truncated or foreign folder: the current map stays
            response.success, response.message = False, f"could not load {folder}: {err}"
        else:
            response.success, response.message = True, f"loaded {folder}"
        return response

    def _on_finish(self, request, response):
        del request
        self.finish()
        response.success, response.message = True, f"global refinement done over {len(self.slam.submaps)} submaps"
        return response

    def _on_reset(self, request, response):
        del request
        self.slam.close()  # deletes the old map's spilled submaps now
        self._reset_state()
        self.frames_processed = 0
        self._queue.clear()
        self._inputs.synchronizer.reset()  # a replay of the same stamps must not look stale
        self.drops.clear()
        self.latencies.clear()
        self._publish_path()
        response.success, response.message = True, "map and trajectory cleared"
        return response


    def interrupt(self) -> None:
        """Shutting down: the frame in progress finishes early (its optimisation cut short)."""
        self.slam.interrupt()

    def destroy_node(self) -> None:
        """With ``save_on_exit``, the map, trajectory and session are written to ``output_dir`` first."""
        if self.params.save_on_exit and self.frames_processed:
            try:
                ply, trajectory = self.save_map(self.params.output_dir)
                self.get_logger().info(f"wrote {ply} and {trajectory}")
            except OSError as err:
                self.get_logger().error(f"save_on_exit: could not write to {self.params.output_dir}: {err}")
        self.slam.close()  # deletes spilled submaps now (a command-line process skips the interpreter's teardown)
        if self._viewer is not None:
            self._viewer.close()
        super().destroy_node()


def latency_stats(latencies: list[float]) -> dict:
    """Median and 95th percentile of latencies in seconds, as ms (empty without any)."""
    if not latencies:
        return {}
    median, p95 = np.percentile(latencies, [50, 95])
    return {"latency_ms.median": round(1e3 * float(median), 1), "latency_ms.p95": round(1e3 * float(p95), 1)}


def main(args=None) -> int:
    return run_node(TrackingMappingNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
