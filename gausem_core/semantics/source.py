"""Where a run's class ids come from (``semantics.segmenter``), the class table they index, and what is inert
without them.

- ``labels``: the class ids that come with the dataset, checked against its class table. A dataset without labels
  runs with one "unlabelled" class; :attr:`FrameSemantics.notice` then says which parts of the method carry no
  information (:data:`INERT_WITHOUT_LABELS`).
- ``ade20k`` / ``dinov2``: every frame is segmented (the shared ADE20K model, its classes mapped to NYU40; or DINOv2 +
  the linear head); the classes are the segmenter's, coloured by the dataset's class table when it is the
  segmenter's (same size, and the same names when the segmenter has names: then the dataset's labels are the ground
  truth for mIoU), else by the NYU40 colours (ade20k) or generic ones.
"""
from __future__ import annotations

import numpy as np
import torch

from gausem_core.config import SemanticsConfig
from gausem_core.data.classes import NYU40_CLASSES, ClassTable, generic_colors
from gausem_core.semantics.segmenter import Segmenter, segmenter_from_config

IMAGE_SEGMENTERS = ("ade20k", "dinov2")  # segmenters that label an image by itself
UNLABELLED_PALETTE = torch.tensor([[0.5, 0.5, 0.5]])
INERT_WITHOUT_LABELS = (
    "the semantic loss terms of tracking and mapping (one class everywhere: they only repeat the silhouette)",
    "semantic sampling at submap initialisation (uniform)",
    "class-aware submap allocation (the class KL is 0 at every keyframe, so submaps.policy 'semantic' never starts "
    "a new submap: one submap, no SGR, no inter-submap loops, nothing offloaded)",
    "the global descriptor of the semantic image (the same for every keyframe: descriptor loop candidates and SGR's "
    "descriptor pairs cannot tell places apart)",
    "landmark re-ranking of loop candidates (Gaussian-IDF over one class)",
    "the semantic and feature terms of SGR and of the global refinement",
    "semantic evaluation (no mIoU)",
)


class FrameSemantics:
    """The class ids of each frame of ``dataset`` under ``cfg`` (``semantics.*``); segmenters run on ``device``.

    ``kind``: "labels" (from the data), "ade20k" or "dinov2" (segmented) or "unlabelled" (no labels, no segmenter:
    class 0).
    ``class_table``: the classes the ids index (None when unlabelled); ``palette``: their semantic colours (C, 3).
    """

    def __init__(self, dataset, cfg: SemanticsConfig, device: torch.device | str = "cpu"):
        table = getattr(dataset, "class_table", None)
        self.segmenter: Segmenter | None = None
        if cfg.segmenter in IMAGE_SEGMENTERS:
            self.segmenter = segmenter_from_config(cfg, device)
            compatible = table is not None and _same_classes(self.segmenter, table)
            self.kind = cfg.segmenter
            self.class_table = table if compatible else _own_table(self.segmenter)
            self.ground_truth_table = table if compatible else None  # the dataset's labels score the run's classes
        elif table is not None and len(dataset) and dataset[0].labels is not None:
            self.segmenter = segmenter_from_config(cfg, device, len(table))
            self.kind, self.class_table, self.ground_truth_table = "labels", table, table
        else:
            segmenter_from_config(cfg, device, 1)  # an unknown kind is an error here too
            self.kind, self.class_table, self.ground_truth_table = "unlabelled", None, None

    @property
    def palette(self) -> torch.Tensor:
        """(C, 3) float32 semantic colours in [0, 1] of the classes."""
        return UNLABELLED_PALETTE if self.class_table is None else self.class_table.palette.float()

    @property
    def notice(self) -> str | None:
        """What a run without labels and without a segmenter loses, in words (None otherwise)."""
        if self.kind != "unlabelled":
            return None
        inert = "".join(f"\n  - {part}" for part in INERT_WITHOUT_LABELS)
        return ("semantics: the dataset has no labels and semantics.segmenter is 'labels', so every pixel gets one "
                "class ('unlabelled'). Inert in this run:" + inert + "\n  For the method's semantics set "
                "semantics.segmenter: ade20k (a pretrained model, ../shared/models) or dinov2 with "
                "semantics.dinov2_weights and semantics.head_weights (README).")

    def labels(self, frame) -> np.ndarray:
        """(H, W) int64 class ids of ``frame``."""
        if self.kind == "unlabelled":
            return np.zeros(frame.depth.shape, np.int64)
        return self.segmenter.segment(frame.rgb, frame.labels)

    def ground_truth(self, frame) -> np.ndarray | None:
        """The frame's labels when they score this run's classes (mIoU), else None."""
        return frame.labels if self.ground_truth_table is not None else None

    def summary(self) -> dict:
        """What metrics.json records: the label source, the number of classes and what is inert."""
        return {"source": self.kind, "classes": len(self.palette), "evaluated": self.ground_truth_table is not None,
                "inert": list(INERT_WITHOUT_LABELS) if self.kind == "unlabelled" else []}


def _same_classes(segmenter: Segmenter, table: ClassTable) -> bool:
    names = segmenter.class_names
    return segmenter.num_classes == len(table) and (names is None or tuple(names) == table.names)


def _own_table(segmenter: Segmenter) -> ClassTable:
    """The segmenter's classes: NYU40's colours for NYU40's names, else generic ones."""
    names = segmenter.class_names
    if names is not None and tuple(names) == NYU40_CLASSES.names:
        return NYU40_CLASSES
    names = tuple(names) if names is not None else tuple(f"class_{i}" for i in range(segmenter.num_classes))
    return ClassTable(names, generic_colors(segmenter.num_classes))
