"""Dataset readers on tiny fabricated folders in each real layout, the shared helpers, and the real TUM sequence."""
import math

import cv2
import numpy as np
import pytest
import torch

from gausem_core.data import (NYU40_CLASSES, SCANNET20_CLASSES, ClassTable, Frame, ReplicaDataset, ScanNetDataset,
                              SyntheticDataset, TumDataset, open_dataset, resize_frame)
from gausem_core.data.classes import nyu40_to_scannet20
from gausem_core.data.tum import Undistortion, associate, nearest_within, read_calibration, register_depth
from gausem_core.geometry import PinholeCamera

W, H = 8, 6


def write_png(path, image):
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), image)


def rgb_image(value):
    return np.full((H, W, 3), value, np.uint8)


def make_tum(root, n=3, offset=0.004, calib=None, associations=False):
    """n frames at 10 Hz; depth stamps shifted by ``offset``; ground truth every 5 ms except near frame 2."""
    rgb_lines, depth_lines, assoc = [], [], []
    for i in range(n):
        t = 100.0 + 0.1 * i
        write_png(root / "rgb" / f"{t:.6f}.png", rgb_image(10 * i))
        write_png(root / "depth" / f"{t + offset:.6f}.png", np.full((H, W), 5000 * (i + 1), np.uint16))
        rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png")
        depth_lines.append(f"{t + offset:.6f} depth/{t + offset:.6f}.png")
        assoc.append(f"{t:.6f} rgb/{t:.6f}.png {t + offset:.6f} depth/{t + offset:.6f}.png")
    (root / "rgb.txt").write_text("# color images\n# timestamp filename\n" + "\n".join(rgb_lines) + "\n")
    (root / "depth.txt").write_text("# depth\n" + "\n".join(depth_lines) + "\n")
    # rotation of 90 deg about z: q = (0, 0, sin 45, cos 45); no sample within 0.02 s of t = 100.2
    s = math.sqrt(0.5)
    gt = [f"{100.0 + 0.005 * k:.4f} 1.0 2.0 {0.001 * k:.3f} 0 0 {s} {s}" for k in range(30)]
    (root / "groundtruth.txt").write_text("# ground truth\n" + "\n".join(gt) + "\n")
    if calib is not None:
        (root / "calib.txt").write_text(calib)
    if associations:
        (root / "associations.txt").write_text("\n".join(assoc) + "\n")
    return root


# --- association ---------------------------------------------------------------------------------------------------
def test_associate_matches_closest_unique_pairs_within_tolerance():
    assert associate([0.0, 0.1, 0.2, 0.3], [0.005, 0.095, 0.33, 0.301]) == [(0, 0), (1, 1), (3, 3)]
    # 0.008 is closer to 0.01 than to 0.0, and each stamp is used once
    assert associate([0.0, 0.01], [0.008]) == [(1, 0)]
    assert associate([0.0], [0.5]) == []


def test_nearest_within():
    stamps = np.array([0.0, 0.01, 0.02, 1.0])
    assert nearest_within([0.004, 0.016, 0.5, 1.019, 5.0], stamps).tolist() == [0, 2, -1, 3, -1]
    assert nearest_within([0.0], np.array([])).tolist() == [-1]


# --- TUM -------------------------------------------------------------------------------------------------------------
def test_tum_without_calib_uses_folder_intrinsics_depth_scale_and_ground_truth(tmp_path):
    ds = TumDataset(make_tum(tmp_path / "rgbd_dataset_freiburg2_xyz"))
    assert len(ds) == 3 and ds.name == "rgbd_dataset_freiburg2_xyz" and ds.class_table is None
    assert ds.camera == PinholeCamera(520.9, 521.0, 325.6, 250.2, W, H)  # fr2, pixel centres shifted by 0.5
    f = ds[1]
    assert f.timestamp == pytest.approx(100.1) and f.rgb[0, 0, 0] == 10 and f.labels is None
    assert np.all(f.depth == 2.0)  # 10000 / 5000
    expected = np.array([[0, -1, 0, 1.0], [1, 0, 0, 2.0], [0, 0, 1, 0.02], [0, 0, 0, 1]])
    np.testing.assert_allclose(f.gt_pose, expected, atol=1e-9)  # t = 100.1 -> GT sample k = 20
    assert ds[2].gt_pose is None  # no ground truth within 0.02 s
    assert ds[-1].index == 2
    with pytest.raises(IndexError):
        ds[3]


