"""TUM trajectories (``stamp tx ty tz qx qy qz qw``) and the numpy SE(3) helpers they need.

A trajectory is ``stamps`` (N,) seconds, strictly increasing, and ``poses`` (N, 4, 4)
``world_from_body`` homogeneous matrices (float64). The files are the ones `evo` reads
(``evo_ape tum gt.tum corrected.tum``): one pose per line, ``#`` comments, unit quaternions in
``x y z w`` order.

The SE(3) helpers (``rotation_to_quaternion``, ``so3_exp``/``so3_log``, ``interpolate_poses``,
``umeyama_alignment``) are vectorised over leading axes so a 10,000-pose trajectory costs a few
numpy calls, not a Python loop.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

#: A quaternion whose norm is further than this from 1 is corrupt, not merely rounded
#: (files written with 6 decimals are within 1e-5).
QUATERNION_NORM_TOLERANCE = 1e-3

__all__ = [
    "blend_poses",
    "check_poses",
    "interpolate_poses",
    "poses_from_tq",
    "quaternion_to_rotation",
    "read_tum",
    "rotation_to_quaternion",
    "so3_exp",
    "so3_log",
    "tq_from_poses",
    "umeyama_alignment",
    "write_tum",
]


def check_poses(poses: ArrayLike, name: str = "poses") -> FloatArray:
    """``poses`` as a float64 (N, 4, 4) array of finite rigid transforms, else ValueError."""
    arr = np.asarray(poses, dtype=np.float64)
    if arr.ndim != 3 or arr.shape[1:] != (4, 4):
        raise ValueError(f"{name}: expected shape (N, 4, 4), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        bad = int(np.argwhere(~np.isfinite(arr))[0][0])
        raise ValueError(f"{name}: pose {bad} is not finite")
    return arr


def _check_stamps(stamps: ArrayLike, n: int, name: str) -> FloatArray:
    arr = np.asarray(stamps, dtype=np.float64)
    if arr.shape != (n,):
        raise ValueError(f"{name}: expected shape ({n},), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: stamps must be finite")
    if n > 1 and np.any(np.diff(arr) <= 0.0):
        i = int(np.argmax(np.diff(arr) <= 0.0))
        raise ValueError(
            f"{name}: stamps must be strictly increasing (index {i + 1}: {arr[i + 1]!r} "
            f"after {arr[i]!r})"
        )
    return arr


# --- rotations ---------------------------------------------------------------------------


def _skew(v: FloatArray) -> FloatArray:
    """(..., 3) vectors to (..., 3, 3) cross-product matrices."""
    out = np.zeros((*v.shape[:-1], 3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def so3_exp(w: ArrayLike) -> FloatArray:
    """Rotation vectors (..., 3) to rotation matrices (..., 3, 3) (Rodrigues)."""
    wa = np.asarray(w, dtype=np.float64)
    theta = np.linalg.norm(wa, axis=-1)[..., None, None]
    k = _skew(wa)
    small = theta < 1e-8
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    return np.eye(3) + a * k + b * (k @ k)


def so3_log(r: ArrayLike) -> FloatArray:
    """Rotation matrices (..., 3, 3) to rotation vectors (..., 3), angles in [0, pi]."""
    # Through the quaternion: accurate near 0 and near pi, where the trace formula is not.
    q = rotation_to_quaternion(np.asarray(r, dtype=np.float64))
    q = np.where(q[..., 3:4] < 0.0, -q, q)  # w >= 0: angle in [0, pi]
    vec = q[..., :3]
    s = np.linalg.norm(vec, axis=-1)
    angle = 2.0 * np.arctan2(s, q[..., 3])
    small = s < 1e-12
    scale = np.where(small, 2.0, angle / np.where(small, 1.0, s))
    return vec * scale[..., None]


def rotation_to_quaternion(r: ArrayLike) -> FloatArray:
    """Rotation matrices (..., 3, 3) to unit quaternions (..., 4) as ``x y z w`` (w >= 0)."""
    ra = np.asarray(r, dtype=np.float64)
    m = ra.reshape(-1, 3, 3)
    tr = np.trace(m, axis1=1, axis2=2)
    # Shepperd: pick the largest of 4w^2, 4x^2, 4y^2, 4z^2 to divide by.
    cand = np.stack([tr, m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]], axis=1)
    pick = np.argmax(cand, axis=1)
    q = np.empty((m.shape[0], 4))
    for case in range(4):
        sel = pick == case
        if not np.any(sel):
            continue
        s = m[sel]
        if case == 0:
            w4 = 2.0 * np.sqrt(np.maximum(1.0 + tr[sel], 1e-300))
            q[sel] = np.stack(
                [
                    (s[:, 2, 1] - s[:, 1, 2]) / w4,
                    (s[:, 0, 2] - s[:, 2, 0]) / w4,
                    (s[:, 1, 0] - s[:, 0, 1]) / w4,
                    0.25 * w4,
                ],
                axis=1,
            )
        else:
            i = case - 1
            j, k = (i + 1) % 3, (i + 2) % 3
            d = 2.0 * np.sqrt(np.maximum(1.0 + s[:, i, i] - s[:, j, j] - s[:, k, k], 1e-300))
            qq = np.empty((s.shape[0], 4))
            qq[:, i] = 0.25 * d
            qq[:, j] = (s[:, j, i] + s[:, i, j]) / d
            qq[:, k] = (s[:, k, i] + s[:, i, k]) / d
            qq[:, 3] = (s[:, k, j] - s[:, j, k]) / d
            q[sel] = qq
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q = np.where(q[:, 3:4] < 0.0, -q, q)
    return q.reshape(*ra.shape[:-2], 4)


def quaternion_to_rotation(q: ArrayLike) -> FloatArray:
    """Quaternions (..., 4) ``x y z w`` (normalised here) to rotation matrices (..., 3, 3)."""
    qa = np.asarray(q, dtype=np.float64)
    qa = qa / np.linalg.norm(qa, axis=-1, keepdims=True)
    x, y, z, w = qa[..., 0], qa[..., 1], qa[..., 2], qa[..., 3]
    out = np.empty((*qa.shape[:-1], 3, 3))
    out[..., 0, 0] = 1 - 2 * (y * y + z * z)
    out[..., 0, 1] = 2 * (x * y - z * w)
    out[..., 0, 2] = 2 * (x * z + y * w)
    out[..., 1, 0] = 2 * (x * y + z * w)
    out[..., 1, 1] = 1 - 2 * (x * x + z * z)
    out[..., 1, 2] = 2 * (y * z - x * w)
    out[..., 2, 0] = 2 * (x * z - y * w)
    out[..., 2, 1] = 2 * (y * z + x * w)
    out[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return out


def poses_from_tq(t: ArrayLike, q: ArrayLike) -> FloatArray:
    """Translations (N, 3) and quaternions (N, 4, ``x y z w``) to (N, 4, 4) poses."""
    ta = np.asarray(t, dtype=np.float64)
    out = np.zeros((ta.shape[0], 4, 4))
    out[:, :3, :3] = quaternion_to_rotation(q)
    out[:, :3, 3] = ta
    out[:, 3, 3] = 1.0
    return out


def tq_from_poses(poses: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """(N, 4, 4) poses to translations (N, 3) and quaternions (N, 4, ``x y z w``)."""
    p = check_poses(poses)
    return p[:, :3, 3].copy(), rotation_to_quaternion(p[:, :3, :3])


# --- files -------------------------------------------------------------------------------


def read_tum(path: str | Path) -> tuple[FloatArray, FloatArray]:
    """Read a TUM trajectory: ``(stamps (N,), world_from_body (N, 4, 4))``.

    Blank lines and ``#`` comments are skipped; every other line must hold 8 finite numbers
    with a unit quaternion (norm within ``QUATERNION_NORM_TOLERANCE`` of 1; it is then
    renormalised) and a stamp larger than the previous one. Anything else raises ValueError
    naming the file and line; a missing file raises FileNotFoundError.
    """
    path = Path(path)
    rows: list[list[float]] = []
    prev = -np.inf
    with path.open(encoding="utf-8") as fh:
        for lineno, raw in enumerate(fh, start=1):
            line = raw.strip()
            if not line or line.startswith("#"):
                continue
            fields = line.replace(",", " ").split()
            where = f"{path}:{lineno}"
            if len(fields) != 8:
                raise ValueError(
                    f"{where}: expected 8 fields `stamp tx ty tz qx qy qz qw`, got {len(fields)}"
                )
            try:
                values = [float(f) for f in fields]
            except ValueError:
                raise ValueError(f"{where}: not a number in {line!r}") from None
            if not all(np.isfinite(values)):
                raise ValueError(f"{where}: non-finite value in {line!r}")
            norm = float(np.linalg.norm(values[4:]))
            if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
                raise ValueError(f"{where}: quaternion norm {norm:.6f} is not 1")
            if values[0] <= prev:
                raise ValueError(
                    f"{where}: stamp {values[0]!r} is not after the previous one {prev!r}"
                )
            prev = values[0]
            rows.append(values)
    if not rows:
        raise ValueError(f"{path}: no poses")
    data = np.asarray(rows)
    return data[:, 0].copy(), poses_from_tq(data[:, 1:4], data[:, 4:8])


def write_tum(path: str | Path, stamps: ArrayLike, poses: ArrayLike) -> None:
    """Write ``stamps`` (N,) and ``world_from_body`` ``poses`` (N, 4, 4) as a TUM file.

    Stamps with 9 decimals (ns), translations with 9 (nm), quaternions with 12, so a
    read/write round trip changes poses by < 1e-9.
    """
    p = check_poses(poses)
    s = _check_stamps(stamps, p.shape[0], f"{path}: stamps")
    t, q = tq_from_poses(p)
    data = np.column_stack([s, t, q])
    fmt = ["%.9f"] * 4 + ["%.12f"] * 4
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    np.savetxt(path, data, fmt=fmt, header="stamp tx ty tz qx qy qz qw")


# --- trajectories ------------------------------------------------------------------------


def interpolate_poses(stamps: ArrayLike, poses: ArrayLike, query: ArrayLike) -> FloatArray:
    """SE(3) interpolation of a trajectory at ``query`` stamps (Q,) -> (Q, 4, 4).

    Translation linear, rotation along the geodesic (``R0 Exp(a Log(R0^T R1))``), between the
    two bracketing poses. Stamps outside ``[stamps[0], stamps[-1]]`` raise ValueError:
    extrapolating a trajectory is the caller's decision, not a silent default.
    """
    p = check_poses(poses)
    s = _check_stamps(stamps, p.shape[0], "interpolate_poses: stamps")
    q = np.atleast_1d(np.asarray(query, dtype=np.float64))
    if q.ndim != 1:
        raise ValueError(f"interpolate_poses: query stamps must be (Q,), got {q.shape}")
    outside = (q < s[0]) | (q > s[-1]) | ~np.isfinite(q)
    if np.any(outside):
        bad = q[outside][0]
        raise ValueError(
            f"interpolate_poses: stamp {bad!r} outside the trajectory [{s[0]!r}, {s[-1]!r}]"
        )
    if p.shape[0] == 1:
        return np.repeat(p, q.shape[0], axis=0)
    i1 = np.clip(np.searchsorted(s, q, side="right"), 1, s.shape[0] - 1)
    i0 = i1 - 1
    alpha = (q - s[i0]) / (s[i1] - s[i0])
    return blend_poses(p[i0], p[i1], alpha)


def blend_poses(a: ArrayLike, b: ArrayLike, alpha: ArrayLike) -> FloatArray:
    """Per-element SE(3) blend of pose stacks ``a``, ``b`` (Q, 4, 4) with weights (Q,):
    ``alpha = 0`` gives ``a`` exactly, ``1`` gives ``b`` (up to rounding)."""
    pa = np.asarray(a, dtype=np.float64)
    pb = np.asarray(b, dtype=np.float64)
    w = np.asarray(alpha, dtype=np.float64)
    rel = np.einsum("nji,njk->nik", pa[:, :3, :3], pb[:, :3, :3])
    out = np.zeros_like(pa)
    out[:, :3, :3] = pa[:, :3, :3] @ so3_exp(so3_log(rel) * w[:, None])
    out[:, :3, 3] = (1.0 - w)[:, None] * pa[:, :3, 3] + w[:, None] * pb[:, :3, 3]
    out[:, 3, 3] = 1.0
    out[w == 0.0] = pa[w == 0.0]
    out[w == 1.0] = pb[w == 1.0]
    return out


def umeyama_alignment(source: ArrayLike, target: ArrayLike) -> FloatArray:
    """The rigid transform (4, 4) ``target_from_source`` minimising the squared distances
    between matched points (N, 3) (Umeyama 1991 without scale)."""
    src = np.asarray(source, dtype=np.float64)
    dst = np.asarray(target, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or src.shape[0] < 3:
        raise ValueError(
            f"umeyama_alignment: expected two (N, 3) arrays with N >= 3, got {src.shape} "
            f"and {dst.shape}"
        )
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    cov = (dst - mu_d).T @ (src - mu_s) / src.shape[0]
    u, _, vt = np.linalg.svd(cov)
    d = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0.0:
        d[2, 2] = -1.0
    r = u @ d @ vt
    out = np.eye(4)
    out[:3, :3] = r
    out[:3, 3] = mu_d - r @ mu_s
    return out
