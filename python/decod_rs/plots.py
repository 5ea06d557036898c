"""PNG figures of a run and its evaluation (matplotlib, Agg backend: no display needed).

* ``plot_trajectories``: odometry vs corrected (and ground truth if given), top view and the
  position along the corridor's main axis over time, accepted loops as lines between the
  query and database positions.
* ``plot_error_over_time``: position error of each estimate against time (paper Fig. 5b).
* ``plot_pr_curve``: precision against recall over the inlier threshold.
* ``plot_descriptor_pair``: two (rows, cols) descriptors side by side, unobserved cells grey;
  ``plot_descriptor_pairs`` several of them on one figure.
* ``plot_map_consistency``: wall thickness where the passes overlap along the corridor, before
  and after correction (``decod run --map``; no ground truth needed).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.axes import Axes
from matplotlib.collections import LineCollection
from matplotlib.ticker import FuncFormatter, NullFormatter
from numpy.typing import ArrayLike, NDArray

from decod_rs.map_quality import Consistency
from decod_rs.tum import check_poses, interpolate_poses

FloatArray = NDArray[np.float64]

__all__ = [
    "DescriptorPair",
    "plot_descriptor_pair",
    "plot_descriptor_pairs",
    "plot_error_over_time",
    "plot_map_consistency",
    "plot_pr_curve",
    "plot_trajectories",
]

_COLOURS = {"ground truth": "0.2", "odometry": "tab:red", "corrected": "tab:blue"}


def _save(fig: Any, path: str | Path, tight: bool = True) -> Path:
    """``tight=False`` for a figure laid out with fixed margins (no second layout pass)."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    # zlib level 1: the figures are mostly flat colour (and the descriptors' noise does not
    # compress anyway); level 6 took 0.04 s of a 0.2 s descriptor figure.
    fig.savefig(
        out, dpi=120, bbox_inches="tight" if tight else None, pil_kwargs={"compress_level": 1}
    )
    plt.close(fig)
    return out


def _main_axis(points: FloatArray) -> FloatArray:
    """Unit first principal direction of (N, 3) points (the corridor's main axis)."""
    centred = points - points.mean(axis=0)
    if points.shape[0] < 2 or not np.any(centred):
        return np.array([1.0, 0.0, 0.0])
    axis: FloatArray = np.linalg.svd(centred, full_matrices=False)[2][0]
    return axis if axis[np.argmax(np.abs(axis))] > 0 else -axis


