"""Boundary tracks: the views of one physical boundary within one pass (beyond the paper).

A joint or ring is detected from several consecutive submaps of the same pass. Over the few
seconds between them the odometry is accurate to centimetres, so two views whose origins
lie within ``matching.duplicate_radius_m`` of each other in the odometry frame, from submaps
less than ``matching.min_time_separation_s`` apart and on the same side of the turnaround
(the same pass), view the same boundary. Views are linked pairwise and the connected
components are the tracks (union-find). Near the turnaround both passes see a boundary
within that time and, the drift between them being small, at one place; the split keeps
them two tracks, tied by a loop (batch mode compares the passes without a time separation)
rather than by a track that would count the same tie twice. On the generalisation matrix
(778 tracks in 67 of 100 runs crossed the turnaround before) that took 9,909 loops to
9,803, none wrong either way, and no run's corrected RMSE up by more than 2 cm (two down:
hume with the forward sensor 7.5 -> 3.7 cm, the shield with it 14.1 -> 10.9 cm). The
radius stays well below the boundary spacing (>= 1 m between pipe joints, >= 1.2 m between
tunnel rings), so distinct boundaries never chain into one track.

The radius alone is not enough when the odometry stalls: with joints 1 m apart and an
odometry reporting 60 % of the distance, views of two joints taken two anchors apart landed
within 1 cm of each other in the odometry frame (simulated hume pipe). So a link also needs
the descriptors to agree (``confirm``: the matcher verifies the pair under the pass's own
heading only, chance agreement below ``matching.false_alarm_rate``).

The matcher uses the tracks as the database's physical boundary ids: every view is kept (a
query is compared with the view taken from the most similar distance), but the views of one
boundary are one candidate, never each other's runner-up.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence

import numpy as np
from numpy.typing import NDArray

from decod_rs._core import Landmark, QueryResult
from decod_rs.maps import pass_of

FloatArray = NDArray[np.float64]

__all__ = [
    "candidate_links",
    "group_views",
    "offsets_from_track_means",
    "tracked_loops",
    "views_per_landmark",
    "world_axes",
    "world_origins",
]


def world_origins(landmarks: Sequence[Landmark], anchors: dict[float, FloatArray]) -> FloatArray:
    """``(N, 3)`` landmark origins in the odometry (world) frame of their anchors."""
    out = np.empty((len(landmarks), 3))
    for k, lm in enumerate(landmarks):
        pose = anchors[lm.submap_stamp]
        out[k] = pose[:3, :3] @ lm.origin + pose[:3, 3]
    return out


def offsets_from_track_means(
    where: FloatArray, tracks: NDArray[np.int64]
) -> Iterator[tuple[NDArray[np.int64], FloatArray]]:
    """Per track of two or more views: the views' indices and their ``where`` rows (N, 3)
    less the track's mean (the spread of one boundary's views)."""
    for t in np.unique(tracks):
        idx = np.flatnonzero(tracks == t)
        if idx.size >= 2:
            yield idx, where[idx] - where[idx].mean(axis=0)


def world_axes(landmarks: Sequence[Landmark], anchors: dict[float, FloatArray]) -> FloatArray:
    """``(N, 3)`` landmark corridor axes (oriented with the sensor's forward) in the odometry
    (world) frame of their anchors."""
    out = np.empty((len(landmarks), 3))
    for k, lm in enumerate(landmarks):
        out[k] = anchors[lm.submap_stamp][:3, :3] @ lm.axis
    return out


def _find(parent: list[int], i: int) -> int:
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


def candidate_links(
    landmarks: Sequence[Landmark],
    anchors: dict[float, FloatArray],
    radius_m: float,
    window_s: float,
    split_stamp: float | None = None,
) -> list[tuple[int, int]]:
    """Pairs (earlier, later) of views from different submaps less than ``window_s`` apart
    whose origins lie within ``radius_m`` in the odometry frame, and of one pass (both at or
    both after ``split_stamp``, the turnaround, when there is one)."""
    where = world_origins(landmarks, anchors)
    stamps = np.array([lm.submap_stamp for lm in landmarks], dtype=np.float64)
    order = np.argsort(stamps, kind="stable")
    t, w = stamps[order], where[order]
    passes = pass_of(t, split_stamp)  # all one pass without a turnaround
    # The later views within the window of each one (sorted stamps: a prefix of the rest;
    # one past the searched end, re-checked exactly, absorbs rounding of t + window).
    ends = np.minimum(np.searchsorted(t, t + window_s, side="left") + 1, len(t))
    links: list[tuple[int, int]] = []
    for a in range(len(t)):
        b = np.arange(a + 1, ends[a])
        if b.size == 0:
            continue
        # One submap's boundaries are distinct by construction (NMS): never linked.
        ok = (t[b] - t[a] < window_s) & (t[b] != t[a]) & (passes[b] == passes[a])
        ok &= np.linalg.norm(w[b] - w[a], axis=1) < radius_m
        links.extend((int(order[a]), int(order[k])) for k in b[ok])
    return links


def group_views(
    landmarks: Sequence[Landmark],
    anchors: dict[float, FloatArray],
    radius_m: float,
    window_s: float,
    confirm: Callable[[list[tuple[int, int]]], list[bool]] | None = None,
    split_stamp: float | None = None,
) -> NDArray[np.int64]:
    """A track id per landmark (module docs); ids are 0.. in order of first view.
    ``confirm(links)``: for each candidate link (earlier, later), whether the descriptors
    agree that the two views show one boundary (None: the radius alone decides);
    ``split_stamp``: the turnaround, which no track crosses."""
    n = len(landmarks)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    links = candidate_links(landmarks, anchors, radius_m, window_s, split_stamp)
    confirmed = [True] * len(links) if confirm is None else confirm(links)
    parent = list(range(n))
    for (i, j), ok in zip(links, confirmed, strict=True):
        ri, rj = _find(parent, i), _find(parent, j)
        if ok and ri != rj:
            parent[max(ri, rj)] = min(ri, rj)
    stamps = np.array([lm.submap_stamp for lm in landmarks])
    roots = [_find(parent, k) for k in range(n)]
    first: dict[int, int] = {}
    ids = np.empty(n, dtype=np.int64)
    for k in np.argsort(stamps, kind="stable"):
        ids[k] = first.setdefault(roots[k], len(first))
    return ids


def views_per_landmark(tracks: NDArray[np.int64]) -> NDArray[np.int64]:
    """For every landmark, how many views (submaps of its pass) its track holds."""
    _, where, counts = np.unique(
        np.asarray(tracks, dtype=np.int64), return_inverse=True, return_counts=True
    )
    return np.asarray(counts[where], dtype=np.int64)


def tracked_loops(
    results: Sequence[QueryResult],
    landmarks: Sequence[Landmark],
    query_views: NDArray[np.int64],
    db_views: NDArray[np.int64],
) -> list[bool]:
    """Per query result: whether its query boundary (``query_views``, per landmark) or its
    Top-1 (``db_views``, per database index) was seen from two or more submaps of its pass,
    i.e. is a track rather than a single detection."""
    index = {
        (float(lm.submap_stamp), tuple(float(v) for v in lm.origin)): k
        for k, lm in enumerate(landmarks)
    }
    out = []
    for r in results:
        q = index.get((float(r.query_stamp), tuple(float(v) for v in r.query_origin)))
        d = r.candidate_index
        out.append(
            (q is not None and int(query_views[q]) >= 2)
            or (d is not None and 0 <= d < len(db_views) and int(db_views[d]) >= 2)
        )
    return out
