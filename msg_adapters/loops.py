"""Loop records <-> the core's loop types: place signatures (tracking_mapping -> loop_detection), candidates
(loop_detection -> tracking_mapping) and registered constraints (tracking_mapping -> pose_graph). A constraint's
(rotation, translation) sigmas travel as the record's 6x6 information matrix, diagonal in twist order (rho, omega):
1/sigma_t^2 three times, then 1/sigma_r^2."""
from __future__ import annotations

import numpy as np
import torch

from gausem_core.slam.loop import LoopCandidate, PlaceSignature
from gausem_core.slam import loop_graphs
from gausem_core.slam.features import DESCRIPTOR_BYTES, OrbFeatures
from gausem_core.slam.loop_closure import LoopConstraint

from .records import (LoopCandidateRecord, LoopConstraintRecord, PlaceSignatureRecord, PoseGraphNode,
                      PoseGraphNodeKind, PoseGraphUpdate)


def place_signature_to_record(place: PlaceSignature, stamp: float, *, loaded: bool = False,
                              new_map: bool = False) -> PlaceSignatureRecord:
    """A keyframe's place signature (stamped like the keyframe) as a record (flags: see the record)."""
    bow = isinstance(place.appearance, OrbFeatures)
    features = place.appearance if bow else OrbFeatures(np.zeros((0, 2), np.float32),
                                                        np.zeros((0, DESCRIPTOR_BYTES), np.uint8),
                                                        np.zeros((0, 3), np.float32), 1)
    descriptor = np.zeros(0, np.float32) if bow else place.appearance.detach().cpu().numpy()
    return PlaceSignatureRecord(place.keyframe_id, stamp, place.submap_id, bow, descriptor, features.keypoints,
                                features.descriptors, features.points, features.scale,
                                place.landmark_scores.detach().cpu().double().numpy(), np.array(place.nearby),
                                loaded, new_map)


def record_to_place_signature(record: PlaceSignatureRecord) -> PlaceSignature:
    """The core's place signature of a record; ValueError when it carries both or neither kind of appearance."""
    rows = {len(record.orb_keypoints), len(record.orb_descriptors), len(record.orb_points)}
    name = f"place signature of keyframe {record.keyframe_id}"
    if len(rows) > 1:
        raise ValueError(f"{name}: ORB keypoints, descriptors and points differ in count ({sorted(rows)})")
    if record.bag_of_words:
        if len(record.descriptor) or record.orb_scale < 1:
            raise ValueError(f"{name}: ORB features need an empty descriptor and orb_scale >= 1, got "
                             f"{len(record.descriptor)} values and {record.orb_scale}")
        appearance = OrbFeatures(np.array(record.orb_keypoints), np.array(record.orb_descriptors),
                                 np.array(record.orb_points), record.orb_scale)
    else:
        if not len(record.descriptor) or rows != {0}:
            raise ValueError(f"{name}: a global descriptor needs values and no ORB rows, got "
                             f"{len(record.descriptor)} values and {rows.pop()} rows")
        appearance = torch.tensor(np.array(record.descriptor))
    return PlaceSignature(record.keyframe_id, record.submap_id, appearance,
                          torch.tensor(np.array(record.landmark_scores)), tuple(record.nearby.tolist()))


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
