"""Scenarios: what one self-identification run is made of, as a YAML-loadable dataclass.

A :class:`Scenario` names the plant ("model", "physics" or "hardware"), the hand (a preset
name or a full :class:`~vlr_drake.hand.HandSpec`), the object (a preset name or a full
:class:`~vlr_drake.objects.ObjectSpec`), the camera, the physics, the filter and its prior,
the exploration policy, the model plant's pose noise and, for a real hand, the hardware
section. Every field carries a comment (DESIGN.md section 8, STYLE.md: the hardware_sim
pattern). :func:`load_scenario` reads a file with Drake's ``yaml_load_typed`` (the file
first, then an override text), turns loader errors into ``ValueError`` naming the file and
the field, and validates every section. :func:`vlr_drake.builder.build_diagram` turns the
result into the diagram.

The example scenarios live in ``diagrams/`` (:func:`example_scenarios` lists them); a new
hand or object needs only a scenario file, e.g.::

    hand_spec:
      name: four_finger
      fingers:
        - {name: f1, base: [0.03, 0.0, 0.0], flexion_direction: [-1.0, 0.0, 0.0], ...}
    object_spec: {name: block, shape: box, size: [0.05, 0.05, 0.05], mass: 0.1, tag_id: 9}

Note on loading: several config dataclasses of the package are declared in modules with
``from __future__ import annotations``, which leaves their field types as strings that
``yaml_load_typed`` cannot read; :func:`_resolve_field_types` replaces them with the
resolved types (once, in place; the dataclasses are otherwise unchanged).
"""

import copy
import dataclasses
import re
import typing
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pydrake.common.yaml import yaml_load_typed

from vlr_drake import filter as pf
from vlr_drake import units
from vlr_drake.hand import HandModel, HandSpec, hand_by_name, thumb_indices
from vlr_drake.hardware.config import HardwareConfig
from vlr_drake.kinematics import is_count
from vlr_drake.objects import ObjectSpec, preset, preset_names
from vlr_drake.perception.camera import CameraConfig
from vlr_drake.perception.tag_pose import TagObserverConfig
from vlr_drake.resources import data_dir
from vlr_drake.systems.physics_plant import PhysicsConfig

# No ``from __future__ import annotations`` here: yaml_load_typed reads the field types.

__all__ = [
    "PLANTS",
    "FILTER_ACTIONS",
    "HAND_PRESETS",
    "DIAGRAMS_DIR",
    "PriorSettings",
    "ExplorationSettings",
    "ModelPlantSettings",
    "NominalGrasp",
    "Scenario",
    "load_scenario",
    "example_scenarios",
    "find_scenario",
    "options_from_scenario",
    "task_settings",
    "ignored_by_identify",
    "ignored_by_plant",
    "config_overrides",
]

#: The plants a scenario can drive.
PLANTS = ("model", "physics", "hardware")
#: What the filter takes as its action (see ``Scenario.filter_action``).
FILTER_ACTIONS = ("measured", "commanded")
#: The hardware interface updates (sends the command, reads motors and camera) at least this
#: many times per action period (``hardware.period_s`` at most T / 4).
HARDWARE_UPDATES_PER_ACTION_MIN = 4
#: Hand preset names accepted by ``Scenario.hand`` (see :func:`vlr_drake.hand.hand_by_name`).
HAND_PRESETS = ("model_o", "NH1", "NH2", "NH3")
#: The folder of the example scenarios and their rendered diagrams (the repository's
#: ``diagrams/``, or an installed wheel's copy: :func:`vlr_drake.resources.data_dir`).
DIAGRAMS_DIR = data_dir("diagrams")


def _shape_of(value) -> tuple | None:
    """``np.shape`` of a (nested) list, or None where its rows differ in length (a ragged
    list, which the shape checks then name instead of numpy's "inhomogeneous shape")."""
    try:
        return np.shape(value)
    except ValueError:
        return None


def _resolve_field_types(cls: type) -> type:
    """Replace string field annotations (postponed evaluation) of the dataclass ``cls`` and of
    the dataclasses its fields hold with the resolved types, so ``yaml_load_typed`` can read
    them. Idempotent; returns ``cls``."""
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        t = hints[f.name]
        f.type = t
        stack = [t]
        while stack:
            s = stack.pop()
            if dataclasses.is_dataclass(s) and isinstance(s, type):
                _resolve_field_types(s)
            stack.extend(typing.get_args(s))
    return cls


for _cls in (
    HandSpec,
    ObjectSpec,
    CameraConfig,
    PhysicsConfig,
    pf.FilterConfig,
    TagObserverConfig,
    HardwareConfig,
):
    _resolve_field_types(_cls)


@dataclass
class PriorSettings:
    """The filter's prior (:class:`vlr_drake.filter.PriorConfig`) in YAML-friendly form
    (lists instead of tuples); :meth:`to_prior` converts."""

    # Half-width of the proximal (first) joint angles around the nominal grasp [rad].
    proximal_half_width: float = 0.15
    # Half-width of the other joint angles [rad].
    distal_half_width: float = 0.25
    # Half-width of the contact positions along the last links [m].
    contact_half_width: float = 0.008
    # Unknown joint stiffnesses as [finger, joint] pairs (empty: all known) ...
    stiffness_unknown: list[list[int]] = field(default_factory=list)
    # ... searched in [min, max] [N m/rad].
    stiffness_range: list[float] = field(default_factory=lambda: [0.05, 0.40])
    # ... drawn "log_uniform" (default: a scale parameter) or "uniform" in that range
    # (PriorConfig.stiffness_prior says what each gave).
    stiffness_prior: str = "log_uniform"
    # Fingers whose proximal link lengths are unknown (empty: all known) ...
    links_unknown: list[int] = field(default_factory=list)
    # ... searched in [min, max] [m].
    link_range: list[float] = field(default_factory=lambda: [0.030, 0.075])
    # Contact positions must stay on the pad: [min, max] along the last link [m], within
    # every finger's last link. Left out: from 5 mm to each finger's own last-link length.
    contact_limits: list[float] | None = None
    # Smallest implied tendon tension of a prior draw [N].
    min_tension: float = 0.0
    # Where each hypothesis' angles are drawn: "nominal", around the nominal grasp; "settled",
    # around the grasp the model settles to under the grasp's tendon command with its own
    # unknown springs and links (PriorConfig.angle_centers).
    angle_centers: str = "nominal"
    # The object's weighed mass [kg] (physics and hardware plants): the filter identifies the
    # object's weight with its mass within +-object_mass_tolerance (a fraction) of this
    # (vlr_drake.identify.IdentifyOptions.object_mass; ``vlr-drake identify --object-mass``).
    # None: not weighed, the object weightless (Eq. 9).
    object_mass: float | None = None
    object_mass_tolerance: float = 0.25
    # Not weighed, the object's weight identified all the same, its mass unknown in
    # [min, max] [kg] (PriorConfig.object_mass_unknown and object_mass_range; the paper's
    # Omega, Eq. 4, "object weight"; ``vlr-drake identify --object-weight``).
    object_mass_unknown: bool = False
    object_mass_range: list[float] = field(default_factory=lambda: list(pf.PriorConfig().object_mass_range))

    def to_prior(self) -> pf.PriorConfig:
        if self.object_mass is not None:
            weight = dict(object_mass_unknown=True,
                          object_mass_range=pf.weighed_mass_range(self.object_mass, self.object_mass_tolerance))
        else:
            weight = dict(object_mass_unknown=bool(self.object_mass_unknown),
                          object_mass_range=(float(self.object_mass_range[0]), float(self.object_mass_range[1])))
        return pf.PriorConfig(**weight,
            proximal_half_width=self.proximal_half_width,
            distal_half_width=self.distal_half_width,
            contact_half_width=self.contact_half_width,
            stiffness_unknown=[(int(i), int(k)) for i, k in self.stiffness_unknown],
            stiffness_range=(float(self.stiffness_range[0]), float(self.stiffness_range[1])),
            stiffness_prior=self.stiffness_prior,
            links_unknown=[int(i) for i in self.links_unknown],
            link_range=(float(self.link_range[0]), float(self.link_range[1])),
            contact_limits=None if self.contact_limits is None
            else (float(self.contact_limits[0]), float(self.contact_limits[1])),
            min_tension=self.min_tension,
            angle_centers=self.angle_centers,
        )

    def validate(self, N: int, K: int) -> "PriorSettings":
        # the YAML forms first; the values are checked where the filter checks them
        for name in ("stiffness_range", "link_range", "contact_limits", "object_mass_range"):
            v = getattr(self, name)
            if v is not None and len(v) != 2:
                raise ValueError(f"prior: '{name}' must be [min, max], got {v}")
        for pair in self.stiffness_unknown:
            if len(pair) != 2:
                raise ValueError(f"prior: 'stiffness_unknown' entry {pair} is not a [finger, joint] pair")
        ranged = list(self.object_mass_range) != list(pf.PriorConfig().object_mass_range)
        if self.object_mass is not None:
            _with_section("prior", lambda: pf.weighed_mass_range(self.object_mass, self.object_mass_tolerance))
            if ranged:
                raise ValueError(f"prior: 'object_mass_range' ({self.object_mass_range}) and 'object_mass' "
                                 f"({self.object_mass}) both say what the object weighs: a weighed object's "
                                 "range is object_mass +- object_mass_tolerance")
        elif self.object_mass_tolerance != PriorSettings.object_mass_tolerance:  # said, not silently dropped
            raise ValueError(f"prior: 'object_mass_tolerance' ({self.object_mass_tolerance}) needs the object's "
                             "weighed mass: 'object_mass'")
        elif ranged and not self.object_mass_unknown:  # said, not silently dropped
            raise ValueError(f"prior: 'object_mass_range' ({self.object_mass_range}) needs object_mass_unknown: true "
                             "(the object's weight identified)")
        self.to_prior().validate(N, K)
        return self


