"""The motion function Gamma (Eq. 4, 9), batched over particles (DESIGN.md section 4).

A grasp holds the contacts at fixed mutual distances (Eq. 8). With ``G = dg/dtheta`` and
the squared-distance constraints ``g_c(theta) = 0.5 (|p_i - p_j|^2 - D_c^2)`` over the
hand's :attr:`~vlr_drake.hand.HandModel.constraint_pairs`, one tendon action ``dl`` moves
the joint angles to

elastic tendon (default; tendon + motor loop as a series spring kappa):
    theta' = argmin U(theta') + sum_i 0.5 kappa_i s_i'^2   s.t.  g(theta') = 0      (Eq. 9)
    s_i'   = s_i + dl_i - R_i (theta' - theta)           (tendon stretch, T = kappa s)

ideal tendon (Eq. 7 as an equality):
    theta' = argmin U(theta')   s.t.  g(theta') = 0,  R (theta' - theta) = dl         (Eq. 9)

with the spring energy ``U = sum 0.5 k (theta - theta0)^2`` (Eq. 6). Both are solved by
Newton's method on their KKT conditions

    elastic:  k (theta - theta0) - R^T kappa s' + G^T lambda = 0,   g = 0
    ideal:    k (theta - theta0) + G^T lambda + R^T mu = 0,  g = 0,  R (theta' - theta) = dl

from the current angles, with analytic first and second derivatives
(:mod:`vlr_drake.kinematics`), a capped step and a per-particle success flag. The implied
tendon tension is ``T = kappa s'`` (elastic) or ``T = -mu`` (ideal); a negative one means
the hypothesis would need a pushing tendon, which :class:`MoveResult` flags.

The per-particle kernel is compiled with numba and runs in parallel over particles; the
reference solver for one configuration is :mod:`vlr_drake.motion_reference`
(Drake MathematicalProgram with IPOPT or SNOPT), and the tests hold the two to 1e-6 rad.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from vlr_drake.hand import HandModel
from vlr_drake.kinematics import as_particles, contacts, finger_contact_derivatives

__all__ = [
    "TENDON_MODELS",
    "TOLERANCES",
    "MoveResult",
    "Equilibrium",
    "TendonLimitError",
    "move",
    "equilibrium",
    "check_action",
    "contact_distances_sq",
]

TENDON_MODELS = ("elastic", "ideal")

#: Convergence tolerances of the Newton solver (SI units: N m, m^2, m), per caller.
#: "tight" (default) solves to round-off, for the controller's finite-difference Jacobians
#: (eps 0.2 mm). "filter" solves to ~1e-8 rad, far below what the camera resolves, and saves a
#: Newton step on about half the particles (``FilterConfig.newton_tolerance`` says what it
#: did to the physics handwriting).
TOLERANCES = {"tight": (1e-12, 1e-15, 1e-13), "filter": (1e-9, 1e-12, 1e-11)}
TOL_TORQUE, TOL_CONSTRAINT, TOL_TENDON = TOLERANCES["tight"]
#: Tolerances accepted when the iteration budget runs out (angles within ~1e-5 rad).
#: The contact distances are accepted as a distance error |g| / D [m] (5 nm): near the
#: Model O's mirror-image grasps the regularised Newton iteration stalls at ~2 nm for the
#: 54 mm side pair, a floor set by the multiplier ridge, not by the physics.
LOOSE_TORQUE = 1e-7
LOOSE_DISTANCE = 5e-9
LOOSE_TENDON = 1e-10
#: Largest joint-angle change of one Newton step [rad].
MAX_STEP = 0.15
MAX_ITER = 30


class TendonLimitError(ValueError):
    """An action would take a tendon outside its range."""


@dataclass
class MoveResult:
    """Result of a batched move. Particles that failed keep their input angles.

    Attributes:
        theta: (P, N, K) joint angles after the action.
        stretch: (P, N) tendon stretch s' (elastic model; ``tension / kappa`` for ideal).
        tension: (P, N) implied tendon tension T [N].
        multipliers: (P, m) contact-constraint multipliers lambda (negative: the fingers
            squeeze the object along that contact pair).
        ok: (P,) True where Newton converged.
        iterations: (P,) Newton iterations used.
        residuals: (P, 3) final max residuals: stationarity [N m], constraints [m^2],
            tendon equations [m] (ideal model).
    """

    theta: np.ndarray
    stretch: np.ndarray
    tension: np.ndarray
    multipliers: np.ndarray
    ok: np.ndarray
    iterations: np.ndarray
    residuals: np.ndarray

    def tension_feasible(self, tol: float = 0.0) -> np.ndarray:
        """(P,) True where every implied tendon tension is >= -tol (tendons only pull)."""
        return np.all(self.tension >= -tol, axis=1)


@dataclass
class Equilibrium:
    """Tendon state that holds given angles in equilibrium (see :func:`equilibrium`)."""

    theta: np.ndarray  # (P, N, K) equilibrium angles (equal to the input for the Model O)
    stretch: np.ndarray  # (P, N)
    tension: np.ndarray  # (P, N)
    multipliers: np.ndarray  # (P, m)
    ok: np.ndarray  # (P,)


# --------------------------------------------------------------------------------------
# numba kernels
# --------------------------------------------------------------------------------------


@njit(cache=True)
def _solve(A, b):  # pragma: no cover - numba
    """Solve A x = b in place (Gaussian elimination, partial pivoting). False if singular."""
    n = A.shape[0]
    scale = 0.0
    for i in range(n):
        for j in range(n):
            v = abs(A[i, j])
            if v > scale:
                scale = v
    if scale == 0.0 or not np.isfinite(scale):
        return False
    for c in range(n):
        piv = c
        best = abs(A[c, c])
        for r in range(c + 1, n):
            v = abs(A[r, c])
            if v > best:
                best = v
                piv = r
        if best <= 1e-300 or best < 1e-17 * scale:
            return False
        if piv != c:
            for j in range(c, n):
                t = A[c, j]
                A[c, j] = A[piv, j]
                A[piv, j] = t
            t = b[c]
            b[c] = b[piv]
            b[piv] = t
        inv = 1.0 / A[c, c]
        for r in range(c + 1, n):
            f = A[r, c] * inv
            if f != 0.0:
                for j in range(c + 1, n):
                    A[r, j] -= f * A[c, j]
                b[r] -= f * b[c]
    for r in range(n - 1, -1, -1):
        s = b[r]
        for j in range(r + 1, n):
            s -= A[r, j] * b[j]
        b[r] = s / A[r, r]
    return True


@njit(cache=True)
def _fk_all(theta, L, a, pad, base, u, Pc, Jc, Hc):  # pragma: no cover - numba
    N = theta.shape[0]
    for i in range(N):
        finger_contact_derivatives(theta[i], L[i], a[i], pad[i], base[i], u[i], Pc[i], Jc[i], Hc[i])


@njit(cache=True)
def _constraint_jacobian(Pc, Jc, pairs, D2, g, G):  # pragma: no cover - numba
    """g_c = 0.5 (|p_i - p_j|^2 - D2_c) and its gradient rows G (m, N*K)."""
    m = pairs.shape[0]
    K = Jc.shape[2]
    G[:, :] = 0.0
    for c in range(m):
        i = pairs[c, 0]
        j = pairs[c, 1]
        dsq = 0.0
        for r in range(3):
            dp = Pc[i, r] - Pc[j, r]
            dsq += dp * dp
            for k in range(K):
                G[c, i * K + k] += dp * Jc[i, r, k]
                G[c, j * K + k] -= dp * Jc[j, r, k]
        g[c] = 0.5 * (dsq - D2[c])


@njit(cache=True)
def _ridge_solve(A, f0, M, rhs):  # pragma: no cover - numba
    """Least squares min |A x + f0| (A: equations x unknowns) by the normal equations, with a
    1e-12-relative ridge that picks the minimum-norm x where A loses rank (multipliers that
    are statically indeterminate). The solution is left in ``rhs``; False if singular.
    Written as loops: numba's ``@`` on these small arrays costs more than the arithmetic."""
    n_eq, nb = A.shape
    scale = 0.0
    for c1 in range(nb):
        v = 0.0
        for q in range(n_eq):
            v += A[q, c1] * f0[q]
        rhs[c1] = -v
        for c2 in range(nb):
            v = 0.0
            for q in range(n_eq):
                v += A[q, c1] * A[q, c2]
            M[c1, c2] = v
        scale = max(scale, M[c1, c1])
    for c in range(nb):
        M[c, c] += 1e-12 * scale
    return _solve(M, rhs)


