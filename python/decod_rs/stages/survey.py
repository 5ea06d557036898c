"""The run against an earlier survey (``--survey``), between stage 4 and stage 5
(:mod:`decod_rs.reinspection`)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from decod_rs.config import Config
from decod_rs.graph import CorrectionResult
from decod_rs.reinspection import Reinspection, reinspect
from decod_rs.stages.extract import SubmapLandmarks
from decod_rs.survey import Survey
from decod_rs.tracks import (
    views_per_landmark,
)

FloatArray = NDArray[np.float64]


def reinspect_run(
    survey: Survey,
    ex: SubmapLandmarks,
    tracks: NDArray[np.int64],
    scans: tuple[FloatArray, FloatArray],
    correction: CorrectionResult,
    cfg: Config,
) -> tuple[Reinspection, CorrectionResult]:
    """The run against an earlier survey, and the trajectory moved into its frame when the
    cross-session loops place it (:mod:`decod_rs.reinspection`)."""
    stamps = np.asarray(ex.anchor_stamps, dtype=np.float64)
    views = views_per_landmark(tracks)
    stage = reinspect(survey, ex.landmarks, views, stamps, scans, correction.poses, cfg)
    if stage.poses is not None:
        correction = replace(correction, poses=stage.poses)
    return stage, correction
