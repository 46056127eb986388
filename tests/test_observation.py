"""The observation function Lambda (Eq. 5) and the rotation helpers of vlr_drake.observation:
rigid prediction of the POM from moved contacts, refusal of collinear contacts, and the
compiled rotation-vector kernels against scipy's implementation."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from vlr_drake import grasps, kinematics, motion, observation


def _random_rotations(rng, count):
    return Rotation.random(count, random_state=rng.integers(2**31)).as_matrix()


def test_pom_pose_recovers_a_rigid_motion(rng):
    P = 200
    p_O = rng.normal(scale=0.04, size=(P, 3, 3))
    R = _random_rotations(rng, P)
    t = rng.normal(scale=0.1, size=(P, 3))
    p_P = np.einsum("pij,pnj->pni", R, p_O) + t[:, None, :]
    R_est, t_est, ok = observation.pom_pose(p_O, p_P)
    assert ok.all()
    np.testing.assert_allclose(R_est, R, atol=1e-12)
    np.testing.assert_allclose(t_est, t, atol=1e-12)


def test_the_pom_moves_rigidly_with_the_contacts_through_gamma(model_o_hand, rng):
    """After a move with Gamma, the predicted POM keeps its distance to every contact."""
    h = model_o_hand
    g = grasps.sample_grasps(h, rng, 300)
    p0 = kinematics.contacts(h, g.theta, g.a)
    pom = rng.normal(scale=0.01, size=(g.theta.shape[0], 3)) + p0.mean(axis=1)  # a POM near the object
    p_O = observation.attach(p0, np.eye(3)[None], pom)
    res = motion.move(h, g.theta, rng.uniform(-1e-3, 1e-3, h.N), a=g.a, D2=g.D2, stretch=g.stretch)
    assert res.ok.mean() > 0.75  # some random actions have no equilibrium (the grasp's fold)
    p1 = kinematics.contacts(h, res.theta, g.a)
    R1, t1, ok = observation.pom_pose(p_O, p1)
    keep = res.ok & ok
    before = np.linalg.norm(p0 - pom[:, None, :], axis=2)[keep]
    after = np.linalg.norm(p1 - t1[:, None, :], axis=2)[keep]
    np.testing.assert_allclose(after, before, rtol=0, atol=1e-9)
    # and the attached points land on the moved contacts
    mapped = np.einsum("pij,pnj->pni", R1, p_O) + t1[:, None, :]
    np.testing.assert_allclose(mapped[keep], p1[keep], rtol=0, atol=1e-9)


def test_collinear_contacts_are_refused_and_flagged():
    line = np.array([[[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.03, 0.0, 0.0]]])
    with pytest.raises(observation.CollinearContactsError, match="collinear"):
        observation.attach(line, np.eye(3)[None], np.zeros((1, 3)))
    good = np.array([[[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.0, 0.02, 0.0]]])
    R, t, ok = observation.pom_pose(np.concatenate([good, good]), np.concatenate([good, line]))
    assert ok.tolist() == [True, False]
    assert np.all(np.isfinite(R)) and np.all(np.isfinite(t))
    np.testing.assert_array_equal(R[1], np.eye(3))
    # a NaN contact (in either set, any finger) is no pose either: it had given ok with a NaN R
    for which in range(3):
        bad = good.copy()
        bad[0, which, 1] = np.nan
        for p_O, p_P in ((good, bad), (bad, good)):
            R, t, ok = observation.pom_pose(np.concatenate([good, p_O]), np.concatenate([good, p_P]))
            assert ok.tolist() == [True, False] and np.all(np.isfinite(R))
    with pytest.raises(ValueError, match="p_O"):
        observation.pom_pose(np.zeros((2, 2, 3)), np.zeros((2, 2, 3)))
    # a fourth contact that is not finite: no pose, and no NaN position (it had been ok)
    four = np.concatenate([good, [[[0.01, 0.01, 0.0]]]], axis=1)
    moved = four.copy()
    moved[0, 3, 0] = np.nan
    R, t, ok = observation.pom_pose(np.concatenate([four, four]), np.concatenate([four, moved]))
    assert ok.tolist() == [True, False] and np.all(np.isfinite(t))
    np.testing.assert_allclose(t[1], good[0].mean(axis=0))  # the finite contacts' centroid


def test_fit_pose_refuses_points_on_one_line(rng):
    """Points on a line leave the turn about it free: the SVD's other directions are
    rounding, and a pose had come back as if it were the fit."""
    line = np.linspace(0.0, 0.05, 4)[:, None] * np.array([1.0, 2.0, -0.5])
    good = rng.normal(scale=0.04, size=(2, 4, 3))
    p_O = np.concatenate([good, line[None] + 0.01])
    with pytest.raises(observation.CollinearContactsError, match="1 of 3 poses lie on one line.*pose 2"):
        observation.fit_pose(p_O, p_O + 0.1)
    with pytest.raises(observation.CollinearContactsError, match="one line"):  # one point
        observation.fit_pose(np.zeros((1, 3, 3)), np.ones((1, 3, 3)))
    R, _ = observation.fit_pose(good, good)  # (points that fix a pose are unchanged)
    np.testing.assert_allclose(R, np.broadcast_to(np.eye(3), R.shape), atol=1e-12)


def test_fit_pose_is_the_least_squares_pose_whatever_the_points_order(rng):
    """pom_pose fits three contacts exactly; for points that are not rigid that depends on
    their order (0.27-0.72 deg on one case), fit_pose's least-squares pose does not."""
    P, N = 50, 4
    p_O = rng.normal(scale=0.04, size=(P, N, 3))
    R = _random_rotations(rng, P)
    t = rng.normal(scale=0.1, size=(P, 3))
    p_P = np.einsum("pij,pnj->pni", R, p_O) + t[:, None, :]
    R1, t1 = observation.fit_pose(p_O, p_P)  # rigid: exact
    np.testing.assert_allclose(R1, R, atol=1e-10)
    np.testing.assert_allclose(t1, t, atol=1e-10)
    noisy = p_P + rng.normal(scale=2e-4, size=p_P.shape)
    order = [2, 0, 3, 1]
    Ra, ta = observation.fit_pose(p_O, noisy)
    Rb, tb = observation.fit_pose(p_O[:, order], noisy[:, order])
    np.testing.assert_allclose(Ra, Rb, atol=1e-12)
    np.testing.assert_allclose(ta, tb, atol=1e-12)
    assert np.allclose(np.linalg.det(Ra), 1.0)
    Rc = observation.pom_pose(p_O, noisy)[0]
    Rd = observation.pom_pose(p_O[:, order], noisy[:, order])[0]
    assert np.abs(Rc - Rd).max() > 1e-4  # the exact fit of three: another three, another pose
    with pytest.raises(ValueError, match="finite"):
        observation.fit_pose(p_O, np.full_like(p_O, np.nan))


