"""A 3D recording of a run for the rerun viewer (issue 13, ``decod run --rerun FILE.rrd``):
what decod decided, where, and when, on one time line (``stamp``, the log's clock).

Entities (in the corrected world frame unless named ``odometry``; static or at a stamp):

- ``world/odometry/trajectory``, ``world/corrected/trajectory`` (static): the trajectory
  before and after (red, blue, as in ``trajectory.png``);
- ``world/odometry/map``, ``world/corrected/map`` (static): the maps (``decod_rs.maps``),
  cyan outbound, orange return;
- ``world/odometry/anchor``, ``world/corrected/anchor`` (each anchor stamp): the current
  submap anchor and its heading;
- ``world/corrected/submaps/NNNNN`` (its anchor stamp): the submap's corrected pose
  (Transform3D), with children ``cloud`` (the voxels it saw first, anchor frame),
  ``boundaries`` (each detected boundary as a ring of its fitted radius) and ``axes``;
- ``world/queries`` (the query's stamp): each query's Top-1 candidate as a line from the
  query boundary to it, green if accepted, red if rejected, labelled with K, score, reason;
- ``log/queries`` (the query's stamp): the same as text, with the chance and the heading;
- ``descriptors/query``, ``descriptors/candidate`` (the query's stamp): the unwrapped
  descriptors of the best accepted pair (rows: axial bins, +z up; columns: arclength from
  the gravity direction; grey: unobserved).

rerun-sdk is optional (``pip install 'decod-rs[rerun]'``) and imported only here, only when
a recording is asked for.
"""

from __future__ import annotations

import contextlib
import functools
import importlib
import importlib.util
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
from numpy.typing import NDArray

from decod_rs._core import Landmark, QueryResult
from decod_rs.maps import PASS_COLOURS, MapCloud, anchor_poses, pass_of

FloatArray = NDArray[np.float64]

__all__ = [
    "RERUN_MISSING",
    "RecordingInput",
    "import_rerun_in_background",
    "require_rerun",
    "write_recording",
]

RERUN_MISSING = (
    "the 3D recording (--rerun) needs the rerun SDK, which is not installed: "
    "pip install 'decod-rs[rerun]' (or: pip install rerun-sdk)"
)
TIMELINE = "stamp"
#: Line colours (RGB): odometry red, corrected blue (as in trajectory.png); accepted green,
#: rejected red, no candidate grey.
ODOMETRY_RGB = (214, 39, 40)
CORRECTED_RGB = (31, 119, 180)
ACCEPTED_RGB = (44, 160, 44)
REJECTED_RGB = (214, 39, 40)
#: Points per boundary ring.
RING_POINTS = 48
#: Points per submap cloud in the recording (evenly strided): a submap's own voxels are
#: ~3,000 (the 30 m hume pipe: 470,000 over 145 submaps); 1,500 still draw its walls, and the
#: maps (static, every point) are there for detail. Halves the recording's size and time.
CLOUD_POINTS = 1500


def require_rerun() -> None:
    """Raise ImportError with ``RERUN_MISSING`` (what to install) unless the rerun SDK is
    installed: checked before any work is done, without importing it."""
    try:
        spec = importlib.util.find_spec("rerun")
    except (ImportError, ValueError):
        spec = None
    if spec is None:
        raise ImportError(RERUN_MISSING)


def import_rerun_in_background() -> None:
    """Start importing the rerun SDK on a background thread. Started once the run is
    configured, where the extraction (Rust, without the GIL) leaves the interpreter free, its
    ~0.4 s of CPU overlaps the stream; started before the configuration, its imports took the
    GIL from the corridor probe and made that stage 0.25-0.3 s longer (hume, 16 beams)."""
    threading.Thread(target=_import_quietly, name="import-rerun", daemon=True).start()


def _import_quietly() -> None:
    # A failure here is reported by the import in write_recording, on the run's thread.
    with contextlib.suppress(Exception):
        importlib.import_module("rerun")


def _rerun() -> ModuleType:
    """The ``rerun`` module (joins the background import if one is under way)."""
    try:
        return importlib.import_module("rerun")
    except ImportError as exc:
        raise ImportError(RERUN_MISSING) from exc


