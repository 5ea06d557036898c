"""A corridor that curves: the straight simulated world bent about the vertical.

Real tunnels follow horizontal curves (a bored metro tunnel's radius is a few hundred metres,
a mine drift's tens) and long pipelines bend gently; every other scene of the simulator is
straight along world x. :class:`Bend` maps the straight world onto one that curves with a
constant radius ``R`` in the horizontal plane (positive ``R``: to the left, +y; negative: to
the right), keeping the arc length: the straight point ``(x, y, z)`` goes to

``C(x) + y N(x) + z e_z``, with ``C(x) = (R sin(x / R), R (1 - cos(x / R)), 0)`` the centre
line and ``N(x) = (-sin(x / R), cos(x / R), 0)`` its left normal,

so a joint at ``x`` in ``joints.json`` is at arc length ``x`` along the bent centre line, a
ring's face stays a plane across the axis, and the inside of the curve is shorter than the
outside by ``y / R`` (as in a real curved tunnel). Poses are bent with their position and
turned by the heading ``x / R`` of the centre line at their ``x``. The odometry is drifted in
the straight world and its error carried into the bent one step by step, in the robot's
frame (:meth:`Bend.carry`): each step reads short or long along the robot's own heading, as
a corridor odometry's does, and integrated along the curve (drifted on the bent path, the
endpoint model's error along world x came out sideways where the corridor had turned: 0.44 m
across the axis at the far end of a 5 m horseshoe on a 100 m curve; carried as one offset in
the frame of the robot's true place, each step of a return 15 % short on a 50 m curve moved
up to 9 % sideways to its heading, which no corridor odometry does).

The scans are cast in the straight world and bent with it (:meth:`Simulation.scan
<decod_rs.sim.api.Simulation.scan>`): each point lies exactly on the bent surface, but the
ray that found it is bent too, by ``t^2 / (2 R)`` sideways at ``t`` metres along the axis.
Where the straight line from the sensor to a point leaves the corridor, the inside wall of
the curve hides that point from a real sensor, and it is dropped (:meth:`Bend.in_sight`; a
real sensor would return the inside wall there instead, which these scans lack: they see
less of the curve's inside wall near the edge of sight than a real sensor). Without that, a
forward sensor in a 0.6 m pipe bent on 30 m saw the pipe 40 m round the bend, and ``auto``
took the bend for the pipe's section (14 m radius). :data:`MIN_RADIUS_FACTOR` keeps the
bend gentle. The IMU is simulated on the straight trajectory: the bend's yaw rate
(``v / R``, 0.004 rad/s at 1.3 m/s on a 300 m curve) is missing from its gyro, which decod
does not read (it takes gravity from the accelerometer, which a turn about the vertical
leaves unchanged but for ``v^2 / R``, 0.006 m/s^2 there).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from decod_rs.sim.fields import F64

#: The bend radius must be at least this many corridor radii (a 6 m tunnel: 60 m; a 0.4 m
#: pipe: 4 m): over one corridor diameter along the axis the bent rays then stray sideways
#: by at most a tenth of the radius.
MIN_RADIUS_FACTOR = 20.0

#: Points checked along each line of sight (:meth:`Bend.in_sight`), and the share of the
#: corridor's radius by which the line may pass outside the nominal section (the wall's
#: relief, a grazing ray's last stretch) before the point counts as hidden.
SIGHT_SAMPLES = 12
SIGHT_MARGIN = 0.02

__all__ = ["MIN_RADIUS_FACTOR", "Bend", "check_bend_radius"]


def check_bend_radius(radius_m: float | None, corridor_radius_m: float) -> float | None:
    """The bend radius, or None for a straight corridor; ``ValueError`` naming the parameter
    when it is not a number or tighter than :data:`MIN_RADIUS_FACTOR` corridor radii."""
    if radius_m is None:
        return None
    r = float(radius_m)
    if not math.isfinite(r):
        raise ValueError(f"curve radius must be a finite number of metres, got {radius_m}")
    floor = MIN_RADIUS_FACTOR * float(corridor_radius_m)
    if abs(r) < floor:
        raise ValueError(
            f"curve radius {r:g} m is tighter than {MIN_RADIUS_FACTOR:g} corridor radii "
            f"({floor:g} m for this scene): the simulator bends a straight corridor and is "
            "only faithful for gentle curves"
        )
    return r


@dataclass(frozen=True)
class Bend:
    """The map from the straight world to the bent one (module docs); ``radius_m`` signed."""

    radius_m: float

    def _frame(self, x: F64) -> tuple[F64, F64, F64]:
        phi = np.asarray(x, dtype=np.float64) / self.radius_m
        return phi, np.sin(phi), np.cos(phi)

    def points(self, pts: F64) -> F64:
        """``(N, 3)`` straight-world points in the bent world."""
        p = np.asarray(pts, dtype=np.float64)
        _, s, c = self._frame(p[:, 0])
        inner = self.radius_m - p[:, 1]
        out = np.empty_like(p)
        out[:, 0] = inner * s
        out[:, 1] = self.radius_m - inner * c
        out[:, 2] = p[:, 2]
        return out

    def unbend(self, pts: F64) -> F64:
        """``(N, 3)`` bent-world points back in the straight world (:meth:`points` inverted;
        for points less than ``|R|`` from the centre line sideways)."""
        p = np.asarray(pts, dtype=np.float64)
        r = self.radius_m
        sign = math.copysign(1.0, r)
        out = np.empty_like(p)
        out[:, 0] = r * np.arctan2(sign * p[:, 0], sign * (r - p[:, 1]))
        out[:, 1] = r - sign * np.hypot(p[:, 0], r - p[:, 1])
        out[:, 2] = p[:, 2]
        return out

    def in_sight(
        self, origin: F64, pts: F64, radius_m: float, floor_z_m: float | None
    ) -> NDArray[np.bool_]:
        """``(N,)`` whether the straight line from ``origin`` to each bent-world point stays
        inside the corridor's nominal section (``radius_m`` about the centre line, above
        ``floor_z_m``), checked at :data:`SIGHT_SAMPLES` points along it: where it leaves
        it, the inside wall of the curve hides the point (module docs)."""
        o = np.asarray(origin, dtype=np.float64)
        p = np.asarray(pts, dtype=np.float64)
        ok = np.ones(p.shape[0], dtype=bool)
        limit = (1.0 + SIGHT_MARGIN) * radius_m
        for f in np.linspace(0.0, 1.0, SIGHT_SAMPLES + 2)[1:-1]:
            q = self.unbend(o + f * (p - o))
            ok &= np.hypot(q[:, 1], q[:, 2]) <= limit
            if floor_z_m is not None:
                ok &= q[:, 2] >= floor_z_m - SIGHT_MARGIN * radius_m
        return ok

    def carry(self, truth: F64, other: F64) -> F64:
        """``(N, 4, 4)`` poses ``other`` (straight world, e.g. the drifted odometry) in the bent
        world, step by step: each step's error against the truth in the robot's frame (``D_k^-1
        O_k``, ``D_k`` and ``O_k`` the truth's and ``other``'s steps from scan ``k - 1``)
        composed with the bent truth's step, from the first pose's offset. A straight world
        gives ``other`` back."""
        t = np.asarray(truth, dtype=np.float64)
        o = np.asarray(other, dtype=np.float64)
        bent = self.poses(t)
        t_inv, o_inv, bent_inv = (np.linalg.inv(x) for x in (t, o, bent))
        # Each bent step followed by that step's error, D_k^-1 O_k = t_k^-1 t_{k-1} o_{k-1}^-1 o_k.
        steps = (bent_inv[:-1] @ bent[1:]) @ (t_inv[1:] @ t[:-1]) @ (o_inv[:-1] @ o[1:])
        out = np.empty_like(o)
        out[0] = bent[0] @ t_inv[0] @ o[0]
        for k, step in enumerate(steps, start=1):
            out[k] = out[k - 1] @ step
        return out

    def poses(self, poses: F64) -> F64:
        """``(N, 4, 4)`` straight-world poses in the bent world: position bent, attitude
        turned by the centre line's heading at the pose's x."""
        t = np.asarray(poses, dtype=np.float64)
        out = t.copy()
        _, s, c = self._frame(t[:, 0, 3])
        yaw = np.zeros((t.shape[0], 3, 3))
        yaw[:, 0, 0], yaw[:, 0, 1] = c, -s
        yaw[:, 1, 0], yaw[:, 1, 1] = s, c
        yaw[:, 2, 2] = 1.0
        out[:, :3, :3] = yaw @ t[:, :3, :3]
        out[:, :3, 3] = self.points(t[:, :3, 3])
        return out
