"""
Kalman filter and RTS smoother: exactness against the simulator, the likelihood, consistency.

What is proved here:
* the filter's prediction is the simulator's step (zero gain reproduces simulate(), held noise
  reproduces simulate(forcing=...)) to rounding;
* Van Loan's Q_d equals the closed form of a double integrator, and the two noise models agree;
* the eq.-26 likelihood equals the Gaussian density of the whole record computed directly from
  its mean and full covariance (an independent, brute-force evaluation);
* the steady-state gain is the limit of the time-varying one;
* with the right model the normalised innovations are white with unit variance (Monte Carlo),
  and the smoother reconstructs rates and the unmeasured inflow from noisy flapping even with
  parameters 20 % wrong (report Ch.2, "updated Kalman filter").
"""

import math

import numpy as np
import pytest
from rotor_id.estimation import kalman
from rotor_id.estimation.simulate import simulate, substeps_for
from rotor_id.physics.models import (MultibladeConstant, MultibladeWake, RotorConstants,
                                     SingleBlade)
from rotor_id.physics.stirring import StirringSchedule
import scipy.linalg

WAKE = MultibladeWake(RotorConstants(advance_ratio=0.0))
WAKE_INPUT = StirringSchedule(collective=0.0, amplitude=1.5, omegadot=-0.1 / math.pi, t0=70.0)
WAKE_T = 70.0 + 0.1 * np.arange(121)


def wake_start(p=None):
    """Equilibrium state at t = 70 (report's 'true' initial values)."""
    p = WAKE.nominal() if p is None else p
    return WAKE.equilibrium(WAKE_T[:1], p, WAKE_INPUT(WAKE_T[:1]))


def propagate(dm, x0, w=None):
    """x_{j+1} = Φ x_j + c_j (+ G w_j)."""
    xs = [np.asarray(x0, dtype=float)]
    for j in range(dm.Phi.shape[0]):
        x = dm.Phi[j] @ xs[-1] + dm.c[j]
        if w is not None:
            x = x + dm.G[j] @ w[j]
        xs.append(x)
    return np.array(xs)


def test_prediction_is_the_simulator_step():
    p = WAKE.nominal()
    x0 = wake_start()
    dm = kalman.discretize(WAKE, p, WAKE_INPUT, WAKE_T)
    sim = simulate(WAKE, p, WAKE_INPUT, WAKE_T, x0)
    assert np.max(np.abs(propagate(dm, x0) - sim.x)) < 1e-12
    # periodic model too (single blade, μ = 0.4)
    blade = SingleBlade(RotorConstants(), collective='delta', angle_unit='deg')
    sched = StirringSchedule(t0=12.0)
    t = 12.0 + 0.1 * np.arange(121)
    dm = kalman.discretize(blade, [5.0, 10.0], sched, t)
    sim = simulate(blade, [5.0, 10.0], sched, t, [-0.92083, 0.98622])
    assert np.max(np.abs(propagate(dm, sim.x[0]) - sim.x)) < 1e-12


def test_held_noise_is_the_simulator_forcing():
    p = WAKE.nominal()
    x0 = wake_start()
    rng = np.random.default_rng(3)
    w = 0.1 * rng.standard_normal((120, 2))
    forcing = np.zeros((120, 6))
    forcing[:, 4:] = w
    sim = simulate(WAKE, p, WAKE_INPUT, WAKE_T, x0, forcing=forcing)
    dm = kalman.discretize(WAKE, p, WAKE_INPUT, WAKE_T, ['lambda_I', 'lambda_II'], 0.1,
                           noise_model='held')
    assert np.max(np.abs(propagate(dm, x0, w) - sim.x)) < 1e-12
    assert np.allclose(dm.Q, 0.01 * dm.G @ np.swapaxes(dm.G, 1, 2), rtol=1e-12, atol=1e-18)


def test_van_loan_double_integrator_and_noise_models_agree():
    F = np.array([[[0.0, 1.0], [0.0, 0.0]]])
    for dt in (0.1, 0.7):
        _, Qd = kalman.van_loan(F, np.diag([0.0, 2.0]), np.array([dt]))
        exact = 2.0 * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
        assert np.allclose(Qd[0], exact, rtol=1e-13, atol=1e-16)
    rng = np.random.default_rng(0)
    A = rng.standard_normal((4, 8, 8)) * np.array([0.01, 0.5, 3.0, 20.0])[:, None, None]
    for i in range(4):
        ref = scipy.linalg.expm(A[i])
        assert np.max(np.abs(kalman.expm_batch(A)[i] - ref)) < 1e-12 * np.max(np.abs(ref))
    # white intensity σ² ≈ a sequence of σ/√Δt held over Δt (first order in Δt)
    p = WAKE.nominal()
    white = kalman.discretize(WAKE, p, WAKE_INPUT, WAKE_T, ['lambda_I', 'lambda_II'], 0.1)
    held = kalman.discretize(WAKE, p, WAKE_INPUT, WAKE_T, ['lambda_I', 'lambda_II'],
                             0.1 / math.sqrt(0.1), noise_model='held')
    assert np.max(np.abs(white.Q - held.Q)) < 1e-3 * np.max(np.abs(white.Q))
    with pytest.raises(ValueError, match='not a state'):
        kalman.discretize(WAKE, p, WAKE_INPUT, WAKE_T, ['lambda_0'], 0.1)


