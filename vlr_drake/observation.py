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
    "fit_pose",
    "attach",
    "in_frame",
    "rotation_angle",
    "rotvec",
    "rotvec_to_matrix",
    "blend_poses",
    "pose_error",
]

#: Smallest admissible triangle area spanned by the first three contacts [m^2].
MIN_TRIANGLE_AREA = 1e-8


class CollinearContactsError(ValueError):
    """The first three contacts are (nearly) collinear: they do not fix an object pose."""


#: Particles per task of the parallel kernels (each task allocates its scratch once).
_CHUNK = 1024


@njit(cache=True)
def _triad_one(p, F):  # pragma: no cover - numba
    """Orthonormal frame (columns) on points p[0], p[1], p[2]; returns twice the area."""
    e1x, e1y, e1z = p[1, 0] - p[0, 0], p[1, 1] - p[0, 1], p[1, 2] - p[0, 2]
    vx, vy, vz = p[2, 0] - p[0, 0], p[2, 1] - p[0, 1], p[2, 2] - p[0, 2]
    nx = e1y * vz - e1z * vy
    ny = e1z * vx - e1x * vz
    nz = e1x * vy - e1y * vx
    area2 = np.sqrt(nx * nx + ny * ny + nz * nz)
    l1 = np.sqrt(e1x * e1x + e1y * e1y + e1z * e1z)
    if area2 <= 0.0 or l1 <= 0.0:
        F[:, :] = np.nan
        return 0.0
    F[0, 0], F[1, 0], F[2, 0] = e1x / l1, e1y / l1, e1z / l1
    F[0, 2], F[1, 2], F[2, 2] = nx / area2, ny / area2, nz / area2
    F[0, 1] = F[1, 2] * F[2, 0] - F[2, 2] * F[1, 0]
    F[1, 1] = F[2, 2] * F[0, 0] - F[0, 2] * F[2, 0]
    F[2, 1] = F[0, 2] * F[1, 0] - F[1, 2] * F[0, 0]
    return area2


@njit(cache=True, parallel=True)
def _pose_kernel(p_O, p_P, R, t, area):  # pragma: no cover - numba
    P, N, _ = p_O.shape
    for cc in prange((P + _CHUNK - 1) // _CHUNK):
        Fo = np.empty((3, 3))
        Fp = np.empty((3, 3))
        for pp in range(cc * _CHUNK, min((cc + 1) * _CHUNK, P)):
            a1 = _triad_one(p_O[pp], Fo)
            a2 = _triad_one(p_P[pp], Fp)
            # NaN contacts give a NaN area (min() would drop it), so the pose is not ok
            area[pp] = 0.5 * min(a1, a2) if (a1 == a1 and a2 == a2) else np.nan
            for r in range(3):
                for c in range(3):  # R = Fp Fo^T
                    R[pp, r, c] = Fp[r, 0] * Fo[c, 0] + Fp[r, 1] * Fo[c, 1] + Fp[r, 2] * Fo[c, 2]
            for r in range(3):  # t = centroid(p_P) - R centroid(p_O)
                v = 0.0
                for i in range(N):
                    v += p_P[pp, i, r] - (R[pp, r, 0] * p_O[pp, i, 0] + R[pp, r, 1] * p_O[pp, i, 1]
                                          + R[pp, r, 2] * p_O[pp, i, 2])
                t[pp, r] = v / N


@njit(cache=True)
def _rotvec_one(R, out):  # pragma: no cover - numba
    """Rotation vector (axis * angle) of one rotation matrix R (3, 3), into ``out`` (3,)."""
    c = 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)
    angle = np.arccos(min(1.0, max(-1.0, c)))
    wx, wy, wz = R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]
    s = np.sin(angle)
    if s >= 1e-6 and c > -0.99:
        f = angle / (2.0 * s)
        out[0], out[1], out[2] = wx * f, wy * f, wz * f
    elif angle < 1.0:  # near 0: R ~ I + [w]x
        out[0], out[1], out[2] = 0.5 * wx, 0.5 * wy, 0.5 * wz
    else:
        # near pi (beyond 171.9 deg): arccos loses the angle there (8e-4 rad off at pi - 1e-6,
        # a review) and dividing by sin amplifies it. The angle by atan2, the axis from the
        # symmetric part, (R + R^T) / 2 = c I + (1 - c) k k^T, its sign from the skew part.
        angle = np.arctan2(0.5 * np.sqrt(wx * wx + wy * wy + wz * wz), c)
        k = 0
        for j in range(1, 3):
            if R[j, j] > R[k, k]:
                k = j
        kk = np.sqrt(max((R[k, k] - c) / (1.0 - c), 1e-300))
        axis = np.empty(3)
        for r in range(3):
            axis[r] = kk if r == k else 0.5 * (R[r, k] + R[k, r]) / ((1.0 - c) * kk)
        if axis[0] * wx + axis[1] * wy + axis[2] * wz < 0.0:
            angle = -angle
        for r in range(3):
            out[r] = axis[r] * angle


