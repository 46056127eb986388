"""The hand specification: the single source of truth for a hand's geometry and physics.

A hand has N fingers with K revolute joints each (DESIGN.md section 2). Finger i is planar:
its base joint sits at ``b_i`` in the palm frame P and it flexes in the plane through ``b_i``
spanned by the palm normal ``z`` and a unit flexion direction ``u_i`` in the palm plane.
With ``e(a) = sin(a) u_i + cos(a) z`` and cumulative angles ``phi_k = theta_1 + ... + theta_k``
its joints and its contact are

    q_1 = b_i,   q_{k+1} = q_k + L_k e(phi_k)            (k = 1 .. K-1)
    p_i = q_K + d_i e(phi_K + gamma_i),   d_i = |(a_i, n_i)|,   gamma_i = atan2(n_i, a_i)

where ``a_i`` is the (unknown) contact position along the last link and ``n_i`` the known
offset of the pad's centre of curvature from the link axis (pad thickness minus pad radius:
a joint at the pad's centre stands for its rolling; see ``FingerSpec.pad_radius``). The segment
``q_K -> p_i`` is the distal *virtual* link of the VLR (Eq. 2).

Everything in this module is SI (metres, radians, newtons). The SDFormat models in
``models/``, the physics plant, the model plant and the filter all read their numbers from a
:class:`HandSpec`; nothing else states the hand's geometry.

The Yale Model O numbers (:func:`model_o`) come from public third-party simulation models
(there is no published measurement); see the docstring of :func:`model_o` for each source.
"""

from __future__ import annotations

import copy
import dataclasses as dc
import re
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from vlr_drake import units

#: What a hand's or finger's name may hold: it names the generated SDF's model, links and joints.
_NAME = r"[A-Za-z0-9_.-]+"

__all__ = [
    "FingerSpec",
    "HandSpec",
    "HandModel",
    "link_mass",
    "model_o",
    "novel_finger",
    "NOVEL_FINGER_NAMES",
    "NOVEL_HANDS",
    "hand_by_name",
    "generic_hand",
]


def link_mass(density, radius, length):
    """Mass [kg] of a link: a solid cylinder of ``radius`` as long as the capsule of
    ``length`` between its joints (``length + 2 radius``; a slight overestimate). Broadcasts."""
    return density * np.pi * np.square(radius) * (np.asarray(length) + 2.0 * np.asarray(radius))


