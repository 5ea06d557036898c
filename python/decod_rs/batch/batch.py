"""``decod batch``: every log through ``run_log`` on an engine, one output directory each,
and a summary table.

``OUT/<name>/`` holds a log's run (the files of ``decod run``); a log that fails gets
``OUT/<name>/error.txt`` (the traceback) and a ``failed`` row, and the others go on. A run
is complete when its ``report.json`` exists (``run_log`` writes it last) and names the same
log: a re-run skips it (``force=True`` redoes it). ``OUT/summary.csv``, ``summary.md`` and
``summary.json`` list every log: status, counts, stage timings, the wall time of the task
and, with ground truth, the evaluation (:mod:`decod_rs.batch.summary`).
"""

from __future__ import annotations

import json
import time
import traceback
from collections.abc import Callable
from concurrent.futures import Future, as_completed
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from decod_rs.allocator import keep_freed_memory
from decod_rs.batch.engine import Engine
from decod_rs.batch.jobs import LogJob
from decod_rs.batch.summary import (
    RUN_COLUMNS,
    evaluation_row,
    report_row,
    write_csv,
    write_markdown,
)
from decod_rs.pipeline import run_log

T = TypeVar("T")
K = TypeVar("K")

ERROR_FILE = "error.txt"
MARKDOWN_COLUMNS = (
    "name",
    "status",
    "scans",
    "landmarks",
    "queries",
    "accepted",
    "odometry_only_m",
    "log_s",
    "wall_s",
    "realtime_x",
    "precision_fine",
    "recall_fine",
    "odom_rmse_m",
    "corrected_rmse_m",
    "odom_endpoint_m",
    "corrected_endpoint_m",
    "error",
)

__all__ = [
    "BatchResult",
    "LogOutcome",
    "collect",
    "complete_run",
    "prepare_run_dir",
    "run_batch",
    "run_one",
    "summary_row",
]


@dataclass
class LogOutcome:
    """What became of one log: ``status`` is ``ok``, ``skipped`` (complete already) or
    ``failed`` (``error``: the exception's type and message); ``wall_s`` the task's time."""

    name: str
    log: str
    run_dir: str
    status: str
    wall_s: float | None = None
    error: str | None = None


@dataclass
class BatchResult:
    """A finished batch: one summary row per job (in the jobs' order), the engine used and
    the wall time."""

    out_dir: Path
    rows: list[dict[str, Any]]
    engine: str
    wall_s: float
    notes: list[str] = field(default_factory=list)

    @property
    def failed(self) -> int:
        return sum(1 for r in self.rows if r["status"] == "failed")


def complete_run(run_dir: Path, log: Path) -> bool:
    """Whether ``run_dir`` holds a complete run of ``log``. Raises ``FileExistsError`` when
    it holds a complete run of another log (never overwritten without ``--force``)."""
    report = run_dir / "report.json"
    if not report.is_file():
        return False
    try:
        ran = json.loads(report.read_text(encoding="utf-8")).get("log")
    except (json.JSONDecodeError, AttributeError):
        return False  # unreadable: not complete, run it again
    if ran is not None and Path(ran).resolve() != log.resolve():
        raise FileExistsError(f"{run_dir} holds a run of {ran}; use --force or another --out")
    return True


def failure(exc: BaseException) -> str:
    """One line for the summary: the exception's type and message."""
    return f"{type(exc).__name__}: {exc}".strip()


def run_one(job: LogJob, run_dir: Path) -> LogOutcome:
    """Run ``job`` into ``run_dir`` (a worker's task). Never raises for a bad log: the
    error goes into the outcome and ``error.txt``."""
    keep_freed_memory()  # a worker process is decod's (decod_rs.allocator)
    t0 = time.perf_counter()
    try:
        run_log(job.log, run_dir, **job.options.run_kwargs())
    except Exception as exc:
        run_dir.mkdir(parents=True, exist_ok=True)
        (run_dir / ERROR_FILE).write_text(traceback.format_exc(), encoding="utf-8")
        wall = time.perf_counter() - t0
        return LogOutcome(job.name, str(job.log), str(run_dir), "failed", wall, failure(exc))
    return LogOutcome(job.name, str(job.log), str(run_dir), "ok", time.perf_counter() - t0)


