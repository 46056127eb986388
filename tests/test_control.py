"""Tests of the Jacobian controller (vlr_drake.control) and its LeafSystems."""

import copy
import dataclasses
import inspect

import numpy as np
import pytest
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource

from vlr_drake import control, observation
from vlr_drake.systems.controller import EstimateFromTruth, JacobianController, TaskTrajectorySource
from vlr_drake.systems.self_identification import ModelPlantSystem
from vlr_drake.tasks import common


@pytest.fixture(scope="module")
def grasp():
    return common.make_model_plant(0, sigma_position=0.0, sigma_rotation_deg=0.0)


def fresh(grasp, sigma_position=0.0, sigma_rotation_deg=0.0, seed=5):
    pl = copy.deepcopy(grasp.plant)
    pl.sigma_position, pl.sigma_rotation = sigma_position, np.deg2rad(sigma_rotation_deg)
    pl.rng = np.random.default_rng(seed)
    return pl


class RecordingPlant:
    """A model plant that records every tendon command it is given."""

    def __init__(self, plant):
        self.plant, self.hand, self.commands = plant, plant.hand, []

    @property
    def state(self):
        return self.plant.state

    def apply_action(self, dl):
        ok = self.plant.apply_action(dl)
        self.commands.append(self.plant.state.tendon_command.copy())
        return ok

    def measure(self):
        return self.plant.measure()


def reachable_goal(grasp, dl):
    """The true pose after the action dl (halved until the plant can make it): reachable by
    construction."""
    for _ in range(6):
        pl = fresh(grasp)
        if pl.apply_action(dl):
            return pl.state.R_PO.copy(), pl.state.t_PO.copy()
        dl = 0.5 * np.asarray(dl)
    raise AssertionError(f"the plant cannot make the action {dl}")


def two_sided_action(grasp):
    """An action the plant can make in both directions (from a few candidates)."""
    for dl in (
        [1e-3, 0.5e-3, -1e-3],
        [-1e-3, 1e-3, 0.0],
        [1e-3, -1e-3, 1e-3],
        [0.5e-3, 0.25e-3, -0.5e-3],
        [0.5e-3, -0.5e-3, 0.0],
        [0.0, 0.5e-3, -0.5e-3],
    ):
        dl = np.array(dl)
        if fresh(grasp).apply_action(dl) and fresh(grasp).apply_action(-dl):
            return dl
    raise AssertionError("no two-sided action for this grasp")


def weighted(e, rows, alpha=1.0):
    w = control.row_weights(rows, alpha, control.POSITION_UNIT, control.ROTATION_UNIT)
    return np.linalg.norm(w * e)


def test_upsilon_zero_action_is_zero_motion(grasp):
    m = control.ControlModel.from_plant_truth(grasp.plant)
    np.testing.assert_allclose(control.upsilon(m, np.zeros(grasp.hand.N)), 0.0, atol=1e-6)


def test_jacobian_matches_direct_perturbation_of_the_model(grasp):
    """Eq. 10: each column equals the central difference of the true plant's pose."""
    m = control.ControlModel.from_plant_truth(grasp.plant)
    J = control.jacobian(m, eps=0.05e-3)
    h = 0.05e-3
    for i in range(grasp.hand.N):
        poses = []
        for s in (+1, -1):
            pl = fresh(grasp)
            dl = np.zeros(grasp.hand.N)
            dl[i] = s * h
            assert pl.apply_action(dl)
            poses.append((pl.state.R_PO.copy(), pl.state.t_PO.copy()))
        (Rp, tp), (Rm, tm) = poses
        R0 = grasp.plant.state.R_PO
        col = np.concatenate(
            [
                (tp - tm) / (2 * h),
                (observation.rotvec(Rp @ R0.T)[0] - observation.rotvec(Rm @ R0.T)[0]) / (2 * h),
            ]
        )
        np.testing.assert_allclose(J[:, i], col, rtol=1e-4, atol=1e-5)
    # the columns are not trivial
    assert np.linalg.norm(J[:3]) > 0.1 and np.linalg.norm(J[3:]) > 1.0


def test_jacobian_predicts_a_small_action(grasp):
    m = control.ControlModel.from_plant_truth(grasp.plant)
    J = control.jacobian(m)
    dl = np.array([0.1e-3, -0.05e-3, 0.08e-3])
    pred = J @ dl  # linear prediction; the motion is mildly nonlinear over 0.1 mm
    np.testing.assert_allclose(control.upsilon(m, dl), pred, atol=0.05 * np.abs(pred).max())


@pytest.mark.parametrize("rows", control.ROWS)
@pytest.mark.parametrize("mode", control.MODES)
def test_control_step_reduces_the_error_on_the_model_plant(grasp, rows, mode):
    R_goal, t_goal = reachable_goal(grasp, np.array([0.6e-3, -0.4e-3, 0.5e-3]))
    pl = fresh(grasp)
    e0 = control.pose_error6(R_goal, t_goal, pl.state.R_PO, pl.state.t_PO)
    m = control.ControlModel.from_plant_truth(pl)
    dl = control.control_step(control.jacobian(m), e0, mode=mode, rows=rows)
    assert np.max(np.abs(dl)) > 0
    assert pl.apply_action(dl)
    e1 = control.pose_error6(R_goal, t_goal, pl.state.R_PO, pl.state.t_PO)
    assert weighted(e1, rows) < 0.7 * weighted(e0, rows)


@pytest.mark.parametrize("rows", control.ROWS)
def test_servo_reaches_a_reachable_goal(grasp, rows):
    R_goal, t_goal = reachable_goal(grasp, np.array([-0.8e-3, 0.5e-3, 0.3e-3]))
    pl = fresh(grasp)
    rep = control.servo_to(
        R_goal,
        t_goal,
        pl,
        control.true_model_fn(pl),
        rows=rows,
        tol_position=0.01e-3,
        tol_rotation=np.deg2rad(0.02),
        max_steps=30,
    )
    assert rep.reached and rep.reason == "reached", rep.summary()
    if rows != "orientation":
        assert np.linalg.norm(pl.state.t_PO - t_goal) < 0.02e-3
    if rows != "position":
        assert observation.rotation_angle(R_goal[None], pl.state.R_PO[None])[0] < np.deg2rad(0.05)


def test_true_model_handwriting_segment_reaches_each_waypoint_within_0p1_mm(grasp):
    from vlr_drake.tasks.write import writing_plane

    pl = fresh(grasp)
    m = control.ControlModel.from_plant_truth(pl)
    x, y, _ = writing_plane(control.jacobian(m))
    t0 = pl.state.t_PO.copy()
    # a short stroke: 1.5 mm diagonal in the writing plane, waypoints every 0.3 mm
    for s in np.linspace(0.3e-3, 1.5e-3, 5):
        goal = t0 + s * (-x + y) / np.sqrt(2)
        rep = control.servo_to(
            np.eye(3),
            goal,
            pl,
            control.true_model_fn(pl),
            rows="position",
            tol_position=0.02e-3,
            max_steps=15,
        )
        assert np.linalg.norm(pl.state.t_PO - goal) < 0.1e-3, rep.summary()


