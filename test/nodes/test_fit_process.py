"""
The identifier's fits, ROS-free (rotor_id/nodes/fit_process.py).

What it proves, on the demo's wake window from the simulated plant: a progress callback that
answers STOP ends the fit after that iteration, through ``identify`` (a final request stops a
growing-window fit this way; the answer was once dropped on its way to the estimator, and the
final waited for the whole growing-window fit); a fit told to hurry skips the extrapolation of
how much more data its targets need (additional_data_s -1: unknown) and one that is not gives
it; the fit process gives the same estimate as a fit in the caller's thread.
"""

import math

import numpy as np
import pytest
from rotor_id.commands.demo import case_files
from rotor_id.estimation.output_error import STOP
from rotor_id.io.run_description import load_run_description
from rotor_id.nodes.fit_process import fit_window, FitOptions, FitProcess
from rotor_id.nodes.test_points import TestPointSequence

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
