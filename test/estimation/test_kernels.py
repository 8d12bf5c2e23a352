"""
The compiled RK4 scan gives the numpy simulator's results (within 1e-9).

Every model (periodic single blade and multiblade, constant-coefficient multiblade, dynamic
wake), with sensitivities to every parameter and initial state and without, on equal and on
jittered sample times and across the simulator's memory chunks: states, outputs and
sensitivities of the kernel agree with the pure-numpy reference to 1e-12 of each array's
largest entry. The kernel itself must load (numba is a pinned requirement).
"""

import os
import subprocess
import sys

import numpy as np
import pytest

from rotor_id.estimation import kernels, simulate as simulate_module
from rotor_id.estimation.simulate import simulate
from rotor_id.physics.models import (Multiblade, MultibladeConstant, MultibladeWake,
                                     RotorConstants, SingleBlade)
from rotor_id.physics.stirring import StirringSchedule

MU04 = RotorConstants(advance_ratio=0.4)
HOVER = RotorConstants(advance_ratio=0.0)
STIR12 = StirringSchedule(t0=12.0)
# the compiled kernels against numpy: nothing to compare where numba is absent
pytestmark = pytest.mark.numba
CASES = {
    'single_blade': (SingleBlade(MU04, 'delta', 'deg'), STIR12, 12.0),
    'multiblade_periodic': (Multiblade(MU04, 'theta0', 'rad'), STIR12, 12.0),
    'multiblade_constant': (MultibladeConstant(MU04, 'delta', 'deg'), STIR12, 12.0),
    'wake': (MultibladeWake(HOVER), StirringSchedule(t0=70.0, omegadot=0.1 / np.pi), 70.0),
}


def _both(monkeypatch, *args, **kwargs):
    """simulate(...) through numpy, then through the kernel."""
    kernel = kernels.load()
    assert kernel is not None, f'the numba kernel did not load: {kernels.status()["error"]}'
    monkeypatch.setitem(kernels._state, 'kernel', None)
    monkeypatch.setenv('ROTOR_ID_KERNELS', 'numpy')
    reference = simulate(*args, **kwargs)
    monkeypatch.setitem(kernels._state, 'kernel', kernel)
    compiled = simulate(*args, **kwargs)
    return reference, compiled


def _assert_close(a, b, what):
    scale = np.max(np.abs(a))
    assert scale > 0, what
    assert np.max(np.abs(a - b)) <= 1e-12 * scale, f'{what}: {np.max(np.abs(a - b)) / scale:.1e}'


@pytest.mark.parametrize('name', sorted(CASES))
@pytest.mark.parametrize('jitter', [False, True])
def test_kernel_matches_numpy(name, jitter, monkeypatch):
    model, stirring, t0 = CASES[name]
    rng = np.random.default_rng(3)
    t = t0 + 0.1 * np.arange(121)
    if jitter:                                  # unequal steps: no constant step map
        t = t + rng.uniform(-0.01, 0.01, t.size)
    p = model.nominal() * np.linspace(0.9, 1.1, len(model.parameters))
    n = model.n_states
    x0 = 0.3 * np.cos(np.arange(1, n + 1))
    P = len(p)
    jac = np.zeros((n, P + n))
    jac[:, P:] = np.eye(n)
    ref, new = _both(monkeypatch, model, p, stirring, t, x0, param_index=range(P),
                     x0_jacobian=jac)
    _assert_close(ref.x, new.x, 'states')
    _assert_close(ref.y, new.y, 'outputs')
    for col in range(P + n):
        _assert_close(ref.dy[:, :, col], new.dy[:, :, col], f'output sensitivity column {col}')
    plain_ref, plain_new = _both(monkeypatch, model, p, stirring, t, x0)
    _assert_close(plain_ref.y, plain_new.y, 'outputs of a plain simulation')
    assert plain_new.dy is None


def test_kernel_across_memory_chunks(monkeypatch):
    model, stirring, t0 = CASES['multiblade_periodic']
    monkeypatch.setattr(simulate_module, '_CHUNK', 40)          # 20 intervals per chunk
    t = t0 + 0.1 * np.arange(101)
    p = model.nominal()
    ref, new = _both(monkeypatch, model, p, stirring, t, np.zeros(model.n_states),
                     param_index=[0, 1])
    _assert_close(ref.x, new.x, 'states')
    _assert_close(ref.dx, new.dx, 'sensitivities')


def test_auto_mode_switches_after_the_numpy_time(monkeypatch):
    monkeypatch.setenv('ROTOR_ID_KERNELS', 'auto')
    monkeypatch.setitem(kernels._state, 'kernel', None)
    monkeypatch.setitem(kernels._state, 'tried', False)
    monkeypatch.setitem(kernels._state, 'numpy_seconds', 0.0)
    assert kernels.rk4_kernel() is None                         # start-up stays light
    kernels.note_numpy_seconds(kernels.AUTO_SWITCH_SECONDS)
    assert kernels.rk4_kernel() is not None, kernels.status()['error']
    monkeypatch.setenv('ROTOR_ID_KERNELS', 'fast')
    with pytest.raises(ValueError, match='ROTOR_ID_KERNELS'):
        kernels.mode()


