"""Writes a dataset as a bag (entry point ``gausem-bag``): ``gausem-bag SPEC OUT [--format sqlite3|mcap|ros1]``.

ROS 2 bags carry GauSem's topics (``/rgb/image``, ``/depth/image``, ``/rgb/camera_info``, ``/semantic/labels`` when
the data has labels); ROS 1 bags the TUM RGB-D names (``/camera/rgb/image_color``, ``/camera/depth/image``,
``/camera/rgb/camera_info``) plus ``/semantic/labels``. Both replay with ``gausem-player``. Ground truth is not written.
"""
from __future__ import annotations

import argparse
import sys
from collections.abc import Iterator

from .bags import ROS2_STORAGE, TUM_TOPICS, write_bag, write_ros1_bag
from .player import GAUSEM_BAG_TOPICS, PlayerFrame, add_source_arguments, open_source

ROS1_TOPICS = {**GAUSEM_BAG_TOPICS, **{key: TUM_TOPICS[key] for key in ("rgb", "depth", "camera_info")}}


def bag_messages(frames, topics: dict[str, str]) -> Iterator[tuple[str, int, object]]:
    """(topic, stamp ns, msg) of every frame's messages, with ``topics`` naming each input key."""
    frame: PlayerFrame
    for frame in frames:
        for key, msg in frame.messages:
            yield topics[key], frame.stamp_ns, msg


def convert(frames, out: str, fmt: str = "sqlite3") -> None:
    """Write ``frames`` (``PlayerFrame`` iterable) to ``out``: a ROS 2 bag folder (sqlite3, mcap) or a ROS 1 bag."""
    if fmt == "ros1":
        write_ros1_bag(out, bag_messages(frames, ROS1_TOPICS))
    else:
        write_bag(out, bag_messages(frames, GAUSEM_BAG_TOPICS), storage=fmt)


def main(args=None) -> int:
    parser = argparse.ArgumentParser(prog="gausem-bag", description=__doc__.split("\n")[0])
    add_source_arguments(parser)
    parser.add_argument("out", help="output: a new ROS 2 bag folder, or a .bag file with --format ros1")
    parser.add_argument("--format", choices=(*ROS2_STORAGE, "ros1"), default="sqlite3")
    ns = parser.parse_args(sys.argv[1:] if args is None else args)
    try:
        convert(open_source(ns.source, size=ns.size, stride=ns.stride, max_frames=ns.max_frames,
                            frame_id=ns.frame_id, depth_encoding=ns.depth_encoding), ns.out, ns.format)
    except (ValueError, FileNotFoundError, FileExistsError) as err:
        print(f"gausem-bag: {err}", file=sys.stderr)
        return 1
    print(f"gausem-bag: wrote {ns.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