@njit(cache=True)
def _newton_one(
    theta0, s0, dl, a, L, kst, D2, pad, base, u, rarm, rest, kappa, pairs,
    ideal, max_iter, max_step, tol, theta, lam, T, s_out, resid, work,
):  # pragma: no cover - numba
    """Newton on the KKT system of one particle; returns (ok, iterations).

    ``tol`` (3,): convergence tolerances on the torque, constraint and tendon residuals
    (:data:`TOLERANCES`).

    ``resid`` (3,) receives the final max residuals (torque, constraint, tendon);
    ``work`` holds the scratch arrays (see :func:`_make_work`), reused across particles."""
    N, K = theta0.shape
    n = N * K
    m = pairs.shape[0]
    nc = N if ideal else 0
    dim = n + m + nc
    Pc, Jc, Hc, g, G, Afull, Ffull, mu, sp, Bfull, f0, BBtfull, rhsfull = work
    A = Afull[:dim, :dim]
    F = Ffull[:dim]
    mu[:] = 0.0
    for i in range(N):
        for k in range(K):
            theta[i, k] = theta0[i, k]

    # Initial multipliers: least squares of the stationarity rows at theta0.
    _fk_all(theta, L, a, pad, base, u, Pc, Jc, Hc)
    _constraint_jacobian(Pc, Jc, pairs, D2, g, G)
    nb = m + nc
    B = Bfull[:, :nb]
    B[:, :] = 0.0
    BBt = BBtfull[:nb, :nb]
    rhs = rhsfull[:nb]
    for i in range(N):
        for k in range(K):
            f0[i * K + k] = kst[i, k] * (theta[i, k] - rest[i, k])
            if not ideal:
                f0[i * K + k] -= rarm[i, k] * kappa[i] * (s0[i] + dl[i])
    for c in range(m):
        for q in range(n):
            B[q, c] = G[c, q]
    if ideal:
        for i in range(N):
            for k in range(K):
                B[i * K + k, m + i] = rarm[i, k]
    if _ridge_solve(B, f0, BBt, rhs):
        for c in range(m):
            lam[c] = rhs[c]
        for i in range(nc):
            mu[i] = rhs[m + i]
    else:
        lam[:] = 0.0

    ok = False
    it = 0
    for it in range(max_iter + 1):
        if it > 0:
            _fk_all(theta, L, a, pad, base, u, Pc, Jc, Hc)
            _constraint_jacobian(Pc, Jc, pairs, D2, g, G)
        # residual
        for i in range(N):
            sp[i] = s0[i] + dl[i]
            for k in range(K):
                sp[i] -= rarm[i, k] * (theta[i, k] - theta0[i, k])
        res_f = 0.0
        for i in range(N):
            for k in range(K):
                q = i * K + k
                v = kst[i, k] * (theta[i, k] - rest[i, k])
                if ideal:
                    v += rarm[i, k] * mu[i]
                else:
                    v -= rarm[i, k] * kappa[i] * sp[i]
                for c in range(m):
                    v += G[c, q] * lam[c]
                F[q] = v
                if abs(v) > res_f:
                    res_f = abs(v)
        res_g = 0.0
        res_d = 0.0  # the same residual as a distance error [m]: |g| / D, g = (d^2 - D^2) / 2
        for c in range(m):
            F[n + c] = g[c]
            if abs(g[c]) > res_g:
                res_g = abs(g[c])
            dd = abs(g[c]) / np.sqrt(D2[c])
            if dd > res_d:
                res_d = dd
        res_t = 0.0
        if ideal:
            for i in range(N):
                v = -dl[i]
                for k in range(K):
                    v += rarm[i, k] * (theta[i, k] - theta0[i, k])
                F[n + m + i] = v
                if abs(v) > res_t:
                    res_t = abs(v)
        if not (np.isfinite(res_f) and np.isfinite(res_g) and np.isfinite(res_t)):
            break
        if res_f < tol[0] and res_g < tol[1] and res_t < tol[2]:
            ok = True
            break
        if it == max_iter:
            # Out of iterations: accept the solution at physical tolerances (convergence is
            # only linear near the Model O's symmetric grasps, where one constraint is second
            # order in the motion), else fail.
            ok = res_f < LOOSE_TORQUE and res_d < LOOSE_DISTANCE and res_t < LOOSE_TENDON
            break
        if it >= 7 and res_f > 1e-3:
            # Not converging at all after 7 steps: an action with no nearby equilibrium (the
            # grasp's fold). Measured (bench motion, 60,000 grasps, +-1.5 mm): 19% of particles
            # end here; stopping at 7 rather than 12 steps took the move from 0.42 to 0.36 s
            # and lost 0.05% of the successes (slow ones, which max_substeps retries).
            break
        # KKT matrix
        A[:, :] = 0.0
        for i in range(N):
            for k in range(K):
                q = i * K + k
                A[q, q] += kst[i, k]
                if not ideal:
                    for k2 in range(K):
                        A[q, i * K + k2] += kappa[i] * rarm[i, k] * rarm[i, k2]
        for c in range(m):
            i = pairs[c, 0]
            j = pairs[c, 1]
            lc = lam[c]
            for k in range(K):
                for k2 in range(K):
                    hii = 0.0
                    hjj = 0.0
                    hij = 0.0
                    for r in range(3):
                        dp = Pc[i, r] - Pc[j, r]
                        hii += Jc[i, r, k] * Jc[i, r, k2] + dp * Hc[i, r, k, k2]
                        hjj += Jc[j, r, k] * Jc[j, r, k2] - dp * Hc[j, r, k, k2]
                        hij -= Jc[i, r, k] * Jc[j, r, k2]
                    A[i * K + k, i * K + k2] += lc * hii
                    A[j * K + k, j * K + k2] += lc * hjj
                    A[i * K + k, j * K + k2] += lc * hij
                    A[j * K + k2, i * K + k] += lc * hij
            for q in range(n):
                A[n + c, q] = G[c, q]
                A[q, n + c] = G[c, q]
        if ideal:
            for i in range(N):
                for k in range(K):
                    q = i * K + k
                    A[n + m + i, q] = rarm[i, k]
                    A[q, n + m + i] = rarm[i, k]
        # A tiny negative diagonal on the multiplier block keeps the KKT matrix regular where
        # a constraint's gradient vanishes: the Model O's side fingers in mirror-image poses,
        # whose contacts are separated along the normal of both finger planes, so that no
        # finger motion changes their distance to first order. It changes the Newton steps,
        # not the solution (the multiplier steps vanish at convergence).
        hscale = 0.0
        for q in range(n):
            if abs(A[q, q]) > hscale:
                hscale = abs(A[q, q])
        for c in range(m + nc):
            A[n + c, n + c] = -1e-12 * hscale
        for q in range(dim):
            F[q] = -F[q]
        if not _solve(A, F):
            break
        big = 0.0
        for q in range(n):
            if abs(F[q]) > big:
                big = abs(F[q])
        scale = 1.0
        if big > max_step:
            scale = max_step / big
        for i in range(N):
            for k in range(K):
                theta[i, k] += scale * F[i * K + k]
        for c in range(m):
            lam[c] += scale * F[n + c]
        for i in range(nc):
            mu[i] += scale * F[n + m + i]
        if big < 1e-15 and res_f < 1e3 * tol[0] and res_g < 1e3 * tol[1] and res_t < 1e3 * tol[2]:
            ok = True  # limited by round-off
            break
    resid[0] = res_f
    resid[1] = res_g
    resid[2] = res_t
    if ok:
        for i in range(N):
            if ideal:
                T[i] = -mu[i]
                s_out[i] = T[i] / kappa[i]
            else:
                s_out[i] = sp[i]
                T[i] = kappa[i] * sp[i]
    else:
        for i in range(N):
            for k in range(K):
                theta[i, k] = theta0[i, k]
            s_out[i] = s0[i]
            T[i] = kappa[i] * s0[i]
        lam[:] = 0.0
    return ok, it