@dataclass
class FingerSpec:
    """One planar, tendon-driven finger with K spring-loaded revolute joints."""

    # Name of the finger, unique in the hand (used for model frames and reports).
    name: str = "finger"
    # Base (first) joint position b_i in the palm frame P [m].
    base: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    # Flexion direction u_i in the palm plane (unit after normalisation, z component 0).
    flexion_direction: list[float] = field(default_factory=lambda: [1.0, 0.0, 0.0])
    # Physical link lengths L_1 .. L_{K-1} between consecutive joints [m].
    link_lengths: list[float] = field(default_factory=lambda: [0.062])
    # Length of the last (distal) physical link from its joint to the tip [m].
    distal_length: float = 0.048
    # Pad thickness: distance of the contact surface from the last link's axis [m].
    pad_offset: float = 0.008
    # Radius of curvature of the pad [m] (the physics pad's spheres). The VLR's contact is
    # the pad's centre of curvature, n_i = pad_offset - pad_radius from the axis (DESIGN.md
    # section 3 correction: with the contact on the pad surface, Eq. 9 predicted the physics
    # plant's motion 2x too large; at the centre, within 5%). It is an approximation: a pad
    # that rolls moves its centre over the object by the pad radius times its rotation
    # relative to the object (0.3 mm per action on the physics plant), which a joint at the
    # centre lacks (vlr_drake.physics.agreement's kinematic check).
    pad_radius: float = 0.008
    # Tendon moment arms (pulley radii) r_k of the K joints [m].
    moment_arms: list[float] = field(default_factory=lambda: [0.009, 0.0045])
    # Joint spring stiffness k_k [N m/rad].
    stiffness: list[float] = field(default_factory=lambda: [0.08, 0.16])
    # Spring rest angles theta0_k [rad] (0 = straight finger).
    rest_angles: list[float] = field(default_factory=lambda: [0.0, 0.0])
    # Joint lower limits [rad].
    joint_lower: list[float] = field(default_factory=lambda: [-0.2, -0.2])
    # Joint upper limits [rad].
    joint_upper: list[float] = field(default_factory=lambda: [1.9, 1.9])
    # Joint viscous damping for the physics plant [N m s/rad].
    joint_damping: list[float] = field(default_factory=lambda: [0.002, 0.001])
    # Series stiffness of tendon plus motor position loop, kappa_i [N/m].
    tendon_stiffness: float = 2000.0
    # Tendon damping c_i for the physics plant [N s/m]: the tendon with the motor's position
    # loop (at 5 N s/m a held object rang at about 4 Hz for over a second after each action).
    # physics.tendon_damping, where set (> 0), replaces every finger's.
    tendon_damping: float = 150.0
    # Range of the commanded tendon pull l_i (0 = taut at a straight finger) [m].
    tendon_range: list[float] = field(default_factory=lambda: [0.0, 0.045])
    # Radius of the capsule links (visual and collision) [m].
    link_radius: float = 0.009
    # Density of the links [kg/m^3]: each is a solid cylinder of link_radius as long as its
    # capsule (link_mass), its centre of mass halfway along it. The physics plant's
    # inertias and the VLR's link weight (HandModel.link_weight_torque) both use it.
    link_density: float = 1100.0
    # Fingertip friction coefficient (static = dynamic) [-].
    friction: float = 1.0

    @property
    def num_joints(self) -> int:
        return len(self.moment_arms)

    def validate(self, where: str | None = None, joints: int | None = None) -> FingerSpec:
        """Check the finger and raise ``ValueError`` naming the offending field (``where``:
        how the message names the finger; ``joints``: the number of joints the hand's fingers
        have, default this finger's own)."""
        from vlr_drake.kinematics import is_number  # (kinematics imports this module)

        f = self
        where = f"finger '{f.name}'" if where is None else where
        if not (isinstance(f.name, str) and re.fullmatch(_NAME, f.name)):  # it names SDF links and joints
            raise ValueError(f"{where}: field 'name' must be letters, digits, '_', '.' or '-', got {f.name!r}")
        if joints is None:
            try:
                joints = len(f.moment_arms)
            except TypeError:
                raise ValueError(f"{where}: field 'moment_arms' must be a list of numbers, got {f.moment_arms!r}") from None
        K = joints
        if K < 2:
            raise ValueError(f"{where}: a finger needs at least 2 joints, got {K}")
        for fname, n in [
            ("moment_arms", K),
            ("stiffness", K),
            ("rest_angles", K),
            ("joint_lower", K),
            ("joint_upper", K),
            ("joint_damping", K),
            ("link_lengths", K - 1),
            ("base", 3),
            ("flexion_direction", 3),
            ("tendon_range", 2),
        ]:
            v = getattr(f, fname)
            try:  # a scalar, a string or a nested list: named here, not a TypeError deep inside
                arr = np.asarray(v, dtype=float)
            except (TypeError, ValueError):
                raise ValueError(f"{where}: field '{fname}' must be a list of {n} numbers, got {v!r}") from None
            if arr.shape != (n,):
                raise ValueError(f"{where}: field '{fname}' must be a list of {n} numbers, got {v!r}")
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"{where}: field '{fname}' is not finite: {v}")
        for fname in ["link_lengths", "moment_arms", "stiffness"]:
            v = np.asarray(getattr(f, fname))
            if np.any(v <= 0):
                raise ValueError(f"{where}: field '{fname}' must be positive, got {v.tolist()}")
        for fname in ["distal_length", "tendon_stiffness", "link_radius", "link_density", "pad_offset",
                      "friction", "tendon_damping", "pad_radius"]:
            v = getattr(f, fname)
            if not is_number(v):
                raise ValueError(f"{where}: field '{fname}' must be a number, got {v!r}")
        for fname in ["distal_length", "tendon_stiffness", "link_radius", "link_density"]:
            if not (np.isfinite(getattr(f, fname)) and getattr(f, fname) > 0):
                raise ValueError(f"{where}: field '{fname}' must be a finite positive number, got {getattr(f, fname)}")
        for fname in ["pad_offset", "friction", "tendon_damping"]:  # (NaN < 0 is False: said so)
            if not (np.isfinite(getattr(f, fname)) and getattr(f, fname) >= 0):
                raise ValueError(f"{where}: field '{fname}' must be a finite number >= 0, got {getattr(f, fname)}")
        if not (np.isfinite(f.pad_radius) and 0 < f.pad_radius <= f.pad_offset + f.link_radius):
            raise ValueError(
                f"{where}: field 'pad_radius' must be in (0, pad_offset + link_radius] = "
                f"(0, {f.pad_offset + f.link_radius:g}], got {f.pad_radius}"
            )
        if np.any(np.asarray(f.joint_damping) < 0):
            raise ValueError(f"{where}: field 'joint_damping' must be >= 0, got {list(f.joint_damping)}")
        u = np.asarray(f.flexion_direction, float)
        if abs(u[2]) > 1e-9 or np.linalg.norm(u) < 1e-9:
            raise ValueError(f"{where}: 'flexion_direction' must be a nonzero vector in the palm plane (z = 0), got {u.tolist()}")
        if not np.all(np.asarray(f.joint_lower) < np.asarray(f.joint_upper)):
            raise ValueError(f"{where}: 'joint_lower' must be below 'joint_upper'")
        if not f.tendon_range[0] < f.tendon_range[1]:
            raise ValueError(f"{where}: 'tendon_range' must be [min, max] with min < max")
        # in the package's units: a value in mm, degrees or g/cm^3 would run, and be wrong
        for fname in ("base", "link_lengths", "distal_length", "pad_offset", "pad_radius", "moment_arms",
                      "tendon_range", "link_radius"):
            units.check_length(getattr(f, fname), f"{where}: field '{fname}'")
        for fname in ("rest_angles", "joint_lower", "joint_upper"):
            units.check_angle(getattr(f, fname), f"{where}: field '{fname}'")
        units.check_stiffness(f.stiffness, f"{where}: field 'stiffness'")
        units.check_density(f.link_density, f"{where}: field 'link_density'")
        return self