@dataclass
class ExplorationSettings:
    """The random exploration policy (:class:`vlr_drake.systems.self_identification.ExplorationPolicy`)."""

    # Each action moves every tendon by a uniform draw in +-span [m] ...
    span: float | None = None
    # ... reflected inside +-window around the grasp's tendon commands [m]. None (either):
    # the plant's default, ``vlr_drake.identify.EXPLORATION`` (model 3 / 6 mm, physics and
    # hardware 0.5 / 1.2 mm: a compliant grasp).
    window: float | None = None
    # A common-mode pull of +-squeeze [m] on every tendon at once, reflected inside
    # +-squeeze_window [m] (vlr_drake.identify.Exploration). None (either): the default of
    # the plant and experiment, ``vlr_drake.identify.SQUEEZE`` (the stiffness experiment on the
    # physics plant and on hardware: 1.5 / 3 mm; else none); 0 and 0: none.
    squeeze: float | None = None
    squeeze_window: float | None = None
    # Action period T [s]; 0: the plant's own (model 1 s, physics ``physics.action_period``
    # (ramp + settle cap), hardware 1 s).
    period_sec: float = 0.0

    def span_and_window(self, plant: str) -> tuple[float, float]:
        """(span, window) [m] for ``plant``: the scenario's, else the plant's default."""
        from vlr_drake.identify import EXPLORATION

        span, window = EXPLORATION["model" if plant == "model" else "physics"]
        return (span if self.span is None else float(self.span),
                window if self.window is None else float(self.window))

    def squeeze_and_window(self, plant: str, experiment: str) -> tuple[float, float]:
        """(squeeze, window) [m] for ``plant`` and ``experiment``: the scenario's, else the
        default (``vlr_drake.identify.SQUEEZE``; (0, 0) where it names none)."""
        from vlr_drake.identify import default_squeeze

        squeeze, window = default_squeeze(plant, experiment)
        return (squeeze if self.squeeze is None else float(self.squeeze),
                window if self.squeeze_window is None else float(self.squeeze_window))

    def validate(self) -> "ExplorationSettings":
        for name in ("span", "window"):
            value = getattr(self, name)
            if value is not None and not (np.isfinite(value) and value > 0):
                raise ValueError(f"exploration: '{name}' must be positive and finite, got {value}")
        for name in ("squeeze", "squeeze_window"):
            value = getattr(self, name)
            if value is not None and not (np.isfinite(value) and value >= 0):
                raise ValueError(f"exploration: '{name}' must be finite and >= 0, got {value}")
        for name in ("span", "window", "squeeze", "squeeze_window"):
            if getattr(self, name) is not None:
                units.check_length(getattr(self, name), f"exploration: '{name}'")
        if self.squeeze is not None and self.squeeze_window is not None and self.squeeze > self.squeeze_window:
            raise ValueError(f"exploration: 'squeeze' ({self.squeeze}) must not exceed 'squeeze_window' "
                             f"({self.squeeze_window})")
        if not (np.isfinite(self.period_sec) and self.period_sec >= 0):
            raise ValueError(f"exploration: 'period_sec' must be finite and >= 0, got {self.period_sec}")
        units.check_period(self.period_sec, "exploration: 'period_sec'")
        return self


@dataclass
class ModelPlantSettings:
    """The model plant (truth simulated by the VLR model) and its camera stand-in."""

    # Pose noise of the camera stand-in (NoisyPoseSensor): position [m] ...
    sigma_position: float = 0.2e-3
    # ... and rotation [deg] standard deviations.
    sigma_rotation_deg: float = 0.5
    # Probability that a measurement is lost (the tag not seen).
    dropout: float = 0.0
    # True joint stiffness per finger [N m/rad] (N lists of K); empty: the hand's in a diagram
    # (python -m vlr_drake.builder --run), while `vlr-drake identify` of a stiffness scenario
    # draws the unknown spring's truth from the seed (identify.STIFFNESS_RANGE), on either
    # plant, as the experiment's trials do.
    stiffness: list[list[float]] = field(default_factory=list)
    # True proximal link lengths per finger [m] (N lists of K-1); empty: the hand's.
    link_lengths: list[list[float]] = field(default_factory=list)
    # The filter's nominal grasp is the true grasp displaced by up to this fraction of the
    # prior's half-widths (uniform; on hardware it would be the grasp planner's guess). The
    # physics plant's contacts, which its pads fix, are displaced by the same fraction.
    center_offset_fraction: float = pf.CENTER_OFFSET_FRACTION
    # Contacts roll along the fingers by this standard deviation per action [m] (0: fixed).
    contact_drift: float = 0.0

    def validate(self, N: int, K: int) -> "ModelPlantSettings":
        for name in ("sigma_position", "sigma_rotation_deg"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"model_plant: '{name}' must be finite and >= 0, got {value}")
        if not 0 <= self.dropout < 1:
            raise ValueError(f"model_plant: 'dropout' must be in [0, 1), got {self.dropout}")
        if self.stiffness and _shape_of(self.stiffness) != (N, K):
            raise ValueError(f"model_plant: 'stiffness' must be {N} lists of {K}, got {self.stiffness}")
        if self.stiffness and not np.all(np.isfinite(self.stiffness) & (np.asarray(self.stiffness) > 0)):
            raise ValueError(f"model_plant: 'stiffness' must be positive and finite, got {self.stiffness}")
        if self.stiffness:  # N m/rad (in N mm/rad it had been blamed on the preset hand's field)
            units.check_stiffness(self.stiffness, "model_plant: 'stiffness'")
        if self.link_lengths and _shape_of(self.link_lengths) != (N, K - 1):
            raise ValueError(
                f"model_plant: 'link_lengths' must be {N} lists of {K - 1}, got {self.link_lengths}"
            )
        if self.link_lengths and not np.all(np.isfinite(self.link_lengths) & (np.asarray(self.link_lengths) > 0)):
            raise ValueError(f"model_plant: 'link_lengths' must be positive and finite, got {self.link_lengths}")
        if self.link_lengths:  # metres, as the hand's (a review: [[50], ...] ran)
            units.check_length(self.link_lengths, "model_plant: 'link_lengths'")
        units.check_pose_noise(self.sigma_position, "model_plant: 'sigma_position'")
        widest = np.rad2deg(units.WIDEST_ROTATION_NOISE)  # (in degrees here: the plant's check said radians)
        if self.sigma_rotation_deg > widest:
            raise ValueError(f"model_plant: 'sigma_rotation_deg' {self.sigma_rotation_deg:g} deg is more than "
                             f"{widest:g} deg, wider than any tag camera's rotation noise")
        if not 0 <= self.center_offset_fraction <= 1:
            raise ValueError(
                f"model_plant: 'center_offset_fraction' must be in [0, 1], got {self.center_offset_fraction}"
            )
        if not (np.isfinite(self.contact_drift) and self.contact_drift >= 0):
            raise ValueError(f"model_plant: 'contact_drift' must be finite and >= 0, got {self.contact_drift}")
        # metres: 0.5 meant as mm threw the contacts to the links' ends at every action
        units.check_length(self.contact_drift, "model_plant: 'contact_drift'", units.WIDEST_POSE_NOISE,
                           "a roll per action wider than a pad could take")
        return self


