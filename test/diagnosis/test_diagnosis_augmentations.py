"""
Every candidate of the catalogue is a correct LinearModel built from the baseline.

* analytic sensitivities of each augmented model equal finite differences of the simulator;
* with its extra parameters at their neutral values an augmentation is the baseline itself;
* the dynamic-inflow augmentation of the multiblade model at μ = 0 *is* the report's wake model
  (Ch.2 eq. 29, MultibladeWake) on the tilt modes;
* the periodic-coefficients candidate is the periodic model (docs/models.md §2.1) on the constant
  model's channels;
* sensor bias has exactly the patterns the channels can see.
"""

import math
import pickle

import numpy as np
import pytest

from rotor_id.estimation.output_error import ExtendedInput
from rotor_id.estimation.simulate import simulate
from rotor_id.physics import augmented as aug
from rotor_id.physics.models import build_model, RotorConstants
from rotor_id.physics.stirring import StirringSchedule

T = np.linspace(0.0, 24.0, 241)
SCHEDULE = StirringSchedule(collective=0.035, amplitude=0.026, t0=8.0, t_step=1.0)
BASES = [('multiblade', 0.0), ('multiblade_constant', 0.4), ('multiblade_wake', 0.0),
         ('multiblade', 0.4)]


def _base(name, mu):
    return build_model(name, RotorConstants(advance_ratio=mu), collective='theta0',
                       angle_unit='rad')


def _augmented(base):
    models = [aug.SensorLag(base), aug.TimeDelay(base), aug.SensorBias(base, T),
              aug.FlapFrequency(base), aug.CubicStiffness(base),
              aug.BladeDissimilarity(base, 2), aug.PitchFlapCoupling(base),
              aug.PitchActuatorLag(base),
              aug.SensorGain(base, T, _flap(aug.BladeView(base).n_blades))]
    if base.name != 'multiblade_wake':
        models.append(aug.DynamicInflow(base))
    return models


def _flap(n_blades):
    """Return a flap record per blade to scale (sensor gain)."""
    return 0.03 + 0.01 * np.column_stack([np.cos(T + k) for k in range(n_blades)])


def _inputs():
    extra = 0.02 + 0.01 * np.column_stack([np.cos(T), np.sin(2 * T), np.cos(3 * T), np.sin(T)])
    return ExtendedInput(SCHEDULE, T, extra)


def _away_from_neutral(model):
    p = model.nominal().copy()
    for i, par in enumerate(model.parameters):
        if p[i] == 0.0:
            p[i] = 30.0 if par.name == 'kappa' else 0.05
    return p


def check_sensitivities(model, inputs, rng):
    """Analytic sensitivities of ``model`` equal central finite differences (1e-5 relative)."""
    p = _away_from_neutral(model)
    x0 = 0.01 * rng.standard_normal(model.n_states)
    idx = list(range(len(p)))
    sim = simulate(model, p, inputs, T, x0, param_index=idx)
    for i in idx:
        h = 1e-6 * max(1.0, abs(p[i]))
        up, down = p.copy(), p.copy()
        up[i] += h
        down[i] -= h
        fd = (simulate(model, up, inputs, T, x0).y
              - simulate(model, down, inputs, T, x0).y) / (2 * h)
        scale = np.max(np.abs(fd)) + 1e-12
        assert np.max(np.abs(fd - sim.dy[:, :, i])) / scale < 1e-5, \
            (model.name, model.parameter_names[i])


@pytest.mark.parametrize('name,mu', BASES)
def test_sensitivities_equal_finite_differences(name, mu):
    rng = np.random.default_rng(3)
    inputs = _inputs()
    for model in _augmented(_base(name, mu)):
        check_sensitivities(model, inputs, rng)