def test_rotation_vectors_match_scipy(rng):
    R = _random_rotations(rng, 2000)
    np.testing.assert_allclose(observation.rotvec(R), Rotation.from_matrix(R).as_rotvec(), atol=1e-9)
    w = rng.normal(size=(2000, 3))
    np.testing.assert_allclose(observation.rotvec_to_matrix(w), Rotation.from_rotvec(w).as_matrix(), atol=1e-12)
    # the edges: no rotation, tiny rotations, and half turns (axis from the symmetric part)
    small = np.array([[0.0, 0.0, 0.0], [1e-9, -2e-9, 3e-9], [0.0, 0.0, 1e-7]])
    np.testing.assert_allclose(observation.rotvec(observation.rotvec_to_matrix(small)), small, atol=1e-15)
    for axis in np.eye(3):
        half = np.pi * axis
        back = observation.rotvec(observation.rotvec_to_matrix(half))[0]
        assert np.isclose(np.linalg.norm(back), np.pi)
        np.testing.assert_allclose(np.abs(back), np.abs(half), atol=1e-7)
    # just short of a half turn, where arccos loses the angle (the round trip had been 8e-4 rad
    # off at pi - 1e-6), with the sign of the axis kept (it had been taken from the diagonal)
    for d in (1e-6, 2e-6, 1e-5, 1e-4, 0.05, 0.13):
        axis = rng.normal(size=(20, 3))
        w = (np.pi - d) * axis / np.linalg.norm(axis, axis=1, keepdims=True)
        np.testing.assert_allclose(observation.rotvec(Rotation.from_rotvec(w).as_matrix()), w, atol=1e-9)
    # bad input named: a reflection, and shapes that are no rotations (they had been reshaped)
    with pytest.raises(ValueError, match="not a rotation"):
        observation.rotvec(np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(ValueError, match="must have shape"):
        observation.rotvec(np.zeros((2, 9)))
    with pytest.raises(ValueError, match="must have shape"):
        observation.rotvec_to_matrix(np.zeros(6))


def test_blend_poses_interpolates_on_the_rotation_group(rng):
    P = 100
    R_a = _random_rotations(rng, P)
    t_a = rng.normal(size=(P, 3))
    R_b = _random_rotations(rng, 1)[0]
    t_b = rng.normal(size=3)
    R0, t0 = observation.blend_poses(R_a, t_a, R_b, t_b, 0.0)
    np.testing.assert_allclose(R0, R_a, atol=1e-12)
    R1, t1 = observation.blend_poses(R_a, t_a, R_b, t_b, 1.0)
    np.testing.assert_allclose(R1, np.broadcast_to(R_b, R_a.shape), atol=1e-9)
    np.testing.assert_allclose(t1, np.broadcast_to(t_b, t_a.shape), atol=1e-15)
    f = 0.3
    Rf, tf = observation.blend_poses(R_a, t_a, R_b, t_b, f)
    d = Rotation.from_matrix(np.swapaxes(R_a, 1, 2) @ R_b).as_rotvec()
    want = R_a @ Rotation.from_rotvec(f * d).as_matrix()
    np.testing.assert_allclose(Rf, want, atol=1e-9)
    np.testing.assert_allclose(tf, (1 - f) * t_a + f * t_b, atol=1e-15)
    # positions of fewer poses than rotations had been written past the output's end
    with pytest.raises(ValueError, match="blend_poses: R_a must be .* and t_a"):
        observation.blend_poses(R_a, t_a[:10], R_b, t_b, f)
    with pytest.raises(ValueError, match="blend_poses: R_b"):
        observation.blend_poses(R_a, t_a, R_b[:2], t_b, f)


def test_in_frame_expresses_points_in_each_particles_frame(rng):
    P = 50
    R = _random_rotations(rng, P)
    t = rng.normal(size=(P, 3))
    p = rng.normal(size=(P, 4, 3))
    want = np.einsum("pji,pnj->pni", R, p - t[:, None, :])  # R^T (p - t)
    np.testing.assert_allclose(observation.in_frame(p, R, t), want, atol=1e-14)
    # one frame for every particle
    np.testing.assert_allclose(observation.in_frame(p, R[0], t[0]),
                               np.einsum("ji,pnj->pni", R[0], p - t[0]), atol=1e-14)
    # rotations per particle with one translation, and the reverse
    np.testing.assert_allclose(observation.in_frame(p, R, t[0]),
                               np.einsum("pji,pnj->pni", R, p - t[0]), atol=1e-14)
    np.testing.assert_allclose(observation.in_frame(p, R[0], t),
                               np.einsum("ji,pnj->pni", R[0], p - t[:, None, :]), atol=1e-14)
    # and back: R p^O + t
    back = np.einsum("pij,pnj->pni", R, observation.in_frame(p, R, t)) + t[:, None, :]
    np.testing.assert_allclose(back, p, atol=1e-14)
    with pytest.raises(ValueError, match="do not match"):
        observation.in_frame(p, R[:3], t)


def test_attach_refuses_contacts_and_poses_it_cannot_attach_by(rng):
    """attach had called NaN contacts collinear, given NaN attachments for a NaN contact after
    the third or a NaN pose, and mirrored ones for a reflection R_PO, all without a word."""
    p = rng.normal(size=(1, 4, 3)) * 0.05
    for i in (0, 3):
        bad = p.copy()
        bad[0, i, 0] = np.nan
        with pytest.raises(ValueError, match="the contacts are not finite"):
            observation.attach(bad, np.eye(3)[None], np.zeros((1, 3)))
    with pytest.raises(ValueError, match="POM pose .* is not finite"):
        observation.attach(p, np.eye(3)[None], np.full((1, 3), np.nan))
    with pytest.raises(ValueError, match="R_PO is not a rotation"):
        observation.attach(p, np.diag([1.0, 1.0, -1.0])[None], np.zeros((1, 3)))
    np.testing.assert_allclose(observation.attach(p, np.eye(3)[None], np.zeros((1, 3))), p)


def test_rotvec_names_a_matrix_that_is_not_finite():
    """A NaN matrix (a lost pose) had been refused as "a reflection"."""
    with pytest.raises(ValueError, match="rotvec: R is not finite"):
        observation.rotvec(np.full((3, 3), np.nan))
    with pytest.raises(ValueError, match="reflection"):
        observation.rotvec(np.diag([1.0, 1.0, -1.0]))


def test_rotvec_refuses_a_scaled_rotation():
    """A rotation times 2 (determinant 8) had come out as a rotation vector of another angle
    (2 I as 0 rad, 2 R_z(30 deg) as 57 deg)."""
    R = np.stack([np.eye(3), observation.rotvec_to_matrix(np.array([0.0, 0.0, np.deg2rad(30)]))[0]])
    with pytest.raises(ValueError, match="not a rotation .*matrix 1's determinant is 8"):
        observation.rotvec(R * np.array([1.0, 2.0])[:, None, None])
    np.testing.assert_allclose(observation.rotvec(R)[1], [0.0, 0.0, np.deg2rad(30)], atol=1e-12)