def test_tum_default_intrinsics_are_freiburg1(tmp_path):
    assert TumDataset(make_tum(tmp_path / "my_sequence")).camera.fx == 517.3


def test_tum_associations_and_calib(tmp_path):
    root = make_tum(tmp_path / "seq", offset=0.03, calib="# fx fy cx cy scale w h\n100 101 3.5 2.5 1000 8 6\n",
                    associations=True)
    ds = TumDataset(root)  # 0.03 s apart: only associations.txt pairs them
    assert len(ds) == 3
    assert ds.camera == PinholeCamera(100.0, 101.0, 4.0, 3.0, W, H)
    assert np.all(ds[0].depth == 5.0)  # 5000 / 1000
    (root / "associations.txt").unlink()
    with pytest.raises(ValueError, match="no associated"):
        TumDataset(root)


def test_tum_calib_without_scale_and_bad_calib(tmp_path):
    root = make_tum(tmp_path / "seq", calib="200 200 3.5 2.5\n")
    ds = TumDataset(root)
    assert ds.camera.fx == 200 and ds.depth_scale == 5000 and (ds.camera.width, ds.camera.height) == (W, H)
    (root / "calib.txt").write_text("200 200 3.5\n")
    with pytest.raises(ValueError, match="calib.txt:1"):
        TumDataset(root)


def test_tum_stride_max_frames_and_resize(tmp_path):
    ds = TumDataset(make_tum(tmp_path / "seq", n=5), stride=2, max_frames=2, size=(4, 3))
    assert len(ds) == 2
    f = ds[1]
    assert f.index == 2 and f.rgb.shape == (3, 4, 3) and f.depth.shape == (3, 4)
    assert f.camera.fx == pytest.approx(517.3 / 2) and f.camera.cx == pytest.approx((318.6 + 0.5) / 2)
    assert len(TumDataset(make_tum(tmp_path / "seq5", n=5), stride=2)) == 3


def test_start_skips_the_first_source_frames(tmp_path):
    root = make_tum(tmp_path / "seq", n=5)
    ds = TumDataset(root, start=1, stride=2)
    assert len(ds) == 2 and [f.index for f in ds] == [1, 3]
    assert len(TumDataset(root, start=5)) == 0
    with pytest.raises(ValueError, match="start"):
        TumDataset(root, start=-1)


def test_resize_frame_area_colour_nearest_depth_labels():
    rgb = np.zeros((4, 4, 3), np.uint8)
    rgb[:2, :2] = 200  # the top-left 2x2 block averages to 200
    rgb[2, 2] = 100  # the bottom-right block averages to 25
    depth = np.arange(16, dtype=np.float32).reshape(4, 4)
    labels = np.arange(16).reshape(4, 4)
    camera = PinholeCamera(4.0, 4.0, 2.0, 2.0, 4, 4)
    f = resize_frame(Frame(0, 0.0, rgb, depth, labels, camera), 2, 2)
    assert f.rgb[..., 0].tolist() == [[200, 0], [0, 25]]
    # output pixel centres 0.5, 1.5 map to input 1.0, 3.0 -> input pixels 1 and 3
    assert f.depth.tolist() == [[5, 7], [13, 15]] and f.labels.tolist() == [[5, 7], [13, 15]]
    assert f.camera == PinholeCamera(2.0, 2.0, 1.0, 1.0, 2, 2)


