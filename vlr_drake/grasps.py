"""Grasp configurations: physical checks and sampling of hand-object hypotheses.

A VLR configuration (theta, a) is a *physical* grasp when (DESIGN.md sections 4 and 6)
- the tendons only pull: the implied tension T >= 0 (:func:`vlr_drake.motion.equilibrium`);
- the fingers squeeze the object: their forces on it are a superposition of pairwise
  squeezes (:func:`squeezes`; for up to four fingers, every contact-pair multiplier
  lambda < 0);
- and, for a strict check, the equilibrium is a constrained *minimum* of the energy of
  Eq. 9: the Hessian of the Lagrangian reduced to the tangent space of the grasp manifold
  is positive definite (:func:`reduced_hessian_min_eig`).

The last condition is worth a word. With contacts pinned to the object (the VLR's fixed
E^C links), a squeezed object acts as a set of compressed struts between the fingertips,
and a strong squeeze makes the stationary point a saddle (a strut under compression
buckles). Newton's method tracks stationary points either way, so the motion function
is defined for both; tests that compare against an optimiser use stable grasps.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from vlr_drake import kinematics, motion
from vlr_drake.hand import HandModel
from vlr_drake.kinematics import is_count, is_number

__all__ = ["GraspSample", "sample_grasps", "squeezes", "all_pairs", "constraint_gradients", "reduced_hessian_min_eig",
           "lagrangian_hessian", "commanded_equilibrium", "settle_under_command"]


def all_pairs(n: int) -> np.ndarray:
    """Every pair (i, j), i < j, of ``n`` contacts (n (n - 1) / 2 x 2)."""
    return np.array([(i, j) for i in range(n) for j in range(i + 1, n)], dtype=np.int64).reshape(-1, 2)


def _kinematics(hand: HandModel, theta, a, pairs, link_lengths=None):
    """Contacts Pc (P, N, 3), their Jacobians Jc (P, N, 3, K) and second derivatives Hc
    (P, N, 3, K, K), and the gradients G (P, m, N*K) of g_c = 0.5 |p_i - p_j|^2 for the
    contact ``pairs`` (m x 2), of each configuration ``theta`` (P, N, K) with contacts ``a``
    (P, N): the batched kernels' quantities, particles first."""
    theta = np.asarray(theta, float).reshape(-1, hand.N, hand.K)
    P, N, K = theta.shape[0], hand.N, hand.K
    L = hand.link_lengths if link_lengths is None else np.asarray(link_lengths, float)
    L = np.broadcast_to(np.reshape(L, (-1, N, K - 1)), (P, N, K - 1))
    pairs = np.ascontiguousarray(pairs, dtype=np.int64)
    Pc, Jc, Hc = np.empty((N, 3, P)), np.empty((N, 3, K, P)), np.empty((N, 3, K, K, P))
    motion._fk_all(np.ascontiguousarray(np.moveaxis(theta, 0, -1)), np.ascontiguousarray(np.moveaxis(L, 0, -1)),
                   np.ascontiguousarray(np.broadcast_to(np.asarray(a, float), (P, N)).T), hand.pad, hand.base, hand.u,
                   Pc, Jc, Hc)
    g, G = np.empty((len(pairs), P)), np.empty((len(pairs), N * K, P))
    motion._constraint_jacobian(Pc, Jc, pairs, np.zeros((len(pairs), P)), g, G)
    return tuple(np.moveaxis(x, -1, 0) for x in (Pc, Jc, Hc, G))


def constraint_gradients(hand: HandModel, theta, a, pairs, link_lengths=None) -> np.ndarray:
    """Gradients (P, m, N*K) of g_c = 0.5 |p_i - p_j|^2 over joint angles, for the contact
    ``pairs`` (m x 2) of each configuration ``theta`` (P, N, K) with contacts ``a`` (P, N)
    (the rows of G in Eq. 9's stationarity conditions, for any set of pairs)."""
    return _kinematics(hand, theta, a, pairs, link_lengths)[3]