@dataclass
class NominalGrasp:
    """The filter's nominal grasp (its prior's centre) when the plant cannot supply one
    (hardware; the model and physics plants derive it, see :mod:`vlr_drake.builder`)."""

    # Joint angles per finger [deg] (N lists of K); empty: a stable grasp of the model
    # sampled with the scenario's seed.
    theta_deg: list[list[float]] = field(default_factory=list)
    # Contact positions along the last links [m] (N); empty: PAD_FRACTION * distal length.
    contact: list[float] = field(default_factory=list)

    def validate(self, N: int, K: int, hand: HandModel | None = None) -> "NominalGrasp":
        """Shapes and finite values; with the ``hand``, also angles within its joint limits and
        contacts on its last links (a hardware run closes the real hand on this grasp)."""
        if self.theta_deg and _shape_of(self.theta_deg) != (N, K):
            raise ValueError(f"grasp: 'theta_deg' must be {N} lists of {K}, got {self.theta_deg}")
        if self.theta_deg and not np.all(np.isfinite(self.theta_deg)):
            raise ValueError(f"grasp: 'theta_deg' must be finite, got {self.theta_deg}")
        if self.theta_deg:  # a real hand closes on it
            units.warn_if_radians(self.theta_deg, "grasp: 'theta_deg'")
        if self.contact and _shape_of(self.contact) != (N,):
            raise ValueError(f"grasp: 'contact' must have {N} entries, got {self.contact}")
        if self.contact and not np.all(np.isfinite(self.contact) & (np.asarray(self.contact) > 0)):
            raise ValueError(f"grasp: 'contact' must be positive and finite [m], got {self.contact}")
        if hand is None:
            return self
        if self.theta_deg:
            theta = np.deg2rad(np.asarray(self.theta_deg, float))
            bad = np.argwhere((theta < hand.joint_lower) | (theta > hand.joint_upper))
            if len(bad):
                i, k = bad[0]
                raise ValueError(
                    f"grasp: 'theta_deg' of finger {i} ({hand.names[i]}) joint {k}, {self.theta_deg[i][k]} deg, is "
                    f"outside the hand's joint limits [{np.rad2deg(hand.joint_lower[i, k]):.1f}, "
                    f"{np.rad2deg(hand.joint_upper[i, k]):.1f}] deg"
                )
        if self.contact:
            a = np.asarray(self.contact, float)
            bad = np.flatnonzero(a > hand.distal_length)
            if len(bad):
                i = bad[0]
                raise ValueError(
                    f"grasp: 'contact' of finger {i} ({hand.names[i]}), {a[i]} m, is past its last link "
                    f"({hand.distal_length[i]} m; contacts are in metres along the link)"
                )
        return self


@dataclass
class ControlSettings:
    """Control after identification, in the same diagram (DESIGN.md sections 7 and 8): after
    ``after_iterations`` action periods of exploration a switch hands the tendons to the
    Jacobian controller (:class:`vlr_drake.systems.controller.JacobianController`), which
    takes the POM through ``goals_mm`` with the filter's estimate while the filter keeps
    identifying from the control actions. No goals: identification only."""

    # POM position goals [mm] in the palm frame, relative to the pose measured when control
    # starts (offsets, one list of 3 per goal); empty: no control.
    goals_mm: list[list[float]] = field(default_factory=list)
    # Action periods of exploration (identification) before control starts.
    after_iterations: int = 60
    # Frames of the held grasp (one per action period) whose mean pose the goals are offsets
    # from: a single frame's noise along a direction the hand cannot move the object in
    # would stay in every goal.
    anchor_frames: int = 5
    # The controlled rows of Eq. 12: "position" (the goals' positions) or "full" (also hold
    # the orientation measured when control starts).
    rows: str = "position"
    # A goal is reached when one frame's measured error is within these tolerances. The
    # defaults suit the rendered camera and a real one (detection about 0.01 mm); with the
    # model plant's stand-in (0.2 mm per axis by default) use about 0.5 mm, or a quieter
    # stand-in, so that the error can fall under them at the goal and not far from it ...
    tol_position_mm: float = 0.1
    tol_rotation_deg: float = 0.5
    # ... or given up after this many action periods.
    max_periods: int = 20
    # Damped least squares' damping, as a fraction of the weighted Jacobian's largest singular
    # value (vlr_drake.control.control_step): larger keeps the steps out of the directions the
    # grasp barely moves the object in. On the physics plant the apple's grasp moves the POM
    # along nearly one line; with 0.01 or 0.1 the controller chased the rest of the error
    # (the object creeping along the palm normal) by releasing every tendon, period after
    # period, until the apple slipped 2-4 mm; with 0.3 the commands held and the POM followed
    # +-0.3 mm goals along the line. The model plant's example takes 0.01 (its grasp moves the
    # POM in a plane, and no friction holds it).
    damping: float = 0.3
    # Largest tendon step per action period [mm] ...
    clip_mm: float = 0.5
    # ... and the window that the controller's commands stay in: +-window_mm [mm] about the
    # commands control starts from; None: the exploration's window.
    window_mm: float | None = None

    def validate(self) -> "ControlSettings":
        shape = _shape_of(self.goals_mm)
        if self.goals_mm and (shape is None or len(shape) != 2 or shape[1] != 3):
            raise ValueError(f"control: 'goals_mm' must be lists of 3 offsets [mm], got {self.goals_mm}")
        if self.goals_mm and not np.all(np.isfinite(self.goals_mm)):
            raise ValueError(f"control: 'goals_mm' must be finite, got {self.goals_mm}")
        if not is_count(self.after_iterations, 1):
            raise ValueError(f"control: 'after_iterations' must be an integer >= 1, got {self.after_iterations!r}")
        if self.rows not in ("position", "full"):
            raise ValueError(f"control: 'rows' must be 'position' or 'full', got '{self.rows}'")
        if not (np.isfinite(self.damping) and self.damping >= 0):
            raise ValueError(f"control: 'damping' must be finite and >= 0, got {self.damping}")
        for name in ("tol_position_mm", "tol_rotation_deg", "clip_mm", "window_mm"):
            v = getattr(self, name)
            if name == "window_mm" and v is None:
                continue
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"control: '{name}' must be positive and finite, got {v}")
        if not is_count(self.anchor_frames, 1):
            raise ValueError(f"control: 'anchor_frames' must be an integer >= 1, got {self.anchor_frames!r}")
        if not is_count(self.max_periods, 1):
            raise ValueError(f"control: 'max_periods' must be an integer >= 1, got {self.max_periods!r}")
        return self

    def start_sec(self, period_sec: float) -> float:
        """When the switch hands the tendons to the controller: the period after the last
        exploration action [s] (the controller holds them for ``anchor_frames`` periods, then
        controls)."""
        return (self.after_iterations + 1) * period_sec

    def iterations_to_finish(self) -> int:
        """Filter iterations (action periods) a run needs for every goal to be reached or
        given up: the exploration's (iteration k reads period k's action; period 0 holds the
        grasp), the anchor's frames (the first in the period the switch hands over) and
        ``max_periods`` for each goal; the last goal is given up in the last of these
        periods, before its filter iteration. 0 without goals (identification only)."""
        if not self.goals_mm:
            return 0
        return self.after_iterations + self.anchor_frames + len(self.goals_mm) * self.max_periods


