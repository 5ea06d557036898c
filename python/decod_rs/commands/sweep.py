"""``decod sweep LOGS... --param matching.min_inliers=6,9,15 --out DIR``: every log at every
setting of the grid, one extraction per log when only ``matching.*`` / ``graph.*`` change;
precision-recall points and trajectory metrics per setting (``sweep.csv``, ``sweep.md``,
``pr_curve.png``). Exit status 1 when a run failed."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING, Any

from decod_rs.batch.cli_options import add_common_arguments, jobs_from_args
from decod_rs.batch.engine import open_engine
from decod_rs.batch.grid import check_params, implied_acceptance, parse_param, settings_from_grid
from decod_rs.commands.batch import engine_note

if TYPE_CHECKING:
    from decod_rs.batch.sweep import TaskOutcome


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "sweep",
        help="many logs over a parameter grid: precision-recall and trajectory per setting",
        description="Run every log at every setting of a grid (--param KEY=V1,V2,... "
        "repeated: the Cartesian product; and/or the manifest's [sweep] table). Settings "
        "that differ only in matching.* / graph.* share one extraction per log. "
        "matching.min_inliers acts under matching.acceptance = 'fixed' (the paper's rule) "
        "and matching.false_alarm_rate under 'null_model' (the default): sweeping either "
        "without giving matching.acceptance sets the one it needs.",
    )
    add_common_arguments(p)
    p.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="KEY=V1,V2",
        help="a swept parameter and its values (decod dump-config lists the keys); a single "
        "value fixes it for every setting",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    # Imported here, not with the parser: GTSAM is not needed to print a command's help.
    from decod_rs.batch.sweep import run_sweep

    jobs, manifest = jobs_from_args(args)
    grid: dict[str, list[Any]] = dict(manifest.grid) if manifest is not None else {}
    grid.update(parse_param(text) for text in args.param)
    settings = settings_from_grid(grid)
    check_params(settings, args.preset)
    if (acceptance := implied_acceptance(grid)) is not None:
        print(f"note: matching.acceptance = {acceptance!r} for every setting (what the grid needs)")
    if (note := engine_note(args.engine)) is not None:
        print(f"note: {note}")
    out = Path(args.out).resolve()
    done = 0

    def progress(task: TaskOutcome) -> None:
        nonlocal done
        for sid, outcome in sorted(task.outcomes.items()):
            done += 1
            error = f": {outcome.error}" if outcome.error else ""
            where = f"[{done}/{len(jobs) * len(settings)}] {sid} {outcome.name}"
            print(f"{where}: {outcome.status}{error}", flush=True)

    with open_engine(
        args.engine,
        address=args.address,
        workers=args.workers,
        memory_per_worker=args.memory_per_worker,
    ) as engine:
        print(f"{len(settings)} settings x {len(jobs)} logs on {engine.description}", flush=True)
        result = run_sweep(jobs, settings, out, engine, force=args.force, on_done=progress)
    print((out / "sweep.md").read_text(encoding="utf-8"))
    print(
        f"wrote {out / 'sweep.csv'}, {out / 'runs.csv'}, {out / 'sweep.md'}, {out / 'pr_curve.png'}"
    )
    return 1 if any(r["failed"] for r in result.setting_rows) else 0
