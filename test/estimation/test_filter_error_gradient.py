"""
Filter error's analytic sensitivities against finite differences.

* the gradient of the likelihood J(θ) from the analytic ∂ν, ∂B equals central differences of J
  itself (the filter run at θ ± h e_i) for every kind of unknown: model parameters (through
  Φ, Q, the forcing and the equilibrium initial state), the process-noise variance, the
  measurement σ's and free initial states; with the rotating measurement and the time-varying
  gain (wake model), and with the steady-state gain (constant-coefficient model);
* the same for a periodic model (μ = .4: Φ_j, Q_j per interval), whose Φ_j, Q_j and their
  derivatives summed as Fourier series of the interval's azimuth equal the intervals' own
  (∂Q, a forward difference of Q, to that difference's rounding);
* the compiled scan and its numpy twin give the same numbers;
* the sensitivities along some of the model parameters alone are those columns of all of them
  (wake, steady gain, periodic; equilibrium initial states, whose ∂x0 moves with them);
* the fit with analytic gradients lands on the finite-difference fit's optimum.
"""

import numpy as np
import pytest
from rotor_id.estimation import filter_error as fe
from rotor_id.estimation import kernels
from rotor_id.estimation.output_error import Experiment
from rotor_id.estimation.simulate import fine_grid, simulate, substeps_for
from rotor_id.physics.models import Multiblade, MultibladeConstant, RotorConstants
from rotor_id.physics.revolution import Series, system_on_record
from rotor_id.physics.stirring import StirringSchedule
from test_filter_error import GUESS, PROGRESSING, T_WAKE, UNKNOWNS, WAKE, wake_data


def _wake_problem(noise_model, initial_state, noise_std=None):
    exp = Experiment(WAKE, PROGRESSING, T_WAKE, wake_data(3, 0.1, 0.05),
                     initial_state=initial_state)
    prob = fe.FilterProblem([exp], UNKNOWNS, GUESS, None, noise_std, None, True, None,
                            noise_model, 'auto', 0.05)
    theta = np.zeros(len(prob.names))
    theta[:3] = [0.45, 0.22, 0.2]
    if initial_state == 'positions':
        theta[3:prob.n_base] = [0.1, -0.05, 0.02, 0.03]
    theta[prob.i_process] = 0.07**2
    if prob.i_meas is not None:
        theta[prob.i_meas] = [0.05, 0.06]
    prob.scale = np.maximum(np.abs(theta), 1e-3)
    return prob, theta


def _constant_problem():
    model = MultibladeConstant(RotorConstants(), collective='delta', angle_unit='deg')
    sched = StirringSchedule(t0=12.0)
    t = 12.0 + 0.1 * np.arange(121)
    p = np.array([5.0, 10.0])
    rng = np.random.default_rng(1)
    forcing = np.zeros((120, 6))
    forcing[:, 3:] = 0.3 * rng.standard_normal((120, 3))
    x0 = model.equilibrium(t[:1], p, sched(t[:1]))
    y = simulate(model, p, sched, t, x0, forcing=forcing).y + 0.05 * rng.standard_normal((121, 3))
    exp = Experiment(model, sched, t, y, initial_state='equilibrium')
    prob = fe.FilterProblem([exp], ['gamma', 'delta'], {'gamma': 4.5, 'delta': 9.0}, None,
                            None, None, True, None, 'held', 'auto', 0.05)
    theta = np.array([4.5, 9.0, 0.25**2, 0.05, 0.04, 0.06])
    prob.scale = np.maximum(np.abs(theta), 1e-3)
    return prob, theta


def _periodic_problem(noise_model, samples=121):
    model = Multiblade(RotorConstants(advance_ratio=0.4))
    p = model.nominal()
    sched = StirringSchedule(t0=12.0)
    t = 12.0 + 0.1 * np.arange(samples)
    x0 = model.equilibrium(t[:1], p, sched(t[:1]))
    rng = np.random.default_rng(2)
    forcing = np.zeros((samples - 1, model.n_states))
    forcing[:, 4:] = 0.2 * rng.standard_normal((samples - 1, model.n_states - 4))
    y = simulate(model, p, sched, t, x0, forcing=forcing).y
    y = y + 0.05 * rng.standard_normal(y.shape)
    exp = Experiment(model, sched, t, y, initial_state='equilibrium')
    names = list(model.parameter_names[:2])
    prob = fe.FilterProblem([exp], names, None, None, None, None, True, None, noise_model,
                            'auto', 0.05)
    theta = np.zeros(len(prob.names))
    theta[:2] = 1.1 * p[:2]
    theta[prob.i_process] = 0.2**2
    theta[prob.i_meas] = 0.05
    prob.scale = np.maximum(np.abs(theta), 1e-3)
    return prob, theta


