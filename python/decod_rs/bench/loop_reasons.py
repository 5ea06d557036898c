"""What the loop selection dropped, and which loops tie a boundary to the one beside it: a
diagnostic of the generalisation matrix (:mod:`decod_rs.bench.matrix`).

Every ``loops.csv`` row with a candidate is placed with the ground truth as the evaluation
places it (:func:`decod_rs.evaluate.loop_geometry_errors`: the candidate's plane moved by the
verified axial offset, as the loop factor uses it), and counted by its reason (``accepted``
for the kept loops) as right or not at the fine tolerance. A selection that drops right
loops as ``inconsistent`` is too strict for the drift it meets: in the full tier, with the
allowance of 15 % per metre of the odometry's path, 168 of the 198 loops it dropped were
right (decisions.md, "A jointly consistent loop set").

The accepted loops whose verified axial offset exceeds twice the run's same-boundary radius
(``joints.LOOP_SHIFT_RADII``) are listed with the distance between their two views'
boundaries (the views' origins, not moved by the offset): a loop of two views of one
boundary has them together, a loop whose patches align a ring apart has them a ring apart,
and the registry must not join those tracks (decisions.md, "Boundary tracks").

``python -m decod_rs.bench.loop_reasons DIR`` reads a matrix output (``DIR/cells/*/*/run``
with the cell's ``sim/gt.tum``) and prints both tables in markdown.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from decod_rs.evaluate import loop_geometry_errors
from decod_rs.joints import ties_one_boundary
from decod_rs.run_files import LoopTable, read_loops_csv
from decod_rs.tum import read_tum

FloatArray = NDArray[np.float64]

__all__ = ["ReasonCounts", "ShiftedLoop", "count_reasons", "format_report", "main", "read_run"]

#: A loop is right when its boundary planes lie within this (m) along the axis: the
#: evaluation's fine tolerance (paper Sec. IV-B.3).
FINE_TOLERANCE_M = 0.3


@dataclass
class ReasonCounts:
    """Per reason (``accepted`` for the kept loops): rows with a candidate and the ground
    truth, and how many of them were right."""

    rows: dict[str, int] = field(default_factory=dict)
    right: dict[str, int] = field(default_factory=dict)

    def add(self, reason: str, right: bool) -> None:
        self.rows[reason] = self.rows.get(reason, 0) + 1
        self.right[reason] = self.right.get(reason, 0) + int(right)


@dataclass(frozen=True)
class ShiftedLoop:
    """An accepted loop whose verified axial offset is beyond twice the same-boundary
    radius: where it is, the offset and how far apart its two views' boundaries are."""

    run: str
    dz_m: float
    views_apart_m: float


def count_reasons(
    loops: LoopTable,
    gt: tuple[FloatArray, FloatArray],
    radius_m: float,
    counts: ReasonCounts,
    name: str = "",
) -> list[ShiftedLoop]:
    """Adds ``loops``' rows to ``counts`` (module docs) and returns its accepted loops whose
    offset ties them beside their candidate's boundary (``radius_m``: the run's
    ``matching.duplicate_radius_m``)."""
    supported, axial, _ = loop_geometry_errors(loops, *gt)
    reasons = loops.extra.get("reason", [""] * len(loops))
    dz = np.array([float(v) if v else 0.0 for v in loops.extra.get("dz_m", [""] * len(loops))])
    _, apart, _ = loop_geometry_errors(loops, *gt, db_origin=loops.db_origin)
    shifted = []
    for k in range(len(loops)):
        if not supported[k] or not np.isfinite(axial[k]):
            continue
        reason = "accepted" if loops.accepted[k] else (reasons[k] or "rejected")
        counts.add(reason, bool(axial[k] <= FINE_TOLERANCE_M))
        if loops.accepted[k] and not ties_one_boundary(dz[k], radius_m):
            shifted.append(ShiftedLoop(name, float(dz[k]), float(apart[k])))
    return shifted


def read_run(run: Path, gt_path: Path) -> tuple[LoopTable, tuple[FloatArray, FloatArray], float]:
    """A run directory's loops, the ground truth and the run's same-boundary radius."""
    report = json.loads((run / "report.json").read_text(encoding="utf-8"))
    radius = float(report["config"]["matching"]["duplicate_radius_m"])
    return read_loops_csv(run / "loops.csv"), read_tum(gt_path), radius


def format_report(counts: ReasonCounts, shifted: Iterable[ShiftedLoop]) -> str:
    """Both tables (module docs) in markdown."""
    lines = [
        f"| reason | loops with a candidate | right at {FINE_TOLERANCE_M} m |",
        "| --- | --- | --- |",
    ]
    for reason in sorted(counts.rows, key=lambda r: (r != "accepted", r)):
        lines.append(f"| {reason} | {counts.rows[reason]} | {counts.right[reason]} |")
    rows = sorted(shifted, key=lambda s: (s.run, s.dz_m))
    lines += [
        "",
        f"{len(rows)} accepted loops with an offset beyond twice the same-boundary radius:",
        "",
        "| run | offset m | views apart m |",
        "| --- | --- | --- |",
    ]
    lines += [f"| {s.run} | {s.dz_m:+.2f} | {s.views_apart_m:.2f} |" for s in rows]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m decod_rs.bench.loop_reasons", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument("matrix_dir", type=Path, help="a matrix output (DIR/cells/*/*/run)")
    args = parser.parse_args(argv)
    counts, shifted = ReasonCounts(), []
    runs = sorted(args.matrix_dir.glob("cells/*/*/run"))
    if not runs:
        parser.error(f"{args.matrix_dir}: no cells/*/*/run directory")
    for run in runs:
        gt_path = run.parent.parent / "sim" / "gt.tum"
        if not (run / "loops.csv").exists() or not gt_path.exists():
            continue
        loops, gt, radius = read_run(run, gt_path)
        name = f"{run.parent.parent.name} {run.parent.name}"
        shifted += count_reasons(loops, gt, radius, counts, name)
    print(format_report(counts, shifted))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