@dataclass
class HandSpec:
    """A hand: N fingers with K joints each, all expressed in the palm frame P."""

    # Name of the hand (model instance name in Drake).
    name: str = "hand"
    # The fingers, in the order used by every array (finger axis of the particle arrays).
    fingers: list[FingerSpec] = field(default_factory=list)
    # Palm disc radius, for the model's visual and collision geometry [m].
    palm_radius: float = 0.075
    # Palm thickness [m].
    palm_thickness: float = 0.02

    def __post_init__(self) -> None:
        # yaml_load_typed builds the dataclass field by field; validation is explicit
        # (validate()) so that a partially built spec can exist while loading.
        pass

    @property
    def num_fingers(self) -> int:
        return len(self.fingers)

    @property
    def num_joints_per_finger(self) -> int:
        return self.fingers[0].num_joints if self.fingers else 0

    def finger_names(self) -> list[str]:
        return [f.name for f in self.fingers]

    def validate(self) -> HandSpec:
        """Check the spec and raise ``ValueError`` naming the offending field."""
        if not (isinstance(self.name, str) and re.fullmatch(_NAME, self.name)):  # it names the SDF model
            raise ValueError(f"hand: field 'name' must be letters, digits, '_', '.' or '-', got {self.name!r}")
        if len(self.fingers) < 3:
            raise ValueError(f"hand '{self.name}': a VLR needs at least 3 fingers, got {len(self.fingers)}")
        from vlr_drake.kinematics import is_number  # (kinematics imports this module)

        for fname in ("palm_radius", "palm_thickness"):
            v = getattr(self, fname)
            if not (is_number(v) and 0 < v < np.inf):
                raise ValueError(f"hand '{self.name}': field '{fname}' must be a finite positive number [m], got {v!r}")
            units.check_length(v, f"hand '{self.name}': field '{fname}'")
        K = self.fingers[0].validate(f"hand '{self.name}', finger '{self.fingers[0].name}'").num_joints  # (first:
        # a scalar moment_arms had raised a TypeError here, not the finger's named message)
        if K < 2:
            raise ValueError(f"hand '{self.name}': fingers need at least 2 joints, got {K}")
        names = set()
        for f in self.fingers:
            where = f"hand '{self.name}', finger '{f.name}'"
            if f.name in names:
                raise ValueError(f"{where}: duplicate finger name")
            names.add(f.name)
            f.validate(where, K)
        if len({f.num_joints for f in self.fingers}) != 1:
            raise ValueError(f"hand '{self.name}': all fingers must have the same number of joints")
        return self

    def replaced(self, replacements: dict[str, FingerSpec]) -> HandSpec:
        """A copy with some fingers swapped for others (keeping base and flexion direction).

        ``replacements`` maps the name of a finger in this hand to the replacement finger
        (e.g. :func:`novel_finger`). The replacement is mounted where the old finger was.
        """
        hand = copy.deepcopy(self)
        for old, new in replacements.items():
            idx = [f.name for f in hand.fingers].index(old) if old in hand.finger_names() else None
            if idx is None:
                raise ValueError(f"hand '{self.name}' has no finger '{old}' (fingers: {self.finger_names()})")
            nf = copy.deepcopy(new)
            nf.base = list(hand.fingers[idx].base)
            nf.flexion_direction = list(hand.fingers[idx].flexion_direction)
            nf.name = f"{old}_{new.name}" if new.name != old else old
            hand.fingers[idx] = nf
        return hand.validate()

    def model(self) -> HandModel:
        """The numeric (array) view of this spec, validated."""
        return HandModel(self.validate())


