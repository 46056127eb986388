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
each thread LANES of them side by side as SIMD loops, as Gamma's does: their KKT matrices,
N K + 3N + 6 square (21 on the Model O), by elimination without pivoting in the augmented
form H + rho J^T J (the same solution; H alone is singular in the object's translation and,
before the multipliers grow, in its turn about the vertical), by partial pivoting
(:func:`vlr_drake.motion._solve`) for the rare lane whose pivot vanishes all the same, by
least squares where that finds it singular. Each hypothesis' result is the same, bit for
bit, whatever batch or lane it is solved in. With ``FilterConfig.motion_model = "rolling"`` it is
the filter's Gamma. The tests hold it to the MathematicalProgram reference to 1e-8 rad.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from vlr_drake import motion, observation
from vlr_drake.hand import HandModel
from vlr_drake.kinematics import is_count

__all__ = ["NORMAL_GUESSES", "RollingMove", "circle_centres", "move_rolling", "guessed_normals", "hinge_axes"]

#: Newton's stopping tolerances: stationarity [N m, N] and attachments [m].
GRAD_TOL = 1e-10
ATTACH_TOL = 1e-12
#: Cap on one Newton step's largest joint change [rad].
MAX_STEP = 0.1
#: [e_a]x, a = 0, 1, 2: the Cayley derivatives' basis (:func:`_cayley_lanes`'s E).
SKEW_BASIS = np.array([[[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]],
                       [[0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [-1.0, 0.0, 0.0]],
                       [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]]])
