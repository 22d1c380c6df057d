"""``gausem run --viewer web`` in a real browser: headless Chromium (WebGL on SwiftShader) opens the page the run
serves, and its screenshot shows the map (in the synthetic scene's class colours) and the trajectory (magenta) in the
3D view, where the same viewer without a recording shows neither; Ctrl-C then ends the run."""
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from gausem_core.data import SYNTHETIC_CLASSES
from gausem_core.viewer import TRAJECTORY_COLOR, free_port
from headless_browser import headless_page
from test_viewer import FAST

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
REPO = Path(__file__).resolve().parents[1]
POLLS = 30  # screenshots, one a second, until the viewer has drawn the recording

pytestmark = [pytest.mark.slow, pytest.mark.skipif(CHROMIUM is None, reason="needs Chromium for the headless-browser "
                                                   "check (Debian: apt-get install chromium)")]


def colour_pixels(png: bytes) -> tuple[int, int]:
    """(trajectory pixels, map pixels) in the 3D view of a 1280-wide screenshot: the left three quarters, below the
    top bar and above the time line (the blueprint's 3:1 split; the images' views are on the right)."""
    image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)[:, :, ::-1].astype(int)
    height, width, _ = image.shape
    view = image[40:height - 40, :int(width * 0.74)]
    trajectory = np.abs(view - TRAJECTORY_COLOR).max(-1) < 40
    classes = np.array([c for c in SYNTHETIC_CLASSES.colors.astype(int) if len(set(c)) > 1])  # greys: the grid's too
    shaded = np.abs(view[:, :, None] - classes).max(-1).min(-1) < 25  # the points are shaded spheres
    return int(trajectory.sum()), int(shaded.sum())


def test_the_web_viewer_shows_the_map_and_the_trajectory_in_headless_chromium(tmp_path):
    pytest.importorskip("rerun")
    port = free_port()
    run = subprocess.Popen([sys.executable, "-u", "-m", "gausem_core.cli", "run", "--dataset", "synthetic", "--frames",
                            "8", *FAST, "--viewer", "web", "--viewer-colors", "class", "--viewer-port", str(port),
                            "--out", str(tmp_path)], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                           text=True)
    try:
        output = []
        for line in run.stdout:  # until the run has finished and serves its recording
            output.append(line)
            if "until Ctrl-C" in line:
                break
        assert "until Ctrl-C" in output[-1], "".join(output)
        url = output[-1].split(" at ")[-1].split()[0]
        with headless_page(CHROMIUM, free_port()) as page:
            page.open(url)
            for _ in range(POLLS):
                shot = page.screenshot()
                trajectory, map_pixels = colour_pixels(shot)
                if trajectory > 30 and map_pixels > 2000:
                    break
                page.call("Runtime.evaluate", expression="new Promise(r => setTimeout(r, 1000))", awaitPromise=True)
            (tmp_path / "viewer.png").write_bytes(shot)
            assert trajectory > 30 and map_pixels > 2000, f"screenshot {tmp_path / 'viewer.png'}"
            page.open(f"http://127.0.0.1:{port}/")  # the same viewer without a recording
            for _ in range(POLLS):
                page.call("Runtime.evaluate", expression="new Promise(r => setTimeout(r, 1000))", awaitPromise=True)
                blank = page.screenshot()
                if cv2.imdecode(np.frombuffer(blank, np.uint8), cv2.IMREAD_GRAYSCALE).mean() > 128:
                    break  # the viewer's light interface, not its dark loading screen
            (tmp_path / "blank.png").write_bytes(blank)
            assert max(np.array(colour_pixels(blank)) / (trajectory, map_pixels)) < 0.1
        run.send_signal(signal.SIGINT)
        assert run.wait(timeout=120) == 0
        assert (tmp_path / "gausem.rrd").stat().st_size > 0
    finally:
        if run.poll() is None:
            run.kill()
            run.wait()