@pytest.mark.parametrize('name,mu', BASES)
def test_neutral_augmentation_is_the_baseline(name, mu):
    base = _base(name, mu)
    inputs = _inputs()
    x0b = 0.01 * np.arange(1, base.n_states + 1)
    ref = simulate(base, base.nominal(), inputs, T, x0b).y
    for model in [aug.TimeDelay(base), aug.SensorBias(base, T), aug.FlapFrequency(base),
                  aug.CubicStiffness(base), aug.BladeDissimilarity(base, 3),
                  aug.PitchFlapCoupling(base), aug.SensorGain(base, T, _flap(4))]:
        x0 = np.concatenate([x0b, np.zeros(model.n_states - base.n_states)])
        y = simulate(model, model.nominal(), inputs, T, x0).y
        np.testing.assert_allclose(y, ref, atol=1e-13, err_msg=model.name)
    # a sensor lag tends to no lag: the error from the baseline shrinks like τ
    lag = aug.SensorLag(base)
    x0 = np.concatenate([x0b, np.zeros(lag.n_states - base.n_states)])
    errs = []
    for tau in (0.2, 0.1, 0.05):
        p = np.concatenate([base.nominal(), [tau]])
        errs.append(np.max(np.abs(simulate(lag, p, inputs, T, x0, max_step=0.01).y - ref)))
    assert errs[1] < 0.6 * errs[0] and errs[2] < 0.6 * errs[1]


def test_dynamic_inflow_on_multiblade_is_the_reports_wake_model():
    rotor = RotorConstants(advance_ratio=0.0)
    base = build_model('multiblade', rotor, collective='theta0', angle_unit='rad')
    wake_aug = aug.DynamicInflow(base)
    wake = build_model('multiblade_wake', rotor)
    gamma = 8 * 0.5 / 0.97**4                       # A = γB⁴/8 = 0.5
    p_aug = wake_aug.parameter_vector({'gamma': gamma, 'theta0': 0.035,
                                       'AL_over_tau': 0.25, 'inv_tau': 0.125})
    t = np.linspace(0.0, 40.0, 401)
    sched = StirringSchedule(collective=0.035, amplitude=0.026, t0=10.0, t_step=1.0)
    a = simulate(wake_aug, p_aug, sched, t, np.zeros(wake_aug.n_states))
    b = simulate(wake, np.array([0.5, 0.25, 0.125]), sched, t, np.zeros(wake.n_states))
    names = wake_aug.state_names
    for s_wake, s_aug in (('beta_I', 'beta_I'), ('beta_II', 'beta_II'),
                          ('lambda_I', 'lambda_I'), ('lambda_II', 'lambda_II')):
        np.testing.assert_allclose(a.x[:, names.index(s_aug)],
                                   b.x[:, wake.state_names.index(s_wake)], atol=1e-12)


def test_periodic_candidate_is_the_periodic_model_on_three_channels():
    rotor = RotorConstants(advance_ratio=0.4)
    const = build_model('multiblade_constant', rotor, collective='theta0', angle_unit='rad')
    cand = aug.periodic_coefficients(const)
    full = build_model('multiblade', rotor, collective='theta0', angle_unit='rad')
    assert cand.parameter_names == const.parameter_names
    assert cand.output_names == const.output_names
    p = full.nominal()
    x0 = np.zeros(8)
    np.testing.assert_allclose(simulate(cand, p, SCHEDULE, T, x0).y,
                               simulate(full, p, SCHEDULE, T, x0).y[:, :3], atol=1e-14)


def test_sensor_bias_patterns_are_what_the_channels_see():
    wake = aug.SensorBias(build_model('multiblade_wake', RotorConstants(advance_ratio=0.0)), T)
    assert wake.basis.shape == (4, 2)               # (β1−β3)/2 and (β2−β4)/2 see two patterns
    proj = wake.basis @ wake.basis.T
    np.testing.assert_allclose(proj @ np.ones(4), 0.0, atol=1e-12)
    np.testing.assert_allclose(proj @ np.array([1.0, 0.0, -1.0, 0.0]),
                               [1.0, 0.0, -1.0, 0.0], atol=1e-12)
    mb = aug.SensorBias(_base('multiblade', 0.0), T)
    assert mb.basis.shape == (4, 3)                 # all but the collective (θ0 absorbs it)
    np.testing.assert_allclose(mb.basis.T @ np.ones(4), 0.0, atol=1e-12)
    known = aug.SensorBias(_base('multiblade', 0.0), T, collective_fitted=False)
    assert known.basis.shape == (4, 4)              # a known collective absorbs nothing
    # in forward flight θ0 drives the 1P flap too: the common offset is a bias of its own
    const = aug.SensorBias(_base('multiblade_constant', 0.4), T)
    assert const.basis.shape == (4, 3)              # no βd channel: no reactionless pattern
    np.testing.assert_allclose(const.basis.T @ (-1.0) ** np.arange(1, 5), 0.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(const.basis.T @ np.ones(4)), 2.0, rtol=1e-12)


