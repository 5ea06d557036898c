"""Real logs as they come (issue 11): cut-off and corrupt files, odometry gaps, backwards
stamps, ROS 1 bags and sqlite3 bags read natively, bad clouds.

Every log is built here (rosbags, the mcap writer, byte surgery), a few kB each. Each case
checks the message (file, topic, time), the partial result, and that nothing hangs or
panics (a Rust panic would surface as ``InternalError``).
"""

from __future__ import annotations

import struct
import warnings
from pathlib import Path

import numpy as np
import pytest
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from rosbags.rosbag1 import Writer as Bag1Writer
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Bag2Writer
from test_io import (
    LAYOUTS,
    NS,
    ODOM_STAMPS,
    R1_SCHEMAS,
    R1_TOPICS,
    cloud_bytes,
    odometry_messages,
    pose_at,
    r1_cloud,
    r1_header,
    r1_livox,
    r1_odometry,
    ros1_log,
    ros2_cloud,
    ros2_header,
    ros2_store,
    write_ros1_mcap,
)

import decod_rs
from decod_rs.cli import main as cli_main

RNG = np.random.default_rng(11)


def random_points(n: int) -> np.ndarray:
    return RNG.uniform(-20, 20, size=(n, 3)).astype(np.float32)


def bag_chunks(raw: bytes) -> list[tuple[int, int]]:
    """``(offset, length)`` of the data of every chunk record of a ROS 1 bag."""
    out, at = [], 13
    while at + 4 <= len(raw):
        hlen = struct.unpack_from("<I", raw, at)[0]
        header = raw[at + 4 : at + 4 + hlen]
        dlen = struct.unpack_from("<I", raw, at + 4 + hlen)[0]
        if b"op=\x05" in header:
            out.append((at + 8 + hlen, dlen))
        at += 8 + hlen + dlen
    return out


def read_all(
    log: Path, **kwargs: object
) -> tuple[list[decod_rs.io.ScanRecord], decod_rs.StreamHealth]:
    """Every scan of ``log`` (undecodable messages skipped as ``decod run`` does, warnings
    silenced) and the stream's health."""
    reader = decod_rs.read_log(log, **kwargs)  # type: ignore[arg-type]
    scans = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", decod_rs.LogWarning)
        while True:
            try:
                scans.append(next(reader))
            except StopIteration:
                break
            except decod_rs.LogFormatError:
                continue  # named in health.message_errors; the stream goes on
    return scans, reader.health


def read_partial(log: Path, **kwargs: object) -> tuple[list, list[decod_rs.LogFaultInfo]]:
    """Like :func:`read_all` for a damaged log; a cut before the topics or the odometry is
    an error that names the file and the damage (then no scan)."""
    try:
        scans, health = read_all(log, **kwargs)
    except decod_rs.LogFormatError as exc:
        assert str(log) in str(exc) and "truncated" in str(exc), str(exc)
        return [], []
    assert health.faults and health.faults[0].message.startswith(str(log))
    return scans, health.faults


def assert_same_clouds(scans: list, clouds: dict[float, np.ndarray]) -> None:
    for s in scans:
        np.testing.assert_array_equal(s.points, clouds[min(clouds, key=lambda c: abs(c - s.stamp))])


