"""A live 3D view of a run in the Rerun viewer, with a recording (``.rrd``) saved for later viewing.

Optional: ``pip install rerun-sdk`` (or the ``gausem[viewer]`` extra); imported only when a :class:`Viewer` is made, so
a run without one neither imports nor does anything for it. ``gausem run --viewer`` and the tracking node's ``viewer``
parameter make one and hand it each frame.

Why Rerun and not Foxglove's SDK (both on the package index): rerun-sdk ships its viewers, the web one served from
this process (works offline, no account) and the native one, and ``rerun FILE.rrd`` reopens a recording; Foxglove's
viewer is a hosted web app (internet, an account) or a separate desktop download.

Entities (timelines ``frame``, the system's frame id, and ``time``, the frames' stamps in seconds):

- ``world``: the camera's axes convention (right, down, forward) and the class table (names and colours);
- ``world/camera``: the camera pose (camera to world); ``world/camera/image``: its pinhole (the frustum);
  ``.../image/rgb`` the input image (JPEG); ``.../image/semantic`` the class ids (coloured by the class table);
- ``world/trajectory``: the frames' positions so far, lost ones left out (a line strip);
- ``world/loops``: accepted loop closures, a segment between the two keyframes' positions;
- ``world/map``: the Gaussians' means (radius: the Gaussian's; colour: its RGB or its class), at most ``max_points``.

The map, the trajectory and the loops are read from the system again at the first frame, every ``map_every``-th one,
after a loop correction and at the end, so that corrections show; between those the trajectory grows by one
position a frame.
"""
from __future__ import annotations

import os
import socket
import sys
import warnings
from pathlib import Path
from urllib.parse import quote

import numpy as np

MODES = ("record", "web", "native")  # record: the .rrd only; web: also served to a browser; native: the desktop app
COLORINGS = ("rgb", "class")
RECORDING = "gausem.rrd"  # the recording's name in a run's output folder
INSTALL_HINT = "pip install rerun-sdk (or the gausem[viewer] extra)"
TRAJECTORY_COLOR = (255, 0, 255)
LOOP_COLOR = (0, 255, 255)
IMAGE_PLANE_M = 0.2  # the frustum's depth in the 3D view


def import_rerun():
    """The ``rerun`` module, or ImportError saying how to install it."""
    try:
        import rerun
    except ImportError as err:
        raise ImportError(f"the viewer needs rerun-sdk: {INSTALL_HINT}") from err
    return rerun


def to_uint8(colors) -> np.ndarray:
    """Colours in [0, 1] (a tensor, any device) as uint8 in 0..255."""
    return (np.clip(colors.detach().float().cpu().numpy(), 0, 1) * 255).round().astype(np.uint8)


