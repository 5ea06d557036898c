"""Public entry points: :func:`generate` (in memory, for tests) and :func:`simulate` (a
rosbag2/MCAP log + ``gt.tum`` + ``odom.tum`` + ``joints.json`` on disk)."""

from __future__ import annotations

import contextlib
import math
import shutil
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from decod_rs.progress import Progress
from decod_rs.sim.bend import Bend, check_bend_radius
from decod_rs.sim.drift import DriftResult, odometry_for_profile, parse_profile
from decod_rs.sim.fields import F64
from decod_rs.sim.imu import ImuSamples, ImuSpec, simulate_imu
from decod_rs.sim.lio import KissOdometry
from decod_rs.sim.livox import Ros1Writer
from decod_rs.sim.raycast import cast
from decod_rs.sim.scenes import SceneDefaults, build_scene, defaults_for, scene_params
from decod_rs.sim.sensors import SCAN_PERIOD_S, SensorSpec, measure, ray_directions, sensor_spec
from decod_rs.sim.surface import Scene
from decod_rs.sim.sweep import swept_points
from decod_rs.sim.trajectory import Trajectory, TrajectorySpec, so3_log
from decod_rs.sim.writer import (
    TOPIC_IMU,
    TOPIC_ODOM,
    TOPIC_POINTS,
    LogWriter,
    stamp_text,
    write_json,
    write_tum,
)

# Stamps start here (2023-11-14T22:13:20Z), whole seconds, so TUM stamps print exactly.
T0_NS = 1_700_000_000 * 10**9
SCAN_PERIOD_NS = round(SCAN_PERIOD_S * 1e9)
LOG_DIRNAME = "log"
ROS1_BAG_NAME = "log.bag"
JOINTS_FORMAT_VERSION = 1
DRIFT_MODELS = {
    "endpoint": "axial scale error + random walk + creep to the endpoint; "
    "yaw/pitch random-walk bridges; functions of travelled distance",
    "legs": "per-leg scale errors (outbound, return) split at the far end + 1 cm/sqrt(m) "
    "axial and small yaw/pitch random walks; functions of travelled distance",
    "slip": "scale errors of sections of 3-15 m (uniform in a range, blended over 0.5 m) + the "
    "legs model's random walks; functions of travelled distance",
}


