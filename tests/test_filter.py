"""The particle filter: its building blocks against their definitions, and honest
self-identification on the model plant (exact truth)."""

import dataclasses

import numpy as np
import pytest

from vlr_drake import filter as pf
from vlr_drake import kinematics, motion, observation
from vlr_drake.hand import model_o
from vlr_drake.identify import IdentifyOptions, _truth_grasp, run_identification
from vlr_drake.model_plant import ModelPlant
from vlr_drake.systems.physics_plant import PhysicsConfig


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


def test_hand_parameter_report_measures_how_far_the_data_narrowed_each_parameter():
    from vlr_drake.identify import WEAKLY_IDENTIFIED, hand_parameter_report

    h = model_o().model()
    prior = pf.PriorConfig(stiffness_unknown=[(0, 1)], links_unknown=[2])
    shape_k, shape_L = (h.N, h.K), (h.N, h.K - 1)

    def est(k, k_lo, k_hi, L, L_lo, L_hi):
        e = {"stiffness": np.full(shape_k, 0.3), "link_lengths": np.full(shape_L, 0.05)}
        for key in ("stiffness", "link_lengths"):  # known entries: a point interval
            e[f"{key}_lo"], e[f"{key}_hi"] = e[key].copy(), e[key].copy()
        e["stiffness"][0, 1], e["stiffness_lo"][0, 1], e["stiffness_hi"][0, 1] = k, k_lo, k_hi
        e["link_lengths"][2, 0], e["link_lengths_lo"][2, 0], e["link_lengths_hi"][2, 0] = L, L_lo, L_hi
        return e

    start = est(0.2, 0.06, 0.38, 0.05, 0.032, 0.072)
    rep = hand_parameter_report(h, prior, est(0.18, 0.16, 0.24, 0.054, 0.036, 0.066), start)
    k = rep["hand_parameters"][f"stiffness:{h.names[0]}/1"]
    L = rep["hand_parameters"][f"link_length:{h.names[2]}"]
    assert k["narrowed_to"] == pytest.approx(0.08 / 0.32) and L["narrowed_to"] == pytest.approx(0.030 / 0.040)
    assert k["interval"] == pytest.approx([0.16, 0.24]) and k["prior_interval"] == pytest.approx([0.06, 0.38])
    assert k["prior_range"] == list(prior.stiffness_range) and L["unit"] == "m" and k["unit"] == "N m/rad"
    assert WEAKLY_IDENTIFIED < 0.75 and rep["weakly_identified"] == [f"link_length:{h.names[2]}"]
    assert (k["finger"], k["joint"], L["finger"], L["joint"]) == (0, 1, 2, 0)
    # a prior cloud of zero width (a fixed value): nothing to compare, not weakly identified
    point = est(0.2, 0.2, 0.2, 0.05, 0.05, 0.05)
    rep = hand_parameter_report(h, prior, point, point)
    assert all(v["narrowed_to"] is None for v in rep["hand_parameters"].values()) and rep["weakly_identified"] == []
    # nothing unknown: nothing to report
    assert hand_parameter_report(h, pf.PriorConfig(), start, start) == {"hand_parameters": {}, "weakly_identified": [],
                                                                           "object_mass_identified": None}
    for bad in (0, True, 8.5, pf.motion.MAX_ITER + 1):
        with pytest.raises(ValueError, match="newton_loose_after"):
            pf.FilterConfig(newton_loose_after=bad).validate()
    assert pf.FilterConfig(newton_loose_after=None).validate().newton_loose_after is None


def test_temper_hits_the_target_ess():
    rng = np.random.default_rng(1)
    log_lik = -0.5 * (rng.standard_normal(1000) * 30) ** 2
    assert pf.effective_sample_size(log_lik) < 100
    beta = pf.temper(log_lik, 100.0)
    assert 0 < beta < 1
    assert pf.effective_sample_size(beta * log_lik) == pytest.approx(100.0, rel=0.02)
    # the largest such beta
    assert pf.effective_sample_size(beta * log_lik) >= 100.0 > pf.effective_sample_size(beta * 1.0001 * log_lik)
    assert pf.temper(np.zeros(50), 10.0) == 1.0


def test_tempered_ess_matches_the_definition():
    """The bisection's compiled ESS equals 1 / sum(w^2) of the tempered weights, with
    impossible particles (-inf) weighing nothing."""
    rng = np.random.default_rng(3)
    log_w0 = rng.normal(size=500)
    log_lik = -0.5 * (3 * rng.standard_normal(500)) ** 2
    log_lik[::7] = -np.inf
    for beta in (0.0, 0.3, 1.0):
        finite = np.isfinite(log_lik)
        want = pf.effective_sample_size(log_w0 + np.where(finite, beta * np.where(finite, log_lik, 0.0), -np.inf))
        assert pf._tempered_ess(log_w0, log_lik, beta) == pytest.approx(want, rel=1e-12)
    assert pf._tempered_ess(np.full(5, -np.inf), np.zeros(5), 1.0) == 0.0


def test_tempering_search_returns_the_bisections_beta(monkeypatch):
    """The Newton search places beta on the bisection's grid exactly where the bisection
    does (where the ESS decreases along the grid, as it does from uniform weights), with
    far fewer ESS evaluations, down to the 1e-6 floor and for other grids; its slope kernel
    is the derivative of log ESS."""
    calls = {"ess": 0, "fallback": 0}
    ess, bisect = pf._tempered_ess, pf._temper_bisect

    def counted_ess(*args):
        calls["ess"] += 1
        return ess(*args)

    def counted_bisect(*args):
        calls["fallback"] += 1
        return bisect(*args)

    rng = np.random.default_rng(4)
    cases = []
    for trial in range(40):
        M = (200, 3000)[trial % 2]
        log_w0 = np.zeros(M) if trial % 4 == 0 else rng.normal(0.0, 0.3, M)
        log_lik = -0.5 * rng.chisquare(6, M) * 10.0 ** (trial % 8)  # beta from ~0.5 down past 1e-6
        log_lik[rng.random(M) < 0.1] = -np.inf
        cases.append((log_w0, log_lik, rng.uniform(0.1, 0.5) * M, (40, 40, 20, 52)[trial % 4]))
    interior = 0
    for log_w0, log_lik, target, iterations in cases:
        want = bisect(log_w0, log_lik, target, iterations)
        monkeypatch.setattr(pf, "_tempered_ess", counted_ess)
        monkeypatch.setattr(pf, "_temper_bisect", counted_bisect)
        calls.update(ess=0, fallback=0)
        beta = pf._temper_increment(log_w0, log_lik, target, iterations)
        monkeypatch.undo()
        assert beta == want
        assert calls["fallback"] == 0 and calls["ess"] <= 12  # the bisection takes iterations + 1
        grid = 2.0**-iterations
        if 1e-6 < beta < 1.0:  # the crossing, on the grid
            interior += 1
            assert ess(log_w0, log_lik, beta) >= target > ess(log_w0, log_lik, beta + grid)
            assert beta / grid == np.floor(beta / grid)
    assert interior >= 20 and sum(bisect(*c) == 1e-6 for c in cases) >= 3
    log_w0, log_lik = rng.normal(size=400), -0.5 * (3 * rng.standard_normal(400)) ** 2
    for beta in (0.01, 0.3):
        g, slope = pf._tempered_ess_slope(log_w0, log_lik, beta)
        assert g == pytest.approx(np.log(ess(log_w0, log_lik, beta)), rel=1e-12)
        e = 1e-6
        numeric = (np.log(ess(log_w0, log_lik, beta + e)) - np.log(ess(log_w0, log_lik, beta - e))) / (2 * e)
        assert slope == pytest.approx(numeric, rel=1e-5)
    # weights below the target already (not a state the filter tempers from): the bisection's answer
    low = np.r_[0.0, np.full(99, -20.0)]
    assert pf._temper_increment(low, -np.arange(100.0), 50.0) == bisect(low, -np.arange(100.0), 50.0)


def test_equal_weight_intervals_are_order_statistics():
    """After resampling (equal weights) the interval ends are the order statistics
    np.partition gives, ties and small clouds included."""
    rng = np.random.default_rng(6)
    for M in (1, 2, 3, 39, 40, 41, 1000, 4001):
        for ties in (False, True):
            x = rng.normal(size=(M, 2, 3))
            if ties:
                x = np.round(x, 1)
            lo, hi = pf.interval95(x, np.full(M, 1.0 / M))
            k = [int(np.ceil(q * M - 1e-9)) - 1 for q in (0.025, 0.975)]
            part = np.partition(x.reshape(M, -1), k, axis=0)
            np.testing.assert_array_equal(lo.ravel(), part[k[0]])
            np.testing.assert_array_equal(hi.ravel(), part[k[1]])
    with pytest.raises(ValueError, match="finite"):
        pf.interval95(np.array([[0.0], [np.inf]]), np.full(2, 0.5))


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


def _sorted_weighted_quantile(x, w, q):
    """The definition: the smallest sample whose cumulative normalised weight reaches q."""
    order = np.argsort(x, kind="stable")
    cw = np.cumsum(w[order])
    return x[order[np.argmax(cw / cw[-1] >= q)]]


def test_pooled_clouds_are_their_equal_mixture():
    """ParticleSet.pool: each cloud's weights normalised and scaled by 1/K whatever its size,
    so the pooled mean is the clouds' means' mean and its 95% interval lies between the
    clouds' own bounds; a known (shared) quantity stays one row; mixed sets are named."""
    prior = pf.PriorConfig(stiffness_unknown=[(0, 1)])
    h, f = _initialised(prior, pf.FilterConfig(particles=300), seed=3)
    a = f.particles
    _, g = _initialised(prior, pf.FilterConfig(particles=500), seed=4)
    b = g.particles
    b.log_w = np.random.default_rng(0).normal(0.0, 2.0, b.size)  # unequal weights, a different scale
    b.log_w[:7] = -np.inf  # hypotheses of weight 0 stay so
    pooled = pf.ParticleSet.pool([a, b])
    assert pooled.size == 800 and pooled.stiffness.shape[0] == 800
    w = pf.normalise(pooled.log_w)
    assert w[:300].sum() == pytest.approx(0.5) and w[300:].sum() == pytest.approx(0.5) and not w[300:307].any()
    est, ea, eb = (pf.cloud_estimate(h, x) for x in (pooled, a, b))
    for key in ("theta", "a", "stiffness"):
        np.testing.assert_allclose(est[key], 0.5 * (ea[key] + eb[key]), atol=1e-12)
        assert np.all(est[f"{key}_lo"] >= np.minimum(ea[f"{key}_lo"], eb[f"{key}_lo"]))
        assert np.all(est[f"{key}_lo"] <= np.maximum(ea[f"{key}_lo"], eb[f"{key}_lo"]))
        assert np.all(est[f"{key}_hi"] >= np.minimum(ea[f"{key}_hi"], eb[f"{key}_hi"]))
        assert np.all(est[f"{key}_hi"] <= np.maximum(ea[f"{key}_hi"], eb[f"{key}_hi"]))
    assert pf.cloud_estimate(h, a)["theta"] == pytest.approx(f.estimate()["theta"])  # the filter's estimate
    # one cloud pooled is itself; the link lengths (known here) stay one shared row
    np.testing.assert_allclose(pf.cloud_estimate(h, pf.ParticleSet.pool([b]))["theta"], eb["theta"])
    assert pooled.link_lengths.shape[0] == 1
    with pytest.raises(ValueError, match="'link_lengths' is known .* not the same"):
        pf.ParticleSet.pool([a, dataclasses.replace(b, link_lengths=b.link_lengths * 1.1)])
    with pytest.raises(ValueError, match="'stiffness' is known \\(one row\\) in some sets and one per particle"):
        pf.ParticleSet.pool([a, dataclasses.replace(b, stiffness=b.stiffness[:1])])
    one = a.take(np.array([5]))  # a one-particle cloud: its one row is per particle and known alike
    assert pf.ParticleSet.pool([one, b]).size == 1 + b.size and pf.ParticleSet.pool([one, b]).link_lengths.shape[0] == 1
    with pytest.raises(ValueError, match="'object_load' is in some sets and not in others"):
        pf.ParticleSet.pool([a, dataclasses.replace(b, object_load=np.zeros((b.size, h.N)))])
    with pytest.raises(ValueError, match="no particle sets"):
        pf.ParticleSet.pool([])


def test_weighted_interval_selection_matches_the_sorted_definition():
    """The weighted selection against a sort, on small hand-made clouds with ties, zero
    weights and one dominant particle, and on a large cloud where the histogram's bins
    hold many values each."""
    rng = np.random.default_rng(5)
    for trial in range(400):
        M = int(rng.integers(2, 40))
        x = rng.integers(0, 4, (M, 2)).astype(float) if trial % 2 else rng.standard_normal((M, 2))
        w = rng.random(M) * (rng.random(M) < 0.6)
        w[rng.integers(M)] += 1.0 if trial % 5 == 0 else 0.01
        lo, hi = pf.interval95(x, w / w.sum())
        for c in range(2):
            assert lo[c] == _sorted_weighted_quantile(x[:, c], w, 0.025)
            assert hi[c] == _sorted_weighted_quantile(x[:, c], w, 0.975)
    x = rng.standard_normal((50_000, 3, 2)).cumsum(axis=0)
    w = rng.random(50_000) ** 4
    lo, hi = pf.interval95(x, w / w.sum())
    flat = x.reshape(50_000, -1)
    np.testing.assert_array_equal(lo.ravel(), [_sorted_weighted_quantile(flat[:, c], w, 0.025) for c in range(6)])
    np.testing.assert_array_equal(hi.ravel(), [_sorted_weighted_quantile(flat[:, c], w, 0.975) for c in range(6)])
    with pytest.raises(ValueError, match="finite"):
        pf.interval95(np.array([[0.0], [np.nan]]), np.array([0.3, 0.7]))


def test_motion_error_widens_sigma_by_the_predicted_motion():
    """The likelihood against its definition: Gaussian in (dp, ang) with sigma^2 = s^2 +
    (c * predicted motion)^2 and its log-normaliser; c = 0 is the plain likelihood."""
    from vlr_drake.hand import model_o

    hand = model_o().model()
    R_prev = np.repeat(np.eye(3)[None], 2, axis=0)
    t_prev = np.zeros((2, 3))
    t_pred = np.array([[0.0, 0.0, 0.0], [0.010, 0.0, 0.0]])  # the second predicts a 10 mm move
    R_pred = R_prev.copy()
    dp = np.array([0.004, 0.004])
    ang = np.zeros(2)
    plain = pf.SelfIdentificationFilter(hand, pf.FilterConfig(), pf.PriorConfig(), np.random.default_rng(0))
    ll0, m0 = plain._log_likelihood(dp, ang, R_pred, t_pred, None, None)
    sp, sr = plain.config.sigma_position, plain.config.sigma_rotation
    np.testing.assert_allclose(m0, (dp / sp) ** 2)
    np.testing.assert_allclose(ll0, -0.5 * m0 - 1.5 * np.log(sp**2) - 1.5 * np.log(sr**2))
    c = 0.5
    f = pf.SelfIdentificationFilter(hand, pf.FilterConfig(motion_error=c), pf.PriorConfig(), np.random.default_rng(0))
    ll, m = f._log_likelihood(dp, ang, R_pred, t_pred, R_prev, t_prev)
    s2 = sp**2 + (c * np.linalg.norm(t_pred - t_prev, axis=1)) ** 2
    np.testing.assert_allclose(m, dp**2 / s2)
    np.testing.assert_allclose(ll, -0.5 * dp**2 / s2 - 1.5 * np.log(s2) - 1.5 * np.log(sr**2))
    assert ll[1] > ll[0]  # a 4 mm miss is plausible after a predicted 10 mm move ...
    ll_small, _ = f._log_likelihood(np.full(2, 1e-5), ang, R_pred, t_pred, R_prev, t_prev)
    assert ll_small[1] < ll_small[0]  # ... but the wider spread costs when both are close
    # the rotation's sigma widens by c times the predicted turn, in radians
    R_turn = R_pred.copy()
    R_turn[1] = observation.rotvec_to_matrix(np.array([0.0, 0.0, np.deg2rad(5.0)]))
    ang = np.array([0.0, 0.01])
    ll, m = f._log_likelihood(dp, ang, R_turn, t_pred, R_prev, t_prev)
    sr2 = sr**2 + (c * np.deg2rad(5.0) * np.array([0.0, 1.0])) ** 2
    np.testing.assert_allclose(m, dp**2 / s2 + ang**2 / sr2)
    np.testing.assert_allclose(ll, -0.5 * (dp**2 / s2 + ang**2 / sr2) - 1.5 * np.log(s2) - 1.5 * np.log(sr2))
    with pytest.raises(ValueError, match="motion_error"):
        pf.FilterConfig(motion_error=-1.0).validate()


def test_student_t_likelihood_matches_its_definition():
    """Two independent 3-D Student-t densities scaled to agree with the Gaussian near zero
    error, with logarithmic tails far out; bad settings are named."""
    from vlr_drake.hand import model_o

    hand = model_o().model()
    cfg = pf.FilterConfig(likelihood="student_t", likelihood_dof=4.0)
    f = pf.SelfIdentificationFilter(hand, cfg, pf.PriorConfig(), np.random.default_rng(0))
    g = pf.SelfIdentificationFilter(hand, pf.FilterConfig(), pf.PriorConfig(), np.random.default_rng(0))
    sp, sr, nu = cfg.sigma_position, cfg.sigma_rotation, 4.0
    dp = np.array([0.0, 1e-6, 0.3e-3, 3e-3])
    ang = np.array([0.0, 1e-6, np.deg2rad(1.5), 0.0])
    R = np.repeat(np.eye(3)[None], 4, axis=0)
    t = np.zeros((4, 3))
    ll, maha2 = f._log_likelihood(dp, ang, R, t, None, None)
    lg, maha2_g = g._log_likelihood(dp, ang, R, t, None, None)
    k = nu + 3  # the t's scale^2 is sigma^2 k / nu: -k/2 log(1 + r^2 nu / (nu k)) ~ -r^2 / 2 near 0
    want = (-0.5 * k * (np.log1p(dp**2 / (k * sp**2)) + np.log1p(ang**2 / (k * sr**2)))
            - 1.5 * np.log(sp**2) - 1.5 * np.log(sr**2))
    np.testing.assert_allclose(ll, want)
    np.testing.assert_allclose(maha2, maha2_g)  # the divergence test is unchanged
    np.testing.assert_allclose(ll[:2] - ll[0], lg[:2] - lg[0], atol=1e-9)  # the same near zero
    assert lg[0] - lg[3] == pytest.approx(50.0) and ll[0] - ll[3] < 10  # a 10-sigma miss: 50 nats, 9.5 for t
    with pytest.raises(ValueError, match="likelihood_dof"):
        pf.FilterConfig(likelihood="student_t", likelihood_dof=0.0).validate()
    with pytest.raises(ValueError, match="likelihood"):
        pf.FilterConfig(likelihood="cauchy").validate()


