"""The batch manifest: per-log options, ground truth and a sweep grid, as data (TOML or JSON).

A manifest is read, never executed. Format version 1 (``version = 1`` is required)::

    version = 1

    [defaults]                 # optional: options for every [[log]] of this manifest
    preset = "pipe"
    imu_topic = "/imu"

    [[log]]
    path = "runs/a/log"        # required; relative paths are from the manifest's folder
    name = "a"                 # optional: the output directory's name
    odom_tum = "runs/a/lio.tum"
    gt = "runs/a/gt.tum"       # optional: evaluate against this ground truth (TUM)
    joints = "runs/a/joints.json"

    [sweep]                    # optional: `decod sweep`'s grid, parameter -> values
    "matching.min_inliers" = [6, 9, 15]

Option keys (in ``[defaults]`` and ``[[log]]``) are ``decod run``'s: ``preset``, ``config``,
``points_topic``, ``odom_topic``, ``odom_tum``, ``imu_topic``, ``use_imu``, ``mode``,
``loops``, ``sequential``, ``plots``, ``map``. A log's own keys beat ``[defaults]``, which beat the
command line. An unknown key, a wrong type or a size beyond the limits below is a
:class:`ManifestError` naming the file and the key.
"""

from __future__ import annotations

import json
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

MANIFEST_VERSION = 1
#: Limits on what a manifest may hold: far above a day of inspections (dozens of logs) or
#: the paper's evaluation (17 GEODE sequences), low enough that a wrong file is refused
#: before anything runs.
MAX_MANIFEST_BYTES = 1 << 20
MAX_LOGS = 10_000
MAX_STRING_CHARS = 4096
MAX_GRID_VALUES = 100

PRESET_VALUES = ("auto", "tunnel", "pipe")
MODE_VALUES = ("auto", "batch", "online")

#: Option key -> its kind: ``str``, ``path`` (resolved from the manifest's folder) or
#: ``bool``; ``preset`` and ``mode`` are strings from a fixed set.
OPTION_KINDS: dict[str, str] = {
    "preset": "str",
    "config": "path",
    "points_topic": "str",
    "odom_topic": "str",
    "odom_tum": "path",
    "imu_topic": "str",
    "use_imu": "bool",
    "mode": "str",
    "loops": "bool",
    "sequential": "bool",
    "plots": "bool",
    "map": "bool",
}
LOG_KINDS: dict[str, str] = {
    "path": "path",
    "name": "str",
    "gt": "path",
    "joints": "path",
    **OPTION_KINDS,
}
TOP_KEYS = ("version", "defaults", "log", "sweep")
CHOICES = {"preset": PRESET_VALUES, "mode": MODE_VALUES}

__all__ = ["MANIFEST_VERSION", "Manifest", "ManifestError", "ManifestLog", "load_manifest"]


class ManifestError(ValueError):
    """A manifest that cannot be used; the message names the file and the key."""


@dataclass(frozen=True)
class ManifestLog:
    """One ``[[log]]``: the log, its optional name, ground truth and joints, and its
    options (``[defaults]`` merged under its own keys; paths resolved)."""

    path: Path
    name: str | None = None
    gt: Path | None = None
    joints: Path | None = None
    options: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Manifest:
    """A loaded manifest: its file, the logs, and the sweep grid (parameter -> values)."""

    source: Path
    logs: list[ManifestLog]
    grid: dict[str, list[Any]]


