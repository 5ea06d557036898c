"""Output: a rosbag2 directory with MCAP storage written with rosbags (``/points``
sensor_msgs/msg/PointCloud2, ``/odom`` nav_msgs/msg/Odometry, ``/imu`` sensor_msgs/msg/Imu),
TUM trajectories and ``joints.json``."""

from __future__ import annotations

import json
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
from numpy.typing import NDArray
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from decod_rs.sim.clouds import cloud_layout
from decod_rs.sim.fields import F64
from decod_rs.sim.livox import CUSTOM_MSG, TOPIC_LIVOX, custom_msg_cdr, livox_types
from decod_rs.sim.trajectory import quat_xyzw

TOPIC_POINTS = "/points"
TOPIC_ODOM = "/odom"
TOPIC_IMU = "/imu"
FRAME_BODY = "body"
FRAME_ODOM = "odom"

_TS = get_typestore(Stores.ROS2_HUMBLE)
_T = _TS.types
_HEADER = _T["std_msgs/msg/Header"]
_TIME = _T["builtin_interfaces/msg/Time"]
_FIELD = _T["sensor_msgs/msg/PointField"]
_CLOUD = _T["sensor_msgs/msg/PointCloud2"]
_ODOM = _T["nav_msgs/msg/Odometry"]
_IMU = _T["sensor_msgs/msg/Imu"]
_POSE_COV = _T["geometry_msgs/msg/PoseWithCovariance"]
_TWIST_COV = _T["geometry_msgs/msg/TwistWithCovariance"]
_POSE = _T["geometry_msgs/msg/Pose"]
_TWIST = _T["geometry_msgs/msg/Twist"]
_POINT = _T["geometry_msgs/msg/Point"]
_QUAT = _T["geometry_msgs/msg/Quaternion"]
_VEC3 = _T["geometry_msgs/msg/Vector3"]


def _header(stamp_ns: int, frame: str) -> Any:
    return _HEADER(stamp=_TIME(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9), frame_id=frame)


def _vec(v: F64) -> Any:
    return _VEC3(x=float(v[0]), y=float(v[1]), z=float(v[2]))


class LogWriter:
    """Streams messages into ``log_dir`` (must not exist; rosbags creates it)."""

    def __init__(self, log_dir: Path, livox: bool = False) -> None:
        self.log_dir = log_dir
        self._writer = Writer(log_dir, version=8, storage_plugin=StoragePlugin.MCAP)
        self.counts = {TOPIC_POINTS: 0, TOPIC_ODOM: 0, TOPIC_IMU: 0}
        self._livox = livox
        self._ts = _TS
        if livox:
            self._ts = get_typestore(Stores.ROS2_HUMBLE)
            self._ts.register(livox_types())
            self.counts[TOPIC_LIVOX] = 0

    def __enter__(self) -> LogWriter:
        w = self._writer
        w.open()
        self._c_points = w.add_connection(TOPIC_POINTS, _CLOUD.__msgtype__, typestore=_TS)
        self._c_odom = w.add_connection(TOPIC_ODOM, _ODOM.__msgtype__, typestore=_TS)
        self._c_imu = w.add_connection(TOPIC_IMU, _IMU.__msgtype__, typestore=_TS)
        if self._livox:
            self._c_livox = w.add_connection(TOPIC_LIVOX, CUSTOM_MSG, typestore=self._ts)
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self._writer.close()

    def points(
        self,
        stamp_ns: int,
        xyz: NDArray[np.float32],
        intensity: NDArray[np.float32],
        times_ns: NDArray[np.uint32] | None = None,
    ) -> None:
        n = xyz.shape[0]
        fields, step, data = cloud_layout(_FIELD, xyz, intensity, times_ns)
        msg = _CLOUD(
            header=_header(stamp_ns, FRAME_BODY),
            height=1,
            width=n,
            fields=fields,
            is_bigendian=False,
            point_step=step,
            row_step=step * n,
            data=data,
            is_dense=True,
        )
        self._write(self._c_points, stamp_ns, msg, TOPIC_POINTS)
        if self._livox:
            raw = custom_msg_cdr(stamp_ns, xyz, intensity, times_ns)
            self._writer.write(self._c_livox, stamp_ns, raw)
            self.counts[TOPIC_LIVOX] += 1

    def odom(self, stamp_ns: int, pose: F64, lin_body: F64, ang_body: F64) -> None:
        q = quat_xyzw(pose[None, :3, :3])[0]
        t = pose[:3, 3]
        msg = _ODOM(
            header=_header(stamp_ns, FRAME_ODOM),
            child_frame_id=FRAME_BODY,
            pose=_POSE_COV(
                pose=_POSE(
                    position=_POINT(x=float(t[0]), y=float(t[1]), z=float(t[2])),
                    orientation=_QUAT(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])),
                ),
                covariance=np.zeros(36),
            ),
            twist=_TWIST_COV(
                twist=_TWIST(linear=_vec(lin_body), angular=_vec(ang_body)),
                covariance=np.zeros(36),
            ),
        )
        self._write(self._c_odom, stamp_ns, msg, TOPIC_ODOM)

    def imu(self, stamp_ns: int, gyro: F64, accel: F64, gyro_var: float, accel_var: float) -> None:
        cov_o = np.zeros(9)
        cov_o[0] = -1.0  # orientation not provided (REP 145)
        msg = _IMU(
            header=_header(stamp_ns, FRAME_BODY),
            orientation=_QUAT(x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=cov_o,
            angular_velocity=_vec(gyro),
            angular_velocity_covariance=np.diag([gyro_var] * 3).reshape(-1),
            linear_acceleration=_vec(accel),
            linear_acceleration_covariance=np.diag([accel_var] * 3).reshape(-1),
        )
        self._write(self._c_imu, stamp_ns, msg, TOPIC_IMU)

    def _write(self, conn: Any, stamp_ns: int, msg: Any, topic: str) -> None:
        self._writer.write(conn, stamp_ns, _TS.serialize_cdr(msg, msg.__msgtype__))
        self.counts[topic] += 1


def stamp_text(stamp_ns: int) -> str:
    """Exact decimal seconds of an integer nanosecond stamp."""
    return f"{stamp_ns // 10**9}.{stamp_ns % 10**9:09d}"


def write_tum(path: Path, stamps_ns: NDArray[np.int64], poses: F64) -> None:
    """TUM trajectory: ``stamp tx ty tz qx qy qz qw`` per line, poses ``(N, 4, 4)``."""
    q = quat_xyzw(poses[:, :3, :3])
    t = poses[:, :3, 3]
    lines = [
        f"{stamp_text(int(s))} {t[i, 0]:.6f} {t[i, 1]:.6f} {t[i, 2]:.6f} "
        f"{q[i, 0]:.9f} {q[i, 1]:.9f} {q[i, 2]:.9f} {q[i, 3]:.9f}"
        for i, s in enumerate(stamps_ns)
    ]
    path.write_text("\n".join(lines) + "\n")


def write_json(path: Path, data: dict[str, Any]) -> None:
    path.write_text(json.dumps(data, indent=2, sort_keys=False) + "\n")
