"""Changes between two inspections of one pipe (issue 12): scene overrides that alter a few
joints of an otherwise identical world, so that a re-inspection run (same ``world_seed``,
another ``seed`` for noise and drift) can be checked against its survey.

Three kinds, each at most one per scene, ``-1`` = none (the defaults):

- ``displaced_segment`` (segment index ``s``: between joints ``s-1`` and ``s``): the whole
  segment moves sideways by ``displacement_m`` (a settled or jacked pipe): a lateral step at
  both its joints.
- ``wider_gap_joint`` (joint index): the joint opens over part of its circumference (about
  50 degrees on the upper right): its groove widens there by up to ``gap_extra_m``.
- ``deposit_joint`` (joint index): a deposit (encrustation, root intrusion) of
  ``deposit_height_m`` on the wall 2.5 cm past the joint, upper left.

They modify the scene after it is built and draw nothing from its generator, so everything
else (every other joint, the roughness, the lateral connections) stays the same world.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from decod_rs.sim.surface import PatchSet, SegmentTable

CHANGE_PARAMS: dict[str, Any] = {
    "displaced_segment": -1,
    "displacement_m": 0.008,
    "wider_gap_joint": -1,
    "gap_extra_m": 0.04,
    "deposit_joint": -1,
    "deposit_height_m": 0.006,
}

#: Where the one-sided changes sit around the circumference (theta = atan2(z, y), radians).
GAP_THETA = 0.6
GAP_SIGMA_RAD = 0.45
DEPOSIT_THETA = 2.3


def changed_joints(params: dict[str, Any]) -> list[int]:
    """The joint indices these parameters change (sorted, unique)."""
    out: set[int] = set()
    s = int(params["displaced_segment"])
    if s >= 0:
        out.update(j for j in (s - 1, s) if j >= 0)
    for key in ("wider_gap_joint", "deposit_joint"):
        if int(params[key]) >= 0:
            out.add(int(params[key]))
    return sorted(out)


def _check(params: dict[str, Any], n_joints: int) -> None:
    for key, top in (
        ("displaced_segment", n_joints),
        ("wider_gap_joint", n_joints - 1),
        ("deposit_joint", n_joints - 1),
    ):
        if int(params[key]) > top:
            raise ValueError(f"scene parameter {key!r}: {params[key]} beyond the {n_joints} joints")


def apply_changes(
    params: dict[str, Any], patches: PatchSet, lips: SegmentTable, theta: np.ndarray
) -> tuple[PatchSet, SegmentTable]:
    """The joint patches and segment offsets with the changes of ``params`` applied (copies;
    the inputs are returned unchanged when there is no change)."""
    if not changed_joints(params):
        return patches, lips
    _check(params, patches.centres.size)
    tables = patches.tables.copy()
    seg = lips.table.copy()
    s = int(params["displaced_segment"])
    if s >= 0:
        seg[s] += np.float32(params["displacement_m"]) * np.cos(theta).astype(np.float32)
    n_u = tables.shape[1]
    u = np.linspace(-patches.half_width, patches.half_width, n_u)
    j = int(params["wider_gap_joint"])
    if j >= 0:
        # Stretch the groove along u by a factor that peaks at GAP_THETA (a joint opened or
        # spalled over about 50 degrees of its circumference).
        dth = (theta - GAP_THETA + np.pi) % (2.0 * np.pi) - np.pi
        side = np.exp(-0.5 * (dth / GAP_SIGMA_RAD) ** 2)
        width = float(params.get("groove_width_m", params.get("gap_width_m", 0.016)))
        for t in range(theta.size):
            factor = (width + params["gap_extra_m"] * side[t]) / width
            tables[j, :, t] = np.interp(u / factor, u, tables[j, :, t]).astype(np.float32)
    k = int(params["deposit_joint"])
    if k >= 0:
        dth = (theta - DEPOSIT_THETA + np.pi) % (2.0 * np.pi) - np.pi
        bump = np.exp(-0.5 * ((u - 0.025) / 0.01) ** 2)[:, None] * np.exp(-0.5 * (dth / 0.25) ** 2)
        tables[k] -= (params["deposit_height_m"] * bump).astype(np.float32)
    return PatchSet(patches.centres, patches.half_width, tables), SegmentTable(lips.boundaries, seg)
