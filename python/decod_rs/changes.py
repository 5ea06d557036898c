"""What changed since the survey (issue 12): ``changes.csv`` and ``changes.png``.

For every boundary matched across sessions (a kept cross-session pair: :class:`ChangePair`),
the normalised
descriptor difference after alignment (``_core.descriptor_change``, ``src/matching/change.rs``:
both fields normalised as the matcher sees them, the survey's view brought to the new one's
heading and verified offsets; 0 = identical, 1 = uncorrelated): over the whole descriptor
(``global_change``), and where the raw offsets differ most once the contour-fit terms are
removed (``local_change``, :func:`residual_difference`, :func:`local_change`: defects are
local). A joint is ranked by ``change``, how far it stands out from the run's typical joint
(:func:`joint_changes`). ``changes.csv`` lists the joints most
changed first with their chainage in the survey frame, the new joint id and the survey's;
joints the new run saw from one side of the boundary only (``two_sided`` 0,
:data:`MIN_SIDE_FRACTION`) follow the others: their difference is the viewpoint's.
"""

from __future__ import annotations

import csv
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from decod_rs import _core
from decod_rs._core import Landmark
from decod_rs.config import Config
from decod_rs.matching import matching_config_json
from decod_rs.survey import Survey

FloatArray = NDArray[np.float64]

CHANGES_COLUMNS = (
    "rank",
    "joint_id",
    "survey_joint_id",
    "chainage_m",
    "change",
    "global_change",
    "local_change",
    "cells",
    "inliers",
    "two_sided",
)

__all__ = [
    "CHANGES_COLUMNS",
    "ChangePair",
    "JointChange",
    "changes_summary",
    "joint_changes",
    "plot_changes",
    "read_changes_csv",
    "write_changes_csv",
]


@dataclass(frozen=True)
class JointChange:
    """One matched joint (:func:`joint_changes`): its ids, chainage (survey frame), the
    relative ``change`` (1 = the run's typical joint), its global normalised difference and
    local change, the mutually observed cells and inliers of its best observed pair, that
    pair's residual difference map (rows, cols, metres; NaN where not both observed), and
    whether it was judged on views of both sides of the boundary (``two_sided``; see
    :data:`MIN_SIDE_FRACTION`)."""

    joint_id: int
    survey_joint_id: int
    chainage_m: float
    change: float
    global_change: float
    local_change: float
    cells: int
    inliers: int
    difference: FloatArray
    two_sided: bool = True


#: Cells whose offset exceeds this fraction of the section's radius in either view are left
#: out of the residual difference (3 cm in a 0.3 m pipe: a 25 cm deep lateral connection
#: ranked first on the simulated hume pipe only because its interior looks different from
#: every distance).
WALL_FRACTION = 0.1
#: Blocks the local change is measured on: one row (z bin) by 16 columns (22 degrees),
#: about the size of a deposit or of a joint opened over part of its circumference.
BLOCK_COLS = 16
#: The local change is the mean of this many highest block scores.
TOP_BLOCKS = 3
#: A joint is judged on its pairs with at least this fraction of the cells of its best
#: observed pair (a far or partial view of one session differs from a near one by
#: incidence and shadows, not by change).
MIN_CELL_FRACTION = 0.5
#: A pair sees both sides of the boundary when each half of the rows (before and after the
#: boundary plane) holds at least this fraction of its compared cells. A joint is where two
#: segments meet: a step, a wider gap or a deposit beside it changes one side against the
#: other, and a view of one side only cannot show that. On the simulated hume re-inspection
#: such one-sided views (rims of lateral connections, and the displaced segment's second
#: joint, seen with 8 of its 1,476 compared cells on the displaced side) differ from the
#: survey by 0.15-0.25 (normalised), two-sided views of unchanged joints by 0.02-0.12: their
#: difference is the viewpoint's. Joints seen from one side only are listed after the others.
MIN_SIDE_FRACTION = 0.2


