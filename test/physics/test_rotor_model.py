"""
The general rotor model (docs/models.md): the report's models as special cases, and its physics.

* every report model built by :class:`RotorModel` equals the report's equations transcribed
  entry by entry (report_models.py) to rounding;
* the multiblade model of N blades equals N single blades simulated one by one and transformed
  (N = 2, 3, 5, 6, forward flight, pitch-flap coupling);
* analytic derivatives equal finite differences for the generalised models;
* pitch-flap coupling raises the hover flap frequency to sqrt(P² + A K_P);
* the trim is periodic; the channel noise follows the transform.
"""

import math

import numpy as np
import pytest
from report_models import Multiblade as ReportMultiblade
from report_models import MultibladeConstant as ReportMultibladeConstant
from report_models import MultibladeWake as ReportMultibladeWake
from report_models import SingleBlade as ReportSingleBlade
from rotor_id.estimation.simulate import simulate
from rotor_id.physics.models import build_model, RotorConstants, RotorModel
from rotor_id.physics.multiblade import blade_from_multiblade_matrix
from rotor_id.physics.stirring import StirringSchedule
from rotor_id.pipeline import channel_noise

RNG = np.random.default_rng(7)
T = np.sort(RNG.uniform(0.0, 30.0, 40))
U = RNG.normal(size=(40, 3))


def _same_system(general, report, p, atol=1e-12):
    assert general.state_names == report.state_names
    assert general.output_names == report.output_names
    assert general.parameter_names == report.parameter_names
    F1, g1 = general.system(T, p, U)
    F2, g2 = report.system(T, p, U)
    np.testing.assert_allclose(F1, F2, rtol=0, atol=atol)
    np.testing.assert_allclose(g1, g2, rtol=0, atol=atol)
    dF1, dg1 = general.system_jacobian(T, p, U)
    dF2, dg2 = report.system_jacobian(T, p, U)
    np.testing.assert_allclose(dF1, dF2, rtol=0, atol=atol)
    np.testing.assert_allclose(dg1, dg2, rtol=0, atol=atol)
    np.testing.assert_allclose(general.output_matrix(T), report.output_matrix(T), atol=atol)


@pytest.mark.parametrize('collective', ['theta0', 'delta'])
def test_report_models_are_special_cases(collective):
    p = np.array([5.0, 0.2])
    for blade in (1, 2, 4):
        _same_system(build_model('single_blade', collective=collective, blade=blade),
                     ReportSingleBlade(collective=collective, blade=blade), p)
    for outputs in ('multiblade', 'blades'):
        _same_system(build_model('multiblade', collective=collective, outputs=outputs),
                     ReportMultiblade(collective=collective, outputs=outputs), p)
    _same_system(build_model('multiblade_constant', collective=collective),
                 ReportMultibladeConstant(collective=collective), p)
    wake = build_model('multiblade_wake', RotorConstants(advance_ratio=0.0))
    _same_system(wake, ReportMultibladeWake(), np.array([0.5, 0.25, 0.125]))
    assert wake.time_invariant and wake.parameter_names == ('A', 'AL_over_tau', 'inv_tau')


def test_constant_model_numbers_of_the_report():
    """docs/models.md §2.2: a = .5533, D, K and the input columns at γ = 5, μ = 0.4."""
    model = build_model('multiblade_constant', collective='delta', angle_unit='deg')
    F, g = model.system([0.0], [5.0, 0.0], [[0.0, 0.0, 1.0]])
    np.testing.assert_allclose(-F[0, 3:, 3:], [[.5533, 0, .1521], [0, .5533, 2],
                                               [.3042, -2, .5533]], atol=6e-5)
    np.testing.assert_allclose(-F[0, 3:, :3], [[1.44, 0, 0], [.3042, .44, .6004],
                                               [0, -.5063, .44]], atol=6e-5)
    np.testing.assert_allclose(g[0, 3:], [0, .6004, 0], atol=6e-5)             # θII column
    _, g = model.system([0.0], [5.0, 0.0], [[0.0, 1.0, 0.0]])
    np.testing.assert_allclose(g[0, 3:], [-.3042, 0, -.6944], atol=6e-5)       # θI column
    _, g = model.system([0.0], [0.0, 1.0], [[0.0, 0.0, 0.0]])
    np.testing.assert_allclose(g[0, 3:], [.1295, 0, .1217], atol=6e-5)         # δ column


