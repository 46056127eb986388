"""The rolling equilibrium for many hypotheses at once: batched Newton on its KKT system.

The same problem as :func:`vlr_drake.rolling_reference.solve_rolling` (see its module
docstring: the pads rolling over the object, the links' and the object's weight, the
object's pose explicit), solved for P hypotheses together, particles on the leading axis.
The unknowns of each are x = (theta (N*K), w (3), tau (3)), w the Cayley parameters of
the object's turn and tau its translation, and the 3N attachment multipliers lambda;
Newton steps on the Lagrangian's stationarity and the attachments,

    [H  J^T] [dx]      [grad E + J^T lambda]
    [J   0 ] [dl]  = - [g                  ],

with H the Lagrangian's Hessian: the springs, the tendons, the links' potential, the
object's potential, the pads' forward kinematics' curvature and the Cayley rotation's.
Every derivative is analytic; the pads' kinematics are Gamma's
(:func:`vlr_drake.motion._fk_all`).

The set-up (the contacts and normals in the object's frame, the roll's Jacobians) is
numpy; the Newton iteration is compiled with numba and runs in parallel over hypotheses,
each thread one hypothesis at a time: its KKT matrix, N K + 3N + 6 square (21 on the Model
O), by elimination with partial pivoting (:func:`vlr_drake.motion._solve`), by least
squares where that finds it singular. With ``FilterConfig.motion_model = "rolling"`` it is
the filter's Gamma. The tests hold it to the MathematicalProgram reference to 1e-8 rad.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from vlr_drake import motion
from vlr_drake.hand import HandModel

__all__ = ["NORMAL_GUESSES", "RollingMove", "circle_centres", "move_rolling", "guessed_normals", "hinge_axes"]

#: Newton's stopping tolerances: stationarity [N m, N] and attachments [m].
GRAD_TOL = 1e-10
ATTACH_TOL = 1e-12
#: Cap on one Newton step's largest joint change [rad].
MAX_STEP = 0.1
#: [e_a]x, a = 0, 1, 2: the Cayley derivatives' basis (:func:`_cayley_derivatives`'s E).
SKEW_BASIS = np.array([[[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]],
                       [[0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [-1.0, 0.0, 0.0]],
                       [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]]])


@dataclass
class RollingMove:
    theta: np.ndarray  # (P, N, K)
    R: np.ndarray  # (P, 3, 3) the object's pose after the move
    t: np.ndarray  # (P, 3)
    ok: np.ndarray  # (P,) converged
    iterations: int  # the most Newton steps any hypothesis took
    stretch: np.ndarray  # (P, N) the tendons' stretch after the move [m]
    tension: np.ndarray  # (P, N) their tension kappa * stretch [N]
    newton_iterations: np.ndarray  # (P,) each hypothesis' Newton steps


def _cayley(w):
    """Cayley rotations (P, 3, 3) of (P, 3) parameters (real or complex)."""
    q = 0.5 * w
    Q = np.zeros(w.shape[:1] + (3, 3), dtype=w.dtype)
    Q[:, 0, 1], Q[:, 0, 2], Q[:, 1, 2] = -q[:, 2], q[:, 1], -q[:, 0]
    Q[:, 1, 0], Q[:, 2, 0], Q[:, 2, 1] = q[:, 2], -q[:, 1], q[:, 0]
    s = 2.0 / (1.0 + np.einsum("pi,pi->p", q, q))
    return np.eye(3) + s[:, None, None] * (Q + Q @ Q)


def _kinematics(hand: HandModel, theta, a, link_lengths):
    """Pads' centres (P, N, 3), their Jacobians dp_i/dtheta_ij (P, N, K, 3) and second
    derivatives d2p_i/dtheta_ij dtheta_ik (P, N, K, K, 3), in the palm frame, for link
    lengths (P or 1, N, K-1): the batched Gamma's compiled kernel
    (:func:`vlr_drake.motion._fk_all`), particles first."""
    P, N, K = theta.shape
    L = np.broadcast_to(np.moveaxis(link_lengths, 0, -1), (N, K - 1, P))
    Pc, Jc, Hc = np.empty((N, 3, P)), np.empty((N, 3, K, P)), np.empty((N, 3, K, K, P))
    motion._fk_all(np.ascontiguousarray(np.moveaxis(theta, 0, -1)), np.ascontiguousarray(L),
                   np.ascontiguousarray(a.T), hand.pad, hand.base, hand.u, Pc, Jc, Hc)
    return np.moveaxis(Pc, -1, 0), np.moveaxis(Jc, (-1, 1), (0, -1)), np.moveaxis(Hc, (-1, 1), (0, -1))


def hinge_axes(hand: HandModel) -> np.ndarray:
    """(N, 3) unit axes z x u_i of the fingers' joints: the normals of their flexion planes."""
    h = np.cross(np.array([0.0, 0.0, 1.0]), hand.u)
    return h / np.linalg.norm(h, axis=1, keepdims=True)


