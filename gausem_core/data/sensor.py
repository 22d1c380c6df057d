"""A Kinect-v1-like RGB-D sensor model applied to clean renders (the synthetic generator's noisy variants).

Depth: range limits with dropout, holes at grazing incidence, at depth discontinuities and in the projector's
shadow, axial noise growing with range and incidence, disparity quantisation. Colour, from linear RGB in [0, 1]:
motion blur (the caller averages renders at :meth:`SensorModel.exposure_offsets`), vignetting, auto-exposure and
auto-white-balance with lag (a state over frames, :class:`AutoExposure`), shot and read noise, 8-bit quantisation.
Each effect has its flag in :class:`~gausem_core.config.SensorConfig`. Random draws come from one stream per
(seed, frame, effect), so switching one effect off leaves what every other effect does unchanged.
"""
from __future__ import annotations

import zlib
from typing import Callable

import cv2
import numpy as np

from gausem_core.config import SensorConfig
from gausem_core.geometry import PinholeCamera

DEPTH_EFFECTS = ("range_dropout", "grazing_holes", "edge_holes", "projector_shadows", "axial_noise",
                 "disparity_quantisation")  # the SensorConfig flags, in the order the depth model applies them
COLOR_EFFECTS = ("motion_blur", "vignetting", "auto_exposure", "white_balance", "shot_noise")
LUMA = np.array([0.2126, 0.7152, 0.0722])  # Rec. 709 luminance weights


def validate(cfg: SensorConfig) -> SensorConfig:
    """``cfg`` when its values are physically meaningful, else a ValueError naming the first bad one."""
    checks = [
        (0 < cfg.min_range < cfg.dropout_start <= cfg.max_range, "need 0 < min_range < dropout_start <= max_range"),
        (0 < cfg.max_incidence_deg < 90, "max_incidence_deg must lie in (0, 90)"),
        (cfg.edge_band >= 0 and cfg.depth_jump > 0, "edge_band must be >= 0 and depth_jump > 0"),
        (cfg.baseline != 0, "baseline must be non-zero"),
        (min(cfg.axial_noise_a, cfg.axial_noise_b, cfg.axial_noise_c) >= 0, "axial noise terms must be >= 0"),
        (cfg.ir_focal > 0 and cfg.ir_width > 0 and cfg.disparity_step > 0,
         "ir_focal, ir_width and disparity_step must be > 0"),
        (cfg.exposure_time >= 0 and cfg.blur_samples >= 1, "exposure_time must be >= 0 and blur_samples >= 1"),
        (0 < cfg.vignetting_corner <= 1, "vignetting_corner must lie in (0, 1]"),
        (cfg.exposure_target > 0 and 0 < cfg.min_gain <= cfg.max_gain,
         "need exposure_target > 0 and 0 < min_gain <= max_gain"),
        (0 < cfg.exposure_rate <= 1 and 0 < cfg.white_balance_rate <= 1, "rates must lie in (0, 1]"),
        (cfg.white_balance_strength >= 0, "white_balance_strength must be >= 0"),
        (cfg.full_well > 0 and cfg.read_noise >= 0, "need full_well > 0 and read_noise >= 0"),
    ]
    for ok, message in checks:
        if not ok:
            raise ValueError(f"sensor config: {message}")
    return cfg


def incidence_angle(depth: np.ndarray, camera: PinholeCamera, depth_jump: float) -> np.ndarray:
    """Angle (rad) between each pixel's ray and its surface normal, from the depth map's back-projected points.

    Per axis the one-sided difference towards the nearer-depth neighbour is used, so normals next to a
    discontinuity (relative jump above ``depth_jump``) belong to the pixel's own surface; pi/2 where undefined.
    """
    rays = camera.pixel_rays().numpy().astype(np.float64)
    points = rays * depth[..., None]
    tangents = []
    for axis in (1, 0):
        ahead = np.roll(points, -1, axis) - points
        behind = points - np.roll(points, 1, axis)
        dz_ahead, dz_behind = np.abs(ahead[..., 2]), np.abs(behind[..., 2])
        last = [slice(None)] * 2
        last[axis] = -1
        dz_ahead[tuple(last)] = np.inf  # no neighbour beyond the border
        last[axis] = 0
        dz_behind[tuple(last)] = np.inf
        tangent = np.where((dz_ahead <= dz_behind)[..., None], ahead, behind)
        smooth = np.minimum(dz_ahead, dz_behind) <= depth_jump * depth
        tangents.append(np.where(smooth[..., None], tangent, np.nan))
    normal = np.cross(tangents[0], tangents[1])
    with np.errstate(invalid="ignore", divide="ignore"):  # NaN tangents and degenerate normals become pi/2
        cosine = np.abs((normal * rays).sum(-1)) / (np.linalg.norm(normal, axis=-1) * np.linalg.norm(rays, axis=-1))
    angle = np.arccos(np.clip(cosine, 0, 1))
    return np.where(np.isfinite(angle) & (depth > 0), angle, np.pi / 2)


