"""Tracking health: the monitor's rules on fabricated signals, the evaluation helpers, and a planted tracking
failure end to end (flagged lost, the map untouched, tracking recovers from the constant-velocity prediction, a wrong
placement is refused, a session saved while lost goes on lost)."""
import math
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from gausem_core.config import HealthConfig, TrackingConfig, load_config
from gausem_core.data import open_dataset
from gausem_core.eval.health import PlantedFailure, flag_scores, relative_errors
from gausem_core.gaussians import GaussianCloud
from gausem_core.geometry import PinholeCamera, invert_pose, make_pose, so3_exp, so3_log
from gausem_core.pipeline import Pipeline
from gausem_core.slam.direct_alignment import ModelView
from gausem_core.slam.health import SIGNALS, HealthMonitor, condition, image_signals, thresholds
from gausem_core.slam.keyframe_view import KeyframeView
from gausem_core.slam.system import GauSemSLAM
from gausem_core.slam.tracker import model_view

SLOT = 10  # the planted failure's frame
GOOD = {"inlier_fraction": 0.95, "condition": 3.0, "valid_depth": 0.9}


def at(x, yaw_deg=0.0):
    """A pose at (x, 0, 0) turned by ``yaw_deg`` about y."""
    rot = so3_exp(torch.tensor([0.0, math.radians(yaw_deg), 0.0], dtype=torch.float64))
    return make_pose(rot, torch.tensor([x, 0.0, 0.0], dtype=torch.float64))


def steady(monitor, frames=10, step=0.02, loss=0.10):
    """Frames moving ``step`` m along x with a steady loss; returns the last pose."""
    for i in range(1, frames + 1):
        health = monitor.assess(loss + 0.001 * (i % 3), GOOD, at(i * step), at((i - 1) * step), at(i * step))
        assert health.status == "ok", health
    return frames * step


def test_image_signals_decide_lost_and_degraded():
    monitor = HealthMonitor(HealthConfig())
    assert monitor.assess(0.1, GOOD, at(0), None, None).status == "ok"
    degraded = monitor.assess(0.1, dict(GOOD, inlier_fraction=0.5), at(0), None, None)
    assert degraded.status == "degraded" and degraded.reasons == ("inlier_fraction",)
    lost = monitor.assess(0.1, dict(GOOD, inlier_fraction=0.1, valid_depth=0.01), at(0), None, None)
    assert lost.status == "lost" and set(lost.reasons) == {"inlier_fraction", "valid_depth"}
    assert monitor.assess(0.1, dict(GOOD, valid_depth=0.2), at(0), None, None).status == "degraded"
    assert monitor.assess(0.1, dict(GOOD, condition=9.0), at(0), None, None).reasons == ("condition",)
    assert monitor.assess(0.1, dict(GOOD, condition=math.inf), at(0), None, None).status == "degraded"
    little_map = monitor.assess(0.1, dict(GOOD, coverage=0.2), at(0), None, None)
    assert little_map.status == "degraded" and little_map.reasons == ("coverage",) and little_map.coverage == 0.2


def test_every_level_threshold_of_the_config_is_in_the_table_under_its_own_field():
    """Each ``degraded_*`` / ``lost_*`` field of HealthConfig is read, for its own level and signal: a field the table
    missed, or read under another name, would silently turn its check off."""
    fields = {name for name in vars(HealthConfig()) if name.startswith(("degraded_", "lost_"))}
    assert len(fields) == 10
    for name in fields:
        level, signal = name.split("_", 1)
        assert signal in SIGNALS
        cfg = replace(HealthConfig(), **{name: 12345.0})
        assert thresholds(cfg)[level][signal] == 12345.0
    assert sum(len(limits) for limits in thresholds(HealthConfig()).values()) == len(fields)


