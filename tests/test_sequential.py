"""Boundaries tracked within each pass (sequential factors, the joint registry) end to end on
simulated pipes with uneven drift: the outbound pass 5 % short, the return 15 % short (the
case where loops alone meet the passes halfway and make the outbound pass worse)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from decod_rs._core import Landmark
from decod_rs.chainage import MIN_STEP_M, outbound_course, revisits
from decod_rs.evaluate import evaluate_run
from decod_rs.joints import landmark_chainage
from decod_rs.pipeline import run_log
from decod_rs.sequential import RIB_POLARITY, boundary_polarity
from decod_rs.sim import simulate
from decod_rs.sim.trajectory import Trajectory, TrajectorySpec
from decod_rs.tum import interpolate_poses, read_tum


@pytest.fixture(scope="module")
def uneven(module_dir: Path) -> Path:
    sim = module_dir / "uneven" / "sim"
    simulate("hume", sim, seed=31, length_m=30.0, drift="legs:-0.05,-0.15", progress=False)
    return sim


def _run(sim: Path, out: Path, **kwargs: object) -> tuple[dict, dict]:
    run_log(sim / "log", out, imu_topic="/imu", progress=False, plots=False, **kwargs)  # type: ignore[arg-type]
    result, _ = evaluate_run(out, sim / "gt.tum", sim / "joints.json")
    return result, json.loads((out / "report.json").read_text())


def _far_end_error(run: Path, sim: Path) -> float:
    """Axial error of the corrected trajectory at the far end, metres."""
    gt_t, gt = read_tum(sim / "gt.tum")
    t, poses = read_tum(run / "corrected.tum")
    far = int(np.argmax(gt[:, 0, 3]))
    here = interpolate_poses(t, poses, gt_t[far : far + 1])[0]
    return float(here[0, 3] - gt[far, 0, 3])


def test_tracks_correct_the_pass_that_loops_alone_cannot(uneven: Path, tmp_path: Path) -> None:
    with_tracks, report = _run(uneven, tmp_path / "seq")
    loops_only, plain = _run(uneven, tmp_path / "loops", sequential=False)
    odo = with_tracks["trajectory"]["odometry"]["rmse_m"]
    rmse = with_tracks["trajectory"]["corrected"]["rmse_m"]
    # The paper's graph makes the trajectory worse here (meets the passes halfway); with the
    # tracks it is better than the odometry by more than half (0.36 of 1.31 m on seed 1).
    assert loops_only["trajectory"]["corrected"]["rmse_m"] > 0.8 * odo
    assert rmse < 0.5 * odo, (rmse, odo, report["sequential"])
    assert report["counts"]["sequential_factors"] > 10
    assert plain["counts"]["sequential_factors"] == 0 and plain["sequential"] is None
    # A pipe's grooves are seen alike from both sides: no side offset is removed
    # (decod_rs.side_offset; too few straddling pairs with a forward sensor to measure one).
    assert report["sequential"]["side_offset"]["applied"] is False
    # The outbound pass keeps its length: far-end error within 1.5 % of the 30 m (the
    # odometry's is 5 %, 1.5 m).
    assert abs(_far_end_error(tmp_path / "seq", uneven)) < 0.015 * 30.0


def test_joint_registry_lists_each_confirmed_joint(uneven: Path, tmp_path: Path) -> None:
    _run(uneven, tmp_path / "run")
    with (tmp_path / "run" / "joints.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    confirmed = np.array([float(r["chainage_m"]) for r in rows if r["loop_confirmed"] == "1"])
    meta = json.loads((uneven / "joints.json").read_text())
    start = meta["trajectory"]["x_start_m"]
    chainages = np.array(meta["joints_x_m"]) - start
    chainages = chainages[(chainages > 0.5) & (chainages < 29.0)]  # seen on both passes
    # Every joint has a loop-confirmed registry row at its chainage within 2 % (the odometry
    # is 5 % off outbound; 1-1.4 % measured on seed 31, short: views of a receding groove
    # put it slightly nearer). Other confirmed rows are wall features that are not joints
    # (lateral connections), which the registry rightly lists too.
    errors = [np.min(np.abs(confirmed - c)) for c in chainages]
    within = [e <= 0.02 * c + 0.05 for e, c in zip(errors, chainages, strict=True)]
    assert np.mean(within) >= 0.8, list(zip(chainages.round(2), np.round(errors, 3), strict=True))
    # One row per physical boundary: no two rows closer than the same-boundary radius of
    # this pipe (0.1 m; before the merge by place, a joint's unlinked tracks were rows of
    # their own, millimetres apart), and one row at nearly every joint (a wall feature
    # 0.1-0.15 m from a joint may add a second).
    every = np.sort([float(r["chainage_m"]) for r in rows])
    assert np.diff(every).min() > 0.09
    at_joint = [int(np.sum(np.abs(every - c) <= 0.15)) for c in chainages]
    assert min(at_joint) >= 1 and np.mean(np.array(at_joint) == 1) >= 0.75, at_joint
    with (tmp_path / "run" / "landmarks.csv").open() as fh:
        landmarks = list(csv.DictReader(fh))
    assert all(int(lm["track_id"]) >= 0 and int(lm["joint_id"]) >= 0 for lm in landmarks)


def test_joints_closer_than_the_drift_of_a_submap_interval_make_no_wrong_track(
    tmp_path: Path,
) -> None:
    # Joints 1 m apart; the odometry reports 60 % of the distance (a frontend that nearly
    # stalls): between two anchors it is off by more than the track radius.
    sim = tmp_path / "sim"
    simulate(
        "hume",
        sim,
        seed=32,
        length_m=15.0,
        drift="legs:-0.4,-0.4",
        scene_overrides={"segment_length_m": 1.0},
        progress=False,
    )
    _run(sim, tmp_path / "run")
    gt_t, gt = read_tum(sim / "gt.tum")
    with (tmp_path / "run" / "landmarks.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    by_track: dict[int, list[float]] = {}
    for r in rows:
        pose = interpolate_poses(gt_t, gt, np.array([float(r["stamp"])]))[0]
        origin = np.array([float(r[f"origin_{a}"]) for a in "xyz"])
        by_track.setdefault(int(r["track_id"]), []).append(
            float((pose[:3, :3] @ origin)[0] + pose[0, 3])
        )
    spans = [max(xs) - min(xs) for xs in by_track.values()]
    # Every track holds views of one joint: its views lie within a few cm in the true world,
    # never a joint spacing (1 m) apart.
    assert max(spans) < 0.3, sorted(spans)[-5:]


def _view(centre_m: float, rng: np.random.Generator) -> Landmark:
    """A view whose two rows about the boundary stand ``centre_m`` off a wall of 1 cm
    roughness (negative: inwards, a rib)."""
    d = rng.normal(0.0, 0.01, (16, 256))
    d[7:9] += centre_m
    return Landmark(
        0.0,
        np.zeros(3),
        np.array([1.0, 0.0, 0.0]),
        np.array([0.0, 0.0, -1.0]),
        d,
        np.ones((16, 256), dtype=bool),
        cell_z_m=0.25,
        perimeter_m=15.0,
    )


def test_boundary_polarity_tells_ribs_from_grooves() -> None:
    rng = np.random.default_rng(4)
    # Steel arches: the surface 3 cm inwards over the boundary rows (the horseshoe measured
    # -1.05 spread units); a few views of rock clutter do not change the median.
    ribs = [_view(-0.03, rng) for _ in range(20)] + [_view(0.0, rng) for _ in range(5)]
    polarity = boundary_polarity(ribs)
    assert polarity is not None and polarity <= RIB_POLARITY, polarity
    # Grooves (4 mm outwards) and a plain wall are not ribs.
    for centre in (0.004, 0.0):
        polarity = boundary_polarity([_view(centre, rng) for _ in range(20)])
        assert polarity is not None and polarity > RIB_POLARITY, (centre, polarity)
    assert boundary_polarity([]) is None


def _yaw(theta: float, x: float, y: float, z: float = 0.0) -> np.ndarray:
    pose = np.eye(4)
    c, s = np.cos(theta), np.sin(theta)
    pose[:2, :2] = [[c, -s], [s, c]]
    pose[:3, 3] = [x, y, z]
    return pose


def test_chainage_follows_each_landmarks_axis_through_stops_and_turns() -> None:
    # The robot stands 2 s at x = 0, drives 10 m along x at 0.5 m/s (10 Hz), creeps to a stop
    # with 2 mm steps that wander 3 mm sideways, then turns on the spot (a turn return).
    stand = [_yaw(0.0, 0.0, 0.0)] * 20
    drive = [_yaw(0.0, 0.05 * k, 0.005 * np.sin(0.05 * k)) for k in range(1, 201)]
    end = drive[-1][:3, 3]
    creep = [_yaw(0.0, end[0] + 0.002 * k, end[1] + 0.003 * (-1) ** k) for k in range(1, 6)]
    stop = creep[-1][:3, 3]
    turn = [_yaw(np.pi * k / 30, stop[0], stop[1]) for k in range(1, 31)]
    poses = np.stack(stand + drive + creep + turn)
    # Along the corridor (x): the creep's 3 mm sideways wander is not distance along it.
    to_stop = float(stop[0])
    stamps = 0.1 * np.arange(len(poses))
    # Landmarks (anchor frame: the pose at their stamp): a ring 3 m ahead of the standing robot,
    # its centre 1.5 m above the sensor; one seen at 5 m; a joint 2 m past the far end seen
    # from the stopped robot, and the same joint seen from behind after half of the turn.
    k_half = len(stand) + len(drive) + len(creep) + 15
    seen_from = [0, len(stand) + 100, len(stand) + 200 + 4, k_half]
    origins = np.array([[3.0, 0.0, 1.5], [0.2, 0.05, 1.5], [2.0, 0.0, 1.5], [0.0, -2.0, 1.5]])
    axes = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    got = landmark_chainage(stamps[seen_from], origins, axes, stamps, poses)
    assert got[0] == pytest.approx(3.0, abs=0.005)
    assert got[1] == pytest.approx(5.25, abs=0.005)  # seen from x = 5.05
    # Past the far end: 2 m beyond the stop (the previous rule put both views of this joint
    # within a few centimetres of the stop).
    assert got[2] == pytest.approx(to_stop + 2.0, abs=0.005)
    assert got[3] == pytest.approx(to_stop + 2.0, abs=0.005)


def test_chainage_does_not_count_a_back_up_twice() -> None:
    # A crawler drives 20 m out at 0.5 m/s, backs up 4 m half-way to look again at a defect,
    # drives on and comes back (the simulator's trajectory, wobble and all). A joint at
    # x = 15 m, seen just after the back-up, is 15 m along the pipe, not 23 m along the path.
    spec = TrajectorySpec(
        x_start_m=0.0,
        length_m=20.0,
        speed_mps=0.5,
        return_mode="reverse",
        backups=((0.0, 0.5, 4.0),),
    )
    traj = Trajectory(spec, np.random.default_rng(3))
    stamps = np.arange(0.0, traj.duration_s, 0.1)
    poses = traj.poses(stamps)
    x = poses[:, 0, 3]
    out = stamps <= traj.t_far_arrive
    # Views from 3 m, from the back-up's far point (6 m: a joint the path passes three
    # times) and from 14 m, after it.
    backmost = int(np.argmin(np.where(out & (stamps > 20.0), x, np.inf)))
    views = [int(np.argmax(x > 3.0)), backmost, int(np.argmax(out & (x > 14.0)))]
    assert x[backmost] == pytest.approx(6.0, abs=0.05)
    joints = np.array([5.0, 9.0, 15.0])
    origins = np.zeros((3, 3))
    for k, (i, joint) in enumerate(zip(views, joints, strict=True)):
        origins[k] = poses[i, :3, :3].T @ (np.array([joint, 0.0, 0.0]) - poses[i, :3, 3])
    axes = np.array([poses[i, :3, :3].T @ np.array([1.0, 0.0, 0.0]) for i in views])
    got = landmark_chainage(stamps[views], origins, axes, stamps, poses)
    # Within a centimetre: the wobble's few mm sideways are not distance along the pipe.
    assert got == pytest.approx(joints, abs=0.01)
    course = outbound_course(poses[:, :3, 3])
    assert np.all(np.diff(course[:, 0]) > 0.0)
    # It reaches the far end (within one step) and is as long as the pipe it covers.
    assert course[-1, 0] > 20.0 - MIN_STEP_M
    assert float(np.sum(np.linalg.norm(np.diff(course, axis=0), axis=1))) == pytest.approx(
        course[-1, 0] - course[0, 0], abs=0.01
    )


def test_revisits_mark_the_ground_driven_again_and_nothing_else() -> None:
    # Out to 36 m, back to 6 m, out to 40 m (a section driven twice), with a stop at 20 m
    # whose positions jitter by 3 mm, and the simulator's wobble.
    spec = TrajectorySpec(
        x_start_m=0.0,
        length_m=40.0,
        speed_mps=1.0,
        return_mode="reverse",
        backups=((0.0, 0.9, 30.0),),
        stops=((0.0, 0.5, 5.0),),
    )
    traj = Trajectory(spec, np.random.default_rng(5))
    stamps = np.arange(0.0, traj.t_far_arrive, 0.1)
    x = traj.poses(stamps)[:, :3, 3]
    rng = np.random.default_rng(6)
    x = x + rng.normal(0.0, 0.003, x.shape)
    again = revisits(x, 0.1)
    front = np.maximum.accumulate(x[:, 0])
    # Exactly the positions 10 cm or more behind the farthest point reached so far (to
    # within the jitter): the 30 m back and the 30 m forward again, not the stop.
    behind = front - x[:, 0]
    assert not np.any(again & (behind < 0.08)) and np.all(again[behind > 0.12])
    assert 0.4 * again.size < np.count_nonzero(again) < 0.7 * again.size
    assert not np.any(revisits(x[x[:, 0] < 30.0][:200], 0.1))