def discontinuities(depth: np.ndarray, depth_jump: float) -> tuple[np.ndarray, np.ndarray]:
    """Boolean (H, W - 1) and (H - 1, W): neighbours along x and y whose depths differ by more than ``depth_jump``
    of the nearer one, or of which one has no reading."""
    def jump(a, b):
        return (np.abs(a - b) > depth_jump * np.minimum(a, b)) | (a <= 0) | (b <= 0)

    return jump(depth[:, :-1], depth[:, 1:]), jump(depth[:-1], depth[1:])


def projector_shadow(depth: np.ndarray, camera: PinholeCamera, baseline: float, depth_jump: float) -> np.ndarray:
    """Pixels whose surface the projector, ``baseline`` metres along the camera's +x, cannot light.

    On each row (an epipolar line) every pair of neighbouring pixels on one surface lights the interval of projector
    columns between theirs (column u - f b / z); a pixel is in shadow when a pair on the projector's side of it
    covers its own projector column (that surface lies between it and the projector).
    """
    height, width = depth.shape
    valid = depth > 0
    column = np.arange(width) + 0.5 - camera.fx * baseline / np.where(valid, depth, np.inf)
    same_surface = ~discontinuities(depth, depth_jump)[0]
    low, high = np.minimum(column[:, :-1], column[:, 1:]), np.maximum(column[:, :-1], column[:, 1:])
    pixels = np.arange(width)
    shadow = np.zeros_like(valid)
    step = 1 if baseline > 0 else -1
    for k in range(width - 1):  # the pair (k, k + 1)
        behind = pixels < k if step > 0 else pixels > k + 1  # on the far side from the projector
        covered = (column >= low[:, k:k + 1]) & (column <= high[:, k:k + 1])
        shadow |= covered & behind & same_surface[:, k:k + 1]
    return shadow & valid


def axial_sigma(depth: np.ndarray, angle: np.ndarray, cfg: SensorConfig) -> np.ndarray:
    """Standard deviation (metres) of a depth reading at ``depth`` and incidence ``angle`` (Nguyen et al. 2012)."""
    theta = np.minimum(angle, np.radians(cfg.max_incidence_deg))
    z = np.maximum(depth, 1e-6)
    return (cfg.axial_noise_a + cfg.axial_noise_b * (z - cfg.axial_noise_z0) ** 2
            + cfg.axial_noise_c * theta**2 / (np.sqrt(z) * (np.pi / 2 - theta) ** 2))


def quantise_disparity(depth: np.ndarray, cfg: SensorConfig) -> np.ndarray:
    """Depth after rounding the disparity f b / z (in IR pixels) to the sensor's step; 0 stays 0."""
    fb = cfg.ir_focal * abs(cfg.baseline)
    valid = depth > 0
    steps = np.maximum(np.round(fb / np.where(valid, depth, 1.0) / cfg.disparity_step), 1)
    return np.where(valid, fb / (steps * cfg.disparity_step), 0.0).astype(np.float32)


def vignetting(camera: PinholeCamera, corner: float) -> np.ndarray:
    """(H, W) relative brightness 1 - (1 - corner) r^2, r = distance from the principal point / half diagonal."""
    v, u = np.mgrid[0:camera.height, 0:camera.width] + 0.5
    return 1.0 - (1.0 - corner) * camera.radius_squared(u, v)


