from pathlib import Path

import pytest

from gausem_core.config import SlamConfig, flatten, from_flat, load_config

PARAMS = Path(__file__).resolve().parents[1] / "params"


@pytest.mark.parametrize("name", ["synthetic", "tum", "replica", "scannet"])
def test_shipped_params_files_load(name):
    cfg = load_config(PARAMS / f"{name}.yaml")
    assert isinstance(cfg, SlamConfig) and cfg.tracking.iterations > 0


def test_yaml_values_and_overrides(tmp_path):
    f = tmp_path / "p.yaml"
    f.write_text("/**:\n  ros__parameters:\n    tracking:\n      iterations: 7\n      lr_rotation: 1\n    use_sim_time: true\n")
    cfg = load_config(f, {"mapping.every": 3})
    assert cfg.tracking.iterations == 7 and cfg.tracking.lr_rotation == 1.0 and cfg.mapping.every == 3
    assert SlamConfig().tracking.iterations != 7  # defaults untouched


def test_flatten_round_trip():
    flat = flatten(SlamConfig())
    assert flat["tracking.w_depth"] == 0.5 and flat["loop.max_descriptor_distance"] == 0.2
    assert flatten(from_flat(flat)) == flat


def test_errors(tmp_path):
    with pytest.raises(ValueError, match="unknown parameter 'tracking.iters'"):
        from_flat({"tracking.iters": 3})
    with pytest.raises(ValueError, match="must be an integer"):
        from_flat({"tracking.iterations": 2.5})
    with pytest.raises(ValueError, match="true/false"):
        from_flat({"loop.enabled": 1})
    with pytest.raises(FileNotFoundError):
        load_config(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("node:\n  tracking: {}\n")
    with pytest.raises(ValueError, match="ros__parameters"):
        load_config(bad)
