"""
Cramér-Rao bound and optimal data utilization (report Ch.3 eqs 16-23).

* Every M⁻¹ the report prints (Ch.2: single blade 2- and 4-parameter, multiblade (a), (b),
  (c), wake progressing, regressing, 7-parameter diagonal; Ch.3 Table 1's nine rows) is
  reproduced at Δt = 0.1. Full matrices: every element within 2 % of the matrix's largest
  diagonal element; the 7-parameter diagonal: each element within 2 %; Table 1 (printed with
  1-2 significant digits, apparently truncated): the printed value is ours rounded or
  truncated to the printed digits.
* M⁻¹ scales like Δt (docs/models.md §1.4 Δt scan) and the continuous form (eq. 21) is 1-3 %
  larger.
* The history M⁻¹(t_f) is the bound of the truncated record, is monotone (eq. 22), and the
  shortest record / information density are consistent with it.
"""

import numpy as np
import pytest

from rotor_id.estimation.information import (continuous_bound, cramer_rao_bound,
                                             information_density, information_history,
                                             inverse_or_nan, inverses_or_nan, sensitivities,
                                             shortest_record)
from rotor_id.estimation.output_error import IdentificationError
from rotor_id.report import cases as C
from rotor_id.report.reproduce import evaluate_matrix_case

SB = C.SCENARIOS['single_blade']


@pytest.mark.parametrize('case', C.MATRIX_CASES, ids=lambda c: c.name)
def test_printed_information_matrix_is_reproduced(case):
    res = evaluate_matrix_case(case)
    assert res.ours.shape == res.report.shape
    assert np.allclose(res.ours, res.ours.T)
    ours, report = res.ours, res.report
    if case.kind == 'full':
        tol = 0.02 * np.max(np.diag(report))
        assert np.max(np.abs(ours - report)) <= tol, (ours, report)
    elif case.kind == 'diagonal':
        np.testing.assert_allclose(np.diag(ours), np.diag(report), rtol=0.02)
    else:
        decimals = C.TABLE1_DECIMALS[case.t_end]
        for value, printed, d in zip(np.diag(ours), np.diag(report), decimals):
            rounded, truncated = round(value, d), np.floor(value * 10**d) / 10**d
            assert np.isclose(printed, rounded) or np.isclose(printed, truncated), \
                (case.name, value, printed)
    assert res.passed


def test_matrix_comparison_can_fail():
    """At a 20 % wrong point the single-blade bound differs from the print by more than 2 %."""
    case = C.MATRIX_CASES[0]
    exp = C.make_experiment(SB, initial_state='truth')
    far = cramer_rao_bound(exp, exp.model.parameter_vector({'gamma': 4.0, 'delta': 8.0}),
                           C.SB)
    assert np.max(np.abs(far.covariance - np.asarray(case.report))) > 0.02 * 0.365


@pytest.mark.parametrize('dt, expected', [
    (0.2, [[0.417, -0.069], [-0.069, 0.728]]),
    (0.1, [[0.212, -0.036], [-0.036, 0.365]]),
    (0.05, [[0.107, -0.018], [-0.018, 0.183]]),
])
def test_bound_scales_with_sampling_interval(dt, expected):
    """docs/models.md §1.4 Δt scan at p = (4.91, 9.82), R = I."""
    exp = C.make_experiment(SB, initial_state='truth')
    exp.t = C.sample_times(12.0, 24.0, dt)
    b = cramer_rao_bound(exp, exp.model.parameter_vector({'gamma': 4.91, 'delta': 9.82}),
                         C.SB)
    np.testing.assert_allclose(b.covariance, expected, atol=0.0015)


def test_continuous_form_is_slightly_larger():
    """Eq. 21 (Δt·[∫SᵀS]⁻¹) is 1-3 % above the discrete sum (docs/models.md §0.1, §1.4)."""
    exp = C.make_experiment(SB, initial_state='truth')
    p = exp.model.parameter_vector({'gamma': 4.91, 'delta': 9.82})
    cont = continuous_bound(exp, p, C.SB)
    disc = cramer_rao_bound(exp, p, C.SB)
    ratio = np.diag(cont.covariance) / np.diag(disc.covariance)
    assert np.all((ratio > 1.0) & (ratio < 1.03)), ratio
    np.testing.assert_allclose(cont.covariance, [[0.215, -0.038], [-0.038, 0.366]], atol=0.0015)


