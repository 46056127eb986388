"""Identification traces: what the filter was given during a run, kept so that the run can
be replayed offline.

A trace holds the filter's inputs (its hand, settings, prior, seed, the nominal grasp and
the first POM measurement, then every action with the POM measured after it and the
motors' tendon commands) and, where the plant knows it, the ground truth after each step.
Replaying a trace with the same settings reproduces the run's estimates exactly; with
other filter settings it answers "what would this filter have made of the same
measurements" without the plant (the physics plant's simulation and rendering, or the
hardware). That is exact whenever the actions did not depend on the filter (random
exploration, the physics plant's and hardware's default); informative actions are replayed
as they were chosen.

``run_identification`` records one for every run (``result["_trace"]``), and the
:class:`~vlr_drake.systems.self_identification.SelfIdentificationSystem` keeps one of the
diagram's filter (``trace(context)``; ``python -m vlr_drake.builder --run hardware.yaml
--trace run.npz`` saves a real hand's run, without truths).

Replay also gives the filter's log evidence, sum_t log p(y_t | y_1..t-1) (Eq. 5's
likelihood integrated over the hypotheses), and :func:`evidence_profile` fixes one
identified hand parameter at a list of values and compares their evidence: how strongly
the measurements themselves favour each value, apart from the prior and the filter's
point estimate.

    vlr-drake identify stiffness --trace out/stiffness.npz
    vlr-drake replay out/stiffness.npz --profile stiffness --values 0.13,0.17,0.21,0.25
"""

from __future__ import annotations

import copy
import dataclasses
import json
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vlr_drake import filter as pf
from vlr_drake import motion, units
from vlr_drake.hand import FingerSpec, HandSpec
from vlr_drake.kinematics import is_count
from vlr_drake.observation import is_rotation

__all__ = ["IdentificationTrace", "TraceRecorder", "replay", "pool_replays", "evidence_profile",
           "statics_profile", "PROFILE_PARAMETERS"]

#: Format version written into every trace file.
TRACE_VERSION = 1
#: Hand parameters :func:`evidence_profile` can fix: the prior's (first) unknown stiffness,
#: or the proximal link length of a named finger ("link_length:<finger>").
PROFILE_PARAMETERS = ("stiffness", "link_length:<finger>")
#: Ground-truth arrays a trace keeps per step (the plant's truth dicts).
TRUTH_KEYS = ("theta", "a", "contacts", "stiffness", "link_lengths")
#: Truths a plant may add, kept where every step has them. The physics plant's object: its
#: mass [kg] and its weight's share at each contact [kg]; its true POM pose in the palm frame
#: (``pom_rotation`` (3, 3), ``pom_translation`` (3,) [m]: what the camera measures, without
#: the camera), its centre of mass (``object_com`` (3,) [m], palm frame) and the points where
#: the pads touch it (``touching`` (N, 3) [m], palm frame; ``contacts`` minus ``touching`` is
#: each pad's lever, the rolling model's radius times the object's normal): for analyses
#: with the truths the filter does not see (the camera's error, the rolling model's normals).
OPTIONAL_TRUTH_KEYS = ("object_mass", "object_load", "pom_rotation", "pom_translation", "object_com", "touching")
#: Settings added after traces were first written, with the value that restores the
#: behaviour of the code that wrote a trace lacking them. A replay is bit-exact only with the
#: code that recorded the trace: later kernels may round differently (the 2026-11-24 ones do,
#: by up to 1e-17 m in the contacts), and the filter's resampling can amplify that.
LEGACY_SETTINGS = {"FilterConfig": {"newton_loose_after": None, "parameter_convergence": None}}
#: PriorConfig.contact_limits as traces before 2026-11-25 recorded it: the default then, the
#: Model O's 48 mm pad written for every finger. Where it reaches past a finger's last link
#: (NH3's 40 mm NF3, which it let contacts leave by 8 mm), the trace loads with today's
#: default, each finger's own link; elsewhere (the Model O, NH1, NH2) as it was.
LEGACY_CONTACT_LIMITS = [0.005, 0.048]


