"""LeafSystems of the self-identification loop (DESIGN.md section 8).

- :class:`SelfIdentificationSystem` wraps :class:`vlr_drake.filter.SelfIdentificationFilter`:
  ``tendon_command``, ``X_PO_measured`` and ``X_PO_valid`` in; ``estimate`` (abstract dict:
  the filter's estimate, the weighted mean, with ``fallbacks``, the :data:`FALLBACKS` live
  hypotheses nearest it, for a controller; ``measured`` and ``lost_measurements``, whether the
  last update weighed a measurement and how many did not; ``reinitialised`` and
  ``reinitialisations``, whether it drew the cloud again, where the estimate jumps, and how
  often), ``theta_estimate``, ``interval_half_width``,
  ``converged``, ``started`` and ``particles`` out (the estimate's arrays and the particles
  read-only: they are the filter's own).
- :class:`ExplorationPolicy`: random exploratory tendon commands (``tendon_command`` out;
  ``enabled`` in, optional: it holds the grasp's command until the filter has started).
- :class:`ModelPlantSystem`: the model plant (the VLR model with hidden truth) with the
  physics plant's truth ports: ``tendon_command`` in; ``X_PO_true``, ``theta_true``,
  ``contacts_true``, ``contact_along_link_true``, ``tendon_position_measured`` out.

Timing within one action period T (all periodic events share T, offsets order them):
the policy commands at k T, the model plant applies the command at k T + 0.25 T (the
physics plant instead ramps and settles during the period), and the filter reads the
command and the measurement at k T + ``filter_offset`` (default 0.9 T), when the plant has
settled. The filter stores the command of its previous update, so its action is
``dl = l_k - l_{k-1}``. It initialises itself at its first update with a valid measurement;
the policy, its ``enabled`` input wired to the filter's ``started``, holds the grasp until
then, so that the prior, drawn around the grasp, is drawn where the hand still is.
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.framework import BasicVector, LeafSystem

from vlr_drake import filter as pf
from vlr_drake.control import FALLBACKS, tendon_limits
from vlr_drake.hand import HandModel
from vlr_drake.identify import Exploration
from vlr_drake.kinematics import checked_flag, checked_offset, checked_period, checked_seed
from vlr_drake.model_plant import ModelPlant
from vlr_drake.trace import IdentificationTrace, TraceRecorder

__all__ = ["SelfIdentificationSystem", "ExplorationPolicy", "ModelPlantSystem"]


def _timing(period_sec, offset_sec=None) -> tuple[float, float | None]:
    """A periodic event's ``period_sec`` (finite, > 0) and ``offset_sec`` (None, or in
    [0, period_sec): the offsets order the events within one period) [s], or a ValueError
    that names the bad one."""
    period_sec = checked_period(period_sec, "period_sec")
    return period_sec, None if offset_sec is None else checked_offset(offset_sec, period_sec, optional=True)


def _read_only(x):
    """A read-only view of an array (other values as they are): an output that hands out the
    filter's own arrays must not let a consumer change them."""
    if isinstance(x, np.ndarray):
        v = x.view()
        v.flags.writeable = False
        return v
    return x


class _FilterBox:
    """Abstract-state payload: the filter object (which tracks the tendon command too) and
    the trace of what it was given."""

    def __init__(self, flt: pf.SelfIdentificationFilter | None = None, recorder: TraceRecorder | None = None):
        self.filter = flt
        self.recorder = recorder

    def __deepcopy__(self, memo):
        """Drake clones the abstract state, twice at every update: share nothing mutable.
        The records that only grow (the filter's history and estimates, the recorder's steps
        and truths), whose entries are never changed once appended, are copied as new lists
        of the same entries: deep-copied, they grew to 6.5 ms a copy after 240 iterations,
        against 0.6 ms for all the rest of a 20,000-particle filter."""
        import copy

        records = [] if self.filter is None else [self.filter.history, self.filter.estimates]
        records += [] if self.recorder is None else self.recorder.records()
        for r in records:
            memo[id(r)] = list(r)
        return _FilterBox(copy.deepcopy(self.filter, memo), copy.deepcopy(self.recorder, memo))


