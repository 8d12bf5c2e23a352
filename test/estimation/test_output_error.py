"""
Output-error ML on the report's cases, noise-free: convergence to the truth or to the bias.

From the report's starting errors (20 % single blade, 50 % multiblade, the 7-parameter wake
start (.4, .0667, .0833) plus its equilibrium) Gauss-Newton reaches the truth to 1e-6 relative
within the number of iterations the report prints. The constant-coefficient multiblade model
fitted to the periodic truth converges instead to the modelling-error bias of docs/models.md §2.3.
"""

import numpy as np
import pytest

from rotor_id.estimation.output_error import fit_output_error, IdentificationError, STOP
from rotor_id.report import cases as C
from rotor_id.report.reproduce import run_iteration_case

ITER = {case.name: case for case in C.ITERATION_CASES}


def _truth_columns(case):
    scenario = C.SCENARIOS[case.scenario]
    values = [scenario.truth[n] for n in case.unknowns]
    if len(case.columns) > len(case.unknowns):
        x0 = C.truth_initial_state(scenario)
        model = scenario.build('model')
        values += [x0[model.state_names.index(c[:-4])] for c in case.columns[len(values):]]
    return np.array(values)


@pytest.mark.parametrize('name, report_iterations, to_1e6', [
    ('single_blade_2par', 3, 3),     # 20 % start (4, 8), correct initial state
    ('single_blade_4par', 3, 3),     # 20 % start + β(12), β′(12) from (−.75, 1.2)
    ('multiblade_periodic', 3, 3),   # 50 % start (2.5, 5), periodic model = truth model
    ('wake_progressing', 4, 4),      # (.4, .2, .25)
    ('wake_regressing', 4, 5),       # 4.4e-6 after the report's 4 iterations, 1e-11 after 5
    ('wake_7par', 4, 4),             # (.4, .0667, .0833) + equilibrium; docs/models.md §3.3
    ('table1_12_24', 3, 3),
])
def test_noise_free_converges_to_truth(name, report_iterations, to_1e6):
    """
    Noise-free Gauss-Newton from the report's start reaches the truth.

    After the report's printed number of iterations the iterate equals the truth to the
    report's printed digits (3 decimals); 1e-6 relative is reached after ``to_1e6`` iterations,
    which is the report's count for every case but the regressing wake (one more).
    """
    case = ITER[name]
    result = run_iteration_case(case, seed=None)
    truth = _truth_columns(case)
    assert result.estimate.converged, result.estimate.message
    at_report_count = result.columns[report_iterations - 1]
    assert np.all(np.abs(at_report_count - truth) < 5e-4), (name, at_report_count, truth)
    at_count = result.columns[to_1e6 - 1]
    rel = np.abs(at_count - truth) / np.maximum(np.abs(truth), 1e-3)
    assert np.all(rel < 1e-6), (f'{name}: after {to_1e6} iterations '
                                f'{at_count} vs truth {truth} (rel {rel.max():.1e})')


@pytest.mark.parametrize('name', ['multiblade_a', 'multiblade_b', 'multiblade_c'])
def test_constant_coefficient_model_converges_to_modelling_error_bias(name):
    case = ITER[name]
    result = run_iteration_case(case, seed=None)
    assert result.estimate.converged
    final = result.columns[-1]
    # docs/models.md §2.3 prints the bias to 3 decimals
    assert np.all(np.abs(final - np.array(case.noise_free_limit)) <= 0.0005 + 1e-9), final
    # and it is a bias: γ and δ are several Cramér-Rao σ (σ = 0.2) away from the truth
    gamma_sigma = result.estimate.std[0]
    assert abs(final[0] - 5.0) > 0.5 * gamma_sigma


def test_multiblade_a_first_iterates_match_models_md():
    """docs/models.md §2.3: case (a) noise-free iterates 4.947/8.578, 4.944/10.095."""
    result = run_iteration_case(ITER['multiblade_a'], seed=None)
    np.testing.assert_allclose(result.columns[:2], [[4.947, 8.578], [4.944, 10.095]],
                               atol=6e-4)


def test_wake_progressing_iterates_match_models_md():
    """docs/models.md §3.3: (.510, .282, .074) → (.501, .249, .120) → (.500, .250, .125)."""
    result = run_iteration_case(ITER['wake_progressing'], seed=None)
    np.testing.assert_allclose(result.columns[:3], [[0.510, 0.282, 0.074],
                                                    [0.501, 0.249, 0.120],
                                                    [0.500, 0.250, 0.125]], atol=6e-4)


def test_noisy_estimate_is_within_a_few_crb_sigma():
    """One seeded draw (σ = .2): estimate within 4 σ_CRB of the truth, R known."""
    result = run_iteration_case(ITER['single_blade_2par'], seed=7)
    est = result.estimate
    z = (est.values - np.array([5.0, 10.0])) / est.std
    assert np.all(np.abs(z) < 4.0), z
    np.testing.assert_allclose(est.std, [0.092, 0.121], atol=0.003)   # docs/models.md §1.4


