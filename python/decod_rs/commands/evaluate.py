"""``decod evaluate DIR --gt gt.tum [--joints joints.json] [--align]``: the paper's metrics
on a run directory (definitions in ``decod_rs.evaluate``); writes ``evaluation.json``,
``error_over_time.png``, ``pr_curve.png`` and ``trajectory_vs_gt.png`` into DIR (or
``--out``) and prints a table."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from decod_rs.config import PRESETS
from decod_rs.tum import read_tum


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "evaluate", help="Recall@1, Precision@1, PR curve and trajectory errors of a run"
    )
    p.add_argument("run_dir", metavar="DIR", type=Path, help="the output directory of `decod run`")
    p.add_argument("--gt", required=True, type=Path, help="ground-truth trajectory (TUM)")
    p.add_argument(
        "--joints", type=Path, help="simulator joints.json (`joints_x_m`): pipe tolerance"
    )
    p.add_argument(
        "--align",
        action="store_true",
        help="rigidly align each estimate to the ground truth (Umeyama) before the errors",
    )
    p.add_argument(
        "--preset", choices=PRESETS, help="tolerance rule (default: report.json's, else tunnel)"
    )
    p.add_argument(
        "--tolerances",
        nargs=2,
        type=float,
        metavar=("FINE", "COARSE"),
        help="axial tolerances in metres instead of the preset's",
    )
    p.add_argument("-o", "--out", type=Path, help="output directory (default: DIR)")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG figures")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    evaluate_and_report(
        args.run_dir,
        args.gt,
        joints=args.joints,
        align=args.align,
        preset=args.preset,
        tolerances=tuple(args.tolerances) if args.tolerances else None,
        out=args.out,
        plots=not args.no_plots,
    )
    return 0


def evaluate_and_report(
    run_dir: Path,
    gt: Path,
    *,
    joints: Path | None = None,
    align: bool = False,
    preset: str | None = None,
    tolerances: tuple[float, ...] | None = None,
    out: Path | None = None,
    plots: bool = True,
) -> dict[str, Any]:
    """Evaluate ``run_dir`` against ``gt``; write evaluation.json (+ plots) into ``out``
    (default: the run directory), print the table, and return the evaluation document."""
    # Imported here, not with the parser: GTSAM and matplotlib are not needed for help.
    from decod_rs.evaluate import evaluate_run, format_table
    from decod_rs.plots import plot_error_over_time, plot_pr_curve, plot_trajectories
    from decod_rs.run_files import read_loops_csv, within_run

    result, errors = evaluate_run(
        run_dir,
        gt,
        joints_path=joints,
        align=align,
        preset=preset,
        tolerances=(tolerances[0], tolerances[1]) if tolerances else None,
    )
    out = out or run_dir
    out.mkdir(parents=True, exist_ok=True)
    (out / "evaluation.json").write_text(json.dumps(result, indent=2), encoding="utf-8")
    print(format_table(result))
    written = [out / "evaluation.json"]
    if plots:
        written.append(
            plot_error_over_time(
                out / "error_over_time.png",
                {name: (m.stamps, m.errors_m) for name, m in errors.items()},
            )
        )
        written.append(
            plot_pr_curve(
                out / "pr_curve.png",
                {
                    f"{m['tolerance_m']:.2f} m": result["pr_curve"][name]
                    for name, m in result["loops"].items()
                },
            )
        )
        stamps, odom = read_tum(run_dir / "odometry.tum")
        c_stamps, corrected = read_tum(run_dir / "corrected.tum")
        if c_stamps.shape == stamps.shape and np.array_equal(c_stamps, stamps):
            loops = within_run(read_loops_csv(run_dir / "loops.csv"))
            pairs = [
                (float(q), float(d))
                for q, d, ok in zip(loops.query_stamp, loops.db_stamp, loops.accepted, strict=True)
                if ok
            ]
            written.append(
                plot_trajectories(
                    out / "trajectory_vs_gt.png",
                    stamps,
                    odom,
                    corrected,
                    pairs,
                    ground_truth=read_tum(gt),
                    unmeasured=_unmeasured(run_dir),
                )
            )
    print("wrote " + ", ".join(str(p) for p in written))
    return result


def _unmeasured(run_dir: Path) -> list[tuple[float, float]]:
    """The run's stretches that only the odometry places (``report.json`` ``unmeasured``;
    none for a run written before it existed)."""
    report = json.loads((run_dir / "report.json").read_text(encoding="utf-8"))
    section = report.get("unmeasured") or {}
    return [(float(s["from_stamp"]), float(s["to_stamp"])) for s in section.get("stretches", [])]