class Simulation:
    """One fully specified run: scene, sensor, trajectory, drift and IMU, all seeded.

    Scans are generated on demand (:meth:`scan`), each from its own seeded generator, so the
    k-th scan does not depend on which scans were generated before it.
    """

    def __init__(
        self,
        scene: str,
        *,
        seed: int = 0,
        length_m: float | None = None,
        sensor: str | None = None,
        return_mode: str | None = None,
        drift: float | str = "medium",
        distinctiveness: float | None = None,
        identical_joints: bool = False,
        speed_mps: float | None = None,
        return_speed_mps: float | None = None,
        return_lateral_m: float = 0.0,
        sensor_overrides: dict[str, Any] | None = None,
        imu: ImuSpec | None = None,
        scene_overrides: dict[str, Any] | None = None,
        world_seed: int | None = None,
        mount_deg: tuple[float, float] = (0.0, 0.0),
        stops: Sequence[tuple[float, float, float]] = (),
        curve_radius_m: float | None = None,
        sensor_height_m: float | None = None,
        backups: Sequence[tuple[float, float, float]] = (),
        standstill_s: tuple[float, float] | None = None,
        sweep: bool = False,
    ) -> None:
        self.scene_overrides = dict(scene_overrides or {})
        #: Each point measured at its own time within the scan (:mod:`decod_rs.sim.sweep`).
        self.sweep = bool(sweep)
        # The world (scene geometry) may come from another seed than the run (noise, drift,
        # trajectory wobble): two inspections of one pipe (issue 12).
        self.world_seed = int(seed if world_seed is None else world_seed)
        params = scene_params(scene, self.scene_overrides)
        defaults = _at_height(defaults_for(scene, params), params, sensor_height_m)
        self.seed = int(seed)
        self.distinctiveness = 1.0 if distinctiveness is None else float(distinctiveness)
        self.identical_joints = bool(identical_joints)
        length = defaults.length_m if length_m is None else float(length_m)
        speed = defaults.speed_mps if speed_mps is None else float(speed_mps)
        _check_lane(return_lateral_m, params)
        self.traj_spec = _trajectory_spec(
            defaults,
            length,
            speed,
            return_mode,
            mount_deg,
            stops,
            return_speed_mps,
            float(return_lateral_m),
            backups,
            standstill_s,
        )
        self.traj = Trajectory(self.traj_spec, np.random.default_rng([self.seed, 2]))
        x_max = defaults.x_start_m + length + defaults.beyond_m
        self.scene: Scene = build_scene(
            scene,
            self.world_seed,
            x_max,
            self.distinctiveness,
            self.identical_joints,
            self.scene_overrides,
        )
        if self.scene.floor_z_m is not None:
            # A pipe's water (a tunnel's floor is always far below its sensor).
            lowest = defaults.z0_m - 2.0 * defaults.vertical_m
            if lowest <= self.scene.floor_z_m:
                raise ValueError(
                    f"the sensor ({defaults.z0_m:+.3f} m, wobbling down to {lowest:+.3f} m) "
                    f"would be under the water at {self.scene.floor_z_m:+.3f} m: lower "
                    "water_depth_m"
                )
        self.sensor: SensorSpec = sensor_spec(sensor or defaults.sensor, **(sensor_overrides or {}))
        self.range_noise_m = (
            self.sensor.range_noise_m
            if self.sensor.range_noise_m is not None
            else self.scene.range_noise_m
        )
        n_scans = int(np.floor(self.traj.duration_s / SCAN_PERIOD_S)) + 1
        self.stamps_ns = T0_NS + SCAN_PERIOD_NS * np.arange(n_scans, dtype=np.int64)
        self.t_s: F64 = np.arange(n_scans, dtype=np.float64) * SCAN_PERIOD_S
        # Scans are cast in the straight world; the ground truth, the odometry and the
        # points written are in the bent one (:mod:`decod_rs.sim.bend`).
        radius = check_bend_radius(curve_radius_m, self.scene.radius_m)
        self.bend: Bend | None = None if radius is None else Bend(radius)
        self.straight_poses = self.traj.poses(self.t_s)
        self.gt_poses = (
            self.straight_poses if self.bend is None else self.bend.poses(self.straight_poses)
        )
        parsed = parse_profile(drift)
        self.drift_profile = str(drift) if isinstance(parsed, float) else parsed.text
        self.drift_request_m: float | None = parsed if isinstance(parsed, float) else None
        # The odometry errs in the corridor's own frame (along its axis where the robot is):
        # drifted in the straight world, its error carried into the bent one.
        drifted = odometry_for_profile(
            self.straight_poses,
            self.traj.travelled(self.t_s),
            drift,
            np.random.default_rng([self.seed, 3]),
            split_index=self.scan_index_at(self.traj.t_far_arrive),
        )
        self.drift: DriftResult = (
            drifted
            if self.bend is None
            else replace(
                drifted, odom_poses=self.bend.carry(self.straight_poses, drifted.odom_poses)
            )
        )
        self.imu_spec = imu or ImuSpec()
        self.imu: ImuSamples = simulate_imu(
            self.traj, self.imu_spec, np.random.default_rng([self.seed, 4])
        )
        refl = np.zeros(8)
        for k, v in self.scene.reflectivity.items():
            refl[k] = v
        self._reflectivity = refl
        frac = np.ones(8)
        for k, v in self.scene.return_fraction.items():
            frac[k] = v
        self._return_fraction = frac

    @property
    def n_scans(self) -> int:
        return int(self.stamps_ns.size)

    def scan(self, k: int) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """Scan ``k``: points ``(M, 3)`` float32 in the body frame and intensities ``(M,)``."""
        pts, inten, _ = self.scan_with_times(k)
        return pts, inten

    def scan_with_times(
        self, k: int
    ) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.uint32] | None]:
        """Scan ``k`` as :meth:`scan`, and with ``sweep`` each point's time since the scan
        stamp (ns; its frame is the body's at that time, :mod:`decod_rs.sim.sweep`)."""
        dirs_body = ray_directions(self.sensor, k)
        rng = np.random.default_rng([self.seed, 5, k])

        def measure_from(
            origin: F64, dirs_world: F64
        ) -> tuple[F64, NDArray[np.float32], NDArray[np.bool_]]:
            hits = cast(self.scene, origin, dirs_world)
            return measure(
                self.sensor,
                hits,
                origin,
                self._reflectivity,
                self.range_noise_m,
                rng,
                self._return_fraction,
            )

        if self.sweep:
            curve = (
                None
                if self.bend is None
                else (self.bend, self.scene.radius_m, self.scene.floor_z_m)
            )
            return swept_points(self.straight_poses, k, dirs_body, self.sensor, measure_from, curve)
        pose = self.straight_poses[k]
        rot, origin = pose[:3, :3], pose[:3, 3]
        pts_w, inten, _ = measure_from(origin, dirs_body @ rot.T)
        if self.bend is not None:
            pts_w = self.bend.points(pts_w)
            rot, origin = self.gt_poses[k, :3, :3], self.gt_poses[k, :3, 3]
            seen = self.bend.in_sight(origin, pts_w, self.scene.radius_m, self.scene.floor_z_m)
            pts_w, inten = pts_w[seen], inten[seen]
        pts_b = (pts_w - origin) @ rot
        return pts_b.astype(np.float32), inten, None

    def odom_twist(self) -> tuple[F64, F64]:
        """Body-frame linear and angular velocity of the odometry at every scan (finite
        differences of the odometry poses; zero at the last scan)."""
        p = self.drift.odom_poses
        lin = np.zeros((self.n_scans, 3))
        ang = np.zeros((self.n_scans, 3))
        if self.n_scans > 1:
            dp = (p[1:, :3, 3] - p[:-1, :3, 3]) / SCAN_PERIOD_S
            lin[:-1] = np.einsum("nji,nj->ni", p[:-1, :3, :3], dp)
            rel = np.einsum("nji,njk->nik", p[:-1, :3, :3], p[1:, :3, :3])
            ang[:-1] = so3_log(rel) / SCAN_PERIOD_S
        return lin, ang

    def scan_index_at(self, t_s: float) -> int:
        return int(min(max(round(t_s / SCAN_PERIOD_S), 0), self.n_scans - 1))

    def metadata(self) -> dict[str, Any]:
        """The ``joints.json`` content (see the module docs of :mod:`decod_rs.sim`)."""
        sc = self.scene
        tr = self.traj
        k_far = self.scan_index_at(tr.t_far_arrive)
        k_ret = self.scan_index_at(tr.t_return_start)
        dr = self.drift
        return {
            "format": "decod-sim",
            "version": JOINTS_FORMAT_VERSION,
            "scene": sc.name,
            "seed": self.seed,
            "world_seed": self.world_seed,
            "distinctiveness": self.distinctiveness,
            "identical_joints": self.identical_joints,
            "sweep": self.sweep,
            "axis": {
                "frame": "world",
                "origin_m": [0.0, 0.0, 0.0],
                "direction": [1.0, 0.0, 0.0],
                "centre_line_y_m": 0.0,
                "centre_line_z_m": 0.0,
                "radius_m": sc.radius_m,
                "curve_radius_m": None if self.bend is None else self.bend.radius_m,
                "floor_z_m": sc.floor_z_m,
                "x_min_m": sc.x_min_m,
                "x_max_m": sc.x_max_m,
            },
            "joints_x_m": [round(float(x), 6) for x in sc.joints_x_m],
            "n_joints": int(sc.joints_x_m.size),
            "scene_params": sc.params,
            "sensor": {**self.sensor.as_dict(), "range_noise_m": self.range_noise_m},
            "trajectory": self.traj_spec.as_dict(),
            "scene_overrides": self.scene_overrides,
            "drift": {
                "profile": self.drift_profile,
                "requested_endpoint_m": self.drift_request_m,
                "endpoint_error_m": dr.endpoint_error_m,
                "endpoint_axial_m": dr.endpoint_axial_m,
                "endpoint_lateral_m": dr.endpoint_lateral_m,
                "max_axial_m": dr.max_axial_m,
                "yaw_end_rad": dr.yaw_end_rad,
                "pitch_end_rad": dr.pitch_end_rad,
                "turnaround_axial_m": dr.turnaround_axial_m,
                "model": DRIFT_MODELS[dr.model],
            },
            "odometry": {"name": "drift-model", "endpoint_error_m": dr.endpoint_error_m},
            "imu": self.imu_spec.as_dict(),
            "time_split": {
                "start_stamp": stamp_text(int(self.stamps_ns[0])),
                "far_end_arrival_stamp": stamp_text(T0_NS + round(tr.t_far_arrive * 1e9)),
                "return_start_stamp": stamp_text(T0_NS + round(tr.t_return_start * 1e9)),
                "end_stamp": stamp_text(int(self.stamps_ns[-1])),
                "outbound_scans": [0, k_far],
                "return_scans": [k_ret, self.n_scans - 1],
                "duration_s": float(self.t_s[-1]),
            },
            "frames": {
                "world": "corridor axis +x from x = 0, z up; gt.tum is world_from_body"
                + (
                    ""
                    if self.bend is None
                    else f"; the axis curves with radius {self.bend.radius_m:g} m (positive: "
                    "to the left) and joints_x_m are arc lengths along it"
                ),
                "body": "sensor frame, x forward, y left, z up (FLU)",
                "odom": "drifting odometry frame, equal to world at the first stamp",
            },
            "topics": {
                TOPIC_POINTS: "sensor_msgs/msg/PointCloud2 (x y z intensity float32, body)",
                TOPIC_ODOM: "nav_msgs/msg/Odometry (odom -> body, drifting)",
                TOPIC_IMU: "sensor_msgs/msg/Imu (body, specific force, 100 Hz)",
            },
        }


