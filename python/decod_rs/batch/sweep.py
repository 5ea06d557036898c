"""``decod sweep``: every log at every setting of a parameter grid, extracting each log once
per distinct set of extraction parameters, and the precision-recall points and trajectory
metrics per setting across all logs (the calibration before trusting decod on a new pipe).

One task per log and group of settings that share their extraction parameters
(:func:`decod_rs.batch.grid.extraction_params`): the task extracts the log once
(:func:`decod_rs.batch.replay.extract_log`) and replays matching, selection and the graph for
each setting (:func:`decod_rs.batch.replay.run_from_extraction`). A grid of ``matching.*``
and ``graph.*`` parameters therefore costs one extraction per log, whatever its size.

Files in ``OUT``: ``settings.json`` (id -> parameters), ``<id>/params.toml`` (the setting as
a ``--config`` file), ``<id>/<log>/`` (a run), ``runs.csv`` (a row per setting and log),
``sweep.csv`` (a row per setting: Precision@1 / Recall@1 pooled over the logs with ground
truth - true positives over accepted, over common queries - at 0.3 m and the coarse
tolerance, mean position RMSE and endpoint error, logs made worse than their odometry),
``sweep.md``, ``sweep.json`` and ``pr_curve.png``.
"""

from __future__ import annotations

import json
import time
import traceback
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from decod_rs.batch.batch import (
    ERROR_FILE,
    LogOutcome,
    collect,
    failure,
    prepare_run_dir,
    summary_row,
)
from decod_rs.batch.engine import Engine
from decod_rs.batch.grid import Setting, extraction_params, params_toml
from decod_rs.batch.jobs import LogJob
from decod_rs.batch.replay import extract_log, replay_params, run_from_extraction
from decod_rs.batch.summary import METRIC_COLUMNS, RUN_COLUMNS, write_csv, write_markdown

SETTING_COLUMNS = (
    "setting",
    "params",
    "logs",
    "failed",
    "evaluated",
    "queries",
    "accepted",
    *METRIC_COLUMNS,
    "worse_than_odometry",
)
RUNS_COLUMNS = ("setting", "params", *RUN_COLUMNS)
MARKDOWN_RUN_COLUMNS = (
    "setting",
    "name",
    "status",
    "accepted",
    "queries",
    "precision_fine",
    "recall_fine",
    "corrected_rmse_m",
    "error",
)

__all__ = ["SweepResult", "TaskOutcome", "run_sweep", "sweep_task"]


@dataclass
class TaskOutcome:
    """A sweep task's result: an outcome per setting id and the extractions it made."""

    outcomes: dict[str, LogOutcome]
    extractions: int = 0
    extract_s: float = 0.0


@dataclass
class SweepResult:
    """A finished sweep: the per-setting rows (pooled over logs), the per-run rows, the
    number of extractions made per log, the engine and the wall time."""

    out_dir: Path
    settings: list[Setting]
    setting_rows: list[dict[str, Any]]
    run_rows: list[dict[str, Any]]
    extractions: dict[str, int]
    engine: str
    wall_s: float
    notes: list[str] = field(default_factory=list)


def _fail_all(
    job: LogJob, runs: Sequence[tuple[Setting, Path]], exc: BaseException
) -> dict[str, LogOutcome]:
    out = {}
    for setting, run_dir in runs:
        run_dir.mkdir(parents=True, exist_ok=True)
        (run_dir / ERROR_FILE).write_text(traceback.format_exc(), encoding="utf-8")
        out[setting.id] = LogOutcome(
            job.name, str(job.log), str(run_dir), "failed", None, failure(exc)
        )
    return out


def sweep_task(
    job: LogJob,
    extraction: dict[str, Any],
    runs: list[tuple[Setting, Path]],
    force: bool,
) -> TaskOutcome:
    """A worker's task: extract ``job``'s log once with the ``extraction`` parameters, then
    replay every setting of ``runs`` (setting, run directory) not complete yet. Errors go
    into the outcomes: an extraction error fails every setting of the task, a replay error
    only its own."""
    result = TaskOutcome({})
    todo = []
    for setting, run_dir in runs:
        if (done := prepare_run_dir(job, run_dir, force)) is not None:
            result.outcomes[setting.id] = done
        else:
            todo.append((setting, run_dir))
    if not todo:
        return result
    t0 = time.perf_counter()
    try:
        result.extractions += 1
        extracted = extract_log(job.log, job.options, extraction, beside=todo[0][1])
    except Exception as exc:
        result.outcomes.update(_fail_all(job, todo, exc))
        return result
    result.extract_s = time.perf_counter() - t0
    for setting, run_dir in todo:
        t0 = time.perf_counter()
        try:
            cfg = replay_params(extracted, setting.params)
            shared = {
                "setting": setting.id,
                "params": setting.params,
                "extraction_shared_by": len(todo),
            }
            run_from_extraction(extracted, run_dir, cfg, {"sweep": shared})
        except Exception as exc:
            result.outcomes.update(_fail_all(job, [(setting, run_dir)], exc))
            continue
        wall = time.perf_counter() - t0
        result.outcomes[setting.id] = LogOutcome(job.name, str(job.log), str(run_dir), "ok", wall)
    return result


