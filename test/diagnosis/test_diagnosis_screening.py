"""
Score-test screening and catalogue bounds of the diagnosis (pins #16).

* The score statistic at the baseline predicts the full fit's 2Δlog L for a nested effect
  (Rao's score test and the likelihood-ratio test agree to first order in a small effect).
* (That screening keeps the verdict of fitting everything is bench/diagnose_speed.py's check.)
* A range limit never removes a candidate: a sensor lag of 0.025 rad, below the lag's
  smallest τ_s (0.03, the RK4 step's stability), is compared on its own likelihood, flagged
  at its limit, beside its first-order equivalent delay d ≈ τ_s; the lag's physics is named.
* The score test's variance of the extra parameter is the delay's Cramér-Rao variance at the
  fitted model: the detection limit's scale.
* A blade's score test (its new initial states at rest in the current model, as they are
  under the null) predicts its fit's 2Δlog L.
* The wake's fit never ends below the model it extends (restarted at no wake where the most
  likely grid start settled lower).
* A score test that integrates only its extra parameters' sensitivities (the others the
  current model's) gives every effect's statistic and variances of the full integration, at
  the baseline and at an augmented model; by output error, and by filter error at a fit with
  random inflow in forward flight.
"""

from dataclasses import replace

from diagnosis_scenarios import Scenario, WAKE, WAKE_TRUTH
import numpy as np
import pytest
from rotor_id.diagnosis import catalogue, noisy
from rotor_id.diagnosis.catalogue import (
    EQUIVALENT, fit_candidate, Job, screen_candidate, SCREENED, SCREENED_AS, Setting,
    start_values)
from rotor_id.diagnosis.diagnose import diagnose
from rotor_id.estimation.filter_error import FilterProblem
from rotor_id.io.run_description import parse_run_description
from rotor_id.pipeline import identify
import truth_generator
from truth_generator import wake_case

SMALL_LAG = Scenario('small_sensor_lag', 'sensor_lag',
                     lambda s: wake_case(seed=s, sensor_lag=0.025), WAKE,
                     accept=('time_delay',), extra_truth={'lag_rad': 0.025},
                     original_truth=WAKE_TRUTH)


@pytest.fixture(scope='module')
def small_lag():
    record, description = SMALL_LAG.record_and_description(1)
    return record, description


def _job(effect, record, description):
    ident = identify(record, description)
    est = ident.estimate
    return Job(Setting.of(record, ident), effect, baseline_nll=est.neg_log_likelihood), est


def test_score_statistic_predicts_the_likelihood_gain(small_lag):
    record, description = small_lag
    job, est = _job('time_delay', record, description)
    _, lm, k, var = screen_candidate(job, np.asarray(est.noise_std)**2)
    fit = fit_candidate(job)
    # the information at the baseline is the fit's to first order: σ of the delay within 15 %
    _, std = fit.parameters['delay_rad']
    assert abs(var['delay_rad']**0.5 - std) < 0.15 * std, (var, std)
    two_dll = 2.0 * (est.neg_log_likelihood - fit.estimate.neg_log_likelihood)
    assert k == 1
    # a delay of 1/4 of a sample interval is small: the local test is within 15 % of the LR
    assert two_dll > 30.0
    assert abs(lm - two_dll) < 0.15 * two_dll, (lm, two_dll)


@pytest.mark.parametrize('scale, seed', [(1.02, 2), (1.04, 1)])
def test_blade_score_test_at_rest_predicts_its_fit_s_gain(scale, seed):
    # a blade's Lock number 2 % or 4 % high: the score test of its four parameters (ε, the
    # static offset and the odd blade's two initial states, at rest in the current model)
    # within 10 % of the fit's 2Δlog L (with the initial states refitted at the null instead,
    # the test left out their gain: 13.5 % short at 4 %)
    scenario = Scenario('blade_small', 'blade_dissimilarity', lambda s: wake_case(
        seed=s, gamma_scale=[1.0, 1.0, scale, 1.0]), WAKE)
    record, description = scenario.record_and_description(seed)
    job, est = _job('blade_dissimilarity', record, description)
    job = replace(job, variant='blade_3')
    _, lm, k, _ = screen_candidate(job, np.asarray(est.noise_std)**2)
    fit = fit_candidate(job)
    two_dll = 2.0 * (est.neg_log_likelihood - fit.estimate.neg_log_likelihood)
    assert k == 4 and two_dll > 30.0
    assert abs(lm - two_dll) < 0.10 * two_dll, (lm, two_dll)


def test_wake_fit_never_ends_below_the_model_it_extends():
    # forward flight with a flap read late: from the most likely of the wake's grid starts
    # the fit settled 111 below the model without a wake (2Δlog L −111); it is restarted at
    # no wake (AL/τ = 0, that model), whence it cannot end below it
    cfg = truth_generator.mu04_case(seed=3, mu=0.35, t0=truth_generator.TruthConfig.t0,
                                    sensor_lag=0.028)
    record = truth_generator.generate(cfg)
    description = parse_run_description(
        truth_generator.run_description_text(cfg, 'multiblade', ('gamma', 'theta0')))
    job, est = _job('dynamic_inflow', record, description)
    fits = []
    fit_runs = catalogue.fit_runs

    def counted(*args, **kwargs):
        fits.append(fit_runs(*args, **kwargs))
        return fits[-1]
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(catalogue, 'fit_runs', counted)
        fit = fit_candidate(job)
    assert len(fits) == 2 and fits[0].neg_log_likelihood > est.neg_log_likelihood
    assert fit.estimate.neg_log_likelihood <= est.neg_log_likelihood
    assert fit.estimate is fits[1]


