"""The particle filter: its building blocks against their definitions, and honest
self-identification on the model plant (exact truth)."""

import numpy as np
import pytest

from vlr_drake import filter as pf
from vlr_drake.identify import IdentifyOptions, _truth_grasp, run_identification
from vlr_drake.model_plant import ModelPlant


def test_effective_sample_size_definition():
    assert pf.effective_sample_size(np.zeros(10)) == pytest.approx(10.0)
    w = np.array([0.5, 0.25, 0.25])
    assert pf.effective_sample_size(np.log(w)) == pytest.approx(1.0 / np.sum(w**2))
    assert pf.effective_sample_size(np.array([0.0, -np.inf, -np.inf])) == pytest.approx(1.0)
    assert pf.effective_sample_size(np.full(4, -np.inf)) == 0.0


def test_systematic_resampling_matches_its_definition():
    rng = np.random.default_rng(0)
    w = np.array([0.1, 0.0, 0.45, 0.2, 0.25])
    idx = pf.systematic_resample(w, rng)
    counts = np.bincount(idx, minlength=5)
    # each particle is copied floor(M w) or ceil(M w) times; zero weight never
    M = len(w)
    assert np.all(counts >= np.floor(M * w)) and np.all(counts <= np.ceil(M * w))
    assert counts[1] == 0
    # the same u reproduces the same ancestors; the definition with u drawn by hand:
    u = np.random.default_rng(7).random()
    expected = np.searchsorted(np.cumsum(w), (u + np.arange(M)) / M, side="right")
    np.testing.assert_array_equal(pf.systematic_resample(w, np.random.default_rng(7)), expected)
    with pytest.raises(ValueError, match="sum to 1"):
        pf.systematic_resample(np.array([0.5, 0.6]), rng)


def test_temper_hits_the_target_ess():
    rng = np.random.default_rng(1)
    log_lik = -0.5 * (rng.standard_normal(1000) * 30) ** 2
    assert pf.effective_sample_size(log_lik) < 100
    beta = pf.temper(log_lik, 100.0)
    assert 0 < beta < 1
    assert pf.effective_sample_size(beta * log_lik) == pytest.approx(100.0, rel=0.02)
    assert pf.temper(np.zeros(50), 10.0) == 1.0


def test_weighted_interval_matches_sorted_definition():
    rng = np.random.default_rng(2)
    x = rng.standard_normal((2000, 3))
    lo, hi = pf.interval95(x, np.full(2000, 1 / 2000))
    s = np.sort(x, axis=0)
    np.testing.assert_allclose(lo, s[int(np.ceil(0.025 * 2000)) - 1])
    np.testing.assert_allclose(hi, s[int(np.ceil(0.975 * 2000)) - 1])
    # weights move the quantiles: all mass on the top half
    w = (x[:, 0] > 0).astype(float)
    lo_w, _ = pf.interval95(x[:, :1], w / w.sum())
    assert lo_w[0] > 0


def _filter_and_plant(seed, particles=4000, **cfg):
    from vlr_drake.hand import model_o

    h = model_o().model()
    rng = np.random.default_rng(seed)
    th, a = _truth_grasp(h, rng)
    plant = ModelPlant(h, th, a, np.eye(3), np.array([0.0, 0.0, 0.11]), np.random.default_rng(seed + 1))
    f = pf.SelfIdentificationFilter(h, pf.FilterConfig(particles=particles, **cfg), pf.PriorConfig(),
                                    np.random.default_rng(seed + 2))
    R, t, _ = plant.measure()
    f.initialise(th + 0.03, a + 0.002, R, t)
    return h, plant, f


