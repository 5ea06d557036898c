"""Map consistency without ground truth (issue 13): how thick the wall is where the outbound
and the return pass overlap, per metre of corridor.

The method (cells of ``CELL_VOXELS`` map voxels, a plane per cell fitted to both passes, the
RMS distance of the points from it per ``BIN_M`` of chainage; each pass alone about its own
planes as the floor; what the figure sees and where it saturates) is documented with its
code in ``src/map_quality.rs``, which does the per-point work in one pass over the map. This
module places the points along the corridor (the outbound path's frame at each submap's
anchor) and wraps the result for ``report.json`` and the plot.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from decod_rs import _core
from decod_rs.chainage import forward_course
from decod_rs.maps import OUTBOUND, RETURN, MapCloud

FloatArray = NDArray[np.float64]

__all__ = [
    "BIN_M",
    "CELL_VOXELS",
    "Consistency",
    "map_consistency",
    "outbound_path",
    "point_chainage",
]

#: Bin length along the corridor, metres (the issue's "per metre of corridor").
BIN_M = 1.0
#: Cell edge in map voxels. A map voxel averages ~9 submap points (3 x 3 on a surface), so a
#: cell holds ~9 voxels of each pass: enough for a plane with 6 degrees of freedom to spare,
#: small enough that curvature stays below the noise (0.4 mm on the 0.3 m hume pipe, 4 mm in
#: a 3 m tunnel, at the auto scaling's 0.054 r voxels). Measured on simulated hume (pipe) and
#: shield (tunnel) maps: 2 voxels leave too few cells with both passes in the tunnel, 5 double
#: the curvature floor in the pipe.
CELL_VOXELS = 3.0
#: Points of each pass for a cell to count (``src/map_quality.rs``).
MIN_CELL_POINTS: int = _core.MIN_CELL_POINTS
PASSES = {"outbound": OUTBOUND, "return": RETURN}


@dataclass
class Consistency:
    """Wall thickness per bin (metres, NaN where the passes do not both reach), each pass's
    own floor, and their medians over the bins where both passes overlap."""

    chainage_m: FloatArray
    overlap_m: FloatArray
    outbound_m: FloatArray
    return_m: FloatArray
    points: dict[str, int] = field(default_factory=dict)
    cell_m: float | None = None

    @property
    def overlap_bins(self) -> int:
        return int(np.count_nonzero(np.isfinite(self.overlap_m)))

    def median_m(self, which: str = "overlap") -> float | None:
        values = getattr(self, f"{which}_m")
        ok = np.isfinite(self.overlap_m) & np.isfinite(values)
        return float(np.median(values[ok])) if np.any(ok) else None

    def mean_m(self) -> float | None:
        """Mean overlap thickness over the bins where both passes reach: weighs the places
        where the passes disagree most (the median keeps the typical wall)."""
        ok = np.isfinite(self.overlap_m)
        return float(np.mean(self.overlap_m[ok])) if np.any(ok) else None

    def summary(self) -> dict[str, Any]:
        """The report's numbers: medians in millimetres, bins, and the figure per bin."""

        def mm(v: float | None) -> float | None:
            return None if v is None else round(1e3 * v, 3)

        def per_bin(a: FloatArray) -> list[float | None]:
            return [None if not np.isfinite(v) else round(1e3 * float(v), 3) for v in a]

        return {
            "median_overlap_mm": mm(self.median_m("overlap")),
            "mean_overlap_mm": mm(self.mean_m()),
            "median_outbound_floor_mm": mm(self.median_m("outbound")),
            "median_return_floor_mm": mm(self.median_m("return")),
            "cell_m": self.cell_m,
            "overlap_bins": self.overlap_bins,
            "bins": int(self.chainage_m.size),
            "chainage_m": [round(float(c), 3) for c in self.chainage_m],
            "overlap_mm": per_bin(self.overlap_m),
            "outbound_floor_mm": per_bin(self.outbound_m),
            "return_floor_mm": per_bin(self.return_m),
        }


