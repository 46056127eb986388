"""The hand specification: validation, derived arrays, novel hands."""

import numpy as np
import pytest

from vlr_drake.hand import HandSpec, generic_hand, hand_by_name, model_o, novel_finger


def test_model_o_arrays(model_o_hand):
    h = model_o_hand
    assert (h.N, h.K) == (3, 2)
    np.testing.assert_allclose(h.link_lengths[:, 0], 0.062)
    # thumb opposes the two fingers
    assert h.u[0] @ h.u[1] == pytest.approx(-1.0)
    np.testing.assert_allclose(h.R[0, :2], h.moment_arms[0])
    assert h.constraint_pairs.tolist() == [[0, 1], [0, 2], [1, 2]]


def test_generic_hand_constraints():
    h = generic_hand(5, 3).model()
    assert h.num_constraints == 3 * 5 - 6
    assert h.R.shape == (5, 15)
    # R theta per finger, batched over particles, agrees with the matrix form of Eq. 7
    theta = np.random.default_rng(0).uniform(-0.2, 1.5, (4, 5, 3))
    np.testing.assert_allclose(h.tendon_travel(theta), theta.reshape(4, 15) @ h.R.T, atol=1e-15)


def test_novel_hands_replace_the_right_fingers():
    nh3 = hand_by_name("NH3").model()
    base = model_o().model()
    np.testing.assert_allclose(nh3.base, base.base)  # mounted where the old fingers were
    assert nh3.link_lengths[:, 0].tolist() == pytest.approx([0.040, 0.050, 0.050])
    nf3 = novel_finger("NF3")
    assert nh3.pad[2] == pytest.approx(nf3.pad_offset - nf3.pad_radius)  # the pad's centre of curvature
    assert nh3.pad_surface[2] == pytest.approx(nf3.pad_offset)
    nh1 = hand_by_name("NH1").model()
    assert nh1.link_lengths[:, 0].tolist() == pytest.approx([0.040, 0.062, 0.062])


@pytest.mark.parametrize(
    "field, value, message",
    [
        ("link_lengths", [-0.01], "link_lengths"),
        ("stiffness", [0.08, -1.0], "stiffness"),
        ("moment_arms", [0.009], "moment_arms"),
        ("flexion_direction", [0.0, 0.0, 1.0], "flexion_direction"),
        ("tendon_range", [0.01, 0.0], "tendon_range"),
        # not finite: a NaN passes a "< 0" check, an infinite length reaches Drake's parser
        ("distal_length", float("inf"), "distal_length"),
        ("tendon_stiffness", float("inf"), "tendon_stiffness"),
        ("friction", float("nan"), "friction"),
        ("tendon_damping", float("nan"), "tendon_damping"),
        ("pad_offset", float("nan"), "pad_offset"),
        ("joint_damping", [0.01, -0.01], "joint_damping"),
        # of the wrong type: numpy's TypeError had come out instead, naming nothing
        ("stiffness", 0.08, "field 'stiffness' must be a list of 2 numbers, got 0.08"),
        ("moment_arms", ["a", "b"], "field 'moment_arms' must be a list of 2 numbers"),
        ("distal_length", "long", "field 'distal_length' must be a number, got 'long'"),
        # in another unit: each ran, and gave a wrong result or none (review)
        ("link_lengths", [62.0], r"'link_lengths': \[62.0\] m .*given in millimetres"),
        ("tendon_range", [0.0, 45.0], "'tendon_range'.*given in millimetres"),
        ("joint_upper", [110.0, 110.0], "'joint_upper'.*given in degrees"),
        ("link_density", 1.1, "'link_density'.*given in g/cm"),
        ("stiffness", [80.0, 160.0], r"'stiffness': \[80.0, 160.0\] N m/rad .*given in N mm/rad"),
    ],
)
def test_bad_finger_fields_are_named(field, value, message):
    spec = model_o()
    setattr(spec.fingers[1], field, value)
    with pytest.raises(ValueError, match=message):
        spec.validate()


def test_too_few_fingers_and_unknown_names():
    spec = model_o()
    with pytest.raises(ValueError, match="at least 3 fingers"):
        HandSpec(name="two", fingers=spec.fingers[:2]).validate()
    with pytest.raises(ValueError, match="'palm_radius': 75.0 m .*millimetres"):
        HandSpec(name="mm", fingers=spec.fingers, palm_radius=75.0).validate()
    # names go into the SDF (a quote had ended in Drake's XML parser); a scalar moment_arms on
    # the first finger had raised a TypeError before the finger's own named check
    with pytest.raises(ValueError, match="hand: field 'name' must be letters"):
        HandSpec(name='my "hand"', fingers=spec.fingers).validate()
    bad = model_o()
    bad.fingers[0].name = "thumb::x"
    with pytest.raises(ValueError, match="field 'name' must be letters"):
        bad.validate()
    bad = model_o()
    bad.fingers[0].moment_arms = 0.009
    with pytest.raises(ValueError, match="field 'moment_arms' must be a list"):
        bad.validate()
    with pytest.raises(ValueError, match="unknown hand"):
        hand_by_name("NH9")
    with pytest.raises(ValueError, match="no finger 'pinky'"):
        spec.replaced({"pinky": novel_finger("NF1")})


def test_joint_limits_and_tendon_range_checks(model_o_hand):
    """Batched limit checks against the hand's arrays: one angle or one pull just outside
    fails its hypothesis only."""
    h = model_o_hand
    theta = np.repeat(((h.joint_lower + h.joint_upper) / 2)[None], 3, axis=0)
    theta[1, 2, 0] = h.joint_upper[2, 0] + 1e-6
    theta[2, 0, 1] = h.joint_lower[0, 1] - 1e-6
    np.testing.assert_array_equal(h.within_joint_limits(theta), [True, False, False])
    l = np.repeat(h.tendon_range.mean(axis=1)[None], 3, axis=0)
    l[1, 1] = h.tendon_range[1, 1] + 1e-9
    l[2, 0] = h.tendon_range[0, 0]  # at the bound: inside
    np.testing.assert_array_equal(h.within_tendon_range(l), [[True] * 3, [True, False, True], [True] * 3])
