"""A run's landmarks waiting on disk once extracted (decod_rs._core.Spill, src/spill.rs): the
same landmarks, the same comparisons, the same files, and nothing left behind."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from decod_rs import _core, synthetic_landmark
from decod_rs.config import load_config
from decod_rs.matching import matching_config_json
from decod_rs.parking import set_aside

RUN_FILES = ("corrected.tum", "loops.csv", "joints.csv", "landmarks.csv", "graph.g2o")


def _landmarks(n: int = 6) -> list[_core.Landmark]:
    # Views of three joints, two each (a candidate of each query is another view of it).
    return [
        synthetic_landmark(4, j // 2, stamp=30.0 * j, view_seed=j, reversed=j % 2 == 1)
        for j in range(n)
    ]


def _left_in(directory: Path) -> list[str]:
    return sorted(p.name for p in directory.iterdir())


def test_landmarks_on_disk_are_the_same_landmarks_and_leave_no_file(tmp_path: Path) -> None:
    held = _landmarks()
    spill = _core.Spill(tmp_path)
    on_disk = spill.put(held)
    assert [lm.on_disk for lm in on_disk] == [True] * len(held)
    assert not any(lm.on_disk for lm in held)
    assert spill.bytes > len(held) * 16 * 256 * 4  # the cells went to the file
    if os.name == "posix":
        assert _left_in(tmp_path) == []  # unlinked at once: nothing to clean up, ever
    for a, b in zip(held, on_disk, strict=True):
        assert a.to_json() == b.to_json()  # lossless, every field
        for name in ("descriptor", "mask", "normal_e1", "normal_e2", "contour", "origin"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
        assert (a.submap_stamp, a.cell_z_m, a.radius_m) == (b.submap_stamp, b.cell_z_m, b.radius_m)
    assert "on disk" in repr(on_disk[0])
    # Put again, they are given back as they are (no second copy on disk).
    size = spill.bytes
    assert all(a is not None for a in spill.put(on_disk)) and spill.bytes == size
    # The file outlives the Spill object: the landmarks keep it.
    del spill
    np.testing.assert_array_equal(on_disk[3].descriptor, held[3].descriptor)


def test_matching_on_disk_gives_the_same_results(tmp_path: Path) -> None:
    held = _landmarks()
    spill = _core.Spill(tmp_path)
    on_disk = spill.put(held)
    config = matching_config_json(load_config().matching)
    pairs = [(i, j) for i in range(len(held)) for j in range(len(held)) if i != j]
    fields = ("inliers", "matches", "score", "dz_m", "dp", "heading_deg", "rejection")

    def summary(results: list[_core.PairResult]) -> list[tuple[object, ...]]:
        return [tuple(getattr(r, f) for f in fields) for r in results]

    expected = summary(_core.compare_pairs(held, pairs, config, False))
    assert summary(_core.compare_pairs(on_disk, pairs, config, False)) == expected
    views = _core.PreparedViews(on_disk, config)
    assert summary(views.compare_pairs(pairs, False)) == expected
    assert max(r.inliers for r in views.compare_pairs(pairs, False)) >= 9  # views of a joint
    # The views' patches on disk too, read back by each comparison.
    size = spill.bytes
    set_aside = _core.PreparedViews(on_disk, config, spill)
    assert spill.bytes > size + len(held) * 16 * 256 * 4
    assert summary(set_aside.compare_pairs(pairs, False)) == expected

    queries = [1, 3, 5]
    results = []
    for v in (views, set_aside):
        db = _core.LandmarkDatabase(config)
        db.extend_prepared(v, [0, 2, 4], [0, 1, 2])
        got = db.query_batch_prepared(v, queries, False)
        results.append([(r.accepted, r.candidate_index, r.chance) for r in got])
    assert results[0] == results[1] and any(a for a, _, _ in results[0])
    stored = db.landmark(1)
    assert stored.on_disk and stored.to_json() == held[2].to_json()


def test_a_survey_of_landmarks_on_disk_is_the_same_file(tmp_path: Path) -> None:
    held = _landmarks()
    on_disk = _core.Spill(tmp_path).put(held)
    header = json.dumps({"joint_ids": list(range(len(held)))})
    _core.write_survey(str(tmp_path / "a.decod"), header, held)
    _core.write_survey(str(tmp_path / "b.decod"), header, on_disk)
    assert (tmp_path / "a.decod").read_bytes() == (tmp_path / "b.decod").read_bytes()


def test_a_round_on_disk_is_not_set_aside_again(tmp_path: Path) -> None:
    round_one = _core.Spill(tmp_path).put(_landmarks())
    before = list(round_one)
    with set_aside([round_one]) as parked:
        parked.leave()
        assert not parked.on_disk and round_one == before  # a few hundred bytes each


def test_a_directory_that_cannot_hold_the_file_is_named(tmp_path: Path) -> None:
    missing = tmp_path / "not-there"
    with pytest.raises(OSError, match="not-there"):
        _core.Spill(missing)


class _FullDisk:
    """A spill on a disk with no room left."""

    bytes = 0

    def put(self, landmarks: list[_core.Landmark]) -> list[_core.Landmark]:
        raise OSError(28, "No space left on device", "landmarks.spill")


def test_a_run_with_its_landmarks_on_disk_writes_the_same_files(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    # A 0.6 m concrete pipe seen by 16 beams whose odometry reports 95 % out and 85 % back:
    # a rebuilt round that stands (its landmarks on disk too, the first round left there).
    # Seed 41 is new to this test.
    from decod_rs import pipeline
    from decod_rs.pipeline import run_log
    from decod_rs.sim import simulate

    sim = tmp_path / "sim"
    simulate(
        "hume",
        sim,
        seed=41,
        sensor="spin16",
        return_mode="reverse",
        length_m=20.0,
        drift="legs:-0.05,-0.15",
        progress=False,
    )
    runs = tmp_path / "runs"
    for name, on_disk in (("disk", True), ("memory", False)):
        run_log(
            sim / "log",
            runs / name,
            imu_topic="/imu",
            progress=False,
            plots=False,
            landmarks_on_disk=on_disk,
        )
    report = json.loads((runs / "disk" / "report.json").read_text())
    assert report["counts"]["accepted"] > 0 and report["rebuild"]["rebuilt"], report["rebuild"]
    # The landmarks went to the file (about 29 KB each; the first round's too).
    assert report["landmarks_on_disk_bytes"] > 25_000 * report["counts"]["landmarks"]
    memory = json.loads((runs / "memory" / "report.json").read_text())
    assert memory["landmarks_on_disk_bytes"] is None
    for name in (*RUN_FILES, "survey.decod"):
        assert (runs / "disk" / name).read_bytes() == (runs / "memory" / name).read_bytes(), name
    assert _left_in(runs) == ["disk", "memory"]  # no spill file beside the runs

    # A disk that fills up: the run goes on with its landmarks in memory, says so once a
    # round, and writes the same files.
    monkeypatch.setattr(pipeline, "landmark_spill", lambda out: _FullDisk())
    capsys.readouterr()
    run_log(sim / "log", runs / "full", imu_topic="/imu", progress=False, plots=False)
    assert "No space left on device" in capsys.readouterr().err
    for name in (*RUN_FILES, "survey.decod"):
        assert (runs / "full" / name).read_bytes() == (runs / "memory" / name).read_bytes(), name