@njit(cache=True)
def _rodrigues_one(w0, w1, w2, R):  # pragma: no cover - numba
    """Rotation matrix of the rotation vector (w0, w1, w2), into ``R`` (3, 3)."""
    th = np.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
    if th > 1e-12:
        kx, ky, kz = w0 / th, w1 / th, w2 / th
    else:
        kx = ky = kz = 0.0
    s = np.sin(th)
    c1 = 1.0 - np.cos(th)
    kk = kx * kx + ky * ky + kz * kz
    # R = I + sin(th) [k]x + (1 - cos(th)) [k]x^2, with [k]x^2 = k k^T - |k|^2 I
    R[0, 0] = 1.0 + c1 * (kx * kx - kk)
    R[1, 1] = 1.0 + c1 * (ky * ky - kk)
    R[2, 2] = 1.0 + c1 * (kz * kz - kk)
    R[0, 1] = -s * kz + c1 * kx * ky
    R[1, 0] = s * kz + c1 * kx * ky
    R[0, 2] = s * ky + c1 * kx * kz
    R[2, 0] = -s * ky + c1 * kx * kz
    R[1, 2] = -s * kx + c1 * ky * kz
    R[2, 1] = s * kx + c1 * ky * kz


@njit(cache=True, parallel=True)
def _rotvec_kernel(R, out, det):  # pragma: no cover - numba
    for p in prange(R.shape[0]):
        _rotvec_one(R[p], out[p])
        m = R[p]
        det[p] = (m[0, 0] * (m[1, 1] * m[2, 2] - m[1, 2] * m[2, 1]) - m[0, 1] * (m[1, 0] * m[2, 2] - m[1, 2] * m[2, 0])
                  + m[0, 2] * (m[1, 0] * m[2, 1] - m[1, 1] * m[2, 0]))


@njit(cache=True, parallel=True)
def _rodrigues_kernel(w, R):  # pragma: no cover - numba
    for p in prange(w.shape[0]):
        _rodrigues_one(w[p, 0], w[p, 1], w[p, 2], R[p])


