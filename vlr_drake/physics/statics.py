"""Where the VLR's statics part from the physics plant's: the plant's joint torques, by load.

Eq. 9 balances, at every joint, the tendon, the joint spring and the contacts, each contact a
frictionless pin at the pad's centre of curvature whose forces on the object cancel (a
weightless object). At rest the plant balances more (torques on the joints [N m], (N, K),
positive flexing):

    tendon + spring + link_weight + pad_contact + other_contacts = residual ~ 0

- ``tendon`` R^T T and ``spring`` -k (theta - theta0), as in the VLR;
- ``link_weight``: the gravity on the fingers' links, which Eq. 9 does not have;
- ``pad_contact``: the pads' contact forces, at the points where pads and object touch. Of
  it, ``pad_moment`` is what the VLR's pin cannot carry: the same forces applied at the
  pads' centres of curvature instead (:attr:`HandModel.pad`) give the rest, and the
  difference is the moment of the forces' tangential (friction) part about the centre, a
  pad radius away, which reaches every joint of the finger;
- ``object_weight``: the object's load, which the pads carry: its weight at its centre of
  mass and the forces of the other bodies touching it. The VLR's contact forces cancel on
  the object, so this is an external load for it, split over the pads' centres as the
  least-norm forces with its sum and its moment (:func:`object_load_shares`). Any two such
  splits differ by forces the VLR's constraints carry. (Until 2026-12-06 the weight alone
  was split by the barycentric weights of the centre of mass projected onto the pads'
  plane: the moment of the centre of mass's offset from that plane, 7.4 mN m on the apple
  with the palm pitched 30 deg, and the other bodies' forces were lost; a review. With the
  palm down, as below, that moment is about nil.)
- ``other_contacts``: bodies other than the pads' links touching the object (a proximal
  link, the palm), which the VLR does not have either;
- ``residual``: what is left (joint limits, damping, a state not quite at rest).

:func:`commanded_offsets` then says how much of the VLR's offset from the plant each load
explains: the VLR's commanded equilibrium (:func:`vlr_drake.grasps.commanded_equilibrium`)
from the plant's state, with the load, as measured there, added as a constant external
joint torque (:func:`vlr_drake.motion.move`'s ``external_torque``).

Measured (``python -m vlr_drake.physics.agreement --object OBJECT --actions 40``, seed 0;
mean |offset| of the commanded equilibrium from the plant's angles over the joints and
actions [deg], with each unmodelled load added):

    object        none   pad_moment  link_weight  object_weight  all
    apple         1.35   1.13        0.92         1.26           0.027
    wine glass    1.86   1.50        1.33         0.88           0.051
    toy block     1.04   0.88        0.42         0.86           0.078
    gelatin box   1.27   0.95        0.88         0.72           0.033

(Measured with the earlier split of the object's weight, which lost its moment off the pads'
plane; palm down that moment is about nil: the apple over 3 actions gives 'all' 0.025 deg
with the present split. With the palm pitched 30 deg: 0.060 deg, against 0.83 with the
earlier split; rolled 30 deg: 0.024.)

With all of them the VLR's statics match the plant's to a twentieth of a degree, and Newton
finds the equilibrium in every action (2 of 40 have none without them on the apple, wine
glass and gelatin box): the kinematics, the tendons and the springs of Eq. 9 are right,
and what it lacks is these loads. On the flat screwdriver (a power grasp) the proximal
links carry 37 mN m and the VLR has no equilibrium with or without them. Of the four, the
filter can know the links' weight, and carries it on the physics plant
(``FilterConfig.gravity_palm``, :data:`vlr_drake.identify.LINK_WEIGHT`); it can identify
the object's weight, a mass split by the barycentric weights above
(``PriorConfig.object_mass_unknown``, off by default); the pads' moments need the contact
normals.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from vlr_drake import kinematics
from vlr_drake.grasps import commanded_equilibrium
from vlr_drake.hand import HandModel

__all__ = ["JointLoads", "LOADS", "UNMODELLED", "plant_loads", "barycentric_weights", "commanded_offsets"]

#: The loads of :class:`JointLoads`, in order.
LOADS = ("tendon", "spring", "link_weight", "pad_contact", "pad_moment", "object_weight", "other_contacts",
         "residual")
#: The loads the VLR's Eq. 9 does not have (its external loads, for :func:`commanded_offsets`).
UNMODELLED = ("pad_moment", "link_weight", "object_weight", "other_contacts")


@dataclass
class JointLoads:
    """Joint torques [N m] (N, K) of one state of the physics plant, by load (module
    docstring); ``pad_moment`` is part of ``pad_contact``, ``object_weight`` a split of the
    weight that ``pad_contact`` carries, so neither enters the balance twice."""

    tendon: np.ndarray
    spring: np.ndarray
    link_weight: np.ndarray
    pad_contact: np.ndarray
    pad_moment: np.ndarray
    object_weight: np.ndarray
    other_contacts: np.ndarray
    residual: np.ndarray

    def unmodelled(self, names=UNMODELLED) -> np.ndarray:
        """The sum of the named loads (default: every load Eq. 9 lacks) (N, K)."""
        return sum((getattr(self, n) for n in names), np.zeros_like(self.tendon))

    def as_dict(self, scale: float = 1.0) -> dict[str, list]:
        return {f.name: (scale * getattr(self, f.name)).tolist() for f in fields(self)}


def barycentric_weights(contacts: np.ndarray, point: np.ndarray) -> np.ndarray:
    """Weights w (N,) with sum w = 1 and sum w_i contacts_i nearest ``point`` (3,) (least
    squares: a point off the contacts' plane is projected onto it)."""
    c = np.asarray(contacts, float)
    A = (c[:-1] - c[-1]).T  # (3, N-1)
    w, *_ = np.linalg.lstsq(A, np.asarray(point, float) - c[-1], rcond=None)
    return np.append(w, 1.0 - w.sum())


def object_load_shares(r: np.ndarray, force: np.ndarray, moment: np.ndarray) -> np.ndarray:
    """Forces (N, 3) at the points ``r`` (N, 3) (the pads' centres, about a reference point)
    whose sum is ``force`` (3,) and whose moment about the reference is ``moment`` (3,): the
    least-norm such split. Any two splits differ by forces along the lines between the
    points, which the VLR's constraints (Eq. 8's distances) carry."""
    N = r.shape[0]
    A = np.zeros((6, 3 * N))
    for i in range(N):
        A[:3, 3 * i: 3 * i + 3] = np.eye(3)
        x, y, z = r[i]
        A[3:, 3 * i: 3 * i + 3] = [[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]]  # r_i x
    f, *_ = np.linalg.lstsq(A, np.concatenate([force, moment]), rcond=None)
    return f.reshape(N, 3)


def plant_loads(ph, root_context) -> JointLoads:
    """The joint torques of the physics hand ``ph`` (:class:`~vlr_drake.systems.physics_plant.PhysicsHand`)
    at its current state, by load. Needs point contact (``PhysicsConfig.contact_model``
    "point", the default): a hydroelastic contact's force is spread over a surface, and its
    moment about the pad's centre is not reported per point."""
    from pydrake.multibody.tree import JacobianWrtVariable

    if ph.physics.contact_model != "point":
        raise ValueError(f"statics budget: needs the physics plant's point contact, got contact_model "
                         f"'{ph.physics.contact_model}'")
    h, plant = ph.hand, ph.plant
    pctx = ph.plant_context(root_context)
    vi = np.asarray(ph.velocity_indices)
    theta = plant.GetPositions(pctx)[np.asarray(ph.position_indices)].reshape(h.N, h.K)
    a = np.asarray(ph.output(root_context, "contact_along_link_true"), float)
    X_WP = plant.EvalBodyPoseInWorld(pctx, ph.palm_body)
    c_W = np.array([X_WP @ p for p in kinematics.contacts(h, theta[None], a[None])[0]])  # pad centres

    def torque(body, p_W, f_W):  # generalized force on the finger joints of f_W applied at p_W on body
        p_B = plant.EvalBodyPoseInWorld(pctx, body).inverse() @ p_W
        J = plant.CalcJacobianTranslationalVelocity(pctx, JacobianWrtVariable.kV, body.body_frame(), p_B,
                                                    plant.world_frame(), plant.world_frame())
        return (J[:, vi].T @ f_W).reshape(h.N, h.K)

    T = np.asarray(ph.output(root_context, "tension"), float)
    zero = np.zeros((h.N, h.K))
    pad_contact, pad_moment, other = zero.copy(), zero.copy(), zero.copy()
    finger_of = {int(b.index()): i for i, b in enumerate(ph.last_links)}
    obj = int(ph.object_body.index())
    results = plant.get_contact_results_output_port().Eval(pctx)
    mass = ph.object_body.default_mass()
    com_W = plant.EvalBodyPoseInWorld(pctx, ph.object_body) @ ph.object_body.default_com()
    g_W = np.asarray(plant.gravity_field().gravity_vector())
    centre = c_W.mean(axis=0)
    # the object's load that the pads carry: its weight at its centre of mass and what the
    # other bodies touching it push on it, as a force and a moment about the pads' centroid
    load_F, load_M = mass * g_W, np.cross(com_W - centre, mass * g_W)
    for k in range(results.num_point_pair_contacts()):
        info = results.point_pair_contact_info(k)
        A, B = int(info.bodyA_index()), int(info.bodyB_index())
        if obj not in (A, B) or A == B:
            continue
        hand_body, sign = (B, 1.0) if A == obj else (A, -1.0)  # contact_force() acts on body B
        f_W = sign * np.asarray(info.contact_force())
        body = plant.get_body(info.bodyB_index() if A == obj else info.bodyA_index())
        p_W = np.asarray(info.contact_point())
        tau = torque(body, p_W, f_W)
        if hand_body in finger_of:
            pad_contact += tau
            pad_moment += tau - torque(body, c_W[finger_of[hand_body]], f_W)
        else:
            other += tau
            load_F, load_M = load_F - f_W, load_M + np.cross(p_W - centre, -f_W)  # (-f_W acts on the object)
    shares = object_load_shares(c_W - centre, load_F, load_M)
    object_weight = sum((torque(ph.last_links[i], c_W[i], shares[i]) for i in range(h.N)), zero.copy())
    tendon = (h.R.T @ T).reshape(h.N, h.K)
    spring = -h.stiffness * (theta - h.rest_angles)
    link_weight = plant.CalcGravityGeneralizedForces(pctx)[vi].reshape(h.N, h.K)
    residual = tendon + spring + link_weight + pad_contact + other
    return JointLoads(tendon, spring, link_weight, pad_contact, pad_moment, object_weight, other, residual)


def commanded_offsets(hand: HandModel, theta, a, tendon_command, loads: JointLoads, D2=None,
                      groups: dict[str, tuple[str, ...]] | None = None) -> dict[str, np.ndarray | None]:
    """The VLR's commanded equilibrium minus the plant's angles ``theta`` (N, K) [rad], with
    each group of unmodelled loads added as an external joint torque (module docstring).
    ``groups``: name -> load names (default: none, each of :data:`UNMODELLED`, and all of
    them). A group whose equilibrium Newton does not find is None."""
    if groups is None:
        groups = {"none": (), **{n: (n,) for n in UNMODELLED}, "all": UNMODELLED}
    theta = np.asarray(theta, float)
    out = {}
    for name, names in groups.items():
        unknown = sorted(set(names) - set(UNMODELLED))
        if unknown:
            raise ValueError(f"statics budget: unknown loads {unknown}; the unmodelled loads are {list(UNMODELLED)}")
        tau = loads.unmodelled(names) if names else None
        th, ok = commanded_equilibrium(hand, theta, a, tendon_command, D2=D2, external_torque=tau)
        out[name] = th - theta if ok else None
    return out
