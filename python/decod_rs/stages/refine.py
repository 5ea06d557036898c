"""Stages 1-4 again on submaps stitched by the first corrected trajectory, where it stitches
them differently enough (:mod:`decod_rs.refinement` decides and judges the round)."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from decod_rs.config import Config
from decod_rs.focus import focused_stitching
from decod_rs.parking import set_aside
from decod_rs.refinement import MAX_ROUNDS, RebuildDecision, rebuild_decision
from decod_rs.stages.extract import Extracted, SubmapLandmarks, restitched
from decod_rs.stages.match import Matched, match_and_select
from decod_rs.stages.solve import Solved, solve

FloatArray = NDArray[np.float64]


def rebuild(
    extraction: Extracted, cfg: Config, corrected: FloatArray, progress: bool
) -> SubmapLandmarks:
    """Stage 1 again, the submaps stitched by the corrected trajectory; the anchors placed
    on the odometry like the first ones (:mod:`decod_rs.refinement`)."""
    return restitched(extraction, cfg, corrected, progress, "rebuild")


def focused(
    extraction: Extracted, solved: Solved, split: float | None, cfg: Config, progress: bool
) -> tuple[Solved, tuple[dict[str, Any], ...]]:
    """``solved`` stitching the passes its round did not measure at their focus scale, where
    one is found (:mod:`decod_rs.focus`), and the focus of each such pass."""
    if not cfg.submap.focus_unmeasured:
        return solved, ()
    passes = 1 if split is None else 2
    reported = [] if solved.scale is None else solved.scale.passes
    if len(reported) == passes:
        unmeasured = [not bool(p["rescaled"]) for p in reported]
    else:  # a pass that did not move has no entry: look at every pass
        unmeasured = [True] * passes
    if not any(unmeasured):
        return solved, ()
    stamps = extraction.scans[0]
    topics = (extraction.processor.points_topic, extraction.imu_topic)
    stitch, found = focused_stitching(
        extraction.log, topics, stamps, solved.stitching, split, unmeasured, cfg, progress
    )
    if any(f.applied for f in found):
        solved = replace(solved, stitch=stitch)
    return solved, tuple(f.report() for f in found)


def rescaled_passes(solved: Solved) -> int:
    """How many passes of a round had their scale measured and applied."""
    return 0 if solved.scale is None else sum(bool(p["rescaled"]) for p in solved.scale.passes)


def rebuilt(
    extraction: Extracted,
    ex: SubmapLandmarks,
    matched: Matched,
    solved: Solved,
    cfg: Config,
    mode: str,
    progress: bool,
) -> tuple[SubmapLandmarks, Matched, Solved, list[RebuildDecision]]:
    """Stages 1-4 again on submaps rebuilt on the corrected trajectory, for as long as the
    newest correction stitches them differently enough from the trajectory they were
    stitched on and the rebuilt round stands (:mod:`decod_rs.refinement`: at most
    ``MAX_ROUNDS`` rebuilds). Before the first, a pass the first round did not measure is
    stitched at its focus scale where one is found (:func:`focused`). The decisions of the
    rounds, first to last."""
    scans = extraction.scans
    stitched_on = scans[1]  # the first submaps were stitched on the odometry
    decisions: list[RebuildDecision] = []
    while len(decisions) < MAX_ROUNDS:
        solved, focus = (
            focused(extraction, solved, matched.split, cfg, progress)
            if not decisions
            else (solved, ())
        )
        decision = replace(rebuild_decision(stitched_on, solved.stitching, cfg), focus=focus)
        if not decision.needed:
            decisions.append(decision)
            break
        # The earlier round's landmarks wait on disk while the rebuilt round runs, and after it
        # if it stands (the extraction's own until a replay asks for them: `restored`).
        earlier = [ex.landmarks] + ([] if matched.pairs is None else [matched.pairs.landmarks])
        with set_aside(earlier) as parked:
            ex2 = rebuild(extraction, cfg, solved.stitching, progress)
            matched2 = match_and_select(
                ex2, cfg, mode, *scans, link_frame=solved.stitching, progress=progress
            )
            matched2, solved2 = solve(
                ex2, matched2, cfg, scans, True, extraction.gap_factors, progress=progress
            )
            decision = replace(
                decision,
                loops=(sum(matched.keep), sum(matched2.keep)),
                rescaled=(rescaled_passes(solved), rescaled_passes(solved2)),
            )
            if decision.kept:
                parked.leave()
        decisions.append(decision)
        if not decision.kept:
            break
        if ex is extraction.extracted:
            ex.parked = parked
        else:
            parked.discard()  # a rebuilt round's, replaced by the next: not needed again
        stitched_on = solved.stitching
        ex, matched, solved = ex2, matched2, solved2
    return ex, matched, solved, decisions
