"""The run directory's CSV files (DESIGN.md "The command line and its files"): readers and
writers for ``loops.csv`` and ``landmarks.csv``, and the bridge from loop rows to graph
constraints.

``loops.csv``: the contract's 17 columns (``LOOPS_COLUMNS``), one row per query boundary with
its Top-1 candidate, then any extra columns (kept as strings in ``LoopTable.extra``). A query
with no candidate may leave the candidate fields empty (read as NaN, never accepted). A run
with ``--survey`` adds one row per landmark against the survey (column ``session`` =
``survey``; :func:`within_run` drops them).

``landmarks.csv``: every detected boundary. Required columns ``stamp, origin_x, origin_y,
origin_z``; optional ``axis_x, axis_y, axis_z`` (NaN when absent), ``radius_m``,
``chainage_m``; other columns are ignored. ``LANDMARKS_COLUMNS`` is what ``write_landmarks_csv``
writes. Origins and axes are in the body frame of the submap's anchor scan at ``stamp``.

A run writes into ``NAME.partial`` beside its directory and publishes at the end
(:func:`staged_run_dir`), so an interrupted run never leaves a directory that looks finished:
``report.json`` appears in ``NAME`` only with every other file of the run beside it.
"""

from __future__ import annotations

import csv
import os
import shutil
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from decod_rs import _core
from decod_rs.graph import LoopConstraint

FloatArray = NDArray[np.float64]

LOOPS_COLUMNS = (
    "query_stamp,db_stamp,query_origin_x,query_origin_y,query_origin_z,"
    "query_axis_x,query_axis_y,query_axis_z,db_origin_x,db_origin_y,db_origin_z,"
    "db_axis_x,db_axis_y,db_axis_z,inliers,score,accepted"
).split(",")

LANDMARKS_COLUMNS = [
    *"stamp,origin_x,origin_y,origin_z,axis_x,axis_y,axis_z,radius_m,chainage_m".split(","),
    "track_id",
    "joint_id",
]

#: A loop stamp matches a graph node if they differ by less than this (stamps are written
#: with 9 decimals; anchors are scan stamps).
STAMP_MATCH_TOLERANCE_S = 1e-6

__all__ = [
    "LANDMARKS_COLUMNS",
    "LOOPS_COLUMNS",
    "LandmarkTable",
    "LoopTable",
    "check_run_dir",
    "landmark_spill",
    "loops_to_constraints",
    "read_landmarks_csv",
    "read_loops_csv",
    "staged_run_dir",
    "within_run",
    "write_landmarks_csv",
    "write_loops_csv",
]


@dataclass
class LoopTable:
    """``loops.csv`` as arrays: L rows; stamps (L,) s; origins (L, 3) m and axes (L, 3) in
    the respective anchor body frames; ``inliers`` (L,) int; ``score`` (L,); ``accepted`` (L,)
    bool; ``extra``: further columns by name, (L,) strings each."""

    query_stamp: FloatArray
    db_stamp: FloatArray
    query_origin: FloatArray
    query_axis: FloatArray
    db_origin: FloatArray
    db_axis: FloatArray
    inliers: NDArray[np.int64]
    score: FloatArray
    accepted: NDArray[np.bool_]
    extra: dict[str, list[str]] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.query_stamp.shape[0])


@dataclass
class LandmarkTable:
    """``landmarks.csv`` as arrays: M rows; ``stamp`` (M,) s; ``origin``/``axis`` (M, 3) in
    the anchor body frame; ``radius_m``, ``chainage_m`` (M,) (NaN where absent);
    ``track_id``/``joint_id`` (M,) the boundary track within a pass and the physical boundary
    (``joints.csv``), -1 where absent."""

    stamp: FloatArray
    origin: FloatArray
    axis: FloatArray
    radius_m: FloatArray
    chainage_m: FloatArray
    track_id: NDArray[np.int64] | None = None
    joint_id: NDArray[np.int64] | None = None

    def __len__(self) -> int:
        return int(self.stamp.shape[0])


def _read_rows(path: Path, required: Sequence[str]) -> tuple[list[str], list[dict[str, str]]]:
    with path.open(encoding="utf-8", newline="") as fh:
        reader = csv.DictReader(fh)
        header = [h.strip() for h in (reader.fieldnames or [])]
        missing = [c for c in required if c not in header]
        if missing:
            raise ValueError(f"{path}: missing column(s) {', '.join(missing)}")
        rows = []
        for row in reader:
            rows.append({k.strip(): (v or "").strip() for k, v in row.items() if k is not None})
    return header, rows