def _filter_and_plant(seed, particles=4000, **cfg):
    from vlr_drake.hand import model_o

    h = model_o().model()
    rng = np.random.default_rng(seed)
    th, a = _truth_grasp(h, rng)
    plant = ModelPlant(h, th, a, np.eye(3), np.array([0.0, 0.0, 0.11]), np.random.default_rng(seed + 1))
    f = pf.SelfIdentificationFilter(h, pf.FilterConfig(particles=particles, **cfg), pf.PriorConfig(),
                                    np.random.default_rng(seed + 2))
    R, t, _ = plant.measure()
    f.initialise(th + 0.03, a + 0.002, R, t, tendon_command=plant.state.tendon_command)
    return h, plant, f


def test_model_plant_refuses_unphysical_actions():
    """The model plant stays put (and counts a failure) when an action has no physical
    equilibrium: with the ideal (inextensible) tendon a 3 mm pull of one tendon would need
    a joint past its limit or a pushing tendon; a 0.05 mm pull moves it."""
    h = model_o().model()
    th, a = _truth_grasp(h, np.random.default_rng(0))
    plant = ModelPlant(h, th, a, np.eye(3), np.array([0.0, 0.0, 0.11]), np.random.default_rng(1), tendon="ideal")
    before = plant.state.theta.copy(), plant.state.tendon_command.copy()
    assert not plant.apply_action(np.array([3e-3, 0.0, 0.0]))
    assert plant.failures == 1
    np.testing.assert_array_equal(plant.state.theta, before[0])
    np.testing.assert_array_equal(plant.state.tendon_command, before[1])
    assert plant.apply_action(np.array([0.05e-3, 0.0, 0.0]))
    assert np.all((plant.state.theta >= h.joint_lower) & (plant.state.theta <= h.joint_upper))
    assert np.max(np.abs(plant.state.theta - before[0])) > 1e-5


def test_the_truth_inside_flags_say_where_the_truth_lies():
    """Every calibration test reads these flags; a review found none that could see them
    False (flags comparing the estimate with its own interval had passed them all). A truth
    just outside an interval, one on its bound and one inside."""
    from vlr_drake.identify import estimate_errors

    h = model_o().model()
    prior = pf.PriorConfig(stiffness_unknown=[(0, 1)], links_unknown=[2])
    theta = np.full((3, 2), 0.5)
    a = np.full(3, 0.02)
    k, L = h.stiffness.copy(), h.link_lengths.copy()
    est = {"theta": theta, "theta_lo": theta - 0.01, "theta_hi": theta + 0.01, "a": a, "a_lo": a - 1e-3,
           "a_hi": a + 1e-3, "contacts": np.zeros((3, 3)), "theta_half_width": np.full((3, 2), 0.01),
           "theta_full_width": np.full((3, 2), 0.02), "stiffness": k, "stiffness_lo": k - 0.01,
           "stiffness_hi": k + 0.01, "link_lengths": L, "link_lengths_lo": L - 1e-3, "link_lengths_hi": L + 1e-3}
    true_theta = theta.copy()
    true_theta[0, 0] += 0.0101  # just outside
    true_theta[1, 1] -= 0.01  # on the bound: inside
    true_a = a.copy()
    true_a[2] += 1.5e-3
    true_k = k.copy()
    true_k[0, 1] += 0.02
    true_L = L.copy()
    true_L[2, 0] -= 0.5e-3
    r = estimate_errors(h, prior, est, {"theta": true_theta, "a": true_a, "contacts": np.zeros((3, 3)),
                                        "stiffness": true_k, "link_lengths": true_L})
    assert r["theta_inside_95"] == [[False, True], [True, True], [True, True]]
    assert r["truth_inside_95_theta"] == pytest.approx(5 / 6)
    assert r["contact_inside_95"] == [True, True, False] and r["truth_inside_95_contact"] == pytest.approx(2 / 3)
    assert r["stiffness_inside_95"] is False
    assert r["hand_parameter_inside_95"] == {f"stiffness:{h.names[0]}/1": False, f"link_length:{h.names[2]}": True}


def test_roughening_keeps_mean_and_covariance():
    """Liu-West roughening with the cloud's full covariance keeps its mean and covariance.
    After a few iterations the angles and contacts lie on a ridge (|correlation| ~0.9), which
    jitter drawn per coordinate would fill in: its smallest eigenvalue grew 30x in a check,
    while each marginal and correlation moved by under 0.04. The whitened covariance after
    the roughening (identity for a kept covariance) sees that."""
    h, plant, f = _filter_and_plant(3, particles=20000)
    rng = np.random.default_rng(5)
    for _ in range(6):
        dl = rng.uniform(-1e-3, 1e-3, h.N)
        if plant.apply_action(dl):
            R, t, _ = plant.measure()
            f.step(dl, R, t, tendon_command=plant.state.tendon_command)
    ps = f.particles
    before = f._unknowns(ps)
    corr = np.corrcoef(before, rowvar=False)
    assert np.abs(corr - np.eye(len(corr))).max() > 0.8  # the ridge has formed
    f._roughen(ps)
    after = f._unknowns(ps)
    # the mean moves by no more than the jitter's sampling error (4 standard errors)
    assert np.all(np.abs(after.mean(0) - before.mean(0)) <= 4 * before.std(0) / np.sqrt(len(before)))
    # (bounds a review tightened: jitter without the shrinkage towards the mean, which grows
    # the variance by 1 + h^2 a roughening, had passed at 1.017-1.022 and 0.047; this cloud
    # gives 0.997-1.003 and 0.007)
    np.testing.assert_allclose(after.std(0), before.std(0), rtol=0.012)
    W = np.linalg.inv(np.linalg.cholesky(np.cov(before, rowvar=False)))
    np.testing.assert_allclose(W @ np.cov(after, rowvar=False) @ W.T, np.eye(len(corr)), atol=0.02)
    # and it does move them: x' - x = (a - 1)(x - mean) + h C^(1/2) eps, a = sqrt(1 - h^2)
    h_ = f.config.roughening
    moved = (after - before).std(0) / before.std(0)
    np.testing.assert_allclose(moved, np.sqrt((1 - np.sqrt(1 - h_**2)) ** 2 + h_**2), rtol=0.05)


def test_roughening_falls_back_to_the_symmetric_square_root(monkeypatch):
    """A collapsed cloud's covariance is rank-deficient and its Cholesky factor may not
    exist (10 particles, 10 unknowns: 'Matrix is not positive definite' ended such a run).
    The fallback, the symmetric square root, keeps the covariance as the factor does."""
    h, plant, f = _filter_and_plant(3, particles=4000)

    def refuse(_):
        raise np.linalg.LinAlgError("Matrix is not positive definite")

    monkeypatch.setattr(pf.np.linalg, "cholesky", refuse)
    before = f._unknowns(f.particles)
    f._roughen(f.particles)
    after = f._unknowns(f.particles)
    W = np.linalg.inv(np.linalg.eigh(np.cov(before, rowvar=False))[1].T)  # any basis: compare variances in it
    Cb, Ca = (W.T @ np.cov(x, rowvar=False) @ W for x in (before, after))
    np.testing.assert_allclose(np.diag(Ca), np.diag(Cb), rtol=0.1)
    monkeypatch.undo()
    # and a run with as few particles as unknowns goes through
    prior = pf.PriorConfig(stiffness_unknown=[(0, 1)])
    g = pf.SelfIdentificationFilter(h, pf.FilterConfig(particles=10), prior, np.random.default_rng(1))
    R, t, _ = plant.measure()
    g.initialise(plant.state.theta, plant.state.a, R, t, tendon_command=plant.state.tendon_command)
    for _ in range(4):
        dl = np.array([0.2e-3, -0.1e-3, 0.1e-3])
        if plant.apply_action(dl):
            R, t, _ = plant.measure()
            g.step(dl, R, t, tendon_command=plant.state.tendon_command)
    assert np.all(np.isfinite(g.particles.theta)) and np.all(np.isfinite(g.particles.stiffness))


def test_information_gain_matches_its_definition():
    """0.5 log det(I + Cov) over the valid predictions; too few valid ones score -inf."""
    rng = np.random.default_rng(3)
    y = rng.normal(size=(3, 50, 6)) * np.array([0.1, 1.0, 3.0])[:, None, None]
    ok = np.ones((3, 50), bool)
    ok[2, :40] = False  # 10 of 50 valid
    got = pf.information_gain(y, ok, min_valid=0.5)
    for c in range(2):
        cov = np.cov(y[c], rowvar=False, bias=True)
        assert got[c] == pytest.approx(0.5 * np.linalg.slogdet(np.eye(6) + cov)[1], rel=1e-12)
    assert got[2] == -np.inf and got[0] < got[1]  # more spread, more information
    ok[2, :] = True
    ok[2, 0] = False  # the invalid prediction is left out, whatever its value
    y[2, 0] = 1e6
    cov = np.cov(y[2, 1:], rowvar=False, bias=True)
    assert pf.information_gain(y, ok)[2] == pytest.approx(0.5 * np.linalg.slogdet(np.eye(6) + cov)[1], rel=1e-12)
    y[2, 0] = np.nan  # ... NaN too (it had made the score NaN: a review)
    assert pf.information_gain(y, ok)[2] == pytest.approx(0.5 * np.linalg.slogdet(np.eye(6) + cov)[1], rel=1e-12)
    with pytest.raises(ValueError, match="information_gain"):
        pf.information_gain(y[0], ok[0])


def test_action_information_scores_actions_without_changing_the_filter():
    """After a few iterations a full action back along a move the grasp made scores more
    than a null action; the particles are untouched. Even a null action scores: the
    roughened hypotheses are off their equilibria and settle under it, differently (here
    null 2.44, half the action 2.40, the whole action 2.72). Right after initialisation
    40% of the hypotheses find no equilibrium even for a null action (they start out of
    equilibrium with the commanded tendons), so every candidate scores -inf there."""
    h, plant, f = _filter_and_plant(4, particles=3000)
    rng = np.random.default_rng(5)
    for _ in range(6):
        dl = rng.uniform(-1e-3, 1e-3, 3)
        if plant.apply_action(dl):
            R, t, _ = plant.measure()
            f.step(dl, R, t)
            last = dl
    before = f.particles.theta.copy(), f.particles.log_w.copy(), f.particles.p_O.copy()
    acts = np.array([0.0, 0.5, 1.0])[:, None] * -last[None]  # back along a move the grasp made
    score = f.action_information(acts, np.random.default_rng(0), samples=300)
    assert score.shape == (3,)
    assert np.all(np.isfinite(score)) and score[2] > score[0] + 0.1, score
    for x, y in zip(before, (f.particles.theta, f.particles.log_w, f.particles.p_O), strict=True):
        np.testing.assert_array_equal(x, y)
    with pytest.raises(ValueError, match="actions"):
        f.action_information(np.zeros(3), np.random.default_rng(0))


def test_informative_exploration_falls_back_to_random_after_a_refusal():
    from vlr_drake.identify import Exploration, InformativeExploration

    class Scores:  # prefers the proposal with the largest first pull
        def action_information(self, proposals, rng):
            return proposals[:, 0]

    h = model_o().model()
    l0 = np.full(3, 0.015)
    ex = InformativeExploration(Exploration(l0, h.tendon_range, 1e-3, 3e-3, np.random.default_rng(1)), Scores(), 8,
                                np.random.default_rng(2))
    twin = Exploration(l0, h.tendon_range, 1e-3, 3e-3, np.random.default_rng(1))
    proposals = np.array([twin.next_action() for _ in range(8)])
    first = ex.next_action()
    np.testing.assert_array_equal(first, proposals[np.argmax(proposals[:, 0])])
    # refused (not committed): the next action is the next plain draw, not another choice
    np.testing.assert_array_equal(ex.next_action(), twin.next_action())
    ex.commit(first)
    np.testing.assert_allclose(ex.l, l0 + first)
    # committed: the next action is chosen again (only follow() had cleared the choice, so on
    # the model plant every other action had been a plain draw: a review)
    twin.commit(first)
    proposals = np.array([twin.next_action() for _ in range(8)])
    np.testing.assert_array_equal(ex.next_action(), proposals[np.argmax(proposals[:, 0])])


@pytest.mark.slow
def test_informative_actions_converge_sooner_and_stay_honest():
    """Model plant, known hand, 20,000 particles, at most 100 iterations, seeds 0-7: choosing
    the most informative of 8 random actions converges in fewer iterations than random
    actions, with the truth inside the 95% intervals as often. Measured over seeds 0-23
    with the model plant's stable truths (2026-11-27): 34.9 against 44.5 iterations (seeds
    0-7: 41.0 against 50.4), 23 of 24 converged either way, coverage 0.96 / 0.96 (joints /
    contacts) against 1.00 / 0.97 (with every other action informative; every action, since
    2026-12-06: 29.5 against 44.2, coverage 0.94 / 0.99 against 0.99 / 0.97); on the truths of before, half of them on saddles, 31.5
    against 56 (vlr_drake.identify.ACTION_CHOICE). Coverage
    comes in clumps (a run that misses, misses several values), so a handful of seeds
    scatters: over seeds 0-35 it was 0.97 / 0.94 (FilterConfig.newton_loose_after 8) and
    0.96 / 0.92 (None), and the pooled coverage of 8 consecutive seeds was at least 0.92
    (8) and 0.86 (None), of 4 seeds at least 0.86 and 0.83 (seeds 0-3 with 8: 0.86, one
    run missing 5 of its 9 values). Hence 8 seeds and a bar of 0.85, which an honest filter
    clears and one that is sure and wrong (0.2-0.7 of the joints inside on the physics plant
    with a sharper likelihood, README) does not."""
    its, inside = {}, {}
    for choice in ("random", "informative"):
        its[choice], inside[choice] = [], []
        for seed in range(8):
            r = run_identification(IdentifyOptions(experiment="known_hand", particles=20000, max_iterations=100,
                                                   seed=seed, progress=False, action_choice=choice))
            assert r["action_choice"] == choice
            its[choice].append(r["iterations"])
            inside[choice] += [r["truth_inside_95_theta"]] * 6 + [r["truth_inside_95_contact"]] * 3
            if r["converged"]:  # (seed 7's grasp, stable but barely told apart, converges in neither: its
                # intervals are wide, 2-3 deg off, and hold the truth)
                assert np.mean(r["proximal_joint_error_deg"]) < 1.5
    assert np.mean(its["informative"]) < 0.9 * np.mean(its["random"]), its
    assert np.mean(inside["informative"]) >= 0.85, inside


def test_lost_tag_moves_but_does_not_learn():
    """A step without a measurement moves every hypothesis and learns nothing from the
    camera, but the move's physics weighs as in a measured step: a hypothesis with no
    equilibrium for the action weighs nothing (or its stuck_probability, where friction may
    hold it), as one that left the physical grasps does. (They had kept their whole weight
    through a lost frame.)"""
    dl = np.array([0.3e-3, -0.2e-3, 0.3e-3])
    for stuck in (None, 0.1):
        h, plant, f = _filter_and_plant(6, particles=2000, stuck_probability=stuck)
        assert plant.apply_action(dl)
        p_O_before, theta_before = f.particles.p_O.copy(), f.particles.theta.copy()
        rep = f.step(dl, None, None, valid=False)
        assert not rep.measured
        # the hypotheses moved with the action (Gamma), as the hand did: all but those with no
        # equilibrium for it (held where they were; 20% of this first move's prior draws)
        moved = np.abs(f.particles.theta - theta_before).max(axis=(1, 2)) > 1e-6
        assert moved.mean() > 0.5 and moved.sum() >= 2000 - rep.solve_failures, (moved.mean(), rep.solve_failures)
        assert rep.solve_failures > 100
        assert set(rep.timing_s) == {"move", "estimate"}  # nothing measured or resampled
        np.testing.assert_array_equal(f.particles.p_O, p_O_before)  # attachments untouched
        assert np.all(np.isfinite(f.particles.theta))
        w = f.particles.log_w
        held = np.log(stuck) if stuck else -np.inf
        assert np.all((w == 0) | (w == held) | np.isneginf(w))
        assert np.all(w[~moved] <= held)  # no equilibrium: discarded, or weighed as held
        # and held they are: with a stuck_probability they weigh it, not nothing (a lost step
        # that discarded them had passed the bound above, which -inf meets)
        assert (w[~moved] == held).mean() > 0.95, np.unique(w[~moved], return_counts=True)
        assert (w[moved] == 0).mean() > 0.95  # the moved ones keep their weight (bar unphysical ones)
        assert rep.ess == pytest.approx(pf.effective_sample_size(w)) and rep.ess < 2000


def test_a_bad_measurement_is_refused_and_changes_nothing():
    """A NaN pose (a lost tag must say valid=False), a matrix that is no rotation or a wrong
    shape is a named error raised before anything moves; the filter then steps on."""
    h, plant, f = _filter_and_plant(6, particles=1000)
    dl = np.array([0.3e-3, -0.2e-3, 0.3e-3])
    assert plant.apply_action(dl)
    R, t, _ = plant.measure()
    theta, p_O, it = f.particles.theta.copy(), f.particles.p_O.copy(), f.iteration
    for R_bad, t_bad, message in [(np.full((3, 3), np.nan), t, "not finite .*valid=False for a lost tag"),
                                  (R, t + np.nan, "not finite"),
                                  (5 * np.eye(3), t, "not a rotation matrix"),
                                  (R, t[:2], r"'measured position' must have shape \(3,\)")]:
        with pytest.raises(ValueError, match=message):
            f.step(dl, R_bad, t_bad)
        np.testing.assert_array_equal(f.particles.theta, theta)
        np.testing.assert_array_equal(f.particles.p_O, p_O)
        assert f.iteration == it
    with pytest.raises(ValueError, match="'dl' must have shape"):
        f.step(np.zeros(4), R, t)
    assert f.step(dl, R, t).measured and np.all(np.isfinite(f.particles.theta))
    with pytest.raises(ValueError, match="initial POM pose is not finite"):
        f.initialise(plant.state.theta, plant.state.a, R, np.array([np.nan, 0.0, 0.08]),
                     tendon_command=plant.state.tendon_command)
    with pytest.raises(ValueError, match=r"not finite \(R \[\[nan"):  # names the rotation, not the position
        f.step(dl, np.full((3, 3), np.nan), t)
    # a transposed nominal grasp ((K, N) for (N, K)) would pair angles and joints wrongly;
    # contacts in mm instead of m would be clipped to the links' ends
    with pytest.raises(ValueError, match=r"'theta_center' must have shape \(3, 2\) \(or be flat\), got \(2, 3\)"):
        f.initialise(plant.state.theta.T, plant.state.a, R, t, tendon_command=plant.state.tendon_command)
    with pytest.raises(ValueError, match="'a_center' must lie along the last links"):
        f.initialise(plant.state.theta, 1e3 * plant.state.a, R, t, tendon_command=plant.state.tendon_command)
    f.initialise(plant.state.theta.ravel(), plant.state.a, R, t, tendon_command=plant.state.tendon_command)  # flat


