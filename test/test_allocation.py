"""Submap allocation: frusta, overlap, class histograms and KL, both policies; the synthetic sequence end to end."""
import dataclasses
import math

import pytest
import torch

from gausem_core.config import SubmapConfig
from gausem_core.data import SYNTHETIC_CLASSES, SyntheticDataset
from gausem_core.eval.fragmentation import allocation_cohesion, object_instances, split_visits, submap_cohesion
from gausem_core.geometry import PinholeCamera, se3_exp
from gausem_core.slam.allocation import (
    Frustum, FrustumUnion, MotionAllocation, SemanticAllocation, SubmapExtent, class_histogram, class_kl,
    depth_range, euler_xyz_deg, frustum_corners, frustum_iou, frustum_overlap, frustum_volume, make_allocation,
    partition_keyframes,
)
from gausem_core.slam.observation import Observation

CAMERA = PinholeCamera(100.0, 100.0, 80.0, 60.0, 160, 120)  # x/z in [-0.8, 0.8], y/z in [-0.6, 0.6]
NEAR, FAR = 1.0, 3.0


def pose(rho=(0.0, 0.0, 0.0), omega=(0.0, 0.0, 0.0)) -> torch.Tensor:
    return se3_exp(torch.tensor([*rho, *omega], dtype=torch.float64))


def union(*poses) -> FrustumUnion:
    volume = FrustumUnion()
    for p in poses:
        volume.add(Frustum(CAMERA, p, NEAR, FAR))
    return volume


def observation(label: int, depth: float = 2.0) -> Observation:
    h, w = CAMERA.height, CAMERA.width
    labels = torch.full((h, w), label, dtype=torch.long)
    return Observation(torch.zeros(h, w, 3), torch.full((h, w), depth), torch.zeros(h, w, 3), labels, CAMERA)


# --- frusta and overlap ----------------------------------------------------------------------------------------------
def test_frustum_corners_by_hand():
    corners = frustum_corners(CAMERA, pose(rho=(1.0, 2.0, 3.0)), 1.0, 2.0)
    expected = torch.tensor([[-0.8, -0.6, 1], [0.8, -0.6, 1], [0.8, 0.6, 1], [-0.8, 0.6, 1]], dtype=torch.float64)
    offset = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    assert torch.allclose(corners, torch.cat([expected, 2 * expected]) + offset)
    with pytest.raises(ValueError, match="near"):
        frustum_corners(CAMERA, pose(), 2.0, 1.0)


def test_depth_range_percentiles_of_valid_depth():
    depth = torch.cat([torch.zeros(50), torch.arange(1, 102, dtype=torch.float32)]).reshape(1, -1)  # 1..101 m valid
    near, far = depth_range(depth)
    assert near == pytest.approx(6.0) and far == pytest.approx(96.0)
    with pytest.raises(ValueError, match="no valid"):
        depth_range(torch.zeros(4, 4))


def test_overlap_identical_and_disjoint():
    rotated = pose(rho=(0.3, -0.2, 0.1), omega=(0.1, 0.7, -0.2))
    assert frustum_overlap(CAMERA, rotated, (NEAR, FAR), union(rotated)) > 0.999
    facing_back = rotated @ pose(omega=(0.0, math.pi, 0.0))
    assert frustum_overlap(CAMERA, facing_back, (NEAR, FAR), union(rotated)) == 0.0
    assert frustum_overlap(CAMERA, rotated, (NEAR, FAR), FrustumUnion()) == 0.0


def test_overlap_half_shifted_along_the_optical_axis():
    # Moved forward by d, the frustum lies inside the first one up to z' = far - d (its cross-section is smaller):
    # fraction = ((far - d)^3 - near^3) / (far^3 - near^3) = 0.5 for (far - d)^3 = (far^3 + near^3) / 2.
    d = FAR - ((FAR**3 + NEAR**3) / 2) ** (1 / 3)
    assert frustum_overlap(CAMERA, pose(rho=(0, 0, d)), (NEAR, FAR), union(pose())) == pytest.approx(0.5, abs=0.01)


