"""Marble maze (the paper's Fig. 6B): tilt a maze plate so a marble rolls to the goal.

The grasped object is a maze plate whose frame is the POM frame O (plate in the O x-y
plane, normal z_O). Orientation control only: a precomputed sequence of plate orientations
(one per straight run of the maze path) is tracked by :func:`vlr_drake.control.servo_to`
with ``rows="orientation"``, one control action per control period; the marble is
simulated by :class:`MarbleMaze` in between.

Axes. The grasp can tilt the plate about the strongest rotation direction k of the
controller's Jacobian (Eq. 10) at the grasp; for the Model O, whose fingers flex in
parallel planes, that is the only rotation it can make (the palm's y axis). Tilting by phi
about k (in the plate frame) adds the in-plane gravity phi g (k x z_O): the *steering*
axis s = k x z_O. The arm holds the plate with a small constant bias tilt beta so that
gravity also pulls along the *fall* axis f = z_O x s. The maze's columns run along s and
its rows along f, so the path is a switchback: horizontal runs steered by +-phi, and
one-cell drops through gaps, during which the plate is tilted by half the previous run's
tilt to hold the marble in the corner above the gap.

:class:`MarbleMaze` is a small rolling-ball simulator: a solid sphere rolling without
slipping on a tilted plane accelerates at (5/7) of the in-plane gravity, with viscous
rolling resistance ``damping`` [1/s]; walls on the cell grid stop it with restitution
``restitution``; semi-implicit Euler with 1 ms steps. The layout is ASCII art (``MAZE``).
On the physics plant (``plant="physics"``, the ``marble_maze`` preset) the plate is the
Drake body, tilted by the physics hand and measured by the rendered camera; the marble is
still this simulator, driven by the true plate orientation (the preset's Drake model has
no marble body; its ``marble_radius`` is this marble's).
"""

from __future__ import annotations

import os
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from vlr_drake import control, observation
from vlr_drake.entry import interrupt_asked, stop_between_steps
from vlr_drake.kinematics import is_number
from vlr_drake.objects import preset
from vlr_drake.tasks import common

__all__ = ["MAZE", "MarbleMaze", "parse_maze", "maze_path", "orientation_sequence", "run_maze"]

#: The default maze (row 0 at the top; rows fall along f, columns along s). S start, G goal.
MAZE = """
+--+--+--+--+
|S       |  |
+--+--+  +--+
|        |  |
+  +--+--+--+
|           |
+--+--+--+  +
|  |  |  | G|
+--+--+--+--+
"""

GRAVITY = 9.81
#: The largest plate tilt and bias [deg]: the Model O's fingertip grasp turns its object by
#: about 10 deg before its fold (the cup-stacking task's tilts, vlr_drake.tasks.stack).
MAX_TILT_DEG = 10.0


def parse_maze(text: str) -> dict:
    """Walls of an ASCII maze: ``right[r, c]`` (wall between (r, c) and (r, c+1)) and
    ``down[r, c]`` (wall between (r, c) and (r+1, c)), the outer border closed; start and
    goal cells."""
    lines = [ln for ln in text.strip("\n").splitlines() if ln.strip()]
    rows = (len(lines) - 1) // 2
    cols = (len(lines[0].rstrip()) - 1) // 3 if lines else 0  # (no line: an IndexError before)
    if rows < 1 or cols < 1:
        raise ValueError("maze text must have at least one cell")
    lines = [ln.ljust(3 * cols + 1) for ln in lines]
    right = np.ones((rows, cols), bool)
    down = np.ones((rows, cols), bool)
    start = goal = None
    for r in range(rows):
        for c in range(cols):
            cell = lines[2 * r + 1][3 * c + 1 : 3 * c + 3]
            if "S" in cell:
                start = (r, c)
            if "G" in cell:
                goal = (r, c)
            if c < cols - 1:
                right[r, c] = lines[2 * r + 1][3 * c + 3] == "|"
            if r < rows - 1:
                down[r, c] = lines[2 * r + 2][3 * c + 1] == "-"
    if start is None or goal is None:
        raise ValueError("maze text must mark a start 'S' and a goal 'G'")
    if start == goal:  # (it had scored a success of no control step and no sample)
        raise ValueError(f"maze text: the start 'S' and the goal 'G' are the same cell {start}")
    return {"rows": rows, "cols": cols, "right": right, "down": down, "start": start, "goal": goal}


