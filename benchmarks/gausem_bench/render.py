"""``python benchmarks/bench.py render``: renderer timing and memory, written as JSON plus a Markdown table.

Forward and forward+backward of :func:`gausem_core.render.render` on a synthetic room (wall at 4 m,
floor, sphere) whose Gaussians are back-projected from the room's depth with a screen radius of 1 px at 320x240
(0.5 px at 160x120, 2 px at 640x480), opacity 0.88 — the SplaTAM-like initial map of a frame.
"""
from __future__ import annotations

import json
import multiprocessing
import math
import os
import platform
import re
import statistics
import subprocess
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import torch

from gausem_bench import results
from gausem_core.gaussians import GaussianCloud
from gausem_core.geometry import PinholeCamera, se3_exp
from gausem_core.options import parse_size

WHAT = ("`python benchmarks/bench.py render`: forward and forward+backward of `render()` on a synthetic room, median of "
        "the repeats, per back-end, Gaussian count and image size; peak extra memory: CUDA allocator peak on a GPU, "
        "else the process's resident high-water mark.")
ROOM_CAMERA = PinholeCamera(fx=262.5, fy=262.5, cx=160.0, cy=120.0, width=320, height=240)  # 1 px radius here


# --- measurement helpers ---------------------------------------------------------------------------------------------
class PeakMemory:
    """Peak extra memory (MB) of a block: CUDA allocator peak on GPU, else the process RSS high-water mark."""

    def __init__(self, device: torch.device):
        self.device = device
        self.mb = float("nan")

    @staticmethod
    def _status_kb(field: str) -> int:
        return int(re.search(rf"{field}:\s+(\d+)", Path("/proc/self/status").read_text()).group(1))

    def __enter__(self):
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            torch.cuda.reset_peak_memory_stats(self.device)
            self._base = torch.cuda.memory_allocated(self.device)
        else:
            Path("/proc/self/clear_refs").write_text("5")  # resets VmHWM to the current RSS
            self._base = self._status_kb("VmRSS") * 1024
        return self

    def __exit__(self, *exc):
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            peak = torch.cuda.max_memory_allocated(self.device)
        else:
            peak = self._status_kb("VmHWM") * 1024
        self.mb = (peak - self._base) / 2**20


def median_ms(fn, repeats: int, device: torch.device) -> float:
    """Median wall time of ``fn()`` in milliseconds (after one untimed warm-up call)."""
    fn()
    times = []
    for _ in range(repeats):
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        start = time.perf_counter()
        fn()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times)


def environment(device: torch.device) -> dict:
    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, check=True,
                                cwd=Path(__file__).resolve().parent).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        commit = "unknown"
    if device.type == "cuda":
        name = torch.cuda.get_device_name(device)
    else:
        match = re.search(r"model name\s*:\s*(.+)", Path("/proc/cpuinfo").read_text())
        name = match.group(1).strip() if match else platform.processor()
    return {"git_commit": commit, "device": device.type, "device_name": name, "torch": torch.__version__,
            "threads": torch.get_num_threads(), "python": platform.python_version(),
            "load_average_at_start": [round(x, 2) for x in os.getloadavg()]}


# --- render target ----------------------------------------------------------------------------------------------------
def room_depth(rays: torch.Tensor) -> torch.Tensor:
    """Depth (z) along camera rays (M, 3) with z = 1 in a room: wall z = 4, floor y = 1.2, sphere r 0.5 at 2.5 m."""
    wall = torch.full(rays.shape[:1], 4.0)
    floor = torch.where(rays[:, 1] > 0, 1.2 / rays[:, 1].clamp_min(1e-9), math.inf)
    centre, radius = torch.tensor([0.3, 0.4, 2.5]), 0.5
    b = rays @ centre
    a = (rays * rays).sum(1)
    disc = b * b - a * (centre @ centre - radius**2)
    sphere = torch.where(disc > 0, (b - disc.clamp_min(0).sqrt()) / a, math.inf)
    return torch.minimum(torch.minimum(wall, floor), sphere)