def _noisy_record(model, stirring, t, seed):
    """Return the noise rows, nominal parameters, a random x0 and its noisy outputs."""
    from rotor_id.estimation import kalman
    rng = np.random.default_rng(seed)
    p = model.nominal()
    x0 = 0.1 * rng.standard_normal(model.n_states)
    y = simulate(model, p, stirring, t, x0).y + 0.05 * rng.standard_normal(
        (t.size, model.n_outputs))
    return kalman.default_noise_rows(model), p, x0, y


@pytest.mark.parametrize('gain', ['time-varying', 'steady'])
def test_filter_kernel_matches_numpy(gain, monkeypatch):
    """The compiled Kalman filter of filter error gives the numpy filter's ν, B, gains, cost."""
    from rotor_id.estimation import kalman
    from rotor_id.estimation.filter_error import filter_batch
    model = MultibladeConstant(MU04, 'delta', 'deg') if gain == 'steady' else \
        CASES['wake'][0]
    stirring, t0 = (STIR12, 12.0) if gain == 'steady' else CASES['wake'][1:]
    t = t0 + 0.1 * np.arange(201)
    rows, p, x0, y = _noisy_record(model, stirring, t, 5)
    dms = [kalman.discretize(model, p * (1 + 0.01 * i), stirring, t, rows, 0.1 * (1 + i))
           for i in range(3)]
    if gain == 'steady':
        assert all(dm.time_invariant for dm in dms)
    x0s = np.array([x0] * 3)
    R = np.array([np.eye(model.n_outputs) * 0.05**2 * (1 + i) for i in range(3)])
    kernel = kernels.load()
    assert kernel is not None, kernels.status()['error']
    monkeypatch.setitem(kernels._state, 'kernel', None)
    monkeypatch.setenv('ROTOR_ID_KERNELS', 'numpy')
    reference = filter_batch(dms, y, x0s, R, gain)
    monkeypatch.setitem(kernels._state, 'kernel', kernel)
    compiled = filter_batch(dms, y, x0s, R, gain)
    for what, a, b in zip(('innovations', 'B', 'gains', 'cost'), reference, compiled):
        _assert_close(a, b, what)


@pytest.mark.parametrize('case', ['wake', 'multiblade_periodic'])
def test_filter_scan_keeping_every_state_matches_kalman_filter(case, monkeypatch):
    """
    The compiled filter scan, keeping every state, gives kalman_filter's loop's results.

    Every predicted and filtered state and covariance, innovation, B, gain and the cost, to
    1e-12, from a non-zero P0 (the scan's update P − K B Kᵀ, the loop's the Joseph form); and
    the states reconstructed from them (filter and smoother).
    """
    from rotor_id.estimation import kalman
    model, stirring, t0 = CASES[case]
    t = t0 + 0.1 * np.arange(201)
    rows, p, x0, y = _noisy_record(model, stirring, t, 7)
    R = np.full(model.n_outputs, 0.05**2)
    P0 = 0.01 * np.eye(model.n_states)
    assert kernels.load() is not None, kernels.status()['error']
    assert kernels.filter_kernel() is not None

    def run():
        dm = kalman.discretize(model, p, stirring, t, rows, 0.1)
        filtered = kalman.kalman_filter(dm, y, x0, P0, R)
        rec = kalman.reconstruct_states(model, p, stirring, t, y, R, x0, P0, rows, 0.1)
        return [filtered.x_pred, filtered.P_pred, filtered.x_filt, filtered.P_filt,
                filtered.innovations, filtered.B, filtered.K, np.array([filtered.cost]),
                rec.x_smoothed, rec.P_smoothed]
    compiled = run()
    monkeypatch.setattr(kernels, 'filter_kernel', lambda: None)
    reference = run()
    names = ('x_pred', 'P_pred', 'x_filt', 'P_filt', 'innovations', 'B', 'K', 'cost',
             'smoothed x', 'smoothed P')
    for what, a, b in zip(names, reference, compiled):
        _assert_close(a, b, what)


