"""Odometry that jitters from scan to scan (:mod:`decod_rs.jitter`): the fit follows real
motion (accelerating, turning), removes noise, never spans a gap, and a run on jittery
odometry says so and stitches on the fit."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from decod_rs.config import load_config
from decod_rs.jitter import JITTER_VOXEL_FRACTION, local_fit, smoothing
from decod_rs.pipeline import run_log
from decod_rs.sim import simulate
from decod_rs.tum import (
    interpolate_poses,
    poses_from_tq,
    read_tum,
    so3_exp,
    so3_log,
    tq_from_poses,
)


def _drive(stamps: np.ndarray) -> np.ndarray:
    """A robot that speeds up along x, sways sideways and turns in place half-way."""
    t = stamps - stamps[0]
    x = 0.3 * t + 0.02 * t**2
    y = 0.05 * np.sin(0.4 * t)
    yaw = np.where(t > 10.0, np.minimum(t - 10.0, 3.0), 0.0)  # 1 rad/s for 3 s
    poses = np.repeat(np.eye(4)[None], t.size, axis=0)
    poses[:, 0, 3], poses[:, 1, 3] = x, y
    poses[:, :3, :3] = so3_exp(np.c_[np.zeros_like(t), np.zeros_like(t), yaw])
    return poses


def _noisy(poses: np.ndarray, metres: float, degrees: float, seed: int = 3) -> np.ndarray:
    rng = np.random.default_rng(seed)
    out = poses.copy()
    out[:, :3, 3] += rng.normal(0.0, metres, (len(poses), 3))
    turn = so3_exp(rng.normal(0.0, np.radians(degrees), (len(poses), 3)))
    out[:, :3, :3] = poses[:, :3, :3] @ turn
    return out


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    rel = np.einsum("nji,njk->nik", a[:, :3, :3], b[:, :3, :3])
    return np.degrees(np.linalg.norm(so3_log(rel), axis=1))


def test_the_fit_follows_real_motion_and_removes_noise() -> None:
    stamps = 100.0 + 0.1 * np.arange(200)
    truth = _drive(stamps)
    # Smooth motion, accelerating and turning at 1 rad/s: the fit moves it by microns.
    fitted, dist = local_fit(stamps, truth, 0.55)
    assert np.nanmedian(dist) < 1e-4
    assert np.max(np.linalg.norm(fitted[:, :3, 3] - truth[:, :3, 3], axis=1)) < 2e-3
    # 3 mm / 0.1 deg of noise per pose: the fit is at least 1.7 times closer to the truth.
    noisy = _noisy(truth, 0.003, 0.1)
    fitted, dist = local_fit(stamps, noisy, 0.55)
    err = np.linalg.norm(fitted[:, :3, 3] - truth[:, :3, 3], axis=1)
    raw = np.linalg.norm(noisy[:, :3, 3] - truth[:, :3, 3], axis=1)
    assert np.median(err) * 1.7 < np.median(raw)
    assert np.median(_angle_deg(fitted, truth)) * 1.7 < np.median(_angle_deg(noisy, truth))
    assert 0.002 < np.median(dist) < 0.006


def test_no_fit_spans_an_odometry_gap() -> None:
    stamps = np.r_[0.1 * np.arange(50), 20.0 + 0.1 * np.arange(50)]
    poses = _drive(stamps)
    poses[50:, 0, 3] += 3.0  # a jump across the gap: a fit spanning it would bend both sides
    fitted, dist = local_fit(stamps, poses, 0.55)
    assert np.all(np.isfinite(dist))
    assert np.max(np.linalg.norm(fitted[:, :3, 3] - poses[:, :3, 3], axis=1)) < 2e-3


def test_stamps_a_microsecond_apart_do_not_size_the_fit() -> None:
    stamps = 0.1 * np.arange(2000)
    stamps[1000] = stamps[999] + 1e-6  # a recorder's duplicate
    poses = _noisy(_drive(stamps), 0.003, 0.1)
    fitted, dist = local_fit(stamps, poses, 0.55)
    assert fitted.shape == poses.shape and np.isfinite(dist).sum() >= 1990


def test_smooth_odometry_is_left_alone_and_a_jittery_one_is_smoothed() -> None:
    cfg = load_config(None, "pipe")
    stamps = 0.1 * np.arange(300)
    truth = _drive(stamps)
    clean = smoothing(stamps, truth, cfg)
    assert clean.threshold_m == pytest.approx(JITTER_VOXEL_FRACTION * cfg.submap.voxel_m)
    assert not clean.applied and clean.jitter_m < 0.1 * clean.threshold_m
    assert smoothing(stamps, _noisy(truth, 0.003, 0.1), cfg).applied
    values = cfg.to_dict()
    values["submap"]["smooth_jittery_odometry"] = False
    off = smoothing(stamps, _noisy(truth, 0.003, 0.1), type(cfg)(values))
    assert off.jitter_m > off.threshold_m and not off.applied


@pytest.fixture(scope="module")
def sim(module_dir: Path) -> Path:
    out = module_dir / "pipe" / "sim"
    simulate("hume", out, progress=False, length_m=8.0, drift=0.5)
    return out


def test_a_run_on_jittery_odometry_stitches_on_the_fit(sim: Path, tmp_path: Path) -> None:
    stamps, poses = read_tum(sim / "odom.tum")
    t, q = tq_from_poses(_noisy(poses, 0.003, 0.1))
    tum = tmp_path / "jittery.tum"
    rows = np.column_stack([stamps, t, q])
    np.savetxt(tum, rows, fmt="%.9f")
    run_log(sim / "log", tmp_path / "out", odom_tum=tum, progress=False, plots=False)
    report = json.loads((tmp_path / "out" / "report.json").read_text(encoding="utf-8"))
    jitter = report["ingest"]["odometry_jitter"]
    assert jitter["smoothed"] and 0.002 < jitter["jitter_m"] < 0.006
    # The run's odometry is the fit: within the noise of the truth, closer than the input.
    used_stamps, used = read_tum(tmp_path / "out" / "odometry.tum")
    truth = interpolate_poses(stamps, poses, used_stamps)
    noisy = interpolate_poses(stamps, poses_from_tq(t, q), used_stamps)
    moved = np.linalg.norm(used[:, :3, 3] - truth[:, :3, 3], axis=1)
    noise = np.linalg.norm(noisy[:, :3, 3] - truth[:, :3, 3], axis=1)
    assert np.median(moved) * 1.5 < np.median(noise)
