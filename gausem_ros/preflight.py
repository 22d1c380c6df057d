"""Checks a launch makes before any node starts: what would otherwise fail in every node (and again at each respawn)
or only after minutes of replay. Each check returns problems as sentences; none means go."""
from __future__ import annotations

import argparse
import os
import shlex
from pathlib import Path

import yaml

from gausem_core.config import dotted_names, load_config
from gausem_core.slam.persistence import SESSION_FILE, SessionError, read_document

from .bags import BagError, bag_topics
from .player import BAG_TOPIC_KEYS, add_player_arguments, is_bag, parse_topics, source_from_args

TRACKING_NODE = "tracking_mapping"


def ros_parameters(params_file: str | None, ros_args: list[str], node: str = TRACKING_NODE) -> dict[str, object]:
    """The parameters ``node`` gets from ``params_file`` (its own section and ``/**``) and from ``-p NAME:=VALUE``
    (or ``-p node:NAME:=VALUE``) in ``ros_args``, later ones winning; nested names dotted. Raises ValueError."""
    values: dict[str, object] = {}
    if params_file:
        if not Path(params_file).is_file():
            raise ValueError(f"parameter file {params_file} does not exist")
        doc = yaml.safe_load(Path(params_file).read_text()) or {}
        for name in ("/**", node, f"/{node}"):
            body = doc.get(name) if isinstance(doc, dict) else None
            if isinstance(body, dict):
                values.update(dotted_names(body.get("ros__parameters") or {}))
    for flag, assignment in zip(ros_args, ros_args[1:]):
        if flag not in ("-p", "--param"):
            continue
        name, sep, raw = assignment.partition(":=")
        target, _, name = name.rpartition(":")
        if not sep:
            raise ValueError(f"-p {assignment!r}: expected NAME:=VALUE")
        if target in ("", node):
            values[name] = yaml.safe_load(raw)
    return values


def check_parameters(params_file: str | None, ros_args: list[str]) -> list[str]:
    """The parameter file exists and has the ROS 2 layout, and the SLAM parameters in it and in ``-p`` read."""
    try:
        values = ros_parameters(params_file, ros_args)
        load_config(params_file, {name: value for name, value in values.items() if "." in name})
    except (OSError, ValueError, yaml.YAMLError) as err:
        return [f"parameters: {err}"]
    return []


def check_map_path(map_path: str) -> list[str]:
    """``map_path`` resumes a session when it holds one (which must read), else a new map is checkpointed there."""
    if not map_path:
        return []
    path = Path(map_path)
    if path.exists() and not path.is_dir():
        return [f"map_path {map_path}: not a folder"]
    if (path / SESSION_FILE).exists():
        try:
            read_document(path)
        except (OSError, SessionError) as err:
            return [f"map_path {map_path} cannot be resumed: {err}"]
        return []
    parent = next((p for p in (path, *path.parents) if p.exists()), Path("."))
    if not parent.is_dir() or not _writable(parent):
        return [f"map_path {map_path}: no session there yet and {parent} is not a writable folder to create it in"]
    return []


def _writable(folder: Path) -> bool:
    return os.access(folder, os.W_OK | os.X_OK)


def check_bag(path: str, topics: dict[str, str]) -> list[str]:
    """A bag the player can replay: it opens, ``--topic`` names its topics, rgb and depth come from it."""
    try:
        available = bag_topics(path)
    except BagError as err:
        return [str(err)]
    missing = sorted(topic for topic in topics.values() if topic not in available)
    if missing:
        return [f"bag {path} has no topics {missing} (--topic); it has {sorted(available)}"]
    keys = {**BAG_TOPIC_KEYS, **{topic: key for key, topic in topics.items()}}
    inputs = {keys[topic] for topic in available if topic in keys}
    absent = [key for key in ("rgb", "depth") if key not in inputs]
    if absent:
        return [f"bag {path}: no {' or '.join(absent)} topic among {sorted(available)} (map one with --topic "
                f"{absent[0]}=TOPIC)"]
    return []


class _RaisingParser(argparse.ArgumentParser):
    def error(self, message):
        raise ValueError(message)


def check_player(player_args: str) -> list[str]:
    """The player's arguments parse, a dataset opens and a bag passes :func:`check_bag`."""
    parser = _RaisingParser(prog="gausem-player")
    add_player_arguments(parser)
    try:
        ns = parser.parse_args(shlex.split(player_args))
        source_from_args(ns)
    except (OSError, ValueError) as err:
        return [f"--play: {err}"]
    return check_bag(ns.source, parse_topics(ns.topic)) if is_bag(ns.source) else []


def launch_problems(params_file: str | None, tracking_args: list[str], player_args: str | None) -> list[str]:
    """Every check for a launch of the tracking node with ``params_file`` and ``tracking_args`` (its ROS arguments)
    and, when given, a player with ``player_args``."""
    problems = check_parameters(params_file, tracking_args)
    if not problems:
        problems += check_map_path(str(ros_parameters(params_file, tracking_args).get("map_path") or ""))
    return problems + (check_player(player_args) if player_args else [])
