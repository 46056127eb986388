"""Self-identification by particle filtering (Algorithm 1; DESIGN.md section 6).

A particle is one hypothesis xi = (theta, a, Omega) of the hand-object system: joint angles
(N, K), contact positions along the last links (N,), and, when the experiment asks, the
physical parameters being identified (joint stiffness, link lengths of novel fingers).
Each particle also carries derived state: its tendon stretch (by default l - R theta from the
motors' absolute tendon command l; or, as in the paper, the stretch that holds it in
equilibrium, :func:`vlr_drake.motion.equilibrium`: ``FilterConfig.tendon_reference``) and
its *attachment* p_i^O, the contacts expressed
in the POM frame, which fixes the E^C links (Eq. 1) and so the grasp distances (Eq. 8).

One iteration (one action dl and one camera measurement of the POM):

1. move every particle with Gamma (Eq. 4/9, batched Newton) from its tendon state,
2. predict its POM pose with Lambda (Eq. 5),
3. weigh: log w = -0.5 (|dp|^2 / sigma_p^2 + angle(dR)^2 / sigma_r^2), minus infinity for
   particles whose solve failed, whose joints left their limits, or whose implied tendon
   tension is negative (a pushing tendon is not a grasp); with ``stuck_probability`` p > 0
   a particle whose solve failed is instead held where it was (friction, which the VLR
   lacks) and weighs p times the likelihood of its unmoved POM pose,
4. temper: if the effective sample size (ESS) would fall below ``ess_fraction * M``, the
   log-likelihood is scaled by beta in (0, 1], found by a safeguarded Newton search on log
   ESS (``_temper_increment``), so that the ESS stays there (weight collapse locks a filter
   into wrong modes),
5. resample (systematic) after a valid measurement that left the ESS below
   ``resample_fraction * M`` (0.5; the weights carry over otherwise),
6. roughen (Liu-West kernel shrinkage: x <- a x + (1 - a) mean + h C^(1/2) eps with C the
   cloud's covariance, a = sqrt(1 - h^2), which keeps the cloud's mean and covariance), recompute each tendon state, and
7. re-anchor the attachment a fraction ``anchor_fraction`` of the way from the particle's own
   predicted POM pose towards the measured one (holding it fixed for ever makes the filter
   overconfident; DESIGN.md section 3).

With ``FilterConfig.motion_model = "rolling"`` steps 1-2 are one solve instead
(:func:`vlr_drake.motion_rolling.move_rolling`): the pads roll over the object, whose pose
is an unknown of the equilibrium, under the links' and the object's weight, and each
hypothesis carries the object's normals at its contacts and its centre of mass as well.

The estimate is the weighted mean of the cloud (weights carry over between resamplings);
the 95% interval of a quantity is its weighted 2.5-97.5 percentile range. The filter has converged when the average over
joint angles of the 95% interval (half-width by default; full width selectable) is below
``convergence_deg`` and, with ``parameter_convergence`` (the default), every unknown spring's
and link length's interval is below that fraction of its estimate. If every particle becomes implausible (the best one is many sigma
away, or every solve failed), the filter re-initialises around its last estimate and says so.
"""

from __future__ import annotations

import copy
import dataclasses
import time
import warnings
from dataclasses import dataclass, field

import numpy as np
from numba import njit, prange

from vlr_drake import kinematics, motion, motion_rolling, observation, units
from vlr_drake.hand import HandModel, HandSpec
from vlr_drake.kinematics import as_particles

__all__ = [
    "PriorError",
    "FilterConfig",
    "TENDON_REFERENCES",
    "PriorConfig",
    "SettledAngles",
    "ParticleSet",
    "StepReport",
    "SelfIdentificationFilter",
    "CALIBRATED_PARTICLES",
    "FewParticlesWarning",
    "warn_if_few_particles",
    "systematic_resample",
    "effective_sample_size",
    "temper",
    "interval95",
    "information_gain",
    "log_evidence_increment",
]


#: Nearest a contact may lie to the distal joint along the last link [m] (PriorConfig.contact_limits).
CONTACT_MIN = 0.005


class PriorError(ValueError):
    """The prior (its ranges around the nominal grasp) holds too few physical grasps to draw
    the particles from: a setting to change, not a failure of the run."""


def _shaped(name: str, x, shape: tuple) -> np.ndarray:
    """``x`` as a finite float array of ``shape`` (or that many numbers in a flat array, in
    the same order), or a ValueError that names it. Another arrangement of the right count,
    e.g. a transposed (K, N) for (N, K), is refused: it would pair values and joints wrongly."""
    arr = np.asarray(x, float)
    if arr.shape != tuple(shape) and arr.shape != (int(np.prod(shape)),):
        raise ValueError(f"filter: '{name}' must have shape {tuple(shape)} (or be flat), got {arr.shape}")
    return as_particles(name, arr.reshape(shape), shape)  # its finiteness check and message


def contact_center(hand: HandModel, a_center) -> np.ndarray:
    """The nominal contacts ``a_center`` (N,) [m] along the last links, checked: finite and
    within 0..``hand.distal_length`` (one off a link would be clipped to its end: it is named
    instead; metres, not mm?), or a ValueError."""
    a_center = _shaped("a_center", a_center, (hand.N,))
    off = (a_center < 0) | (a_center > hand.distal_length)
    if np.any(off):
        raise ValueError(f"filter: 'a_center' must lie along the last links, 0..{np.round(hand.distal_length, 4).tolist()} "
                         f"[m]; {np.round(a_center, 4).tolist()} is off finger(s) "
                         f"{[hand.names[i] for i in np.flatnonzero(off)]}")
    return a_center


def _pose(name: str, R, t) -> tuple[np.ndarray, np.ndarray]:
    """A measured or nominal POM pose as a (3, 3) rotation and a (3,) position, checked:
    finite (a lost tag is ``valid=False``, not NaN), and R a rotation to 1e-6."""
    R, t = np.asarray(R, float), np.asarray(t, float)
    if R.size == 9 and t.size == 3 and not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        bad = (f"t {t.ravel().tolist()}" if np.all(np.isfinite(R))
               else f"R {R.reshape(3, 3).round(6).tolist()}")
        raise ValueError(f"filter: the {name} POM pose is not finite ({bad}); pass valid=False for a lost tag")
    R, t = _shaped(f"{name} rotation", R, (3, 3)), _shaped(f"{name} position", t, (3,))
    if not observation.is_rotation(R):
        raise ValueError(f"filter: the {name} rotation is not a rotation matrix: {np.round(R, 6).tolist()}")
    return R, t


# --------------------------------------------------------------------------------------
# Pure building blocks (tested against their definitions)
# --------------------------------------------------------------------------------------


def effective_sample_size(log_w: np.ndarray) -> float:
    """ESS = 1 / sum(w_i^2) of the normalised weights exp(log_w)."""
    log_w = np.asarray(log_w, float)
    finite = np.isfinite(log_w)
    if not finite.any():
        return 0.0
    w = np.exp(log_w - log_w[finite].max())
    w[~finite] = 0.0
    w /= w.sum()
    return float(1.0 / np.sum(w * w))


def normalise(log_w: np.ndarray) -> np.ndarray:
    """Normalised weights from log weights (-inf allowed; all -inf gives uniform)."""
    log_w = np.asarray(log_w, float)
    finite = np.isfinite(log_w)
    if not finite.any():
        return np.full(log_w.shape, 1.0 / log_w.size)
    w = np.exp(log_w - log_w[finite].max())
    w[~finite] = 0.0
    return w / w.sum()


def log_evidence_increment(log_w: np.ndarray, log_lik: np.ndarray) -> float:
    """log p(y_t | y_1..t-1) ~= log sum_i w_i exp(log_lik_i), the weights w normalised from
    ``log_w``: the particle estimate of the marginal likelihood of one measurement (its sum
    over a run is the log evidence of the model behind the filter). -inf entries of either
    array contribute nothing; -inf when no particle explains the measurement. Up to the
    likelihood's dropped constant, which is the same for every filter with the same noise
    model, so differences between runs over the same measurements compare their models."""
    log_w = np.asarray(log_w, float)
    joint = _logsumexp(log_w + np.asarray(log_lik, float))
    return joint if joint == -np.inf else joint - _logsumexp(log_w)


def _logsumexp(x: np.ndarray) -> float:
    """log sum exp(x) over the finite entries (-inf when there are none)."""
    x = x[np.isfinite(x)]
    if x.size == 0:
        return -np.inf
    m = x.max()
    return float(m + np.log(np.exp(x - m).sum()))


def systematic_resample(weights: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Systematic (low-variance) resampling: ancestor indices for normalised ``weights``.

    One uniform draw u ~ U[0, 1/M); particle j is copied once for each of the points
    u + k/M (k = 0..M-1) that falls in its slice of the cumulative weights.
    """
    w = np.asarray(weights, float)
    M = w.size
    if M == 0 or not np.isclose(w.sum(), 1.0) or np.any(w < 0):
        raise ValueError("systematic_resample needs non-negative weights that sum to 1")
    positions = (rng.random() + np.arange(M)) / M
    cdf = np.cumsum(w)
    cdf[-1] = 1.0
    # (a position that rounds to 1, or falls past a cumulative sum a little short of 1,
    # would pick the last particle whatever its weight: no ancestor past the last one with
    # weight)
    return np.minimum(np.searchsorted(cdf, positions, side="right"), np.flatnonzero(w > 0)[-1])


def temper(log_lik: np.ndarray, ess_target: float, iterations: int = 40) -> float:
    """Largest beta in (0, 1] with ESS(beta * log_lik) >= ess_target, to the grid of
    ``iterations`` halvings (what bisection returns; :func:`_temper_increment`).

    Returns 1 when the full likelihood keeps the ESS above the target.
    """
    return _temper_increment(np.zeros_like(np.asarray(log_lik, float)), log_lik, ess_target, iterations)


@njit(cache=True, parallel=True)
def _tempered_ess(log_w0, log_lik, beta):  # pragma: no cover - numba
    """ESS of the log weights log_w0 + beta log_lik (non-finite ones weigh nothing), in two
    passes without temporaries, each split into blocks summed in parallel. Every decision
    of :func:`_temper_increment` (and of the bisection it reproduces) is made with it."""
    M = log_w0.shape[0]
    nb = 16
    size = (M + nb - 1) // nb
    part = np.full(nb, -np.inf)
    for b in prange(nb):
        top = -np.inf
        for i in range(b * size, min(M, (b + 1) * size)):
            v = log_w0[i] + beta * log_lik[i]
            if v > top and v < np.inf:
                top = v
        part[b] = top
    top = part.max()
    if not np.isfinite(top):
        return 0.0
    s1 = np.zeros(nb)
    s2 = np.zeros(nb)
    for b in prange(nb):
        a1 = 0.0
        a2 = 0.0
        for i in range(b * size, min(M, (b + 1) * size)):
            v = log_w0[i] + beta * log_lik[i]
            if v > -np.inf and v < np.inf:
                e = np.exp(v - top)
                a1 += e
                a2 += e * e
        s1[b] = a1
        s2[b] = a2
    s = s1.sum()
    return s * s / s2.sum()


@njit(cache=True, parallel=True)
def _tempered_ess_slope(log_w0, log_lik, beta):  # pragma: no cover - numba
    """log ESS(beta) and its derivative d log ESS / d beta for the log weights
    log_w0 + beta log_lik (non-finite ones weigh nothing): with e_i = exp(v_i - max v),
    ESS = (sum e)^2 / sum e^2 and d log ESS / d beta = 2 (sum l e / sum e - sum l e^2 / sum e^2).
    Used by :func:`_temper_increment`'s Newton search; the decisions use :func:`_tempered_ess`.
    The maximum's pass is written out as in :func:`_tempered_ess` on purpose: taken from a
    helper kernel called before the parallel loop, it gave wrong sums under numba 0.68.1."""
    M = log_w0.shape[0]
    nb = 16
    size = (M + nb - 1) // nb
    part = np.full(nb, -np.inf)
    for b in prange(nb):
        top = -np.inf
        for i in range(b * size, min(M, (b + 1) * size)):
            v = log_w0[i] + beta * log_lik[i]
            if v > top and v < np.inf:
                top = v
        part[b] = top
    top = part.max()
    if not np.isfinite(top):
        return -np.inf, 0.0
    sums = np.zeros((nb, 4))
    for b in prange(nb):
        a1 = 0.0
        a2 = 0.0
        d1 = 0.0
        d2 = 0.0
        for i in range(b * size, min(M, (b + 1) * size)):
            v = log_w0[i] + beta * log_lik[i]
            if v > -np.inf and v < np.inf:
                e = np.exp(v - top)
                a1 += e
                a2 += e * e
                d1 += log_lik[i] * e
                d2 += log_lik[i] * e * e
        sums[b, 0] = a1
        sums[b, 1] = a2
        sums[b, 2] = d1
        sums[b, 3] = d2
    s1, s2 = sums[:, 0].sum(), sums[:, 1].sum()
    return 2.0 * np.log(s1) - np.log(s2), 2.0 * (sums[:, 2].sum() / s1 - sums[:, 3].sum() / s2)


def _temper_increment(log_w0: np.ndarray, log_lik: np.ndarray, ess_target: float, iterations: int = 40) -> float:
    """Largest beta in (0, 1] with ESS(log_w0 + beta * log_lik) >= ess_target, to the grid
    of ``iterations`` halvings of [0, 1], and at least 1e-6.

    The result is what bisection with ``iterations`` halvings returns
    (:func:`_temper_bisect`: the grid point k / 2^iterations where the ESS is at least the
    target and one grid step above it is not), whenever the computed ESS decreases along
    the grid, found with fewer ESS evaluations: a safeguarded Newton search on log ESS
    over log beta (:func:`_tempered_ess_slope`) gets within a few grid points of the root,
    and :func:`_tempered_ess` at grid points, the bisection's own test, places it; a
    bisection over the grid points between the last ones tested finishes where that does
    not. About 6-15 evaluations instead of 41 (the first iteration's weighing at 60,000
    particles: 17 -> 8 ms); 1,600 tempering steps of replayed physics runs gave the
    bisection's beta bit for bit. Where the likelihood is so weak that neighbouring grid
    points' ESS differ by less than its round-off, the two may pick crossings a few grid
    steps (~1e-11) apart.

    All ``iterations`` halvings' precision is kept: stopping at 0.1% of beta (10-20
    halvings) left the model plant's spring inside its interval in 9 of 12 runs instead of
    11 (stiffness, 5,000 particles, 60 iterations, seeds 0-11), probably chance, but not
    worth the risk."""
    log_w0 = np.ascontiguousarray(log_w0, dtype=float)
    log_lik = np.ascontiguousarray(log_lik, dtype=float)
    if _tempered_ess(log_w0, log_lik, 1.0) >= ess_target:
        return 1.0
    if _tempered_ess(log_w0, log_lik, 0.0) < ess_target:
        # the carried weights of the hypotheses the likelihood keeps are below the target
        # already: no crossing to search for (the filter lowers its target to the live
        # cloud's instead of calling this; the bisection's floor, 1e-6, discards the
        # measurement)
        return _temper_bisect(log_w0, log_lik, ess_target, iterations)
    grid = 2.0**-iterations
    steps = 1 << iterations
    floor = 1e-6  # the smallest increment returned
    known = {0: True, steps: False}  # grid point -> ESS >= target (0: bisection's lo; steps: beta = 1)

    def above(k):
        if k not in known:
            known[k] = bool(_tempered_ess(log_w0, log_lik, k * grid) >= ess_target)
        return known[k]

    k_floor = min(int(floor / grid), steps - 1)
    if not above(k_floor + 1):  # the crossing lies below 1e-6, which is returned
        return floor
    # safeguarded Newton on h(u) = log ESS(e^u) - log target, u = log beta, over the
    # bracket [u_a, u_b] with h(u_a) >= 0 > h(u_b)
    goal = np.log(ess_target)
    u_a, u_b = np.log((k_floor + 1) * grid), 0.0
    u = 0.5 * (u_a + u_b)
    for _ in range(16):
        g, slope = _tempered_ess_slope(log_w0, log_lik, np.exp(u))
        if not np.isfinite(g):
            break
        if g >= goal:
            u_a = u
        else:
            u_b = u
        if abs(g - goal) < 1e-10 or np.exp(u_b) - np.exp(u_a) <= 4.0 * grid:
            break
        dh = slope * np.exp(u)  # dh/du = beta dg/dbeta
        step = u - (g - goal) / dh if dh < 0.0 else np.nan
        u = step if u_a < step < u_b else 0.5 * (u_a + u_b)
    # place the crossing on the grid with the bisection's own test, from the Newton root
    k = min(max(int(np.floor(np.exp(u) / grid)), k_floor + 1), steps - 1)
    for _ in range(8):
        if not above(k):
            k -= 1
        elif above(k + 1):
            k += 1
        else:
            return max(k * grid, floor)
    # bisection over the grid points between the highest one above and the lowest below
    lo = max(j for j, v in known.items() if v)
    hi = min(j for j, v in known.items() if not v and j > lo)
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if above(mid):
            lo = mid
        else:
            hi = mid
    return max(lo * grid, floor)


def _temper_bisect(log_w0: np.ndarray, log_lik: np.ndarray, ess_target: float, iterations: int = 40) -> float:
    """The bisection that :func:`_temper_increment` reproduces (and falls back on)."""
    if _tempered_ess(log_w0, log_lik, 1.0) >= ess_target:
        return 1.0
    lo, hi = 0.0, 1.0
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        if _tempered_ess(log_w0, log_lik, mid) >= ess_target:
            lo = mid
        else:
            hi = mid
    return max(lo, 1e-6)


def information_gain(y: np.ndarray, ok: np.ndarray, min_valid: float = 0.9) -> np.ndarray:
    """0.5 log det(I + Cov_s(y[c])) per candidate c (C,), for predicted measurements ``y``
    (C, S, D) in units of the measurement noise and validity flags ``ok`` (C, S): the mutual
    information between a Gaussian cloud of predictions and one noisy measurement of it. The
    covariance is over the valid predictions; a candidate with fewer than ``min_valid`` of
    them valid scores -inf."""
    y = np.asarray(y, float)
    ok = np.asarray(ok, bool)
    if y.ndim != 3 or ok.shape != y.shape[:2]:
        raise ValueError(f"information_gain: y must be (C, S, D) and ok (C, S), got {y.shape} and {ok.shape}")
    n = ok.sum(axis=1)
    w = ok / np.maximum(n, 1)[:, None]
    y = np.where(ok[..., None], y, 0.0)  # an invalid prediction may be NaN: 0 x NaN is NaN
    mean = np.einsum("cs,csd->cd", w, y)
    d = np.where(ok[..., None], y - mean[:, None], 0.0)
    cov = np.einsum("cs,csd,cse->cde", w, d, d)
    logdet = np.linalg.slogdet(np.eye(y.shape[2])[None] + cov)[1]
    return np.where((n >= min_valid * y.shape[1]) & (n > 1), 0.5 * logdet, -np.inf)


def interval95(x: np.ndarray, w: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Weighted 2.5 and 97.5 percentiles over the particle axis (axis 0).

    With weights, the quantile is the smallest sample whose cumulative normalised weight
    reaches the level (the inverse of the weighted empirical CDF); it is found by weighted
    selection (:func:`_weighted_quantiles`, linear time per column) rather than a sort.
    Without weights, numpy's interpolated percentiles (the filter always passes weights)."""
    x = np.asarray(x, float)
    if w is None:
        lo, hi = np.percentile(x, [2.5, 97.5], axis=0)
        return lo, hi
    flat = x.reshape(x.shape[0], -1)
    w = np.asarray(w, float)
    if not np.isfinite(flat).all():
        raise ValueError("interval95: the samples must be finite")
    if w.shape != (flat.shape[0],):
        raise ValueError(f"interval95: the weights must have shape ({flat.shape[0]},), got {w.shape}")
    if not (np.isfinite(w).all() and (w >= 0).all() and w.sum() > 0):
        raise ValueError("interval95: the weights must be finite, non-negative and not all zero")
    cols = np.ascontiguousarray(flat.T)
    if w.size and np.all(w == w[0]):  # equal weights (after resampling): order statistics
        # the k-th smallest value is the smallest whose count reaches k + 1: with unit
        # weights the counts are exact, so this is the order statistic np.partition gives
        M = flat.shape[0]
        ranks = np.array([float(np.ceil(q * M - 1e-9)) for q in (0.025, 0.975)])
        out = _weighted_quantiles(cols, np.ones(M), ranks, True)
    else:
        out = _weighted_quantiles(cols, w, np.array([0.025, 0.975]), False)
    return out[:, 0].reshape(x.shape[1:]), out[:, 1].reshape(x.shape[1:])


