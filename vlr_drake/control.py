"""The Jacobian controller of the POM (the paper's Eq. 10-12, DESIGN.md section 7).

Pure numpy around the motion function Gamma (:func:`vlr_drake.motion.move`) and the
observation function Lambda (:func:`vlr_drake.observation.pom_pose`):

- :class:`ControlModel`: the controller's model of the hand-object system, built from the
  self-identification estimate (or the truth) and anchored at the *measured* POM pose, so
  Upsilon predicts motion relative to what the camera sees.
- :func:`upsilon`: Upsilon = Lambda o Gamma, a tendon action dl (N,) to the POM motion
  dphi (6,) = [translation of the POM origin [m], rotation vector [rad]], both in the palm
  frame P (rotation: R' = exp([w]x) R, left-multiplied).
- :func:`jacobian`: the 6 x N Jacobian by central finite differences (Eq. 10), all 2N
  perturbed actions in one batched move.
- :func:`control_step`: dl from a 6-vector error, either the paper's transpose form
  (Eq. 11) or damped least squares (default), on the rows the task controls (position,
  orientation or full) with the rotational weight alpha (Eq. 12); gain and step clip.
- :func:`servo_to`: camera-feedback iteration until the error is under tolerance, a step
  budget is spent, or progress stalls; always returns a :class:`ServoReport` (with the
  closest pose reached), never loops forever and never commands past the tendon range.

Units of the weighted error (Eq. 12): positions are measured in ``position_unit`` (default
1 mm) and rotations in ``rotation_unit`` (default 1 degree) before alpha weights the
rotational rows, so alpha = 1 trades 1 mm against 1 degree. The paper's alpha = 9.5 (cup
stacking) does not say its units; :mod:`vlr_drake.tasks.stack` measures rotations in
radians for it (1 rad against 9.5 mm, about 0.17 mm a degree), as the cups' nesting weighs
tilt against offset.
"""

from __future__ import annotations

import copy
import functools
import inspect
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from vlr_drake import kinematics, motion, observation
from vlr_drake.hand import HandModel

__all__ = [
    "MODES",
    "ROWS",
    "ControlModel",
    "ServoReport",
    "upsilon",
    "jacobian",
    "control_step",
    "pose_error6",
    "limit_action",
    "tendon_limits",
    "servo_to",
    "true_model_fn",
    "filter_model_fn",
    "usable_model",
    "row_weights",
    "FALLBACKS",
    "PredictedPlant",
]

MODES = ("dls", "transpose")
ROWS = ("position", "orientation", "full")
#: Default units of the weighted error (Eq. 12): 1 mm and 1 degree.
POSITION_UNIT = 1e-3
ROTATION_UNIT = np.deg2rad(1.0)


@dataclass
class ControlModel:
    """The controller's model of the grasp (one VLR hypothesis, DESIGN.md section 3).

    ``p_O`` are the contacts attached to the POM at the measured pose ``(R_PO, t_PO)``
    (``observation.attach``), so the model's current POM pose equals the measurement.
    """

    hand: HandModel
    theta: np.ndarray  # (N, K) joint angles [rad]
    a: np.ndarray  # (N,) contact positions along the last links [m]
    stiffness: np.ndarray  # (N, K) joint stiffness [N m/rad]
    link_lengths: np.ndarray  # (N, K-1) [m]
    stretch: np.ndarray  # (N,) equilibrium tendon stretch [m]
    p_O: np.ndarray  # (N, 3) contacts in the POM frame [m]
    R_PO: np.ndarray  # (3, 3) anchor pose (the measurement)
    t_PO: np.ndarray  # (3,)
    tendon: str = "elastic"
    # A physical grasp: an equilibrium whose implied tendon tensions pull (>= 0), the filter's
    # feasibility test. A weighted-mean estimate need not be one (see filter_model_fn).
    physical: bool = True

    @classmethod
    def from_estimate(
        cls, hand: HandModel, estimate: dict, R_PO, t_PO, *, tendon: str = "elastic"
    ) -> ControlModel:
        """Build from an estimate dict (keys ``theta`` (N,K), ``a`` (N,), optional
        ``stiffness`` (N,K) and ``link_lengths`` (N,K-1); e.g.
        :meth:`vlr_drake.filter.SelfIdentificationFilter.estimate`) and a measured pose."""
        N, K = hand.N, hand.K
        for key in ("theta", "a"):
            if key not in estimate:
                raise ValueError(f"estimate is missing '{key}'")
        theta = _shaped("estimate['theta']", estimate["theta"], (N, K))
        a = _shaped("estimate['a']", estimate["a"], (N,))
        k = estimate.get("stiffness")
        k = hand.stiffness.copy() if k is None else _shaped("estimate['stiffness']", k, (N, K))
        L = estimate.get("link_lengths")
        L = hand.link_lengths.copy() if L is None else _shaped("estimate['link_lengths']", L, (N, K - 1))
        R_PO = _shaped("R_PO", R_PO, (3, 3))
        t_PO = _shaped("t_PO", t_PO, (3,))
        eq = motion.equilibrium(hand, theta[None], a=a[None], link_lengths=L[None], stiffness=k[None])
        theta = eq.theta[0]
        p = kinematics.contacts(hand, theta[None], a[None], L[None])
        p_O = observation.attach(p, R_PO[None], t_PO[None])[0]
        physical = bool(eq.ok[0] and np.all(eq.tension[0] >= 0.0))
        return cls(hand, theta, a, k, L, eq.stretch[0], p_O, R_PO, t_PO, tendon, physical)

    @classmethod
    def from_plant_truth(cls, plant, R_PO=None, t_PO=None) -> ControlModel:
        """The true model of a :class:`vlr_drake.model_plant.ModelPlant` (for tests and the
        true-model task runs), anchored at a measured pose (default: the true pose)."""
        s = plant.state
        est = {"theta": s.theta, "a": s.a, "stiffness": plant.stiffness, "link_lengths": plant.link_lengths}
        return cls.from_estimate(
            plant.hand,
            est,
            s.R_PO if R_PO is None else R_PO,
            s.t_PO if t_PO is None else t_PO,
            tendon=plant.tendon,
        )