def test_bad_unknown_is_a_clear_error():
    case = ITER['single_blade_2par']
    scenario = C.SCENARIOS[case.scenario]
    exp = C.make_experiment(scenario, y=C.truth_outputs(scenario, C.sample_times(12, 24)))
    with pytest.raises(IdentificationError, match='unknown parameter .theta_zero.'):
        fit_output_error([exp], ['gamma', 'theta_zero'])


def test_equilibrium_start_and_two_runs_have_exact_sensitivities():
    """
    θ of two wake runs (one starting in equilibrium, one with free deflections) by FD.

    The equilibrium start x0 = −F⁻¹g depends on the parameters (equilibrium_jacobian); the
    second run's initial states are named with the run index.
    """
    from rotor_id.estimation.output_error import Problem, evaluate
    prog, regr = C.SCENARIOS['wake_progressing'], C.SCENARIOS['wake_regressing']
    t = C.sample_times(70.0, 82.0)
    runs = [C.make_experiment(prog, y=C.noisy_outputs(prog, t, 1), initial_state='equilibrium'),
            C.make_experiment(regr, y=C.noisy_outputs(regr, t, 2), initial_state='positions')]
    problem = Problem(runs, list(C.WAKE), None, None)
    assert problem.names[3:] == ['beta_I(t0)[2]', 'beta_II(t0)[2]', 'lambda_I(t0)[2]',
                                 'lambda_II(t0)[2]']
    theta = np.array([0.45, 0.22, 0.14, 0.5, 0.2, -0.8, -0.3])
    dy = np.concatenate([dy for _, dy, _ in evaluate(problem, theta)])

    def outputs(th):
        return np.concatenate([sim.y for _, _, sim in evaluate(problem, th,
                                                               sensitivities=False)])

    for i, name in enumerate(problem.names):
        h = 1e-6
        step = np.zeros_like(theta)
        step[i] = h
        fd = (outputs(theta + step) - outputs(theta - step)) / (2 * h)
        err = np.max(np.abs(fd - dy[:, :, i])) / np.max(np.abs(dy[:, :, i]))
        assert err < 1e-6, (name, err)
    est = fit_output_error(runs, list(C.WAKE), noise_std=0.1)
    assert est.converged
    # two runs: tighter than either alone (progressing alone: σ_A = .0228 at the truth)
    assert est.std_of('A') < 0.0228


def test_sensitivities_along_some_columns_are_those_columns():
    # model parameters and initial states (each run's own; another run's is zero)
    from rotor_id.estimation.output_error import Problem, evaluate
    prog, regr = C.SCENARIOS['wake_progressing'], C.SCENARIOS['wake_regressing']
    t = C.sample_times(70.0, 82.0)
    runs = [C.make_experiment(prog, y=C.noisy_outputs(prog, t, 1), initial_state='equilibrium'),
            C.make_experiment(regr, y=C.noisy_outputs(regr, t, 2), initial_state='positions')]
    problem = Problem(runs, list(C.WAKE), None, None)
    theta = np.array([0.45, 0.22, 0.14, 0.5, 0.2, -0.8, -0.3])
    everything = evaluate(problem, theta)
    columns = [1, 2, 4, 6]
    some = evaluate(problem, theta, columns=columns)
    for (res, dy, _), (res1, dy1, _) in zip(everything, some):
        np.testing.assert_array_equal(res1, res)
        assert dy1.shape == dy.shape[:2] + (len(columns),)
        np.testing.assert_allclose(dy1, dy[:, :, columns], rtol=0.0,
                                   atol=1e-12 * np.max(np.abs(dy)))
    assert np.max(np.abs(everything[0][1][:, :, 4])) == 0.0     # run 2's state in run 1
    assert np.max(np.abs(everything[1][1][:, :, 4])) > 0.0
    with pytest.raises(ValueError, match='model parameters come before'):
        evaluate(problem, theta, columns=[4, 1])


def test_progress_can_stop_the_fit_after_an_iteration():
    """A caller that must publish now stops Gauss-Newton and gets that iterate's estimate."""
    case = ITER['single_blade_2par']
    scenario = C.SCENARIOS[case.scenario]
    exp = C.make_experiment(scenario, y=C.noisy_outputs(scenario, C.sample_times(12, 24), 3))
    seen = []

    def stop_at_two(info):
        seen.append(info['values'].copy())
        return STOP if info['iteration'] == 2 else None

    start = {'gamma': 4.0, 'delta': 8.0}
    stopped = fit_output_error([exp], list(C.SB), guess=start, progress=stop_at_two)
    assert stopped.iterations == 2 and not stopped.converged
    assert stopped.message == 'stopped by the caller before convergence'
    assert stopped.message in stopped.warnings
    np.testing.assert_array_equal(stopped.values, seen[-1])
    full = fit_output_error([exp], list(C.SB), guess=start, progress=lambda info: None)
    assert full.converged and full.iterations > 2
    np.testing.assert_array_equal(full.history[1]['values'], seen[-1])


