"""The tracking-and-mapping node: owns :class:`GauSemSLAM` (and so the Gaussian map).

Subscribes ``rgb/image``, ``depth/image``, ``rgb/camera_info`` and ``semantic/labels`` (not with ``use_labels:
false``), approximately synchronised, in their own callback group, so inputs keep arriving while a frame is processed.
Frames are processed one at a time, the newest first (``NewestFrameQueue``): a tracker that falls behind skips frames
(counted by reason, docs/ROS.md "Every frame accounted for"; the core hears of them as skipped ones) instead of
building a backlog. In ``worker.mode: async`` (the default) a frame's odometry goes out once it is tracked and its
keyframe's events once the mapping worker has mapped it. This module holds the inputs, the call into the core and the
wiring; each output is a part in :mod:`gausem_ros.nodes.tracking`. Topics, services, parameters: docs/ROS.md.
"""
from __future__ import annotations

import math
import time
from pathlib import Path

import torch
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from sensor_msgs.msg import Image

import msg_adapters as ma
from gausem_core.geometry import rigid_float64
from gausem_core.maps.slam_grid import floor_class_id
from gausem_core.runtime import resolve_device
from gausem_core.semantics.source import UNLABELLED_PALETTE
from gausem_core.slam.events import FrameEvents
from gausem_core.slam.health import TrackingHealth
from gausem_core.slam.observation import Observation
from gausem_core.slam.persistence import SESSION_FILE
from gausem_core.slam.system import GauSemSLAM

from ..qos import input_qos
from ..sync import make_synchronizer
from ..tf import make_transform_broadcaster
from .common import (AccountingLock, DropReport, FrameRejected, NewestFrameQueue, class_table, count_error,
                     declare_parameters, declare_slam_config, run_node)
from .tracking.checkpoints import SessionCheckpoints
from .tracking.diagnostics import HEALTH_LEVELS, FrameAccounting, core_status, unpublished
from .tracking.frame_input import NO_LABELS_FIX, FrameInput
from .tracking.live_view import LiveView
from .tracking.loop_link import LoopNodesLink
from .tracking.map_outputs import MapPublisher
from .tracking.parameters import LIVE_DEFAULTS, NODE_DEFAULTS, check_parameters
from .tracking.records import RecordPublisher
from .tracking.services import MapServices, write_map
from .tracking.trajectory import TrajectoryPublisher

SYNC_REASONS = {"backwards": "stale_stamp", "duplicate": "duplicate_stamp", "unmatched": "unmatched",
                "lost_in_transport": "lost_in_transport"}


