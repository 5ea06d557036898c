"""The command-line options ``decod batch`` and ``decod sweep`` share: the logs, the
manifest, ``decod run``'s options (applied to every log), the output and the engine.

``--odom-tum`` is not among them: a TUM file belongs to one log, so it goes into the
manifest (``odom_tum`` in that log's ``[[log]]``); nor is ``--rerun FILE.rrd``, a viewer's
recording of one run (``decod run`` it on the log you want to look at).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from decod_rs.batch.engine import ENGINES
from decod_rs.batch.jobs import LogJob, RunOptions, build_jobs
from decod_rs.batch.manifest import Manifest, load_manifest
from decod_rs.config import MODES, PRESETS

__all__ = ["add_common_arguments", "jobs_from_args", "run_options"]


def _add_run_options(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("decod run options (every log; a manifest's keys beat them)")
    g.add_argument("--preset", choices=("auto", *PRESETS), default="auto")
    g.add_argument("--points-topic", help="PointCloud2 / Livox CustomMsg topic")
    g.add_argument("--odom-topic", help="odometry topic (per-log TUM files: the manifest)")
    imu = g.add_mutually_exclusive_group()
    imu.add_argument("--imu-topic", help="IMU topic for gravity (default: the unique one)")
    imu.add_argument("--no-imu", action="store_true", help="gravity is the sensor's -z axis")
    g.add_argument("--config", type=Path, help="TOML file overriding preset parameters")
    g.add_argument("--mode", choices=MODES, default="auto")
    g.add_argument("--no-loops", action="store_true", help="report matches, add no factor")
    g.add_argument("--no-sequential", action="store_true", help="graph.sequential = false")
    g.add_argument("--no-plots", action="store_true", help="no PNG per run (faster)")
    g.add_argument("--map", action="store_true", help="PLY maps and map_consistency.png per run")


def _add_engine_options(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("engine")
    g.add_argument(
        "--engine",
        choices=ENGINES,
        default="auto",
        help="auto (default): dask if installed (pip install 'decod-rs[batch]'), else a "
        "local process pool; serial: one log after another in this process",
    )
    g.add_argument(
        "--address", help="a dask scheduler's address (tcp://host:8786) instead of a local cluster"
    )
    g.add_argument("--workers", type=int, help="local workers (default: one per core)")
    g.add_argument("--memory-per-worker", help="dask's memory limit per local worker, e.g. 4GiB")


def add_common_arguments(p: argparse.ArgumentParser) -> None:
    """LOGS, --manifest, --out, --force, decod run's options and the engine's."""
    p.add_argument(
        "logs",
        nargs="*",
        metavar="LOGS",
        help=".mcap / .bag files, rosbag2 or other "
        "directories (every log below), globs (quote them: 'runs/*/log')",
    )
    p.add_argument(
        "--manifest", type=Path, help="TOML/JSON manifest: per-log options, ground truth, grid"
    )
    p.add_argument("-o", "--out", type=Path, required=True, help="output directory")
    p.add_argument("--force", action="store_true", help="redo runs that are complete")
    _add_run_options(p)
    _add_engine_options(p)


def run_options(args: argparse.Namespace) -> RunOptions:
    """The ``decod run`` options given on the command line."""
    return RunOptions(
        preset=args.preset,
        config=None if args.config is None else args.config.resolve(),
        points_topic=args.points_topic,
        odom_topic=args.odom_topic,
        imu_topic=args.imu_topic,
        use_imu=not args.no_imu,
        mode=args.mode,
        loops=not args.no_loops,
        sequential=False if args.no_sequential else None,
        plots=not args.no_plots,
        map=args.map,
    )


def jobs_from_args(args: argparse.Namespace) -> tuple[list[LogJob], Manifest | None]:
    """The jobs named by LOGS and --manifest, and the manifest (None without one)."""
    manifest = load_manifest(args.manifest) if args.manifest is not None else None
    return build_jobs(list(args.logs), manifest, run_options(args)), manifest