#: The guesses of the object's normals at the contacts (guessed_normals' ``kind``).
NORMAL_GUESSES = ("flexion_plane", "circle")


def guessed_normals(hand: HandModel, p, kind: str = "flexion_plane") -> np.ndarray:
    """A guess (P, N, 3) of the object's outward unit normals at the contacts ``p`` (P, N, 3)
    (palm frame).

    ``kind`` "flexion_plane": each contact's direction from the contacts' centroid, in its
    finger's flexion plane (the component along the finger's hinge axis z x u_i removed): a
    flat-faced object gripped face-on. On the physics plant's toy block it is 0.2 deg from
    the block's face normals at the true grasp; on the apple, whose side-by-side fingers
    touch it 35 deg out of their flexion planes, 34-38 deg off at the fingers.

    ``kind`` "circle": each contact's direction from the centre of the circle through the
    contacts (least squares in their plane; their centroid where they are collinear or fewer
    than three): a round object whose centre lies in the contacts' plane. On the apple
    (NH2's grasp) it is within 2 deg of the sphere's normals.

    A filter draws its hypotheses' normals around a guess once and keeps them fixed in the
    object's frame (re-guessed at every step from each hypothesis' own contacts, it turns
    the normals with the hypothesis' error, which made the filter worse: docs/results.md)."""
    p = np.asarray(p, float)
    if p.ndim != 3 or p.shape[1:] != (hand.N, 3):
        raise ValueError(f"guessed_normals: 'p' must have shape (P, {hand.N}, 3), got {p.shape}")
    if kind not in NORMAL_GUESSES:
        raise ValueError(f"guessed_normals: 'kind' must be one of {NORMAL_GUESSES}, got '{kind}'")
    if kind == "circle":
        d = p - circle_centres(p)[:, None]
        n = np.linalg.norm(d, axis=-1, keepdims=True)
        if not np.all(n > 1e-9):
            raise ValueError("guessed_normals: a contact sits at the centre of the contacts' circle; no outward "
                             "direction to guess from")
        return d / n
    d = p - p.mean(axis=1, keepdims=True)
    hinge = hinge_axes(hand)
    d -= np.einsum("pni,ni->pn", d, hinge)[..., None] * hinge[None]
    n = np.linalg.norm(d, axis=-1, keepdims=True)
    if not np.all(n > 1e-9):
        raise ValueError("guessed_normals: a contact sits at the contacts' centroid (within its finger's plane); "
                         "no outward direction to guess from")
    return d / n


def circle_centres(p: np.ndarray) -> np.ndarray:
    """(P, 3) centres of the circles through each hypothesis' contacts ``p`` (P, N, 3): in
    the contacts' least-squares plane, the centre c minimising sum_i (|p_i - c|^2 - r^2)^2
    (exact through three contacts); the centroid where the contacts are fewer than three or
    collinear."""
    m = p.mean(axis=1)
    d = p - m[:, None]
    if p.shape[1] < 3:
        return m
    _, sv, vt = np.linalg.svd(d)
    e1, e2 = vt[:, 0], vt[:, 1]
    x, y = np.einsum("pni,pi->pn", d, e1), np.einsum("pni,pi->pn", d, e2)
    A = np.stack([2 * x, 2 * y, np.ones_like(x)], axis=-1)
    ok = sv[:, 1] > 1e-6 * np.maximum(sv[:, 0], 1e-300)  # not collinear
    out = m.copy()
    if np.any(ok):
        AtA = np.einsum("pni,pnj->pij", A[ok], A[ok])
        Atb = np.einsum("pni,pn->pi", A[ok], x[ok] ** 2 + y[ok] ** 2)
        z = np.linalg.solve(AtA, Atb[..., None])[..., 0]
        out[ok] += z[:, :1] * e1[ok] + z[:, 1:2] * e2[ok]
    return out


