"""Benchmarks that print their figures (never timed tests): ``vlr-drake bench motion``,
``vlr-drake bench rolling`` and ``vlr-drake bench filter``.

The motion benchmark measures, in one run, one batched move of ``particles`` Model O
hypotheses (numba Newton, DESIGN.md section 4) and single MathematicalProgram solves of
the same problem with IPOPT and with SNOPT (those that succeed; the failures counted), and
reports the per-particle speed-up. The rolling benchmark does the same for the rolling
model's move (:func:`vlr_drake.motion_rolling.move_rolling` against
:func:`vlr_drake.rolling_reference.solve_rolling`, IPOPT), with the pinned move of the same
hypotheses beside it. The filter benchmark times full filter iterations and a
physics-plant identification. Field names follow docs/result-files.md.
"""

from __future__ import annotations

import time
import warnings

import numpy as np

from vlr_drake import grasps, motion
from vlr_drake import motion_reference as ref
from vlr_drake.hand import hand_by_name


def _check_counts(what: str, **counts) -> None:
    """A ValueError naming the first argument that is not an integer >= its minimum
    (``name=(value, minimum)``)."""
    for name, (value, least) in counts.items():
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
            raise ValueError(f"bench {what}: '{name}' must be an integer >= {least}, got {value!r}")


def bench_motion(particles: int = 60_000, seed: int = 0, hand: str = "model_o", repeats: int = 5,
                 reference_solves: int = 30, tendon: str = "elastic") -> dict:
    """Time one batched move of ``particles`` hypotheses and single reference solves.

    A reference solve is one MathematicalProgram (IPOPT or SNOPT) of one hypothesis' move,
    timed as a caller pays it: building the program and solving it (``*_solve_s``, the
    speed-ups' figure), with the solver's own time beside it (``*_solver_time_s``). Medians
    over the solves that succeeded; how many failed (the reference stops where the move
    leaves its local search box, which the batched Newton's continuation does not) is
    reported, and a solver with no success is an error."""
    _check_counts("motion", particles=(particles, 1), repeats=(repeats, 1), reference_solves=(reference_solves, 1))
    h = hand_by_name(hand).model()
    rng = np.random.default_rng(seed)
    base = grasps.sample_grasps(h, rng, min(particles, 2000))
    idx = rng.integers(0, len(base.theta), particles)
    theta, a, s, D2 = base.theta[idx], base.a[idx], base.stretch[idx], base.D2[idx]
    dl = rng.uniform(-1.5e-3, 1.5e-3, h.N)
    motion.move(h, theta[:10], dl, a=a[:10], D2=D2[:10], stretch=s[:10], tendon=tendon)  # compile
    times = {tol: [] for tol in motion.TOLERANCES}
    for _ in range(repeats):  # interleaved, so that both see the same machine load
        for tol in motion.TOLERANCES:
            t0 = time.perf_counter()
            res = motion.move(h, theta, dl, a=a, D2=D2, stretch=s, tendon=tendon, tolerance=tol)
            times[tol].append(time.perf_counter() - t0)
            if tol == "tight":
                res_tight = res
    batched = float(np.median(times["tight"]))
    batched_filter = float(np.median(times["filter"]))
    res = res_tight
    solve_times, solver_times, failures = {}, {}, {}
    n_ref = min(reference_solves, particles)
    for solver in ref.SOLVERS:
        ts, own = [], []
        failures[solver] = 0
        for p in range(n_ref):
            t0 = time.perf_counter()
            try:
                r = ref.solve_move(h, theta[p], dl, a=a[p], D2=D2[p], stretch=s[p], tendon=tendon, solver=solver)
            except ref.MotionSolveError:
                failures[solver] += 1
                continue
            ts.append(time.perf_counter() - t0)
            own.append(r.solve_time_s)
        if not ts:
            raise RuntimeError(f"bench motion: every one of the {n_ref} {solver} reference solves failed (seed "
                               f"{seed}); try another --seed")
        solve_times[solver], solver_times[solver] = float(np.median(ts)), float(np.median(own))
    return {
        "benchmark": "motion",
        "hand": hand,
        "tendon": tendon,
        "particles": particles,
        "batched_move_s": batched,
        # with motion.TOLERANCES["filter"] (FilterConfig.newton_tolerance = "filter")
        "batched_move_filter_tolerance_s": batched_filter,
        "batched_success_fraction": float(res.ok.mean()),
        "median_newton_iterations": float(np.median(res.iterations)),
        # one reference solve that succeeded, median: building the program and solving it
        "ipopt_solve_s": solve_times["ipopt"],
        "snopt_solve_s": solve_times["snopt"],
        # ... the solver's own part of it
        "ipopt_solver_time_s": solver_times["ipopt"],
        "snopt_solver_time_s": solver_times["snopt"],
        # how many of the reference solves were tried, and how many of them failed
        "reference_solves": n_ref,
        "ipopt_failures": failures["ipopt"],
        "snopt_failures": failures["snopt"],
        # the same hypotheses' batched success (the first reference_solves of the move)
        "batched_success_reference_particles": int(res.ok[:n_ref].sum()),
        "speedup_per_particle": solve_times["ipopt"] / (batched / particles),
        "speedup_per_particle_snopt": solve_times["snopt"] / (batched / particles),
        "speedup_per_particle_filter_tolerance": solve_times["ipopt"] / (batched_filter / particles),
        "threads": _threads(),
    }