def _float(path: Path, lineno: int, name: str, text: str, allow_empty: bool) -> float:
    if text == "" and allow_empty:
        return float("nan")
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"{path}:{lineno}: column {name}: not a number: {text!r}") from None
    if not np.isfinite(value) and not allow_empty:
        raise ValueError(f"{path}:{lineno}: column {name}: not finite: {text!r}")
    return value


def read_loops_csv(path: str | Path) -> LoopTable:
    """Read ``loops.csv``; a malformed value raises ValueError naming file, line and column."""
    path = Path(path)
    header, rows = _read_rows(path, LOOPS_COLUMNS)
    n = len(rows)
    num = np.full((n, 16), np.nan)
    accepted = np.zeros(n, dtype=bool)
    for r, row in enumerate(rows):
        lineno = r + 2
        for c, name in enumerate(LOOPS_COLUMNS[:16]):
            # Candidate fields may be empty (no candidate); the query's may not.
            optional = not name.startswith("query_")
            num[r, c] = _float(path, lineno, name, row[name], optional)
        flag = row["accepted"].lower()
        if flag in ("1", "true"):
            accepted[r] = True
        elif flag not in ("0", "false", ""):
            raise ValueError(f"{path}:{lineno}: column accepted: expected 0 or 1, got {flag!r}")
    inliers = np.where(np.isfinite(num[:, 14]), num[:, 14], 0).astype(np.int64)
    extra = {h: [row.get(h, "") for row in rows] for h in header if h not in LOOPS_COLUMNS}
    return LoopTable(
        query_stamp=num[:, 0],
        db_stamp=num[:, 1],
        query_origin=num[:, 2:5],
        query_axis=num[:, 5:8],
        db_origin=num[:, 8:11],
        db_axis=num[:, 11:14],
        inliers=inliers,
        score=num[:, 15],
        accepted=accepted & np.isfinite(num[:, 1]),
        extra=extra,
    )


