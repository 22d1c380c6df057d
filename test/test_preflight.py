"""gausem-launch checks parameters, map_path and the player's source before any node starts."""
import json

import pytest

pytest.importorskip("rclpy")
pytest.importorskip("rosbags")

from gausem_core.slam.persistence import FORMAT, SESSION_FILE, VERSION  # noqa: E402
from gausem_ros import launcher  # noqa: E402
from gausem_ros.preflight import (check_bag, check_map_path, check_parameters, check_player,  # noqa: E402
                                  launch_problems, ros_parameters)
from test_player_topics import bag_with_labels_elsewhere  # noqa: E402


def test_parameters_come_from_the_file_and_the_command_line_in_ros_order(tmp_path):
    params = tmp_path / "p.yaml"
    params.write_text("/**:\n  ros__parameters:\n    map_path: a\n    mapping:\n      iterations: 3\n"
                      "tracking_mapping:\n  ros__parameters:\n    map_path: b\n"
                      "pose_graph:\n  ros__parameters:\n    map_path: c\n")
    assert ros_parameters(str(params), []) == {"map_path": "b", "mapping.iterations": 3}
    assert ros_parameters(str(params), ["-p", "tracking_mapping:map_path:=d", "-p", "pose_graph:map_path:=e",
                                        "-p", "mapping.iterations:=5"]) == {"map_path": "d", "mapping.iterations": 5}


def test_bad_parameters_are_named(tmp_path):
    assert check_parameters("params/synthetic.yaml", ["-p", "mapping.iterations:=7"]) == []
    assert "does not exist" in check_parameters(str(tmp_path / "none.yaml"), [])[0]
    assert "mapping.iterations" in check_parameters(None, ["-p", "mapping.iterations:=many"])[0]
    flat = tmp_path / "flat.yaml"
    flat.write_text("mapping:\n  iterations: 3\n")
    assert "ros__parameters" in check_parameters(str(flat), [])[0]


def test_map_path_resumes_a_readable_session_or_starts_a_new_one_where_it_can(tmp_path):
    assert check_map_path("") == []
    assert check_map_path(str(tmp_path / "new" / "session")) == []  # created at the first checkpoint
    (tmp_path / "file").write_text("x")
    assert "not a folder" in check_map_path(str(tmp_path / "file"))[0]
    assert "not a writable folder" in check_map_path(str(tmp_path / "file" / "below"))[0]
    saved = tmp_path / "saved"
    saved.mkdir()
    (saved / SESSION_FILE).write_text(json.dumps({"format": FORMAT, "version": VERSION}))
    assert check_map_path(str(saved)) == []
    (saved / SESSION_FILE).write_text(json.dumps({"format": FORMAT, "version": -1}))
    assert "cannot be resumed" in check_map_path(str(saved))[0]
    (saved / SESSION_FILE).write_text("{")
    assert "cannot be resumed" in check_map_path(str(saved))[0]


def test_a_bag_must_open_and_carry_rgb_and_depth(tmp_path):
    path = tmp_path / "labels.bag"
    bag_with_labels_elsewhere(path)
    assert check_bag(str(path), {}) == []
    assert check_bag(str(path), {"labels": "/camera/labels"}) == []
    assert "/camera/semantics" in check_bag(str(path), {"labels": "/camera/semantics"})[0]
    assert "does not exist" in check_bag(str(tmp_path / "none.bag"), {})[0]
    truncated = tmp_path / "truncated.bag"
    truncated.write_bytes(path.read_bytes()[:200])
    assert "corrupt or truncated" in check_bag(str(truncated), {})[0]


def test_player_arguments_are_checked_as_the_player_would(tmp_path):
    assert check_player("synthetic --lockstep --max-frames 2") == []
    assert "unrecognized" in check_player("synthetic --bogus")[0]
    assert "TUM folder" in check_player(f"tum:{tmp_path / 'none'}")[0]
    path = tmp_path / "labels.bag"
    bag_with_labels_elsewhere(path)
    assert "datasets, not to bags" in check_player(f"{path} --size 8x6")[0]
    (tmp_path / "file").write_text("x")
    map_problem, bag_problem = launch_problems(None, ["-p", f"map_path:={tmp_path / 'file'}"],
                                               f"{path} --topic labels=/x")
    assert "not a folder" in map_problem and "has no topics ['/x'] (--topic)" in bag_problem


def test_the_launcher_starts_nothing_when_a_check_fails(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(launcher.subprocess, "Popen", lambda *a, **k: pytest.fail("a child was started"))
    (tmp_path / "file").write_text("x")
    with pytest.raises(SystemExit) as exit_info:
        launcher.main(["--respawn", "--", "-p", f"map_path:={tmp_path / 'file'}"])
    assert exit_info.value.code == 2
    assert "map_path" in capsys.readouterr().err
