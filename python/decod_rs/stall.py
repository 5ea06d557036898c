"""A frontend that stalls along the axis (beyond the paper): the axial motion measured from
the boundaries passing through the sensor's view.

In a smooth pipe a LiDAR odometry has nothing to register along the axis, and it may stop
there altogether: KISS-ICP on the simulated hume pipes reports 0-4 % of the distance driven.
The boundaries then say what the odometry cannot. A joint is seen from many consecutive short
submaps as it passes by, each time at its distance ahead of the sensor, and that distance
shrinks at the robot's speed along the axis whatever the odometry reports.

decod checks for it where the odometry's typical moving speed is below a descriptor's half
length in ``STALL_TIME_S`` (the odometry hardly moves: a robot standing still, or a stall).
A sample of the log (``SAMPLE_S`` of every ``SAMPLE_EVERY_S``), and where that sample says
the odometry stalled the whole log, is then extracted again in windows of a few scans (those
that fill a descriptor, at least ``MIN_WINDOW_SCANS``), so that little of the unseen motion
smears a window, and every boundary's distance along its window's axis is taken:

- Distances where boundaries pile up whatever the robot does are the sensor's, not the
  corridor's (the range window's ends: on the simulated 0.6 m pipe with the forward sensor,
  half of all detections lie within 0.3 m of the far end). Bins holding more than
  ``PILE_UP`` times the median bin's views, in at least ``PILE_UP_SPREAD`` of the log's
  stretches spread over half of it (not a stop's joint), are left out (``sensor_fixed``).
  Counting which views stand still from one window to the next instead flagged 1,325 of
  2,181 views in a tunnel (its rings 1.5 m apart, many views a window: neighbours coincide
  by chance).
- Every pair of the remaining views one to ``PAIR_WINDOWS`` windows apart votes for the
  speed that would carry one onto the other: a joint seen from several windows gives votes
  that agree, chance pairs spread over all speeds. Near pairs only: in a tunnel whose rings
  are 1.5 m apart, at 1.5 m/s, every pair 1 s apart pairs a ring with its neighbour and
  votes for standing still.
- The votes are binned per ``BLOCK_S`` stretch, and the speed is the path through the
  stretches that collects the most votes less ``JUMP_PENALTY`` per ``VOTE_BIN_MPS`` of change
  (a Viterbi pass: a stretch without votes keeps its neighbours' speed, a stop shows as the
  many votes of joints standing still). Each stretch's speed is then refined by the median
  of the pairs up to ``LONG_PAIR_S`` apart within ``REFINE_GATE`` of it (``block_speeds``).
- The odometry's steps along the axis (the body frame's axis from the views) are replaced
  by that speed's, its rotations and its steps across the axis kept (``restitched``), and
  the whole measurement is made once more on windows stitched on it (``AXIAL_PASSES``),
  which smear the boundaries less.

Where the measured travel is ``STALL_RATIO`` times the odometry's or more, and the speed's
path collects more votes than the same views shuffled among the windows by ``CHANCE_SIGMAS``
of the shuffles' spread (a null model: the same views without motion to carry them;
``chance_votes``; a sample passes the whole log on at ``SAMPLE_SIGMAS``), the run's odometry
is the restitched one (``report.json`` ``ingest.odometry_stall`` says what was measured):
the corridor is configured again on it and the run goes on as on any drifting odometry, the
loops and boundary tracks correcting what the speed left. On seven simulated logs whose
odometry reported 3 % of the distance (pipes and tunnels seen by the forward sensor), the
corrected far end came within 86-109 % of the truth (3 % before), with no wrong loop; with
16 beams in the 0.6 m pipe the speed's path collects what shuffled views collect and the
odometry is kept (``docs/measurements.md``, "Frontends that stall").
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

__all__ = [
    "SAMPLE_EVERY_S",
    "SAMPLE_S",
    "SAMPLE_SIGMAS",
    "STALL_TIME_S",
    "AxialMotion",
    "block_speeds",
    "chance_votes",
    "odometry_speed",
    "path_length",
    "restitched",
    "sensor_fixed",
]

#: The walls are asked whether the odometry stalled where its typical moving speed
#: (``odometry_speed``) is below a descriptor's half length in this many seconds: a boundary
#: then stays within its own descriptor of where the odometry places it for that long (0.096
#: m/s in the 0.6 m pipe, 0.9 m/s in a 6 m tunnel). KISS-ICP on the simulated hume pipe
#: (0.4 m/s) moves at 0.036-0.054 m/s; the slowest matrix robots at 0.2 m/s in a pipe and
#: 0.8 m/s in a tunnel, the one that is checked (and kept).
STALL_TIME_S = 2.5
#: Windows of at least this many scans for the axial measurement.
MIN_WINDOW_SCANS = 2
#: A distance bin holding this many times the median bin's views, in at least this share of
#: the log's stretches, spread from first to last over this share of them, is the sensor's.
PILE_UP = 3.0
PILE_UP_SPREAD = 0.1
PILE_UP_SPAN = 0.5
#: Pairs of views one to this many windows apart vote for the speed.
PAIR_WINDOWS = 2
#: A stretch's speed is refined by the pairs up to this far apart in time (s: as long as a
#: joint stays in a forward sensor's view in a pipe at walking speed) within this share of it.
LONG_PAIR_S = 2.0
REFINE_GATE = 0.25
#: A speed per stretch of this length (s), votes in bins of this width (m/s) spread by this
#: Gaussian, this many votes lost per bin of change from one stretch to the next, and this
#: many agreeing votes for a stretch to count as measured.
BLOCK_S = 2.0
VOTE_BIN_MPS = 0.04
VOTE_SIGMA_MPS = 0.02
JUMP_PENALTY = 0.1
MIN_VOTES = 3
#: The check first measures a sample of the log, this many seconds of every so many (a log
#: shorter than two of those whole), and the whole log only where the sample stalled: on the
#: 10 m tunnels with the forward sensor at 1-1.3 m/s, which are checked (and kept), measuring
#: the whole log took 4-6 s and the run from 29-35x real time to 8-12x.
SAMPLE_S = 6.0
SAMPLE_EVERY_S = 30.0
#: A sample screens: it passes the whole log on with its votes this many standard deviations
#: above the shuffles' (the shield with a turn, stalled: 3.0 in its sample), and the whole
#: log's measurement decides with ``CHANCE_SIGMAS``.
SAMPLE_SIGMAS = 2.0
#: Measurements of the whole log: the first on windows stitched on the odometry, the next on
#: windows stitched on the one before.
AXIAL_PASSES = 2
#: The restitched odometry replaces the run's where it travels this many times as far, and
#: its path collects more votes than the same views shuffled (``chance_votes``, this many
#: shuffles) by this many of their standard deviations.
STALL_RATIO = 2.0
CHANCE_SHUFFLES = 8
CHANCE_SIGMAS = 4.0


def odometry_speed(stamps: FloatArray, positions: FloatArray) -> float:
    """The odometry's typical moving speed (m/s): the median of its displacements over 1 s
    steps, among those above 2 cm (``auto``'s speed, :mod:`decod_rs.autoscale`). A robot's
    stops do not lower it, nor does a frontend's jitter raise it as a path length would:
    KISS-ICP's stalled odometry on the simulated hume pipe reports 5.8 m of path over 160 s
    for 0.04 m/s, but a median step of 0.036 m/s."""
    if stamps.size < 2 or stamps[-1] <= stamps[0]:
        return 0.0
    grid = np.arange(stamps[0], stamps[-1], 1.0)
    if grid.size < 2:
        return float(np.linalg.norm(positions[-1] - positions[0]) / (stamps[-1] - stamps[0]))
    at = np.stack([np.interp(grid, stamps, positions[:, i]) for i in range(3)], axis=1)
    steps = np.linalg.norm(np.diff(at, axis=0), axis=1)
    moving = steps[steps > 0.02]
    return float(np.median(moving)) if moving.size else 0.0


def path_length(positions: FloatArray) -> float:
    """The odometry's path length (m)."""
    return float(np.linalg.norm(np.diff(positions, axis=0), axis=1).sum())


def sensor_fixed(stamps: FloatArray, axial: FloatArray, bin_m: float) -> NDArray[np.bool_]:
    """Views at distances where detections pile up (module docs): distance bins (``bin_m``)
    holding more than ``PILE_UP`` times the median occupied bin's views, in at least
    ``PILE_UP_SPREAD`` of the log's ``BLOCK_S`` stretches, from first to last over at least
    ``PILE_UP_SPAN`` of them. The spread keeps a stop's views: a joint in view while the
    robot stands still piles up in its bin too, but only for the stretches of the stop."""
    if axial.size == 0:
        return np.zeros(0, dtype=bool)
    index = np.floor((axial - axial.min()) / bin_m).astype(np.int64)
    views = np.bincount(index)
    block = np.floor((stamps - stamps.min()) / BLOCK_S).astype(np.int64)
    blocks = int(block.max()) + 1
    occupied = np.unique(index * blocks + block)
    stretches = np.bincount(occupied // blocks, minlength=views.size)
    first = np.full(views.size, blocks)
    np.minimum.at(first, occupied // blocks, occupied % blocks)
    last = np.zeros(views.size, dtype=np.int64)
    np.maximum.at(last, occupied // blocks, occupied % blocks)
    piled = views > PILE_UP * float(np.median(views[views > 0]))
    spread = (stretches >= PILE_UP_SPREAD * blocks) & (last - first >= PILE_UP_SPAN * blocks)
    return (piled & spread)[index]


@dataclass(frozen=True)
class BlockSpeeds:
    """Speed along the axis (m/s, positive towards the sensor's view) at the centre of each
    stretch, and the near pairs' votes within ``VOTE_BIN_MPS`` of it."""

    centres: FloatArray
    speeds: FloatArray
    votes: NDArray[np.int64]


def _pair_votes(
    stamps: FloatArray, axial: FloatArray, window_s: float, horizon_s: float
) -> tuple[FloatArray, FloatArray]:
    """Every pair's (mid time, speed) for pairs from one window to ``horizon_s`` apart: views
    sorted by time, so each view's partners are a contiguous run after it."""
    order = np.argsort(stamps, kind="stable")
    t, a = stamps[order], axial[order]
    lo = np.searchsorted(t, t + 0.5 * window_s, side="left")
    hi = np.searchsorted(t, t + horizon_s, side="right")
    counts = np.maximum(hi - lo, 0)
    first = np.repeat(np.arange(t.size), counts)
    offsets = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    second = np.repeat(lo, counts) + offsets
    dt = t[second] - t[first]
    # The distance ahead shrinks as the sensor moves forward along its axis.
    return 0.5 * (t[first] + t[second]), (a[first] - a[second]) / dt


def _vote_histograms(
    mid: FloatArray, speed: FloatArray, start: float, blocks: int, grid: FloatArray
) -> FloatArray:
    """``(blocks, len(grid))`` votes per ``BLOCK_S`` stretch and speed bin, each vote spread
    over its neighbouring bins by a Gaussian of ``VOTE_SIGMA_MPS``."""
    step = float(grid[1] - grid[0])
    row = np.clip(((mid - start) // BLOCK_S).astype(np.int64), 0, blocks - 1)
    col = np.clip(np.rint((speed - grid[0]) / step).astype(np.int64), 0, grid.size - 1)
    hist = np.zeros((blocks, grid.size))
    np.add.at(hist, (row, col), 1.0)
    half = int(np.ceil(3.0 * VOTE_SIGMA_MPS / step))
    offsets = np.arange(-half, half + 1) * step
    kernel = np.exp(-0.5 * (offsets / VOTE_SIGMA_MPS) ** 2)
    return np.apply_along_axis(lambda h: np.convolve(h, kernel, mode="same"), 1, hist)


def _l1_envelope(score: FloatArray, penalty: float) -> tuple[FloatArray, NDArray[np.int64]]:
    """``max_j score[j] - penalty * |i - j|`` for every bin ``i``, and the ``j`` reaching it
    (the distance transform of an L1 cost: one pass each way)."""
    n = score.size
    idx = np.arange(n)
    up = score + penalty * idx  # best j <= i: max(score[j] + p j) - p i
    up_arg = np.maximum.accumulate(np.where(up == np.maximum.accumulate(up), idx, 0))
    down = score - penalty * idx  # best j >= i: max(score[j] - p j) + p i
    rev = down[::-1]
    rev_best = np.maximum.accumulate(rev)
    down_arg = (n - 1 - np.maximum.accumulate(np.where(rev == rev_best, idx, 0)))[::-1]
    from_up = np.maximum.accumulate(up) - penalty * idx
    from_down = rev_best[::-1] + penalty * idx
    take_up = from_up >= from_down
    return np.where(take_up, from_up, from_down), np.where(take_up, up_arg, down_arg)


def block_speeds(
    stamps: FloatArray, axial: FloatArray, window_s: float, max_speed: float
) -> BlockSpeeds:
    """The speed along the axis in each ``BLOCK_S`` stretch (module docs): the path through
    the stretches' vote histograms that collects the most votes, less ``JUMP_PENALTY`` per
    ``VOTE_BIN_MPS`` of change between stretches (a Viterbi pass: a stop shows as the many
    votes of boundaries standing still, a stretch without votes keeps the speed). Speeds
    beyond ``max_speed`` (a view could not be matched across a window at that speed) are
    not counted."""
    empty = BlockSpeeds(np.zeros(0), np.zeros(0), np.zeros(0, dtype=np.int64))
    if stamps.size < 2:
        return empty
    mid, speed = _pair_votes(stamps, axial, window_s, (PAIR_WINDOWS + 0.5) * window_s)
    keep = np.abs(speed) <= max_speed
    mid, speed = mid[keep], speed[keep]
    if mid.size < MIN_VOTES:
        return empty
    start = float(stamps.min())
    blocks = max(1, int(np.ceil((float(stamps.max()) - start) / BLOCK_S)))
    step = VOTE_BIN_MPS / 4.0
    grid = np.arange(-max_speed, max_speed + 0.5 * step, step)
    hist = _vote_histograms(mid, speed, start, blocks, grid)
    penalty = JUMP_PENALTY * step / VOTE_BIN_MPS
    score = hist[0].copy()
    back = np.zeros((blocks, grid.size), dtype=np.int64)
    for b in range(1, blocks):
        best, back[b] = _l1_envelope(score, penalty)
        score = best + hist[b]
    path = np.zeros(blocks, dtype=np.int64)
    path[-1] = int(np.argmax(score))
    for b in range(blocks - 1, 0, -1):
        path[b - 1] = back[b, path[b]]
    centres = start + (np.arange(blocks) + 0.5) * BLOCK_S
    row = np.clip(((mid - start) // BLOCK_S).astype(np.int64), 0, blocks - 1)
    votes = np.array(
        [
            np.sum((row == b) & (np.abs(speed - grid[path[b]]) <= VOTE_BIN_MPS))
            for b in range(blocks)
        ],
        dtype=np.int64,
    )
    coarse = BlockSpeeds(np.asarray(centres, dtype=np.float64), grid[path], votes)
    return _refined(stamps, axial, window_s, coarse)


def _refined(
    stamps: FloatArray, axial: FloatArray, window_s: float, coarse: BlockSpeeds
) -> BlockSpeeds:
    """Each stretch's speed refined by the pairs up to ``LONG_PAIR_S`` apart that agree with
    its coarse speed within ``REFINE_GATE`` of it (at least ``VOTE_BIN_MPS``): their median,
    where ``MIN_VOTES`` or more agree. Pairs far apart resolve the speed finely, but in a
    corridor of evenly spaced rings they also pair each ring with its neighbour (at 1.5 m/s
    and 1.5 m between rings, every pair 1 s apart votes for standing still), so they only
    refine what the near pairs chose."""
    mid, speed = _pair_votes(stamps, axial, window_s, max(LONG_PAIR_S, 1.5 * window_s))
    start = coarse.centres[0] - 0.5 * BLOCK_S
    row = np.clip(((mid - start) // BLOCK_S).astype(np.int64), 0, coarse.centres.size - 1)
    expected = coarse.speeds[row]
    gate = np.maximum(REFINE_GATE * np.abs(expected), VOTE_BIN_MPS)
    agree = np.abs(speed - expected) <= gate
    speeds = coarse.speeds.copy()
    for b in np.unique(row[agree]):
        near = speed[agree & (row == b)]
        if near.size >= MIN_VOTES:
            speeds[b] = float(np.median(near))
    return BlockSpeeds(coarse.centres, speeds, coarse.votes)


def chance_votes(
    stamps: FloatArray, axial: FloatArray, window_s: float, max_speed: float
) -> tuple[float, float]:
    """Mean and standard deviation of the votes :func:`block_speeds` collects along its path
    over ``CHANCE_SHUFFLES`` shuffles of the views' distances among them (the null model:
    the same views and distances, no motion carrying one window's onto the next's)."""
    rng = np.random.default_rng(0)
    votes = [
        int(block_speeds(stamps, rng.permutation(axial), window_s, max_speed).votes.sum())
        for _ in range(CHANCE_SHUFFLES)
    ]
    return float(np.mean(votes)), float(np.std(votes))


def restitched(
    stamps: FloatArray, poses: FloatArray, speed: FloatArray, axis: FloatArray
) -> FloatArray:
    """``poses`` (N, 4, 4) at ``stamps`` with each step along the body-frame ``axis`` (3,)
    replaced by ``speed`` (N,) times the step's duration; rotations and the steps across
    the axis kept."""
    out = poses.copy()
    if stamps.size < 2:
        return out
    world_axis = poses[:-1, :3, :3] @ axis  # (N-1, 3)
    steps = np.diff(poses[:, :3, 3], axis=0)
    along = np.einsum("ij,ij->i", steps, world_axis)
    mean_speed = 0.5 * (speed[:-1] + speed[1:])
    steps += world_axis * (mean_speed * np.diff(stamps) - along)[:, None]
    out[1:, :3, 3] = poses[0, :3, 3] + np.cumsum(steps, axis=0)
    return out


@dataclass(frozen=True)
class AxialMotion:
    """The axial check of a log (module docs): the odometry's travel and speed, and where it
    was measured, the views (and those at sensor-fixed distances), the stretches (and those
    with ``MIN_VOTES`` agreeing votes), the votes along the speed's path and along the
    shuffled views' path, the measured travel, and whether the run's odometry is the
    restitched one."""

    odometry_speed_mps: float
    odometry_travel_m: float
    checked: bool
    views: int = 0
    sensor_fixed_views: int = 0
    blocks: int = 0
    blocks_measured: int = 0
    votes: int = 0
    chance_votes: tuple[float, float] = (0.0, 0.0)
    measured_travel_m: float = 0.0
    applied: bool = False
    poses: FloatArray | None = None
    sampled: bool = False

    def report(self) -> dict[str, Any]:
        """``report.json`` ``ingest.odometry_stall``."""
        return {
            "odometry_speed_mps": round(self.odometry_speed_mps, 4),
            "odometry_travel_m": round(self.odometry_travel_m, 3),
            "checked": self.checked,
            "views": self.views,
            "sensor_fixed_views": self.sensor_fixed_views,
            "stretches": self.blocks,
            "stretches_measured": self.blocks_measured,
            "votes": self.votes,
            "chance_votes": round(self.chance_votes[0], 1),
            "chance_votes_std": round(self.chance_votes[1], 2),
            "measured_travel_m": round(self.measured_travel_m, 3),
            "applied": self.applied,
            "sample_only": self.sampled,
        }
