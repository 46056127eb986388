"""The observation function Lambda (Eq. 5): the POM pose predicted from the contacts.

The object moves rigidly with the contacts (DESIGN.md section 5). A hypothesis carries its
contacts expressed in the POM frame O, ``p_i^O`` (the *attachment*, which fixes every E^C
link of Eq. 1). After a move, the POM pose X_PO' is the rigid transform that maps the
attached points onto the moved contacts ``p_i(theta')``. Because the grasp constraints keep
the contacts rigid (Eq. 8), the transform is exact and follows in closed form from an
orthonormal frame on the first three contacts; the remaining contacts agree with it.

Poses are (R (P, 3, 3), t (P, 3)) pairs here, particles first: ``p^P = R p^O + t``.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

__all__ = [
    "CollinearContactsError",
    "triad",
    "pom_pose",
    "attach",
    "rotation_angle",
    "rotvec",
    "rotvec_to_matrix",
    "pose_error",
]

#: Smallest admissible triangle area spanned by the first three contacts [m^2].
MIN_TRIANGLE_AREA = 1e-8


class CollinearContactsError(ValueError):
    """The first three contacts are (nearly) collinear: they do not fix an object pose."""


@njit(cache=True)
def _triad_one(p, F):  # pragma: no cover - numba
    """Orthonormal frame (columns) on points p[0], p[1], p[2]; returns twice the area."""
    e1 = p[1] - p[0]
    v = p[2] - p[0]
    n = np.empty(3)
    n[0] = e1[1] * v[2] - e1[2] * v[1]
    n[1] = e1[2] * v[0] - e1[0] * v[2]
    n[2] = e1[0] * v[1] - e1[1] * v[0]
    area2 = np.sqrt(n[0] ** 2 + n[1] ** 2 + n[2] ** 2)
    l1 = np.sqrt(e1[0] ** 2 + e1[1] ** 2 + e1[2] ** 2)
    if area2 <= 0.0 or l1 <= 0.0:
        F[:, :] = np.nan
        return 0.0
    for r in range(3):
        F[r, 0] = e1[r] / l1
        F[r, 2] = n[r] / area2
    F[0, 1] = F[1, 2] * F[2, 0] - F[2, 2] * F[1, 0]
    F[1, 1] = F[2, 2] * F[0, 0] - F[0, 2] * F[2, 0]
    F[2, 1] = F[0, 2] * F[1, 0] - F[1, 2] * F[0, 0]
    return area2


@njit(cache=True, parallel=True)
def _pose_kernel(p_O, p_P, R, t, area):  # pragma: no cover - numba
    P, N, _ = p_O.shape
    for pp in prange(P):
        Fo = np.empty((3, 3))
        Fp = np.empty((3, 3))
        a1 = _triad_one(p_O[pp], Fo)
        a2 = _triad_one(p_P[pp], Fp)
        area[pp] = 0.5 * min(a1, a2)
        Rp = Fp @ Fo.T
        co = np.zeros(3)
        cp = np.zeros(3)
        for i in range(N):
            co += p_O[pp, i]
            cp += p_P[pp, i]
        co /= N
        cp /= N
        R[pp] = Rp
        t[pp] = cp - Rp @ co


def triad(points: np.ndarray) -> np.ndarray:
    """Orthonormal frames (P, 3, 3) on the first three of ``points`` (P, N, 3)."""
    points = np.ascontiguousarray(points, dtype=float)
    F = np.empty((points.shape[0], 3, 3))
    for i in range(points.shape[0]):
        _triad_one(points[i, :3], F[i])
    return F


def _check_points(name: str, x) -> np.ndarray:
    x = np.ascontiguousarray(x, dtype=float)
    if x.ndim != 3 or x.shape[2] != 3 or x.shape[1] < 3:
        raise ValueError(f"'{name}' must have shape (P, N >= 3, 3), got {x.shape}")
    return x


def pom_pose(p_O, p_P) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Lambda (Eq. 5): POM poses (R (P,3,3), t (P,3)) mapping attachments onto contacts.

    Returns (R, t, ok): ``ok`` is False where the contacts are (nearly) collinear and no
    pose follows from them; such particles get an identity rotation, never NaN.
    """
    p_O = _check_points("p_O", p_O)
    p_P = _check_points("p_P", p_P)
    if p_O.shape != p_P.shape:
        raise ValueError(f"'p_O' {p_O.shape} and 'p_P' {p_P.shape} must have the same shape")
    P = p_O.shape[0]
    R = np.empty((P, 3, 3))
    t = np.empty((P, 3))
    area = np.empty(P)
    _pose_kernel(p_O, p_P, R, t, area)
    ok = area > MIN_TRIANGLE_AREA
    if not ok.all():
        R[~ok] = np.eye(3)
        t[~ok] = p_P[~ok].mean(axis=1)
    return R, t, ok