@dataclass
class SimData:
    """A run in memory. ``stamps_ns (N,)``; ``points``: N arrays ``(M_k, 3)`` float32 (body
    frame); ``intensities``: N arrays ``(M_k,)``; ``gt_poses``/``odom_poses`` ``(N, 4, 4)``
    (``world_from_body`` / ``odom_from_body``); ``imu_stamps_ns (M,)``, ``imu_gyro``/
    ``imu_accel`` ``(M, 3)``; ``joints_x_m (J,)``; ``metadata`` = the joints.json content."""

    stamps_ns: NDArray[np.int64]
    points: list[NDArray[np.float32]]
    intensities: list[NDArray[np.float32]]
    gt_poses: F64
    odom_poses: F64
    imu_stamps_ns: NDArray[np.int64]
    imu_gyro: F64
    imu_accel: F64
    joints_x_m: F64
    scene: Scene
    metadata: dict[str, Any] = field(default_factory=dict)


def generate(
    scene: str,
    *,
    seed: int = 0,
    length_m: float | None = None,
    sensor: str | None = None,
    return_mode: str | None = None,
    drift: float | str = "medium",
    distinctiveness: float | None = None,
    identical_joints: bool = False,
    speed_mps: float | None = None,
    return_speed_mps: float | None = None,
    return_lateral_m: float = 0.0,
    sensor_overrides: dict[str, Any] | None = None,
    scan_indices: list[int] | None = None,
    scene_overrides: dict[str, Any] | None = None,
    world_seed: int | None = None,
    mount_deg: tuple[float, float] = (0.0, 0.0),
    curve_radius_m: float | None = None,
    sensor_height_m: float | None = None,
) -> SimData:
    """Simulate a run in memory (every scan, or only ``scan_indices``; the poses, IMU and
    drift always cover the whole run and ``stamps_ns`` the selected scans). Arguments as
    :func:`simulate`."""
    sim = Simulation(
        scene,
        seed=seed,
        length_m=length_m,
        sensor=sensor,
        return_mode=return_mode,
        drift=drift,
        distinctiveness=distinctiveness,
        identical_joints=identical_joints,
        speed_mps=speed_mps,
        return_speed_mps=return_speed_mps,
        return_lateral_m=return_lateral_m,
        sensor_overrides=sensor_overrides,
        scene_overrides=scene_overrides,
        world_seed=world_seed,
        mount_deg=mount_deg,
        curve_radius_m=curve_radius_m,
        sensor_height_m=sensor_height_m,
    )
    idx = list(range(sim.n_scans)) if scan_indices is None else list(scan_indices)
    scans = [sim.scan(k) for k in idx]
    return SimData(
        stamps_ns=sim.stamps_ns[idx],
        points=[p for p, _ in scans],
        intensities=[i for _, i in scans],
        gt_poses=sim.gt_poses[idx],
        odom_poses=sim.drift.odom_poses[idx],
        imu_stamps_ns=T0_NS + np.round(sim.imu.t_s * 1e9).astype(np.int64),
        imu_gyro=sim.imu.gyro_radps,
        imu_accel=sim.imu.accel_mps2,
        joints_x_m=sim.scene.joints_x_m.copy(),
        scene=sim.scene,
        metadata=sim.metadata(),
    )