@njit(cache=True)
def _make_work(N, K, m):  # pragma: no cover - numba
    """Scratch arrays of one Newton solve (sized for the ideal model, the larger one)."""
    n = N * K
    dim = n + m + N
    return (
        np.empty((N, 3)), np.empty((N, 3, K)), np.empty((N, 3, K, K)), np.empty(m), np.empty((m, n)),
        np.empty((dim, dim)), np.empty(dim), np.zeros(N), np.empty(N), np.empty((n, m + N)), np.empty(n),
        np.empty((m + N, m + N)), np.empty(m + N),
    )


@njit(cache=True)
def _move_one(
    theta0, s0, dl, a, L, kst, D2, pad, base, u, rarm, rest, kappa, pairs,
    ideal, max_iter, max_step, tol, max_substeps, theta, lam, T, s_out, resid, work, th_c, s_c,
):  # pragma: no cover - numba
    o, it = _newton_one(
        theta0, s0, dl, a, L, kst, D2, pad, base, u, rarm, rest,
        kappa, pairs, ideal, max_iter, max_step, tol, theta, lam, T, s_out, resid, work,
    )
    # Continuation: a failed particle is retried with the action ramped in substeps,
    # following the quasi-static branch from the current configuration.
    nsub = 4
    while not o and nsub <= max_substeps:
        th_c[:, :] = theta0
        s_c[:] = s0
        ddl = dl / nsub
        it = 0
        for _ in range(nsub):
            o, it_k = _newton_one(
                th_c, s_c, ddl, a, L, kst, D2, pad, base, u, rarm, rest,
                kappa, pairs, ideal, max_iter, max_step, tol, theta, lam, T, s_out, resid, work,
            )
            it += it_k
            if not o:
                break
            th_c[:, :] = theta
            s_c[:] = s_out
        if not o:
            theta[:, :] = theta0
            s_out[:] = s0
            for i in range(theta0.shape[0]):
                T[i] = kappa[i] * s0[i]
        nsub *= 4
    return o, it


