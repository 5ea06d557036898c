"""Reading logs: scans paired with odometry, log summaries, TUM files.

The Rust core (``decod::io``) decodes ROS 2 (CDR) and ROS 1 messages from MCAP files, ROS 1
``.bag`` files (format 2.0; chunks uncompressed, bz2 or lz4), rosbag2 sqlite3 ``.db3`` files
and rosbag2 directories (MCAP or sqlite3 storage) natively; this module gives it a typed,
streaming Python face. A damaged log is read as far as it goes (:mod:`decod_rs.ingest`).
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from decod_rs import _core
from decod_rs.ingest import LogWarning, StreamHealth

PathLike = str | os.PathLike[str]


@dataclass(frozen=True)
class ScanRecord:
    """One scan with its odometry pose.

    Attributes:
        stamp: header stamp of the cloud, seconds.
        points: ``(N, 3)`` float32 points in the body (cloud) frame, metres; NaN/inf dropped.
        pose: ``(4, 4)`` float64 ``T_world_body`` interpolated (SE(3)) at ``stamp``.
        specific_force: ``(3,)`` float64 mean IMU linear acceleration over the scan (m/s^2,
            body = IMU frame), or ``None`` without IMU.
    """

    stamp: float
    points: npt.NDArray[np.float32]
    pose: npt.NDArray[np.float64]
    specific_force: npt.NDArray[np.float64] | None


class ScanReader(Iterator[ScanRecord]):
    """Streams :class:`ScanRecord` from a log, one cloud decoded per step (GIL released).

    Memory is bounded by one chunk plus one cloud, not by the log. Errors name the file,
    topic and log time: a bad message raises ``LogFormatError`` and the next ``next()`` goes
    on. Damage to the log itself does not raise: every complete message before a cut is
    read, a corrupt chunk is skipped, and at the end one :class:`~decod_rs.ingest.LogWarning`
    says what was lost (:attr:`health` has the details). Clouds inside an odometry gap or
    stamped out of order are left out (:attr:`health`).
    """

    def __init__(self, inner: _core._ScanReader) -> None:
        self._inner = inner
        self._warned = False

    def __iter__(self) -> ScanReader:
        return self

    def __next__(self) -> ScanRecord:
        try:
            stamp, points, pose, force = next(self._inner)
        except StopIteration:
            faults = self.health.faults
            if faults and not self._warned:
                self._warned = True
                text = "; ".join(f.message for f in faults)
                warnings.warn(f"partial log: {text}", LogWarning, stacklevel=2)
            raise
        return ScanRecord(stamp=stamp, points=points, pose=pose, specific_force=force)

    @property
    def health(self) -> StreamHealth:
        """Damage, odometry gaps and clouds left out so far."""
        return StreamHealth.from_core(self._inner.health())

    @property
    def points_topic(self) -> str:
        """The point-cloud topic being read."""
        return self._inner.points_topic()

    @property
    def total_scans_hint(self) -> int:
        """Cloud messages on the points topic (a progress-bar total)."""
        return self._inner.total_scans_hint()

    @property
    def skipped_outside_odometry(self) -> list[float]:
        """Stamps of clouds skipped so far because they fall outside the odometry span."""
        return self._inner.skipped_outside_odometry()

    @property
    def dropped_non_finite_points(self) -> int:
        """Points dropped so far because a coordinate was NaN or infinite."""
        return self._inner.dropped_non_finite_points()

    def imu_samples(self) -> npt.NDArray[np.float64] | None:
        """The IMU samples the stream read before its first cloud, ``(N, 4)``: stamp (s) and
        specific force (m/s^2); ``None`` without an IMU. A later ``LogProcessor`` of the same
        log takes them (``imu_samples=``) instead of reading the whole file again."""
        return self._inner.imu_samples()

    def odometry(self) -> npt.NDArray[np.float64]:
        """The odometry as ``(M, 8)`` TUM rows ``stamp tx ty tz qx qy qz qw``, by stamp."""
        return self._inner.odometry()


def read_log(
    path: PathLike,
    points: str | None = None,
    odom: str | None = None,
    odom_tum: PathLike | None = None,
    imu: str | None = None,
    gap_periods: float = 5.0,
    deskew: bool = True,
) -> ScanReader:
    """Streams the scans of a log (``.mcap``, ROS 1 ``.bag``, ``.db3`` or a rosbag2
    directory) with their poses.

    Args:
        path: the log.
        points: PointCloud2 or Livox CustomMsg topic; ``None`` = the unique one.
        odom: odometry topic (Odometry, PoseStamped, TransformStamped, TFMessage); ``None``
            (and no ``odom_tum``) = the unique one.
        odom_tum: a TUM file to take odometry from instead of a topic.
        imu: sensor_msgs/Imu topic for the specific force; ``None`` = no IMU
            (:func:`find_imu_topic` finds the unique one).
        gap_periods: odometry intervals longer than this many median periods are gaps: no
            pose is interpolated inside (``submap.odometry_gap_periods``; 0: no gaps).
        deskew: each point moved to the pose at its scan's stamp by its own time, where the
            clouds carry per-point times (``submap.deskew``; ``decod_rs.deskew`` in the Rust
            crate); False: the points as the driver wrote them.

    Raises:
        TopicError: a topic is missing or ambiguous (the message lists candidates).
        UnsupportedMessageError: a topic has a type or encoding decod does not read.
        LogFormatError: a log or TUM file is malformed.
        FileNotFoundError: the log or TUM file does not exist.
    """
    tum = None if odom_tum is None else os.fspath(odom_tum)
    inner = _core.open_scan_stream(os.fspath(path), points, odom, tum, imu, gap_periods, deskew)
    return ScanReader(inner)


@dataclass(frozen=True)
class TopicInfo:
    """One topic of a log: name, message type as written, MCAP encoding, message count."""

    topic: str
    message_type: str
    encoding: str
    count: int


@dataclass(frozen=True)
class LogInfo:
    """What a log holds (``decod inspect``).

    Attributes:
        files: the files read.
        topics: topics sorted by name.
        start, end: log time of the first/last message, seconds (``None`` when empty).
        problem: why counts may be partial (truncated or corrupt file without summary).
    """

    files: list[Path]
    topics: list[TopicInfo]
    start: float | None
    end: float | None
    problem: str | None

    @property
    def duration(self) -> float:
        """``end - start`` in seconds (0 for an empty log)."""
        if self.start is None or self.end is None:
            return 0.0
        return self.end - self.start

    @property
    def message_count(self) -> int:
        """Messages over all topics."""
        return sum(t.count for t in self.topics)


def inspect_log(path: PathLike) -> LogInfo:
    """Topics, types, encodings, counts and time span of a log (``.mcap``, ``.bag``,
    ``.db3`` or a rosbag2 directory), from its index when it has one."""
    files, topics, start, end, problem = _core.inspect_log(os.fspath(path))
    return LogInfo(
        files=[Path(f) for f in files],
        topics=[TopicInfo(*row) for row in topics],
        start=start,
        end=end,
        problem=problem,
    )


@dataclass(frozen=True)
class TopicCheck:
    """One topic after reading and decoding every message (:func:`check_log`).

    Attributes:
        supported: decod decodes this type and encoding (else only counted).
        messages: messages read; ``decoded``: decoded without error.
        points: finite points over the decoded clouds (point-cloud topics).
        first_error: the first decode error, if any.
    """

    topic: str
    message_type: str
    supported: bool
    messages: int
    decoded: int
    points: int
    first_error: str | None

    @property
    def ok(self) -> bool:
        """Every message of a supported topic decoded (unsupported topics are ok)."""
        return not self.supported or self.decoded == self.messages


def check_log(path: PathLike) -> list[TopicCheck]:
    """Reads and decodes every message of a log (chunk CRCs checked); raises
    LogFormatError on a truncated or corrupt log (after reading all of it), reports decode
    failures per topic."""
    return [TopicCheck(*row) for row in _core.check_log(os.fspath(path))]


def find_imu_topic(path: PathLike) -> str | None:
    """The unique sensor_msgs/Imu topic of a log, ``None`` if none (TopicError if several)."""
    return _core.find_imu_topic(os.fspath(path))


def read_tum(path: PathLike) -> npt.NDArray[np.float64]:
    """A TUM file as ``(N, 8)`` rows ``stamp tx ty tz qx qy qz qw`` (quaternions normalised)."""
    return _core.read_tum(os.fspath(path))