def plot_trajectories(
    path: str | Path,
    stamps: ArrayLike,
    odometry: ArrayLike,
    corrected: ArrayLike,
    loops: Sequence[tuple[float, float]] = (),
    ground_truth: tuple[ArrayLike, ArrayLike] | None = None,
    unmeasured: Sequence[tuple[float, float]] = (),
    faces: Sequence[float] = (),
) -> Path:
    """Trajectory before/after: ``stamps`` (N,), ``odometry`` and ``corrected`` (N, 4, 4)
    ``world_from_body``; ``loops``: accepted (query_stamp, db_stamp) pairs, drawn between
    the two positions on each estimate; ``ground_truth``: optional (stamps, poses);
    ``unmeasured``: (from, to) stamps that only the odometry places (``decod_rs.unmeasured``),
    shaded on the along-the-corridor panel; ``faces``: stamps of the anchors an end-face
    factor ties (``decod_rs.end_faces``), marked on the corrected trajectory there."""
    st = np.asarray(stamps, dtype=np.float64)
    series: dict[str, tuple[FloatArray, FloatArray]] = {}
    if ground_truth is not None:
        series["ground truth"] = (
            np.asarray(ground_truth[0], dtype=np.float64),
            check_poses(ground_truth[1], "ground_truth"),
        )
    series["odometry"] = (st, check_poses(odometry, "odometry"))
    series["corrected"] = (st, check_poses(corrected, "corrected"))
    ref = series.get("ground truth", series["odometry"])[1][:, :3, 3]
    axis = _main_axis(ref)
    t0 = min(s[0] for s, _ in series.values())

    # Fixed margins, no constrained layout or tight bounding box: the figure of every run.
    fig, (top, along) = plt.subplots(2, 1, figsize=(10, 8))
    fig.subplots_adjust(left=0.08, right=0.98, bottom=0.065, top=0.96, hspace=0.25)
    for name, (s, p) in series.items():
        xyz = p[:, :3, 3]
        style = "--" if name == "ground truth" else "-"
        top.plot(xyz[:, 0], xyz[:, 1], style, color=_COLOURS[name], label=name, lw=1.2)
        along.plot(s - t0, xyz @ axis, style, color=_COLOURS[name], label=name, lw=1.2)
    for name in ("odometry", "corrected"):
        _draw_loops(top, along, *series[name], loops, name, (axis, t0))
    top.set_xlabel("x [m]")
    top.set_ylabel("y [m]")
    top.set_title("top view")
    top.axis("equal")
    top.legend(loc="best", fontsize=8)
    for k, (a, b) in enumerate(unmeasured):
        label = "odometry only (no loop or track)" if k == 0 else None
        along.axvspan(a - t0, b - t0, color="0.88", zorder=0, label=label)
    s, p = series["corrected"]
    seen = np.array([f for f in faces if s[0] <= f <= s[-1]], dtype=np.float64)
    if seen.size:
        where = interpolate_poses(s, p, seen)[:, :3, 3] @ axis
        along.plot(seen - t0, where, "k|", ms=12, mew=1.5, label="end face in view (factor)")
    along.set_xlabel("time [s]")
    along.set_ylabel("position along the main axis [m]")
    along.set_title("along the corridor")
    along.grid(alpha=0.3)
    along.legend(loc="best", fontsize=8)
    return _save(fig, path, tight=False)


def _draw_loops(
    top: Axes,
    along: Axes,
    s: FloatArray,
    p: FloatArray,
    loops: Sequence[tuple[float, float]],
    name: str,
    frame: tuple[FloatArray, float],
) -> None:
    """The loops within the span of trajectory ``name`` (stamps ``s``, poses ``p``) as dotted
    segments between the two positions, on the top view and along the axis (``frame``: the
    main axis and the time origin)."""
    axis, t0 = frame
    usable = [(q, d) for q, d in loops if s[0] <= min(q, d) and max(q, d) <= s[-1]]
    if not usable:
        return
    q_st = np.array([q for q, _ in usable])
    d_st = np.array([d for _, d in usable])
    pq = interpolate_poses(s, p, q_st)[:, :3, 3]
    pd = interpolate_poses(s, p, d_st)[:, :3, 3]
    # One collection per panel, not one line per loop: a 64-beam run keeps 200+ loops,
    # and 800 line artists took 2.6-3.5 s to draw (and to place the legend around).
    segments = {
        top: np.stack([pq[:, :2], pd[:, :2]], axis=1),
        along: np.stack(
            [np.column_stack([q_st - t0, pq @ axis]), np.column_stack([d_st - t0, pd @ axis])],
            axis=1,
        ),
    }
    for ax, lines in segments.items():
        ax.add_collection(
            LineCollection(
                list(lines),
                colors=_COLOURS[name],
                linewidths=0.6,
                linestyles=":",
                alpha=0.6,
                label=f"loops ({name})",
            )
        )


def plot_error_over_time(
    path: str | Path, errors: Mapping[str, tuple[ArrayLike, ArrayLike]]
) -> Path:
    """Position error against time: ``errors`` maps a label to (stamps (K,), errors_m (K,))."""
    fig, ax = plt.subplots(figsize=(10, 4), layout="constrained")
    t0 = min(float(np.min(s)) for s, _ in errors.values()) if errors else 0.0
    for name, (s, e) in errors.items():
        ax.plot(np.asarray(s) - t0, e, color=_COLOURS.get(name), label=name, lw=1.2)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("position error [m]")
    ax.set_title("position error against ground truth")
    ax.grid(alpha=0.3)
    ax.legend(loc="best")
    return _save(fig, path)


