"""vlr_drake: self-identifying in-hand manipulation with virtual linkage-based representations.

The math (hand model, motion function Gamma, observation function Lambda, particle filter,
Jacobian controller) is plain vectorised numpy/numba with particles on the leading axis;
``vlr_drake.systems`` wraps it as Drake LeafSystems.
"""

from vlr_drake.hand import FingerSpec, HandModel, HandSpec, hand_by_name, model_o

__version__ = "0.1.0"
__all__ = ["FingerSpec", "HandModel", "HandSpec", "hand_by_name", "model_o", "__version__"]
