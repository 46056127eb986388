"""The one diagram builder: a :class:`~vlr_drake.scenario.Scenario` in, the
self-identification diagram out (DESIGN.md section 8), for each plant:

- ``model``:    exploration -> hand (:class:`ModelPlantSystem`) -> pose_sensor
  (:class:`NoisyPoseSensor`) -> self_identification
- ``physics``:  exploration -> hand (the physics plant's Diagram, rendered palm camera)
  -> tag_observer (:class:`TagObserver`) -> self_identification
- ``hardware``: exploration -> hand (:class:`HardwareInterface`, real motors and camera)
  -> tag_observer -> self_identification

The filter's action input is the hand's ``tendon_position_measured`` (what the plant
applied: the model plant keeps its pose when it finds no equilibrium for a command), or the
policy's ``tendon_command`` with ``filter_action: commanded``. Systems are added with
``AddNamedSystem`` under those names; outputs are exported as ``<system>.<signal>`` (e.g.
``self_identification.interval_half_width``, ``hand.theta_true``).

The filter's nominal grasp (its prior's centre): on the model plant, the (hidden) true grasp
displaced by up to ``model_plant.center_offset_fraction`` of the prior's half-widths; on the
physics plant, the angles :meth:`PhysicsHand.place` puts the pads on the object with and a
guess of the contacts, which the pads fix at ``PAD_FRACTION`` of the distal length (displaced
by up to ``model_plant.center_offset_fraction`` of the prior's half-width,
:func:`vlr_drake.identify.contact_guess_rng`); on hardware, the scenario's ``grasp``
section. The physics grasp needs :func:`initialize` before simulating: it places the object
and fingers (``place``), whose tendon commands are the policy's initial (grasp) commands,
and simulates to settle; the first action comes at t = T.

Diagram pictures: ``python -m vlr_drake.builder --write-diagrams`` writes
``diagrams/<file>.dot`` (``GetGraphvizString(max_depth=1)``) for every example scenario
``diagrams/<file>.yaml`` and, when Graphviz's ``dot`` is installed, ``diagrams/<file>.svg``. The ``.dot`` text is the source
of truth (a test checks it is current); the picture is a convenience.
``python -m vlr_drake.builder --run diagrams/model_plant.yaml --iterations 20 --set 'seed: 3'``
runs a scenario (:func:`run`) and prints the estimate beside the truth.
"""

import argparse
import math
import re
import shutil
import subprocess
import sys
import traceback
import warnings
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from pydrake.geometry import Meshcat
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import Diagram, DiagramBuilder, LeafSystem

from vlr_drake import filter as pf
from vlr_drake.entry import (
    Stopped,
    check_not_trace,
    check_output,
    count,
    interrupted,
    path_text,
    plain,
    saved_trace,
)
from vlr_drake.entry import run as run_command
from vlr_drake.hand import HandModel
from vlr_drake.identify import _truth_grasp, contact_guess_rng, hand_parameter_report
from vlr_drake.kinematics import is_count, is_number
from vlr_drake.model_plant import ModelPlant
from vlr_drake.models import PAD_FRACTION
from vlr_drake.perception.tag_pose import TagObserverConfig, vtk_render_intrinsics
from vlr_drake.scenario import (
    DIAGRAMS_DIR,
    FILTER_ACTIONS,
    Scenario,
    example_scenarios,
    find_scenario,
    ignored_by_plant,
    load_scenario,
)
from vlr_drake.systems.physics_plant import PhysicsHand, PlacementError, add_physics_hand, placed_grasp
from vlr_drake.systems.self_identification import (
    ExplorationPolicy,
    ModelPlantSystem,
    SelfIdentificationSystem,
)
from vlr_drake.systems.tag_observer import NoisyPoseSensor, TagObserver
from vlr_drake.trace import pool_draws

__all__ = [
    "BuiltDiagram",
    "build_diagram",
    "build_model_plant_diagram",
    "initialize",
    "wire_identification",
    "graphviz_text",
    "graphviz_available",
    "write_diagrams",
    "run",
    "main",
]

#: The object's POM in the palm for the model plant's grasp [m] (as in vlr_drake.identify).
MODEL_PLANT_t_PO = (0.0, 0.0, 0.11)
#: Seed offsets of the systems' random draws (policy, sensor, filter, model plant, grasp).
#: The systems take seed + offset, as `vlr-drake identify` takes seed + 1, 2, 3 (so one
#: run's sensor stream is the next seed's policy stream: streams of different purpose,
#: drawn differently; tuple seeds would separate them, at the cost of every recorded
#: figure, and are left for a change that re-measures them).
SEED_POLICY, SEED_SENSOR, SEED_FILTER, SEED_PLANT = 1, 2, 3, 4

# Outputs exported as "<system>.<signal>" when the system has them.
_EXPORTS = {
    "exploration": ["tendon_command"],
    "hand": [
        "theta_true",
        "X_PO_true",
        "contacts_true",
        "contact_along_link_true",
        "tension",
        "tendon_position_measured",
        "rgb_image",
        "camera_valid",
    ],
    "sensor": ["X_PO_measured", "X_PO_valid", "reprojection_error"],  # those it has, under its own name
    "self_identification": ["estimate", "theta_estimate", "interval_half_width", "converged", "particles"],
}


@dataclass
class BuiltDiagram:
    """The diagram of a scenario and handles to its parts."""

    diagram: Diagram
    scenario: Scenario | None
    hand: HandModel  # the hand of the filter and the policy
    policy: ExplorationPolicy  # "exploration"
    plant: LeafSystem | Diagram  # "hand": ModelPlantSystem, the physics Diagram or HardwareInterface
    sensor: LeafSystem  # "pose_sensor" (NoisyPoseSensor) or "tag_observer" (TagObserver)
    filter: SelfIdentificationSystem  # "self_identification"
    period_sec: float  # action period T [s]
    theta_center: np.ndarray  # (N, K) the filter's nominal grasp angles [rad]
    a_center: np.ndarray  # (N,) nominal contacts along the last links [m]
    l_grasp: np.ndarray  # (N,) the policy's initial (grasp) tendon commands [m]
    physics_hand: PhysicsHand | None = None  # the physics plant's handles (plant "physics")


