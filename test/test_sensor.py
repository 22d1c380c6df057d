"""The Kinect-like sensor model: each effect on analytic inputs, and the noisy synthetic variants end to end."""
import dataclasses

import numpy as np
import pytest

from gausem_core.config import SensorConfig
from gausem_core.data import SyntheticDataset, open_dataset
from gausem_core.data.sensor import (COLOR_EFFECTS, DEPTH_EFFECTS, AutoExposure, SensorModel, axial_sigma,
                                     incidence_angle, projector_shadow)
from gausem_core.data.synthetic import default_camera

CAMERA = default_camera(160, 120)


def only(*effects, **values) -> SensorConfig:
    """The default sensor with every effect but ``effects`` off."""
    flags = {name: name in effects for name in DEPTH_EFFECTS + COLOR_EFFECTS}
    return SensorConfig(**flags, **values)


def step_depth(near=1.0, far=2.0):
    """A wall at ``far`` with a square at ``near`` in columns 60..99, rows 40..79."""
    depth = np.full((120, 160), far, np.float32)
    depth[40:80, 60:100] = near
    return depth


def test_every_effect_has_a_flag_and_none_on_is_clean():
    flags = {f.name for f in dataclasses.fields(SensorConfig) if f.type in (bool, "bool")}
    assert flags == set(DEPTH_EFFECTS + COLOR_EFFECTS)
    sensor, depth = SensorModel(only()), step_depth()
    assert np.array_equal(sensor.depth(depth, CAMERA, 0), depth)
    linear = np.random.default_rng(0).uniform(0, 1, (120, 160, 3))
    assert np.array_equal(sensor.color(linear, CAMERA, 0, 1.0, np.ones(3)),
                          np.clip(linear * 255 + 0.5, 0, 255).astype(np.uint8))


def test_bad_parameters_are_rejected():
    for bad in ({"min_range": 5.0}, {"max_incidence_deg": 95.0}, {"blur_samples": 0}, {"vignetting_corner": 0.0},
                {"exposure_rate": 0.0}, {"full_well": -1.0}, {"baseline": 0.0}):
        with pytest.raises(ValueError, match="sensor config"):
            SensorModel(SensorConfig(**bad))
    with pytest.raises(ValueError, match="already names"):
        SyntheticDataset("default_noisy", sensor=SensorConfig())
    with pytest.raises(ValueError, match="default_noisy"):
        open_dataset("synthetic:nope")


def test_axial_noise_grows_with_range_as_nguyen_et_al():
    sensor = SensorModel(only("axial_noise"))
    for z in (1.0, 3.0):
        depth = np.full((120, 160), z, np.float32)
        error = sensor.depth(depth, CAMERA, 0) - depth
        centre = error[30:90, 40:120]  # near-frontal incidence, where the angle term is negligible
        expected = 0.0012 + 0.0019 * (z - 0.4) ** 2
        assert abs(centre.mean()) < 0.1 * expected and centre.std() == pytest.approx(expected, rel=0.05)
    oblique, frontal = axial_sigma(np.array([1.0, 1.0]), np.radians([70.0, 0.0]), sensor.cfg)
    assert oblique > 1.5 * frontal  # readings at 70 deg incidence are noisier


def test_disparity_quantisation_puts_depth_on_the_disparity_grid():
    depth = np.linspace(0.6, 4.0, 120 * 160, dtype=np.float32).reshape(120, 160)
    out = SensorModel(only("disparity_quantisation")).depth(depth, CAMERA, 0)
    disparity = 580.0 * 0.075 / out / 0.125
    assert np.allclose(disparity, np.round(disparity), atol=1e-3)
    step = out[1:] - out[:-1]
    assert len(np.unique(out)) < 0.2 * out.size  # far readings share few levels
    assert np.abs(out - depth).max() <= 0.5 * 0.125 * 4.0**2 / (580 * 0.075) * 1.01  # half a step at 4 m
    assert step.min() >= 0  # monotone


def test_range_dropout_removes_far_and_near_readings_only():
    depth = np.linspace(0.3, 5.0, 120 * 160, dtype=np.float32).reshape(120, 160)
    out = SensorModel(only("range_dropout")).depth(depth, CAMERA, 0)
    kept = out > 0
    assert np.array_equal(out[kept], depth[kept])  # holes only, values untouched
    assert not kept[(depth < 0.5) | (depth > 4.5)].any() and kept[(depth > 0.5) & (depth < 3.5)].all()
    ramp = (depth > 3.5) & (depth < 4.5)
    assert kept[ramp].mean() == pytest.approx(0.5, abs=0.05)  # linear ramp: half survive on average