def test_a_prior_without_physical_grasps_is_a_prior_error():
    """PriorError (a ValueError: the user's setting) names the count of physical draws."""
    h, plant, _ = _filter_and_plant(3, particles=300)
    prior = pf.PriorConfig(stiffness_unknown=[(0, 1)], stiffness_range=(0.001, 0.002))
    f = pf.SelfIdentificationFilter(h, pf.FilterConfig(particles=300), prior, np.random.default_rng(0))
    R, t, _ = plant.measure()
    with pytest.raises(pf.PriorError, match=r"prior: only \d+ of 30000 draws are physical grasps \(positive "
                                            r"tension, joints within limits\), and the filter needs 300"):
        f.initialise(plant.state.theta, plant.state.a, R, t, tendon_command=plant.state.tendon_command)


def test_bad_gravity_and_rng_are_named():
    h = model_o().model()
    theta = np.repeat(h.rest_angles[None] + 0.3, 2, axis=0)
    with pytest.raises(ValueError, match=r"'gravity' must be 3 finite numbers \[m/s\^2\], got \[0.0, 9.81\]"):
        a = np.full((2, h.N), 0.02)
        D2 = pf.motion.contact_distances_sq(h, pf.kinematics.contacts(h, theta, a))
        pf.motion.move(h, theta, np.zeros(h.N), a=a, D2=D2, stretch=np.full((2, h.N), 1e-3),
                       gravity=np.array([0.0, 9.81]))
    with pytest.raises(TypeError, match="'rng' must be a numpy.random.Generator"):
        pf.SelfIdentificationFilter(h, pf.FilterConfig(), pf.PriorConfig(), 3)


def test_prior_half_widths_must_be_positive():
    h = model_o().model()
    with pytest.raises(ValueError, match=r"prior: the half-widths must be positive and finite, got \{'proximal_half_width': -0.1\}"):
        pf.SelfIdentificationFilter(h, pf.FilterConfig(), pf.PriorConfig(proximal_half_width=-0.1),
                                    np.random.default_rng(0))


def test_an_unknown_named_twice_is_refused():
    """A repeated entry would give the same quantity two columns of the unknowns, drawn and
    roughened separately, the last one written winning."""
    h = model_o().model()
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match=r"prior: stiffness_unknown names \[\(0, 1\)\] more than once"):
        pf.SelfIdentificationFilter(h, pf.FilterConfig(), pf.PriorConfig(stiffness_unknown=[(0, 1), (0, 1)]), rng)
    with pytest.raises(ValueError, match=r"prior: links_unknown names \[0\] more than once"):
        pf.SelfIdentificationFilter(h, pf.FilterConfig(), pf.PriorConfig(links_unknown=[0, 1, 0]), rng)
    pf.SelfIdentificationFilter(h, pf.FilterConfig(), pf.PriorConfig(stiffness_unknown=[(0, 1), (1, 1)]), rng)


def test_a_resampling_threshold_the_tempering_never_reaches_is_refused():
    with pytest.raises(ValueError, match=r"'resample_fraction' \(0.25\) must be above 'ess_fraction' \(0.3\)"):
        pf.FilterConfig(resample_fraction=0.25).validate()
    with pytest.raises(ValueError, match=r"'resample_fraction' must be in \[0, 1\], got 1.5"):
        pf.FilterConfig(resample_fraction=1.5).validate()
    pf.FilterConfig(resample_fraction=0.0).validate()  # never, on purpose
    pf.FilterConfig(resample_fraction=0.31).validate()


@pytest.mark.parametrize("field, value", [("sigma_position", np.nan), ("sigma_rotation", np.inf),
                                          ("motion_error", np.nan), ("convergence_deg", -5.0),
                                          ("divergence_sigmas", 0.0)])
def test_filter_settings_must_be_finite(field, value):
    with pytest.raises(ValueError, match=f"'{field}' must be a .*finite number"):
        pf.FilterConfig(**{field: value}).validate()


def test_contacts_stay_on_each_fingers_own_pad():
    """Left out, the contact limits are each finger's last link: NH3's finger_right (NF3)
    has a 40 mm distal link, the others 48 mm. A wide contact box drawn and roughened
    around the pads' ends keeps every contact on its own finger's pad."""
    from vlr_drake.hand import hand_by_name

    h = hand_by_name("NH3").model()
    assert list(h.distal_length) == [0.048, 0.048, 0.040]
    lo, hi = pf.PriorConfig().contact_bounds(h)
    np.testing.assert_array_equal(lo, pf.CONTACT_MIN)
    np.testing.assert_array_equal(hi, h.distal_length)
    th, a = _truth_grasp(h, np.random.default_rng(0))
    plant = ModelPlant(h, th, a, np.eye(3), np.array([0.0, 0.0, 0.11]), np.random.default_rng(1))
    f = pf.SelfIdentificationFilter(h, pf.FilterConfig(particles=2000), pf.PriorConfig(contact_half_width=0.02),
                                    np.random.default_rng(2))
    R, t, _ = plant.measure()
    f.initialise(th, np.full(h.N, 0.038), R, t, tendon_command=plant.state.tendon_command)
    reach = [f.particles.a.max(axis=0)]
    for dl in ([0.3e-3, -0.2e-3, 0.2e-3], [-0.2e-3, 0.3e-3, -0.1e-3]):
        assert plant.apply_action(np.array(dl))
        f.step(np.array(dl), *plant.measure()[:2])
        reach.append(f.particles.a.max(axis=0))
    reach = np.array(reach)
    assert np.all(reach <= h.distal_length + 1e-15) and np.all(f.particles.a >= pf.CONTACT_MIN)
    assert reach[0, 2] > 0.039 and reach[0, 0] > 0.041  # the box reached past 40 mm where it may


def test_a_guessed_grasp_keeps_its_contacts_in_their_range():
    """PriorConfig.guessed_contacts: a contact guessed past the end of its last link is
    clipped to it; a guess inside the range is the displacement drawn. guessed_grasp (the
    model plant's) draws its angles first, then the same contacts, clipped too: unclipped,
    the filter refused a guess past NF3's 40 mm pad (a review: 13 of 200 draws of a truth
    at 35.8 mm)."""
    from vlr_drake.hand import hand_by_name

    h = hand_by_name("NH3").model()
    prior = pf.PriorConfig()
    lo, hi = prior.contact_bounds(h)
    a = hi - 0.001  # the truth 1 mm from each pad's end: a guess may land past it
    rng = np.random.default_rng(4)
    free = a + pf.CENTER_OFFSET_FRACTION * prior.contact_half_width * rng.uniform(-1, 1, h.N)
    clipped = prior.guessed_contacts(a, np.random.default_rng(4), h)
    assert np.any(free > hi)  # this seed pushes some guess past the link ...
    np.testing.assert_array_equal(clipped, np.clip(free, lo, hi))  # ... and only those move
    assert np.all(clipped <= hi) and np.all(clipped >= lo)
    # the model plant's guess draws its angles first, then the same contact displacement
    theta = np.full((h.N, h.K), 0.3)
    rng = np.random.default_rng(4)
    th, a_model = prior.guessed_grasp(theta, a, rng, h)
    replay = np.random.default_rng(4)
    replay.uniform(-1, 1, h.N), replay.uniform(-1, 1, (h.N, h.K - 1))
    free = a + pf.CENTER_OFFSET_FRACTION * prior.contact_half_width * replay.uniform(-1, 1, h.N)
    assert np.any(free > hi)  # this draw too pushes some guess past the link
    np.testing.assert_array_equal(a_model, np.clip(free, lo, hi))
    assert not np.allclose(th, theta)
    with pytest.raises(ValueError, match="'a_center' must lie along the last links"):
        pf.contact_center(h, free)  # the filter had refused the unclipped guess ...
    pf.contact_center(h, a_model)  # ... and takes this one


def test_contact_limits_past_a_finger_are_named():
    from vlr_drake.hand import hand_by_name

    h = hand_by_name("NH3").model()
    with pytest.raises(ValueError, match=r"prior: 'contact_limits' max 45.0 mm reaches past the last link of "
                                         r"'finger_right_NF3' \(40.0 mm\)"):
        pf.SelfIdentificationFilter(h, pf.FilterConfig(), pf.PriorConfig(contact_limits=(0.005, 0.045)),
                                    np.random.default_rng(0))
    with pytest.raises(ValueError, match=r"'contact_limits' must be \[min, max\] \[m\] with 0 <= min < max"):
        pf.PriorConfig(contact_limits=(0.03, 0.01)).contact_bounds(h)
    lo, hi = pf.PriorConfig(contact_limits=(0.01, 0.035)).contact_bounds(h)
    assert np.all(lo == 0.01) and np.all(hi == 0.035)
    # a spring's range in N mm/rad is named as such (it had drawn springs of 50-400 N m/rad)
    with pytest.raises(ValueError, match=r"prior: 'stiffness_range': \[50.0, 400.0\] N m/rad is stiffer.*N mm/rad"):
        pf.PriorConfig(stiffness_range=(50.0, 400.0)).validate()
    # millimetres are named as such (had been "max 38000.0 mm reaches past the last link")
    with pytest.raises(ValueError, match=r"prior: 'contact_limits': \[5.0, 38.0\] m is longer than 1 m.*millimetres"):
        pf.PriorConfig(contact_limits=(5, 38)).contact_bounds(h)
    short = hand_by_name("NH3")
    short.fingers[1].distal_length = 0.004
    with pytest.raises(ValueError, match=r"prior: the last link of 'finger_left_NF2' \(4.0 mm\) is no longer than"):
        pf.PriorConfig().contact_bounds(short.model())


def test_the_first_move_after_initialisation_takes_its_own_continuation(monkeypatch):
    """first_move_substeps applies to the move that carries the prior's draws (the first
    after initialise and after a re-initialisation), max_substeps to every other."""
    calls, in_step = [], []
    move, step = pf.motion.move, pf.SelfIdentificationFilter.step

    def spy_move(*args, **kwargs):  # the filter's moves only (the model plant moves too)
        if in_step:
            calls.append(kwargs.get("max_substeps"))
        return move(*args, **kwargs)

    def spy_step(self, *args, **kwargs):
        in_step.append(True)
        try:
            return step(self, *args, **kwargs)
        finally:
            in_step.pop()

    monkeypatch.setattr(pf.motion, "move", spy_move)
    monkeypatch.setattr(pf.SelfIdentificationFilter, "step", spy_step)
    h, plant, f = _filter_and_plant(3, particles=500, first_move_substeps=0, max_substeps=4)
    dl = np.array([0.2e-3, -0.1e-3, 0.1e-3])
    for _ in range(2):
        assert plant.apply_action(dl)
        f.step(dl, *plant.measure()[:2])
    R, t, _ = plant.measure()
    f._reinitialise(R, t)
    f.step(np.zeros(3), R, t, valid=False)  # a lost tag's step still moves the draws
    f.step(np.zeros(3), R, t)
    assert calls == [0, 4, 0, 4]
    calls.clear()
    h, plant, f = _filter_and_plant(3, particles=500, first_move_substeps=None, max_substeps=4)
    f.step(np.zeros(3), *plant.measure()[:2])
    assert calls == [4]


@pytest.mark.parametrize("value", [-1, 1.5, True])
def test_first_move_substeps_must_be_a_count(value):
    with pytest.raises(ValueError, match=r"'first_move_substeps' must be None or an integer >= 0"):
        pf.FilterConfig(first_move_substeps=value).validate()


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
    assert {"move", "weigh", "reinitialise", "estimate"} == set(rep.timing_s)
    assert f.particles.size == 2000 and np.all(np.isfinite(f.particles.theta))
    # it keeps working afterwards
    rep = f.step(np.zeros(3), R_far, t + np.array([0.02, 0.0, 0.0]))
    assert np.isfinite(rep.mean_interval_deg)


def test_reinitialisation_centres_on_the_moved_cloud_then_on_the_whole_prior(monkeypatch):
    """A re-initialisation draws around the estimate of the cloud as this iteration moved
    it (not the last estimate, one action old); another within REINIT_RECENT iterations
    draws from the whole prior around the nominal grasp again (a box around an estimate
    that was lost again at once may not hold the truth); the nominal grasp is kept."""
    h, plant, f = _filter_and_plant(5, particles=2000)
    nominal = f._theta_center.copy()
    centres = []
    initialise = pf.SelfIdentificationFilter.initialise

    def spy(self, theta_center, *args, **kwargs):
        centres.append(np.array(theta_center))
        return initialise(self, theta_center, *args, **kwargs)

    monkeypatch.setattr(pf.SelfIdentificationFilter, "initialise", spy)
    dl = np.array([1.0e-3, 0.5e-3, -0.8e-3])
    for _ in range(3):
        assert plant.apply_action(dl)
        f.step(dl, *plant.measure()[:2])
    before = f.estimates[-1]["theta"]
    from vlr_drake.observation import rotvec_to_matrix

    assert plant.apply_action(dl)
    R, t, _ = plant.measure()
    R_far = rotvec_to_matrix(np.array([0.0, np.deg2rad(30), 0.0]))[0] @ R  # the object swapped
    assert f.step(dl, R_far, t + np.array([0.02, 0.0, 0.0])).reinitialised
    moved = centres[-1] - before  # centred on the cloud the action moved, not on the estimate before
    assert 1e-3 < np.abs(moved).max() < 0.2
    f.iteration += REINIT_GAP
    f._reinitialise(R, t)
    np.testing.assert_array_equal(centres[-1], nominal)
    np.testing.assert_array_equal(f._theta_center, nominal)
    assert f.reinitialisations == 2


REINIT_GAP = pf.REINIT_RECENT


def test_centred_draws_fold_back_at_the_prior_bounds():
    """Draws centred near a bound (re-initialisation) fold back into the range instead of
    piling onto the bound (clipped, 28% of the links centred at 40 mm sat exactly at 30 mm);
    a log-uniform spring is drawn in log k, symmetric there about its centre."""
    from vlr_drake.hand import hand_by_name

    h = hand_by_name("NH2").model()
    prior = pf.PriorConfig(links_unknown=[0, 1], stiffness_unknown=[(0, 1)])
    f = pf.SelfIdentificationFilter(h, pf.FilterConfig(particles=3000), prior, np.random.default_rng(0))
    n = 50_000
    L = f._draw_links(n, np.full((3, 1), 0.040), 1.0)[:, :2, 0]
    lo, hi = prior.link_range
    assert L.min() >= lo and L.max() <= hi and np.mean(L == lo) == 0.0
    near = np.mean(L < lo + 1e-3) / (1e-3 / (hi - lo))  # density at the bound, relative to uniform
    assert 1.5 < near < 2.5  # folded: the box's mass past the bound lands just inside it
    centre = np.full((3, 2), 0.08)
    k = f._draw_stiffness(n, centre, 1.0)[:, 0, 1]
    klo, khi = prior.stiffness_range
    assert k.min() >= klo and k.max() <= khi and np.mean(k == klo) == 0.0
    half = 0.5 * np.log(khi / klo)  # the box's half-width in log k
    x = np.log(k / 0.08)
    assert x.max() == pytest.approx(half, abs=1e-3)
    # uniform in log k above the fold (which reaches 0.1 above the centre): density 1 / (2 half)
    assert np.mean((x > 0.2) & (x < 1.0)) == pytest.approx(0.8 / (2 * half), abs=0.01)
    np.testing.assert_allclose(pf._reflect_into(np.array([0.5, 1.2, -0.3, 2.7]), 0.0, 1.0), [0.5, 0.8, 0.3, 0.7])


def test_roughening_folds_springs_links_and_contacts_back_at_their_ranges():
    """A cloud spread over its whole range, roughened: every spring, link and contact stays
    in its range and none piles on a bound (clipped, 4-5% of each sat exactly on one), and
    the cloud keeps its mean."""
    from vlr_drake.hand import hand_by_name

    h = hand_by_name("NH2").model()
    prior = pf.PriorConfig(links_unknown=[0, 1], stiffness_unknown=[(0, 1)])
    th, a = _truth_grasp(h, np.random.default_rng(0))
    plant = ModelPlant(h, th, a, np.eye(3), np.array([0.0, 0.0, 0.11]), np.random.default_rng(1))
    f = pf.SelfIdentificationFilter(h, pf.FilterConfig(particles=20000, roughening=0.3), prior,
                                    np.random.default_rng(2))
    ps = f.initialise(th, a, *plant.measure()[:2], tendon_command=plant.state.tendon_command)
    n = ps.size
    (llo, lhi), (klo, khi) = prior.link_range, prior.stiffness_range
    alo, ahi = f._contact_bounds
    L = ps.link_lengths.copy()
    L[:, :2, 0] = np.linspace(llo, lhi, n)[:, None]
    k = ps.stiffness.copy()
    k[:, 0, 1] = np.linspace(klo, khi, n)
    ps.link_lengths, ps.stiffness = L, k
    ps.a = alo + (ahi - alo) * np.linspace(0.0, 1.0, n)[:, None]
    a0 = ps.a.copy()
    before = f._unknowns(ps).mean(0)
    f._roughen(ps)
    for v, lo, hi in ((ps.link_lengths[:, :2, 0], llo, lhi), (ps.stiffness[:, 0, 1], klo, khi), (ps.a, alo, ahi)):
        assert np.all((v >= lo - 1e-15) & (v <= hi + 1e-15))
        assert np.mean(np.isclose(v, lo, rtol=0, atol=1e-9) | np.isclose(v, hi, rtol=0, atol=1e-9)) < 0.002
    after = f._unknowns(ps).mean(0)
    c = h.N * h.K + h.N  # the hand parameters' columns after the angles and contacts
    np.testing.assert_allclose(after[c:], before[c:], rtol=0.01)
    # it did roughen each of them (the spread given already met every check above without a
    # roughening: springs, links or contacts left where they were had passed them)
    for name, v, v0 in (("links", ps.link_lengths[:, :2, 0], L[:, :2, 0]), ("spring", ps.stiffness[:, 0, 1], k[:, 0, 1]),
                        ("contacts", ps.a, a0)):
        moved = np.std(v - v0, axis=0) / np.std(v0, axis=0)
        assert np.all(moved > 0.5 * f.config.roughening), (name, moved)