def test_filter_kernel_compiles_nothing_for_read_only_or_strided_inputs():
    """
    Views of any layout reach the one cached specialisation of the filter scan.

    numba compiles a new specialisation for each layout and read-only flag it meets: seconds
    at the first call, mid-run in a live node (a 5-bladed rig's state estimator stalled 4 s).
    """
    kernel = kernels.load()
    assert kernel is not None, kernels.status()['error']
    scan = kernels.filter_kernel()
    from rotor_id.estimation import _kernels_numba
    dispatcher = _kernels_numba.filter_scan          # where a call off the signature would go

    def compiled_variants():
        return list(dispatcher.signatures), kernels.status()['just_in_time_calls']
    before = compiled_variants()
    rng = np.random.default_rng(3)
    K_, T, n, m = 1, 6, 3, 2
    Phi = 0.3 * rng.standard_normal((T - 1, K_, n, n)) + np.eye(n)
    c = rng.standard_normal((T - 1, K_, n))
    Q = np.broadcast_to(0.01 * np.eye(n), (T - 1, K_, n, n))        # read-only, stride 0
    H = rng.standard_normal((T, K_, m, n))
    d = np.zeros((T, K_, m))
    y = rng.standard_normal((T, m))
    R = np.eye(m)[None] * 0.1
    P0 = np.eye(n)[None] * 0.2
    read_only = Phi.copy()
    read_only.flags.writeable = False
    strided = np.zeros((T - 1, K_, n, 2 * n))
    strided[..., ::2] = Phi
    outputs = []
    for phi in (Phi, read_only, strided[..., ::2]):
        out = (np.empty((K_, T, m)), np.empty((K_, T, m, m)), np.empty((K_, T, n, m)),
               np.empty(K_), np.empty((K_, n)), np.empty((K_, n, n)))
        scan(phi, c, Q, H, d, y, np.zeros((K_, n)), R, P0, False, *out)
        outputs.append(out)
    assert compiled_variants() == before
    for out in outputs[1:]:
        for a, b in zip(outputs[0], out):
            np.testing.assert_array_equal(a, b)


# -- the prepared time-invariant path (TimeInvariantPlan) ---------------------------------------

def _plan_of(model, stirring, t, p):
    return simulate_module.TimeInvariantPlan.prepare(model, stirring, t,
                                                     simulate_module.DEFAULT_MAX_STEP, p)


def test_plan_only_for_time_invariant_models():
    """Constant-coefficient and wake models get a plan; periodic ones and jittered times do not."""
    assert kernels.load() is not None, kernels.status()['error']
    for name, expected in (('wake', True), ('multiblade_constant', True),
                           ('multiblade_periodic', False), ('single_blade', False)):
        model, stirring, t0 = CASES[name]
        t = t0 + 0.1 * np.arange(121)
        assert (_plan_of(model, stirring, t, model.nominal()) is not None) is expected, name
        jittered = t + np.random.default_rng(1).uniform(-0.01, 0.01, t.size)
        assert _plan_of(model, stirring, jittered, model.nominal()) is None, name


def _augmented_cases():
    from rotor_id.physics import augmented as aug
    from rotor_id.estimation.output_error import ExtendedInput
    from rotor_id.physics.models import build_model
    t = 8.0 + 0.1 * np.arange(161)
    schedule = StirringSchedule(collective=0.035, amplitude=0.026, t0=8.0, t_step=1.0)
    base = build_model('multiblade_wake', HOVER, collective='theta0', angle_unit='rad')
    const = build_model('multiblade_constant', MU04, collective='theta0', angle_unit='rad')
    rates = 0.01 * np.column_stack([np.zeros_like(t), np.cos(t), np.sin(t)])
    return t, [(aug.SensorBias(base, t), schedule), (aug.SensorLag(const), schedule),
               (aug.TimeDelay(const), ExtendedInput(schedule, t, rates)),
               (aug.PitchFlapCoupling(base), schedule)]


def test_plan_matches_numpy_on_augmented_models(monkeypatch):
    """Offsets, extra states and extra inputs through the plan: the numpy results to 1e-12."""
    t, cases = _augmented_cases()
    planned = 0
    for model, inputs in cases:
        p = model.nominal().copy()
        p[p == 0.0] = 0.05                       # away from the neutral extra parameters
        n, P = model.n_states, len(p)
        planned += _plan_of(model, inputs, t, p) is not None
        jac = np.zeros((n, P + n))
        jac[:, P:] = np.eye(n)
        x0 = 0.01 * np.cos(np.arange(1, n + 1))
        ref, new = _both(monkeypatch, model, p, inputs, t, x0, param_index=range(P),
                         x0_jacobian=jac)
        _assert_close(ref.y, new.y, f'{model.name} outputs')
        for col in range(P + n):
            if np.any(ref.dy[:, :, col]):
                _assert_close(ref.dy[:, :, col], new.dy[:, :, col], f'{model.name} column {col}')
            else:
                assert np.max(np.abs(new.dy[:, :, col])) <= 1e-14
    assert planned >= 3, 'the plan should take most time-invariant augmentations'


@pytest.mark.parametrize('path', ['whole fit', 'per iteration'])
@pytest.mark.parametrize('case_name, noise', [('wake_7par', 'given'), ('multiblade_c', 'given'),
                                              ('wake_7par', 'estimated, prior')])
