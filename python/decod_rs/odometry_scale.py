"""The odometry's scale along the corridor, measured by the boundaries each pass tracks
(beyond the paper).

A sequential factor (:mod:`decod_rs.sequential`) pins the axial displacement of two anchors
of one pass where a boundary is in view of both; between such windows the graph has only
the odometry, so a pass that under-reports its distance by 5 % keeps that error there, and
loop closures then meet the passes halfway. But the scale error of LiDAR odometry in a
degenerate corridor varies slowly along the path (simulated and real frontends alike drift
by a few per cent per leg, not per metre), so the windows that *are* measured say what the
scale is in the gaps too.

Per pass (outbound and return, split at the turnaround), with ``u_k`` the odometry's axial
position of anchor ``k`` along the pass direction, one scale ``s_k`` per anchor interval is
the posterior mean of a linear Gaussian model:

- every sequential pair ``(a, b)`` measures ``sum_{k=a}^{b-1} s_k (u_{k+1} - u_k) = D_ab``,
  the LiDAR-measured axial displacement (the boundary seen from ``a`` minus the same boundary
  seen from ``b``, both rotated into the world with the odometry's attitude, which the walls
  constrain), sigma ``sqrt(2)`` times the measured detection noise;
- the scales are the pass's own scale (prior 1, sigma 1: it only matters where nothing else
  does) plus a deviation per interval of spread ``tau``, correlated over ``length`` metres of
  path (exponentially): the *slip model*. ``tau`` and ``length`` are chosen per pass by the
  evidence (the marginal likelihood of the pairs) among ``SLIP_SPREADS`` x
  ``SLIP_LENGTHS_M``; a spread must raise it by ``SLIP_EVIDENCE_MARGIN`` over none. Odometry
  whose scale holds for a pass (one frontend on one kind of wall) gets ``tau = 0``: one
  measured scale for the pass, the loops and sequential factors of the graph taking up the
  rest. Odometry whose scale changes along the way (wheels that slip more on some stretches,
  a LiDAR odometry that under-reads featureless ones more) gets the deviations its pairs
  show; between measured windows they decay to the pass's scale over ``length``, so a gap
  takes the pass's scale, not the last window's.

  It replaced a smoothness prior on ``s_{k+1} - s_k`` of 0.1 % per metre of path, one fixed
  walk for every log, which kept each pass close to one scale. Measured then: 1 %/m followed
  the measured windows and carried their local scale into the gaps (horseshoe 1.10 -> 0.45 m,
  worse than the 0.20 m without rescaling); 0.3 %/m on the whole matrix (m97 against m95) no
  net gain. With the slip model (m152 against m147, the m88 logs): corrected RMSE geometric
  mean x0.955 (28 rows better by more than 10 %, 15 worse), registry runs with every joint
  within 1 % 75 -> 76 of 98, 11,407 -> 11,455 loops, none wrong; fresh tier (fresh20 against
  fresh19) x0.991, registry 19 -> 21 of 30; the full tier under odometry that slips (scale
  errors of sections of 3-15 m in [-15 %, -1 %], ``--profiles slip``, s3 against s1) x1.019,
  registry 26 -> 31 of 47 runs.

The scan odometry is then rescaled along the pass direction (where the corridor curves,
``axis.curved``, along the local direction of travel: :func:`travel_directions`; rotations
unchanged) and the pose graph starts from it. Scales are clipped to [0.5, 2]: a frontend
that stalls (KISS-ICP in the simulated pipes reports 0-2 % of the distance) has no usable
increments to rescale; ``report.json`` says how much of each pass the tracks measured. A
pass whose pairs do not measure its scale (``MIN_PAIRS``, ``MAX_SCALE_SIGMA``; pairs that
all lie in one stretch of a pass whose scale changes along it measure the stretch, not the
pass: :func:`_pass_scale_sigma`) keeps its odometry scale, and when the other pass was
measured, the graph trusts it less (``UNMEASURED_SIGMA_FACTOR``); when both were, it trusts
the less well measured pass less in proportion (``odometry_sigma_factors``).

Without a loop between the passes (``tied=False``), a pass is rescaled only when every other
pass is too. The odometry of a return pass usually errs with the same sign of scale as the
outbound's (one frontend, one corridor), so on the way back its error cancels the
outbound's, to nothing at the start when the scales are equal; only a loop or both passes'
own measurements can say by how much. Rescaling one pass alone keeps the other's error and
drops the cancellation:

- the outbound alone moves its end, and with it the whole return: in the matrix, a pe pipe
  whose outbound pass alone was measured (one pair, 1.042 against the true 1.048) and that
  closed no loop ended 1.78 m RMSE from the truth with the outbound rescaled, against the
  odometry's 1.32 m;
- the return alone starts from the outbound's wrong far end and holds that error all the
  way back: a 9 m shield seen by a forward sensor, with odometry whose scale error changed
  every 3-15 m between -15 % and -1 % (``slip``), closed no loop; its return, measured on
  the tunnel's end face (4 pairs, 1.134), was rescaled alone and the RMSE went 2.48 -> 3.69 m
  (the odometry's own 2.48 m with the rule of both passes).

Submaps rebuilt on the corrected trajectory (:mod:`decod_rs.stages.refine`) are still
stitched on a pass rescaled alone (:func:`decod_rs.stages.solve.optimise`), where only the
pass's own geometry counts: the held-out 10 m shield with the forward sensor under uneven
drift closes no loop in its first round, its return measured on the end face, and 12 in
the round rebuilt on the return rescaled (RMSE 1.77 -> 0.08 m; 0 loops when the rebuild
followed the output).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from decod_rs.graph import LoopConstraint
from decod_rs.maps import pass_of
from decod_rs.path_curve import path_length, points_along

FloatArray = NDArray[np.float64]

SCALE_LIMITS = (0.5, 2.0)
#: A pass is rescaled when at least ``MIN_PAIRS`` pairs measure its scale to within
#: ``MAX_SCALE_SIGMA`` (standard error of the pairs' ratios ``D_ab / (u_b - u_a)``, weighted
#: by ``|u_b - u_a| / (sqrt 2 sigma)``; or where the evidence chose a spread of scales along
#: the pass, the posterior sigma of the pass's mean scale under it if larger,
#: :func:`_pass_scale_sigma`, ``pass_scale_sigma`` in ``report.json``): a measured
#: 1.04 +- 0.02 is a better estimate than an assumed 1, whose error is the drift itself
#: (LiDAR odometry in a degenerate corridor is off by a few per cent per leg; 5-15 % under
#: the matrix's uneven profile). Over the 196 passes
#: of the generalisation matrix (m61), the measured scale was off the true one by 0.71 %
#: (mean) with one pair and 5 % allowed, 1.18 % with the three pairs and 3 % required before,
#: and by more than 2 % in 8 passes instead of 17: the pe pipe's passes, whose couplers are
#: tracked once or twice per pass, measured 1.04-1.20 to within 0.4-2 % and were left at 1.
#: A measured scale within one sigma of 1 is applied too: left at 1 instead (m104 against
#: m99, the same logs), the registry had every joint within 1 % in 67 runs of 96 instead of
#: 71, the far end within 1 % in 96 rows of 98 instead of 97, corrected RMSE x1.011.
MIN_PAIRS = 1
MAX_SCALE_SIGMA = 0.05
#: Odometry sigmas of a pass that was not rescaled, relative to a rescaled one, when the
#: other pass was: its scale error is the odometry's drift (15 % on the return of the
#: matrix's uneven profile) against the measured pass's 1-2 %, so the loops should move it,
#: not meet it halfway. When both were rescaled, the pass measured less well gets the ratio
#: of the two scale errors, up to this factor: the loops then share the disagreement left
#: after rescaling in proportion to what is known of each pass (one or two pe coupler pairs
#: measure a pass to 2-5 %, a hundred shield ring pairs to 0.2 %). Full matrix (m63 -> m70):
#: outbound far end within 1 % in 88 -> 91 of 98 rows, position RMSE -80 % where the
#: odometry drifted >= 1 m in 67 -> 69 of 75 (pe forward uneven turn 0.36 -> 0.14 m,
#: symmetric reverse 0.28 -> 0.08 m), no wrong loop.
UNMEASURED_SIGMA_FACTOR = 3.0

__all__ = ["ScaleEstimate", "odometry_sigma_factors", "rescale_odometry", "travel_directions"]


@dataclass
class ScaleEstimate:
    """Per pass: anchors, sequential pairs used, the mean scale applied and the share of the
    pass's odometry distance that some pair measured."""

    passes: list[dict[str, Any]] = field(default_factory=list)


