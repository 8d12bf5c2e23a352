"""
The catalogue's augmentations on rotors other than the report's (any N, μ > 0, δ3).

They wrap the general model (docs/models.md), so their analytic sensitivities must equal finite
differences of the simulator for 3- and 5-bladed rotors in forward flight with pitch-flap
coupling, and the dynamic-inflow candidate must be the wake model itself.
"""

import numpy as np
import pytest
from rotor_id.estimation.output_error import ExtendedInput
from rotor_id.estimation.simulate import simulate
from rotor_id.physics import augmented as aug
from rotor_id.physics.models import build_model, RotorConstants
import test_diagnosis_augmentations as four_blades  # noqa: I100

T = four_blades.T
BASES = [('multiblade', 3, 0.3, {}), ('multiblade_constant', 5, 0.3, {}),
         ('multiblade_wake', 3, 0.25, {'outputs': 'blades'}), ('multiblade_wake', 5, 0.0, {})]


def _base(name, n_blades, mu, options):
    rotor = RotorConstants(n_blades=n_blades, advance_ratio=mu, pitch_flap_coupling=0.2)
    return build_model(name, rotor, collective='theta0', angle_unit='rad', **options)


def _inputs(n_blades):
    k = np.arange(1, n_blades + 1)
    extra = 0.02 + 0.01 * np.cos(np.outer(T, k) + k)
    return ExtendedInput(four_blades.SCHEDULE, T, extra)


@pytest.mark.parametrize('name,n_blades,mu,options', BASES)
def test_sensitivities_equal_finite_differences(name, n_blades, mu, options):
    base = _base(name, n_blades, mu, options)
    rng = np.random.default_rng(5)
    for model in four_blades._augmented(base):
        four_blades.check_sensitivities(model, _inputs(n_blades), rng)


@pytest.mark.parametrize('n_blades,mu', [(3, 0.3), (5, 0.0)])
def test_dynamic_inflow_candidate_is_the_wake_model(n_blades, mu):
    """The γ-model plus the wake candidate equals the wake model with A = γB⁴/8."""
    rotor = RotorConstants(n_blades=n_blades, advance_ratio=mu)
    base = build_model('multiblade', rotor, outputs='blades')
    candidate = aug.DynamicInflow(base)
    wake = build_model('multiblade_wake', rotor, outputs='blades')
    gamma, theta0, c, r = 5.5, 0.04, 0.3, 0.1
    p_candidate = candidate.parameter_vector({'gamma': gamma, 'theta0': theta0,
                                              'AL_over_tau': c, 'inv_tau': r})
    p_wake = wake.parameter_vector({'A': gamma * rotor.tip_loss**4 / 8, 'theta0': theta0,
                                    'AL_over_tau': c, 'inv_tau': r})
    x0 = 0.01 * np.random.default_rng(1).standard_normal(wake.n_states)
    order = [wake.state_names.index(n) for n in candidate.state_names]
    y_wake = simulate(wake, p_wake, four_blades.SCHEDULE, T, x0).y
    y_candidate = simulate(candidate, p_candidate, four_blades.SCHEDULE, T, x0[order]).y
    np.testing.assert_allclose(y_candidate, y_wake, atol=1e-12)


def test_nested_candidates_equal_finite_differences():
    """Two effects at once: the wake over a sensor lag, an odd blade over the wake."""
    base = _base('multiblade', 3, 0.3, {'outputs': 'blades'})
    rng = np.random.default_rng(9)
    for model in (aug.DynamicInflow(aug.SensorLag(base)),
                  aug.BladeDissimilarity(aug.DynamicInflow(base), 2)):
        four_blades.check_sensitivities(model, _inputs(3), rng)


@pytest.mark.study
def test_diagnose_names_the_wake_of_a_three_bladed_rotor_in_forward_flight():
    """Independent truth (N = 3, μ = 0.3, δ3), wake-free baseline: the wake is named, in bounds."""
    from rotor_id.diagnosis.diagnose import diagnose
    from rotor_id.io.run_description import parse_run_description
    from truth_generator import generate, run_description_text, TruthConfig
    cfg = TruthConfig(n_blades=3, mu=0.3, gamma=6.0, pitch_flap=0.2, t0=20.0, wake_L=3.0,
                      wake_tau=6.0, sensor_bias=[0.0] * 3, gamma_scale=[1.0] * 3,
                      pitch_offset=[0.0] * 3, seed=4)
    text = (run_description_text(cfg, 'multiblade', ['gamma', 'theta0'], guess=False)
            + f'measurement: blades\nnoise_std_rad: {cfg.flap_noise}\n')
    result = diagnose(generate(cfg), parse_run_description(text), workers=1).as_json()
    explanation = result['explanation']
    assert result['mismatch'] and explanation['effect'] == 'dynamic_inflow'
    A = cfg.gamma * cfg.tip_loss**4 / 8
    truth = {'A': A, 'AL_over_tau': A * cfg.wake_L / cfg.wake_tau, 'inv_tau': 1 / cfg.wake_tau}
    for name, value in truth.items():
        estimate = explanation['parameters'][name]
        assert abs(estimate['value'] - value) < 4 * estimate['std'], (name, estimate, value)


