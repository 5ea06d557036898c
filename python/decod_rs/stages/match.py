"""Stages 2-3 of Algorithm 1 (paper Sec. III-C, III-D): the views of each pass linked into
boundary tracks, outbound landmarks in the database and return landmarks querying it (batch)
or every landmark querying all older ones (online), then the jointly consistent loop set
(:mod:`decod_rs.selection`); stage 3b places ambiguous queries by the corrected trajectory
(:mod:`decod_rs.disambiguation`)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray

from decod_rs._core import Landmark, QueryResult
from decod_rs.chainage import revisits
from decod_rs.config import Config
from decod_rs.disambiguation import CorrectedFrame, near_loops, resolve_with_prior
from decod_rs.matching import LandmarkDatabase, PairMemo
from decod_rs.progress import Progress
from decod_rs.selection import path_along, select_loops
from decod_rs.sequential import (
    same_boundary,
)
from decod_rs.stages.extract import SubmapLandmarks
from decod_rs.tracks import (
    group_views,
    tracked_loops,
    views_per_landmark,
    world_axes,
    world_origins,
)
from decod_rs.tum import interpolate_poses

FloatArray = NDArray[np.float64]
T = TypeVar("T")


#: In ``auto`` mode the log is split at the turnaround (the scan farthest from the start) when
#: the return leg covers at least this fraction of the outbound distance; otherwise every
#: landmark queries all older ones (online).
MIN_RETURN_FRACTION = 0.25

#: Batch queries go to the matcher in this many slices, so a long log's matching shows its
#: progress (each slice is still parallel inside: a kilometre of tunnel has ~1,800 queries).
QUERY_CHUNKS = 20


def split_stamp(stamps: FloatArray, poses: FloatArray) -> float | None:
    """The turnaround stamp of an out-and-back run, or None if there is no real return."""
    positions = poses[:, :3, 3]
    reach = np.linalg.norm(positions - positions[0], axis=1)
    far = int(np.argmax(reach))
    back = float(np.linalg.norm(positions[-1] - positions[far]))
    if reach[far] <= 0 or back < MIN_RETURN_FRACTION * reach[far]:
        return None
    return float(stamps[far])


@dataclass
class Matched:
    """Stages 2-3: the tracks, every query's Top-1 and which stay loops (and why not);
    ``db_order[i]``: the landmark behind database index ``i``; ``by_prior``: the loops kept
    by :mod:`decod_rs.disambiguation`; ``tracked[k]``: query ``k`` or its Top-1 is a track
    (:func:`decod_rs.selection.drop_if_untracked`)."""

    split: float | None
    tracks: NDArray[np.int64]
    results: list[QueryResult]
    mode: str
    db_order: list[int]
    keep: list[bool]
    reasons: list[str]
    by_prior: frozenset[int] = frozenset()
    pairs: PairMemo | None = None
    tracked: list[bool] | None = None
    #: Views left out of the database: taken on ground covered before (:func:`revisit_views`).
    revisited: int = 0

    @property
    def database(self) -> int:
        return len(self.db_order)


def revisit_views(
    landmarks: list[Landmark],
    scans: tuple[FloatArray, FloatArray],
    split: float | None,
    behind_m: float,
) -> NDArray[np.bool_]:
    """Per landmark, whether its anchor lies on ground its pass covered before
    (:func:`decod_rs.chainage.revisits` on the odometry, ``behind_m`` behind the front):
    the robot backed up there or drives over a backed-up stretch again. The views of one
    boundary from two traversals of a pass are two tracks (more than
    ``matching.min_time_separation_s`` apart); in the database they were each other's
    runner-up, so queries of the stretch came out ``not_unique`` and near ties made the
    corridor look aliased (held out, seed 239: a 0.6 m pipe driven out to 36 m, back to 6 m
    and out to 40 m closed no loop). The first traversal's views stand for the stretch."""
    stamps, poses = scans
    out = np.zeros(len(landmarks), dtype=bool)
    if stamps.size < 2 or not landmarks:
        return out
    first = np.ones(stamps.size, dtype=bool) if split is None else stamps <= split
    again = np.zeros(stamps.size, dtype=bool)
    again[first] = revisits(poses[first, :3, 3], behind_m)
    anchor = np.array([lm.submap_stamp for lm in landmarks], dtype=np.float64)
    nearest = np.clip(np.searchsorted(stamps, anchor), 0, stamps.size - 1)
    before = np.clip(nearest - 1, 0, stamps.size - 1)
    closer = np.abs(stamps[before] - anchor) < np.abs(stamps[nearest] - anchor)
    return np.asarray(again[np.where(closer, before, nearest)], dtype=bool)


