"""msg_adapters: stamps, images, CameraInfo, poses, the Gaussian map PointCloud2 and the typed records."""
import dataclasses
import math

import numpy as np
import pytest
import torch

pytest.importorskip("sensor_msgs.msg")

from builtin_interfaces.msg import Time  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image, PointField  # noqa: E402

import msg_adapters as ma  # noqa: E402
from gausem_core.gaussians import GaussianCloud  # noqa: E402
from gausem_core.geometry import PinholeCamera, se3_exp  # noqa: E402
from msg_adapters.gaussian_map import pack_rgb, unpack_rgb  # noqa: E402
from msg_adapters.pointcloud2 import pointcloud2_to_structured, structured_to_pointcloud2  # noqa: E402

HEADER = ma.make_header(1305031102.175304, "camera_optical")


def random_pose(rng) -> np.ndarray:
    return se3_exp(torch.from_numpy(rng.normal(size=6) * [1, 1, 1, 1.5, 1.5, 1.5])).numpy()


# --- stamps ---------------------------------------------------------------------------------------------------------
def test_stamp_hand_values():
    assert ma.seconds_to_time(1.5) == Time(sec=1, nanosec=500_000_000)
    assert ma.seconds_to_ns(0.1) == 100_000_000
    assert ma.time_to_seconds(Time(sec=2, nanosec=250_000_000)) == 2.25


def test_float_stamps_survive_time_exactly():
    rng = np.random.default_rng(1)
    for t in list(1.3e9 + rng.random(200) * 1e6) + [0.0, 1305031102.175304, 1e-9]:
        assert ma.time_to_seconds(ma.seconds_to_time(t)) == t
    assert ma.header_seconds(HEADER) == 1305031102.175304


@pytest.mark.parametrize("bad", [-1.0, math.nan, math.inf, 2.0**31])
def test_invalid_stamps_are_rejected(bad):
    with pytest.raises(ValueError):
        ma.seconds_to_time(bad)


# --- images ---------------------------------------------------------------------------------------------------------
def _pixels(encoding, rng):
    dtype, channels = ma.images.ENCODINGS[encoding]
    shape = (5, 7) if channels == 1 else (5, 7, channels)
    if dtype == np.float32:
        return rng.random(shape).astype(np.float32)
    return rng.integers(0, np.iinfo(dtype).max, shape, endpoint=True).astype(dtype)


@pytest.mark.parametrize("encoding", sorted(ma.images.ENCODINGS))
def test_every_encoding_round_trips(encoding):
    pixels = _pixels(encoding, np.random.default_rng(0))
    msg = ma.numpy_to_image(pixels, encoding, HEADER)
    assert (msg.height, msg.width, msg.is_bigendian) == (5, 7, 0)
    assert msg.step == 7 * pixels.itemsize * (pixels.shape[2] if pixels.ndim == 3 else 1)
    np.testing.assert_array_equal(ma.image_to_numpy(msg), pixels)


def _padded(pixels, encoding, pad=5, bigendian=False):
    """An Image with ``pad`` junk bytes after every row."""
    h = pixels.shape[0]
    rows = pixels.astype(pixels.dtype.newbyteorder(">" if bigendian else "<")).reshape(h, -1).view(np.uint8)
    data = np.concatenate([rows, np.full((h, pad), 0xEE, np.uint8)], 1)
    return Image(height=h, width=pixels.shape[1], encoding=encoding, is_bigendian=int(bigendian),
                 step=data.shape[1], data=data.tobytes())


@pytest.mark.parametrize("encoding", ["rgb8", "mono16", "32FC1", "16UC1"])
def test_row_padding_is_skipped(encoding):
    pixels = _pixels(encoding, np.random.default_rng(2))
    np.testing.assert_array_equal(ma.image_to_numpy(_padded(pixels, encoding)), pixels)


@pytest.mark.parametrize("pad", [0, 3])
def test_big_endian_mono16(pad):
    pixels = np.array([[1, 256, 0x1234]], dtype=np.uint16)
    msg = _padded(pixels, "mono16", pad=pad, bigendian=True)
    assert bytes(msg.data[:2]) == b"\x00\x01"
    out = ma.image_to_numpy(msg)
    np.testing.assert_array_equal(out, pixels)
    assert out.dtype == np.uint16 and out.dtype.isnative