#: ``bench_rolling`` keeps the drawn grasps that settle under their object's weight within this
#: [rad] of where they were drawn (larger settles are grasps the weight pulls apart).
SETTLE_RAD = 0.1
#: A reference solve that moves a joint further than this [rad] on a 0.5 mm action (such an
#: action moves one by a few hundredths) found another stationary point: IPOPT has no local
#: search box on the rolling problem, and about one solve in five goes 0.3-4 rad away.
WANDER_RAD = 0.2


def bench_rolling(particles: int = 20_000, seed: int = 0, repeats: int = 3, reference_solves: int = 20) -> dict:
    """Time one batched rolling move (:func:`vlr_drake.motion_rolling.move_rolling`, the
    filter's Gamma with ``motion_model = "rolling"``) of ``particles`` Model O hypotheses
    and single MathematicalProgram solves of the same problem (IPOPT,
    :func:`vlr_drake.rolling_reference.solve_rolling`, building and solving), and the pinned
    move (Eq. 9, :func:`vlr_drake.motion.move`) of the same grasps. The hypotheses are
    physical grasps (:func:`vlr_drake.grasps.sample_grasps`) holding an object that weighs
    10-60 g (uniform), palm up, its centre of mass drawn around the contacts' centroid (3 mm
    SD per axis: within 1 cm for 99% of them) and its normals at the contacts within about
    10 deg of :func:`motion_rolling.guessed_normals`, each settled at its rolling equilibrium under that
    weight before the timed action (+-0.5 mm per tendon, the exploration's).
    Medians; the reference's failures are counted, and the solutions that both found are
    compared (``max_angle_difference_rad``)."""
    from vlr_drake import kinematics, motion_rolling
    from vlr_drake import rolling_reference as rref

    _check_counts("rolling", particles=(particles, 1), repeats=(repeats, 1), reference_solves=(reference_solves, 1))
    h = hand_by_name("model_o").model()
    rng = np.random.default_rng(seed)
    base = grasps.sample_grasps(h, rng, min(particles, 2000))
    idx = rng.integers(0, len(base.theta), particles)
    theta, a, s = base.theta[idx], base.a[idx], base.stretch[idx]
    p = kinematics.contacts(h, theta, a)
    normals = motion_rolling.guessed_normals(h, p) + rng.normal(0.0, 0.05, (particles, h.N, 3))
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    R, t = np.broadcast_to(np.eye(3), (particles, 3, 3)), p.mean(axis=1)
    mass = rng.uniform(0.01, 0.06, particles)
    com = t + rng.normal(0.0, 0.003, (particles, 3))
    g = np.array([0.0, 0.0, -9.81])
    # each hypothesis settles under its object's weight first (the filter's hypotheses sit at
    # rolling equilibria before each action); those that find none are redrawn from the rest
    rest = motion_rolling.move_rolling(h, theta, a, R, t, normals, s, gravity=g, object_mass=mass, com=com)
    held = rest.ok & (np.abs(rest.theta - theta).max(axis=(1, 2)) < SETTLE_RAD) & h.within_joint_limits(rest.theta)
    if not held.any():
        raise RuntimeError(f"bench rolling: no drawn grasp holds its object (seed {seed}); try another --seed")
    keep = rng.choice(np.flatnonzero(held), particles)
    dR = np.einsum("pij,pkj->pik", rest.R, R)[keep]  # the settling turn R' R^T
    theta, a, s = rest.theta[keep], a[keep], rest.stretch[keep]
    normals = np.einsum("pij,pnj->pni", dR, normals[keep])
    com = np.einsum("pij,pj->pi", dR, com[keep] - t[keep]) + rest.t[keep]
    R, t, mass = rest.R[keep], rest.t[keep], mass[keep]
    D2 = motion.contact_distances_sq(h, kinematics.contacts(h, theta, a))
    dl = rng.uniform(-0.5e-3, 0.5e-3, h.N)

    def rolling(n=particles):
        return motion_rolling.move_rolling(h, theta[:n], a[:n], R[:n], t[:n], normals[:n], s[:n], dl=dl, gravity=g,
                                           object_mass=mass[:n], com=com[:n])

    rolling(10)  # compile
    motion.move(h, theta[:10], dl, a=a[:10], D2=D2[:10], stretch=s[:10])
    t_roll, t_pin = [], []
    for _ in range(repeats):  # interleaved, so that both see the same machine load
        t0 = time.perf_counter()
        res = rolling()
        t_roll.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        motion.move(h, theta, dl, a=a, D2=D2, stretch=s, tolerance="filter")
        t_pin.append(time.perf_counter() - t0)
    n_ref = min(reference_solves, particles)
    ts, failures, wandered, diffs = [], 0, 0, []
    for q in range(n_ref):
        state = rref.RollingState(theta[q], a[q], R[q], t[q], normals[q], s[q], float(mass[q]), com[q])
        t0 = time.perf_counter()
        try:
            r = rref.solve_rolling(h, state, dl, gravity=g)
        except rref.RollingSolveError:
            failures += 1
            continue
        ts.append(time.perf_counter() - t0)
        if np.abs(r.theta - theta[q]).max() > WANDER_RAD:
            wandered += 1
        elif res.ok[q]:
            diffs.append(float(np.abs(r.theta - res.theta[q]).max()))
    if not ts:
        raise RuntimeError(f"bench rolling: every one of the {n_ref} reference solves failed (seed {seed}); "
                           "try another --seed")
    batched = float(np.median(t_roll))
    return {
        "benchmark": "rolling",
        "hand": "model_o",
        "particles": particles,
        "batched_move_s": batched,
        "batched_success_fraction": float(res.ok.mean()),
        "newton_iterations_max": int(res.iterations),
        # the pinned move (Eq. 9, the filter's default Gamma, "filter" tolerance) of the same grasps
        "pinned_move_s": float(np.median(t_pin)),
        "ipopt_solve_s": float(np.median(ts)),
        "reference_solves": n_ref,
        "ipopt_failures": failures,
        # IPOPT's solutions that moved a joint more than WANDER_RAD (another stationary point)
        "reference_wandered": wandered,
        # of the other reference solves that the batched move solved too: how many agree to
        # 1e-6 rad, and the largest joint-angle difference
        "max_angle_difference_rad": max(diffs, default=float("nan")),
        "reference_agreements": int(np.sum(np.asarray(diffs) < 1e-6)),
        "reference_compared": len(diffs),
        "speedup_per_particle": float(np.median(ts)) / (batched / particles),
        "threads": _threads(),
    }