@njit(cache=True, parallel=True)
def _move_kernel(
    theta0, s0, dl, a, L, kst, D2, pad, base, u, rarm, rest, kappa, pairs,
    ideal, max_iter, max_step, tol, max_substeps, theta, lam, T, s_out, ok, iters, resid,
):  # pragma: no cover - numba
    P, N, K = theta0.shape
    m = pairs.shape[0]
    chunk = 256
    nchunks = (P + chunk - 1) // chunk
    for cc in prange(nchunks):
        work = _make_work(N, K, m)
        th_c = np.empty((N, K))
        s_c = np.empty(N)
        start = np.int64(cc) * chunk
        stop = min(start + chunk, P)
        for p in range(start, stop):
            pl = p if L.shape[0] > 1 else 0
            pk = p if kst.shape[0] > 1 else 0
            pd = p if dl.shape[0] > 1 else 0
            o, it = _move_one(
                theta0[p], s0[p], dl[pd], a[p], L[pl], kst[pk], D2[p], pad, base, u, rarm, rest,
                kappa, pairs, ideal, max_iter, max_step, tol, max_substeps, theta[p], lam[p], T[p], s_out[p],
                resid[p], work, th_c, s_c,
            )
            ok[p] = o
            iters[p] = it


@njit(cache=True)
def _equilibrium_one(theta, a, L, kst, pad, base, u, rarm, rest, pairs, T, lam, work):  # pragma: no cover
    """Least-squares (T, lambda) of one particle; returns the residual norm (inf: singular).

    ``work`` holds scratch arrays (see :func:`_make_equilibrium_work`), reused across
    particles; the products are written as loops (numba's ``@`` on small arrays goes
    through BLAS calls that cost more than the arithmetic)."""
    N, K = theta.shape
    m = pairs.shape[0]
    n = N * K
    nb = N + m
    Pc, Jc, Hc, g, G, D2, B, f0, M, rhs = work
    _fk_all(theta, L, a, pad, base, u, Pc, Jc, Hc)
    _constraint_jacobian(Pc, Jc, pairs, D2, g, G)
    B[:, :] = 0.0
    for i in range(N):
        for k in range(K):
            q = i * K + k
            f0[q] = kst[i, k] * (theta[i, k] - rest[i, k])
            B[q, i] = -rarm[i, k]
            for c in range(m):
                B[q, N + c] = G[c, q]
    if not _ridge_solve(B, f0, M, rhs):
        T[:] = 0.0
        lam[:] = 0.0
        return np.inf
    for i in range(N):
        T[i] = rhs[i]
    for c in range(m):
        lam[c] = rhs[N + c]
    r2 = 0.0
    for q in range(n):
        v = f0[q]
        for c in range(nb):
            v += B[q, c] * rhs[c]
        r2 += v * v
    return np.sqrt(r2)


