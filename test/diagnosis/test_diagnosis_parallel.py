"""Cross-validation split into its two directions (one per worker) gives the same RMS."""

import math
from pathlib import Path

import pytest
from rotor_id.diagnosis.catalogue import (combine_halves, Job, validate_candidate,
                                          validation_halves)
from rotor_id.io.bag import read_run
from rotor_id.io.run_description import load_run_description
from rotor_id.pipeline import identify

RECORDINGS = Path(__file__).resolve().parents[2].parent / 'shared' / 'recordings'


def test_combine_halves_is_the_rms_of_both_directions():
    """√((r0² + r1²)/2): the mean square over channels and directions, from each direction."""
    assert combine_halves(3.0, 4.0) == pytest.approx(math.sqrt(12.5), rel=1e-15)
    assert combine_halves(None, 4.0) is None


@pytest.mark.parametrize('effect', ['baseline', 'dynamic_inflow'])
def test_two_directions_as_two_jobs_equal_one_job(effect):
    """The baseline's and the wake's validation RMS from two half jobs equal one job's."""
    config = RECORDINGS / 'dx_dynamic_inflow.yaml'
    if not config.is_file():
        pytest.skip(f'{config} not available (practice recordings)')
    description = load_run_description(config)
    record = read_run(description)
    est = identify(record, description).estimate
    unknowns = list(description.unknowns)
    values = {n: est.model_parameters[n] for n in unknowns}
    known = {n: v for n, v in est.model_parameters.items() if n not in unknowns}
    job = Job(effect, '', record, description, values, unknowns, known,
              tuple(description.window_s))
    _, _, both = validate_candidate(job)
    halves = [validate_candidate(h)[2] for h in validation_halves(job)]
    assert both is not None and all(h is not None for h in halves)
    assert halves[0] != halves[1]                          # two different predictions
    assert combine_halves(*halves) == pytest.approx(both, rel=1e-12)
