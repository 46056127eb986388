"""The compiled contact kinematics the Newton solver uses: position, first and second
derivatives against the batched forward kinematics and central differences."""

import numpy as np
import pytest

from vlr_drake import kinematics


def _derivatives(hand, theta, a):
    """Contact, Jacobian and Hessian of every finger of one configuration."""
    N, K = hand.N, hand.K
    P, J, H = np.empty((N, 3)), np.empty((N, 3, K)), np.empty((N, 3, K, K))
    for i in range(N):
        kinematics.finger_contact_derivatives(theta[i], hand.link_lengths[i], a[i], hand.pad[i], hand.base[i],
                                              hand.u[i], P[i], J[i], H[i])
    return P, J, H


@pytest.mark.parametrize("hand_name", ["model_o_hand", "hand_4x3"])
def test_contact_derivatives_match_central_differences(request, hand_name, rng):
    hand = request.getfixturevalue(hand_name)
    N, K = hand.N, hand.K
    h = 1e-6
    for _ in range(20):
        theta = rng.uniform(-0.3, 1.2, (N, K))
        a = rng.uniform(0.01, 0.04, N)
        P, J, H = _derivatives(hand, theta, a)
        np.testing.assert_allclose(P, kinematics.contacts(hand, theta[None], a[None])[0], atol=1e-15)
        for k in range(K):
            step = np.zeros((N, K))
            step[:, k] = h
            Pp, Jp, _ = _derivatives(hand, theta + step, a)
            Pm, Jm, _ = _derivatives(hand, theta - step, a)
            # a finger's contact depends on its own joints only: one column per finger at once
            np.testing.assert_allclose(J[:, :, k], (Pp - Pm) / (2 * h), atol=1e-10)
            np.testing.assert_allclose(H[:, :, :, k], (Jp - Jm) / (2 * h), atol=1e-9)
        np.testing.assert_array_equal(H, np.swapaxes(H, 2, 3))
