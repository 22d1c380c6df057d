"""sensor_msgs/PointCloud2 <-> numpy structured arrays (one row per point; sub-arrays are PointField count > 1).

Built clouds are unordered (height 1), little-endian, dense and packed (point_step = the dtype's itemsize). Reading
accepts any offsets, row padding and either byte order, and returns native-endian data.
"""
from __future__ import annotations

import numpy as np
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header

_DTYPES = {
    PointField.INT8: np.int8, PointField.UINT8: np.uint8, PointField.INT16: np.int16, PointField.UINT16: np.uint16,
    PointField.INT32: np.int32, PointField.UINT32: np.uint32, PointField.FLOAT32: np.float32,
    PointField.FLOAT64: np.float64,
}
_DATATYPES = {np.dtype(v): k for k, v in _DTYPES.items()}
_MAX_POINT_STEP = np.iinfo(np.int32).max  # numpy's largest itemsize


def structured_to_pointcloud2(points: np.ndarray, header: Header) -> PointCloud2:
    """A 1-D structured array -> PointCloud2 whose fields are the array's fields, in order."""
    if points.ndim != 1 or points.dtype.names is None:
        raise ValueError(f"expected a 1-D structured array, got dtype {points.dtype} shape {points.shape}")
    fields = []
    for name in points.dtype.names:
        dtype, offset = points.dtype.fields[name][:2]
        base, shape = dtype.base.newbyteorder("="), dtype.shape
        if base not in _DATATYPES:
            raise ValueError(f"field {name!r}: {base} has no PointField datatype")
        fields.append(PointField(name=name, offset=offset, datatype=_DATATYPES[base], count=int(np.prod(shape))))
    little = points.astype(points.dtype.newbyteorder("<"), copy=False)
    step = points.dtype.itemsize
    return PointCloud2(header=header, height=1, width=len(points), fields=fields, is_bigendian=False,
                       point_step=step, row_step=step * len(points), data=little.tobytes(), is_dense=True)


def pointcloud2_to_structured(msg: PointCloud2) -> np.ndarray:
    """PointCloud2 -> 1-D structured array (rows of all ``height`` rows concatenated), native byte order."""
    order = ">" if msg.is_bigendian else "<"
    names, formats, offsets = [], [], []
    if msg.point_step > _MAX_POINT_STEP:
        raise ValueError(f"PointCloud2 point_step {msg.point_step} exceeds {_MAX_POINT_STEP} bytes")
    for f in msg.fields:
        if f.datatype not in _DTYPES:
            raise ValueError(f"PointCloud2 field {f.name!r} has unknown datatype {f.datatype}")
        base = np.dtype(_DTYPES[f.datatype]).newbyteorder(order)
        end = f.offset + base.itemsize * f.count
        if end > msg.point_step:  # checked here: numpy overflows (and crashes) on offsets near 2**31
            raise ValueError(f"PointCloud2 field {f.name!r} ({f.count} x {base.name} at offset {f.offset}) ends at "
                             f"byte {end}, beyond point_step {msg.point_step}")
        names.append(f.name)
        formats.append(base if f.count == 1 else (base, (f.count,)))
        offsets.append(f.offset)
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": msg.point_step})
    h, w = msg.height, msg.width
    if msg.row_step < w * msg.point_step or len(msg.data) != h * msg.row_step:
        raise ValueError(f"PointCloud2 {w}x{h}: {len(msg.data)} data bytes do not match point_step {msg.point_step} "
                         f"and row_step {msg.row_step}")
    rows = np.frombuffer(msg.data, np.uint8).reshape(h, msg.row_step)[:, :w * msg.point_step]
    points = np.ascontiguousarray(rows).view(dtype).reshape(-1)
    return points.astype(dtype.newbyteorder("="), copy=False)
