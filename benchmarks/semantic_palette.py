"""Per-keyframe cost of learning the loop closure's semantic palette: the keyed lookup of
:class:`~gausem_core.slam.loop_closure.SemanticPalette` against the full ``torch.unique(dim=0)`` sort it replaced
(commit e6ce9ea), on the keyframes of a synthetic sequence. Both run in one process, interleaved keyframe by keyframe;
prints the median milliseconds per keyframe of each and their ratio, and checks that both learn the same colours.
Run from the repository root (``--device cuda`` on a GPU):

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/semantic_palette.py --size 640x480 --keyframes 20
"""
from __future__ import annotations

import argparse
import statistics
import time

import torch

from gausem_core.data.synthetic import SyntheticDataset
from gausem_core.slam.loop_closure import SemanticPalette
from gausem_core.slam.observation import Observation
from gausem_core.tools.run import parse_size


class UniqueSortPalette:
    """The replaced SemanticPalette.update: a unique sort of every pixel's colour, then the unknown ones appended."""

    def __init__(self):
        self.colors = torch.zeros(0, 3)

    def update(self, semantic: torch.Tensor) -> None:
        found = torch.unique(semantic.detach().reshape(-1, 3).float().cpu(), dim=0)
        if len(self.colors):
            found = found[torch.cdist(found, self.colors).min(1).values > 1e-4]
        self.colors = torch.cat([self.colors, found])


def keyframe_semantics(sequence: str, size: tuple[int, int], keyframes: int, every: int,
                       device: torch.device) -> list[torch.Tensor]:
    """The semantic images (H, W, 3) of every ``every``-th frame of a synthetic sequence, on ``device``."""
    dataset = SyntheticDataset(sequence, resolution=size)
    palette = dataset.class_table.palette.float()
    semantics = []
    for index in range(0, keyframes * every, every):
        frame = dataset[index]
        semantics.append(Observation.from_arrays(frame.rgb, frame.depth, frame.labels, frame.camera, palette,
                                                 device=device).semantic)
    return semantics


def timed(fn) -> float:
    """Seconds ``fn()`` takes (the device synchronised before and after)."""
    synchronise = torch.cuda.synchronize if torch.cuda.is_available() else (lambda: None)
    synchronise()
    start = time.perf_counter()
    fn()
    synchronise()
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sequence", default="loop")
    parser.add_argument("--size", type=parse_size, default=(640, 480))
    parser.add_argument("--keyframes", type=int, default=20)
    parser.add_argument("--every", type=int, default=6, help="frames between keyframes")
    parser.add_argument("--repeats", type=int, default=5, help="passes over the keyframes")
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    device = torch.device(args.device)
    semantics = keyframe_semantics(args.sequence, args.size, args.keyframes, args.every, device)
    times = {"old": [], "new": []}
    for _ in range(args.repeats):
        palettes = {"old": UniqueSortPalette(), "new": SemanticPalette()}
        for k, semantic in enumerate(semantics):
            for name in sorted(palettes, reverse=k % 2 == 1):  # alternate which goes first
                times[name].append(timed(lambda: palettes[name].update(semantic)))
        if not torch.equal(palettes["new"].colors, palettes["old"].colors):
            raise SystemExit("the two palettes differ")
    old, new = (statistics.median(times[name]) * 1e3 for name in ("old", "new"))
    w, h = args.size
    print(f"synthetic_{args.sequence} {w}x{h}, {args.keyframes} keyframes x {args.repeats}, {device}, "
          f"{torch.get_num_threads()} threads: unique sort {old:.3f} ms, keyed lookup {new:.3f} ms per keyframe "
          f"(median); {old / new:.1f}x; {len(palettes['new'])} colours")


if __name__ == "__main__":
    main()
