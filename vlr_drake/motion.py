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

The kernel is compiled with numba and runs in parallel over particles. Each thread solves
:data:`LANES` particles side by side, the particles on the last axis of every array, so
that the arithmetic (kinematics, KKT assembly, elimination without pivoting) runs as SIMD
loops; each lane keeps its own particle's Newton iteration (iteration count, step cap,
convergence test) and takes the next particle when it is done, and a lane whose matrix
needs pivoting is solved again with partial pivoting. The reference solver for one
configuration is :mod:`vlr_drake.motion_reference` (Drake MathematicalProgram with IPOPT
or SNOPT), and the tests hold the two to 1e-6 rad.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from vlr_drake.hand import HandModel
from vlr_drake.kinematics import (
    as_particles,
    contact_force_torque,
    contacts,
    finger_contact_derivatives,
    is_count,
    is_number,
    sincos,
)

__all__ = [
    "TENDON_MODELS",
    "TOLERANCES",
    "MoveResult",
    "Equilibrium",
    "TendonLimitError",
    "move",
    "stable_equilibria",
    "equilibrium",
    "check_action",
    "contact_distances_sq",
    "gravity_torque",
]

TENDON_MODELS = ("elastic", "ideal")

#: Convergence tolerances of the Newton solver (SI units: N m, m^2, m), per caller.
#: "tight" (default) solves to round-off, for the controller's finite-difference Jacobians
#: (eps 0.2 mm). "filter" solves to ~1e-8 rad, far below what the camera resolves, and saves a
#: Newton step on about half the particles (``FilterConfig.newton_tolerance`` says what it
#: did to the physics handwriting).
TOLERANCES = {"tight": (1e-12, 1e-15, 1e-13), "filter": (1e-9, 1e-12, 1e-11)}
TOL_TORQUE, TOL_CONSTRAINT, TOL_TENDON = TOLERANCES["tight"]
#: Tolerances accepted when the iteration budget runs out, or after ``loose_after`` steps
#: (angles within ~1e-5 rad of a tight solution; near the mirror-image grasps up to 3e-4).
#: The contact distances are accepted as a distance error |g| / D [m] (5 nm): at the
#: Model O's mirror-image grasps the regularised Newton iteration stalls at ~2 nm for the
#: 54 mm side pair, a floor set by the multiplier ridge (the regulariser of the pivoted
#: re-solve, which these lanes take), not by the physics.
LOOSE_TORQUE = 1e-7
LOOSE_DISTANCE = 5e-9
LOOSE_TENDON = 1e-10
#: The tiny negative diagonal on the KKT matrix's multipliers' block, relative to the lane's
#: largest Hessian diagonal: in the pivoted re-solve of a lane whose pivot fails, and on
#: every step of a retried attempt (:func:`_move_lanes`).
KKT_REGULARISER = 1e-12
#: Largest joint-angle change of one Newton step [rad].
MAX_STEP = 0.15
MAX_ITER = 30


class TendonLimitError(ValueError):
    """An action would take a tendon outside its range."""


@dataclass
class MoveResult:
    """Result of a batched move. Particles that failed keep their input angles, and with
    the elastic tendon the stretch the action leaves there, s + dl (ideal: their input
    tension).

    Attributes:
        theta: (P, N, K) joint angles after the action.
        stretch: (P, N) tendon stretch s' (elastic model; ``tension / kappa`` for ideal).
        tension: (P, N) implied tendon tension T [N].
        multipliers: (P, m) contact-constraint multipliers lambda (negative: the fingers
            squeeze the object along that contact pair).
        ok: (P,) True where Newton converged: to a stationary point of Eq. 9 under its
            constraints, which need not be a minimum (``stable`` says; a review found
            unstable equilibria among the converged moves: 5 of 300 stable NH3 grasps under
            +-3 mm actions, many more from a wide prior's draws). Joint limits and tension
            are not in ``ok`` either (:meth:`tension_feasible`; the filter and the model
            plant add both).
        iterations: (P,) Newton steps of the attempt that was kept (a failed attempt that was
            retried, with the regulariser or with substeps, is not counted).
        residuals: (P, 3) final max residuals: stationarity [N m], constraints [m^2],
            tendon equations [m] (ideal model); for a failed particle, those of the last
            iterate Newton abandoned, not of the input angles it is returned at (a review).
        stable: (P,) True where ``ok`` and the equilibrium is a strict constrained minimum
            (:func:`stable_equilibria`); all ``ok`` when :func:`move` was asked not to check.
    """

    theta: np.ndarray
    stretch: np.ndarray
    tension: np.ndarray
    multipliers: np.ndarray
    ok: np.ndarray
    iterations: np.ndarray
    residuals: np.ndarray
    stable: np.ndarray

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
    ok: np.ndarray  # (P,) solved (a finite least-squares residual), not exact: see _ridge_solve
    # (P,) [N m] how far theta is from an equilibrium of that tendon state: the norm of the
    # least-squares stationarity residual (where settled, the settling move's largest one);
    # inf where not solved
    residual: np.ndarray


# --------------------------------------------------------------------------------------
# numba kernels
# --------------------------------------------------------------------------------------


@njit(cache=True)
def _worst(r, v):  # pragma: no cover - numba
    """The larger of a residual so far ``r`` and ``v``, NaN if ``v`` is NaN (``max(r, nan)``
    is ``r``: a lane whose numbers had gone NaN read residual 0 and was called converged)."""
    return r if (r >= v or r != r) else v  # (r != r: a NaN already, kept)


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
        if not best > 1e-300 or best < 1e-17 * scale:  # (a NaN pivot too: not a solution)
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


#: Hypotheses solved side by side by one thread of the Newton kernel ("lanes"): every
#: array of a solve has them on its last axis, so the arithmetic runs as SIMD loops (AVX2:
#: four doubles at a time). Longer lanes amortise each short loop's set-up; measured per
#: 60,000-particle move on 2 cores: 16 lanes 114 ms, 32 95 ms, 64 87 ms, 128 89 ms.
LANES = 64


@njit(cache=True)
def _fk_all(theta, L, a, pad, base, u, Pc, Jc, Hc):  # pragma: no cover - numba
    """Contacts and their derivatives of all fingers: theta (N, K, W), L (N, K-1, W),
    a (N, W) -> Pc (N, 3, W), Jc (N, 3, K, W), Hc (N, 3, K, K, W)."""
    N = theta.shape[0]
    for i in range(N):
        finger_contact_derivatives(theta[i], L[i], a[i], pad[i], base[i], u[i], Pc[i], Jc[i], Hc[i])


@njit(cache=True)
def _constraint_jacobian(Pc, Jc, pairs, D2, g, G):  # pragma: no cover - numba
    """g_c = 0.5 (|p_i - p_j|^2 - D2_c) (m, W) and its gradient rows G (m, N*K, W)."""
    m = pairs.shape[0]
    K = Jc.shape[2]
    W = Pc.shape[2]
    n = G.shape[1]
    for c in range(m):
        i = pairs[c, 0]
        j = pairs[c, 1]
        for q in range(n):
            for w in range(W):
                G[c, q, w] = 0.0
        for w in range(W):
            g[c, w] = -0.5 * D2[c, w]
        for r in range(3):
            for w in range(W):
                dp = Pc[i, r, w] - Pc[j, r, w]
                g[c, w] += 0.5 * dp * dp
            for k in range(K):
                for w in range(W):
                    dp = Pc[i, r, w] - Pc[j, r, w]
                    G[c, i * K + k, w] += dp * Jc[i, r, k, w]
                    G[c, j * K + k, w] -= dp * Jc[j, r, k, w]