def test_image_signals_measure_the_map_in_view_and_the_share_it_explains():
    camera = PinholeCamera(8.0, 8.0, 5.0, 4.0, 10, 8)
    depth = torch.full((8, 10), 2.0)
    mask = torch.zeros(8, 10, dtype=torch.bool)
    mask[:, :4] = True  # the map covers 32 of 80 pixels
    rendered = depth.clone()
    rendered[:2, :4] += 0.5  # 8 of them disagree with the observed depth
    rgb = torch.zeros(8, 10, 3)
    view = ModelView(rgb, rgb, rendered, mask, camera)
    obs = SimpleNamespace(valid_depth=torch.ones(8, 10, dtype=torch.bool), depth=depth, rgb=rgb, camera=camera)
    signals = image_signals(view, obs, None, HealthConfig())
    assert signals["coverage"] == pytest.approx(0.4) and signals["inlier_fraction"] == pytest.approx(24 / 32)
    assert signals["valid_depth"] == 1.0 and signals["condition"] == math.inf
    # the same view moved a pixel to the right (0.25 m at 2 m): all 32 land, each on the observed pixel one column on
    shifted = image_signals(view, obs, None, HealthConfig(), make_pose(torch.eye(3), torch.tensor([0.25, 0.0, 0.0])))
    assert shifted["coverage"] == pytest.approx(0.4) and shifted["inlier_fraction"] == pytest.approx(24 / 32)
    beside = image_signals(view, obs, None, HealthConfig(), make_pose(torch.eye(3), torch.tensor([-0.5, 0.0, 0.0])))
    assert beside["coverage"] == pytest.approx(16 / 80)  # two columns of four leave the image
    assert beside["inlier_fraction"] == pytest.approx(12 / 16)


def test_coverage_counts_what_tracking_aligns_against_the_newest_keyframes_pixels_too():
    """A map grown but not optimised yet (one layer of Gaussians at opacity 0.9) renders no pixel above the 0.99
    silhouette that tracking compares: without the keyframe fill nothing covers the view; with it (async mode),
    tracking aligns against the newest keyframe's own pixels there, and coverage counts them."""
    camera = PinholeCamera(20.0, 20.0, 10.0, 8.0, 20, 16)
    xs, ys = torch.meshgrid(torch.linspace(-0.4, 0.0, 9), torch.linspace(-0.5, 0.5, 11), indexing="xy")
    means = torch.stack([xs.reshape(-1), ys.reshape(-1), torch.full((99,), 1.0)], 1)  # the left half, 1 m ahead
    grey = torch.full((99, 3), 0.5)
    cloud = GaussianCloud.from_points(means, grey, grey, torch.full((99,), 0.04), opacity=0.9)
    depth = torch.ones(16, 20)
    depth[:, 15:] = 0  # the keyframe has no depth on the right quarter: nothing to fill there
    obs = SimpleNamespace(valid_depth=depth > 0, depth=depth, rgb=torch.full((16, 20, 3), 0.5),
                          semantic=torch.zeros(16, 20, 3), camera=camera)
    bare = model_view(cloud, torch.eye(4), camera, TrackingConfig(), "torch")
    assert not bare.mask.any() and image_signals(bare, obs, None, HealthConfig())["coverage"] == 0.0
    filled = model_view(cloud, torch.eye(4), camera, TrackingConfig(), "torch", KeyframeView.of(obs, torch.eye(4)))
    assert image_signals(filled, obs, None, HealthConfig())["coverage"] == pytest.approx(0.75)


def test_residual_is_judged_against_its_recent_distribution_not_its_level():
    monitor = HealthMonitor(HealthConfig())
    x = steady(monitor)
    spike = monitor.assess(0.2, GOOD, at(x + 0.02), at(x), at(x + 0.02))
    assert spike.status == "degraded" and spike.reasons == ("residual_z",) and spike.residual_z > 5
    drifting = HealthMonitor(HealthConfig())  # a loss that climbs slowly over the run stays ok
    for i in range(1, 60):
        health = drifting.assess(0.1 * 1.01 ** i, GOOD, at(0.02 * i), at(0.02 * (i - 1)), at(0.02 * i))
        assert health.status == "ok", (i, health)