def _check_settings(out_dir: Path, settings: list[Setting], force: bool) -> None:
    """Write ``settings.json``; refuse (without ``force``) a directory whose settings of the
    same ids differ: its runs would be skipped as complete at the wrong parameters."""
    path = out_dir / "settings.json"
    new = {s.id: s.params for s in settings}
    if path.is_file() and not force:
        old = json.loads(path.read_text(encoding="utf-8"))
        changed = sorted(k for k in new if k in old and old[k] != new[k])
        if changed:
            raise FileExistsError(
                f"{out_dir} holds a sweep whose settings {', '.join(changed)} have other "
                f"parameters; use --force or another --out"
            )
        new = {**old, **new}
    out_dir.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(new, indent=2), encoding="utf-8")
    for s in settings:
        (out_dir / s.id).mkdir(exist_ok=True)
        (out_dir / s.id / "params.toml").write_text(params_toml(s.params), encoding="utf-8")


def _tasks(
    jobs: list[LogJob], settings: list[Setting], out_dir: Path
) -> list[tuple[LogJob, dict[str, Any], list[tuple[Setting, Path]]]]:
    """One task per log and group of settings with equal extraction parameters."""
    tasks = []
    for job in jobs:
        groups: dict[tuple[tuple[str, str], ...], list[Setting]] = {}
        for s in settings:
            groups.setdefault(extraction_params(s.params), []).append(s)
        for key, members in groups.items():
            params = {k: members[0].params[k] for k, _ in key}
            tasks.append((job, params, [(s, out_dir / s.id / job.name) for s in members]))
    return tasks


def run_sweep(
    jobs: list[LogJob],
    settings: list[Setting],
    out_dir: Path,
    engine: Engine,
    *,
    force: bool = False,
    on_done: Callable[[TaskOutcome], None] | None = None,
) -> SweepResult:
    """Run every job at every setting on ``engine`` and write the sweep's files (module
    doc); ``on_done`` is called with each task's outcome as it arrives."""
    t0 = time.perf_counter()
    _check_settings(out_dir, settings, force)
    tasks = _tasks(jobs, settings, out_dir)
    futures: dict[Future[TaskOutcome], int] = {
        engine.executor.submit(sweep_task, job, params, runs, force): k
        for k, (job, params, runs) in enumerate(tasks)
    }

    def lost(k: int, exc: BaseException) -> TaskOutcome:
        job, _, runs = tasks[k]
        return TaskOutcome(_fail_all(job, runs, exc))

    done = collect(futures, lost, on_done)
    extractions = {job.name: 0 for job in jobs}
    outcomes: dict[tuple[str, str], LogOutcome] = {}
    for k, task in done.items():
        extractions[tasks[k][0].name] += task.extractions
        for sid, outcome in task.outcomes.items():
            outcomes[sid, tasks[k][0].name] = outcome
    run_rows = [
        {"setting": s.id, "params": s.label(), **summary_row(job, outcomes[s.id, job.name])}
        for s in settings
        for job in jobs
    ]
    setting_rows = [
        pool_setting(s, [r for r in run_rows if r["setting"] == s.id]) for s in settings
    ]
    result = SweepResult(
        out_dir,
        settings,
        setting_rows,
        run_rows,
        extractions,
        engine.description,
        time.perf_counter() - t0,
    )
    write_sweep_summary(result)
    return result


def _ratio(num: float, den: float) -> float | None:
    return num / den if den else None


def _mean(values: list[float]) -> float | None:
    return sum(values) / len(values) if values else None