def residual_difference(
    query: Landmark, candidate: Landmark, heading_deg: float, dz_m: float, dp: float
) -> FloatArray:
    """The raw offsets' difference ``query - candidate`` (rows, cols, metres; NaN where not
    both observed), the candidate brought to the query's heading and offsets, minus the
    least-squares fit of what two contour fits of one unchanged surface can differ by:
    ``alpha(p) + z (beta1 n1(p) + beta2 n2(p))`` (Eq. 2 without ``gamma(z)``, since a change
    of the axial profile, such as a joint opening, is what we look for). Solved by
    alternating the column means and the two tilt coefficients (a few rounds converge: the
    tilt regressors are nearly orthogonal to column constants)."""
    c, m = candidate.descriptor, candidate.mask
    if heading_deg > 90.0:
        c, m = c[::-1, ::-1], m[::-1, ::-1]
    rows, cols = c.shape
    shift_z = round(dz_m / query.cell_z_m)
    shift_p = round(dp * cols)
    # Query row r compares with candidate row r + shift_z, columns rolled by shift_p.
    aligned = np.full((rows, cols), np.nan)
    lo, hi = max(0, -shift_z), min(rows, rows - shift_z)
    if lo < hi:
        rolled = np.roll(np.where(m, c, np.nan), -shift_p, axis=1)
        aligned[lo:hi] = rolled[lo + shift_z : hi + shift_z]
    diff = np.where(query.mask, query.descriptor, np.nan) - aligned
    # Cells far off the wall in either view (an opening, a pipe connection, a shadow edge)
    # differ with the viewpoint by centimetres: not a change of the wall.
    # Their rims too (one cell around): a rim's cell straddles wall and opening.
    limit = WALL_FRACTION * query.radius_m
    far = (np.abs(query.descriptor) > limit) | (np.abs(np.nan_to_num(aligned)) > limit)
    rim = far.copy()
    for axis in (0, 1):
        for step in (-1, 1):
            rim |= np.roll(far, step, axis=axis)
    diff[rim] = np.nan
    seen = np.isfinite(diff)
    x = np.where(seen, diff, 0.0)
    z = (np.arange(rows) - 0.5 * (rows - 1))[:, None] * np.ones((1, cols))
    tilt = np.stack(
        [np.where(seen, z * query.normal_e1, 0.0), np.where(seen, z * query.normal_e2, 0.0)]
    )
    count = np.maximum(seen.sum(axis=0), 1)
    regressors = tilt.reshape(2, -1)
    # Two unknowns: their normal equations, the same every round (640 pairs of a 64-beam
    # re-inspection: 0.75 -> 0.52 s with the rows shifted by slices, changes.csv identical);
    # a rank-deficient pair (a tilt regressor unseen) keeps the least squares' minimum norm.
    normal = regressors @ regressors.T
    solvable = abs(float(np.linalg.det(normal))) > 1e-12 * float(np.trace(normal)) ** 2
    beta = np.zeros(2)
    for _ in range(4):
        alpha = np.where(seen, x - np.tensordot(beta, tilt, 1), 0.0).sum(axis=0) / count
        y = np.where(seen, x - alpha[None, :], 0.0)
        if solvable:
            beta = np.linalg.solve(normal, regressors @ y.ravel())
        else:
            beta = np.linalg.lstsq(regressors.T, y.ravel(), rcond=None)[0]
    return np.where(seen, x - alpha[None, :] - np.tensordot(beta, tilt, 1), np.nan)


def local_change(residual: FloatArray) -> float:
    """How much the most changed blocks stand out: the mean of the ``TOP_BLOCKS`` highest
    block mean squares of ``residual`` (1 x ``BLOCK_COLS`` blocks, at least half observed)
    over the median block's. A deposit or a joint opened over part of its circumference
    covers a few blocks; averaged over the descriptor it hides in the sensor noise (the
    normalised difference of both moved from 0.10 to 0.105 on the simulated hume pipe)."""
    seen = np.isfinite(residual)
    rows, cols = residual.shape
    nb = cols // BLOCK_COLS
    sq = np.where(seen, residual, 0.0)[:, : nb * BLOCK_COLS] ** 2
    n = seen[:, : nb * BLOCK_COLS].reshape(rows, nb, BLOCK_COLS).sum(axis=2)
    energy = sq.reshape(rows, nb, BLOCK_COLS).sum(axis=2)
    ok = n >= BLOCK_COLS // 2
    if ok.sum() < 2 * TOP_BLOCKS:
        return float("nan")
    block = energy[ok] / n[ok]
    typical = float(np.median(block))
    if typical <= 0.0:
        return float("nan")
    return float(np.mean(np.sort(block)[::-1][:TOP_BLOCKS]) / typical)


