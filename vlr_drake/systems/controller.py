"""LeafSystems of the control loop (DESIGN.md sections 7 and 8).

- :class:`JacobianController`: the controller of :mod:`vlr_drake.control` (Eq. 10-12).
  Inputs ``X_PO_goal`` (RigidTransform), ``X_PO_measured`` (RigidTransform), ``X_PO_valid``
  (1) and ``estimate`` (abstract dict, e.g. the ``estimate`` port of
  :class:`vlr_drake.systems.self_identification.SelfIdentificationSystem`); outputs
  ``tendon_command`` (N, absolute pulls [m], always inside the tendon range), ``at_goal``
  (1: 1.0 when the measured error is under tolerance on the controlled rows),
  ``pose_error`` (2: position [m], rotation [rad] of the last measurement) and ``has_model``
  (1: 1.0 when the last step found a usable model in the estimate: its weighted mean, else
  one of its ``fallbacks``, the filter's hypotheses nearest the mean; 0.0 while it holds the
  command for want of one).
- :class:`TaskTrajectorySource`: a sequence of goal poses; ``at_goal`` in, ``X_PO_goal``,
  ``waypoint_index``, ``done`` and ``ready`` out. It moves to the next goal once the controller is at
  the current one, or after ``max_periods`` action periods. With ``relative_start_sec`` the
  goals are offsets from the POM pose measured when control starts (``X_PO_measured`` and
  ``X_PO_valid`` in; ``ready`` 1 once anchored, the controller's ``enabled``), as the scenario
  builder's control section wires it.
- :class:`ControlPhase`: the selector of a PortSwitch that hands the tendons from the
  exploration policy to the controller at a given time (the scenario builder's control).
- :class:`EstimateFromTruth`: packs a plant's truth ports (``theta_true``,
  ``contact_along_link_true``) into an ``estimate`` dict (control with the true model).

Timing within one action period T: the controller commands at k T + ``offset_sec``
(default 0, the slot of the exploration policy), so the self-identification system, which
keeps updating during control at 0.9 T, takes each control action as evidence
(``dl = l_k - l_{k-1}``) and rolling contacts stay tracked. The trajectory source updates
at k T + 0.5 T, between the two.
"""

from __future__ import annotations

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.framework import BasicVector, LeafSystem

from vlr_drake import control
from vlr_drake.hand import HandModel
from vlr_drake.kinematics import checked_flag, checked_offset, checked_period

__all__ = ["JacobianController", "TaskTrajectorySource", "EstimateFromTruth", "ControlPhase"]