def test_fit_through_the_plan_matches_numpy(case_name, noise, path, monkeypatch):
    """
    Output-error ML through the plan gives the numpy estimate, bound and cost to 1e-9.

    The residual sums are formed in the kernel; the iterations must be the same. Without a
    progress callback the whole fit is one compiled call (gn_fit); with one, every iteration
    is (gn_iteration), and the callback sees each iterate.
    """
    from rotor_id.estimation.output_error import fit_output_error
    from rotor_id.report import cases as C
    from rotor_id.report.reproduce import case_data, iteration_experiment
    case = next(c for c in C.ITERATION_CASES if c.name == case_name)
    exp = iteration_experiment(case, case_data(case, 1))
    sigma = C.SCENARIOS[case.scenario].noise_std

    options = {'noise_std': sigma} if noise == 'given' else {
        'prior': {'mean': {case.unknowns[0]: 0.45}, 'std': {case.unknowns[0]: 0.05}}}

    seen = []

    def fit(progress=None):
        return fit_output_error([exp], list(case.unknowns), guess=dict(case.start),
                                progress=progress, **options)
    kernel = kernels.load()
    assert kernel is not None, kernels.status()['error']
    assert _plan_of(exp.model, exp.inputs, exp.t, exp.model.nominal()) is not None
    monkeypatch.setitem(kernels._state, 'kernel', None)
    monkeypatch.setenv('ROTOR_ID_KERNELS', 'numpy')
    reference = fit()
    monkeypatch.setitem(kernels._state, 'kernel', kernel)
    from rotor_id.estimation import output_error
    calls = []
    for method in ('iterate', 'whole_fit'):
        original = getattr(output_error._CompiledIteration, method)
        monkeypatch.setattr(output_error._CompiledIteration, method,
                            lambda self, *args, _f=original, _m=method:
                            calls.append(_m) or _f(self, *args))
    planned = fit(seen.append if path == 'per iteration' else None)
    if path == 'whole fit':
        assert calls == ['whole_fit'], 'the whole fit should be one compiled call'
    else:
        assert calls == ['iterate'] * planned.iterations, 'every iteration compiled, one call'
        assert [info['iteration'] for info in seen] == list(range(1, planned.iterations + 1))
    assert planned.iterations == reference.iterations and planned.converged
    assert planned.message == reference.message and planned.warnings == reference.warnings
    assert len(planned.history) == len(reference.history)
    for ours, theirs in zip(planned.history, reference.history):
        np.testing.assert_allclose(ours['values'], theirs['values'], rtol=1e-9, atol=0)
        np.testing.assert_allclose([ours['cost'], ours['rms']], [theirs['cost'], theirs['rms']],
                                   rtol=1e-9)
        np.testing.assert_allclose(ours['noise_std'], theirs['noise_std'], rtol=1e-9)
        assert 0 < ours['elapsed'] <= planned.history[-1]['elapsed']
    elapsed = [info['elapsed'] for info in planned.history]
    assert elapsed == sorted(elapsed) and len(set(elapsed)) == len(elapsed), \
        'each iteration timed when it ended, not the whole fit for all'
    np.testing.assert_allclose(planned.neg_log_likelihood, reference.neg_log_likelihood,
                               rtol=1e-9)
    np.testing.assert_allclose(planned.covariance, reference.covariance, rtol=1e-8,
                               atol=1e-12 * np.max(np.abs(reference.covariance)))
    np.testing.assert_allclose(planned.fitted[0], reference.fitted[0], rtol=1e-9)
    np.testing.assert_allclose(planned.initial_states[0], reference.initial_states[0],
                               rtol=1e-9, atol=1e-12)
    assert planned.model_parameters.keys() == reference.model_parameters.keys()
    np.testing.assert_allclose(planned.values, reference.values, rtol=1e-9, atol=0)
    np.testing.assert_allclose(planned.std, reference.std, rtol=1e-9, atol=0)
    np.testing.assert_allclose(planned.cost, reference.cost, rtol=1e-9)
    np.testing.assert_allclose(planned.noise_std, reference.noise_std, rtol=1e-9)
    np.testing.assert_allclose(planned.residuals[0], reference.residuals[0], rtol=0,
                               atol=1e-9 * np.max(np.abs(reference.residuals[0])))