def squeezes(hand: HandModel, theta, a, multipliers, link_lengths=None, tol: float = 1e-9) -> np.ndarray:
    """(P,) whether the fingers squeeze the object at equilibria ``theta`` (P, N, K) with
    contacts ``a`` (P, N) and the grasp's contact-pair ``multipliers`` (P, m)
    (:attr:`HandModel.constraint_pairs`; lambda < 0 pushes the pair's contacts together).

    The fingers' forces on the object enter Eq. 9 as the joint torques G^T lambda. They
    squeeze it when the same torques come from pushing every pair of contacts together:
    some mu <= 0 over *all* contact pairs with G_all^T mu = G^T lambda. Up to four fingers
    the hand constrains every pair and this is lambda < 0 on each. With five or more the
    hand constrains 3N - 6 of them (a rigid framework), the multipliers depend on which, and
    a grasp that squeezes can have one lambda > 0 (a review found no grasp of
    ``generic_hand(6, 3)`` passing lambda < 0 in 300,000 draws); the squeeze is then
    sought as a linear programme over all pairs, with pair forces that leave the joints'
    torques unchanged (force along a finger's hinge axis, which its joints carry). ``tol``:
    the least squeeze the linear programme accepts, relative to the largest |lambda| (five or
    more fingers only: with every pair constrained the test is lambda < 0, without a margin).
    """
    lam = np.asarray(multipliers, float).reshape(-1, hand.num_constraints)
    strict = np.all(lam < 0, axis=1)
    N = hand.N
    if hand.num_constraints == N * (N - 1) // 2:  # every pair constrained: the multipliers are the squeeze
        return strict
    theta = np.asarray(theta, float).reshape(-1, N, hand.K)
    a = np.broadcast_to(np.asarray(a, float), (theta.shape[0], N))
    pairs = all_pairs(N)
    out = strict.copy()
    todo = np.flatnonzero(~strict & np.all(np.isfinite(lam), axis=1))
    if not todo.size:
        return out
    L = None if link_lengths is None else np.broadcast_to(
        np.reshape(np.asarray(link_lengths, float), (-1, N, hand.K - 1)), (theta.shape[0], N, hand.K - 1))[todo]
    G_all = constraint_gradients(hand, theta[todo], a[todo], pairs, L)
    # the hand's pairs among all of them: their gradients are those rows
    rows = [int(np.flatnonzero((pairs == pr).all(axis=1))[0]) for pr in hand.constraint_pairs]
    for q, p in enumerate(todo):
        scale = np.abs(lam[p]).max()
        if scale > 0:
            out[p] = _best_squeeze(G_all[q].T, G_all[q, rows].T @ (lam[p] / scale)) > tol
    return out


def _best_squeeze(A: np.ndarray, b: np.ndarray) -> float:
    """max t subject to mu_c + t <= 0 for every pair c and A mu = b (t capped at 1): how
    hard the gentlest pair can push while the pair forces mu give the joint torques b.
    Solved in the null space of A (mu = mu0 + Z y): in closed form where it is at most one
    dimension (five fingers), else by a linear programme."""
    U, S, Vt = np.linalg.svd(A)
    r = int(np.sum(S > 1e-10 * S[0]))
    mu0 = Vt[:r].T @ ((U[:, :r].T @ b) / S[:r])
    if np.linalg.norm(A @ mu0 - b) > 1e-8 * max(1.0, np.linalg.norm(b)):
        return -np.inf  # these torques are no pair forces at all
    Z = Vt[r:].T
    if Z.shape[1] == 0:
        return min(1.0, float(-mu0.max()))
    if Z.shape[1] == 1:  # t(y) = min_c (-mu0_c - z_c y), a concave envelope of lines
        z = Z[:, 0]
        flat = np.abs(z) <= 1e-12
        cap = min(1.0, float(-mu0[flat].max())) if flat.any() else 1.0
        up, down = z < -1e-12, z > 1e-12
        if not up.any() or not down.any():
            return cap  # y can move every non-flat pair as far into a push as wanted
        # the envelope peaks where a rising line crosses a falling one
        ya = (mu0[up][:, None] - mu0[down][None, :]) / (z[down][None, :] - z[up][:, None])
        y = ya.ravel()
        t = np.min(-mu0[:, None] - z[:, None] * y[None, :], axis=0)
        return min(cap, float(t.max()))
    from scipy.optimize import linprog  # (two or more free dimensions: six or more fingers)

    n = A.shape[1]
    c = np.zeros(n + 1)
    c[-1] = -1.0
    res = linprog(c, A_ub=np.hstack([np.eye(n), np.ones((n, 1))]), b_ub=np.zeros(n),
                  A_eq=np.hstack([A, np.zeros((A.shape[0], 1))]), b_eq=b,
                  bounds=[(None, None)] * n + [(None, 1.0)], method="highs")
    return float(-res.fun) if res.status == 0 else -np.inf


