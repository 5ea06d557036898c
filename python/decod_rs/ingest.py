"""What reading a real log met (issue 11): damage to the file, odometry gaps, unusable clouds.

The Rust scan stream reads a damaged log as far as it goes (every complete message before a
cut; a corrupt chunk skipped) and never interpolates across an odometry gap or reorders
stamps; this module turns what it recorded into ``report.json``'s ``ingest`` section, warns
once, and decides how the pose graph joins the two sides of each gap:

- ``"odometry"``: the odometry's relative pose across the gap is plausible (the travel it
  implies is at most ``GAP_SPEED_FACTOR`` times the fastest normal motion over the gap's
  duration, plus ``GAP_SLACK_M``): the edge stays the odometry's, its random-walk sigma
  growing with the distance like any other edge;
- ``"weak"``: the odometry jumped across the gap (e.g. a LIO restarted in a new frame): the
  edge's sigmas are multiplied by ``WEAK_GAP_SIGMA_FACTOR``, so loops decide where the two
  sides lie and the odometry barely pulls;
- ``"none"``: the gap is before the first or after the last scan (nothing to join).
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

#: Travel across a gap is plausible up to this many times the 95th-percentile scan-to-scan
#: speed times the gap's duration (a robot may speed up, not teleport).
GAP_SPEED_FACTOR = 3.0
#: ... plus this much, metres (a robot standing still through the gap may still settle).
GAP_SLACK_M = 0.5
#: Sigma factor of the odometry edge across a gap whose relative pose is implausible: 1e3
#: turns 1 cm into 10 m, weaker than any loop factor, strong enough to keep the graph
#: connected (no gauge freedom).
WEAK_GAP_SIGMA_FACTOR = 1e3
#: Out-of-order stamps listed in the report (the rest are counted).
MAX_LISTED = 100

__all__ = [
    "LogFaultInfo",
    "LogWarning",
    "StreamHealth",
    "gap_bridges",
    "ingest_section",
    "outside_odometry",
    "unused_ends",
]


class LogWarning(UserWarning):
    """The log was damaged or had odometry gaps; the run went on (see ``report.json``)."""


@dataclass(frozen=True)
class LogFaultInfo:
    """Damage found in a log file (``decod::io::LogFault``).

    Attributes:
        file: the file at fault.
        kind: ``truncated`` (cut off: reading of the file stopped; every complete message
            before was read), ``corrupt`` (a chunk or record skipped, reading went on) or
            ``unreadable`` (reading of the file stopped).
        offset: byte offset of the record at fault (sqlite3: the last row id read).
        reason: what was wrong.
        last_complete_s: log time of the last complete message before it, seconds.
        lost_span_s: ``(start, end)`` log time lost, seconds, when the container says.
        messages_lost: messages lost, when the container says.
        message: all of it in one line, naming the file.
    """

    file: str
    kind: str
    offset: int
    reason: str
    last_complete_s: float | None
    lost_span_s: tuple[float, float] | None
    messages_lost: int | None
    message: str


@dataclass(frozen=True)
class StreamHealth:
    """What a scan stream met so far (``_core.LogProcessor.health()``).

    Attributes:
        faults: damage to the log files.
        gaps: odometry intervals ``(start_s, end_s, kind)`` not interpolated; kind is
            ``gap``, ``backwards`` or ``duplicate``.
        skipped_in_gaps: stamps of the clouds left out because they fall inside a gap.
        out_of_order: ``(stamp, previous)`` of clouds stamped at or before the scan before.
        clouds: counts on the points topic: ``messages, undecodable, zero_size, empty,
            non_finite_points, out_of_order``, and ``deskewed`` (scans moved to their stamp's
            pose by their points' times) and ``times_unused`` (scans with a time field that
            could not be used so: ``submap.deskew``).
        message_errors: undecodable messages, each naming file, topic and log time.
    """

    faults: list[LogFaultInfo]
    gaps: list[tuple[float, float, str]]
    skipped_in_gaps: list[float]
    out_of_order: list[tuple[float, float]]
    clouds: dict[str, int]
    message_errors: list[str]
    #: Stamps of the clouds before the odometry's first pose or after its last (not used).
    outside_odometry: list[float] = field(default_factory=list)

    @classmethod
    def from_core(cls, row: Any, outside_odometry: Sequence[float] = ()) -> StreamHealth:
        """From the tuple ``health()`` returns (``src/python/io.rs`` ``HealthRow``) and the
        processor's ``skipped_outside_odometry()``."""
        faults, gaps, in_gaps, order, counts, errors = row
        names = ("messages", "undecodable", "zero_size", "empty", "non_finite_points")
        return cls(
            faults=[LogFaultInfo(*f) for f in faults],
            gaps=[(float(a), float(b), str(k)) for a, b, k in gaps],
            skipped_in_gaps=[float(t) for t in in_gaps],
            out_of_order=[(float(a), float(b)) for a, b in order],
            clouds=dict(
                zip(
                    (*names, "out_of_order", "deskewed", "times_unused"),
                    (int(c) for c in counts),
                    strict=True,
                )
            ),
            message_errors=list(errors),
            outside_odometry=[float(t) for t in outside_odometry],
        )

    def problems(self) -> int:
        """Faults, gaps, undecodable and out-of-order clouds: what deserves a warning."""
        c = self.clouds
        return len(self.faults) + len(self.gaps) + c["undecodable"] + c["out_of_order"]