@pytest.mark.parametrize('n_blades', [2, 3, 5, 6])
def test_multiblade_equals_blade_by_blade(n_blades):
    """N single blades simulated separately, transformed, equal the multiblade model."""
    rotor = RotorConstants(n_blades=n_blades, advance_ratio=0.35, flap_frequency=1.1,
                           tip_loss=0.96, pitch_flap_coupling=0.3)
    schedule = StirringSchedule(collective=0.04, amplitude=0.02, omegadot=-0.1 / math.pi,
                                t0=3.0, t_step=1.0)
    t = np.linspace(0.0, 15.0, 301)
    p = np.array([6.0, 0.04])
    mbc = build_model('multiblade', rotor, outputs='blades')
    assert mbc.n_states == 2 * n_blades
    step = 0.01            # RK4 error ~1e-11 for both (the transformed equations are stiffer)
    x = simulate(mbc, p, schedule, t, np.zeros(mbc.n_states), max_step=step).x
    flap = np.einsum('tkn,tn->tk', mbc.output_matrix(t), x)
    for k in range(1, n_blades + 1):
        blade = build_model('single_blade', rotor, blade=k)
        beta = simulate(blade, p, schedule, t, np.zeros(2), max_step=step).x[:, 0]
        np.testing.assert_allclose(flap[:, k - 1], beta, rtol=0, atol=1e-9)


def _finite_difference_check(model, p):
    dF, dg = model.system_jacobian(T, p, U)
    for i in range(len(p)):
        h = 1e-6 * max(1.0, abs(p[i]))
        up, down = p.copy(), p.copy()
        up[i] += h
        down[i] -= h
        (Fu, gu), (Fd, gd) = model.system(T, up, U), model.system(T, down, U)
        np.testing.assert_allclose(dF[:, i], (Fu - Fd) / (2 * h), atol=1e-7)
        np.testing.assert_allclose(dg[:, i], (gu - gd) / (2 * h), atol=1e-7)


@pytest.mark.parametrize('n_blades,mu,inflow,outputs', [
    (3, 0.3, 'cyclic', 'blades'), (5, 0.2, 'three_state', 'blades'), (4, 0.0, 'three_state',
                                                                      'blades'),
    (3, 0.0, 'cyclic', 'eq30'), (5, 0.25, 'cyclic', 'multiblade')])
def test_wake_jacobians(n_blades, mu, inflow, outputs):
    rotor = RotorConstants(n_blades=n_blades, advance_ratio=mu, pitch_flap_coupling=0.2)
    model = build_model('multiblade_wake', rotor, outputs=outputs, inflow=inflow)
    p = model.nominal() * RNG.uniform(0.7, 1.3, len(model.parameters))
    _finite_difference_check(model, p)
    if mu > 0 or outputs == 'blades':
        assert 'theta0' in model.parameter_names and 'beta_0' in model.state_names
    assert model.output_matrix(T).shape == (T.size, model.n_outputs, model.n_states)


def test_wake_at_mu0_reduces_to_the_report_for_any_blade_count():
    """At μ = 0 the tilt-mode wake model is the same for N = 3, 4, 5, 6 (Ch.2 eq. 29)."""
    report = ReportMultibladeWake()
    for n in (3, 5, 6):
        model = build_model('multiblade_wake', RotorConstants(n_blades=n, advance_ratio=0.0))
        _same_system(model, report, np.array([0.5, 0.25, 0.125]))


