"""Trajectory plot for humans: estimated vs ground-truth camera positions, top (x-y) and side (x-z) views."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure


def _positions(points, name: str) -> np.ndarray:
    points = np.asarray(points, np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
        raise ValueError(f"trajectory plot: {name} must be a non-empty (N, 3) array, got shape {points.shape}")
    return points


def write_trajectory_plot(path: str | Path, estimate, reference=None, *, title: str = "",
                          size_px: tuple[int, int] = (1200, 600)) -> None:
    """Write a PNG of (N, 3) estimated positions and optional (M, 3) reference positions (metres, same frame)."""
    estimate = _positions(estimate, "estimate")
    reference = None if reference is None else _positions(reference, "reference")
    dpi = 100
    figure = Figure(figsize=(size_px[0] / dpi, size_px[1] / dpi), dpi=dpi)
    FigureCanvasAgg(figure)
    for k, (axis, label) in enumerate(((1, "y"), (2, "z"))):
        ax = figure.add_subplot(1, 2, k + 1)
        if reference is not None:
            ax.plot(reference[:, 0], reference[:, axis], "--", color="0.4", label="ground truth")
        ax.plot(estimate[:, 0], estimate[:, axis], color="tab:blue", label="estimate")
        ax.plot(*estimate[0, [0, axis]], "o", color="tab:green", label="start")
        ax.set(xlabel="x [m]", ylabel=f"{label} [m]", title=f"x-{label}")
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
        ax.legend(loc="best", fontsize="small")
    if title:
        figure.suptitle(title)
    figure.tight_layout()
    figure.savefig(Path(path), format="png")