@njit(cache=True, parallel=True)
def _blend_kernel(R_a, t_a, R_b, t_b, fraction, R_out, t_out):  # pragma: no cover - numba
    P = R_a.shape[0]
    for cc in prange((P + _CHUNK - 1) // _CHUNK):
        dR = np.empty((3, 3))
        E = np.empty((3, 3))
        v = np.empty(3)
        for p in range(cc * _CHUNK, min((cc + 1) * _CHUNK, P)):
            for r in range(3):
                for c in range(3):  # R_a^T R_b
                    dR[r, c] = R_a[p, 0, r] * R_b[0, c] + R_a[p, 1, r] * R_b[1, c] + R_a[p, 2, r] * R_b[2, c]
            _rotvec_one(dR, v)
            _rodrigues_one(fraction * v[0], fraction * v[1], fraction * v[2], E)
            for r in range(3):
                for c in range(3):  # R_a exp(fraction log(R_a^T R_b))
                    R_out[p, r, c] = R_a[p, r, 0] * E[0, c] + R_a[p, r, 1] * E[1, c] + R_a[p, r, 2] * E[2, c]
                t_out[p, r] = (1.0 - fraction) * t_a[p, r] + fraction * t_b[r]


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

    Returns (R, t, ok): ``ok`` is False where the contacts are (nearly) collinear, or not
    finite, and no pose follows from them; such particles get an identity rotation, never
    NaN. The rotation is the exact one of contacts 0-2 (the filter's contacts are rigid, and
    fit exactly); for points that are not rigid it depends on their order, and
    :func:`fit_pose` is the least-squares fit.
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
    # (a contact after the third that is not finite had given ok with a NaN position)
    ok = (area > MIN_TRIANGLE_AREA) & np.isfinite(t).all(axis=1)
    if not ok.all():
        R[~ok] = np.eye(3)
        bad = p_P[~ok]
        fin = np.isfinite(bad).all(axis=2)  # the finite contacts' centroid (0 where none is)
        t[~ok] = np.where(fin[..., None], bad, 0.0).sum(axis=1) / np.maximum(fin.sum(axis=1), 1)[:, None]
    return R, t, ok


def fit_pose(p_O, p_P) -> tuple[np.ndarray, np.ndarray]:
    """The least-squares rigid pose (R (P, 3, 3), t (P, 3)) taking points ``p_O`` (P, N, 3)
    onto ``p_P`` (Kabsch): for points that are not exactly rigid, where :func:`pom_pose`'s
    exact fit of three of them depends on which three. Non-finite points are a ValueError;
    points ``p_O`` on one line (or one point) leave the turn about that line free and are a
    :class:`CollinearContactsError`."""
    p_O, p_P = _check_points("p_O", p_O), _check_points("p_P", p_P)
    if p_O.shape != p_P.shape:
        raise ValueError(f"'p_O' {p_O.shape} and 'p_P' {p_P.shape} must have the same shape")
    if not (np.all(np.isfinite(p_O)) and np.all(np.isfinite(p_P))):
        raise ValueError("fit_pose: the points must be finite")
    c_O, c_P = p_O.mean(axis=1), p_P.mean(axis=1)
    q_O = p_O - c_O[:, None]
    # (on a line the SVD's second and third directions are rounding: any turn about the line
    # had come back as "the" pose)
    spread = np.linalg.svd(q_O, compute_uv=False)  # (P, min(N, 3)), largest first
    second = spread[:, 1] if spread.shape[1] > 1 else np.zeros(len(spread))
    flat = second <= 1e-9 * spread[:, 0]  # (one point: 0 <= 0)
    if np.any(flat):
        raise CollinearContactsError(
            f"fit_pose: the points of {int(flat.sum())} of {flat.size} poses lie on one line "
            f"(first: pose {int(np.argmax(flat))}): they do not fix a rotation about it"
        )
    H = np.einsum("pni,pnj->pij", q_O, p_P - c_P[:, None])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.einsum("pji,pkj->pik", Vt, U)))  # no reflection
    D = np.zeros_like(H)
    D[:, 0, 0], D[:, 1, 1], D[:, 2, 2] = 1.0, 1.0, d
    R = np.einsum("pji,pjk,plk->pil", Vt, D, U)
    return R, c_P - np.einsum("pij,pj->pi", R, c_O)


def attach(p_P, R_PO, t_PO) -> np.ndarray:
    """Contacts expressed in the POM frame: p^O = R_PO^T (p^P - t_PO), (P, N, 3).

    ``R_PO`` (P or 1, 3, 3) and ``t_PO`` (P or 1, 3) is the observed POM pose. Raises
    :class:`CollinearContactsError` if any particle's contacts are collinear, and ValueError
    for contacts or a pose that are not finite or an ``R_PO`` that is not a rotation.
    """
    p_P = _check_points("p_P", p_P)
    R_PO = np.asarray(R_PO, float).reshape(-1, 3, 3)
    t_PO = np.asarray(t_PO, float).reshape(-1, 3)
    # (NaN contacts had been called collinear, or after the third given NaN attachments; a NaN
    # pose NaN attachments, and a reflection mirrored ones, all silently)
    if not np.all(np.isfinite(p_P)):
        raise ValueError("attach: the contacts are not finite")
    if not (np.all(np.isfinite(R_PO)) and np.all(np.isfinite(t_PO))):
        raise ValueError("attach: the POM pose (R_PO, t_PO) is not finite")
    if not np.all(is_rotation(R_PO)):
        raise ValueError("attach: R_PO is not a rotation matrix (orthonormal, determinant +1)")
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
    return in_frame(p_P, R_PO, t_PO)


