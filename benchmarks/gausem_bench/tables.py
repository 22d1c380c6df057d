"""Markdown tables shaped like the paper's, from benchmark run records (:func:`gausem_bench.worker.run_case`).

Columns are sequences (after ``Avg.``, the mean over sequences, shown where every sequence has a value) and rows are
configurations, in suite order; ``–`` marks a value a run did not produce (a failed run, or a metric its method does
not report). Tables without a single value (e.g. loops when no run reports loop scores) are left out.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

DASH = "–"
UNREGISTERED = "†"  # depth not registered to colour, used as if it were
RESAMPLED = "‡"  # depth not registered to colour; colour resampled into the depth camera


@dataclass(frozen=True)
class Metric:
    label: str
    get: Callable[[dict], float | None]  # metrics dict -> value (None when absent)
    digits: int


def _path(*keys: str, scale: float = 1.0) -> Callable[[dict], float | None]:
    def get(metrics: dict):
        value = metrics
        for key in keys:
            value = value.get(key) if isinstance(value, dict) else None
        return value * scale if isinstance(value, (int, float)) and math.isfinite(value) else None
    return get


ATE = Metric("ATE RMSE [cm] ↓", _path("ate_rmse_cm"), 2)
RENDERING = [Metric("PSNR [dB] ↑", _path("rendering", "psnr"), 2), Metric("SSIM ↑", _path("rendering", "ssim"), 3),
             Metric("LPIPS ↓", _path("rendering", "lpips"), 3),
             Metric("mIoU [%] ↑", _path("rendering", "miou", scale=100.0), 1),
             Metric("Depth L1 [cm] ↓", _path("rendering", "depth_l1_m", scale=100.0), 2)]
LOOPS = [Metric("Precision ↑", _path("loops", "precision"), 2), Metric("Recall ↑", _path("loops", "recall"), 2),
         Metric("F1 ↑", _path("loops", "f1"), 2)]
PERFORMANCE = [Metric("fps ↑", _path("fps"), 2), Metric("s/frame ↓", _path("seconds_per_frame"), 3),
               Metric("peak CPU [MB] ↓", _path("peak_rss_mb"), 0),
               Metric("peak GPU [MB] ↓", _path("gpu_peak_mb"), 0)]
SUBMAPS = Metric("submaps", _path("num_submaps"), 1)
GAUSSIANS = Metric("Gaussians [k]", _path("num_gaussians", scale=1e-3), 0)


def sequence_mark(record: dict) -> str:
    if record.get("color_calibration"):
        return RESAMPLED
    return UNREGISTERED if record.get("depth_registered") is False else ""


def _format(value: float | None, digits: int) -> str:
    return DASH if value is None else f"{value:.{digits}f}"


def _value(record: dict | None, metric: Metric) -> float | None:
    if record is None or record.get("status") != "ok":
        return None
    return metric.get(record.get("metrics") or {})


def _names(records: list[dict], key: str) -> list[str]:
    return list(dict.fromkeys(r[key] for r in records))


def _table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return "\n".join(lines + ["| " + " | ".join(row) + " |" for row in rows])


class Grid:
    """Records indexed by (sequence, configuration)."""

    def __init__(self, records: list[dict]):
        self.records = records
        self.sequences = _names(records, "sequence")
        self.configurations = _names(records, "configuration")
        self.cell = {(r["sequence"], r["configuration"]): r for r in records}
        self.marks = {s: "" for s in self.sequences}
        for r in records:
            self.marks[r["sequence"]] = self.marks[r["sequence"]] or sequence_mark(r)
        self.headers = [s + self.marks[s] for s in self.sequences]

    def has(self, metric: Metric, configurations: list[str] | None = None) -> bool:
        return any(_value(self.cell.get((s, c)), metric) is not None
                   for s in self.sequences for c in configurations or self.configurations)

    def average(self, configuration: str, metric: Metric) -> float | None:
        """Mean over the sequences; None unless every sequence has a value."""
        values = [_value(self.cell.get((s, configuration)), metric) for s in self.sequences]
        return sum(values) / len(values) if values and None not in values else None

    def row(self, configuration: str, metric: Metric) -> list[str]:
        """The average over sequences (when there are several), then one cell per sequence."""
        cells = [_format(_value(self.cell.get((s, configuration)), metric), metric.digits) for s in self.sequences]
        return ([_format(self.average(configuration, metric), metric.digits)] if len(cells) > 1 else []) + cells

    def columns(self) -> list[str]:
        return (["Avg."] if len(self.sequences) > 1 else []) + self.headers

    def methods(self, method: str) -> list[str]:
        """Configurations that run ``method`` on some sequence."""
        return [c for c in self.configurations if any(r["configuration"] == c and r["method"] == method
                                                      for r in self.records)]


def tracking_table(grid: Grid) -> str:
    """Tab. V: ATE RMSE per sequence, one row per configuration."""
    return _table(["Method", *grid.columns()], [[c, *grid.row(c, ATE)] for c in grid.configurations])


def rendering_table(grid: Grid) -> str:
    """Tab. IV: PSNR, SSIM, LPIPS, mIoU (and depth L1) per sequence, a block of rows per configuration."""
    metrics = [m for m in RENDERING if grid.has(m)]
    rows = [[c, m.label, *grid.row(c, m)] for c in grid.configurations if any(grid.has(n, [c]) for n in metrics)
            for m in metrics]
    return _table(["Method", "Metric", *grid.columns()], rows)


def loops_table(grid: Grid) -> str:
    """Tab. VII: loop precision, recall, F1 with PSNR and ATE, per sequence and configuration."""
    metrics = [*LOOPS, RENDERING[0], ATE]
    rows = [[h, c, *[_format(_value(grid.cell.get((s, c)), m), m.digits) for m in metrics]]
            for s, h in zip(grid.sequences, grid.headers) for c in grid.configurations
            if any(_value(grid.cell.get((s, c)), m) is not None for m in LOOPS)]
    return _table(["Sequence", "Method", *[m.label for m in metrics]], rows)


def ablation_table(grid: Grid) -> str:
    """Tab. VIII: GauSem configurations (their overrides) with rendering, semantics, ATE and the map's size averaged over
    sequences."""
    metrics = [m for m in (*RENDERING[:4], ATE) if grid.has(m)] + [SUBMAPS, GAUSSIANS, PERFORMANCE[0]]
    rows = []
    for c in grid.methods("gausem"):
        overrides = next(r.get("overrides") or {} for r in grid.records if r["configuration"] == c)
        text = ", ".join(f"{k}={v}" for k, v in overrides.items()) or "(defaults)"
        rows.append([c, text, *[_format(grid.average(c, m), m.digits) for m in metrics]])
    return _table(["Configuration", "Overrides", *[m.label for m in metrics]], rows)


def performance_table(grid: Grid) -> str:
    rows = []
    for r in grid.records:
        size = "x".join(str(v) for v in r["size"]) if r.get("size") else "native"
        status = r["status"] if r["status"] == "ok" else f"{r['status']}: {r.get('error', '')}"
        rows.append([r["sequence"], r["configuration"], str(r["frames"]), size,
                     *[_format(_value(r, m), m.digits) for m in PERFORMANCE], status.replace("|", "\\|")])
    return _table(["Sequence", "Method", "frames", "size", *[m.label for m in PERFORMANCE], "status"], rows)


def provenance_table(grid: Grid) -> str:
    rows = [[r["sequence"], r["configuration"], r["method"], str(r["seed"]), r.get("device") or DASH,
             (r.get("git_commit") or "unknown")[:10], r["out_dir"]] for r in grid.records]
    return _table(["Sequence", "Configuration", "method", "seed", "device", "commit", "outputs"], rows)


def markdown_report(records: list[dict], title: str, preamble: str = "") -> str:
    """Every table the records allow, with headings, under ``title``."""
    grid = Grid(records)
    sections = [("Tracking: ATE RMSE [cm] (SE(3)-aligned, lower is better)", tracking_table(grid), True),
                ("Rendering and semantics (own views, final map)", rendering_table(grid),
                 any(grid.has(m) for m in RENDERING)),
                ("Loop detection", loops_table(grid), any(grid.has(m) for m in LOOPS)),
                (f"Ablations (GauSem configurations, averages over {len(grid.sequences)} sequence(s))",
                 ablation_table(grid), len(grid.methods("gausem")) > 1),
                ("Runtime and memory", performance_table(grid), True),
                ("Runs", provenance_table(grid), True)]
    parts = [f"# {title}", preamble.strip()] if preamble.strip() else [f"# {title}"]
    parts += [f"## {heading}\n\n{table}" for heading, table, shown in sections if shown]
    notes = {UNREGISTERED: "depth not registered to colour and no colour calibration given: depth pixels used as "
                           "if aligned with colour pixels.",
             RESAMPLED: "depth not registered to colour: colour resampled into the depth camera with the suite's "
                        "color_calibration."}
    parts += [f"{mark} {text}" for mark, text in notes.items() if mark in grid.marks.values()]
    return "\n\n".join(parts) + "\n"
