"""Plots of a self-identification run, in the style of the paper's Fig. 4C, 5B and 8E.

Each identified quantity is drawn against the filter iteration: the estimate (the mean of
the particle cloud) as a solid line, its 95% interval (2.5-97.5 percentiles, DESIGN.md
section 6) as a shaded band, and the ground truth, where known, dashed.

Inputs are the filter's history as :class:`vlr_drake.filter.SelfIdentificationFilter`
keeps it:

- ``estimates``: list of dicts from ``SelfIdentificationFilter.estimate()``, one per
  iteration, the first one at initialisation (iteration 0). Keys used: ``theta``,
  ``theta_lo``, ``theta_hi`` (N, K) [rad]; ``a``, ``a_lo``, ``a_hi`` (N,) [m];
  ``stiffness``/``_lo``/``_hi`` (N, K) [N m/rad]; ``link_lengths``/``_lo``/``_hi``
  (N, K-1) [m].
- ``truths``: ``None`` or a list of the same length of dicts (or ``None`` entries) with
  keys ``theta``, ``a``, ``stiffness``, ``link_lengths``; a missing entry is not drawn.
- ``names``: the finger names (N,).

:func:`make_reproduction_figure` draws ``vlr-drake reproduce``'s table: each row of ours
beside the paper's.

Every ``make_*_figure`` function returns a :class:`matplotlib.figure.Figure` (for tests
and notebooks); every ``plot_*`` function saves that figure and returns the path written.
Figures are made with the object-oriented API and the Agg canvas only: no pyplot, no
global state.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from vlr_drake.kinematics import is_count, is_number

__all__ = [
    "Panel",
    "band_figure",
    "make_joint_angles_figure",
    "make_contacts_figure",
    "make_stiffness_figure",
    "make_link_lengths_figure",
    "make_convergence_figure",
    "make_hypotheses_figure",
    "make_reproduction_figure",
    "plot_joint_angles",
    "plot_contacts",
    "plot_stiffness",
    "plot_link_lengths",
    "plot_convergence",
    "plot_hypotheses",
    "plot_reproduction",
    "save_figure",
]

#: Colours: the band and the estimate line share one colour; the truth is black, dashed.
ESTIMATE_COLOR = "tab:blue"
TRUTH_COLOR = "black"
BAND_ALPHA = 0.3


@dataclass
class Panel:
    """One axes of a band figure: a scalar quantity over the iterations (display units)."""

    title: str
    mean: np.ndarray  # (T,)
    lo: np.ndarray  # (T,) lower end of the 95% interval
    hi: np.ndarray  # (T,) upper end of the 95% interval
    truth: np.ndarray | None  # (T,) with NaN where unknown, or None


# ------------------------------------------------------------------------------ inputs
def _stack(estimates: Sequence[dict], key: str, shape: tuple) -> np.ndarray:
    """Stack ``estimates[t][key]`` into a (T, *shape) array; errors name the key and t."""
    out = np.empty((len(estimates), *shape))
    for t, est in enumerate(estimates):
        if est is None or key not in est:
            raise ValueError(f"estimates[{t}] has no '{key}'")
        value = np.asarray(est[key], dtype=float)
        if value.shape != shape:
            raise ValueError(f"estimates[{t}]['{key}'] must have shape {shape}, got {value.shape}")
        out[t] = value
    return out


def _truth_series(truths: Sequence[dict | None] | None, key: str, shape: tuple, T: int) -> np.ndarray | None:
    """Stack ``truths[t][key]`` into (T, *shape), NaN where a truth is missing; None if none."""
    if truths is None:
        return None
    if len(truths) != T:
        raise ValueError(
            f"truths has {len(truths)} entries but estimates has {T}: they must align per iteration"
        )
    out = np.full((T, *shape), np.nan)
    any_known = False
    for t, tr in enumerate(truths):
        if tr is not None and not isinstance(tr, Mapping):  # (an AttributeError on 'get')
            raise ValueError(f"truths[{t}] must be a dict of truths or None, got {type(tr).__name__}")
        if tr is None or tr.get(key) is None:
            continue
        value = np.asarray(tr[key], dtype=float)
        if value.shape != shape:
            raise ValueError(f"truths[{t}]['{key}'] must have shape {shape}, got {value.shape}")
        out[t] = value
        any_known = True
    return out if any_known else None


def _dims(estimates: Sequence[dict], names: Sequence[str]) -> tuple[int, int]:
    """(N, K) from the first estimate's ``theta``, checked against ``names``."""
    if len(estimates) == 0:
        raise ValueError("estimates is empty: nothing to plot")
    if estimates[0] is None or "theta" not in estimates[0]:
        raise ValueError("estimates[0] has no 'theta'")
    theta = np.asarray(estimates[0]["theta"])
    if theta.ndim != 2:
        raise ValueError(f"estimates[0]['theta'] must have shape (N, K), got {theta.shape}")
    N, K = theta.shape
    if len(names) != N:
        raise ValueError(f"names has {len(names)} entries but the estimates have {N} fingers")
    return N, K