def test_roughening_keeps_the_objects_mass_and_the_prior_folds_contacts():
    """The object's mass through 30 roughenings with no data stays where it was (its loads
    had been clipped at 0 before summing, which added mass each time: a light cloud grew 7%)
    and no load sits on 0; the prior's contacts drawn around a guess 3 mm from the pad's end
    are folded back onto the pad (clipped, a third of them had sat exactly on its end)."""
    h = model_o().model()
    th, a = _truth_grasp(h, np.random.default_rng(0))
    prior = pf.PriorConfig(object_mass_unknown=True, stiffness_unknown=[(0, 1)])
    cfg = pf.FilterConfig(particles=4000, gravity_palm=[0.0, 0.0, 9.81], gravity_loads="following")
    f = pf.SelfIdentificationFilter(h, cfg, prior, np.random.default_rng(2))
    lo, hi = f._contact_bounds
    a_guess = a.copy()
    a_guess[0] = lo[0] + 0.003
    ps = f.initialise(th, a_guess, np.eye(3), np.array([0.0, 0.0, 0.1]),
                      tendon_command=h.tendon_travel(th[None])[0] + 0.004)
    assert np.all((ps.a >= lo) & (ps.a <= hi)) and not np.any((ps.a == lo) | (ps.a == hi))
    shares = ps.object_load / ps.object_load.sum(1, keepdims=True)
    ps.object_load = (0.02 + 0.003 * np.random.default_rng(1).standard_normal(ps.size))[:, None] * shares
    m0 = ps.object_load.sum(1)
    for _ in range(30):
        f._roughen(ps)
    m = ps.object_load.sum(1)
    # the masses were roughened (left alone, they had met every check below): 30 Liu-West
    # steps x' - mean = s (x - mean) + h C^(1/2) eps, s = sqrt(1 - h^2), move each by
    # sqrt(2 (1 - s^30)) of the spread
    shrink = np.sqrt(1 - f.config.roughening**2)
    moved = np.std(m - m0) / m0.std()
    assert moved == pytest.approx(np.sqrt(2 * (1 - shrink**30)), rel=0.05), moved  # (measured 0.955 of 0.957)
    assert abs(m.mean() / m0.mean() - 1) < 0.005 and abs(m.std() / m0.std() - 1) < 0.05, (m.mean(), m0.mean())
    assert np.all(ps.object_load > 0)


def test_loads_go_to_log_ratios_and_back():
    """Roughening's coordinates of the object's loads (the mass and its shares' log-ratios)
    give the loads back; a contact that carries nothing keeps a finite log-ratio (the share
    floor), and a cloud without mass gets equal shares, never a NaN."""
    rng = np.random.default_rng(0)
    load = rng.uniform(0.02, 0.2, 50)[:, None] * rng.dirichlet(np.ones(3), 50)
    x = pf._mass_and_log_ratios(load)
    assert x.shape == (50, 3)
    np.testing.assert_allclose(x[:, 0][:, None] * pf._shares_from_log_ratios(x[:, 1:]), load, rtol=1e-12)
    odd = pf._mass_and_log_ratios(np.array([[0.0, 0.03, 0.01], [0.0, 0.0, 0.0]]))
    assert np.all(np.isfinite(odd))
    np.testing.assert_allclose(pf._shares_from_log_ratios(odd[:, 1:]), [[0.0, 0.75, 0.25], [1 / 3, 1 / 3, 1 / 3]],
                               atol=1e-11)
    assert np.all(np.isfinite(pf._shares_from_log_ratios(np.array([[800.0, -800.0]]))))


def test_a_fold_gives_back_the_spread_it_takes():
    """Values that reached past a bound are folded back and spread to their standard
    deviation before the fold; values that stayed inside are returned as they were."""
    rng = np.random.default_rng(0)
    inside = rng.uniform(0.2, 0.8, 5000)
    np.testing.assert_array_equal(pf._fold_keeping_spread(inside, 0.0, 1.0), inside)
    past = rng.normal(0.1, 0.15, 5000)  # a third of it below 0
    y = pf._fold_keeping_spread(past, 0.0, 1.0)
    assert np.all((y >= 0.0) & (y <= 1.0))
    assert pf._reflect_into(past, 0.0, 1.0).std() < 0.75 * past.std()  # what the fold alone leaves
    assert abs(y.std() / past.std() - 1) < 0.02
    # a cloud with no spread stays where the fold puts it
    np.testing.assert_allclose(pf._fold_keeping_spread(np.full(4, -0.1), 0.0, 1.0), np.full(4, 0.1), rtol=1e-12)


def test_roughening_keeps_a_prior_cloud_without_data():
    """A cloud the data leave alone stays its prior through roughening: a log-uniform spring,
    a link and the object's mass, 120 roughenings with no measurement. Folded back at the
    ranges' ends without giving back the spread the fold takes, their spread fell to 0.66 /
    0.72 / 0.71 of the prior's in 60 roughenings (the cloud wore towards its range's middle,
    as if the data had narrowed it), and the spring, roughened as k, lost its log-uniform
    shape. The contacts' shares of the mass keep their Dirichlet prior's spread too: roughened
    as loads folded back at 0 they had worn towards equal shares (a share's SD 0.236 -> 0.11,
    shares under 5% 0.098 -> 0.008 of the cloud after 120 roughenings)."""
    from vlr_drake.hand import hand_by_name

    h = hand_by_name("NH2").model()
    th, a = _truth_grasp(h, np.random.default_rng(0))
    prior = pf.PriorConfig(links_unknown=[0], stiffness_unknown=[(0, 1)], object_mass_unknown=True,
                           object_mass_range=(0.0, 0.15))
    cfg = pf.FilterConfig(particles=6000, gravity_palm=[0.0, 0.0, 9.81], gravity_loads="following")
    f = pf.SelfIdentificationFilter(h, cfg, prior, np.random.default_rng(2))
    ps = f.initialise(th, a, np.eye(3), np.array([0.0, 0.0, 0.1]),
                      tendon_command=h.tendon_travel(th[None])[0] + 0.004)
    (klo, khi), (llo, lhi), (mlo, mhi) = prior.stiffness_range, prior.link_range, prior.object_mass_range
    # the prior itself (a grasp's physical draws hold fewer soft springs: this checks the kernel)
    rng, n = np.random.default_rng(3), ps.size
    k, L = ps.stiffness.copy(), ps.link_lengths.copy()
    k[:, 0, 1] = np.exp(rng.uniform(np.log(klo), np.log(khi), n))
    L[:, 0, 0] = rng.uniform(llo, lhi, n)
    ps.stiffness, ps.link_lengths = k, L
    ps.object_load = rng.uniform(mlo, mhi, n)[:, None] * rng.dirichlet(np.ones(h.N), n)
    given = np.column_stack([k[:, 0, 1], L[:, 0, 0], ps.object_load])
    for _ in range(120):
        ps.log_w = np.zeros(ps.size)
        f._roughen(ps)
    m = ps.object_load.sum(1)
    uniforms = {"spring": np.log(ps.stiffness[:, 0, 1] / klo) / np.log(khi / klo),  # uniform on [0, 1]
                "link": (ps.link_lengths[:, 0, 0] - llo) / (lhi - llo), "mass": (m - mlo) / (mhi - mlo)}
    # each hypothesis wandered off its own draw (h = 0.2: a correlation of about 0.1 after 120
    # roughenings): a spring, link or load the roughening left alone had kept its prior too
    moved = np.column_stack([ps.stiffness[:, 0, 1], ps.link_lengths[:, 0, 0], ps.object_load])
    corr = [np.corrcoef(given[:, i], moved[:, i])[0, 1] for i in range(given.shape[1])]
    assert max(corr) < 0.5, corr
    for name, u in uniforms.items():
        assert abs(u.std() * np.sqrt(12) - 1) < 0.08, (name, u.std() * np.sqrt(12))
        # each tenth of the range keeps its tenth (sampling error about 0.004; worn, the
        # first tenth of the mass held 0.025 after 60 roughenings)
        np.testing.assert_allclose(np.histogram(u, np.linspace(0.0, 1.0, 11))[0] / n, 0.1, atol=0.025, err_msg=name)
    shares = ps.object_load / m[:, None]  # each Beta(1, N - 1) under the prior: SD 0.236 for N = 3
    sd0 = np.sqrt((h.N - 1) / (h.N**2 * (h.N + 1)))
    under = 1 - (1 - 0.05) ** (h.N - 1)  # the prior's fraction of shares under 5%
    for i in range(h.N):
        assert 0.85 < shares[:, i].std() / sd0 < 1.25, (i, shares[:, i].std() / sd0)
        assert 0.6 * under < np.mean(shares[:, i] < 0.05) < 1.6 * under, (i, np.mean(shares[:, i] < 0.05))


def test_an_unknown_spring_stays_one_per_hypothesis_when_a_batch_keeps_one(monkeypatch):
    """The prior's batches of draws are joined by what the prior leaves unknown: a first
    batch with a single physical draw had been taken for a known (shared) spring, and every
    hypothesis got that one spring."""
    h = model_o().model()
    th, a = _truth_grasp(h, np.random.default_rng(0))
    f = pf.SelfIdentificationFilter(h, pf.FilterConfig(particles=50), pf.PriorConfig(stiffness_unknown=[(0, 1)]),
                                    np.random.default_rng(1))
    real, batches = f._draw_grasps, []

    def first_keeps_one(*args):
        out = real(*args)
        if not batches:  # a prior that accepts few draws: one physical draw in the first batch
            good = out[-1]
            keep = np.flatnonzero(good)[:1]
            good[:] = False
            good[keep] = True
        batches.append(int(out[-1].sum()))
        return out

    monkeypatch.setattr(f, "_draw_grasps", first_keeps_one)
    ps = f.initialise(th, a, np.eye(3), np.array([0.0, 0.0, 0.1]),
                      tendon_command=h.tendon_travel(th[None])[0] + 0.004)
    assert batches[0] == 1 and len(batches) > 1
    assert ps.stiffness.shape == (50, h.N, h.K) and np.unique(ps.stiffness[:, 0, 1]).size == 50


def test_tendon_state_follows_the_commanded_pull():
    """tendon_reference "commanded": every hypothesis' stretch is l - R theta for the motors'
    absolute pull l, after initialisation, moves, resampling and roughening alike (so the
    motor state is evidence); "implied" (the paper's) keeps the equilibrium stretch instead.
    Without the command, the filter says what it needs."""
    h, plant, f = _filter_and_plant(6, particles=2000)

    def pull(filt):
        ps = filt.particles
        return np.einsum("nk,pnk->pn", h.moment_arms, ps.theta) + ps.stretch

    np.testing.assert_allclose(pull(f), np.broadcast_to(plant.state.tendon_command, (2000, 3)), atol=1e-12)
    for i in range(4):
        dl = (-1) ** i * np.array([0.3e-3, -0.2e-3, 0.3e-3])
        assert plant.apply_action(dl)
        f.step(dl, *plant.measure()[:2], tendon_command=plant.state.tendon_command)
        live = np.isfinite(f.particles.log_w)  # (a failed move keeps its old state, and dies)
        assert live.mean() > 0.9
        np.testing.assert_allclose(pull(f)[live], np.broadcast_to(plant.state.tendon_command, (live.sum(), 3)),
                                   atol=1e-12)
    assert f.resamples > 0
    implied = pf.SelfIdentificationFilter(h, pf.FilterConfig(particles=500, tendon_reference="implied"),
                                          pf.PriorConfig(), np.random.default_rng(0))
    implied.initialise(plant.state.theta, plant.state.a, *plant.measure()[:2])  # no command needed
    assert np.ptp(pull(implied), axis=0).max() > 1e-3  # each hypothesis its own equilibrium pull
    commanded = pf.SelfIdentificationFilter(h, pf.FilterConfig(particles=500), pf.PriorConfig(),
                                            np.random.default_rng(0))
    with pytest.raises(ValueError, match="tendon_command"):
        commanded.initialise(plant.state.theta, plant.state.a, *plant.measure()[:2])
    with pytest.raises(ValueError, match="tendon_reference"):
        pf.FilterConfig(tendon_reference="absolute").validate()


@pytest.mark.parametrize("held_motion", ["still", "elastic"])
def test_failed_moves_are_discarded_or_held(monkeypatch, held_motion):
    """stuck_probability: a hypothesis whose move finds no equilibrium weighs nothing at 0;
    above 0 it keeps its angles ("still"; "elastic": moved from where friction holds it),
    predicts a POM, and the camera weighs that prediction, times the probability (here the
    measurement is exactly hypothesis 0's unmoved pose: held still, it weighs the most at 1,
    and the moved ones gain log(1/p) on it at p). The elastically moved held ones had
    escaped the probability (a review)."""
    from vlr_drake import kinematics, observation

    real_move = pf.motion.move
    solved = {}

    def move_failing_evens(hand, theta, dl, **kw):  # every other hypothesis finds no equilibrium
        res = real_move(hand, theta, dl, **kw)
        if theta.shape[0] == 400:  # (the commanded move; not the held ones' elastic moves)
            res.ok[::2] = False
            res.theta[::2] = theta[::2]  # as motion.move leaves a failed hypothesis
            solved["ok"] = res.ok.copy()
        return res

    monkeypatch.setattr(pf.motion, "move", move_failing_evens)
    dl = np.array([0.3e-3, -0.2e-3, 0.3e-3])
    relative = {}
    for p in (0.0, 1.0, 0.1):  # no tempering, no resampling: the weights are the likelihoods
        h, plant, f = _filter_and_plant(6, particles=400, stuck_probability=p, resample_fraction=0.0,
                                        ess_fraction=1e-12, held_motion=held_motion)
        ps = f.particles
        theta0 = ps.theta.copy()
        R0, t0, _ = observation.pom_pose(ps.p_O, kinematics.contacts(h, ps.theta, ps.a, ps.link_lengths))
        rep = f.step(dl, R0[0], t0[0])  # the camera sees hypothesis 0's unmoved pose
        assert rep.solve_failures >= 200 and rep.beta == 1.0
        log_w = f.particles.log_w
        if p == 0:
            assert np.all(np.isneginf(log_w[~solved["ok"]])) and np.isfinite(log_w[solved["ok"]]).mean() > 0.9
            continue
        if held_motion == "still":
            np.testing.assert_array_equal(f.particles.theta[::2], theta0[::2])
        else:  # most held ones moved from their own equilibrium
            assert np.mean(np.any(f.particles.theta[::2] != theta0[::2], axis=(1, 2))) > 0.5
        assert np.isfinite(log_w[::2]).mean() > 0.9
        relative[p] = log_w - log_w[0]
        if p == 1 and held_motion == "still":
            assert np.argmax(log_w) == 0 and log_w[0] == 0.0
    live = np.isfinite(relative[1.0])
    moved, held = live & solved["ok"], live & ~solved["ok"]
    assert moved.sum() > 100 and held.sum() > 150
    np.testing.assert_allclose(relative[0.1][moved], relative[1.0][moved] + np.log(10.0))
    np.testing.assert_allclose(relative[0.1][held], relative[1.0][held])
    with pytest.raises(ValueError, match="stuck_probability"):
        pf.FilterConfig(stuck_probability=1.5).validate()


def test_held_hypotheses_move_elastically_from_their_own_equilibrium():
    """held_motion "elastic": a hypothesis whose move under the commanded tendon state
    fails is moved by the action from the stretch of its own equilibrium (what friction
    would hold), exactly as motion.move does from there; "still" keeps it where it was."""
    from vlr_drake import kinematics

    h, plant, f = _filter_and_plant(7, particles=300, stuck_probability=1.0, held_motion="elastic")
    ps = f.particles
    ps.stretch = f._commanded_stretch(ps.theta)
    D2 = pf.motion.contact_distances_sq(h, ps.p_O)
    dl = np.array([5e-3, 5e-3, -5e-3])  # large enough that some find no equilibrium from their own state
    res = pf.motion.move(h, ps.theta, dl, a=ps.a, D2=D2, stretch=ps.stretch)
    res.ok[::3] = False  # as if these found no equilibrium under the commanded state
    res.theta[::3] = ps.theta[::3]
    out = f._move_held(res, dl, D2, f.config.max_substeps)
    eq = pf.motion.equilibrium(h, ps.theta[::3], a=ps.a[::3])
    want = pf.motion.move(h, eq.theta, dl, a=ps.a[::3], D2=D2[::3], stretch=eq.stretch,
                          max_substeps=f.config.max_substeps, loose_after=f.config.newton_loose_after)
    assert 80 < want.ok.sum() < 100  # most have an equilibrium from their own state, not all (91)
    np.testing.assert_array_equal(out.ok[::3], want.ok & eq.ok)
    np.testing.assert_array_equal(out.theta[::3][want.ok], want.theta[want.ok])
    np.testing.assert_array_equal(out.theta[::3][~want.ok], ps.theta[::3][~want.ok])  # still held
    np.testing.assert_array_equal(out.theta[res.ok], res.theta[res.ok])  # the solved ones untouched
    assert not np.allclose(kinematics.contacts(h, out.theta[::3][want.ok], ps.a[::3][want.ok]),
                           kinematics.contacts(h, ps.theta[::3][want.ok], ps.a[::3][want.ok]))
    rep = f.step(dl, *plant.measure()[:2])  # and in a filter iteration
    assert np.isfinite(rep.log_evidence)
    with pytest.raises(ValueError, match="held_motion"):
        pf.FilterConfig(held_motion="sliding").validate()


def test_a_small_cloud_says_its_intervals_are_too_narrow():
    """Fewer than CALIBRATED_PARTICLES hypotheses give overconfident intervals (measured in
    its comment): such a filter warns, once, and a calibrated one does not."""
    import warnings

    h = model_o().model()
    with pytest.warns(pf.FewParticlesWarning, match="500 particles: fewer than 3,000 hypotheses"):
        pf.SelfIdentificationFilter(h, pf.FilterConfig(particles=500), pf.PriorConfig(), np.random.default_rng(0))
    with warnings.catch_warnings():
        warnings.simplefilter("error", pf.FewParticlesWarning)
        pf.SelfIdentificationFilter(h, pf.FilterConfig(particles=pf.CALIBRATED_PARTICLES), pf.PriorConfig(),
                                    np.random.default_rng(0))


