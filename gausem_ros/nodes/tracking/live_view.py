"""A live 3D view (``gausem_core.viewer``, needs rerun-sdk): ``viewer`` ``record`` logs every processed frame, the
trajectory, the loops and the map to a Rerun recording (``viewer_path``, default ``output_dir/gausem.rrd``), ``web``
also serves it to a browser on ``viewer_port`` (the URL is logged), ``native`` opens the desktop viewer; ``off`` (the
default) imports nothing. ``viewer_colors``: the map's points by ``rgb`` or ``class``; ``viewer_map_every``: the map
every this many frames."""
from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import torch

from gausem_core.slam.observation import Observation
from gausem_core.slam.system import FrameResult, GauSemSLAM

from ..common import class_table


class LiveView:
    """The ``viewer`` parameter's :class:`~gausem_core.viewer.Viewer` (ValueError naming the parameter when it cannot
    be opened); with ``off`` nothing is imported and every call does nothing."""

    def __init__(self, logger, params: SimpleNamespace, palette: torch.Tensor):
        self._viewer = None
        p = params
        if p.viewer == "off":
            return
        from gausem_core.viewer import RECORDING, Viewer

        try:
            self._viewer = Viewer(p.viewer_path or Path(p.output_dir) / RECORDING, palette,
                                  class_table(p.classes).names if p.use_labels else None, p.viewer, p.viewer_colors,
                                  p.viewer_map_every, web_port=p.viewer_port)
        except (ImportError, ValueError) as err:
            raise ValueError(f"tracking_mapping: viewer {p.viewer!r}: {err}") from err
        url = self._viewer.url
        logger.info(f"viewer: recording to {self._viewer.path}" + (f", web viewer at {url}" if url else ""))

    def frame(self, obs: Observation, result: FrameResult, slam: GauSemSLAM) -> None:
        if self._viewer is not None:
            self._viewer.frame(obs, result, slam)

    def finish(self, slam: GauSemSLAM) -> None:
        if self._viewer is not None:
            self._viewer.finish(slam)

    def close(self) -> None:
        if self._viewer is not None:
            self._viewer.close()
