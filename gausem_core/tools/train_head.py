"""``gausem train-head``: train the linear segmentation head on DINOv2 patch tokens from a labelled dataset."""
from __future__ import annotations

import math
import time


def add_arguments(parser) -> None:
    parser.add_argument("--dataset", required=True,
                        help="labelled dataset: synthetic[:default|loop], scannet:PATH or replica:PATH")
    parser.add_argument("--dinov2-weights", required=True,
                        help="local Hugging Face DINOv2 directory (config.json + weights); nothing is downloaded")
    parser.add_argument("--output", required=True, help="head file to write (.pt)")
    parser.add_argument("--short-side", type=int, default=224, help="backbone input short side (multiple of 14)")
    parser.add_argument("--epochs", type=int, default=20)
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--stride", type=int, default=1, help="use every n-th frame (default: 1)")
    parser.add_argument("--frames", type=int, help="use at most this many frames")
    parser.add_argument("--device", default="cpu")


def main(args) -> int:
    import torch

    from gausem_core.data import open_dataset
    from gausem_core.semantics import HeadInfo, load_dinov2, save_head
    from gausem_core.semantics.backbone import image_batch
    from gausem_core.semantics.head import encode_labelled, fit_linear_head

    dataset = open_dataset(args.dataset, stride=args.stride, max_frames=args.frames)
    if dataset.class_table is None:
        raise ValueError(f"dataset {args.dataset!r} has no class table, so no labels to train on")
    backbone = load_dinov2(args.dinov2_weights, args.device)
    num_classes = len(dataset.class_table)

    def labelled_frames():
        for frame in dataset:
            if frame.labels is None:
                raise ValueError(f"{dataset.name}: frame {frame.index} has no labels")
            yield frame.rgb, frame.labels

    def encode(rgb):
        return backbone.tokens(image_batch(rgb), args.short_side)[1][0]

    start = time.perf_counter()
    features, targets = encode_labelled(encode, labelled_frames(), num_classes)
    print(f"{dataset.name}: {len(dataset)} frames, {len(features)} patch tokens, {num_classes} classes, "
          f"encoded in {time.perf_counter() - start:.1f} s")
    head, losses = fit_linear_head(features, targets, num_classes, epochs=args.epochs, lr=args.lr)
    for epoch, loss in enumerate(losses, 1):
        print(f"epoch {epoch:3d}  cross-entropy {loss:.4f}")
    with torch.no_grad():
        accuracy = (head(features).argmax(1) == targets).float().mean().item()
    print(f"patch accuracy on the training set: {accuracy:.3f}")
    if not math.isfinite(losses[-1]):
        print(f"training diverged (final loss {losses[-1]}); try a smaller --lr. No head written.")
        return 1
    info = HeadInfo(num_classes, backbone.hidden_size, backbone.patch_size, args.short_side,
                    dataset.class_table.names)
    save_head(args.output, head.cpu(), info)
    print(f"trained in {time.perf_counter() - start:.1f} s; head written to {args.output}")
    return 0
