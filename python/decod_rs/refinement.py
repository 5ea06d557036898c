"""Submaps built again on the corrected trajectory (beyond the paper).

A submap stitches ``scans_per_submap`` scans with the odometry's relative poses. Where the
odometry's scale is off, so is the stitching: a pass whose odometry is 15 % short places a
boundary seen from the first and the last scan of a submap 15 % of the submap's travel
apart, and the descriptor sees a smeared ring (0.4 m at 1.3 m/s with 2 s submaps, more than
one 0.3 m descriptor row in the simulated shield tunnel). Descriptors of the two passes then
disagree exactly where the odometry is worst, which is where loops are needed.

After the first optimisation, loops and boundary tracks have measured each pass's scale, and
the corrected trajectory stitches better than the odometry. When the two disagree about the
distance travelled within one submap by more than half a descriptor row
(:func:`rebuild_threshold_m`; the 90th percentile over the distance travelled in
submap-length windows, :func:`travel_disagreement_m`), decod builds the submaps again on the
corrected trajectory and matches them again. Only the submaps' *content* changes: the pose
graph keeps the odometry's factors, and the new anchors are placed on the odometry like the
first ones, so no measurement is counted twice. ``submap.rebuild_on_correction = false``
turns it off.

The rebuilt round also *links* the views of a boundary into tracks (:mod:`decod_rs.tracks`)
in the first round's corrected trajectory rather than the odometry: a pass 15 % short puts
two views of one arch from anchors 2.4 m apart 0.36 m apart in the odometry frame, beyond
the track radius, so that pass had almost no track and its scale stayed unmeasured (5 pairs
on the return of the simulated horseshoe + forward sensor, endpoint 4.34 -> 1.75 m). In the
corrected frame the same views coincide; the sequential factors still measure against the
odometry (only which views belong together changes), the return's scale is measured (1.19,
40 pairs), and the last metres, where no loop closes, get it too (endpoint 0.02 m).

The corrected trajectory is not better everywhere: far from any loop it can stitch worse than
the odometry. So the rounds are compared (:func:`keep_rebuilt`), first by how many passes
had their scale measured and applied (:mod:`decod_rs.odometry_scale`), then by the loops
that survive the whole selection (how well the two passes' submaps agree); the rebuilt
submaps replace the first ones unless they measure fewer passes or close fewer loops by
more than the counts' own noise, ``sqrt(first + rebuilt)``. Strictly fewer loops was the
rule before: in the matrix (m94) it kept four first rounds over rebuilt ones that closed
one or two loops fewer (39 / 38, 9 / 8, 9 / 8, 15 / 13), and the 0.3 m hume pipe under
uneven drift, its first submaps stitched 15 % short, ended with the far end -2.3 % off and
an RMSE of 0.40 m; rebuilt, -0.7 % and 0.12 m (m95). The other three are pe pipes under
symmetric drift, whose far ends went -1.02 -> -0.32 % (forward sensor, reversing), -0.94 -> -1.18 %
(forward sensor, a turn) and -1.01 -> -1.01 % (16 beams, a turn): loop counts this small
do not say which stitching is better, and the odometry's own scale there is within 3 %.

Why passes come first: a pass whose scale is not measured keeps the odometry's drift
wherever no loop reaches, and loops are few exactly where that matters: in the matrix's pe
pipe with 16 beams and uneven drift the first round closed 4 loops with the return
unmeasured (its odometry 15 % short: endpoint 3.2 -> 2.1 m), the rebuilt round 2 with the
return measured at 1.18 (true 1.176), and the loop count had kept the first. (Loop ties go
to the rebuilt submaps: requiring strictly more loops kept one first-round loop 0.34 m off
in the matrix, and one more pe run ended above the odometry's RMSE.)

A second rebuild. The first rebuild is stitched on the first round's correction, and that
is only as good as what the first round measured: where its loops and tracks could not
measure a pass's scale, the first correction is as short as the odometry there, and so are
the rebuilt submaps. The rebuilt round, with cleaner tracks, often measures it; its
correction then disagrees with the trajectory the rebuilt submaps were stitched on, and the
same rule (the same threshold, now against that trajectory rather than the odometry) builds
them once more, kept or not by the same comparison. In the matrix's pe pipe with 16 beams
and uneven drift (ribs every 3.5 cm, 1.2 mm high), submaps stitched 15 % short put one
scan's ribs out of step with the next's and the detector took the steps for boundaries: 114
views on the return, 97 of them off any coupler. The first rebuild, still stitched about
15 % short on that pass, kept 59 of those; the second, stitched on a correction within
1-2 %, none (24 views, all at couplers), and the run went from 0 loops to 4
(pe-spin16-reverse-s1). Whole matrix (m92 against m89): a second rebuild ran in 7 of 100
rows (pipes and one shield row, never a 64-beam row: there the first correction already
measured both passes), 9,761 -> 9,780 loops, none wrong, joint coverage below 50 % in 5
rows instead of 6. ``MAX_ROUNDS`` caps it at two: run with a cap of three, none of those 7 rows
needed a third (after the second rebuild a submap's travel moved by at most 0.15 cm in the
0.4 m pipes against a 1 cm threshold, 0.6 cm against 3 cm in the 1.2 m pipe, 3.8 cm against
14 cm in the shield).

A re-inspection (``decod run --survey``) does not rebuild: its change report compares its
descriptors with the survey's, stitched on the survey's own odometry, and a second stitching
on one side only made unchanged joints differ (on the simulated hume re-inspection the
widened joint fell from the top three of ``changes.csv`` to fourth, and the coarse short
list held the exhaustive Top-1 in 87 of 90 queries instead of all).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from decod_rs.path_curve import path_length

FloatArray = NDArray[np.float64]

__all__ = [
    "MAX_ROUNDS",
    "RebuildDecision",
    "keep_rebuilt",
    "rebuild_decision",
    "rebuild_report",
    "rebuild_threshold_m",
    "travel_disagreement_m",
]

#: Percentile of the per-window disagreement that decides, over the distance travelled (a few
#: windows at a turn, where the trajectories differ in shape rather than scale, must not
#: decide alone).
PERCENTILE = 90.0

#: Rebuilds at most (module docs, "A second rebuild": no matrix row needed a third).
MAX_ROUNDS = 2


def travel_disagreement_m(odometry: FloatArray, corrected: FloatArray, scans: int) -> float:
    """How much the two trajectories (N x 4 x 4 at the same scan stamps) disagree about the
    distance travelled over ``scans`` consecutive scans: the 90th percentile of ``|corrected
    travel - odometry travel|`` over such windows, each weighed by the distance travelled in
    it (the larger of the two trajectories'), metres (0 for fewer scans or no travel).

    Weighed by distance, not counted by window: a robot standing still (an inspection stop,
    the turn in place at the far end) is stitched alike by both trajectories, and its windows
    once made most of a run that stopped for a minute, so that a pass 5 % short in motion
    was not rebuilt (the fresh tier's hume pipe with stops: 1.47 cm against a 1.5 cm
    threshold, where the same world driven through measured 1.84 cm)."""
    odometry, corrected = np.asarray(odometry), np.asarray(corrected)
    if odometry.shape != corrected.shape:
        raise ValueError(f"trajectories differ in shape: {odometry.shape} vs {corrected.shape}")
    n = int(scans)
    if n < 1:
        raise ValueError(f"scans_per_submap: {scans} must be >= 1")
    if odometry.shape[0] <= n:
        return 0.0
    a, b = path_length(odometry[:, :3, 3]), path_length(corrected[:, :3, 3])
    travel_a, travel_b = a[n:] - a[:-n], b[n:] - b[:-n]
    diff = np.abs(travel_b - travel_a)
    weight = np.maximum(travel_a, travel_b)
    total = float(weight.sum())
    if not total > 0.0:
        return 0.0
    order = np.argsort(diff, kind="stable")
    reached = np.cumsum(weight[order])
    k = int(np.searchsorted(reached, PERCENTILE / 100.0 * total))
    return float(diff[order][min(k, diff.size - 1)])


def rebuild_threshold_m(cfg: Any) -> float:
    """Half a descriptor row along the axis (``descriptor.half_length_m`` spans ``rows / 2``
    rows on either side of the boundary), metres."""
    rows = max(int(cfg.descriptor.rows), 1)
    return float(cfg.descriptor.half_length_m) / rows


@dataclass(frozen=True)
class RebuildDecision:
    """Whether to rebuild, and the figures behind it (``report.json`` ``rebuild``)."""

    needed: bool
    disagreement_m: float
    threshold_m: float
    loops: tuple[int, int] | None = None
    rescaled: tuple[int, int] = (0, 0)
    #: The focus of the passes the earlier round did not measure (:mod:`decod_rs.focus`),
    #: ``PassFocus.report()`` each.
    focus: tuple[dict[str, Any], ...] = ()

    @property
    def kept(self) -> bool:
        """Whether the rebuilt submaps replace the first ones (:func:`keep_rebuilt`)."""
        return self.loops is not None and keep_rebuilt(*self.loops, *self.rescaled)

    def report(self) -> dict[str, Any]:
        return {
            "rebuilt": self.needed,
            "kept": self.kept,
            "loops_first_and_rebuilt": None if self.loops is None else list(self.loops),
            "rescaled_passes_first_and_rebuilt": None
            if self.loops is None
            else list(self.rescaled),
            "travel_disagreement_m": self.disagreement_m,
            "threshold_m": self.threshold_m,
            "focus": list(self.focus),
        }


def keep_rebuilt(
    first_loops: int, rebuilt_loops: int, first_rescaled: int = 0, rebuilt_rescaled: int = 0
) -> bool:
    """The rebuilt submaps are kept unless they measure fewer passes' scales than the first
    ones or, measuring as many, close fewer loops by more than the counts' own noise,
    ``sqrt(first + rebuilt)`` (module docs)."""
    if rebuilt_rescaled != first_rescaled:
        return rebuilt_rescaled > first_rescaled
    return rebuilt_loops >= first_loops - math.sqrt(first_loops + rebuilt_loops)


def rebuild_decision(odometry: FloatArray, corrected: FloatArray, cfg: Any) -> RebuildDecision:
    """Rebuild when the corrected trajectory stitches a submap differently enough to move a
    boundary by more than half a descriptor row (module docs)."""
    disagreement = travel_disagreement_m(odometry, corrected, int(cfg.submap.scans_per_submap))
    threshold = rebuild_threshold_m(cfg)
    return RebuildDecision(disagreement > threshold, disagreement, threshold)


def rebuild_report(rounds: list[RebuildDecision]) -> dict[str, Any]:
    """``report.json`` ``rebuild``: the first rebuild's figures (whether it was needed, kept,
    the loops and measured passes of the first and rebuilt rounds, the disagreement and the
    threshold), ``rounds`` with every rebuild's in order (a second one is decided against
    the trajectory the first rebuilt submaps were stitched on), and ``rebuilds``: how many
    rebuilt rounds stand, so how many times the submaps that were used were stitched again."""
    if not rounds:
        raise ValueError("rebuild_report needs the decision of at least one round")
    report = rounds[0].report()
    report["rounds"] = [r.report() for r in rounds]
    stand = 0
    for r in rounds:
        if not r.kept:
            break
        stand += 1
    report["rebuilds"] = stand
    return report
