"""
The directional frequency response (pins #37): the model's transfer function, the estimate.

* the transfer function of the linear model in complex coordinates is the steady response to
  a rotating cyclic pitch, time-invariant and periodic (harmonic transfer function);
* on a noise-free simulated sweep the estimate matches it to 1 % and 1° where γ² > 0.9;
* on a sweep cut off by the end of the record (the report's, made by the independent
  blade-by-blade simulator) the estimate matches the model through the same estimate, and the
  difference from the transfer function is said, with its size;
* with noise the scatter of the estimate matches its stated random error (a CI-sized Monte
  Carlo whose bound comes from the sampling distribution of the statistic; the full study
  under ROTOR_ID_SLOW=1).
"""

import math
from pathlib import Path
import sys

import numpy as np
import pytest
from rotor_id import pipeline
from rotor_id.estimation.frequency_response import (cifer_cost, coherence_weight,
                                                    estimate_frequency_response,
                                                    estimated_model_response, random_error,
                                                    sweep_from_record)
from rotor_id.estimation.simulate import simulate
from rotor_id.physics.models import build_model, directional_frequency_response, RotorConstants

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'diagnosis'))
from frequency_helpers import COLLECTIVE, sweep_record  # noqa: E402,I100
from truth_generator import generate, wake_case  # noqa: E402,I100

WAKE = build_model('multiblade_wake', RotorConstants(advance_ratio=0.0))
PERIODIC = build_model('multiblade', RotorConstants(advance_ratio=0.4))


def _steady_response(model, p, omega, revolutions=40, harmonics=(0,)):
    """Least-squares amplitude of e^{i(ω+n)t} in β_c after the transient, θ_c = e^{iωt}/100."""
    amplitude = 0.01

    def inputs(t):
        t = np.atleast_1d(t)
        c = amplitude * np.exp(1j * omega * t)
        return np.column_stack([np.full(t.size, COLLECTIVE), c.real, c.imag])
    t = np.arange(0.0, 2.0 * math.pi * revolutions, 0.02)
    x = simulate(model, p, inputs, t, np.zeros(model.n_states)).x
    names = list(model.state_names)
    flap = x[:, names.index('beta_I')] + 1j * x[:, names.index('beta_II')]
    late = t > 0.6 * t[-1]                          # the slow mode has decayed by e^-12
    tl = t[late]
    columns = [np.exp(1j * (omega + n) * tl) for n in harmonics]
    columns += [np.exp(-1j * (omega + n) * tl) for n in harmonics]
    columns.append(np.ones(tl.size))
    coef, *_ = np.linalg.lstsq(np.column_stack(columns), flap[late], rcond=None)
    return coef[:len(harmonics)] / amplitude


@pytest.mark.parametrize('omega', [0.7, -0.3])
def test_transfer_function_is_the_steady_response_of_the_wake_model(omega):
    p = WAKE.nominal()
    H = directional_frequency_response(WAKE, p, [omega]).principal[0]
    steady = _steady_response(WAKE, p, omega)[0]
    assert abs(steady / H - 1.0) < 1e-6


def test_harmonic_transfer_function_is_the_steady_response_of_the_periodic_model():
    """μ = 0.4: the principal response and the 4/rev sidebands, against a simulation."""
    # θ0 = 0: no periodic trim response beside the one to the cyclic input
    p = PERIODIC.parameter_vector({'gamma': 5.0, 'theta0': 0.0})
    omega = 0.6
    response = directional_frequency_response(PERIODIC, p, [omega])
    steady = _steady_response(PERIODIC, p, omega, harmonics=(0, 4, -4))
    assert abs(steady[0] / response.principal[0] - 1.0) < 1e-6
    for value, n in zip(steady[1:], (4, -4)):
        assert abs(value - response.sidebands[n][0]) < 1e-6 * abs(response.principal[0])
        # the periodic coefficients do make sidebands here (the check is not of zeros)
        assert abs(response.sidebands[n][0]) > 1e-4 * abs(response.principal[0])