class SelfIdentificationSystem(LeafSystem):
    """The particle filter of Algorithm 1 as a LeafSystem.

    Parameters:
        hand: the filter's hand model.
        config, prior: filter and prior configuration.
        theta_center (N, K), a_center (N,): the nominal grasp the prior is drawn around.
        period_sec: action period T; offset_sec: when in the period the filter updates.
        seed: seed of the filter's random draws.
    """

    def __init__(self, hand: HandModel, config: pf.FilterConfig, prior: pf.PriorConfig, theta_center, a_center,
                 period_sec: float, offset_sec: float | None = None, seed: int = 0):
        super().__init__()
        period_sec, offset_sec = _timing(period_sec, offset_sec)
        self._hand, self._config, self._prior, self._seed = hand, config.validate(), prior, checked_seed(seed)
        pf.warn_if_few_particles(self._config)  # now, not at the first measurement mid-run
        with warnings.catch_warnings():  # the filter's checks of config, prior and hand together, now too
            warnings.simplefilter("ignore", pf.FewParticlesWarning)  # (a setting that does not fit the hand
            pf.SelfIdentificationFilter(hand, self._config, prior, np.random.default_rng(0))  # had stopped the run)
        self._theta_center = pf._shaped("theta_center", theta_center, (hand.N, hand.K))
        self._a_center = pf.contact_center(hand, a_center)  # on the links, now, not at the first measurement
        n = hand.N * hand.K
        self._command = self.DeclareVectorInputPort(name="tendon_command", size=hand.N)
        self._X_PO = self.DeclareAbstractInputPort(name="X_PO_measured", model_value=AbstractValue.Make(RigidTransform()))
        self._valid = self.DeclareVectorInputPort(name="X_PO_valid", size=1)
        self._box = self.DeclareAbstractState(model_value=AbstractValue.Make(_FilterBox()))
        self._estimate = self.DeclareAbstractOutputPort(
            name="estimate", alloc=lambda: AbstractValue.Make({}), calc=self._calc_estimate,
            prerequisites_of_calc={self.abstract_state_ticket(self._box)})
        self._theta_out = self.DeclareVectorOutputPort(
            name="theta_estimate", size=n, calc=self._calc_theta,
            prerequisites_of_calc={self.abstract_state_ticket(self._box)})
        self._width_out = self.DeclareVectorOutputPort(
            name="interval_half_width", size=n, calc=self._calc_width,
            prerequisites_of_calc={self.abstract_state_ticket(self._box)})
        self._converged_out = self.DeclareVectorOutputPort(
            name="converged", size=1, calc=self._calc_converged,
            prerequisites_of_calc={self.abstract_state_ticket(self._box)})
        self._started_out = self.DeclareVectorOutputPort(  # 1 once the filter has its first measurement
            name="started", size=1, calc=self._calc_started,
            prerequisites_of_calc={self.abstract_state_ticket(self._box)})
        self._particles_out = self.DeclareAbstractOutputPort(
            name="particles", alloc=lambda: AbstractValue.Make(object()), calc=self._calc_particles,
            prerequisites_of_calc={self.abstract_state_ticket(self._box)})
        offset = pf.FILTER_PHASE * period_sec if offset_sec is None else offset_sec
        self.DeclarePeriodicUnrestrictedUpdateEvent(period_sec=period_sec, offset_sec=offset, update=self._update)
        self.DeclareForcedUnrestrictedUpdateEvent(update=self._update)

    # ports, kept as handles
    def tendon_command_input_port(self):
        return self._command

    def X_PO_measured_input_port(self):
        return self._X_PO

    def X_PO_valid_input_port(self):
        return self._valid

    def config(self) -> pf.FilterConfig:
        """The filter configuration this system runs."""
        return self._config

    def filter(self, context) -> pf.SelfIdentificationFilter | None:
        """The filter object held in ``context`` (None before the first valid measurement)."""
        return context.get_abstract_state(self._box).get_value().filter

    def _update(self, context, state):
        box = state.get_mutable_abstract_state(self._box).get_mutable_value()
        l_now = np.array(self._command.Eval(context), float)
        if not np.all(np.isfinite(l_now)):
            raise ValueError(f"self-identification: input 'tendon_command' is not finite: {l_now.tolist()}")
        X = self._X_PO.Eval(context)
        valid = checked_flag(self._valid.Eval(context)[0], "self-identification: input 'X_PO_valid'")
        if box.filter is None:
            if not valid:
                return  # wait for the first valid measurement
            with warnings.catch_warnings():  # said when the system was made
                warnings.simplefilter("ignore", pf.FewParticlesWarning)
                flt = pf.SelfIdentificationFilter(self._hand, self._config, self._prior,
                                                  np.random.default_rng(self._seed))
            flt.initialise(self._theta_center, self._a_center, X.rotation().matrix(), X.translation(),
                           tendon_command=l_now)
            box.filter = flt
            box.recorder = TraceRecorder(self._hand.spec, self._config, self._prior, self._seed,
                                         meta={"plant": "diagram", "stops_at_convergence": False})  # it runs on, converged or not
            box.recorder.start(self._theta_center, self._a_center, X.rotation().matrix(), X.translation(), l_now)
            return
        dl = l_now - box.filter.tendon_command
        box.filter.step(dl, X.rotation().matrix(), X.translation(), valid, tendon_command=l_now)
        box.recorder.step(dl, X.rotation().matrix(), X.translation(), valid, l_now)

    def trace(self, context) -> IdentificationTrace | None:
        """What the filter in ``context`` was given so far (no truth: the diagram's plant may
        be hardware), for :func:`vlr_drake.trace.replay`; None before it started."""
        recorder = context.get_abstract_state(self._box).get_value().recorder
        return None if recorder is None else recorder.trace()

    def _calc_estimate(self, context, output):
        f = self.filter(context)
        if f is None:
            output.set_value({})
            return
        # the weighted mean, and the live hypotheses nearest it for a controller whose model
        # the mean cannot be (control.filter_model_fn; the JacobianController tries them in
        # turn); whether the last update weighed a measurement, and how many were lost; and
        # whether it drew the cloud again (the estimate may have jumped), and how often
        lost = sum(not r.measured for r in f.history)
        output.set_value({**{k: _read_only(v) for k, v in f.estimates[-1].items()},
                          "fallbacks": [{k: _read_only(v) for k, v in h.items()} for h in f.nearest_hypotheses(FALLBACKS)],
                          "measured": bool(f.history[-1].measured) if f.history else True,
                          "lost_measurements": lost,
                          "reinitialised": bool(f.history[-1].reinitialised) if f.history else False,
                          "reinitialisations": int(f.reinitialisations)})

    def _calc_theta(self, context, output: BasicVector):
        f = self.filter(context)
        output.SetFromVector(self._theta_center.ravel() if f is None else f.estimates[-1]["theta"].ravel())

    def _calc_width(self, context, output: BasicVector):
        f = self.filter(context)
        if f is None:
            output.SetFromVector(np.full(self._hand.N * self._hand.K, np.inf))
        else:
            output.SetFromVector(f.estimates[-1]["theta_half_width"])

    def _calc_converged(self, context, output: BasicVector):
        f = self.filter(context)
        output.SetFromVector([1.0 if (f is not None and f.converged) else 0.0])

    def _calc_started(self, context, output: BasicVector):
        output.SetFromVector([0.0 if self.filter(context) is None else 1.0])

    def _calc_particles(self, context, output):
        f = self.filter(context)
        if f is None:
            output.set_value(None)
            return
        p = f.particles
        output.set_value(dataclasses.replace(p, **{k.name: _read_only(getattr(p, k.name))
                                                   for k in dataclasses.fields(p)}))


