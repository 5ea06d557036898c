"""Native log ingestion (issue 4): logs written here by rosbags (ROS 2 CDR, rosbag2 + MCAP)
and by the ``mcap`` package (ROS 1 encoding, serialised by hand), read back by decod_rs.

Ground truth: a known trajectory (translation linear in time, yaw at a constant rate about
z), for which decod's SE(3) interpolation (lerp + slerp) is exact; tolerances are float
round-off (1e-9 on poses; points are float32, compared exactly after the float32 cast)."""

from __future__ import annotations

import itertools
import re
import struct
from pathlib import Path

import numpy as np
import pytest
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Bag2Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

import decod_rs
from decod_rs.cli import main as cli_main

RNG = np.random.default_rng(4)
NS = 1_000_000_000
ODOM_DT = 0.1  # odometry period (s); clouds fall between odometry stamps


def pose_at(t: float) -> np.ndarray:
    """The known trajectory: T_world_body at time t."""
    yaw = 0.3 * t
    c, s = np.cos(yaw), np.sin(yaw)
    m = np.eye(4)
    m[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    m[:3, 3] = [1.0 * t, 0.5 * t, 0.1]
    return m


def quat_at(t: float) -> tuple[float, float, float, float]:
    yaw = 0.3 * t
    return (0.0, 0.0, float(np.sin(yaw / 2)), float(np.cos(yaw / 2)))


def random_points(n: int) -> np.ndarray:
    return RNG.uniform(-20, 20, size=(n, 3)).astype(np.float32)


# --- PointCloud2 layouts --------------------------------------------------------------
# (name, [(field, offset, datatype, numpy type)], point_step, big-endian)
F32, F64, U8, U16, U32 = 7, 8, 2, 4, 6
LAYOUTS = {
    "xyz_f32_intensity": (
        [("x", 0, F32), ("y", 4, F32), ("z", 8, F32), ("intensity", 12, F32)],
        16,
        False,
    ),
    "ouster": (
        [
            ("x", 0, F32),
            ("y", 4, F32),
            ("z", 8, F32),
            ("intensity", 16, F32),
            ("t", 20, U32),
            ("reflectivity", 24, U16),
            ("ring", 26, U16),
            ("ambient", 28, U16),
            ("range", 32, U32),
        ],
        48,
        False,
    ),
    "velodyne": (
        [
            ("x", 0, F32),
            ("y", 4, F32),
            ("z", 8, F32),
            ("intensity", 12, F32),
            ("ring", 16, U16),
            ("time", 18, F32),
        ],
        22,
        False,
    ),
    "livox_packed": (
        [
            ("x", 0, F32),
            ("y", 4, F32),
            ("z", 8, F32),
            ("intensity", 12, F32),
            ("tag", 16, U8),
            ("line", 17, U8),
            ("timestamp", 18, F64),
        ],
        26,
        False,
    ),
    "xyz_f64_shuffled": ([("t", 0, U32), ("z", 4, F64), ("x", 12, F64), ("y", 20, F64)], 32, False),
    "big_endian": ([("x", 0, F32), ("y", 4, F32), ("z", 8, F32), ("intensity", 12, F32)], 16, True),
}
NP_TYPES = {F32: "f4", F64: "f8", U8: "u1", U16: "u2", U32: "u4"}


def cloud_bytes(
    points: np.ndarray, fields: list, step: int, big: bool, height: int = 1, row_pad: int = 0
) -> tuple[bytes, int, int]:
    """Serialises points in the layout; returns (data, width, row_step)."""
    order = ">" if big else "<"
    dtype = np.dtype(
        {
            "names": [f[0] for f in fields],
            "formats": [order + NP_TYPES[f[2]] for f in fields],
            "offsets": [f[1] for f in fields],
            "itemsize": step,
        }
    )
    n = len(points)
    width = n // height
    arr = np.zeros(n, dtype=dtype)
    for k, axis in enumerate("xyz"):
        arr[axis] = points[:, k]
    raw = arr.tobytes()
    row_step = width * step + row_pad
    rows = [
        raw[r * width * step : (r + 1) * width * step] + b"\xee" * row_pad for r in range(height)
    ]
    return b"".join(rows), width, row_step


# --- ROS 2 (CDR) logs through rosbags ---------------------------------------------------
LIVOX_MSGS = {
    "CustomPoint": "uint32 offset_time\nfloat32 x\nfloat32 y\nfloat32 z\nuint8 reflectivity\n"
    "uint8 tag\nuint8 line\n",
    "CustomMsg": "std_msgs/Header header\nuint64 timebase\nuint32 point_num\nuint8 lidar_id\n"
    "uint8[3] rsvd\n{pkg}/CustomPoint[] points\n",
}


def ros2_store(livox_pkg: str | None = None):
    store = get_typestore(Stores.ROS2_HUMBLE)
    if livox_pkg:
        types = {}
        for name, text in LIVOX_MSGS.items():
            types.update(get_types_from_msg(text.format(pkg=livox_pkg), f"{livox_pkg}/msg/{name}"))
        store.register(types)
    return store


def ros2_header(store, t: float, frame: str):
    sec = int(np.floor(t))
    return store.types["std_msgs/msg/Header"](
        stamp=store.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=round((t - sec) * NS)),
        frame_id=frame,
    )