@njit(cache=True)
def _weighted_select(v, w, target):  # pragma: no cover - numba
    """Smallest value x of ``v`` with W(v <= x) >= ``target`` (W: the summed weights ``w``),
    by three-way quickselect; ``v`` and ``w`` are scratch (reordered in place). Expected
    linear time: every pass keeps only the side that holds the answer."""
    lo, hi = 0, v.shape[0]
    below = 0.0  # weight of the values already known to lie below v[lo:hi]
    while hi - lo > 1:
        a, b, c = v[lo], v[(lo + hi) // 2], v[hi - 1]  # median-of-three pivot
        p = max(min(a, b), min(max(a, b), c))
        # partition v[lo:hi] into < p | == p | > p, carrying the weights along
        i, lt, gt = lo, lo, hi
        w_lt = 0.0
        w_eq = 0.0
        while i < gt:
            if v[i] < p:
                w_lt += w[i]
                v[i], v[lt] = v[lt], v[i]
                w[i], w[lt] = w[lt], w[i]
                lt += 1
                i += 1
            elif v[i] > p:
                gt -= 1
                v[i], v[gt] = v[gt], v[i]
                w[i], w[gt] = w[gt], w[i]
            else:
                w_eq += w[i]
                i += 1
        if below + w_lt >= target and lt > lo:
            hi = lt
        elif below + w_lt + w_eq >= target or gt == hi:
            return p
        else:
            below += w_lt + w_eq
            lo = gt
    return v[lo]


@njit(cache=True, parallel=True)
def _weighted_quantiles(cols, w, levels, absolute):  # pragma: no cover - numba
    """Weighted quantiles (C, Q) of every row of ``cols`` (C, M) (finite values) with
    weights ``w`` (M,) at ``levels`` (Q,) in (0, 1]: the smallest value whose cumulative
    normalised weight reaches the level (with ``absolute``, whose cumulative weight reaches
    ``levels`` itself: with unit weights and ranks, order statistics). Rows in parallel; per row, a weight histogram of
    1024 bins finds the bin that holds each quantile, and :func:`_weighted_select` picks it
    among that bin's values (two passes over the row instead of a sort)."""
    C, M = cols.shape
    B = 1024
    total = 0.0
    for i in range(M):
        total += w[i]
    out = np.empty((C, levels.shape[0]))
    for c in prange(C):
        x = cols[c]
        vmin, vmax = x[0], x[0]
        for i in range(M):
            vmin = min(vmin, x[i])
            vmax = max(vmax, x[i])
        if vmax == vmin:
            out[c, :] = vmin
            continue
        scale = B / (vmax - vmin)
        hist = np.zeros(B)
        bins = np.empty(M, dtype=np.int64)
        for i in range(M):
            bins[i] = min(int((x[i] - vmin) * scale), B - 1)
            hist[bins[i]] += w[i]
        for q in range(levels.shape[0]):
            target = levels[q] if absolute else levels[q] * total
            below = 0.0
            k = 0
            while k < B - 1 and below + hist[k] < target:
                below += hist[k]
                k += 1
            n = 0
            for i in range(M):
                n += bins[i] == k
            v = np.empty(n)
            ww = np.empty(n)
            n = 0
            for i in range(M):
                if bins[i] == k:
                    v[n] = x[i]
                    ww[n] = w[i]
                    n += 1
            out[c, q] = _weighted_select(v, ww, target - below)
    return out


# --------------------------------------------------------------------------------------
# Configuration
# --------------------------------------------------------------------------------------


#: Where a plant knows the true grasp (the model plant, the physics plant), the filter's
#: nominal grasp (its prior's centre) is a guess made from it: the truth displaced by up to
#: this fraction of the prior's half-widths, uniformly and independently per coordinate
#: (PriorConfig.guessed_grasp). On hardware the nominal grasp is the scenario's grasp
#: section: a person's or a grasp planner's guess.
CENTER_OFFSET_FRACTION = 0.6


@dataclass
class PriorConfig:
    """Where the hypotheses start: uniform boxes around a nominal grasp (documented ranges).

    Every range is a half-width around the centre; centres default to the nominal grasp
    that the caller passes (e.g. from the scenario's object placement).
    """

    # Half-width of the proximal (first) joint angles [rad].
    proximal_half_width: float = 0.15
    # Half-width of the other joint angles [rad].
    distal_half_width: float = 0.25
    # Half-width of the contact positions along the last links [m].
    contact_half_width: float = 0.008
    # Unknown joint stiffness: (finger, joint) pairs, with the range [min, max] [N m/rad].
    stiffness_unknown: list[tuple[int, int]] = field(default_factory=list)
    stiffness_range: tuple[float, float] = (0.05, 0.40)
    # How the unknown stiffness is drawn in its range: "log_uniform" (default; a scale
    # parameter: every factor of 2 as likely) or "uniform". A uniform draw over 0.05-0.40
    # N m/rad puts 46% of the hypotheses above 0.24, stiffer than any spring the experiment
    # draws, and where the motions tell little (a stiff distal joint barely moves) the
    # estimate keeps that mass; the log-uniform puts 25% there. Measured (2026-11-27): on
    # the physics plant (stiffness, toy block, seeds 0-44, replays of fresh 240-iteration
    # runs) 0.0190 +- 0.0186 N m/rad against uniform's 0.0221 +- 0.0285 at the stiffness's
    # likelihood width (1.75), 0.0151 +- 0.0145 against 0.0182 +- 0.0218 at 1.5, springs
    # inside 39-41 of 45 against 38, fewer stiff outliers (seed 10: 0.092 -> 0.024 N m/rad);
    # on the model plant (identify's defaults, seeds 0-9) 0.0022 +- 0.0025 against 0.0029 +-
    # 0.0024, every spring inside either way (an older measurement, 5000 particles and 60
    # iterations, seeds 0-7, had 0.0043 against 0.0022).
    stiffness_prior: str = "log_uniform"
    # Fingers whose proximal link lengths are unknown, with the range [min, max] [m].
    links_unknown: list[int] = field(default_factory=list)
    link_range: tuple[float, float] = (0.030, 0.075)
    # Unknown object weight (needs FilterConfig.gravity_palm): the object's mass [kg], drawn
    # uniformly in ``object_mass_range``, carried by the contacts in shares w_i drawn
    # uniformly on the simplex (sum w_i = 1): the barycentric weights of the object's centre
    # of mass over the contacts, which stay put in the object as it turns. Each hypothesis
    # carries its contacts' loads m w_i (``ParticleSet.object_load``), and the weight m w_i g
    # at its contacts loads its joints in every move (FilterConfig.gravity_loads must be
    # "following"; the VLR's contact forces cancel on the object, so Eq. 9 treats it as
    # weightless).
    object_mass_unknown: bool = False
    object_mass_range: tuple[float, float] = (0.0, 0.25)
    # With FilterConfig.motion_model "rolling", the object's weight acts at its centre of
    # mass, fixed in the object's frame (ParticleSet.com_O), drawn as ``com_prior`` says:
    # "contacts", at the barycentre of the contacts with the shares above (anywhere in their
    # triangle), moved along the normal of the contacts' plane by up to ``com_half_width``
    # (the centre of mass need not lie in that plane); or "balanced", uniformly within a
    # ball of radius ``com_half_width`` around the contacts' balanced barycentre, whose
    # shares balance the fingers' closing directions (sum_i w_i u_i = 0: on the Model O half
    # at the thumb, a quarter at each finger): an object held near its centre of mass; or
    # "shape", following each hypothesis' guess of the object's shape (FilterConfig.normal_guess):
    # a round object's (the "circle" guess) within a ball of ``com_half_width`` around the
    # centre of the circle through its contacts (a uniform ball's centre of mass), a
    # flat-faced one's as "contacts". On the apple the contacts' barycentre lies about 13 mm
    # from its centre, towards the fingers.
    # The rolling model's spring trades off against the centre of mass (on the toy block a
    # stiffer thumb spring by about 1.4% per mm towards the fingers), and the contacts'
    # shares put it 11 mm towards the fingers on average (docs/results.md).
    com_prior: str = "contacts"
    com_half_width: float = 0.02
    # Contact positions must stay on the pad: [min, max] along the last link [m], the same
    # for every finger and within each finger's last link. None: from CONTACT_MIN to each
    # finger's own last-link length (HandModel.distal_length), so a shorter novel distal
    # link (NF3's 40 mm) keeps its contacts on it.
    contact_limits: tuple[float, float] | None = None
    # Smallest implied tendon tension of a prior draw [N].
    min_tension: float = 0.0
    # Where each hypothesis' joint angles are drawn: "nominal", in the boxes around the
    # nominal grasp whatever its springs and links (the physics plant's nominal grasp is
    # placed with the believed hand, believed_hand: unknowns at their middles); "settled",
    # around the grasp the filter's model settles to under the grasp's tendon command with
    # the hypothesis' own unknown springs and links (SettledAngles: settled at a few values
    # of each across its range, interpolated), so that the prior's angles carry no spring
    # or link of their own. On the Model O holding the toy block the thumb's distal joint
    # settles at 9 deg with a 0.40 N m/rad spring and 40 deg with a 0.10 one, against the
    # 3.5 deg it is placed at: a hypothesis near the placed angles is at rest under the
    # command only with a stiff spring.
    angle_centers: str = "nominal"

    def believed_hand(self, spec: HandSpec) -> HandSpec:
        """The hand the filter believes in before any measurement: a copy of ``spec`` whose
        unknown proximal links (``links_unknown``) are the middle of ``link_range`` and whose
        unknown springs (``stiffness_unknown``) are the middle of ``stiffness_range`` in the
        prior's own space (:meth:`stiffness_middle`), for whatever is computed from the
        hand's geometry and springs before the particles are drawn (the nominal grasp's
        placed angles, which follow the springs' closing path), so that no true length of a
        replaced finger and no true spring reaches the filter."""
        believed = copy.deepcopy(spec)
        middle = self.link_middle()
        for fi in self.links_unknown:
            lengths = list(believed.fingers[fi].link_lengths)
            lengths[0] = middle
            believed.fingers[fi].link_lengths = lengths
        for fi, j in self.stiffness_unknown:
            k = list(believed.fingers[fi].stiffness)
            k[j] = self.stiffness_middle()
            believed.fingers[fi].stiffness = k
        return believed

    def link_middle(self) -> float:
        """The middle of ``link_range`` [m]."""
        return 0.5 * (self.link_range[0] + self.link_range[1])

    def stiffness_middle(self) -> float:
        """The middle of ``stiffness_range`` in the prior's space: the geometric mean for
        the log-uniform prior, the arithmetic mean for the uniform one [N m/rad]."""
        lo, hi = self.stiffness_range
        return float(np.sqrt(lo * hi)) if self.stiffness_prior == "log_uniform" else 0.5 * (lo + hi)

    def guessed_grasp(self, theta, a, rng: np.random.Generator, hand: HandModel,
                      fraction: float = CENTER_OFFSET_FRACTION) -> tuple[np.ndarray, np.ndarray]:
        """A nominal grasp guessed from the true one, ``theta`` (N, K) [rad] and ``a`` (N,)
        [m]: each proximal angle, distal angle and contact displaced uniformly by up to
        ``fraction`` of its half-width (drawn in that order; the model plant), the contacts
        clipped to :meth:`contact_bounds` as :meth:`guessed_contacts` clips them (a guess
        past a short last link's end, NH3's 40 mm NF3, had been refused by the filter)."""
        theta_c = np.array(theta, float)
        N, K = theta_c.shape
        theta_c[:, 0] += fraction * self.proximal_half_width * rng.uniform(-1, 1, N)
        theta_c[:, 1:] += fraction * self.distal_half_width * rng.uniform(-1, 1, (N, K - 1))
        return theta_c, self.guessed_contacts(a, rng, hand, fraction)

    def guessed_contacts(self, a, rng: np.random.Generator, hand: HandModel,
                         fraction: float = CENTER_OFFSET_FRACTION) -> np.ndarray:
        """The contacts of a nominal grasp guessed from the true ones ``a`` (N,) [m], each
        displaced uniformly by up to ``fraction`` of the contact half-width and clipped to
        :meth:`contact_bounds` (a truth may lie near a bound: pads on a short last link,
        custom limits). The physics plant's guess, whose nominal angles, the placed grasp,
        already differ from where the grasp settles; :meth:`guessed_grasp`'s contacts after
        its angles."""
        return np.clip(self._displaced_contacts(a, rng, fraction), *self.contact_bounds(hand))

    def _displaced_contacts(self, a, rng: np.random.Generator, fraction: float) -> np.ndarray:
        a = np.asarray(a, float)
        return a + fraction * self.contact_half_width * rng.uniform(-1, 1, a.shape[0])

    def validate(self, N: int | None = None, K: int | None = None) -> PriorConfig:
        """Check the settings, and with ``N`` and ``K`` that the unknowns name fingers and
        joints of a hand of N fingers of K joints; raises ``ValueError`` naming the field.
        (``contact_limits`` needs the hand's links: :meth:`contact_bounds`.)"""
        # numbers first (text had ended in a bare TypeError, True been read as 1 rad or 1 m, and a
        # range that is no pair in "cannot unpack")
        for name in ("proximal_half_width", "distal_half_width", "contact_half_width", "min_tension",
                     "com_half_width"):
            if not kinematics.is_number(getattr(self, name)):
                raise ValueError(f"prior: '{name}' must be a number, got {getattr(self, name)!r}")
        for name in ("stiffness_range", "link_range", "object_mass_range"):
            v = getattr(self, name)
            if not (isinstance(v, list | tuple | np.ndarray) and len(v) == 2 and all(kinematics.is_number(x) for x in v)):
                raise ValueError(f"prior: '{name}' must be (min, max), a pair of numbers, got {v!r}")
        widths = {n: getattr(self, n) for n in ("proximal_half_width", "distal_half_width", "contact_half_width")}
        bad = {n: v for n, v in widths.items() if not (np.isfinite(v) and v > 0)}
        if bad:
            raise ValueError(f"prior: the half-widths must be positive and finite, got {bad}")
        for name in ("proximal_half_width", "distal_half_width"):  # (5 meant as deg had drawn 5 rad either side)
            units.check_angle(getattr(self, name), f"prior: '{name}'", np.pi / 2, "a quarter turn either side")
        units.check_length(self.contact_half_width, "prior: 'contact_half_width'")
        for name in ("stiffness_range", "link_range"):
            lo, hi = getattr(self, name)
            if not (np.isfinite([lo, hi]).all() and 0 < lo < hi):
                raise ValueError(f"prior: '{name}' must be finite [min, max] with 0 < min < max, "
                                 f"got {getattr(self, name)}")
        units.check_length(self.link_range, "prior: 'link_range'")
        units.check_stiffness(self.stiffness_range, "prior: 'stiffness_range'")
        if self.angle_centers not in ANGLE_CENTERS:
            raise ValueError(f"prior: 'angle_centers' must be one of {ANGLE_CENTERS}, got '{self.angle_centers}'")
        if self.stiffness_prior not in STIFFNESS_PRIORS:
            raise ValueError(f"prior: 'stiffness_prior' must be one of {STIFFNESS_PRIORS}, got '{self.stiffness_prior}'")
        if not (np.isfinite(self.min_tension) and self.min_tension >= 0):
            raise ValueError(f"prior: 'min_tension' must be a finite number >= 0 (tendons only pull) [N], "
                             f"got {self.min_tension}")
        # indices (1.5 or 1.0 had failed deep in numpy, True had named finger 1)
        index = kinematics.is_count
        if not (isinstance(self.stiffness_unknown, list | tuple)
                and all(np.shape(e) == (2,) and all(index(x) for x in e) for e in self.stiffness_unknown)):
            raise ValueError(f"prior: 'stiffness_unknown' must be a list of (finger, joint) integer pairs, "
                             f"got {self.stiffness_unknown!r}")
        if not (isinstance(self.links_unknown, list | tuple) and all(index(fi) for fi in self.links_unknown)):
            raise ValueError(f"prior: 'links_unknown' must be a list of finger indices (integers), "
                             f"got {self.links_unknown!r}")
        for fi, j in self.stiffness_unknown if N is not None else ():
            if not (0 <= fi < N and 0 <= j < K):
                raise ValueError(f"prior: stiffness_unknown entry ({fi}, {j}) is not a joint of a {N} x {K} hand")
        for fi in self.links_unknown if N is not None else ():
            if not 0 <= fi < N:
                raise ValueError(f"prior: links_unknown entry {fi} is not a finger of a {N}-finger hand")
        # one column of the unknowns per quantity: a repeated one would be drawn and roughened twice
        joints = [(int(fi), int(j)) for fi, j in self.stiffness_unknown]
        for name, entries in (("stiffness_unknown", joints), ("links_unknown", [int(fi) for fi in self.links_unknown])):
            repeated = sorted({e for e in entries if entries.count(e) > 1})
            if repeated:
                raise ValueError(f"prior: {name} names {repeated} more than once")
        if not isinstance(self.object_mass_unknown, bool | np.bool_):  # "false" had been read as true
            raise ValueError(f"prior: 'object_mass_unknown' must be True or False, got {self.object_mass_unknown!r}")
        if np.shape(self.object_mass_range) != (2,):
            raise ValueError(f"prior: 'object_mass_range' must be (min, max) [kg], got {self.object_mass_range}")
        if self.object_mass_unknown:
            lo, hi = self.object_mass_range
            if not (np.isfinite([lo, hi]).all() and 0 <= lo < hi):
                raise ValueError(f"prior: 'object_mass_range' must be 0 <= min < max [kg], got {self.object_mass_range}")
            units.warn_if_grams(hi, "prior: 'object_mass_range'")
        elif tuple(self.object_mass_range) != PriorConfig.object_mass_range:  # said, not silently dropped
            raise ValueError(f"prior: 'object_mass_range' ({tuple(self.object_mass_range)}) needs object_mass_unknown "
                             "(the object's weight identified); without it the filter carries no object weight, and a "
                             "weighed object_mass makes its own range")
        if self.com_prior not in COM_PRIORS:
            raise ValueError(f"prior: 'com_prior' must be one of {COM_PRIORS}, got '{self.com_prior}'")
        if not (np.isfinite(self.com_half_width) and self.com_half_width >= 0):
            raise ValueError(f"prior: 'com_half_width' must be a finite distance >= 0 [m], got {self.com_half_width}")
        units.check_length(self.com_half_width, "prior: 'com_half_width'")
        return self

    def contact_bounds(self, hand: HandModel) -> tuple[np.ndarray, np.ndarray]:
        """Each finger's contact range along its last link [m]: (lower (N,), upper (N,)).

        Raises ``ValueError`` naming the finger when ``contact_limits`` is not an
        increasing pair of finite distances or reaches past a finger's last link (and the
        field when ``contact_half_width`` is longer than every last link).
        """
        L = np.asarray(hand.distal_length, float)
        # metres: a half-width past every pad draws the contacts anywhere on them, and 0.5
        # meant as mm had run so
        units.check_length(self.contact_half_width, "prior: 'contact_half_width'", float(L.max()),
                           f"more than the longest last link ({1e3 * L.max():.0f} mm)")
        if self.contact_limits is None:
            short = [f"'{name}' ({length * 1e3:.1f} mm)" for name, length in zip(hand.names, L, strict=True)
                     if not length > CONTACT_MIN]
            if short:
                raise ValueError(f"prior: the last link of {', '.join(short)} is no longer than the contacts' "
                                 f"least distance from the distal joint ({CONTACT_MIN * 1e3:.1f} mm); give "
                                 "'contact_limits'")
            return np.full(hand.N, CONTACT_MIN), L.copy()
        lim = np.asarray(self.contact_limits, float)
        if lim.shape != (2,) or not (np.isfinite(lim).all() and 0 <= lim[0] < lim[1]):
            raise ValueError(f"prior: 'contact_limits' must be [min, max] [m] with 0 <= min < max, "
                             f"got {self.contact_limits}")
        # metres: [5, 38] meant as mm had been said to reach "38000.0 mm" past the links
        units.check_length(lim, "prior: 'contact_limits'")
        past = [f"'{name}' ({length * 1e3:.1f} mm)" for name, length in zip(hand.names, L, strict=True)
                if lim[1] > length + 1e-12]
        if past:
            raise ValueError(f"prior: 'contact_limits' max {lim[1] * 1e3:.1f} mm reaches past the last link of "
                             f"{', '.join(past)}; lower it, or leave it out to use each finger's own length")
        return np.full(hand.N, lim[0]), np.full(hand.N, lim[1])


def contact_plane_normals(p: np.ndarray) -> np.ndarray:
    """(M, 3) unit normals of the least-squares planes through each hypothesis' contacts
    ``p`` (M, N, 3), N >= 3, turned to the side of (p_1 - p_0) x (p_2 - p_0). The singular
    vector alone has no sign of its own: three contacts lie in their plane exactly, and
    rounding at 1e-15 m turned half of 20,000 hypotheses' normals over (a draw along it then
    changed with any change of the code's last digits, though its distribution did not)."""
    normal = np.linalg.svd(p - p.mean(axis=1, keepdims=True))[2][:, -1]
    side = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    return np.where((np.einsum("pi,pi->p", normal, side) < 0)[:, None], -normal, normal)


@dataclass
class SettledAngles:
    """How the grasp's settled angles follow one unknown hand parameter
    (``PriorConfig.angle_centers`` "settled"): the filter's model settled under the grasp's
    tendon command from the nominal grasp with that parameter at each of ``values`` and
    every other unknown at its prior middle (:meth:`SelfIdentificationFilter.settled_angles`)."""

    parameter: str  # "stiffness" or "link" (a finger's proximal link)
    finger: int
    joint: int  # the spring's joint; 0 for a link
    values: np.ndarray  # (S,) increasing [N m/rad] or [m]
    theta: np.ndarray  # (S, N, K) the settled angles at each value [rad]

    def at(self, v) -> np.ndarray:
        """(P, N, K) angles at the parameter values ``v`` (P,): linear interpolation (in log v
        for a spring, a scale parameter), held at the table's ends."""
        x = np.log(self.values) if self.parameter == "stiffness" else self.values
        u = np.log(v) if self.parameter == "stiffness" else np.asarray(v, float)
        flat = self.theta.reshape(x.shape[0], -1)
        out = np.stack([np.interp(u, x, flat[:, c]) for c in range(flat.shape[1])], axis=-1)
        return out.reshape(np.shape(v) + self.theta.shape[1:])


#: PriorConfig.angle_centers
ANGLE_CENTERS = ("nominal", "settled")
#: How many values of each unknown spring or link SettledAngles settles the grasp at (an
#: odd count puts the prior's middle on a node).
SETTLED_VALUES = 7

#: Where the rolling model's centre of mass is drawn (PriorConfig.com_prior).
COM_PRIORS = ("contacts", "balanced", "shape")
#: Distributions of an unknown stiffness in its range (PriorConfig.stiffness_prior).
STIFFNESS_PRIORS = ("log_uniform", "uniform")
#: What a held hypothesis predicts (FilterConfig.held_motion).
HELD_MOTIONS = ("still", "elastic")
#: How a move carries the gravity loads (FilterConfig.gravity_loads).
GRAVITY_LOADS = ("held", "following")

#: Sources of an elastic tendon's stretch (FilterConfig.tendon_reference).
TENDON_REFERENCES = ("commanded", "implied")

#: Shapes of the measurement likelihood (FilterConfig.likelihood).
LIKELIHOODS = ("gaussian", "student_t")

#: Where the filter asks a hypothesis' equilibrium to be stable (FilterConfig.stable_grasps).
STABLE_GRASPS = ("off", "prior", "always")
#: How a move carries the hypotheses (FilterConfig.motion_model).
MOTION_MODELS = ("pinned", "rolling")
#: How the rolling model's normals are drawn around their guess (FilterConfig.normal_tilt).
NORMAL_TILTS = ("cone", "in_plane")
#: Which guess the rolling model's normals are drawn around (FilterConfig.normal_guess).
NORMAL_GUESS_CHOICES = (*motion_rolling.NORMAL_GUESSES, "either")
#: The object's surface under the rolling pads (FilterConfig.object_curvature).
OBJECT_CURVATURES = ("flat", "round")
#: The smallest surface radius a round hypothesis takes [m] (its contacts' circle less the
#: pad radius: three pads on a tiny circle would otherwise give a radius near zero).
MIN_CURVATURE_RADIUS = 0.005


def weighed_mass_range(mass, tolerance) -> tuple[float, float]:
    """The object's mass range [kg] (PriorConfig.object_mass_range) for an object weighed at
    ``mass`` [kg] and known within +-``tolerance`` (a fraction of it, in (0, 1)): (mass (1 -
    tolerance), mass (1 + tolerance)). Raises ``ValueError`` naming a bad mass or tolerance."""
    if not (kinematics.is_number(mass) and np.isfinite(mass) and mass > 0):
        raise ValueError(f"object_mass must be the object's weighed mass, a finite number > 0 [kg], got {mass!r}")
    if not (kinematics.is_number(tolerance) and 0 < tolerance < 1):
        raise ValueError(f"object_mass_tolerance must be a fraction of the mass in (0, 1), got {tolerance!r}")
    units.warn_if_grams(mass, "object_mass")
    return float(mass) * (1.0 - tolerance), float(mass) * (1.0 + tolerance)


@dataclass
class FilterConfig:
    """Likelihood, resampling and convergence settings (DESIGN.md section 6)."""

    # Number of particles M (the paper: 60,000).
    particles: int = 20_000
    # Position noise of the POM measurement plus model error, sigma_p [m].
    sigma_position: float = 0.3e-3
    # Rotation noise of the POM measurement plus model error, sigma_r [rad].
    sigma_rotation: float = np.deg2rad(1.5)
    # The likelihood's width: both sigmas above are multiplied by this factor (sigmas()).
    # Wider, the filter learns less from each measurement and its intervals allow more of the
    # model's mismatch to the plant. None: 1 here; an identification run takes its plant's
    # and experiment's default (vlr_drake.identify.LIKELIHOOD_WIDTH: 1.5 for the known hand
    # and 1.75 for the stiffness on the physics plant, measured there).
    likelihood_width: float | None = None
    # Shape of the likelihood of each 3-D error (position, rotation): "gaussian" (default)
    # or "student_t", a multivariate t with ``likelihood_dof`` degrees of freedom whose
    # scale makes it agree with the Gaussian near zero error (scale^2 = sigma^2 (nu + 3) /
    # nu): heavy tails, so that an occasional large error (a slip or a stuck step the VLR
    # does not model) costs a hypothesis log(error) instead of error squared. Measured on
    # the physics plant (nu = 4, 20,000 particles, 100 iterations, seeds 0-1 or 0-2), against
    # the Gaussian: known hand, apple / gelatin box / wine glass 0.89 deg against 1.05,
    # truth inside 0.89 either way, no run converged (with sigma_r 0.75 deg as well: 1.08
    # deg, 0.83 inside); but flat screwdriver 2.43 / 4.12 against 2.51 / 2.48 deg, NH2 4.40
    # mm against 3.48, NH1 2.01 / 5.90 against 0.25 / 5.85 mm, toy block stiffness 0.049
    # against 0.044 N m/rad. So the default stays Gaussian.
    likelihood: str = "gaussian"
    likelihood_dof: float = 4.0
    # Motion-model error, relative: each particle's predicted POM motion of this iteration
    # (translation |dt|, rotation |dr|) adds c |dt| and c |dr| in quadrature to sigma_p and
    # sigma_r. 0 trusts Gamma exactly (the model plant); a real hand or the physics plant,
    # whose motion the pinned-contact VLR predicts in direction but not in magnitude, needs
    # c of about 0.5-1 for honest intervals.
    motion_error: float = 0.0
    # Tendon model of Gamma: "elastic" (default; stiffness identifiable) or "ideal".
    tendon: str = "elastic"
    # Where an elastic tendon's stretch comes from. "commanded" (default): before each move a
    # hypothesis' stretch is s = l - R theta, with l the absolute tendon command (the motors'
    # positions: known on every plant, and on hardware after the tendon-zero calibration), so
    # the motor state is evidence too. "implied": the paper's Eq. 7 ("independent of the
    # absolute tendon length"): the stretch that holds the hypothesis' grasp in equilibrium,
    # carried through moves. Under "implied" a finger's proximal/distal split is a ridge the POM
    # barely sees; on the physics plant the cloud slid along it (apple, 0.5 mm actions, seeds
    # 0-2: proximal error 3.0 -> 3.9, 4.8, 2.9 deg in 40 iterations; "commanded": -> 0.23,
    # 0.23, 0.36 deg, every truth inside its 95% interval). No effect with the ideal tendon.
    tendon_reference: str = "commanded"
    # A particle whose move fails with the whole action is retried with the action ramped in
    # 4, 16, ... substeps up to this many (quasi-static continuation; motion.move). Without
    # it, particles near a fold die more often than the truth does, which biases the cloud
    # away from the truth: with the paper's implied tendon state the truth fell inside the
    # 95% joint intervals 85% of the time with 0 and 89% with 16 (model plant, 12 seeds).
    # With the commanded tendon state 4 is enough (12 seeds: coverage 1.00 with 4, 0.97 with
    # 16) and cheaper: a particle with no equilibrium costs up to 7 + 4 x 7 Newton steps
    # instead of 147 (60,000 particles: 0.43 s per iteration instead of 0.48). A review
    # (2026-11-27) found the truth itself failing to move with 4, and killed: a filter of ten
    # copies of the truth stepped beside the run (model plant, whose truth moves with 64; NH2,
    # 5,000 particles, seeds 0-23) lost them on seeds 11 and 19, never with 16 or 64 (seed 19's
    # cloud then re-initialised 11-23 times and ended 18 deg off). But 16 was measured the
    # less honest: the spring inside its 95% interval in 35 of 40 runs against 39 of 40
    # (stiffness, 5,000 particles, 60 iterations, seeds 0-39; the same error, 0.0116 N m/rad),
    # and at 20,000 particles 4 and 64 gave the same rows (NH2 seeds 0-35: links 1.40 / 1.38
    # mm, 69 of 72 inside either way; known hand seeds 0-23: proximal joints 0.62 / 0.57 deg,
    # joints inside 0.99 / 0.97), 64 at a third more time (16: median iteration 143 against
    # 122 ms at 60,000 particles). So 4 stays: a run that loses its truth re-initialises, and
    # draws from the whole prior when it does so again within REINIT_RECENT iterations.
    max_substeps: int = 4
    # ``max_substeps`` of the first move after (re)initialisation, which carries each prior
    # draw from its own equilibrium to the one under the motors' command; None (default):
    # ``max_substeps``, as every other move. 0 makes the first iteration fast: the
    # continuation's retries cost that move a quarter of its time (model plant, 60,000
    # particles: first iteration 157-162 ms with 0, 190-201 ms with None), and the draws
    # they rescue (0.07-0.7% of them, seeds 0-3) are far from the commanded equilibrium the
    # plant is at, so the first measurement gives them 0.00001-0.35% of the weight. But
    # replays of the physics traces (2026-11-25) with 0 gave the same known hand (1.08
    # against 1.07 deg) and spring (0.0255 against 0.0258 N m/rad) and worse novel hands
    # (NH1 3.13 against 2.54 mm, NH3 3.10 against 2.71; NH2 2.19 against 2.25), whose
    # failed draws are held rather than rescued (stuck_probability), so it is not the
    # default. Re-measured with the novel hands' balanced tensions (replays of the fifteen
    # 240-iteration traces per hand): 1.53 / 3.20 / 1.54 mm against 1.21 / 2.72 / 1.35.
    first_move_substeps: int | None = None
    # Probability that a hypothesis whose move finds no equilibrium (even with the
    # continuation) is held where it was by friction, which the VLR does not model (the
    # physics plant and a real hand have it). Such a hypothesis keeps its joint angles,
    # predicts that the POM did not move, and weighs stuck_probability times the camera's
    # likelihood of that; 0 discards it. None: 0 here; an identification run takes its
    # plant's and experiment's default (vlr_drake.identify.STUCK_PROBABILITY).
    stuck_probability: float | None = None
    # What a held hypothesis (stuck_probability > 0) predicts: "still", the POM does not
    # move; or "elastic", friction holds it where it is, so its tendons carry the stretch of
    # its own equilibrium there (motion.equilibrium) instead of the commanded one, and the
    # action moves it from that state by Gamma (held still where even that finds none).
    # Measured on NH1 (physics, 20,000 particles, replays of seeds 0-14): on seed 11 the
    # plant's state has a commanded equilibrium in only 41% of the steps at the true link
    # (95% at +5 mm; vlr-drake replay --statics), the held hypotheses near the truth
    # predicted no motion while the apple moved, and the cloud converged 15 mm long with a
    # third of its joints inside, although fixed-length replays favour the true length by
    # 115 (log evidence). "elastic" took the link errors from 3.90 mm (mean of 15; 15.0 at
    # most) to 2.06 (3.9 at most), but the joints from 0.88 inside their intervals to 0.47
    # (mean joint error 3.5 deg): a hypothesis held at any angles no longer has the
    # commanded statics to tell its angles apart. With stuck_probability 0.3 as well (six
    # seeds) the links were worse again and the joints no better (measured while the
    # elastically moved ones escaped the 0.3; not measured again since). Giving a held hypothesis
    # the cloud's average likelihood (measured, not built) removed NH1's collapses (3.22 mm,
    # joints inside 0.90) but doubled its joint error (3.86 deg against 1.67) and broke NH2
    # and NH3 (7.05 and 9.24 mm against 3.09 and 3.75). So "still" stays.
    held_motion: str = "still"
    # Start every prior draw at rest under the motors' command (tendon_reference "commanded"):
    # each drawn grasp is moved by Gamma with a zero action before it is attached to the
    # measured POM pose, and draws with no physical equilibrium there are drawn again.
    # Without it (False, the default) a draw is an equilibrium of its own implied tendon
    # state, and the first iteration's move carries it to the commanded one: its predicted
    # motion includes that settling, which the camera never saw. Settled, the first
    # iteration is cheaper (60,000 particles, model plant: 3% of the moves fail instead of
    # 15%, 0.20 s instead of 0.25 s), but on the physics plant the estimates were worse
    # (known hand, 20,000 particles, 100 iterations, seeds 0-1: apple 1.11 / 0.65 deg against
    # 0.78 / 0.39, wine glass 1.54 / 1.24 against 1.62 / 1.06, gelatin box 1.48 / 2.02
    # against 1.05 / 1.41; NH2 seeds 0-2 4.23 mm against 3.48): friction holds the plant's
    # grasp away from the VLR's commanded equilibrium, and the settled cloud starts there.
    settle_prior: bool = False
    # Newton tolerances of the moves (a key of motion.TOLERANCES). "filter" solves each
    # hypothesis to ~1e-8 rad, far finer than the camera resolves, and saves a Newton step on
    # about half the particles (60,000-particle move 1.31-1.35x faster than the previous
    # kernels instead of 1.22-1.25x). With it, physics handwriting 'SCIENCE' seed 0 once had
    # 34-66 "no_equilibrium" control steps; the cause was the controller's use of an
    # unphysical mean estimate (control.filter_model_fn now falls back to a hypothesis), and
    # with that fallback "filter" wrote seeds 0-1 at 0.11 and 0.16 mm. The physics table's
    # identification rows with "filter" (replays of its 40 traces, vlr-drake replay): known
    # hand 1.66 deg against 1.71, stiffness 0.037 against 0.040 N m/rad, NH1 2.70 / NH2 3.78 /
    # NH3 3.82 mm against 2.85 / 3.23 / 3.84; joints inside as often except on the stiffness
    # (0.57 against 0.70): a perturbation within the seeds' scatter, not an improvement, so
    # "tight" stays the default.
    newton_tolerance: str = "tight"
    # Newton steps after which a hypothesis within the physical tolerances (motion.LOOSE_*:
    # angles within ~1e-5 rad of the tight solution, at most 3e-4 near the mirror-image
    # grasps; the camera's sigma is 0.026 rad) is accepted rather than iterated on to
    # ``newton_tolerance`` (motion.move's ``loose_after``; None: only at the 30-step cap, the
    # behaviour before). Near the Model O's symmetric grasps Newton converged only linearly,
    # and those 3-4% of the hypotheses ran to the cap, a fifth of the move's Newton steps:
    # with 8, a 60,000-particle move inside the filter took 9-14% fewer steps. (That tail
    # was the KKT matrix's regulariser's, set on every step until the forty-fifth session:
    # without it Newton is quadratic there, and only within a few mrad of exact mirror
    # images, where a first attempt fails and is retried regularised, is it linear; see
    # motion._move_lanes.) The results
    # move within the seeds' scatter: replays of the physics table's 40 runs with the same
    # code gave known hand 1.69 deg (1.71 with None), stiffness 0.0365 N m/rad (0.0403),
    # NH1 / NH2 / NH3 2.23 / 3.95 / 3.90 mm (2.97 / 3.23 / 3.84; held-out seeds 5-9: 2.52 /
    # 2.51 / 4.08 against 3.42 / 2.20 / 3.89), the log evidence within about 1 per run; on
    # the model plant (informative actions, seeds 0-35) the truth lay inside 0.97 / 0.94 of
    # the joint / contact intervals, against 0.96 / 0.92 with None.
    newton_loose_after: int | None = 8
    # Liu-West kernel width h (fraction of the cloud's spread added as jitter). DESIGN.md
    # section 6 suggests about 0.1 and tempering below about 10% of M; 0.2 and 0.3 are what
    # the physics runs were tuned to (docs/results.md, "Tempering, roughening, a mismatch that
    # repeats": 0.15 and 0.5 each cost some row, 0.3 roughening did not help the links).
    roughening: float = 0.2
    # Temper the likelihood when ESS would fall below this fraction of M.
    ess_fraction: float = 0.3
    # Resample (then roughen) when the ESS of the accumulated weights falls below this
    # fraction of M; weights accumulate over iterations until then.
    resample_fraction: float = 0.5
    # Fraction of the way each attachment moves towards the measured POM per iteration.
    anchor_fraction: float = 0.3
    # Convergence: mean 95% interval of the joint angles below this [deg] ...
    convergence_deg: float = 2.0
    # ... measured as the "half_width" or the "full_width" of the interval.
    convergence_measure: str = "half_width"
    # Convergence of the identified hand parameters as well: a run has converged only when,
    # besides the joints, every unknown spring's and link length's 95% interval (measured as
    # ``convergence_measure`` says) is below this fraction of its estimate (0.05: a 0.15 N
    # m/rad spring within +-0.0075, a 50 mm link within +-2.5 mm). None: the joints alone
    # (the paper's test, and the behaviour before 2026-11-27, twenty-fourth session), which
    # let a run stop with its spring's interval spanning half its prior. Measured on the
    # model plant (identify's defaults, 120 iterations): the spring 0.0192 +- 0.0267 ->
    # 0.0070 +- 0.0103 N m/rad (seeds 0-9), NH1 / NH2 / NH3 1.42 / 1.37 / 1.38 -> 0.67 /
    # 0.64 / 0.78 mm (seeds 0-4), joints inside 1.00 / 0.93 / 0.97 (docs/results.md).
    # (An unknown object mass, which may be near zero, is not in the test.)
    parameter_convergence: float | None = 0.05
    # Re-initialise when the best particle is further than this many sigmas (Mahalanobis).
    divergence_sigmas: float = 12.0
    # Gravity in the palm frame P [m/s^2], for the weight of the fingers' links (and of the
    # object, with PriorConfig.object_mass_unknown): each hypothesis' moves and equilibria
    # carry the links' weight (motion.move's gravity; HandModel.link_weight_torque), held at
    # the angles before each move or following them, as ``gravity_loads`` says; Eq. 9 does
    # not have it. Zero (the default): Eq. 9 as the paper. The physics plant sets it from
    # its mounting (identify's link_weight); a hardware scenario gives its hand's.
    gravity_palm: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    # How a move carries those loads: "held" (default), as joint torques evaluated at each
    # hypothesis' angles before the move and held through it (motion.move's
    # external_torque; they follow the hypothesis from one action to the next), or
    # "following", as a potential that follows the angles within the move, with its
    # stiffness in Gamma's Newton matrix (motion.move's gravity and object_load: exact).
    # The object's weight needs "following": held, its stiffness (half the springs', palm
    # down) is missed within every move, and the filter drove the mass to ~0 on the physics
    # plant (wine glass 12 g against 133; with the mass fixed at its truth the log evidence
    # fell by 72). For the links' weight "held" measured better on the known hand and the
    # novel fingers, "following" on the stiffness (vlr_drake.identify.GRAVITY_LOADS). None:
    # the experiment's default where identify or the builder sets the filter up, else "held".
    gravity_loads: str | None = None
    # Which equilibria must be stable, a strict minimum of Eq. 9's energy on the grasp
    # manifold (motion.stable_equilibria; Newton's stationary points include saddles, which
    # a hand balances on rather than holds): "always", the prior's draws and every move's
    # result (an unstable one weighs nothing, as an unsolved one); "prior", the draws only;
    # "off", neither (the behaviour before 2026-11-27, twenty-third session).
    stable_grasps: str = "off"
    # The motion model of a move (Gamma and Lambda): "pinned" (default), the paper's Eq. 8-9,
    # each pad's centre pinned to the object (the object's pose follows from the contacts,
    # Lambda); or "rolling" (vlr_drake.motion_rolling.move_rolling): the pads roll over the
    # object, whose pose is an unknown of the equilibrium, with the links' weight and, with
    # PriorConfig.object_mass_unknown, the object's weight at its centre of mass following
    # the angles. Each hypothesis then carries the object's outward normals at its contacts
    # (drawn within ``normal_cone_deg`` of a guess from its contacts' centroid, fixed in the
    # object's frame, roughened with the rest) and its centre of mass. Started from the
    # physics plant's true state the rolling model predicts the toy block's motion five times
    # better than Eq. 9 (the agreement command's rolling_* fields). It needs the elastic
    # tendon, and does not check stability (stable_grasps "always" or "prior") or hold moves
    # elastically (held_motion "elastic") or settle the prior's draws (settle_prior), all of
    # which Eq. 9 would do, and takes its tendons' stretch from the motors'
    # command (tendon_reference "commanded"). Its Newton is compiled (numba, 64 hypotheses
    # side by side per thread), but its KKT system is 21 square against Eq. 9's 9: a move
    # of 60,000 hypotheses costs about seven times the pinned model's (0.42 s against 0.056
    # s, 2 cores; `vlr-drake bench rolling`), a replay of a 240-step stiffness trace at
    # 20,000 particles 43 s (docs/results.md).
    motion_model: str = "pinned"
    normal_cone_deg: float = 20.0
    # How the rolling model's normals leave their guess (NORMAL_TILTS): "cone", uniformly over
    # the spherical cap of ``normal_cone_deg``; or "in_plane", tilted only within the finger's
    # flexion plane, by an angle uniform in +-normal_cone_deg. A tilt out of that plane barely
    # changes the roll (5 deg: 0.049 against 0.051 mm per action on the toy block), a tilt in
    # it trades off against the joints' springs (docs/results.md, "The rolling model in the
    # filter..."): "in_plane" spends the hypotheses on the three angles that matter. The
    # roughening's covariance keeps such normals in their planes.
    normal_tilt: str = "cone"
    # Which guess the normals are drawn around (NORMAL_GUESSES;
    # vlr_drake.motion_rolling.guessed_normals): "flexion_plane", the direction from the
    # contacts' centroid within each finger's flexion plane (a flat-faced object gripped
    # face-on: 0.2 deg off on the toy block, 34-38 deg off at the apple's side-by-side
    # fingers); "circle", the direction from the centre of the circle through the contacts (a
    # round object: within 2 deg on the apple, 35 deg off on the block); or "either", each
    # hypothesis drawing its guess from one of the two with probability 1/2 (an object of
    # unknown shape: the measurements weigh the two).
    normal_guess: str = "flexion_plane"
    # The object's surface under the pads (OBJECT_CURVATURES): "flat" (default), each pad's
    # roll linear in its turn, as over a flat face; or "round": the hypotheses that guess a
    # round object (normal_guess "circle", or that half of "either") roll over a sphere whose
    # radius is their contacts' circle's less the pad radius (a ball on a ball: the pads'
    # centres keep their distance from the object's centre, which adds the roll's own
    # stiffness; motion_rolling.move_rolling's curvature_radius), the others as "flat". From
    # the plant's truth on NH2's apple the rolling reference so predicts an action to 0.134 mm
    # / 0.066 deg against the flat roll's 0.193 / 0.095, and moves every joint as the plant
    # does (the agreement command's rolling_shaped fields; docs/results.md).
    object_curvature: str = "flat"

    def validate(self) -> FilterConfig:
        if not kinematics.is_count(self.particles, 10):
            raise ValueError(f"filter: 'particles' must be an integer >= 10, got {self.particles!r}")
        for name in ("sigma_position", "sigma_rotation", "likelihood_dof", "divergence_sigmas",
                     "motion_error", "convergence_deg", "roughening", "ess_fraction", "resample_fraction",
                     "anchor_fraction", "stuck_probability", "likelihood_width"):
            v = getattr(self, name)
            if not (kinematics.is_number(v) or (v is None and name in ("stuck_probability", "likelihood_width"))):
                raise ValueError(f"filter: '{name}' must be a number, got {v!r}")
        for name in ("sigma_position", "sigma_rotation", "likelihood_dof", "divergence_sigmas"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"filter: '{name}' must be a positive finite number, got {v}")
        # metres and radians (5000 and 30 had run, then 0.3 and 1.5)
        units.check_pose_noise(self.sigma_position, "filter: 'sigma_position'", self.sigma_rotation,
                               "filter: 'sigma_rotation'")
        for name in ("motion_error", "convergence_deg"):  # convergence_deg 0: never converged (a benchmark)
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"filter: '{name}' must be a finite number >= 0, got {v}")
        if not isinstance(self.settle_prior, bool | np.bool_):  # "false" had been read as true
            raise ValueError(f"filter: 'settle_prior' must be True or False, got {self.settle_prior!r}")
        if self.tendon not in motion.TENDON_MODELS:
            raise ValueError(f"filter: 'tendon' must be one of {motion.TENDON_MODELS}, got '{self.tendon}'")
        if self.tendon_reference not in TENDON_REFERENCES:
            raise ValueError(
                f"filter: 'tendon_reference' must be one of {TENDON_REFERENCES}, got '{self.tendon_reference}'")
        if self.likelihood not in LIKELIHOODS:
            raise ValueError(f"filter: 'likelihood' must be one of {LIKELIHOODS}, got '{self.likelihood}'")
        if self.stuck_probability is not None and not 0 <= self.stuck_probability <= 1:
            raise ValueError(f"filter: 'stuck_probability' must be in [0, 1], got {self.stuck_probability}")
        w = self.likelihood_width
        if w is not None and not (np.isfinite(w) and w > 0):
            raise ValueError(f"filter: 'likelihood_width' must be None or a positive finite number, got {w}")
        if self.gravity_loads is not None and self.gravity_loads not in GRAVITY_LOADS:
            raise ValueError(f"filter: 'gravity_loads' must be one of {GRAVITY_LOADS}, got '{self.gravity_loads}'")
        if self.stable_grasps not in STABLE_GRASPS:
            raise ValueError(f"filter: 'stable_grasps' must be one of {STABLE_GRASPS}, got '{self.stable_grasps}'")
        if self.held_motion not in HELD_MOTIONS:
            raise ValueError(f"filter: 'held_motion' must be one of {HELD_MOTIONS}, got '{self.held_motion}'")
        if not kinematics.is_count(self.max_substeps):
            raise ValueError(f"filter: 'max_substeps' must be an integer >= 0, got {self.max_substeps!r}")
        if self.first_move_substeps is not None and not kinematics.is_count(self.first_move_substeps):
            raise ValueError(f"filter: 'first_move_substeps' must be None or an integer >= 0, "
                             f"got {self.first_move_substeps!r}")
        if self.newton_tolerance not in motion.TOLERANCES:
            raise ValueError(f"filter: 'newton_tolerance' must be one of {tuple(motion.TOLERANCES)}, "
                             f"got '{self.newton_tolerance}'")
        n = self.newton_loose_after
        if n is not None and not (kinematics.is_count(n, 1) and n <= motion.MAX_ITER):
            raise ValueError(f"filter: 'newton_loose_after' must be None or in [1, {motion.MAX_ITER}], "
                             f"got {n!r}")
        if not 0 < self.roughening < 1:
            raise ValueError("filter: 'roughening' must be in (0, 1)")
        if not 0 < self.ess_fraction <= 1:
            raise ValueError("filter: 'ess_fraction' must be in (0, 1]")
        if not 0 <= self.resample_fraction <= 1:
            raise ValueError(f"filter: 'resample_fraction' must be in [0, 1], got {self.resample_fraction}")
        if 0 < self.resample_fraction <= self.ess_fraction:
            # measured on the physics traces: with resample_fraction 0.25 the filter almost
            # never resampled, and the links came out 4.5-8.9 mm off against 2.3-2.7
            # (docs/results.md; a model-plant run: 1 resampling in 25 iterations)
            raise ValueError(f"filter: 'resample_fraction' ({self.resample_fraction}) must be above 'ess_fraction' "
                             f"({self.ess_fraction}): the tempering holds the ESS at about ess_fraction x M or above, so "
                             "the filter would almost never resample and roughen (0: never, on purpose)")
        if not 0 <= self.anchor_fraction <= 1:
            raise ValueError("filter: 'anchor_fraction' must be in [0, 1]")
        if self.convergence_measure not in ("half_width", "full_width"):
            raise ValueError("filter: 'convergence_measure' must be 'half_width' or 'full_width'")
        c = self.parameter_convergence
        if c is not None and not (kinematics.is_number(c) and np.isfinite(c) and c > 0):
            raise ValueError(f"filter: 'parameter_convergence' must be None or a positive finite fraction, got {c!r}")
        try:
            g = np.asarray(self.gravity_palm, float)
        except (TypeError, ValueError):  # text, None in a list: named below
            g = np.full(1, np.nan)
        if g.shape != (3,) or not np.all(np.isfinite(g)):
            v = self.gravity_palm  # (a number has no list() to show: the message had raised a TypeError)
            raise ValueError(f"filter: 'gravity_palm' must be 3 finite numbers [m/s^2], got "
                             f"{list(v) if isinstance(v, list | tuple) else repr(v)}")
        units.check_gravity(g, "filter: 'gravity_palm'")
        if self.motion_model not in MOTION_MODELS:
            raise ValueError(f"filter: 'motion_model' must be one of {MOTION_MODELS}, got '{self.motion_model}'")
        if not (kinematics.is_number(self.normal_cone_deg) and 0 <= self.normal_cone_deg < 90):
            raise ValueError(f"filter: 'normal_cone_deg' must be in [0, 90) [deg], got {self.normal_cone_deg!r}")
        if self.normal_tilt not in NORMAL_TILTS:
            raise ValueError(f"filter: 'normal_tilt' must be one of {NORMAL_TILTS}, got '{self.normal_tilt}'")
        if self.normal_guess not in NORMAL_GUESS_CHOICES:
            raise ValueError(f"filter: 'normal_guess' must be one of {NORMAL_GUESS_CHOICES}, got '{self.normal_guess}'")
        if self.object_curvature not in OBJECT_CURVATURES:
            raise ValueError(f"filter: 'object_curvature' must be one of {OBJECT_CURVATURES}, got "
                             f"'{self.object_curvature}'")
        if self.object_curvature == "round" and self.normal_guess == "flexion_plane":
            raise ValueError("filter: object_curvature 'round' rolls the hypotheses that guess a round object, and "
                             "normal_guess 'flexion_plane' guesses none: use normal_guess 'circle' or 'either'")
        if self.motion_model == "rolling":
            for name, bad, why in (("tendon", "ideal", "the rolling model has the elastic tendon only"),
                                   ("tendon_reference", "implied", "the implied stretch would be Eq. 9's equilibrium"),
                                   ("stable_grasps", "always", "the rolling model does not check stability"),
                                   ("stable_grasps", "prior", "the draws' stability would be Eq. 9's"),
                                   ("settle_prior", True, "the draws would settle at Eq. 9's equilibrium"),
                                   ("held_motion", "elastic", "the rolling model holds failed moves still")):
                if getattr(self, name) == bad:
                    raise ValueError(f"filter: motion_model 'rolling' does not take {name} '{bad}': {why}")
        return self

    def sigmas(self) -> tuple[float, float]:
        """(sigma_p [m], sigma_r [rad]) of the likelihood: the sigmas times ``likelihood_width``."""
        width = 1.0 if self.likelihood_width is None else float(self.likelihood_width)
        return self.sigma_position * width, self.sigma_rotation * width