def test_frame_validation_and_depth_sanitising():
    camera = PinholeCamera(4.0, 4.0, 2.0, 1.5, 4, 3)
    depth = np.array([[1, np.nan, np.inf, -2]] * 3, np.float64)
    f = Frame(0, 0.0, np.zeros((3, 4, 3), np.uint8), depth, None, camera)
    assert f.depth.dtype == np.float32 and f.depth[0].tolist() == [1, 0, 0, 0]
    with pytest.raises(ValueError, match="depth size"):
        Frame(0, 0.0, np.zeros((3, 4, 3), np.uint8), np.zeros((2, 4)), None, camera)
    with pytest.raises(ValueError, match="uint8"):
        Frame(0, 0.0, np.zeros((3, 4, 3)), np.zeros((3, 4)), None, camera)
    with pytest.raises(ValueError, match="camera"):
        Frame(0, 0.0, np.zeros((3, 5, 3), np.uint8), np.zeros((3, 5)), None, camera)


def test_tum_errors_missing_corrupt_and_mismatched_files(tmp_path):
    root = make_tum(tmp_path / "missing")
    next((root / "depth").iterdir()).unlink()
    with pytest.raises(FileNotFoundError, match="missing file"):
        TumDataset(root)

    root = make_tum(tmp_path / "corrupt")
    sorted((root / "rgb").iterdir())[1].write_bytes(b"not a png")
    ds = TumDataset(root)
    with pytest.raises(ValueError, match="corrupt, frame 1: cannot decode"):
        ds[1]

    root = make_tum(tmp_path / "mismatch")
    write_png(sorted((root / "depth").iterdir())[0], np.zeros((3, 4), np.uint16))
    with pytest.raises(ValueError, match="depth size"):
        TumDataset(root)[0]

    with pytest.raises(FileNotFoundError):
        TumDataset(tmp_path / "nowhere")
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "rgb.txt").write_text("# nothing\n")
    (empty / "depth.txt").write_text("")
    with pytest.raises(ValueError, match="no associated"):
        TumDataset(empty)


def test_register_depth_reprojects_a_plane_into_the_colour_camera():
    camera = PinholeCamera(20.0, 20.0, 10.0, 8.0, 20, 16)
    depth_to_color = np.eye(4)
    depth_to_color[0, 3] = -0.1  # colour camera 10 cm to the right of the depth camera
    registered = register_depth(np.full((16, 20), 2.0, np.float32), camera, camera, depth_to_color)
    # a fronto-parallel plane stays at 2 m and shifts left by fx * 0.1 / 2 = 1 pixel: the last column is unseen
    assert np.all(registered[:, :-1] == pytest.approx(2.0)) and np.all(registered[:, -1] == 0)
    # nearest surface wins where two depth pixels land on one colour pixel
    depth = np.full((16, 20), 2.0, np.float32)
    depth[:, 5] = 1.0
    registered = register_depth(depth, camera, camera, np.eye(4))
    assert registered[0, 5] == 1.0


def test_tum_depth_registration_from_calib(tmp_path):
    calib = ("4 4 3.5 2.5 5000 8 6\ndepth_intrinsics 4 4 3.5 2.5 8 6\n"
             "depth_to_color 1 0 0 0  0 1 0 0  0 0 1 0\n")
    ds = TumDataset(make_tum(tmp_path / "seq", calib=calib))
    assert ds.depth_registered and np.all(ds[0].depth == 1.0)


def test_tum_unregistered_depth_without_calibration_warns(tmp_path):
    root = make_tum(tmp_path / "seq", calib="585 585 319.5 239.5 5000\n# RGB is NOT registered to depth\n")
    with pytest.warns(UserWarning, match="not registered"):
        ds = TumDataset(root)
    assert not ds.depth_registered
    assert TumDataset(root, depth_registered=True).depth_registered


