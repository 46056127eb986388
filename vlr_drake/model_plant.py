"""The model plant: the quasi-static VLR model itself with hidden true parameters.

For fast experiments and for tests where the truth must be exact (DESIGN.md section 8).
The true hand-object state evolves by the same motion function Gamma (Eq. 9) that the
filter uses, with the true stiffness, link lengths, contacts and attachment; the POM pose
is then measured with seeded Gaussian noise (position sigma [m], rotation sigma [rad] as a
random rotation vector), and a measurement can drop out (a lost tag).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vlr_drake import kinematics, motion, observation, units
from vlr_drake.hand import HandModel

__all__ = ["ModelPlantState", "ModelPlant"]


def _sized(name: str, x, shape: tuple) -> np.ndarray:
    """``x`` as floats of ``shape`` (any array of as many numbers is taken), else a ValueError
    naming it (numpy's "cannot reshape array of size 2 into shape (3,)" had named nothing)."""
    x = np.asarray(x, float)
    if x.size != int(np.prod(shape)):
        raise ValueError(f"model plant: '{name}' must have shape {shape}, got {x.shape}")
    return x.reshape(shape)


@dataclass
class ModelPlantState:
    theta: np.ndarray  # (N, K)
    a: np.ndarray  # (N,)
    stretch: np.ndarray  # (N,)
    tendon_command: np.ndarray  # (N,) absolute pull l [m]
    R_PO: np.ndarray  # (3, 3)
    t_PO: np.ndarray  # (3,)


class ModelPlant:
    """A hand holding an object, simulated by the VLR model with hidden truth."""

    def __init__(self, hand: HandModel, theta, a, R_PO, t_PO, rng: np.random.Generator, *,
                 stiffness=None, link_lengths=None, sigma_position: float = 0.2e-3,
                 sigma_rotation: float = np.deg2rad(0.5), dropout: float = 0.0, tendon: str = "elastic",
                 contact_drift: float = 0.0, gravity=None, object_load=None):
        """``gravity`` (3,) [m/s^2] in the palm frame and ``object_load`` (N,) [kg]: the
        truth carries the links' weight and an object's weight at its contacts (motion.move's
        gravity loads); default: none (Eq. 9, the paper's model)."""
        self.hand = hand
        if object_load is not None and gravity is None:
            raise ValueError("model plant: an 'object_load' needs the 'gravity' that weighs it (3,) [m/s^2]")
        if not isinstance(rng, np.random.Generator):
            raise TypeError(f"model plant: 'rng' must be a numpy Generator (np.random.default_rng(seed)), "
                            f"got {type(rng).__name__}")
        R_PO, t_PO = np.asarray(R_PO, float), np.asarray(t_PO, float)
        if R_PO.shape != (3, 3) or t_PO.shape != (3,) or not (np.isfinite(R_PO).all() and np.isfinite(t_PO).all()):
            raise ValueError(f"model plant: the POM pose must be a finite R_PO (3, 3) and t_PO (3,), got shapes "
                             f"{R_PO.shape} and {t_PO.shape}")
        if not observation.is_rotation(R_PO):
            raise ValueError(f"model plant: 'R_PO' is not a rotation matrix: {np.round(R_PO, 6).tolist()}")
        self.loads = {} if gravity is None else {
            "gravity": _sized("gravity", gravity, (3,)),
            "object_load": None if object_load is None else _sized("object_load", object_load, (1, hand.N))}
        self.rng = rng
        self.stiffness = hand.stiffness.copy() if stiffness is None else _sized("stiffness", stiffness, (hand.N, hand.K))
        self.link_lengths = (hand.link_lengths.copy() if link_lengths is None
                             else _sized("link_lengths", link_lengths, (hand.N, hand.K - 1)))
        for name, v in (("sigma_position", sigma_position), ("sigma_rotation", sigma_rotation),
                        ("contact_drift", contact_drift)):
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"model plant: '{name}' must be a finite number >= 0, got {v}")
        units.check_pose_noise(sigma_position, "model plant: 'sigma_position'", sigma_rotation,
                               "model plant: 'sigma_rotation'")
        if not 0 <= dropout < 1:  # (NaN too)
            raise ValueError(f"model plant: 'dropout' must be a probability in [0, 1), got {dropout}")
        self.sigma_position, self.sigma_rotation, self.dropout = sigma_position, sigma_rotation, dropout
        self.tendon = tendon
        self.contact_drift = contact_drift
        self.failures = 0  # actions for which the model found no nearby equilibrium
        theta = _sized("theta", theta, (hand.N, hand.K))
        a = _sized("a", a, (hand.N,))
        if np.any(a < 0) or np.any(a > hand.distal_length):
            raise ValueError(f"model plant: the initial contacts {a.tolist()} m are not on the last links "
                             f"(0 to {hand.distal_length.tolist()} m)")
        eq = motion.equilibrium(hand, theta[None], a=a[None], link_lengths=self.link_lengths[None],
                                stiffness=self.stiffness[None], **self.loads)
        if not eq.ok[0] or np.any(eq.tension[0] < 0):
            raise ValueError(f"model plant: the initial grasp is not physical (tensions {eq.tension[0]} N)")
        if not hand.within_joint_limits(eq.theta)[0]:
            raise ValueError(f"model plant: the initial grasp has joints past their limits "
                             f"({np.round(np.rad2deg(eq.theta[0]), 1).tolist()} deg)")
        if not hand.within_tendon_range(hand.tendon_travel(eq.theta) + eq.stretch).all():
            raise ValueError("model plant: the initial grasp needs tendon commands outside the tendon range "
                             f"({np.round(1e3 * (hand.tendon_travel(eq.theta) + eq.stretch)[0], 2).tolist()} mm)")
        if not self._stable(eq.theta, a[None], eq.multipliers)[0]:
            raise ValueError("model plant: the initial grasp is not stable (a saddle of Eq. 9's energy, which a "
                             "hand balances on rather than holds)")
        theta = eq.theta[0]
        l0 = hand.tendon_travel(theta) + eq.stretch[0]
        self.state = ModelPlantState(theta, a, eq.stretch[0], l0, np.asarray(R_PO, float), np.asarray(t_PO, float))
        p = self.contacts()
        self.p_O = observation.attach(p[None], self.state.R_PO[None], self.state.t_PO[None])[0]
        # what a lost tag reports: the last valid measurement (the pose given here before the first)
        self._held = (self.state.R_PO.copy(), self.state.t_PO.copy())

    def contacts(self) -> np.ndarray:
        s = self.state
        return kinematics.contacts(self.hand, s.theta[None], s.a[None], self.link_lengths[None])[0]

    def _moves(self, dls: np.ndarray, l_now=None):
        """The true system moved from its current state by each action of ``dls`` (S, N)
        (batched; the state is not changed), and which of them it can make (S,). ``l_now``:
        check the one action against the tendon range (raises TendonLimitError)."""
        h, s = self.hand, self.state
        S = dls.shape[0]

        def rep(x):
            return np.repeat(x[None], S, axis=0)

        D2 = motion.contact_distances_sq(h, self.p_O[None])
        res = motion.move(h, rep(s.theta), dls, a=rep(s.a), D2=np.repeat(D2, S, axis=0), stretch=rep(s.stretch),
                          link_lengths=rep(self.link_lengths), stiffness=rep(self.stiffness), tendon=self.tendon,
                          l_now=l_now, max_substeps=64, **self.loads)
        return res, res.ok & res.stable & h.within_joint_limits(res.theta) & res.tension_feasible()

    def _stable(self, theta, a, multipliers) -> np.ndarray:
        """(P,) whether equilibria ``theta`` (P, N, K) of the true hand are stable."""
        return motion.stable_equilibria(self.hand, theta, multipliers, a=a, link_lengths=self.link_lengths[None],
                                        stiffness=self.stiffness[None], tendon=self.tendon, **self.loads)

    def possible_actions(self, dls) -> np.ndarray:
        """(S,) whether the true system has a nearby physical equilibrium for each action of
        ``dls`` (S, N) from where it is now (what :meth:`apply_action` would accept; an action
        past the tendon range is False here, and :meth:`apply_action` raises
        :class:`~vlr_drake.motion.TendonLimitError` for it)."""
        dls = np.asarray(dls, float)
        if dls.ndim != 2 or dls.shape[1] != self.hand.N:
            raise ValueError(f"possible_actions: dls must have shape (S, {self.hand.N}), got {dls.shape}")
        in_range = self.hand.within_tendon_range(self.state.tendon_command + dls).all(axis=1)
        return self._moves(dls)[1] & in_range

    def apply_action(self, dl) -> bool:
        """Move the true system by ``dl``; returns False (and stays put) if the model has
        no nearby physical equilibrium for it: the solve fails or ends on a saddle, a joint
        would pass its limit, or a tendon would have to push (the tendon command is not
        changed then). A real hand
        cannot get there either; the ideal tendon's ill-conditioned solve otherwise jumps to
        far-away roots for mm actions (joints at -130 deg)."""
        h, s = self.hand, self.state
        dl = _sized("dl", dl, (h.N,))
        res, ok = self._moves(dl[None], l_now=s.tendon_command)
        if not ok[0]:
            self.failures += 1
            return False
        s.theta, s.stretch = res.theta[0], res.stretch[0]
        s.tendon_command = s.tendon_command + dl
        p = self.contacts()
        R, t, _ = observation.pom_pose(self.p_O[None], p[None])
        s.R_PO, s.t_PO = R[0], t[0]
        if self.contact_drift > 0:  # contacts roll a little on the fingers (physics does)
            self._drift_contacts()
        return True

    def _drift_contacts(self) -> None:
        """Roll the contacts by ``contact_drift`` (SD) along the last links, kept on them; the
        joints stay and the tendon state that holds them changes, reported as the command so
        that l = R theta + stretch stays true (a filter reads it). A roll after which the grasp
        would not hold (no equilibrium, a pushing tendon, a command out of the tendon range)
        does not happen: the true grasp stays physical."""
        h, s = self.hand, self.state
        a = np.clip(s.a + self.contact_drift * self.rng.standard_normal(h.N), 0.0, h.distal_length)
        p = kinematics.contacts(h, s.theta[None], a[None], self.link_lengths[None])[0]
        eq = motion.equilibrium(h, s.theta[None], a=a[None], link_lengths=self.link_lengths[None],
                                stiffness=self.stiffness[None], **self.loads)
        command = s.tendon_command + eq.stretch[0] - s.stretch
        # (a hand with more joints than the Model O settles elsewhere after a roll: no roll
        # that would move its joints happens, since the truth must stay an equilibrium)
        if not (eq.ok[0] and np.all(eq.tension[0] >= 0) and h.within_tendon_range(command[None]).all()
                and np.max(np.abs(eq.theta[0] - s.theta)) < 1e-9
                and self._stable(s.theta[None], a[None], eq.multipliers)[0]):
            return
        s.a, s.tendon_command, s.stretch = a, command, eq.stretch[0]
        self.p_O = observation.attach(p[None], s.R_PO[None], s.t_PO[None])[0]

    def measure(self) -> tuple[np.ndarray, np.ndarray, bool]:
        """Noisy POM pose (R, t, valid). A dropout (probability ``dropout``) is a lost tag:
        valid False with the held pose, the last valid measurement, as the physics plant and
        the tag observer hold theirs, not the truth of now. Before the first valid
        measurement nothing has been seen, and the held pose is the one the plant was made
        with (a caller that needs a measurement looks again: identify does)."""
        s = self.state
        if self.dropout > 0 and self.rng.random() < self.dropout:
            return self._held[0].copy(), self._held[1].copy(), False
        t = s.t_PO + self.sigma_position * self.rng.standard_normal(3)
        dR = observation.rotvec_to_matrix(self.sigma_rotation * self.rng.standard_normal(3))[0]
        R = s.R_PO @ dR
        self._held = (R.copy(), t.copy())
        return R, t, True
