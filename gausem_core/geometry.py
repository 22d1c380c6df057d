"""Rigid-body geometry in torch: SE(3)/so(3) exp and log (differentiable), poses, the pinhole camera.

Conventions used everywhere in GauSem:
- Poses are 4x4 homogeneous matrices. ``cam_to_world`` (a.k.a. world-from-camera, the TUM trajectory pose)
  maps camera points to world points; ``world_to_cam`` is its inverse and is what the renderer takes.
- A twist ``xi`` is a 6-vector ``(rho, omega)``: translation part first, rotation part (axis-angle) second.
- Camera frame: x right, y down, z forward (optical frame, REP-103 ``*_optical_frame``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

_SMALL = 1e-4  # below this angle (rad) the Taylor series are used


def skew(v: torch.Tensor) -> torch.Tensor:
    """(..., 3) -> (..., 3, 3) cross-product matrices."""
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], dim=-1).reshape(v.shape[:-1] + (3, 3))


def _vee(m: torch.Tensor) -> torch.Tensor:
    return torch.stack([m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1)


def _so3_coefficients(theta2: torch.Tensor):
    """A = sin t / t, B = (1 - cos t) / t^2, C = (t - sin t) / t^3, safe (value and gradient) near t = 0."""
    small = theta2 < _SMALL**2
    t2 = torch.where(small, torch.ones_like(theta2), theta2)
    t = t2.sqrt()
    a = torch.where(small, 1 - theta2 / 6 + theta2**2 / 120, torch.sin(t) / t)
    b = torch.where(small, 0.5 - theta2 / 24 + theta2**2 / 720, (1 - torch.cos(t)) / t2)
    c = torch.where(small, 1 / 6 - theta2 / 120 + theta2**2 / 5040, (t - torch.sin(t)) / (t2 * t))
    return a, b, c


def so3_exp(omega: torch.Tensor) -> torch.Tensor:
    """Axis-angle (..., 3) -> rotation matrices (..., 3, 3) (Rodrigues)."""
    k = skew(omega)
    a, b, _ = _so3_coefficients((omega * omega).sum(-1))
    eye = torch.eye(3, dtype=omega.dtype, device=omega.device).expand(k.shape)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


def so3_log(rot: torch.Tensor) -> torch.Tensor:
    """Rotation matrices (..., 3, 3) -> axis-angle (..., 3), valid on the whole of SO(3) (including angles near pi)."""
    cos = ((rot.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1.0, 1.0)
    theta = torch.acos(cos)
    v = _vee(rot)
    small = theta < _SMALL
    near_pi = theta > np.pi - 1e-3
    safe_sin = torch.where(small | near_pi, torch.ones_like(theta), torch.sin(theta))
    regular = torch.where(small, 0.5 + theta**2 / 12, theta / (2 * safe_sin))[..., None] * v
    # Near pi: R ~ 2 n n^T - I, so n_i = sqrt((R_ii + 1) / 2); signs from the largest component's row.
    diag = rot.diagonal(dim1=-2, dim2=-1)
    n = ((diag + 1) / 2).clamp_min(0).sqrt()
    i = diag.argmax(-1, keepdim=True)
    row = torch.take_along_dim(rot, i[..., None], dim=-2).squeeze(-2) + torch.take_along_dim(rot, i[..., None], -1).squeeze(-1)
    signs = torch.where(row >= 0, 1.0, -1.0).to(rot.dtype)
    n = n * signs
    n = n * torch.where((n * v).sum(-1, keepdim=True) < 0, -1.0, 1.0).to(rot.dtype)
    return torch.where(near_pi[..., None], n * theta[..., None], regular)


def se3_exp(xi: torch.Tensor) -> torch.Tensor:
    """Twists (..., 6) = (rho, omega) -> 4x4 transforms (..., 4, 4)."""
    rho, omega = xi[..., :3], xi[..., 3:]
    k = skew(omega)
    a, b, c = _so3_coefficients((omega * omega).sum(-1))
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device).expand(k.shape)
    kk = k @ k
    rot = eye + a[..., None, None] * k + b[..., None, None] * kk
    v = eye + b[..., None, None] * k + c[..., None, None] * kk
    t = (v @ rho[..., None])[..., 0]
    return make_pose(rot, t)


def se3_log(pose: torch.Tensor) -> torch.Tensor:
    """4x4 transforms (..., 4, 4) -> twists (..., 6) = (rho, omega)."""
    rot, t = pose[..., :3, :3], pose[..., :3, 3]
    omega = so3_log(rot)
    theta2 = (omega * omega).sum(-1)
    a, b, _ = _so3_coefficients(theta2)
    small = theta2 < _SMALL**2
    t2 = torch.where(small, torch.ones_like(theta2), theta2)
    d = torch.where(small, 1 / 12 + theta2 / 720, (1 - a / (2 * b)) / t2)
    k = skew(omega)
    eye = torch.eye(3, dtype=pose.dtype, device=pose.device).expand(k.shape)
    v_inv = eye - 0.5 * k + d[..., None, None] * (k @ k)
    return torch.cat([(v_inv @ t[..., None])[..., 0], omega], -1)


def make_pose(rot: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Rotation (..., 3, 3) and translation (..., 3) -> 4x4 (..., 4, 4)."""
    top = torch.cat([rot, t[..., None]], -1)
    bottom = torch.zeros(top.shape[:-2] + (1, 4), dtype=top.dtype, device=top.device)
    bottom[..., 0, 3] = 1
    return torch.cat([top, bottom], -2)