@njit(cache=True)
def _load_lanes(th, Jc, Hc, mu, gw, fc, tau, dtau, phi, acc_c, acc_s):  # pragma: no cover - numba
    """Joint torques ``tau`` (N, K, W) of the gravity loads of every lane, and their
    derivatives ``dtau`` (N, K, K, W) (symmetric: the loads have a potential V, tau = -dV/dtheta):

    - the links' weight, with first moments ``mu`` (N, K, W) and gravity's in-plane
      components ``gw`` (N, 2) (:meth:`HandModel.link_weight_torque`): with
      c_l = mu_l (g_u cos phi_l - g_z sin phi_l), tau_j = sum_{l >= j} c_l and
      dtau_j/dtheta_k = -sum_{l >= max(j, k)} mu_l (g_u sin phi_l + g_z cos phi_l);
    - forces ``fc`` (N, 3, W) [N] at the contacts: tau_j = J_j . f, dtau_j/dtheta_k = H_jk . f
      (``Jc``, ``Hc``: the contacts' first and second derivatives).

    ``phi``, ``acc_c``, ``acc_s`` (W,) are scratch."""
    N, K, W = th.shape
    for i in range(N):
        gu = gw[i, 0]
        gz = gw[i, 1]
        for w in range(W):
            phi[w] = 0.0
            acc_c[w] = 0.0
            acc_s[w] = 0.0
        for k in range(K):
            for w in range(W):
                phi[w] += th[i, k, w]
        for l in range(K - 1, -1, -1):  # suffix sums over the links l, l+1, ..., K-1
            for w in range(W):
                sn, cs = sincos(phi[w])
                acc_c[w] += mu[i, l, w] * (gu * cs - gz * sn)
                acc_s[w] -= mu[i, l, w] * (gu * sn + gz * cs)
                phi[w] -= th[i, l, w]
                tau[i, l, w] = acc_c[w]
            for j in range(l + 1):  # max(j, k) == l
                for w in range(W):
                    dtau[i, j, l, w] = acc_s[w]
                    dtau[i, l, j, w] = acc_s[w]
        for k in range(K):
            for r in range(3):
                for w in range(W):
                    tau[i, k, w] += Jc[i, r, k, w] * fc[i, r, w]
            for k2 in range(K):
                for r in range(3):
                    for w in range(W):
                        dtau[i, k, k2, w] += Hc[i, r, k, k2, w] * fc[i, r, w]