@dataclass
class Scenario:
    """One self-identification run (DESIGN.md section 8): plant, hand, object and settings."""

    # Name of the scenario (names the diagram and its rendered picture in diagrams/).
    name: str = "default"
    # Seed of every random draw of the run (the systems get seed + a fixed offset each).
    seed: int = 0
    # The plant: "model" (VLR model, exact truth, fast), "physics" (MultibodyPlant +
    # rendered palm camera + AprilTag observer) or "hardware" (real motors and camera).
    plant: str = "physics"
    # Hand preset: "model_o", "NH1", "NH2", "NH3". Leave it out when giving hand_spec.
    hand: str = "model_o"
    # A hand written out in full (any N fingers and K joints); replaces the preset.
    hand_spec: HandSpec | None = None
    # Object preset (see vlr_drake.objects.preset_names()). Leave it out when giving object_spec.
    object: str = "apple"
    # An object written out in full (shape, size, mass, tag id and size, placement).
    object_spec: ObjectSpec | None = None
    # The palm camera (intrinsics, pose X_PC in the palm, render scale, pixel noise).
    camera: CameraConfig = field(default_factory=CameraConfig)
    # The physics plant's settings (time step, contact, tendon ramp and settle, pretension).
    physics: PhysicsConfig = field(default_factory=PhysicsConfig)
    # The AprilTag observer (its tag_id and tag_size are taken from the object).
    observer: TagObserverConfig = field(default_factory=TagObserverConfig)
    # The particle filter (particles, likelihood noise, resampling, convergence).
    filter: pf.FilterConfig = field(default_factory=pf.FilterConfig)
    # Whether the filter's model carries the weight of the fingers' links, with gravity from
    # the physics section's mounting (physics plant only). None: the default of the plant and
    # experiment (vlr_drake.identify.LINK_WEIGHT: on for every physics experiment, with the
    # loads held through each move or following the angles as vlr_drake.identify.GRAVITY_LOADS
    # says; off for the model plant, whose truth is Eq. 9). A hardware hand gives its gravity
    # in the palm frame as filter.gravity_palm instead.
    link_weight: bool | None = None
    # The filter's prior around the nominal grasp.
    prior: PriorSettings = field(default_factory=PriorSettings)
    # The filter's action (the tendon pulls it moves its hypotheses by): "measured" (the
    # hand's tendon_position_measured: what the plant applied; the model plant keeps its
    # pose when it finds no equilibrium for a command, a motor may lag) or "commanded" (the
    # exploration policy's tendon_command).
    filter_action: str = "measured"
    # The random exploration policy.
    exploration: ExplorationSettings = field(default_factory=ExplorationSettings)
    # The model plant's truth and camera stand-in (plant "model" only; its
    # center_offset_fraction also sizes the physics plant's guess of the contacts).
    model_plant: ModelPlantSettings = field(default_factory=ModelPlantSettings)
    # The nominal grasp for the hardware plant.
    grasp: NominalGrasp = field(default_factory=NominalGrasp)
    # Motors and camera of a real hand (plant "hardware" only); relative file names are
    # resolved against the scenario file's folder.
    hardware: HardwareConfig | None = None
    # Show the physics plant in Meshcat (the builder then needs a Meshcat instance).
    meshcat: bool = False
    # Control after identification (python -m vlr_drake.builder --run); no goals: none.
    control: ControlSettings = field(default_factory=ControlSettings)

    # -- resolved parts ----------------------------------------------------------------------

    def hand_spec_resolved(self) -> HandSpec:
        """The hand: ``hand_spec`` when given, else the preset ``hand``."""
        if self.hand_spec is not None:
            return copy.deepcopy(self.hand_spec)
        return hand_by_name(self.hand)

    def object_spec_resolved(self) -> ObjectSpec:
        """The object: ``object_spec`` when given, else the preset ``object``."""
        if self.object_spec is not None:
            return copy.deepcopy(self.object_spec)
        return preset(self.object)

    def experiment(self) -> str:
        """The identification experiment its prior describes: "stiffness", "novel_fingers"
        or "known_hand" (what the prior leaves unknown)."""
        return _experiment_of(self.prior)

    def period_sec(self) -> float:
        """The action period T [s] (``exploration.period_sec`` or the plant's own)."""
        if self.exploration.period_sec > 0:
            return float(self.exploration.period_sec)
        return float(self.physics.action_period) if self.plant == "physics" else 1.0

    def validate(self) -> "Scenario":
        """Check every section; raises ``ValueError`` naming the section and field."""
        # the name names the run's files in its output folder: a plain stem, no path (a
        # review's '../../../escaped' wrote outside --out) and not empty
        if not (isinstance(self.name, str) and re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.-]*", self.name)):
            raise ValueError(f"'name' must be a plain file name (letters, digits, '_', '.', '-'; it names the run's "
                             f"output files), got {self.name!r}")
        if not is_count(self.seed):
            raise ValueError(f"'seed' must be an integer >= 0, got {self.seed!r}")
        if self.physics.seed != 0:  # it would be replaced without a word
            raise ValueError(f"physics: 'seed' ({self.physics.seed!r}) is set from the scenario's 'seed', which "
                             "every random draw of the run takes (the camera's pixel noise too): set 'seed'")
        if self.plant not in PLANTS:
            raise ValueError(f"'plant' must be one of {list(PLANTS)}, got '{self.plant}'")
        if self.filter_action not in FILTER_ACTIONS:
            raise ValueError(
                f"'filter_action' must be one of {list(FILTER_ACTIONS)}, got '{self.filter_action}'"
            )
        if self.hand_spec is None and self.hand not in HAND_PRESETS:
            raise ValueError(
                f"'hand' must be a preset {list(HAND_PRESETS)} or hand_spec given, got '{self.hand}'"
            )
        if self.object_spec is None and self.object not in preset_names():
            raise ValueError(
                f"'object' must be a preset {preset_names()} or object_spec given, got '{self.object}'"
            )
        hand = self.hand_spec_resolved()
        _with_section("hand_spec" if self.hand_spec is not None else "hand", hand.validate)
        _with_section(
            "object_spec" if self.object_spec is not None else "object", self.object_spec_resolved().validate
        )
        _with_section("camera", self.camera.validate)
        _with_section("physics", self.physics.validate)
        names = {"hand": hand.name, "object": self.object_spec_resolved().name}
        for what, name in names.items():  # Drake's model instances (they had ended in its traceback)
            if name in DRAKE_RESERVED_NAMES:
                raise ValueError(f"{what}: the name '{name}' is Drake's own (a model instance it reserves); "
                                 f"rename the {what}")
        if names["hand"] == names["object"]:
            raise ValueError(f"hand and object are both named '{names['hand']}': Drake names its model instances "
                             f"by them, so they must differ")
        model = hand.model()
        if self.physics.pretension_mode_for(model) == "thumb_factor" and not thumb_indices(model.names):
            # (it had gone to no finger)
            raise ValueError(f"physics: pretension_mode 'thumb_factor' gives thumb_factor to the fingers named "
                             f"thumb...; the hand '{hand.name}' has none ({[f.name for f in hand.fingers]}): name "
                             f"one, or use 'balanced'")
        _with_section("filter", self.filter.validate)
        for name in ("tag_id", "tag_size"):  # the object's: they had been replaced without a word
            mine, default = getattr(self.observer, name), getattr(TagObserverConfig(), name)
            if _differs(mine, default):
                raise ValueError(f"observer: '{name}' ({mine!r}) is the object's tag: set it in object_spec "
                                 f"('{name}'; a preset object has its own), which the camera renders and the "
                                 "observer looks for")
        obs = copy.deepcopy(self.observer)
        obs.tag_size = self.object_spec_resolved().tag_size
        _with_section("observer", obs.validate)
        N, K = hand.num_fingers, hand.num_joints_per_finger
        self.prior.validate(N, K)
        _with_section("prior", lambda: self.prior.to_prior().contact_bounds(model))
        self.exploration.validate()
        travel = float(np.min(np.diff(model.tendon_range, axis=1)))
        for name in ("span", "window", "squeeze", "squeeze_window"):  # (0.8 meant as mm had run)
            if getattr(self.exploration, name) is not None:
                units.check_length(getattr(self.exploration, name), f"exploration: '{name}'", travel,
                                   f"more than a tendon's whole travel ({1e3 * travel:g} mm)")
        self.model_plant.validate(N, K)
        self.grasp.validate(N, K, model)
        self.control.validate()
        if self.plant != "hardware" and np.any(self.filter.gravity_palm):
            raise ValueError(f"filter: 'gravity_palm' is a hardware hand's mounting; the {self.plant} plant sets "
                             "it from its own ('link_weight')")
        if self.prior.object_mass is not None and self.plant == "model":
            raise ValueError("prior: 'object_mass': the model plant's truth (Eq. 9) has no weight; a weighed object "
                             "needs the physics or hardware plant")
        if self.link_weight and self.plant != "physics":
            raise ValueError(f"'link_weight': only the physics plant knows its mounting (plant '{self.plant}'); "
                             "a hardware hand gives filter.gravity_palm, the model plant has no link weight")
        phase = pf.FILTER_PHASE  # the filter measures at 0.9 T
        if self.plant == "physics":  # ... when the tendons' ramp is over
            T, ramp = self.period_sec(), self.physics.ramp_time + 2 * self.physics.ramp_update_period
            if phase * T < ramp:  # (a review: 0.15 s against a 0.2 s ramp read tendons mid-ramp)
                # the period given, or the plant's own (ramp and settle): name the fields that made it
                given = (f"exploration: 'period_sec' {T} s" if self.exploration.period_sec > 0 else
                         f"the physics plant's period {T:.3g} s (physics: ramp_time, and fixed_settle_time or "
                         "settle_max; exploration: 'period_sec' not given)")
                raise ValueError(
                    f"{given}: the filter measures at {phase:g} of it ({phase * T:.3g} s), "
                    f"before the tendons' ramp ends (physics.ramp_time {self.physics.ramp_time} s, and two "
                    f"updates): a period of at least {ramp / phase:.3g} s")
        if self.plant == "hardware":
            if self.hardware is None:
                raise ValueError("'hardware': plant 'hardware' needs a hardware section")
            _with_section("hardware", lambda: self.hardware.validate(num_fingers=N))
            # the exploration's rules that options_from_scenario checks on the other plants
            # (a review: a span past the hardware's 1.2 mm window was built and run, its draws
            # reflected once and clipped onto the window's edges)
            span, window = self.exploration.span_and_window(self.plant)
            if not span <= window:
                raise ValueError(f"exploration: 'span' ({span} m) must not exceed 'window' ({window} m; the "
                                 "hardware's default where not given): each action is reflected inside the window")
            squeeze, squeeze_window = self.exploration.squeeze_and_window(self.plant, self.experiment())
            if squeeze > squeeze_window or (squeeze > 0) != (squeeze_window > 0):
                raise ValueError(f"exploration: 'squeeze' ({squeeze} m) must be in (0, 'squeeze_window'] "
                                 f"({squeeze_window} m), or both 0 (the defaults of the plant and experiment "
                                 "where not given)")
            T = self.period_sec()
            if self.hardware.period_s * HARDWARE_UPDATES_PER_ACTION_MIN > T * (1 + 1e-9):
                raise ValueError(
                    f"hardware: 'period_s' {self.hardware.period_s} s must be at most 1/"
                    f"{HARDWARE_UPDATES_PER_ACTION_MIN} of the action period ({T} s): the motors get each action's "
                    "command at the interface's next update, and the filter measures 0.9 of a period after it"
                )
            from vlr_drake.hardware.camera import resolved_mode

            newest = phase * T - 2 * self.hardware.period_s  # the motors have the action by then, at the latest
            if resolved_mode(self.hardware.camera_mode, self.hardware.camera) == "latest" and \
                    self.hardware.camera_max_frame_age_s > newest:  # (a review: a frozen camera's frame from
                # before the action, 0.18 s old, was taken as its result at T = 0.25 s)
                raise ValueError(
                    f"hardware: 'camera_max_frame_age_s' {self.hardware.camera_max_frame_age_s} s lets a frame from "
                    f"before the action count as its measurement: at most {phase:g} T - 2 period_s = {newest:.3g} s "
                    f"(T = {T} s)")
        else:
            # One YAML, one run: what `vlr-drake identify --scenario` refuses (an exploration span
            # past its window, an object's weight without the links', a squeeze on the model
            # plant, ...) is refused here, for the diagram builder too (a review found such
            # files built and run by the one and refused by the other).
            options_from_scenario(self).validate()
        return self


