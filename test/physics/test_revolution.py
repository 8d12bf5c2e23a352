"""
A periodic model over a long record from one revolution's samples equals the model itself.

:func:`rotor_id.physics.revolution.on_record` sums F, g and their derivatives as Fourier series
found from one revolution; it must give what the model gives at every stage time, to rounding,
for every augmentation of the catalogue and their stacks in forward flight, and fall back to
the model itself wherever the series does not hold.
"""

import numpy as np
import pytest

from rotor_id.physics import augmented as aug
from rotor_id.physics.models import build_model, compact, LinearModel, RotorConstants
from rotor_id.physics.revolution import entries_on_record, on_record

#: a one-second record at 900 rpm sampled at 1 kHz, two RK4 stages per sample
GRID = 0.03 + 0.0471 * np.arange(4000)


def _base(name='multiblade', mu=0.4, blades=4):
    return build_model(name, RotorConstants(n_blades=blades, advance_ratio=mu),
                       collective='theta0', angle_unit='rad')


def _inputs(model, rng):
    """Pitch [θ0, θI, θII] and every extra input, smooth and non-periodic in ψ."""
    n = 3 + len(getattr(model, 'all_extra_inputs', ()))
    rates = rng.uniform(0.3, 2.5, n)
    phases = rng.uniform(0.0, 2.0 * np.pi, n)
    return 0.02 * np.sin(np.multiply.outer(GRID, rates) + phases) + 0.01


def _models():
    base = _base()
    t_all = GRID[::2]
    flap = 0.03 + 0.01 * np.column_stack([np.cos(t_all + k) for k in range(4)])
    singles = {
        'sensor_lag': aug.SensorLag(base), 'time_delay': aug.TimeDelay(base),
        'pitch_delay': aug.PitchDelay(base), 'sensor_bias': aug.SensorBias(base, t_all),
        'flap_frequency': aug.FlapFrequency(base), 'cubic': aug.CubicStiffness(base),
        'blade': aug.BladeDissimilarity(base, 2), 'delta3': aug.PitchFlapCoupling(base),
        'actuator_lag': aug.PitchActuatorLag(base), 'gain': aug.SensorGain(base, t_all, flap),
        'wake': aug.DynamicInflow(base), 'azimuth': aug.AzimuthOffset(base),
        'random_inflow': aug.PitchLikeRandomInflow(base)}
    stacks = {
        'delay+azimuth': aug.AzimuthOffset(aug.TimeDelay(base)),
        'wake+cubic+blade': aug.BladeDissimilarity(aug.CubicStiffness(aug.DynamicInflow(base)),
                                                   3),
        'blade+random_inflow': aug.PitchLikeRandomInflow(aug.BladeDissimilarity(base, 1)),
        'azimuth+random_inflow': aug.PitchLikeRandomInflow(aug.AzimuthOffset(base)),
        'five_blades_lag+delay': aug.TimeDelay(aug.SensorLag(_base(blades=5))),
        'three_blades_wake': aug.DynamicInflow(_base(blades=3, mu=0.3)),
    }
    return {**singles, **stacks}


def _away_from_neutral(model, rng):
    p = model.nominal().copy()
    for i, par in enumerate(model.parameters):
        if p[i] == 0.0:
            p[i] = 30.0 if par.name == 'kappa' else 0.05 * rng.uniform(0.5, 1.5)
    return p


@pytest.mark.parametrize('name', sorted(_models()))
def test_series_over_a_record_is_the_model_at_every_time(name):
    rng = np.random.default_rng(7)
    model = _models()[name]
    u = _inputs(model, rng)
    for p in (model.nominal(), _away_from_neutral(model, rng)):
        for method in ('system', 'system_jacobian'):
            series = on_record(model, method, GRID, p, u)
            exact = compact(model, method, GRID, p, u)
            for got, want in zip(series, exact):
                assert got.shape == want.shape
                scale = np.abs(want).max()
                np.testing.assert_allclose(got, want, rtol=0.0, atol=1e-9 * scale,
                                           err_msg=f'{name} {method}')
            _assert_entries_are_the_model(model, method, p, u)
    # (1e-9: an azimuth offset's ∂/∂Δψ is a central difference, its rounding ~1e-11)
    # the series was used (the model varies with ψ; a hover model is time-invariant)
    assert model.__dict__['_revolution_samples'] > 0, name


