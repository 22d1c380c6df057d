"""The chaos benchmark's parts: the seeded plan, how a kill's moment is told from the map folder and the node's
events, and the trajectory prefix check."""
import os

import numpy as np
import pytest

pytest.importorskip("rclpy")

import msg_adapters as ma  # noqa: E402
from chaos import checkpoint_phase, moment, named_files, open_in, path_rows, plan, prefix  # noqa: E402


def test_the_plan_is_seeded_and_aims_at_every_target_in_turn():
    kills = plan(3, 10, 1.0, 5.0)
    assert kills == plan(3, 10, 1.0, 5.0) and kills != plan(4, 10, 1.0, 5.0)
    targets = [target for target, _ in kills]
    assert (targets.count("checkpoint"), targets.count("event"), targets.count("any")) == (4, 3, 3)
    assert all(1.0 <= wait <= 5.0 for _, wait in kills)


def test_a_checkpoint_write_is_told_from_the_folder_and_the_open_files():
    session = '{"state": {"submaps": [{"cloud": {"$tensor": "submap_0000.aa11.pt:0"}}], "t": {"$tensor": ' \
              '"state.aa11.pt:3"}}}'
    named = named_files(session)
    assert named == {"submap_0000.aa11.pt", "state.aa11.pt"}
    settled = ["session.json", "state.aa11.pt", "submap_0000.aa11.pt"]
    assert checkpoint_phase(settled, named, []) is None
    assert checkpoint_phase(settled, named, ["state.bb22.pt"]) == "writing state.bb22.pt"
    assert checkpoint_phase([*settled, "session.json.partial"], named, []).startswith("session.json.partial")
    new = checkpoint_phase([*settled, "submap_0000.bb22.pt"], named, [])  # the next save's, before the rename
    assert new == "1 tensor files session.json does not name (submap_0000.bb22.pt)"
    assert checkpoint_phase(["state.aa11.pt"], None, []).startswith("1 tensor files")  # no session yet
    assert checkpoint_phase(["grid.pgm", *settled], named, []) is None


def test_a_kill_is_during_a_checkpoint_write_an_event_or_tracking():
    assert moment("writing state.bb22.pt", {"loop closure": None, "submap opening": 0.2}) == \
        "checkpoint write + submap opening"
    assert moment(None, {"loop closure": 0.5, "submap opening": 3.0}) == "loop closure"
    assert moment(None, {"loop closure": 1.5, "submap opening": None}) == "tracking"


def test_open_in_names_the_files_a_process_holds_open_in_a_folder(tmp_path):
    with open(tmp_path / "state.cc33.pt", "wb"):
        assert open_in(os.getpid(), tmp_path) == ["state.cc33.pt"]
    assert open_in(os.getpid(), tmp_path) == []


def _path(poses: list[tuple[float, np.ndarray]]):
    return path_rows(ma.poses_to_path(poses, "map"))


def test_a_trajectory_is_resumed_when_the_path_begins_with_it_bit_for_bit():
    rng = np.random.default_rng(0)
    poses = [(10.0 + i / 30, np.eye(4) + np.pad(rng.normal(0, 0.01, (3, 1)), ((0, 1), (3, 0)))) for i in range(6)]
    held = _path(poses[:4])
    assert prefix(held, _path(poses)) == {"frames": 4, "published": 6, "stamps": True, "poses": True,
                                          "position_m": 0.0, "rotation_deg": 0.0}
    moved = [(t, m.copy()) for t, m in poses]
    moved[1][1][0, 3] += 1e-6
    check = prefix(held, _path(moved))
    assert check["stamps"] and not check["poses"] and check["position_m"] == pytest.approx(1e-6)
    flipped = path_rows(ma.poses_to_path(poses, "map"))
    flipped[1][2, 3:] *= -1  # the same rotation
    assert prefix(held, flipped)["rotation_deg"] == pytest.approx(0.0, abs=1e-4)
    assert not prefix(held, _path(poses[1:]))["stamps"]  # a frame missing
    assert not prefix(held, _path(poses[:3]))["stamps"]  # shorter than the checkpoint
    assert prefix(_path([]), _path(poses))["poses"]
