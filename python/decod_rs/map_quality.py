"""Map consistency without ground truth (issue 13): how thick the wall is where the outbound
and the return pass overlap, per metre of corridor.

A user with a real log has no ground truth, but the paper's own evidence on real pipes is the
map (Fig. 5): under odometry the two passes place the same wall at two positions; after a
correct loop closure they overlap. The figure measures that, one bin of corridor at a time
(``BIN_M`` of chainage along the map's own outbound path):

1. the points of both passes in the bin (each pass needs ``MIN_POINTS_PER_PASS``), in a local
   frame whose axis is the outbound path's direction, refined so that the centres of thin
   slices (``SLICES_PER_BIN``, circle fits) lie on it: a pipe's axis, not the robot's heading;
2. the cross-section: the median distance from that centre line per ``SECTORS`` angular
   sector, of both passes together (a circle, a horseshoe, a floor: any star-shaped section);
3. the wall thickness: the RMS of the points' radial residuals about that profile, residuals
   beyond ``GATE_FRACTION`` of the radius dropped (clutter, not wall). Passes offset by ``d``
   put their points ``d / 2`` either side of it, so thickness ~ sqrt(noise^2 + d^2 / 4).

The same procedure on each pass alone (its own centre line and profile) gives the noise
floor: what the wall measures when no second pass can disagree with it. Only the lateral
and angular misalignment shows: in a uniform corridor an axial offset moves the wall along
itself (the degeneracy DeCOD exists for), so the figure is blind to the axial error except
where joints and features change the section. It complements ground truth; it does not
replace it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from decod_rs.maps import OUTBOUND, RETURN, MapCloud

FloatArray = NDArray[np.float64]

__all__ = ["BIN_M", "Consistency", "map_consistency", "outbound_path", "point_chainage"]

#: Bin length along the corridor, metres (the issue's "per metre of corridor").
BIN_M = 1.0
#: Thin slices per bin for the centre line: 8, or fewer so that a slice spans at least
#: ``SLICE_VOXELS`` map voxels (thinner slices hold partial rings whose circle fits wander: on
#: the simulated shield tunnel at 0.165 m voxels, 8 slices per metre made one pass's wall
#: 60-190 mm thick against 25 mm with whole rings).
SLICES_PER_BIN = 8
SLICE_VOXELS = 4
#: Largest tilt of the centre line against the path (rad): the robot drives along the
#: corridor, a steeper fit is a bad fit.
MAX_TILT = 0.1
#: Angular sectors of the cross-section profile (5 deg: 2.6 cm of arc in a 0.3 m pipe, 26 cm
#: in a 3 m tunnel, where a horseshoe's radius changes by < 1 % within a sector).
SECTORS = 72
#: A point farther than this fraction of the radius from the profile is not wall.
GATE_FRACTION = 0.5
#: Points per pass for a bin to count: a few slices' worth of circle fits.
MIN_POINTS_PER_PASS = 200
#: Points for a slice's circle fit.
MIN_SLICE_POINTS = 12
#: Points kept per bin and pass (evenly strided): the RMS of 1 000 residuals is within 2.2 %
#: (one sigma) of the RMS of all of them, and the figure costs ~25 ms per map and 15 m.
MAX_POINTS_PER_GROUP = 1000
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
        """The report's numbers: medians in millimetres, bins, and the profile per bin."""

        def mm(v: float | None) -> float | None:
            return None if v is None else round(1e3 * v, 3)

        def per_bin(a: FloatArray) -> list[float | None]:
            return [None if not np.isfinite(v) else round(1e3 * float(v), 3) for v in a]

        return {
            "median_overlap_mm": mm(self.median_m("overlap")),
            "mean_overlap_mm": mm(self.mean_m()),
            "median_outbound_floor_mm": mm(self.median_m("outbound")),
            "median_return_floor_mm": mm(self.median_m("return")),
            "overlap_bins": self.overlap_bins,
            "bins": int(self.chainage_m.size),
            "chainage_m": [round(float(c), 3) for c in self.chainage_m],
            "overlap_mm": per_bin(self.overlap_m),
            "outbound_floor_mm": per_bin(self.outbound_m),
            "return_floor_mm": per_bin(self.return_m),
        }