def test_fit_of_two_runs_through_the_plan_matches_numpy(monkeypatch):
    """Two runs, each with its own initial states and R: the plan's sums scattered into θ."""
    from rotor_id.estimation.output_error import Experiment, fit_output_error
    model, stirring, t0 = CASES['wake']
    rng = np.random.default_rng(7)
    p = model.nominal()
    runs = []
    for r in range(2):
        t = t0 + 0.1 * np.arange(121) + 12.0 * r
        x0 = 0.05 * rng.standard_normal(model.n_states)
        y = simulate(model, p, stirring, t, x0).y
        y = y + 0.01 * (1 + r) * rng.standard_normal(y.shape)
        runs.append(Experiment(model, stirring, t, y, 'positions', name=f'run{r}',
                               noise_group=r))
    unknowns = ['A', 'AL_over_tau', 'inv_tau']
    guess = {'A': 0.4, 'AL_over_tau': 0.2, 'inv_tau': 0.2}
    kernel = kernels.load()
    assert kernel is not None
    monkeypatch.setitem(kernels._state, 'kernel', None)
    monkeypatch.setenv('ROTOR_ID_KERNELS', 'numpy')
    reference = fit_output_error(runs, unknowns, guess=guess)
    monkeypatch.setitem(kernels._state, 'kernel', kernel)
    planned = fit_output_error(runs, unknowns, guess=guess)
    assert planned.iterations == reference.iterations
    np.testing.assert_allclose(planned.values, reference.values, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(planned.covariance, reference.covariance, rtol=1e-8,
                               atol=1e-12 * np.max(np.abs(reference.covariance)))
    np.testing.assert_allclose(planned.noise_std, reference.noise_std, rtol=1e-9)


def test_refit_of_a_record_reuses_its_plan(monkeypatch):
    """
    A second fit of the same record and model takes the kept plan and reference point.

    It evaluates neither the inputs nor the model at the starting point again, gives the first
    fit's estimate exactly, and a fit of other unknowns on the kept plan (a new reference with
    those checked) still runs every iteration compiled and matches the numpy path to 1e-9.
    """
    from rotor_id.estimation import output_error
    from rotor_id.estimation.output_error import Experiment, fit_output_error
    assert kernels.load() is not None, kernels.status()['error']
    model, stirring, t0 = CASES['wake']
    t = t0 + 0.1 * np.arange(121)
    rng = np.random.default_rng(11)
    p = model.nominal()
    y = simulate(model, p, stirring, t, 0.05 * np.cos(np.arange(6))).y
    exp = Experiment(model, stirring, t, y + 0.01 * rng.standard_normal(y.shape), 'positions')
    guess = {'A': 0.4, 'inv_tau': 0.2}
    first = fit_output_error([exp], list(guess), guess=guess)
    plan = _plan_of(model, stirring, t.copy(), p)
    assert plan is not None and plan is _plan_of(model, stirring, t.copy(), p)
    evaluations = []
    system = type(model).system
    monkeypatch.setattr(type(model), 'system',
                        lambda self, *a: evaluations.append(1) or system(self, *a))
    again = fit_output_error([exp], list(guess), guess=guess)
    assert not evaluations, 'the kept reference point should spare every model evaluation'
    np.testing.assert_array_equal(again.values, first.values)
    np.testing.assert_array_equal(again.covariance, first.covariance)
    monkeypatch.setattr(type(model), 'system', system)
    # other unknowns (one of them not among the kept reference's) on the same kept plan
    other = {'A': 0.45, 'AL_over_tau': 0.2, 'inv_tau': 0.15}
    assert not plan.checked[model.parameter_names.index('AL_over_tau')]
    calls = []
    whole_fit = output_error._CompiledIteration.whole_fit
    monkeypatch.setattr(output_error._CompiledIteration, 'whole_fit',
                        lambda self, *args: calls.append(1) or whole_fit(self, *args))
    planned = fit_output_error([exp], list(other), guess=other)
    assert plan.checked[[model.parameter_names.index(n) for n in other]].all()
    assert calls == [1], 'the fit on the kept plan should be one compiled call'
    kernel = kernels._state['kernel']
    monkeypatch.setitem(kernels._state, 'kernel', None)
    monkeypatch.setenv('ROTOR_ID_KERNELS', 'numpy')
    reference = fit_output_error([exp], list(other), guess=other)
    monkeypatch.setitem(kernels._state, 'kernel', kernel)
    assert planned.iterations == reference.iterations
    np.testing.assert_allclose(planned.values, reference.values, rtol=1e-9, atol=1e-12)


def test_kept_plans_follow_the_record_and_the_model():
    """New sample times give a new plan; sampled (mutable) inputs and dead models are not kept."""
    import gc
    import weakref
    from rotor_id.physics.stirring import SampledInput
    assert kernels.load() is not None, kernels.status()['error']
    model = MultibladeWake(HOVER)
    stirring = StirringSchedule(t0=70.0)
    t = 70.0 + 0.1 * np.arange(121)
    p = model.nominal()
    plan = _plan_of(model, stirring, t, p)
    assert plan is not None and plan is _plan_of(model, stirring, t, p)
    t[5] += 0.05                                 # the caller's array changed in place
    assert _plan_of(model, stirring, t, p) is None          # jittered: no plan, not the kept one
    t[5] -= 0.05
    shifted = t + 0.1
    assert _plan_of(model, stirring, shifted, p) is not plan
    sampled = SampledInput(t, stirring(t))
    assert _plan_of(model, sampled, t, p) is not _plan_of(model, sampled, t, p)
    alive = weakref.ref(model)
    del model, plan
    gc.collect()
    assert alive() is None, 'a kept plan must not keep its model alive'


def test_step_test_sigma_by_cholesky_is_pinv():
    """gn_iteration's σ of the step test: diag(M⁻¹) by Cholesky equals pinv's, else pinv."""
    assert kernels.load() is not None, kernels.status()['error']
    from rotor_id.estimation import _kernels_numba      # an inner kernel: numba's own
    inverse_diagonal = _kernels_numba._inverse_diagonal
    rng = np.random.default_rng(5)
    for scale in (1.0, 30.0):
        A = rng.standard_normal((60, 7)) * np.logspace(0, np.log10(scale), 7)
        M = A.T @ A
        out = np.empty(7)
        assert inverse_diagonal(M, out)
        np.testing.assert_allclose(out, np.diag(np.linalg.pinv(M)), rtol=1e-12)
    A[:, 6] = 2.0 * A[:, 5] + 1e-6 * rng.standard_normal(60)     # nearly dependent
    assert not inverse_diagonal(A.T @ A, out)
    assert not inverse_diagonal(np.diag([1e6, 1.0, 1.0]), np.empty(3))   # badly scaled
    assert not inverse_diagonal(np.ones((3, 3)), np.empty(3))           # singular


def test_dependence_warnings_with_and_without_the_eigen_analysis():
    """The Cholesky pre-test skips eigh only where no eigenvalue ratio can be below 1e-7."""
    from rotor_id.estimation.output_error import dependence_warnings
    rng = np.random.default_rng(6)
    names = ['a', 'b', 'c', 'd']
    A = rng.standard_normal((40, 4)) * [1.0, 10.0, 0.1, 3.0]
    assert dependence_warnings(names, A.T @ A) == ([], None)
    for eps, warned in ((1e-2, False), (1e-6, True)):   # ratio ~ eps² against 1e-7
        B = A.copy()
        B[:, 3] = 2.0 * B[:, 1] + eps * 10.0 * rng.standard_normal(40)
        warnings, vals = dependence_warnings(names, B.T @ B)
        assert bool(warnings) is warned, (eps, warnings)
        if warned:
            assert 'near-dependent' in warnings[0] and '·b' in warnings[0] and '·d' in warnings[0]
            assert vals[0] / vals[-1] < 1e-7
    M = A.T @ A
    M[2, :] = M[:, 2] = 0.0
    warnings, _ = dependence_warnings(names, M)
    assert warnings[0].startswith('no information at all on c')


def _numpy_and_compiled(monkeypatch, fit):
    """fit() through the numpy simulator, then through the compiled kernels."""
    kernel = kernels.load()
    assert kernel is not None, kernels.status()['error']
    monkeypatch.setitem(kernels._state, 'kernel', None)
    monkeypatch.setenv('ROTOR_ID_KERNELS', 'numpy')
    reference = fit()
    monkeypatch.setitem(kernels._state, 'kernel', kernel)
    monkeypatch.setenv('ROTOR_ID_KERNELS', 'numba')
    return reference, fit()


@pytest.mark.parametrize('story', ['at a bound', 'near-dependent', 'singular on the way'])
def test_whole_fit_stops_and_warns_as_the_python_loop(story, monkeypatch):
    """
    The one-call fit ends as the loop does: bound message, dependence warning, fallback.

    A wake that grows (1/τ < 0) stops at the bound of inv_tau; before the stirring the wake
    parameters and the unknown initial deflections are near-dependent; where gn_fit meets
    singular step equations the fit runs again an iteration at a time (here forced): all as
    the numpy path.
    """
    from rotor_id.estimation import _kernels_numba
    from rotor_id.estimation.output_error import Experiment, fit_output_error
    model, stirring = MultibladeWake(HOVER), StirringSchedule(collective=2.0, t0=70.0)
    truth = np.array([0.5, 0.25, 0.125])
    start = 40.0 if story == 'near-dependent' else 70.0
    t = start + 0.1 * np.arange(121)
    x0 = model.equilibrium(start, truth, stirring([start - 1.0]))
    p = truth if story != 'at a bound' else np.array([0.5, 0.25, -0.05])
    y = simulate(model, p, stirring, t, x0).y
    y = y + 0.01 * np.random.default_rng(0).standard_normal(y.shape)
    # (before the stirring, with the initial deflections unknown: one near-null direction)
    exp = Experiment(model, stirring, t, y,
                     initial_state='positions' if story == 'near-dependent' else x0)
    unknowns = ['A', 'AL_over_tau', 'inv_tau']
    if story == 'singular on the way':
        assert kernels.load() is not None, kernels.status()['error']
        compiled = kernels.affine_kernels()
        gn_fit = compiled.gn_fit
        monkeypatch.setattr(compiled, 'gn_fit',
                            lambda *args: gn_fit(*args) * 0 + _kernels_numba.FIT_SINGULAR)
    reference, planned = _numpy_and_compiled(
        monkeypatch, lambda: fit_output_error([exp], unknowns, noise_std=0.01))
    assert planned.message == reference.message
    assert planned.warnings == reference.warnings
    assert planned.iterations == reference.iterations
    assert planned.converged == reference.converged
    if story == 'near-dependent':           # not identifiable: rounding moves it along σ
        np.testing.assert_allclose(planned.values, reference.values, rtol=0,
                                   atol=1e-6 * np.min(reference.std))
    else:
        np.testing.assert_allclose(planned.values, reference.values, rtol=1e-9, atol=1e-12)
    if story == 'at a bound':
        assert 'physical bound: inv_tau' in planned.message
    elif story == 'near-dependent':
        assert 'not identifiable' in ' '.join(planned.warnings)
    else:
        assert 'elapsed_of' not in planned.history[-1], 'an iteration at a time: timed each'


def test_compiled_clock_is_perf_counter():
    """gn_fit's per-iteration times come from time.perf_counter's clock, read in the kernel."""
    import time
    from rotor_id.estimation.output_error import PERF_COUNTER_CLOCK_ID
    assert kernels.load() is not None, kernels.status()['error']
    if PERF_COUNTER_CLOCK_ID < 0:
        pytest.skip('perf_counter is not clock_gettime here: whole-fit times (elapsed_of)')
    clock_ns = kernels._state['module'].clock_ns
    before = time.perf_counter_ns()
    inside = clock_ns(PERF_COUNTER_CLOCK_ID)
    after = time.perf_counter_ns()
    assert before <= inside <= after


# -- the kernels compiled ahead of time (make build) and numba's just-in-time ones --------------

def test_make_build_compiled_the_kernels_ahead_of_time():
    """The kernels load from the ahead-of-time module that make build made, without numba."""
    import subprocess
    import sys
    code = ('import sys; from rotor_id.estimation import kernels; kernels.load(); '
            's = kernels.status(); print(s["compiled"], "numba" in sys.modules, s["ahead_error"])')
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, check=True)
    assert out.stdout.split()[:2] == ['ahead', 'of'], f'run make build: {out.stdout.strip()}'
    assert out.stdout.split()[3] == 'False', 'numba imported although compiled ahead of time'


