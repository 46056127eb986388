"""Benchmarks that print their figures (never timed tests): ``vlr-drake bench motion``.

The motion benchmark measures, in one run, one batched move of ``particles`` Model O
hypotheses (numba Newton, DESIGN.md section 4) and single MathematicalProgram solves of
the same problem with IPOPT and with SNOPT, and reports the per-particle speed-up. Field
names follow DESIGN.md section 11.
"""

from __future__ import annotations

import time

import numpy as np

from vlr_drake import grasps, motion
from vlr_drake import motion_reference as ref
from vlr_drake.hand import hand_by_name


def bench_motion(particles: int = 60_000, seed: int = 0, hand: str = "model_o", repeats: int = 5,
                 reference_solves: int = 30, tendon: str = "elastic") -> dict:
    """Time one batched move of ``particles`` hypotheses and single reference solves."""
    h = hand_by_name(hand).model()
    rng = np.random.default_rng(seed)
    base = grasps.sample_grasps(h, rng, min(particles, 2000))
    idx = rng.integers(0, len(base.theta), particles)
    theta, a, s, D2 = base.theta[idx], base.a[idx], base.stretch[idx], base.D2[idx]
    dl = rng.uniform(-1.5e-3, 1.5e-3, h.N)
    motion.move(h, theta[:10], dl, a=a[:10], D2=D2[:10], stretch=s[:10], tendon=tendon)  # compile
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        res = motion.move(h, theta, dl, a=a, D2=D2, stretch=s, tendon=tendon)
        times.append(time.perf_counter() - t0)
    batched = float(np.median(times))
    solve_times = {}
    for solver in ref.SOLVERS:
        ts = []
        for p in range(reference_solves):
            t0 = time.perf_counter()
            try:
                ref.solve_move(h, theta[p], dl, a=a[p], D2=D2[p], stretch=s[p], tendon=tendon, solver=solver)
            except ref.MotionSolveError:
                pass
            ts.append(time.perf_counter() - t0)
        solve_times[solver] = float(np.median(ts))
    return {
        "benchmark": "motion",
        "hand": hand,
        "tendon": tendon,
        "particles": particles,
        "batched_move_s": batched,
        "batched_success_fraction": float(res.ok.mean()),
        "median_newton_iterations": float(np.median(res.iterations)),
        "ipopt_solve_s": solve_times["ipopt"],
        "snopt_solve_s": solve_times["snopt"],
        "speedup_per_particle": solve_times["ipopt"] / (batched / particles),
        "speedup_per_particle_snopt": solve_times["snopt"] / (batched / particles),
        "threads": _threads(),
    }


def _threads() -> int:
    import numba

    return int(numba.get_num_threads())


def format_motion(r: dict) -> str:
    return (
        f"batched move of {r['particles']} particles ({r['hand']}, {r['tendon']} tendon, {r['threads']} threads): "
        f"{r['batched_move_s'] * 1e3:.1f} ms  ({r['batched_success_fraction'] * 100:.1f}% converged, "
        f"median {r['median_newton_iterations']:.0f} Newton iterations)\n"
        f"MathematicalProgram, one solve: IPOPT {r['ipopt_solve_s'] * 1e3:.2f} ms, SNOPT {r['snopt_solve_s'] * 1e3:.2f} ms\n"
        f"speed-up per particle: {r['speedup_per_particle']:.0f}x vs IPOPT, {r['speedup_per_particle_snopt']:.0f}x vs SNOPT"
    )