def _stacked(base):
    """Pairs a rig produces together, stacked as the forward selection stacks them."""
    def extended(columns):
        return ExtendedInput(SCHEDULE, T, columns)
    rates = 0.01 * np.column_stack([np.zeros_like(T), np.cos(T), np.sin(T)])
    flap = 0.02 + 0.01 * np.column_stack([np.cos(T), np.sin(2 * T), np.cos(3 * T), np.sin(T)])
    out = [(aug.SensorBias(aug.SensorLag(base), T), extended(np.zeros((T.size, 0)))),
           (aug.SensorLag(aug.TimeDelay(base)), extended(rates)),
           (aug.TimeDelay(aug.CubicStiffness(base)),
            ExtendedInput(ExtendedInput(SCHEDULE, T, flap), T, rates)),
           (aug.SensorLag(aug.BladeDissimilarity(aug.FlapFrequency(base), 3)),
            extended(np.zeros((T.size, 0))))]
    return out


@pytest.mark.parametrize('name,mu', [('multiblade_wake', 0.0), ('multiblade', 0.4)])
def test_stacked_effects_have_exact_sensitivities_and_nest(name, mu):
    # two or three effects on the one rotor model: analytic sensitivities equal finite
    # differences, and with the outer effect neutral the stack is the inner model exactly
    rng = np.random.default_rng(4)
    base = _base(name, mu)
    for model, inputs in _stacked(base):
        check_sensitivities(model, inputs, rng)
    inner = aug.TimeDelay(base)
    outer = aug.SensorBias(inner, T)
    inputs = ExtendedInput(SCHEDULE, T, 0.01 * np.column_stack(
        [np.zeros_like(T), np.cos(T), np.sin(T)]))
    p_inner = _away_from_neutral(inner)
    p_outer = np.concatenate([p_inner, np.zeros(len(outer.parameters) - len(p_inner))])
    x0 = 0.01 * rng.standard_normal(inner.n_states)
    assert np.allclose(simulate(outer, p_outer, inputs, T, x0).y,
                       simulate(inner, p_inner, inputs, T, x0).y, atol=1e-14)


def test_pitch_flap_coupling_at_mu_0_is_a_flap_frequency_change():
    # Δθ_k = −K β_k in β″ + (γB⁴/8) β′ + P² β = (γB⁴/8) θ (μ = 0, no wake) is the stiffness
    # P² + (γB⁴/8) K: the coupling read off the rotor model's pitch forcing must say so
    base = _base('multiblade', 0.0)
    coupled = aug.PitchFlapCoupling(base)
    freq = aug.FlapFrequency(base)
    p0 = base.nominal()
    gamma = p0[base.parameter_names.index('gamma')]
    K = 0.1
    P = base.rotor.flap_frequency
    P_eq = math.sqrt(P**2 + gamma * base.rotor.tip_loss**4 / 8.0 * K)
    x0 = 0.01 * np.arange(1, base.n_states + 1)
    a = simulate(coupled, np.concatenate([p0, [K]]), SCHEDULE, T, x0)
    b = simulate(freq, np.concatenate([p0, [P_eq]]), SCHEDULE, T, x0)
    # the tilt modes (the collective is a constant parameter of the model: coning uncoupled)
    names = ('beta_I', 'beta_II', 'beta_I_dot', 'beta_II_dot')
    tilt = [base.state_names.index(n) for n in names]
    np.testing.assert_allclose(a.x[:, tilt], b.x[:, tilt], atol=1e-10)


