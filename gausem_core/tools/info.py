"""``gausem info``: versions of the stack and which optional back-ends work on this machine."""
from __future__ import annotations

import importlib
import importlib.metadata
import platform


def add_arguments(parser) -> None:  # no options
    del parser


def component_status() -> dict[str, str]:
    """Name -> version or the reason it is unavailable."""
    import torch

    status = {"python": platform.python_version(), "torch": torch.__version__,
              "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else "not available"}
    from gausem_core.native import kernel_error

    error = kernel_error()
    status["cpu renderer"] = "compiled C++ kernel" if error is None else f"torch only ({error})".splitlines()[0]
    for dist, module in [("numpy", "numpy"), ("gtsam", "gtsam"), ("faiss-cpu", "faiss"), ("gsplat", "gsplat"),
                         ("transformers", "transformers"), ("rosbags", "rosbags"), ("rclpy", "rclpy")]:
        try:
            importlib.import_module(module)
            status[dist] = importlib.metadata.version(dist)
        except Exception as exc:  # any import failure is a status to report, not a crash
            status[dist] = f"unavailable ({type(exc).__name__}: {exc})".splitlines()[0]
    return status


def main(args) -> int:
    del args
    for name, value in component_status().items():
        print(f"{name:>14}  {value}")
    return 0