def _with_section(section: str, check) -> None:
    try:
        check()
    except ValueError as e:
        msg = str(e)
        raise ValueError(msg if msg.startswith(section) else f"{section}: {msg}") from e


#: A preset name no scenario file gives (load_scenario's "not given").
_UNSET = "\0unset"


def load_scenario(path: str | Path, overrides: str | list[str] | None = None) -> Scenario:
    """Load a scenario: ``yaml_load_typed(filename=path)`` on the defaults, then the YAML
    ``overrides`` text (or each of a list of texts, in order) on the result; resolve the
    hardware section's relative file names against the file's folder; validate every
    section (:meth:`Scenario.validate`).

    Raises ``ValueError`` naming the file and the field for an unknown field, a value of the
    wrong type, both a preset and a full spec given, a missing file, or a failed check.
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: scenario file not found")
    try:  # a trace (.npz) given as a scenario had ended in "'utf-8' codec can't decode byte 0xb4 ..."
        file_text = path.read_text()
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not a scenario YAML file (not text; a trace .npz is replayed with "
                         "vlr-drake replay)") from None
    # Load with unset preset names so that a preset written next to a full spec is caught
    # (a sentinel no file writes: an empty name given is an error, not the default)
    scenario = Scenario(hand=_UNSET, object=_UNSET)
    # each override text in order (a second --set had replaced the first without a word)
    texts = [overrides] if isinstance(overrides, str) else list(overrides or [])
    for source, text in [("file", None)] + [("override text", t) for t in texts if t]:
        kwargs = dict(filename=str(path)) if source == "file" else dict(data=text)
        text = file_text if source == "file" else text
        duplicate = _duplicate_key(text)
        if duplicate:
            raise ValueError(f"{path} ({source}): {duplicate}")
        if source == "file":
            _check_some_scenario_field(path, text)
        try:
            scenario = yaml_load_typed(schema=Scenario, defaults=scenario, **kwargs)
        except Exception as e:  # the loader raises RuntimeError, ValueError, TypeError ...
            where = _locate_error(text, scenario)
            raise ValueError(f"{path} ({source}){where}: {e}") from e
    for preset_field, spec_field, default in [
        ("hand", "hand_spec", "model_o"),
        ("object", "object_spec", "apple"),
    ]:
        name, spec = getattr(scenario, preset_field), getattr(scenario, spec_field)
        if name != _UNSET and spec is not None:
            raise ValueError(f"{path}: give either '{preset_field}' or '{spec_field}', not both")
        if name == _UNSET:
            setattr(scenario, preset_field, default if spec is None else "")
    if scenario.hardware is not None:
        scenario.hardware.resolve_paths(path.resolve().parent)
        cal = Path(scenario.hardware.calibration_file)
        if not cal.is_file():
            raise ValueError(f"{path}: field 'hardware.calibration_file': file not found: {cal}")
    try:
        scenario.validate()
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from e
    return scenario


def _check_some_scenario_field(path: Path, text: str) -> None:
    """Refuse an empty file, one whose top level is no mapping, and one whose top-level
    mapping has more fields that are no scenario's than fields that are (at least 3): a run's
    result JSON given as --scenario had been refused with every one of its 50 fields listed."""
    import yaml

    try:
        root = yaml.safe_load(text)
    except yaml.YAMLError:
        return  # the loader says why
    # (an empty file had been "YAML root was a <class 'NoneType'> but should have been a dict")
    if root is None:
        raise ValueError(f"{path}: the scenario file is empty (a scenario is a YAML mapping of fields: "
                         "name, seed, plant, hand, object, filter, prior, ...)")
    if not isinstance(root, dict):
        raise ValueError(f"{path}: a scenario is a YAML mapping of fields (name, seed, plant, hand, object, "
                         f"filter, prior, ...), got a {type(root).__name__}")
    if not root:
        return
    known = {f.name for f in dataclasses.fields(Scenario)}
    unknown = [str(k) for k in root if str(k) not in known]
    if len(unknown) >= 3 and len(unknown) > len(root) - len(unknown):  # (a result JSON shares seed, plant, hand)
        shown = ", ".join(unknown[:4]) + (", ..." if len(unknown) > 4 else "")
        raise ValueError(f"{path}: not a scenario file: {len(unknown)} of its {len(root)} fields ({shown}) are "
                         f"no scenario's (name, seed, plant, hand, object, filter, prior, ...: "
                         "vlr_drake.scenario.Scenario); a run's result JSON is no scenario")


def _duplicate_key(text: str) -> str:
    """"field 'a.b' is given twice (lines 3 and 9)" for the first key that a mapping of the
    YAML ``text`` repeats ("" if none, or if the text does not parse: the loader says why).
    YAML loaders keep the last value silently, so a setting written twice would be lost."""
    import yaml

    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError:
        return ""

    seen_nodes = set()  # an alias repeats a node (and may contain itself): each is read once

    def walk(node, prefix):
        if id(node) in seen_nodes:
            return ""
        seen_nodes.add(id(node))
        if isinstance(node, yaml.MappingNode):
            seen = {}
            for key, value in node.value:
                if not isinstance(key, yaml.ScalarNode):  # a complex key: the loader refuses it
                    continue
                name = f"{prefix}{key.value}"
                if key.value in seen:
                    return (f"field '{name}' is given twice (lines {seen[key.value] + 1} and "
                            f"{key.start_mark.line + 1})")
                seen[key.value] = key.start_mark.line
                found = walk(value, f"{name}.")
                if found:
                    return found
        elif isinstance(node, yaml.SequenceNode):
            for i, item in enumerate(node.value):
                found = walk(item, f"{prefix[:-1]}[{i}].")
                if found:
                    return found
        return ""

    return walk(root, "") if root is not None else ""


def _dataclass_of(t) -> type | None:
    """The dataclass a field type holds (itself, Optional[...] of it, or list[...] of it)."""
    if dataclasses.is_dataclass(t) and isinstance(t, type):
        return t
    for a in typing.get_args(t):
        d = _dataclass_of(a)
        if d is not None:
            return d
    return None


def _unknown_fields(data, schema: type, prefix: str) -> list[str]:
    """Dotted names of the keys in ``data`` that ``schema`` (a dataclass) does not have."""
    if not isinstance(data, dict):
        return []
    fields = {f.name: f.type for f in dataclasses.fields(schema)}
    bad = []
    for key, value in data.items():
        name = f"{prefix}{key}"
        if key not in fields:
            bad.append(name)
            continue
        sub = _dataclass_of(fields[key])
        if sub is None:
            continue
        items = value if isinstance(value, list) else [value]
        for i, item in enumerate(items):
            bad += _unknown_fields(item, sub, f"{name}[{i}]." if isinstance(value, list) else f"{name}.")
    return bad


def _locate_error(text: str, defaults: Scenario) -> str:
    """Best effort: ", field 'a.b'" for the field behind a loader error in the YAML ``text``
    (an unknown field, or the top-level section that alone fails to load); "" if not found."""
    import yaml

    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError:
        return ""
    if not isinstance(data, dict):
        return ""
    bad = _unknown_fields(data, Scenario, "")
    if bad:
        return f", unknown field '{bad[0]}'"
    def loads(path: list, value) -> bool:
        nested = value
        for key in reversed(path):
            nested = {key: nested}
        try:
            yaml_load_typed(schema=Scenario, data=yaml.safe_dump(nested), defaults=copy.deepcopy(defaults))
        except Exception:
            return False
        return True

    def first_bad(path: list, value) -> list | None:
        """The deepest path under ``path`` whose value alone fails to load."""
        if loads(path, value):
            return None
        if isinstance(value, dict):
            for key, sub in value.items():
                found = first_bad(path + [key], sub)
                if found is not None:
                    return found
        return path

    for key, value in data.items():
        bad = first_bad([key], value)
        if bad is not None:
            section = bad == [key] and dataclasses.is_dataclass(getattr(defaults, key, None))
            if section and not isinstance(value, dict):  # e.g. "filter: null" or a list
                return f", field '{key}' (a section: a mapping of its fields, e.g. '{key}: {{...}}')"
            return f", field '{'.'.join(map(str, bad))}'"
    return ""


def example_scenarios(folder: str | Path | None = None) -> list[Path]:
    """The scenario files in ``diagrams/`` (sorted)."""
    folder = DIAGRAMS_DIR if folder is None else Path(folder)
    return sorted(p for p in folder.glob("*.yaml") if not p.name.startswith("_"))


def find_scenario(name_or_path: str | Path) -> Path:
    """The scenario file ``name_or_path`` names: a YAML file, or an example's name in
    ``diagrams/`` (``default``, ``model_plant``, ...). Raises ``ValueError`` naming what was
    asked for and what is accepted."""
    path = Path(name_or_path)
    if path.is_file():
        return path
    example = DIAGRAMS_DIR / f"{name_or_path}.yaml"
    if example.is_file():
        return example
    names = ", ".join(p.stem for p in example_scenarios())
    if path.is_dir():  # (had been "not found")
        raise ValueError(f"scenario '{name_or_path}' is a folder: give a YAML file in it or an example name ({names})")
    raise ValueError(f"scenario '{name_or_path}' not found: give a YAML file or an example name ({names})")


def _experiment_of(prior: PriorSettings) -> str:
    """The identification experiment a prior describes (what it leaves unknown)."""
    if prior.stiffness_unknown:
        return "stiffness"
    if prior.links_unknown:
        return "novel_fingers"
    return "known_hand"


def _common_settings(scenario: Scenario, path, plant: str | None) -> dict:
    """The settings identification runs and tasks share: seed, plant (``plant`` when given),
    particles, exploration span and window, the model plant's pose noise, the physics plant
    and camera, the scenario's name and file. A hardware scenario needs a plant override."""
    s = scenario
    plant = plant or s.plant
    if plant == "hardware":
        raise ValueError(
            f"scenario '{s.name}': plant 'hardware' runs as a diagram (python -m vlr_drake.builder --run "
            f"{path or 'SCENARIO'}); identification runs and tasks take --plant model or physics"
        )
    span, window = s.exploration.span_and_window(plant)
    out = {
        "scenario": s.name,
        "scenario_path": None if path is None else str(path),
        "seed": s.seed,
        "plant": plant,
        "particles": s.filter.particles,
        "action_range": span,
        "window": window,
        "physics": copy.deepcopy(s.physics),
        "camera": copy.deepcopy(s.camera),
    }
    if plant == "model":
        out["sigma_position"] = s.model_plant.sigma_position
        out["sigma_rotation_deg"] = s.model_plant.sigma_rotation_deg
    return out