def test_overlap_shifted_sideways_matches_the_integral():
    # x/z in [-a, a]; shifted by dx the overlap width at depth z is 2 a z - dx (>= 0 on [near, far] here), the height
    # is unchanged: fraction = int (2 a z - dx) z dz / int 2 a z^2 dz over [near, far].
    a, dx = 0.8, 0.8
    inside = 2 * a * (FAR**3 - NEAR**3) / 3 - dx * (FAR**2 - NEAR**2) / 2
    expected = inside / (2 * a * (FAR**3 - NEAR**3) / 3)
    got = frustum_overlap(CAMERA, pose(rho=(dx, 0, 0)), (NEAR, FAR), union(pose()))
    assert got == pytest.approx(expected, abs=0.01)
    assert got == frustum_overlap(CAMERA, pose(rho=(dx, 0, 0)), (NEAR, FAR), union(pose()))  # deterministic


def test_volume_grows_with_keyframes():
    volume = union(pose())
    lo, hi = volume.bounds()
    probe = pose(omega=(0.0, 0.9, 0.0))  # turned right about the camera's y axis
    before = frustum_overlap(CAMERA, probe, (NEAR, FAR), volume)
    volume.add(Frustum(CAMERA, pose(omega=(0.0, 0.6, 0.0)), NEAR, FAR))
    lo2, hi2 = volume.bounds()
    assert bool((lo2 <= lo).all() and (hi2 >= hi).all()) and float(hi2[0]) > float(hi[0])
    after = frustum_overlap(CAMERA, probe, (NEAR, FAR), volume)
    assert after > before + 0.2


# --- class content ---------------------------------------------------------------------------------------------------
def test_class_histogram_by_hand():
    labels = torch.tensor([[0, 0], [1, 2]])
    proportions = torch.tensor([0.5, 0.25, 0.25, 0.0], dtype=torch.float64)
    assert torch.allclose(class_histogram(labels, 4, epsilon=0.0), proportions)
    eps = 0.01
    expected = (proportions + eps) / (1 + 4 * eps)
    assert torch.allclose(class_histogram(labels, 4, epsilon=eps), expected)
    valid = torch.tensor([[True, False], [True, False]])
    assert torch.allclose(class_histogram(labels, 2, valid, epsilon=0.0), torch.tensor([0.5, 0.5], dtype=torch.float64))
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        class_histogram(labels, 2)


def test_class_kl_by_hand_and_direction():
    p = torch.tensor([0.5, 0.5], dtype=torch.float64)
    q = torch.tensor([0.25, 0.75], dtype=torch.float64)
    assert class_kl(p, q) == pytest.approx(0.5 * math.log(2) + 0.5 * math.log(2 / 3))
    assert class_kl(q, p) == pytest.approx(0.25 * math.log(0.5) + 0.75 * math.log(1.5))
    assert class_kl(p, p) == 0.0
    with pytest.raises(ValueError, match="positive"):
        class_kl(torch.tensor([1.0, 0.0], dtype=torch.float64), q)


# --- policies --------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("turn, label, new",
                         [(0.0, 0, False), (0.0, 1, False), (math.pi, 0, False), (math.pi, 1, True)])
def test_semantic_policy_needs_both_conditions(turn, label, new):
    extent = SubmapExtent.start(observation(0), pose(), num_classes=3)
    policy = SemanticAllocation(0.5, 0.4)
    decision = policy.should_start_new(extent, observation(label), pose(omega=(0, turn, 0)))
    assert decision.new is new and decision.rule == "semantic"
    assert (decision.overlap < 0.5) == (turn > 0)
    assert (decision.kl > 0.4) == (label != 0)
    assert "overlap" in decision.reason and "class KL" in decision.reason