def _assert_entries_are_the_model(model, method, p, u):
    """entries_on_record: F's non-zero entries (of some parameters) and g, as the model's."""
    columns = None if method == 'system' else list(range(0, len(p), 2))
    (values, index), g = entries_on_record(model, method, GRID, p, u, columns)
    F_exact, g_exact = compact(model, method, GRID, p, u)
    if columns is not None:
        F_exact, g_exact = F_exact[:, columns], g_exact[:, columns]
    F = np.zeros((values.shape[0],) + F_exact.shape[1:])
    F[(slice(None),) + index] = values
    if values.shape[0] == 1:                                # constant: given once
        assert np.all(F_exact == F_exact[:1])
        F_exact = F_exact[:1]
    scale = np.abs(F_exact).max()
    np.testing.assert_allclose(F, F_exact, rtol=0.0, atol=1e-9 * scale)
    np.testing.assert_allclose(g, g_exact, rtol=0.0, atol=1e-9 * np.abs(g_exact).max())
    # every entry left out is zero at every time
    assert np.count_nonzero(np.any(F_exact != 0.0, axis=0)) <= values.shape[1]


class _Drifting(LinearModel):
    """A model whose F drifts with t: not periodic in ψ."""

    name = 'drifting'
    state_names = ('x',)
    output_names = ('x',)
    parameters = ()

    def system(self, t, p, u):
        t = np.atleast_1d(t)
        return (-1.0 - 1e-3 * t)[:, None, None], u[:, :1]

    def system_jacobian(self, t, p, u):
        t = np.atleast_1d(t)
        return np.zeros((t.size, 0, 1, 1)), np.zeros((t.size, 0, 1))


class _Squared(_Drifting):
    """A periodic model whose forcing is not affine in the input."""

    def system(self, t, p, u):
        t = np.atleast_1d(t)
        return (-1.0 + 0.1 * np.cos(t))[:, None, None], u[:, :1] ** 2


@pytest.mark.parametrize('name', ['wake+cubic+blade', 'azimuth+random_inflow'])
def test_a_model_gives_the_same_values_whether_or_not_it_was_probed_before(name):
    # the first call finds the samples per revolution; it sums from those samples too, so
    # that a result does not depend on which call came first (a diagnosis's evaluations
    # happen in an order that depends on the search)
    rng = np.random.default_rng(3)
    u = _inputs(_models()[name], rng)
    p = _away_from_neutral(_models()[name], rng)
    first = _models()[name]
    after_probe = _models()[name]
    on_record(after_probe, 'system_jacobian', GRID, p, u)
    for method in ('system', 'system_jacobian'):
        for a, b in zip(on_record(first, method, GRID, p, u),
                        on_record(after_probe, method, GRID, p, u)):
            assert np.array_equal(a, b), method
        first = _models()[name]


@pytest.mark.parametrize('model', [_Drifting(), _Squared()], ids=lambda m: type(m).__name__)
def test_a_model_the_series_does_not_hold_for_is_evaluated_itself(model):
    u = np.column_stack([np.sin(0.7 * GRID)])
    for _ in range(2):
        F, g = on_record(model, 'system', GRID, np.zeros(0), u)
        F_exact, g_exact = model.system(GRID, np.zeros(0), u)
        np.testing.assert_array_equal(F, F_exact)
        np.testing.assert_array_equal(g, g_exact)
    assert model.__dict__['_revolution_samples'] == 0


def test_a_short_grid_or_a_hover_model_is_evaluated_itself():
    hover = _base(mu=0.0)
    u = _inputs(hover, np.random.default_rng(1))
    F, g = on_record(hover, 'system', GRID, hover.nominal(), u)
    F_exact, g_exact = compact(hover, 'system', GRID, hover.nominal(), u)
    np.testing.assert_array_equal(F, F_exact)
    np.testing.assert_array_equal(g, g_exact)
    model = _base()
    u = _inputs(model, np.random.default_rng(1))[:50]
    on_record(model, 'system', GRID[:50], model.nominal(), u)
    assert '_revolution_samples' not in model.__dict__


def test_a_function_zero_at_every_phase_sums_to_zeros_of_its_shape():
    # e.g. an input matrix whose fitted parameters move no entry: no entries to sum
    from rotor_id.physics.revolution import Series
    t = np.linspace(0.0, 20.0, 300)
    u = np.ones((t.size, 3))
    for values, weights in ((np.zeros((12, 4, 2)), None), (np.zeros((12, 4, 2, 3)), u)):
        series = Series.of(values, 0.0, weights is not None)
        assert series.entries(t, weights).shape[1] == 0
        np.testing.assert_array_equal(series.values(t, weights), np.zeros((t.size, 4, 2)))