def test_pose_jump_is_scaled_by_recent_motion():
    monitor = HealthMonitor(HealthConfig())
    x = steady(monitor, step=0.02)  # 2 cm per frame
    predicted = at(x + 0.02)
    small = monitor.assess(0.1, GOOD, at(x + 0.05), at(x), predicted)  # 3 cm off: 1.5 typical motions
    assert small.status == "ok" and small.jump == pytest.approx(1.5)
    x += 0.05
    jumped = monitor.assess(0.1, GOOD, at(x + 0.02 + 0.15), at(x), at(x + 0.02))  # 7.5 typical motions
    assert jumped.status == "degraded" and jumped.reasons == ("jump",)
    turned = monitor.assess(0.1, GOOD, at(x + 0.02, yaw_deg=20.0), at(x), at(x + 0.02))  # 20 deg >> 1 deg floor
    assert turned.status == "lost" and turned.reasons == ("jump",) and turned.jump == pytest.approx(20.0)


def test_lost_frames_do_not_teach_the_monitor_and_reset_forgets_the_motion():
    monitor = HealthMonitor(HealthConfig())
    x = steady(monitor)
    residuals, motions = list(monitor.residuals), list(monitor.motions)
    lost = monitor.assess(5.0, dict(GOOD, inlier_fraction=0.0), at(x + 3.0), at(x), at(x + 0.02))
    assert lost.status == "lost"
    assert list(monitor.residuals) == residuals and list(monitor.motions) == motions
    monitor.reset()
    assert not monitor.motions and list(monitor.residuals) == residuals
    assert monitor.assess(0.1, GOOD, at(x + 1.0), at(x), at(x + 0.02)).jump == 0.0  # no motion history yet


def test_condition_is_scale_aware_and_infinite_when_degenerate():
    depth = torch.full((100,), 2.0)
    h = torch.diag(torch.tensor([0.25, 0.25, 0.25, 1.0, 1.0, 1.0], dtype=torch.float64))
    assert condition(h, depth) == pytest.approx(0.0, abs=1e-9)  # translation scaled by the 2 m depth
    h[0, 0] = 0.0
    assert condition(h, depth) == math.inf and condition(None, depth) == math.inf


def test_relative_errors_and_flag_scores():
    truths = np.stack([np.eye(4)] * 4)
    truths[:, 0, 3] = [0.0, 0.1, 0.2, 0.3]
    poses = truths.copy()
    poses[2, 0, 3] += 0.05
    translation, rotation = relative_errors(poses, truths)
    assert translation == pytest.approx([0.0, 0.0, 0.05, 0.05]) and rotation == pytest.approx([0, 0, 0, 0])
    errors = np.arange(100.0)
    flagged = np.zeros(100, bool)
    flagged[[99, 98, 10]] = True
    scores = flag_scores(errors, flagged)
    assert scores["worst_1%_flagged"] == 1.0 and scores["worst_5%_flagged"] == pytest.approx(0.4)
    assert scores["false_flag_rate"] == pytest.approx(1 / 95)


def test_monitor_state_round_trips_and_judging_learns_nothing():
    monitor = HealthMonitor(HealthConfig())
    x = steady(monitor)
    state = monitor.state_dict()
    judged = monitor.judge(0.5, GOOD, at(x + 0.02), at(x + 0.02))
    assert judged.status == "degraded" and monitor.state_dict() == state
    restored = HealthMonitor(HealthConfig())
    restored.load_state_dict(state)
    assert restored.state_dict() == state and restored.judge(0.5, GOOD, at(x + 0.02), at(x + 0.02)) == judged
    short = HealthMonitor(HealthConfig(window=4))
    short.load_state_dict(state)
    assert short.state_dict() == {name: values[-4:] for name, values in state.items()}


@pytest.fixture(scope="module")
def planted_run(tmp_path_factory):
    """GauSemSLAM over the first 18 synthetic frames at 160x120 with frame 30's images at frame 10's slot (a
    keyframe); the active submap's Gaussians and keyframe count just before and just after frame 10, the results,
    the observations, and a session saved just after frame 10."""
    cfg = load_config("params/synthetic.yaml", {"device": "cpu", "loop.enabled": False})
    dataset = PlantedFailure(open_dataset("synthetic", size=(160, 120), max_frames=31), SLOT, 30)
    pipeline = Pipeline(dataset, cfg, progress=False)
    slam = GauSemSLAM(cfg, "cpu", num_classes=len(pipeline.palette))
    observations = [pipeline.observation(dataset[i]) for i in range(18)]
    results, before, session = [], None, tmp_path_factory.mktemp("lost_session")
    for i, obs in enumerate(observations):
        if i == SLOT:
            before = ({k: v.clone() for k, v in slam.active.cloud.tensors().items()}, len(slam.active.keyframes))
        results.append(slam.process(obs))
        if i == SLOT:
            after = ({k: v.clone() for k, v in slam.active.cloud.tensors().items()}, len(slam.active.keyframes),
                     slam.lost)
            slam.save(session)
    origin = np.linalg.inv(dataset[0].gt_pose)
    truths = [torch.tensor(origin @ dataset[i].gt_pose, dtype=torch.float32) for i in range(18)]
    return slam, results, truths, before, after, observations, session