def test_history_is_the_bound_of_each_truncated_record():
    exp = C.make_experiment(SB, initial_state='truth')
    p = exp.model.parameter_vector({'gamma': 4.0, 'delta': 8.0})
    hist = information_history(exp, p, C.SB, noise_std=0.2)
    assert hist.covariance.shape == (121, 2, 2)
    # t0 alone: the state is known, so no information on (γ, δ) yet
    assert np.all(np.isnan(hist.covariance[0]))
    for t_end in (14.0, 18.0, 24.0):
        short = C.make_experiment(SB, t_end=t_end, initial_state='truth')
        bound = cramer_rao_bound(short, p, C.SB, noise_std=0.2)
        np.testing.assert_allclose(hist.at(t_end), bound.covariance, rtol=1e-10)
    # eq. 22: every diagonal element is non-increasing in t_f
    var = np.einsum('tii->ti', hist.covariance)[2:]
    assert np.all(np.diff(var, axis=0) <= 1e-12 * var[:-1])
    # Table 1 row 1 at t_f = 14: 48 / 6.5
    np.testing.assert_allclose(np.diag(hist.at(14.0)), [48.26, 6.534], rtol=2e-3)


def test_batched_inverses_equal_the_loop_exactly():
    """inverses_or_nan (used by the history) is inverse_or_nan on every matrix, bit for bit."""
    rng = np.random.default_rng(1)
    S = rng.standard_normal((150, 9))
    S[:, 4] *= 1e-9                               # ill-conditioned, NaN until enough samples
    M = np.cumsum(np.einsum('ti,tj->tij', S, S), axis=0)
    M[20, 2, 2] = 0.0                             # a zero diagonal element
    loop = np.array([inverse_or_nan(m) for m in M])
    assert np.isnan(loop[:8]).all() and np.isnan(loop[20]).all() and np.isfinite(loop[-1]).all()
    np.testing.assert_array_equal(inverses_or_nan(M), loop)
    assert inverses_or_nan(np.zeros((0, 3, 3))).shape == (0, 3, 3)


def test_shortest_record_meets_the_stipulated_sigmas():
    exp = C.make_experiment(SB, initial_state='truth')
    p = exp.model.parameter_vector({'gamma': 4.91, 'delta': 9.83})
    hist = information_history(exp, p, C.SB, noise_std=0.2)
    std = hist.std()
    j = 80                                        # t = 20
    target = {'gamma': std[j, 0] * (1 + 1e-9), 'delta': 10.0}
    answer = shortest_record(hist, target)
    assert answer.met and answer.t_f <= hist.t[j] + 1e-9
    assert np.all(std[answer.index, 0] <= target['gamma'])
    assert std[answer.index - 1, 0] > target['gamma']
    assert answer.limiting == 'gamma'
    assert np.isclose(answer.duration, answer.t_f - 12.0)
    # M⁻¹(γ) ≤ 0.1 (σ_γ ≈ .32) needs data to about t = 17.5 (the report's steep descent)
    first_descent = shortest_record(hist, {'gamma': 0.1 ** 0.5})
    assert first_descent.met and 17.0 <= first_descent.t_f <= 18.0, first_descent.t_f
    never = shortest_record(hist, [1e-4, 1e-4])
    assert not never.met and never.t_f is None
    with pytest.raises(ValueError, match='no parameter theta0'):
        shortest_record(hist, {'theta0': 0.1})