@njit(cache=True)
def _ridge_solve(A, f0, M, rhs):  # pragma: no cover - numba
    """Least squares min |A x + f0| (A: equations x unknowns) by the normal equations, with a
    1e-12-relative ridge that picks the minimum-norm x where A loses rank (multipliers that
    are statically indeterminate). The solution is left in ``rhs``; False if singular.
    The normal equations square A's condition number, so near a singular grasp the
    solution is not exact: a review (2026-11-27) found residuals above 1e-3 N m in 976 of
    200,000 random NH2 grasps, where a pivoted solve is exact. Those grasps ask kilonewtons
    of their tendons either way (max |T| median 2.2 kN here, 3.4 kN exact): neither is a
    physical grasp. Kept, because the ridge is what keeps a grasp near the Model O's
    mirror-image pose usable (the exact tensions 1e-4 rad from it are +-88 kN, with which
    no move succeeds; ``test_symmetric_model_o_grasp_moves``).
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
def _lu_lanes(A, b, n1, tiny1, tiny2, bad):  # pragma: no cover - numba
    """Solve the symmetric systems A x = b of every lane at once, in place (A (d, d, W),
    b (d, W); only A's upper triangle is read), by Gaussian elimination without pivoting,
    which vectorises across lanes; the trailing matrices stay symmetric, so only their
    upper triangles are updated. A lane with a pivot below ``tiny1`` (W,) in the first
    ``n1`` columns or below ``tiny2`` (W,) in the others is marked in ``bad`` (W,), to be
    solved again with pivoting (:func:`_solve`)."""
    d = A.shape[0]
    W = A.shape[2]
    for c in range(d):
        tiny = tiny1 if c < n1 else tiny2
        for w in range(W):
            small = not abs(A[c, c, w]) > tiny[w]
            bad[w] = bad[w] or small
            # 1 / pivot, kept on the diagonal for the back substitution (1 where the pivot
            # is too small, to keep the other lanes' arithmetic finite)
            A[c, c, w] = 1.0 if small else 1.0 / A[c, c, w]
        for r in range(c + 1, d):
            for w in range(W):  # the multiplier, kept in the (unused) lower triangle
                A[r, c, w] = A[c, r, w] * A[c, c, w]
            for j in range(r, d):
                for w in range(W):
                    A[r, j, w] -= A[r, c, w] * A[c, j, w]
            for w in range(W):
                b[r, w] -= A[r, c, w] * b[c, w]
    for r in range(d - 1, -1, -1):
        for j in range(r + 1, d):
            for w in range(W):
                b[r, w] -= A[r, j, w] * b[j, w]
        for w in range(W):
            b[r, w] *= A[r, r, w]


@njit(cache=True)
def _initial_multipliers(fresh, th, s0, dls, kst, rarm, rest, kappa, G, ideal, lam, mu, f0, M, rhs, scale, bad,
                         tau, loaded):  # pragma: no cover
    """Multipliers of the lanes starting a solve (``fresh``, then cleared): least squares
    of the stationarity rows at their starting angles (with the gravity loads ``tau`` where ``loaded``), min |B x + f0| with B = [G^T, R^T]
    (ideal tendon) or G^T, by the normal equations with a 1e-12-relative ridge that picks
    the minimum-norm multipliers where B loses rank (as :func:`_ridge_solve`, vectorised
    over all lanes); a singular lane starts from zero multipliers."""
    N, K, W = th.shape
    n = N * K
    m = G.shape[0]
    nc = N if ideal else 0
    nb = m + nc
    any_fresh = False
    for w in range(W):
        any_fresh = any_fresh or fresh[w]
    if not any_fresh:
        return
    for i in range(N):
        for k in range(K):
            q = i * K + k
            for w in range(W):
                f0[q, w] = kst[i, k, w] * (th[i, k, w] - rest[i, k, w])
            if loaded:
                for w in range(W):
                    f0[q, w] -= tau[i, k, w]
            if not ideal:
                for w in range(W):
                    f0[q, w] -= rarm[i, k] * kappa[i] * (s0[i, w] + dls[i, w])
    # normal equations M = B^T B (upper triangle), rhs = -B^T f0
    for c1 in range(m):
        for w in range(W):
            rhs[c1, w] = 0.0
        for q in range(n):
            for w in range(W):
                rhs[c1, w] -= G[c1, q, w] * f0[q, w]
        for c2 in range(c1, m):
            for w in range(W):
                M[c1, c2, w] = 0.0
            for q in range(n):
                for w in range(W):
                    M[c1, c2, w] += G[c1, q, w] * G[c2, q, w]
        for i in range(nc):
            for w in range(W):
                M[c1, m + i, w] = 0.0
            for k in range(K):
                for w in range(W):
                    M[c1, m + i, w] += G[c1, i * K + k, w] * rarm[i, k]
    for i in range(nc):
        r2 = 0.0
        for k in range(K):
            r2 += rarm[i, k] * rarm[i, k]
        for w in range(W):
            rhs[m + i, w] = 0.0
            M[m + i, m + i, w] = r2
        for k in range(K):
            for w in range(W):
                rhs[m + i, w] -= rarm[i, k] * f0[i * K + k, w]
        for i2 in range(i + 1, nc):
            for w in range(W):
                M[m + i, m + i2, w] = 0.0
    for w in range(W):
        scale[w] = 0.0
        bad[w] = False
    for c in range(nb):
        for w in range(W):
            scale[w] = max(scale[w], M[c, c, w])
    for c in range(nb):
        for w in range(W):
            M[c, c, w] += 1e-12 * scale[w]
    for w in range(W):
        scale[w] *= 1e-17  # a singular matrix (the pivoted solve's test)
    _lu_lanes(M, rhs, nb, scale, scale, bad)
    for w in range(W):
        if not fresh[w]:
            continue
        fresh[w] = False
        ok = not bad[w]
        for c in range(nb):
            ok = ok and np.isfinite(rhs[c, w])
        for c in range(m):
            lam[c, w] = rhs[c, w] if ok else 0.0
        for i in range(N):
            mu[i, w] = rhs[m + i, w] if (ok and ideal) else 0.0


@njit(cache=True)
def _residuals_lanes(th, th0, s0, dls, kst, rest, rarm, kappa, G, g, lam, mu, sqD, ideal, sp, F, res, res_d,
                     tau, loaded):  # pragma: no cover
    """The KKT residuals F (dim, W) of every lane (with the gravity loads ``tau`` where ``loaded``), the tendon stretch s' (N, W) and the
    largest residuals ``res`` (3, W): torque [N m], constraint [m^2], tendon [m] (ideal);
    ``res_d`` (W,) the constraint residual as a distance error [m]."""
    N, K, W = th.shape
    n = N * K
    m = G.shape[0]
# residuals
    for i in range(N):
        for w in range(W):
            v = s0[i, w] + dls[i, w]
            for k in range(K):
                v -= rarm[i, k] * (th[i, k, w] - th0[i, k, w])
            sp[i, w] = v
    for w in range(W):
        res[0, w] = 0.0
        res[1, w] = 0.0
        res[2, w] = 0.0
        res_d[w] = 0.0
    for i in range(N):
        for k in range(K):
            q = i * K + k
            for w in range(W):
                v = kst[i, k, w] * (th[i, k, w] - rest[i, k, w])
                if ideal:
                    v += rarm[i, k] * mu[i, w]
                else:
                    v -= rarm[i, k] * kappa[i] * sp[i, w]
                F[q, w] = v
            if loaded:
                for w in range(W):
                    F[q, w] -= tau[i, k, w]
            for c in range(m):
                for w in range(W):
                    F[q, w] += G[c, q, w] * lam[c, w]
            for w in range(W):
                res[0, w] = _worst(res[0, w], abs(F[q, w]))
    for c in range(m):
        for w in range(W):
            F[n + c, w] = g[c, w]
            res[1, w] = _worst(res[1, w], abs(g[c, w]))
            # the same residual as a distance error [m]: |g| / D, g = (d^2 - D^2) / 2
            res_d[w] = _worst(res_d[w], abs(g[c, w]) / sqD[c, w])
    if ideal:
        for i in range(N):
            for w in range(W):
                v = -dls[i, w]
                for k in range(K):
                    v += rarm[i, k] * (th[i, k, w] - th0[i, k, w])
                F[n + m + i, w] = v
                res[2, w] = _worst(res[2, w], abs(v))


@njit(cache=True)
def _kkt_lanes(Pc, Jc, Hc, G, kst, Hten, rarm, lam, pairs, ideal, A, hscale, gscale, dtau, loaded):  # pragma: no cover
    """The upper triangle of the (symmetric) KKT matrix A (dim, dim, W) of every lane (the
    multipliers' block zero; with the gravity loads' -dtau/dtheta where ``loaded``);
    ``hscale`` and ``gscale`` (W,) receive each lane's largest Hessian diagonal and
    constraint-gradient entries. Hten (n, n) is the elastic tendons' part, the same for
    every lane."""
    N = Pc.shape[0]
    K = Jc.shape[2]
    W = Pc.shape[2]
    n = N * K
    m = pairs.shape[0]
    nc = N if ideal else 0
    dim = n + m + nc
    # (lanes not stepping compute on valid numbers, unused)
    for q in range(dim):
        for q2 in range(q, dim):
            for w in range(W):
                A[q, q2, w] = 0.0
    for i in range(N):
        for k in range(K):
            q = i * K + k
            for w in range(W):
                A[q, q, w] += kst[i, k, w]
            if not ideal:
                for k2 in range(k, K):
                    q2 = i * K + k2
                    for w in range(W):
                        A[q, q2, w] += Hten[q, q2]
            if loaded:
                for k2 in range(k, K):
                    for w in range(W):
                        A[q, i * K + k2, w] -= dtau[i, k, k2, w]
    for c in range(m):
        i = pairs[c, 0]
        j = pairs[c, 1]
        for k in range(K):
            for k2 in range(K):
                # the pair's cross block, in the upper triangle
                q1 = min(i * K + k, j * K + k2)
                q2 = max(i * K + k, j * K + k2)
                for w in range(W):
                    hij = 0.0
                    for r in range(3):
                        hij -= Jc[i, r, k, w] * Jc[j, r, k2, w]
                    A[q1, q2, w] += lam[c, w] * hij
            for k2 in range(k, K):
                for w in range(W):
                    hii = 0.0
                    hjj = 0.0
                    for r in range(3):
                        dp = Pc[i, r, w] - Pc[j, r, w]
                        hii += Jc[i, r, k, w] * Jc[i, r, k2, w] + dp * Hc[i, r, k, k2, w]
                        hjj += Jc[j, r, k, w] * Jc[j, r, k2, w] - dp * Hc[j, r, k, k2, w]
                    A[i * K + k, i * K + k2, w] += lam[c, w] * hii
                    A[j * K + k, j * K + k2, w] += lam[c, w] * hjj
        for q in range(n):
            for w in range(W):
                A[q, n + c, w] = G[c, q, w]
    if ideal:
        for i in range(N):
            for k in range(K):
                q = i * K + k
                for w in range(W):
                    A[q, n + m + i, w] = rarm[i, k]
    for w in range(W):
        hscale[w] = 0.0
        gscale[w] = 0.0
    for q in range(n):
        for w in range(W):
            hscale[w] = max(hscale[w], abs(A[q, q, w]))
    # The pivots' scales: |H| for the angles' columns and |G|^2 / |H| (a Schur complement)
    # for the multipliers' (the ideal tendon's rows R are scaled like G's by the arms).
    for c in range(m):
        for q in range(n):
            for w in range(W):
                gscale[w] = max(gscale[w], abs(G[c, q, w]))
    for i in range(nc):
        for k in range(K):
            for w in range(W):
                gscale[w] = max(gscale[w], abs(rarm[i, k]))


#: A lane's state at the end of a Newton cycle (see :func:`_move_lanes`).
RUNNING, CONVERGED, FAILED, EMPTY = 0, 1, 2, 3


@njit(cache=True)
def _move_lanes(
    theta0, s0_all, dl, a_all, L_all, kst_all, D2_all, pad, base, u, rarm, rest_all, kappa, pairs,
    mu_all, fc_all, gw, loaded,
    ideal, max_iter, loose_after, max_step, tol, max_substeps, start, stop, stride,
    theta, lam_out, T_out, s_out, ok_out, iters, resid,
):  # pragma: no cover - numba
    """Newton on the KKT system of Eq. 9 for particles ``start:stop:stride``, LANES at a time.

    Each lane runs its own particle's Newton iteration (its own iteration count, step cap
    and convergence test, those of a one-particle Newton method); a lane whose particle is
    done, converged or failed, writes it out and takes the next one, so the lanes stay
    busy. A particle that fails with the whole action is retried in the same lane with the
    action ramped in 4, 16, ... substeps up to ``max_substeps`` (quasi-static continuation).
    With ``loaded``, the gravity loads of :func:`_load_lanes` (links' first moments
    ``mu_all`` (P or 1, N, K), contact forces ``fc_all`` (P or 1, N, 3), gravity ``gw`` (N, 2))
    join the stationarity conditions and the KKT matrix, at the current angles.
    """
    if start >= stop:  # no particle in this share (more tasks than particles)
        return
    P, N, K = theta0.shape
    n = N * K
    m = pairs.shape[0]
    nc = N if ideal else 0
    dim = n + m + nc
    W = LANES
    nb = m + nc
    # scratch, C-contiguous with the lanes last (so that the loops over them vectorise)
    Pc, Jc, Hc = np.empty((N, 3, W)), np.empty((N, 3, K, W)), np.empty((N, 3, K, K, W))
    g, G = np.empty((m, W)), np.empty((m, n, W))
    A, F = np.empty((dim, dim, W)), np.empty((dim, W))  # KKT matrix and right-hand side
    A2, F2 = np.empty((dim, dim, W)), np.empty((dim, W))  # their copies for the pivoted re-solve
    A1, F1 = np.empty((dim, dim)), np.empty(dim)  # one lane's pivoted re-solve
    f0l, Ml, rhsl, scl = np.empty((n, W)), np.empty((nb, nb, W)), np.empty((nb, W)), np.empty(W)  # multipliers
    # the lanes' particles: current angles, the current (sub)solve's start, the particle's own start
    th = np.empty((N, K, W))
    th0 = np.empty((N, K, W))
    thP = np.empty((N, K, W))
    s0 = np.empty((N, W))
    sP = np.empty((N, W))
    dls = np.empty((N, W))
    dlP = np.empty((N, W))
    a = np.empty((N, W))
    L = np.empty((N, K - 1, W))
    kst = np.empty((N, K, W))
    rest = np.empty((N, K, W))
    lmu = np.zeros((N, K, W))  # the gravity loads: links' first moments, contact forces,
    lfc = np.zeros((N, 3, W))  # their torques and derivatives, scratch
    tau = np.zeros((N, K, W))
    dtau = np.zeros((N, K, K, W))
    sc1, sc2, sc3 = np.empty(W), np.empty(W), np.empty(W)
    D2 = np.empty((m, W))
    sqD = np.empty((m, W))
    lam = np.zeros((m, W))
    mu = np.zeros((N, W))
    sp = np.zeros((N, W))
    res = np.zeros((3, W))
    res_d = np.zeros(W)
    hscale = np.zeros(W)
    gscale = np.zeros(W)
    tiny1 = np.zeros(W)
    tiny2 = np.zeros(W)
    bad = np.zeros(W, dtype=np.bool_)  # lanes whose KKT matrix needs pivoting
    pid = np.full(W, -1, dtype=np.int64)
    itn = np.zeros(W, dtype=np.int64)  # Newton steps of the lane's current solve
    it_acc = np.zeros(W, dtype=np.int64)  # steps of the finished substeps of this attempt
    nsub = np.ones(W, dtype=np.int64)
    sub = np.zeros(W, dtype=np.int64)
    fresh = np.zeros(W, dtype=np.bool_)
    regd = np.zeros(W, dtype=np.bool_)  # lanes whose attempt regularises every step (see below)
    step = np.zeros(W, dtype=np.bool_)  # lanes that take a Newton step this cycle
    status = np.full(W, EMPTY, dtype=np.int64)
    Hten = _tendon_hessian(kappa, rarm, ideal)
    nxt = _finish_lanes(
        status, start, start, stop, stride, ideal, max_substeps, theta0, s0_all, dl, a_all, L_all, kst_all, rest_all,
        D2_all, kappa, th, th0, thP, s0, sP, dls, dlP, a, L, kst, rest, D2, sqD, lam, mu, sp, res, pid, itn, it_acc,
        nsub, sub, fresh, regd, theta, lam_out, T_out, s_out, ok_out, iters, resid, mu_all, fc_all, lmu, lfc, loaded,
    )
    while _lanes_busy(pid):
        _fk_all(th, L, a, pad, base, u, Pc, Jc, Hc)
        _constraint_jacobian(Pc, Jc, pairs, D2, g, G)
        if loaded:
            _load_lanes(th, Jc, Hc, lmu, gw, lfc, tau, dtau, sc1, sc2, sc3)
        _initial_multipliers(fresh, th, s0, dls, kst, rarm, rest, kappa, G, ideal, lam, mu, f0l, Ml, rhsl, scl, bad,
                             tau, loaded)
        _residuals_lanes(th, th0, s0, dls, kst, rest, rarm, kappa, G, g, lam, mu, sqD, ideal, sp, F, res, res_d,
                         tau, loaded)
        # each lane's decision, as in a one-particle Newton method
        any_step = False
        for w in range(W):
            step[w] = False
            if pid[w] < 0:
                continue
            rf, rg, rt = res[0, w], res[1, w], res[2, w]
            it = itn[w]
            if not (np.isfinite(rf) and np.isfinite(rg) and np.isfinite(rt)):
                status[w] = FAILED
            elif rf < tol[0] and rg < tol[1] and rt < tol[2]:
                status[w] = CONVERGED
            elif it >= loose_after and rf < LOOSE_TORQUE and res_d[w] < LOOSE_DISTANCE and rt < LOOSE_TENDON:
                # Still short of ``tol`` after ``loose_after`` steps (convergence is only
                # linear near the Model O's symmetric grasps, where one constraint is second
                # order in the motion) but within the physical tolerances: accepted.
                status[w] = CONVERGED
            elif it == max_iter:  # out of iterations and not within the physical tolerances
                status[w] = FAILED
            elif it >= 7 and rf > 1e-3:
                # Not converging at all after 7 steps: an action with no nearby equilibrium
                # (the grasp's fold). Measured (bench motion, 60,000 grasps, +-1.5 mm): 19% of
                # particles end here; stopping at 7 rather than 12 steps took the move from
                # 0.42 to 0.36 s and lost 0.05% of the successes (slow ones, which
                # max_substeps retries).
                status[w] = FAILED
            else:
                step[w] = True
                any_step = True
        if any_step:
            _kkt_lanes(Pc, Jc, Hc, G, kst, Hten, rarm, lam, pairs, ideal, A, hscale, gscale, dtau, loaded)
            for w in range(W):
                if regd[w]:
                    for q in range(n, dim):
                        A[q, q, w] = -KKT_REGULARISER * hscale[w]
            for q in range(dim):
                for w in range(W):
                    F[q, w] = -F[q, w]
                    F2[q, w] = F[q, w]
            for w in range(W):
                bad[w] = False
                tiny1[w] = 1e-9 * hscale[w]
                # (a lane whose Hessian overflowed to NaN has no scale: it fails on its NaN residual)
                tiny2[w] = 1e-9 * gscale[w] * gscale[w] / hscale[w] if hscale[w] > 0 else 0.0
            _lu_lanes(A, F, n, tiny1, tiny2, bad)
            any_bad = False
            for w in range(W):
                any_bad = any_bad or (bad[w] and step[w])
            if any_bad:  # rare: the matrices again, for the lanes that need pivoting
                _kkt_lanes(Pc, Jc, Hc, G, kst, Hten, rarm, lam, pairs, ideal, A2, hscale, gscale, dtau, loaded)
            for w in range(W):
                if not step[w]:
                    continue
                if bad[w]:
                    # A small pivot: this lane again, with partial pivoting and a tiny
                    # negative diagonal on the multipliers' block, which keeps the matrix
                    # regular where a constraint's gradient vanishes (the Model O's side
                    # fingers in mirror-image poses, whose contacts are separated along the
                    # normal of both finger planes, so that no finger motion changes their
                    # distance to first order). It changes the step, not the solution (the
                    # multiplier steps vanish at convergence). Set on every step it makes
                    # Newton linear, or fail, on the regular but ill-conditioned grasps near
                    # those poses; left out, Newton stalls within a few mrad of them. So a
                    # particle's first attempt sets it only here, and an attempt that fails
                    # is retried with it on every step (``regd``, :func:`_finish_lanes`):
                    # docs/results.md, "The KKT regulariser".
                    for q in range(dim):
                        F1[q] = F2[q, w]
                        for q2 in range(q, dim):
                            A1[q, q2] = A2[q, q2, w]
                            A1[q2, q] = A2[q, q2, w]
                    for q in range(n, dim):
                        A1[q, q] -= KKT_REGULARISER * hscale[w]
                    if not _solve(A1, F1):
                        status[w] = FAILED
                        continue
                    for q in range(dim):
                        F[q, w] = F1[q]
                big = 0.0
                for q in range(n):
                    big = max(big, abs(F[q, w]))
                sc = 1.0
                if big > max_step:
                    sc = max_step / big
                for i in range(N):
                    for k in range(K):
                        th[i, k, w] += sc * F[i * K + k, w]
                for c in range(m):
                    lam[c, w] += sc * F[n + c, w]
                for i in range(nc):
                    mu[i, w] += sc * F[n + m + i, w]
                if big < 1e-15 and res[0, w] < 1e3 * tol[0] and res[1, w] < 1e3 * tol[1] and res[2, w] < 1e3 * tol[2]:
                    status[w] = CONVERGED  # limited by round-off
                else:
                    itn[w] += 1
        nxt = _finish_lanes(
            status, nxt, start, stop, stride, ideal, max_substeps, theta0, s0_all, dl, a_all, L_all, kst_all, rest_all,
            D2_all, kappa, th, th0, thP, s0, sP, dls, dlP, a, L, kst, rest, D2, sqD, lam, mu, sp, res, pid, itn, it_acc,
            nsub, sub, fresh, regd, theta, lam_out, T_out, s_out, ok_out, iters, resid, mu_all, fc_all, lmu, lfc, loaded,
        )


@njit(cache=True)
def _lanes_busy(pid):  # pragma: no cover - numba
    """Whether any lane still holds a particle (``pid`` (W,) >= 0; -1 for none)."""
    for w in range(pid.shape[0]):
        if pid[w] >= 0:
            return True
    return False


@njit(cache=True)
def _finish_lanes(
    status, nxt, start, stop, stride, ideal, max_substeps, theta0, s0_all, dl, a_all, L_all, kst_all, rest_all,
    D2_all, kappa, th, th0, thP, s0, sP, dls, dlP, a, L, kst, rest, D2, sqD, lam, mu, sp, res, pid, itn, it_acc,
    nsub, sub, fresh, regd, theta, lam_out, T_out, s_out, ok_out, iters, resid, mu_all, fc_all, lmu, lfc, loaded,
):  # pragma: no cover - numba
    """The lanes whose Newton solve ended (``status`` CONVERGED or FAILED) go on with the
    next substep, retry (a first attempt that failed once more with the KKT regulariser on
    every step, ``regd``, then with more substeps), or write their particle out; those and the
    EMPTY ones take the next unclaimed particle ``nxt``, which is returned. A lane left
    without a particle gets ``pid`` -1 (and, if it never had one, particle ``start``'s
    numbers, so that it computes on valid ones)."""
    N, K, W = th.shape
    m = lam.shape[0]
    for w in range(W):
        st = status[w]
        if st == RUNNING:
            continue
        status[w] = RUNNING
        if st != EMPTY:
            o = st == CONVERGED
            p = pid[w]
            it = it_acc[w] + itn[w]
            if o and sub[w] < nsub[w] - 1:
                # the next substep of the continuation, from where this one ended
                for i in range(N):
                    s0[i, w] = -mu[i, w] / kappa[i] if ideal else sp[i, w]
                    for k in range(K):
                        th0[i, k, w] = th[i, k, w]
                sub[w] += 1
                it_acc[w] = it
                itn[w] = 0
                fresh[w] = True
                continue
            more = 4 if nsub[w] == 1 else 4 * nsub[w]
            if not o and (not regd[w] or more <= max_substeps):
                # retry from the particle's start: the same attempt with the regulariser on
                # every step (see _move_lanes), then with the action ramped in ``more`` substeps
                if regd[w]:
                    nsub[w] = more
                regd[w] = True
                sub[w] = 0
                it_acc[w] = 0
                itn[w] = 0
                fresh[w] = True
                for i in range(N):
                    s0[i, w] = sP[i, w]
                    dls[i, w] = dlP[i, w] / nsub[w]
                    for k in range(K):
                        th[i, k, w] = thP[i, k, w]
                        th0[i, k, w] = thP[i, k, w]
                continue
            # the particle is done
            for r in range(3):
                resid[p, r] = res[r, w]
            ok_out[p] = o
            iters[p] = it
            for i in range(N):
                if o:
                    T = -mu[i, w] if ideal else kappa[i] * sp[i, w]
                    T_out[p, i] = T
                    s_out[p, i] = T / kappa[i] if ideal else sp[i, w]
                else:  # held at its angles: the elastic tendon stretched by the action
                    s_fail = sP[i, w] if ideal else sP[i, w] + dlP[i, w]
                    s_out[p, i] = s_fail
                    T_out[p, i] = kappa[i] * s_fail
                for k in range(K):
                    theta[p, i, k] = th[i, k, w] if o else thP[i, k, w]
            for c in range(m):
                lam_out[p, c] = lam[c, w] if o else 0.0
        # the next particle into this lane
        q = nxt
        nxt += stride
        if q >= stop:
            pid[w] = -1
            if st != EMPTY:
                continue
            q = start
        else:
            pid[w] = q
        nsub[w] = 1
        sub[w] = 0
        it_acc[w] = 0
        itn[w] = 0
        fresh[w] = True
        regd[w] = False
        pl = q if L_all.shape[0] > 1 else 0
        pk = q if kst_all.shape[0] > 1 else 0
        pr = q if rest_all.shape[0] > 1 else 0
        pd = q if dl.shape[0] > 1 else 0
        for i in range(N):
            s0[i, w] = s0_all[q, i]
            sP[i, w] = s0_all[q, i]
            dls[i, w] = dl[pd, i]
            dlP[i, w] = dl[pd, i]
            a[i, w] = a_all[q, i]
            for k in range(K):
                th[i, k, w] = theta0[q, i, k]
                th0[i, k, w] = theta0[q, i, k]
                thP[i, k, w] = theta0[q, i, k]
                kst[i, k, w] = kst_all[pk, i, k]
                rest[i, k, w] = rest_all[pr, i, k]
            for k in range(K - 1):
                L[i, k, w] = L_all[pl, i, k]
        if loaded:
            _lane_loads(mu_all, fc_all, q, w, lmu, lfc)
        for c in range(m):
            D2[c, w] = D2_all[q, c]
            # coincident contacts (D2 = 0): a huge residual that fails this particle alone,
            # not a division by zero that ends its thread's whole share of the batch
            sqD[c, w] = np.sqrt(max(D2_all[q, c], 1e-300))
    return nxt


@njit(cache=True)
def _tendon_hessian(kappa, rarm, ideal):  # pragma: no cover - numba
    """The elastic tendons' part of the KKT matrix, kappa_i R_i^T R_i per finger block
    (n, n): the same for every lane (zero for the ideal tendon)."""
    N, K = rarm.shape
    H = np.zeros((N * K, N * K))
    if not ideal:
        for i in range(N):
            for k in range(K):
                for k2 in range(K):
                    H[i * K + k, i * K + k2] = kappa[i] * rarm[i, k] * rarm[i, k2]
    return H


@njit(cache=True)
def _lane_loads(mu_all, fc_all, q, w, lmu, lfc):  # pragma: no cover - numba
    """Particle ``q``'s gravity loads into lane ``w``: its links' first moments (``mu_all``
    (P or 1, N, K)) and contact forces (``fc_all`` (P or 1, N, 3))."""
    N, K = lmu.shape[0], lmu.shape[1]
    pm = q if mu_all.shape[0] > 1 else 0
    pf = q if fc_all.shape[0] > 1 else 0
    for i in range(N):
        for k in range(K):
            lmu[i, k, w] = mu_all[pm, i, k]
        for r in range(3):
            lfc[i, r, w] = fc_all[pf, i, r]


@njit(cache=True, parallel=True)
def _move_kernel(
    theta0, s0, dl, a, L, kst, D2, pad, base, u, rarm, rest, kappa, pairs, mu_all, fc_all, gw, loaded,
    ideal, max_iter, loose_after, max_step, tol, max_substeps, theta, lam, T, s_out, ok, iters, resid, tasks,
):  # pragma: no cover - numba
    """Every particle's move (:func:`_move_lanes`) in ``tasks`` parallel tasks, task t
    taking particles t, t + tasks, t + 2 tasks, ... (see :func:`_move_tasks`)."""
    P = theta0.shape[0]
    for t in prange(tasks):
        _move_lanes(
            theta0, s0, dl, a, L, kst, D2, pad, base, u, rarm, rest, kappa, pairs, mu_all, fc_all, gw, loaded,
            ideal, max_iter, loose_after, max_step, tol, max_substeps, np.int64(t), P, tasks,
            theta, lam, T, s_out, ok, iters, resid,
        )


@njit(cache=True)
def _equilibrium_lanes(theta, a, L, kst, pad, base, u, rarm, rest, pairs, start, stop, T, lam, resid):  # pragma: no cover
    """Least-squares (T, lambda) with k (theta - theta0) - R^T T + G^T lambda = 0 for
    particles ``start:stop``: the kinematics LANES at a time, then each particle's ridge
    solve (:func:`_ridge_solve`); ``resid`` receives the residual norm (inf: singular)."""
    P, N, K = theta.shape
    m = pairs.shape[0]
    n = N * K
    nb = N + m
    W = LANES
    th = np.zeros((N, K, W))
    Ll = np.ones((N, K - 1, W))
    al = np.zeros((N, W))
    Pc, Jc, Hc = np.empty((N, 3, W)), np.empty((N, 3, K, W)), np.empty((N, 3, K, K, W))
    g, G, D2 = np.empty((m, W)), np.empty((m, n, W)), np.zeros((m, W))
    B, f0, M, rhs = np.zeros((n, nb)), np.empty(n), np.empty((nb, nb)), np.empty(nb)
    for b0 in range(start, stop, W):
        nw = min(W, stop - b0)
        for w in range(nw):
            p = b0 + w
            pl = p if L.shape[0] > 1 else 0
            for i in range(N):
                al[i, w] = a[p, i]
                for k in range(K):
                    th[i, k, w] = theta[p, i, k]
                for k in range(K - 1):
                    Ll[i, k, w] = L[pl, i, k]
        _fk_all(th, Ll, al, pad, base, u, Pc, Jc, Hc)
        _constraint_jacobian(Pc, Jc, pairs, D2, g, G)
        for w in range(nw):
            p = b0 + w
            pk = p if kst.shape[0] > 1 else 0
            pr = p if rest.shape[0] > 1 else 0
            for i in range(N):
                for k in range(K):
                    q = i * K + k
                    f0[q] = kst[pk, i, k] * (theta[p, i, k] - rest[pr, i, k])
                    B[q, i] = -rarm[i, k]
                    for c in range(m):
                        B[q, N + c] = G[c, q, w]
            if not _ridge_solve(B, f0, M, rhs):
                for i in range(N):
                    T[p, i] = 0.0
                for c in range(m):
                    lam[p, c] = 0.0
                resid[p] = np.inf
                continue
            for i in range(N):
                T[p, i] = rhs[i]
            for c in range(m):
                lam[p, c] = rhs[N + c]
            r2 = 0.0
            for q in range(n):
                v = f0[q]
                for c in range(nb):
                    v += B[q, c] * rhs[c]
                r2 += v * v
            resid[p] = np.sqrt(r2)


@njit(cache=True, parallel=True)
def _equilibrium_kernel(theta, a, L, kst, pad, base, u, rarm, rest, pairs, T, lam, resid):  # pragma: no cover
    """Least-squares (T, lambda) of every particle (:func:`_equilibrium_lanes`)."""
    P = theta.shape[0]
    chunk = 2048
    nchunks = (P + chunk - 1) // chunk
    for cc in prange(nchunks):
        start = np.int64(cc) * chunk
        _equilibrium_lanes(theta, a, L, kst, pad, base, u, rarm, rest, pairs, start, min(start + chunk, P), T, lam,
                           resid)


@njit(cache=True)
def _stability_lanes(theta, lam, ok, a, L, kst, pad, base, u, rarm, kappa, pairs, mu_all, fc_all, gw, loaded, ideal,
                     dependent, start, stop, stable):  # pragma: no cover - numba
    """:func:`_stability_kernel` for particles ``start:stop``, LANES at a time."""
    P, N, K = theta.shape
    n = N * K
    m = pairs.shape[0]
    nc = N if ideal else 0
    dim = n + m + nc
    W = LANES
    th = np.zeros((N, K, W))
    Ll = np.ones((N, K - 1, W))
    al = np.zeros((N, W))
    kl = np.ones((N, K, W))
    lm = np.zeros((m, W))
    lmu = np.zeros((N, K, W))
    lfc = np.zeros((N, 3, W))
    tau = np.zeros((N, K, W))
    dtau = np.zeros((N, K, K, W))
    sc1, sc2, sc3 = np.empty(W), np.empty(W), np.empty(W)
    Pc, Jc, Hc = np.empty((N, 3, W)), np.empty((N, 3, K, W)), np.empty((N, 3, K, K, W))
    g, G, D2 = np.empty((m, W)), np.empty((m, n, W)), np.zeros((m, W))
    A, A2, b = np.empty((dim, dim, W)), np.empty((dim, dim, W)), np.zeros((dim, W))
    A1 = np.empty((dim, dim))
    hscale, gscale = np.zeros(W), np.zeros(W)
    tiny1, tiny2 = np.zeros(W), np.zeros(W)
    bad = np.zeros(W, dtype=np.bool_)
    Hten = _tendon_hessian(kappa, rarm, ideal)
    for b0 in range(start, stop, W):
        nw = min(W, stop - b0)
        for w in range(W):
            p = b0 + w if w < nw else b0  # idle lanes compute on a valid particle, unused
            pl = p if L.shape[0] > 1 else 0
            pk = p if kst.shape[0] > 1 else 0
            for i in range(N):
                al[i, w] = a[p, i]
                for k in range(K):
                    th[i, k, w] = theta[p, i, k]
                    kl[i, k, w] = kst[pk, i, k]
                for k in range(K - 1):
                    Ll[i, k, w] = L[pl, i, k]
            for c in range(m):
                lm[c, w] = lam[p, c]
            if loaded:
                _lane_loads(mu_all, fc_all, p, w, lmu, lfc)
        _fk_all(th, Ll, al, pad, base, u, Pc, Jc, Hc)
        _constraint_jacobian(Pc, Jc, pairs, D2, g, G)
        if loaded:
            _load_lanes(th, Jc, Hc, lmu, gw, lfc, tau, dtau, sc1, sc2, sc3)
        _kkt_lanes(Pc, Jc, Hc, G, kl, Hten, rarm, lm, pairs, ideal, A, hscale, gscale, dtau, loaded)
        for w in range(W):
            bad[w] = False
            tiny1[w] = 1e-9 * hscale[w]
            tiny2[w] = 1e-9 * gscale[w] * gscale[w] / hscale[w]
        for q in range(dim):
            for q2 in range(q, dim):
                for w in range(W):
                    A2[q, q2, w] = A[q, q2, w]
        _lu_lanes(A, b, n, tiny1, tiny2, bad)  # A's diagonal: the reciprocal pivots
        for w in range(nw):
            p = b0 + w
            if not ok[p]:
                stable[p] = False
                continue
            if dependent:
                # a hand whose constraint gradients are dependent at every configuration (rank
                # r < m + nc: six or more fingers that all flex in planes square to the palm,
                # HandModel.constraints_dependent) has a zero eigenvalue whose round-off decided
                # a count of the negative ones, and a zero pivot that can hide above any
                # threshold. Its inertia is Z^T H Z's plus (r, r, m + nc - r), Z spanning the
                # wider tangent space (the hand has a mechanism the tendons do not fix), so a
                # strict minimum has exactly n positive eigenvalues whatever r is: counted on the
                # matrix scaled by congruence (which keeps the inertia) so that the joints' and
                # the constraints' blocks are both of order one and a tolerance can tell a zero
                # eigenvalue from a small one.
                for q in range(dim):
                    dq = 1.0 / np.sqrt(hscale[w]) if q < n else np.sqrt(hscale[w]) / gscale[w]
                    for q2 in range(q, dim):
                        dq2 = 1.0 / np.sqrt(hscale[w]) if q2 < n else np.sqrt(hscale[w]) / gscale[w]
                        A1[q, q2] = A2[q, q2, w] * dq * dq2
                        A1[q2, q] = A1[q, q2]
                ev = np.linalg.eigvalsh(A1)
                tol = 1e-9 * max(abs(ev[0]), abs(ev[dim - 1]))
                pos = 0
                for q in range(dim):
                    if ev[q] > tol:
                        pos += 1
                stable[p] = pos == n
                continue
            neg = 0
            if bad[w]:  # a small pivot: the eigenvalues of this lane's matrix instead
                # (a gradient that vanishes at one configuration, as the pair of the Model O's
                # side fingers at mirror-image grasps, keeps that pair's second-order hold on
                # the fingers: its zero eigenvalue is not counted, as the original tangent space)
                for q in range(dim):
                    for q2 in range(q, dim):
                        A1[q, q2] = A2[q, q2, w]
                        A1[q2, q] = A2[q, q2, w]
                ev = np.linalg.eigvalsh(A1)
                for q in range(dim):
                    if ev[q] < 0.0:
                        neg += 1
            else:
                for q in range(dim):
                    if A[q, q, w] < 0.0:
                        neg += 1
            stable[p] = neg == m + nc


@njit(cache=True, parallel=True)
def _stability_kernel(theta, lam, ok, a, L, kst, pad, base, u, rarm, kappa, pairs, mu_all, fc_all, gw, loaded, ideal,
                      dependent, stable):  # pragma: no cover - numba
    """Whether each particle's equilibrium is a strict constrained minimum of Eq. 9's energy
    (``stable`` (P,)), from the inertia of its KKT matrix [[H, G^T], [G, 0]] (H: the
    Hessian of the Lagrangian, with the elastic tendons' and the gravity loads' parts; G:
    the constraint gradients, with the ideal tendon's rows R): the reduced Hessian
    Z^T H Z is positive definite if and only if the KKT matrix has exactly as many negative
    eigenvalues as constraints (Gould 1985). The inertia is read off the pivots of the
    same elimination without pivoting as the Newton steps (Sylvester's law of inertia);
    a lane with a small pivot counts its matrix's negative eigenvalues instead, and every
    lane of a hand whose constraint gradients are ``dependent``
    (:attr:`HandModel.constraints_dependent`) the positive eigenvalues of its scaled matrix."""
    P = theta.shape[0]
    chunk = 2048
    nchunks = (P + chunk - 1) // chunk
    for cc in prange(nchunks):
        start = np.int64(cc) * chunk
        _stability_lanes(theta, lam, ok, a, L, kst, pad, base, u, rarm, kappa, pairs, mu_all, fc_all, gw, loaded,
                         ideal, dependent, start, min(start + chunk, P), stable)


# --------------------------------------------------------------------------------------
# Python API
# --------------------------------------------------------------------------------------


def contact_distances_sq(hand: HandModel, p: np.ndarray) -> np.ndarray:
    """Squared distances D_c^2 (P, m) of the constraint pairs, for contacts p (P, N, 3)."""
    p = np.ascontiguousarray(p, dtype=np.float64)
    if p.ndim != 3 or p.shape[1:] != (hand.N, 3):
        raise ValueError(f"contacts must have shape (P, {hand.N}, 3), got {p.shape}")
    out = np.empty((p.shape[0], hand.num_constraints))
    _distances_sq_kernel(p, hand.constraint_pairs, out)
    return out


@njit(cache=True)
def _distances_sq_kernel(p, pairs, out):  # pragma: no cover - numba
    for q in range(p.shape[0]):
        for c in range(pairs.shape[0]):
            i, j = pairs[c, 0], pairs[c, 1]
            d0 = p[q, i, 0] - p[q, j, 0]
            d1 = p[q, i, 1] - p[q, j, 1]
            d2 = p[q, i, 2] - p[q, j, 2]
            out[q, c] = d0 * d0 + d1 * d1 + d2 * d2


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
    bad = np.flatnonzero(~hand.within_tendon_range(l_new))
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


def _rest_angles(hand: HandModel, P: int, k: np.ndarray, external_torque) -> np.ndarray:
    """The springs' rest angles (1 or P, N, K) that carry a constant ``external_torque``
    (P or 1, N, K) [N m] at every joint: k (theta - theta0) - tau = k (theta - (theta0 + tau / k))."""
    if external_torque is None:
        return np.require(hand.rest_angles[None], np.float64, ["C", "W"])  # (one kernel type: as_particles)
    tau = as_particles("external_torque", external_torque, (P, hand.N, hand.K), allow_shared=True)
    if not np.all(np.isfinite(tau)):
        raise ValueError("'external_torque' must be finite")
    return np.ascontiguousarray(hand.rest_angles[None] + tau / k)


def _gravity_loads(hand: HandModel, P: int, L: np.ndarray, gravity, object_load):
    """The kernel's gravity loads (links' first moments (P or 1, N, K), contact forces (P or
    1, N, 3) [N], gravity in the finger planes (N, 2), loaded) for :func:`move`'s
    ``gravity`` and ``object_load``."""
    gw = None if gravity is None else hand.gravity_in_finger_planes(gravity)  # checks gravity first
    fc = _contact_forces(hand, P, gravity, object_load)
    if gw is None:
        return np.zeros((1, hand.N, hand.K)), fc, np.zeros((hand.N, 2)), False
    return np.ascontiguousarray(hand.link_moments(L)), fc, gw, True


def _contact_forces(hand: HandModel, P: int, gravity, object_load) -> np.ndarray:
    """The weight ``object_load_i * gravity`` carried at each contact, (P or 1, N, 3) [N]
    (zeros without an object load)."""
    if object_load is None:
        return np.zeros((1, hand.N, 3))
    if gravity is None:
        raise ValueError("'object_load' needs 'gravity' (the gravity in the palm frame [m/s^2])")
    load = as_particles("object_load", object_load, (P, hand.N), allow_shared=True)
    if np.any(load < 0):
        raise ValueError("'object_load' must be >= 0 [kg]")
    return np.ascontiguousarray(load[..., None] * np.asarray(gravity, float).reshape(3))


def gravity_torque(hand: HandModel, theta, *, a, gravity, object_load=None, link_lengths=None) -> np.ndarray:
    """The joint torques (P, N, K) [N m] of :func:`move`'s gravity loads at ``theta``: the
    links' weight (:meth:`HandModel.link_weight_torque`) and, with ``object_load`` (P or 1,
    N) [kg], the weight ``object_load_i * gravity`` carried at contact i
    (:func:`~vlr_drake.kinematics.contact_force_torque`)."""
    theta = _check_theta(hand, theta)
    P = theta.shape[0]
    L, _ = _hand_params(hand, P, link_lengths, None)
    fc = _contact_forces(hand, P, gravity, object_load)
    tau = hand.link_weight_torque(theta, gravity, L)
    if object_load is not None:
        tau = tau + contact_force_torque(hand, theta, a, fc, L)
    return tau


def _check_theta(hand: HandModel, theta) -> np.ndarray:
    theta = np.asarray(theta, float)
    if theta.ndim != 3 or theta.shape[1:] != (hand.N, hand.K):
        raise ValueError(f"'theta' must have shape (P, {hand.N}, {hand.K}), got {theta.shape}")
    return as_particles("theta", theta, theta.shape)


def _move_tasks(P: int) -> int:
    """Parallel tasks of a ``P``-particle move: one per thread, each taking every
    ``tasks``-th particle.

    A task's lanes go idle one by one at its end while its slowest particles finish (up
    to 30 Newton steps, four times over with the continuation), and every cycle costs all
    LANES lanes, so each task ends in a tail of mostly idle cycles: one task per thread
    has one tail per thread. Interleaved rather than contiguous shares, because after
    resampling a hypothesis' copies sit side by side, and a slow one's copies (a grasp
    near the mirror-image ones) would load one thread. A 60,000-particle move inside the
    filter (2 threads) took 75-95 ms over its first nine iterations (first: 98-137), against
    85-131 ms in contiguous tasks of 2,048 particles, 100-145 ms in 30 interleaved tasks.
    The results do not depend on the split (each lane runs its own particle)."""
    import numba

    return min(P, max(1, int(numba.get_num_threads())))  # 0 for no particles: nothing to run


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
    loose_after: int | None = None,
    max_step: float = MAX_STEP,
    max_substeps: int = 0,
    tolerance: str = "tight",
    external_torque=None,
    gravity=None,
    object_load=None,
    check_stability: bool = True,
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
        loose_after: after this many Newton steps a particle within the physical
            tolerances (``LOOSE_*``; angles within ~1e-5 rad of the solution) is accepted
            rather than iterated on to ``tolerance``; None (default), or any value from
            ``max_iter`` up, accepts it only at the cap.
            Only the particles at the Model O's mirror-image grasps, where a constraint's
            gradient vanishes and Newton converges linearly, and a few slow ones elsewhere
            get there; the filter stops them early (``FilterConfig.newton_loose_after``).
        max_substeps: a particle that fails with the whole action is retried with the
            action ramped in 4, 16, ... substeps up to this many (quasi-static continuation;
            0, the default, disables it: on 60,000 wide-prior particles it rescued 0.1% of
            them for 40% more time). Particles that fail keep their angles and ``ok = False``.
        tolerance: a key of :data:`TOLERANCES`: "tight" (default; the controller's
            finite differences need it) or "filter".
        external_torque: (P or 1, N, K) joint torques [N m] besides the tendons, springs
            and contacts (e.g. the links' weight, :meth:`~vlr_drake.hand.HandModel.link_weight_torque`),
            held constant through the move: the stationarity condition becomes
            ``k (theta - theta0) - tau - R^T kappa s' + G^T lambda = 0``. Default: none (Eq. 9).
        gravity: (3,) gravity in the palm frame [m/s^2], or None (Eq. 9, which neglects it):
            the links' weight (:meth:`~vlr_drake.hand.HandModel.link_weight_torque`, masses
            from the link lengths) joins the stationarity conditions as a load that follows
            the angles, with its derivative in the Newton matrix: the energy gains the
            links' potential V(theta).
        object_load: (P or 1, N) [kg], with ``gravity``: the object's weight carried at each
            contact, ``object_load_i * gravity`` applied at the contact (the pad's centre),
            likewise following the angles (the energy gains -sum_i f_i . p_i(theta)). A
            torque held constant instead (``external_torque`` evaluated before the move)
            misses the loads' stiffness, which for the object's weight is half the springs'.
        check_stability: whether to test each converged equilibrium for a constrained
            minimum (``MoveResult.stable``, :func:`stable_equilibria`); without it ``stable``
            repeats ``ok``.
    """
    if tendon not in TENDON_MODELS:
        raise ValueError(f"tendon model must be one of {TENDON_MODELS}, got '{tendon}'")
    if tolerance not in TOLERANCES:
        raise ValueError(f"Newton tolerance must be one of {tuple(TOLERANCES)}, got '{tolerance}'")
    if loose_after is not None and not is_count(loose_after, 1):
        raise ValueError(f"'loose_after' must be None or an integer >= 1, got {loose_after!r}")
    # (a review: max_iter -1 ran 5,392 iterations and 2.7 was cut to 2; a NaN step cap took
    # uncapped steps, and one <= 0 failed every hypothesis without a word)
    if not is_count(max_iter, 1):
        raise ValueError(f"'max_iter' must be an integer >= 1, got {max_iter!r}")
    if not is_count(max_substeps):  # (-3, 2.5, "4" and True had been taken)
        raise ValueError(f"'max_substeps' must be an integer >= 0, got {max_substeps!r}")
    if not (is_number(max_step) and 0 < max_step < np.inf):
        raise ValueError(f"'max_step' must be a positive finite angle [rad], got {max_step!r}")
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
    if np.any(D2 < 0):  # squared distances (every hypothesis had failed); 0, two contacts that
        # coincide, fails its own hypothesis alone (a degenerate draw must not stop a batch)
        raise ValueError(f"'D2' must be squared contact distances >= 0 [m^2], got {D2[np.any(D2 < 0, axis=1)][0]}")
    if stretch is None:
        if tendon == "elastic":
            raise ValueError("the elastic tendon model needs 'stretch' (see motion.equilibrium)")
        stretch = np.zeros((P, hand.N))
    s0 = as_particles("stretch", stretch, (P, hand.N))
    L, k = _hand_params(hand, P, link_lengths, stiffness)
    rest = _rest_angles(hand, P, k, external_torque)
    mu_all, fc_all, gw, loaded = _gravity_loads(hand, P, L, gravity, object_load)
    # prefilled with the inputs (the tension with NaN): a hypothesis the kernel does not write
    # keeps its angles, as a failed one does, never uninitialised memory
    out_theta = theta.copy()
    lam = np.zeros((P, hand.num_constraints))
    T = np.full((P, hand.N), np.nan)
    s_out = s0.copy()
    ok = np.zeros(P, dtype=np.bool_)
    iters = np.zeros(P, dtype=np.int64)
    resid = np.zeros((P, 3))
    _move_kernel(
        theta, s0, dl, a, L, k, D2, hand.pad, hand.base, hand.u, hand.moment_arms, rest,
        hand.kappa, hand.constraint_pairs, mu_all, fc_all, gw, loaded, tendon == "ideal", int(max_iter),
        int(max_iter if loose_after is None else min(loose_after, max_iter)), float(max_step),
        np.array(TOLERANCES[tolerance]), int(max_substeps), out_theta, lam, T, s_out, ok, iters, resid,
        _move_tasks(P),
    )
    ok &= np.isfinite(out_theta).all(axis=(1, 2)) & np.isfinite(T).all(axis=1) & np.isfinite(lam).all(axis=1)
    stable = ok.copy()
    if check_stability:
        _stability_kernel(out_theta, lam, ok, a, L, k, hand.pad, hand.base, hand.u, hand.moment_arms, hand.kappa,
                          hand.constraint_pairs, mu_all, fc_all, gw, loaded, tendon == "ideal",
                          hand.constraints_dependent, stable)
    return MoveResult(out_theta, s_out, T, lam, ok, iters, resid, stable)