def _gradient_check(prob, theta):
    """Largest |analytic − central difference| of ∂J/∂θ_i, relative to |∂J/∂θ_i|."""
    results = prob.evaluate(theta)
    grad, M = fe.gradient_information(results, len(theta))
    worst = 0.0
    for i in range(len(theta)):
        h = 1e-5 * max(abs(theta[i]), prob.scale[i])
        up, down = theta.copy(), theta.copy()
        up[i] += h
        down[i] -= h
        fd = (fe.innovations_cost(prob.evaluate(up, sensitivities=False))
              - fe.innovations_cost(prob.evaluate(down, sensitivities=False))) / (2 * h)
        worst = max(worst, abs(grad[i] - fd) / max(abs(fd), 1e-3 * np.sqrt(M[i, i])))
    return worst, results


@pytest.mark.parametrize('noise_model, initial_state',
                         [('held', 'equilibrium'), ('white', 'positions')])
def test_analytic_gradient_matches_differences_of_the_likelihood(noise_model, initial_state):
    """Wake model: rotating H, time-varying gain; every kind of unknown."""
    prob, theta = _wake_problem(noise_model, initial_state)
    assert prob.analytic_sensitivities(0, theta) is not None        # the analytic path runs
    worst, _ = _gradient_check(prob, theta)
    assert worst < 1e-5


def test_analytic_gradient_with_the_steady_state_gain():
    prob, theta = _constant_problem()
    dm, _, _ = prob.discretized(0, theta)
    assert prob.gain_mode(dm) == 'steady'
    worst, _ = _gradient_check(prob, theta)
    assert worst < 1e-5


@pytest.mark.parametrize('noise_model', ['held', 'white'])
def test_analytic_gradient_for_a_periodic_model(noise_model):
    """μ = .4: F, Φ_j and Q_j vary over the revolution; time-varying gain."""
    prob, theta = _periodic_problem(noise_model)
    dm, _, _ = prob.discretized(0, theta)
    assert not dm.time_invariant
    assert prob.analytic_sensitivities(0, theta) is not None
    worst, _ = _gradient_check(prob, theta)
    assert worst < 1e-5


@pytest.mark.parametrize('make', [lambda: _wake_problem('held', 'equilibrium'),
                                  lambda: _wake_problem('white', 'positions'),
                                  _constant_problem, lambda: _periodic_problem('white')])
def test_sensitivities_along_some_parameters_are_those_columns(make):
    prob, theta = make()
    everything = prob.evaluate(theta)
    for columns in ([1], [0, 1]):
        some = prob.evaluate(theta, columns=columns)
        for (nu, B, dnu, dB, cost), (nu1, B1, dnu1, dB1, cost1) in zip(everything, some):
            # (the steady gain's Riccati solution differs by rounding with fewer directions)
            np.testing.assert_allclose(nu1, nu, rtol=0.0, atol=1e-12 * np.max(np.abs(nu)))
            np.testing.assert_allclose(B1, B, rtol=0.0, atol=1e-12 * np.max(np.abs(B)))
            assert cost1 == pytest.approx(cost, rel=1e-12)
            assert dnu1.shape[-1] == dB1.shape[-1] == len(columns)
            # to rounding: a periodic model's ∂P recursion sums terms far larger than the ∂B it
            # leaves (γ's: 2e-13 against 4e-5; its ∂ν agree to 5e-11)
            scale = np.max(np.abs(dnu[..., columns]))
            assert np.max(np.abs(dnu1 - dnu[..., columns])) <= 1e-9 * scale
            scale = np.max(np.abs(dB[..., columns]))
            assert np.max(np.abs(dB1 - dB[..., columns])) <= 1e-7 * max(scale, 1e-300)


