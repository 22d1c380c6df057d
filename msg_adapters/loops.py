"""Loop records <-> the core's loop types: candidates (loop_detection -> tracking_mapping) and registered
constraints (tracking_mapping -> pose_graph). A constraint's (rotation, translation) sigmas travel as the record's
6x6 information matrix, diagonal in twist order (rho, omega): 1/sigma_t^2 three times, then 1/sigma_r^2."""
from __future__ import annotations

import numpy as np
import torch

from gausem_core.slam.loop import LoopCandidate
from gausem_core.slam import loop_graphs
from gausem_core.slam.loop_closure import LoopConstraint

from .records import LoopCandidateRecord, LoopConstraintRecord, PoseGraphNode, PoseGraphNodeKind, PoseGraphUpdate


def loop_candidate_to_record(candidate: LoopCandidate) -> LoopCandidateRecord:
    return LoopCandidateRecord(candidate.query_keyframe, candidate.match_keyframe, candidate.query_submap,
                               candidate.match_submap, candidate.descriptor_distance, candidate.landmark_distance,
                               candidate.intra)


def record_to_loop_candidate(record: LoopCandidateRecord) -> LoopCandidate:
    candidate = LoopCandidate(record.query_keyframe_id, record.match_keyframe_id, record.query_submap_id,
                              record.match_submap_id, record.descriptor_distance, record.landmark_distance)
    if candidate.intra != record.intra_submap:
        raise ValueError(f"loop candidate {record.query_keyframe_id}->{record.match_keyframe_id}: intra_submap is "
                         f"{record.intra_submap} but the submaps are {record.query_submap_id} and "
                         f"{record.match_submap_id}")
    return candidate


def sigmas_to_information(sigmas: tuple[float, float]) -> np.ndarray:
    rotation, translation = sigmas
    if not (rotation > 0 and translation > 0):
        raise ValueError(f"sigmas must be positive (rotation, translation), got {sigmas}")
    return np.diag([translation**-2] * 3 + [rotation**-2] * 3)


def information_to_sigmas(information: np.ndarray) -> tuple[float, float]:
    """(rotation, translation) sigmas from the diagonal of an information matrix (the mean of each block)."""
    diagonal = np.diag(np.asarray(information, dtype=np.float64))
    if not (np.isfinite(diagonal).all() and (diagonal > 0).all()):
        raise ValueError(f"the information matrix needs a finite positive diagonal, got {diagonal}")
    return float(diagonal[3:].mean() ** -0.5), float(diagonal[:3].mean() ** -0.5)


def loop_constraint_to_record(constraint: LoopConstraint) -> LoopConstraintRecord:
    return LoopConstraintRecord(constraint.keyframe_a, constraint.keyframe_b, constraint.submap_a,
                                constraint.submap_b, constraint.relative.detach().cpu().double().numpy(),
                                float(constraint.fitness), sigmas_to_information(constraint.sigmas), constraint.intra)


def record_to_loop_constraint(record: LoopConstraintRecord) -> LoopConstraint:
    if record.intra_submap != (record.submap_a == record.submap_b):
        raise ValueError(f"loop constraint {record.keyframe_a}-{record.keyframe_b}: intra_submap is "
                         f"{record.intra_submap} but the submaps are {record.submap_a} and {record.submap_b}")
    return LoopConstraint(record.keyframe_a, record.keyframe_b, record.submap_a, record.submap_b,
                          torch.tensor(np.asarray(record.relative_pose), dtype=torch.float64),
                          information_to_sigmas(record.information), record.fitness, record.intra_submap)


def pose_graph_update_from_core(update: loop_graphs.PoseGraphUpdate) -> PoseGraphUpdate:
    """The core's corrected poses as records: KEYFRAME nodes (by frame id), then ANCHOR nodes (by submap id)."""
    return PoseGraphUpdate([PoseGraphNode(PoseGraphNodeKind.KEYFRAME, k, pose) for k, pose in update.keyframes.items()]
                           + [PoseGraphNode(PoseGraphNodeKind.ANCHOR, s, pose) for s, pose in update.anchors.items()])


def pose_graph_update_to_core(update: PoseGraphUpdate) -> loop_graphs.PoseGraphUpdate:
    """Records back to the core's corrected poses (keyframes by frame id, anchors by submap id)."""
    return loop_graphs.PoseGraphUpdate({n.node_id: n.pose for n in update.nodes if n.kind == PoseGraphNodeKind.KEYFRAME},
                                       {n.node_id: n.pose for n in update.nodes if n.kind == PoseGraphNodeKind.ANCHOR})