def in_frame(p_P, R, t) -> np.ndarray:
    """Points p (P, N, 3) expressed in the frames (R, t): R^T (p - t), particle by particle.

    R (P or 1, 3, 3) and t (P or 1, 3); a leading axis of 1 is shared by every particle. No
    checks on the contacts (see :func:`attach`)."""
    p_P = np.ascontiguousarray(p_P, dtype=float)
    R = np.ascontiguousarray(np.reshape(R, (-1, 3, 3)), dtype=float)
    t = np.ascontiguousarray(np.reshape(t, (-1, 3)), dtype=float)
    if p_P.ndim != 3 or p_P.shape[2] != 3 or R.shape[0] not in (1, p_P.shape[0]) or t.shape[0] not in (1, p_P.shape[0]):
        raise ValueError(f"in_frame: points {p_P.shape}, rotations {R.shape} and translations {t.shape} do not match")
    out = np.empty_like(p_P)
    _in_frame_kernel(p_P, R, t, out)
    return out


@njit(cache=True, parallel=True)
def _in_frame_kernel(p, R, t, out):  # pragma: no cover - numba
    P, N = p.shape[0], p.shape[1]
    for cc in prange((P + _CHUNK - 1) // _CHUNK):
        for q in range(cc * _CHUNK, min((cc + 1) * _CHUNK, P)):
            f = q if R.shape[0] > 1 else 0
            g = q if t.shape[0] > 1 else 0
            for i in range(N):
                d0 = p[q, i, 0] - t[g, 0]
                d1 = p[q, i, 1] - t[g, 1]
                d2 = p[q, i, 2] - t[g, 2]
                for c in range(3):
                    out[q, i, c] = d0 * R[f, 0, c] + d1 * R[f, 1, c] + d2 * R[f, 2, c]


def is_rotation(R, tol: float = 1e-6) -> np.ndarray:
    """Whether each 3 x 3 matrix of ``R`` (..., 3, 3) is a rotation: orthonormal within
    ``tol`` and of determinant +1 (not a reflection); a boolean array of R's leading shape.
    Compiled, one pass: the rolling move checks its hypotheses' poses with it every step
    (numpy's batched product and determinant took 22 ms at 60,000)."""
    R = np.asarray(R, dtype=np.float64)
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"is_rotation: R must have shape (..., 3, 3), got {R.shape}")
    flat = np.ascontiguousarray(R.reshape(-1, 3, 3))
    ok = np.empty(flat.shape[0], dtype=np.bool_)
    _is_rotation_kernel(flat, float(tol), ok)
    return ok.reshape(R.shape[:-2])


