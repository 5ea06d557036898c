"""What the landmark factors take across the corridor axis: the height of a boundary's
origin is used only where the views place it more tightly than the odometry holds the
robot's height over one submap interval.

A landmark factor's origin is the contour's centre at the boundary. Along the axis it is
what DeCOD exists for. Across the axis the odometry is already constrained (the walls hold
it sideways, gravity and the floor hold its height), and the origin is only as good as the
section is round: where a tunnel's floor or invert is cut off, the centre moves up and down
with how much of the section a view sees.

Measured on the tracks of the matrix m138 (pooled RMS of each view origin's height about
its track's mean, odometry frame): pipes (round, fully seen) 0.01-0.15 cm; tunnels 0.8-5 cm
(64-beam shields 3.8-4.5 cm). Under the ground-truth poses the 64-beam shield's factors
disagree by 5 cm RMS vertically (0.2-0.4 cm laterally), with a mean of -1.5 cm between the
passes. At the sigma across the axis those factors had (5 cm), hundreds of them outweighed
the odometry's height, which the simulated odometries hold to 0.4-0.5 cm: corrected height
errors of 4.3 cm (median over the shields, 10.9 cm at the far end of one), the poses pitched
by 1.5-6.5 mrad. The same run with the factors' vertical sigma at 1 m: position RMSE 0.071
-> 0.024 m.

The rule: the views' vertical spread is compared with the odometry's sigma across its
direction of travel over the median distance between consecutive anchors (the graph's own
odometry model, ``graph.odom_translation_sigma_per_m`` x ``graph.odom_across_sigma_ratio``
x sqrt(distance), :func:`decod_rs.graph.odometry_covariances`). Where the views scatter
more, every landmark factor's vertical sigma becomes ``FREE_SIGMA_M`` (the odometry holds
the height); otherwise the factors keep the spread across the axis
(:func:`decod_rs.sequential.transverse_noise_m`). In the matrix (m141) the pipes' spread is
0.02-0.36 times the odometry's sigma (0.24-0.44 cm there), the tunnels' 1.03-5.4 times it
(0.6-1.1 cm there); the few tunnel runs within a factor 1.5 of it are listed in
``decisions.md``. The lateral spread is measured and reported beside it but not acted on:
the sections are symmetric left to right, and leaving the lateral to the odometry too
(where it scattered more) cost held-out runs (an 8 m horseshoe: 8 cm of lateral error,
RMSE 0.071 -> 0.108 m; ``decisions.md``). ``report.json`` records both spreads, the
odometry's sigma and the decision (``cross_axis``).

The comparison is with the odometry as the graph models it, not as it was measured: an
odometry whose height drifts more than 0.5 cm per root metre (a LiDAR-only frontend without
gravity, say) should say so through ``graph.odom_across_sigma_ratio``, and the factors then
keep the boundaries' heights wherever they scatter less than that.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from decod_rs._core import Landmark
from decod_rs.tracks import offsets_from_track_means, world_axes, world_origins

FloatArray = NDArray[np.float64]

__all__ = [
    "FREE_SIGMA_M",
    "MIN_SPREAD_DOF",
    "CrossAxis",
    "cross_axis",
    "cross_axis_spread",
    "odometry_across_sigma_m",
]

#: Vertical sigma (m) of the factors that leave the height to the odometry. 1 m: a 5 cm
#: disagreement then weighs 0.25 % of what it did at 5 cm. On the 64-beam shield 0.4 m gave
#: the same RMSE within 0.002 m (0.2 m: 0.031 m, 0.1 m: 0.047 m, 0.05 m: 0.071 m).
FREE_SIGMA_M = 1.0

#: Views beyond the first of each track below which no spread is measured
#: (the factors then keep the sigma they had).
MIN_SPREAD_DOF = 10

#: An anchor interval shorter than this fraction of the 90th percentile interval is the
#: robot standing still, not an interval of travel (:func:`odometry_across_sigma_m`).
MOVING_FRACTION = 0.1


@dataclass(frozen=True)
class CrossAxis:
    """The views' measured spread across the axis, laterally and vertically (m), the
    odometry's sigma over one anchor interval the vertical one is compared with, and the
    vertical sigma every landmark factor takes (None: the spread across the axis, unchanged)."""

    lateral_spread_m: float
    vertical_spread_m: float
    odometry_sigma_m: float
    degrees_of_freedom: int

    @property
    def vertical_sigma_m(self) -> float | None:
        return FREE_SIGMA_M if self.vertical_spread_m > self.odometry_sigma_m else None

    def report(self) -> dict[str, Any]:
        return {
            "lateral_spread_m": self.lateral_spread_m,
            "vertical_spread_m": self.vertical_spread_m,
            "odometry_sigma_m": self.odometry_sigma_m,
            "degrees_of_freedom": self.degrees_of_freedom,
            "height_left_to_odometry": self.vertical_sigma_m is not None,
        }


def cross_axis_spread(
    landmarks: Sequence[Landmark],
    tracks: NDArray[np.int64],
    anchors: dict[float, FloatArray],
) -> tuple[float, float, int] | None:
    """Pooled RMS (m) of each view origin's offset from its track's mean, laterally
    (horizontal, across the track's mean axis) and vertically, in the odometry frame, and the
    degrees of freedom (views beyond the first of each track); None below
    ``MIN_SPREAD_DOF``."""
    if len(landmarks) == 0:
        return None
    where = world_origins(landmarks, anchors)
    axes = world_axes(landmarks, anchors)
    up = np.array([0.0, 0.0, 1.0])
    lat_sq = vert_sq = 0.0
    dof = 0
    for idx, d in offsets_from_track_means(where, tracks):
        a = axes[idx] * np.sign(axes[idx] @ axes[idx[0]])[:, None]
        side = np.cross(up, a.mean(axis=0))
        norm = float(np.linalg.norm(side))
        if norm < 1e-6:  # a vertical shaft: no lateral or vertical direction across it
            continue
        side /= norm
        lat_sq += float(np.sum((d @ side) ** 2))
        vert_sq += float(np.sum(d[:, 2] ** 2))
        dof += idx.size - 1
    if dof < MIN_SPREAD_DOF:
        return None
    return float(np.sqrt(lat_sq / dof)), float(np.sqrt(vert_sq / dof)), dof


def odometry_across_sigma_m(
    anchor_stamps: FloatArray, path_at: Callable[[float], float], graph: Any
) -> float | None:
    """The graph's odometry sigma across the direction of travel over the median distance
    between consecutive anchors while the robot moves (:mod:`decod_rs.graph`); None with
    fewer than two anchors or no motion. Anchor intervals shorter than a tenth of the 90th
    percentile are standing still (an inspection stop, the turn in place): counted, a run that
    stood for half its time would have a median interval of 0 and no sigma."""
    if len(anchor_stamps) < 2:
        return None
    steps = np.diff(np.array([path_at(float(s)) for s in anchor_stamps]))
    steps = steps[np.isfinite(steps)]
    if steps.size == 0:
        return None
    moving = steps[steps > MOVING_FRACTION * float(np.percentile(steps, 90.0))]
    step = float(np.median(moving)) if moving.size else 0.0
    if not step > 0.0:
        return None
    per_m = float(graph.odom_translation_sigma_per_m) * float(graph.odom_across_sigma_ratio)
    return per_m * float(np.sqrt(step))


def cross_axis(
    landmarks: Sequence[Landmark],
    tracks: NDArray[np.int64],
    anchors: dict[float, FloatArray],
    anchor_stamps: FloatArray,
    path_at: Callable[[float], float],
    graph: Any,
) -> CrossAxis | None:
    """The decision of the module docs for one run; None when the tracks are too short to
    measure the spread or the anchors do not move (the factors then keep their sigmas)."""
    spread = cross_axis_spread(landmarks, tracks, anchors)
    odom = odometry_across_sigma_m(anchor_stamps, path_at, graph)
    if spread is None or odom is None:
        return None
    return CrossAxis(spread[0], spread[1], odom, spread[2])