def _quantity(estimates, truths, key: str, shape: tuple, scale: float):
    """(mean, lo, hi, truth) series of one estimate key, in display units (times ``scale``)."""
    T = len(estimates)
    mean = scale * _stack(estimates, key, shape)
    lo = scale * _stack(estimates, f"{key}_lo", shape)
    hi = scale * _stack(estimates, f"{key}_hi", shape)
    truth = _truth_series(truths, key, shape, T)
    return mean, lo, hi, None if truth is None else scale * truth


def _entries(name: str, value) -> list:
    """The entries of the sequence ``value``, or a ValueError naming ``name``."""
    try:
        return list(value)
    except TypeError:
        raise ValueError(f"{name} must be a list, got {value!r}") from None


def _joints(which, N: int, K: int) -> list[tuple[int, int]]:
    """``which`` as (finger, joint) pairs of whole indices of an N x K hand, or a ValueError
    naming the entry (a bare pair, (0, 1), had failed in a TypeError; 0.7 was cut to 0)."""
    pairs = []
    for w in _entries("which", which):
        try:
            fi, j = w
        except (TypeError, ValueError):
            raise ValueError(f"which: {w!r} is not a (finger, joint) pair; e.g. which=[(0, 1)]") from None
        if not (is_count(fi) and is_count(j) and fi < N and j < K):
            raise ValueError(f"which: ({fi!r}, {j!r}) is not a joint of a {N} x {K} hand")
        pairs.append((int(fi), int(j)))
    return pairs


def _iterations(iterations: Sequence[int] | None, T: int) -> np.ndarray:
    if iterations is None:
        return np.arange(T)
    try:
        it = np.asarray(iterations, dtype=float)
    except (TypeError, ValueError):
        it = None
    if it is None or not np.all(np.isfinite(it)):  # (NaN had drawn empty axes)
        raise ValueError(f"iterations must be finite numbers, got {iterations!r}")
    if it.shape != (T,):
        raise ValueError(f"iterations must have shape ({T},) to match the estimates, got {it.shape}")
    return it