def _slices(items: list[T]) -> Iterator[list[T]]:
    """``items`` in ``QUERY_CHUNKS`` consecutive slices (fewer for fewer items), for work
    whose items are independent, reported slice by slice."""
    step = max(1, -(-len(items) // QUERY_CHUNKS))
    for start in range(0, len(items), step):
        yield items[start : start + step]


def _in_slices(
    confirm: Callable[[list[tuple[int, int]]], list[bool]], progress: bool
) -> Callable[[list[tuple[int, int]]], list[bool]]:
    """``confirm`` of the track links (:func:`decod_rs.sequential.same_boundary`) in
    :func:`_slices` with a progress bar: each link is compared on its own, so the verdicts
    are those of one batch (the links of a kilometre of tunnel took 5 s without a word; the
    first slice also prepares every view for the matcher)."""

    def run(links: list[tuple[int, int]]) -> list[bool]:
        bar = Progress("link", len(links) or None, enabled=progress, unit="pairs")
        verdicts: list[bool] = []
        for chunk in _slices(links):
            verdicts.extend(confirm(chunk))
            bar.advance(len(chunk))
        bar.close()
        return verdicts

    return run


def query_database(
    landmarks: list[Landmark],
    tracks: NDArray[np.int64],
    where: tuple[FloatArray, FloatArray],
    cfg: Config,
    mode: str,
    split: float | None,
    pairs: PairMemo,
    revisited: NDArray[np.bool_] | None = None,
    progress: bool = False,
) -> tuple[list[QueryResult], str, list[int]]:
    """Queries and their top-1 results, the mode used, and the landmark behind each
    database index. Every view goes into the database under its track (physical boundary)
    id, placed at ``where`` (origins and axes, (N, 3) each, in the odometry frame: the
    coarse stage's neighbours and the heading prior), but those ``revisited`` marks
    (:func:`revisit_views`), which still query it; batch mode takes the landmarks as the
    track links prepared them (``pairs.views``) and queries in ``QUERY_CHUNKS`` slices (each
    query is independent of the others: the same results, with ``progress`` on stderr)."""
    origins, axes = where
    again = np.zeros(len(landmarks), dtype=bool) if revisited is None else revisited
    db = LandmarkDatabase(cfg)
    if mode == "auto":
        mode = "batch" if split is not None else "online"
    if mode == "batch":
        if split is None:
            raise ValueError(
                "--mode batch: the trajectory has no return leg to query with (use --mode online)"
            )
        outbound = [
            k for k, lm in enumerate(landmarks) if lm.submap_stamp <= split and not again[k]
        ]
        views = pairs.views
        ids = [int(tracks[k]) for k in outbound]
        db.extend_prepared(views, outbound, ids, origins[outbound], axes[outbound])
        queries = [k for k, lm in enumerate(landmarks) if lm.submap_stamp > split]
        bar = Progress("match", len(queries) or None, enabled=progress)
        results = []
        for chunk in _slices(queries):
            results.extend(
                db.query_batch_prepared(views, chunk, across_passes=True, directions=axes[chunk])
            )
            bar.advance(len(chunk))
        bar.close()
        return results, mode, outbound
    results = []
    order = sorted(range(len(landmarks)), key=lambda k: landmarks[k].submap_stamp)
    added = []
    bar = Progress("match", len(order) or None, enabled=progress)
    for k in order:
        results.append(db.query(landmarks[k], direction=axes[k]))
        if not again[k]:
            db.add(landmarks[k], int(tracks[k]), origins[k], axes[k])
            added.append(k)
        bar.advance()
    bar.close()
    return results, mode, added


def match_and_select(
    ex: SubmapLandmarks,
    cfg: Config,
    mode: str,
    scan_stamps: FloatArray,
    scan_odom: FloatArray,
    link_frame: FloatArray | None = None,
    progress: bool = False,
) -> Matched:
    """Stages 2-3: tracks, matching, selection. ``link_frame``: the scan poses in which views
    are linked into tracks (default the odometry; a rebuilt round links in the corrected
    trajectory of the first, :mod:`decod_rs.refinement`); ``progress``: the queries' on
    stderr."""
    split = split_stamp(scan_stamps, scan_odom)
    anchors = dict(zip(ex.anchor_stamps, ex.anchor_poses, strict=True))
    m = cfg.matching
    linking = anchors
    if link_frame is not None and ex.anchor_stamps:
        stamps = np.asarray(ex.anchor_stamps, dtype=np.float64)
        poses = interpolate_poses(scan_stamps, link_frame, stamps)
        linking = dict(zip(ex.anchor_stamps, poses, strict=True))
    pairs = PairMemo(ex.landmarks, m, ex.spill)
    tracks = group_views(
        ex.landmarks,
        linking,
        float(m.duplicate_radius_m),
        float(m.min_time_separation_s),
        _in_slices(same_boundary(ex.landmarks, m, pairs), progress),
        split_stamp=split,
    )
    where = (world_origins(ex.landmarks, anchors), world_axes(ex.landmarks, anchors))
    again = revisit_views(
        ex.landmarks, (scan_stamps, scan_odom), split, float(m.duplicate_radius_m)
    )
    results, used_mode, db_order = query_database(
        ex.landmarks, tracks, where, cfg, mode, split, pairs, again, progress
    )
    pairs.release_views()
    views = views_per_landmark(tracks)
    tracked = tracked_loops(results, ex.landmarks, views, views[db_order])
    keep, reasons = select_loops(results, anchors, scan_stamps, scan_odom, m, tracked=tracked)
    return Matched(
        split,
        tracks,
        results,
        used_mode,
        db_order,
        keep,
        reasons,
        pairs=pairs,
        tracked=tracked,
        revisited=int(np.count_nonzero(again)),
    )


def resolve(
    ex: SubmapLandmarks,
    matched: Matched,
    cfg: Config,
    scans: tuple[FloatArray, FloatArray],
    corrected: FloatArray,
) -> Matched:
    """Stage 3b: ambiguous queries placed by the corrected trajectory, then the whole
    loop set selected again (:mod:`decod_rs.disambiguation`)."""
    m = cfg.matching
    loops = [r.query_stamp for r, ok in zip(matched.results, matched.keep, strict=True) if ok]
    promoted = resolve_with_prior(
        matched.results,
        matched.reasons,
        [ex.landmarks[i] for i in matched.db_order],
        CorrectedFrame(scans[0], corrected),
        float(m.consistency_tolerance_m),
        near_loops(loops, path_along(*scans), float(m.consistency_window_m)),
        float(m.duplicate_radius_m),
    )
    if not promoted:
        return matched
    anchors = dict(zip(ex.anchor_stamps, ex.anchor_poses, strict=True))
    keep, reasons = select_loops(
        matched.results, anchors, *scans, m, also=promoted, tracked=matched.tracked
    )
    by_prior = frozenset(k for k in promoted if keep[k])
    return replace(matched, keep=keep, reasons=reasons, by_prior=by_prior)