@dataclass
class IdentificationTrace:
    """The filter's inputs of one identification run (shapes: T steps, N fingers, K joints)."""

    hand: HandSpec  # the filter's hand
    filter: pf.FilterConfig
    prior: pf.PriorConfig
    filter_seed: int  # seed of the filter's random generator
    theta_center: np.ndarray  # (N, K) nominal grasp [rad]
    a_center: np.ndarray  # (N,) [m]
    R0: np.ndarray  # (3, 3) first POM measurement
    t0: np.ndarray  # (3,) [m]
    tendon_command0: np.ndarray  # (N,) [m]
    actions: np.ndarray  # (T, N) [m]
    R: np.ndarray  # (T, 3, 3), NaN where the tag was lost
    t: np.ndarray  # (T, 3) [m], NaN where the tag was lost
    valid: np.ndarray  # (T,) bool
    tendon_commands: np.ndarray  # (T, N) [m] after each action
    truths: dict[str, np.ndarray] | None = None  # TRUTH_KEYS -> (T + 1, ...), or None (hardware)
    meta: dict = field(default_factory=dict)  # experiment, plant, object, seed, ...

    @property
    def steps(self) -> int:
        return int(self.actions.shape[0])

    def validate(self) -> IdentificationTrace:
        """Check the arrays' shapes against the hand; raises ``ValueError`` naming the field."""
        self.hand.validate()
        seed = self.filter_seed
        if not is_count(seed):
            raise ValueError(f"trace: 'filter_seed' must be an integer >= 0, got {seed!r}")
        if not isinstance(self.meta, dict):
            raise ValueError(f"trace: 'meta' must be a JSON object, got {self.meta!r}")
        extra = self.meta.get("extra_iterations", 0)
        if not is_count(extra):
            raise ValueError(f"trace: meta 'extra_iterations' must be an integer >= 0, got {extra!r}")
        for key in ("experiment", "plant", "hand", "object"):  # (a list had ended replay in a TypeError)
            if not isinstance(self.meta.get(key), str | None):
                raise ValueError(f"trace: meta '{key}' must be a name, got {self.meta[key]!r}")
        # the experiment's unknowns are the prior's (a known-hand trace labelled "stiffness" had
        # ended replay's rows in a TypeError)
        wants = {"stiffness": ("stiffness_unknown", "unknown spring"),
                 "novel_fingers": ("links_unknown", "unknown links")}.get(self.meta.get("experiment"))
        if wants is not None and not getattr(self.prior, wants[0]):
            raise ValueError(f"trace: meta 'experiment' is {self.meta['experiment']!r} but its prior has no "
                             f"{wants[1]} ({wants[0]} is empty)")
        if not isinstance(self.meta.get("stops_at_convergence", False), bool):
            raise ValueError(f"trace: meta 'stops_at_convergence' must be true or false, "
                             f"got {self.meta['stops_at_convergence']!r}")
        N, K, T = self.hand.num_fingers, self.hand.num_joints_per_finger, self.steps
        expected = {"theta_center": (N, K), "a_center": (N,), "R0": (3, 3), "t0": (3,), "tendon_command0": (N,),
                    "actions": (T, N), "R": (T, 3, 3), "t": (T, 3), "valid": (T,), "tendon_commands": (T, N)}
        for name, shape in expected.items():
            got = np.shape(getattr(self, name))
            if got != shape:
                raise ValueError(f"trace: '{name}' must have shape {shape}, got {got}")
        for name in ("theta_center", "a_center", "R0", "t0", "tendon_command0", "actions", "tendon_commands"):
            arr = np.asarray(getattr(self, name))
            if arr.dtype.kind not in "fiu" or not np.all(np.isfinite(arr)):
                where = ""
                if arr.dtype.kind in "fiu" and arr.ndim == 2 and name in ("actions", "tendon_commands"):
                    where = f" (step {int(np.flatnonzero(~np.isfinite(arr).all(axis=1))[0]) + 1})"
                raise ValueError(f"trace: '{name}' must be finite numbers{where}")
        valid = np.asarray(self.valid)
        if valid.dtype.kind in "iu" and np.isin(valid, (0, 1)).all():  # 0/1 flags, as a hand-made trace may have
            valid = valid.astype(bool)
        if valid.dtype != bool:
            raise ValueError(f"trace: 'valid' must be booleans (or 0/1), got {valid.dtype}")
        self.valid = valid  # (a list of flags had failed below in a TypeError on its indexing)
        for name in ("R", "t"):
            if np.asarray(getattr(self, name)).dtype.kind not in "fiu":
                raise ValueError(f"trace: '{name}' must be numbers, got {np.asarray(getattr(self, name)).dtype}")
        bad = self.valid & ~(np.isfinite(self.R).all(axis=(1, 2)) & np.isfinite(self.t).all(axis=1))
        if bad.any():
            raise ValueError(f"trace: step {int(np.flatnonzero(bad)[0]) + 1} is marked valid but its POM pose is not finite")
        # ... nor a rotation (named here, with its step, rather than by the filter mid-replay)
        if not is_rotation(self.R0):
            raise ValueError(f"trace: 'R0' is not a rotation matrix: {np.round(self.R0, 6).tolist()}")
        off = self.valid & ~is_rotation(np.where(self.valid[:, None, None], self.R, np.eye(3)))
        if off.any():
            k = int(np.flatnonzero(off)[0])
            raise ValueError(f"trace: step {k + 1} is marked valid but its POM rotation is not a rotation matrix: "
                             f"{np.round(self.R[k], 6).tolist()}")
        if self.truths is not None:
            if not isinstance(self.truths, dict):
                raise ValueError(f"trace: 'truths' must be a dict of arrays or None, got {type(self.truths).__name__}")
            # arrays, as a loaded trace's are (a hand-made trace's lists had failed in an AttributeError)
            self.truths = {k: np.asarray(v) for k, v in self.truths.items()}
            missing = [k for k in TRUTH_KEYS if k not in self.truths]
            if missing:
                raise ValueError(f"trace: truths lack {missing}")
            unknown = sorted(set(self.truths) - set(TRUTH_KEYS + OPTIONAL_TRUTH_KEYS))
            if unknown:  # (saved, then dropped by load without a word)
                raise ValueError(f"trace: truths {unknown} are not truths a trace keeps: "
                                 f"{list(TRUTH_KEYS + OPTIONAL_TRUTH_KEYS)}")
            for k in self.truths:
                if np.ndim(self.truths[k]) == 0 or self.truths[k].shape[0] != T + 1:
                    raise ValueError(f"trace: truths '{k}' must have {T + 1} rows (start and every step), "
                                     f"got shape {np.shape(self.truths[k])}")
            shapes = {"theta": (N, K), "a": (N,), "contacts": (N, 3), "stiffness": (N, K), "link_lengths": (N, K - 1),
                      "object_mass": (), "object_load": (N,), "pom_rotation": (3, 3), "pom_translation": (3,),
                      "object_com": (3,), "touching": (N, 3)}
            for k, shape in shapes.items():
                if k in self.truths and self.truths[k].shape != (T + 1, *shape):
                    raise ValueError(f"trace: truths '{k}' must have shape {(T + 1, *shape)}, "
                                     f"got {self.truths[k].shape}")
            for k in self.truths:
                if self.truths[k].dtype.kind not in "fiu":
                    raise ValueError(f"trace: truths '{k}' must be numbers, got {self.truths[k].dtype}")
            for k in TRUTH_KEYS:  # (a NaN contact had been scored "outside every interval")
                if not np.all(np.isfinite(self.truths[k])):
                    raise ValueError(f"trace: truths '{k}' must be finite numbers")
        return self

    # ------------------------------------------------------------------ files
    def save(self, path: str | Path) -> Path:
        """Write the trace as one compressed ``.npz`` (arrays, and the settings as JSON)."""
        self.validate()  # (what load would refuse or drop is said before it is written)
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        header = {"version": TRACE_VERSION, "hand": dataclasses.asdict(self.hand),
                  "filter": dataclasses.asdict(self.filter), "prior": dataclasses.asdict(self.prior),
                  "filter_seed": int(self.filter_seed), "meta": self.meta, "has_truths": self.truths is not None}
        arrays = {name: np.asarray(getattr(self, name)) for name in (
            "theta_center", "a_center", "R0", "t0", "tendon_command0", "actions", "R", "t", "valid", "tendon_commands")}
        if self.truths is not None:
            arrays.update({f"truth_{k}": np.asarray(v) for k, v in self.truths.items()})
        from vlr_drake.entry import replacing

        with replacing(path) as temporary, open(temporary, "wb") as fh:  # (in one piece: a cut one is none)
            np.savez_compressed(fh, header=np.array(json.dumps(header, default=_json_default)), **arrays)
        return path

    @staticmethod
    def _read(path: Path) -> tuple[dict, dict]:
        """The header and the arrays of the archive at ``path``, checked (a ``ValueError``
        naming what is wrong; a damaged archive's own errors pass through)."""
        try:
            z = np.load(path, allow_pickle=False)
        except (ValueError, OSError) as e:  # not a NumPy file (numpy's message speaks of pickles)
            raise ValueError(f"{path}: not an identification trace (not a .npz archive written by "
                             f"vlr-drake identify --trace)") from e
        if not hasattr(z, "files"):  # a bare .npy array
            raise ValueError(f"{path}: not an identification trace (a single array, not a .npz archive)")
        with z:
            if "header" not in z.files:
                raise ValueError(f"{path}: not an identification trace (no header)")
            try:
                header = json.loads(str(z["header"]))
            except ValueError:
                header = None
            if not isinstance(header, dict):
                raise ValueError(f"{path}: not an identification trace (its header is not a JSON object)")
            if header.get("version") != TRACE_VERSION:
                raise ValueError(f"{path}: trace version {header.get('version')}, this vlr_drake reads {TRACE_VERSION}")
            arrays = {}
            for k in z.files:
                if k == "header":
                    continue
                try:
                    arrays[k] = z[k]
                except ValueError as e:  # an object array (numpy's message speaks of pickles)
                    raise ValueError(f"{path}: member '{k}' is not an array of numbers or flags ({e})") from None
            return header, arrays

    @classmethod
    def load(cls, path: str | Path) -> IdentificationTrace:
        """Read a trace written by :meth:`save`; raises ``ValueError`` naming what is wrong."""
        path = Path(path)
        if path.is_dir():
            raise ValueError(f"{path} is a folder, not a trace file (a .npz written by vlr-drake identify --trace)")
        if not path.is_file():
            raise FileNotFoundError(f"trace file not found: {path}")
        try:
            header, arrays = cls._read(path)
        except (zipfile.BadZipFile, zlib.error, EOFError) as e:  # truncated or damaged (an interrupted copy)
            raise ValueError(f"{path}: a damaged .npz archive ({e}); copy or record the trace again") from e
        for key in ("hand", "filter", "prior"):
            if key in header and not isinstance(header[key], dict):
                raise ValueError(f"{path}: the header's '{key}' must be a JSON object of settings, "
                                 f"got {type(header[key]).__name__}")
        try:
            truths = ({k: arrays[f"truth_{k}"] for k in TRUTH_KEYS + OPTIONAL_TRUTH_KEYS if f"truth_{k}" in arrays}
                      if header["has_truths"] else None)
            trace = cls(
                hand=_hand_from_dict(header["hand"]),
                filter=_config_from_dict(pf.FilterConfig, header["filter"]),
                prior=_config_from_dict(pf.PriorConfig, header["prior"]),
                filter_seed=header["filter_seed"],
                truths=truths, meta=header.get("meta", {}),
                **{k: arrays[k] for k in ("theta_center", "a_center", "R0", "t0", "tendon_command0", "actions",
                                          "R", "t", "valid", "tendon_commands")},
            )
        except KeyError as e:
            raise ValueError(f"{path}: trace lacks {e}") from None
        except (ValueError, TypeError, AttributeError) as e:  # a setting or an array that is not what it should be
            raise ValueError(f"{path}: {e}") from None
        limits, hand = trace.prior.contact_limits, trace.hand.model()
        if limits is not None and list(limits) == LEGACY_CONTACT_LIMITS:
            try:
                trace.prior.contact_bounds(hand)
            except ValueError:  # the old default, past a shorter finger's pad
                trace.prior.contact_limits = None
        try:  # every setting now, not at its replay (several traces are read before the first replay)
            trace.filter.validate()
            trace.prior.validate(hand.N, hand.K)
            trace.prior.contact_bounds(hand)
            return trace.validate()
        except (ValueError, TypeError) as e:
            raise ValueError(f"{path}: {e}") from None