def wire_identification(
    builder: DiagramBuilder,
    policy: ExplorationPolicy,
    plant,
    sensor: LeafSystem,
    flt: SelfIdentificationSystem,
    sensor_name: str,
    filter_action: str = "measured",
    command=None,
) -> None:
    """Add the four parts by name (``exploration``, ``hand`` unless already added,
    ``sensor_name``, ``self_identification``), connect policy -> plant -> sensor -> filter
    (the sensor reads the hand's ``X_PO_true`` where it has that input, a pose sensor, else
    its ``rgb_image``, a tag observer),
    and the filter's action input to the hand's ``tendon_position_measured``
    (``filter_action="measured"``) or to the commands ("commanded": the hardware interface's
    ``tendon_command_sent``, the commands after its clipping at the limits and its ramp, where
    the plant has one; else the command the hand is given), and export their outputs as
    ``<system>.<signal>``. ``command``: the output port that drives the hand (default the
    policy's ``tendon_command``; the control section's switch between policy and controller)."""
    if filter_action not in FILTER_ACTIONS:
        raise ValueError(f"'filter_action' must be one of {list(FILTER_ACTIONS)}, got '{filter_action}'")
    builder.AddNamedSystem("exploration", policy)
    if not builder.HasSubsystemNamed("hand"):
        builder.AddNamedSystem("hand", plant)
    builder.AddNamedSystem(sensor_name, sensor)
    builder.AddNamedSystem("self_identification", flt)
    if command is None:  # what drives the hand: the policy, or a switch between it and a controller
        command = policy.GetOutputPort("tendon_command")
    builder.Connect(command, plant.GetInputPort("tendon_command"))
    # what the sensor reads, by its ports (by its name, any other than "pose_sensor" had
    # been taken for a camera's and "tag_observer"'s only exported; a review)
    seen = "X_PO_true" if sensor.HasInputPort("X_PO_true") else "rgb_image"
    builder.Connect(plant.GetOutputPort(seen), sensor.GetInputPort(seen))
    if filter_action == "measured":
        action = plant.GetOutputPort("tendon_position_measured")
    elif plant.HasOutputPort("tendon_command_sent"):  # hardware: what went to the motors, clipped and ramped
        action = plant.GetOutputPort("tendon_command_sent")
    else:
        action = command
    builder.Connect(action, flt.tendon_command_input_port())
    builder.Connect(sensor.GetOutputPort("X_PO_measured"), flt.X_PO_measured_input_port())
    builder.Connect(sensor.GetOutputPort("X_PO_valid"), flt.X_PO_valid_input_port())
    # the policy holds the grasp until the filter has its first measurement (the prior is
    # drawn around the grasp: a hand that had moved on could leave the truth outside it)
    builder.Connect(flt.GetOutputPort("started"), policy.GetInputPort("enabled"))
    for name, system, kind in [
        ("exploration", policy, "exploration"),
        ("hand", plant, "hand"),
        (sensor_name, sensor, "sensor"),
        ("self_identification", flt, "self_identification"),
    ]:
        for port in _EXPORTS[kind]:
            if system.HasOutputPort(port):
                builder.ExportOutput(system.GetOutputPort(port), f"{name}.{port}")


def _motor_limits(s: Scenario) -> np.ndarray | None:
    """(N, 2) [m]: a hardware hand's motor limits (``hardware.tendon_lower`` / ``tendon_upper``,
    within the hand's range and possibly narrower), which the exploration and the controller
    keep to; None on the other plants."""
    return np.column_stack(s.hardware.tendon_limits(s.hand_spec_resolved())) if s.plant == "hardware" else None


def _add_control(builder: DiagramBuilder, s: Scenario, h: HandModel, l0, T: float, window: float) -> dict:
    """The control section's systems, added by name: ``command_switch`` (a PortSwitch of the
    exploration's and the controller's commands), its ``control_phase`` selector (the
    controller's from the section's start), ``controller`` (JacobianController, within
    ``window`` (the exploration's, unless the section gives one) of the commands it starts
    from, and on hardware within the motors' limits) and ``trajectory`` (the goals, relative
    to the pose measured when control starts)."""
    from pydrake.systems.primitives import PortSwitch

    from vlr_drake.systems.controller import ControlPhase, JacobianController, TaskTrajectorySource

    c = s.control
    start = c.start_sec(T)  # the switch to the controller; it holds the tendons for the anchor's frames
    switch = builder.AddNamedSystem("command_switch", PortSwitch(h.N))
    explore_in, control_in = switch.DeclareInputPort("exploration"), switch.DeclareInputPort("control")
    phase = builder.AddNamedSystem("control_phase", ControlPhase(start, explore_in.get_index(), control_in.get_index()))
    builder.Connect(phase.get_output_port(), switch.get_port_selector_input_port())
    l0 = np.asarray(l0, float)
    w = window if c.window_mm is None else 1e-3 * c.window_mm
    limits = _motor_limits(s)  # hardware: also within the motors' limits
    controller = builder.AddNamedSystem("controller", JacobianController(
        h, l0, T, offset_sec=0.05 * T, rows=c.rows, damping=c.damping, clip=1e-3 * c.clip_mm,
        tol_position=1e-3 * c.tol_position_mm,
        tol_rotation=np.deg2rad(c.tol_rotation_deg), tendon=s.filter.tendon, limits=limits, window=w,
        start_sec=start))
    goals = [(np.eye(3), 1e-3 * np.asarray(g, float)) for g in c.goals_mm]
    trajectory = builder.AddNamedSystem("trajectory", TaskTrajectorySource(
        goals, T, max_periods=c.max_periods, relative_start_sec=start, anchor_frames=c.anchor_frames))
    return {"switch": switch, "explore_in": explore_in, "control_in": control_in, "controller": controller,
            "trajectory": trajectory}


def _wire_control(builder: DiagramBuilder, c: dict, policy, plant, sensor, flt) -> None:
    """Connect the control section's systems (:func:`_add_control`) to the exploration, the
    hand, the sensor and the filter, and export their outputs as ``controller.<signal>`` and
    ``trajectory.<signal>``. The controller steps from what the hand was given (on hardware
    what the motors were sent, after the interface's clipping and ramp) and waits for the
    trajectory's goals to be anchored. Beside a tag observer both read the frame it held at the
    filter's offset (``X_PO_held``), the one the filter's estimate was last updated from: a
    frame of their own at 0.05 T and 0.5 T would be rendered (or grabbed) and detected again,
    a second frame every control period. The model plant's pose sensor measures at no cost
    and is read as it measures."""
    ctrl, traj, switch = c["controller"], c["trajectory"], c["switch"]
    pose, valid = (("X_PO_held", "X_PO_held_valid") if sensor.HasOutputPort("X_PO_held")
                   else ("X_PO_measured", "X_PO_valid"))
    builder.Connect(policy.GetOutputPort("tendon_command"), c["explore_in"])
    builder.Connect(ctrl.tendon_command_output_port(), c["control_in"])
    applied = (plant.GetOutputPort("tendon_command_sent") if plant.HasOutputPort("tendon_command_sent")
               else switch.get_output_port())
    builder.Connect(applied, ctrl.tendon_command_applied_input_port())
    builder.Connect(traj.ready_output_port(), ctrl.enabled_input_port())
    for dest in (ctrl, traj):
        builder.Connect(sensor.GetOutputPort(pose), dest.GetInputPort("X_PO_measured"))
        builder.Connect(sensor.GetOutputPort(valid), dest.GetInputPort("X_PO_valid"))
    builder.Connect(flt.GetOutputPort("estimate"), ctrl.estimate_input_port())
    builder.Connect(traj.X_PO_goal_output_port(), ctrl.X_PO_goal_input_port())
    builder.Connect(ctrl.at_goal_output_port(), traj.at_goal_input_port())
    for name, system, ports in (("controller", ctrl, ("at_goal", "pose_error", "has_model", "tendon_command")),
                                ("trajectory", traj, ("waypoint_index", "done", "ready"))):
        for port in ports:
            builder.ExportOutput(system.GetOutputPort(port), f"{name}.{port}")


