"""Saving and loading a SLAM session: a bit-identical round trip, a self-contained folder, clear errors, and
relocalisation of the first frame after loading."""
import json
import math
import os
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from gausem_core.config import RENAMED, MappingConfig, from_flat
from gausem_core.data import SYNTHETIC_CLASSES
from gausem_core.geometry import invert_pose, so3_log
from gausem_core.slam.loop import LoopDetector
from gausem_core.slam.loop_closure import LoopConstraint, LoopRecord
from gausem_core.slam.mapper import Mapper
from gausem_core.slam.observation import Observation
from gausem_core.slam.persistence import SESSION_FILE, SessionError, _state_tree, _TensorWriter
from gausem_core.slam.submap import Submap
from gausem_core.slam.system import GauSemSLAM
from gausem_core.tools.run import session_config
from scripted_policy import script_submaps

SETTINGS = {"mapping.every": 2, "mapping.iterations": 10, "mapping.init_iterations": 60,
            "submaps.boundary_iterations": 2, "submaps.memory_budget_mb": 0.0, "refinement.enabled": False}
SWITCH_AT = (6, 12, 18)  # frames that start a new submap: three submaps when saved, the first two on disk; one more
SAVED, NEXT = 16, 4
SEQUENCE_STRIDE = 2  # the conftest's `sequence`: every 2nd frame


def scripted(slam, observations):
    return script_submaps(slam, (observations[i].timestamp for i in SWITCH_AT))


@pytest.fixture(scope="module")
def saved(sequence, tmp_path_factory):
    """A system after SAVED frames (real tracking and loop closure), saved to a folder."""
    observations, _ = sequence
    slam = scripted(GauSemSLAM(from_flat(SETTINGS), "cpu", len(SYNTHETIC_CLASSES)), observations)
    for obs in observations[:SAVED]:
        slam.process(obs)
    folder = tmp_path_factory.mktemp("session")
    slam.save(folder)
    return slam, folder


def state(slam):
    """Everything a session holds, as (JSON tree, tensors by file)."""
    writer = _TensorWriter()
    return _state_tree(slam.front_end, slam.back_end, writer), writer.files


def assert_same_state(a, b):
    tree_a, files_a = state(a)
    tree_b, files_b = state(b)
    assert tree_a == tree_b and files_a.keys() == files_b.keys()
    for name in files_a:
        for key, tensor in files_a[name].items():
            other = files_b[name][key]
            assert tensor.dtype == other.dtype and torch.equal(tensor, other), f"{name}:{key}"


def assert_same_tree(a, b, where="state"):
    """Two state dicts alike: the same keys and plain values, tensors bit-identical (dtype too)."""
    if isinstance(a, torch.Tensor):
        assert isinstance(b, torch.Tensor) and a.dtype == b.dtype and torch.equal(a, b), where
    elif isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), where
        for key in a:
            assert_same_tree(a[key], b[key], f"{where}.{key}")
    elif isinstance(a, (list, tuple)):
        assert type(a) is type(b) and len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            assert_same_tree(x, y, f"{where}[{i}]")
    else:
        assert a == b, where


@pytest.mark.slow
def test_a_loaded_session_goes_on_bit_identically(sequence, saved):
    observations, _ = sequence
    original, folder = saved
    assert len(original.submaps) == 3 and [s.is_active for s in original.submaps] == [False, False, True]
    assert original.back_end.store.on_disk(("cloud", 0)) and original.loop_closure.detector.database.ids.size > 0
    loaded = scripted(GauSemSLAM.load(folder, relocalise=False), observations)
    assert_same_state(original, loaded)
    assert not loaded.submaps[0].is_active and loaded.back_end.store.on_disk(("cloud", 0))
    for obs in observations[SAVED:SAVED + NEXT]:
        a, b = original.process(obs), loaded.process(obs)
        assert (a.frame_id, a.submap_id, a.is_keyframe) == (b.frame_id, b.submap_id, b.is_keyframe)
        assert torch.equal(a.cam_to_world, b.cam_to_world) and a.tracking_loss == b.tracking_loss
        assert (a.health.status, a.health.residual_z, a.health.jump) == (b.health.status, b.health.residual_z,
                                                                         b.health.jump)
    assert loaded.frames[-1].frame_id == SAVED + NEXT - 1 and b.submap_id == 3  # ids go on after the saved ones
    assert_same_state(original, loaded)
    for x, y in zip(original.global_cloud().tensors().values(), loaded.global_cloud().tensors().values()):
        assert torch.equal(x, y)