@njit(cache=True, parallel=True)
def _is_rotation_kernel(R, tol, ok):  # pragma: no cover - numba
    """ok[p]: max |R R^T - I| <= tol and det R > 0 (NaN fails both)."""
    for cc in prange((R.shape[0] + _CHUNK - 1) // _CHUNK):
        for p in range(cc * _CHUNK, min((cc + 1) * _CHUNK, R.shape[0])):
            off = 0.0
            for i in range(3):
                for j in range(3):
                    d = R[p, i, 0] * R[p, j, 0] + R[p, i, 1] * R[p, j, 1] + R[p, i, 2] * R[p, j, 2]
                    e = abs(d - (1.0 if i == j else 0.0))
                    if not e <= off:  # (NaN too)
                        off = e
            det = (R[p, 0, 0] * (R[p, 1, 1] * R[p, 2, 2] - R[p, 1, 2] * R[p, 2, 1])
                   - R[p, 0, 1] * (R[p, 1, 0] * R[p, 2, 2] - R[p, 1, 2] * R[p, 2, 0])
                   + R[p, 0, 2] * (R[p, 1, 0] * R[p, 2, 1] - R[p, 1, 1] * R[p, 2, 0]))
            ok[p] = off <= tol and det > 0.0


def rotation_angle(R_a, R_b) -> np.ndarray:
    """Angle [rad] of R_a^T R_b, batched (P,)."""
    c = (np.einsum("pij,pij->p", R_a, R_b) - 1.0) / 2.0
    return np.arccos(np.clip(c, -1.0, 1.0))


def rotvec(R) -> np.ndarray:
    """Rotation vectors (P, 3) of rotation matrices (P, 3, 3) (axis * angle)."""
    R = np.asarray(R, float)
    if R.shape[-2:] != (3, 3) or R.ndim not in (2, 3):
        raise ValueError(f"rotvec: R must have shape (3, 3) or (P, 3, 3), got {R.shape}")
    # (only a reflection is refused here: the kernel's pass takes no full is_rotation test)
    R = np.ascontiguousarray(R.reshape(-1, 3, 3))
    out, det = np.empty((R.shape[0], 3)), np.empty(R.shape[0])
    _rotvec_kernel(R, out, det)  # (the determinants in the same pass: a full is_rotation test
    # per matrix cost six times the rotation vectors on the informative actions' 20,000)
    if not np.all((det > 0.5) & (det < 1.5)):  # a reflection (det -1) had come out as the identity,
        # a scaled rotation (det s^3) as a rotation vector of some other angle
        if not np.all(np.isfinite(R)):  # (NaN had been reported as a reflection)
            raise ValueError("rotvec: R is not finite")
        if np.all(det > 0.5):
            bad = int(np.argmax(det >= 1.5))
            raise ValueError(f"rotvec: R is not a rotation (matrix {bad}'s determinant is {det[bad]:.3g}, not 1)")
        raise ValueError("rotvec: R is a reflection (determinant below 0.5), not a rotation")
    return out


def rotvec_to_matrix(w) -> np.ndarray:
    """Rodrigues: rotation matrices (P, 3, 3) of rotation vectors (P, 3)."""
    w = np.asarray(w, float)
    if w.shape[-1:] != (3,) or w.ndim not in (1, 2):
        raise ValueError(f"rotvec_to_matrix: w must have shape (3,) or (P, 3), got {w.shape}")
    w = np.ascontiguousarray(w.reshape(-1, 3))
    R = np.empty((w.shape[0], 3, 3))
    _rodrigues_kernel(w, R)
    return R


def blend_poses(R_a, t_a, R_b, t_b, fraction: float) -> tuple[np.ndarray, np.ndarray]:
    """Poses a ``fraction`` of the way from (R_a (P, 3, 3), t_a (P, 3)) to one pose
    (R_b (3, 3), t_b (3,)): R_a exp(fraction log(R_a^T R_b)) and the linear blend of t."""
    R_a = np.ascontiguousarray(R_a, dtype=float)
    t_a = np.ascontiguousarray(t_a, dtype=float)
    # (shapes checked: the kernel reads R_a's count of poses from t_a unchecked, and a shorter
    # t_a had written past its output's end)
    if R_a.ndim != 3 or R_a.shape[1:] != (3, 3) or t_a.shape != (R_a.shape[0], 3):
        raise ValueError(f"blend_poses: R_a must be (P, 3, 3) and t_a (P, 3), got {R_a.shape} and {t_a.shape}")
    if np.size(R_b) != 9 or np.size(t_b) != 3:
        raise ValueError(f"blend_poses: R_b must be (3, 3) and t_b (3,), got sizes {np.size(R_b)} and {np.size(t_b)}")
    R_b = np.ascontiguousarray(np.reshape(R_b, (3, 3)), dtype=float)
    t_b = np.ascontiguousarray(np.reshape(t_b, 3), dtype=float)
    R = np.empty_like(R_a)
    t = np.empty_like(t_a)
    _blend_kernel(R_a, t_a, R_b, t_b, float(fraction), R, t)
    return R, t


def pose_error(R_pred, t_pred, R_meas, t_meas) -> tuple[np.ndarray, np.ndarray]:
    """Position error [m] and rotation error [rad] of predicted vs measured poses, (P,)."""
    dp = np.linalg.norm(np.asarray(t_pred) - np.asarray(t_meas), axis=-1)
    R_meas = np.broadcast_to(R_meas, np.shape(R_pred))
    return dp, rotation_angle(R_pred, R_meas)