# --- ScanNet -------------------------------------------------------------------------------------------------------
def make_scannet(root, n=2, tsv=True):
    k_color = "32 0 7.5 0\n0 32 5.5 0\n0 0 1 0\n0 0 0 1\n"
    k_depth = "16 0 3.5 0\n0 16 2.5 0\n0 0 1 0\n0 0 0 1\n"
    (root / "intrinsic").mkdir(parents=True)
    (root / "intrinsic" / "intrinsic_color.txt").write_text(k_color)
    (root / "intrinsic" / "intrinsic_depth.txt").write_text(k_depth)
    for i in range(n):
        write_png(root / "color" / f"{i}.jpg", np.full((2 * H, 2 * W, 3), 60 * (i + 1), np.uint8))
        write_png(root / "depth" / f"{i}.png", np.full((H, W), 1500, np.uint16))
        labels = np.zeros((2 * H, 2 * W), np.uint16)
        labels[:, W:] = 7  # raw id 7 -> nyu40 12 (counter)
        labels[:H, :] = 3  # raw id 3 -> nyu40 39 (otherfurniture)
        write_png(root / "label-filt" / f"{i}.png", labels)
        pose = np.eye(4)
        pose[0, 3] = i
        if i == 1:
            pose[:] = -np.inf
        (root / "pose").mkdir(exist_ok=True)
        np.savetxt(root / "pose" / f"{i}.txt", pose)
    if tsv:
        (root / "scannetv2-labels.combined.tsv").write_text("id\traw_category\tnyu40id\n3\tx\t39\n7\ty\t12\n")
    return root


def test_scannet_reader(tmp_path):
    ds = ScanNetDataset(make_scannet(tmp_path / "scene0000_00"))
    assert len(ds) == 2 and ds.class_table is NYU40_CLASSES
    assert ds.camera == PinholeCamera(16.0, 16.0, 4.0, 3.0, W, H)  # depth intrinsics at depth resolution
    f = ds[0]
    assert f.rgb.shape == (H, W, 3) and abs(int(f.rgb[3, 3, 0]) - 60) <= 2  # colour resized to depth size
    assert np.all(f.depth == 1.5)
    assert f.labels[0, 0] == 39 and f.labels[-1, 0] == 0 and f.labels[-1, -1] == 12
    assert f.gt_pose[0, 3] == 0 and ds[1].gt_pose is None and ds[1].timestamp == pytest.approx(1 / 30)
    twenty = ScanNetDataset(tmp_path / "scene0000_00", classes="scannet20")
    assert twenty.class_table is SCANNET20_CLASSES
    assert twenty[0].labels[0, 0] == 20 and twenty[0].labels[-1, -1] == 12


def test_scannet_without_label_map_warns_and_drops_labels(tmp_path):
    root = make_scannet(tmp_path / "scene", tsv=False)
    with pytest.warns(UserWarning, match="no labels"):
        ds = ScanNetDataset(root)
    assert ds.class_table is None and ds[0].labels is None
    nyu = ScanNetDataset(root, label_map="nyu40")
    assert nyu[0].labels[0, 0] == 3


def test_scannet_errors(tmp_path):
    root = make_scannet(tmp_path / "scene")
    (root / "pose" / "1.txt").unlink()
    with pytest.raises(FileNotFoundError, match="1.txt"):
        ScanNetDataset(root)
    (root / "pose" / "1.txt").write_text("1 2 3\n")
    with pytest.raises(ValueError, match="expected 4x4"):
        ScanNetDataset(root)[1]
    with pytest.raises(ValueError, match="classes"):
        ScanNetDataset(root, classes="ade20k")
    with pytest.raises(ValueError, match="no colour frames"):
        ScanNetDataset(tmp_path)


# --- Replica -------------------------------------------------------------------------------------------------------
def make_replica(root, n=2):
    for i in range(n):
        write_png(root / "results" / f"frame{i:06d}.jpg", rgb_image(100))
        write_png(root / "results" / f"depth{i:06d}.png", np.full((H, W), 13107, np.uint16))
    poses = [np.eye(4) for _ in range(n)]
    poses[1][:3, 3] = [0.5, 0, 0]
    (root / "traj.txt").write_text("\n".join(" ".join(f"{v:g}" for v in p.ravel()) for p in poses) + "\n")
    return root


def test_replica_reader(tmp_path):
    camera = PinholeCamera(6.0, 6.0, 4.0, 3.0, W, H)
    ds = ReplicaDataset(make_replica(tmp_path / "room0"), camera=camera)
    f = ds[1]
    assert len(ds) == 2 and np.allclose(f.depth, 2.0) and f.gt_pose[0, 3] == 0.5 and f.labels is None
    with pytest.raises(ValueError, match="camera is 1200x680"):
        ReplicaDataset(tmp_path / "room0")[0]  # the default camera does not fit 8x6 images
    (tmp_path / "room0" / "traj.txt").write_text("1 2 3\n")
    with pytest.raises(ValueError, match="traj.txt:1: expected 16"):
        ReplicaDataset(tmp_path / "room0")


