"""
The diagnosis's stated probability means what it says (pins #34): checked.

The scoring and the statistics of bench/calibration_study.py on made-up verdicts
(milliseconds), the random draw's reproducibility and concealment, and a CI-sized sample of
random records whose bounds come from the sampling distribution: among n verdicts stated at
high confidence (≥ 0.95) a calibrated engine is wrong at most 5 % of the time, so more than
the binomial(n, 0.05) 99 % quantile of confidently wrong verdicts rejects calibration at the
1 % level; likewise false alarms on the effect-free records against binomial(n, 0.02).

Full study (marker ``study``, ROTOR_ID_SLOW=1; hours): the same bounds on 300 records.
"""

import importlib.util
import math
from pathlib import Path
import sys

import pytest
from random_scenarios import conceal, draw, EXCESS_RANGE, residual_power, score

ROOT = Path(__file__).resolve().parents[2]


def _bench():
    if str(ROOT / 'bench') not in sys.path:         # the benchmark imports bench/common.py
        sys.path.insert(0, str(ROOT / 'bench'))
    spec = importlib.util.spec_from_file_location(
        'calibration_study', ROOT / 'bench' / 'calibration_study.py')
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _result(effect, named=(), confounded=None, confidence='high', probability=None):
    confounded = confounded or {}
    explanation = {'effect': effect, 'confidence': confidence,
                   'effects': [{'effect': n, 'confounded_with': confounded.get(n, [])}
                               for n in named]}
    if probability is not None:
        explanation['probability'] = probability
    return {'explanation': explanation, 'fit': {'baseline_rms': 1.05, 'noise_floor': 1.0}}


def _scenario(seed, kind):
    # a draw of that kind with the given effects (no record made)
    return draw(seed, kind)


def test_score_right_only_for_the_concealed_set():
    null = _scenario(3, 'null')
    assert score(null, _result('none'))['right']
    assert not score(null, _result('sensor_bias', ['sensor_bias']))['right']
    assert not score(null, _result('unexplained'))['right']
    pair = next(s for s in (draw(k, 'pair') for k in range(100))
                if s.mu == 0.0 and 'sensor_lag' in s.effects
                and not {'flap_frequency', 'cubic_stiffness', 'pitch_flap_coupling'}
                & set(s.effects))
    other = next(e for e in pair.effects if e != 'sensor_lag')
    # the lag named by its hover equivalent is right; one of the two alone, or an extra, not
    assert score(pair, _result('time_delay', ['time_delay', other]))['right']
    assert not score(pair, _result('time_delay', ['time_delay']))['right']
    assert not score(pair, _result('time_delay', ['time_delay', other,
                                                  'azimuth_offset']))['right']
    # a name reported as confounded with the concealed effect covers it, and is accounted
    out = score(pair, _result(other, [other, 'flap_frequency'],
                              {'flap_frequency': ['sensor_lag']}))
    assert out['right'] and out['confounded'] == ['sensor_lag']


def test_stated_probability_from_the_engine_or_its_label():
    null = _scenario(3, 'null')
    assert score(null, _result('none', probability=0.81))['probability'] == 0.81
    assert score(null, _result('none', confidence='high'))['probability'] == 0.95
    assert score(null, _result('none', confidence='low'))['probability'] == 0.5


def test_wilson_interval_and_binomial_bounds():
    bench = _bench()
    # Wilson (1927): 0/10 -> [0, z²/(n+z²)]; symmetric about 1/2 at 5/10
    lo, hi = bench.wilson(0, 10)
    z2 = bench.Z95 ** 2
    assert lo == 0.0 and math.isclose(hi, z2 / (10 + z2), rel_tol=1e-12)
    lo, hi = bench.wilson(5, 10)
    assert math.isclose(lo + hi, 1.0, rel_tol=1e-12) and 0.23 < lo < 0.24
    # the 99 % quantile: P(X ≤ q) ≥ 0.99 > P(X ≤ q − 1), from the binomial sums
    for n, rate in ((20, 0.05), (60, 0.02), (300, 0.05)):
        q = bench.binomial_bound(n, rate)
        cdf = [sum(math.comb(n, k) * rate**k * (1 - rate)**(n - k) for k in range(m + 1))
               for m in (q - 1, q)]
        assert cdf[0] < 0.99 <= cdf[1]