#: The slip model's candidates (module docs): the spread ``tau`` of the interval scales
#: about the pass's own scale and their correlation length along the path (m).
SLIP_SPREADS = (0.0, 0.0025, 0.005, 0.01, 0.02, 0.04, 0.08)
SLIP_LENGTHS_M = (2.0, 5.0, 15.0)
#: A spread above 0 must raise the evidence by this much (natural log) over no spread: the
#: price of one more parameter (BIC-like with a handful of pairs).
SLIP_EVIDENCE_MARGIN = 2.0


def _pass_scales(
    u: FloatArray, pairs: list[tuple[int, int, float]], sigma_m: float
) -> tuple[FloatArray, float, tuple[float, float]]:
    """Scales of the ``len(u) - 1`` intervals, the measured share of the distance and the
    chosen ``(tau, length)`` of the slip model (module docs)."""
    n = u.size - 1
    du = np.diff(u)
    a_mat, y, counts, gap = _pair_design(u, pairs)
    covered = np.any(a_mat != 0.0, axis=0)
    total = float(np.abs(du).sum())
    share = float(np.abs(du[covered]).sum() / total) if total > 0 else 0.0
    if not pairs:
        return np.ones(n), share, (0.0, 0.0)
    residual = y - a_mat.sum(axis=1)  # against every scale 1
    best: tuple[float, FloatArray, tuple[float, float]] | None = None
    for tau in SLIP_SPREADS:
        for length in SLIP_LENGTHS_M if tau > 0 else SLIP_LENGTHS_M[:1]:
            prior, c = _slip_covariances(a_mat, counts, gap, sigma_m, (tau, length))
            sign, logdet = np.linalg.slogdet(c)
            if sign <= 0:
                continue
            solved = np.linalg.solve(c, residual)
            evidence = -0.5 * (residual @ solved + logdet)
            if tau > 0:
                evidence -= SLIP_EVIDENCE_MARGIN
            if best is None or evidence > best[0]:
                best = (evidence, 1.0 + prior @ a_mat.T @ solved, (tau, length if tau else 0.0))
    if best is None:
        return np.ones(n), share, (0.0, 0.0)
    return np.clip(best[1], *SCALE_LIMITS), share, best[2]