def outbound_path(stamps: FloatArray, poses: FloatArray, split_stamp: float | None) -> FloatArray:
    """Positions (P, 3) of the outbound leg (all of it without a return) that take the robot
    further along (:func:`decod_rs.chainage.forward_course`: not a back-up)."""
    keep = np.ones(stamps.shape, dtype=bool) if split_stamp is None else stamps <= split_stamp
    return forward_course(np.asarray(poses, dtype=np.float64)[keep, :3, 3])


def _path_frame(path: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Arclength (P,) and unit tangent (P, 3) along a polyline, each tangent the chord over
    one bin around the sample (a robot's wobble is not the corridor's direction)."""
    steps = np.linalg.norm(np.diff(path, axis=0), axis=1)
    arclength = np.concatenate([[0.0], np.cumsum(steps)])
    lo = np.searchsorted(arclength, arclength - BIN_M / 2, side="left")
    hi = np.searchsorted(arclength, arclength + BIN_M / 2, side="right") - 1
    chord = path[hi] - path[lo]
    norm = np.linalg.norm(chord, axis=1, keepdims=True)
    tangent = np.where(norm > 1e-9, chord / np.maximum(norm, 1e-12), [1.0, 0.0, 0.0])
    return arclength, tangent


def _submap_frames(
    anchor_positions: FloatArray, path: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Per submap (anchors K x 3): the sample of ``path`` nearest to its anchor (K, 3), the
    path's tangent there (K, 3) and its arclength (K,): K x P distances, in blocks."""
    arclength, tangent = _path_frame(path)
    nearest = np.empty(anchor_positions.shape[0], dtype=np.int64)
    for start in range(0, anchor_positions.shape[0], 256):
        block = anchor_positions[start : start + 256]
        d2 = ((block[:, None, :] - path[None, :, :]) ** 2).sum(axis=2)
        nearest[start : start + 256] = np.argmin(d2, axis=1)
    return path[nearest], tangent[nearest], arclength[nearest]


def point_chainage(cloud: MapCloud, anchor_positions: FloatArray, path: FloatArray) -> FloatArray:
    """Chainage (N,) of each map point along ``path`` (the outbound positions, P x 3): each
    point is projected through the path sample nearest to the anchor of the submap that saw
    it (``anchor_positions`` K x 3), linear within a submap's reach."""
    origin, tangent, arclength = _submap_frames(np.asarray(anchor_positions, np.float64), path)
    return _core.point_chainage(
        np.asarray(cloud.points, dtype=np.float64),
        np.asarray(cloud.submap, dtype=np.uint32),
        origin,
        tangent,
        arclength,
    )


def map_consistency(
    cloud: MapCloud,
    anchor_positions: FloatArray,
    path: FloatArray,
    voxel_m: float,
) -> Consistency:
    """Wall thickness per ``BIN_M`` of chainage along ``path`` (the map's outbound positions,
    P x 3) where both passes of ``cloud`` reach, and each pass's own floor, in cells of
    ``CELL_VOXELS`` x ``voxel_m`` (the map's voxel; ``src/map_quality.rs``).
    ``anchor_positions`` (K, 3): the submap anchors in the same trajectory."""
    if not (np.isfinite(voxel_m) and voxel_m > 0):
        raise ValueError(f"voxel_m: must be finite and > 0, got {voxel_m}")
    cell_m = CELL_VOXELS * float(voxel_m)
    empty = np.zeros(0)
    points = {name: int(np.count_nonzero(cloud.pass_ == p)) for name, p in PASSES.items()}
    if cloud.points.shape[0] == 0 or path.shape[0] < 2:
        return Consistency(empty, empty, empty, empty, points, cell_m)
    chainage = point_chainage(cloud, anchor_positions, path)
    start, overlap, outbound, ret = _core.wall_thickness(
        np.asarray(cloud.points, dtype=np.float64),
        np.asarray(cloud.pass_, dtype=np.uint8),
        chainage,
        cell_m,
        BIN_M,
    )
    return Consistency(
        chainage_m=start + BIN_M * (np.arange(overlap.size, dtype=np.float64) + 0.5),
        overlap_m=overlap,
        outbound_m=outbound,
        return_m=ret,
        points=points,
        cell_m=cell_m,
    )