def ros2_cloud(
    store,
    t: float,
    data: bytes,
    fields: list,
    step: int,
    big: bool,
    width: int,
    height: int,
    row_step: int,
):
    T = store.types
    return T["sensor_msgs/msg/PointCloud2"](
        header=ros2_header(store, t, "lidar"),
        height=height,
        width=width,
        fields=[
            T["sensor_msgs/msg/PointField"](name=n, offset=o, datatype=d, count=1)
            for n, o, d in fields
        ],
        is_bigendian=big,
        point_step=step,
        row_step=row_step,
        data=np.frombuffer(data, dtype=np.uint8),
        is_dense=False,
    )


def ros2_odometry(store, t: float):
    T = store.types
    tx, ty, tz = pose_at(t)[:3, 3]
    qx, qy, qz, qw = quat_at(t)
    pose = T["geometry_msgs/msg/Pose"](
        position=T["geometry_msgs/msg/Point"](x=tx, y=ty, z=tz),
        orientation=T["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
    )
    v3 = T["geometry_msgs/msg/Vector3"]
    return T["nav_msgs/msg/Odometry"](
        header=ros2_header(store, t, "odom"),
        child_frame_id="base",
        pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        twist=T["geometry_msgs/msg/TwistWithCovariance"](
            twist=T["geometry_msgs/msg/Twist"](linear=v3(x=0, y=0, z=0), angular=v3(x=0, y=0, z=0)),
            covariance=np.zeros(36),
        ),
    )


def ros2_imu(store, t: float, acc: np.ndarray):
    T = store.types
    v3 = T["geometry_msgs/msg/Vector3"]
    return T["sensor_msgs/msg/Imu"](
        header=ros2_header(store, t, "imu"),
        orientation=T["geometry_msgs/msg/Quaternion"](x=0, y=0, z=0, w=1),
        orientation_covariance=np.zeros(9),
        angular_velocity=v3(x=0, y=0, z=0),
        angular_velocity_covariance=np.zeros(9),
        linear_acceleration=v3(x=acc[0], y=acc[1], z=acc[2]),
        linear_acceleration_covariance=np.zeros(9),
    )


def write_ros2(
    path: Path,
    store,
    topics: dict[str, str],
    messages: list[tuple[str, float, object]],
    little_endian: bool = True,
) -> Path:
    """A rosbag2 directory with MCAP storage; messages = (topic, log time, message)."""
    with Bag2Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {t: writer.add_connection(t, ty, typestore=store) for t, ty in topics.items()}
        for topic, t, msg in sorted(messages, key=lambda m: m[1]):
            data = store.serialize_cdr(msg, topics[topic], little_endian=little_endian)
            writer.write(conns[topic], round(t * NS), data)
    return path


CLOUD_STAMPS = [0.05 + 0.2 * k for k in range(8)]  # inside the odometry span [0, 2]
ODOM_STAMPS = [ODOM_DT * k for k in range(21)]


def odometry_messages(store) -> list:
    return [("/odom", t, ros2_odometry(store, t)) for t in ODOM_STAMPS]


ROS2_TOPICS = {
    "/points": "sensor_msgs/msg/PointCloud2",
    "/odom": "nav_msgs/msg/Odometry",
    "/imu": "sensor_msgs/msg/Imu",
}


@pytest.mark.parametrize("layout", sorted(LAYOUTS))
def test_ros2_layouts_round_trip_with_interpolated_poses(tmp_path, layout):
    store = ros2_store()
    fields, step, big = LAYOUTS[layout]
    clouds = {t: random_points(60) for t in CLOUD_STAMPS}
    height = 3 if layout == "velodyne" else 1  # organised cloud with padded rows
    msgs = odometry_messages(store)
    for t, pts in clouds.items():
        data, width, row_step = cloud_bytes(pts, fields, step, big, height, 6 if height > 1 else 0)
        msgs.append(
            ("/points", t, ros2_cloud(store, t, data, fields, step, big, width, height, row_step))
        )
    log = write_ros2(tmp_path / "bag", store, ROS2_TOPICS, msgs)
    reader = decod_rs.read_log(log)
    assert reader.total_scans_hint == len(clouds)
    scans = list(reader)
    assert [s.stamp for s in scans] == pytest.approx(CLOUD_STAMPS, abs=1e-9)
    for s in scans:
        assert s.points.dtype == np.float32 and s.points.shape == (60, 3)
        np.testing.assert_array_equal(s.points, clouds[min(clouds, key=lambda c: abs(c - s.stamp))])
        np.testing.assert_allclose(s.pose, pose_at(s.stamp), atol=1e-9)
        assert s.specific_force is None
    assert reader.skipped_outside_odometry == []
    assert reader.odometry().shape == (len(ODOM_STAMPS), 8)


def test_nan_points_dropped_and_counted_and_big_endian_cdr(tmp_path):
    store = ros2_store()
    fields, step, big = LAYOUTS["xyz_f32_intensity"]
    pts = random_points(10)
    pts[[2, 7], 1] = [np.nan, np.inf]
    data, width, row_step = cloud_bytes(pts, fields, step, big)
    msgs = [
        *odometry_messages(store),
        ("/points", 0.5, ros2_cloud(store, 0.5, data, fields, step, big, width, 1, row_step)),
    ]
    log = write_ros2(tmp_path / "bag", store, ROS2_TOPICS, msgs, little_endian=False)
    reader = decod_rs.read_log(log, points="/points", odom="/odom")
    (scan,) = list(reader)
    np.testing.assert_array_equal(scan.points, np.delete(pts, [2, 7], axis=0))
    assert reader.dropped_non_finite_points == 2


def test_imu_mean_and_scans_outside_odometry_skipped(tmp_path):
    store = ros2_store()
    fields, step, big = LAYOUTS["xyz_f32_intensity"]
    imu_stamps = np.arange(0.0, 2.0, 0.01)
    accs = RNG.normal([0.1, -0.2, 9.81], 0.05, size=(len(imu_stamps), 3))
    msgs = odometry_messages(store)
    msgs += [("/imu", t, ros2_imu(store, t, a)) for t, a in zip(imu_stamps, accs, strict=True)]
    stamps = [-0.5, *CLOUD_STAMPS, 2.5]
    for t in stamps:
        data, width, row_step = cloud_bytes(random_points(5), fields, step, big)
        msgs.append(
            (
                "/points",
                t + 10 if t < 0 else t,  # log time need not equal the stamp
                ros2_cloud(store, t, data, fields, step, big, width, 1, row_step),
            )
        )
    log = write_ros2(tmp_path / "bag", store, ROS2_TOPICS, msgs)
    assert decod_rs.find_imu_topic(log) == "/imu"
    reader = decod_rs.read_log(log, imu="/imu")
    scans = list(reader)
    assert sorted(reader.skipped_outside_odometry) == pytest.approx([-0.5, 2.5])
    assert len(scans) == len(CLOUD_STAMPS)
    # first scan: nearest IMU sample; then the mean over (previous stamp, stamp]
    first = np.argmin(np.abs(imu_stamps - scans[0].stamp))
    np.testing.assert_allclose(scans[0].specific_force, accs[first], atol=1e-12)
    for prev, cur in itertools.pairwise(scans):
        sel = (imu_stamps >= prev.stamp - 1e-12) & (imu_stamps <= cur.stamp + 1e-12)
        np.testing.assert_allclose(cur.specific_force, accs[sel].mean(axis=0), atol=1e-9)


@pytest.mark.parametrize("pkg", ["livox_ros_driver", "livox_ros_driver2"])
def test_livox_custom_msg_cdr(tmp_path, pkg):
    store = ros2_store(pkg)
    T = store.types
    pts = random_points(7)
    msg = T[f"{pkg}/msg/CustomMsg"](
        header=ros2_header(store, 0.75, "livox"),
        timebase=750_000_000,
        point_num=7,
        lidar_id=1,
        rsvd=np.zeros(3, dtype=np.uint8),
        points=[
            T[f"{pkg}/msg/CustomPoint"](
                offset_time=k * 10_000_000,
                x=p[0],
                y=p[1],
                z=p[2],
                reflectivity=9,
                tag=0,
                line=k % 4,
            )
            for k, p in enumerate(pts)
        ],
    )
    topics = {"/livox/lidar": f"{pkg}/msg/CustomMsg", "/odom": "nav_msgs/msg/Odometry"}
    log = write_ros2(
        tmp_path / "bag", store, topics, [*odometry_messages(store), ("/livox/lidar", 0.75, msg)]
    )
    (scan,) = list(decod_rs.read_log(log, deskew=False))
    np.testing.assert_array_equal(scan.points, pts)
    np.testing.assert_allclose(scan.pose, pose_at(0.75), atol=1e-9)
    # Each point's time is timebase + offset_time (10k ms after the stamp), in the body frame
    # of that moment: deskewed, it is where the stamp's pose sees it. The odometry drives
    # 1.1 m/s and turns 0.3 rad/s, constant in the world frame, where deskewing takes the
    # body's velocity constant: within a few mm over 60 ms.
    (moved,) = list(decod_rs.read_log(log))
    seen_from = [np.linalg.inv(pose_at(0.75)) @ pose_at(0.75 + 0.01 * k) for k in range(7)]
    truth = np.array([m[:3, :3] @ q + m[:3, 3] for m, q in zip(seen_from, pts, strict=True)])
    np.testing.assert_allclose(moved.points, truth, atol=3e-3)
    assert np.abs(pts - truth).max() > 0.05  # what the correction had to move


# --- ROS 1 encoding through the mcap package -------------------------------------------
def r1_header(t: float, frame: str, seq: int = 0) -> bytes:
    sec = int(np.floor(t))
    return struct.pack("<III", seq, sec, round((t - sec) * NS)) + r1_string(frame)


def r1_string(s: str) -> bytes:
    return struct.pack("<I", len(s)) + s.encode()


def r1_cloud(
    t: float,
    data: bytes,
    fields: list,
    step: int,
    big: bool,
    width: int,
    height: int = 1,
    row_step: int | None = None,
) -> bytes:
    out = r1_header(t, "lidar") + struct.pack("<II", height, width) + struct.pack("<I", len(fields))
    for name, offset, datatype in fields:
        out += r1_string(name) + struct.pack("<IBI", offset, datatype, 1)
    row_step = width * step if row_step is None else row_step
    out += struct.pack("<BII", int(big), step, row_step) + struct.pack("<I", len(data)) + data
    return out + b"\x00"


def r1_pose(t: float) -> bytes:
    tx, ty, tz = pose_at(t)[:3, 3]
    return struct.pack("<7d", tx, ty, tz, *quat_at(t))


def r1_odometry(t: float) -> bytes:
    return (
        r1_header(t, "odom")
        + r1_string("base")
        + r1_pose(t)
        + struct.pack("<36d", *[0.0] * 36)
        + struct.pack("<6d36d", *[0.0] * 42)
    )


def r1_livox(t: float, pts: np.ndarray) -> bytes:
    out = r1_header(t, "livox") + struct.pack(
        "<QIB3BI", round(t * NS), len(pts), 1, 0, 0, 0, len(pts)
    )
    for k, p in enumerate(pts):
        out += struct.pack("<I3f3B", k, *p, 5, 0, k % 6)
    return out


R1_SCHEMAS = {
    "sensor_msgs/PointCloud2": "std_msgs/Header header\nuint32 height\n...",
    "nav_msgs/Odometry": "std_msgs/Header header\nstring child_frame_id\n...",
    "geometry_msgs/PoseStamped": "std_msgs/Header header\ngeometry_msgs/Pose pose\n",
    "geometry_msgs/TransformStamped": "std_msgs/Header header\nstring child_frame_id\n...",
    "livox_ros_driver/CustomMsg": "std_msgs/Header header\nuint64 timebase\n...",
    "livox_ros_driver2/CustomMsg": "std_msgs/Header header\nuint64 timebase\n...",
    "std_msgs/String": "string data\n",
    "tf2_msgs/TFMessage": "geometry_msgs/TransformStamped[] transforms\n",
}


def write_ros1_mcap(
    path: Path,
    topics: dict[str, str],
    messages: list[tuple[str, float, bytes]],
    chunk_size: int = 1 << 20,
    compression: CompressionType = CompressionType.NONE,
) -> Path:
    with path.open("wb") as f:
        w = McapWriter(f, chunk_size=chunk_size, compression=compression)
        w.start(profile="ros1")
        ids = {}
        for topic, ty in topics.items():
            sid = w.register_schema(ty, "ros1msg", R1_SCHEMAS[ty].encode())
            ids[topic] = w.register_channel(topic, "ros1", sid)
        for seq, (topic, t, data) in enumerate(sorted(messages, key=lambda m: m[1])):
            w.add_message(ids[topic], round(t * NS), data, round(t * NS), seq)
        w.finish()
    return path


R1_TOPICS = {"/velodyne_points": "sensor_msgs/PointCloud2", "/odom": "nav_msgs/Odometry"}


def r1_odometry_messages() -> list:
    return [("/odom", t, r1_odometry(t)) for t in ODOM_STAMPS]


def ros1_log(
    tmp_path: Path,
    n_clouds: int = 8,
    chunk_size: int = 1 << 20,
    bad: dict[int, bytes] | None = None,
) -> tuple[Path, dict[float, np.ndarray]]:
    fields, step, big = LAYOUTS["velodyne"]
    clouds, msgs = {}, r1_odometry_messages()
    for k in range(n_clouds):
        t = 0.05 + 1.9 * k / n_clouds
        clouds[t] = random_points(200)
        data, width, _ = cloud_bytes(clouds[t], fields, step, big)
        body = (bad or {}).get(k) or r1_cloud(t, data, fields, step, big, width)
        msgs.append(("/velodyne_points", t, body))
    return write_ros1_mcap(tmp_path / "r1.mcap", R1_TOPICS, msgs, chunk_size), clouds


@pytest.mark.parametrize("layout", ["ouster", "livox_packed", "xyz_f64_shuffled", "big_endian"])
def test_ros1_layouts_round_trip(tmp_path, layout):
    fields, step, big = LAYOUTS[layout]
    pts = random_points(33)
    data, width, _ = cloud_bytes(pts, fields, step, big)
    msgs = [
        *r1_odometry_messages(),
        ("/velodyne_points", 1.23, r1_cloud(1.23, data, fields, step, big, width)),
    ]
    for compression in CompressionType:  # none, lz4, zstd chunks
        log = write_ros1_mcap(
            tmp_path / f"{compression.name}.mcap", R1_TOPICS, msgs, 4096, compression
        )
        (scan,) = list(decod_rs.read_log(log))
        np.testing.assert_array_equal(scan.points, pts)
        np.testing.assert_allclose(scan.pose, pose_at(1.23), atol=1e-9)


@pytest.mark.parametrize("pkg", ["livox_ros_driver", "livox_ros_driver2"])
def test_ros1_livox_custom_msg(tmp_path, pkg):
    pts = random_points(11)
    topics = {"/livox/lidar": f"{pkg}/CustomMsg", "/odom": "nav_msgs/Odometry"}
    log = write_ros1_mcap(
        tmp_path / "r1.mcap",
        topics,
        [*r1_odometry_messages(), ("/livox/lidar", 0.4, r1_livox(0.4, pts))],
    )
    (scan,) = list(decod_rs.read_log(log, points="/livox/lidar"))
    np.testing.assert_array_equal(scan.points, pts)


def test_ros1_pose_stamped_and_transform_stamped_odometry(tmp_path):
    fields, step, big = LAYOUTS["velodyne"]
    pts = random_points(4)
    data, width, _ = cloud_bytes(pts, fields, step, big)
    topics = {
        "/velodyne_points": "sensor_msgs/PointCloud2",
        "/pose": "geometry_msgs/PoseStamped",
        "/tf_body": "geometry_msgs/TransformStamped",
    }
    msgs = [("/velodyne_points", 0.33, r1_cloud(0.33, data, fields, step, big, width))]
    msgs += [("/pose", t, r1_header(t, "map") + r1_pose(t)) for t in ODOM_STAMPS]
    msgs += [
        ("/tf_body", t, r1_header(t, "map") + r1_string("base") + r1_pose(t)) for t in ODOM_STAMPS
    ]
    log = write_ros1_mcap(tmp_path / "r1.mcap", topics, msgs)
    with pytest.raises(decod_rs.TopicError, match=r"several odometry.*/pose.*/tf_body"):
        decod_rs.read_log(log)
    for odom in ("/pose", "/tf_body"):
        (scan,) = list(decod_rs.read_log(log, odom=odom))
        np.testing.assert_allclose(scan.pose, pose_at(0.33), atol=1e-9)


def test_tum_odometry_path(tmp_path):
    log, clouds = ros1_log(tmp_path)
    tum = tmp_path / "odom.tum"
    rows = [
        f"{t:.9f} " + " ".join(f"{v:.12f}" for v in (*pose_at(t)[:3, 3], *quat_at(t)))
        for t in np.arange(0.0, 1.0, 0.05)
    ]
    tum.write_text("# stamp tx ty tz qx qy qz qw\n" + "\n".join(rows) + "\n")
    np.testing.assert_allclose(decod_rs.io.read_tum(tum)[:, 0], np.arange(0.0, 1.0, 0.05))
    reader = decod_rs.read_log(log, odom_tum=tum)
    scans = list(reader)
    inside = [t for t in clouds if t <= 0.95 + 1e-9]
    assert [s.stamp for s in scans] == pytest.approx(inside)
    assert len(reader.skipped_outside_odometry) == len(clouds) - len(inside)
    for s in scans:
        np.testing.assert_allclose(s.pose, pose_at(s.stamp), atol=1e-8)  # TUM text: 12 decimals
    with pytest.raises(ValueError, match="not both"):
        decod_rs.read_log(log, odom="/odom", odom_tum=tum)
    tum.write_text("0 1 2 3\n")
    with pytest.raises(decod_rs.LogFormatError, match=r"odom\.tum.*line 1"):
        decod_rs.read_log(log, odom_tum=tum)


# --- errors ----------------------------------------------------------------------------
def test_truncated_file_keeps_earlier_scans(tmp_path):
    log, clouds = ros1_log(tmp_path, n_clouds=10, chunk_size=4096)
    raw = log.read_bytes()
    log.write_bytes(raw[: int(len(raw) * 0.6)])
    reader = decod_rs.read_log(log, odom_tum=None)
    with pytest.warns(decod_rs.LogWarning, match=r"r1\.mcap: truncated at byte"):
        scans = list(reader)
    (fault,) = reader.health.faults
    assert fault.kind == "truncated" and fault.offset < len(raw) * 0.6
    assert 0 < len(scans) < len(clouds)
    for s in scans:
        np.testing.assert_array_equal(s.points, clouds[min(clouds, key=lambda c: abs(c - s.stamp))])
    info = decod_rs.inspect_log(log)
    assert info.problem is not None and info.topics
    with pytest.raises(decod_rs.LogFormatError, match=r"r1\.mcap: truncated"):
        decod_rs.check_log(log)


def test_corrupt_chunk_crc_is_skipped_and_reading_goes_on(tmp_path):
    log, clouds = ros1_log(tmp_path, n_clouds=10, chunk_size=4096)
    raw = bytearray(log.read_bytes())
    victim = clouds[sorted(clouds)[6]].tobytes()[:12]  # x y z of the 7th cloud's first point
    at = raw.find(victim)
    assert at > 0
    raw[at] ^= 0xFF
    log.write_bytes(bytes(raw))
    reader = decod_rs.read_log(log, odom="/odom")
    with pytest.warns(
        decod_rs.LogWarning, match=r"r1\.mcap: corrupt at byte \d+: chunk skipped: CRC"
    ):
        got = list(reader)
    (fault,) = reader.health.faults
    assert fault.lost_span_s is not None and fault.messages_lost is not None
    # Only the corrupt chunk's clouds are lost; the 7th cloud is among them, the last is not.
    stamps = sorted(clouds)
    assert stamps[6] not in [s.stamp for s in got] and len(got) >= 7
    assert got[-1].stamp == pytest.approx(stamps[-1])
    assert fault.lost_span_s[0] <= stamps[6] <= fault.lost_span_s[1]


def test_unknown_ambiguous_and_unsupported_topics(tmp_path):
    fields, step, big = LAYOUTS["velodyne"]
    data, width, _ = cloud_bytes(random_points(3), fields, step, big)
    cloud = r1_cloud(0.5, data, fields, step, big, width)
    topics = {**R1_TOPICS, "/os_cloud": "sensor_msgs/PointCloud2", "/chatter": "std_msgs/String"}
    msgs = [
        *r1_odometry_messages(),
        ("/velodyne_points", 0.5, cloud),
        ("/os_cloud", 0.5, cloud),
        ("/chatter", 0.5, r1_string("hi")),
    ]
    log = write_ros1_mcap(tmp_path / "r1.mcap", topics, msgs)
    with pytest.raises(
        decod_rs.TopicError, match=r"r1\.mcap.*several point cloud.*/os_cloud, /velodyne_points"
    ):
        decod_rs.read_log(log)
    with pytest.raises(
        decod_rs.TopicError, match=r"no topic `/nope`.*candidates: \[/os_cloud, /velodyne_points\]"
    ):
        decod_rs.read_log(log, points="/nope")
    with pytest.raises(decod_rs.UnsupportedMessageError, match=r"topic /chatter.*std_msgs/String"):
        decod_rs.read_log(log, points="/chatter")
    with pytest.raises(decod_rs.TopicError, match="IMU"):
        decod_rs.read_log(log, points="/os_cloud", imu="/imu")
    with pytest.raises(FileNotFoundError):
        decod_rs.read_log(tmp_path / "missing.mcap")


@pytest.mark.parametrize(
    ("body", "match"),
    [
        ("no_xyz", r"no `x` field"),
        ("short_row_step", r"inconsistent steps: row_step 10 < width"),
        ("short_data", r"inconsistent steps.*needs"),
    ],
)
def test_bad_clouds_are_clear_errors_and_stream_goes_on(tmp_path, body, match):
    fields, step, big = LAYOUTS["velodyne"]
    pts = random_points(20)
    data, width, _ = cloud_bytes(pts, fields, step, big)
    bad = {
        "no_xyz": r1_cloud(0.5, data, [("a", 0, F32), ("b", 4, F32)], step, big, width),
        "short_row_step": r1_cloud(0.5, data, fields, step, big, width, row_step=10),
        "short_data": r1_cloud(0.5, data[:-5], fields, step, big, width),
    }[body]
    log, _ = ros1_log(tmp_path, n_clouds=4, bad={2: bad})
    (check,) = [c for c in decod_rs.check_log(log) if c.topic == "/velodyne_points"]
    assert (check.messages, check.decoded, check.ok) == (4, 3, False)
    assert check.first_error is not None and re.search(match, check.first_error)
    reader = decod_rs.read_log(log)
    got = [next(reader), next(reader)]
    with pytest.raises(
        decod_rs.LogFormatError,
        match=r"r1\.mcap \[topic /velodyne_points\]: message at log time 1\.0.*" + match,
    ):
        next(reader)
    got.append(next(reader))  # a bad message does not end the stream
    assert len(got) == 3 and list(reader) == []


# --- inspect and convert ---------------------------------------------------------------
def test_inspect_cli_table(tmp_path, capsys):
    log, _ = ros1_log(tmp_path)
    info = decod_rs.inspect_log(log)
    assert {t.topic: t.count for t in info.topics} == {"/odom": 21, "/velodyne_points": 8}
    assert (
        info.topics[1].message_type == "sensor_msgs/PointCloud2"
        and info.topics[1].encoding == "ros1"
    )
    assert info.start == pytest.approx(0.0) and info.end == pytest.approx(2.0)
    assert cli_main(["inspect", str(log)]) == 0
    out = capsys.readouterr().out
    assert "/velodyne_points" in out and "29 messages, 2.000 s" in out
    assert cli_main(["inspect", str(tmp_path / "nope.mcap")]) == 2


def test_convert_ros1_bag_to_mcap_and_read_back(tmp_path, capsys):
    from rosbags.rosbag1 import Writer as Bag1Writer

    store = get_typestore(Stores.ROS1_NOETIC)
    T = store.types
    fields, step, big = LAYOUTS["xyz_f32_intensity"]
    bag = tmp_path / "in.bag"
    clouds = {t: random_points(25) for t in CLOUD_STAMPS[:3]}

    def header(t: float, frame: str):
        sec = int(np.floor(t))
        return T["std_msgs/msg/Header"](
            seq=0,
            stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=round((t - sec) * NS)),
            frame_id=frame,
        )

    with Bag1Writer(bag) as w:
        cc = w.add_connection("/points", "sensor_msgs/msg/PointCloud2", typestore=store)
        oc = w.add_connection("/pose", "geometry_msgs/msg/PoseStamped", typestore=store)
        for t in ODOM_STAMPS:
            tx, ty, tz = pose_at(t)[:3, 3]
            qx, qy, qz, qw = quat_at(t)
            msg = T["geometry_msgs/msg/PoseStamped"](
                header=header(t, "map"),
                pose=T["geometry_msgs/msg/Pose"](
                    position=T["geometry_msgs/msg/Point"](x=tx, y=ty, z=tz),
                    orientation=T["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
                ),
            )
            w.write(oc, round(t * NS), store.serialize_ros1(msg, "geometry_msgs/msg/PoseStamped"))
        for t, pts in clouds.items():
            data, width, row_step = cloud_bytes(pts, fields, step, big)
            msg = T["sensor_msgs/msg/PointCloud2"](
                header=header(t, "lidar"),
                height=1,
                width=width,
                fields=[
                    T["sensor_msgs/msg/PointField"](name=n, offset=o, datatype=d, count=1)
                    for n, o, d in fields
                ],
                is_bigendian=False,
                point_step=step,
                row_step=row_step,
                data=np.frombuffer(data, dtype=np.uint8),
                is_dense=True,
            )
            w.write(cc, round(t * NS), store.serialize_ros1(msg, "sensor_msgs/msg/PointCloud2"))
    out = tmp_path / "out"
    assert cli_main(["convert", str(bag), str(out)]) == 0
    printed = capsys.readouterr().out
    assert "MCAP" in printed and "/points" in printed
    assert "verified: 24/24 messages of supported types decoded, 75 points" in printed
    assert list(out.glob("*.mcap")) and (out / "metadata.yaml").exists()
    info = decod_rs.inspect_log(out)
    assert {t.topic: t.encoding for t in info.topics} == {"/points": "cdr", "/pose": "cdr"}
    scans = list(decod_rs.read_log(out))
    assert len(scans) == 3
    for s in scans:
        np.testing.assert_array_equal(s.points, clouds[min(clouds, key=lambda c: abs(c - s.stamp))])
        np.testing.assert_allclose(s.pose, pose_at(s.stamp), atol=1e-9)
    assert cli_main(["convert", str(bag), str(out)]) == 2  # refuses to overwrite


def test_ros1_tf_message_odometry_needs_one_chain(tmp_path):
    fields, step, big = LAYOUTS["velodyne"]
    data, width, _ = cloud_bytes(random_points(4), fields, step, big)
    topics = {"/velodyne_points": "sensor_msgs/PointCloud2", "/tf": "tf2_msgs/TFMessage"}

    def tf(t: float, children: list[str]) -> bytes:
        body = struct.pack("<I", len(children))
        for child in children:
            body += r1_header(t, "map") + r1_string(child) + r1_pose(t)
        return body

    cloud = ("/velodyne_points", 0.71, r1_cloud(0.71, data, fields, step, big, width))
    log = write_ros1_mcap(
        tmp_path / "one.mcap", topics, [cloud, *[("/tf", t, tf(t, ["base"])) for t in ODOM_STAMPS]]
    )
    (scan,) = list(decod_rs.read_log(log))
    np.testing.assert_allclose(scan.pose, pose_at(0.71), atol=1e-9)
    msgs = [cloud, *[("/tf", t, tf(t, ["base", "wheel"])) for t in ODOM_STAMPS]]
    log = write_ros1_mcap(tmp_path / "two.mcap", topics, msgs)
    with pytest.raises(
        decod_rs.TopicError, match=r"`/tf` carries several transforms.*map -> base, map -> wheel"
    ):
        decod_rs.read_log(log, odom="/tf")


def test_not_a_log_and_empty_logs(tmp_path):
    bag = tmp_path / "in.bag"
    bag.write_bytes(b"#ROSBAG V1.2\n" + bytes(200))
    with pytest.raises(decod_rs.LogFormatError, match=r"in\.bag: ROS bag version .*V1\.2"):
        decod_rs.read_log(bag)
    text = tmp_path / "notes.mcap"
    text.write_bytes(b"hello, this is not a log")
    with pytest.raises(decod_rs.LogFormatError, match=r"notes\.mcap: not an MCAP file"):
        decod_rs.read_log(text)
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    with pytest.raises(decod_rs.LogFormatError, match=r"empty\.mcap: truncated"):
        decod_rs.read_log(empty)
    (tmp_path / "bag2").mkdir()
    (tmp_path / "bag2" / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    with pytest.raises(decod_rs.LogFormatError, match=r"bag2: no \.mcap or \.db3 file"):
        decod_rs.read_log(tmp_path / "bag2")


def test_convert_livox_ros1_bag(tmp_path):
    """GEODE's case: a ROS 1 bag whose lidar publishes only Livox CustomMsg."""
    from rosbags.rosbag1 import Writer as Bag1Writer

    store = get_typestore(Stores.ROS1_NOETIC)
    types = {}
    for name, text in LIVOX_MSGS.items():
        msgdef = text.format(pkg="livox_ros_driver")
        types.update(get_types_from_msg(msgdef, f"livox_ros_driver/msg/{name}"))
    store.register(types)
    T = store.types
    pts = random_points(9)
    stamp = T["builtin_interfaces/msg/Time"](sec=0, nanosec=500_000_000)
    msg = T["livox_ros_driver/msg/CustomMsg"](
        header=T["std_msgs/msg/Header"](seq=1, stamp=stamp, frame_id="livox"),
        timebase=500_000_000,
        point_num=9,
        lidar_id=0,
        rsvd=np.zeros(3, np.uint8),
        points=[
            T["livox_ros_driver/msg/CustomPoint"](
                offset_time=k, x=p[0], y=p[1], z=p[2], reflectivity=1, tag=0, line=0
            )
            for k, p in enumerate(pts)
        ],
    )
    bag = tmp_path / "livox.bag"
    with Bag1Writer(bag) as w:
        conn = w.add_connection("/livox/lidar", "livox_ros_driver/msg/CustomMsg", typestore=store)
        w.write(conn, 500_000_000, store.serialize_ros1(msg, "livox_ros_driver/msg/CustomMsg"))
    assert cli_main(["convert", str(bag), str(tmp_path / "out")]) == 0
    tum = tmp_path / "odom.tum"
    tum.write_text("0 0 0 0 0 0 0 1\n1 2 0 0 0 0 0 1\n")
    (scan,) = list(decod_rs.read_log(tmp_path / "out", odom_tum=tum))
    np.testing.assert_array_equal(scan.points, pts)
    np.testing.assert_allclose(scan.pose[:3, 3], [1.0, 0.0, 0.0], atol=1e-12)


@pytest.mark.parametrize("outside", [False, True])
def test_auto_probe_keeps_the_windows_of_the_scans_that_pair_with_odometry(tmp_path, outside):
    """The auto probe keeps only its windows' scans; they are the windows it would cut from
    every scan read, also when clouds outside the odometry make the log announce more scans
    than pair (it plans on the announced count, then reads again with the real one)."""
    from decod_rs.autoscale import PROBE_SCANS, _probe_starts, _read_probe_scans

    store = ros2_store()
    fields, step, big = LAYOUTS["xyz_f32_intensity"]
    stamps = [0.05 + 0.07 * k for k in range(27)] + ([-0.5, -0.3, 2.5, 2.7] if outside else [])
    msgs = odometry_messages(store)
    for t in stamps:
        data, width, row_step = cloud_bytes(random_points(5), fields, step, big)
        msgs.append(
            (
                "/points",
                t + 10 if t < 0 else t,
                ros2_cloud(store, t, data, fields, step, big, width, 1, row_step),
            )
        )
    log = write_ros2(tmp_path / "bag", store, ROS2_TOPICS, msgs)
    every = list(decod_rs.read_log(log))
    assert len(every) == 27 and decod_rs.read_log(log).total_scans_hint == len(stamps)

    windows, read, odometry, imu = _read_probe_scans(log, None, None, None, None)

    np.testing.assert_array_equal(read, [s.stamp for s in every])
    expected = [every[s : s + PROBE_SCANS] for s in _probe_starts(len(every))]
    assert len(windows) == len(expected) == 4
    for got, want in zip(windows, expected, strict=True):
        assert [s.stamp for s in got] == [s.stamp for s in want]
        for a, b in zip(got, want, strict=True):
            np.testing.assert_array_equal(a.points, b.points)
    assert odometry.shape == (len(ODOM_STAMPS), 8) and imu is None