def test_transfer_function_jacobian_matches_differences():
    p = WAKE.nominal()
    omega = np.array([-0.9, -0.13, 0.4, 1.3])
    response = directional_frequency_response(WAKE, p, omega, jacobian=True)
    for j in range(p.size):
        h = 1e-6
        up, down = p.copy(), p.copy()
        up[j] += h
        down[j] -= h
        numeric = (directional_frequency_response(WAKE, up, omega).principal
                   - directional_frequency_response(WAKE, down, omega).principal) / (2 * h)
        np.testing.assert_allclose(response.jacobian[:, j], numeric, rtol=1e-6, atol=1e-8)


def test_models_without_cyclic_flap_are_refused_in_one_line():
    blade = build_model('single_blade', RotorConstants())
    with pytest.raises(ValueError, match='no fixed-frame cyclic flap'):
        directional_frequency_response(blade, blade.nominal(), [0.5])


@pytest.mark.parametrize('model, omegadot', [
    (WAKE, -0.01 / math.pi), (WAKE, 0.01 / math.pi),
    (build_model('multiblade_constant', RotorConstants(advance_ratio=0.3)), -0.01 / math.pi),
    (PERIODIC, -0.01 / math.pi)])
def test_noise_free_sweep_matches_the_transfer_function(model, omegadot):
    """
    A slow sweep ending in trim: 1 % in magnitude and 1° in phase where γ² > 0.9.

    A rotor in forward flight is not axisymmetric: it also answers θ_c(−ω) at ω (the mirror
    response, 10 % of the direct one here), and the lateral-cyclic step puts input at −ω. So
    for μ > 0 the claim holds where that mirror input is below 0.1 % of the direct input (the
    estimate reports it per point; a model through the same estimate carries it alike).
    """
    p = model.parameter_vector({'theta0': COLLECTIVE} if 'theta0' in model.parameter_names
                               else {})
    record = sweep_record(model, p, omegadot, t_end=420.0, stirring=240.0)
    sweep = sweep_from_record(record)
    assert (sweep.band[0] > 0) == (omegadot < 0)        # progressing: positive frequencies
    estimate = estimate_frequency_response([sweep])
    H = directional_frequency_response(model, p, estimate.frequency_per_rev).principal
    good = estimate.coherence > 0.9
    assert good.sum() > 0.9 * good.size >= 80
    if model.rotor.advance_ratio > 0:
        good &= estimate.spectra.mirror_input < 1e-3
        assert good.sum() >= 25
    ratio = estimate.response[good] / H[good]
    assert np.max(np.abs(np.abs(ratio) - 1.0)) < 0.01
    assert np.max(np.abs(np.degrees(np.angle(ratio)))) < 1.0


@pytest.fixture(scope='module')
def truncated_wake():
    """Return the report's μ = 0 wake case by the blade-by-blade generator (cut off at 24)."""
    return generate(wake_case(flap_noise=0.0, pitch_noise=0.0, seed=3))


def test_cut_off_sweep_matches_the_model_through_the_same_estimate(truncated_wake):
    sweep = sweep_from_record(truncated_wake)
    estimate = estimate_frequency_response([sweep])
    p = WAKE.nominal()
    through, _ = estimated_model_response(WAKE, p, [sweep], estimate.spectra, COLLECTIVE)
    good = estimate.coherence > 0.9
    assert good.sum() >= 15
    assert np.max(np.abs(estimate.response[good] / through[good] - 1.0)) < 0.01
    # ... while the transfer function is off by far more: the stirring's end is cut off
    H = directional_frequency_response(WAKE, p, estimate.frequency_per_rev).principal
    assert np.max(np.abs(estimate.response[good] / H[good] - 1.0)) > 0.1


