"""Chaos: ``kill -9`` of the tracking node, again and again, under ``gausem-launch --respawn``; does every restart
resume its checkpoint?

Runs ``gausem-launch --respawn`` (the player ``--loop``-ing a bag of SOURCE at ``--rate`` 1, 160x120; the tracking
node on the CPU in its live defaults, checkpointing into a temporary ``map_path`` every ``checkpoint_keyframes`` (5)
keyframes or ``--checkpoint-period`` s) and SIGKILLs ``tracking_mapping`` ``--kills`` times. Each kill waits until
the node (re)started is tracking and has written a checkpoint of its own, then a seeded random ``--min-wait`` to
``--max-wait`` s, then for its target (seeded, in turn):

- ``checkpoint``: a checkpoint being written, seen every few ms in the map folder and the node's open files
  (``/proc/PID/fd``): a tensor file open, ``session.json.partial`` not yet renamed, or tensor files that
  ``session.json`` does not name (the new save's before the rename, the previous one's until they are deleted);
- ``event``: the node publishing a submap's opening (``gausem/submaps``) or a loop closure
  (``gausem/loop_constraints``): the keyframe that opened it or closed the loop was just mapped, and the node is
  handing its events on (a checkpoint often falls due then);
- ``any``: the moment the wait ends.

A target not met within ``--arm-timeout`` s is killed anyway. Each kill's moment is classified by the evidence at
the kill (:func:`moment`). Right after the kill (the process gone, the respawn ``--respawn-delay`` s away) the map
folder is copied: it is what the next node loads. Each restart is checked: the copy loads with the core's loader
(``GauSemSLAM.load``); what an interrupted write left there; a new process under the launcher, its diagnostics
flowing again and its log saying it loaded the map; the first ``gausem/path`` it publishes (rebuilt from the loaded
trajectory, latched) begins with the checkpoint's trajectory, stamps and poses identical (:func:`prefix`); the
checkpoint's frames are the first of those the killed node had published (its last path: stamps identical; poses
compared, as a loop closure or mapping after the checkpoint may have moved them); and it goes on tracking:
``--frames-after`` frames processed, frames in = processed + dropped + pending at that sample. Writes the record
``benchmarks/results/<name>.json`` and the log ``out/<name>.log``. Issue 63's acceptance (exit code 1 when not met):
every restart resumed a readable checkpoint, and the counts add up (kills = the launcher's SIGKILL reports = its
restarts; the input accounting at every restart's sample).

    python benchmarks/chaos.py [--kills 10] [--seed 0] [--source synthetic:loop] [--name NAME] [-- ROS_ARGS]
"""
from __future__ import annotations

import argparse
import os
import random
import re
import shutil
import signal
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from nav_msgs.msg import Path as PathMsg
from sensor_msgs.msg import PointCloud2

import msg_adapters as ma
from gausem_bench import results
from gausem_bench.launch import (DiagnosticsListener, add_launch_arguments, adds_up, children, launch_command,
                                 local_domain, log_file, parse_launch_arguments, process_stats, scan_log, source_bag,
                                 start_launcher, stop)
from gausem_core.slam.persistence import SESSION_FILE
from gausem_core.slam.system import GauSemSLAM
from gausem_ros.nodes.tracking.trajectory import path_poses
from gausem_ros.preflight import TRACKING_NODE
from gausem_ros.qos import EVENT_QOS, LATCHED_QOS

WHAT = ("`benchmarks/chaos.py`: `gausem-launch --respawn` with the player looping a bag of the source at the "
        "recorded pace (CPU, 160x120, the tracking node's live defaults checkpointing into `map_path`), the tracking "
        "node killed with SIGKILL at seeded random moments, some aimed at a checkpoint being written, some at a "
        "submap's opening or a loop closure; each restart checked: the checkpoint left reads with the core's loader, "
        "the restarted node loads it and publishes its trajectory unchanged, and goes on tracking.")