@njit(cache=True)
def _make_equilibrium_work(N, K, m):  # pragma: no cover - numba
    n = N * K
    return (np.empty((N, 3)), np.empty((N, 3, K)), np.empty((N, 3, K, K)), np.empty(m), np.empty((m, n)),
            np.zeros(m), np.zeros((n, N + m)), np.empty(n), np.empty((N + m, N + m)), np.empty(N + m))


@njit(cache=True, parallel=True)
def _equilibrium_kernel(theta, a, L, kst, pad, base, u, rarm, rest, pairs, T, lam, resid):  # pragma: no cover
    """Least-squares (T, lambda) with k (theta - theta0) - R^T T + G^T lambda = 0."""
    P, N, K = theta.shape
    m = pairs.shape[0]
    chunk = 256
    nchunks = (P + chunk - 1) // chunk
    for cc in prange(nchunks):
        work = _make_equilibrium_work(N, K, m)
        start = np.int64(cc) * chunk
        stop = min(start + chunk, P)
        for p in range(start, stop):
            pl = p if L.shape[0] > 1 else 0
            pk = p if kst.shape[0] > 1 else 0
            resid[p] = _equilibrium_one(theta[p], a[p], L[pl], kst[pk], pad, base, u, rarm, rest, pairs, T[p],
                                        lam[p], work)


