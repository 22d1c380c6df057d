"""The camera's vignetting, estimated online and divided out of each frame's colour (issue #25).

A lens and sensor darken the image towards its corners; the model here is V(r) = exp(a r^2), r the distance from the
principal point over the half diagonal (a < 0: darker corners; the synthetic sensor model's 75 % corners are about
a = -0.28). A map fitted to vignetted frames learns a blend of the gains under which its keyframes saw each surface, so
surfaces brighten and darken as they cross the image and the colour terms of tracking and mapping pull against the
motion (the synthetic loop through the sensor model: 1.56 cm ATE, 1.13 without its vignetting; docs/BENCHMARKS.md).

Each frame's colour is divided by V before the system uses it, without clipping: a bright surface seen in a darkened
corner stays brighter than 1 (the map's colours go up to ``MAX_COLOR``; clipping at 1 cut a fifth of TUM fr1/rpy's
pixels at a = -0.33 and cost 1 dB of PSNR). After each keyframe is mapped, the active submap is rendered at the
keyframe's pose and the slope of log(recorded / rendered luminance) over r^2 is fitted on the pixels the map covers and
the camera did not saturate, averaged in blocks (a line: its offset absorbs the frame's exposure); that slope less the
current ``a`` is what the estimate leaves uncorrected, and ``a`` moves by a damped, clipped share of it. The map is
built from the corrected frames, so the estimate converges over keyframes rather than in one step, and a single blurred
or mis-tracked keyframe moves it little.
"""
from __future__ import annotations

import math
from dataclasses import replace

import torch
import torch.nn.functional as F

from gausem_core.config import VignettingConfig
from gausem_core.geometry import PinholeCamera
from gausem_core.slam.observation import MAX_COLOR, Observation

_MIN_ALPHA = 0.99  # pixels the map covers this fully are compared ...
_MIN_RENDERED = 0.05  # ... where it renders at least this bright (log of a ratio) ...
_OBSERVED_RANGE = (0.02, 0.98)  # ... and the frame is neither black (mean) nor saturated (any channel) there
_BLOCK = 0.05  # the log ratio is taken of block means, blocks this fraction of the image width on a side


def radius_squared(camera: PinholeCamera, device: torch.device | str = "cpu") -> torch.Tensor:
    """(H, W) squared distance of each pixel centre from the principal point, over the squared half diagonal."""
    v = torch.arange(camera.height, dtype=torch.float32, device=device)[:, None] + 0.5
    u = torch.arange(camera.width, dtype=torch.float32, device=device)[None, :] + 0.5
    return ((u - camera.cx) ** 2 + (v - camera.cy) ** 2) / ((camera.width / 2) ** 2 + (camera.height / 2) ** 2)


def radial_slope(observed: torch.Tensor, rendered: torch.Tensor, alpha: torch.Tensor, r2: torch.Tensor,
                 min_pixels: int) -> float | None:
    """Weighted least-squares slope over r^2 (``r2``) of log(observed / rendered luminance), (H, W, 3) colours
    (``observed`` as the camera recorded it, in [0, 1]), on blocks of ``_BLOCK`` of the width: the means of the pixels
    the render covers (``alpha``) where both are well exposed, blocks at least half such pixels. Block means, not
    pixels: a pixel's log ratio is biased low where the render is misaligned or blurred against the frame (Jensen), and
    that grows towards the image border (lens distortion, motion blur of a rotation). None with fewer than
    ``min_pixels`` pixels in such blocks or without spread in r^2."""
    seen, model = observed.mean(-1), rendered.mean(-1)
    usable = ((alpha > _MIN_ALPHA) & (model > _MIN_RENDERED) & (seen > _OBSERVED_RANGE[0])
              & (observed.amax(-1) < _OBSERVED_RANGE[1])).double()
    block = max(1, round(_BLOCK * observed.shape[1]))
    sums = F.avg_pool2d(torch.stack([usable, usable * seen, usable * model, usable * r2]).double()[:, None],
                        block).reshape(4, -1)
    kept = sums[0] >= 0.5
    weight = sums[0][kept]
    if float(weight.sum()) * block * block < max(min_pixels, 2) or int(kept.sum()) < 2:
        return None
    seen_b, model_b, x = (sums[i][kept] / weight for i in (1, 2, 3))
    y = torch.log(seen_b / model_b)
    x = x - (weight * x).sum() / weight.sum()
    spread = float((weight * x * x).sum())
    if spread <= 1e-12:
        return None
    return float((weight * x * (y - (weight * y).sum() / weight.sum())).sum()) / spread


class Vignetting:
    """The running estimate ``a`` of V(r) = exp(a r^2) (``cfg.initial`` at start) and its use on frames and renders."""

    def __init__(self, cfg: VignettingConfig):
        if cfg.rate < 0 or cfg.max_slope < 0 or not 0 <= cfg.min_coverage <= 1:
            raise ValueError("vignetting.rate and vignetting.max_slope must be >= 0 and vignetting.min_coverage in "
                             f"[0, 1], got {cfg.rate}, {cfg.max_slope} and {cfg.min_coverage}")
        self.cfg = cfg
        self.a = float(cfg.initial)
        self._r2: dict[tuple, torch.Tensor] = {}

    def _radius_squared(self, camera: PinholeCamera, device: torch.device | str) -> torch.Tensor:
        key = (camera.cx, camera.cy, camera.width, camera.height, str(device))
        if key not in self._r2:
            self._r2[key] = radius_squared(camera, device)
        return self._r2[key]

    def gain(self, camera: PinholeCamera, device: torch.device | str) -> torch.Tensor:
        """(H, W, 1) relative brightness V(r) the camera records."""
        return torch.exp(self.a * self._radius_squared(camera, device))[..., None]

    def correct(self, obs: Observation) -> Observation:
        """``obs`` with its colour divided by V, not clipped (a bright surface in a darkened corner exceeds 1, up to
        ``MAX_COLOR``); ``obs`` itself while a is 0."""
        if self.a == 0.0:
            return obs
        return replace(obs, rgb=obs.rgb / self.gain(obs.camera, obs.rgb.device))

    def apply(self, color: torch.Tensor, camera: PinholeCamera) -> torch.Tensor:
        """A rendered (H, W, 3) colour as the camera would record it: times V."""
        return color if self.a == 0.0 else color * self.gain(camera, color.device)

    def update(self, corrected: Observation, rendered: torch.Tensor, alpha: torch.Tensor) -> float | None:
        """Move a by ``rate`` times the slope the corrected keyframe ``corrected`` still shows against the map's
        render of it (``rendered`` colour, ``alpha`` silhouette), the slope clipped to +-``max_slope`` and a kept
        >= -log(MAX_COLOR); returns the slope (None: too few usable pixels, a unchanged). Nothing while
        ``calibrate`` is off."""
        if not self.cfg.calibrate:
            return None
        r2 = self._radius_squared(corrected.camera, rendered.device)
        recorded = self.apply(corrected.rgb, corrected.camera)  # the frame as the camera gave it: its range tells
        # saturated pixels, whose ratio to the map is meaningless, from bright ones
        slope = radial_slope(recorded, rendered, alpha, r2, math.ceil(self.cfg.min_coverage * r2.numel()))
        if slope is None:
            return None
        slope -= self.a  # what the recorded frame shows beyond the current estimate
        step = self.cfg.rate * max(-self.cfg.max_slope, min(self.cfg.max_slope, slope))
        self.a = max(self.a + step, -math.log(MAX_COLOR))
        return slope