class _Fanout:
    """Sends every message to several writers (ROS 2 MCAP and, optionally, ROS 1)."""

    def __init__(self, writers: list[LogWriter | Ros1Writer]) -> None:
        self._writers = writers

    def points(self, *args: Any) -> None:
        for w in self._writers:
            w.points(*args)

    def odom(self, *args: Any) -> None:
        for w in self._writers:
            w.odom(*args)

    def imu(self, *args: Any) -> None:
        for w in self._writers:
            w.imu(*args)


def _backward_twist(poses: F64, k: int) -> tuple[F64, F64]:
    """Body-frame velocity between scans ``k - 1`` and ``k`` (zero at ``k = 0``)."""
    if k == 0:
        return np.zeros(3), np.zeros(3)
    prev, cur = poses[k - 1], poses[k]
    lin = prev[:3, :3].T @ (cur[:3, 3] - prev[:3, 3]) / SCAN_PERIOD_S
    ang = so3_log((prev[:3, :3].T @ cur[:3, :3])[None])[0] / SCAN_PERIOD_S
    return lin, ang


@dataclass(frozen=True)
class SimResult:
    """What :func:`simulate` wrote and measured."""

    out_dir: Path
    log_dir: Path
    mcap_path: Path
    gt_tum: Path
    odom_tum: Path
    joints_json: Path
    scene: str
    sensor: str
    n_scans: int
    n_points: int
    n_imu: int
    n_joints: int
    duration_s: float
    endpoint_error_m: float
    log_size_bytes: int
    time_total_s: float
    time_setup_s: float
    time_scans_s: float
    time_write_s: float
    time_odometry_s: float = 0.0

    @property
    def time_per_scan_s(self) -> float:
        """Ray casting + measurement time per scan (excludes serialisation and writing)."""
        return self.time_scans_s / max(self.n_scans, 1)