def stable_equilibria(
    hand: HandModel, theta, multipliers, *, a, ok=None, link_lengths=None, stiffness=None, tendon: str = "elastic",
    gravity=None, object_load=None,
) -> np.ndarray:
    """(P,) True where the equilibrium at ``theta`` (P, N, K) with contact multipliers
    ``multipliers`` (P, m) (from :func:`move` or :func:`equilibrium`) is a strict
    constrained minimum of Eq. 9's energy: a grasp the hand can hold, rather than one it
    balances on (a saddle, from which the least disturbance moves it away).

    The test is the KKT matrix's inertia (Gould 1985; :func:`_stability_kernel`), which
    needs no null-space basis: it agrees with the reduced Hessian's smallest eigenvalue
    (``grasps.reduced_hessian_min_eig``) away from zero. ``ok`` (P,): where the
    equilibrium was found (default all); the others are reported unstable. The elastic
    tendons' stiffness and, with ``gravity`` (and ``object_load``), the gravity loads'
    stiffness (:func:`move`) are part of the energy; a constant ``external_torque`` adds none.
    """
    if tendon not in TENDON_MODELS:
        raise ValueError(f"tendon model must be one of {TENDON_MODELS}, got '{tendon}'")
    theta = _check_theta(hand, theta)
    P = theta.shape[0]
    ok = np.ones(P, dtype=np.bool_) if ok is None else np.require(np.broadcast_to(ok, (P,)), np.bool_, ["C", "W"])
    lam = np.asarray(multipliers, float)
    if lam.shape == (P, hand.num_constraints):  # (an equilibrium not found may carry NaN: it is not read)
        lam = np.where(ok[:, None], lam, 0.0)
    lam = as_particles("multipliers", lam, (P, hand.num_constraints))
    a = as_particles("a", a, (P, hand.N))
    L, k = _hand_params(hand, P, link_lengths, stiffness)
    mu_all, fc_all, gw, loaded = _gravity_loads(hand, P, L, gravity, object_load)
    stable = np.empty(P, dtype=np.bool_)
    _stability_kernel(theta, lam, ok, a, L, k, hand.pad, hand.base, hand.u,
                      hand.moment_arms, hand.kappa, hand.constraint_pairs, mu_all, fc_all, gw, loaded,
                      tendon == "ideal", hand.constraints_dependent, stable)
    return stable


