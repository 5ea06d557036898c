"""A sensor mounted pitched or rolled (not in the matrix, whose sensors are all level).

Pitched 20 deg nose down, a 16-beam spinning sensor sees the floor ahead of it and the crown
behind: the submap's principal direction leans about 11 deg off the corridor axis and, with
the axis taken from it, the two passes' descriptors did not overlap (0 of 541 queries
accepted on a 100 m horseshoe run). The axis is now also taken from the wall's normals and
settled by the contour (``src/wall_normals.rs``, ``extract::best_frame``). What a user relies
on: loops are found on such a log, none is wrong, and the axes the landmarks carry are the
corridor's. Seed 71, 30 m one way: new to every rule involved.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from decod_rs.evaluate import evaluate_run
from decod_rs.pipeline import run_log
from decod_rs.run_files import read_landmarks_csv
from decod_rs.sim import generate, simulate
from decod_rs.tum import read_tum


def _axis_errors_deg(sim: Path, run: Path) -> np.ndarray:
    """Each landmark's axis against the true corridor axis (world x) in its anchor frame."""
    stamps, poses = read_tum(sim / "gt.tum")
    lms = read_landmarks_csv(run / "landmarks.csv")
    out = []
    for stamp, axis in zip(lms.stamp, lms.axis, strict=True):
        rot = poses[int(np.argmin(np.abs(stamps - stamp)))][:3, :3]
        true = rot.T @ np.array([1.0, 0.0, 0.0])
        cos = abs(float(true @ axis)) / float(np.linalg.norm(axis))
        out.append(np.degrees(np.arccos(min(cos, 1.0))))
    return np.asarray(out)


def test_a_pitched_spinning_sensor_finds_the_axis_and_closes_loops(tmp_path: Path) -> None:
    sim = tmp_path / "sim"
    simulate(
        "horseshoe",
        sim,
        seed=71,
        sensor="spin16",
        return_mode="turn",
        length_m=30.0,
        drift=2.0,
        mount_deg=(0.0, 20.0),
        progress=False,
    )
    run = tmp_path / "run"
    run_log(sim / "log", run, imu_topic="/imu", progress=False, plots=False)
    errors = _axis_errors_deg(sim, run)
    # Level, the same sensor's axes are within 0.1 deg (median); PCA alone left 11 deg.
    assert np.median(errors) < 1.0, np.quantile(errors, [0.5, 0.9])
    result, _ = evaluate_run(run, sim / "gt.tum", sim / "joints.json")
    fine, coarse = result["loops"]["fine"], result["loops"]["coarse"]
    assert fine["accepted"] >= 10 and fine["false_positives"] == 0, fine
    assert coarse["false_positives"] == 0, coarse


def test_the_mount_is_checked_before_anything_is_written(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="pitch"):
        simulate("pe", tmp_path / "a", mount_deg=(0.0, 75.0), progress=False)
    with pytest.raises(ValueError, match="roll"):
        simulate("pe", tmp_path / "b", mount_deg=(float("nan"), 0.0), progress=False)
    assert not any(tmp_path.iterdir())


def test_the_mount_turns_scans_imu_and_ground_truth_alike() -> None:
    # Pitched 20 deg nose down: the sensor's x axis points 20 deg below the corridor in the
    # ground truth (the trajectory's own pitch wobble is 8 mrad at most), gravity in the
    # IMU (at rest before the run starts) is as far from the sensor's -z, and the sensor's
    # position is the level run's.
    level = generate("horseshoe", seed=3, sensor="spin16", scan_indices=[0])
    pitched = generate(
        "horseshoe", seed=3, sensor="spin16", scan_indices=[0], mount_deg=(0.0, 20.0)
    )
    x_world = pitched.gt_poses[0][:3, 0]
    assert np.degrees(np.arcsin(-x_world[2])) == pytest.approx(20.0, abs=0.6)
    np.testing.assert_allclose(pitched.gt_poses[0][:3, 3], level.gt_poses[0][:3, 3])
    down = -pitched.imu_accel[0] / np.linalg.norm(pitched.imu_accel[0])
    assert np.degrees(np.arccos(-down[2])) == pytest.approx(20.0, abs=0.6)
    assert pitched.metadata["trajectory"]["mount_pitch_rad"] == pytest.approx(np.radians(20.0))