def lagrangian_hessian(hand: HandModel, theta, a, multipliers, link_lengths=None, stiffness=None, tendon="elastic"):
    """Hessian of the Lagrangian of Eq. 9 and the constraint Jacobian, for one configuration.

    Returns (H (n, n), G (m, n)) with n = N*K.
    """
    if tendon not in motion.TENDON_MODELS:
        raise ValueError(f"tendon model must be one of {motion.TENDON_MODELS}, got '{tendon}'")
    N, K = hand.N, hand.K
    k = hand.stiffness if stiffness is None else np.asarray(stiffness).reshape(N, K)
    Pc, Jc, Hc, G = (x[0] for x in _kinematics(hand, np.reshape(theta, (1, N, K)), np.reshape(a, (1, N)),
                                               hand.constraint_pairs, link_lengths))
    H = np.diag(k.ravel()).astype(float)
    if tendon == "elastic":
        H += hand.R.T @ np.diag(hand.kappa) @ hand.R
    for c, (i, j) in enumerate(hand.constraint_pairs):
        Jd = np.zeros((3, N * K))
        Jd[:, i * K : (i + 1) * K] = Jc[i]
        Jd[:, j * K : (j + 1) * K] -= Jc[j]
        Hg = Jd.T @ Jd
        dp = Pc[i] - Pc[j]
        Hg[i * K : (i + 1) * K, i * K : (i + 1) * K] += np.einsum("r,rkl->kl", dp, Hc[i])
        Hg[j * K : (j + 1) * K, j * K : (j + 1) * K] -= np.einsum("r,rkl->kl", dp, Hc[j])
        H += multipliers[c] * Hg
    return H, G


def reduced_hessian_min_eig(hand: HandModel, theta, a, multipliers, link_lengths=None, stiffness=None,
                            tendon="elastic") -> np.ndarray:
    """Smallest eigenvalue of the reduced Hessian, per particle (P,) [N m/rad], of the
    configurations ``theta`` (P, N, K) with contacts ``a`` (P, N), ``multipliers`` (P, m)
    and, where given, per-particle ``link_lengths`` (P or 1, N, K-1) and ``stiffness``
    (P or 1, N, K).

    Positive: the configuration is a strict constrained minimum of Eq. 9's energy.
    For the ideal tendon the tangent space also keeps the tendon lengths fixed. Where the
    constraints' gradients are dependent at every configuration
    (:attr:`HandModel.constraints_dependent`) the tangent space is wider and the
    multipliers are not unique: the test is then for the ``multipliers`` given.
    """
    theta = np.asarray(theta, float)
    P = theta.shape[0]
    N, K = hand.N, hand.K
    # (the hand's own (N, K) stiffness had been indexed by particle: a row of it, then a
    # numpy reshape error)
    if link_lengths is not None:
        link_lengths = kinematics.as_particles("link_lengths", link_lengths, (P, N, K - 1), allow_shared=True)
    if stiffness is not None:
        stiffness = kinematics.as_particles("stiffness", stiffness, (P, N, K), allow_shared=True)
    out = np.empty(P)
    for p in range(P):
        L = None if link_lengths is None else link_lengths[min(p, len(link_lengths) - 1)]
        k = None if stiffness is None else stiffness[min(p, len(stiffness) - 1)]
        H, G = lagrangian_hessian(hand, theta[p], np.asarray(a)[p], np.asarray(multipliers)[p], L, k, tendon)
        A = G if tendon == "elastic" else np.vstack([G, hand.R])
        _, S, Vt = np.linalg.svd(A)
        # the tangent space is the null space of the constraints' gradients: of their rank
        # where they are dependent at every configuration (a mechanism the tendons do not
        # fix: HandModel.constraints_dependent), of their number otherwise (a gradient that
        # vanishes at one configuration, as at the Model O's mirror-image grasps, still holds)
        r = int(np.sum(S > 1e-10 * S[0])) if hand.constraints_dependent else A.shape[0]
        Z = Vt[r:].T
        out[p] = np.linalg.eigvalsh(Z.T @ H @ Z).min() if Z.shape[1] else np.inf
    return out


@dataclass
class GraspSample:
    """Physical grasp configurations (P of them) with their tendon state."""

    theta: np.ndarray  # (P, N, K)
    a: np.ndarray  # (P, N)
    stretch: np.ndarray  # (P, N)
    tension: np.ndarray  # (P, N)
    multipliers: np.ndarray  # (P, m)
    D2: np.ndarray  # (P, m)


