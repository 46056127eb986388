"""Does the physics hand hold the paper's objects through random exploratory actions?

For each object: grasp it (:meth:`PhysicsHand.grasp`), then apply ``actions`` random
exploratory actions, uniform in +-``step`` per tendon (DESIGN.md section 6: +-1.5 mm), kept
within ``window`` of the grasp's tendon commands by reflection (a random walk that wanders
off slackens a tendon and drops the object, DESIGN.md section 8) and within the tendon
range. Reports whether the object stayed in hand (all pads in contact and the POM within
``fall_distance`` of the grasp), how far each contact drifted on the object surface (the
contact point expressed in the POM frame O), tensions, settle statistics and wall time per
action (ramp + settle, and render when a camera is used).

    python -m vlr_drake.physics.check                 # 5 objects x 50 actions, with camera
    python -m vlr_drake.physics.check --actions 10 --objects apple --json out.json
    python -m vlr_drake.physics.check --actions 10 --objects apple --html-dir /tmp/html
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vlr_drake.entry import check_output, count, path_text, plain, run
from vlr_drake.hand import hand_by_name
from vlr_drake.identify import Exploration
from vlr_drake.kinematics import is_count, is_number
from vlr_drake.objects import PAPER_OBJECTS, ObjectSpec, preset
from vlr_drake.perception.camera import CameraConfig
from vlr_drake.systems.physics_plant import PhysicsConfig, build_physics_hand

__all__ = ["CheckResult", "exploration_step", "run_check", "main"]


def _check_walk(step, window) -> None:
    """The random walk's ``step`` and ``window`` [m]: finite numbers >= 0, or a ValueError naming them."""
    for name, value in (("step", step), ("window", window)):
        if not (is_number(value) and 0 <= value < np.inf):
            raise ValueError(f"'{name}' must be a finite number >= 0 [m], got {value!r}")


def exploration_step(
    rng: np.random.Generator,
    current: np.ndarray,
    center: np.ndarray,
    step: float,
    window: float,
    tendon_range: np.ndarray,
) -> np.ndarray:
    """A random action dl (uniform in +-step per tendon) such that current + dl stays within
    center +- window and the tendon range, reflecting at the bounds: the identification's
    walk (:class:`vlr_drake.identify.Exploration`) from ``current``. A step or window that
    is negative or not finite is named."""
    _check_walk(step, window)
    explore = Exploration(center, tendon_range, step, window, rng)
    explore.l = np.array(current, float)
    return explore.next_action()


@dataclass
class CheckResult:
    """Outcome of one object's run (numbers in the units their names say)."""

    object: str
    hand: str
    actions: int
    held: bool  # every pad still touches the object and it never moved past fall_distance
    first_loss: int | None  # index (from 0) of the first action after which the object was lost (None: never)
    grasp_held: bool  # the grasp held the object (GraspResult.held; False: lost before any action)
    grasp_settled: bool
    grasp_tension_N: list[float]
    contact_drift_per_action_mm_mean: list[float]  # per finger: mean |dp^O| per action
    contact_drift_per_action_mm_max: list[float]
    contact_drift_total_mm: list[float]  # per finger: |p^O(end) - p^O(grasp)|
    pom_motion_per_action_mm_mean: float
    pom_rotation_per_action_deg_mean: float
    min_tension_N: float
    max_command_violation_m: float  # > 0: the exploration asked for a command past the tendon range (a guard: the
    # walk reflects at the range, so 0 unless it is broken; test_the_check_reports_a_command_asked_past_...)
    settled_fraction: float
    settle_time_s_mean: float
    creep_mm_per_s_max: float  # object speed over the last settle window of an action (max)
    creep_hold_mm_per_s: float  # POM drift rate while holding 0.5 s after the last action
    wall_per_action_s_mean: float  # ramp + settle (+ render)
    wall_physics_s_mean: float
    wall_render_s_mean: float
    wall_grasp_s: float

    def as_dict(self) -> dict:
        return dict(self.__dict__)