def test_alpha_trades_position_for_orientation(grasp):
    """Eq. 12: a goal the tendon range cannot reach in full (orientation from one action,
    position from the opposite one, range +-half the action); larger alpha, smaller rotation error,
    larger position error."""
    dl_goal = two_sided_action(grasp)
    R_goal, _ = reachable_goal(grasp, dl_goal)
    _, t_goal = reachable_goal(grasp, -dl_goal)
    hand = copy.deepcopy(grasp.hand)
    l0 = grasp.plant.state.tendon_command
    half = 0.5 * np.abs(dl_goal).max()
    hand.tendon_range = np.column_stack([l0 - half, l0 + half])
    out = {}
    for alpha in (0.1, 10.0):
        pl = fresh(grasp)
        pl.hand = hand

        def model_fn(dl, R, t, valid, pl=pl):
            m = control.ControlModel.from_plant_truth(pl, R, t)
            m.hand = hand
            return m

        control.servo_to(R_goal, t_goal, pl, model_fn, rows="full", alpha=alpha, max_steps=40)
        ep, er = observation.pose_error(pl.state.R_PO[None], pl.state.t_PO[None], R_goal[None], t_goal[None])
        out[alpha] = (ep[0], er[0])
    assert out[10.0][1] < out[0.1][1] - np.deg2rad(1.0)
    assert out[10.0][0] > out[0.1][0] + 0.05e-3


def test_unreachable_goal_reports_closest_pose_and_respects_tendon_limits(grasp):
    pl = RecordingPlant(fresh(grasp))
    t0 = pl.state.t_PO.copy()
    goal = t0 + np.array([0.0, 0.0, 0.03])  # 30 mm away: far outside the hand's workspace
    rep = control.servo_to(
        np.eye(3), goal, pl, control.true_model_fn(pl.plant), rows="position", max_steps=40
    )
    assert not rep.reached
    # pulled towards it the grasp reaches its fold: the plant refuses the step and every
    # shorter one of the back-off (control.servo_to's ``backoff``), and the run says so
    assert rep.reason == "no_equilibrium" and 0 < rep.iterations < 40, rep.summary()
    backoff = inspect.signature(control.servo_to).parameters["backoff"].default
    assert pl.plant.failures >= 1 + backoff  # the last step's refusals, and earlier halved steps'
    assert rep.closest_position_error < np.linalg.norm(goal - t0)
    assert np.linalg.norm(rep.t_closest - goal) == pytest.approx(rep.closest_position_error)
    lo, hi = grasp.hand.tendon_range[:, 0], grasp.hand.tendon_range[:, 1]
    for l in pl.commands:
        assert np.all(l >= lo - 1e-12) and np.all(l <= hi + 1e-12)
    assert "closest" in rep.summary()


def test_goal_beyond_tendon_limits_stops_at_the_limit(grasp):
    """A goal along the strongest direction, too far for the tendon range: the run ends at
    the range (clamped, never past it) with a report, and the budget bounds it."""
    m = control.ControlModel.from_plant_truth(grasp.plant)
    hand = copy.deepcopy(grasp.hand)
    l0 = grasp.plant.state.tendon_command
    hand.tendon_range = np.column_stack([l0 - 0.3e-3, l0 + 0.3e-3])  # a tight range around the grasp
    pl = fresh(grasp)
    pl.hand = hand
    pl = RecordingPlant(pl)
    J = control.jacobian(m)
    u = np.linalg.svd(J[:3])[0][:, 0]

    def model_fn(dl, R, t, valid):
        mm = control.ControlModel.from_plant_truth(pl.plant, R, t)
        mm.hand = hand
        return mm

    rep = control.servo_to(np.eye(3), pl.state.t_PO + 5e-3 * u, pl, model_fn, rows="position", max_steps=30)
    assert not rep.reached
    assert rep.at_limit and rep.iterations <= 30
    for l in pl.commands:
        assert np.all(l >= hand.tendon_range[:, 0] - 1e-12) and np.all(l <= hand.tendon_range[:, 1] + 1e-12)


def test_servo_does_not_steer_with_a_model_that_is_no_physical_grasp(grasp):
    """A model with a Jacobian that is no physical grasp (a pushing tendon: the mean of a
    cloud, filter_model_fn's last resort) had steered the plant, 1 mm off becoming 5.3 (a
    review); the servo stops with "no_equilibrium", as filter_model_fn's docstring says,
    and the task's first model is refused."""
    pl = RecordingPlant(fresh(grasp))
    model = dataclasses.replace(control.ControlModel.from_plant_truth(pl.plant), physical=False)
    control.jacobian(model)  # it has a Jacobian
    rep = control.servo_to(np.eye(3), pl.state.t_PO + [1e-3, 0.0, 0.0], pl, lambda dl, R, t, valid: model,
                           rows="position", max_steps=5)
    assert rep.reason == "no_equilibrium" and rep.iterations == 0 and not pl.commands
    with pytest.raises(common.TaskSetupError, match="write, seed 3: the controller's model is no physical grasp"):
        common.start_model(pl, lambda dl, R, t, valid: model, pl.hand, "write", 3)


def test_servo_never_loops_forever_with_zero_budget(grasp):
    pl = fresh(grasp)
    rep = control.servo_to(np.eye(3), pl.state.t_PO + 1e-3, pl, control.true_model_fn(pl), max_steps=0)
    assert rep.iterations == 0 and rep.reason == "budget"


def test_a_lost_tag_reports_the_held_pose_not_the_truth(grasp):
    """The model plant's dropout is a lost tag: valid False with its last valid measurement,
    as the physics plant and the tag observer hold theirs, not the noise-free truth of now
    (which servo_to had used as its first measurement after a move)."""
    pl = fresh(grasp, sigma_position=0.3e-3, sigma_rotation_deg=1.0, seed=3)
    pl.dropout = 0.5
    held, lost = None, 0
    for k in range(40):
        if k % 5 == 4:
            assert pl.apply_action(np.full(pl.hand.N, 0.2e-3 * (-1) ** k))
        R, t, valid = pl.measure()
        if valid:
            held = (R, t)
        elif held is not None:
            lost += 1
            np.testing.assert_array_equal(R, held[0])
            np.testing.assert_array_equal(t, held[1])
            assert np.linalg.norm(t - pl.state.t_PO) > 1e-6  # the held pose is a noisy measurement
    assert lost >= 10
    # before any valid measurement the plant holds the pose it was made with
    pl = fresh(grasp, seed=3)
    pl.dropout = 0.99
    R, t, valid = pl.measure()
    assert not valid and np.allclose(t, grasp.plant.state.t_PO)


def test_servo_through_lost_tags_does_not_overshoot(grasp):
    """A goal 1 mm away with the tag lost half the time: the servo predicts the pose through
    the model instead of stepping again on the stale error (which had left runs 1.2-2.1 mm
    from the goal, further than they started), and calls the goal reached only on a
    measured pose; a tag lost for good ends the run as "lost_tag"."""
    m = control.ControlModel.from_plant_truth(grasp.plant)
    x = np.linalg.svd(control.jacobian(m)[:3])[0][:, 0]  # the best controlled direction
    for seed in range(6):
        pl = fresh(grasp, seed=seed)
        pl.dropout = 0.5
        goal = pl.state.t_PO + 1.0e-3 * x
        rep = control.servo_to(np.eye(3), goal, pl, control.true_model_fn(pl), rows="position",
                               tol_position=0.02e-3, max_steps=30)
        assert np.linalg.norm(pl.state.t_PO - goal) < 0.05e-3, (seed, rep.reason)
        assert rep.reason in ("reached", "lost_tag") and rep.lost > 0
    pl = fresh(grasp)
    pl.dropout = 0.999  # effectively lost for good (the plant refuses 1)
    rep = control.servo_to(np.eye(3), pl.state.t_PO + 1.0e-3 * x, pl, control.true_model_fn(pl), rows="position",
                           max_lost=3)
    assert rep.reason == "lost_tag" and rep.lost == 3
    with pytest.raises(ValueError, match="'max_lost'"):
        control.servo_to(np.eye(3), goal, pl, control.true_model_fn(pl), max_lost=0)


