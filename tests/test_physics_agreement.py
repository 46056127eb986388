"""The model-vs-physics agreement command (vlr_drake.physics.agreement)."""

import json

import numpy as np
import pytest

from vlr_drake.hand import model_o
from vlr_drake.physics.agreement import _explained, main, run_agreement


def test_gamma_predicts_the_physics_plants_first_actions(tmp_path):
    """From the plant's true state, Gamma with the contact at the pad's centre of curvature
    predicts a thumb-vs-fingers pull's object motion in direction and size (measured: 1.18x,
    0.55 mm off a 3.1 mm motion; with the contact on the pad surface it was ~2x), and the
    carried model has not drifted yet."""
    path = tmp_path / "agreement.json"
    r = main(["--direction", "-1", "1", "1", "--step", "0.5e-3", "--actions", "2", "--hold", "0.05",
              "--json", str(path)])
    assert json.loads(path.read_text())["object"] == "apple"
    first = r["actions"][0]
    assert first["true_motion_mm"] > 1.0  # a compliant grasp: mm of motion per 0.5 mm of pull
    assert 0.8 < first["predicted_motion_mm"] / first["true_motion_mm"] < 1.5
    assert first["one_step_error_mm"] < 0.4 * first["true_motion_mm"]
    assert first["carried_error_mm"] == pytest.approx(first["one_step_error_mm"])  # the same start
    assert r["model_failures"] == 0 and not r["carried_model_failed"]
    # the joint angles are compared too: one step from the truth stays within a few degrees
    split = np.array(first["one_step_joint_error_deg"])
    assert split.shape == (3, 2) and np.max(np.abs(split)) < 5.0
    np.testing.assert_allclose(first["carried_joint_error_deg"], split)
    assert r["one_step_error_mm_median"] == pytest.approx(np.median([a["one_step_error_mm"] for a in r["actions"]]))
    # the commanded equilibrium: the VLR under the plant's own tendon state sits within a few
    # degrees of the plant's angles (the object's weight, which the VLR lacks, is most of it)
    offset = np.array(first["commanded_offset_deg"])
    assert offset.shape == (3, 2) and 0.0 < np.max(np.abs(offset)) < 5.0
    assert r["commanded_offset_deg_mean"] == pytest.approx(
        np.mean([np.abs(row["commanded_offset_deg"]) for row in r["actions"]]))
    assert r["gravity"] == pytest.approx(9.81) and r["commanded_failures"] == 0
    assert first["settled_one_step_error_mm"] < 0.4 * first["true_motion_mm"]
    # the statics budget: the plant's joint torques close at rest (a sign or a Jacobian wrong
    # would leave tens of mN m), the pads' friction moments on the apple flex the fingers and
    # the links' weight straightens them (palm down), and with every load Eq. 9 lacks added
    # the VLR's commanded equilibrium lands on the plant's angles (measured 0.02-0.08 deg
    # against 1.0-1.9 on four objects)
    b = r["statics_budget"]
    assert b["residual_mNm_max"] < 1.0
    loads = b["loads_mNm_mean"]
    assert np.min(loads["pad_moment"]) > 2.0 and np.max(loads["link_weight"]) < 0.0
    assert np.allclose(loads["other_contacts"], 0.0)
    with_loads = b["commanded_offset_deg_mean_with"]
    assert with_loads["none"] == pytest.approx(r["commanded_offset_deg_mean"])
    assert with_loads["all"] < 0.15 * with_loads["none"] and b["failures_with"]["all"] == 0
    assert with_loads["pad_moment"] < with_loads["none"] and with_loads["link_weight"] < with_loads["none"]
    np.testing.assert_allclose(first["commanded_offset_with_deg"]["none"], first["commanded_offset_deg"])
    # the kinematic check: with the plant's true links, the object follows the points where
    # the pads touch it (they roll), not the pads' centres, which the VLR pins (measured 0.02-
    # 0.05 mm / 0.02-0.05 deg against 0.30-0.31 mm / 0.51-0.52 deg on 3 mm motions)
    for row in r["actions"]:
        mm, deg = row["kinematic_error_mm"], row["kinematic_error_deg"]
        assert mm["touching"] < 0.1 and mm["touching"] < 0.3 * mm["centre"]
        assert deg["touching"] < 0.3 * deg["centre"]
    assert r["kinematic_error_mm_median"]["touching"] == pytest.approx(
        np.median([row["kinematic_error_mm"]["touching"] for row in r["actions"]]))
    # Eq. 9's commanded equilibria move the distal joints as the plant does and the proximal
    # ones too far (measured slopes 0.77-0.82 proximal, 0.97-1.02 distal); with the links' and
    # the object's weight following the angles the proximal ones move as the plant's (0.95-
    # 1.04), and the POM's prediction, still with the pads' centres pinned, gets worse (0.35-
    # 0.39 mm against 0.30-0.31): docs/results.md, "The pads roll"
    slope = np.array(r["joint_motion_slope"], float)
    with_weights = np.array(r["joint_motion_slope_with_weights"], float)
    assert slope.shape == with_weights.shape == (3, 2)
    assert np.all((0.6 < slope[:, 0]) & (slope[:, 0] < 0.9)) and np.all((0.85 < slope[:, 1]) & (slope[:, 1] < 1.15))
    assert np.all(np.abs(with_weights[:, 0] - 1.0) < 0.08)
    for row in r["actions"]:
        assert row["settled_one_step_error_with_weights_mm"] > row["settled_one_step_error_mm"]
    # the rolling reference (the pads rolling and the weights, from the plant's state) sits
    # nearer the plant's angles at rest and predicts the motion better than Eq. 9 (measured:
    # offsets 0.43 against 1.17-1.33 deg, 0.14-0.18 mm / 0.14 deg against 0.30-0.31 mm /
    # 0.38-0.40 deg) and moves each joint as the plant does (slopes 0.93-1.11)
    assert r["rolling_failures"] == 0
    for row in r["actions"]:
        assert np.mean(np.abs(row["rolling_offset_deg"])) < 0.5 * np.mean(np.abs(row["commanded_offset_deg"]))
        assert row["rolling_one_step_error_mm"] < 0.7 * row["settled_one_step_error_mm"]
        assert row["rolling_one_step_error_deg"] < 0.5 * row["settled_one_step_error_deg"]
    assert np.all(np.abs(np.array(r["joint_motion_slope_rolling"]) - 1.0) < 0.15)
    # the apple is a sphere: the reference again on its curved surface, with the pads' offsets
    # (rolling_shaped); at rest it sits at the plant's angles as well (measured 0.01-0.14 deg).
    # The Model O's side fingers hold it at a mirror-image grasp, where one direction of their
    # attachments holds the sphere only at second order, and holding it locks the grasp: the
    # apple moves 0.6-0.7 mm where the plant moves it 3.1 mm (measured 2.34 / 2.53 mm off,
    # against 0.14 / 0.18 for the flat roll). Released (rolling_released), the curved roll
    # predicts this sweep far better than the flat one (measured 0.025 / 0.019 mm) and
    # explains the joints' motion (0.995-0.999; held, the proximal joints' 0.54-0.69)
    for row in r["actions"]:
        assert np.mean(np.abs(row["rolling_shaped_offset_deg"])) < 0.3
        assert 1.5 < row["rolling_shaped_one_step_error_mm"] < 3.5
        assert row["rolling_shaped_one_step_error_mm"] > 5 * row["rolling_one_step_error_mm"]
        assert np.mean(np.abs(row["rolling_released_offset_deg"])) < 0.1
        assert row["rolling_released_one_step_error_mm"] < 0.3 * row["rolling_one_step_error_mm"]
        assert row["rolling_released_one_step_error_deg"] < 0.3 * row["rolling_one_step_error_deg"]
    true = np.array([a["true_joint_motion_deg"] for a in r["actions"]])
    for name in ("shaped", "released"):
        for unit in ("mm", "deg"):
            assert r[f"rolling_{name}_one_step_error_{unit}_median"] == pytest.approx(
                np.median([a[f"rolling_{name}_one_step_error_{unit}"] for a in r["actions"]]))
        model = np.array([a[f"rolling_{name}_joint_motion_deg"] for a in r["actions"]])
        explained = np.array(r[f"joint_motion_explained_rolling_{name}"], float)
        np.testing.assert_allclose(explained, 1.0 - ((true - model) ** 2).sum(0) / (true**2).sum(0))
        slope = np.array(r[f"joint_motion_slope_rolling_{name}"], float)
        np.testing.assert_allclose(slope, (true * model).sum(0) / (model**2).sum(0), rtol=1e-9)
    explained = np.array(r["joint_motion_explained_rolling_shaped"], float)
    assert explained.shape == (3, 2) and np.all(explained[:, 0] > 0.5) and np.all(explained <= 1.0)
    assert np.all(np.array(r["joint_motion_explained_rolling_released"], float) > 0.95)
    # held after the last action, the plant is not quite at rest (SAP's creep): it drifts,
    # by far less than an action moves it
    held = r["hold"]
    assert held["seconds"] == pytest.approx(0.05)
    drift = np.abs(np.array(held["joint_drift_deg"]))
    assert drift.shape == (3, 2) and 0.0 < drift.max() < 0.5
    assert held["joint_drift_deg_per_s_max"] == pytest.approx(drift.max() / 0.05)
    assert 0.0 < held["object_drift_mm"] < 0.2 * first["true_motion_mm"]


