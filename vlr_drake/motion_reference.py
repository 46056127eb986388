"""Reference motion function: Eq. 9 as a Drake MathematicalProgram, one configuration.

The same problem as :func:`vlr_drake.motion.move`, written as an optimisation and handed to
IPOPT or SNOPT (both ship with the drake wheel), warm-started from the current angles:

    elastic:  min_theta  sum 0.5 k (theta - theta0)^2 - tau . theta + sum_i 0.5 kappa_i s_i'^2
              s.t.       0.5 (|p_i - p_j|^2 - D_ij^2) = 0              (Eq. 8)
              with       s_i' = s_i + dl_i - R_i (theta - theta_prev)
    ideal:    min_theta  sum 0.5 k (theta - theta0)^2 - tau . theta
              s.t.       Eq. 8 and R (theta - theta_prev) = dl          (Eq. 7)

(tau: constant external joint torques, ``external_torque``; zero in Eq. 9.)

It is slow (milliseconds) and used where one answer is needed with certainty: the tests
that hold the batched Newton solver to it, the benchmark, and checks in the controller.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from pydrake.solvers import IpoptSolver, MathematicalProgram, SnoptSolver, SolverOptions

from vlr_drake.hand import HandModel
from vlr_drake.kinematics import is_number
from vlr_drake.motion import TENDON_MODELS, equilibrium

__all__ = ["MotionSolveError", "ReferenceResult", "solve_move", "SOLVERS"]

SOLVERS = ("ipopt", "snopt")


#: Scale of the cost (energies are ~1e-2 J) and of the squared-distance constraints (~1e-3 m^2).
COST_SCALE = 1e3
CONSTRAINT_SCALE = 1e3


class MotionSolveError(RuntimeError):
    """The MathematicalProgram solver did not find a solution."""


@dataclass
class ReferenceResult:
    theta: np.ndarray  # (N, K)
    tension: np.ndarray  # (N,)
    solver: str
    solve_time_s: float


def _values(name: str, value, shape: tuple) -> np.ndarray:
    """``value`` as a finite array of ``shape`` (any array of that many values), or a
    ValueError naming it (a wrong size had failed in numpy's reshape, a NaN as a solver
    failure, and a NaN ``local_range`` had aborted the process in Drake; a ragged or
    non-numeric one in numpy's own words)."""
    try:
        x = np.asarray(value, float)
    except (TypeError, ValueError):
        raise ValueError(f"'{name}' must be numbers of shape {shape}, got {value!r}") from None
    if x.size != int(np.prod(shape)):
        raise ValueError(f"'{name}' must have shape {shape}, got {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"'{name}' contains NaN or infinite values")
    return x.reshape(shape)


def _contact_expressions(hand: HandModel, x, a, L):
    """Symbolic contact points (N x 3 list) for decision variables x (N*K,)."""
    from pydrake.symbolic import cos, sin

    N, K = hand.N, hand.K
    pts = []
    for i in range(N):
        phi = 0
        sx = 0
        sz = 0
        for k in range(K):
            phi = phi + x[i * K + k]
            if k < K - 1:
                ell, psi = L[i, k], phi
            else:
                ell = float(np.hypot(a[i], hand.pad[i]))
                psi = phi + float(np.arctan2(hand.pad[i], a[i]))
            sx = sx + ell * sin(psi)
            sz = sz + ell * cos(psi)
        b, u = hand.base[i], hand.u[i]
        pts.append([b[0] + sx * u[0], b[1] + sx * u[1], b[2] + sz])
    return pts


def solve_move(
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
    solver: str = "ipopt",
    tolerance: float = 1e-12,
    local_range: float = 0.3,
    external_torque=None,
    gravity=None,
    object_load=None,
) -> ReferenceResult:
    """Solve Eq. 9 for one configuration (no particle axis): theta (N, K), dl (N,), a (N,),
    D2 (m,), stretch (N,), external_torque (N, K) [N m] or None; ``gravity`` (3,) [m/s^2]
    and ``object_load`` (N,) [kg]: the gravity loads of :func:`vlr_drake.motion.move`, as
    their potential (the links' -sum_l mu_l (g_u sin phi_l + g_z cos phi_l) per finger, the
    contacts' -sum_i m_i g . p_i). Raises :class:`MotionSolveError` if the solver fails, a
    ValueError naming an input that is misshapen, not finite or not physical."""
    if tendon not in TENDON_MODELS:
        raise ValueError(f"tendon model must be one of {TENDON_MODELS}, got '{tendon}'")
    if solver not in SOLVERS:
        raise ValueError(f"solver must be one of {SOLVERS}, got '{solver}'")
    for name, value in (("tolerance", tolerance), ("local_range", local_range)):
        if not (is_number(value) and 0 < value < np.inf):
            raise ValueError(f"'{name}' must be a positive finite number, got {value!r}")
    N, K = hand.N, hand.K
    theta0 = _values("theta", theta, (N, K))
    if np.shape(theta) != (N, K):
        raise ValueError(f"'theta' must have shape ({N}, {K}), got {np.shape(theta)}")
    dl = _values("dl", dl, (N,))
    a = _values("a", a, (N,))
    D2 = _values("D2", D2, (hand.num_constraints,))
    if np.any(D2 < 0):
        raise ValueError(f"'D2' must be squared contact distances >= 0 [m^2], got {D2.tolist()}")
    L = hand.link_lengths if link_lengths is None else _values("link_lengths", link_lengths, (N, K - 1))
    k = hand.stiffness if stiffness is None else _values("stiffness", stiffness, (N, K))
    if np.any(L <= 0) or np.any(k <= 0):  # as motion.move refuses them
        raise ValueError("'link_lengths' and 'stiffness' must be positive")
    if external_torque is not None:
        external_torque = _values("external_torque", external_torque, (N, K))
    if gravity is not None:
        gravity = _values("gravity", gravity, (3,))
    if object_load is not None:  # as motion.move refuses them (a load without gravity had been ignored)
        if gravity is None:
            raise ValueError("'object_load' needs 'gravity' (the gravity in the palm frame [m/s^2])")
        object_load = _values("object_load", object_load, (N,))
        if np.any(object_load < 0):
            raise ValueError("'object_load' must be >= 0 [kg]")
    if tendon == "elastic":
        if stretch is None:
            raise ValueError("the elastic tendon model needs 'stretch'")
        s0 = _values("stretch", stretch, (N,))

    prog = MathematicalProgram()
    x = prog.NewContinuousVariables(N * K, "theta")
    kf = k.ravel()
    rest = hand.rest_angles.ravel()
    R = hand.R
    # Spring energy (Eq. 6) as a quadratic cost.
    # Energies are millijoules: scale the cost (not the solution) so that the solvers'
    # relative optimality tolerances bite at the 1e-8 rad level.
    cs = COST_SCALE
    prog.AddQuadraticCost(cs * np.diag(kf), -cs * kf * rest, 0.5 * cs * float(kf @ rest**2), x, is_convex=True)
    if external_torque is not None:  # the potential of constant joint torques: -tau . theta
        tau = np.asarray(external_torque, float).reshape(N * K)
        prog.AddLinearCost(-cs * tau, 0.0, x)
    if tendon == "elastic":
        # 0.5 kappa (s0 + dl - R (x - theta0))^2 = 0.5 x^T Q x + b^T x + c
        c0 = s0 + dl + R @ theta0.ravel()  # s' = c0 - R x
        Q = R.T @ np.diag(hand.kappa) @ R
        b = -R.T @ (hand.kappa * c0)
        prog.AddQuadraticCost(cs * Q, cs * b, 0.5 * cs * float(hand.kappa @ c0**2), x, is_convex=True)
    else:
        prog.AddLinearEqualityConstraint(R, R @ theta0.ravel() + dl, x)
    pts = _contact_expressions(hand, x, a, L)
    if gravity is not None:  # the gravity loads' potential
        from pydrake.symbolic import cos, sin

        mu = hand.link_moments(L[None])[0]
        gw = hand.gravity_in_finger_planes(gravity)
        V = 0.0
        for i in range(N):
            phi = 0.0
            for kk in range(K):
                phi = phi + x[i * K + kk]
                V = V - mu[i, kk] * (gw[i, 0] * sin(phi) + gw[i, 1] * cos(phi))
        if object_load is not None:
            g = np.asarray(gravity, float).reshape(3)
            load = np.asarray(object_load, float).reshape(N)
            for i in range(N):
                V = V - load[i] * sum(g[r] * pts[i][r] for r in range(3))
        prog.AddCost(cs * V)
    for c, (i, j) in enumerate(hand.constraint_pairs):
        d = [pts[i][r] - pts[j][r] for r in range(3)]
        expr = CONSTRAINT_SCALE * (0.5 * (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) - 0.5 * D2[c])
        prog.AddConstraint(expr, 0.0, 0.0)
    # Eq. 9 is a local motion model (contacts held fixed under local motions): keep the
    # search within a box around the current angles so the solver cannot jump to a far
    # minimum of the same energy.
    prog.AddBoundingBoxConstraint(theta0.ravel() - local_range, theta0.ravel() + local_range, x)
    prog.SetInitialGuess(x, theta0.ravel())

    s = IpoptSolver() if solver == "ipopt" else SnoptSolver()
    if not s.available() or not s.enabled():
        raise MotionSolveError(f"solver '{solver}' is not available in this drake build")
    guess = theta0.ravel()
    t_start = time.perf_counter()
    for attempt in range(2):
        options = SolverOptions()
        if solver == "ipopt":
            options.SetOption(s.solver_id(), "tol", tolerance)
            options.SetOption(s.solver_id(), "constr_viol_tol", tolerance)
            options.SetOption(s.solver_id(), "print_level", 0)
        else:
            # SNOPT's tolerances are relative, and it stops with "current point cannot be
            # improved" when asked for more than round-off allows: first 1e-10 (angles to
            # ~1e-8 rad), then, if that stalls, 1e-9 from where it stopped.
            opt = max(tolerance, 1e-10 if attempt == 0 else 1e-9)
            options.SetOption(s.solver_id(), "Major optimality tolerance", opt)
            options.SetOption(s.solver_id(), "Major feasibility tolerance", max(tolerance, 1e-10))
        result = s.Solve(prog, guess, options)
        if result.is_success() or solver == "ipopt":
            break
        guess = result.GetSolution(x)
    elapsed = time.perf_counter() - t_start
    if not result.is_success():
        raise MotionSolveError(
            f"{solver} failed on the motion problem (Eq. 9, {tendon} tendon): {result.get_solution_result()}"
        )
    th = result.GetSolution(x).reshape(N, K)
    reach = float(np.max(np.abs(th - theta0)))
    if reach >= local_range - 1e-6:  # a solver "succeeds" on the box's face: no equilibrium there
        raise MotionSolveError(
            f"{solver} stopped on the local search box (a joint moved {reach:.4f} rad, the box is +-{local_range} rad): "
            f"the nearest minimum of Eq. 9 lies further; no equilibrium within the box")
    if tendon == "elastic":
        T = hand.kappa * (s0 + dl - R @ (th - theta0).ravel())
    else:
        # The tension is the multiplier of the tendon equation; recover it from the
        # stationarity conditions at the solution (exact there).
        tau = None if external_torque is None else np.asarray(external_torque, float).reshape(1, N, K)
        load = None if object_load is None else np.asarray(object_load, float).reshape(1, N)
        T = equilibrium(hand, th[None], a=a[None], link_lengths=L[None], stiffness=k[None], settle=False,
                        external_torque=tau, gravity=gravity, object_load=load).tension[0]
    return ReferenceResult(th, T, solver, elapsed)
