"""
The simulator's sensitivities are the derivatives of its own output.

For every model (single blade, periodic multiblade in both output sets, constant-coefficient
multiblade, dynamic wake) and every parameter and initial state, the analytic output
sensitivities of :func:`simulate` agree with central finite differences of :func:`simulate`
to 1e-6 relative to the largest sensitivity of that column (docs/models.md §0.1).
"""

import numpy as np
import pytest

from rotor_id.estimation.simulate import simulate
from rotor_id.physics.models import (Multiblade, MultibladeConstant, MultibladeWake,
                                     RotorConstants, SingleBlade)
from rotor_id.physics.stirring import StirringSchedule

MU04 = RotorConstants(advance_ratio=0.4)
HOVER = RotorConstants(advance_ratio=0.0)


def _cases():
    stir12 = StirringSchedule(t0=12.0)
    stir70 = StirringSchedule(t0=70.0, omegadot=0.1 / np.pi)
    return {
        'single_blade_deg_delta': (SingleBlade(MU04, 'delta', 'deg'), stir12, 12.0),
        'single_blade_rad_theta0_blade3': (SingleBlade(MU04, 'theta0', 'rad', blade=3),
                                           StirringSchedule(collective=0.035, amplitude=0.026,
                                                            t0=12.0), 12.0),
        'multiblade_periodic': (Multiblade(MU04, 'delta', 'deg'), stir12, 12.0),
        'multiblade_periodic_blades': (Multiblade(MU04, 'theta0', 'deg', outputs='blades'),
                                       stir12, 12.0),
        'multiblade_constant': (MultibladeConstant(MU04, 'delta', 'deg'), stir12, 12.0),
        'wake': (MultibladeWake(HOVER), stir70, 70.0),
    }


CASES = _cases()


@pytest.mark.parametrize('name', sorted(CASES))
def test_sensitivities_match_central_differences(name):
    model, stirring, t0 = CASES[name]
    t = np.round(t0 + 0.1 * np.arange(121), 10)
    p = model.nominal() * np.linspace(0.9, 1.1, len(model.parameters))   # off the nominal
    n = model.n_states
    x0 = 0.3 * np.cos(np.arange(1, n + 1))                             # a generic state
    P = len(p)
    jac = np.zeros((n, P + n))
    jac[:, P:] = np.eye(n)
    sim = simulate(model, p, stirring, t, x0, param_index=range(P), x0_jacobian=jac)
    assert sim.dy.shape == (t.size, model.n_outputs, P + n)
    columns = [('p', i) for i in range(P)] + [('x0', i) for i in range(n)]
    for col, (kind, i) in enumerate(columns):
        if kind == 'p':
            h = 1e-5 * max(1.0, abs(p[i]))
            up, down = p.copy(), p.copy()
            up[i] += h
            down[i] -= h
            fd = (simulate(model, up, stirring, t, x0).y
                  - simulate(model, down, stirring, t, x0).y) / (2 * h)
            label = model.parameter_names[i]
        else:
            h = 1e-4
            up, down = x0.copy(), x0.copy()
            up[i] += h
            down[i] -= h
            fd = (simulate(model, p, stirring, t, up).y
                  - simulate(model, p, stirring, t, down).y) / (2 * h)
            label = f'{model.state_names[i]}(t0)'
        analytic = sim.dy[:, :, col]
        scale = np.max(np.abs(analytic))
        if kind == 'x0' and scale == 0.0:
            # an unobserved direction (none here, but then FD must be zero as well)
            assert np.max(np.abs(fd)) < 1e-12
            continue
        assert scale > 0.0, f'{name}: sensitivity to {label} is identically zero'
        err = np.max(np.abs(analytic - fd)) / scale
        assert err < 1e-6, f'{name}: ∂y/∂{label} differs from central FD by {err:.2e} relative'


def test_sensitivity_columns_are_parameter_specific():
    """A sanity check that the test above can fail: swapped columns do not agree."""
    model, stirring, t0 = CASES['single_blade_deg_delta']
    t = np.round(t0 + 0.1 * np.arange(61), 10)
    p = model.nominal()
    sim = simulate(model, p, stirring, t, np.zeros(2), param_index=[0, 1])
    h = 1e-5 * p[0]
    fd_gamma = (simulate(model, p + [h, 0], stirring, t, np.zeros(2)).y
                - simulate(model, p - [h, 0], stirring, t, np.zeros(2)).y) / (2 * h)
    wrong = np.max(np.abs(sim.dy[:, :, 1] - fd_gamma)) / np.max(np.abs(sim.dy[:, :, 1]))
    assert wrong > 0.1


def test_forcing_is_a_piecewise_constant_input():
    """A constant forcing w on one state equals the same step added to g (analytic check)."""
    model = MultibladeWake(HOVER)
    stirring = StirringSchedule(t0=70.0)
    t = np.round(70.0 + 0.1 * np.arange(41), 10)
    p = model.nominal()
    x0 = model.equilibrium(t[:1], p, stirring(t[:1]))
    w = np.zeros((t.size - 1, 6))
    w[:, 4] = 0.01
    forced = simulate(model, p, stirring, t, x0, forcing=w)

    class Shifted(MultibladeWake):
        def system(self, tt, pp, u):
            F, g = super().system(tt, pp, u)
            g = g.copy()
            g[:, 4] += 0.01
            return F, g

    shifted = simulate(Shifted(HOVER), p, stirring, t, x0)
    assert np.max(np.abs(forced.x - shifted.x)) < 1e-12
    assert np.max(np.abs(forced.x - simulate(model, p, stirring, t, x0).x)) > 1e-4