def test_control_step_clip_and_validation():
    J = np.vstack([np.eye(3), np.eye(3)]) * 2.0
    dl = control.control_step(J, np.array([1.0, 0, 0, 0, 0, 0]), rows="position", clip=0.5e-3)
    assert np.max(np.abs(dl)) == pytest.approx(0.5e-3)
    assert dl[0] > 0 and abs(dl[1]) < 1e-12
    with pytest.raises(ValueError, match="rows"):
        control.control_step(J, np.zeros(6), rows="everything")
    with pytest.raises(ValueError, match="mode"):
        control.control_step(J, np.zeros(6), mode="pinv")
    with pytest.raises(ValueError, match="'J'"):
        control.control_step(np.zeros((3, 3)), np.zeros(6))
    with pytest.raises(ValueError, match="error6"):
        control.control_step(J, np.zeros(5))
    with pytest.raises(ValueError, match="alpha"):
        control.control_step(J, np.ones(6), alpha=0.0)
    with pytest.raises(ValueError, match="damping >= 0"):
        control.control_step(J, np.ones(6), damping=float("nan"))
    # undamped on a rank-deficient Jacobian (two tendons with the same effect): the
    # pseudo-inverse's minimum-norm step, not a singular-matrix error
    Js = np.zeros((6, 3))
    Js[0, 0] = Js[0, 1] = 1.0
    dl = control.control_step(Js, np.array([1e-4, 0, 0, 0, 0, 0]), rows="position", damping=0.0, gain=1.0)
    np.testing.assert_allclose(dl, [0.5e-4, 0.5e-4, 0.0], atol=1e-15)


def test_transpose_form_is_the_scaled_gradient():
    rng = np.random.default_rng(3)
    J = rng.standard_normal((6, 3))
    e = rng.standard_normal(6) * 1e-3
    dl = control.control_step(J, e, mode="transpose", rows="full", gain=1.0, clip=1.0)
    w = control.row_weights("full", 1.0, control.POSITION_UNIT, control.ROTATION_UNIT)
    g = (w[:, None] * J).T @ (w * e)
    np.testing.assert_allclose(dl / np.linalg.norm(dl), g / np.linalg.norm(g), atol=1e-12)


def test_control_model_from_estimate_validates_shapes(grasp):
    with pytest.raises(ValueError, match="theta"):
        control.ControlModel.from_estimate(
            grasp.hand, {"theta": np.zeros(3), "a": np.zeros(3)}, np.eye(3), np.zeros(3)
        )
    with pytest.raises(ValueError, match="'a'"):
        control.ControlModel.from_estimate(grasp.hand, {"theta": grasp.theta0}, np.eye(3), np.zeros(3))


# ------------------------------------------------------------------ LeafSystems


def _X(R, t):
    return RigidTransform(RotationMatrix(R), t)


def test_controller_system_forced_update_moves_towards_goal(grasp):
    pl = fresh(grasp)
    R_goal, t_goal = reachable_goal(grasp, np.array([-0.3e-3, 0.2e-3, -0.1e-3]))
    l0 = pl.state.tendon_command.copy()
    ctrl = JacobianController(grasp.hand, l0, 0.1, rows="full", clip=0.3e-3)
    ctx = ctrl.CreateDefaultContext()
    est = {"theta": pl.state.theta, "a": pl.state.a}
    ctrl.X_PO_goal_input_port().FixValue(ctx, _X(R_goal, t_goal))
    ctrl.X_PO_measured_input_port().FixValue(ctx, _X(pl.state.R_PO, pl.state.t_PO))
    ctrl.estimate_input_port().FixValue(ctx, est)
    ctrl.X_PO_valid_input_port().FixValue(ctx, [0.0])
    ctrl.ExecuteForcedEvents(ctx)
    np.testing.assert_allclose(ctrl.tendon_command_output_port().Eval(ctx), l0)  # invalid: held
    ctrl.X_PO_valid_input_port().FixValue(ctx, [np.nan])  # no number: named, not read as invalid
    with pytest.raises(ValueError, match="controller: input 'X_PO_valid' must be 0 or 1"):
        ctrl.ExecuteForcedEvents(ctx)
    ctrl.X_PO_valid_input_port().FixValue(ctx, [1.0])
    ctrl.ExecuteForcedEvents(ctx)
    l1 = ctrl.tendon_command_output_port().Eval(ctx)
    assert np.max(np.abs(l1 - l0)) > 1e-5
    assert ctrl.at_goal_output_port().Eval(ctx)[0] == 0.0
    e0 = control.pose_error6(R_goal, t_goal, pl.state.R_PO, pl.state.t_PO)
    assert ctrl.pose_error_output_port().Eval(ctx)[0] == pytest.approx(np.linalg.norm(e0[:3]))
    assert pl.apply_action(l1 - l0)
    e1 = control.pose_error6(R_goal, t_goal, pl.state.R_PO, pl.state.t_PO)
    assert weighted(e1, "full") < 0.7 * weighted(e0, "full")


def test_controller_at_goal_is_not_held_through_a_lost_tag(grasp):
    """At the goal, then the tag is lost: at_goal drops to 0 (held at 1, it let a
    TaskTrajectorySource skip goals the hand was never seen to reach), and comes back when
    the tag is seen at the goal again."""
    pl = fresh(grasp)
    ctrl = JacobianController(grasp.hand, pl.state.tendon_command.copy(), 0.1, rows="full")
    ctx = ctrl.CreateDefaultContext()
    here = _X(pl.state.R_PO, pl.state.t_PO)
    ctrl.X_PO_goal_input_port().FixValue(ctx, here)
    ctrl.X_PO_measured_input_port().FixValue(ctx, here)
    ctrl.estimate_input_port().FixValue(ctx, {"theta": pl.state.theta, "a": pl.state.a})
    ctrl.X_PO_valid_input_port().FixValue(ctx, [1.0])
    ctrl.ExecuteForcedEvents(ctx)
    assert ctrl.at_goal_output_port().Eval(ctx)[0] == 1.0
    ctrl.X_PO_valid_input_port().FixValue(ctx, [0.0])
    ctrl.ExecuteForcedEvents(ctx)
    assert ctrl.at_goal_output_port().Eval(ctx)[0] == 0.0
    ctrl.X_PO_valid_input_port().FixValue(ctx, [1.0])
    ctrl.ExecuteForcedEvents(ctx)
    assert ctrl.at_goal_output_port().Eval(ctx)[0] == 1.0