def run_check(
    obj: ObjectSpec | str,
    hand_name: str = "model_o",
    actions: int = 50,
    seed: int = 0,
    physics: PhysicsConfig | None = None,
    camera: CameraConfig | None = None,
    step: float = 0.0015,
    window: float = 0.004,
    html: str | None = None,
) -> CheckResult:
    """Grasp ``obj`` with ``hand_name`` and apply ``actions`` random actions (see module doc).
    With ``html``, the run is recorded in Meshcat and saved there as static HTML."""
    if not is_count(actions):  # (2.5 had failed in range() and -1 had given NaN statistics, after the grasp)
        raise ValueError(f"'actions' must be an integer >= 0, got {actions!r}")
    _check_walk(step, window)  # before the plant is built and grasps
    obj = preset(obj) if isinstance(obj, str) else obj
    rng = np.random.default_rng(seed)
    physics = physics or PhysicsConfig()
    meshcat = None
    if html:
        from pydrake.geometry import Meshcat

        meshcat = Meshcat()
    _, ph, sim = build_physics_hand(hand_by_name(hand_name), obj, physics, camera, meshcat)
    root = sim.get_mutable_context()
    if meshcat is not None:
        ph.start_recording()
    g = ph.grasp(sim)
    N = ph.hand.N
    center = g.command.copy()
    rng_T = ph.hand.tendon_range

    def contacts_O(X_PO, contacts):
        X_OP = X_PO.inverse()
        return np.array([X_OP @ c for c in contacts])

    p_O0 = contacts_O(g.X_PO, g.contacts)
    prev_p, prev_X = p_O0, g.X_PO
    drift, pom_dp, pom_dr = [], [], []
    min_T = float(np.min(g.tension))
    violation = 0.0
    settled, t_settle, creep, wall, wall_p, wall_r = [], [], [], [], [], []
    first_loss = None
    for k in range(actions):
        dl = exploration_step(rng, ph.command(root), center, step, window, rng_T)
        # what the exploration asked for, before the plant clamps it into the range (the
        # applied pull, read after, could not leave the range: the test on it could not fail)
        asked = ph.command(root) + dl
        violation = max(violation, float(np.max(np.concatenate([rng_T[:, 0] - asked, asked - rng_T[:, 1]]))))
        r = ph.apply_action(sim, dl, render=camera is not None)
        min_T = min(min_T, float(np.min(r.tension)))
        p = contacts_O(r.X_PO, r.contacts)
        drift.append(np.linalg.norm(p - prev_p, axis=1))
        pom_dp.append(np.linalg.norm(r.X_PO.translation() - prev_X.translation()))
        pom_dr.append((prev_X.rotation().inverse() @ r.X_PO.rotation()).ToAngleAxis().angle())
        prev_p, prev_X = p, r.X_PO
        settled.append(r.settled)
        t_settle.append(r.settle_time)
        creep.append(r.creep_mm_per_s)
        wall_p.append(r.wall_physics_s)
        wall_r.append(r.wall_render_s)
        wall.append(r.wall_physics_s + r.wall_render_s)
        if first_loss is None and ph.object_fell(root):
            first_loss = k
    X_end = ph.output(root, "X_PO_true")
    sim.AdvanceTo(root.get_time() + 0.5)
    creep_hold = float(np.linalg.norm(ph.output(root, "X_PO_true").translation() - X_end.translation())) / 0.5
    if meshcat is not None:
        ph.publish_recording()
        ph.save_html(html)
    drift = np.array(drift).reshape(-1, N)
    total = np.linalg.norm(prev_p - p_O0, axis=1)
    return CheckResult(
        object=obj.name,
        hand=hand_name,
        actions=actions,
        held=g.held and first_loss is None,
        first_loss=first_loss,
        grasp_held=g.held,
        grasp_settled=g.settled,
        grasp_tension_N=[float(x) for x in g.tension],
        contact_drift_per_action_mm_mean=[float(x) for x in 1e3 * drift.mean(axis=0)]
        if actions
        else [0.0] * N,
        contact_drift_per_action_mm_max=[float(x) for x in 1e3 * drift.max(axis=0)] if actions else [0.0] * N,
        contact_drift_total_mm=[float(x) for x in 1e3 * total],
        pom_motion_per_action_mm_mean=float(1e3 * np.mean(pom_dp)) if actions else 0.0,
        pom_rotation_per_action_deg_mean=float(np.rad2deg(np.mean(pom_dr))) if actions else 0.0,
        min_tension_N=min_T,
        max_command_violation_m=violation,
        settled_fraction=float(np.mean(settled)) if actions else 1.0,
        settle_time_s_mean=float(np.mean(t_settle)) if actions else 0.0,
        creep_mm_per_s_max=float(np.max(creep)) if actions else 0.0,
        creep_hold_mm_per_s=1e3 * creep_hold,
        wall_per_action_s_mean=float(np.mean(wall)) if actions else 0.0,
        wall_physics_s_mean=float(np.mean(wall_p)) if actions else 0.0,
        wall_render_s_mean=float(np.mean(wall_r)) if actions else 0.0,
        wall_grasp_s=g.wall_s,
    )