def test_steep_descents_found_by_information_density():
    """Ch.3: M⁻¹ drops steeply to t ≈ 17.5 and again before t ≈ 23 (figs 2-3)."""
    exp = C.make_experiment(SB, initial_state='truth')
    p = exp.model.parameter_vector({'gamma': 4.91, 'delta': 9.83})
    dens = information_density(exp, p, C.SB, noise_std=0.2)
    hist = information_history(exp, p, C.SB, noise_std=0.2)
    # per-sample information adds up to the total information
    np.testing.assert_allclose(dens.diagonal.sum(axis=0), np.diag(hist.information[-1]))
    # variance reductions add up to the fall of M⁻¹(i, i) after the first finite value
    var = np.einsum('tii->ti', hist.covariance)
    first = np.argmax(np.isfinite(var[:, 0]))
    np.testing.assert_allclose(dens.variance_reduction.sum(axis=0), var[first] - var[-1],
                               rtol=1e-9)
    finite = np.isfinite(dens.log_det_increment)
    assert np.all(dens.log_det_increment[finite] >= -1e-12)
    # relative fall of M⁻¹(γ) (log scale, as in figs 2-3): steep to 17.5, flat 18-19.5,
    # steep again 21.5-23.5
    log_var = np.log(var[:, 0])
    t = hist.t

    def fall(a, b):
        return log_var[np.searchsorted(t, a - 1e-9)] - log_var[np.searchsorted(t, b - 1e-9)]

    assert fall(16.0, 17.5) > 1.5 and fall(21.5, 23.5) > 1.0 and fall(18.0, 19.5) < 0.2
    # and the density says the same per sample: the flat span carries < 5 % of the late fall
    red = dens.variance_reduction[:, 0] / var[:, 0]
    late = t > 16.0
    assert red[(t > 18.0) & (t <= 19.5)].sum() < 0.05 * red[late].sum()


def test_free_initial_states_need_a_value_or_data():
    exp = C.make_experiment(SB, initial_state='estimate')
    p = exp.model.parameter_vector({})
    with pytest.raises(IdentificationError, match='neither measurements nor x0_guess'):
        cramer_rao_bound(exp, p, C.SB)
    with_x0 = sensitivities(exp, p, C.SB, x0=np.array([-0.92, 0.99]))
    assert with_x0.names == ['gamma', 'delta', 'beta(t0)', 'beta_dot(t0)']
    np.testing.assert_allclose(with_x0.dy[0, 0], [0.0, 0.0, 1.0, 0.0])
    # with data the initial state is fitted by least squares (noise-free: the truth)
    y = C.truth_outputs(SB, exp.t)
    exp_y = C.make_experiment(SB, y=y, initial_state='estimate')
    fitted = sensitivities(exp_y, exp.model.parameter_vector({}), C.SB)
    np.testing.assert_allclose(fitted.values[2:], C.truth_initial_state(SB), atol=1e-9)


def test_noise_must_be_positive():
    exp = C.make_experiment(SB, initial_state='truth')
    with pytest.raises(ValueError, match='positive'):
        cramer_rao_bound(exp, exp.model.parameter_vector({}), C.SB, noise_std=0.0)


@pytest.mark.parametrize('omegadot, half, corr, ratio, is_report', [
    (-0.1 / np.pi, False, -0.130, 1.725, True),    # the law the report's numbers need
    (-1.0 / np.pi, False, -0.081, 2.291, False),   # Ch.2 eq. 6 as OCR'd
    (-0.1 / np.pi, True, -0.155, 1.131, False),    # φ = ω̇(t − t0)²/2
])
def test_stirring_law_decided_by_the_bound(omegadot, half, corr, ratio, is_report):
    """docs/models.md §1.3: corr(γ, δ) and var δ/var γ at (4.91, 9.82) single out ω̇ = −0.1/π."""
    from dataclasses import replace

    from rotor_id.physics.stirring import StirringSchedule

    class HalfPhase(StirringSchedule):
        def phase(self, t):
            return 0.5 * super().phase(t)

    exp = C.make_experiment(SB, initial_state='truth')
    law = (HalfPhase if half else StirringSchedule)(omegadot=omegadot, t0=12.0)
    exp = replace(exp, inputs=law)
    b = cramer_rao_bound(exp, exp.model.parameter_vector({'gamma': 4.91, 'delta': 9.82}), C.SB)
    c = b.covariance
    ours_corr = c[0, 1] / np.sqrt(c[0, 0] * c[1, 1])
    assert ours_corr == pytest.approx(corr, abs=0.002)
    assert c[1, 1] / c[0, 0] == pytest.approx(ratio, abs=0.003)
    matches_report = bool(abs(ours_corr + 0.130) < 0.005 and abs(c[1, 1] / c[0, 0] - 1.730) < 0.01)
    assert matches_report is is_report