# ------------------------------------------------------------------------------ figures
def band_figure(
    panels: Sequence[Panel], iterations: np.ndarray, ylabel: str, title: str, ncols: int | None = None
) -> Figure:
    """One axes per panel: estimate (solid), 95% band (shaded), truth (dashed).

    In each axes ``ax.collections[0]`` is the band, ``ax.lines[0]`` the estimate and
    ``ax.lines[1]`` the truth (when the panel has one).
    """
    if not panels:
        raise ValueError("panels is empty: nothing to plot")
    n = len(panels)
    ncols = ncols or min(n, 3)
    nrows = int(np.ceil(n / ncols))
    fig = Figure(figsize=(4.0 * ncols, 2.8 * nrows), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, ncols, squeeze=False, sharex=True)
    for ax, p in zip(axes.ravel()[:n], panels, strict=True):
        ax.fill_between(
            iterations, p.lo, p.hi, color=ESTIMATE_COLOR, alpha=BAND_ALPHA, linewidth=0, label="95% interval"
        )
        ax.plot(iterations, p.mean, color=ESTIMATE_COLOR, linewidth=1.5, label="estimate")
        if p.truth is not None:
            ax.plot(
                iterations, p.truth, color=TRUTH_COLOR, linestyle="--", linewidth=1.2, label="ground truth"
            )
        ax.set_title(p.title)
        ax.set_ylabel(ylabel)
        ax.grid(True, alpha=0.3)
    for ax in axes.ravel()[n:]:
        ax.set_visible(False)
    axes[0, 0].xaxis.set_major_locator(MaxNLocator(integer=True))  # (shared) iterations are whole
    for c in range(ncols):  # each column's lowest panel shows the iteration axis (sharex hides the others')
        shown = [axes[r, c] for r in range(nrows) if r * ncols + c < n]
        if shown:
            shown[-1].xaxis.set_tick_params(labelbottom=True)
            shown[-1].set_xlabel("iteration")
    axes.ravel()[0].legend(loc="best", fontsize="small")
    fig.suptitle(title)
    return fig


def make_joint_angles_figure(
    estimates: Sequence[dict],
    truths: Sequence[dict | None] | None,
    names: Sequence[str],
    joints: str = "proximal",
    iterations: Sequence[int] | None = None,
) -> Figure:
    """Joint angles theta [deg] against iterations (Fig. 4C). ``joints``: "proximal" (one
    panel per finger, joint 1) or "all" (one panel per joint, a row per finger)."""
    N, K = _dims(estimates, names)
    if joints not in ("proximal", "all"):
        raise ValueError(f"joints must be 'proximal' or 'all', got {joints!r}")
    mean, lo, hi, truth = _quantity(estimates, truths, "theta", (N, K), np.rad2deg(1.0))
    js = [0] if joints == "proximal" else list(range(K))
    panels = [
        Panel(
            f"{names[i]} joint {j + 1}",
            mean[:, i, j],
            lo[:, i, j],
            hi[:, i, j],
            None if truth is None else truth[:, i, j],
        )
        for i in range(N)
        for j in js
    ]
    title = "proximal joint angles" if joints == "proximal" else "joint angles"
    return band_figure(
        panels,
        _iterations(iterations, len(estimates)),
        "angle [deg]",
        title,
        ncols=min(N, 3) if joints == "proximal" else K,
    )


def make_contacts_figure(
    estimates: Sequence[dict],
    truths: Sequence[dict | None] | None,
    names: Sequence[str],
    iterations: Sequence[int] | None = None,
) -> Figure:
    """Contact positions a_i along the last links [mm] against iterations (DESIGN.md section 3)."""
    N, _ = _dims(estimates, names)
    mean, lo, hi, truth = _quantity(estimates, truths, "a", (N,), 1e3)
    panels = [
        Panel(f"{names[i]} contact a", mean[:, i], lo[:, i], hi[:, i], None if truth is None else truth[:, i])
        for i in range(N)
    ]
    return band_figure(panels, _iterations(iterations, len(estimates)), "a [mm]", "contact positions")


def make_stiffness_figure(
    estimates: Sequence[dict],
    truths: Sequence[dict | None] | None,
    names: Sequence[str],
    which: Sequence[tuple[int, int]] = ((0, 1),),
    iterations: Sequence[int] | None = None,
) -> Figure:
    """Joint stiffness [N m/rad] of the (finger, joint) pairs in ``which`` (Fig. 5B; the
    paper's experiment identifies the thumb's distal joint, (0, 1) on the Model O)."""
    N, K = _dims(estimates, names)
    which = _joints(which, N, K)
    if not which:
        raise ValueError("which is empty: name at least one (finger, joint)")
    mean, lo, hi, truth = _quantity(estimates, truths, "stiffness", (N, K), 1.0)
    panels = [
        Panel(
            f"{names[fi]} joint {j + 1} stiffness (stiffness:{names[fi]}/{j})",  # (the result's name)
            mean[:, fi, j],
            lo[:, fi, j],
            hi[:, fi, j],
            None if truth is None else truth[:, fi, j],
        )
        for fi, j in which
    ]
    return band_figure(
        panels, _iterations(iterations, len(estimates)), "stiffness [N m/rad]", "joint stiffness"
    )