TARGETS = ("checkpoint", "event", "any")
EVENT_KINDS = ("loop closure", "submap opening")
MOMENTS = ("checkpoint write", *EVENT_KINDS, "tracking")
TENSOR_FILE = re.compile(r"^(state|submap_\d{4})(\.[0-9a-f]+)?\.pt$")
PARTIAL = SESSION_FILE + ".partial"
EVENT_WINDOW_S = 1.0  # a kill this soon after a submap opened or a loop closed counts as during it
POLL_S = 0.003  # how often a kill aimed at a checkpoint looks at the map folder
STALL_WINDOW_S = 5.0  # a node that does not get ready: its CPU time is measured over this long


# --- the plan and the moments ---------------------------------------------------------------------------------------
def plan(seed: int, kills: int, min_wait: float, max_wait: float) -> list[tuple[str, float]]:
    """Each kill's target (the three in turn, in a seeded order) and its wait (seeded, uniform)."""
    rng = random.Random(seed)
    targets = [TARGETS[i % len(TARGETS)] for i in range(kills)]
    rng.shuffle(targets)
    return [(target, round(rng.uniform(min_wait, max_wait), 2)) for target in targets]


def named_files(session_text: str) -> set[str]:
    """The tensor files a ``session.json``'s references name."""
    return set(re.findall(r'"\$tensor": "([^":]+):', session_text))


def named_files_of(folder: Path) -> set[str] | None:
    """The tensor files the ``session.json`` in ``folder`` names; None without one."""
    try:
        return named_files((folder / SESSION_FILE).read_text())
    except OSError:
        return None


def checkpoint_phase(listing: list[str], named: set[str] | None, open_files: list[str]) -> str | None:
    """What a checkpoint write is doing, from the map folder's file names, the tensor files its ``session.json``
    names (None: no session yet) and the folder's files the node holds open; None when none is under way."""
    if open_files:
        return f"writing {', '.join(sorted(open_files))}"
    if PARTIAL in listing:
        return f"{PARTIAL} written, not yet renamed"
    unnamed = sorted(n for n in listing if TENSOR_FILE.match(n) and n not in (named or set()))
    if unnamed:
        return f"{len(unnamed)} tensor files session.json does not name ({', '.join(unnamed)})"
    return None


def moment(phase: str | None, ages: dict[str, float | None]) -> str:
    """A kill's moment: ``checkpoint write`` when one was under way (``phase``), ``loop closure`` and ``submap
    opening`` when the node published one at most :data:`EVENT_WINDOW_S` before (``ages``: seconds since the last
    of each, None: none yet), joined by `` + ``; ``tracking`` when none of them."""
    kinds = ["checkpoint write"] if phase else []
    kinds += [kind for kind in EVENT_KINDS if ages.get(kind) is not None and ages[kind] <= EVENT_WINDOW_S]
    return " + ".join(kinds) or "tracking"


def path_rows(path: PathMsg) -> tuple[np.ndarray, np.ndarray]:
    """A path's stamps (ns) and poses (x y z qx qy qz qw), as published."""
    stamps = np.array([ma.time_to_ns(p.header.stamp) for p in path.poses], dtype=np.int64)
    poses = np.array([[p.pose.position.x, p.pose.position.y, p.pose.position.z, p.pose.orientation.x,
                       p.pose.orientation.y, p.pose.orientation.z, p.pose.orientation.w] for p in path.poses],
                     dtype=np.float64).reshape(-1, 7)
    return stamps, poses