# --------------------------------------------------------------------------------------
# Python API
# --------------------------------------------------------------------------------------


def contact_distances_sq(hand: HandModel, p: np.ndarray) -> np.ndarray:
    """Squared distances D_c^2 (P, m) of the constraint pairs, for contacts p (P, N, 3)."""
    pairs = hand.constraint_pairs
    d = p[:, pairs[:, 0]] - p[:, pairs[:, 1]]
    return np.einsum("pcx,pcx->pc", d, d)


def check_action(hand: HandModel, l_now, dl) -> np.ndarray:
    """Validate an action against the tendon range; returns l_now + dl (N,).

    Raises :class:`TendonLimitError` naming the finger whose tendon would leave its range.
    """
    l_now = np.asarray(l_now, float).reshape(-1)
    dl = np.asarray(dl, float).reshape(-1)
    if l_now.shape != (hand.N,) or dl.shape != (hand.N,):
        raise ValueError(f"tendon command and action must have {hand.N} entries, got {l_now.shape} and {dl.shape}")
    l_new = l_now + dl
    lo, hi = hand.tendon_range[:, 0], hand.tendon_range[:, 1]
    bad = np.flatnonzero((l_new < lo - 1e-12) | (l_new > hi + 1e-12))
    if bad.size:
        i = bad[0]
        raise TendonLimitError(
            f"action would take tendon '{hand.names[i]}' to {l_new[i] * 1e3:.3f} mm, "
            f"outside its range [{lo[i] * 1e3:.3f}, {hi[i] * 1e3:.3f}] mm"
        )
    return l_new