# --- open_dataset and class tables -------------------------------------------------------------------------------
def test_open_dataset_specs(tmp_path):
    assert isinstance(open_dataset("synthetic"), SyntheticDataset)
    loop = open_dataset("synthetic:loop", max_frames=3)
    assert loop.name == "synthetic_loop" and len(loop) == 3
    assert len(open_dataset(f"tum:{make_tum(tmp_path / 'tum')}")) == 3
    assert len(open_dataset(f"replica:{make_replica(tmp_path / 'replica')}", size=(W, H))) == 2
    assert len(open_dataset(f"scannet:{make_scannet(tmp_path / 'scannet')}")) == 2
    for spec, message in [("kitti:/x", "unknown dataset kind"), ("tum", "lacks a folder"),
                          ("synthetic:spiral", "unknown synthetic sequence")]:
        with pytest.raises(ValueError, match=message):
            open_dataset(spec)


def test_class_tables(tmp_path):
    table = ClassTable(("a", "b"), np.array([[0, 0, 0], [255, 0, 10]]))
    assert table.id_of("b") == 1 and table.ids.tolist() == [0, 1]
    assert torch.allclose(table.palette[1], torch.tensor([1.0, 0.0, 10 / 255]))
    assert table.colorize(np.array([[1, 0]])).tolist() == [[[255, 0, 10], [0, 0, 0]]]
    with pytest.raises(ValueError, match="outside"):
        table.colorize(np.array([2]))
    with pytest.raises(ValueError, match="distinct"):
        ClassTable(("a", "b"), np.zeros((2, 3)))
    table.save(tmp_path / "classes.txt")
    loaded = ClassTable.load(tmp_path / "classes.txt")
    assert loaded.names == table.names and np.array_equal(loaded.colors, table.colors)
    assert len(NYU40_CLASSES) == 41 and len(SCANNET20_CLASSES) == 21
    lut = nyu40_to_scannet20()
    assert lut[NYU40_CLASSES.id_of("desk")] == SCANNET20_CLASSES.id_of("desk") and lut[13] == 0  # blinds: not in 20


# --- real data -------------------------------------------------------------------------------------------------------
def test_real_tum_fr1_rpy(shared_data):
    ds = TumDataset(shared_data / "tum_fr1_rpy")
    assert len(ds) == 200 and ds.depth_registered
    assert "(fx 517.3 fy 516.5 cx 318.6 cy 255.3, 640x480, lens distortion 0.2624 -0.9531" in ds.description
    assert ds.camera.fx == pytest.approx(546.75, abs=0.01) and (ds.camera.width, ds.camera.height) == (640, 480)
    f = ds[100]
    valid = f.depth[f.depth > 0]
    assert valid.size > 0.5 * f.depth.size and 0.5 < np.median(valid) < 4.0  # a desk scene at arm's length
    assert all(ds.gt_poses[i] is not None for i in range(len(ds)))
    assert np.allclose(f.gt_pose[:3, :3] @ f.gt_pose[:3, :3].T, np.eye(3), atol=1e-6)


# --- TUM layouts as they come: label folders, class tables, intrinsics files -----------------------------------------
def add_labels(root, folder, n=3):
    """16-bit class ids 0..2 under ``root/folder`` for the frames make_tum wrote."""
    for k, line in enumerate((root / "rgb.txt").read_text().splitlines()[2:2 + n]):
        stem = line.split()[1].split("/")[1][:-4]
        labels = np.zeros((H, W), np.uint16)
        labels[:, :k + 1] = k
        write_png(root / folder / f"{stem}.png", labels)