def test_the_session_folder_is_self_contained(saved, tmp_path):
    """A system's offloaded submaps (spilled to its temporary store) survive that store's deletion in the save."""
    _, folder = saved
    system = GauSemSLAM.load(folder, relocalise=False)
    assert system.back_end.store.on_disk(("cloud", 0))
    system.save(tmp_path / "again")
    cloud, trajectory = system.global_cloud(), system.trajectory()
    images = system.submaps[0].observation(system.submaps[0].keyframes[-1]).rgb
    system.close()  # deletes the spill folder
    loaded = GauSemSLAM.load(tmp_path / "again")
    assert all(torch.equal(x, y) for x, y in zip(cloud.tensors().values(), loaded.global_cloud().tensors().values()))
    assert all(t == u and torch.equal(p, q) for (t, p), (u, q) in zip(trajectory, loaded.trajectory()))
    assert torch.equal(loaded.submaps[0].observation(loaded.submaps[0].keyframes[-1]).rgb, images)


def test_each_part_exports_and_restores_its_own_state(saved):
    """Submaps, the back end (frame records, vignetting, mapper, loop closure) and the front end each round-trip their
    state dicts on their own, without a session folder; restoring the back end leaves the front end as it was."""
    original, _ = saved
    back, front = original.back_end, original.front_end
    assert not back.state_dict().keys() & front.state_dict().keys()  # side by side in a session's tree
    with GauSemSLAM(original.cfg, "cpu", original.num_classes) as fresh:
        untouched = fresh.front_end.state_dict()
        submaps = [Submap.from_state(submap.state_dict(), "cpu", fresh.back_end.store) for submap in back.submaps]
        active = [s.is_active for s in back.submaps]  # the module's system: earlier tests may have gone on with it
        assert [s.is_active for s in submaps] == active and active[-1] and not any(active[:-1]) and len(active) > 1
        for copy, submap in zip(submaps, back.submaps):
            assert_same_tree(copy.state_dict(), submap.state_dict(), f"submap {submap.submap_id}")
        fresh.back_end.load_state_dict(back.state_dict(), submaps)
        assert_same_tree(fresh.back_end.state_dict(), back.state_dict(), "back end")
        assert fresh.loop_closure.records == original.loop_closure.records
        assert all(torch.equal(p, q) for (_, p), (_, q) in zip(fresh.trajectory(), original.trajectory(), strict=True))
        assert_same_tree(fresh.front_end.state_dict(), untouched, "front end")
        fresh.front_end.load_state_dict(front.state_dict())
        assert_same_tree(fresh.front_end.state_dict(), front.state_dict(), "front end")
        active = original.submaps[-1]  # the keyframe decision goes on from the map's newest keyframe
        frame_id, pose = fresh.front_end.keyframes.last
        assert frame_id == active.keyframes[-1].frame_id and torch.equal(pose, active.world_pose(active.keyframes[-1]))
        with pytest.raises(ValueError, match="not empty"):
            fresh.back_end.load_state_dict(back.state_dict(), submaps)


def test_the_mapper_restores_its_random_draws():
    saved, other = Mapper(MappingConfig(), seed=1), Mapper(MappingConfig(), seed=2)
    torch.randint(100, (3,), generator=saved.generator)
    other.load_state_dict(saved.state_dict())
    draws = [torch.randint(100, (8,), generator=mapper.generator) for mapper in (saved, other)]
    assert torch.equal(*draws)


def test_the_session_tree_keeps_its_layout(saved):
    """The parts' state dicts compose the tree that sessions have always had (older sessions load as they are)."""
    _, folder = saved
    state = json.loads((folder / SESSION_FILE).read_text())["state"]
    assert set(state) == {"submaps", "frames", "vignetting", "mapper_generator", "loop_closure", "segment_start",
                          "lost", "dropped", "skipped", "health", "feature_start"}
    submap, frame = state["submaps"][0], state["frames"][0]
    assert set(submap) == {"id", "active", "anchor", "starts_segment", "extent", "cloud", "keyframes"}
    assert set(submap["keyframes"][0]) == {"frame_id", "fixed", "timestamp", "camera", "cam_to_world", "images"}
    assert set(frame) == {"frame_id", "timestamp", "submap", "reference", "relative", "lost", "skipped"}
    assert submap["cloud"]["means"]["$tensor"].startswith("submap_0000.")  # its own file; poses in the state file
    assert submap["keyframes"][0]["images"]["rgb"]["$tensor"].startswith("submap_0000.")
    assert submap["anchor"]["$tensor"].startswith("state.")


def _copy(folder, dest):
    """A copy of a saved session folder, to edit."""
    dest.mkdir()
    for path in folder.iterdir():
        (dest / path.name).write_bytes(path.read_bytes())
    return dest


