"""The bounded stirring test point: its end, its ramp back to trim, its abort, its limits."""

import math

import numpy as np
import pytest
from rotor_id.excitation import (check_excitation_limits, PHASE_CYCLIC_STEP, PHASE_DONE,
                                 PHASE_RAMP_DOWN, PHASE_STIRRING, PHASE_TRIM, StirringTestPoint)
from rotor_id.physics.stirring import StirringSchedule

OMEGA = 2 * math.pi * 15                 # rad/s
DEG = math.radians(1.0)
SCHEDULE = StirringSchedule(collective=2 * DEG, amplitude=1.5 * DEG, omegadot=-0.1 / math.pi,
                            t0=70.0 + 2 * math.pi, t_step=2 * math.pi)


def point(duration_rad=20.0, max_rate=1e4, ramp_s=0.1):
    return StirringTestPoint(SCHEDULE, OMEGA, duration_rad, max_rate, ramp_s, 3 * DEG)


def cyclic(p, t):
    u = p.inputs(t)
    return np.hypot(u[:, 1], u[:, 2])


def test_end_of_schedule_by_duration_then_ramp_then_done():
    p = point(duration_rad=20.0, ramp_s=0.1)
    t_end = SCHEDULE.t0 + 20.0
    ramp = 0.1 * OMEGA                                     # 9.42 rad of azimuth
    assert p.t_end == pytest.approx(t_end) and p.t_done == pytest.approx(t_end + ramp)
    assert 'duration' in p.end_reason
    assert [p.phase(t) for t in (0.0, 10.0, SCHEDULE.t0 + 1, t_end + 1, t_end + ramp + 1e-9)] \
        == [PHASE_TRIM, PHASE_CYCLIC_STEP, PHASE_STIRRING, PHASE_RAMP_DOWN, PHASE_DONE]
    # up to the end the report's schedule, exactly
    t = np.linspace(0.0, t_end, 2001)
    np.testing.assert_array_equal(p.inputs(t), SCHEDULE.inputs(t))
    # the ramp: the cyclic vector frozen in direction, its size falling linearly to zero
    t = t_end + np.linspace(0.0, ramp, 11)
    u = p.inputs(t)
    np.testing.assert_allclose(cyclic(p, t), 1.5 * DEG * np.linspace(1, 0, 11), atol=1e-15)
    direction = np.arctan2(u[:-1, 1], u[:-1, 2])
    np.testing.assert_allclose(direction, direction[0], atol=1e-12)
    assert np.all(u[:, 0] == 2 * DEG)                       # the collective never moves
    # done: trim only, no stirring, for ever after
    t = t_end + ramp + np.array([1e-9, 1.0, 1e4])
    np.testing.assert_array_equal(cyclic(p, t), 0.0)
    assert all(p.stirring_rate(x) == 0.0 for x in t)


def test_stirring_rate_never_exceeds_its_limit():
    max_rate = 2 * math.pi * 15                             # 1 per rev
    p = point(duration_rad=1e6, max_rate=max_rate)
    assert 'max_stirring_rate' in p.end_reason
    t = np.linspace(0.0, p.t_done + 100.0, 20001)
    rates = np.array([abs(p.stirring_rate(x)) for x in t])
    assert rates.max() <= max_rate * (1 + 1e-12)
    assert rates.max() > 0.99 * max_rate                    # and it does reach it
    # the rate law 2 ω̇ (t − t0) Ω until then: the end follows from the limit analytically
    assert p.t_end - SCHEDULE.t0 == pytest.approx(max_rate / (2 * 0.1 / math.pi * OMEGA))


def test_abort_ramps_from_the_abort_time():
    p = point(duration_rad=50.0, ramp_s=0.2)
    t_abort = SCHEDULE.t0 + 5.0
    before = p.inputs([t_abort - 1e-6])
    assert p.abort(t_abort, 'operator') and p.aborted == 'operator'
    assert p.phase(t_abort) == PHASE_RAMP_DOWN
    assert p.t_done == pytest.approx(t_abort + 0.2 * OMEGA)
    np.testing.assert_allclose(p.inputs([t_abort]), before, atol=1e-6)   # no jump
    assert p.stirring_rate(t_abort + 0.1) == 0.0
    assert p.phase(p.t_done) == PHASE_DONE
    np.testing.assert_array_equal(cyclic(p, [p.t_done, p.t_done + 50.0]), 0.0)
    # a second abort, or one during the ramp, changes nothing
    assert not p.abort(t_abort + 1.0)
    assert p.t_done == pytest.approx(t_abort + 0.2 * OMEGA)


def test_abort_before_the_cyclic_step_is_done_at_once():
    p = point()
    assert p.abort(1.0)
    assert p.phase(1.0) == PHASE_DONE
    np.testing.assert_array_equal(cyclic(p, [1.0, 10.0, 100.0]), 0.0)


def test_abort_after_done_is_refused():
    p = point(duration_rad=5.0, ramp_s=0.0)
    assert p.phase(p.t_end) == PHASE_DONE
    assert not p.abort(p.t_end + 1.0) and p.aborted is None


@pytest.mark.parametrize('values, words', [
    ((4 * DEG, 3 * DEG, 10.0, 100.0, 0.5), ['amplitude_rad', 'max_amplitude_rad']),
    ((1.5, 0.5, 10.0, 100.0, 0.5), ['amplitude_rad = 1.5', 'degrees']),
    ((DEG, 3 * DEG, 0.0, 100.0, 0.5), ['duration_rad', 'positive']),
    ((DEG, 3 * DEG, 10.0, -1.0, 0.5), ['max_stirring_rate_rad_s', 'positive']),
    ((DEG, 3 * DEG, 10.0, 100.0, -0.1), ['ramp_s']),
    ((DEG, 3 * DEG, math.nan, 100.0, 0.1), ['duration_rad = nan']),
])
def test_limits_are_checked_with_a_reason(values, words):
    reason = check_excitation_limits(*values)
    assert reason is not None
    for word in words:
        assert word in reason
    with pytest.raises(ValueError, match=words[0]):
        StirringTestPoint(StirringSchedule(amplitude=values[0]), OMEGA, *values[2:4],
                          values[4], values[1])


def test_sane_limits_pass():
    assert check_excitation_limits(1.5 * DEG, 3 * DEG, 100.0, OMEGA, 0.5) is None