@dataclass(frozen=True)
class ChangePair:
    """A new view ``index`` (into the run's landmarks) compared with survey landmark
    ``survey_index`` under ``heading_deg`` and the offsets ``dz_m``, ``dp`` (as in
    ``PairResult``), with its verified ``inliers``."""

    index: int
    survey_index: int
    heading_deg: float
    dz_m: float
    dp: float
    inliers: int


@dataclass(frozen=True)
class _View:
    """One compared pair of a joint."""

    cells: int
    inliers: int
    global_change: float
    local_change: float
    survey_joint_id: int
    difference: FloatArray
    two_sided: bool


def two_sided(residual: FloatArray) -> bool:
    """Whether both halves of the rows hold ``MIN_SIDE_FRACTION`` of the compared cells."""
    seen = np.isfinite(residual)
    half = seen.shape[0] // 2
    before, after = int(seen[:half].sum()), int(seen[seen.shape[0] - half :].sum())
    total = before + after
    return total > 0 and min(before, after) >= MIN_SIDE_FRACTION * total


def _view(
    pair: ChangePair, landmarks: Sequence[Landmark], survey: Survey, config: str
) -> _View | None:
    new_lm, survey_lm = landmarks[pair.index], survey.landmarks[pair.survey_index]
    args = (pair.heading_deg, pair.dz_m, pair.dp)
    value, cells, _ = _core.descriptor_change(new_lm, survey_lm, *args, config)
    residual = residual_difference(new_lm, survey_lm, *args)
    local = local_change(residual)
    if not (np.isfinite(value) and np.isfinite(local)):
        return None
    sj = int(survey.joint_ids[pair.survey_index])
    return _View(cells, pair.inliers, float(value), local, sj, residual, two_sided(residual))


def joint_changes(
    pairs: Sequence[ChangePair],
    survey: Survey,
    landmarks: Sequence[Landmark],
    joint_of: NDArray[np.int64],
    chainage_m: FloatArray,
    cfg: Config,
) -> list[JointChange]:
    """Per matched joint (module docs), most changed first.

    A joint is judged on its well-observed pairs (at least ``MIN_CELL_FRACTION`` of the
    cells of its best observed one): the median of their normalised differences
    (``global_change``) and of their local changes (``local_change``). On the simulated
    hume pipe one unchanged joint gave local changes from 4 to 12 over its pairs (a forward
    looking sensor's view depends on its distance: incidence, shadows), so one pair says
    little. ``change`` is how far the joint stands out from the run's typical joint: the
    larger of its two values over their medians across the matched joints (1 = typical; a
    displaced segment moves the global value, a deposit or a locally opened joint the local
    one)."""
    config = matching_config_json(cfg)
    per_joint: dict[int, list[_View]] = {}
    for pair in pairs:
        view = _view(pair, landmarks, survey, config)
        if view is not None:
            per_joint.setdefault(int(joint_of[pair.index]), []).append(view)
    judged = {jid: _judge(views) for jid, views in per_joint.items()}
    # The typical joint: over the joints seen from both sides (all of them if none is).
    reference = [j for j in judged.values() if j[2].two_sided] or list(judged.values())
    typical_g = float(np.median([j[0] for j in reference])) if reference else 1.0
    typical_l = float(np.median([j[1] for j in reference])) if reference else 1.0
    out = [
        JointChange(
            joint_id=jid,
            survey_joint_id=best.survey_joint_id,
            chainage_m=float(np.median(chainage_m[joint_of == jid])),
            change=max(g / (typical_g or 1.0), lc / (typical_l or 1.0)),
            global_change=g,
            local_change=lc,
            cells=best.cells,
            inliers=best.inliers,
            difference=best.difference,
            two_sided=best.two_sided,
        )
        for jid, (g, lc, best) in judged.items()
    ]
    out.sort(key=lambda c: (not c.two_sided, -c.change))
    return out


