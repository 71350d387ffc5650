"""sensor_msgs/PointCloud2 encoding and decoding, vectorized from ``msg.fields``.

Datatype codes are those of sensor_msgs/PointField: 1 INT8, 2 UINT8, 3 INT16, 4 UINT16,
5 INT32, 6 UINT32, 7 FLOAT32, 8 FLOAT64.
"""

from __future__ import annotations

import numpy as np

POINTFIELD_DTYPES: dict[int, str] = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4",
                                     7: "f4", 8: "f8"}
DTYPE_TO_POINTFIELD: dict[str, int] = {v: k for k, v in POINTFIELD_DTYPES.items()}


def encode_pointcloud2(columns: dict[str, np.ndarray], layout: list[tuple[str, int, str]],
                       point_step: int, big_endian: bool = False) -> tuple[bytes, list[tuple[str, int, int, int]]]:
    """Pack per-point columns into PointCloud2 ``data`` bytes.

    ``layout`` lists ``(name, byte_offset, numpy_kind)`` with kinds from ``POINTFIELD_DTYPES``
    values (``"f4"``, ``"f8"``, ``"u2"``, ...). Bytes not covered by a field (padding) are zero.
    Returns ``(data, fields)`` where ``fields`` are ``(name, offset, datatype, count=1)`` tuples
    ready to become ``sensor_msgs/PointField`` messages.
    """
    n = len(next(iter(columns.values()))) if columns else 0
    order = ">" if big_endian else "<"
    dtype = np.dtype({"names": [f[0] for f in layout],
                      "formats": [order + f[2] for f in layout],
                      "offsets": [f[1] for f in layout],
                      "itemsize": point_step})
    arr = np.zeros(n, dtype=dtype)
    for name, _, _ in layout:
        arr[name] = columns[name]
    fields = [(name, off, DTYPE_TO_POINTFIELD[kind], 1) for name, off, kind in layout]
    return arr.tobytes(), fields
