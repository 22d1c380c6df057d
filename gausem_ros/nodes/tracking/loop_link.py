"""``loop_closure: nodes`` (distributed, docs/DESIGN.md §4): the tracking node's side of loop closure over three
nodes running the same core code.

The node's core describes each loop keyframe (:meth:`~gausem_core.slam.loop_closure.LoopClosure.describe`); its place
signature goes out on ``gausem/place_signatures`` (PlaceSignatureRecord); loop_detection runs the core's detector on
it and answers with the ranked candidates (``gausem/loop_candidates``); the core here confirms one (the bag of words:
geometric verification in order, which needs both keyframes' images, held here) and registers it (keyframe alignment
or SGR: it holds the Gaussians, ``GauSemSLAM.register_loop``), and an accepted loop goes out on
``gausem/loop_constraints`` (after every keyframe is re-published with its current pose and anchor, which bundle
adjustment and corrections changed since, as the core's :meth:`~gausem_core.slam.loop_closure.LoopClosure.correct`
takes them); pose_graph optimises (the core's :class:`~gausem_core.slam.loop_graphs.LoopGraphs`) and answers on
``gausem/pose_graph``, applied here (``GauSemSLAM.apply_pose_graph``). The next frame waits for those answers
(:mod:`~gausem_ros.nodes.loop_answers`, ``loop_answer_timeout`` s at most), as ``gausem run`` applies them within the
keyframe's call: a lock-step replay gives the same loops, but for the check of the last loop keyframes at the end of
a run (``loop.check_at_end``, off by default), which only ``loop_closure: core`` makes.

A loaded map's loop database goes to loop_detection too: its stored place signatures, flagged loaded, the first
flagged new_map, one at a time in step with loop_detection's answers, before the next frame, so loops close into the
loaded map as with ``core``."""
from __future__ import annotations

from collections.abc import Callable
from types import SimpleNamespace

from sensor_msgs.msg import PointCloud2

import msg_adapters as ma
from gausem_core.slam.loop import PlaceSignature
from gausem_core.slam.system import GauSemSLAM

from ...qos import EVENT_QOS
from ..common import DropReport, survives_errors
from ..loop_answers import LoopAnswers
from .records import RecordPublisher