def test_a_session_without_the_tracking_loss_fields_loads_as_never_lost(saved, tmp_path):
    _, folder = saved
    old = _copy(folder, tmp_path / "old")
    document = json.loads((old / SESSION_FILE).read_text())
    state = document["state"]
    assert state["health"]["residuals"] and not state["lost"]
    for name in ("lost", "dropped", "health"):
        del state[name]
    for frame in state["frames"]:
        del frame["lost"]
    (old / SESSION_FILE).write_text(json.dumps(document))
    loaded = GauSemSLAM.load(old, relocalise=False)
    assert not loaded.lost and loaded.front_end.dropped == 0 and not any(f.lost for f in loaded.frames)
    assert loaded.front_end.health.state_dict() == {"residuals": [], "motions": []}
    current = GauSemSLAM.load(folder, relocalise=False)
    assert all(torch.equal(p, q) for (_, p), (_, q) in zip(current.trajectory(), loaded.trajectory(), strict=True))


def test_a_session_saved_under_the_old_parameter_names_loads_with_its_values(saved, tmp_path):
    _, folder = saved
    old = _copy(folder, tmp_path / "old_names")
    document = json.loads((old / SESSION_FILE).read_text())
    new_names = {new: name for name, new in RENAMED.items()}
    document["config"] = {new_names.get(name, name): value for name, value in document["config"].items()}
    assert "tracking.iterations" in document["config"] and "loop.global_refinement" in document["config"]
    (old / SESSION_FILE).write_text(json.dumps(document))
    assert GauSemSLAM.load(old, relocalise=False).cfg == GauSemSLAM.load(folder, relocalise=False).cfg
    # gausem run --resume reads the parameters the same way, its overrides on top
    original = GauSemSLAM.load(folder, relocalise=False).cfg
    resumed = session_config(old, {"mapping.iterations": original.mapping.iterations + 1})
    assert resumed.mapping.iterations == original.mapping.iterations + 1
    assert replace(resumed, mapping=replace(resumed.mapping, iterations=original.mapping.iterations)) == original


def test_relocalisation_places_an_earlier_frame(sequence, saved):
    observations, poses = sequence
    _, folder = saved
    loaded = GauSemSLAM.load(folder)
    assert loaded.lost
    frames = len(loaded.frames)
    result = loaded.process(observations[3])  # a frame from the first (offloaded) submap's part of the sequence
    reloc = result.relocalisation
    assert reloc is not None and reloc.accepted and not loaded.lost and reloc.starts > 1
    error = invert_pose(poses[3].double()) @ result.cam_to_world.double()
    assert float(error[:3, 3].norm()) < 0.02
    assert math.degrees(float(so3_log(error[:3, :3]).norm())) < 2.0
    assert len(loaded.frames) == frames + 1 and loaded.front_end.segment_start == frames
    follow = loaded.process(observations[4])  # tracking goes on from there
    assert follow.relocalisation is None


def test_a_frame_that_does_not_fit_the_map_is_dropped(sequence, saved):
    observations, _ = sequence
    _, folder = saved
    loaded = GauSemSLAM.load(folder)
    before = state(loaded)
    far = observations[3]
    wrong = Observation(far.rgb.flip(0), far.depth.flip(1) * 3.0, far.semantic, far.labels, far.camera, far.timestamp)
    result = loaded.process(wrong)
    assert result.relocalisation is not None and not result.relocalisation.accepted and loaded.lost
    tree, files = state(loaded)
    assert tree == {**before[0], "dropped": 1}  # counted (the motion model's steps), nothing else changed
    assert all(torch.equal(t, before[1][n][k]) for n in files for k, t in files[n].items())


