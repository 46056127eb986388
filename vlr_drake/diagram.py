"""Compatibility name for the model-plant identification diagram.

The one builder is :mod:`vlr_drake.builder` (scenario -> diagram for the model plant, the
physics plant or hardware); this module keeps the model-plant entry point under its
earlier name.
"""

from vlr_drake.builder import BuiltDiagram as IdentificationDiagram
from vlr_drake.builder import build_model_plant_diagram as build_model_identification_diagram

__all__ = ["IdentificationDiagram", "build_model_identification_diagram"]