def _brute_force_loglik(dm, y, x0, P0, R):
    """Return log N(y; μ, Σ) of the whole record from the stacked state covariance."""
    T, m = y.shape
    n = dm.Phi.shape[1]
    # state j = A_j x0 + Σ_i<j B_ji w_i + offsets; build mean and covariance of all x_j
    mean = [np.asarray(x0, dtype=float)]
    trans = [np.eye(n)]
    for j in range(T - 1):
        mean.append(dm.Phi[j] @ mean[-1] + dm.c[j])
        trans.append(dm.Phi[j] @ trans[-1])
    cov = np.zeros((T * n, T * n))
    P_list = [np.asarray(P0, dtype=float)]
    for j in range(T - 1):
        P_list.append(dm.Phi[j] @ P_list[-1] @ dm.Phi[j].T + dm.Q[j])
    for j in range(T):
        cov[j * n:(j + 1) * n, j * n:(j + 1) * n] = P_list[j]
        cross = P_list[j]
        for i in range(j + 1, T):
            cross = dm.Phi[i - 1] @ cross
            cov[i * n:(i + 1) * n, j * n:(j + 1) * n] = cross
            cov[j * n:(j + 1) * n, i * n:(i + 1) * n] = cross.T
    Hbig = scipy.linalg.block_diag(*dm.H)
    mu = Hbig @ np.concatenate(mean) + dm.d.ravel()
    S = Hbig @ cov @ Hbig.T + np.kron(np.eye(T), R)
    sign, logdet = np.linalg.slogdet(S)
    r = y.ravel() - mu
    return -0.5 * (r @ np.linalg.solve(S, r) + logdet + T * m * math.log(2 * math.pi))


def test_likelihood_equals_brute_force_gaussian_density():
    t = WAKE_T[:40]
    p = WAKE.nominal()
    dm = kalman.discretize(WAKE, p, WAKE_INPUT, t, ['lambda_I', 'lambda_II'], 0.1)
    rng = np.random.default_rng(11)
    y = simulate(WAKE, p, WAKE_INPUT, t, wake_start()).y + 0.05 * rng.standard_normal((40, 2))
    x0 = wake_start() + 0.01
    P0 = np.diag([1e-3, 2e-3, 1e-3, 2e-3, 5e-3, 5e-3])
    R = np.diag([0.05**2, 0.04**2])
    fr = kalman.kalman_filter(dm, y, x0, P0, R)
    ref = _brute_force_loglik(dm, y, x0, P0, R)
    assert fr.log_likelihood == pytest.approx(ref, rel=1e-10)
    assert fr.cost == pytest.approx(-2 * ref - 40 * 2 * math.log(2 * math.pi), rel=1e-10)


def test_steady_state_gain_is_the_limit_of_the_time_varying_gain():
    model = MultibladeConstant(RotorConstants(), collective='delta', angle_unit='deg')
    sched = StirringSchedule(t0=12.0)
    t = 12.0 + 0.1 * np.arange(400)
    p = np.array([5.0, 10.0])
    dm = kalman.discretize(model, p, sched, t, rows=None or [3, 4, 5], noise_std=0.3)
    assert dm.time_invariant
    y = simulate(model, p, sched, t, np.zeros(6)).y
    R = 0.04 * np.eye(3)
    tv = kalman.kalman_filter(dm, y, np.zeros(6), np.eye(6), R)
    ss = kalman.kalman_filter(dm, y, np.zeros(6), np.eye(6), R, gain='steady')
    P_ss = kalman.steady_state_covariance(dm, R)
    assert np.max(np.abs(tv.P_pred[-1] - P_ss)) < 1e-9 * np.max(np.abs(P_ss))
    assert np.max(np.abs(tv.K[-1] - ss.K[-1])) < 1e-8
    # the periodic wake measurement (eq. 30) has no steady gain
    wdm = kalman.discretize(WAKE, WAKE.nominal(), WAKE_INPUT, WAKE_T)
    with pytest.raises(ValueError, match='time-invariant'):
        kalman.kalman_filter(wdm, np.zeros((121, 2)), wake_start(), np.eye(6), np.eye(2),
                             gain='steady')


