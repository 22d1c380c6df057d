"""Lock-step replay answers every frame: a frame the synchroniser drops is answered by the diagnostics, so the player
spends no timeout on it."""
import copy
import dataclasses

import pytest

pytest.importorskip("rclpy")

from gausem_ros.nodes.tracking_mapping import TrackingMappingNode  # noqa: E402
from gausem_ros.sync import ApproximateTimeSync  # noqa: E402
from gausem_ros.player import Player, open_source  # noqa: E402
from ros_harness import FAST_SLAM, overrides, ros_session, spin_until  # noqa: E402


@pytest.fixture(autouse=True)
def _localhost(monkeypatch):
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")


def test_a_frame_the_synchroniser_cannot_match_costs_the_lockstep_player_no_timeout():
    """Frame 3's depth is 0.2 s off its rgb image (beyond sync_slop): in lock-step no later frame comes to match past
    it; after sync_wait the node drops it as unmatched and names its stamp as handled, and the player goes on."""
    frames = list(open_source("synthetic", size=(40, 30), max_frames=5))
    late = frames[3].stamp_ns + 200_000_000
    frames[3] = dataclasses.replace(frames[3], messages=[(key, _restamped(msg, late) if key == "depth" else msg)
                                                         for key, msg in frames[3].messages])
    with ros_session(168) as (ctx, executor):
        tracking = TrackingMappingNode(context=ctx, parameter_overrides=overrides(
            {**FAST_SLAM, "worker.mode": "sync", "sync_wait": 0.5}))
        player = Player(frames, rate=0.0, lockstep=True, timeout=60.0, context=ctx)
        executor.add_node(tracking)
        executor.add_node(player)
        assert spin_until(executor, lambda: player.done, 120.0)
        assert player.published == 5 and player.timeouts == 0
        assert tracking.frames_processed == 4 and tracking.drops.counts["unmatched"] == 1, dict(tracking.drops.counts)


def _restamped(msg, stamp_ns: int):
    """A copy of ``msg`` stamped ``stamp_ns`` (a frame's messages share one header)."""
    msg = copy.deepcopy(msg)
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 10**9)
    return msg


def test_flush_drops_only_the_messages_that_waited_longer_than_max_age():
    now = [0.0]
    drops = []
    s = ApproximateTimeSync(["rgb", "depth"], lambda *msgs: None, slop=0.01,
                            on_drop=lambda *drop: drops.append(drop), clock=lambda: now[0])
    s.add(1, 9.0, "depth9")  # depth arrives (for a later frame): no input is silent
    s.add(0, 1.0, "rgb1")
    now[0] = 0.4
    s.add(0, 2.0, "rgb2")
    now[0] = 0.6
    s.flush(0.5)
    assert [(index, reason, stamp) for index, reason, _, stamp in drops] == [(0, "unmatched", 1.0),
                                                                            (1, "unmatched", 9.0)]
    assert s.pending(0) == 1 and s.dropped[("rgb", "unmatched")] == 1 and "nearest depth" in drops[0][2]


def test_while_an_input_has_never_delivered_flush_drops_every_waiting_message():
    """Labels that never come: the first frames wait max_age as usual; after that, each flush drops what waits, so a
    frame is dropped at the next flush instead of max_age after it arrived."""
    now = [0.0]
    drops = []
    s = ApproximateTimeSync(["rgb", "labels"], lambda *msgs: None, slop=0.01,
                            on_drop=lambda *drop: drops.append(drop), clock=lambda: now[0])
    s.add(0, 1.0, "rgb1")
    now[0] = 0.3
    s.flush(0.5)
    assert drops == [] and s.pending(0) == 1  # not yet silent for max_age
    now[0] = 0.5
    s.add(0, 2.0, "rgb2")
    s.flush(0.5)
    assert [stamp for *_, stamp in drops] == [1.0, 2.0]  # rgb2 waited no time at all
    assert "no labels received at all" in drops[1][2]
    s.add(1, 3.0, "labels3")  # labels arrive after all: messages wait max_age again
    now[0] = 0.7
    s.add(0, 4.0, "rgb4")
    s.flush(0.5)
    assert s.pending(0) == 1 and s.pending(1) == 1
