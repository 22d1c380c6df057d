"""Submaps (paper §III-A) and the records of processed frames that hang off their keyframes.

Each submap has its own frame, anchored at its first keyframe (``anchor`` = world-from-submap; the first keyframe sits
at the identity and is never moved by bundle adjustment). Frames are stored relative to a reference keyframe of their
submap, so corrections of anchors or keyframe poses (loop closure, pose graph) carry every frame along. Memory: only
the active submap (Gaussians and keyframe images) lives on the compute device; a closed submap's tensors go to a
:class:`~gausem_core.slam.submap_store.SubmapStore` and come back on demand, its anchor and keyframe poses at hand.
"""
from __future__ import annotations

import threading
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass

import torch

from gausem_core.gaussians import GaussianCloud
from gausem_core.geometry import PinholeCamera
from gausem_core.slam.allocation import SubmapExtent
from gausem_core.slam.mapper import Keyframe
from gausem_core.slam.observation import Observation
from gausem_core.slam.submap_store import SubmapStore

KEYFRAME_IMAGES = ("rgb", "depth", "semantic", "labels")  # a keyframe observation's images, as stored


@dataclass
class StoredObservation:
    """A closed submap's keyframe observation: camera and timestamp at hand, the images in the store."""

    store: SubmapStore
    key: tuple
    camera: PinholeCamera
    timestamp: float

    def load(self, device: torch.device | str = "cpu") -> Observation:
        """The observation, its images read back (bit-identical) onto ``device``."""
        return Observation(**self.store.load(self.key, device), camera=self.camera, timestamp=self.timestamp)


