"""Sequential boundary factors: a boundary tracked within one pass measures the axial motion
between the anchors that see it (beyond the paper, which uses boundaries only for loops).

Loops between the outbound and the return pass say the passes must agree; they cannot say
which pass is wrong, so with uneven drift (outbound -5 %, return -15 %) the optimiser meets
them halfway and the outbound pass gets worse. A boundary seen from two anchors of the same
pass is where it is: the change of its position relative to each anchor comes from the
LiDAR, not the odometry, and measures their displacement along the axis directly, scale
error and stall included.

For every track (:mod:`decod_rs.tracks`) its consecutive views from different anchors are
compared with the matcher (:func:`decod_rs.matching.compare`); a pair becomes a 5-DoF factor
(the loop factor of Eq. 3, between two anchors of one pass) only if

- the descriptors confirm it: compared under the pass's own heading only, chance agreement below
  ``matching.false_alarm_rate`` (one candidate) and an axial offset within the verification
  window;
- it agrees with the odometry: the implied correction is within
  ``consistency_tolerance_m + consistency_drift_fraction * path`` (a wrong association with
  a neighbouring joint implies a jump of a joint spacing over a few decimetres of path).

Weight: the axial detection noise *measured* on the tracks. Within a track, view positions
(odometry frame, along the axis) scatter by the detection noise plus the odometry's drift
over the few seconds between views; a straight line in time per track absorbs the drift, and
the pooled residual spread (``n - 2`` degrees of freedom per track) is the noise, floored at
the profile bin and capped at the loop sigma. ``report.json`` records it.

Across the axis: the origin of a boundary is the contour's centre at it, and where the
section is not round (a tunnel's flat invert, a horseshoe's floor) that centre moves with
how much of the section a view sees, so two views of one ring from 3 m and from 10 m place
it at different heights. The odometry, which the walls constrain across the corridor, does
not (2-5 mm vertical RMS in the simulated tunnels), yet with one isotropic sigma the loop and
sequential factors pulled the corrected trajectory 0.19 m off vertically (shield + 64 beams;
the position RMSE after correction was mostly that). So the spread of the views across the
axis is measured too (:func:`transverse_noise_m`: about its track's mean, the odometry frame,
pooled) and every landmark factor, loops included, takes it as its sigma across the axis
(never below the loop sigma); along the axis the sigmas stay as they were.

Axial offset at ribs: a pair's factor puts the earlier view's boundary at its origin plus
the verification's axial offset ``dz`` (the mean row offset of the inliers). Where the
corridor's boundaries are ribs (steel arches: :func:`boundary_polarity` at most
``RIB_POLARITY``), a far view does not see behind them, and the one-row votes lean. On
consecutive views of one arch (exact poses, 0.25 m rows), ``dz`` averaged +1.0 cm per 2.4 m
pair against +0.4 cm from the origins alone (217 pairs), and the tracks read it as 0.6 % of
odometry scale. So there, an offset within half a row of 0 is taken as 0: the two views
are of the same feature, and the side-lobe rule (``src/boundary.rs``) places both origins
to about 1 cm. The loop factors do the same at ribs (``stages.solve.loop_constraints``: the
horseshoe with the forward sensor and a turn, 85 -> 90 % of RMSE reduction, no loop lost or
wrong in the matrix's horseshoe cells). At grooves (pipe joints, ring seams) the offset is
kept. In the pipes a row is 2-3 cm, and its sub-cell part is worth more than the origins:
taking 0 there too cost pe with the forward sensor 10-17 points of RMSE reduction in the
matrix, and for every loop two wrong loops in the shield.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from decod_rs._core import Landmark, PairResult
from decod_rs.end_faces import FaceFactors
from decod_rs.graph import LoopConstraint
from decod_rs.matching import PairMemo
from decod_rs.side_offset import SideOffset, measure_side_offset, without_offset
from decod_rs.tracks import offsets_from_track_means, world_origins

FloatArray = NDArray[np.float64]

__all__ = [
    "SequentialFactors",
    "at_ribs",
    "axial_offset_m",
    "boundary_polarity",
    "detection_noise_m",
    "same_boundary",
    "sequential_constraints",
    "transverse_noise_m",
]


@dataclass
class SequentialFactors:
    """The factors and what became of the candidate pairs."""

    constraints: list[LoopConstraint]
    sigma_m: float
    pairs: int
    rejected: dict[str, int]
    sigma_transverse_m: float | None = None
    polarity: float | None = None
    #: The factors between views of an end face (:mod:`decod_rs.end_faces`), also in
    #: ``constraints``.
    end_faces: FaceFactors | None = None
    #: The side offset measured on these factors and removed from them
    #: (:mod:`decod_rs.side_offset`).
    side: SideOffset | None = None

    def report(self) -> dict[str, Any]:
        faces = self.end_faces
        return {
            "factors": len(self.constraints),
            "end_face_factors": 0 if faces is None else len(faces.constraints),
            "end_face_jumps": 0 if faces is None else faces.jumps,
            "candidate_pairs": self.pairs,
            "rejected": self.rejected,
            "detection_sigma_m": self.sigma_m,
            "transverse_sigma_m": self.sigma_transverse_m,
            "boundary_polarity": self.polarity,
            "ribs": at_ribs(self.polarity),
            "side_offset": None if self.side is None else self.side.report(),
        }


#: Polarity (:func:`boundary_polarity`) at or below which a corridor's boundaries are ribs:
#: measured -1.05 and -1.1 on the simulated horseshoe arches (64 beams, forward sensor),
#: -0.02 to +0.73 on the pipes' grooves and the shield's ring seams.
RIB_POLARITY = -0.5

#: Views :func:`boundary_polarity` reads at most (evenly spaced): 0.07 ms each, and the
#: median of 64 is as clear as that of all (horseshoe -1.05 of 648 views).
POLARITY_VIEWS = 64


def boundary_polarity(landmarks: Sequence[Landmark]) -> float | None:
    """How the surface stands at a corridor's boundaries: the median over the views of the
    mean descriptor offset of the two rows about the boundary, in units of the descriptor's
    robust spread (1.4826 MAD); negative where the surface stands inwards (steel arches,
    ribs), positive at grooves; from at most ``POLARITY_VIEWS`` views, evenly spaced. None
    without landmarks."""
    values = []
    step = max(1, len(landmarks) // POLARITY_VIEWS)
    for lm in list(landmarks)[::step]:
        d, m = np.asarray(lm.descriptor), np.asarray(lm.mask, dtype=bool)
        r = d.shape[0] // 2
        centre, every = d[r - 1 : r + 1][m[r - 1 : r + 1]], d[m]
        if centre.size == 0 or every.size == 0:
            continue
        spread = 1.4826 * float(np.median(np.abs(every - np.median(every))))
        if spread > 0:
            values.append(float(centre.mean()) / spread)
    return float(np.median(values)) if values else None


def at_ribs(polarity: float | None) -> bool:
    """Whether a corridor of this :func:`boundary_polarity` has ribs for boundaries."""
    return polarity is not None and polarity <= RIB_POLARITY


def axial_offset_m(dz_m: float, cell_z_m: float, ribs: bool) -> float:
    """The verification's axial offset ``dz_m`` as a factor uses it: at ribs, 0 within half a
    descriptor row (``cell_z_m``) of 0 (module docs, "Axial offset at ribs")."""
    return 0.0 if ribs and abs(dz_m) < 0.5 * cell_z_m else float(dz_m)


#: Degrees of freedom (views beyond two per track, summed) below which the detection noise
#: is not considered measured and the loop sigma stands in: a spread from a handful of
#: residuals said 0.7 mm on a pe pipe, where views of one coupler from near and far differ by
#: centimetres.
MIN_NOISE_DOF = 10


def detection_noise_m(
    stamps: FloatArray,
    axial: FloatArray,
    tracks: NDArray[np.int64],
    floor_m: float,
    unmeasured_m: float | None = None,
) -> float:
    """Pooled residual spread of view positions about a line in time per track (module
    docs), at least ``floor_m``; ``unmeasured_m`` (default ``floor_m``) when the tracks hold
    fewer than ``MIN_NOISE_DOF`` degrees of freedom."""
    sq, dof = 0.0, 0
    for t in np.unique(tracks):
        idx = np.flatnonzero(tracks == t)
        if idx.size < 3:
            continue
        x = stamps[idx] - stamps[idx].mean()
        design = np.column_stack([np.ones_like(x), x])
        coef, *_ = np.linalg.lstsq(design, axial[idx], rcond=None)
        sq += float(np.sum((axial[idx] - design @ coef) ** 2))
        dof += idx.size - 2
    if dof < MIN_NOISE_DOF:
        return floor_m if unmeasured_m is None else unmeasured_m
    return max(float(np.sqrt(sq / dof)), floor_m)


def transverse_noise_m(
    landmarks: Sequence[Landmark],
    tracks: NDArray[np.int64],
    anchors: dict[float, FloatArray],
    floor_m: float,
) -> float | None:
    """Spread across the corridor of the views of one boundary (module docs, "Across the
    axis"): pooled RMS over the tracks of each view origin's offset from its track's mean,
    the along-axis part removed, in the odometry frame; at least ``floor_m``; None when the
    tracks hold fewer than ``MIN_NOISE_DOF`` degrees of freedom (two per view beyond the
    first of each track)."""
    if len(landmarks) == 0:
        return None
    where = world_origins(landmarks, anchors)
    axes = np.array([lm.axis for lm in landmarks]).reshape(-1, 3)
    axes *= np.sign(axes @ axes[0])[:, None]
    sq, dof = 0.0, 0
    for idx, d in offsets_from_track_means(where, tracks):
        a = axes[idx].mean(axis=0)
        a /= max(float(np.linalg.norm(a)), 1e-12)
        d -= np.outer(d @ a, a)
        sq += float(np.sum(d**2))
        dof += 2 * (idx.size - 1)
    if dof < MIN_NOISE_DOF:
        return None
    return max(float(np.sqrt(sq / dof)), floor_m)


def _verdict(pair: PairResult, matching: Any) -> str:
    """Why a within-pass pair is not one boundary ("" if it is)."""
    if pair.rejection is not None:
        return pair.rejection
    if abs(pair.heading_deg) > 90.0:
        return "heading"
    if pair.chance > float(matching.false_alarm_rate):
        return "chance"
    return ""


def same_boundary(
    landmarks: Sequence[Landmark], matching: Any, pairs: PairMemo | None = None
) -> Callable[[list[tuple[int, int]]], list[bool]]:
    """A track-link confirmation (:func:`decod_rs.tracks.group_views`): the matcher
    verifies each (earlier, later) pair as one boundary (all pairs in one batch; through
    ``pairs`` when given, so later rounds reuse them)."""
    memo = pairs if pairs is not None else PairMemo(landmarks, matching)

    def confirm(links: list[tuple[int, int]]) -> list[bool]:
        found = memo.compare([(j, i) for i, j in links])
        return [not _verdict(p, matching) for p in found]

    return confirm


def sequential_constraints(
    landmarks: Sequence[Landmark],
    tracks: NDArray[np.int64],
    anchors: dict[float, FloatArray],
    anchor_stamps: FloatArray,
    path_at: Any,
    cfg: Any,
    sigma_transverse_m: float | None = None,
    pairs: PairMemo | None = None,
    *,
    polarity: float | None,
    sigma_vertical_m: float | None = None,
) -> SequentialFactors:
    """Factors between consecutive views of every track (module docs). ``path_at(stamp)``:
    path length along the odometry at a stamp (metres); ``sigma_transverse_m``: their sigma
    across the axis (:func:`transverse_noise_m`; None: the same as along it); ``pairs``:
    the comparisons already made on ``landmarks`` (the track links', earlier rounds');
    ``polarity``: :func:`boundary_polarity` of ``landmarks``; ``sigma_vertical_m``: their
    vertical sigma over ``sigma_transverse_m`` (:mod:`decod_rs.cross_axis`; None: that)."""
    m = cfg.matching
    where = world_origins(landmarks, anchors)
    stamps = np.array([lm.submap_stamp for lm in landmarks])
    axes = np.array([lm.axis for lm in landmarks]).reshape(-1, 3)
    axial = np.einsum("ij,ij->i", where, axes) if len(landmarks) else np.zeros(0)
    # Axes of one corridor agree up to sign; orient by the first so positions compare.
    if len(landmarks):
        axial *= np.sign(axes @ axes[0])
    loop_sigma = float(cfg.graph.landmark_position_sigma_m)
    floor = float(cfg.boundary.profile_bin_m)
    sigma = min(detection_noise_m(stamps, axial, tracks, floor, loop_sigma), loop_sigma)
    ribs = at_ribs(polarity)
    out = SequentialFactors(
        constraints=[],
        sigma_m=sigma,
        pairs=0,
        rejected={},
        sigma_transverse_m=sigma_transverse_m,
        polarity=polarity,
    )
    consecutive = []
    for t in np.unique(tracks):
        views = sorted((int(k) for k in np.flatnonzero(tracks == t)), key=lambda k: stamps[k])
        consecutive += [(a, b) for a, b in itertools.pairwise(views) if stamps[a] != stamps[b]]
    memo = pairs if pairs is not None else PairMemo(landmarks, m)
    results = memo.compare([(b, a) for a, b in consecutive])
    out.pairs = len(consecutive)
    for (a, b), pair in zip(consecutive, results, strict=True):
        why = _verdict(pair, m)
        ok = not why
        dz = axial_offset_m(pair.dz_m, landmarks[a].cell_z_m, ribs)
        earlier = np.asarray(landmarks[a].origin) + dz * np.asarray(landmarks[a].axis)
        if ok:
            pose = anchors[stamps[a]]
            shift = pose[:3, :3] @ earlier + pose[:3, 3] - where[b]
            path = abs(path_at(stamps[b]) - path_at(stamps[a]))
            allowance = m.consistency_tolerance_m + m.consistency_drift_fraction * path
            ok, why = (True, "") if np.linalg.norm(shift) <= allowance else (False, "jump")
        if not ok:
            out.rejected[why] = out.rejected.get(why, 0) + 1
            continue
        out.constraints.append(
            LoopConstraint(
                query_index=int(np.argmin(np.abs(anchor_stamps - stamps[b]))),
                db_index=int(np.argmin(np.abs(anchor_stamps - stamps[a]))),
                query_origin=np.asarray(landmarks[b].origin, dtype=np.float64),
                query_axis=np.asarray(landmarks[b].axis, dtype=np.float64),
                db_origin=earlier,
                db_axis=np.asarray(landmarks[a].axis, dtype=np.float64),
                kind="sequential",
                sigma_m=sigma,
                sigma_transverse_m=sigma_transverse_m,
                sigma_vertical_m=sigma_vertical_m,
            )
        )
    poses = [anchors[t] for t in anchor_stamps]
    out.side = measure_side_offset(out.constraints, poses)
    out.constraints = without_offset(out.constraints, out.side)
    return out