def test_bgr_and_alpha_become_rgb():
    rgb = np.array([[[10, 20, 30], [40, 50, 60]]], dtype=np.uint8)
    bgr = ma.numpy_to_image(rgb[..., ::-1], "bgr8", HEADER)
    np.testing.assert_array_equal(ma.image_to_rgb(bgr), rgb)
    np.testing.assert_array_equal(ma.image_to_rgb(ma.rgb_to_image(rgb, HEADER, "bgr8")), rgb)
    assert bytes(ma.rgb_to_image(rgb, HEADER, "bgr8").data[:3]) == bytes([30, 20, 10])
    alpha = np.full((1, 2, 1), 255, np.uint8)
    rgba = np.concatenate([rgb, alpha], 2)
    np.testing.assert_array_equal(ma.image_to_rgb(ma.numpy_to_image(rgba, "rgba8", HEADER)), rgb)
    bgra = np.concatenate([rgb[..., ::-1], alpha], 2)
    np.testing.assert_array_equal(ma.image_to_rgb(ma.numpy_to_image(bgra, "bgra8", HEADER)), rgb)


def _readers(encoding):
    """The typed readers that accept ``encoding`` (rgb, depth, labels)."""
    return [read for read, kinds in ((ma.image_to_rgb, ma.images.COLOR_ENCODINGS),
                                     (ma.image_to_depth, ma.images.DEPTH_ENCODINGS),
                                     (ma.image_to_labels, ma.images.LABEL_ENCODINGS)) if encoding in kinds]


@pytest.mark.parametrize("pad", [0, 3])
@pytest.mark.parametrize("bigendian", [False, True])
@pytest.mark.parametrize("encoding", sorted(ma.images.ENCODINGS))
def test_every_documented_encoding_reads_into_contiguous_arrays_torch_takes(encoding, bigendian, pad):
    """Issue 24: bgr8/bgra8 came back as negative-stride views that torch refused; every encoding, byte order and
    row padding reads back as C-contiguous arrays with the right values."""
    pixels = _pixels(encoding, np.random.default_rng(3))
    msg = _padded(pixels, encoding, pad=pad, bigendian=bigendian)
    np.testing.assert_array_equal(ma.image_to_numpy(msg), pixels)
    for read in _readers(encoding):
        out = read(msg)
        assert out.flags.c_contiguous and torch.as_tensor(out).shape == out.shape
        assert out.shape == pixels.shape[:2] + ((3,) if read is ma.image_to_rgb else ())
    if encoding in ma.images.COLOR_ENCODINGS:
        rgb = pixels[..., 2::-1] if encoding.startswith("bgr") else pixels[..., :3]
        np.testing.assert_array_equal(ma.image_to_rgb(msg), rgb)


def test_depth_16uc1_millimetres_to_metres():
    msg = ma.numpy_to_image(np.array([[0, 1234, 65535]], np.uint16), "16UC1", HEADER)
    depth = ma.image_to_depth(msg)
    assert depth.dtype == np.float32
    np.testing.assert_allclose(depth, [[0.0, 1.234, 65.535]], rtol=1e-6)


def test_depth_32fc1_invalid_values_become_zero():
    raw = np.array([[1.5, np.nan, np.inf, -2.0, 0.0, -np.inf, 9999.0, 2e4, 3e38]], np.float32)
    np.testing.assert_array_equal(ma.image_to_depth(ma.numpy_to_image(raw, "32FC1", HEADER)),
                                  [[1.5, 0, 0, 0, 0, 0, 9999.0, 0, 0]])  # 3e38 (random bytes) crashed the renderer