def _shaped(name: str, x, shape: tuple) -> np.ndarray:
    x = np.asarray(x, float)
    if x.shape != shape:
        raise ValueError(f"'{name}' must have shape {shape}, got {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"'{name}' must be finite, got {x.tolist()}")
    return x


#: Gamma's grasp constraint: the attachment p_O (rigid-body form) or the contact distances
#: D^2 (Eq. 8), whichever :func:`vlr_drake.motion.move` of this checkout takes.
_MOVE_TAKES_ATTACHMENT = "p_O" in inspect.signature(motion.move).parameters


def _move(model: ControlModel, theta: np.ndarray, dl, stretch: np.ndarray, l_now=None):
    """Gamma for B copies of the model's grasp (theta (B, N, K), stretch (B, N))."""
    h = model.hand
    B = theta.shape[0]
    a = np.broadcast_to(model.a, (B, h.N)).copy()
    if _MOVE_TAKES_ATTACHMENT:
        grasp = {"p_O": np.broadcast_to(model.p_O, (B, h.N, 3)).copy()}
    else:
        D2 = motion.contact_distances_sq(h, model.p_O[None])
        grasp = {"D2": np.broadcast_to(D2, (B, D2.shape[1])).copy()}
    return motion.move(
        h,
        theta,
        dl,
        a=a,
        stretch=stretch,
        link_lengths=model.link_lengths[None],
        stiffness=model.stiffness[None],
        tendon=model.tendon,
        l_now=l_now,
        **grasp,
    )


def upsilon(model: ControlModel, dl) -> np.ndarray:
    """Upsilon = Lambda o Gamma: POM motion dphi (6,) or (B, 6) for actions dl (N,) or (B, N).

    dphi = [t' - t, rotvec(R' R^T)] in the palm frame, with (R, t) the model's pose before
    the action. Actions whose move fails (no nearby equilibrium) give NaN rows.
    """
    h = model.hand
    dl = np.asarray(dl, float)
    single = dl.ndim == 1
    dl = np.atleast_2d(dl)
    if dl.shape[1] != h.N:
        raise ValueError(f"'dl' must have {h.N} entries per action, got shape {dl.shape}")
    B = dl.shape[0]
    res = _move(
        model,
        np.broadcast_to(model.theta, (B, h.N, h.K)).copy(),
        dl,
        np.broadcast_to(model.stretch, (B, h.N)).copy(),
    )
    p_O = np.broadcast_to(model.p_O, (B, h.N, 3))
    p0 = kinematics.contacts(h, model.theta[None], model.a[None], model.link_lengths[None])
    R0, t0, _ = observation.pom_pose(model.p_O[None], p0)
    p1 = kinematics.contacts(h, res.theta, np.broadcast_to(model.a, (B, h.N)), model.link_lengths[None])
    R1, t1, ok = observation.pom_pose(p_O, p1)
    out = np.concatenate([t1 - t0, observation.rotvec(np.einsum("bij,kj->bik", R1, R0[0]))], axis=1)
    out[~(res.ok & ok)] = np.nan
    return out[0] if single else out


#: The central differences' tendon step [m] of the Jacobian (Eq. 10): the default of
#: :func:`jacobian`, :func:`servo_to`, :func:`filter_model_fn` and the JacobianController.
JACOBIAN_EPS = 0.2e-3


def jacobian(model: ControlModel, eps: float = JACOBIAN_EPS, retries: int = 2) -> np.ndarray:
    """J (6, N) = dUpsilon/dl by central differences with step ``eps`` [m] (Eq. 10).

    A column whose perturbed move finds no equilibrium is retried with eps/4 (``retries``
    times), then one-sided from the side that works; raises RuntimeError if neither does.
    """
    if not (kinematics.is_number(eps) and 0 < eps < np.inf):  # NaN too
        raise ValueError(f"'eps' must be a positive finite number, got {eps!r}")
    if not kinematics.is_count(retries):  # (-1 had tried nothing and said "no equilibrium")
        raise ValueError(f"'retries' must be an integer >= 0, got {retries!r}")
    N = model.hand.N
    J = np.full((6, N), np.nan)
    todo = np.arange(N)
    h = eps
    for attempt in range(retries + 1):
        E = h * np.eye(N)[todo]
        d = upsilon(model, np.concatenate([E, -E]))
        plus, minus = d[: todo.size], d[todo.size :]
        good = np.all(np.isfinite(plus), axis=1) & np.all(np.isfinite(minus), axis=1)
        J[:, todo[good]] = ((plus[good] - minus[good]) / (2.0 * h)).T
        if attempt == retries:
            for j, col in enumerate(todo):
                if good[j]:
                    continue
                if np.all(np.isfinite(plus[j])):
                    J[:, col] = plus[j] / h
                elif np.all(np.isfinite(minus[j])):
                    J[:, col] = -minus[j] / h
        todo = todo[~good]
        if todo.size == 0:
            break
        h *= 0.25
    if not np.all(np.isfinite(J)):
        raise RuntimeError("jacobian: the model has no equilibrium for a perturbed action on either side")
    return J


def row_weights(rows: str, alpha: float, position_unit: float, rotation_unit: float) -> np.ndarray:
    """The weights W (6,) of Eq. 12 on [dt, dw]: 1/position_unit on the position rows,
    alpha/rotation_unit on the rotation rows, 0 on the rows ``rows`` does not control."""
    if rows not in ROWS:
        raise ValueError(f"'rows' must be one of {ROWS}, got '{rows}'")
    for name, v in (("alpha", alpha), ("position_unit", position_unit), ("rotation_unit", rotation_unit)):
        if not (np.isfinite(v) and v > 0):
            raise ValueError(f"'{name}' must be a positive finite number, got {v}")
    w = np.concatenate([np.full(3, 1.0 / position_unit), np.full(3, alpha / rotation_unit)])
    if not np.all(np.isfinite(w)):
        raise ValueError(f"'alpha' / 'rotation_unit' ({alpha} / {rotation_unit}) overflows: no finite weight")
    if rows == "position":
        w[3:] = 0.0
    elif rows == "orientation":
        w[:3] = 0.0
    return w


def _tamed(w: np.ndarray) -> np.ndarray:
    """Weights W whose largest is huge scaled down by a power of two (exactly): neither the
    step nor the comparison of weighted errors depends on W's scale, and a huge one had
    overflowed (alpha 1e308 hung in lstsq, 1e200 ended in "'dl' must be finite"; a review).
    The usual weights (up to 1e6) are left as they are, to the bit."""
    top = float(np.max(w))
    return np.ldexp(w, -int(np.ceil(np.log2(top)))) if top > 1e6 else w


def control_step(
    J,
    error6,
    *,
    mode: str = "dls",
    rows: str = "full",
    alpha: float = 1.0,
    damping: float = 0.01,
    gain: float = 0.7,
    clip: float = 1.0e-3,
    position_unit: float = POSITION_UNIT,
    rotation_unit: float = ROTATION_UNIT,
) -> np.ndarray:
    """One control action dl (N,) towards the error ``error6`` = [dt [m], dw [rad]] (6,).

    The error and J's rows are weighted by W = diag(1/position_unit (x3), alpha/rotation_unit
    (x3)) (Eq. 12), rows not controlled get weight 0 (truncation). Then

    - ``"dls"``: dl = gain (Jw^T Jw + lambda^2 I)^-1 Jw^T ew with lambda = ``damping`` times
      the largest singular value of Jw (damped least squares);
    - ``"transpose"``: dl = gain * s * Jw^T ew (Eq. 11), with the steepest-descent step
      length s = |Jw^T ew|^2 / |Jw Jw^T ew|^2 (the paper leaves the scale to the gain).
      Jw^T ew = J^T W^2 e, the gradient of the weighted squared error that the damped least
      squares minimises too; the paper's Eq. 11 with Eq. 12's error applies W once, J^T W e,
      so an ``alpha`` here acts as alpha^2 would there (a review; the default mode, "dls",
      solves the weighted least squares, in which W's square is the only form).

    Finally dl is scaled down (direction kept) so that max |dl_i| <= ``clip`` [m].
    """
    J = np.asarray(J, float)
    e = np.asarray(error6, float).reshape(-1)
    if J.ndim != 2 or J.shape[0] != 6:
        raise ValueError(f"'J' must have shape (6, N), got {J.shape}")
    if e.shape != (6,):
        raise ValueError(f"'error6' must have 6 entries, got {e.shape}")
    if not (np.all(np.isfinite(J)) and np.all(np.isfinite(e))):
        bad = "error6" if np.all(np.isfinite(J)) else "J"
        raise ValueError(f"'{bad}' must be finite, got {(e if bad == 'error6' else J).tolist()}")
    if mode not in MODES:
        raise ValueError(f"'mode' must be one of {MODES}, got '{mode}'")
    if not (gain > 0 and clip > 0 and damping >= 0 and np.isfinite([gain, clip, damping]).all()):  # NaN too
        raise ValueError(f"gain and clip must be positive and damping >= 0 (finite), got {gain}, {clip}, {damping}")
    w = _tamed(row_weights(rows, alpha, position_unit, rotation_unit))
    Jw = w[:, None] * J
    ew = w * e
    g = Jw.T @ ew
    if not np.any(g):
        return np.zeros(J.shape[1])
    if mode == "dls":
        smax = np.linalg.norm(Jw, 2)
        lam2 = (damping * smax) ** 2
        if lam2 > 0:
            dl = np.linalg.solve(Jw.T @ Jw + lam2 * np.eye(J.shape[1]), g)
        else:  # undamped: the pseudo-inverse's least-squares step, defined where Jw^T Jw is singular
            dl = np.linalg.lstsq(Jw, ew, rcond=None)[0]
    else:
        Jg = Jw @ g
        dl = g * (g @ g) / max(Jg @ Jg, 1e-300)
    dl = gain * dl
    m = np.max(np.abs(dl))
    if m > clip:
        dl *= clip / m
    return dl


def pose_error6(R_goal, t_goal, R, t) -> np.ndarray:
    """Error (6,) = [t_goal - t, rotvec(R_goal R^T)] in the palm frame (same convention as
    :func:`upsilon`, so a step with dphi = error reaches the goal)."""
    t_goal, t = (np.asarray(x, float) for x in (t_goal, t))
    if t_goal.shape != (3,) or t.shape != (3,):  # (a broadcasting error had named neither)
        raise ValueError(f"pose_error6: 't_goal' and 't' must have shape (3,), got {t_goal.shape} and {t.shape}")
    dw = observation.rotvec(np.asarray(R_goal) @ np.asarray(R).T)[0]
    return np.concatenate([t_goal - t, dw])


def limit_action(hand: HandModel, l_now, dl, limits=None) -> np.ndarray:
    """dl with every tendon kept inside ``limits`` (N, 2) (default ``hand.tendon_range``;
    always within it), per tendon clamp. A tendon that starts outside ``limits`` (but inside
    the range) never moves further out, and inwards by at most its own dl: it is not pulled
    into them in one jump past the step the caller clipped dl to (nor at all, while its dl
    points outwards)."""
    lim = tendon_limits(hand, limits)
    l_now = np.asarray(l_now, float).reshape(hand.N)
    dl = np.asarray(dl, float).reshape(hand.N)
    for name, x in (("l_now", l_now), ("dl", dl)):
        if not np.all(np.isfinite(x)):  # np.clip keeps NaN: it would leave the range
            raise ValueError(f"'{name}' must be finite, got {x.tolist()}")
    rng = hand.tendon_range
    lo = np.maximum(np.minimum(lim[:, 0], l_now), rng[:, 0])
    hi = np.minimum(np.maximum(lim[:, 1], l_now), rng[:, 1])
    l_new = np.clip(l_now + dl, lo, hi)
    return l_new - l_now


def tendon_limits(hand: HandModel, limits=None) -> np.ndarray:
    """(N, 2) command limits: ``limits`` intersected with ``hand.tendon_range`` (+-inf for no
    limit on that side). NaN limits, a lower above an upper one, or limits that miss the
    range altogether (e.g. given in millimetres), are a ValueError (NaN had passed through the
    clamps into the commands; limits past the range had become one point outside it)."""
    if limits is None:
        return hand.tendon_range.copy()
    limits = np.asarray(limits, float)
    if limits.shape != (hand.N, 2):
        raise ValueError(f"'limits' must have shape ({hand.N}, 2), got {limits.shape}")
    if np.any(np.isnan(limits)) or np.any(limits[:, 0] > limits[:, 1]):
        raise ValueError(f"'limits' must be (lower, upper) pairs with lower <= upper [m], no NaN, got "
                         f"{limits.tolist()}")
    lo = np.maximum(limits[:, 0], hand.tendon_range[:, 0])
    hi = np.minimum(limits[:, 1], hand.tendon_range[:, 1])
    if np.any(lo > hi):
        raise ValueError(f"'limits' {limits.tolist()} m miss the hand's tendon range "
                         f"{hand.tendon_range.tolist()} m for tendons {np.flatnonzero(lo > hi).tolist()} "
                         "(lengths are in metres)")
    return np.column_stack([lo, hi])


@dataclass
class ServoReport:
    """Outcome of :func:`servo_to` (errors of the measured pose against the goal)."""

    reached: bool  # the error came under tolerance
    reason: str  # "reached" | "budget" | "stalled" | "tendon_limit" | "no_equilibrium" | "lost_tag"
    iterations: int  # actions applied
    position_error: float  # final |dt| [m]
    rotation_error: float  # final angle [rad]
    R_closest: np.ndarray  # measured pose with the smallest weighted error
    t_closest: np.ndarray
    closest_position_error: float  # [m]
    closest_rotation_error: float  # [rad]
    at_limit: bool  # some tendon ended at a limit of the servo's ``limits`` (default: its range)
    history: list = field(default_factory=list)  # per iteration: (position_error, rotation_error, dl)
    lost: int = 0  # measurements that came without the tag (the pose was predicted instead)
    R_final: np.ndarray | None = None  # the pose at the end: measured, else predicted (for ``resume``)
    t_final: np.ndarray | None = None
    lost_in_a_row: int = 0  # lost tags since the last measured pose, at the end

    def summary(self) -> str:
        return (
            f"{self.reason} after {self.iterations} steps: error {self.position_error * 1e3:.3f} mm, "
            f"{np.rad2deg(self.rotation_error):.3f} deg (closest {self.closest_position_error * 1e3:.3f} mm, "
            f"{np.rad2deg(self.closest_rotation_error):.3f} deg)"
        )


def _tendon_command(plant) -> np.ndarray:
    if hasattr(plant, "tendon_command"):
        l = plant.tendon_command
        return np.asarray(l() if callable(l) else l, float).copy()
    return np.asarray(plant.state.tendon_command, float).copy()


def _measured(plant) -> tuple:
    """``plant.measure()``, (R, t, valid), with a pose marked valid that is not finite named
    (it had ended a task deep in the control model, as "'t_PO' must be finite")."""
    R, t, valid = plant.measure()
    if valid and not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        raise ValueError(f"servo: the plant's measurement is marked valid but its pose is not finite "
                         f"(R {np.asarray(R).tolist()}, t {np.asarray(t).tolist()}); a lost tag is valid=False")
    return R, t, valid


def servo_to(
    R_goal,
    t_goal,
    plant,
    model_fn: Callable[[np.ndarray, np.ndarray, np.ndarray, bool], ControlModel],
    *,
    rows: str = "full",
    mode: str = "dls",
    alpha: float = 1.0,
    gain: float = 0.7,
    damping: float = 0.01,
    clip: float = 1.0e-3,
    eps: float = JACOBIAN_EPS,
    tol_position: float = 0.05e-3,
    tol_rotation: float = np.deg2rad(0.2),
    max_steps: int = 30,
    stall_steps: int = 6,
    backoff: int = 3,
    max_lost: int = 5,
    limits=None,
    position_unit: float = POSITION_UNIT,
    rotation_unit: float = ROTATION_UNIT,
    on_step: Callable[[int, np.ndarray, np.ndarray], None] | None = None,
    resume: ServoReport | None = None,
) -> ServoReport:
    """Drive the POM to (R_goal, t_goal) with camera feedback (DESIGN.md section 7).

    ``plant`` has ``hand``, ``measure() -> (R, t, valid)``, ``apply_action(dl) -> bool`` and
    a tendon command (``plant.tendon_command``, an array or a method, or
    ``plant.state.tendon_command``), e.g.
    :class:`vlr_drake.model_plant.ModelPlant`. ``model_fn(dl, R, t, valid)`` returns the
    controller's model after the action ``dl`` (zeros before the first) and the measurement
    (R, t, valid); a filter-backed ``model_fn`` also takes the action as evidence.
    Tolerances apply to the controlled rows only. Stops when under tolerance, after
    ``max_steps`` actions, or when the weighted error has not improved for
    ``stall_steps`` steps (e.g. an unreachable goal or tendons at their limits).
    ``limits`` (N, 2) narrows the tendon commands further than the hand's range (e.g. a
    window around the grasp, so the grip never loosens enough to drop the object); the
    commands never leave it nor the hand's range.
    A step for which the plant finds no equilibrium (e.g. the grip would loosen) is
    halved up to ``backoff`` times before the run ends with ``"no_equilibrium"``.
    ``on_step(i, R, t)`` is called after every measurement (progress, marble simulation).
    A lost tag (``valid`` False) is not a measurement: the pose is predicted from the last one
    through the model, pose + J dl (Eq. 10; stepping again on the stale error had overshot
    the goal), the model is told the measurement is not valid, the closest pose and the
    stall count consider measured poses only, and ``max_lost`` lost tags in a row end the
    run with ``"lost_tag"``. The first measurement, if lost, is the plant's held pose (its
    last valid one). ``resume`` is the report of the call before, for a caller that servos a
    step at a time without moving the hand in between (e.g. the maze): where that call ended
    on a measured pose, the pose is this call's first measurement (one frame per action, not
    two); where it ended on a lost tag, the plant is measured again and, if lost once more,
    that call's predicted pose is the first, with its lost tags in a row counting on.
    """
    for name, value, least in (("max_steps", max_steps, 0), ("stall_steps", stall_steps, 1),
                               ("backoff", backoff, 0), ("max_lost", max_lost, 1)):
        if not kinematics.is_count(value, least):  # (inf steps on an unreachable goal never ended)
            raise ValueError(f"'{name}' must be an integer >= {least}, got {value!r}")
    for name, value in (("tol_position", tol_position), ("tol_rotation", tol_rotation), ("damping", damping)):
        if not (kinematics.is_number(value) and 0 <= value < np.inf):
            raise ValueError(f"'{name}' must be a finite number >= 0, got {value!r}")
    for name, value in (("gain", gain), ("clip", clip), ("eps", eps)):
        if not (kinematics.is_number(value) and 0 < value < np.inf):
            raise ValueError(f"'{name}' must be a positive finite number, got {value!r}")
    R_goal = _shaped("R_goal", R_goal, (3, 3))
    t_goal = _shaped("t_goal", t_goal, (3,))
    w = _tamed(row_weights(rows, alpha, position_unit, rotation_unit))  # (compared, never reported)
    ctrl_pos, ctrl_rot = rows in ("position", "full"), rows in ("orientation", "full")
    if resume is not None and resume.R_final is not None and resume.lost_in_a_row == 0:
        # the call before ended on a measured pose and the hand has not moved since: that
        # frame is this one (the maze had looked twice per action, a second render and
        # detection per control period on the physics plant)
        R, t, valid = resume.R_final, resume.t_final, True
    else:
        R, t, valid = _measured(plant)
    R_last, t_last = np.array(R, float), np.array(t, float)
    lost = lost_in_a_row = int(not valid)
    if not valid and resume is not None and resume.R_final is not None:
        R_last, t_last = np.array(resume.R_final, float), np.array(resume.t_final, float)
        lost_in_a_row += resume.lost_in_a_row
    model = model_fn(np.zeros(plant.hand.N), R_last, t_last, valid)
    hand = model.hand
    best = None
    since_best = 0
    history: list = []
    reason = "budget"
    it = 0
    measured = bool(valid)  # the pose at the top of the loop was measured (not held or predicted)
    step = functools.partial(control_step, mode=mode, rows=rows, alpha=alpha, damping=damping, gain=gain, clip=clip,
                             position_unit=position_unit, rotation_unit=rotation_unit)

    def errors(R_, t_):
        e = pose_error6(R_goal, t_goal, R_, t_)
        return e, float(np.linalg.norm(e[:3])), float(np.linalg.norm(e[3:])), float(np.linalg.norm(w * e))

    while True:
        e, ep, er, ew = errors(R_last, t_last)
        if best is None or (measured and ew < best[0] - 1e-9):
            best, since_best = (ew, R_last.copy(), t_last.copy(), ep, er), 0
        elif measured:
            since_best += 1
        if lost_in_a_row >= max_lost:
            reason = "lost_tag"
            break
        if (not ctrl_pos or ep <= tol_position) and (not ctrl_rot or er <= tol_rotation):
            if measured:
                reason = "reached"
                break
            # predicted there: look again before calling it reached
            R, t, valid = _measured(plant)
            measured = bool(valid)
            if valid:
                R_last, t_last, lost_in_a_row = np.asarray(R, float), np.asarray(t, float), 0
                model = model_fn(np.zeros(hand.N), R_last, t_last, valid)
            else:
                lost += 1
                lost_in_a_row += 1
            continue
        if it >= max_steps:
            reason = "budget"
            break
        if since_best >= stall_steps:
            reason = "stalled"
            break
        # a model that is no physical grasp (a pushing tendon: a mean of hypotheses,
        # filter_model_fn's last resort) had steered on its Jacobian (a review)
        J = _jacobian_if_usable(model, eps)
        if J is None:
            reason = "no_equilibrium"
            break
        dl = step(J, e)
        if np.max(np.abs(dl)) < 1e-9:
            reason = "stalled"  # the error lies outside the motions the model can make
            break
        l_now = _tendon_command(plant)
        # tendons at a limit that the step pushes against are left out and the step is
        # solved again with the others (active set), so the free tendons still help
        lim = tendon_limits(hand, limits)
        lo, hi = lim[:, 0], lim[:, 1]
        blocked = ((l_now <= lo + 1e-9) & (dl < 0)) | ((l_now >= hi - 1e-9) & (dl > 0))
        if blocked.any() and not blocked.all():
            dl = step(J * ~blocked[None, :], e)
            dl[blocked] = 0.0
        dl_lim = limit_action(hand, l_now, dl, limits)
        if np.max(np.abs(dl_lim)) < 1e-9:
            reason = "tendon_limit"
            break
        applied = plant.apply_action(dl_lim)
        for _ in range(backoff):  # no equilibrium for the whole step: shorter steps
            if applied:
                break
            dl_lim = 0.5 * dl_lim
            applied = plant.apply_action(dl_lim)
        if not applied:
            reason = "no_equilibrium"
            break
        it += 1
        R, t, valid = _measured(plant)
        measured = bool(valid)
        if valid:
            R_last, t_last = np.asarray(R, float), np.asarray(t, float)
            lost_in_a_row = 0
        else:  # dead reckoning through the model's Jacobian
            d = J @ dl_lim
            t_last = t_last + d[:3]
            R_last = observation.rotvec_to_matrix(d[3:])[0] @ R_last
            lost += 1
            lost_in_a_row += 1
        model = model_fn(dl_lim, R_last, t_last, valid)
        history.append((ep, er, dl_lim))
        if on_step is not None:
            on_step(it, R_last, t_last)
    l_now, lim = _tendon_command(plant), tendon_limits(hand, limits)
    at_limit = bool(np.any((l_now <= lim[:, 0] + 1e-9) | (l_now >= lim[:, 1] - 1e-9)))
    return ServoReport(
        reached=reason == "reached",
        reason=reason,
        iterations=it,
        position_error=ep,
        rotation_error=er,
        R_closest=best[1],
        t_closest=best[2],
        closest_position_error=best[3],
        closest_rotation_error=best[4],
        at_limit=at_limit,
        history=history,
        lost=lost,
        R_final=R_last.copy(),
        t_final=t_last.copy(),
        lost_in_a_row=lost_in_a_row,
    )


def true_model_fn(plant) -> Callable[[np.ndarray, np.ndarray, np.ndarray, bool], ControlModel]:
    """``model_fn`` for :func:`servo_to` that uses the model plant's hidden truth,
    anchored at the measured pose."""

    def fn(dl, R, t, valid):
        return ControlModel.from_plant_truth(plant, R, t)

    return fn


#: How many live hypotheses nearest the filter's mean a controller tries when the mean is no
#: usable model (:func:`filter_model_fn`, the JacobianController's ``estimate["fallbacks"]``).
FALLBACKS = 8


def _jacobian_if_usable(model: ControlModel, eps: float = JACOBIAN_EPS) -> np.ndarray | None:
    """The model's Jacobian (Eq. 10, step ``eps``) when it is a physical grasp and every
    perturbed action has an equilibrium, else None: what makes a model usable for control."""
    if not model.physical:
        return None
    try:
        return jacobian(model, eps)
    except RuntimeError:
        return None


def usable_model(hand: HandModel, est: dict, R, t, *, tendon: str = "elastic", eps: float = JACOBIAN_EPS):
    """``(model, J)``: the :class:`ControlModel` of ``est`` anchored at the measured pose
    (R, t) and its Jacobian when it is a physical grasp whose Jacobian exists, else those of
    the first of ``est["fallbacks"]`` (estimate dicts, e.g. the filter's nearest hypotheses)
    that is; None when none is."""
    for candidate in [est, *est.get("fallbacks", [])]:
        try:
            model = ControlModel.from_estimate(hand, candidate, R, t, tendon=tendon)
        except ValueError:
            continue
        J = _jacobian_if_usable(model, eps)
        if J is not None:
            return model, J
    return None


def filter_model_fn(filt, hand: HandModel, *, tendon: str = "elastic", fallbacks: int = FALLBACKS,
                    eps: float = JACOBIAN_EPS):
    """``model_fn`` for :func:`servo_to` backed by a
    :class:`vlr_drake.filter.SelfIdentificationFilter`: every control action (non-zero dl)
    is also one filter iteration (evidence), so rolling contacts are tracked.

    The model is the filter's weighted-mean estimate when it is a physical grasp whose
    Jacobian exists, else the first of the ``fallbacks`` live hypotheses nearest to it
    (:meth:`~vlr_drake.filter.SelfIdentificationFilter.nearest_hypotheses`) that is (else the
    mean, and the servo reports "no_equilibrium"). The mean of a cloud is more symmetric
    than its members: on the physics plant (handwriting 'SCIENCE', seed 0) it settled where
    the side fingers mirror each other, with a pushing tendon (-13 N) or a side pair pulled
    apart, and no perturbed action had an equilibrium: 53 control steps ended
    "no_equilibrium" and the letters came out 3.6-4.0 mm off (0.12 mm with the fallback).
    ``eps``: the Jacobian's step the servo uses (:func:`servo_to`'s), at which a model must
    be usable."""

    failed = []  # the filter's failure during control, once: it had ended the task in a traceback (a review)

    def fn(dl, R, t, valid):
        if np.any(dl) and not failed:
            try:
                filt.step(dl, R, t, valid)
            except Exception as e:  # noqa: BLE001 - control goes on with the last estimate, said once
                failed.append(e)
                warnings.warn(f"the filter failed during control at its iteration {len(filt.history) + 1} "
                              f"({type(e).__name__}: {e}): the control goes on with its last estimate",
                              RuntimeWarning, stacklevel=2)
        model = ControlModel.from_estimate(hand, filt.estimate(), R, t, tendon=tendon)
        if _jacobian_if_usable(model, eps) is not None:
            return model
        for est in filt.nearest_hypotheses(fallbacks):  # only when the mean is no usable model
            candidate = ControlModel.from_estimate(hand, est, R, t, tendon=tendon)
            if _jacobian_if_usable(candidate, eps) is not None:
                return candidate
        return model

    return fn


class PredictedPlant:
    """The controller's model used as a plant (no noise): what the model predicts the hand
    will do. For planning (e.g. probing the reachable workspace before writing) and tests.
    Same interface as :class:`vlr_drake.model_plant.ModelPlant` for :func:`servo_to`."""

    def __init__(self, model: ControlModel, l_now):
        self.model = copy.deepcopy(model)  # moved in place; the caller's model is kept
        self.hand = model.hand
        self.tendon_command = np.asarray(l_now, float).reshape(model.hand.N).copy()

    def pose(self) -> tuple[np.ndarray, np.ndarray]:
        m = self.model
        p = kinematics.contacts(m.hand, m.theta[None], m.a[None], m.link_lengths[None])
        R, t, _ = observation.pom_pose(m.p_O[None], p)
        return R[0], t[0]

    def apply_action(self, dl) -> bool:
        m = self.model
        dl = np.asarray(dl, float).reshape(m.hand.N)
        res = _move(m, m.theta[None], dl, m.stretch[None], l_now=self.tendon_command)
        if not res.ok[0]:
            return False
        m.theta, m.stretch = res.theta[0], res.stretch[0]
        self.tendon_command = self.tendon_command + dl
        return True

    def measure(self) -> tuple[np.ndarray, np.ndarray, bool]:
        R, t = self.pose()
        return R, t, True

    def model_fn(self, dl, R, t, valid) -> ControlModel:
        """``model_fn`` for :func:`servo_to`: the model itself (it is the truth here)."""
        return self.model