def test_commanded_equilibrium_holds_a_model_equilibrium_and_follows_the_command():
    """A VLR grasp at rest under its own tendon state is its own commanded equilibrium; a
    longer thumb command (a release) moves it by a fraction of a degree or more."""
    from vlr_drake import kinematics, motion
    from vlr_drake.grasps import commanded_equilibrium
    from vlr_drake.identify import _truth_grasp

    h = model_o().model()
    theta, a = _truth_grasp(h, np.random.default_rng(3))
    D2 = motion.contact_distances_sq(h, kinematics.contacts(h, theta[None], a[None]))[0]
    stretch = motion.equilibrium(h, theta[None], a=a[None]).stretch[0]
    l_cmd = stretch + h.tendon_travel(theta)
    th, ok = commanded_equilibrium(h, theta, a, l_cmd, D2=D2)
    assert ok
    np.testing.assert_allclose(th, theta, atol=1e-8)
    th2, ok2 = commanded_equilibrium(h, theta, a, l_cmd + np.array([0.5e-3, 0.0, 0.0]))  # D2 from theta
    assert ok2 and np.max(np.abs(np.rad2deg(th2 - theta))) > 0.1


def test_physics_overrides_parse_and_name_bad_keys():
    from vlr_drake.physics.agreement import physics_overrides

    cfg = physics_overrides(["gravity=0", "settle_object_speed=1e-4", "seed=3"])
    assert cfg.gravity == 0.0 and cfg.settle_object_speed == 1e-4 and cfg.seed == 3
    with pytest.raises(ValueError, match="'bogus=1'.*gravity"):
        physics_overrides(["bogus=1"])
    with pytest.raises(ValueError, match="'contact_model=point'"):
        physics_overrides(["contact_model=point"])  # not a number
    with pytest.raises(ValueError, match="'heavy' is not a number"):
        physics_overrides(["gravity=heavy"])
    with pytest.raises(ValueError, match="'gravity' must be a finite number >= 0"):
        physics_overrides(["gravity=-9.81"])