@pytest.mark.parametrize("folder", ["labels", "semantic", "label"])
def test_tum_reads_labels_from_each_label_folder(tmp_path, folder):
    root = make_tum(tmp_path / "seq_fr1")
    add_labels(root, folder)
    ClassTable(("a", "b", "c"), np.array([[1, 2, 3], [4, 5, 6], [7, 8, 9]])).save(root / "classes.txt")
    ds = TumDataset(root)
    assert ds.labels_dir.name == folder and ds[2].labels.max() == 2 and len(ds.class_table) == 3
    assert f"from {folder}/, 3 classes from classes.txt" in ds.description


def test_tum_class_tables_from_json_and_palette(tmp_path):
    root = make_tum(tmp_path / "seq_fr1")
    add_labels(root, "semantic")
    (root / "classes.json").write_text('{"classes": [{"id": 1, "name": "wall", "color": [10, 20, 30]}, '
                                       '{"id": 0, "name": "floor"}, {"id": 2, "name": "chair"}]}')
    table = TumDataset(root).class_table
    assert table.names == ("floor", "wall", "chair") and table.colors[1].tolist() == [10, 20, 30]
    (root / "classes.json").write_text('["floor", "wall", "chair", "table"]')
    assert TumDataset(root).class_table.names == ("floor", "wall", "chair", "table")
    (root / "classes.json").write_text('{"1": {"name": "wall", "color": [10, 20, 30]}, "0": "floor", '
                                       '"2": {"name": "chair"}}')  # an object keyed by class id
    table = TumDataset(root).class_table
    assert table.names == ("floor", "wall", "chair") and table.colors[1].tolist() == [10, 20, 30]
    (root / "classes.json").unlink()
    (root / "palette.txt").write_text("# r g b\n0 0 0\n255 0 0\n0 255 0\n")
    ds = TumDataset(root)
    assert ds.class_table.names == ("class_0", "class_1", "class_2") and "from palette.txt" in ds.description
    (root / "classes.json").write_text('[{"id": 0, "name": "a"}, {"id": 2, "name": "b"}]')
    with pytest.warns(UserWarning, match=r"no class has the ids \[1\]"):
        assert TumDataset(root).class_table.names == ("a", "class_1", "b")  # the gap assumed, and said
    (root / "classes.json").write_text('[{"id": 0, "name": "a"}, {"id": 0, "name": "b"}]')
    with pytest.raises(ValueError, match="each needs its own id"):
        TumDataset(root)


def test_tum_labels_without_a_table_get_generic_classes_and_say_so(tmp_path):
    root = make_tum(tmp_path / "seq_fr1")
    add_labels(root, "semantic")
    with pytest.warns(UserWarning, match="3 generic classes assumed"):
        ds = TumDataset(root)
    assert len(ds.class_table) == 3 and len({tuple(c) for c in ds.class_table.colors.tolist()}) == 3


def test_tum_intrinsics_from_camera_yaml_then_published_values(tmp_path):
    root = make_tum(tmp_path / "rgbd_dataset_freiburg3_office")
    (root / "camera.yaml").write_text("fx: 300.0\nfy: 301.0\ncx: 3.5\ncy: 2.5\nwidth: 8\nheight: 6\n"
                                      "depth_scale: 1000\n")
    ds = TumDataset(root)
    assert (ds.camera.fx, ds.camera.fy, ds.camera.cx, ds.depth_scale) == (300.0, 301.0, 4.0, 1000.0)
    assert "intrinsics from camera.yaml" in ds.description
    (root / "calib.txt").write_text("200 200 3.5 2.5\n")  # calib.txt comes first
    assert TumDataset(root).camera.fx == 200.0
    (root / "calib.txt").unlink()
    (root / "camera.yaml").unlink()
    ds = TumDataset(root)
    assert ds.camera.fx == 535.4 and "published TUM freiburg3 values" in ds.description
    (root / "camera.yaml").write_text("fx: 300\n")
    with pytest.raises(ValueError, match="camera.yaml: expected the keys fx, fy, cx, cy"):
        TumDataset(root)