def test_estimated_noise_is_the_residual_rms():
    """R estimated from the residuals: σ̂² = Σε²/N, and the bound uses it (Maine & Iliff)."""
    case = ITER['single_blade_2par']
    scenario = C.SCENARIOS[case.scenario]
    t = C.sample_times(12.0, 24.0)
    exp = C.make_experiment(scenario, y=C.noisy_outputs(scenario, t, 3))
    est = fit_output_error([exp], list(C.SB), guess={'gamma': 4.0, 'delta': 8.0})
    res = est.residuals[0]
    assert est.noise_std[0] == pytest.approx(np.sqrt(np.mean(res ** 2)), rel=1e-9)
    assert abs(est.noise_std[0] - 0.2) < 3 * 0.2 / np.sqrt(2 * t.size)
    known = fit_output_error([exp], list(C.SB), guess={'gamma': 4.0, 'delta': 8.0},
                             noise_std=est.noise_std[0])
    np.testing.assert_allclose(known.values, est.values, rtol=1e-6)
    np.testing.assert_allclose(known.covariance, est.covariance, rtol=1e-6)


@pytest.mark.numba
def test_refits_of_a_record_keep_only_what_their_layout_shares():
    # the compiled fit keeps the initial-state map (free states, x0_base, S0) on the record's
    # plan by initial-state mode and θ's layout: refits of one record with other modes and
    # unknowns, in any order, give what a fresh record (nothing kept) gives, bit for bit
    import dataclasses
    from rotor_id.estimation import kernels
    from rotor_id.report.reproduce import case_data, iteration_experiment
    assert kernels.load() is not None, kernels.status()['error']
    case = next(c for c in C.ITERATION_CASES if c.name == 'wake_7par')
    sigma = C.SCENARIOS[case.scenario].noise_std
    exp = iteration_experiment(case, case_data(case, 1))
    variants = [('estimate', list(case.unknowns)), ('zero', list(case.unknowns)),
                ('estimate', list(case.unknowns)[:2]), ('estimate', list(case.unknowns))]

    def fit(record, mode, unknowns):
        run = dataclasses.replace(record, initial_state=mode, x0_guess=None)
        return fit_output_error([run], unknowns, guess=dict(case.start), noise_std=sigma)
    names = set()
    for mode, unknowns in variants:
        kept = fit(exp, mode, unknowns)
        fresh = fit(dataclasses.replace(exp, inputs=dataclasses.replace(exp.inputs)), mode,
                    unknowns)
        assert kept.names == fresh.names
        np.testing.assert_array_equal(kept.values, fresh.values)
        np.testing.assert_array_equal(kept.covariance, fresh.covariance)
        names.add(tuple(kept.names))
    assert len(names) == 3                      # the variants fit different θ


def test_the_kept_layout_follows_new_parameter_bounds_and_starts():
    # θ's layout is kept per model object: new bounds (a new parameter tuple, as with_bounds
    # makes) and another guess give their own layout, the same arguments the kept one
    import dataclasses
    from rotor_id.estimation.output_error import Problem
    from rotor_id.report.reproduce import case_data, iteration_experiment
    case = next(c for c in C.ITERATION_CASES if c.name == 'wake_7par')
    exp = iteration_experiment(case, case_data(case, 1))
    model, unknowns = exp.model, list(case.unknowns)
    first = Problem([exp], unknowns, dict(case.start), None)
    again = Problem([exp], unknowns, dict(case.start), None)
    assert again.lo is first.lo and again.names == first.names      # kept
    moved = Problem([exp], unknowns, {**case.start, unknowns[0]: 0.123}, None)
    assert moved.p_base[moved.param_index[0]] == 0.123
    assert first.p_base[first.param_index[0]] == case.start[unknowns[0]]
    saved = model.parameters
    try:
        model.parameters = tuple(dataclasses.replace(par, lower=par.lower - 1.0)
                                 for par in saved)
        wider = Problem([exp], unknowns, dict(case.start), None)
    finally:
        model.parameters = saved
    np.testing.assert_array_equal(wider.lo[:len(unknowns)], first.lo[:len(unknowns)] - 1.0)


def test_a_diverging_trial_step_is_rejected_without_a_numeric_warning():
    """
    A trial far out (a simulation that blows up) costs inf and is halved back, silently.

    Before, numpy's overflow in the trial's residual sum reached the user as
    ``warning: overflow encountered in square`` from `rotor-id diagnose` (a catalogue
    candidate's first Gauss-Newton step at a large concealed lag), a line that said nothing
    about the result, which was right.
    """
    import warnings
    from rotor_id.estimation.output_error import damped_gauss_newton_step

    def trial_cost(trial):          # (t − 1)², but the "simulation" overflows beyond |t| = 2
        t = float(trial[0])
        blown = np.array([1e200 if abs(t) > 2 else t - 1.0])
        return float(np.sum(blown ** 2)), t

    with warnings.catch_warnings():
        warnings.simplefilter('error')
        # M = 0.1: the Gauss-Newton step from 0 is 20; halved to 1.25 it lowers the cost
        accepted, trial, cost, payload, _ = damped_gauss_newton_step(
            np.zeros(1), np.array([-2.0]), np.array([[0.1]]), np.array([-100.0]),
            np.array([100.0]), 1.0, trial_cost, 0.0)
    assert accepted and trial[0] == pytest.approx(1.25) and cost == pytest.approx(0.0625)
