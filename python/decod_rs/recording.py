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

rerun-sdk is optional (``pip install 'decod-rs[rerun]'``) and imported only when a recording
is asked for. ``decod run`` hands the run's arrays (an ``.npz``, read without pickle) to a
worker process (:class:`RecordingJob`), which imports the SDK and writes the file on the other
core while the run draws its figures; with ``--no-plots`` there is nothing to overlap, and the
recording is written in the run's own process (the SDK imported in the background during the
extraction). ``python -m decod_rs.recording DATA.npz OUT.rrd`` is that worker.
"""

from __future__ import annotations

import contextlib
import functools
import importlib
import importlib.util
import json
import shutil
import subprocess
import sys
import tempfile
import threading
import time
import weakref
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
    "RecordingJob",
    "import_rerun_in_background",
    "recording_data",
    "require_rerun",
    "write_recording",
    "write_recording_data",
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


#: Version of the arrays a worker reads (:func:`recording_data`). 2: map points float32 (as
#: the viewer gets them), submap clouds thinned to ``CLOUD_POINTS`` before the handoff.
DATA_VERSION = 2
#: The descriptor images' diverging colours, blue (-) to red (+): ColorBrewer's 11-class
#: RdBu, reversed, as RGB bytes (the scale matplotlib's ``RdBu_r`` interpolates, used by
#: ``descriptors_pair*.png``); interpolated here so the worker needs no matplotlib (its
#: import was 0.3 s of a 2 s worker on the pe pipe with 64 beams).
DIVERGING_ANCHORS = (
    "053061 2166ac 4393c3 92c5de d1e5f0 f7f7f7 fddbc7 f4a582 d6604d b2182b 67001f"
).split()


def require_rerun() -> None:
    """Raise ImportError with ``RERUN_MISSING`` (what to install) unless the rerun SDK is
    installed: checked before any work is done, without importing it."""
    try:
        spec = importlib.util.find_spec("rerun")
    except (ImportError, ValueError):
        spec = None
    if spec is None:
        raise ImportError(RERUN_MISSING)


def _rerun() -> ModuleType:
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


Arrays = dict[str, NDArray[Any]]


def recording_data(run: RecordingInput) -> Arrays:
    """``run`` as plain arrays (numbers and strings, no objects: an ``.npz`` of them loads
    without pickle): what :func:`write_recording_data` draws."""
    f64 = functools.partial(np.asarray, dtype=np.float64)
    lms, results = run.landmarks, run.results
    data: Arrays = {
        "version": np.array(DATA_VERSION),
        "scan_stamps": f64(run.scan_stamps),
        "odometry": f64(run.odometry),
        "corrected": f64(run.corrected),
        "split_stamp": np.array(np.nan if run.split_stamp is None else run.split_stamp),
        "anchor_stamps": f64(run.anchor_stamps),
        **_thinned_clouds(run.submap_points, run.submap_index, run.anchor_stamps.size),
        "lm_stamp": f64([lm.submap_stamp for lm in lms]),
        "lm_origin": f64([lm.origin for lm in lms]).reshape(-1, 3),
        "lm_axis": f64([lm.axis for lm in lms]).reshape(-1, 3),
        "lm_radius": f64([lm.radius_m for lm in lms]),
        "query_stamp": f64([r.query_stamp for r in results]),
        "query_origin": f64([r.query_origin for r in results]).reshape(-1, 3),
        "found": np.array([r.candidate_index is not None for r in results], dtype=bool),
        "keep": np.array(run.keep, dtype=bool).reshape(-1),
        "reason": np.array(list(run.reasons), dtype=str).reshape(-1),
    }
    for name in ("candidate_stamp", "inliers", "score", "chance", "heading_deg"):
        data[name] = f64(
            [getattr(r, name) if r.candidate_index is not None else np.nan for r in results]
        )
    data["candidate_origin"] = f64(
        [r.candidate_origin if r.candidate_index is not None else (np.nan,) * 3 for r in results]
    ).reshape(-1, 3)
    for name, cloud in run.maps.items():
        # float32, as the viewer takes them: half the bytes through the file.
        data[f"map_{name}_points"] = np.asarray(cloud.points, dtype=np.float32).reshape(-1, 3)
        data[f"map_{name}_pass"] = np.asarray(cloud.pass_, dtype=np.uint8)
    data.update(_descriptor_pairs(run))
    return data


def _thinned_clouds(points: NDArray[Any], index: NDArray[Any], submaps: int) -> Arrays:
    """The submap clouds as drawn: each submap's points (grouped by ``index``, ascending)
    evenly strided to at most ``CLOUD_POINTS`` (the 64-beam pe pipe: 781,000 -> 250,000
    points handed to the worker)."""
    p = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    i = np.asarray(index, dtype=np.uint32).reshape(-1)
    bounds = np.searchsorted(i, np.arange(submaps + 1))
    sizes = np.diff(bounds)
    stride = np.maximum(-(-sizes // CLOUD_POINTS), 1)
    start = np.repeat(bounds[:-1], sizes)
    keep = (np.arange(start.size) - start) % np.repeat(stride, sizes) == 0
    return {"submap_points": p[: start.size][keep], "submap_index": i[: start.size][keep]}


def _descriptor_pairs(run: RecordingInput) -> Arrays:
    """The descriptors (and masks) of the best accepted pair of every query stamp that has
    one: ``pair_stamp`` (P,), ``pair_{query,candidate}_{descriptor,mask}`` (P, rows, cols)."""
    by_key = {(lm.submap_stamp, tuple(np.round(lm.origin, 6))): lm for lm in run.landmarks}
    best: dict[float, QueryResult] = {}
    for r, ok in zip(run.results, run.keep, strict=True):
        if ok and (r.query_stamp not in best or r.score > best[r.query_stamp].score):
            best[r.query_stamp] = r
    stamps, images = [], []
    for stamp, r in sorted(best.items()):
        q = by_key.get((r.query_stamp, tuple(np.round(r.query_origin, 6))))
        d = by_key.get((r.candidate_stamp, tuple(np.round(r.candidate_origin, 6))))
        if q is None or d is None:
            continue
        stamps.append(stamp)
        images.append(
            [np.asarray(lm.descriptor, dtype=np.float64) for lm in (q, d)]
            + [np.asarray(lm.mask, dtype=bool) for lm in (q, d)]
        )
    out: Arrays = {"pair_stamp": np.asarray(stamps, dtype=np.float64)}
    names = ("query_descriptor", "candidate_descriptor", "query_mask", "candidate_mask")
    for k, name in enumerate(names):
        dtype = bool if name.endswith("mask") else np.float64
        out[f"pair_{name}"] = (
            np.stack([im[k] for im in images]) if images else np.zeros((0, 0, 0), dtype=dtype)
        )
    return out


def write_recording(path: str | Path, run: RecordingInput) -> dict[str, Any]:
    """Write ``run`` as a rerun recording (``.rrd``, opened by ``rerun FILE``) in this
    process; returns what it holds (entity counts) for the report."""
    return write_recording_data(path, recording_data(run))


def write_recording_data(path: str | Path, data: Arrays) -> dict[str, Any]:
    """:func:`write_recording` from :func:`recording_data`'s arrays."""
    version = int(data["version"]) if "version" in data else None
    if version != DATA_VERSION:
        raise ValueError(f"recording data version {version}, this decod reads {DATA_VERSION}")
    rr = _rerun()
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    rec = rr.RecordingStream("decod")
    rec.save(str(out))
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    _log_static(rr, rec, data)
    submaps = _log_submaps(rr, rec, data)
    queries = _log_queries(rr, rec, data)
    pairs = _log_descriptors(rr, rec, data)
    rec.flush()
    rec.disconnect()
    return {"file": str(out), "submaps": submaps, "queries": queries, "descriptor_pairs": pairs}


