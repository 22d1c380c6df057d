"""GauSem's internal event records, defined once, and their generic PointCloud2 codec.

Carrier: ``sensor_msgs/PointCloud2`` with one row ("point") per record and one PointField per record field, named
after it; arrays (poses, descriptors, information matrices) are a field with ``count > 1`` (row-major); the header
carries the message stamp and frame. Why PointCloud2: it is the only standard type with a header and arbitrary named,
typed, fixed-size columns; a batch of records is one message; RViz and ``ros2 topic echo`` handle it; its layout is
self-describing, so a reader checks that the fields are exactly the record's and fails clearly otherwise.

Each record field declares its wire type through ``dataclasses.field`` metadata (the helpers below); the codec reads
that table, so adding a record is only declaring its dataclass. Integers are INT32, floats FLOAT64 (so stamps and
distances round-trip exactly), flags and enums UINT8, matrices FLOAT64; vectors of any length D and tables of any
number N of fixed-width rows (N x K values, row-major in one field of count N K) take their element type from the
field (one D, one N per message).
"""
from __future__ import annotations

import dataclasses
import enum
from typing import TypeVar

import numpy as np
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header

from .pointcloud2 import pointcloud2_to_structured, structured_to_pointcloud2
from .poses import check_pose

_INT32 = np.iinfo(np.int32)


@dataclasses.dataclass(frozen=True)
class _Wire:
    dtype: np.dtype
    shape: tuple = ()          # () scalar; None inside = any length (one per message)
    kind: str = "number"       # number | flag | enum | pose | array
    enum_type: type | None = None


def _field(wire: _Wire, default=dataclasses.MISSING):
    return dataclasses.field(default=default, metadata={"wire": wire})


def int_field():
    return _field(_Wire(np.dtype("<i4")))


def float_field():
    return _field(_Wire(np.dtype("<f8")))


def flag_field(default=dataclasses.MISSING):
    return _field(_Wire(np.dtype("u1"), kind="flag"), default)


def enum_field(enum_type: type[enum.IntEnum]):
    return _field(_Wire(np.dtype("u1"), kind="enum", enum_type=enum_type))


def pose_field():
    return _field(_Wire(np.dtype("<f8"), (4, 4), kind="pose"))


def matrix_field(rows: int, cols: int):
    return _field(_Wire(np.dtype("<f8"), (rows, cols), kind="array"))


def vector_field(dtype: str):
    return _field(_Wire(np.dtype(dtype), (None,), kind="array"))


def rows_field(dtype: str, columns: int):
    return _field(_Wire(np.dtype(dtype), (None, columns), kind="array"))


class _Record:
    """Base of the records: validates and normalises fields from their wire table; array-aware equality (NaN equal
    to NaN: a value read back equals the one sent)."""

    def __post_init__(self):
        for f, wire in _wires(type(self)):
            object.__setattr__(self, f.name, _normalise(getattr(self, f.name), wire, f"{type(self).__name__}.{f.name}"))

    def __eq__(self, other):
        if type(other) is not type(self):
            return NotImplemented
        return all(np.array_equal(getattr(self, f.name), getattr(other, f.name), equal_nan=True)
                   for f in dataclasses.fields(self))

    __hash__ = None


def _wires(cls) -> list[tuple[dataclasses.Field, _Wire]]:
    return [(f, f.metadata["wire"]) for f in dataclasses.fields(cls)]


def _normalise(value, wire: _Wire, where: str):
    if wire.kind == "enum":
        return wire.enum_type(value)
    if wire.kind == "flag":
        return bool(value)
    if wire.shape == ():
        if wire.dtype.kind == "i":
            if int(value) != value or not _INT32.min <= value <= _INT32.max:
                raise ValueError(f"{where}: {value!r} is not an int32")
            return int(value)
        return float(value)
    arr = np.array(value, dtype=wire.dtype.newbyteorder("="))
    if wire.kind == "pose":
        arr = check_pose(arr, where)
    if arr.ndim != len(wire.shape) or any(s is not None and s != a for s, a in zip(wire.shape, arr.shape)):
        raise ValueError(f"{where}: expected shape {wire.shape} (None = any), got {arr.shape}")
    arr.setflags(write=False)
    return arr


@dataclasses.dataclass(frozen=True, eq=False)
class KeyframeRecord(_Record):
    """A keyframe: its pose ``cam_to_world`` in its submap's frame and the submap's anchor pose (submap frame in
    the map)."""

    keyframe_id: int = int_field()
    stamp: float = float_field()
    submap_id: int = int_field()
    pose: np.ndarray = pose_field()
    anchor_pose: np.ndarray = pose_field()


@dataclasses.dataclass(frozen=True, eq=False)
class PlaceSignatureRecord(_Record):
    """A loop keyframe's place signature (the core's ``PlaceSignature``): with ``bag_of_words`` its ORB features, N
    rows of ``orb_keypoints`` (pixels), ``orb_descriptors`` (32 bytes) and ``orb_points`` (camera frame, NaN without
    depth) found at ``orb_scale``, and an empty ``descriptor``; else its global ``descriptor`` and no ORB rows. Then
    the Eq. 7 ``landmark_scores`` and the ids of the ``nearby`` keyframes. ``loaded``: a keyframe of a map the tracker
    loaded, to store without a loop check; ``new_map``: the first signature since the tracker started a new map (the
    detector forgets the keyframes before it). One record per message (lengths vary)."""

    keyframe_id: int = int_field()
    stamp: float = float_field()
    submap_id: int = int_field()
    bag_of_words: bool = flag_field()
    descriptor: np.ndarray = vector_field("<f4")
    orb_keypoints: np.ndarray = rows_field("<f4", 2)
    orb_descriptors: np.ndarray = rows_field("u1", 32)
    orb_points: np.ndarray = rows_field("<f4", 3)
    orb_scale: int = int_field()
    landmark_scores: np.ndarray = vector_field("<f8")
    nearby: np.ndarray = vector_field("<i4")
    loaded: bool = flag_field(default=False)
    new_map: bool = flag_field(default=False)


