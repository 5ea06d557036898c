"""Optional extra outputs: Livox ``livox_ros_driver2/msg/CustomMsg`` (the only point message
GEODE's Livox device publishes) in CDR (ROS 2) and ROS 1 encodings, and a ROS 1 bag of the
whole log.

CustomMsg payloads are packed with numpy (a 6,000-point message would otherwise be 6,000
Python objects): ROS 1 packs each ``CustomPoint`` in 19 bytes; CDR aligns every point's
``uint32 offset_time`` to 4 bytes, so points take 20 bytes (one pad byte) except the last.
"""

from __future__ import annotations

import struct
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
from numpy.typing import NDArray
from rosbags.rosbag1 import Writer as Writer1
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from decod_rs.sim.clouds import cloud_layout
from decod_rs.sim.fields import F64
from decod_rs.sim.trajectory import quat_xyzw

CUSTOM_MSG = "livox_ros_driver2/msg/CustomMsg"
CUSTOM_POINT = "livox_ros_driver2/msg/CustomPoint"
TOPIC_LIVOX = "/livox/lidar"

CUSTOM_POINT_DEF = """
uint32 offset_time
float32 x
float32 y
float32 z
uint8 reflectivity
uint8 tag
uint8 line
"""
CUSTOM_MSG_DEF = """
std_msgs/Header header
uint64 timebase
uint32 point_num
uint8 lidar_id
uint8[3] rsvd
livox_ros_driver2/CustomPoint[] points
"""


def livox_types() -> dict[str, Any]:
    """The two Livox message definitions, for ``Typestore.register``."""
    types: dict[str, Any] = {}
    types.update(get_types_from_msg(CUSTOM_POINT_DEF, CUSTOM_POINT))
    types.update(get_types_from_msg(CUSTOM_MSG_DEF, CUSTOM_MSG))
    return types


