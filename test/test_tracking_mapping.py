"""Tracker (Eq. 2) and mapper (Eq. 3-4) on real synthetic frames: known motions are recovered, mapping lowers loss."""
import dataclasses

import numpy as np
import pytest
import torch

from gausem_core.config import SlamConfig, load_config
from gausem_core.data import open_dataset
from gausem_core.data.sensor import vignetting
from gausem_core.geometry import invert_pose, project_to_se3, se3_exp, so3_log
from gausem_core.pipeline import Pipeline
from gausem_core.render import render
from gausem_core.slam.densification import semantic_sample
from gausem_core.slam.mapper import Keyframe, Mapper
from gausem_core.slam.health import image_signals
from gausem_core.slam.tracker import Tracker, constant_velocity, inspect_pose, repeat_motion
from gausem_core.options import default_params_file


def map_and_frames(cfg: SlamConfig, size: tuple[int, int], backend: str):
    """A map made from synthetic frame 0 (``mapping.init_iterations``), frames 0-2 as observations with ground truth
    relative to frame 0, and the mapping losses."""
    dataset = open_dataset("synthetic", size=size, max_frames=3)
    pipeline = Pipeline(dataset, cfg, progress=False)
    observations = [pipeline.observation(dataset[i]) for i in range(3)]
    origin = np.linalg.inv(dataset[0].gt_pose)
    truths = [torch.tensor(origin @ dataset[i].gt_pose, dtype=torch.float32) for i in range(3)]
    mapper = Mapper(cfg.mapping, backend, seed=0)
    keyframe = Keyframe(0, observations[0], torch.eye(4), fixed=True)
    initial = mapper.strategy.initial(observations[0], torch.eye(4))
    cloud, losses = mapper.optimise(initial, [keyframe], cfg.mapping.init_iterations)
    return cloud, observations, truths, losses


def tracked_errors(tracker: Tracker, cloud, observations, truths) -> list[tuple[float, float, float]]:
    """(translation error, rotation error in degrees, true translation) of frames 1 and 2, each tracked from the
    constant-velocity prediction."""
    poses, errors = [torch.eye(4)], []
    for k in (1, 2):
        init = constant_velocity(poses[-1], poses[-2] if len(poses) > 1 else None)
        poses.append(tracker.track(cloud, observations[k], init).cam_to_world)
        errors.append((*pose_error(poses[-1], truths[k]), float((truths[k][:3, 3] - truths[k - 1][:3, 3]).norm())))
    return errors


@pytest.fixture(scope="module")
def scene():
    """A map made from synthetic frame 0 at 80x60 and the next frames as observations with ground truth."""
    cfg = SlamConfig(device="cpu")
    cfg.mapping.init_iterations = 60
    cloud, observations, truths, losses = map_and_frames(cfg, (80, 60), "torch")
    return cfg, cloud, observations, truths, losses


def pose_error(estimate, truth):
    delta = invert_pose(estimate) @ truth
    return delta[:3, 3].norm().item(), float(np.degrees(so3_log(delta[:3, :3]).norm().item()))


def test_mapping_lowers_the_loss_and_covers_the_view(scene):
    _, cloud, observations, _, losses = scene
    assert np.mean(losses[-5:]) < 0.5 * np.mean(losses[:5])
    out = render(cloud, torch.eye(4), observations[0].camera, backend="torch")
    assert (out.alpha > 0.99).float().mean() > 0.95
    valid = observations[0].valid_depth
    assert (out.expected_depth - observations[0].depth)[valid].abs().mean() < 0.005  # metres: no depth bias


@pytest.mark.parametrize("method", ["gauss_newton", "adam"])
def test_tracker_recovers_a_perturbed_pose_of_the_mapped_frame(scene, method):
    cfg, cloud, observations, truths, _ = scene
    tracking = dataclasses.replace(cfg.tracking, method=method)
    start = se3_exp(torch.tensor([0.01, -0.008, 0.006, 0.004, -0.006, 0.003])) @ truths[0]
    before = pose_error(start, truths[0])
    result = Tracker(tracking, "torch").track(cloud, observations[0], start)
    translation, rotation = pose_error(result.cam_to_world, truths[0])
    assert translation < before[0] and rotation < before[1]
    if method == "gauss_newton":
        assert translation < 0.002 and rotation < 0.2


