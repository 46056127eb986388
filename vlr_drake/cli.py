"""The ``vlr-drake`` command line.

    vlr-drake demo        the main job: self-check, then a self-identification run with a
                          summary table and convergence plots, then handwriting ('VLR')
                          on the model plant
    vlr-drake selfcheck   build the default hand, move it with both solvers, compare
    vlr-drake identify    one of the paper's identification experiments (JSON + plots)
    vlr-drake replay      replay an identification's trace offline: other filter settings,
                          or the evidence profile of a hand parameter
    vlr-drake write       handwriting with the POM (position control, Eq. 10-12)
    vlr-drake maze        a marble maze by orientation control
    vlr-drake stack       cup stacking in SE(3) with the rotational weight alpha
    vlr-drake reproduce   the paper's experiments and tasks, its numbers beside ours
    vlr-drake diagrams    write the example scenarios' system diagrams (.dot, and .svg with Graphviz)
    vlr-drake bench       benchmarks that print their figures (motion, rolling, filter)

Every run (identify, write, maze, stack, reproduce, demo) takes ``--scenario`` (a scenario
YAML file, or the name of an example in diagrams/: default, model_plant, stiffness,
novel_NH1, custom_hand_and_object, ...), ``--seed``, ``--particles``, ``--out`` and
``--meshcat/--no-meshcat``, and writes its result as JSON (``--json PATH``, or a file in
``--out``). Flags given on the command line override the scenario; without a scenario the
built-in defaults apply. Bad input (a missing scenario, an unknown object or hand, a bad
value in a scenario file) exits with status 2 and one line on stderr.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

from vlr_drake.entry import (
    USER_ERRORS,
    as_spelled,
    clear_interrupt,
    count,
    interrupt_asked,
    path_text,
    plain,
    replacing,
    report,
    saved_trace,
    stop_between_steps,
    warning_lines,
)


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o)}")


def _finite(x):
    """``x`` with every NaN or infinite float (numpy's too) as None: JSON has no NaN or
    Infinity, and a strict reader refuses them (a run whose every hypothesis failed has a
    log evidence of -inf; it is written as null)."""
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    if isinstance(x, np.ndarray):
        return _finite(x.tolist())
    if isinstance(x, (float, np.floating)):
        return float(x) if np.isfinite(x) else None
    return x


def write_json(result: dict, path: str | None) -> None:
    if not path:
        return
    clean = {k: v for k, v in result.items() if not k.startswith("_")}
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps(_finite(clean), indent=2, default=_json_default, allow_nan=False)
    with replacing(path) as temporary:
        temporary.write_text(text)
    print(f"wrote {path}")


#: The fields of an identification's result that say how it was set up (note_replaced).
IDENTIFY_SETTINGS = ("experiment", "scenario_path", "hand", "object", "plant", "particles", "max_iterations",
                     "action_choice", "draws", "object_mass_given_kg", "object_mass_tolerance", "filter_settings",
                     "prior_settings")
#: ... and of a task's.
TASK_SETTINGS = ("task", "plant", "model", "word", "scenario", "particles", "identify_iterations", "alpha")


def note_replaced(path: Path, result: dict, keys: tuple, command: str) -> None:
    """Warn where ``path`` holds the result of a run set up otherwise (any of ``keys`` differs;
    a dict's entries are named one by one), which this run's result and plots replace: an
    output folder keeps one result per run name, and runs that differ only in their settings
    share it (a review: the README's four stiffness commands wrote one file). ``command`` names
    the command in the warning, as its errors name it."""
    try:
        old = json.loads(Path(path).read_text())
    except (OSError, ValueError):  # none there, or not ours: nothing to compare
        return
    if not isinstance(old, dict):
        return
    new = json.loads(json.dumps(_finite({k: result.get(k) for k in keys}), default=_json_default))
    differ = []
    for k in keys:
        a, b = old.get(k), new[k]
        if isinstance(a, dict) and isinstance(b, dict):
            differ += [f"{k}.{j}" for j in sorted(set(a) | set(b)) if a.get(j) != b.get(j)]
        elif a != b:
            differ.append(k)
    if differ:
        shown = ", ".join(differ[:4]) + (f" and {len(differ) - 4} more" if len(differ) > 4 else "")
        print(f"vlr-drake {command}: warning: {path} held a run set up otherwise ({shown}); this run replaces it and its "
              "plots (--json, or another --out, keeps both)", file=sys.stderr)


# ------------------------------------------------------------------------------ selfcheck
def selfcheck(seed: int = 0, actions: int = 5) -> dict:
    """Build the default hand, move one grasp through a few random tendon actions with the
    batched solver and with IPOPT and SNOPT, and report how far apart they are."""
    from vlr_drake import grasps, kinematics, motion
    from vlr_drake import motion_reference as ref
    from vlr_drake.hand import model_o

    hand = model_o().model()
    rng = np.random.default_rng(seed)
    g = grasps.sample_grasps(hand, rng, 1, proximal_range=(0.05, 0.35), distal_range=(0.3, 0.9),
                             contact_range=(0.02, 0.032), min_tension=2.0, stable=True)
    theta, a, s, D2 = g.theta, g.a, g.stretch, g.D2
    print(f"hand '{hand.spec.name}': {hand.N} fingers x {hand.K} joints ({', '.join(hand.names)})")
    print(f"grasp: proximal {np.rad2deg(theta[0, :, 0]).round(1)} deg, distal {np.rad2deg(theta[0, :, 1]).round(1)} deg, "
          f"contacts {1e3 * a[0].round(4)} mm, tensions {g.tension[0].round(2)} N")
    worst = {"ipopt": 0.0, "snopt": 0.0}
    compared = {"ipopt": 0, "snopt": 0}
    failed = {"ipopt": 0, "snopt": 0}
    for k in range(actions):
        dl = rng.uniform(-1e-3, 1e-3, hand.N)
        res = motion.move(hand, theta, dl, a=a, D2=D2, stretch=s)
        line = f"action {k + 1}: dl = {1e3 * dl.round(5)} mm"
        if not res.ok[0]:
            print(line + "  -> no nearby equilibrium (flagged)")
            continue
        for solver in worst:
            try:
                r = ref.solve_move(hand, theta[0], dl, a=a[0], D2=D2[0], stretch=s[0], solver=solver)
            except ref.MotionSolveError as e:  # counted and said, not a crash
                failed[solver] += 1
                print(f"{line}  -> {e}")
                continue
            compared[solver] += 1
            worst[solver] = max(worst[solver], float(np.abs(r.theta - res.theta[0]).max()))
        p = kinematics.contacts(hand, res.theta, a)
        dist_err = np.abs(np.sqrt(motion.contact_distances_sq(hand, p)) - np.sqrt(D2)).max()
        print(f"{line}  -> dtheta {np.rad2deg(res.theta[0] - theta[0]).ravel().round(2)} deg, "
              f"tensions {res.tension[0].round(2)} N, grasp distance error {dist_err:.1e} m")
        theta, s = res.theta, res.stretch
    print(f"batched Newton vs MathematicalProgram: max |dtheta| IPOPT {worst['ipopt']:.1e} rad over "
          f"{compared['ipopt']} actions, SNOPT {worst['snopt']:.1e} rad over {compared['snopt']}")
    out = {"check": "selfcheck", "seed": seed, "max_difference_ipopt_rad": worst["ipopt"],
           "max_difference_snopt_rad": worst["snopt"], "actions_compared": compared, "reference_failures": failed}
    if min(compared.values()) == 0:  # a check that compared nothing has not passed
        raise SelfCheckError(f"selfcheck compared no action with {[k for k, v in compared.items() if v == 0]} "
                             f"(seed {seed}: every action flagged or failed); try another --seed")
    if max(worst.values()) > SELFCHECK_TOLERANCE_RAD:
        raise SelfCheckError(f"selfcheck: the batched solver is {max(worst.values()):.1e} rad from the "
                             f"MathematicalProgram solve, more than {SELFCHECK_TOLERANCE_RAD:.0e} rad")
    return out


#: How far the batched solver's angles may lie from IPOPT's and SNOPT's for `selfcheck` [rad].
SELFCHECK_TOLERANCE_RAD = 1e-6


class SelfCheckError(ValueError):
    """``vlr-drake selfcheck`` found the batched solver and the reference apart, or compared
    nothing (the command ends with status 2 and says which)."""


# ------------------------------------------------------------------------------ scenario
def _check_outputs(args) -> None:
    """Refuse an output path that cannot be written before the run, not after it."""
    from vlr_drake.entry import check_not_trace, check_output

    check_output("--out", getattr(args, "out", None), folder=True)
    check_output("--json", getattr(args, "json", None))
    if args.command == "identify":  # (replay's traces are its inputs)
        check_output("--trace", args.trace)
    # a file where the run makes its --out folder (a review: --json or --trace named as --out
    # ended a finished run in a traceback, its result or its plots never written)
    out = Path(args.out).resolve() if getattr(args, "out", None) else None
    for flag, given in (("--json", getattr(args, "json", None)),
                        ("--trace", args.trace if args.command == "identify" else None)):
        if out is not None and given and Path(given).resolve() in (out, *out.parents):
            raise ValueError(f"{flag} {given} is the --out folder {args.out} (or a folder above it): the run writes "
                             "its results and plots in that folder; name a file")
    # the JSON over the run's trace, or over a trace a replay reads
    traces = {"identify": [args.trace] if args.command == "identify" else [],
              "replay": getattr(args, "trace", None) or []}.get(args.command, [])
    check_not_trace(getattr(args, "json", None), traces)


def _load_scenario(args) -> None:
    """Resolve ``--scenario`` (a file or an example's name) into ``args.loaded`` (the
    Scenario or None) and ``args.scenario_path``; the seed: ``--seed``, else the scenario's,
    else 0."""
    from vlr_drake.scenario import find_scenario, load_scenario

    args.loaded, args.scenario_path = None, None
    if getattr(args, "scenario", None):
        args.scenario_path = find_scenario(args.scenario)
        args.loaded = load_scenario(args.scenario_path)
    if getattr(args, "seed", 0) is None:
        args.seed = args.loaded.seed if args.loaded is not None else 0
    # the paper's setting: the physics plant with the rendered camera, unless a scenario says
    # otherwise or --plant model asks for the fast one
    if hasattr(args, "plant") and args.plant is None and args.loaded is None:
        args.plant = "physics"


def _identify_options(args):
    from vlr_drake.scenario import ignored_by_identify, ignored_by_plant, options_from_scenario

    opts = options_from_scenario(
        args.loaded, args.scenario_path, experiment=args.experiment, plant=args.plant, object=args.object,
        hand=args.hand, seed=args.seed, particles=args.particles, max_iterations=args.iterations,
        progress=not args.no_progress, action_choice=getattr(args, "actions", None),
    )
    first = not getattr(args, "told_ignored", False)  # warnings once per command (the demo builds the
    args.told_ignored = True  # options twice; its --object warning had been said twice)
    ignored = [] if args.loaded is None or not first else ignored_by_identify(args.loaded, opts.plant)
    if ignored:  # said, not silently dropped (once the scenario is known to run), each with why
        by_plant = ignored_by_plant(args.loaded, opts.plant)
        diagram = [n for n in ignored if n not in by_plant]
        why = ([f"{', '.join(diagram)} (the diagram's settings: python -m vlr_drake.builder --run takes them)"]
               if diagram else []) + ([f"{', '.join(by_plant)} (the {opts.plant} plant has no use for them)"]
                                      if by_plant else [])
        print(f"vlr-drake {args.command}: warning: scenario '{args.loaded.name}': an identification run does not use "
              f"{'; nor '.join(why)}", file=sys.stderr)
    if first and args.object is not None and opts.plant == "model":  # said, not silently dropped
        print(f"vlr-drake {args.command}: warning: --object {args.object}: the model plant does not use the object "
              "(its truth is the VLR, Eq. 9); the physics plant holds it", file=sys.stderr)
    if args.loaded is None:
        opts.scenario = None  # described by the flags alone
    if getattr(args, "stuck_probability", None) is not None:
        opts.filter.stuck_probability = args.stuck_probability
    if getattr(args, "link_weight", None) is not None:
        opts.link_weight = args.link_weight
    if getattr(args, "object_weight", False):
        opts.object_weight = True
    if getattr(args, "object_mass", None) is not None:
        opts.object_mass = args.object_mass
    if getattr(args, "object_mass_tolerance", None) is not None:
        if opts.object_mass is None:  # said, not silently dropped
            raise ValueError("--object-mass-tolerance needs the object's weighed mass: --object-mass (or a "
                             "scenario's prior.object_mass)")
        opts.object_mass_tolerance = args.object_mass_tolerance
    _config_flags(args, opts)
    return opts


#: Filter settings an identification run sets itself, with the flag that sets them.
RUN_SET_FILTER = {"particles": "--particles", "gravity_palm": "--link-weight (the physics plant's mounting)"}


def _config_flags(args, opts) -> None:
    """``identify``'s ``--filter`` / ``--prior KEY=VALUE`` overrides (as replay's) on the
    options' filter and prior, after the scenario's; refuses the filter settings the run sets
    from its own flags."""
    from vlr_drake import filter as pf
    from vlr_drake.scenario import config_overrides

    for item in getattr(args, "filter", None) or []:
        key = item.partition("=")[0]
        if key in RUN_SET_FILTER:
            raise ValueError(f"--filter '{item}': the run sets '{key}' itself; use {RUN_SET_FILTER[key]}")
        if key == "stuck_probability" and getattr(args, "stuck_probability", None) is not None:
            raise ValueError(f"--filter '{item}' and --stuck-probability {args.stuck_probability} set the same "
                             "thing: give one (the --filter had won without a word)")
    if getattr(args, "filter", None):
        opts.filter = config_overrides(opts.filter, args.filter, "--filter")
    if getattr(args, "prior", None):
        opts.prior = config_overrides(opts.prior if opts.prior is not None else pf.PriorConfig(), args.prior, "--prior")


def _preset_hand(text: str) -> str:
    """A --hand value as the preset's own name whatever its case (``nh2`` -> ``NH2``); other
    names are left for the run to refuse, with the list of presets."""
    from vlr_drake.hand import NOVEL_HANDS

    return as_spelled(text, ("model_o", *NOVEL_HANDS))


def _task_settings(args) -> dict:
    from vlr_drake.scenario import ignored_by_tasks, task_settings

    kw = task_settings(args.loaded, args.scenario_path, seed=args.seed, plant=args.plant, particles=args.particles)
    ignored = [] if args.loaded is None else ignored_by_tasks(args.loaded, kw["plant"])
    if ignored:  # said, not silently dropped
        print(f"vlr-drake {args.command}: warning: scenario '{args.loaded.name}': the task does not use "
              f"{', '.join(ignored)} (it takes the seed, plant, particle count, exploration, the model plant's "
              f"noise and dropout on the model plant, physics and camera on the physics plant; its objects, filter and prior are "
              f"its own)", file=sys.stderr)
    return kw if args.loaded is not None else {**kw, "scenario": None}


def _meshcat(args):
    """A Meshcat instance (its URL printed) when ``--meshcat`` is given, or when neither
    ``--meshcat`` nor ``--no-meshcat`` is and the scenario says ``meshcat: true``; else None."""
    wanted = getattr(args, "meshcat", None)
    if wanted is None:
        loaded = getattr(args, "loaded", None)
        wanted = bool(loaded is not None and loaded.meshcat)
    if not wanted:
        return None
    if getattr(args, "meshcat_instance", None) is None:
        from pydrake.geometry import Meshcat

        args.meshcat_instance = Meshcat()
        print(f"Meshcat: {args.meshcat_instance.web_url()}")
    return args.meshcat_instance


# ------------------------------------------------------------------------------ identify


def run_notes(result: dict) -> list[str]:
    """What a run (an identification's or a diagram's result) went through, said where it
    happened: iterations without a tag pose, re-initialisations, actions the plant refused."""
    return [f"{count} {text}" for count, text in (
        (result.get("lost_measurements"), "iterations without a tag pose"),
        (result.get("reinitialisations"), "re-initialisations (every hypothesis implausible)"),
        (result.get("actions_refused"), "actions refused by the plant")) if count]


def print_summary(result: dict) -> None:
    names = result.get("_finger_names", [])
    est = result["_estimates"][-1]
    truth = result["_truths"][-1]
    print(f"\n{result['experiment']} on the {result['plant']} plant, seed {result['seed']}, "
          f"{result['particles']} particles: {'converged' if result['converged'] else 'not converged'} "
          f"after {result['iterations']} iterations")
    said = run_notes(result)
    if said:  # (said by the diagram's run, not by identify's summary: a run that had lost 10 of 12
        print("; ".join(said))  # frames had looked like a clean one; a review)
    if result.get("iterations") and result.get("lost_measurements", 0) > 0.5 * result["iterations"]:
        print("most iterations had no measurement: the estimate is mostly the prior moved by the actions "
              + ("(the model plant's dropout)" if result["plant"] == "model" else "(check the camera and the tag)"))
    if result.get("stopped"):
        print(f"the run stopped early, at {result['stopped']}")
    # the label column fits the longest name (novel fingers: "finger_left_NF2 proximal [deg]")
    w = max([28] + [len(n) + len(" contact along link [mm]") for n in names]
            + [len(name.split(":", 1)[1]) + len(" link [mm]") for name in result.get("hand_parameters", {})])
    print(f"{'quantity':{w}s} {'estimate':>10s} {'95% interval':>20s} {'truth':>10s} {'error':>8s}")
    for i, n in enumerate(names):
        K = est["theta"].shape[1]  # proximal, the middle joints by the Drake model's number (from 1), distal
        for j, label in enumerate(["proximal", *(f"joint{j + 1}" for j in range(1, K - 1)), "distal"]):
            e, lo, hi, t = (np.rad2deg(x[i, j]) for x in (est["theta"], est["theta_lo"], est["theta_hi"], truth["theta"]))
            print(f"{n + ' ' + label + ' [deg]':{w}s} {e:10.2f} {f'[{lo:.2f}, {hi:.2f}]':>20s} {t:10.2f} {abs(e - t):8.2f}")
        e, lo, hi, t = (1e3 * x[i] for x in (est["a"], est["a_lo"], est["a_hi"], truth["a"]))
        # a_i, the contact's position along the last link (the JSON's contact_error_mm is the
        # distance between the estimated and the true contact points, joint angles' errors included)
        print(f"{n + ' contact along link [mm]':{w}s} {e:10.2f} {f'[{lo:.2f}, {hi:.2f}]':>20s} {t:10.2f} {abs(e - t):8.2f}")
    for name, p in result.get("hand_parameters", {}).items():  # identified springs and links
        kind, where = name.split(":", 1)
        key, scale, unit, d = (("link_lengths", 1e3, "mm", 2) if kind == "link_length"
                               else ("stiffness", 1.0, p["unit"], 4))
        e, lo, hi = scale * p["estimate"], scale * p["interval"][0], scale * p["interval"][1]
        t = scale * truth[key][p["finger"], p["joint"]]
        label = f"{where} {'link' if kind == 'link_length' else 'k'} [{unit}]"
        print(f"{label:{w}s} {e:10.{d}f} {f'[{lo:.{d}f}, {hi:.{d}f}]':>20s} {t:10.{d}f} {abs(e - t):8.{d}f}")
    if result.get("object_mass_estimate_kg") is not None:  # identified object's weight
        e, (lo, hi), t = (1e3 * result["object_mass_estimate_kg"], (1e3 * x for x in result["object_mass_interval_kg"]),
                          1e3 * result["object_mass_true_kg"])
        print(f"{'object mass [g]':{w}s} {e:10.1f} {f'[{lo:.1f}, {hi:.1f}]':>20s} {t:10.1f} {abs(e - t):8.1f}")
    for name in result.get("weakly_identified", []):
        p = result["hand_parameters"][name]
        print(f"weakly identified: {name} (its 95% interval is {100 * p['narrowed_to']:.0f}% as wide as the "
              f"prior's: the estimate leans on the prior)")
    if np.isfinite(result.get("parameter_interval", np.nan)):  # (NaN: every hand parameter known)
        limit = result.get("parameter_convergence")
        print(f"widest hand parameter's 95% {result['convergence_measure'].replace('_', '-')}: "
              f"{100 * result['parameter_interval']:.1f}% of its estimate"
              + ("" if limit is None else f" (converges below {100 * limit:g}%)"))
    print(f"mean joint error {result['joint_error_deg_mean']:.2f} deg; mean 95% half-width "
          f"{result['interval_half_width_deg_mean']:.2f} deg; truth inside 95%: "
          f"{100 * result['truth_inside_95_theta']:.0f}% of joints, {100 * result['truth_inside_95_contact']:.0f}% of contacts")
    t = result["timing_s"]
    print("time: " + ", ".join(f"{k} {v:.1f} s" for k, v in t.items()))


def identify(args) -> dict:
    from vlr_drake.identify import options_run_name, run_identification

    opts = _identify_options(args)
    out = Path(args.out)
    name = options_run_name(opts)
    stem = f"identify_{name}"
    path = args.json or str(out / f"{stem}.json")
    _check_own_files(args, _identify_files(args, opts))
    meshcat = _meshcat(args)
    on_iteration, finish = _meshcat_hypotheses(meshcat, out / f"{stem}.html") if meshcat else (None, None)
    result = run_identification(opts, on_iteration=on_iteration)
    print_summary(result)
    result["draws"] = draws = getattr(args, "draws", 1)  # (the demo's identification has one)
    if finish is not None:
        result["recording"] = str(finish())
    if getattr(args, "trace", None):
        result["trace"] = saved_trace(result["_trace"], args.trace, f"vlr-drake {args.command}")
        if result["trace"]:
            print(f"wrote {result['trace']}")
    if not args.json:
        note_replaced(path, result, IDENTIFY_SETTINGS, args.command)
    write_json(result, path)  # first: the run is kept whatever the pooling and the plots do
    if draws > 1 and not interrupt_asked():  # K times the filter's time, offline: after the run's own result
        try:
            result["pooled"] = pool_run_draws(result["_trace"], draws, progress=not args.no_progress)
        except (ValueError, RuntimeError, FloatingPointError, np.linalg.LinAlgError) as e:
            result["pooled"] = {"reason": f"a draw of the filter failed: {type(e).__name__}: {e}"}
            print(f"vlr-drake identify: warning: no pooled estimate ({result['pooled']['reason']}); the run's own "
                  "result is kept", file=sys.stderr)
        write_json(result, path)
    _plots(result, out / name)
    return result


#: The plots an identification run may write, ``<out>/<run name>_<what>.png`` (:func:`_plots`).
PLOT_KINDS = ("proximal", "contacts", "convergence", "stiffness", "links")


def _plot_path(stem: Path, kind: str) -> str:
    """The file of one of a run's plots (:data:`PLOT_KINDS`)."""
    assert kind in PLOT_KINDS, kind
    return f"{stem}_{kind}.png"


def _identify_files(args, opts) -> dict[Path, str]:
    """The files an identification run writes in ``--out`` besides ``--json`` and ``--trace``,
    each with what it is: its default JSON (without ``--json``), its plots
    ``<out>/<run name>_<what>.png`` and its Meshcat recording."""
    from vlr_drake.identify import options_run_name

    out, name = Path(args.out), options_run_name(opts)
    files = {Path(_plot_path(out / name, kind)): f"the run's {kind} plot" for kind in PLOT_KINDS}
    files[out / f"identify_{name}.html"] = "the run's Meshcat recording"
    if not args.json:
        files[out / f"identify_{name}.json"] = "the run's result JSON (name another file, or give --json)"
    return files


def _check_own_files(args, files: dict) -> None:
    """Refuse a ``--trace`` or ``--json`` that one of the command's own ``files`` (path: what
    it is) would overwrite, or be written over by, before anything runs. (A trace named as
    identify's default JSON had been written over by it, a ``--json`` named as a plot by the
    plot, and the demo's identification result by the writing's plot.)"""
    files = {Path(path).resolve(): what for path, what in files.items()}
    for flag in ("--trace", "--json"):
        given = getattr(args, flag[2:], None)
        if given and Path(given).resolve() in files:
            raise ValueError(f"{flag} {given} is {files[Path(given).resolve()]} too: one would be written over "
                             "the other")


def pool_run_draws(trace, draws: int, progress: bool = False) -> dict:
    """``vlr-drake identify --draws K``: the run's measurements (its ``trace``) filtered under
    ``draws`` draws of the filter's randomness and pooled (:func:`vlr_drake.trace.pool_draws`):
    the result's ``pooled``, printed."""
    from vlr_drake.trace import pool_draws

    p, errors = print_pooled(pool_draws(trace, draws, progress=progress, announce=print), "")
    return {**p, **(errors or {})}


def hand_parameter_line(name: str, q: dict) -> str:
    """One identified hand parameter (a ``hand_parameters`` item) as a line: estimate, unit, 95% interval."""
    return f"{name}: {q['estimate']:.4g} {q['unit']}, 95% [{q['interval'][0]:.4g}, {q['interval'][1]:.4g}]"


def print_pooled(p: dict, indent: str) -> tuple[dict, dict | None]:
    """Print a pooled estimate (:func:`vlr_drake.trace.pool_replays`' ``p``); returns it
    without its ``errors``, and them (None without truths)."""
    errors = p.pop("errors", None)
    print(f"{indent}pooled over {p['draws']} draws (the mixture of their clouds after {p['steps']} steps):")
    for name, q in p["hand_parameters"].items():
        print(f"{indent}  {hand_parameter_line(name, q)}")
    if p.get("object_mass_identified"):
        print(f"{indent}  {hand_parameter_line('object mass', p['object_mass_identified'])}")
    if errors:
        print(f"{indent}  {_errors_line(errors)}")
    return p, errors


def replay_trace(args) -> dict:
    """``vlr-drake replay``: each trace's run again with ``--filter`` overrides, and for
    several traces the table's rows (mean +- SD of the paper's measures); or, with
    ``--profile``, each trace's evidence profile over ``--values``."""
    from vlr_drake.scenario import config_overrides
    from vlr_drake.trace import (
        STATICS_FILTER_KEYS,
        IdentificationTrace,
        draw_seed,
        evidence_profile,
        replay,
        statics_profile,
    )

    if args.profile is None and args.values is not None:
        raise ValueError("--values needs --profile")
    if args.statics and args.profile is None:
        raise ValueError("--statics needs --profile and --values")
    if args.all_steps and args.profile is not None:
        raise ValueError("--all-steps is for a replay: an evidence profile always replays every step")
    if args.draws > 1 and args.profile is not None:
        raise ValueError("--draws is for a replay, not for a profile")
    at_steps = []
    if args.at is not None:
        if args.profile is not None:
            raise ValueError("--at is for a replay, not for a profile")
        try:
            at_steps = [int(k) for k in args.at.split(",")]
        except ValueError:
            raise ValueError(f"--at '{args.at}': expected comma-separated iteration counts, e.g. 60,120,240") from None
    values = None
    if args.profile is not None:
        if args.values is None:
            raise ValueError("--profile needs --values, e.g. --values 0.13,0.17,0.21")
        try:
            values = [float(v) for v in args.values.split(",")]  # an empty item (",,", a trailing comma) too
        except ValueError:
            raise ValueError(f"--values '{args.values}': expected comma-separated numbers, e.g. 0.13,0.17,0.21") \
                from None
        if not all(np.isfinite(values)):
            raise ValueError(f"--values '{args.values}': expected finite numbers")
    seen = {}
    for path in args.trace:
        if Path(path).resolve() in seen:
            raise ValueError(f"trace {path} is given twice (as {seen[Path(path).resolve()]} before): each trace "
                             "counts once in the rows (--draws replays one several times)")
        seen[Path(path).resolve()] = path
    traces = [(path, IdentificationTrace.load(path)) for path in args.trace]  # all read before the first replay
    # traces of several plants count in rows of their own plant's (a review: a model-plant trace
    # had been averaged with three physics ones into one row)
    by_plant = len({trace.meta.get("plant") for _, trace in traces}) > 1
    if args.filter_seed is not None:
        same = [str(path) for path, trace in traces if trace.filter_seed == args.filter_seed]
        if same:  # (identify seeds its filter with seed + 1: a seed-0 run's filter seed is 1)
            print(f"vlr-drake replay: warning: --filter-seed {args.filter_seed} is the filter seed "
                  f"{', '.join(same)} was run with: the same draw, not another", file=sys.stderr)
        traces = [(path, dataclasses.replace(trace, filter_seed=args.filter_seed)) for path, trace in traces]
    for path, trace in traces if at_steps else ():  # and all checked: no replay is lost to a later trace's error
        if any(not 1 <= k <= trace.steps for k in at_steps):
            raise ValueError(f"--at '{args.at}': {path} has {trace.steps} steps (iteration counts 1-{trace.steps})")
        if trace.truths is None:
            raise ValueError(f"--at '{args.at}': {path} has no truths to measure the estimates against "
                             "(a hardware trace)")
    runs, measured, pooled, pooled_measured, draws_of = [], {}, [], {}, []
    jobs = [(i, path, dataclasses.replace(trace, filter_seed=draw_seed(trace.filter_seed, j)), j)
            for i, (path, trace) in enumerate(traces) for j in range(args.draws)]
    with stop_between_steps("the replay"):
        for i, path, trace, draw in jobs:
            if interrupt_asked():  # Ctrl-C: the replays done are kept and written
                break
            config = config_overrides(trace.filter, args.filter or [], "--filter")
            prior = config_overrides(trace.prior, args.prior or [], "--prior")
            meta = trace.meta
            which = f", draw {draw + 1} of {args.draws} (filter seed {trace.filter_seed})" if args.draws > 1 else ""
            print(f"{path}: {meta.get('experiment')} on the {meta.get('plant')} plant, hand {meta.get('hand')}, object "
                  f"{meta.get('object')}, seed {meta.get('seed')}, {trace.steps} steps, {config.particles} particles"
                  f"{which}")
            if values is None:
                r = replay(trace, config, prior, progress=not args.no_progress, stop_at_convergence=not args.all_steps,
                           at_steps=at_steps)
                run = {"trace": str(path), "filter_seed": trace.filter_seed, "draw": draw, "log_evidence": r["log_evidence"],
                       "converged_at": r["converged_at"],
                       "steps": r["steps"],
                       "reinitialisations": r["reinitialisations"], "hand_parameters": r["hand_parameters"],
                       "weakly_identified": r["weakly_identified"], "object_mass_identified": r["object_mass_identified"],
                       **(r.get("errors") or {})}
                conv = "not converged" if r["converged_at"] is None else f"converged at iteration {r['converged_at']}"
                if r["steps"] < trace.steps:
                    conv += f", where a run stops: {r['steps']} of the trace's {trace.steps} steps replayed"
                print(f"  log evidence {r['log_evidence']:.2f}; {conv}; {r['reinitialisations']} re-initialisations")
                if r["weakly_identified"]:
                    print("  weakly identified: " + ", ".join(
                        f"{n} (interval {100 * r['hand_parameters'][n]['narrowed_to']:.0f}% as wide as the prior's)"
                        for n in r["weakly_identified"]))
                if at_steps:
                    run["errors_at"] = r["errors_at"]
                    for e in r["errors_at"]:
                        print(f"  after {e['steps']} steps: {_errors_line(e)}")
                    if len(r["errors_at"]) < len(set(at_steps)):
                        print(f"  (the replay stopped after {r['steps']} steps; --all-steps replays every step)")
                if r.get("errors"):
                    print(f"  {_errors_line(r['errors'])}")
                    _measure(measured, i, meta, r["errors"], by_plant)
                if args.draws > 1:  # kept for the trace's pooled estimate, until its last draw
                    draws_of.append(r)
                if args.draws > 1 and draw == args.draws - 1:  # the trace's last draw: pool its draws
                    p, errors = _pooled_run(path, trace, draws_of, prior)
                    pooled.append(p)
                    if errors:
                        _measure(pooled_measured, i, meta, errors, by_plant)
                    draws_of = []
            elif args.statics:
                # it runs no filter: what only a filter reads is said, not recorded as applied
                if args.prior:
                    raise ValueError("--prior is for a replay or an evidence profile: a statics profile runs no filter")
                if args.filter_seed is not None:
                    raise ValueError("--filter-seed is for a replay or an evidence profile: a statics profile runs no "
                                     "filter")
                unused = [item for item in args.filter or [] if item.partition("=")[0] not in STATICS_FILTER_KEYS]
                if unused:
                    raise ValueError(f"--filter {' '.join(unused)}: a statics profile runs no filter and reads only "
                                     f"{' and '.join(STATICS_FILTER_KEYS)}")
                rows = statics_profile(trace, args.profile, values, config)
                unit = "N m/rad" if args.profile == "stiffness" else "m"
                print(f"  statics profile of {args.profile} [{unit}] (the VLR's commanded equilibrium against the "
                      "plant's true angles):")
                own = "the spring's joint" if args.profile == "stiffness" else "the link's finger"
                for r in rows:
                    print(f"    {r['value']:.5g}: offset {r['offset_deg']:.2f} deg ({own} "
                          f"{r['parameter_offset_deg']:.2f}), motion rms {r['motion_rms_deg']:.3f} deg, "
                          f"solved {100 * r['solved']:.0f}%")
                run = {"trace": str(path), "parameter": args.profile, "statics": rows}
            else:
                rows = evidence_profile(trace, args.profile, values, config, progress=not args.no_progress,
                                        prior=prior if args.prior else None)  # (its errors name whose prior)
                unit = "N m/rad" if args.profile == "stiffness" else "m"
                print(f"  evidence profile of {args.profile} [{unit}] (log Bayes factor against the best value):")
                for r in rows:
                    extra = f"; {_errors_line(r['errors'])}" if r["errors"] else ""
                    print(f"    {r['value']:.5g}: {r['relative']:8.2f} (log evidence {r['log_evidence']:.2f}; "
                          f"{r['replay']['reinitialisations']} re-initialisations){extra}")
                run = {"trace": str(path), "parameter": args.profile,
                       "profile": [{k: v for k, v in r.items() if k != "replay"} for r in rows]}
            runs.append(run)
    table = {row: _replay_row(v, args.draws) for row, v in measured.items()}
    if len(jobs) > 1 and table:
        over = "the traces" if args.draws == 1 else "every draw of every trace"
        print(f"rows (the paper's measure, mean +- SD over {over}; the population SD, as reproduce's):")
        for row, t in table.items():
            print(f"  {row}: {t['mean']:.4g} +- {t['sd']:.3g} ({t['trials']} runs; truth inside "
                  f"{t['truth_inside_95_theta']:.2f} of the joint intervals)")
            if args.draws > 1:
                print(f"    {t['traces']} traces x {args.draws} draws: the traces' means over their draws "
                      f"{t['trace_mean']:.4g} +- {t['trace_mean_sd']:.3g}; one draw moves it by {t['draw_sd']:.3g} "
                      f"(the sample SD over a trace's draws, few as they are, mean over the traces)")
    pooled_table = {row: _replay_row(v, 1) for row, v in pooled_measured.items()}
    if len(pooled) > 1 and pooled_table:
        left = [p["trace"] for p in pooled if "reason" in p]
        print(f"rows of the pooled estimates (mean +- SD over the traces, each its {args.draws} draws' mixture"
              + (f"; {len(left)} of {len(pooled)} traces could not be pooled: {', '.join(left)}" if left else "")
              + "):")
        for row, t in pooled_table.items():
            print(f"  {row}: {t['mean']:.4g} +- {t['sd']:.3g} ({t['trials']} traces; truth inside "
                  f"{t['truth_inside_95_theta']:.2f} of the joint intervals)")
    spread = (draw_spread([(i, run) for (i, *_), run in zip(jobs[:len(runs)], runs, strict=True)])
              if args.draws > 1 and values is None else {})
    if spread:
        print("the identified hand parameters' estimates, one draw of the filter against another (the sample SD "
              "over a trace's draws; no truth needed):")
        for name, d in spread.items():
            print(f"  {name}: {d['sd_mean']:.4g} {d['unit']} (mean over the traces; largest {d['sd_max']:.4g})")
    out = {"filter_overrides": args.filter or [], "prior_overrides": args.prior or [], "all_steps": bool(args.all_steps),
           "draws": args.draws, "profile": args.profile, "values": values, "statics": bool(args.statics),
           "runs": runs, "rows": table, "draw_spread": spread, "pooled": pooled, "pooled_rows": pooled_table,
           "interrupted": interrupt_asked()}
    write_json(out, args.json)
    return out


def _measure(measured: dict, i: int, meta: dict, errors: dict, by_plant: bool = False) -> None:
    """Add trace ``i``'s paper measures (its experiment's table rows) from ``errors`` to
    ``measured``; with ``by_plant``, in rows of its plant's (``stiffness (model plant)``)."""
    from vlr_drake.reproduce import IDENTIFICATION_MEASURES, identification_rows

    experiment = meta.get("experiment")
    where = f" ({meta.get('plant')} plant)" if by_plant else ""
    if experiment in IDENTIFICATION_MEASURES:
        for row, measure in identification_rows(experiment, meta.get("hand")):
            measured.setdefault(row + where, []).append((i, float(measure(errors)), errors["truth_inside_95_theta"]))


def _pooled_run(path, trace, replays: list, prior) -> tuple[dict, dict | None]:
    """``replay --draws``' pooled estimate of one trace (:func:`vlr_drake.trace.pool_replays`),
    printed, as a JSON ``pooled`` item and its errors (None without truths); where the draws
    stopped at different steps, no estimate and the ``reason``."""
    from vlr_drake.trace import pool_replays

    try:
        p = pool_replays(trace, replays, prior)
    except ValueError as e:
        print(f"  not pooled: {e}")
        return {"trace": str(path), "draws": len(replays), "reason": str(e)}, None
    p, errors = print_pooled(p, "  ")
    return {"trace": str(path), **p, **(errors or {})}, errors


def draw_spread(runs: list) -> dict:
    """How far one draw of the filter moves each identified hand parameter's estimate, from
    ``runs``, (trace index, replay run) per draw: {parameter: ``sd_mean`` and ``sd_max``,
    the SD of its estimate over a trace's draws, mean and largest over the traces, and its
    ``unit``}. It needs no truth: on a hardware trace it is the one measure of the filter's
    own noise. Empty where no hand parameter was identified."""
    by = {}
    for i, run in runs:
        for name, p in (run.get("hand_parameters") or {}).items():
            by.setdefault(name, {"unit": p["unit"], "draws": {}})["draws"].setdefault(i, []).append(p["estimate"])
    out = {}
    for name, d in by.items():
        sds = [float(np.std(v, ddof=1)) for v in d["draws"].values()]  # unbiased variance: few draws
        out[name] = {"sd_mean": float(np.mean(sds)), "sd_max": float(np.max(sds)), "unit": d["unit"]}
    return out


def _replay_row(values: list, draws: int) -> dict:
    """One row of a replay's table from ``values``, (trace index, measure, truth inside) per
    run: the mean +- SD over every run and, over the traces, each trace's mean over its
    ``draws`` draws (mean, SD) and the draws' own spread (SD within a trace, mean over them).
    The SDs across runs and traces are population SDs, as ``reproduce``'s rows; the one within
    a trace's few draws is the sample SD."""
    idx = np.array([i for i, _, _ in values])
    m = np.array([v for _, v, _ in values], float)
    row = {"mean": float(m.mean()), "sd": float(m.std()),
           "truth_inside_95_theta": float(np.mean([c for _, _, c in values])), "trials": len(values),
           "traces": len(set(idx.tolist()))}
    if draws > 1:
        per = [m[idx == i] for i in sorted(set(idx.tolist()))]
        means = np.array([x.mean() for x in per])
        row.update(trace_mean=float(means.mean()), trace_mean_sd=float(means.std()),
                   draw_sd=float(np.mean([x.std(ddof=1) for x in per])))
    return row


def _errors_line(e: dict) -> str:
    text = (f"mean joint error {e['joint_error_deg_mean']:.2f} deg, truth inside 95%: "
            f"{100 * e['truth_inside_95_theta']:.0f}% of joints")
    if e.get("stiffness_error_Nm_per_rad") is not None:
        text += (f", spring {e['stiffness_estimate_Nm_per_rad']:.4f} N m/rad (truth "
                 f"{e['stiffness_true_Nm_per_rad']:.4f})")
    if e.get("link_length_error_mm"):
        inside = e.get("link_length_inside_95", {})
        text += ", link errors " + ", ".join(
            f"{k} {v:.2f} mm" + ("" if k not in inside else " (inside)" if inside[k] else " (outside its 95%)")
            for k, v in e["link_length_error_mm"].items())
    if e.get("object_mass_error_kg") is not None:
        text += (f", object mass {1e3 * e['object_mass_estimate_kg']:.0f} g (truth {1e3 * e['object_mass_true_kg']:.0f}"
                 f", {'inside' if e['object_mass_inside_95'] else 'outside'} its 95%)")
    return text


def _meshcat_hypotheses(meshcat, html_path: Path):
    """Meshcat drawing of the hypotheses (the paper's Fig. 4 colours), one recorded frame per
    iteration, saved as a static HTML recording at the end. Returns (callback, finish)."""
    from vlr_drake.visualization import HypothesisDrawer, save_recording

    meshcat.Delete("/hypotheses")
    meshcat.DeleteRecording()
    meshcat.StartRecording()
    state = {}

    def on_iteration(iteration, flt):
        if "drawer" not in state:
            state["drawer"] = HypothesisDrawer(meshcat, flt.hand)
        state["drawer"].draw_particles(flt.particles, flt.estimates[-1], np.random.default_rng(iteration),
                                       time_in_recording=float(iteration))

    def finish():
        path = save_recording(meshcat, html_path, publish_recording=True)
        print(f"wrote {path}")
        meshcat.Delete("/hypotheses")  # saved: a later scene (the demo's writing) is not drawn over them
        return path

    return on_iteration, finish


def _plots(result: dict, stem: Path) -> None:
    """The run's plots, ``<stem>_<what>.png``."""
    from vlr_drake import plots

    stem.parent.mkdir(parents=True, exist_ok=True)
    est, truths, names = result["_estimates"], result["_truths"], result["_finger_names"]
    if not result["_history"]:  # the prior alone: a plot of one point shows no band and no line
        why = result.get("stopped") or f"{result.get('actions_refused', 0)} actions refused"
        print(f"no plots: no filter iteration ran ({why})")
        return
    written = [
        plots.plot_joint_angles(est, truths, names, _plot_path(stem, "proximal"), joints="proximal"),
        plots.plot_contacts(est, truths, names, _plot_path(stem, "contacts")),
        plots.plot_convergence(result["_history"], _plot_path(stem, "convergence"), result["convergence_deg"],
                               result["convergence_measure"], result.get("parameter_convergence")),
    ]
    if result.get("stiffness_error_Nm_per_rad") is not None:
        which = [(p["finger"], p["joint"]) for p in result["hand_parameters"].values() if p["unit"] == "N m/rad"]
        written.append(plots.plot_stiffness(est, truths, names, _plot_path(stem, "stiffness"), which=which))
    if result.get("link_length_error_mm"):
        fingers = [names.index(n) for n in result["link_length_error_mm"]]
        written.append(plots.plot_link_lengths(est, truths, names, _plot_path(stem, "links"), fingers=fingers))
    for p in written:
        print(f"wrote {p}")


# ------------------------------------------------------------------------------ tasks
def task(args) -> dict:
    given = [flag for flag, value in (("--particles", args.particles), ("--iterations", args.iterations))
             if value is not None]
    if args.model == "true" and given:  # said, not silently ignored
        raise ValueError(f"{', '.join(given)} set the self-identification of --model filter; --model true controls "
                         "with the plant's hidden truth and runs no filter")
    from vlr_drake.tasks.common import output_files

    _check_own_files(args, output_files(args.command, args.out))
    budget = {} if args.iterations is None else {"identify_iterations": args.iterations}  # (else the task's, 40)
    common = dict(model=args.model, out=args.out, progress=not args.no_progress, meshcat=_meshcat(args), **budget,
                  **_task_settings(args))
    if args.command == "write":
        from vlr_drake.tasks.write import run_write

        result = run_write(args.word, **common)
    elif args.command == "maze":
        from vlr_drake.tasks.maze import run_maze

        result = run_maze(**common)
    else:
        from vlr_drake.tasks.stack import run_stack

        result = run_stack(alpha=args.alpha, **common)
    pos, rot = result.get("position_error_mm"), result.get("orientation_error_deg")
    line = f"{result['task']} on the {result['plant']} plant: success {result['success']}"
    if pos:
        line += f"; position error {pos['mean']:.3f} +- {pos['sd']:.3f} mm (max {pos['max']:.3f})"
    if rot:
        line += f"; orientation error {rot['mean']:.2f} +- {rot['sd']:.2f} deg (max {rot['max']:.2f})"
    print(line)
    if result.get("recording"):
        print(f"wrote {result['recording']}")
    path = args.json or str(Path(args.out) / f"{args.command}_seed{result['seed']}.json")
    if not args.json:
        note_replaced(path, result, TASK_SETTINGS, args.command)
    write_json(result, path)
    return result


# ------------------------------------------------------------------------------ bench
def bench(args) -> dict:
    from vlr_drake import bench as b

    if args.particles is None:
        args.particles = 20_000 if args.what == "rolling" else 60_000
    if args.what != "filter":
        given = [flag for flag, value in (("--iterations", args.iterations), ("--run-iterations", args.run_iterations))
                 if value is not None]
        if given:  # the filter benchmark's options: said, not silently ignored
            raise ValueError(f"bench {args.what}: {', '.join(given)} set the filter benchmark ('bench filter')")
    if args.what == "motion":
        r = b.bench_motion(particles=args.particles, seed=args.seed)
        print(b.format_motion(r))
    elif args.what == "rolling":
        r = b.bench_rolling(particles=args.particles, seed=args.seed)
        print(b.format_rolling(r))
    else:
        counts = {k: v for k, v in (("iterations", args.iterations), ("run_iterations", args.run_iterations))
                  if v is not None}  # (not given: bench_filter's defaults)
        r = b.bench_filter(particles=args.particles, seed=args.seed, **counts)
        print(b.format_filter(r))
    write_json(r, args.json)
    return r


# ------------------------------------------------------------------------------ demo
#: The demo's writing result, in ``--out`` (its identification's JSON: ``--json`` or identify's).
DEMO_WRITE_JSON = "demo_write.json"


def demo(args) -> None:
    t0 = time.perf_counter()
    args.experiment, args.hand = "known_hand", "model_o"
    s = args.loaded
    if s is not None and (s.hand_spec is not None or s.hand not in (None, "model_o")):
        raise ValueError(f"demo: scenario '{s.name}' holds another hand than the Model O's (the demo's); "
                         f"run it with vlr-drake identify --scenario")
    # a scenario for another experiment, or a bad --object, is refused before anything runs (an
    # unknown --object had been refused after the self-check)
    opts = _identify_options(args)
    opts.validate()
    from vlr_drake.tasks.common import output_files

    out = Path(args.out)
    _check_own_files(args, {**_identify_files(args, opts), out / DEMO_WRITE_JSON: "the demo's writing result",
                            **output_files("write", out)})
    print("== self-check: the motion function, batched vs MathematicalProgram ==")
    selfcheck(args.seed)
    print("\n== self-identification: Model O holding an object, known hand ==")
    identify(args)
    if interrupt_asked():  # (a Ctrl-C had stopped the identification and then run the writing anyway)
        return
    print("\n== in-hand manipulation: the identified model writes with the POM ==")
    # the writing identifies its own grasp on the model plant, with the scenario's seed, pose
    # noise and exploration where it sets them (it had taken none of them; a review): at most
    # 10,000 particles and 100 iterations (fewer when the demo was asked for fewer)
    from vlr_drake.scenario import task_settings
    from vlr_drake.tasks.write import run_write

    kw = task_settings(args.loaded, args.scenario_path, seed=args.seed, plant="model", particles=args.particles)
    kw["particles"] = min(10_000, kw.get("particles") or 10_000)
    result = run_write("VLR", model="filter", identify_iterations=min(100, args.iterations), out=args.out,
                       progress=not args.no_progress, meshcat=_meshcat(args), **{"scenario": None, **kw})
    pos = result["position_error_mm"]
    print(f"wrote 'VLR': position error {pos['mean']:.3f} +- {pos['sd']:.3f} mm (max {pos['max']:.3f}); "
          f"plot in {args.out}/write_path.png")
    write_json(result, str(Path(args.out) / DEMO_WRITE_JSON))
    print(f"\ndemo finished in {time.perf_counter() - t0:.0f} s; outputs in {args.out}/")


_SCENARIO_HELP = ("scenario: a YAML file, or the name of an example in diagrams/ (default, model_plant, stiffness, "
                  "novel_NH1, novel_NH2, novel_NH3, custom_hand_and_object, ...); flags given here override it")

_DESCRIPTIONS = {
    "selfcheck": """Build the default hand (Model O), draw one stable fingertip grasp, move it through a few
random tendon actions with the batched Newton solver of the motion function (Eq. 9) and with
MathematicalProgram (IPOPT and SNOPT), and print how far apart the joint angles are.""",
    "identify": """Run one self-identification experiment of the paper (Algorithm 1): grasp, then exploratory
tendon actions (random on the physics plant, as the paper's; informative on the model
plant), each followed by a camera measurement of the POM and a particle filter iteration,
until the 95% intervals of the joint angles, and of the identified springs and links,
are narrow (converged; --filter convergence_deg=..., parameter_convergence=...) or the
iteration budget is spent. Prints a table of estimated vs true joint angles, contacts (and
stiffness or link lengths), writes convergence plots and the JSON result (its fields: docs/result-files.md)
to --out. The experiment follows from the scenario's prior when not given:
known_hand (joint angles and contacts unknown), stiffness (also the thumb's distal spring),
novel_fingers (also the proximal link lengths of the replaced fingers of NH1/NH2/NH3).
Plants: physics (the default without a scenario, as in the paper's experiments: Drake
MultibodyPlant, rendered palm camera, AprilTag observer) or model (the VLR model with hidden
truth, fast; --plant model). --meshcat draws the hypotheses per iteration (the
paper's Fig. 4 colours) and saves an HTML recording.""",
    "demo": """The main job: the self-check, then a self-identification run of the Model O holding the
apple on the physics plant seen by the rendered camera (summary table, convergence plots,
JSON; --plant model for the fast model plant), then a short handwriting task on the model
plant with its identified model (plot and JSON). Outputs go to --out; --meshcat prints the Meshcat URL and
saves HTML recordings of the hypotheses and of the writing.""",
    "write": """Handwriting (the paper's Fig. 6A): the Model O moves the POM of the grasped object along the
strokes of the letters, by the Jacobian controller (Eq. 10-12, position rows) with camera
feedback. --model filter self-identifies the grasp first (--particles, --iterations) and
keeps updating the filter during control; --model true uses the plant's hidden truth.
Writes write_path.png and the JSON result (position error, success) to --out; --meshcat
shows the target strokes beside the object and saves write.html.""",
    "maze": """Marble maze (the paper's Fig. 6B): the hand tilts a maze plate (orientation control only)
through a precomputed sequence of plate orientations so that a simulated marble rolls from
start to goal. Writes maze.png and the JSON result (orientation error, success) to --out;
--meshcat shows the goal orientation beside the plate and saves maze.html.""",
    "stack": """Cup stacking (the paper's Fig. 7): each of four cups is grasped at an unknown tilt and
offset and aligned over the cup below in SE(3) by the Jacobian controller with the
rotational weight alpha (Eq. 12), then released; success when every cup nests. Writes
stack.png and the JSON result (position and orientation error) to --out; --meshcat shows
each cup's goal pose beside it and saves stack.html.""",
    "reproduce": """The paper's table: the identification experiments (known hand, stiffness, NH1-NH3) and the
tasks (writing, maze, stacking), --trials trials each (seeds --seed, --seed + 1, ...; on the
physics plant the known hand's with each of the paper's four objects, the stiffness with the
toy block), mean +- SD of the paper's measure beside the paper's, whether ours is better, and
for the identification rows how often the truth lay inside the 95% intervals (joints,
contacts, springs, links) and how many identified hand parameters stayed weakly identified.
Prints the markdown table and writes reproduce.md, reproduce.json and a figure of the rows
against the paper's (reproduce.png) to --out. The default is
the paper's setting, the physics plant with the rendered camera (5 trials: about an hour and
a half on 2 cores, most of it the identification rows, each with identify's budget); --plant model runs
the fast model plant (5 trials: about 5 minutes); --experiments runs some of the rows. A --scenario
supplies the plant and its settings; each row sets its own experiment, hand and object.
--quick: one small trial of each (a smoke run, not a result).""",
    "replay": """Replay an identification's trace (vlr-drake identify --trace PATH) without the plant: the
filter gets the same measurements, actions and motor readings, so with the run's settings it
reproduces the run exactly, and with --filter KEY=VALUE overrides it shows what other
settings would have made of the same data (exact for random exploration, the physics
plant's default): a replay stops where such a run would have stopped, at convergence
(--all-steps replays the whole trace), and one that has not converged ends with the trace,
where the recorded run stopped. Given several traces (vlr-drake reproduce keeps one per identification
run in out/reproduce/traces/), it also prints the table's rows for them. --profile fixes one identified hand parameter (stiffness, or
link_length:<finger>) at each of --values and prints each value's log evidence, the sum over
the run of log p(measurement | the ones before), relative to the best: how strongly the
measurements themselves favour each value, apart from the prior and the point estimate.
With --statics it runs no filter: it says, from a simulation trace's plant truths, how far
the VLR's equilibrium under the motors' commands sits from the plant's angles with the
parameter at each value, and how well its motions follow the plant's (where the model's
statics match the plant, and how much of the parameter the motions show).""",
    "diagrams": """Write the system diagram of each example scenario (diagrams/*.yaml) as Graphviz .dot text
beside it, and render .svg pictures when Graphviz's dot is installed.""",
    "bench": """Benchmarks that print their figures: motion (one batched move of all particles vs one
MathematicalProgram solve), rolling (the same for the rolling model's move, motion_model=rolling, with
the pinned move of the same grasps beside it) or filter (full filter iterations on the model plant, then a known-hand
identification on the physics plant with its wall time split into physics, rendering, detection,
filtering and the rest: building the plant, the grasp). The motion benchmark's reference solves are
timed as a caller pays them (building the program and solving it, the solver's own part beside it),
over those that succeed; how many failed is printed.""",
}


#: Fewest particles a filter runs with (FilterConfig.validate says the same).
MIN_PARTICLES = 10


def _common(p: argparse.ArgumentParser, particles: int, iterations: int | None, out: str = "out",
            least_iterations: int = 1, iterations_help: str | None = None,
            scenario_help: str = _SCENARIO_HELP) -> None:
    p.add_argument("--scenario", type=path_text, default=None, help=scenario_help)
    p.add_argument("--seed", type=count(0), default=None,
                   help="seed of every random draw (default: the scenario's, else 0)")
    p.add_argument("--particles", type=count(MIN_PARTICLES), default=None,
                   help=f"number of particles (default: the scenario's filter.particles, else {particles})")
    p.add_argument("--iterations", type=count(least_iterations), default=iterations,
                   help=f"iteration budget of the identification (default {iterations_help or iterations})")
    p.add_argument("--json", type=path_text, default=None, help="write the result as JSON to this path (default: a file in --out)")
    p.add_argument("--out", type=path_text, default=out, help=f"output folder for plots, recordings and results (default ./{out})")
    p.add_argument("--plant", choices=["model", "physics"], default=None,
                   help="model: the VLR model with hidden truth (fast); physics: Drake MultibodyPlant with the "
                        "rendered camera (default: the scenario's, else physics)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--meshcat", action=argparse.BooleanOptionalAction, default=None,
                   help="show the run in Meshcat (URL printed) and save an HTML recording in --out "
                        "(default: the scenario's meshcat, else no)")


def _config_arguments(p: argparse.ArgumentParser, filter_note: str, prior_note: str) -> None:
    """``--filter KEY=VALUE`` and ``--prior KEY=VALUE`` (repeatable), for identify and replay."""
    p.add_argument("--filter", action="append", metavar="KEY=VALUE",
                   help=f"override a filter setting (vlr_drake.filter.FilterConfig), {filter_note}; repeatable")
    p.add_argument("--prior", action="append", metavar="KEY=VALUE",
                   help=f"override a prior setting (vlr_drake.filter.PriorConfig), {prior_note}; repeatable")


def _parser(name: str, sub, help_text: str) -> argparse.ArgumentParser:
    return sub.add_parser(name, help=help_text, description=_DESCRIPTIONS[name],
                          formatter_class=argparse.RawDescriptionHelpFormatter)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="vlr-drake", description=plain(__doc__),
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)

    p = _parser("selfcheck", sub, "move the default hand with both solvers and compare")
    p.add_argument("--seed", type=count(0), default=0, help="seed of the grasp and the actions (default 0)")
    p.add_argument("--json", type=path_text, default=None, help="write the result as JSON to this path")

    for name, help_text in [("identify", "run a self-identification experiment"),
                            ("demo", "the main job: self-check, self-identification, handwriting")]:
        p = _parser(name, sub, help_text)
        if name == "identify":  # None: the experiment's (IdentifyOptions.max_iterations)
            _common(p, particles=20_000, iterations=None,
                    iterations_help="120; 240 for the stiffness and the novel fingers on the physics plant, and the "
                                    "stiffness on the model plant too, whose hand parameters narrow slowly: "
                                    "vlr_drake.identify.ITERATIONS")
        else:  # the demo's identification is the Model O's known hand
            _common(p, particles=20_000, iterations=120,
                    scenario_help="a known-hand scenario of the Model O: a YAML file, or the name of an example "
                                  "in diagrams/ (default, model_plant); flags given here override it")
        if name == "identify":
            p.add_argument("experiment", nargs="?", default=None, choices=["known_hand", "stiffness", "novel_fingers"],
                           help="known_hand: angles and contacts; stiffness: also the thumb's distal spring; "
                                "novel_fingers: also the proximal lengths of replaced fingers (default: what the "
                                "scenario's prior leaves unknown, else known_hand)")
        if name == "identify":
            p.add_argument("--actions", choices=["random", "informative"], default=None,
                           help="how each exploratory action is chosen: random (the paper's) or informative (the "
                                "most informative of 8 random proposals; default: informative on the model plant, "
                                "random on the physics plant)")
            p.add_argument("--trace", type=path_text, default=None, metavar="PATH",
                           help="also save the run's trace (the filter's inputs and the truth) as .npz, for "
                                "vlr-drake replay")
            p.add_argument("--draws", type=count(1), default=1, metavar="K",
                           help="after the run, filter its measurements again under K draws of the filter's "
                                "randomness (the first the run's own) and pool them: the result's 'pooled', "
                                "the mixture of their clouds, whose intervals are honest where one draw's are "
                                "too sure (a spring, a link; as vlr-drake replay --draws; K times the "
                                "filter's time)")
            p.add_argument("--stuck-probability", type=float, default=None, metavar="P",
                           help="probability that a hypothesis with no equilibrium after an action is held "
                                "where it was by friction (0 discards it; default: 1 for novel fingers on the "
                                "physics plant, else 0; vlr_drake.identify.STUCK_PROBABILITY)")
            p.add_argument("--link-weight", action=argparse.BooleanOptionalAction, default=None,
                           help="the filter's model carries the weight of the fingers' links, gravity from the "
                                "physics plant's mounting (physics plant only: on by default there; the model "
                                "plant's truth, the paper's Eq. 9, has none; vlr_drake.identify.LINK_WEIGHT)")
            p.add_argument("--object-weight", action="store_true",
                           help="identify the object's weight as well (its mass and how the contacts share it), "
                                "carried with the links' weight (physics plant only); off by default "
                                "(IdentifyOptions.object_weight)")
            p.add_argument("--object-mass", type=float, default=None, metavar="KG",
                           help="the object's weighed mass [kg]: identify its weight (--object-weight) with the "
                                "mass known within --object-mass-tolerance (the toy block: 0.028; "
                                "IdentifyOptions.object_mass)")
            p.add_argument("--object-mass-tolerance", type=float, default=None, metavar="FRACTION",
                           help="how well --object-mass is known, a fraction of it (default 0.25)")
            _config_arguments(p, "after the scenario's, e.g. --filter motion_model=rolling",
                              "after the scenario's, e.g. --prior link_range=0.035,0.07")
        p.add_argument("--object", default=None, help="object preset held (default: the scenario's, else the experiment's: "
                                                        "toy_block for stiffness as in the paper, apple otherwise)"
                       if name == "identify" else "object preset held (default: the scenario's, else apple)")
        if name == "identify":  # the demo's hand is the Model O
            p.add_argument("--hand", default=None, type=_preset_hand,
                           help="hand preset: model_o, or NH1/NH2/NH3 for novel_fingers (default: the scenario's, "
                                "else model_o)")

    for name, help_text in [("write", "write a word with the POM (position control)"),
                            ("maze", "play a marble maze (orientation control)"),
                            ("stack", "stack cups (SE(3) control with the rotational weight alpha)")]:
        p = _parser(name, sub, help_text)
        _common(p, particles=3000, iterations=None, least_iterations=0, iterations_help="40")
        p.add_argument("--model", choices=["true", "filter"], default="filter",
                       help="the controller's model: the plant's hidden truth, or self-identified first "
                            "(default: filter)")
        if name == "write":
            p.add_argument("word", nargs="?", default="SCIENCE", help="letters A-Z (default SCIENCE)")
        if name == "stack":
            p.add_argument("--alpha", type=float, default=9.5,
                           help="rotational weight of Eq. 12, on rotations in rad against positions in mm (paper: 9.5)")

    p = _parser("reproduce", sub, "the paper's table: experiments and tasks, paper vs ours")
    _common(p, particles=20_000, iterations=None, out="out/reproduce",
            iterations_help="each experiment's, as identify's: 120, 240 for the stiffness and the novel "
                            "fingers on the physics plant and the stiffness on the model plant; 100 for the "
                            "tasks' self-identification")
    p.add_argument("--trials", type=count(1), default=None, help="trials per row (default 5)")
    p.add_argument("--quick", action="store_true", help="one trial of each, small: a smoke run")
    p.add_argument("--experiments", default=None,
                   help="comma-separated experiments to run (any case), e.g. known_hand,stiffness,NH1,NH2,NH3 "
                        "(default: all of known_hand, stiffness, NH1, NH2, NH3, write, maze, stack)")

    p = _parser("replay", sub, "replay an identification's trace offline")
    p.add_argument("trace", nargs="+", help="traces written by vlr-drake identify --trace (or by reproduce, in "
                                            "traces/ of its --out, by default out/reproduce/traces/)")
    _config_arguments(p, "e.g. --filter particles=60000 --filter sigma_rotation=0.02",
                      "e.g. --prior object_mass_unknown=true (with --filter gravity_loads=following)")
    p.add_argument("--profile", default=None, metavar="PARAMETER",
                   help="fix this identified hand parameter at each of --values and compare the evidence: "
                        "stiffness [N m/rad] or link_length:<finger> [m]")
    p.add_argument("--values", default=None, help="comma-separated values of the --profile parameter (positive: "
                                                  "N m/rad or m)")
    p.add_argument("--statics", action="store_true",
                   help="with --profile: no replay; how the VLR's equilibrium under the motors' commands, with the "
                        "parameter at each value, agrees with the plant's true angles along the trace (simulation "
                        "traces)")
    p.add_argument("--all-steps", action="store_true",
                   help="replay every step of the trace; by default a replay stops where a run with its settings "
                        "would have stopped, at convergence (plus the run's extra iterations)")
    p.add_argument("--at", default=None, metavar="STEPS",
                   help="comma-separated iteration counts, e.g. 60,120,240: also the errors of the estimate "
                        "after each (what a shorter budget would have given; simulation traces)")
    p.add_argument("--filter-seed", type=count(0), default=None, metavar="SEED",
                   help="seed of the filter's own random draws (the prior's, resampling's and roughening's) "
                        "instead of the run's: the same measurements under another draw, the filter's own spread")
    p.add_argument("--draws", type=count(1), default=1, metavar="K",
                   help="replay each trace K times under K draws of the filter's own randomness (the first "
                        "with the run's seed, or --filter-seed's; vlr_drake.trace.draw_seed), and give the rows "
                        "with the traces' means over their draws and how far one draw moves them: compare "
                        "settings with several draws, since one draw can move an estimate as much as its error; "
                        "also each trace's pooled estimate, the equal mixture of its draws' clouds (its mean "
                        "the draws' mean, its intervals their spread as well; --all-steps where draws would "
                        "stop at different steps)")
    p.add_argument("--json", type=path_text, default=None, help="write the result as JSON to this path")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")

    p = _parser("diagrams", sub, "write each example scenario's diagram (.dot; .svg if Graphviz is installed)")
    p.add_argument("--folder", type=path_text, default=None,
                   help="folder of scenario files; the diagrams are written beside them (default: diagrams/)")
    p.add_argument("--no-render", action="store_true", help="only the .dot text")

    p = _parser("bench", sub, "benchmarks that print their figures")
    p.add_argument("what", choices=["motion", "rolling", "filter"])
    p.add_argument("--particles", type=count(MIN_PARTICLES), default=None,
                   help="number of particles (default 60,000; rolling 20,000)")
    p.add_argument("--iterations", type=count(1), default=None, help="filter iterations timed (default 10)")
    p.add_argument("--run-iterations", type=count(0), default=None,
                   help="filter: iterations of the known-hand identification on the physics plant whose wall "
                        "time is split into physics, rendering, detection, filtering and the rest (default 30; "
                        "0: none)")
    p.add_argument("--seed", type=count(0), default=0, help="seed of every random draw (default 0)")
    p.add_argument("--json", type=path_text, default=None, help="write the result as JSON to this path")

    args = parser.parse_args(argv)
    with warning_lines(f"vlr-drake {args.command}"):
        return _command(args)


def _command(args) -> int:
    """Run the parsed command: 0, or 2 after :func:`report` on a user's error, or 130 where
    a Ctrl-C stopped its loop (:func:`vlr_drake.entry.stop_between_steps`) and what it had
    done was written."""
    clear_interrupt()
    try:
        _check_outputs(args)
        _load_scenario(args)
        if args.command == "selfcheck":
            write_json(selfcheck(args.seed), args.json)
        elif args.command == "identify":
            identify(args)
        elif args.command == "replay":
            replay_trace(args)
        elif args.command == "demo":
            demo(args)
        elif args.command == "bench":
            bench(args)
        elif args.command in ("write", "maze", "stack"):
            task(args)
        elif args.command == "diagrams":
            from vlr_drake.builder import graphviz_available, write_diagrams

            for path in write_diagrams(args.folder, render=not args.no_render):
                print(f"wrote {path}")
            if not args.no_render and graphviz_available() is None:
                print("Graphviz's dot is not on the PATH: no .svg written")
        elif args.command == "reproduce":
            from vlr_drake.reproduce import TABLE_FILES, format_table, reproduce

            given = [flag for flag, value in (("--trials", args.trials), ("--particles", args.particles),
                                              ("--iterations", args.iterations)) if value is not None]
            if args.quick and given:  # said, not silently replaced by the quick run's
                raise ValueError(f"--quick sets the trials, particles and iterations itself (1, 1,000 and 8): "
                                 f"drop {', '.join(given)} or --quick")
            # (a --json named as the table's own reproduce.json had written the table without its
            # runs over it: every trial's result lost)
            json_file, markdown, figure = (Path(args.out) / name for name in TABLE_FILES)
            _check_own_files(args, {json_file: "the table's JSON with every trial's result", markdown: "the table's markdown",
                                    figure: "the table's figure"})
            r = reproduce(trials=5 if args.trials is None else args.trials, plant=args.plant,
                          particles=(args.particles if args.particles is not None
                                     else args.loaded.filter.particles if args.loaded else 20_000),
                          iterations=args.iterations, quick=args.quick, out=args.out,
                          progress=not args.no_progress, seed=args.seed, scenario=args.loaded,
                          scenario_path=args.scenario_path, meshcat=_meshcat(args),
                          experiments=None if args.experiments is None else [
                              e.strip() for e in args.experiments.split(",") if e.strip()])
            print(format_table(r))
            print(f"wrote {markdown}, {json_file}" + (f" and {r['plot']}" if r["plot"] else ""))
            write_json(r, args.json)
    except USER_ERRORS as e:
        return report(f"vlr-drake {args.command}", e)
    except KeyboardInterrupt:  # a Ctrl-C where no loop takes it between steps, or a second one
        print(f"vlr-drake {args.command}: stopped by Ctrl-C before its results were written", file=sys.stderr)
        return 130
    if interrupt_asked():
        print(f"vlr-drake {args.command}: stopped by {interrupt_asked()}; what it had done is written above",
              file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