def import_rerun_in_background() -> None:
    """Start importing the rerun SDK on a background thread, for a recording written in this
    process: started once the run is configured, its ~0.4 s of CPU overlaps the extraction
    (Rust, without the GIL); started before, it took the GIL from the corridor probe's Python
    (configure 0.44 -> 0.16 s on the hume run with 16 beams)."""
    threading.Thread(target=_import_quietly, name="import-rerun", daemon=True).start()


def _import_quietly() -> None:
    # A failure here is reported by the import in write_recording, on the run's thread.
    with contextlib.suppress(Exception):
        importlib.import_module("rerun")


class RecordingJob:
    """A recording under way: written by a worker process (``python -m decod_rs.recording``,
    ``worker=True``) while this one goes on, or in this process when :meth:`wait` is called.
    :meth:`wait` returns what :func:`write_recording` does, or raises (a worker's failure:
    RuntimeError with its own message).

    A worker costs a fresh interpreter and its imports (numpy, the SDK: ~1.1 s of CPU against
    ~0.4 s in a process that has numpy and matplotlib), worth it only when the caller has
    other work for the other core meanwhile: ``decod run`` draws its figures."""

    def __init__(self, path: str | Path, run: RecordingInput, *, worker: bool = True) -> None:
        self.path = Path(path)
        self._run: RecordingInput | None = None
        self._proc: subprocess.Popen[str] | None = None
        if not worker:
            self._run = run
            return
        self._tmp = Path(tempfile.mkdtemp(prefix="decod-recording-"))
        # Removed by wait(), or when the job is dropped (a run that failed meanwhile).
        self._cleanup = weakref.finalize(self, shutil.rmtree, self._tmp, True)
        data = self._tmp / "recording.npz"
        arrays: dict[str, Any] = recording_data(run)
        np.savez(data, allow_pickle=False, **arrays)
        self._started = time.perf_counter()
        cmd = [sys.executable, "-m", "decod_rs.recording", str(data), str(self.path)]
        self._proc = subprocess.Popen(
            cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )

    def wait(self) -> dict[str, Any]:
        if self._run is not None:
            return write_recording(self.path, self._run)
        proc = self._proc
        if proc is None:  # only a job without a run has no worker: never
            raise RuntimeError(f"{self.path}: no recording under way")
        try:
            stdout, stderr = proc.communicate()
        finally:
            self._cleanup()
        if proc.returncode != 0:
            detail = stderr.strip().splitlines()[-1] if stderr.strip() else "no message"
            raise RuntimeError(
                f"{self.path}: the recording was not written "
                f"(worker exit {proc.returncode}): {detail}"
            )
        recorded: dict[str, Any] = json.loads(stdout)
        recorded["worker_s"] = time.perf_counter() - self._started
        return recorded


