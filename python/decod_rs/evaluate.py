"""The paper's evaluation protocol (§IV-B.3, DESIGN.md "Evaluation") on a run directory.

Inputs: the run's ``odometry.tum``, ``corrected.tum``, ``loops.csv``, optional
``landmarks.csv`` and ``report.json``, the ground truth ``gt.tum`` (same world frame as the
estimates, as in the simulator) and optionally the simulator's ``joints.json``
(``joints_x_m``: true boundary positions along world x).

Loop metrics. Each ``loops.csv`` row is one query boundary with its Top-1 candidate. Both
boundary planes go into the world with the ground-truth pose interpolated at their submap
stamps (rows whose stamps lie outside the ground truth are dropped, as the paper drops submaps
without ground-truth support). The axial error is ``|a_q_w . (o_db_w - o_q_w)|`` (the paper's
"absolute boundary plane residual"); the lateral offset is the rest of that vector. At a
tolerance ``tau``:

* an accepted row is a true positive if axial error <= tau and lateral offset <= the lateral
  gate (default twice the coarse tolerance: the same cross-section, not an axially aligned
  point of another corridor leg); else a false positive;
* a query is *common* if some database landmark lies within tau of it in that sense. The
  database of a query: the ``landmarks.csv`` rows at least ``min_time_separation_s`` (from
  ``report.json``, default 30 s) older than it, or, in batch mode (``report.json``
  ``eligibility = "across_passes"``), every row of the outbound pass (stamped at or before
  ``split_stamp``); plus its own Top-1 candidate (eligible by construction), so every true
  positive is common;
* Recall@1 = TP / common queries, Precision@1 = TP / accepted (None when a denominator is 0).

Tolerances: fine 0.3 m; coarse 2.4 m for tunnels, half the joint spacing (median difference
of ``joints_x_m``) for pipes. The preset comes from ``report.json`` (``preset`` key anywhere)
or the caller, default tunnel; a pipe without joints.json needs explicit tolerances.

PR curve: for each inlier threshold K among the rows' ``inliers`` values, the rows with a
candidate and ``inliers >= K`` count as accepted (the Top-1 curve over the threshold, other
acceptance gates not replayed).

Trajectory: every estimated pose inside the ground truth's time span is compared with the
ground truth interpolated at its stamp: position RMSE, maximum, endpoint error (last such
pose), and the reduction in percent from odometry to corrected. ``align=True`` first applies
the rigid Umeyama alignment of each estimate onto the ground truth (for estimates in another
world frame).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from decod_rs.run_files import (
    LandmarkTable,
    LoopTable,
    read_landmarks_csv,
    read_loops_csv,
    within_run,
)
from decod_rs.tum import check_poses, interpolate_poses, read_tum, umeyama_alignment

FloatArray = NDArray[np.float64]

FINE_TOLERANCE_M = 0.3
TUNNEL_COARSE_TOLERANCE_M = 2.4
DEFAULT_MIN_SEPARATION_S = 30.0
#: Lateral gate = this times the coarse tolerance (see the module doc).
LATERAL_GATE_FACTOR = 2.0

__all__ = [
    "FINE_TOLERANCE_M",
    "TrajectoryMetrics",
    "evaluate_run",
    "format_table",
    "loop_geometry_errors",
    "loop_metrics",
    "pr_curve",
    "tolerances_for",
    "trajectory_metrics",
]


def tolerances_for(preset: str, joints_x_m: FloatArray | None = None) -> tuple[float, float]:
    """(fine, coarse) tolerances in metres for ``preset`` (paper §IV-B.3 and §IV-E); an
    ``auto`` run is evaluated by the corridor kind it measured (``report.json`` ``auto``),
    passed here as ``pipe`` or ``tunnel``."""
    if preset == "tunnel":
        return FINE_TOLERANCE_M, TUNNEL_COARSE_TOLERANCE_M
    if preset == "pipe":
        if joints_x_m is None or len(joints_x_m) < 2:
            raise ValueError(
                "pipe preset: the coarse tolerance is half the joint spacing; pass "
                "--joints joints.json (with >= 2 joints_x_m) or --tolerances FINE COARSE"
            )
        spacing = float(np.median(np.diff(np.sort(np.asarray(joints_x_m, dtype=np.float64)))))
        return FINE_TOLERANCE_M, 0.5 * spacing
    raise ValueError(f"unknown preset {preset!r}; expected 'tunnel' or 'pipe'")


def _planes_in_world(
    gt_stamps: FloatArray,
    gt_poses: FloatArray,
    stamps: FloatArray,
    origins: FloatArray,
    axes: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    t = interpolate_poses(gt_stamps, gt_poses, stamps)
    o = np.einsum("nij,nj->ni", t[:, :3, :3], origins) + t[:, :3, 3]
    a = np.einsum("nij,nj->ni", t[:, :3, :3], axes)
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    return o, a


def _axial_lateral(
    o_q: FloatArray, a_q: FloatArray, o_db: FloatArray
) -> tuple[FloatArray, FloatArray]:
    d = o_db - o_q
    axial = np.einsum("...i,...i->...", a_q, d)
    lateral = np.linalg.norm(d - axial[..., None] * a_q, axis=-1)
    return np.abs(axial), lateral


def matched_db_origin(loops: LoopTable) -> FloatArray:
    """The database-side point each row's loop ties to the query origin: the candidate's
    origin moved by the verified axial offset (``dz_m`` along the candidate axis, sign by
    ``heading_deg``), which is what the 5-DoF factor uses. Rows of a ``loops.csv`` without
    those columns (other tools) keep the candidate's origin."""
    dz = loops.extra.get("dz_m")
    heading = loops.extra.get("heading_deg")
    if dz is None or heading is None:
        return loops.db_origin
    shift = np.array([float(v) if v else 0.0 for v in dz])
    sign = np.array([1.0 if (not h or abs(float(h)) < 90.0) else -1.0 for h in heading])
    return np.asarray(loops.db_origin + (shift * sign)[:, None] * loops.db_axis)