def main(argv: list[str] | None = None) -> list[CheckResult]:
    ap = argparse.ArgumentParser(prog="python -m vlr_drake.physics.check", description=plain(__doc__),
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--objects", nargs="+", action="extend", default=None,
                    help="object presets (given twice, both lists run; default: the paper's "
                         f"{', '.join(PAPER_OBJECTS)})")
    ap.add_argument("--hand", default="model_o", help="model_o, NH1, NH2 or NH3")
    ap.add_argument("--actions", type=count(1), default=50, help="random actions per object (default 50)")
    ap.add_argument("--seed", type=count(0), default=0, help="seed of the random actions (default 0)")
    ap.add_argument("--no-camera", action="store_true", help="skip rendering")
    ap.add_argument("--time-step", type=float, default=None, help="plant time step [s]")
    ap.add_argument("--pretension-mode", default=None, help="auto, thumb_factor or balanced (default: auto)")
    ap.add_argument(
        "--html-dir", default=None, help="save a Meshcat recording per object here (<object>.html)"
    )
    ap.add_argument("--json", type=path_text, default=None, help="write the results here")
    args = ap.parse_args(argv)
    args.objects = args.objects or list(PAPER_OBJECTS)  # (a default list would be extended, not replaced)
    check_output("--json", args.json)
    check_output("--html-dir", args.html_dir, folder=True)
    physics = PhysicsConfig()
    if args.time_step is not None:  # (0 and NaN are refused by the validation, not read as "default")
        physics.time_step = args.time_step
    if args.pretension_mode:
        physics.pretension_mode = args.pretension_mode
    try:
        physics.validate()
    except ValueError as e:
        ap.error(str(e))
    hand_by_name(args.hand)  # every name before the first run, not a typo in the last one after minutes
    for name in args.objects:
        preset(name)
    camera = None if args.no_camera else CameraConfig()
    results = []
    t0 = time.perf_counter()
    for name in args.objects:
        html = None
        if args.html_dir:
            Path(args.html_dir).mkdir(parents=True, exist_ok=True)
            html = str(Path(args.html_dir) / f"{name}.html")
        r = run_check(name, args.hand, args.actions, args.seed, physics, camera, html=html)
        results.append(r)
        print(
            f"{r.object:17s} held={r.held!s:5s} drift/action [mm] mean {np.round(r.contact_drift_per_action_mm_mean, 2)} "
            f"max {np.round(r.contact_drift_per_action_mm_max, 2)} total {np.round(r.contact_drift_total_mm, 1)} | "
            f"POM {r.pom_motion_per_action_mm_mean:.2f} mm {r.pom_rotation_per_action_deg_mean:.2f} deg/action | "
            f"T_min {r.min_tension_N:.1f} N | settled {100 * r.settled_fraction:.0f}% "
            f"({r.settle_time_s_mean:.2f} s) hold creep {r.creep_hold_mm_per_s:.3f} mm/s | wall/action "
            f"{r.wall_per_action_s_mean:.3f} s (physics {r.wall_physics_s_mean:.3f}, render {r.wall_render_s_mean:.3f})"
        )
    print(f"total wall {time.perf_counter() - t0:.1f} s")
    if args.json:
        out = {
            "hand": args.hand,
            "actions": args.actions,
            "seed": args.seed,
            "physics": dict(physics.__dict__),
            "camera": bool(camera),
            "results": [r.as_dict() for r in results],
        }
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        with open(args.json, "w") as f:
            json.dump(out, f, indent=2)
    return results


if __name__ == "__main__":
    raise SystemExit(run("python -m vlr_drake.physics.check", main))
