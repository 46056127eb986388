"""The self-identification LeafSystems: ports with FixValue, and the loop under Simulator."""

import numpy as np
import pytest
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.analysis import Simulator

from vlr_drake import filter as pf
from vlr_drake.diagram import build_model_identification_diagram
from vlr_drake.hand import model_o
from vlr_drake.identify import Exploration, IdentifyOptions, _truth_grasp
from vlr_drake.model_plant import ModelPlant
from vlr_drake.systems.self_identification import (
    ExplorationPolicy,
    ModelPlantSystem,
    SelfIdentificationSystem,
)


def _grasp(seed=0):
    h = model_o().model()
    th, a = _truth_grasp(h, np.random.default_rng(seed))
    return h, th, a


def _fixed_filter_system(particles: int, valid: float):
    """A SelfIdentificationSystem on the model plant's grasp, its inputs fixed to the grasp's
    tendon command and POM pose, measured ``valid``: (hand, theta, a, plant, system, context)."""
    h, th, a = _grasp()
    plant = ModelPlant(h, th, a, np.eye(3), np.array([0.0, 0.0, 0.11]), np.random.default_rng(1))
    sys = SelfIdentificationSystem(h, pf.FilterConfig(particles=particles), pf.PriorConfig(), th, a, period_sec=1.0)
    ctx = sys.CreateDefaultContext()
    sys.tendon_command_input_port().FixValue(ctx, plant.state.tendon_command)
    sys.X_PO_measured_input_port().FixValue(ctx, RigidTransform(RotationMatrix(plant.state.R_PO), plant.state.t_PO))
    sys.X_PO_valid_input_port().FixValue(ctx, [valid])
    return h, th, a, plant, sys, ctx


def test_a_small_cloud_is_named_when_the_system_is_made_not_mid_run():
    """The system makes its filter at the first valid measurement, in the middle of a run;
    a FewParticlesWarning comes when the system is made, once."""
    import warnings

    with pytest.warns(pf.FewParticlesWarning, match="500 particles") as record:
        h, th, a, plant, sys, ctx = _fixed_filter_system(500, valid=1.0)
    assert len(record) == 1
    with warnings.catch_warnings():
        warnings.simplefilter("error", pf.FewParticlesWarning)
        sys.ExecuteForcedEvents(ctx)  # the filter is made here, without a second warning
    assert sys.filter(ctx) is not None