def test_controller_system_keeps_a_grip_window_and_the_task_units(grasp):
    """The LeafSystem takes the servo's grip window (limits) and Eq. 12's units, as the
    tasks' servo_to does: a far goal drives the commands to the window's edge, not past it,
    and the units change the step as they do in control_step."""
    pl = fresh(grasp)
    l0 = pl.state.tendon_command.copy()
    window = np.column_stack([l0 - 0.2e-3, l0 + 0.2e-3])
    R_goal, t_goal = reachable_goal(grasp, np.array([1.5e-3, -1.0e-3, 1.0e-3]))
    ctrl = JacobianController(grasp.hand, l0, 0.1, rows="full", limits=window, clip=0.5e-3)
    ctx = ctrl.CreateDefaultContext()
    ctrl.X_PO_goal_input_port().FixValue(ctx, _X(R_goal, t_goal))
    ctrl.X_PO_measured_input_port().FixValue(ctx, _X(pl.state.R_PO, pl.state.t_PO))
    ctrl.estimate_input_port().FixValue(ctx, {"theta": pl.state.theta, "a": pl.state.a})
    ctrl.X_PO_valid_input_port().FixValue(ctx, [1.0])
    for _ in range(3):
        ctrl.ExecuteForcedEvents(ctx)
    l = ctrl.tendon_command_output_port().Eval(ctx)
    assert np.all(l >= window[:, 0] - 1e-12) and np.all(l <= window[:, 1] + 1e-12)
    assert np.any(np.isclose(l, window[:, 0]) | np.isclose(l, window[:, 1]))  # at the edge
    steps = []
    for unit in (np.deg2rad(1.0), 1.0):  # degrees, then radians: the rotation rows weigh less
        c = JacobianController(grasp.hand, l0, 0.1, rows="full", alpha=9.5, rotation_unit=unit, clip=1.0)
        cx = c.CreateDefaultContext()
        for port, value in ((c.X_PO_goal_input_port(), _X(R_goal, t_goal)),
                            (c.X_PO_measured_input_port(), _X(pl.state.R_PO, pl.state.t_PO)),
                            (c.estimate_input_port(), {"theta": pl.state.theta, "a": pl.state.a}),
                            (c.X_PO_valid_input_port(), [1.0])):
            port.FixValue(cx, value)
        c.ExecuteForcedEvents(cx)
        steps.append(c.tendon_command_output_port().Eval(cx) - l0)
    m = control.ControlModel.from_plant_truth(pl)
    J = control.jacobian(m)
    e = control.pose_error6(R_goal, t_goal, pl.state.R_PO, pl.state.t_PO)
    assert np.max(np.abs(steps[0] - steps[1])) > 1e-5  # the units matter here
    for unit, dl in zip((np.deg2rad(1.0), 1.0), steps, strict=True):
        want = control.control_step(J, e, alpha=9.5, rotation_unit=unit, clip=1.0)
        np.testing.assert_allclose(dl, want, atol=2e-6)
    with pytest.raises(ValueError, match="'tol_position'"):
        JacobianController(grasp.hand, l0, 0.1, tol_position=float("nan"))


def test_trajectory_source_advances_on_at_goal():
    goals = [(np.eye(3), np.array([0.0, 0.0, z])) for z in (0.1, 0.11, 0.12)]
    src = TaskTrajectorySource(goals, 0.1, max_periods=3)
    ctx = src.CreateDefaultContext()
    src.at_goal_input_port().FixValue(ctx, [0.0])
    assert src.X_PO_goal_output_port().Eval(ctx).translation()[2] == pytest.approx(0.1)
    src.ExecuteForcedEvents(ctx)
    assert src.waypoint_index_output_port().Eval(ctx)[0] == 0
    src.at_goal_input_port().FixValue(ctx, [1.0])
    src.ExecuteForcedEvents(ctx)
    assert src.waypoint_index_output_port().Eval(ctx)[0] == 1
    assert src.X_PO_goal_output_port().Eval(ctx).translation()[2] == pytest.approx(0.11)
    src.at_goal_input_port().FixValue(ctx, [0.0])
    for _ in range(3):  # times out on goal 1
        src.ExecuteForcedEvents(ctx)
    assert src.waypoint_index_output_port().Eval(ctx)[0] == 2
    assert src.done_output_port().Eval(ctx)[0] == 0.0
    src.at_goal_input_port().FixValue(ctx, [1.0])
    src.ExecuteForcedEvents(ctx)
    assert src.done_output_port().Eval(ctx)[0] == 1.0
    assert src.waypoint_index_output_port().Eval(ctx)[0] == 2


def test_closed_loop_diagram_on_the_model_plant(grasp):
    """Trajectory source -> controller -> model plant -> (truth as measurement and estimate)."""
    pl = fresh(grasp)
    goals = [
        reachable_goal(grasp, dl) for dl in (np.array([0.4e-3, 0.2e-3, 0.0]), np.array([0.8e-3, 0.0, 0.3e-3]))
    ]
    T = 0.1
    b = DiagramBuilder()
    plant_sys = b.AddNamedSystem("hand", ModelPlantSystem(pl, T))
    est = b.AddNamedSystem("estimate", EstimateFromTruth(grasp.hand))
    ctrl = b.AddNamedSystem(
        "controller",
        JacobianController(
            grasp.hand,
            pl.state.tendon_command,
            T,
            rows="full",
            tol_position=0.02e-3,
            tol_rotation=np.deg2rad(0.05),
        ),
    )
    src = b.AddNamedSystem("trajectory", TaskTrajectorySource(goals, T, max_periods=40))
    valid = b.AddNamedSystem("valid", ConstantVectorSource([1.0]))
    b.Connect(plant_sys.GetOutputPort("theta_true"), est.theta_true_input_port())
    b.Connect(plant_sys.GetOutputPort("contact_along_link_true"), est.contact_along_link_true_input_port())
    b.Connect(est.estimate_output_port(), ctrl.estimate_input_port())
    b.Connect(plant_sys.GetOutputPort("X_PO_true"), ctrl.X_PO_measured_input_port())
    b.Connect(valid.get_output_port(), ctrl.X_PO_valid_input_port())
    b.Connect(src.X_PO_goal_output_port(), ctrl.X_PO_goal_input_port())
    b.Connect(ctrl.at_goal_output_port(), src.at_goal_input_port())
    b.Connect(ctrl.tendon_command_output_port(), plant_sys.GetInputPort("tendon_command"))
    diagram = b.Build()
    sim = Simulator(diagram)
    ctx = sim.get_mutable_context()
    sim.AdvanceTo(3.0)
    assert src.done_output_port().Eval(src.GetMyContextFromRoot(ctx))[0] == 1.0
    X = plant_sys.GetOutputPort("X_PO_true").Eval(plant_sys.GetMyContextFromRoot(ctx))
    R_goal, t_goal = goals[-1]
    assert np.linalg.norm(X.translation() - t_goal) < 0.05e-3
    l = ctrl.tendon_command_output_port().Eval(ctrl.GetMyContextFromRoot(ctx))
    assert np.all(l >= grasp.hand.tendon_range[:, 0]) and np.all(l <= grasp.hand.tendon_range[:, 1])


