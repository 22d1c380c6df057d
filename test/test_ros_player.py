"""The player (ROS 1 bag with TUM topic names, ROS 2 bag from gausem-bag, a looped source), and nodes as separate
processes."""
import argparse
import functools
import itertools
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy")
pytest.importorskip("rosbags")

import rclpy  # noqa: E402
from rosgraph_msgs.msg import Clock  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

import msg_adapters as ma  # noqa: E402
from gausem_core.geometry import PinholeCamera  # noqa: E402
from gausem_ros import bags, convert  # noqa: E402
from gausem_ros.player import (GAUSEM_BAG_TOPICS, Player, add_player_arguments, looped, open_source,  # noqa: E402
                               player_from_args, source_from_args)
from gausem_ros.player import main as player_main  # noqa: E402
from gausem_ros.qos import IMAGE_QOS  # noqa: E402
from gausem_ros.run_all import main as run_all_main  # noqa: E402
from ros_harness import FAST_SLAM, Recorder, ros_param_args, ros_session, spin_until  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(autouse=True)
def _localhost(monkeypatch):
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")


def _tum_bag(path: Path, frames: int) -> list[float]:
    """A TUM-style ROS 1 bag: rgb, depth (32FC1, 5 ms after the rgb image), camera_info and mocap /tf."""
    camera = PinholeCamera(30.0, 30.0, 8.0, 6.0, 16, 12)
    stamps = [1305031102.175304 + k / 30 for k in range(frames)]
    messages = []
    for k, t in enumerate(stamps):
        header = ma.make_header(t, "/openni_rgb_optical_frame")
        rgb = np.full((12, 16, 3), 10 * k, np.uint8)
        depth_header = ma.make_header(t + 0.005, "/openni_depth_optical_frame")
        gt = bags.TFMessageStandIn([ma.matrix_to_transform(np.eye(4), ma.make_header(t, "/world"), "/kinect")])
        messages += [(bags.TUM_TOPICS["rgb"], ma.seconds_to_ns(t), ma.rgb_to_image(rgb, header)),
                     (bags.TUM_TOPICS["camera_info"], ma.seconds_to_ns(t), ma.camera_to_camera_info(camera, header)),
                     (bags.TUM_TOPICS["depth"], ma.seconds_to_ns(t + 0.005),
                      ma.depth_to_image(np.full((12, 16), 1.0 + k, np.float32), depth_header)),
                     (bags.TUM_TOPICS["tf"], ma.seconds_to_ns(t), gt)]
    bags.write_ros1_bag(path, messages)
    return stamps


def test_player_replays_a_ros1_bag_with_tum_topic_names_and_never_ground_truth(tmp_path):
    stamps = _tum_bag(tmp_path / "tum.bag", 3)
    with ros_session(111) as (ctx, executor):
        player = Player(open_source(str(tmp_path / "tum.bag")), rate=0.0, context=ctx)
        recorder = Recorder(ctx, [(Image, "rgb/image", IMAGE_QOS), (Image, "depth/image", IMAGE_QOS),
                                  (CameraInfo, "rgb/camera_info", IMAGE_QOS), (Clock, "/clock", IMAGE_QOS),
                                  (Image, "semantic/labels", IMAGE_QOS)])
        executor.add_node(player)
        executor.add_node(recorder.node)
        assert spin_until(executor, lambda: player.done and len(recorder.messages["depth/image"]) == 3
                          and len(recorder.messages["/clock"]) == 3, 10.0)
        topics = dict(recorder.node.get_topic_names_and_types())
        got = recorder.messages
    assert player.published == 3
    assert [ma.header_seconds(m.header) for m in got["rgb/image"]] == pytest.approx(stamps, abs=1e-6)
    assert [float(ma.image_to_rgb(m)[0, 0, 0]) for m in got["rgb/image"]] == [0, 10, 20]
    assert [float(ma.image_to_depth(m)[0, 0]) for m in got["depth/image"]] == [1.0, 2.0, 3.0]
    assert ma.camera_info_to_camera(got["rgb/camera_info"][0]).fx == 30.0
    assert [ma.time_to_seconds(c.clock) for c in got["/clock"]] == pytest.approx(stamps, abs=1e-6)
    assert "/tf" not in topics and not got["semantic/labels"]  # ground truth stays in the bag; it has no labels


