"""What the map, its consistency figure and the 3D recording cost, and how well the figure
tracks the true error (issue 13).

``python -m decod_rs.bench.visuals --out DIR [--quick]``

**Cases** (:data:`CASES`): simulated out-and-back runs over pipes and a tunnel, at several
drift levels and seeds, each run twice: with loops (the corrected map) and ``--no-loops``
(corrected == odometry: a second "before" point on the same log).

**Overhead.** Per run, the seconds of the stages ``map`` (render both maps, PLYs, figure,
plot) and ``rerun`` (the recording) against the rest of ``run_log`` (``report.json``
``timings_s``, plots included), and the voxel map's share of the stream: the extraction
stage of ``_core.LogProcessor`` with and without the map (best of :data:`REPEATS`).

**Tracking.** Per map (odometry, corrected): the median wall thickness where the passes
overlap, against the ground truth's position RMSE, lateral RMSE (the error across the
corridor, world y and z: the simulated corridors run along world x) and the *pass
disagreement*: for every return scan, the lateral part of the difference between its error
and the error of the outbound scan nearest to it in ground truth (the misalignment the
figure measures). Spearman rank correlations over all maps of all cases.

**Output**: ``DIR/visuals.json`` and ``DIR/visuals.md``; simulated logs cached in
``DIR/sims/``.
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from decod_rs import _core
from decod_rs.bench.map_truth import wall_truth
from decod_rs.config import load_config
from decod_rs.pipeline import run_log
from decod_rs.sim import simulate
from decod_rs.tum import interpolate_poses, read_tum

FloatArray = NDArray[np.float64]

REPEATS = 5


@dataclass(frozen=True)
class Case:
    scene: str
    seed: int
    length_m: float
    drift: float | str
    preset: str
    sensor: str = "avia"

    @property
    def name(self) -> str:
        sensor = "" if self.sensor == "avia" else f"-{self.sensor}"
        return f"{self.scene}{sensor}-s{self.seed}-{self.length_m:g}m-d{self.drift}"


CASES = [
    Case("hume", 3, 15.0, 1.7, "pipe"),
    Case("hume", 1, 30.0, 0.5, "pipe"),
    Case("hume", 2, 30.0, 1.7, "pipe"),
    Case("hume", 4, 30.0, 3.0, "pipe"),
    Case("pe", 1, 30.0, 1.7, "pipe"),
    Case("shield", 1, 40.0, 1.7, "tunnel"),
    Case("shield", 1, 40.0, 1.7, "auto"),
    Case("shield", 2, 30.0, 5.0, "auto"),
    Case("shield", 3, 30.0, 3.0, "auto", "spin16"),
    Case("shield", 3, 15.0, 3.0, "tunnel", "spin16"),
]
QUICK = CASES[:2]


def _sim(case: Case, root: Path) -> Path:
    out = root / "sims" / case.name
    if not (out / "joints.json").exists():
        simulate(
            case.scene,
            out,
            seed=case.seed,
            sensor=case.sensor,
            length_m=case.length_m,
            drift=case.drift,
            progress=False,
            overwrite=True,
        )
    return out


def _extract_seconds(log: Path, preset: str) -> tuple[float, float]:
    """Best-of-``REPEATS`` seconds to stream the log through the LogProcessor with and
    without the map, interleaved so that a busy machine slows both alike."""
    cfg = json.dumps(load_config(None, preset).to_dict())
    best = {True: float("inf"), False: float("inf")}
    for _ in range(REPEATS):
        for map_on in (True, False):
            t0 = time.perf_counter()
            proc = _core.LogProcessor(str(log), cfg, imu_topic="/imu", map=map_on)
            while proc.step() is not None:
                pass
            best[map_on] = min(best[map_on], time.perf_counter() - t0)
    return best[True], best[False]


def _errors(sim: Path, run: Path) -> dict[str, dict[str, float]]:
    """Position RMSE, lateral RMSE and pass disagreement (module doc) of both trajectories."""
    gt_stamps, gt = read_tum(sim / "gt.tum")
    split = json.loads((run / "report.json").read_text())["split_stamp"]
    out = {}
    for name in ("odometry", "corrected"):
        stamps, poses = read_tum(run / f"{name}.tum")
        inside = (stamps >= gt_stamps[0]) & (stamps <= gt_stamps[-1])
        stamps, poses = stamps[inside], poses[inside]
        truth = interpolate_poses(gt_stamps, gt, stamps)[:, :3, 3]
        err = poses[:, :3, 3] - truth
        ret = stamps > split
        out_idx = np.flatnonzero(~ret)
        d2 = ((truth[ret][:, None, :] - truth[out_idx][None, :, :]) ** 2).sum(axis=2)
        partner = out_idx[np.argmin(d2, axis=1)]
        disagreement = err[ret][:, 1:] - err[partner][:, 1:]
        out[name] = {
            "rmse_m": float(np.sqrt(np.mean(np.sum(err**2, axis=1)))),
            "lateral_rmse_m": float(np.sqrt(np.mean(np.sum(err[:, 1:] ** 2, axis=1)))),
            "pass_disagreement_m": float(np.sqrt(np.mean(np.sum(disagreement**2, axis=1)))),
        }
    return out


def _one_run(case: Case, sim: Path, run: Path, loops: bool) -> dict[str, Any]:
    summary = run_log(
        sim / "log",
        run,
        preset=case.preset,
        imu_topic="/imu",
        progress=False,
        loops=loops,
        map=True,
        rerun=run / "run.rrd",
    )
    report = json.loads((run / "report.json").read_text())
    t = summary.timings_s
    rest = sum(v for k, v in t.items() if k not in ("map", "rerun"))
    figure = report["map"]["consistency"]
    truth = _errors(sim, run)
    wall = {name: wall_truth(sim, run, name) for name in ("odometry", "corrected")}
    return {
        "loops": loops,
        "accepted": report["counts"]["accepted"],
        "run_s": rest,
        "map_s": t.get("map", 0.0),
        "rerun_s": t.get("rerun", 0.0),
        "overhead_percent": 100 * (t.get("map", 0.0) + t.get("rerun", 0.0)) / rest,
        "points": report["map"]["points"],
        "stored_voxels": report["map"]["stored_voxels"],
        "ply_mb": {
            name: (run / f"map_{name}.ply").stat().st_size / 1e6
            for name in ("corrected", "odometry")
        },
        "rrd_mb": (run / "run.rrd").stat().st_size / 1e6,
        "thickness_mm": {
            name: figure[name]["median_overlap_mm"] for name in ("odometry", "corrected")
        },
        "mean_thickness_mm": {
            name: figure[name]["mean_overlap_mm"] for name in ("odometry", "corrected")
        },
        "floor_mm": figure["corrected"]["median_outbound_floor_mm"],
        "truth": truth,
        "wall_truth": wall,
    }


def _spearman(a: Sequence[float], b: Sequence[float]) -> float | None:
    x, y = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    ok = np.isfinite(x) & np.isfinite(y)
    if np.count_nonzero(ok) < 3:
        return None
    rx = np.argsort(np.argsort(x[ok])).astype(np.float64)
    ry = np.argsort(np.argsort(y[ok])).astype(np.float64)
    return float(np.corrcoef(rx, ry)[0, 1])


def _tracking(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Rank correlations of the figure (median and mean over the bins) with each true error
    over every map (the odometry maps of the loop runs, the corrected maps of both runs)."""
    points = []
    for row in rows:
        for name in ("odometry", "corrected") if row["loops"] else ("corrected",):
            if row["thickness_mm"][name] is not None:
                figures = (row["thickness_mm"][name], row["mean_thickness_mm"][name])
                wall = row["wall_truth"][name]["half_misalignment_median_mm"]
                truth = {**row["truth"][name], "wall_half_misalignment_mm": wall}
                points.append((figures, truth))
    out: dict[str, Any] = {"maps": len(points)}
    for k, figure in enumerate(("median", "mean")):
        for key in (
            "rmse_m",
            "lateral_rmse_m",
            "pass_disagreement_m",
            "wall_half_misalignment_mm",
        ):
            values = [p[0][k] for p in points]
            out[f"{figure}_vs_{key}"] = _spearman(values, [p[1][key] for p in points])
    return out