def test_an_unphysical_mean_estimate_falls_back_to_the_nearest_hypothesis(grasp, monkeypatch):
    """The filter's weighted mean need not be a grasp: where the side fingers mirror each
    other (measured on the physics plant, handwriting seed 0) it implies a pushing tendon.
    Its perturbed actions have equilibria of the equations (they had none while the KKT
    regulariser sat on every Newton lane), but of a hand that does not exist. The filter's
    model_fn hands the controller the live hypothesis nearest the mean instead."""
    from vlr_drake import filter as pf

    h = grasp.hand
    mirror = {"theta": np.array([[-0.0799, 0.3909], [0.0946, 0.2374], [0.0918, 0.2188]]),
              "a": np.array([0.0265, 0.0264, 0.0274])}
    bad = control.ControlModel.from_estimate(h, mirror, np.eye(3), np.array([0.0, 0.0, 0.11]))
    assert not bad.physical and np.min(bad.stretch * h.kappa) < 0
    assert control.ControlModel.from_plant_truth(grasp.plant).physical

    plant = fresh(grasp)
    f = pf.SelfIdentificationFilter(h, pf.FilterConfig(particles=500), pf.PriorConfig(), np.random.default_rng(0))
    R, t, _ = plant.measure()
    f.initialise(plant.state.theta, plant.state.a, R, t, tendon_command=plant.state.tendon_command)
    near = f.nearest_hypothesis()
    i = np.flatnonzero(np.all(f.particles.theta == near["theta"], axis=(1, 2)))
    assert i.size == 1 and f.particles.a[i[0]] == pytest.approx(near["a"])
    x = f._unknowns(f.particles)
    z = (x - x.mean(axis=0)) / x.std(axis=0)
    assert np.argmin((z**2).sum(axis=1)) == i[0]  # equal weights after initialisation
    # an unphysical mean is replaced by that hypothesis; a physical one is kept
    assert len(f.nearest_hypotheses(5)) == 5 and np.all(f.nearest_hypotheses(5)[0]["theta"] == near["theta"])
    fn = control.filter_model_fn(f, h)
    f.estimate = lambda: mirror  # the mean as measured
    m = fn(np.zeros(h.N), R, t, True)
    assert m.physical and any(np.allclose(m.theta, c["theta"], atol=1e-9) for c in f.nearest_hypotheses(8))
    control.jacobian(m)
    # usable at the servo's own step: the model_fn tries its models with the eps it is given
    # (it had always tried them at the default, whatever step the servo then used)
    steps, real = [], control.jacobian

    def recorded(model, eps=control.JACOBIAN_EPS, retries=2):
        steps.append(eps)
        return real(model, eps, retries)

    monkeypatch.setattr(control, "jacobian", recorded)
    control.filter_model_fn(f, h, eps=0.05e-3)(np.zeros(h.N), R, t, True)
    assert steps and set(steps) == {0.05e-3}
    with pytest.raises(ValueError, match="'retries' must be an integer >= 0"):
        real(m, retries=-1)  # (it had tried nothing and said "no equilibrium on either side")


# ------------------------------------------------------------------ bad input and failures


def _nan_pose():
    X = RigidTransform()
    X.set_translation([np.nan, 0.0, 0.0])
    return X


def _controller_context(grasp, pl, goal, measured, valid=1.0):
    ctrl = JacobianController(grasp.hand, pl.state.tendon_command, 0.1)
    ctx = ctrl.CreateDefaultContext()
    ctrl.X_PO_goal_input_port().FixValue(ctx, goal)
    ctrl.X_PO_measured_input_port().FixValue(ctx, measured)
    ctrl.estimate_input_port().FixValue(ctx, {"theta": pl.state.theta, "a": pl.state.a})
    ctrl.X_PO_valid_input_port().FixValue(ctx, [valid])
    return ctrl, ctx


def test_controller_system_refuses_a_non_finite_goal_instead_of_commanding_nan(grasp):
    """A NaN goal pose used to pass through control_step and limit_action (np.clip keeps
    NaN) into the tendon_command output."""
    pl = fresh(grasp)
    ctrl, ctx = _controller_context(grasp, pl, _nan_pose(), _X(pl.state.R_PO, pl.state.t_PO))
    with pytest.raises(ValueError, match="X_PO_goal"):
        ctrl.ExecuteForcedEvents(ctx)
    assert np.all(np.isfinite(ctrl.tendon_command_output_port().Eval(ctx)))


def test_controller_system_refuses_a_non_finite_measurement_marked_valid(grasp):
    """A lost tag is X_PO_valid 0 (the command is held); a NaN pose marked valid is a
    broken sensor, refused as the filter refuses it (it used to give pose_error NaN)."""
    pl = fresh(grasp)
    goal = _X(pl.state.R_PO, pl.state.t_PO + 1e-3)
    ctrl, ctx = _controller_context(grasp, pl, goal, _nan_pose(), valid=0.0)
    ctrl.ExecuteForcedEvents(ctx)  # invalid: held, no error
    np.testing.assert_array_equal(ctrl.tendon_command_output_port().Eval(ctx), pl.state.tendon_command)
    ctrl.X_PO_valid_input_port().FixValue(ctx, [1.0])
    with pytest.raises(ValueError, match="X_PO_measured"):
        ctrl.ExecuteForcedEvents(ctx)


def test_controller_system_refuses_a_non_finite_initial_command(grasp):
    with pytest.raises(ValueError, match="l_initial"):
        JacobianController(grasp.hand, np.full(grasp.hand.N, np.nan), 0.1)


def test_control_step_and_limit_action_refuse_non_finite_values(grasp):
    J = np.vstack([np.eye(3), np.eye(3)])
    with pytest.raises(ValueError, match=r"'t_goal' and 't' must have shape \(3,\), got \(3, 1\) and \(3,\)"):
        control.pose_error6(np.eye(3), np.zeros((3, 1)), np.eye(3), np.zeros(3))  # (had broadcast to (3, 3))
    with pytest.raises(ValueError, match="error6"):
        control.control_step(J, np.full(6, np.nan))
    with pytest.raises(ValueError, match="'J'"):
        control.control_step(np.full((6, 3), np.nan), np.ones(6))
    l0 = grasp.plant.state.tendon_command
    with pytest.raises(ValueError, match="'dl'"):
        control.limit_action(grasp.hand, l0, np.full(3, np.nan))  # np.clip keeps NaN
    with pytest.raises(ValueError, match="l_now"):
        control.limit_action(grasp.hand, np.full(3, np.nan), np.zeros(3))
    # NaN limits had passed through the clamps into the commands; inverted ones had been a
    # window of one point
    rng = grasp.hand.tendon_range
    for bad in (np.full((3, 2), np.nan), rng[:, ::-1]):
        with pytest.raises(ValueError, match="'limits' must be .* lower <= upper"):
            control.limit_action(grasp.hand, l0, np.zeros(3), bad)
    np.testing.assert_array_equal(control.tendon_limits(grasp.hand, np.column_stack([np.full(3, -np.inf), rng[:, 1]])),
                                  rng)  # +-inf: no limit on that side
    # limits that miss the range (here in mm) had become one point outside it, silently: the
    # commands could then only tighten (a review)
    mm = 1e3 * np.column_stack([l0 - 2e-3, l0 + 2e-3])
    for bad in (mm, rng - 1.0):
        with pytest.raises(ValueError, match="'limits' .* miss the hand's tendon range"):
            control.tendon_limits(grasp.hand, bad)
        with pytest.raises(ValueError, match="miss the hand's tendon range"):
            control.limit_action(grasp.hand, l0, np.full(3, -1e-3), bad)
    touching = np.column_stack([rng[:, 1], rng[:, 1] + 1.0])  # one point of the range is a window
    np.testing.assert_array_equal(control.tendon_limits(grasp.hand, touching), rng[:, [1, 1]])
    for unit in ("position_unit", "rotation_unit"):
        for v in (np.nan, 0.0, -1.0):
            with pytest.raises(ValueError, match=f"'{unit}' must be a positive finite number"):
                control.row_weights("full", 1.0, **{"position_unit": 1e-3, "rotation_unit": 0.01, unit: v})