@pytest.mark.parametrize("field", ["roughening", "ess_fraction", "resample_fraction", "anchor_fraction",
                                   "stuck_probability", "likelihood_width"])
@pytest.mark.parametrize("value", ["0.5", True, [0.5]])
def test_filter_fractions_must_be_numbers(field, value):
    """Text or a list had ended validate() in a TypeError from a comparison ("'<' not supported
    between instances of 'int' and 'str'"), and True had been taken as 1 (resample at every step,
    anchor all the way, every stuck hypothesis kept)."""
    with pytest.raises(ValueError, match=f"filter: '{field}' must be a number, got"):
        pf.FilterConfig(**{field: value}).validate()


@pytest.mark.parametrize("value", [9.81, None, "0,0,-9.81", [0.0, "x", -9.81], np.array([0.0, np.nan, -9.81])])
def test_gravity_that_is_no_three_numbers_is_named(value):
    """A single number or None had ended validate() in a TypeError raised while its own
    message was written ("'float' object is not iterable"); text, an unnamed ValueError."""
    with pytest.raises(ValueError, match=r"filter: 'gravity_palm' must be 3 finite numbers \[m/s\^2\], got"):
        pf.FilterConfig(gravity_palm=value).validate()


@pytest.mark.parametrize("value", ["false", "no", 0, 1, None])
def test_the_configurations_switches_must_be_true_or_false(value):
    """Text was read by its truth: settle_prior "false" settled every prior draw, and
    object_mass_unknown "false" identified the object's weight."""
    with pytest.raises(ValueError, match="filter: 'settle_prior' must be True or False, got"):
        pf.FilterConfig(settle_prior=value).validate()
    with pytest.raises(ValueError, match="prior: 'object_mass_unknown' must be True or False, got"):
        pf.PriorConfig(object_mass_unknown=value).validate()
    pf.FilterConfig(settle_prior=np.bool_(True)).validate()
    pf.PriorConfig(object_mass_unknown=np.bool_(False)).validate()


@pytest.mark.parametrize("field, value", [("proximal_half_width", "0.1"), ("contact_half_width", True),
                                          ("min_tension", None), ("com_half_width", [0.02]),
                                          ("link_range", (0.03,)), ("stiffness_range", "0.05-0.4"),
                                          ("object_mass_range", (0.0, "0.2"))])
def test_the_priors_numbers_must_be_numbers(field, value):
    """Text had ended in a bare TypeError ("'<' not supported ..."), True been read as 1 (rad
    or m), a range that is no pair in "cannot unpack"."""
    with pytest.raises(ValueError, match=f"prior: '{field}' must be (a number|\\(min, max\\), a pair)"):
        pf.PriorConfig(**{field: value}).validate()
    pf.PriorConfig(link_range=np.array([0.03, 0.075]), proximal_half_width=np.float64(0.1)).validate()


@pytest.mark.parametrize("field, value", [("stiffness_unknown", [(1.5, 0)]), ("stiffness_unknown", [(True, 1)]),
                                          ("stiffness_unknown", [(0, 1, 2)]), ("stiffness_unknown", [0, 1]),
                                          ("stiffness_unknown", None), ("links_unknown", [1.0]),
                                          ("links_unknown", [True]), ("links_unknown", 2), ("links_unknown", ["1"])])
def test_unknowns_must_name_fingers_and_joints_by_integers(field, value):
    """A float index (1.5, or 1.0) had passed the prior's check and failed at the first draw in
    numpy's 'only integers ... are valid indices', True had named finger 1 and failed there in
    a shape mismatch, and a misshapen list ended in a TypeError from unpacking."""
    with pytest.raises(ValueError, match=f"prior: '{field}' must be a list of"):
        pf.PriorConfig(**{field: value}).validate(3, 2)
    pf.PriorConfig(stiffness_unknown=[(np.int64(0), 1)], links_unknown=(np.int64(2),)).validate(3, 2)


def test_bad_configuration_is_named():
    with pytest.raises(ValueError, match="particles"):
        pf.FilterConfig(particles=1).validate()
    with pytest.raises(ValueError, match="tendon"):
        pf.FilterConfig(tendon="rope").validate()
    from vlr_drake.hand import model_o

    with pytest.raises(ValueError, match="stiffness_unknown"):
        pf.SelfIdentificationFilter(model_o().model(), pf.FilterConfig(), pf.PriorConfig(stiffness_unknown=[(5, 0)]),
                                    np.random.default_rng(0))
    with pytest.raises(ValueError, match="stiffness_prior"):
        pf.SelfIdentificationFilter(model_o().model(), pf.FilterConfig(), pf.PriorConfig(stiffness_prior="normal"),
                                    np.random.default_rng(0))
    with pytest.raises(ValueError, match="newton_tolerance"):
        pf.FilterConfig(newton_tolerance="sloppy").validate()
    with pytest.raises(ValueError, match="nominal_grasp"):
        IdentifyOptions(plant="physics", nominal_grasp="guessed").validate()
    with pytest.raises(ValueError, match="'gravity_palm' must be 3 finite numbers"):
        pf.FilterConfig(gravity_palm=(0.0, 9.81)).validate()
    with pytest.raises(ValueError, match="link_weight needs the physics plant"):
        IdentifyOptions(plant="model", link_weight=True).validate()


def test_link_weight_defaults_per_plant_and_experiment():
    """The physics plant carries the links' weight, held through a move for the known hand
    and the novel fingers and following the angles for the stiffness (GRAVITY_LOADS); the
    model plant does not (its truth is Eq. 9); a given value is kept, the object's weight
    follows, and the builder resolves a scenario the same way."""
    from vlr_drake.builder import build_diagram
    from vlr_drake.scenario import Scenario

    def resolved(**kw):
        o = IdentifyOptions(**kw).validate()
        return o.link_weight, o.filter.gravity_loads

    assert resolved(plant="physics", experiment="known_hand") == (True, "held")
    assert resolved(plant="physics", experiment="novel_fingers", hand="NH2") == (True, "held")
    assert resolved(plant="physics", experiment="stiffness") == (True, "following")
    assert not resolved(plant="model", experiment="known_hand")[0]
    assert not resolved(plant="physics", experiment="known_hand", link_weight=False)[0]
    assert resolved(plant="physics", experiment="known_hand", object_weight=True) == (True, "following")
    given = IdentifyOptions(plant="physics", filter=pf.FilterConfig(gravity_loads="following")).validate()
    assert given.filter.gravity_loads == "following"
    with pytest.raises(ValueError, match=r"object_weight \(or a weighed object_mass\) needs link_weight"):
        IdentifyOptions(plant="physics", object_weight=True, link_weight=False).validate()
    with pytest.raises(ValueError, match="object_weight needs filter gravity_loads"):
        IdentifyOptions(plant="physics", object_weight=True, filter=pf.FilterConfig(gravity_loads="held")).validate()
    g = PhysicsConfig(palm_rpy_deg=[90.0, 0.0, 0.0]).gravity_in_palm()
    np.testing.assert_allclose(g, [0.0, -9.81, 0.0], atol=1e-12)  # palm facing sideways
    np.testing.assert_allclose(PhysicsConfig().gravity_in_palm(), [0.0, 0.0, 9.81], atol=1e-12)  # palm down
    s = Scenario(plant="model", link_weight=True)
    with pytest.raises(ValueError, match="'link_weight': only the physics plant"):
        s.validate()
    with pytest.raises(ValueError, match="'gravity_palm' is a hardware hand's mounting"):  # not silently replaced
        build_diagram(Scenario(plant="model", filter=pf.FilterConfig(particles=100, gravity_palm=(0.0, 0.0, 1.0))))
    built = build_diagram(Scenario(plant="model", filter=pf.FilterConfig(particles=100)))
    assert built.filter._config.gravity_palm == [0.0, 0.0, 0.0]  # the model plant's truth has no link weight
    physics = build_diagram(Scenario(plant="physics", filter=pf.FilterConfig(particles=100)))
    np.testing.assert_allclose(physics.filter._config.gravity_palm, [0.0, 0.0, 9.81], atol=1e-12)
    assert physics.filter._config.gravity_loads == "held"


def test_likelihood_width_scales_both_sigmas_and_has_per_experiment_defaults():
    """likelihood_width w is the likelihood with sigmas w sigma_p and w sigma_r (None: 1);
    identification runs and scenario diagrams take LIKELIHOOD_WIDTH's defaults (1.5 for the
    physics known hand, 1.75 for its stiffness, 1 for the novel fingers and the model plant)."""
    from vlr_drake.builder import build_diagram
    from vlr_drake.identify import default_likelihood_width
    from vlr_drake.scenario import Scenario

    hand = model_o().model()
    R = np.repeat(np.eye(3)[None], 3, axis=0)
    t = np.zeros((3, 3))
    dp, ang = np.array([0.0, 2e-4, 5e-4]), np.array([0.02, 0.0, 0.01])

    def ll(**kw):
        f = pf.SelfIdentificationFilter(hand, pf.FilterConfig(**kw), pf.PriorConfig(), np.random.default_rng(0))
        return f._log_likelihood(dp, ang, R, t, R, t)

    base, wide = pf.FilterConfig(), pf.FilterConfig(likelihood_width=2.0)
    assert wide.sigmas() == (2 * base.sigma_position, 2 * base.sigma_rotation) and base.sigmas() == (
        base.sigma_position, base.sigma_rotation)
    np.testing.assert_allclose(ll(likelihood_width=2.0)[0], ll(sigma_position=2 * base.sigma_position,
                                                                sigma_rotation=2 * base.sigma_rotation)[0])
    np.testing.assert_allclose(ll(likelihood_width=None)[1], ll(likelihood_width=1.0)[1])
    with pytest.raises(ValueError, match="'likelihood_width' must be None or a positive finite number, got 0"):
        pf.FilterConfig(likelihood_width=0.0).validate()
    assert default_likelihood_width("physics", "known_hand") == default_likelihood_width("hardware", "known_hand") == 1.5
    assert default_likelihood_width("physics", "stiffness") == default_likelihood_width("hardware", "stiffness") == 1.75
    assert default_likelihood_width("physics", "novel_fingers") == default_likelihood_width("model", "known_hand") == 1.0
    physics = build_diagram(Scenario(plant="physics", filter=pf.FilterConfig(particles=100)))
    assert physics.filter._config.likelihood_width == 1.5  # the default scenario: the known hand
    model = build_diagram(Scenario(plant="model", filter=pf.FilterConfig(particles=100, likelihood_width=1.2)))
    assert model.filter._config.likelihood_width == 1.2  # a given value is kept


def test_each_experiment_holds_its_papers_object_unless_told():
    """The stiffness experiment holds the toy block, as the paper's Fig. 5 did (and as
    reproduce runs it); the others the apple; a given object is kept."""
    from vlr_drake.reproduce import STIFFNESS_OBJECT

    assert IdentifyOptions(experiment="stiffness").validate().object == "toy_block" == STIFFNESS_OBJECT
    assert IdentifyOptions(experiment="known_hand").validate().object == "apple"
    assert IdentifyOptions(experiment="stiffness", object="apple").validate().object == "apple"


def test_iteration_budget_is_the_experiments_unless_told():
    """The stiffness on either plant and the novel fingers on the physics plant run 240
    iterations (their hand parameters narrow slowly), the rest 120; a given budget is kept,
    and one that is not a positive integer is named."""
    from vlr_drake.identify import DEFAULT_ITERATIONS, default_iterations
    from vlr_drake.scenario import DIAGRAMS_DIR, load_scenario, options_from_scenario

    assert DEFAULT_ITERATIONS == 120 and default_iterations("hardware", "stiffness") == 240
    budgets = {(p, e): IdentifyOptions(experiment=e, plant=p, hand="NH1" if e == "novel_fingers" else "model_o")
               .validate().max_iterations for p in ("model", "physics") for e in ("known_hand", "stiffness",
                                                                                  "novel_fingers")}
    assert budgets == {("model", "known_hand"): 120, ("model", "stiffness"): 240, ("model", "novel_fingers"): 120,
                       ("physics", "known_hand"): 120, ("physics", "stiffness"): 240,
                       ("physics", "novel_fingers"): 240}
    assert IdentifyOptions(experiment="stiffness", plant="physics", max_iterations=30).validate().max_iterations == 30
    scenario = load_scenario(DIAGRAMS_DIR / "stiffness.yaml")  # the model plant
    assert options_from_scenario(scenario, max_iterations=None).validate().max_iterations == 240
    assert options_from_scenario(scenario, plant="physics", max_iterations=None).validate().max_iterations == 240
    for bad in (0, 2.5, True):
        with pytest.raises(ValueError, match="max_iterations must be an integer >= 1"):
            IdentifyOptions(max_iterations=bad).validate()


@pytest.mark.parametrize("kind", ["uniform", "log_uniform"])
def test_unknown_stiffness_prior_draws(kind):
    """The unknown stiffness is drawn in its range, uniformly or log-uniformly (the median
    at the range's mean or its geometric mean)."""
    h = model_o().model()
    prior = pf.PriorConfig(stiffness_unknown=[(0, 1)], stiffness_range=(0.05, 0.40), stiffness_prior=kind)
    f = pf.SelfIdentificationFilter(h, pf.FilterConfig(particles=100), prior, np.random.default_rng(0))
    k = f._draw_stiffness(20000, None, 1.0)
    assert k[:, 0, 1].min() >= 0.05 and k[:, 0, 1].max() <= 0.40
    np.testing.assert_array_equal(np.delete(k.reshape(20000, -1), 1, axis=1)[0], np.delete(h.stiffness.ravel(), 1))
    median = np.sqrt(0.05 * 0.40) if kind == "log_uniform" else 0.225
    assert abs(np.median(k[:, 0, 1]) - median) < 0.01


def _initialised(prior, config=None, seed=0):
    h = model_o().model()
    theta, a = _truth_grasp(h, np.random.default_rng(seed))
    f = pf.SelfIdentificationFilter(h, config or pf.FilterConfig(particles=8000), prior, np.random.default_rng(seed + 1))
    l = h.tendon_travel(theta[None])[0] + 0.004  # a squeeze: the tendons pull 4 mm past the grasp
    f.initialise(theta, a, np.eye(3), np.array([0.0, 0.0, 0.1]), tendon_command=l)
    return h, f


def test_settled_prior_is_at_rest_under_the_command():
    """With settle_prior every initial hypothesis is an equilibrium under the motors'
    command: a zero action leaves it where it is (no settling in the first prediction),
    and each is a physical grasp. Without it the first move carries hypotheses degrees away."""
    prior = pf.PriorConfig()
    for settle in (False, True):
        h, f = _initialised(prior, pf.FilterConfig(particles=2000, settle_prior=settle))
        ps = f.particles
        assert np.all(ps.stretch > 0) and np.all(h.within_joint_limits(ps.theta))
        res = pf.motion.move(h, ps.theta, np.zeros(h.N), a=ps.a, D2=pf.motion.contact_distances_sq(h, ps.p_O),
                             stretch=ps.stretch, link_lengths=ps.link_lengths, stiffness=ps.stiffness)
        jump = np.rad2deg(np.abs(res.theta - ps.theta).max(axis=(1, 2)))[res.ok]
        if settle:
            assert res.ok.all() and jump.max() < 1e-3
        else:
            assert np.median(jump) > 1.0


@pytest.mark.parametrize("mode", pf.GRAVITY_LOADS)
def test_link_weight_reaches_every_model_call_of_the_filter(monkeypatch, mode):
    """With ``gravity_palm`` every move and equilibrium of the filter (prior, settling,
    the step's move, roughening) carries the links' weight: as each hypothesis' torques at
    its angles (``gravity_loads`` "held") or as the gravity that follows them ("following");
    without it none does, and the weight moves the settled hypotheses."""
    calls = []
    for name in ("move", "equilibrium"):
        real = getattr(pf.motion, name)

        def spy(*args, _real=real, _name=name, **kw):
            calls.append((_name, kw.get("gravity"), kw.get("external_torque")))
            return _real(*args, **kw)

        monkeypatch.setattr(pf.motion, name, spy)
    g = (0.0, 0.0, 9.81)  # the physics plant's palm-down mounting
    h = model_o().model()
    theta, a = _truth_grasp(h, np.random.default_rng(0))
    l = h.tendon_travel(theta[None])[0] + 0.004
    settled = {}
    for gravity in ((0.0, 0.0, 0.0), g):
        calls.clear()
        cfg = pf.FilterConfig(particles=500, gravity_palm=gravity, resample_fraction=1.0, settle_prior=True,
                              gravity_loads=mode)
        f = pf.SelfIdentificationFilter(h, cfg, pf.PriorConfig(), np.random.default_rng(1))
        f.initialise(theta, a, np.eye(3), np.array([0.0, 0.0, 0.1]), tendon_command=l)
        settled[gravity] = f.particles.theta.copy()
        f.step(np.full(h.N, 0.2e-3), np.eye(3), np.array([0.0, 0.0, 0.1]))
        assert {n for n, _, _ in calls} == {"move", "equilibrium"}
        for name, g_passed, tau in calls:
            if gravity == (0.0, 0.0, 0.0):
                assert g_passed is None and tau is None, name
            elif mode == "following":
                assert g_passed is not None and tau is None, name
            else:  # held: the torques at the hypotheses' angles
                assert g_passed is None and tau is not None and np.all(np.isfinite(tau)), name
    # the same draws (same seed), settled under the weight or not
    assert np.max(np.abs(settled[g] - settled[(0.0, 0.0, 0.0)])) > 1e-3


@pytest.mark.slow
def test_known_hand_converges_accurately_and_honestly():
    """Model plant, exact truth, 12 seeds x at most 180 iterations at 20,000 particles (the
    issue's calibration check): proximal joint errors under a degree and contact errors
    under 3 mm in a typical run (the median seed; the mean under 2 degrees), and the truth
    inside the reported 95% intervals at least 90% of the time, pooled over every joint angle
    and contact position of every seed. A filter that is sure and wrong fails this even when
    its typical error is small. Measured here (3 mm exploration, tendon state from the
    commanded pull): median 0.46 deg, mean 0.49 deg, contacts 1.4 mm, 12/12 converged in
    28-92 iterations, pooled coverage 0.97 (with the paper's implied tendon state: 0.58 deg,
    7/12 converged, 0.95)."""
    inside, proximal, contact, converged = [], [], [], []
    for seed in range(12):
        r = run_identification(IdentifyOptions(experiment="known_hand", particles=20000, max_iterations=180,
                                               seed=seed, progress=False))
        inside += [r["truth_inside_95_theta"]] * 6 + [r["truth_inside_95_contact"]] * 3
        proximal.append(np.mean(r["proximal_joint_error_deg"]))
        contact.append(np.mean(r["contact_error_mm"]))
        converged.append(r["converged"])
        assert r["interval_half_width_deg_mean"] < 6.0  # it learnt: the prior is ~11 deg
    assert np.median(proximal) < 1.0 and np.mean(proximal) < 2.0, proximal
    assert np.median(contact) < 3.0, contact
    assert np.mean(converged) >= 0.6, converged
    assert np.mean(inside) >= 0.9, np.round(inside, 2)