def format_rolling(r: dict) -> str:
    return (
        f"batched rolling move of {r['particles']} particles ({r['hand']}, {r['threads']} threads): "
        f"{r['batched_move_s'] * 1e3:.1f} ms ({r['batched_success_fraction'] * 100:.1f}% converged, at most "
        f"{r['newton_iterations_max']} Newton iterations); the pinned move (Eq. 9) of the same grasps "
        f"{r['pinned_move_s'] * 1e3:.1f} ms ({r['batched_move_s'] / r['pinned_move_s']:.1f}x)\n"
        f"MathematicalProgram (IPOPT), one rolling solve (building and solving), median of those that succeeded: "
        f"{r['ipopt_solve_s'] * 1e3:.2f} ms; failed {r['ipopt_failures']} of {r['reference_solves']}, wandered off "
        f"(a joint moved over {WANDER_RAD} rad) {r['reference_wandered']}; the same angles "
        f"(1e-6 rad) as the batched move in {r['reference_agreements']} of {r['reference_compared']} (largest "
        f"difference {r['max_angle_difference_rad']:.1e} rad)\n"
        f"speed-up per particle: {r['speedup_per_particle']:.0f}x vs IPOPT"
    )


def _threads() -> int:
    import numba

    return int(numba.get_num_threads())