class HandModel:
    """Arrays of a validated :class:`HandSpec`, with the finger as leading axis.

    Attributes (N fingers, K joints):
        base (N, 3), u (N, 3), z (3,), link_lengths (N, K-1), distal_length (N,),
        pad (N,), moment_arms (N, K), stiffness (N, K), rest_angles (N, K),
        joint_lower (N, K), joint_upper (N, K), kappa (N,), tendon_range (N, 2),
        link_radius (N,), link_density (N,).
    """

    def __init__(self, spec: HandSpec):
        self.spec = spec
        f = spec.fingers
        self.N = len(f)
        self.K = f[0].num_joints
        self.names = [x.name for x in f]
        self.base = np.array([x.base for x in f], float)
        u = np.array([x.flexion_direction for x in f], float)
        self.u = u / np.linalg.norm(u, axis=1, keepdims=True)
        self.z = np.array([0.0, 0.0, 1.0])
        self.link_lengths = np.array([x.link_lengths for x in f], float).reshape(self.N, self.K - 1)
        self.distal_length = np.array([x.distal_length for x in f], float)
        # n_i of the VLR: the pad's centre of curvature (see FingerSpec.pad_radius).
        self.pad = np.array([x.pad_offset - x.pad_radius for x in f], float)
        self.pad_surface = np.array([x.pad_offset for x in f], float)
        # the pads' radius of curvature, from the pad's centre to its surface (the rolling model's)
        self.pad_radius = self.pad_surface - self.pad
        self.moment_arms = np.array([x.moment_arms for x in f], float)
        self.stiffness = np.array([x.stiffness for x in f], float)
        self.rest_angles = np.array([x.rest_angles for x in f], float)
        self.joint_lower = np.array([x.joint_lower for x in f], float)
        self.joint_upper = np.array([x.joint_upper for x in f], float)
        self.kappa = np.array([x.tendon_stiffness for x in f], float)
        self.tendon_range = np.array([x.tendon_range for x in f], float)
        self.link_radius = np.array([x.link_radius for x in f], float)
        self.link_density = np.array([x.link_density for x in f], float)
        for name in list(vars(self)):
            v = getattr(self, name)
            if isinstance(v, np.ndarray):
                v.setflags(write=False)

    @property
    def num_angles(self) -> int:
        return self.N * self.K

    def within_joint_limits(self, theta) -> np.ndarray:
        """(...,) True where every joint angle of ``theta`` (..., N, K) is inside its limits."""
        theta = np.asarray(theta, float)
        return np.all((theta >= self.joint_lower) & (theta <= self.joint_upper), axis=(-2, -1))

    def within_tendon_range(self, l) -> np.ndarray:
        """(..., N) True where each tendon pull of ``l`` (..., N) [m] is inside its range
        (to 1e-12 m)."""
        l = np.asarray(l, float)
        return (l >= self.tendon_range[:, 0] - 1e-12) & (l <= self.tendon_range[:, 1] + 1e-12)

    def tendon_travel(self, theta) -> np.ndarray:
        """R theta per finger: the tendon length the joints take up, (..., N) for angles
        (..., N, K) [m] (Eq. 7 without the differences)."""
        theta = np.asarray(theta, float)
        out = theta[..., 0] * self.moment_arms[:, 0]
        for k in range(1, self.K):  # the order of numpy's sum over this short axis: same round-off
            out += theta[..., k] * self.moment_arms[:, k]
        return out

    def link_weight_torque(self, theta, gravity, link_lengths=None) -> np.ndarray:
        """The links' weight as joint torques (P, N, K) [N m] at angles ``theta`` (P, N, K),
        for ``gravity`` (3,) in the palm frame [m/s^2] and the physical link lengths (P or 1,
        N, K-1) (default: the hand's; the masses follow them, :func:`link_mass`).

        Link l of finger i, of mass m_l with its centre of mass halfway along it, and the
        links beyond it, whose masses its length L_l carries, have the first moment
        mu_l = m_l L_l / 2 + L_l sum_{k > l} m_k along e(phi_l), so the potential is
        V = -sum_l mu_l (g_u sin phi_l + g_z cos phi_l) (g_u = g . u_i, g_z = g . z; the
        component across the finger's plane does no work), and the torque on joint j is

            tau_j = -dV/dtheta_j = sum_{l >= j} mu_l (g_u cos phi_l - g_z sin phi_l).

        Eq. 9 has no such term (the paper neglects it); :func:`vlr_drake.motion.move` takes
        it as ``external_torque`` held through a move, or with ``gravity`` as a load that
        follows the angles (its potential V in the energy, dtau/dtheta in Newton's matrix).
        """
        theta = np.asarray(theta, float)
        if theta.ndim != 3 or theta.shape[1:] != (self.N, self.K):
            raise ValueError(f"'theta' must have shape (P, {self.N}, {self.K}), got {theta.shape}")
        if not np.all(np.isfinite(theta)):
            raise ValueError("'theta' contains NaN or infinite values")
        mu = self.link_moments(link_lengths)
        phi = np.cumsum(theta, axis=-1)
        g_u, g_z = self.gravity_in_finger_planes(gravity).T
        per_link = mu * (g_u[None, :, None] * np.cos(phi) - g_z[None, :, None] * np.sin(phi))
        return np.cumsum(per_link[..., ::-1], axis=-1)[..., ::-1]

    def link_moments(self, link_lengths=None) -> np.ndarray:
        """The links' first moments mu_l = m_l L_l / 2 + L_l sum_{k > l} m_k [kg m], (P or 1,
        N, K), for the physical link lengths (P or 1, N, K-1) (default: the hand's): link l's
        own mass at its middle and the mass of the links beyond it at its end
        (:meth:`link_weight_torque`)."""
        L = self.link_lengths[None] if link_lengths is None else np.asarray(link_lengths, float)
        # (an (N, K-1) array without its particles' axis had broadcast into N x N fingers, and a
        # (K-1,) one had given every finger the same links)
        if L.ndim != 3 or L.shape[1:] != (self.N, self.K - 1):
            raise ValueError(f"'link_lengths' must have shape (P or 1, {self.N}, {self.K - 1}), got {L.shape}")
        if not np.all(np.isfinite(L) & (L > 0)):
            raise ValueError("'link_lengths' must be finite lengths > 0 [m]")
        lengths = np.concatenate([np.broadcast_to(L, (L.shape[0], self.N, self.K - 1)),
                                  np.broadcast_to(self.distal_length[None, :, None], (L.shape[0], self.N, 1))], axis=2)
        m = link_mass(self.link_density[None, :, None], self.link_radius[None, :, None], lengths)
        beyond = np.cumsum(m[..., ::-1], axis=-1)[..., ::-1] - m  # sum_{k > l} m_k
        return lengths * (0.5 * m + beyond)

    def gravity_in_finger_planes(self, gravity) -> np.ndarray:
        """(N, 2) components (g . u_i, g . z) of ``gravity`` (3,) [m/s^2] in the palm frame,
        in each finger's plane: the part that does work on the finger's joints."""
        g = np.asarray(gravity, float)
        if g.size != 3 or not np.all(np.isfinite(g)):
            raise ValueError(f"'gravity' must be 3 finite numbers [m/s^2], got {g.tolist()}")
        g = g.reshape(3)
        return np.ascontiguousarray(np.stack([self.u @ g, np.full(self.N, float(g @ self.z))], axis=1))

    @cached_property
    def R(self) -> np.ndarray:
        """Tendon moment-arm matrix R (N x N*K): dl_i = R_i . dtheta (Eq. 7)."""
        R = np.zeros((self.N, self.N * self.K))
        for i in range(self.N):
            R[i, i * self.K : (i + 1) * self.K] = self.moment_arms[i]
        R.setflags(write=False)
        return R

    @cached_property
    def constraint_pairs(self) -> np.ndarray:
        """Contact pairs (m x 2) whose distances hold the grasp rigid (Eq. 8).

        All three pairs among contacts 0, 1, 2, then each further contact tied to
        contacts 0, 1, 2: m = 3N - 6 independent distances, a generically rigid framework.
        """
        pairs = [(0, 1), (0, 2), (1, 2)]
        for i in range(3, self.N):
            pairs += [(0, i), (1, i), (2, i)]
        out = np.array(pairs, dtype=np.int64)
        out.setflags(write=False)
        return out

    @property
    def num_constraints(self) -> int:
        return len(self.constraint_pairs)

    @cached_property
    def constraints_dependent(self) -> bool:
        """True where the gradients of the grasp's constraints over the joint angles are
        dependent at every configuration (rank below :attr:`num_constraints`): a hand of six
        or more fingers that all flex in planes square to the palm, whose hinges can carry a
        pattern of sideways contact forces that the object balances. Judged at three
        configurations drawn inside the joint limits (a fixed seed)."""
        from vlr_drake import grasps  # grasps builds on this module

        rng = np.random.default_rng(0)
        lo, hi = self.joint_lower, self.joint_upper
        theta = lo + (hi - lo) * rng.uniform(0.3, 0.7, (3, self.N, self.K))
        a = np.broadcast_to(0.6 * self.distal_length, (3, self.N))
        G = grasps.constraint_gradients(self, theta, a, self.constraint_pairs)
        sv = np.linalg.svd(G, compute_uv=False)
        return bool(np.all(sv[:, -1] <= 1e-10 * sv[:, 0]))

    @property
    def statically_determinate(self) -> bool:
        """True where the grasp's stationarity conditions are square in (T, lambda)
        (N K = N + m, the Model O): every grasp configuration is then an equilibrium for
        exactly one tendon state (:func:`vlr_drake.motion.equilibrium`)."""
        return self.N * self.K == self.N + self.num_constraints

    def finger_index(self, name: str) -> int:
        if name not in self.names:
            raise ValueError(f"hand '{self.spec.name}' has no finger '{name}' (fingers: {self.names})")
        return self.names.index(name)