#: Largest stationarity residual [N m] of a sampled grasp's equilibrium, a hundredth of the
#: springs' smallest torques (0.01-0.06 N m): sampled grasps solve to 3e-8 (Model O) and
#: 6e-8 (NH3) at the 99th percentile, 4e-6 at most on the Model O in 20,000; near the
#: mirror images the regularised solve left NH3 draws at 6.5e-3 and a Model O truth grasp
#: (identify's seed 2) at 0.029. Not applied where the hand's constraint gradients are
#: dependent (six fingers and more), whose equilibria keep a least-squares residual.
EQUILIBRIUM_RESIDUAL = 1e-4


def sample_grasps(
    hand: HandModel,
    rng: np.random.Generator,
    count: int,
    *,
    proximal_range=(-0.1, 0.6),
    distal_range=(0.0, 1.2),
    contact_range=(0.015, 0.04),
    min_tension: float = 0.5,
    stable: bool = False,
    min_stability: float = 1e-3,
    max_tension: float = np.inf,
    max_draws: int = 2_000_000,
    in_tendon_range: bool = False,
) -> GraspSample:
    """Draw ``count`` physical grasps by rejection from uniform angle and contact ranges.

    Proximal joints (the first) in ``proximal_range``, the others in ``distal_range`` split
    evenly over the K-1 distal joints, contacts along the last link in ``contact_range``.
    Kept: an equilibrium (its stationarity residual at most :data:`EQUILIBRIUM_RESIDUAL`
    where the hand's constraints are independent),
    tension >= ``min_tension`` [N] on every tendon, a squeeze (:func:`squeezes`),
    at most ``max_tension``, joints within their limits, contacts on the last links, with
    ``in_tendon_range`` tendon commands within their range (a grasp a real hand can hold;
    the motion tests' abstract grasps need not), and with ``stable`` a strict constrained minimum whose
    reduced Hessian's smallest eigenvalue exceeds ``min_stability`` [N m/rad] (a margin
    keeps the grasp away from folds where small actions snap it). Raises if too few are
    found.
    """
    if not is_count(count, 1):
        raise ValueError(f"'count' must be an integer >= 1, got {count!r}")
    for name, (lo, hi) in (("proximal_range", proximal_range), ("distal_range", distal_range),
                           ("contact_range", contact_range)):
        if not (np.isfinite(lo) and np.isfinite(hi) and lo <= hi):
            raise ValueError(f"'{name}' must be finite (low, high) with low <= high, got {(lo, hi)}")
    if contact_range[0] < 0:
        raise ValueError(f"'contact_range' must lie on the last links (>= 0 m), got {contact_range}")
    # (a NaN bound, or a maximum tension below the minimum, had kept nothing: max_draws draws,
    # 2,000,000 by default, then an error that asked for wider ranges)
    for name, value in (("min_tension", min_tension), ("max_tension", max_tension), ("min_stability", min_stability)):
        if not (is_number(value) and not np.isnan(value)):
            raise ValueError(f"'{name}' must be a number, got {value!r}")
        if value < 0:  # (a negative one had let pushing tendons or saddles through as physical: a review)
            raise ValueError(f"'{name}' must be >= 0, got {value!r}")
    if max_tension < min_tension:
        raise ValueError(f"'max_tension' ({max_tension}) must be >= 'min_tension' ({min_tension}) [N]")
    if not is_count(max_draws, 1):
        raise ValueError(f"'max_draws' must be an integer >= 1, got {max_draws!r}")
    N, K = hand.N, hand.K
    kept: list[tuple] = []
    total = 0
    drawn = 0
    batch = max(4 * count, 4096)
    while total < count:
        if drawn >= max_draws:
            raise RuntimeError(f"found only {total} of {count} physical grasps in {drawn} draws; widen the ranges")
        th = np.empty((batch, N, K))
        th[..., 0] = rng.uniform(*proximal_range, (batch, N))
        th[..., 1:] = rng.uniform(*distal_range, (batch, N, K - 1)) / (K - 1)
        a = rng.uniform(*contact_range, (batch, N))
        drawn += batch
        eq = motion.equilibrium(hand, th, a=a)
        good = (eq.ok & ((eq.residual <= EQUILIBRIUM_RESIDUAL) | hand.constraints_dependent)
                & np.all(eq.tension >= min_tension, axis=1) & np.all(eq.tension <= max_tension, axis=1)
                & hand.within_joint_limits(eq.theta) & np.all(a <= hand.distal_length, axis=1))
        if in_tendon_range:
            good &= hand.within_tendon_range(hand.tendon_travel(eq.theta) + eq.stretch).all(axis=1)
        idx = np.flatnonzero(good)
        if idx.size:
            idx = idx[squeezes(hand, eq.theta[idx], a[idx], eq.multipliers[idx])]
        if stable and idx.size:
            eig = reduced_hessian_min_eig(hand, eq.theta[idx], a[idx], eq.multipliers[idx])
            idx = idx[eig > min_stability]
        if idx.size:
            th_eq = eq.theta[idx]
            D2 = motion.contact_distances_sq(hand, kinematics.contacts(hand, th_eq, a[idx]))
            kept.append((th_eq, a[idx], eq.stretch[idx], eq.tension[idx], eq.multipliers[idx], D2))
            total += idx.size
    cat = [np.concatenate([k[i] for k in kept])[:count] for i in range(6)]
    return GraspSample(*cat)


