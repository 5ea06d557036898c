"""End faces seen within one pass: the axial motion between the anchors that see the end of
the corridor (beyond the paper).

Driving back to where it started, a forward-looking sensor sees the tunnel's end face (a
blind end, a shaft wall, a pipe's cap) from as far as its range window reaches. Near the end
the wall ahead is too short a stub for a boundary seen from two anchors, so before this
nothing measured the last 9-26 m of the return (``report.json`` ``unmeasured``), and the
corrected trajectory there was the odometry rescaled by the pass's average scale: in the
held-out 9 m shield with the forward sensor and symmetric drift, the return's scale changes
along it and the corrected end was 0.82 m off where the odometry was 1.20 m off.

The face is where it is: its distance along its normal from each anchor that sees it
(``decod_rs._core.SubmapDiagnostics.face_point``, the foot of the sensor on the face;
``src/corridor_end.rs``, also in the last submaps that are no corridor) comes from the
LiDAR, so the change between two anchors of one pass measures their displacement along the
axis, like a boundary tracked within a pass (:mod:`decod_rs.sequential`). Placed with the
ground truth, the views of the held-out 9 m shield's face (16, 12 and 8 m away) put it within
1.5 cm of where it is; stitched on the ground truth, those of a 7 m shield within 1 cm and of
the 10 m horseshoe within 1.3 cm (2.7 cm from 3 m, its floor in view).

Consecutive views of one pass become a factor when the anchors moved apart (by the detection
sigma or more: at a standstill a pair measures nothing the odometry does not) and the
odometry agrees with them (``consistency_tolerance_m + consistency_drift_fraction * path``,
the sequential factors' rule, along the face's normal: a face mistaken for another implies a
jump). The factor is the
landmark factor of Eq. 3 between the two anchors, on the feet and the face's normals; along
the axis it takes the detection noise measured on the run's boundary tracks (a face is
measured at least as well as a boundary); across it the feet are wherever the sensor was, so
the factor does not constrain it (:data:`ACROSS_SIGMA_M`: the walls and the odometry hold the
robot across the corridor). The factors join the sequential ones, so the passes' scales
(:mod:`decod_rs.odometry_scale`) take them too: kept out of the scales (m120 against m119,
the same logs), the held-out 9 m shield under uneven drift fell back to 4 loops and a 56 %
endpoint reduction, and four more rows missed a target.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from decod_rs.graph import LoopConstraint

FloatArray = NDArray[np.float64]

__all__ = ["ACROSS_SIGMA_M", "FaceFactors", "FaceView", "face_constraints", "tied_anchors"]

#: Sigma across the axis of a face factor, metres: large against the odometry's few
#: centimetres across a corridor, so the factor measures along the axis only.
ACROSS_SIGMA_M = 1.0


@dataclass(frozen=True)
class FaceView:
    """An end face in view of one anchor: its stamp, the foot of the sensor on the face and
    the face's unit normal (anchor frame)."""

    stamp: float
    point: FloatArray
    normal: FloatArray


@dataclass
class FaceFactors:
    """The factors and how many consecutive pairs of views were rejected as a jump."""

    constraints: list[LoopConstraint]
    pairs: int
    jumps: int


def face_constraints(
    views: Sequence[FaceView],
    anchors: dict[float, FloatArray],
    anchor_stamps: FloatArray,
    path_at: Callable[[float], float],
    split: float | None,
    cfg: Any,
    sigma_m: float,
) -> FaceFactors:
    """Factors between consecutive views of an end face within each pass (module docs).
    ``anchors``: world pose (odometry frame) by anchor stamp; ``path_at(stamp)``: path length
    along the odometry; ``split``: the stamp between the passes (None: one pass);
    ``sigma_m``: the sigma along the axis."""
    m = cfg.matching
    out = FaceFactors(constraints=[], pairs=0, jumps=0)
    ordered = sorted(views, key=lambda v: v.stamp)
    for a, b in itertools.pairwise(ordered):
        if split is not None and (a.stamp <= split) != (b.stamp <= split):
            continue  # views of different passes: their agreement is a loop's business
        path = abs(path_at(b.stamp) - path_at(a.stamp))
        if path < sigma_m:
            continue  # at a standstill the pair measures nothing the odometry does not
        out.pairs += 1
        # Where the odometry puts the face from each anchor, along the face's normal (the
        # feet also move across it, with the robot).
        pose_a, pose_b = anchors[a.stamp], anchors[b.stamp]
        normal = pose_a[:3, :3] @ a.normal
        apart = float((_world(pose_a, a.point) - _world(pose_b, b.point)) @ normal)
        allowance = m.consistency_tolerance_m + m.consistency_drift_fraction * path
        if abs(apart) > allowance:
            out.jumps += 1
            continue
        out.constraints.append(
            LoopConstraint(
                query_index=int(np.argmin(np.abs(anchor_stamps - b.stamp))),
                db_index=int(np.argmin(np.abs(anchor_stamps - a.stamp))),
                query_origin=b.point,
                query_axis=b.normal,
                db_origin=a.point,
                db_axis=a.normal,
                kind="sequential",
                sigma_m=sigma_m,
                sigma_transverse_m=ACROSS_SIGMA_M,
            )
        )
    return out


def _world(pose: FloatArray, point: FloatArray) -> FloatArray:
    return np.asarray(pose[:3, :3] @ point + pose[:3, 3], dtype=np.float64)


def tied_anchors(faces: FaceFactors | None, anchor_stamps: FloatArray) -> list[float]:
    """The stamps of the anchors the face factors tie, first to last (for the figure)."""
    if faces is None:
        return []
    ends = {k for c in faces.constraints for k in (c.db_index, c.query_index)}
    return [float(anchor_stamps[k]) for k in sorted(ends)]