# --------------------------------------------------------------------------------------
# The Yale Model O (default instance) and its novel fingers.
# --------------------------------------------------------------------------------------

#: Distance of the fingers' proximal joints from the palm centre along x [m].
MODEL_O_BASE_X = 0.054
#: Half the spacing of the two side-by-side fingers [m].
MODEL_O_FINGER_HALF_SPACING = 0.027


def thumb_indices(names) -> list[int]:
    """The fingers that are thumbs, by index: those whose name starts with "thumb" (the
    Model O's "thumb", a novel hand's "thumb_NF1"), which the thumb factor of the physics
    plant's pretension and the stiffness experiment's spring go to."""
    return [i for i, name in enumerate(names) if name.startswith("thumb")]


def _model_o_finger(name: str, base: list[float], direction: list[float]) -> FingerSpec:
    return FingerSpec(
        name=name,
        base=base,
        flexion_direction=direction,
        link_lengths=[0.062],
        distal_length=0.048,
        pad_offset=0.008,
        moment_arms=[0.009, 0.0045],
        stiffness=[0.08, 0.16],
        rest_angles=[0.0, 0.0],
    )


def model_o() -> HandSpec:
    """The Yale Model O-like default hand: a thumb opposing two fingers, K = 2.

    Sources (third-party simulation models; the Model O has no published measurements):
    - proximal link 62 mm, finger swivel positions (-34, +-27) mm and thumb (+34, 0) mm,
      proximal joints 20 mm out from the swivel axes: Gazebo model
      avishais/gazebo_adaptive_hand_simulator, urdf/hand_O.xacro. The bases here are the
      swivel positions pushed 20 mm outwards (x = -+54 mm), which a physics prototype found
      necessary to hold 50-90 mm objects on the distal pads (DESIGN.md section 2).
    - distal link 48 mm with an 8 mm pad offset: same model, pad geometry.
    - distal spring twice as stiff as the proximal one and distal moment arm half the
      proximal one: grablab openhand_node and its simulators; magnitudes k_p = 0.08,
      k_d = 0.16 N m/rad, r_p = 9 mm, r_d = 4.5 mm, tendon stiffness 2000 N/m, friction 1
      (DESIGN.md section 2).
    The fourth (spread) motor is held fixed during manipulation, so the flexion directions
    are constant: the two fingers flex towards +x, the thumb towards -x.
    """
    x, y = MODEL_O_BASE_X, MODEL_O_FINGER_HALF_SPACING
    return HandSpec(
        name="model_o",
        fingers=[
            _model_o_finger("thumb", [x, 0.0, 0.0], [-1.0, 0.0, 0.0]),
            _model_o_finger("finger_left", [-x, y, 0.0], [1.0, 0.0, 0.0]),
            _model_o_finger("finger_right", [-x, -y, 0.0], [1.0, 0.0, 0.0]),
        ],
    ).validate()