def test_tracker_follows_the_next_frames_with_constant_velocity(scene):
    cfg, cloud, observations, truths, _ = scene
    for translation, rotation, motion in tracked_errors(Tracker(cfg.tracking, "torch"), cloud, observations, truths):
        assert translation < 0.25 * motion and rotation < 0.5, (translation, rotation, motion)


@pytest.mark.slow
def test_the_first_frames_at_320x240_are_tracked_as_well_as_at_160x120():
    """The shipped parameters (tuned at 160x120) at twice the size: the pyramid gets a level more, so its coarsest
    level sees the first frames' motion (about 3 cm, 5 pixels at 320x240) in as few pixels; with the 160x120 level
    count the first frame came out 13.6 cm off (measured)."""
    cfg = load_config(default_params_file("synthetic"), {"device": "cpu"})
    cloud, observations, truths, _ = map_and_frames(cfg, (320, 240), "cpu")
    for translation, rotation, motion in tracked_errors(Tracker(cfg.tracking, "cpu"), cloud, observations, truths):
        assert translation < 0.1 * motion and rotation < 0.2, (translation, rotation, motion)


def test_gauss_newton_tracking_on_local_contrast_is_not_pulled_by_vignetting_and_gains(scene):
    """Map and frames all darkened to 75 % in the corners, the tracked frame with other exposure and white-balance
    gains than the mapped one: on raw colour a surface's brightness changes as it moves across the image, which
    pulls the estimate towards no motion; colour over its local mean is blind to that."""
    cfg, _, observations, truths, _ = scene
    falloff = torch.from_numpy(vignetting(observations[0].camera, 0.75)).to(torch.float32)[..., None]
    mapped = dataclasses.replace(observations[0], rgb=observations[0].rgb * falloff)
    seen = dataclasses.replace(observations[2], rgb=(observations[2].rgb * falloff * torch.tensor([1.0, 1.2, 1.4]))
                               .clamp(0, 1))
    mapper = Mapper(cfg.mapping, "torch", seed=0)
    cloud, _ = mapper.optimise(mapper.strategy.initial(mapped, torch.eye(4)), [Keyframe(0, mapped, torch.eye(4), fixed=True)],
                               cfg.mapping.init_iterations)
    motion = float((truths[2][:3, 3] - truths[0][:3, 3]).norm())
    width = cfg.tracking.gauss_newton.color_normalisation_width
    assert width > 0  # on by default

    def normalised(w: float):
        return dataclasses.replace(cfg.tracking, gauss_newton=dataclasses.replace(cfg.tracking.gauss_newton,
                                                                                  color_normalisation_width=w))

    errors = {w: pose_error(Tracker(normalised(w), "torch").track(cloud, seen, truths[0]).cam_to_world, truths[2])
              for w in (0.0, width)}
    assert errors[width][0] < 0.1 * motion and errors[width][1] < 0.25, errors
    # measured (translation, rotation) over raw colour: 0.82 and 0.42 (per_frame, checkerboard), 0.70 and 0.47 per_level
    assert errors[width][0] < 0.9 * errors[0.0][0] and errors[width][1] < 0.5 * errors[0.0][1], errors


def test_constant_velocity_repeats_the_last_motion_and_stays_rigid():
    a = se3_exp(torch.tensor([0.1, 0.0, 0.02, 0.0, 0.05, 0.0]))
    b = a @ se3_exp(torch.tensor([0.03, 0.01, 0.0, 0.01, 0.0, 0.02]))
    c = constant_velocity(b, a)
    assert torch.allclose(invert_pose(b) @ c, invert_pose(a) @ b, atol=1e-5)
    assert torch.allclose(c[:3, :3] @ c[:3, :3].T, torch.eye(3), atol=1e-6)
    assert torch.equal(constant_velocity(b, None), b)


