"""Builders that wire the self-identification loop into a Drake diagram.

``build_model_identification_diagram`` wires exploration policy -> model plant -> noisy
pose sensor -> self-identification filter (the fast, exact-truth configuration). Systems
are added by name (``exploration``, ``hand``, ``pose_sensor``, ``self_identification``) and
the truth and estimate ports are exported as ``<system>.<signal>``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydrake.systems.framework import Diagram, DiagramBuilder

from vlr_drake import filter as pf
from vlr_drake.hand import HandModel
from vlr_drake.model_plant import ModelPlant
from vlr_drake.systems.self_identification import (
    ExplorationPolicy,
    ModelPlantSystem,
    SelfIdentificationSystem,
)
from vlr_drake.systems.tag_observer import NoisyPoseSensor

__all__ = ["IdentificationDiagram", "build_model_identification_diagram"]


@dataclass
class IdentificationDiagram:
    diagram: Diagram
    policy: ExplorationPolicy
    plant: ModelPlantSystem
    sensor: NoisyPoseSensor
    filter: SelfIdentificationSystem
    period_sec: float


def build_model_identification_diagram(
    hand: HandModel, plant: ModelPlant, config: pf.FilterConfig, prior: pf.PriorConfig, theta_center, a_center,
    *, period_sec: float = 1.0, sigma_position: float = 0.2e-3, sigma_rotation: float = np.deg2rad(0.5),
    dropout: float = 0.0, seed: int = 0,
) -> IdentificationDiagram:
    builder = DiagramBuilder()
    plant_sys = ModelPlantSystem(plant, period_sec)
    policy = ExplorationPolicy(hand, plant_sys.grasp_command(), period_sec, seed=seed + 1)
    sensor = NoisyPoseSensor(sigma_position, sigma_rotation, dropout_probability=dropout, seed=seed + 2,
                             update_period_sec=period_sec)
    flt = SelfIdentificationSystem(hand, config, prior, theta_center, a_center, period_sec, seed=seed + 3)
    for name, sys in [("exploration", policy), ("hand", plant_sys), ("pose_sensor", sensor),
                      ("self_identification", flt)]:
        builder.AddNamedSystem(name, sys)
    builder.Connect(policy.GetOutputPort("tendon_command"), plant_sys.GetInputPort("tendon_command"))
    builder.Connect(plant_sys.GetOutputPort("X_PO_true"), sensor.GetInputPort("X_PO_true"))
    builder.Connect(policy.GetOutputPort("tendon_command"), flt.tendon_command_input_port())
    builder.Connect(sensor.GetOutputPort("X_PO_measured"), flt.X_PO_measured_input_port())
    builder.Connect(sensor.GetOutputPort("X_PO_valid"), flt.X_PO_valid_input_port())
    for sys, port in [(plant_sys, "theta_true"), (plant_sys, "contacts_true"), (plant_sys, "X_PO_true"),
                      (flt, "estimate"), (flt, "theta_estimate"), (flt, "interval_half_width"), (flt, "converged"),
                      (policy, "tendon_command")]:
        builder.ExportOutput(sys.GetOutputPort(port), f"{sys.get_name()}.{port}")
    diagram = builder.Build()
    diagram.set_name("self_identification_model_plant")
    return IdentificationDiagram(diagram, policy, plant_sys, sensor, flt, period_sec)
