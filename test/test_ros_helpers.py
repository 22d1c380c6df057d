"""gausem_ros helpers: approximate-time sync, TF broadcaster selection, QoS profiles and bag IO."""
import gc
import sys
import threading
import time
import types

import numpy as np
import pytest

pytest.importorskip("rclpy")
pytest.importorskip("rosbags")

import rclpy  # noqa: E402
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.qos import DurabilityPolicy, ReliabilityPolicy  # noqa: E402
from rosbags.highlevel import AnyReader  # noqa: E402
from rosbags.rosbag2 import Writer as Ros2Writer  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402
from sensor_msgs.msg import Image  # noqa: E402

import msg_adapters as ma  # noqa: E402
from gausem_core.geometry import PinholeCamera  # noqa: E402
from gausem_ros import bags, qos, sync, tf  # noqa: E402
from gausem_ros.executor import NodeExecutor  # noqa: E402
from ros_harness import spin_for, spin_until  # noqa: E402


# --- approximate-time sync ------------------------------------------------------------------------------------------
class Collector:
    def __init__(self):
        self.matches = []

    def __call__(self, *msgs):
        self.matches.append(msgs)


def test_jittered_streams_match_frame_by_frame():
    rng = np.random.default_rng(0)
    out = Collector()
    s = sync.ApproximateTimeSync(["rgb", "depth", "labels"], out, queue_size=5, slop=0.015)
    for frame in range(30):
        t = 1.0 + frame / 30
        arrivals = [(i, t + rng.uniform(-0.005, 0.005), (i, frame)) for i in range(3)]
        for i in rng.permutation(3):
            s.add(*arrivals[i])
    assert [tuple(m[1] for m in match) for match in out.matches] == [(f, f, f) for f in range(30)]
    assert all([m[0] for m in match] == [0, 1, 2] for match in out.matches)
    assert s.matched == 30 and sum(s.dropped.values()) == 0 and s.received == [30, 30, 30]


class Drops(list):
    def __call__(self, index, reason, detail, stamp):
        self.append((index, reason, detail, stamp))


def test_unmatched_and_late_messages_are_dropped_and_reported_with_the_offset_seen():
    out, drops = Collector(), Drops()
    s = sync.ApproximateTimeSync(["rgb", "depth"], out, queue_size=10, slop=0.01, on_drop=drops)
    s.add(0, 1.000, "rgb1")     # its depth never arrives in time
    s.add(1, 1.050, "depth0")   # 50 ms away from rgb1: no match
    s.add(0, 1.100, "rgb2")
    s.add(1, 1.101, "depth2")   # matches rgb2; rgb1 and depth0 are left behind
    assert out.matches == [("rgb2", "depth2")]
    assert [(i, reason) for i, reason, _, _ in drops] == [(0, "unmatched"), (1, "unmatched")]
    assert "nearest depth 0.050 s away" in drops[0][2] and [stamp for *_, stamp in drops] == [1.000, 1.050]
    s.add(1, 1.001, "depth1")   # out of order, older than the last match on its input
    assert drops[-1][:2] == (1, "backwards") and len(out.matches) == 1
    assert s.dropped == {("rgb", "unmatched"): 1, ("depth", "unmatched"): 1, ("depth", "backwards"): 1}
    # every message is matched, pending or dropped
    assert all(s.received[i] == s.matched + s.pending(i) + sum(n for (name, _), n in s.dropped.items()
                                                                 if name == s.names[i]) for i in range(2))


def test_an_input_that_never_arrives_is_named():
    drops = Drops()
    s = sync.ApproximateTimeSync(["rgb", "depth", "labels"], Collector(), queue_size=2, slop=0.01, on_drop=drops)
    for k in range(3):
        s.add(0, k, f"rgb{k}")
        s.add(1, k, f"depth{k}")
    assert drops[0][:2] == (0, "unmatched") and "no labels received at all" in drops[0][2]
    assert s.pending(0) == 2


def test_duplicates_keep_the_first_and_overflow_evicts_the_oldest():
    out = Collector()
    s = sync.ApproximateTimeSync(["rgb", "depth"], out, queue_size=2, slop=0.01)
    s.add(0, 1.0, "first")
    s.add(0, 1.0, "second")
    assert s.dropped[("rgb", "duplicate")] == 1
    s.add(1, 1.0, "depth")
    assert out.matches == [("first", "depth")]
    for t in (2.0, 3.0, 4.0):
        s.add(0, t, f"rgb{t}")
    assert s.dropped[("rgb", "unmatched")] == 1
    s.add(1, 2.0, "depth2")      # rgb2.0 was evicted
    s.add(1, 3.0, "depth3")
    assert out.matches[1:] == [("rgb3.0", "depth3")]


