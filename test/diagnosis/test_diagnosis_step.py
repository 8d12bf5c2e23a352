"""
The RK4 step of the diagnosis's fits (:func:`rotor_id.diagnosis.catalogue.record_step`).

One RK4 step per sample interval where the baseline model so integrated stays within the
policy's ``integration_error`` of each channel's noise of its integration at the default step:
a one-second 4-blade record at μ = 0.35 and 1 kHz (0.094 rad a sample) takes it; a stricter
tolerance, or a record sampled finer than the default step, keeps the default. The baseline
of the table is then the run's model refitted at that step, within the tolerance's share of
the run's own fit in log L.
"""

from dataclasses import replace

import numpy as np
from rotor_id.diagnosis.catalogue import record_step, Setting
from rotor_id.diagnosis.likelihood import OutputError
from rotor_id.diagnosis.policy import DEFAULT_POLICY
from rotor_id.estimation.simulate import DEFAULT_MAX_STEP
from rotor_id.io.run_description import parse_run_description
from rotor_id.pipeline import identify
import truth_generator as truth


def _forward_flight_fit():
    cfg = truth.mu04_case(seed=3, mu=0.35, t0=truth.TruthConfig.t0, time_delay_s=0.0003)
    record = truth.generate(cfg)
    description = parse_run_description(truth.run_description_text(cfg, 'multiblade',
                                                                   ('gamma', 'theta0')))
    return record, identify(record, description)


def test_one_step_per_sample_where_it_is_within_the_tolerance_of_the_noise():
    record, ident = _forward_flight_fit()
    interval = float(np.max(np.diff(ident.experiments[0].t)))
    assert interval > 1.5 * DEFAULT_MAX_STEP                # 0.094 rad: two default steps
    assert record_step(ident, DEFAULT_POLICY.integration_error) == interval
    # measured: the sample step moves the outputs by at most 1.6e-4 of the noise here
    assert record_step(ident, 1e-6) == DEFAULT_MAX_STEP
    # the table's baseline: the run's model refitted at that step, as every candidate is
    setting = Setting.of(record, ident, max_step=interval)
    refit = OutputError(setting, ident, n_obs=1).baseline()
    n = sum(e.t.size * e.model.n_outputs for e in ident.experiments)
    # an output change δ ≤ 1e-3 σ moves log L by at most about √N·δ/σ (random residuals)
    assert abs(refit.loglik + ident.estimate.neg_log_likelihood) <= \
        3.0 * np.sqrt(n) * DEFAULT_POLICY.integration_error
    # the default step keeps the run's own estimate
    same = OutputError(Setting.of(record, ident), ident, n_obs=1).baseline()
    assert same.estimate is ident.estimate


def test_a_record_sampled_finer_than_the_default_step_keeps_it():
    record, ident = _forward_flight_fit()
    exp = ident.experiments[0]
    fine = exp.t[0] + 0.5 * (exp.t - exp.t[0])              # the same samples, twice as dense
    ident.experiments[0] = replace(exp, t=fine)
    assert record_step(ident, DEFAULT_POLICY.integration_error) == DEFAULT_MAX_STEP