def _model_plant_parts(s: Scenario, h: HandModel, prior: pf.PriorConfig, T: float):
    mp = s.model_plant
    rng = np.random.default_rng((s.seed, SEED_PLANT))
    # The true grasp is a stable grasp of the *true* hand (its stiffness and link lengths).
    true_spec = s.hand_spec_resolved()
    for i, finger in enumerate(true_spec.fingers):
        if mp.stiffness:
            finger.stiffness = [float(k) for k in mp.stiffness[i]]
        if mp.link_lengths:
            finger.link_lengths = [float(L) for L in mp.link_lengths[i]]
    try:
        theta, a = _truth_grasp(true_spec.model(), rng)
    except (RuntimeError, ValueError) as e:
        raise ValueError(
            f"scenario '{s.name}': no stable grasp of the true hand (model_plant section): {e}"
        ) from e
    plant = ModelPlant(
        h,
        theta,
        a,
        np.eye(3),
        np.array(MODEL_PLANT_t_PO),
        np.random.default_rng((s.seed, SEED_PLANT + 1)),
        stiffness=np.asarray(mp.stiffness, float) if mp.stiffness else None,
        link_lengths=np.asarray(mp.link_lengths, float) if mp.link_lengths else None,
        sigma_position=mp.sigma_position,
        sigma_rotation=np.deg2rad(mp.sigma_rotation_deg),
        dropout=mp.dropout,
        tendon=s.filter.tendon,
        contact_drift=mp.contact_drift,
    )
    theta_c, a_c = prior.guessed_grasp(plant.state.theta, plant.state.a, rng, h, mp.center_offset_fraction)
    plant_sys = ModelPlantSystem(plant, T)
    sensor = NoisyPoseSensor(
        mp.sigma_position,
        np.deg2rad(mp.sigma_rotation_deg),
        dropout_probability=mp.dropout,
        seed=s.seed + SEED_SENSOR,
        update_period_sec=T,
    )
    return plant_sys, sensor, theta_c, a_c, plant_sys.grasp_command()


def _observer_config(s: Scenario) -> TagObserverConfig:
    obj = s.object_spec_resolved()
    import copy

    cfg = copy.deepcopy(s.observer)
    cfg.tag_id, cfg.tag_size = int(obj.tag_id), float(obj.tag_size)
    return cfg.validate()


