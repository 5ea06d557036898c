"""A real LiDAR odometry on the simulated scans: KISS-ICP (``pip install decod-rs[kiss]``).

In a corridor, point-to-point ICP cannot measure the translation along the axis; KISS-ICP's
constant-velocity prediction then decides how far it believes it moved. Used by
``simulate(..., odometry="kiss-icp")`` and ``scripts/measure_kiss_icp.py``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from decod_rs.sim.fields import F64

# Per scene: max range (m) and voxel size (m). KISS-ICP's own rule is voxel = max_range/100;
# in a 0.4-0.6 m pipe that would be 10 cm, coarser than the pipe wall's curvature, so pipes
# use 2 cm; tunnels use the rule.
KISS_SETTINGS: dict[str, tuple[float, float]] = {
    "hume": (10.0, 0.02),
    "pe": (10.0, 0.02),
    "shield": (60.0, 0.5),
    "horseshoe": (60.0, 0.5),
}


class KissOdometry:
    """Feeds body-frame scans to KISS-ICP and returns ``odom_from_body`` poses, with the
    odometry frame anchored at ``first_pose`` (the first ground-truth pose)."""

    def __init__(self, scene: str, first_pose: F64) -> None:
        try:
            from kiss_icp.config import KISSConfig
            from kiss_icp.kiss_icp import KissICP
        except ImportError as exc:  # pragma: no cover - depends on the environment
            raise ImportError(
                "odometry='kiss-icp' needs KISS-ICP: pip install 'decod-rs[kiss]'"
            ) from exc
        max_range, voxel = KISS_SETTINGS[scene]
        cfg = KISSConfig()
        cfg.data.max_range = max_range
        cfg.data.min_range = 0.0
        cfg.data.deskew = False
        cfg.mapping.voxel_size = voxel
        cfg.registration.max_num_threads = 1
        self._odo = KissICP(cfg)
        self._first = first_pose
        self.settings: dict[str, Any] = {
            "name": "kiss-icp",
            "max_range_m": max_range,
            "voxel_size_m": voxel,
            "deskew": False,
        }

    def step(self, points_body: NDArray[np.float32]) -> F64:
        frame = np.asarray(points_body, dtype=np.float64)
        self._odo.register_frame(frame, np.zeros(frame.shape[0]))
        return np.asarray(self._first @ self._odo.last_pose, dtype=np.float64)