@pytest.mark.parametrize('samples', [121, 161])
def test_periodic_pieces_from_one_revolution_are_every_interval_s(monkeypatch, samples):
    """
    Φ_j, Q_j, ∂Φ_j, ∂Q_j from 32 interval azimuths: the filter's outputs to rounding.

    F and ∂F at those azimuths come from the model (121 samples: too short a record for its
    revolution series) or from the record's series (161).
    """
    prob, theta = _periodic_problem('white', samples)
    exp = prob.experiments[0]
    tf = fine_grid(exp.t, substeps_for(exp.t, prob.max_step))
    p = prob.base.full_parameters(prob.split(theta)[0])
    F, _ = system_on_record(exp.model, 'system', tf, p, exp.inputs(tf))
    assert isinstance(F, Series) == (samples == 161)
    used = []
    series = fe.FilterProblem._phase_series

    def spy(self, *args):
        out = series(self, *args)
        used.append(out is not None)
        return out
    monkeypatch.setattr(fe.FilterProblem, '_phase_series', spy)
    (nu, B, dnu, dB, cost), = prob.evaluate(theta)
    assert used == [True]
    monkeypatch.setattr(fe, 'PHASES', ())             # every interval's own pieces
    (nu_0, B_0, dnu_0, dB_0, cost_0), = prob.evaluate(theta)
    assert used == [True, False]
    for got, want in ((nu, nu_0), (B, B_0), (dnu, dnu_0), (dB, dB_0)):
        assert np.max(np.abs(got - want)) <= 1e-9 * np.max(np.abs(want))
    assert cost == pytest.approx(cost_0, rel=1e-12)


def test_analytic_sensitivities_match_the_finite_difference_ones():
    """∂ν and ∂B themselves, against the filter differenced at θ ± h (the old method)."""
    for prob, theta in (_wake_problem('held', 'equilibrium'), _constant_problem(),
                        _periodic_problem('white')):
        (nu, B, dnu, dB, cost), = prob.evaluate(theta)
        prob.gradients = 'finite-difference'
        (nu_fd, B_fd, dnu_fd, dB_fd, cost_fd), = prob.evaluate(theta)
        assert np.max(np.abs(nu - nu_fd)) < 1e-12 * np.max(np.abs(nu_fd)) + 1e-15
        assert np.max(np.abs(B - B_fd)) < 1e-12 * np.max(np.abs(B_fd))
        assert cost == pytest.approx(cost_fd, rel=1e-12, abs=1e-9)
        scale_nu = np.max(np.abs(dnu_fd), axis=(0, 1))
        scale_B = np.max(np.abs(dB_fd), axis=(0, 1, 2))
        assert np.all(np.max(np.abs(dnu - dnu_fd), axis=(0, 1)) < 1e-7 * scale_nu)
        assert np.all(np.max(np.abs(dB - dB_fd), axis=(0, 1, 2)) < 1e-7 * scale_B + 1e-300)


def test_compiled_scan_equals_numpy(monkeypatch):
    loaded = kernels.mode() != 'numpy' and kernels.prefer() is not None
    if not loaded or kernels.filter_sensitivity_kernel() is None:
        pytest.skip(f'no compiled kernel here ({kernels.status()["error"]})')
    for prob, theta in (_wake_problem('white', 'positions'), _constant_problem(),
                        _periodic_problem('held')):
        compiled, = prob.evaluate(theta)
        monkeypatch.setattr(kernels, 'filter_sensitivity_kernel', lambda: None)
        reference, = prob.evaluate(theta)
        monkeypatch.undo()
        for a, b in zip(compiled[:4], reference[:4]):
            assert np.max(np.abs(a - b)) <= 1e-11 * np.max(np.abs(b))
        assert compiled[4] == pytest.approx(reference[4], rel=1e-12)


def test_the_covariance_moves_along_model_and_noise_parameters_only(monkeypatch):
    # the compiled scan propagates ∂P along these directions alone; its agreement with the
    # numpy twin (which propagates every one) above is on this problem, whose free initial
    # states leave P alone
    prob, theta = _wake_problem('white', 'positions')
    seen = []

    def spy(*args):
        seen.append(args[12])
        return fe.sensitivity_scan_numpy(*args)
    monkeypatch.setattr(kernels, 'filter_sensitivity_kernel', lambda: spy)
    prob.evaluate(theta)
    states = range(len(prob.base.param_index), prob.n_base)
    assert seen[0].dtype == np.int64
    assert seen[0].tolist() == [i for i in range(len(theta)) if i not in states]
    assert [prob.names[i] for i in states] == ['beta_I(t0)', 'beta_II(t0)', 'lambda_I(t0)',
                                               'lambda_II(t0)']


