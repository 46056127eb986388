"""How well does the VLR motion model (Eq. 9) predict the physics plant?

The filter can only be as right as its model. This command grasps an object with the physics
hand, applies tendon actions (random exploration like the identification's, or a sweep along
one direction), and compares, action by action, the object's true motion with what Gamma
predicts from the plant's *true* state (joint angles, contacts: ``theta_true``,
``contact_along_link_true``; tendon stretch from the equilibrium, Model O: exact):

- one step: Gamma started at the truth before the action, vs the true motion of that action
  (translation error [mm], rotation error [deg], and the ratio of predicted to true motion);
- carried: one model state started at the grasp's truth and moved through every action (how
  far the model drifts from the plant over a run, which is what a particle lives through);
- the joint angles of both against the plant's (model minus truth, N x K, degrees): how the
  model splits a tendon's pull between a finger's joints;
- bodies other than the last links touching the object (contacts the VLR does not have);
- the commanded equilibrium, as the filter sees the truth: the VLR's equilibrium under the
  motors' commands (stretch l - R theta, the filter's ``tendon_reference = "commanded"``),
  reached from the plant's angles with the object's shape held
  (:func:`vlr_drake.grasps.commanded_equilibrium`). Its angles minus the
  plant's (``commanded_offset_deg``) are how far the best hypothesis sits from the truth
  even with a perfect camera, and the motion between the commanded equilibria before and
  after an action, applied to the true pose, is that hypothesis' one-step prediction
  (``settled_one_step_error_mm`` / ``_deg``, settling excluded);
- the statics budget (:mod:`vlr_drake.physics.statics`, point contact): the plant's joint
  torques by load (tendon, spring, link weight, pad contacts and their moments about the
  pads' centres, the object's weight, other bodies' contacts) and the commanded offset with
  each load Eq. 9 lacks added (``loads_mNm``, ``commanded_offset_with_deg``;
  ``statics_budget`` over the actions);
- the kinematic check, which needs no model of forces: the object moved by the plant's true
  last links with it attached at link-fixed points, the pads' centres (the VLR's contacts)
  or the points where the pads touch the object (``kinematic_error_mm`` / ``_deg``, medians
  ``kinematic_error_*_median``); and the joints' motion, the plant's against the commanded
  equilibria's (``true_joint_motion_deg``, ``settled_joint_motion_deg``; per joint the
  least-squares slope ``joint_motion_slope``, 1 where the model moves a joint as far as the
  plant does), and both again with the links' and the object's weight following the angles
  (the object's true mass, shared over the contacts by its centre of mass:
  ``*_with_weights``);
- the rolling reference (:mod:`vlr_drake.rolling_reference`): the equilibria before and
  after the action with the pads rolling and the links' and the object's weight, from the
  plant's state (its tendons' stretch under the commands, the object's normals from where
  the pads touch it, its mass and centre of mass): ``rolling_offset_deg`` (its angles at
  rest minus the plant's), ``rolling_one_step_error_mm`` / ``_deg``,
  ``rolling_joint_motion_deg`` and the slopes ``joint_motion_slope_rolling``;
- for a sphere (the apple), the rolling reference again on the object's shape
  (``rolling_shaped_*``): the pads rolling over its curved surface (a ball on a ball,
  ``RollingState.curvature_radius``), the normals from its centre, and each pad's offset from
  the pad sphere that touches (``RollingState.pad_offset``; a side finger touches with its
  inner sphere, 6 mm out of its flexion plane). Measured on NH2 (20 random actions, seed 0):
  one-step 0.134 mm / 0.066 deg against the flat roll's 0.193 / 0.095, every joint's slope
  0.99-1.09 against 0.94-1.22 (the right finger's distal 1.01 against 1.22). On the Model O
  it locks the grasp (0.739 mm against the flat roll's 0.168 on the same apple, 20 random
  actions; 2.3-2.5 mm on a thumb-vs-fingers sweep): the side fingers are mirror images,
  and one direction of their attachments holds a round object only at second order, with
  an internal force no point contact gives
  (:func:`vlr_drake.rolling_reference.attachment_directions`). ``rolling_released_*``: the
  same with that direction released, 0.159 mm (0.02 mm on the sweep), the plant's motion of
  the apple; but the side fingers' distal joints are explained 0.69-0.72 of their motion
  against the flat roll's 0.94, as if the plant's friction held in part what the release
  frees;
- with ``--spring-profile SCALE ...``, each action predicted again by the rolling reference
  and by Eq. 9 with the model's thumb distal spring scaled (``spring_profile``): whether a
  model can see the spring in the object's motions. ``--squeeze`` adds the stiffness
  experiment's common-mode squeezes to the random actions;
- per joint, the fraction of the plant's motion each rolling prediction explains, action by
  action (``joint_motion_explained_rolling``, ``_shaped``: 1 - sum (plant - model)^2 / sum
  plant^2). A slope near 1 says a model moves a joint as far as the plant on average; this
  says whether it moves it when the plant does. With ``--hold SECONDS`` the commands are held
  after the last action and the plant's drift is reported (``hold``). ``--hand NH2`` (or
  NH1, NH3) grasps with a novel hand.

SAP's regularised friction lets a contact under a tangential load creep, more slowly at a
smaller time step, and the grasp relaxes through it along a mode no-slip contacts
forbid: the object turning about the thumb-fingers axis, one side finger's distal joint
flexing as the other's extends. ``--hand NH2 --actions 30 --span 0.001 --window 0.002
--hold 2`` (seed 0): at the default 1 ms step the curved roll explains 0.825 of the right
finger's distal motion (0.933-0.998 of the other joints'), one-step 0.140 mm; held 2 s
after the last action that joint drifts -0.46 deg and the left distal +0.41. With
``--physics time_step=0.00025``: 0.965 (0.987-0.998), 0.103 mm, and -0.37 / +0.32 deg in
2 s (docs/results.md, "The plant creeps").

The one-step and carried models start from the tendon stretch that holds the plant's angles
in the VLR's equilibrium (a least-squares split of the tensions: for the Model O's two side
fingers it is poorly determined and can differ from the plant's by several mm of stretch);
the commanded equilibrium uses the plant's own tendon state.

    python -m vlr_drake.physics.agreement --object apple --actions 40
    python -m vlr_drake.physics.agreement --object apple --direction -1 1 1 --step 0.5e-3 --actions 8
    python -m vlr_drake.physics.agreement --tendon-stiffness 20000 --span 0.3e-3 --window 0.8e-3
    python -m vlr_drake.physics.agreement --object toy_block --actions 20 --squeeze --spring-profile 0.85 1 1.15
    python -m vlr_drake.physics.agreement --hand NH2 --actions 30 --span 0.001 --window 0.002 --hold 2

Measured with it (apple, seed 0, 2000 N/m tendons): a thumb-vs-fingers pull (-1, 1, 1) moves
the apple 10.8 mm per mm in the plant and 12.1 mm in the model; past ~1 mm the apple touches
the thumb's proximal link and the plant stiffens (13.9 mm at 2 mm of pull, model 24.4 mm).

The commanded equilibrium's angles are off the plant's by 1.1-1.9 deg on average (20
actions, seed 0: toy block 1.11, apple 1.41, wine glass 1.94, gelatin box 1.31; the flat
screwdriver, a power grasp, has none). Without gravity in the plant (``--physics
gravity=0``) that is 0.39, 1.39, 0.20 and 0.10 deg: the objects' weight, which Eq. 9 does
not have, is most of it everywhere but on the apple. The statics budget splits it (40
actions): with the pads' friction moments, the links' weight and the object's weight
added, 0.03-0.08 deg remain on all four objects; on the apple the pad moments (10 mN m at
the thumb) and the links' weight matter most.

The pads roll (2026-11-28; toy block, 30 random actions, seed 0): attached at the
touching points the object follows the true links to 0.002 mm / 0.003 deg, at the pads'
centres only to 0.272 mm / 0.396 deg (apple, 20 actions: 0.015 against 0.157 mm; measured
again on 2026-12-06 with the least-squares fit of the points, observation.fit_pose). A
rolling pad's centre travels a pad radius times its rotation relative to the object, a
first-order motion that the VLR's pinned centre lacks; a VLR pinned at the touching points
instead predicts far worse (3-4 mm on the toy block's actions), because the rolling's
curvature, which a pin at either point gets wrong, shapes the equilibrium. Eq. 9's
commanded equilibria move the proximal joints 20-25% further than the plant (slopes
0.75-0.84, 0.74-1.12 distal). The weights are most of that: with the links' and the
object's weight following the angles (``joint_motion_slope_with_weights``; a weight held
as a constant torque misses its stiffness) the proximal slopes are 0.92-0.96 on the toy
block and 1.03-1.05 on the apple, yet the POM's prediction gets worse (0.247 against 0.148
mm on the toy block), because with the pads' centres pinned it had relied on the two errors
cancelling. The filter needs both, the weights and the rolling, or neither. With both
(the rolling reference; 20 random actions, seed 0) the angles at rest sit 0.02-0.41 deg from
the plant's instead of 1.1-1.9, every joint moves as the plant's (slopes 0.93-1.14), and the
one-step error is toy block 0.089 mm / 0.048 deg (Eq. 9: 0.162 / 0.277), apple 0.168 / 0.106
(0.174 / 0.210), wine glass 0.137 / 0.064 (0.302 / 0.154) and gelatin box 0.138 / 0.039
(0.111 / 0.155).

Whether the spring shows (toy block, ``--squeeze --spring-profile 0.7 0.85 1 1.15 1.3``, 20
actions, seed 0; sums of squares over 17 actions in units of 0.05 mm and 0.05 deg): the
rolling reference 3121 / 352 / 45 / 168 / 365, Eq. 9 11320 / 2682 / 2275 / 2480 / 2736.
To the rolling model the plant's own spring stands out (a likelihood of that width would
put about 1% on it from these 17 actions); to Eq. 9 the springs from 0.85x to 1.3x are
within 20% of each other. Without the squeezes the rolling model's profile is flat too
(137 at 1x, 140 at 0.85x, 159 at 1.15x): the squeezes load the spring.

``--physics KEY=VALUE`` overrides a setting of the physics plant
(:class:`vlr_drake.systems.physics_plant.PhysicsConfig`), e.g. ``gravity=0`` (no object
weight, which the VLR lacks) or ``settle_object_speed=1e-4`` (a stricter settle test).
"""

