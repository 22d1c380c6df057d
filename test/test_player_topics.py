"""The player's bag topics: an input recorded under another name is replayed with --topic INPUT=TOPIC."""
import numpy as np
import pytest

pytest.importorskip("rclpy")
pytest.importorskip("rosbags")

import msg_adapters as ma  # noqa: E402
from gausem_core.geometry import PinholeCamera  # noqa: E402
from gausem_ros import bags  # noqa: E402
from gausem_ros.player import bag_frames, open_source, parse_topics  # noqa: E402


def bag_with_labels_elsewhere(path, frames: int = 3) -> None:
    camera = PinholeCamera(30.0, 30.0, 8.0, 6.0, 16, 12)
    messages = []
    for k in range(frames):
        t = 100.0 + k / 30
        header = ma.make_header(t, "camera")
        messages += [(bags.TUM_TOPICS["rgb"], ma.seconds_to_ns(t), ma.rgb_to_image(np.zeros((12, 16, 3), np.uint8),
                                                                                   header)),
                     (bags.TUM_TOPICS["camera_info"], ma.seconds_to_ns(t), ma.camera_to_camera_info(camera, header)),
                     (bags.TUM_TOPICS["depth"], ma.seconds_to_ns(t), ma.depth_to_image(
                         np.full((12, 16), 1.0, np.float32), header)),
                     ("/camera/labels", ma.seconds_to_ns(t), ma.labels_to_image(np.full((12, 16), k, np.int64),
                                                                                header))]
    bags.write_ros1_bag(path, messages)


def test_a_labels_topic_of_another_name_is_replayed_when_mapped(tmp_path):
    path = tmp_path / "labels.bag"
    bag_with_labels_elsewhere(path)
    unmapped = list(bag_frames(path))
    assert len(unmapped) == 3 and all("labels" not in dict(f.messages) for f in unmapped)
    mapped = list(open_source(str(path), topics=parse_topics(["labels=/camera/labels"])))
    assert [int(ma.image_to_labels(dict(f.messages)["labels"])[0, 0]) for f in mapped] == [0, 1, 2]
    assert {key for key, _ in mapped[0].messages} == {"rgb", "depth", "camera_info", "labels"}


def test_bad_topic_mappings_are_named():
    with pytest.raises(ValueError, match="INPUT=TOPIC"):
        parse_topics(["semantics=/x"])
    with pytest.raises(ValueError, match="INPUT=TOPIC"):
        parse_topics(["labels="])
    with pytest.raises(ValueError, match="applies to bags"):
        open_source("synthetic", topics={"labels": "/x"})
