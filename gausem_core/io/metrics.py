"""Metrics JSON with provenance (git commit, time, parameters, device) and a short plain-text summary.

Non-finite numbers (NaN for undefined ratios, inf for the PSNR of identical images) are written as ``null``.
"""
from __future__ import annotations

import dataclasses
import json
import math
import platform
import subprocess
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import torch


def git_commit(directory: str | Path | None = None) -> str | None:
    """HEAD commit of the git checkout holding ``directory`` (default: this package), or None outside git."""
    cwd = Path(directory) if directory is not None else Path(__file__).resolve().parent
    try:
        done = subprocess.run(["git", "rev-parse", "HEAD"], cwd=cwd, capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout.strip() if done.returncode == 0 else None


def describe_device(device: str | torch.device = "cpu") -> str:
    """Human-readable compute device, e.g. ``cuda:0 (NVIDIA H100)`` or ``cpu (x86_64, 2 threads)``."""
    device = torch.device(device)
    if device.type == "cuda":
        return f"{device} ({torch.cuda.get_device_name(device)})"
    return f"{device} ({platform.machine()}, {torch.get_num_threads()} threads)"


def to_jsonable(value):
    """Plain JSON types from nested dicts/lists, dataclasses, numpy/torch values and paths; NaN/inf -> None."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        value = dataclasses.asdict(value)
    if isinstance(value, dict):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu().numpy()
    if isinstance(value, (np.ndarray, np.generic)):
        value = value.tolist()
    if isinstance(value, (list, tuple)):
        return [to_jsonable(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    raise ValueError(f"to_jsonable: cannot convert {type(value).__name__} value {value!r} to JSON")


def write_metrics_json(path: str | Path, metrics: dict, *, parameters: dict | None = None,
                       device: str | torch.device = "cpu") -> dict:
    """Write ``{timestamp, git_commit, device, parameters, metrics}`` to ``path``; returns what was written."""
    document = to_jsonable({"timestamp": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                            "git_commit": git_commit(), "device": describe_device(device),
                            "parameters": parameters or {}, "metrics": metrics})
    Path(path).write_text(json.dumps(document, indent=2, allow_nan=False) + "\n")
    return document


def _flatten(metrics: dict, prefix: str = "") -> list[tuple[str, object]]:
    items = []
    for key, value in metrics.items():
        name = f"{prefix}{key}"
        items.extend(_flatten(value, name + ".") if isinstance(value, dict) else [(name, value)])
    return items


def _format_value(value) -> str:
    if isinstance(value, float):
        return "n/a" if math.isnan(value) else f"{value:.4g}"
    if isinstance(value, (list, tuple)):
        return f"[{len(value)} values]"
    return str(value)


def format_summary(metrics: dict) -> str:
    """One ``name  value`` line per metric, nested dicts flattened with dots (``ate.rmse``), floats to 4 digits."""
    items = _flatten(to_jsonable(metrics))
    if not items:
        return "(no metrics)"
    width = max(len(name) for name, _ in items)
    return "\n".join(f"{name:<{width}}  {_format_value(v if v is not None else float('nan'))}" for name, v in items)