from __future__ import annotations

import argparse
import copy
import json
import time
from pathlib import Path

import numpy as np

from vlr_drake import filter as pf
from vlr_drake import kinematics, motion, observation
from vlr_drake.entry import check_output, count, path_text, plain, run
from vlr_drake.grasps import commanded_equilibrium
from vlr_drake.hand import HandSpec, hand_by_name, model_o
from vlr_drake.identify import EXPLORATION, default_squeeze
from vlr_drake.kinematics import is_count, is_number
from vlr_drake.physics.statics import LOADS, commanded_offsets, plant_loads
from vlr_drake.systems.physics_plant import PhysicsConfig

__all__ = ["run_agreement", "physics_overrides", "main"]


def _pose(adapter):
    X = adapter.ph.output(adapter.root, "X_PO_true")
    return X.rotation().matrix(), X.translation().copy()


class _ModelState:
    """One VLR hypothesis (angles, contacts, tendon stretch, attachment p_O) at the plant's
    truth, moved by Gamma; its POM pose is Lambda of its contacts."""

    def __init__(self, h, theta, a, R, t):
        self.h, self.a = h, np.asarray(a, float)[None]
        eq = motion.equilibrium(h, np.asarray(theta, float)[None], a=self.a)
        if not eq.ok[0]:  # (it had started from a zero stretch, silently)
            raise RuntimeError("agreement: the VLR finds no tendon state that holds the plant's grasp (no "
                               "equilibrium at its true angles and contacts); nothing to compare the plant with")
        # the equilibrium's angles: the plant's (the Model O's), or settled to the nearest
        # equilibrium on a hand with more joints than tendons and contacts
        self.theta, self.stretch = eq.theta, eq.stretch
        self.p_O = observation.attach(kinematics.contacts(h, self.theta, self.a), R[None], t[None])

    def move(self, dl) -> bool:
        h = self.h
        res = motion.move(h, self.theta, dl, a=self.a, D2=motion.contact_distances_sq(h, self.p_O),
                          stretch=self.stretch, max_substeps=16)
        if res.ok[0]:
            self.theta, self.stretch = res.theta, res.stretch
        return bool(res.ok[0])

    def pose(self):
        R, t, _ = observation.pom_pose(self.p_O, kinematics.contacts(self.h, self.theta, self.a))
        return R[0], t[0]


def _last_link_poses(adapter) -> list:
    """The last links' poses in the palm frame P (RigidTransforms)."""
    plant, ctx = adapter.ph.plant, adapter.ph.plant_context(adapter.root)
    X_PW = plant.EvalBodyPoseInWorld(ctx, adapter.ph.palm_body).inverse()
    return [X_PW @ plant.EvalBodyPoseInWorld(ctx, b) for b in adapter.ph.last_links]


def _kinematic_prediction(points, X_before, X_after, R, t):
    """The object's pose after an action if it were attached to ``points`` (N, 3) in P, each
    fixed on its last link, whose poses before and after are ``X_before`` / ``X_after``: the
    object attached to the points at its true pose (R, t) before, then fitted to where the
    links carry them (Eq. 5's attachment, and the least-squares pose fit: the points are not
    rigid, and the exact fit of three of them had depended on the fingers' order). Returns
    (R_pred, t_pred)."""
    moved = np.array([(X_after[i] @ X_before[i].inverse()).multiply(points[i]) for i in range(len(points))])
    p_O = observation.attach(points[None], R[None], t[None])
    R1, t1 = observation.fit_pose(p_O, moved[None])
    return R1[0], t1[0]