def _nominal_grasp(s: Scenario, h: HandModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Hardware: (theta (N, K), a (N,), tendon commands (N,)) of the scenario's grasp section,
    or of a stable model grasp sampled with the seed; commands from the model's equilibrium."""
    if s.grasp.theta_deg:
        theta = np.deg2rad(np.asarray(s.grasp.theta_deg, float))
        a = (
            np.asarray(s.grasp.contact, float)
            if s.grasp.contact
            else np.full(h.N, PAD_FRACTION) * h.distal_length
        )
    else:
        theta, a = _truth_grasp(h, np.random.default_rng((s.seed, SEED_PLANT)))
        if s.grasp.contact:
            a = np.asarray(s.grasp.contact, float)
    try:
        mp = ModelPlant(
            h, theta, a, np.eye(3), np.array(MODEL_PLANT_t_PO), np.random.default_rng(0), tendon=s.filter.tendon
        )
    except ValueError as e:
        given = [name for name, v in (("theta_deg", s.grasp.theta_deg), ("contact", s.grasp.contact)) if v]
        what = " and ".join(f"'{n}'" for n in given) if given else "the grasp sampled with the seed"
        raise ValueError(f"grasp: {what} {'do' if len(given) == 2 else 'does'} not make a grasp the model can "
                         f"hold ({e})") from e
    l0 = mp.state.tendon_command.copy()
    if s.hardware is not None:  # the real hand closes on these commands: refuse them before any motor moves
        lower, upper = s.hardware.tendon_limits(s.hand_spec_resolved())
        bad = np.flatnonzero((l0 < lower - 1e-9) | (l0 > upper + 1e-9))
        if len(bad):
            i = bad[0]
            raise ValueError(
                f"grasp: the grasp needs finger {i} ({h.names[i]})'s tendon at {1e3 * l0[i]:.2f} mm, outside its "
                f"limits [{1e3 * lower[i]:.2f}, {1e3 * upper[i]:.2f}] mm (hardware tendon_lower/tendon_upper or the "
                "hand's tendon_range): change 'theta_deg' or 'contact'"
            )
    return mp.state.theta.copy(), mp.state.a.copy(), l0


def build_diagram(scenario: Scenario, meshcat: Meshcat | None = None) -> BuiltDiagram:
    """Turn ``scenario`` into the self-identification diagram (module docstring).

    A given ``meshcat`` shows the physics plant; without one, ``scenario.meshcat: true``
    creates one. The physics diagram needs :func:`initialize` before it is simulated.
    Raises ``ValueError`` for an invalid scenario or a model-plant truth with no stable grasp.
    """
    s = scenario.validate()
    ignored = ignored_by_plant(s)
    if s.plant != "physics" and (s.meshcat or meshcat is not None):  # the diagram shows the physics plant only
        ignored.append("meshcat")  # (`vlr-drake identify` draws the model plant's hypotheses in it)
    if ignored:  # said, not silently dropped
        warnings.warn(f"scenario '{s.name}': the {s.plant} plant does not use {', '.join(ignored)}", stacklevel=2)
    spec = s.hand_spec_resolved()
    h = spec.model()
    prior = s.prior.to_prior()
    believed = prior.believed_hand(spec)  # the filter's hand: unknown links and springs at their range's middle
    T = s.period_sec()
    builder = DiagramBuilder()
    ph = None
    if s.plant == "model":
        plant, sensor, theta_c, a_c, l0 = _model_plant_parts(s, h, prior, T)
        sensor_name = "pose_sensor"
    elif s.plant == "physics":
        if s.meshcat and meshcat is None:
            meshcat = Meshcat()
        obj = s.object_spec_resolved()
        theta0, l0 = placed_grasp(spec, obj, s.physics)
        if believed != spec:  # the grasp placed with the hand the filter believes in, as vlr-drake identify
            theta0 = placed_grasp(believed, obj, s.physics)[0]
        # the camera's pixel noise takes the scenario's seed (PhysicsConfig.seed)
        ph = add_physics_hand(builder, spec, obj, replace(s.physics, seed=s.seed), s.camera, meshcat)
        plant = ph.diagram
        theta_c = np.asarray(theta0, float).reshape(h.N, h.K)
        # the pads fix the true contacts at PAD_FRACTION of the distal links: a guess of them,
        # as vlr-drake identify makes
        a_c = prior.guessed_contacts(np.full(h.N, PAD_FRACTION) * h.distal_length, contact_guess_rng(s.seed), h,
                                     s.model_plant.center_offset_fraction)
        sensor = TagObserver(
            _observer_config(s),
            vtk_render_intrinsics(s.camera),
            None,
            s.camera.X_PC(),
            obj.X_TO(),
            update_period_sec=T,
            update_offset_sec=pf.FILTER_PHASE * T,  # the filter's: one frame rendered and detected per period
            image_size=(s.camera.width, s.camera.height),
        )
        sensor_name = "tag_observer"
    else:
        from vlr_drake.systems.hardware_interface import add_hardware_interface

        theta_c, a_c, l0 = _nominal_grasp(s, h)
        plant = add_hardware_interface(builder, spec, s.hardware, name="hand", grasp_command=l0)
        sensor = TagObserver(
            _observer_config(s),
            plant.camera_matrix(),
            plant.distortion_coefficients(),
            s.camera.X_PC(),
            s.object_spec_resolved().X_TO(),
            update_period_sec=T,
            update_offset_sec=pf.FILTER_PHASE * T,  # the filter's: one frame rendered and detected per period
            image_size=plant.image_size(),
        )
        sensor_name = "tag_observer"
    span, window = s.exploration.span_and_window(s.plant)
    squeeze, squeeze_window = s.exploration.squeeze_and_window(s.plant, s.experiment())
    policy = ExplorationPolicy(h, l0, T, span=span, window=window, seed=s.seed + SEED_POLICY, squeeze=squeeze,
                               squeeze_window=squeeze_window, limits=_motor_limits(s))  # as the controller
    config = s.filter
    if s.plant != "hardware":  # the links' weight (hardware: the filter section's gravity_palm)
        from vlr_drake.identify import default_link_weight, filter_gravity

        weight = default_link_weight(s.plant, s.experiment()) if s.link_weight is None else s.link_weight
        config = replace(config, gravity_palm=filter_gravity(s.physics if weight else None))
    if config.gravity_loads is None:  # how the moves carry the links' weight: the experiment's default,
        from vlr_drake.identify import default_gravity_loads  # following with a weighed object's

        config = replace(config, gravity_loads=default_gravity_loads(s.plant, s.experiment(), prior.object_mass_unknown,
                                                                     config.motion_model))
    if config.stuck_probability is None:  # the plant's and experiment's default
        from vlr_drake.identify import default_stuck_probability

        config = replace(config, stuck_probability=default_stuck_probability(s.plant, s.experiment()))
    if config.likelihood_width is None:  # likewise
        from vlr_drake.identify import default_likelihood_width

        config = replace(config, likelihood_width=default_likelihood_width(s.plant, s.experiment()))
    h_filter = believed.model()  # no replaced link's true length, no unknown spring's true value
    flt = SelfIdentificationSystem(h_filter, config, prior, theta_c, a_c, T, seed=s.seed + SEED_FILTER)
    ctrl = _add_control(builder, s, h_filter, l0, T, window) if s.control.goals_mm else None
    wire_identification(builder, policy, plant, sensor, flt, sensor_name, s.filter_action,
                        command=None if ctrl is None else ctrl["switch"].get_output_port())
    if ctrl is not None:
        _wire_control(builder, ctrl, policy, plant, sensor, flt)
    diagram = builder.Build()
    diagram.set_name(f"self_identification_{s.name}")
    return BuiltDiagram(
        diagram,
        s,
        h_filter,
        policy,
        plant,
        sensor,
        flt,
        T,
        np.asarray(theta_c, float).reshape(h.N, h.K),
        np.asarray(a_c, float).reshape(h.N),
        np.asarray(l0, float),
        ph,
    )


def build_model_plant_diagram(
    hand: HandModel,
    plant: ModelPlant,
    config: pf.FilterConfig,
    prior: pf.PriorConfig,
    theta_center,
    a_center,
    *,
    period_sec: float = 1.0,
    sigma_position: float = 0.2e-3,
    sigma_rotation: float = np.deg2rad(0.5),
    dropout: float = 0.0,
    seed: int = 0,
    filter_action: str = "commanded",
) -> BuiltDiagram:
    """The model-plant loop around an already made :class:`ModelPlant` (the signature and,
    with the default ``filter_action="commanded"``, the wiring of
    ``vlr_drake.diagram.build_model_identification_diagram``), wired by the same
    :func:`wire_identification` as :func:`build_diagram`."""
    builder = DiagramBuilder()
    plant_sys = ModelPlantSystem(plant, period_sec)
    l0 = plant_sys.grasp_command()
    policy = ExplorationPolicy(hand, l0, period_sec, seed=seed + SEED_POLICY)
    sensor = NoisyPoseSensor(
        sigma_position,
        sigma_rotation,
        dropout_probability=dropout,
        seed=seed + SEED_SENSOR,
        update_period_sec=period_sec,
    )
    flt = SelfIdentificationSystem(
        hand, config, prior, theta_center, a_center, period_sec, seed=seed + SEED_FILTER
    )
    wire_identification(builder, policy, plant_sys, sensor, flt, "pose_sensor", filter_action)
    diagram = builder.Build()
    diagram.set_name("self_identification_model_plant")
    return BuiltDiagram(
        diagram,
        None,
        hand,
        policy,
        plant_sys,
        sensor,
        flt,
        period_sec,
        np.asarray(theta_center, float).reshape(hand.N, hand.K),
        np.asarray(a_center, float).reshape(hand.N),
        l0,
    )


def initialize(built: BuiltDiagram, simulator: Simulator, settle_sec: float | None = None) -> dict:
    """Prepare ``simulator`` (of ``built.diagram``) for a run and return grasp facts.

    Physics plant: :meth:`PhysicsHand.place` (object at its placement, pads on it, tendons at
    the grasp's commands, which the policy already outputs: checked), ``Initialize``, then
    simulate ``settle_sec`` (default: the smaller of ``physics.grasp_settle_max`` and 0.8 T,
    before the filter's first update at 0.9 T) so the grasp settles under the object's
    weight. Hardware: ``Initialize``, in which the interface opens the motors and closes the
    hand on the grasp's commands, then the real-time clock starts. The model plant:
    ``Initialize`` only (``settle_sec``, checked, is the physics plant's). Returns
    ``{"theta_placed", "command", "in_contact"}`` (``theta_placed`` and ``in_contact`` None
    off the physics plant; on it ``in_contact`` is all True: a grasp that lost the object
    raises :class:`PlacementError`).

    One simulator per physics diagram: a second ``Simulator`` of the same ``built.diagram``,
    made after the first was freed, rendered frames without the object's textured tag from
    about 0.6 s on (drake 1.51's VTK renderer with textured models; :func:`run` builds a
    diagram per run and is not touched). Build the diagram again for another run."""
    first = pf.FILTER_PHASE * built.period_sec
    if settle_sec is not None and not (is_number(settle_sec) and 0 <= settle_sec < first):
        # (a negative or NaN settle aborted the interpreter in AdvanceTo; one past 0.9 T settled
        # through the filter's first update and the first action)
        raise ValueError(f"'settle_sec' must be a time in [0, {pf.FILTER_PHASE:g} T) = [0, {first:.3g}) s, before the "
                         f"filter's first measurement, got {settle_sec!r}")
    root = simulator.get_mutable_context()
    if built.physics_hand is None:
        simulator.Initialize()  # hardware: the motors open and close on the grasp (HardwareInterface)
        simulator.ResetStatistics()  # a real-time run's clock starts after that
        return {"theta_placed": None, "command": built.l_grasp.copy(), "in_contact": None}
    ph = built.physics_hand
    theta0, l = ph.place(root)
    if not np.allclose(l, built.l_grasp, atol=1e-9):
        raise RuntimeError(f"physics grasp: placed commands {l} differ from the policy's {built.l_grasp}")
    simulator.Initialize()
    X_placed = ph.output(root, "X_PO_true")
    if settle_sec is None:
        settle_sec = min(built.scenario.physics.grasp_settle_max, 0.8 * built.period_sec)
    simulator.AdvanceTo(root.get_time() + settle_sec)
    ph.grasp_X_PO = ph.output(root, "X_PO_true")
    in_contact = ph.in_contact(root)
    shift = float(np.linalg.norm(ph.grasp_X_PO.translation() - X_placed.translation()))
    if not np.all(in_contact) or shift >= built.scenario.physics.fall_distance:
        # said here, not later as a tag the camera never saw (the object had fallen out of view)
        lost = [name for name, held in zip(ph.hand.names, in_contact, strict=True) if not held]
        raise PlacementError(
            f"scenario '{built.scenario.name}': the grasp did not hold the {ph.obj.name}: "
            + (f"{', '.join(lost)} lost it" if lost else "every pad touches it")
            + f", and it moved {1e3 * shift:.1f} mm from its placement in the grasp's {settle_sec:.2f} s settle "
            f"(check the grasp's placement and the physics' pretension)")
    return {"theta_placed": np.asarray(theta0), "command": l, "in_contact": in_contact}


# -- diagram pictures ----------------------------------------------------------------------


_GRAPHVIZ_ID = re.compile(r"(?<![A-Za-z0-9_])(clusters|cluster|s|_)(\d+)")


def graphviz_text(built: BuiltDiagram) -> str:
    """Drake's GraphViz text of the diagram, one level deep (the committed ``.dot``).

    Drake names the graph's nodes after the systems' process-wide ids (``s17``,
    ``cluster17diagram``), which depend on what was built before; they are renumbered in
    order of first appearance, and the connections (listed in hash order) sorted, so the
    text depends only on the scenario."""
    text = built.diagram.GetGraphvizString(max_depth=1)
    ids: dict[str, str] = {}

    def renumber(m: re.Match) -> str:
        return m.group(1) + ids.setdefault(m.group(2), str(len(ids)))

    lines = _GRAPHVIZ_ID.sub(renumber, text).splitlines()
    # Drake lists the connections in hash order: sort each run of edge lines.
    out: list[str] = []
    run: list[str] = []
    for line in lines + [""]:
        if " -> " in line:
            run.append(line)
            continue
        out.extend(sorted(run))
        run = []
        out.append(line)
    return "\n".join(out[:-1]) + "\n"


def graphviz_available() -> str | None:
    """The path of Graphviz's ``dot``, or None where it is not installed (then only the
    ``.dot`` text is written)."""
    return shutil.which("dot")


def write_diagrams(folder: str | Path | None = None, render: bool = True) -> list[Path]:
    """Write ``<file>.dot`` beside every scenario file ``<file>.yaml`` in ``folder`` (default
    ``diagrams/``; named after the file, so that a copy of an example gets its own) and,
    with ``render`` and Graphviz's ``dot`` on the PATH (:func:`graphviz_available`),
    ``<file>.svg``. Returns the written paths. A folder that does not exist, or holds no
    scenario file, is an error."""
    folder = DIAGRAMS_DIR if folder is None else Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"--folder: no folder '{folder}'")
    scenarios = example_scenarios(folder)
    if not scenarios:
        raise ValueError(f"--folder: '{folder}' holds no scenario file (*.yaml)")
    dot = graphviz_available() if render else None
    written = []
    for path in scenarios:
        s = load_scenario(path)
        text = graphviz_text(build_diagram(s))
        out = path.with_suffix(".dot")
        out.write_text(text)
        written.append(out)
        if dot:
            svg = out.with_suffix(".svg")
            subprocess.run([dot, "-Tsvg", str(out), "-o", str(svg)], check=True)
            written.append(svg)
    return written