def prefix(held: tuple[np.ndarray, np.ndarray], published: tuple[np.ndarray, np.ndarray]) -> dict:
    """Whether ``published`` (stamps, poses) begins with the frames ``held``: ``stamps`` the same, ``poses`` too
    (bit for bit), and the largest position (m) and rotation (degrees) differences over them (None when the stamps
    differ)."""
    n = len(held[0])
    same = len(published[0]) >= n and np.array_equal(published[0][:n], held[0])
    out = {"frames": n, "published": len(published[0]), "stamps": bool(same),
           "poses": bool(same and np.array_equal(published[1][:n], held[1])), "position_m": None, "rotation_deg": None}
    if same and n:
        ours, theirs = held[1], published[1][:n]
        cos = np.clip(np.abs(np.sum(ours[:, 3:] * theirs[:, 3:], axis=1)), 0.0, 1.0)  # q and -q: one rotation
        out.update(position_m=float(np.linalg.norm(ours[:, :3] - theirs[:, :3], axis=1).max()),
                   rotation_deg=float(np.degrees(2 * np.arccos(cos)).max()))
    return out


# --- watching the node ----------------------------------------------------------------------------------------------
class NodeWatch:
    """What the node publishes besides its diagnostics (its latest path, when it last opened a submap or closed a
    loop) and what its map folder shows."""

    def __init__(self, listener: DiagnosticsListener, folder: Path):
        self.listener, self.folder = listener, folder
        node = listener.node
        node.create_subscription(PathMsg, "gausem/path", self._on_path, LATCHED_QOS)
        node.create_subscription(PointCloud2, "gausem/submaps", self._on_submaps, EVENT_QOS)
        node.create_subscription(PointCloud2, "gausem/loop_constraints", self._on_loop, EVENT_QOS)
        self.last: dict[str, float] = {}  # when each kind of event last arrived (time.monotonic)
        self.events = 0
        self._session: tuple[tuple[int, int], set[str] | None] | None = None  # session.json's (inode, mtime) and names
        self.forget()

    def forget(self) -> None:
        """A new node: its path and diagnostics are still to come."""
        self.path: PathMsg | None = None
        self.listener.latest, self.listener.values = None, {}

    def _on_path(self, msg: PathMsg) -> None:
        self.path = msg

    def _on_submaps(self, msg: PointCloud2) -> None:
        if any(e.kind == ma.SubmapEventKind.CREATED for e in ma.pointcloud2_to_records(msg, ma.SubmapEvent)):
            self._event("submap opening")

    def _on_loop(self, msg: PointCloud2) -> None:
        del msg
        self._event("loop closure")

    def _event(self, kind: str) -> None:
        self.last[kind] = time.monotonic()
        self.events += 1

    def ages(self) -> dict[str, float | None]:
        now = time.monotonic()
        return {kind: round(now - self.last[kind], 3) if kind in self.last else None
                for kind in EVENT_KINDS}

    def phase(self, pid: int) -> str | None:
        """What a checkpoint write of process ``pid`` is doing now (:func:`checkpoint_phase`)."""
        try:
            listing = os.listdir(self.folder)
        except OSError:
            return None
        return checkpoint_phase(listing, self._named(), open_in(pid, self.folder))

    def _named(self) -> set[str] | None:
        try:
            stat = (self.folder / SESSION_FILE).stat()
        except OSError:
            return None
        key = (stat.st_ino, stat.st_mtime_ns)
        if self._session is None or self._session[0] != key:
            self._session = (key, named_files_of(self.folder))
        return self._session[1]


def open_in(pid: int, folder: Path) -> list[str]:
    """The names of the files in ``folder`` that process ``pid`` holds open."""
    names, fds = [], Path(f"/proc/{pid}/fd")
    try:
        entries = os.listdir(fds)
    except OSError:
        return names
    for fd in entries:
        try:
            target = Path(os.readlink(fds / fd))
        except OSError:
            continue
        if target.parent == folder:
            names.append(target.name)
    return names


