"""Runs a Python module with its threads' stacks sampled, to see where a node's time goes and who holds the
interpreter lock.

About every ``--interval`` s (at most once per switch interval while other threads run Python) a sampler thread
records, for each other thread, its innermost frame and the innermost frame in GauSem's code. A thread is only
sampled when the sampler holds the lock, so a thread seen running Python at many samples held it then; one seen in a
C call (an rcl wait, a torch op) had released it. At the end (also when the module ends its process with
``os._exit``, as GauSem's commands do) it prints each thread's most frequent places and the CPU seconds of every
thread of the process (Python's threads by name, the rest by kernel name: torch's and DDS's).

    .venv/bin/python benchmarks/stack_sampler.py [--interval 0.01] [--switch-interval S] [--top 12]
        -m gausem_ros.nodes.tracking_mapping --ros-args --params-file params/synthetic.yaml
"""
from __future__ import annotations

import argparse
import collections
import os
import runpy
import sys
import threading
import time
import traceback

OURS = ("/gausem_core/", "/gausem_ros/")


def place(frame) -> str:
    """A frame's innermost function (file:line), and the innermost one in GauSem's code when that is another."""
    stack = traceback.extract_stack(frame)
    top = stack[-1]
    where = f"{top.name} ({os.path.basename(top.filename)}:{top.lineno})"
    ours = [f for f in stack if any(part in f.filename for part in OURS)]
    if ours and ours[-1] is not top:
        where += f" <- {ours[-1].name} ({os.path.basename(ours[-1].filename)}:{ours[-1].lineno})"
    return where


class StackSampler:
    """Counts where every other thread is, every ``interval`` s, on a daemon thread; :meth:`report` prints it."""

    def __init__(self, interval: float, top: int):
        self.interval, self.top = interval, top
        self._start = time.monotonic()
        self.counts: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
        self.samples = 0
        self.cpu: dict[str, float] = {}  # thread -> CPU seconds, read every second (threads that end keep theirs)
        self._stop = threading.Event()
        self._reported = False
        self._thread = threading.Thread(target=self._run, name="stack-sampler", daemon=True)

    def start(self) -> None:
        self._start = time.monotonic()
        self._thread.start()

    def _run(self) -> None:
        me, cpu_read = threading.get_ident(), time.monotonic()
        while not self._stop.wait(self.interval):
            names = {t.ident: t.name for t in threading.enumerate()}
            for ident, frame in sys._current_frames().items():
                if ident != me:
                    self.counts[names.get(ident, str(ident))][place(frame)] += 1
            self.samples += 1
            if time.monotonic() - cpu_read >= 1.0:
                self.cpu.update(thread_cpu_seconds())
                cpu_read = time.monotonic()

    def report(self) -> None:
        if self._reported:
            return
        self._reported = True
        self._stop.set()
        if threading.current_thread() is not self._thread:
            self._thread.join(timeout=1.0)  # no sample half-counted while printing
        out = sys.__stderr__
        print(f"\n[stack-sampler] {self.samples} samples in {time.monotonic() - self._start:.1f} s", file=out)
        for name, counter in list(self.counts.items()):
            print(f"[stack-sampler] thread {name}: {sum(counter.values())} samples", file=out)
            for where, n in counter.most_common(self.top):
                print(f"  {n:6d}  {where}", file=out)
        self.cpu.update(thread_cpu_seconds())
        for name, seconds in sorted(self.cpu.items(), key=lambda item: -item[1]):
            if seconds >= 0.01:
                print(f"[stack-sampler] cpu {seconds:8.2f} s  {name}", file=out)
        out.flush()


def thread_cpu_seconds() -> dict[str, float]:
    """User + system CPU seconds of every live thread of this process, by name (and kernel thread id)."""
    python_names = {t.native_id: t.name for t in threading.enumerate()}
    tick = os.sysconf("SC_CLK_TCK")
    rows = {}
    for tid in os.listdir("/proc/self/task"):
        try:
            stat = open(f"/proc/self/task/{tid}/stat").read()
        except OSError:
            continue
        kernel_name = stat[stat.index("(") + 1:stat.rindex(")")]
        fields = stat[stat.rindex(")") + 2:].split()
        name = f"{python_names.get(int(tid), kernel_name)} [{tid}]"
        rows[name] = (int(fields[11]) + int(fields[12])) / tick
    return rows


def main() -> None:
    argv = sys.argv[1:]
    if "-m" not in argv:
        raise SystemExit("usage: stack_sampler.py [options] -m MODULE [ARGS...]")
    split = argv.index("-m")
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--interval", type=float, default=0.01, help="seconds between samples")
    parser.add_argument("--switch-interval", type=float, help="sys.setswitchinterval for the run (default 0.005)")
    parser.add_argument("--top", type=int, default=12, help="places listed per thread")
    args = parser.parse_args(argv[:split])
    module, sys.argv = argv[split + 1], [argv[split + 1], *argv[split + 2:]]
    if args.switch_interval:
        sys.setswitchinterval(args.switch_interval)
    sampler = StackSampler(args.interval, args.top)
    real_exit = os._exit

    def exit_with_report(code: int) -> None:
        sampler.report()
        real_exit(code)

    os._exit = exit_with_report
    sampler.start()
    try:
        runpy.run_module(module, run_name="__main__", alter_sys=True)
    finally:
        sampler.report()


if __name__ == "__main__":
    main()
