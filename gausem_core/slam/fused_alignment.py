"""The normal equations of one alignment step in one Triton kernel launch (issue 47): warp, bilinear samples of the
observed level, residuals of colour, semantics, depth and features, IRLS weights, Jacobians and their reduction into
H, g, the cost and the count, with no host sync. Same maths as
:func:`~gausem_core.slam.direct_alignment.normal_equation_sums` (the torch reference, which serves without Triton).

Compiled for CUDA tensors; for CPU tensors only through Triton's interpreter, which a process chooses before it
imports Triton (``TRITON_INTERPRET=1``: the parity tests do) and which is far too slow to track with."""
from __future__ import annotations

import os

import torch

from gausem_core.slam.direct_alignment import AlignmentWeights, ObservedImages, channel_weight_column, cost_cap

try:
    import triton
    import triton.language as tl
except ImportError:  # optional: without it the torch reference computes the same sums
    triton = tl = None

_INTERPRETED = os.environ.get("TRITON_INTERPRET") == "1"
_BLOCK = 1024 if _INTERPRETED else 64  # points per program (the interpreter pays per program)


def fused_available(device: torch.device | str) -> bool:
    """Whether the tracker computes its steps with :func:`fused_normal_equation_sums` on ``device``: Triton
    importable, compiled (not interpreted), CUDA."""
    return triton is not None and not _INTERPRETED and torch.device(device).type == "cuda"


def fused_normal_equation_sums(observed: ObservedImages, motion: torch.Tensor, weights: AlignmentWeights,
                               points: torch.Tensor, ref: torch.Tensor):
    """:func:`~gausem_core.slam.direct_alignment.normal_equation_sums` in one kernel launch: ``H`` (6, 6), ``g``
    (6), the summed cost and the count of valid model points, as tensors on the points' device."""
    if triton is None:
        raise RuntimeError("fused alignment needs Triton (pip install triton)")
    if points.device.type != "cuda" and not _INTERPRETED:
        raise RuntimeError(f"fused alignment runs on CUDA (or on the CPU with TRITON_INTERPRET=1 set before Triton "
                           f"is imported), not on {points.device}")
    features = observed.feature_channels
    cam, dtype = observed.camera, points.dtype
    chan = channel_weight_column(weights, features, dtype, points.device)
    out = torch.zeros(64 + 8 + 2, dtype=dtype, device=points.device)
    n = len(points)
    _normal_equations[(triton.cdiv(max(n, 1), _BLOCK),)](
        points.contiguous(), ref.contiguous(), observed.samples_last.to(dtype), motion.to(dtype).contiguous(), chan,
        out, n, cam.height, cam.width, float(cam.fx), float(cam.fy), float(cam.cx), float(cam.cy),
        float(weights.huber_delta), float(weights.max_depth_residual), float(weights.max_depth_slope),
        float(cost_cap(weights, features)), C=7 + features, BLOCK=_BLOCK)
    return out[:64].view(8, 8)[:6, :6], out[64:70], out[72], out[73]