def _normal_speed(stamps: FloatArray, poses: FloatArray, gaps: list[tuple[float, float]]) -> float:
    """95th-percentile scan-to-scan speed (m/s) over the intervals that cross no gap."""
    if stamps.size < 2:
        return 0.0
    dt = np.diff(stamps)
    dp = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    ok = dt > 0
    for a, b in gaps:
        ok &= ~((stamps[:-1] < b) & (stamps[1:] > a))
    return float(np.percentile(dp[ok] / dt[ok], 95)) if np.any(ok) else 0.0


def gap_bridges(
    stamps: FloatArray,
    poses: FloatArray,
    gaps: list[tuple[float, float, str]],
    anchor_stamps: FloatArray | None = None,
) -> tuple[list[str], FloatArray | None]:
    """How each gap is bridged (module doc) and the per-scan sigma factors (M,) for
    ``correct_trajectory`` (None when no gap is weak). A weak gap's factor sits on the scans
    from the first after it to the first submap anchor after it (``anchor_stamps``), so the
    edge across the gap is weak at scan and at submap granularity (an edge takes the larger
    factor of its ends: the edge after that scan or anchor is weakened too)."""
    spans = [(a, b) for a, b, _ in gaps]
    speed = _normal_speed(stamps, poses, spans)
    factors = np.ones(stamps.size)
    bridges = []
    for _start, b in spans:
        after = int(np.searchsorted(stamps, b, side="left"))
        if after == 0 or after >= stamps.size:
            bridges.append("none")
            continue
        travel = float(np.linalg.norm(poses[after, :3, 3] - poses[after - 1, :3, 3]))
        limit = GAP_SPEED_FACTOR * speed * float(stamps[after] - stamps[after - 1]) + GAP_SLACK_M
        if travel <= limit:
            bridges.append("odometry")
        else:
            bridges.append("weak")
            last = after
            if anchor_stamps is not None:
                later = np.asarray(anchor_stamps, dtype=np.float64)
                later = later[later >= stamps[after]]
                if later.size:
                    last = int(np.searchsorted(stamps, later.min(), side="left"))
            factors[after : last + 1] = WEAK_GAP_SIGMA_FACTOR
    return bridges, (factors if np.any(factors != 1.0) else None)


