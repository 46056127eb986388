"""Plots of the identification history: files are written and the drawn data are the inputs."""

import re

import matplotlib
import numpy as np
import pytest

from vlr_drake import plots
from vlr_drake.filter import StepReport

N, K, T = 3, 2, 6
NAMES = ["thumb", "index", "middle"]


def _history(rng, truth_every=1):
    """Synthetic estimates whose intervals shrink around a drifting truth."""
    estimates, truths = [], []
    for t in range(T):
        width = 0.5 / (t + 1)
        truth = {
            "theta": np.deg2rad(20.0 + 5 * rng.standard_normal((N, K))),
            "a": 0.02 + 0.005 * rng.standard_normal(N),
            "stiffness": 0.1 + 0.01 * rng.standard_normal((N, K)),
            "link_lengths": 0.05 + 0.005 * rng.standard_normal((N, K - 1)),
        }
        est = {}
        for key, v in truth.items():
            mean = v + width * 0.1 * rng.standard_normal(v.shape) * np.abs(v)
            est[key] = mean
            est[f"{key}_lo"] = mean - width * np.abs(v)
            est[f"{key}_hi"] = mean + width * np.abs(v) * 1.3
        estimates.append(est)
        truths.append(truth if t % truth_every == 0 else None)
    return estimates, truths