@pytest.mark.slow
def test_stiffness_is_identified_with_the_elastic_tendon():
    """The thumb's distal spring unknown (prior 0.05-0.40 N m/rad, log-uniform), elastic
    tendon (the spring shapes Eq. 9's motion through the tendon's stretch), 6 seeds x 10,000
    particles x 60 iterations: the interval narrows to a fraction of the prior around the
    truth, and holds it in at least 5 of 6 runs (at 95% coverage that fails 3% of the time).
    Measured (seeds 0-11, 2026-11-27, the model plant's truths stable grasps, the runs
    stopping only once the spring's interval is within 5% of its estimate as well): errors
    0.0007-0.042 N m/rad, median 0.0042 (the paper: 0.0026 +- 0.0012), interval widths
    0.02-0.58 of the prior, median 0.10, 12 of 12 inside. With 5,000 particles the same seeds
    gave median 0.0073 and 9 of 12 inside (three runs converged sure of a spring 0.006-0.013
    off: too few hypotheses for honest intervals with a spring unknown); with the joints alone
    deciding convergence, 0.0088 and 10 of 12. (On the truths of before, half of
    them balanced on saddles of the energy, where the spring shows more: errors 0.0009-0.0113,
    mean 0.0036, widths 2-5% but one of 23%.) A prior the data did not narrow keeps 0.94 of
    its width. The ideal tendon cannot do this: its motion does not depend on the springs
    at all (test_motion.py::test_ideal_motion_does_not_depend_on_the_springs). With the KKT
    regulariser only on failed attempts (the forty-fifth session): errors 0.002-0.0086 on
    seeds 0-4, and seed 5 weakly identified, 0.118 off inside an interval over half the
    prior (0.041 before, in an interval of 45%): a wrong spring is a failure only where the
    run is sure of it."""
    errors, widths, inside = [], [], []
    for seed in range(6):
        r = run_identification(IdentifyOptions(experiment="stiffness", particles=10_000, max_iterations=60, seed=seed,
                                               progress=False))
        lo, hi = r["stiffness_interval_Nm_per_rad"]
        p_lo, p_hi = r["stiffness_prior_Nm_per_rad"]
        errors.append(r["stiffness_error_Nm_per_rad"])
        widths.append((hi - lo) / (p_hi - p_lo))
        inside.append(r["stiffness_inside_95"])
    assert np.median(errors) < 0.012, errors
    for e, w, i in zip(errors, widths, inside, strict=True):  # far off only where honestly unsure
        assert e < 0.05 or (i and w > 0.4), (errors, widths, inside)
    assert np.median(widths) < 0.2 and max(widths) < 0.7, widths
    assert sum(inside) >= 5, inside


@pytest.mark.slow
def test_novel_finger_links_are_identified_honestly():
    """The replaced fingers' proximal links unknown (NH1, NH2, NH3; model plant, identify's
    defaults: 20,000 particles, at most 120 iterations), seeds 0-2: the links' 95% intervals
    hold their truths and the joints' do too (pooled), around errors below the paper's.
    Measured (2026-11-27, the runs stopping only once the links' intervals are within 5% of
    their estimates as well): 18 of 18 links inside, joints 1.00, link errors 0.01-2.5 mm,
    mean 0.74, 47-120 iterations (with the joints alone deciding: 0.98, 0.14-3.7 mm, mean
    1.16; the paper: 2.4 / 2.9 / 3.4 mm on NH1 / NH2 / NH3). With 5,000 particles and
    60 iterations NH2's seed 2 converged at iteration 30 with both links 5.7-7.5 mm off and
    outside their intervals: the kind of run this test is here to catch."""
    links_inside, joints_inside, errors = [], [], []
    for hand in ("NH1", "NH2", "NH3"):
        for seed in range(3):
            r = run_identification(IdentifyOptions(experiment="novel_fingers", hand=hand, plant="model", seed=seed,
                                                   progress=False))
            links_inside += list(r["link_length_inside_95"].values())
            joints_inside.append(r["truth_inside_95_theta"])
            errors += list(r["link_length_error_mm"].values())
    assert len(links_inside) == 3 * (1 + 2 + 3)  # NH1 replaces one finger, NH2 two, NH3 three
    assert sum(links_inside) >= 16, links_inside
    assert np.mean(joints_inside) >= 0.9, joints_inside
    assert np.mean(errors) < 2.4 and max(errors) < 6.0, np.round(errors, 2)


def _run_weighed(seed, load_true, object_mass_unknown, iterations=40, particles=3000):
    """A filter with the links' weight (and, with ``object_mass_unknown``, the object's) on a
    model plant whose truth carries the links' weight and ``load_true`` (N,) [kg] at its
    contacts, palm down; random 3 mm actions. Returns the filter's last estimate."""
    from vlr_drake.identify import Exploration

    h = model_o().model()
    g = np.array([0.0, 0.0, 9.81])
    rng = np.random.default_rng(seed)
    th, a = _truth_grasp(h, rng)
    plant = ModelPlant(h, th, a, np.eye(3), np.array([0.0, 0.0, 0.11]), np.random.default_rng(seed + 1),
                       gravity=g, object_load=load_true)
    prior = pf.PriorConfig(object_mass_unknown=object_mass_unknown)
    cfg = pf.FilterConfig(particles=particles, gravity_palm=g.tolist(), gravity_loads="following")
    f = pf.SelfIdentificationFilter(h, cfg, prior, np.random.default_rng(seed + 2))
    R, t, _ = plant.measure()
    f.initialise(th + 0.03, a + 0.002, R, t, tendon_command=plant.state.tendon_command)
    explore = Exploration(plant.state.tendon_command, h.tendon_range, 3e-3, 6e-3, np.random.default_rng(seed + 3))
    for _ in range(iterations):
        dl = explore.next_action()
        if not plant.apply_action(dl):
            continue
        explore.commit(dl)
        R, t, valid = plant.measure()
        f.step(dl, R, t, valid, tendon_command=plant.state.tendon_command)
    return f.estimate(), plant.state


def test_object_weight_is_identified_where_the_truth_has_it():
    """PriorConfig.object_mass_unknown on a model plant that carries a 120 g object at its
    contacts (thumb half, the fingers a quarter each): the mass's 95% interval holds the truth
    and has narrowed from the prior's (0-250 g), each contact's share lies inside its interval,
    and the joints are found; a filter that knows only the links' weight is further off.
    Measured (seeds 0-2): mass 92 / 151 / 107 g, joints 1.04 / 0.61 / 1.32 deg against
    1.93 / 2.88 / 2.12 without the object's weight. Since roughening folds the mass back at
    its range's ends instead of clipping it there (2026-12-06; seeds 0-3): mass 114 / 125 /
    102 / 148 g in intervals 149 / 182 / 97 / 140 g wide (the prior cloud's: 238 g), joints
    1.02 / 0.35 / 1.21 / 0.78 deg. With the KKT regulariser only where a pivot fails (the
    forty-fifth session; the plant moves with the same Newton): 96 / 162 / 141 / 180 g; over
    seeds 0-19 the mass 141 g on average (138 before), the truth inside 19 of 20 intervals
    (20 before)."""
    load_true = 0.12 * np.array([0.5, 0.25, 0.25])
    masses = []
    for seed in (0, 1):
        est, truth = _run_weighed(seed, load_true, True)
        lo, hi = float(est["object_mass_lo"]), float(est["object_mass_hi"])
        assert lo <= 0.12 <= hi and hi - lo < 0.8 * 0.25, (seed, lo, float(est["object_mass"]), hi)
        masses.append(float(est["object_mass"]))
        # the split is weakly identified in 40 actions, but honestly: each share inside its interval
        assert np.all((est["object_load_lo"] <= load_true) & (load_true <= est["object_load_hi"])), est["object_load"]
        err = np.rad2deg(np.abs(est["theta"] - truth.theta)).mean()
        blind, truth_b = _run_weighed(seed, load_true, False)
        err_blind = np.rad2deg(np.abs(blind["theta"] - truth_b.theta)).mean()
        assert err < 1.5 and err < err_blind, (seed, err, err_blind)
        assert float(blind["object_mass"]) == 0.0  # no load identified: a weightless object
    # and near it: a filter carrying three quarters of each hypothesis' load passed the
    # intervals' checks on seed 0 (a review; its estimate is a third too heavy)
    assert abs(np.mean(masses) - 0.12) < 0.025, masses


def test_object_weight_needs_gravity_and_a_mass_range():
    h = model_o().model()
    with pytest.raises(ValueError, match="object_mass_unknown needs gravity"):
        pf.SelfIdentificationFilter(h, pf.FilterConfig(particles=100), pf.PriorConfig(object_mass_unknown=True),
                                    np.random.default_rng(0))
    with pytest.raises(ValueError, match="gravity_loads"):
        pf.SelfIdentificationFilter(h, pf.FilterConfig(particles=100, gravity_palm=[0.0, 0.0, 9.81]),
                                    pf.PriorConfig(object_mass_unknown=True), np.random.default_rng(0))
    with pytest.raises(ValueError, match="gravity_loads"):
        pf.FilterConfig(gravity_loads="lagged").validate()
    with pytest.raises(ValueError, match="object_mass_range"):
        pf.SelfIdentificationFilter(h, pf.FilterConfig(particles=100, gravity_palm=[0.0, 0.0, 9.81],
                                                       gravity_loads="following"),
                                    pf.PriorConfig(object_mass_unknown=True, object_mass_range=(0.2, 0.1)),
                                    np.random.default_rng(0))


def test_weighed_object_mass_sets_the_object_weight_and_its_range():
    """IdentifyOptions.object_mass (a weighed object) identifies the object's weight with the
    mass drawn within +-object_mass_tolerance of it; a scenario's prior that asks for the
    object's mass gets the same gravity loads (following); bad masses and tolerances are named;
    the experiment's unknowns keep the prior's own ranges."""
    from vlr_drake.identify import _hands

    o = IdentifyOptions(plant="physics", experiment="stiffness", object="toy_block", object_mass=0.028).validate()
    assert o.object_weight and o.filter.gravity_loads == "following"
    _, _, prior = _hands(o, np.random.default_rng(0))
    assert prior.object_mass_unknown and prior.object_mass_range == pytest.approx((0.021, 0.035))
    o = IdentifyOptions(plant="physics", experiment="known_hand",
                        prior=pf.PriorConfig(object_mass_unknown=True, object_mass_range=(0.05, 0.1))).validate()
    assert o.object_weight and o.filter.gravity_loads == "following"
    assert _hands(o, np.random.default_rng(0))[2].object_mass_range == (0.05, 0.1)  # the prior's, not weighed
    for bad in (0.0, -0.1, float("nan"), "heavy"):
        with pytest.raises(ValueError, match="object_mass must be the object's weighed mass"):
            IdentifyOptions(plant="physics", object_mass=bad).validate()
    for bad in (0.0, 1.0, -0.2):
        with pytest.raises(ValueError, match="object_mass_tolerance must be a fraction"):
            IdentifyOptions(plant="physics", object_mass=0.1, object_mass_tolerance=bad).validate()
    # on the model plant the message was "needs link_weight", and --link-weight then "needs the
    # physics plant" (review): it names the plant at once
    with pytest.raises(ValueError, match="object_weight .* needs the physics plant"):
        IdentifyOptions(plant="model", object_mass=0.1).validate()
    # a range given beside the weighed mass was replaced by the weighed one without a word (review)
    with pytest.raises(ValueError, match=r"'object_mass_range' \(\(0.05, 0.1\)\) and the weighed object_mass"):
        IdentifyOptions(plant="physics", object_mass=0.028,
                        prior=pf.PriorConfig(object_mass_unknown=True, object_mass_range=(0.05, 0.1))).validate()
    weighed = pf.PriorConfig(object_mass_unknown=True, object_mass_range=pf.weighed_mass_range(0.028, 0.25))
    IdentifyOptions(plant="physics", object_mass=0.028, prior=weighed).validate()  # a weighed scenario's own range
    # a range without the weight identified was dropped; a malformed one failed unnamed; grams
    with pytest.raises(ValueError, match="'object_mass_range' \\(\\(0.05, 0.1\\)\\) needs object_mass_unknown"):
        pf.PriorConfig(object_mass_range=(0.05, 0.1)).validate()
    with pytest.raises(ValueError, match="'object_mass_range' must be \\(min, max\\)"):
        pf.PriorConfig(object_mass_unknown=True, object_mass_range=(0.0, 0.1, 0.2)).validate()
    with pytest.warns(UserWarning, match="28 kg .*was it given in grams"):
        pf.weighed_mass_range(28.0, 0.25)
    with pytest.warns(UserWarning, match="was it given in grams"):
        pf.PriorConfig(object_mass_unknown=True, object_mass_range=(0.0, 250.0)).validate()
    o = IdentifyOptions(plant="physics", experiment="stiffness", prior=pf.PriorConfig(stiffness_range=(0.1, 0.3)))
    assert _hands(o.validate(), np.random.default_rng(0))[2].stiffness_range == (0.1, 0.3)
    o = IdentifyOptions(plant="physics", experiment="novel_fingers", hand="NH2",
                        prior=pf.PriorConfig(link_range=(0.04, 0.06))).validate()
    prior = _hands(o, np.random.default_rng(0))[2]
    assert prior.links_unknown and prior.link_range == (0.04, 0.06)


def test_object_weight_result_fields():
    """estimate_errors reports the object's mass against the plant's truth (estimate, error,
    interval, inside) and the shares, only where the prior identifies it and the truth has it."""
    from vlr_drake.identify import estimate_errors

    h = model_o().model()
    g = [0.0, 0.0, 9.81]
    th, a = _truth_grasp(h, np.random.default_rng(0))
    f = pf.SelfIdentificationFilter(h, pf.FilterConfig(particles=2000, gravity_palm=g, gravity_loads="following"),
                                    pf.PriorConfig(object_mass_unknown=True), np.random.default_rng(1))
    f.initialise(th, a, np.eye(3), np.array([0.0, 0.0, 0.11]), tendon_command=h.tendon_travel(th[None])[0] + 0.004)
    est = f.estimate()
    load = f.particles.object_load
    assert load.shape == (2000, h.N) and np.all(load >= 0)
    np.testing.assert_allclose(float(est["object_mass"]), np.mean(load.sum(axis=1)), rtol=1e-12)  # equal weights
    truth = {"theta": th, "a": a, "contacts": est["contacts"], "stiffness": h.stiffness, "link_lengths": h.link_lengths,
             "object_mass": 0.1, "object_load": [0.05, 0.025, 0.025]}
    res = estimate_errors(h, f.prior, est, truth)
    assert res["object_mass_true_kg"] == 0.1
    assert res["object_mass_error_kg"] == pytest.approx(abs(float(est["object_mass"]) - 0.1))
    lo, hi = res["object_mass_interval_kg"]
    assert 0.0 <= lo < 0.1 < hi <= 0.25 and res["object_mass_inside_95"]  # the prior's 0-250 g
    assert len(res["object_load_estimate_kg"]) == h.N
    plain = estimate_errors(h, pf.PriorConfig(), est, truth)
    assert "object_mass_error_kg" not in plain
    # the identified mass needs no truth (a hardware run's report): a skewed cloud's weighted
    # estimate and quantiles against the prior cloud's (review)
    from vlr_drake.identify import hand_parameter_report

    est0 = est
    m = load.sum(axis=1)
    f.particles.log_w = np.where(m < 0.1, 0.0, -np.inf)  # only the hypotheses lighter than 100 g
    est = f.estimate()
    q = hand_parameter_report(h, f.prior, est, est0)["object_mass_identified"]
    assert q["unit"] == "kg" and q["prior_range"] == [0.0, 0.25]
    assert q["estimate"] == pytest.approx(m[m < 0.1].mean(), rel=1e-12)
    assert 0.0 <= q["interval"][0] < q["estimate"] < q["interval"][1] < 0.1 <= q["prior_interval"][1]
    assert q["narrowed_to"] == pytest.approx((q["interval"][1] - q["interval"][0])
                                             / (q["prior_interval"][1] - q["prior_interval"][0]))
    assert 0.3 < q["narrowed_to"] < 0.5  # a cloud cut to 100 of its 250 g
    assert hand_parameter_report(h, pf.PriorConfig(), est, est0)["object_mass_identified"] is None


def test_contact_drift_keeps_the_model_plant_physical():
    """The model plant's contacts roll by contact_drift per action; a roll that would leave a
    link, need a pushing tendon or a command outside the tendon range does not happen, and the
    exploration follows the restated commands. Before, 5 mm of drift took contacts to -13 and
    54 mm, commands out of range and the identification to a TendonLimitError."""
    h = model_o().model()
    for seed in range(3):
        r = run_identification(IdentifyOptions(experiment="known_hand", plant="model", particles=300,
                                               max_iterations=40, seed=seed, contact_drift=5e-3, progress=False))
        truths = r["_truths"]
        a = np.array([t["a"] for t in truths])
        assert np.all(a >= 0) and np.all(a <= h.distal_length + 1e-12)
        assert not np.array_equal(a[0], a[-1])  # the contacts did roll
        commands = r["_trace"].tendon_commands
        assert h.within_tendon_range(commands).all()
        assert np.all(np.isfinite(r["proximal_joint_error_deg"]))


