"""Semantic segmentation metrics from a confusion matrix: per-class IoU, mIoU and pixel accuracy.

Convention: ``confusion[g, p]`` counts pixels of ground-truth class g predicted as p. Pixels whose ground truth
equals ``ignore_index`` are left out. IoU_c = TP / (TP + FP + FN). mIoU averages IoU over the classes present in the
ground truth (row sum > 0); a class that is only predicted is not averaged in, but its false positives still lower
the IoU of the classes they were taken from. Confusion matrices of several frames add up.
"""
from __future__ import annotations

import numpy as np
import torch


def _numpy(a) -> np.ndarray:
    return a.detach().cpu().numpy() if isinstance(a, torch.Tensor) else np.asarray(a)


def confusion_matrix(predicted, ground_truth, num_classes: int, ignore_index: int | None = None) -> np.ndarray:
    """(C, C) int64 counts of integer label maps of equal shape (numpy or torch), rows = ground truth.

    Every non-ignored label must lie in ``0..num_classes-1`` (a ValueError names the offending values otherwise).
    """
    pred, gt = _numpy(predicted), _numpy(ground_truth)
    if pred.shape != gt.shape:
        raise ValueError(f"confusion_matrix: predicted shape {pred.shape} differs from ground truth shape {gt.shape}")
    pred, gt = pred.astype(np.int64).reshape(-1), gt.astype(np.int64).reshape(-1)
    if num_classes < 1:
        raise ValueError(f"confusion_matrix: num_classes must be positive, got {num_classes}")
    if ignore_index is not None:
        keep = gt != ignore_index
        pred, gt = pred[keep], gt[keep]
    for name, labels in (("ground truth", gt), ("predicted", pred)):
        bad = (labels < 0) | (labels >= num_classes)
        if bad.any():
            raise ValueError(f"confusion_matrix: {name} labels {np.unique(labels[bad])[:10].tolist()} are outside "
                             f"0..{num_classes - 1} (ignore_index={ignore_index})")
    return np.bincount(gt * num_classes + pred, minlength=num_classes**2).reshape(num_classes, num_classes)


def per_class_iou(confusion: np.ndarray) -> np.ndarray:
    """(C,) IoU per class; NaN for a class that is neither in the ground truth nor predicted."""
    confusion = np.asarray(confusion, np.float64)
    tp = np.diag(confusion)
    union = confusion.sum(0) + confusion.sum(1) - tp
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(union > 0, tp / union, np.nan)


def mean_iou(confusion: np.ndarray) -> float:
    """Mean IoU over the classes present in the ground truth (NaN when no pixel was counted)."""
    present = np.asarray(confusion).sum(1) > 0
    return float(per_class_iou(confusion)[present].mean()) if present.any() else float("nan")


def pixel_accuracy(confusion: np.ndarray) -> float:
    """Fraction of counted pixels whose class is predicted correctly (NaN when no pixel was counted)."""
    confusion = np.asarray(confusion)
    total = confusion.sum()
    return float(np.trace(confusion) / total) if total > 0 else float("nan")


def semantic_scores(confusion: np.ndarray) -> dict[str, float | list[float]]:
    """mIoU, pixel accuracy and per-class IoU (NaN entries for classes absent from both) of a confusion matrix."""
    return {"miou": mean_iou(confusion), "pixel_accuracy": pixel_accuracy(confusion),
            "per_class_iou": per_class_iou(confusion).tolist()}