@pytest.mark.parametrize('name', ['multiblade', 'multiblade_constant', 'multiblade_wake',
                                  'single_blade'])
def test_azimuth_offset_sensitivity_in_forward_flight(name):
    # the offset alone and outermost on effects with fixed-frame cyclic states and inputs
    # (wake inflow, pitch error, pitch rates): analytic ∂y/∂Δψ equals finite differences
    rng = np.random.default_rng(5)
    base = _base(name, 0.4)
    check_sensitivities(aug.AzimuthOffset(base), _inputs(), rng)
    if name == 'multiblade':
        for inner in (aug.DynamicInflow(base), aug.PitchActuatorLag(base), aug.TimeDelay(base)):
            check_sensitivities(aug.AzimuthOffset(inner), _inputs(), rng)


@pytest.mark.parametrize('name', ['multiblade', 'multiblade_wake'])
def test_azimuth_offset_is_invisible_in_hover(name):
    # at μ = 0 the rotor is axisymmetric: turning every cyclic quantity by Δψ (S of
    # physics.multiblade) commutes with the dynamics, so the recording cannot depend on Δψ.
    # That holds only if every cyclic state and input is turned alike, so it checks the
    # rotation of each inner effect's states; and the neutral offset is the model itself.
    rng = np.random.default_rng(6)
    base = _base(name, 0.0)
    inners = [base, aug.PitchActuatorLag(base), aug.TimeDelay(base), aug.SensorLag(base),
              aug.BladeDissimilarity(base, 2)]
    if name == 'multiblade':
        inners.append(aug.DynamicInflow(base))
    inputs = _inputs()
    for inner in inners:
        model = aug.AzimuthOffset(inner)
        p = _away_from_neutral(model)
        x0 = 0.01 * rng.standard_normal(model.n_states)
        sim = simulate(model, p, inputs, T, x0, param_index=list(range(len(p))),
                       max_step=0.01)
        assert np.max(np.abs(sim.dy[:, :, -1])) < 1e-9 * np.max(np.abs(sim.dy[:, :, 0])), \
            model.name
        neutral = np.concatenate([p[:-1], [0.0]])
        np.testing.assert_allclose(simulate(model, neutral, inputs, T, x0).y,
                                   simulate(inner, p[:-1], inputs, T, x0).y, atol=1e-14)


def test_azimuth_offset_turns_the_cyclic_coordinates():
    # S of physics.multiblade: collective and differential kept, each cyclic pair of harmonic
    # h turned by hΔψ (the measured cos/sin coordinates of the blades with ψ read Δψ ahead)
    from rotor_id.physics.multiblade import azimuth_offset_matrix, multiblade_coordinates
    psi = np.linspace(0.0, 7.0, 50)
    coords = {'collective': 0.02, 'cos': 0.01 * np.cos(psi), 'sin': 0.004, 'cos2': 0.003,
              'sin2': -0.002}
    from rotor_id.physics.multiblade import blade_values
    blades = blade_values(coords, psi, 5)
    offset = 0.3
    read = multiblade_coordinates(blades, psi + offset)
    S = azimuth_offset_matrix(5, offset)
    true = np.column_stack([np.broadcast_to(coords[k], psi.shape)
                            for k in ('collective', 'cos', 'sin', 'cos2', 'sin2')])
    np.testing.assert_allclose(np.column_stack(list(read.values())), true @ S.T, atol=1e-15)
    c, s = math.cos(offset), math.sin(offset)
    np.testing.assert_allclose(S[1:3, 1:3], [[c, -s], [s, c]], atol=1e-15)
    c2, s2 = math.cos(2 * offset), math.sin(2 * offset)
    np.testing.assert_allclose(S[3:5, 3:5], [[c2, -s2], [s2, c2]], atol=1e-15)