def _pair_design(
    u: FloatArray, pairs: list[tuple[int, int, float]]
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """The slip model's design, pairs between the same two anchors taken together: per
    anchor pair the odometry's length of each interval it spans (``(groups, intervals)``),
    the mean measured displacement and the number of pairs averaged (each mean has the
    noise of one pair over that number), and the path distance between the intervals'
    middles (``(intervals, intervals)``).

    The means are sufficient statistics of the Gaussian model: the scales and the evidence's
    differences between slip models are those of the pairs one by one, but the solves are of
    the anchor pairs' size. One by one they grew with the cube of the pairs (a 64-beam shield
    sees each ring from the same two anchors several times: 1,200 pairs along a 300 m pass
    took 1.3 s a solve, and a kilometre would take minutes)."""
    du = np.diff(u)
    groups: dict[tuple[int, int], list[float]] = {}
    for a, b, d in pairs:
        groups.setdefault((a, b), []).append(d)
    a_mat = np.zeros((len(groups), du.size))
    y = np.zeros(len(groups))
    counts = np.zeros(len(groups))
    for i, ((a, b), ds) in enumerate(groups.items()):
        a_mat[i, a:b] = du[a:b]
        y[i] = float(np.mean(ds))
        counts[i] = len(ds)
    path = np.cumsum(np.abs(du)) - 0.5 * np.abs(du)
    return a_mat, y, counts, np.abs(path[:, None] - path[None, :])


def _slip_covariances(
    a_mat: FloatArray,
    counts: FloatArray,
    gap: FloatArray,
    sigma_m: float,
    slip: tuple[float, float],
) -> tuple[FloatArray, FloatArray]:
    """Under the slip model ``slip`` = ``(tau, length)``: the prior covariance of the
    intervals' scales (the pass's own scale, sigma 1, plus the spread ``tau`` correlated over
    ``length``) and the covariance of the anchor pairs' mean displacements (the design of
    :func:`_pair_design`, each mean with one pair's noise over its count)."""
    tau, length = slip
    prior = np.ones_like(gap)
    if tau > 0 and length > 0:
        prior += tau**2 * np.exp(-gap / length)
    return prior, a_mat @ prior @ a_mat.T + np.diag(2.0 * sigma_m**2 / counts)


def _pass_scale_sigma(
    u: FloatArray, pairs: list[tuple[int, int, float]], sigma_m: float, slip: tuple[float, float]
) -> float:
    """Posterior standard deviation of the pass's mean scale (its intervals' scales weighted
    by their odometry lengths: what the rescaled pass's length and far end follow) under the
    slip model the evidence chose (``slip`` = ``(tau, length)``; module docs).

    Without a spread it is the pairs' standard error (:func:`_measured_scale`, to the prior's
    1e-6). With one, pairs measure the stretches they cover: where they cover the pass, its
    mean scale is known as well as the pairs say; where they cover one stretch of it, the
    rest may differ from that stretch by about ``tau``, and so does the mean. Held out (seed
    251, the fresh tier's 16 beams pitched 20 deg in the horseshoe, symmetric drift): the
    return's 10 pairs, all within its first 5 m, measured 1.14 and 1.06 (true there 1.11 and
    1.08) with a spread of 8 % chosen; as a standard error they said 1.087 +- 0.0075 for the
    pass, whose odometry was within 0.2 % overall, and the rescaled return ended 3.35 m from
    the start instead of 1.20 m."""
    if not pairs:
        return float("inf")
    a_mat, _, counts, gap = _pair_design(u, pairs)
    length_of = np.abs(np.diff(u))
    if float(length_of.sum()) <= 0.0:
        return float("inf")
    w = length_of / length_of.sum()
    prior, c = _slip_covariances(a_mat, counts, gap, sigma_m, slip)
    m = a_mat @ prior @ w  # the covariance of the pairs with the pass's mean scale
    try:
        explained = float(m @ np.linalg.solve(c, m))
    except np.linalg.LinAlgError:
        return float("inf")
    return float(np.sqrt(max(float(w @ prior @ w) - explained, 0.0)))


def _measured_scale(
    u: FloatArray, pairs: list[tuple[int, int, float]], sigma_m: float
) -> tuple[float, float]:
    """The pass's scale from its pairs alone and its standard error (1, inf without)."""
    if not pairs:
        return 1.0, float("inf")
    du = np.array([u[b] - u[a] for a, b, _ in pairs])
    d = np.array([p[2] for p in pairs])
    keep = np.abs(du) > 1e-6
    if not np.any(keep):
        return 1.0, float("inf")
    w = (du[keep] / (np.sqrt(2.0) * sigma_m)) ** 2
    ratio = float(np.sum(w * d[keep] / du[keep]) / np.sum(w))
    return ratio, float(1.0 / np.sqrt(np.sum(w)))


def _direction(positions: FloatArray) -> FloatArray:
    d = positions[-1] - positions[0]
    norm = float(np.linalg.norm(d))
    return d / norm if norm > 1e-9 else np.array([1.0, 0.0, 0.0])


def odometry_sigma_factors(
    scan_stamps: FloatArray, estimate: ScaleEstimate, split_stamp: float | None
) -> FloatArray:
    """Per scan, the factor on the graph's odometry sigmas: on the pass whose scale is the
    less well known, the ratio of the two passes' scale errors (``measured_scale_sigma``; an
    unrescaled pass's is its drift, taken as infinite), at most ``UNMEASURED_SIGMA_FACTOR``;
    1 on the other pass, and everywhere when neither pass was rescaled."""
    out = np.ones(scan_stamps.size)
    errors = [
        float(p["measured_scale_sigma"]) if p["rescaled"] else np.inf for p in estimate.passes
    ]
    if split_stamp is None or len(errors) != 2 or not np.isfinite(min(errors)):
        return out
    k = int(np.argmax(errors))  # the pass measured less well (the outbound on a tie)
    worst, best = errors[k], errors[1 - k]
    ratio = UNMEASURED_SIGMA_FACTOR if worst >= best * UNMEASURED_SIGMA_FACTOR else worst / best
    out[pass_of(scan_stamps, split_stamp) == k] = ratio
    return out


def rescale_odometry(
    scan_stamps: FloatArray,
    scan_odom: FloatArray,
    anchor_stamps: FloatArray,
    anchor_odom: FloatArray,
    sequential: Sequence[LoopConstraint],
    sigma_m: float,
    split_stamp: float | None,
    tied: bool = True,
    curved: bool = False,
) -> tuple[FloatArray, ScaleEstimate]:
    """The scan odometry rescaled per pass along its direction (module docs); ``tied``:
    whether loops join the passes; ``curved``: the corridor curves (``axis.curved``), each
    step is stretched along the local direction of travel (:func:`travel_directions`)
    instead."""
    bounds = (
        [(-np.inf, np.inf)]
        if split_stamp is None
        else [(-np.inf, split_stamp), (split_stamp, np.inf)]
    )
    passes = [
        _measure_pass(scan_stamps, anchor_stamps, anchor_odom, sequential, sigma_m, lo, hi)
        for lo, hi in bounds
    ]
    if not tied and any(p is not None and not p.measured for p in passes):
        # One pass rescaled alone drops the cancellation of the passes' errors (module docs).
        for p in passes:
            if p is not None:
                p.measured = False
    out = scan_odom.copy()
    estimate = ScaleEstimate()
    offset = np.zeros(3)
    for p in passes:
        if p is None:
            continue
        if p.direction is None:
            out[p.scans, :3, 3] += offset
            continue
        scales = p.scales if p.measured else np.ones_like(p.scales)
        # Scan increments along the local direction of travel, scaled by their anchor
        # interval's scale.
        where = np.clip(np.searchsorted(p.anchor_stamps, scan_stamps[p.scans]) - 1, 0, None)
        where = np.minimum(where, scales.size - 1)
        positions = scan_odom[p.scans, :3, 3]
        steps = np.diff(positions, axis=0)
        if curved:
            local = travel_directions(positions, p.direction)
        else:
            local = np.broadcast_to(p.direction, steps.shape)
        along = np.einsum("ij,ij->i", steps, local)
        fixed = steps + ((scales[where[1:]] - 1.0) * along)[:, None] * local
        start = scan_odom[p.scans[0], :3, 3] + offset
        out[p.scans, :3, 3] = start + np.concatenate([np.zeros((1, 3)), np.cumsum(fixed, axis=0)])
        offset = out[p.scans[-1], :3, 3] - scan_odom[p.scans[-1], :3, 3]
        estimate.passes.append(p.report(scales))
    return out, estimate


#: The direction of travel at a scan is that of the path from this far behind it to this far
#: ahead of it (metres of travel; :func:`travel_directions`).
TANGENT_HALF_WINDOW_M = 1.0


def travel_directions(positions: FloatArray, fallback: FloatArray) -> FloatArray:
    """``(N - 1, 3)`` unit directions of travel of the steps between ``positions`` (N, 3): the
    path's chord from ``TANGENT_HALF_WINDOW_M`` of travel behind the step to as far ahead
    (clamped at the ends), ``fallback`` where the path does not move. Where the corridor
    curves, the pass's end-to-end direction is not the axis: rescaled along it, a return
    15 % short on a 50 m curve (0.6 rad over the 30 m pass) was bent sideways, which the
    graph, holding the odometry tight across its direction of travel, kept (held out, seed
    211). Only there: on the straight logs of the full tier the local directions, which
    follow the robot's wobble and turn at the turnaround, moved 46 of 100 rows' RMSE by
    more than 10 % (geometric mean x1.054, m162 against m159)."""
    p = np.asarray(positions, dtype=np.float64)
    n = p.shape[0]
    if n < 2:
        return np.zeros((0, 3))
    travel = path_length(p)
    mid = 0.5 * (travel[1:] + travel[:-1])
    ahead = points_along(p, travel, mid + TANGENT_HALF_WINDOW_M)
    chord = ahead - points_along(p, travel, mid - TANGENT_HALF_WINDOW_M)
    norm = np.linalg.norm(chord, axis=1, keepdims=True)
    return np.where(norm > 1e-9, chord / np.maximum(norm, 1e-12), np.asarray(fallback)[None, :])


@dataclass
class _Pass:
    """One pass's anchors, scans and what its sequential pairs measure."""

    scans: NDArray[np.int64]
    anchor_stamps: FloatArray
    direction: FloatArray | None = None
    scales: FloatArray = field(default_factory=lambda: np.ones(0))
    pairs: int = 0
    slip: tuple[float, float] = (0.0, 0.0)
    ratio: float = 1.0
    error: float = float("inf")
    #: The sigma of the pass's mean scale: ``error`` or, under a spread of scales, more.
    pass_error: float = float("inf")
    share: float = 0.0
    measured: bool = False

    def report(self, scales: FloatArray) -> dict[str, Any]:
        return {
            "anchors": int(self.anchor_stamps.size),
            "pairs": self.pairs,
            "mean_scale": float(np.mean(scales)),
            "measured_scale": self.ratio,
            "measured_scale_sigma": self.error,
            "pass_scale_sigma": self.pass_error,
            "measured_share": self.share,
            "rescaled": self.measured,
            "scale_spread": self.slip[0],
            "scale_length_m": self.slip[1],
        }


def _measure_pass(
    scan_stamps: FloatArray,
    anchor_stamps: FloatArray,
    anchor_odom: FloatArray,
    sequential: Sequence[LoopConstraint],
    sigma_m: float,
    lo: float,
    hi: float,
) -> _Pass | None:
    """The scans and anchors with stamps in ``(lo, hi]`` and the scale their pairs measure;
    None without scans; no direction with fewer than two anchors."""
    in_pass = np.flatnonzero((anchor_stamps > lo) & (anchor_stamps <= hi))
    scans = np.flatnonzero((scan_stamps > lo) & (scan_stamps <= hi))
    if scans.size == 0:
        return None
    p = _Pass(scans=scans, anchor_stamps=anchor_stamps[in_pass])
    if in_pass.size < 2:
        return p
    p.direction = _direction(anchor_odom[in_pass, :3, 3])
    u = anchor_odom[in_pass, :3, 3] @ p.direction
    local = {int(g): k for k, g in enumerate(in_pass)}
    pairs = []
    for c in sequential:
        a, b = local.get(c.db_index), local.get(c.query_index)
        if a is None or b is None or a == b:
            continue
        world_a = anchor_odom[c.db_index, :3, :3] @ c.db_origin
        world_b = anchor_odom[c.query_index, :3, :3] @ c.query_origin
        d = float((world_a - world_b) @ p.direction)
        pairs.append((min(a, b), max(a, b), d if b > a else -d))
    p.scales, p.share, p.slip = _pass_scales(u, pairs, sigma_m)
    p.ratio, p.error = _measured_scale(u, pairs, sigma_m)
    p.pass_error = max(p.error, _pass_scale_sigma(u, pairs, sigma_m, p.slip))
    p.pairs = len(pairs)
    p.measured = len(pairs) >= MIN_PAIRS and p.pass_error <= MAX_SCALE_SIGMA
    return p