#: E_a E_b + E_b E_a (3, 3, 3, 3): half the Cayley numerator's second derivatives.
SKEW_PRODUCTS = (np.einsum("aij,bjk->abik", SKEW_BASIS, SKEW_BASIS)
                 + np.einsum("bij,ajk->abik", SKEW_BASIS, SKEW_BASIS))


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
    if not np.all(np.isfinite(p)):  # (a NaN had been called a contact at the centroid, or failed in an SVD)
        raise ValueError("guessed_normals: 'p' contains NaN or infinite values")
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
    p = np.asarray(p, float)
    if p.ndim != 3 or p.shape[2] != 3 or not np.all(np.isfinite(p)):
        raise ValueError(f"circle_centres: 'p' must be finite contacts of shape (P, N, 3), got shape {p.shape}"
                         + ("" if np.all(np.isfinite(p)) else " with NaN or infinite values"))
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
    at the hypotheses' own angles and pose; ``ok`` is False where it has not converged
    within ``max_iter`` steps (each step's result checked), or met a value that is not
    finite (a hypothesis with NaN angles or pose fails alone). About 1% of hypotheses drawn
    0.02 rad and 2 mm around a grasp fail: most wander off by 10-40 deg, and some stall near
    the side fingers' redundant attachment
    (:func:`vlr_drake.rolling_reference.attachment_directions`), where the KKT matrix is
    nearly singular. ``newton_iterations`` counts each hypothesis' steps. The hand's and the
    object's parameters (pads, springs, links, mass, gravity, a pose's rotation) are
    checked, and a ValueError names the one that is not physical; a hypothesis whose normals
    are zero or not finite fails alone."""
    theta = np.asarray(theta, float)
    if theta.ndim != 3 or theta.shape[1:] != (hand.N, hand.K):
        raise ValueError(f"move_rolling: 'theta' must have shape (P, {hand.N}, {hand.K}), got {theta.shape}")
    P, N, K = theta.shape
    if not is_count(max_iter, 1):
        raise ValueError(f"move_rolling: 'max_iter' must be an integer >= 1, got {max_iter!r}")
    a, R, t = _broadcast("a", a, (P, N)), _broadcast("R", R, (P, 3, 3)), _broadcast("t", t, (P, 3))
    finite = np.isfinite(R).all(axis=(1, 2))  # a NaN pose fails its hypothesis in the kernel
    turned = observation.is_rotation(R[finite])
    if not turned.all():
        raise ValueError(f"move_rolling: 'R' must hold rotations (R^T R = I, det +1); hypothesis "
                         f"{int(np.flatnonzero(finite)[np.argmin(turned)])} is not one")
    nrm = _broadcast("normals", normals, (P, N, 3))
    size = np.linalg.norm(nrm, axis=-1, keepdims=True)
    bad = ~(np.isfinite(size) & (size > 0)).all(axis=(1, 2))  # no normal: that hypothesis fails alone,
    if bad.any():  # as one with NaN angles does (a NaN normal had divided into NaN silently)
        theta = theta.copy()
        theta[bad] = np.nan
        size = np.where(np.isfinite(size) & (size > 0), size, 1.0)
    nrm = nrm / size
    stretch = _broadcast("stretch", stretch, (P, N))
    dl = np.zeros((P, N)) if dl is None else _broadcast("dl", dl, (P, N))
    r = hand.pad_radius if pad_radius is None else _broadcast("pad_radius", pad_radius, (N,))
    g = np.zeros(3) if gravity is None else np.asarray(gravity, float)
    k = _broadcast("stiffness", hand.stiffness if stiffness is None else stiffness, (P, N, K))
    mass = np.zeros(P) if object_mass is None else _broadcast("object_mass", object_mass, (P,))
    for name, value, fine in (("pad_radius", r, "finite radii >= 0 [m]"), ("stiffness", k, "finite springs > 0 [N m/rad]"),
                              ("object_mass", mass, "finite masses >= 0 [kg]")):
        if not np.all(np.isfinite(value) & ((value > 0) if name == "stiffness" else (value >= 0))):
            raise ValueError(f"move_rolling: '{name}' must be {fine}, got values down to {np.nanmin(value)}")
    if g.shape != (3,) or not np.all(np.isfinite(g)):
        raise ValueError(f"move_rolling: 'gravity' must be a finite (3,) vector [m/s^2], got shape {g.shape}")
    if com is None and gravity is not None and np.any(mass != 0):  # else its weight would act at t
        raise ValueError("move_rolling: an object with mass needs its centre of mass 'com' (P, 3)")
    L = hand.link_lengths[None] if link_lengths is None else np.asarray(link_lengths, float)
    if L.ndim != 3 or L.shape[0] not in (1, P) or L.shape[1:] != (N, K - 1):
        raise ValueError(f"move_rolling: 'link_lengths' must have shape (1 or {P}, {N}, {K - 1}), got {L.shape}")
    if not np.all(np.isfinite(L) & (L > 0)):
        raise ValueError(f"move_rolling: 'link_lengths' must be finite lengths > 0 [m], got values down to "
                         f"{np.nanmin(L)}")
    L = np.broadcast_to(L, (P, N, K - 1))
    RT = np.swapaxes(R, 1, 2)
    p0, _, _ = _kinematics(hand, theta, a, L)
    cO = np.einsum("pij,pnj->pni", RT, p0 - t[:, None])  # centres in the object frame
    nO = np.einsum("pij,pnj->pni", RT, nrm)
    comO = np.zeros((P, 3)) if com is None else np.einsum("pij,pj->pi", RT, _broadcast("com", com, (P, 3)) - t)
    hinge = hinge_axes(hand)  # (N, 3)
    # v_i = cO_i + r_i (R^T (dphi_i h_i - w)) x nO_i = cO_i - r_i [nO_i]x R^T (dphi_i h_i - w)
    B = r[None, :, None, None] * np.einsum("pnij,pjk->pnik", _skew(nO), RT)  # dv_i/dw (P, N, 3, 3)
    b = -np.einsum("pnij,nj->pni", B, hinge)  # dv_i/dtheta_ik (P, N, 3), every k of finger i
    # a round object: v_i also moves by -(kap_i / 2) |P_t y_i|^2 nO_i, y_i = dphi_i h_i - w, with
    # kap_i = r_i^2 / (radius_i + r_i) and P_t the projection off the normal (a ball on a ball)
    kap = np.zeros((P, N))
    if curvature_radius is not None:
        rad = _broadcast("curvature_radius", curvature_radius, (P, N))
        if np.any(np.isnan(rad)) or not np.all(rad > 0):
            raise ValueError("move_rolling: 'curvature_radius' must be radii > 0 [m] (inf: a flat face)")
        kap = np.where(np.isfinite(rad), r[None] ** 2 / (rad + r[None]), 0.0)
    mu = np.broadcast_to(hand.link_moments(L) if gravity is not None else np.zeros((1, N, K)), (P, N, K))
    g_u, g_z = hand.gravity_in_finger_planes(g).T
    x_theta, w, tau = np.empty((P, N, K)), np.empty((P, 3)), np.empty((P, 3))
    ok, iters = np.zeros(P, bool), np.zeros(P, np.int64)

    def c(x):  # C-contiguous and writable: a read-only view would compile a second kernel
        return np.require(x, float, ["C", "W"])

    _newton_kernel(c(theta), c(a), c(R), c(t), c(cO), c(B), c(b), c(nO), c(kap), c(hinge), c(stretch), c(dl), c(mass),
                   c(comO), c(g),
                   c(mu), c(g_u), c(g_z), c(k), c(L), c(hand.pad), c(hand.base), c(hand.u), c(hand.moment_arms),
                   c(hand.rest_angles), c(hand.kappa), int(max_iter), MAX_STEP, GRAD_TOL, ATTACH_TOL,
                   x_theta, w, tau, ok, iters, motion._move_tasks(P))
    iterations = int(iters.max()) if P else 0
    C = _cayley(w)
    ok &= np.isfinite(x_theta).all(axis=(1, 2)) & np.isfinite(w).all(axis=1)
    s_new = stretch + dl - np.einsum("nk,pnk->pn", hand.moment_arms, x_theta - theta)
    return RollingMove(x_theta, C @ R, t + tau, ok, iterations, s_new, hand.kappa[None] * s_new, iters)



def _broadcast(name: str, value, shape: tuple) -> np.ndarray:
    """move_rolling's ``value`` broadcast to ``shape`` (a writable float copy), or a ValueError
    naming it (numpy's broadcast error had named no argument)."""
    x = np.asarray(value, float)
    try:
        return np.broadcast_to(x, shape).copy()
    except ValueError:
        raise ValueError(f"move_rolling: '{name}' must broadcast to shape {shape}, got {x.shape}") from None


def _skew(v):
    """(..., 3) -> (..., 3, 3) with _skew(v) y = v x y."""
    S = np.zeros(v.shape + (3,))
    S[..., 0, 1], S[..., 0, 2], S[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    S[..., 1, 0], S[..., 2, 0], S[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    return S


@njit(cache=True, error_model="numpy")
def _cayley_lanes(w, E, E2, C, dC, d2C, Wm, Nm, Na, D):  # pragma: no cover - numba
    """The Cayley rotation C = I + (4 W + 2 W^2) / (4 + |w|^2), W = [w]x (the same rotation
    as :func:`_cayley`), of every lane's ``w`` (3, W), into C (3, 3, W), dC[a] = dC/dw_a
    (3, 3, 3, W) and d2C[a, b] = d2C/dw_a dw_b (3, 3, 3, 3, W), analytically. E (3, 3, 3)
    holds [e_a]x and E2[a, b] (3, 3, 3, 3) the constant E_a E_b + E_b E_a; Wm, Nm (3, 3, W),
    Na (3, 3, 3, W) and D (W,) are scratch."""
    L = w.shape[1]
    for i in range(3):
        for j in range(3):
            for q in range(L):
                Wm[i, j, q] = w[0, q] * E[0, i, j] + w[1, q] * E[1, i, j] + w[2, q] * E[2, i, j]
    for q in range(L):
        D[q] = 4.0 + w[0, q] * w[0, q] + w[1, q] * w[1, q] + w[2, q] * w[2, q]
    for i in range(3):
        for j in range(3):
            for q in range(L):  # the numerator N(w) = 4 W + 2 W^2
                Nm[i, j, q] = 4.0 * Wm[i, j, q] + 2.0 * (Wm[i, 0, q] * Wm[0, j, q] + Wm[i, 1, q] * Wm[1, j, q]
                                                       + Wm[i, 2, q] * Wm[2, j, q])
                C[i, j, q] = (1.0 if i == j else 0.0) + Nm[i, j, q] / D[q]
    for a in range(3):
        for i in range(3):
            for j in range(3):
                for q in range(L):  # dN/dw_a = 4 E_a + 2 (E_a W + W E_a)
                    Na[a, i, j, q] = 4.0 * E[a, i, j] + 2.0 * (
                        E[a, i, 0] * Wm[0, j, q] + E[a, i, 1] * Wm[1, j, q] + E[a, i, 2] * Wm[2, j, q]
                        + Wm[i, 0, q] * E[a, 0, j] + Wm[i, 1, q] * E[a, 1, j] + Wm[i, 2, q] * E[a, 2, j])
                    dC[a, i, j, q] = Na[a, i, j, q] / D[q] - 2.0 * w[a, q] * Nm[i, j, q] / (D[q] * D[q])
    for a in range(3):
        for b in range(a, 3):
            for i in range(3):
                for j in range(3):
                    for q in range(L):  # d2N/dw_a dw_b = 2 (E_a E_b + E_b E_a)
                        D2 = D[q] * D[q]
                        v = (2.0 * E2[a, b, i, j] / D[q] - 2.0 * (w[b, q] * Na[a, i, j, q] + w[a, q] * Na[b, i, j, q]) / D2
                             + 8.0 * w[a, q] * w[b, q] * Nm[i, j, q] / (D2 * D[q]))
                        if a == b:
                            v -= 2.0 * Nm[i, j, q] / D2
                        d2C[a, b, i, j, q] = v
                        d2C[b, a, i, j, q] = v


#: Hypotheses solved side by side by one thread of the Newton kernel ("lanes", as Gamma's:
#: :data:`vlr_drake.motion.LANES`); every array of a solve has them on its last axis.
LANES = motion.LANES


@njit(cache=True)
def _load_lane(q, p, theta0, a, R, t, cO, B, b, nO, kap, stretch, dl, mass, comO, mu, kst, L, hinge,
               x, x0, al, Ll, Rl, tl, cOl, Bl, bl, nOl, kapl, strl, dll, massl, mul, kstl,
               RcomO, Rn, hn, Rb, RB, w, tau, lam):  # pragma: no cover - numba
    """Hypothesis ``p``'s numbers into lane ``q``, its Newton started at its own angles and
    pose (w = tau = 0) with zero multipliers; the products with its pose that stay fixed
    through the solve (R com_O, R n_O and its hinge component, R b, R B) computed once."""
    N, K = x.shape[0], x.shape[1]
    for i in range(N):
        al[i, q] = a[p, i]
        kapl[i, q] = kap[p, i]
        strl[i, q] = stretch[p, i]
        dll[i, q] = dl[p, i]
        for k in range(K - 1):
            Ll[i, k, q] = L[p, i, k]
        for k in range(K):
            x[i, k, q] = theta0[p, i, k]
            x0[i, k, q] = theta0[p, i, k]
            mul[i, k, q] = mu[p, i, k]
            kstl[i, k, q] = kst[p, i, k]
        for r in range(3):
            cOl[i, r, q] = cO[p, i, r]
            bl[i, r, q] = b[p, i, r]
            nOl[i, r, q] = nO[p, i, r]
            for c in range(3):
                Bl[i, r, c, q] = B[p, i, r, c]
    massl[q] = mass[p]
    for r in range(3):
        tl[r, q] = t[p, r]
        w[r, q] = 0.0
        tau[r, q] = 0.0
        RcomO[r, q] = R[p, r, 0] * comO[p, 0] + R[p, r, 1] * comO[p, 1] + R[p, r, 2] * comO[p, 2]
        for c in range(3):
            Rl[r, c, q] = R[p, r, c]
    for i in range(N):
        h = 0.0
        for j in range(3):
            Rn[i, j, q] = R[p, j, 0] * nO[p, i, 0] + R[p, j, 1] * nO[p, i, 1] + R[p, j, 2] * nO[p, i, 2]
            h += Rn[i, j, q] * hinge[i, j]
            Rb[i, j, q] = R[p, j, 0] * b[p, i, 0] + R[p, j, 1] * b[p, i, 1] + R[p, j, 2] * b[p, i, 2]
            for c in range(3):
                RB[i, j, c, q] = R[p, j, 0] * B[p, i, 0, c] + R[p, j, 1] * B[p, i, 1, c] + R[p, j, 2] * B[p, i, 2, c]
        hn[i, q] = h  # G = I - Rn Rn^T
    for r in range(lam.shape[0]):
        lam[r, q] = 0.0


@njit(cache=True, error_model="numpy")
def _newton_lanes(start, stop, stride, theta0, a, R, t, cO, B, b, nO, kap, hinge, stretch, dl, mass, comO, g, mu,
                  g_u, g_z, kst, L, pad, base, u, marm, rest, kappa, max_iter, max_step, grad_tol, attach_tol,
                  x_out, w_out, tau_out, ok, iters):  # pragma: no cover - numba
    """Newton on the rolling equilibrium's KKT system (module docstring) for hypotheses
    ``start:stop:stride``, LANES at a time: each lane runs its own hypothesis' iteration (its
    own step count, step cap and convergence test, those of a one-hypothesis Newton method),
    and a lane whose hypothesis is done takes the next one, so the lanes stay busy. The KKT
    systems are solved side by side without pivoting (:func:`vlr_drake.motion._lu_lanes`) in
    their augmented form (below), the unknowns ordered (theta, w, tau, lambda). A lane with
    a pivot that vanishes all the same (3% of hypotheses, once) is solved again with partial
    pivoting (:func:`vlr_drake.motion._solve`), by least squares where that finds it
    singular."""
    if start >= stop:
        return
    N, K = theta0.shape[1], theta0.shape[2]
    nK = N * K
    m = 3 * N
    OW, OT, OL = nK, nK + 3, nK + 6  # the KKT's blocks: theta, w, tau, lambda
    dim = OL + m
    W = LANES
    E = SKEW_BASIS.copy()
    E2 = SKEW_PRODUCTS.copy()
    # the lanes' hypotheses
    x, x0 = np.empty((N, K, W)), np.empty((N, K, W))
    al, Ll = np.empty((N, W)), np.ones((N, max(K - 1, 1), W))
    Rl, tl = np.empty((3, 3, W)), np.empty((3, W))
    cOl, Bl, bl, nOl = np.empty((N, 3, W)), np.empty((N, 3, 3, W)), np.empty((N, 3, W)), np.empty((N, 3, W))
    kapl, strl, dll, massl = np.empty((N, W)), np.empty((N, W)), np.empty((N, W)), np.empty(W)
    mul, kstl = np.empty((N, K, W)), np.empty((N, K, W))
    RcomO, Rn, hn = np.empty((3, W)), np.empty((N, 3, W)), np.empty((N, W))
    Rb, RB = np.empty((N, 3, W)), np.empty((N, 3, 3, W))
    w, tau, lam = np.empty((3, W)), np.empty((3, W)), np.empty((m, W))
    # scratch
    Pc, Jc, Hc = np.empty((N, 3, W)), np.empty((N, 3, K, W)), np.empty((N, 3, K, K, W))
    C, dC, d2C = np.empty((3, 3, W)), np.empty((3, 3, 3, W)), np.empty((3, 3, 3, 3, W))
    Wm, Nm, Na, Dc = np.empty((3, 3, W)), np.empty((3, 3, W)), np.empty((3, 3, 3, W)), np.empty(W)
    CR = np.empty((3, 3, W))
    v, Rv, CRb, CRn = np.empty((N, 3, W)), np.empty((N, 3, W)), np.empty((N, 3, W)), np.empty((N, 3, W))
    yv, Gy, dCRn = np.empty((N, 3, W)), np.empty((N, 3, W)), np.empty((3, N, 3, W))
    dphi, Gyh, lCRn, yGy, ny = np.empty((N, W)), np.empty((N, W)), np.empty((N, W)), np.empty(W), np.empty(W)
    Jth, Jw, gv = np.empty((N, 3, K, W)), np.empty((m, 3, W)), np.empty((m, W))  # the attachments' Jacobian
    per, curv, phi, snew = np.empty((N, K, W)), np.empty((N, K, W)), np.empty((K, W)), np.empty(W)
    A, F = np.empty((dim, dim, W)), np.empty((dim, W))  # KKT matrix and right-hand side
    A2, F2 = np.empty((dim, dim, W)), np.empty((dim, W))  # their copies for a pivoted re-solve
    A1, F1, A0 = np.empty((dim, dim)), np.empty(dim), np.empty((dim, dim))
    gmax, rmax, hscale, gscale, rho = np.empty(W), np.empty(W), np.empty(W), np.empty(W), np.empty(W)
    cols, vals = np.empty(K + 4, np.int64), np.empty((K + 4, W))  # one attachment row's nonzeros
    tiny1, tiny2 = np.empty(W), np.empty(W)
    finite, bad, stepping = np.empty(W, np.bool_), np.zeros(W, np.bool_), np.zeros(W, np.bool_)
    done = np.zeros(W, np.int64)  # 0 running, 1 converged, 2 failed
    pid, itn = np.full(W, -1, np.int64), np.zeros(W, np.int64)
    nxt = start
    for q in range(W):  # every lane computes on valid numbers, the first hypothesis' where it has none
        p = nxt if nxt < stop else start
        if nxt < stop:
            pid[q] = nxt
            nxt += stride
        _load_lane(q, p, theta0, a, R, t, cO, B, b, nO, kap, stretch, dl, mass, comO, mu, kst, L, hinge,
                   x, x0, al, Ll, Rl, tl, cOl, Bl, bl, nOl, kapl, strl, dll, massl, mul, kstl,
                   RcomO, Rn, hn, Rb, RB, w, tau, lam)
    while motion._lanes_busy(pid):
        motion._fk_all(x, Ll, al, pad, base, u, Pc, Jc, Hc)
        _cayley_lanes(w, E, E2, C, dC, d2C, Wm, Nm, Na, Dc)
        for r in range(3):
            for c in range(3):
                for q in range(W):
                    CR[r, c, q] = C[r, 0, q] * Rl[0, c, q] + C[r, 1, q] * Rl[1, c, q] + C[r, 2, q] * Rl[2, c, q]
        # the rolled attachment points v_i (object frame) and the roll's terms
        for i in range(N):
            for q in range(W):
                s = 0.0
                for k in range(K):
                    s += x[i, k, q] - x0[i, k, q]
                dphi[i, q] = s
                ny[q] = 0.0
            for c in range(3):
                for q in range(W):
                    yv[i, c, q] = dphi[i, q] * hinge[i, c] - w[c, q]
                    ny[q] += Rn[i, c, q] * yv[i, c, q]
            for q in range(W):
                yGy[q] = 0.0
                Gyh[i, q] = 0.0
            for c in range(3):
                for q in range(W):
                    Gy[i, c, q] = yv[i, c, q] - ny[q] * Rn[i, c, q]
                    yGy[q] += yv[i, c, q] * Gy[i, c, q]
                    Gyh[i, q] += Gy[i, c, q] * hinge[i, c]
            for r in range(3):
                for q in range(W):
                    v[i, r, q] = (cOl[i, r, q] - 0.5 * kapl[i, q] * yGy[q] * nOl[i, r, q]
                                  - Bl[i, r, 0, q] * yv[i, 0, q] - Bl[i, r, 1, q] * yv[i, 1, q]
                                  - Bl[i, r, 2, q] * yv[i, 2, q])
        for i in range(N):
            for r in range(3):
                for q in range(W):
                    Rv[i, r, q] = Rl[r, 0, q] * v[i, 0, q] + Rl[r, 1, q] * v[i, 1, q] + Rl[r, 2, q] * v[i, 2, q]
                    CRn[i, r, q] = CR[r, 0, q] * nOl[i, 0, q] + CR[r, 1, q] * nOl[i, 1, q] + CR[r, 2, q] * nOl[i, 2, q]
                    CRb[i, r, q] = CR[r, 0, q] * bl[i, 0, q] + CR[r, 1, q] * bl[i, 1, q] + CR[r, 2, q] * bl[i, 2, q]
                    for aa in range(3):
                        dCRn[aa, i, r, q] = (dC[aa, r, 0, q] * Rn[i, 0, q] + dC[aa, r, 1, q] * Rn[i, 1, q]
                                             + dC[aa, r, 2, q] * Rn[i, 2, q])
        # the attachments g_i = p_i - C R v_i - (t + tau) and their Jacobian (theta, w; tau's is -I)
        for q in range(W):
            gmax[q] = 0.0
            finite[q] = True
        for i in range(N):
            for r in range(3):
                row = 3 * i + r
                for q in range(W):
                    s = (Pc[i, r, q] - tl[r, q] - tau[r, q] - CR[r, 0, q] * v[i, 0, q] - CR[r, 1, q] * v[i, 1, q]
                         - CR[r, 2, q] * v[i, 2, q])
                    gv[row, q] = s
                    gmax[q] = max(gmax[q], abs(s))
                    finite[q] = finite[q] and np.isfinite(s)
                for k in range(K):
                    for q in range(W):
                        Jth[i, r, k, q] = Jc[i, r, k, q] - CRb[i, r, q] + kapl[i, q] * Gyh[i, q] * CRn[i, r, q]
                for aa in range(3):
                    for q in range(W):
                        s = 0.0
                        for c in range(3):
                            s += dC[aa, r, c, q] * Rv[i, c, q] + CR[r, c, q] * Bl[i, c, aa, q]
                        Jw[row, aa, q] = -s - kapl[i, q] * Gy[i, aa, q] * CRn[i, r, q]
        for i in range(N):
            for q in range(W):
                lCRn[i, q] = lam[3 * i, q] * CRn[i, 0, q] + lam[3 * i + 1, q] * CRn[i, 1, q] + lam[3 * i + 2, q] * CRn[i, 2, q]
        # stationarity: grad E + J^T lambda, into F in the KKT's order (negated below)
        for i in range(N):
            for q in range(W):
                snew[q] = strl[i, q] + dll[i, q]
            for k in range(K):
                for q in range(W):
                    snew[q] -= marm[i, k] * (x[i, k, q] - x0[i, k, q])
                    phi[k, q] = x[i, k, q] + (phi[k - 1, q] if k > 0 else 0.0)
            for k in range(K):
                for q in range(W):
                    cs, sn = np.cos(phi[k, q]), np.sin(phi[k, q])
                    per[i, k, q] = mul[i, k, q] * (g_u[i] * cs - g_z[i] * sn)
                    curv[i, k, q] = mul[i, k, q] * (g_u[i] * sn + g_z[i] * cs)
            for k in range(K - 2, -1, -1):  # suffix sums over l >= k
                for q in range(W):
                    per[i, k, q] += per[i, k + 1, q]
                    curv[i, k, q] += curv[i, k + 1, q]
            for k in range(K):
                for q in range(W):
                    F[i * K + k, q] = (kstl[i, k, q] * (x[i, k, q] - rest[i, k]) - kappa[i] * snew[q] * marm[i, k]
                                       - per[i, k, q] + Jth[i, 0, k, q] * lam[3 * i, q]
                                       + Jth[i, 1, k, q] * lam[3 * i + 1, q] + Jth[i, 2, k, q] * lam[3 * i + 2, q])
        for aa in range(3):
            for q in range(W):
                s = 0.0
                for i in range(3):
                    for j in range(3):
                        s += g[i] * dC[aa, i, j, q] * RcomO[j, q]
                s = -massl[q] * s
                st = -massl[q] * g[aa]
                for row in range(m):
                    s += Jw[row, aa, q] * lam[row, q]
                for i in range(N):
                    st -= lam[3 * i + aa, q]
                F[OW + aa, q] = s
                F[OT + aa, q] = st
        for q in range(W):
            rmax[q] = 0.0
        for c in range(OL):
            for q in range(W):
                rmax[q] = max(rmax[q], abs(F[c, q]))
                finite[q] = finite[q] and np.isfinite(F[c, q])
        # each lane's decision, as in a one-hypothesis Newton method
        any_step = False
        for q in range(W):
            stepping[q] = False
            if pid[q] < 0:
                continue
            if not finite[q]:  # a NaN or an overflow: failed
                done[q] = 2
            elif rmax[q] < grad_tol and gmax[q] < attach_tol:
                done[q] = 1
            elif itn[q] >= max_iter:  # max_iter steps taken, the last one checked: failed
                done[q] = 2
            else:
                stepping[q] = True
                itn[q] += 1
                any_step = True
        if any_step:
            # the KKT matrix (both triangles; the lanes' elimination reads the upper one)
            for c1 in range(dim):
                for c2 in range(dim):
                    for q in range(W):
                        A[c1, c2, q] = 0.0
            for i in range(N):
                for k in range(K):
                    qk = i * K + k
                    for k2 in range(K):
                        for q in range(W):
                            hv = (kappa[i] * marm[i, k] * marm[i, k2] + curv[i, max(k, k2), q]
                                  + kapl[i, q] * lCRn[i, q] * (1.0 - hn[i, q] * hn[i, q])
                                  + lam[3 * i, q] * Hc[i, 0, k, k2, q] + lam[3 * i + 1, q] * Hc[i, 1, k, k2, q]
                                  + lam[3 * i + 2, q] * Hc[i, 2, k, k2, q])
                            A[qk, i * K + k2, q] = hv
                    for q in range(W):
                        A[qk, qk, q] += kstl[i, k, q]
                for aa in range(3):  # theta_ik with w_a, the same for every k of finger i
                    for q in range(W):
                        s = 0.0
                        for c in range(3):
                            s -= lam[3 * i + c, q] * (dC[aa, c, 0, q] * Rb[i, 0, q] + dC[aa, c, 1, q] * Rb[i, 1, q]
                                                      + dC[aa, c, 2, q] * Rb[i, 2, q])
                        # a round object's roll: kap ((Gy.h) lam.dC_a R n - (lam.CRn) (G h)_a)
                        ldn = (lam[3 * i, q] * dCRn[aa, i, 0, q] + lam[3 * i + 1, q] * dCRn[aa, i, 1, q]
                               + lam[3 * i + 2, q] * dCRn[aa, i, 2, q])
                        s += kapl[i, q] * (Gyh[i, q] * ldn - lCRn[i, q] * (hinge[i, aa] - hn[i, q] * Rn[i, aa, q]))
                        for k in range(K):
                            A[i * K + k, OW + aa, q] = s
                            A[OW + aa, i * K + k, q] = s
            # the object's turn: its weight, the attachments' curvature and their cross terms
            for aa in range(3):
                for bb in range(aa, 3):
                    for q in range(W):
                        hv = 0.0
                        for i in range(3):
                            for j in range(3):
                                hv -= massl[q] * g[i] * d2C[aa, bb, i, j, q] * RcomO[j, q]
                        for n in range(N):
                            for c in range(3):
                                for j in range(3):
                                    hv -= lam[3 * n + c, q] * (d2C[aa, bb, c, j, q] * Rv[n, j, q]
                                                               + dC[aa, c, j, q] * RB[n, j, bb, q]
                                                               + dC[bb, c, j, q] * RB[n, j, aa, q])
                        for n in range(N):
                            la = (lam[3 * n, q] * dCRn[aa, n, 0, q] + lam[3 * n + 1, q] * dCRn[aa, n, 1, q]
                                  + lam[3 * n + 2, q] * dCRn[aa, n, 2, q])
                            lb = (lam[3 * n, q] * dCRn[bb, n, 0, q] + lam[3 * n + 1, q] * dCRn[bb, n, 1, q]
                                  + lam[3 * n + 2, q] * dCRn[bb, n, 2, q])
                            G_ab = (1.0 if aa == bb else 0.0) - Rn[n, aa, q] * Rn[n, bb, q]
                            hv += kapl[n, q] * (lCRn[n, q] * G_ab - la * Gy[n, bb, q] - lb * Gy[n, aa, q])
                        A[OW + aa, OW + bb, q] = hv
                        A[OW + bb, OW + aa, q] = hv
            for i in range(N):  # the attachments' rows and columns
                for r in range(3):
                    row = OL + 3 * i + r
                    for k in range(K):
                        for q in range(W):
                            A[i * K + k, row, q] = Jth[i, r, k, q]
                            A[row, i * K + k, q] = Jth[i, r, k, q]
                    for aa in range(3):
                        for q in range(W):
                            A[OW + aa, row, q] = Jw[3 * i + r, aa, q]
                            A[row, OW + aa, q] = Jw[3 * i + r, aa, q]
                    for q in range(W):
                        A[OT + r, row, q] = -1.0
                        A[row, OT + r, q] = -1.0
            for i in range(N):
                for r in range(3):
                    for q in range(W):
                        F[OL + 3 * i + r, q] = gv[3 * i + r, q]
            for c in range(dim):
                for q in range(W):
                    F[c, q] = -F[c, q]
            # The Hessian alone is singular (tau has none; w's is the weight's, zero about
            # the vertical before the multipliers grow), so the system is solved in its
            # augmented form: rho J^T times the attachments' rows added to the stationarity
            # rows, (H + rho J^T J) dx + J^T dlambda = -r - rho J^T g, the same solution,
            # whose (theta, w, tau) block is regular where the grasp's reduced Hessian is.
            # rho = |H| / |J|^2 puts the two on one scale (|J| over theta's and w's
            # columns, in metres; tau's entries are 1).
            for q in range(W):
                hscale[q] = 0.0
                gscale[q] = 0.0
            for c in range(nK):
                for q in range(W):
                    hscale[q] = max(hscale[q], abs(A[c, c, q]))
            for c in range(OT):
                for r in range(OL, dim):
                    for q in range(W):
                        gscale[q] = max(gscale[q], abs(A[c, r, q]))
            for q in range(W):
                rho[q] = hscale[q] / max(gscale[q] * gscale[q], 1e-300)
            for i in range(N):
                for r in range(3):
                    row = OL + 3 * i + r
                    for k in range(K):
                        cols[k] = i * K + k
                    for aa in range(3):
                        cols[K + aa] = OW + aa
                    cols[K + 3] = OT + r
                    for e in range(K + 4):
                        for q in range(W):
                            vals[e, q] = A[row, cols[e], q]
                    for e1 in range(K + 4):
                        c1 = cols[e1]
                        for q in range(W):
                            F[c1, q] += rho[q] * vals[e1, q] * F[row, q]
                        for e2 in range(K + 4):
                            c2 = cols[e2]
                            for q in range(W):
                                A[c1, c2, q] += rho[q] * vals[e1, q] * vals[e2, q]
            # the pivots' scales: |H| for theta's, w's and tau's columns, |J|^2 / |H| (a
            # Schur complement) for lambda's
            for q in range(W):
                hscale[q] = 0.0
                gscale[q] = max(gscale[q], 1.0)
            for c in range(OL):
                for q in range(W):
                    hscale[q] = max(hscale[q], abs(A[c, c, q]))
            for q in range(W):
                bad[q] = False
                tiny1[q] = 1e-9 * hscale[q]
                tiny2[q] = 1e-9 * gscale[q] * gscale[q] / hscale[q]
            A2[:, :, :] = A
            F2[:, :] = F
            motion._lu_lanes(A, F, OL, tiny1, tiny2, bad)
            for q in range(W):
                if not stepping[q]:
                    continue
                if bad[q]:  # a vanishing pivot: this lane again, with partial pivoting
                    for c1 in range(dim):
                        F1[c1] = F2[c1, q]
                        for c2 in range(dim):
                            A1[c1, c2] = A2[c1, c2, q]
                    A0[:, :] = A1
                    if not motion._solve(A1, F1):  # singular: the least-squares step
                        for c1 in range(dim):
                            F1[c1] = F2[c1, q]
                        F1[:] = np.linalg.lstsq(A0, F1)[0]
                    for c1 in range(dim):
                        F[c1, q] = F1[c1]
                big = 0.0
                for c1 in range(nK):
                    big = max(big, abs(F[c1, q]))
                sc = max_step / big if big > max_step else 1.0
                for i in range(N):
                    for k in range(K):
                        x[i, k, q] += sc * F[i * K + k, q]
                for c in range(3):
                    w[c, q] += sc * F[OW + c, q]
                    tau[c, q] += sc * F[OT + c, q]
                for row in range(m):
                    lam[row, q] += sc * F[OL + row, q]
        # the lanes that are done write their hypothesis out and take the next one
        for q in range(W):
            if pid[q] < 0 or done[q] == 0:
                continue
            p = pid[q]
            ok[p] = done[q] == 1
            iters[p] = itn[q]
            for i in range(N):
                for k in range(K):
                    x_out[p, i, k] = x[i, k, q]
            for c in range(3):
                w_out[p, c] = w[c, q]
                tau_out[p, c] = tau[c, q]
            done[q] = 0
            itn[q] = 0
            if nxt < stop:
                pid[q] = nxt
                _load_lane(q, nxt, theta0, a, R, t, cO, B, b, nO, kap, stretch, dl, mass, comO, mu, kst, L, hinge,
                           x, x0, al, Ll, Rl, tl, cOl, Bl, bl, nOl, kapl, strl, dll, massl, mul, kstl,
                           RcomO, Rn, hn, Rb, RB, w, tau, lam)
                nxt += stride
            else:
                pid[q] = -1


@njit(cache=True, parallel=True)
def _newton_kernel(theta0, a, R, t, cO, B, b, nO, kap, hinge, stretch, dl, mass, comO, g, mu, g_u, g_z, kst, L, pad,
                   base, u, marm, rest, kappa, max_iter, max_step, grad_tol, attach_tol,
                   x_out, w_out, tau_out, ok, iters, tasks):  # pragma: no cover - numba
    """Every hypothesis' Newton (:func:`_newton_lanes`) in ``tasks`` parallel tasks, task k
    taking hypotheses k, k + tasks, k + 2 tasks, ... (:func:`vlr_drake.motion._move_tasks`)."""
    P = theta0.shape[0]
    for k in prange(tasks):
        _newton_lanes(np.int64(k), P, tasks, theta0, a, R, t, cO, B, b, nO, kap, hinge, stretch, dl, mass, comO, g,
                      mu, g_u, g_z, kst, L, pad, base, u, marm, rest, kappa, max_iter, max_step, grad_tol,
                      attach_tol, x_out, w_out, tau_out, ok, iters)