def test_depth_builders():
    depth = np.array([[1.2344, np.nan, -1.0, 3.0]], np.float32)
    np.testing.assert_array_equal(ma.image_to_numpy(ma.depth_to_image(depth, HEADER, "16UC1")), [[1234, 0, 0, 3000]])
    np.testing.assert_array_equal(ma.image_to_depth(ma.depth_to_image(depth, HEADER)), [[depth[0, 0], 0, 0, 3.0]])
    with pytest.raises(ValueError, match="65.535"):
        ma.depth_to_image(np.array([[70.0]]), HEADER, "16UC1")


def test_labels():
    labels = np.array([[0, 3, 255]])
    for enc in ("mono8", "mono16"):
        out = ma.image_to_labels(ma.labels_to_image(labels, HEADER, enc))
        np.testing.assert_array_equal(out, labels)
        assert out.dtype == np.int64
    with pytest.raises(ValueError, match="outside mono8"):
        ma.labels_to_image(np.array([[256]]), HEADER, "mono8")
    with pytest.raises(ValueError, match="integers"):
        ma.labels_to_image(np.array([[1.0]]), HEADER)


@pytest.mark.parametrize("encoding", ["yuv422", "32FC3", "bayer_rggb8", "8UC3"])
def test_unsupported_encodings_are_named(encoding):
    msg = Image(height=1, width=1, encoding=encoding, step=4, data=b"\0" * 4)
    with pytest.raises(ma.ImageEncodingError) as err:
        ma.image_to_numpy(msg)
    assert encoding in str(err.value) and "rgb8" in str(err.value) and "32FC1" in str(err.value)
    assert isinstance(err.value, ValueError)


def test_wrong_kind_of_image_is_rejected():
    mono = ma.numpy_to_image(np.zeros((2, 2), np.uint8), "mono8", HEADER)
    with pytest.raises(ma.ImageEncodingError, match="colour image encoding 'mono8'"):
        ma.image_to_rgb(mono)
    with pytest.raises(ma.ImageEncodingError, match="depth image"):
        ma.image_to_depth(mono)
    with pytest.raises(ValueError, match="rgb8 needs"):
        ma.numpy_to_image(np.zeros((2, 2), np.uint8), "rgb8", HEADER)


def test_size_mismatches_are_reported():
    msg = ma.numpy_to_image(np.zeros((4, 3, 3), np.uint8), "rgb8", HEADER)
    msg.data = msg.data[:-1]
    with pytest.raises(ValueError, match="expected height\\*step = 4\\*9 = 36"):
        ma.image_to_numpy(msg)
    with pytest.raises(ValueError, match="step 8 is shorter"):
        ma.image_to_numpy(Image(height=1, width=3, encoding="rgb8", step=8, data=b"\0" * 8))


# --- CameraInfo -----------------------------------------------------------------------------------------------------
def test_camera_info_round_trip_and_pixel_centre_shift():
    info = CameraInfo(width=640, height=480, k=[525.0, 0, 319.5, 0, 526.0, 239.5, 0, 0, 1])
    cam = ma.camera_info_to_camera(info)
    assert cam == PinholeCamera(525.0, 526.0, 320.0, 240.0, 640, 480)
    back = ma.camera_to_camera_info(cam, HEADER)
    np.testing.assert_array_equal(back.k, info.k)
    np.testing.assert_array_equal(np.asarray(back.p).reshape(3, 4)[:, :3], np.asarray(info.k).reshape(3, 3))
    assert ma.camera_info_to_camera(back) == cam and back.header.frame_id == HEADER.frame_id


@pytest.mark.parametrize("k, size, match", [
    ([0.0] * 9, (640, 480), "invalid K"),
    ([525.0, 0, 319.5, 0, math.nan, 239.5, 0, 0, 1], (640, 480), "invalid K"),
    ([525.0, 0, 319.5, 0, 525.0, 239.5, 0, 0, 1], (0, 480), "image size 0x480"),
    ([525.0, 0, 319.5, 0, 525.0, 239.5, 0, 0, 1], (640, 0), "image size 640x0"),
    ([math.inf, 0, 319.5, 0, 525.0, 239.5, 0, 0, 1], (640, 480), "invalid K"),
    ([525.0, 0, math.nan, 0, 525.0, 239.5, 0, 0, 1], (640, 480), "invalid K"),
    ([-525.0, 0, 319.5, 0, 525.0, 239.5, 0, 0, 1], (640, 480), "invalid K"),
    ([525.0, 0, 319.5, 0, 0.0, 239.5, 0, 0, 1], (640, 480), "invalid K"),
])
def test_camera_info_errors(k, size, match):
    with pytest.raises(ValueError, match=match):
        ma.camera_info_to_camera(CameraInfo(width=size[0], height=size[1], k=k))