def loop_geometry_errors(
    loops: LoopTable,
    gt_stamps: FloatArray,
    gt_poses: FloatArray,
    db_origin: FloatArray | None = None,
) -> tuple[NDArray[np.bool_], FloatArray, FloatArray]:
    """Per row: ``supported`` (L,) (both stamps inside the ground truth; a row without a
    candidate is supported if its query stamp is), axial and lateral errors (L,) in metres
    (NaN where unsupported or no candidate) of the plane the loop asserts
    (:func:`matched_db_origin`; ``db_origin`` (L, 3) in its place: e.g. the candidate's own
    origin, for how far apart the two views' boundaries are)."""
    t0, t1 = gt_stamps[0], gt_stamps[-1]
    has_q = (loops.query_stamp >= t0) & (loops.query_stamp <= t1)
    has_db = np.isfinite(loops.db_stamp) & (loops.db_stamp >= t0) & (loops.db_stamp <= t1)
    supported = has_q & (has_db | ~np.isfinite(loops.db_stamp))
    axial = np.full(len(loops), np.nan)
    lateral = np.full(len(loops), np.nan)
    both = has_q & has_db
    if np.any(both):
        o_q, a_q = _planes_in_world(
            gt_stamps,
            gt_poses,
            loops.query_stamp[both],
            loops.query_origin[both],
            loops.query_axis[both],
        )
        o_db, _ = _planes_in_world(
            gt_stamps,
            gt_poses,
            loops.db_stamp[both],
            (matched_db_origin(loops) if db_origin is None else db_origin)[both],
            loops.db_axis[both],
        )
        axial[both], lateral[both] = _axial_lateral(o_q, a_q, o_db)
    return supported, axial, lateral