def write_loops_csv(path: str | Path, table: LoopTable) -> None:
    """Write ``table`` with the contract's columns first, then ``table.extra``."""
    extra_names = list(table.extra)
    with Path(path).open("w", encoding="utf-8", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(LOOPS_COLUMNS + extra_names)
        for r in range(len(table)):
            nums = [
                table.query_stamp[r],
                table.db_stamp[r],
                *table.query_origin[r],
                *table.query_axis[r],
                *table.db_origin[r],
                *table.db_axis[r],
            ]
            cells = ["" if not np.isfinite(v) else f"{v:.9f}" for v in nums]
            cells += [str(int(table.inliers[r])), f"{table.score[r]:.6f}"]
            cells.append("1" if table.accepted[r] else "0")
            cells += [table.extra[name][r] for name in extra_names]
            w.writerow(cells)


def read_landmarks_csv(path: str | Path) -> LandmarkTable:
    """Read ``landmarks.csv`` (columns in the module doc; unknown columns ignored)."""
    path = Path(path)
    header, rows = _read_rows(path, LANDMARKS_COLUMNS[:4])
    n = len(rows)

    def column(name: str, optional: bool) -> FloatArray:
        if name not in header:
            return np.full(n, np.nan)
        return np.array(
            [_float(path, r + 2, name, row[name], optional) for r, row in enumerate(rows)]
        )

    def ids(name: str) -> NDArray[np.int64] | None:
        if name not in header:
            return None
        values = column(name, True)
        return np.where(np.isfinite(values), values, -1).astype(np.int64)

    origin = np.column_stack([column(f"origin_{a}", False) for a in "xyz"]).reshape(n, 3)
    axis = np.column_stack([column(f"axis_{a}", True) for a in "xyz"]).reshape(n, 3)
    return LandmarkTable(
        stamp=column("stamp", False),
        origin=origin,
        axis=axis,
        radius_m=column("radius_m", True),
        chainage_m=column("chainage_m", True),
        track_id=ids("track_id"),
        joint_id=ids("joint_id"),
    )


def write_landmarks_csv(path: str | Path, table: LandmarkTable) -> None:
    """Write ``table`` with ``LANDMARKS_COLUMNS``."""
    with Path(path).open("w", encoding="utf-8", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(LANDMARKS_COLUMNS)
        none = np.full(len(table), -1, dtype=np.int64)
        tracks = none if table.track_id is None else table.track_id
        joints = none if table.joint_id is None else table.joint_id
        for r in range(len(table)):
            nums = [
                table.stamp[r],
                *table.origin[r],
                *table.axis[r],
                table.radius_m[r],
                table.chainage_m[r],
            ]
            cells = ["" if not np.isfinite(v) else f"{v:.9f}" for v in nums]
            w.writerow([*cells, str(int(tracks[r])), str(int(joints[r]))])


def within_run(table: LoopTable) -> LoopTable:
    """The rows of the run itself: without the cross-session rows of a run with ``--survey``
    (column ``session`` = ``survey``: their ``db_stamp`` is the survey's, not this run's)."""
    session = table.extra.get("session")
    if session is None:
        return table
    rows = np.array([s != "survey" for s in session], dtype=bool)
    return LoopTable(
        query_stamp=table.query_stamp[rows],
        db_stamp=table.db_stamp[rows],
        query_origin=table.query_origin[rows],
        query_axis=table.query_axis[rows],
        db_origin=table.db_origin[rows],
        db_axis=table.db_axis[rows],
        inliers=table.inliers[rows],
        score=table.score[rows],
        accepted=table.accepted[rows],
        extra={
            k: [v for v, ok in zip(col, rows, strict=True) if ok] for k, col in table.extra.items()
        },
    )


def loops_to_constraints(
    table: LoopTable, node_stamps: ArrayLike, accepted_only: bool = True
) -> list[LoopConstraint]:
    """Graph constraints from loop rows: each stamp becomes the index of the node with that
    stamp in ``node_stamps`` (N,) (e.g. the submap anchors). A stamp with no node within
    ``STAMP_MATCH_TOLERANCE_S`` raises ValueError: the geometry is in that anchor's frame."""
    nodes = np.asarray(node_stamps, dtype=np.float64)
    if nodes.ndim != 1 or nodes.size == 0:
        raise ValueError(f"node_stamps: expected (N,) with N >= 1, got {nodes.shape}")

    def index(stamp: float) -> int:
        k = int(np.argmin(np.abs(nodes - stamp)))
        if abs(nodes[k] - stamp) > STAMP_MATCH_TOLERANCE_S:
            raise ValueError(f"loop stamp {stamp!r} is not a node stamp (nearest {nodes[k]!r})")
        return k

    table = within_run(table)
    out = []
    for r in range(len(table)):
        if accepted_only and not table.accepted[r]:
            continue
        if not np.isfinite(table.db_stamp[r]):
            continue
        out.append(
            LoopConstraint(
                query_index=index(float(table.query_stamp[r])),
                db_index=index(float(table.db_stamp[r])),
                query_origin=table.query_origin[r],
                query_axis=table.query_axis[r],
                db_origin=table.db_origin[r],
                db_axis=table.db_axis[r],
                inliers=int(table.inliers[r]),
                score=float(table.score[r]),
            )
        )
    return out


#: Suffix of the directory a run writes into before it is published.
PARTIAL_SUFFIX = ".partial"


def _publish(staging: Path, out: Path) -> None:
    """Moves every entry of ``staging`` into ``out``, ``report.json`` last; entries of
    ``out`` with other names (the user's, ``error.txt`` of a batch) are left alone."""
    if not out.exists():
        os.replace(staging, out)  # one atomic rename
        return
    entries = sorted(staging.iterdir(), key=lambda p: p.name == "report.json")
    for entry in entries:
        target = out / entry.name
        if target.is_dir() and not target.is_symlink():
            shutil.rmtree(target)
        os.replace(entry, target)
    staging.rmdir()


def check_run_dir(out: Path) -> Path:
    """``out`` if a run can be published there (a directory, or nothing yet), else
    ``NotADirectoryError`` (checked before the run, not after it)."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise NotADirectoryError(20, "the run's output must be a directory", str(out))
    return out


def landmark_spill(out: Path) -> _core.Spill:
    """Where a run into ``out`` keeps its landmarks' cells (:class:`decod_rs._core.Spill`):
    a file in the directory ``out`` is published in (created if missing), on the disk the
    user chose for the run's files rather than in a temporary directory that may be held in
    memory; on Unix it is unlinked at once and leaves nothing behind. ``OSError`` naming the
    directory when no file can be created there."""
    where = check_run_dir(out).resolve().parent
    where.mkdir(parents=True, exist_ok=True)
    return _core.Spill(where)


@contextmanager
def staged_run_dir(out: Path) -> Iterator[Path]:
    """A fresh ``OUT.partial`` directory beside ``out`` to write a run into, published into
    ``out`` when the block completes (:func:`_publish`). If the block raises (an exception,
    Ctrl-C), ``OUT.partial`` stays as it is, clearly incomplete, and ``out`` is untouched: a
    previous complete run there stays complete. A stale ``OUT.partial`` is cleared first."""
    out = check_run_dir(out).resolve()  # `--out .` has no name to put a sibling beside
    staging = out.with_name(out.name + PARTIAL_SUFFIX)
    if staging.exists():
        shutil.rmtree(staging)
    staging.mkdir(parents=True)
    yield staging
    _publish(staging, out)