# --- poses ----------------------------------------------------------------------------------------------------------
def test_quaternion_hand_value_and_pose_round_trips():
    quarter_turn_z = np.array([[0, -1, 0, 1], [1, 0, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]], float)
    q = ma.matrix_to_pose(quarter_turn_z).orientation
    np.testing.assert_allclose([q.x, q.y, q.z, q.w], [0, 0, math.sqrt(0.5), math.sqrt(0.5)], atol=1e-12)
    rng = np.random.default_rng(3)
    for _ in range(20):
        pose = random_pose(rng)
        np.testing.assert_allclose(ma.pose_to_matrix(ma.matrix_to_pose(pose)), pose, atol=1e-12)
        np.testing.assert_allclose(ma.pose_stamped_to_matrix(ma.matrix_to_pose_stamped(pose, HEADER)), pose, atol=1e-12)
        tf = ma.matrix_to_transform(pose, ma.make_header(2.0, "map"), "camera")
        assert (tf.header.frame_id, tf.child_frame_id) == ("map", "camera")
        np.testing.assert_allclose(ma.transform_to_matrix(tf), pose, atol=1e-12)
        odom = ma.matrix_to_odometry(pose, ma.make_header(2.0, "map"), "camera")
        assert (odom.header.frame_id, odom.child_frame_id) == ("map", "camera")
        np.testing.assert_allclose(ma.odometry_to_matrix(odom), pose, atol=1e-12)


def test_path_round_trip():
    rng = np.random.default_rng(4)
    poses = [(1305031102.175304 + i / 30, random_pose(rng)) for i in range(5)]
    path = ma.poses_to_path(poses, "map")
    assert path.header.frame_id == "map" and ma.header_seconds(path.header) == poses[-1][0]
    back = ma.path_to_poses(path)
    assert [t for t, _ in back] == [t for t, _ in poses]
    for (_, a), (_, b) in zip(back, poses):
        np.testing.assert_allclose(a, b, atol=1e-12)
    assert ma.poses_to_path([], "map", stamp=3.0).poses == []


@pytest.mark.parametrize("bad", [np.eye(3), np.diag([2.0, 1, 1, 1]), np.diag([1.0, 1, -1, 1]), np.full((4, 4), np.nan)])
def test_non_rigid_matrices_are_rejected(bad):
    with pytest.raises(ValueError, match="pose"):
        ma.matrix_to_pose(bad)


# --- Gaussian map ---------------------------------------------------------------------------------------------------
PALETTE = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]])


def _cloud(n=50):
    labels = torch.randint(0, len(PALETTE), (n,))
    return GaussianCloud.from_points(torch.randn(n, 3), torch.rand(n, 3), PALETTE[labels] * 0.9,
                                     torch.rand(n) * 0.1 + 0.01, torch.rand(n) * 0.9 + 0.05), labels


def test_map_pointcloud2_layout():
    msg = ma.cloud_to_pointcloud2(_cloud(3)[0], ma.make_header(5.0, "map"), PALETTE)
    layout = [(f.name, f.offset, f.datatype, f.count) for f in msg.fields]
    f32, i32 = PointField.FLOAT32, PointField.INT32
    assert layout == [("x", 0, f32, 1), ("y", 4, f32, 1), ("z", 8, f32, 1), ("rgb", 12, f32, 1),
                      ("label", 16, i32, 1), ("opacity", 20, f32, 1), ("radius", 24, f32, 1)]
    assert (msg.point_step, msg.row_step, msg.width, msg.height) == (28, 84, 3, 1)
    assert not msg.is_bigendian and msg.is_dense and len(msg.data) == 84


