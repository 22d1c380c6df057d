"""Classical RGB-D baselines from Open3D, run on the very frames GauSem sees (a benchmark-only dependency).

``open3d_odometry``: frame-to-frame multi-scale RGB-D odometry (``open3d.t.pipelines.odometry``), each frame
registered to the previous one from an identity guess and the increments chained. ``open3d_slam``: Open3D's dense
frame-to-model SLAM (``open3d.t.pipelines.slam``): each frame is tracked against a ray cast of a TSDF voxel-block
grid and then fused into it. Neither has loop closure. Frames come from the same dataset object (same size, stride
and frame limit), as float depth in metres and RGB in [0, 1]; intrinsics are converted to Open3D's convention (pixel
centres at integer coordinates). A frame whose registration raises is counted in ``tracking_failures`` and keeps
the previous pose. ``open3d`` is imported only when a baseline runs (:func:`import_open3d`).
"""
from __future__ import annotations

import time
from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np
from tqdm import tqdm

INSTALL_HINT = "pip install -r requirements-bench.txt (open3d==0.19.0; `make bench` installs it into .venv)"


@dataclass(frozen=True)
class Open3DParams:
    """Baseline parameters (suite ``overrides`` use these names). Defaults are those of Open3D's own examples."""

    device: str = "auto"  # "auto" (CUDA when Open3D has it), "cpu" or "cuda"
    method: str = "hybrid"  # odometry residual: "hybrid" (depth + intensity), "point_to_plane" or "intensity"
    depth_min: float = 0.1  # metres; ray-casting near plane (open3d_slam)
    depth_max: float = 3.0  # metres; farther depth readings are ignored
    depth_diff: float = 0.07  # metres; correspondences whose depths differ more are outliers
    voxel_size: float = 0.0  # metres (open3d_slam); 0 = auto_voxel_size(camera)
    block_count: int = 40000  # voxel blocks of 16^3 allocated for the TSDF (open3d_slam)
    trunc_voxel_multiplier: float = 8.0  # TSDF truncation in voxels (open3d_slam)


def auto_voxel_size(camera) -> float:
    """Open3D's default voxel (3/512 m, set for 640x480 images) or, when larger, the footprint of a pixel at 1.5 m,
    so that low-resolution input still observes every voxel near a surface (160x120 TUM-like: about 1.2 cm)."""
    return max(3.0 / 512, 1.5 / camera.focal)


BASELINES = {"open3d_odometry": Open3DParams(), "open3d_slam": Open3DParams(method="point_to_plane")}


def import_open3d():
    """The ``open3d`` module, or an ImportError that says how to install it."""
    try:
        import open3d
    except ImportError as exc:
        raise ImportError(f"the Open3D baselines need the benchmark-only package open3d: {INSTALL_HINT}") from exc
    open3d.utility.set_verbosity_level(open3d.utility.VerbosityLevel.Error)
    return open3d


@dataclass
class BaselineRun:
    """Estimated cam_to_world poses (N, 4, 4) of the processed frames, their timestamps and ground truth."""

    timestamps: list[float]
    poses: np.ndarray
    gt_poses: list[np.ndarray | None]
    seconds: float
    tracking_failures: int
    device: str
    details: dict  # effective settings the parameters leave open (e.g. the automatic voxel size)


class _Open3DTracker(ABC):
    """Shared set-up: device, intrinsics and frame conversion; subclasses implement :meth:`step`."""

    def __init__(self, o3d, params: Open3DParams, camera):
        self.o3d, self.params = o3d, params
        o3c = o3d.core
        if params.device not in ("auto", "cpu", "cuda"):
            raise ValueError(f"Open3D device must be auto, cpu or cuda, got {params.device!r}")
        cuda = o3c.cuda.is_available()
        if params.device == "cuda" and not cuda:
            raise ValueError("Open3D device 'cuda' requested but this Open3D build sees no CUDA device")
        self.device = o3c.Device("CUDA:0" if cuda and params.device != "cpu" else "CPU:0")
        methods = {"hybrid": "Hybrid", "point_to_plane": "PointToPlane", "intensity": "Intensity"}
        if params.method not in methods:
            raise ValueError(f"Open3D method must be one of {', '.join(methods)}, got {params.method!r}")
        self.method = getattr(o3d.t.pipelines.odometry.Method, methods[params.method])
        k = [[camera.fx, 0.0, camera.cx - 0.5], [0.0, camera.fy, camera.cy - 0.5], [0.0, 0.0, 1.0]]
        self.intrinsics = o3c.Tensor(np.array(k), o3c.float64)
        self.pose = np.eye(4)
        self.details: dict = {}

    def images(self, frame):
        """(colour, depth) Open3D images on the device: RGB float32 in [0, 1], depth float32 metres."""
        image = self.o3d.t.geometry.Image
        tensor = self.o3d.core.Tensor
        color = image(tensor(np.ascontiguousarray(frame.rgb, dtype=np.float32) / 255.0)).to(self.device)
        depth = image(tensor(np.ascontiguousarray(frame.depth[..., None], dtype=np.float32))).to(self.device)
        return color, depth

    @abstractmethod
    def step(self, index: int, frame) -> bool:
        """Estimate frame ``index``'s pose into ``self.pose``; False when the registration failed."""