class TraceRecorder:
    """Collects a trace while an identification runs (``run_identification`` feeds it)."""

    def __init__(self, hand: HandSpec, config: pf.FilterConfig, prior: pf.PriorConfig, filter_seed: int,
                 meta: dict | None = None):
        self._fixed = dict(hand=copy.deepcopy(hand), filter=copy.deepcopy(config), prior=copy.deepcopy(prior),
                           filter_seed=int(filter_seed), meta=dict(meta or {}))
        self._start: dict | None = None
        self._steps: list[tuple] = []
        self._truths: list[dict] = []

    def start(self, theta_center, a_center, R0, t0, tendon_command, truth: dict | None = None) -> None:
        self._start = dict(theta_center=np.array(theta_center, float), a_center=np.array(a_center, float),
                           R0=np.array(R0, float), t0=np.array(t0, float),
                           tendon_command0=np.array(tendon_command, float))
        self._add_truth(truth)

    def step(self, dl, R, t, valid: bool, tendon_command, truth: dict | None = None) -> None:
        valid = bool(valid) and R is not None and t is not None
        self._steps.append((np.array(dl, float), np.array(R, float) if valid else np.full((3, 3), np.nan),
                            np.array(t, float) if valid else np.full(3, np.nan), valid,
                            np.array(tendon_command, float)))
        self._add_truth(truth)

    def records(self) -> list[list]:
        """The recorder's lists that only grow (the steps and the truths): an entry is never
        changed once appended, so a copy of the recorder may share the entries."""
        return [self._steps, self._truths]

    def _add_truth(self, truth):
        if truth is not None:
            self._truths.append({k: np.array(truth[k], float) for k in TRUTH_KEYS + OPTIONAL_TRUTH_KEYS
                                 if k in truth})

    def trace(self) -> IdentificationTrace:
        if self._start is None:
            raise RuntimeError("trace recorder: start() was never called")
        N = self._start["a_center"].shape[0]
        steps = self._steps
        truths = None
        if self._truths and len(self._truths) == len(steps) + 1:
            truths = {k: np.stack([tr[k] for tr in self._truths]) for k in TRUTH_KEYS + OPTIONAL_TRUTH_KEYS
                      if all(k in tr for tr in self._truths)}
        return IdentificationTrace(
            **self._fixed, **self._start,
            actions=np.array([s[0] for s in steps]).reshape(len(steps), N),
            R=np.array([s[1] for s in steps]).reshape(len(steps), 3, 3),
            t=np.array([s[2] for s in steps]).reshape(len(steps), 3),
            valid=np.array([s[3] for s in steps], dtype=bool),
            tendon_commands=np.array([s[4] for s in steps]).reshape(len(steps), N),
            truths=truths,
        ).validate()


