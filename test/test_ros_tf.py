"""TF by REP-105 (issue 49.1): the map -> odom -> camera composition, and tracking_mapping's /tf and /tf_static as a
tf2 listener receives them (type name and hash of the official tf2_msgs/TFMessage)."""
import numpy as np
import pytest

pytest.importorskip("rclpy")
pytestmark = pytest.mark.ros

from nav_msgs.msg import Odometry  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile  # noqa: E402
from sensor_msgs.msg import PointCloud2  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

import msg_adapters as ma  # noqa: E402
from gausem_ros.frames import Rep105Frames, extrinsic_matrix, inverse  # noqa: E402
from gausem_ros.nodes.tracking_mapping import TrackingMappingNode  # noqa: E402
from gausem_ros.player import Player, open_source  # noqa: E402
from gausem_ros.qos import EVENT_QOS  # noqa: E402
from ros_harness import FAST_SLAM, Recorder, overrides, ros_session, spin_until  # noqa: E402

try:
    from tf2_msgs.msg import TFMessage
except ImportError:
    TFMessage = None
needs_tf2_msgs = pytest.mark.skipif(TFMessage is None, reason="tf2_msgs is not importable: `make setup` builds it "
                                    "(tools/build_tf2_msgs.sh; needs cmake and g++)")
TF_TYPE = "tf2_msgs/msg/TFMessage"
EXTRINSIC = [0.1, 0.0, 0.2, -0.5, 0.5, -0.5, 0.5]  # a camera's optical frame on a base: z forward = base x


@pytest.fixture(autouse=True)
def _localhost(monkeypatch):
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")