def _hand_params(hand: HandModel, P: int, link_lengths, stiffness):
    L = hand.link_lengths[None] if link_lengths is None else link_lengths
    L = as_particles("link_lengths", L, (P, hand.N, hand.K - 1), allow_shared=True)
    if np.any(L <= 0):
        raise ValueError("'link_lengths' must be positive")
    k = hand.stiffness[None] if stiffness is None else stiffness
    k = as_particles("stiffness", k, (P, hand.N, hand.K), allow_shared=True)
    if np.any(k <= 0):
        raise ValueError("'stiffness' must be positive")
    return L, k


def _check_theta(hand: HandModel, theta) -> np.ndarray:
    theta = np.asarray(theta, float)
    if theta.ndim != 3 or theta.shape[1:] != (hand.N, hand.K):
        raise ValueError(f"'theta' must have shape (P, {hand.N}, {hand.K}), got {theta.shape}")
    return as_particles("theta", theta, theta.shape)


def move(
    hand: HandModel,
    theta,
    dl,
    *,
    a,
    D2,
    stretch=None,
    link_lengths=None,
    stiffness=None,
    tendon: str = "elastic",
    l_now=None,
    max_iter: int = MAX_ITER,
    max_step: float = MAX_STEP,
    max_substeps: int = 0,
    tolerance: str = "tight",
) -> MoveResult:
    """Gamma (Eq. 4/9): move every particle by the tendon action ``dl``.

    Args:
        hand: the hand's arrays.
        theta: (P, N, K) current joint angles.
        dl: (N,) one action for all particles, or (P, N).
        a: (P, N) contact positions along the last links.
        D2: (P, m) squared contact distances that the grasp holds (Eq. 8); see
            :func:`contact_distances_sq`.
        stretch: (P, N) current tendon stretch (elastic model; see :func:`equilibrium`).
        link_lengths: (P or 1, N, K-1) per-particle link lengths (default: the hand's).
        stiffness: (P or 1, N, K) per-particle joint stiffness (default: the hand's).
        tendon: ``"elastic"`` or ``"ideal"``.
        l_now: (N,) current tendon commands; when given, the action is checked against the
            tendon range (:class:`TendonLimitError`).
        max_iter, max_step: Newton iteration cap and joint step cap [rad].
        max_substeps: a particle that fails with the whole action is retried with the
            action ramped in 4, 16, ... substeps up to this many (quasi-static continuation;
            0, the default, disables it: on 60,000 wide-prior particles it rescued 0.1% of
            them for 40% more time). Particles that fail keep their angles and ``ok = False``.
        tolerance: a key of :data:`TOLERANCES`: "tight" (default; the controller's
            finite differences need it) or "filter".
    """
    if tendon not in TENDON_MODELS:
        raise ValueError(f"tendon model must be one of {TENDON_MODELS}, got '{tendon}'")
    if tolerance not in TOLERANCES:
        raise ValueError(f"Newton tolerance must be one of {tuple(TOLERANCES)}, got '{tolerance}'")
    theta = _check_theta(hand, theta)
    P = theta.shape[0]
    dl = np.asarray(dl, float)
    dl = as_particles("dl", dl[None] if dl.ndim == 1 else dl, (P, hand.N), allow_shared=True)
    if l_now is not None:
        if dl.shape[0] != 1:
            raise ValueError("'l_now' can only be checked for one action shared by all particles")
        check_action(hand, l_now, dl[0])
    a = as_particles("a", a, (P, hand.N))
    D2 = as_particles("D2", D2, (P, hand.num_constraints))
    if stretch is None:
        if tendon == "elastic":
            raise ValueError("the elastic tendon model needs 'stretch' (see motion.equilibrium)")
        stretch = np.zeros((P, hand.N))
    s0 = as_particles("stretch", stretch, (P, hand.N))
    L, k = _hand_params(hand, P, link_lengths, stiffness)
    out_theta = np.empty_like(theta)
    lam = np.zeros((P, hand.num_constraints))
    T = np.empty((P, hand.N))
    s_out = np.empty((P, hand.N))
    ok = np.zeros(P, dtype=np.bool_)
    iters = np.zeros(P, dtype=np.int64)
    resid = np.zeros((P, 3))
    _move_kernel(
        theta, s0, dl, a, L, k, D2, hand.pad, hand.base, hand.u, hand.moment_arms, hand.rest_angles,
        hand.kappa, hand.constraint_pairs, tendon == "ideal", int(max_iter), float(max_step),
        np.array(TOLERANCES[tolerance]), int(max_substeps), out_theta, lam, T, s_out, ok, iters, resid,
    )
    return MoveResult(out_theta, s_out, T, lam, ok, iters, resid)


