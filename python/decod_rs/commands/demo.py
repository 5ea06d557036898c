"""``decod demo``: no arguments, no data. Simulates a hume concrete pipe driven out and back
by a crawler whose odometry drifts along the pipe, its scans taken over a sweep as a real
LiDAR takes them (each point at its own time, :mod:`decod_rs.sim.sweep`), runs DeCOD on the
log, evaluates the result against the simulator's ground truth, and prints before/after and
where the plots are.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from decod_rs.commands.evaluate import evaluate_and_report
from decod_rs.commands.run import print_outcome, print_summary

#: One-way length of the demo pipe: long enough for a dozen joints and metres of drift, short
#: enough that the whole demo takes well under a minute on two cores.
DEMO_LENGTH_M = 40.0


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo",
        help="simulate a drifting pipe inspection, correct it and evaluate (no data needed)",
    )
    p.add_argument(
        "-o", "--out", type=Path, default=Path("decod_demo"), help="default ./decod_demo"
    )
    p.add_argument("--seed", type=int, default=7)
    p.add_argument("--drift", default="3.0", help="odometry endpoint error, metres (default 3)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    # Imported here, not with the parser (every command's help would wait for them).
    from decod_rs.pipeline import run_log
    from decod_rs.sim import simulate

    out: Path = args.out
    t0 = time.perf_counter()
    print(f"1/3 simulating a hume pipe, {DEMO_LENGTH_M:.0f} m out and back, into {out}/sim")
    sim = simulate(
        "hume",
        out / "sim",
        seed=args.seed,
        length_m=DEMO_LENGTH_M,
        drift=float(args.drift),
        sweep=True,
        overwrite=True,
    )
    print(
        f"    {sim.n_scans} scans, {sim.log_size_bytes / 1e6:.0f} MB, odometry drifts "
        f"{sim.endpoint_error_m:.2f} m by the end"
    )
    print("2/3 running DeCOD (auto configuration: the pipe is measured, not assumed)")
    summary = run_log(sim.log_dir, out / "run", imu_topic="/imu")
    print_summary(summary)
    print_outcome(out / "run")
    print("3/3 evaluating against ground truth")
    result = evaluate_and_report(out / "run", sim.gt_tum, joints=sim.joints_json)
    traj = result["trajectory"]
    before, after = traj["odometry"]["endpoint_error_m"], traj["corrected"]["endpoint_error_m"]
    rmse_before, rmse_after = traj["odometry"]["rmse_m"], traj["corrected"]["rmse_m"]
    print(
        f"\nendpoint error {before:.3f} m -> {after:.3f} m, position RMSE "
        f"{rmse_before:.3f} m -> {rmse_after:.3f} m; "
        f"{summary.accepted} loops accepted of {summary.queries} queries; "
        f"total {time.perf_counter() - t0:.0f} s"
    )
    print(
        f"plots: {out / 'run' / 'trajectory.png'}, {out / 'run' / 'trajectory_vs_gt.png'}, "
        f"{out / 'run' / 'error_over_time.png'}"
    )
    (out / "demo.json").write_text(
        json.dumps(
            {
                "endpoint_before_m": before,
                "endpoint_after_m": after,
                "rmse_before_m": rmse_before,
                "rmse_after_m": rmse_after,
            }
        ),
        encoding="utf-8",
    )
    return 0