def cpu_seconds(pid: int | None) -> float | None:
    """The CPU time (user and system) process ``pid`` used so far; None when it is gone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def spin_until(listener: DiagnosticsListener, condition: Callable[[], bool], timeout: float,
               step: float = 0.1) -> bool:
    """Spin until ``condition()`` or ``timeout`` s passed; whether it held."""
    end = time.monotonic() + timeout
    while not condition():
        if time.monotonic() >= end:
            return False
        listener.spin(step)
    return True


# --- one kill and its restart ---------------------------------------------------------------------------------------
class Chaos:
    """The launcher, the listener and the kills."""

    def __init__(self, args, launcher, listener: DiagnosticsListener, watch: NodeWatch, log_path: Path, copies: Path):
        self.args, self.launcher, self.listener, self.watch = args, launcher, listener, watch
        self.log_path, self.copies = log_path, copies

    def tracker(self) -> int | None:
        return children(self.launcher.pid).get(TRACKING_NODE)

    def loads_logged(self) -> int:
        return self.log_path.read_text(errors="replace").count("loaded the map in ")

    def ready(self, timeout: float) -> int | None:
        """The node's PID once it tracks (frames processed) and has checkpointed since it started; None when it does
        not within ``timeout`` s."""
        ok = spin_until(self.listener, lambda: self.launcher.poll() is None and self.tracker() is not None
                        and int(self.listener.values.get("frames_processed", 0)) > 0
                        and int(self.listener.values.get("checkpoint.written", 0)) > 0, timeout)
        return self.tracker() if ok else None

    def stalled(self) -> dict:
        """What the node showed when it did not get ready: its last diagnostics (the counts, the checkpoints, the
        mapping worker) and their age, and the CPU seconds its process used over :data:`STALL_WINDOW_S`."""
        pid, values = self.tracker(), self.listener.values
        keys = ("frames_in", "frames_processed", "frames_pending", "checkpoint.written", "worker.queue_depth",
                "worker.lag_frames", "tracking.status")
        before = cpu_seconds(pid)
        self.listener.spin(STALL_WINDOW_S)
        after = cpu_seconds(pid)
        return {"pid": pid, "diagnostics": {k: values[k] for k in keys if k in values},
                "diagnostics_age_s": round(time.monotonic() - self.listener.received_at, 1) if values else None,
                "cpu_s": round(after - before, 2) if None not in (before, after) else None}

    def aim(self, pid: int, target: str) -> tuple[str | None, bool]:
        """Wait for ``target``'s moment (at most ``--arm-timeout`` s); the checkpoint phase then and whether the
        target was met."""
        end = time.monotonic() + self.args.arm_timeout
        events = self.watch.events
        spun = time.monotonic()
        while time.monotonic() < end:
            if target == "any":
                return self.watch.phase(pid), True
            if target == "checkpoint":
                if (phase := self.watch.phase(pid)) is not None:
                    return phase, True
                time.sleep(POLL_S)
                if time.monotonic() - spun > 0.2:  # the subscriptions' callbacks now and then
                    self.listener.executor.spin_once(timeout_sec=0)
                    spun = time.monotonic()
            else:
                self.listener.executor.spin_once(timeout_sec=0.01)
                if self.watch.events > events:
                    return self.watch.phase(pid), True
        return self.watch.phase(pid), False

    def kill(self, index: int, target: str, wait: float) -> dict:
        """One kill (after the node is ready and ``wait`` s) and its restart's checks."""
        entry = {"kill": index + 1, "target": target, "wait_s": wait}
        pid = self.ready(self.args.restart_timeout)
        if pid is None:
            return {**entry, "error": "the node was not tracking and checkpointing", "stalled": self.stalled()}
        self.listener.spin(wait)
        phase, met = self.aim(pid, target)
        ages, loads = self.watch.ages(), self.loads_logged()
        os.kill(pid, signal.SIGKILL)
        killed_at = time.monotonic()
        spin_until(self.listener, lambda: process_stats(pid) is None, 5.0, 0.01)
        copy = self.copies / f"kill_{index + 1:02d}"
        shutil.copytree(self.watch.folder, copy)
        entry.update(pid=pid, target_met=met, phase=phase, ages=ages, moment=moment(phase, ages),
                     left=checkpoint_phase(os.listdir(copy), named_files_of(copy), []))
        self.listener.spin(0.3)  # what the killed node sent before it died
        killed_path, frames_before = self.watch.path, int(self.listener.values.get("frames_processed", 0))
        self.watch.forget()
        entry.update(frames_before=frames_before, **checkpoint_checks(copy, killed_path))
        entry.update(self.restart(pid, killed_at, loads, entry.get("held")))
        entry.pop("held", None)
        checks = {"readable": entry["readable"], "loaded": entry.get("loaded"),
                  "trajectory": entry.get("trajectory", {}).get("poses"),
                  "killed_path": entry.get("killed_path", {}).get("stamps"), "tracking": entry.get("tracking")}
        entry["failed"] = [name for name, ok in checks.items() if not ok]
        entry["resumed"] = not entry["failed"]
        return entry

    def restart(self, pid: int, killed_at: float, loads: int, held) -> dict:
        """The restarted node: new PID, diagnostics again, the load logged, its first path against the checkpoint's
        trajectory, frames processed after it."""
        found = {}

        def back() -> bool:
            new = self.tracker()
            if new is not None and new != pid and "new_pid" not in found:
                found.update(new_pid=new, process_s=round(time.monotonic() - killed_at, 1))
            if self.listener.latest is not None and "diagnostics_s" not in found:
                found["diagnostics_s"] = round(time.monotonic() - killed_at, 1)
            if self.watch.path is not None and "path" not in found:
                found["path"] = self.watch.path
            return (self.listener.latest is not None and self.listener.latest["frames_processed"]
                    >= self.args.frames_after and "path" in found and "new_pid" in found)
        tracking = spin_until(self.listener, back, self.args.restart_timeout)
        out = {"new_pid": found.get("new_pid"), "process_s": found.get("process_s"),
               "diagnostics_s": found.get("diagnostics_s"), "loaded": self.loads_logged() > loads,
               "tracking": tracking, "frames_after": (self.listener.latest or {}).get("frames_processed"),
               "counts_after": self.listener.latest, "rss_mb": (process_stats(found["new_pid"]) or {}).get("rss_mb")
               if "new_pid" in found else None}
        if held is not None and "path" in found:
            out["trajectory"] = prefix(held, path_rows(found["path"]))
        return out