class JacobianController(LeafSystem):
    """Jacobian control of the POM with camera feedback (Eq. 10-12) as a LeafSystem.

    Parameters:
        hand: the controller's hand model (tendon range, geometry).
        l_initial (N,): the tendon command before control (the grasp's).
        period_sec, offset_sec: action period T and when in it the command changes.
        rows, mode, alpha, gain, damping, clip, eps: see :func:`vlr_drake.control.control_step`
            and :func:`vlr_drake.control.jacobian`.
        position_unit [m], rotation_unit [rad]: the units of Eq. 12's weighted error
            (:func:`vlr_drake.control.control_step`; the cup stacking's are mm and rad).
        limits (N, 2) [m]: a window narrower than the hand's tendon range that the commands
            never leave (a grip window, as the tasks' servo keeps); None: the range.
        window [m]: also keep the commands within +-window of the command the controller
            starts controlling from (where exploration left the tendons); None: no such window.
        tol_position [m], tol_rotation [rad]: the ``at_goal`` tolerances.
        tendon: tendon model of the controller's Gamma ("elastic" or "ideal").
        stall_periods: once the measured (weighted) error has not improved for this many
            periods on the current goal, hold the command until the goal changes (as
            :func:`vlr_drake.control.servo_to`'s ``stall_steps``).
        start_sec: before this time, and while the ``enabled`` input (when connected) is 0,
            the controller does not control: it follows the ``tendon_command_applied`` input
            (when connected) and reads ``at_goal`` 0.

    Without a valid measurement or with an empty estimate the command is held; so it is when
    neither the estimate nor any of its ``fallbacks`` is a physical grasp with a Jacobian
    (``has_model`` then reads 0).
    """

    def __init__(
        self,
        hand: HandModel,
        l_initial,
        period_sec: float,
        *,
        offset_sec: float = 0.0,
        rows: str = "full",
        mode: str = "dls",
        alpha: float = 1.0,
        gain: float = 0.7,
        damping: float = 0.01,
        clip: float = 1.0e-3,
        eps: float = control.JACOBIAN_EPS,
        tol_position: float = 0.1e-3,
        tol_rotation: float = np.deg2rad(0.3),
        tendon: str = "elastic",
        position_unit: float = control.POSITION_UNIT,
        rotation_unit: float = control.ROTATION_UNIT,
        limits=None,
        start_sec: float = 0.0,
        window: float | None = None,
        stall_periods: int = 6,
    ):
        super().__init__()
        period_sec = checked_period(period_sec, "period_sec")
        offset_sec = checked_offset(offset_sec, period_sec)
        if not (np.isfinite(start_sec) and start_sec >= 0):
            raise ValueError(f"'start_sec' must be a finite time >= 0 [s], got {start_sec}")
        self._start = float(start_sec)
        l_initial = np.asarray(l_initial, float).reshape(-1)
        if l_initial.shape != (hand.N,):
            raise ValueError(f"'l_initial' must have {hand.N} entries, got {l_initial.shape}")
        if not np.all(np.isfinite(l_initial)):
            raise ValueError(f"'l_initial' must be finite, got {l_initial.tolist()}")
        control.control_step(
            np.zeros((6, hand.N)),
            np.zeros(6),
            mode=mode,
            rows=rows,
            alpha=alpha,
            gain=gain,
            damping=damping,
            clip=clip,
            position_unit=position_unit,
            rotation_unit=rotation_unit,
        )  # validates the settings
        for name, v in (("tol_position", tol_position), ("tol_rotation", tol_rotation)):
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"'{name}' must be a finite number >= 0, got {v}")
        self._limits = None if limits is None else control.tendon_limits(hand, limits)
        if window is not None and not (np.isfinite(window) and window > 0):
            raise ValueError(f"'window' must be None or a positive finite length [m], got {window}")
        self._window = window
        if isinstance(stall_periods, bool) or not isinstance(stall_periods, int | np.integer) or stall_periods < 1:
            raise ValueError(f"'stall_periods' must be an integer >= 1, got {stall_periods!r}")
        self._stall = int(stall_periods)
        if not (np.isfinite(eps) and eps > 0):  # jacobian's error would be taken for "no usable model"
            raise ValueError(f"'eps' must be a positive finite number [m], got {eps}")
        self._hand = hand
        self._kw = dict(mode=mode, rows=rows, alpha=alpha, gain=gain, damping=damping, clip=clip,
                        position_unit=position_unit, rotation_unit=rotation_unit)
        self._eps, self._tendon = eps, tendon
        self._weights = control.row_weights(rows, alpha, position_unit, rotation_unit)  # Eq. 12's, for progress
        self._tol = (tol_position, tol_rotation)
        self._rows = rows
        self._goal = self.DeclareAbstractInputPort(
            name="X_PO_goal", model_value=AbstractValue.Make(RigidTransform())
        )
        self._X_PO = self.DeclareAbstractInputPort(
            name="X_PO_measured", model_value=AbstractValue.Make(RigidTransform())
        )
        self._valid = self.DeclareVectorInputPort(name="X_PO_valid", size=1)
        self._estimate = self.DeclareAbstractInputPort(name="estimate", model_value=AbstractValue.Make({}))
        # optional: the command the plant is given (a switch between this controller and the
        # exploration policy); connected, each step starts from it and, before start_sec, the
        # controller follows it so that control starts where exploration left the tendons
        self._applied = self.DeclareVectorInputPort(name="tendon_command_applied", size=hand.N)
        # optional: 1 when the goals are ready (e.g. the trajectory's ``ready``); connected and
        # 0, the controller does not control yet, as before start_sec
        self._enabled = self.DeclareVectorInputPort(name="enabled", size=1)
        rng = hand.tendon_range
        if np.any((l_initial < rng[:, 0] - 1e-12) | (l_initial > rng[:, 1] + 1e-12)):
            raise ValueError(f"'l_initial' {np.round(1e3 * l_initial, 3).tolist()} mm is outside the hand's tendon "
                             f"range {np.round(1e3 * rng, 3).tolist()} mm")
        # a start outside a narrower window moves into it one clipped step at a time (limit_action)
        self._command_state = self.DeclareDiscreteState(l_initial.copy())
        # the commands' limits (N x 2, row-major) and whether they are set: ``limits`` (else the
        # range) from the start, or, with ``window``, +-window about the command control starts from
        lim0 = hand.tendon_range if self._limits is None else self._limits
        self._limit_state = self.DeclareDiscreteState(np.concatenate([lim0.ravel(), [float(window is None)]]))
        self._status_state = self.DeclareDiscreteState(
            np.array([0.0, np.inf, np.inf, 0.0])
        )  # at_goal, |dt|, angle, whether the last step had a usable model
        # progress on the current goal: the goal (R row-major, t), the best weighted measured
        # error so far and the periods since it improved
        self._progress_state = self.DeclareDiscreteState(np.concatenate([np.full(12, np.nan), [np.inf, 0.0]]))
        self._command_out = self.DeclareStateOutputPort("tendon_command", self._command_state)
        self._at_goal_out = self.DeclareVectorOutputPort(
            name="at_goal",
            size=1,
            calc=self._calc_at_goal,
            prerequisites_of_calc={self.discrete_state_ticket(self._status_state)},
        )
        self._error_out = self.DeclareVectorOutputPort(
            name="pose_error",
            size=2,
            calc=self._calc_error,
            prerequisites_of_calc={self.discrete_state_ticket(self._status_state)},
        )
        self._model_out = self.DeclareVectorOutputPort(
            name="has_model",
            size=1,
            calc=self._calc_has_model,
            prerequisites_of_calc={self.discrete_state_ticket(self._status_state)},
        )
        self.DeclarePeriodicDiscreteUpdateEvent(
            period_sec=period_sec, offset_sec=offset_sec, update=self._update
        )
        self.DeclareForcedDiscreteUpdateEvent(update=self._update)

    # ports, kept as handles
    def X_PO_goal_input_port(self):
        return self._goal

    def X_PO_measured_input_port(self):
        return self._X_PO

    def X_PO_valid_input_port(self):
        return self._valid

    def estimate_input_port(self):
        return self._estimate

    def tendon_command_applied_input_port(self):
        return self._applied

    def enabled_input_port(self):
        return self._enabled

    def tendon_command_output_port(self):
        return self._command_out

    def at_goal_output_port(self):
        return self._at_goal_out

    def pose_error_output_port(self):
        return self._error_out

    def has_model_output_port(self):
        return self._model_out

    def _update(self, context, discrete_state):
        l_now = np.array(context.get_discrete_state(self._command_state).get_value())
        if self._applied.HasValue(context):
            l_now = np.asarray(self._applied.Eval(context), float).copy()
            if not np.all(np.isfinite(l_now)):
                raise ValueError(f"controller: input 'tendon_command_applied' is not finite: {l_now.tolist()}")
        waiting = self._enabled.HasValue(context) and not checked_flag(self._enabled.Eval(context)[0],
                                                                       "controller: input 'enabled'")
        if waiting or context.get_time() < self._start - 1e-9:  # not controlling yet: follow the applied command
            discrete_state.get_mutable_vector(self._command_state).SetFromVector(l_now)
            discrete_state.get_mutable_vector(self._status_state).SetAtIndex(0, 0.0)
            return
        packed = np.array(context.get_discrete_state(self._limit_state).get_value())
        if packed[-1] < 0.5:  # the first step in control: the window about where it starts
            lim0 = packed[:-1].reshape(self._hand.N, 2)
            both = np.column_stack([np.maximum(l_now - self._window, lim0[:, 0]),
                                    np.minimum(l_now + self._window, lim0[:, 1])])
            # a tendon that starts further outside the limits than the window: the limits, which
            # it moves into one clipped step at a time (the empty intersection had been refused
            # as 'limits' never given: a review)
            both = np.where((both[:, 0] > both[:, 1])[:, None], lim0, both)
            packed = np.concatenate([control.tendon_limits(self._hand, both).ravel(), [1.0]])
            discrete_state.get_mutable_vector(self._limit_state).SetFromVector(packed)
        lim = packed[:-1].reshape(self._hand.N, 2)
        valid = checked_flag(self._valid.Eval(context)[0], "controller: input 'X_PO_valid'")
        est = self._estimate.Eval(context)
        if not valid or not est:  # hold the command; the goal is not known to be reached
            discrete_state.get_mutable_vector(self._command_state).SetFromVector(l_now)
            status = discrete_state.get_mutable_vector(self._status_state)
            status.SetAtIndex(0, 0.0)  # (at_goal held at 1 had let a trajectory skip its goals)
            return
        X = self._X_PO.Eval(context)
        G = self._goal.Eval(context)
        R, t = X.rotation().matrix(), X.translation()
        for name, pose in (("X_PO_goal", G), ("X_PO_measured", X)):
            if not np.all(np.isfinite(pose.GetAsMatrix34())):  # a lost tag is X_PO_valid 0, not NaN
                raise ValueError(f"controller: input '{name}' is not finite: {pose.GetAsMatrix34().tolist()}")
        e = control.pose_error6(G.rotation().matrix(), G.translation(), R, t)
        ep, er = float(np.linalg.norm(e[:3])), float(np.linalg.norm(e[3:]))
        at_goal = (self._rows == "orientation" or ep <= self._tol[0]) and (
            self._rows == "position" or er <= self._tol[1]
        )
        status = discrete_state.get_mutable_vector(self._status_state)
        status.SetFromVector([float(at_goal), ep, er, status.GetAtIndex(3)])
        discrete_state.get_mutable_vector(self._command_state).SetFromVector(l_now)  # held unless a step follows
        if at_goal:
            return
        # stalled: the weighted error has not improved for stall_periods measured periods on
        # this goal (it lies where the hand cannot move the object, or friction holds it there,
        # as the physics plant's palm-normal direction under a common-mode release): hold,
        # rather than wind the tendons on, until the goal changes
        progress = discrete_state.get_mutable_vector(self._progress_state)
        key = G.GetAsMatrix34().ravel()
        ew = float(np.linalg.norm(self._weights * e))
        p = np.array(progress.get_value())
        if not np.array_equal(p[:12], key) or ew < p[12] - 1e-9:
            progress.SetFromVector(np.concatenate([key, [ew, 0.0]]))
        else:
            progress.SetAtIndex(13, p[13] + 1.0)
            if p[13] + 1.0 >= self._stall:
                return
        _check_estimate(self._hand, est)  # a malformed one is a wiring mistake, not "no model here"
        for fallback in est.get("fallbacks", []):
            _check_estimate(self._hand, fallback)
        # the mean, else the first fallback hypothesis that is a physical grasp with a Jacobian
        usable = control.usable_model(self._hand, est, R, t, tendon=self._tendon, eps=self._eps)
        status.SetAtIndex(3, float(usable is not None))
        if usable is None:
            return  # no usable model here: hold, and say so (has_model 0)
        dl = control.control_step(usable[1], e, **self._kw)
        dl = control.limit_action(self._hand, l_now, dl, lim)
        discrete_state.get_mutable_vector(self._command_state).SetFromVector(l_now + dl)

    def _calc_at_goal(self, context, output: BasicVector):
        output.SetFromVector([context.get_discrete_state(self._status_state).GetAtIndex(0)])

    def _calc_error(self, context, output: BasicVector):
        output.SetFromVector(np.array(context.get_discrete_state(self._status_state).get_value())[1:3])

    def _calc_has_model(self, context, output: BasicVector):
        output.SetFromVector([context.get_discrete_state(self._status_state).GetAtIndex(3)])