def _common_queries(
    loops: LoopTable,
    landmarks: LandmarkTable | None,
    gt_stamps: FloatArray,
    gt_poses: FloatArray,
    supported: NDArray[np.bool_],
    tolerance_m: float,
    lateral_gate_m: float,
    min_separation_s: float,
    split_stamp: float | None = None,
) -> NDArray[np.bool_]:
    """Whether each row's query has a database landmark within tolerance (module doc);
    ``split_stamp``: the database is the outbound pass (batch mode), not the older rows."""
    common = np.zeros(len(loops), dtype=bool)
    if landmarks is None or len(landmarks) == 0:
        return common
    t0, t1 = gt_stamps[0], gt_stamps[-1]
    inside = (landmarks.stamp >= t0) & (landmarks.stamp <= t1)
    if not np.any(inside):
        return common
    lm_st = landmarks.stamp[inside]
    lm_t = interpolate_poses(gt_stamps, gt_poses, lm_st)
    lm_o = np.einsum("nij,nj->ni", lm_t[:, :3, :3], landmarks.origin[inside]) + lm_t[:, :3, 3]
    rows = np.flatnonzero(supported)
    if rows.size == 0:
        return common
    o_q, a_q = _planes_in_world(
        gt_stamps,
        gt_poses,
        loops.query_stamp[rows],
        loops.query_origin[rows],
        loops.query_axis[rows],
    )
    axial, lateral = _axial_lateral(o_q[:, None, :], a_q[:, None, :], lm_o[None, :, :])
    if split_stamp is None:
        eligible = lm_st[None, :] <= loops.query_stamp[rows][:, None] - min_separation_s
    else:
        eligible = np.repeat((lm_st <= split_stamp)[None, :], rows.size, axis=0)
    near = eligible & (axial <= tolerance_m) & (lateral <= lateral_gate_m)
    common[rows] = np.any(near, axis=1)
    return common


def loop_metrics(
    loops: LoopTable,
    landmarks: LandmarkTable | None,
    gt_stamps: FloatArray,
    gt_poses: FloatArray,
    tolerance_m: float,
    lateral_gate_m: float,
    min_separation_s: float = DEFAULT_MIN_SEPARATION_S,
    split_stamp: float | None = None,
) -> dict[str, Any]:
    """Recall@1, Precision@1 and their counts at one tolerance (definitions: module doc;
    ``split_stamp`` given: batch mode, the database is the outbound pass)."""
    supported, axial, lateral = loop_geometry_errors(loops, gt_stamps, gt_poses)
    within = (axial <= tolerance_m) & (lateral <= lateral_gate_m)  # NaN compares False
    accepted = loops.accepted & supported
    tp = accepted & within
    common = _common_queries(
        loops,
        landmarks,
        gt_stamps,
        gt_poses,
        supported,
        tolerance_m,
        lateral_gate_m,
        min_separation_s,
        split_stamp,
    ) | (supported & within)
    n_acc, n_tp, n_common = int(accepted.sum()), int(tp.sum()), int(common.sum())
    return {
        "tolerance_m": tolerance_m,
        "common_queries": n_common,
        "accepted": n_acc,
        "true_positives": n_tp,
        "false_positives": n_acc - n_tp,
        "recall_at_1": n_tp / n_common if n_common else None,
        "precision_at_1": n_tp / n_acc if n_acc else None,
    }


def pr_curve(
    loops: LoopTable,
    gt_stamps: FloatArray,
    gt_poses: FloatArray,
    tolerance_m: float,
    lateral_gate_m: float,
    common_queries: int,
) -> list[dict[str, Any]]:
    """Precision and recall of the Top-1 candidates for every inlier threshold K (module
    doc), ascending in K."""
    supported, axial, lateral = loop_geometry_errors(loops, gt_stamps, gt_poses)
    candidate = supported & np.isfinite(loops.db_stamp)
    within = (axial <= tolerance_m) & (lateral <= lateral_gate_m)
    out = []
    for k in np.unique(loops.inliers[candidate]):
        pred = candidate & (loops.inliers >= k)
        n, tp = int(pred.sum()), int((pred & within).sum())
        out.append(
            {
                "min_inliers": int(k),
                "accepted": n,
                "true_positives": tp,
                "precision": tp / n if n else None,
                "recall": tp / common_queries if common_queries else None,
            }
        )
    return out


@dataclass
class TrajectoryMetrics:
    """Position errors of one estimate against the ground truth: ``stamps`` (K,) and
    ``errors_m`` (K,) of the poses inside the ground truth's span, their RMSE, maximum and
    the endpoint error (last pose), all metres."""

    stamps: FloatArray
    errors_m: FloatArray
    rmse_m: float
    max_m: float
    endpoint_m: float

    def to_json(self) -> dict[str, Any]:
        return {
            "poses": int(self.stamps.size),
            "rmse_m": self.rmse_m,
            "max_error_m": self.max_m,
            "endpoint_error_m": self.endpoint_m,
        }