def test_unreadable_sessions_are_named(saved, tmp_path):
    _, folder = saved
    with pytest.raises(FileNotFoundError, match="no saved session"):
        GauSemSLAM.load(tmp_path / "missing")
    document = json.loads((folder / SESSION_FILE).read_text())
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / SESSION_FILE).write_text(json.dumps({**document, "version": 99}))
    with pytest.raises(SessionError, match="version 99"):
        GauSemSLAM.load(bad)
    truncated = tmp_path / "truncated"
    truncated.mkdir()
    for path in folder.iterdir():
        (truncated / path.name).write_bytes(path.read_bytes())
    [submap] = truncated.glob("submap_0001.*.pt")
    data = submap.read_bytes()
    submap.write_bytes(data[:len(data) // 2])
    with pytest.raises(SessionError, match=submap.name):
        GauSemSLAM.load(truncated)
    (truncated / SESSION_FILE).write_text((folder / SESSION_FILE).read_text()[:100])
    with pytest.raises(SessionError, match=SESSION_FILE):
        GauSemSLAM.load(truncated)


def test_loop_records_and_constraints_survive(saved, tmp_path):
    _, folder = saved
    system = GauSemSLAM.load(folder, relocalise=False)
    loop = system.loop_closure
    loop.records.append(LoopRecord(14, 2, 2, 0, False, True, 0.91, 0.5))
    loop.detector.detections.append((14, 2))
    loop.constraints.append(LoopConstraint(2, 14, 0, 2, torch.eye(4, dtype=torch.float64) * 1.5, (0.01, 0.02), 0.91,
                                           False))
    system.save(tmp_path / "loops")
    back = GauSemSLAM.load(tmp_path / "loops").loop_closure
    assert back.records == loop.records and back.detector.detections == loop.detector.detections
    (a,), (b,) = loop.constraints, back.constraints
    assert torch.equal(a.relative, b.relative) and a.relative.dtype == b.relative.dtype
    assert (a.keyframe_a, a.submap_b, a.sigmas, a.fitness, a.intra) == (b.keyframe_a, b.submap_b, b.sigmas,
                                                                        b.fitness, b.intra)


def test_the_stored_places_rebuild_the_loop_database_in_another_detector(saved):
    """What tracking_mapping sends loop_detection after a load (ROS, loop_closure: nodes): stored unchecked in a new
    detector, a loaded session's places give its database (the bag of words here: features, vocabulary, words)."""
    _, folder = saved
    loop = GauSemSLAM.load(folder, relocalise=False).loop_closure
    other = LoopDetector.from_config(loop.cfg, loop.place_recognition)
    for place in loop.stored_places():
        assert other.add_keyframe(place, check=False) == []
    assert len(loop.detector.database) > 1
    torch.testing.assert_close(other.database.state_dict(), loop.detector.database.state_dict(), rtol=0, atol=0,
                               equal_nan=True)
    torch.testing.assert_close(other.keyframes, loop.detector.keyframes, rtol=0, atol=0)


def test_a_session_loads_only_with_the_place_recognition_it_was_saved_with(saved):
    _, folder = saved
    other = from_flat({**SETTINGS, "loop.place_recognition": "descriptor"})
    with pytest.raises(ValueError, match="place_recognition: bow"):
        GauSemSLAM.load(folder, cfg=other)


def test_a_save_killed_midway_leaves_the_previous_session_whole(saved, tmp_path, monkeypatch):
    """Saving into a folder that holds a session: until the new session.json replaces the old one, the old session
    loads as it was; after, only the new save's files remain."""
    original, _ = saved
    folder = tmp_path / "session"
    original.save(folder)
    first = sorted(path.name for path in folder.iterdir())
    trajectory = original.trajectory()
    real_save, written = torch.save, []

    def dies_after_two_files(tensors, file):  # (the submap store spills with torch.save too: those go on)
        path = Path(getattr(file, "name", file))  # a path, or the file object it is written through
        if path.parent == folder:
            if len(written) == 2:
                raise KeyboardInterrupt("killed")
            written.append(path)
        real_save(tensors, file)
    monkeypatch.setattr(torch, "save", dies_after_two_files)
    with pytest.raises(KeyboardInterrupt):
        original.save(folder)
    monkeypatch.setattr(torch, "save", real_save)
    assert len(written) == 2 and all(path.name not in first for path in written)
    loaded = GauSemSLAM.load(folder, relocalise=False)
    assert all(t == u and torch.equal(p, q) for (t, p), (u, q) in zip(trajectory, loaded.trajectory()))
    loaded.close()
    original.save(folder)
    files = sorted(path.name for path in folder.iterdir())
    assert len(files) == len(first) and not set(files) & (set(first) - {SESSION_FILE})


def test_a_save_reaches_the_disk_before_session_json_replaces_the_previous_one(saved, tmp_path, monkeypatch):
    """A power cut, not only a kill: every tensor file and the new session.json are fsynced before the rename, and the
    folder after it (before the previous save's files are deleted)."""
    original, _ = saved
    folder = tmp_path / "session"
    original.save(folder)
    events, real_fsync, real_replace, real_unlink = [], os.fsync, os.replace, Path.unlink

    def fsync(fd):
        events.append(("fsync", Path(os.readlink(f"/proc/self/fd/{fd}")).name))
        real_fsync(fd)
    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", lambda a, b: (events.append(("replace", Path(b).name)), real_replace(a, b)))
    monkeypatch.setattr(Path, "unlink", lambda p, **kw: (events.append(("unlink", p.name)) if p.parent == folder
                                                         else None, real_unlink(p, **kw)))
    original.save(folder)
    names = [name for kind, name in events]
    replaced = names.index(SESSION_FILE)
    written = {path.name for path in folder.iterdir()} - {SESSION_FILE}
    assert written and written <= set(names[:replaced])  # every new tensor file fsynced before the rename
    assert ("fsync", SESSION_FILE + ".partial") in events[:replaced]
    assert events[replaced + 1] == ("fsync", folder.name)  # the folder, right after the rename
    assert all(kind != "unlink" for kind, _ in events[:replaced + 1])  # the previous files go only then