def test_filter_system_ports_with_fixvalue():
    # an invalid measurement: the filter waits
    h, th, a, plant, sys, ctx = _fixed_filter_system(500, valid=0.0)
    sys.ExecuteForcedEvents(ctx)
    assert sys.filter(ctx) is None
    assert sys.GetOutputPort("converged").Eval(ctx)[0] == 0.0 and sys.GetOutputPort("started").Eval(ctx)[0] == 0.0
    np.testing.assert_allclose(sys.GetOutputPort("theta_estimate").Eval(ctx), th.ravel())
    # a valid one initialises it around the nominal grasp
    sys.X_PO_valid_input_port().FixValue(ctx, [1.0])
    sys.ExecuteForcedEvents(ctx)
    f = sys.filter(ctx)
    assert f is not None and f.particles.size == 500
    width = sys.GetOutputPort("interval_half_width").Eval(ctx)
    assert width.shape == (6,) and np.all(width > 0)
    # one action and its measurement
    dl = np.array([0.3e-3, 0.2e-3, -0.2e-3])
    assert plant.apply_action(dl)
    sys.tendon_command_input_port().FixValue(ctx, plant.state.tendon_command)
    R, t, _ = plant.measure()
    sys.X_PO_measured_input_port().FixValue(ctx, RigidTransform(RotationMatrix(R), t))
    sys.ExecuteForcedEvents(ctx)
    assert sys.filter(ctx).iteration == 1
    est = sys.GetOutputPort("estimate").Eval(ctx)
    assert set(["theta", "a", "theta_lo", "theta_hi"]) <= set(est)
    assert sys.GetOutputPort("particles").Eval(ctx).size == 500
    assert sys.GetOutputPort("started").Eval(ctx)[0] == 1.0
    # the outputs hand out the filter's own arrays, read-only: a consumer cannot change them
    with pytest.raises(ValueError, match="read-only"):
        est["theta"][...] = 0.0
    with pytest.raises(ValueError, match="read-only"):
        sys.GetOutputPort("particles").Eval(ctx).theta[0] = 0.0
    fallback = est["fallbacks"][0]  # the nearest hypotheses too: their springs are the filter's own array
    assert np.shares_memory(fallback["stiffness"], sys.filter(ctx).particles.stiffness)
    with pytest.raises(ValueError, match="read-only"):
        fallback["stiffness"][...] = 0.0
    np.testing.assert_array_equal(est["theta"], sys.filter(ctx).estimate()["theta"])  # recomputed from the cloud
    assert np.all(sys.filter(ctx).particles.stiffness > 0)
    assert est["measured"] and est["lost_measurements"] == 0
    # a lost tag after the start: the particles move, nothing measured weighs them (only the move's
    # physics: a hypothesis it left unphysical weighs nothing), and the estimate says so
    log_w = sys.filter(ctx).particles.log_w.copy()
    assert plant.apply_action(dl)
    sys.tendon_command_input_port().FixValue(ctx, plant.state.tendon_command)
    sys.X_PO_measured_input_port().FixValue(ctx, RigidTransform(RotationMatrix(np.eye(3)), [np.nan] * 3))
    sys.X_PO_valid_input_port().FixValue(ctx, [0.0])
    sys.ExecuteForcedEvents(ctx)
    f = sys.filter(ctx)
    assert f.iteration == 2 and not f.history[-1].measured and np.all(np.isfinite(f.particles.theta))
    kept = np.isfinite(f.particles.log_w)
    np.testing.assert_array_equal(f.particles.log_w[kept], log_w[kept])
    assert kept.mean() > 0.9
    est = sys.GetOutputPort("estimate").Eval(ctx)
    assert not est["measured"] and est["lost_measurements"] == 1 and np.all(np.isfinite(est["theta"]))
    assert not est["reinitialised"] and est["reinitialisations"] == 0
    # the object swapped (the POM 20 mm away, turned 30 deg): the cloud is drawn again and the
    # estimate says so, for a consumer that would otherwise see only the estimate jump
    R_far = RotationMatrix.MakeYRotation(np.deg2rad(30)) @ RotationMatrix(R)
    sys.X_PO_measured_input_port().FixValue(ctx, RigidTransform(R_far, t + np.array([0.02, 0.0, 0.0])))
    sys.X_PO_valid_input_port().FixValue(ctx, [1.0])
    sys.ExecuteForcedEvents(ctx)
    est = sys.GetOutputPort("estimate").Eval(ctx)
    assert est["reinitialised"] and est["reinitialisations"] == 1 and est["measured"]
    # a validity that is no number is refused, naming the input, not read as a lost tag
    sys.X_PO_valid_input_port().FixValue(ctx, [np.nan])
    with pytest.raises(ValueError, match="input 'X_PO_valid' must be 0 or 1"):
        sys.ExecuteForcedEvents(ctx)


