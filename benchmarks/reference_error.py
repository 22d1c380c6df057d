"""How far off is a reference trajectory itself? A three-cornered hat over three or more trajectories of one sequence.

Pseudo ground truth (7-Scenes' poses are KinectFusion's estimates) has errors of its own, which ATE against it counts
as the method's. Given trajectories of the same frames (TUM format; e.g. two methods and the reference), this
computes the ATE RMSE (SE(3)-aligned) of every pair and, assuming the trajectories' errors are independent, each one's
own error s_i from d_ij^2 = s_i^2 + s_j^2 (least squares over the pairs; exact for three). Errors shared by the
methods (the same depth, the same sensor) look like the reference's, so read the reference's share as an upper bound.

    .venv/bin/python benchmarks/reference_error.py \
        out/bench/paper_b/7scenes_redkitchen/{gausem,open3d_slam}/trajectory.txt \
        --reference out/bench/paper_b/7scenes_redkitchen/gausem/trajectory_gt.txt
"""
from __future__ import annotations

import argparse
import itertools
from pathlib import Path

import numpy as np

from gausem_core.eval.trajectory import absolute_trajectory_error, associate_trajectories
from gausem_core.io.trajectory import read_tum_trajectory


def pairwise_rmse(trajectories: list) -> np.ndarray:
    """Symmetric matrix of the ATE RMSE (metres) of each pair, the first of a pair aligned to the second."""
    n = len(trajectories)
    d = np.zeros((n, n))
    for i, j in itertools.combinations(range(n), 2):
        d[i, j] = d[j, i] = absolute_trajectory_error(*associate_trajectories(trajectories[i], trajectories[j])).rmse
    return d


def own_errors(d: np.ndarray) -> np.ndarray:
    """Each trajectory's own RMS error from the pairwise ones, d_ij^2 = s_i^2 + s_j^2 (least squares, s^2 >= 0)."""
    n = len(d)
    if n < 3:
        raise ValueError("a three-cornered hat needs at least three trajectories")
    pairs = list(itertools.combinations(range(n), 2))
    a = np.zeros((len(pairs), n))
    for row, (i, j) in enumerate(pairs):
        a[row, [i, j]] = 1.0
    variances = np.linalg.lstsq(a, np.array([d[i, j] ** 2 for i, j in pairs]), rcond=None)[0]
    return np.sqrt(np.clip(variances, 0.0, None))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("trajectories", nargs="+", type=Path, help="estimates (TUM format), two at least")
    parser.add_argument("--reference", type=Path, required=True, help="the reference trajectory (TUM format)")
    args = parser.parse_args()
    paths = [*args.trajectories, args.reference]
    names = [f"{p.parent.name}/{p.name}" for p in args.trajectories] + ["reference"]
    d = pairwise_rmse([read_tum_trajectory(p) for p in paths])
    s = own_errors(d)
    print("| trajectory | ATE against the reference [cm] | own error, three-cornered hat [cm] |")
    print("|---|---|---|")
    for k, name in enumerate(names):
        print(f"| {name} | {100 * d[k, -1]:.2f} | {100 * s[k]:.2f} |")
    for i, j in itertools.combinations(range(len(names) - 1), 2):
        print(f"\n{names[i]} against {names[j]}: {100 * d[i, j]:.2f} cm")


if __name__ == "__main__":
    main()