class SubmapEventKind(enum.IntEnum):
    CREATED = 0
    CLOSED = 1


@dataclasses.dataclass(frozen=True, eq=False)
class SubmapEvent(_Record):
    submap_id: int = int_field()
    anchor_keyframe_id: int = int_field()
    anchor_pose: np.ndarray = pose_field()
    kind: SubmapEventKind = enum_field(SubmapEventKind)


@dataclasses.dataclass(frozen=True, eq=False)
class LoopCandidateRecord(_Record):
    query_keyframe_id: int = int_field()
    match_keyframe_id: int = int_field()
    query_submap_id: int = int_field()
    match_submap_id: int = int_field()
    descriptor_distance: float = float_field()
    landmark_distance: float = float_field()
    intra_submap: bool = flag_field()


@dataclasses.dataclass(frozen=True, eq=False)
class LoopConstraintRecord(_Record):
    """A registered loop: ``relative_pose`` maps frame b to frame a (keyframe frames for intra-submap loops, submap
    frames otherwise); ``information`` is the 6x6 information matrix in twist order (rho, omega)."""

    keyframe_a: int = int_field()
    keyframe_b: int = int_field()
    submap_a: int = int_field()
    submap_b: int = int_field()
    relative_pose: np.ndarray = pose_field()
    fitness: float = float_field()
    information: np.ndarray = matrix_field(6, 6)
    intra_submap: bool = flag_field()


class PoseGraphNodeKind(enum.IntEnum):
    KEYFRAME = 0
    ANCHOR = 1


@dataclasses.dataclass(frozen=True, eq=False)
class PoseGraphNode(_Record):
    """A corrected pose: a keyframe's pose in its submap frame, or a submap anchor's pose in the map."""

    kind: PoseGraphNodeKind = enum_field(PoseGraphNodeKind)
    node_id: int = int_field()
    pose: np.ndarray = pose_field()


@dataclasses.dataclass(frozen=True)
class PoseGraphUpdate:
    """The corrected poses of one pose-graph optimisation (one PointCloud2, one row per node)."""

    nodes: tuple[PoseGraphNode, ...]

    def __post_init__(self):
        object.__setattr__(self, "nodes", tuple(self.nodes))


R = TypeVar("R", bound=_Record)


def _row_dtype(cls, lengths: dict[str, int]) -> np.dtype:
    columns = []
    for f, wire in _wires(cls):
        shape = tuple(lengths[f.name] if s is None else s for s in wire.shape)
        columns.append((f.name, wire.dtype, shape) if shape else (f.name, wire.dtype))
    return np.dtype(columns)


def records_to_pointcloud2(records, header: Header, record_type: type[R] | None = None) -> PointCloud2:
    """Records of one type -> PointCloud2 (``record_type`` is needed only to encode an empty batch)."""
    records = list(records)
    cls = record_type or (type(records[0]) if records else None)
    if cls is None:
        raise ValueError("records_to_pointcloud2: an empty batch needs record_type")
    if any(type(r) is not cls for r in records):
        raise ValueError(f"records_to_pointcloud2: mixed record types in a {cls.__name__} batch")
    lengths = {}
    for f, wire in _wires(cls):
        if None in wire.shape:
            sizes = {getattr(r, f.name).shape[0] for r in records} or {0}
            if len(sizes) > 1:
                raise ValueError(f"{cls.__name__}.{f.name}: lengths {sorted(sizes)} differ within one message")
            lengths[f.name] = sizes.pop()
    rows = np.empty(len(records), _row_dtype(cls, lengths))
    for f, _ in _wires(cls) if records else ():
        rows[f.name] = [getattr(r, f.name) for r in records]
    return structured_to_pointcloud2(rows, header)


def pointcloud2_to_records(msg: PointCloud2, record_type: type[R]) -> list[R]:
    """PointCloud2 -> records; its fields must be exactly ``record_type``'s."""
    rows = pointcloud2_to_structured(msg)
    wires = _wires(record_type)
    expected = [f.name for f, _ in wires]
    if list(rows.dtype.names) != expected:
        raise ValueError(f"PointCloud2 fields {list(rows.dtype.names)} are not a {record_type.__name__} "
                         f"(expected {expected})")
    counts = {f.name: f.count for f in msg.fields}
    columns = {}
    for f, wire in wires:
        width = int(np.prod([s for s in wire.shape if s is not None]))
        if counts[f.name] % width:
            raise ValueError(f"PointCloud2 field {f.name!r} holds {counts[f.name]} values, not rows of {width}")
        shape = tuple(counts[f.name] // width if s is None else s for s in wire.shape)
        columns[f.name] = rows[f.name].reshape((len(rows), *shape))
    return [record_type(**{name: col[i] for name, col in columns.items()}) for i in range(len(rows))]


def pose_graph_update_to_pointcloud2(update: PoseGraphUpdate, header: Header) -> PointCloud2:
    return records_to_pointcloud2(update.nodes, header, PoseGraphNode)


def pointcloud2_to_pose_graph_update(msg: PointCloud2) -> PoseGraphUpdate:
    return PoseGraphUpdate(tuple(pointcloud2_to_records(msg, PoseGraphNode)))