class TrackingMappingNode(Node):
    """``slam_defaults``: SLAM parameter defaults of this node (default :data:`LIVE_DEFAULTS`; the parameters given
    still win)."""

    def __init__(self, slam_defaults: dict | None = None, **kwargs):
        super().__init__("tracking_mapping", **kwargs)
        self.cfg = declare_slam_config(self, LIVE_DEFAULTS if slam_defaults is None else slam_defaults)
        self.params = p = declare_parameters(self, NODE_DEFAULTS)
        check_parameters(self.cfg, p)
        table = class_table(p.classes) if p.use_labels else None
        self.palette = table.palette if table is not None else UNLABELLED_PALETTE
        self.device = resolve_device(self.cfg.device)
        counting = AccountingLock()  # the input accounting's one lock (FrameAccounting)
        self.drops = DropReport(self, status=self._status, level=lambda: HEALTH_LEVELS[self.health.status],
                                lock=counting)
        if self.device.type == "cuda":  # the images are subscribed once the renderer is ready
            self.get_logger().info("preparing the renderer on cuda (gsplat compiles on a machine's first run: 1-2 min)")
        tf_static = make_transform_broadcaster(self, static=True) if p.base_frame or p.grid_frame else None
        self.trajectory = TrajectoryPublisher(self, p, tf_static)
        self.records = RecordPublisher(self)
        floor_class = floor_class_id(table.names if table is not None else None, self.cfg.grid.floor_class)
        self.map_outputs = MapPublisher(self, p, self.cfg.grid, self.palette, floor_class, tf_static, self.stamp)
        self.checkpoints = SessionCheckpoints(self.get_logger(), p) if p.map_path else None
        self.loop_link = LoopNodesLink(self, p, self.records, self.drops, lambda: self._queue.wake(), self.stamp,
                                       self.map_moved) if self.loop_nodes else None
        qos, input_group = input_qos(p.input_qos), MutuallyExclusiveCallbackGroup()  # arriving while one processes
        self.frame_input = FrameInput(self, p, self.palette, self.device, self.drops, qos, input_group)
        self._reset_state()
        self.viewer = LiveView(self.get_logger(), p, self.palette)
        inputs = [("rgb", Image, "rgb/image"), ("depth", Image, "depth/image")] + (
            [("labels", Image, "semantic/labels")] if p.use_labels else [])
        self._inputs = make_synchronizer(self, inputs, self._on_frame, qos, queue_size=p.sync_queue_size,
                                         slop=p.sync_slop, on_drop=self._on_sync_drop, callback_group=input_group,
                                         lock=counting)
        self._queue = NewestFrameQueue(self, self._process, lambda _: self.drops.drop(
            "superseded", "a newer synchronised frame arrived before this one was processed"),
            ready=self.loop_link.settled if self.loop_link else lambda: True, lock=counting)
        self.accounting = FrameAccounting(self._inputs.synchronizer, self._queue, self.drops, counting)
        if p.sync_wait:
            self.create_timer(min(p.sync_wait / 2, 0.5), lambda: self._inputs.synchronizer.flush(p.sync_wait),
                              callback_group=input_group)
        self.map_services = MapServices(self)
        if p.map_path and (Path(p.map_path) / SESSION_FILE).exists():
            try:
                self.map_services.load_map(p.map_path)
            except (OSError, ValueError) as err:  # a truncated or foreign session: say which parameter names it
                raise ValueError(f"tracking_mapping: cannot load map_path {p.map_path!r}: {err}") from err
        elif p.map_path:
            self.get_logger().info(f"no session in map_path {p.map_path} yet: a new map, checkpointed there")

    @property
    def loop_nodes(self) -> bool:
        """Whether loops come from the loop_detection and pose_graph nodes (``loop_closure: nodes``)."""
        return self.cfg.loop.enabled and self.params.loop_closure == "nodes"

    @property
    def frames_processed(self) -> int:
        """Frames whose pose was published (kept across load_map, cleared by gausem/reset)."""
        return self.accounting.processed

    @property
    def seconds(self) -> float:
        """Wall time from the first processed frame's start to the last one's end (0 before any frame)."""
        return self._busy[1] - self._busy[0] if self._busy else 0.0

    def stamp(self) -> float:
        """The stamp of what is published between frames: the last frame's (0 before any)."""
        return max(self._last_stamp, 0.0)

    def _reset_state(self, slam: GauSemSLAM | None = None) -> None:
        """A new map (or ``slam``, a loaded one) with the node's and its parts' per-map state cleared."""
        torch.manual_seed(self.cfg.seed)
        self.slam = slam or GauSemSLAM(self.cfg, self.device, num_classes=len(self.palette),
                                       detect_loops=not self.loop_nodes)
        self._busy: tuple[float, float] | None = None  # perf_counter at the first processed frame's start, last end
        self._last_stamp = -math.inf
        self.map_age = 0  # frames between the last frame and the newest keyframe of the map it was tracked against
        self.health = TrackingHealth("ok")  # the last frame's
        self.health_log: list[tuple[int, float, TrackingHealth]] = []  # every frame the core took, dropped ones too
        self.frame_input.reset()
        for part in (self.trajectory, self.map_outputs, self.checkpoints, self.loop_link):
            if part is not None:
                part.reset(self.slam)

    def replace_map(self, slam: GauSemSLAM | None = None) -> None:
        """Close the map (its spilled submaps deleted now; no map output reads it meanwhile) for ``slam`` or anew."""
        with self.map_outputs.paused():
            self.slam.close()
            self._reset_state(slam)

    def _on_frame(self, *msgs: Image) -> None:
        self._queue.put(msgs, ma.header_seconds(msgs[0].header))

    def _on_sync_drop(self, index: int, reason: str, detail: str, stamp: float | None) -> None:
        """An rgb image the synchroniser dropped: a lost frame, counted by reason and named as handled."""
        if index:
            return
        if stamp is not None:
            self.accounting.handled_ns = max(self.accounting.handled_ns, ma.seconds_to_ns(stamp))
        sync = self._inputs.synchronizer
        silent = [name for name, received in zip(sync.names, sync.received) if not received]
        if reason == "unmatched" and silent:
            reason = f"no_{silent[0]}"
            detail += f"; {NO_LABELS_FIX}" if silent[0] == "labels" else ""
        if reason == "lost_in_transport":  # unstamped, but after the last rgb received, so after any pending frame
            stamp = math.inf
        self._skip(SYNC_REASONS.get(reason, reason), detail, stamp)

    def _skip(self, reason: str, detail: str, stamp: float | None = None) -> None:
        """A frame dropped before the core: counted by reason, passed on with the next frame as a skipped one."""
        self._queue.skip(stamp=stamp)
        self.drops.drop(reason, detail)

    def _observation(self, *msgs: Image) -> Observation:
        """The observation of one synchronised frame in the map's camera, or FrameRejected (``frame_input``)."""
        map_camera = self.slam.submaps[0].keyframes[0].obs.camera if self.slam.submaps else None
        return self.frame_input.observation(msgs, self._last_stamp, map_camera)

    def _process(self, msgs: tuple[Image, ...], arrived: float, skipped: int) -> None:
        """One synchronised frame, ``skipped`` dropped before it; an exception is counted as a processing_error drop
        of the frame (one raised after its pose went out: of no frame) and the node goes on."""
        try:
            self._process_frame(msgs, arrived, skipped)
        except Exception as err:  # noqa: BLE001 -- one frame must never end the node
            with self.accounting.lock:
                frame = bool(self._queue.in_progress)
                self._queue.settle()
                count_error(self, "_process", err, frame)

    def _process_frame(self, msgs: tuple[Image, ...], arrived: float, skipped: int) -> None:
        start = time.perf_counter()
        self.accounting.handled_ns = ma.time_to_ns(msgs[0].header.stamp)
        try:
            obs = self._observation(*msgs)
        except Exception as err:
            self._queue.skip(skipped)  # passed on with the next frame, as is this one when it is rejected
            if not isinstance(err, FrameRejected):
                raise  # counted as a processing_error drop
            with self.accounting.lock:
                self._queue.settle()
                self._skip(err.reason, str(err))
            return
        self._track_and_publish(obs, msgs[0].header.frame_id, arrived, skipped)
        self._busy = (self._busy[0] if self._busy else start, time.perf_counter())
        if self.checkpoints is not None:
            self.checkpoints.after_frame()

    def _track_and_publish(self, obs: Observation, image_frame: str, arrived: float, skipped: int) -> None:
        result = self.slam.process(obs, skipped)
        self.viewer.frame(obs, result, self.slam)
        self._last_stamp = obs.timestamp
        self.map_age = result.map_age
        self._publish_mapped(result.mapped)
        self.health = result.health
        self.health_log.append((result.frame_id, obs.timestamp, result.health))
        reloc, pose = result.relocalisation, rigid_float64(result.cam_to_world).numpy()
        if reloc is not None and reloc.accepted:
            self.get_logger().info(f"relocalised against the map (submap {reloc.submap_id}, inlier fraction "
                                   f"{reloc.inlier_fraction:.2f}); tracking goes on")
        if "new_segment" in result.health.reasons:
            self.get_logger().warning(f"map lost for good: a new tracking segment starts (submap {result.submap_id}) "
                                      "at the last good pose; a loop to the old map will merge them")
        if (why := unpublished(result, pose, obs.timestamp)) is not None:
            self.accounting.dropped(*why)
            return
        self.trajectory.publish_odometry(pose, obs.timestamp, image_frame, result.health.status == "degraded")
        self.accounting.published(arrived)
        self.trajectory.publish_motion(result, pose, obs.timestamp)
        self._publish_events(result.events, ma.make_header(obs.timestamp, self.params.map_frame))
        self.map_outputs.map_changed()
        self.drops.publish()

    def _publish_mapped(self, mapped: tuple[FrameEvents, ...]) -> None:
        """The events of keyframes the mapping worker finished (async), stamped like their keyframes."""
        for events in mapped:
            self.trajectory.note_events(events)
            stamp = events.keyframe.timestamp if events.keyframe is not None else self.stamp()
            self._publish_events(events, ma.make_header(stamp, self.params.map_frame))

    def _publish_events(self, events: FrameEvents, header) -> None:
        """A frame's records; a loop keyframe's place signature goes to loop_detection (``loop_closure: nodes``)."""
        self.records.publish_events(events, header)
        if events.keyframe is not None:
            self.map_outputs.grid_changed()
        if events.place is not None:
            self.loop_link.publish_place(events.place, events.keyframe.timestamp)

    def map_moved(self) -> None:
        """The map was corrected or replaced: the path rebuilt now, the map and grid with their next periods."""
        self.trajectory.path_corrected()
        self.trajectory.publish_path()
        self.map_outputs.map_changed()
        self.map_outputs.grid_changed()

    def finish(self) -> None:
        """End of the sequence: the core's end of a run (``GauSemSLAM.finish``), counted in ``seconds``; then the
        outputs are re-published (``MapServices.republish``)."""
        start = time.perf_counter()
        loop = self.slam.finish()
        if self._busy:
            self._busy = (self._busy[0], self._busy[1] + time.perf_counter() - start)
        self._publish_mapped(self.slam.take_mapped())  # async: the keyframes mapped after the last frame
        self.map_services.republish(loop)
        self.viewer.finish(self.slam)

    def save_map(self, folder: str | Path) -> tuple[Path, Path]:
        """Write ``map.ply``, ``trajectory.txt`` and ``session/`` to ``folder`` (``services.write_map``)."""
        return write_map(self.slam, folder, self.palette)

    def reset(self) -> None:
        """A new map, with the trajectory and the input accounting cleared."""
        self.replace_map()
        with self.accounting.lock:
            self.accounting.clear()
            self._queue.clear()
            self._inputs.synchronizer.reset()  # a replay of the same stamps must not look stale
            self.drops.clear()
        self.trajectory.publish_path()

    def _status(self) -> dict:
        """gausem/diagnostics' values besides the drop counts (``diagnostics``)."""
        return self.accounting.status({
            **core_status(self.slam, self.health, self.map_age, bool(self.frame_input.lens_distortion)),
            **(self.checkpoints.status() if self.checkpoints is not None else {})})

    def summary(self) -> dict:
        """The whole run's input accounting: frames in = processed + dropped (by reason) + pending; latency."""
        return self.accounting.summary()

    def interrupt(self) -> None:
        """Shutting down: the frame in progress finishes early (its optimisation cut short)."""
        self.slam.interrupt()

    def destroy_node(self) -> None:
        """With ``save_on_exit``, the map, trajectory and session are written to ``output_dir`` first."""
        self.map_services.save_on_exit()
        self.slam.close()  # deletes spilled submaps now (a command-line process skips the interpreter's teardown)
        self.viewer.close()
        super().destroy_node()


def main(args=None) -> int:
    return run_node(TrackingMappingNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