def _check_band(ax, x, mean, lo, hi, truth):
    """The band polygon spans [lo, hi] at every x, the lines are the mean and the truth."""
    poly = ax.collections[0].get_paths()[0].vertices
    for xi, l, h in zip(x, lo, hi, strict=True):
        ys = poly[np.isclose(poly[:, 0], xi), 1]
        np.testing.assert_allclose([ys.min(), ys.max()], [l, h], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(ax.lines[0].get_xdata(), x)
    np.testing.assert_allclose(ax.lines[0].get_ydata(), mean)
    if truth is None:
        assert len(ax.lines) == 1
    else:
        assert ax.lines[1].get_linestyle() == "--"
        np.testing.assert_allclose(ax.lines[1].get_ydata(), truth, equal_nan=True)


def test_joint_angles_proximal_in_degrees(rng):
    est, tr = _history(rng)
    fig = plots.make_joint_angles_figure(est, tr, NAMES, joints="proximal")
    axes = [ax for ax in fig.axes if ax.get_visible()]
    assert len(axes) == N
    for i, ax in enumerate(axes):
        assert NAMES[i] in ax.get_title()
        _check_band(
            ax,
            np.arange(T),
            [np.rad2deg(e["theta"][i, 0]) for e in est],
            [np.rad2deg(e["theta_lo"][i, 0]) for e in est],
            [np.rad2deg(e["theta_hi"][i, 0]) for e in est],
            [np.rad2deg(t["theta"][i, 0]) for t in tr],
        )


def test_joint_angles_all_joints_missing_truths_are_gaps(rng):
    est, tr = _history(rng, truth_every=2)
    fig = plots.make_joint_angles_figure(est, tr, NAMES, joints="all", iterations=np.arange(T) + 10)
    axes = [ax for ax in fig.axes if ax.get_visible()]
    assert len(axes) == N * K
    ax = axes[1 * K + 1]  # finger 1, joint 2
    truth = [np.rad2deg(t["theta"][1, 1]) if t is not None else np.nan for t in tr]
    _check_band(
        ax,
        np.arange(T) + 10,
        [np.rad2deg(e["theta"][1, 1]) for e in est],
        [np.rad2deg(e["theta_lo"][1, 1]) for e in est],
        [np.rad2deg(e["theta_hi"][1, 1]) for e in est],
        truth,
    )
    assert np.isnan(ax.lines[1].get_ydata()[1])


def test_contacts_in_mm_without_truth(rng):
    est, _ = _history(rng)
    fig = plots.make_contacts_figure(est, None, NAMES)
    ax = fig.axes[2]
    _check_band(
        ax,
        np.arange(T),
        [1e3 * e["a"][2] for e in est],
        [1e3 * e["a_lo"][2] for e in est],
        [1e3 * e["a_hi"][2] for e in est],
        None,
    )
    assert "mm" in ax.get_ylabel()


def test_stiffness_and_link_lengths(rng):
    est, tr = _history(rng)
    fig = plots.make_stiffness_figure(est, tr, NAMES, which=[(0, 1), (2, 0)])
    axes = [ax for ax in fig.axes if ax.get_visible()]
    assert len(axes) == 2
    _check_band(
        axes[1],
        np.arange(T),
        [e["stiffness"][2, 0] for e in est],
        [e["stiffness_lo"][2, 0] for e in est],
        [e["stiffness_hi"][2, 0] for e in est],
        [t["stiffness"][2, 0] for t in tr],
    )
    fig = plots.make_link_lengths_figure(est, tr, NAMES, fingers=[1])
    axes = [ax for ax in fig.axes if ax.get_visible()]
    assert len(axes) == K - 1
    _check_band(
        axes[0],
        np.arange(T),
        [1e3 * e["link_lengths"][1, 0] for e in est],
        [1e3 * e["link_lengths_lo"][1, 0] for e in est],
        [1e3 * e["link_lengths_hi"][1, 0] for e in est],
        [1e3 * t["link_lengths"][1, 0] for t in tr],
    )


def _reports():
    widths = [20.0, 9.0, 4.0, 30.0, 1.5, 0.8]
    return [
        StepReport(
            iteration=i + 1,
            measured=True,
            ess=100.0 - i,
            beta=1.0,
            solve_failures=0,
            infeasible=0,
            reinitialised=(i == 3),
            best_mahalanobis=1.0,
            mean_interval_deg=w,
            converged=w < 2.0,
        )
        for i, w in enumerate(widths)
    ]


def test_convergence_lines():
    hist = _reports()
    fig = plots.make_convergence_figure(hist, threshold_deg=2.0)
    ax, ax_ess = fig.axes
    np.testing.assert_allclose(ax.lines[0].get_xdata(), np.arange(1, 7))
    np.testing.assert_allclose(ax.lines[0].get_ydata(), [r.mean_interval_deg for r in hist])
    np.testing.assert_allclose(ax.lines[1].get_ydata(), [2.0, 2.0])
    vlines = {(tuple(line.get_xdata()), line.get_color()) for line in ax.lines[2:]}
    assert ((4, 4), "tab:red") in vlines  # the re-initialisation
    assert ((5, 5), "tab:green") in vlines  # first converged iteration
    np.testing.assert_allclose(ax_ess.lines[0].get_ydata(), [r.ess for r in hist])


def test_convergence_draws_the_runs_own_threshold_and_a_plain_ess_axis():
    """The run's own threshold and measure (a plot that drew the default 2 deg whatever it was
    given passed the test above, which gives 2); the ESS from 0 in plain numbers (an ESS held
    at 90.0000000009 was drawn as 0-10 with an offset), whole iterations on the x axis."""
    from dataclasses import replace

    hist = [replace(r, ess=90.0 + 1e-9 * k) for k, r in enumerate(_reports())]
    fig = plots.make_convergence_figure(hist, threshold_deg=3.3, measure="full_width")
    ax, ax_ess = fig.axes
    np.testing.assert_allclose(ax.lines[1].get_ydata(), [3.3, 3.3])
    assert ax.lines[0].get_label() == "mean 95% interval width" and ax.lines[1].get_label() == "threshold 3.3 deg"
    fig.canvas.draw()
    assert ax_ess.get_ylim()[0] == 0.0 and not ax_ess.yaxis.get_major_formatter().get_useOffset()
    assert ax_ess.yaxis.get_offset_text().get_text() == ""
    assert all(float(t).is_integer() for t in ax_ess.get_xticks())


def test_convergence_shows_the_hand_parameters_where_identified():
    """A run that identified springs or links gets a third panel (axes 2, drawn between the
    joints' and the ESS's) with their widest interval in percent and the threshold; a known
    hand keeps two panels."""
    from dataclasses import replace

    hist = [replace(r, parameter_interval=p) for r, p in zip(_reports(), [0.5, 0.3, 0.2, 0.1, 0.06, 0.04], strict=True)]
    fig = plots.make_convergence_figure(hist, threshold_deg=2.0, parameter_threshold=0.05)
    ax, ax_ess, ax_par = fig.axes
    np.testing.assert_allclose(ax_par.lines[0].get_ydata(), [50, 30, 20, 10, 6, 4])
    np.testing.assert_allclose(ax_par.lines[1].get_ydata(), [5.0, 5.0])
    np.testing.assert_allclose(ax_ess.lines[0].get_ydata(), [r.ess for r in hist])
    assert ax.get_position().y0 > ax_par.get_position().y0 > ax_ess.get_position().y0
    assert len(plots.make_convergence_figure(_reports()).axes) == 2


def test_files_written_and_no_pyplot_state(tmp_path, rng):
    est, tr = _history(rng)
    before = matplotlib.get_backend()
    written = [
        plots.plot_joint_angles(est, tr, NAMES, tmp_path / "a" / "proximal.png", joints="proximal"),
        plots.plot_contacts(est, tr, NAMES, str(tmp_path / "contacts.png")),
        plots.plot_stiffness(est, tr, NAMES, tmp_path / "stiffness.png", which=[(0, 1)]),
        plots.plot_link_lengths(est, tr, NAMES, tmp_path / "links.svg", fingers=[0, 2]),
        plots.plot_convergence(_reports(), tmp_path / "convergence.png"),
    ]
    for p in written:
        assert p.exists() and p.stat().st_size > 1000, p
    assert written[0].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # the format is the suffix's: none (matplotlib had written "<path>.png" and returned a path
    # that did not exist) or another is named, and no folder is made for it
    for name in ("none/convergence", "other/convergence.v2"):
        with pytest.raises(ValueError, match=r"convergence.*: the plot's file needs an image suffix \(.*\.png"):
            plots.plot_convergence(_reports(), tmp_path / name)
        assert not (tmp_path / name).parent.exists()
    assert matplotlib.get_backend() == before
    import sys

    if "matplotlib.pyplot" in sys.modules:  # imported by someone else: it must hold no figure of ours
        import matplotlib.pyplot as plt

        assert plt.get_fignums() == []


def test_bad_inputs_name_the_field(rng):
    est, tr = _history(rng)
    with pytest.raises(ValueError, match="names"):
        plots.make_contacts_figure(est, tr, NAMES[:2])
    with pytest.raises(ValueError, match="truths"):
        plots.make_contacts_figure(est, tr[:-1], NAMES)
    with pytest.raises(ValueError, match="joints"):
        plots.make_joint_angles_figure(est, tr, NAMES, joints="distal")
    with pytest.raises(ValueError, match="which"):
        plots.make_stiffness_figure(est, tr, NAMES, which=[(3, 0)])
    # a bare pair failed in a TypeError ("'int' object is not iterable"), and a fraction was cut
    # to a whole finger or joint and drawn
    with pytest.raises(ValueError, match=r"which: 0 is not a \(finger, joint\) pair"):
        plots.make_stiffness_figure(est, tr, NAMES, which=(0, 1))
    with pytest.raises(ValueError, match=r"which: \(0, 1.5\) is not a joint of a 3 x 2 hand"):
        plots.make_stiffness_figure(est, tr, NAMES, which=[(0, 1.5)])
    with pytest.raises(ValueError, match="fingers: 0.5 is not a finger of a 3-finger hand"):
        plots.make_link_lengths_figure(est, tr, NAMES, fingers=[0.5])
    with pytest.raises(ValueError, match="fingers must be a list, got 1"):
        plots.make_link_lengths_figure(est, tr, NAMES, fingers=1)
    bad = [dict(e) for e in est]
    bad[2]["a_lo"] = np.zeros(N + 1)
    with pytest.raises(ValueError, match=r"estimates\[2\]\['a_lo'\]"):
        plots.make_contacts_figure(bad, tr, NAMES)
    with pytest.raises(ValueError, match="empty"):
        plots.make_convergence_figure([])
    # the thresholds are the run's settings (a word failed in a format code error, NaN drew none)
    for threshold in ("2", np.nan, -1.0):
        with pytest.raises(ValueError, match="threshold_deg must be a finite number >= 0"):
            plots.make_convergence_figure(_reports(), threshold_deg=threshold)
    for threshold in ("0.05", np.nan, -0.1):
        with pytest.raises(ValueError, match="parameter_threshold must be None or a positive finite fraction"):
            plots.make_convergence_figure(_reports(), parameter_threshold=threshold)
    # a truth that is not a dict (an AttributeError), iterations that are not finite numbers
    # (NaN drew empty axes; a word, numpy's "could not convert string to float")
    with pytest.raises(ValueError, match=r"truths\[1\] must be a dict of truths or None, got list"):
        plots.make_contacts_figure(est, [tr[0], [0.02] * N, *tr[2:]], NAMES)
    for iterations in (np.full(T, np.nan), ["a"] * T):
        with pytest.raises(ValueError, match="iterations must be finite numbers"):
            plots.make_contacts_figure(est, tr, NAMES, iterations=iterations)
    with pytest.raises(ValueError, match=r"estimates\[0\] has no 'theta'"):  # was an AttributeError
        plots.make_contacts_figure([None, *est[1:]], None, NAMES)


def test_hypotheses_still_segments_in_mm(rng, tmp_path):
    P, N_, K_ = 4, 3, 2
    joints = rng.uniform(-0.05, 0.05, (P, N_, K_, 3))
    contacts = rng.uniform(-0.05, 0.05, (P, N_, 3))
    pom = rng.uniform(-0.05, 0.05, (P, 3))
    fig = plots.make_hypotheses_figure(joints, contacts, pom, contacts[0])
    ax = fig.axes[0]
    # the 3D segments as given (matplotlib keeps them in Line3DCollection._segments3d)
    assert len(ax.collections[0]._segments3d) == P * N_ * K_
    seg = np.asarray(ax.collections[0]._segments3d).reshape(P, N_, K_, 2, 3)
    np.testing.assert_allclose(seg[..., 0, :], 1e3 * joints)  # starts at q_1..q_K
    np.testing.assert_allclose(seg[:, :, -1, 1, :], 1e3 * contacts)  # the last ends at p_i
    red = np.asarray(ax.collections[3]._segments3d)
    assert red.shape == (3 + N_, 2, 3)  # pairs of contacts, then contact -> POM
    np.testing.assert_allclose(red[3:, 1], np.repeat(1e3 * pom.mean(axis=0)[None], N_, axis=0))
    out = plots.plot_hypotheses(joints, contacts, tmp_path / "hyp.png", None, None, title="it 0")
    assert out.stat().st_size > 1000
    with pytest.raises(ValueError, match="contacts"):
        plots.make_hypotheses_figure(joints, contacts[:, :2])
    # no particles, or a non-finite one, failed inside matplotlib ("need at least one array to
    # concatenate", "Axis limits cannot be NaN or Inf")
    with pytest.raises(ValueError, match=r"joints has no particles \(P = 0\)"):
        plots.make_hypotheses_figure(joints[:0], contacts[:0])
    bad = joints.copy()
    bad[1, 0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="joints must be finite"):
        plots.make_hypotheses_figure(bad, contacts)
    with pytest.raises(ValueError, match="pom_position must be finite"):
        plots.make_hypotheses_figure(joints, contacts, np.full((P, 3), np.inf))
    # one POM position per particle (HypothesisDrawer.draw's): an empty array had failed inside
    # matplotlib ("Axis limits cannot be NaN or Inf"), a (P, 2) one in numpy's reshape
    for shape in ((0, 3), (P, 2), (2, 3)):
        with pytest.raises(ValueError, match=re.escape(f"pom_position must have shape ({P}, 3), got {shape}")):
            plots.make_hypotheses_figure(joints, contacts, np.zeros(shape))


def test_every_column_keeps_its_iteration_axis():
    """Four fingers in three columns: the panels above an empty slot are their columns'
    lowest and show the iteration axis (a review found them without, as sharex hides the
    labels of all but the bottom row)."""
    rng = np.random.default_rng(0)
    panels = [plots.Panel(f"f{i}", *rng.normal(size=(3, 5)), None) for i in range(4)]
    fig = plots.band_figure(panels, np.arange(5), "deg", "four fingers")
    shown = {ax.get_title(): ax for ax in fig.axes if ax.get_visible()}
    assert len(shown) == 4
    for title in ("f1", "f2", "f3"):  # each column's lowest (f0 has f3 below it)
        assert shown[title].get_xlabel() == "iteration", title
        assert shown[title].xaxis.get_tick_params()["labelbottom"], title


def test_reproduction_figure_draws_each_row_against_the_papers(tmp_path):
    """One strip per row: the paper's mean +- SD above, ours below (green where it beats the
    paper, red where not), each trial's figure a dot; a row with no mean of ours (every
    trial failed) shows the paper's alone."""
    from matplotlib.colors import to_rgba

    row = dict(key="NH2", experiment="NH2 link length error", unit="mm", paper_mean=2.9, paper_sd=1.7)
    rows = [{**row, "ours_mean": 1.2, "ours_sd": 0.4, "better": True},
            {**row, "key": "spring", "unit": "N m/rad", "paper_mean": 0.0026, "paper_sd": 0.0012,
             "ours_mean": 0.0149, "ours_sd": 0.0129, "better": False},
            {**row, "key": "stack", "ours_mean": 0.6, "ours_sd": 0.5, "better": False, "succeeded": [1, 2]},
            {**row, "key": "NH3", "ours_mean": None, "ours_sd": None, "better": False}]
    fig = plots.make_reproduction_figure(rows, {"NH2": [0.8, 1.2, 1.6, float("nan")]}, title="t")
    axes = fig.axes
    assert len(axes) == 4
    paper, ours = axes[0].lines[0], axes[0].lines[3]  # (each errorbar: its marker line, then its caps)
    assert (paper.get_xdata()[0], paper.get_ydata()[0]) == (2.9, 1.0)
    assert (ours.get_xdata()[0], ours.get_ydata()[0]) == (1.2, 0.0)
    assert to_rgba(ours.get_color()) == to_rgba("tab:green")
    assert to_rgba(axes[1].lines[3].get_color()) == to_rgba("tab:red")
    np.testing.assert_allclose(np.sort(axes[0].collections[-1].get_offsets()[:, 0]), [0.8, 1.2, 1.6])  # NaN left out
    assert axes[0].get_title(loc="left").endswith("(beats the paper)")
    assert axes[1].get_title(loc="left") == "NH2 link length error [N m/rad]  (does not beat the paper)"
    assert axes[2].get_title(loc="left").endswith("(does not beat the paper: 1 of 2 succeeded)")
    assert len(axes[3].lines) == 3 and axes[3].get_title(loc="left") == "NH2 link length error [mm]"  # the paper's alone
    path = plots.plot_reproduction(rows, tmp_path / "r.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(ValueError, match=r"rows\[0\] has no 'better'"):
        plots.make_reproduction_figure([{k: v for k, v in rows[0].items() if k != "better"}])
    with pytest.raises(ValueError, match="rows is empty"):
        plots.make_reproduction_figure([])