# ---------------------------------------------------------------------- replay
def replay(trace: IdentificationTrace, config: pf.FilterConfig | None = None, prior: pf.PriorConfig | None = None,
           hand: HandSpec | None = None, progress: bool = False, stop_at_convergence: bool = False,
           at_steps=()) -> dict:
    """Run the filter over the trace's measurements.

    ``config``, ``prior`` and ``hand`` replace the trace's own (the filter's random seed is
    the run's). Returns ``estimates`` (one per step and the initial one), ``history`` (the
    StepReports), ``log_evidence`` (their sum of ``log_evidence``, NaN steps skipped),
    ``log_evidence_steps`` (one per replayed step), ``steps`` (how many were replayed), ``particles`` and
    ``initial_particles`` (the final and the prior cloud, :func:`pool_replays`), ``hand_parameters`` and
    ``weakly_identified`` (the identified springs and links,
    :func:`vlr_drake.identify.hand_parameter_report`) and, where the trace has truths,
    ``errors`` (the result fields of docs/result-files.md that compare the final estimate with
    the truth at that step).

    ``at_steps`` (iteration counts in 1..the trace's steps, a simulation trace's): also
    ``errors_at``, the same fields for the estimate after each of those steps against the
    truth then, one ``{"steps": k, ...}`` per count the replay reached, in order: what a
    shorter budget would have given, from one replay of a long trace.

    ``stop_at_convergence``: stop where a run with these settings would have stopped, at the
    step where the filter converged plus the run's ``extra_iterations`` (the trace's
    ``meta``; 0 if it has none), instead of at the trace's end; only for a run that stopped
    at convergence (``vlr-drake identify``'s, whose traces say so in ``meta``; a diagram's run
    lasts its iterations, and its trace's ``meta["stops_at_convergence"]`` is False; a trace
    that does not say is taken to be identify's if its ``meta`` has identify's
    ``action_choice``). Without it (the default) every step is
    replayed, as an evidence profile needs. Either way, a replay whose filter has not
    converged ends with the trace, where the recorded run stopped.
    """
    from tqdm.auto import tqdm

    from vlr_drake.identify import estimate_errors, hand_parameter_report

    at_steps = sorted({_step_count(k, trace.steps) for k in at_steps})
    if at_steps and trace.truths is None:
        raise ValueError("at_steps: the trace has no truths to measure the estimates against (a hardware trace)")
    config = copy.deepcopy(trace.filter if config is None else config)
    prior = copy.deepcopy(trace.prior if prior is None else prior)
    spec = trace.hand if hand is None else hand
    h = spec.validate().model()
    f = pf.SelfIdentificationFilter(h, config, prior, np.random.default_rng(trace.filter_seed))
    f.initialise(trace.theta_center, trace.a_center, trace.R0, trace.t0, tendon_command=trace.tendon_command0)
    initial = copy.deepcopy(f.particles)
    extra = int(trace.meta.get("extra_iterations", 0) or 0)
    stop_at_convergence = stop_at_convergence and trace.meta.get("stops_at_convergence",
                                                                 "action_choice" in trace.meta)
    converged_at = None
    for i in tqdm(range(trace.steps), disable=not progress, desc="replay", unit="it", leave=False):
        valid = bool(trace.valid[i])
        rep = f.step(trace.actions[i], trace.R[i] if valid else None, trace.t[i] if valid else None, valid,
                     tendon_command=trace.tendon_commands[i])
        if rep.converged and converged_at is None:
            converged_at = i + 1
        if stop_at_convergence and converged_at is not None and i + 1 >= converged_at + extra:
            break
    steps = np.array([r.log_evidence for r in f.history])
    out = {"estimates": f.estimates, "history": f.history, "log_evidence_steps": steps, "steps": len(f.history),
           "log_evidence": float(np.nansum(steps)), "reinitialisations": f.reinitialisations,
           "converged_at": next((r.iteration for r in f.history if r.converged), None),
           "particles": f.particles, "initial_particles": initial,
           **hand_parameter_report(h, prior, f.estimates[-1], f.estimates[0])}
    if trace.truths is not None:
        # truths[0] is the grasp's, truths[i] the plant's after step i (estimates[i] likewise)
        def errors(i):
            return estimate_errors(h, prior, f.estimates[i], {k: v[i] for k, v in trace.truths.items()})

        out["errors"] = errors(len(f.history))
        if at_steps:
            out["errors_at"] = [{"steps": i, **errors(i)} for i in at_steps if i <= len(f.history)]
    return out