def test_bad_direction_is_named():
    with pytest.raises(ValueError, match="'direction' must be a finite, nonzero vector of 3"):
        run_agreement(direction=[1.0, 0.0])
    with pytest.raises(ValueError, match="'direction' must be a finite"):  # (had been named as 'dl')
        run_agreement(direction=[np.inf, 1.0, 1.0])
    with pytest.raises(ValueError, match="'actions' must be an integer >= 1"):
        run_agreement(actions=0)
    # (2.5 actions and a NaN sweep step had failed only after the grasp, the step named as 'dl')
    with pytest.raises(ValueError, match="'actions' must be an integer >= 1, got 2.5"):
        run_agreement(actions=2.5)
    with pytest.raises(ValueError, match="'step' must be a finite number"):
        run_agreement(direction=[-1.0, 1.0, 1.0], step=float("nan"))
    # a sweep step in millimetres (--step 0.5 had pulled 0.5 m until the apple fell out)
    with pytest.raises(ValueError, match=r"'step' 0.5 m is a tendon's whole travel \(45 mm\) or more.*millimetres"):
        run_agreement(direction=[-1.0, 1.0, 1.0], step=0.5)
    with pytest.raises(ValueError, match="'hold' must be a duration >= 0"):
        run_agreement(hold=-1.0)
    # a span or window in millimetres is named before any plant is built (--span 1.5
    # --window 4 had run until "the apple fell out of the hand ... check the pretension")
    for kw, field in ((dict(span=1.5, window=4.0), "action_range"), (dict(window=4.0), "window"),
                      (dict(span=2.0), "action_range")):
        with pytest.raises(ValueError, match=rf"{field} \(exploration\.\w+\): .* m is longer than 1 m.*millimetres"):
            run_agreement(**kw)