def _clear_outputs(paths: tuple[Path, ...], overwrite: bool) -> None:
    """Remove the outputs of an earlier simulation, or refuse (``FileExistsError``)."""
    for existing in paths:
        if existing.exists():
            if not overwrite:
                raise FileExistsError(
                    f"{existing} exists (pass overwrite=True / --force to replace)"
                )
            if existing.is_dir():
                shutil.rmtree(existing)
            else:
                existing.unlink()


@dataclass
class _Stream:
    """What writing the log produced: the odometry as written (the drift model's, or
    KISS-ICP's), point and IMU counts, and the seconds spent on scans and odometry."""

    odom_poses: NDArray[np.float64]
    n_points: int = 0
    n_imu: int = 0
    t_scans: float = 0.0
    t_odom: float = 0.0


def _write_stream(
    sim: Simulation, w: _Fanout, kiss: KissOdometry | None, progress: bool, label: str
) -> _Stream:
    """Every scan, odometry message and IMU sample of ``sim`` in time order into ``w``."""
    stream = _Stream(odom_poses=sim.drift.odom_poses.copy())
    imu_ns = T0_NS + np.round(sim.imu.t_s * 1e9).astype(np.int64)
    lin, ang = sim.odom_twist()
    var_g = sim.imu_spec.gyro_noise_radps**2
    var_a = sim.imu_spec.accel_noise_mps2**2

    def imu_until(stamp: float) -> None:
        while stream.n_imu < imu_ns.size and imu_ns[stream.n_imu] <= stamp:
            i = stream.n_imu
            w.imu(int(imu_ns[i]), sim.imu.gyro_radps[i], sim.imu.accel_mps2[i], var_g, var_a)
            stream.n_imu += 1

    bar = Progress(label, sim.n_scans, enabled=progress)
    for k in range(sim.n_scans):
        stamp = int(sim.stamps_ns[k])
        imu_until(stamp)
        t0 = time.perf_counter()
        pts, inten, times = sim.scan_with_times(k)
        stream.t_scans += time.perf_counter() - t0
        stream.n_points += pts.shape[0]
        w.points(stamp, pts, inten, times)
        if kiss is not None:
            t1 = time.perf_counter()
            stream.odom_poses[k] = kiss.step(pts)
            stream.t_odom += time.perf_counter() - t1
            lin[k], ang[k] = _backward_twist(stream.odom_poses, k)
        w.odom(stamp, stream.odom_poses[k], lin[k], ang[k])
        bar.advance()
    imu_until(math.inf)
    bar.close()
    return stream


def _kiss_summary(
    kiss: KissOdometry, odom: NDArray[np.float64], gt: NDArray[np.float64], endpoint: float
) -> dict[str, Any]:
    """``joints.json`` ``odometry`` for a KISS-ICP run: its settings and its errors."""
    err = odom[:, :3, 3] - gt[:, :3, 3]
    return {
        **kiss.settings,
        "endpoint_error_m": endpoint,
        "endpoint_axial_m": float(err[-1, 0]),
        "max_axial_m": float(np.max(np.abs(err[:, 0]))),
        "max_lateral_m": float(np.max(np.hypot(err[:, 1], err[:, 2]))),
    }