def test_grazing_holes_follow_the_incidence_angle():
    # a floor 1.4 m below the camera, seen by a camera looking level: incidence grows towards the horizon
    rays = CAMERA.pixel_rays().numpy()
    depth = np.where(rays[..., 1] > 0.02, 1.4 / np.maximum(rays[..., 1], 1e-6), 0).astype(np.float32)
    true_angle = np.arccos(rays[..., 1] / np.linalg.norm(rays, axis=-1))
    estimated = incidence_angle(depth.astype(np.float64), CAMERA, 0.05)
    floor = (depth > 0) & (depth < 9)  # farther, neighbouring rows are discontinuities (>5 % apart)
    assert np.abs(estimated - true_angle)[floor].max() < np.radians(1.0)
    out = SensorModel(only("grazing_holes")).depth(depth, CAMERA, 0)
    assert np.array_equal(out[out > 0], depth[out > 0])
    clear = floor & (np.abs(true_angle - np.radians(75)) > np.radians(1))
    assert np.array_equal((out > 0)[clear], (true_angle < np.radians(75))[clear])


def test_edge_holes_lie_in_a_band_along_discontinuities():
    depth = step_depth()
    sensor = SensorModel(only("edge_holes", edge_band=8.0))  # 2 render pixels on each side at 160 wide
    holes = sensor.depth(depth, CAMERA, 0) == 0
    rows, cols = np.nonzero(holes)
    distance_to_edge = np.minimum.reduce([np.abs(cols - 59.5), np.abs(cols - 99.5), np.abs(rows - 39.5),
                                          np.abs(rows - 79.5)])
    assert distance_to_edge.max() <= 2.5 and holes.sum() > 0.5 * 4 * 160  # a band about 2 pixels wide each side
    assert not holes[:30].any() and not holes[50:70, 70:90].any()


def test_projector_shadow_falls_beside_the_occluder_on_the_far_side_of_the_projector():
    depth = step_depth(near=1.0, far=2.0)
    shadow = projector_shadow(depth, CAMERA, 0.075, 0.05)
    width = CAMERA.fx * 0.075 * (1 / 1.0 - 1 / 2.0)  # disparity difference of the two surfaces, pixels
    band = shadow[40:80].sum(1)
    assert np.all(np.abs(band - width) <= 1) and shadow[40:80, 60 - int(width) - 1:60].any(1).all()
    assert not shadow[:40].any() and not shadow[80:].any() and not shadow[:, 60:].any()  # only left of it
    assert not projector_shadow(depth, CAMERA, -0.075, 0.05)[:, :100].any()  # a projector on the left: right side
    out = SensorModel(only("projector_shadows")).depth(depth, CAMERA, 0)
    assert np.array_equal(out == 0, shadow)


def test_vignetting_darkens_corners_only():
    grey = np.full((120, 160, 3), 0.6)
    out = SensorModel(only("vignetting")).color(grey, CAMERA, 0, 1.0, np.ones(3)).astype(float)
    assert out[58:62, 78:82].mean() == pytest.approx(0.6 * 255, abs=1)
    assert out[0, 0].mean() == pytest.approx(0.6 * 255 * 0.75, abs=2)


def test_shot_noise_variance_grows_with_signal_and_gain():
    sensor = SensorModel(only("shot_noise"))
    variances = {}
    for level, gain in ((0.2, 1.0), (0.8, 1.0), (0.8, 2.0)):
        out = sensor.color(np.full((120, 160, 3), level / gain), CAMERA, 0, gain, np.ones(3)).astype(float) / 255
        assert out.mean() == pytest.approx(level, abs=0.005)
        variances[level, gain] = out.var()
    expected = {k: k[1] * k[0] / 4000 + (1 / 255) ** 2 + (1 / 255) ** 2 / 12 for k in variances}  # + rounding
    for k in variances:
        assert variances[k] == pytest.approx(expected[k], rel=0.1)