class _GoalRecorder:
    """A Simulator monitor for a diagram with a control section: each time the trajectory
    leaves a goal (reached, or its periods spent), that goal's measured error and, where the
    plant has its truth, the true POM's distance from it (the goal as anchored on the
    measured frames, so the anchor's own noise is in it). A monitor runs before the events
    due at the end of a step: a goal left at k T + 0.5 T is seen, and its ``time_s``
    recorded, at the next event (the filter's, 0.9 T). The controller's at-goal flag and
    ``measured_error_mm`` are those of its last step on the goal (k T + 0.05 T), measured
    before that step's action; the true error is read at the monitor's time, after the plant
    applied the action (k T + 0.25 T). For a goal reached they agree (the step held still);
    for one left when its periods ran out they are the error before and after the last
    step (a review found the two set side by side as one)."""

    def __init__(self, built: BuiltDiagram):
        self.d = built.diagram
        self.traj = built.diagram.GetSubsystemByName("trajectory")
        self.goals: list[dict] = []
        self._last = (0, 0.0)

    def __call__(self, root):
        from pydrake.systems.framework import EventStatus

        index = int(self.d.GetOutputPort("trajectory.waypoint_index").Eval(root)[0])
        done = float(self.d.GetOutputPort("trajectory.done").Eval(root)[0])
        if (index, done) != self._last and len(self.goals) < self.traj.num_goals:
            left = self._last[0]  # the goal just left: the previous index's (or the last one, once done)
            reached = bool(self.d.GetOutputPort("controller.at_goal").Eval(root)[0] > 0.5)
            entry = {"goal": left, "time_s": root.get_time(), "reached": reached,
                     "measured_error_mm": 1e3 * float(self.d.GetOutputPort("controller.pose_error").Eval(root)[0])}
            if self.d.HasOutputPort("hand.X_PO_true"):
                t_goal = self.traj.goal(self.traj.GetMyContextFromRoot(root), left).translation()
                t_true = self.d.GetOutputPort("hand.X_PO_true").Eval(root).translation()
                entry["true_error_mm"] = 1e3 * float(np.linalg.norm(t_true - t_goal))
                entry["true_offset_mm"] = (1e3 * (t_true - t_goal)).tolist()  # palm frame: where the error lies
            self.goals.append(entry)
            self._last = (index, done)
        return EventStatus.Succeeded()

    def report(self) -> dict:
        """``goals`` (one entry per goal left), ``total`` (the goals' count), ``done`` (every
        goal left), ``reached`` (how many within tolerance) and ``error_mm``: the mean and
        largest true (else measured) error over them [mm]."""
        key = "true_error_mm" if self.goals and "true_error_mm" in self.goals[0] else "measured_error_mm"
        errors = [g[key] for g in self.goals]
        return {"goals": self.goals, "total": self.traj.num_goals, "done": len(self.goals) == self.traj.num_goals,
                "reached": sum(g["reached"] for g in self.goals),
                "error_mm": {"mean": float(np.mean(errors)), "max": float(np.max(errors)), "of": key}
                if errors else None}


