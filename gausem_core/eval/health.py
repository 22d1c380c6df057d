"""How well the tracking status predicts pose error: per-frame relative errors, flags of the worst frames, and a
planted failure (a frame's images swapped in from elsewhere in the sequence) to test it on."""
from __future__ import annotations

from dataclasses import replace

import numpy as np


class PlantedFailure:
    """A dataset whose frame ``slot`` carries frame ``source``'s images (index, timestamp and ground truth stay the
    slot's): a one-frame tracking failure with a known answer."""

    def __init__(self, dataset, slot: int, source: int):
        if not (0 <= slot < len(dataset) and 0 <= source < len(dataset)):
            raise ValueError(f"planted failure: frames {slot} and {source} must lie in [0, {len(dataset) - 1}]")
        self.dataset, self.slot, self.source = dataset, slot, source
        self.class_table = getattr(dataset, "class_table", None)

    def __len__(self) -> int:
        return len(self.dataset)

    def __getitem__(self, i: int):
        frame = self.dataset[i]
        if i != self.slot:
            return frame
        swapped = self.dataset[self.source]
        return replace(frame, rgb=swapped.rgb, depth=swapped.depth, labels=swapped.labels)


def relative_errors(poses: np.ndarray, truths: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame relative pose error (frame i-1 to i) of cam_to_world ``poses`` against ``truths`` (N, 4, 4):
    translation (metres) and rotation (degrees), (N,) each, 0 for the first frame."""
    translation, rotation = np.zeros(len(poses)), np.zeros(len(poses))
    for i in range(1, len(poses)):
        est = np.linalg.inv(poses[i - 1]) @ poses[i]
        ref = np.linalg.inv(truths[i - 1]) @ truths[i]
        delta = np.linalg.inv(ref) @ est
        translation[i] = np.linalg.norm(delta[:3, 3])
        rotation[i] = np.degrees(np.arccos(np.clip((np.trace(delta[:3, :3]) - 1) / 2, -1.0, 1.0)))
    return translation, rotation


def flag_scores(errors: np.ndarray, flagged: np.ndarray, shares=(0.01, 0.05)) -> dict:
    """For each share s: the fraction of the s worst frames by ``errors`` that are ``flagged`` (recall; at least one
    frame), and the false-flag rate: flagged frames outside the 5 % worst, over the frames outside it."""
    order = np.argsort(-errors)
    scores = {}
    for share in shares:
        worst = order[:max(1, int(round(share * len(errors))))]
        scores[f"worst_{share:.0%}_flagged"] = float(flagged[worst].mean())
    rest = np.ones(len(errors), bool)
    rest[order[:max(1, int(round(max(shares) * len(errors))))]] = False
    scores["false_flag_rate"] = float(flagged[rest].mean()) if rest.any() else 0.0
    return scores
