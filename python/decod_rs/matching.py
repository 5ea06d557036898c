"""Landmark matching (paper §III-B, §III-C): pairwise comparison and the landmark database.

The work runs in Rust with the GIL released; results are the native ``PairResult`` and
``QueryResult`` classes (attributes, numpy ``(3,)`` vectors). ``config`` everywhere accepts a
resolved :class:`~decod_rs.config.Config` (whole or its ``matching`` section), a preset name
(``"tunnel"``, ``"pipe"``), a plain dict of the ``matching`` section, or ``None`` (tunnel).

Example::

    db = LandmarkDatabase(config="pipe")
    db.extend(outbound_landmarks)
    for result in db.query_batch(return_landmarks):
        if result.accepted:
            print(result.query_stamp, result.candidate_stamp, result.inliers, result.dz_m)
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from decod_rs import _core
from decod_rs._core import Landmark, PairResult, QueryResult
from decod_rs.config import Config, load_config

MatchingConfigLike = Config | str | dict[str, Any] | None


def matching_config_json(config: MatchingConfigLike = None) -> str:
    """The ``matching`` section of ``config`` as the JSON the native layer reads."""
    if config is None or isinstance(config, str):
        config = load_config(preset=config or "tunnel")
    values = config.to_dict() if isinstance(config, Config) else dict(config)
    if "matching" in values:
        values = values["matching"]
    return json.dumps(values)


def compare(query: Landmark, candidate: Landmark, config: MatchingConfigLike = None) -> PairResult:
    """Compare two landmarks under both headings (0° and 180°); the better one is returned."""
    return _core.compare(query, candidate, matching_config_json(config))


def compare_pairs(
    landmarks: Sequence[Landmark],
    pairs: Sequence[tuple[int, int]],
    config: MatchingConfigLike = None,
    *,
    same_heading: bool = False,
) -> list[PairResult]:
    """Many comparisons at once: ``pairs`` of (query, candidate) indices into ``landmarks``,
    each landmark prepared once, pairs in parallel; results in the order of ``pairs``.
    ``same_heading``: under 0 degrees only (views of one pass share the sensor's heading)."""
    if not pairs:
        return []
    return _core.compare_pairs(
        list(landmarks),
        [(int(i), int(j)) for i, j in pairs],
        matching_config_json(config),
        same_heading,
    )


def synthetic_landmark(
    pipe_seed: int,
    joint_seed: int,
    *,
    stamp: float = 0.0,
    reversed: bool = False,
    view_seed: int = 0,
    grid: str = "tunnel",
    random_view: bool = True,
    shift_z_m: float | None = None,
    missing_arc: tuple[float, float] | None = None,
    noise_m: float | None = None,
) -> Landmark:
    """A realistic synthetic observation of one joint (tests, examples, benchmarks).

    Joints of one ``pipe_seed`` share the groove geometry; equal seeds give the identical
    joint (aliasing). ``missing_arc=(start_p, fraction)`` hides part of the circumference.
    """
    return _core.synthetic_landmark(
        pipe_seed,
        joint_seed,
        stamp=stamp,
        reversed=reversed,
        view_seed=view_seed,
        grid=grid,
        random_view=random_view,
        shift_z_m=shift_z_m,
        missing_arc=missing_arc,
        noise_m=noise_m,
    )


class PairMemo:
    """:func:`compare_pairs` of views of one pass (``same_heading``) over one list of
    landmarks under one config, each (query, candidate) pair compared once: a run links
    tracks with the matcher, then builds the sequential factors from the same pairs in every
    optimisation round."""

    def __init__(
        self,
        landmarks: Sequence[Landmark],
        config: MatchingConfigLike = None,
        spill: _core.Spill | None = None,
    ) -> None:
        self._landmarks = list(landmarks)
        self._config = matching_config_json(config)
        self._spill = spill
        self._views: _core.PreparedViews | None = None
        self._released = False
        self._done: dict[tuple[int, int], PairResult] = {}

    @property
    def landmarks(self) -> list[Landmark]:
        """The landmarks compared: the list itself (:mod:`decod_rs.parking` empties and
        refills it in place while a rebuilt round runs)."""
        return self._landmarks

    @property
    def views(self) -> _core.PreparedViews:
        """Every landmark prepared for the matcher once (on first use): the comparisons
        here and the run's database and queries (:meth:`LandmarkDatabase.extend_prepared`)
        share them until :meth:`release_views`. Given a spill, each view's patches (about
        17 KB of its 22) wait there and every comparison reads back what it needs."""
        if self._views is None:
            self._views = _core.PreparedViews(self._landmarks, self._config, self._spill)
        return self._views

    def release_views(self) -> None:
        """Free the prepared views (about 22 KB a landmark with their patches in memory,
        3 KB with them on disk, beside the landmark's own 29 KB:
        ``docs/measurements.md``, "Long logs"); later comparisons prepare only the
        landmarks they use."""
        self._views, self._released = None, True

    def compare(self, pairs: Sequence[tuple[int, int]]) -> list[PairResult]:
        """Results in the order of ``pairs`` (see :func:`compare_pairs`)."""
        keys = [(int(i), int(j)) for i, j in pairs]
        missing = [k for k in dict.fromkeys(keys) if k not in self._done]
        if missing:
            if self._released:
                found = _core.compare_pairs(self._landmarks, missing, self._config, True)
            else:
                found = self.views.compare_pairs(missing, True)
            self._done.update(zip(missing, found, strict=True))
        return [self._done[k] for k in keys]


class LandmarkDatabase:
    """Landmarks prepared once on insertion; queried with eligibility, both headings, rayon.

    A query is accepted iff the best candidate has ``K >= min_inliers`` and its score beats
    the runner-up's by ``uniqueness_ratio`` (aliasing guard).
    """

    def __init__(self, config: MatchingConfigLike = None) -> None:
        self._config = matching_config_json(config)
        self._db = _core.LandmarkDatabase(self._config)

    @classmethod
    def _wrap(cls, native: _core.LandmarkDatabase, config_json: str) -> LandmarkDatabase:
        db = cls.__new__(cls)
        db._config = config_json
        db._db = native
        return db

    def _json(self, config: MatchingConfigLike) -> str:
        return self._config if config is None else matching_config_json(config)

    def add(
        self,
        landmark: Landmark,
        boundary: int | None = None,
        position: ArrayLike | None = None,
        direction: ArrayLike | None = None,
    ) -> int:
        """Prepare and store ``landmark``; returns its index. ``boundary``: the id of the
        physical boundary it views (views sharing an id are one candidate: never each
        other's runner-up); None = a boundary of its own. ``position``: where the boundary
        lies (3,) in a frame shared by the database (see :meth:`set_positions`);
        ``direction``: its corridor axis (3,) in that frame (see :meth:`set_directions`)."""
        if boundary is None:
            index = self._db.add(landmark)
        else:
            index = self._db.add_view(landmark, int(boundary))
        if position is not None:
            self.set_positions([index], np.asarray(position, dtype=np.float64).reshape(1, 3))
        if direction is not None:
            self.set_directions([index], np.asarray(direction, dtype=np.float64).reshape(1, 3))
        return index

    def extend(
        self,
        landmarks: Iterable[Landmark],
        boundaries: Iterable[int] | None = None,
        positions: ArrayLike | None = None,
        spill: _core.Spill | None = None,
    ) -> list[int]:
        """Prepare (in parallel) and store ``landmarks``; returns their indices.
        ``boundaries``: one physical boundary id per landmark (see :meth:`add`);
        ``positions``: (N, 3) where each boundary lies (see :meth:`set_positions`);
        ``spill``: where the entries' patches wait (about 18 of an entry's 22 KB; None:
        memory), read back by each comparison: the same results."""
        items = list(landmarks)
        placed = None if positions is None else np.asarray(positions, dtype=np.float64)
        if placed is not None and placed.shape != (len(items), 3):
            raise ValueError(f"positions: shape {placed.shape} for {len(items)} landmarks")
        if boundaries is None:
            indices = self._db.extend(items, spill)
        else:
            ids = [int(b) for b in boundaries]
            if len(ids) != len(items):
                raise ValueError(f"boundaries: {len(ids)} ids for {len(items)} landmarks")
            indices = self._db.extend_views(items, ids, spill)
        if placed is not None:
            self.set_positions(indices, placed)
        return indices

    def extend_prepared(
        self,
        views: _core.PreparedViews,
        indices: Sequence[int],
        boundaries: Sequence[int],
        positions: ArrayLike | None = None,
        directions: ArrayLike | None = None,
    ) -> list[int]:
        """:meth:`extend` with landmarks ``indices`` of ``views`` (:attr:`PairMemo.views`,
        prepared under this database's config): nothing is prepared twice. ``directions``:
        (N, 3) their corridor axes in the positions' frame (:meth:`set_directions`)."""
        idx = [int(i) for i in indices]
        rows = {
            name: None if a is None else np.asarray(a, dtype=np.float64)
            for name, a in (("positions", positions), ("directions", directions))
        }
        for name, a in rows.items():
            if a is not None and a.shape != (len(idx), 3):
                raise ValueError(f"{name}: shape {a.shape} for {len(idx)} landmarks")
        stored = self._db.extend_prepared(views, idx, [int(b) for b in boundaries])
        if rows["positions"] is not None:
            self.set_positions(stored, rows["positions"])
        if rows["directions"] is not None:
            self.set_directions(stored, rows["directions"])
        return stored

    def query_batch_prepared(
        self,
        views: _core.PreparedViews,
        indices: Sequence[int],
        *,
        cross_session: bool = False,
        across_passes: bool = False,
        directions: ArrayLike | None = None,
    ) -> list[QueryResult]:
        """:meth:`query_batch` with landmarks ``indices`` of ``views`` as the queries.
        ``across_passes``: the queries are another pass of this run than the database's
        (batch mode), so every entry that shares no scan with a query is eligible, without
        ``min_time_separation_s``. ``directions``: (k, 3) each query's corridor axis in the
        frame of :meth:`set_directions`; a query is then compared with an oriented entry only
        under the heading the odometry allows (``matching.heading_from_odometry``)."""
        idx = [int(i) for i in indices]
        axes = None
        if directions is not None:
            axes = np.ascontiguousarray(directions, dtype=np.float64)
            if axes.shape != (len(idx), 3):
                raise ValueError(f"directions: shape {axes.shape} for {len(idx)} queries")
        return self._db.query_batch_prepared(views, idx, cross_session, across_passes, axes)

    def boundaries(self) -> list[int]:
        """The physical boundary id of every stored view."""
        return self._db.boundaries()

    def set_positions(self, indices: Sequence[int], positions: ArrayLike) -> None:
        """Place stored views: ``positions`` (k, 3), the boundary origins of ``indices`` in
        one frame shared by the whole database (a run's odometry, a survey's corrected
        frame). The coarse short list is then widened by the eligible views within a
        descriptor's extent of a listed one (``matching.retrieval_neighbour_extents``), so
        the neighbouring ring that competes with the best is tested for uniqueness."""
        array = np.ascontiguousarray(positions, dtype=np.float64)
        self._db.set_positions([int(i) for i in indices], array)

    def set_directions(self, indices: Sequence[int], directions: ArrayLike) -> None:
        """Orient stored views: ``directions`` (k, 3), the corridor axes of ``indices`` (each
        landmark's axis, oriented with the sensor's forward) in the frame of
        :meth:`set_positions`. The same-place rule (``matching.runner_up_same_place_rows``)
        compares stored views with each other, so any frame they share serves it; the
        heading prior compares them with a query's axis, which must then be in the same
        frame (a run's own odometry, :meth:`query_batch_prepared`)."""
        array = np.ascontiguousarray(directions, dtype=np.float64)
        self._db.set_directions([int(i) for i in indices], array)

    def directions(self) -> NDArray[np.float64]:
        """(n, 3) each stored view's direction, NaN where none was set."""
        return self._db.directions()

    def positions(self) -> NDArray[np.float64]:
        """(n, 3) each stored view's position, NaN where none was set."""
        return self._db.positions()

    def query(
        self,
        query: Landmark,
        config: MatchingConfigLike = None,
        direction: ArrayLike | None = None,
    ) -> QueryResult:
        """The best eligible candidate for ``query`` (database config unless given).
        ``direction``: (3,) its corridor axis in the frame of :meth:`set_directions` (online
        mode within a run: only the heading the odometry allows is compared with an oriented
        view)."""
        axis = None
        if direction is not None:
            a = np.asarray(direction, dtype=np.float64).reshape(-1)
            if a.shape != (3,):
                raise ValueError(f"direction: shape {a.shape}, expected (3,)")
            axis = (float(a[0]), float(a[1]), float(a[2]))
        return self._db.query(query, self._json(config), axis)

    def query_batch(
        self,
        queries: Iterable[Landmark],
        config: MatchingConfigLike = None,
        *,
        cross_session: bool = False,
    ) -> list[QueryResult]:
        """Batch mode: every query against the (outbound) database. ``cross_session``: the
        database is an earlier survey, every entry is eligible (no time separation)."""
        return self._db.query_batch(list(queries), self._json(config), cross_session)

    def bytes_per_landmark(self) -> int:
        """Memory held per stored landmark (prepared data, coarse signature, id), bytes."""
        return self._db.bytes_per_landmark()

    def query_online(
        self, landmark: Landmark, config: MatchingConfigLike = None
    ) -> tuple[QueryResult, int]:
        """Online mode: query against all older landmarks, then add; (result, new index)."""
        return self._db.query_online(landmark, self._json(config))

    def landmark(self, index: int) -> Landmark:
        """The stored landmark at ``index``."""
        return self._db.landmark(index)

    def save(self, path: str | Path) -> None:
        """Write the database (versioned JSON)."""
        self._db.save(str(path))

    @classmethod
    def load(cls, path: str | Path, config: MatchingConfigLike = None) -> LandmarkDatabase:
        """Read a saved database; ``DatabaseError`` on another format version."""
        config_json = None if config is None else matching_config_json(config)
        native = _core.LandmarkDatabase.load(str(path), config_json)
        return cls._wrap(native, native.config_json())

    def __len__(self) -> int:
        return len(self._db)


__all__ = [
    "LandmarkDatabase",
    "PairMemo",
    "PairResult",
    "QueryResult",
    "compare",
    "matching_config_json",
    "synthetic_landmark",
]
