"""Tracking health: whether a frame's tracked pose can be trusted, as ok / degraded / lost.

Signals of a tracked frame (:class:`TrackingHealth`):

- ``inlier_fraction``: among the pixels where the map renders a silhouette, the share it explains: observed depth
  within ``inlier_depth`` of the rendered depth, or, where the depth is invalid, colour within ``inlier_color`` (NaN
  when the map renders no silhouette: then no rule on it fires, and ``coverage`` decides);
- ``residual_z``: robust z-score of the tracking residual against the median/MAD of the recent frames' (the raw loss
  drifts over a run, its jumps do not);
- ``condition``: log10 of the condition number of the Gauss-Newton Hessian at the pose, translation scaled by the
  median depth so that metres and radians compare (large: the pose is weakly constrained in some direction);
- ``jump``: how far the pose departs from the constant-velocity prediction, in typical per-frame motions (the median
  of the recent ones, floored by ``min_translation`` / ``min_rotation``), the larger of translation and rotation;
- ``valid_depth``: the fraction of pixels with a valid depth;
- ``coverage``: the fraction of the image that tracking aligns against at the pose: the map's silhouette and, where
  ``tracking.keyframe_fill`` applies, the newest keyframe's own pixels (little of it leaves the pose weakly
  constrained, as few tracked map points do in feature-based SLAM, and calls for a keyframe; almost none: the camera
  looks where the map is not, e.g. it jumped, and the pose is only the start it was tracked from).

Rules (:class:`HealthMonitor`, thresholds in ``HealthConfig``): lost when the inlier fraction, the valid depth, the
coverage or the jump passes its ``lost_`` threshold; else degraded when any signal passes its ``degraded_`` threshold; else ok.
The residual and motion histories learn from frames that are not lost only; a session saves them
(:meth:`HealthMonitor.state_dict`).
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import asdict, dataclass

import torch

from gausem_core.config import HealthConfig
from gausem_core.geometry import invert_pose, so3_log

STATUSES = ("ok", "degraded", "lost")
SIGNALS = ("inlier_fraction", "residual_z", "condition", "jump", "valid_depth", "coverage")
LOW_IS_BAD = ("inlier_fraction", "valid_depth", "coverage")  # signals whose small values are the bad ones


def thresholds(cfg: HealthConfig) -> dict[str, dict[str, float]]:
    """The thresholds of each level by signal; a signal a level does not list never fires it."""
    return {
        "lost": {"inlier_fraction": cfg.lost_inlier_fraction, "jump": cfg.lost_jump,
                 "valid_depth": cfg.lost_valid_depth, "coverage": cfg.lost_coverage},
        "degraded": {"inlier_fraction": cfg.degraded_inlier_fraction, "residual_z": cfg.degraded_residual_z,
                     "condition": cfg.degraded_condition, "jump": cfg.degraded_jump,
                     "valid_depth": cfg.degraded_valid_depth, "coverage": cfg.degraded_coverage},
    }


@dataclass(frozen=True)
class TrackingHealth:
    """A frame's status and the signals it was judged from; ``reasons`` names the rules that fired."""

    status: str
    inlier_fraction: float = float("nan")
    residual_z: float = 0.0
    condition: float = float("nan")
    jump: float = 0.0
    valid_depth: float = float("nan")
    coverage: float = float("nan")
    reasons: tuple[str, ...] = ()

    def signals(self) -> dict[str, float]:
        """The signals by name (:data:`SIGNALS`)."""
        values = asdict(self)
        return {name: values[name] for name in SIGNALS}


def image_signals(view, obs, hessian: torch.Tensor | None, cfg: HealthConfig,
                  motion: torch.Tensor | None = None) -> dict[str, float]:
    """``inlier_fraction``, ``condition``, ``valid_depth`` and ``coverage`` (of the view's mask, a keyframe's filled
    pixels included) of a frame from the model ``view`` (a
    :class:`~gausem_core.slam.direct_alignment.ModelView`, colour as rendered) and the alignment ``hessian`` at its
    pose (see :func:`gausem_core.slam.tracker.inspect_pose`). ``motion`` (observed-from-model camera; None: the view
    was rendered at the pose) moves the view's pixels into the frame, each compared with the observed pixel it lands
    on; at the identity that is the pixel it was rendered at."""
    points, values = view.samples
    cam = obs.camera
    landed, z, row, col = _land(points, motion, cam)
    depth_ok = (z[landed] - obs.depth[row, col]).abs() < cfg.inlier_depth
    color_ok = (values[:3, landed].T - obs.rgb[row, col]).abs().mean(-1) < cfg.inlier_color
    inliers = torch.where(obs.valid_depth[row, col], depth_ok, color_ok)
    inlier_fraction = float(inliers.sum()) / len(row) if len(row) else math.nan
    return {"inlier_fraction": inlier_fraction, "condition": condition(hessian, z[landed]),
            "valid_depth": float(obs.valid_depth.float().mean()), "coverage": len(row) / (cam.width * cam.height)}