def pool_replays(trace: IdentificationTrace, replays: list[dict], prior: pf.PriorConfig | None = None,
                 hand: HandSpec | None = None) -> dict:
    """One estimate from several :func:`replay` s of ``trace`` under independent draws of the
    filter's randomness: the equal mixture of their final clouds (:meth:`~vlr_drake.filter.
    ParticleSet.pool`), whose mean is the mean of the draws' estimates and whose 95% intervals
    hold the spread between the draws as well as within each. Returns ``draws``, ``steps``,
    ``hand_parameters`` and ``weakly_identified`` (as a replay's, against the pooled prior
    clouds) and, where the trace has truths, ``errors`` (the result fields) against the truth
    at that step. ``prior`` and ``hand`` are the replays' (the trace's by default). The
    replays must have stopped at the same step: the clouds must describe the same instant."""
    from vlr_drake.identify import estimate_errors, hand_parameter_report

    if not replays:
        raise ValueError("pool_replays: no replays to pool")
    steps = sorted({int(r["steps"]) for r in replays})
    if len(steps) > 1:
        raise ValueError(f"the draws stopped at different steps ({steps}), where each converged; their clouds "
                         "describe different instants (replay every step to pool them: vlr-drake replay "
                         "--all-steps)")
    prior = trace.prior if prior is None else prior
    h = (trace.hand if hand is None else hand).validate().model()
    est = pf.cloud_estimate(h, pf.ParticleSet.pool([r["particles"] for r in replays]))
    est0 = pf.cloud_estimate(h, pf.ParticleSet.pool([r["initial_particles"] for r in replays]))
    out = {"draws": len(replays), "steps": steps[0], **hand_parameter_report(h, prior, est, est0)}
    if trace.truths is not None:
        out["errors"] = estimate_errors(h, prior, est, {k: v[steps[0]] for k, v in trace.truths.items()})
    return out


