"""``gausem info``: versions of the stack and which optional back-ends work on this machine."""
from __future__ import annotations

import importlib
import importlib.metadata
import platform


PLACE_RECOGNITION = {"bow": "bag of binary ORB words of the images, vocabulary learned online, verified by PnP",
                     "dinov2": "DINOv2 CLS descriptor of the semantic image (the paper's)",
                     "fallback": "colour-layout descriptor of the semantic image"}


def add_arguments(parser) -> None:
    parser.add_argument("--params", default=None, help="ROS-format parameter YAML whose loop closure to describe "
                                                       "(default: the built-in defaults)")


def place_recognition(params: str | None = None) -> str:
    """What a run with these parameters uses to find loop candidates (without loading any weights)."""
    from gausem_core.config import load_config

    cfg = load_config(params)
    if not cfg.loop.enabled:
        return "off (loop.enabled: false)"
    semantics = cfg.semantics
    kind = "dinov2" if semantics.descriptor == "dinov2" or (semantics.descriptor == "auto"
                                                          and semantics.dinov2_weights) else "fallback"
    chosen = cfg.loop.place_recognition_for(kind)
    return f"{chosen}: {PLACE_RECOGNITION[chosen]}"


def component_status() -> dict[str, str]:
    """Name -> version or the reason it is unavailable."""
    import torch

    status = {"python": platform.python_version(), "torch": torch.__version__,
              "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else "not available"}
    from gausem_core.native import kernel_error

    error = kernel_error()
    status["cpu renderer"] = "compiled C++ kernel" if error is None else f"torch only ({error})".splitlines()[0]
    for dist, module in [("numpy", "numpy"), ("opencv-python-headless", "cv2"), ("gtsam", "gtsam"), ("faiss-cpu", "faiss"), ("gsplat", "gsplat"),
                         ("transformers", "transformers"), ("ai-edge-litert", "ai_edge_litert"),
                         ("rosbags", "rosbags"), ("rclpy", "rclpy")]:
        try:
            importlib.import_module(module)
            status[dist] = importlib.metadata.version(dist)
        except Exception as exc:  # any import failure is a status to report, not a crash
            status[dist] = f"unavailable ({type(exc).__name__}: {exc})".splitlines()[0]
    status["ade20k model"] = ade20k_model_status()
    return status


def ade20k_model_status() -> str:
    """Where the ade20k segmenter's model would be read from, or why it cannot be."""
    from gausem_core.semantics.ade20k import resolve_model

    try:
        return str(resolve_model(None))
    except FileNotFoundError as err:
        return f"absent: {err}"


def main(args) -> int:
    status = {**component_status(), "place recognition": place_recognition(args.params)}
    for name, value in status.items():
        print(f"{name:>17}  {value}")
    return 0