def prepare_run_dir(job: LogJob, run_dir: Path, force: bool) -> LogOutcome | None:
    """The outcome of a job that needs no task (skipped, or a conflicting directory), else
    None after clearing what would make a crashed run look complete."""
    try:
        if not force and complete_run(run_dir, job.log):
            return LogOutcome(job.name, str(job.log), str(run_dir), "skipped")
    except FileExistsError as exc:
        return LogOutcome(job.name, str(job.log), str(run_dir), "failed", error=str(exc))
    for stale in ("report.json", ERROR_FILE, "evaluation.json"):
        (run_dir / stale).unlink(missing_ok=True)
    return None


def summary_row(job: LogJob, outcome: LogOutcome) -> dict[str, Any]:
    row: dict[str, Any] = {
        "name": job.name,
        "status": outcome.status,
        "log": str(job.log),
        "wall_s": outcome.wall_s,
        "error": outcome.error,
    }
    if outcome.status == "failed":
        return row
    run_dir = Path(outcome.run_dir)
    row.update(report_row(run_dir))
    if job.gt is not None:
        row.update(evaluation_row(run_dir, job.gt, job.joints))
    return row


def collect(
    futures: dict[Future[T], K],
    lost: Callable[[K, BaseException], T],
    on_done: Callable[[T], None] | None = None,
) -> dict[K, T]:
    """Each future's result by its key, as they complete (``on_done`` is called with each);
    a future that raised (a worker killed, a pool broken) gives ``lost(key, exc)``."""
    results: dict[K, T] = {}
    for future in as_completed(futures):
        key = futures[future]
        try:
            results[key] = future.result()
        except Exception as exc:
            results[key] = lost(key, exc)
        if on_done is not None:
            on_done(results[key])
    return results


def run_batch(
    jobs: list[LogJob],
    out_dir: Path,
    engine: Engine,
    *,
    force: bool = False,
    on_done: Callable[[LogOutcome], None] | None = None,
) -> BatchResult:
    """Run ``jobs`` on ``engine`` into ``out_dir/<job.name>/`` and write the summary
    (module doc). ``on_done`` is called with each outcome as it arrives (progress)."""
    t0 = time.perf_counter()
    out_dir.mkdir(parents=True, exist_ok=True)
    outcomes: dict[str, LogOutcome] = {}
    futures: dict[Future[Any], str] = {}
    by_name = {job.name: job for job in jobs}
    for job in jobs:
        run_dir = out_dir / job.name
        if (done := prepare_run_dir(job, run_dir, force)) is not None:
            outcomes[job.name] = done
            if on_done is not None:
                on_done(done)
            continue
        futures[engine.executor.submit(run_one, job, run_dir)] = job.name

    def lost(name: str, exc: BaseException) -> LogOutcome:
        job = by_name[name]
        return LogOutcome(name, str(job.log), str(out_dir / name), "failed", None, failure(exc))

    outcomes.update(collect(futures, lost, on_done))
    rows = [summary_row(job, outcomes[job.name]) for job in jobs]
    result = BatchResult(out_dir, rows, engine.description, time.perf_counter() - t0)
    write_batch_summary(result)
    return result


def write_batch_summary(result: BatchResult) -> list[Path]:
    """``summary.csv``, ``summary.md`` and ``summary.json`` in the batch's directory."""
    out = result.out_dir
    counts = {s: sum(1 for r in result.rows if r["status"] == s) for s in ("ok", "skipped")}
    notes = [
        f"{len(result.rows)} logs: {counts['ok']} run, {counts['skipped']} skipped "
        f"(complete already), {result.failed} failed; {result.wall_s:.1f} s wall time on "
        f"{result.engine}.",
        *result.notes,
    ]
    doc = {"engine": result.engine, "wall_s": result.wall_s, "notes": notes, "rows": result.rows}
    return [
        write_csv(out / "summary.csv", result.rows, RUN_COLUMNS),
        write_markdown(
            out / "summary.md", "decod batch", notes, [("logs", result.rows, MARKDOWN_COLUMNS)]
        ),
        _write_json(out / "summary.json", doc),
    ]


def _write_json(path: Path, doc: dict[str, Any]) -> Path:
    path.write_text(json.dumps(doc, indent=2, default=str), encoding="utf-8")
    return path
