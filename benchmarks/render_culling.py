"""Rendering with and without view culling (``gausem_core.render.pairs.in_view``), paired and interleaved.

A shell of 70k Gaussians 1-3 m around the camera, shifted forward so that 36-100 % of them have a pixel in their
footprint box; render forward + backward (and forward only) at 160x120, 80x60 and 40x30 with the default back-end,
culling on and off alternately; median times and the median of the paired ratios. Writes
benchmarks/results/render_culling.md. Run from the repository root:

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/render_culling.py
"""
from __future__ import annotations

import os
import statistics
import time
from pathlib import Path

import torch

import gausem_core.render as render_module
from gausem_core.gaussians import GaussianCloud
from gausem_core.geometry import PinholeCamera
from gausem_core.io.metrics import git_commit

OUT = Path(__file__).resolve().parent / "results" / "render_culling.md"
CULL = render_module.in_view


def shell(forward_shift: float, n: int = 70000) -> GaussianCloud:
    g = torch.Generator().manual_seed(0)
    d = torch.randn(n, 3, generator=g)
    d[:, 1] *= 0.5
    d[:, 2] += forward_shift
    means = d / d.norm(dim=1, keepdim=True) * (1 + 2 * torch.rand(n, 1, generator=g))
    return GaussianCloud.from_points(means, torch.rand(n, 3, generator=g), torch.rand(n, 3, generator=g),
                                     torch.full((n,), 0.01), 0.5)


def measure(cloud: GaussianCloud, width: int, height: int, backward: bool, repeats: int = 12) -> dict:
    for t in cloud.tensors().values():
        t.requires_grad_(backward)
    focal = 130.0 * width / 160
    camera = PinholeCamera(fx=focal, fy=focal, cx=width / 2, cy=height / 2, width=width, height=height)
    pose = torch.eye(4)
    seen = CULL(cloud, pose, camera, 0.01)
    times = {True: [], False: []}
    for _ in range(repeats):
        for cull in (True, False):
            render_module.in_view = CULL if cull else (lambda *args: None)
            start = time.perf_counter()
            out = render_module.render(cloud, pose, camera)
            if backward:
                (out.color.sum() + out.depth.sum()).backward()
            times[cull].append(time.perf_counter() - start)
    render_module.in_view = CULL
    on, off = times[True][2:], times[False][2:]  # the first two pairs warm up
    return {"size": f"{width}x{height}", "backward": backward,
            "in_view": 1.0 if seen is None else len(seen) / len(cloud),
            "ms_cull": 1000 * statistics.median(on), "ms_no_cull": 1000 * statistics.median(off),
            "ratio": statistics.median(a / b for a, b in zip(on, off))}


def main() -> None:
    rows = [measure(shell(shift), w, h, True) for shift in (1.2, 3.0, 8.0) for w, h in ((160, 120), (80, 60), (40, 30))]
    rows += [measure(shell(shift), 160, 120, False) for shift in (1.2, 8.0)]
    lines = [f"# View culling (commit {git_commit()[:10]}, {torch.get_num_threads()} threads, load average "
             f"{os.getloadavg()[0]:.1f})", "",
             "70k Gaussians; times are medians of 10 interleaved pairs, the ratio the median of the pairs' ratios.", "",
             "| in view | size | backward | ms culled | ms not culled | culled / not |", "|---|---|---|---|---|---|"]
    lines += [f"| {r['in_view']:.2f} | {r['size']} | {r['backward']} | {r['ms_cull']:.1f} | {r['ms_no_cull']:.1f} | "
              f"{r['ratio']:.2f} |" for r in rows]
    OUT.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