def free_port() -> int:
    """A TCP port free on this machine now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Viewer:
    """Logs a run to a Rerun recording at ``path`` and, by ``mode``, to a web viewer served on ``web_port`` (:attr:`url`)
    or a spawned native viewer. ``palette`` (C, 3) in [0, 1] and ``names``: the class table. Call :meth:`frame` after
    each processed frame, :meth:`finish` after the system's ``finish``, then :meth:`close`.

    The web page and its data server listen on every interface (Rerun's default); from another machine, open
    :attr:`url` with this machine's address in place of both ``127.0.0.1``."""

    def __init__(self, path: str | Path, palette, names: tuple[str, ...] | None = None,
                 mode: str = "record", colors: str = "rgb", map_every: int = 10, max_points: int = 100_000,
                 web_port: int = 9090):
        if mode not in MODES or colors not in COLORINGS:
            raise ValueError(f"viewer: mode must be one of {MODES} and colors one of {COLORINGS}, got {mode!r}, "
                             f"{colors!r}")
        if map_every < 1 or max_points < 1:
            raise ValueError(f"viewer: map_every and max_points must be >= 1, got {map_every}, {max_points}")
        if mode == "native" and sys.platform == "linux" and not (os.environ.get("DISPLAY")
                                                                  or os.environ.get("WAYLAND_DISPLAY")):
            raise ValueError("viewer: native needs a display (DISPLAY and WAYLAND_DISPLAY are unset); use web and "
                             "open the page it names, or record and open the recording with `rerun FILE.rrd`")
        self.rr = rr = import_rerun()
        self.path, self.colors = Path(path), colors
        self.map_every, self.max_points = map_every, max_points
        self.palette = palette  # (C, 3) tensor
        self.url: str | None = None
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.rec = rr.RecordingStream("gausem", make_default=False)
        sinks = [rr.FileSink(str(self.path))]
        if mode != "record":
            port = free_port()
            grpc = f"rerun+http://127.0.0.1:{port}/proxy"
            if mode == "native":
                rr.spawn(port=port, connect=False)  # returns once the viewer listens
            sinks.append(rr.GrpcServerSink(port=port) if mode == "web" else rr.GrpcSink(grpc))
        self.rec.set_sinks(*sinks)
        if mode == "web":
            rr.serve_web_viewer(web_port=web_port, open_browser=False, connect_to=grpc)
            self.url = f"http://127.0.0.1:{web_port}/?url={quote(grpc, safe='')}"
        self.rec.send_blueprint(self._blueprint())
        names = names or tuple(f"class_{i}" for i in range(len(self.palette)))
        rgb = to_uint8(palette).tolist()
        self.rec.log("world", rr.ViewCoordinates.RDF, static=True)
        self.rec.log("world", rr.AnnotationContext([(i, n, tuple(c)) for i, (n, c) in enumerate(zip(names, rgb))]),
                     static=True)
        self._positions: list[np.ndarray] = []
        self._camera = None
        self._frames = 0
        self._frame_id = 0

    def _blueprint(self):
        """The 3D view (map, trajectory, loops, camera frustum) beside the input and semantic images."""
        import rerun.blueprint as rrb

        images = "/world/camera/image"
        return rrb.Blueprint(rrb.Horizontal(
            rrb.Spatial3DView(origin="world", name="map",
                              contents=["+ /world/**", f"- {images}/rgb", f"- {images}/semantic"]),
            rrb.Vertical(rrb.Spatial2DView(origin=images, contents="$origin/rgb", name="image"),
                         rrb.Spatial2DView(origin=images, contents="$origin/semantic", name="semantic")),
            column_shares=[3, 1]), collapse_panels=True)

    def frame(self, obs, result, slam) -> None:
        """One processed frame: its ``Observation``, its ``FrameResult`` and the system that processed it."""
        rr, rec = self.rr, self.rec
        self._frame_id = result.frame_id
        rec.set_time("frame", sequence=result.frame_id)
        rec.set_time("time", duration=obs.timestamp)
        self._log_images(obs)
        pose = result.cam_to_world.detach().cpu().double().numpy()
        dropped = result.relocalisation is not None and not result.relocalisation.accepted
        lost = result.health is not None and result.health.status == "lost"
        if not (dropped or lost) and np.isfinite(pose).all():
            rec.log("world/camera", rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]))
            self._positions.append(pose[:3, 3])
        corrected = any(e.loop is not None and e.loop.correction for e in (result.events, *result.mapped))
        if corrected or self._frames % self.map_every == 0:
            self.refresh(slam)
        else:
            self._log_trajectory()
        self._frames += 1

    def finish(self, slam) -> None:
        """After the system's ``finish``: the final trajectory, loops and map, at the last frame."""
        self.rec.set_time("frame", sequence=self._frame_id)
        self.refresh(slam)

    def refresh(self, slam) -> None:
        """Trajectory, loops and map as the system holds them now."""
        self._positions = [pose.detach().cpu().double().numpy()[:3, 3] for _, pose in slam.trajectory(False)]
        self._log_trajectory()
        self._log_loops(slam)
        self._log_map(slam.global_cloud())

    def close(self) -> None:
        """Flush and close the recording (and stop serving); a native viewer closed before is only warned of."""
        try:
            self.rec.flush()
        except RuntimeError as err:  # the gRPC sink's viewer is gone; the file sink has its data all the same
            warnings.warn(f"viewer: {err}", stacklevel=2)
        self.rec.disconnect()

    def _log_images(self, obs) -> None:
        rr, camera = self.rr, obs.camera
        if camera != self._camera:
            self._camera = camera
            self.rec.log("world/camera/image", rr.Pinhole(
                focal_length=[camera.fx, camera.fy], principal_point=[camera.cx, camera.cy], width=camera.width,
                height=camera.height, image_plane_distance=IMAGE_PLANE_M), static=True)
        self.rec.log("world/camera/image/rgb", rr.Image(to_uint8(obs.rgb)).compress(jpeg_quality=90))
        self.rec.log("world/camera/image/semantic",
                     rr.SegmentationImage(obs.labels.detach().cpu().numpy().astype(np.uint16)))

    def _log_trajectory(self) -> None:
        if len(self._positions) > 1:
            self.rec.log("world/trajectory", self.rr.LineStrips3D([np.stack(self._positions)],
                                                                  colors=[TRAJECTORY_COLOR], radii=[-2.0]))

    def _log_loops(self, slam) -> None:
        loops = slam.loop_closure.loops if slam.loop_closure is not None else []
        if loops:
            frames = slam.frames
            segments = [[frames[r.query_frame].cam_to_world.detach().cpu().double().numpy()[:3, 3],
                         frames[r.match_frame].cam_to_world.detach().cpu().double().numpy()[:3, 3]] for r in loops]
            self.rec.log("world/loops", self.rr.LineStrips3D(segments, colors=[LOOP_COLOR], radii=[-2.0]))

    def _log_map(self, cloud) -> None:
        n = len(cloud)
        if n == 0:
            return
        keep = cloud.means.new_zeros(n).bool()
        keep[np.linspace(0, n - 1, min(n, self.max_points)).round().astype(np.int64)] = True  # evenly spread
        cloud = cloud.prune(keep).to("cpu")
        class_ids = cloud.class_ids(self.palette).numpy().astype(np.uint16)
        colors = to_uint8(cloud.colors) if self.colors == "rgb" else None
        self.rec.log("world/map", self.rr.Points3D(cloud.means.numpy(), radii=cloud.radii.numpy(), colors=colors,
                                                   class_ids=class_ids))