def _object_com(adapter) -> np.ndarray:
    """The object's centre of mass in the palm frame (3,) [m]."""
    plant, ctx = adapter.ph.plant, adapter.ph.plant_context(adapter.root)
    body = adapter.ph.object_body
    X_PW = plant.EvalBodyPoseInWorld(ctx, adapter.ph.palm_body).inverse()
    return np.asarray(X_PW @ (plant.EvalBodyPoseInWorld(ctx, body) @ body.default_com()), float)


def _rolling_prediction(h, truth, touching, l_before, dl, R, t, gravity, com, sphere=None, release_weak=False):
    """The rolling reference (:mod:`vlr_drake.rolling_reference`) from the plant's state:
    its equilibria before and after ``dl`` with the pads rolling and the links' and the
    object's weight, the object's normals from the pads' touching points (``touching``,
    (N, 3) in P), the tendons' stretch of the commands ``l_before``. ``sphere`` (centre (3,)
    in P, radius) [m]: the object's shape as well, a sphere (``rolling_shaped``): the normals
    from its centre through the touching points, the pad spheres rolling over its curved
    surface, and each pad's offset from the sphere that touches to its centre line;
    ``release_weak``: with the attachment directions the sphere holds only at second order
    released (``solve_rolling``'s ``release_weak``).
    Returns (offset before [rad] (N, K), (R_pred, t_pred), joint motion [rad] (N, K)), or
    three Nones where IPOPT finds no equilibrium."""
    from vlr_drake.rolling_reference import RollingSolveError, RollingState, solve_rolling

    shape = {}
    normals = truth["contacts"] - touching
    if sphere is not None:
        centre, radius = sphere
        normals = (touching - centre) / np.linalg.norm(touching - centre, axis=1, keepdims=True)
        touching_sphere = touching + h.pad_radius[:, None] * normals
        shape = {"curvature_radius": np.full(h.N, float(radius)), "pad_offset": truth["contacts"] - touching_sphere}
    state = RollingState(truth["theta"], truth["a"], R, t, normals,
                         np.asarray(l_before, float) - h.tendon_travel(truth["theta"]),
                         truth["object_mass"], com, **shape)
    try:
        e0 = solve_rolling(h, state, None, gravity=gravity, release_weak=release_weak)
        e1 = solve_rolling(h, state, dl, gravity=gravity, release_weak=release_weak)
    except RollingSolveError:
        return None, None, None
    dR = e1.R @ e0.R.T
    return e0.theta - truth["theta"], (dR @ R, dR @ (t - e0.t) + e1.t), e1.theta - e0.theta


def _settled_prediction(h, truth, l_before, dl, R, t, gravity=None, object_load=None):
    """Commanded equilibria before and after ``dl`` from the plant's state (``truth``), and
    the predicted POM pose: their relative motion applied to the true pose (R, t). Returns
    (offset before [rad] (N, K) or None, (R_pred, t_pred) or None, the equilibria's joint
    motion th_after - th_before [rad] (N, K) or None). ``gravity`` / ``object_load``: the
    weights following the angles (:func:`vlr_drake.grasps.commanded_equilibrium`)."""
    a = truth["a"]
    p = kinematics.contacts(h, truth["theta"][None], a[None])
    D2 = motion.contact_distances_sq(h, p)[0]
    weights = {"gravity": gravity, "object_load": object_load}
    th0, ok0 = commanded_equilibrium(h, truth["theta"], a, l_before, D2=D2, **weights)
    if not ok0:
        return None, None, None
    th1, ok1 = commanded_equilibrium(h, th0, a, l_before + dl, D2=D2, **weights)
    if not ok1:
        return th0 - truth["theta"], None, None
    p_O = observation.attach(p, R[None], t[None])
    R0, t0, _ = observation.pom_pose(p_O, kinematics.contacts(h, th0[None], a[None]))
    R1, t1, _ = observation.pom_pose(p_O, kinematics.contacts(h, th1[None], a[None]))
    dR = R1[0] @ R0[0].T
    return th0 - truth["theta"], (dR @ R, dR @ (t - t0[0]) + t1[0]), th1 - th0


def physics_overrides(items: list[str]) -> PhysicsConfig:
    """A PhysicsConfig with ``KEY=VALUE`` overrides of its numeric fields (e.g.
    ``gravity=0``); an unknown or non-numeric key is named."""
    from vlr_drake.scenario import config_overrides

    return config_overrides(PhysicsConfig(), items, "--physics", kinds=(float, int))


def _other_contacts(adapter) -> list[str]:
    """Names of bodies other than the last links that touch the object."""
    plant, ctx = adapter.ph.plant, adapter.ph.plant_context(adapter.root)
    results = plant.get_contact_results_output_port().Eval(ctx)
    obj = int(adapter.ph.object_body.index())
    last = {int(b.index()) for b in adapter.ph.last_links}
    names = set()
    for k in range(results.num_point_pair_contacts()):
        info = results.point_pair_contact_info(k)
        a, b = int(info.bodyA_index()), int(info.bodyB_index())
        other = b if a == obj else a if b == obj else None
        if other is not None and other not in last:
            names.add(plant.get_body(info.bodyA_index() if other == a else info.bodyB_index()).name())
    return sorted(names)