class FrameToFrameOdometry(_Open3DTracker):
    def __init__(self, o3d, params: Open3DParams, camera):
        super().__init__(o3d, params, camera)
        self.previous = None

    def step(self, index: int, frame) -> bool:
        odometry = self.o3d.t.pipelines.odometry
        current = self.o3d.t.geometry.RGBDImage(*self.images(frame))
        ok = True
        if self.previous is not None:
            try:
                result = odometry.rgbd_odometry_multi_scale(
                    current, self.previous, self.intrinsics, depth_scale=1.0, depth_max=self.params.depth_max,
                    method=self.method, params=odometry.OdometryLossParams(self.params.depth_diff))
                self.pose = self.pose @ result.transformation.cpu().numpy()  # previous-from-current
            except RuntimeError:
                ok = False
        self.previous = current
        return ok


class DenseSlam(_Open3DTracker):
    def __init__(self, o3d, params: Open3DParams, camera):
        super().__init__(o3d, params, camera)
        slam, o3c = o3d.t.pipelines.slam, o3d.core
        voxel_size = params.voxel_size or auto_voxel_size(camera)
        self.details = {"voxel_size": voxel_size}
        self.model = slam.Model(voxel_size, 16, params.block_count, o3c.Tensor(np.eye(4)), self.device)
        self.input = slam.Frame(camera.height, camera.width, self.intrinsics, self.device)
        self.raycast = slam.Frame(camera.height, camera.width, self.intrinsics, self.device)

    def step(self, index: int, frame) -> bool:
        p = self.params
        color, depth = self.images(frame)
        self.input.set_data_from_image("depth", depth)
        self.input.set_data_from_image("color", color)
        ok = True
        if index > 0:
            try:
                result = self.model.track_frame_to_model(self.input, self.raycast, 1.0, p.depth_max, p.depth_diff,
                                                         self.method)
                self.pose = self.pose @ result.transformation.cpu().numpy()
            except RuntimeError:
                ok = False
        self.model.update_frame_pose(index, self.o3d.core.Tensor(self.pose))
        self.model.integrate(self.input, 1.0, p.depth_max, p.trunc_voxel_multiplier)
        self.model.synthesize_model_frame(self.raycast, 1.0, p.depth_min, p.depth_max, p.trunc_voxel_multiplier,
                                          p.method != "point_to_plane")  # colour for the photometric residuals
        return ok


TRACKERS = {"open3d_odometry": FrameToFrameOdometry, "open3d_slam": DenseSlam}


def run_baseline(method: str, dataset, params: Open3DParams, progress: bool = True) -> BaselineRun:
    """Run one baseline over every frame of ``dataset``; timing covers reading the frames, as GauSem's does."""
    if method not in TRACKERS:
        raise ValueError(f"unknown baseline {method!r}; known: {', '.join(TRACKERS)}")
    o3d = import_open3d()
    o3d.utility.random.seed(0)
    tracker, stamps, poses, gt, failures = None, [], [], [], 0
    start = time.perf_counter()
    bar = tqdm(range(len(dataset)), desc=method, unit="frame", disable=not progress)
    for i in bar:
        frame = dataset[i]
        tracker = tracker or TRACKERS[method](o3d, params, frame.camera)
        failures += not tracker.step(i, frame)
        stamps.append(frame.timestamp)
        poses.append(tracker.pose.copy())
        gt.append(frame.gt_pose)
        bar.set_postfix(fps=f"{(i + 1) / (time.perf_counter() - start):.2f}", failures=failures)
    return BaselineRun(stamps, np.stack(poses), gt, time.perf_counter() - start, failures, str(tracker.device),
                       tracker.details)