@pytest.mark.slow
def test_a_swapped_in_frame_is_lost_leaves_the_map_alone_and_the_next_is_relocalised(planted_run):
    slam, results, truths, (cloud, keyframes), (cloud_after, keyframes_after, lost_after), _, _ = planted_run
    assert [r.health.status for r in results[:SLOT]].count("lost") == 0
    swapped = results[SLOT]
    assert swapped.health.status == "lost" and lost_after and not swapped.is_keyframe
    assert keyframes_after == keyframes and cloud.keys() == cloud_after.keys()
    assert all(torch.equal(cloud[k], cloud_after[k]) for k in cloud)  # the map is untouched by the lost frame
    relocalised = results[SLOT + 1].relocalisation
    assert relocalised is not None and relocalised.accepted
    # the features' and the motion model's starts reach the same pose (the frame after the lost one); either wins
    assert relocalised.start in ("features", "constant velocity")
    recovered = results[SLOT + 1].health  # the signals find it fine, but it was not tracked from the frame before
    assert recovered.status == "degraded" and recovered.reasons == ("relocalised",)
    assert recovered.residual_z == relocalised.health.residual_z and recovered.inlier_fraction > 0.9
    assert not slam.lost and all(r.relocalisation is None for r in results[SLOT + 2:])
    assert all(r.health.status != "lost" for r in results[SLOT + 1:])


@pytest.mark.slow
def test_after_a_planted_failure_tracking_resumes_with_small_error(planted_run):
    _, results, truths, _, _, _, _ = planted_run
    for result, truth in zip(results[SLOT + 1:], truths[SLOT + 1:]):  # from the relocalised frame on
        delta = invert_pose(result.cam_to_world) @ truth
        assert delta[:3, 3].norm() < 0.02 and math.degrees(float(so3_log(delta[:3, :3]).norm())) < 1.0


@pytest.mark.slow
def test_a_placement_far_off_after_a_loss_is_refused(planted_run):
    """Without the constant-velocity and feature starts, the frame after the loss is best placed from the last good
    pose, ~23 cm off: enough inliers for the recovery threshold, but its residual is far outside the frames' before
    the loss."""
    slam, _, truths, _, _, observations, session = planted_run
    tracking = slam.cfg.tracking
    cfg = replace(slam.cfg, tracking=replace(tracking, constant_velocity=False,
                                             feature_start=replace(tracking.feature_start, mode="never")))
    loaded = GauSemSLAM.load(session, cfg=cfg, relocalise=False)
    placed = loaded.relocalise(observations[SLOT + 1])
    error = invert_pose(placed.cam_to_world) @ truths[SLOT + 1]
    assert float(error[:3, 3].norm()) > 0.1
    assert placed.inlier_fraction >= loaded.cfg.health.recovery_inlier_fraction
    assert not placed.accepted and placed.health.residual_z > loaded.cfg.health.recovery_residual_z


@pytest.mark.slow
def test_a_session_saved_while_lost_goes_on_as_the_original(planted_run):
    slam, results, _, _, _, observations, session = planted_run
    loaded = GauSemSLAM.load(session, relocalise=False)
    assert loaded.lost and loaded.frames[SLOT].lost and not any(f.lost for f in loaded.frames[:SLOT])
    assert loaded.front_end.health.state_dict()["residuals"] and loaded.front_end.health.state_dict()["motions"]
    resumed = loaded.process(observations[SLOT + 1])
    original = results[SLOT + 1]
    assert torch.equal(resumed.cam_to_world, original.cam_to_world) and resumed.health == original.health
    assert resumed.relocalisation.start == original.relocalisation.start and not loaded.lost