@dataclass
class RecordingInput:
    """What a recording shows: the trajectories at ``scan_stamps`` (N,) (``odometry`` and
    ``corrected`` (N, 4, 4) world_from_body), the maps, the submap clouds (``submap_points``
    (M, 3) in each submap's anchor frame, ``submap_index`` (M,) into ``anchor_stamps`` (K,)),
    the landmarks and every query's Top-1 with its verdict."""

    scan_stamps: FloatArray
    odometry: FloatArray
    corrected: FloatArray
    split_stamp: float | None
    anchor_stamps: FloatArray
    maps: dict[str, MapCloud]
    submap_points: NDArray[np.float32]
    submap_index: NDArray[np.uint32]
    landmarks: Sequence[Landmark]
    results: Sequence[QueryResult]
    keep: Sequence[bool]
    reasons: Sequence[str]


def write_recording(path: str | Path, run: RecordingInput) -> dict[str, Any]:
    """Write ``run`` as a rerun recording (``.rrd``, opened by ``rerun FILE``); returns what
    it holds (entity counts) for the report."""
    rr = _rerun()
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    rec = rr.RecordingStream("decod")
    rec.save(str(out))
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    _log_static(rr, rec, run)
    submaps = _log_submaps(rr, rec, run)
    queries, pairs = _log_queries(rr, rec, run)
    rec.flush()
    rec.disconnect()
    return {"file": str(out), "submaps": submaps, "queries": queries, "descriptor_pairs": pairs}


def _packed(rgb: NDArray[np.uint8]) -> NDArray[np.uint32]:
    """(N, 3) RGB as rerun's packed 0xRRGGBBAA (opaque): no per-point conversion in the SDK."""
    c = np.asarray(rgb, dtype=np.uint32)
    return np.asarray((c[:, 0] << 24) | (c[:, 1] << 16) | (c[:, 2] << 8) | 0xFF, dtype=np.uint32)


def _log_static(rr: Any, rec: Any, run: RecordingInput) -> None:
    for name, poses, rgb in (
        ("odometry", run.odometry, ODOMETRY_RGB),
        ("corrected", run.corrected, CORRECTED_RGB),
    ):
        rec.log(
            f"world/{name}/trajectory",
            rr.LineStrips3D([poses[:, :3, 3]], colors=[rgb], labels=[name]),
            static=True,
        )
        cloud = run.maps.get(name)
        if cloud is not None:
            colours = _packed(PASS_COLOURS[np.minimum(cloud.pass_, len(PASS_COLOURS) - 1)])
            rec.log(
                f"world/{name}/map",
                rr.Points3D(cloud.points.astype(np.float32), colors=colours),
                static=True,
            )


def _set_time(rec: Any, stamp: float) -> None:
    rec.set_time(TIMELINE, timestamp=float(stamp))


def _rings(origins: FloatArray, axes: FloatArray, radii: FloatArray) -> FloatArray:
    """(n, RING_POINTS + 1, 3) closed circles of ``radii`` (n,) about ``origins`` (n, 3),
    normal to ``axes`` (n, 3), all at once (one call per submap cost 0.2 ms a ring)."""
    a = axes / np.maximum(np.linalg.norm(axes, axis=1, keepdims=True), 1e-12)
    helper = np.where((np.abs(a[:, 2]) < 0.9)[:, None], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0])
    u = np.cross(a, helper)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(a, u)
    t = np.linspace(0.0, 2 * np.pi, RING_POINTS + 1)
    circle = np.cos(t)[None, :, None] * u[:, None, :] + np.sin(t)[None, :, None] * v[:, None, :]
    return np.asarray(origins[:, None, :] + radii[:, None, None] * circle)


def _log_anchors(rr: Any, rec: Any, run: RecordingInput, poses: dict[str, FloatArray]) -> None:
    """The current anchor of each trajectory, one row per anchor stamp, in one call each."""
    times = [rr.TimeColumn(TIMELINE, timestamp=run.anchor_stamps)]
    for name, rgb in (("odometry", ODOMETRY_RGB), ("corrected", CORRECTED_RGB)):
        p = poses[name]
        k = p.shape[0]
        columns = rr.Arrows3D.columns(
            origins=p[:, :3, 3],
            vectors=0.3 * p[:, :3, 0],
            colors=np.full(k, _packed(np.array([rgb], dtype=np.uint8))[0], dtype=np.uint32),
        )
        rec.send_columns(f"world/{name}/anchor", indexes=times, columns=columns)


