"""Out-and-back trajectories along the corridor (world +x) and rotation helpers.

The vehicle stands still for ``pre_s``, drives ``length_m`` out with cosine speed ramps,
stops at the far end (``reverse``: drives back with the heading unchanged, a pipe crawler;
``turn``: turns 180 deg in place, then drives back), and stands still for ``post_s``.
``return_speed_mps`` drives the return at another cruise speed than the outbound (a
crawler that inspects slowly on the way out and comes back fast). ``stops`` make it halt
along a leg, as an inspection robot does at a defect: each
``(leg, fraction, seconds)`` (leg 0 outbound, 1 return) slows down over ``ramp_s`` to stand
still about ``fraction`` of the way along that leg, stays for ``seconds`` and drives on
(a time warp of the leg: the path and the wobble along it are unchanged). ``backups`` make
it stop, drive back some metres the way it came and forward over them again before it goes
on, as an operator does to look again at a defect: each ``(leg, fraction, metres)`` a halt
whose standing time is spent backing up (:func:`_backup_shape`).
Lateral, vertical, roll, pitch and yaw wobble are functions of the travelled distance (a path
that wanders in space; no wobble while standing still), so the IMU is quiet at rest.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from decod_rs.sim.fields import F64

#: Metres of the return over which a vehicle changes lane (``return_lateral_m``): a road
#: vehicle's lane change at walking pace, turning at most 15-20 deg for 3-4 m to the side.
LANE_CHANGE_M = 15.0


def rot_x(a: F64) -> F64:
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack(
        [np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)], -2
    )


def rot_y(a: F64) -> F64:
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack(
        [np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2
    )


def rot_z(a: F64) -> F64:
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack(
        [np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2
    )


def quat_xyzw(rot: F64) -> F64:
    """Unit quaternions ``(N, 4)`` as x, y, z, w (w >= 0) from rotation matrices ``(N, 3, 3)``."""
    m = rot
    tr = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    cands = np.stack(
        [
            np.stack(
                [m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0], m[:, 1, 0] - m[:, 0, 1], 1 + tr],
                -1,
            ),
            np.stack(
                [
                    1 + m[:, 0, 0] - m[:, 1, 1] - m[:, 2, 2],
                    m[:, 0, 1] + m[:, 1, 0],
                    m[:, 0, 2] + m[:, 2, 0],
                    m[:, 2, 1] - m[:, 1, 2],
                ],
                -1,
            ),
            np.stack(
                [
                    m[:, 0, 1] + m[:, 1, 0],
                    1 + m[:, 1, 1] - m[:, 0, 0] - m[:, 2, 2],
                    m[:, 1, 2] + m[:, 2, 1],
                    m[:, 0, 2] - m[:, 2, 0],
                ],
                -1,
            ),
            np.stack(
                [
                    m[:, 0, 2] + m[:, 2, 0],
                    m[:, 1, 2] + m[:, 2, 1],
                    1 + m[:, 2, 2] - m[:, 0, 0] - m[:, 1, 1],
                    m[:, 1, 0] - m[:, 0, 1],
                ],
                -1,
            ),
        ],
        1,
    )
    choice = np.argmax(np.stack([tr, m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]], -1), axis=1)
    q = cands[np.arange(m.shape[0]), choice]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return np.where(q[:, 3:4] < 0, -q, q)


def so3_log(rot: F64) -> F64:
    """Rotation vectors ``(N, 3)`` of rotation matrices ``(N, 3, 3)`` (angles below pi)."""
    cos_a = np.clip((np.trace(rot, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    ang = np.arccos(cos_a)
    w = np.stack(
        [rot[:, 2, 1] - rot[:, 1, 2], rot[:, 0, 2] - rot[:, 2, 0], rot[:, 1, 0] - rot[:, 0, 1]], -1
    )
    sin_a = np.sin(ang)
    scale = np.where(sin_a > 1e-9, ang / (2.0 * np.where(sin_a > 1e-9, sin_a, 1.0)), 0.5)
    return w * scale[:, None]


@dataclass(frozen=True)
class TrajectorySpec:
    """Parameters of an out-and-back run (metres, seconds, radians)."""

    x_start_m: float
    length_m: float
    speed_mps: float
    return_mode: str  # "reverse" | "turn"
    y0_m: float = 0.0
    z0_m: float = 0.0
    ramp_s: float = 2.0
    pre_s: float = 2.0
    post_s: float = 1.0
    pause_s: float = 2.0
    turn_s: float = 6.0
    lateral_m: float = 0.01
    vertical_m: float = 0.005
    roll_rad: float = 0.03
    pitch_rad: float = 0.008
    yaw_rad: float = 0.01
    wobble_wavelength_m: float = 3.0
    #: The sensor's static mount on the vehicle: rolled about its forward axis, then pitched
    #: (positive: nose down) about its lateral axis. The scans, the odometry, the IMU and the
    #: ground truth are all of the mounted sensor, as a driver publishes them.
    mount_roll_rad: float = 0.0
    mount_pitch_rad: float = 0.0
    #: Halts along the legs: ``(leg, fraction, seconds)``, leg 0 (outbound) or 1 (return),
    #: ``fraction`` of the leg's length in (0, 1) (within the cruise, away from the ramps).
    stops: tuple[tuple[float, float, float], ...] = ()
    #: The return leg's cruise speed (m/s); None: ``speed_mps``, as the outbound.
    return_speed_mps: float | None = None
    #: The return leg runs this far to the side of the outbound (m, world +y to the left of
    #: the outbound direction): a vehicle that comes back in the other lane of a tunnel. It
    #: changes lane over the first ``LANE_CHANGE_M`` of the return, heading along its path.
    return_lateral_m: float = 0.0
    #: Back-ups along the legs: ``(leg, fraction, metres)``: about ``fraction`` of the way
    #: along leg 0 or 1 the vehicle slows to a halt, drives ``metres`` back the way it came
    #: and forward over them again (at up to the leg's speed), then drives on. Placed like a
    #: stop; the metres must lie within the leg travelled so far.
    backups: tuple[tuple[float, float, float], ...] = ()

    def leg_speed(self, leg: int) -> float:
        """The cruise speed of ``leg`` (0 outbound, 1 return), m/s."""
        if leg == 1 and self.return_speed_mps is not None:
            return float(self.return_speed_mps)
        return float(self.speed_mps)

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def _halted(t: F64, ramp: float, hold: float) -> F64:
    """Seconds of motion a halt has taken out ``t`` seconds after it began to slow down: the
    speed falls to 0 over ``ramp`` seconds (cosine), stays 0 for ``hold``, and comes back over
    ``ramp`` (in all ``ramp + hold`` seconds once it is over)."""
    t = np.asarray(t, dtype=np.float64)

    def ramped(u: F64) -> F64:  # integral of (1 - cos(pi u / ramp)) / 2 over [0, u]
        u = np.clip(u, 0.0, ramp)
        return 0.5 * (u - ramp / np.pi * np.sin(np.pi * u / ramp))

    slowing = ramped(t)
    stopped = np.clip(t - ramp, 0.0, hold)
    resuming = np.clip(t - ramp - hold, 0.0, ramp) - ramped(t - ramp - hold)
    return slowing + stopped + resuming


def _backup_shape(u: F64, metres: float) -> tuple[F64, F64]:
    """A back-up ``u`` (0-1) of the way through its standing time: how far the vehicle is
    behind the point it stopped at (a cosine out to ``metres`` and back, so it starts, turns
    and ends at rest) and the path it has driven so far (``2 metres`` in all)."""
    u = np.clip(u, 0.0, 1.0)
    behind = 0.5 * metres * (1.0 - np.cos(2.0 * np.pi * u))
    return behind, np.where(u < 0.5, behind, 2.0 * metres - behind)


def _halt_entries(spec: TrajectorySpec) -> list[tuple[int, float, float, float, str]]:
    """Every stop and back-up as ``(leg, fraction, seconds, metres backed up, label)``, a
    back-up standing for ``pi metres / v`` (its peak speed is the leg's ``v``)."""
    entries = []
    for stop in spec.stops:
        leg, fraction, hold = (float(v) for v in stop)
        if leg not in (0.0, 1.0) or not (np.isfinite(hold) and hold > 0.0):
            raise ValueError(f"stop {stop}: leg must be 0 or 1 and seconds > 0")
        entries.append((int(leg), fraction, hold, 0.0, f"stop {stop}"))
    for backup in spec.backups:
        leg, fraction, metres = (float(v) for v in backup)
        if leg not in (0.0, 1.0) or not (np.isfinite(metres) and metres > 0.0):
            raise ValueError(f"backup {backup}: leg must be 0 or 1 and metres > 0")
        if fraction * spec.length_m - metres < spec.leg_speed(int(leg)) * spec.ramp_s:
            raise ValueError(
                f"backup {backup}: {metres:g} m back from {fraction * spec.length_m:g} m along "
                "the leg would pass its start"
            )
        hold = np.pi * metres / spec.leg_speed(int(leg))
        entries.append((int(leg), fraction, hold, metres, f"backup {backup}"))
    return entries


def _halts(
    spec: TrajectorySpec, leg_s: tuple[float, float]
) -> tuple[list[tuple[float, float, float]], ...]:
    """Per leg, its stops and back-ups as ``(elapsed time the slowing starts, seconds, metres
    backed up)`` in order; a halt is refused unless it lies within the leg's cruise (the
    ramps at either end are the leg's own start and stop) and a ramp of motion away from the
    leg's other halts (two halts overlapping would drive the vehicle backwards)."""
    legs: tuple[list[tuple[float, float, float]], ...] = ([], [])
    for leg, fraction, hold, metres, label in _halt_entries(spec):
        # Motion time at which the vehicle is `fraction` along (cruise: d = v (tau - ramp/2)).
        tau = fraction * spec.length_m / spec.leg_speed(leg) + 0.5 * spec.ramp_s
        if not (2.0 * spec.ramp_s <= tau <= leg_s[leg] - 2.0 * spec.ramp_s):
            raise ValueError(f"{label}: fraction must lie within the leg's cruise")
        legs[leg].append((tau, hold, metres))
    out: tuple[list[tuple[float, float, float]], ...] = ([], [])
    for leg, halts in enumerate(legs):
        lost, last = 0.0, -np.inf
        for tau, hold, metres in sorted(halts):
            if tau - last < spec.ramp_s:
                raise ValueError(f"stops on leg {leg}: closer than one ramp of driving apart")
            # It slows down half a ramp of motion before the stop point, after the time
            # the earlier stops of the leg took.
            out[leg].append((tau - 0.5 * spec.ramp_s + lost, hold, metres))
            lost += hold + spec.ramp_s
            last = tau
    return out


class Trajectory:
    """Ground-truth ``world_from_body`` poses at arbitrary times (vectorised)."""

    def __init__(self, spec: TrajectorySpec, rng: np.random.Generator) -> None:
        if spec.return_mode not in ("reverse", "turn"):
            raise ValueError(f"return_mode must be 'reverse' or 'turn', got {spec.return_mode!r}")
        for leg in (0, 1):
            sp = spec.leg_speed(leg)
            if not (np.isfinite(sp) and sp > 0) or spec.length_m <= sp * spec.ramp_s:
                raise ValueError(
                    f"length_m ({spec.length_m}) must exceed the speed times ramp_s "
                    f"({sp * spec.ramp_s}) and the speed of leg {leg} must be > 0"
                )
        self.spec = spec
        # Motion time of each leg (without its stops) and, per leg, its stops' warps.
        self.leg_s = (
            spec.length_m / spec.leg_speed(0) + spec.ramp_s,
            spec.length_m / spec.leg_speed(1) + spec.ramp_s,
        )
        self._halts = _halts(spec, self.leg_s)
        self.stop_s = spec.turn_s if spec.return_mode == "turn" else spec.pause_s
        out_s, back_s = (
            motion + sum(h + spec.ramp_s for _, h, _ in halts)
            for motion, halts in zip(self.leg_s, self._halts, strict=True)
        )
        self.t_far_arrive = spec.pre_s + out_s
        self.t_return_start = self.t_far_arrive + self.stop_s
        self.duration_s = self.t_return_start + back_s + spec.post_s
        # Wobble: per degree of freedom, three spatial harmonics with random phases.
        self._wob: dict[str, tuple[F64, F64, F64]] = {}
        lam = spec.wobble_wavelength_m
        for name, amp in (
            ("y", spec.lateral_m),
            ("z", spec.vertical_m),
            ("roll", spec.roll_rad),
            ("pitch", spec.pitch_rad),
            ("yaw", spec.yaw_rad),
        ):
            wavelengths = lam * np.array([2.7, 1.0, 0.37]) * rng.uniform(0.8, 1.25, 3)
            amps = amp * np.array([0.7, 0.5, 0.15])
            phases = rng.uniform(0.0, 2.0 * np.pi, 3)
            self._wob[name] = (2.0 * np.pi / wavelengths, amps, phases)

    def _leg(self, leg: int, tau: F64) -> F64:
        """Distance covered ``tau`` seconds into ``leg`` (cosine speed ramps)."""
        sp, tr, tl = self.spec.leg_speed(leg), self.spec.ramp_s, self.leg_s[leg]
        tau = np.clip(tau, 0.0, tl)

        def up(t: F64) -> F64:
            tt = np.minimum(t, tr)
            return 0.5 * sp * (tt - tr / np.pi * np.sin(np.pi * tt / tr)) + sp * np.maximum(
                t - tr, 0.0
            )

        return np.where(tau <= 0.5 * tl, up(tau), self.spec.length_m - up(tl - tau))

    def _motion(self, leg: int, elapsed: F64) -> F64:
        """Motion time of ``leg`` after ``elapsed`` seconds of it, its stops taken out."""
        tau = np.asarray(elapsed, dtype=np.float64).copy()
        ramp = self.spec.ramp_s
        for start, hold, _ in self._halts[leg]:
            tau -= _halted(elapsed - start, ramp, hold)
        return tau

    def _leg_parts(self, leg: int, t: F64) -> tuple[F64, F64, F64]:
        """At times ``t``, the distance ``leg`` has covered without its back-ups, how far its
        back-ups have it behind that, and the path they have driven."""
        elapsed = np.asarray(t, dtype=np.float64) - (
            self.spec.pre_s if leg == 0 else self.t_return_start
        )
        made = self._leg(leg, self._motion(leg, elapsed))
        behind, driven = np.zeros_like(made), np.zeros_like(made)
        for start, hold, metres in self._halts[leg]:
            if metres > 0.0:
                b, d = _backup_shape((elapsed - start - self.spec.ramp_s) / hold, metres)
                behind, driven = behind + b, driven + d
        return made, behind, driven

    def _legs(self, t: F64) -> tuple[F64, F64]:
        """How far along the outbound and the return leg the vehicle is at times ``t``."""
        out, out_behind, _ = self._leg_parts(0, t)
        back, back_behind, _ = self._leg_parts(1, t)
        return out - out_behind, back - back_behind

    def travelled(self, t: F64) -> F64:
        """Distance travelled along the axis since the start, metres (monotone: a back-up's
        path counts both ways)."""
        out, _, out_driven = self._leg_parts(0, t)
        back, _, back_driven = self._leg_parts(1, t)
        return out + out_driven + back + back_driven

    def axial(self, t: F64) -> F64:
        """Nominal axial position (world x) without wobble."""
        out, back = self._legs(t)
        return self.spec.x_start_m + out - back

    def _wobble(self, name: str, d: F64) -> F64:
        k, a, ph = self._wob[name]
        return np.sum(a[None, :] * np.sin(d[:, None] * k[None, :] + ph[None, :]), axis=1)

    def heading(self, t: F64) -> F64:
        if self.spec.return_mode == "reverse":
            return np.zeros_like(t)
        frac = np.clip((t - self.t_far_arrive) / self.stop_s, 0.0, 1.0)
        return np.pi * frac * frac * (3.0 - 2.0 * frac)

    def _lane(self, t: F64) -> tuple[F64, F64]:
        """The return's lane change at times ``t``: the sideways offset (m) and the yaw (rad)
        that heads the body along the path (a cosine step over ``LANE_CHANGE_M``)."""
        side = self.spec.return_lateral_m
        _, back = self._legs(t)
        if side == 0.0:
            return np.zeros_like(back), np.zeros_like(back)
        u = np.clip(back / LANE_CHANGE_M, 0.0, 1.0)
        offset = 0.5 * side * (1.0 - np.cos(np.pi * u))
        slope = 0.5 * side * np.pi / LANE_CHANGE_M * np.sin(np.pi * u)
        # Along -x, the path's direction is (-1, slope): facing -x (turn) or +x (reverse),
        # the body turns by -atan(slope) to lie along it.
        return offset, -np.arctan(slope)

    def poses(self, t: F64) -> F64:
        """``world_from_body`` ``(N, 4, 4)`` at times ``t (N,)`` (seconds from the start)."""
        t = np.asarray(t, dtype=np.float64)
        d = self.travelled(t)
        s = self.spec
        lane, lane_yaw = self._lane(t)
        pos = np.stack(
            [self.axial(t), s.y0_m + lane + self._wobble("y", d), s.z0_m + self._wobble("z", d)],
            axis=1,
        )
        rot = (
            rot_z(self.heading(t) + lane_yaw + self._wobble("yaw", d))
            @ rot_y(self._wobble("pitch", d))
            @ rot_x(self._wobble("roll", d))
            @ rot_y(np.full_like(t, s.mount_pitch_rad))
            @ rot_x(np.full_like(t, s.mount_roll_rad))
        )
        out = np.zeros((t.size, 4, 4))
        out[:, :3, :3] = rot
        out[:, :3, 3] = pos
        out[:, 3, 3] = 1.0
        return out