def pool_setting(setting: Setting, rows: list[dict[str, Any]]) -> dict[str, Any]:
    """One setting's figures over its runs (module doc): counts summed, precision and
    recall from the pooled counts, trajectory errors averaged over the evaluated logs."""
    ok = [r for r in rows if r["status"] != "failed"]
    evaluated = [r for r in ok if r.get("tp_fine") is not None]
    out: dict[str, Any] = {
        "setting": setting.id,
        "params": setting.label(),
        "logs": len(rows),
        "failed": len(rows) - len(ok),
        "evaluated": len(evaluated),
        "queries": sum(r.get("queries") or 0 for r in ok),
        "accepted": sum(r.get("accepted") or 0 for r in ok),
    }
    for tol in ("fine", "coarse"):
        for key in ("tp", "accepted", "common"):
            out[f"{key}_{tol}"] = sum(r[f"{key}_{tol}"] for r in evaluated)
        out[f"precision_{tol}"] = _ratio(out[f"tp_{tol}"], out[f"accepted_{tol}"])
        out[f"recall_{tol}"] = _ratio(out[f"tp_{tol}"], out[f"common_{tol}"])
    for key in ("odom_rmse_m", "corrected_rmse_m", "odom_endpoint_m", "corrected_endpoint_m"):
        out[key] = _mean([r[key] for r in evaluated])
    out["worse_than_odometry"] = sum(
        1 for r in evaluated if r["corrected_rmse_m"] > r["odom_rmse_m"]
    )
    return out


def plot_pr(path: Path, rows: list[dict[str, Any]]) -> Path | None:
    """Precision@1 against Recall@1, a point per setting (the fine series labelled by the
    setting ids), one series per tolerance; None when no setting was evaluated."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    series = {
        tol: [
            r for r in rows if r[f"precision_{tol}"] is not None and r[f"recall_{tol}"] is not None
        ]
        for tol in ("fine", "coarse")
    }
    if not any(series.values()):
        return None
    fig, ax = plt.subplots(figsize=(5.5, 5), layout="constrained")
    for tol, pts in series.items():
        pts = sorted(pts, key=lambda r: r[f"recall_{tol}"])
        xs, ys = [r[f"recall_{tol}"] for r in pts], [r[f"precision_{tol}"] for r in pts]
        ax.plot(xs, ys, "o-", ms=4, label=f"{tol} tolerance")
        for r, x, y in zip(pts, xs, ys, strict=True) if tol == "fine" else ():
            ax.annotate(r["setting"], (x, y), fontsize=7, xytext=(3, 3), textcoords="offset points")
    ax.set_xlim(0.0, 1.02)
    ax.set_ylim(0.0, 1.02)
    ax.set_xlabel("Recall@1 (pooled over logs)")
    ax.set_ylabel("Precision@1 (pooled over logs)")
    ax.set_title("decod sweep: one point per setting")
    ax.grid(alpha=0.3)
    ax.legend(loc="lower left")
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def write_sweep_summary(result: SweepResult) -> list[Path]:
    """``runs.csv``, ``sweep.csv``, ``sweep.md``, ``sweep.json`` and ``pr_curve.png``."""
    out = result.out_dir
    extractions = sum(result.extractions.values())
    notes = [
        f"{len(result.settings)} settings x {len(result.extractions)} logs; {extractions} "
        f"extractions; {result.wall_s:.1f} s wall time on {result.engine}.",
        *[f"- `{s.id}`: {s.label()}" for s in result.settings],
        *result.notes,
    ]
    doc = {
        "engine": result.engine,
        "wall_s": result.wall_s,
        "settings": {s.id: s.params for s in result.settings},
        "extractions": result.extractions,
        "notes": notes,
        "setting_rows": result.setting_rows,
        "run_rows": result.run_rows,
    }
    written = [
        write_csv(out / "runs.csv", result.run_rows, RUNS_COLUMNS),
        write_csv(out / "sweep.csv", result.setting_rows, SETTING_COLUMNS),
        write_markdown(
            out / "sweep.md",
            "decod sweep",
            notes,
            [
                ("settings (pooled over logs)", result.setting_rows, SETTING_COLUMNS),
                ("runs", result.run_rows, MARKDOWN_RUN_COLUMNS),
            ],
        ),
    ]
    (out / "sweep.json").write_text(json.dumps(doc, indent=2, default=str), encoding="utf-8")
    written.append(out / "sweep.json")
    if (png := plot_pr(out / "pr_curve.png", result.setting_rows)) is not None:
        written.append(png)
    return written