@pytest.mark.study
def test_a_three_bladed_rotors_sensor_offsets_in_forward_flight_are_not_a_pitch_flap_coupling():
    """
    N = 3, μ = 0.4, periodic terms and per-blade sensor biases with a common part: both named.

    In forward flight θ0 also drives the once-per-rev flap, so it cannot absorb the biases'
    common part (it moves β0 alone). Without that pattern in the bias candidate, what was left
    of it let δ3 in at high confidence (2Δlog L = 20.8 on this seed).
    """
    from rotor_id.diagnosis.diagnose import diagnose
    from rotor_id.io.run_description import parse_run_description
    from truth_generator import generate, mu04_case, run_description_text
    bias = [6.8e-4, -3.4e-4, 5.1e-4]                # common part 2.8e-4 rad
    cfg = mu04_case(seed=1000, n_blades=3, sensor_bias=bias, gamma_scale=[1.0] * 3,
                    pitch_offset=[0.0] * 3, sensor_gain=[0.0] * 3)
    text = run_description_text(cfg, 'multiblade_constant', ['gamma', 'theta0'])
    result = diagnose(generate(cfg), parse_run_description(text), workers=1).as_json()
    named = {e['effect']: e for e in result['explanation']['effects']}
    assert set(named) == {'periodic_coefficients', 'sensor_bias'}, list(named)
    for k, b in enumerate(bias, start=1):
        estimate = named['sensor_bias']['parameters'][f'bias_{k}']
        assert abs(estimate['value'] - b) < 4 * estimate['std'], (k, estimate, b)


@pytest.mark.parametrize('n_blades, mu, name, outputs', [
    (3, 0.0, 'multiblade', 'multiblade'), (4, 0.0, 'multiblade_wake', 'multiblade'),
    (5, 0.0, 'multiblade', 'blades'), (4, 0.3, 'multiblade', 'multiblade'),
    (5, 0.35, 'multiblade_constant', 'eq30'), (4, 0.0, 'single_blade', 'multiblade')])
def test_sensor_lag_in_flap_coordinates_is_the_blade_form(n_blades, mu, name, outputs,
                                                          monkeypatch):
    """The sensor lag carried in the flap's coordinates simulates as the per-blade lag."""
    options = {} if name == 'single_blade' else {'outputs': outputs}
    base = build_model(name, RotorConstants(n_blades=n_blades, advance_ratio=mu),
                       collective='theta0', angle_unit='rad', **options)
    coordinates = aug.SensorLag(base)
    monkeypatch.setattr(aug, 'flap_basis', lambda view: None)
    blades = aug.SensorLag(base)
    if name != 'single_blade':
        assert coordinates.constant_terms() and not blades.constant_terms()
    if mu == 0.0 and name != 'single_blade':
        F, _ = coordinates.system_compact(T, coordinates.nominal(), four_blades.SCHEDULE(T))
        assert F.shape[0] == 1                          # time-invariant over a hover rotor
    p = coordinates.nominal().copy()
    p[-1] = 0.2                                         # τ_s
    x0 = np.zeros(coordinates.n_states)
    x0[:base.n_states] = 0.01 * np.cos(np.arange(base.n_states))
    index = list(range(len(p)))
    # the same ODE: the two RK4 solutions differ by the step's truncation (h⁴), under 1e-9
    # of the signal at h = 0.00625 (6e-7 at the default 0.05)
    a = simulate(coordinates, p, four_blades.SCHEDULE, T, x0, param_index=index,
                 max_step=0.00625)
    b = simulate(blades, p, four_blades.SCHEDULE, T, np.concatenate(
        [x0[:base.n_states], np.zeros(blades.n_states - base.n_states)]), param_index=index,
        max_step=0.00625)
    assert np.abs(a.y - b.y).max() < 1e-8 * np.abs(b.y).max()
    assert np.abs(a.dy - b.dy).max() < 1e-7 * np.abs(b.dy).max()
