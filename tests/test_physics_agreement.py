"""The model-vs-physics agreement command (vlr_drake.physics.agreement)."""

import json

import numpy as np
import pytest

from vlr_drake.physics.agreement import main, run_agreement


def test_gamma_predicts_the_physics_plants_first_actions(tmp_path):
    """From the plant's true state, Gamma with the contact at the pad's centre of curvature
    predicts a thumb-vs-fingers pull's object motion in direction and size (measured: 1.18x,
    0.55 mm off a 3.1 mm motion; with the contact on the pad surface it was ~2x), and the
    carried model has not drifted yet."""
    path = tmp_path / "agreement.json"
    r = main(["--direction", "-1", "1", "1", "--step", "0.5e-3", "--actions", "2", "--json", str(path)])
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
    assert np.isfinite(r["one_step_error_mm_median"])


def test_bad_direction_is_named():
    with pytest.raises(ValueError, match="'direction' must be a nonzero vector of 3"):
        run_agreement(direction=[1.0, 0.0])
    with pytest.raises(ValueError, match="'actions' must be >= 1"):
        run_agreement(actions=0)