def plot_pr_curve(
    path: str | Path,
    curves: Mapping[str, Sequence[Mapping[str, Any]]],
) -> Path:
    """Precision against recall over the inlier threshold: ``curves`` maps a label (e.g.
    ``"0.30 m"``) to the ``pr_curve`` points (dicts with ``recall``, ``precision``,
    ``min_inliers``)."""
    fig, ax = plt.subplots(figsize=(5.5, 5), layout="constrained")
    for name, points in curves.items():
        pts = [p for p in points if p["recall"] is not None and p["precision"] is not None]
        if not pts:
            continue
        r = [p["recall"] for p in pts]
        pr = [p["precision"] for p in pts]
        ax.plot(r, pr, "o-", ms=3, label=name)
        for p in pts[:: max(1, len(pts) // 6)]:
            ax.annotate(f"K={p['min_inliers']}", (p["recall"], p["precision"]), fontsize=7)
    ax.set_xlim(0.0, 1.02)
    ax.set_ylim(0.0, 1.02)
    ax.set_xlabel("Recall@1")
    ax.set_ylabel("Precision@1")
    ax.set_title("precision-recall over the inlier threshold K")
    ax.grid(alpha=0.3)
    ax.legend(loc="lower left")
    return _save(fig, path)


@dataclass(frozen=True)
class DescriptorPair:
    """One figure of :func:`plot_descriptor_pairs`: where it goes, the two (rows, cols)
    descriptors with their observed masks (True = observed) and its title."""

    path: str | Path
    query: ArrayLike
    query_mask: ArrayLike
    database: ArrayLike
    database_mask: ArrayLike
    title: str = ""


def _masked(pair: DescriptorPair) -> list[np.ma.MaskedArray[Any, Any]]:
    arrays = []
    for name, d, m in (
        ("query", pair.query, pair.query_mask),
        ("database", pair.database, pair.database_mask),
    ):
        da = np.asarray(d, dtype=np.float64)
        ma = np.asarray(m, dtype=bool)
        if da.ndim != 2 or ma.shape != da.shape:
            raise ValueError(
                f"plot_descriptor_pair: {name}: expected a (rows, cols) descriptor and a mask "
                f"of the same shape, got {da.shape} and {ma.shape}"
            )
        arrays.append(np.ma.masked_array(da, mask=~ma | ~np.isfinite(da)))
    return arrays


def plot_descriptor_pair(
    path: str | Path,
    query: ArrayLike,
    query_mask: ArrayLike,
    database: ArrayLike,
    database_mask: ArrayLike,
    title: str = "",
) -> Path:
    """Two descriptors (rows = axial bins z, cols = arclength bins p, e.g. (16, 256)) with
    their observed masks (same shape, True = observed) side by side on one colour scale
    (signed normal offset s, metres); unobserved cells grey."""
    pair = DescriptorPair(path, query, query_mask, database, database_mask, title)
    return plot_descriptor_pairs([pair])[0]


def plot_descriptor_pairs(pairs: Sequence[DescriptorPair]) -> list[Path]:
    """:func:`plot_descriptor_pair` for several pairs, drawn on one figure whose images,
    colour scale and title change from file to file (the same PNGs, byte for byte, as one
    figure each: four pairs 0.75 -> 0.54 s, a run draws four). Every pair is checked first."""
    masked = [_masked(pair) for pair in pairs]
    if not pairs:
        return []
    titled = any(pair.title for pair in pairs)
    top = 0.8 if titled else 0.88
    cmap = plt.get_cmap("RdBu_r").with_extremes(bad="0.6")
    # Fixed margins instead of a constrained layout and a tight bounding box (two layout
    # passes over every tick label): 0.48-0.60 -> 0.2 s a figure.
    fig, axes = plt.subplots(1, 2, figsize=(12, 3.4))
    fig.subplots_adjust(left=0.055, right=0.9, bottom=0.16, top=top, wspace=0.2)
    images = []
    for ax, arr, name in zip(axes, masked[0], ("query", "database"), strict=True):
        image = ax.imshow(arr, cmap=cmap, aspect="auto", interpolation="nearest", origin="lower")
        images.append(image)
        ax.set_title(name)
        ax.set_xlabel("arclength bin p (from the gravity direction)")
        ax.set_ylabel("axial bin z (boundary at the centre)")
    cax = fig.add_axes((0.915, 0.16, 0.012, top - 0.16))
    fig.colorbar(images[0], cax=cax, label="signed offset s [m]")
    heading = fig.suptitle("") if titled else None
    out = []
    for pair, arrays in zip(pairs, masked, strict=True):
        observed = [a.compressed() for a in arrays if a.count()]
        lim = float(np.max(np.abs(np.concatenate(observed)))) if observed else 1.0
        lim = lim or 1.0
        for ax, image, arr in zip(axes, images, arrays, strict=True):
            if arr.shape != image.get_array().shape:
                rows, cols = arr.shape
                image.set_extent((-0.5, cols - 0.5, -0.5, rows - 0.5))
                ax.set_xlim(-0.5, cols - 0.5)
                ax.set_ylim(-0.5, rows - 0.5)
            image.set_data(arr)
            image.set_clim(-lim, lim)
        if heading is not None:
            heading.set_text(pair.title)
        target = Path(pair.path)
        target.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(target, dpi=120, pil_kwargs={"compress_level": 1})
        out.append(target)
    plt.close(fig)
    return out


def plot_map_consistency(path: str | Path, figures: Mapping[str, Consistency]) -> Path:
    """Wall thickness where the outbound and return passes overlap (millimetres) against
    chainage along the outbound path (metres), one line per map (``"odometry"``,
    ``"corrected"``), with each pass's own thickness (the floor, dashed) of the corrected map;
    log scale when the lines span more than a factor 20."""
    # Fixed margins instead of a constrained layout and a tight bounding box: half the time
    # of a figure drawn at the end of every --map run.
    fig, ax = plt.subplots(figsize=(10, 4.2))
    fig.subplots_adjust(left=0.08, right=0.98, bottom=0.12, top=0.92)
    values = []
    for name, fig_data in figures.items():
        mm = 1e3 * fig_data.overlap_m
        median = fig_data.median_m()
        text = "no overlap" if median is None else f"median {1e3 * median:.1f} mm"
        ax.plot(
            fig_data.chainage_m,
            mm,
            "o-",
            ms=3,
            lw=1.2,
            color=_COLOURS.get(name),
            label=f"{name}: both passes ({text})",
        )
        values.append(mm[np.isfinite(mm)])
    floor_source = figures.get("corrected") or next(iter(figures.values()), None)
    if floor_source is not None:
        for which, style in (("outbound", "--"), ("return", ":")):
            ax.plot(
                floor_source.chainage_m,
                1e3 * getattr(floor_source, f"{which}_m"),
                style,
                color="0.45",
                lw=1.0,
                label=f"{which} pass alone (floor)",
            )
    finite = np.concatenate(values) if values else np.zeros(0)
    finite = finite[finite > 0]
    if finite.size and finite.max() / finite.min() > 20:
        ax.set_yscale("log")
        # Plain numbers, not mathtext powers (whose parser costs more than the figure).
        ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        ax.yaxis.set_minor_formatter(NullFormatter())
    ax.set_xlabel("chainage along the outbound path [m]")
    ax.set_ylabel("wall thickness (RMS about local planes) [mm]")
    # y fixed: no automatic placement above the axes' decorations (none on top here):
    # 0.083-0.088 instead of 0.091-0.110 s of CPU per figure (best 4 of 8, 40 bins).
    ax.set_title("map consistency without ground truth: the wall where the passes overlap", y=1.0)
    ax.grid(alpha=0.3)
    ax.legend(loc="upper right", fontsize=8)
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    # zlib level 1 instead of 6: 0.095 instead of 0.113 s of CPU per figure (measured on a
    # 60-bin figure), a PNG of about the same size (mostly flat colour).
    fig.savefig(out, dpi=120, pil_kwargs={"compress_level": 1})
    plt.close(fig)
    return out