def _write_truth(
    out: Path,
    sim: Simulation,
    stream: _Stream,
    kiss: KissOdometry | None,
    *,
    ros1: bool,
    livox: bool,
) -> float:
    """``gt.tum``, ``odom.tum`` and ``joints.json`` (the scene's metadata, the files and topics
    written, KISS-ICP's summary) beside the log; returns the odometry's endpoint error (m)."""
    write_tum(out / "gt.tum", sim.stamps_ns, sim.gt_poses)
    write_tum(out / "odom.tum", sim.stamps_ns, stream.odom_poses)
    endpoint = float(np.linalg.norm(stream.odom_poses[-1, :3, 3] - sim.gt_poses[-1, :3, 3]))
    meta = sim.metadata()
    if kiss is not None:
        meta["odometry"] = _kiss_summary(kiss, stream.odom_poses, sim.gt_poses, endpoint)
    meta["files"] = {"log": LOG_DIRNAME, "gt": "gt.tum", "odom": "odom.tum"}
    if ros1:
        meta["files"]["ros1_bag"] = ROS1_BAG_NAME
    if livox:
        meta["topics"]["/livox/lidar"] = "livox_ros_driver2/msg/CustomMsg (same points, body)"
    write_json(out / "joints.json", meta)
    return endpoint


def _sim_result(
    out: Path,
    scene: str,
    sim: Simulation,
    stream: _Stream,
    endpoint: float,
    times: tuple[float, float],
) -> SimResult:
    """What :func:`simulate` wrote into ``out``, its sizes and where its time went (``times``:
    the start and the seconds spent setting up)."""
    t_start, t_setup = times
    log_dir = out / LOG_DIRNAME
    gt_tum, odom_tum, joints = out / "gt.tum", out / "odom.tum", out / "joints.json"
    mcaps = sorted(log_dir.glob("*.mcap"))
    size = sum(f.stat().st_size for f in log_dir.iterdir())
    total = time.perf_counter() - t_start
    return SimResult(
        out_dir=out,
        log_dir=log_dir,
        mcap_path=mcaps[0] if mcaps else log_dir,
        gt_tum=gt_tum,
        odom_tum=odom_tum,
        joints_json=joints,
        scene=scene,
        sensor=sim.sensor.name,
        n_scans=sim.n_scans,
        n_points=stream.n_points,
        n_imu=stream.n_imu,
        n_joints=int(sim.scene.joints_x_m.size),
        duration_s=float(sim.t_s[-1]),
        endpoint_error_m=endpoint,
        log_size_bytes=size,
        time_total_s=total,
        time_setup_s=t_setup,
        time_scans_s=stream.t_scans,
        time_write_s=total - t_setup - stream.t_scans - stream.t_odom,
        time_odometry_s=stream.t_odom,
    )


def _trajectory_spec(
    defaults: SceneDefaults,
    length: float,
    speed: float,
    return_mode: str | None,
    mount_deg: tuple[float, float],
    stops: Sequence[tuple[float, float, float]] = (),
    return_speed: float | None = None,
    return_lateral: float = 0.0,
    backups: Sequence[tuple[float, float, float]] = (),
    standstill_s: tuple[float, float] | None = None,
) -> TrajectorySpec:
    """The run's trajectory: the scene's ``defaults`` (:func:`defaults_for`) with the length,
    speed, return mode (None: the scene's), sensor mount, stops, return speed (None: the
    outbound's), return lane offset, back-ups and standing still before and after (None:
    2 s and 1 s) asked for."""
    if not (np.isfinite(length) and length > 0):
        raise ValueError(f"length_m must be > 0, got {length}")
    roll, pitch = _mount(mount_deg)
    pre, post = (2.0, 1.0) if standstill_s is None else (float(v) for v in standstill_s)
    if not (np.isfinite(pre) and np.isfinite(post) and pre >= 0.0 and post >= 0.0):
        raise ValueError(f"standstill_s: {standstill_s} must be two finite seconds >= 0")
    return TrajectorySpec(
        x_start_m=defaults.x_start_m,
        length_m=length,
        speed_mps=speed,
        return_mode=return_mode or defaults.return_mode,
        z0_m=defaults.z0_m,
        lateral_m=defaults.lateral_m,
        vertical_m=defaults.vertical_m,
        roll_rad=defaults.roll_rad,
        pitch_rad=defaults.pitch_rad,
        yaw_rad=defaults.yaw_rad,
        wobble_wavelength_m=defaults.wobble_wavelength_m,
        mount_roll_rad=float(np.radians(roll)),
        mount_pitch_rad=float(np.radians(pitch)),
        stops=tuple((float(a), float(b), float(c)) for a, b, c in stops),
        return_speed_mps=None if return_speed is None else float(return_speed),
        return_lateral_m=return_lateral,
        backups=tuple((float(a), float(b), float(c)) for a, b, c in backups),
        pre_s=pre,
        post_s=post,
    )


