"""
The selection and the verdict rules on recorded candidate tables (synthetic fits, no model).

A table gives each explanation its log-likelihood gain over the baseline and its extra
parameters; the fake likelihood answers fits from it and score tests with the exact gain.
The checks are against the rules of docs/diagnosis.md: BIC evidence with the effective sample
size, the prior over sizes and sets, the 0.95 confidence rule, shares of equivalents,
detection limits from the noncentral χ², ``unexplained`` when residuals are not noise.
"""

from dataclasses import replace
import math
from types import SimpleNamespace

import numpy as np
import pytest
from rotor_id.diagnosis.likelihood import canonical, FitResult, Likelihood, ScoreTest
from rotor_id.diagnosis.policy import SelectionPolicy
from rotor_id.diagnosis.selection import Prior, search
from rotor_id.diagnosis.verdict import acceptance_noncentrality, explain
from scipy.stats import ncx2

N_OBS = 4000
POLICY = SelectionPolicy()
UNTEMPERED = replace(POLICY, evidence_tempering=1.0)
EFFECTS = ('sensor_lag', 'time_delay', 'sensor_bias', 'flap_frequency', 'sensor_gain',
           'pitch_actuator_lag')


class TableSpace(Likelihood):
    """A likelihood that answers from a table {frozenset(effects): (gain, k)}."""

    def __init__(self, table, rho=1.0, at_bound=(), variance=1e-4):
        self.table, self.rho, self.at_bound, self.variance = table, rho, at_bound, variance
        self.fits, self.refits, self.scored = [], [], []

    def _result(self, effects, gain_shift=0.0):
        gain, k = self.table.get(frozenset(e for e, _ in effects), (None, None))
        if gain is None:            # not in the table: the effects add up (no interaction)
            gain = sum(self.table.get(frozenset([e]), (0.0, 1))[0] for e, _ in effects)
            k = sum(self.table.get(frozenset([e]), (0.0, 1))[1] for e, _ in effects)
        fit = SimpleNamespace(estimate=SimpleNamespace(model_parameters={'lag_rad': 0.05,
                                                                         'delay_rad': 0.05}),
                              unknowns=['lag_rad', 'delay_rad'], effect_parameters={},
                              model=None)
        return FitResult(canonical(effects), -1000.0 + gain + gain_shift, k, N_OBS, self.rho,
                         True, tuple(a for a in self.at_bound
                                     if any(a.startswith(e) for e, _ in effects)),
                         fit, 'output error')

    def baseline(self):
        return self._result(())

    def fit_many(self, requests):
        self.fits += [canonical(e) for e, _ in requests]
        return [self._result(e) for e, _ in requests]

    def refit_from(self, effects, values):
        self.refits.append((canonical(effects), dict(values)))
        return self._result(effects, gain_shift=self.table.get('restart_gain', 0.0))

    def score_many(self, current, effects):
        self.scored.append(current.effects)
        return {e: self.score(current, e) for e in effects}

    def score(self, current, effect):
        new = self._result(current.effects + ((effect, ''),))
        lm = self.table.get(('score', frozenset(new.names)), 2.0 * (new.loglik - current.loglik))
        return ScoreTest(effect, '', lm,
                         new.n_params - current.n_params,
                         {f'{effect}_size': self.variance})


def _run(table, effects=EFFECTS, policy=POLICY, adequate=lambda r: True, **options):
    space = TableSpace(table, **options)
    prior = Prior(effects, policy.max_effects, 4)
    selection = search(space, list(effects), prior, policy)
    explanation, top, rows = explain(space, selection, prior, policy, adequate,
                                     lambda r: None)
    return explanation, selection, space