def test_repeat_motion_moves_on_step_by_step():
    start = se3_exp(torch.tensor([0.1, 0.0, 0.02, 0.0, 0.05, 0.0]))
    step = se3_exp(torch.tensor([0.03, 0.01, 0.0, 0.01, 0.0, 0.02]))
    three = repeat_motion(start, step, 3)
    assert torch.allclose(three, start @ se3_exp(3 * torch.tensor([0.03, 0.01, 0.0, 0.01, 0.0, 0.02])), atol=1e-5)
    assert torch.allclose(repeat_motion(start, step), start @ step, atol=1e-6)
    half = repeat_motion(start, step, 0.5)  # half the screw motion: twice that is one step
    assert torch.allclose(repeat_motion(start, invert_pose(start) @ half, 2.0), start @ step, atol=1e-5)
    assert torch.allclose(repeat_motion(start, step, 2.5),
                          start @ se3_exp(2.5 * torch.tensor([0.03, 0.01, 0.0, 0.01, 0.0, 0.02])), atol=1e-5)
    with pytest.raises(ValueError, match="steps"):
        repeat_motion(start, step, 0)


def test_project_to_se3_repairs_a_drifted_rotation():
    pose = se3_exp(torch.tensor([0.2, -0.1, 0.3, 0.3, 0.2, -0.1]))
    drifted = pose.clone()
    drifted[:3, :3] *= 1.001
    fixed = project_to_se3(drifted)
    assert torch.allclose(fixed[:3, :3] @ fixed[:3, :3].T, torch.eye(3), atol=1e-6)
    assert torch.allclose(fixed, pose, atol=1e-3) and torch.equal(fixed[:3, 3], pose[:3, 3])


def test_semantic_sampling_follows_the_area_power_law():
    labels = torch.zeros(40, 50, dtype=torch.long)
    labels[:, 40:] = 1  # class 0: 1600 px, class 1: 400 px
    valid = torch.ones_like(labels, dtype=torch.bool)
    picked = semantic_sample(labels, valid, 300, 0.5, torch.Generator().manual_seed(0))
    counts = torch.bincount(labels.reshape(-1)[picked], minlength=2)
    assert counts.tolist() == [200, 100]  # floor(300 * sqrt(A_c) / (40 + 20))
    assert len(torch.unique(picked)) == len(picked)


def test_mapping_loss_is_eq3_with_the_eq4_ssim_losses_of_colour_and_semantics():
    from gausem_core.eval.image import ssim
    from gausem_core.render import RenderOutput
    from gausem_core.slam.losses import mapping_loss
    from gausem_core.slam.observation import Observation

    g = torch.Generator().manual_seed(3)
    h, w = 14, 11
    out = RenderOutput(torch.rand(h, w, 3, generator=g, dtype=torch.float64),
                       torch.rand(h, w, generator=g, dtype=torch.float64),
                       torch.rand(h, w, 3, generator=g, dtype=torch.float64),
                       0.5 + 0.5 * torch.rand(h, w, generator=g, dtype=torch.float64))
    obs = Observation(rgb=torch.rand(h, w, 3, generator=g, dtype=torch.float64),
                      depth=torch.rand(h, w, generator=g, dtype=torch.float64) * (torch.rand(h, w, generator=g) > 0.3),
                      semantic=torch.rand(h, w, 3, generator=g, dtype=torch.float64),
                      labels=torch.zeros(h, w, dtype=torch.long), camera=None, timestamp=0.0)

    def eq4(rendered, target, lam):
        return lam * (rendered - target).abs().mean() + (1 - lam) * (1 - ssim(rendered, target))

    valid = obs.depth > 0
    depth = (out.expected_depth - obs.depth).abs()[valid].mean() + (1 - out.alpha)[valid].mean()
    expected = 2.0 * depth + 1.5 * eq4(out.color, obs.rgb, 0.8) + 0.25 * eq4(out.semantic, obs.semantic, 0.8)
    assert mapping_loss(out, obs, 1.5, 2.0, 0.25, 0.8).item() == pytest.approx(expected.item(), rel=1e-12)


