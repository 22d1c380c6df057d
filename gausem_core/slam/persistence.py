"""Save a SLAM session to a folder and load it to go on (a restarted tracker keeps its map).

The folder (format ``gausem-session``, version :data:`VERSION`) is self-contained:

- ``session.json``: format and version, the configuration (dotted ROS parameter names), ``num_classes``,
  ``detect_loops`` and the state tree: submaps (id, anchor, keyframes with poses, cameras and timestamps, allocation
  extent), frames (id, timestamp, submap, reference keyframe, relative pose, whether tracking was lost), the tracker's
  motion segment, whether the system is lost and how many frames it dropped since the last recorded one, the health
  monitor's histories, the vignetting estimate, the mapper's random generator and the loop closure's
  :meth:`~gausem_core.slam.loop_closure.LoopClosure.state_dict`. Every tensor in the tree is a reference
  ``{"$tensor": "FILE:KEY"}`` into one of the tensor files. Written last: a folder without it holds no (complete)
  session. Sessions written before the tracking-loss fields existed load as never lost, with empty health histories.
- ``state.TOKEN.pt``: the small tensors of the tree (poses, descriptors, ...).
- ``submap_NNNN.TOKEN.pt``: one submap's Gaussians and keyframe images (an offloaded submap's read back from its store).

Saving again into the same folder is crash-safe: each save's tensor files carry a new random ``TOKEN``, ``session.json``
is replaced atomically once they are written and flushed to the disk (``fsync``), the folder is flushed after the
rename, and only then are the previous save's files deleted. A process killed, or a machine losing power, at any point
leaves the previous session or the new one, whole (sessions written before tokens, ``state.pt`` and
``submap_NNNN.pt``, load too).

Tensor files are ``torch.save`` dicts of CPU tensors, read with ``torch.load(weights_only=True)``. Ids go on after the
saved ones (frame ids count the recorded frames, submap ids the submaps), and every value comes back bit-identical.
"""
from __future__ import annotations

import dataclasses
import json
import os
import secrets
from pathlib import Path

import torch

from gausem_core.config import RENAMED, SlamConfig, flatten, from_flat
from gausem_core.gaussians import GaussianCloud
from gausem_core.geometry import PinholeCamera
from gausem_core.slam.allocation import Frustum, FrustumUnion, SubmapExtent
from gausem_core.slam.mapper import Keyframe
from gausem_core.slam.observation import Observation
from gausem_core.slam.submap import KEYFRAME_IMAGES, FrameRecord, Submap
from gausem_core.slam.submap_store import SubmapStore
from gausem_core.slam.system import GauSemSLAM

FORMAT = "gausem-session"
VERSION = 1
SESSION_FILE = "session.json"
STATE = "state"  # the small tensors' file (its name gets the save's token)


class SessionError(ValueError):
    """A session folder that cannot be read (wrong format or version, a missing or truncated file)."""


# --- tensors in a JSON tree -----------------------------------------------------------------------------------------
class _TensorWriter:
    """Replaces the tensors of a tree by references and collects them per file."""

    def __init__(self, token: str = ""):
        self.token = token  # every file name gets it: ``NAME.TOKEN.pt``
        self.files: dict[str, dict[str, torch.Tensor]] = {}

    def pack(self, tree, name: str):
        file = f"{name}.{self.token}.pt" if self.token else f"{name}.pt"
        if isinstance(tree, torch.Tensor):
            tensors = self.files.setdefault(file, {})
            key = str(len(tensors))
            tensors[key] = tree.detach().cpu()
            return {"$tensor": f"{file}:{key}"}
        if isinstance(tree, dict):
            return {key: self.pack(value, name) for key, value in tree.items()}
        if isinstance(tree, (list, tuple)):
            return [self.pack(value, name) for value in tree]
        return tree


class _TensorReader:
    """Resolves the references of a tree, reading each tensor file once (until :meth:`forget`)."""

    def __init__(self, folder: Path):
        self.folder = folder
        self._files: dict[str, dict[str, torch.Tensor]] = {}

    def unpack(self, tree):
        if isinstance(tree, dict):
            if set(tree) == {"$tensor"}:
                return self._tensor(tree["$tensor"])
            return {key: self.unpack(value) for key, value in tree.items()}
        if isinstance(tree, list):
            return [self.unpack(value) for value in tree]
        return tree

    def forget(self, tree) -> None:
        """Drop the tensor files the references in ``tree`` name, read before (their tensors stay wherever the tree
        put them)."""
        for name in _files(tree):
            self._files.pop(name, None)

    def _tensor(self, reference: str) -> torch.Tensor:
        name, _, key = reference.rpartition(":")
        if name not in self._files:
            path = self.folder / name
            try:
                self._files[name] = torch.load(path, map_location="cpu", weights_only=True)
            except (OSError, RuntimeError, EOFError, ValueError) as err:
                raise SessionError(f"{path}: cannot read the session's tensors (missing or truncated file?): {err}") \
                    from err
        try:
            return self._files[name][key]
        except (KeyError, TypeError):
            raise SessionError(f"{self.folder / name}: no tensor {key!r} (the file does not match {SESSION_FILE})") \
                from None