def test_player_paces_frames_at_the_recorded_rate(tmp_path):
    """No frame goes out before its recorded time over the rate (a loaded machine may only delay them)."""
    _tum_bag(tmp_path / "tum.bag", 4)  # 3 intervals of 1/30 s -> 0.1 s at rate 1, 1 s at rate 0.1
    with ros_session(112) as (ctx, executor):
        player = Player(open_source(str(tmp_path / "tum.bag")), rate=0.1, context=ctx)
        recorder = Recorder(ctx, [(Image, "rgb/image", IMAGE_QOS), (Image, "depth/image", IMAGE_QOS),
                                  (CameraInfo, "rgb/camera_info", IMAGE_QOS)])
        arrivals = []
        recorder.node.create_subscription(Image, "rgb/image", lambda m: arrivals.append(
            recorder.node.get_clock().now().nanoseconds / 1e9), IMAGE_QOS)
        executor.add_node(player)
        executor.add_node(recorder.node)
        assert spin_until(executor, lambda: len(arrivals) == 4, 30.0)
    assert player.published == 4 and arrivals[-1] - arrivals[0] >= 0.95  # rate 1 or 0 would take 0.1 s or none


def test_gausem_bag_writes_a_ros2_bag_the_player_replays(tmp_path):
    out = tmp_path / "synthetic_bag"
    assert convert.main(["synthetic", str(out), "--size", "40x30", "--max-frames", "2", "--format", "mcap"]) == 0
    by_topic = {}
    for item in bags.read_bag(out):
        by_topic.setdefault(item.topic, []).append(item.msg)
    assert {t: len(m) for t, m in by_topic.items()} == {"/rgb/image": 2, "/depth/image": 2, "/rgb/camera_info": 2,
                                                        "/semantic/labels": 2}
    frames = list(open_source(str(out)))
    assert [sorted(k for k, _ in f.messages) for f in frames] == [["camera_info", "depth", "labels", "rgb"]] * 2
    assert by_topic["/semantic/labels"][0].encoding == "mono16"