@pytest.mark.parametrize("shift, new", [(0.1, False), (0.8, True)])
def test_without_classes_the_motion_rule_decides(shift, new):
    """Data without labels: anchor and keyframe are all one class, the class KL is 0; the fallback splits by the
    motion rule (and says so); without it the submap never splits."""
    extent = SubmapExtent.start(observation(0), pose(), num_classes=1)
    moved = pose(rho=(0, 0, -shift))  # backwards along the view
    decision = SemanticAllocation(0.5, 0.4, fallback=MotionAllocation(0.5, 50.0)).should_start_new(
        extent, observation(0), moved)
    assert decision.new is new and decision.kl == 0.0
    assert decision.rule == "motion (no classes)" and "no classes known" in decision.reason
    assert not SemanticAllocation(0.5, 0.4).should_start_new(extent, observation(0), moved).new
    two_classes = SubmapExtent.start(observation(0), pose(), num_classes=2)
    two_classes.anchor_counts[1] = 5  # the anchor saw a second class: classes are known, the semantic rule holds
    assert SemanticAllocation(0.5, 0.4, fallback=MotionAllocation()).should_start_new(
        two_classes, observation(0), moved).rule == "semantic"


def test_semantic_policy_hysteresis_waits_for_min_keyframes():
    extent = SubmapExtent.start(observation(0), pose(), num_classes=2)
    policy = SemanticAllocation(0.5, 0.4, min_keyframes=3)
    turned = pose(omega=(0, math.pi, 0))
    first = policy.should_start_new(extent, observation(1), turned)
    assert not first.new and "1 < 3 keyframes" in first.reason and first.overlap == 0.0 and first.kl > 0.4
    extent.add(observation(0), pose(rho=(0.1, 0, 0)))
    extent.add(observation(0), pose(rho=(0.2, 0, 0)))
    assert extent.num_keyframes == 3 and policy.should_start_new(extent, observation(1), turned).new


def test_kl_to_anchor_grows_the_histograms_with_unseen_class_ids():
    extent = SubmapExtent.start(observation(0), pose(), num_classes=1)  # e.g. a system without a class table
    expected = class_kl(class_histogram(observation(4).labels, 5), class_histogram(observation(0).labels, 5))
    assert extent.kl_to_anchor(observation(4).labels) == pytest.approx(expected) and expected > 1.0
    assert extent.kl_to_anchor(observation(0).labels) == 0.0


@pytest.mark.parametrize("rho, omega, new", [((0.4, 0, 0), (0, 0, 0), False), ((0.3, 0.3, 0.3), (0, 0, 0), True),
                                             ((0, 0, 0), (0, math.radians(45), 0), False),
                                             ((0, 0, 0), (math.radians(55), 0, 0), True)])
def test_motion_policy_thresholds(rho, omega, new):
    first = pose(rho=(1.0, 0.0, 0.0), omega=(0.0, 0.0, 0.5))
    extent = SubmapExtent.start(observation(0), first, num_classes=2)
    decision = MotionAllocation(0.5, 50.0).should_start_new(extent, observation(0), first @ pose(rho, omega))
    assert decision.new is new and math.isnan(decision.overlap) and math.isnan(decision.kl)


def test_euler_angles_zyx():
    rot = (pose(omega=(0, 0, math.radians(20))) @ pose(omega=(0, math.radians(10), 0))
           @ pose(omega=(math.radians(5), 0, 0)))[:3, :3]
    assert torch.allclose(euler_xyz_deg(rot), torch.tensor([5.0, 10.0, 20.0], dtype=torch.float64))


def test_make_allocation_from_config():
    semantic = SubmapConfig(max_overlap=0.3, min_class_kl=0.2, min_keyframes=2)
    assert make_allocation(semantic) == SemanticAllocation(0.3, 0.2, 2)  # no fallback by default
    assert make_allocation(SubmapConfig(fallback_without_classes=True)).fallback == MotionAllocation(0.5, 50.0)
    motion = SubmapConfig(policy="motion", motion_translation=1.0, motion_rotation_deg=30.0)
    assert make_allocation(motion) == MotionAllocation(1.0, 30.0)
    with pytest.raises(ValueError, match="policy"):
        make_allocation(SubmapConfig(policy="size"))