def run_agreement(
    object_name: str = "apple",
    *,
    hand: HandSpec | None = None,
    actions: int = 40,
    seed: int = 0,
    span: float = EXPLORATION["physics"][0],
    window: float = EXPLORATION["physics"][1],
    direction=None,
    step: float = 0.5e-3,
    physics: PhysicsConfig | None = None,
    spring_scales=None,
    spring: tuple[int, int] | None = None,
    squeeze: tuple[float, float] | None = None,
    hold: float = 0.0,
) -> dict:
    """Grasp ``object_name`` with the physics hand (``hand``: the Model O by default) and
    compare ``actions`` actions with Gamma's predictions (module docstring). Actions: random,
    uniform in +-``span`` per tendon within +-``window`` of the grasp (seeded), or, with
    ``direction`` (N,), ``step`` [m] times its unit vector each time (a sweep). ``physics``:
    the plant's settings (default: PhysicsConfig()). ``spring_scales``: a profile of one
    spring, ``spring`` (finger, joint; default the first finger's last joint, the Model O's
    thumb's distal spring): each action predicted again by the rolling reference and by
    Eq. 9's commanded equilibria with the model's spring scaled by each factor
    (``spring_profile``; the plant keeps its own). ``squeeze``: (squeeze, window) [m] of
    common-mode pulls on top of the random actions, as the stiffness experiment's
    (:func:`vlr_drake.identify.default_squeeze`); default none. ``hold`` [s]: after the last
    action, hold the commands that long and report how far the plant drifts meanwhile
    (``hold``: joints [deg], the object [mm, deg]), which an equilibrium model has no room
    for: SAP's regularised friction lets a contact under a tangential load creep, more
    slowly at a smaller time step (``PhysicsConfig.time_step``)."""
    from vlr_drake.identify import Exploration, IdentifyOptions, RunStopped
    from vlr_drake.physics_identify import PhysicsAdapter

    if not is_count(actions, 1):  # (2.5 had failed in range() after the grasp)
        raise ValueError(f"'actions' must be an integer >= 1, got {actions!r}")
    if not (is_number(step) and np.isfinite(step)):  # (NaN had been named as 'dl' after the grasp)
        raise ValueError(f"'step' must be a finite number [m], got {step!r}")
    if not (np.isfinite(hold) and hold >= 0):
        raise ValueError(f"'hold' must be a duration >= 0 [s], got {hold}")
    spec = hand if hand is not None else model_o()
    h = spec.model()
    profile = _profile_hands(spec, spring_scales, spring)
    if direction is not None:
        direction = np.asarray(direction, float).reshape(-1)
        if direction.shape != (h.N,) or not np.all(np.isfinite(direction)) or not np.linalg.norm(direction) > 0:
            raise ValueError(f"'direction' must be a finite, nonzero vector of {h.N} tendon pulls, got "
                             f"{direction.tolist()}")
        direction = direction / np.linalg.norm(direction)
        travel = float(np.min(np.diff(h.tendon_range, axis=1)))
        if abs(step) >= travel:  # (0.5 meant as mm had pulled 0.5 m, and the apple fell out of the hand)
            raise ValueError(f"'step' {step:g} m is a tendon's whole travel ({travel * 1e3:g} mm) or more; the step "
                             "is in metres: was it given in millimetres?")
    opts = IdentifyOptions(plant="physics", object=object_name, seed=seed, action_range=span, window=window).validate()
    t_start = time.perf_counter()
    adapter = PhysicsAdapter(opts, spec, np.random.default_rng(seed), physics)
    adapter.start(pf.PriorConfig())
    sq = {} if squeeze is None else {"squeeze": float(squeeze[0]), "squeeze_window": float(squeeze[1])}
    explore = Exploration(adapter.tendon_command(), h.tendon_range, opts.action_range, opts.window,
                          np.random.default_rng(seed + 2), **sq)
    truth = adapter.truth()
    R, t = _pose(adapter)
    carried = _ModelState(h, truth["theta"], truth["a"], R, t)  # lives through every action
    carried_ok = True
    rows = []
    stopped = None  # why the actions stopped early (the object fell), None where all ran
    timing = {"physics": 0.0, "render": 0.0, "detect": 0.0}
    budget = adapter.physics.contact_model == "point"  # plant_loads needs point contact
    gravity = np.asarray(adapter.physics.gravity_in_palm(), float)
    for _ in range(actions):
        dl = step * direction if direction is not None else explore.next_action()
        try:  # restarted at the truth
            one = _ModelState(h, truth["theta"], truth["a"], R, t)
            one_ok = one.move(dl)
        except RuntimeError:  # no equilibrium at this true state: this action's model failure (it had
            one, one_ok = None, False  # ended the run in a traceback, the actions before it lost: a review)
        carried_ok = carried_ok and carried.move(dl)
        offset, settled, settled_motion = _settled_prediction(h, truth, adapter.tendon_command(), dl, R, t)
        # the same with the links' and the object's weight following the angles (the object's
        # true mass, shared over the contacts by its centre of mass)
        _, settled_w, settled_motion_w = _settled_prediction(h, truth, adapter.tendon_command(), dl, R, t,
                                                             gravity=gravity, object_load=truth["object_load"])
        # link-fixed points for the kinematic check: the pads' centres (the VLR's contacts)
        # and the points where the pads touch the object
        X_links = _last_link_poses(adapter)
        fixed = {"centre": truth["contacts"],
                 "touching": np.asarray(adapter.ph.output(adapter.root, "contacts_true"), float).reshape(h.N, 3)}
        # the rolling reference: the pads rolling and the weights, from the plant's state
        com = _object_com(adapter)
        rolling_offset, rolling, rolling_motion = _rolling_prediction(
            h, truth, fixed["touching"], adapter.tendon_command(), dl, R, t, gravity, com)
        # the same with the object's shape where it is a sphere (centred at its centre of mass)
        sphere = (com, adapter.obj.size[0]) if adapter.obj.shape == "sphere" else None
        shaped_offset, shaped, shaped_motion = (_rolling_prediction(
            h, truth, fixed["touching"], adapter.tendon_command(), dl, R, t, gravity, com, sphere=sphere)
            if sphere is not None else (None, None, None))
        released_offset, released, released_motion = (_rolling_prediction(
            h, truth, fixed["touching"], adapter.tendon_command(), dl, R, t, gravity, com, sphere=sphere,
            release_weak=True) if sphere is not None else (None, None, None))
        profiled = [(_rolling_prediction(hs, truth, fixed["touching"], adapter.tendon_command(), dl, R, t, gravity, com)[1],
                     _settled_prediction(hs, truth, adapter.tendon_command(), dl, R, t)[1]) for hs in profile["hands"]]
        loads = with_loads = None
        if budget:  # the statics budget of the state the commanded equilibrium starts from
            loads = plant_loads(adapter.ph, adapter.root)
            D2 = motion.contact_distances_sq(h, kinematics.contacts(h, truth["theta"][None], truth["a"][None]))[0]
            with_loads = commanded_offsets(h, truth["theta"], truth["a"], adapter.tendon_command(), loads, D2=D2)
        try:
            adapter.act(dl, timing)
        except RunStopped as e:  # the object fell: the actions compared so far are reported
            if not rows:
                raise ValueError(f"agreement: action 1: {e}") from None
            stopped = f"action {len(rows) + 1}: {e}"
            break
        explore.commit(dl)
        R1, t1 = _pose(adapter)
        truth_after = adapter.truth()
        true_motion = truth_after["theta"] - truth["theta"]
        X_links1 = _last_link_poses(adapter)
        kinematic = {name: _pose_error(_kinematic_prediction(points, X_links, X_links1, R, t), R1, t1)
                     for name, points in fixed.items()}
        truth = truth_after
        row = {"action_mm": (dl * 1e3).tolist(), "true_motion_mm": float(np.linalg.norm(t1 - t) * 1e3),
               "true_rotation_deg": float(np.rad2deg(observation.rotation_angle(R1[None], R[None])[0])),
               "other_contacts": _other_contacts(adapter),
               "one_step_error_mm": None, "one_step_error_deg": None, "predicted_motion_mm": None,
               "carried_error_mm": None, "carried_error_deg": None,
               "one_step_joint_error_deg": None, "carried_joint_error_deg": None,
               "commanded_offset_deg": None if offset is None else np.rad2deg(offset).tolist(),
               "settled_one_step_error_mm": None, "settled_one_step_error_deg": None,
               # the plant's joint motion and the commanded equilibria's [deg] (N, K)
               "true_joint_motion_deg": np.rad2deg(true_motion).tolist(),
               "settled_joint_motion_deg": None if settled_motion is None else np.rad2deg(settled_motion).tolist(),
               "settled_joint_motion_with_weights_deg": (None if settled_motion_w is None
                                                         else np.rad2deg(settled_motion_w).tolist()),
               "settled_one_step_error_with_weights_mm": None, "settled_one_step_error_with_weights_deg": None,
               # the rolling reference: its angles at rest minus the plant's, its joint motion
               # [deg] (N, K) and its one-step POM error
               "rolling_offset_deg": None if rolling_offset is None else np.rad2deg(rolling_offset).tolist(),
               "rolling_joint_motion_deg": None if rolling_motion is None else np.rad2deg(rolling_motion).tolist(),
               "rolling_one_step_error_mm": None, "rolling_one_step_error_deg": None,
               # the same with the object's shape (a sphere only: rolling_shaped)
               "rolling_shaped_offset_deg": None if shaped_offset is None else np.rad2deg(shaped_offset).tolist(),
               "rolling_shaped_joint_motion_deg": (None if shaped_motion is None
                                                   else np.rad2deg(shaped_motion).tolist()),
               "rolling_shaped_one_step_error_mm": None, "rolling_shaped_one_step_error_deg": None,
               # the same with its weakly held attachment directions released (rolling_released)
               "rolling_released_offset_deg": (None if released_offset is None
                                               else np.rad2deg(released_offset).tolist()),
               "rolling_released_joint_motion_deg": (None if released_motion is None
                                                     else np.rad2deg(released_motion).tolist()),
               "rolling_released_one_step_error_mm": None, "rolling_released_one_step_error_deg": None,
               # the object moved with the plant's true links, attached at link-fixed
               # points: the pads' centres (the VLR) or their touching points [mm], [deg]
               "kinematic_error_mm": {k: v[0] for k, v in kinematic.items()},
               "kinematic_error_deg": {k: v[1] for k, v in kinematic.items()},
               # the statics budget (vlr_drake.physics.statics): joint torques by load [mN m],
               # and the commanded offset with each unmodelled load added [deg]
               "loads_mNm": None if loads is None else loads.as_dict(1e3),
               "commanded_offset_with_deg": None if with_loads is None else {
                   k: None if v is None else np.rad2deg(v).tolist() for k, v in with_loads.items()}}
        if profile["hands"]:
            row["spring_profile"] = {k: [] for k in ("rolling_mm", "rolling_deg", "eq9_mm", "eq9_deg")}
            for preds in profiled:
                for name, pred in zip(("rolling", "eq9"), preds, strict=True):
                    err = (None, None) if pred is None else _pose_error(pred, R1, t1)
                    row["spring_profile"][name + "_mm"].append(err[0])
                    row["spring_profile"][name + "_deg"].append(err[1])
        for key, pred in (("settled_one_step_error", settled), ("settled_one_step_error_with_weights", settled_w),
                          ("rolling_one_step_error", rolling), ("rolling_shaped_one_step_error", shaped),
                          ("rolling_released_one_step_error", released)):
            if pred is not None:
                row[key + "_mm"], row[key + "_deg"] = _pose_error(pred, R1, t1)
        if one_ok:
            Rp, tp = one.pose()
            dp, ang = observation.pose_error(Rp[None], tp[None], R1[None], t1[None])
            row.update(one_step_error_mm=float(dp[0] * 1e3), one_step_error_deg=float(np.rad2deg(ang[0])),
                       predicted_motion_mm=float(np.linalg.norm(tp - t) * 1e3),
                       one_step_joint_error_deg=np.rad2deg(one.theta[0] - truth["theta"]).tolist())
        if carried_ok:
            Rc, tc = carried.pose()
            dp, ang = observation.pose_error(Rc[None], tc[None], R1[None], t1[None])
            row.update(carried_error_mm=float(dp[0] * 1e3), carried_error_deg=float(np.rad2deg(ang[0])),
                       carried_joint_error_deg=np.rad2deg(carried.theta[0] - truth["theta"]).tolist())
        rows.append(row)
        R, t = R1, t1
    held = None
    if hold > 0 and stopped is None:  # the commands held: how far the plant drifts without an action
        theta0 = truth["theta"]
        adapter.sim.AdvanceTo(adapter.root.get_time() + hold)
        R1, t1 = _pose(adapter)
        theta1 = adapter.truth()["theta"]
        turn = float(np.rad2deg(observation.rotation_angle(R1[None], R[None])[0]))
        held = {"seconds": float(hold), "joint_drift_deg": np.rad2deg(theta1 - theta0).tolist(),
                "object_drift_mm": float(np.linalg.norm(t1 - t) * 1e3), "object_turn_deg": turn,
                "joint_drift_deg_per_s_max": float(np.rad2deg(np.abs(theta1 - theta0).max()) / hold)}
    ok = [r for r in rows if r["one_step_error_mm"] is not None]
    moved = [r for r in ok if r["true_motion_mm"] > 0.05]
    carried_errors = [r["carried_error_mm"] for r in rows if r["carried_error_mm"] is not None]
    offsets = [np.abs(r["commanded_offset_deg"]) for r in rows if r["commanded_offset_deg"] is not None]
    settled = [r for r in rows if r["settled_one_step_error_mm"] is not None]
    return {
        "object": object_name,
        "hand": spec.name,
        "tendon_stiffness": float(h.kappa[0]),
        "seed": seed,
        "actions": rows,
        "stopped": stopped,
        "model_failures": len(rows) - len(ok),
        "one_step_error_mm_median": float(np.median([r["one_step_error_mm"] for r in ok])) if ok else None,
        "one_step_error_deg_median": float(np.median([r["one_step_error_deg"] for r in ok])) if ok else None,
        "motion_ratio_median": (float(np.median([r["predicted_motion_mm"] / r["true_motion_mm"] for r in moved]))
                                if moved else None),
        "carried_error_mm_max": max(carried_errors) if carried_errors else None,
        "carried_model_failed": not carried_ok,
        "actions_with_other_contacts": int(sum(bool(r["other_contacts"]) for r in rows)),
        "gravity": float(adapter.physics.gravity),
        # the commanded equilibrium (module docstring): mean |offset| per joint (N, K) and
        # over all joints [deg], the failures, and the settled one-step errors' medians
        "commanded_offset_deg_mean_per_joint": np.mean(offsets, axis=0).tolist() if offsets else None,
        "commanded_offset_deg_mean": float(np.mean(offsets)) if offsets else None,
        "commanded_failures": len(rows) - len(settled),
        "settled_one_step_error_mm_median": (float(np.median([r["settled_one_step_error_mm"] for r in settled]))
                                             if settled else None),
        "settled_one_step_error_deg_median": (float(np.median([r["settled_one_step_error_deg"] for r in settled]))
                                              if settled else None),
        "statics_budget": _budget_summary(rows) if budget else None,
        # the kinematic check's medians over the actions, per attachment point
        "kinematic_error_mm_median": {k: float(np.median([r["kinematic_error_mm"][k] for r in rows])) for k in fixed},
        "kinematic_error_deg_median": {k: float(np.median([r["kinematic_error_deg"][k] for r in rows])) for k in fixed},
        # per joint (N, K): least-squares slope of the plant's joint motion on the commanded
        # equilibria's (1 = the model moves the joint as much as the plant does)
        "joint_motion_slope": _slopes(rows, "settled_joint_motion_deg"),
        # the same with the weights following the angles, and that prediction's POM error
        "joint_motion_slope_with_weights": _slopes(rows, "settled_joint_motion_with_weights_deg"),
        "settled_one_step_error_with_weights_mm_median": _median(rows, "settled_one_step_error_with_weights_mm"),
        "settled_one_step_error_with_weights_deg_median": _median(rows, "settled_one_step_error_with_weights_deg"),
        # the rolling reference's (vlr_drake.rolling_reference): slopes, one-step error, the
        # mean |offset| of its angles at rest from the plant's [deg], and its failures
        "joint_motion_slope_rolling": _slopes(rows, "rolling_joint_motion_deg"),
        "rolling_one_step_error_mm_median": _median(rows, "rolling_one_step_error_mm"),
        "rolling_one_step_error_deg_median": _median(rows, "rolling_one_step_error_deg"),
        "rolling_offset_deg_mean": (float(np.mean([np.abs(r["rolling_offset_deg"]) for r in rows
                                                   if r["rolling_offset_deg"] is not None]))
                                    if any(r["rolling_offset_deg"] is not None for r in rows) else None),
        "rolling_failures": sum(r["rolling_one_step_error_mm"] is None for r in rows),
        # with the object's shape, a sphere's (None for other shapes)
        "joint_motion_slope_rolling_shaped": _slopes(rows, "rolling_shaped_joint_motion_deg"),
        "joint_motion_slope_rolling_released": _slopes(rows, "rolling_released_joint_motion_deg"),
        # per joint (N, K): the fraction of the plant's joint motion each rolling prediction
        # explains, action by action (_explained)
        "joint_motion_explained_rolling": _explained(rows, "rolling_joint_motion_deg"),
        "joint_motion_explained_rolling_shaped": _explained(rows, "rolling_shaped_joint_motion_deg"),
        "joint_motion_explained_rolling_released": _explained(rows, "rolling_released_joint_motion_deg"),
        # the drift while the commands were held after the last action (None: no hold)
        "hold": held,
        "rolling_shaped_one_step_error_mm_median": _median(rows, "rolling_shaped_one_step_error_mm"),
        "rolling_shaped_one_step_error_deg_median": _median(rows, "rolling_shaped_one_step_error_deg"),
        "rolling_released_one_step_error_mm_median": _median(rows, "rolling_released_one_step_error_mm"),
        "rolling_released_one_step_error_deg_median": _median(rows, "rolling_released_one_step_error_deg"),
        "spring_profile": _profile_summary(rows, profile),
        "wall_s": time.perf_counter() - t_start,
    }


