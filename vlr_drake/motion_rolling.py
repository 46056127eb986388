"""The rolling equilibrium for many hypotheses at once: batched Newton on its KKT system.

The same problem as :func:`vlr_drake.rolling_reference.solve_rolling` (see its module
docstring: the pads rolling over the object, the links' and the object's weight, the
object's pose explicit), solved for P hypotheses together in plain numpy, particles on the
leading axis. The unknowns of each are x = (theta (N*K), w (3), tau (3)) and the 3N
attachment multipliers; Newton steps on the Lagrangian's stationarity and the attachments,

    [H  J^T] [dx]      [grad E + J^T lambda]
    [J   0 ] [dl]  = - [g                  ],

with H the Lagrangian's Hessian: the springs, the tendons, the links' potential, the
object's potential, the pads' forward kinematics' curvature and the Cayley rotation's. The
Cayley rotation's first and second derivatives are taken by complex steps (exact to
round-off) and central differences of those (1e-10); the pads' kinematics are Gamma's
compiled kernel; everything else is analytic.

It is not yet Gamma: the filter still moves its hypotheses with Eq. 9
(:func:`vlr_drake.motion.move`). This is the batched solver a rolling Gamma would use, held
to the MathematicalProgram reference by the tests.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vlr_drake import motion
from vlr_drake.hand import HandModel

__all__ = ["RollingMove", "move_rolling", "guessed_normals", "hinge_axes"]

#: Newton's stopping tolerances: stationarity [N m, N] and attachments [m].
GRAD_TOL = 1e-10
ATTACH_TOL = 1e-12
#: Cap on one Newton step's largest joint change [rad].
MAX_STEP = 0.1


@dataclass
class RollingMove:
    theta: np.ndarray  # (P, N, K)
    R: np.ndarray  # (P, 3, 3) the object's pose after the move
    t: np.ndarray  # (P, 3)
    ok: np.ndarray  # (P,) converged
    iterations: int
    stretch: np.ndarray  # (P, N) the tendons' stretch after the move [m]
    tension: np.ndarray  # (P, N) their tension kappa * stretch [N]


def _cayley(w):
    """Cayley rotations (P, 3, 3) of (P, 3) parameters (real or complex)."""
    q = 0.5 * w
    Q = np.zeros(w.shape[:1] + (3, 3), dtype=w.dtype)
    Q[:, 0, 1], Q[:, 0, 2], Q[:, 1, 2] = -q[:, 2], q[:, 1], -q[:, 0]
    Q[:, 1, 0], Q[:, 2, 0], Q[:, 2, 1] = q[:, 2], -q[:, 1], q[:, 0]
    s = 2.0 / (1.0 + np.einsum("pi,pi->p", q, q))
    return np.eye(3) + s[:, None, None] * (Q + Q @ Q)


def _cayley_derivatives(w, h=1e-20, d=1e-6):
    """C (P, 3, 3), dC/dw_a (P, 3, 3, 3) and d2C/dw_a dw_b (P, 3, 3, 3, 3) at ``w`` (P, 3)."""
    P = w.shape[0]

    def first(wr):
        out = np.empty((P, 3, 3, 3))
        for a in range(3):
            wc = wr.astype(complex)
            wc[:, a] += 1j * h
            out[:, a] = _cayley(wc).imag / h
        return out

    dC = first(w)
    d2C = np.empty((P, 3, 3, 3, 3))
    for b in range(3):
        plus, minus = w.copy(), w.copy()
        plus[:, b] += d
        minus[:, b] -= d
        d2C[:, :, b] = (first(plus) - first(minus)) / (2 * d)
    return _cayley(w), dC, d2C


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


def guessed_normals(hand: HandModel, p) -> np.ndarray:
    """A guess (P, N, 3) of the object's outward unit normals at the contacts ``p`` (P, N, 3)
    (palm frame): each contact's direction from the contacts' centroid, in its finger's
    flexion plane (the component along the finger's hinge axis z x u_i removed). On the
    physics plant's toy block it is 0.2 deg from the block's face normals at the true grasp;
    a filter draws its hypotheses' normals around it once and keeps them fixed in the
    object's frame (re-guessed at every step from each hypothesis' own contacts, it turns
    the normals with the hypothesis' error, which made the filter worse: docs/results.md)."""
    p = np.asarray(p, float)
    if p.ndim != 3 or p.shape[1:] != (hand.N, 3):
        raise ValueError(f"guessed_normals: 'p' must have shape (P, {hand.N}, 3), got {p.shape}")
    d = p - p.mean(axis=1, keepdims=True)
    hinge = hinge_axes(hand)
    d -= np.einsum("pni,ni->pn", d, hinge)[..., None] * hinge[None]
    n = np.linalg.norm(d, axis=-1, keepdims=True)
    if not np.all(n > 1e-9):
        raise ValueError("guessed_normals: a contact sits at the contacts' centroid (within its finger's plane); "
                         "no outward direction to guess from")
    return d / n


def move_rolling(hand: HandModel, theta, a, R, t, normals, stretch, dl=None, gravity=None, object_mass=None,
                 com=None, pad_radius=None, stiffness=None, link_lengths=None, max_iter: int = 50) -> RollingMove:
    """The rolling equilibrium of each of P hypotheses after the action ``dl``.

    theta (P, N, K), a (P, N), R (P, 3, 3) and t (P, 3) the object's pose, normals (P, N, 3)
    the object's outward normals at the contacts (palm frame), stretch (P, N); ``dl`` (N,)
    or (P, N) (default none); ``gravity`` (3,) [m/s^2] (None: no weights); object_mass (P,)
    [kg] and com (P, 3) (palm frame) with gravity; ``pad_radius`` (N,) (default the hand's);
    ``stiffness`` (P or 1, N, K) per-hypothesis springs and ``link_lengths`` (P or 1, N,
    K-1) per-hypothesis links (default the hand's; the links' masses follow their lengths,
    :meth:`HandModel.link_moments`). Newton starts
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
    r = (hand.pad_surface - hand.pad) if pad_radius is None else np.broadcast_to(np.asarray(pad_radius, float), (N,))
    g = np.zeros(3) if gravity is None else np.asarray(gravity, float)
    k = np.broadcast_to(hand.stiffness if stiffness is None else np.asarray(stiffness, float), (P, N, K)).copy()
    mass = np.zeros(P) if object_mass is None else np.broadcast_to(np.asarray(object_mass, float), (P,)).copy()
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

    def skew(v):  # (..., 3) -> (..., 3, 3), skew(v) y = v x y
        S = np.zeros(v.shape + (3,))
        S[..., 0, 1], S[..., 0, 2], S[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
        S[..., 1, 0], S[..., 2, 0], S[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
        return S

    # v_i = cO_i + r_i (R^T (dphi_i h_i - w)) x nO_i = cO_i - r_i [nO_i]x R^T (dphi_i h_i - w)
    Sn = skew(nO)  # (P, N, 3, 3)
    B = r[None, :, None, None] * np.einsum("pnij,pjk->pnik", Sn, RT)  # dv_i/dw (P, N, 3, 3)
    b = -np.einsum("pnij,nj->pni", B, hinge)  # dv_i/dtheta_ik (P, N, 3), every k of finger i
    mu = np.broadcast_to(hand.link_moments(L) if gravity is not None else np.zeros((1, N, K)), (P, N, K))
    g_u, g_z = hand.gravity_in_finger_planes(g).T
    nx, m = N * K + 6, 3 * N
    x_theta, w, tau = theta.copy(), np.zeros((P, 3)), np.zeros((P, 3))
    lam = np.zeros((P, m))
    ok = np.zeros(P, bool)
    idx_max = np.maximum.outer(np.arange(K), np.arange(K))
    iterations = 0
    for _ in range(max_iter):
        act = np.flatnonzero(~ok)
        if act.size == 0:
            break
        iterations += 1
        rx, rg, KKT = _kkt(hand, act, x_theta, w, tau, lam, theta, a, R, t, cO, B, b, hinge, stretch, dl, mass, comO,
                           g, mu, g_u, g_z, idx_max, k, L)
        done = (np.abs(rx).max(axis=1) < GRAD_TOL) & (np.abs(rg).max(axis=1) < ATTACH_TOL)
        ok[act[done]] = True
        act, rx, rg, KKT = act[~done], rx[~done], rg[~done], KKT[~done]
        if act.size == 0:
            break
        rhs = -np.concatenate([rx, rg], axis=1)
        try:
            step = np.linalg.solve(KKT, rhs[..., None])[..., 0]
        except np.linalg.LinAlgError:  # a singular KKT matrix: least squares, particle by particle
            step = np.stack([np.linalg.lstsq(M, y, rcond=None)[0] for M, y in zip(KKT, rhs, strict=True)])
        dx = step[:, :nx]
        big = np.abs(dx[:, : N * K]).max(axis=1)
        scale = np.where(big > MAX_STEP, MAX_STEP / np.maximum(big, 1e-300), 1.0)[:, None]
        x_theta[act] += (scale * dx[:, : N * K]).reshape(-1, N, K)
        w[act] += scale * dx[:, N * K:N * K + 3]
        tau[act] += scale * dx[:, N * K + 3:]
        lam[act] += scale * step[:, nx:]
    C = _cayley(w)
    ok &= np.all(np.isfinite(x_theta.reshape(P, -1)), axis=1) & np.all(np.isfinite(w), axis=1)
    s_new = stretch + dl - np.einsum("nk,pnk->pn", hand.moment_arms, x_theta - theta)
    return RollingMove(x_theta, C @ R, t + tau, ok, iterations, s_new, hand.kappa[None] * s_new)


def _kkt(hand, act, x_theta, w, tau, lam, theta, a, R, t, cO, B, b, hinge, stretch, dl, mass, comO, g, mu, g_u, g_z,
         idx_max, k, L):
    """Residuals (stationarity (A, nx), attachments (A, 3N)) and KKT matrices (A, nx + 3N,
    nx + 3N) of the particles ``act`` (module docstring)."""
    N, K = hand.N, hand.K
    nx, m = N * K + 6, 3 * N
    x_theta, w, tau, lam = x_theta[act], w[act], tau[act], lam[act]
    theta, a, R, t, cO, B, b = theta[act], a[act], R[act], t[act], cO[act], B[act], b[act]
    stretch, dl, mass, comO, k, mu, L = stretch[act], dl[act], mass[act], comO[act], k[act], mu[act], L[act]
    A = act.size
    p, J1, J2 = _kinematics(hand, x_theta, a, L)
    C, dC, d2C = _cayley_derivatives(w)
    dphi = (x_theta - theta).sum(axis=-1)  # (A, N)
    v = cO - np.einsum("pnij,pnj->pni", B, dphi[..., None] * hinge[None] - w[:, None])
    CR = C @ R
    gvec = p - np.einsum("pij,pnj->pni", CR, v) - (t + tau)[:, None]  # (A, N, 3)
    J = np.zeros((A, N, 3, nx))
    CRb = np.einsum("pij,pnj->pni", CR, b)
    for i in range(N):
        J[:, i, :, i * K:(i + 1) * K] = np.swapaxes(J1[:, i], 1, 2) - CRb[:, i, :, None]
    Rv = np.einsum("pij,pnj->pni", R, v)
    J[..., N * K:N * K + 3] = -np.einsum("paij,pnj->pnia", dC, Rv) - np.einsum("pij,pnjk->pnik", CR, B)
    J[..., N * K + 3:] = -np.eye(3)
    J = J.reshape(A, m, nx)
    s_new = stretch + dl - np.einsum("nk,pnk->pn", hand.moment_arms, x_theta - theta)
    grad = np.zeros((A, nx))
    H = np.zeros((A, nx, nx))
    phi = np.cumsum(x_theta, axis=-1)
    per = mu * (g_u[None, :, None] * np.cos(phi) - g_z[None, :, None] * np.sin(phi))
    link_torque = np.cumsum(per[..., ::-1], axis=-1)[..., ::-1]
    grad[:, : N * K] = (k * (x_theta - hand.rest_angles)
                        - hand.kappa[None, :, None] * s_new[..., None] * hand.moment_arms[None] - link_torque).reshape(A, -1)
    curv = mu * (g_u[None, :, None] * np.sin(phi) + g_z[None, :, None] * np.cos(phi))
    tailc = np.cumsum(curv[..., ::-1], axis=-1)[..., ::-1]  # sum over l >= j
    lam3 = lam.reshape(A, N, 3)
    Rb = np.einsum("pij,pnj->pni", R, b)
    for i in range(N):
        sl = slice(i * K, (i + 1) * K)
        H[:, sl, sl] = (k[:, i, :, None] * np.eye(K) + hand.kappa[i] * np.outer(hand.moment_arms[i], hand.moment_arms[i])
                        + tailc[:, i][:, idx_max] + np.einsum("pc,pjkc->pjk", lam3[:, i], J2[:, i]))
        cross = -np.einsum("pc,pacj,pj->pa", lam3[:, i], dC, Rb[:, i])  # theta_ik, w_a
        H[:, sl, N * K:N * K + 3] += cross[:, None, :]
        H[:, N * K:N * K + 3, sl] += cross[:, :, None]
    RcomO = np.einsum("pij,pj->pi", R, comO)
    grad[:, N * K:N * K + 3] = -mass[:, None] * np.einsum("i,paij,pj->pa", g, dC, RcomO)
    grad[:, N * K + 3:] = -mass[:, None] * g[None]
    RB = np.einsum("pij,pnjk->pnik", R, B)
    t1 = -np.einsum("pnc,pacj,pnjb->pab", lam3, dC, RB)
    H[:, N * K:N * K + 3, N * K:N * K + 3] += (-mass[:, None, None] * np.einsum("i,pabij,pj->pab", g, d2C, RcomO)
                                               - np.einsum("pnc,pabcj,pnj->pab", lam3, d2C, Rv) + t1
                                               + np.swapaxes(t1, 1, 2))
    rx = grad + np.einsum("pmx,pm->px", J, lam)
    KKT = np.zeros((A, nx + m, nx + m))
    KKT[:, :nx, :nx] = H
    KKT[:, :nx, nx:] = np.swapaxes(J, 1, 2)
    KKT[:, nx:, :nx] = J
    return rx, gvec.reshape(A, m), KKT
