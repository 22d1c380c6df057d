"""The ``ade20k`` segmenter: DeepLabV3 + MobileNetV2 trained on ADE20K, run by LiteRT on the CPU, its 150 classes
mapped to the NYU40 class table (``ade20k_to_nyu40.txt`` beside this module says how).

The model (2.4 MB, from ``../shared/models/deeplabv3_mnv2_ade20k``; provenance in its README) takes a fixed 513x513
RGB image in [-1, 1] and returns 151 logits a pixel. An image is scaled to fit 513 on its long side with its aspect
kept, padded (as DeepLab pads, with the mean grey), segmented, cropped back, and its class ids resized to the image by
nearest neighbour. Nothing is downloaded: the model comes from ``semantics.ade20k_model``, else from
``$GAUSEM_SHARED_MODELS``, else from ``../shared/models`` beside the checkout.
"""
from __future__ import annotations

import os
import threading
from pathlib import Path

import cv2
import numpy as np

from gausem_core.data.classes import NYU40_CLASSES
from gausem_core.semantics.base import Segmenter, check_rgb

MODEL_FILE = Path("deeplabv3_mnv2_ade20k") / "deeplabv3_mnv2_ade20k_default_1.tflite"
MODELS_VARIABLE = "GAUSEM_SHARED_MODELS"
MAPPING_FILE = Path(__file__).with_name("ade20k_to_nyu40.txt")
INPUT_SIDE = 513  # the model's only input size (LiteRT refuses to prepare others)
ADE20K_CLASSES = 151  # 0 = others, 1..150 the ADE20K SceneParsing classes


def shared_models() -> Path:
    """``$GAUSEM_SHARED_MODELS``, by default ``../shared/models`` beside the checkout."""
    folder = os.environ.get(MODELS_VARIABLE)
    return Path(folder) if folder else Path(__file__).resolve().parents[3] / "shared" / "models"


def resolve_model(path: str | Path | None) -> Path:
    """The model file: ``path`` when given, else the shared copy; a clear error naming the parameter when absent."""
    model = Path(path) if path else shared_models() / MODEL_FILE
    if not model.is_file():
        where = f"semantics.ade20k_model is {str(path)!r}" if path else (
            f"semantics.ade20k_model is unset and the shared copy {model} is absent")
        raise FileNotFoundError(f"the ade20k segmenter's model was not found ({where}): set semantics.ade20k_model to "
                                f"the .tflite file, or {MODELS_VARIABLE} to the folder holding {MODEL_FILE}")
    return model


def ade20k_to_nyu40(path: Path = MAPPING_FILE) -> np.ndarray:
    """(151,) lookup array: ADE20K class id -> NYU40 class id, read from the mapping file."""
    lut = np.full(ADE20K_CLASSES, -1, np.int64)
    for line in path.read_text().splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        ade_id, _, target = line.split()
        lut[int(ade_id)] = NYU40_CLASSES.id_of(target)
    if (lut < 0).any():
        raise ValueError(f"{path}: no NYU40 class for ADE20K ids {np.flatnonzero(lut < 0).tolist()}")
    return lut


def letterbox(rgb: np.ndarray) -> tuple[np.ndarray, tuple[int, int]]:
    """The model's (1, 513, 513, 3) input in [-1, 1]: ``rgb`` scaled to fit with its aspect kept, at the top left,
    padded with the mean grey (0); and the (height, width) it fills."""
    h, w = rgb.shape[:2]
    scale = INPUT_SIDE / max(h, w)
    fit = max(1, min(INPUT_SIDE, round(h * scale))), max(1, min(INPUT_SIDE, round(w * scale)))
    batch = np.zeros((1, INPUT_SIDE, INPUT_SIDE, 3), np.float32)
    batch[0, :fit[0], :fit[1]] = cv2.resize(rgb, fit[::-1], interpolation=cv2.INTER_AREA) / 127.5 - 1.0
    return batch, fit


def crop_back(ids: np.ndarray, fit: tuple[int, int], shape: tuple[int, int]) -> np.ndarray:
    """(513, 513) class ids of a :func:`letterbox` input -> (H, W) int64 ids of the image (``shape``), nearest."""
    cropped = np.ascontiguousarray(ids[:fit[0], :fit[1]].astype(np.uint8))
    return cv2.resize(cropped, shape[::-1], interpolation=cv2.INTER_NEAREST).astype(np.int64)


class Ade20kSegmenter(Segmenter):
    """An RGB image -> NYU40 class ids, through the ADE20K DeepLabV3 model. ``model``: the .tflite file (default:
    the shared copy); ``threads``: LiteRT's CPU threads. Safe to call from several threads (one runs at a time)."""

    class_names = NYU40_CLASSES.names
    num_classes = len(NYU40_CLASSES)

    def __init__(self, model: str | Path | None = None, threads: int = 1):
        path = resolve_model(model)
        try:
            from ai_edge_litert.interpreter import Interpreter
        except ImportError as error:
            raise ImportError("the ade20k segmenter runs on LiteRT: pip install ai-edge-litert "
                              "(requirements.txt)") from error
        self._interpreter = Interpreter(model_path=str(path), num_threads=int(threads))
        self._interpreter.allocate_tensors()
        self._input = self._interpreter.get_input_details()[0]
        self._output = self._interpreter.get_output_details()[0]
        expected = ((1, INPUT_SIDE, INPUT_SIDE, 3), (1, INPUT_SIDE, INPUT_SIDE, ADE20K_CLASSES))
        if (tuple(self._input["shape"]), tuple(self._output["shape"])) != expected:
            raise ValueError(f"{path}: expected the ADE20K DeepLabV3 model ({expected[0]} in, {expected[1]} out), got "
                             f"{tuple(self._input['shape'])} in, {tuple(self._output['shape'])} out")
        self._lut = ade20k_to_nyu40()
        self._lock = threading.Lock()

    def ade20k_ids(self, rgb: np.ndarray) -> np.ndarray:
        """(H, W) ADE20K class ids (0..150) of ``rgb``."""
        check_rgb(rgb)
        batch, fit = letterbox(rgb)
        with self._lock:
            self._interpreter.set_tensor(self._input["index"], batch)
            self._interpreter.invoke()
            ids = self._interpreter.get_tensor(self._output["index"])[0].argmax(-1)
        return crop_back(ids, fit, rgb.shape[:2])

    def segment(self, rgb: np.ndarray, labels: np.ndarray | None = None) -> np.ndarray:
        del labels  # the image alone decides
        return self._lut[self.ade20k_ids(rgb)]