# --- the system's state as a tree -----------------------------------------------------------------------------------
def _extent_tree(extent: SubmapExtent | None) -> dict | None:
    if extent is None:
        return None
    return {"first_pose": extent.first_pose, "anchor_counts": extent.anchor_counts, "num_classes": extent.num_classes,
            "frusta": [{"camera": dataclasses.asdict(f.camera), "cam_to_world": f.cam_to_world, "near": f.near,
                        "far": f.far} for f in extent.volume.frusta]}


def _files(tree) -> set[str]:
    """The tensor files a tree's references name."""
    if isinstance(tree, dict):
        if set(tree) == {"$tensor"}:
            return {tree["$tensor"].rpartition(":")[0]}
        return set().union(*map(_files, tree.values()))
    if isinstance(tree, list):
        return set().union(*map(_files, tree))
    return set()


def _submap_tree(submap: Submap, writer: _TensorWriter) -> dict:
    file = f"submap_{submap.submap_id:04d}"
    keyframes = []
    for kf in submap.keyframes:
        obs = submap.observation(kf)
        keyframes.append({"frame_id": kf.frame_id, "fixed": kf.fixed, "timestamp": obs.timestamp,
                          "camera": dataclasses.asdict(obs.camera),
                          "cam_to_world": writer.pack(kf.cam_to_world, STATE),
                          "images": writer.pack({name: getattr(obs, name) for name in KEYFRAME_IMAGES}, file)})
    return {"id": submap.submap_id, "active": submap.is_active, "anchor": writer.pack(submap.anchor, STATE),
            "extent": writer.pack(_extent_tree(submap.extent), STATE),
            "cloud": writer.pack(submap.load_cloud().tensors(), file), "keyframes": keyframes}


def _state_tree(slam: GauSemSLAM, writer: _TensorWriter) -> dict:
    frames = [{"frame_id": f.frame_id, "timestamp": f.timestamp, "submap": f.submap.submap_id,
               "reference": f.reference.frame_id, "relative": f.relative, "lost": f.lost,
               "skipped": f.skipped} for f in slam.frames]
    loop = slam.loop_closure.state_dict() if slam.loop_closure is not None else None
    front, back = slam.front_end, slam.back_end
    return {"submaps": [_submap_tree(s, writer) for s in slam.submaps],
            **writer.pack({"frames": frames, "segment_start": front.segment_start, "lost": front.lost,
                           "dropped": front.dropped, "skipped": front.skipped, "health": front.health.state_dict(),
                           "feature_start": front.feature_start.state_dict(), "vignetting": back.vignetting.state_dict(),
                           "mapper_generator": back.mapper.generator.get_state(), "loop_closure": loop}, STATE)}


def save_session(slam: GauSemSLAM, folder: str | Path) -> Path:
    """Write ``slam``'s whole state into ``folder`` (created; an earlier save there is replaced, crash-safe: see the
    module doc). Returns the path of ``session.json``, written last."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    writer = _TensorWriter(secrets.token_hex(4))
    document = {"format": FORMAT, "version": VERSION, "config": flatten(slam.cfg), "num_classes": slam.num_classes,
                "detect_loops": slam.detect_loops, "state": _state_tree(slam, writer)}
    for name, tensors in writer.files.items():
        with open(folder / name, "wb") as f:
            torch.save(tensors, f)
            _flush_to_disk(f)
    path = folder / SESSION_FILE
    partial = path.with_suffix(".json.partial")
    with open(partial, "w") as f:
        f.write(json.dumps(document))
        _flush_to_disk(f)
    os.replace(partial, path)
    _flush_folder(folder)  # the rename itself reaches the disk before the previous files go
    for stale in [*folder.glob("state*.pt"), *folder.glob("submap_*.pt")]:  # an earlier save's files
        if stale.name not in writer.files:
            stale.unlink()
    return path


def _flush_to_disk(f) -> None:
    f.flush()
    os.fsync(f.fileno())


def _flush_folder(folder: Path) -> None:
    """fsync a folder's entries (POSIX; where folders cannot be opened, e.g. Windows, the rename is all there is)."""
    try:
        handle = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(handle)
    finally:
        os.close(handle)