def _parse(path: Path) -> dict[str, Any]:
    size = path.stat().st_size
    if size > MAX_MANIFEST_BYTES:
        raise ManifestError(f"{path}: {size} bytes, more than the {MAX_MANIFEST_BYTES} allowed")
    text = path.read_text(encoding="utf-8")
    try:
        if path.suffix == ".json":
            doc = json.loads(text)
        else:
            doc = tomllib.loads(text)
    except (json.JSONDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ManifestError(f"{path}: not valid {path.suffix[1:] or 'TOML'}: {exc}") from None
    if not isinstance(doc, dict):
        raise ManifestError(f"{path}: expected a table (object) at the top level")
    return doc


def _value(path: Path, where: str, kind: str, value: Any) -> Any:
    """One checked value: the right type, within the size limits, a path resolved."""
    if kind == "bool":
        if not isinstance(value, bool):
            raise ManifestError(f"{path}: {where}: expected true or false, got {value!r}")
        return value
    if not isinstance(value, str) or not value:
        raise ManifestError(f"{path}: {where}: expected a non-empty string, got {value!r}")
    if len(value) > MAX_STRING_CHARS:
        raise ManifestError(f"{path}: {where}: longer than {MAX_STRING_CHARS} characters")
    key = where.rsplit(".", 1)[-1]
    if key in CHOICES and value not in CHOICES[key]:
        raise ManifestError(f"{path}: {where}: {value!r} is not one of {CHOICES[key]}")
    if kind == "path":
        return (path.parent / value).resolve()
    return value


def _table(path: Path, where: str, table: Any, kinds: dict[str, str]) -> dict[str, Any]:
    if not isinstance(table, dict):
        raise ManifestError(f"{path}: {where}: expected a table (object)")
    out = {}
    for key, value in table.items():
        if key not in kinds:
            raise ManifestError(
                f"{path}: unknown key {where}.{key} (known: {', '.join(sorted(kinds))})"
            )
        out[key] = _value(path, f"{where}.{key}", kinds[key], value)
    return out


def _name(path: Path, where: str, name: str | None) -> str | None:
    if name is not None and (name in (".", "..") or "/" in name or "\\" in name):
        raise ManifestError(f"{path}: {where}.name: {name!r} is not a plain directory name")
    return name


def _logs(path: Path, doc: dict[str, Any]) -> list[ManifestLog]:
    defaults = _table(path, "defaults", doc.get("defaults", {}), OPTION_KINDS)
    entries = doc.get("log", [])
    if not isinstance(entries, list):
        raise ManifestError(f"{path}: log: expected an array of tables ([[log]])")
    if len(entries) > MAX_LOGS:
        raise ManifestError(f"{path}: log: {len(entries)} logs, more than {MAX_LOGS}")
    logs = []
    for k, entry in enumerate(entries):
        where = f"log[{k}]"
        values = _table(path, where, entry, LOG_KINDS)
        if "path" not in values:
            raise ManifestError(f"{path}: {where}: missing key `path`")
        options = {**defaults, **{o: values[o] for o in OPTION_KINDS if o in values}}
        logs.append(
            ManifestLog(
                path=values["path"],
                name=_name(path, where, values.get("name")),
                gt=values.get("gt"),
                joints=values.get("joints"),
                options=options,
            )
        )
    names = [lg.name for lg in logs if lg.name is not None]
    if dupes := sorted({n for n in names if names.count(n) > 1}):
        raise ManifestError(f"{path}: log names used twice: {', '.join(dupes)}")
    return logs


def _grid(path: Path, table: Any) -> dict[str, list[Any]]:
    if not isinstance(table, dict):
        raise ManifestError(f"{path}: sweep: expected a table of parameter = [values]")
    grid = {}
    for key, values in table.items():
        where = f"sweep.{key}"
        if isinstance(values, dict):
            raise ManifestError(
                f"{path}: {where}: a table; write dotted parameters in quotes "
                f'("matching.min_inliers" = [6, 9])'
            )
        values = values if isinstance(values, list) else [values]
        if not values or len(values) > MAX_GRID_VALUES:
            raise ManifestError(f"{path}: {where}: expected 1 to {MAX_GRID_VALUES} values")
        if any(isinstance(v, dict | list) for v in values):
            raise ManifestError(f"{path}: {where}: values must be numbers, strings or booleans")
        grid[key] = values
    return grid


def load_manifest(path: str | Path) -> Manifest:
    """Read and check the manifest at ``path`` (``.json`` is JSON, anything else TOML)."""
    source = Path(path)
    if not source.is_file():
        raise FileNotFoundError(f"manifest {source}: no such file")
    doc = _parse(source)
    for key in doc:
        if key not in TOP_KEYS:
            raise ManifestError(f"{source}: unknown key {key} (known: {', '.join(TOP_KEYS)})")
    version = doc.get("version")
    if version != MANIFEST_VERSION:
        raise ManifestError(
            f"{source}: version: expected {MANIFEST_VERSION}, got {version!r} "
            f"(add `version = {MANIFEST_VERSION}` at the top)"
        )
    return Manifest(source, _logs(source, doc), _grid(source, doc.get("sweep", {})))
