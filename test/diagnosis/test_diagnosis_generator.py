"""
The truth generator is a faithful stand-in for the test stand; the noise floor is model-free.

The generator (an independent blade-by-blade simulation) must reproduce the four given dx_*
recordings, noise-free, to within their flap noise: then the concealed-effect recordings of the
study are of the same kind as the hidden ones. The noise-floor estimator must recover the
generator's flap noise from the data alone.
"""

import json
import math

import numpy as np
from practice import RECORDINGS, require_practice
import pytest
from rotor_id.residuals import blade_noise_floor, ljung_box
from truth_generator import generate, TruthConfig, wake_case


def _answers():
    path = require_practice() / 'answers.json'
    return json.loads(path.read_text())


@pytest.mark.parametrize('name', ['dx_none_wake', 'dx_periodic_coefficients',
                                  'dx_sensor_lag', 'dx_dynamic_inflow'])
def test_generator_reproduces_given_recordings(name):
    from rotor_id.io.bag import read_run
    from rotor_id.io.run_description import load_run_description
    truth = dict(_answers()[name]['truth'])
    noise = truth['flap_noise']
    truth.update(flap_noise=0.0, pitch_noise=0.0)
    record = generate(TruthConfig(**truth))
    given = read_run(load_run_description(RECORDINGS / f'{name}.yaml'))
    assert len(record) == len(given)
    np.testing.assert_allclose(record.t, given.t, atol=1e-9)
    diff = given.blade_flap - record.blade_flap
    # what is left is the recording's white flap noise: its σ, and no structure
    ratio = np.std(diff, axis=0) / noise
    assert np.all(np.abs(ratio - 1.0) < 0.1), ratio
    for k in range(4):
        assert ljung_box(diff[:, k])[1] > 1e-4
    pitch_noise = _answers()[name]['truth']['pitch_noise']
    assert np.max(np.abs(given.blade_pitch - record.blade_pitch)) < 6 * pitch_noise


def test_noise_floor_recovers_the_flap_noise_without_a_model():
    sigmas = []
    for seed in range(5):
        cfg = wake_case(seed=seed, flap_noise=math.radians(0.05))
        sigmas.append(blade_noise_floor(generate(cfg).blade_flap))
    sigmas = np.array(sigmas) / math.radians(0.05)
    # each σ̂ from 1065 third differences: var(σ̂²)/σ⁴ = 2·2.31/1065, so SE(σ̂) ≈ 3.3 %;
    # the mean of 20 has SE ≈ 0.74 %. Bounds at about 4 SE.
    assert abs(np.mean(sigmas) - 1.0) < 0.03
    assert np.all(np.abs(sigmas - 1.0) < 0.13)


def test_turbulent_record_integrated_knot_by_knot_matches_one_adaptive_run():
    # the turbulence is piecewise linear between knots 0.02 rad apart; the generator restarts
    # its DOP853 at each knot (≈ 10× fewer steps than one adaptive run stepping over the kinks).
    # A short record integrated both ways: they agree to far below the flap noise (0.05° =
    # 8.7e-4 rad). Measured once against rtol 1e-12: knot by knot 1.7e-10 rad off, one adaptive
    # run 1.5e-8 (its error estimate does not hold across a kink).
    from scipy.integrate import solve_ivp
    from truth_generator import _GaussMarkov, _integrate_between_knots, _rhs_factory
    cfg = wake_case(turbulence=0.0004, t_step=1.0, t0=1.0, sensor_lag=0.05)
    rng = np.random.default_rng(3)
    turbulence = _GaussMarkov(cfg.turbulence, cfg.turbulence_corr, -3.0, 8.0, rng)
    rhs = _rhs_factory(cfg, turbulence)
    s0 = np.zeros(4 * cfg.n_blades + 2)
    s0[3 * cfg.n_blades + 2:] = cfg.theta0
    t_eval = np.arange(0.0, 6.0, 0.0942477796)
    knots = _integrate_between_knots(rhs, s0, -2.0, 6.0, t_eval, turbulence.t)
    one = solve_ivp(rhs, (-2.0, 6.0), s0, method='DOP853', t_eval=t_eval, rtol=1e-9,
                    atol=1e-12, max_step=0.05).y.T
    flap = slice(0, cfg.n_blades)
    assert np.abs(knots[:, flap]).max() > 1e-3               # the blades flap
    assert np.abs(knots - one).max() < 1e-7
    assert np.abs(knots - one).max() > 0.0                    # not the same integration


def test_truth_cache_returns_the_generated_record_and_keys_on_the_truth(tmp_path, monkeypatch):
    import truth_generator
    monkeypatch.setenv(truth_generator.CACHE_ENV, str(tmp_path))
    cfg = wake_case(t_settle=5.0, t0=3.0, t_stir=2.0, seed=7)
    first = generate(cfg)
    assert len(list(tmp_path.glob('truth_*.npz'))) == 1
    again = generate(cfg)
    for name in ('time_s', 't', 'rotor_speed_rad_s', 'blade_flap', 'blade_pitch'):
        np.testing.assert_array_equal(getattr(again, name), getattr(first, name))
    assert again.blade_names == first.blade_names
    other = generate(cfg.with_(seed=8))
    assert len(list(tmp_path.glob('truth_*.npz'))) == 2
    assert not np.array_equal(other.blade_flap, first.blade_flap)
    assert truth_generator.cache_key(cfg) != truth_generator.cache_key(cfg.with_(sensor_lag=0.01))