def _neighbours(maze: dict, r: int, c: int):
    if c + 1 < maze["cols"] and not maze["right"][r, c]:
        yield r, c + 1
    if c > 0 and not maze["right"][r, c - 1]:
        yield r, c - 1
    if r + 1 < maze["rows"] and not maze["down"][r, c]:
        yield r + 1, c
    if r > 0 and not maze["down"][r - 1, c]:
        yield r - 1, c


def maze_path(maze: dict) -> list[tuple[int, int]]:
    """Cells from start to goal (breadth-first search); ValueError if there is none."""
    prev = {maze["start"]: None}
    q = deque([maze["start"]])
    while q:
        cell = q.popleft()
        if cell == maze["goal"]:
            break
        for nb in _neighbours(maze, *cell):
            if nb not in prev:
                prev[nb] = cell
                q.append(nb)
    if maze["goal"] not in prev:
        raise ValueError("maze has no path from start to goal")
    path, cell = [], maze["goal"]
    while cell is not None:
        path.append(cell)
        cell = prev[cell]
    return path[::-1]


def orientation_sequence(path: list[tuple[int, int]], tilt: float) -> list[dict]:
    """Runs of the path with their steering tilt [rad] about k: horizontal runs +-tilt,
    drops (one row down) half the previous run's tilt. Raises for a path that climbs."""
    runs = []
    k = 0
    last = 0.0
    while k < len(path) - 1:
        dr, dc = path[k + 1][0] - path[k][0], path[k + 1][1] - path[k][1]
        if dr < 0:
            raise ValueError("the maze path climbs against the fall axis; design it as a switchback")
        j = k
        while j < len(path) - 1 and (path[j + 1][0] - path[j][0], path[j + 1][1] - path[j][1]) == (dr, dc):
            j += 1
        if dc != 0:
            phi = np.sign(dc) * tilt
            last = phi
        else:
            phi = 0.5 * last
        runs.append(
            {"cells": path[k : j + 1], "end": path[j], "tilt": float(phi), "kind": "drop" if dr else "run"}
        )
        k = j
    return runs