class ExplorationPolicy(LeafSystem):
    """Random exploratory tendon commands: every ``period_sec`` the command moves by a
    uniform draw in +-``span`` per tendon, reflected inside +-``window`` around the initial
    (grasp) commands and inside the tendon range, plus, with ``squeeze`` > 0, a common-mode
    pull of +-``squeeze`` inside +-``squeeze_window`` (see :class:`vlr_drake.identify.Exploration`).
    ``limits`` (N, 2) [m] narrow the tendon range it stays in (a hardware hand's motor limits,
    which the interface would clip the commands to: the policy had walked past them while the
    tendons sat at the limit).
    While its ``enabled`` input, where connected, reads 0 (the filter's ``started``), it holds
    the command and draws nothing: the first action comes once the filter has started.

    Its actions are random, the paper's choice, on every plant: the informative choice of
    ``vlr-drake identify`` on the model plant (:class:`vlr_drake.identify.InformativeExploration`)
    scores proposals against the filter's hypotheses and lives in the identification loop."""

    def __init__(self, hand: HandModel, l_grasp, period_sec: float, span: float = 1.5e-3, window: float = 4e-3,
                 seed: int = 0, squeeze: float = 0.0, squeeze_window: float = 0.0, limits=None):
        super().__init__()
        period_sec, _ = _timing(period_sec)
        self._l0 = np.asarray(l_grasp, float)
        self._seed = checked_seed(seed)
        self._state = self.DeclareDiscreteState(self._l0)
        self._draws = self.DeclareDiscreteState(1)
        self._out = self.DeclareStateOutputPort("tendon_command", self._state)
        self._enabled = self.DeclareVectorInputPort(name="enabled", size=1)
        self.DeclarePeriodicDiscreteUpdateEvent(period_sec=period_sec, offset_sec=period_sec, update=self._update)
        self._span, self._window, self._range = span, window, tendon_limits(hand, limits)
        self._squeeze = (squeeze, squeeze_window)
        Exploration(self._l0, self._range, span, window, None, squeeze, squeeze_window)  # checks the settings
        out = (self._l0 < self._range[:, 0]) | (self._l0 > self._range[:, 1])
        if np.any(out):  # its window would collapse onto the limit: one jump there, then no exploration
            raise ValueError(f"exploration: 'l_grasp' {np.round(1e3 * self._l0, 3).tolist()} mm is outside the tendon "
                             f"limits {np.round(1e3 * self._range, 3).tolist()} mm (tendon(s) {np.flatnonzero(out).tolist()})")

    def _update(self, context, discrete_state):
        if self._enabled.HasValue(context) and not checked_flag(self._enabled.Eval(context)[0], "exploration: input 'enabled'"):
            return  # held: the filter has not started
        n = int(context.get_discrete_state(self._draws).GetAtIndex(0))
        l_now = np.array(context.get_discrete_state(self._state).get_value())
        ex = Exploration(self._l0, self._range, self._span, self._window, np.random.default_rng((self._seed, n)),
                         *self._squeeze)
        ex.l = l_now
        discrete_state.get_mutable_vector(self._state).SetFromVector(l_now + ex.next_action())
        discrete_state.get_mutable_vector(self._draws).SetAtIndex(0, n + 1)