def _markdown(rows: list[dict[str, Any]], tracking: dict[str, Any], extract: list[Any]) -> str:
    lines = [
        "| case | loops | accepted | thickness odom -> corr [mm] | floor [mm] | "
        "true d/2 across the wall odom -> corr [mm] | r along the corridor odom, corr | "
        "RMSE odom -> corr [m] | lateral RMSE [m] | pass disagreement [m] | "
        "points (corr) | stored voxels | PLY [MB] | rrd [MB] | run [s] | map [s] | "
        "rerun [s] | overhead |",
        "|" + " --- |" * 18,
    ]
    for r in rows:
        th, tr = r["thickness_mm"], r["truth"]
        pts = sum(r["points"]["corrected"].values())

        def pair(key: str, t: dict[str, Any] = tr) -> str:
            return f"{t['odometry'][key]:.3f} -> {t['corrected'][key]:.3f}"

        def wall(key: str, w: dict[str, Any] = r["wall_truth"], sep: str = " -> ") -> str:
            v = [w[n][key] for n in ("odometry", "corrected")]
            return sep.join("-" if x is None else f"{x:.2f}" for x in v)

        lines.append(
            f"| {r['case']} | {'yes' if r['loops'] else 'no'} | {r['accepted']} | "
            f"{th['odometry']} -> {th['corrected']} | {r['floor_mm']} | "
            f"{wall('half_misalignment_median_mm')} | {wall('along_corridor_r', sep=', ')} | "
            f"{pair('rmse_m')} | "
            f"{pair('lateral_rmse_m')} | {pair('pass_disagreement_m')} | {pts} | "
            f"{r['stored_voxels']} | {r['ply_mb']['corrected']:.1f} | {r['rrd_mb']:.1f} | "
            f"{r['run_s']:.2f} | {r['map_s']:.2f} | {r['rerun_s']:.2f} | "
            f"{r['overhead_percent']:.0f} % |"
        )
    lines += ["", f"Spearman rank correlation of the thickness with the true error: {tracking}"]
    lines += [
        "",
        "| case | stream with map [s] | without [s] | map share |",
        "| --- | --- | --- | --- |",
    ]
    for name, on, off in extract:
        lines.append(f"| {name} | {on:.3f} | {off:.3f} | {100 * (on / off - 1):+.1f} % |")
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--quick", action="store_true", help=f"only {len(QUICK)} cases")
    p.add_argument("--cases", help="comma-separated case indices into CASES")
    p.add_argument("--no-extract", action="store_true", help="skip the stream timings")
    args = p.parse_args(argv)
    rows, extract = [], []
    cases = QUICK if args.quick else CASES
    if args.cases:
        cases = [CASES[int(i)] for i in args.cases.split(",")]
    for case in cases:
        sim = _sim(case, args.out)
        for loops in (True, False):
            run = args.out / "runs" / case.name / ("loops" if loops else "no_loops")
            rows.append({"case": case.name, **_one_run(case, sim, run, loops)})
            print(json.dumps(rows[-1]), flush=True)
        if not args.no_extract:
            on, off = _extract_seconds(sim / "log", case.preset)
            extract.append((case.name, on, off))
    tracking = _tracking(rows)
    (args.out / "visuals.json").write_text(
        json.dumps({"runs": rows, "tracking": tracking, "extract_s": extract}, indent=2)
    )
    (args.out / "visuals.md").write_text(_markdown(rows, tracking, extract))
    print(_markdown(rows, tracking, extract))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