#: Units of the spring profile's sum of squares: the rolling reference's one-step error on
#: the toy block is about this much (docs/results.md, "The pads roll").
PROFILE_UNITS = (0.05, 0.05)  # [mm], [deg]


def _pose_error(pred, R1, t1) -> tuple[float, float]:
    """(mm, deg) between a predicted pose (R, t) and the true one."""
    dp, ang = observation.pose_error(pred[0][None], pred[1][None], R1[None], t1[None])
    return float(dp[0] * 1e3), float(np.rad2deg(ang[0]))


def _profile_hands(spec: HandSpec, scales, spring) -> dict:
    """The hand models of a spring profile: ``spring`` (finger, joint) scaled by each of
    ``scales`` (none: no profile). Bad input is named."""
    if scales is None:
        return {"scales": [], "hands": [], "spring": None}
    scales = [float(x) for x in np.atleast_1d(np.asarray(scales, float))]
    if not scales or not all(np.isfinite(x) and x > 0 for x in scales):
        raise ValueError(f"'spring_scales' must be positive numbers, got {scales}")
    fi, j = (0, len(spec.fingers[0].stiffness) - 1) if spring is None else (int(spring[0]), int(spring[1]))
    if not (0 <= fi < len(spec.fingers) and 0 <= j < len(spec.fingers[fi].stiffness)):
        raise ValueError(f"'spring' must name a finger and joint of the hand, got {spring}")
    hands = []
    for x in scales:
        scaled = copy.deepcopy(spec)
        k = list(scaled.fingers[fi].stiffness)
        k[j] *= x
        scaled.fingers[fi].stiffness = k
        hands.append(scaled.validate().model())
    return {"scales": scales, "hands": hands, "spring": [fi, j]}