@pytest.mark.parametrize('name,mu', [('multiblade', 0.4), ('multiblade_wake', 0.0)])
def test_pitch_like_random_inflow_acts_as_pitch(name, mu):
    # random inflow's states w = (w0, wI, wII) enter as the pitch inputs do: a w held still
    # (τ_w far beyond the record) gives the response to the pitch shifted by w, also through
    # an azimuth offset underneath (forward flight: in hover it is invisible); its
    # sensitivities are exact. The model reads the collective from its parameter θ0, not
    # from u[0]: w0 shifts θ0 (at μ = 0.4 it drives the coning β0 and, through the periodic
    # coefficients, the tilt; with w0 on u[0] it moved nothing)
    base = _base(name, mu)
    for inner in (base, aug.AzimuthOffset(base)) if mu > 0 else (base,):
        model = aug.PitchLikeRandomInflow(inner)
        assert model.state_names[-3:] == ('random_inflow_0', 'random_inflow_I',
                                          'random_inflow_II')
        shift = np.array([0.004, -0.003, 0.002])
        p_inner = _away_from_neutral(inner) if inner is not base else inner.nominal()
        x0b = 0.01 * np.arange(1, inner.n_states + 1)
        p_shifted = np.array(p_inner, dtype=float)
        if 'theta0' in inner.parameter_names:
            p_shifted[inner.parameter_names.index('theta0')] += shift[0]
        cyclic = shift * np.array([0.0, 1.0, 1.0])
        ref = simulate(inner, p_shifted, lambda t: SCHEDULE(t) + cyclic, T, x0b).y
        if mu > 0:      # the collective turbulence reaches the outputs in forward flight
            still = simulate(inner, p_inner, lambda t: SCHEDULE(t) + cyclic, T, x0b).y
            assert np.abs(ref - still).max() > 0.01 * np.abs(ref).max()
        p = np.concatenate([p_inner, [1e9]])
        y = simulate(model, p, SCHEDULE, T, np.concatenate([x0b, shift])).y
        np.testing.assert_allclose(y, ref, atol=1e-9 * np.abs(ref).max(), err_msg=inner.name)
        check_sensitivities(model, SCHEDULE, np.random.default_rng(5))


@pytest.mark.parametrize('name,mu', [('multiblade_constant', 0.4), ('multiblade', 0.4),
                                     ('multiblade', 0.0)])
def test_wake_with_constant_blocks_is_the_full_sum(name, mu, monkeypatch):
    # the wake adds the inner and root models' F (and ∂F) of length 1 along time where they
    # are constant: bit for bit what adding the arrays copied to every time gives
    model = aug.CubicStiffness(aug.DynamicInflow(_base(name, mu)))
    p = _away_from_neutral(model)
    u = _inputs()(T)
    fast = model.system(T, p, u) + model.system_jacobian(T, p, u)
    monkeypatch.setattr(aug, 'compact', lambda inner, method, *args: getattr(inner, method)(*args))
    slow = model.system(T, p, u) + model.system_jacobian(T, p, u)
    for a, b in zip(fast, slow):
        np.testing.assert_array_equal(a, b)


def test_cubic_spring_forcing_follows_the_grid_and_the_measured_flap():
    # the kept forcing −G(t) β³ is the one of the grid and flap cubes asked for, never a
    # stale one
    base = _base('multiblade', 0.4)
    p = _away_from_neutral(aug.CubicStiffness(base))
    u = _inputs()(T)
    other = u.copy()
    other[:, 3:] *= 1.5
    model = aug.CubicStiffness(base)
    for t, inputs in ((T, u), (T, other), (T[:100], u[:100]), (T, u), (T, other)):
        fresh = aug.CubicStiffness(base)
        np.testing.assert_array_equal(model.system(t, p, inputs)[1],
                                      fresh.system(t, p, inputs)[1])
        np.testing.assert_array_equal(model.system_jacobian(t, p, inputs)[1],
                                      fresh.system_jacobian(t, p, inputs)[1])
    # the cubes β³ scaled by 1.5: the forcing (g − baseline g) scales with them, a check on
    # the values
    g_base = aug.CubicStiffness(base).system(T, np.concatenate([p[:-1], [0.0]]), u)[1]
    change = model.system(T, p, u)[1] - g_base
    moved = np.abs(change) > 1e-12
    assert moved.any()
    np.testing.assert_allclose((model.system(T, p, other)[1] - g_base)[moved] / change[moved],
                               1.5, rtol=1e-9)
    assert '_forcing_memo' in model.__dict__
    assert '_forcing_memo' not in pickle.loads(pickle.dumps(model)).__dict__


