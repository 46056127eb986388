"""Shared pieces of the three tasks: the grasp on the model plant, the controller's model
(the truth or a running self-identification filter) and the error statistics of the result
files (docs/result-files.md)."""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from vlr_drake import control, grasps
from vlr_drake import filter as pf
from vlr_drake.hand import HandModel, model_o
from vlr_drake.kinematics import is_count, is_number
from vlr_drake.model_plant import ModelPlant

__all__ = [
    "TaskSetupError",
    "start_model",
    "MODELS",
    "grip_window",
    "object_fell",
    "TaskPlant",
    "PhysicsTaskPlant",
    "make_model_plant",
    "make_model_fn",
    "stats",
    "pooled",
    "grasp_config",
    "TASK_EXPLORATION",
    "task_view",
    "followed",
    "save_view",
]

class TaskSetupError(ValueError):
    """A task that cannot start from its seed's draw (no grasp away from a fold, a grasp that
    cannot make the task's motions): a command says so in one line; another seed may do."""


def start_model(pl, model_fn, hand, task: str, seed: int):
    """The task's first measurement and the controller's model there: ``(R, t, model, J)``
    (J: the model's Jacobian, Eq. 10). A lost first tag is passed on as not valid (the pose
    is the plant's held one); a model with no equilibrium about the grasp is a
    :class:`TaskSetupError` naming the task and seed."""
    R, t, valid = pl.measure()
    model = model_fn(np.zeros(hand.N), R, t, valid)
    if not model.physical:  # (its Jacobian had been taken all the same: a review)
        raise TaskSetupError(f"{task}, seed {seed}: the controller's model is no physical grasp (a tendon would "
                             "push); try another seed")
    try:
        J = control.jacobian(model)
    except RuntimeError as e:
        raise TaskSetupError(f"{task}, seed {seed}: the controller's model has no equilibrium about the grasp "
                             f"({e}); try another seed") from e
    return np.asarray(R, float), np.asarray(t, float), model, J


#: The tasks' identification exploration: (action range, window) [m]; the window is also
#: the control's grip window (``grip_window``).
TASK_EXPLORATION = (1.5e-3, 4.0e-3)

#: Where the controller's model comes from: the plant's hidden truth, or a particle filter
#: that identifies the grasp first and keeps updating during control (each action is evidence).
MODELS = ("true", "filter")
#: Palm-frame position of the POM at the grasp [m] (the identification experiments' value).
GRASP_T_PO = np.array([0.0, 0.0, 0.11])


#: Largest POM motion per tendon motion a task grasp may have: near a fold of the grasp
#: (snap-through) the Jacobian grows without bound and a tiny action flips the object.
MAX_TRANSLATION_GAIN = 5.0  # [m/m]
MAX_ROTATION_GAIN = np.deg2rad(10.0) / 1e-3  # [rad/m]: 10 degrees per millimetre
#: Smallest fraction of random tendon offsets inside the grip window (``TASK_EXPLORATION``)
#: for which a task grasp must have a nearby equilibrium (64 offsets, from the grasp). The
#: gain test alone let through grasps next to a fold: handwriting seed 0 refused 192 of
#: 405 actions and ended 35 of 61 waypoints with no equilibrium (letters 1.09 mm off).
MIN_POSSIBLE_ACTIONS = 0.9