def test_packed_rgb_like_pcl():
    packed = pack_rgb(np.array([[1.0, 0.5, 0.0]]))
    assert packed.view(np.uint32)[0] == 0xFF8000
    np.testing.assert_allclose(unpack_rgb(packed), [[1.0, 128 / 255, 0.0]])


def test_map_round_trip():
    cloud, labels = _cloud()
    back, back_labels = ma.pointcloud2_to_cloud(ma.cloud_to_pointcloud2(cloud, HEADER, PALETTE), PALETTE)
    np.testing.assert_array_equal(back_labels, labels.numpy())
    torch.testing.assert_close(back.means, cloud.means, rtol=0, atol=0)
    torch.testing.assert_close(back.colors, cloud.colors, rtol=0, atol=0.5 / 255 + 1e-6)
    torch.testing.assert_close(back.radii, cloud.radii, rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(back.opacities, cloud.opacities, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(back.semantics, PALETTE[labels])
    unlabelled, _ = ma.pointcloud2_to_cloud(ma.cloud_to_pointcloud2(cloud, HEADER, PALETTE))
    assert unlabelled.semantics.abs().sum() == 0


def test_map_points_one_per_voxel_the_most_opaque_and_moved_rigidly():
    means = torch.tensor([[0.01, 0.01, 0.01], [0.04, 0.02, 0.03], [0.07, 0.0, 0.0], [-0.01, 0.0, 0.0]])
    cloud = GaussianCloud.from_points(means, torch.rand(4, 3), PALETTE[torch.tensor([0, 1, 2, 1])].float(),
                                      torch.full((4,), 0.01), torch.tensor([0.3, 0.9, 0.5, 0.2]))
    every = ma.cloud_to_points(cloud, PALETTE)
    assert len(every) == 4 and list(every["label"]) == [0, 1, 2, 1]
    kept = ma.cloud_to_points(cloud, PALETTE, voxel_size=0.05)  # voxels x < 0, 0 <= x < 0.05 (two), x >= 0.05
    assert list(kept["label"]) == [1, 2, 1] and kept["opacity"][0] == pytest.approx(0.9)
    pose = np.eye(4)
    pose[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    pose[:3, 3] = [1.0, 2.0, 3.0]
    moved = ma.transform_points(every, pose)
    xyz = np.stack([moved["x"], moved["y"], moved["z"]], -1)
    np.testing.assert_allclose(xyz, means.numpy() @ pose[:3, :3].T + pose[:3, 3], atol=1e-6)
    assert np.array_equal(moved["label"], every["label"]) and np.array_equal(every["x"], means[:, 0].numpy())


def test_map_rejects_foreign_clouds():
    msg = structured_to_pointcloud2(np.zeros(2, [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]), HEADER)
    with pytest.raises(ValueError, match="missing fields"):
        ma.pointcloud2_to_cloud(msg)


def test_pointcloud2_big_endian_and_padded_points_read():
    little = np.array([(1.5, 7), (-2.0, 300)], dtype=[("a", "<f4"), ("b", "<i2")])
    msg = structured_to_pointcloud2(little, HEADER)
    big = little.astype([("a", ">f4"), ("b", ">i2")])
    padded = np.zeros(2, dtype={"names": ["a", "b"], "formats": [">f4", ">i2"], "offsets": [0, 4], "itemsize": 8})
    padded["a"], padded["b"] = big["a"], big["b"]
    msg.is_bigendian, msg.point_step, msg.row_step, msg.data = True, 8, 16, padded.tobytes()
    out = pointcloud2_to_structured(msg)
    np.testing.assert_array_equal(out["a"], [1.5, -2.0])
    np.testing.assert_array_equal(out["b"], [7, 300])


@pytest.mark.parametrize("offset, count", [(2**31 - 1, 16), (16, 2**29), (200, 16)])
def test_pointcloud2_fields_beyond_the_point_are_rejected(offset, count):
    """Issue 24 (found by the fuzz test): numpy segfaulted on a field offset near 2**31."""
    record = ma.KeyframeRecord(1, 1.0, 0, np.eye(4), np.eye(4))
    msg = ma.records_to_pointcloud2([record], HEADER)  # the pose: 16 float64 at offset 16 of a 272-byte point
    msg.fields[3].offset, msg.fields[3].count = offset, count
    with pytest.raises(ValueError, match=f"'pose' \\({count} x float64 at offset {offset}\\) ends at byte "
                                         f"{offset + 8 * count}, beyond point_step 272"):
        ma.pointcloud2_to_records(msg, ma.KeyframeRecord)
    msg.point_step = 2**31
    with pytest.raises(ValueError, match="point_step 2147483648 exceeds"):
        pointcloud2_to_structured(msg)


# --- typed records --------------------------------------------------------------------------------------------------
def _place_record(rng, features: int = 5) -> ma.PlaceSignatureRecord:
    """A bag-of-words place signature with ``features`` ORB rows."""
    points = rng.normal(size=(features, 3)).astype(np.float32)
    points[:1, :] = np.nan  # no depth at the first keypoint
    return ma.PlaceSignatureRecord(40, 9.5, 5, True, np.zeros(0, np.float32),
                                   rng.uniform(0, 80, (features, 2)).astype(np.float32),
                                   rng.integers(0, 256, (features, 32), dtype=np.uint8), points, 3,
                                   rng.random(4), np.array([0, 7, 12], np.int32))


def _records(rng):
    info = np.diag(rng.random(6) + 1)
    return [
        ma.KeyframeRecord(7, 1305031102.175304, 2, random_pose(rng), random_pose(rng)),
        ma.SubmapEvent(2, 7, random_pose(rng), ma.SubmapEventKind.CLOSED),
        ma.LoopCandidateRecord(40, 7, 5, 2, float(rng.random()), 3.25, False),
        ma.LoopConstraintRecord(40, 7, 5, 2, random_pose(rng), 0.87, info, True),
        ma.PoseGraphNode(ma.PoseGraphNodeKind.ANCHOR, 5, random_pose(rng)),
        _place_record(rng),
    ]


@pytest.mark.parametrize("index", range(6))
def test_every_record_round_trips(index):
    record = _records(np.random.default_rng(index))[index]
    other = _records(np.random.default_rng(index + 10))[index]
    msg = ma.records_to_pointcloud2([record, other], ma.make_header(9.5, "map"))
    assert (msg.width, msg.header.frame_id, ma.header_seconds(msg.header)) == (2, "map", 9.5)
    back = ma.pointcloud2_to_records(msg, type(record))
    assert back == [record, other] and back[0] != other
    assert ma.pointcloud2_to_records(ma.records_to_pointcloud2([], HEADER, type(record)), type(record)) == []


def test_record_fields_name_the_pointfields():
    kf = _records(np.random.default_rng(0))[0]
    msg = ma.records_to_pointcloud2([kf], HEADER)
    f64, f32, i32 = PointField.FLOAT64, PointField.FLOAT32, PointField.INT32
    assert [(f.name, f.offset, f.datatype, f.count) for f in msg.fields] == [
        ("keyframe_id", 0, i32, 1), ("stamp", 4, f64, 1), ("submap_id", 12, i32, 1), ("pose", 16, f64, 16),
        ("anchor_pose", 144, f64, 16)]
    assert msg.point_step == 272
    row = pointcloud2_to_structured(msg)[0]
    np.testing.assert_array_equal(row["pose"].reshape(4, 4), kf.pose)
    event = ma.records_to_pointcloud2([_records(np.random.default_rng(0))[1]], HEADER)
    assert [(f.name, f.datatype) for f in event.fields][-1] == ("kind", PointField.UINT8)
    assert pointcloud2_to_structured(event)["kind"][0] == 1
    place = ma.records_to_pointcloud2([_place_record(np.random.default_rng(0), features=5)], HEADER)
    assert [(f.name, f.datatype, f.count) for f in place.fields][3:9] == [
        ("bag_of_words", PointField.UINT8, 1), ("descriptor", f32, 0), ("orb_keypoints", f32, 10),
        ("orb_descriptors", PointField.UINT8, 160), ("orb_points", f32, 15), ("orb_scale", i32, 1)]
    place.fields[6].count = 161  # not whole 32-byte rows
    with pytest.raises(ValueError, match="'orb_descriptors' holds 161 values, not rows of 32"):
        ma.pointcloud2_to_records(place, ma.PlaceSignatureRecord)


def test_pose_graph_update_round_trip():
    rng = np.random.default_rng(5)
    update = ma.PoseGraphUpdate([ma.PoseGraphNode(ma.PoseGraphNodeKind.KEYFRAME, i, random_pose(rng)) for i in range(4)]
                                + [ma.PoseGraphNode(ma.PoseGraphNodeKind.ANCHOR, 0, np.eye(4))])
    back = ma.pointcloud2_to_pose_graph_update(ma.pose_graph_update_to_pointcloud2(update, HEADER))
    assert back == update and back.nodes[-1].kind is ma.PoseGraphNodeKind.ANCHOR


def test_record_validation_and_decoding_errors():
    rng = np.random.default_rng(6)
    kf, event = _records(rng)[:2]
    with pytest.raises(ValueError, match="not a SubmapEvent"):
        ma.pointcloud2_to_records(ma.records_to_pointcloud2([kf], HEADER), ma.SubmapEvent)
    with pytest.raises(ValueError, match="KeyframeRecord.pose"):
        ma.KeyframeRecord(1, 0.0, 0, np.eye(3), np.eye(4))
    with pytest.raises(ValueError, match="int32"):
        ma.SubmapEvent(2**31, 0, np.eye(4), ma.SubmapEventKind.CREATED)
    with pytest.raises(ValueError):
        ma.SubmapEvent(1, 0, np.eye(4), 7)
    with pytest.raises(ValueError, match="orb_keypoints: lengths \\[2, 5\\] differ"):
        ma.records_to_pointcloud2([_place_record(rng), _place_record(rng, features=2)], HEADER)
    with pytest.raises(ValueError, match="orb_descriptors: expected shape \\(None, 32\\)"):
        dataclasses.replace(_place_record(rng), orb_descriptors=np.zeros((5, 31), np.uint8))
    with pytest.raises(ValueError, match="mixed record types"):
        ma.records_to_pointcloud2([kf, event], HEADER)
    with pytest.raises(ValueError, match="empty batch"):
        ma.records_to_pointcloud2([], HEADER)
    assert not kf.pose.flags.writeable


def test_loop_candidates_and_constraints_to_and_from_the_core_types():
    from gausem_core.slam.loop import LoopCandidate
    from gausem_core.slam.loop_closure import LoopConstraint
    candidate = LoopCandidate(40, 5, 2, 0, 0.12, 0.3)
    record = ma.loop_candidate_to_record(candidate)
    assert record.intra_submap is False and ma.record_to_loop_candidate(record) == candidate
    with pytest.raises(ValueError, match="intra_submap"):
        ma.record_to_loop_candidate(ma.LoopCandidateRecord(40, 5, 2, 0, 0.12, 0.3, True))

    information = ma.sigmas_to_information((0.005, 0.02))
    np.testing.assert_allclose(np.diag(information), [2500.0] * 3 + [40000.0] * 3)  # (rho, omega) order
    assert ma.information_to_sigmas(information) == pytest.approx((0.005, 0.02))
    relative = torch.from_numpy(random_pose(np.random.default_rng(3)))
    constraint = LoopConstraint(5, 40, 0, 2, relative, (0.005, 0.02), 0.9, False)
    back = ma.record_to_loop_constraint(ma.loop_constraint_to_record(constraint))
    assert (back.keyframe_a, back.keyframe_b, back.submap_a, back.submap_b, back.intra, back.fitness) == \
        (5, 40, 0, 2, False, 0.9)
    assert back.sigmas == pytest.approx((0.005, 0.02)) and torch.equal(back.relative, relative)
    assert back.edge[:2] == (0, 2)  # an inter-submap edge joins the anchors
    for bad in (np.zeros((6, 6)), np.diag([1.0] * 5 + [np.nan])):
        with pytest.raises(ValueError, match="information"):
            ma.information_to_sigmas(bad)
    with pytest.raises(ValueError, match="intra_submap"):
        ma.record_to_loop_constraint(ma.LoopConstraintRecord(5, 40, 0, 2, relative.numpy(), 0.9, information, True))


def test_place_signatures_to_and_from_the_core_type():
    """Both kinds of appearance round-trip exactly (the loop detector stores what the tracker computed); a record
    with both or neither, or ORB columns of different counts, is refused."""
    from gausem_core.slam.loop import PlaceSignature
    from gausem_core.slam.features import OrbFeatures
    rng = np.random.default_rng(8)
    descriptor = PlaceSignature(40, 5, torch.from_numpy(rng.random(384).astype(np.float32)),
                                torch.from_numpy(rng.random(6)), (0, 7))
    features = OrbFeatures(rng.uniform(0, 80, (9, 2)).astype(np.float32),
                           rng.integers(0, 256, (9, 32), dtype=np.uint8), rng.normal(size=(9, 3)).astype(np.float32), 2)
    bow = PlaceSignature(45, 6, features, torch.zeros(0, dtype=torch.float64))
    for place in (descriptor, bow):
        record = ma.place_signature_to_record(place, 9.5)
        msg = ma.records_to_pointcloud2([record], ma.make_header(9.5, "map"))
        back = ma.record_to_place_signature(ma.pointcloud2_to_records(msg, ma.PlaceSignatureRecord)[0])
        assert (back.keyframe_id, back.submap_id, back.nearby) == (place.keyframe_id, place.submap_id, place.nearby)
        assert torch.equal(back.landmark_scores, place.landmark_scores)
        assert record.bag_of_words == (place is bow)
    assert torch.equal(ma.record_to_place_signature(ma.place_signature_to_record(descriptor, 1.0)).appearance,
                       descriptor.appearance)
    orb = ma.record_to_place_signature(ma.place_signature_to_record(bow, 1.0)).appearance
    for name in ("keypoints", "descriptors", "points"):
        np.testing.assert_array_equal(getattr(orb, name), getattr(features, name))
    assert orb.scale == 2 and orb.descriptors.flags.writeable

    record = ma.place_signature_to_record(bow, 1.0)
    for bad, message in ((dataclasses.replace(record, descriptor=np.ones(3, np.float32)), "empty descriptor"),
                         (dataclasses.replace(record, orb_scale=0), "orb_scale >= 1"),
                         (dataclasses.replace(record, orb_points=np.zeros((2, 3), np.float32)), "differ in count"),
                         (dataclasses.replace(record, bag_of_words=False), "needs values and no ORB rows")):
        with pytest.raises(ValueError, match=message):
            ma.record_to_place_signature(bad)


# --- occupancy grid -------------------------------------------------------------------------------------------------
def test_occupancy_grid_round_trips_with_its_tilted_origin():
    from gausem_core.maps.floor import FloorPlane
    from gausem_core.maps.occupancy import OccupancyGrid

    cells = np.random.default_rng(0).choice(np.array([-1, 0, 100], np.int8), (7, 5))
    floor = FloorPlane(np.array([0.0, -1.0, 0.0]), 1.2, 100, "class")  # an optical map frame: y is down
    grid = OccupancyGrid(cells, 0.05, (-0.35, 0.2, 0.0), floor)
    msg = ma.grid_to_occupancy_grid(grid, ma.make_header(3.5, "map"))
    assert (msg.info.width, msg.info.height, msg.header.frame_id) == (5, 7, "map")
    back, resolution, origin = ma.occupancy_grid_to_cells(msg)
    assert np.array_equal(back, cells) and resolution == pytest.approx(0.05)
    assert np.allclose(origin, grid.origin_pose, atol=1e-9)
    assert np.allclose(origin[:3, 2], [0.0, -1.0, 0.0])  # the grid's z axis is the floor's up
    assert origin[1, 3] == pytest.approx(1.2)  # on the floor, 1.2 m below the first camera