def test_fit_with_analytic_gradients_lands_on_the_same_optimum():
    """Same joint optimum as finite differences, to well below 1 % of a σ."""
    exp = Experiment(WAKE, PROGRESSING, T_WAKE, wake_data(5, 0.1, 0.05),
                     initial_state='equilibrium')
    kw = {'guess': GUESS, 'noise_std': 0.05, 'noise_model': 'held'}
    analytic = fe.fit_filter_error_ml([exp], UNKNOWNS, **kw)
    reference = fe.fit_filter_error_ml([exp], UNKNOWNS, gradients='finite-difference', **kw)
    assert analytic.converged and reference.converged
    assert np.all(np.abs(analytic.values - reference.values) < 0.01 * reference.std)
    assert np.allclose(analytic.std, reference.std, rtol=1e-3)


def test_unknown_gradient_method_is_a_clear_error():
    exp = Experiment(WAKE, PROGRESSING, T_WAKE, wake_data(3, 0.1, 0.05))
    with pytest.raises(fe.IdentificationError, match='gradients must be one of'):
        fe.fit_filter_error([exp], UNKNOWNS, gradients='exact')


def test_analytic_gradient_with_output_offsets_and_two_runs():
    """Sensor-bias parameters (∂d/∂p ≠ 0) and two runs, each with its own free states."""
    from rotor_id.physics.augmented import SensorBias
    model = SensorBias(WAKE, T_WAKE)
    biases = [n for n in model.parameter_names if n.startswith('bias')]
    assert biases
    runs = [Experiment(model, PROGRESSING, T_WAKE, wake_data(seed, 0.1, 0.05) + [0.02, -0.01],
                       initial_state='positions', name=f'run{seed}') for seed in (3, 4)]
    prob = fe.FilterProblem(runs, UNKNOWNS + biases, GUESS, None, None, None, True, None,
                            'held', 'auto', 0.05)
    theta = np.zeros(len(prob.names))
    theta[:3] = [0.45, 0.22, 0.2]
    theta[3:3 + len(biases)] = 0.01
    theta[3 + len(biases):prob.n_base] = 0.05
    theta[prob.i_process] = 0.07**2
    theta[prob.i_meas] = [0.05, 0.06]
    prob.scale = np.maximum(np.abs(theta), 1e-3)
    assert all(prob.analytic_sensitivities(r, theta) is not None for r in range(2))
    worst, _ = _gradient_check(prob, theta)
    assert worst < 1e-5


def test_series_noise_derivative_is_judged_against_its_difference_s_rounding():
    """
    A series of ∂Q is judged against the rounding of the difference it is.

    ∂Q along a parameter of F is a forward difference of two Q's over the step: a series of it
    equals the intervals' own to that difference's rounding (eps·|Q|/step), which is far
    above PHASE_AGREE of ∂Q where the parameter hardly moves Q; along σ_V² it is Q itself.
    """
    rng = np.random.default_rng(4)
    Q = np.abs(rng.standard_normal((2, 3, 3)))
    step = 1e-7
    rounding = np.finfo(float).eps * np.max(Q) / step
    exact = np.zeros((2, 2, 3, 3))
    exact[:, 0] = 1e-3 * rounding * rng.standard_normal((2, 3, 3))   # F's parameter: tiny ∂Q
    exact[:, 1] = Q                                                   # σ_V²: ∂Q = Q
    directions, kp = np.array([0, 5]), 1

    def agrees(error_0, error_1=0.0):
        series = exact.copy()
        series[:, 0] += error_0
        series[:, 1] += error_1
        return fe._noise_derivatives_agree(series, exact, Q, [step], directions, kp)
    assert agrees(0.5 * rounding)                           # rounding of the difference
    assert 0.5 * rounding > 1e3 * fe.PHASE_AGREE * np.max(np.abs(exact[:, 0]))
    assert not agrees(2.0 * fe.DIFFERENCE_ROUNDINGS * rounding)
    assert not agrees(0.0, 1e3 * fe.PHASE_AGREE * np.max(Q))    # Q's own: PHASE_AGREE
    assert agrees(0.0, 0.1 * fe.PHASE_AGREE * np.max(Q))