def test_auto_exposure_follows_a_brightness_step_with_lag():
    means = [np.full(3, 0.2)] * 10 + [np.full(3, 0.4)] * 40
    ae = AutoExposure(only("auto_exposure", exposure_target=0.3), lambda i: means[i])
    gains = np.array([ae.gains(i)[0] for i in range(50)])
    assert gains[:11] == pytest.approx(1.5)  # converged, and frame 10 still exposes for the dark frame 9
    assert 0.75 < gains[12] < gains[11] < 1.5 and gains[-1] == pytest.approx(0.75, rel=1e-3)
    assert np.log(gains[12] / 0.75) == pytest.approx(0.8**2 * np.log(2), rel=1e-6)  # 20 % of the error per frame
    assert ae.gains(3)[1].tolist() == [1, 1, 1]  # white balance off


def test_white_balance_drifts_towards_grey_world_slowly():
    means = [np.array([0.3, 0.3, 0.3])] * 5 + [np.array([0.6, 0.3, 0.3])] * 100
    ae = AutoExposure(only("white_balance"), lambda i: means[i])
    wb = np.array([ae.gains(i)[1] for i in range(105)])
    assert wb[:6] == pytest.approx(np.ones((6, 3)))
    assert 0.5**0.3 < wb[10, 0] < 1 and wb[10, 1:] == pytest.approx([1, 1])  # red is corrected, with lag
    assert wb[-1, 0] == pytest.approx(0.5**0.3, rel=1e-2)
    assert ae.gains(50)[0] == 1.0  # exposure off


@pytest.fixture(scope="module")
def clean_frames():
    ds = SyntheticDataset()
    return {i: ds[i] for i in (0, 18)}  # 18 sees past 3.5 m


@pytest.mark.parametrize("effect", DEPTH_EFFECTS + COLOR_EFFECTS)
def test_each_effect_alone_changes_only_its_own_channel(effect, clean_frames):
    ds = SyntheticDataset(sensor=only(effect))
    clean, noisy = clean_frames[18], ds[18]
    assert np.array_equal(noisy.labels, clean.labels) and np.array_equal(noisy.gt_pose, clean.gt_pose)
    changed, same = ("depth", "rgb") if effect in DEPTH_EFFECTS else ("rgb", "depth")
    assert np.array_equal(getattr(noisy, same), getattr(clean, same))
    assert not np.array_equal(getattr(noisy, changed), getattr(clean, changed))


def test_motion_blur_smears_along_the_motion(clean_frames):
    clean = clean_frames[18].rgb.astype(float)
    blurred = {t: SyntheticDataset(sensor=only("motion_blur", exposure_time=t))[18].rgb.astype(float)
               for t in (0.005, 0.03)}
    difference = {t: np.abs(b - clean).mean() for t, b in blurred.items()}
    assert 0 < difference[0.005] < difference[0.03]
    sharpness = {t: np.abs(np.diff(b.mean(-1), axis=1)).mean() for t, b in blurred.items()}
    assert sharpness[0.03] < sharpness[0.005] < np.abs(np.diff(clean.mean(-1), axis=1)).mean()


def test_noisy_variant_is_seeded_and_effects_draw_independently(clean_frames):
    a, b = open_dataset("synthetic:default_noisy", max_frames=19), SyntheticDataset("default_noisy", seed=0)
    c = SyntheticDataset("default_noisy", seed=1)
    assert a.name == "synthetic_default_noisy" and len(a) == 19
    fa, fb, fc = a[18], b[18], c[18]
    assert np.array_equal(fa.rgb, fb.rgb) and np.array_equal(fa.depth, fb.depth)
    assert not np.array_equal(fa.depth, c[18].depth) and not np.array_equal(fa.rgb, fc.rgb)
    assert not np.array_equal(fa.depth, a[0].depth)
    # switching colour effects off leaves the depth reading exactly as it was, and vice versa
    no_colour = SyntheticDataset(sensor=SensorConfig(**{e: False for e in COLOR_EFFECTS}))[18]
    assert np.array_equal(no_colour.depth, fa.depth) and np.array_equal(no_colour.rgb, clean_frames[18].rgb)
    no_depth = SyntheticDataset(sensor=SensorConfig(**{e: False for e in DEPTH_EFFECTS}))[18]
    assert np.array_equal(no_depth.rgb, fa.rgb) and np.array_equal(no_depth.depth, clean_frames[18].depth)