def _log_submaps(rr: Any, rec: Any, run: RecordingInput) -> int:
    """Each submap at its anchor stamp: pose, cloud (at most ``CLOUD_POINTS``), boundaries;
    the current anchors."""
    poses = {
        "odometry": anchor_poses(run.anchor_stamps, run.scan_stamps, run.odometry),
        "corrected": anchor_poses(run.anchor_stamps, run.scan_stamps, run.corrected),
    }
    _log_anchors(rr, rec, run, poses)
    passes = pass_of(run.anchor_stamps, run.split_stamp)
    colours = _packed(PASS_COLOURS)
    bounds = np.searchsorted(run.submap_index, np.arange(run.anchor_stamps.size + 1))
    by_stamp: dict[float, list[Landmark]] = {}
    for lm in run.landmarks:
        by_stamp.setdefault(lm.submap_stamp, []).append(lm)
    for k, stamp in enumerate(run.anchor_stamps):
        _set_time(rec, stamp)
        base = f"world/corrected/submaps/{k:05d}"
        pose = poses["corrected"][k]
        rec.log(base, rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]))
        cloud = run.submap_points[bounds[k] : bounds[k + 1]]
        if cloud.shape[0]:
            stride = -(-cloud.shape[0] // CLOUD_POINTS)
            rec.log(f"{base}/cloud", rr.Points3D(cloud[::stride], colors=colours[passes[k]]))
        lms = by_stamp.get(float(stamp), [])
        if lms:
            origins = np.array([lm.origin for lm in lms], dtype=np.float64)
            axes = np.array([lm.axis for lm in lms], dtype=np.float64)
            radii = np.array([lm.radius_m for lm in lms], dtype=np.float64)
            labels = [f"boundary r={r:.3f} m" for r in radii]
            rec.log(
                f"{base}/boundaries",
                rr.LineStrips3D(list(_rings(origins, axes, radii)), labels=labels),
            )
            rec.log(f"{base}/axes", rr.Arrows3D(origins=origins, vectors=axes * radii[:, None]))
    return int(run.anchor_stamps.size)


def _world_points(run: RecordingInput, stamps: FloatArray, local: FloatArray) -> FloatArray:
    """Points (n, 3) of submaps' anchor frames (submaps at ``stamps`` (n,)) in the corrected
    world."""
    poses = anchor_poses(stamps, run.scan_stamps, run.corrected)
    return np.asarray(np.einsum("nij,nj->ni", poses[:, :3, :3], local) + poses[:, :3, 3])


def _verdict(r: QueryResult, ok: bool, reason: str) -> str:
    if r.candidate_index is None:
        return f"query {r.query_stamp:.2f} s: no candidate ({reason or 'none eligible'})"
    verdict = "ACCEPTED" if ok else f"rejected: {reason or 'unknown'}"
    return (
        f"query {r.query_stamp:.2f} s -> {r.candidate_stamp:.2f} s: K={r.inliers}, "
        f"S={r.score:.2f}, chance={r.chance:.2g}, heading {r.heading_deg:.0f} deg, {verdict}"
    )


def _log_queries(rr: Any, rec: Any, run: RecordingInput) -> tuple[int, int]:
    """Each query's Top-1 and verdict at the query's stamp (the texts and the lines in one
    call each, rows at the query stamps); descriptors of accepted pairs."""
    by_key = {(lm.submap_stamp, tuple(np.round(lm.origin, 6))): lm for lm in run.landmarks}
    groups: dict[float, list[int]] = {}
    for i, r in enumerate(run.results):
        groups.setdefault(r.query_stamp, []).append(i)
    texts: tuple[list[float], list[str], list[str]] = ([], [], [])
    lines: tuple[list[float], list[int], list[FloatArray], list[int], list[str]] = (
        [],
        [],
        [],
        [],
        [],
    )
    found = [i for i, r in enumerate(run.results) if r.candidate_index is not None]
    hits = [run.results[i] for i in found]
    starts = _world_points(
        run,
        np.array([r.query_stamp for r in hits], dtype=np.float64),
        np.array([r.query_origin for r in hits], dtype=np.float64).reshape(-1, 3),
    )
    stops = _world_points(
        run,
        np.array([r.candidate_stamp for r in hits], dtype=np.float64),
        np.array([r.candidate_origin for r in hits], dtype=np.float64).reshape(-1, 3),
    )
    ends = {i: (a, b) for i, a, b in zip(found, starts, stops, strict=True)}
    pairs = 0
    for stamp, idx in sorted(groups.items()):
        strips = 0
        for i in idx:
            r, ok, why = run.results[i], bool(run.keep[i]), run.reasons[i]
            texts[0].append(stamp)
            texts[1].append(_verdict(r, ok, why))
            texts[2].append("INFO" if ok else "WARN")
            if r.candidate_index is None:
                continue
            lines[2].append(np.stack(ends[i]))
            lines[3].append(int(_packed(np.array([ACCEPTED_RGB if ok else REJECTED_RGB]))[0]))
            lines[4].append(f"K={r.inliers} S={r.score:.2f} " + ("accepted" if ok else why))
            strips += 1
        if strips:
            lines[0].append(stamp)
            lines[1].append(strips)
        accepted = [run.results[i] for i in idx if run.keep[i]]
        if accepted:
            _set_time(rec, stamp)
            if _log_descriptors(rr, rec, max(accepted, key=lambda r: r.score), by_key):
                pairs += 1
    if texts[0]:
        rec.send_columns(
            "log/queries",
            indexes=[rr.TimeColumn(TIMELINE, timestamp=texts[0])],
            columns=rr.TextLog.columns(text=texts[1], level=texts[2]),
        )
    if lines[0]:
        columns = rr.LineStrips3D.columns(
            strips=lines[2], colors=np.asarray(lines[3], dtype=np.uint32), labels=lines[4]
        )
        rec.send_columns(
            "world/queries",
            indexes=[rr.TimeColumn(TIMELINE, timestamp=lines[0])],
            columns=columns.partition(lines[1]),
        )
    return len(run.results), pairs


@functools.cache
def _diverging_lut() -> NDArray[np.uint8]:
    """The RdBu_r colour of each of the colormap's 256 entries as RGB bytes."""
    from matplotlib import colormaps

    cmap = colormaps["RdBu_r"]
    return np.asarray((cmap(np.arange(cmap.N))[:, :3] * 255).astype(np.uint8))


def _descriptor_rgb(values: NDArray[np.float64], mask: NDArray[np.bool_]) -> NDArray[np.uint8]:
    """A (rows, cols) descriptor as an RGB image: blue-white-red over its own +-max offset,
    unobserved cells grey, +z (row 0 of the descriptor is -z) at the top. The colormap's
    entries are looked up directly (its own call took 0.4 ms a descriptor, two per accepted
    query): the entry of x in [0, 1] is floor(x N), 1 itself the last, as the colormap does."""
    lut = _diverging_lut()
    observed = mask & np.isfinite(values)
    lim = float(np.max(np.abs(values[observed]))) if np.any(observed) else 1.0
    scaled = np.clip(0.5 + 0.5 * np.where(observed, values, 0.0) / (lim or 1.0), 0.0, 1.0)
    rgb = lut[np.minimum((scaled * len(lut)).astype(np.int64), len(lut) - 1)]
    rgb[~observed] = 153
    return np.ascontiguousarray(rgb[::-1])


def _log_descriptors(
    rr: Any, rec: Any, r: QueryResult, by_key: dict[tuple[float, tuple[float, ...]], Landmark]
) -> bool:
    q = by_key.get((r.query_stamp, tuple(np.round(r.query_origin, 6))))
    d = by_key.get((r.candidate_stamp, tuple(np.round(r.candidate_origin, 6))))
    if q is None or d is None:
        return False
    for name, lm in (("query", q), ("candidate", d)):
        image = _descriptor_rgb(np.asarray(lm.descriptor), np.asarray(lm.mask, dtype=bool))
        rec.log(f"descriptors/{name}", rr.Image(image, magnification_filter="Nearest"))
    return True