class ModelPlantSystem(LeafSystem):
    """The model plant as a LeafSystem with the physics plant's truth ports."""

    def __init__(self, plant: ModelPlant, period_sec: float, offset_sec: float | None = None):
        super().__init__()
        import copy

        period_sec, offset_sec = _timing(period_sec, offset_sec)
        self._template = copy.deepcopy(plant)
        h = plant.hand
        self._N, self._K = h.N, h.K
        self._command = self.DeclareVectorInputPort(name="tendon_command", size=h.N)
        self._plant = self.DeclareAbstractState(model_value=AbstractValue.Make(copy.deepcopy(plant)))
        # the command it last moved to: a contact drift restates the plant's own command
        # (ModelPlant._drift_contacts), which is no new action (read against it, a held
        # command had moved the plant again every period: a review)
        self._given = self.DeclareDiscreteState(plant.state.tendon_command.copy())
        ticket = {self.abstract_state_ticket(self._plant)}
        self.DeclareAbstractOutputPort(name="X_PO_true", alloc=lambda: AbstractValue.Make(RigidTransform()),
                                       calc=self._calc_pose, prerequisites_of_calc=ticket)
        self.DeclareVectorOutputPort(name="theta_true", size=h.N * h.K, calc=self._calc_theta,
                                     prerequisites_of_calc=ticket)
        self.DeclareVectorOutputPort(name="contacts_true", size=3 * h.N, calc=self._calc_contacts,
                                     prerequisites_of_calc=ticket)
        self.DeclareVectorOutputPort(name="contact_along_link_true", size=h.N, calc=self._calc_a,
                                     prerequisites_of_calc=ticket)
        self.DeclareVectorOutputPort(name="tendon_position_measured", size=h.N, calc=self._calc_l,
                                     prerequisites_of_calc=ticket)
        offset = 0.25 * period_sec if offset_sec is None else offset_sec
        self.DeclarePeriodicUnrestrictedUpdateEvent(period_sec=period_sec, offset_sec=offset, update=self._update)

    def grasp_command(self) -> np.ndarray:
        return self._template.state.tendon_command.copy()

    def _update(self, context, state):
        plant = state.get_mutable_abstract_state(self._plant).get_mutable_value()
        l = np.array(self._command.Eval(context), float)
        if not np.all(np.isfinite(l)):  # |NaN| > 0 is False: it would be skipped silently
            raise ValueError(f"model plant: input 'tendon_command' is not finite: {l.tolist()}")
        given = state.get_mutable_discrete_state(self._given)
        dl = l - given.get_value()
        # a refused action (no nearby equilibrium) leaves the plant where it was: its
        # measured tendon positions say so to the filter, refused() counts it, and the next
        # update tries the whole difference again
        if np.any(np.abs(dl) > 0) and plant.apply_action(dl):
            given.SetFromVector(l)

    def refused(self, context) -> int:
        """Actions the model plant refused so far in ``context`` (a root context: a
        diagram's, or its own where it runs alone): where it found no nearby equilibrium for
        the command (an identification run's ``actions_refused``)."""
        return int(self._p(self.GetMyContextFromRoot(context)).failures)

    def _p(self, context) -> ModelPlant:
        return context.get_abstract_state(self._plant).get_value()

    def _calc_pose(self, context, output):
        s = self._p(context).state
        from pydrake.math import RotationMatrix

        output.set_value(RigidTransform(RotationMatrix(s.R_PO), s.t_PO))

    def _calc_theta(self, context, output):
        output.SetFromVector(self._p(context).state.theta.ravel())

    def _calc_contacts(self, context, output):
        output.SetFromVector(self._p(context).contacts().ravel())

    def _calc_a(self, context, output):
        output.SetFromVector(self._p(context).state.a)

    def _calc_l(self, context, output):
        output.SetFromVector(self._p(context).state.tendon_command)