def test_cut_off_sweep_is_reported_with_its_transient_error(truncated_wake, tmp_path):
    from rotor_id.io.run_description import parse_run_description
    from truth_generator import run_description_text
    cfg = wake_case()
    description = parse_run_description(run_description_text(
        cfg, 'multiblade_wake', ['A', 'AL_over_tau', 'inv_tau'], window_s=(0.8094, 0.9367)))
    analysis = pipeline.frequency_analysis([(truncated_wake, description, 'run')])
    overlay = analysis.overlay
    assert overlay.cost < 5.0                          # the right model, seen alike
    assert overlay.cost_transfer_function > 3 * overlay.cost
    assert any('same estimate' in w for w in analysis.warnings)
    data = analysis.as_json()
    assert len(data['model']['transient_error']) == len(data['frequency_per_rev'])


def test_cifer_cost_weights():
    """J of a 1 dB / 7.57° error at γ² = 1 is 20·W_γ(1)·2 (W_p·7.57² = 1)."""
    measured = np.array([1.0 + 0j])
    model = 10 ** (1 / 20) * np.exp(1j * math.radians(math.sqrt(1 / 0.01745)))
    w = coherence_weight(1.0)
    assert w == pytest.approx((1.58 * (1 - math.exp(-1))) ** 2)
    assert cifer_cost(measured, np.array([model]), np.array([1.0])) == pytest.approx(40 * w)


def test_random_error_is_bendat_and_piersol():
    assert random_error(0.8, 4) == pytest.approx(math.sqrt(0.2) / (math.sqrt(0.8) * math.sqrt(8)))


def _scatter_ratio(draws, seed0):
    """Σ |Ĥ/H₀ − 1|² over Σ 2 ε̂² for ``draws`` noisy copies of one sweep (expect 1)."""
    p = WAKE.nominal()
    clean = sweep_record(WAKE, p, -0.02 / math.pi, t_end=220.0, stirring=120.0)
    reference = estimate_frequency_response([sweep_from_record(clean)])
    observed, stated, count = 0.0, 0.0, 0
    for d in range(draws):
        noisy = sweep_record(WAKE, p, -0.02 / math.pi, t_end=220.0, stirring=120.0,
                             noise=0.003, seed=seed0 + d)
        est = estimate_frequency_response([sweep_from_record(noisy)],
                                          frequency=reference.frequency_per_rev)
        observed += np.sum(np.abs(est.response / reference.response - 1.0) ** 2)
        stated += np.sum(2.0 * est.random_error ** 2)
        count += est.response.size
    return observed / stated, count


def test_scatter_matches_the_stated_random_error_ci():
    """
    40 draws: the ratio of the observed to the stated variance is 1 within its sampling spread.

    Each |Ĥ/H₀ − 1|²/(2ε²) is an exponential draw (mean 1, variance 1) for a complex Gaussian
    error, so the ratio of sums over n points has a standard deviation of about 1/√n; the
    stated ε̂ itself is estimated with three degrees of freedom, which adds about as much again.
    The bound is four of those. The noise (0.003 rad per blade against a 0.026 rad cyclic)
    keeps ε_r near 5 %, where Bendat & Piersol's first-order formula applies (at ε_r ≈ 20 % the
    noise in |Ĥ|² of its denominator overstates ε_r² by about 10 %).
    """
    ratio, n = _scatter_ratio(40, 100)
    assert abs(ratio - 1.0) < 4.0 * math.sqrt(2.0 / n), (ratio, n)


@pytest.mark.study
def test_scatter_matches_the_stated_random_error_study():
    """The same at 400 draws: a bound ten times tighter in variance."""
    ratio, n = _scatter_ratio(400, 10_000)
    assert abs(ratio - 1.0) < 4.0 * math.sqrt(2.0 / n), (ratio, n)


def test_a_window_of_several_tests_is_one_line_before_any_spectrum():
    """An hour-like window would need gigabytes: refused at once, naming the window."""
    import time
    record = sweep_record(WAKE, WAKE.nominal(), -0.01 / math.pi, t_end=4000.0, stirring=240.0,
                          dt=0.2)
    sweep = sweep_from_record(record)
    started = time.process_time()
    with pytest.raises(ValueError, match='too long for a frequency response') as err:
        estimate_frequency_response([sweep])
    assert '\n' not in str(err.value) and '--window-s' in str(err.value)
    assert time.process_time() - started < 1.0
