"""Gauss-Newton alignment of an observed RGB-D-semantic frame to a rendered model view (dense direct odometry).

The model (colour, semantic colour, expected depth) is rendered once per level at the current pose estimate; its
pixels with silhouette > threshold are back-projected, moved by the relative motion, projected into the observed
frame and compared with the observed colour, semantics and depth there: the residuals of paper Eq. 2 with the model
and the observation swapped in role. The L1 norm of Eq. 2 is minimised by iteratively re-weighted least squares
(weights 1 / max(|r|, delta)); the Jacobian comes from the observed images' gradients, so no back-propagation through
the rasteriser is needed, and a coarse-to-fine image pyramid widens the basin of convergence. Optional dense feature
channels (the feature term of SGR's Eq. 6) enter exactly like colour: per-pixel residuals with their own weight.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F

from gausem_core.geometry import PinholeCamera, se3_exp
from gausem_core.native import kernel_available, require_kernel


@dataclass
class ModelView:
    """A rendered model view: colour and semantic colour (H,W,3), expected depth (H,W), valid mask (H,W), and
    optional dense features (H,W,F) matching the observation's feature channels."""

    color: torch.Tensor
    semantic: torch.Tensor
    depth: torch.Tensor
    mask: torch.Tensor
    camera: PinholeCamera
    features: torch.Tensor | None = None

    @functools.cached_property
    def samples(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The pixels inside the mask back-projected (N, 3) and their colour + semantic (+ feature) values
        (6 + F, N), made once per view (views are not changed once made: ``dataclasses.replace`` makes a new one)."""
        rays = self.camera.pixel_rays(self.depth.dtype, self.depth.device)
        values = [self.color, self.semantic] + ([self.features] if self.features is not None else [])
        return (rays * self.depth[..., None])[self.mask], torch.cat([v[self.mask] for v in values], 1).T.contiguous()

    @functools.cached_property
    def median_depth(self) -> float:
        """The median depth inside the mask (inf for an empty view)."""
        depth = self.depth[self.mask]
        return float(depth.median()) if len(depth) else float("inf")

    def checkerboard(self) -> "ModelView":
        """The view with half its pixels: those of the mask whose row plus column is even. At a full resolution
        where a Gaussian covers several pixels, neighbours see about the same surface: the alignment keeps its
        accuracy at half the cost."""
        rows = torch.arange(self.mask.shape[0], device=self.mask.device)[:, None]
        cols = torch.arange(self.mask.shape[1], device=self.mask.device)[None, :]
        return replace(self, mask=self.mask & ((rows + cols) % 2 == 0))

    def downsampled(self) -> "ModelView":
        """Half resolution: the pixels whose 2x2 block lies mostly inside the silhouette, their values averaged over
        the block's pixels inside it."""
        h, w = self.depth.shape[0] // 2 * 2, self.depth.shape[1] // 2 * 2
        inside = self.mask[:h, :w, None].to(self.depth.dtype)
        count = F.avg_pool2d(inside.permute(2, 0, 1)[None], 2)[0].permute(1, 2, 0)

        def pool(t: torch.Tensor) -> torch.Tensor:  # (H, W, C) -> (H/2, W/2, C), over the silhouette
            summed = F.avg_pool2d((t[:h, :w] * inside).permute(2, 0, 1)[None], 2)[0].permute(1, 2, 0)
            return summed / count.clamp_min(1e-6)

        return ModelView(pool(self.color), pool(self.semantic), pool(self.depth[..., None])[..., 0],
                         count[..., 0] > 0.6, self.camera.scaled(w // 2, h // 2),
                         None if self.features is None else pool(self.features))


@dataclass
class ObservedImages:
    """One pyramid level of the observation, channels first for sampling: ``stack`` (C, H, W) is colour 3 + semantic
    colour 3 + depth 1, then F feature channels (F = 0 without features); ``samples`` (3C, H, W) is the stack, its
    horizontal and its vertical gradient, sampled together."""

    samples: torch.Tensor
    camera: PinholeCamera

    @classmethod
    def build(cls, rgb: torch.Tensor, semantic: torch.Tensor, depth: torch.Tensor, camera: PinholeCamera,
              features: torch.Tensor | None = None):
        parts = [rgb.permute(2, 0, 1), semantic.permute(2, 0, 1), depth[None]]
        stack = torch.cat(parts + ([features.permute(2, 0, 1)] if features is not None else []), 0)
        padded = F.pad(stack[None], (1, 1, 1, 1), mode="replicate")[0]
        grad_u = 0.5 * (padded[:, 1:-1, 2:] - padded[:, 1:-1, :-2])
        grad_v = 0.5 * (padded[:, 2:, 1:-1] - padded[:, :-2, 1:-1])
        return cls(torch.cat([stack, grad_u, grad_v], 0), camera)

    @property
    def stack(self) -> torch.Tensor:
        return self.samples[:self.samples.shape[0] // 3]

    @functools.cached_property
    def samples_last(self) -> torch.Tensor:
        """``samples`` channels last (H, W, 3C), made once: a pixel's bilinear corners are then four contiguous
        runs (the compiled kernel reads them so)."""
        return self.samples.permute(1, 2, 0).contiguous()

    def downsampled(self) -> "ObservedImages":
        """Half resolution: colour, semantics and features averaged, depth averaged over valid pixels only."""
        h, w = self.stack.shape[1] // 2 * 2, self.stack.shape[2] // 2 * 2
        s = self.stack[:, :h, :w]
        pooled = F.avg_pool2d(s[None], 2)[0]  # colour, semantics and features
        depth, valid = s[6:7], (s[6:7] > 0).float()
        depth_sum, count = F.avg_pool2d((depth * valid)[None], 2)[0], F.avg_pool2d(valid[None], 2)[0]
        depth = torch.where(count > 0.99, depth_sum / count.clamp_min(1e-6), torch.zeros_like(depth_sum))
        camera = self.camera.scaled(w // 2, h // 2)
        features = pooled[7:].permute(1, 2, 0) if self.feature_channels else None
        return ObservedImages.build(pooled[:3].permute(1, 2, 0), pooled[3:6].permute(1, 2, 0), depth[0], camera,
                                    features)

    def pyramid(self, levels: int, coarsest_width: int) -> list["ObservedImages"]:
        """These images and their halvings, finest first: at least ``levels`` of them, and more while the coarsest is
        wider than ``coarsest_width`` pixels, so that a large input's coarsest level sees the motion in as few pixels
        as a small one's does (the basin of convergence of a level is a pixel or two)."""
        pyramid = [self]
        while ((len(pyramid) < levels or pyramid[-1].camera.width > coarsest_width)
               and min(pyramid[-1].camera.width, pyramid[-1].camera.height) >= 2):
            pyramid.append(pyramid[-1].downsampled())
        return pyramid

    def with_features(self, features: torch.Tensor | None) -> "ObservedImages":
        """The same images with these (H, W, F) feature channels instead of the present ones."""
        s = self.stack
        return ObservedImages.build(s[:3].permute(1, 2, 0), s[3:6].permute(1, 2, 0), s[6], self.camera, features)

    @property
    def feature_channels(self) -> int:
        return self.stack.shape[0] - 7


_MAX_COLOR_RESIDUAL = 0.5  # per channel (colours in [0, 1]): an unexplained pixel's colour error in the cost cap


def _sample(image: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Bilinear samples (C, N) of a (C, H, W) image at continuous pixel coordinates (centres at +0.5)."""
    h, w = image.shape[1:]
    grid = torch.stack([2 * u / w - 1, 2 * v / h - 1], -1)[None, None]
    return F.grid_sample(image[None], grid, mode="bilinear", align_corners=False)[0, :, 0]


@dataclass
class AlignmentWeights:
    color: float
    semantic: float
    depth: float
    huber_delta: float = 0.01  # IRLS floor of |r| (L1 weights 1/|r| are capped at 1/delta)
    max_depth_residual: float = 0.1  # metres: larger depth residuals are occlusions, not misalignment
    max_depth_slope: float = 3.0  # observed depth gradient (metres per metre across the view) beyond: a discontinuity
    feature: float = 0.0  # weight of each dense feature channel (when the images carry any)


def _channel_weights(weights: AlignmentWeights, features: int) -> list[float]:
    """The weight of each of the 7 + F channels (colour, semantics, depth, features)."""
    return [weights.color] * 3 + [weights.semantic] * 3 + [weights.depth] + [weights.feature] * features


def channel_weight_column(weights: AlignmentWeights, features: int, dtype: torch.dtype,
                          device: torch.device) -> torch.Tensor:
    """(C, 1) tensor of the channel weights, made once per device: a fresh one would be a host-to-device copy (a wait
    on the GPU) in every Gauss-Newton step."""
    return _weight_column(tuple(_channel_weights(weights, features)), dtype, device)


@functools.lru_cache(maxsize=32)
def _weight_column(values: tuple[float, ...], dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    return torch.tensor(values, dtype=dtype, device=device)[:, None]


def cost_cap(weights: AlignmentWeights, features: int) -> float:
    """What a model pixel costs at most: a ``max_depth_residual`` depth error and colour, semantic and feature errors
    of ``_MAX_COLOR_RESIDUAL``."""
    return (weights.depth * weights.max_depth_residual
            + (3 * weights.color + 3 * weights.semantic + features * weights.feature) * _MAX_COLOR_RESIDUAL)


def normal_equations(observed: ObservedImages, motion: torch.Tensor, weights: AlignmentWeights, points: torch.Tensor,
                     ref: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, float] | None:
    """``(H, g, cost)`` of one IRLS Gauss-Newton step at ``motion``: H = sum w J J^T (6, 6), g = sum w J r (6) over the
    7 + F channels (colour, semantics, depth, features) of the model ``points`` (N, 3) with values ``ref`` (6 + F, N),
    and the mean cost per model point.

    The cost is the weighted L1 per model pixel, truncated at :func:`cost_cap`, which is also what a model pixel
    without a valid observed counterpart costs: comparable across poses. Depth residuals where the observed depth is
    steeper than ``max_depth_slope`` (discontinuities: sensor noise and mixed pixels, no surface derivative) get no
    IRLS weight. Returns None when fewer than 12 model pixels land on valid observed pixels. On CPU tensors the
    compiled kernel computes it in one pass (``native/alignment.cpp``) when it loads; torch otherwise, same maths.
    """
    if points.device.type == "cpu" and kernel_available():
        return _normal_equations_compiled(observed, motion, weights, points, ref)
    return _normal_equations_torch(observed, motion, weights, points, ref)


def _kernel_arguments(observed: ObservedImages, weights: AlignmentWeights) -> tuple:
    """The observed samples, camera, channel weights and tolerances as the compiled kernels take them."""
    cam, features = observed.camera, observed.feature_channels
    return (observed.samples_last, [cam.fx, cam.fy, cam.cx, cam.cy], _channel_weights(weights, features),
            weights.huber_delta, weights.max_depth_residual, weights.max_depth_slope, cost_cap(weights, features))


def _normal_equations_compiled(observed: ObservedImages, motion: torch.Tensor, weights: AlignmentWeights,
                               points: torch.Tensor, ref: torch.Tensor):
    h, g, cost, valid = require_kernel().alignment_normal_equations(points, ref, motion,
                                                                    *_kernel_arguments(observed, weights))
    return None if valid < 12 else (h, g, cost / len(points))


def _normal_equations_torch(observed: ObservedImages, motion: torch.Tensor, weights: AlignmentWeights,
                            points: torch.Tensor, ref: torch.Tensor):
    """The torch implementation: :func:`normal_equation_sums` and a single copy of ``(H, g, cost, count)`` to the
    host."""
    h, g, cost, count = normal_equation_sums(observed, motion, weights, points, ref)
    packed = torch.cat([h.reshape(-1), g, cost[None], count[None].to(h.dtype)]).to("cpu", torch.float64)
    h, g, cost, count = packed[:36].view(6, 6), packed[36:42], float(packed[42]), int(packed[43])
    return None if count < 12 else (h, g, cost / len(points))


@dataclass
class AlignmentTerms:
    """One Gauss-Newton step's terms per channel c and model point k, before they are summed: the Jacobian (C, N, 6)
    of each residual (C, N), its IRLS weight (C, N; zero where the point has no valid observed counterpart), the
    point's truncated cost (N) and whether it is valid (N). H = sum w J J^T, g = sum w J r."""

    jacobian: torch.Tensor
    weight: torch.Tensor
    residual: torch.Tensor
    cost: torch.Tensor
    valid: torch.Tensor


def alignment_terms(observed: ObservedImages, motion: torch.Tensor, weights: AlignmentWeights, points: torch.Tensor,
                    ref: torch.Tensor) -> AlignmentTerms:
    """The terms of :func:`normal_equation_sums`, on the points' device. Every model point is weighted (invalid ones
    by zero) rather than selected, so that on a GPU the step is one stream of kernels."""
    cam = observed.camera
    p = points @ motion[:3, :3].T + motion[:3, 3]
    z = p[:, 2]
    u, v = cam.fx * p[:, 0] / z + cam.cx, cam.fy * p[:, 1] / z + cam.cy
    inside = (z > 1e-3) & (u > 0.5) & (u < cam.width - 0.5) & (v > 0.5) & (v < cam.height - 0.5)
    z, u, v = torch.where(inside, z, 1.0), torch.where(inside, u, -1.0), torch.where(inside, v, -1.0)  # finite
    samples = _sample(observed.samples, u, v)
    depth_res = samples[6] - z
    valid = inside & (samples[6] > 0) & (depth_res.abs() < weights.max_depth_residual)
    obs, gu, gv = samples.chunk(3)
    # d(u, v, z)/dxi (N, 6) of the projection of p moved by a left increment exp(xi): dp/dxi = [I | -[p]x]
    x, y, inv_z = p[:, 0], p[:, 1], 1 / z
    xn, yn, zero, one = x * inv_z, y * inv_z, torch.zeros_like(z), torch.ones_like(z)
    du = cam.fx * torch.stack([inv_z, zero, -xn * inv_z, -xn * yn, 1 + xn * xn, -yn], -1)
    dv = cam.fy * torch.stack([zero, inv_z, -yn * inv_z, -1 - yn * yn, xn * yn, xn], -1)
    dz = torch.stack([zero, zero, one, y, -x, zero], -1)
    jac = gu[..., None] * du + gv[..., None] * dv  # (C, N, 6)
    jac[6] -= dz  # the observed depth moves with the pixel, and so does z
    res = torch.cat([obs[:6] - ref[:6], depth_res[None], obs[7:] - ref[6:]], 0)
    features = observed.feature_channels
    chan = channel_weight_column(weights, features, p.dtype, p.device)
    irls = chan / res.abs().clamp_min(weights.huber_delta) * valid  # IRLS weights of the L1 norm
    # depth discontinuities: the observed depth's gradient there is no derivative of the surface, leave them out
    slope = (gu[6].abs() * cam.fx + gv[6].abs() * cam.fy) / z
    irls[6] = irls[6] * (slope < weights.max_depth_slope)
    cap = cost_cap(weights, features)
    cost = torch.where(valid, (chan * res.abs()).sum(0).clamp_max(cap), cap)
    return AlignmentTerms(jac, irls, res, cost, valid)


def normal_equation_sums(observed: ObservedImages, motion: torch.Tensor, weights: AlignmentWeights,
                         points: torch.Tensor, ref: torch.Tensor):
    """The sums of :func:`normal_equations` as tensors on the points' device, nothing read back: ``H`` (6, 6), ``g``
    (6), the summed (not mean) cost and the count of valid model points."""
    terms = alignment_terms(observed, motion, weights, points, ref)
    jacobian = terms.jacobian.reshape(-1, 6)
    jw = (terms.jacobian * terms.weight[..., None]).reshape(-1, 6)
    return jw.T @ jacobian, jw.T @ terms.residual.reshape(-1), terms.cost.sum(), terms.valid.sum()


def model_samples(model: ModelView, observed: ObservedImages) -> tuple[torch.Tensor, torch.Tensor]:
    """Back-projected model pixels (N, 3) and their colour + semantic (+ feature) values (6 + F, N)."""
    channels = 0 if model.features is None else model.features.shape[-1]
    if channels != observed.feature_channels:
        raise ValueError(f"the model view has {channels} feature channels, the observation "
                         f"{observed.feature_channels}")
    return model.samples


def alignment_cost(model: ModelView, observed: ObservedImages, motion: torch.Tensor,
                   weights: AlignmentWeights) -> float:
    """Mean weighted L1 residual of the model seen through ``motion`` (inf when the views do not overlap)."""
    step = normal_equations(observed, motion, weights, *model_samples(model, observed))
    return float("inf") if step is None else step[2]


def compared_costs(model: ModelView, observed: ObservedImages, motions: list[torch.Tensor],
                   weights: AlignmentWeights) -> list[float]:
    """Mean weighted L1 residuals of ``model`` seen through each of ``motions``, over the model points that land
    inside the observed image (half a pixel in from the edge of the bilinear support) under every one of them: a
    comparison of poses that the view's border, which moves out of view at a cap's cost, does not tilt towards the
    motion it was rendered at (inf for a motion without 12 valid points)."""
    points, ref = model_samples(model, observed)
    cam, inside = observed.camera, torch.ones(len(points), dtype=torch.bool, device=points.device)
    for motion in motions:
        p = points @ motion[:3, :3].T.to(points) + motion[:3, 3].to(points)
        z = p[:, 2].clamp_min(1e-3)
        u, v = cam.fx * p[:, 0] / z + cam.cx, cam.fy * p[:, 1] / z + cam.cy
        inside &= (p[:, 2] > 1e-3) & (u > 1) & (u < cam.width - 1) & (v > 1) & (v < cam.height - 1)
    points, ref = points[inside], ref[:, inside].contiguous()
    steps = [normal_equations(observed, motion, weights, points, ref) for motion in motions]
    return [float("inf") if step is None else step[2] for step in steps]


def align_level(model: ModelView, observed: ObservedImages, motion: torch.Tensor, weights: AlignmentWeights,
                iterations: int, damping: float = 1e-4, min_step: float = 1e-6) -> tuple[torch.Tensor, float]:
    """Refine ``motion`` (observed-camera-from-model-camera, 4x4) on one level by at most ``iterations`` steps,
    stopping after a step |xi| < ``min_step``; returns it and the last mean L1. The normal equations are summed where
    the images are; the 6x6 solve and the pose update run on the host (on a GPU each would be a handful of kernel
    launches and a wait). On CPU tensors the compiled kernel runs the whole loop when it loads (no Python per step)."""
    points, ref = model_samples(model, observed)
    if points.device.type == "cpu" and kernel_available():  # the same loop in the compiled kernel, in double
        moved, cost = require_kernel().alignment_level(points, ref, motion, *_kernel_arguments(observed, weights),
                                                       iterations, damping, min_step)
        return moved.to(motion.dtype), cost
    device, motion = motion.device, motion.detach().cpu()
    cost = float("nan")
    for _ in range(iterations):
        step = normal_equations(observed, motion.to(device), weights, points, ref)
        if step is None:
            break
        h, g, cost = step
        h = h + damping * torch.diag(h.diagonal()) + 1e-9 * torch.eye(6, dtype=h.dtype)
        xi = -torch.linalg.solve(h, g).to(motion.dtype)
        motion = se3_exp(xi) @ motion
        if float(xi.norm()) < min_step:
            break
    return motion.to(device), cost