def move_rolling(hand: HandModel, theta, a, R, t, normals, stretch, dl=None, gravity=None, object_mass=None,
                 com=None, pad_radius=None, stiffness=None, link_lengths=None, curvature_radius=None,
                 max_iter: int = 50) -> RollingMove:
    """The rolling equilibrium of each of P hypotheses after the action ``dl``.

    theta (P, N, K), a (P, N), R (P, 3, 3) and t (P, 3) the object's pose, normals (P, N, 3)
    the object's outward normals at the contacts (palm frame), stretch (P, N); ``dl`` (N,)
    or (P, N) (default none); ``gravity`` (3,) [m/s^2] (None: no weights); object_mass (P,)
    [kg] and com (P, 3) (palm frame) with gravity; ``pad_radius`` (N,) (default the hand's);
    ``stiffness`` (P or 1, N, K) per-hypothesis springs and ``link_lengths`` (P or 1, N,
    K-1) per-hypothesis links (default the hand's; the links' masses follow their lengths,
    :meth:`HandModel.link_moments`); ``curvature_radius`` (P or 1, N) [m] the object's surface
    radius at each contact (inf, or None for all: a flat face), with which a pad rolls over a
    round object as a ball on a ball, its centre's path curving towards the object's centre of
    curvature (:class:`vlr_drake.rolling_reference.RollingState`; here to second order in the
    pad's turn, the reference exactly). Newton starts
    at the hypotheses' own angles and pose; ``ok`` is False where it has not converged in
    ``max_iter`` steps (about 1% of hypotheses drawn 0.02 rad and 2 mm around a grasp, which
    wander off by 10-40 deg)."""
    theta = np.asarray(theta, float)
    P, N, K = theta.shape
    if (N, K) != (hand.N, hand.K):
        raise ValueError(f"move_rolling: 'theta' must have shape (P, {hand.N}, {hand.K}), got {theta.shape}")
    a = np.broadcast_to(np.asarray(a, float), (P, N)).copy()
    R = np.broadcast_to(np.asarray(R, float), (P, 3, 3)).copy()
    t = np.broadcast_to(np.asarray(t, float), (P, 3)).copy()
    nrm = np.broadcast_to(np.asarray(normals, float), (P, N, 3))
    nrm = nrm / np.linalg.norm(nrm, axis=-1, keepdims=True)
    stretch = np.broadcast_to(np.asarray(stretch, float), (P, N)).copy()
    dl = np.zeros((P, N)) if dl is None else np.broadcast_to(np.asarray(dl, float), (P, N)).copy()
    r = hand.pad_radius if pad_radius is None else np.broadcast_to(np.asarray(pad_radius, float), (N,))
    g = np.zeros(3) if gravity is None else np.asarray(gravity, float)
    k = np.broadcast_to(hand.stiffness if stiffness is None else np.asarray(stiffness, float), (P, N, K)).copy()
    mass = np.zeros(P) if object_mass is None else np.broadcast_to(np.asarray(object_mass, float), (P,)).copy()
    if com is None and gravity is not None and np.any(mass != 0):  # else its weight would act at t
        raise ValueError("move_rolling: an object with mass needs its centre of mass 'com' (P, 3)")
    L = hand.link_lengths[None] if link_lengths is None else np.asarray(link_lengths, float)
    if L.ndim != 3 or L.shape[0] not in (1, P) or L.shape[1:] != (N, K - 1):
        raise ValueError(f"move_rolling: 'link_lengths' must have shape (1 or {P}, {N}, {K - 1}), got {L.shape}")
    L = np.broadcast_to(L, (P, N, K - 1))
    RT = np.swapaxes(R, 1, 2)
    p0, _, _ = _kinematics(hand, theta, a, L)
    cO = np.einsum("pij,pnj->pni", RT, p0 - t[:, None])  # centres in the object frame
    nO = np.einsum("pij,pnj->pni", RT, nrm)
    comO = np.zeros((P, 3)) if com is None else np.einsum("pij,pj->pi", RT, np.asarray(com, float) - t)
    hinge = hinge_axes(hand)  # (N, 3)
    # v_i = cO_i + r_i (R^T (dphi_i h_i - w)) x nO_i = cO_i - r_i [nO_i]x R^T (dphi_i h_i - w)
    B = r[None, :, None, None] * np.einsum("pnij,pjk->pnik", _skew(nO), RT)  # dv_i/dw (P, N, 3, 3)
    b = -np.einsum("pnij,nj->pni", B, hinge)  # dv_i/dtheta_ik (P, N, 3), every k of finger i
    # a round object: v_i also moves by -(kap_i / 2) |P_t y_i|^2 nO_i, y_i = dphi_i h_i - w, with
    # kap_i = r_i^2 / (radius_i + r_i) and P_t the projection off the normal (a ball on a ball)
    kap = np.zeros((P, N))
    if curvature_radius is not None:
        rad = np.broadcast_to(np.asarray(curvature_radius, float), (P, N))
        if np.any(np.isnan(rad)) or not np.all(rad > 0):
            raise ValueError("move_rolling: 'curvature_radius' must be radii > 0 [m] (inf: a flat face)")
        kap = np.where(np.isfinite(rad), r[None] ** 2 / (rad + r[None]), 0.0)
    mu = np.broadcast_to(hand.link_moments(L) if gravity is not None else np.zeros((1, N, K)), (P, N, K))
    g_u, g_z = hand.gravity_in_finger_planes(g).T
    x_theta, w, tau = np.empty((P, N, K)), np.empty((P, 3)), np.empty((P, 3))
    ok, iters = np.zeros(P, bool), np.zeros(P, np.int64)

    def c(x):
        return np.ascontiguousarray(x, dtype=float)

    _newton_kernel(c(theta), c(a), c(R), c(t), c(cO), c(B), c(b), c(nO), c(kap), c(hinge), c(stretch), c(dl), c(mass),
                   c(comO), c(g),
                   c(mu), c(g_u), c(g_z), c(k), c(L), c(hand.pad), c(hand.base), c(hand.u), c(hand.moment_arms),
                   c(hand.rest_angles), c(hand.kappa), int(max_iter), MAX_STEP, GRAD_TOL, ATTACH_TOL,
                   x_theta, w, tau, ok, iters)
    iterations = int(iters.max()) if P else 0
    C = _cayley(w)
    ok &= np.isfinite(x_theta).all(axis=(1, 2)) & np.isfinite(w).all(axis=1)
    s_new = stretch + dl - np.einsum("nk,pnk->pn", hand.moment_arms, x_theta - theta)
    return RollingMove(x_theta, C @ R, t + tau, ok, iterations, s_new, hand.kappa[None] * s_new, iters)