def _profile_summary(rows: list[dict], profile: dict) -> dict | None:
    """Per scale, the median one-step errors of both models and the sum over the actions
    (those where every scale solved for both) of (mm / 0.05)^2 + (deg / 0.05)^2."""
    if not profile["hands"]:
        return None
    full = [r["spring_profile"] for r in rows
            if all(x is not None for v in r["spring_profile"].values() for x in v)]
    out = {"spring": profile["spring"], "scales": profile["scales"], "actions": len(full)}
    for name in ("rolling", "eq9"):  # (reshaped to the scales' count: an empty list of actions too)
        mm = np.array([p[name + "_mm"] for p in full]).reshape(len(full), len(profile["scales"]))
        deg = np.array([p[name + "_deg"] for p in full]).reshape(len(full), len(profile["scales"]))
        out[name + "_mm_median"] = np.median(mm, axis=0).tolist() if full else None
        out[name + "_deg_median"] = np.median(deg, axis=0).tolist() if full else None
        out[name + "_sum_sq"] = (((mm / PROFILE_UNITS[0]) ** 2 + (deg / PROFILE_UNITS[1]) ** 2).sum(axis=0).tolist()
                                 if full else None)
    return out


def _median(rows: list[dict], key: str) -> float | None:
    """Median of ``key`` over the rows that have it, None if none has."""
    got = [r[key] for r in rows if r[key] is not None]
    return float(np.median(got)) if got else None