class Submap:
    """Gaussians and keyframes in a local frame anchored at the first keyframe; ``anchor`` is world-from-submap.

    While active, the Gaussians and the keyframes' ``obs`` are tensors on the compute device. After :meth:`offload`
    (inactive) they live in a :class:`SubmapStore`: ``cloud`` reads a CPU copy back (assigning it writes the store)
    and each keyframe's ``obs`` is a :class:`StoredObservation`. Anchor and keyframe poses always stay in memory.

    Two threads change an active submap's Gaussians (``worker.mode: async``). The tracker only adds: a keyframe's new
    Gaussians (:meth:`grow`) wait in a pending cloud, part of the map at once. The mapping worker owns the rest: it
    takes the pending ones in with :meth:`take_cloud` before it optimises, and assigns ``cloud`` after; Gaussians
    grown meanwhile stay pending, so neither thread's work is lost. Readers (``cloud``, :meth:`load_cloud`) see both.
    ``version`` counts the changes of the Gaussians (a reader may keep what it derived from a version).
    """

    def __init__(self, submap_id: int, anchor: torch.Tensor, cloud: GaussianCloud,
                 keyframes: list[Keyframe] | None = None, extent: SubmapExtent | None = None,
                 starts_segment: bool = False):
        self.submap_id = submap_id
        self.anchor = anchor
        self.starts_segment = starts_segment  # opened after the tracker lost the map for good: no odometry joins it
        # to the previous submap, and its anchor is a guess until a loop merges its segment with the others
        self.keyframes = list(keyframes or [])
        self.extent = extent  # what allocation needs while the submap is active
        self._cloud: GaussianCloud | None = cloud
        self._pending: GaussianCloud | None = None  # grown by the tracker, not yet taken in by the mapping worker
        self._whole: GaussianCloud | None = cloud  # both, as readers get them (made once per change)
        self._growth = threading.Lock()  # guards the swaps of _cloud, _pending and _whole (never held while mapping)
        self._store: SubmapStore | None = None
        self.num_gaussians = len(cloud)
        self.version = 0

    @property
    def is_active(self) -> bool:
        """Whether the tensors are resident (not offloaded to a store)."""
        return self._store is None

    @property
    def cloud(self) -> GaussianCloud:
        """The Gaussians in the submap frame, pending ones included (for an inactive submap: a copy read from the
        store)."""
        return self.load_cloud()

    @cloud.setter
    def cloud(self, cloud: GaussianCloud) -> None:
        """The mapping worker's Gaussians replaced (those grown since its :meth:`take_cloud` stay pending)."""
        with self._growth:
            if self._store is None:
                self._cloud = cloud
                self._whole = None
            else:
                self._store.store(self._cloud_key, cloud.tensors())
            self.num_gaussians = len(cloud) + (len(self._pending) if self._pending is not None else 0)
            self.version += 1

    def take_cloud(self, device: torch.device | str | None = None) -> GaussianCloud:
        """The mapping worker's Gaussians with the pending ones taken in: what it optimises and then assigns back to
        :attr:`cloud`."""
        with self._growth:
            if self._store is None:
                self._cloud, self._pending = self._merged(), None
        return self.load_cloud(device)

    def grow(self, new_gaussians: Callable[[GaussianCloud], GaussianCloud]) -> int:
        """Add ``new_gaussians(current Gaussians)`` to the map as pending (the tracker's keyframes, before any
        optimisation); how many were added (none to an inactive submap)."""
        added = new_gaussians(self.load_cloud())
        with self._growth:
            if self._store is not None or len(added) == 0:
                return 0
            self._pending = added if self._pending is None else GaussianCloud.cat([self._pending, added])
            self._whole = None
            self.num_gaussians += len(added)
            self.version += 1
        return len(added)

    def load_cloud(self, device: torch.device | str | None = None) -> GaussianCloud:
        """The Gaussians on ``device`` (default: where they are; the CPU for an inactive submap). An inactive
        submap's come back as a bit-identical copy (read from its store, where nothing moves: ``SubmapStore.read``);
        an active submap's are its own tensors (moved if asked)."""
        with self._growth:
            whole = self._merged() if self._store is None else None
        if whole is not None:
            return whole if device is None else whole.to(device)
        return GaussianCloud(**self._store.read(self._cloud_key, device or "cpu"))

    def _merged(self) -> GaussianCloud:
        """An active submap's Gaussians and the pending ones, as one cloud (made once per change); under _growth."""
        if self._whole is None:
            self._whole = self._cloud if self._pending is None else GaussianCloud.cat([self._cloud, self._pending])
        return self._whole

    def observation(self, keyframe: Keyframe, device: torch.device | str = "cpu") -> Observation:
        """One of the keyframes' observation: an active submap's own, an inactive one's read back onto ``device``."""
        obs = keyframe.obs
        return obs.load(device) if isinstance(obs, StoredObservation) else obs

    def world_pose(self, keyframe: Keyframe) -> torch.Tensor:
        """World-from-camera of one of this submap's keyframes."""
        return self.anchor @ keyframe.cam_to_world

    def offload(self, store: SubmapStore) -> None:
        """Move the Gaussians (pending ones included) and the keyframe images into ``store``; the submap becomes
        inactive."""
        if self._store is not None:
            raise ValueError(f"submap {self.submap_id} is already offloaded")
        with self._growth:
            store.store(self._cloud_key, self._merged().tensors())
            self._cloud = self._pending = self._whole = None
            self._store = store
        for kf in self.keyframes:
            key = ("keyframe", self.submap_id, kf.frame_id)
            store.store(key, {name: getattr(kf.obs, name) for name in KEYFRAME_IMAGES})
            kf.obs = StoredObservation(store, key, kf.obs.camera, kf.obs.timestamp)

    @property
    def _cloud_key(self) -> tuple:
        return ("cloud", self.submap_id)

    def state_dict(self) -> dict:
        """The submap as plain values and tensors (an inactive one's read back from its store): id, whether active,
        anchor, whether it starts a segment, allocation extent, Gaussians and keyframes (pose, camera, timestamp, images); :meth:`from_state`
        rebuilds it."""
        keyframes = []
        for kf in self.keyframes:
            obs = self.observation(kf)
            keyframes.append({"frame_id": kf.frame_id, "fixed": kf.fixed, "timestamp": obs.timestamp,
                              "camera": asdict(obs.camera), "cam_to_world": kf.cam_to_world,
                              "images": {name: getattr(obs, name) for name in KEYFRAME_IMAGES}})
        extent = None if self.extent is None else self.extent.state_dict()
        return {"id": self.submap_id, "active": self.is_active, "anchor": self.anchor,
                "starts_segment": self.starts_segment, "extent": extent, "cloud": self.load_cloud().tensors(), "keyframes": keyframes}

    @classmethod
    def from_state(cls, state: dict, device: torch.device | str, store: SubmapStore) -> "Submap":
        """The submap of a :meth:`state_dict`, its poses on ``device``; its Gaussians and images too when it was
        active, else offloaded to ``store``."""
        place = device if state["active"] else "cpu"
        keyframes = [Keyframe(kf["frame_id"], Observation(**{name: t.to(place) for name, t in kf["images"].items()},
                                                          camera=PinholeCamera(**kf["camera"]),
                                                          timestamp=kf["timestamp"]),
                              kf["cam_to_world"].to(device), kf["fixed"]) for kf in state["keyframes"]]
        extent = None if state["extent"] is None else SubmapExtent.from_state(state["extent"], device)
        submap = cls(state["id"], state["anchor"].to(device), GaussianCloud(**state["cloud"]).to(place), keyframes,
                     extent, state.get("starts_segment", False))
        if not state["active"]:
            submap.offload(store)
        return submap


@dataclass
class FrameRecord:
    """A processed frame, stored relative to its reference keyframe so map corrections carry it along."""

    frame_id: int
    timestamp: float
    submap: Submap
    reference: Keyframe
    relative: torch.Tensor  # reference-keyframe-from-camera
    lost: bool = False  # tracking was judged lost: the pose is kept for the record, nothing else uses it
    skipped: int = 0  # camera frames missed just before this one (skipped by the caller, or dropped)

    @property
    def cam_to_world(self) -> torch.Tensor:
        return self.submap.anchor @ self.reference.cam_to_world @ self.relative

    def state_dict(self) -> dict:
        """The record as plain values and a tensor, its submap and reference keyframe by id."""
        return {"frame_id": self.frame_id, "timestamp": self.timestamp, "submap": self.submap.submap_id,
                "reference": self.reference.frame_id, "relative": self.relative, "lost": self.lost,
                "skipped": self.skipped}

    @classmethod
    def from_state(cls, state: dict, submaps: Mapping[int, Submap], device: torch.device | str) -> "FrameRecord":
        """The record of a :meth:`state_dict` in the submap it names among ``submaps`` (by id); a record saved before
        tracking loss was judged is not lost."""
        submap = submaps[state["submap"]]
        reference = next(kf for kf in submap.keyframes if kf.frame_id == state["reference"])
        return cls(state["frame_id"], state["timestamp"], submap, reference, state["relative"].to(device),
                   state.get("lost", False), state.get("skipped", 0))
