"""
Validation statistics: analytic properties, their null distributions, and the report's cases.

* Theil's U and the correlation functions on sequences with known answers.
* Ljung-Box on white Gaussian noise: Q has the χ²(L) mean and the 5 % test rejects about 5 %
  of 400 sequences (binomial band); an AR(1) sequence is rejected.
* On the report's single-blade case (σ = 0.2) the fitted residuals are white with RMS ≈ σ;
  the constant-coefficient multiblade model on the periodic truth leaves coloured residuals
  correlated with the input (the modelling error docs/models.md §2.2 describes).
* Held-out prediction (wake, regressing run predicted with the progressing-run estimate):
  RMS ≈ σ at the estimate, significantly larger at a wrong A.
"""

import math

import numpy as np
import pytest
from rotor_id.estimation.output_error import fit_output_error
from rotor_id.estimation.validation import (autocorrelation, channel_statistics,
                                            cross_correlation, ljung_box, predict,
                                            score_statistic, theil_inequality, validate)
from rotor_id.report import cases as C
from scipy.stats import binom


def test_theil_inequality_known_values():
    y = np.sin(np.linspace(0, 10, 200))
    assert theil_inequality(y, y) == 0.0
    assert theil_inequality(y, np.zeros_like(y)) == pytest.approx(1.0)
    assert theil_inequality(y, -y) == pytest.approx(1.0)
    assert theil_inequality(y, 0.5 * y) == pytest.approx(0.5 / 1.5)


def test_correlation_functions_known_values():
    rng = np.random.default_rng(3)
    u = rng.standard_normal(2000)
    lagged = np.concatenate([np.zeros(3), u[:-3]])          # ε_t = u_{t−3}
    rho = cross_correlation(lagged, u, 5)
    assert np.argmax(np.abs(rho)) == 5 + 3 and rho[8] == pytest.approx(1.0, abs=0.01)
    assert np.max(np.abs(np.delete(rho, 8))) < 4 / math.sqrt(2000)
    x = np.cos(0.3 * np.arange(4000))
    np.testing.assert_allclose(autocorrelation(x, 3), np.cos(0.3 * np.arange(1, 4)), atol=3e-3)


def test_ljung_box_null_distribution():
    """White noise, N = 121 (the report's record), L = 20: E[Q] ≈ 20, 5 % rejections."""
    rng = np.random.default_rng(11)
    n, lag, draws = 121, 20, 400
    qs, rejected = [], 0
    for _ in range(draws):
        q, dof, p = ljung_box(autocorrelation(rng.standard_normal(n), lag), n)
        assert dof == lag
        qs.append(q)
        rejected += p < 0.05
    # mean of 400 χ²(20) draws: sd = √(40/400) = 0.32; allow 4 sd (Ljung-Box is ~χ² at N=121)
    assert abs(np.mean(qs) - lag) < 4 * math.sqrt(2 * lag / draws), np.mean(qs)
    low, high = binom.ppf([0.0005, 0.9995], draws, 0.05)
    assert low <= rejected <= high, rejected


def test_ljung_box_rejects_coloured_residuals():
    rng = np.random.default_rng(5)
    e = rng.standard_normal(500)
    ar = np.zeros(500)
    for t in range(1, 500):
        ar[t] = 0.5 * ar[t - 1] + e[t]
    stats = channel_statistics(ar, np.zeros(500))
    assert stats.ljung_box_p < 1e-6 and not stats.white()
    assert stats.autocorrelation[0] == pytest.approx(0.5, abs=0.1)
    assert stats.outside_band > 0.1


def test_bad_input_is_a_clear_error():
    with pytest.raises(ValueError, match='at least 8 samples'):
        channel_statistics(np.zeros(4), np.zeros(4))
    with pytest.raises(ValueError, match='equal length'):
        channel_statistics(np.zeros(40), np.zeros(41))
    with pytest.raises(ValueError, match='max_lag'):
        channel_statistics(np.zeros(40), np.zeros(40), max_lag=30)


def _fit(scenario_name, seed, noise_std=None, initial_state='truth', unknowns=None, start=None):
    scenario = C.SCENARIOS[scenario_name]
    t = C.sample_times(scenario.t0, scenario.t0 + 12.0)
    y = C.noisy_outputs(scenario, t, seed, noise_std)
    exp = C.make_experiment(scenario, y=y, initial_state=initial_state)
    unknowns = unknowns or list(scenario.truth)
    est = fit_output_error([exp], unknowns, guess=start or dict(scenario.truth),
                           noise_std=noise_std or scenario.noise_std)
    return exp, est


def test_single_blade_fit_residuals_are_white():
    exp, est = _fit('single_blade', seed=21)
    [run] = validate(est, [exp])
    [chan] = run.channels
    n = chan.n_samples
    # RMS of N residuals of a 2-parameter fit: √((N−2)/N)·σ, sampling sd σ/√(2N)
    assert abs(chan.rms - 0.2 * math.sqrt((n - 2) / n)) < 3 * 0.2 / math.sqrt(2 * n)
    assert chan.white() and chan.uncorrelated_with_input()
    assert chan.input_names == ['theta_I', 'theta_II']
    assert chan.theil < 0.15
    np.testing.assert_allclose(run.residuals, est.residuals[0])