def test_the_motion_model_predicts_across_skipped_frames_by_their_timestamps():
    """A live node that falls behind skips frames: the constant-velocity prediction for the next one it processes
    repeats the last motion over the time elapsed, not once; without increasing stamps it counts frames. Frames 1-3
    are recorded at their true poses (the motion model alone, not the tracker, is under test)."""
    from gausem_core.slam.submap import FrameRecord
    from gausem_core.slam.system import GauSemSLAM

    cfg = load_config("params/synthetic.yaml", {"device": "cpu", "loop.enabled": False, "mapping.init_iterations": 5})
    dataset = open_dataset("synthetic", size=(40, 30), max_frames=12)
    pipeline = Pipeline(dataset, cfg, progress=False)
    slam = GauSemSLAM(cfg, "cpu", num_classes=len(pipeline.palette))
    slam.process(pipeline.observation(dataset[0]))
    origin = np.linalg.inv(dataset[0].gt_pose)

    def truth(i):
        return torch.tensor(origin @ dataset[i].gt_pose, dtype=torch.float32)
    keyframe = slam.active.keyframes[0]
    for i in range(1, 4):
        slam.frames.append(FrameRecord(i, dataset[i].timestamp, slam.active, keyframe,
                                       invert_pose(keyframe.cam_to_world) @ truth(i)))
    skipped = slam.front_end.motion_model(dataset[10].timestamp)  # frames 4-9 skipped
    once = constant_velocity(truth(3), truth(2))

    def error(pose):
        return float((invert_pose(pose.double()) @ truth(10).double())[:3, 3].norm())
    assert error(skipped.predicted) < 0.3 * error(once) and skipped.gap  # a gap: the tracker searches around it
    jittered = dataset[3].timestamp + 1.3 * (dataset[3].timestamp - dataset[2].timestamp)  # stamp jitter, no gap
    for stamp in (jittered, dataset[3].timestamp):  # ... and no time elapsed: one frame on, by the count
        motion = slam.front_end.motion_model(stamp)
        assert torch.allclose(motion.predicted, once, atol=1e-5) and motion.steps == 1 and not motion.gap


def test_the_motion_model_counts_the_frames_a_caller_skipped():
    """A node steadily four times slower than its camera: the stamps alone show no gap (every interval alike), the
    skipped frames it passes on do; the prediction repeats the latest motion once per the camera frames that motion
    spanned. The count goes into the frame's record."""
    from gausem_core.slam.submap import FrameRecord
    from gausem_core.slam.system import GauSemSLAM

    # a 40x30 map of 5 iterations renders views with no silhouette pixel: every frame would be lost by coverage
    cfg = load_config("params/synthetic.yaml", {"device": "cpu", "loop.enabled": False, "mapping.init_iterations": 5,
                                                "health.lost_coverage": 0.0})
    dataset = open_dataset("synthetic", size=(40, 30), max_frames=17)
    pipeline = Pipeline(dataset, cfg, progress=False)
    slam = GauSemSLAM(cfg, "cpu", num_classes=len(pipeline.palette))
    slam.process(pipeline.observation(dataset[0]), skipped=5)
    assert slam.front_end.skipped == 0 and slam.frames[0].skipped == 0
    origin = np.linalg.inv(dataset[0].gt_pose)
    keyframe = slam.active.keyframes[0]
    for i in (4, 8):
        truth = torch.tensor(origin @ dataset[i].gt_pose, dtype=torch.float32)
        slam.frames.append(FrameRecord(i, dataset[i].timestamp, slam.active, keyframe,
                                       invert_pose(keyframe.cam_to_world) @ truth, skipped=3))
    slam.front_end.skipped = 3
    told = slam.front_end.motion_model(dataset[12].timestamp)
    assert told.gap and told.steps == pytest.approx(1.0, abs=0.1)
    slam.front_end.skipped = 5  # six camera frames on, the pair spanned four
    assert slam.front_end.motion_model(dataset[14].timestamp).steps == pytest.approx(1.5)
    for record in slam.frames:
        record.skipped = 0
    slam.front_end.skipped = 0
    unknown = slam.front_end.motion_model(dataset[12].timestamp)
    assert not unknown.gap and unknown.steps == 1 and torch.allclose(told.predicted, unknown.predicted, atol=1e-3)
    with pytest.raises(ValueError, match="skipped must be >= 0"):
        slam.process(pipeline.observation(dataset[12]), skipped=-1)
    result = slam.process(pipeline.observation(dataset[16]), skipped=7)
    assert result.health.status != "lost" and slam.front_end.skipped == 0 and slam.frames[-1].skipped == 7
    assert result.is_keyframe  # after that gap the map covers too little of the view