def _skew(v):
    """(..., 3) -> (..., 3, 3) with _skew(v) y = v x y."""
    S = np.zeros(v.shape + (3,))
    S[..., 0, 1], S[..., 0, 2], S[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    S[..., 1, 0], S[..., 2, 0], S[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    return S


@njit(cache=True)
def _sym_product(A, B, out):  # pragma: no cover - numba
    """out = A B + B A for 3x3 matrices (no BLAS call: these are too small for one)."""
    for i in range(3):
        for j in range(3):
            out[i, j] = (A[i, 0] * B[0, j] + A[i, 1] * B[1, j] + A[i, 2] * B[2, j]
                         + B[i, 0] * A[0, j] + B[i, 1] * A[1, j] + B[i, 2] * A[2, j])


@njit(cache=True)
def _cayley_derivatives(w, C, dC, d2C, E, W, Nm, Na, Nab):  # pragma: no cover - numba
    """The Cayley rotation C = I + (4 W + 2 W^2) / (4 + |w|^2), W = [w]x, of ``w`` (3,)
    (the same rotation as :func:`_cayley`), into C (3, 3), dC[a] = dC/dw_a (3, 3, 3) and
    d2C[a, b] = d2C/dw_a dw_b (3, 3, 3, 3), analytically. E (3, 3, 3) holds [e_a]x; W,
    Nm (3, 3), Na (3, 3, 3) and Nab (3, 3) are scratch."""
    for i in range(3):
        for j in range(3):
            W[i, j] = w[0] * E[0, i, j] + w[1] * E[1, i, j] + w[2] * E[2, i, j]
    _sym_product(W, W, Nm)  # 2 W^2
    for i in range(3):
        for j in range(3):
            Nm[i, j] += 4.0 * W[i, j]  # the numerator N(w) = 4 W + 2 W^2
    D = 4.0 + w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    for a in range(3):
        _sym_product(E[a], W, Na[a])
        for i in range(3):
            for j in range(3):
                Na[a, i, j] = 4.0 * E[a, i, j] + 2.0 * Na[a, i, j]  # dN/dw_a
    for i in range(3):
        for j in range(3):
            C[i, j] = (1.0 if i == j else 0.0) + Nm[i, j] / D
    for a in range(3):
        for i in range(3):
            for j in range(3):
                dC[a, i, j] = Na[a, i, j] / D - 2.0 * w[a] * Nm[i, j] / (D * D)
    for a in range(3):
        for b in range(a, 3):
            _sym_product(E[a], E[b], Nab)  # d2N/dw_a dw_b = 2 (E_a E_b + E_b E_a)
            for i in range(3):
                for j in range(3):
                    v = (2.0 * Nab[i, j] / D - 2.0 * (w[b] * Na[a, i, j] + w[a] * Na[b, i, j]) / (D * D)
                         + 8.0 * w[a] * w[b] * Nm[i, j] / (D * D * D))
                    if a == b:
                        v -= 2.0 * Nm[i, j] / (D * D)
                    d2C[a, b, i, j] = v
                    d2C[b, a, i, j] = v


@njit(cache=True)
def _newton_range(start, stop, theta0, a, R, t, cO, B, b, nO, kap, hinge, stretch, dl, mass, comO, g, mu, g_u, g_z,
                  kst, L,
                  pad, base, u, marm, rest, kappa, max_iter, max_step, grad_tol, attach_tol,
                  x_out, w_out, tau_out, ok, iters):  # pragma: no cover - numba
    """Newton on the rolling equilibrium's KKT system (module docstring) for hypotheses
    ``start:stop``, one at a time; scratch allocated once."""
    N, K = theta0.shape[1], theta0.shape[2]
    nK = N * K
    nx = nK + 6
    m = 3 * N
    dim = nx + m
    th, Ll, al = np.empty((N, K, 1)), np.ones((N, max(K - 1, 1), 1)), np.empty((N, 1))
    Pc, Jc, Hc = np.empty((N, 3, 1)), np.empty((N, 3, K, 1)), np.empty((N, 3, K, K, 1))
    C, dC, d2C = np.empty((3, 3)), np.empty((3, 3, 3)), np.empty((3, 3, 3, 3))
    E = SKEW_BASIS.copy()
    Wc, Nm, Na, Nab = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3, 3)), np.empty((3, 3))
    x, w, tau, lam = np.empty((N, K)), np.empty(3), np.empty(3), np.empty(m)
    v, Rv, CRb, Rb = np.empty((N, 3)), np.empty((N, 3)), np.empty((N, 3)), np.empty((N, 3))
    RB, RcomO, CR = np.empty((N, 3, 3)), np.empty(3), np.empty((3, 3))
    Jm, KKT, KKT0, rhs, rhs0 = np.empty((m, nx)), np.empty((dim, dim)), np.empty((dim, dim)), np.empty(dim), np.empty(dim)
    phi, per, curv, dphi = np.empty(K), np.empty(K), np.empty(K), np.empty(N)
    Rn, CRn, yv, Gy, dCRn = np.empty((N, 3)), np.empty((N, 3)), np.empty((N, 3)), np.empty((N, 3)), np.empty((3, N, 3))
    lCRn, hn, Gyh = np.empty(N), np.empty(N), np.empty(N)
    for p in range(start, stop):
        for i in range(N):
            al[i, 0] = a[p, i]
            for k in range(K - 1):
                Ll[i, k, 0] = L[p, i, k]
            for k in range(K):
                x[i, k] = theta0[p, i, k]
        w[:] = 0.0
        tau[:] = 0.0
        lam[:] = 0.0
        for j in range(3):
            RcomO[j] = R[p, j, 0] * comO[p, 0] + R[p, j, 1] * comO[p, 1] + R[p, j, 2] * comO[p, 2]
        for i in range(N):
            for j in range(3):
                Rn[i, j] = R[p, j, 0] * nO[p, i, 0] + R[p, j, 1] * nO[p, i, 1] + R[p, j, 2] * nO[p, i, 2]
            hn[i] = Rn[i, 0] * hinge[i, 0] + Rn[i, 1] * hinge[i, 1] + Rn[i, 2] * hinge[i, 2]  # G = I - Rn Rn^T
        for i in range(N):
            for j in range(3):
                Rb[i, j] = R[p, j, 0] * b[p, i, 0] + R[p, j, 1] * b[p, i, 1] + R[p, j, 2] * b[p, i, 2]
                for c in range(3):
                    RB[i, j, c] = R[p, j, 0] * B[p, i, 0, c] + R[p, j, 1] * B[p, i, 1, c] + R[p, j, 2] * B[p, i, 2, c]
        ok[p] = False
        iters[p] = 0
        for it in range(max_iter):
            iters[p] = it + 1
            for i in range(N):
                for k in range(K):
                    th[i, k, 0] = x[i, k]
            motion._fk_all(th, Ll, al, pad, base, u, Pc, Jc, Hc)
            _cayley_derivatives(w, C, dC, d2C, E, Wc, Nm, Na, Nab)
            for r in range(3):
                for c in range(3):
                    CR[r, c] = C[r, 0] * R[p, 0, c] + C[r, 1] * R[p, 1, c] + C[r, 2] * R[p, 2, c]
            # the attachments g_i = p_i - C R v_i - (t + tau), and their Jacobian
            for i in range(N):
                dphi[i] = 0.0
                for k in range(K):
                    dphi[i] += x[i, k] - theta0[p, i, k]
                ny = 0.0
                for c in range(3):
                    yv[i, c] = dphi[i] * hinge[i, c] - w[c]
                    ny += Rn[i, c] * yv[i, c]
                yGy = 0.0
                Gyh[i] = 0.0
                for c in range(3):
                    Gy[i, c] = yv[i, c] - ny * Rn[i, c]
                    yGy += yv[i, c] * Gy[i, c]
                    Gyh[i] += Gy[i, c] * hinge[i, c]
                for r in range(3):
                    s = cO[p, i, r] - 0.5 * kap[p, i] * yGy * nO[p, i, r]
                    for c in range(3):
                        s -= B[p, i, r, c] * yv[i, c]
                    v[i, r] = s
            for i in range(N):
                for r in range(3):
                    Rv[i, r] = R[p, r, 0] * v[i, 0] + R[p, r, 1] * v[i, 1] + R[p, r, 2] * v[i, 2]
                    if kap[p, i] != 0.0:  # a round object's roll (else its terms vanish: no work)
                        CRn[i, r] = CR[r, 0] * nO[p, i, 0] + CR[r, 1] * nO[p, i, 1] + CR[r, 2] * nO[p, i, 2]
                        for aa in range(3):
                            dCRn[aa, i, r] = dC[aa, r, 0] * Rn[i, 0] + dC[aa, r, 1] * Rn[i, 1] + dC[aa, r, 2] * Rn[i, 2]
                    else:
                        CRn[i, r] = 0.0
                        for aa in range(3):
                            dCRn[aa, i, r] = 0.0
                    CRb[i, r] = CR[r, 0] * b[p, i, 0] + CR[r, 1] * b[p, i, 1] + CR[r, 2] * b[p, i, 2]
            gmax, finite = 0.0, True
            Jm[:, :] = 0.0
            for i in range(N):
                for r in range(3):
                    row = 3 * i + r
                    gv = Pc[i, r, 0] - t[p, r] - tau[r]
                    for c in range(3):
                        gv -= CR[r, c] * v[i, c]
                    rhs[nx + row] = gv
                    gmax = max(gmax, abs(gv))
                    finite &= np.isfinite(gv)
                    for k in range(K):
                        Jm[row, i * K + k] = Jc[i, r, k, 0] - CRb[i, r] + kap[p, i] * Gyh[i] * CRn[i, r]
                    for aa in range(3):
                        s = 0.0
                        for c in range(3):
                            s += dC[aa, r, c] * Rv[i, c] + CR[r, c] * B[p, i, c, aa]
                        Jm[row, nK + aa] = -s - kap[p, i] * Gy[i, aa] * CRn[i, r]
                    Jm[row, nK + 3 + r] = -1.0
            # stationarity: grad E + J^T lambda
            KKT[:, :] = 0.0
            for i in range(N):
                lCRn[i] = lam[3 * i] * CRn[i, 0] + lam[3 * i + 1] * CRn[i, 1] + lam[3 * i + 2] * CRn[i, 2]
            for i in range(N):
                s_new = stretch[p, i] + dl[p, i]
                acc = 0.0
                for k in range(K):
                    s_new -= marm[i, k] * (x[i, k] - theta0[p, i, k])
                    acc += x[i, k]
                    phi[k] = acc
                for k in range(K):
                    cs, sn = np.cos(phi[k]), np.sin(phi[k])
                    per[k] = mu[p, i, k] * (g_u[i] * cs - g_z[i] * sn)
                    curv[k] = mu[p, i, k] * (g_u[i] * sn + g_z[i] * cs)
                for k in range(K - 2, -1, -1):  # suffix sums over l >= k
                    per[k] += per[k + 1]
                    curv[k] += curv[k + 1]
                for k in range(K):
                    q = i * K + k
                    rhs[q] = kst[p, i, k] * (x[i, k] - rest[i, k]) - kappa[i] * s_new * marm[i, k] - per[k]
                    for k2 in range(K):
                        hv = kappa[i] * marm[i, k] * marm[i, k2] + curv[max(k, k2)] + kap[p, i] * lCRn[i] * (1.0 - hn[i] * hn[i])
                        for c in range(3):
                            hv += lam[3 * i + c] * Hc[i, c, k, k2, 0]
                        KKT[q, i * K + k2] = hv
                    KKT[q, q] += kst[p, i, k]
                for aa in range(3):  # theta_ik with w_a, the same for every k of finger i
                    s = 0.0
                    for c in range(3):
                        for j in range(3):
                            s -= lam[3 * i + c] * dC[aa, c, j] * Rb[i, j]
                    if kap[p, i] != 0.0:  # a round object's roll: kap ((Gy.h) lam.dC_a R n - (lam.CRn) (G h)_a)
                        ldn = lam[3 * i] * dCRn[aa, i, 0] + lam[3 * i + 1] * dCRn[aa, i, 1] + lam[3 * i + 2] * dCRn[aa, i, 2]
                        s += kap[p, i] * (Gyh[i] * ldn - lCRn[i] * (hinge[i, aa] - hn[i] * Rn[i, aa]))
                    for k in range(K):
                        KKT[i * K + k, nK + aa] += s
                        KKT[nK + aa, i * K + k] += s
            for aa in range(3):
                s = 0.0
                for i in range(3):
                    for j in range(3):
                        s += g[i] * dC[aa, i, j] * RcomO[j]
                rhs[nK + aa] = -mass[p] * s
                rhs[nK + 3 + aa] = -mass[p] * g[aa]
            for q in range(nx):
                s = 0.0
                for row in range(m):
                    s += Jm[row, q] * lam[row]
                rhs[q] += s
            rmax = 0.0
            for q in range(nx):
                rmax = max(rmax, abs(rhs[q]))
                finite &= np.isfinite(rhs[q])
            if not finite:  # a NaN or an overflow: failed
                break
            if rmax < grad_tol and gmax < attach_tol:
                ok[p] = True
                break
            # the object's turn: its weight, the attachments' curvature and their cross terms
            for aa in range(3):
                for bb in range(3):
                    hv = 0.0
                    for i in range(3):
                        for j in range(3):
                            hv -= mass[p] * g[i] * d2C[aa, bb, i, j] * RcomO[j]
                    for n in range(N):
                        for c in range(3):
                            for j in range(3):
                                hv -= lam[3 * n + c] * (d2C[aa, bb, c, j] * Rv[n, j] + dC[aa, c, j] * RB[n, j, bb]
                                                        + dC[bb, c, j] * RB[n, j, aa])
                    for n in range(N):
                        if kap[p, n] != 0.0:
                            la = lam[3 * n] * dCRn[aa, n, 0] + lam[3 * n + 1] * dCRn[aa, n, 1] + lam[3 * n + 2] * dCRn[aa, n, 2]
                            lb = lam[3 * n] * dCRn[bb, n, 0] + lam[3 * n + 1] * dCRn[bb, n, 1] + lam[3 * n + 2] * dCRn[bb, n, 2]
                            G_ab = (1.0 if aa == bb else 0.0) - Rn[n, aa] * Rn[n, bb]
                            hv += kap[p, n] * (lCRn[n] * G_ab - la * Gy[n, bb] - lb * Gy[n, aa])
                    KKT[nK + aa, nK + bb] += hv
            for row in range(m):
                for q in range(nx):
                    KKT[q, nx + row] = Jm[row, q]
                    KKT[nx + row, q] = Jm[row, q]
            for q in range(dim):
                rhs[q] = -rhs[q]
            KKT0[:, :] = KKT
            rhs0[:] = rhs
            if not motion._solve(KKT, rhs):  # singular: the least-squares step
                rhs[:] = np.linalg.lstsq(KKT0, rhs0)[0]
            big = 0.0
            for q in range(nK):
                big = max(big, abs(rhs[q]))
            scale = max_step / big if big > max_step else 1.0
            for i in range(N):
                for k in range(K):
                    x[i, k] += scale * rhs[i * K + k]
            for c in range(3):
                w[c] += scale * rhs[nK + c]
                tau[c] += scale * rhs[nK + 3 + c]
            for row in range(m):
                lam[row] += scale * rhs[nx + row]
        for i in range(N):
            for k in range(K):
                x_out[p, i, k] = x[i, k]
        for c in range(3):
            w_out[p, c] = w[c]
            tau_out[p, c] = tau[c]


#: Hypotheses per parallel task of :func:`_newton_kernel`.
CHUNK = 64


@njit(cache=True, parallel=True)
def _newton_kernel(theta0, a, R, t, cO, B, b, nO, kap, hinge, stretch, dl, mass, comO, g, mu, g_u, g_z, kst, L, pad,
                   base, u,
                   marm, rest, kappa, max_iter, max_step, grad_tol, attach_tol,
                   x_out, w_out, tau_out, ok, iters):  # pragma: no cover - numba
    """Every hypothesis' Newton (:func:`_newton_range`), CHUNK of them per parallel task."""
    P = theta0.shape[0]
    tasks = (P + CHUNK - 1) // CHUNK
    for tk in prange(tasks):
        start = np.int64(tk) * CHUNK
        _newton_range(start, min(start + CHUNK, P), theta0, a, R, t, cO, B, b, nO, kap, hinge, stretch, dl, mass, comO,
                      g, mu,
                      g_u, g_z, kst, L, pad, base, u, marm, rest, kappa, max_iter, max_step, grad_tol, attach_tol,
                      x_out, w_out, tau_out, ok, iters)