def test_pitch_flap_coupling_raises_the_flap_frequency():
    """Hover: β″ + Aβ′ + (P² + A K_P) β = Aθ: eigenvalues −A/2 ± i sqrt(P² + A K_P − A²/4)."""
    KP = math.tan(math.radians(30.0))
    rotor = RotorConstants(advance_ratio=0.0, pitch_flap_coupling=KP)
    model = build_model('single_blade', rotor)
    gamma = 6.0
    A = gamma * rotor.tip_loss**4 / 8
    F, _ = model.system([0.0], [gamma, 0.0], [[0.0, 0.0, 0.0]])
    eig = np.sort_complex(np.linalg.eigvals(F[0]))
    omega = math.sqrt(rotor.flap_frequency**2 + A * KP - A**2 / 4)
    np.testing.assert_allclose(eig, [-A / 2 - 1j * omega, -A / 2 + 1j * omega], atol=1e-12)
    coning = model.trim_state([gamma, 0.05], 0.05)[0]
    assert coning == pytest.approx(A * 0.05 / (rotor.flap_frequency**2 + A * KP), rel=1e-12)


@pytest.mark.parametrize('name,n_blades', [('multiblade', 5), ('single_blade', 3),
                                           ('multiblade_wake', 3)])
def test_trim_is_periodic(name, n_blades):
    rotor = RotorConstants(n_blades=n_blades, advance_ratio=0.3, pitch_flap_coupling=0.1)
    options = {'outputs': 'blades'} if name == 'multiblade_wake' else {}
    model = build_model(name, rotor, **options)
    p = model.nominal()
    x0 = model.trim_state(p, 0.05, t=0.7)
    hold = StirringSchedule(collective=0.05, amplitude=0.0, t0=0.0, t_step=0.0)
    x1 = simulate(model, p, hold, np.array([0.7, 0.7 + 2 * math.pi]), x0).x[-1]
    np.testing.assert_allclose(x1, x0, atol=1e-8)


@pytest.mark.parametrize('n_blades', [3, 4, 5])
def test_channel_noise_follows_the_transform(n_blades):
    """Coordinates average N blades: σ/√N for β0 and βd, σ·√(2/N) for the cyclics."""
    rotor = RotorConstants(n_blades=n_blades)
    model = build_model('multiblade', rotor)
    expected = [1 / math.sqrt(n_blades) if n in ('beta_0', 'beta_d') else math.sqrt(2 / n_blades)
                for n in model.output_names]
    np.testing.assert_allclose(channel_noise(model, 1.0), expected)
    t = np.linspace(0, 7, 5)
    C = model.channel_matrix(t)
    np.testing.assert_allclose(C @ blade_from_multiblade_matrix(t, n_blades),
                               np.broadcast_to(np.eye(n_blades), (5, n_blades, n_blades)),
                               atol=1e-14)
    wake = build_model('multiblade_wake', RotorConstants(n_blades=n_blades, advance_ratio=0.0))
    assert channel_noise(wake, 1.0) == pytest.approx(math.sqrt(2 / n_blades))


def test_bad_rotors_are_refused_with_the_reason():
    with pytest.raises(ValueError, match='at least 2 blades|>= 2'):
        RotorModel(RotorConstants(n_blades=1))
    with pytest.raises(ValueError, match='no cyclic flap'):
        build_model('multiblade_wake', RotorConstants(n_blades=2, advance_ratio=0.0))
    with pytest.raises(ValueError, match='uniform inflow only moves the coning'):
        build_model('multiblade_wake', RotorConstants(advance_ratio=0.0), inflow='three_state')


@pytest.mark.parametrize('name,n_blades,mu,inflow', [
    ('multiblade_wake', 5, 0.2, 'three_state'), ('multiblade_wake', 2, 0.0, 'cyclic'),
    ('single_blade', 3, 0.3, 'cyclic'), ('multiblade', 6, 0.3, 'cyclic')])