def room_cloud(n: int, seed: int = 0) -> GaussianCloud:
    """``n`` Gaussians back-projected from random sub-pixel positions of the room seen by ``ROOM_CAMERA``."""
    gen = torch.Generator().manual_seed(seed)
    uv = torch.rand(n, 2, generator=gen) * torch.tensor([ROOM_CAMERA.width, ROOM_CAMERA.height])
    rays = torch.stack([(uv[:, 0] - ROOM_CAMERA.cx) / ROOM_CAMERA.fx, (uv[:, 1] - ROOM_CAMERA.cy) / ROOM_CAMERA.fy,
                        torch.ones(n)], 1)
    depth = room_depth(rays)
    means = rays * depth[:, None]
    colors = 0.5 + 0.5 * torch.sin(means * torch.tensor([7.0, 5.0, 3.0]))
    semantics = torch.stack([depth >= 3.99, means[:, 1] > 1.19, depth < 3.0], 1).float()
    return GaussianCloud.from_points(means, colors, semantics, depth / ROOM_CAMERA.fx, opacity=0.88)


def _render_case(case: dict) -> dict:
    from gausem_core.render import render

    backend, n, width, height = case["backend"], case["gaussians"], case["width"], case["height"]
    device, repeats = torch.device(case["device"]), case["repeats"]
    camera = ROOM_CAMERA.scaled(width, height)
    cloud = room_cloud(n).to(device).requires_grad_()
    xi = torch.zeros(6, device=device, requires_grad=True)

    def forward():
        with torch.no_grad():
            render(cloud, se3_exp(xi), camera, backend=backend)

    def forward_backward():
        out = render(cloud, se3_exp(xi), camera, backend=backend)
        loss = sum((image - 0.5).abs().sum() for image in (out.color, out.depth, out.semantic, out.alpha))
        loss.backward()

    start = time.perf_counter()
    with PeakMemory(device) as memory:  # the first call of a fresh process: nothing cached by the allocator yet
        forward_backward()
    repeats = max(1, min(repeats, int(case["case_seconds"] / (time.perf_counter() - start))))
    return {"backend": backend, "gaussians": n, "width": width, "height": height, "repeats": repeats,
            "forward_ms": round(median_ms(forward, repeats, device), 2),
            "forward_backward_ms": round(median_ms(forward_backward, repeats, device), 2),
            "peak_extra_mb": round(memory.mb, 1)}


def _render_backends(device: torch.device) -> list[str]:
    from gausem_core.native import kernel_available
    from gausem_core.render.gsplat_backend import gsplat_available

    if device.type == "cuda":
        return ["torch", "gsplat"] if gsplat_available() else ["torch"]
    return ["torch", "cpu"] if kernel_available() else ["torch"]


def add_arguments(parser) -> None:
    parser.add_argument("--repeats", type=int, default=5, help="timed repeats per case, median reported")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results"), help="output folder")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--sizes", nargs="+", type=parse_size, default=[(160, 120), (320, 240), (640, 480)],
                        help="WxH image sizes")
    parser.add_argument("--counts", nargs="+", type=int, default=[5000, 20000, 50000, 200000], help="Gaussian counts")
    parser.add_argument("--backend", nargs="+", choices=["torch", "cpu", "gsplat"], help="default: every available one")
    parser.add_argument("--case-seconds", type=float, default=30.0,
                        help="fewer repeats for cases whose first forward+backward is slow (default: %(default)s)")


def run_render(args) -> list[dict]:
    backends = args.backend or _render_backends(torch.device(args.device))
    rows = []
    for width, height in args.sizes:
        for n in args.counts:
            for backend in backends:
                case = {"backend": backend, "gaussians": n, "width": width, "height": height, "device": args.device,
                        "repeats": args.repeats, "case_seconds": args.case_seconds}
                # one fresh process per case, so that the peak memory of one case is not hidden by another's
                with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
                    row = pool.submit(_render_case, case).result()
                print(json.dumps(row), flush=True)
                rows.append(row)
    return rows


def render_table(rows: list[dict]) -> str:
    lines = ["| backend | gaussians | size | forward ms | forward+backward ms | peak extra MB | repeats |",
             "|---|---|---|---|---|---|---|"]
    lines += [f"| {r['backend']} | {r['gaussians']} | {r['width']}x{r['height']} | {r['forward_ms']} | "
              f"{r['forward_backward_ms']} | {r['peak_extra_mb']} | {r['repeats']} |" for r in rows]
    return "\n".join(lines)


def main(args) -> int:
    if args.repeats < 1:
        raise ValueError(f"--repeats must be >= 1, got {args.repeats}")
    env = environment(torch.device(args.device))
    rows = run_render(args)
    results.write_report(args.out / f"render_{env['device']}", title=f"Renderer on the {env['device'].upper()}",
                         what=WHAT, markdown=render_table(rows),
                         machine=f"{env['device_name']}, {os.cpu_count()} cores ({env['threads']} threads, torch "
                                 f"{env['torch']})", data={**env, "target": "render", "results": rows})
    return 0
