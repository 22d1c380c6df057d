"""Benchmark suites: sequences x configurations read from a small YAML file and expanded into validated runs.

A suite file (``benchmarks/suites/*.yaml``)::

    name: paper                         # results are written as slam_<name>.json / .md
    defaults: {size: 160x120}           # sequence keys applied where a sequence does not set them
    sequences:
      - {name: tum_fr1_rpy, dataset: "tum:$GAUSEM_SHARED_DATA/tum_fr1_rpy", frames: 200}
    configurations:
      - {name: gausem}                                    # method gausem, parameters from params/<kind>.yaml
      - {name: motion_submaps, overrides: {submaps.policy: motion}, note: "LoopSplat's submap rule"}
      - {name: open3d_slam, method: open3d_slam}

Sequence keys: ``name``, ``dataset`` (an :func:`~gausem_core.data.open_dataset` spec; relative paths are taken from
the working directory), ``params`` (GauSem parameter file; default ``params/<kind>.yaml``), ``size`` (WxH),
``stride``, ``frames``, ``eval_every``, ``open3d`` (parameter values for the Open3D baselines on this sequence,
e.g. its depth range) and ``color_calibration`` (for depth that is not registered to colour: the colour camera's
``intrinsics`` [fx, fy, cx, cy] at ``size`` [w, h] and an optional ``depth_to_color`` 3x4/4x4 transform; colour is
then resampled into the depth camera, :mod:`~gausem_bench.color_registration`).

Instead of ``sequences``, ``sequences_of: paper.yaml`` runs the sequences (and defaults) of another suite file beside
this one, e.g. a comparison of settings over the paper suite's sequences.

Configuration keys: ``name``, ``method`` (``gausem``, ``open3d_odometry`` or ``open3d_slam``), ``overrides``
(parameter values, dotted or nested names; GauSem's are those of :class:`~gausem_core.config.SlamConfig`, the
baselines' those of :class:`~gausem_bench.baselines.Open3DParams`) and ``note``. Every name is checked
before anything runs: an unknown key or parameter raises :class:`SuiteError`.
"""
from __future__ import annotations

import argparse
import dataclasses
import difflib
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from gausem_bench.baselines import BASELINES
from gausem_bench.data import expand
from gausem_bench.color_registration import ColorCalibration
from gausem_core.config import SlamConfig, flatten, load_config, reject_renamed
from gausem_core.options import default_params_file, parse_size

METHODS = ("gausem", *BASELINES)
SEQUENCE_KEYS = {"name", "dataset", "params", "size", "stride", "frames", "eval_every", "open3d", "color_calibration"}
CONFIGURATION_KEYS = {"name", "method", "overrides", "note"}
SUITE_KEYS = {"name", "defaults", "sequences", "configurations"}


class SuiteError(ValueError):
    """A suite, sequence, configuration or parameter name that cannot be run."""


@dataclass(frozen=True)
class SequenceSpec:
    name: str
    dataset: str
    params: str | None = None
    size: tuple[int, int] | None = None
    stride: int = 1
    frames: int | None = None
    eval_every: int = 5
    open3d: dict[str, Any] = field(default_factory=dict)
    color_calibration: dict[str, Any] | None = None  # see color_registration.ColorCalibration.from_dict


@dataclass(frozen=True)
class Configuration:
    name: str
    method: str = "gausem"
    overrides: dict[str, Any] = field(default_factory=dict)
    note: str = ""


@dataclass(frozen=True)
class Suite:
    name: str
    sequences: list[SequenceSpec]
    configurations: list[Configuration]

    def select(self, sequences: list[str] | None = None, configurations: list[str] | None = None) -> "Suite":
        """The suite restricted to the named sequences and configurations (None keeps all), in suite order."""
        return Suite(self.name, _pick(self.sequences, sequences, "sequence"),
                     _pick(self.configurations, configurations, "configuration"))


@dataclass
class Case:
    """One run: a sequence under a configuration, with every parameter it uses resolved."""

    sequence: SequenceSpec
    configuration: Configuration
    overrides: dict[str, Any]  # the values set on top of the defaults / parameter file
    parameters: dict[str, Any]  # every parameter: GauSem's flattened SlamConfig, or the baseline's Open3DParams
    params_file: str | None
    seed: int
    dataset_name: str
    frames: int
    depth_registered: bool
    out_dir: Path
    lpips_weights: str | None = None
    threads: int | None = None
    progress: bool = True

    @property
    def method(self) -> str:
        return self.configuration.method

    @property
    def label(self) -> str:
        return f"{self.sequence.name} / {self.configuration.name}"


def _pick(items: list, names: list[str] | None, kind: str) -> list:
    if names is None:
        return list(items)
    known = [item.name for item in items]
    for name in names:
        if name not in known:
            raise SuiteError(f"unknown {kind} '{name}'{_did_you_mean(name, known)}; the suite has: {', '.join(known)}")
    return [item for item in items if item.name in names]


def _did_you_mean(name: str, known) -> str:
    close = difflib.get_close_matches(name, list(known), n=1)
    return f" (did you mean '{close[0]}'?)" if close else ""


