"""User-facing outputs: Gaussian PLY (header and round trip), montage PNG, metrics JSON and summary, trajectory plot."""
import json
import math
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from gausem_core.gaussians import GaussianCloud
from gausem_core.io.metrics import format_summary, git_commit, to_jsonable, write_metrics_json
from gausem_core.io.montage import COLORBAR_WIDTH, HEADER_HEIGHT, MontageRow, write_montage
from gausem_core.io.plots import write_trajectory_plot
from gausem_core.io.ply import SH_C0, read_gaussian_ply, read_ply_vertices, write_gaussian_ply

SPLAT_PROPERTIES = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1",
                    "scale_2", "rot_0", "rot_1", "rot_2", "rot_3", "sem_r", "sem_g", "sem_b"]


def random_cloud(n: int) -> GaussianCloud:
    return GaussianCloud.from_points(torch.randn(n, 3), torch.rand(n, 3), torch.rand(n, 3),
                                     torch.rand(n) * 0.1 + 0.01, torch.rand(n) * 0.9 + 0.05)


def header_lines(path: Path) -> list[str]:
    data = path.read_bytes()
    return data[: data.index(b"end_header\n")].decode("ascii").splitlines() + ["end_header"]


# --- PLY ------------------------------------------------------------------------------------------------------------
def test_ply_header_follows_the_3dgs_layout(tmp_path):
    write_gaussian_ply(tmp_path / "map.ply", random_cloud(50), torch.arange(50) % 4)
    lines = header_lines(tmp_path / "map.ply")
    assert lines[:2] == ["ply", "format binary_little_endian 1.0"]
    assert "element vertex 50" in lines and lines[-1] == "end_header"
    properties = [line.split()[1:] for line in lines if line.startswith("property")]
    assert properties == [["float", p] for p in SPLAT_PROPERTIES] + [["int", "class_id"]]
    header_bytes = len("\n".join(lines)) + 1
    assert (tmp_path / "map.ply").stat().st_size == header_bytes + 50 * (20 * 4 + 4)


def test_ply_stores_3dgs_conventions(tmp_path):
    cloud = GaussianCloud.from_points(torch.zeros(2, 3), torch.tensor([[0.5, 1.0, 0.0], [0.2, 0.2, 0.2]]),
                                      torch.zeros(2, 3), torch.tensor([0.1, 0.2]), torch.tensor([0.5, 0.9]))
    write_gaussian_ply(tmp_path / "map.ply", cloud)
    v = read_ply_vertices(tmp_path / "map.ply")
    np.testing.assert_allclose(v["f_dc_0"][0], 0.0, atol=1e-7)
    np.testing.assert_allclose(v["f_dc_1"][0], 0.5 / SH_C0, rtol=1e-6)
    np.testing.assert_allclose(v["opacity"], [0.0, math.log(0.9 / 0.1)], atol=1e-6)
    for k in range(3):
        np.testing.assert_allclose(v[f"scale_{k}"], np.log([0.1, 0.2]), rtol=1e-6)
    np.testing.assert_array_equal(np.stack([v[f"rot_{k}"] for k in range(4)], 1), [[1, 0, 0, 0]] * 2)
    assert "class_id" not in v


def test_ply_round_trip(tmp_path):
    cloud, ids = random_cloud(37), torch.randint(0, 20, (37,))
    write_gaussian_ply(tmp_path / "map.ply", cloud, ids)
    back, back_ids = read_gaussian_ply(tmp_path / "map.ply")
    for name, tensor in cloud.tensors().items():
        torch.testing.assert_close(getattr(back, name), tensor, atol=1e-6, rtol=1e-6)
    assert torch.equal(back_ids, ids)
    write_gaussian_ply(tmp_path / "empty.ply", GaussianCloud.empty())
    empty, no_ids = read_gaussian_ply(tmp_path / "empty.ply")
    assert len(empty) == 0 and no_ids is None


def test_ply_errors(tmp_path):
    with pytest.raises(ValueError, match="class_ids"):
        write_gaussian_ply(tmp_path / "map.ply", random_cloud(3), torch.zeros(4))
    write_gaussian_ply(tmp_path / "map.ply", random_cloud(3))
    data = (tmp_path / "map.ply").read_bytes()
    (tmp_path / "cut.ply").write_bytes(data[:-5])
    with pytest.raises(ValueError, match="truncated"):
        read_ply_vertices(tmp_path / "cut.ply")
    (tmp_path / "ascii.ply").write_bytes(data.replace(b"binary_little_endian", b"ascii"))
    with pytest.raises(ValueError, match="binary_little_endian"):
        read_ply_vertices(tmp_path / "ascii.ply")
    v = read_ply_vertices(tmp_path / "map.ply")
    v["scale_1"] = v["scale_1"] + 1.0
    end = data.index(b"end_header\n") + len(b"end_header\n")
    table = np.empty(3, dtype=[(name, "<f4") for name in SPLAT_PROPERTIES])
    for name in SPLAT_PROPERTIES:
        table[name] = v[name]
    (tmp_path / "aniso.ply").write_bytes(data[:end] + table.tobytes())
    with pytest.raises(ValueError, match="anisotropic"):
        read_gaussian_ply(tmp_path / "aniso.ply")