def make_link_lengths_figure(
    estimates: Sequence[dict],
    truths: Sequence[dict | None] | None,
    names: Sequence[str],
    fingers: Sequence[int] | None = None,
    iterations: Sequence[int] | None = None,
) -> Figure:
    """Link lengths L_ik [mm] of the given fingers (all by default) against iterations
    (Fig. 8E): one panel per link, a row per finger."""
    N, K = _dims(estimates, names)
    fingers = list(range(N)) if fingers is None else _entries("fingers", fingers)
    if not fingers:
        raise ValueError("fingers is empty: name at least one finger")
    for fi in fingers:  # (0.5 had been cut to finger 0)
        if not (is_count(fi) and fi < N):
            raise ValueError(f"fingers: {fi!r} is not a finger of a {N}-finger hand")
    fingers = [int(fi) for fi in fingers]
    mean, lo, hi, truth = _quantity(estimates, truths, "link_lengths", (N, K - 1), 1e3)
    panels = [
        Panel(
            f"{names[fi]} link {k + 1}",
            mean[:, fi, k],
            lo[:, fi, k],
            hi[:, fi, k],
            None if truth is None else truth[:, fi, k],
        )
        for fi in fingers
        for k in range(K - 1)
    ]
    return band_figure(
        panels,
        _iterations(iterations, len(estimates)),
        "length [mm]",
        "link lengths",
        ncols=max(K - 1, 1) if len(fingers) > 1 else None,
    )


