"""Binary PLY point clouds (little-endian), the format every point-cloud viewer opens
(CloudCompare, MeshLab, Open3D, PDAL): a header naming each per-vertex property and its type,
then one packed record per point. Written with numpy in one pass; no dependency.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

__all__ = ["PLY_TYPES", "write_ply"]

#: numpy dtype -> PLY type name (the PLY 1.0 names every reader knows).
PLY_TYPES: dict[np.dtype[np.generic], str] = {
    np.dtype(np.int8): "char",
    np.dtype(np.uint8): "uchar",
    np.dtype(np.int16): "short",
    np.dtype(np.uint16): "ushort",
    np.dtype(np.int32): "int",
    np.dtype(np.uint32): "uint",
    np.dtype(np.float32): "float",
    np.dtype(np.float64): "double",
}


def write_ply(
    path: str | Path,
    properties: Mapping[str, NDArray[np.generic]],
    comments: tuple[str, ...] = (),
) -> Path:
    """Write one ``vertex`` element with ``properties`` (name -> ``(N,)`` array, in order;
    each array's dtype is its PLY type, see ``PLY_TYPES``) as binary little-endian PLY.

    Raises ValueError naming the property when the arrays differ in length, are not 1-D or
    have a type PLY cannot hold.
    """
    if not properties:
        raise ValueError("write_ply: no properties")
    columns = {name: np.asarray(values) for name, values in properties.items()}
    n = next(iter(columns.values())).shape[0] if columns else 0
    fields = []
    for name, values in columns.items():
        if values.ndim != 1 or values.shape[0] != n:
            raise ValueError(
                f"write_ply: property {name!r} must have shape ({n},), got {values.shape}"
            )
        if values.dtype not in PLY_TYPES:
            raise ValueError(f"write_ply: property {name!r} has unsupported dtype {values.dtype}")
        if not name.isidentifier():
            raise ValueError(f"write_ply: property name {name!r} is not a plain word")
        fields.append((name, values.dtype.newbyteorder("<")))
    records = np.empty(n, dtype=np.dtype(fields))
    for name, values in columns.items():
        records[name] = values
    header = ["ply", "format binary_little_endian 1.0"]
    header += ["comment " + " ".join(c.split()) for c in comments]
    header.append(f"element vertex {n}")
    header += [f"property {PLY_TYPES[values.dtype]} {name}" for name, values in columns.items()]
    header.append("end_header")
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    with out.open("wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(records.tobytes())
    return out
