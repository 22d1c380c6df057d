"""Save a SLAM session to a folder and load it to go on (a restarted tracker keeps its map).

The entry points are ``GauSemSLAM.save`` and ``GauSemSLAM.load``. Each part exports and restores its own state
(``state_dict`` / ``load_state_dict``); this module composes them and places their tensors in files, writing none
of their fields. The folder (format ``gausem-session``, version :data:`VERSION`) is self-contained:

- ``session.json``: format and version, the configuration (dotted ROS parameter names), ``num_classes``,
  ``detect_loops`` and the state tree: ``submaps``, each one's :meth:`~gausem_core.slam.submap.Submap.state_dict`
  (id, anchor, whether it starts a tracking segment, keyframes with poses, cameras and timestamps, allocation
  extent), and beside it the keys of the back end's :meth:`~gausem_core.slam.back_end.BackEnd.state_dict` (frame
  records, the vignetting estimate, the mapper's random generator, the loop closure's state) and of the front end's
  :meth:`~gausem_core.slam.front_end.FrontEnd.state_dict` (the tracker's motion segment, whether the system is lost,
  the frames dropped and skipped since the last recorded one, the health monitor's histories, the feature start's
  last good frame). Every tensor in the tree is a reference ``{"$tensor": "FILE:KEY"}`` into one of the tensor
  files. Written last: a folder without it holds no (complete) session. Sessions written before the tracking-loss
  fields existed load as never lost, with empty health histories.
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

import json
import os
import secrets
from pathlib import Path

import torch

from gausem_core.config import RENAMED, SlamConfig, flatten, from_flat
from gausem_core.slam.back_end import BackEnd
from gausem_core.slam.front_end import FrontEnd
from gausem_core.slam.submap import Submap
from gausem_core.slam.submap_store import SubmapStore

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
def _files(tree) -> set[str]:
    """The tensor files a tree's references name."""
    if isinstance(tree, dict):
        if set(tree) == {"$tensor"}:
            return {tree["$tensor"].rpartition(":")[0]}
        return set().union(*map(_files, tree.values()))
    if isinstance(tree, list):
        return set().union(*map(_files, tree))
    return set()


def _submap_tree(state: dict, writer: _TensorWriter) -> dict:
    """A submap's :meth:`~gausem_core.slam.submap.Submap.state_dict` packed: its Gaussians and keyframe images into a
    file of its own, the rest into the small tensors' file."""
    file = f"submap_{state['id']:04d}"
    keyframes = [{**kf, "images": writer.pack(kf["images"], file)} for kf in state["keyframes"]]
    return writer.pack({**state, "cloud": writer.pack(state["cloud"], file), "keyframes": keyframes}, STATE)


def _state_tree(front: FrontEnd, back: BackEnd, writer: _TensorWriter) -> dict:
    """The session's state: the submaps', the back end's and the front end's state dicts (the latter two's keys
    side by side)."""
    return {"submaps": [_submap_tree(submap.state_dict(), writer) for submap in back.submaps],
            **writer.pack({**back.state_dict(), **front.state_dict()}, STATE)}


def save_session(folder: str | Path, front: FrontEnd, back: BackEnd) -> Path:
    """Write a system's whole state, its ``front`` and ``back`` end's, into ``folder`` (created; an earlier save there
    is replaced, crash-safe: see the module doc). Returns the path of ``session.json``, written last."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    writer = _TensorWriter(secrets.token_hex(4))
    document = {"format": FORMAT, "version": VERSION, "config": flatten(back.cfg), "num_classes": back.num_classes,
                "detect_loops": back.detect_loops, "state": _state_tree(front, back, writer)}
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


def saved_config(document: dict) -> SlamConfig:
    """The configuration a session was saved with (older sessions' parameter names read under their new ones)."""
    return from_flat({RENAMED.get(name, name): value for name, value in document["config"].items()})


def _submap(tree: dict, reader: _TensorReader, device: torch.device, store: SubmapStore) -> Submap:
    """One submap, its tensors on ``device`` when active, else offloaded to ``store``; its file is read and forgotten
    (one submap's file in memory at a time)."""
    submap = Submap.from_state(reader.unpack(tree), device, store)
    reader.forget(tree)
    return submap


def restore_session(folder: str | Path, document: dict, front: FrontEnd, back: BackEnd) -> None:
    """Restore the session of ``folder``, whose :func:`read_document` is ``document``, onto a new system's ``front``
    and ``back`` end (built with the document's configuration, unless the caller chose another, ``num_classes`` and
    ``detect_loops``)."""
    reader = _TensorReader(Path(folder))
    tree = document["state"]
    submaps = [_submap(submap, reader, back.device, back.store) for submap in tree["submaps"]]
    state = reader.unpack({key: value for key, value in tree.items() if key != "submaps"})
    back.load_state_dict(state, submaps)
    front.load_state_dict(state)
