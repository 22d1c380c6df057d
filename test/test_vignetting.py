"""Online vignetting calibration (slam.vignetting): a planted radial falloff is measured and divided out, none is
invented on a clean camera, and the estimate lives in the system's state."""
import math

import pytest
import torch

from gausem_core.config import SensorConfig, VignettingConfig, from_flat
from gausem_core.data import SYNTHETIC_CLASSES, SyntheticDataset
from gausem_core.data.sensor import COLOR_EFFECTS, DEPTH_EFFECTS, vignetting
from gausem_core.geometry import PinholeCamera
from gausem_core.slam.observation import Observation
from gausem_core.slam.system import GauSemSLAM
from gausem_core.slam.vignetting import Vignetting, radial_slope, radius_squared

CAMERA = PinholeCamera(80.0, 80.0, 40.0, 30.0, 80, 60)
SETTINGS = {"loop.enabled": False, "refinement.enabled": False, "mapping.every": 2, "mapping.iterations": 10,
            "mapping.init_iterations": 60}
FRAMES = 30  # every 2nd frame of the default sequence at 80x60: 15 keyframes


def texture(seed=0):
    """(60, 80, 3) colours in [0.2, 0.8]."""
    coarse = torch.rand(1, 3, 15, 20, generator=torch.Generator().manual_seed(seed))
    return (0.2 + 0.6 * torch.nn.functional.interpolate(coarse, size=(60, 80), mode="bilinear"))[0].permute(1, 2, 0)


def observation(rgb):
    return Observation(rgb, torch.ones(60, 80), torch.zeros(60, 80, 3), torch.zeros(60, 80, dtype=torch.long), CAMERA)


def test_the_slope_of_a_planted_falloff_is_measured_whatever_the_exposure():
    scene, r2 = texture(), radius_squared(CAMERA)
    alpha = torch.ones(60, 80)
    for a, exposure in ((-0.3, 1.0), (-0.3, 0.7), (0.1, 1.2), (0.0, 0.5)):
        seen = scene * exposure * torch.exp(a * r2)[..., None]
        assert radial_slope(seen, scene, alpha, r2, 100) == pytest.approx(a, abs=1e-3)
    # only covered, well-exposed pixels count
    assert radial_slope(scene, scene, torch.zeros(60, 80), r2, 100) is None
    assert radial_slope(torch.ones(60, 80, 3), scene, alpha, r2, 100) is None  # saturated


def test_a_render_blurred_towards_the_border_does_not_look_like_vignetting():
    # a map renders blurrier than the frame where it is seen less sharply (the border: lens distortion, rotation blur);
    # per pixel, log(sharp / blurred) is biased low there, block means are not
    r2 = radius_squared(CAMERA)
    sharp = (0.05 + 0.9 * torch.rand(60, 80, 1, generator=torch.Generator().manual_seed(1))).expand(60, 80, 3)
    blurred = sum(torch.roll(sharp, (i, j), (0, 1)) for i in (-1, 0, 1) for j in (-1, 0, 1)) / 9
    rendered = torch.where((r2 > 0.3)[..., None], blurred, sharp)
    seen = sharp * torch.exp(-0.2 * r2)[..., None]
    assert radial_slope(seen, rendered, torch.ones(60, 80), r2, 100) == pytest.approx(-0.2, abs=0.01)


def test_correction_divides_the_falloff_out_and_the_render_gets_it_back():
    falloff = torch.from_numpy(vignetting(CAMERA, 0.75)).float()[..., None]  # the sensor model's: 75 % in the corners
    scene = texture()
    model = Vignetting(VignettingConfig(calibrate=False, initial=math.log(0.75)))
    corrected = model.correct(observation(scene * falloff)).rgb
    raw_error = (scene * falloff - scene).abs().mean()
    assert (corrected - scene).abs().mean() < 0.15 * raw_error  # exp(a r^2) against 1 - 0.25 r^2: close, not equal
    assert torch.allclose(model.apply(corrected, CAMERA), scene * falloff, atol=0.02)
    unit = Vignetting(VignettingConfig())
    obs = observation(scene)
    assert unit.correct(obs) is obs and unit.apply(scene, CAMERA) is scene


def test_updates_move_towards_the_residual_slope_damped_and_clipped():
    scene, alpha = texture(), torch.ones(60, 80)
    r2 = radius_squared(CAMERA)
    model = Vignetting(VignettingConfig(rate=0.5, max_slope=0.1))
    assert model.update(observation(scene * torch.exp(-0.04 * r2)[..., None]), scene, alpha) == pytest.approx(-0.04,
                                                                                                              abs=1e-3)
    assert model.a == pytest.approx(-0.02, abs=1e-3)
    model.update(observation(scene * torch.exp(-0.5 * r2)[..., None]), scene, alpha)
    assert model.a == pytest.approx(-0.07, abs=1e-3)  # a slope of -0.5 moves a by 0.5 * 0.1 only
    fixed = Vignetting(VignettingConfig(calibrate=False, initial=-0.2))
    assert fixed.update(observation(scene), scene, alpha) is None and fixed.a == -0.2
    with pytest.raises(ValueError, match="vignetting.min_coverage"):
        Vignetting(VignettingConfig(min_coverage=2.0))


def run(sensor_vignetting: bool) -> GauSemSLAM:
    flags = {effect: effect == "vignetting" and sensor_vignetting for effect in DEPTH_EFFECTS + COLOR_EFFECTS}
    data = SyntheticDataset("default", resolution=(80, 60), stride=2, sensor=SensorConfig(**flags))
    slam = GauSemSLAM(from_flat({**SETTINGS, "device": "cpu"}), "cpu",
                      num_classes=len(SYNTHETIC_CLASSES.palette))
    for i in range(FRAMES):
        f = data[i]
        slam.process(Observation.from_arrays(f.rgb, f.depth, f.labels, f.camera, SYNTHETIC_CLASSES.palette,
                                             f.timestamp))
    return slam


@pytest.mark.slow
def test_the_system_learns_the_sensors_vignetting_and_invents_none():
    # the sensor darkens its corners to 75 %: exp(a r^2) fits 1 - 0.25 r^2 best at about a = -0.28
    learnt = run(sensor_vignetting=True).vignetting.a
    assert -0.34 < learnt < -0.2, learnt
    assert abs(run(sensor_vignetting=False).vignetting.a) < 0.03