def options_from_scenario(scenario: Scenario | None, path: str | Path | None = None, **overrides):
    """The :class:`vlr_drake.identify.IdentifyOptions` of an identification run: the
    scenario's plant, hand (preset or ``hand_spec``), object (preset or ``object_spec``),
    seed, filter (and its particle count), prior, exploration span, window and squeeze, the model
    plant's noise, dropout, contact drift, nominal-grasp offset and true stiffness and link
    lengths (plant "model"), the physics settings and camera, then the ``overrides``
    (IdentifyOptions fields; None means "not given"). ``scenario=None``: the IdentifyOptions
    defaults and the overrides.

    The experiment follows from the prior's unknowns (stiffness, link lengths, or neither);
    an ``experiment`` override may add its unknowns to a prior that has none, and must
    otherwise agree with it. A ``hand``/``object`` override replaces a full spec; another
    hand than the scenario's drops the scenario's finger-wise settings (the prior's
    ``links_unknown``, the model plant's true stiffness and link lengths, the latter two
    warned), and another object than a weighed scenario's (``prior.object_mass``) needs its
    own ``object_mass``. Raises ``ValueError`` naming the conflict."""
    from vlr_drake.identify import IdentifyOptions

    given = {k: v for k, v in overrides.items() if v is not None}
    if scenario is None:
        return IdentifyOptions(**given)
    s = scenario
    inferred = _experiment_of(s.prior)
    if inferred != "known_hand" and given.get("experiment", inferred) != inferred:
        raise ValueError(
            f"scenario '{s.name}' identifies {inferred} (its prior's unknowns), "
            f"not the experiment '{given['experiment']}'"
        )
    opts = _common_settings(s, path, given.get("plant"))
    opts.update(
        experiment=inferred,
        hand=s.hand,
        hand_spec=copy.deepcopy(s.hand_spec),
        object=s.object,
        object_spec=copy.deepcopy(s.object_spec),
        filter=copy.deepcopy(s.filter),
        # a weighed object's range is the run's to make from object_mass and its tolerance
        # (IdentifyOptions), which a flag may weigh again
        prior=dataclasses.replace(s.prior, object_mass=None, object_mass_unknown=True).to_prior()
        if s.prior.object_mass is not None else s.prior.to_prior(),
        object_mass=s.prior.object_mass,
        object_mass_tolerance=s.prior.object_mass_tolerance,
        link_weight=s.link_weight,
        squeeze_range=s.exploration.squeeze,
        squeeze_window=s.exploration.squeeze_window,
        observer=copy.deepcopy(s.observer),
    )
    # the nominal grasp's guess: the model plant's, and the physics plant's contacts
    opts["center_offset_fraction"] = s.model_plant.center_offset_fraction
    if opts["plant"] == "model":
        mp = s.model_plant
        opts.update(
            dropout=mp.dropout,
            contact_drift=mp.contact_drift,
            true_stiffness=copy.deepcopy(mp.stiffness) or None,
            true_link_lengths=copy.deepcopy(mp.link_lengths) or None,
        )
    for preset_field, spec_field in (("hand", "hand_spec"), ("object", "object_spec")):
        if preset_field in given:
            opts[spec_field] = None
    if "hand" in given and (s.hand_spec is not None or given["hand"] != s.hand):
        # the prior's unknown links and the model plant's true springs and links name the
        # scenario's own fingers: another hand's replaced fingers are its own (identify
        # derives them) and its truth is its preset's (reproduce's NH1 row under NH2's
        # scenario had identified a stock Model O finger and NH3's had left one novel finger out)
        dropped = [name for name, v in (("model_plant.stiffness", opts.get("true_stiffness")),
                                        ("model_plant.link_lengths", opts.get("true_link_lengths"))) if v]
        if dropped:  # (the replaced fingers are the hand's own: no loss to say)
            warnings.warn(f"scenario '{s.name}': {', '.join(dropped)} name the fingers of its own hand, not of "
                          f"'{given['hand']}': not used", stacklevel=2)
        opts["prior"].links_unknown = []
        opts.update(true_stiffness=None, true_link_lengths=None)
    own_object = s.object_spec.name if s.object_spec is not None else s.object
    if s.prior.object_mass is not None and "object_mass" not in given and given.get("object", own_object) != own_object:
        # a weighed mass is its own object's (the apple's 68 g had been the wine glass's prior)
        raise ValueError(f"scenario '{s.name}' weighs its object '{own_object}' (prior.object_mass "
                         f"{s.prior.object_mass:g} kg): the object '{given['object']}' needs its own (--object-mass)")
    return IdentifyOptions(**{**opts, **given})


