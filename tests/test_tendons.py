"""TendonForces: T = kappa max(0, l - R theta) (+ damping), tau = R^T T, clamping, ramp."""

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator

from vlr_drake.hand import generic_hand, model_o
from vlr_drake.systems.tendons import TendonForces, tendon_tension

# A fake plant layout: 2 extra positions/velocities before the joints (e.g. an object's),
# joints stored in reverse order, so the index mapping is exercised.
EXTRA = 2


def _system(hand, ramp_time=0.2, damping=None):
    nk = hand.num_angles
    qi = EXTRA + np.arange(nk)[::-1]
    vi = EXTRA + np.arange(nk)[::-1]
    nq = nv = EXTRA + nk
    return (
        TendonForces(hand, qi, vi, nq, nv, ramp_time=ramp_time, update_period=0.001, damping=damping),
        qi,
        vi,
    )


def _state(qi, vi, theta, theta_dot=None):
    n = EXTRA + len(theta)
    x = np.zeros(2 * n)
    x[qi] = theta
    if theta_dot is not None:
        x[n + vi] = theta_dot
    return x


def test_force_is_R_transpose_T_on_the_joints():
    hand = model_o().model()
    sys, qi, vi = _system(hand, damping=[0.0] * hand.N)
    ctx = sys.CreateDefaultContext()
    rng = np.random.default_rng(0)
    theta = rng.uniform(0.4, 0.8, hand.num_angles)
    l = hand.R @ theta + np.array([0.01, -0.002, 0.004])  # finger 1 slack
    assert np.all(l > hand.tendon_range[:, 0])
    sys.set_applied(ctx, l)
    sys.tendon_command_input.FixValue(ctx, l)
    sys.state_input.FixValue(ctx, _state(qi, vi, theta))
    T = sys.tension_output.Eval(ctx)
    expected_T = hand.kappa * np.maximum(0.0, l - hand.R @ theta)
    np.testing.assert_allclose(T, expected_T, rtol=1e-12)
    assert T[1] == 0.0 and T[0] == pytest.approx(2000.0 * 0.01)
    tau = sys.generalized_force_output.Eval(ctx)
    assert tau.shape == (EXTRA + hand.num_angles,)
    np.testing.assert_allclose(tau[vi], hand.R.T @ expected_T, rtol=1e-12)
    np.testing.assert_array_equal(tau[:EXTRA], 0.0)
    np.testing.assert_allclose(sys.tendon_position_output.Eval(ctx), l)


def test_the_outputs_do_not_feed_the_command_through():
    """The command reaches the tendons through the ramp's update, not at once: the tension and
    force outputs depend on the state input, not on the command (declared so, they had made a
    false direct feedthrough, an algebraic loop for a tension-feedback controller)."""
    hand = model_o().model()
    sys, qi, vi = _system(hand)
    command, state = sys.tendon_command_input.get_index(), sys.state_input.get_index()
    for out in (sys.tension_output, sys.generalized_force_output, sys.tendon_position_output):
        assert not sys.HasDirectFeedthrough(command, out.get_index()), out.get_name()
    assert sys.HasDirectFeedthrough(state, sys.tension_output.get_index())
    ctx = sys.CreateDefaultContext()
    theta = np.full(hand.num_angles, 0.5)
    sys.state_input.FixValue(ctx, _state(qi, vi, theta))
    sys.tendon_command_input.FixValue(ctx, hand.tendon_range[:, 0])
    before = sys.tension_output.Eval(ctx).copy()
    sys.tendon_command_input.FixValue(ctx, hand.tendon_range[:, 1])  # a new command: nothing until the update
    np.testing.assert_array_equal(sys.tension_output.Eval(ctx), before)


def test_tension_never_negative_with_damping():
    """A fast-flexing finger (stretch shrinking) must not push: T >= 0, and a slack tendon
    carries nothing whatever its rate."""
    hand = generic_hand(4, 3).model()
    sys, qi, vi = _system(hand, damping=[50.0] * hand.N)
    ctx = sys.CreateDefaultContext()
    rng = np.random.default_rng(1)
    for _ in range(50):
        theta = rng.uniform(0.0, 1.0, hand.num_angles)
        theta_dot = rng.uniform(-20.0, 20.0, hand.num_angles)
        l = np.clip(hand.R @ theta + rng.uniform(-0.003, 0.003, hand.N), *hand.tendon_range.T)
        sys.set_applied(ctx, l)
        sys.tendon_command_input.FixValue(ctx, l)
        sys.state_input.FixValue(ctx, _state(qi, vi, theta, theta_dot))
        T = sys.tension_output.Eval(ctx)
        assert np.all(T >= 0.0)
        s = l - hand.R @ theta
        assert np.all(T[s <= 0] == 0.0)
        expected = np.where(s > 0, np.maximum(0.0, hand.kappa * s - 50.0 * (hand.R @ theta_dot)), 0.0)
        np.testing.assert_allclose(T, expected, rtol=1e-12, atol=1e-12)
    # The pure function agrees.
    np.testing.assert_allclose(tendon_tension(hand, l, theta, theta_dot, None, np.full(hand.N, 50.0)), T)