class SensorModel:
    """The depth and colour effects of a :class:`SensorConfig` for one generator ``seed``."""

    def __init__(self, cfg: SensorConfig, seed: int = 0):
        self.cfg = validate(cfg)
        self.seed = int(seed)

    def _rng(self, index: int, effect: str) -> np.random.Generator:
        return np.random.default_rng([self.seed, int(index), zlib.crc32(effect.encode())])

    def exposure_offsets(self) -> np.ndarray:
        """Seconds from the frame's time (mid-exposure) of the sub-frame renders that make up one image."""
        cfg = self.cfg
        if not cfg.motion_blur or cfg.blur_samples == 1:
            return np.zeros(1)
        return cfg.exposure_time * (np.arange(cfg.blur_samples) / (cfg.blur_samples - 1) - 0.5)

    def depth(self, depth: np.ndarray, camera: PinholeCamera, index: int) -> np.ndarray:
        """The sensor's reading (H, W) float32 metres, 0 = none, of the clean ``depth`` of frame ``index``."""
        cfg, clean = self.cfg, depth.astype(np.float64)
        holes = clean <= 0
        if cfg.range_dropout:
            chance = np.clip((clean - cfg.dropout_start) / (cfg.max_range - cfg.dropout_start), 0, 1)
            holes |= (clean < cfg.min_range) | (clean > cfg.max_range)
            holes |= self._rng(index, "range").random(clean.shape) < chance
        angle = incidence_angle(clean, camera, cfg.depth_jump)
        if cfg.grazing_holes:
            holes |= angle > np.radians(cfg.max_incidence_deg)
        if cfg.edge_holes:
            holes |= self._edge_holes(clean, camera, index)
        if cfg.projector_shadows:
            holes |= projector_shadow(clean, camera, cfg.baseline, cfg.depth_jump)
        out = clean
        if cfg.axial_noise:
            out = out + axial_sigma(clean, angle, cfg) * self._rng(index, "axial").standard_normal(clean.shape)
        if cfg.disparity_quantisation:
            out = quantise_disparity(np.maximum(out, 0), cfg)
        return np.where(holes, 0.0, np.maximum(out, 0)).astype(np.float32)

    def _edge_holes(self, depth: np.ndarray, camera: PinholeCamera, index: int) -> np.ndarray:
        """Pixels within a ragged band (mean half-width ``edge_band`` IR pixels, scaled to the render) of a depth
        discontinuity."""
        along_x, along_y = discontinuities(depth, self.cfg.depth_jump)
        edge = np.zeros(depth.shape, bool)
        edge[:, :-1] |= along_x
        edge[:, 1:] |= along_x
        edge[:-1] |= along_y
        edge[1:] |= along_y
        if not edge.any():
            return edge
        distance = cv2.distanceTransform((~edge).astype(np.uint8), cv2.DIST_L2, 3)
        band = self.cfg.edge_band * camera.width / self.cfg.ir_width
        return distance < band - 1 + self._rng(index, "edges").random(depth.shape)

    def color(self, linear: np.ndarray, camera: PinholeCamera, index: int, gain: float,
              white_balance: np.ndarray) -> np.ndarray:
        """The 8-bit image (H, W, 3) of ``linear`` RGB in [0, 1] (motion blur already averaged in), with exposure
        ``gain`` and per-channel ``white_balance`` gains (from :class:`AutoExposure`)."""
        cfg = self.cfg
        value = linear.astype(np.float64)
        if cfg.vignetting:
            value = value * vignetting(camera, cfg.vignetting_corner)[..., None]
        value = value * gain
        if cfg.shot_noise:  # photo-electrons value / gain * full_well are Poisson; read noise after the gain
            rng = self._rng(index, "shot")
            electrons = rng.poisson(np.maximum(value, 0) / gain * cfg.full_well)
            value = electrons * gain / cfg.full_well + cfg.read_noise / 255 * rng.standard_normal(value.shape)
        value = value * white_balance
        return np.clip(value * 255 + 0.5, 0, 255).astype(np.uint8)

    def meter(self, linear: np.ndarray, camera: PinholeCamera) -> np.ndarray:
        """Mean RGB (3,) of a (small) clean render as the camera's own metering sees it (after vignetting)."""
        if self.cfg.vignetting:
            linear = linear * vignetting(camera, self.cfg.vignetting_corner)[..., None]
        return linear.reshape(-1, 3).mean(0)


class AutoExposure:
    """Exposure gain and white-balance gains per frame, each reacting with lag to the metered previous frame.

    ``meter(i)`` gives the mean RGB (3,) of frame ``i`` before any gain. Frame 0 starts converged; from then on the
    log gain moves ``exposure_rate`` of the way to ``exposure_target / luminance`` of the previous frame, and the
    white balance ``white_balance_rate`` of the way to ``white_balance_strength`` of the grey-world correction
    (green fixed). Gains are computed in frame order once and kept, so any frame can be asked for in any order.
    """

    def __init__(self, cfg: SensorConfig, meter: Callable[[int], np.ndarray]):
        self.cfg = cfg
        self.meter = meter
        self._log_gains: list[np.ndarray] = []  # per frame: log exposure gain, log white balance (3,)

    def _target(self, index: int) -> np.ndarray:
        mean = np.maximum(np.asarray(self.meter(index), np.float64), 1e-6)
        exposure = np.log(self.cfg.exposure_target / float(mean @ LUMA))
        return np.concatenate([[exposure], self.cfg.white_balance_strength * np.log(mean[1] / mean)])

    def gains(self, index: int) -> tuple[float, np.ndarray]:
        """(exposure gain, white-balance gains (3,)) of frame ``index``; 1 where the effect is off."""
        cfg = self.cfg
        if not (cfg.auto_exposure or cfg.white_balance):
            return 1.0, np.ones(3)
        if index < 0:
            raise ValueError(f"frame index must be >= 0, got {index}")
        rates = np.array([cfg.exposure_rate] + [cfg.white_balance_rate] * 3)
        while len(self._log_gains) <= index:
            i = len(self._log_gains)
            target = self._target(max(i - 1, 0))
            state = target if i == 0 else self._log_gains[-1] + rates * (target - self._log_gains[-1])
            state[0] = np.clip(state[0], np.log(cfg.min_gain), np.log(cfg.max_gain))
            self._log_gains.append(state)
        state = self._log_gains[index]
        gain = float(np.exp(state[0])) if cfg.auto_exposure else 1.0
        return gain, np.exp(state[1:]) if cfg.white_balance else np.ones(3)