def test_servo_refuses_a_non_finite_goal_before_moving(grasp):
    """It used to run the NaN error through the controller into the plant, whose solver
    then complained about a NaN 'dl'."""
    pl = RecordingPlant(fresh(grasp))
    with pytest.raises(ValueError, match="t_goal"):
        control.servo_to(np.eye(3), pl.state.t_PO + np.nan, pl, control.true_model_fn(pl.plant), max_steps=3)
    assert pl.commands == []


def test_control_model_refuses_a_non_finite_anchor(grasp):
    """A NaN measured pose used to give a ControlModel whose contacts p_O were all NaN."""
    est = {"theta": grasp.plant.state.theta, "a": grasp.plant.state.a}
    with pytest.raises(ValueError, match="R_PO"):
        control.ControlModel.from_estimate(grasp.hand, est, np.full((3, 3), np.nan), np.zeros(3))


@pytest.mark.parametrize(
    "goal, match",
    [
        ((np.eye(3), np.array([np.nan, 0.0, 0.0])), "goal 1"),  # was accepted, a NaN goal output
        ((np.ones((3, 3)), np.zeros(3)), "goal 1.*rotation"),  # was accepted: not a rotation
        ((np.eye(3), np.zeros(2)), "goal 1"),
        (np.zeros(3), "goal 1"),  # was "too many values to unpack"
    ],
)
def test_trajectory_source_checks_its_goals(goal, match):
    with pytest.raises(ValueError, match=match):
        TaskTrajectorySource([(np.eye(3), np.zeros(3)), goal], 0.1)


def test_the_controller_systems_check_their_periods(grasp):
    """Drake takes any period: an infinite one never fires, 0 or a negative one fires
    without end. The controller had refused only periods <= 0, the trajectory source
    nothing (checked by kinematics.checked_period, as the filter's and observer's)."""
    goal = [(np.eye(3), np.zeros(3))]
    l0 = grasp.plant.state.tendon_command
    for period in (np.inf, 0.0, -0.1, np.nan, "0.1"):
        with pytest.raises(ValueError, match="'period_sec' must be a positive finite number"):
            TaskTrajectorySource(goal, period)
        with pytest.raises(ValueError, match="'period_sec' must be a positive finite number"):
            JacobianController(grasp.hand, l0, period)
    with pytest.raises(ValueError, match="'offset_sec' must be None or in"):
        TaskTrajectorySource(goal, 0.1, offset_sec=0.1)
    assert TaskTrajectorySource(goal, 0.1, offset_sec=0.0) is not None
    # the controller's offset had gone to Drake unchecked, which takes one past its period
    # (the first command periods late) and a negative one
    for offset in (0.1, 0.25, -0.01, np.nan):
        with pytest.raises(ValueError, match=r"'offset_sec' must be in \[0, period_sec = 0.1\)"):
            JacobianController(grasp.hand, l0, 0.1, offset_sec=offset)


def test_trajectory_source_checks_max_periods():
    with pytest.raises(ValueError, match="max_periods"):  # was "cannot convert float NaN to integer"
        TaskTrajectorySource([(np.eye(3), np.zeros(3))], 0.1, max_periods=np.nan)
    with pytest.raises(ValueError, match="max_periods"):  # was truncated to 2
        TaskTrajectorySource([(np.eye(3), np.zeros(3))], 0.1, max_periods=2.5)


def test_controller_system_names_a_bad_eps_at_construction(grasp):
    """eps <= 0 was accepted; jacobian's ValueError was then caught as 'no usable model'
    and the command held for ever, silently."""
    with pytest.raises(ValueError, match="eps"):
        JacobianController(grasp.hand, grasp.plant.state.tendon_command, 0.1, eps=0.0)


def test_controller_system_names_a_malformed_estimate(grasp):
    """An estimate without 'a', or of another hand's shape (a wiring mistake), was caught as
    'no usable model here' and the command held for ever, silently."""
    pl = fresh(grasp)
    ctrl, ctx = _controller_context(grasp, pl, _X(pl.state.R_PO, pl.state.t_PO + 1e-3), _X(pl.state.R_PO, pl.state.t_PO))
    ctrl.estimate_input_port().FixValue(ctx, {"theta": pl.state.theta})
    with pytest.raises(ValueError, match="estimate.*'a'"):
        ctrl.ExecuteForcedEvents(ctx)
    ctrl.estimate_input_port().FixValue(ctx, {"theta": pl.state.theta, "a": pl.state.a[:2]})
    with pytest.raises(ValueError, match=r"estimate\['a'\].*\(3,\)"):
        ctrl.ExecuteForcedEvents(ctx)
    # a non-finite estimate (a filter gone wrong) has no usable model: the command is held
    ctrl.estimate_input_port().FixValue(ctx, {"theta": pl.state.theta * np.nan, "a": pl.state.a})
    ctrl.ExecuteForcedEvents(ctx)
    np.testing.assert_array_equal(ctrl.tendon_command_output_port().Eval(ctx), pl.state.tendon_command)


def test_servo_a_step_at_a_time_carries_the_predicted_pose(grasp):
    """One action per call (as the maze servos): given the call before's report
    (``resume``), a lost tag's pose is that call's predicted pose, not the plant's held one,
    so the steps do not repeat on a stale error, and lost tags in a row count across calls."""
    m = control.ControlModel.from_plant_truth(grasp.plant)
    x = np.linalg.svd(control.jacobian(m)[:3])[0][:, 0]
    for seed in range(6):
        pl = fresh(grasp, seed=seed)
        pl.dropout = 0.5
        t0 = pl.state.t_PO.copy()
        goal = t0 + 1.0e-3 * x
        rep, lost, overshoot = None, 0, 0.0
        for _ in range(40):
            rep = control.servo_to(np.eye(3), goal, pl, control.true_model_fn(pl), rows="position",
                                   tol_position=0.02e-3, max_steps=1, max_lost=12, resume=rep)
            lost += rep.lost
            overshoot = max(overshoot, (pl.state.t_PO - t0) @ x - 1.0e-3)
            assert rep.reason != "lost_tag"
            if rep.reached:
                break
        # without resume, steps on the held pose's error went 0.04-0.4 mm past the goal on three seeds of six
        assert overshoot < 0.01e-3, seed
        assert rep.reached and lost > 0, seed
        assert np.linalg.norm(pl.state.t_PO - goal) < 0.05e-3, seed
        assert rep.R_final is not None and rep.lost_in_a_row == 0
    pl = fresh(grasp)
    pl.dropout = 0.999
    reps = [None]
    for _ in range(3):
        reps.append(control.servo_to(np.eye(3), pl.state.t_PO + 1.0e-3 * x, pl, control.true_model_fn(pl),
                                     rows="position", max_steps=1, max_lost=3, resume=reps[-1]))
    assert [r.lost_in_a_row for r in reps[1:]] == [2, 3, 4]  # the first call steps once; then no step
    assert [r.reason for r in reps[1:]] == ["budget", "lost_tag", "lost_tag"] and reps[-1].iterations == 0