def test_lens_distortion_is_read_from_calib_txt_camera_yaml_or_the_published_values(tmp_path):
    calib = tmp_path / "calib.txt"
    calib.write_text("517.3 516.5 318.6 255.3 5000 640 480\ndistortion 0.26 -0.95 -0.005 0.003 1.16\n")
    assert read_calibration(calib).distortion == (0.26, -0.95, -0.005, 0.003, 1.16)
    calib.write_text("517.3 516.5 318.6 255.3\n"
                     "# distortion k1 k2 p1 p2 k3 (images are NOT undistorted): 0.2 -0.9 0 0\n")
    assert read_calibration(calib).distortion == (0.2, -0.9, 0.0, 0.0)  # a comment as the shared TUM folder has it
    calib.write_text("517.3 516.5 318.6 255.3\ndistortion 0.2 0.1\n")
    with pytest.raises(ValueError, match="calib.txt:2: distortion needs k1 k2 p1 p2"):
        read_calibration(calib)
    root = make_tum(tmp_path / "rgbd_dataset_freiburg2_desk")
    (root / "camera.yaml").write_text("fx: 8.0\nfy: 8.0\ncx: 3.5\ncy: 2.5\nk1: 0.1\n")
    ds = TumDataset(root)
    assert ds.undistortion is not None and "lens distortion 0.1 0 0 0 0; undistorted at load into" in ds.description
    (root / "camera.yaml").unlink()
    assert "its published distortion not applied to 8x6 images" in TumDataset(root).description
    full = tmp_path / "rgbd_dataset_freiburg2_xyz"  # the size the published values describe
    write_png(full / "rgb" / "1.0.png", np.full((480, 640, 3), 100, np.uint8))
    write_png(full / "depth" / "1.0.png", np.full((480, 640), 5000, np.uint16))
    (full / "rgb.txt").write_text("1.0 rgb/1.0.png\n")
    (full / "depth.txt").write_text("1.0 depth/1.0.png\n")
    ds = TumDataset(full)
    assert "lens distortion 0.2312 -0.7849 -0.0033 -0.0001 0.9172; undistorted at load" in ds.description
    depth = ds[0].depth
    assert (depth == 1.0).all() and ds.camera.fx > 520.9  # every pixel has a source: a longer focal length
    fr3 = make_tum(tmp_path / "rgbd_dataset_freiburg3_office")
    assert TumDataset(fr3).undistortion is None  # fr3's images are undistorted already


def test_undistortion_samples_where_the_lens_put_each_point():
    camera = PinholeCamera(40.0, 40.0, 32.0, 24.0, 64, 48)
    k1 = 0.2
    v, u = np.mgrid[0:48, 0:64].astype(np.float64)
    color = np.stack([u * 3, v * 4, np.zeros_like(u)], -1).astype(np.uint8)  # channels encode the source pixel
    depth = np.full((48, 64), 2.0, np.float32)
    undistortion = Undistortion(camera, (k1, 0.0, 0.0, 0.0))
    out, out_depth = undistortion.color(color), undistortion.nearest(depth)
    pinhole = undistortion.camera  # every pixel of it sees through the lens: a longer focal length
    assert pinhole.fx > camera.fx and (pinhole.width, pinhole.height) == (64, 48) and (out_depth == 2.0).all()
    x = (u + 0.5 - pinhole.cx) / pinhole.fx  # each output pixel's ray (pixel centres at integer + 0.5)
    y = (v + 0.5 - pinhole.cy) / pinhole.fy
    scale = 1 + k1 * (x * x + y * y)
    source_u, source_v = 40.0 * x * scale + 31.5, 40.0 * y * scale + 23.5  # where the lens put it (OpenCV pixels)
    assert source_u.min() > -0.5 and source_u.max() < 63.5 and source_v.min() > -0.5 and source_v.max() < 47.5
    inside = (source_u >= 0) & (source_u <= 63) & (source_v >= 0) & (source_v <= 47)
    assert np.abs(out[..., 0][inside] - 3 * source_u[inside]).max() < 1.6  # bilinear, then rounded to uint8
    assert np.abs(out[..., 1][inside] - 4 * source_v[inside]).max() < 2.1


def test_tum_unnamed_camera_warns_that_freiburg1_is_assumed(tmp_path):
    with pytest.warns(UserWarning, match="freiburg1 values, assumed"):
        TumDataset(make_tum(tmp_path / "my_sequence"))
