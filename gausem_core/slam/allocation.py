"""Submap allocation (paper §III-A): when does a keyframe start a new submap?

Two interchangeable policies with one call signature, built from :class:`SubmapConfig` by :func:`make_allocation`:

- :class:`SemanticAllocation` (the paper's rule): a new submap when the current keyframe's viewing frustum overlaps
  the active submap's bounding volume by less than ``max_overlap`` AND the KL divergence of its class histogram from
  the submap anchor's exceeds ``min_class_kl``; with hysteresis, not before the submap holds ``min_keyframes``
  keyframes (1 = the paper's rule as written). Without it, the rule fires right after a submap starts whenever the
  object that filled the anchor view leaves it, and splits that object.
- :class:`MotionAllocation` (LoopSplat's rule): a new submap when the keyframe moved more than ``translation`` metres
  or turned more than ``rotation_deg`` about any Euler axis relative to the submap's first keyframe.

The submap's bounding volume is the UNION of its keyframes' viewing frusta (:class:`FrustumUnion`), each frustum cut
at the keyframe's own depth range (5th-95th percentile of valid depth). A union follows an outward-looking walk far
more tightly than an axis-aligned box around the same frusta, which for a camera turning on the spot soon covers the
whole room and never lets the overlap fall. It grows by one frustum per keyframe; containment tests cost O(keyframes).

The overlap ratio r_olap (``submaps.overlap``) is by default the intersection over union of the current frustum F and
the submap volume V: |F n V| / (|F| + |V| - |F n V|). |F| is exact; |F n V| / |F| is the fraction of a fixed
scrambled-Sobol sample uniform in F's volume that lies in V, |V| the fraction of a Sobol sample of V's bounding box
that does (deterministic: same inputs, same value). The alternative ``view`` is |F n V| / |F| alone, the fraction of
the current view the submap already covers. Measured on ground-truth keyframe poses
(``benchmarks/results/submap_allocation.json``), ``view`` is set by the previous keyframe: V always holds that frustum,
d_map frames back, which alone covers most of F (median 0.72 alone vs 0.73 for the whole V on the 360-frame synthetic
loop), so r_olap < 0.5 needs a jump of about half a field of view between two keyframes: 6 of 71 keyframes of the loop
(whose class KL exceeds 0.4 at 66), 3 submaps over the room. The IoU also falls as V grows beyond the view: below
0.5 once |F u V| > 2 |F n V|, which a walk reaches within a few keyframes (IoU < 0.5 at 51 of the loop's 71
keyframes), so in practice the class KL and the ``min_keyframes`` hysteresis decide: 13 submaps on that loop. The
price, on the faster 180-frame 'default' walk: 9 submaps instead of 4, object cohesion 0.78 instead of 0.93 per visit
(LoopSplat's motion rule: 12 submaps, 0.69; ``benchmarks/submaps.py allocation``).

All poses handed to one :class:`SubmapExtent` must be in the same frame (the submap's, in the SLAM system).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import torch
import torch.nn.functional as F

from gausem_core.config import SubmapConfig
from gausem_core.geometry import PinholeCamera, invert_pose, transform_points
from gausem_core.slam.observation import Observation

OVERLAP_SAMPLES = 4096
HISTOGRAM_EPSILON = 1e-3
DEPTH_PERCENTILES = (5.0, 95.0)


# --- frusta -------------------------------------------------------------------------------------------------------
def depth_range(depth: torch.Tensor, percentiles: tuple[float, float] = DEPTH_PERCENTILES) -> tuple[float, float]:
    """(near, far) of a depth image (H, W) in metres: the given percentiles of its valid (> 0) readings."""
    valid = depth[depth > 0]
    if valid.numel() == 0:
        raise ValueError("depth_range: the depth image has no valid (> 0) reading")
    lo, hi = percentiles
    if not 0 <= lo < hi <= 100:
        raise ValueError(f"depth_range: percentiles must satisfy 0 <= lo < hi <= 100, got {percentiles}")
    levels = torch.tensor([lo / 100, hi / 100], dtype=torch.float64, device=valid.device)
    near, far = torch.quantile(valid.double(), levels).tolist()
    if far <= near:  # a flat depth image (e.g. a wall seen head-on): give the frustum a sliver of thickness
        far = near * 1.01
    return near, far


def _check_range(near: float, far: float) -> None:
    if not 0 < near < far:
        raise ValueError(f"frustum depth range must satisfy 0 < near < far, got near={near}, far={far}")


def _image_bounds(camera: PinholeCamera) -> tuple[float, float, float, float]:
    """x/z and y/z limits of the image (its outer pixel edges, 0..W and 0..H)."""
    return (-camera.cx / camera.fx, (camera.width - camera.cx) / camera.fx,
            -camera.cy / camera.fy, (camera.height - camera.cy) / camera.fy)


def frustum_corners(camera: PinholeCamera, cam_to_world: torch.Tensor, near: float, far: float) -> torch.Tensor:
    """(8, 3) corners of the viewing frustum in the pose's frame: near plane first, then far plane, each in image
    order top-left, top-right, bottom-right, bottom-left."""
    _check_range(near, far)
    x0, x1, y0, y1 = _image_bounds(camera)
    dtype = cam_to_world.dtype
    rays = torch.tensor([[x0, y0, 1.0], [x1, y0, 1.0], [x1, y1, 1.0], [x0, y1, 1.0]], dtype=dtype,
                        device=cam_to_world.device)
    return transform_points(cam_to_world, torch.cat([rays * near, rays * far]))


def frustum_samples(camera: PinholeCamera, cam_to_world: torch.Tensor, near: float, far: float,
                    n: int = OVERLAP_SAMPLES) -> torch.Tensor:
    """(n, 3) fixed quasi-random points uniform in the frustum's volume (scrambled Sobol, seed 0), in the pose's frame.

    Uniform in volume: image-plane coordinates uniform, depth with density proportional to z^2 (inverse CDF).
    """
    _check_range(near, far)
    unit = torch.quasirandom.SobolEngine(3, scramble=True, seed=0).draw(n, dtype=torch.float64).to(cam_to_world.device)
    x0, x1, y0, y1 = _image_bounds(camera)
    z = (near**3 + unit[:, 2] * (far**3 - near**3)) ** (1 / 3)
    points = torch.stack([(x0 + unit[:, 0] * (x1 - x0)) * z, (y0 + unit[:, 1] * (y1 - y0)) * z, z], -1)
    return transform_points(cam_to_world.double(), points).to(cam_to_world.dtype)


@dataclass(frozen=True)
class Frustum:
    """One keyframe's viewing frustum: camera, cam_to_world (4, 4) and depth range [near, far]."""

    camera: PinholeCamera
    cam_to_world: torch.Tensor
    near: float
    far: float

    def __post_init__(self):
        _check_range(self.near, self.far)
        if tuple(self.cam_to_world.shape) != (4, 4):
            raise ValueError(f"Frustum: cam_to_world must be (4, 4), got {tuple(self.cam_to_world.shape)}")

    def contains(self, points: torch.Tensor) -> torch.Tensor:
        """(N,) bool: points (N, 3) inside the frustum (image bounds, near <= z <= far)."""
        local = transform_points(invert_pose(self.cam_to_world.to(points.dtype)), points)
        z = local[:, 2]
        x0, x1, y0, y1 = _image_bounds(self.camera)
        x, y = local[:, 0], local[:, 1]
        return ((z >= self.near) & (z <= self.far) & (x >= x0 * z) & (x <= x1 * z) & (y >= y0 * z) & (y <= y1 * z))