def test_the_search_starts_surround_the_start_and_an_unknown_mode_is_rejected():
    cfg = dataclasses.replace(SlamConfig().tracking, gauss_newton=dataclasses.replace(
        SlamConfig().tracking.gauss_newton, search_translation=0.04, search_rotation_deg=2.0))
    pose = se3_exp(torch.tensor([0.3, -0.1, 0.2, 0.1, 0.4, -0.2], dtype=torch.float64))
    offsets = [invert_pose(pose) @ start for start in Tracker(cfg)._search_starts(pose)]
    moves = [float(offset[:3, 3].norm()) for offset in offsets]
    turns = [float(so3_log(offset[:3, :3]).norm()) for offset in offsets]
    assert len(offsets) == 12 and np.allclose(moves[:6], 0.04) and np.allclose(turns[6:], np.radians(2.0))
    assert np.allclose(turns[:6], 0) and np.allclose(sum(o[:3, 3] for o in offsets[:6]), 0)  # both ways each axis
    no_turns = dataclasses.replace(cfg, gauss_newton=dataclasses.replace(cfg.gauss_newton, search_rotation_deg=0.0))
    assert len(Tracker(no_turns)._search_starts(pose)) == 6
    with pytest.raises(ValueError, match="tracking.gauss_newton.search must be one of"):
        Tracker(dataclasses.replace(cfg, gauss_newton=dataclasses.replace(cfg.gauss_newton, search="sometimes")))


def test_the_feature_start_places_a_frame_that_moved_beyond_the_dense_basin():
    """Six frames of the synthetic loop apart (a node at 5 Hz on a 30 Hz camera), ORB matches with the last good
    frame and PnP on its depth put the frame within a few centimetres; without a remembered frame, or when the
    images share no features, there is no start."""
    from gausem_core.config import FeatureStartConfig
    from gausem_core.slam.feature_start import FeatureStart
    from loop_scene import frame

    (reference, reference_pose), (current, current_pose) = frame(120), frame(126)
    start = FeatureStart(FeatureStartConfig(mode="always"))
    assert start.predict(current, reference_pose) is None  # nothing remembered yet
    start.remember(reference)
    predicted = start.predict(current, reference_pose)
    moved, _ = pose_error(reference_pose, current_pose)
    assert predicted is not None and predicted.dtype == reference_pose.dtype
    translation, rotation = pose_error(predicted, current_pose)
    assert moved > 0.15 and translation < 0.04 and rotation < 1.5
    blank = dataclasses.replace(current, rgb=torch.full_like(current.rgb, 0.5))
    assert start.predict(blank, reference_pose) is None
    assert start.wanted(gap=False) and not FeatureStart(FeatureStartConfig(mode="gaps")).wanted(gap=False)
    with pytest.raises(ValueError, match="tracking.feature_start.mode must be one of"):
        FeatureStart(FeatureStartConfig(mode="sometimes"))