def _motions(rows: list[dict], key: str) -> tuple[np.ndarray, np.ndarray] | None:
    """(the model's joint motion ``key``, the plant's ``true_joint_motion_deg``), (M, N, K)
    each, over the M rows that have the model's; None where none has."""
    rows = [r for r in rows if r[key] is not None]
    if not rows:
        return None
    return np.array([r[key] for r in rows]), np.array([r["true_joint_motion_deg"] for r in rows])


def _slopes(rows: list[dict], key: str) -> list | None:
    """Per joint, the least-squares slope of ``true_joint_motion_deg`` on the model's joint
    motion ``key`` over the rows that have it (N, K), None where the model never moved it."""
    pair = _motions(rows, key)
    if pair is None:
        return None
    pred, true = pair
    den = (pred * pred).sum(0)
    slope = np.where(den > 0, (pred * true).sum(0) / np.where(den > 0, den, 1.0), np.nan)
    return [[None if not np.isfinite(x) else float(x) for x in row] for row in slope]


def _explained(rows: list[dict], key: str) -> list | None:
    """Per joint, the fraction of the plant's joint motion (``true_joint_motion_deg``, its sum
    of squares over the rows) that the model's motion ``key`` explains, 1 - sum (true -
    model)^2 / sum true^2 (N, K): 1 for a model that moves the joint as the plant does, action
    by action. Unlike the slope, which only says how far the model moves a joint on average,
    it falls where the plant moves a joint in ways the model does not (e.g. a slow creep that
    carries one action's motion into the next). None where the plant never moved the joint."""
    pair = _motions(rows, key)
    if pair is None:
        return None
    pred, true = pair
    den = (true * true).sum(0)
    frac = np.where(den > 0, 1.0 - ((true - pred) ** 2).sum(0) / np.where(den > 0, den, 1.0), np.nan)
    return [[None if not np.isfinite(x) else float(x) for x in row] for row in frac]