def test_bad_command_line_is_named(capsys):
    for argv, what in ((["--hand", "NH9"], "--hand: unknown hand 'NH9'"), (["--hold", "-2"], "--hold: a duration"),
                       (["--direction", "1", "1", "1", "--squeeze"], "--squeeze: the random actions' squeezes")):
        with pytest.raises(SystemExit):
            main(argv)
        assert what in capsys.readouterr().err


def test_explained_fraction_matches_its_definition():
    """1 - sum (plant - model)^2 / sum plant^2 per joint, over the rows that have the model's
    motion; None for a joint the plant never moved."""
    plant = np.array([[[1.0, 0.0]], [[-2.0, 0.0]], [[0.5, 0.0]]])
    model = 0.5 * plant
    rows = [{"true_joint_motion_deg": p.tolist(), "m": m.tolist()} for p, m in zip(plant, model, strict=True)]
    rows.append({"true_joint_motion_deg": [[9.0, 9.0]], "m": None})  # no prediction: left out
    frac = _explained(rows, "m")
    assert frac[0][0] == pytest.approx(0.75) and frac[0][1] is None
    rows[0]["m"] = [[1.0, 0.0]]  # one action predicted exactly, the others at half
    expected = 1.0 - (0.0 + 1.0 + 0.0625) / (1.0 + 4.0 + 0.25)
    assert _explained(rows, "m")[0][0] == pytest.approx(expected)
    assert _explained([{"true_joint_motion_deg": [[1.0]], "m": None}], "m") is None