def test_a_clear_single_effect_is_named_with_high_confidence():
    # the untempered posterior (η = 1): the temperature is checked on its own below
    explanation, selection, _ = _run({frozenset(['sensor_bias']): (60.0, 2)}, policy=UNTEMPERED)
    assert explanation.names == ('sensor_bias',)
    assert explanation.effect == 'sensor_bias'
    assert explanation.confidence == 'high' and explanation.probability >= 0.95
    # the posterior is normalised over the explanations fitted and score-tested
    total = sum(a.probability for a in explanation.alternatives) + explanation.probability
    assert total <= 1.0 + 1e-12


def test_the_posterior_odds_are_the_bic_evidence_with_the_prior():
    # one effect of k = 1 gaining Δlog L = g: log odds against none = g − ½ log N
    # − log C(m, 1) (prior: sizes uniform, then sets of physics; the lag, the delay and the
    # actuator lag are one physics in hover, so m = 4 for the six effects)
    # and the stated probability temperature-scales those log odds by η
    m, g = 4, 10.0
    for eta in (1.0, POLICY.evidence_tempering):
        explanation, selection, _ = _run({frozenset(['flap_frequency']): (g, 1)},
                                         policy=replace(POLICY, evidence_tempering=eta))
        odds = eta * (g - 0.5 * math.log(N_OBS) - math.log(m))
        expected = 1.0 / (1.0 + math.exp(-odds))
        probs = {tuple(a.effects): a.probability for a in explanation.alternatives}
        probs[explanation.names] = explanation.probability
        p_one, p_none = probs[('flap_frequency',)], probs[()]
        assert p_one / (p_one + p_none) == pytest.approx(expected, rel=1e-9)


def test_a_small_gain_leaves_none_less_probable_than_a_null_does():
    weak, _, _ = _run({frozenset(['flap_frequency']): (4.0, 1)})
    assert weak.effect == 'none' and weak.confidence == 'low'
    null, _, _ = _run({})
    assert null.effect == 'none' and null.probability > weak.probability
    # the posterior of a null table is high (every effect pays BIC's Occam factor
    # ½ log N = 4.1 and the prior's multiplicity); the stated one is tempered below it
    untempered, _, _ = _run({}, policy=UNTEMPERED)
    assert untempered.effect == 'none' and untempered.confidence == 'high'
    assert null.probability < untempered.probability


def test_the_autocorrelation_correction_tempers_the_gain():
    clear, _, _ = _run({frozenset(['sensor_bias']): (20.0, 1)}, rho=1.0)
    tempered, _, _ = _run({frozenset(['sensor_bias']): (20.0, 1)}, rho=0.2)
    assert clear.names == ('sensor_bias',)
    assert tempered.names == ()


def test_false_alarms_on_null_tables_stay_under_two_percent():
    # every effect's 2Δlog L is χ²_k under the null (white residuals): the search names
    # something in far fewer than 2 % of records
    rng = np.random.default_rng(34)
    named = 0
    runs = 400
    for _ in range(runs):
        table = {frozenset([e]): (0.5 * rng.chisquare(1), 1) for e in EFFECTS}
        # the lag, the delay and the actuator lag see one statistic (the delay's)
        for lag in ('sensor_lag', 'pitch_actuator_lag'):
            table[frozenset([lag])] = table[frozenset(['time_delay'])]
        explanation, _, _ = _run(table)
        named += bool(explanation.names)
    assert named / runs < 0.02


def test_equivalents_share_the_probability_and_the_established_one_is_named():
    table = {frozenset(['sensor_lag']): (80.0, 1), frozenset(['pitch_actuator_lag']): (80.2, 1),
             frozenset(['time_delay']): (79.9, 1)}
    explanation, _, _ = _run(table)
    # one physics to first order: the probabilities add; the record cannot tell them apart
    assert explanation.confidence == 'high' and explanation.probability >= 0.95
    assert explanation.effect == 'sensor_lag'
    [effect] = explanation.effects
    shares = {s.effect: s.share for s in effect.shares}
    assert set(shares) == {'sensor_lag', 'pitch_actuator_lag', 'time_delay'}
    assert sum(shares.values()) == pytest.approx(1.0)
    assert shares['pitch_actuator_lag'] > shares['sensor_lag'] > shares['time_delay']


