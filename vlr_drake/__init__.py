"""vlr_drake: self-identifying in-hand manipulation with virtual linkage-based representations.

The math (hand model, motion function Gamma, observation function Lambda, particle filter,
Jacobian controller) is plain vectorised numpy/numba with particles on the leading axis;
``vlr_drake.systems`` wraps it as Drake LeafSystems.
"""

import hashlib
import os
from pathlib import Path

# The filter runs many short parallel kernels per iteration (ESS reductions, contacts,
# intervals). With OpenMP's default wait policy an idle thread spins at each barrier, which
# on a shared 2-core machine takes the core from the thread doing the work. Passive waiting
# costs nothing measurable on an idle machine (bench filter, 60,000 particles: median 148 /
# 153 ms against 147 / 156 with the default) and helps when two jobs share the cores (two
# benches side by side: median 216 / 226 ms and first iteration 376 / 320 ms, against 257 /
# 302 and 434 / 938). It must be set before numba loads its OpenMP pool; a user's own
# setting wins. Results do not depend on it (fixed reduction order).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

#: Modules with compiled kernels (numba, ``cache=True``). Kernels call each other across them.
_KERNEL_MODULES = ("kinematics.py", "motion.py", "observation.py")


def _drop_stale_kernel_caches(here: Path = Path(__file__).parent) -> None:
    """Delete numba's on-disk kernel caches when any kernel module changed.

    numba keys a cached kernel on its own file's timestamp only, so after an edit (or a
    ``git pull``) that changes ``kinematics.py`` alone, ``motion.py``'s cached kernels would
    keep the old, inlined kinematics: silently stale code. A hash of all kernel modules,
    kept beside the caches, catches that. Does nothing where the package folder is read-only.
    """
    digest = hashlib.sha256(b"".join((here / m).read_bytes() for m in _KERNEL_MODULES)).hexdigest()
    cache = here / "__pycache__"
    stamp = cache / "kernels.sha256"
    try:
        if stamp.exists() and stamp.read_text() == digest:
            return
        for f in list(cache.glob("*.nbi")) + list(cache.glob("*.nbc")):
            f.unlink()
        cache.mkdir(exist_ok=True)
        stamp.write_text(digest)
    except OSError:
        pass


_drop_stale_kernel_caches()

from vlr_drake.hand import FingerSpec, HandModel, HandSpec, hand_by_name, model_o  # noqa: E402

__version__ = "0.1.0"
__all__ = ["FingerSpec", "HandModel", "HandSpec", "hand_by_name", "model_o", "__version__"]
