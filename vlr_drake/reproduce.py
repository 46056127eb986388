"""``vlr-drake reproduce``: the paper's experiments and tasks, with its numbers beside ours.

Each row runs its trials (5 by default, seeds 0..4), takes mean +- SD over the trials of the
paper's measure, and says whether ours is better (smaller) than the paper's mean. The
table is printed and written as markdown (and the rows as JSON). ``quick`` runs one trial
of each with few particles and iterations: a smoke run of the whole table, not a result.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vlr_drake.identify import run_identification
from vlr_drake.scenario import options_from_scenario, task_settings

__all__ = ["PAPER_ROWS", "reproduce", "format_table"]


@dataclass(frozen=True)
class PaperRow:
    key: str
    label: str
    mean: float
    sd: float
    unit: str


#: The paper's figures (Hang et al. 2021, real hardware; DESIGN.md section 10).
PAPER_ROWS = [
    PaperRow("known_hand", "proximal joint error, known hand", 1.78, 0.92, "deg"),
    PaperRow("known_hand_iterations", "iterations to converge, known hand", 15.1, 3.6, "it"),
    PaperRow("stiffness", "thumb distal stiffness error", 0.0026, 0.0012, "N m/rad"),
    PaperRow("NH1", "NH1 link length error", 2.4, 2.1, "mm"),
    PaperRow("NH2", "NH2 link length error", 2.9, 1.7, "mm"),
    PaperRow("NH3", "NH3 link length error", 3.4, 2.3, "mm"),
    PaperRow("write", "handwriting position error", 0.42, 0.34, "mm"),
    PaperRow("maze", "marble maze orientation error", 1.20, 1.38, "deg"),
    PaperRow("stack_position", "cup stacking position error", 2.1, 0.92, "mm"),
    PaperRow("stack_orientation", "cup stacking orientation error", 5.16, 1.83, "deg"),
]


def _identify(experiment, hand, seed, plant, particles, iterations, scenario=None, scenario_path=None):
    opts = options_from_scenario(scenario, scenario_path, experiment=experiment, hand=hand, seed=seed, plant=plant,
                                 particles=particles, max_iterations=iterations, progress=False)
    r = run_identification(opts)
    return {k: v for k, v in r.items() if not k.startswith("_")}


def reproduce(trials: int = 5, plant: str | None = "physics", particles: int = 20_000, iterations: int = 100,
              quick: bool = False, out: str | Path = "out/reproduce", progress: bool = True, seed: int = 0,
              scenario=None, scenario_path=None, meshcat=None) -> dict:
    """Run the table; returns {"rows": [...], "runs": {...}} and writes markdown + JSON.

    Trials use seeds ``seed`` .. ``seed + trials - 1``. ``scenario`` (a
    :class:`vlr_drake.scenario.Scenario`, loaded from ``scenario_path``) supplies the plant
    (``plant=None``) and its settings (noise, physics, camera, exploration); each row still
    sets its own experiment, hand and object. ``meshcat``: the tasks show their targets and
    save a recording beside their plots (:class:`vlr_drake.visualization.TaskView`)."""
    from tqdm.auto import tqdm

    from vlr_drake.tasks.maze import run_maze
    from vlr_drake.tasks.stack import run_stack
    from vlr_drake.tasks.write import run_write

    if quick:
        trials, particles, iterations = 1, 1000, 8
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    plant = plant or (scenario.plant if scenario is not None else "physics")
    seeds = range(seed, seed + trials)
    sc = (scenario, scenario_path)
    runs: dict[str, list] = {}
    jobs = [("known_hand", lambda s: _identify("known_hand", "model_o", s, plant, particles, iterations, *sc)),
            ("stiffness", lambda s: _identify("stiffness", "model_o", s, plant, particles, iterations, *sc))]
    for nh in ("NH1", "NH2", "NH3"):
        jobs.append((nh, lambda s, nh=nh: _identify("novel_fingers", nh, s, plant, particles, iterations, *sc)))
    # Tasks run with the identified model (self-identification first, then the filter keeps
    # updating during control), at up to 10,000 particles and 100 identification iterations.
    task_model = "true" if quick else "filter"
    def task(name, s):
        return dict(model=task_model, progress=False, out=str(out / f"{name}_{s}"), meshcat=meshcat,
                    identify_iterations=iterations,
                    **task_settings(scenario, scenario_path, seed=s, plant=plant, particles=min(particles, 10_000)))

    jobs += [("write", lambda s: run_write("I" if quick else "SCIENCE", **task("write", s))),
             ("maze", lambda s: run_maze(**task("maze", s))),
             ("stack", lambda s: run_stack(**task("stack", s)))]
    bar = tqdm(total=len(jobs) * trials, disable=not progress, desc="reproduce", unit="run")
    for name, job in jobs:
        runs[name] = []
        for s in seeds:
            runs[name].append(job(s))
            bar.update(1)
    bar.close()

    def ident(name, key):
        return [float(np.mean(r[key])) for r in runs[name]]

    ours = {
        "known_hand": ident("known_hand", "proximal_joint_error_deg"),
        "known_hand_iterations": [float(r["iterations"]) for r in runs["known_hand"]],
        "stiffness": [float(r["stiffness_error_Nm_per_rad"]) for r in runs["stiffness"]],
        "write": [r["position_error_mm"]["mean"] for r in runs["write"]],
        "maze": [r["orientation_error_deg"]["mean"] for r in runs["maze"]],
        "stack_position": [r["position_error_mm"]["mean"] for r in runs["stack"]],
        "stack_orientation": [r["orientation_error_deg"]["mean"] for r in runs["stack"]],
    }
    for nh in ("NH1", "NH2", "NH3"):
        ours[nh] = [float(np.mean(list(r["link_length_error_mm"].values()))) for r in runs[nh]]
    rows = []
    for p in PAPER_ROWS:
        v = np.asarray(ours[p.key], float)
        rows.append({"key": p.key, "experiment": p.label, "unit": p.unit, "paper_mean": p.mean, "paper_sd": p.sd,
                     "ours_mean": float(v.mean()), "ours_sd": float(v.std()), "trials": len(v),
                     "better": bool(v.mean() < p.mean)})
    result = {"plant": plant, "trials": trials, "particles": particles, "iterations": iterations, "quick": quick,
              "seed": seed, "scenario": None if scenario is None else scenario.name,
              "scenario_path": None if scenario_path is None else str(scenario_path),
              "rows": rows}
    (out / "reproduce.md").write_text(format_table(result))
    (out / "reproduce.json").write_text(json.dumps({**result, "runs": runs}, indent=2, default=float))
    return result


def format_table(result: dict) -> str:
    head = (f"Reproduction on the {result['plant']} plant, {result['trials']} trial(s) each"
            f"{' (quick: a smoke run, not a result)' if result['quick'] else ''}\n\n")
    lines = ["| experiment | paper | ours | better |", "|---|---|---|---|"]
    for r in result["rows"]:
        fmt = ".4f" if r["unit"] == "N m/rad" else ".2f"
        lines.append(f"| {r['experiment']} [{r['unit']}] | {r['paper_mean']:{fmt}} +- {r['paper_sd']:{fmt}} | "
                     f"{r['ours_mean']:{fmt}} +- {r['ours_sd']:{fmt}} | {'yes' if r['better'] else 'no'} |")
    return head + "\n".join(lines) + "\n"
