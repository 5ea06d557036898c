"""Summary tables of a batch or a sweep: one row per run read back from its files (CSV and
markdown), the metrics of runs with ground truth, and a sweep's figures per setting.

A row's counts and stage timings come from the run's ``report.json``, so a run skipped
because it was complete reads exactly like a fresh one. With ground truth the run is
evaluated (:func:`decod_rs.evaluate.evaluate_run`, written to ``evaluation.json``):
Precision@1 / Recall@1 at the fine (0.3 m) and coarse tolerance, and the position RMSE and
endpoint error of odometry and corrected trajectories.
"""

from __future__ import annotations

import csv
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from decod_rs.evaluate import evaluate_run

#: The columns of ``summary.csv``: identity and status, counts, timings, metrics, error.
COUNT_COLUMNS = ("scans", "submaps", "landmarks", "queries", "accepted", "mode")
TIMING_COLUMNS = ("wall_s", "log_s", "realtime_x", "extract_s", "match_s", "optimise_s")
METRIC_COLUMNS = (
    "tp_fine",
    "accepted_fine",
    "common_fine",
    "precision_fine",
    "recall_fine",
    "tp_coarse",
    "accepted_coarse",
    "common_coarse",
    "precision_coarse",
    "recall_coarse",
    "odom_rmse_m",
    "corrected_rmse_m",
    "odom_endpoint_m",
    "corrected_endpoint_m",
)
#: Metres of the corrected trajectory that only the odometry places (``report.json``
#: ``unmeasured``, summed over the stretches; empty for a run written before it existed).
QUALITY_COLUMNS = ("odometry_only_m",)
RUN_COLUMNS = (
    "name",
    "status",
    "log",
    *COUNT_COLUMNS,
    *QUALITY_COLUMNS,
    *TIMING_COLUMNS,
    *METRIC_COLUMNS,
    "error",
)
#: Errors are cut to this many characters in the markdown table (the CSV keeps them whole).
MARKDOWN_ERROR_CHARS = 160

__all__ = [
    "RUN_COLUMNS",
    "evaluation_row",
    "report_row",
    "write_csv",
    "write_markdown",
]


def report_row(run_dir: Path) -> dict[str, Any]:
    """Counts, stage timings and the metres only the odometry places, of a complete run (its
    ``report.json``)."""
    report = json.loads((run_dir / "report.json").read_text(encoding="utf-8"))
    counts, timings = report["counts"], report.get("timings_s", {})
    row: dict[str, Any] = {k: counts.get(k) for k in COUNT_COLUMNS if k != "mode"}
    row["mode"] = report.get("mode")
    row["log_s"] = report.get("log_duration_s")
    row["realtime_x"] = report.get("realtime_factor")
    unmeasured = report.get("unmeasured")
    row["odometry_only_m"] = (
        None if unmeasured is None else sum(s["length_m"] for s in unmeasured["stretches"])
    )
    for stage in ("extract", "match", "optimise"):
        row[f"{stage}_s"] = timings.get(stage)
    return row


def evaluation_row(run_dir: Path, gt: Path, joints: Path | None) -> dict[str, Any]:
    """The run's metrics against ``gt`` (``joints``: the simulator's joints.json for a
    pipe's coarse tolerance); ``evaluation.json`` is written into ``run_dir``. An
    evaluation that fails gives ``error`` instead (the run itself stays ``ok``)."""
    try:
        result, _ = evaluate_run(run_dir, gt, joints_path=joints)
    except (OSError, ValueError, KeyError) as exc:
        return {"error": f"evaluation: {type(exc).__name__}: {exc}"}
    (run_dir / "evaluation.json").write_text(json.dumps(result, indent=2), encoding="utf-8")
    row: dict[str, Any] = {}
    for tol in ("fine", "coarse"):
        m = result["loops"][tol]
        row[f"tp_{tol}"] = m["true_positives"]
        row[f"accepted_{tol}"] = m["accepted"]
        row[f"common_{tol}"] = m["common_queries"]
        row[f"precision_{tol}"] = m["precision_at_1"]
        row[f"recall_{tol}"] = m["recall_at_1"]
    traj = result["trajectory"]
    for name, short in (("odometry", "odom"), ("corrected", "corrected")):
        row[f"{short}_rmse_m"] = traj[name]["rmse_m"]
        row[f"{short}_endpoint_m"] = traj[name]["endpoint_error_m"]
    return row


def _cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)


def write_csv(path: Path, rows: Sequence[dict[str, Any]], columns: Sequence[str]) -> Path:
    """``rows`` as CSV with ``columns`` (missing values empty, floats to 6 digits)."""
    with path.open("w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh)
        writer.writerow(columns)
        for row in rows:
            writer.writerow([_cell(row.get(c)) for c in columns])
    return path


def _md(value: Any, column: str) -> str:
    if value is None or value == "":
        return "-"
    if column.startswith(("precision", "recall")) and isinstance(value, float):
        return f"{100.0 * value:.1f} %"
    if isinstance(value, float):
        return f"{value:.3f}" if abs(value) < 100 else f"{value:.0f}"
    text = str(value).replace("|", "\\|").replace("\n", " ")
    if column == "error" and len(text) > MARKDOWN_ERROR_CHARS:
        text = text[: MARKDOWN_ERROR_CHARS - 3] + "..."
    return text


def markdown_table(rows: Sequence[dict[str, Any]], columns: Sequence[str]) -> list[str]:
    """A markdown table of ``rows`` (percentages for precision and recall)."""
    lines = ["| " + " | ".join(columns) + " |", "|" + " --- |" * len(columns)]
    for row in rows:
        lines.append("| " + " | ".join(_md(row.get(c), c) for c in columns) + " |")
    return lines


def write_markdown(
    path: Path,
    title: str,
    notes: Sequence[str],
    tables: Sequence[tuple[str, Sequence[dict[str, Any]], Sequence[str]]],
) -> Path:
    """A markdown page: ``title``, ``notes`` (one line each), then each ``(heading, rows,
    columns)`` table."""
    lines = [f"# {title}", "", *notes]
    for heading, rows, columns in tables:
        lines += ["", f"## {heading}", "", *markdown_table(rows, columns)]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path