def _pose(x: float, yaw: float = 0.0) -> np.ndarray:
    m = np.eye(4)
    m[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    m[0, 3] = x
    return m


def _matrices(transforms) -> dict:
    """(parent, child) -> 4x4 of TransformStamped messages."""
    return {(t.header.frame_id, t.child_frame_id): ma.transform_to_matrix(t) for t in transforms}


def test_a_correction_moves_map_to_odom_and_odom_to_camera_stays_continuous():
    tracked = [_pose(0.1 * i, 0.05 * i) for i in range(4)]  # the camera as tracked
    correction = _pose(0.5, 0.3)  # a loop closure moves the whole map before frame 2 is sent
    frames = Rep105Frames("map", "odom")
    sent = []
    for i, (map_pose, last_now) in enumerate([(tracked[0], None), (tracked[1], tracked[0]),
                                               (correction @ tracked[2], correction @ tracked[1]),
                                               (correction @ tracked[3], correction @ tracked[2])]):
        motion = None if last_now is None else inverse(last_now) @ map_pose
        sent.append(_matrices(frames.transforms(float(i), "camera", map_pose, motion)))
    for i, tf in enumerate(sent):
        np.testing.assert_allclose(tf["odom", "camera"], tracked[i], atol=1e-12)  # the motion as tracked
        np.testing.assert_allclose(tf["map", "odom"], np.eye(4) if i < 2 else correction, atol=1e-12)
        np.testing.assert_allclose(tf["map", "odom"] @ tf["odom", "camera"],
                                   tracked[i] if i < 2 else correction @ tracked[i], atol=1e-12)


def test_a_frame_not_tracked_from_the_last_keeps_odom_and_map_to_odom_takes_the_jump():
    frames = Rep105Frames("map", "odom")
    frames.transforms(0.0, "camera", _pose(0.0), None)
    frames.transforms(1.0, "camera", _pose(0.1), inverse(_pose(0.0)) @ _pose(0.1))
    relocalised = _pose(3.0, 1.0)
    tf = _matrices(frames.transforms(2.0, "camera", relocalised, None))
    np.testing.assert_allclose(tf["odom", "camera"], _pose(0.1), atol=1e-12)
    np.testing.assert_allclose(tf["map", "odom"] @ tf["odom", "camera"], relocalised, atol=1e-12)


def test_with_a_base_frame_odom_carries_the_base_and_the_camera_hangs_on_it_statically():
    frames = Rep105Frames("world", "odometry", "base_link", EXTRINSIC)
    pose = _pose(1.0, 0.2)
    tf = _matrices(frames.transforms(4.0, "cam", pose, None) + frames.static_transforms(4.0, "cam"))
    assert set(tf) == {("world", "odometry"), ("odometry", "base_link"), ("base_link", "cam")}
    np.testing.assert_allclose(tf["base_link", "cam"], extrinsic_matrix(EXTRINSIC), atol=1e-12)
    np.testing.assert_allclose(tf["base_link", "cam"][:3, 2], [1, 0, 0], atol=1e-12)  # optical z = base x
    np.testing.assert_allclose(tf["world", "odometry"] @ tf["odometry", "base_link"] @ tf["base_link", "cam"], pose,
                               atol=1e-12)
    assert Rep105Frames("map", "odom").static_transforms(4.0, "cam") == []


@pytest.mark.parametrize("names, extrinsic, match", [(("map", "map", ""), EXTRINSIC, "distinct"),
                                                     (("map", "", ""), EXTRINSIC, "non-empty"),
                                                     (("map", "odom", "base"), [0.0] * 7, "camera_extrinsic"),
                                                     (("map", "odom", "base"), [0.0] * 6, "camera_extrinsic")])
def test_bad_frame_parameters_are_refused_naming_them(names, extrinsic, match):
    with pytest.raises(ValueError, match=match):
        Rep105Frames(*names, extrinsic)


def _play(ctx, executor, frames) -> None:
    """Replay frames in lock-step with a player node that is gone afterwards."""
    player = Player(frames, rate=0.0, lockstep=True, timeout=30.0, context=ctx)
    executor.add_node(player)
    assert spin_until(executor, lambda: player.done, 50.0)
    assert executor.retire_node(player)


@needs_tf2_msgs
def test_a_tf2_listener_gets_map_odom_base_camera_composing_to_the_odometry_and_the_loop_correction():
    """tracking_mapping in lock-step with the player; between the third and the fourth frame a pose-graph answer
    moves the map 0.5 m (as a loop closure does): map -> odom takes it with the fourth frame, odom -> base_link goes on
    without a jump."""
    shift = _pose(0.5)
    with ros_session(190) as (ctx, executor):
        tracking = TrackingMappingNode(context=ctx, parameter_overrides=overrides(
            {**FAST_SLAM, "loop_closure": "nodes", "base_frame": "base_link", "camera_extrinsic": EXTRINSIC}))
        listener = Recorder(ctx, [(TFMessage, "/tf", QoSProfile(depth=100)),  # tf2_ros' listener QoS
                                  (TFMessage, "/tf_static", QoSProfile(depth=100,
                                                                       durability=DurabilityPolicy.TRANSIENT_LOCAL)),
                                  (Odometry, "gausem/odometry", EVENT_QOS)], name="tf_listener")
        for node in (tracking, listener.node):
            executor.add_node(node)
        frames = list(open_source("synthetic", size=(80, 60), max_frames=6))
        _play(ctx, executor, frames[:3])
        update = ma.PoseGraphUpdate([ma.PoseGraphNode(ma.PoseGraphNodeKind.ANCHOR, 0, shift)])
        listener.node.create_publisher(PointCloud2, "gausem/pose_graph", EVENT_QOS).publish(
            ma.pose_graph_update_to_pointcloud2(update, ma.make_header(1.0, "map")))
        assert spin_until(executor, lambda: tracking.loop_link.pose_graph_updates, 10.0)
        _play(ctx, executor, frames[3:])
        assert spin_until(executor, lambda: len(listener.messages["gausem/odometry"]) == 6
                          and len(listener.messages["/tf"]) == 6 and listener.messages["/tf_static"], 10.0)
        publishers = {topic: listener.node.get_publishers_info_by_topic(topic) for topic in ("/tf", "/tf_static")}
    official = get_typestore(Stores.ROS2_JAZZY).hash_rihs01(TF_TYPE)
    for topic, infos in publishers.items():
        assert [(i.node_name, i.topic_type, str(i.topic_type_hash)) for i in infos] == [
            ("tracking_mapping", TF_TYPE, official)], topic
    assert tracking.frames_processed == 6
    static = _matrices(listener.messages["/tf_static"][-1].transforms)
    assert list(static) == [("base_link", "camera")]
    np.testing.assert_allclose(static["base_link", "camera"], extrinsic_matrix(EXTRINSIC), atol=1e-9)
    odometry = listener.messages["gausem/odometry"]
    tf = {ma.header_seconds(m.transforms[0].header): _matrices(m.transforms) for m in listener.messages["/tf"]}
    for i, odom in enumerate(odometry):
        frame = tf[ma.header_seconds(odom.header)]
        assert set(frame) == {("map", "odom"), ("odom", "base_link")}
        np.testing.assert_allclose(frame["map", "odom"], np.eye(4) if i < 3 else shift, atol=1e-6)
        np.testing.assert_allclose(frame["map", "odom"] @ frame["odom", "base_link"] @ static["base_link", "camera"],
                                   ma.odometry_to_matrix(odom), atol=1e-6)
    map_poses = [ma.odometry_to_matrix(o) for o in odometry]
    odom_poses = [tf[ma.header_seconds(o.header)]["odom", "base_link"] for o in odometry]
    map_step = np.linalg.norm(map_poses[3][:3, 3] - map_poses[2][:3, 3])
    odom_step = np.linalg.norm(odom_poses[3][:3, 3] - odom_poses[2][:3, 3])
    assert map_step > 0.4 and odom_step < 0.1  # the odometry topic jumps with the correction, odom does not