def equilibrium(
    hand: HandModel, theta, *, a, link_lengths=None, stiffness=None, settle: bool | None = None, external_torque=None,
    gravity=None, object_load=None,
) -> Equilibrium:
    """Tendon stretch and tension that hold the grasp at ``theta`` (DESIGN.md section 4b).

    Solves the stationarity conditions ``k (theta - theta0) - R^T T + G^T lambda = 0`` for
    (T, lambda). For the Model O (N*K = N + m) this is square: almost every grasp
    configuration is an equilibrium for exactly one tendon state. Not at the mirror-image
    grasps, where a column of the system vanishes and no tension state balances the springs:
    there ``ok`` is reported although the stationarity residual is up to 9e-3 N m (a review,
    2026-12-06: 11 of 20,000 sampled NH3 grasps above 1e-6 N m). ``residual`` says how far
    each is from one: the prior keeps such draws (refusing them would refuse the mirror
    pose itself, :func:`_ridge_solve`), and a hypothesis' first move settles it. For hands with more
    joints (N*K > N + m) the least-squares tension is used and, with ``settle`` (default for
    such hands), the elastic model with a zero action moves the angles to the nearest true
    equilibrium, which is returned as ``theta``. ``external_torque`` (P or 1, N, K) [N m]:
    further joint torques, as in :func:`move` (``k (theta - theta0) - tau - R^T T + G^T lambda = 0``).
    ``gravity`` and ``object_load``: the gravity loads of :func:`move`, at ``theta``
    (:func:`gravity_torque`), and through the settling move.
    """
    theta = _check_theta(hand, theta)
    P = theta.shape[0]
    a = as_particles("a", a, (P, hand.N))
    L, k = _hand_params(hand, P, link_lengths, stiffness)
    tau = external_torque
    if gravity is not None:
        tau = gravity_torque(hand, theta, a=a, gravity=gravity, object_load=object_load, link_lengths=L)
        if external_torque is not None:
            tau = tau + external_torque
    elif object_load is not None:
        raise ValueError("'object_load' needs 'gravity' (the gravity in the palm frame [m/s^2])")
    rest = _rest_angles(hand, P, k, tau)
    T = np.empty((P, hand.N))
    lam = np.empty((P, hand.num_constraints))
    resid = np.empty(P)
    _equilibrium_kernel(
        theta, a, L, k, hand.pad, hand.base, hand.u, hand.moment_arms, rest,
        hand.constraint_pairs, T, lam, resid,
    )
    ok = np.isfinite(resid)
    if settle is None:
        settle = not hand.statically_determinate
    stretch = np.where(ok[:, None], T / hand.kappa, 0.0)
    if not settle:
        return Equilibrium(theta.copy(), stretch, np.where(ok[:, None], T, 0.0), np.nan_to_num(lam), ok, resid)
    p = contacts(hand, theta, a, L)
    res = move(
        hand, theta, np.zeros(hand.N), a=a, D2=contact_distances_sq(hand, p), stretch=stretch,
        link_lengths=L, stiffness=k, tendon="elastic", external_torque=external_torque, gravity=gravity,
        object_load=object_load, check_stability=False,  # (an Equilibrium does not say; stable_equilibria does)
    )
    return Equilibrium(res.theta, res.stretch, res.tension, res.multipliers, ok & res.ok,
                       np.where(ok & res.ok, res.residuals[:, 0], np.inf))