def _check_estimate(hand: HandModel, est: dict) -> None:
    """The ``estimate`` input's keys and shapes (its values may be anything numeric)."""
    N, K = hand.N, hand.K
    for key, shape in (("theta", (N, K)), ("a", (N,)), ("stiffness", (N, K)), ("link_lengths", (N, K - 1))):
        if key not in est:
            if key in ("theta", "a"):
                raise ValueError(f"controller: input 'estimate' is missing '{key}' (keys {sorted(est)})")
        elif est[key] is not None and np.shape(est[key]) != shape:
            raise ValueError(f"controller: input estimate['{key}'] must have shape {shape}, got {np.shape(est[key])}")


class TaskTrajectorySource(LeafSystem):
    """Goal poses of a task, one after another (``X_PO_goal`` out).

    Moves to the next goal at k T + ``offset_sec`` when ``at_goal`` (input) is 1, or after
    ``max_periods`` periods on one goal; ``done`` becomes 1 after the last goal was reached
    (or timed out); the last goal is held. With ``relative_start_sec`` each goal (R_rel,
    t_rel) is taken relative to the first valid measured pose (R0, t0) at or after that time:
    the goal is (R_rel R0, t0 + t_rel), and the goals' count starts once it is anchored.
    (R0, t0) is the mean of the first ``anchor_frames`` such measurements, one per update
    (the hand held still meanwhile): the camera's noise along a direction the hand cannot
    move the object in would otherwise stay in every goal.

    ``offset_sec`` (default 0.5 T) must differ from the controller's (JacobianController's
    ``offset_sec``, 0 by default; the scenario builder takes 0.05 T): events at the same
    instant read each other's state from before it, so the source would read the at-goal
    flag of the goal it had just left and skip every other goal (a review; measured with
    both at 0: goals 0, 2 and 4 of six reached, 1, 3 and 5 held one period each).
    """

    def __init__(
        self, goals: list, period_sec: float, *, offset_sec: float | None = None, max_periods: int = 20,
        relative_start_sec: float | None = None, anchor_frames: int = 1,
    ):
        super().__init__()
        if not goals:
            raise ValueError("'goals' must hold at least one pose")
        self._goals = [_goal_pose(i, g) for i, g in enumerate(goals)]
        if relative_start_sec is not None and not (np.isfinite(relative_start_sec) and relative_start_sec >= 0):
            raise ValueError(f"'relative_start_sec' must be None or a finite time >= 0 [s], got {relative_start_sec}")
        if isinstance(anchor_frames, bool) or not isinstance(anchor_frames, int | np.integer) or anchor_frames < 1:
            raise ValueError(f"'anchor_frames' must be an integer >= 1, got {anchor_frames!r}")
        self._relative, self._frames = relative_start_sec, int(anchor_frames)
        if (isinstance(max_periods, bool) or not np.isfinite(max_periods) or max_periods != int(max_periods)
                or max_periods < 1):
            raise ValueError(f"'max_periods' must be an integer >= 1, got {max_periods}")
        self._max = int(max_periods)
        self._at_goal = self.DeclareVectorInputPort(name="at_goal", size=1)
        self._state = self.DeclareDiscreteState(np.array([0.0, 0.0, 0.0]))  # index, periods on it, done
        # relative goals: the sums of the anchor frames' R (row-major) and t, and their count
        self._anchor = self.DeclareDiscreteState(np.zeros(13))
        if relative_start_sec is not None:
            self._X_PO = self.DeclareAbstractInputPort(
                name="X_PO_measured", model_value=AbstractValue.Make(RigidTransform()))
            self._valid = self.DeclareVectorInputPort(name="X_PO_valid", size=1)
        ticket = {self.discrete_state_ticket(self._state)}
        self._goal_out = self.DeclareAbstractOutputPort(
            name="X_PO_goal",
            alloc=lambda: AbstractValue.Make(RigidTransform()),
            calc=self._calc_goal,
            prerequisites_of_calc={self.discrete_state_ticket(self._state), self.discrete_state_ticket(self._anchor)},
        )
        self._index_out = self.DeclareVectorOutputPort(
            name="waypoint_index", size=1, calc=self._calc_index, prerequisites_of_calc=ticket
        )
        self._done_out = self.DeclareVectorOutputPort(
            name="done", size=1, calc=self._calc_done, prerequisites_of_calc=ticket
        )
        self._ready_out = self.DeclareVectorOutputPort(
            name="ready", size=1, calc=self._calc_ready,
            prerequisites_of_calc={self.discrete_state_ticket(self._anchor)})
        period_sec = checked_period(period_sec, "period_sec")
        offset = 0.5 * period_sec if offset_sec is None else checked_offset(offset_sec, period_sec, optional=True)
        self.DeclarePeriodicDiscreteUpdateEvent(period_sec=period_sec, offset_sec=offset, update=self._update)
        self.DeclareForcedDiscreteUpdateEvent(update=self._update)

    def at_goal_input_port(self):
        return self._at_goal

    def X_PO_measured_input_port(self):
        """Relative goals only: the measured POM pose, read to anchor the goals."""
        return self.GetInputPort("X_PO_measured")  # absolute goals: a RuntimeError naming the port

    def X_PO_valid_input_port(self):
        return self.GetInputPort("X_PO_valid")

    def X_PO_goal_output_port(self):
        return self._goal_out

    def waypoint_index_output_port(self):
        return self._index_out

    def done_output_port(self):
        return self._done_out

    def ready_output_port(self):
        """1 once the goals are anchored (always, for absolute goals): a controller's ``enabled``."""
        return self._ready_out

    def _update(self, context, discrete_state):
        if not self.anchored(context):
            # not anchored yet: the valid measurements at or after relative_start_sec, one per update
            if context.get_time() >= self._relative - 1e-9 and checked_flag(
                    self._valid.Eval(context)[0], "goal anchor: input 'X_PO_valid'"):
                X = self._X_PO.Eval(context)
                sums = np.asarray(context.get_discrete_state(self._anchor).get_value())
                discrete_state.get_mutable_vector(self._anchor).SetFromVector(
                    sums + np.concatenate([X.rotation().matrix().ravel(), X.translation(), [1.0]]))
            return
        i, n, done = context.get_discrete_state(self._state).get_value()
        i, n = int(i), int(n) + 1
        if done < 0.5 and (self._at_goal.Eval(context)[0] > 0.5 or n >= self._max):
            if i + 1 < len(self._goals):
                i, n = i + 1, 0
            else:
                done = 1.0
        discrete_state.get_mutable_vector(self._state).SetFromVector([i, n, done])

    @property
    def num_goals(self) -> int:
        return len(self._goals)

    def goal(self, context, i: int) -> RigidTransform:
        """Goal ``i`` in the palm frame: as given, or, with relative goals, (R_rel R0, t0 +
        t_rel) about the anchor (before anchoring, about the identity)."""
        goal = self._goals[i]
        if self._relative is None:
            return goal
        from pydrake.math import RotationMatrix

        sums = np.asarray(context.get_discrete_state(self._anchor).get_value())
        n = max(sums[12], 1.0)
        U, _, Vt = np.linalg.svd(sums[:9].reshape(3, 3) / n if sums[12] > 0 else np.eye(3))
        R0 = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt  # the frames' mean rotation
        return RigidTransform(RotationMatrix(goal.rotation().matrix() @ R0), sums[9:12] / n + goal.translation())

    def _calc_goal(self, context, output):
        output.set_value(self.goal(context, int(context.get_discrete_state(self._state).GetAtIndex(0))))

    def anchored(self, context) -> bool:
        """Whether relative goals have their anchor (always True for absolute goals)."""
        return self._relative is None or context.get_discrete_state(self._anchor).GetAtIndex(12) >= self._frames

    def _calc_index(self, context, output: BasicVector):
        output.SetFromVector([context.get_discrete_state(self._state).GetAtIndex(0)])

    def _calc_ready(self, context, output: BasicVector):
        output.SetFromVector([float(self.anchored(context))])

    def _calc_done(self, context, output: BasicVector):
        output.SetFromVector([context.get_discrete_state(self._state).GetAtIndex(2)])


