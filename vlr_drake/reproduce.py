"""``vlr-drake reproduce``: the paper's experiments and tasks, with its numbers beside ours.

Each row runs its trials (5 by default, seeds 0..4; on the physics plant the known hand's
with each of the paper's four objects, so 20 runs, as the paper's Fig. 4 did), takes mean
+- SD over the runs of the paper's measure, and says whether ours is better (smaller) than
the paper's mean. The table is printed and written as markdown (and the rows as JSON).
``quick`` runs one trial of each with few particles and iterations: a smoke run of the
whole table, not a result.
"""

from __future__ import annotations

import json
import sys
import traceback
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vlr_drake.entry import (
    as_spelled,
    interrupt_asked,
    interrupted,
    replacing,
    saved_trace,
    stop_between_steps,
)
from vlr_drake.identify import DEFAULT_OBJECT, KNOWN_HAND_OBJECTS, run_identification
from vlr_drake.kinematics import is_count
from vlr_drake.scenario import ignored_by_tasks, options_from_scenario, task_settings

__all__ = ["PAPER_ROWS", "EXPERIMENTS", "known_hand_objects", "reproduce", "format_table", "honesty"]


@dataclass(frozen=True)
class PaperRow:
    key: str
    label: str
    mean: float
    sd: float
    unit: str


#: The table's experiments, in its order (``reproduce(experiments=...)`` runs some of them).
EXPERIMENTS = ("known_hand", "stiffness", "NH1", "NH2", "NH3", "write", "maze", "stack")

#: The object of the stiffness experiment (the paper's Fig. 5: the toy block).
STIFFNESS_OBJECT = DEFAULT_OBJECT["stiffness"]

#: The stacking rows' errors of the cups as grasped, before control (the stack result's fields).
STACK_INITIAL = {"stack_position": "initial_position_error_mm", "stack_orientation": "initial_orientation_error_deg"}

#: The identification experiments' (experiment, hand) runs.
IDENTIFICATION_RUNS = {"known_hand": ("known_hand", "model_o"), "stiffness": ("stiffness", "model_o"),
                       **{nh: ("novel_fingers", nh) for nh in ("NH1", "NH2", "NH3")}}

#: The paper's figures (Hang et al. 2021, real hardware; DESIGN.md section 10).
PAPER_ROWS = [
    PaperRow("known_hand", "proximal joint error, known hand", 1.78, 0.92, "deg"),
    PaperRow("known_hand_iterations", "iterations to converge, known hand", 15.1, 3.6, "it"),
    PaperRow("stiffness", "thumb distal stiffness error", 0.0026, 0.0012, "N m/rad"),
    PaperRow("NH1", "NH1 link length error", 2.4, 2.1, "mm"),
    PaperRow("NH2", "NH2 link length error", 2.9, 1.7, "mm"),
    PaperRow("NH3", "NH3 link length error", 3.4, 2.3, "mm"),
    # the novel hands' joint configuration, measured by the paper with tags on the fingertips;
    # here the proximal joints, as for the known hand
    PaperRow("NH1_joints", "NH1 proximal joint error", 2.58, 1.20, "deg"),
    PaperRow("NH2_joints", "NH2 proximal joint error", 3.04, 1.49, "deg"),
    PaperRow("NH3_joints", "NH3 proximal joint error", 3.21, 1.26, "deg"),
    PaperRow("write", "handwriting position error", 0.42, 0.34, "mm"),
    PaperRow("maze", "marble maze orientation error", 1.20, 1.38, "deg"),
    PaperRow("stack_position", "cup stacking position error", 2.1, 0.92, "mm"),
    PaperRow("stack_orientation", "cup stacking orientation error", 5.16, 1.83, "deg"),
]


def known_hand_objects(plant: str) -> tuple:
    """The objects of the known-hand row on ``plant``: the paper's four on the physics
    plant; on the model plant, whose hidden truth does not depend on the object, one run
    per trial (None: the scenario's or the default object)."""
    return KNOWN_HAND_OBJECTS if plant == "physics" else (None,)