def task_settings(scenario: Scenario | None, path: str | Path | None = None, **overrides) -> dict:
    """Keyword arguments of the tasks (:func:`vlr_drake.tasks.write.run_write`, ``run_maze``,
    ``run_stack``) from a scenario: seed, plant, the filter's particle count, exploration span
    and window where the scenario sets them (the grip window of the control too; else the
    tasks' defaults), the model plant's pose noise and dropout, the
    physics settings and camera, the scenario's name and file; then the ``overrides`` that
    are not None. The tasks hold their own objects (pen stand-in, maze plate, cups) with the
    Model O: a scenario with another hand raises ``ValueError``."""
    given = {k: v for k, v in overrides.items() if v is not None}
    if scenario is None:
        return given
    s = scenario
    if s.hand_spec is not None or s.hand != "model_o":
        hand = s.hand_spec.name if s.hand_spec is not None else s.hand
        raise ValueError(f"scenario '{s.name}': the tasks run with the Model O hand (model_o), not '{hand}'")
    settings = _common_settings(s, path, given.get("plant"))
    # a scenario without exploration span or window leaves the tasks' own defaults
    # (tasks.common.TASK_EXPLORATION, whose window is also the control's grip window)
    if s.exploration.span is None:
        del settings["action_range"]
    if s.exploration.window is None:
        del settings["window"]
    if settings["plant"] == "model":  # the model plant's lost tags (they had been said and not used)
        settings["dropout"] = s.model_plant.dropout
    return {**settings, **given}


