"""The simulated logs' sensor_msgs/PointCloud2 layout, shared by the ROS 2 and ROS 1 writers."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

FLOAT32 = 7  # sensor_msgs/PointField.FLOAT32
UINT32 = 6  # sensor_msgs/PointField.UINT32


def cloud_layout(
    field: Any,
    xyz: NDArray[np.float32],
    intensity: NDArray[np.float32],
    times_ns: NDArray[np.uint32] | None = None,
) -> tuple[list[Any], int, NDArray[np.uint8]]:
    """A PointCloud2's fields (made with the typestore's ``field`` type), point step and data:
    x, y, z, intensity as float32, and with ``times_ns`` each point's time since the stamp as
    Ouster's ``t`` (uint32 ns; :mod:`decod_rs.sim.sweep`)."""
    names = ["x", "y", "z", "intensity"] + ([] if times_ns is None else ["t"])
    formats = ["<f4"] * 4 + ([] if times_ns is None else ["<u4"])
    buf = np.empty(xyz.shape[0], dtype=np.dtype({"names": names, "formats": formats}))
    buf["x"], buf["y"], buf["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    buf["intensity"] = intensity
    if times_ns is not None:
        buf["t"] = times_ns
    fields = [
        field(name=n, offset=4 * i, datatype=UINT32 if n == "t" else FLOAT32, count=1)
        for i, n in enumerate(names)
    ]
    return fields, 4 * len(names), buf.view(np.uint8).reshape(-1)