# --------------------------------------------------------------------------------------
# Particles
# --------------------------------------------------------------------------------------


@dataclass
class ParticleSet:
    """M hypotheses, particles on the leading axis."""

    theta: np.ndarray  # (M, N, K)
    a: np.ndarray  # (M, N)
    stiffness: np.ndarray  # (M, N, K) or (1, N, K) when known
    link_lengths: np.ndarray  # (M, N, K-1) or (1, N, K-1) when known
    stretch: np.ndarray  # (M, N) equilibrium tendon stretch
    p_O: np.ndarray  # (M, N, 3) attachment: contacts in the POM frame
    log_w: np.ndarray  # (M,)
    # The object's weight carried at each contact, as a mass [kg] (M, N) (PriorConfig.
    # object_mass_unknown), or None: a weightless object (Eq. 9).
    object_load: np.ndarray | None = None
    # FilterConfig.motion_model "rolling": the object's outward unit normals at the contacts
    # (M, N, 3) and, with an unknown object weight, its centre of mass (M, 3), both in the POM
    # frame; None otherwise.
    normals_O: np.ndarray | None = None
    com_O: np.ndarray | None = None
    # FilterConfig.object_curvature "round": the object's surface radius at each contact
    # (M, N) [m], inf where a hypothesis guesses a flat face; None otherwise.
    curvature_radius: np.ndarray | None = None

    @property
    def size(self) -> int:
        return self.theta.shape[0]

    def take(self, idx: np.ndarray) -> ParticleSet:
        """The particles ``idx`` (with repeats: a resampling's copies), with equal weights."""

        def rows(x):  # np.take copies rows about twice as fast as x[idx] (60,000 particles)
            return np.take(x, idx, axis=0)

        def pick(x):
            return rows(x) if x.shape[0] > 1 else x

        return ParticleSet(
            rows(self.theta), rows(self.a), pick(self.stiffness), pick(self.link_lengths),
            rows(self.stretch), rows(self.p_O), np.zeros(len(idx)),
            *(None if x is None else rows(x) for x in (self.object_load, self.normals_O, self.com_O,
                                                        self.curvature_radius)),
        )

    @classmethod
    def pool(cls, sets: list[ParticleSet]) -> ParticleSet:
        """The equal mixture of ``sets``, independent clouds of the same filter (one per draw
        of its randomness): every cloud's weights normalised and scaled by 1/len(sets), so
        that each cloud counts as one of the mixture's components whatever its size or its
        evidence (an evidence-weighted mixture collapses onto one draw: the log evidences of
        a trace's draws differ by 3-4 nats). The pooled cloud's weighted mean is the mean of
        the clouds' means. A quantity every cloud shares (a known spring or link, one row)
        stays one row, and must be the same in each."""
        if not sets:
            raise ValueError("ParticleSet.pool: no particle sets to pool")
        with np.errstate(divide="ignore"):  # a hypothesis of weight 0 stays one (log 0 = -inf)
            log_w = np.concatenate([np.log(normalise(s.log_w)) - np.log(len(sets)) for s in sets])

        def cat(name):
            xs = [getattr(s, name) for s in sets]
            if any(x is None for x in xs):
                if not all(x is None for x in xs):
                    raise ValueError(f"ParticleSet.pool: '{name}' is in some sets and not in others")
                return None
            # known: one row in a set of several particles (a one-particle set's row is both)
            if any(x.shape[0] == 1 and s.size > 1 for x, s in zip(xs, sets, strict=True)):
                if any(x.shape[0] != 1 for x in xs):
                    raise ValueError(f"ParticleSet.pool: '{name}' is known (one row) in some sets and one per "
                                     "particle in others")
                if any(not np.array_equal(x, xs[0]) for x in xs[1:]):
                    raise ValueError(f"ParticleSet.pool: '{name}' is known in every set but not the same in all")
                return xs[0]
            return np.concatenate(xs, axis=0)

        return cls(cat("theta"), cat("a"), cat("stiffness"), cat("link_lengths"), cat("stretch"), cat("p_O"),
                   log_w, *(cat(n) for n in ("object_load", "normals_O", "com_O", "curvature_radius")))