def _check_lane(side_m: float, params: dict[str, Any]) -> None:
    """``ValueError`` unless a return ``side_m`` to the side keeps the sensor within 0.6 of
    the section's radius of its centre line (a tunnel's other lane; a pipe has none)."""
    radius = float(params.get("radius_m", 0.0))
    if not (np.isfinite(side_m) and abs(side_m) <= 0.6 * radius):
        raise ValueError(
            f"return_lateral_m: {side_m} m must be finite and within 0.6 of the radius "
            f"({0.6 * radius:.2f} m) of the centre line"
        )


def _at_height(
    defaults: SceneDefaults, params: dict[str, Any], height_m: float | None
) -> SceneDefaults:
    """``defaults`` with the sensor ``height_m`` above the section's lowest point (a tunnel's
    floor, a pipe's invert); unchanged for None. ``ValueError`` unless the sensor stays
    inside the section, a tenth of the radius from its top and bottom."""
    if height_m is None:
        return defaults
    radius = float(params["radius_m"])
    floor = params.get("floor_z_m")
    bottom = -radius if floor is None else float(floor)
    room = radius - bottom
    if not (np.isfinite(height_m) and 0.1 * radius <= height_m <= room - 0.1 * radius):
        raise ValueError(
            f"sensor_height_m must be within {0.1 * radius:.3f}-{room - 0.1 * radius:.3f} m "
            f"(inside the section, a tenth of the radius from its top and bottom), got {height_m}"
        )
    return replace(defaults, z0_m=bottom + float(height_m))


def _mount(mount_deg: tuple[float, float]) -> tuple[float, float]:
    """``(roll, pitch)`` degrees checked: finite, roll within +-180, pitch within +-60 (a
    sensor pitched further does not look along the corridor)."""
    roll, pitch = (float(v) for v in mount_deg)
    if not (np.isfinite(roll) and abs(roll) <= 180.0):
        raise ValueError(f"mount roll must be within +-180 deg, got {roll}")
    if not (np.isfinite(pitch) and abs(pitch) <= 60.0):
        raise ValueError(f"mount pitch must be within +-60 deg, got {pitch}")
    return roll, pitch