def _budget_summary(rows: list[dict]) -> dict:
    """Over the actions: each load's mean joint torque (N, K) [mN m], the largest |residual|
    [mN m], and per group of unmodelled loads the mean |commanded offset| [deg] and its
    failures (vlr_drake.physics.statics)."""
    groups = rows[0]["commanded_offset_with_deg"].keys()
    out = {"loads_mNm_mean": {k: np.mean([r["loads_mNm"][k] for r in rows], axis=0).tolist() for k in LOADS},
           "residual_mNm_max": float(np.max([np.abs(r["loads_mNm"]["residual"]) for r in rows])),
           "commanded_offset_deg_mean_with": {}, "failures_with": {}}
    for g in groups:
        got = [np.abs(r["commanded_offset_with_deg"][g]) for r in rows if r["commanded_offset_with_deg"][g] is not None]
        out["commanded_offset_deg_mean_with"][g] = float(np.mean(got)) if got else None
        out["failures_with"][g] = len(rows) - len(got)
    return out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(prog="python -m vlr_drake.physics.agreement", description=plain(__doc__),
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--object", default="apple", help="object preset (default apple)")
    ap.add_argument("--hand", default="model_o",
                    help="the physics hand: model_o (default) or a novel hand, NH1, NH2 or NH3")
    ap.add_argument("--actions", type=count(1), default=40, help="number of actions (default 40)")
    ap.add_argument("--seed", type=count(0), default=0, help="seed of the random actions (default 0)")
    ap.add_argument("--span", type=float, default=EXPLORATION["physics"][0],
                    help="random actions: +-span per tendon [m] (default: the identification's, %(default)s)")
    ap.add_argument("--window", type=float, default=EXPLORATION["physics"][1],
                    help="random actions: window around the grasp [m] (default: the identification's, %(default)s)")
    ap.add_argument("--direction", type=float, nargs="+", default=None,
                    help="sweep instead: tendon pulls of one direction (N numbers, normalised)")
    ap.add_argument("--step", type=float, default=0.5e-3, help="sweep step along --direction [m]")
    ap.add_argument("--tendon-stiffness", type=float, default=None,
                    help="tendon stiffness of every finger [N/m] (default: the Model O spec's)")
    # extend: a second --physics had replaced the first's settings without a word
    ap.add_argument("--physics", nargs="+", action="extend", default=[], metavar="KEY=VALUE",
                    help="physics plant settings, e.g. gravity=0 settle_object_speed=1e-4; repeatable")
    ap.add_argument("--spring-profile", type=float, nargs="+", default=None, metavar="SCALE",
                    help="predict each action again with the thumb's distal spring scaled by each factor, "
                         "e.g. 0.85 1 1.15 (the rolling reference and Eq. 9)")
    ap.add_argument("--squeeze", action="store_true",
                    help="add the stiffness experiment's common-mode squeezes to the random actions")
    ap.add_argument("--hold", type=float, default=0.0, metavar="SECONDS",
                    help="after the last action, hold the commands this long and report the plant's drift")
    ap.add_argument("--json", type=path_text, default=None, help="write the result as JSON to this path")
    args = ap.parse_args(argv)
    if not (np.isfinite(args.hold) and args.hold >= 0):
        ap.error(f"--hold: a duration >= 0 [s], got {args.hold}")
    check_output("--json", args.json)
    try:
        physics = physics_overrides(args.physics)
    except ValueError as e:
        ap.error(str(e))
    try:
        spec = hand_by_name(args.hand)
    except ValueError as e:
        ap.error(f"--hand: {e}")
    if args.tendon_stiffness is not None:
        for f in spec.fingers:
            f.tendon_stiffness = args.tendon_stiffness
        spec.validate()
    if args.direction is not None and args.squeeze:  # (a sweep draws no random action: it had been ignored)
        ap.error("--squeeze: the random actions' squeezes, and --direction sweeps instead")
    if args.spring_profile is not None and not all(np.isfinite(x) and x > 0 for x in args.spring_profile):
        ap.error(f"--spring-profile: the scales must be positive numbers, got {args.spring_profile}")
    r = run_agreement(args.object, hand=spec, actions=args.actions, seed=args.seed, span=args.span,
                      window=args.window, direction=args.direction, step=args.step, physics=physics,
                      spring_scales=args.spring_profile,
                      squeeze=default_squeeze("physics", "stiffness") if args.squeeze else None, hold=args.hold)
    print(f"{r['object']}, {r['hand']}, tendons {r['tendon_stiffness']:.0f} N/m, {len(r['actions'])} actions")
    if r["stopped"] is not None:
        print(f"stopped at {r['stopped']}")
    print(" k   true [mm]  one-step err [mm, deg]  predicted/true  carried err [mm]  other contacts")
    for k, row in enumerate(r["actions"]):
        one = ("      -" if row["one_step_error_mm"] is None
               else f"{row['one_step_error_mm']:7.2f} {row['one_step_error_deg']:6.2f}")
        ratio = ("   -" if row["predicted_motion_mm"] is None or row["true_motion_mm"] < 0.05
                 else f"{row['predicted_motion_mm'] / row['true_motion_mm']:5.2f}")
        carried = "      -" if row["carried_error_mm"] is None else f"{row['carried_error_mm']:7.2f}"
        print(f"{k:2d} {row['true_motion_mm']:9.2f}  {one}          {ratio}         {carried}   "
              f"{', '.join(row['other_contacts']) or '-'}")
    last = r["actions"][-1]["carried_joint_error_deg"]
    if last is not None:
        print("carried model's joint angles minus the plant's after the last action [deg]:")
        for name, row in zip(spec.finger_names(), last, strict=True):
            print(f"  {name:14s} " + " ".join(f"{x:7.2f}" for x in row))
    def num(x):
        return "n/a" if x is None else f"{x:.3f}"

    print(f"median one-step error {num(r['one_step_error_mm_median'])} mm / {num(r['one_step_error_deg_median'])} deg, "
          f"predicted/true motion {num(r['motion_ratio_median'])}, carried model off by up to "
          f"{num(r['carried_error_mm_max'])} mm, "
          f"{r['actions_with_other_contacts']} actions with other bodies touching the object")
    if r["settled_one_step_error_mm_median"] is not None:
        print(f"commanded equilibrium (gravity {r['gravity']:g} m/s^2): angles off the plant's by "
              f"{r['commanded_offset_deg_mean']:.2f} deg on average (per joint: "
              + ", ".join(f"{name} " + "/".join(f"{x:.2f}" for x in row)
                          for name, row in zip(spec.finger_names(), r["commanded_offset_deg_mean_per_joint"], strict=True))
          + f"); settled one-step error {r['settled_one_step_error_mm_median']:.3f} mm / "
          f"{r['settled_one_step_error_deg_median']:.3f} deg; {r['commanded_failures']} failures")
    else:
        print(f"commanded equilibrium: the VLR found none before and after the action under the plant's tendon "
              f"state in {len(r['actions'])} actions")
    ke, kd = r["kinematic_error_mm_median"], r["kinematic_error_deg_median"]
    print("kinematic check (the object moved by the plant's true links, attached at link-fixed points): "
          + ", ".join(f"{k} {ke[k]:.3f} mm / {kd[k]:.3f} deg" for k in ke) + " (median)")
    for key, what in (("joint_motion_slope", "Eq. 9"), ("joint_motion_slope_with_weights", "the weights following"),
                      ("joint_motion_slope_rolling", "the pads rolling and the weights"),
                      ("joint_motion_slope_rolling_shaped", "the same on the object's shape"),
                      ("joint_motion_slope_rolling_released", "the same, its weak directions released")):
        if r[key] is not None:
            print(f"plant's joint motion / the commanded equilibria's, {what} (least-squares slope per joint): "
                  + ", ".join(f"{name} " + "/".join(num(x) for x in row)
                              for name, row in zip(spec.finger_names(), r[key], strict=True)))
    print(f"settled one-step error with the weights following: {num(r['settled_one_step_error_with_weights_mm_median'])} mm / "
          f"{num(r['settled_one_step_error_with_weights_deg_median'])} deg (median)")
    print(f"rolling reference (the pads rolling and the weights, vlr_drake.rolling_reference): one-step error "
          f"{num(r['rolling_one_step_error_mm_median'])} mm / {num(r['rolling_one_step_error_deg_median'])} deg (median), "
          f"angles at rest off the plant's by {num(r['rolling_offset_deg_mean'])} deg on average, "
          f"{r['rolling_failures']} failures")
    if r["rolling_shaped_one_step_error_mm_median"] is not None:
        print(f"with the object's shape (a sphere: the pads rolling over its curved surface, the touching pad "
              f"sphere's offset): one-step error {num(r['rolling_shaped_one_step_error_mm_median'])} mm / "
              f"{num(r['rolling_shaped_one_step_error_deg_median'])} deg (median); with the attachment directions "
              f"it holds only at second order released: {num(r['rolling_released_one_step_error_mm_median'])} mm / "
              f"{num(r['rolling_released_one_step_error_deg_median'])} deg")
    for key, what in (("joint_motion_explained_rolling", "the rolling reference"),
                      ("joint_motion_explained_rolling_shaped", "the same on the object's shape"),
                      ("joint_motion_explained_rolling_released", "the same, its weak directions released")):
        if r[key] is not None:
            print(f"fraction of the plant's joint motion explained by {what}, action by action: "
                  + ", ".join(f"{name} " + "/".join(num(x) for x in row)
                              for name, row in zip(spec.finger_names(), r[key], strict=True)))
    if args.hold > 0 and r["hold"] is None:  # (it had been skipped without a word)
        print(f"no hold: the run stopped before its last action ({r['stopped']})")
    if r["hold"] is not None:
        d = r["hold"]
        print(f"held {d['seconds']:g} s after the last action: the object drifted {d['object_drift_mm']:.3f} mm / "
              f"{d['object_turn_deg']:.3f} deg, the joints [deg] "
              + ", ".join(f"{name} " + "/".join(f"{x:+.3f}" for x in row)
                          for name, row in zip(spec.finger_names(), d["joint_drift_deg"], strict=True)))
    sp = r["spring_profile"]
    if sp is not None:
        print(f"spring profile ({sp['actions']} actions; sum of squares in units of {PROFILE_UNITS[0]} mm and "
              f"{PROFILE_UNITS[1]} deg): scale, rolling reference median mm / deg and sum, Eq. 9 median mm / deg and sum")
        for k, x in enumerate(sp["scales"]):
            if sp["rolling_sum_sq"] is None:
                print(f"  x{x:g}: no action solved at every scale")
                continue
            print(f"  x{x:<5g} {sp['rolling_mm_median'][k]:.3f} / {sp['rolling_deg_median'][k]:.3f}  "
                  f"{sp['rolling_sum_sq'][k]:8.0f}    {sp['eq9_mm_median'][k]:.3f} / {sp['eq9_deg_median'][k]:.3f}  "
                  f"{sp['eq9_sum_sq'][k]:8.0f}")
    b = r["statics_budget"]
    if b is not None:
        print("statics budget: the plant's joint torques by load, mean over the actions [mN m] (Eq. 9 lacks "
              "pad_moment, link_weight, object_weight and other_contacts)")
        for load, v in b["loads_mNm_mean"].items():
            print(f"  {load:15s} " + "  ".join("/".join(f"{x:7.2f}" for x in row) for row in v))
        print("  commanded equilibrium's mean |offset| with the unmodelled loads added [deg]: "
              + ", ".join(f"{g} {num(x)}" for g, x in b["commanded_offset_deg_mean_with"].items())
              + f"; largest |residual| {b['residual_mNm_max']:.2f} mN m")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        with open(args.json, "w") as fh:
            json.dump(r, fh, indent=1)
    return r


if __name__ == "__main__":
    raise SystemExit(run("python -m vlr_drake.physics.agreement", main))
