"""Place recognition and loop closure with and without weights (issue #23): per sequence, loops detected / accepted /
true, precision and recall on the paper's protocol, revisits closed, ATE with and without loop closure, submaps and
the time in loop closure by phase. Writes benchmarks/results/place_recognition.json (a results record); each part replaces its own
rows. Run from the repository root (one thread; the TUM part runs the real tracker, minutes per run):

    PYTHONPATH=$PWD OMP_NUM_THREADS=1 .venv/bin/python benchmarks/place_recognition.py --part synthetic
    PYTHONPATH=$PWD OMP_NUM_THREADS=1 .venv/bin/python benchmarks/place_recognition.py --part tum

Ground truth beyond the protocol: a keyframe pair is a TRUE loop when the ground-truth view overlap (the fraction of
the match keyframe's depth pixels that land in the query's view on agreeing depth, from the ground-truth poses) is at
least 0.5. A REVISIT is a run of consecutive database keyframes each of which overlaps by >= 0.5 an earlier keyframe
at least ``exclude_recent`` database keyframes older; it is closed when an accepted loop's query keyframe lies in it.
Synthetic: the drifting loop of test/test_loop_e2e.py (odometry with a known bias), its first 20 frames walked again,
panned by 0-30 degrees (less overlap); ATE without loop closure is that odometry (exact, see the test). TUM fr1/rpy:
the real tracker at 160x120 without labels (params/tum.yaml), run with and without loop closure.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))
from test_loop_e2e import ate_rmse, drifting_run, integrate_odometry, revisit_frames, timestamps  # noqa: E402

from gausem_bench import results  # noqa: E402
from gausem_bench.data import SHARED_DATA  # noqa: E402
from gausem_core.config import load_config  # noqa: E402
from gausem_core.data.tum import TumDataset  # noqa: E402
from gausem_core.eval.loops import DEFAULT_PROTOCOL, loop_scores, view_overlap  # noqa: E402
from gausem_core.io.metrics import git_commit  # noqa: E402
from gausem_core.pipeline import Pipeline  # noqa: E402
from gausem_core.semantics.source import UNLABELLED_PALETTE  # noqa: E402
from gausem_core.report import estimated_trajectory, ground_truth_trajectory, trajectory_metrics  # noqa: E402
from gausem_core.slam.observation import Observation  # noqa: E402

OUT = results.RESULTS
WHAT = ("`benchmarks/place_recognition.py` (definitions in its docstring): a drifting walk of the synthetic loop (80x60, "
        "every 3rd frame, odometry biased by 2 mm and 0.08° per frame, then the first places again, optionally "
        "panned) and the real TUM frames. *true*: the loop's keyframes see each other's view with ≥ 0.5 overlap under "
        "the ground truth; *protocol*: the paper's; *revisits closed*: runs of keyframes that see an earlier place and "
        "hold an accepted loop.")
ROOT = Path(__file__).resolve().parents[1]
TUM = SHARED_DATA / "tum_fr1_rpy"
MIN_OVERLAP = 0.5
# (place recognition, labelled, revisit pan in degrees)
SYNTHETIC = [("descriptor", True, 0.0), ("auto", True, 0.0), ("descriptor", False, 0.0), ("auto", False, 0.0),
             ("auto", False, 15.0), ("auto", False, 30.0)]


def loop_quality(closure, observe, poses: dict[int, np.ndarray], positions: np.ndarray, stamps) -> dict:
    """Protocol scores, overlap-true detections and revisits closed for a finished run's loop closure; ``observe``
    gives a frame id's observation, ``poses`` its ground-truth cam_to_world; ``stamps`` the frames' timestamps."""
    records = closure.records
    observations = {}

    def overlap(query: int, match: int) -> float:
        for frame_id in (query, match):
            if frame_id not in observations:
                observations[frame_id] = observe(frame_id)
        return view_overlap(observations[match], poses[match], observations[query], poses[query])

    keyframes = closure.detector.database.ids.tolist()
    gap = closure.cfg.exclude_recent
    revisiting = [any(overlap(k, j) >= MIN_OVERLAP for j in keyframes[:max(n - gap, 0)])
                  for n, k in enumerate(keyframes)]
    revisits, run = [], []
    for k, revisit in zip(keyframes, revisiting):
        if revisit:
            run.append(k)
        elif run:
            revisits.append(run)
            run = []
    revisits += [run] if run else []
    accepted = [r for r in records if r.accepted]
    runs = [{"frames": [run[0], run[-1]], "keyframes": len(run), "closed": any(r.query_frame in run for r in accepted)}
            for run in revisits]
    row = {"place_recognition": closure.place_recognition, "detected": len(records), "accepted": len(accepted),
           "rejected_by_verification": closure.rejected_candidates,
           "detected_true": sum(overlap(r.query_frame, r.match_frame) >= MIN_OVERLAP for r in records),
           "accepted_true": sum(overlap(r.query_frame, r.match_frame) >= MIN_OVERLAP for r in accepted),
           "revisits": len(runs), "revisits_closed": sum(run["closed"] for run in runs), "revisit_runs": runs,
           "loops": [{"k": r.query_frame, "j": r.match_frame, "intra": r.intra, "accepted": r.accepted,
                      "inliers": r.inliers, "fitness": round(r.fitness, 3),
                      "true_overlap": round(overlap(r.query_frame, r.match_frame), 3)} for r in records]}
    for name, pairs in (("protocol_detected", records), ("protocol_accepted", accepted)):
        row[name] = loop_scores([(r.query_frame, r.match_frame) for r in pairs], positions, timestamps=stamps,
                                **DEFAULT_PROTOCOL).as_dict()
    row["seconds_by_phase"] = dict(closure.seconds)
    return row


def synthetic(place_recognition: str, labelled: bool, pan: float) -> dict:
    start = time.perf_counter()
    slam, truth = drifting_run(overrides={"loop.place_recognition": place_recognition}, labelled=labelled,
                               revisit_pan_deg=pan)
    seconds = time.perf_counter() - start
    _, frames = revisit_frames(revisit_pan_deg=pan)
    poses = {n: p.double().numpy() for n, p in enumerate(truth)}
    palette = UNLABELLED_PALETTE

    def observe(n: int) -> Observation:
        f = frames[n]
        return Observation.from_arrays(f.rgb, f.depth, np.zeros_like(f.labels), f.camera, palette)

    positions = np.stack([p[:3, 3] for p in poses.values()])
    row = {"sequence": f"synthetic loop, revisit panned {pan:g} deg", "labels": labelled, "frames": len(truth),
           "submaps": len(slam.submaps), "ate_rmse_m_without": ate_rmse(integrate_odometry(truth), truth),
           "ate_rmse_m_with": ate_rmse([p for _, p in slam.trajectory()], truth), "seconds": seconds,
           **loop_quality(slam.loop_closure, observe, poses, positions, timestamps(len(truth)))}
    row["loop_fraction_of_run"] = sum(row["seconds_by_phase"].values()) / seconds
    return row


def tum(frames: int, loop: bool) -> dict:
    cfg = load_config(ROOT / "params/tum.yaml", {"device": "cpu", "loop.enabled": loop})
    data = TumDataset(TUM, size=(160, 120), max_frames=frames)
    result = Pipeline(data, cfg, progress=False).run()
    metrics, _ = trajectory_metrics(estimated_trajectory(result), ground_truth_trajectory(result))
    row = {"sequence": f"tum_fr1_rpy ({frames} frames, 160x120)", "labels": False, "frames": len(result.frame_ids),
           "submaps": len(result.slam.submaps), "ate_rmse_m": metrics["ate_rmse_cm"] / 100, "seconds": result.seconds,
           "loop_closure": loop}
    if loop:
        palette = UNLABELLED_PALETTE

        def observe(n: int) -> Observation:
            f = data[n]
            return Observation.from_arrays(f.rgb, f.depth, np.zeros(f.depth.shape, np.int64), f.camera, palette)

        poses = {n: data[n].gt_pose for n in range(len(data))}
        positions = np.stack([p[:3, 3] for p in result.gt_poses])
        row.update(loop_quality(result.slam.loop_closure, observe, poses, positions, result.timestamps))
        row["loop_fraction_of_run"] = sum(row["seconds_by_phase"].values()) / result.seconds
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--part", choices=("synthetic", "tum"), required=True)
    parser.add_argument("--tum-frames", type=int, default=200)
    args = parser.parse_args()
    torch.set_num_threads(1)
    path = OUT / "place_recognition.json"
    started = {"commit": git_commit(), "threads": torch.get_num_threads(), "load_average": os.getloadavg()}
    if args.part == "synthetic":
        rows = [synthetic(*setting) for setting in SYNTHETIC]
    else:
        without, with_loops = tum(args.tum_frames, False), tum(args.tum_frames, True)
        rows = [{**with_loops, "ate_rmse_m_without": without["ate_rmse_m"], "ate_rmse_m_with": with_loops["ate_rmse_m"],
                 "seconds_without": without["seconds"]}]
    document = results.read(path)["data"] if path.exists() else {}  # read now: the other part may have run meanwhile
    document[args.part] = {**started, "rows": rows}
    results.write_report(path, title="Place recognition without labels or weights", what=WHAT,
                         markdown=markdown(document), data=document)


def markdown(document: dict) -> str:
    lines = ["# Place recognition and loop closure (issue #23)", "",
             "Command and definitions: the docstring of benchmarks/place_recognition.py. true = ground-truth view "
             f"overlap >= {MIN_OVERLAP} between the loop's keyframes; protocol = the paper's (intervals of "
             f"{DEFAULT_PROTOCOL['interval']} camera frames at {DEFAULT_PROTOCOL['frame_rate']:g} Hz, dt_min "
             f"{DEFAULT_PROTOCOL['min_frame_gap']}, tau_loop {DEFAULT_PROTOCOL['tau_loop']} m), P / R of the accepted "
             "loops; revisits closed: runs of keyframes that see an earlier place with >= 0.5 overlap and hold an "
             "accepted loop's query keyframe. "
             "Loop closure time: describe (descriptors, ORB) + detect + verify + register + correct, wall clock, one "
             "thread on a shared 2-core machine.", ""]
    for part, data in document.items():
        lines += [f"## {part} (load average {data['load_average'][0]:.1f})", "",
                  "| sequence | labels | place recognition | submaps | detected / accepted / true accepted | "
                  "rejected by verification | protocol P / R | revisits closed | ATE m without / with loop closure "
                  "| loop closure s (share of run) | describe / detect / verify / register / correct s |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in data["rows"]:
            p = r["protocol_accepted"]
            phases = r["seconds_by_phase"]
            lines.append(
                f"| {r['sequence']} | {'yes' if r['labels'] else 'no'} | {r['place_recognition']} | {r['submaps']} | "
                f"{r['detected']} / {r['accepted']} / {r['accepted_true']} | {r['rejected_by_verification']} | "
                f"{p['precision']:.2f} / {p['recall']:.2f} ({p['ground_truth_loops']} loops) | "
                f"{r['revisits_closed']} of {r['revisits']} | {r['ate_rmse_m_without']:.4f} / "
                f"{r['ate_rmse_m_with']:.4f} | {sum(phases.values()):.1f} of {r['seconds']:.0f} "
                f"({100 * r['loop_fraction_of_run']:.1f} %) | "
                f"{' / '.join(f'{phases[k]:.1f}' for k in ('describe', 'detect', 'verify', 'register', 'correct'))} |")
        lines.append("")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