def test_partition_keyframes_starts_submaps_at_new_decisions():
    turned = pose(omega=(0, math.pi, 0))
    keyframes = [(observation(0), pose()), (observation(0), pose()), (observation(1), turned), (observation(1), turned)]
    ids, decisions = partition_keyframes(SemanticAllocation(), keyframes, num_classes=2)
    assert ids == [0, 0, 1, 1] and [d.new for d in decisions] == [False, True, False]


# --- fragmentation measurement ------------------------------------------------------------------------------------
def test_object_instances_are_touching_same_class_voxels():
    points = torch.tensor([[0.0, 0, 0], [0.15, 0, 0], [0.25, 0.1, 0.05], [2.0, 0, 0], [0.2, 0, 0], [5.0, 5, 5]],
                          dtype=torch.float64)
    labels = torch.tensor([1, 1, 1, 1, 2, 0])
    ids = object_instances(points, labels, voxel=0.1, ignore_classes=(0,))
    assert ids[0] == ids[1] == ids[2] and len({int(ids[0]), int(ids[3]), int(ids[4])}) == 3 and ids[5] == -1


def test_submap_cohesion_by_hand():
    instances = torch.tensor([0, 0, 0, 0, 1, 1, -1])
    labels = torch.tensor([3, 3, 3, 3, 4, 4, 0])
    submaps = torch.tensor([0, 0, 0, 1, 1, 1, 0])
    cohesion = submap_cohesion(instances, labels, submaps, min_points=2)
    assert cohesion.objects == [(0, 3, 4, 0.75), (1, 4, 2, 1.0)]
    assert cohesion.mean == pytest.approx(0.875) and cohesion.worst == 0.75


def test_split_visits_separates_revisits():
    instances = torch.tensor([0, 0, 0, 0, 1, 1, -1, 0])
    keyframes = torch.tensor([0, 1, 3, 9, 2, 8, 5, 9])
    assert split_visits(instances, keyframes, revisit_gap=2).tolist() == [0, 0, 0, 1, 2, 3, -1, 1]
    assert split_visits(instances, keyframes, revisit_gap=6).tolist() == [0, 0, 0, 0, 1, 1, -1, 0]
    with pytest.raises(ValueError, match="revisit_gap"):
        split_visits(instances, keyframes, revisit_gap=0)


# --- the synthetic sequence -------------------------------------------------------------------------------------------
STRUCTURE = tuple(SYNTHETIC_CLASSES.id_of(n) for n in ("floor", "wall", "ceiling"))


@pytest.fixture(scope="module")
def synthetic_keyframes():
    """Every 5th frame of the 'default' sequence, with ground-truth poses standing in for estimates."""
    data = SyntheticDataset("default")
    frames = [data[i] for i in range(0, len(data), 5)]
    return [(Observation.from_arrays(f.rgb, f.depth, f.labels, f.camera, SYNTHETIC_CLASSES.palette),
             torch.tensor(f.gt_pose)) for f in frames]


def visible_objects(obs: Observation) -> set[int]:
    """Non-structural classes covering at least 1% of the image."""
    counts = torch.bincount(obs.labels.reshape(-1), minlength=len(SYNTHETIC_CLASSES))
    return {c for c in range(len(counts)) if c not in STRUCTURE and counts[c] >= 0.01 * obs.labels.numel()}


