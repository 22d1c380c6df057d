"""The tracking node's services (std_srvs/Trigger): ``gausem/save_map`` writes ``map.ply``, ``trajectory.txt``
(TUM) and the whole SLAM state (``session/``, :mod:`gausem_core.slam.persistence`) to ``output_dir``;
``gausem/load_map`` replaces the map by the session in ``map_path`` (default: ``output_dir/session``) and
re-publishes it (submaps, keyframes, path, map: pose_graph rebuilds its graph), relocalising the next frames against
it (until one is placed, frames are dropped as ``relocalisation_failed`` and nothing is published for them);
``gausem/finish`` ends the sequence with the global refinement (as the offline pipeline does after the last frame);
``gausem/reset`` starts a new map. ``save_on_exit``: what save_map writes, also when the node shuts down."""
from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from std_srvs.srv import Trigger

import msg_adapters as ma
from gausem_core.geometry import rigid_float64
from gausem_core.io.ply import write_gaussian_ply
from gausem_core.io.trajectory import Trajectory, write_tum_trajectory
from gausem_core.slam.loop_closure import LoopOutcome
from gausem_core.slam.system import GauSemSLAM


def write_map(slam: GauSemSLAM, folder: str | Path, palette: torch.Tensor) -> tuple[Path, Path]:
    """Write the map (3DGS-style PLY with class ids: the nearest ``palette`` colour), the trajectory (TUM) and the
    session (``session/``, what ``map_path`` loads) to ``folder``; the PLY's and the trajectory's paths."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    slam.save(folder / "session")
    cloud = slam.global_cloud()
    ply, trajectory = folder / "map.ply", folder / "trajectory.txt"
    write_gaussian_ply(ply, cloud, cloud.class_ids(palette.to(cloud.means.device)))
    poses = slam.trajectory(include_lost=False)  # as published: a lost frame has no odometry
    write_tum_trajectory(trajectory, Trajectory([t for t, _ in poses],
                                                np.array([rigid_float64(p).numpy() for _, p in poses]
                                                         ).reshape(-1, 4, 4)))
    return ply, trajectory


class MapServices:
    """The map as a whole: the four triggers and what they do, over the node's parts."""

    def __init__(self, node):
        self._node = node
        node.create_service(Trigger, "gausem/save_map", self._on_save_map)
        node.create_service(Trigger, "gausem/reset", self._on_reset)
        node.create_service(Trigger, "gausem/load_map", self._on_load_map)
        node.create_service(Trigger, "gausem/finish", self._on_finish)

    def load_map(self, folder: str | Path) -> None:
        """Replace the map by a saved session (raises OSError / ValueError when it cannot be read), re-publish it
        (submaps, keyframes, with ``loop_closure: nodes`` the loop database, path, map) and relocalise the next
        frames against it."""
        node = self._node
        slam = GauSemSLAM.load(folder, node.device, cfg=node.cfg)
        slam.detect_loops = not node.loop_nodes
        node.replace_map(slam)
        header = ma.make_header(max((t for t, _ in slam.trajectory()), default=0.0), node.params.map_frame)
        node.records.publish_submaps(slam.submap_states(), header)
        keyframes = slam.keyframe_states()
        node.records.publish_keyframes(keyframes, header)
        if node.loop_link is not None:
            node.loop_link.send_loaded({k.frame_id: k.timestamp for k in keyframes})
        node.map_moved()
        node.get_logger().info(f"loaded the map in {folder}: {len(slam.submaps)} submaps, "
                               f"{len(slam.trajectory())} frames; the next frames are relocalised against it")

    def save_on_exit(self) -> None:
        """With ``save_on_exit`` (and frames processed), what save_map writes, as the node shuts down."""
        node, folder = self._node, self._node.params.output_dir
        if not (node.params.save_on_exit and node.frames_processed):
            return
        try:
            ply, trajectory = node.save_map(folder)
            node.get_logger().info(f"wrote {ply} and {trajectory}")
        except OSError as err:
            node.get_logger().error(f"save_on_exit: could not write to {folder}: {err}")

    def republish(self, loop: LoopOutcome | None) -> None:
        """After the end of a run: the loop closed then (if accepted), the keyframes as loop closure and refinement
        left them, the corrected path, the map and the grid, now (a caller that finishes may stop spinning right
        after)."""
        node = self._node
        header = ma.make_header(node.stamp(), node.params.map_frame)
        node.records.publish_loop(loop, header)
        if node.slam.submaps:
            node.records.publish_keyframes(node.slam.keyframe_states(), header)
        node.map_moved()
        node.map_outputs.publish_now()

    def _on_save_map(self, request, response):
        folder = self._node.params.output_dir
        return _answer(response, lambda: "wrote {} and {}".format(*self._node.save_map(folder)), OSError,
                       f"could not write to {folder}")

    def _on_load_map(self, request, response):
        folder = self._node.get_parameter("map_path").value or str(Path(self._node.params.output_dir) / "session")

        def load() -> str:
            self.load_map(folder)
            return f"loaded {folder}"
        # missing, truncated or foreign folder: the current map stays
        return _answer(response, load, (OSError, ValueError), f"could not load {folder}")

    def _on_finish(self, request, response):
        def finish() -> str:
            self._node.finish()
            return f"global refinement done over {len(self._node.slam.submaps)} submaps"
        return _answer(response, finish)

    def _on_reset(self, request, response):
        def reset() -> str:
            self._node.reset()
            return "map and trajectory cleared"
        return _answer(response, reset)


def _answer(response, action: Callable[[], str], errors: type[Exception] | tuple[type[Exception], ...] = (),
            failure: str = ""):
    """A Trigger's response: success with ``action()``'s message, or on one of ``errors`` failure with ``failure``
    and the error."""
    try:
        message = action()
    except errors as err:
        response.success, response.message = False, f"{failure}: {err}"
    else:
        response.success, response.message = True, message
    return response