def ingest_section(
    health: StreamHealth,
    points_topic: str,
    scans: tuple[FloatArray, FloatArray],
    gap_periods: float,
    anchor_stamps: FloatArray | None = None,
) -> tuple[dict[str, Any], FloatArray | None]:
    """``report.json``'s ``ingest`` section and the gap sigma factors (see
    :func:`gap_bridges`) from a stream's health and the scan odometry it yielded."""
    bridges, factors = gap_bridges(scans[0], scans[1], health.gaps, anchor_stamps)
    skipped = np.asarray(health.skipped_in_gaps, dtype=np.float64)
    gaps = [
        {
            "start_s": a,
            "end_s": b,
            "duration_s": b - a,
            "kind": kind,
            "scans_skipped": int(np.sum((skipped > a) & (skipped < b))),
            "bridge": bridge,
        }
        for (a, b, kind), bridge in zip(health.gaps, bridges, strict=True)
    ]
    section = {
        "complete": not health.faults,
        "faults": [
            {
                "file": f.file,
                "kind": f.kind,
                "byte_offset": f.offset,
                "reason": f.reason,
                "last_complete_log_time_s": f.last_complete_s,
                "lost_log_time_s": None if f.lost_span_s is None else list(f.lost_span_s),
                "messages_lost": f.messages_lost,
            }
            for f in health.faults
        ],
        "odometry_gap_periods": gap_periods,
        "odometry_gaps": gaps,
        "scans_skipped_in_gaps": len(health.skipped_in_gaps),
        "scans_outside_odometry": outside_odometry(health.outside_odometry, scans[0]),
        "out_of_order_scans": [
            {"stamp": t, "previous_stamp": p} for t, p in health.out_of_order[:MAX_LISTED]
        ],
        "clouds": {points_topic: health.clouds},
        "message_errors": health.message_errors,
    }
    return section, factors


def outside_odometry(outside: Sequence[float], scan_stamps: FloatArray) -> dict[str, Any]:
    """``ingest.scans_outside_odometry``: the clouds before the first scan paired with
    odometry and after the last (``clouds``; ``span_s``: their first and last stamps,
    ``None`` when there are none). Clouds inside the span but in a gap are the gaps'."""
    t = np.sort(np.asarray(outside, dtype=np.float64))
    stamps = np.asarray(scan_stamps, dtype=np.float64)
    first = stamps[0] if stamps.size else np.inf
    last = stamps[-1] if stamps.size else np.inf
    ends = {"before": t[t < first], "after": t[t > last]}
    return {
        side: {
            "clouds": int(v.size),
            "span_s": [float(v[0]), float(v[-1])] if v.size else None,
        }
        for side, v in ends.items()
    }


def unused_ends(section: dict[str, Any], scan_stamps: FloatArray, gap_periods: float) -> list[str]:
    """What :func:`outside_odometry` found that deserves a warning, one phrase per end: a
    stretch of clouds without odometry before its first pose or after its last that lasts as
    long as an odometry gap would (``submap.odometry_gap_periods`` scan periods; a cloud or
    two before the odometry starts is how logs begin, not lost data)."""
    stamps = np.asarray(scan_stamps, dtype=np.float64)
    period = float(np.median(np.diff(stamps))) if stamps.size > 1 else 0.0
    phrases = []
    for side, pose in (("before", "first"), ("after", "last")):
        end = section[side]
        if not end["clouds"]:
            continue
        a, b = end["span_s"]
        if stamps.size:  # from the first unused cloud to the first used scan, or likewise
            lasting = float(stamps[0]) - a if side == "before" else b - float(stamps[-1])
        else:
            lasting = b - a
        if lasting >= gap_periods * period:
            phrases.append(
                f"{end['clouds']} clouds {side} the odometry's {pose} pose "
                f"({a:.3f}-{b:.3f} s, {lasting:.1f} s) were not used"
            )
    return phrases


def warn_once(
    log: object,
    health: StreamHealth,
    scan_stamps: FloatArray | None = None,
    gap_periods: float = 5.0,
) -> None:
    """One :class:`LogWarning` summing up what the log had, if it had anything (with the
    scans used, ``scan_stamps``, also clouds left without odometry at either end)."""
    ends: list[str] = []
    if scan_stamps is not None:
        section = outside_odometry(health.outside_odometry, scan_stamps)
        ends = unused_ends(section, scan_stamps, gap_periods)
    if not health.problems() and not ends:
        return
    parts = [f.message for f in health.faults[:3]] + ends
    if health.gaps:
        parts.append(f"{len(health.gaps)} odometry gap(s) not interpolated")
    c = health.clouds
    if c["undecodable"] or c["out_of_order"]:
        parts.append(f"{c['undecodable']} undecodable and {c['out_of_order']} out-of-order clouds")
    more = "" if len(health.faults) <= 3 else f" (+{len(health.faults) - 3} more faults)"
    text = "; ".join(parts)
    where = "" if health.faults else f"{log}: "  # a fault's message names its file
    warnings.warn(
        f"{where}{text}{more}; the run went on, see report.json 'ingest'", LogWarning, stacklevel=3
    )