#: The paper's measure of one identification run, per experiment (the table's rows).
IDENTIFICATION_MEASURES = {
    "known_hand": lambda r: np.mean(r["proximal_joint_error_deg"]),
    "stiffness": lambda r: r["stiffness_error_Nm_per_rad"],
    "novel_fingers": lambda r: np.mean(list(r["link_length_error_mm"].values())),
}


def honesty(runs: list[dict]) -> dict:
    """How often the truth lay inside the reported 95% intervals over identification runs
    (result dicts): the mean share of joint angles and of contacts, the springs and links
    inside as [count, of], and the identified hand parameters still weakly identified
    (:func:`vlr_drake.identify.hand_parameter_report`) as [count, of]."""
    out = {"joints": float(np.mean([r["truth_inside_95_theta"] for r in runs])),
           "contacts": float(np.mean([r["truth_inside_95_contact"] for r in runs]))}
    inside = [(n, v) for r in runs for n, v in r.get("hand_parameter_inside_95", {}).items()]
    springs = [v for n, v in inside if n.startswith("stiffness:")]
    links = [v for n, v in inside if n.startswith("link_length:")]
    params = sum(len(r.get("hand_parameters", {})) for r in runs)
    if springs:
        out["stiffness"] = [int(sum(springs)), len(springs)]
    if links:
        out["links"] = [int(sum(links)), len(links)]
    if params:
        out["weakly_identified"] = [sum(len(r.get("weakly_identified", [])) for r in runs), params]
    return out


def format_honesty(h: dict | None) -> str:
    """One table cell: "joints 0.93, contacts 0.90, link 5 of 5, weak 1 of 5"."""
    if not h:
        return ""
    text = f"joints {h['joints']:.2f}, contacts {h['contacts']:.2f}"
    for key, label in (("stiffness", "spring"), ("links", "link"), ("weakly_identified", "weak")):
        if key in h:
            text += f", {label} {h[key][0]} of {h[key][1]}"
    return text


def identification_rows(experiment: str, hand: str) -> list[tuple[str, object]]:
    """The table rows an identification run counts in, as (row key, measure of its result
    or errors dict): its experiment's, or for a novel hand the hand's link row and its
    joint row."""
    if experiment == "novel_fingers":
        return [(hand, IDENTIFICATION_MEASURES["novel_fingers"]), (f"{hand}_joints", IDENTIFICATION_MEASURES["known_hand"])]
    return [(experiment, IDENTIFICATION_MEASURES[experiment])]


def _identify(experiment, hand, seed, plant, particles, iterations, scenario=None, scenario_path=None, obj=None,
              traces: Path | None = None):
    opts = options_from_scenario(scenario, scenario_path, experiment=experiment, hand=hand, seed=seed, plant=plant,
                                 particles=particles, max_iterations=iterations, progress=False, object=obj)
    r = run_identification(opts)
    # the filter's inputs, for vlr-drake replay, but a run a Ctrl-C stopped (its part-trace had replaced a
    # finished one's of the same name; a review); the plant named where it is not the physics plant (a
    # model-plant reproduce had replaced the physics runs' traces)
    if traces is not None and not interrupted(r.get("stopped")):
        where = "" if plant == "physics" else f"_{plant}"
        r["trace"] = saved_trace(r["_trace"], Path(traces) / f"{experiment}_{hand}_{r['object']}{where}_seed{seed}.npz",
                                 "reproduce")
    return {k: v for k, v in r.items() if not k.startswith("_")}


#: The table's files in ``out``: its JSON (every trial's result), its markdown and its figure
#: (:func:`vlr_drake.plots.make_reproduction_figure`, written once the table is finished).
TABLE_FILES = ("reproduce.json", "reproduce.md", "reproduce.png")