def test_roughening_keeps_mean_and_covariance():
    h, plant, f = _filter_and_plant(3, particles=20000)
    ps = f.particles
    before = f._unknowns(ps)
    f._roughen(ps)
    after = f._unknowns(ps)
    # the mean moves by no more than the jitter's sampling error (4 standard errors)
    assert np.all(np.abs(after.mean(0) - before.mean(0)) <= 4 * before.std(0) / np.sqrt(len(before)))
    np.testing.assert_allclose(after.std(0), before.std(0), rtol=0.05)
    # and the correlations (the ridge of angles and contacts) survive
    np.testing.assert_allclose(np.corrcoef(after, rowvar=False), np.corrcoef(before, rowvar=False), atol=0.05)


def test_lost_tag_moves_but_does_not_learn():
    h, plant, f = _filter_and_plant(6, particles=2000)
    dl = np.array([0.3e-3, -0.2e-3, 0.3e-3])
    assert plant.apply_action(dl)
    p_O_before = f.particles.p_O.copy()
    rep = f.step(dl, None, None, valid=False)
    assert not rep.measured and rep.ess == 2000
    np.testing.assert_array_equal(f.particles.p_O, p_O_before)  # attachments untouched
    assert np.all(np.isfinite(f.particles.theta))
    assert np.all(f.particles.log_w == 0)


def test_swapped_object_triggers_reinitialisation():
    h, plant, f = _filter_and_plant(5, particles=2000)
    for _ in range(3):
        dl = np.array([0.4e-3, 0.2e-3, -0.3e-3])
        plant.apply_action(dl)
        R, t, _ = plant.measure()
        f.step(dl, R, t)
    assert f.reinitialisations == 0
    # the object is swapped: the POM jumps 20 mm and turns 30 degrees
    from vlr_drake.observation import rotvec_to_matrix

    R_far = rotvec_to_matrix(np.array([0.0, np.deg2rad(30), 0.0]))[0] @ R
    rep = f.step(np.zeros(3), R_far, t + np.array([0.02, 0.0, 0.0]))
    assert rep.reinitialised and f.reinitialisations == 1
    assert f.particles.size == 2000 and np.all(np.isfinite(f.particles.theta))
    # it keeps working afterwards
    rep = f.step(np.zeros(3), R_far, t + np.array([0.02, 0.0, 0.0]))
    assert np.isfinite(rep.mean_interval_deg)


def test_bad_configuration_is_named():
    with pytest.raises(ValueError, match="particles"):
        pf.FilterConfig(particles=1).validate()
    with pytest.raises(ValueError, match="tendon"):
        pf.FilterConfig(tendon="rope").validate()
    from vlr_drake.hand import model_o

    with pytest.raises(ValueError, match="stiffness_unknown"):
        pf.SelfIdentificationFilter(model_o().model(), pf.FilterConfig(), pf.PriorConfig(stiffness_unknown=[(5, 0)]),
                                    np.random.default_rng(0))


@pytest.mark.slow
def test_known_hand_converges_accurately_and_honestly():
    """Model plant, exact truth, 3 seeds x 100 iterations at 20,000 particles: joint errors
    of a degree or two, contacts within a few millimetres, and the truth inside the 95%
    intervals for most joints. (Measured over 5 seeds: proximal 0.94 +- 0.35 deg, truth
    inside 80% of the joint intervals; the issue's goal of 90% is not reached yet, and this
    test holds what is.)"""
    inside, errors, proximal, contact = [], [], [], []
    for seed in range(3):
        r = run_identification(IdentifyOptions(experiment="known_hand", particles=20000, max_iterations=100,
                                               seed=seed, progress=False))
        inside.append(r["truth_inside_95_theta"])
        errors.append(r["joint_error_deg_mean"])
        proximal.append(np.mean(r["proximal_joint_error_deg"]))
        contact.append(np.mean(r["contact_error_mm"]))
        assert r["interval_half_width_deg_mean"] < 4.0  # it learnt: the prior is ~11 deg
    assert np.mean(proximal) < 1.5, proximal
    assert np.mean(errors) < 2.2, errors
    assert np.mean(contact) < 4.5, contact
    assert np.mean(inside) >= 0.7, inside
