"""The detection's own error against the range it saw a boundary from: a diagnostic of the
generalisation matrix (:mod:`decod_rs.bench.matrix`).

Each view (a ``landmarks.csv`` row) is placed with the ground-truth pose of its anchor, so its
axial error against the nearest true joint is the detection's alone, with no trajectory in
it. Its signed range ``d`` is the joint's axial distance from the view's anchor, positive
ahead along the corridor's axis. A detection that places boundaries farther from the sensor
in proportion to range (error ``beta * d``) makes every displacement the boundary tracks
measure between two anchors ``1 + beta`` times the true one, whichever anchors see it: the
tracks then give the odometry's scale off by ``beta`` (:mod:`decod_rs.odometry_scale`), and
the loops cannot tell, since both passes get the same. The corrected trajectory comes out
stretched by ``beta``. This module measures ``beta`` (``view_bias_slope_percent``) and the
median error per range band (``view_bias_cm_by_range``), so that a matrix shows it beside
the far-end error it explains.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Sequence
from itertools import pairwise
from typing import Any

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

#: Edges (m) of the signed-range bands: behind the anchor (negative) and ahead of it.
RANGE_EDGES_M = (-6.0, -3.0, -1.0, 1.0, 3.0, 6.0)
#: Fewer views than this give no figure (a band's median, a slope).
MIN_VIEWS = 5
#: The slope's fit leaves out views farther off the line than this many robust sigmas ...
TRIM_SIGMAS = 3.0
#: ... or than this (m), whichever is larger.
TRIM_FLOOR_M = 0.01
#: A slope needs the middle half of the views' ranges to span at least this (m).
MIN_RANGE_SPREAD_M = 1.0

__all__ = ["MIN_VIEWS", "RANGE_EDGES_M", "band_labels", "format_section", "view_bias"]


def band_labels() -> list[str]:
    """The bands of :data:`RANGE_EDGES_M` as text: ``< -6``, ``-6..-3``, ..., ``>= 6`` (m)."""
    edges = [f"{e:g}" for e in RANGE_EDGES_M]
    inner = [f"{a}..{b}" for a, b in pairwise(edges)]
    return [f"< {edges[0]}", *inner, f">= {edges[-1]}"]


def view_bias(
    view_x: FloatArray, anchor_x: FloatArray, joints_x: FloatArray, tolerance_m: float
) -> dict[str, Any]:
    """The views' axial errors against the joints, by signed range (module doc).

    ``view_x`` and ``anchor_x``: each view's and its anchor's axial position with the ground
    truth's poses (m, the same views in the same order); ``joints_x``: the true joints. A
    view farther than ``tolerance_m`` from every joint is a wall feature's and is left out.
    Returns ``view_bias_views`` (views counted), ``view_bias_slope_percent`` (the slope of
    the error on the range, %, robust to the views of other features: :func:`_robust_slope`)
    and ``view_bias_cm_by_range`` (the median error
    in each band of :func:`band_labels`, cm; ``None`` under :data:`MIN_VIEWS` views)."""
    view_x = np.asarray(view_x, dtype=np.float64)
    anchor_x = np.asarray(anchor_x, dtype=np.float64)
    joints = np.asarray(joints_x, dtype=np.float64)
    if view_x.shape != anchor_x.shape:
        raise ValueError(f"view_x {view_x.shape} and anchor_x {anchor_x.shape} differ in shape")
    bands: list[float | None] = [None] * (len(RANGE_EDGES_M) + 1)
    empty = {"view_bias_views": 0, "view_bias_slope_percent": None, "view_bias_cm_by_range": bands}
    if view_x.size == 0 or joints.size == 0:
        return empty
    nearest = joints[np.argmin(np.abs(view_x[:, None] - joints[None, :]), axis=1)]
    error = view_x - nearest
    keep = np.abs(error) <= tolerance_m
    error, d = error[keep], (nearest - anchor_x)[keep]
    if error.size == 0:
        return empty
    band = np.searchsorted(np.asarray(RANGE_EDGES_M), d, side="right")
    for b in range(len(bands)):
        inside = error[band == b]
        if inside.size >= MIN_VIEWS:
            bands[b] = float(100.0 * np.median(inside))
    return {
        "view_bias_views": int(error.size),
        "view_bias_slope_percent": _robust_slope(d, error),
        "view_bias_cm_by_range": bands,
    }


def _robust_slope(d: FloatArray, error: FloatArray) -> float | None:
    """The slope (%) of ``error`` on ``d`` by least squares, twice refitted without the views
    more than :data:`TRIM_SIGMAS` robust sigmas (at least :data:`TRIM_FLOOR_M`) off the line:
    a wall feature's view 0.15-0.26 m from a joint, or a twin band's 0.2 m, is not the
    detection's range error. ``None`` under :data:`MIN_VIEWS` views or when the middle half
    of their ranges spans less than :data:`MIN_RANGE_SPREAD_M` (a forward sensor in a pipe
    sees its joints from 0-1.5 m: a slope over that, with one view in ten another feature's
    at +-0.2 m, is noise)."""
    keep = np.ones(d.size, dtype=bool)
    coef = None
    for _ in range(3):
        if int(keep.sum()) < MIN_VIEWS or _spread(d[keep]) < MIN_RANGE_SPREAD_M:
            return None
        design = np.stack([np.ones(int(keep.sum())), d[keep]], axis=1)
        coef = np.linalg.lstsq(design, error[keep], rcond=None)[0]
        residual = error - (coef[0] + coef[1] * d)
        spread = 1.4826 * float(np.median(np.abs(residual[keep] - np.median(residual[keep]))))
        keep = np.abs(residual) <= max(TRIM_SIGMAS * spread, TRIM_FLOOR_M)
    return None if coef is None else float(100.0 * coef[1])


def _spread(d: FloatArray) -> float:
    """The interquartile range of ``d``."""
    q1, q3 = np.percentile(d, [25.0, 75.0])
    return float(q3 - q1)


def format_section(rows: Sequence[dict[str, Any]]) -> list[str]:
    """``matrix.md``'s section: per scene, sensor and variant, over its rows, the slope (median
    and range) and each band's median error (median over the rows that have one), beside the
    corrected far-end error the slope stretches."""
    groups: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for r in rows:
        if r.get("view_bias_slope_percent") is not None:
            label = f"{r['scene']}, {r['sensor']}" + (f", {r['variant']}" if r["variant"] else "")
            groups[label].append(r)
    if not groups:
        return []
    labels = band_labels()
    lines = [
        "## Detection error against range",
        "",
        "Views placed with the ground truth, their axial error against the nearest joint by the "
        "joint's signed distance from the view's anchor (m, positive ahead): a slope stretches "
        "the corrected trajectory by as much (`decod_rs.bench.detection_bias`).",
        "",
        "| scene, sensor | rows | views | slope % (median, range) | far-end corrected % | "
        + " | ".join(f"{b} m: cm" for b in labels)
        + " |",
        "| --- " * (5 + len(labels)) + "|",
    ]
    for label, group in sorted(groups.items()):
        slopes = [float(r["view_bias_slope_percent"]) for r in group]
        far = [
            r["turnaround_corr_percent"]
            for r in group
            if r.get("turnaround_corr_percent") is not None
        ]
        cells = []
        for b in range(len(labels)):
            values = [r["view_bias_cm_by_range"][b] for r in group]
            found = [float(v) for v in values if v is not None]
            cells.append(f"{np.median(found):+.1f}" if found else "-")
        far_text = f"{np.median(far):+.2f}" if far else "-"
        lines.append(
            f"| {label} | {len(group)} | {sum(int(r['view_bias_views']) for r in group)} | "
            f"{np.median(slopes):+.2f} ({min(slopes):+.2f} to {max(slopes):+.2f}) | {far_text} | "
            + " | ".join(cells)
            + " |"
        )
    return lines