def _land(points: torch.Tensor, motion: torch.Tensor | None, cam
          ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Which of a view's ``points`` (N, 3), moved by ``motion``, land in ``cam``'s image, their depths (N) and the
    rows and columns they land on."""
    if motion is not None:
        points = points @ motion[:3, :3].T.to(points) + motion[:3, 3].to(points)
    z = points[:, 2]
    u = cam.fx * points[:, 0] / z.clamp_min(1e-6) + cam.cx
    v = cam.fy * points[:, 1] / z.clamp_min(1e-6) + cam.cy
    landed = (z > 1e-6) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
    return landed, z, v[landed].long(), u[landed].long()


def condition(hessian: torch.Tensor | None, depths: torch.Tensor) -> float:
    """log10 of the condition number of ``hessian`` with its translation scaled by the median of ``depths`` (inf
    without a Hessian or when it is singular)."""
    if hessian is None or not len(depths):
        return math.inf
    scale = torch.ones(6, dtype=torch.float64)
    scale[:3] = float(depths.median())
    h = hessian.double().cpu() * scale[:, None] * scale[None, :]
    eig = torch.linalg.eigvalsh(h)
    return math.log10(float(eig[-1]) / float(eig[0])) if float(eig[0]) > 0 else math.inf


def motion(a: torch.Tensor, b: torch.Tensor) -> tuple[float, float]:
    """Translation (metres) and rotation (degrees) of b relative to a (4x4 poses)."""
    delta = (invert_pose(a.double()) @ b.double()).cpu()
    return float(delta[:3, 3].norm()), math.degrees(float(so3_log(delta[:3, :3]).norm()))


class HealthMonitor:
    """Judges each tracked frame against the recent ones (see the module doc); :meth:`reset` when tracking starts
    over (after a relocalisation)."""

    def __init__(self, cfg: HealthConfig):
        self.cfg = cfg
        self.residuals: deque[float] = deque(maxlen=cfg.window)
        self.motions: deque[tuple[float, float]] = deque(maxlen=cfg.window)

    def reset(self) -> None:
        """Forget the motion history (the motion model restarts); residuals stay comparable."""
        self.motions.clear()

    def assess(self, loss: float, image: dict[str, float], pose: torch.Tensor, previous: torch.Tensor | None,
               predicted: torch.Tensor | None, steps: float = 1.0) -> TrackingHealth:
        """The health of a frame tracked to ``pose`` with residual ``loss`` and :func:`image_signals` ``image``
        (:meth:`judge`), learnt from unless lost (:meth:`learn`); ``previous`` is the pose of the last good frame
        (None when unknown), ``predicted`` the motion model's (None at a segment start), which repeats the latest
        motion ``steps`` times since ``previous``. The motion learnt is per step: the one since ``previous`` over
        ``steps``."""
        health = self.judge(loss, image, pose, predicted, steps)
        if health.status != "lost":
            moved = None if previous is None else tuple(m / max(steps, 1.0) for m in motion(previous, pose))
            self.learn(loss, moved)
        return health

    def judge(self, loss: float, image: dict[str, float], pose: torch.Tensor,
              predicted: torch.Tensor | None, steps: float = 1.0) -> TrackingHealth:
        """The health of a frame at ``pose`` against the recent frames, learning nothing (see :meth:`assess`); the
        pose jump from ``predicted`` counts in typical motions per step it predicts over (a prediction across skipped
        frames errs more)."""
        signals = dict(image, residual_z=self._residual_z(loss), jump=self._jump(pose, predicted) / max(steps, 1.0))
        lost = self._fired(signals, "lost")
        degraded = self._fired(signals, "degraded")
        status = "lost" if lost else "degraded" if degraded else "ok"
        return TrackingHealth(status, reasons=tuple(lost or degraded), **signals)

    def learn(self, loss: float, frame_motion: tuple[float, float] | None) -> None:
        """Add a trusted frame's residual and, when known, its motion from the frame before (:func:`motion`)."""
        self.residuals.append(loss)
        if frame_motion is not None:
            self.motions.append(frame_motion)

    def state_dict(self) -> dict[str, list]:
        """The residual and motion histories, as plain lists."""
        return {"residuals": list(self.residuals), "motions": [list(m) for m in self.motions]}

    def load_state_dict(self, state: dict[str, list]) -> None:
        """Restore the histories of :meth:`state_dict` (the newest ``window`` of each)."""
        self.residuals = deque(state["residuals"], maxlen=self.cfg.window)
        self.motions = deque((tuple(m) for m in state["motions"]), maxlen=self.cfg.window)

    def _fired(self, signals: dict[str, float], level: str) -> list[str]:
        """Names of the signals past their ``level`` threshold (below it for fractions, above for the rest)."""
        limits = thresholds(self.cfg)[level]
        return [name for name, value in signals.items() if name in limits
                and ((value < limits[name]) if name in LOW_IS_BAD else (value > limits[name]))]

    def _residual_z(self, loss: float) -> float:
        if len(self.residuals) < self.cfg.min_history:
            return 0.0
        recent = torch.tensor(list(self.residuals), dtype=torch.float64)
        median = float(recent.median())
        mad = float((recent - median).abs().median())
        spread = max(1.4826 * mad, 0.01 * abs(median), 1e-12)
        return (loss - median) / spread

    def _jump(self, pose: torch.Tensor, predicted: torch.Tensor | None) -> float:
        if predicted is None or len(self.motions) < self.cfg.min_history:
            return 0.0
        translation, rotation = motion(predicted, pose)
        recent = torch.tensor(list(self.motions), dtype=torch.float64)
        typical = recent.median(0).values
        return max(translation / max(float(typical[0]), self.cfg.min_translation),
                   rotation / max(float(typical[1]), self.cfg.min_rotation))
