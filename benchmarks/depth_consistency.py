"""Which trajectory explains the sensor's own depth best? Point-to-plane distances between frame pairs' depth maps.

ATE against pseudo ground truth (7-Scenes' poses are KinectFusion's estimates) counts the reference's own errors as the
method's. The depth maps give a check that does not need a reference: for frame pairs ``gap`` frames apart, each
trajectory's relative pose carries the later frame's depth points into the earlier frame, where projection matches
them to its surface; the median point-to-plane distance of the matches (those under ``--max-distance``) says how well
that relative pose aligns the two surfaces. Closer to the truth aligns better, down to the depth's own errors (noise,
the intrinsics, the lens), which every trajectory shares. With motion capture (TUM) the reference should win.

    .venv/bin/python benchmarks/depth_consistency.py --dataset "tum:${GAUSEM_SHARED_DATA:-../shared/data}/7scenes_redkitchen" \\
        out/bench/paper_b/7scenes_redkitchen/{gausem,open3d_slam}/trajectory.txt \\
        --reference out/bench/paper_b/7scenes_redkitchen/gausem/trajectory_gt.txt
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from gausem_bench import results
from gausem_core.data import open_dataset
from gausem_core.data.tum import nearest_within
from gausem_core.geometry import PinholeCamera
from gausem_core.io.trajectory import Trajectory, read_tum_trajectory
from gausem_core.options import parse_size


def surface(depth: np.ndarray, camera: PinholeCamera, max_step: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points (H, W, 3) and unit normals (H, W, 3) of a depth map (metres; 0 = no reading).

    Normals come from central differences; a pixel whose neighbours lack depth or jump by more than ``max_step`` of
    its depth (an occluding edge) gets a zero normal.
    """
    z = depth.astype(np.float64)
    points = camera.backproject(torch.from_numpy(z)).numpy()
    normals = np.zeros_like(points)
    centre = z[1:-1, 1:-1]
    neighbours = np.stack([z[1:-1, 2:], z[1:-1, :-2], z[2:, 1:-1], z[:-2, 1:-1]])
    smooth = (centre > 0) & (neighbours > 0).all(0) & (np.abs(neighbours - centre).max(0) <= max_step * centre)
    n = np.cross(points[1:-1, 2:] - points[1:-1, :-2], points[2:, 1:-1] - points[:-2, 1:-1])
    n /= np.linalg.norm(n, axis=-1, keepdims=True) + 1e-12
    normals[1:-1, 1:-1] = np.where(smooth[..., None], n, 0.0)
    return points, normals