@dataclass
class StepReport:
    """What one filter iteration did (for logs, plots and the LeafSystem's outputs)."""

    iteration: int
    measured: bool
    ess: float
    beta: float
    solve_failures: int
    infeasible: int
    reinitialised: bool
    best_mahalanobis: float
    mean_interval_deg: float
    converged: bool
    # log p(measurement | the ones before) under the filter's model (log_evidence_increment);
    # NaN where nothing was measured.
    log_evidence: float = float("nan")
    # The widest unknown spring's or link length's 95% interval as a fraction of its
    # estimate (measured as FilterConfig.convergence_measure says); NaN where the hand's
    # parameters are all known.
    parameter_interval: float = float("nan")
    # Wall time of the iteration's phases [s]: "move" (the tendon state, Gamma, Lambda and the
    # feasibility tests), "weigh" (likelihood, evidence, tempering), "resample" (resampling, roughening,
    # re-anchoring), "reinitialise" (where it happened) and "estimate" (mean and intervals).
    timing_s: dict = field(default_factory=dict)


#: Fewer hypotheses than this give overconfident 95% intervals. On the model plant (known
#: hand, nine unknowns, identify's defaults, seeds 0-11, 2026-11-27) the fraction of the true
#: joint angles inside their intervals was 0.40 / 0.63 / 0.81 / 0.86 / 0.94 / 0.93 / 0.97 at
#: 100 / 300 / 1,000 / 2,000 / 3,000 / 10,000 / 20,000 particles, and every one of those runs
#: converged: a small cloud converges sure and wrong. More unknowns (a spring, replaced
#: fingers, more fingers) need more. A filter with fewer says so (FewParticlesWarning).
CALIBRATED_PARTICLES = 3000

