"""The hand's tendons as a LeafSystem: tendon commands and joint state in, joint torques out.

Drake 1.51's Python API has no commanded tendon, so the tendons are a system that feeds the
plant's ``applied_generalized_force`` input (DESIGN.md section 8). Tendon i (finger i) has
series stiffness kappa_i (tendon plus motor position loop) and damping c_i. With the
applied pull l_i (0 = taut at a straight finger) and the finger's joint angles theta_i
(moment arms r_i, the row R_i of the matrix R of Eq. 7):

    s_i = l_i - R_i theta_i                                   (stretch)
    T_i = max(0, kappa_i s_i + c_i ds_i/dt)  if s_i > 0, else 0   (a tendon only pulls)
    tau = R^T T                                               (generalized joint torque)

Commands are clamped to each tendon's ``tendon_range`` (never past the limits). A new
command is not applied at once: the applied pull moves linearly from where it was to the
new command over ``ramp_time`` (discrete state, updated every ``update_period``), so one
action of the paper is a ramp of the motors, as on the hardware.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from pydrake.systems.framework import BasicVector, Context, DiscreteValues, LeafSystem

from vlr_drake.hand import HandModel

__all__ = ["TendonForces", "tendon_tension"]


def tendon_tension(
    hand: HandModel,
    l: np.ndarray,
    theta: np.ndarray,
    theta_dot: np.ndarray | None = None,
    l_dot: np.ndarray | None = None,
    damping: np.ndarray | None = None,
) -> np.ndarray:
    """Tendon tensions T (N,) for pulls ``l`` (N,) and angles ``theta`` (N*K, finger-major):
    T_i = max(0, kappa_i s_i + c_i ds_i/dt) where the stretch s_i > 0, else 0."""
    R = hand.R
    s = np.asarray(l, float) - R @ np.asarray(theta, float)
    T = hand.kappa * s
    if damping is not None:
        sdot = -(R @ (np.zeros(R.shape[1]) if theta_dot is None else np.asarray(theta_dot, float)))
        if l_dot is not None:
            sdot = sdot + l_dot
        T = T + np.asarray(damping, float) * sdot
    return np.where(s > 0, np.maximum(T, 0.0), 0.0)


class TendonForces(LeafSystem):
    """Tendons of an N-finger, K-joint hand acting on a MultibodyPlant.

    Input ports:
        tendon_command (N): commanded absolute pulls l [m] (clamped to ``tendon_range``).
        state (nq + nv): the plant's state [q; v].
    Output ports:
        generalized_force (nv): tau = R^T T on the finger joints' velocities, 0 elsewhere.
        tension (N): T [N], never negative.
        tendon_position_measured (N): the applied (ramped) pulls l [m], as a motor reports.
    Discrete state: applied pull (N), ramp start (N), ramp target (N), ramp start time (1).
    """

    def __init__(
        self,
        hand: HandModel,
        position_indices: Sequence[int],
        velocity_indices: Sequence[int],
        num_positions: int,
        num_velocities: int,
        ramp_time: float = 0.2,
        update_period: float = 0.001,
        damping: Sequence[float] | None = None,
    ):
        super().__init__()
        self._hand = hand
        N, nk = hand.N, hand.num_angles
        self._qi = np.asarray(position_indices, dtype=int)
        self._vi = np.asarray(velocity_indices, dtype=int)
        if self._qi.shape != (nk,) or self._vi.shape != (nk,):
            raise ValueError(
                f"position_indices and velocity_indices must have N*K = {nk} entries "
                f"(finger-major), got {self._qi.shape} and {self._vi.shape}"
            )
        for name, idx, n in (("position_indices", self._qi, num_positions), ("velocity_indices", self._vi, num_velocities)):
            if np.any(idx < 0) or np.any(idx >= n) or len(set(idx.tolist())) != idx.size:
                raise ValueError(f"{name} must be distinct indices in [0, {n}) of the plant's state, got {idx.tolist()}")
        if not (np.isfinite(ramp_time) and ramp_time >= 0 and np.isfinite(update_period) and update_period > 0):
            raise ValueError(  # (an infinite ramp never moves)
                f"ramp_time must be finite and >= 0 and update_period finite and > 0 [s], got {ramp_time}, "
                f"{update_period}"
            )
        self._nq, self._nv = num_positions, num_velocities
        self._ramp_time = float(ramp_time)
        self._period = float(update_period)
        self._lo = hand.tendon_range[:, 0].copy()
        self._hi = hand.tendon_range[:, 1].copy()
        # Tendon damping c_i [N s/m]: the spec's, unless given (e.g. a motor position loop's).
        if damping is None:
            damping = [f.tendon_damping for f in hand.spec.fingers]
        self._damping = np.asarray(damping, float)
        if self._damping.shape != (N,) or not np.all(np.isfinite(self._damping) & (self._damping >= 0)):
            raise ValueError(f"damping must have {N} finite, non-negative entries [N s/m], got {damping}")
        self._N = N
        self.tendon_command_input = self.DeclareVectorInputPort(name="tendon_command", size=N)
        self.state_input = self.DeclareVectorInputPort(name="state", size=num_positions + num_velocities)
        init = np.concatenate([self._lo, self._lo, self._lo, [-1e9]])
        self._ramp_state = self.DeclareDiscreteState(BasicVector(init))
        self.DeclarePeriodicDiscreteUpdateEvent(
            period_sec=self._period, offset_sec=0.0, update=self._update_ramp
        )
        self.generalized_force_output = self.DeclareVectorOutputPort(
            name="generalized_force",
            size=num_velocities,
            calc=self._calc_force,
            # the plant's state, the ramp's and the time (the damping term uses the ramp's rate
            # at the context's time); not the command, which reaches the tendons through the
            # ramp's update (declaring it had made a feedthrough, e.g. a false algebraic loop)
            prerequisites_of_calc={self.state_input.ticket(), self.xd_ticket(), self.time_ticket()},
        )
        self.tension_output = self.DeclareVectorOutputPort(
            name="tension",
            size=N,
            calc=self._calc_tension,
            prerequisites_of_calc={self.state_input.ticket(), self.xd_ticket(), self.time_ticket()},
        )
        self.tendon_position_output = self.DeclareVectorOutputPort(
            name="tendon_position_measured",
            size=N,
            calc=self._calc_position,
            prerequisites_of_calc={self.xd_ticket()},
        )

    # -- helpers --------------------------------------------------------------------------

    @property
    def damping(self) -> np.ndarray:
        """Each tendon's damping c_i [N s/m] (a copy)."""
        return self._damping.copy()

    @property
    def hand(self) -> HandModel:
        return self._hand

    @property
    def ramp_time(self) -> float:
        return self._ramp_time

    def clamp(self, l: np.ndarray) -> np.ndarray:
        """Commands clipped to each tendon's range [lo, hi]."""
        l = np.asarray(l, float)
        if l.shape != (self._N,):
            raise ValueError(f"tendon_command must have shape ({self._N},), got {l.shape}")
        if not np.all(np.isfinite(l)):
            raise ValueError(f"tendon_command must be finite, got {l}")
        return np.clip(l, self._lo, self._hi)

    def set_applied(self, context: Context, l: np.ndarray) -> None:
        """Set the applied pull directly (no ramp), e.g. at the grasp. The command input is
        not touched: give it ``l`` as well (a connected source's state, or ``FixValue``), or
        the next update ramps from ``l`` to whatever the input says."""
        l = self.clamp(l)
        x = np.concatenate([l, l, l, [context.get_time() - self._ramp_time - 1.0]])
        context.SetDiscreteState(self._ramp_state, x)

    def applied(self, context: Context) -> np.ndarray:
        """The applied (ramped) pull l (N,)."""
        return context.get_discrete_state(self._ramp_state).value()[: self._N].copy()

    def _ramp(self, x: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Applied pull and its rate at time t for ramp state x."""
        N = self._N
        l_from, l_to, t0 = x[N : 2 * N], x[2 * N : 3 * N], x[3 * N]
        if self._ramp_time <= 0:
            return l_to.copy(), np.zeros(N)
        s = (t - t0) / self._ramp_time
        if s >= 1.0:
            return l_to.copy(), np.zeros(N)
        s = max(s, 0.0)
        return l_from + s * (l_to - l_from), (l_to - l_from) / self._ramp_time

    # -- events and outputs ---------------------------------------------------------------

    def _update_ramp(self, context: Context, discrete_state: DiscreteValues) -> None:
        """Start a ramp at a new command (at this update: a command given between updates
        waits up to one ``update_period``), and hold the applied pull at the ramp's value at
        the end of this period: it leads the ramp by one period and reaches the command at
        ``ramp_time - update_period``, while the damping term's rate is the ramp's over the
        whole ``ramp_time`` (0.5% of a 0.2 s ramp at the 1 ms default; the plant allows
        ``ramp_time + 2 update_period`` for an action)."""
        N = self._N
        x = context.get_discrete_state(self._ramp_state).value().copy()
        t = context.get_time()
        cmd = self.clamp(self.tendon_command_input.Eval(context))
        if np.any(np.abs(cmd - x[2 * N : 3 * N]) > 1e-12):
            # A new command: ramp from the pull applied now.
            x[N : 2 * N] = x[:N]
            x[2 * N : 3 * N] = cmd
            x[3 * N] = t
        l, _ = self._ramp(x, t + self._period)
        x[:N] = l
        discrete_state.set_value(self._ramp_state, x)

    def _tensions(self, context: Context) -> np.ndarray:
        N = self._N
        x = context.get_discrete_state(self._ramp_state).value()
        xs = self.state_input.Eval(context)
        theta = xs[self._qi]
        theta_dot = xs[self._nq + self._vi]
        l = x[:N]
        _, l_dot = self._ramp(x, context.get_time())
        return tendon_tension(self._hand, l, theta, theta_dot, l_dot, self._damping)

    def _calc_force(self, context: Context, output: BasicVector) -> None:
        tau = np.zeros(self._nv)
        tau[self._vi] = self._hand.R.T @ self._tensions(context)
        output.SetFromVector(tau)

    def _calc_tension(self, context: Context, output: BasicVector) -> None:
        output.SetFromVector(self._tensions(context))

    def _calc_position(self, context: Context, output: BasicVector) -> None:
        output.SetFromVector(context.get_discrete_state(self._ramp_state).value()[: self._N])