def grasp_config(
    hand: HandModel, rng: np.random.Generator, max_draws: int = 50, min_possible: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """A realistic fingertip grasp (theta (N, K), a (N,)) drawn with ``rng``, away from
    folds: its Jacobian (Eq. 10) stays under ``MAX_TRANSLATION_GAIN`` and
    ``MAX_ROTATION_GAIN`` (column norms), and it has an equilibrium for at least
    ``min_possible`` of random tendon offsets inside the grip window (what a grasp planner
    would check before writing or stacking with it; the tasks ask for
    ``MIN_POSSIBLE_ACTIONS``)."""
    for _ in range(max_draws):
        gs = grasps.sample_grasps(
            hand,
            rng,
            1,
            proximal_range=(0.05, 0.35),
            distal_range=(0.3, 0.9),
            contact_range=(0.02, 0.032),
            min_tension=2.0,
            stable=True,
        )
        theta, a = gs.theta[0], gs.a[0]
        est = {"theta": theta, "a": a}
        try:
            J = control.jacobian(control.ControlModel.from_estimate(hand, est, np.eye(3), GRASP_T_PO))
        except RuntimeError:
            continue
        if (
            np.linalg.norm(J[:3], axis=0).max() <= MAX_TRANSLATION_GAIN
            and np.linalg.norm(J[3:], axis=0).max() <= MAX_ROTATION_GAIN
            and (min_possible <= 0 or _possible_fraction(hand, theta, a) >= min_possible)
        ):
            return theta, a
    raise TaskSetupError(f"no grasp away from a fold in {max_draws} draws (the task's seed draws them; try another)")


@dataclass
class TaskPlant:
    """A model plant with its hand and the grasp it started from (the tasks' plant).

    ``plant`` is what :func:`vlr_drake.control.servo_to` drives; ``true_pose``,
    ``truth_estimate`` and ``nominal`` give the truth for the errors, the true-model
    controller and the filter's prior centre.
    """

    hand: HandModel
    plant: ModelPlant
    theta0: np.ndarray
    a0: np.ndarray
    kind: str = "model"

    def true_pose(self) -> tuple[np.ndarray, np.ndarray]:
        return self.plant.state.R_PO.copy(), self.plant.state.t_PO.copy()

    def tendon_command(self) -> np.ndarray:
        return self.plant.state.tendon_command.copy()

    def truth_estimate(self) -> dict:
        s = self.plant.state
        return {
            "theta": s.theta.copy(),
            "a": s.a.copy(),
            "stiffness": self.plant.stiffness,
            "link_lengths": self.plant.link_lengths,
        }

    def nominal(self, rng: np.random.Generator, prior: pf.PriorConfig) -> tuple[np.ndarray, np.ndarray]:
        """The filter's nominal grasp: the truth displaced by up to
        CENTER_OFFSET_FRACTION of the prior's half-widths (as in the identification
        experiments)."""
        return prior.guessed_grasp(self.theta0, self.a0, rng, self.hand)


def _possible_fraction(hand: HandModel, theta, a, samples: int = 64) -> float:
    """Fraction of ``samples`` random tendon offsets within +-``TASK_EXPLORATION[1]`` (a
    fixed draw) for which the grasp (theta, a) has a nearby physical equilibrium."""
    plant = ModelPlant(hand, theta, a, np.eye(3), GRASP_T_PO, np.random.default_rng(0))
    window = TASK_EXPLORATION[1]
    dls = np.random.default_rng(0).uniform(-window, window, (samples, hand.N))
    return float(plant.possible_actions(dls).mean())


def make_model_plant(
    seed: int,
    *,
    hand: HandModel | None = None,
    R_PO=None,
    t_PO=None,
    sigma_position: float = 0.2e-3,
    sigma_rotation_deg: float = 0.5,
    theta=None,
    a=None,
    min_possible: float = 0.0,
    dropout: float = 0.0,
) -> TaskPlant:
    """The model plant (DESIGN.md section 8) holding an object in a grasp drawn from ``seed``
    (or the given ``theta``, ``a``; ``min_possible``: see :func:`grasp_config`), with the
    camera stand-in's Gaussian pose noise and its ``dropout`` (the probability of a lost tag)."""
    hand = model_o().model() if hand is None else hand
    rng = np.random.default_rng(seed)
    if (theta is None) != (a is None):  # (one alone had been replaced by a drawn grasp without a word)
        raise ValueError("make_model_plant: give the grasp's 'theta' and 'a' together, or neither (a drawn grasp)")
    if theta is None:
        theta, a = grasp_config(hand, rng, min_possible=min_possible)
    plant = ModelPlant(
        hand,
        theta,
        a,
        np.eye(3) if R_PO is None else R_PO,
        GRASP_T_PO if t_PO is None else t_PO,
        np.random.default_rng(seed + 1000),
        sigma_position=sigma_position,
        sigma_rotation=np.deg2rad(sigma_rotation_deg),
        dropout=dropout,
    )
    return TaskPlant(hand, plant, np.asarray(theta, float), np.asarray(a, float))


class PhysicsTaskPlant:
    """The physics plant (MultibodyPlant, rendered palm camera, AprilTag observer; see
    :class:`vlr_drake.physics_identify.PhysicsAdapter`) holding a preset object, behind the
    same interface as :class:`TaskPlant`; it is its own ``plant`` for ``servo_to``. One
    action ramps and settles the physics; a lost tag repeats the last pose as invalid."""

    kind = "physics"

    def __init__(self, object_name: str, seed: int, physics=None, camera=None, object_spec=None):
        """``object_spec`` (an :class:`vlr_drake.objects.ObjectSpec`) replaces the preset
        ``object_name``, e.g. to place it differently."""
        from types import SimpleNamespace

        from vlr_drake.physics_identify import PhysicsAdapter

        self.adapter = PhysicsAdapter(
            SimpleNamespace(object=object_name, object_spec=object_spec, seed=seed), model_o(), np.random.default_rng(seed),
            physics, camera,
        )
        self.hand = self.adapter.hand
        self.plant = self
        self.timing = {"physics": 0.0, "render": 0.0, "detect": 0.0}
        self.fell: str | None = None
        theta_c, a_c, R, t = self.adapter.start(None)
        self.theta0 = np.asarray(theta_c, float).reshape(self.hand.N, self.hand.K)
        self.a0 = np.broadcast_to(np.asarray(a_c, float), (self.hand.N,)).copy()
        self._last = (R, t)
        X = self.adapter.obj.X_PB() @ self.adapter.obj.X_BO()
        #: the POM pose the object was planned to have in the palm (before it settled)
        self.X_PO_planned = (X.rotation().matrix(), X.translation())

    def tendon_command(self) -> np.ndarray:
        return self.adapter.tendon_command()

    def apply_action(self, dl) -> bool:
        if self.fell:
            return False
        try:
            return self.adapter.act(dl, self.timing)
        except RuntimeError as err:  # the object fell out of the hand
            self.fell = str(err)
            return False

    def measure(self):
        R, t, valid = self.adapter.measure(self.timing)
        if not valid:
            return self._last[0], self._last[1], False
        self._last = (R, t)
        return R, t, True

    def true_pose(self) -> tuple[np.ndarray, np.ndarray]:
        X = self.adapter.ph.output(self.adapter.root, "X_PO_true")
        return X.rotation().matrix().copy(), X.translation().copy()

    def truth_estimate(self) -> dict:
        return self.adapter.truth()

    def nominal(self, rng, prior) -> tuple[np.ndarray, np.ndarray]:
        """The filter's nominal grasp: the placed grasp's angles and a guess of the contacts,
        which the pads fix, displaced by up to CENTER_OFFSET_FRACTION of the contact
        half-width as in the identification experiments (drawn from the task's ``rng``)."""
        return np.array(self.theta0, float), prior.guessed_contacts(self.a0, rng, self.hand)


def check_plant(plant: str) -> None:
    """ValueError unless ``plant`` names a task's plant: "model" or "physics"."""
    if plant not in ("model", "physics"):
        raise ValueError(f"plant must be 'model' or 'physics', got '{plant}'")


def task_plant(plant: str, seed: int, physics_object: str, physics=None, camera=None, *,
               sigma_position: float, sigma_rotation_deg: float, dropout: float = 0.0):
    """The plant a task runs on: the model plant (a grasp drawn from ``seed``, measurement
    noise ``sigma_position`` [m] and ``sigma_rotation_deg``, lost tags with probability
    ``dropout``; :func:`make_model_plant`) or the physics plant holding ``physics_object``
    (:class:`PhysicsTaskPlant`)."""
    check_plant(plant)
    if plant == "model":
        return make_model_plant(seed, sigma_position=sigma_position, sigma_rotation_deg=sigma_rotation_deg,
                                min_possible=MIN_POSSIBLE_ACTIONS, dropout=dropout)
    return PhysicsTaskPlant(physics_object, seed, physics, camera)


def model_settings(model: str, particles: int, identify_iterations: int) -> dict:
    """A task result's record of its self-identification's setup: ``particles`` and
    ``identify_iterations`` with ``model`` "filter", None for both with the true model (no
    filter runs)."""
    used = model == "filter"
    return {"particles": int(particles) if used else None,
            "identify_iterations": int(identify_iterations) if used else None}


def make_model_fn(
    kind: str,
    tp,
    *,
    seed: int = 0,
    particles: int = 3000,
    identify_iterations: int = 40,
    action_range: float | None = None,
    window: float = TASK_EXPLORATION[1],
) -> tuple[Callable, object | None]:
    """The controller's ``model_fn`` for :func:`vlr_drake.control.servo_to`, and the filter
    (or None), for a :class:`TaskPlant` or :class:`PhysicsTaskPlant`.

    ``"true"``: the plant's truth (the physics plant's: its joint angles and contact
    positions read as a VLR), anchored at each measurement. ``"filter"``: a
    :class:`vlr_drake.filter.SelfIdentificationFilter` initialised around the nominal grasp,
    run for ``identify_iterations`` random exploratory actions (then the tendons return to
    the grasp command), and kept running during control (each action is evidence).
    Exploration: actions of +-``action_range`` (None: 1.5 mm on the model plant, 0.5 mm on
    the physics plant) inside ``window`` (on the physics plant at most 1.2 mm).
    """
    if kind not in MODELS:
        raise ValueError(f"model must be one of {MODELS}, got '{kind}'")
    if not is_count(identify_iterations):  # (2.5 had failed in range(), -1 run none silently)
        raise ValueError(f"'identify_iterations' must be an integer >= 0, got {identify_iterations!r}")
    plant, h = tp.plant, tp.hand
    if kind == "true":

        def true_fn(dl, R, t, valid):
            return control.ControlModel.from_estimate(h, tp.truth_estimate(), R, t)

        return true_fn, None
    from vlr_drake.identify import Exploration

    rng = np.random.default_rng(seed + 7)
    prior = pf.PriorConfig()
    theta_c, a_c = tp.nominal(rng, prior)
    filt = pf.SelfIdentificationFilter(
        h, pf.FilterConfig(particles=particles), prior, np.random.default_rng(seed + 8)
    )
    R, t, _ = plant.measure()
    l_grasp = tp.tendon_command()
    filt.initialise(theta_c, a_c, R, t, tendon_command=l_grasp)
    from vlr_drake.identify import EXPLORATION

    physics = isinstance(tp, PhysicsTaskPlant)
    if action_range is None:
        action_range = EXPLORATION["physics"][0] if physics else TASK_EXPLORATION[0]
    explore_window = min(window, EXPLORATION["physics"][1]) if physics else window
    if action_range > explore_window:  # (identify refuses it; the tasks had walked 1.5 mm steps in 1.2 mm)
        raise ValueError(f"the tasks' exploration span ({action_range * 1e3:g} mm, a scenario's exploration.span) "
                         f"must be at most their exploration window, {explore_window * 1e3:g} mm (the grip window "
                         f"exploration.window, on the physics plant at most {EXPLORATION['physics'][1] * 1e3:g} mm)")
    explore = Exploration(l_grasp, h.tendon_range, action_range, explore_window, np.random.default_rng(seed + 9))
    for _ in range(identify_iterations):
        dl = explore.next_action()
        if not plant.apply_action(dl):
            continue
        explore.commit(dl)
        _identify_step(filt, dl, plant, tp, seed)
    # back to the grasp command (in small steps, each one evidence too)
    for _ in range(8):
        dl = np.clip(l_grasp - tp.tendon_command(), -action_range, action_range)
        if np.max(np.abs(dl)) < 1e-9 or not plant.apply_action(dl):
            break
        _identify_step(filt, dl, plant, tp, seed)
    return control.filter_model_fn(filt, h), filt


def _identify_step(filt, dl, plant, tp, seed: int) -> None:
    """One filter iteration of a task's self-identification (the measurement after ``dl``);
    where the filter fails, a :class:`TaskSetupError` that says so, in one line (it had ended
    the task in a traceback, nothing written; a review)."""
    R, t, valid = plant.measure()
    try:
        filt.step(dl, R, t, valid, tendon_command=tp.tendon_command())
    except Exception as e:  # noqa: BLE001 - said as the task's, not lost in a traceback
        raise TaskSetupError(f"seed {seed}: the task's self-identification failed at its iteration "
                             f"{len(filt.history) + 1} ({type(e).__name__}: {e})") from e


def grip_window(hand: HandModel, l_grasp, window: float) -> np.ndarray:
    """(N, 2) tendon command limits: +-``window`` [m] around the grasp's commands, within
    the tendon range (see :func:`vlr_drake.control.tendon_limits`)."""
    l_grasp = np.asarray(l_grasp, float).reshape(hand.N)
    if not (is_number(window) and window > 0):  # (NaN had been named as NaN 'limits')
        raise ValueError(f"'window' must be positive, got {window!r}")
    return control.tendon_limits(hand, np.column_stack([l_grasp - window, l_grasp + window]))


def object_fell(tp) -> bool:
    """True when the plant reports that the object fell out of the hand (physics plant)."""
    return bool(getattr(tp, "fell", None))


def stats(values_m_or_rad, scale: float) -> dict | None:
    """{"mean", "sd", "max", "n"} of the values times ``scale`` (1e3 for mm, rad2deg for deg);
    ``n`` (how many) lets trials be pooled (:func:`pooled`)."""
    v = np.asarray(values_m_or_rad, float) * scale
    if v.size == 0:
        return None
    return {"mean": float(v.mean()), "sd": float(v.std()), "max": float(v.max()), "n": int(v.size)}


def check_positive(**values) -> None:
    """ValueError naming the first of ``values`` that is not a positive finite number."""
    for name, v in values.items():
        if not (is_number(v) and 0 < v < np.inf):
            raise ValueError(f"'{name}' must be a positive finite number, got {v!r}")


def save_figure(fig, path, dpi: int = 110) -> None:
    """A task's plot saved to ``path`` in one piece (:func:`vlr_drake.entry.replacing`)."""
    from vlr_drake.entry import replacing

    with replacing(path) as temporary:
        fig.savefig(temporary, dpi=dpi, format=os.path.splitext(str(path))[1][1:].lower() or "png")


def pooled(runs: list[dict | None]) -> dict | None:
    """The :func:`stats` of all the values of several runs together (mean, SD over every
    waypoint, sample or cup of every run, as the paper gives its task figures), from each
    run's mean, SD and n; a run with no values (None, e.g. a maze run whose tag was lost
    from the start) adds none, and with none at all the result is None."""
    runs = [r for r in runs if r is not None and r["n"] > 0]
    if not runs:
        return None
    n = np.array([r["n"] for r in runs], float)
    m = np.array([r["mean"] for r in runs], float)
    sd = np.array([r["sd"] for r in runs], float)
    mean = float(np.sum(n * m) / np.sum(n))
    var = float(np.sum(n * (sd**2 + (m - mean) ** 2)) / np.sum(n))
    return {"mean": mean, "sd": float(np.sqrt(var)), "max": float(max(r["max"] for r in runs)), "n": int(n.sum())}


def task_view(meshcat):
    """A :class:`vlr_drake.visualization.TaskView` on ``meshcat`` (None: no view)."""
    if meshcat is None:
        return None
    from vlr_drake.visualization import TaskView

    return TaskView(meshcat)


def followed(view, tp):
    """The plant of ``tp`` to drive: recorded by ``view`` (its true pose now, then after each
    action) when a view is given."""
    if view is None:
        return tp.plant
    view.object_pose(*tp.true_pose())
    return view.follow(tp.plant, tp.true_pose)


#: Each task's plot in its ``out`` folder (and, with Meshcat, its recording ``<task>.html``).
PLOT_FILES = {"write": "write_path.png", "maze": "maze.png", "stack": "stack.png"}


def output_files(task: str, out) -> dict:
    """The files a task run writes in its ``out`` folder besides its JSON (paths), each with
    what it is (the command line refuses a ``--json`` that one of them would overwrite)."""
    from pathlib import Path

    return {Path(out) / PLOT_FILES[task]: f"the {task} task's plot",
            Path(out) / f"{task}.html": f"the {task} task's Meshcat recording"}


def save_view(view, out: str | None, name: str, result: dict) -> None:
    """Save the view's recording as ``out/<name>.html`` and name it in ``result["recording"]``."""
    if view is not None and out is not None:
        import os

        result["recording"] = str(view.save(os.path.join(out, f"{name}.html")))