#: The fraction of an action period T at which a diagram's filter takes the period's command
#: and measurement (SelfIdentificationSystem's default offset): the plant has settled by then.
FILTER_PHASE = 0.9

#: A re-initialisation within this many iterations of the last one draws from the whole
#: prior again, around the nominal grasp, not around the last estimate: the estimate the
#: last one centred on was lost again at once, and a box around it may no longer hold the
#: truth (a review found a cloud re-initialised 23 times in 60 iterations around estimates
#: 11-25 deg off, its box +-8.6 deg).
REINIT_RECENT = 5


#: A cloud whose live hypotheses (feasible, carrying weight) weigh less than this fraction of
#: it in effective sample size is lost, as one whose every hypothesis became implausible,
#: and is drawn again (SelfIdentificationFilter._live_floor). The tempering's own floor,
#: ``ess_fraction`` of the live cloud, is far above it: none of the 98 physics traces behind
#: the README's rows had a live cloud below ``ess_fraction`` (0.3) of its particles.
COLLAPSED_FRACTION = 0.01


def _finite_moves(res: motion.MoveResult, theta0, stretch0, kappa) -> motion.MoveResult:
    """``res`` with every hypothesis whose angles, stretch or tension are not finite made a
    failed move, at its angles before it (``theta0``) and the stretch the action left it
    (``stretch0``): the solvers keep failures at their start, and a NaN passed on would end
    the run in the contacts' check (a review's injected fault)."""
    bad = ~(np.isfinite(res.theta).all(axis=(1, 2)) & np.isfinite(res.stretch).all(axis=1)
            & np.isfinite(res.tension).all(axis=1))
    if not bad.any():
        return res
    keep = ~bad
    stretch = np.where(keep[:, None], res.stretch, stretch0)
    return dataclasses.replace(
        res, theta=np.where(keep[:, None, None], res.theta, theta0), stretch=stretch,
        tension=np.where(keep[:, None], res.tension, kappa[None] * stretch), ok=res.ok & keep,
        stable=res.stable & keep)


def balanced_shares(hand: HandModel) -> np.ndarray:
    """(N,) shares w >= 0, sum 1, nearest equal shares with sum_i w_i u_i = 0: the barycentre
    of the contacts at which the fingers' closing directions u_i (in the palm's plane)
    balance (PriorConfig.com_prior "balanced"; the Model O: 1/2 at the thumb, 1/4 at each
    finger). Equal shares where no such balance exists (fingers that do not oppose)."""
    N = hand.N
    A = np.vstack([hand.u[:, :2].T, np.ones((1, N))])
    b = np.array([0.0, 0.0, 1.0])
    w0 = np.full(N, 1.0 / N)
    w = w0 + np.linalg.lstsq(A, b - A @ w0, rcond=None)[0]  # the least change of w0 onto A w = b
    if np.any(w < -1e-12) or np.abs(A @ w - b).max() > 1e-9:
        return w0
    return np.clip(w, 0.0, None) / np.clip(w, 0.0, None).sum()