def test_detection_limits_at_a_named_equivalent_come_from_the_tests_the_search_made():
    table = {frozenset(['sensor_lag']): (80.0, 1), frozenset(['pitch_actuator_lag']): (80.2, 1),
             frozenset(['time_delay']): (79.9, 1)}
    explanation, selection, space = _run(table)
    # the search went on from the most probable form; the established one is named
    assert selection.final.names == ('pitch_actuator_lag',)
    assert explanation.effect == 'sensor_lag'
    # its limits are those of the equivalent's score tests: no test at the named model
    assert (('sensor_lag', ''),) not in space.scored
    limits = {d.effect: d.limits for d in explanation.detection_limits}
    assert set(limits) == {'sensor_bias', 'flap_frequency', 'sensor_gain'}
    assert all(v > 0.0 for d in limits.values() for v in d.values())


def test_rivals_that_are_not_equivalent_take_the_confidence_away():
    table = {frozenset(['sensor_bias']): (60.0, 2), frozenset(['sensor_gain']): (61.0, 2),
             frozenset(['sensor_bias', 'sensor_gain']): (61.5, 4)}
    explanation, _, _ = _run(table)
    assert explanation.confidence == 'low'
    [effect] = explanation.effects
    assert {s.effect for s in effect.shares} == {'sensor_bias', 'sensor_gain'}


def test_a_stand_in_kept_first_does_not_hide_the_pair_it_stands_in_for():
    # flap_frequency alone explains part of both; the pair explains all, and beside the
    # stand-in neither passes: the second most probable single effect is extended too
    table = {frozenset(['flap_frequency']): (70.0, 1), frozenset(['sensor_bias']): (50.0, 2),
             frozenset(['sensor_gain']): (40.0, 4),
             frozenset(['flap_frequency', 'sensor_bias']): (75.0, 3),
             frozenset(['flap_frequency', 'sensor_gain']): (72.0, 5),
             frozenset(['sensor_bias', 'sensor_gain']): (140.0, 6),
             frozenset(['flap_frequency', 'sensor_bias', 'sensor_gain']): (140.5, 7)}
    explanation, selection, _ = _run(table, policy=UNTEMPERED)
    assert set(explanation.names) == {'sensor_bias', 'sensor_gain'}
    assert [(s.action, s.effect) for s in selection.steps] == [('add', 'flap_frequency'),
                                                               ('add', 'sensor_gain')]
    assert explanation.confidence == 'high'


def test_the_backward_check_drops_an_effect_the_others_make_redundant():
    # the third effect explains what the first did: without the first the model is likelier.
    # bias + gain is not fitted on the way (its score tests say little: a nonlinear pair),
    # only by the backward check
    table = {frozenset(['flap_frequency']): (70.0, 1), frozenset(['sensor_bias']): (30.0, 2),
             frozenset(['sensor_gain']): (20.0, 4),
             frozenset(['flap_frequency', 'sensor_bias']): (100.0, 3),
             frozenset(['flap_frequency', 'sensor_gain']): (75.0, 5),
             frozenset(['sensor_bias', 'sensor_gain']): (199.9, 6),
             frozenset(['flap_frequency', 'sensor_bias', 'sensor_gain']): (200.0, 7),
             ('score', frozenset(['sensor_bias', 'sensor_gain'])): 1.0}
    explanation, selection, _ = _run(table)
    assert ('drop', 'flap_frequency') in [(s.action, s.effect) for s in selection.steps]
    assert set(selection.final.names) == {'sensor_bias', 'sensor_gain'}
    assert set(explanation.names) == {'sensor_bias', 'sensor_gain'}