def test_reset_lets_a_replay_of_the_same_stamps_match_again():
    out = Collector()
    s = sync.ApproximateTimeSync(["rgb", "depth"], out, slop=0.01)
    for _ in range(2):
        s.add(0, 1.0, "rgb")
        s.add(1, 1.0, "depth")
        s.reset()
    assert out.matches == [("rgb", "depth")] * 2 and s.received == [0, 0]


def test_sync_rejects_bad_arguments():
    with pytest.raises(ValueError):
        sync.ApproximateTimeSync([], print)
    with pytest.raises(ValueError, match="out of range"):
        sync.ApproximateTimeSync(["rgb", "depth"], print).add(2, 1.0, None)


class FakeNode:
    """Records subscriptions and publishers like rclpy.node.Node (no ROS context needed)."""

    def __init__(self):
        self.subscriptions, self.publishers, self.warnings = [], [], []

    def create_subscription(self, msg_type, topic, callback, qos_profile, callback_group=None, event_callbacks=None):
        self.subscriptions.append((msg_type, topic, callback, qos_profile))
        return types.SimpleNamespace(topic_name=topic, event_callbacks=event_callbacks)

    def create_timer(self, period, callback):
        return types.SimpleNamespace(period=period, callback=callback)

    def create_publisher(self, msg_type, topic, qos_profile):
        pub = types.SimpleNamespace(topic=topic, qos=qos_profile, sent=[])
        pub.publish = pub.sent.append
        self.publishers.append(pub)
        return pub

    def get_logger(self):
        return types.SimpleNamespace(warning=self.warnings.append)


def test_make_synchronizer_feeds_header_stamps():
    node, out = FakeNode(), Collector()
    handle = sync.make_synchronizer(node, [("rgb", Image, "rgb/image"), ("depth", Image, "depth/image")], out,
                                    qos.IMAGE_QOS, queue_size=3, slop=0.01)
    assert [(t, topic, q) for t, topic, _, q in node.subscriptions] == [(Image, "rgb/image", qos.IMAGE_QOS),
                                                                       (Image, "depth/image", qos.IMAGE_QOS)]
    rgb = ma.rgb_to_image(np.zeros((2, 2, 3), np.uint8), ma.make_header(5.000, "cam"))
    depth = ma.depth_to_image(np.ones((2, 2)), ma.make_header(5.004, "cam"))
    node.subscriptions[1][2](depth, {"publication_sequence_number": 1})
    node.subscriptions[0][2](rgb, {"publication_sequence_number": 1})
    assert out.matches == [(rgb, depth)] and handle.synchronizer.matched == 1


def test_gaps_in_the_publication_sequence_are_counted_as_lost():
    drops = Drops()
    s = sync.ApproximateTimeSync(["rgb", "depth"], Collector(), slop=0.01, on_drop=drops)
    for stamp, sequence in ((1.0, 7), (2.0, 8), (3.0, 11), (4.0, 1), (5.0, 2)):  # 9, 10 lost; then a new publisher
        s.add(0, stamp, f"rgb{stamp}", sequence)
    assert s.lost == [2, 0] and s.dropped[("rgb", "lost_in_transport")] == 2
    assert [reason for _, reason, _, _ in drops] == ["lost_in_transport"] * 2 and "sequence 8 -> 11" in drops[0][2]
    assert [stamp for *_, stamp in drops] == [None, None]  # never received: no stamp


# --- TF ---------------------------------------------------------------------------------------------------------------
def test_tf_degrades_to_a_warning_once_without_tf2(monkeypatch):
    monkeypatch.setitem(sys.modules, "tf2_ros", None)
    monkeypatch.setitem(sys.modules, "tf2_msgs", None)
    monkeypatch.setitem(sys.modules, "tf2_msgs.msg", None)  # where the set-up built it, it may be imported already
    node = FakeNode()
    broadcaster = tf.make_transform_broadcaster(node)
    transform = ma.matrix_to_transform(np.eye(4), ma.make_header(1.0, "map"), "camera")
    broadcaster.sendTransform(transform)
    broadcaster.sendTransform([transform])
    assert len(node.warnings) == 1 and "TF is unavailable" in node.warnings[0] and not node.publishers