#: Names of Drake's own model instances, which a hand or an object cannot take.
DRAKE_RESERVED_NAMES = ("world", "WorldModelInstance", "DefaultModelInstance")


#: What the tasks take from a scenario (task_settings): the rest is theirs or the task's own.
TASK_SECTIONS = {"name", "seed", "plant", "hand", "camera", "physics", "meshcat"}
TASK_FIELDS = {"filter": {"particles"}, "exploration": {"span", "window"},
               "model_plant": {"sigma_position", "sigma_rotation_deg", "dropout"}}


def ignored_by_tasks(scenario: Scenario, plant: str | None = None) -> list[str]:
    """The fields of ``scenario`` set away from their defaults that the tasks do not use
    (they hold their own objects, and build their filter, prior and truth themselves), nor,
    of those they take, the task's ``plant`` (default: the scenario's; :func:`ignored_by_plant`:
    the model plant's camera and physics, the physics plant's the model plant's noise), as
    dotted names, so that a command can say so rather than ignore them silently."""
    default = Scenario()
    out = []
    for f in dataclasses.fields(Scenario):
        if f.name in TASK_SECTIONS:
            continue
        mine, theirs = getattr(scenario, f.name), getattr(default, f.name)
        if f.name in TASK_FIELDS and dataclasses.is_dataclass(mine):
            out += [f"{f.name}.{g.name}" for g in dataclasses.fields(mine)
                    if g.name not in TASK_FIELDS[f.name] and _differs(getattr(mine, g.name), getattr(theirs, g.name))]
        elif _differs(mine, theirs):
            out.append(f.name)
    taken = [*TASK_SECTIONS, *(f"{section}.{name}" for section, names in TASK_FIELDS.items() for name in names)]
    by_plant = [n for n in _plant_ignores(scenario.plant if plant is None else plant) if n in taken]
    return out + [n for n in _set_fields(scenario, by_plant) if n not in out]


#: What an identification run (``vlr-drake identify``) does not take from a scenario: the
#: diagram's own settings (the filter's action input, the action period in simulated time,
#: the hardware's grasp section, the control after identification; :func:`vlr_drake.builder.run`
#: takes them).
IDENTIFY_IGNORES = ("filter_action", "grasp", "exploration.period_sec", "control")


def ignored_by_identify(scenario: Scenario, plant: str | None = None) -> list[str]:
    """The fields of ``scenario`` set away from their defaults that an identification run on
    ``plant`` (default: the scenario's) does not use (:data:`IDENTIFY_IGNORES` and
    :func:`ignored_by_plant`), as dotted names, so that the command can say so."""
    return _set_fields(scenario, [*IDENTIFY_IGNORES, *_plant_ignores(scenario.plant if plant is None else plant)])


def ignored_by_plant(scenario: Scenario, plant: str | None = None) -> list[str]:
    """The sections and fields of ``scenario`` set away from their defaults that ``plant``
    (default: the scenario's) does not use, as dotted names: the model plant takes no object,
    camera, observer or physics; the others take no model-plant truth (the physics plant does take
    ``model_plant.center_offset_fraction``, for its guess of the contacts); only hardware
    takes ``grasp``, ``hardware`` and ``filter.gravity_palm``, and of the camera only its pose
    (``camera.xyz`` and ``rpy_deg``: the intrinsics are the calibration file's)."""
    return _set_fields(scenario, _plant_ignores(scenario.plant if plant is None else plant))


def _plant_ignores(plant: str) -> list[str]:
    names = []
    if plant == "model":  # (its truth is the VLR: no object, camera or contact physics)
        names += ["object", "object_spec", "camera", "observer", "physics"]
    else:
        names += [f"model_plant.{f.name}" for f in dataclasses.fields(ModelPlantSettings)
                  if not (plant == "physics" and f.name == "center_offset_fraction")]
    if plant == "hardware":
        names.append("physics")
        # the camera's intrinsics and images are the calibration file's and the real camera's:
        # of the camera section only its pose in the palm is used (a review: a width or field of
        # view written for the real camera had been dropped without a word)
        names += [f"camera.{f.name}" for f in dataclasses.fields(CameraConfig) if f.name not in ("xyz", "rpy_deg")]
    else:
        names += ["grasp", "hardware", "filter.gravity_palm"]
    return names


def _set_fields(scenario: Scenario, names) -> list[str]:
    default = Scenario()
    out = []
    for name in dict.fromkeys(names):  # (in order, once each)
        mine, theirs = scenario, default
        for part in name.split("."):
            mine, theirs = getattr(mine, part), getattr(theirs, part)
        if _differs(mine, theirs):
            out.append(name)
    return out


def _differs(a, b) -> bool:
    try:
        return not bool(np.all(np.asarray(a == b)))
    except (TypeError, ValueError):  # e.g. arrays of other shapes
        return True


def config_overrides(config, items: list[str], flag: str, kinds: tuple = (float, int, bool, str)):
    """A copy of the dataclass ``config`` with ``KEY=VALUE`` overrides of its scalar fields
    (those whose type is one of ``kinds``, optionally ``| None``; "none" sets such a field
    to None) and of its vectors of floats (``KEY=X,Y,Z``, as many as it has), validated when the
    class has ``validate()``. A bad key or value is named with the command-line ``flag`` it
    came from."""
    cls = type(config)
    hints = typing.get_type_hints(cls)
    scalar, vector = {}, {}
    for f in dataclasses.fields(cls):
        t, args = hints[f.name], typing.get_args(hints[f.name])
        optional = type(None) in args and len(args) == 2
        if optional:
            t = next(a for a in args if a is not type(None))
        targs = typing.get_args(t)
        if t in kinds:
            scalar[f.name] = (t, optional)
        elif float in kinds and typing.get_origin(t) in (tuple, list) and targs and all(a is float for a in targs):
            # as many numbers as a tuple type has, else as the value has now
            current = getattr(config, f.name)
            n = len(targs) if typing.get_origin(t) is tuple else (None if current is None else len(current))
            vector[f.name] = (n, optional, typing.get_origin(t))
    out = copy.deepcopy(config)
    for item in items:
        key, sep, value = item.partition("=")
        if sep and key in vector:
            n, optional, kind = vector[key]
            if optional and value.lower() == "none":
                setattr(out, key, None)
                continue
            count = "" if n is None else f"{n} "
            try:
                v = tuple(float(x) for x in value.split(","))
            except ValueError:
                raise ValueError(f"{flag} '{item}': '{value}' is not {count}comma-separated numbers") from None
            if n is not None and len(v) != n:
                raise ValueError(f"{flag} '{item}': '{key}' takes {n} comma-separated numbers, got {len(v)}")
            setattr(out, key, list(v) if kind is list else v)
            continue
        if not sep or key not in scalar:
            raise ValueError(f"{flag} '{item}': expected KEY=VALUE with KEY one of {', '.join(sorted({*scalar, *vector}))}")
        t, optional = scalar[key]
        if optional and value.lower() == "none":
            v = None
        elif t is bool:
            if value.lower() not in ("true", "false", "1", "0"):
                raise ValueError(f"{flag} '{item}': '{value}' is not true or false")
            v = value.lower() in ("true", "1")
        elif t is str:
            v = value
        else:
            try:
                v = t(value)
            except ValueError:
                raise ValueError(f"{flag} '{item}': '{value}' is not {'an integer' if t is int else 'a number'}") from None
        setattr(out, key, v)
    return out.validate() if hasattr(out, "validate") else out
