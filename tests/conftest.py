"""Shared fixtures: hands and seeded random generators."""

import numpy as np
import pytest

from vlr_drake.hand import generic_hand, model_o


@pytest.fixture(scope="session")
def model_o_hand():
    return model_o().model()


@pytest.fixture(scope="session")
def hand_4x3():
    return generic_hand(4, 3).model()


@pytest.fixture
def rng():
    return np.random.default_rng(12345)