# --- cut-off and corrupt MCAP --------------------------------------------------------------
def test_mcap_cut_at_many_offsets_keeps_every_complete_message(tmp_path: Path) -> None:
    log, clouds = ros1_log(tmp_path, n_clouds=10, chunk_size=4096)
    raw = log.read_bytes()
    full, _ = read_all(log)
    assert len(full) == len(clouds)
    summary_start = raw.rfind(b"\x0f" + struct.pack("<Q", 4))  # DataEnd: the summary follows
    cuts = sorted(
        {0, 5, 8, 12, 30, *range(200, summary_start, max(1, summary_start // 23))}
        | {summary_start + 20, len(raw) - 30, len(raw) - 4}
    )
    previous = 0
    cut_log = tmp_path / "cut.mcap"
    for cut in cuts:
        cut_log.write_bytes(raw[:cut])
        scans, faults = read_partial(cut_log)
        assert len(scans) >= previous, cut  # a longer file never yields fewer scans
        previous = len(scans)
        assert_same_clouds(scans, clouds)
        if not faults:
            continue
        (fault,) = faults
        assert fault.kind == "truncated" and fault.offset <= cut, (cut, fault)
        info = decod_rs.inspect_log(cut_log)
        assert info.problem is not None or cut > summary_start
        if cut > summary_start + 20:  # inside the summary: nothing lost
            assert len(scans) == len(clouds) and fault.messages_lost == 0


def test_flipped_byte_in_an_uncompressed_record_and_length_past_the_end(tmp_path: Path) -> None:
    fields, step, big = LAYOUTS["velodyne"]
    clouds, msgs = {}, [("/odom", t, r1_odometry(t)) for t in ODOM_STAMPS]
    for t in (0.1, 0.4, 0.7, 1.0, 1.3, 1.6):
        clouds[t] = random_points(50)
        data, width, _ = cloud_bytes(clouds[t], fields, step, big)
        msgs.append(("/velodyne_points", t, r1_cloud(t, data, fields, step, big, width)))
    log = tmp_path / "flat.mcap"
    with log.open("wb") as f:  # no chunks: records stand alone, without CRC
        w = McapWriter(f, use_chunking=False)
        w.start(profile="ros1")
        ids = {}
        for topic, ty in R1_TOPICS.items():
            sid = w.register_schema(ty, "ros1msg", R1_SCHEMAS[ty].encode())
            ids[topic] = w.register_channel(topic, "ros1", sid)
        for seq, (topic, t, data) in enumerate(sorted(msgs, key=lambda m: m[1])):
            w.add_message(ids[topic], round(t * NS), data, round(t * NS), seq)
        w.finish()
    raw = bytearray(log.read_bytes())
    # The width field of the 4th cloud: width * height no longer matches its data.
    at = raw.find(r1_header(1.0, "lidar") + struct.pack("<II", 1, 50))
    assert at > 0
    raw[at + 21 + 4] ^= 0x40
    bad = tmp_path / "flipped.mcap"
    bad.write_bytes(bytes(raw))
    reader = decod_rs.read_log(bad)
    got = [next(reader) for _ in range(3)]
    with pytest.raises(
        decod_rs.LogFormatError,
        match=r"flipped\.mcap \[topic /velodyne_points\]: message at log time 1\.0+ s: "
        r"inconsistent steps",
    ):
        next(reader)
    got.extend(reader)  # the stream goes on after the bad message
    assert len(got) == 5 and reader.health.clouds["undecodable"] == 1
    # The length of the 5th cloud's record now points far past the end of the file.
    raw = bytearray(log.read_bytes())
    record = raw.find(r1_header(1.3, "lidar")) - 31  # opcode, length, message header
    assert raw[record] == 0x05
    raw[record + 1 : record + 9] = struct.pack("<Q", 1 << 29)
    past = tmp_path / "past.mcap"
    past.write_bytes(bytes(raw))
    scans, health = read_all(past)
    (fault,) = health.faults
    assert fault.kind == "truncated" and "claims 536870912 bytes" in fault.reason
    assert fault.last_complete_s is not None and len(scans) == 4


def test_corrupt_compressed_chunk_costs_only_its_messages(tmp_path: Path) -> None:
    fields, step, big = LAYOUTS["velodyne"]
    clouds, msgs = {}, [("/odom", t, r1_odometry(t)) for t in ODOM_STAMPS]
    for k in range(8):
        t = 0.05 + 0.24 * k
        clouds[t] = random_points(300)
        data, width, _ = cloud_bytes(clouds[t], fields, step, big)
        msgs.append(("/velodyne_points", t, r1_cloud(t, data, fields, step, big, width)))
    for compression in (CompressionType.ZSTD, CompressionType.LZ4):
        log = write_ros1_mcap(tmp_path / "c.mcap", R1_TOPICS, msgs, 4096, compression)
        raw = bytearray(log.read_bytes())
        chunks = mcap_chunks(bytes(raw))
        assert len(chunks) > 4
        raw[chunks[len(chunks) // 2] + 10 : chunks[len(chunks) // 2] + 26] = bytes(16)
        log.write_bytes(bytes(raw))
        scans, health = read_all(log)
        (fault,) = health.faults
        assert fault.kind == "corrupt" and fault.lost_span_s is not None
        lost = fault.messages_lost or 0
        assert 0 < lost and len(scans) >= len(clouds) - lost
        assert_same_clouds(scans, clouds)
        assert scans[-1].stamp == pytest.approx(max(clouds))  # read on after the bad chunk


def mcap_chunks(raw: bytes) -> list[int]:
    """Byte offsets of the compressed data of every chunk record of an MCAP file."""
    out, at = [], 8
    while at + 9 <= len(raw):
        opcode, length = raw[at], struct.unpack_from("<Q", raw, at + 1)[0]
        if opcode == 0x06:
            name_len = struct.unpack_from("<I", raw, at + 9 + 28)[0]
            out.append(at + 9 + 28 + 4 + name_len + 8)
        at += 9 + length
    return out


# --- odometry gaps and stamps ---------------------------------------------------------------
def test_odometry_gap_is_not_interpolated_and_scans_in_it_are_listed(tmp_path: Path) -> None:
    odom = [t for t in ODOM_STAMPS if not 0.75 < t < 1.45]  # 0.8 s missing, period 0.1 s
    fields, step, big = LAYOUTS["velodyne"]
    clouds, msgs = {}, [("/odom", t, r1_odometry(t)) for t in odom]
    for k in range(10):
        t = 0.05 + 0.19 * k
        clouds[t] = random_points(20)
        data, width, _ = cloud_bytes(clouds[t], fields, step, big)
        msgs.append(("/velodyne_points", t, r1_cloud(t, data, fields, step, big, width)))
    log = write_ros1_mcap(tmp_path / "gap.mcap", R1_TOPICS, msgs)
    scans, health = read_all(log)
    assert health.gaps == [(pytest.approx(0.7), pytest.approx(1.5), "gap")]
    inside = [t for t in clouds if 0.7 < t < 1.5]
    assert health.skipped_in_gaps == pytest.approx(inside) and inside
    assert len(scans) == len(clouds) - len(inside)
    for s in scans:
        np.testing.assert_allclose(s.pose, pose_at(s.stamp), atol=1e-9)
    # A bound of 0 interpolates across anything (the behaviour before issue 11).
    scans, health = read_all(log, gap_periods=0.0)
    assert len(scans) == len(clouds) and not health.gaps


def test_backwards_and_duplicated_stamps_are_left_out_never_reordered(tmp_path: Path) -> None:
    odom = [*ODOM_STAMPS[:8], 0.55, *ODOM_STAMPS[8:14], ODOM_STAMPS[13], *ODOM_STAMPS[14:]]
    fields, step, big = LAYOUTS["velodyne"]
    cloud_stamps = [0.05, 0.25, 0.45, 0.42, 0.65, 0.85, 0.85, 1.65, 1.85]
    msgs = [("/odom", t, r1_odometry(t)) for t in odom]
    msgs = [(topic, 0.01 * k, body) for k, (topic, _, body) in enumerate(msgs)]  # record order
    for k, t in enumerate(cloud_stamps):
        data, width, _ = cloud_bytes(random_points(10), fields, step, big)
        msgs.append(
            ("/velodyne_points", 0.3 + 0.01 * k, r1_cloud(t, data, fields, step, big, width))
        )
    log = write_ros1_mcap(tmp_path / "order.mcap", R1_TOPICS, msgs)
    scans, health = read_all(log)
    kinds = [(round(a, 3), round(b, 3), kind) for a, b, kind in health.gaps]
    assert kinds == [(0.5, 0.8, "backwards"), (1.3, 1.4, "duplicate")]
    assert health.out_of_order == [pytest.approx((0.42, 0.45)), pytest.approx((0.85, 0.85))]
    assert health.clouds["out_of_order"] == 2 and health.skipped_in_gaps == [0.65]
    assert [s.stamp for s in scans] == pytest.approx([0.05, 0.25, 0.45, 0.85, 1.65, 1.85])


# --- ROS 1 bags and sqlite3 bags, natively -------------------------------------------------
def write_bag(
    path: Path, messages: list[tuple[str, float, bytes]], types: dict[str, str], fmt: str
) -> Path:
    """A ROS 1 bag of raw ROS 1 messages; ``fmt``: none, bz2 or lz4 chunks of ~4 kB."""
    w = Bag1Writer(path)
    if fmt != "none":
        w.set_compression(getattr(Bag1Writer.CompressionFormat, fmt.upper()))
    w.chunk_threshold = 4096
    with w:
        conns = {
            topic: w.add_connection(
                topic, ty.replace("/", "/msg/", 1), msgdef=R1_SCHEMAS[ty], md5sum="0" * 32
            )
            for topic, ty in types.items()
        }
        for topic, t, data in sorted(messages, key=lambda m: m[1]):
            w.write(conns[topic], round(t * NS), data)
    return path


def ros1_corpus(livox: bool) -> tuple[list[tuple[str, float, bytes]], dict[str, str]]:
    fields, step, big = LAYOUTS["ouster"]
    topic, ty = (
        ("/livox/lidar", "livox_ros_driver/CustomMsg")
        if livox
        else ("/points", "sensor_msgs/PointCloud2")
    )
    msgs = [("/odom", t, r1_odometry(t)) for t in ODOM_STAMPS]
    for k in range(12):
        t = 0.05 + 0.16 * k
        pts = random_points(150)
        if livox:
            body = r1_livox(t, pts)
        else:
            data, width, _ = cloud_bytes(pts, fields, step, big)
            body = r1_cloud(t, data, fields, step, big, width)
        msgs.append((topic, t, body))
    return msgs, {topic: ty, "/odom": "nav_msgs/Odometry"}


def assert_same_logs(a: Path, b: Path) -> None:
    """``b`` reads message for message like ``a``: scans, summary, verification."""
    scans_a, health_a = read_all(a)
    scans_b, health_b = read_all(b)
    assert len(scans_a) == len(scans_b) > 0
    for x, y in zip(scans_a, scans_b, strict=True):
        assert x.stamp == y.stamp
        np.testing.assert_array_equal(x.points, y.points)
        np.testing.assert_array_equal(x.pose, y.pose)
    assert not health_a.faults and not health_b.faults
    ia, ib = decod_rs.inspect_log(a), decod_rs.inspect_log(b)
    assert [(t.topic, t.count) for t in ia.topics] == [(t.topic, t.count) for t in ib.topics]
    assert (ia.start, ia.end) == (ib.start, ib.end) and ib.problem is None
    ca, cb = decod_rs.check_log(a), decod_rs.check_log(b)
    assert [(c.topic, c.decoded, c.points) for c in ca] == [
        (c.topic, c.decoded, c.points) for c in cb
    ]


@pytest.mark.parametrize("livox", [False, True], ids=["pointcloud2", "livox"])
@pytest.mark.parametrize("fmt", ["none", "bz2", "lz4"])
def test_ros1_bag_reads_like_mcap(tmp_path: Path, fmt: str, livox: bool) -> None:
    msgs, types = ros1_corpus(livox)
    mcap = write_ros1_mcap(tmp_path / "ref.mcap", types, msgs)
    bag = write_bag(tmp_path / "log.bag", msgs, types, fmt)
    assert_same_logs(mcap, bag)
    assert cli_main(["inspect", str(bag)]) == 0


@pytest.mark.parametrize("fmt", ["none", "lz4"])
def test_cut_and_corrupt_bags_keep_what_they_can(tmp_path: Path, fmt: str) -> None:
    msgs, types = ros1_corpus(False)
    bag = write_bag(tmp_path / "log.bag", msgs, types, fmt)
    raw = bytearray(bag.read_bytes())
    full, _ = read_all(bag)
    cut = tmp_path / "cut.bag"
    previous = 0
    for end in range(13, len(raw), len(raw) // 17):
        cut.write_bytes(bytes(raw[:end]))
        scans, faults = read_partial(cut)
        assert len(scans) >= previous and len(scans) <= len(full)
        previous = len(scans)
        assert not faults or faults[0].kind == "truncated", end
    # A chunk's data garbled: that chunk's messages are lost (counted from the index).
    chunks = bag_chunks(bytes(raw))
    assert len(chunks) > 3
    data_at = chunks[1][0] + chunks[1][1] // 2  # the middle of the second chunk's data
    raw[data_at : data_at + 8] = b"\xff" * 8
    bad = tmp_path / "bad.bag"
    bad.write_bytes(bytes(raw))
    scans, health = read_all(bad)
    if fmt == "lz4":
        (fault,) = health.faults
        assert fault.kind == "corrupt" and (fault.messages_lost or 0) > 0
        assert scans and scans[-1].stamp == full[-1].stamp
    else:  # uncompressed: no CRC, the garbled bytes land in a record (named, skipped)
        assert len(scans) >= len(full) - 2


def ros2_livox(store: object, t: float, pts: np.ndarray) -> object:
    T = store.types  # type: ignore[attr-defined]
    return T["livox_ros_driver2/msg/CustomMsg"](
        header=ros2_header(store, t, "livox"),
        timebase=round(t * NS),
        point_num=len(pts),
        lidar_id=1,
        rsvd=np.zeros(3, dtype=np.uint8),
        points=[
            T["livox_ros_driver2/msg/CustomPoint"](
                offset_time=k, x=p[0], y=p[1], z=p[2], reflectivity=9, tag=0, line=k % 4
            )
            for k, p in enumerate(pts)
        ],
    )


@pytest.mark.parametrize("livox", [False, True], ids=["pointcloud2", "livox"])
def test_db3_reads_like_mcap(tmp_path: Path, livox: bool) -> None:
    store = ros2_store("livox_ros_driver2")
    fields, step, big = LAYOUTS["xyz_f32_intensity"]
    cloud_type = "livox_ros_driver2/msg/CustomMsg" if livox else "sensor_msgs/msg/PointCloud2"
    topics = {"/points": cloud_type, "/odom": "nav_msgs/msg/Odometry"}
    msgs: list[tuple[str, float, object]] = list(odometry_messages(store))
    for k in range(9):
        t = 0.1 + 0.2 * k
        pts = random_points(80)
        if livox:
            msgs.append(("/points", t, ros2_livox(store, t, pts)))
        else:
            data, width, row_step = cloud_bytes(pts, fields, step, big)
            msgs.append(
                ("/points", t, ros2_cloud(store, t, data, fields, step, big, width, 1, row_step))
            )
    paths = {}
    for name, plugin in (("mcap", StoragePlugin.MCAP), ("db3", StoragePlugin.SQLITE3)):
        paths[name] = tmp_path / name
        with Bag2Writer(paths[name], version=8, storage_plugin=plugin) as w:
            conns = {t: w.add_connection(t, ty, typestore=store) for t, ty in topics.items()}
            for topic, t, msg in sorted(msgs, key=lambda m: m[1]):
                w.write(conns[topic], round(t * NS), store.serialize_cdr(msg, topics[topic]))
    assert_same_logs(paths["mcap"], paths["db3"])
    (db3,) = paths["db3"].glob("*.db3")
    assert_same_logs(paths["mcap"], db3)  # the file alone, too
    assert cli_main(["inspect", str(db3)]) == 0


def test_damaged_db3_is_a_fault_not_a_crash(tmp_path: Path) -> None:
    store = ros2_store()
    topics = {"/odom": "nav_msgs/msg/Odometry"}
    with Bag2Writer(tmp_path / "b", version=8, storage_plugin=StoragePlugin.SQLITE3) as w:
        conn = w.add_connection("/odom", topics["/odom"], typestore=store)
        for _, t, msg in odometry_messages(store) * 40:
            w.write(conn, round(t * NS), store.serialize_cdr(msg, topics["/odom"]))
    (db3,) = (tmp_path / "b").glob("*.db3")
    raw = db3.read_bytes()
    db3.write_bytes(raw[: len(raw) // 2])
    try:
        info = decod_rs.inspect_log(db3)
    except decod_rs.LogFormatError as exc:  # SQLite refuses the file as a whole
        assert "b_0.db3" in str(exc) or str(db3) in str(exc)
    else:
        assert info.problem is not None or sum(t.count for t in info.topics) <= 21 * 40


def test_unusable_clouds_are_counted_per_topic(tmp_path: Path) -> None:
    fields, step, big = LAYOUTS["velodyne"]
    some_nan = random_points(5)
    some_nan[[1, 3], 2] = np.nan
    clouds = {
        0.1: random_points(10),
        0.3: np.zeros((0, 3), np.float32),  # zero-size (width 0)
        0.5: np.full((4, 3), np.inf, np.float32),  # every point non-finite
        0.7: some_nan,
        1.1: random_points(10),
    }
    msgs = [("/odom", t, r1_odometry(t)) for t in ODOM_STAMPS]
    for t, pts in clouds.items():
        data, width, _ = cloud_bytes(pts, fields, step, big)
        msgs.append(("/velodyne_points", t, r1_cloud(t, data, fields, step, big, width)))
    # A field beyond point_step: z at offset step - 2.
    data, width, _ = cloud_bytes(random_points(3), fields, step, big)
    beyond = [(n, step - 2 if n == "z" else o, d) for n, o, d in fields]
    msgs.append(("/velodyne_points", 0.9, r1_cloud(0.9, data, beyond, step, big, width)))
    log = write_ros1_mcap(tmp_path / "bad.mcap", R1_TOPICS, msgs)
    scans, health = read_all(log)
    assert [len(s.points) for s in scans] == [10, 0, 0, 3, 10]
    assert health.clouds == {
        "messages": 6,
        "undecodable": 1,
        "zero_size": 1,
        "empty": 1,
        "non_finite_points": 6,
        "out_of_order": 0,
        # Velodyne's `time` read on the three clouds with points (all 0 here: no change).
        "deskewed": 3,
        "times_unused": 0,
    }
    (error,) = health.message_errors
    assert str(log) in error and "[topic /velodyne_points]" in error
    assert "log time 0.900000000 s" in error and "overruns point_step" in error
