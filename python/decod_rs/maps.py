"""The run's point-cloud maps (issue 13): the submaps placed by the corrected poses and by the
odometry, one point per voxel and pass, written as binary PLY.

The Rust ``LogProcessor`` keeps a bounded voxel map while it streams the log
(``src/map.rs``: segments of submaps, memory growing with the distance travelled, not with
the log's duration); :func:`render_map` places it by a trajectory once the graph is solved.
The passes are the outbound leg (submaps anchored up to the turnaround, ``split_stamp``) and
the return leg; a run without a return is one pass. Colours follow the paper's Fig. 5:
cyan outbound, orange return.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from decod_rs import _core
from decod_rs.ply import write_ply
from decod_rs.tum import interpolate_poses

FloatArray = NDArray[np.float64]

__all__ = [
    "OUTBOUND",
    "PASS_COLOURS",
    "PASS_NAMES",
    "RETURN",
    "MapCloud",
    "anchor_poses",
    "pass_of",
    "render_map",
    "write_map_ply",
]

OUTBOUND, RETURN = 0, 1
PASS_NAMES = ("outbound", "return")
#: RGB per pass: the paper's Fig. 5 (cyan outbound, orange return).
PASS_COLOURS = np.array([[0, 190, 230], [255, 140, 0]], dtype=np.uint8)
#: Coordinates are written as float32 while every |coordinate| stays below this (float32
#: keeps 0.06 mm there); beyond it (a georeferenced frame) as float64.
FLOAT32_LIMIT_M = 1000.0


@dataclass(frozen=True)
class MapCloud:
    """A map placed by one trajectory: ``points`` (N, 3) metres in its world frame,
    ``pass_`` (N,) 0 outbound / 1 return, ``submap`` (N,) the first submap that saw each
    point (index into the map's submap stamps), ``stamp`` (N,) that submap's anchor stamp,
    seconds, and ``count`` (N,) the submap points merged into the point."""

    points: FloatArray
    pass_: NDArray[np.uint8]
    submap: NDArray[np.uint32]
    stamp: FloatArray
    count: NDArray[np.uint32]

    def of_pass(self, which: int) -> FloatArray:
        """The points of one pass, (M, 3)."""
        return self.points[self.pass_ == which]


def pass_of(stamps: FloatArray, split_stamp: float | None) -> NDArray[np.uint8]:
    """0 (outbound) for stamps up to the turnaround ``split_stamp``, 1 (return) after it; all
    0 when the run has no return (``split_stamp`` None)."""
    s = np.asarray(stamps, dtype=np.float64)
    if split_stamp is None:
        return np.zeros(s.shape, dtype=np.uint8)
    return (s > split_stamp).astype(np.uint8)


def anchor_poses(anchor_stamps: FloatArray, stamps: FloatArray, poses: FloatArray) -> FloatArray:
    """The poses ``(N, 4, 4)`` of a trajectory sampled at ``stamps`` (N,), at the submap
    anchors (K,): the pose at the same stamp (anchors are scans), interpolated otherwise."""
    a = np.asarray(anchor_stamps, dtype=np.float64)
    s = np.asarray(stamps, dtype=np.float64)
    idx = np.clip(np.searchsorted(s, a), 0, max(s.size - 1, 0))
    exact = np.abs(s[idx] - a) <= 1e-9 * np.maximum(1.0, np.abs(a))
    out = np.asarray(poses, dtype=np.float64)[idx].copy()
    if not np.all(exact):
        out[~exact] = interpolate_poses(s, poses, a[~exact])
    return out


def render_map(
    processor: _core.LogProcessor,
    stamps: FloatArray,
    poses: FloatArray,
    split_stamp: float | None,
) -> MapCloud:
    """The processor's voxel map placed by the trajectory ``poses`` (N, 4, 4) at ``stamps``
    (N,) (each submap by its anchor's pose; see ``src/map.rs``), one point per voxel and pass."""
    anchors = np.asarray(processor.map_submap_stamps(), dtype=np.float64)
    world_from_submap = anchor_poses(anchors, stamps, poses)
    points, pass_, submap, count = processor.render_map(
        world_from_submap, pass_of(anchors, split_stamp)
    )
    return MapCloud(
        points=np.asarray(points, dtype=np.float64),
        pass_=np.asarray(pass_, dtype=np.uint8),
        submap=np.asarray(submap, dtype=np.uint32),
        stamp=anchors[submap] if anchors.size else np.zeros(0),
        count=np.asarray(count, dtype=np.uint32),
    )


def write_map_ply(path: str | Path, cloud: MapCloud, t0: float, what: str) -> Path:
    """``cloud`` as binary PLY: ``x y z`` (float, or double beyond ``FLOAT32_LIMIT_M``),
    ``red green blue`` by pass (``PASS_COLOURS``), ``pass`` (0 outbound, 1 return),
    ``time`` (seconds from ``t0`` at which the point was first seen) and ``count`` (submap
    points merged). ``what`` goes into the header's comment."""
    p = cloud.points
    big = p.size > 0 and float(np.max(np.abs(p))) >= FLOAT32_LIMIT_M
    coords = p if big else p.astype(np.float32)
    rgb = PASS_COLOURS[np.minimum(cloud.pass_, len(PASS_COLOURS) - 1)]
    return write_ply(
        path,
        {
            "x": coords[:, 0],
            "y": coords[:, 1],
            "z": coords[:, 2],
            "red": rgb[:, 0],
            "green": rgb[:, 1],
            "blue": rgb[:, 2],
            "pass": cloud.pass_,
            "time": (cloud.stamp - t0).astype(np.float32),
            "count": cloud.count,
        },
        comments=(
            f"decod {what} map: submaps placed by the {what} poses, voxel-filtered",
            "pass 0 = outbound (cyan), 1 = return (orange); time = s from the first scan",
        ),
    )
