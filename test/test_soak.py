"""The soak benchmark's parts and the launch helpers it shares (``gausem_bench.launch``): the input accounting read
from diagnostics values, the RSS growth window, the log scan and the shutdown that leaves no process behind."""
import subprocess
import time

import pytest

pytest.importorskip("rclpy")

from gausem_bench.launch import adds_up, counts, scan_log, stop  # noqa: E402
from soak import rss_growth  # noqa: E402


def test_the_accounting_adds_every_drop_reason():
    values = {"frames_in": "10", "frames_processed": "4", "dropped.superseded": "3", "dropped.unmatched": "2",
              "rejected.bad_camera_info": "5", "frames_pending": "1", "tracking.status": "ok"}
    assert counts(values) == {"frames_in": 10, "frames_processed": 4, "dropped": 5, "frames_pending": 1}
    assert adds_up(counts(values)) and not adds_up(counts({**values, "frames_in": "11"}))


def test_the_rss_growth_is_taken_over_the_last_20_minutes():
    samples = [{"t_s": 60.0 * m, "processes": {"tracking_mapping": {"rss_mb": rss}}}
               for m, rss in [(1, 500.0), (10, 900.0), (11, 1000.0), (20, 1200.0), (31, 1100.0)]]
    assert rss_growth(samples) == {"from_s": 660.0, "to_s": 1860.0, "from_mb": 1000.0, "to_mb": 1100.0,
                                   "peak_mb": 1200.0, "growth_pct": 10.0}
    assert rss_growth(samples[:1]) is None


def test_the_log_scan_finds_exceptions_errors_and_dead_nodes():
    log = ("[INFO] [1.0] [tracking_mapping]: started\nTraceback (most recent call last):\n  File \"x.py\", line 1\n"
           "    boom()\nRuntimeError: boom\n[ERROR] [2.0] [player]: bad\n"
           "[gausem-launch] tracking_mapping ended with signal SIGKILL (exit code 137); the other nodes go on\n")
    found = scan_log(log)
    assert found["exceptions"] == ["RuntimeError: boom"] and found["errors"] == ["[ERROR] [2.0] [player]: bad"]
    assert found["launcher"] == [log.splitlines()[-1]]


def test_the_shutdown_kills_what_ignores_sigint():
    launcher = subprocess.Popen(["bash", "-c", "trap '' INT; sleep 60 & sleep 60; wait"], start_new_session=True)
    time.sleep(0.5)
    left = stop(launcher, 0.5)
    assert len(left) == 3 and launcher.returncode == -9, left