@pytest.fixture
def just_in_time(monkeypatch):
    """Run the test's second half on numba's just-in-time kernels; yield a switch to them."""
    assert kernels.load() is not None, kernels.status()['error']
    from rotor_id.estimation import _filter_kernels_numba, _kernels_numba

    def switch():
        _kernels_numba.warm_up()
        monkeypatch.setitem(kernels._state, 'module', _kernels_numba)
        monkeypatch.setitem(kernels._state, 'kernel', _kernels_numba.rk4_scan)
        monkeypatch.setitem(kernels._state, 'sensitivity', _filter_kernels_numba.sensitivity_scan)
    return switch


def _every_compiled_path():
    """
    Run every path through the kernels; return the arrays it gives.

    Simulation of every model (RK4 scan, affine run), an output-error fit in one call
    (gn_fit), the filter with and without sensitivities (filter error's likelihood), and the
    filter that keeps every state (state reconstruction).
    """
    from rotor_id.estimation import filter_error as fe, kalman
    from rotor_id.estimation.output_error import Experiment, fit_output_error
    out = []
    for model, stirring, t0 in CASES.values():
        t = t0 + 0.1 * np.arange(121)
        run = simulate(model, model.nominal(), stirring, t, np.zeros(model.n_states),
                       param_index=[0, 1])
        out += [run.x, run.dx]
    model, stirring = MultibladeWake(HOVER), StirringSchedule(collective=2.0, t0=70.0)
    t = 70.0 + 0.1 * np.arange(121)
    truth = np.array([0.5, 0.25, 0.125])
    y = simulate(model, truth, stirring, t, np.zeros(model.n_states)).y
    y = y + 0.01 * np.random.default_rng(0).standard_normal(y.shape)
    exp = Experiment(model, stirring, t, y, initial_state=np.zeros(model.n_states))
    fit = fit_output_error([exp], ['A', 'AL_over_tau', 'inv_tau'], noise_std=0.01)
    out += [fit.values, fit.std]
    noisy = fe.fit_filter_error_ml([exp], ['A', 'AL_over_tau', 'inv_tau'], noise_std=0.01,
                                   noise_model='held', max_iter=3)
    states = kalman.reconstruct_states(model, truth, stirring, t, y, np.full(2, 1e-4),
                                       np.zeros(model.n_states),
                                       1e-4 * np.eye(model.n_states), noise_std=0.1)
    return out + [noisy.values, noisy.std, states.x_smoothed, states.P_smoothed]