def test_reference_point_test_on_lists_is_numpys():
    # TimeInvariantPlan._on_reference and affine_along read p, the checked parameters and the
    # affine mask of the kept reference point on Python lists: the same verdicts as numpy's
    # checked[index].all() and not np.any((p != p_ref) & ~affine), NaN included, and they
    # follow a new reference
    from rotor_id.estimation.simulate import TimeInvariantPlan
    rng = np.random.default_rng(7)
    plan = TimeInvariantPlan.__new__(TimeInvariantPlan)
    plan._reference_lists = None
    verdicts = set()
    for _ in range(400):
        p_ref = rng.integers(0, 3, 6).astype(float)
        affine = rng.random(6) < 0.5
        plan.checked = rng.random(6) < 0.8
        ref = (p_ref, None, None, None, None, affine)
        p = p_ref.copy()
        p[rng.integers(0, 6)] = rng.choice([0.0, 1.0, 2.0, np.nan])
        index = np.flatnonzero(rng.random(6) < 0.5)
        expected = bool(plan.checked[index].all()) and not np.any((p != p_ref) & ~affine)
        assert plan._on_reference(p, ref, index.tolist()) == expected
        assert plan.affine_along(ref, index.tolist()) == bool(affine[index].all())
        verdicts.add(expected)
    assert verdicts == {True, False}


@pytest.mark.parametrize('name', ['multiblade_periodic', 'wake'])
def test_lost_samples_cost_their_own_substeps_not_the_whole_records(name, monkeypatch):
    """
    A record with 100 periods of samples lost integrates as the record without the loss does.

    Every RK4 substep count along a sample grid is that of its longest interval; a gap would
    give it to every interval (100 times the work here). The gap is integrated over a filled
    grid instead: states and sensitivities at the samples equal those of the gap's substeps
    everywhere to the RK4 step error, at the cost of the record with its samples.
    """
    from rotor_id.estimation import simulate as simulation
    model, schedule, t0 = CASES[name]
    p = model.nominal()
    x0 = 0.3 * np.cos(np.arange(1, model.n_states + 1))                # a generic state
    whole = t0 + 0.094 * np.arange(400)
    t = np.delete(whole, np.arange(150, 250))
    index = list(range(len(model.parameters)))
    steps = []
    grid = simulation.fine_grid
    monkeypatch.setattr(simulation, 'fine_grid',
                        lambda ts, m: steps.append(len(ts) * m) or grid(ts, m))
    sim = simulate(model, p, schedule, t, x0, index)
    cost = sum(steps)
    steps.clear()
    regular = simulate(model, p, schedule, whole, x0, index)
    assert cost <= 1.1 * sum(steps)
    monkeypatch.setattr(simulation, 'gap_refinement', lambda *a: None)
    steps.clear()
    reference = simulate(model, p, schedule, t, x0, index)
    assert sum(steps) > 20 * cost                  # the substeps of the gap on every interval
    # the reference takes steps of 1/200 interval: its error is negligible beside RK4's at the
    # regular step, the error of the record without the loss
    fine = simulate(model, p, schedule, whole, x0, index, max_step=5e-4)
    kept = np.isin(whole, t)
    for what in ('x', 'dy'):
        error = np.abs(getattr(sim, what) - getattr(reference, what))
        rk4 = np.abs(getattr(regular, what)[kept] - getattr(fine, what)[kept])
        axes = (0,) if what == 'x' else (0, 1)
        assert np.all(np.max(error, axis=axes) <= 2.0 * np.max(rk4, axis=axes) + 1e-12), what


@pytest.mark.parametrize('varying', [(True, True), (True, False), (False, False)])
def test_rk4_step_derivatives_equal_finite_differences_of_the_step(varying):
    # the filter's ∂Φ of every RK4 step (all state columns at once) and the batched
    # matrix-vector products under it: central differences of Φ along dF, for a varying
    # (periodic) or constant F and ∂F
    from rotor_id.estimation import simulate as sim
    rng = np.random.default_rng(11)
    M, k, n = 6, 3, 4
    F = rng.standard_normal((2 * M + 1 if varying[0] else 1, n, n))
    dF = rng.standard_normal((2 * M + 1 if varying[1] else 1, k, n, n))
    h = rng.uniform(0.05, 0.2, M)
    got = np.broadcast_to(sim.rk4_transition_derivative(F, dF, h), (M, k, n, n))
    eps = 1e-6
    for i in range(k):
        fd = (sim.rk4_transition(F + eps * dF[:, i], h)
              - sim.rk4_transition(F - eps * dF[:, i], h)) / (2 * eps)
        assert np.max(np.abs(got[:, i] - fd)) < 1e-8 * np.max(np.abs(fd))
    # column c of ∂Φ is the step derivative from the unit state e_c (the per-column form)
    for c in range(n):
        unit = np.zeros((M, n))
        unit[:, c] = 1.0
        column = sim._rk4_step_derivative(F, np.zeros((1, n)), h, dF, np.zeros((1, k, n)), unit)
        assert np.allclose(column, got[..., c], rtol=0, atol=1e-13)