def alignment_distances(target: tuple[np.ndarray, np.ndarray], source_points: np.ndarray, camera: PinholeCamera,
                        target_from_source: np.ndarray, max_distance: float) -> np.ndarray:
    """Point-to-plane distances (metres) of the source's depth points, moved into the target frame and matched to
    the target's surface by projection; matches further than ``max_distance`` (occlusion, no overlap) are left out."""
    target_points, target_normals = target
    points = source_points[source_points[..., 2] > 0] @ target_from_source[:3, :3].T + target_from_source[:3, 3]
    points = points[points[:, 2] > 1e-3]
    u = np.floor(camera.fx * points[:, 0] / points[:, 2] + camera.cx).astype(np.int64)
    v = np.floor(camera.fy * points[:, 1] / points[:, 2] + camera.cy).astype(np.int64)
    inside = (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    points, u, v = points[inside], u[inside], v[inside]
    normals = target_normals[v, u]
    valid = np.abs(normals).sum(-1) > 0
    distances = np.abs(((points - target_points[v, u]) * normals).sum(-1))[valid]
    return distances[distances < max_distance]


def poses_at(trajectory: Trajectory, stamps: np.ndarray) -> list[np.ndarray | None]:
    """Each stamp's pose in the trajectory (nearest within 20 ms), or None."""
    index = nearest_within(stamps, trajectory.stamps)
    return [None if k < 0 else trajectory.poses[k] for k in index]


def compare(dataset, trajectories: dict[str, Trajectory], reference: str, gaps: list[int], every: int,
            max_distance: float = 0.05, min_overlap: float = 0.05) -> list[dict]:
    """Per frame pair (i, i + gap), i every ``every`` frames: each trajectory's median point-to-plane distance (m),
    None where it matched nothing. Pairs where the reference matches under ``min_overlap`` of the pixels are left
    out."""
    frames = list(dataset)
    stamps = np.array([f.timestamp for f in frames])
    poses = {name: poses_at(t, stamps) for name, t in trajectories.items()}
    surfaces = [surface(f.depth, f.camera) for f in frames]
    pairs = []
    for gap in gaps:
        for i in range(0, len(frames) - gap, every):
            j = i + gap
            if any(p[i] is None or p[j] is None for p in poses.values()):
                continue
            distances = {name: alignment_distances(surfaces[i], surfaces[j][0], frames[i].camera,
                                                   np.linalg.inv(p[i]) @ p[j], max_distance)
                         for name, p in poses.items()}
            if len(distances[reference]) < min_overlap * frames[i].depth.size:
                continue  # the two views hardly overlap
            medians = {name: float(np.median(d)) if len(d) else None for name, d in distances.items()}
            pairs.append({"first": i, "second": j, "gap": gap, "median_distance_m": medians})
    return pairs


def summary(pairs: list[dict], names: list[str]) -> list[dict]:
    """Per gap: the median over pairs of each trajectory's median distance, and in how many pairs each was best."""
    rows = []
    for gap in sorted({p["gap"] for p in pairs}):
        of_gap = [p["median_distance_m"] for p in pairs if p["gap"] == gap]
        table = np.array([[np.inf if m[name] is None else m[name] for name in names] for m in of_gap])
        best = np.argmin(table, axis=1)
        rows.append({"gap": gap, "pairs": len(of_gap),
                     "median_mm": {n: float(1000 * np.median(table[:, k])) for k, n in enumerate(names)},
                     "best_in": {n: int((best == k).sum()) for k, n in enumerate(names)}})
    return rows


WHAT = ("`benchmarks/depth_consistency.py` needs no reference: for frame pairs 10, 30 and 60 frames apart (one every 10 "
        "frames) each trajectory's relative pose carries the later frame's depth points (320x240) into the earlier "
        "frame; the median point-to-plane distance of the matches under 5 cm says how well that pose aligns the two "
        "surfaces (pairs whose views overlap under 5 % left out).")


def markdown(rows: list[dict], names: list[str], title: str) -> str:
    lines = [f"*{title}: median point-to-plane distance [mm] (best in how many pairs)*", "",
             "| gap (frames) | pairs | " + " | ".join(names) + " |", "|---|---|" + "---|" * len(names)]
    for r in rows:
        cells = [f"{r['median_mm'][n]:.2f} ({r['best_in'][n]})" for n in names]
        lines.append(f"| {r['gap']} | {r['pairs']} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("trajectories", nargs="+", type=Path, help="estimates (TUM format)")
    parser.add_argument("--reference", type=Path, required=True, help="the reference trajectory (TUM format)")
    parser.add_argument("--dataset", required=True, help="the frames' dataset spec, e.g. tum:PATH")
    parser.add_argument("--size", type=parse_size, default=(320, 240), help="depth resolution to compare at")
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--gaps", type=int, nargs="+", default=[10, 30, 60])
    parser.add_argument("--every", type=int, default=10, help="a pair starts every this many frames")
    parser.add_argument("--max-distance", type=float, default=0.05, help="metres; further matches are left out")
    parser.add_argument("--out", type=Path, help="write the results record OUT.json")
    args = parser.parse_args()
    dataset = open_dataset(args.dataset, size=args.size, max_frames=args.frames)
    named = {f"{p.parent.name}/{p.name}": p for p in args.trajectories} | {"reference": args.reference}
    trajectories = {name: read_tum_trajectory(p) for name, p in named.items()}
    names = list(trajectories)
    pairs = compare(dataset, trajectories, "reference", args.gaps, args.every, args.max_distance)
    rows = summary(pairs, names)
    report = markdown(rows, names, f"{dataset.name}, {len(dataset)} frames, depth at {args.size[0]}x{args.size[1]}")
    if not args.out:
        print(report)
        return
    document = {"dataset": args.dataset, "size": list(args.size), "frames": len(dataset),
                "trajectories": {n: str(p) for n, p in named.items()}, "summary": rows, "pairs": pairs}
    results.write_report(args.out, title=f"Depth consistency: {dataset.name}", what=WHAT, markdown=report,
                         data=document)


if __name__ == "__main__":
    main()