def test_a_cloned_context_shares_the_records_entries_not_their_lists():
    """Drake clones the filter's state at every update: the records that only grow (history,
    estimates, the trace's steps) are new lists of the same entries, the rest deep copies;
    an update in the clone leaves the original as it was."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", pf.FewParticlesWarning)
        h, th, a, plant, sys, ctx = _fixed_filter_system(300, valid=1.0)
    for _ in range(3):
        sys.ExecuteForcedEvents(ctx)
    clone = ctx.Clone()
    f, g = sys.filter(ctx), sys.filter(clone)
    assert g is not f and g.particles.theta is not f.particles.theta
    np.testing.assert_array_equal(g.particles.theta, f.particles.theta)
    for mine, theirs in ((f.history, g.history), (f.estimates, g.estimates)):
        assert theirs is not mine and len(theirs) == len(mine) and all(x is y for x, y in zip(mine, theirs, strict=True))
    for mine, theirs in zip(context_box(ctx).recorder.records(), context_box(clone).recorder.records(), strict=True):
        assert theirs is not mine and len(theirs) == len(mine) and all(x is y for x, y in zip(mine, theirs, strict=True))
    sys.ExecuteForcedEvents(clone)
    assert sys.filter(clone).iteration == f.iteration + 1 and len(sys.filter(clone).history) == len(f.history) + 1
    assert sys.filter(ctx).iteration == f.iteration == 2 and len(f.history) == 2 and len(f.estimates) == 3
    assert len(sys.trace(clone).actions) == 3 and len(sys.trace(ctx).actions) == 2


def context_box(ctx):
    """A SelfIdentificationSystem's abstract state in its ``ctx``: the filter and its trace
    recorder."""
    return ctx.get_abstract_state(0).get_value()


def test_the_policy_holds_the_grasp_until_the_filter_has_started():
    """Lost measurements at the grasp (the model plant's dropout): the filter starts late, and
    the hand has not moved by then, so the prior drawn around the grasp holds the truth (the
    policy had acted from T on, whatever the filter, and moved the hand away from it)."""
    h, th, a = _grasp()
    for seed in range(20):
        plant = ModelPlant(h, th, a, np.eye(3), np.array([0.0, 0.0, 0.11]), np.random.default_rng(1))
        b = build_model_identification_diagram(h, plant, pf.FilterConfig(particles=300), pf.PriorConfig(), th, a,
                                               dropout=0.6, seed=seed)
        sim = Simulator(b.diagram)
        ctx = sim.get_mutable_context()
        sim.Initialize()
        fctx = b.filter.GetMyContextFromRoot(ctx)
        k = 0
        while b.filter.filter(fctx) is None and k < 10:
            k += 1
            sim.AdvanceTo(k)  # the filter updates at 0.9 T of each period
            if b.filter.filter(fctx) is None:
                np.testing.assert_array_equal(b.diagram.GetOutputPort("exploration.tendon_command").Eval(ctx),
                                              b.l_grasp)
        if k > 1:  # this seed lost the first measurement: the filter started at period k
            f = b.filter.filter(fctx)
            assert f is not None and f.tendon_command.tolist() == b.l_grasp.tolist()
            break
    else:
        pytest.fail("no seed lost its first measurement")


def test_systems_refuse_bad_seeds_and_offsets():
    h, th, a = _grasp()
    for seed in (-1, 2.9):
        with pytest.raises(ValueError, match=rf"'seed' must be an integer >= 0, got {seed}"):
            ExplorationPolicy(h, np.full(3, 0.015), 1.0, seed=seed)
        with pytest.raises(ValueError, match=rf"'seed' must be an integer >= 0, got {seed}"):
            SelfIdentificationSystem(h, pf.FilterConfig(particles=3000), pf.PriorConfig(), th, a, 1.0, seed=seed)
    with pytest.raises(ValueError, match=r"'offset_sec' must be None or in \[0, period_sec"):
        SelfIdentificationSystem(h, pf.FilterConfig(particles=3000), pf.PriorConfig(), th, a, 1.0, offset_sec=5.0)


def _commands(policy, n: int) -> np.ndarray:
    """The policy's first ``n`` commands (n, N), each read half a period after it."""
    sim = Simulator(policy)
    out = []
    for k in range(1, n + 1):
        sim.AdvanceTo(k + 0.5)
        out.append(policy.GetOutputPort("tendon_command").Eval(sim.get_context()).copy())
    return np.array(out)


def test_exploration_policy_stays_in_its_window():
    h, th, a = _grasp()
    l0 = np.full(3, 0.015)
    ls = _commands(ExplorationPolicy(h, l0, period_sec=1.0, span=1.5e-3, window=4e-3, seed=3), 59)
    assert np.all(np.abs(ls - l0) <= 4e-3 + 1e-12)
    steps = np.abs(np.diff(ls, axis=0))
    assert steps.max() <= 1.5e-3 + 1e-12 and steps.mean() > 2e-4  # it does explore
    # a hardware hand's motor limits, narrower than the window: kept to (the policy had walked
    # past them, 0.8 mm, while the interface clipped what reached the motors)
    limits = np.column_stack([l0 - 0.4e-3, l0 + 0.4e-3])
    ls = _commands(ExplorationPolicy(h, l0, period_sec=1.0, span=1.5e-3, window=4e-3, seed=3, limits=limits), 39)
    assert np.all((ls >= limits[:, 0] - 1e-12) & (ls <= limits[:, 1] + 1e-12)) and np.ptp(ls, axis=0).min() > 4e-4
    # a grasp outside the limits is named: the policy had jumped to the limit in one action
    # (5 mm, against a 1.5 mm span) and stayed there, its window collapsed, exploring nothing
    with pytest.raises(ValueError, match=r"'l_grasp' \[15.0, 15.0, 15.0\] mm is outside the tendon limits"):
        ExplorationPolicy(h, l0, period_sec=1.0, limits=np.column_stack([np.zeros(3), np.full(3, 0.010)]))


def _simulated_identification(seed: int):
    """The model plant's identification diagram on the Model O's truth grasp of ``seed``,
    simulated 15.5 s (14 action periods): (diagram, simulator, context, the plant's state)."""
    h, th, a = _grasp(seed)
    plant = ModelPlant(h, th, a, np.eye(3), np.array([0.0, 0.0, 0.11]), np.random.default_rng(1))
    d = build_model_identification_diagram(h, plant, pf.FilterConfig(particles=3000), pf.PriorConfig(),
                                           th + 0.04, a + 0.002, period_sec=1.0, seed=5)
    sim = Simulator(d.diagram)
    ctx = sim.get_mutable_context()
    width = d.diagram.GetOutputPort("self_identification.interval_half_width")
    sim.AdvanceTo(1.5)
    w0 = width.Eval(ctx).mean()
    sim.AdvanceTo(15.5)
    return d, sim, ctx, w0


def test_identification_loop_under_the_simulator():
    d, sim, ctx, w0 = _simulated_identification(0)
    theta_true = d.diagram.GetOutputPort("hand.theta_true")
    theta_est = d.diagram.GetOutputPort("self_identification.theta_estimate")
    width = d.diagram.GetOutputPort("self_identification.interval_half_width")
    f = d.filter.filter(d.filter.GetMyContextFromRoot(ctx))
    assert f.iteration == 14  # one filter iteration per action period
    assert width.Eval(ctx).mean() < 0.6 * w0  # it learns (0.50 of the first width in this run)
    # The estimate against the truth it describes: the plant moved at 15.25 s, the filter
    # steps at 15.9 s (at 15.5 s the truth is an action ahead of the estimate). It is nearer
    # than the prior's centre (0.04 rad off every joint; 0.026 rad on average here) and its
    # 95% intervals hold it (all 6 joints here).
    sim.AdvanceTo(15.95)
    error = np.abs(theta_est.Eval(ctx) - theta_true.Eval(ctx))
    assert error.mean() < 0.04
    assert np.sum(error <= width.Eval(ctx)) >= 5


def test_a_refused_action_leaves_the_model_plant_where_it_was():
    """The plant holds the policy's command: a refused action (where the model has no
    equilibrium: 9 of 14 on seed 2's grasp, near a fold) leaves the plant where it was, and
    the next period's command, an absolute pull, takes it there (this run's last action
    was made). (Seed 2's truth grasp had been no equilibrium until the fifty-fifth session.)"""
    d, sim, ctx, _ = _simulated_identification(2)
    plant = d.plant._p(d.plant.GetMyContextFromRoot(ctx))
    assert 0 < plant.failures < 14
    np.testing.assert_allclose(d.diagram.GetOutputPort("exploration.tendon_command").Eval(ctx),
                               plant.state.tendon_command)


def test_squeeze_exploration_splits_common_and_differential_modes():
    """With a squeeze the commands' offset from the grasp is a common mode (mean over the
    tendons) inside +-squeeze_window, walking by at most +-squeeze per action, and a
    differential mode inside +-window; every command stays in the tendon range."""
    h = model_o().model()
    l0 = np.full(3, 0.015)
    ex = Exploration(l0, h.tendon_range, 0.5e-3, 1.2e-3, np.random.default_rng(4), squeeze=1.5e-3,
                     squeeze_window=3e-3)
    common, diff = [0.0], []
    for _ in range(400):
        dl = ex.next_action()
        ex.commit(dl)
        u = ex.l - l0
        common.append(u.mean())
        diff.append(u - u.mean())
        assert np.all(ex.l >= h.tendon_range[:, 0]) and np.all(ex.l <= h.tendon_range[:, 1])
    common, diff = np.array(common), np.array(diff)
    assert np.all(np.abs(common) <= 3e-3 + 1e-12) and np.all(np.abs(diff) <= 1.2e-3 + 1e-12)
    assert np.abs(np.diff(common)).max() <= 1.5e-3 + 1e-12
    assert common.max() > 2e-3 and common.min() < -2e-3  # it squeezes and releases across the window
    assert np.abs(diff).max() > 0.8e-3  # and still moves the object


def test_exploration_without_squeeze_keeps_its_draws():
    """squeeze = 0 is the plain per-tendon walk, draw for draw."""
    h = model_o().model()
    l0 = np.full(3, 0.015)
    a = Exploration(l0, h.tendon_range, 0.5e-3, 1.2e-3, np.random.default_rng(9))
    rng = np.random.default_rng(9)
    l = l0.copy()
    for _ in range(50):
        dl = a.next_action()
        a.commit(dl)
        want = l + rng.uniform(-0.5e-3, 0.5e-3, 3)
        hi, lo = l0 + 1.2e-3, l0 - 1.2e-3
        want = np.clip(np.where(want < lo, 2 * lo - want, np.where(want > hi, 2 * hi - want, want)), lo, hi)
        np.testing.assert_allclose(a.l, want, atol=1e-15)
        l = want


@pytest.mark.parametrize("squeeze, window", [(1e-3, 0.0), (-1e-3, 2e-3), (0.0, 2e-3)])
def test_bad_squeeze_settings_are_named(squeeze, window):
    h = model_o().model()
    with pytest.raises(ValueError, match="squeeze"):
        Exploration(np.full(3, 0.015), h.tendon_range, 0.5e-3, 1.2e-3, np.random.default_rng(0), squeeze, window)
    with pytest.raises(ValueError, match="squeeze"):
        ExplorationPolicy(h, np.full(3, 0.015), 1.0, 0.5e-3, 1.2e-3, squeeze=squeeze, squeeze_window=window)
    with pytest.raises(ValueError, match="squeeze_range"):
        IdentifyOptions(squeeze_range=squeeze, squeeze_window=window).validate()


def test_exploration_policy_squeezes_by_its_settings():
    h = model_o().model()
    l0 = np.full(3, 0.015)
    pol = ExplorationPolicy(h, l0, period_sec=1.0, span=0.5e-3, window=1.2e-3, seed=3, squeeze=1.5e-3,
                            squeeze_window=3e-3)
    sim = Simulator(pol)
    u = []
    for k in range(1, 80):
        sim.AdvanceTo(k + 0.5)
        u.append(pol.GetOutputPort("tendon_command").Eval(sim.get_context()) - l0)
    common = np.array(u).mean(axis=1)
    assert np.abs(common).max() > 1.5e-3 and np.all(np.abs(common) <= 3e-3 + 1e-12)


# ------------------------------------------------------------------ bad input and failures


def test_model_plant_system_refuses_a_non_finite_command():
    """The physics plant's TendonForces refuses a NaN command; the model plant used to skip
    it (|NaN| > 0 is False) and keep reporting its old tendon position as measured."""
    h, th, a = _grasp()
    plant = ModelPlant(h, th, a, np.eye(3), np.array([0.0, 0.0, 0.11]), np.random.default_rng(1))
    sys = ModelPlantSystem(plant, 1.0)
    sim = Simulator(sys)
    sys.GetInputPort("tendon_command").FixValue(sim.get_mutable_context(), np.full(h.N, np.nan))
    with pytest.raises(ValueError, match="tendon_command"):
        sim.AdvanceTo(1.5)


def test_model_plant_system_counts_the_actions_it_refuses():
    """A command the model plant has no nearby equilibrium for (the thumb's tendon 5 mm
    tighter on this grasp) leaves it where it was, its measured tendon positions unchanged,
    and is counted (a diagram run's ``actions_refused``; it had gone unreported); a possible
    one is taken and not counted."""
    h, th, a = _grasp()
    plant = ModelPlant(h, th, a, np.eye(3), np.array([0.0, 0.0, 0.11]), np.random.default_rng(1))
    l0 = plant.state.tendon_command.copy()
    far, near = np.array([5e-3, 0.0, 0.0]), np.array([1e-3, 0.0, 0.0])
    assert plant.possible_actions(np.stack([far, near])).tolist() == [False, True]
    sys = ModelPlantSystem(plant, 1.0)
    sim = Simulator(sys)
    ctx = sim.get_mutable_context()
    sys.GetInputPort("tendon_command").FixValue(ctx, l0 + far)
    sim.AdvanceTo(2.5)  # three updates (at 0.25, 1.25, 2.25 s), each refused
    assert sys.refused(ctx) == 3
    np.testing.assert_array_equal(sys.GetOutputPort("tendon_position_measured").Eval(ctx), l0)
    np.testing.assert_array_equal(sys.GetOutputPort("theta_true").Eval(ctx), th.ravel())
    sys.GetInputPort("tendon_command").FixValue(ctx, l0 + near)
    sim.AdvanceTo(3.5)
    assert sys.refused(ctx) == 3
    np.testing.assert_allclose(sys.GetOutputPort("tendon_position_measured").Eval(ctx), l0 + near, atol=1e-15)


def test_a_drifting_contact_is_no_new_action_for_the_model_plant_system():
    """With contact_drift the model plant restates its own tendon command after each move
    (l = R theta + stretch stays true). The system had read that against the command it was
    given as a new action, so a held command moved the plant again every period; one move
    per command now, as vlr-drake identify makes."""
    h, th, a = _grasp()
    plant = ModelPlant(h, th, a, np.eye(3), np.array([0.0, 0.0, 0.11]), np.random.default_rng(1),
                       contact_drift=0.5e-3)
    l0 = plant.state.tendon_command.copy()
    sys = ModelPlantSystem(plant, 1.0)
    sim = Simulator(sys)
    ctx = sim.get_mutable_context()
    sys.GetInputPort("tendon_command").FixValue(ctx, l0 + np.array([0.5e-3, -0.3e-3, 0.2e-3]))
    sim.AdvanceTo(0.5)  # the move, then the drift
    theta = sys.GetOutputPort("theta_true").Eval(ctx).copy()
    l_drifted = sys.GetOutputPort("tendon_position_measured").Eval(ctx).copy()
    assert np.abs(l_drifted - (l0 + np.array([0.5e-3, -0.3e-3, 0.2e-3]))).max() > 1e-5  # the restated command
    sim.AdvanceTo(3.5)  # three more updates with the command held
    np.testing.assert_array_equal(sys.GetOutputPort("theta_true").Eval(ctx), theta)
    np.testing.assert_array_equal(sys.GetOutputPort("tendon_position_measured").Eval(ctx), l_drifted)
    assert sys.refused(ctx) == 0


@pytest.mark.parametrize("l_grasp, match", [(np.full(3, np.nan), "finite"), (np.full(2, 0.015), "shape")])
def test_exploration_refuses_a_bad_grasp_command(l_grasp, match):
    """A NaN grasp command used to give NaN tendon commands on the policy's output; a
    wrong-sized one a numpy broadcasting error."""
    h = model_o().model()
    with pytest.raises(ValueError, match=f"l_grasp.*{match}"):
        Exploration(l_grasp, h.tendon_range, 0.5e-3, 1.2e-3, np.random.default_rng(0))
    with pytest.raises(ValueError, match=f"l_grasp.*{match}"):
        ExplorationPolicy(h, l_grasp, 1.0)


@pytest.mark.parametrize("span, window", [(np.nan, 1e-3), (1e-3, -1e-3), (-1e-3, 1e-3), (1e-3, np.inf)])
def test_exploration_refuses_bad_span_and_window(span, window):
    h = model_o().model()
    with pytest.raises(ValueError, match="span|window"):
        Exploration(np.full(3, 0.015), h.tendon_range, span, window, np.random.default_rng(0))


def test_filter_system_checks_its_nominal_grasp_at_construction():
    h, th, a = _grasp()
    cfg, prior = pf.FilterConfig(particles=200), pf.PriorConfig()
    with pytest.raises(ValueError, match=r"theta_center.*\(3, 2\)"):  # was numpy's "cannot reshape"
        SelfIdentificationSystem(h, cfg, prior, th[:2], a, period_sec=1.0)
    with pytest.raises(ValueError, match="theta_center.*finite"):  # was refused only at the first measurement
        SelfIdentificationSystem(h, cfg, prior, th * np.nan, a, period_sec=1.0)
    with pytest.raises(ValueError, match="a_center"):
        SelfIdentificationSystem(h, cfg, prior, th, np.full(3, np.inf), period_sec=1.0)
    with pytest.raises(ValueError, match="'a_center' must lie along the last links"):  # mm for m: was refused
        SelfIdentificationSystem(h, cfg, prior, th, a * 1000, period_sec=1.0)  # only at the first measurement


def test_filter_system_names_a_non_finite_tendon_command_port():
    """It used to fail inside the filter with "'dl' contains NaN", a name the diagram
    does not have."""
    h, *_, sys, ctx = _fixed_filter_system(200, valid=1.0)
    sys.ExecuteForcedEvents(ctx)
    assert sys.filter(ctx) is not None
    sys.tendon_command_input_port().FixValue(ctx, np.full(h.N, np.nan))
    with pytest.raises(ValueError, match="input 'tendon_command'"):
        sys.ExecuteForcedEvents(ctx)
    assert sys.filter(ctx).iteration == 0  # nothing moved


@pytest.mark.parametrize("period, offset", [(np.inf, None), (np.nan, None), (0.0, None), (1.0, np.nan), (1.0, -0.1),
                                            (1.0, np.inf)])
def test_periodic_systems_name_a_bad_period_or_offset(period, offset):
    """A period or offset that is not a finite time is named at construction, by each of the
    three periodic systems (an infinite period or a NaN offset used to be accepted)."""
    h, th, a = _grasp()
    plant = ModelPlant(h, th, a, np.eye(3), np.array([0.0, 0.0, 0.11]), np.random.default_rng(1))
    name = "period_sec" if offset is None else "offset_sec"
    with pytest.raises(ValueError, match=f"'{name}' must be"):
        SelfIdentificationSystem(h, pf.FilterConfig(particles=200), pf.PriorConfig(), th, a, period_sec=period,
                                 offset_sec=offset)
    with pytest.raises(ValueError, match=f"'{name}' must be"):
        ModelPlantSystem(plant, period_sec=period, offset_sec=offset)
    if offset is None:
        with pytest.raises(ValueError, match="'period_sec' must be"):
            ExplorationPolicy(h, plant.state.tendon_command, period_sec=period)
