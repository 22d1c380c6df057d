"""``open_dataset("kind[:argument]", **options)``: one string names any dataset (CLI, params files, players)."""
from __future__ import annotations

from gausem_core.data.frame import Dataset
from gausem_core.data.replica import ReplicaDataset
from gausem_core.data.scannet import ScanNetDataset
from gausem_core.data.synthetic import SyntheticDataset, sequence_names
from gausem_core.data.tum import TumDataset

_FOLDER_READERS = {"tum": TumDataset, "scannet": ScanNetDataset, "replica": ReplicaDataset}
SPEC_HELP = ("'synthetic' or 'synthetic:SEQUENCE' (" + ", ".join(sequence_names()) + "), 'tum:PATH', 'scannet:PATH', "
             "'replica:PATH'")


def open_dataset(spec: str, **options) -> Dataset:
    """Open the dataset a spec names; ``options`` go to the reader (e.g. size=(w, h), stride, max_frames)."""
    kind, _, argument = spec.partition(":")
    if kind == "synthetic":
        return SyntheticDataset(argument or "default", **options)
    if kind not in _FOLDER_READERS:
        raise ValueError(f"unknown dataset kind {kind!r} in {spec!r}; expected {SPEC_HELP}")
    if not argument:
        raise ValueError(f"dataset spec {spec!r} lacks a folder; expected '{kind}:PATH'")
    return _FOLDER_READERS[kind](argument, **options)
