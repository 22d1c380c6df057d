"""The live 3D view (``gausem_core.viewer``): ``gausem run --viewer`` writes a Rerun recording that reads back with
every entity, loops and class colours are logged as the map holds them, and a run without it never imports rerun."""
import sys
from collections import defaultdict
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from gausem_core.cli import main
from gausem_core.data import SYNTHETIC_CLASSES
from gausem_core.gaussians import GaussianCloud
from gausem_core.io.ply import read_gaussian_ply
from gausem_core.io.trajectory import read_tum_trajectory
from gausem_core.viewer import TRAJECTORY_COLOR, Viewer

FAST = ["--set", "mapping.init_iterations=60", "--set", "mapping.iterations=5", "--set", "device=cpu", "--quiet",
        "--size", "80x60"]
TIMES = ("log_time", "time")  # nanosecond timelines, which pyarrow's to_pylist cannot convert without pandas


def read_recording(path) -> dict[str, list[dict]]:
    """Entity path -> its rows (column -> value; the timelines but ``frame`` left out), static ones first, then by
    frame."""
    from rerun.chunk import RrdReader

    rows = defaultdict(list)
    for chunk in RrdReader(path).stream():
        batch = chunk.to_record_batch()
        rows[chunk.entity_path] += batch.select([n for n in batch.schema.names if n not in TIMES]).to_pylist()
    for entity_rows in rows.values():
        entity_rows.sort(key=lambda row: row.get("frame", -1))
    return rows


def test_gausem_run_with_the_viewer_records_every_entity(tmp_path):
    pytest.importorskip("rerun")
    out = tmp_path / "run"
    assert main(["run", "--dataset", "synthetic", "--frames", "6", *FAST, "--viewer", "--viewer-map-every", "2",
                 "--out", str(out)]) == 0
    rows = read_recording(out / "gausem.rrd")
    for entity in ("/world/camera/image/rgb", "/world/camera/image/semantic", "/world/camera"):
        assert [r["frame"] for r in rows[entity]] == list(range(6)), entity
    assert rows["/world/camera/image"][0]["Pinhole:resolution"] == [[80.0, 60.0]]
    semantic = rows["/world/camera/image/semantic"][-1]
    labels = np.frombuffer(bytes(semantic["SegmentationImage:buffer"][0]), np.uint16)
    assert semantic["SegmentationImage:format"][0]["width"] == 80 and labels.size == 80 * 60
    assert 1 < len(np.unique(labels)) and labels.max() < len(SYNTHETIC_CLASSES)
    # the map at frames 0, 2 and 4 and, at the end, as written to map.ply (all of it: fewer than max_points)
    assert [r["frame"] for r in rows["/world/map"]] == [0, 2, 4, 5]
    assert len(rows["/world/map"][-1]["Points3D:positions"]) == len(read_gaussian_ply(out / "map.ply")[0])
    # the trajectory grows a position a frame; at the end it is the refined trajectory.txt
    trajectory = rows["/world/trajectory"]
    assert [len(r["LineStrips3D:strips"][0]) for r in trajectory] == [2, 3, 4, 5, 6, 6]
    final = read_tum_trajectory(out / "trajectory.txt").poses[:, :3, 3]
    np.testing.assert_allclose(trajectory[-1]["LineStrips3D:strips"][0], final, atol=1e-5)
    assert "/world/loops" not in rows  # no loop in six frames


class FakeSlam:
    """What the viewer reads of a system: the trajectory, the frames' poses, the accepted loops, the map."""

    def __init__(self, positions, loops, cloud):
        poses = [torch.eye(4, dtype=torch.float64) for _ in positions]
        for pose, position in zip(poses, positions):
            pose[:3, 3] = torch.tensor(position)
        self.frames = [SimpleNamespace(cam_to_world=pose) for pose in poses]
        self.loop_closure = SimpleNamespace(loops=[SimpleNamespace(query_frame=q, match_frame=m) for q, m in loops])
        self.cloud = cloud

    def trajectory(self, include_lost=True):
        return [(float(i), f.cam_to_world) for i, f in enumerate(self.frames)]

    def global_cloud(self):
        return self.cloud


def test_loops_are_segments_between_the_frames_and_the_map_is_subsampled_in_class_colours(tmp_path):
    pytest.importorskip("rerun")
    palette = SYNTHETIC_CLASSES.palette
    classes = torch.arange(100) % len(palette)
    cloud = GaussianCloud.from_points(torch.rand(100, 3), torch.rand(100, 3), palette[classes], torch.full((100,), .01))
    positions = [(0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (1.0, 1.0, 0.0), (0.1, 0.0, 0.0)]
    viewer = Viewer(tmp_path / "view.rrd", palette, SYNTHETIC_CLASSES.names, colors="class", max_points=10)
    viewer.refresh(FakeSlam(positions, [(3, 0)], cloud))
    viewer.close()
    rows = read_recording(tmp_path / "view.rrd")
    np.testing.assert_allclose(rows["/world/loops"][0]["LineStrips3D:strips"], [[positions[3], positions[0]]])
    assert rows["/world/trajectory"][0]["LineStrips3D:colors"] == [int.from_bytes(bytes([*TRAJECTORY_COLOR, 255]))]
    points = rows["/world/map"][0]
    keep = np.linspace(0, 99, 10).round().astype(int)
    np.testing.assert_allclose(points["Points3D:positions"], cloud.means[keep].numpy(), atol=1e-6)
    assert points["Points3D:class_ids"] == classes[keep].tolist() and points.get("Points3D:colors") is None
    context = next(r["AnnotationContext:context"][0] for r in rows["/world"] if "AnnotationContext:context" in r)
    assert [c["class_description"]["info"]["label"] for c in context] == list(SYNTHETIC_CLASSES.names)


def test_a_run_without_the_viewer_never_imports_rerun(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "rerun", None)  # any import of rerun now fails
    assert main(["run", "--dataset", "synthetic", "--frames", "2", *FAST, "--out", str(tmp_path)]) == 0
    assert not (tmp_path / "gausem.rrd").exists() and "viewer:" not in capsys.readouterr().out
    with pytest.raises(ImportError, match="pip install rerun-sdk"):
        Viewer(tmp_path / "view.rrd", SYNTHETIC_CLASSES.palette)


def test_the_native_viewer_without_a_display_is_refused_before_the_run(tmp_path, monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr(sys, "platform", "linux")
    with pytest.raises(ValueError, match="native needs a display"):
        Viewer(tmp_path / "view.rrd", SYNTHETIC_CLASSES.palette, mode="native")