def test_plant_physics_any_rotor_starts_in_trim(name, n_blades, mu, inflow):
    """The simulated plant holds any rotor in its periodic trim until commanded (no settling)."""
    from rotor_id.nodes.live import PlantStepper, rotor_constants
    rotor = rotor_constants(n_blades, mu, 1.2, 0.97, 0.2)
    omega, rate = 2 * math.pi * 15, 1000.0
    plant = PlantStepper(name, rotor, {'A': 0.6, 'AL_over_tau': 0.3, 'inv_tau': 0.15,
                                       'AL0_over_tau0': 0.3, 'inv_tau0': 0.2, 'gamma': 6.0},
                         omega, rate, 0.04, inflow=inflow)
    per_rev = int(round(2 * math.pi / (omega / rate)))          # 67 samples ≈ one revolution
    _, flap, pitch = plant.advance(3 * per_rev)
    assert flap.shape == (3 * per_rev, n_blades)
    assert np.all(np.abs(flap) < 0.2) and np.allclose(pitch, 0.04)
    # one revolution later the trimmed flap repeats (to the 67-sample ≠ 2π rounding)
    shift = 2 * math.pi - per_rev * omega / rate
    rate_of_flap = np.gradient(flap, omega / rate, axis=0)
    repeat = flap[per_rev:] + shift * rate_of_flap[per_rev:] - flap[:-per_rev]
    assert np.max(np.abs(repeat)) < 1e-3 * max(np.max(np.abs(flap)), 1e-3)


@pytest.mark.parametrize('n_blades', [2, 3, 4, 5, 7])
def test_periodic_blocks_from_their_harmonics_equal_the_blade_by_blade_construction(n_blades):
    # the periodic model's blocks are evaluated as a short Fourier series in ψ found from
    # one revolution of samples (cheap on every shifted grid of an azimuth-offset fit); the
    # series must be the blocks themselves at any ψ, not an interpolation between samples,
    # and an exact zero must stay an exact zero (it decides a parameter's identifiability)
    from dataclasses import replace
    t = np.sort(RNG.uniform(0.0, 400.0, 300))
    cases = [{}, {'blade': 1}, {'all_coordinates': True}]
    if n_blades >= 3:
        cases += [{'inflow': 'cyclic'}, {'inflow': 'three_state'}]
    for mu in (0.1, 0.4):
        rotor = replace(RotorConstants(), n_blades=n_blades, advance_ratio=mu,
                        pitch_flap_coupling=0.2)
        for options in cases:
            model = RotorModel(rotor, **options)
            series = model._pieces(t)
            direct = model._restrict(model._full_pieces(t))
            for key, value in series.items():
                for got, want in zip(*(v if isinstance(v, tuple) else (v,)
                                       for v in (value, direct[key]))):
                    scale = max(np.max(np.abs(want)), 1e-300)
                    assert np.max(np.abs(got - want)) < 1e-12 * scale, (options, key)
                    zero = np.all(want == 0.0, axis=0)
                    assert np.all(got[:, zero] == 0.0), (options, key)


def test_a_pickled_model_leaves_its_per_grid_blocks_behind_and_evaluates_the_same():
    # a fitted model travels between the diagnosis's worker processes: its blocks kept per
    # time grid (megabytes on a 1-second record) are recomputed where needed, not sent
    import pickle
    from dataclasses import replace
    from rotor_id.physics.augmented import BladeView, FlapFrequency
    from rotor_id.physics.models import Multiblade
    rotor = replace(RotorConstants(), n_blades=4, advance_ratio=0.35)
    t = np.linspace(0.0, 60.0, 4000)
    model = Multiblade(rotor)
    p, u = model.parameter_vector({}), np.full((t.size, 3), 0.01)
    before, flap = model.system(t, p, u), BladeView(model).flap(t)
    blocks = pickle.dumps(model._pieces(t))                     # what a filter's steps use
    assert len(pickle.dumps(model._cache)) > 1e6 and len(pickle.dumps(model)) < 1e4
    copy = pickle.loads(pickle.dumps(model))
    for got, want in zip(copy.system(t, p, u), before):
        assert np.array_equal(got, want)
    assert np.array_equal(BladeView(copy).flap(t), flap)
    assert pickle.dumps(copy._pieces(t)) == blocks
    # and inside an augmentation that keeps a model per value of its parameter
    wrapped = FlapFrequency(model)
    wrapped.system(t, wrapped.parameter_vector({'P': 1.1}), u)
    assert len(pickle.dumps(wrapped)) < 1e5