def draw_seed(seed: int, draw: int) -> int:
    """The filter seed of draw ``draw`` of a trace whose filter seed is ``seed`` (``vlr-drake
    replay --draws``, :func:`pool_draws`): draw 0 is the seed itself (the run's own draw), each
    later one a seed derived from both (numpy's SeedSequence), unrelated to the next trace's
    run seed (a run seed plus one would replay trace S + 1's own draw on trace S)."""
    if draw == 0:
        return int(seed)
    return int(np.random.SeedSequence([int(seed), int(draw)]).generate_state(1, np.uint32)[0])


def pool_draws(trace: IdentificationTrace, draws: int, progress: bool = False, announce=None) -> dict:
    """The trace's measurements filtered under ``draws`` draws of the filter's randomness
    (:func:`draw_seed`; the first is the run's own), every step each (a draw that converges
    early goes on: the clouds must describe the same instant), and pooled
    (:func:`pool_replays`; its dict). What ``vlr-drake identify --draws`` and a scenario run's
    ``--draws`` (``python -m vlr_drake.builder --run``) add to a run: it costs ``draws`` times
    the filter's time and nothing of the plant's, so a hardware run pools offline, after the
    motors are off. ``announce``, if given, is called with a line before each draw."""
    if not is_count(draws, 1):
        raise ValueError(f"draws must be a count of at least 1, got {draws!r}")
    replays = []
    for j in range(draws):
        if announce is not None:
            announce(f"draw {j + 1} of {draws} of the filter over the run's {trace.steps} measurements")
        replays.append(replay(dataclasses.replace(trace, filter_seed=draw_seed(trace.filter_seed, j)),
                              progress=progress))
    return pool_replays(trace, replays)


def _step_count(k, steps: int) -> int:
    """``k`` as an iteration count of a trace of ``steps`` steps (1..steps), or a ValueError naming it."""
    if isinstance(k, (bool, np.bool_)) or not isinstance(k, (int, np.integer)) or not 1 <= k <= steps:
        raise ValueError(f"at_steps: {k!r} is not an iteration count of this trace (1-{steps})")
    return int(k)


