"""Forward kinematics of the VLR, batched over particles (DESIGN.md sections 2-3).

Finger i is planar. In its plane (coordinates x along u_i, z along the palm normal) the
chain of *virtual* links (Eq. 2) has lengths ``ell_k`` and absolute angles ``psi_k``:

    ell_k = L_k,           psi_k = phi_k              (k < K, physical links)
    ell_K = d_i = |(a_i, n_i)|,  psi_K = phi_K + gamma_i,  gamma_i = atan2(n_i, a_i)

with ``phi_k = theta_1 + ... + theta_k``. Joint k+1 sits at ``q_{k+1} = q_k + ell_k e(psi_k)``
and the contact at the end of the chain, ``p_i = q_K + d_i e(psi_K)``, with
``e(a) = sin(a) u_i + cos(a) z``. The derivatives used by the Newton solver are

    dp/dtheta_j = sum_{k >= j} ell_k e'(psi_k),     e'(a) = cos(a) u - sin(a) z
    d2p/dtheta_j dtheta_l = -sum_{k >= max(j, l)} ell_k e(psi_k)

Arrays follow the particle-first convention: ``theta`` is (P, N, K), ``a`` is (P, N),
per-particle hand parameters (link lengths (P, N, K-1)) may have a leading axis of 1 to
share one value across particles.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from vlr_drake.hand import HandModel

__all__ = [
    "contacts",
    "joint_positions",
    "virtual_links",
    "as_particles",
    "is_count",
    "finger_contact_derivatives",
    "contact_force_torque",
]


#: Taylor coefficients of sin (x, x^3, ..., x^17) and cos (1, x^2, ..., x^18): on the reduced
#: range |r| <= pi/4 the first omitted terms are below 1e-19, so the series are exact in
#: double precision.
_SIN_TAYLOR = tuple((-1.0) ** j / math.factorial(2 * j + 1) for j in range(9))
_COS_TAYLOR = tuple((-1.0) ** j / math.factorial(2 * j) for j in range(10))
# pi/2 in three parts for the range reduction (Cody-Waite): the first two have at most 27
# significant bits, so k times them is exact for |k| < 2^26; the third is the rest of pi/2.
_PIO2_1 = math.ldexp(math.floor(math.ldexp(math.pi / 2, 26)), -26)
_PIO2_2 = math.pi / 2 - _PIO2_1
_PIO2_3 = 6.123233995736766e-17


@njit(cache=True)
def sincos(x):  # pragma: no cover - numba
    """(sin x, cos x), written without calls or branches so that loops over it vectorise
    (numba's np.sin and np.cos are library calls that stay scalar).

    x = k pi/2 + r with |r| <= pi/4; the Taylor series give sin r and cos r, and the
    quadrant k mod 4 swaps and signs them. Accurate to a few units in the last place for
    the angles a hand reaches (tested against numpy up to |x| = 100).
    """
    k = np.floor(x * (2.0 / np.pi) + 0.5)
    r = ((x - k * _PIO2_1) - k * _PIO2_2) - k * _PIO2_3
    r2 = r * r
    ps = _SIN_TAYLOR[8]
    for j in range(7, -1, -1):
        ps = ps * r2 + _SIN_TAYLOR[j]
    pc = _COS_TAYLOR[9]
    for j in range(8, -1, -1):
        pc = pc * r2 + _COS_TAYLOR[j]
    s = r * ps
    q = k - 4.0 * np.floor(0.25 * k)  # the quadrant, 0..3
    swap = q == 1.0 or q == 3.0
    sin_x = pc if swap else s
    cos_x = s if swap else pc
    if q >= 2.0:
        sin_x = -sin_x
    if q == 1.0 or q == 2.0:
        cos_x = -cos_x
    return sin_x, cos_x


@njit(cache=True, fastmath=False)
def finger_contact_derivatives(theta, L, a, n, base, u, P_out, J_out, H_out):  # pragma: no cover - numba
    """Contact of one finger with its first and second derivatives, for W hypotheses side
    by side (in place).

    theta (K, W), L (K-1, W), a (W,), n scalar, base (3,), u (3,) -> P_out (3, W),
    J_out (3, K, W), H_out (3, K, K, W). z is the palm normal (0, 0, 1). The hypotheses
    ("lanes") are the last axis so that every loop over them is a SIMD loop; the Newton
    solver of :mod:`vlr_drake.motion` runs eight at once, other callers one (W = 1).
    """
    K, W = theta.shape
    # Walk from the tip back to the base with the suffix sums (ex, ez) of the links'
    # in-plane vectors ell_k e(psi_k); P_out's rows hold them (and phi) until the end, so no
    # scratch arrays are allocated. Since e'(psi) is e(psi) turned by -90 degrees, the
    # suffix sums of ell_k e'(psi_k) are (ez, -ex). The virtual last link d e(phi + gamma)
    # is a e(phi) + n e'(phi) (d cos gamma = a, d sin gamma = n): no square root or arctangent.
    ex = P_out[0]
    phi = P_out[1]
    ez = P_out[2]
    for w in range(W):
        ex[w] = 0.0
        ez[w] = 0.0
        phi[w] = 0.0
    for k in range(K):
        for w in range(W):
            phi[w] += theta[k, w]
    for k in range(K - 1, -1, -1):
        if k < K - 1:
            for w in range(W):
                s, c = sincos(phi[w])
                ex[w] += L[k, w] * s
                ez[w] += L[k, w] * c
                phi[w] -= theta[k, w]
        else:
            for w in range(W):
                s, c = sincos(phi[w])
                ex[w] += a[w] * s + n * c
                ez[w] += a[w] * c - n * s
                phi[w] -= theta[k, w]
        for r in range(3):
            ur = u[r]
            for w in range(W):
                J_out[r, k, w] = ez[w] * ur
        for w in range(W):
            J_out[2, k, w] -= ex[w]
        # second derivatives with max(j, l) == k
        for l in range(k + 1):
            for r in range(3):
                ur = u[r]
                for w in range(W):
                    v = -ex[w] * ur
                    H_out[r, k, l, w] = v
                    H_out[r, l, k, w] = v
            for w in range(W):
                H_out[2, k, l, w] -= ez[w]
            if l != k:
                for w in range(W):
                    H_out[2, l, k, w] -= ez[w]
    b0, b1, b2 = base[0], base[1], base[2]
    u0, u1, u2 = u[0], u[1], u[2]
    for w in range(W):
        x = ex[w]
        z = ez[w]
        P_out[0, w] = b0 + x * u0
        P_out[1, w] = b1 + x * u1
        P_out[2, w] = b2 + x * u2 + z


@njit(cache=True, parallel=True)
def _contacts_kernel(theta, L, a, pad, base, u, out):  # pragma: no cover - numba
    P, N, K = theta.shape
    for pp in prange(P):
        p = np.int64(pp)
        pl = p if L.shape[0] > 1 else 0
        for i in range(N):
            phi = 0.0
            x = 0.0
            z = 0.0
            for k in range(K):
                phi += theta[p, i, k]
                s, c = sincos(phi)
                if k < K - 1:
                    x += L[pl, i, k] * s
                    z += L[pl, i, k] * c
                else:  # the pad's centre: a along the last link, pad across it
                    x += a[p, i] * s + pad[i] * c
                    z += a[p, i] * c - pad[i] * s
            for r in range(3):
                out[p, i, r] = base[i, r] + x * u[i, r]
            out[p, i, 2] += z


def is_count(value, least: int = 0) -> bool:
    """Whether ``value`` is an integer (Python's or numpy's, not a bool) >= ``least``: the
    check of every count and seed a caller may pass (2.5 would be cut to 2, True read as 1)."""
    return not isinstance(value, bool) and isinstance(value, (int, np.integer)) and value >= least


def is_number(value) -> bool:
    """Whether ``value`` is a real number (Python's or numpy's, not a bool or a string): the
    type check of a setting read from a file, before its range is checked."""
    return not isinstance(value, bool) and isinstance(value, (int, float, np.integer, np.floating))


def checked_flag(value, name: str) -> bool:
    """A system's 0/1 input (a valid flag, an enable) read as a flag, above 0.5; a value
    that is not finite, or no number, is refused, naming the input, rather than read as 0
    (a bool is taken as it is)."""
    if isinstance(value, bool | np.bool_):
        return bool(value)
    if not (is_number(value) and np.isfinite(value)):
        raise ValueError(f"{name} must be 0 or 1, got {value if is_number(value) else repr(value)}")
    return bool(value > 0.5)


def checked_period(value, name: str) -> float:
    """A periodic event's period [s] as a float: a finite number > 0 (an infinite period
    would never fire, 0 would fire without end), or a ValueError naming it. What a system
    checks when it is made."""
    if not (is_number(value) and 0 < value < np.inf):
        raise ValueError(f"'{name}' must be a positive finite number [s], got {value!r}")
    return float(value)


def checked_offset(value, period: float, name: str = "offset_sec", period_name: str = "period_sec",
                   optional: bool = False) -> float:
    """When in its period a periodic event comes [s], as a float: a number in [0, ``period``)
    (the offsets order a diagram's events within one action period), or a ValueError naming
    it; ``optional``: the message says None is allowed too (the caller's default)."""
    if not (is_number(value) and 0 <= value < period):
        allowed = "None or in" if optional else "in"
        raise ValueError(f"'{name}' must be {allowed} [0, {period_name} = {period}) [s], got {value!r}")
    return float(value)


def checked_seed(seed) -> int:
    """``seed`` as an int, or a ValueError naming it (numpy refuses a negative seed only at
    the first draw, without naming it; 2.9 would be cut to 2): what a system checks when it
    is made."""
    if not is_count(seed):
        raise ValueError(f"'seed' must be an integer >= 0, got {seed!r}")
    return int(seed)


def as_particles(name: str, value, shape: tuple, allow_shared: bool = False) -> np.ndarray:
    """Validate a particle-first array; ``shape`` is the full (P, ...) shape expected.

    With ``allow_shared`` a leading axis of 1 (one value for all particles) is accepted.
    Raises ``ValueError`` naming the array and both shapes.
    """
    arr = np.asarray(value, dtype=np.float64)
    ok = arr.shape == tuple(shape) or (allow_shared and arr.shape == (1, *shape[1:]))
    if not ok:
        want = f"{tuple(shape)}" + (f" or {(1, *shape[1:])}" if allow_shared else "")
        raise ValueError(f"'{name}' must have shape {want}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"'{name}' contains NaN or infinite values")
    # C-contiguous and writable, whatever was given: the compiled kernels take one array
    # type (a read-only view, such as the hand's own arrays, compiled another copy of each)
    return np.require(arr, np.float64, ["C", "W"])


def _particle_count(theta, hand: HandModel) -> int:
    theta = np.asarray(theta)
    if theta.ndim != 3 or theta.shape[1:] != (hand.N, hand.K):
        raise ValueError(f"'theta' must have shape (P, {hand.N}, {hand.K}), got {theta.shape}")
    return theta.shape[0]


def contacts(hand: HandModel, theta, a, link_lengths=None) -> np.ndarray:
    """Contact points p_i in the palm frame, (P, N, 3), for angles (P, N, K) and a (P, N)."""
    P = _particle_count(theta, hand)
    theta = as_particles("theta", theta, (P, hand.N, hand.K))
    a = as_particles("a", a, (P, hand.N))
    L = hand.link_lengths[None] if link_lengths is None else link_lengths
    L = as_particles("link_lengths", L, (P, hand.N, hand.K - 1), allow_shared=True)
    if np.any(L <= 0):  # (a negative length had given a finger folded through its base)
        raise ValueError(f"'link_lengths' must be positive [m], got {np.unique(L[L <= 0]).tolist()}")
    out = np.empty((P, hand.N, 3))
    _contacts_kernel(theta, L, a, hand.pad, hand.base, hand.u, out)
    return out


def joint_positions(hand: HandModel, theta, link_lengths=None) -> np.ndarray:
    """Joint positions q_1..q_K of every finger in the palm frame, (P, N, K, 3)."""
    P = _particle_count(theta, hand)
    theta = as_particles("theta", theta, (P, hand.N, hand.K))
    L = hand.link_lengths[None] if link_lengths is None else link_lengths
    L = as_particles("link_lengths", L, (P, hand.N, hand.K - 1), allow_shared=True)
    if np.any(L <= 0):  # (a negative length had given a finger folded through its base)
        raise ValueError(f"'link_lengths' must be positive [m], got {np.unique(L[L <= 0]).tolist()}")
    phi = np.cumsum(theta, axis=-1)[..., : hand.K - 1]  # (P, N, K-1)
    step_x = L * np.sin(phi)
    step_z = L * np.cos(phi)
    q = np.empty((P, hand.N, hand.K, 3))
    q[:, :, 0, :] = hand.base[None]
    cx = np.cumsum(step_x, axis=-1)
    cz = np.cumsum(step_z, axis=-1)
    q[:, :, 1:, :] = hand.base[None, :, None, :] + cx[..., None] * hand.u[None, :, None, :]
    q[:, :, 1:, 2] += cz
    return q


def contact_force_torque(hand: HandModel, theta, a, force, link_lengths=None) -> np.ndarray:
    """Joint torques (P, N, K) [N m] of forces ``force`` (P or 1, N, 3) [N] in the palm frame
    applied at the contacts (the pads' centres, :func:`contacts`): tau_ij = (dp_i/dtheta_ij) . f_i.

    In finger i's plane the contact sits at (x_j, z_j) = ((p_i - q_ij) . u_i, (p_i - q_ij) . z)
    from joint j, and dp_i/dtheta_j = z_j u_i - x_j z (module docstring), so

        tau_ij = z_j (f_i . u_i) - x_j (f_i . z),

    positive flexing. The force's component across the finger's plane does no work.
    """
    P = _particle_count(theta, hand)
    f = as_particles("force", force, (P, hand.N, 3), allow_shared=True)
    r = contacts(hand, theta, a, link_lengths)[:, :, None, :] - joint_positions(hand, theta, link_lengths)
    x = np.einsum("pnkc,nc->pnk", r, hand.u)
    f_u = np.einsum("pnc,nc->pn", f, hand.u)
    return r[..., 2] * f_u[..., None] - x * f[:, :, 2][..., None]


def virtual_links(hand: HandModel, theta, a, link_lengths=None) -> dict[str, np.ndarray]:
    """The VLR's point sets (Eq. 1-2): joints (P, N, K, 3) and contacts (P, N, 3).

    E^J of finger i is the polyline joints[:, i] -> contacts[:, i]; its last segment is the
    distal virtual link. E^C are the segments between all pairs of contacts and the POM.
    """
    return {"joints": joint_positions(hand, theta, link_lengths), "contacts": contacts(hand, theta, a, link_lengths)}