def test_synthetic_semantic_boundaries_follow_class_content_and_keep_objects_whole(synthetic_keyframes):
    """The allocation alone on ground-truth poses (fast and deterministic), default parameters: submap boundaries
    (frames), counts, and object cohesion per visit (revisits after a loop are loop closure's business)."""
    num_classes = len(SYNTHETIC_CLASSES)
    policies = {"semantic": SubmapConfig(), "paper": SubmapConfig(min_keyframes=1),
                "view": SubmapConfig(overlap="view"), "motion": SubmapConfig(policy="motion")}
    ids = {name: partition_keyframes(make_allocation(cfg), synthetic_keyframes, num_classes)[0]
           for name, cfg in policies.items()}

    def boundaries(name):
        return [k for k in range(1, len(ids[name])) if ids[name][k] != ids[name][k - 1]]

    assert [5 * k for k in boundaries("semantic")] == list(range(20, 180, 20))  # IoU < 0.5 from about 4 keyframes
    assert [5 * k for k in boundaries("view")] == [55, 85, 145]
    assert ids["paper"][-1] + 1 == 13 and ids["motion"][-1] + 1 == 12
    for name in ("semantic", "view"):
        anchors = [0] + boundaries(name)
        for previous, boundary in zip(anchors, boundaries(name)):  # the objects in view changed since the anchor
            assert visible_objects(synthetic_keyframes[boundary][0]) != visible_objects(
                synthetic_keyframes[previous][0])
    views = [(o.depth, o.labels, o.camera, p) for o, p in synthetic_keyframes]
    cohesion = {name: allocation_cohesion(views, submaps, STRUCTURE, stride=3, revisit_gap=5).mean
                for name, submaps in ids.items()}
    assert cohesion["view"] >= 0.9 and cohesion["view"] > cohesion["semantic"] > cohesion["paper"] > \
        cohesion["motion"]
    assert cohesion["semantic"] > cohesion["motion"] + 0.05
    whole = allocation_cohesion(views, ids["semantic"], STRUCTURE, stride=3)  # a revisited object is split
    assert whole.mean < cohesion["semantic"]


def test_a_slow_turn_splits_with_the_iou_and_never_with_the_view_fraction():
    """A camera turning on the spot 10 deg per keyframe, a new class in every view: the previous keyframe covers
    ~74 % of each view, so the view fraction never falls below 0.5 and the submap never splits; the IoU falls below
    0.5 once |F u V| > 2 |F n V|, here when the submap's fan is 20 deg wider than the view (its third keyframe)."""
    ramp = torch.linspace(NEAR, FAR, CAMERA.height)[:, None].expand(CAMERA.height, CAMERA.width)
    keyframes = [(dataclasses.replace(observation(k), depth=ramp.clone()),
                  pose(omega=(0.0, math.radians(10 * k), 0.0))) for k in range(30)]
    view, view_decisions = partition_keyframes(SemanticAllocation(overlap="view"), keyframes, num_classes=30)
    assert view[-1] == 0 and min(d.overlap for d in view_decisions) > 0.7
    assert min(d.kl for d in view_decisions) > 0.4
    iou, decisions = partition_keyframes(SemanticAllocation(overlap="iou"), keyframes, num_classes=30)
    assert iou[:5] == [0, 0, 1, 1, 2] and decisions[0].overlap > 0.5 > decisions[1].overlap
    assert iou[-1] == 14  # every second keyframe


def test_volumes_exact_and_sampled():
    assert frustum_volume(CAMERA, NEAR, FAR) == pytest.approx(1.6 * 1.2 * (FAR**3 - NEAR**3) / 3)
    one = union(pose())
    assert one.volume() == pytest.approx(frustum_volume(CAMERA, NEAR, FAR), rel=0.02)
    assert union(pose(), pose(rho=(0.0, 0.0, 10.0))).volume() == pytest.approx(2 * one.volume(), rel=0.03)
    assert union(pose(), pose()).volume() == pytest.approx(one.volume(), rel=0.02)
    assert FrustumUnion().volume() == 0.0
    assert frustum_iou(CAMERA, pose(), (NEAR, FAR), one) == pytest.approx(1.0, abs=0.03)
    with pytest.raises(ValueError, match="submaps.overlap"):
        SemanticAllocation(overlap="volume")