def test_ramp_is_linear_and_clamped_to_the_range():
    hand = model_o().model()
    sys, qi, vi = _system(hand, ramp_time=0.2)
    ctx = sys.CreateDefaultContext()
    l0 = np.array([0.01, 0.012, 0.014])
    sys.set_applied(ctx, l0)
    sys.state_input.FixValue(ctx, _state(qi, vi, np.zeros(hand.num_angles)))
    # The last tendon is commanded past its upper limit: it must stop at the limit.
    hi = hand.tendon_range[:, 1]
    cmd = np.array([0.02, 0.002, hi[2] + 0.05])
    target = np.array([0.02, 0.002, hi[2]])
    sys.tendon_command_input.FixValue(ctx, cmd)
    sim = Simulator(sys, ctx)
    sim.Initialize()
    sim.AdvanceTo(0.1)
    l_half = sys.tendon_position_output.Eval(ctx)
    np.testing.assert_allclose(l_half, l0 + 0.5 * (target - l0), atol=0.01 * np.max(np.abs(target - l0)))
    sim.AdvanceTo(0.25)
    np.testing.assert_allclose(sys.tendon_position_output.Eval(ctx), target, atol=1e-12)
    assert np.all(sys.tendon_position_output.Eval(ctx) <= hi)
    # A new command after the ramp ramps from the reached pull, over ramp_time again ...
    sys.tendon_command_input.FixValue(ctx, l0)
    sim.AdvanceTo(0.35)
    middle = target + 0.5 * (l0 - target)
    np.testing.assert_allclose(sys.tendon_position_output.Eval(ctx), middle, atol=0.01 * np.max(np.abs(target - l0)))
    # ... and one that comes mid-ramp ramps from where the pull is then, not from the old start
    middle = sys.tendon_position_output.Eval(ctx).copy()
    sys.tendon_command_input.FixValue(ctx, target)
    sim.AdvanceTo(0.45)
    np.testing.assert_allclose(sys.tendon_position_output.Eval(ctx), middle + 0.5 * (target - middle),
                               atol=0.01 * np.max(np.abs(target - l0)))
    sim.AdvanceTo(0.56)
    np.testing.assert_allclose(sys.tendon_position_output.Eval(ctx), target, atol=1e-12)


def test_clamp_validates_shape():
    hand = model_o().model()
    sys, _, _ = _system(hand)
    with pytest.raises(ValueError, match="tendon_command"):
        sys.clamp(np.zeros(4))
    np.testing.assert_allclose(
        sys.clamp(np.array([-1.0, 0.01, 1.0])), [hand.tendon_range[0, 0], 0.01, hand.tendon_range[2, 1]]
    )


def test_bad_indices_raise():
    hand = model_o().model()
    with pytest.raises(ValueError, match="position_indices"):
        TendonForces(hand, np.arange(5), np.arange(6), 6, 6)
    # negative or repeated indices would read another coordinate ([q; v] wraps round)
    for qi, vi, name in ((np.arange(6) - 1, np.arange(6), "position_indices"),
                         (np.arange(6), np.array([0, 1, 2, 3, 4, 4]), "velocity_indices")):
        with pytest.raises(ValueError, match=f"{name} must be distinct indices"):
            TendonForces(hand, qi, vi, 6, 6)
    # a damping of NaN gave NaN joint torques, an infinite ramp never moved (a review)
    with pytest.raises(ValueError, match="damping must have 3 finite, non-negative entries"):
        _system(hand, damping=[50.0, np.nan, 50.0])
    for ramp_time, period in ((np.inf, 0.001), (0.2, np.inf), (-0.1, 0.001)):
        with pytest.raises(ValueError, match="ramp_time must be finite and >= 0 and update_period finite"):
            TendonForces(hand, np.arange(6), np.arange(6), 6, 6, ramp_time=ramp_time, update_period=period)


def test_damping_follows_the_ramp_rate_and_the_time():
    """Mid-ramp the damping term carries the ramp's rate: the tension at a time inside the
    ramp, and after it, from one context whose time is set (the output depends on time)."""
    hand = model_o().model()
    c = 50.0
    sys, qi, vi = _system(hand, ramp_time=0.2, damping=[c] * hand.N)
    ctx = sys.CreateDefaultContext()
    theta = np.full(hand.num_angles, 0.3)
    l0 = hand.R @ theta + 0.003
    sys.set_applied(ctx, l0)
    sys.state_input.FixValue(ctx, _state(qi, vi, theta))
    l1 = l0 + 0.002
    sys.tendon_command_input.FixValue(ctx, l1)
    sim = Simulator(sys, ctx)
    sim.Initialize()
    sim.AdvanceTo(0.1)  # mid-ramp: pull rate (l1 - l0) / 0.2
    l = sys.tendon_position_output.Eval(ctx)
    rate = (l1 - l0) / 0.2
    np.testing.assert_allclose(sys.tension_output.Eval(ctx), hand.kappa * (l - hand.R @ theta) + c * rate, rtol=1e-9)
    ctx.SetTime(0.5)  # the same ramp state read past the ramp's end: no rate any more
    np.testing.assert_allclose(sys.tension_output.Eval(ctx), hand.kappa * (l - hand.R @ theta), rtol=1e-9)