class ControlPhase(LeafSystem):
    """The selector of a PortSwitch: its ``exploration`` input before ``start_sec``, its
    ``control`` input from then on (an abstract InputPortIndex output, a function of time)."""

    def __init__(self, start_sec: float, exploration, control):
        super().__init__()
        if not (np.isfinite(start_sec) and start_sec >= 0):
            raise ValueError(f"'start_sec' must be a finite time >= 0 [s], got {start_sec}")
        self._start, self._ports = float(start_sec), (exploration, control)
        self.DeclareAbstractOutputPort("selector", lambda: AbstractValue.Make(exploration), self._calc)

    def _calc(self, context, output) -> None:
        output.set_value(self._ports[int(context.get_time() >= self._start - 1e-9)])


def _goal_pose(i: int, g) -> RigidTransform:
    """Goal ``i`` as a RigidTransform, from one or from (R (3, 3), t (3,)); a ValueError
    names it unless it is finite with R a rotation to 1e-6 (pydrake does not check)."""
    from pydrake.math import RotationMatrix

    if isinstance(g, RigidTransform):
        R, t = g.rotation().matrix(), g.translation()
    else:
        try:
            R, t = g
        except (TypeError, ValueError):
            raise ValueError(f"'goals': goal {i} must be a RigidTransform or (R (3, 3), t (3,)), got {g!r}") from None
        R, t = np.asarray(R, float), np.asarray(t, float)
        if R.shape != (3, 3) or t.shape != (3,):
            raise ValueError(f"'goals': goal {i} must be (R (3, 3), t (3,)), got shapes {R.shape} and {t.shape}")
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        raise ValueError(f"'goals': goal {i} is not finite: R {R.tolist()}, t {t.tolist()}")
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0:
        raise ValueError(f"'goals': goal {i}'s R is not a rotation matrix: {np.round(R, 6).tolist()}")
    return g if isinstance(g, RigidTransform) else RigidTransform(RotationMatrix(R), t)


