"""What a batch runs: one :class:`LogJob` per log, with the ``decod run`` options it gets.

Logs come from the command line (files, directories or globs, :func:`discover_logs`) and
from a manifest (:mod:`decod_rs.batch.manifest`). Every job has a unique output name (its
directory under ``--out``): the log's stem, prefixed with as many parent folder names as it
takes to tell logs apart (``a/log`` and ``b/log`` become ``a_log`` and ``b_log``), or the
manifest's ``name``.
"""

from __future__ import annotations

import glob
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any

from decod_rs.batch.manifest import Manifest

#: File suffixes taken as logs when a directory is scanned or a glob matches (``decod run``
#: reads MCAP files and ROS 1 bags; a rosbag2 directory is recognised by its metadata.yaml).
LOG_SUFFIXES = (".mcap", ".bag")
ROSBAG2_METADATA = "metadata.yaml"

__all__ = ["LOG_SUFFIXES", "LogJob", "RunOptions", "build_jobs", "discover_logs", "unique_names"]


@dataclass(frozen=True)
class RunOptions:
    """The ``decod run`` options of one log (same names and defaults as
    :func:`decod_rs.pipeline.run_log`; ``config`` is ``config_path``)."""

    preset: str = "auto"
    config: Path | None = None
    points_topic: str | None = None
    odom_topic: str | None = None
    odom_tum: Path | None = None
    imu_topic: str | None = None
    use_imu: bool = True
    mode: str = "auto"
    loops: bool = True
    sequential: bool | None = None
    plots: bool = True
    map: bool = False

    def run_kwargs(self) -> dict[str, Any]:
        """Keyword arguments of :func:`decod_rs.pipeline.run_log` (progress bars off)."""
        values = {f.name: getattr(self, f.name) for f in fields(self)}
        values["config_path"] = values.pop("config")
        values["progress"] = False
        return values

    def updated(self, values: dict[str, Any]) -> RunOptions:
        """A copy with ``values`` (option name -> value) replacing the defaults here."""
        return replace(self, **values)


@dataclass(frozen=True)
class LogJob:
    """One log to run: its output ``name`` (a directory under ``--out``), the log, its
    options, and the ground truth (TUM) and simulator ``joints.json`` to evaluate it with."""

    name: str
    log: Path
    options: RunOptions
    gt: Path | None = None
    joints: Path | None = None


def _has_glob(spec: str) -> bool:
    return any(ch in spec for ch in "*?[")


def _logs_under(root: Path) -> list[Path]:
    """Rosbag2 directories and MCAP / bag files under ``root`` (a rosbag2 directory is one
    log: its own files are not listed again), sorted."""
    if (root / ROSBAG2_METADATA).is_file():
        return [root]
    found: list[Path] = []
    for child in sorted(root.iterdir()):
        if child.is_dir():
            found.extend(_logs_under(child))
        elif child.suffix in LOG_SUFFIXES:
            found.append(child)
    return found


def discover_logs(specs: list[str]) -> list[Path]:
    """The logs named by ``specs``: a file is a log as given; a directory is a log if it is
    a rosbag2 directory, else every log below it; a glob expands to its matches (files among
    them only with a log suffix). Duplicates are dropped, order is kept.

    Raises ``FileNotFoundError`` naming a spec that matches no log, so that a typo stops
    the batch before hours of runs rather than after.
    """
    logs: list[Path] = []
    for spec in specs:
        if _has_glob(spec):
            matches = [Path(m) for m in sorted(glob.glob(spec, recursive=True))]
            found = [
                log
                for m in matches
                for log in (_logs_under(m) if m.is_dir() else [m])
                if log.is_dir() or log.suffix in LOG_SUFFIXES
            ]
        else:
            path = Path(spec)
            if not path.exists():
                raise FileNotFoundError(f"log {spec}: no such file or directory")
            found = _logs_under(path) if path.is_dir() else [path]
        if not found:
            raise FileNotFoundError(f"{spec}: no log found (.mcap, .bag or rosbag2 directory)")
        logs.extend(found)
    unique: dict[Path, None] = {}
    for log in logs:
        unique.setdefault(log.resolve(), None)
    return list(unique)


def _name_parts(log: Path) -> list[str]:
    parts = [p for p in log.resolve().parts if p not in ("/", "")]
    parts[-1] = Path(parts[-1]).stem if log.suffix in LOG_SUFFIXES else parts[-1]
    return parts


def unique_names(logs: list[Path], taken: set[str] | None = None) -> list[str]:
    """An output name per log, unique among themselves and ``taken``: the stem, then as
    many parent folders as needed, joined with ``_``."""
    parts = [_name_parts(log) for log in logs]
    depth = [1] * len(logs)
    reserved = set(taken or ())
    while True:
        names = ["_".join(p[-d:]) for p, d in zip(parts, depth, strict=True)]
        clash = {n for n in names if names.count(n) > 1 or n in reserved}
        grow = [k for k, n in enumerate(names) if n in clash and depth[k] < len(parts[k])]
        if not grow:
            break
        for k in grow:
            depth[k] += 1
    for k, name in enumerate(names):
        if name in clash:  # identical full paths cannot happen (discover_logs drops them)
            names[k] = f"{name}_{k}"
    return names


def build_jobs(specs: list[str], manifest: Manifest | None, options: RunOptions) -> list[LogJob]:
    """The jobs of a batch: the logs named on the command line (``specs``, with
    ``options``), then the manifest's logs (its options over ``options``). Raises
    ``ValueError`` when there is no log at all."""
    logs = discover_logs(specs) if specs else []
    entries = manifest.logs if manifest is not None else []
    taken = {e.name for e in entries if e.name is not None}
    unnamed = [e.path for e in entries if e.name is None]
    names = iter(unique_names(logs + unnamed, taken))
    jobs = [LogJob(next(names), log, options) for log in logs]
    for entry in entries:
        jobs.append(
            LogJob(
                name=entry.name if entry.name is not None else next(names),
                log=entry.path,
                options=options.updated(entry.options),
                gt=entry.gt,
                joints=entry.joints,
            )
        )
    if not jobs:
        raise ValueError("no log to run: give LOGS (files, directories, globs) or --manifest")
    return jobs