def test_every_path_reaches_the_code_compiled_ahead_of_time():
    """
    The library's calls match the signatures make build compiled (typed from the examples).

    A call off them would go to the just-in-time kernel: numba compiling for seconds in the
    middle of a run, in every process.
    """
    assert kernels.load() is not None, kernels.status()['error']
    if kernels.status()['compiled'] != 'ahead of time':
        pytest.skip('no module compiled ahead of time here (make build compiles it)')
    before = kernels.status()['just_in_time_calls']
    _every_compiled_path()
    assert kernels.status()['just_in_time_calls'] == before, 'a call missed the signatures'


def test_both_compiled_kernels_give_the_same_results(just_in_time, monkeypatch):
    """
    Ahead-of-time and just-in-time kernels agree to rounding on every path that uses them.

    Whichever module loads, the numbers are numba's. It compiles every kernel just in time
    (about 2 min of CPU, which make build spends only where the ahead-of-time module fails),
    so it runs with ROTOR_ID_SLOW=1; CI compares the filter scan
    (test_a_call_off_the_compiled_signature_goes_just_in_time).
    """
    if not os.environ.get('ROTOR_ID_SLOW'):
        pytest.skip('compiles every kernel just in time (about 2 min of CPU): set '
                    'ROTOR_ID_SLOW=1 to run it (CI compares the filter scan)')
    ahead = _every_compiled_path()
    just_in_time()
    again = _every_compiled_path()
    assert kernels.status()['compiled'] in ('ahead of time', 'just in time')
    for a, b in zip(ahead, again):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12 * np.max(np.abs(b)))


