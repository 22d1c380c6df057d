from pathlib import Path

import pytest

from gausem_core.config import RENAMED, SlamConfig, flatten, from_flat, load_config

PARAMS = Path(__file__).resolve().parents[1] / "params"


@pytest.mark.parametrize("name", ["synthetic", "tum", "replica", "scannet"])
def test_shipped_params_files_load(name):
    cfg = load_config(PARAMS / f"{name}.yaml")
    assert isinstance(cfg, SlamConfig) and cfg.tracking.gauss_newton.pyramid_levels > 0


def test_yaml_values_and_overrides(tmp_path):
    f = tmp_path / "p.yaml"
    f.write_text("/**:\n  ros__parameters:\n    tracking:\n      adam:\n        iterations: 7\n        lr_rotation: 1\n"
                 "    refinement:\n      w_depth: 0.25\n    use_sim_time: true\n")
    cfg = load_config(f, {"mapping.every": 3, "tracking.gauss_newton.level_iterations": 5})
    assert cfg.tracking.adam.iterations == 7 and cfg.tracking.adam.lr_rotation == 1.0 and cfg.mapping.every == 3
    assert cfg.tracking.gauss_newton.level_iterations == 5 and cfg.refinement.w_depth == 0.25
    defaults = SlamConfig()  # untouched
    assert defaults.tracking.adam.iterations != 7 and defaults.tracking.gauss_newton.level_iterations != 5


def test_flatten_round_trip():
    flat = flatten(SlamConfig())
    assert flat["tracking.w_depth"] == 0.5 and flat["loop.max_descriptor_distance"] == 0.2
    assert flatten(from_flat(flat)) == flat


def test_errors(tmp_path):
    with pytest.raises(ValueError, match="unknown parameter 'tracking.iters'"):
        from_flat({"tracking.iters": 3})
    with pytest.raises(ValueError, match="must be an integer"):
        from_flat({"tracking.adam.iterations": 2.5})
    with pytest.raises(ValueError, match="true/false"):
        from_flat({"loop.enabled": 1})
    unquoted = tmp_path / "unquoted.yaml"
    unquoted.write_text("/**:\n  ros__parameters:\n    tracking:\n      feature_start:\n        mode: off\n")
    with pytest.raises(ValueError, match="'tracking.feature_start.mode' must be a string, got False .*quote"):
        load_config(unquoted)
    with pytest.raises(FileNotFoundError):
        load_config(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("node:\n  tracking: {}\n")
    with pytest.raises(ValueError, match="ros__parameters"):
        load_config(bad)


def test_each_tracking_method_and_the_refinement_have_their_own_section():
    flat = flatten(SlamConfig())
    assert {"tracking.gauss_newton.level_iterations", "tracking.adam.iterations", "tracking.adam.patience",
            "refinement.enabled", "refinement.iterations_per_keyframe"} <= set(flat)
    assert "tracking.w_depth" in flat and "tracking.huber_delta" in flat  # read whichever method tracks
    assert not any(name.startswith("loop.refine") or name == "loop.global_refinement" for name in flat)


@pytest.mark.parametrize("old, new", [("tracking.iterations", "tracking.adam.iterations"),
                                      ("tracking.pyramid_levels", "tracking.gauss_newton.pyramid_levels"),
                                      ("loop.global_refinement", "refinement.enabled"),
                                      ("loop.refine_w_depth", "refinement.w_depth")])
def test_an_old_name_fails_naming_the_new_one(tmp_path, old, new):
    value = flatten(SlamConfig())[new]
    with pytest.raises(ValueError, match=f"renamed parameter: '{old}' is now '{new}'"):
        from_flat({old: value})
    section, name = old.split(".")
    f = tmp_path / "old.yaml"
    f.write_text(f"/**:\n  ros__parameters:\n    {section}:\n      {name}: {str(value).lower()}\n")
    with pytest.raises(ValueError, match=f"'{old}' is now '{new}'"):
        load_config(f)


def test_every_old_name_is_gone_and_its_new_name_exists():
    flat = flatten(SlamConfig())
    assert not set(RENAMED) & set(flat) and set(RENAMED.values()) <= set(flat)
    with pytest.raises(ValueError, match="renamed parameters: 'tracking.patience' is now 'tracking.adam.patience', "
                                         "'loop.refine_w_depth' is now 'refinement.w_depth'"):
        from_flat({"mapping.every": 2, "tracking.patience": 3, "loop.refine_w_depth": 0.5})
