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


@pytest.fixture(autouse=True)
def _motor_records(tmp_path_factory, monkeypatch):
    """Each test keeps its motors' records (HardwareConfig.motor_record "auto") in a folder of
    its own, not in the user's ~/.local/state: emulated buses reuse their pty names."""
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path_factory.mktemp("state")))


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


@pytest.fixture
def filter_fails_at_4(monkeypatch):
    """The particle filter's fourth step raises FloatingPointError("an injected failure"): a
    solver's or the filter's own failure, for the runs that must keep the iterations before it."""
    from vlr_drake import filter as pf

    step = pf.SelfIdentificationFilter.step

    def fails_at_4(self, *args, **kwargs):
        if self.iteration == 3:
            raise FloatingPointError("an injected failure")
        return step(self, *args, **kwargs)

    monkeypatch.setattr(pf.SelfIdentificationFilter, "step", fails_at_4)