class EstimateFromTruth(LeafSystem):
    """``theta_true`` (N*K) and ``contact_along_link_true`` (N) in, an ``estimate`` dict out
    (with the hand's stiffness and link lengths, or the given true ones)."""

    def __init__(self, hand: HandModel, stiffness=None, link_lengths=None):
        super().__init__()
        self._hand = hand
        self._k = (
            hand.stiffness.copy()
            if stiffness is None
            else np.asarray(stiffness, float).reshape(hand.N, hand.K)
        )
        self._L = (
            hand.link_lengths.copy()
            if link_lengths is None
            else np.asarray(link_lengths, float).reshape(hand.N, hand.K - 1)
        )
        self._theta = self.DeclareVectorInputPort(name="theta_true", size=hand.N * hand.K)
        self._a = self.DeclareVectorInputPort(name="contact_along_link_true", size=hand.N)
        self._out = self.DeclareAbstractOutputPort(
            name="estimate", alloc=lambda: AbstractValue.Make({}), calc=self._calc
        )

    def theta_true_input_port(self):
        return self._theta

    def contact_along_link_true_input_port(self):
        return self._a

    def estimate_output_port(self):
        return self._out

    def _calc(self, context, output):
        h = self._hand
        output.set_value(
            {
                "theta": np.array(self._theta.Eval(context)).reshape(h.N, h.K),
                "a": np.array(self._a.Eval(context)),
                "stiffness": self._k,
                "link_lengths": self._L,
            }
        )