def test_innovations_are_white_with_unit_variance():
    """Right model → ν_j/√B_j ~ iid N(0, 1): mean square 1 and no lag-1 correlation."""
    p = WAKE.nominal()
    dm = kalman.discretize(WAKE, p, WAKE_INPUT, WAKE_T, ['lambda_I', 'lambda_II'], 0.1,
                           noise_model='held')
    R = np.diag([0.05**2, 0.05**2])
    z = []
    for seed in range(40):
        rng = np.random.default_rng(seed)
        w = 0.1 * rng.standard_normal((120, 2))
        forcing = np.zeros((120, 6))
        forcing[:, 4:] = w
        y = simulate(WAKE, p, WAKE_INPUT, WAKE_T, wake_start(), forcing=forcing).y
        y = y + 0.05 * rng.standard_normal(y.shape)
        fr = kalman.kalman_filter(dm, y, wake_start(), np.zeros((6, 6)), R)
        chol = np.linalg.cholesky(fr.B)
        z.append(np.linalg.solve(chol, fr.innovations[:, :, None])[:, :, 0])
    z = np.array(z)                                   # (40, 121, 2)
    n = z.size
    assert abs(np.mean(z**2) - 1.0) < 4 * math.sqrt(2.0 / n)      # 9680 values: ±0.06
    lag1 = np.mean(z[:, 1:] * z[:, :-1])
    assert abs(lag1) < 4 / math.sqrt(n)


def test_smoother_reconstructs_rates_and_accelerations_with_wrong_parameters():
    """
    Report Ch.2: a Kalman filter with 20 % wrong parameters still gives rates and accelerations.

    Single blade at μ = 0.4 (the report's case), β measured with σ = 0.2, filter built with
    γ = 4, δ = 8 (truth 5, 10) and process noise on the acceleration row.
    """
    blade = SingleBlade(RotorConstants(), collective='delta', angle_unit='deg')
    sched = StirringSchedule(t0=12.0)
    tt = 0.1 * np.arange(241)
    full = simulate(blade, [5.0, 10.0], sched, tt, [0.0, 0.0])
    t, x_true = tt[120:], full.x[120:]
    acc_true = kalman.state_derivatives(blade, [5.0, 10.0], sched, t, x_true)[:, 1]
    y = full.y[120:] + 0.2 * np.random.default_rng(2).standard_normal((121, 1))
    rec = kalman.reconstruct_states(blade, [4.0, 8.0], sched, t, y, np.array([[0.04]]),
                                    1.2 * x_true[0], 0.1 * np.eye(2), rows=['beta_dot'],
                                    noise_std=0.3)
    amp = np.sqrt(np.mean(x_true**2, axis=0))
    err = np.sqrt(np.mean((rec.x_smoothed - x_true)**2, axis=0)) / amp
    err_acc = np.sqrt(np.mean((rec.derivatives[:, 1] - acc_true)**2)) / np.sqrt(
        np.mean(acc_true**2))
    model_only = simulate(blade, [4.0, 8.0], sched, t, x_true[0]).x
    err_model = np.sqrt(np.mean((model_only - x_true)**2, axis=0)) / amp
    # measured 1.6 % (β), 4.0 % (β′), 11 % (β″) against 19 %, 17 % for the wrong model alone
    assert err[0] < 0.03 and err[1] < 0.06 and err_acc < 0.15, (err, err_acc)
    assert np.all(err < err_model / 3)


def test_smoother_reconstructs_the_unmeasured_inflow():
    """Wake model, parameters 20 % off: λI, λII (never measured) within 15 % of their size."""
    rng = np.random.default_rng(5)
    p_true = WAKE.nominal()
    truth = simulate(WAKE, p_true, WAKE_INPUT, WAKE_T, wake_start())
    y = truth.y + 0.05 * rng.standard_normal(truth.y.shape)
    p_wrong = p_true * np.array([0.8, 1.2, 0.8])
    R = np.diag([0.05**2, 0.05**2])
    rec = kalman.reconstruct_states(WAKE, p_wrong, WAKE_INPUT, WAKE_T, y, R, wake_start(p_wrong),
                                    0.01 * np.eye(6), rows=[1, 3, 4, 5], noise_std=0.1)
    amp = np.sqrt(np.mean(truth.x**2, axis=0))
    err = np.sqrt(np.mean((rec.x_smoothed - truth.x)**2, axis=0)) / amp
    model_only = simulate(WAKE, p_wrong, WAKE_INPUT, WAKE_T, wake_start(p_wrong)).x
    err_model = np.sqrt(np.mean((model_only - truth.x)**2, axis=0)) / amp
    # measured: βI, βII 5.5 %, 3.5 % (model alone 33 %, 32 %); λI, λII 10 %, 10 %
    assert np.all(err[[4, 5]] < 0.15), err
    assert np.all(err[[0, 2]] < err_model[[0, 2]] / 4), (err, err_model)