def test_frames_the_map_covers_too_little_of_are_mapped_as_keyframes():
    """A camera outrunning its map (every 3rd frame of the walk): with ``mapping.coverage_keyframes: gaps`` a frame
    after skipped frames is a keyframe wherever the map covers less of its view than ``mapping.min_coverage``; without
    the skipped frames counted (the stamps alike) or with the mode off, only every N-th frame is one."""
    from gausem_core.slam.system import GauSemSLAM

    dataset = open_dataset("synthetic", size=(64, 48), max_frames=22)
    for mode, skipped in (("never", 2), ("gaps", 0), ("gaps", 2)):
        cfg = load_config("params/synthetic.yaml", {"device": "cpu", "loop.enabled": False, "refinement.enabled": False,
                                                    "mapping.init_iterations": 40, "mapping.iterations": 5,
                                                    "mapping.every": 100, "mapping.min_coverage": 0.6,
                                                    "mapping.coverage_keyframes": mode})
        pipeline = Pipeline(dataset, cfg, progress=False)
        slam = GauSemSLAM(cfg, "cpu", num_classes=len(pipeline.palette))
        results = [slam.process(pipeline.observation(dataset[i]), skipped if i else 0) for i in range(0, 22, 3)]
        keyframes = [r.frame_id for r in results if r.is_keyframe]
        assert keyframes == sorted(kf.frame_id for s in slam.submaps for kf in s.keyframes)
        if mode == "never" or not skipped:
            assert keyframes == [0], (mode, skipped)
            continue
        assert len(keyframes) > 1
        for r in results[1:]:
            assert r.is_keyframe == (r.health.status != "lost" and r.health.coverage < 0.6), r.health
    with pytest.raises(ValueError, match="mapping.coverage_keyframes must be one of"):
        GauSemSLAM(dataclasses.replace(cfg, mapping=dataclasses.replace(cfg.mapping, coverage_keyframes="often")))


@pytest.mark.parametrize("mode", ["gaps", "never"])
def test_a_segments_second_frame_gets_the_gap_measures(mode):
    """Without a motion model yet (the frame after the map's first) the motion since the last good frame is unknown,
    as after a gap: with the gap measures (the search around the start, the feature start) the walk's 3.2 cm step is
    found; without them the start from the first frame's pose fell 2.4 cm short of it (160x120, shipped parameters,
    the tracker that renders the model per level: one model view per frame found the step without them, 4.1 mm)."""
    from gausem_core.slam.system import GauSemSLAM

    cfg = load_config("params/synthetic.yaml", {"device": "cpu", "loop.enabled": False,
                                                "tracking.feature_start.mode": mode,
                                                "tracking.gauss_newton.search": mode,
                                                "tracking.gauss_newton.model_views": "per_level"})
    dataset = open_dataset("synthetic", size=(160, 120), max_frames=2)
    pipeline = Pipeline(dataset, cfg, progress=False)
    slam = GauSemSLAM(cfg, "cpu", num_classes=len(pipeline.palette))
    slam.process(pipeline.observation(dataset[0]))
    tracked = slam.process(pipeline.observation(dataset[1])).cam_to_world
    truth = torch.tensor(np.linalg.inv(dataset[0].gt_pose) @ dataset[1].gt_pose, dtype=torch.float32)
    translation, _ = pose_error(tracked.cpu(), truth)
    assert (translation < 0.005) == (mode == "gaps"), translation


def test_the_search_starts_only_where_the_feature_start_finds_no_pose(monkeypatch):
    """After a gap the feature start goes first; the blind search around the prediction (a dozen more coarse
    alignments) is tried only where it finds no pose. Lock-step frames with a motion model get neither."""
    from gausem_core.slam.system import GauSemSLAM
    from gausem_core.slam.tracker import TrackingResult

    cfg = load_config("params/synthetic.yaml", {"device": "cpu", "loop.enabled": False, "mapping.init_iterations": 5,
                                                "mapping.iterations": 2, "health.lost_coverage": 0.0})  # thin map
    dataset = open_dataset("synthetic", size=(40, 30), max_frames=12)
    pipeline = Pipeline(dataset, cfg, progress=False)
    slam = GauSemSLAM(cfg, "cpu", num_classes=len(pipeline.palette))
    calls = []

    class Recording:
        def track(self, cloud, obs, init_cam_to_world, alternatives=(), search=False, keyframe=None):
            calls.append((len(alternatives), search))
            return TrackingResult(init_cam_to_world, 0.0, 0)
    slam.front_end.tracker = Recording()
    features = {"pose": None}
    monkeypatch.setattr(slam.front_end.feature_start, "predict", lambda obs, previous: features["pose"])
    slam.process(pipeline.observation(dataset[0]))
    for i, skipped, found in ((1, 0, False), (2, 0, False), (3, 0, False), (6, 2, True), (9, 2, False)):
        features["pose"] = torch.eye(4) if found else None
        slam.process(pipeline.observation(dataset[i]), skipped)
    # frame 1: no motion model (no features here: searched); 2, 3: lock-step; 6: features found; 9: none found
    assert calls == [(0, True), (1, False), (1, False), (2, False), (1, True)]