def test_a_call_off_the_compiled_signature_goes_just_in_time():
    """
    A strided or read-only array never reaches code compiled for contiguous writable ones.

    And the filter scan compiled ahead of time gives the just-in-time kernel's numbers to
    rounding (the CI-sized part of test_both_compiled_kernels_give_the_same_results).
    """
    assert kernels.load() is not None, kernels.status()['error']
    if kernels.status()['compiled'] != 'ahead of time':
        pytest.skip('the just-in-time kernels compile any layout they meet: nothing to route')
    from rotor_id.estimation import _kernels_numba
    module = kernels.affine_kernels()
    rng = np.random.default_rng(5)
    K_, T, n, m = 1, 6, 3, 2
    Phi = 0.3 * rng.standard_normal((T - 1, K_, n, n)) + np.eye(n)
    args = [Phi, rng.standard_normal((T - 1, K_, n)), np.broadcast_to(
        0.01 * np.eye(n), (T - 1, K_, n, n)).copy(), rng.standard_normal((T, K_, m, n)),
        np.zeros((T, K_, m)), rng.standard_normal((T, m)), np.zeros((K_, n)),
        np.eye(m)[None] * 0.1, np.eye(n)[None] * 0.2, False]
    strided_y = np.zeros((m, T)).T                   # y as a transposed (strided) view
    strided_y[:] = args[5]

    def run(scan, y):
        out = (np.empty((K_, T, m)), np.empty((K_, T, m, m)), np.empty((K_, T, n, m)),
               np.empty(K_), np.empty((K_, n)), np.empty((K_, n, n)), np.empty((K_, T, n)),
               np.empty((K_, T, n, n)), np.empty((K_, T, n)), np.empty((K_, T, n, n)))
        scan(*args[:5], y, *args[6:], *out)
        return out
    reference = run(_kernels_numba.filter_scan, args[5])
    before = kernels.status()['just_in_time_calls']
    routed = run(module.filter_scan, strided_y)
    assert kernels.status()['just_in_time_calls'] == before + 1
    for a, b in zip(reference, routed):
        np.testing.assert_array_equal(a, b)
    ahead = run(module.filter_scan, args[5])
    assert kernels.status()['just_in_time_calls'] == before + 1, 'a matching call went round'
    for a, b in zip(ahead, reference):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-15)


def test_the_compiled_linear_algebra_runs_without_importing_scipy_linalg():
    """
    A fit through the compiled kernels leaves the scipy.linalg package unimported.

    numba's compiled matrix products and solves call BLAS and LAPACK through scipy's pointer
    modules; the package around them takes a third of a second to import, a large share of a
    short diagnosis. The loader reads the two modules alone; scipy.linalg imported later
    still finds them.
    """
    code = '\n'.join([
        'import sys',
        'import numpy as np',
        'from rotor_id.estimation import kernels',
        'from rotor_id.estimation.output_error import Experiment, fit_output_error',
        'from rotor_id.estimation.simulate import simulate',
        'from rotor_id.physics.models import MultibladeWake, RotorConstants',
        'from rotor_id.physics.stirring import StirringSchedule',
        'model = MultibladeWake(RotorConstants(advance_ratio=0.0))',
        'stirring = StirringSchedule(collective=2.0, t0=70.0)',
        't = 70.0 + 0.1 * np.arange(121)',
        'x0 = np.zeros(model.n_states)',
        'y = simulate(model, np.array([0.5, 0.25, 0.125]), stirring, t, x0).y',
        'y = y + 0.01 * np.random.default_rng(0).standard_normal(y.shape)',
        'exp = Experiment(model, stirring, t, y, initial_state=np.zeros(model.n_states))',
        "fit = fit_output_error([exp], ['A', 'AL_over_tau', 'inv_tau'], noise_std=0.01)",
        "print(kernels.status()['compiled'])",
        "print(sorted(m for m in sys.modules if m.startswith('scipy.linalg')))",
        'import scipy.linalg',
        'from scipy.linalg import cython_blas, cython_lapack',
        "print(cython_blas is sys.modules['scipy.linalg.cython_blas'], fit.values.round(2))",
    ])
    env = {**os.environ, 'ROTOR_ID_KERNELS': 'numba'}
    done = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, env=env,
                          timeout=120)
    assert done.returncode == 0, done.stderr
    compiled, loaded, last = done.stdout.splitlines()
    if compiled != 'ahead of time':
        pytest.skip('no module compiled ahead of time here (make build compiles it)')
    assert loaded == "['scipy.linalg.cython_blas', 'scipy.linalg.cython_lapack']", loaded
    assert last.startswith('True'), last


def test_numba_version_for_the_module_key_is_the_installed_one():
    """The ahead-of-time module's key names numba's version, read without importing it."""
    from importlib.metadata import version
    assert kernels._numba_version() == version('numba')