def _check_keys(given: dict, allowed: set[str], where: str) -> None:
    for key in given:
        if key not in allowed:
            raise SuiteError(f"{where}: unknown key '{key}'{_did_you_mean(key, allowed)}; "
                             f"allowed: {', '.join(sorted(allowed))}")


def flatten_names(values: dict, prefix: str = "") -> dict[str, Any]:
    """Nested ``{loop: {enabled: false}}`` and dotted ``{loop.enabled: false}`` alike -> dotted names."""
    out: dict[str, Any] = {}
    for key, value in (values or {}).items():
        name = f"{prefix}{key}"
        out.update(flatten_names(value, name + ".") if isinstance(value, dict) else {name: value})
    return out


def check_parameter_names(values: dict, known, where: str) -> None:
    """SuiteError naming the first parameter of ``values`` that is not in ``known``."""
    for name in values:
        if name not in known:
            raise SuiteError(f"{where}: unknown parameter '{name}'{_did_you_mean(name, known)}")


def suite_size(text) -> tuple[int, int] | None:
    """A sequence's ``size`` (WxH, or None): :func:`~gausem_core.options.parse_size` raising SuiteError."""
    if text is None:
        return None
    try:
        return parse_size(str(text))
    except argparse.ArgumentTypeError as exc:
        raise SuiteError(str(exc)) from None


def sequence_from_dict(entry: dict, defaults: dict | None = None) -> SequenceSpec:
    if not isinstance(entry, dict):
        raise SuiteError(f"a sequence must be a mapping, got {entry!r}")
    where = f"sequence '{entry.get('name', entry.get('dataset', '?'))}'"
    _check_keys(entry, SEQUENCE_KEYS, where)
    values = {**(defaults or {}), **entry}
    if "dataset" not in values:
        raise SuiteError(f"{where}: 'dataset' is required (e.g. synthetic:default or tum:PATH)")
    values["dataset"] = expand(values["dataset"])
    values.setdefault("name", sequence_name(values["dataset"]))
    values["size"] = suite_size(values.get("size"))
    values["open3d"] = flatten_names(values.get("open3d"))
    check_parameter_names(values["open3d"], dataclasses.asdict(BASELINES["open3d_odometry"]), f"{where}: open3d")
    if values.get("color_calibration") is not None:
        try:
            ColorCalibration.from_dict(values["color_calibration"])
        except (KeyError, TypeError, ValueError) as exc:
            raise SuiteError(f"{where}: color_calibration: {exc!r}") from None
    for key in ("stride", "eval_every", "frames"):
        if values.get(key) is not None and (not isinstance(values[key], int) or values[key] < 1):
            raise SuiteError(f"{where}: {key} must be a positive integer, got {values[key]!r}")
    return SequenceSpec(**values)


def configuration_from_dict(entry: dict) -> Configuration:
    if not isinstance(entry, dict) or "name" not in entry:
        raise SuiteError(f"a configuration must be a mapping with a 'name', got {entry!r}")
    where = f"configuration '{entry['name']}'"
    _check_keys(entry, CONFIGURATION_KEYS, where)
    method = entry.get("method", "gausem")
    if method not in METHODS:
        raise SuiteError(f"{where}: unknown method '{method}'{_did_you_mean(method, METHODS)}; "
                         f"known: {', '.join(METHODS)}")
    return Configuration(entry["name"], method, flatten_names(entry.get("overrides")), entry.get("note", ""))


def sequence_name(spec: str) -> str:
    """A short name for a dataset spec: ``synthetic_loop``, or the folder name of ``tum:PATH``."""
    kind, _, argument = spec.partition(":")
    if kind == "synthetic":
        return f"synthetic_{argument or 'default'}"
    return Path(argument).name or kind


def _unique(items: list, kind: str) -> list:
    names = [item.name for item in items]
    for name in names:
        if names.count(name) > 1:
            raise SuiteError(f"{kind} '{name}' appears more than once")
    return items


def parse_suite(document: dict, name: str) -> Suite:
    """A suite from a parsed YAML document (``name`` when the document does not set one)."""
    if not isinstance(document, dict):
        raise SuiteError(f"suite {name}: expected a mapping at the top level")
    _check_keys(document, SUITE_KEYS, f"suite {name}")
    defaults = document.get("defaults") or {}
    _check_keys(defaults, SEQUENCE_KEYS - {"name", "dataset"}, f"suite {name}: defaults")
    sequences = [sequence_from_dict(entry, defaults) for entry in document.get("sequences") or []]
    configurations = [configuration_from_dict(entry) for entry in document.get("configurations") or []]
    if not configurations:
        raise SuiteError(f"suite {name}: no configurations")
    return Suite(document.get("name", name), _unique(sequences, "sequence"), _unique(configurations, "configuration"))


def load_suite(path: str | Path) -> Suite:
    path = Path(path)
    if not path.is_file():
        raise SuiteError(f"suite file {path} does not exist")
    document = yaml.safe_load(path.read_text())
    if isinstance(document, dict) and "sequences_of" in document:
        document = _with_sequences_of(document, path)
    return parse_suite(document, path.stem)