def test_remembered_noise_covariance_is_the_one_of_each_discretisation():
    """Batches of one stream reuse Q by its exact arguments; another Δt, σ or p gets its own."""
    model = MultibladeWake(RotorConstants(advance_ratio=0.0))
    p = model.nominal()
    schedule = StirringSchedule(0.0349, 0.0262, -0.1 / math.pi, 2.0, 1.0)
    kalman._Q_MEMO.clear()
    for dt, sigma, scale in ((0.0942, 0.01, 1.0), (0.0942, 0.01, 1.0), (0.0943, 0.01, 1.0),
                             (0.0942, 0.02, 1.0), (0.0942, 0.01, 1.1)):
        t = 5.0 + dt * np.arange(30)
        dm = kalman.discretize(model, p * scale, schedule, t, [4, 5], sigma)
        F = model.system(t[:1], p * scale, schedule(t[:1]))[0][0]
        fresh = kalman.constant_noise_covariance(F, np.diff(t)[0], substeps_for(t), [4, 5],
                                                 np.array([sigma] * 2), 'white')
        np.testing.assert_array_equal(dm.Q[0], fresh)
        np.testing.assert_array_equal(dm.Q[-1], fresh)
    assert len(kalman._Q_MEMO) == 4                 # the repeated discretisation reused its Q
    for k in range(2 * kalman._Q_MEMO_SIZE):        # bounded however many models come
        kalman.discretize(model, p * (1 + 1e-3 * k), schedule, t, [4, 5], 0.01)
    assert len(kalman._Q_MEMO) <= kalman._Q_MEMO_SIZE


@pytest.mark.parametrize('noise_model', ['white', 'held'])
@pytest.mark.parametrize('case', ['wake', 'periodic'])
def test_lost_samples_are_discretised_at_the_cost_of_their_own_substeps(
        case, noise_model, monkeypatch):
    """
    A grid with 100 periods of samples lost is the whole grid with those samples unused.

    Φ, c and Q over the gap are the whole record's intervals composed (x, the noise response
    and, for held noise, the one value held over the gap carried through them), every other
    interval is the whole record's; the work is that of the whole record, not 100 times it
    (every interval given the gap's substeps). Φ and c agree with that costly grid to the RK4
    step error (its Q is cruder for white noise on a periodic model: F frozen at the gap's
    midpoint).
    """
    if case == 'wake':
        model, schedule, t0, p = WAKE, WAKE_INPUT, 70.0, WAKE.nominal()
    else:
        model = SingleBlade(RotorConstants(), collective='delta', angle_unit='deg')
        schedule, t0, p = StirringSchedule(t0=12.0), 12.0, np.array([5.0, 10.0])
    rows = kalman.default_noise_rows(model)
    sigma = 0.01
    whole = t0 + 0.094 * np.arange(400)
    lost = np.arange(150, 250)
    t = np.delete(whole, lost)
    steps = []
    grid = kalman.fine_grid
    monkeypatch.setattr(kalman, 'fine_grid',
                        lambda ts, m: steps.append(len(ts) * m) or grid(ts, m))
    dm = kalman.discretize(model, p, schedule, t, rows, sigma, noise_model)
    cost = sum(steps)
    steps.clear()
    full = kalman.discretize(model, p, schedule, whole, rows, sigma, noise_model)
    assert cost <= 1.1 * sum(steps)
    # the whole record's intervals 149..249 composed into the gap's one
    Phi, c, Q = np.eye(model.n_states), np.zeros(model.n_states), np.zeros_like(full.Q[0])
    G = None if full.G is None else np.zeros_like(full.G[0])
    for i in range(lost[0] - 1, lost[-1] + 1):
        Phi, c = full.Phi[i] @ Phi, full.Phi[i] @ c + full.c[i]
        if G is None:
            Q = full.Phi[i] @ Q @ full.Phi[i].T + full.Q[i]
        else:
            G = full.Phi[i] @ G + full.G[i]
    if G is not None:
        Q = sigma**2 * G @ G.T
    keep = np.delete(np.arange(whole.size - 1), lost)
    for what, gap in (('Phi', Phi), ('c', c), ('Q', Q)):
        want = np.array(getattr(full, what)[keep])
        want[lost[0] - 1] = gap
        got = getattr(dm, what)
        assert np.max(np.abs(got - want)) < 1e-9 * np.max(np.abs(want)), what
    monkeypatch.setattr(kalman, 'gap_refinement', lambda *a: None)
    steps.clear()
    costly = kalman.discretize(model, p, schedule, t, rows, sigma, noise_model)
    assert sum(steps) > 20 * cost
    for what in ('Phi', 'c'):
        got, want = getattr(dm, what), getattr(costly, what)
        assert np.max(np.abs(got - want)) < 1e-5 * np.max(np.abs(want)), what
