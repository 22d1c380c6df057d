"""Never lost for good: a tracker that cannot relocalise starts a new, disconnected tracking segment."""
from dataclasses import replace

import pytest
import torch

from gausem_core.config import load_config
from gausem_core.data import open_dataset
from gausem_core.geometry import make_pose
from gausem_core.pipeline import Pipeline
from gausem_core.slam.system import GauSemSLAM
from gausem_core.slam.tracker import TrackingResult

LOST_FROM, AFTER = 6, 3  # the first frame the tracker cannot place; relocalisation.new_segment_after


class Blinded:
    """The real tracker, its answers a metre off from frame ``LOST_FROM`` to the segment's start (its frames are then
    lost, and relocalisation, which tracks with it too, fails)."""

    def __init__(self, tracker):
        self.tracker, self.backend, self.blind = tracker, tracker.backend, False

    def track(self, cloud, obs, init, *args, **kwargs) -> TrackingResult:
        result = self.tracker.track(cloud, obs, init, *args, **kwargs)
        if not self.blind:
            return result
        off = make_pose(torch.eye(3, dtype=init.dtype), torch.tensor([1.0, 0.0, 0.0], dtype=init.dtype))
        return replace(result, cam_to_world=result.cam_to_world @ off.to(init.device))


@pytest.fixture(scope="module")
def segmented(tmp_path_factory):
    """The synthetic walk at 80x60: frames lost from LOST_FROM on until the segment starts, then tracked again; the
    system, its results and a session saved at the end."""
    cfg = load_config("params/synthetic.yaml", {"device": "cpu", "loop.enabled": False,
                                                 "relocalisation.new_segment_after": AFTER})
    dataset = open_dataset("synthetic", size=(80, 60), max_frames=LOST_FROM + AFTER + 5)
    pipeline = Pipeline(dataset, cfg, progress=False)
    slam = GauSemSLAM(cfg, "cpu", num_classes=len(pipeline.palette))
    slam.front_end.tracker = Blinded(slam.front_end.tracker)
    results = []
    for i in range(len(dataset)):
        slam.front_end.tracker.blind = LOST_FROM <= i < LOST_FROM + 1 + AFTER
        results.append(slam.process(pipeline.observation(dataset[i])))
    session = tmp_path_factory.mktemp("segments")
    slam.save(session)
    return slam, results, session


def test_after_failed_relocalisations_a_new_segment_starts_at_the_last_good_pose(segmented):
    slam, results, _ = segmented
    lost, start = LOST_FROM, LOST_FROM + AFTER  # the lost frame is recorded, AFTER - 1 dropped, the AFTER-th starts
    assert all(r.health.status != "lost" for r in results[:lost])
    assert results[lost].health.status == "lost" and slam.frames[lost].lost
    assert all(r.health.status == "lost" and "relocalisation_failed" in r.health.reasons
               for r in results[lost + 1:start])
    first = results[start]
    assert first.is_keyframe and first.health.status == "degraded" and first.health.reasons[-1] == "new_segment"
    new = slam.submaps[first.submap_id]
    assert new.starts_segment and new is slam.active and not any(s.starts_segment for s in slam.submaps[:-1])
    assert all(not s.is_active for s in slam.submaps[:-1])  # the old segment's submap is closed
    assert slam.back_end.segments() == [set(range(len(slam.submaps) - 1)), {new.submap_id}]
    record = slam.frames[-(len(results) - start)]
    last_good = slam.frames[lost - 1]
    assert record.skipped == AFTER - 1
    # the last good pose as it was then (the old submap's boundary adjustment has moved it by millimetres since)
    torch.testing.assert_close(record.cam_to_world, last_good.cam_to_world, atol=0.01, rtol=0)
    assert all(r.health.status != "lost" and r.submap_id == new.submap_id for r in results[start + 1:])


def test_a_saved_session_keeps_its_segments(segmented):
    slam, _, session = segmented
    loaded = GauSemSLAM.load(session, relocalise=False)
    assert [s.starts_segment for s in loaded.submaps] == [s.starts_segment for s in slam.submaps]
    assert loaded.back_end.segments() == slam.back_end.segments()
    assert loaded.back_end.segment_submaps() == [loaded.submaps[-1]]  # relocalisation looks in the active segment