def _profile_parameter(trace: IdentificationTrace, parameter: str, values, what: str,
                       prior: pf.PriorConfig | None = None):
    """Checked ``values`` (V,) and the (finger, joint) of a profile's ``parameter`` (see
    :func:`evidence_profile`; joint 0 for a link length) among ``prior``'s unknowns (the
    trace's by default); errors start with ``what``."""
    try:
        values = np.atleast_1d(np.asarray(values, float))
    except (TypeError, ValueError):
        values = None
    if values is None or values.ndim != 1 or values.size == 0:
        raise ValueError(f"{what}: 'values' must be a non-empty list of numbers")
    if not np.all(np.isfinite(values)) or np.any(values <= 0):
        raise ValueError(f"{what}: '{parameter}' values must be finite and positive, got {values.tolist()}")
    whose = "the trace's prior" if prior is None else "the given prior"
    prior, names = trace.prior if prior is None else prior, trace.hand.finger_names()
    if parameter == "stiffness":
        if not prior.stiffness_unknown:
            raise ValueError(f"{what}: {whose} identifies no stiffness")
        fi, j = (int(x) for x in prior.stiffness_unknown[0])
        # N m/rad: 130,170 meant as N mm/rad had run, and said which of them the data favour
        units.check_stiffness(values, f"{what}: 'stiffness' values")
        return values, fi, j
    if parameter.startswith("link_length:"):
        finger = parameter.split(":", 1)[1]
        if finger not in names:
            raise ValueError(f"{what}: the hand has no finger '{finger}' (fingers: {names})")
        fi = names.index(finger)
        if fi not in [int(x) for x in prior.links_unknown]:
            unknown = [names[int(i)] for i in prior.links_unknown]
            raise ValueError(f"{what}: finger '{finger}' has a known link length in {whose} "
                             f"(unknown: {unknown or 'none'})")
        # metres: 40,50 meant as mm had given a statics profile of nan at status 0
        units.check_length(values, f"{what}: '{parameter}' values")
        return values, fi, 0
    raise ValueError(f"{what}: parameter must be one of {PROFILE_PARAMETERS}, got '{parameter}'")


#: The filter settings a statics profile reads (:func:`statics_profile`; it runs no filter).
STATICS_FILTER_KEYS = ("tendon", "max_substeps")


def statics_profile(trace: IdentificationTrace, parameter: str, values,
                    config: pf.FilterConfig | None = None) -> list[dict]:
    """How the VLR with one hand parameter set to each of ``values`` agrees with the plant's
    truth along the trace (simulation traces only; no filter is run).

    At every step the VLR's equilibrium under the motors' commands (the tendon stretch
    l - R theta, as the filter moves a hypothesis) is found from the plant's true angles,
    holding the object's true contact distances, with the true hand but ``parameter``
    (as in :func:`evidence_profile`) at the value. Per value: ``offset_deg``, the mean
    |equilibrium - true angle| over the joints and steps; ``parameter_offset_deg``, the same
    for the parameter's joint (a spring) or finger (a link); ``motion_rms_deg``, the rms
    difference between the equilibria's motion from one step to the next and the plant's
    joint motion (what the camera can see of the parameter, in joint space); ``solved``,
    the fraction of steps with an equilibrium. Where the offsets are least the model's
    statics match the plant; a flat ``motion_rms_deg`` means the actions' motions hardly
    depend on the parameter, so the camera learns it slowly. The contacts stay where they
    are on the last links (the truth's), so a link length is seen without the trade-off
    against the contact positions that the filter's hypotheses can make. ``config`` (default
    the trace's filter settings) gives the tendon model and the substeps; the links' weight
    that a physics run's filter carries is left out (the equilibria move by 0.2 deg on
    average with it, a review measured: about a sixth of the offsets compared).

    Measured (stiffness traces of the physics table, seeds 0-4, the spring 0.7-2x): the
    offsets are least at the true spring on four seeds and at 1.15x on the softest, while
    the motions' rms changes by 0.05-0.15 deg between 1x and 2x (docs/results.md, "What the
    measurements themselves say").
    """
    values, fi, j = _profile_parameter(trace, parameter, values, "statics profile")
    if trace.truths is None:
        raise ValueError("statics profile: the trace has no plant truths (a hardware run)")
    h = trace.hand.validate().model()
    theta, a = trace.truths["theta"], trace.truths["a"]
    D2 = motion.contact_distances_sq(h, trace.truths["contacts"])
    commands = np.vstack([trace.tendon_command0[None], trace.tendon_commands])
    stretch = commands - h.tendon_travel(theta)
    rows = []
    for v in values:
        k, L = trace.truths["stiffness"].copy(), trace.truths["link_lengths"].copy()
        if parameter == "stiffness":
            k[:, fi, j] = v
        else:
            L[:, fi, 0] = v
        cfg = trace.filter if config is None else config
        r = motion.move(h, theta, np.zeros(h.N), a=a, D2=D2, stretch=stretch, stiffness=k, link_lengths=L,
                        tendon=cfg.tendon, max_substeps=cfg.max_substeps)
        off = np.rad2deg(np.abs(r.theta - theta))[r.ok]
        mine = off[:, fi, j] if parameter == "stiffness" else off[:, fi, :]
        both = r.ok[1:] & r.ok[:-1]
        miss = np.diff(r.theta, axis=0)[both] - np.diff(theta, axis=0)[both]
        rows.append({"value": float(v), "solved": float(r.ok.mean()),
                     "offset_deg": float(off.mean()) if off.size else np.nan,
                     "parameter_offset_deg": float(mine.mean()) if mine.size else np.nan,
                     "motion_rms_deg": float(np.rad2deg(np.sqrt(np.mean(miss**2)))) if both.any() else np.nan})
    return rows