def _stand_in_table(lag_and_bias):
    # per-blade gains (k = 4) stand in for per-blade offsets (k = 2) beside a lag: the gains
    # gain most alone, and the offsets are score-tested at the baseline, never fitted there
    return {frozenset(['sensor_gain']): (224.0, 4), frozenset(['sensor_lag']): (160.0, 1),
            frozenset(['sensor_bias']): (92.0, 2),
            frozenset(['sensor_lag', 'sensor_gain']): (283.0, 5),
            frozenset(['sensor_lag', 'sensor_bias']): (lag_and_bias, 3),
            frozenset(['sensor_gain', 'sensor_bias']): (224.0, 6),
            frozenset(['sensor_lag', 'sensor_gain', 'sensor_bias']): (lag_and_bias + 0.5, 7)}


STAND_IN = ('sensor_lag', 'sensor_bias', 'sensor_gain')


def _greedy(table):
    # one explanation extended per step (residuals noise: beam of one), so only the exchange
    # can reach the offsets beside the lag
    space = TableSpace(table)
    return search(space, list(STAND_IN), Prior(STAND_IN, POLICY.max_effects, 4), POLICY,
                  adequate=lambda r: True), space


def test_the_exchange_swaps_a_stand_in_for_the_effect_it_stands_in_for():
    selection, space = _greedy(_stand_in_table(283.1))
    assert canonical([('sensor_bias', '')]) not in space.fits
    assert ('exchange', 'sensor_bias') in [(s.action, s.effect) for s in selection.steps]
    assert set(selection.final.names) == {'sensor_lag', 'sensor_bias'}


def test_a_swap_its_score_test_rules_out_is_not_fitted():
    # beside the lag the offsets' score test (2Δlog L 10, the table's exact gain) cannot
    # reach the pair the search found: branch and bound at the model the swap extends
    selection, space = _greedy(_stand_in_table(165.0))
    assert canonical([('sensor_lag', ''), ('sensor_bias', '')]) not in space.fits
    assert canonical([('sensor_gain', ''), ('sensor_bias', '')]) not in space.fits
    assert set(selection.final.names) == {'sensor_lag', 'sensor_gain'}
    # still in the posterior, by its score-test approximation
    assert not selection.candidates[canonical([('sensor_lag', ''), ('sensor_bias', '')])].fitted


def test_never_more_effects_than_the_policy_allows():
    table = {frozenset([e]): (100.0, 1) for e in ('sensor_bias', 'flap_frequency',
                                                  'sensor_gain', 'sensor_lag')}
    explanation, selection, _ = _run(table, policy=replace(POLICY, max_effects=2))
    assert len(explanation.names) == 2
    assert all(len(k) <= 2 for k in selection.candidates)


def test_a_fit_at_its_range_limit_is_still_compared():
    explanation, _, _ = _run({frozenset(['sensor_lag']): (80.0, 1)}, at_bound=('sensor_lag',))
    assert explanation.names == ('sensor_lag',)
    assert explanation.effects[0].inclusion_probability > 0.99


def test_a_worse_optimum_is_restarted_from_its_first_order_equivalent():
    # the delay's score test predicts the lag's gain (one statistic), its fit stops at 15.6
    table = {frozenset(['sensor_lag']): (75.0, 1), frozenset(['time_delay']): (15.6, 1),
             ('score', frozenset(['time_delay'])): 150.0, 'restart_gain': 59.0}
    _, selection, space = _run(table)
    restarted = dict(space.refits)
    assert restarted[(('time_delay', ''),)]['delay_rad'] == pytest.approx(0.05)
    delay = selection.candidates[(('time_delay', ''),)]
    assert delay.loglik == pytest.approx(-1000.0 + 15.6 + 59.0)


def test_residuals_that_are_not_noise_make_the_verdict_unexplained():
    explanation, _, _ = _run({frozenset(['sensor_bias']): (60.0, 2)},
                             adequate=lambda r: False)
    assert explanation.effect == 'unexplained' and explanation.confidence == 'low'
    assert explanation.effects == [] and not explanation.residuals_are_noise