def test_reliability_table_from_scored_lines():
    bench = _bench()

    def line(kind, right, p, verdict='x'):
        return {'seed': 0, 'draw': {'kind': kind, 'concealed': [], 'n_blades': 4, 'mu': 0.0,
                                    'wake': True, 'accepted': [] if kind == 'null' else [[
                                        verdict if right else 'sensor_lag']]},
                'verdict': verdict, 'named_text': verdict, 'named': [verdict], 'right': right,
                'probability': p,
                'probability_source': 'test', 'excess': 0.05, 'cpu_s': 1.0}
    runs = ([line('single', True, 0.97)] * 18 + [line('single', False, 0.99)] * 2
            + [line('single', True, 0.6)] * 3 + [line('null', True, 0.96, 'none')] * 9
            + [line('null', False, 0.7, 'sensor_bias')]
            + [line('single', False, 0.99, 'unexplained')])
    s = bench.summarize(runs)
    top = s['reliability'][-1]
    assert (top['n'], top['right']) == (29, 27)
    assert s['reliability'][1]['n'] == 4 and s['unexplained'] == 1
    assert s['high_confidence']['confidently_wrong'] == 2
    assert s['high_confidence']['named_right'] == 27
    assert s['nulls'] == {**s['nulls'], 'n': 10, 'false_alarms': 1, 'false_alarms_high': 0}


def test_draw_is_reproducible_and_sized_by_the_quadratic_rule():
    first, again = draw(11), draw(11)
    assert first.as_dict() == again.as_dict()
    # the residual power an effect leaves in the baseline fit is quadratic in its size for a
    # small effect: at the size found, the noise-free check gives the target power within
    # 10 %, an excess within 0.005 of a 10 % target: a fifth of the record's own sampling
    # error (0.015-0.024), immaterial to the concealment
    for seed in (21, 23, 24, 28):
        scenario = conceal(draw(seed, 'single'))
        (c,) = scenario.concealed
        assert EXCESS_RANGE[0] <= c.target_excess <= EXCESS_RANGE[1]
        if c.capped:
            continue
        wanted = (1.0 + c.target_excess) ** 2 - 1.0
        power = residual_power(scenario, c)
        assert abs(power / wanted - 1.0) <= 0.1, (seed, c.knob, power, wanted)


#: The CI sample: seeds outside the study's range (1-300), kinds stratified so that the
#: false-alarm claim always has nulls to stand on (an unstratified draw of five would hold
#: no null with probability 0.8⁵ = 0.33). Its size is what a minute of CPU buys with the
#: engine of today (a null diagnoses in seconds, one effect in up to a minute, a pair in
#: more: bench/results/calibration.md); a faster engine affords more records, and the
#: bounds below follow n. At n = 5 they catch only a gross failure: 3 of 5 confidently
#: wrong (P = 0.001 at 5 %) or 2 of 3 false alarms (P = 0.001 at 2 %).
CI_DRAWS = ((90001, 'null'), (90002, 'null'), (90003, 'null'), (90004, 'single'),
            (90005, 'single'))


def _check_bounds(lines, bench):
    errors = [line for line in lines if 'error' in line]
    assert not errors, errors
    high = [line for line in lines
            if line['verdict'] != 'unexplained' and line['probability'] >= bench.HIGH]
    wrong = [line for line in high if not line['right']]
    assert len(wrong) <= bench.binomial_bound(len(high), 1 - bench.TARGET_ACCURACY_HIGH), [
        (line['seed'], line['draw']['truth'], line['named_text']) for line in wrong]
    nulls = [line for line in lines if line['draw']['kind'] == 'null']
    alarms = [line for line in nulls if line['verdict'] not in ('none', 'unexplained')]
    assert len(alarms) <= bench.binomial_bound(len(nulls), bench.TARGET_FALSE_ALARMS), [
        (line['seed'], line['named_text']) for line in alarms]


def test_calibration_bounds_on_a_ci_sample():
    bench = _bench()
    _check_bounds([bench.run_one(seed, kind) for seed, kind in CI_DRAWS], bench)


@pytest.mark.slow
@pytest.mark.study
def test_calibration_study():
    bench = _bench()
    import multiprocessing
    with multiprocessing.get_context('fork').Pool(2) as pool:
        lines = pool.starmap(bench.run_one, [(seed, None) for seed in range(1, 301)])
    _check_bounds(lines, bench)