def _hardware_summary(plant) -> dict | None:
    """A hardware run's interface counts (None on other plants): its updates, how many sent a
    command clipped at a tendon limit or ramped towards a far one, and how closing on the grasp
    went (``HardwareInterface.grasp_report``)."""
    if not hasattr(plant, "num_clipped"):
        return None
    cam = plant.camera  # what the camera delivered: frames, reads with none, frames delivered again
    return {"updates": int(plant.num_updates), "clipped": int(plant.num_clipped), "ramped": int(plant.num_ramped),
            "grasp": plant.grasp_report,
            "camera": {k: int(getattr(cam, k, 0)) for k in ("frames", "misses", "repeats")}}


def _run_record(flt, built: BuiltDiagram, ctx) -> dict:
    """A diagram run's ``lost_measurements`` (iterations without a tag pose),
    ``reinitialisations``, ``log_evidence``, ``actions_refused`` (as an identification run's:
    the model plant's; the physics plant and hardware refuse none) and, on the physics plant,
    ``object_fell`` (the object moved ``fall_distance`` from the grasp or a pad lost it; None
    on the other plants)."""
    hist = [] if flt is None else flt.history
    ph = built.physics_hand
    return {"lost_measurements": int(sum(not r.measured for r in hist)),
            "actions_refused": built.plant.refused(ctx) if isinstance(built.plant, ModelPlantSystem) else 0,
            "reinitialisations": 0 if flt is None else int(flt.reinitialisations),
            "log_evidence": float(np.nansum([r.log_evidence for r in hist])),
            "object_fell": None if ph is None or ph.grasp_X_PO is None else ph.object_fell(ctx)}


def _contacts(flt, N: int) -> dict:
    """``contact_estimate`` (N,) and ``contact_interval`` (N, 2) [m] of the filter's last
    estimate (NaN before the filter started)."""
    if flt is None:
        return {"contact_estimate": np.full(N, np.nan), "contact_interval": np.full((N, 2), np.nan)}
    est = flt.estimates[-1]
    return {"contact_estimate": np.asarray(est["a"], float).copy(),
            "contact_interval": np.stack([est["a_lo"], est["a_hi"]], axis=1)}


