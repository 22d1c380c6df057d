"""Does a colour calibration fit 7-Scenes? Photometric consistency under the reference poses, per colour handling.

For frame pairs (k, k + 5), every depth pixel of frame k is moved into frame k + 5 with its depth and the reference
(KinectFusion) poses; the grey level it has in frame k is compared with the grey level at its new place in frame
k + 5. Colour that is correctly aligned with depth makes the two agree better. The frames come through the
benchmark's own reader (``open_sequence``), so this checks the shipped resampling too.

    .venv/bin/python benchmarks/seven_scenes_colour.py [--data ../shared/data/7scenes_redkitchen]
"""
from __future__ import annotations

import argparse
import warnings

import cv2
import numpy as np
import torch
import yaml

from gausem_bench.suite import load_suite, open_sequence, sequence_from_dict

SUITE = "benchmarks/suites/paper.yaml"


def grey(rgb: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float64)


def bilinear(image: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``image`` at continuous pixel coordinates (pixel centres at integers), inside the image."""
    u0, v0 = np.floor(u).astype(int), np.floor(v).astype(int)
    du, dv = u - u0, v - v0
    return ((1 - du) * (1 - dv) * image[v0, u0] + du * (1 - dv) * image[v0, u0 + 1]
            + (1 - du) * dv * image[v0 + 1, u0] + du * dv * image[v0 + 1, u0 + 1])


def grey_error(dataset, pairs: int = 10, gap: int = 5, margin: int = 10) -> float:
    """Mean absolute grey-level difference (0-255) of depth pixels moved from frame k to k + gap."""
    errors = []
    for k in np.linspace(0, len(dataset) - gap - 1, pairs).astype(int):
        a, b = dataset[k], dataset[k + gap]
        camera = a.camera
        valid = a.depth > 0
        points = camera.backproject(torch.from_numpy(a.depth.astype(np.float64))).numpy()[valid]
        b_from_a = np.linalg.inv(b.gt_pose) @ a.gt_pose
        moved = points @ b_from_a[:3, :3].T + b_from_a[:3, 3]
        u = camera.fx * moved[:, 0] / moved[:, 2] + camera.cx - 0.5
        v = camera.fy * moved[:, 1] / moved[:, 2] + camera.cy - 0.5
        inside = ((moved[:, 2] > 0) & (u > margin) & (u < camera.width - margin) & (v > margin)
                  & (v < camera.height - margin))
        grey_a = grey(a.rgb)[valid][inside]
        grey_b = bilinear(grey(b.rgb), u[inside], v[inside])
        errors.append(np.abs(grey_a - grey_b).mean())
    return float(np.mean(errors))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", default="../shared/data/7scenes_redkitchen")
    args = parser.parse_args()
    calibration = next(s for s in load_suite(SUITE).sequences if s.name == "7scenes_redkitchen").color_calibration
    variants = {"colour used as if aligned with depth": None,
                "colour focal 525 px, no extrinsic": {k: v for k, v in calibration.items() if k != "depth_to_color"},
                f"{SUITE} calibration (focal 525 px + depth-to-colour)": calibration}
    warnings.simplefilter("ignore")  # the reader's "not registered" warning: that is the point here
    for name, colour in variants.items():
        spec = {"dataset": f"tum:{args.data}", "color_calibration": colour}
        print(f"{grey_error(open_sequence(sequence_from_dict(spec))):6.2f}  {name}")
    print(yaml.safe_dump({"calibration": calibration}, default_flow_style=None).strip())


if __name__ == "__main__":
    main()