def make_convergence_figure(history: Sequence, threshold_deg: float | None = None,
                            measure: str = "half_width", parameter_threshold: float | None = None) -> Figure:
    """Mean 95% interval of the joint angles per iteration (``StepReport.mean_interval_deg``,
    its half-width or full width as the run's ``FilterConfig.convergence_measure``, named by
    ``measure``) with the convergence threshold (``FilterConfig.convergence_deg`` by default;
    pass the run's own), and the effective sample size below it. Re-initialisations are
    marked by red vertical lines, the first converged iteration by a green one. Where the run
    identified springs or link lengths (``StepReport.parameter_interval`` finite), a third
    panel, between the two, shows their widest interval in percent of its estimate, with
    ``parameter_threshold`` (the run's ``FilterConfig.parameter_convergence``; None: none
    drawn).

    Axes 0: ``lines[0]`` the interval, ``lines[1]`` the threshold; axes 1: ``lines[0]`` ESS;
    axes 2 (where drawn): ``lines[0]`` the parameters' interval [%], ``lines[1]`` its threshold.
    """
    if len(history) == 0:
        raise ValueError("history is empty: nothing to plot")
    if threshold_deg is None:
        from vlr_drake.filter import FilterConfig

        threshold_deg = FilterConfig().convergence_deg
    # the run's settings, as FilterConfig.validate takes them (a word had failed in a format
    # code error, NaN drawn no threshold, and a negative one below the axis)
    if not (is_number(threshold_deg) and np.isfinite(threshold_deg) and threshold_deg >= 0):
        raise ValueError(f"threshold_deg must be a finite number >= 0 [deg] (FilterConfig.convergence_deg), "
                         f"got {threshold_deg!r}")
    c = parameter_threshold
    if c is not None and not (is_number(c) and np.isfinite(c) and c > 0):
        raise ValueError(f"parameter_threshold must be None or a positive finite fraction "
                         f"(FilterConfig.parameter_convergence), got {c!r}")
    if measure not in ("half_width", "full_width"):
        raise ValueError(f"measure must be 'half_width' or 'full_width' (FilterConfig.convergence_measure), got {measure!r}")
    label = "mean 95% half-width" if measure == "half_width" else "mean 95% interval width"
    for t, rep in enumerate(history):
        for field in ("iteration", "mean_interval_deg", "ess", "converged", "reinitialised"):
            if not hasattr(rep, field):
                raise ValueError(f"history[{t}] has no field '{field}' (expected a filter.StepReport)")
    it = np.array([r.iteration for r in history], dtype=float)
    width = np.array([r.mean_interval_deg for r in history], dtype=float)
    ess = np.array([r.ess for r in history], dtype=float)
    param = np.array([getattr(r, "parameter_interval", np.nan) for r in history], dtype=float)
    has_param = bool(np.isfinite(param).any())
    fig = Figure(figsize=(6.0, 6.5 if has_param else 5.0), layout="constrained")
    FigureCanvasAgg(fig)
    if has_param:  # axes in the order the docstring names them, drawn interval / parameters / ESS
        grid = fig.add_gridspec(3, 1, height_ratios=[2, 1.3, 1])
        ax = fig.add_subplot(grid[0])
        ax_ess = fig.add_subplot(grid[2], sharex=ax)
        ax_par = fig.add_subplot(grid[1], sharex=ax)
    else:
        ax, ax_ess = fig.subplots(2, 1, sharex=True, height_ratios=[2, 1])
    ax.plot(it, width, color=ESTIMATE_COLOR, marker="o", markersize=3, label=label)
    ax.axhline(threshold_deg, color=TRUTH_COLOR, linestyle="--", label=f"threshold {threshold_deg:g} deg")
    for r in history:
        if r.reinitialised:
            ax.axvline(r.iteration, color="tab:red", linestyle=":", alpha=0.8)
    first = next((r.iteration for r in history if r.converged), None)
    if first is not None:
        ax.axvline(first, color="tab:green", linestyle="-", alpha=0.6, label=f"converged at {first}")
    ax.set_ylabel(f"{label.removeprefix('mean 95% ')} [deg]")
    ax.set_yscale("log" if np.all(width > 0) and width.max() > 20 * max(width.min(), 1e-12) else "linear")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize="small")
    ax.set_title("convergence of the joint angle" + (" and hand parameter" if has_param else "") + " intervals")
    if has_param:
        what = "half-width" if measure == "half_width" else "width"
        ax_par.plot(it, 100.0 * param, color="tab:purple", marker=".", label=f"widest hand parameter's 95% {what}")
        if parameter_threshold is not None:
            ax_par.axhline(100.0 * parameter_threshold, color=TRUTH_COLOR, linestyle="--",
                           label=f"threshold {100.0 * parameter_threshold:g}%")
        ax_par.set_ylabel("% of estimate")
        if np.nanmin(param) > 0:  # log, labelled 2, 5, 10, 20, 50 rather than 2x10^0
            from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

            ax_par.set_yscale("log")
            ax_par.yaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
            ax_par.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
            ax_par.yaxis.set_minor_formatter(NullFormatter())
        ax_par.grid(True, alpha=0.3)
        ax_par.legend(loc="best", fontsize="small")
    ax_ess.plot(it, ess, color="tab:gray", marker=".", label="ESS")
    ax_ess.set_ylabel("ESS")
    # from 0, in plain numbers: an ESS held at the tempering's floor (90.0000000009) had been
    # drawn as 0-10 with an offset of 1e-10 + 90 (a review)
    ax_ess.ticklabel_format(axis="y", useOffset=False, style="plain")
    ax_ess.set_ylim(bottom=0.0, top=max(1.05 * float(np.nanmax(ess)), 1.0) if np.isfinite(ess).any() else None)
    ax_ess.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax_ess.set_xlabel("iteration")
    ax_ess.grid(True, alpha=0.3)
    return fig