def run(scenario: Scenario, iterations: int, meshcat: Meshcat | None = None, trace: str | Path | None = None,
        draws: int = 1, progress: bool = False) -> dict:
    """Build ``scenario``'s diagram, :func:`initialize` it and simulate ``iterations`` filter
    iterations (to (iterations + 0.95) T: the filter starts at 0.9 T). Returns the filter's
    last estimate and the truth (``theta_estimate``, ``theta_true`` (N, K) [rad],
    ``interval_half_width`` [rad], ``converged``, ``contact_estimate`` (N,) and
    ``contact_interval`` (N, 2) [m] along the last links, ``iterations``, ``sim_time`` [s],
    ``wall_s``, ``realtime_rate`` (sim time over wall time; a hardware scenario runs in real
    time, at most 1, and warns below 0.9); ``hardware``: the interface's counts of updates,
    clipped and ramped commands and its grasp report (None on the simulated plants);
    ``control``: with a control section, each goal left and its errors (``_GoalRecorder``),
    else None; ``trace``: where the filter's trace was saved, for ``vlr-drake replay``, when
    ``trace`` names a file; ``hand_parameters`` and ``weakly_identified``: the identified
    springs and links, estimate and 95% interval, as :func:`vlr_drake.identify.hand_parameter_report`
    gives them (empty where none is unknown); ``draws`` and, with ``draws`` > 1, ``pooled``: the
    run's measurements filtered again under that many draws of the filter's randomness, the
    first the run's own, and pooled, :func:`vlr_drake.trace.pool_draws`, with its ``wall_s``; a
    single draw of a spring or a link is often too sure, the pooled intervals are honest;
    ``progress``: a line and a progress bar per draw).
    A hardware interface is closed (torque off) at the end, before the draws are filtered."""
    import time

    if not is_count(iterations):  # (2.5 had run 2, True 1; NaN aborted the interpreter in AdvanceTo)
        raise ValueError(f"'iterations' must be an integer >= 0, got {iterations!r}")
    if trace is not None and iterations == 0:
        raise ValueError("'iterations' is 0: a trace needs at least one iteration (the filter starts at the first)")
    if not is_count(draws, 1):
        raise ValueError(f"'draws' must be a count of at least 1, got {draws!r}")
    if draws > 1 and iterations == 0:
        raise ValueError("'iterations' is 0: pooled draws need at least one iteration (the filter starts at the first)")
    t0 = time.perf_counter()
    built = build_diagram(scenario, meshcat)
    simulator = Simulator(built.diagram)
    if scenario.plant == "hardware":  # the motors and the camera keep the clock's time
        simulator.set_target_realtime_rate(1.0)
    goals = _GoalRecorder(built) if scenario.control.goals_mm else None
    if goals is not None:
        simulator.set_monitor(goals)
    try:
        initialize(built, simulator)
        stopped = None
        try:
            simulator.AdvanceTo((iterations + 0.95) * built.period_sec)
        except Stopped as e:  # Ctrl-C (entry.unwinding_signals): a simulated run keeps and reports what it
            if scenario.plant == "hardware" or e.name != "SIGINT":  # had done (it had lost it all, and said a
                raise  # real hand's torque was off; a review); a real hand stops (torque off), a kill ends it
            stopped = f"t = {simulator.get_context().get_time():.3f} s: interrupted ({e.name})"
        except (RuntimeError, ValueError, FloatingPointError, np.linalg.LinAlgError) as e:
            if scenario.plant == "hardware":  # a real hand stops (torque off below) and says why
                raise
            # a failure inside a simulated diagram (the physics solver, the filter): the
            # iterations before it are kept and reported, as an identification run's (the
            # context holds the state before the failed update)
            stopped = f"t = {simulator.get_context().get_time():.3f} s: {type(e).__name__}: {e}"
            warnings.warn(f"scenario '{scenario.name}': the run stopped at {stopped}\n{traceback.format_exc()}",
                          RuntimeWarning, stacklevel=2)
        ctx = simulator.get_context()
        rate = simulator.get_actual_realtime_rate()
        if scenario.plant == "hardware" and rate < 0.9:
            warnings.warn(f"scenario '{scenario.name}': the hardware run kept {rate:.2f} "
                          f"of real time (each action period of {built.period_sec} s took longer: fewer particles, "
                          f"or a longer exploration period_sec)", stacklevel=2)
        d, h = built.diagram, built.hand
        sys_ctx = built.filter.GetMyContextFromRoot(ctx)
        flt = built.filter.filter(sys_ctx)
        if flt is None and iterations > 0 and stopped:  # it failed before it started: that, not the camera
            raise ValueError(f"scenario '{scenario.name}': the self-identification never started: the run stopped "
                             f"at {stopped}")
        # why measurements are lost: on the model plant its dropout, else the camera (the
        # model plant had been told to check a camera and a tag it does not have; a review)
        check = (f"the model plant drops {scenario.model_plant.dropout:g} of its samples (model_plant.dropout)"
                 if scenario.plant == "model" else "check the camera and the object's tag_face and tag_size")
        if flt is None and iterations > 0:  # the filter starts at the first POM measurement
            raise ValueError(
                f"scenario '{scenario.name}': the self-identification never started in {iterations} action "
                f"periods: no POM measurement arrived ({check})")
        if flt is not None and not stopped and flt.iteration < iterations:  # periods spent waiting for it
            warnings.warn(f"scenario '{scenario.name}': the filter ran {flt.iteration} of the {iterations} iterations "
                          f"asked: it starts at the first POM measurement, which came late ({check})", stacklevel=2)
        record = _run_record(flt, built, ctx)
        if record["lost_measurements"] > 0.5 * max(len(flt.history) if flt is not None else 0, 1):
            warnings.warn(f"scenario '{scenario.name}': most filter iterations had no measurement "
                          f"({record['lost_measurements']} of {len(flt.history)} lost): the estimate is mostly the "
                          f"prior moved by the actions ({check})", stacklevel=2)
        recorded = built.filter.trace(sys_ctx) if trace is not None or draws > 1 else None
        if recorded is not None:
            recorded.meta.update(
                scenario=scenario.name, plant=scenario.plant, seed=scenario.seed, experiment=scenario.experiment(),
                hand=scenario.hand_spec.name if scenario.hand_spec is not None else scenario.hand,
                object=scenario.object_spec.name if scenario.object_spec is not None else scenario.object)
        result = {
            "trace": None if trace is None else saved_trace(recorded, trace, "python -m vlr_drake.builder"),
            "scenario": scenario.name,
            "iterations": 0 if flt is None else int(flt.iteration),
            "theta_estimate": d.GetOutputPort("self_identification.theta_estimate")
            .Eval(ctx)
            .reshape(h.N, h.K),
            "theta_true": (
                d.GetOutputPort("hand.theta_true").Eval(ctx).reshape(h.N, h.K)
                if d.HasOutputPort("hand.theta_true")
                else None
            ),
            "interval_half_width": d.GetOutputPort("self_identification.interval_half_width")
            .Eval(ctx)
            .reshape(h.N, h.K),
            "converged": bool(d.GetOutputPort("self_identification.converged").Eval(ctx)[0] > 0.5),
            # the contacts along the last links [m] and their 95% intervals (N, 2): the VLR's
            # other half, which a hardware run has no other way to report
            **_contacts(flt, h.N),
            "sim_time": ctx.get_time(),
            "wall_s": time.perf_counter() - t0,
            "realtime_rate": rate,
            "hardware": _hardware_summary(built.plant),
            # what an identification run reports too (a review: a run whose tags were lost, whose
            # cloud was drawn again or whose object fell had looked like any other)
            **record,
            "stopped": stopped,
            "control": None if goals is None else goals.report(),
            **(hand_parameter_report(flt.hand, flt.prior, flt.estimates[-1], flt.estimates[0]) if flt is not None
               else {"hand_parameters": {}, "weakly_identified": [], "object_mass_identified": None}),
            "draws": draws,
        }
    finally:
        if hasattr(built.plant, "close"):
            built.plant.close()
    if draws > 1 and not interrupted(result["stopped"]):  # offline, from the run's
        t1 = time.perf_counter()  # measurements (the motors are off by now); not after a Ctrl-C
        result["pooled"] = pool_draws(recorded, draws, progress=progress, announce=print if progress else None)
        result["pooled"]["wall_s"] = time.perf_counter() - t1
    return result


#: Filter iterations of ``python -m vlr_drake.builder --run`` without ``--iterations`` (a
#: scenario without a control section; see :func:`default_iterations`).
RUN_ITERATIONS = 10


def periods_for_frames(frames: int, dropout: float, probability: float = 0.999) -> int:
    """Action periods within which ``frames`` valid frames arrive with ``probability`` when
    each is lost with probability ``dropout`` (the negative binomial's quantile)."""
    if dropout <= 0:
        return frames
    n, cdf = frames, 0.0
    log_p, log_q = math.log1p(-dropout), math.log(dropout)
    while cdf < probability and n < frames + 1_000_000:  # (the terms in logs: 200 frames at 0.95 had overflowed)
        cdf += math.exp(math.lgamma(n) - math.lgamma(frames) - math.lgamma(n - frames + 1)
                        + frames * log_p + (n - frames) * log_q)
        n += 1
    return n - 1


