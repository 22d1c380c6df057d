"""The camera's vignetting, estimated online from pairs of keyframes and divided out of each frame's colour (#25).

A lens and sensor darken the image towards its corners; the model here is V(r) = exp(a r^2), r the distance from the
principal point over the half diagonal (a < 0: darker corners; the synthetic sensor model's 75 % corners are about
a = -0.28). A map fitted to vignetted frames learns a blend of the gains under which its keyframes saw each surface, so
surfaces brighten and darken as they cross the image and the colour terms of tracking and mapping pull against the
motion (the synthetic loop through the sensor model: 1.56 cm ATE, 1.13 without its vignetting; docs/BENCHMARKS.md).

Each frame's colour is divided by V before the system uses it, without clipping: a bright surface seen in a darkened
corner stays brighter than 1 (the map's colours go up to ``MAX_COLOR``; clipping at 1 cut a fifth of TUM fr1/rpy's
pixels at a = -0.33 and cost 1 dB of PSNR).

The estimate comes from the images alone, as in online photometric calibration (Bergmann et al., 2017): a surface
point two keyframes both see, at radii r1 and r2, was recorded with brightness ratio I2 / I1 = e V(r2) / V(r1), e the
change of exposure between them, so log(I2 / I1) = log e + a (r2^2 - r1^2). Each new keyframe is paired with the one
before it in the same submap (its depth and the two tracked poses give the correspondences); the slope of that line
over the pair's points, averaged in blocks, is one measurement of ``a`` weighted by the spread of r2^2 - r1^2 (a
rotation that carries points from the centre to a corner tells much, a pure forward motion little), and ``a`` is the
weighted median of all measurements so far, with ``initial`` as a prior of weight one: no feedback through the map,
which is built from the corrected frames, and one blurred or mis-tracked pair moves it little.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F

from gausem_core.config import VignettingConfig
from gausem_core.geometry import PinholeCamera
from gausem_core.slam.observation import MAX_COLOR, Observation

_EXPOSED = (0.02, 0.98)  # points count where both keyframes recorded them neither black (mean) nor saturated (any
# channel) ...
_SAME_SURFACE = (0.03, 0.01)  # ... and the later keyframe's depth there agrees with the point's (relative, metres)
_BLOCK = 0.05  # the log ratio is taken of block means, blocks this fraction of the image width on a side
_PRIOR_WEIGHT = 1.0  # ``initial`` weighs as much as a pair whose blocks' r^2 changes spread this much (TUM fr1/rpy's
# keyframe pairs, 5 frames apart: 0.02 to 7.4, median 3.4)


def radius_squared(camera: PinholeCamera, device: torch.device | str = "cpu") -> torch.Tensor:
    """(H, W) squared distance of each pixel centre from the principal point, over the squared half diagonal."""
    v = torch.arange(camera.height, dtype=torch.float32, device=device)[:, None] + 0.5
    u = torch.arange(camera.width, dtype=torch.float32, device=device)[None, :] + 0.5
    return camera.radius_squared(u, v)


@dataclass(frozen=True)
class PairSlope:
    """One keyframe pair's measurement: the slope of log(I2 / I1) over r2^2 - r1^2, and its weight (the spread of
    r2^2 - r1^2 about its mean, summed over the blocks)."""

    slope: float
    weight: float


def pair_slope(earlier: torch.Tensor, earlier_depth: torch.Tensor, later: torch.Tensor, later_depth: torch.Tensor,
               later_from_earlier: torch.Tensor, camera: PinholeCamera, min_pixels: int) -> PairSlope | None:
    """The slope of log(later / earlier luminance) over the change of r^2 of the surface points both see: (H, W, 3)
    colours as the camera recorded them, (H, W) depths (0: none), the 4x4 pose of the earlier camera in the later
    one's frame. Points are the earlier keyframe's pixels with depth that land inside the later image on the same
    surface, both well exposed; the line is fitted to blocks of ``_BLOCK`` of the width (means of such points, blocks at
    least half such points), not to pixels: a pixel's log ratio is biased low where the two views are misaligned or
    one is blurred (Jensen). None with fewer than ``min_pixels`` points in such blocks or without spread."""
    h, w = earlier_depth.shape
    points = camera.backproject(earlier_depth) @ later_from_earlier[:3, :3].T + later_from_earlier[:3, 3]
    z = points[..., 2]
    uv = camera.project(torch.where((z > 1e-3)[..., None], points, torch.ones_like(points)))
    grid = torch.stack([2 * uv[..., 0] / w - 1, 2 * uv[..., 1] / h - 1], -1)[None]
    later_color = F.grid_sample(later.permute(2, 0, 1)[None], grid, mode="bilinear",
                                align_corners=False)[0].permute(1, 2, 0)
    nearest_depth = F.grid_sample(later_depth[None, None], grid, mode="nearest", align_corners=False)[0, 0]
    centres = torch.tensor([1 - 1 / w, 1 - 1 / h], device=grid.device)  # between the outermost pixel centres
    inside = (earlier_depth > 0) & (z > 1e-3) & (grid[0].abs() <= centres).all(-1)
    same = (nearest_depth - z).abs() < _SAME_SURFACE[0] * z + _SAME_SURFACE[1]

    def exposed(color):
        return (color.mean(-1) > _EXPOSED[0]) & (color.amax(-1) < _EXPOSED[1])

    usable = (inside & same & exposed(earlier) & exposed(later_color)).double()
    r2_later = camera.radius_squared(uv[..., 0], uv[..., 1])
    planes = torch.stack([usable, earlier.mean(-1), later_color.mean(-1), radius_squared(camera, earlier.device),
                          r2_later]).double()
    planes[1:] *= usable
    block = max(1, round(_BLOCK * w))
    sums = F.avg_pool2d(planes[:, None], block).reshape(5, -1)
    kept = sums[0] >= 0.5
    weight = sums[0][kept]
    if float(weight.sum()) * block * block < max(min_pixels, 2) or int(kept.sum()) < 2:
        return None
    first, second, r2_first, r2_second = (sums[i][kept] / weight for i in (1, 2, 3, 4))
    x, y = r2_second - r2_first, torch.log(second / first)
    x, y = (t - (weight * t).sum() / weight.sum() for t in (x, y))
    spread = float((weight * x * x).sum())
    if spread <= 1e-9:
        return None
    return PairSlope(float((weight * x * y).sum()) / spread, spread)


def weighted_median(values: list[float], weights: list[float]) -> float:
    """The value at which the cumulative weight (values in order) first reaches half the total."""
    order = sorted(range(len(values)), key=values.__getitem__)
    half, total = 0.5 * sum(weights), 0.0
    for i in order:
        total += weights[i]
        if total >= half:
            return values[i]
    raise ValueError("weighted_median of nothing")


class Vignetting:
    """The running estimate ``a`` of V(r) = exp(a r^2) (``cfg.initial`` at start) and its use on frames and renders."""

    def __init__(self, cfg: VignettingConfig):
        if not 0 <= cfg.min_coverage <= 1:
            raise ValueError(f"vignetting.min_coverage must lie in [0, 1], got {cfg.min_coverage}")
        self.cfg = cfg
        self.a = float(cfg.initial)
        self.pairs: list[PairSlope] = []
        self._previous: tuple[object, torch.Tensor, torch.Tensor, torch.Tensor] | None = None  # (frame of
        # reference, recorded colour, depth, cam_to_world) of the last keyframe
        self._r2: dict[tuple, torch.Tensor] = {}

    def _radius_squared(self, camera: PinholeCamera, device: torch.device | str) -> torch.Tensor:
        key = (camera.cx, camera.cy, camera.width, camera.height, str(device))
        if key not in self._r2:
            self._r2[key] = radius_squared(camera, device)
        return self._r2[key]

    def gain(self, camera: PinholeCamera, device: torch.device | str, a: float | None = None) -> torch.Tensor:
        """(H, W, 1) relative brightness V(r) the camera records (under ``a``, default the estimate)."""
        return torch.exp((self.a if a is None else a) * self._radius_squared(camera, device))[..., None]

    def correct(self, obs: Observation, corrected_with: float = 0.0) -> Observation:
        """``obs`` with its colour divided by V, not clipped (a bright surface in a darkened corner exceeds 1, up to
        ``MAX_COLOR``); ``corrected_with``: the a its colour was divided by already (0: as recorded). ``obs`` itself
        when that is the estimate."""
        if self.a == corrected_with:
            return obs
        return replace(obs, rgb=obs.rgb * self.gain(obs.camera, obs.rgb.device, corrected_with - self.a))

    def apply(self, color: torch.Tensor, camera: PinholeCamera) -> torch.Tensor:
        """A rendered (H, W, 3) colour as the camera would record it: times V."""
        return color if self.a == 0.0 else color * self.gain(camera, color.device)

    def update(self, corrected: Observation, cam_to_world: torch.Tensor,
               frame_of_reference: object) -> PairSlope | None:
        """Pair a keyframe (``corrected`` by the current estimate; ``cam_to_world`` in ``frame_of_reference``, e.g. its
        submap) with the last one in the same frame of reference, and re-estimate a from all pairs so far; returns
        the pair's measurement (None: no pair, or too few points both see). Nothing while ``calibrate`` is off."""
        if not self.cfg.calibrate:
            return None
        recorded = self.apply(corrected.rgb, corrected.camera)
        previous, self._previous = self._previous, (frame_of_reference, recorded, corrected.depth, cam_to_world)
        if previous is None or previous[0] != frame_of_reference:
            return None
        earlier, earlier_depth, earlier_pose = (t.to(recorded.device) for t in previous[1:])  # a loaded one: on the CPU
        later_from_earlier = torch.linalg.solve(cam_to_world.double(), earlier_pose.double()).to(recorded.dtype)
        pixels = corrected.depth.numel()
        pair = pair_slope(earlier, earlier_depth, recorded, corrected.depth, later_from_earlier, corrected.camera,
                          math.ceil(self.cfg.min_coverage * pixels))
        if pair is not None:
            self.pairs.append(pair)
            self.a = max(weighted_median([self.cfg.initial] + [p.slope for p in self.pairs],
                                         [_PRIOR_WEIGHT] + [p.weight for p in self.pairs]), -math.log(MAX_COLOR))
        return pair

    def state_dict(self) -> dict:
        """The estimate, the pairs' measurements and the last keyframe (tensors) that the next one pairs with."""
        previous = None if self._previous is None else dict(zip(("reference", "recorded", "depth", "pose"),
                                                                self._previous))
        return {"a": self.a, "pairs": [(p.slope, p.weight) for p in self.pairs], "previous": previous}

    def load_state_dict(self, state: dict | float) -> None:
        """A saved :meth:`state_dict` (a bare float: a session from before pairs were kept; it becomes the estimate)."""
        state = {"a": state, "pairs": []} if isinstance(state, float) else state
        self.a = float(state["a"])
        self.pairs = [PairSlope(s, w) for s, w in state["pairs"]]
        previous = state.get("previous")
        self._previous = None if previous is None else tuple(previous[k] for k in ("reference", "recorded", "depth",
                                                                                     "pose"))