NOVEL_FINGER_NAMES = ("NF1", "NF2", "NF3")


def novel_finger(name: str) -> FingerSpec:
    """Replacement fingers of the paper's novel-finger experiment (its Fig. 8).

    NF1: proximal link 40 mm; NF2: proximal link 50 mm; NF3: proximal link 50 mm with a
    differently shaped distal link (shorter, 40 mm, with a thicker 12 mm pad). Springs,
    moment arms and tendon as the Model O's.
    """
    base = _model_o_finger(name, [0.0, 0.0, 0.0], [1.0, 0.0, 0.0])
    if name == "NF1":
        base.link_lengths = [0.040]
    elif name == "NF2":
        base.link_lengths = [0.050]
    elif name == "NF3":
        base.link_lengths = [0.050]
        base.distal_length = 0.040
        base.pad_offset = 0.012
    else:
        raise ValueError(f"unknown novel finger '{name}' (known: {', '.join(NOVEL_FINGER_NAMES)})")
    return base


#: The paper's novel hands: which Model O fingers are replaced by which novel finger.
NOVEL_HANDS: dict[str, dict[str, str]] = {
    "NH1": {"thumb": "NF1"},
    "NH2": {"thumb": "NF1", "finger_left": "NF2"},
    "NH3": {"thumb": "NF1", "finger_left": "NF2", "finger_right": "NF3"},
}