def test_servo_a_step_at_a_time_looks_once_per_action(grasp):
    """Given the call before's report, a call that ended on a measured pose, the next one
    starts from that frame: one measurement per action (the maze had looked twice, a second
    render and detection per control period on the physics plant). After a lost tag it looks
    again (test_servo_a_step_at_a_time_carries_the_predicted_pose)."""
    m = control.ControlModel.from_plant_truth(grasp.plant)
    x = np.linalg.svd(control.jacobian(m)[:3])[0][:, 0]
    pl = fresh(grasp, sigma_position=0.02e-3, seed=3)
    looks = []
    measure = pl.measure
    pl.measure = lambda: looks.append(1) or measure()
    goal = pl.state.t_PO + 1.0e-3 * x
    rep, steps = None, 0
    for _ in range(25):
        rep = control.servo_to(np.eye(3), goal, pl, control.true_model_fn(pl), rows="position",
                               tol_position=0.01e-3, max_steps=1, resume=rep)
        steps += rep.iterations
    assert steps > 10
    assert len(looks) == 1 + steps  # one look before the first action and one after each
    assert np.linalg.norm(pl.state.t_PO - goal) < 0.1e-3


def test_a_command_outside_its_window_moves_into_it_one_step_at_a_time(grasp):
    """A tendon that starts outside the grip window had been clamped into it in one jump (2 mm
    where the servo had clipped its step to 0.5 mm); it now moves towards the window by its
    own step, and never further out. The controller system refuses a start outside the range."""
    h = grasp.hand
    l0 = grasp.plant.state.tendon_command.copy()
    window = np.column_stack([l0 + 2e-3, l0 + 4e-3])
    step = control.limit_action(h, l0, np.full(3, 0.5e-3), window)
    assert step == pytest.approx(np.full(3, 0.5e-3))  # inwards, by the step asked for
    assert control.limit_action(h, l0, np.full(3, -0.5e-3), window) == pytest.approx(np.zeros(3))  # never out
    inside = l0 + 3e-3
    assert control.limit_action(h, inside, np.full(3, 2e-3), window) == pytest.approx(np.full(3, 1e-3))  # clamped
    pl = fresh(grasp)
    rep = control.servo_to(pl.state.R_PO, pl.state.t_PO + [0.3e-3, 0.0, 0.0], pl, control.true_model_fn(pl),
                           rows="position", limits=window, clip=0.5e-3, max_steps=3)
    steps = np.diff(np.array([l0] + [pl.state.tendon_command]), axis=0)
    assert np.max(np.abs(steps)) <= 3 * 0.5e-3 + 1e-12 and rep.iterations <= 3
    with pytest.raises(ValueError, match="'l_initial' .* is outside the hand's tendon range"):
        JacobianController(h, h.tendon_range[:, 1] + 1e-3, 0.1)


def test_the_controller_system_falls_back_to_a_hypothesis_and_says_when_it_has_no_model(grasp):
    """The weighted mean of a cloud can be no grasp (the side fingers mirrored, a pushing
    tendon): the system had held its command forever without a word. It now tries the
    estimate's fallbacks (the filter's hypotheses nearest the mean, which the
    self-identification system's estimate port carries) and reads has_model 0 while none is
    usable."""
    from vlr_drake import filter as pf
    from vlr_drake.systems.self_identification import SelfIdentificationSystem

    h, pl = grasp.hand, fresh(grasp)
    mirror = {"theta": np.array([[-0.0799, 0.3909], [0.0946, 0.2374], [0.0918, 0.2188]]),
              "a": np.array([0.0265, 0.0264, 0.0274])}
    truth = {"theta": pl.state.theta.copy(), "a": pl.state.a.copy()}
    l0 = pl.state.tendon_command.copy()
    R, t = pl.state.R_PO, pl.state.t_PO
    for est, moves in ((mirror, False), ({**mirror, "fallbacks": [mirror, truth]}, True)):
        c = JacobianController(h, l0, 0.1)
        cx = c.CreateDefaultContext()
        c.X_PO_goal_input_port().FixValue(cx, RigidTransform(RotationMatrix(R), t + [0.5e-3, 0.0, 0.0]))
        c.X_PO_measured_input_port().FixValue(cx, RigidTransform(RotationMatrix(R), t))
        c.X_PO_valid_input_port().FixValue(cx, [1.0])
        c.estimate_input_port().FixValue(cx, est)
        c.ExecuteForcedEvents(cx)
        changed = np.any(c.tendon_command_output_port().Eval(cx) != l0)
        assert changed == moves and c.has_model_output_port().Eval(cx)[0] == float(moves)
    # the self-identification system's estimate carries the fallbacks, nearest the mean first
    sid = SelfIdentificationSystem(h, pf.FilterConfig(particles=500), pf.PriorConfig(), pl.state.theta, pl.state.a, 1.0)
    sx = sid.CreateDefaultContext()
    sid.tendon_command_input_port().FixValue(sx, l0)
    sid.X_PO_measured_input_port().FixValue(sx, RigidTransform(RotationMatrix(R), t))
    sid.X_PO_valid_input_port().FixValue(sx, [1.0])
    sid.ExecuteForcedEvents(sx)
    est = sid.GetOutputPort("estimate").Eval(sx)
    f = sid.filter(sx)
    assert len(est["fallbacks"]) == control.FALLBACKS
    assert np.array_equal(est["fallbacks"][0]["theta"], f.nearest_hypothesis()["theta"])


def test_relative_goals_are_anchored_on_the_mean_of_the_first_frames():
    """With relative_start_sec the goals are offsets from the mean of the first anchor_frames
    valid measurements at or after that time; before it and on a lost tag nothing is read,
    and the goals' count starts once anchored."""
    from pydrake.math import RollPitchYaw

    src = TaskTrajectorySource([(np.eye(3), [1e-3, 0.0, 0.0]), (np.eye(3), [0.0, 0.0, 0.0])], 0.1, max_periods=2,
                               relative_start_sec=1.0, anchor_frames=2)
    ctx = src.CreateDefaultContext()
    src.at_goal_input_port().FixValue(ctx, [1.0])
    R1 = RollPitchYaw(0.02, 0.0, 0.0).ToRotationMatrix()
    for time, t, valid in ((0.5, [9.0, 9.0, 9.0], 1.0),  # before the start: ignored
                           (1.0, [0.0, 0.0, 0.110], 1.0),
                           (1.1, [5.0, 5.0, 5.0], 0.0),  # a lost tag: ignored
                           (1.2, [0.0, 0.0, 0.112], 1.0)):
        ctx.SetTime(time)
        src.X_PO_measured_input_port().FixValue(ctx, RigidTransform(R1, t))
        src.X_PO_valid_input_port().FixValue(ctx, [valid])
        assert not src.anchored(ctx) and src.ready_output_port().Eval(ctx)[0] == 0.0
        src.ExecuteForcedEvents(ctx)
    assert src.anchored(ctx) and src.waypoint_index_output_port().Eval(ctx)[0] == 0  # not counted yet
    assert src.ready_output_port().Eval(ctx)[0] == 1.0
    goal = src.X_PO_goal_output_port().Eval(ctx)
    assert goal.translation() == pytest.approx([1e-3, 0.0, 0.111]) and np.allclose(goal.rotation().matrix(), R1.matrix(), atol=1e-12)
    src.ExecuteForcedEvents(ctx)
    assert src.waypoint_index_output_port().Eval(ctx)[0] == 1
    with pytest.raises(ValueError, match="'anchor_frames' must be an integer >= 1"):
        TaskTrajectorySource([RigidTransform()], 0.1, relative_start_sec=1.0, anchor_frames=0)