def test_one_model_view_per_frame_recovers_the_motion_with_a_render_or_two(scene, monkeypatch):
    """tracking.gauss_newton.model_views per_frame: the map rendered once at the start, its pyramid downsampled from
    it, rendered again only when the estimate moved rerender_motion: frames 1 and 2 come out as well as with a
    render per level and round, in far fewer renders, with all the full-resolution pixels or a checkerboard of them."""
    from gausem_core.slam import tracker as tracker_module

    cfg, cloud, observations, truths, _ = scene
    renders = {}
    for views, points in (("per_level", "all"), ("per_frame", "all"), ("per_frame", "checkerboard")):
        calls = []
        monkeypatch.setattr(tracker_module, "render", lambda *a, _render=render, _calls=calls, **k: (
            _calls.append(1), _render(*a, **k))[1])
        tracking = dataclasses.replace(cfg.tracking, gauss_newton=dataclasses.replace(
            cfg.tracking.gauss_newton, model_views=views, full_resolution_points=points))
        for translation, rotation, motion in tracked_errors(Tracker(tracking, "torch"), cloud, observations, truths):
            assert translation < 0.25 * motion and rotation < 0.5, (views, points, translation, rotation, motion)
        renders[views, points] = len(calls)
    assert renders["per_frame", "all"] <= renders["per_level", "all"] / 3, renders
    assert renders["per_frame", "checkerboard"] <= renders["per_level", "all"] / 3, renders
    for name, value in (("model_views", "sometimes"), ("full_resolution_points", "some")):
        with pytest.raises(ValueError, match=name):
            Tracker(dataclasses.replace(cfg.tracking, gauss_newton=dataclasses.replace(cfg.tracking.gauss_newton,
                                                                                       **{name: value})))


@pytest.mark.parametrize("margin, kept", [(0.2, "estimate"), (0.05, "start")])
def test_per_frame_keeps_a_start_only_when_it_explains_the_frame_better_by_the_margin(scene, monkeypatch, margin,
                                                                                      kept):
    """per_frame's final check: the start replaces the estimate only when the estimate costs more than the start's
    cost times 1 + keep_start_margin (here the estimate 1.0 against the start 0.9); a negative margin is refused."""
    from gausem_core.slam import tracker as tracker_module

    cfg, cloud, observations, _, _ = scene
    compared = []
    monkeypatch.setattr(tracker_module, "compared_costs", lambda view, level, motions, weights: (
        compared.append(len(motions)), [1.0] + [0.9] * (len(motions) - 1))[1])
    tracking = dataclasses.replace(cfg.tracking, gauss_newton=dataclasses.replace(
        cfg.tracking.gauss_newton, model_views="per_frame", keep_start_margin=margin))
    start = torch.eye(4)
    start[0, 3] = 0.01  # a centimetre off: the estimate moves away from it
    result = Tracker(tracking, "torch").track(cloud, observations[0], start)
    assert compared[-1] == 2  # the estimate and the one start
    assert torch.equal(result.cam_to_world, start) == (kept == "start"), result.cam_to_world
    assert result.loss == (0.9 if kept == "start" else 1.0)
    with pytest.raises(ValueError, match="keep_start_margin"):
        Tracker(dataclasses.replace(tracking, gauss_newton=dataclasses.replace(tracking.gauss_newton,
                                                                               keep_start_margin=-0.1)))