def hand_by_name(name: str) -> HandSpec:
    """``model_o``, ``NH1``, ``NH2`` or ``NH3``."""
    if name == "model_o":
        return model_o()
    if name in NOVEL_HANDS:
        hand = model_o().replaced({old: novel_finger(new) for old, new in NOVEL_HANDS[name].items()})
        hand.name = name
        return hand
    raise ValueError(f"unknown hand '{name}' (known: model_o, {', '.join(NOVEL_HANDS)})")


def generic_hand(num_fingers: int, num_joints: int, radius: float = 0.055) -> HandSpec:
    """A symmetric hand with ``num_fingers`` fingers of ``num_joints`` joints around a circle.

    Used to exercise the general-N, general-K code paths (the paper's VLR claim). The
    proximal links share the Model O's 62 mm, and the distal link is 40 mm (the Model O's
    48): a finger 102 mm long.
    """
    if num_fingers < 3 or num_joints < 2:
        raise ValueError("generic_hand needs num_fingers >= 3 and num_joints >= 2")
    fingers = []
    K = num_joints
    for i in range(num_fingers):
        ang = 2 * np.pi * i / num_fingers
        c, s = float(np.cos(ang)), float(np.sin(ang))  # plain floats: the spec prints and writes as YAML
        fingers.append(
            FingerSpec(
                name=f"f{i}",
                base=[radius * c, radius * s, 0.0],
                flexion_direction=[-c, -s, 0.0],
                link_lengths=[0.062 / (K - 1)] * (K - 1),
                distal_length=0.040,
                pad_offset=0.008,
                moment_arms=np.linspace(0.009, 0.0045, K).tolist(),
                stiffness=np.linspace(0.08, 0.16, K).tolist(),
                rest_angles=[0.0] * K,
                joint_lower=[-0.2] * K,
                joint_upper=[1.9] * K,
                joint_damping=[0.002] * K,
            )
        )
    return HandSpec(name=f"generic_{num_fingers}x{num_joints}", fingers=fingers).validate()


def spec_fields(cls: type) -> list[str]:
    """Field names of a spec dataclass (for error messages and YAML checks)."""
    return [f.name for f in dc.fields(cls)]