def _judge(views: list[_View]) -> tuple[float, float, _View]:
    """A joint's global and local change and its best view: over its two-sided views if it
    has any (else over all), those with at least ``MIN_CELL_FRACTION`` of the cells of the
    best observed one."""
    views = [v for v in views if v.two_sided] or views
    most = max(v.cells for v in views)
    good = [v for v in views if v.cells >= MIN_CELL_FRACTION * most]
    best = max(good, key=lambda v: (v.cells, v.inliers))
    return (
        float(np.median([v.global_change for v in good])),
        float(np.median([v.local_change for v in good])),
        best,
    )


def write_changes_csv(path: str | Path, changes: Sequence[JointChange]) -> None:
    """``changes.csv`` with ``CHANGES_COLUMNS``, most changed first."""
    with Path(path).open("w", encoding="utf-8", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(CHANGES_COLUMNS)
        for rank, c in enumerate(changes, start=1):
            w.writerow(
                [
                    rank,
                    c.joint_id,
                    c.survey_joint_id,
                    f"{c.chainage_m:.4f}",
                    f"{c.change:.4f}",
                    f"{c.global_change:.6f}",
                    f"{c.local_change:.6f}",
                    c.cells,
                    c.inliers,
                    int(c.two_sided),
                ]
            )


def plot_changes(path: str | Path, changes: Sequence[JointChange], top: int = 3) -> None:
    """``changes.png``: the change of every matched joint along the chainage (the ``top``
    most changed labelled with their survey joint ids), and the difference maps of those."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shown = list(changes[:top])
    fig = plt.figure(figsize=(10, 3.2 + 1.6 * max(len(shown), 1)))
    grid = fig.add_gridspec(1 + len(shown), 1, height_ratios=[2.0] + [1.0] * len(shown))
    ax = fig.add_subplot(grid[0])
    chain = np.array([c.chainage_m for c in changes])
    value = np.array([c.change for c in changes])
    ax.vlines(chain, 0.0, value, color="0.6")
    ax.plot(chain, value, "o", color="tab:blue")
    for c in shown:
        ax.annotate(f"joint {c.survey_joint_id}", (c.chainage_m, c.change), color="tab:red")
        ax.plot([c.chainage_m], [c.change], "o", color="tab:red")
    ax.set_xlabel("chainage in the survey frame [m]")
    ax.set_ylabel("change (1 = typical joint)")
    ax.set_title("change since the survey, per matched joint (most changed in red)")
    for n, c in enumerate(shown, start=1):
        axd = fig.add_subplot(grid[n])
        lim = float(np.nanmax(np.abs(c.difference))) if np.isfinite(c.difference).any() else 1.0
        axd.imshow(
            c.difference * 1e3, aspect="auto", cmap="RdBu_r", vmin=-lim * 1e3, vmax=lim * 1e3
        )
        axd.set_ylabel("z bin")
        axd.set_title(
            f"survey joint {c.survey_joint_id} at {c.chainage_m:.2f} m: change {c.change:.2f} "
            "(new - survey offsets, contour terms removed, mm)",
            fontsize=9,
        )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def changes_summary(changes: Sequence[JointChange], top: int = 5) -> dict[str, object]:
    """The ``report.json`` section: how many joints were compared and the most changed."""
    return {
        "joints_compared": len(changes),
        "most_changed": [
            {
                "survey_joint_id": c.survey_joint_id,
                "joint_id": c.joint_id,
                "chainage_m": round(c.chainage_m, 4),
                "change": round(c.change, 4),
            }
            for c in changes[:top]
        ],
        "median_change": float(np.median([c.change for c in changes])) if changes else None,
    }


def read_changes_csv(path: str | Path) -> list[dict[str, str]]:
    """``changes.csv`` rows as dicts (strings), in file order."""
    with Path(path).open(encoding="utf-8", newline="") as fh:
        return list(csv.DictReader(fh))