def checkpoint_checks(copy: Path, killed_path: PathMsg | None) -> dict:
    """The checkpoint a kill left (``copy``): whether the core's loader reads it, its frames, and how its trajectory
    (as a path rebuilt from it publishes it) compares with what the killed node had published."""
    try:
        slam = GauSemSLAM.load(copy, "cpu")
    except (OSError, ValueError) as err:  # SessionError is a ValueError
        return {"readable": False, "load_error": str(err)}
    try:
        held = path_rows(ma.poses_to_path(path_poses(slam), "map"))
        submaps = len(slam.submaps)
    finally:
        slam.close()
    out = {"readable": True, "held": held, "checkpoint_frames": len(held[0]), "checkpoint_submaps": submaps}
    if killed_path is not None:
        out["killed_path"] = prefix(held, path_rows(killed_path))
    return out


# --- the run and its record -----------------------------------------------------------------------------------------
def chaos(args, bag: str, ros_args: list[str], log_path: Path, folder: Path) -> dict:
    """Run the launcher with ``--respawn`` playing ``bag`` and kill the tracking node ``args.kills`` times."""
    domain = local_domain(72)
    listener = DiagnosticsListener(domain, "chaos_listener")
    watch = NodeWatch(listener, folder / "map")
    ros_args = ["-p", f"map_path:={watch.folder}", "-p", f"checkpoint_period:={float(args.checkpoint_period)!r}",
                *ros_args]
    launcher = start_launcher(launch_command(args, bag, ros_args, ("--respawn", "--respawn-delay",
                                                                   f"{args.respawn_delay:g}")), log_path)
    run = Chaos(args, launcher, listener, watch, log_path, folder / "copies")
    kills, ended, start = [], "done", time.monotonic()
    previous = signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        for index, (target, wait) in enumerate(plan(args.seed, args.kills, args.min_wait, args.max_wait)):
            kills.append(run.kill(index, target, wait))
            k = kills[-1]
            print(f"kill {k['kill']}: {k['target']} -> {k.get('moment')} ({k.get('phase')}); resumed: "
                  f"{k.get('resumed')} {k.get('failed') or ''} ({time.monotonic() - start:.0f} s)", flush=True)
            if "error" in k or launcher.poll() is not None:
                ended = f"stopped early: {k.get('error') or 'the launcher ended'}"
                break
    except KeyboardInterrupt:
        ended = f"interrupted after {time.monotonic() - start:.0f} s"
    finally:
        signal.signal(signal.SIGTERM, previous)
        killed = stop(launcher, args.grace + 15)
        listener.close()
    return {"kills": kills, "ended": ended, "seconds": round(time.monotonic() - start), "killed": killed,
            "launcher_exit_code": launcher.returncode, "diagnostics_messages": listener.messages,
            "diagnostics_mismatches": listener.mismatches, "domain": domain}


