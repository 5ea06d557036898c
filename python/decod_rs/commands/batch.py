"""``decod batch LOGS... --out DIR``: ``decod run`` on every log (on Dask or a local process
pool), one output directory each, and ``summary.csv`` / ``summary.md``. Exit status 1 when
a log failed (the others still ran)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from decod_rs.batch.cli_options import add_common_arguments, jobs_from_args
from decod_rs.batch.engine import dask_available, open_engine

if TYPE_CHECKING:
    from decod_rs.batch.batch import LogOutcome


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "batch",
        help="decod run on many logs (Dask or a process pool); a summary table",
        description="Run every log (files, directories, globs and/or a --manifest with "
        "per-log options and ground truth) into OUT/<name>/, skipping complete runs "
        "(--force redoes them), and write OUT/summary.csv and summary.md. A failed log is "
        "reported (OUT/<name>/error.txt) and does not stop the others.",
    )
    add_common_arguments(p)
    p.set_defaults(func=run)


def engine_note(kind: str) -> str | None:
    """A line saying the engine fell back, or None."""
    if kind == "auto" and not dask_available():
        return "dask not installed (pip install 'decod-rs[batch]'): local process pool"
    return None


def run(args: argparse.Namespace) -> int:
    # Imported here, not with the parser: GTSAM is not needed to print a command's help.
    from decod_rs.batch.batch import run_batch

    jobs, manifest = jobs_from_args(args)
    if manifest is not None and manifest.grid:
        print(f"note: {manifest.source}'s [sweep] grid is for `decod sweep`; ignored here")
    if (note := engine_note(args.engine)) is not None:
        print(f"note: {note}")
    out = Path(args.out).resolve()
    done = 0

    def progress(outcome: LogOutcome) -> None:
        nonlocal done
        done += 1
        wall = "" if outcome.wall_s is None else f" ({outcome.wall_s:.1f} s)"
        error = f": {outcome.error}" if outcome.error else ""
        print(f"[{done}/{len(jobs)}] {outcome.name}: {outcome.status}{wall}{error}", flush=True)

    with open_engine(
        args.engine,
        address=args.address,
        workers=args.workers,
        memory_per_worker=args.memory_per_worker,
    ) as engine:
        print(f"{len(jobs)} logs on {engine.description}", flush=True)
        result = run_batch(jobs, out, engine, force=args.force, on_done=progress)
    print((out / "summary.md").read_text(encoding="utf-8"))
    print(f"wrote {out / 'summary.csv'}, {out / 'summary.md'}")
    return 1 if result.failed else 0