@pytest.mark.slow
def test_launcher_runs_tracking_and_player_as_separate_processes(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(REPO), "ROS_DOMAIN_ID": "113", "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    cmd = [sys.executable, "-m", "gausem_ros.launcher", "--params-file", str(REPO / "params" / "synthetic.yaml"),
           "--nodes", "tracking_mapping", "--play",
           f"synthetic --size 80x60 --max-frames 2 --rate 0 --lockstep --timeout 30 --gt-out {tmp_path / 'gt.txt'}",
           "--", *ros_param_args(FAST_SLAM)]
    result = subprocess.run(cmd, env=env, cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "2 odometry messages received, 0 lock-step timeouts" in result.stderr
    assert len((tmp_path / "gt.txt").read_text().splitlines()) == 3  # header + 2 ground-truth poses


def test_a_damaged_bag_ends_playback_with_an_error_and_the_player_survives(tmp_path, monkeypatch, capfd):
    def damaged(frames):  # damage found part-way: rosbags raises while iterating
        yield from frames
        raise bags.BagError("bag x.bag is corrupt or truncated: unexpected end of file")

    with ros_session(114) as (ctx, executor):
        player = Player(damaged(open_source("synthetic", size=(16, 12), max_frames=2)), rate=0.0, context=ctx)
        recorder = Recorder(ctx, [(Image, topic, IMAGE_QOS) for topic in ("rgb/image", "depth/image",
                                                                          "semantic/labels")]
                            + [(CameraInfo, "rgb/camera_info", IMAGE_QOS)])
        executor.add_node(player)
        executor.add_node(recorder.node)
        assert spin_until(executor, lambda: player.done and len(recorder.messages["rgb/image"]) == 2, 10.0)
    assert player.published == 2 and "playback stopped after 2 frames" in player.error

    _tum_bag(tmp_path / "tum.bag", 3)  # damage found on opening: the ROS 1 index is gone
    with (tmp_path / "tum.bag").open("r+b") as f:
        f.truncate((tmp_path / "tum.bag").stat().st_size * 2 // 3)
    monkeypatch.setenv("ROS_DOMAIN_ID", "115")
    assert player_main([str(tmp_path / "tum.bag"), "--rate", "0", "--wait-subscribers", "0"]) == 1
    error = f"playback stopped after 0 frames: bag {tmp_path / 'tum.bag'} is corrupt or truncated"
    assert error in capfd.readouterr().err


def test_player_finishes_the_sequence_through_gausem_finish_and_survives_without_it():
    calls = []

    def on_finish(request, response):
        calls.append(request)
        response.success, response.message = True, "refined"
        return response

    with ros_session(116) as (ctx, executor):
        service_node = rclpy.create_node("fake_tracking", context=ctx)
        service_node.create_service(Trigger, "gausem/finish", on_finish)
        player = Player(open_source("synthetic", size=(16, 12), max_frames=2), rate=0.0, finish=True,
                        wait_subscribers=0.0, context=ctx)
        executor.add_node(service_node)
        executor.add_node(player)
        assert spin_until(executor, lambda: player.done, 10.0)
        assert player.published == 2 and player.finished is True and len(calls) == 1

    with ros_session(117) as (ctx, executor):  # nobody offers gausem/finish: the player gives up after its timeout
        player = Player(open_source("synthetic", size=(16, 12), max_frames=1), rate=0.0, finish=True, timeout=0.5,
                        wait_subscribers=0.0, context=ctx)
        executor.add_node(player)
        assert spin_until(executor, lambda: player.done, 10.0)
        assert player.published == 1 and player.finished is False


def test_a_replay_whose_labels_never_come_stops_with_code_2_and_names_the_fix(tmp_path, monkeypatch, capfd):
    """The bag records its labels under a topic the player does not know: with use_labels true nothing can be
    processed, and gausem-ros says so after a few frames instead of playing the whole bag; mapped with --topic, every
    frame is processed."""
    bag = tmp_path / "bag"
    frames = open_source("synthetic", size=(40, 30), max_frames=12)
    bags.write_bag(bag, convert.bag_messages(frames, {**GAUSEM_BAG_TOPICS, "labels": "/camera/labels"}))
    monkeypatch.setenv("ROS_DOMAIN_ID", "129")
    ros_args = ["--ros-args", *ros_param_args({**FAST_SLAM, "sync_wait": 0.5})]
    assert run_all_main([str(bag), "--lockstep", "--rate", "0", "--timeout", "30", "--quiet", *ros_args]) == 2
    err = capfd.readouterr().err
    assert "the replay cannot work" in err and "--topic labels=TOPIC" in err and "use_labels:=false" in err
    processed, published = (int(v) for v in re.search(r"processed (\d+),.* player published (\d+) frames",
                                                      err).groups())
    assert processed == 0 and published < 12
    assert run_all_main([str(bag), "--topic", "labels=/camera/labels", "--lockstep", "--rate", "0", "--timeout", "30",
                         "--quiet", *ros_args]) == 0
    assert re.search(r"frames in 12, processed 12, dropped 0", capfd.readouterr().err)


def test_a_looped_source_plays_on_with_increasing_stamps():
    """--loop: the source again and again, each pass one frame interval after the last (the nodes drop stale and
    duplicate stamps), its headers restamped with it, without ground truth; the player plays on past its end."""
    source = functools.partial(open_source, "synthetic", size=(16, 12), max_frames=3)
    frames = list(itertools.islice(looped(source(), source), 7))
    stamps = [frame.stamp_ns for frame in frames]
    assert all(abs(gap - 33_333_333) <= 1 for gap in np.diff(stamps)), stamps
    assert all(ma.time_to_ns(msg.header.stamp) == frame.stamp_ns for frame in frames for _, msg in frame.messages)
    assert all(frame.gt_pose is None for frame in frames)
    rgb = [ma.image_to_rgb(dict(frame.messages)["rgb"]) for frame in frames]
    assert np.array_equal(rgb[3], rgb[0]) and np.array_equal(rgb[6], rgb[0]) and not np.array_equal(rgb[1], rgb[0])
    assert len(list(looped(source(), lambda: iter(())))) == 3  # a pass of nothing ends it

    parser = argparse.ArgumentParser()
    add_player_arguments(parser)
    with pytest.raises(ValueError, match="--loop"):
        source_from_args(parser.parse_args(["synthetic", "--loop", "--gt-out", "gt.txt"]))
    ns = parser.parse_args(["synthetic", "--size", "16x12", "--max-frames", "2", "--rate", "0", "--loop",
                            "--wait-subscribers", "0"])
    with ros_session(118) as (ctx, executor):
        player = player_from_args(ns, context=ctx)
        recorder = Recorder(ctx, [(Clock, "/clock", IMAGE_QOS)])
        executor.add_node(player)
        executor.add_node(recorder.node)
        assert spin_until(executor, lambda: len(recorder.messages["/clock"]) >= 5, 20.0)
        clock = [ma.time_to_ns(c.clock) for c in recorder.messages["/clock"]]
        assert not player.done
    assert all(b > a for a, b in zip(clock, clock[1:])), clock