def test_the_model_plant_starts_from_a_seen_tag(monkeypatch):
    """The first measurement anchors the hypotheses: on the model plant a lost tag at the grasp
    is looked for again (it had been used as if seen: the noise-free truth), and a run that
    never sees it says so. A dropout outside [0, 1) is refused."""
    import vlr_drake.identify as identify

    for bad in (1.0, -0.1, float("nan")):
        with pytest.raises(ValueError, match="dropout must be a probability in"):
            IdentifyOptions(plant="model", dropout=bad).validate()
    r = run_identification(IdentifyOptions(plant="model", particles=300, max_iterations=3, seed=0, dropout=0.9,
                                           progress=False))
    assert r["iterations"] == 3 and np.all(np.isfinite(r["_trace"].t0))
    monkeypatch.setattr(identify, "START_LOOKS", 1)
    # the model plant's camera stand-in draws from default_rng(seed + 3), the dropout first
    lost_first = [s for s in range(20) if np.random.default_rng(s + 3).random() < 0.9]
    with pytest.raises(ValueError, match="the tag was lost in all 1 measurements at the grasp"):
        run_identification(IdentifyOptions(plant="model", particles=300, max_iterations=3, seed=lost_first[0],
                                           dropout=0.9, progress=False))


@pytest.mark.parametrize("w", [np.zeros(4), np.array([1.0, np.nan, 1.0, 1.0]), np.array([1.0, -0.5, 1.0, 1.0]),
                               np.ones(3)])
def test_interval95_refuses_weights_that_are_no_distribution(w):
    """All-zero weights had given unweighted quantiles, a NaN or negative one garbage."""
    with pytest.raises(ValueError, match="interval95: the weights"):
        pf.interval95(np.arange(4.0), w)


def test_implied_roughening_drops_hypotheses_without_an_equilibrium(monkeypatch):
    """tendon_reference "implied": a roughened hypothesis whose equilibrium fails has no
    tendon state (stretch 0) to be moved by, so it loses its weight instead of staying in
    the cloud as a slack hand (a review found it kept); the others keep theirs."""
    h, plant, f = _filter_and_plant(6, particles=1000, tendon_reference="implied")
    ps = f.particles.take(np.arange(f.particles.size))
    real = pf.motion.equilibrium

    def failing_half(*args, **kwargs):
        eq = real(*args, **kwargs)
        eq.ok[::2] = False
        return eq

    monkeypatch.setattr(pf.motion, "equilibrium", failing_half)
    f._roughen(ps)
    assert np.all(np.isneginf(ps.log_w[::2])) and np.all(ps.log_w[1::2] == 0.0)
    w = pf.normalise(ps.log_w)
    assert w[::2].sum() == 0.0 and w.sum() == pytest.approx(1.0)
    # none with an equilibrium: none keeps its weight (they had all kept it, with stretch 0)
    ps = f.particles.take(np.arange(f.particles.size))

    def failing_all(*args, **kwargs):
        eq = real(*args, **kwargs)
        eq.ok[:] = False
        return eq

    monkeypatch.setattr(pf.motion, "equilibrium", failing_all)
    f._roughen(ps)
    assert np.all(np.isneginf(ps.log_w))


def test_stable_grasps_conditions_the_prior_and_the_moves():
    """``stable_grasps``: "prior" and "always" draw only stable equilibria (about a third
    of the physical draws are saddles otherwise); "always" also gives a move that ends on a
    saddle no weight, as one that found no equilibrium."""
    prior = pf.PriorConfig()
    unstable = {}
    for mode in pf.STABLE_GRASPS:
        h, f = _initialised(prior, pf.FilterConfig(particles=2000, stable_grasps=mode))
        ps = f.particles
        eq = pf.motion.equilibrium(h, ps.theta, a=ps.a, link_lengths=ps.link_lengths, stiffness=ps.stiffness)
        stable = pf.motion.stable_equilibria(h, ps.theta, eq.multipliers, a=ps.a, ok=eq.ok)
        unstable[mode] = 1.0 - stable.mean()
        # a move's saddles: feasible unless "always"
        res = pf.motion.move(h, ps.theta, np.full(h.N, 0.5e-3), a=ps.a, D2=pf.motion.contact_distances_sq(h, ps.p_O),
                             stretch=ps.stretch)
        res.stable[::3] = False  # as if these had ended on saddles
        pose_ok = np.ones(ps.size, bool)
        plain = f._feasible(pf.motion.MoveResult(**{**res.__dict__, "stable": res.ok.copy()}), pose_ok)
        feasible = f._feasible(res, pose_ok)
        if mode == "always":
            np.testing.assert_array_equal(feasible, plain & res.stable)
            assert plain[::3].any()
        else:
            np.testing.assert_array_equal(feasible, plain)
    assert unstable["off"] > 0.1
    assert unstable["prior"] == 0.0 and unstable["always"] == 0.0
    with pytest.raises(ValueError, match="'stable_grasps' must be one of"):
        pf.FilterConfig(stable_grasps="yes").validate()


def test_the_model_plant_truth_stays_an_equilibrium_and_starts_physical():
    """A review of the model plant: on a hand with more joints than the Model O, a contact
    roll kept the angles but took the tendon state of an equilibrium elsewhere (a zero action
    then moved the joints by 0.01 rad); such rolls do not happen now, and a zero action
    leaves the truth where it is. And an initial grasp past a joint limit, off its links or
    beyond the tendon range is refused by name (it had been accepted, with every action then
    refused or raising)."""
    from vlr_drake import motion
    from vlr_drake.hand import generic_hand

    h = generic_hand(4, 3).model()
    theta, a = _truth_grasp(h, np.random.default_rng(0))
    plant = ModelPlant(h, theta, a, np.eye(3), np.array([0.0, 0.0, 0.11]), np.random.default_rng(1),
                       contact_drift=2e-3)
    rng = np.random.default_rng(2)
    for _ in range(8):
        plant.apply_action(rng.uniform(-1e-4, 1e-4, h.N))
        s = plant.state
        D2 = motion.contact_distances_sq(h, plant.contacts()[None])
        still = motion.move(h, s.theta[None], np.zeros(h.N), a=s.a[None], D2=D2, stretch=s.stretch[None])
        assert still.ok[0] and np.max(np.abs(still.theta[0] - s.theta)) < 1e-9
    m = model_o().model()
    theta, a = _truth_grasp(m, np.random.default_rng(0))
    args = (np.eye(3), np.array([0.0, 0.0, 0.11]), np.random.default_rng(1))
    bad_theta = theta.copy()
    bad_theta[0, 0] = -0.53  # the limit is -0.2
    with pytest.raises(ValueError, match="model plant: the initial (grasp has joints past their limits|grasp is not)"):
        ModelPlant(m, bad_theta, a, *args)
    with pytest.raises(ValueError, match="model plant: the initial contacts .* are not on the last links"):
        ModelPlant(m, theta, np.r_[a[:2], -0.01], *args)
    for kw, name in [({"dropout": float("nan")}, "dropout"), ({"sigma_position": -1e-3}, "sigma_position"),
                     ({"sigma_position": 0.2}, "sigma_position': 0.2 m is longer than 0.01 m, wider than any tag"),
                     ({"sigma_rotation": 1.0}, "sigma_rotation': 1.0 rad is more than 15 deg")]:  # (mm and deg ran)
        with pytest.raises(ValueError, match=f"model plant: '{name}"):
            ModelPlant(m, theta, a, *args, **kw)
    # a pose that is no rotation, a NaN pose, a missing generator or an object's weight
    # without gravity had been accepted (every action then refused, or a later error that
    # named something else)
    R, t, rng = args
    for pose, message in [((2 * np.eye(3), t), "'R_PO' is not a rotation matrix"),
                          ((np.full((3, 3), np.nan), t), "POM pose must be a finite"),
                          ((R, t[:2]), "POM pose must be a finite")]:
        with pytest.raises(ValueError, match=message):
            ModelPlant(m, theta, a, *pose, rng)
    with pytest.raises(TypeError, match="'rng' must be a numpy Generator"):
        ModelPlant(m, theta, a, R, t, None)
    with pytest.raises(ValueError, match="'object_load' needs the 'gravity'"):
        ModelPlant(m, theta, a, *args, object_load=np.full(3, 0.01))
    # a misshapen input is named (numpy's "cannot reshape array of size 3 into shape (3,2)"
    # had named none of them)
    for kw, name in [({"stiffness": np.ones(3)}, "stiffness"), ({"link_lengths": np.ones(2)}, "link_lengths"),
                     ({"gravity": [0.0, -9.81]}, "gravity"),
                     ({"gravity": [0.0, 0.0, -9.81], "object_load": [0.01, 0.01]}, "object_load")]:
        with pytest.raises(ValueError, match=rf"model plant: '{name}' must have shape \("):
            ModelPlant(m, theta, a, *args, **kw)
    with pytest.raises(ValueError, match=r"model plant: 'theta' must have shape \(3, 2\)"):
        ModelPlant(m, theta[:, :1], a, *args)
    with pytest.raises(ValueError, match=r"model plant: 'a' must have shape \(3,\)"):
        ModelPlant(m, theta, a[:2], *args)
    with pytest.raises(ValueError, match=r"model plant: 'dl' must have shape \(3,\)"):
        ModelPlant(m, theta, a, *args).apply_action([1e-4, 0.0])


def test_convergence_waits_for_the_identified_hand_parameters():
    """parameter_interval is the widest unknown spring's or link's 95% interval over its
    estimate (half width, or the full width with convergence_measure "full_width"), NaN for a
    known hand; with parameter_convergence set, a cloud whose joints have converged has not
    while that interval is wider (None: the joints alone, the paper's test)."""

    h = model_o().model()
    M = 2000
    rng = np.random.default_rng(3)
    prior = pf.PriorConfig(stiffness_unknown=[(0, 1)], links_unknown=[1])
    f = pf.SelfIdentificationFilter(h, pf.FilterConfig(particles=M), prior, np.random.default_rng(0))
    k = np.broadcast_to(h.stiffness, (M, h.N, h.K)).copy()
    k[:, 0, 1] = rng.uniform(0.14, 0.16, M)  # +-6.7% around 0.15
    L = np.broadcast_to(h.link_lengths, (M, h.N, h.K - 1)).copy()
    L[:, 1, 0] = rng.uniform(0.049, 0.051, M)  # +-2%
    theta = np.broadcast_to(np.full((h.N, h.K), 0.3), (M, h.N, h.K)).copy()  # the joints: all alike
    f.particles = pf.ParticleSet(theta=theta, a=np.full((M, h.N), 0.02), stiffness=k, link_lengths=L,
                                 stretch=np.zeros((M, h.N)), p_O=np.zeros((M, h.N, 3)), log_w=np.zeros(M))
    lo_k, hi_k = pf.interval95(k[:, 0, 1], np.full(M, 1.0 / M))
    lo_l, hi_l = pf.interval95(L[:, 1, 0], np.full(M, 1.0 / M))
    expected = max(0.5 * (hi_k - lo_k) / k[:, 0, 1].mean(), 0.5 * (hi_l - lo_l) / L[:, 1, 0].mean())
    assert f.parameter_interval() == pytest.approx(expected, rel=1e-9)
    assert 0.05 < f.parameter_interval() < 0.07

    def report(filt):
        return filt._report(True, float(M), 1.0, np.ones(M, bool), np.ones(M, bool), False, 0.0)

    assert f.config.parameter_convergence == 0.05  # the default
    rep = report(f)
    assert rep.mean_interval_deg == 0.0 and rep.parameter_interval == pytest.approx(expected) and not rep.converged
    f.config.parameter_convergence = None
    assert report(f).converged
    f.config.parameter_convergence = 0.1
    assert report(f).converged
    f.config.convergence_measure = "full_width"
    assert f.parameter_interval() == pytest.approx(2 * expected, rel=1e-9) and not report(f).converged
    known = pf.SelfIdentificationFilter(h, pf.FilterConfig(particles=M), pf.PriorConfig(), np.random.default_rng(0))
    known.particles = pf.ParticleSet(theta=theta, a=np.full((M, h.N), 0.02), stiffness=h.stiffness[None].copy(),
                                     link_lengths=h.link_lengths[None].copy(), stretch=np.zeros((M, h.N)),
                                     p_O=np.zeros((M, h.N, 3)), log_w=np.zeros(M))
    assert np.isnan(known.parameter_interval()) and report(known).converged
    with pytest.raises(ValueError, match="parameter_convergence"):
        pf.FilterConfig(parameter_convergence=-0.1).validate()


def test_systematic_resampling_never_picks_a_particle_without_weight():
    """A position that rounds to 1 (u at the generator's largest value), or one past a
    cumulative sum a little short of 1, picked the last particle whatever its weight (a
    review)."""

    class Top:  # the largest value Generator.random() returns
        def random(self):
            return 1.0 - 2.0**-53

    np.testing.assert_array_equal(pf.systematic_resample(np.array([0.25, 0.25, 0.5, 0.0]), Top()), [0, 2, 2, 2])
    np.testing.assert_array_equal(pf.systematic_resample(np.array([0.5, 0.5 - 1e-7, 0.0]), Top()), [0, 1, 1])


def test_tempering_keeps_the_measurement_when_most_hypotheses_fail():
    """With more hypotheses infeasible than the ESS target leaves room for, no beta reaches
    the target over all M; the filter tempers relative to the live cloud instead of taking
    the bisection's floor (1e-6, which discarded the measurement: a review's case, 424 of 600
    infeasible with the ideal tendon and a 0.55 mm pull of every tendon)."""
    h, plant, f = _filter_and_plant(3, particles=600, tendon="ideal", tendon_reference="implied")
    R, t, _ = plant.measure()
    rep = f.step(np.full(3, 0.55e-3), R, t)
    assert not rep.reinitialised and rep.infeasible > 0.7 * 600  # the target (0.3 M) is out of the live cloud's reach
    assert rep.beta > 1e-3  # (1e-6 before)
    assert rep.ess == pytest.approx(0.3 * (600 - rep.infeasible), rel=0.05)  # the live cloud's target


def test_a_cloud_whose_weighted_hypotheses_all_fail_is_reinitialised(monkeypatch):
    """Particles already weighing nothing (carried at -inf since the last resampling) do not
    keep a cloud alive: where every particle that carries weight becomes infeasible the
    filter re-initialises (a review found it resampled uniformly over the failures)."""
    h, plant, f = _filter_and_plant(3, particles=400)
    dead = np.arange(400) % 2 == 1
    f.particles.log_w[dead] = -np.inf
    feasible = f._feasible
    monkeypatch.setattr(f, "_feasible", lambda *args, **kwargs: feasible(*args, **kwargs) & dead)
    dl = np.array([0.2e-3, -0.1e-3, 0.1e-3])
    assert plant.apply_action(dl)
    R, t, _ = plant.measure()
    rep = f.step(dl, R, t, tendon_command=plant.state.tendon_command)
    assert rep.reinitialised and f.reinitialisations == 1
    assert np.isfinite(f.particles.log_w).all()


def test_prior_angles_can_be_drawn_where_each_hypothesis_own_springs_and_links_settle():
    """PriorConfig.angle_centers "settled": the nominal grasp settled by the model under the
    tendon command with the unknowns at their middles is the new centre, and each
    hypothesis' angles are drawn around it moved by the settled angles' difference between
    its own spring and link and the middles (SettledAngles, interpolated in log k and in L).
    The same random draws as "nominal", so the difference is that shift exactly."""
    from vlr_drake.grasps import commanded_equilibrium

    h = model_o().model()
    theta0, a0 = _truth_grasp(h, np.random.default_rng(0))
    l = h.tendon_travel(theta0[None])[0] + 0.004  # a squeeze
    prior = pf.PriorConfig(stiffness_unknown=[(0, 1)], links_unknown=[2], angle_centers="settled")
    f = pf.SelfIdentificationFilter(h, pf.FilterConfig(particles=500), prior, np.random.default_rng(5))
    with pytest.raises(ValueError, match="angle_centers 'settled' needs the absolute tendon command"):
        f.settled_angles(theta0, a0)
    f.tendon_command = l
    center, tables = f.settled_angles(theta0, a0)
    k_mid, L_mid = h.stiffness.copy(), h.link_lengths.copy()
    k_mid[0, 1], L_mid[2, 0] = prior.stiffness_middle(), 0.5 * sum(prior.link_range)
    expected, ok = commanded_equilibrium(h, theta0, a0, l, L_mid, k_mid[None])
    assert ok and np.abs(center - theta0).max() > np.deg2rad(1.0)  # the squeeze moves the grasp
    np.testing.assert_allclose(center, expected, atol=1e-12)
    assert [(t.parameter, t.finger, t.joint) for t in tables] == [("stiffness", 0, 1), ("link", 2, 0)]
    k_tab, L_tab = tables
    np.testing.assert_allclose(k_tab.at(np.array([prior.stiffness_middle()]))[0], center, atol=1e-8)
    np.testing.assert_allclose(L_tab.at(np.array([0.5 * sum(prior.link_range)]))[0], center, atol=1e-8)
    assert np.all(np.diff(k_tab.theta[:, 0, 1]) < 0)  # a stiffer spring gives way less to the squeeze
    for v, row in zip(k_tab.values, k_tab.theta, strict=True):  # each node: the model's own settle
        k = k_mid.copy()
        k[0, 1] = v
        np.testing.assert_allclose(row, commanded_equilibrium(h, theta0, a0, l, L_mid, k[None])[0], atol=1e-12)
    # each link row holds the object the nominal grasp holds: its contacts at the same mutual
    # distances (a review found each row recomputing them with its own link, a smaller or
    # larger object for each link, which barely moved the angles)
    D2 = motion.contact_distances_sq(h, kinematics.contacts(h, theta0[None], a0[None], L_mid[None]))
    assert L_tab.values.size >= 3
    for v, row in zip(L_tab.values, L_tab.theta, strict=True):
        L = L_mid.copy()
        L[2, 0] = v
        np.testing.assert_allclose(motion.contact_distances_sq(h, kinematics.contacts(h, row[None], a0[None], L[None])),
                                   D2, rtol=1e-7)
    assert np.abs(L_tab.theta[0] - center).max() > np.deg2rad(5.0)  # a short link must close further on it
    mid = np.sqrt(k_tab.values[1] * k_tab.values[2])  # between two nodes in log k; held beyond the ends
    np.testing.assert_allclose(k_tab.at(np.array([mid, 1e-3, 10.0])),
                               [0.5 * (k_tab.theta[1] + k_tab.theta[2]), k_tab.theta[0], k_tab.theta[-1]])
    # the draws: the nominal filter's around theta0, the settled one's around each own settle
    draws = {}
    for mode, c, tabs in (("nominal", theta0, []), ("settled", center, tables)):
        g = pf.SelfIdentificationFilter(h, pf.FilterConfig(particles=500),
                                        dataclasses.replace(prior, angle_centers=mode), np.random.default_rng(5))
        g.settled = tabs
        draws[mode] = g._draw_grasps(2000, c, a0, 1.0, (None, None, None))
    (th_n, _, k_n, L_n, *_), (th_s, _, k_s, L_s, *_) = draws["nominal"], draws["settled"]
    np.testing.assert_array_equal(k_n, k_s)
    np.testing.assert_array_equal(L_n, L_s)
    shift = (center - theta0) + (k_tab.at(k_s[:, 0, 1]) - center) + (L_tab.at(L_s[:, 2, 0]) - center)
    np.testing.assert_allclose(th_s - th_n, shift, atol=1e-12)
    # a re-initialisation's centre: no shift for a draw at the centre's own spring and link
    k_c, L_c = k_mid.copy(), L_mid.copy()
    k_c[0, 1], L_c[2, 0] = 0.2, 0.06
    np.testing.assert_allclose(g._settled_shift(k_c[None], L_c[None], k_c, L_c), 0.0, atol=1e-12)
    # initialise settles once and keeps the tables and the centre for the re-initialisations
    f = pf.SelfIdentificationFilter(h, pf.FilterConfig(particles=500), prior, np.random.default_rng(5))
    f.initialise(theta0, a0, np.eye(3), np.array([0.0, 0.0, 0.1]), tendon_command=l)
    np.testing.assert_allclose(f._theta_center, center, atol=1e-12)
    assert len(f.settled) == 2
    # a first initialise given a centre draws around that centre's own settle (the shifts,
    # measured from the centre, had been added to the middle's angles: a review found no
    # physical draw at a spring 2.5 times the middle's); the re-initialisations keep the middle's
    k_c = h.stiffness.copy()
    k_c[0, 1] = 0.35
    f = pf.SelfIdentificationFilter(h, pf.FilterConfig(particles=500), prior, np.random.default_rng(5))
    ps = f.initialise(theta0, a0, np.eye(3), np.array([0.0, 0.0, 0.1]), tendon_command=l, stiffness_center=k_c,
                      scale=0.3)
    np.testing.assert_allclose(f._theta_center, center, atol=1e-12)
    near = np.abs(np.log(ps.stiffness[:, 0, 1] / 0.35)) < 0.05
    want = k_tab.at(np.array([0.35]))[0, 0, 1] + (L_tab.at(ps.link_lengths[near, 2, 0]) - center)[:, 0, 1]
    assert near.sum() > 20 and np.abs(ps.theta[near, 0, 1] - want).max() < prior.distal_half_width * 0.3 + 0.02
    with pytest.raises(ValueError, match="'angle_centers' must be one of"):
        pf.PriorConfig(angle_centers="placed").validate()