def _packed(rgb: NDArray[np.uint8]) -> NDArray[np.uint32]:
    """(N, 3) RGB as rerun's packed 0xRRGGBBAA (opaque): no per-point conversion in the SDK."""
    c = np.asarray(rgb, dtype=np.uint32)
    return np.asarray((c[:, 0] << 24) | (c[:, 1] << 16) | (c[:, 2] << 8) | 0xFF, dtype=np.uint32)


def _log_static(rr: Any, rec: Any, data: Arrays) -> None:
    for name, rgb in (("odometry", ODOMETRY_RGB), ("corrected", CORRECTED_RGB)):
        rec.log(
            f"world/{name}/trajectory",
            rr.LineStrips3D([data[name][:, :3, 3]], colors=[rgb], labels=[name]),
            static=True,
        )
        if f"map_{name}_points" in data:
            passes = np.minimum(data[f"map_{name}_pass"], len(PASS_COLOURS) - 1)
            rec.log(
                f"world/{name}/map",
                rr.Points3D(
                    data[f"map_{name}_points"].astype(np.float32),
                    colors=_packed(PASS_COLOURS[passes]),
                ),
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


def _anchor_poses(data: Arrays, name: str) -> FloatArray:
    return anchor_poses(data["anchor_stamps"], data["scan_stamps"], data[name])


def _log_anchors(rr: Any, rec: Any, data: Arrays) -> None:
    """The current anchor of each trajectory, one row per anchor stamp, in one call each."""
    times = [rr.TimeColumn(TIMELINE, timestamp=data["anchor_stamps"])]
    for name, rgb in (("odometry", ODOMETRY_RGB), ("corrected", CORRECTED_RGB)):
        p = _anchor_poses(data, name)
        columns = rr.Arrows3D.columns(
            origins=p[:, :3, 3],
            vectors=0.3 * p[:, :3, 0],
            colors=np.full(p.shape[0], _packed(np.array([rgb]))[0], dtype=np.uint32),
        )
        rec.send_columns(f"world/{name}/anchor", indexes=times, columns=columns)


def _log_submaps(rr: Any, rec: Any, data: Arrays) -> int:
    """Each submap at its anchor stamp: pose, cloud (as :func:`recording_data` thinned it),
    boundaries; the current anchors."""
    anchors = data["anchor_stamps"]
    poses = _anchor_poses(data, "corrected")
    _log_anchors(rr, rec, data)
    split = float(data["split_stamp"])
    passes = pass_of(anchors, None if np.isnan(split) else split)
    colours = _packed(PASS_COLOURS)
    index, points = data["submap_index"], data["submap_points"]
    bounds = np.searchsorted(index, np.arange(anchors.size + 1))
    order = np.argsort(data["lm_stamp"], kind="stable")
    lm_stamps = data["lm_stamp"][order]
    for k, stamp in enumerate(anchors):
        _set_time(rec, stamp)
        base = f"world/corrected/submaps/{k:05d}"
        rec.log(base, rr.Transform3D(translation=poses[k][:3, 3], mat3x3=poses[k][:3, :3]))
        cloud = points[bounds[k] : bounds[k + 1]]
        if cloud.shape[0]:
            rec.log(f"{base}/cloud", rr.Points3D(cloud, colors=colours[passes[k]]))
        lo = np.searchsorted(lm_stamps, stamp, side="left")
        hi = np.searchsorted(lm_stamps, stamp, side="right")
        if hi > lo:
            mine = order[lo:hi]
            origins, axes = data["lm_origin"][mine], data["lm_axis"][mine]
            radii = data["lm_radius"][mine]
            labels = [f"boundary r={r:.3f} m" for r in radii]
            rec.log(
                f"{base}/boundaries",
                rr.LineStrips3D(list(_rings(origins, axes, radii)), labels=labels),
            )
            rec.log(f"{base}/axes", rr.Arrows3D(origins=origins, vectors=axes * radii[:, None]))
    return int(anchors.size)


def _world_points(data: Arrays, stamps: FloatArray, local: FloatArray) -> FloatArray:
    """Points (n, 3) of submaps' anchor frames (submaps at ``stamps`` (n,)) in the corrected
    world."""
    poses = anchor_poses(stamps, data["scan_stamps"], data["corrected"])
    return np.asarray(np.einsum("nij,nj->ni", poses[:, :3, :3], local) + poses[:, :3, 3])


def _verdict(data: Arrays, i: int) -> str:
    q, ok, reason = float(data["query_stamp"][i]), bool(data["keep"][i]), str(data["reason"][i])
    if not data["found"][i]:
        return f"query {q:.2f} s: no candidate ({reason or 'none eligible'})"
    verdict = "ACCEPTED" if ok else f"rejected: {reason or 'unknown'}"
    return (
        f"query {q:.2f} s -> {data['candidate_stamp'][i]:.2f} s: K={data['inliers'][i]:.0f}, "
        f"S={data['score'][i]:.2f}, chance={data['chance'][i]:.2g}, "
        f"heading {data['heading_deg'][i]:.0f} deg, {verdict}"
    )


def _log_queries(rr: Any, rec: Any, data: Arrays) -> int:
    """Each query's Top-1 and verdict at the query's stamp: the texts and the lines in one
    call each, rows at the query stamps."""
    stamps = data["query_stamp"]
    order = np.argsort(stamps, kind="stable")
    levels = np.where(data["keep"], "INFO", "WARN")
    if order.size:
        rec.send_columns(
            "log/queries",
            indexes=[rr.TimeColumn(TIMELINE, timestamp=stamps[order])],
            columns=rr.TextLog.columns(
                text=[_verdict(data, int(i)) for i in order], level=levels[order].tolist()
            ),
        )
    hits = order[data["found"][order]]
    if hits.size:
        starts = _world_points(data, stamps[hits], data["query_origin"][hits])
        stops = _world_points(data, data["candidate_stamp"][hits], data["candidate_origin"][hits])
        ok = data["keep"][hits]
        colours = np.where(
            ok, _packed(np.array([ACCEPTED_RGB]))[0], _packed(np.array([REJECTED_RGB]))[0]
        ).astype(np.uint32)
        labels = [
            f"K={data['inliers'][i]:.0f} S={data['score'][i]:.2f} "
            + ("accepted" if data["keep"][i] else str(data["reason"][i]))
            for i in hits
        ]
        times, counts = np.unique(stamps[hits], return_counts=True)
        columns = rr.LineStrips3D.columns(
            strips=list(np.stack([starts, stops], axis=1)), colors=colours, labels=labels
        )
        rec.send_columns(
            "world/queries",
            indexes=[rr.TimeColumn(TIMELINE, timestamp=times)],
            columns=columns.partition(counts.tolist()),
        )
    return int(stamps.size)


@functools.cache
def _diverging_lut(entries: int = 256) -> NDArray[np.uint8]:
    """``entries`` RGB bytes evenly along ``DIVERGING_ANCHORS``, linear between neighbours
    (how matplotlib builds ``RdBu_r``'s 256 entries from the same anchors)."""
    anchors = np.array([[int(h[i : i + 2], 16) for i in (0, 2, 4)] for h in DIVERGING_ANCHORS])
    at = np.linspace(0.0, 1.0, len(anchors))
    x = np.linspace(0.0, 1.0, entries)
    rgb = np.stack([np.interp(x, at, anchors[:, c] / 255.0) for c in range(3)], axis=1)
    return np.asarray((rgb * 255).astype(np.uint8))


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


def _log_descriptors(rr: Any, rec: Any, data: Arrays) -> int:
    """The descriptors of each query stamp's best accepted pair, at that stamp."""
    for k, stamp in enumerate(data["pair_stamp"]):
        _set_time(rec, stamp)
        for name in ("query", "candidate"):
            image = _descriptor_rgb(
                data[f"pair_{name}_descriptor"][k], data[f"pair_{name}_mask"][k]
            )
            rec.log(f"descriptors/{name}", rr.Image(image, magnification_filter="Nearest"))
    return int(data["pair_stamp"].size)


def main(argv: Sequence[str] | None = None) -> int:
    """The worker: ``python -m decod_rs.recording DATA.npz OUT.rrd``; prints what the
    recording holds as JSON."""
    args = list(sys.argv[1:] if argv is None else argv)
    if len(args) != 2:
        print("usage: python -m decod_rs.recording DATA.npz OUT.rrd", file=sys.stderr)
        return 2
    with np.load(args[0], allow_pickle=False) as npz:
        data = {name: npz[name] for name in npz.files}
    print(json.dumps(write_recording_data(args[1], data)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