class LoopNodesLink:
    """The place signatures out, the loop answers in. ``wake()``: a frame waiting for :meth:`settled` may go on;
    ``stamp()``: the stamp of what goes out between frames; ``map_moved()``: a pose-graph answer moved the map."""

    def __init__(self, node, params: SimpleNamespace, records: RecordPublisher, drops: DropReport,
                 wake: Callable[[], None], stamp: Callable[[], float], map_moved: Callable[[], None]):
        self.get_logger, self.drops = node.get_logger, drops  # as survives_errors takes them
        self._map_frame, self._records, self._wake, self._stamp, self._map_moved = (
            params.map_frame, records, wake, stamp, map_moved)
        self._signature_pub = node.create_publisher(PointCloud2, "gausem/place_signatures", EVENT_QOS)
        node.create_subscription(PointCloud2, "gausem/loop_candidates", self._on_loop_candidates, EVENT_QOS)
        node.create_subscription(PointCloud2, "gausem/pose_graph", self._on_pose_graph, EVENT_QOS)
        self._answer_timer = node.create_timer(0.05, self._await_answers)
        self._answer_timer.cancel()  # runs while an answer is awaited
        timeout = params.loop_answer_timeout
        self._answers = LoopAnswers(
            timeout, lambda: self._signature_pub.get_subscription_count() > 0, records.constraint_listened,
            lambda what: self.get_logger().warning(f"no {what} answer within loop_answer_timeout = {timeout} s; "
                                                   "going on with the next frame"))
        self.candidates: list[ma.LoopCandidateRecord] = []  # handled
        self.pose_graph_updates: list[ma.PoseGraphUpdate] = []  # applied

    def reset(self, slam: GauSemSLAM) -> None:
        """A new map (or a loaded one): nothing awaited, the next signature is the map's first."""
        self._slam = slam
        self._answers.clear()
        self._new_map = True  # the next place signature is the map's first (loop_detection starts over)
        self._loaded_places: list[tuple[PlaceSignature, float]] = []  # a loaded map's, still to go to loop_detection

    def send_loaded(self, stamps: dict[int, float]) -> None:
        """Send the loaded map's loop database (``stamps``: its keyframes' by frame id), each once the last one was
        answered."""
        self._loaded_places = [(p, stamps[p.keyframe_id]) for p in self._slam.loop_closure.stored_places()]
        self._send_loaded_places()

    def settled(self) -> bool:
        """Whether the next frame may be processed: loop_detection holds the loaded map and no answer is awaited."""
        return not self._loaded_places and self._answers.settled()

    def publish_place(self, place: PlaceSignature, stamp: float, loaded: bool = False) -> None:
        """Send a place signature (stamped like its keyframe) to loop_detection; its answer is awaited."""
        self._answers.expect_candidates(stamp)
        self._answer_timer.reset()
        record = ma.place_signature_to_record(place, stamp, loaded=loaded, new_map=self._new_map)
        self._new_map = False
        self._signature_pub.publish(ma.records_to_pointcloud2([record], ma.make_header(stamp, self._map_frame)))

    def _send_loaded_places(self) -> None:
        while self._loaded_places and self._answers.settled():
            self.publish_place(*self._loaded_places.pop(0), loaded=True)

    def _await_answers(self) -> None:
        """While answers are awaited: once they are given up (timeout, helper gone), send the next loaded signature,
        if any, or wake the waiting frame."""
        self._send_loaded_places()
        if self.settled():
            self._answer_timer.cancel()
            self._wake()

    @survives_errors(frame=False)
    def _on_loop_candidates(self, msg: PointCloud2) -> None:
        """One query keyframe's ranked candidates (possibly none): the loop closure confirms one (verification with
        the bag of words) and registers it; an accepted loop goes out to pose_graph, whose answer is then awaited."""
        try:
            self._close_loop(msg)
        finally:
            self._answers.candidates_arrived(ma.header_seconds(msg.header))
            self._send_loaded_places()
            self._wake()

    def _close_loop(self, msg: PointCloud2) -> None:
        try:
            candidates = ma.pointcloud2_to_records(msg, ma.LoopCandidateRecord)
            outcome = self._slam.register_loop([ma.record_to_loop_candidate(c) for c in candidates])
        except ValueError as err:  # unknown keyframes (e.g. from before a reset), inconsistent records
            self.drops.drop("bad_loop_candidates", str(err), frame=False)
            return
        self.candidates += candidates
        if outcome is None:
            return
        constraint, record = outcome.constraint, outcome.record
        self.get_logger().info(f"loop candidate {record.query_frame}->{record.match_frame} (submaps "
                               f"{record.query_submap}, {record.match_submap}, {len(candidates)} ranked): "
                               f"{'accepted' if constraint else 'rejected'}, fitness {record.fitness:.3f}, "
                               f"{record.seconds:.2f} s")
        if constraint is None:
            return
        header = ma.make_header(self._stamp(), self._map_frame)
        self._records.publish_keyframes(self._slam.keyframe_states(), header)  # the poses and anchors as they are now
        self._answers.expect_pose_graph()
        self._answer_timer.reset()
        self._records.publish_loop(outcome, header)

    @survives_errors(frame=False)
    def _on_pose_graph(self, msg: PointCloud2) -> None:
        try:
            self._apply_pose_graph(msg)
        finally:
            self._answers.pose_graph_arrived()
            self._wake()

    def _apply_pose_graph(self, msg: PointCloud2) -> None:
        try:
            update = ma.pointcloud2_to_pose_graph_update(msg)
        except ValueError as err:
            self.drops.drop("bad_pose_graph", str(err), frame=False)
            return
        correction = self._slam.apply_pose_graph(ma.pose_graph_update_to_core(update))
        self.get_logger().info(f"pose graph update of {len(update.nodes)} poses: moved {correction.anchors} submaps "
                               f"and {correction.keyframes} keyframes (in {len(correction.submaps)} submaps)")
        if correction:
            self._map_moved()
        self.pose_graph_updates.append(update)