def test_settled_prior_settles_with_the_weighed_object_once_and_says_what_it_leaves_out(monkeypatch):
    """The settled prior (review): a weighed object's weight moves the settled grasp as a
    move carries it (its middle mass at the balanced shares, following the angles); a spring
    range the command cannot hold everywhere leaves values out with a warning that names
    them; the ideal tendon, which has no stretch to settle through, is refused; and a
    re-initialisation keeps the first settle's tables instead of settling again."""
    from vlr_drake.grasps import commanded_equilibrium

    h = model_o().model()
    theta0, a0 = _truth_grasp(h, np.random.default_rng(0))
    l = h.tendon_travel(theta0[None])[0] + 0.004
    g = np.asarray(PhysicsConfig().gravity_in_palm())  # the physics plant's, in the palm frame
    k_mid = h.stiffness.copy()
    centers = {}
    for lo, hi in ((0.027, 0.029), (0.24, 0.26)):
        prior = pf.PriorConfig(stiffness_unknown=[(0, 1)], angle_centers="settled", object_mass_unknown=True,
                               object_mass_range=(lo, hi))
        f = pf.SelfIdentificationFilter(h, pf.FilterConfig(particles=500, gravity_palm=g.tolist(),
                                                           gravity_loads="following"), prior, np.random.default_rng(5))
        f.tendon_command = l
        centers[lo], _ = f.settled_angles(theta0, a0)
        k_mid[0, 1] = prior.stiffness_middle()
        expected, ok = commanded_equilibrium(h, theta0, a0, l, h.link_lengths, k_mid[None], gravity=g,
                                             object_load=0.5 * (lo + hi) * pf.balanced_shares(h))
        assert ok
        np.testing.assert_allclose(centers[lo], expected, atol=1e-12)
    assert np.abs(centers[0.24] - centers[0.027]).max() > np.deg2rad(0.3)  # a heavier object settles elsewhere

    prior = pf.PriorConfig(stiffness_unknown=[(0, 1)], angle_centers="settled", stiffness_range=(0.001, 10.0))
    f = pf.SelfIdentificationFilter(h, pf.FilterConfig(particles=500), prior, np.random.default_rng(5))
    f.tendon_command = l
    with pytest.warns(UserWarning, match=r"no equilibrium of the grasp with the stiffness of finger 0 at \["):
        _, (tab,) = f.settled_angles(theta0, a0)
    assert 2 <= tab.values.size < pf.SETTLED_VALUES
    with pytest.raises(ValueError, match="angle_centers 'settled' needs filter tendon 'elastic'"):
        pf.SelfIdentificationFilter(h, pf.FilterConfig(particles=500, tendon="ideal", tendon_reference="implied"),
                                    prior, np.random.default_rng(5))

    prior = pf.PriorConfig(stiffness_unknown=[(0, 1)], angle_centers="settled")
    f = pf.SelfIdentificationFilter(h, pf.FilterConfig(particles=2000), prior, np.random.default_rng(5))
    R, t = np.eye(3), np.array([0.0, 0.0, 0.1])
    f.initialise(theta0, a0, R, t, tendon_command=l)
    tables, center = f.settled, f._theta_center.copy()

    def settle_again(*args):
        raise AssertionError("a re-initialisation settled the grasp again")

    monkeypatch.setattr(f, "settled_angles", settle_again)
    for _ in range(2):  # around the estimate, then (recent) around the kept centre
        f._reinitialise(R, t)
    assert f.reinitialisations == 2 and f.settled is tables
    np.testing.assert_array_equal(f._theta_center, center)


def test_a_cloud_collapsed_onto_a_few_hypotheses_is_lost_not_converged(monkeypatch):
    """Where the move leaves only a few live hypotheses (here one of 2,000), the cloud is
    drawn again and reported, not resampled into copies of the survivor: roughening found
    no spread among copies, and the filter had reported convergence with a 2e-8 deg
    interval and every truth outside (a review). A live cloud above the floor is weighed."""
    move = pf.motion.move
    for keep_count, lost in ((1, True), (5, True), (200, False)):
        h, plant, f = _filter_and_plant(6, particles=2000)
        dl = np.array([0.3e-3, -0.2e-3, 0.3e-3])
        assert plant.apply_action(dl)
        f.step(dl, *plant.measure()[:2], tendon_command=plant.state.tendon_command)
        keep = np.random.default_rng(0).choice(2000, keep_count, replace=False)

        def few(hand, theta, dl, keep=keep, **kwargs):
            res = move(hand, theta, dl, **kwargs)
            if len(res.ok) != 2000:  # (a single grasp's solve)
                return res
            failed = np.ones(len(res.ok), bool)
            failed[keep] = False
            res.ok[failed] = False
            res.theta[failed] = theta[failed]
            return res

        monkeypatch.setattr(pf.motion, "move", few)
        assert plant.apply_action(dl)
        rep = f.step(dl, *plant.measure()[:2], tendon_command=plant.state.tendon_command)
        monkeypatch.setattr(pf.motion, "move", move)
        assert rep.reinitialised is lost and not rep.converged, (keep_count, rep)
        assert f._live_floor() == 20.0  # 1% of the cloud, above the 9 unknowns + 1
        if lost:
            assert f.reinitialisations == 1 and rep.mean_interval_deg > 5.0
            est = f.estimates[-1]
            assert np.all((est["theta_lo"] <= plant.state.theta) & (plant.state.theta <= est["theta_hi"]))


def test_a_move_that_is_not_finite_is_a_failed_one(monkeypatch):
    """A solver that hands back NaN angles or stretch (marked solved or not) fails those
    hypotheses at their start; the step goes on. It had ended the run in the contacts'
    check ("'theta' contains NaN"; a review's injected fault)."""
    h, plant, f = _filter_and_plant(6, particles=1000)
    move = pf.motion.move
    rows = np.arange(1000) % 4 == 0

    def nan_rows(hand, theta, dl, **kwargs):
        res = move(hand, theta, dl, **kwargs)
        if len(res.ok) != 1000:  # (a single grasp's solve)
            return res
        res.theta[rows] = np.nan
        res.stretch[rows[:500].repeat(2)] = np.nan  # some marked solved with a NaN stretch
        res.ok[rows & (np.arange(1000) % 8 == 0)] = False
        return res

    monkeypatch.setattr(pf.motion, "move", nan_rows)
    dl = np.array([0.3e-3, -0.2e-3, 0.3e-3])
    theta_before = f.particles.theta.copy()
    assert plant.apply_action(dl)
    rep = f.step(dl, *plant.measure()[:2], tendon_command=plant.state.tendon_command)
    bad = rows | rows[:500].repeat(2)
    assert rep.solve_failures >= bad.sum() and not rep.reinitialised
    assert np.isfinite(f.particles.theta).all() and np.isfinite(f.particles.stretch).all()
    assert np.isfinite(f.particles.log_w).any() and not np.isnan(f.particles.log_w).any()
    assert rep.infeasible >= bad.sum()
    # lost: the failures are held at their start, nothing is weighed
    assert plant.apply_action(dl)
    before = f.particles.theta.copy()
    rep = f.step(dl, None, None, valid=False, tendon_command=plant.state.tendon_command)
    np.testing.assert_array_equal(f.particles.theta[rows], before[rows])
    assert np.isfinite(f.particles.stretch).all() and theta_before.shape == before.shape


def test_a_lost_step_reports_the_carried_weights_ess(monkeypatch):
    """A lost tag measures nothing, so the weights carried on are the last measured step's,
    less the hypotheses the move left unphysical: their ESS, not the cloud's size (which it
    had reported)."""
    h, plant, f = _filter_and_plant(6, particles=1000, resample_fraction=0.0)  # never resampled
    dl = np.array([0.3e-3, -0.2e-3, 0.3e-3])
    assert plant.apply_action(dl)
    measured = f.step(dl, *plant.measure()[:2], tendon_command=plant.state.tendon_command)
    assert measured.ess < 900
    assert plant.apply_action(dl)
    lost = f.step(dl, None, None, valid=False, tendon_command=plant.state.tendon_command)
    assert lost.ess == pytest.approx(pf.effective_sample_size(f.particles.log_w))
    assert 0.9 * measured.ess < lost.ess <= measured.ess


def test_bad_step_arguments_are_refused_before_the_iteration_counts():
    """A NaN or misshapen tendon command was refused after the iteration had been counted
    (the history's numbers then skipped); a NaN or text 'valid' was read as true."""
    h, plant, f = _filter_and_plant(6, particles=500)
    dl = np.array([0.3e-3, -0.2e-3, 0.3e-3])
    R, t, _ = plant.measure()
    for kwargs, message in [({"tendon_command": np.full(3, np.nan)}, "'tendon_command' contains NaN"),
                            ({"tendon_command": np.zeros(2)}, "'tendon_command' must have shape"),
                            ({"valid": np.nan}, "filter: 'valid' must be 0 or 1"),
                            ({"valid": "no"}, "filter: 'valid' must be 0 or 1")]:
        with pytest.raises((ValueError, TypeError), match=message):
            f.step(dl, R, t, **kwargs)
        assert f.iteration == 0 and not f.history
    # a position without its rotation had been taken as no measurement at all (measured False)
    with pytest.raises(ValueError, match="a measured position 't_meas' without its rotation 'R_meas'"):
        f.step(dl, None, t)
    assert f.iteration == 0 and not f.history
    assert f.step(dl, R, t, valid=1, tendon_command=plant.state.tendon_command).iteration == 1


def test_initialise_names_its_centres_and_scale():
    """A misshapen spring centre had raised an IndexError, a NaN centre or scale an error about
    the draws, a scale past 1 blamed the prior, a negative one was taken, and a link centre in
    mm was folded into the link range silently; so were a spring centre in N mm/rad (clipped
    to the range's top), a negative one and a negative mass (a review)."""
    h, plant, f = _filter_and_plant(6, particles=300)
    R, t, _ = plant.measure()
    th, a = plant.state.theta, plant.state.a
    for kwargs, message in [({"scale": -0.5}, "'scale' must be in \\(0, 1\\]"), ({"scale": 3.0}, "'scale'"),
                            ({"scale": np.nan}, "'scale'"), ({"scale": "1"}, "'scale'"),
                            ({"stiffness_center": np.ones(3)}, "'stiffness_center' must have shape \\(3, 2\\)"),
                            ({"link_center": np.full((3, 1), np.nan)}, "'link_center' contains NaN"),
                            ({"link_center": np.full((3, 1), 50.0)}, "'link_center'.*millimetres"),
                            ({"stiffness_center": 1e3 * h.stiffness}, "'stiffness_center'.*N mm/rad"),
                            ({"stiffness_center": -h.stiffness}, "'stiffness_center' must be positive"),
                            ({"mass_center": np.nan}, "'mass_center' must be a finite number"),
                            ({"mass_center": -0.05}, "'mass_center' must be a finite number >= 0"),
                            ({"com_center": np.zeros(2)}, "'com_center' must have shape \\(3,\\)")]:
        with pytest.raises(ValueError, match=message):
            f.initialise(th, a, R, t, tendon_command=plant.state.tendon_command, **kwargs)
    f.initialise(th, a, R, t, tendon_command=plant.state.tendon_command, scale=0.5,
                 stiffness_center=h.stiffness, link_center=h.link_lengths)
    with pytest.warns(UserWarning, match="'mass_center': 28 kg .*grams"):
        f.initialise(th, a, R, t, tendon_command=plant.state.tendon_command, mass_center=28.0)


def test_nearest_hypotheses_takes_a_count():
    """A negative count had sliced the sorted hypotheses from the far end: -1 gave all but the
    farthest (299 of 300; control.filter_model_fn(fallbacks=-1) then tried every one), 2.0 a
    TypeError from the slice."""
    h, plant, f = _filter_and_plant(6, particles=300)
    for bad in (-1, 2.0, True, None):
        with pytest.raises(ValueError, match="nearest_hypotheses' 'count' must be an integer >= 0"):
            f.nearest_hypotheses(bad)
    assert len(f.nearest_hypotheses(np.int64(3))) == 3 and f.nearest_hypotheses(0) == []


def test_a_failed_re_initialisation_around_the_estimate_draws_from_the_whole_prior(monkeypatch):
    """Where no physical grasp is found around the estimate (the prior's draws all fail),
    the re-initialisation draws from the whole prior around the nominal grasp, as a second
    loss would, rather than end the run with an error blaming the prior."""
    h, plant, f = _filter_and_plant(5, particles=1000)
    nominal = f._theta_center.copy()
    initialise, centres = pf.SelfIdentificationFilter.initialise, []

    def around_estimate_fails(self, theta_center, *args, **kwargs):
        centres.append(np.array(theta_center))
        if not np.array_equal(theta_center, nominal):
            raise pf.PriorError("prior: only 0 of 1000 draws are physical grasps")
        return initialise(self, theta_center, *args, **kwargs)

    dl = np.array([1.0e-3, 0.5e-3, -0.8e-3])
    for _ in range(2):
        assert plant.apply_action(dl)
        f.step(dl, *plant.measure()[:2])
    monkeypatch.setattr(pf.SelfIdentificationFilter, "initialise", around_estimate_fails)
    from vlr_drake.observation import rotvec_to_matrix

    assert plant.apply_action(dl)
    R, t, _ = plant.measure()
    rep = f.step(dl, rotvec_to_matrix(np.array([0.0, np.deg2rad(30), 0.0]))[0] @ R, t + np.array([0.02, 0.0, 0.0]))
    assert rep.reinitialised and f.reinitialisations == 1
    assert len(centres) == 2 and not np.array_equal(centres[0], nominal)
    np.testing.assert_array_equal(centres[1], nominal)
    assert np.isfinite(f.particles.theta).all()


def test_max_substeps_must_be_a_whole_count():
    for bad in (2.5, np.nan, "4", -1, True):
        with pytest.raises(ValueError, match="'max_substeps' must be an integer >= 0"):
            pf.FilterConfig(max_substeps=bad).validate()


def test_a_short_distal_link_has_a_truth_grasp_and_the_thumb_is_found_by_its_name():
    """The model plant's truth drew its contacts 18-36 mm along the distal links whatever
    their length: a hand with 18 mm links had no truth grasp and was told to check its
    springs. The stiffness experiment took finger 0 for the thumb whatever its name (a
    review): with the Model O's fingers reordered, the thumb's spring is still the thumb's."""
    from vlr_drake.identify import _hands

    spec = model_o()
    for f in spec.fingers:
        f.distal_length = 0.018
    th, a = _truth_grasp(spec.model(), np.random.default_rng(0))
    assert np.all((a > 0.0) & (a < 0.018))
    spec = model_o()
    spec.fingers = [spec.fingers[1], spec.fingers[2], spec.fingers[0]]
    opts = IdentifyOptions(experiment="stiffness", plant="model", hand_spec=spec).validate()
    true_spec, _, prior = _hands(opts, np.random.default_rng(0))
    assert [tuple(e) for e in prior.stiffness_unknown] == [(2, 1)] and spec.fingers[2].name == "thumb"
    assert true_spec.fingers[2].stiffness[1] != model_o().fingers[0].stiffness[1]  # the thumb's spring drawn


def test_truths_the_prior_leaves_out_are_said():
    """A lab's own hand or object can hold a truth the prior's range leaves out (a 350 g
    object against 0-250 g, an 85 mm link against 30-75 mm): said, as the filter cannot
    find it (it had only been 'weakly identified'; a review)."""
    from vlr_drake.hand import hand_by_name
    from vlr_drake.identify import truths_outside_prior

    spec = hand_by_name("NH1")
    prior = pf.PriorConfig(links_unknown=[0], stiffness_unknown=[(1, 1)], object_mass_unknown=True)
    assert truths_outside_prior(spec, prior, 0.068) == []
    spec.fingers[0].link_lengths = [0.085]
    spec.fingers[1].stiffness = [spec.fingers[1].stiffness[0], 0.9]
    said = truths_outside_prior(spec, prior, 0.35)
    assert len(said) == 3 and "85 mm, lies outside the prior's link_range [30, 75] mm" in said[0]
    assert "0.9 N m/rad, lies outside" in said[1] and "350 g, lies outside the prior's object_mass_range" in said[2]
