"""The true misalignment across the wall in a simulated run's maps: what the map-consistency
figure (:mod:`decod_rs.map_quality`) estimates without ground truth (issue 13).

Every map point was placed by the pose of the submap that first saw it (``time`` in the PLY:
that submap's anchor stamp). With the ground truth at the same stamp its true position is
``p_true = T_true T_est^-1 p``, and its error ``p - p_true``. The simulated corridors run along
world x, where the axial error is invisible to a wall, so only the error's y and z count.
In cells of the *true* positions (``CELL_VOXELS`` map voxels, where both passes saw the same
wall) the error is projected on the wall's true normal (the smallest principal axis of the
cell's true points); the passes' mean errors differ by the misalignment ``d``, and a point of
the map sits ``d / 2`` from the wall both passes would agree on. Per bin of chainage (the
figure's bins): the RMS of ``d / 2`` over the points, next to the figure computed from the
same PLY.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from decod_rs.map_quality import (
    BIN_M,
    CELL_VOXELS,
    MIN_CELL_POINTS,
    map_consistency,
    outbound_path,
    point_chainage,
)
from decod_rs.maps import MapCloud, anchor_poses
from decod_rs.tum import interpolate_poses, read_tum

FloatArray = NDArray[np.float64]

__all__ = ["wall_truth"]


def _cloud(run: Path, name: str) -> tuple[MapCloud, FloatArray, FloatArray, FloatArray]:
    """The map ``name`` read back from its PLY, with its submap anchors (K,), and the run's
    scan stamps (N,) and poses (N, 4, 4) of that trajectory."""
    from plyfile import PlyData  # the dev extra

    v = PlyData.read(str(run / f"map_{name}.ply"))["vertex"].data
    stamps, poses = read_tum(run / f"{name}.tum")
    times, submap = np.unique(np.asarray(v["time"]), return_inverse=True)
    anchors = times.astype(np.float64) + stamps[0]
    points = np.column_stack([v["x"], v["y"], v["z"]]).astype(np.float64)
    cloud = MapCloud(
        points,
        np.asarray(v["pass"], dtype=np.uint8),
        submap.astype(np.uint32).ravel(),
        anchors[submap.ravel()],
        np.asarray(v["count"], dtype=np.uint32),
    )
    return cloud, anchors, stamps, poses


def _half_misalignment(
    cloud: MapCloud, error: FloatArray, true_points: FloatArray, cell_m: float
) -> FloatArray:
    """Per point: half the passes' mean error difference along the true wall normal of its
    true cell; NaN where the cell lacks one of the passes."""
    key = np.floor(true_points / cell_m).astype(np.int64)
    _, cell = np.unique(key, axis=0, return_inverse=True)
    cell = cell.ravel()
    m = int(cell.max()) + 1
    ps = cloud.pass_.astype(np.int64)
    count = np.bincount(cell * 2 + ps, minlength=2 * m).reshape(m, 2)
    size = np.maximum(count.sum(axis=1), 1)
    mean = np.column_stack([np.bincount(cell, true_points[:, i], m) for i in range(3)])
    d = true_points - (mean / size[:, None])[cell]
    scatter = np.empty((m, 3, 3))
    for i in range(3):
        for j in range(3):
            scatter[:, i, j] = np.bincount(cell, d[:, i] * d[:, j], m)
    normal = np.linalg.eigh(scatter)[1][:, :, 0]
    e = np.einsum("ij,ij->i", error, normal[cell])
    sums = np.bincount(cell * 2 + ps, weights=e, minlength=2 * m).reshape(m, 2)
    per_pass = sums / np.maximum(count, 1)
    half = 0.5 * (per_pass[:, 1] - per_pass[:, 0])
    ok = np.all(count >= MIN_CELL_POINTS, axis=1)
    return np.where(ok, half, np.nan)[cell]


def wall_truth(sim: Path, run: Path, name: str) -> dict[str, object]:
    """For the map ``name`` (``odometry``/``corrected``) of ``run`` on the simulation
    ``sim``: per bin the figure and the true half-misalignment (metres), their medians over
    the bins both have, and their Pearson correlation along the corridor."""
    report = json.loads((run / "report.json").read_text())
    cloud, anchors, stamps, poses = _cloud(run, name)
    gt_stamps, gt = read_tum(sim / "gt.tum")
    est = anchor_poses(anchors, stamps, poses)
    true = interpolate_poses(gt_stamps, gt, np.clip(anchors, gt_stamps[0], gt_stamps[-1]))
    true_from_est = true @ np.linalg.inv(est)
    t = true_from_est[cloud.submap]
    true_points = np.einsum("nij,nj->ni", t[:, :3, :3], cloud.points) + t[:, :3, 3]
    error = cloud.points - true_points
    error[:, 0] = 0.0  # along the corridor (world x): invisible to a wall
    voxel = float(report["map"]["voxel_m"])
    half = _half_misalignment(cloud, error, true_points, CELL_VOXELS * voxel)
    split = report["split_stamp"]
    path = outbound_path(stamps, poses, split)
    positions = est[:, :3, 3]
    figure = map_consistency(cloud, positions, path, voxel)
    chainage = point_chainage(cloud, positions, path)
    lo = np.floor(chainage.min() / BIN_M) * BIN_M
    bins = np.clip(((chainage - lo) // BIN_M).astype(np.int64), 0, figure.chainage_m.size - 1)
    ok = np.isfinite(half)
    n = figure.chainage_m.size
    sq = np.bincount(bins[ok], weights=half[ok] ** 2, minlength=n)
    k = np.bincount(bins[ok], minlength=n)
    truth = np.where(k > 0, np.sqrt(sq / np.maximum(k, 1)), np.nan)
    both = np.isfinite(truth) & np.isfinite(figure.overlap_m)
    corr = None
    if np.count_nonzero(both) >= 3 and np.std(truth[both]) > 0:
        corr = float(np.corrcoef(figure.overlap_m[both], truth[both])[0, 1])
    floor = figure.median_m("outbound")

    def median_mm(values: FloatArray) -> float | None:
        return 1e3 * float(np.median(values[both])) if both.any() else None

    return {
        "figure_median_mm": median_mm(figure.overlap_m),
        "floor_median_mm": None if floor is None else 1e3 * floor,
        "half_misalignment_median_mm": median_mm(truth),
        "along_corridor_r": corr,
        "bins": int(np.count_nonzero(both)),
    }