def outbound_path(stamps: FloatArray, poses: FloatArray, split_stamp: float | None) -> FloatArray:
    """Positions (P, 3) of the outbound leg (all of it without a return)."""
    keep = np.ones(stamps.shape, dtype=bool) if split_stamp is None else stamps <= split_stamp
    return np.asarray(poses, dtype=np.float64)[keep, :3, 3]


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


def point_chainage(
    cloud: MapCloud, anchor_positions: FloatArray, path: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Chainage (N,) of each map point along ``path`` (the outbound positions, P x 3) and the
    path's tangent there (N, 3). Each point is projected through the path sample nearest to
    the anchor of the submap that saw it (``anchor_positions`` K x 3): linear within a
    submap's reach, and K x P distances instead of N x P."""
    arclength, tangent = _path_frame(path)
    nearest_to_anchor = np.empty(anchor_positions.shape[0], dtype=np.int64)
    for start in range(0, anchor_positions.shape[0], 256):
        block = anchor_positions[start : start + 256]
        d2 = ((block[:, None, :] - path[None, :, :]) ** 2).sum(axis=2)
        nearest_to_anchor[start : start + 256] = np.argmin(d2, axis=1)
    nearest = nearest_to_anchor[cloud.submap]
    along = np.einsum("ij,ij->i", cloud.points - path[nearest], tangent[nearest])
    return arclength[nearest] + along, tangent[nearest]


def _group_mean(values: FloatArray, group: NDArray[np.int64], n: int) -> FloatArray:
    """Mean of ``values`` (N, C) per group (n, C); 0 for empty groups."""
    counts = np.maximum(np.bincount(group, minlength=n), 1)
    cols = [np.bincount(group, weights=values[:, c], minlength=n) for c in range(values.shape[1])]
    return np.column_stack(cols) / counts[:, None]


def _basis(axis: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Unit vectors (G, 3) completing each axis (G, 3) to a right-handed frame."""
    helper = np.where(np.abs(axis[:, 2:3]) < 0.9, [0.0, 0.0, 1.0], [1.0, 0.0, 0.0])
    e1 = np.cross(axis, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return e1, np.cross(axis, e1)


def _slice_centres(
    xy: FloatArray, u: FloatArray, group: NDArray[np.int64], n: int, slices: int
) -> tuple[FloatArray, FloatArray]:
    """Per group, the least-squares line through the centres of ``slices`` thin
    slices along ``u`` (algebraic circle fits from batched moments): intercept (n, 2) and
    slope (n, 2) of the centre as a function of ``u``; zero where no slice has a fit."""
    u_min = np.full(n, np.inf)
    u_max = np.full(n, -np.inf)
    np.minimum.at(u_min, group, u)
    np.maximum.at(u_max, group, u)
    span = np.maximum(u_max - u_min, 1e-9)[group]
    sl = np.minimum(((u - u_min[group]) / span * slices).astype(np.int64), slices - 1)
    sid = group * slices + sl
    m = n * slices
    x, y = xy[:, 0], xy[:, 1]
    b = x * x + y * y
    mom = [
        np.bincount(sid, weights=w, minlength=m)
        for w in (x * x, x * y, x, y * y, y, b * x, b * y, b)
    ]
    count = np.bincount(sid, minlength=m).astype(np.float64)
    a = np.stack(
        [
            np.stack([mom[0], mom[1], mom[2]], 1),
            np.stack([mom[1], mom[3], mom[4]], 1),
            np.stack([mom[2], mom[4], count], 1),
        ],
        1,
    )
    scale = np.maximum(mom[0] * mom[3] * count, 1e-300)
    ok = (count >= MIN_SLICE_POINTS) & (np.abs(np.linalg.det(a)) > 1e-9 * scale)
    sol = np.zeros((m, 3))
    sol[ok] = np.linalg.solve(a[ok], np.stack([mom[5], mom[6], mom[7]], 1)[ok][..., None])[..., 0]
    centre = sol[:, :2] / 2.0
    us = np.bincount(sid, weights=u, minlength=m) / np.maximum(count, 1.0)
    g = np.repeat(np.arange(n), slices)
    w = ok.astype(np.float64)
    s1 = np.bincount(g, weights=w, minlength=n)
    su = np.bincount(g, weights=w * us, minlength=n)
    suu = np.bincount(g, weights=w * us * us, minlength=n)
    sc = np.column_stack([np.bincount(g, weights=w * centre[:, c], minlength=n) for c in (0, 1)])
    suc = np.column_stack(
        [np.bincount(g, weights=w * us * centre[:, c], minlength=n) for c in (0, 1)]
    )
    den = s1 * suu - su * su
    line = (s1 >= 2) & (den > 1e-12 * np.maximum(s1 * suu, 1e-30))
    slope = np.zeros((n, 2))
    slope[line] = (s1[line, None] * suc[line] - su[line, None] * sc[line]) / den[line, None]
    slope = np.clip(slope, -MAX_TILT, MAX_TILT)
    intercept = np.where(
        s1[:, None] > 0, (sc - slope * su[:, None]) / np.maximum(s1, 1.0)[:, None], 0.0
    )
    return intercept, slope


def _frame(
    points: FloatArray, group: NDArray[np.int64], axis: FloatArray, origin: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Per-group basis (e1, e2), axial coordinate ``u`` (N,) and transverse ``xy`` (N, 2)."""
    e1, e2 = _basis(axis)
    rel = points - origin[group]
    u = np.einsum("ij,ij->i", rel, axis[group])
    xy = np.column_stack(
        [np.einsum("ij,ij->i", rel, e1[group]), np.einsum("ij,ij->i", rel, e2[group])]
    )
    return e1, e2, u, xy


def _transverse(
    points: FloatArray, group: NDArray[np.int64], axis: FloatArray, n: int, slices: int
) -> FloatArray:
    """Coordinates (N, 2) of each point about its group's fitted centre line: the axis
    (n, 3) is tilted onto the slice centres' line and the fit repeated in that frame."""
    origin = _group_mean(points, group, n)
    e1, e2, u, xy = _frame(points, group, axis, origin)
    intercept, slope = _slice_centres(xy, u, group, n, slices)
    tilted = axis + slope[:, :1] * e1 + slope[:, 1:] * e2
    axis = tilted / np.linalg.norm(tilted, axis=1, keepdims=True)
    origin = origin + intercept[:, :1] * e1 + intercept[:, 1:] * e2
    _, _, u, xy = _frame(points, group, axis, origin)
    intercept, slope = _slice_centres(xy, u, group, n, slices)
    return np.asarray(xy - intercept[group] - slope[group] * u[:, None], dtype=np.float64)


def _thickness(
    points: FloatArray, group: NDArray[np.int64], axis: FloatArray, n: int, slices: int
) -> FloatArray:
    """RMS radial residual (n,) of each group's points about the group's own cross-section
    profile (median radius per sector about its centre line); NaN for empty groups."""
    xy = _transverse(points, group, axis, n, slices)
    rho = np.hypot(xy[:, 0], xy[:, 1])
    sector = ((np.arctan2(xy[:, 1], xy[:, 0]) + np.pi) / (2 * np.pi) * SECTORS).astype(np.int64)
    sid = group * SECTORS + np.clip(sector, 0, SECTORS - 1)
    order = np.lexsort((rho, sid))
    counts = np.bincount(sid, minlength=n * SECTORS)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    filled = counts > 0
    median = np.full(n * SECTORS, np.nan)
    median[filled] = rho[order][starts[filled] + (counts[filled] - 1) // 2]
    residual = rho - median[sid]
    # The gate's scale: each group's mean sector radius.
    med = np.where(filled, median, 0.0).reshape(n, SECTORS)
    sectors = filled.reshape(n, SECTORS).sum(axis=1)
    radius = med.sum(axis=1) / np.maximum(sectors, 1)
    inside = np.abs(residual) <= GATE_FRACTION * radius[group]
    sq = np.bincount(group[inside], weights=residual[inside] ** 2, minlength=n)
    k = np.bincount(group[inside], minlength=n)
    return np.where(k > 0, np.sqrt(sq / np.maximum(k, 1)), np.nan)


def _subsample(group: NDArray[np.int64], n: int) -> NDArray[np.int64]:
    """Indices keeping at most ~``MAX_POINTS_PER_GROUP`` evenly strided points per group."""
    order = np.argsort(group, kind="stable")
    counts = np.bincount(group, minlength=n)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    rank = np.arange(group.size) - starts[group[order]]
    stride = np.maximum(np.ceil(counts / MAX_POINTS_PER_GROUP).astype(np.int64), 1)
    return np.sort(order[rank % stride[group[order]] == 0])


def map_consistency(
    cloud: MapCloud,
    anchor_positions: FloatArray,
    path: FloatArray,
    voxel_m: float | None = None,
) -> Consistency:
    """Wall thickness per ``BIN_M`` of chainage along ``path`` (the map's outbound positions,
    P x 3) where both passes of ``cloud`` reach, and each pass's own floor (module doc).
    ``anchor_positions`` (K, 3): the submap anchors in the same trajectory; ``voxel_m``: the
    map's voxel (sets the slices per bin, ``SLICE_VOXELS``; None: ``SLICES_PER_BIN``)."""
    slices = SLICES_PER_BIN
    if voxel_m is not None and voxel_m > 0:
        slices = int(np.clip(BIN_M // (SLICE_VOXELS * voxel_m), 1, SLICES_PER_BIN))
    empty = np.zeros(0)
    points = {name: int(np.count_nonzero(cloud.pass_ == p)) for name, p in PASSES.items()}
    if cloud.points.shape[0] == 0 or path.shape[0] < 2:
        return Consistency(empty, empty, empty, empty, points)
    chainage, tangent = point_chainage(cloud, anchor_positions, path)
    lo = np.floor(chainage.min() / BIN_M) * BIN_M
    bins = ((chainage - lo) // BIN_M).astype(np.int64)
    n = int(bins.max()) + 1
    is_return = (cloud.pass_ == RETURN).astype(np.int64)
    both = np.bincount(bins * 2 + is_return, minlength=2 * n).reshape(n, 2)
    usable = np.all(both >= MIN_POINTS_PER_PASS, axis=1)
    keep = _subsample(bins * 2 + is_return, 2 * n)
    keep = keep[usable[bins[keep]]]
    b, ret, pts = bins[keep], is_return[keep], cloud.points[keep]
    axis = _group_mean(tangent[keep], b, n)
    norm = np.linalg.norm(axis, axis=1, keepdims=True)
    axis = np.where(norm > 1e-9, axis / np.maximum(norm, 1e-12), [1.0, 0.0, 0.0])
    overlap = _thickness(pts, b, axis, n, slices)
    axes = np.repeat(axis, 2, axis=0)
    per_pass = _thickness(pts, b * 2 + ret, axes, 2 * n, slices).reshape(n, 2)
    nan = np.where(usable, 0.0, np.nan)
    return Consistency(
        chainage_m=lo + BIN_M * (np.arange(n) + 0.5),
        overlap_m=overlap + nan,
        outbound_m=per_pass[:, 0] + nan,
        return_m=per_pass[:, 1] + nan,
        points=points,
    )