def test_constant_coefficient_model_leaves_coloured_residuals():
    """Periodic truth, constant model, small noise (σ = .02): the modelling error shows."""
    exp, est = _fit('multiblade_constant', seed=4, noise_std=0.02, initial_state='zero')
    runs = validate(est, [exp])
    chans = runs[0].channels
    assert [c.channel for c in chans] == ['beta_0', 'beta_I', 'beta_II']
    assert all(c.rms > 2 * 0.02 for c in chans)
    assert any(c.ljung_box_p < 1e-6 for c in chans)
    assert any(not c.uncorrelated_with_input() for c in chans)


def test_held_out_prediction_of_the_other_stirring_direction():
    """Estimate from the progressing wake run, predict the regressing run (new noise)."""
    exp, est = _fit('wake_progressing', seed=8)
    regressing = C.SCENARIOS['wake_regressing']
    t = C.sample_times(70.0, 82.0)
    new = C.make_experiment(regressing, y=C.noisy_outputs(regressing, t, 9),
                            initial_state='estimate', name='regressing (held out)')
    runs = validate(est, [exp], held_out=[new])
    assert [r.held_out for r in runs] == [False, True]
    held = runs[1]
    # the initial state fitted with parameters held is close to the true equilibrium
    truth_x0 = C.truth_initial_state(regressing)
    assert np.max(np.abs(held.initial_state - truth_x0)) < 0.3
    n = held.channels[0].n_samples
    for chan in held.channels:
        # 6 initial states fitted per 2 channels: residual RMS ≈ σ·√(1 − 3/N), sd σ/√(2N)
        assert abs(chan.rms - 0.1) < 4 * 0.1 / math.sqrt(2 * n) + 0.01, chan.rms
    # the same prediction with A doubled is clearly worse
    model = exp.model
    wrong = model.parameter_vector(dict(est.model_parameters, A=1.0))
    _, pred_wrong = predict(new, wrong)
    rms_wrong = np.sqrt(np.mean((new.y - pred_wrong) ** 2, axis=0))
    # noise-free, A = 1 moves the prediction by 0.08 rms (the wake data are weakly informative,
    # M⁻¹(A) = .17); the excess mean square must exceed 4 sampling sd of σ² (σ²·√(2/N))
    excess = rms_wrong ** 2 - np.array([c.rms for c in held.channels]) ** 2
    assert np.all(excess > 4 * 0.1 ** 2 * math.sqrt(2 / n)), excess


def test_predict_needs_data_or_a_state():
    scenario = C.SCENARIOS['wake_progressing']
    exp = C.make_experiment(scenario, initial_state='estimate')
    p = exp.model.parameter_vector(scenario.truth)
    with pytest.raises(ValueError, match='no measurements'):
        predict(exp, p)
    x0 = C.truth_initial_state(scenario)
    x_start, y = predict(exp, p, x0=x0)
    np.testing.assert_allclose(x_start, x0)
    np.testing.assert_allclose(y, C.truth_outputs(scenario, exp.t), atol=1e-9)


def test_input_correlation_limit_null_rate():
    """White residuals independent of the stirring input fail at most ≈ 5 % of the time."""
    scenario = C.SCENARIOS['single_blade']
    t = C.sample_times(12.0, 24.0)
    u = scenario.stirring()(t)
    rng = np.random.default_rng(17)
    draws = 300
    failed = 0
    for _ in range(draws):
        e = rng.standard_normal(t.size)
        stats = channel_statistics(e, np.zeros_like(e), inputs=u,
                                   input_names=['theta_0', 'theta_I', 'theta_II'])
        assert stats.input_names == ['theta_I', 'theta_II']      # θ0 is constant
        failed += not stats.uncorrelated_with_input()
    assert failed <= binom.ppf(0.999, draws, 0.05), failed
    # and a residual that is the input (shifted) is caught
    lagged = np.roll(u[:, 2], 4) + 0.1 * rng.standard_normal(t.size)
    caught = channel_statistics(lagged, np.zeros_like(lagged), inputs=u)
    assert not caught.uncorrelated_with_input()


def test_student_t_tail_and_its_inverse_are_scipy_numbers():
    """The finite series of Student's t tail, and its inverse, against scipy (integer ν)."""
    from rotor_id.estimation.validation import student_t_isf, student_t_sf
    from scipy.stats import t as student
    for dof in range(1, 31):
        for x in (-5.0, -1.3, 0.0, 0.2, 1.0, 2.5, 7.0, 40.0):
            # the series' rounding is absolute (1 − P(|T| < t)): ~1e-16 of the tail's scale
            assert abs(student_t_sf(x, dof) - student.sf(x, dof)) <= 1e-15
        for p in (1e-4, 1e-3, 0.00625, 0.05, 0.3, 0.5, 0.7, 0.95):
            # scipy's inverse is a numerical search: 1.11's is good to a few 1e-9 (ν = 4 at
            # 0.05: 2.3e-9; ν = 1 at 0.00625: 6e-10 off cot(πp)); the closed forms below hold
            # ours to 1e-12
            assert student_t_isf(p, dof) == pytest.approx(student.isf(p, dof), rel=1e-8,
                                                          abs=1e-12)
    for p in (1e-4, 0.00625, 0.05, 0.3, 0.7):
        a = 1.0 - 2.0 * p
        assert student_t_isf(p, 1) == pytest.approx(1.0 / math.tan(math.pi * p), rel=1e-12)
        assert student_t_isf(p, 2) == pytest.approx(a * math.sqrt(2.0 / (1.0 - a * a)),
                                                    rel=1e-12)
    with pytest.raises(ValueError, match='positive integer'):
        student_t_sf(1.0, 2.5)