def test_the_controller_follows_the_applied_command_until_it_starts_then_keeps_a_window_about_it(grasp):
    """Before start_sec, and while its enabled input is 0 (the trajectory's goals not yet
    anchored), the controller system follows its tendon_command_applied input (the command a
    switch gives the hand) and reads at_goal 0; then it steps from the applied command,
    within +-window of where it started; ControlPhase hands the switch over."""
    from vlr_drake.systems.controller import ControlPhase

    h, pl = grasp.hand, fresh(grasp)
    l0 = pl.state.tendon_command.copy()
    c = JacobianController(h, l0, 0.1, start_sec=1.0, window=0.3e-3, clip=1e-3)
    cx = c.CreateDefaultContext()
    R, t = pl.state.R_PO, pl.state.t_PO
    c.X_PO_goal_input_port().FixValue(cx, RigidTransform(RotationMatrix(R), t + [2e-3, 0.0, 0.0]))
    c.X_PO_measured_input_port().FixValue(cx, RigidTransform(RotationMatrix(R), t))
    c.X_PO_valid_input_port().FixValue(cx, [1.0])
    c.estimate_input_port().FixValue(cx, {"theta": pl.state.theta.copy(), "a": pl.state.a.copy()})
    applied = l0 + 0.2e-3
    c.tendon_command_applied_input_port().FixValue(cx, applied)
    cx.SetTime(0.5)
    c.ExecuteForcedEvents(cx)
    assert np.array_equal(c.tendon_command_output_port().Eval(cx), applied)
    assert c.at_goal_output_port().Eval(cx)[0] == 0.0
    cx.SetTime(1.0)
    c.enabled_input_port().FixValue(cx, [0.0])  # the goals not anchored yet (a lost frame): still waiting
    c.ExecuteForcedEvents(cx)
    assert np.array_equal(c.tendon_command_output_port().Eval(cx), applied)
    c.enabled_input_port().FixValue(cx, [np.nan])  # had been read as enabled, and a full step taken
    with pytest.raises(ValueError, match="controller: input 'enabled' must be 0 or 1"):
        c.ExecuteForcedEvents(cx)
    c.enabled_input_port().FixValue(cx, [1.0])
    for _ in range(5):  # a far goal: the steps pile up against the window about the start
        c.ExecuteForcedEvents(cx)
        c.tendon_command_applied_input_port().FixValue(cx, c.tendon_command_output_port().Eval(cx).copy())
    moved = c.tendon_command_output_port().Eval(cx) - applied
    assert np.any(moved != 0) and np.max(np.abs(moved)) <= 0.3e-3 + 1e-12
    with pytest.raises(ValueError, match="'window' must be None or a positive"):
        JacobianController(h, l0, 0.1, window=0.0)
    # a start further below narrower limits than the window: it moves into the limits one
    # clipped step at a time, as without a window (the empty window had been refused as
    # 'limits' the user never gave: a review)
    lim = np.column_stack([l0 + 3e-3, l0 + 6e-3])
    for window in (None, 2e-3):
        c = JacobianController(h, l0, 0.1, rows="position", limits=lim, window=window)
        cx = c.CreateDefaultContext()
        c.X_PO_goal_input_port().FixValue(cx, RigidTransform(RotationMatrix(R), t + [1e-3, 0.0, 0.0]))
        c.X_PO_measured_input_port().FixValue(cx, RigidTransform(RotationMatrix(R), t))
        c.X_PO_valid_input_port().FixValue(cx, [1.0])
        c.estimate_input_port().FixValue(cx, {"theta": pl.state.theta.copy(), "a": pl.state.a.copy()})
        c.ExecuteForcedEvents(cx)
        step = c.tendon_command_output_port().Eval(cx) - l0
        assert np.all(step > 0) and np.max(step) <= 1e-3 + 1e-12, (window, step)  # towards the limits, clipped
    phase = ControlPhase(2.0, "explore", "control")
    px = phase.CreateDefaultContext()
    px.SetTime(1.9)
    assert phase.get_output_port().Eval(px) == "explore"
    px.SetTime(2.0)
    assert phase.get_output_port().Eval(px) == "control"


def test_the_controller_holds_once_its_error_stops_improving(grasp):
    """A goal the hand cannot reach (or friction holds the object short of): after
    stall_periods periods without progress the controller holds its command, instead of
    winding the tendons on (on the physics plant that released every tendon until the apple
    slipped), and steps again once the goal changes."""
    h, pl = grasp.hand, fresh(grasp)
    l0 = pl.state.tendon_command.copy()
    R, t = pl.state.R_PO, pl.state.t_PO
    c = JacobianController(h, l0, 0.1, stall_periods=3, clip=0.2e-3)
    cx = c.CreateDefaultContext()
    c.estimate_input_port().FixValue(cx, {"theta": pl.state.theta.copy(), "a": pl.state.a.copy()})
    c.X_PO_valid_input_port().FixValue(cx, [1.0])
    c.X_PO_measured_input_port().FixValue(cx, RigidTransform(RotationMatrix(R), t))  # the object never moves
    c.X_PO_goal_input_port().FixValue(cx, RigidTransform(RotationMatrix(R), t + [1e-3, 0.0, 0.0]))
    commands = []
    for _ in range(8):
        c.ExecuteForcedEvents(cx)
        commands.append(c.tendon_command_output_port().Eval(cx).copy())
    moves = [bool(np.any(b != a)) for a, b in zip([l0] + commands[:-1], commands, strict=True)]
    assert moves[:3] == [True, True, True] and not any(moves[3:]), moves  # three steps, then held
    c.X_PO_goal_input_port().FixValue(cx, RigidTransform(RotationMatrix(R), t + [-1e-3, 0.0, 0.0]))
    c.ExecuteForcedEvents(cx)
    assert np.any(c.tendon_command_output_port().Eval(cx) != commands[-1])  # a new goal: steps again
    with pytest.raises(ValueError, match="'stall_periods' must be an integer >= 1"):
        JacobianController(h, l0, 0.1, stall_periods=0)


def test_a_huge_rotation_weight_steers_on_the_rotation_alone(grasp):
    """W's scale does not change the step: a huge alpha (1e308 had hung in lstsq, 1e200 had
    ended in "'dl' must be finite"; a review) steers as the rotation rows alone do, and
    weights that overflow are refused by name."""
    J = control.jacobian(control.ControlModel.from_plant_truth(grasp.plant))
    e = np.array([1e-3, -2e-3, 0.5e-3, 0.02, -0.01, 0.03])
    for mode in control.MODES:
        huge = control.control_step(J, e, mode=mode, alpha=1e308, rotation_unit=1.0, clip=1.0)
        alone = control.control_step(J, e, mode=mode, rows="orientation", clip=1.0)
        assert np.all(np.isfinite(huge)) and huge == pytest.approx(alone, rel=1e-9, abs=1e-15), mode
    with pytest.raises(ValueError, match="overflows: no finite weight"):
        control.row_weights("full", 1e308, 1e-3, 0.01)