def format_motion(r: dict) -> str:
    return (
        f"batched move of {r['particles']} particles ({r['hand']}, {r['tendon']} tendon, {r['threads']} threads): "
        f"{r['batched_move_s'] * 1e3:.1f} ms  ({r['batched_success_fraction'] * 100:.1f}% converged, "
        f"median {r['median_newton_iterations']:.0f} Newton iterations); with the \"filter\" tolerance "
        f"{r['batched_move_filter_tolerance_s'] * 1e3:.1f} ms\n"
        f"MathematicalProgram, one solve (building and solving; the solver's own part), median of those that "
        f"succeeded: IPOPT {r['ipopt_solve_s'] * 1e3:.2f} ms ({r['ipopt_solver_time_s'] * 1e3:.2f} ms), "
        f"SNOPT {r['snopt_solve_s'] * 1e3:.2f} ms ({r['snopt_solver_time_s'] * 1e3:.2f} ms); failed: IPOPT "
        f"{r['ipopt_failures']}, SNOPT {r['snopt_failures']} of {r['reference_solves']} (the batched move: "
        f"{r['reference_solves'] - r['batched_success_reference_particles']} of the same)\n"
        f"speed-up per particle: {r['speedup_per_particle']:.0f}x vs IPOPT, {r['speedup_per_particle_snopt']:.0f}x vs SNOPT "
        f"({r['speedup_per_particle_filter_tolerance']:.0f}x vs IPOPT when the batched move takes the "
        f"\"filter\" tolerance)"
    )


#: How many refused actions per timed iteration ``bench_filter`` draws past before it gives up
#: (the model plant refuses an action where it finds no equilibrium: about 1 in 10).
MAX_REFUSED_PER_ITERATION = 10


def bench_filter(particles: int = 60_000, seed: int = 0, iterations: int = 10, run_iterations: int = 30) -> dict:
    """Time ``iterations`` full filter iterations (move, predict, weigh, resample, roughen)
    on the model plant (an action it refuses is drawn again, not timed), then a known-hand
    identification of ``run_iterations`` iterations with as many particles on the physics
    plant with the rendered camera, its wall time split into physics, rendering, detection,
    filtering and the rest (building the plant and the diagram, the grasp; 0: no
    identification run)."""
    from vlr_drake import filter as pf
    from vlr_drake.identify import Exploration, _truth_grasp
    from vlr_drake.model_plant import ModelPlant

    _check_counts("filter", particles=(particles, 10), iterations=(iterations, 1), run_iterations=(run_iterations, 0))

    h = hand_by_name("model_o").model()
    theta, a = _truth_grasp(h, np.random.default_rng(seed))

    def new_plant():  # the same grasp and measurement noise for every call
        return ModelPlant(h, theta, a, np.eye(3), np.array([0.0, 0.0, 0.11]), np.random.default_rng(seed + 1))

    def setup(**settings):  # the same grasp, prior draws and actions for every call
        plant = new_plant()
        f = pf.SelfIdentificationFilter(h, pf.FilterConfig(particles=particles, **settings), pf.PriorConfig(),
                                        np.random.default_rng(seed + 2))
        R, t, _ = plant.measure()
        t0 = time.perf_counter()
        f.initialise(theta, a, R, t, tendon_command=plant.state.tendon_command)
        init_s = time.perf_counter() - t0
        explore = Exploration(plant.state.tendon_command, h.tendon_range, 1.5e-3, 4e-3,
                              np.random.default_rng(seed + 3))
        return plant, f, explore, init_s, (R, t)

    # warm-up (compilation) on a tiny filter at the same grasp, before anything is timed
    # (resampling every step and a tight ESS target, so that every kernel of an iteration is
    # compiled or loaded from numba's cache before the timed ones; the initialisation's too:
    # timed cold it included numba's compilation, 1.7 s)
    plant = new_plant()
    R, t, _ = plant.measure()
    with warnings.catch_warnings():  # a warm-up, not an estimate
        warnings.simplefilter("ignore", pf.FewParticlesWarning)
        small = pf.SelfIdentificationFilter(h, pf.FilterConfig(particles=100, resample_fraction=1.0,
                                                               ess_fraction=0.99),
                                            pf.PriorConfig(), np.random.default_rng(0))
    small.initialise(theta, a, R, t, tendon_command=plant.state.tendon_command)
    for _ in range(2):
        small.step(np.zeros(h.N), R, t)
    pf.interval95(np.arange(8.0)[:, None], np.arange(1.0, 9.0) / 36.0)  # weighted intervals
    pf.temper(-np.arange(8.0) ** 2, 4.0)  # tempering
    plant, f, explore, init_s, (R, t) = setup()
    times, resampled, phases = [], [], []
    refused = 0
    while len(times) < iterations:  # a refused action is not an iteration: another is drawn
        dl = explore.next_action()
        if not plant.apply_action(dl):
            refused += 1
            if refused > MAX_REFUSED_PER_ITERATION * iterations:
                raise ValueError(f"bench filter: the model plant refused {refused} actions and took {len(times)}; "
                                 f"try another --seed")
            continue
        explore.commit(dl)
        R, t, v = plant.measure()
        n0 = f.resamples
        t0 = time.perf_counter()
        report = f.step(dl, R, t, v)
        times.append(time.perf_counter() - t0)
        resampled.append(f.resamples > n0)
        phases.append(report.timing_s)
    it_s = float(np.median(times))
    # the first iteration again, without the continuation in the move that settles the
    # prior's draws (FilterConfig.first_move_substeps; not the default, see there)
    plant, fast, explore, _, _ = setup(first_move_substeps=0)
    first_fast_s = float("nan")
    for _ in range(MAX_REFUSED_PER_ITERATION * iterations + 1):
        dl = explore.next_action()
        if plant.apply_action(dl):
            explore.commit(dl)
            R, t, v = plant.measure()
            t0 = time.perf_counter()
            fast.step(dl, R, t, v)
            first_fast_s = time.perf_counter() - t0
            break
    out = {
        "benchmark": "filter",
        "particles": particles,
        "iteration_s": it_s,
        "iterations_timed": len(times),
        "actions_refused": refused,
        "iteration_max_s": float(np.max(times)),
        # the first iteration moves the whole prior: the widest cloud, the most failed moves
        "first_iteration_s": float(times[0]),
        "first_iteration_without_first_continuation_s": first_fast_s,
        "first_move_substeps_compared": [f.config.first_move_substeps, fast.config.first_move_substeps],
        # per phase (StepReport.timing_s): the median over the iterations, and the slowest
        # iteration's split
        "iteration_phases_s": {k: float(np.median([p.get(k, 0.0) for p in phases]))
                               for k in dict.fromkeys(k for p in phases for k in p)},
        "slowest_iteration_phases_s": phases[int(np.argmax(times))],
        "resampled_fraction": float(np.mean(resampled)),
        "particles_per_s": particles / it_s,
        "initialise_s": init_s,
        "threads": _threads(),
    }
    if run_iterations > 0:
        from vlr_drake.identify import IdentifyOptions, run_identification

        # no extra_iterations and a 0-degree threshold: the run lasts run_iterations
        opts = IdentifyOptions(experiment="known_hand", plant="physics", particles=particles,
                               max_iterations=run_iterations, seed=seed, progress=False)
        opts.filter.convergence_deg = 0.0
        r = run_identification(opts)
        t = dict(r["timing_s"])
        # what none of the parts holds: building the plant and diagram, the grasp, bookkeeping
        t["other"] = max(t["total"] - sum(t[k] for k in ("physics", "render", "detect", "filter")), 0.0)
        out["identification"] = {"plant": "physics", "object": r["object"], "iterations": r["iterations"],
                                 "timing_s": t}
    return out


