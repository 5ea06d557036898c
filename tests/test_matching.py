"""Matching from Python: typed results, the issue's scenarios, database round trip.

Descriptors come from the Rust synthetic generator (``decod_rs.synthetic_landmark``), seeded;
thresholds are the config's own (``min_inliers``), so a regression in the matcher fails here.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import decod_rs
from decod_rs import LandmarkDatabase, compare, load_config, synthetic_landmark

CFG = load_config(preset="tunnel")
MIN_INLIERS = CFG.matching.min_inliers


def test_same_joint_from_the_reversed_heading_is_matched() -> None:
    a = synthetic_landmark(1, 5, stamp=0.0, view_seed=1)
    b = synthetic_landmark(1, 5, stamp=500.0, view_seed=2, reversed=True)
    r = compare(a, b, CFG)
    assert isinstance(r, decod_rs.PairResult)
    assert r.heading_deg == 180.0
    assert r.inliers >= MIN_INLIERS
    assert r.rejection is None
    assert r.score == pytest.approx(2 * r.inliers / (r.query_keypoints + r.candidate_keypoints))


def test_pairs_of_one_pass_are_compared_under_its_own_heading_only() -> None:
    # Views of one pass share the sensor's heading: with ``same_heading`` a pair that agrees
    # only turned round is judged at 0 degrees (and fails), an unturned pair is unchanged.
    from decod_rs.matching import PairMemo, compare_pairs

    a = synthetic_landmark(1, 5, stamp=0.0, view_seed=1)
    turned = synthetic_landmark(1, 5, stamp=500.0, view_seed=2, reversed=True)
    same = synthetic_landmark(1, 5, stamp=500.0, view_seed=3)
    both = compare_pairs([a, turned, same], [(0, 1), (0, 2)], CFG)
    one = compare_pairs([a, turned, same], [(0, 1), (0, 2)], CFG, same_heading=True)
    assert both[0].heading_deg == 180.0 and both[0].inliers >= MIN_INLIERS
    assert one[0].heading_deg == 0.0 and one[0].inliers < MIN_INLIERS
    assert (one[1].heading_deg, one[1].inliers, one[1].chance) == (
        both[1].heading_deg,
        both[1].inliers,
        both[1].chance,
    )
    assert both[1].heading_deg == 0.0 and both[1].inliers >= MIN_INLIERS
    memo = PairMemo([a, turned, same], CFG)
    assert [r.heading_deg for r in memo.compare([(0, 1), (0, 2)])] == [0.0, 0.0]


def test_a_runs_views_prepared_once_give_the_database_the_same_answers() -> None:
    # The pipeline prepares each landmark once (PairMemo.views) for its track links, its
    # database and its queries: the answers equal those of the paths that prepare their own.
    from decod_rs.matching import PairMemo

    db_views = [synthetic_landmark(2, j, stamp=float(j), view_seed=j) for j in range(12)]
    queries = [
        synthetic_landmark(2, j, stamp=500.0 + j, view_seed=50 + j, reversed=j % 2 == 1)
        for j in range(0, 12, 3)
    ]
    memo = PairMemo(db_views + queries, CFG)
    fresh, shared = LandmarkDatabase(CFG), LandmarkDatabase(CFG)
    fresh.extend(db_views, list(range(12)))
    shared.extend_prepared(memo.views, list(range(12)), list(range(12)))
    want = fresh.query_batch(queries)
    got = shared.query_batch_prepared(memo.views, list(range(12, 16)))
    assert [r.to_json() for r in got] == [r.to_json() for r in want]
    assert sum(r.accepted for r in got) >= 3
    assert [r.candidate_index for r in got if r.accepted] == [
        r.candidate_index for r in want if r.accepted
    ]
    with pytest.raises(ValueError, match="16 out of range for 16 views"):
        shared.query_batch_prepared(memo.views, [16])


def test_a_runs_queries_in_slices_give_the_same_answers_and_show_progress(
    capsys: pytest.CaptureFixture[str],
) -> None:
    # decod run queries a batch in slices (QUERY_CHUNKS) to show its progress on a long log:
    # the answers are those of the whole batch at once.
    from decod_rs.matching import PairMemo
    from decod_rs.stages.match import query_database

    outbound = [synthetic_landmark(2, j, stamp=float(j), view_seed=j) for j in range(12)]
    back = [
        synthetic_landmark(2, j, stamp=500.0 + j, view_seed=50 + j, reversed=j % 2 == 1)
        for j in range(0, 12, 2)
    ]
    landmarks = outbound + back
    origins = np.array([lm.origin for lm in landmarks])
    axes = np.array([lm.axis for lm in landmarks])
    tracks = np.arange(len(landmarks), dtype=np.int64)
    memo = PairMemo(landmarks, CFG.matching)
    results, mode, order = query_database(
        landmarks, tracks, (origins, axes), CFG, "batch", 250.0, memo, progress=True
    )
    db = LandmarkDatabase(CFG)
    db.extend_prepared(memo.views, list(range(12)), list(range(12)), origins[:12], axes[:12])
    queries = list(range(12, len(landmarks)))
    want = db.query_batch_prepared(memo.views, queries, across_passes=True, directions=axes[12:])
    assert (mode, order) == ("batch", list(range(12)))
    assert [r.to_json() for r in results] == [r.to_json() for r in want]
    assert sum(r.accepted for r in results) >= 3
    lines = [x for x in capsys.readouterr().err.splitlines() if x.startswith("match")]
    assert lines and lines[-1].split()[2] == f"{len(queries)}/{len(queries)}"


def test_the_odometry_heading_keeps_a_runs_answers_and_refuses_bad_axes() -> None:
    # A run orients its views (each landmark's axis in the odometry frame): the return pass
    # reversed, along -x, the outbound along +x, turned 20 degrees to stand for yaw drift.
    # Only the heading the odometry allows is compared, and the accepted loops are those of
    # the comparison under both headings.
    from decod_rs.matching import PairMemo

    db_views = [synthetic_landmark(3, j, stamp=float(j), view_seed=j) for j in range(12)]
    turned = [j % 2 == 1 for j in range(0, 12, 3)]
    queries = [
        synthetic_landmark(3, j, stamp=500.0 + j, view_seed=50 + j, reversed=turned[k])
        for k, j in enumerate(range(0, 12, 3))
    ]
    memo = PairMemo(db_views + queries, CFG)
    yaw = np.deg2rad(20.0)
    out = np.tile([1.0, 0.0, 0.0], (12, 1))
    back = np.array([[-np.cos(yaw), np.sin(yaw), 0.0] if t else [1.0, 0.0, 0.0] for t in turned])
    plain, oriented = LandmarkDatabase(CFG), LandmarkDatabase(CFG)
    plain.extend_prepared(memo.views, list(range(12)), list(range(12)))
    oriented.extend_prepared(memo.views, list(range(12)), list(range(12)), directions=out)
    assert oriented.directions() == pytest.approx(out)
    assert np.isnan(plain.directions()).all()
    want = plain.query_batch_prepared(memo.views, list(range(12, 16)))
    got = oriented.query_batch_prepared(memo.views, list(range(12, 16)), directions=back)
    assert sum(r.accepted for r in want) >= 3
    assert [(r.accepted, r.candidate_index, r.heading_deg, r.inliers) for r in got] == [
        (r.accepted, r.candidate_index, r.heading_deg, r.inliers) for r in want
    ]
    with pytest.raises(ValueError, match=r"directions: shape \(1, 3\) for 4 queries"):
        oriented.query_batch_prepared(memo.views, list(range(12, 16)), directions=back[:1])
    # Online mode: one query at a time, with its own axis.
    for q, axis, r in zip(queries, back, want, strict=True):
        one = oriented.query(q, direction=axis)
        assert (one.accepted, one.candidate_index, one.heading_deg) == (
            r.accepted,
            r.candidate_index,
            r.heading_deg,
        )
    with pytest.raises(ValueError, match=r"direction: shape \(2,\)"):
        oriented.query(queries[0], direction=[1.0, 0.0])
    with pytest.raises(ValueError, match=r"directions.*is zero"):
        oriented.set_directions([0], np.zeros((1, 3)))
    with pytest.raises(ValueError, match=r"directions.*not finite"):
        oriented.set_directions([0], np.full((1, 3), np.nan))


def test_half_missing_and_misaligned_views_match() -> None:
    a = synthetic_landmark(1, 6, view_seed=1, random_view=False)
    half = synthetic_landmark(
        1, 6, stamp=100.0, view_seed=2, random_view=False, missing_arc=(0.75, 0.5)
    )
    assert compare(a, half, "tunnel").inliers >= MIN_INLIERS
    shifted = synthetic_landmark(1, 6, stamp=100.0, view_seed=3, random_view=False, shift_z_m=0.3)
    r = compare(a, shifted)
    assert r.inliers >= MIN_INLIERS
    # Origin moved +1 cell (0.3 m): the query's features lie 0.3 m earlier in the candidate.
    assert r.dz_m == pytest.approx(-0.3, abs=0.15)


def test_different_joints_are_not_matched() -> None:
    a = synthetic_landmark(2, 1, view_seed=1)
    b = synthetic_landmark(2, 2, stamp=100.0, view_seed=2)
    r = compare(a, b, CFG)
    assert r.inliers < MIN_INLIERS
    assert r.rejection == "too_few_inliers"


def test_batch_query_finds_the_right_joints_and_carries_factor_data() -> None:
    # The paper's trajectory threshold (9): these synthetic true pairs reach K = 13-28, below
    # the tunnel preset's 16 (set against the shield tunnel's two-ring periodicity) for half.
    db = LandmarkDatabase({**CFG.to_dict()["matching"], "min_inliers": 9})
    assert db.extend(
        synthetic_landmark(3, k, stamp=8.0 * k, view_seed=k) for k in range(8)
    ) == list(range(8))
    assert len(db) == 8
    queries = [
        synthetic_landmark(3, k, stamp=900.0 - k, view_seed=100 + k, reversed=True)
        for k in range(8)
    ]
    results = db.query_batch(queries)
    # The top-1 is right for every query; a weak one may still be refused by the count margin
    # of the uniqueness test (uniqueness_sigma), never accepted wrongly.
    assert sum(r.accepted for r in results) >= 6  # 8 of 8 at 2.5 sigma, 4 at 3 (seed 3)
    for k, r in enumerate(results):
        assert r.candidate_index == k
        assert r.accepted or r.rejection == "not_unique", r
        assert r.heading_deg == 180.0
        assert r.candidate_stamp == pytest.approx(8.0 * k)
        assert r.query_origin.shape == (3,) and r.candidate_axis.shape == (3,)
        assert np.isclose(np.linalg.norm(r.query_axis), 1.0)
        assert r.runner_up_score < r.score
        assert json.loads(r.to_json())["accepted"] is r.accepted


def test_aliased_joints_are_not_accepted() -> None:
    db = LandmarkDatabase("tunnel")
    db.extend(synthetic_landmark(4, 9, stamp=10.0 * k, view_seed=k) for k in range(4))
    r = db.query(synthetic_landmark(4, 9, stamp=999.0, view_seed=77))
    assert r.inliers >= MIN_INLIERS  # it does look like a loop...
    assert not r.accepted  # ...but not a unique one
    assert r.rejection == "not_unique"


def test_online_mode_respects_eligibility() -> None:
    db = LandmarkDatabase()
    first, i0 = db.query_online(synthetic_landmark(5, 1, stamp=0.0, view_seed=1))
    assert (first.rejection, i0) == ("no_candidates", 0)
    close, _ = db.query_online(synthetic_landmark(5, 1, stamp=5.0, view_seed=2))
    assert close.rejection == "ineligible" and close.eligible == 0
    revisit, _ = db.query_online(synthetic_landmark(5, 1, stamp=300.0, view_seed=3))
    assert not revisit.accepted  # two views of the joint in the database: not unique
    assert revisit.eligible == 2


def test_database_save_load_round_trip_and_version_error(tmp_path: Path) -> None:
    db = LandmarkDatabase("tunnel")
    db.extend(synthetic_landmark(6, k, stamp=10.0 * k, view_seed=k) for k in range(3))
    path = tmp_path / "db.json"
    db.save(path)
    back = LandmarkDatabase.load(path)
    assert len(back) == 3
    q = synthetic_landmark(6, 1, stamp=500.0, view_seed=9, reversed=True)
    a, b = db.query(q), back.query(q)
    assert (a.candidate_index, a.inliers, a.score, a.accepted) == (
        b.candidate_index,
        b.inliers,
        b.score,
        b.accepted,
    )
    np.testing.assert_array_equal(back.landmark(1).descriptor, db.landmark(1).descriptor)
    pipe = LandmarkDatabase("pipe")
    pipe.add(synthetic_landmark(6, 1, grid="pipe"))
    pipe.save(tmp_path / "pipe.json")
    # A loaded database keeps the config it was saved with (pipe, not the tunnel default).
    saved = json.loads(LandmarkDatabase.load(tmp_path / "pipe.json")._db.config_json())
    assert saved == load_config(preset="pipe").to_dict()["matching"]
    doc = json.loads(path.read_text())
    doc["version"] = 99
    path.write_text(json.dumps(doc))
    with pytest.raises(decod_rs.DatabaseError, match="version 99"):
        LandmarkDatabase.load(path)
    with pytest.raises(FileNotFoundError):
        LandmarkDatabase.load(tmp_path / "missing.json")


def test_ablation_switches_and_bad_config() -> None:
    a = synthetic_landmark(7, 1, view_seed=1)
    b = synthetic_landmark(7, 1, stamp=100.0, view_seed=2)
    base = CFG.to_dict()["matching"]
    for overrides in (
        {"verification": False},
        {"normalisation": "scale_only"},
        {"sign_only": True},
    ):
        r = compare(a, b, {**base, **overrides})
        assert r.inliers > 0
    no_verif = compare(a, b, {**base, "verification": False})
    assert no_verif.inliers == no_verif.matches  # every tentative match counts
    with pytest.raises(decod_rs.ConfigError, match="normalisation"):
        compare(a, b, {**base, "normalisation": "bogus"})
    with pytest.raises(decod_rs.ConfigError):
        compare(a, b, {**base, "no_such_key": 1})