# --- montage --------------------------------------------------------------------------------------------------------
def test_montage_png_size_and_panels(tmp_path):
    h, w = 12, 16
    rgb = np.random.default_rng(0).integers(0, 256, (h, w, 3), dtype=np.uint8)
    gt = np.full((h, w), 2.0, np.float32)
    gt[:, :4] = 0  # no ground-truth depth: black
    rows = [MontageRow(rgb, torch.rand(h, w, 3), np.zeros((h, w, 3)), gt + 0.1, gt),
            MontageRow(rgb, rgb, rgb, torch.from_numpy(gt), torch.from_numpy(gt))]
    image = write_montage(tmp_path / "montage.png", rows, max_depth_error=0.1)
    png = cv2.cvtColor(cv2.imread(str(tmp_path / "montage.png")), cv2.COLOR_BGR2RGB)
    assert png.shape == (HEADER_HEIGHT + 2 * h, 4 * w + COLORBAR_WIDTH, 3)
    np.testing.assert_array_equal(png, image)
    second = png[HEADER_HEIGHT + h:]
    np.testing.assert_array_equal(second[:, :w], rgb)  # input panel (no label drawn)
    error_first, error_second = png[HEADER_HEIGHT:HEADER_HEIGHT + h, 3 * w:4 * w], second[:, 3 * w:4 * w]
    assert (error_first[:, :4] == 0).all() and (error_second[:, :4] == 0).all()
    hot, cold = cv2.applyColorMap(np.uint8([[255, 0]]), cv2.COLORMAP_INFERNO)[0, :, ::-1]
    assert (error_first[:, 4:] == hot).all() and (error_second[:, 4:] == cold).all()


def test_montage_rejects_mixed_sizes(tmp_path):
    small, big = np.zeros((4, 4, 3)), np.zeros((5, 4, 3))
    row = MontageRow(small, small, big, np.ones((4, 4)), np.ones((4, 4)))
    with pytest.raises(ValueError, match="sizes"):
        write_montage(tmp_path / "m.png", [row])
    with pytest.raises(ValueError, match="no rows"):
        write_montage(tmp_path / "m.png", [])


# --- metrics and plots ----------------------------------------------------------------------------------------------
def test_metrics_json_with_provenance(tmp_path):
    metrics = {"ate": {"rmse": np.float64(0.0123), "max": 0.05}, "psnr": math.inf, "loop": {"precision": math.nan},
               "frames": np.int64(200), "per_class_iou": np.array([0.5, 0.25])}
    written = write_metrics_json(tmp_path / "metrics.json", metrics, parameters={"mapping.iterations": 40,
                                                                                 "out": tmp_path})
    loaded = json.loads((tmp_path / "metrics.json").read_text())
    assert loaded == written
    assert loaded["metrics"] == {"ate": {"rmse": 0.0123, "max": 0.05}, "psnr": None, "loop": {"precision": None},
                                 "frames": 200, "per_class_iou": [0.5, 0.25]}
    assert loaded["parameters"] == {"mapping.iterations": 40, "out": str(tmp_path)}
    assert loaded["device"].startswith("cpu") and loaded["timestamp"].endswith("+00:00")
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=Path(__file__).parent, capture_output=True, text=True)
    assert loaded["git_commit"] == (head.stdout.strip() if head.returncode == 0 else None)
    assert git_commit(tmp_path) is None  # not inside a checkout
    with pytest.raises(ValueError, match="cannot convert object"):
        to_jsonable({"bad": object()})


def test_format_summary():
    text = format_summary({"ate": {"rmse": 0.012345678}, "loop": {"f1": math.nan}, "frames": 200,
                           "per_class_iou": [0.1, 0.2, 0.3]})
    assert text.splitlines() == ["ate.rmse       0.01235", "loop.f1        n/a", "frames         200",
                                 "per_class_iou  [3 values]"]


def test_trajectory_plot_png(tmp_path):
    t = np.linspace(0, 2 * np.pi, 50)
    reference = np.column_stack([np.cos(t), np.sin(t), 0.1 * t])
    write_trajectory_plot(tmp_path / "traj.png", reference + 0.01, reference, title="test", size_px=(800, 400))
    image = cv2.imread(str(tmp_path / "traj.png"))
    assert image.shape == (400, 800, 3) and image.std() > 0
    with pytest.raises(ValueError, match="estimate"):
        write_trajectory_plot(tmp_path / "bad.png", np.zeros((0, 3)))