def format_filter(r: dict) -> str:
    text = (f"filter iteration with {r['particles']} particles ({r['threads']} threads): median "
            f"{r['iteration_s'] * 1e3:.0f} ms, max {r['iteration_max_s'] * 1e3:.0f} ms, first "
            f"{r.get('first_iteration_s', float('nan')) * 1e3:.0f} ms "
            f"({r['particles_per_s']:.0f} particles/s; resampled in {100 * r['resampled_fraction']:.0f}% of "
            f"iterations); initialisation {r['initialise_s']:.1f} s")
    fast = r.get("first_iteration_without_first_continuation_s")
    if fast is not None and np.isfinite(fast):
        text += (f"\n  first iteration without the first move's continuation (FilterConfig.first_move_substeps=0): "
                 f"{fast * 1e3:.0f} ms")
    for label, split in (("median", r.get("iteration_phases_s")), ("slowest", r.get("slowest_iteration_phases_s"))):
        if split:
            text += f"\n  {label} iteration: " + ", ".join(f"{k} {v * 1e3:.0f} ms" for k, v in split.items())
    run = r.get("identification")
    if run:
        t = run["timing_s"]
        parts = ", ".join(f"{k} {t[k]:.1f} s" for k in ("physics", "render", "detect", "filter", "other") if k in t)
        text += (f"\nknown-hand identification on the {run['plant']} plant ({run['object']}, {run['iterations']} "
                 f"iterations): total {t['total']:.1f} s ({parts})")
    return text