#: Identification iterations of the tasks' self-identification in :func:`reproduce` when no
#: budget is given.
TASK_IDENTIFY_ITERATIONS = 100


def reproduce(trials: int = 5, plant: str | None = "physics", particles: int = 20_000, iterations: int | None = None,
              quick: bool = False, out: str | Path = "out/reproduce", progress: bool = True, seed: int = 0,
              scenario=None, scenario_path=None, meshcat=None, experiments=None) -> dict:
    """Run the table; returns {"rows": [...], "runs": {...}} and writes markdown + JSON.

    ``experiments``: the names (of :data:`EXPERIMENTS`) to run, in the table's order, e.g.
    the identification experiments alone; None runs them all. A row is in the table when its
    experiment ran.

    Trials use seeds ``seed`` .. ``seed + trials - 1``. ``scenario`` (a
    :class:`vlr_drake.scenario.Scenario`, loaded from ``scenario_path``) supplies the plant
    (``plant=None``) and its settings (noise, physics, camera, exploration); each row still
    sets its own experiment, hand and object. ``meshcat``: the tasks show their targets and
    save a recording beside their plots (:class:`vlr_drake.visualization.TaskView`).
    ``iterations``: the budget of every identification, the tasks' included; None: each
    experiment's own (``vlr-drake identify``'s: :func:`vlr_drake.identify.default_iterations`),
    and :data:`TASK_IDENTIFY_ITERATIONS` for the tasks."""
    from tqdm.auto import tqdm

    from vlr_drake.tasks.common import TaskSetupError
    from vlr_drake.tasks.maze import run_maze
    from vlr_drake.tasks.stack import run_stack
    from vlr_drake.tasks.write import run_write

    if quick:
        trials, particles, iterations = 1, 1000, 8
    # checked once here, not by every trial in turn (each of which had failed on its own)
    counts = {"trials": (trials, 1), "particles": (particles, 1), "seed": (seed, 0)}
    if iterations is not None:  # (None: each experiment's own budget)
        counts["iterations"] = (iterations, 1)
    for name, (value, least) in counts.items():
        if not is_count(value, least):
            raise ValueError(f"reproduce: '{name}' must be an integer >= {least}, got {value!r}")
    # named in any case, as --hand's names are (nh2 for NH2)
    chosen = EXPERIMENTS if experiments is None else tuple(as_spelled(e, EXPERIMENTS) for e in experiments)
    unknown = [e for e in chosen if e not in EXPERIMENTS]
    if unknown or not chosen:
        raise ValueError(f"reproduce: experiments must be some of {', '.join(EXPERIMENTS)}, got {list(chosen)}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    plant = plant or (scenario.plant if scenario is not None else "physics")
    seeds = range(seed, seed + trials)
    sc = (scenario, scenario_path)
    objects = {"known_hand": known_hand_objects(plant), "stiffness": (STIFFNESS_OBJECT,)}
    for name in chosen if scenario is not None else ():  # a row the scenario cannot run, said before
        try:  # any trial (each trial had failed in turn, with its traceback, into a table of nan rows)
            if name in IDENTIFICATION_RUNS:
                experiment, hand = IDENTIFICATION_RUNS[name]
                for o in objects.get(name, (None,)):
                    options_from_scenario(scenario, scenario_path, experiment=experiment, hand=hand, plant=plant,
                                          object=o).validate()
            else:
                task_settings(scenario, scenario_path, plant=plant)
        except ValueError as e:
            raise ValueError(f"reproduce: the row '{name}' cannot run under this scenario: {e}") from None
    tasks = [name for name in chosen if name not in IDENTIFICATION_RUNS]
    ignored = ignored_by_tasks(scenario, plant) if scenario is not None and tasks else []
    if ignored:  # said, as the task commands say it (a dropout had reached the identification rows alone)
        print(f"reproduce: warning: scenario '{scenario.name}': the task rows ({', '.join(tasks)}) do not use "
              f"{', '.join(ignored)}", file=sys.stderr)
    tr = out / "traces"  # one trace per identification run (vlr-drake replay)
    runs: dict[str, list] = {}
    # As the paper ran them: the known hand with each of its four objects (Fig. 4; trials
    # each), the stiffness with the toy block (Fig. 5); the novel hands name no object.
    # (each object's run its own trial: one that fails loses none of the seed's others)
    jobs = [(name, lambda s, name=name, run=run: [
                _attempt(name, s, lambda o=o: _identify(*run, s, plant, particles, iterations, *sc, obj=o, traces=tr),
                         obj=o)
                for o in objects.get(name, (None,)) if not interrupt_asked()])
            for name, run in IDENTIFICATION_RUNS.items()]
    # Tasks run with the identified model (self-identification first, then the filter keeps
    # updating during control), at up to 10,000 particles and 100 identification iterations.
    task_model = "true" if quick else "filter"
    def task(name, s):
        return dict(model=task_model, progress=False, out=str(out / f"{name}_{s}"), meshcat=meshcat,
                    identify_iterations=TASK_IDENTIFY_ITERATIONS if iterations is None else iterations,
                    **task_settings(scenario, scenario_path, seed=s, plant=plant, particles=min(particles, 10_000)))

    jobs += [("write", lambda s: run_write("I" if quick else "SCIENCE", **task("write", s))),
             ("maze", lambda s: run_maze(**task("maze", s))),
             ("stack", lambda s: run_stack(**task("stack", s)))]
    jobs = [(name, job) for name, job in jobs if name in chosen]
    bar = tqdm(total=len(jobs) * trials, disable=not progress, desc="reproduce", unit="trial")
    settings = {"plant": plant, "trials": trials, "particles": particles, "iterations": iterations, "quick": quick,
                "seed": seed, "experiments": [name for name, _ in jobs],
                "scenario": None if scenario is None else scenario.name,
                "scenario_path": None if scenario_path is None else str(scenario_path), "interrupted": None}
    with stop_between_steps("the table"):  # a Ctrl-C keeps the trials done (it had lost even those;
        for name, job in jobs:  # a review): the one under way stops, is left out, and the table is written
            if interrupt_asked():
                break
            runs[name] = []
            for s in seeds:
                if interrupt_asked():
                    break
                try:
                    r = job(s)
                except TaskSetupError as e:  # a task that cannot start from this seed's draw: a failed
                    # trial, counted and said, not the end of the table (a review: one lost every run)
                    print(f"reproduce: {name}, seed {s}: {e}")
                    r = {"task": name, "seed": s, "success": False, "setup_error": str(e),
                         "position_error_mm": None, "orientation_error_deg": None}
                except Exception as e:
                    r = _failed(name, s, e)
                # a run a Ctrl-C stopped part-way is no trial
                runs[name] += [x for x in (r if isinstance(r, list) else [r]) if not interrupted(x.get("stopped"))]
                settings["interrupted"] = interrupt_asked()
                bar.update(1)
                if any(runs.values()):  # (an empty table had replaced the last one's; a review)
                    _write_table(out, settings, runs, tr)  # the table so far, kept whatever comes after
    bar.close()
    if interrupt_asked() and not any(runs.values()):
        raise KeyboardInterrupt  # stopped before a trial was done: nothing to write (the command says so)
    return _write_table(out, settings, runs, tr, figure=True)


def _failed(name: str, seed: int, e: Exception, obj: str | None = None) -> dict:
    """A trial that failed, said (with its traceback) and kept as a result that counts as
    failed: the rest of the table runs on (a review: a failure late in an hours-long table
    had lost every finished row). ``obj``: the known hand's object, of four per seed."""
    where = f", seed {seed}" + ("" if obj is None else f", object {obj}")
    print(f"reproduce: {name}{where} failed: {type(e).__name__}: {e}", file=sys.stderr)
    traceback.print_exc()
    return {"seed": seed, "failed": f"{type(e).__name__}: {e}", "success": False,
            "position_error_mm": None, "orientation_error_deg": None, **({} if obj is None else {"object": obj})}


def _attempt(name: str, seed: int, run, obj: str | None = None) -> dict:
    """``run()``, or where it fails (an Exception), :func:`_failed`'s result."""
    try:
        return run()
    except Exception as e:
        return _failed(name, seed, e, obj)


def _write_table(out: Path, settings: dict, runs: dict, traces: Path, figure: bool = False) -> dict:
    """The table of ``runs`` (one list of result dicts per experiment) as ``reproduce.md`` and
    ``reproduce.json`` in ``out``, and with ``figure`` as ``reproduce.png`` (the result's
    ``plot``, else null); returns the result dict. Called after every trial, so that a table
    cut short keeps the rows it finished; the figure, a second or so, once at the end."""
    measures = {  # row key: (experiment, the paper's measure of one run)
        "known_hand": ("known_hand", IDENTIFICATION_MEASURES["known_hand"]),
        # a run that did not converge counts its budget (one that stopped early, e.g. on refused
        # actions, had counted only the iterations it ran)
        "known_hand_iterations": ("known_hand", lambda r: r["iterations"] if r["converged"]
                                  else r.get("max_iterations", r["iterations"])),
        "stiffness": ("stiffness", IDENTIFICATION_MEASURES["stiffness"]),
        **{key: (nh, measure) for nh in ("NH1", "NH2", "NH3") for key, measure in identification_rows("novel_fingers", nh)},
        # the tasks: every waypoint / sample / cup of every trial, pooled (the paper's spread
        # is over those, not over trials' means)
        "write": ("write", lambda r: r["position_error_mm"]),
        "maze": ("maze", lambda r: r["orientation_error_deg"]),
        "stack_position": ("stack", lambda r: r["position_error_mm"]),
        "stack_orientation": ("stack", lambda r: r["orientation_error_deg"]),
    }
    from vlr_drake.tasks.common import pooled

    rows = []
    values = {}  # row key: each trial's figure (a task's its mean), for the figure's dots
    for p in PAPER_ROWS:
        name, measure = measures[p.key]
        if not runs.get(name):
            continue
        is_task = name in ("write", "maze", "stack")
        ran = runs[name] if is_task else [r for r in runs[name] if "failed" not in r]
        got = [measure(r) for r in ran]
        if is_task:  # a task's stats: pooled over its samples (a trial with none adds none)
            all_ = pooled(got) or {"mean": float("nan"), "sd": float("nan"), "n": 0}
            mean, sd, over = all_["mean"], all_["sd"], all_["n"]
        else:  # one number per trial that gave one (a failed run, or a NaN measure, gives none)
            v = np.asarray(got, float)
            v = v[np.isfinite(v)]
            mean, sd, over = (float(v.mean()), float(v.std()), len(v)) if v.size else (float("nan"), float("nan"), 0)
        values[p.key] = ([g["mean"] for g in got if g is not None and g["n"] > 0] if is_task
                         else [float(g) for g in got])
        identification = name in ("known_hand", "stiffness", "NH1", "NH2", "NH3") and p.key != "known_hand_iterations"
        row = {"key": p.key, "experiment": p.label, "unit": p.unit, "paper_mean": p.mean, "paper_sd": p.sd,
               "ours_mean": mean, "ours_sd": sd, "trials": len(runs[name]), "samples": over,
               "better": bool(mean < p.mean),
               "truth_inside_95": honesty(ran) if identification and ran else None}
        if not is_task and over < len(runs[name]):  # said in the cell, and no row beats the paper with them
            row["failed"] = [len(runs[name]) - over, len(runs[name])]
            row["better"] = False
        if is_task:
            # a trial that failed (a letter not written, the marble short of the goal, a cup
            # not nested) does not beat the paper whatever its error samples say
            done = sum(bool(r["success"]) for r in runs[name])
            row["succeeded"] = [done, len(got)]
            row["better"] = row["better"] and done == len(got)
        if p.key in STACK_INITIAL:
            # the cups as grasped (before control): a row the control did not improve on does not
            # beat the paper (the drawn offsets, under 2.8 mm, had beaten it with no control; a review)
            start = pooled([r.get(STACK_INITIAL[p.key]) for r in runs[name]])
            row["initial_mean"] = start["mean"] if start else None
            row["better"] = row["better"] and start is not None and mean < start["mean"]
        if p.key == "known_hand_iterations":
            # a run that did not converge counts its budget, a lower bound on the iterations it
            # needs: the row beats the paper only if every run converged
            done = sum(bool(r["converged"]) for r in ran)
            row["converged"] = [done, len(runs[name])]
            row["better"] = row["better"] and done == len(runs[name])
        rows.append(row)
    # the traces this table's runs saved (a folder of an earlier run's had been named too)
    saved = sorted(str(Path(r["trace"])) for rs in runs.values() for r in rs if r.get("trace"))
    plot = None
    if figure and rows:
        from vlr_drake.plots import plot_reproduction

        plot = str(plot_reproduction(rows, out / TABLE_FILES[2], values, title=(
            f"ours ({settings['plant']} plant, {settings['trials']} trial(s) each) against the paper's hardware")))
    result = {**settings, "traces": str(traces) if saved else None, "trace_files": saved, "rows": rows, "plot": plot}
    with replacing(out / TABLE_FILES[1]) as temporary:  # (each in one piece: a cut one had replaced the last)
        temporary.write_text(format_table(result))
    from vlr_drake.cli import _finite, _json_default  # (JSON has no NaN: a row without samples is null)

    result["runs"] = runs  # (every trial's result: the docstring's promise, which only the file had kept)
    text = json.dumps(_finite(result), indent=2, default=_json_default, allow_nan=False)
    with replacing(out / TABLE_FILES[0]) as temporary:
        temporary.write_text(text)
    return result


def format_table(result: dict) -> str:
    objects = f" (the known hand's with each of the paper's {len(KNOWN_HAND_OBJECTS)} objects)"
    head = (f"Reproduction on the {result['plant']} plant, {result['trials']} trial(s) each"
            f"{objects if 'known_hand' in result.get('experiments', EXPERIMENTS) and result['plant'] == 'physics' else ''}"
            f"{' (quick: a smoke run, not a result)' if result['quick'] else ''}\n\n")
    lines = ["| experiment | paper | ours | better | truth inside 95% |", "|---|---|---|---|---|"]
    for r in result["rows"]:
        fmt = ".4f" if r["unit"] == "N m/rad" else ".2f"
        done = f" ({r['converged'][0]} of {r['converged'][1]} converged)" if "converged" in r else ""
        if "succeeded" in r and r["succeeded"][0] < r["succeeded"][1]:
            done += f" ({r['succeeded'][0]} of {r['succeeded'][1]} succeeded)"
        if "failed" in r:  # runs that failed or gave no number: not in the mean
            done += f" ({r['failed'][0]} of {r['failed'][1]} failed)"
        if r.get("initial_mean") is not None:  # the cups as grasped, which the control improves on
            done += f" (as grasped {r['initial_mean']:{fmt}})"
        lines.append(f"| {r['experiment']} [{r['unit']}] | {r['paper_mean']:{fmt}} +- {r['paper_sd']:{fmt}} | "
                     f"{r['ours_mean']:{fmt}} +- {r['ours_sd']:{fmt}}{done} | {'yes' if r['better'] else 'no'} | "
                     f"{format_honesty(r.get('truth_inside_95'))} |")
    return head + "\n".join(lines) + "\n"
