"""Simulator tests: short corridors, few scans, seeded; every assertion has a known answer."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore

from decod_rs.cli import main as cli_main
from decod_rs.sim import (
    LegProfile,
    Simulation,
    SlipProfile,
    build_scene,
    drift_odometry,
    generate,
    odometry_for_profile,
    parse_profile,
    scene_params,
    simulate,
)
from decod_rs.sim.raycast import cast
from decod_rs.sim.surface import Scene
from decod_rs.sim.sweep import poses_between
from decod_rs.sim.trajectory import Trajectory, TrajectorySpec
from decod_rs.tum import read_tum

TS = get_typestore(Stores.ROS2_HUMBLE)
# Short runs: 2 m out and back at 0.5 m/s is ~17 s of log (171 scans); 800 rays per scan.
SHORT = {"length_m": 2.0, "speed_mps": 0.5, "sensor_overrides": {"rays_per_scan": 800}}


def _tum(path: Path) -> np.ndarray:
    return np.loadtxt(path, dtype=np.float64).reshape(-1, 8)


def _quat_to_matrix(x: float, y: float, z: float, w: float) -> np.ndarray:
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


@pytest.fixture(scope="module")
def hume_log(module_dir: Path):
    out = module_dir / "hume"
    res = simulate("hume", out, seed=3, drift=0.5, progress=False, **SHORT)
    return res


def test_log_has_types_counts_and_stamps(hume_log) -> None:
    res = hume_log
    assert res.log_dir == res.out_dir / "log"
    assert (res.log_dir / "metadata.yaml").is_file()
    with res.mcap_path.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        channels = {c.id: c for c in summary.channels.values()}
        schemas = {s.id: s for s in summary.schemas.values()}
        types = {c.topic: schemas[c.schema_id].name for c in channels.values()}
        assert types == {
            "/points": "sensor_msgs/msg/PointCloud2",
            "/odom": "nav_msgs/msg/Odometry",
            "/imu": "sensor_msgs/msg/Imu",
        }
        assert all(c.message_encoding == "cdr" for c in channels.values())
        counts = {
            channels[cid].topic: n for cid, n in summary.statistics.channel_message_counts.items()
        }
        stamps: dict[str, list[int]] = {"/points": [], "/odom": [], "/imu": []}
        first_cloud = None
        first_odom = []
        for _schema, channel, message in reader.iter_messages():
            stamps[channel.topic].append(message.log_time)
            if channel.topic == "/points" and first_cloud is None:
                first_cloud = TS.deserialize_cdr(message.data, "sensor_msgs/msg/PointCloud2")
            if channel.topic == "/odom":
                first_odom.append(TS.deserialize_cdr(message.data, "nav_msgs/msg/Odometry"))
    gt = _tum(res.gt_tum)
    odom = _tum(res.odom_tum)
    n = res.n_scans
    assert counts == {"/points": n, "/odom": n, "/imu": res.n_imu}
    assert gt.shape[0] == n and odom.shape[0] == n
    # One scan and one odometry message per gt.tum stamp, at 10 Hz; IMU at 100 Hz.
    scan_ns = np.array(stamps["/points"], dtype=np.int64)
    assert np.array_equal(scan_ns, np.array(stamps["/odom"], dtype=np.int64))
    assert np.all(np.diff(scan_ns) == 100_000_000)
    assert np.allclose(scan_ns / 1e9, gt[:, 0], atol=1e-6, rtol=0)
    imu_ns = np.array(stamps["/imu"], dtype=np.int64)
    assert np.all(np.diff(imu_ns) == 10_000_000)
    assert res.n_imu == pytest.approx(res.duration_s * 100 + 1, abs=1)
    # The point cloud layout of the contract.
    c = first_cloud
    assert c is not None
    assert [(f.name, f.offset, f.datatype) for f in c.fields] == [
        ("x", 0, 7),
        ("y", 4, 7),
        ("z", 8, 7),
        ("intensity", 12, 7),
    ]
    assert c.point_step == 16 and c.height == 1 and c.is_dense and not c.is_bigendian
    assert c.header.frame_id == "body" and c.row_step == 16 * c.width
    assert c.data.size == 16 * c.width and c.width > 400
    # /odom carries the drifting odometry of odom.tum.
    o = first_odom[-1]
    assert o.header.frame_id == "odom" and o.child_frame_id == "body"
    p = o.pose.pose.position
    assert np.allclose([p.x, p.y, p.z], odom[-1, 1:4], atol=1e-5)
    assert np.linalg.norm(odom[-1, 1:4] - gt[-1, 1:4]) == pytest.approx(0.5, abs=1e-5)


def test_rosbags_reads_the_directory(hume_log) -> None:
    with Reader(hume_log.log_dir) as reader:
        topics = {c.topic: c.msgtype for c in reader.connections}
        assert topics["/imu"] == "sensor_msgs/msg/Imu"
        imu_conn = [c for c in reader.connections if c.topic == "/imu"]
        msgs = [
            TS.deserialize_cdr(raw, "sensor_msgs/msg/Imu")
            for _, _, raw in reader.messages(connections=imu_conn)
        ]
    # At rest (first 1.5 s) the specific force is gravity negated, in the body frame:
    # R^T (0, 0, 9.81) with R the ground-truth attitude (the crawler rests slightly rolled).
    acc = np.array(
        [
            [m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z]
            for m in msgs[:150]
        ]
    )
    qx, qy, qz, qw = _tum(hume_log.gt_tum)[0, 4:8]
    rot = _quat_to_matrix(qx, qy, qz, qw)
    expected = rot.T @ np.array([0.0, 0.0, 9.81])
    # Bias std 0.03 m/s^2 per axis (4 sigma = 0.12) + noise 0.02 / sqrt(150).
    assert np.allclose(acc.mean(axis=0), expected, atol=0.13)
    assert abs(np.linalg.norm(acc.mean(axis=0)) - 9.81) < 0.13
    assert msgs[0].header.frame_id == "body" and msgs[0].orientation_covariance[0] == -1.0


def _surface_residual(scene: Scene, pts: np.ndarray) -> np.ndarray:
    """Distance (m) from world points to the nearest modelled surface: wall, floor, caps,
    arch inner surfaces and faces."""
    x, y, z = pts.T
    th = np.arctan2(z, y)
    res = [np.abs(np.hypot(y, z) - scene.radius_m - scene.wall_dr(x, th))]
    if scene.floor_z_m is not None:
        res.append(np.abs(z - scene.floor_z_m - scene.floor_dz(x, y)))
    res.append(np.minimum(np.abs(x - scene.x_max_m), np.abs(x - scene.x_min_m)))
    if scene.arches is not None:
        a = scene.arches.nearest(x)
        c = scene.arches.centre(a, th)
        r_in = scene.arches.radius(a, th)
        band = np.abs(x - c) <= scene.arches.half_width + 0.05
        res.append(np.where(band, np.abs(np.hypot(y, z) - r_in), np.inf))
        face = np.abs(np.abs(x - c) - scene.arches.half_width)
        res.append(np.where(np.hypot(y, z) >= r_in - 0.05, face, np.inf))
    return np.min(np.stack(res), axis=0)


@pytest.mark.parametrize(
    ("scene", "sensor", "length"),
    [
        ("hume", "avia", 2.0),
        ("pe", "avia", 2.0),
        ("shield", "spin16", 6.0),
        ("horseshoe", "spin64", 6.0),
    ],
)
def test_points_lie_on_the_surface(scene: str, sensor: str, length: float) -> None:
    overrides = {"rays_per_scan": 3000} if sensor == "avia" else {"h_res_deg": 2.0}
    data = generate(
        scene,
        seed=1,
        length_m=length,
        sensor=sensor,
        sensor_overrides=overrides,
        drift=3.0,
        scan_indices=[0, 60, 90],
    )
    sigma = data.metadata["sensor"]["range_noise_m"]
    for pts, pose in zip(data.points, data.gt_poses, strict=True):
        world = pts.astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]
        r = _surface_residual(data.scene, world)
        # The range noise is along the ray, so the distance to the surface is at most |noise|
        # (+ float32 rounding of coordinates ~1e-6 m): 4 sigma keeps >= 99.9 % of Gaussian
        # draws; allow 0.5 % for points snapped at groove/pocket edges.
        assert np.mean(r < 4 * sigma + 1e-5) >= 0.995, (scene, np.percentile(r, [50, 99, 100]))
    # The check can fail: the same points with the pose moved sideways by 10 sigma are off
    # the surface. (An axial shift would not show in a uniform corridor: the degeneracy.)
    bad = data.gt_poses[-1].copy()
    bad[1, 3] += 10 * sigma
    world = data.points[-1].astype(np.float64) @ bad[:3, :3].T + bad[:3, 3]
    assert np.mean(_surface_residual(data.scene, world) < 4 * sigma + 1e-5) < 0.8


@pytest.mark.parametrize("endpoint", [0.2, 1.7, 15.0])
@pytest.mark.parametrize("mode", ["reverse", "turn"])
def test_drift_gives_the_requested_endpoint_error(endpoint: float, mode: str) -> None:
    spec = TrajectorySpec(x_start_m=0.5, length_m=60.0, speed_mps=0.4, return_mode=mode)
    traj = Trajectory(spec, np.random.default_rng(0))
    t = np.arange(0.0, traj.duration_s, 0.1)
    gt = traj.poses(t)
    dr = drift_odometry(gt, traj.travelled(t), endpoint, np.random.default_rng(7))
    err = dr.odom_poses[:, :3, 3] - gt[:, :3, 3]
    # Exact by construction (to float rounding).
    assert np.linalg.norm(err[-1]) == pytest.approx(endpoint, rel=1e-9)
    assert dr.endpoint_error_m == pytest.approx(endpoint, rel=1e-9)
    # Mostly along the axis: lateral/vertical error at most 20 % of the endpoint error.
    assert np.max(np.hypot(err[:, 1], err[:, 2])) <= 0.2 * endpoint + 1e-9
    assert abs(err[-1, 0]) >= 0.97 * endpoint
    # No drift at the start nor while standing still before moving.
    still = t < spec.pre_s
    assert np.allclose(dr.odom_poses[still], gt[still])


def test_zero_drift_is_ground_truth() -> None:
    sim = Simulation("pe", seed=2, length_m=2.0, speed_mps=0.5, drift="none")
    assert np.array_equal(sim.drift.odom_poses, sim.gt_poses)


def test_same_seed_same_log(tmp_path: Path) -> None:
    kw = {"length_m": 1.5, "speed_mps": 0.5, "sensor_overrides": {"rays_per_scan": 300}}
    a = simulate("pe", tmp_path / "a", seed=5, progress=False, **kw)
    b = simulate("pe", tmp_path / "b", seed=5, progress=False, **kw)
    c = simulate("pe", tmp_path / "c", seed=6, progress=False, **kw)
    assert a.mcap_path.read_bytes() == b.mcap_path.read_bytes()
    assert a.gt_tum.read_text() == b.gt_tum.read_text()
    assert a.joints_json.read_text() == b.joints_json.read_text()
    assert a.mcap_path.read_bytes() != c.mcap_path.read_bytes()


def _cell_maps(scene: Scene, half: float, n_z: int = 16, n_p: int = 256) -> np.ndarray:
    """Unrolled wall offset maps ``(J, n_z, n_p)`` of the interior joints, cell means over
    the descriptor grid (+-``half`` axially, full circumference), 6 x 2 samples per cell."""
    sub_z, sub_p = 6, 2
    maps = []
    inner = [
        j
        for j, x in enumerate(scene.joints_x_m)
        if x - half - 1.0 > scene.x_min_m and x + half + 1.0 < scene.x_max_m
    ]
    for j in inner:
        m = scene.joint_offset_map(j, half - half / (n_z * sub_z), n_z * sub_z, n_p * sub_p)
        maps.append(m.reshape(n_z, sub_z, n_p, sub_p).mean(axis=(1, 3)))
    return np.array(maps)


@pytest.mark.parametrize(("scene", "half"), [("hume", 0.24), ("pe", 0.24), ("shield", 2.4)])
def test_mean_profile_fails_where_the_2d_map_succeeds(scene: str, half: float) -> None:
    sc = build_scene(scene, 0, 45.0)
    maps = _cell_maps(sc, half)
    n_j = maps.shape[0]
    assert n_j >= 6
    rng = np.random.default_rng(0)
    # Two noisy observations of every joint: one range-noise draw per cell.
    obs_a = maps + rng.normal(0.0, sc.range_noise_m, maps.shape)
    obs_b = maps + rng.normal(0.0, sc.range_noise_m, maps.shape)
    prof, prof_a, prof_b = maps.mean(axis=2), obs_a.mean(axis=2), obs_b.mean(axis=2)
    iu = np.triu_indices(n_j, 1)
    between = np.sqrt(((prof[:, None] - prof[None]) ** 2).mean(-1))[iu]
    noise = np.sqrt(((prof_a - prof_b) ** 2).mean(-1))
    # Mean profiles of different joints are closer than two noisy looks at one joint ...
    assert np.median(between) < np.median(noise)
    # ... so identifying a joint by its mean profile mostly fails ...
    d_prof = ((prof_a[:, None] - prof_b[None]) ** 2).sum(-1)
    assert np.mean(d_prof.argmin(axis=1) == np.arange(n_j)) <= 0.5
    # ... while the full 2D maps identify (nearly) every joint.
    d_map = ((obs_a[:, None] - obs_b[None]) ** 2).sum((-1, -2))
    assert np.mean(d_map.argmin(axis=1) == np.arange(n_j)) >= 0.9


@pytest.mark.parametrize("scene", ["hume", "pe", "shield", "horseshoe"])
def test_identical_joints_are_identical(scene: str) -> None:
    sc = build_scene(scene, 4, 30.0, identical_joints=True)
    half = 0.24 if scene in ("hume", "pe") else 0.6
    maps = _cell_maps(sc, half, n_z=8, n_p=64)
    assert maps.shape[0] >= 3
    assert np.max(np.abs(maps - maps[0])) < 1e-6
    if sc.floor_z_m is not None:
        # The floor beside every boundary repeats as well.
        y = np.linspace(-1.5, 1.5, 31)
        floors = [sc.floor_dz(x + np.zeros_like(y), y) for x in sc.joints_x_m[1:-1] + 0.3]
        assert np.max(np.abs(np.array(floors) - floors[0])) < 1e-6
    # Without the flag the joints differ by far more than that.
    diff = _cell_maps(build_scene(scene, 4, 30.0), half, n_z=8, n_p=64)
    assert np.max(np.abs(diff - diff[0])) > 1e-4


def test_turn_rotates_heading_and_gyro_integrates_it() -> None:
    sim = Simulation(
        "shield",
        seed=0,
        length_m=6.0,
        speed_mps=1.5,
        return_mode="turn",
        sensor_overrides={"h_res_deg": 4.0},
    )
    yaw = np.arctan2(sim.gt_poses[:, 1, 0], sim.gt_poses[:, 0, 0])
    assert abs(yaw[0]) < 0.1 and abs(abs(yaw[-1]) - np.pi) < 0.1
    imu = sim.imu
    turn = (imu.t_s >= sim.traj.t_far_arrive - 0.5) & (imu.t_s <= sim.traj.t_return_start + 0.5)
    # Gyro bias 0.5 mrad/s * 7 s and white noise are far below the 1 % tolerance.
    assert np.sum(imu.gyro_radps[turn, 2]) / 100.0 == pytest.approx(np.pi, rel=0.01)


def test_stops_halt_the_vehicle_where_asked_and_keep_the_path() -> None:
    length, speed = 20.0, 1.0
    plain = TrajectorySpec(x_start_m=1.0, length_m=length, speed_mps=speed, return_mode="turn")
    stops = ((0.0, 0.5, 10.0), (1.0, 0.3, 5.0))
    spec = TrajectorySpec(**{**plain.as_dict(), "stops": stops})
    tr, ref = (Trajectory(s, np.random.default_rng(0)) for s in (spec, plain))
    # Each halt costs its seconds plus one ramp (slowing down and speeding up half a ramp each).
    assert tr.duration_s == pytest.approx(ref.duration_s + 10.0 + 5.0 + 2 * spec.ramp_s)
    t = np.arange(0.0, tr.duration_s, 0.01)
    x, v = tr.axial(t), np.gradient(tr.axial(t), t)
    out, back = t < tr.t_far_arrive - 1.0, t > tr.t_return_start + 1.0
    halted_out = out & (t > spec.pre_s + 1.0) & (np.abs(v) < 1e-9)
    halted_back = back & (t < tr.duration_s - spec.post_s - 1.0) & (np.abs(v) < 1e-9)
    # Standing still for the seconds asked, half-way out and 30 % of the way back.
    assert np.ptp(t[halted_out]) == pytest.approx(10.0, abs=0.02)
    assert np.ptp(t[halted_back]) == pytest.approx(5.0, abs=0.02)
    assert np.allclose(x[halted_out], 1.0 + 0.5 * length, atol=1e-6)
    assert np.allclose(x[halted_back], 1.0 + length - 0.3 * length, atol=1e-6)
    # The same path: pose at equal travelled distance unchanged, far end and end the same.
    assert x.max() == pytest.approx(ref.axial(np.array([ref.t_far_arrive]))[0])
    assert tr.travelled(np.array([tr.duration_s]))[0] == pytest.approx(2 * length)
    probe = np.array([30.0])  # 15 m along the outbound after the stop
    d = tr.travelled(probe)[0]
    tr_ref = np.interp(d, ref.travelled(t), t)
    assert np.allclose(tr.poses(probe), ref.poses(np.array([tr_ref])), atol=1e-6)
    # Smooth enough for the IMU: the deceleration is the leg ramps' own.
    assert np.abs(np.gradient(v, t)).max() < 1.1 * np.pi * speed / (2 * spec.ramp_s)
    for bad in ((2.0, 0.5, 1.0), (0.0, 0.01, 1.0), (0.0, 0.5, 0.0)):
        spec = TrajectorySpec(**{**plain.as_dict(), "stops": (bad,)})
        with pytest.raises(ValueError, match="stop"):
            Trajectory(spec, np.random.default_rng(0))
    # Two halts a metre apart at 1 m/s overlap their 2 s ramps: refused, not driven backwards.
    close = ((0.0, 0.5, 3.0), (0.0, 0.55, 3.0))
    spec = TrajectorySpec(**{**plain.as_dict(), "stops": close})
    with pytest.raises(ValueError, match="closer than one ramp"):
        Trajectory(spec, np.random.default_rng(0))


def test_a_back_up_drives_back_and_forward_again_and_counts_as_travel() -> None:
    length, speed = 20.0, 0.5
    plain = TrajectorySpec(x_start_m=1.0, length_m=length, speed_mps=speed, return_mode="reverse")
    spec = TrajectorySpec(**{**plain.as_dict(), "backups": ((0.0, 0.5, 3.0), (1.0, 0.5, 2.0))})
    tr, ref = (Trajectory(s, np.random.default_rng(0)) for s in (spec, plain))
    # Each back-up is a halt of pi * metres / v seconds (its peak speed the leg's) and a ramp.
    held = np.pi * (3.0 + 2.0) / speed
    assert tr.duration_s == pytest.approx(ref.duration_s + held + 2 * spec.ramp_s)
    t = np.arange(0.0, tr.duration_s, 0.01)
    x, v = tr.axial(t), np.gradient(tr.axial(t), t)
    out, back = t < tr.t_far_arrive, t > tr.t_return_start
    # Out: half-way (11 m) it goes 3 m back towards the start and on again; back: half-way
    # (11 m) it goes 2 m back towards the far end.
    turn_out = int(np.argmin(np.where(out & (t > 30.0), x, np.inf)))
    assert x[turn_out] == pytest.approx(1.0 + 0.5 * length - 3.0, abs=1e-3)
    half_back = int(np.argmax(back & (x < 1.0 + 0.5 * length + 1e-3)))
    assert x[half_back:].max() == pytest.approx(1.0 + 0.5 * length + 2.0, abs=1e-3)
    assert np.abs(v).max() == pytest.approx(speed, rel=1e-3)
    assert x.max() == pytest.approx(1.0 + length) and x[-1] == pytest.approx(1.0)
    # Travel counts the back-ups both ways and never decreases; the far end is where it was.
    d = tr.travelled(t)
    assert np.all(np.diff(d) >= -1e-12)
    assert d[-1] == pytest.approx(2 * length + 2 * (3.0 + 2.0))
    assert tr.t_far_arrive == pytest.approx(ref.t_far_arrive + np.pi * 3.0 / speed + spec.ramp_s)
    # Smooth enough for the IMU: the back-up's acceleration 2 pi^2 m / T^2 is below the ramps'.
    assert np.abs(np.gradient(v, t)).max() < 1.1 * np.pi * speed / (2 * spec.ramp_s)
    # Backing up past the leg's start, or by nothing, is refused by name.
    for bad in ((0.0, 0.2, 5.0), (0.0, 0.5, 0.0), (1.0, 0.3, np.nan)):
        spec = TrajectorySpec(**{**plain.as_dict(), "backups": (bad,)})
        with pytest.raises(ValueError, match="backup"):
            Trajectory(spec, np.random.default_rng(0))


def test_a_faster_return_keeps_the_path_and_drives_it_at_its_own_speed() -> None:
    length = 20.0
    plain = TrajectorySpec(x_start_m=1.0, length_m=length, speed_mps=0.5, return_mode="reverse")
    spec = TrajectorySpec(**{**plain.as_dict(), "return_speed_mps": 1.5, "stops": ((1, 0.5, 3),)})
    tr, ref = (Trajectory(s, np.random.default_rng(0)) for s in (spec, plain))
    # The return's cruise takes a third of the outbound's; the halt its seconds and a ramp.
    assert tr.t_far_arrive == pytest.approx(ref.t_far_arrive)
    back = tr.duration_s - tr.t_return_start - spec.post_s
    assert back == pytest.approx(length / 1.5 + spec.ramp_s + 3.0 + spec.ramp_s)
    t = np.arange(0.0, tr.duration_s, 0.01)
    v = np.abs(np.gradient(tr.axial(t), t))
    assert v[t < tr.t_far_arrive].max() == pytest.approx(0.5, rel=1e-3)
    assert v[t > tr.t_return_start].max() == pytest.approx(1.5, rel=1e-3)
    halted = (t > tr.t_return_start + 1.0) & (t < tr.duration_s - spec.post_s - 1.0) & (v < 1e-9)
    assert np.ptp(t[halted]) == pytest.approx(3.0, abs=0.05)
    assert np.allclose(tr.axial(t[halted]), 1.0 + 0.5 * length, atol=1e-6)
    # The same path: the end back at the start, the pose at equal travelled distance unchanged.
    assert tr.travelled(np.array([tr.duration_s]))[0] == pytest.approx(2 * length)
    d = length + 7.0
    at = np.interp(d, tr.travelled(t), t), np.interp(d, ref.travelled(t), t)
    assert np.allclose(tr.poses(np.array([at[0]])), ref.poses(np.array([at[1]])), atol=1e-5)
    with pytest.raises(ValueError, match="leg 1"):
        Trajectory(
            TrajectorySpec(**{**plain.as_dict(), "return_speed_mps": 0.0}),
            np.random.default_rng(0),
        )


@pytest.mark.parametrize("mode", ["turn", "reverse"])
def test_a_return_in_the_other_lane_heads_along_its_path(mode: str) -> None:
    from decod_rs.sim.trajectory import LANE_CHANGE_M

    plain = TrajectorySpec(x_start_m=1.0, length_m=40.0, speed_mps=1.0, return_mode=mode)
    spec = TrajectorySpec(**{**plain.as_dict(), "return_lateral_m": 2.0})
    tr, ref = (Trajectory(s, np.random.default_rng(0)) for s in (spec, plain))
    t = np.arange(0.0, tr.duration_s, 0.05)
    moved = tr.poses(t)[:, :3, 3] - ref.poses(t)[:, :3, 3]
    back = tr.travelled(t) - 40.0
    # The outbound as before; the return 2 m to the side once the lane change is over.
    assert np.abs(moved[back <= 0.0]).max() < 1e-12
    assert np.allclose(moved[back >= LANE_CHANGE_M], [0.0, 2.0, 0.0], atol=1e-9)
    # While it changes lane the body turns with its path: moving along -x, a path that
    # gains dy/d(back) to the left turns the body by -atan of it.
    changing = (back > 1.0) & (back < LANE_CHANGE_M - 1.0)
    slope = np.gradient(moved[changing, 1], back[changing])
    fwd, fwd_ref = (p.poses(t)[changing][:, :2, 0] for p in (tr, ref))
    turned = np.angle(
        (fwd[:, 0] + 1j * fwd[:, 1]) / (fwd_ref[:, 0] + 1j * fwd_ref[:, 1])
    )  # wrapped to (-pi, pi]
    assert np.abs(slope).max() > 0.2  # pi / 15: 12 deg at the middle of the change
    assert np.allclose(turned, -np.arctan(slope), atol=2e-3)
    with pytest.raises(ValueError, match="return_lateral_m"):
        Simulation("hume", return_lateral_m=0.5)


@pytest.mark.parametrize(
    ("scene", "sensor", "radius"), [("pe", "avia", 6.0), ("shield", "spin16", -90.0)]
)
def test_a_curved_corridor_bends_the_points_and_the_truth_together(
    scene: str, sensor: str, radius: float
) -> None:
    overrides = {"rays_per_scan": 3000} if sensor == "avia" else {"h_res_deg": 2.0}
    kwargs = {"seed": 2, "length_m": 8.0, "sensor": sensor, "sensor_overrides": overrides}
    idx = [20, 60]
    straight = generate(scene, scan_indices=idx, **kwargs)  # type: ignore[arg-type]
    bent = generate(scene, scan_indices=idx, curve_radius_m=radius, **kwargs)  # type: ignore[arg-type]
    assert bent.metadata["axis"]["curve_radius_m"] == radius
    assert straight.metadata["axis"]["curve_radius_m"] is None
    sigma = bent.metadata["sensor"]["range_noise_m"]
    for pts, pose, pose_s in zip(bent.points, bent.gt_poses, straight.gt_poses, strict=True):
        world = pts.astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]
        # Back into the straight world (arc length along the bent centre line, offset from
        # it): the straight scene's surface.
        rel = world[:, :2] - np.array([0.0, radius])
        phi = np.arctan2(rel[:, 0] / radius, -rel[:, 1] / radius)
        lateral = np.sign(radius) * (abs(radius) - np.hypot(rel[:, 0], rel[:, 1]))
        unbent = np.column_stack([radius * phi, lateral, world[:, 2]])
        r = _surface_residual(bent.scene, unbent)
        assert np.mean(r < 4 * sigma + 1e-5) >= 0.995, (scene, np.percentile(r, [50, 99, 100]))
        # In the bent world itself the straight surface is missed by the curve's sagitta.
        assert np.mean(_surface_residual(bent.scene, world) < 4 * sigma + 1e-5) < 0.8
        # The truth follows the arc: at arc length x, heading x / R, on the circle.
        x = pose_s[0, 3]
        assert np.arctan2(pose[1, 0], pose[0, 0]) == pytest.approx(
            np.arctan2(pose_s[1, 0], pose_s[0, 0]) + x / radius, abs=1e-9
        )
        centre = np.array([0.0, radius])
        assert np.hypot(*(pose[:2, 3] - centre)) == pytest.approx(
            abs(radius) - np.sign(radius) * pose_s[1, 3], abs=1e-9
        )

    # Each odometry step errs as on the straight corridor, in the robot's own frame (along
    # its heading, not along world x, which would put the error sideways where the corridor
    # has turned).
    def step_errors(radius_m: float | None) -> np.ndarray:
        sim = Simulation(scene, curve_radius_m=radius_m, drift="legs:-0.05,-0.15", **kwargs)  # type: ignore[arg-type]
        gt, odom = sim.gt_poses, sim.drift.odom_poses
        steps = np.linalg.inv(gt[:-1]) @ gt[1:]
        return np.linalg.inv(steps) @ (np.linalg.inv(odom[:-1]) @ odom[1:])

    errors = step_errors(None)
    assert np.allclose(step_errors(radius), errors, atol=1e-9)
    assert np.abs(errors[:, 0, 3]).max() > 0.001  # the steps do err (5-15 % of 2-3 cm)
    # The inside wall hides what lies round the bend: a forward sensor in a 0.4 m pipe sees
    # it along the straight pipe to the end of the 8 m run, round a 6 m bend only as far as
    # a line of sight stays inside (sqrt(8 R a) = 3.1 m), with a margin for the wall's relief.
    if scene == "pe":
        reach = [
            float(np.linalg.norm(p, axis=1).max()) for p in (straight.points[0], bent.points[0])
        ]
        assert reach[0] > 5.0 and reach[1] < 1.2 * np.sqrt(8 * abs(radius) * 0.2), reach
    with pytest.raises(ValueError, match="tighter than 20 corridor radii"):
        generate(scene, scan_indices=[0], curve_radius_m=radius / 10, **kwargs)  # type: ignore[arg-type]


def test_bad_input_is_named(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="unknown scene"):
        Simulation("sewer")
    with pytest.raises(ValueError, match="drift"):
        Simulation("hume", drift=-1.0, length_m=2.0)
    with pytest.raises(ValueError, match="unknown sensor"):
        Simulation("hume", sensor="hdl32", length_m=2.0)
    with pytest.raises(ValueError, match="return_mode"):
        Simulation("hume", return_mode="fly", length_m=2.0)
    (tmp_path / "log").mkdir()
    with pytest.raises(FileExistsError, match="log"):
        simulate("hume", tmp_path, progress=False, **SHORT)


def test_cli_simulate(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rc = cli_main(
        [
            "simulate",
            "pe",
            "--out",
            str(tmp_path),
            "--length",
            "1.5",
            "--speed",
            "0.5",
            "--rays",
            "200",
            "--drift",
            "low",
            "--quiet",
        ]
    )
    assert rc == 0
    out = capsys.readouterr().out
    assert "endpoint error 0.200 m" in out and "ms per scan" in out
    assert (tmp_path / "joints.json").is_file() and (tmp_path / "log" / "metadata.yaml").is_file()


def test_livox_custom_msg_and_ros1_bag(tmp_path: Path) -> None:
    from rosbags.highlevel import AnyReader

    res = simulate(
        "pe",
        tmp_path,
        seed=1,
        length_m=1.5,
        speed_mps=0.5,
        livox=True,
        ros1=True,
        sensor_overrides={"rays_per_scan": 200},
        progress=False,
    )
    first_cloud = None
    for path in (res.log_dir, res.out_dir / "log.bag"):
        with AnyReader([path]) as reader:
            counts = {c.topic: c.msgcount for c in reader.connections}
            assert counts == {
                "/points": res.n_scans,
                "/odom": res.n_scans,
                "/imu": res.n_imu,
                "/livox/lidar": res.n_scans,
            }
            conns = [c for c in reader.connections if c.topic in ("/points", "/livox/lidar")]
            msgs = {}
            for conn, _, raw in reader.messages(connections=conns):
                msgs.setdefault(conn.topic, reader.deserialize(raw, conn.msgtype))
                if len(msgs) == 2:
                    break
        cloud = np.frombuffer(msgs["/points"].data, dtype="<f4").reshape(-1, 4)
        custom = msgs["/livox/lidar"]
        xyz = np.array([[p.x, p.y, p.z] for p in custom.points], dtype=np.float32)
        # Same points in both messages and in both bag formats.
        assert custom.point_num == cloud.shape[0] == xyz.shape[0]
        assert np.array_equal(xyz, cloud[:, :3])
        assert custom.timebase == msgs["/points"].header.stamp.sec * 10**9 + (
            msgs["/points"].header.stamp.nanosec
        )
        if first_cloud is None:
            first_cloud = cloud
        assert np.array_equal(first_cloud, cloud)


@pytest.mark.parametrize(
    ("scene", "sensor", "curve"),
    [("horseshoe", "avia", None), ("shield", "spin16", None), ("shield", "spin16", -90.0)],
)
def test_a_swept_scan_lies_on_the_surface_from_each_points_own_pose(
    scene: str, sensor: str, curve: float | None
) -> None:
    """``sweep``: every ray cast from the pose at its own time (one call, one origin per
    ray); each point, put back through the pose at its time (in a curving corridor the bent
    one, and then unbent), lies on the surface. Checked in the turn, where the heading
    changes within a sweep (a rosette's rays one by one, a spinning sensor's columns)."""
    sim = Simulation(
        scene,
        seed=2,
        length_m=8.0,
        sensor=sensor,
        return_mode="turn",
        sweep=True,
        curve_radius_m=curve,
    )
    poses = sim.straight_poses
    yaw = np.unwrap(np.arctan2(poses[:, 1, 0], poses[:, 0, 0]))
    k = int(np.argmax(np.abs(np.diff(yaw))))
    assert abs(yaw[k + 1] - yaw[k]) > np.deg2rad(2.0)  # turning within the sweep
    pts, _, t_ns = sim.scan_with_times(k)
    assert t_ns is not None and t_ns.size == len(pts) and t_ns.max() > 0.09e9
    at = poses_between(poses[k], poses[k + 1], t_ns.astype(np.float64) / 1e8)
    stamp_pose = poses[k]
    if sim.bend is not None:  # the bent poses at the points' times, and back
        at, stamp_pose = sim.bend.poses(at), sim.gt_poses[k]
    rot, origin = at[:, :3, :3], at[:, :3, 3]
    world = np.einsum("nij,nj->ni", rot, pts.astype(np.float64)) + origin
    stamp = pts.astype(np.float64) @ stamp_pose[:3, :3].T + stamp_pose[:3, 3]
    if sim.bend is not None:
        world, stamp = sim.bend.unbend(world), sim.bend.unbend(stamp)
    sigma = sim.range_noise_m
    r = _surface_residual(sim.scene, world)
    assert np.mean(r < 4 * sigma + 1e-5) >= 0.995, np.percentile(r, [50, 99, 100])
    # The check can fail: every point through the stamp's pose, as a consumer that does not
    # deskew takes them, is off the surface by the turn within the sweep.
    assert np.mean(_surface_residual(sim.scene, stamp) < 4 * sigma + 1e-5) < 0.9


def test_rays_from_their_own_origins_hit_as_each_from_its_origin_alone() -> None:
    """``cast`` with one origin per ray gives, ray for ray, what a cast from that ray's
    origin alone gives (walls, floor, caps and arches)."""
    sc = build_scene("horseshoe", 3, 12.0)
    rng = np.random.default_rng(5)
    origins = np.column_stack(
        [rng.uniform(2.0, 10.0, 60), rng.uniform(-1.0, 1.0, 60), rng.uniform(-0.5, 1.0, 60)]
    )
    dirs = rng.normal(size=(60, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    together = cast(sc, origins, dirs)
    alone = [cast(sc, o, d[None, :]) for o, d in zip(origins, dirs, strict=True)]
    assert np.allclose(together.points, np.concatenate([h.points for h in alone]), atol=1e-9)
    assert np.array_equal(together.kind, np.concatenate([h.kind for h in alone]))
    assert len(set(together.kind.tolist())) >= 3  # several surfaces among the hits
    with pytest.raises(ValueError, match="origin"):
        cast(sc, origins[:5], dirs)


@pytest.mark.parametrize("scene", ["hume", "pe", "shield", "horseshoe"])
def test_surface_lookups_do_not_depend_on_array_shape(scene: str) -> None:
    sc = build_scene(scene, 2, 20.0)
    rng = np.random.default_rng(0)
    # Points concentrated around joints so the per-joint patches are exercised.
    x = rng.choice(sc.joints_x_m, (40, 30)) + rng.normal(0.0, 0.03, (40, 30))
    th = rng.uniform(-np.pi, np.pi, (40, 30))
    grid = sc.wall_dr(x, th)
    flat = sc.wall_dr(x.ravel(), th.ravel())
    assert grid.shape == (40, 30)
    assert np.array_equal(grid.ravel(), flat)
    assert np.any(grid != 0.0)


@pytest.mark.parametrize("mode", ["reverse", "turn"])
def test_uneven_leg_profile_scales_each_leg(mode: str) -> None:
    length = 60.0
    spec = TrajectorySpec(x_start_m=0.5, length_m=length, speed_mps=0.8, return_mode=mode)
    traj = Trajectory(spec, np.random.default_rng(0))
    t = np.arange(0.0, traj.duration_s, 0.1)
    gt = traj.poses(t)
    k_far = round(traj.t_far_arrive / 0.1)
    dr = odometry_for_profile(
        gt, traj.travelled(t), "legs:-0.05,-0.15", np.random.default_rng(3), split_index=k_far
    )
    err = dr.odom_poses[:, :3, 3] - gt[:, :3, 3]
    # Outbound: the odometry reports 95 % of the distance driven, so it is 5 % short at the far
    # end (the 1 cm/sqrt(m) axial walk is ~8 cm = 0.13 % here; 0.5 % is ~4 sigma).
    out_m = gt[k_far, 0, 3] - gt[0, 0, 3]
    assert out_m == pytest.approx(length, abs=0.1)
    assert err[k_far, 0] / out_m == pytest.approx(-0.05, abs=0.005)
    assert dr.turnaround_axial_m == pytest.approx(err[k_far, 0])
    # Return: 85 % of the way back, so the end is (-0.05 + 0.15) L = +6 m beyond the start
    # (walk ~11 cm at 120 m travelled).
    assert err[-1, 0] == pytest.approx(0.10 * length, abs=0.5)
    assert dr.endpoint_axial_m == pytest.approx(err[-1, 0])
    # Small attitude walks: lateral error stays centimetres.
    assert np.max(np.hypot(err[:, 1], err[:, 2])) < 0.1
    # No drift before moving; the default split (farthest scan) gives the same outbound error.
    assert np.allclose(dr.odom_poses[t < spec.pre_s], gt[t < spec.pre_s])
    again = odometry_for_profile(
        gt, traj.travelled(t), "legs:-0.05,-0.15", np.random.default_rng(3)
    )
    assert abs(again.odom_poses[k_far, 0, 3] - dr.odom_poses[k_far, 0, 3]) < 0.01


def test_slip_profile_changes_the_scale_along_the_way() -> None:
    spec = TrajectorySpec(x_start_m=0.5, length_m=60.0, speed_mps=0.8, return_mode="reverse")
    traj = Trajectory(spec, np.random.default_rng(0))
    t = np.arange(0.0, traj.duration_s, 0.1)
    gt, d = traj.poses(t), traj.travelled(t)
    dr = odometry_for_profile(gt, d, "slip:-0.15,-0.01", np.random.default_rng(3))
    assert dr.model == "slip"
    # The local scale: odometry displacement over true displacement, per 2 m of travel (the
    # axial walk, 1 cm/sqrt(m), is ~1 % of 2 m: 0.03 of slack on either side).
    step = np.diff(gt[:, 0, 3])
    moving = np.abs(step) > 1e-6
    odo = np.diff(dr.odom_poses[:, 0, 3])
    bins = np.floor(d[1:] / 2.0).astype(int)
    ratios = np.array(
        [
            odo[(bins == b) & moving].sum() / step[(bins == b) & moving].sum()
            for b in np.unique(bins[moving])
            if np.abs(step[(bins == b) & moving].sum()) > 1.5
        ]
    )
    assert ratios.size > 50
    assert np.all(ratios > 1 - 0.15 - 0.03) and np.all(ratios < 1 - 0.01 + 0.03)
    # Sections, not one scale: over 120 m of 3-15 m sections the stretches differ by more
    # than a third of the range somewhere on each leg.
    half = ratios.size // 2
    for leg in (ratios[:half], ratios[half:]):
        assert leg.max() - leg.min() > 0.05
    # Seeded: the same generator gives the same odometry; the turnaround's error is read.
    again = odometry_for_profile(gt, d, "slip:-0.15,-0.01", np.random.default_rng(3))
    assert np.array_equal(again.odom_poses, dr.odom_poses)
    k_far = int(np.argmax(gt[:, 0, 3]))
    assert dr.turnaround_axial_m == pytest.approx(dr.odom_poses[k_far, 0, 3] - gt[k_far, 0, 3])


def test_profiles_parse_and_feed_the_simulator() -> None:
    assert parse_profile("legs:-0.05, -0.15") == LegProfile(-0.05, -0.15)
    assert parse_profile("medium") == 1.7 and parse_profile(2.5) == 2.5
    assert parse_profile(" slip:-0.15,-0.01") == SlipProfile(-0.15, -0.01)
    for bad in ("legs:-0.05", "legs:a,b", "legs:-1.5,0", "fast", "slip:-0.1", "slip:0.1,-0.1"):
        with pytest.raises(ValueError, match=r"legs:|slip:"):
            parse_profile(bad)
    sim = Simulation("pe", seed=1, length_m=10.0, speed_mps=1.0, drift="legs:-0.05,-0.15")
    meta = sim.metadata()["drift"]
    assert meta["profile"] == "legs:-0.05,-0.15" and meta["requested_endpoint_m"] is None
    assert meta["turnaround_axial_m"] == pytest.approx(-0.5, abs=0.06)
    assert meta["endpoint_axial_m"] == pytest.approx(1.0, abs=0.1)
    # The endpoint model through the same entry point is the original one, bit for bit.
    gt, d = sim.gt_poses, sim.traj.travelled(sim.t_s)
    a = odometry_for_profile(gt, d, "1.7", np.random.default_rng(9))
    b = drift_odometry(gt, d, 1.7, np.random.default_rng(9))
    assert np.array_equal(a.odom_poses, b.odom_poses)


def test_scene_overrides_change_the_geometry_consistently() -> None:
    with pytest.raises(ValueError, match=r"'radius'.*valid: .*radius_m"):
        scene_params("hume", {"radius": 0.5})
    with pytest.raises(ValueError, match="segment_length_m"):
        scene_params("pe", {"segment_length_m": 0.0})
    assert scene_params("pe", {"segment_length_m": 3})["ribs_per_segment"] == 86  # 35 mm ribs
    # A 1.0 m hume pipe with 4 m joints: the sensor mount scales with the radius.
    data = generate(
        "hume",
        seed=1,
        length_m=6.0,
        speed_mps=1.0,
        sensor_overrides={"rays_per_scan": 2000},
        scene_overrides={"radius_m": 0.5, "segment_length_m": 4.0},
        scan_indices=[0, 40],
    )
    assert data.scene.radius_m == 0.5 and data.metadata["axis"]["radius_m"] == 0.5
    assert data.metadata["scene_params"]["segment_length_m"] == 4.0
    assert data.metadata["scene_overrides"] == {"radius_m": 0.5, "segment_length_m": 4.0}
    assert np.allclose(np.diff(data.joints_x_m), 4.0, atol=0.02)
    assert data.metadata["trajectory"]["z0_m"] == pytest.approx(-0.03 * 0.5 / 0.3)
    for pts, pose in zip(data.points, data.gt_poses, strict=True):
        world = pts.astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]
        assert np.mean(_surface_residual(data.scene, world) < 0.01) > 0.99
    # A 9 m wide shield tunnel: the floor moves with the radius, the sensor keeps 1.6 m above it.
    sim = Simulation("shield", seed=0, length_m=6.0, scene_overrides={"radius_m": 4.5})
    assert sim.scene.floor_z_m == pytest.approx(-3.0)
    assert sim.traj_spec.z0_m == pytest.approx(-3.0 + 1.6)


def test_water_hides_the_bottom_of_a_pipe_and_seldom_returns() -> None:
    from decod_rs.sim.pipes import WATER_RETURN_FRACTION

    # A 0.4 m pe pipe 30 % full (a sewer's flow): no point below the water's surface, and of
    # the rays that meet the surface only WATER_RETURN_FRACTION return (calm water mirrors
    # the beam away). Measured against the same run in the dry pipe.
    def run(depth: float) -> tuple[np.ndarray, float]:
        data = generate(
            "pe",
            seed=3,
            length_m=2.0,
            sensor="spin16",
            sensor_overrides={"h_res_deg": 1.0},
            scene_overrides={"water_depth_m": depth} if depth else None,
            scan_indices=[10, 30, 50],
        )
        world = [
            p.astype(np.float64) @ g[:3, :3].T + g[:3, 3]
            for p, g in zip(data.points, data.gt_poses, strict=True)
        ]
        return np.concatenate(world), data.metadata["axis"]["floor_z_m"]

    dry, no_floor = run(0.0)
    wet, level = run(0.12)
    assert no_floor is None and level == pytest.approx(-0.2 + 0.12)
    sigma = 4 * 0.0015
    assert np.count_nonzero(wet[:, 2] < level - sigma) == 0
    below = np.count_nonzero(dry[:, 2] < level)  # wall the water now covers (or fewer rays)
    surface = np.count_nonzero(np.abs(wet[:, 2] - level) <= sigma)
    assert 0 < surface < 3 * WATER_RETURN_FRACTION * below, (surface, below)
    # Above the water the wall is seen as in the dry pipe (+-10 %: dropouts are random).
    above = (dry[:, 2] > level + 0.02).sum(), (wet[:, 2] > level + 0.02).sum()
    assert above[1] == pytest.approx(above[0], rel=0.1)
    # A pipe at least half full, or a sensor under the water, is refused by name.
    with pytest.raises(ValueError, match="water_depth_m"):
        scene_params("pe", {"water_depth_m": 0.2})
    with pytest.raises(ValueError, match="under the water"):
        Simulation("hume", seed=0, length_m=2.0, scene_overrides={"water_depth_m": 0.28})


def test_sensor_height_puts_the_sensor_above_the_invert_or_the_floor() -> None:
    # A crawler low in a 1.2 m pipe (0.25 m above the invert) and a small robot in the 6 m
    # shield (0.5 m above its floor, 2 m below the centre).
    pipe = Simulation("hume", length_m=2.0, scene_overrides={"radius_m": 0.6}, sensor_height_m=0.25)
    assert pipe.traj_spec.z0_m == pytest.approx(-0.6 + 0.25)
    tunnel = Simulation("shield", length_m=6.0, sensor_height_m=0.5)
    assert tunnel.traj_spec.z0_m == pytest.approx(-2.0 + 0.5)
    assert Simulation("shield", length_m=6.0).traj_spec.z0_m == pytest.approx(-0.4)
    # The points are still on the corridor's surface, seen from there.
    data = generate(
        "hume",
        seed=1,
        length_m=2.0,
        sensor_overrides={"rays_per_scan": 2000},
        scene_overrides={"radius_m": 0.6},
        sensor_height_m=0.25,
        scan_indices=[5],
    )
    world = data.points[0].astype(np.float64) @ data.gt_poses[0][:3, :3].T + data.gt_poses[0][:3, 3]
    assert data.gt_poses[0][2, 3] == pytest.approx(-0.35, abs=0.02)
    assert np.mean(_surface_residual(data.scene, world) < 0.01) > 0.99
    # Outside the section, or at its wall, is refused by name.
    for bad in (0.0, 1.2, float("nan")):
        with pytest.raises(ValueError, match="sensor_height_m"):
            Simulation("hume", length_m=2.0, scene_overrides={"radius_m": 0.6}, sensor_height_m=bad)


def test_cli_scene_param(tmp_path: Path) -> None:
    args = ["simulate", "pe", "--out", str(tmp_path), "--length", "1.5", "--speed", "0.5"]
    args += ["--rays", "200", "--quiet", "--scene-param", "radius_m=0.3"]
    assert cli_main([*args, "--scene-param", "segment_length_m=3"]) == 0
    doc = json.loads((tmp_path / "joints.json").read_text())
    assert doc["scene_params"]["radius_m"] == 0.3 and doc["scene_params"]["segment_length_m"] == 3
    assert cli_main([*args, "--scene-param", "diameter=1", "--force"]) == 2


def test_cli_curve_radius(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    args = ["simulate", "pe", "--out", str(tmp_path), "--length", "1.5", "--speed", "0.5"]
    args += ["--rays", "200", "--quiet"]
    assert cli_main([*args, "--curve-radius", "-12"]) == 0
    doc = json.loads((tmp_path / "joints.json").read_text())
    assert (
        doc["axis"]["curve_radius_m"] == -12.0
        and "curves with radius -12 m" in doc["frames"]["world"]
    )
    assert "curves with radius -12 m" in capsys.readouterr().out
    # A 0.2 m pipe bent on 3 m is no gentle curve: refused, naming the parameter.
    assert cli_main([*args, "--curve-radius", "3", "--force"]) == 2
    assert "curve radius 3 m is tighter" in capsys.readouterr().err


def test_cli_backup(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    args = ["simulate", "pe", "--out", str(tmp_path), "--length", "6", "--speed", "0.5"]
    args += ["--rays", "100", "--drift", "none", "--quiet"]
    assert cli_main([*args, "--backup", "out:0.5:1"]) == 0
    assert "backup         1 m back and on, 50 % of the way out" in capsys.readouterr().out
    doc = json.loads((tmp_path / "joints.json").read_text())
    assert doc["trajectory"]["backups"] == [[0.0, 0.5, 1.0]]
    _, poses = read_tum(tmp_path / "gt.tum")
    x = poses[:, 0, 3] - poses[0, 0, 3]
    # Half-way out (3 m) it drives 1 m back before going on to the far end.
    first, far = int(np.argmax(x > 2.99)), int(np.argmax(x))
    assert np.min(x[first:far]) == pytest.approx(2.0, abs=0.02) and x[far] == pytest.approx(6.0)
    capsys.readouterr()
    with pytest.raises(SystemExit) as refused:
        cli_main([*args, "--backup", "out:0.5", "--force"])
    assert refused.value.code == 2 and "LEG:FRACTION:METRES" in capsys.readouterr().err
    assert cli_main([*args, "--backup", "out:0.3:2.5", "--force"]) == 2
    assert "would pass its start" in capsys.readouterr().err


def test_cli_standstill(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    args = ["simulate", "pe", "--out", str(tmp_path), "--length", "3", "--speed", "0.5"]
    args += ["--rays", "100", "--drift", "none", "--quiet"]
    assert cli_main([*args, "--standstill", "6,4"]) == 0
    doc = json.loads((tmp_path / "joints.json").read_text())
    assert (doc["trajectory"]["pre_s"], doc["trajectory"]["post_s"]) == (6.0, 4.0)
    stamps, poses = read_tum(tmp_path / "gt.tum")
    t, x = stamps - stamps[0], poses[:, 0, 3] - poses[0, 0, 3]
    # Standing for the 6 s asked before moving off and the 4 s after coming back.
    assert np.all(x[t < 6.0] == 0.0) and abs(x[t > 6.05][0]) > 0.0
    still_end = t[np.abs(x - x[-1]) < 1e-12]
    assert t[-1] - still_end[np.argmax(np.diff(still_end, prepend=-1.0) > 0.15)] >= 3.9
    capsys.readouterr()
    with pytest.raises(SystemExit) as refused:
        cli_main([*args, "--standstill", "60", "--force"])
    assert refused.value.code == 2 and "START,END" in capsys.readouterr().err
    assert cli_main([*args, "--standstill=-1,0", "--force"]) == 2
    assert "standstill_s" in capsys.readouterr().err


def test_cli_stop(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    args = ["simulate", "pe", "--out", str(tmp_path), "--length", "4", "--speed", "0.5"]
    args += ["--rays", "100", "--drift", "none", "--quiet"]
    assert cli_main([*args, "--stop", "out:0.5:3"]) == 0
    assert "stop           3 s standing, 50 % of the way out" in capsys.readouterr().out
    doc = json.loads((tmp_path / "joints.json").read_text())
    assert doc["trajectory"]["stops"] == [[0.0, 0.5, 3.0]]
    stamps, poses = read_tum(tmp_path / "gt.tum")
    x = poses[:, 0, 3]
    # Standing still (scan to scan) for the 3 s asked, half-way along the outbound leg.
    still = np.flatnonzero((np.abs(np.diff(x)) < 1e-9) & (np.abs(x[1:] - x[0] - 2.0) < 0.01))
    assert 29 <= still.size <= 31 and np.ptp(stamps[still]) == pytest.approx(2.9, abs=0.11)
    capsys.readouterr()
    with pytest.raises(SystemExit) as refused:
        cli_main([*args, "--stop", "halfway:0.5:3", "--force"])
    assert refused.value.code == 2 and "LEG:FRACTION:SECONDS" in capsys.readouterr().err
    # A stop on the leg's own ramp is refused by name, the earlier log kept.
    assert cli_main([*args, "--stop", "back:0.01:3", "--force"]) == 2
    assert "cruise" in capsys.readouterr().err
    assert (tmp_path / "log" / "metadata.yaml").is_file()