def trajectory_metrics(
    stamps: FloatArray,
    poses: FloatArray,
    gt_stamps: FloatArray,
    gt_poses: FloatArray,
    align: bool = False,
) -> TrajectoryMetrics:
    """Compare an estimate (stamps (N,), poses (N, 4, 4)) with the ground truth."""
    p = check_poses(poses)
    inside = (stamps >= gt_stamps[0]) & (stamps <= gt_stamps[-1])
    if not np.any(inside):
        raise ValueError(
            f"no estimated pose lies inside the ground truth's time span "
            f"[{gt_stamps[0]!r}, {gt_stamps[-1]!r}]"
        )
    st = stamps[inside]
    est = p[inside, :3, 3]
    gt = interpolate_poses(gt_stamps, gt_poses, st)[:, :3, 3]
    if align:
        t = umeyama_alignment(est, gt)
        est = est @ t[:3, :3].T + t[:3, 3]
    err = np.linalg.norm(est - gt, axis=1)
    return TrajectoryMetrics(
        stamps=st,
        errors_m=err,
        rmse_m=float(np.sqrt(np.mean(err**2))),
        max_m=float(err.max()),
        endpoint_m=float(err[-1]),
    )


def _reduction(before: float, after: float) -> float | None:
    return 100.0 * (1.0 - after / before) if before > 0.0 else None


def _find_key(obj: Any, key: str) -> Any:
    """The first value under ``key`` in a nested JSON document (depth first), else None."""
    if isinstance(obj, dict):
        if key in obj:
            return obj[key]
        for value in obj.values():
            found = _find_key(value, key)
            if found is not None:
                return found
    return None


def evaluate_run(
    run_dir: str | Path,
    gt_path: str | Path,
    joints_path: str | Path | None = None,
    align: bool = False,
    preset: str | None = None,
    tolerances: tuple[float, float] | None = None,
    lateral_gate_m: float | None = None,
) -> tuple[dict[str, Any], dict[str, TrajectoryMetrics]]:
    """Evaluate the run in ``run_dir`` against ``gt_path``: the ``evaluation.json`` document
    and the per-estimate trajectory errors (for plots). See the module doc for every
    definition."""
    run = Path(run_dir)
    if not run.is_dir():
        raise FileNotFoundError(f"run directory {run} does not exist")
    gt_stamps, gt_poses = read_tum(gt_path)
    report: dict[str, Any] = {}
    if (run / "report.json").exists():
        report = json.loads((run / "report.json").read_text(encoding="utf-8"))
    joints = None if joints_path is None else _read_joints(Path(joints_path))
    preset = preset or _find_key(report, "preset") or "tunnel"
    if preset == "auto":
        preset = (report.get("auto") or {}).get("corridor", "tunnel")
    fine, coarse = tolerances or tolerances_for(str(preset), joints)
    gate = lateral_gate_m if lateral_gate_m is not None else LATERAL_GATE_FACTOR * coarse
    sep = _find_key(report, "min_time_separation_s")
    min_sep = float(sep) if sep is not None else DEFAULT_MIN_SEPARATION_S
    split = report.get("split_stamp") if report.get("eligibility") == "across_passes" else None

    loops = within_run(read_loops_csv(run / "loops.csv"))
    landmarks = (
        read_landmarks_csv(run / "landmarks.csv") if (run / "landmarks.csv").exists() else None
    )
    supported, axial, lateral = loop_geometry_errors(loops, gt_stamps, gt_poses)
    result: dict[str, Any] = {
        "run_dir": str(run),
        "gt": str(gt_path),
        "joints": str(joints_path) if joints_path is not None else None,
        "preset": preset,
        "min_time_separation_s": min_sep,
        "lateral_gate_m": gate,
        "queries": int(supported.sum()),
        "queries_without_gt": int((~supported).sum()),
        "accepted": int((loops.accepted & supported).sum()),
        "loops": {},
        "pr_curve": {},
    }
    for name, tol in (("fine", fine), ("coarse", coarse)):
        m = loop_metrics(loops, landmarks, gt_stamps, gt_poses, tol, gate, min_sep, split)
        result["loops"][name] = m
        result["pr_curve"][name] = pr_curve(
            loops, gt_stamps, gt_poses, tol, gate, m["common_queries"]
        )
    result["loop_rows"] = _loop_rows(loops, axial, lateral)
    result["trajectory"], errors = _trajectory_section(run, gt_stamps, gt_poses, align)
    return result, errors