def test_an_evaluation_asked_again_is_kept_and_any_change_evaluates_the_model(monkeypatch):
    # a fit evaluates the same parameters twice (its initial states, then its residuals): the
    # second time is answered from the kept result; other parameters, inputs, columns or
    # another model object are evaluated, and give what the model gives
    from rotor_id.physics import revolution
    calls = []

    def counting(*args, **kwargs):
        calls.append(args[1])
        return compact(*args, **kwargs)
    monkeypatch.setattr(revolution, 'compact', counting)
    rng = np.random.default_rng(5)
    model = _models()['delay+azimuth']
    u = _inputs(model, rng)
    p = _away_from_neutral(model, rng)
    first = on_record(model, 'system_jacobian', GRID, p, u)
    count = len(calls)
    assert count > 0
    again = on_record(model, 'system_jacobian', GRID, p.copy(), u.copy())
    assert len(calls) == count
    for a, b in zip(first, again):
        assert np.array_equal(a, b)
    other_p = p.copy()
    other_p[0] *= 1.01
    other_u = u.copy()
    other_u[-1, 0] += 1e-3
    for changed_model, changed_p, changed_u, columns in (
            (model, other_p, u, None), (model, p, other_u, None), (model, p, u, [0, 2]),
            (_models()['delay+azimuth'], p, u, None)):
        before = len(calls)
        got = on_record(changed_model, 'system_jacobian', GRID, changed_p, changed_u, columns)
        assert len(calls) > before
        F_exact, g_exact = compact(changed_model, 'system_jacobian', GRID, changed_p, changed_u)
        if columns is not None:
            F_exact, g_exact = F_exact[:, columns], g_exact[:, columns]
        np.testing.assert_allclose(got[0], F_exact, rtol=0.0, atol=1e-9 * np.abs(F_exact).max())
        np.testing.assert_allclose(got[1], g_exact, rtol=0.0, atol=1e-9 * np.abs(g_exact).max())


def _hover_models():
    base, single = _base(mu=0.0), _base('single_blade', mu=0.0)
    t_all = GRID[::2]
    flap = 0.03 + 0.01 * np.column_stack([np.cos(t_all + k) for k in range(4)])
    return {
        'sensor_lag': aug.SensorLag(base), 'time_delay': aug.TimeDelay(base),
        'sensor_bias': aug.SensorBias(base, t_all), 'flap_frequency': aug.FlapFrequency(base),
        'blade': aug.BladeDissimilarity(base, 2), 'delta3': aug.PitchFlapCoupling(base),
        'actuator_lag': aug.PitchActuatorLag(base), 'gain': aug.SensorGain(base, t_all, flap),
        'wake': aug.DynamicInflow(base), 'azimuth': aug.AzimuthOffset(base),
        'lag+blade': aug.SensorLag(aug.BladeDissimilarity(base, 1)),
        'lag+gain': aug.SensorLag(aug.SensorGain(base, t_all, flap)),
        'single_blade_gain': aug.SensorGain(single, t_all, flap[:, :1]),
        'single_blade_lag': aug.SensorLag(single)}


@pytest.mark.parametrize('name', sorted(_hover_models()))
def test_a_hover_model_is_flagged_time_invariant_exactly_when_it_is(name):
    # a term of one blade (a dissimilar blade, one blade's sensor gain) is periodic in
    # multiblade coordinates even in hover; a flag that claims otherwise keeps the model
    # from its series (on_record evaluates it at every time of a record)
    model = _hover_models()[name]
    p = _away_from_neutral(model, np.random.default_rng(3))
    times = np.array([0.4, 1.3, 2.2, 3.7, 5.0])
    u = np.tile([0.1, 0.02, -0.01] + [0.0] * len(getattr(model, 'all_extra_inputs', ())),
                (times.size, 1))
    arrays = compact(model, 'system', times, p, u) + compact(model, 'system_jacobian', times,
                                                             p, u)
    constant = all(np.allclose(a, a[:1], rtol=0.0, atol=1e-11 * max(np.abs(a).max(), 1e-300))
                   for a in arrays)
    if model.time_invariant or not getattr(model, 'all_extra_inputs', ()):
        assert model.time_invariant == constant
    # (a model with extra inputs, a measured pitch rate or cubed flap, is flagged periodic
    # either way: the flag never claims what only its inputs would decide)