def attach(p_P, R_PO, t_PO) -> np.ndarray:
    """Contacts expressed in the POM frame: p^O = R_PO^T (p^P - t_PO), (P, N, 3).

    ``R_PO`` (P or 1, 3, 3) and ``t_PO`` (P or 1, 3) is the observed POM pose. Raises
    :class:`CollinearContactsError` if any particle's contacts are collinear.
    """
    p_P = _check_points("p_P", p_P)
    R_PO = np.asarray(R_PO, float).reshape(-1, 3, 3)
    t_PO = np.asarray(t_PO, float).reshape(-1, 3)
    F = triad(p_P)
    if not np.all(np.isfinite(F)):
        raise CollinearContactsError("the first three contacts are collinear: they do not define an object pose")
    e1 = p_P[:, 1] - p_P[:, 0]
    e2 = p_P[:, 2] - p_P[:, 0]
    area = 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1)
    if np.any(area < MIN_TRIANGLE_AREA):
        raise CollinearContactsError(
            f"the first three contacts are nearly collinear (triangle area {area.min():.3g} m^2 "
            f"< {MIN_TRIANGLE_AREA:g}): they do not define an object pose"
        )
    return (p_P - t_PO[:, None, :]) @ R_PO  # R^T (p - t), particle by particle


def rotation_angle(R_a, R_b) -> np.ndarray:
    """Angle [rad] of R_a^T R_b, batched (P,)."""
    c = (np.einsum("pij,pij->p", R_a, R_b) - 1.0) / 2.0
    return np.arccos(np.clip(c, -1.0, 1.0))


def rotvec(R) -> np.ndarray:
    """Rotation vectors (P, 3) of rotation matrices (P, 3, 3) (axis * angle)."""
    R = np.asarray(R, float).reshape(-1, 3, 3)
    angle = rotation_angle(np.broadcast_to(np.eye(3), R.shape), R)
    w = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1)
    s = np.sin(angle)
    out = np.empty_like(w)
    small = s < 1e-6
    out[~small] = w[~small] * (angle[~small] / (2.0 * s[~small]))[:, None]
    # near 0: R ~ I + [w]x ; near pi: from the symmetric part
    near0 = small & (angle < 1.0)
    out[near0] = 0.5 * w[near0]
    nearpi = small & ~near0
    for p in np.flatnonzero(nearpi):
        B = 0.5 * (R[p] + np.eye(3))
        k = np.argmax(np.diag(B))
        v = B[:, k] / np.sqrt(max(B[k, k], 1e-300))
        out[p] = v * angle[p]
    return out


def rotvec_to_matrix(w) -> np.ndarray:
    """Rodrigues: rotation matrices (P, 3, 3) of rotation vectors (P, 3)."""
    w = np.asarray(w, float).reshape(-1, 3)
    th = np.linalg.norm(w, axis=1)
    k = np.where(th[:, None] > 1e-12, w / np.maximum(th, 1e-300)[:, None], 0.0)
    Kx = np.zeros((len(w), 3, 3))
    Kx[:, 0, 1], Kx[:, 0, 2] = -k[:, 2], k[:, 1]
    Kx[:, 1, 0], Kx[:, 1, 2] = k[:, 2], -k[:, 0]
    Kx[:, 2, 0], Kx[:, 2, 1] = -k[:, 1], k[:, 0]
    s, c = np.sin(th)[:, None, None], np.cos(th)[:, None, None]
    return np.eye(3) + s * Kx + (1 - c) * Kx @ Kx


def pose_error(R_pred, t_pred, R_meas, t_meas) -> tuple[np.ndarray, np.ndarray]:
    """Position error [m] and rotation error [rad] of predicted vs measured poses, (P,)."""
    dp = np.linalg.norm(np.asarray(t_pred) - np.asarray(t_meas), axis=-1)
    R_meas = np.broadcast_to(R_meas, np.shape(R_pred))
    return dp, rotation_angle(R_pred, R_meas)