def test_detection_limit_is_the_size_found_with_the_policy_power():
    explanation, selection, space = _run({}, variance=4e-6)
    limit = next(d for d in explanation.detection_limits if d.effect == 'sensor_bias')
    lam = limit.noncentrality
    # the search adds an effect of k = 1 when 2Δlog L > log N + 2 log m (sizes uniform: the
    # prior odds of one effect against none are 1/m, m = 4 physics)
    c = math.log(N_OBS) + 2.0 * math.log(4)
    assert ncx2.sf(c, 1, lam) == pytest.approx(POLICY.detection_power, abs=1e-6)
    assert limit.limits['sensor_bias_size'] == pytest.approx(math.sqrt(lam * 4e-6))
    # a stricter power asks for a larger effect
    test = ScoreTest('sensor_bias', '', 0.0, 1, {})
    prior = Prior(EFFECTS, POLICY.max_effects, 4)
    half = acceptance_noncentrality(selection.final, test, prior,
                                    replace(POLICY, detection_power=0.5), 1.0)
    assert half < lam


def test_the_prior_weighs_physics_and_shares_it_among_equivalent_forms():
    # hover: lag, delay and actuator lag are one physics; flap frequency, bias, gain others
    prior = Prior(EFFECTS, 3, 4)
    one = [math.exp(prior.log(((e, ''),))) for e in EFFECTS]
    assert sum(one) == pytest.approx(1.0 / 4)            # size 1: a quarter of the prior
    forms = [math.exp(prior.log(((e, ''),)))
             for e in ('sensor_lag', 'time_delay', 'pitch_actuator_lag')]
    assert sum(forms) == pytest.approx(math.exp(prior.log((('sensor_bias', ''),))))
    # an odd blade is one of N
    blade = Prior(EFFECTS + ('blade_dissimilarity',), 3, 4)
    assert math.exp(blade.log((('blade_dissimilarity', 'blade_2'),))) == pytest.approx(
        math.exp(blade.log((('sensor_bias', ''),))) / 4)


class AheadTableSpace(TableSpace):
    """The table, with the fits a step may ask for next begun ahead (and some given up)."""

    def __init__(self, table, **options):
        super().__init__(table, **options)
        self.begun, self.given_up, self._ahead = [], [], {}

    def fit_ahead(self, requests):
        for effects, _ in requests:
            self._ahead[canonical(effects)] = self._result(effects)
            self.begun.append(canonical(effects))

        def keep(wanted):
            kept = {canonical(e) for e, _ in wanted}
            self.given_up += [k for k in self._ahead if k not in kept]
            self._ahead = {k: v for k, v in self._ahead.items() if k in kept}
        return keep


def test_fits_begun_ahead_and_given_up_never_enter_the_table():
    # a step whose first fit bounds the others out: they were begun ahead, then given up
    table = {frozenset(['sensor_bias']): (90.0, 2), frozenset(['sensor_gain']): (8.0, 4),
             frozenset(['flap_frequency']): (9.0, 1),
             ('score', frozenset(['flap_frequency'])): 40.0,
             ('score', frozenset(['sensor_gain'])): 40.0}
    plain = _run(table, policy=UNTEMPERED)
    space = AheadTableSpace(table)
    prior = Prior(EFFECTS, POLICY.max_effects, 4)
    selection = search(space, list(EFFECTS), prior, UNTEMPERED)
    assert space.given_up and set(space.given_up) <= set(space.begun)
    fitted = {k for k, c in selection.candidates.items() if c.fitted}
    # in the table only as asked for; one given up and never asked for later is not in it
    assert fitted - {()} <= set(space.fits)
    assert set(space.given_up) - set(space.fits) and not fitted & (set(space.given_up)
                                                                   - set(space.fits))
    assert fitted == {k for k, c in plain[1].candidates.items() if c.fitted}
    assert selection.final.effects == plain[1].final.effects