def _with_sequences_of(document: dict, path: Path) -> dict:
    """``document`` with the sequences and defaults (its own on top) of the suite file its ``sequences_of`` names,
    beside ``path``."""
    where = f"suite {path.stem}: sequences_of"
    if "sequences" in document:
        raise SuiteError(f"{where}: give sequences or sequences_of, not both")
    source = path.parent / str(document["sequences_of"])
    if not source.is_file():
        raise SuiteError(f"{where}: suite file {source} does not exist")
    other = yaml.safe_load(source.read_text()) or {}
    rest = {key: value for key, value in document.items() if key != "sequences_of"}
    return {**rest, "sequences": other.get("sequences"),
            "defaults": {**(other.get("defaults") or {}), **(document.get("defaults") or {})}}


def _coerce(name: str, value, default, where: str):
    kind = type(default)
    if kind is bool and isinstance(value, bool):
        return value
    if kind in (int, float) and isinstance(value, (int, float)) and not isinstance(value, bool):
        if kind is int and not float(value).is_integer():
            raise SuiteError(f"{where}: parameter '{name}' must be an integer, got {value!r}")
        return kind(value)
    if kind is str and isinstance(value, str):
        return value
    raise SuiteError(f"{where}: parameter '{name}' must be of type {kind.__name__}, got {value!r}")


def gausem_parameters(sequence: SequenceSpec, configuration: Configuration,
                      extra: dict[str, Any]) -> tuple[str | None, dict[str, Any], dict[str, Any]]:
    """(parameter file, overrides, flattened SlamConfig) of a GauSem run: file < configuration < ``extra``."""
    where = f"configuration '{configuration.name}'"
    overrides = {**configuration.overrides, **extra}
    try:
        reject_renamed(overrides)
    except ValueError as exc:
        raise SuiteError(f"{where}: {exc}") from None
    check_parameter_names(overrides, flatten(SlamConfig()), where)
    params_file = sequence.params or default_params_file(sequence.dataset)
    try:
        cfg = load_config(params_file, overrides)
    except (ValueError, FileNotFoundError) as exc:
        raise SuiteError(f"{where} on sequence '{sequence.name}': {exc}") from None
    return (str(params_file) if params_file else None), overrides, flatten(cfg)


def baseline_parameters(sequence: SequenceSpec,
                        configuration: Configuration) -> tuple[dict[str, Any], dict[str, Any]]:
    """(overrides, Open3DParams) of a baseline run: the baseline's defaults < the sequence's ``open3d`` < the
    configuration's overrides."""
    where = f"configuration '{configuration.name}'"
    defaults = dataclasses.asdict(BASELINES[configuration.method])
    overrides = {**sequence.open3d, **configuration.overrides}
    check_parameter_names(overrides, defaults, where)
    values = {name: _coerce(name, value, defaults[name], where) for name, value in overrides.items()}
    return overrides, {**defaults, **values}


def open_sequence(sequence: SequenceSpec):
    """The sequence's frames; with a ``color_calibration``, colour resampled into the depth camera."""
    from gausem_bench.color_registration import ColorRegistered
    from gausem_core.data import open_dataset

    options = {"size": sequence.size, "stride": sequence.stride, "max_frames": sequence.frames}
    if sequence.color_calibration is None:
        return open_dataset(sequence.dataset, **options)
    with warnings.catch_warnings():  # the reader's "used as if aligned" warning does not apply here
        warnings.filterwarnings("ignore", message=".*not registered to colour.*")
        dataset = open_dataset(sequence.dataset, **options)
    return ColorRegistered(dataset, ColorCalibration.from_dict(sequence.color_calibration))


def plan(suite: Suite, work_dir: str | Path, *, overrides: dict[str, Any] | None = None,
         lpips_weights: str | None = None, threads: int | None = None, progress: bool = True) -> list[Case]:
    """Every (sequence, configuration) run of ``suite``, validated; ``overrides`` go on top of GauSem's parameters.

    Datasets are opened (not read) here, so a missing folder fails before anything runs.
    """
    if not suite.sequences:
        raise SuiteError(f"suite {suite.name}: no sequences (give them in the suite or with --dataset)")
    cases = []
    for sequence in suite.sequences:
        try:
            dataset = open_sequence(sequence)
        except (ValueError, FileNotFoundError) as exc:
            raise SuiteError(f"sequence '{sequence.name}': {exc}") from None
        for configuration in suite.configurations:
            if configuration.method == "gausem":
                params_file, values, parameters = gausem_parameters(sequence, configuration, overrides or {})
                seed = parameters["seed"]
            else:
                params_file, seed = None, 0  # the baselines are deterministic; run_baseline seeds Open3D with 0
                values, parameters = baseline_parameters(sequence, configuration)
            cases.append(Case(sequence, configuration, values, parameters, params_file, seed, dataset.name,
                              len(dataset), getattr(dataset, "depth_registered", True),
                              Path(work_dir) / sequence.name / configuration.name, lpips_weights, threads, progress))
    return cases