def summarise(run: dict, log: dict, restarts: int, planned: int) -> dict:
    """The acceptance figures: restarts that resumed a readable checkpoint, the kills by moment (a kill counts under
    each kind its moment names), whether the counts add up (``restarts``: the launcher's); ``passed`` when every
    planned kill's restart resumed and the counts add up."""
    kills = run["kills"]
    sigkills = sum("ended with signal SIGKILL" in line for line in log["launcher"])
    samples = [k["counts_after"] for k in kills if k.get("counts_after")]
    summary = {"kills": len(kills), "planned": planned, "resumed": sum(bool(k.get("resumed")) for k in kills),
               "readable": sum(bool(k.get("readable")) for k in kills),
               "moments": {m: sum(m in (k.get("moment") or "").split(" + ") for k in kills) for m in MOMENTS},
               "targets_met": sum(bool(k.get("target_met")) for k in kills),
               "launcher_sigkills": sigkills, "launcher_restarts": restarts,
               "samples_adding_up": f"{sum(map(adds_up, samples))} of {len(samples)}",
               "exceptions": log["exceptions"], "errors": log["errors"][:20], "errors_total": len(log["errors"]),
               "ended": run["ended"]}
    summary["counts_add_up"] = (sigkills == restarts == len(kills) and len(samples) == len(kills)
                                and all(map(adds_up, samples)))
    summary["passed"] = summary["resumed"] == planned == len(kills) and summary["counts_add_up"]
    return summary


def untokened(text: str | None) -> str:
    """Tensor file names without their save's token (the page takes hex words for commit hashes); "–" for none."""
    return re.sub(r"\.[0-9a-f]+\.pt\b", ".pt", text) if text else "–"


def kill_table(kills: list[dict]) -> dict:
    def yes(value) -> str | None:
        return None if value is None else ("yes" if value else "NO")
    rows = []
    for k in kills:
        trajectory, killed = k.get("trajectory") or {}, k.get("killed_path") or {}
        rows.append([k["kill"], k["target"], k.get("moment"), untokened(k.get("phase")), k.get("checkpoint_frames"),
                     yes(k.get("readable")), untokened(k.get("left")), k.get("diagnostics_s"), yes(k.get("loaded")),
                     f"{'identical' if trajectory.get('poses') else 'DIFFERS'} ({trajectory.get('frames')} of "
                     f"{trajectory.get('published')})" if trajectory else None,
                     f"first {killed['frames']}, poses within {killed['position_m'] or 0:.3f} m, "
                     f"{killed['rotation_deg'] or 0:.2f} deg" if killed.get("stamps") else
                     ("NOT its first frames" if killed else None),
                     k.get("frames_after"), yes(k.get("resumed"))])
    return results.table(["kill", "aimed at", "moment", "checkpoint write then", "frames in checkpoint", "readable",
                          "an interrupted write left", "diagnostics again (s)", "loaded", "trajectory resumed",
                          "killed node's path held them", "frames after", "resumed"], rows, title=TRACKING_NODE)