def test_tf_falls_back_to_a_tfmessage_publisher(monkeypatch):
    fake_msgs = types.ModuleType("tf2_msgs.msg")
    fake_msgs.TFMessage = lambda transforms: types.SimpleNamespace(transforms=transforms)
    monkeypatch.setitem(sys.modules, "tf2_ros", None)
    monkeypatch.setitem(sys.modules, "tf2_msgs", types.ModuleType("tf2_msgs"))
    monkeypatch.setitem(sys.modules, "tf2_msgs.msg", fake_msgs)
    node = FakeNode()
    dynamic, static = tf.make_transform_broadcaster(node), tf.make_transform_broadcaster(node, static=True)
    a = ma.matrix_to_transform(np.eye(4), ma.make_header(1.0, "map"), "camera")
    b = ma.matrix_to_transform(np.eye(4), ma.make_header(1.0, "camera"), "lens")
    dynamic.sendTransform(a)
    static.sendTransform(a)
    static.sendTransform([b])
    pub_tf, pub_static = node.publishers
    assert (pub_tf.topic, pub_tf.qos.depth) == ("/tf", 100)
    assert pub_static.topic == "/tf_static" and pub_static.qos.durability == DurabilityPolicy.TRANSIENT_LOCAL
    assert [m.transforms for m in pub_tf.sent] == [[a]]
    assert [m.transforms for m in pub_static.sent] == [[a], [a, b]]