def commanded_equilibrium(hand: HandModel, theta, a, tendon_command, link_lengths=None, stiffness=None, D2=None,
                          external_torque=None, gravity=None, object_load=None):
    """The model's equilibrium (N, K) under the absolute tendon commands ``tendon_command``
    (N,), reached from ``theta`` (N, K) with the contacts ``a`` (N,) held at their mutual
    distances (``D2`` (m,), squared; default: those at ``theta``): Eq. 9 with a zero action
    and the elastic tendon's stretch ``s = l - R theta``, as the filter moves a hypothesis
    (``FilterConfig.tendon_reference = "commanded"``). Returns (angles, ok); the angles are
    ``theta`` where Newton, with continuation, finds no equilibrium. ``external_torque``
    (N, K) [N m]: further joint torques; ``gravity`` (3,) [m/s^2] and ``object_load`` (N,)
    [kg]: the links' and the object's weight, following the angles (:func:`vlr_drake.motion.move`)."""
    # named when misshapen (numpy's reshape message named neither the array nor the hand)
    theta = kinematics.as_particles("theta", theta, (hand.N, hand.K))[None]
    a = np.broadcast_to(np.asarray(a, float), (hand.N,)).reshape(1, hand.N).copy()
    L = None if link_lengths is None else np.asarray(link_lengths, float).reshape(1, hand.N, hand.K - 1)
    if D2 is None:
        D2 = motion.contact_distances_sq(hand, kinematics.contacts(hand, theta, a, L))
    stretch = kinematics.as_particles("tendon_command", tendon_command, (hand.N,))[None] - hand.tendon_travel(theta)
    res = motion.move(hand, theta, np.zeros(hand.N), a=a, D2=np.asarray(D2, float).reshape(1, -1), stretch=stretch,
                      link_lengths=L, stiffness=stiffness, max_substeps=64, check_stability=False,
                      external_torque=None if external_torque is None else np.reshape(external_torque, (1, hand.N, hand.K)),
                      gravity=gravity,
                      object_load=None if object_load is None else np.reshape(np.asarray(object_load, float), (1, hand.N)))
    ok = bool(res.ok[0] and res.tension_feasible()[0])  # a tendon that would push holds nothing
    return (res.theta[0] if ok else theta[0]).copy(), ok


def settle_under_command(hand: HandModel, theta, a, tendon_command, link_lengths=None, stiffness=None) -> np.ndarray:
    """Where the model predicts a placed grasp settles once its tendons hold ``tendon_command``.

    A grasp is planned by placing the pads on the object (``theta``, (N, K), with the
    contacts ``a`` (N,) held at their mutual distances); the tendons are then pulled to the
    grasp's commands and the fingers settle. The settled angles are the model's equilibrium
    reached from the placement with the tendon state ``s = l - R theta`` of the commands
    (:func:`commanded_equilibrium`). On the physics plant (Model O) the
    thumb's distal joint is placed at 0.05 rad and settles at 0.32-0.35 rad; this predicts
    (0.05, 0.39) for the thumb against the true (0.09, 0.32). A filter may centre its prior
    here (``IdentifyOptions.nominal_grasp = "settled"``, measured there). Where the model
    finds no equilibrium the placement is returned, with a warning.
    """
    settled, ok = commanded_equilibrium(hand, theta, a, tendon_command, link_lengths, stiffness)
    if not ok:
        warnings.warn("settle_under_command: the model finds no equilibrium under the grasp's tendon "
                      "commands; the placed angles are used as the nominal grasp", RuntimeWarning, stacklevel=2)
    return settled