def test_statics_budget_parts_and_bad_input():
    """The barycentric split of a point over the contacts, the commanded offsets' groups, and
    the errors that name a wrong load or a contact model the budget cannot read."""
    from types import SimpleNamespace

    from vlr_drake import kinematics, motion
    from vlr_drake.identify import _truth_grasp
    from vlr_drake.physics.statics import (
        LOADS,
        UNMODELLED,
        JointLoads,
        barycentric_weights,
        commanded_offsets,
        plant_loads,
    )

    c = np.array([[0.0, 0.0, 0.1], [0.06, 0.0, 0.1], [0.0, 0.04, 0.1]])
    point = np.array([0.02, 0.01, 0.1])
    w = barycentric_weights(c, point)
    assert w.sum() == pytest.approx(1.0)
    np.testing.assert_allclose(w @ c, point, atol=1e-15)
    w_off = barycentric_weights(c, point + [0.0, 0.0, 0.03])  # off the contacts' plane: projected
    np.testing.assert_allclose(w_off, w, atol=1e-12)
    # the budget's split of the object's load: the forces sum to it and carry its moment, the
    # centre of mass's offset from the contacts' plane included (the projected barycentric
    # split had lost that moment: 7.4 mN m on the apple with the palm pitched 30 deg)
    from vlr_drake.physics.statics import object_load_shares

    g = np.array([0.0, 4.9, -8.5])  # a tilted palm
    com = point + [0.0, 0.0, 0.03]
    centre = c.mean(axis=0)
    shares = object_load_shares(c - centre, 0.1 * g, np.cross(com - centre, 0.1 * g))
    np.testing.assert_allclose(shares.sum(axis=0), 0.1 * g, atol=1e-12)
    np.testing.assert_allclose(np.cross(c - centre, shares).sum(axis=0), np.cross(com - centre, 0.1 * g), atol=1e-12)
    barycentric = np.outer(w_off, 0.1 * g)
    assert np.abs(np.cross(c - centre, barycentric).sum(axis=0) - np.cross(com - centre, 0.1 * g)).max() > 1e-4

    h = model_o().model()
    theta, a = _truth_grasp(h, np.random.default_rng(3))
    D2 = motion.contact_distances_sq(h, kinematics.contacts(h, theta[None], a[None]))[0]
    l_cmd = motion.equilibrium(h, theta[None], a=a[None]).stretch[0] + h.tendon_travel(theta)
    zero = JointLoads(*(np.zeros((h.N, h.K)) for _ in LOADS))
    off = commanded_offsets(h, theta, a, l_cmd, zero, D2=D2)
    assert set(off) == {"none", *UNMODELLED, "all"}
    for v in off.values():  # no load: the grasp is its own commanded equilibrium
        np.testing.assert_allclose(v, 0.0, atol=1e-6)
    # a flexing torque on the thumb's joints moves the equilibrium; the other groups do not see it
    thumb = np.zeros((h.N, h.K))
    thumb[0] = 5e-3
    loaded = JointLoads(*(thumb if name == "pad_moment" else np.zeros((h.N, h.K)) for name in LOADS))
    off = commanded_offsets(h, theta, a, l_cmd, loaded, D2=D2,
                            groups={"moment": ("pad_moment",), "weight": ("link_weight",)})
    assert np.max(np.abs(np.rad2deg(off["moment"]))) > 0.1
    np.testing.assert_allclose(off["weight"], 0.0, atol=1e-6)
    with pytest.raises(ValueError, match="unknown loads \\['tendon'\\]"):
        commanded_offsets(h, theta, a, l_cmd, zero, groups={"x": ("tendon",)})
    with pytest.raises(ValueError, match="needs the physics plant's point contact, got contact_model 'hydroelastic'"):
        plant_loads(SimpleNamespace(physics=SimpleNamespace(contact_model="hydroelastic")), None)


def test_the_spring_shows_in_the_motions_to_the_rolling_model():
    """With the stiffness experiment's squeezes, the rolling reference predicts the toy
    block's motions best at the plant's own thumb spring and clearly worse at +-15%
    (measured, 3 actions: sums of squares 22 / 6.9 / 14 in units of 0.05 mm and 0.05 deg; 20
    actions: 352 / 45 / 168), while Eq. 9 barely tells them apart (292 / 290 / 311)."""
    from vlr_drake.identify import default_squeeze

    r = run_agreement("toy_block", actions=4, squeeze=default_squeeze("physics", "stiffness"),
                      spring_scales=[0.85, 1.0, 1.15])
    sp = r["spring_profile"]
    assert sp["spring"] == [0, 1] and sp["scales"] == [0.85, 1.0, 1.15] and sp["actions"] >= 3
    rolling, eq9 = np.array(sp["rolling_sum_sq"]), np.array(sp["eq9_sum_sq"])
    assert rolling[1] < 0.6 * min(rolling[0], rolling[2])
    contrast_rolling = min(rolling[0], rolling[2]) / rolling[1]
    contrast_eq9 = min(eq9[0], eq9[2]) / eq9[1]
    assert contrast_eq9 < 1.2 and contrast_rolling > 1.5 * contrast_eq9
    # the toy block is a box: no curved surface to roll over, no rolling_shaped prediction
    assert r["rolling_shaped_one_step_error_mm_median"] is None and r["joint_motion_slope_rolling_shaped"] is None
    assert r["rolling_released_one_step_error_mm_median"] is None
    # the profile's scales and spring are checked
    with pytest.raises(ValueError, match="'spring_scales' must be positive"):
        run_agreement("toy_block", actions=1, spring_scales=[0.0])
    with pytest.raises(ValueError, match="'spring' must name a finger and joint"):
        run_agreement("toy_block", actions=1, spring_scales=[1.0], spring=(5, 0))
    # no action solved at every scale (a power grasp, a run of one action): said as none, where
    # the summary had raised after the whole run
    from vlr_drake.physics.agreement import _profile_summary

    none = _profile_summary([{"spring_profile": {"rolling_mm": [0.1, None], "rolling_deg": [0.1, 0.2],
                                                 "eq9_mm": [0.1, 0.2], "eq9_deg": [0.1, 0.2]}}],
                            {"hands": [object()], "spring": [0, 1], "scales": [0.9, 1.1]})
    assert none["actions"] == 0 and none["rolling_mm_median"] is None and none["eq9_sum_sq"] is None