def make_reproduction_figure(rows: Sequence[Mapping], values: Mapping[str, Sequence[float]] | None = None,
                             title: str = "") -> Figure:
    """The paper's table against ours (``vlr-drake reproduce``): one strip per row, in the
    row's own unit, with the paper's mean +- SD (grey, above) and ours (blue, below; green
    where the row beats the paper, red where it does not, with the row's ``converged``,
    ``succeeded`` or ``failed`` where they are why), and each trial's figure (for a task its
    mean over its waypoints, samples or cups) as a dot in a lane below, where ``values[row
    key]`` gives them.

    ``rows``: :func:`vlr_drake.reproduce.reproduce`'s rows (keys ``key``, ``experiment``,
    ``unit``, ``paper_mean``, ``paper_sd``, ``ours_mean``, ``ours_sd``, ``better``); a row
    without a finite mean of ours (every trial failed) shows the paper's alone. Axes i is
    row i: ``lines`` hold the two error bars' lines, ``collections[0]`` the dots where given.
    """
    if len(rows) == 0:
        raise ValueError("rows is empty: nothing to plot")
    for i, r in enumerate(rows):
        missing = [k for k in ("key", "experiment", "unit", "paper_mean", "paper_sd", "ours_mean", "ours_sd", "better")
                   if k not in r]
        if missing:
            raise ValueError(f"rows[{i}] has no {', '.join(repr(k) for k in missing)} (expected a reproduce row)")
    values = {} if values is None else values
    fig = Figure(figsize=(7.0, 0.95 * len(rows) + 0.9), layout="constrained")
    FigureCanvasAgg(fig)
    axes = np.atleast_1d(fig.subplots(len(rows), 1))
    for ax, r in zip(axes, rows, strict=True):
        ours = r["ours_mean"] is not None and np.isfinite(r["ours_mean"])
        ax.errorbar([r["paper_mean"]], [1.0], xerr=[r["paper_sd"]], fmt="s", color="tab:gray", capsize=3)
        if ours:
            color = "tab:green" if r["better"] else "tab:red"
            ax.errorbar([r["ours_mean"]], [0.0], xerr=[r["ours_sd"] or 0.0], fmt="o", color=color, capsize=3)
        dots = np.asarray(values.get(r["key"], ()), float).ravel()
        dots = dots[np.isfinite(dots)]
        if dots.size:  # a lane of their own below ours, jittered (fixed: the same picture every time)
            jitter = np.random.default_rng(0).uniform(-0.12, 0.12, dots.size)
            ax.scatter(dots, -0.55 + jitter, s=10, color=ESTIMATE_COLOR, alpha=0.6, linewidths=0)
        ax.set_ylim(-0.85, 1.5)
        ax.set_yticks([1.0, 0.0, -0.55], ["paper", "ours", "trials"], fontsize="small")
        ax.set_xlim(left=0.0)
        why = [f"{r[k][0]} of {r[k][1]} {k}" for k in ("converged", "succeeded") if k in r and r[k][0] < r[k][1]]
        why += [f"{r['failed'][0]} of {r['failed'][1]} failed"] if "failed" in r else []
        verdict = "" if not ours else ("  (beats the paper)" if r["better"] else
                                       f"  (does not beat the paper{': ' + ', '.join(why) if why else ''})")
        ax.set_title(f"{r['experiment']} [{r['unit']}]{verdict}", fontsize="small", loc="left")
        ax.tick_params(axis="x", labelsize="small")
        ax.grid(True, axis="x", alpha=0.3)
    if title:
        fig.suptitle(title, fontsize="medium")
    return fig