def test_compiled_simulation_with_constant_blocks_is_the_full_one(monkeypatch):
    # the simulator takes F and ∂F of length 1 along time where the model says they are
    # constant (the wake and the cubic spring on the constant-coefficient model at μ = 0.4):
    # states, outputs and sensitivities bit for bit those of the arrays copied to every time
    # (the model evaluated at every stage time: test/physics/test_revolution.py checks the
    # one-revolution series against that)
    from rotor_id.estimation import kernels, simulate as simulate_module
    from rotor_id.physics.models import compact
    from rotor_id.physics.revolution import nonzero_entries
    assert kernels.load() is not None, kernels.status()['error']
    model = aug.CubicStiffness(aug.DynamicInflow(_base('multiblade_constant', 0.4)))
    p = _away_from_neutral(model)
    x0 = 0.01 * np.random.default_rng(5).standard_normal(model.n_states)
    index = list(range(len(p)))
    inputs = _inputs()
    rows = []

    def counted(inner, method, t, p, u, columns=None):
        F, g = compact(inner, method, t, p, u)
        rows.append(F.shape[0])
        if columns is not None:
            F, g = F[:, columns], g[:, columns]
        return nonzero_entries(F), g

    def every_time(inner, method, t, p, u, columns=None):
        F, g = getattr(inner, method)(t, p, u)
        if columns is not None:
            F, g = F[:, columns], g[:, columns]
        entries = np.nonzero(np.any(F != 0.0, axis=0))
        return (np.ascontiguousarray(F[(slice(None),) + entries]),
                tuple(i.astype(np.int64) for i in entries)), g
    monkeypatch.setattr(simulate_module, 'entries_on_record', counted)
    fast = simulate(model, p, inputs, T, x0, param_index=index)
    assert rows and set(rows) == {1}            # the compact path was taken
    monkeypatch.setattr(simulate_module, 'entries_on_record', every_time)
    full = simulate(model, p, inputs, T, x0, param_index=index)
    for name in ('x', 'y', 'dx', 'dy'):
        np.testing.assert_array_equal(getattr(fast, name), getattr(full, name), err_msg=name)


def test_innovations_of_the_true_filter_in_forward_flight_turbulence_are_white():
    # the truth generator adds turbulence w0 + wI cos ψ + wII sin ψ to every blade's pitch,
    # as PitchLikeRandomInflow models it: a Kalman filter at the true parameters leaves white
    # innovations on every channel. With w0 unmodelled (its column was read from u[0], which
    # the rotor model ignores), β0's innovations kept the coning's turbulence: effective
    # fraction 0.28-0.86 over seeds 1000-1009 of process_noise_mu04 (449 samples), 0.75-1.0
    # with it. Here the turbulence is three times that size (σ 1.6e-3 rad), so one record
    # decides; the bound is white noise's 0.1 % quantile of the smallest of four channels'
    # fractions (0.48, 2000 draws of 449 samples). Measured: 0.96 (β_I; the others 1.0), and
    # 0.36 on β0 without w0's column. ~4 s CPU
    from rotor_id.diagnosis import noisy
    from rotor_id.diagnosis.catalogue import Setting
    from rotor_id.residuals import effective_fraction
    from rotor_id.estimation.filter_error import fit_filter_error_ml
    from rotor_id.io.run_description import parse_run_description
    from truth_generator import generate, mu04_case, run_description_text
    cfg = mu04_case(seed=1001, turbulence=3 * 5.24e-4, t_settle=20.0)
    record = generate(cfg)
    description = parse_run_description(run_description_text(cfg, 'multiblade',
                                                             ('gamma', 'theta0')))
    setting = Setting(record, description, {}, [], {}, description.window_s)
    setup = noisy.setup_for(setting)
    runs, rows, _ = noisy.random_inflow_states(setup.experiments)
    truth = {'gamma': cfg.gamma, 'theta0': cfg.theta0,
             'turbulence_corr_rad': cfg.turbulence_corr}
    sigma_v = cfg.turbulence * math.sqrt(2.0 / cfg.turbulence_corr)   # white-noise intensity
    est = fit_filter_error_ml(runs, [], known=truth, process_noise_std=sigma_v,
                              estimate_process_noise=False, rows=rows, max_iter=10)
    nu = np.concatenate(est.residuals, axis=0)
    assert nu.shape[1] == 4 and nu.shape[0] > 400
    fractions = [effective_fraction(nu[:, j]) for j in range(nu.shape[1])]
    assert min(fractions) > 0.48, dict(zip(est.channel_names, fractions))