def test_noncentral_tail_and_its_inverse_are_scipy_numbers():
    """The noncentral χ² tail (above 1e-10) and the λ of a given power: scipy's numbers."""
    from rotor_id.estimation.validation import noncentral_chi2_sf, noncentrality_for_power
    from scipy.special import chndtr, chndtrinc
    from scipy.stats import ncx2
    for q in (0.5, 3.8, 10.0, 40.0, 150.0, 800.0):
        for dof in (1, 2, 3, 5, 8.5):
            for lam in (0.3, 2.0, 10.0, 60.0, 300.0, 1500.0):
                theirs = ncx2.sf(q, dof, lam)
                if theirs > 1e-10:
                    assert abs(noncentral_chi2_sf(q, dof, lam) / theirs - 1.0) <= 1e-12
            for power in (0.5, 0.9, 0.95, 0.99):
                ours = noncentrality_for_power(q, dof, power)
                if 1.0 - chndtr(q, dof, 0.0) >= power:
                    assert ours == 0.0
                else:
                    # scipy's inverse (cdflib's search) is good to ~1e-9 in some versions;
                    # the tail at our λ is the power to 1e-11
                    assert abs(ours / chndtrinc(q, dof, 1.0 - power) - 1.0) <= 1e-8
                    assert abs(noncentral_chi2_sf(q, dof, ours) - power) <= 1e-11


def test_tails_are_scipy_stats_numbers():
    """χ² and normal tails (evaluated without scipy) agree with scipy.stats to 1e-12."""
    from rotor_id.estimation.validation import chi2_sf, normal_isf, normal_sf
    from scipy.stats import chi2, norm

    def assert_relative(ours, theirs):
        theirs = np.asarray(theirs)
        assert np.all(np.isfinite(ours)) and np.all(theirs > 0)
        assert np.max(np.abs(ours / theirs - 1.0)) <= 1e-12

    q = np.concatenate([np.linspace(0.0, 300.0, 3001), np.logspace(-8.0, 2.0, 301)])
    for dof in (0.3, 1, 2, 5, 20, 20.7, 40, 200):      # real dof: the Satterthwaite χ²
        assert_relative(chi2_sf(q, dof), chi2.sf(q, dof))
    assert isinstance(chi2_sf(25.0, 20), float)
    assert chi2_sf(-1.0, 3) == 1.0 and chi2_sf(np.inf, 3) == 0.0
    assert np.isnan(chi2_sf(np.nan, 3)) and np.isnan(chi2_sf(3.0, 0))
    z = np.linspace(-37.0, 37.0, 4001)                  # norm.sf(37) ~ 6e-300
    assert_relative(normal_sf(z), norm.sf(z))
    assert normal_sf(-np.inf) == 1.0 and normal_sf(np.inf) == 0.0
    p = np.logspace(-300.0, -1e-3, 3001)
    assert np.array_equal(normal_isf(p), norm.isf(p))


def test_score_statistic_of_a_linear_model_is_twice_the_likelihood_gain():
    # y = X β + ε, σ = 1: at β restricted to 0 in its last two entries (the others refitted),
    # the score statistic is exactly 2Δlog L of freeing them, and M⁻¹ the covariance of β̂
    rng = np.random.default_rng(3)
    X = rng.normal(size=(200, 4))
    y = X @ np.array([1.0, -0.5, 0.3, 0.2]) + rng.normal(size=200)
    free = np.linalg.lstsq(X, y, rcond=None)[0]
    restricted = np.zeros(4)
    restricted[:2] = np.linalg.lstsq(X[:, :2], y, rcond=None)[0]
    gain = np.sum((y - X @ restricted)**2) - np.sum((y - X @ free)**2)
    lm, variance = score_statistic(-X.T @ (y - X @ restricted), X.T @ X)
    assert lm == pytest.approx(gain, rel=1e-10)
    assert variance == pytest.approx(np.diag(np.linalg.inv(X.T @ X)), rel=1e-10)


def test_score_statistic_gives_an_uninformed_parameter_no_finite_variance():
    # the third parameter is the sum of the first two: the data inform two directions only
    X = np.array([[1.0, 0.0, 1.0], [0.0, 1.0, 1.0], [1.0, 1.0, 2.0], [2.0, 1.0, 3.0]])
    lm, variance = score_statistic(np.array([1.0, 2.0, 3.0]), X.T @ X)
    assert np.all(np.isinf(variance))
    assert math.isfinite(lm) and lm > 0.0
