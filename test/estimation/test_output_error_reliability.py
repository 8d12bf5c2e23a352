"""Output-error ML on problems a user should be warned about (pins #7)."""

import numpy as np
import pytest

from rotor_id.estimation.output_error import Experiment, fit_output_error, IdentificationError
from rotor_id.estimation.simulate import simulate
from rotor_id.physics.models import MultibladeWake
from rotor_id.physics.stirring import StirringSchedule

WAKE = MultibladeWake()
SCHEDULE = StirringSchedule(collective=2.0, t0=70.0)
TRUTH = np.array([0.5, 0.25, 0.125])
UNKNOWNS = ['A', 'AL_over_tau', 'inv_tau']


def test_unexcited_window_names_the_dependent_combination():
    """Before stirring the rotor sits in trim: 2 outputs cannot fix 3 wake parameters."""
    t = 40.0 + 0.1 * np.arange(121)
    x0 = WAKE.equilibrium(40.0, TRUTH, SCHEDULE([40.0]))
    y = simulate(WAKE, TRUTH, SCHEDULE, t, x0).y
    y = y + 0.01 * np.random.default_rng(0).standard_normal(y.shape)
    est = fit_output_error([Experiment(WAKE, SCHEDULE, t, y, initial_state='equilibrium')],
                           UNKNOWNS, noise_std=0.01)
    text = ' '.join(est.warnings)
    assert 'not identifiable' in text
    assert all(name in text for name in UNKNOWNS)   # the combination is written out


def test_excited_window_has_no_dependence_warning():
    t = 70.0 + 0.1 * np.arange(121)
    x0 = WAKE.equilibrium(70.0, TRUTH, SCHEDULE([69.0]))
    y = simulate(WAKE, TRUTH, SCHEDULE, t, x0).y
    est = fit_output_error([Experiment(WAKE, SCHEDULE, t, y, initial_state=x0)], UNKNOWNS,
                           noise_std=0.01)
    assert not [w for w in est.warnings if 'identifiable' in w]
    assert est.converged and est.message == 'converged'


def test_non_physical_optimum_stops_at_the_bound_with_the_reason():
    """Data from a wake that grows (1/τ < 0) cannot be fitted within the physical bounds."""
    t = 70.0 + 0.1 * np.arange(121)
    x0 = WAKE.equilibrium(70.0, TRUTH, SCHEDULE([69.0]))
    y = simulate(WAKE, [0.5, 0.25, -0.05], SCHEDULE, t, x0).y
    est = fit_output_error([Experiment(WAKE, SCHEDULE, t, y, initial_state=x0)], UNKNOWNS,
                           noise_std=0.01)
    assert est.value('inv_tau') == pytest.approx(WAKE.parameter('inv_tau').lower)
    assert 'physical bound: inv_tau' in est.message
    assert any('limited by the bound' in w for w in est.warnings)


def test_nan_samples_are_refused_with_what_to_do():
    t = 70.0 + 0.1 * np.arange(20)
    y = np.zeros((20, 2))
    y[5, 0] = np.nan
    with pytest.raises(IdentificationError, match='NaN or inf.*drop those samples'):
        fit_output_error([Experiment(WAKE, SCHEDULE, t, y)], UNKNOWNS)


def test_unknown_parameter_is_refused_with_the_valid_names():
    t = 70.0 + 0.1 * np.arange(20)
    with pytest.raises(IdentificationError, match='gamma.*A, AL_over_tau, inv_tau'):
        fit_output_error([Experiment(WAKE, SCHEDULE, t, np.zeros((20, 2)))], ['gamma'])