def _read_joints(path: Path) -> FloatArray:
    """The true joint positions along the corridor (``joints.json``'s ``joints_x_m``)."""
    doc = json.loads(path.read_text(encoding="utf-8"))
    if "joints_x_m" not in doc:
        raise ValueError(f"{path}: no `joints_x_m` list")
    return np.asarray(doc["joints_x_m"], dtype=np.float64)


def _loop_rows(loops: LoopTable, axial: FloatArray, lateral: FloatArray) -> list[dict[str, Any]]:
    """One row per query: its stamps, inliers, whether it was kept and its true errors."""

    def finite(v: float) -> float | None:
        return float(v) if np.isfinite(v) else None

    return [
        {
            "query_stamp": float(loops.query_stamp[r]),
            "db_stamp": finite(loops.db_stamp[r]),
            "inliers": int(loops.inliers[r]),
            "accepted": bool(loops.accepted[r]),
            "axial_error_m": finite(axial[r]),
            "lateral_offset_m": finite(lateral[r]),
        }
        for r in range(len(loops))
    ]


def _trajectory_section(
    run: Path, gt_stamps: FloatArray, gt_poses: FloatArray, align: bool
) -> tuple[dict[str, Any], dict[str, TrajectoryMetrics]]:
    """The odometry's and the corrected trajectory's errors against ground truth, and the
    reductions of the RMSE and the endpoint error."""
    errors: dict[str, TrajectoryMetrics] = {}
    traj: dict[str, Any] = {"aligned": align}
    for name in ("odometry", "corrected"):
        stamps, poses = read_tum(run / f"{name}.tum")
        errors[name] = trajectory_metrics(stamps, poses, gt_stamps, gt_poses, align)
        traj[name] = errors[name].to_json()
    traj["rmse_reduction_percent"] = _reduction(
        errors["odometry"].rmse_m, errors["corrected"].rmse_m
    )
    traj["endpoint_reduction_percent"] = _reduction(
        errors["odometry"].endpoint_m, errors["corrected"].endpoint_m
    )
    return traj, errors


def _pct(v: float | None) -> str:
    return "-" if v is None else f"{100.0 * v:.1f} %"


def format_table(result: dict[str, Any]) -> str:
    """The evaluation as a plain-text table."""
    lines = [
        f"queries {result['queries']} ({result['queries_without_gt']} without ground truth), "
        f"accepted {result['accepted']}",
        f"{'tolerance':>10} {'common':>7} {'TP':>5} {'FP':>5} {'recall@1':>9} {'precision@1':>12}",
    ]
    for m in result["loops"].values():
        lines.append(
            f"{m['tolerance_m']:>8.2f} m {m['common_queries']:>7d} {m['true_positives']:>5d} "
            f"{m['false_positives']:>5d} {_pct(m['recall_at_1']):>9} "
            f"{_pct(m['precision_at_1']):>12}"
        )
    t = result["trajectory"]
    lines.append(
        f"{'trajectory' + (' (aligned)' if t['aligned'] else ''):<22} {'RMSE':>10} "
        f"{'endpoint':>10} {'max':>10}"
    )
    for name in ("odometry", "corrected"):
        m = t[name]
        lines.append(
            f"{name:<22} {m['rmse_m']:>8.3f} m {m['endpoint_error_m']:>8.3f} m "
            f"{m['max_error_m']:>8.3f} m"
        )
    red = [t["rmse_reduction_percent"], t["endpoint_reduction_percent"]]
    cells = ["-" if v is None else f"{v:.1f} %" for v in red]
    lines.append(f"{'reduction':<22} {cells[0]:>10} {cells[1]:>10}")
    return "\n".join(lines)