def frustum_volume(camera: PinholeCamera, near: float, far: float) -> float:
    """Volume (m^3) of the frustum between depths ``near`` and ``far``: image-plane area per depth^2 times the
    integral of z^2."""
    _check_range(near, far)
    x0, x1, y0, y1 = _image_bounds(camera)
    return (x1 - x0) * (y1 - y0) * (far**3 - near**3) / 3


@dataclass
class FrustumUnion:
    """A submap's bounding volume: the union of its keyframes' frusta; grows with every keyframe added."""

    frusta: list[Frustum] = field(default_factory=list)
    _volume: float | None = field(default=None, init=False, repr=False, compare=False)  # cache of :meth:`volume`

    def add(self, frustum: Frustum) -> None:
        self.frusta.append(frustum)
        self._volume = None

    def volume(self, samples: int = 4 * OVERLAP_SAMPLES) -> float:
        """|V| (m^3): the bounding box's volume times the fraction of a fixed Sobol sample of the box inside the union
        (0 for an empty union); computed once per set of frusta."""
        if not self.frusta:
            return 0.0
        if self._volume is None:
            low, high = (b.double() for b in self.bounds())
            unit = torch.quasirandom.SobolEngine(3, scramble=True, seed=1).draw(samples, dtype=torch.float64)
            inside = self.contains(low + unit.to(low.device) * (high - low))
            self._volume = float((high - low).prod()) * float(inside.double().mean())
        return self._volume

    def contains(self, points: torch.Tensor) -> torch.Tensor:
        """(N,) bool: points (N, 3) inside at least one frustum (all False for an empty union)."""
        inside = torch.zeros(points.shape[0], dtype=torch.bool, device=points.device)
        for frustum in self.frusta:
            inside |= frustum.contains(points)
        return inside

    def bounds(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Axis-aligned (min (3,), max (3,)) of all frustum corners."""
        if not self.frusta:
            raise ValueError("FrustumUnion.bounds: the volume is empty")
        corners = torch.cat([frustum_corners(f.camera, f.cam_to_world, f.near, f.far) for f in self.frusta])
        return corners.min(0).values, corners.max(0).values


def frustum_overlap(camera: PinholeCamera, cam_to_world: torch.Tensor, depth_range: tuple[float, float],
                    volume: FrustumUnion, samples: int = OVERLAP_SAMPLES) -> float:
    """|F n V| / |F| in [0, 1]: fraction of the frustum's volume inside ``volume`` (deterministic sample)."""
    points = frustum_samples(camera, cam_to_world, *depth_range, n=samples)
    return float(volume.contains(points).double().mean())


def frustum_iou(camera: PinholeCamera, cam_to_world: torch.Tensor, depth_range: tuple[float, float],
                volume: FrustumUnion, samples: int = OVERLAP_SAMPLES) -> float:
    """|F n V| / |F u V| in [0, 1] of the frustum F and ``volume`` V (deterministic samples)."""
    frustum = frustum_volume(camera, *depth_range)
    common = frustum * frustum_overlap(camera, cam_to_world, depth_range, volume, samples)
    return common / max(frustum + volume.volume() - common, common, 1e-12)


OVERLAP_MEASURES = {"iou": frustum_iou, "view": frustum_overlap}


# --- class content ------------------------------------------------------------------------------------------------
def class_histogram(labels: torch.Tensor, num_classes: int, valid: torch.Tensor | None = None,
                    epsilon: float = HISTOGRAM_EPSILON) -> torch.Tensor:
    """h (C,) float64: class proportions of ``labels`` (where ``valid``), smoothed as h_c = (p_c + eps) / (1 + C eps).

    The smoothing keeps every bin positive so that the KL divergence stays finite when a class is absent.
    """
    if num_classes < 1:
        raise ValueError(f"class_histogram: num_classes must be positive, got {num_classes}")
    flat = labels.reshape(-1) if valid is None else labels[valid]
    if flat.numel() == 0:
        raise ValueError("class_histogram: no (valid) label to count")
    if flat.min() < 0 or flat.max() >= num_classes:
        raise ValueError(f"class_histogram: labels must lie in [0, {num_classes - 1}], "
                         f"got [{int(flat.min())}, {int(flat.max())}]")
    return smoothed_histogram(torch.bincount(flat.long(), minlength=num_classes), epsilon)


def smoothed_histogram(counts: torch.Tensor, epsilon: float = HISTOGRAM_EPSILON) -> torch.Tensor:
    """Per-class counts (C,) -> the smoothed proportions of :func:`class_histogram`."""
    counts = counts.double()
    return (counts / counts.sum() + epsilon) / (1 + len(counts) * epsilon)


def class_kl(h_current: torch.Tensor, h_anchor: torch.Tensor) -> float:
    """r_kl = KL(current || anchor) = sum_c h_current[c] * ln(h_current[c] / h_anchor[c]), in nats.

    Both histograms must be strictly positive and sum to 1 (as :func:`class_histogram` makes them).
    """
    if h_current.shape != h_anchor.shape or h_current.ndim != 1:
        raise ValueError(f"class_kl: histograms must be 1-D of one length, got {tuple(h_current.shape)} "
                         f"and {tuple(h_anchor.shape)}")
    for name, h in (("current", h_current), ("anchor", h_anchor)):
        if bool((h <= 0).any()) or abs(float(h.sum()) - 1) > 1e-6:
            raise ValueError(f"class_kl: the {name} histogram must be positive and sum to 1 (smooth it first)")
    p, q = h_current.double(), h_anchor.double()
    return float((p * (p / q).log()).sum())


# --- the submap's summary and the policies -------------------------------------------------------------------------
@dataclass
class SubmapExtent:
    """What allocation needs of the active submap: its first keyframe's pose, its anchor keyframe's class counts and
    its bounding volume (union of keyframe frusta). Update it with :meth:`add` for every keyframe the submap keeps.

    ``num_classes`` is the histogram length; a keyframe that shows a larger class id lengthens both histograms (so a
    system that does not know its class table can pass 1)."""

    first_pose: torch.Tensor
    anchor_counts: torch.Tensor
    volume: FrustumUnion
    num_classes: int

    @classmethod
    def start(cls, obs: Observation, cam_to_world: torch.Tensor, num_classes: int) -> "SubmapExtent":
        """The extent of a submap whose anchor (first) keyframe is ``obs`` at ``cam_to_world``."""
        counts = torch.bincount(obs.labels.reshape(-1).long(), minlength=num_classes).cpu()
        extent = cls(cam_to_world.detach().clone(), counts, FrustumUnion(), num_classes)
        extent.add(obs, cam_to_world)
        return extent

    @property
    def num_keyframes(self) -> int:
        """Keyframes added (with valid depth)."""
        return len(self.volume.frusta)

    def add(self, obs: Observation, cam_to_world: torch.Tensor) -> None:
        """Grow the bounding volume by a keyframe's frustum (none for a keyframe without valid depth)."""
        if bool(obs.valid_depth.any()):
            self.volume.add(Frustum(obs.camera, cam_to_world.detach().clone(), *depth_range(obs.depth)))

    def state_dict(self) -> dict:
        """The extent as plain values and tensors; :meth:`from_state` rebuilds it."""
        return {"first_pose": self.first_pose, "anchor_counts": self.anchor_counts, "num_classes": self.num_classes,
                "frusta": [{"camera": asdict(f.camera), "cam_to_world": f.cam_to_world, "near": f.near,
                            "far": f.far} for f in self.volume.frusta]}

    @classmethod
    def from_state(cls, state: dict, device: torch.device | str) -> "SubmapExtent":
        """The extent of a :meth:`state_dict`, its poses on ``device``."""
        frusta = [Frustum(PinholeCamera(**f["camera"]), f["cam_to_world"].to(device), f["near"], f["far"])
                  for f in state["frusta"]]
        return cls(state["first_pose"].to(device), state["anchor_counts"], FrustumUnion(frusta), state["num_classes"])

    def classes_known(self, labels: torch.Tensor) -> bool:
        """Whether the anchor keyframe or a keyframe's class ids (H, W) hold more than one class (without labels every
        pixel is one class, and the class KL is 0 whatever the view)."""
        return int(self.anchor_counts.count_nonzero()) > 1 or int(labels.unique().numel()) > 1

    def kl_to_anchor(self, labels: torch.Tensor) -> float:
        """r_kl of a keyframe's class ids (H, W) against the anchor keyframe's."""
        classes = max(self.num_classes, len(self.anchor_counts), int(labels.max()) + 1)
        anchor = F.pad(self.anchor_counts.to(labels.device), (0, classes - len(self.anchor_counts)))
        return class_kl(class_histogram(labels, classes), smoothed_histogram(anchor))


@dataclass(frozen=True)
class Decision:
    """Outcome of an allocation test; ``overlap``/``kl`` are NaN for the motion rule, which does not compute them."""

    new: bool
    overlap: float
    kl: float
    reason: str
    rule: str = "custom"  # which rule decided: "semantic", "motion (no classes)", "motion" (custom: a policy of the
    # caller's that names none)


@dataclass(frozen=True)
class SemanticAllocation:
    """The paper's spatial-semantic rule: new submap iff r_olap < max_overlap AND r_kl > min_class_kl, with
    hysteresis: never before the active submap holds ``min_keyframes`` keyframes. ``overlap``: how r_olap is measured,
    "iou" or "view" (module docstring). ``fallback``: where no classes are known (the anchor and the keyframe each
    hold a single class, as data without labels does) the class KL is 0 and could never fire, so this rule (the motion
    rule) decides; None: such a run stays one submap that grows without bound."""

    max_overlap: float = 0.5
    min_class_kl: float = 0.4
    min_keyframes: int = 1
    overlap: str = "iou"
    fallback: "MotionAllocation | None" = None

    def __post_init__(self):
        if self.overlap not in OVERLAP_MEASURES:
            raise ValueError(f"submaps.overlap must be one of {', '.join(OVERLAP_MEASURES)}, got {self.overlap!r}")

    def should_start_new(self, extent: SubmapExtent, obs: Observation, cam_to_world: torch.Tensor) -> Decision:
        if not bool(obs.valid_depth.any()):
            return Decision(False, math.nan, math.nan, "no valid depth: the keyframe has no frustum")
        measure = OVERLAP_MEASURES[self.overlap]
        overlap = measure(obs.camera, cam_to_world, depth_range(obs.depth), extent.volume)
        kl = extent.kl_to_anchor(obs.labels)
        spatial, semantic = overlap < self.max_overlap, kl > self.min_class_kl
        grown = extent.num_keyframes >= self.min_keyframes
        reason = (f"overlap ({self.overlap}) {overlap:.3f} {'<' if spatial else '>='} {self.max_overlap} and "
                  f"class KL {kl:.3f} {'>' if semantic else '<='} {self.min_class_kl}")
        if self.fallback is not None and not extent.classes_known(obs.labels):
            moved = self.fallback.should_start_new(extent, obs, cam_to_world)
            return Decision(moved.new, overlap, kl, f"no classes known, the motion rule decides: {moved.reason}",
                            "motion (no classes)")
        if not grown:
            reason += f"; the submap holds {extent.num_keyframes} < {self.min_keyframes} keyframes"
        return Decision(spatial and semantic and grown, overlap, kl, reason, "semantic")


def euler_xyz_deg(rot: torch.Tensor) -> torch.Tensor:
    """(3,) Euler angles (x, y, z) in degrees with rot = Rz @ Ry @ Rx (LoopSplat's ``rotation_to_euler``)."""
    sy = torch.hypot(rot[0, 0], rot[1, 0])
    if float(sy) < 1e-6:  # gimbal lock: put the whole remaining rotation on x
        angles = [torch.atan2(-rot[1, 2], rot[1, 1]), torch.atan2(-rot[2, 0], sy), torch.zeros_like(sy)]
    else:
        angles = [torch.atan2(rot[2, 1], rot[2, 2]), torch.atan2(-rot[2, 0], sy), torch.atan2(rot[1, 0], rot[0, 0])]
    return torch.stack(angles) * (180 / math.pi)


@dataclass(frozen=True)
class MotionAllocation:
    """LoopSplat's rule: new submap iff the motion relative to the submap's first keyframe exceeds ``translation``
    metres or ``rotation_deg`` degrees about any Euler axis."""

    translation: float = 0.5
    rotation_deg: float = 50.0

    def should_start_new(self, extent: SubmapExtent, obs: Observation, cam_to_world: torch.Tensor) -> Decision:
        delta = invert_pose(extent.first_pose.double()) @ cam_to_world.double()
        moved = float(delta[:3, 3].norm())
        turned = float(euler_xyz_deg(delta[:3, :3]).abs().max())
        new = moved > self.translation or turned > self.rotation_deg
        reason = (f"moved {moved:.3f} m (limit {self.translation}), turned {turned:.1f} deg "
                  f"(limit {self.rotation_deg})")
        return Decision(new, math.nan, math.nan, reason, "motion")


Allocation = SemanticAllocation | MotionAllocation


def make_allocation(cfg: SubmapConfig) -> Allocation:
    """The policy named by ``cfg.policy`` ("semantic" or "motion") with its thresholds."""
    if cfg.policy == "semantic":
        fallback = MotionAllocation(cfg.motion_translation, cfg.motion_rotation_deg)
        return SemanticAllocation(cfg.max_overlap, cfg.min_class_kl, cfg.min_keyframes, cfg.overlap,
                                  fallback if cfg.fallback_without_classes else None)
    if cfg.policy == "motion":
        return MotionAllocation(cfg.motion_translation, cfg.motion_rotation_deg)
    raise ValueError(f"submaps.policy must be 'semantic' or 'motion', got {cfg.policy!r}")


def partition_keyframes(policy: Allocation, keyframes: list[tuple[Observation, torch.Tensor]],
                        num_classes: int) -> tuple[list[int], list[Decision]]:
    """Run ``policy`` over keyframes (obs, cam_to_world, one common frame) as the SLAM system does.

    Returns the submap index of every keyframe and the decision taken at each keyframe after the first.
    """
    if not keyframes:
        raise ValueError("partition_keyframes: no keyframe")
    obs, pose = keyframes[0]
    extent = SubmapExtent.start(obs, pose, num_classes)
    submap_ids, decisions = [0], []
    for obs, pose in keyframes[1:]:
        decision = policy.should_start_new(extent, obs, pose)
        decisions.append(decision)
        if decision.new:
            extent = SubmapExtent.start(obs, pose, num_classes)
        else:
            extent.add(obs, pose)
        submap_ids.append(submap_ids[-1] + decision.new)
    return submap_ids, decisions