def test_health_is_judged_on_the_view_tracking_aligned_against_without_a_render(scene, monkeypatch):
    """inspect_pose takes the view that tracking last rendered, moved by the result's motion, while that motion is
    within rerender_motion: no render, and signals and Hessian as from a view rendered at the pose; a result that
    moved further from its view, or none, gets the model rendered at the pose."""
    from gausem_core.slam import tracker as tracker_module

    cfg, cloud, observations, truths, _ = scene
    tracking = dataclasses.replace(cfg.tracking, gauss_newton=dataclasses.replace(cfg.tracking.gauss_newton,
                                                                                   model_views="per_frame"))
    obs = observations[1]
    tracked = Tracker(tracking, "torch").track(cloud, obs, torch.eye(4))  # from frame 0's pose
    assert pose_error(tracked.cam_to_world, truths[1])[0] < 0.01 and tracked.view is not None
    calls = []
    monkeypatch.setattr(tracker_module, "render", lambda *a, _render=render, **k: (calls.append(1),
                                                                                   _render(*a, **k))[1])
    reused = inspect_pose(cloud, obs, tracked.cam_to_world, tracking, "torch", tracked)
    assert not calls and reused[0] is tracked.view
    fresh = inspect_pose(cloud, obs, tracked.cam_to_world, tracking, "torch")
    assert len(calls) == 1 and torch.equal(fresh[1], torch.eye(4))
    signals = [image_signals(view, obs, hessian, cfg.health, motion) for view, motion, hessian in (reused, fresh)]
    for name in ("coverage", "inlier_fraction"):
        assert abs(signals[0][name] - signals[1][name]) < 0.03, (name, signals)
    assert abs(signals[0]["condition"] - signals[1]["condition"]) < 0.2, signals
    far = dataclasses.replace(tracked, motion=tracked.motion @ se3_exp(torch.tensor([0.2, 0, 0, 0, 0, 0.0])))
    assert inspect_pose(cloud, obs, tracked.cam_to_world, tracking, "torch", far)[0] is not tracked.view
    assert len(calls) == 2


def test_a_checkerboard_model_view_keeps_every_other_pixel_of_its_silhouette():
    from gausem_core.geometry import PinholeCamera
    from gausem_core.slam.direct_alignment import ModelView

    depth = torch.ones(4, 6)
    mask = torch.ones(4, 6, dtype=torch.bool)
    mask[0, :] = False
    view = ModelView(torch.zeros(4, 6, 3), torch.zeros(4, 6, 3), depth, mask, PinholeCamera(6.0, 6.0, 3.0, 2.0, 6, 4))
    board = view.checkerboard()
    assert int(board.mask.sum()) == 9 and not bool((board.mask & ~mask).any())
    assert not bool((board.mask[:, 1:] & board.mask[:, :-1]).any())  # no two neighbours in a row ...
    assert not bool((board.mask[1:] & board.mask[:-1]).any())  # ... or a column
    assert len(board.samples[0]) == 9 and len(view.samples[0]) == 18


def test_a_downsampled_model_view_averages_inside_the_silhouette():
    from gausem_core.geometry import PinholeCamera
    from gausem_core.slam.direct_alignment import ModelView

    depth = torch.tensor([[1.0, 3.0, 2.0, 2.0], [1.0, 9.0, 2.0, 2.0]])
    mask = torch.tensor([[True, True, True, False], [True, False, False, False]])
    color = depth[..., None].repeat(1, 1, 3)
    half = ModelView(color, color, depth, mask, PinholeCamera(4.0, 4.0, 2.0, 1.0, 4, 2)).downsampled()
    assert half.depth.shape == (1, 2) and half.camera.width == 2 and half.camera.height == 1
    assert half.mask.tolist() == [[True, False]]  # 3 of 4 pixels inside, then 1 of 4
    assert float(half.depth[0, 0]) == pytest.approx(5 / 3) and float(half.color[0, 0, 1]) == pytest.approx(5 / 3)