def notes(run: dict, summary: dict) -> list[str]:
    moments = ", ".join(f"{m} {n}" for m, n in summary["moments"].items())
    lines = [f"{summary['resumed']} of {summary['planned']} restarts resumed a readable checkpoint "
             f"(acceptance, issue 63: {'passed' if summary['passed'] else 'FAILED'}); the run {summary['ended']}, "
             f"in {run['seconds']} s.",
             f"Kills by moment: {moments}; {summary['targets_met']} of {summary['kills']} met what they were aimed at.",
             f"The launcher reported {summary['launcher_sigkills']} SIGKILLs and {summary['launcher_restarts']} "
             f"restarts for {summary['kills']} kills; frames in = processed + dropped + pending at "
             f"{summary['samples_adding_up']} restart samples and in "
             f"{run['diagnostics_messages'] - run['diagnostics_mismatches']} of {run['diagnostics_messages']} "
             "diagnostics messages.",
             f"Exceptions in the nodes' log: {'; '.join(summary['exceptions']) or 'none'}; error lines: "
             f"{summary['errors_total']}" + (f"; killed at shutdown: {', '.join(run['killed'])}" if run["killed"]
                                            else "") + "."]
    lines += [f"Kill {k['kill']}: the node (pid {k['stalled']['pid']}) did not get ready; its last diagnostics, "
              f"{k['stalled']['diagnostics_age_s']} s old: {k['stalled']['diagnostics']}; it used "
              f"{k['stalled']['cpu_s']} CPU s in {STALL_WINDOW_S:g} s." for k in run["kills"] if "stalled" in k]
    return lines


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--kills", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--min-wait", type=float, default=0.0, help="seconds after the node is ready, at least")
    parser.add_argument("--max-wait", type=float, default=10.0, help="... and at most")
    parser.add_argument("--arm-timeout", type=float, default=60.0, help="seconds a kill waits for its target")
    parser.add_argument("--restart-timeout", type=float, default=180.0, help="seconds a restart may take")
    parser.add_argument("--frames-after", type=int, default=10, help="frames a restarted node must process")
    parser.add_argument("--checkpoint-period", type=float, default=5.0, help="the node's checkpoint_period")
    parser.add_argument("--respawn-delay", type=float, default=1.0, help="gausem-launch --respawn-delay")
    add_launch_arguments(parser, "chaos_synthetic_loop_160x120")
    args, ros_args = parse_launch_arguments(parser, sys.argv[1:])
    log_path = log_file(args.name)
    with tempfile.TemporaryDirectory() as tmp:
        bag = source_bag(args.source, args.size, tmp)
        run = chaos(args, bag, ros_args, log_path, Path(tmp))
    text = log_path.read_text(errors="replace")
    summary = summarise(run, scan_log(text), text.count(f"{TRACKING_NODE} restarted ("), args.kills)
    title = (f"Chaos: {args.kills} kills of {TRACKING_NODE} under gausem-launch --respawn, "
             f"{results.label(args.source)}, {args.size}")
    doc = {"source": args.source, "size": args.size, "rate": args.rate, "seed": args.seed, "params_file":
           str(args.params), "nodes": args.nodes, "device": args.device, "ros_args": ros_args,
           "checkpoint_period_s": args.checkpoint_period, "respawn_delay_s": args.respawn_delay,
           "wait_s": [args.min_wait, args.max_wait], "summary": summary, **run}
    results.write_report(results.RESULTS / args.name, title=title, what=WHAT,
                         markdown=f"*{TRACKING_NODE}*\n\n" + results.markdown_table(kill_table(run["kills"])),
                         notes=notes(run, summary),
                         data=doc)
    print("\n".join(notes(run, summary)) + f"\nlog: {log_path}")
    return 0 if summary["passed"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
