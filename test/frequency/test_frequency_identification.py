"""
``identify --method frequency-response`` beside output error (pins #37).

On the report's wake case (config/report_wake_*.yaml, the package's simulator) and on a
recording of the independent blade-by-blade generator the two estimates agree within their
combined bounds, and each is within its bounds of the truth.
"""

import math
from pathlib import Path
import sys

import numpy as np
import pytest
from rotor_id import pipeline
from rotor_id.io.run_description import load_run_description, parse_run_description
from rotor_id.report import cases as C

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'diagnosis'))
from truth_generator import generate, mu04_case, run_description_text, wake_case  # noqa: E402,I100

WAKE_TRUTH = {'A': 0.5, 'AL_over_tau': 0.25, 'inv_tau': 0.125}


def _both(record, description):
    oe = pipeline.identify(record, description, multi_start=False)
    fr = pipeline.identify(record, description, method='frequency-response')
    return oe, fr


def _assert_agree(oe, fr, truth, limit=3.0):
    assert oe.estimate.converged and fr.estimate.converged
    assert fr.estimate.method == 'frequency-response'
    for name, value in truth.items():
        a, sa = oe.estimate.value(name), oe.estimate.std_of(name)
        b, sb = fr.estimate.value(name), fr.estimate.std_of(name)
        assert abs(a - b) < limit * math.hypot(sa, sb), (name, a, sa, b, sb)
        assert abs(b - value) < limit * sb, (name, b, sb, value)
        assert 0.0 < sb < abs(value), (name, sb)          # a real bound, not a blank


@pytest.mark.parametrize('direction', ['progressing', 'regressing'])
def test_report_wake_case_agrees_with_output_error(repo_root, direction):
    """The report's wake case, its stirring continued to t = 94 (1.5 per rev), σ = 0.1°·√2."""
    description = load_run_description(repo_root / 'config' / f'report_wake_{direction}.yaml')
    record = C.report_record(f'wake_{direction}', t_end=94.0, dt=0.05,
                             blade_noise_std_deg=0.1 * math.sqrt(2.0), seed=11)
    oe, fr = _both(record, description)
    _assert_agree(oe, fr, WAKE_TRUTH)
    data = fr.as_json()
    assert data['method'] == 'frequency-response'
    assert data['frequency_response']['cost_J'] < 100.0
    assert data['frequency_response']['points'] >= 10


def test_independent_generator_recording_agrees_with_output_error():
    cfg = wake_case(seed=23)
    record = generate(cfg)
    description = parse_run_description(run_description_text(
        cfg, 'multiblade_wake', ['A', 'AL_over_tau', 'inv_tau'], window_s=(0.8094, 0.9367)))
    oe, fr = _both(record, description)
    _assert_agree(oe, fr, WAKE_TRUTH)


def test_periodic_model_at_mu_04_agrees_with_output_error():
    """μ = 0.4, periodic model: γ by J on the dFRF, θ0 alone in the time domain (said so)."""
    cfg = mu04_case(seed=5)
    record = generate(cfg)
    description = parse_run_description(run_description_text(
        cfg, 'multiblade', ['gamma', 'theta0'], window_s=(0.194, 0.3213)))
    oe, fr = _both(record, description)
    _assert_agree(oe, fr, {'gamma': cfg.gamma, 'theta0': cfg.theta0})
    assert any('constant input' in w for w in fr.warnings)


def test_too_few_coherent_points_is_one_clear_error():
    """A sweep that barely turns leaves too few frequencies: one line, before fitting."""
    cfg = wake_case(seed=2, t_stir=9.0)
    record = generate(cfg)
    description = parse_run_description(run_description_text(
        cfg, 'multiblade_wake', ['A', 'AL_over_tau', 'inv_tau']))
    with pytest.raises(ValueError) as err:
        pipeline.identify(record, description, method='frequency-response')
    assert '\n' not in str(err.value)
    assert np.isfinite(len(str(err.value)))