def evidence_profile(trace: IdentificationTrace, parameter: str, values, config: pf.FilterConfig | None = None,
                     progress: bool = False, prior: pf.PriorConfig | None = None) -> list[dict]:
    """Replay the trace once per value with one identified hand parameter fixed there.

    ``parameter``: "stiffness" (the prior's first unknown spring, finger and joint from
    ``prior.stiffness_unknown``) [N m/rad], or "link_length:<finger>" (that finger's
    proximal link, which must be one of the prior's ``links_unknown``) [m]. The parameter
    leaves the prior's unknowns and is set in the filter's hand. Returns one dict per value:
    ``value``, ``log_evidence`` and ``relative`` (minus the largest: log Bayes factors),
    ``errors`` (where the trace has truths) and ``replay`` (the full :func:`replay` output).
    ``config`` and ``prior`` replace the trace's own (a replay's ``--filter`` and ``--prior``;
    the prior had been the trace's whatever the command said). Where every value's log
    evidence is -inf (a step that no hypothesis follows), a ValueError names the steps.
    """
    base_prior = trace.prior if prior is None else prior
    # the parameter is one of the prior's the replays use (the trace's had been read whatever
    # ``prior`` said: another first spring was fixed and the given one left unknown, and a
    # link the given prior identifies was refused as known)
    values, fi, j = _profile_parameter(trace, parameter, values, "evidence profile", prior)
    rows = []
    for v in values:
        spec, prior = copy.deepcopy(trace.hand), copy.deepcopy(base_prior)
        if parameter == "stiffness":
            k = list(spec.fingers[fi].stiffness)
            k[j] = float(v)
            spec.fingers[fi].stiffness = k
            prior.stiffness_unknown = [p for p in prior.stiffness_unknown if tuple(int(x) for x in p) != (fi, j)]
        else:
            spec.fingers[fi].link_lengths = [float(v)] + list(spec.fingers[fi].link_lengths[1:])
            prior.links_unknown = [i for i in prior.links_unknown if int(i) != fi]
        try:
            r = replay(trace, config, prior, spec, progress=progress)
        except ValueError as e:  # e.g. no physical grasp with a spring or link far off: name the value
            raise ValueError(f"evidence profile of {parameter} at {v:g}: {e}") from e
        rows.append({"value": float(v), "log_evidence": r["log_evidence"], "errors": r.get("errors"), "replay": r})
    best = max(r["log_evidence"] for r in rows)
    if not np.isfinite(best):  # -inf - -inf: no value to compare against (it had printed nan)
        lost = sorted({int(k) + 1 for r in rows for k in np.flatnonzero(np.isneginf(r["replay"]["log_evidence_steps"]))})
        raise ValueError(f"evidence profile of {parameter}: every value's log evidence is -inf: no hypothesis follows "
                         f"step(s) {lost[:10]} of the trace (an action or a measurement no grasp can explain)")
    for r in rows:
        r["relative"] = r["log_evidence"] - best
    return rows


# ---------------------------------------------------------------------- helpers
def _json_default(x):
    if isinstance(x, (np.ndarray, np.generic)):  # tolist(): a list, or the Python scalar
        return x.tolist()
    raise TypeError(f"cannot write {type(x).__name__} into a trace header")


def _config_from_dict(cls, data: dict):
    """A FilterConfig / PriorConfig from its ``asdict``; JSON lists become the tuples the
    defaults use, unknown keys are named, and a field the trace's version did not have
    takes its behaviour then (:data:`LEGACY_SETTINGS`), else its default."""
    known = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(known))
    if unknown:
        raise ValueError(f"trace: {cls.__name__} has no fields {unknown} (written by another vlr_drake version?)")
    default = cls()
    kw = {}
    for name, value in data.items():
        d = getattr(default, name)
        if isinstance(d, tuple) and isinstance(value, list):
            value = tuple(value)
        elif name == "stiffness_unknown":
            if not (isinstance(value, list) and all(isinstance(p, list) and len(p) == 2 for p in value)):
                raise ValueError(f"trace: PriorConfig 'stiffness_unknown' must be a list of (finger, joint) pairs, "
                                 f"got {value!r}")
            value = [tuple(int(x) for x in p) for p in value]
        elif name == "contact_limits" and value is not None:
            value = tuple(value)
        kw[name] = value
    for name, value in LEGACY_SETTINGS.get(cls.__name__, {}).items():
        kw.setdefault(name, value)
    return cls(**kw)


def _hand_from_dict(data: dict) -> HandSpec:
    fingers = [FingerSpec(**f) for f in data.get("fingers", [])]
    return HandSpec(**{**data, "fingers": fingers}).validate()