def simulate(
    scene: str,
    out_dir: Path | str,
    *,
    seed: int = 0,
    length_m: float | None = None,
    sensor: str | None = None,
    return_mode: str | None = None,
    drift: float | str = "medium",
    distinctiveness: float | None = None,
    identical_joints: bool = False,
    speed_mps: float | None = None,
    return_speed_mps: float | None = None,
    return_lateral_m: float = 0.0,
    sensor_overrides: dict[str, Any] | None = None,
    scene_overrides: dict[str, Any] | None = None,
    world_seed: int | None = None,
    mount_deg: tuple[float, float] = (0.0, 0.0),
    stops: Sequence[tuple[float, float, float]] = (),
    curve_radius_m: float | None = None,
    sensor_height_m: float | None = None,
    backups: Sequence[tuple[float, float, float]] = (),
    standstill_s: tuple[float, float] | None = None,
    odometry: str = "drift",
    livox: bool = False,
    ros1: bool = False,
    progress: bool = True,
    overwrite: bool = False,
    sweep: bool = False,
) -> SimResult:
    """Simulate ``scene`` and write ``out_dir/log/`` (rosbag2, MCAP storage: ``/points``,
    ``/odom``, ``/imu``), ``out_dir/gt.tum``, ``out_dir/odom.tum`` and ``out_dir/joints.json``.

    ``return_mode`` defaults to the scene's (``reverse`` for pipes, ``turn`` for tunnels);
    ``drift`` is a drift profile (:mod:`decod_rs.sim.drift`): an endpoint error in metres or a
    preset, ``"legs:OUT,RET"`` or ``"slip:LO,HI"``. ``scene_overrides`` change
    the scene builder's parameters (``radius_m``, ``segment_length_m``, ``ring_width_m``,
    ``arch_spacing_m``, ...; an unknown key is a ``ValueError`` listing the valid ones; the
    sensor mount follows the radius, :func:`decod_rs.sim.scenes.defaults_for`).
    ``odometry="kiss-icp"`` replaces the drift model by a real LiDAR odometry (KISS-ICP) run
    on the simulated scans (``drift`` is then ignored). ``world_seed`` builds the scene from
    another seed than ``seed`` (default: the same): two inspections of one world with their
    own noise and drift. ``mount_deg``: the sensor's static mount, ``(roll, pitch)`` in
    degrees (pitch positive nose down), which the scans, odometry, IMU and ground truth all
    carry (:class:`TrajectorySpec`).
    ``return_speed_mps``: the return leg's cruise speed (None: ``speed_mps``), a robot that
    inspects on the way out and drives back faster. ``return_lateral_m``: the return runs
    that far to the side (m, to the left of the outbound direction; within 0.6 of the radius),
    a vehicle that comes back in a tunnel's other lane.
    ``stops``: halts along the legs, ``(leg, fraction, seconds)`` (leg 0 outbound, 1 return;
    :class:`TrajectorySpec`), as an inspection robot makes at defects.
    ``backups``: ``(leg, fraction, metres)``: there the vehicle stops, drives ``metres`` back
    the way it came and forward over them again before it goes on, as an operator does to
    look again at a defect (:class:`TrajectorySpec`). ``standstill_s``: seconds standing
    still before moving off and after coming back (None: 2 and 1), as a log whose recording
    starts while the operator gets ready.
    ``curve_radius_m``: the corridor curves in the horizontal plane with this radius
    (positive to the left; :mod:`decod_rs.sim.bend`); None: straight.
    ``sensor_height_m``: the sensor's height above the lowest point of the section (a
    pipe's invert, a tunnel's floor) instead of the scene's (near the centre of a pipe, 1.6 m
    above a tunnel's floor): a crawler low in a large pipe, a small robot in a tunnel.
    ``livox=True`` adds ``/livox/lidar`` (livox_ros_driver2/msg/CustomMsg, the same points);
    ``ros1=True`` also writes the log as a ROS 1 bag ``out_dir/log.bag``.
    ``sweep=True``: each point measured at its own time within its scan, in the sensor's frame
    at that time, with Ouster's per-point ``t`` (:mod:`decod_rs.sim.sweep`) and, with
    ``livox``, Livox's ``offset_time`` since ``timebase``.
    Raises ``FileExistsError`` if the log exists and not ``overwrite``.
    """
    if odometry not in ("drift", "kiss-icp"):
        raise ValueError(f"odometry must be 'drift' or 'kiss-icp', got {odometry!r}")
    _mount(mount_deg)  # refused before anything is written
    t_start = time.perf_counter()
    out = Path(out_dir)
    log_dir = out / LOG_DIRNAME
    bag_path = out / ROS1_BAG_NAME
    if not overwrite:
        _clear_outputs((log_dir, bag_path), overwrite)  # refused before the work
    sim = Simulation(
        scene,
        seed=seed,
        length_m=length_m,
        sensor=sensor,
        return_mode=return_mode,
        drift=drift,
        distinctiveness=distinctiveness,
        identical_joints=identical_joints,
        speed_mps=speed_mps,
        return_speed_mps=return_speed_mps,
        return_lateral_m=return_lateral_m,
        sensor_overrides=sensor_overrides,
        scene_overrides=scene_overrides,
        world_seed=world_seed,
        mount_deg=mount_deg,
        stops=stops,
        curve_radius_m=curve_radius_m,
        sensor_height_m=sensor_height_m,
        backups=backups,
        standstill_s=standstill_s,
        sweep=sweep,
    )
    if overwrite:
        # Every argument checked (the Simulation refuses a bad one): only now is an earlier
        # simulation in ``out`` replaced.
        _clear_outputs((log_dir, bag_path), overwrite)
    out.mkdir(parents=True, exist_ok=True)
    kiss = KissOdometry(scene, sim.gt_poses[0]) if odometry == "kiss-icp" else None
    t_setup = time.perf_counter() - t_start
    with contextlib.ExitStack() as stack:
        writers: list[LogWriter | Ros1Writer] = [
            stack.enter_context(LogWriter(log_dir, livox=livox))
        ]
        if ros1:
            writers.append(stack.enter_context(Ros1Writer(bag_path, livox=livox)))
        stream = _write_stream(sim, _Fanout(writers), kiss, progress, f"simulate {scene}")
    endpoint = _write_truth(out, sim, stream, kiss, ros1=ros1, livox=livox)
    return _sim_result(out, scene, sim, stream, endpoint, (t_start, t_setup))
