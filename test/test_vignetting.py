"""Online vignetting calibration (slam.back_end.vignetting): a planted radial falloff is measured and divided out, none is
invented on a clean camera, and the estimate lives in the system's state."""
import math
from dataclasses import replace

import pytest
import torch

from gausem_core.config import SensorConfig, VignettingConfig, from_flat
from gausem_core.data import SYNTHETIC_CLASSES, SyntheticDataset
from gausem_core.data.sensor import COLOR_EFFECTS, DEPTH_EFFECTS, vignetting
from gausem_core.geometry import PinholeCamera
from gausem_core.slam.observation import Observation
from gausem_core.slam.system import GauSemSLAM
from gausem_core.slam.vignetting import Vignetting, pair_slope, radius_squared, weighted_median

CAMERA = PinholeCamera(80.0, 80.0, 40.0, 30.0, 80, 60)
SETTINGS = {"loop.enabled": False, "refinement.enabled": False, "mapping.every": 2, "mapping.iterations": 10,
            "mapping.init_iterations": 60}
FRAMES = 30  # every 2nd frame of the default sequence at 80x60: 15 keyframes


def texture(seed=0):
    """(60, 80, 3) colours in [0.2, 0.8]."""
    coarse = torch.rand(1, 3, 15, 20, generator=torch.Generator().manual_seed(seed))
    return (0.2 + 0.6 * torch.nn.functional.interpolate(coarse, size=(60, 80), mode="bilinear"))[0].permute(1, 2, 0)


def observation(rgb):
    """A frame of ``rgb`` seeing a wall 1 m away."""
    return Observation(rgb, torch.ones(60, 80), torch.zeros(60, 80, 3), torch.zeros(60, 80, dtype=torch.long), CAMERA)


def planar_pair(angle_deg: float, a: float, exposure: float = 1.0, seed: int = 0):
    """Two views of a textured wall 1 m away, the second panned by ``angle_deg`` (points move between radii) and
    shifted 5 cm, both recorded through exp(a r^2), the second with ``exposure``: (earlier colour, depth, later colour,
    depth, later_from_earlier)."""
    angle = math.radians(angle_deg)
    later_from_earlier = torch.eye(4)
    later_from_earlier[[0, 0, 2, 2], [0, 2, 0, 2]] = torch.tensor([math.cos(angle), math.sin(angle), -math.sin(angle),
                                                                   math.cos(angle)])
    later_from_earlier[0, 3] = 0.05
    rotation, shift = later_from_earlier[:3, :3], later_from_earlier[:3, 3]

    def wall(x, y):  # albedo on the plane z = 1 m of the earlier camera
        return 0.5 + 0.3 * torch.sin(20 * x + 3 * seed) * torch.cos(17 * y)

    rays = CAMERA.pixel_rays()
    directions, origin = rays @ rotation, -shift @ rotation  # the later pixels' rays in the earlier frame
    reach = (1 - origin[2]) / directions[..., 2]  # along each ray to z = 1: also the later depth (its rays' z is 1)
    hit = origin + reach[..., None] * directions
    gain = torch.exp(a * radius_squared(CAMERA))
    earlier, later = wall(rays[..., 0], rays[..., 1]) * gain, exposure * wall(hit[..., 0], hit[..., 1]) * gain
    return (earlier[..., None].expand(60, 80, 3), torch.ones(60, 80), later[..., None].expand(60, 80, 3), reach,
            later_from_earlier)


def test_the_slope_of_a_planted_falloff_is_measured_from_a_pair_whatever_the_exposure():
    for a, exposure in ((-0.3, 1.0), (-0.3, 0.8), (0.1, 1.1), (0.0, 0.9)):
        pair = pair_slope(*planar_pair(20, a, exposure), CAMERA, 100)
        assert pair.slope == pytest.approx(a, abs=0.02) and pair.weight > 0
    # a larger pan carries points further between radii: more weight
    assert pair_slope(*planar_pair(10, -0.3), CAMERA, 100).weight > pair_slope(*planar_pair(3, -0.3), CAMERA,
                                                                                100).weight


def test_a_pair_without_common_well_exposed_points_measures_nothing():
    earlier, depth, later, _, pose = planar_pair(20, -0.3)
    assert pair_slope(earlier, depth, later, torch.zeros_like(depth), pose, CAMERA, 100) is None  # no depth
    assert pair_slope(earlier, depth, later, depth + 1, pose, CAMERA, 100) is None  # another surface
    assert pair_slope(torch.ones_like(earlier), depth, later, depth, pose, CAMERA, 100) is None  # saturated
    assert pair_slope(earlier, depth, later, depth, torch.eye(4), CAMERA, 100) is None  # no motion: no spread
    assert pair_slope(earlier, depth, later, depth, pose, CAMERA, 60 * 80 + 1) is None  # too few points


def test_the_estimate_is_the_weighted_median_of_the_pairs_and_the_prior():
    assert weighted_median([0.0, -0.3, -0.2], [1.0, 3.0, 1.0]) == -0.3
    assert weighted_median([0.0, -0.3, -0.2], [1.0, 1.0, 1.0]) == -0.2
    model = Vignetting(VignettingConfig())
    pose = torch.eye(4)
    earlier, _, later, later_depth, later_from_earlier = planar_pair(20, -0.3)
    later_obs, moved = replace(observation(later), depth=later_depth), torch.linalg.inv(later_from_earlier)
    assert model.update(observation(earlier), pose, 0) is None and model.a == 0.0  # nothing to pair with yet
    assert model.update(later_obs, moved, 0).slope == pytest.approx(-0.3, abs=0.02)
    assert model.a == pytest.approx(-0.3, abs=0.02)  # the pair outweighs the prior (weight 1)
    assert model.update(observation(earlier), pose, 1) is None  # another submap: no pair across
    assert len(model.pairs) == 1
    fixed = Vignetting(VignettingConfig(calibrate=False, initial=-0.2))
    assert fixed.update(observation(earlier), pose, 0) is None and fixed.update(observation(later), pose, 0) is None
    assert fixed.a == -0.2
    restored = Vignetting(VignettingConfig())
    restored.load_state_dict(model.state_dict())
    assert restored.a == model.a and restored.pairs == model.pairs
    # the restored estimate pairs the next keyframe as the original does
    assert restored.update(later_obs, moved, 1).slope == model.update(later_obs, moved, 1).slope
    with pytest.raises(ValueError, match="vignetting.min_coverage"):
        Vignetting(VignettingConfig(min_coverage=2.0))


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
    learnt = run(sensor_vignetting=True).back_end.vignetting.a
    assert -0.34 < learnt < -0.2, learnt
    assert abs(run(sensor_vignetting=False).back_end.vignetting.a) < 0.03
