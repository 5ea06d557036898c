"""The survey stage of ``decod run --survey`` and the survey a run leaves behind: what
:mod:`decod_rs.pipeline` calls, so that Algorithm 1 there reads as before with one stage more.

- :func:`write_run_survey`: every run writes ``survey.decod`` (:mod:`decod_rs.survey`).
- :func:`reinspect`: match against the survey, keep the consistent pairs, place the run in
  the survey's frame (:mod:`decod_rs.survey`).
- :class:`Reinspection`: the stage's result; it adds the cross-session rows to ``loops.csv``
  (column ``session`` = ``survey``; their ``db_*`` fields are the survey's stamps and
  anchor-frame geometry), measures chainage along the survey's path, names the survey joint
  of each matched joint and writes the change report (:mod:`decod_rs.changes`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from decod_rs._core import Landmark
from decod_rs.aliasing import aliasing
from decod_rs.chainage import outbound_course
from decod_rs.changes import (
    ChangePair,
    changes_summary,
    joint_changes,
    plot_changes,
    write_changes_csv,
)
from decod_rs.config import Config
from decod_rs.joints import Joint, ties_one_boundary
from decod_rs.run_files import LoopTable
from decod_rs.selection import path_along
from decod_rs.survey import (
    CrossSession,
    Survey,
    chainage_along,
    cross_session,
    place_in_survey,
    survey_joint_ids,
    write_survey,
)
from decod_rs.tum import interpolate_poses

FloatArray = NDArray[np.float64]

__all__ = ["Reinspection", "reinspect", "write_run_survey"]


def write_run_survey(
    out: Path,
    landmarks: list[Landmark],
    joint_of: NDArray[np.int64],
    anchor_stamps: FloatArray,
    scans: tuple[FloatArray, FloatArray],
    joints: list[Joint],
    cfg: Config,
) -> Path:
    """``out/survey.decod`` from a finished run: ``scans`` = (stamps, corrected poses)."""
    anchors = (
        interpolate_poses(*scans, anchor_stamps) if anchor_stamps.size else np.zeros((0, 4, 4))
    )
    return write_survey(
        out,
        landmarks,
        joint_of,
        (anchor_stamps, anchors),
        outbound_course(scans[1][:, :3, 3]),
        {j.joint_id: j.chainage_m for j in joints},
        cfg,
    )


@dataclass
class Reinspection:
    """The survey stage: the cross-session pairs and, when some stayed, the run's scan poses
    (M, 4, 4) in the survey frame (``poses``; None: the run stays in its own frame)."""

    cross: CrossSession
    poses: FloatArray | None

    @property
    def placed(self) -> bool:
        """Whether the run was placed in the survey's frame."""
        return self.poses is not None

    def chainage(
        self, landmarks: list[Landmark], scan_stamps: FloatArray, corrected: FloatArray
    ) -> FloatArray:
        """Each landmark's chainage along the survey's outbound path (survey frame)."""
        world = np.empty((len(landmarks), 3))
        for k, lm in enumerate(landmarks):
            pose = corrected[int(np.argmin(np.abs(scan_stamps - lm.submap_stamp)))]
            world[k] = pose[:3, :3] @ lm.origin + pose[:3, 3]
        return chainage_along(self.cross.survey.path, world)

    def loop_rows(self, table: LoopTable, cross_table: LoopTable) -> LoopTable:
        """``table`` (the run's own rows) followed by ``cross_table`` (one row per landmark
        against the survey), with the column ``session``: ``run`` or ``survey``."""
        extra = {
            name: table.extra.get(name, []) + cross_table.extra.get(name, [""] * len(cross_table))
            for name in {**table.extra, **cross_table.extra}
        }
        extra["session"] = ["run"] * len(table) + ["survey"] * len(cross_table)
        return LoopTable(
            query_stamp=np.concatenate([table.query_stamp, cross_table.query_stamp]),
            db_stamp=np.concatenate([table.db_stamp, cross_table.db_stamp]),
            query_origin=np.concatenate([table.query_origin, cross_table.query_origin]),
            query_axis=np.concatenate([table.query_axis, cross_table.query_axis]),
            db_origin=np.concatenate([table.db_origin, cross_table.db_origin]),
            db_axis=np.concatenate([table.db_axis, cross_table.db_axis]),
            inliers=np.concatenate([table.inliers, cross_table.inliers]),
            score=np.concatenate([table.score, cross_table.score]),
            accepted=np.concatenate([table.accepted, cross_table.accepted]),
            extra=extra,
        )

    def survey_ids(self, joint_of: NDArray[np.int64], radius_m: float) -> dict[int, int]:
        """The run's joint id -> the survey's joint id, where a view matched (``radius_m``:
        the same-boundary radius, :func:`survey_joint_ids`)."""
        return survey_joint_ids(self.cross, joint_of, radius_m)

    def change_pairs(self, radius_m: float) -> list[ChangePair]:
        """The pairs the change report compares: the kept cross-session pairs that tie one
        boundary (``radius_m``: :func:`decod_rs.joints.ties_one_boundary`). (Views that
        did not match could be paired by position once the run is in the survey's frame; on
        the simulated hume pipe such pairs of unchanged joints, seen at the turnaround or
        from other distances, looked as changed as the changed ones, so they are left out.)"""
        c = self.cross
        return [
            ChangePair(
                k,
                int(r.candidate_index),
                float(r.heading_deg),
                float(r.dz_m),
                float(r.dp),
                int(r.inliers),
            )
            for k, r in ((k, c.results[k]) for k in c.kept)
            if r.candidate_index is not None and ties_one_boundary(r.dz_m, radius_m)
        ]

    def write_changes(
        self,
        out: Path,
        landmarks: list[Landmark],
        joint_of: NDArray[np.int64],
        chainage_m: FloatArray,
        cfg: Config,
        plot: bool = True,
    ) -> dict[str, Any]:
        """``changes.csv`` and (``plot``) ``changes.png``; returns the ``report.json``
        section."""
        pairs = self.change_pairs(float(cfg.matching.duplicate_radius_m))
        changes = joint_changes(pairs, self.cross.survey, landmarks, joint_of, chainage_m, cfg)
        write_changes_csv(out / "changes.csv", changes)
        if changes and plot:
            plot_changes(out / "changes.png", changes)
        return changes_summary(changes)

    def report(self) -> dict[str, Any]:
        """The ``report.json`` ``survey`` section (without the changes)."""
        c = self.cross
        rejected: dict[str, int] = {}
        for ok, why in zip(c.keep, c.reasons, strict=True):
            if not ok:
                rejected[why or "unknown"] = rejected.get(why or "unknown", 0) + 1
        return {
            "source": str(c.survey.source),
            "survey_decod_version": c.survey.header.get("decod_version"),
            "survey_landmarks": len(c.survey.landmarks),
            "survey_joints": int(np.unique(c.survey.joint_ids).size),
            "queries": len(c.results),
            "accepted": int(sum(r.accepted for r in c.results)),
            "kept": len(c.kept),
            "rejections": rejected,
            "aliasing": aliasing(c.results).report(),
            "placed_in_survey_frame": self.placed,
            "survey_from_odometry": np.asarray(c.survey_from_odometry).round(6).tolist(),
        }


def reinspect(
    survey: Survey,
    landmarks: list[Landmark],
    views: NDArray[np.int64],
    anchor_stamps: FloatArray,
    scans: tuple[FloatArray, FloatArray],
    corrected: FloatArray,
    cfg: Config,
) -> Reinspection:
    """The survey stage (module docs): ``anchor_stamps`` (A,) the run's submap anchors (the
    landmarks' submap stamps among them), ``views`` the views of each landmark's track,
    ``scans`` = (stamps, odometry), ``corrected`` the run's own corrected scan poses."""
    # Pairs are judged on the run's own corrected anchors (its loops removed most drift).
    own = (
        interpolate_poses(scans[0], corrected, anchor_stamps)
        if anchor_stamps.size
        else np.zeros((0, 4, 4))
    )
    by_stamp = {float(s): p for s, p in zip(anchor_stamps, own, strict=True)}
    cross = cross_session(survey, landmarks, by_stamp, path_along(*scans), cfg, views)
    poses = place_in_survey(cross, landmarks, (scans[0], corrected), anchor_stamps, cfg)
    return Reinspection(cross, poses)