def test_small_sensor_lag_is_not_decided_by_the_bound(small_lag):
    record, description = small_lag
    result = diagnose(record, description, workers=1).as_json()
    explanation = result['explanation']
    assert explanation['effect'] in ('sensor_lag',) + EQUIVALENT['sensor_lag']
    # the lag's physics holds most of the probability; the rest goes to the pairs it could be
    # part of (score-tested only), so the stated figure sits about the 0.95 line
    assert explanation['probability'] >= 0.9
    # the lag at its smallest τ_s is fitted and compared on its own likelihood: it explains
    # most of the record, less well than its equivalent delay, which is named
    lag = next(c for c in result['candidates'] if c['effects'] == ['sensor_lag'])
    delay = next(c for c in result['candidates'] if c['effects'] == ['time_delay'])
    assert lag['fitted'] and lag['two_delta_loglik'] > 30.0
    assert lag['two_delta_loglik'] < delay['two_delta_loglik']
    params = explanation['parameters']
    delay = params.get('delay_rad') or params['lag_rad']
    assert abs(delay['value'] - 0.025) < 3.0 * delay['std']


def test_widened_bound_is_refitted(small_lag):
    # a catalogue range the fit stops at is widened and the fit repeated (delay range ±0.01
    # set here below the concealed 0.025 rad): the result is not at the first bound
    record, description = small_lag
    job, est = _job('time_delay', record, description)
    fit = fit_candidate(replace(job, bounds={'delay_rad': (-0.01, 0.01)}))
    assert not fit.bound_limited
    assert fit.bounds['delay_rad'][1] > 0.01
    value, std = fit.parameters['delay_rad']
    assert abs(value - 0.025) < 3.0 * std


def test_score_test_of_the_extra_columns_is_the_full_one(small_lag, monkeypatch):
    record, description = small_lag
    job, est = _job('time_delay', record, description)
    noise_var = np.asarray(est.noise_std)**2
    lag = fit_candidate(job)
    at_lag = {'prior': (('time_delay', ''),), 'start': start_values(lag)}
    whole = []
    for where in ({}, at_lag):
        for effect in sorted({SCREENED_AS.get(e, e) for e in SCREENED} - {'time_delay'}):
            for variant in catalogue.tested_variants(effect, job.setting.prepared()[0]):
                tested = replace(job, effect=effect, variant=variant, **where)
                shared = screen_candidate(tested, noise_var)
                with monkeypatch.context() as patch:      # every column integrated
                    patch.setattr(catalogue.CurrentColumns, 'new_columns', lambda *a: None)
                    full = screen_candidate(tested, noise_var)
                whole.append(effect)
                assert shared[1] == pytest.approx(full[1], rel=1e-6, abs=1e-9), (effect, where)
                assert shared[2] == full[2]
                assert shared[3] == pytest.approx(full[3], rel=1e-6), (effect, where)
    assert len(whole) >= 2 * 8


def test_filter_error_score_test_of_the_extra_columns_is_the_full_one(monkeypatch):
    # (a flap read late: misfit that random inflow takes up; a turbulent record takes 10 s to
    # generate, and the identity holds at any fit)
    cfg = truth_generator.mu04_case(seed=5, mu=0.35, t0=truth_generator.TruthConfig.t0,
                                    time_delay_s=0.0003)
    record = truth_generator.generate(cfg)
    description = parse_run_description(
        truth_generator.run_description_text(cfg, 'multiblade', ('gamma', 'theta0')))
    setting = Setting.of(record, identify(record, description))
    setup = noisy.setup_for(setting)
    current = noisy.fit_alone(setting, setup)
    assert current.available, current.reason
    # a delay of the output, of the pitch, a change of the flap equation, an output offset, a
    # blade's Lock number (which adds initial states, at rest under the null: theirs are
    # integrated beside its parameters')
    tested = ('time_delay', 'pitch_delay', 'flap_frequency', 'sensor_bias',
              'blade_dissimilarity')
    shared_ones = 0
    for effect in tested:
        for variant in catalogue.tested_variants(effect, setup.base_model)[:1]:
            calls = []
            monkeypatch.setattr(FilterProblem, 'evaluate', _counted(calls))
            shared = noisy.screen(effect, variant, [], current, setting, setup)
            monkeypatch.undo()
            shared_ones += 'columns' in calls
            with monkeypatch.context() as patch:       # every column integrated
                patch.setattr(noisy, 'current_innovations', lambda *a: None)
                full = noisy.screen(effect, variant, [], current, setting, setup)
            assert shared[1] == pytest.approx(full[1], rel=1e-6, abs=1e-9), effect
            assert shared[2] == full[2]
            assert shared[3] == pytest.approx(full[3], rel=1e-6), effect
    assert shared_ones == len(tested)


def _counted(calls):
    evaluate = FilterProblem.evaluate

    def counted(self, theta, sensitivities=True, columns=None):
        calls.append('all' if columns is None else 'columns')
        return evaluate(self, theta, sensitivities, columns)
    return counted