def _normal_equations(points, ref, samples, motion, chan, out, n, height, width, fx, fy, cx, cy, huber, max_dres,
                      max_slope, cap, C: tl.constexpr, BLOCK: tl.constexpr):
    """One block of model points: its H (8 x 8, the first 6 x 6 used), g (8), cost and count added into ``out``."""
    offs = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    live = offs < n
    px = tl.load(points + offs * 3, mask=live, other=0.0)
    py = tl.load(points + offs * 3 + 1, mask=live, other=0.0)
    pz = tl.load(points + offs * 3 + 2, mask=live, other=1.0)
    x = tl.load(motion + 0) * px + tl.load(motion + 1) * py + tl.load(motion + 2) * pz + tl.load(motion + 3)
    y = tl.load(motion + 4) * px + tl.load(motion + 5) * py + tl.load(motion + 6) * pz + tl.load(motion + 7)
    z = tl.load(motion + 8) * px + tl.load(motion + 9) * py + tl.load(motion + 10) * pz + tl.load(motion + 11)
    z = tl.where(live, z, 1.0)
    u = fx * x / z + cx
    v = fy * y / z + cy
    inside = live & (z > 1e-3) & (u > 0.5) & (u < width - 0.5) & (v > 0.5) & (v < height - 0.5)
    z = tl.where(inside, z, 1.0)
    # bilinear corners of (u, v), pixel centres at +0.5 (grid_sample, align_corners=False); in range when inside
    su = tl.where(inside, u, 1.0) - 0.5
    sv = tl.where(inside, v, 1.0) - 0.5
    u0 = tl.floor(su)
    v0 = tl.floor(sv)
    au = su - u0
    av = sv - v0
    w00 = (1 - au) * (1 - av)
    w01 = au * (1 - av)
    w10 = (1 - au) * av
    w11 = au * av
    o00 = (v0.to(tl.int32) * width + u0.to(tl.int32)) * (3 * C)
    o01 = o00 + 3 * C
    o10 = o00 + width * (3 * C)
    o11 = o10 + 3 * C
    # per point, over the channels but depth: sum w gu^2, w gu gv, w gv^2, w gu r, w gv r and the weighted L1
    a_uu = z * 0.0
    a_uv = z * 0.0
    a_vv = z * 0.0
    b_u = z * 0.0
    b_v = z * 0.0
    l1 = z * 0.0
    depth = z * 0.0
    depth_u = z * 0.0
    depth_v = z * 0.0
    depth_w = z * 0.0
    for c in tl.static_range(C):
        value = _bilinear(samples + c, o00, o01, o10, o11, w00, w01, w10, w11, inside)
        grad_u = _bilinear(samples + C + c, o00, o01, o10, o11, w00, w01, w10, w11, inside)
        grad_v = _bilinear(samples + 2 * C + c, o00, o01, o10, o11, w00, w01, w10, w11, inside)
        weight = tl.load(chan + c)
        if c == 6:  # depth: its residual moves with z, and steep observed depth (a discontinuity) gets no weight
            depth = value
            depth_u = grad_u
            depth_v = grad_v
            residual = value - z
            slope = (tl.abs(grad_u) * fx + tl.abs(grad_v) * fy) / z
            depth_w = tl.where(slope < max_slope, weight / tl.maximum(tl.abs(residual), huber), 0.0)
        else:
            if c < 6:
                row = c
            else:
                row = c - 1  # the reference values skip depth
            residual = value - tl.load(ref + row * n + offs, mask=live, other=0.0)
            irls = weight / tl.maximum(tl.abs(residual), huber)
            a_uu += irls * grad_u * grad_u
            a_uv += irls * grad_u * grad_v
            a_vv += irls * grad_v * grad_v
            b_u += irls * grad_u * residual
            b_v += irls * grad_v * residual
        l1 += weight * tl.abs(residual)
    depth_res = depth - z
    valid = inside & (depth > 0) & (tl.abs(depth_res) < max_dres)
    keep = tl.where(valid, 1.0, 0.0)
    # d(u, v, z)/dxi of the point moved by a left increment exp(xi) (dp/dxi = [I | -[p]x]), 8 columns (2 unused)
    col = tl.arange(0, 8)[None, :]
    iz = 1 / z
    xn = x * iz
    yn = y * iz
    du = fx * (tl.where(col == 0, iz[:, None], 0.0) + tl.where(col == 2, (-xn * iz)[:, None], 0.0)
               + tl.where(col == 3, (-xn * yn)[:, None], 0.0) + tl.where(col == 4, (1 + xn * xn)[:, None], 0.0)
               + tl.where(col == 5, -yn[:, None], 0.0))
    dv = fy * (tl.where(col == 1, iz[:, None], 0.0) + tl.where(col == 2, (-yn * iz)[:, None], 0.0)
               + tl.where(col == 3, (-1 - yn * yn)[:, None], 0.0) + tl.where(col == 4, (xn * yn)[:, None], 0.0)
               + tl.where(col == 5, xn[:, None], 0.0))
    dz = tl.where(col == 2, 1.0, 0.0) + tl.where(col == 3, y[:, None], 0.0) + tl.where(col == 4, -x[:, None], 0.0)
    jd = depth_u[:, None] * du + depth_v[:, None] * dv - dz
    wd = (depth_w * keep)[:, None, None]
    h = ((a_uu * keep)[:, None, None] * du[:, :, None] * du[:, None, :]
         + (a_uv * keep)[:, None, None] * (du[:, :, None] * dv[:, None, :] + dv[:, :, None] * du[:, None, :])
         + (a_vv * keep)[:, None, None] * dv[:, :, None] * dv[:, None, :]
         + wd * jd[:, :, None] * jd[:, None, :])
    g = ((b_u * keep)[:, None] * du + (b_v * keep)[:, None] * dv + (depth_w * keep * depth_res)[:, None] * jd)
    cost = tl.where(valid, tl.minimum(l1, cap), cap)
    rows = tl.arange(0, 8)
    tl.atomic_add(out + rows[:, None] * 8 + rows[None, :], tl.sum(h, 0))
    tl.atomic_add(out + 64 + rows, tl.sum(g, 0))
    tl.atomic_add(out + 72, tl.sum(tl.where(live, cost, 0.0), 0))
    tl.atomic_add(out + 73, tl.sum(keep, 0))


def _bilinear(channel, o00, o01, o10, o11, w00, w01, w10, w11, inside):
    """One channel's bilinear samples from its four corners' offsets and weights (0 outside)."""
    return (w00 * tl.load(channel + o00, mask=inside, other=0.0)
            + w01 * tl.load(channel + o01, mask=inside, other=0.0)
            + w10 * tl.load(channel + o10, mask=inside, other=0.0)
            + w11 * tl.load(channel + o11, mask=inside, other=0.0))


if triton is not None:  # jitted here, not decorated: the module imports without Triton
    _bilinear = triton.jit(_bilinear)
    _normal_equations = triton.jit(_normal_equations)