def equilibrium(
    hand: HandModel, theta, *, a, link_lengths=None, stiffness=None, settle: bool | None = None
) -> Equilibrium:
    """Tendon stretch and tension that hold the grasp at ``theta`` (DESIGN.md section 4b).

    Solves the stationarity conditions ``k (theta - theta0) - R^T T + G^T lambda = 0`` for
    (T, lambda). For the Model O (N*K = N + m) this is square and exact: every grasp
    configuration is an equilibrium for exactly one tendon state. For hands with more
    joints (N*K > N + m) the least-squares tension is used and, with ``settle`` (default for
    such hands), the elastic model with a zero action moves the angles to the nearest true
    equilibrium, which is returned as ``theta``.
    """
    theta = _check_theta(hand, theta)
    P = theta.shape[0]
    a = as_particles("a", a, (P, hand.N))
    L, k = _hand_params(hand, P, link_lengths, stiffness)
    T = np.empty((P, hand.N))
    lam = np.empty((P, hand.num_constraints))
    resid = np.empty(P)
    _equilibrium_kernel(
        theta, a, L, k, hand.pad, hand.base, hand.u, hand.moment_arms, hand.rest_angles,
        hand.constraint_pairs, T, lam, resid,
    )
    ok = np.isfinite(resid)
    square = hand.N * hand.K == hand.N + hand.num_constraints
    if settle is None:
        settle = not square
    stretch = np.where(ok[:, None], T / hand.kappa, 0.0)
    if not settle:
        return Equilibrium(theta.copy(), stretch, np.where(ok[:, None], T, 0.0), np.nan_to_num(lam), ok)
    p = contacts(hand, theta, a, L)
    res = move(
        hand, theta, np.zeros(hand.N), a=a, D2=contact_distances_sq(hand, p), stretch=stretch,
        link_lengths=L, stiffness=k, tendon="elastic",
    )
    return Equilibrium(res.theta, res.stretch, res.tension, res.multipliers, ok & res.ok)