def default_iterations(scenario: Scenario) -> int:
    """Filter iterations of a ``--run`` without ``--iterations``: :data:`RUN_ITERATIONS`, or
    with a control section as many as its goals need (the exploration, the anchor and
    ``max_periods`` for each goal: :meth:`ControlSettings.iterations_to_finish`), so that
    the run reaches the control it describes. The anchor waits for valid frames: on a model
    plant that drops them, the periods in which its frames arrive 999 times in 1,000 (at
    ``dropout`` 0.5 a run of anchor_frames periods had left its last goal unreached)."""
    c = scenario.control
    extra = 0
    if c.goals_mm and scenario.plant == "model":
        extra = periods_for_frames(c.anchor_frames, scenario.model_plant.dropout) - c.anchor_frames
    return max(RUN_ITERATIONS, c.iterations_to_finish() + extra)


def main(argv: list[str] | None = None) -> int:
    # the docstring's first paragraph and its list of plants, as written
    parser = argparse.ArgumentParser(prog="python -m vlr_drake.builder",
                                     formatter_class=argparse.RawDescriptionHelpFormatter,
                                     description=plain("\n\n".join(__doc__.split("\n\n")[:2])))
    parser.add_argument("--write-diagrams", action="store_true", help="write diagrams/<file>.dot (and .svg) beside each scenario file")
    parser.add_argument("--no-render", action="store_true", help="do not run Graphviz's dot")
    parser.add_argument("--folder", type=path_text, default=None, help="scenario folder (default diagrams/)")
    parser.add_argument("--run", metavar="SCENARIO", default=None,
                        help="run a scenario: a file, or an example's name in diagrams/ (e.g. model_plant)")
    parser.add_argument("--iterations", type=count(0), default=None,
                        help=f"filter iterations of --run (default {RUN_ITERATIONS}; with a control section, as many "
                             "as its goals need: ControlSettings.iterations_to_finish)")
    parser.add_argument("--set", action="append", default=None,
                        help="YAML override text for --run, e.g. 'seed: 3'; repeatable, applied in order")
    parser.add_argument("--trace", type=path_text, default=None, metavar="PATH",
                        help="save the filter's trace of --run (.npz) for vlr-drake replay (e.g. of a hardware run)")
    parser.add_argument("--json", type=path_text, default=None, metavar="PATH",
                        help="write --run's result as JSON (docs/result-files.md, 'Diagram run')")
    parser.add_argument("--draws", type=count(1), default=None, metavar="K",
                        help="after --run, filter its measurements again under K draws of the filter's randomness "
                             "(the first the run's own) and pool them: the mixture of their clouds, whose intervals "
                             "are honest where one draw's are too sure (a spring, a link); offline, K times the "
                             "filter's time, with a hardware run's motors off (default 1: none)")
    args = parser.parse_args(argv)
    for flag, value in (("--set", args.set), ("--trace", args.trace), ("--iterations", args.iterations),
                        ("--draws", args.draws), ("--json", args.json)):
        if value is not None and not args.run:
            parser.error(f"{flag} needs --run SCENARIO")
    for flag, value in (("--write-diagrams", args.write_diagrams), ("--folder", args.folder),
                        ("--no-render", args.no_render)):
        if value and args.run:
            parser.error(f"{flag} does not go with --run (it writes the example diagrams)")
    if args.run:
        check_output("--trace", args.trace)  # before the run, not after it
        check_output("--json", args.json)
        check_not_trace(args.json, [args.trace])  # (a hardware run's trace is its only record of the measurements)
        # a file, or an example's name in diagrams/ (as vlr-drake's --scenario takes)
        scenario = load_scenario(find_scenario(args.run), args.set)
        iterations = default_iterations(scenario) if args.iterations is None else args.iterations
        r = run(scenario, iterations, trace=args.trace, draws=args.draws or 1, progress=True)
        np.set_printoptions(precision=2, suppress=True)
        print(
            f"{r['scenario']}: {r['iterations']} iterations, converged {r['converged']}, wall {r['wall_s']:.1f} s"
        )
        from vlr_drake.cli import hand_parameter_line, print_pooled, run_notes, write_json

        said = ([f"stopped at {r['stopped']}"] if r["stopped"] else []) + run_notes(r) + (
            ["the object fell out of the hand"] if r["object_fell"] else [])
        if said:
            print("; ".join(said))
        print("theta estimate [deg]\n", np.rad2deg(r["theta_estimate"]))
        if r["theta_true"] is not None:
            print("theta true [deg]\n", np.rad2deg(r["theta_true"]))
        print("95% half-width [deg]\n", np.rad2deg(r["interval_half_width"]))
        print("contacts along the last links [mm] (95% interval)\n",
              "  ".join(f"{1e3 * a:.2f} [{1e3 * lo:.2f}, {1e3 * hi:.2f}]"
                        for a, (lo, hi) in zip(r["contact_estimate"], r["contact_interval"], strict=True)))
        for name, q in r["hand_parameters"].items():
            print(hand_parameter_line(name, q) + (" (weakly identified)" if name in r["weakly_identified"] else ""))
        if r.get("object_mass_identified"):
            print(hand_parameter_line("object mass", r["object_mass_identified"]))
        if "pooled" in r:
            print_pooled(dict(r["pooled"]), "")
        if r["control"] is not None:
            c = r["control"]
            print(f"control: {len(c['goals'])} goals left ({c['reached']} reached within tolerance)"
                  + ("" if c["done"] else f" of {c['total']}: the run ended first, give more --iterations")
                  + ("" if c["error_mm"] is None else
                     f"; {c['error_mm']['of'].replace('_mm', '').replace('_', ' ')} {c['error_mm']['mean']:.3f} mm mean, "
                     f"{c['error_mm']['max']:.3f} mm at most"))
        if r["hardware"] is not None:
            hw = r["hardware"]
            print(f"hardware: {hw['updates']} updates, {hw['clipped']} with a command clipped at a tendon limit, "
                  f"{hw['ramped']} ramped towards a far command; camera: {hw['camera']['frames']} frames, "
                  f"{hw['camera']['misses']} reads without one, {hw['camera']['repeats']} repeated")
        if r["trace"]:
            print(f"wrote {r['trace']}")
        write_json(r, args.json)
        if interrupted(r["stopped"]):
            print(f"python -m vlr_drake.builder: stopped by Ctrl-C at {r['stopped']}; what it had done is written "
                  "above", file=sys.stderr)
            return 130
        return 0
    if not args.write_diagrams:
        parser.print_help()
        return 0
    for p in write_diagrams(args.folder, render=not args.no_render):
        print(p)
    if not args.no_render and graphviz_available() is None:
        print("Graphviz's dot is not on the PATH: no .svg written")
    return 0


if __name__ == "__main__":

    sys.exit(run_command("python -m vlr_drake.builder", main, hardware=True))
