"""The whole system on a CUDA device (issue 22): every tensor it hands back stays on the GPU, and nothing mixes devices
on the way (a mix raises there; torch on the CPU cannot see one). Skipped without a GPU; a few minutes on one.

Covered: a 30-frame ``gausem run`` at 160x120 with its outputs (tracking, mapping, semantic allocation, loop detection,
global refinement, evaluation, export); a 640x480 run that accepts a loop; submaps offloaded to the store's memory and
disk and read back; the global refinement over several submaps. What stays on the CPU by design (the store's copies,
descriptors, the loop database, pose-graph results, loop constraints) is not a result and is not checked here.
"""
import json

import pytest
import torch

from gausem_core.config import load_config
from gausem_core.data import SYNTHETIC_CLASSES, open_dataset
from gausem_core.pipeline import Pipeline
from gausem_core.report import write_outputs
from gausem_core.slam.observation import Observation
from gausem_core.slam.system import GauSemSLAM
from gausem_core.options import default_params_file
from device_check import CUDA, assert_events_on_cpu, assert_on_cuda, frame_results, system_results

pytestmark = [pytest.mark.cuda, pytest.mark.slow,
              pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")]

# one submap, keyframes every 2nd frame, each queried against all earlier ones: keyframe 2 closes a loop to keyframe 0
# (the fallback descriptor's threshold opened up), as in the tracking node's in-core loop test
LOOP = {"mapping.every": 2, "submaps.min_keyframes": 100, "loop.keyframe_every": 2, "loop.check_every": 1,
        "loop.exclude_recent": 0, "loop.max_fallback_descriptor_distance": 2.0, "refinement.enabled": False}
# a new submap at every keyframe after the first, all but the active one spilled to disk
SUBMAPS = {"mapping.every": 2, "submaps.policy": "motion", "submaps.motion_translation": 1e-6,
           "submaps.memory_budget_mb": 0, "loop.enabled": False, "refinement.enabled": False}


def config(**overrides):
    return load_config(default_params_file("synthetic"), {"device": CUDA.type, **overrides})


def run_system(cfg, size: tuple[int, int], frames: int) -> tuple[GauSemSLAM, list]:
    """GauSemSLAM over the first frames of the default synthetic sequence; the system and its frame results."""
    dataset = open_dataset("synthetic", size=size, max_frames=frames)
    slam = GauSemSLAM(cfg, CUDA, len(SYNTHETIC_CLASSES))
    palette = SYNTHETIC_CLASSES.palette.float()
    results = []
    for i in range(len(dataset)):
        frame = dataset[i]
        results.append(slam.process(Observation.from_arrays(frame.rgb, frame.depth, frame.labels, frame.camera,
                                                            palette, frame.timestamp, CUDA)))
    return slam, results


def test_a_30_frame_run_at_160x120_keeps_its_results_on_the_gpu(tmp_path):
    dataset = open_dataset("synthetic", size=(160, 120), max_frames=30)
    cfg = config()
    result = Pipeline(dataset, cfg, progress=False).run()
    assert result.slam.device == CUDA and result.slam.loop_closure is not None
    assert_on_cuda(**system_results(result.slam))
    metrics = write_outputs(result, dataset, cfg, tmp_path, eval_every=10)
    assert metrics["frames"] == 30 and metrics["ate_rmse_cm"] < 5 and metrics["rendering"]["psnr"] > 25
    assert json.loads((tmp_path / "metrics.json").read_text())["device"].startswith(CUDA.type)
    assert (tmp_path / "map.ply").stat().st_size > 0


def test_a_640x480_run_accepts_a_loop_on_the_gpu():
    slam, results = run_system(config(**LOOP), (640, 480), 5)
    loops = slam.loop_closure.loops
    # keyframes 0, 2, 4 in one submap: a later one closes an intra-submap loop back to the first (keyframe 4 on an
    # H200, 2026-11-26)
    assert any(r.match_frame == 0 and r.query_frame in (2, 4) and r.intra for r in loops), loops
    assert_on_cuda(results=frame_results(results), **system_results(slam))
    assert_events_on_cpu(results)


def test_submaps_offloaded_to_disk_come_back_onto_the_gpu():
    slam, results = run_system(config(**SUBMAPS), (160, 120), 9)
    assert [r.submap_id for r in results if r.is_keyframe] == [0, 1, 2, 3, 4]
    inactive = [s for s in slam.submaps if not s.is_active]
    assert len(inactive) == 4 and slam.back_end.store.nbytes == 0 and slam.back_end.store.disk_bytes > 0  # all spilled
    assert_on_cuda(results=frame_results(results), **system_results(slam))
    assert_events_on_cpu(results)
    for submap in inactive:  # read back bit-identically: the store's copy equals what the GPU gets
        stored = submap.load_cloud()
        assert all(torch.equal(a.cpu(), b) for a, b in zip(submap.load_cloud(CUDA).tensors().values(),
                                                             stored.tensors().values()))


def test_the_global_refinement_keeps_the_map_on_the_gpu():
    slam, _ = run_system(config(**{**SUBMAPS, "refinement.enabled": True,
                                   "refinement.iterations_per_keyframe": 2}), (160, 120), 9)
    anchors = [s.anchor.clone() for s in slam.submaps]
    slam.finish()
    assert_on_cuda(**system_results(slam))
    assert slam.submaps[0].anchor.equal(anchors[0])  # the world's reference stays