def test_an_object_that_falls_ends_the_comparison_with_what_it_compared(monkeypatch, tmp_path, capsys):
    """The object falling out of the hand (RunStopped) had ended the command in a traceback,
    the actions compared before it lost: they are reported, with when and why it stopped."""
    from vlr_drake.identify import RunStopped
    from vlr_drake.physics_identify import PhysicsAdapter

    act, calls = PhysicsAdapter.act, []

    def falls_at_2(self, dl, timing):
        calls.append(dl)
        if len(calls) == 2:
            raise RunStopped("the apple fell out of the hand (injected)")
        return act(self, dl, timing)

    monkeypatch.setattr(PhysicsAdapter, "act", falls_at_2)
    path = tmp_path / "fell.json"
    r = main(["--actions", "3", "--hold", "0.05", "--json", str(path)])
    assert len(r["actions"]) == 1 and r["stopped"] == "action 2: the apple fell out of the hand (injected)"
    assert r["hold"] is None and json.loads(path.read_text())["stopped"] == r["stopped"]
    assert "stopped at action 2: the apple fell out" in capsys.readouterr().out



def test_the_model_state_starts_at_the_vlrs_equilibrium_or_says_it_has_none(monkeypatch):
    """The agreement's VLR starts from the tendon state that holds the plant's grasp (the
    Model O's angles kept as they are), and a grasp the VLR holds with no tendon state is
    said (it had started from a zero stretch, silently)."""
    import dataclasses

    from vlr_drake import grasps, motion
    from vlr_drake.physics import agreement

    h = model_o().model()
    g = grasps.sample_grasps(h, np.random.default_rng(0), 1)
    R, t = np.eye(3), np.array([0.0, 0.0, 0.1])
    state = agreement._ModelState(h, g.theta[0], g.a[0], R, t)
    eq = motion.equilibrium(h, g.theta, a=g.a)
    np.testing.assert_array_equal(state.theta, g.theta)
    np.testing.assert_array_equal(state.stretch, eq.stretch)
    monkeypatch.setattr(motion, "equilibrium", lambda *args, **kw: dataclasses.replace(eq, ok=np.array([False])))
    with pytest.raises(RuntimeError, match="no tendon state that holds the plant's grasp"):
        agreement._ModelState(h, g.theta[0], g.a[0], R, t)


def test_each_physics_flag_applies(monkeypatch):
    """--physics gravity=0 --physics time_step=0.00025 had run with gravity: the second flag
    replaced the first's settings."""
    import vlr_drake.physics.agreement as agreement

    class Ran(Exception):
        pass

    seen = {}

    def fake_run(*args, physics=None, **kw):
        seen["physics"] = physics
        raise Ran

    monkeypatch.setattr(agreement, "run_agreement", fake_run)
    with pytest.raises(Ran):
        main(["--physics", "gravity=0", "--physics", "time_step=0.00025", "settle_window=0.02"])
    assert (seen["physics"].gravity, seen["physics"].time_step, seen["physics"].settle_window) == (0.0, 0.00025, 0.02)


def test_a_model_with_no_equilibrium_at_a_later_action_is_one_failure(monkeypatch):
    """The one-step model restarts at the plant's truth before each action; where the VLR
    had no equilibrium there, the run had ended in a RuntimeError traceback and lost the
    actions before it (a review). That action counts as a model failure."""
    from vlr_drake.physics import agreement

    real, calls = agreement.motion.equilibrium, [0]

    def failing_third(*args, **kwargs):  # the one-step model's restart at action 2
        eq = real(*args, **kwargs)
        calls[0] += 1
        if calls[0] == 3:
            eq.ok[:] = False
        return eq

    monkeypatch.setattr(agreement.motion, "equilibrium", failing_third)
    r = run_agreement("toy_block", actions=3)
    assert len(r["actions"]) == 3 and r["model_failures"] == 1 and r["stopped"] is None