def invert_pose(pose: torch.Tensor) -> torch.Tensor:
    """Inverse of rigid transforms (..., 4, 4), without a general matrix inverse."""
    rt = pose[..., :3, :3].transpose(-1, -2)
    return make_pose(rt, -(rt @ pose[..., :3, 3:])[..., 0])


def project_to_se3(pose: torch.Tensor) -> torch.Tensor:
    """The nearest rigid transform (rotation part projected onto SO(3) by SVD, computed in float64 on the host), in
    pose's dtype and on its device.

    Chains of float32 pose products drift off SO(3); left alone, inverses by transposition amplify the drift.
    """
    m = pose.to("cpu", torch.float64, copy=True)
    u, _, vt = torch.linalg.svd(m[:3, :3])
    fix = torch.ones(3, dtype=m.dtype, device=m.device)
    fix[2] = torch.det(u @ vt)
    m[:3, :3] = u @ torch.diag(fix) @ vt
    return m.to(pose)


def rigid_product(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """a @ b for 4x4 rigid transforms, computed in float64 with the rotation projected back onto SO(3) (SVD), in a's
    dtype: chains of anchors then stay rigid instead of accumulating rounding."""
    return project_to_se3(a.double() @ b.double()).to(a.dtype)


def rigid_float64(pose: torch.Tensor) -> torch.Tensor:
    """A pose as a float64 CPU tensor, projected onto SE(3) when finite (a non-finite pose is returned as is)."""
    m = pose.detach().cpu().double()
    return project_to_se3(m) if torch.isfinite(m).all() else m


def transform_points(pose: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Apply a 4x4 transform to points (N, 3)."""
    return points @ pose[:3, :3].T + pose[:3, 3]


def quaternion_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """Quaternions (..., 4) in (x, y, z, w) order (TUM, ROS) -> rotation matrices (..., 3, 3)."""
    q = q / q.norm(dim=-1, keepdim=True)
    x, y, z, w = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
        2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
        2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
    ], -1).reshape(q.shape[:-1] + (3, 3))


def matrix_to_quaternion(rot: torch.Tensor) -> torch.Tensor:
    """Rotation matrices (..., 3, 3) -> unit quaternions (..., 4) in (x, y, z, w) order with w >= 0."""
    omega = so3_log(rot)
    theta = omega.norm(dim=-1, keepdim=True)
    axis = omega / theta.clamp_min(1e-12)
    q = torch.cat([axis * torch.sin(theta / 2), torch.cos(theta / 2)], -1)
    return q * torch.where(q[..., 3:] < 0, -1.0, 1.0).to(q.dtype)


@dataclass(frozen=True)
class PinholeCamera:
    """Pinhole intrinsics of an image of ``width`` x ``height`` pixels (pixel centres at integer + 0.5)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self):
        if self.width <= 0 or self.height <= 0 or self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"invalid camera {self}: focal lengths and image size must be positive")

    @property
    def K(self) -> torch.Tensor:  # noqa: N802 (the usual name)
        return torch.tensor([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1]], dtype=torch.float32)

    @property
    def focal(self) -> float:
        return 0.5 * (self.fx + self.fy)

    def scaled(self, width: int, height: int) -> "PinholeCamera":
        """The same camera for an image resized to ``width`` x ``height``."""
        sx, sy = width / self.width, height / self.height
        return PinholeCamera(self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, width, height)

    def pixel_rays(self, dtype=torch.float32, device=None) -> torch.Tensor:
        """(H, W, 3) camera-frame directions with z = 1 through every pixel centre."""
        v, u = torch.meshgrid(torch.arange(self.height, dtype=dtype, device=device),
                              torch.arange(self.width, dtype=dtype, device=device), indexing="ij")
        return torch.stack([(u + 0.5 - self.cx) / self.fx, (v + 0.5 - self.cy) / self.fy, torch.ones_like(u)], -1)

    def radius_squared(self, u, v):
        """Squared distance of pixel coordinates ``u``, ``v`` (arrays or tensors) from the principal point, over the
        squared half diagonal of the image (the radius of vignetting models: 1 in the corners of a centred camera)."""
        return ((u - self.cx) ** 2 + (v - self.cy) ** 2) / ((self.width / 2) ** 2 + (self.height / 2) ** 2)

    def backproject(self, depth: torch.Tensor) -> torch.Tensor:
        """Depth (H, W) in metres -> camera-frame points (H, W, 3)."""
        return self.pixel_rays(depth.dtype, depth.device) * depth[..., None]

    def project(self, points: torch.Tensor) -> torch.Tensor:
        """Camera-frame points (..., 3) -> pixel coordinates (..., 2) (continuous, pixel centres at +0.5)."""
        z = points[..., 2:3]
        return torch.cat([self.fx * points[..., 0:1] / z + self.cx, self.fy * points[..., 1:2] / z + self.cy], -1)