def _read_late_and_modelled(mu, delay):
    """
    Return a flap record read ``delay`` late, blade by blade, and the two delay models.

    The reference simulates the rotor, turns its multiblade flap into each blade's flap
    (physics.multiblade), reads every blade ``delay`` late and forms the multiblade coordinates
    again with the azimuth of the reading: no rotation matrix of the models is used. The models
    start from the rotor's state at −delay (turned into the reading's frame) and see the
    pitch and its rate at t (a smooth stirring: the cyclic step lies before the record).
    Returns (reference, TimeDelay's y, PitchDelay's y, the response's
    range).
    """
    from rotor_id.physics.multiblade import blade_values, multiblade_coordinates
    base = _base('multiblade', mu)
    smooth = StirringSchedule(collective=0.035, amplitude=0.026, t0=8.0, t_step=-10.0)
    keys = ('collective', 'cos', 'sin', 'differential')
    fine = np.arange(-delay, T[-1] + 1e-9, 0.001)
    rotor = simulate(base, base.nominal(), smooth, fine, 0.01 * np.arange(1, 9),
                     max_step=0.01)
    blades = blade_values(dict(zip(keys, rotor.y.T)), fine, 4)
    late = np.column_stack([np.interp(T - delay, fine, blades[:, k]) for k in range(4)])
    read = multiblade_coordinates(late, T)
    reference = np.column_stack([read[k] for k in keys])
    inputs = ExtendedInput(smooth, fine, np.gradient(smooth(fine), fine, axis=0))
    p = np.concatenate([base.nominal(), [delay]])
    x0 = aug.TimeDelay(base).rotation(delay) @ rotor.x[0]
    models = [simulate(model, p, inputs, T, x0, max_step=0.01).y
              for model in (aug.TimeDelay(base), aug.PitchDelay(base))]
    return reference, *models, np.ptp(reference, axis=0).max()


def test_time_delay_is_the_flap_read_late_in_forward_flight():
    # a flap read d late shows the rotor of t − d, periodic aerodynamics included; the model
    # differs from it only by θ(t − d) ≈ θ − dθ′ (O(d²): a quarter when d halves). Delaying
    # the pitch alone is that only in hover: at μ = 0.4 it is off at first order in μ d.
    errors = {}
    for delay in (0.1, 0.05):
        reference, reading, pitch, scale = _read_late_and_modelled(0.4, delay)
        errors[delay] = np.max(np.abs(reading - reference)) / scale
        pitch_error = np.max(np.abs(pitch - reference)) / scale
        assert pitch_error > 10.0 * errors[delay], (delay, pitch_error, errors[delay])
    assert errors[0.1] < 0.002, errors
    assert errors[0.05] < 0.35 * errors[0.1], errors
    reference, reading, pitch, scale = _read_late_and_modelled(0.0, 0.1)
    np.testing.assert_allclose(reading, pitch, rtol=0, atol=1e-12 * scale)