def _points_struct(
    xyz: NDArray[np.float32],
    intensity: NDArray[np.float32],
    pad: int,
    times_ns: NDArray[np.uint32] | None,
) -> NDArray[np.void]:
    n = xyz.shape[0]
    names = ["offset_time", "x", "y", "z", "reflectivity", "tag", "line"]
    formats = ["<u4", "<f4", "<f4", "<f4", "u1", "u1", "u1"]
    if pad:
        names.append("pad")
        formats.append(f"V{pad}")
    arr = np.zeros(n, dtype=np.dtype({"names": names, "formats": formats}))
    arr["x"], arr["y"], arr["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    arr["reflectivity"] = np.clip(np.round(intensity), 0, 255).astype(np.uint8)
    # offset_time: each point's ns since ``timebase`` (the scan stamp), 0 for a scan taken
    # from one pose; line = Avia's 6 lasers.
    if times_ns is not None:
        arr["offset_time"] = times_ns
    arr["line"] = (np.arange(n) % 6).astype(np.uint8)
    return arr


def custom_msg_ros1(
    stamp_ns: int,
    seq: int,
    xyz: NDArray[np.float32],
    intensity: NDArray[np.float32],
    times_ns: NDArray[np.uint32] | None = None,
) -> bytes:
    frame = b"body"
    head = struct.pack("<III", seq, stamp_ns // 10**9, stamp_ns % 10**9)
    head += struct.pack("<I", len(frame)) + frame
    n = xyz.shape[0]
    body = struct.pack("<QIB3sI", stamp_ns, n, 0, b"\0\0\0", n)
    return head + body + _points_struct(xyz, intensity, 0, times_ns).tobytes()


def custom_msg_cdr(
    stamp_ns: int,
    xyz: NDArray[np.float32],
    intensity: NDArray[np.float32],
    times_ns: NDArray[np.uint32] | None = None,
) -> bytes:
    frame = b"body\0"
    out = bytearray(b"\x00\x01\x00\x00")  # CDR little endian encapsulation
    out += struct.pack("<iI", stamp_ns // 10**9, stamp_ns % 10**9)
    out += struct.pack("<I", len(frame)) + frame

    def align(k: int) -> None:
        while (len(out) - 4) % k:
            out.append(0)

    align(8)
    out += struct.pack("<Q", stamp_ns)
    n = xyz.shape[0]
    out += struct.pack("<I", n) + b"\x00" + b"\0\0\0"
    align(4)
    out += struct.pack("<I", n)
    if n:
        pts = _points_struct(xyz, intensity, 1, times_ns).tobytes()
        out += pts[:-1]  # no padding after the last point
    return bytes(out)


class Ros1Writer:
    """ROS 1 bag with ``/points``, ``/odom``, ``/imu`` (and ``/livox/lidar`` if ``livox``)."""

    def __init__(self, path: Path, livox: bool) -> None:
        self.ts = get_typestore(Stores.ROS1_NOETIC)
        if livox:
            self.ts.register(livox_types())
        self._w = Writer1(path)
        self._livox = livox
        self._seq: dict[str, int] = {}

    def __enter__(self) -> Ros1Writer:
        self._w.open()
        t = self.ts
        self._c = {
            "/points": self._w.add_connection(
                "/points", "sensor_msgs/msg/PointCloud2", typestore=t
            ),
            "/odom": self._w.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=t),
            "/imu": self._w.add_connection("/imu", "sensor_msgs/msg/Imu", typestore=t),
        }
        if self._livox:
            self._c[TOPIC_LIVOX] = self._w.add_connection(TOPIC_LIVOX, CUSTOM_MSG, typestore=t)
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self._w.close()

    def _next(self, topic: str) -> int:
        self._seq[topic] = self._seq.get(topic, -1) + 1
        return self._seq[topic]

    def _header(self, stamp_ns: int, frame: str, topic: str) -> Any:
        t = self.ts.types
        return t["std_msgs/msg/Header"](
            seq=self._next(topic),
            stamp=t["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9),
            frame_id=frame,
        )

    def _write(self, topic: str, stamp_ns: int, msg: Any) -> None:
        self._w.write(self._c[topic], stamp_ns, self.ts.serialize_ros1(msg, msg.__msgtype__))

    def points(
        self,
        stamp_ns: int,
        xyz: NDArray[np.float32],
        inten: NDArray[np.float32],
        times_ns: NDArray[np.uint32] | None = None,
    ) -> None:
        t = self.ts.types
        n = xyz.shape[0]
        fields, step, data = cloud_layout(t["sensor_msgs/msg/PointField"], xyz, inten, times_ns)
        msg = t["sensor_msgs/msg/PointCloud2"](
            header=self._header(stamp_ns, "body", "/points"),
            height=1,
            width=n,
            fields=fields,
            is_bigendian=False,
            point_step=step,
            row_step=step * n,
            data=data,
            is_dense=True,
        )
        self._write("/points", stamp_ns, msg)
        if self._livox:
            raw = custom_msg_ros1(stamp_ns, self._next(TOPIC_LIVOX), xyz, inten, times_ns)
            self._w.write(self._c[TOPIC_LIVOX], stamp_ns, raw)

    def odom(self, stamp_ns: int, pose: F64, lin: F64, ang: F64) -> None:
        t = self.ts.types
        q = quat_xyzw(pose[None, :3, :3])[0]
        vec = t["geometry_msgs/msg/Vector3"]
        msg = t["nav_msgs/msg/Odometry"](
            header=self._header(stamp_ns, "odom", "/odom"),
            child_frame_id="body",
            pose=t["geometry_msgs/msg/PoseWithCovariance"](
                pose=t["geometry_msgs/msg/Pose"](
                    position=t["geometry_msgs/msg/Point"](
                        x=float(pose[0, 3]), y=float(pose[1, 3]), z=float(pose[2, 3])
                    ),
                    orientation=t["geometry_msgs/msg/Quaternion"](
                        x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])
                    ),
                ),
                covariance=np.zeros(36),
            ),
            twist=t["geometry_msgs/msg/TwistWithCovariance"](
                twist=t["geometry_msgs/msg/Twist"](
                    linear=vec(x=float(lin[0]), y=float(lin[1]), z=float(lin[2])),
                    angular=vec(x=float(ang[0]), y=float(ang[1]), z=float(ang[2])),
                ),
                covariance=np.zeros(36),
            ),
        )
        self._write("/odom", stamp_ns, msg)

    def imu(self, stamp_ns: int, gyro: F64, accel: F64, gyro_var: float, accel_var: float) -> None:
        t = self.ts.types
        vec = t["geometry_msgs/msg/Vector3"]
        cov_o = np.zeros(9)
        cov_o[0] = -1.0
        msg = t["sensor_msgs/msg/Imu"](
            header=self._header(stamp_ns, "body", "/imu"),
            orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=cov_o,
            angular_velocity=vec(x=float(gyro[0]), y=float(gyro[1]), z=float(gyro[2])),
            angular_velocity_covariance=np.diag([gyro_var] * 3).reshape(-1),
            linear_acceleration=vec(x=float(accel[0]), y=float(accel[1]), z=float(accel[2])),
            linear_acceleration_covariance=np.diag([accel_var] * 3).reshape(-1),
        )
        self._write("/imu", stamp_ns, msg)