def _reflect_into(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """``x`` folded back into [lo, hi] at its bounds (as often as needed): a centred draw
    that reaches past a bound stays a density, where clipping would pile it on the bound."""
    w = hi - lo
    y = np.mod(np.asarray(x, float) - lo, 2.0 * w)
    return lo + np.where(y > w, 2.0 * w - y, y)


SHARE_FLOOR = 1e-12
"""The smallest share of the object's weight a contact is taken to carry where its log-ratio is
taken (:func:`_mass_and_log_ratios`): a share drawn or rounded to 0 keeps a finite log."""


def _mass_and_log_ratios(load: np.ndarray) -> np.ndarray:
    """(M, N) object loads -> (M, N): the mass (their sum) and the additive log-ratios of its
    shares, log(w_i / w_N) for i < N, the coordinates roughening moves them in
    (:func:`_shares_from_log_ratios` inverts). Liu-West's kernel with the full covariance
    draws the same cloud in any linear recombination of these, so the last contact's place as
    the reference is no choice. A cloud without mass has equal shares."""
    mass = load.sum(axis=1)
    shares = np.full(load.shape, 1.0 / load.shape[1])
    has = mass > 0
    shares[has] = load[has] / mass[has, None]
    log_w = np.log(np.maximum(shares, SHARE_FLOOR))
    return np.column_stack([mass, log_w[:, :-1] - log_w[:, -1:]])


def _shares_from_log_ratios(z: np.ndarray) -> np.ndarray:
    """(M, N - 1) additive log-ratios -> (M, N) shares on the simplex (a softmax with the
    last share's log-ratio 0): the inverse of :func:`_mass_and_log_ratios`'s shares."""
    full = np.column_stack([z, np.zeros(z.shape[0])])
    e = np.exp(full - full.max(axis=1, keepdims=True))
    return e / e.sum(axis=1, keepdims=True)


def _fold_keeping_spread(x: np.ndarray, lo: float, hi: float, rounds: int = 3) -> np.ndarray:
    """Roughened values ``x`` (M,) folded back into [lo, hi] (:func:`_reflect_into`) and,
    where some reached past a bound, spread about their mean back to the standard deviation
    they had before the fold (and folded again; ``rounds`` times): roughening keeps the
    cloud's variance, and a fold alone takes some away each time, so that a cloud the data
    leave alone had narrowed towards its range's middle (a prior's spread to 0.66-0.72 of
    itself in 60 roughenings). Values that all stayed inside are returned as they were."""
    x = np.asarray(x, float)
    y = _reflect_into(x, lo, hi)
    if not np.any((x < lo) | (x > hi)):
        return y
    target = x.std()
    for _ in range(rounds):
        m, sd = y.mean(), y.std()
        if not sd > 0:
            break
        y = _reflect_into(m + (y - m) * (target / sd), lo, hi)
    return y


class FewParticlesWarning(UserWarning):
    """A filter with fewer than :data:`CALIBRATED_PARTICLES` hypotheses: it runs, but its
    intervals are too narrow to be trusted (quick checks and tests, not results)."""


def warn_if_few_particles(config: FilterConfig, stacklevel: int = 2) -> None:
    """A :class:`FewParticlesWarning` when ``config`` asks for fewer than
    :data:`CALIBRATED_PARTICLES` (a filter does it when it is made; a system that makes its
    filter later, at its first measurement, when the system is made)."""
    if config.particles < CALIBRATED_PARTICLES:
        warnings.warn(FewParticlesWarning(
            f"{config.particles:,} particles: fewer than {CALIBRATED_PARTICLES:,} hypotheses give 95% "
            f"intervals that are too narrow (0.81 of the truths inside at 1,000, 0.40 at 100; "
            f"vlr_drake.filter.CALIBRATED_PARTICLES): use them for quick checks, not for results"),
            stacklevel=stacklevel + 1)


def cloud_estimate(hand: HandModel, ps: ParticleSet) -> dict:
    """Weighted mean and 95% intervals (:func:`interval95`) of every identified quantity of
    the cloud ``ps``: ``theta``, ``a``, ``stiffness``, ``link_lengths``, ``object_load``,
    ``object_mass`` (each with ``_lo`` and ``_hi``), the rolling model's mean ``normals_O``
    and ``object_com_O``, the joints' interval widths and the mean's ``contacts``."""
    w = normalise(ps.log_w)
    out = {}
    for name, x in [("theta", ps.theta), ("a", ps.a), ("stiffness", ps.stiffness),
                    ("link_lengths", ps.link_lengths)]:
        mean = np.tensordot(w, x, axes=1) if x.shape[0] > 1 else x[0]
        out[name] = mean
        if x.shape[0] > 1:
            lo, hi = interval95(x, w)
        else:
            lo = hi = x[0]
        out[f"{name}_lo"], out[f"{name}_hi"] = lo, hi
    load = np.zeros((1, hand.N)) if ps.object_load is None else ps.object_load
    for name, x in [("object_load", load), ("object_mass", load.sum(axis=1))]:
        out[name] = np.tensordot(w, x, axes=1) if x.shape[0] > 1 else x[0]
        lo, hi = interval95(x, w) if x.shape[0] > 1 else (x[0], x[0])
        out[f"{name}_lo"], out[f"{name}_hi"] = lo, hi
    if ps.normals_O is not None:  # the rolling model's object (POM frame): mean direction, centre of mass
        n = np.tensordot(w, ps.normals_O, axes=1)
        out["normals_O"] = n / np.linalg.norm(n, axis=-1, keepdims=True)
    if ps.com_O is not None:
        out["object_com_O"] = np.tensordot(w, ps.com_O, axes=1)
        out["object_com_O_lo"], out["object_com_O_hi"] = interval95(ps.com_O, w)
    out["theta_full_width"] = (out["theta_hi"] - out["theta_lo"]).ravel()
    out["theta_half_width"] = 0.5 * out["theta_full_width"]
    out["contacts"] = kinematics.contacts(hand, out["theta"][None], out["a"][None],
                                          out["link_lengths"][None])[0]
    return out


class SelfIdentificationFilter:
    """Algorithm 1 on the VLR model. The math only; ``systems/`` wraps it for Drake."""

    def __init__(self, hand: HandModel, config: FilterConfig, prior: PriorConfig, rng: np.random.Generator):
        self.hand = hand
        self.config = config.validate()
        self.prior = prior
        if not isinstance(rng, np.random.Generator):
            raise TypeError(f"filter: 'rng' must be a numpy.random.Generator (np.random.default_rng(seed)), "
                            f"got {type(rng).__name__}")
        warn_if_few_particles(self.config)
        self.rng = rng
        self.particles: ParticleSet | None = None
        self._first_move = False
        self.iteration = 0
        self.history: list[StepReport] = []
        self.estimates: list[dict] = []
        self.reinitialisations = 0
        self._last_reinit: int | None = None  # the iteration of the last re-initialisation
        self.resamples = 0
        self.tendon_command: np.ndarray | None = None  # absolute tendon pull l (N,) [m]
        self.settled: list[SettledAngles] = []  # PriorConfig.angle_centers "settled"
        N, K = hand.N, hand.K
        prior.validate(N, K)
        self._contact_bounds = prior.contact_bounds(hand)
        if self.config.motion_model == "rolling" and not hand.statically_determinate:
            # roughening settles such a hand's angles to Eq. 9's equilibrium (_roughen), which
            # is not the rolling model's; every hand the project ships is determinate
            raise ValueError(f"filter: motion_model 'rolling' needs a statically determinate hand (N K = N + "
                             f"constraints); '{hand.spec.name}' has {N} fingers of {K} joints")
        if self.config.motion_model == "rolling" and np.any(self.config.gravity_palm) \
                and self.config.gravity_loads != "following":  # None is "held"
            raise ValueError(f"filter: motion_model 'rolling' carries the weights following the angles in every move; "
                             f"gravity_loads '{self.config.gravity_loads or 'held'}' would hold them through the "
                             "prior's test of a physical grasp: set gravity_loads 'following'")
        if self.config.motion_model != "rolling":  # the rolling model's object: said, not silently dropped
            for name, value, default in (("com_prior", prior.com_prior, PriorConfig.com_prior),
                                         ("object_curvature", self.config.object_curvature, FilterConfig.object_curvature),
                                         ("normal_guess", self.config.normal_guess, FilterConfig.normal_guess)):
                if value != default:
                    raise ValueError(f"filter: {name} '{value}' is the rolling model's (the object's centre of mass, "
                                     f"shape and normals); motion_model '{self.config.motion_model}' has none")
        if prior.angle_centers == "settled" and self.config.tendon != "elastic":
            raise ValueError("prior: angle_centers 'settled' needs filter tendon 'elastic': the grasp settles "
                             "under the motors' command through the tendons' stretch, which the ideal tendon "
                             "does not have")
        if prior.object_mass_unknown:
            if not np.any(self.config.gravity_palm):
                raise ValueError("prior: object_mass_unknown needs gravity: set filter 'gravity_palm' (the gravity "
                                 "in the palm frame [m/s^2]); without it the object's weight moves nothing")
            if self.config.gravity_loads != "following":  # None is "held"
                raise ValueError("prior: object_mass_unknown needs filter 'gravity_loads' = 'following': held "
                                 "through a move, the object's weight misses its stiffness and the mass comes out ~0")

    # ---------------------------------------------------------------- initialisation
    def initialise(self, theta_center, a_center, R_PO, t_PO, stiffness_center=None, link_center=None,
                   scale: float = 1.0, tendon_command=None, mass_center=None, com_center=None) -> ParticleSet:
        """Draw M hypotheses from the prior box around a nominal grasp and attach them to
        the measured POM pose (R_PO, t_PO). ``scale`` shrinks the box (1: the whole box, as the
        re-initialisation draws it);
        ``stiffness_center``, ``link_center`` and ``mass_center`` centre the unknown hand
        parameters' draws (default: their whole prior ranges), and ``com_center`` (3,) [m, POM
        frame] the rolling model's centre of mass (default: ``PriorConfig.com_prior``'s).

        ``tendon_command`` (N,) [m] is the absolute tendon pull l at this grasp; the filter
        advances it by each action (or takes it from ``step``). It is required with the
        elastic tendon and ``tendon_reference="commanded"``, and with the prior's
        ``angle_centers`` "settled", whose angles the first initialise settles under it
        (:meth:`settled_angles`; kept, with their centre, for the re-initialisations)."""
        h, M = self.hand, self.config.particles
        if tendon_command is not None:
            self.tendon_command = as_particles("tendon_command", tendon_command, (h.N,))
        elif self._uses_command() and self.tendon_command is None:
            raise ValueError(
                "filter: tendon_reference 'commanded' needs the absolute tendon command: pass "
                "tendon_command=(N,) [m] to initialise() (or set tendon_reference='implied')")
        theta_center = _shaped("theta_center", theta_center, (h.N, h.K))
        a_center = contact_center(h, a_center)
        R_PO, t_PO = _pose("initial", R_PO, t_PO)
        # the centres and the box's scale named here (a misshapen spring centre had raised an
        # IndexError, a NaN one or a NaN scale a message about the draws, a large scale blamed
        # the prior, a negative one was taken, a link centre in mm was folded into the range)
        if not (kinematics.is_number(scale) and 0 < scale <= 1):
            raise ValueError(f"filter: initialise's 'scale' must be in (0, 1] (the prior box's fraction), got {scale!r}")
        if stiffness_center is not None:
            stiffness_center = _shaped("stiffness_center", stiffness_center, (h.N, h.K))
            if np.any(stiffness_center <= 0):  # (its log had been taken, or it was clipped into the range)
                raise ValueError(f"filter: 'stiffness_center' must be positive [N m/rad], got {stiffness_center.tolist()}")
            units.check_stiffness(stiffness_center, "filter: 'stiffness_center'")
        if link_center is not None:
            link_center = _shaped("link_center", link_center, (h.N, h.K - 1))
            units.check_length(link_center, "filter: 'link_center'")
        if mass_center is not None and not (kinematics.is_number(mass_center) and np.isfinite(mass_center)
                                            and mass_center >= 0):
            raise ValueError(f"filter: 'mass_center' must be a finite number >= 0 [kg], got {mass_center!r}")
        if mass_center is not None:
            units.warn_if_grams(mass_center, "filter: 'mass_center'")
        if com_center is not None:
            com_center = _shaped("com_center", com_center, (3,))
        draw_center = theta_center
        if self.prior.angle_centers == "settled" and self.reinitialisations == 0:
            theta_center, self.settled = self.settled_angles(theta_center, a_center)
            draw_center = theta_center  # the draws' centre; theta_center, the middle's settle, is kept for re-initialising
            if stiffness_center is not None or link_center is not None:
                # settled with the prior's middle: moved to where the given centre's springs and
                # links settle it, which the draws' shifts are measured from (they had been
                # measured from the centre but added to the middle's angles: a review found no
                # physical draw at a spring 2.5x the middle's)
                pr = self.prior
                k = np.array(h.stiffness, float)
                L = np.array(h.link_lengths, float)
                for fi, j in pr.stiffness_unknown:
                    k[fi, j] = pr.stiffness_middle() if stiffness_center is None else stiffness_center[fi, j]
                for fi in pr.links_unknown:
                    L[fi, 0] = pr.link_middle() if link_center is None else link_center[fi, 0]
                draw_center = theta_center + self._settled_shift(k[None], L[None], None, None)[0]
        centers = (stiffness_center, link_center, mass_center)
        theta, a, stiff, links, load, stretch = self._grasps(draw_center, a_center, scale, centers)
        if self._uses_command():
            stretch = self._commanded_stretch(theta)
        p = kinematics.contacts(h, theta, a, links)
        p_O = observation.attach(p, np.asarray(R_PO)[None], np.asarray(t_PO)[None])
        normals_O = com_O = radius = None
        if self.config.motion_model == "rolling":
            normals_O, com_O, radius = self._draw_object(p, p_O, R_PO, load, com_center)
        self.particles = ParticleSet(theta, a, stiff, links, stretch, p_O, np.zeros(M), load, normals_O, com_O, radius)
        self._first_move = True  # the next move carries the prior's draws (first_move_substeps)
        self._theta_center, self._a_center = theta_center, a_center
        self.estimates.append(self.estimate())
        return self.particles

    def _draw_grasps(self, n, theta_center, a_center, scale, centers):
        """``n`` draws of a grasp from the prior boxes and of the unknown hand parameters:
        (theta, a, stiffness, link lengths, object load, stretch, good), ``good`` where the grasp is
        physical (an equilibrium of pulling tendons with at least ``min_tension``, joints in
        their limits; with ``settle_prior``, also at rest under the motors' command)."""
        h, pr = self.hand, self.prior
        theta = np.empty((n, h.N, h.K))
        theta[..., 0] = theta_center[:, 0] + scale * pr.proximal_half_width * self.rng.uniform(-1, 1, (n, h.N))
        theta[..., 1:] = theta_center[:, 1:] + scale * pr.distal_half_width * self.rng.uniform(-1, 1, (n, h.N, h.K - 1))
        a = a_center + scale * pr.contact_half_width * self.rng.uniform(-1, 1, (n, h.N))
        a = _reflect_into(a, *self._contact_bounds)  # folded back onto the pad, as roughening does
        stiffness_center, link_center, mass_center = centers
        stiff = self._draw_stiffness(n, stiffness_center, scale)
        links = self._draw_links(n, link_center, scale)
        load = self._draw_load(n, mass_center, scale)
        if self.settled:  # each around the angles settled with its own springs and links
            theta += self._settled_shift(stiff, links, stiffness_center, link_center)
        eq = motion.equilibrium(h, theta, a=a, link_lengths=links, stiffness=stiff,
                                **self._loads(theta, a, links, load))
        good = eq.ok & np.all(eq.tension >= pr.min_tension, axis=1) & h.within_joint_limits(eq.theta)
        if self.config.stable_grasps != "off" and good.any():
            idx = np.flatnonzero(good)
            good[idx] = self._stable(eq.theta[idx], a[idx], eq.multipliers[idx],
                                     stiff[idx] if stiff.shape[0] > 1 else stiff,
                                     links[idx] if links.shape[0] > 1 else links, None if load is None else load[idx])
        theta, stretch = eq.theta, eq.stretch
        if self.config.settle_prior and self._uses_command() and good.any():  # only the physical draws
            idx = np.flatnonzero(good)
            theta, stretch = theta.copy(), stretch.copy()
            theta[idx], stretch[idx], good[idx] = self._settle(
                theta[idx], a[idx], stiff[idx] if stiff.shape[0] > 1 else stiff,
                links[idx] if links.shape[0] > 1 else links, None if load is None else load[idx])
        return theta, a, stiff, links, load, stretch, good

    def _grasps(self, theta_center, a_center, scale, centers):
        """M physical draws of grasp and hand parameters together (rejection sampling): the
        prior conditioned on a physical grasp. A parameter value with few physical grasps
        in the boxes is drawn less often, which is evidence, not bias: drawing a grasp for
        each value until one is physical (its marginal as drawn) made the physics plant's
        novel hands worse (NH2 4.30 mm against 3.23, NH3 seeds 0-3 6.0 against 3.8; 20,000
        particles, 100 iterations)."""
        M = self.config.particles
        kept, total, drawn = [], 0, 0
        for _ in range(50):
            n = 2 * M
            drawn += n
            theta, a, stiff, links, load, stretch, good = self._draw_grasps(n, theta_center, a_center, scale,
                                                                            centers)
            idx = np.flatnonzero(good)
            if idx.size:
                kept.append((theta[idx], a[idx], stiff[idx] if stiff.shape[0] > 1 else stiff,
                             links[idx] if links.shape[0] > 1 else links,
                             None if load is None else load[idx], stretch[idx]))
                total += idx.size
            if total >= M:
                break
        if total < M:
            raise PriorError(
                f"prior: only {total} of {drawn} draws are physical grasps (positive tension, joints within "
                f"limits), and the filter needs {M}; check the nominal grasp and the prior ranges"
            )

        def cat(i):
            parts = [k[i] for k in kept]
            if parts[0] is None:  # no object weight
                return None
            if (i == 2 and not self.prior.stiffness_unknown) or (i == 3 and not self.prior.links_unknown):
                return parts[0]  # a known (shared) hand parameter, whatever a batch's size
            return np.concatenate(parts)[:M]

        return tuple(cat(i) for i in range(6))

    def _settle(self, theta, a, stiffness, link_lengths, load):
        """Each drawn grasp at rest under the motors' command (``settle_prior``): Gamma with a
        zero action from the drawn angles, the object's shape (its contacts' distances) held.
        Returns the settled angles, their stretch l - R theta and which (P,) found a physical
        equilibrium (pulling tendons of at least the prior's ``min_tension``, joints inside
        their limits)."""
        h = self.hand
        D2 = motion.contact_distances_sq(h, kinematics.contacts(h, theta, a, link_lengths))
        res = motion.move(h, theta, np.zeros(h.N), a=a, D2=D2, stretch=self._commanded_stretch(theta),
                          link_lengths=link_lengths, stiffness=stiffness, tendon=self.config.tendon,
                          max_substeps=self.config.max_substeps, tolerance=self.config.newton_tolerance,
                          loose_after=self.config.newton_loose_after,
                          check_stability=self.config.stable_grasps != "off",
                          **self._loads(theta, a, link_lengths, load))
        ok = res.ok & np.all(res.tension >= self.prior.min_tension, axis=1) & h.within_joint_limits(res.theta)
        if self.config.stable_grasps != "off":
            ok &= res.stable
        return res.theta, self._commanded_stretch(res.theta), ok

    def _check_moves(self) -> bool:
        """Whether a move's stability matters (``stable_grasps`` "always"): only then is it
        computed (9 ms of a 60,000-hypothesis move)."""
        return self.config.stable_grasps == "always"

    def _stable(self, theta, a, multipliers, stiffness, link_lengths, load) -> np.ndarray:
        """(P,) equilibria ``theta`` (with their contact ``multipliers``) that are stable
        under the filter's model: its tendon and, where they follow the angles, its gravity
        loads (``gravity_loads``; held ones add no stiffness)."""
        kw = self._loads(theta, a, link_lengths, load)
        kw.pop("external_torque", None)
        return motion.stable_equilibria(self.hand, theta, multipliers, a=a, link_lengths=link_lengths,
                                        stiffness=stiffness, tendon=self.config.tendon, **kw)

    def _draw_object(self, p, p_O, R_PO, load, com_center=None):
        """The rolling model's object (FilterConfig.motion_model "rolling") for hypotheses with
        contacts ``p`` (M, N, 3) (palm frame) and ``p_O`` (POM frame): the outward normals
        at the contacts (M, N, 3), each drawn uniformly over the cone of ``normal_cone_deg``
        around :func:`motion_rolling.guessed_normals` (``normal_tilt`` "cone"), or tilted
        from it within its finger's flexion plane by an angle uniform in +-``normal_cone_deg``
        ("in_plane"); the guess is ``normal_guess``'s, for "either" one of the two per
        hypothesis. With object loads (M, N), the centre of mass (M, 3) at the contacts'
        barycentre with the loads' shares, moved along the normal of the contacts' plane
        uniformly within ``PriorConfig.com_half_width`` (``com_prior`` "contacts"; "shape":
        a round hypothesis' within that radius of its contacts' circle's centre; "balanced":
        within it of the balanced barycentre; given a ``com_center`` (3,), within it of that
        point, as a re-initialisation draws it); both in the POM frame. Third, with
        ``object_curvature`` "round", the object's surface radius at each contact (M, N) [m]:
        a round hypothesis' circle's radius less the pad radius, a flat one's inf (else None)."""
        M, N = p.shape[:2]
        kind = self.config.normal_guess
        round_ = np.full(M, kind == "circle")  # the hypotheses that guess a round object
        if kind == "either":  # a flat-faced or a round object, half the hypotheses each
            round_ = self.rng.random(M) < 0.5
            guess = np.where(round_[:, None, None], motion_rolling.guessed_normals(self.hand, p, "circle"),
                             motion_rolling.guessed_normals(self.hand, p))
        else:
            guess = motion_rolling.guessed_normals(self.hand, p, kind)
        cone = np.deg2rad(self.config.normal_cone_deg)
        e1 = np.broadcast_to(motion_rolling.hinge_axes(self.hand), guess.shape)  # normal to the plane of the guess
        if kind != "flexion_plane":  # a guess out of its finger's plane: the hinge axis made square to it
            e1 = e1 - np.einsum("pni,pni->pn", e1, guess)[..., None] * guess
            e1 = e1 / np.linalg.norm(e1, axis=-1, keepdims=True)
        e2 = np.cross(guess, e1)  # in the finger's flexion plane, across the guess
        if self.config.normal_tilt == "in_plane":  # a signed tilt about the finger's hinge axis
            ang = self.rng.uniform(-cone, cone, (M, N))
            side = e2
        else:  # a uniform draw on the spherical cap: cos(angle) uniform, the azimuth uniform
            ang = np.arccos(self.rng.uniform(np.cos(cone), 1.0, (M, N)))
            az = self.rng.uniform(0.0, 2 * np.pi, (M, N))
            side = np.cos(az)[..., None] * e1 + np.sin(az)[..., None] * e2
        n_P = np.cos(ang)[..., None] * guess + np.sin(ang)[..., None] * side
        normals_O = np.einsum("ji,pnj->pni", R_PO, n_P)
        radius = None
        if self.config.object_curvature == "round":
            radius = np.full((M, N), np.inf)
            if np.any(round_):
                pr = p[round_]
                to_centre = np.linalg.norm(pr - motion_rolling.circle_centres(pr)[:, None], axis=-1)
                radius[round_] = np.maximum(to_centre - self.hand.pad_radius[None], MIN_CURVATURE_RADIUS)
        if load is None:
            return normals_O, None, radius
        half = self.prior.com_half_width
        if com_center is not None:
            return normals_O, np.asarray(com_center, float)[None] + self._ball(M, half), radius
        if self.prior.com_prior == "balanced":
            centre = np.einsum("n,pni->pi", balanced_shares(self.hand), p_O)
            return normals_O, centre + self._ball(M, half), radius
        share = load / np.maximum(load.sum(axis=1, keepdims=True), 1e-300)
        centre = np.einsum("pn,pni->pi", share, p_O)
        if N >= 3:  # the normal of the contacts' (least-squares) plane
            centre += half * self.rng.uniform(-1, 1, (M, 1)) * contact_plane_normals(p_O)
        if self.prior.com_prior == "shape" and np.any(round_):  # a round object's: around its centre
            centre[round_] = motion_rolling.circle_centres(p_O[round_]) + self._ball(int(round_.sum()), half)
        return normals_O, centre, radius

    def _ball(self, n, radius) -> np.ndarray:
        """``n`` points (n, 3) drawn uniformly within a ball of ``radius`` around the origin."""
        ball = self.rng.standard_normal((n, 3))
        return ball * (radius * self.rng.uniform(0, 1, (n, 1)) ** (1 / 3)) / np.linalg.norm(ball, axis=1, keepdims=True)

    def settled_angles(self, theta_center, a_center) -> tuple[np.ndarray, list[SettledAngles]]:
        """``PriorConfig.angle_centers`` "settled": the nominal grasp ``theta_center`` (N, K)
        settled under the tendon command (:attr:`tendon_command`), with every unknown spring
        and link at its prior middle (the new centre), and again with each unknown at
        :data:`SETTLED_VALUES` values across its range (log-spaced for a spring), the others
        at their middles (the tables). Every settle holds the same object: the contacts
        ``a_center`` at the mutual distances they have in the nominal grasp with the middle
        links, so that a table row says where a hand with that link would hold the object
        the nominal grasp holds. The model is Eq. 9's (:func:`grasps.commanded_equilibrium`),
        also for a rolling filter (whose pads' roll is not in a settle from rest), with the
        loads of a move: the links' weight and a weighed object's middle mass at its
        balanced shares (:func:`balanced_shares`). Values where the model finds no pulling
        equilibrium within the joints' limits are left out of a table (a spring too soft for
        the command, a link too short for the object), with a warning that names them; a
        table with fewer than two values, or a centre with no such equilibrium, falls back
        to the nominal grasp, with a warning."""
        from vlr_drake.grasps import commanded_equilibrium

        h, pr = self.hand, self.prior
        if self.tendon_command is None:
            raise ValueError("prior: angle_centers 'settled' needs the absolute tendon command: pass "
                             "tendon_command=(N,) [m] to initialise()")
        k_mid, L_mid = h.stiffness.copy(), h.link_lengths.copy()
        for fi, j in pr.stiffness_unknown:
            k_mid[fi, j] = pr.stiffness_middle()
        for fi in pr.links_unknown:
            L_mid[fi, 0] = pr.link_middle()
        load = None
        if pr.object_mass_unknown:
            load = 0.5 * sum(pr.object_mass_range) * balanced_shares(h)[None]

        # the object every settle holds: the nominal grasp's contact distances (middle links)
        D2 = motion.contact_distances_sq(h, kinematics.contacts(h, theta_center[None], a_center[None], L_mid[None]))

        def settle(k, L):
            kw = self._loads(theta_center[None], a_center[None], L[None], load)
            if "external_torque" in kw:
                kw["external_torque"] = kw["external_torque"][0]
            th, ok = commanded_equilibrium(h, theta_center, a_center, self.tendon_command, L, k[None], D2=D2, **kw)
            return th, ok and bool(h.within_joint_limits(th[None])[0])

        center, ok = settle(k_mid, L_mid)
        if not ok:
            warnings.warn("prior: angle_centers 'settled': the model finds no equilibrium of the nominal grasp "
                          "under the tendon command within the joints' limits; the angles are drawn around the "
                          "nominal grasp", stacklevel=3)
            return theta_center, []
        tables = []
        unknowns = [("stiffness", fi, j) for fi, j in pr.stiffness_unknown] + [("link", fi, 0) for fi in pr.links_unknown]
        for parameter, fi, j in unknowns:
            values = (np.geomspace(*pr.stiffness_range, SETTLED_VALUES) if parameter == "stiffness"
                      else np.linspace(*pr.link_range, SETTLED_VALUES))
            kept, rows = [], []
            for v in values:
                k, L = k_mid.copy(), L_mid.copy()
                if parameter == "stiffness":
                    k[fi, j] = v
                else:
                    L[fi, 0] = v
                th, ok = settle(k, L)
                if ok:
                    kept.append(v)
                    rows.append(th)
            if len(kept) < 2:
                warnings.warn(f"prior: angle_centers 'settled': the model settles the grasp at {len(kept)} of "
                              f"{values.size} values of the {parameter} of finger {fi}; its hypotheses' angles are "
                              "drawn around the settled centre", stacklevel=3)
                continue
            if len(kept) < values.size:
                dropped = np.round(np.setdiff1d(values, kept), 4).tolist()
                warnings.warn(f"prior: angle_centers 'settled': the model finds no equilibrium of the grasp with the "
                              f"{parameter} of finger {fi} at {dropped}; draws there take angles interpolated between the "
                              f"values it settles ({np.round(kept, 4).tolist()}), or the nearest one's beyond them", stacklevel=3)
            tables.append(SettledAngles(parameter, int(fi), int(j), np.array(kept), np.array(rows)))
        return center, tables

    def _settled_shift(self, stiff, links, stiffness_center, link_center) -> np.ndarray:
        """(n, N, K) how far the angles settled with each draw's springs and links
        (:attr:`settled`) lie from those settled with the draws' centre: the prior's middle,
        or the re-initialisation's centre."""
        pr, shift = self.prior, 0.0
        for tab in self.settled:
            if tab.parameter == "stiffness":
                v = stiff[:, tab.finger, tab.joint]
                c = (pr.stiffness_middle() if stiffness_center is None
                     else np.clip(stiffness_center[tab.finger, tab.joint], *pr.stiffness_range))
            else:
                v = links[:, tab.finger, 0]
                c = pr.link_middle() if link_center is None else link_center[tab.finger, 0]
            shift = shift + tab.at(v) - tab.at(np.array([c]))
        return shift

    def _draw_stiffness(self, n, center, scale):
        h, pr = self.hand, self.prior
        if not pr.stiffness_unknown:
            return h.stiffness[None].copy()
        k = np.broadcast_to(h.stiffness, (n, h.N, h.K)).copy()
        lo, hi = pr.stiffness_range
        for fi, j in pr.stiffness_unknown:
            # centred (re-initialisation): a box of ``scale`` times the range's half-width in
            # the prior's own space (log k for the log-uniform prior), folded back at the bounds
            if center is None and pr.stiffness_prior == "log_uniform":
                k[:, fi, j] = np.exp(self.rng.uniform(np.log(lo), np.log(hi), n))
            elif center is None:
                k[:, fi, j] = self.rng.uniform(lo, hi, n)
            elif pr.stiffness_prior == "log_uniform":
                half = 0.5 * scale * (np.log(hi) - np.log(lo))
                c = np.log(np.clip(center[fi, j], lo, hi))
                k[:, fi, j] = np.exp(_reflect_into(c + half * self.rng.uniform(-1, 1, n), np.log(lo), np.log(hi)))
            else:
                half = 0.5 * scale * (hi - lo)
                k[:, fi, j] = _reflect_into(center[fi, j] + half * self.rng.uniform(-1, 1, n), lo, hi)
        return k

    def _draw_links(self, n, center, scale):
        h, pr = self.hand, self.prior
        if not pr.links_unknown:
            return h.link_lengths[None].copy()
        L = np.broadcast_to(h.link_lengths, (n, h.N, h.K - 1)).copy()
        lo, hi = pr.link_range
        for fi in pr.links_unknown:
            if center is None:
                L[:, fi, 0] = self.rng.uniform(lo, hi, n)
            else:  # centred, folded back at the bounds as the stiffness
                half = 0.5 * scale * (hi - lo)
                L[:, fi, 0] = _reflect_into(center[fi, 0] + half * self.rng.uniform(-1, 1, n), lo, hi)
        return L

    def _draw_load(self, n, mass_center, scale):
        """(n, N) object loads [kg] (PriorConfig.object_mass_unknown): a mass uniform in its
        range (or within ``scale`` of the range's half-width around ``mass_center``), split
        by shares uniform on the simplex (Dirichlet(1, ..., 1)); None without the object's weight."""
        pr = self.prior
        if not pr.object_mass_unknown:
            return None
        lo, hi = pr.object_mass_range
        if mass_center is None:
            mass = self.rng.uniform(lo, hi, n)
        else:
            mass = _reflect_into(mass_center + 0.5 * scale * (hi - lo) * self.rng.uniform(-1, 1, n), lo, hi)
        return mass[:, None] * self.rng.dirichlet(np.ones(self.hand.N), n)

    def _loads(self, theta, a, link_lengths, load) -> dict:
        """The gravity loads Eq. 9 lacks that the filter knows, as keyword arguments of
        :func:`motion.move` and :func:`motion.equilibrium` for hypotheses at ``theta`` (none
        without gravity, ``FilterConfig.gravity_palm``): the links' weight, and the object's
        weight carried at the contacts where ``load`` (P, N) [kg] is given
        (``ParticleSet.object_load``); held at their torques at ``theta`` through a move, or
        following the angles (``FilterConfig.gravity_loads``)."""
        g = self.config.gravity_palm
        if not np.any(g):
            return {}
        g = np.asarray(g, float)
        if self.config.gravity_loads == "following":
            return {"gravity": g, "object_load": load}
        return {"external_torque": motion.gravity_torque(self.hand, theta, a=a, gravity=g, object_load=load,
                                                         link_lengths=link_lengths)}

    def _uses_command(self) -> bool:
        return self.config.tendon == "elastic" and self.config.tendon_reference == "commanded"

    def _commanded_stretch(self, theta) -> np.ndarray:
        """(M, N) stretch l - R theta of hypotheses ``theta`` under the current tendon command."""
        return self.tendon_command[None] - self.hand.tendon_travel(theta)

    def _feasible(self, res, pose_ok) -> np.ndarray:
        """(P,) hypotheses that stay physical after the move ``res``: solved, a POM pose
        (``pose_ok``), pulling tendons, joints inside their limits and, with ``stable_grasps``
        "always", a stable equilibrium. With a
        ``stuck_probability`` an unsolved hypothesis (which keeps its angles) counts as solved."""
        solved = res.ok | bool(self.config.stuck_probability)
        physical = res.tension_feasible()
        if self.config.stable_grasps == "always":
            physical &= res.stable
        return solved & pose_ok & (physical | ~res.ok) & self.hand.within_joint_limits(res.theta)

    # ---------------------------------------------------------------- action choice
    def action_information(self, actions, rng: np.random.Generator, samples: int = 256,
                           min_valid: float = 0.9) -> np.ndarray:
        """Expected information (C,) of each candidate action (C, N) about the hypotheses.

        A weighted subsample of ``samples`` hypotheses (systematic, drawn with ``rng``) is
        moved by every candidate with Gamma (the filter's ``motion_model``: with "rolling",
        each from its own POM pose, its object's normals, weight and centre of mass), and
        each predicts the POM's motion (translation
        and rotation vector in its own frame, in units of sigma_p and sigma_r). Where the
        hypotheses disagree the camera can tell them apart: the score is the Gaussian
        mutual information between hypothesis and measurement, 0.5 log det(I + Cov), over
        the hypotheses that stay physical (an equilibrium, pulling tendons, joints in their
        limits; :func:`information_gain`). A candidate under which more than
        ``1 - min_valid`` of them find no equilibrium scores -inf: the grasp itself may have
        none there. The filter is not changed."""
        if self.particles is None:
            raise RuntimeError("filter: call initialise() before action_information()")
        cfg, h, ps = self.config, self.hand, self.particles
        actions = np.asarray(actions, float)
        if actions.ndim != 2 or actions.shape[1] != h.N or actions.shape[0] < 1:
            raise ValueError(f"filter: 'actions' must have shape (C, {h.N}), got {actions.shape}")
        if samples < 2:
            raise ValueError(f"filter: 'samples' must be >= 2, got {samples}")
        C = actions.shape[0]
        idx = systematic_resample(normalise(ps.log_w), rng)
        sub = ps.take(idx[:: max(1, ps.size // samples)][:samples])
        S = sub.size
        stretch = self._commanded_stretch(sub.theta) if self._uses_command() else sub.stretch

        def tile(x):  # candidate-major: row c * S + s is hypothesis s under candidate c
            return x if x.shape[0] == 1 else np.tile(x, (C,) + (1,) * (x.ndim - 1))

        dl = np.repeat(actions, S, axis=0)
        if cfg.motion_model == "rolling":  # each hypothesis rolls from its own POM pose
            tiled = sub.take(np.tile(np.arange(S), C))
            tiled.stretch = tile(stretch)
            R0, t0, ok0 = observation.pom_pose(tiled.p_O, kinematics.contacts(h, tiled.theta, tiled.a,
                                                                              tiled.link_lengths))
            res, R1, t1 = self._move_rolling(dl, R0, t0, tiled)
            ok1 = np.all(np.isfinite(t1), axis=1)
        else:
            theta, a, L, p_O = tile(sub.theta), tile(sub.a), tile(sub.link_lengths), tile(sub.p_O)
            load = None if sub.object_load is None else tile(sub.object_load)
            res = motion.move(h, theta, dl, a=a, D2=motion.contact_distances_sq(h, p_O),
                              stretch=tile(stretch), link_lengths=L, stiffness=tile(sub.stiffness), tendon=cfg.tendon,
                              tolerance=cfg.newton_tolerance, loose_after=cfg.newton_loose_after,
                              check_stability=self._check_moves(),
                              **self._loads(theta, a, L, load))
            R0, t0, ok0 = observation.pom_pose(p_O, kinematics.contacts(h, theta, a, L))
            R1, t1, ok1 = observation.pom_pose(p_O, kinematics.contacts(h, res.theta, a, L))
        solved = (res.ok & ok0 & ok1).reshape(C, S)
        live = self._feasible(res, ok0 & ok1).reshape(C, S)
        turn = observation.rotvec(np.einsum("pji,pjk->pik", R0, R1))
        sp, sr = cfg.sigmas()
        y = np.concatenate([(t1 - t0) / sp, turn / sr], axis=1)
        score = information_gain(y.reshape(C, S, 6), live, min_valid=0.0)
        return np.where(solved.mean(axis=1) >= min_valid, score, -np.inf)

    # ---------------------------------------------------------------- one iteration
    def step(self, dl, R_meas=None, t_meas=None, valid: bool = True, tendon_command=None) -> StepReport:
        """One iteration of Algorithm 1 for action ``dl`` (N,) and the measured POM pose.

        With ``valid`` False (lost tag), or no pose given (both ``R_meas`` and ``t_meas``
        None), the particles are moved but not weighed by the camera, resampled or
        re-anchored: nothing is learnt from it and nothing is corrupted (a hypothesis the
        move left unphysical still weighs nothing, one held by friction its
        ``stuck_probability``; with the rolling model each hypothesis' contacts are
        re-expressed in the object pose its move predicts, as the pads rolled over the object).
        ``tendon_command`` (N,) [m]: the absolute tendon pull after the action, where the
        motors report it (hardware); by default the previous command plus ``dl``.
        """
        if self.particles is None:
            raise RuntimeError("filter: call initialise() before step()")
        cfg, h, ps = self.config, self.hand, self.particles
        # checked before anything moves or is counted: a bad input changes nothing
        dl = _shaped("dl", dl, (h.N,))
        valid = kinematics.checked_flag(valid, "filter: 'valid'")
        if valid and R_meas is None and t_meas is not None:  # had been a step without a measurement
            raise ValueError("filter: a measured position 't_meas' without its rotation 'R_meas'; pass both, "
                             "or valid=False for a lost tag")
        if valid and R_meas is not None:
            R_meas, t_meas = _pose("measured", R_meas, t_meas)
        if tendon_command is not None:
            tendon_command = as_particles("tendon_command", tendon_command, (h.N,))
        lap = _Laps()
        self.iteration += 1
        if tendon_command is not None:  # the motors' reading after the action
            self.tendon_command = tendon_command - dl
        if self._uses_command():  # each hypothesis' tendon state from the motors (tendon_reference)
            ps.stretch = self._commanded_stretch(ps.theta)
        if self.tendon_command is not None:
            self.tendon_command = self.tendon_command + dl
        rolling = cfg.motion_model == "rolling"
        if cfg.motion_error > 0 or rolling:  # each particle's POM pose before the move
            R_prev, t_prev, prev_ok = observation.pom_pose(ps.p_O, kinematics.contacts(h, ps.theta, ps.a,
                                                                                       ps.link_lengths))
        else:
            R_prev = t_prev = None
        substeps = cfg.max_substeps
        if self._first_move and cfg.first_move_substeps is not None:  # the prior's draws settle
            substeps = cfg.first_move_substeps
        self._first_move = False
        held = None  # the hypotheses held by friction, where held_motion "elastic" moved them
        if rolling:
            res, R_pred, t_pred = self._move_rolling(dl, R_prev, t_prev)
            p_new = kinematics.contacts(h, res.theta, ps.a, ps.link_lengths)
            pose_ok = prev_ok & np.isfinite(t_pred).all(axis=1) & np.isfinite(R_pred).all(axis=(1, 2))
        else:
            D2 = motion.contact_distances_sq(h, ps.p_O)
            res = motion.move(h, ps.theta, dl, a=ps.a, D2=D2, stretch=ps.stretch, link_lengths=ps.link_lengths,
                              stiffness=ps.stiffness, tendon=cfg.tendon, max_substeps=substeps,
                              tolerance=cfg.newton_tolerance, loose_after=cfg.newton_loose_after,
                              check_stability=self._check_moves(),
                              **self._loads(ps.theta, ps.a, ps.link_lengths, ps.object_load))
            if cfg.stuck_probability and cfg.held_motion == "elastic" and not res.ok.all():
                held = ~res.ok
                res = self._move_held(res, dl, D2, substeps)
            res = _finite_moves(res, ps.theta, ps.stretch + dl, h.kappa)
            p_new = kinematics.contacts(h, res.theta, ps.a, ps.link_lengths)
            R_pred, t_pred, pose_ok = observation.pom_pose(ps.p_O, p_new)
        feasible = self._feasible(res, pose_ok)
        # the hypotheses held by friction weigh stuck_probability, moved elastically from
        # where they were held or not (the elastic ones had escaped it: a review)
        moved = res.ok if held is None else res.ok & ~held
        ps.theta, ps.stretch = res.theta, res.stretch
        lap("move")
        if not valid or R_meas is None:
            if rolling:  # the pads rolled over the object: the contacts in the pose it predicts
                p_O = observation.in_frame(p_new, R_pred, t_pred)
                ps.p_O = np.where(np.isfinite(p_O).all(axis=(1, 2))[:, None, None], p_O, ps.p_O)
            # Nothing measured, but the move's physics weighs as in a measured step (a flat
            # likelihood): a hypothesis that left the physical grasps weighs nothing, one held
            # by friction its stuck_probability (a review: they had kept their whole weight
            # through a lost frame). Where that leaves none the weights stay as they were,
            # and the next measurement finds the cloud implausible.
            physics = np.where(feasible, 0.0, -np.inf)
            if cfg.stuck_probability:
                physics = np.where(moved, physics, physics + np.log(cfg.stuck_probability))
            if np.any(np.isfinite(ps.log_w + physics)):
                ps.log_w = ps.log_w + physics
            return self._report(False, effective_sample_size(ps.log_w), 1.0, moved, feasible, False, np.nan, lap=lap)
        dp, ang = observation.pose_error(R_pred, t_pred, R_meas[None], t_meas[None])
        log_lik, maha2 = self._log_likelihood(dp, ang, R_pred, t_pred, R_prev, t_prev)
        if cfg.stuck_probability:  # held by friction where it was (motion.move kept its angles)
            log_lik = np.where(moved, log_lik, log_lik + np.log(cfg.stuck_probability))
        log_lik = np.where(feasible, log_lik, -np.inf)
        # the hypotheses that still carry weight and are feasible now: where none is, every
        # particle has become implausible, whatever those already weighing nothing say
        live = feasible & np.isfinite(ps.log_w) & np.isfinite(log_lik)
        log_lik = np.where(live, log_lik, -np.inf)
        best = float(np.sqrt(np.min(maha2[live]))) if live.any() else np.inf
        evidence = log_evidence_increment(ps.log_w, log_lik)
        live_ess = _tempered_ess(np.ascontiguousarray(ps.log_w, float), np.ascontiguousarray(log_lik, float), 0.0)
        # A cloud that has (nearly) collapsed onto a few hypotheses is lost too: resampling
        # would copy them, roughening would find no spread among them, and the intervals would
        # shrink to nothing, sure and wrong (a review: one survivor of 2,000, reported
        # converged with a 2e-8 deg interval and every truth outside).
        collapsed = not live.any() or not live_ess >= self._live_floor()
        if collapsed or best > cfg.divergence_sigmas:
            lap("weigh")
            self._reinitialise(R_meas, t_meas)
            lap("reinitialise")
            return self._report(True, float(self.particles.size), 0.0, moved, feasible, True, best, evidence, lap=lap)
        # temper this iteration's likelihood only, relative to the weights carried so far
        target = cfg.ess_fraction * ps.size
        if live_ess < target:
            # so many hypotheses failed that the live cloud is below the target at any beta:
            # temper relative to it (the conditional ESS of adaptive SMC) rather than take the
            # bisection's floor, 1e-6, which would discard this measurement (a review: 424
            # of 600 infeasible, beta 1e-6). On the model plant 3 of about 2,300 iterations
            # (NH2, NH3, seeds 0-4) came here; none of the 98 physics traces behind the rows.
            target = cfg.ess_fraction * live_ess
        beta = _temper_increment(ps.log_w, log_lik, target)
        log_w = ps.log_w + beta * log_lik
        ess = effective_sample_size(log_w)
        lap("weigh")
        # Re-anchoring (DESIGN.md section 3): blend each particle's predicted POM pose
        # towards the measured one, then re-express its contacts in that frame.
        R_anchor, t_anchor = _blend_poses(R_pred, t_pred, R_meas, t_meas, cfg.anchor_fraction)
        if ess < cfg.resample_fraction * ps.size:
            idx = systematic_resample(normalise(log_w), self.rng)
            new = ps.take(idx)
            R_anchor, t_anchor = R_anchor[idx], t_anchor[idx]
            self._roughen(new)
            self.resamples += 1
            p_now = kinematics.contacts(h, new.theta, new.a, new.link_lengths)
        else:
            new = ps
            new.log_w = log_w - log_w[np.isfinite(log_w)].max()
            p_now = p_new  # the moved particles' contacts
        new.p_O = observation.in_frame(p_now, R_anchor, t_anchor)  # R^T (p - t), particle by particle
        self.particles = new
        lap("resample")
        return self._report(True, ess, beta, moved, feasible, False, best, evidence, lap=lap)

    def _live_floor(self) -> float:
        """The effective number of live hypotheses below which the cloud counts as lost: one
        more than the identified quantities (fewer give roughening's covariance no full rank),
        and at least :data:`COLLAPSED_FRACTION` of the cloud; at most a tenth of it (a cloud
        of a few dozen hypotheses, a quick check's, is not lost for its size)."""
        M = self.particles.size
        dims = self._unknowns(self.particles.take(np.zeros(1, dtype=np.intp))).shape[1]
        return min(max(dims + 1.0, COLLAPSED_FRACTION * M), 0.1 * M)

    def _move_rolling(self, dl, R_prev, t_prev, ps: ParticleSet | None = None):
        """Move every hypothesis of ``ps`` (default the filter's) by the action ``dl`` (N,)
        or (M, N) with the rolling model (``motion_model`` "rolling";
        :func:`motion_rolling.move_rolling`) from its POM pose before the move (R_prev,
        t_prev): (a :class:`motion.MoveResult`, the predicted POM poses R (M, 3, 3), t (M,
        3)). A hypothesis whose Newton did not converge keeps its angles and pose, as the
        pinned model's failures do (held where it was with a ``stuck_probability``,
        discarded without one)."""
        cfg, h = self.config, self.hand
        ps = self.particles if ps is None else ps
        M = ps.size
        g = np.asarray(cfg.gravity_palm, float)
        mass = com = None
        if ps.com_O is not None:
            mass = ps.object_load.sum(axis=1)
            com = np.einsum("pij,pj->pi", R_prev, ps.com_O) + t_prev
        mv = motion_rolling.move_rolling(
            h, ps.theta, ps.a, R_prev, t_prev, np.einsum("pij,pnj->pni", R_prev, ps.normals_O), ps.stretch, dl=dl,
            gravity=g if np.any(g) else None, object_mass=mass, com=com, stiffness=ps.stiffness,
            link_lengths=ps.link_lengths, curvature_radius=ps.curvature_radius)
        # a move that is not finite is a failed one (the rotation and translation included:
        # a NaN pose marked solved had switched the divergence test off; a review)
        ok = (mv.ok & np.isfinite(mv.theta).all(axis=(1, 2)) & np.isfinite(mv.stretch).all(axis=1)
              & np.isfinite(mv.R).all(axis=(1, 2)) & np.isfinite(mv.t).all(axis=1))
        theta = np.where(ok[:, None, None], mv.theta, ps.theta)
        stretch = np.where(ok[:, None], mv.stretch, ps.stretch + dl)
        R = np.where(ok[:, None, None], mv.R, R_prev)
        t = np.where(ok[:, None], mv.t, t_prev)
        res = motion.MoveResult(theta=theta, stretch=stretch, tension=h.kappa[None] * stretch,
                                multipliers=np.zeros((M, 0)), ok=ok, iterations=mv.newton_iterations,
                                residuals=np.zeros((M, 3)), stable=ok.copy())
        return res, R, t

    def _move_held(self, res: motion.MoveResult, dl, D2, substeps: int) -> motion.MoveResult:
        """``held_motion = "elastic"``: each hypothesis whose move under the commanded tendon
        state found no equilibrium is held by friction where it is, with the tendon stretch
        of its own equilibrium there, and moved by the action ``dl`` from that state. Those
        solved replace the failures in ``res`` (marked solved; the step still weighs every
        held one by ``stuck_probability``); the rest stay held still.
        ``substeps``: the continuation of this move (``max_substeps``, or
        ``first_move_substeps`` for the prior's draws)."""
        cfg, h, ps = self.config, self.hand, self.particles
        bad = np.flatnonzero(~res.ok)

        def pick(x):
            return x[bad] if x.shape[0] > 1 else x

        load = None if ps.object_load is None else ps.object_load[bad]
        eq = motion.equilibrium(h, ps.theta[bad], a=ps.a[bad], link_lengths=pick(ps.link_lengths),
                                stiffness=pick(ps.stiffness),
                                **self._loads(ps.theta[bad], ps.a[bad], pick(ps.link_lengths), load))
        moved = motion.move(h, eq.theta, dl, a=ps.a[bad], D2=D2[bad], stretch=eq.stretch,
                            link_lengths=pick(ps.link_lengths), stiffness=pick(ps.stiffness), tendon=cfg.tendon,
                            max_substeps=substeps, tolerance=cfg.newton_tolerance,
                            loose_after=cfg.newton_loose_after, check_stability=self._check_moves(),
                            **self._loads(eq.theta, ps.a[bad], pick(ps.link_lengths), load))
        good = eq.ok & moved.ok
        idx = bad[good]
        out = motion.MoveResult(*(np.array(getattr(res, f.name)) for f in dataclasses.fields(res)))
        for f in dataclasses.fields(res):
            getattr(out, f.name)[idx] = getattr(moved, f.name)[good]
        return out

    def _log_likelihood(self, dp, ang, R_pred, t_pred, R_prev, t_prev):
        """Log-likelihood of the measured POM pose (up to a constant; Gaussian, or Student-t
        with ``likelihood = "student_t"``) and the squared Mahalanobis distance, (P,) each. Position error ``dp`` [m] and rotation error ``ang``
        [rad] against sigma_p and sigma_r, widened in quadrature by the relative motion-model
        error c times each particle's predicted motion (``motion_error``); the log-normaliser
        (-3 log sigma per 3-D error) keeps particles that predict large motions from being
        favoured for their wider spread."""
        cfg = self.config
        sp, sr = cfg.sigmas()
        sp2, sr2 = sp**2, sr**2  # per particle with motion_error
        if cfg.motion_error > 0:
            move_t = np.linalg.norm(t_pred - t_prev, axis=1)
            move_r = observation.rotation_angle(R_pred, R_prev)
            sp2 = sp2 + (cfg.motion_error * move_t) ** 2
            sr2 = sr2 + (cfg.motion_error * move_r) ** 2
        maha2 = dp**2 / sp2 + ang**2 / sr2
        norm = -1.5 * (np.log(sp2) + np.log(sr2))
        if cfg.likelihood == "student_t":  # two independent 3-D t's (the constant dropped)
            k = cfg.likelihood_dof + 3.0  # scale^2 = sigma^2 (nu + 3) / nu: the Gaussian's core
            shape = np.log1p(dp**2 / (k * sp2)) + np.log1p(ang**2 / (k * sr2))
            return -0.5 * k * shape + norm, maha2
        return -0.5 * maha2 + norm, maha2

    def _unknowns(self, ps: ParticleSet) -> np.ndarray:
        """The identified quantities as one (M, D) matrix: theta, a, then extras (an unknown
        spring as log k under the log-uniform prior, the space the prior is uniform in; the
        object's loads as its mass and its shares' log-ratios)."""
        cols = [ps.theta.reshape(ps.size, -1), ps.a]
        for fi, j in self.prior.stiffness_unknown:  # log k for the log-uniform prior: its own space
            k = ps.stiffness[:, fi, j]
            cols.append((np.log(k) if self.prior.stiffness_prior == "log_uniform" else k)[:, None])
        for fi in self.prior.links_unknown:
            cols.append(ps.link_lengths[:, fi, 0][:, None])
        if ps.object_load is not None:  # the mass and its shares' log-ratios
            cols.append(_mass_and_log_ratios(ps.object_load))
        if ps.normals_O is not None:
            cols.append(ps.normals_O.reshape(ps.size, -1))
        if ps.com_O is not None:
            cols.append(ps.com_O)
        return np.concatenate(cols, axis=1)

    def _set_unknowns(self, ps: ParticleSet, x: np.ndarray) -> None:
        """The identified quantities from ``x`` laid out as :meth:`_unknowns`, each back in
        its range: contacts folded onto the pad, springs, links and the mass folded keeping
        their spread, the shares from their log-ratios, the normals on the unit sphere."""
        h, pr = self.hand, self.prior
        n = h.N * h.K
        ps.theta = x[:, :n].reshape(-1, h.N, h.K).copy()
        # contacts, springs and links folded back at their ranges' ends, as the prior's draws
        # are (clipped, up to 4% of an NH1 cloud's link sat on a bound after a roughening);
        # springs, links and the mass given back the spread the fold takes (_fold_keeping_spread)
        ps.a = _reflect_into(x[:, n : n + h.N], *self._contact_bounds)
        c = n + h.N
        if pr.stiffness_unknown:
            k = ps.stiffness.copy()
            lo, hi = pr.stiffness_range
            for fi, j in pr.stiffness_unknown:
                if pr.stiffness_prior == "log_uniform":  # roughened as log k (_unknowns)
                    k[:, fi, j] = np.exp(_fold_keeping_spread(x[:, c], np.log(lo), np.log(hi)))
                else:
                    k[:, fi, j] = _fold_keeping_spread(x[:, c], lo, hi)
                c += 1
            ps.stiffness = k
        if pr.links_unknown:
            L = ps.link_lengths.copy()
            for fi in pr.links_unknown:
                L[:, fi, 0] = _fold_keeping_spread(x[:, c], *pr.link_range)
                c += 1
            ps.link_lengths = L
        if ps.object_load is not None:  # the mass inside its range, the shares on the simplex
            # The mass folded back at the range's ends keeping its spread (clipped, 4-5% of a
            # weighed cloud sat on them after each roughening and the interval ended on the
            # bound: a review). The shares need no fold: roughened as log-ratios, any value is
            # a point of the simplex (roughened as loads and folded back at 0, a prior cloud's
            # shares had worn towards equal ones: a KS distance of 0.20 from their Dirichlet
            # prior after 60 roughenings without data, 0.36 after 240).
            mass = _fold_keeping_spread(x[:, c], *pr.object_mass_range)
            ps.object_load = mass[:, None] * _shares_from_log_ratios(x[:, c + 1 : c + h.N])
            c += h.N
        if ps.normals_O is not None:  # roughened as vectors, back on the unit sphere
            nv = x[:, c : c + 3 * h.N].reshape(-1, h.N, 3)
            ps.normals_O = nv / np.linalg.norm(nv, axis=-1, keepdims=True)
            c += 3 * h.N
        if ps.com_O is not None:
            ps.com_O = x[:, c : c + 3].copy()

    def _roughen(self, ps: ParticleSet) -> None:
        """Liu-West kernel shrinkage with the cloud's full covariance, then each hypothesis'
        tendon state: the commanded stretch l - R theta (after settling the angles to an
        equilibrium on hands with more joints than tendons and contact pairs), or the implied
        equilibrium stretch (``tendon_reference = "implied"``).

        x <- a x + (1 - a) mean + h C^(1/2) eps,  a = sqrt(1 - h^2): the cloud keeps its mean
        and covariance. The full covariance matters: joint angles and contact positions of a
        finger form a nearly degenerate ridge, and per-coordinate jitter would knock
        particles off it.

        Springs (as log k under the log-uniform prior), links and the object's mass fold
        back at their ranges' ends, and each is then spread back to the standard deviation
        the fold took from it (:func:`_fold_keeping_spread`): folded alone, a cloud the data
        leave alone narrowed towards its range's middle (to 0.66-0.72 of its spread in 60
        roughenings), as if measured. Roughening them as their prior's normal scores kept
        such a cloud as well, but measured worse on the physics plant (NF1's link and the
        rolling model's object mass settled against their ranges' lower ends):
        docs/results.md, forty-eighth session. The mass's shares are roughened as their
        log-ratios (:func:`_mass_and_log_ratios`), which need no fold.
        """
        hh = self.config.roughening
        shrink = np.sqrt(1.0 - hh * hh)
        x = self._unknowns(ps)
        mean = x.mean(axis=0)
        cov = np.cov(x, rowvar=False) + 1e-18 * np.eye(x.shape[1])
        try:
            Lc = np.linalg.cholesky(cov)
        except np.linalg.LinAlgError:  # a collapsed cloud (few particles, many copies): rank-deficient
            lam, V = np.linalg.eigh(cov)  # a square root V sqrt(lam): the same covariance where it is PSD
            Lc = V * np.sqrt(np.clip(lam, 0.0, None))
        jitter = self.rng.standard_normal(x.shape) @ (hh * Lc.T)
        x *= shrink  # in place: x is the fresh matrix of _unknowns
        x += (1.0 - shrink) * mean
        x += jitter
        self._set_unknowns(ps, x)
        if self._uses_command():
            if not self.hand.statically_determinate:  # settle the angles to an equilibrium
                eq = motion.equilibrium(self.hand, ps.theta, a=ps.a, link_lengths=ps.link_lengths,
                                        stiffness=ps.stiffness,
                                        **self._loads(ps.theta, ps.a, ps.link_lengths, ps.object_load))
                # one that found none keeps its roughened angles and weighs nothing
                ps.theta = np.where(eq.ok[:, None, None], eq.theta, ps.theta)
                ps.log_w = np.where(eq.ok, ps.log_w, -np.inf)
            ps.stretch = self._commanded_stretch(ps.theta)
        else:
            eq = motion.equilibrium(self.hand, ps.theta, a=ps.a, link_lengths=ps.link_lengths, stiffness=ps.stiffness,
                                    **self._loads(ps.theta, ps.a, ps.link_lengths, ps.object_load))
            ps.theta, ps.stretch = eq.theta, eq.stretch
            # no implied tendon state (stretch 0): nothing to move it by. Where none has one, the
            # whole cloud weighs nothing and the next measurement draws it again.
            ps.log_w = np.where(eq.ok, ps.log_w, -np.inf)

    def _reinitialise(self, R_meas, t_meas) -> None:
        """Draw the cloud again (every hypothesis implausible): around the estimate of the
        cloud as this iteration moved it (the last estimate is one action old), or, within
        ``REINIT_RECENT`` iterations of the last re-initialisation, from the whole prior
        around the nominal grasp.

        The rolling model's object: its centre of mass, fixed in the object's frame as its
        mass is, is drawn around the estimate with them (within ``com_half_width``); its
        normals at the contacts are drawn again around the guess from the new contacts, as the
        attachments are taken again from the measured pose: a divergence that is a slip puts
        the pads on other points of the object's surface."""
        nominal = self._theta_center, self._a_center  # the first initialise's, kept
        recent = self._last_reinit is not None and self.iteration - self._last_reinit <= REINIT_RECENT
        self.reinitialisations += 1
        self._last_reinit = self.iteration
        if recent:
            theta_c, a_c, k_c, L_c, m_c, c_c = *nominal, None, None, None, None
        else:
            est = self.estimate()
            theta_c, a_c = est["theta"], est["a"]
            k_c = est["stiffness"] if self.prior.stiffness_unknown else None
            L_c = est["link_lengths"] if self.prior.links_unknown else None
            m_c = float(est["object_mass"]) if self.prior.object_mass_unknown else None
            c_c = est.get("object_com_O")  # (the rolling model's, with the object's weight)
        try:
            self.initialise(theta_c, a_c, R_meas, t_meas, k_c, L_c, scale=1.0, mass_center=m_c, com_center=c_c)
        except PriorError:
            if recent:  # the whole prior around the nominal grasp holds no grasp: nothing to fall back to
                raise
            # no physical grasp around the estimate (a review: every draw's equilibrium solve
            # failed): the whole prior around the nominal grasp, as a second loss would draw
            self.initialise(*nominal, R_meas, t_meas, scale=1.0)
        self._theta_center, self._a_center = nominal
        self.estimates.pop()  # initialise appended one; the report below appends the current

    def _report(self, measured, ess, beta, moved, feasible, reinit, best, evidence=np.nan, lap=None) -> StepReport:
        est = self.estimate()
        self.estimates.append(est)
        if lap is not None:
            lap("estimate")
        width = est["theta_half_width"] if self.config.convergence_measure == "half_width" else est["theta_full_width"]
        mean_int = float(np.rad2deg(width.mean()))
        param = self.parameter_interval(est)
        limit = self.config.parameter_convergence
        params_done = limit is None or np.isnan(param) or param < limit
        report = StepReport(
            iteration=self.iteration, measured=measured, ess=ess, beta=beta,
            solve_failures=int((~moved).sum()), infeasible=int((~feasible).sum()), reinitialised=reinit,
            best_mahalanobis=best, mean_interval_deg=mean_int,
            converged=bool(mean_int < self.config.convergence_deg and params_done and not reinit),
            log_evidence=evidence, parameter_interval=param, timing_s={} if lap is None else dict(lap.times),
        )
        self.history.append(report)
        return report

    def parameter_interval(self, est: dict | None = None) -> float:
        """The widest 95% interval among the unknown springs and link lengths, as a fraction
        of its estimate (half or full width, as ``FilterConfig.convergence_measure`` says),
        of ``est`` (an :meth:`estimate`; None: the current one). NaN where every hand
        parameter is known."""
        est = self.estimate() if est is None else est
        half = 0.5 if self.config.convergence_measure == "half_width" else 1.0
        rel = [half * (est["stiffness_hi"][fi, j] - est["stiffness_lo"][fi, j]) / est["stiffness"][fi, j]
               for fi, j in self.prior.stiffness_unknown]
        rel += [half * (est["link_lengths_hi"][fi, 0] - est["link_lengths_lo"][fi, 0]) / est["link_lengths"][fi, 0]
                for fi in self.prior.links_unknown]
        return float(max(rel)) if rel else float("nan")

    # ---------------------------------------------------------------- estimate
    def estimate(self) -> dict:
        """Weighted mean and 95% intervals of every identified quantity (:func:`cloud_estimate`)."""
        return cloud_estimate(self.hand, self.particles)

    def nearest_hypotheses(self, count: int = 1) -> list[dict]:
        """The ``count`` live hypotheses nearest the weighted mean, nearest first, as estimate
        dicts (``theta``, ``a``, ``stiffness``, ``link_lengths``, ``contacts``): distances in
        units of each identified quantity's weighted standard deviation. Unlike the mean, each
        is one of the hypotheses the filter moved."""
        if not kinematics.is_count(count):  # -1 had sliced off the farthest: M - 1 hypotheses
            raise ValueError(f"filter: nearest_hypotheses' 'count' must be an integer >= 0, got {count!r}")
        ps = self.particles
        w = normalise(ps.log_w)
        x = self._unknowns(ps)
        mean = w @ x
        sd = np.sqrt(np.maximum(w @ (x - mean) ** 2, 1e-30))
        d2 = (((x - mean) / sd) ** 2).sum(axis=1)
        d2[~(w > 0)] = np.inf
        order = np.argsort(d2)[:count]
        near = ps.take(order[np.isfinite(d2[order])])
        p = kinematics.contacts(self.hand, near.theta, near.a, near.link_lengths)
        shared = near.stiffness.shape[0] == 1, near.link_lengths.shape[0] == 1
        return [{"theta": near.theta[j], "a": near.a[j], "stiffness": near.stiffness[0 if shared[0] else j],
                 "link_lengths": near.link_lengths[0 if shared[1] else j], "contacts": p[j]}
                for j in range(near.size)]

    def nearest_hypothesis(self) -> dict:
        """The live hypothesis nearest the weighted mean (:meth:`nearest_hypotheses`)."""
        return self.nearest_hypotheses(1)[0]

    @property
    def converged(self) -> bool:
        return bool(self.history and self.history[-1].converged)


class _Laps:
    """Wall time between successive calls, by phase name [s] (StepReport.timing_s)."""

    def __init__(self):
        self.last = time.perf_counter()
        self.times: dict[str, float] = {}

    def __call__(self, name: str) -> None:
        now = time.perf_counter()
        self.times[name] = self.times.get(name, 0.0) + now - self.last
        self.last = now


def _blend_poses(R_a, t_a, R_b, t_b, fraction):
    """Poses a fraction of the way from (R_a, t_a) (P, ...) to one pose (R_b, t_b)."""
    if fraction == 0.0:
        return R_a, t_a
    return observation.blend_poses(R_a, t_a, R_b, t_b, fraction)