# --- loading --------------------------------------------------------------------------------------------------------
def read_document(folder: str | Path) -> dict:
    """The checked ``session.json`` of a session folder (:class:`SessionError` or FileNotFoundError otherwise)."""
    path = Path(folder) / SESSION_FILE
    if not path.is_file():
        raise FileNotFoundError(f"no saved session in {folder}: {path} does not exist")
    try:
        document = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise SessionError(f"{path}: not a readable session file (truncated?): {err}") from err
    if not isinstance(document, dict) or document.get("format") != FORMAT:
        raise SessionError(f"{path}: not a {FORMAT} file")
    if document.get("version") != VERSION:
        raise SessionError(f"{path}: session format version {document.get('version')!r}; this GauSem reads "
                           f"version {VERSION}")
    return document


def _extent(tree: dict | None, device: torch.device) -> SubmapExtent | None:
    if tree is None:
        return None
    frusta = [Frustum(PinholeCamera(**f["camera"]), f["cam_to_world"].to(device), f["near"], f["far"])
              for f in tree["frusta"]]
    return SubmapExtent(tree["first_pose"].to(device), tree["anchor_counts"], FrustumUnion(frusta), tree["num_classes"])


def _submap(tree: dict, reader: _TensorReader, device: torch.device, store: SubmapStore) -> Submap:
    """One submap, its tensors on ``device`` when active, else offloaded to ``store``."""
    raw, tree = tree, reader.unpack(tree)
    place = device if tree["active"] else "cpu"
    keyframes = [Keyframe(kf["frame_id"], Observation(**{n: t.to(place) for n, t in kf["images"].items()},
                                                      camera=PinholeCamera(**kf["camera"]),
                                                      timestamp=kf["timestamp"]),
                          kf["cam_to_world"].to(device), kf["fixed"]) for kf in tree["keyframes"]]
    cloud = GaussianCloud(**tree["cloud"]).to(place)
    submap = Submap(tree["id"], tree["anchor"].to(device), cloud, keyframes, _extent(tree["extent"], device))
    if not tree["active"]:
        submap.offload(store)
    reader.forget(raw)
    return submap


def load_session(folder: str | Path, cfg: SlamConfig | None = None, device: torch.device | str = "cpu",
                 relocalise: bool = True) -> GauSemSLAM:
    """The system saved in ``folder``, on ``device``, with its saved configuration unless ``cfg`` is given. With
    ``relocalise`` (default) it starts :attr:`~GauSemSLAM.lost` with a new tracking segment: its next frame is placed
    against the map by relocalisation, without the motion model, before tracking goes on; without, it goes on exactly
    as the saved system would have (lost too if that was)."""
    folder = Path(folder)
    document = read_document(folder)
    saved = {RENAMED.get(name, name): value for name, value in document["config"].items()}  # older sessions' names
    slam = GauSemSLAM(cfg or from_flat(saved), device, document["num_classes"], document["detect_loops"])
    reader = _TensorReader(folder)
    tree = document["state"]
    front, back = slam.front_end, slam.back_end
    back.submaps.extend(_submap(submap, reader, slam.device, back.store) for submap in tree["submaps"])
    state = reader.unpack({key: value for key, value in tree.items() if key != "submaps"})
    by_id = {s.submap_id: s for s in slam.submaps}
    for f in state["frames"]:
        submap = by_id[f["submap"]]
        reference = next(kf for kf in submap.keyframes if kf.frame_id == f["reference"])
        slam.frames.append(FrameRecord(f["frame_id"], f["timestamp"], submap, reference,
                                       f["relative"].to(slam.device), f.get("lost", False), f.get("skipped", 0)))
    front.segment_start = state["segment_start"]
    front.dropped = state.get("dropped", 0)
    front.skipped = state.get("skipped", 0)
    if "health" in state:
        front.health.load_state_dict(state["health"])
    front.feature_start.load_state_dict(state.get("feature_start"))
    if "vignetting" in state:
        back.vignetting.load_state_dict(state["vignetting"])
    back.mapper.generator.set_state(state["mapper_generator"])
    if slam.loop_closure is not None and state["loop_closure"] is not None:
        slam.loop_closure.load_state_dict(state["loop_closure"])
    front.lost = state.get("lost", False)
    if slam.submaps:
        submap, keyframe = max(((s, kf) for s in slam.submaps for kf in s.keyframes), key=lambda k: k[1].frame_id)
        front.keyframes.remember(keyframe.frame_id, submap.world_pose(keyframe))
    if relocalise and slam.submaps:
        front.lost, front.segment_start = True, len(slam.frames)
    return slam
