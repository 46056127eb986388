"""The compiled contact kinematics the Newton solver uses: position, first and second
derivatives against the batched forward kinematics and central differences."""

import numpy as np
import pytest

from vlr_drake import kinematics


def _derivatives(hand, theta, a):
    """Contact, Jacobian and Hessian of every finger for W configurations side by side:
    theta (W, N, K), a (W, N) -> (W, N, 3), (W, N, 3, K), (W, N, 3, K, K)."""
    W = theta.shape[0]
    N, K = hand.N, hand.K
    P, J, H = np.empty((N, 3, W)), np.empty((N, 3, K, W)), np.empty((N, 3, K, K, W))
    lanes = np.ascontiguousarray(np.moveaxis(theta, 0, -1))  # (N, K, W): the kernels' layout
    L = np.ascontiguousarray(np.repeat(hand.link_lengths[..., None], W, axis=-1))
    a_l = np.ascontiguousarray(a.T)
    for i in range(N):
        kinematics.finger_contact_derivatives(lanes[i], L[i], a_l[i], hand.pad[i], hand.base[i], hand.u[i],
                                              P[i], J[i], H[i])
    return np.moveaxis(P, -1, 0), np.moveaxis(J, -1, 0), np.moveaxis(H, -1, 0)


@pytest.mark.parametrize("hand_name", ["model_o_hand", "hand_4x3"])
def test_contact_derivatives_match_central_differences(request, hand_name, rng):
    hand = request.getfixturevalue(hand_name)
    N, K = hand.N, hand.K
    h = 1e-6
    W = 20  # twenty configurations as lanes of one call
    theta = rng.uniform(-0.3, 1.2, (W, N, K))
    a = rng.uniform(0.01, 0.04, (W, N))
    P, J, H = _derivatives(hand, theta, a)
    np.testing.assert_allclose(P, kinematics.contacts(hand, theta, a), atol=1e-15)
    for k in range(K):
        step = np.zeros((N, K))
        step[:, k] = h
        Pp, Jp, _ = _derivatives(hand, theta + step, a)
        Pm, Jm, _ = _derivatives(hand, theta - step, a)
        # a finger's contact depends on its own joints only: one column per finger at once
        np.testing.assert_allclose(J[..., k], (Pp - Pm) / (2 * h), atol=1e-10)
        np.testing.assert_allclose(H[..., k], (Jp - Jm) / (2 * h), atol=1e-9)
    np.testing.assert_array_equal(H, np.swapaxes(H, -1, -2))


def test_lanes_are_independent(model_o_hand, rng):
    """Each lane's derivatives are those of its configuration computed alone."""
    theta = rng.uniform(-0.3, 1.2, (7, model_o_hand.N, model_o_hand.K))
    a = rng.uniform(0.01, 0.04, (7, model_o_hand.N))
    together = _derivatives(model_o_hand, theta, a)
    for w in range(7):
        alone = _derivatives(model_o_hand, theta[w : w + 1], a[w : w + 1])
        for x, y in zip(together, alone, strict=True):
            np.testing.assert_array_equal(x[w], y[0])


def test_sincos_matches_numpy_to_a_few_ulp():
    """The vectorisable sine and cosine of the Newton kernel agree with numpy's to 2 units in
    the last place, across quadrants, signs and many turns."""
    x = np.concatenate([np.linspace(-100.0, 100.0, 400_001), [0.0, -0.0, np.pi / 4, np.pi / 2, -np.pi, 1e-300]])
    s, c = np.empty_like(x), np.empty_like(x)
    for j, v in enumerate(x):
        s[j], c[j] = kinematics.sincos(v)
    np.testing.assert_allclose(s, np.sin(x), rtol=0, atol=2.3e-16)
    np.testing.assert_allclose(c, np.cos(x), rtol=0, atol=2.3e-16)
    big = np.abs(np.sin(x)) > 1e-3
    assert np.max(np.abs(s - np.sin(x))[big] / np.spacing(np.abs(np.sin(x[big])))) <= 2


@pytest.mark.parametrize("hand_name", ["model_o_hand", "hand_4x3"])
def test_contact_force_torque_is_the_virtual_work_of_the_forces(request, hand_name, rng):
    """tau = J^T f: the joint torques of forces at the contacts are the derivatives of the
    forces' work f . p(theta) (central differences), per particle and with link lengths of
    their own; a force across a finger's plane does no work, and one force shared by every
    particle (leading axis 1) gives the same torques as the force repeated."""
    hand = request.getfixturevalue(hand_name)
    N, K, P = hand.N, hand.K, 6
    theta = rng.uniform(-0.3, 1.2, (P, N, K))
    a = rng.uniform(0.01, 0.04, (P, N))
    L = hand.link_lengths[None] * rng.uniform(0.8, 1.2, (P, N, K - 1))
    f = rng.normal(size=(P, N, 3))
    tau = kinematics.contact_force_torque(hand, theta, a, f, L)
    h = 1e-6
    for k in range(K):
        step = np.zeros((N, K))
        step[:, k] = h
        work = [np.einsum("pnc,pnc->pn", f, kinematics.contacts(hand, theta + s, a, L)) for s in (step, -step)]
        np.testing.assert_allclose(tau[..., k], (work[0] - work[1]) / (2 * h), atol=1e-9)
    across = np.cross(np.array([0.0, 0.0, 1.0]), hand.u)  # each finger's joint axis
    np.testing.assert_allclose(kinematics.contact_force_torque(hand, theta, a, across[None], L), 0.0, atol=1e-15)
    shared = kinematics.contact_force_torque(hand, theta, a, f[:1], L)
    np.testing.assert_allclose(shared, kinematics.contact_force_torque(hand, theta, a, np.repeat(f[:1], P, 0), L))
    with pytest.raises(ValueError, match="'force' must have shape"):
        kinematics.contact_force_torque(hand, theta, a, f[:, :, :2], L)
