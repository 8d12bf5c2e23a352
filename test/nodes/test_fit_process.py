"""
The identifier's fits, ROS-free (rotor_id/nodes/fit_process.py).

What it proves, on the demo's wake window from the simulated plant: a progress callback that
answers STOP ends the fit after that iteration, through ``identify`` (a final request stops a
growing-window fit this way; the answer was once dropped on its way to the estimator, and the
final waited for the whole growing-window fit); a fit told to hurry skips the extrapolation of
how much more data its targets need (additional_data_s -1: unknown) and one that is not gives
it; the fit process gives the same estimate as a fit in the caller's thread; the model the
live fits keep per description structure (built once, not per fit) gives the estimate a fresh
model gives, is shared only by descriptions that differ in their starting values, and the
bound history's last σ is the fit's own Cramér-Rao σ (one run: no double pseudo-inverse).
"""

from dataclasses import replace
import math

import numpy as np
import pytest
from rotor_id.commands.demo import case_files
from rotor_id.estimation.output_error import STOP
from rotor_id.io.run_description import load_run_description
from rotor_id.nodes.fit_process import fit_window, FitOptions, FitProcess, live_model
from rotor_id.nodes.live import bound_history
from rotor_id.nodes.test_points import TestPointSequence
from rotor_id.pipeline import identify

from test_test_points import _stream, OMEGA, WINDOW  # noqa: I100


@pytest.fixture(scope='module')
def request_and_description():
    """Return the final FitRequest of the first test point and the demo's wake description."""
    data = _stream(points=1)
    machine = TestPointSequence(4, WINDOW, [f'blade_{k}' for k in range(1, 5)],
                                auto_start='data')
    final = None
    for i, stamp in enumerate(data['stamps']):
        machine.add_flap(int(stamp), data['flap'][i])
        machine.add_pitch(int(stamp), data['pitch'][i])
        machine.add_azimuth(int(stamp), data['psi'][i], OMEGA)
        request = machine.due()
        if request is not None and request.final:
            final = request
            break
    assert final is not None and final.record is not None
    return final, load_run_description(case_files('wake')[1])


def _options(targets=(0.0, 0.0, 0.0), full_verdict=True):
    return FitOptions(max_iter=30, multi_start=False, step_tol=1e-3, targets=targets,
                      full_verdict=full_verdict)


def test_stop_ends_the_fit_after_that_iteration(request_and_description):
    request, desc = request_and_description
    seen = []

    def progress(info):
        seen.append(info['iteration'])
        return STOP
    ident, _, timing = fit_window(request, desc, _options(), progress)
    assert len(seen) == 1 and ident.estimate.iterations == 1 == timing['iterations']
    full, _, timing = fit_window(request, desc, _options())
    assert full.estimate.converged and timing['iterations'] > 1


def test_a_hurried_fit_skips_the_data_length_extrapolation(request_and_description):
    request, desc = request_and_description
    unreachable = (1e-9, 1e-9, 1e-9)                 # never met: the verdict extrapolates
    _, verdict, _ = fit_window(request, desc, _options(unreachable))
    assert verdict[0] is False and verdict[1] > 0
    _, verdict, _ = fit_window(request, desc, _options(unreachable), hurry=lambda: True)
    assert verdict == (False, -1.0)


def test_the_fit_process_gives_the_callers_estimate(request_and_description):
    request, desc = request_and_description
    here, _, _ = fit_window(request, desc, _options())
    fitter = FitProcess()
    try:
        assert math.isfinite(fitter.wait_ready())
        there, _, timing = fitter.fit(request, desc, _options())
    finally:
        fitter.close()
    np.testing.assert_allclose(there.estimate.values, here.estimate.values, rtol=1e-12)
    assert timing['fit_cpu'] > 0


def test_the_kept_model_gives_a_fresh_models_estimate(request_and_description):
    request, desc = request_and_description
    warm = replace(desc, initial_guess={'A': 0.45, 'AL_over_tau': 0.22, 'inv_tau': 0.11})
    assert live_model(warm) is live_model(desc)      # starting values only: the same model
    other = replace(desc, rotor=replace(desc.rotor, flap_frequency=desc.rotor.flap_frequency
                                        * 1.01))
    assert live_model(other) is not live_model(desc)
    assert live_model(other).rotor.flap_frequency != live_model(desc).rotor.flap_frequency
    for _ in range(2):                               # the second fit reuses the kept model
        kept, _, _ = fit_window(request, warm, _options())
    fresh = identify(request.record, warm, window_s=request.window_s, multi_start=False,
                     max_iter=30, step_tol=1e-3, check_adequacy=False)
    assert kept.estimate.iterations == fresh.estimate.iterations
    np.testing.assert_allclose(kept.estimate.values, fresh.estimate.values, rtol=1e-12)


def test_the_bound_historys_last_sigma_is_the_fits(request_and_description):
    request, desc = request_and_description
    ident, _, _ = fit_window(request, desc, _options())
    t, std = bound_history(ident)
    assert t.size == ident.experiments[0].t.size and np.isnan(std[0]).all()
    sigma = [ident.estimate.std_of(n) for n in ident.unknowns]
    np.testing.assert_allclose(std[-1], sigma, rtol=1e-6)
    good = np.isfinite(std).all(axis=1)
    assert np.all(np.diff(std[good], axis=0) <= 1e-12 * std[good][1:])   # σ falls with data