def test_a_static_broadcaster_shared_by_several_threads_sends_one_at_a_time():
    """tracking_mapping's parts send static transforms from two callback groups; tf2_ros' static broadcaster
    rebuilds its latched message in Python, so overlapping sends could lose one."""
    inside, most = [0], [0]

    class Slow:
        def sendTransform(self, transforms):  # noqa: N802 (tf2_ros' name)
            inside[0] += 1
            most[0] = max(most[0], inside[0])
            time.sleep(0.01)
            inside[0] -= 1

    broadcaster = tf.SerialisedBroadcaster(Slow())
    threads = [threading.Thread(target=lambda: [broadcaster.sendTransform([]) for _ in range(5)]) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert most == [1]


# --- QoS --------------------------------------------------------------------------------------------------------------
def test_incompatibility_follows_the_request_offered_rules():
    assert qos.incompatibility(qos.SENSOR_QOS, qos.IMAGE_QOS) == ("it publishes best effort and this subscription "
                                                                  "is reliable")
    assert qos.incompatibility(qos.IMAGE_QOS, qos.SENSOR_QOS) is None  # reliable reaches best effort
    assert "volatile" in qos.incompatibility(qos.IMAGE_QOS, qos.LATCHED_QOS)
    assert qos.incompatibility(qos.LATCHED_QOS, qos.IMAGE_QOS) is None


def _camera_node(context, callback, default_event_handlers=False):
    node = rclpy.create_node("camera_input", context=context)
    group = MutuallyExclusiveCallbackGroup()
    topics = ("rgb/image", "depth/image", "semantic/labels")
    if default_event_handlers:  # as rclpy makes them
        return node, [node.create_subscription(Image, t, callback, qos.IMAGE_QOS, callback_group=group) for t in topics]
    return node, [qos.subscribe_camera(node, Image, t, callback, qos.IMAGE_QOS, group, qos.INPUT_QOS_HINT)
                  for t in topics]


class CountingExecutor(NodeExecutor):
    """Counts how often the executor asks whether it may wait on one of ``watched`` (once per wait set it builds)."""

    def __init__(self, watched, **kwargs):
        super().__init__(**kwargs)
        self.watched, self.asked = watched, 0

    def can_execute(self, entity) -> bool:
        self.asked += any(entity is w for w in self.watched)
        return super().can_execute(entity)


def _wait_sets_per_message(domain_id: int, default_event_handlers: bool) -> float:
    """Three camera inputs at 30 Hz in one callback group, each callback 1 ms of Python: wait sets the executor
    builds per message received."""
    context = Context()
    rclpy.init(context=context, domain_id=domain_id)
    received = []

    def callback(msg):
        received.append(msg)
        end = time.perf_counter() + 0.001
        while time.perf_counter() < end:
            pass

    node, subs = _camera_node(context, callback, default_event_handlers)
    executor = CountingExecutor(subs[:1], num_threads=2, context=context)
    source = rclpy.create_node("camera", context=context)
    pubs = [source.create_publisher(Image, sub.topic_name, qos.IMAGE_QOS) for sub in subs]
    image = ma.rgb_to_image(np.zeros((60, 80, 3), np.uint8), ma.make_header(0.0, "cam"))
    stop = threading.Event()

    def camera():
        while not stop.is_set():
            for pub in pubs:
                pub.publish(image)
            time.sleep(1 / 30)

    executor.add_node(node)
    thread = threading.Thread(target=camera)
    try:
        thread.start()
        arrived = spin_until(executor, lambda: len(received) >= 150, 120.0)  # about 5 s at 30 Hz
    finally:
        stop.set()
        thread.join()
        executor.shutdown()
        node.destroy_node()
        source.destroy_node()
        rclpy.shutdown(context=context)
    assert arrived, f"{len(received)} of 150 messages"
    return executor.asked / len(received)


def test_camera_subscriptions_do_not_make_the_executor_loop():
    """With rclpy's default QoS-event handlers on camera inputs, Fast DDS leaves their conditions ready while a
    message waits untaken, and the executor rebuilds its wait set in a loop (taking the interpreter lock from the
    SLAM thread every time). Measured in one test: the same inputs with and without those handlers."""
    ours = _wait_sets_per_message(165, default_event_handlers=False)
    default = _wait_sets_per_message(167, default_event_handlers=True)
    assert ours < 0.6 * default, f"wait sets per message: {ours:.2f} without the handlers, {default:.2f} with them"


def test_a_publisher_with_incompatible_qos_is_reported_once():
    context = Context()
    rclpy.init(context=context, domain_id=166)
    executor = NodeExecutor(num_threads=2, context=context)
    node, (rgb, depth, _) = _camera_node(context, lambda msg: None)
    source = rclpy.create_node("camera", context=context)
    source.create_publisher(Image, "rgb/image", qos.SENSOR_QOS)  # best effort: a reliable input hears nothing
    source.create_publisher(Image, "depth/image", qos.IMAGE_QOS)
    executor.add_node(node)
    executor.add_node(source)
    try:
        assert spin_until(executor, lambda: rgb.incompatible_publishers.reported, 10.0)
        spin_for(executor, 2.5)  # another look: still one warning
    finally:
        executor.shutdown()
        node.destroy_node()
        source.destroy_node()
        rclpy.shutdown(context=context)
    [warning] = rgb.incompatible_publishers.reported.values()
    assert warning.startswith("/rgb/image: publisher /camera offers an incompatible QoS (it publishes best effort")
    assert warning.endswith("input_qos:=sensor_data") and not depth.incompatible_publishers.reported


def test_qos_profiles():
    assert qos.IMAGE_QOS.reliability == ReliabilityPolicy.RELIABLE and qos.IMAGE_QOS.depth == 10
    assert qos.SENSOR_QOS.reliability == ReliabilityPolicy.BEST_EFFORT
    assert qos.LATCHED_QOS.durability == DurabilityPolicy.TRANSIENT_LOCAL and qos.LATCHED_QOS.depth == 1
    assert qos.input_qos("sensor_data") is qos.SENSOR_QOS and qos.input_qos("reliable") is qos.IMAGE_QOS
    with pytest.raises(ValueError, match="reliable, sensor_data"):
        qos.input_qos("fast")


# --- bags -------------------------------------------------------------------------------------------------------------
TF_MESSAGE = bags._message_class(bags.TF_TYPE)  # tf2_msgs' TFMessage where importable (the set-up builds it)


def _tum_messages(n=6):
    rng = np.random.default_rng(7)
    camera = PinholeCamera(525.0, 525.0, 320.0, 240.0, 16, 12)
    out = []
    for i in range(n):
        t = 1305031102.175304 + i / 30
        stamp = ma.seconds_to_ns(t)
        rgb = ma.rgb_to_image(rng.integers(0, 256, (12, 16, 3), dtype=np.uint8), ma.make_header(t, "rgb"))
        depth = ma.depth_to_image(rng.random((12, 16), dtype=np.float32) + 0.5, ma.make_header(t + 0.002, "depth"))
        info = ma.camera_to_camera_info(camera, ma.make_header(t, "rgb"))
        pose = np.eye(4)
        pose[:3, 3] = [i, 2.0 * i, -1.0]
        tf_msg = TF_MESSAGE(transforms=[ma.matrix_to_transform(pose, ma.make_header(t, "/world"), "/kinect")])
        out += [(bags.TUM_TOPICS["rgb"], stamp, rgb), (bags.TUM_TOPICS["depth"], stamp + 2_000_000, depth),
                (bags.TUM_TOPICS["camera_info"], stamp, info), (bags.TUM_TOPICS["tf"], stamp + 1, tf_msg)]
    return out


def _write(fmt, path, messages):
    if fmt == "ros1":
        bags.write_ros1_bag(path, messages)
    else:
        bags.write_bag(path, messages, storage=fmt)


@pytest.mark.parametrize("fmt, name", [("sqlite3", "bag2"), ("mcap", "bag2"), ("ros1", "tum.bag")])
def test_bag_write_read_round_trip(tmp_path, fmt, name):
    messages = _tum_messages()
    path = tmp_path / name
    _write(fmt, path, messages)
    back = list(bags.read_bag(path))
    expected = sorted(messages, key=lambda m: m[1])
    assert [(m.topic, m.stamp_ns) for m in back] == [(t, s) for t, s, _ in expected]
    assert all(m.msg == e[2] for m, e in zip(back, expected))
    assert np.array_equal(ma.image_to_rgb(back[0].msg), ma.image_to_rgb(expected[0][2]))
    only_depth = list(bags.read_bag(path, topics=[bags.TUM_TOPICS["depth"]]))
    assert [m.topic for m in only_depth] == [bags.TUM_TOPICS["depth"]] * 6


def test_ros1_bag_uses_the_tum_legacy_tf_type(tmp_path):
    path = tmp_path / "tum.bag"
    bags.write_ros1_bag(path, _tum_messages(1))
    with AnyReader([path]) as reader:
        types_by_topic = {c.topic: c.msgtype for c in reader.connections}
    assert types_by_topic[bags.TUM_TOPICS["tf"]] == "tf/msg/tfMessage"
    assert types_by_topic[bags.TUM_TOPICS["camera_info"]] == "sensor_msgs/msg/CameraInfo"


@pytest.mark.parametrize("fmt, name", [("sqlite3", "bag2"), ("mcap", "bag2"), ("ros1", "tum.bag")])
def test_truncated_bags_raise_a_clear_error(tmp_path, fmt, name):
    path = tmp_path / name
    _write(fmt, path, _tum_messages())
    data_file = path if path.is_file() else next(p for p in path.iterdir() if p.suffix in (".db3", ".mcap"))
    with data_file.open("r+b") as f:
        f.truncate(data_file.stat().st_size * 2 // 3)
    with pytest.raises(bags.BagError, match=f"bag {path} is corrupt or truncated"):
        list(bags.read_bag(path))


def test_bag_reading_errors(tmp_path):
    with pytest.raises(bags.BagError, match="does not exist"):
        list(bags.read_bag(tmp_path / "missing.bag"))
    path = tmp_path / "bag2"
    bags.write_bag(path, _tum_messages(1))
    with pytest.raises(bags.BagError, match=r"no topics \['/nope'\]"):
        list(bags.read_bag(path, topics=["/nope"]))


def test_topics_without_an_rclpy_class_are_skipped_with_a_warning(tmp_path):
    store = get_typestore(Stores.ROS2_JAZZY)
    error_type = "tf2_msgs/msg/TF2Error"  # in rosbags' Jazzy store; tf2_msgs is not importable here
    if bags._message_class(error_type) is not None:
        pytest.skip("tf2_msgs is importable")
    path = tmp_path / "bag2"
    with Ros2Writer(path, version=8) as writer:
        conn = writer.add_connection("/tf_error", error_type, typestore=store)
        raw = store.serialize_cdr(store.types[error_type](error=1, error_string="x"), error_type)
        writer.write(conn, 5, raw)
        conn = writer.add_connection("/rgb", "sensor_msgs/msg/Image", typestore=store)
        writer.write(conn, 6, bags._to_cdr(ma.rgb_to_image(np.zeros((1, 1, 3), np.uint8), ma.make_header(0.0, "c"))))
    with pytest.warns(UserWarning, match="/tf_error"):
        assert [m.topic for m in bags.read_bag(path)] == ["/rgb"]
    with pytest.raises(bags.BagError, match="no rclpy message class"):
        list(bags.read_bag(path, topics=["/tf_error"]))


def test_bag_writing_errors(tmp_path):
    img = ma.rgb_to_image(np.zeros((1, 1, 3), np.uint8), ma.make_header(0.0, "c"))
    with pytest.raises(bags.BagError, match="integer nanoseconds"):
        bags.write_bag(tmp_path / "a", [("/rgb", 1.5, img)])
    with pytest.raises(bags.BagError, match="carries sensor_msgs/msg/Image"):
        bags.write_bag(tmp_path / "b", [("/rgb", 1, img), ("/rgb", 2, ma.make_header(0.0, "c"))])
    with pytest.raises(bags.BagError, match="unknown ROS 2 bag storage"):
        bags.write_bag(tmp_path / "c", [], storage="zip")


def test_loop_answers_hold_the_next_frame_until_answered_given_up_or_unheard():
    """What tracking_mapping waits for in loop_closure: nodes: candidates for the last loop keyframe (an older
    keyframe's do not count), then the pose graph's answer to an accepted loop; not while nobody listens; at most
    the timeout; never with timeout 0."""
    from gausem_ros.nodes.loop_answers import LoopAnswers
    listening = {"detector": True, "graph": True}
    given_up = []
    answers = LoopAnswers(60.0, lambda: listening["detector"], lambda: listening["graph"], given_up.append)
    assert answers.settled()
    answers.expect_candidates(2.0)
    answers.candidates_arrived(1.0)  # a late answer for an older keyframe
    assert not answers.settled()
    answers.candidates_arrived(2.0)
    answers.expect_pose_graph()
    assert not answers.settled()
    answers.pose_graph_arrived()
    assert answers.settled()
    answers.expect_candidates(3.0)
    listening["detector"] = False  # loop_detection went down while its answer was awaited
    assert answers.settled() and given_up == []
    answers.expect_candidates(4.0)  # and nobody listens when the next signature goes out
    listening["detector"] = True
    assert answers.settled()

    impatient = LoopAnswers(1e-3, lambda: True, lambda: True, given_up.append)
    impatient.expect_pose_graph()
    time.sleep(2e-3)
    assert impatient.settled() and given_up == ["pose_graph"]
    never = LoopAnswers(0.0, lambda: True, lambda: True, given_up.append)
    never.expect_candidates(1.0)
    assert never.settled()
    with pytest.raises(ValueError, match="loop_answer_timeout"):
        LoopAnswers(-1.0, lambda: True, lambda: True, given_up.append)


# --- the executor ----------------------------------------------------------------------------------------------------
def test_executor_shutdown_waits_for_the_callbacks_and_leaves_no_failed_task(capfd):
    """shutdown returns after the callback in progress, and the handlers still queued then run against a live
    executor (rclpy's own shutdown destroyed its guard condition first: 'cannot use Destroyable', printed at exit)."""
    context = Context()
    rclpy.init(context=context, domain_id=163)
    executor = NodeExecutor(num_threads=2, context=context)
    node = rclpy.create_node("slow_callbacks", context=context)
    started, finished = [], []

    def slow():
        started.append(time.monotonic())
        time.sleep(0.2)
        finished.append(time.monotonic())

    for _ in range(3):  # one more than the pool's threads: a handler waits in the queue
        node.create_timer(0.005, slow, callback_group=MutuallyExclusiveCallbackGroup())
    executor.add_node(node)
    try:
        assert spin_until(executor, lambda: len(started) >= 2, 30.0)  # both threads busy: the third handler queues
        executor.shutdown()
        assert len(finished) == len(started) >= 2  # every callback that started ran to its end before shutdown returned
    finally:
        node.destroy_node()
        rclpy.shutdown(context=context)
    del executor
    gc.collect()
    assert "never retrieved" not in capfd.readouterr().err


def test_a_retired_node_is_destroyed_only_after_its_callback_in_progress():
    """retire_node removes a node from the running executor and destroys it once its callback on a worker thread has
    ended: that callback's publish still finds its publisher (destroyed under it: 'cannot use Destroyable', raised
    by the next spin)."""
    context = Context()
    rclpy.init(context=context, domain_id=164)
    executor = NodeExecutor(num_threads=2, context=context)
    node = rclpy.create_node("slow_publisher", context=context)
    publisher = node.create_publisher(Image, "slow", 1)
    started, published = [], []

    def slow():
        started.append(True)
        time.sleep(0.2)
        publisher.publish(Image())
        published.append(True)

    node.create_timer(0.005, slow)
    executor.add_node(node)
    try:
        assert spin_until(executor, lambda: started, 30.0)
        assert executor.retire_node(node)
        assert published and node not in executor.get_nodes()
        spin_for(executor, 0.1)  # collects the finished handlers: one that failed would raise here
        assert len(published) == 1  # the node's timer is gone
    finally:
        executor.shutdown()
        rclpy.shutdown(context=context)