def make_hypotheses_figure(
    joints: np.ndarray,
    contacts: np.ndarray,
    pom_position: np.ndarray | None = None,
    estimate_contacts: np.ndarray | None = None,
    title: str = "hypotheses",
) -> Figure:
    """A still of the hypotheses in the colours of Fig. 4A (the PNG twin of
    :class:`vlr_drake.visualization.HypothesisDrawer`), palm frame, in mm.

    ``joints`` (P, N, K, 3) and ``contacts`` (P, N, 3) of the drawn particles (see
    :func:`vlr_drake.visualization.hypothesis_points`), ``pom_position`` (P, 3) or None,
    ``estimate_contacts`` (N, 3) or None (the mean of ``contacts``).
    ``ax.collections``: [0] the magenta E^J segments, [1] the blue distal joints, [2] the
    yellow contacts, [3] the red E^C segments.
    """
    from mpl_toolkits.mplot3d.art3d import Line3DCollection

    joints = np.asarray(joints, dtype=float)
    if joints.ndim != 4 or joints.shape[-1] != 3:
        raise ValueError(f"joints must have shape (P, N, K, 3), got {joints.shape}")
    P, N, K, _ = joints.shape
    if P == 0:
        raise ValueError("joints has no particles (P = 0): nothing to draw")
    contacts = np.asarray(contacts, dtype=float)
    if contacts.shape != (P, N, 3):
        raise ValueError(f"contacts must have shape ({P}, {N}, 3), got {contacts.shape}")
    p_hat = contacts.mean(axis=0) if estimate_contacts is None else np.asarray(estimate_contacts, dtype=float)
    if p_hat.shape != (N, 3):
        raise ValueError(f"estimate_contacts must have shape ({N}, 3), got {p_hat.shape}")
    # one POM position per particle, as HypothesisDrawer.draw takes them (an empty array had
    # ended in "Axis limits cannot be NaN or Inf", a (P, 2) one in numpy's reshape error)
    if pom_position is not None and np.shape(pom_position) != (P, 3):
        raise ValueError(f"pom_position must have shape ({P}, 3), got {np.shape(pom_position)}")
    for name, value in [("joints", joints), ("contacts", contacts), ("estimate_contacts", p_hat),
                        ("pom_position", pom_position)]:
        if value is not None and not np.all(np.isfinite(np.asarray(value, dtype=float))):
            raise ValueError(f"{name} must be finite (a hypothesis with NaN or inf positions)")
    mm = 1e3
    # E^J: q_1 -> ... -> q_K -> p_i per particle and finger
    chain = np.concatenate([joints, contacts[:, :, None, :]], axis=2) * mm  # (P, N, K+1, 3)
    seg_j = np.stack([chain[:, :, :-1], chain[:, :, 1:]], axis=-2).reshape(-1, 2, 3)
    # E^C: pairs of estimated contacts, and each to the POM
    seg_c = [(p_hat[a] * mm, p_hat[b] * mm) for a in range(N) for b in range(a + 1, N)]
    if pom_position is not None:
        pom = np.asarray(pom_position, dtype=float).mean(axis=0) * mm
        seg_c += [(p_hat[i] * mm, pom) for i in range(N)]
    fig = Figure(figsize=(6.0, 5.5), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(projection="3d")
    ax.add_collection3d(Line3DCollection(seg_j, colors=[(1.0, 0.0, 1.0, 0.4)], linewidths=0.8))
    distal = joints[:, :, K - 1].reshape(-1, 3) * mm
    ax.scatter(distal[:, 0], distal[:, 1], distal[:, 2], color=(0.1, 0.3, 1.0), s=6, depthshade=False)
    ax.scatter(
        p_hat[:, 0] * mm,
        p_hat[:, 1] * mm,
        p_hat[:, 2] * mm,
        color=(1.0, 0.9, 0.0),
        s=40,
        edgecolors="k",
        depthshade=False,
    )
    ax.add_collection3d(Line3DCollection(np.array(seg_c).reshape(-1, 2, 3), colors="red", linewidths=1.5))
    pts = np.concatenate(
        [chain.reshape(-1, 3), seg_j.reshape(-1, 3)] + ([np.array(seg_c).reshape(-1, 3)] if seg_c else [])
    )
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    centre, half = 0.5 * (lo + hi), 0.5 * max((hi - lo).max(), 1e-6) * 1.05
    ax.set_xlim(centre[0] - half, centre[0] + half)
    ax.set_ylim(centre[1] - half, centre[1] + half)
    ax.set_zlim(centre[2] - half, centre[2] + half)
    ax.set_box_aspect((1.0, 1.0, 1.0))
    ax.set_xlabel("x [mm]")
    ax.set_ylabel("y [mm]")
    ax.set_zlabel("z [mm]")
    ax.set_title(title)
    return fig


# ------------------------------------------------------------------------------ files
def save_figure(fig: Figure, path: str | Path, dpi: int = 120) -> Path:
    """Write ``fig`` (format from the suffix), creating the folder; returns the path. A
    suffix that is no image format (or none) is a ValueError naming the path, before any
    folder is made (without one, matplotlib had written ``<path>.png`` and the path returned
    did not exist)."""
    path = Path(path)
    formats = fig.canvas.get_supported_filetypes()
    if path.suffix[1:].lower() not in formats:
        raise ValueError(f"{path}: the plot's file needs an image suffix ({', '.join('.' + f for f in sorted(formats))}), "
                         f"got {path.suffix or 'none'!r}")
    path.parent.mkdir(parents=True, exist_ok=True)
    from vlr_drake.entry import replacing

    with replacing(path) as temporary:  # in one piece
        fig.savefig(temporary, dpi=dpi, format=path.suffix[1:].lower())
    return path


def plot_joint_angles(
    estimates: Sequence[dict],
    truths: Sequence[dict | None] | None,
    names: Sequence[str],
    path: str | Path,
    joints: str = "proximal",
    iterations: Sequence[int] | None = None,
) -> Path:
    """Save :func:`make_joint_angles_figure` to ``path``; returns the path."""
    return save_figure(make_joint_angles_figure(estimates, truths, names, joints, iterations), path)


def plot_contacts(
    estimates: Sequence[dict],
    truths: Sequence[dict | None] | None,
    names: Sequence[str],
    path: str | Path,
    iterations: Sequence[int] | None = None,
) -> Path:
    """Save :func:`make_contacts_figure` to ``path``; returns the path."""
    return save_figure(make_contacts_figure(estimates, truths, names, iterations), path)


def plot_stiffness(
    estimates: Sequence[dict],
    truths: Sequence[dict | None] | None,
    names: Sequence[str],
    path: str | Path,
    which: Sequence[tuple[int, int]] = ((0, 1),),
    iterations: Sequence[int] | None = None,
) -> Path:
    """Save :func:`make_stiffness_figure` to ``path``; returns the path."""
    return save_figure(make_stiffness_figure(estimates, truths, names, which, iterations), path)


def plot_link_lengths(
    estimates: Sequence[dict],
    truths: Sequence[dict | None] | None,
    names: Sequence[str],
    path: str | Path,
    fingers: Sequence[int] | None = None,
    iterations: Sequence[int] | None = None,
) -> Path:
    """Save :func:`make_link_lengths_figure` to ``path``; returns the path."""
    return save_figure(make_link_lengths_figure(estimates, truths, names, fingers, iterations), path)


def plot_convergence(history: Sequence, path: str | Path, threshold_deg: float | None = None,
                     measure: str = "half_width", parameter_threshold: float | None = None) -> Path:
    """Save :func:`make_convergence_figure` to ``path``; returns the path."""
    return save_figure(make_convergence_figure(history, threshold_deg, measure, parameter_threshold), path)


def plot_reproduction(rows: Sequence[Mapping], path: str | Path, values: Mapping[str, Sequence[float]] | None = None,
                      title: str = "") -> Path:
    """Save :func:`make_reproduction_figure` to ``path``."""
    return save_figure(make_reproduction_figure(rows, values, title), path)


def plot_hypotheses(
    joints: np.ndarray,
    contacts: np.ndarray,
    path: str | Path,
    pom_position: np.ndarray | None = None,
    estimate_contacts: np.ndarray | None = None,
    title: str = "hypotheses",
) -> Path:
    """Save :func:`make_hypotheses_figure` to ``path`` (a per-iteration still); returns the path."""
    return save_figure(make_hypotheses_figure(joints, contacts, pom_position, estimate_contacts, title), path)