@dataclass
class MarbleMaze:
    """A marble rolling on the maze plate (plate coordinates (s, f) [m], origin at the
    outer corner of cell (0, 0))."""

    maze: dict
    cell: float = 0.025  # cell size [m]
    # marble radius [m]: the marble_maze preset's (vlr_drake.objects)
    radius: float = field(default_factory=lambda: preset("marble_maze").marble_radius)
    damping: float = 3.0  # viscous rolling resistance [1/s] (felt-lined plate: slow marble)
    restitution: float = 0.3  # wall bounce
    dt: float = 1e-3  # integration step [s]

    def __post_init__(self):
        # (a restitution of 3 had bounced the marble to 1e251 m/s, a zero or NaN step failed
        # in the step count's division or int(); a review)
        for name, value, lo, hi, unit in (("cell", self.cell, 0.0, np.inf, "m"), ("dt", self.dt, 0.0, np.inf, "s")):
            if not (is_number(value) and lo < value < hi):
                raise ValueError(f"marble maze: '{name}' must be a positive finite number [{unit}], got {value!r}")
        if not (is_number(self.damping) and 0 <= self.damping < np.inf):
            raise ValueError(f"marble maze: 'damping' must be a finite number >= 0 [1/s], got {self.damping!r}")
        if not (is_number(self.restitution) and 0 <= self.restitution <= 1):
            raise ValueError(f"marble maze: 'restitution' must be in [0, 1], got {self.restitution!r}")
        if not 0 < self.radius < 0.5 * self.cell:
            raise ValueError(f"marble radius must be in (0, cell/2), got {self.radius}")
        r, c = self.maze["start"]
        self.pos = np.array([(c + 0.5) * self.cell, (r + 0.5) * self.cell])
        self.vel = np.zeros(2)

    def cell_of(self) -> tuple[int, int]:
        c = int(np.clip(self.pos[0] // self.cell, 0, self.maze["cols"] - 1))
        r = int(np.clip(self.pos[1] // self.cell, 0, self.maze["rows"] - 1))
        return r, c

    def _wall(self, r: int, c: int, axis: int, sign: int) -> bool:
        m = self.maze
        if axis == 0:
            cc = c if sign > 0 else c - 1
            return cc < 0 or cc >= m["cols"] - 1 or bool(m["right"][r, cc])
        rr = r if sign > 0 else r - 1
        return rr < 0 or rr >= m["rows"] - 1 or bool(m["down"][r if sign > 0 else rr, c])

    def step(self, g_plate: np.ndarray, duration: float) -> None:
        """Advance by ``duration`` [s] under gravity ``g_plate`` (3,) in the plate frame
        expressed along (s, f, normal)."""
        if not (is_number(duration) and 0 <= duration < np.inf):
            raise ValueError(f"marble maze: 'duration' must be a finite number >= 0 [s], got {duration!r}")
        acc = (5.0 / 7.0) * np.asarray(g_plate, float)[:2]
        # substeps of at most dt that add up to the duration (round(duration / dt) steps of dt
        # had simulated 1 ms for a 0.4 ms period and 2 ms for 2.5 ms; a review)
        n = max(1, int(np.ceil(duration / self.dt - 1e-9)))
        h = duration / n
        for _ in range(n):
            self.vel += h * (acc - self.damping * self.vel)
            for axis in (0, 1):
                r, c = self.cell_of()
                new = self.pos[axis] + h * self.vel[axis]
                idx = c if axis == 0 else r
                lo, hi = idx * self.cell + self.radius, (idx + 1) * self.cell - self.radius
                if new > hi and self._wall(r, c, axis, +1):
                    new, self.vel[axis] = hi, -self.restitution * self.vel[axis]
                elif new < lo and self._wall(r, c, axis, -1):
                    new, self.vel[axis] = lo, -self.restitution * self.vel[axis]
                self.pos[axis] = new


def run_maze(
    *,
    seed: int = 0,
    plant: str = "model",
    model: str = "true",
    maze_text: str = MAZE,
    tilt_deg: float = 3.0,
    bias_deg: float = 1.5,
    period: float = 0.2,
    segment_time: float = 12.0,
    tol_rotation_deg: float = 0.5,
    sigma_position: float = 0.2e-3,
    sigma_rotation_deg: float = 0.5,
    dropout: float = 0.0,
    particles: int = 3000,
    identify_iterations: int = 40,
    out: str | None = None,
    progress: bool = True,
    scenario: str = "default",
    scenario_path: str | None = None,
    window: float = common.TASK_EXPLORATION[1],
    action_range: float | None = None,
    physics=None,
    camera=None,
    meshcat=None,
) -> dict:
    """Steer the marble through the maze; returns the task result dict (DESIGN.md 11).

    One control period (``period`` [s] of marble time) = at most one control action.
    Orientation errors are those of the true plate orientation against the current goal,
    sampled every period once the servo has settled on that goal (reached its tolerance
    or stopped; the last sample of a goal that the marble left earlier); a run whose marble has not left it after ``segment_time`` [s] fails.
    Plots (``out``): ``maze.png`` (orientation error over time; marble path in the maze).

    Scenario settings: ``action_range`` and ``window`` [m] bound the identification's random
    actions (None: the plant's default, see :func:`vlr_drake.tasks.common.make_model_fn`;
    ``window`` also the control's grip window), ``physics`` and ``camera`` configure
    the physics plant (None: defaults), ``scenario`` and ``scenario_path`` are recorded.
    ``meshcat``: a Meshcat instance that shows the goal plate orientation beside the plate's
    true pose per action (:class:`vlr_drake.visualization.TaskView`); the recording is saved as
    ``maze.html`` in ``out``.
    """
    common.check_plant(plant)
    common.check_positive(period=period, segment_time=segment_time, tol_rotation_deg=tol_rotation_deg, window=window)
    # the plate's steering tilt and its constant bias towards the fall axis: angles the grasp
    # can turn (a negative tilt steered the wrong way, 363 deg wrapped round and 30 deg was
    # "solved" 17 deg off its goals; a review)
    if not (is_number(tilt_deg) and 0 < tilt_deg <= MAX_TILT_DEG):
        raise ValueError(f"'tilt_deg' must be in (0, {MAX_TILT_DEG:g}] deg, got {tilt_deg!r}")
    if not (is_number(bias_deg) and 0 <= bias_deg <= MAX_TILT_DEG):
        raise ValueError(f"'bias_deg' must be in [0, {MAX_TILT_DEG:g}] deg, got {bias_deg!r}")
    from tqdm.auto import tqdm

    mz = parse_maze(maze_text)
    cells = maze_path(mz)
    order = {cell: i for i, cell in enumerate(cells)}
    runs = orientation_sequence(cells, np.deg2rad(tilt_deg))
    tp = common.task_plant(plant, seed, "marble_maze", physics, camera, sigma_position=sigma_position,
                           sigma_rotation_deg=sigma_rotation_deg, dropout=dropout)
    model_fn, filt = common.make_model_fn(
        model, tp, seed=seed, particles=particles, identify_iterations=identify_iterations,
        action_range=action_range, window=window,
    )
    view = common.task_view(meshcat)
    pl = common.followed(view, tp)
    _, _, _, J = common.start_model(pl, model_fn, tp.hand, "maze", seed)
    R_PO0 = tp.true_pose()[0]  # the plate's level orientation (arm's frame of reference)
    limits = common.grip_window(tp.hand, tp.tendon_command(), window)
    U, S, _ = np.linalg.svd(J[3:])
    k_P = U[:, 0]
    k = R_PO0.T @ k_P  # tilt axis in the plate frame
    z = np.array([0.0, 0.0, 1.0])
    s_ax = np.cross(k, z)
    if np.linalg.norm(s_ax) < 0.3:
        raise common.TaskSetupError(f"maze, seed {seed}: the grasp cannot tilt the plate (its rotation axis is "
                                    f"the plate normal); try another seed")
    s_ax /= np.linalg.norm(s_ax)
    f_ax = np.cross(z, s_ax)
    k = f_ax  # the in-plane part of the tilt axis: tilting by phi about it steers along s
    beta = np.deg2rad(bias_deg)
    g_M0 = GRAVITY * (-np.cos(beta) * z + np.sin(beta) * f_ax)
    g_P = R_PO0 @ g_M0
    marble = MarbleMaze(mz)

    def g_plate():
        g = tp.true_pose()[0].T @ g_P
        return np.array([g @ s_ax, g @ f_ax, g @ z])

    times, errs, settled_err, track = [], [], [], [marble.pos.copy()]
    switch_times = []
    time_s = 0.0
    success = True
    bar = tqdm(total=len(runs), disable=not progress, desc="maze", unit="run", leave=False)
    iterations = lost = 0
    rep = None  # the last servo call's report: one step per call, so a lost tag's predicted pose carries on
    stopped = None
    skipped_runs = 0
    with stop_between_steps("the maze"):  # a Ctrl-C: the steps done are scored and written
        for run in runs:
            R_goal = R_PO0 @ observation.rotvec_to_matrix(run["tilt"] * k)[0]
            if view is not None:
                view.target_pose(R_goal, tp.true_pose()[1])
            switch_times.append(time_s)
            t_run = 0.0
            settled = False
            run_samples = 0
            run_steps = 0
            while order.get(marble.cell_of(), -1) < order[run["end"]]:  # the marble may run ahead
                if interrupt_asked():
                    success, stopped = False, f"interrupted ({interrupt_asked()})"
                    break
                if t_run > segment_time or common.object_fell(tp):
                    success, stopped = False, "object_fell" if common.object_fell(tp) else "timeout"
                    break
                rep = control.servo_to(
                    R_goal,
                    np.zeros(3),
                    pl,
                    model_fn,
                    rows="orientation",
                    max_steps=1,
                    tol_rotation=np.deg2rad(tol_rotation_deg),
                    stall_steps=100,
                    limits=limits,
                    resume=rep,
                )
                iterations += rep.iterations
                lost += rep.lost
                if rep.reason == "lost_tag":  # the camera lost the plate for good: nothing to steer by
                    success, stopped = False, "lost_tag"
                    break
                if common.object_fell(tp):  # the plate fell during this step: its pose is no sample (a
                    success, stopped = False, "object_fell"  # fallen plate had been scored, 90 deg off)
                    break
                settled = settled or rep.reached or rep.reason != "budget"
                marble.step(g_plate(), period)
                time_s += period
                t_run += period
                run_steps += 1
                err = np.rad2deg(observation.rotation_angle(R_goal[None], tp.true_pose()[0][None])[0])
                times.append(time_s)
                errs.append(err)
                track.append(marble.pos.copy())
                if settled:
                    settled_err.append(err)
                    run_samples += 1
            if run_samples == 0 and run_steps > 0:  # the marble left before the servo settled: score its last sample
                settled_err.append(errs[-1])
            elif run_steps == 0 and success:  # the marble had passed this run's goal already: nothing to score
                # (a run stopped before its first step, e.g. by a fall during identification, is not one)
                skipped_runs += 1
            bar.update(1)
            if not success:
                break
    bar.close()
    reached = success and marble.cell_of() == mz["goal"]
    result = {
        "task": "maze",
        "scenario": scenario,
        "scenario_path": scenario_path,
        "seed": seed,
        "plant": plant,
        "model": model,
        **common.model_settings(model, particles, identify_iterations),
        "position_error_mm": None,
        "orientation_error_deg": common.stats(np.deg2rad(settled_err), np.rad2deg(1.0)),
        "success": bool(reached),
        "marble_reached_goal": bool(reached),
        "object_fell": common.object_fell(tp),
        "marble_cell": list(marble.cell_of()),
        "time_s": time_s,
        "control_iterations": int(iterations),
        "lost_measurements": int(lost),
        "stopped": stopped,  # why the run ended early: "timeout", "object_fell" or "lost_tag"; null if it did not
        "runs": len(runs),
        "skipped_runs": int(skipped_runs),  # runs the marble had passed before their goal was set (unscored)
        "tilt_deg": tilt_deg,
        "orientation_error_all_deg": common.stats(np.deg2rad(errs), np.rad2deg(1.0)),
        "tilt_axis_palm": k_P.tolist(),
        "paper_orientation_error_deg": {"mean": 1.20, "sd": 1.38},
    }
    if filt is not None:
        result["filter_iterations"] = int(filt.iteration)
    if out is not None:
        os.makedirs(out, exist_ok=True)
        result["plots"] = [
            _plot(mz, marble, np.array(track), times, errs, switch_times, os.path.join(out, common.PLOT_FILES["maze"]))
        ]
    common.save_view(view, out, "maze", result)
    return result


def _plot(mz, marble, track, times, errs, switch_times, path: str) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 4))
    a1.plot(times, errs, "-", color="C0")
    for t in switch_times:
        a1.axvline(t, color="0.8", lw=0.8)
    a1.set_xlabel("time [s]")
    a1.set_ylabel("orientation error [deg]")
    a1.set_title("plate orientation error (grey: new goal)")
    c = marble.cell * 1e3
    for r in range(mz["rows"]):
        for col in range(mz["cols"]):
            x0, y0 = col * c, r * c
            if mz["right"][r, col]:
                a2.plot([x0 + c, x0 + c], [y0, y0 + c], "k-", lw=2)
            if mz["down"][r, col]:
                a2.plot([x0, x0 + c], [y0 + c, y0 + c], "k-", lw=2)
            if col == 0:
                a2.plot([x0, x0], [y0, y0 + c], "k-", lw=2)
            if r == 0:
                a2.plot([x0, x0 + c], [y0, y0], "k-", lw=2)
    a2.plot(track[:, 0] * 1e3, track[:, 1] * 1e3, ".-", color="C3", ms=2, label="marble")
    for name, (r, col) in (("S", mz["start"]), ("G", mz["goal"])):
        a2.text((col + 0.5) * c, (r + 0.5) * c, name, ha="center", va="center", fontsize=12, color="C2")
    a2.invert_yaxis()
    a2.set_aspect("equal")
    a2.set_xlabel("steering axis s [mm]")
    a2.set_ylabel("fall axis f [mm]")
    a2.set_title("marble path")
    fig.tight_layout()
    common.save_figure(fig, path)
    plt.close(fig)
    return path
