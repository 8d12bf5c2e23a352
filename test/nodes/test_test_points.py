"""
The live identifier's test points without ROS (rotor_id/nodes/test_points.py).

What it proves, on the demo's wake case simulated by the plant's own stepper at 1 kHz:
three test points in a row, each armed by its excitation schedule, are each identified within
3σ of the truth from exactly their own window's samples; a window missing samples at its start,
in its middle or at its end (in any channel), an azimuth that slips, a first sample not received
or a starved consumer that lost the oldest samples is never reported converged, and says what
is missing; the state machine moves idle -> armed -> recording -> fitting -> done/aborted with
the reason as a value; buffers stay bounded by the window; the streaming azimuth unwrapper is
the bag reader's rule bit for bit.
"""

from collections import deque
import math
import os

from hypothesis import given, settings, strategies as st
import numpy as np
import pytest
from rotor_id.io.run_description import load_run_description
from rotor_id.io.timebase import AzimuthUnwrapper, TWO_PI, unwrap_azimuth
from rotor_id.nodes.live import PlantStepper, rotor_constants, StampedSeries
from rotor_id.nodes.test_points import (channel_coverage, check_window, Excitation,
                                        FitSchedule, outcome, Phase, Reason,
                                        TestPointSequence)
from rotor_id.physics.stirring import StirringSchedule
from rotor_id.pipeline import identify

OMEGA = 2 * math.pi * 15
RATE = 1000
MS = 1_000_000
WAKE = {'A': 0.5, 'AL_over_tau': 0.25, 'inv_tau': 0.125}
THETA0 = math.radians(2.0)
WINDOW = (0.80939, 0.93671)
LENGTH = 1000                          # samples per test point (the window ends at 937)
BASE = 1_700_000_000 * 1_000_000_000   # stamp of the first sample
BLADES = [f'blade_{k}' for k in range(1, 5)]


def _stream(points=3, noise=math.radians(0.05), seed=3):
    """
    Simulate the plant's samples of ``points`` test points of LENGTH samples (own schedules).

    Test point k starts at sample k*LENGTH from trim: the cyclic step one revolution later and
    progressing stirring 70 after (the demo's schedule, so WINDOW is its identification window).
    """
    stepper = PlantStepper('multiblade_wake', rotor_constants(4, 0.0, 1.2, 0.97), WAKE, OMEGA,
                           RATE, THETA0, flap_noise_std=noise, pitch_noise_std=noise / 10,
                           seed=seed)
    t_first = [stepper.step * (k * LENGTH + 1) for k in range(points)]
    schedules = [StirringSchedule(THETA0, math.radians(1.5), -0.1 / math.pi,
                                  tk + TWO_PI + 70.0, tk + TWO_PI) for tk in t_first]

    def command(t):
        k = max(0, int(np.searchsorted(t_first, t, side='right')) - 1)
        return schedules[k]([t])[0]

    parts = []
    for block in range(points * LENGTH // 5):
        for j in range(5):
            tc = stepper.t + stepper.step * (j + 1)
            stepper.command(tc, command(tc))
        parts.append(stepper.advance(5))
    t, flap, pitch = (np.concatenate(p) for p in zip(*parts))
    stamps = BASE + np.arange(t.size, dtype=np.int64) * MS
    return {'stamps': stamps, 't': t, 'psi': np.mod(t, TWO_PI), 'flap': flap, 'pitch': pitch}


@pytest.fixture(scope='module')
def stream():
    """Three test points of the wake plant, with noise."""
    return _stream()


def _feed(machine, data, drop=None, excitation=None, late=20):
    """
    Feed the samples in order; return the fit requests the machine asks for.

    ``drop``: {channel: set of sample indices} not delivered. ``excitation``: {sample index:
    phase} delivered ``late`` samples after the sample it is stamped with (as a command that
    arrives after the sensor data it refers to).
    """
    drop = drop or {}
    events = {i + late: (phase, data['stamps'][i]) for i, phase in (excitation or {}).items()}
    requests = []
    for i, stamp in enumerate(data['stamps']):
        if i not in drop.get('flap', ()):
            machine.add_flap(int(stamp), data['flap'][i])
        if i not in drop.get('pitch', ()):
            machine.add_pitch(int(stamp), data['pitch'][i])
        if i not in drop.get('azimuth', ()):
            machine.add_azimuth(int(stamp), data['psi'][i], OMEGA)
        if i in events:
            machine.on_excitation(*events[i])
        request = machine.due(worker_idle=True)
        if request is not None:
            requests.append(request)
    return requests


def _schedules(points):
    """Return the excitation's phases of each test point: trim, step, stirring, done."""
    phases = {}
    for k in range(points):
        phases.update({k * LENGTH: Excitation.TRIM, k * LENGTH + 67: Excitation.CYCLIC_STEP,
                       k * LENGTH + 810: Excitation.STIRRING,
                       k * LENGTH + 960: Excitation.DONE})
    return phases


def _machine(**kw):
    return TestPointSequence(4, WINDOW, BLADES, **kw)


def _finals(requests):
    return [r for r in requests if r.final]


def test_three_test_points_in_a_row_each_identified_from_its_own_window(stream):
    machine = _machine()
    requests = _feed(machine, stream, excitation=_schedules(3))
    finals = _finals(requests)
    assert [r.test_point for r in finals] == [1, 2, 3]
    assert all(any(not r.final and r.test_point == k for r in requests) for k in (1, 2, 3))
    description = load_run_description(
        __import__('pathlib').Path(__file__).parents[2] / 'config' / 'demo_wake.yaml')
    first, last = math.ceil(WINDOW[0] * RATE), math.floor(WINDOW[1] * RATE)
    for k, request in enumerate(finals):
        # its origin is its own first sample, found in the buffer although the command came late
        assert request.stamp0_ns == stream['stamps'][k * LENGTH]
        assert request.check.complete, request.check.describe()
        assert request.check.used_ns() == (stream['stamps'][k * LENGTH + first],
                                           stream['stamps'][k * LENGTH + last])
        # the samples of the window are exactly this test point's (none of another)
        rec = request.record.window(*WINDOW)
        index = np.round(rec.time_s * RATE).astype(int) + k * LENGTH
        assert index[0] == k * LENGTH + first and index[-1] == k * LENGTH + last
        assert np.array_equal(rec.blade_flap, stream['flap'][index])
        ident = identify(request.record, description, window_s=request.window_s)
        est = ident.estimate
        assert est.converged
        assert outcome(request.check, True, est.converged) == 'converged'
        for name in WAKE:
            assert abs(est.values[est.names.index(name)] - WAKE[name]) < 3 * est.std_of(name)
        assert machine.finish(request.test_point, 'converged').phase == Phase.DONE
    assert [machine.points[k].reason for k in (1, 2, 3)] == [Reason.CONVERGED] * 3
    assert machine.phase == Phase.IDLE


def _one_test_point(stream, drop):
    machine = _machine()
    requests = _feed(machine, stream, drop=drop, excitation={0: Excitation.TRIM})
    return [r for r in requests if r.test_point == 1]


@pytest.mark.parametrize('channel', ['flap', 'pitch', 'azimuth'])
@pytest.mark.parametrize('where', ['start', 'middle', 'end'])
def test_a_window_missing_samples_is_never_converged(stream, channel, where):
    lo, hi = math.ceil(WINDOW[0] * RATE), math.floor(WINDOW[1] * RATE)
    # two samples lost, at the window's first samples, in its middle, at its last samples
    first = {'start': lo, 'middle': (lo + hi) // 2, 'end': hi - 1}[where]
    requests = _one_test_point(stream, {channel: {first, first + 1}})
    final = _finals(requests)[0]
    check = final.check
    assert not check.complete
    assert outcome(check, True, True) == 'incomplete'
    assert set(check.missing) == {channel} and check.missing[channel] >= 1, check.describe()
    assert channel in check.describe()
    coverage = next(c for c in check.channels if c.name == channel)
    part = {'start': coverage.missing_start, 'middle': coverage.missing_inside,
            'end': coverage.missing_end}[where]
    assert part >= 1, check.describe()
    if channel == 'flap' and where != 'middle':   # the samples used, not the bounds asked
        used = check.used_ns()
        expected = {'start': (stream['stamps'][lo + 2], stream['stamps'][hi]),
                    'end': (stream['stamps'][lo], stream['stamps'][hi - 2])}[where]
        assert used == expected
    # the fit still runs (values for a person to look at), but the claim is 'incomplete'
    assert final.record is not None


def test_one_lost_sample_counts_and_jitter_does_not():
    stamps = np.arange(0, 200 * MS, MS)
    jitter = stamps + np.round(np.random.default_rng(1).uniform(-0.2, 0.2, stamps.size) * MS)
    assert channel_coverage('x', jitter.astype(np.int64), 50 * MS, 150 * MS).complete
    lost = np.delete(stamps, 100)
    assert channel_coverage('x', lost, 50 * MS, 150 * MS).missing_inside == 1
    # a window that starts or ends inside a loss: the bounds count, within 1.5 periods
    assert channel_coverage('x', np.delete(stamps, [50, 51]), 50 * MS, 150 * MS).missing_start == 2
    assert channel_coverage('x', np.delete(stamps, [149, 150]), 50 * MS,
                            150 * MS).missing_end == 2
    assert channel_coverage('x', stamps, 49 * MS + MS // 2, 150 * MS).complete
    # the one sample stamped on the window's start, or end, lost: the neighbours tell
    assert channel_coverage('x', np.delete(stamps, 50), 50 * MS, 150 * MS).missing_start == 1
    assert channel_coverage('x', np.delete(stamps, 150), 50 * MS, 150 * MS).missing_end == 1
    assert channel_coverage('x', np.delete(stamps, 49), 50 * MS, 150 * MS).complete
    assert not channel_coverage('x', stamps[:1], 0, 150 * MS).complete


def test_an_azimuth_that_slips_is_an_inconsistent_time_base(stream):
    machine = _machine()
    lo = int(round(WINDOW[0] * RATE))
    bad = dict(stream, psi=stream['psi'].copy())
    bad['psi'][lo + 40:] = np.mod(bad['psi'][lo + 40:] + 0.3, TWO_PI)   # an encoder jump
    final = _finals(_feed(machine, bad, excitation={0: Excitation.TRIM}))[0]
    assert not final.check.time_base_consistent and not final.check.complete
    assert final.check.azimuth_slips == 1
    assert 'azimuth' in final.check.describe()
    assert outcome(final.check, True, True) == 'incomplete'


def test_a_first_sample_not_received_makes_every_result_incomplete(stream):
    # the schedule started at sample 0, the identifier received flap only from sample 30 on
    requests = _one_test_point(stream, {'flap': set(range(30))})
    assert requests and all(not r.check.complete for r in requests)
    assert all('first flap sample' in r.check.describe() for r in requests)
    assert requests[-1].stamp0_ns == stream['stamps'][30]


def test_a_first_sample_lost_from_a_regular_stream_is_placed_by_its_grid(stream):
    """
    Test point 2's first 30 flap samples are lost (a best-effort stream on a loaded machine).

    The samples before them (test point 1's) and after them lie on one 1 ms grid, so the lost
    first sample's stamp is known: the window starts exactly where it would have, its samples
    are all there, and the result may claim convergence.
    """
    drop = {'flap': set(range(LENGTH, LENGTH + 30))}
    finals = _finals(_feed(_machine(), stream, drop=drop, excitation=_schedules(2)))
    whole = _finals(_feed(_machine(), stream, excitation=_schedules(2)))
    assert [r.test_point for r in finals] == [1, 2]
    lost, kept = finals[1], whole[1]
    assert lost.stamp0_ns == stream['stamps'][LENGTH] == kept.stamp0_ns
    assert lost.check.complete, lost.check.describe()
    window, reference = lost.record.window(*WINDOW), kept.record.window(*WINDOW)
    assert np.array_equal(window.time_s, reference.time_s)
    assert np.array_equal(window.blade_flap, reference.blade_flap)


def test_a_first_sample_lost_from_an_irregular_stream_is_not_placed(stream):
    """Where the step over the loss is not a whole number of periods, nothing is inferred."""
    data = dict(stream)
    data['stamps'] = stream['stamps'].copy()
    data['stamps'][LENGTH + 30:] += MS // 2        # 30.5 periods from the last sample before
    drop = {'flap': set(range(LENGTH, LENGTH + 30))}
    finals = _finals(_feed(_machine(), data, drop=drop, excitation=_schedules(2)))
    assert finals[1].stamp0_ns == data['stamps'][LENGTH + 30]
    assert not finals[1].check.complete
    assert 'first flap sample' in finals[1].check.describe()


def test_a_starved_consumer_loses_the_oldest_samples_and_says_so(stream):
    """
    A subscriber's queue keeps the newest ``depth`` samples (DDS keep-last); the consumer stalls.

    The consumer takes samples as they come, then stalls for 200 ms from 50 ms before the
    window (a starved executor): when it resumes, the queue of 100 holds the newest 100, so the
    window's first 51 samples are lost in every channel. The final estimate must not be converged.
    """
    machine = _machine()
    depth, lo = 100, math.ceil(WINDOW[0] * RATE)
    queues = {c: deque(maxlen=depth) for c in ('flap', 'pitch', 'azimuth')}
    requests = []
    for i, stamp in enumerate(stream['stamps'][:LENGTH]):
        queues['flap'].append((int(stamp), stream['flap'][i]))
        queues['pitch'].append((int(stamp), stream['pitch'][i]))
        queues['azimuth'].append((int(stamp), stream['psi'][i]))
        if i == 20:
            machine.on_excitation(Excitation.TRIM, int(stream['stamps'][0]))
        if lo - 50 <= i < lo + 150:
            continue                                  # stalled
        for channel, queue in queues.items():
            while queue:
                s, v = queue.popleft()
                if channel == 'azimuth':
                    machine.add_azimuth(s, v, OMEGA)
                else:
                    getattr(machine, f'add_{channel}')(s, v)
        request = machine.due()
        if request is not None:
            requests.append(request)
    final = _finals(requests)[0]
    assert not final.check.complete
    lost = 150 - depth + 1
    assert all(c.missing_start == lost for c in final.check.channels), final.check.describe()
    assert outcome(final.check, True, True) == 'incomplete'


def test_state_machine_transitions_and_reasons(stream):
    machine = _machine(auto_start='none')
    assert machine.phase == Phase.IDLE
    machine.on_excitation(Excitation.TRIM, 0)       # auto start off: ignored
    assert machine.phase == Phase.IDLE
    point, text = machine.arm()
    assert point.number == 1 and 'test point 1 armed' in text and machine.phase == Phase.ARMED
    again, text = machine.arm()
    assert again is None and 'test point 1 (armed) is in progress' in text
    machine.add_flap(int(stream['stamps'][0]), stream['flap'][0])
    assert machine.phase == Phase.RECORDING and point.stamp0_ns == stream['stamps'][0]
    aborted = machine.abort()
    assert aborted is point and point.phase == Phase.ABORTED
    assert point.reason == Reason.ABORT_REQUESTED and machine.phase == Phase.IDLE
    assert machine.abort() is None
    assert machine.finish(1, 'converged') is None       # an aborted point's result is dropped
    assert point.describe() == 'test point 1 (aborted: abort requested)'

    # excitation: a new schedule supersedes the one recording; an early end aborts
    machine = _machine()
    requests = _feed(machine, {k: v[:500] for k, v in stream.items()},
                     excitation={0: Excitation.TRIM, 100: Excitation.STIRRING,
                                 300: Excitation.TRIM})
    assert not _finals(requests)
    assert machine.points[1].phase == Phase.ABORTED
    assert machine.points[1].reason == Reason.SUPERSEDED
    assert machine.points[2].phase == Phase.RECORDING
    assert machine.points[2].stamp0_ns == stream['stamps'][300]
    machine.on_excitation(Excitation.RAMP_DOWN, int(stream['stamps'][499]))
    assert machine.points[2].reason == Reason.EXCITATION_ENDED and machine.phase == Phase.IDLE
    machine.on_excitation(Excitation.DONE, int(stream['stamps'][499]))
    assert machine.phase == Phase.IDLE and machine.count == 2
    # a DONE after the window's end leaves the test point alone
    machine.on_excitation(Excitation.TRIM, int(stream['stamps'][499]))
    machine.add_flap(int(stream['stamps'][499]), stream['flap'][499])
    machine.on_excitation(Excitation.DONE, int(stream['stamps'][499]) + 2 * 10**9)
    assert machine.phase == Phase.RECORDING and machine.count == 3

    # the final request moves the point to FITTING; the next one can be armed meanwhile
    machine = _machine(auto_start='data')
    final = _finals(_feed(machine, {k: v[:LENGTH] for k, v in stream.items()}))[0]
    assert machine.points[1].phase == Phase.FITTING and machine.phase == Phase.IDLE
    second, _ = machine.arm()
    assert second.number == 2
    assert machine.finish(final.test_point, 'incomplete').reason == Reason.INCOMPLETE
    with pytest.raises(ValueError, match='auto_start'):
        _machine(auto_start='stirring')


def test_buffers_stay_bounded_by_the_window():
    machine = _machine(schedule=FitSchedule(update_every_rad=0.0))
    n = 20 * RATE                                     # 20 s of samples, no test point
    for i in range(n):
        stamp = BASE + i * MS
        machine.add_flap(stamp, np.zeros(4))
        machine.add_pitch(stamp, np.zeros(4))
        machine.add_azimuth(stamp, (OMEGA * i / RATE) % TWO_PI, OMEGA)
    need = ((WINDOW[1] - WINDOW[0]) + 2 * 3 * math.pi / OMEGA + 5.0) * RATE
    for series in (machine.flap, machine.pitch, machine.azimuth.series):
        # what a window needs is kept; the arrays are trimmed, not grown (2.7x at most)
        assert need - 2 <= series.size <= series.capacity <= 4 * need
        assert series.last_stamp == BASE + (n - 1) * MS


def test_streaming_unwrap_is_the_bag_readers_rule_bit_for_bit():
    rng = np.random.default_rng(5)
    stamps = np.cumsum(rng.integers(500_000, 40_000_000, 400)).astype(np.int64)
    omega = OMEGA * (1 + 0.05 * np.sin(np.arange(400) / 30))
    truth = np.cumsum(omega * np.diff(stamps, prepend=stamps[0]) / 1e9) + 1.0
    wrapped = np.mod(truth, TWO_PI)
    unwrapper = AzimuthUnwrapper()
    streamed = np.array([unwrapper.add(int(s), p, w) for s, p, w in zip(stamps, wrapped, omega)])
    batch = unwrap_azimuth(wrapped, (stamps - stamps[0]) / 1e9, omega)
    assert np.array_equal(streamed, batch)
    assert np.allclose(streamed, truth - truth[0] + wrapped[0], atol=1e-9)


def test_a_series_trimmed_keeps_order_and_values():
    series = StampedSeries(1, capacity=8)
    for i in range(100):
        series.append(i, [float(i)], keep_from_ns=i - 5)
    assert series.capacity <= 16
    assert np.array_equal(series.stamps, series.values[:, 0].astype(int))
    assert series.last_stamp == 99 and series.first_stamp >= 94 - 8


def test_check_window_of_a_complete_stream(stream):
    machine = _machine(auto_start='data')
    _feed(machine, {k: v[:LENGTH] for k, v in stream.items()})
    lo = BASE + int(WINDOW[0] * 1e9)
    hi = BASE + int(WINDOW[1] * 1e9)
    check = check_window(machine.flap, machine.pitch, machine.azimuth.series, lo, hi)
    assert check.complete and check.describe() == '' and check.missing == {}


def _final_check(drops, jitter_seed, offset_ms):
    """Feed a 1 kHz stream (±20 % stamp jitter) with samples dropped; return the final check."""
    rng = np.random.default_rng(jitter_seed)
    n = 1100
    stamps = BASE + np.arange(n) * MS + (rng.uniform(-0.2, 0.2, n) * MS).astype(np.int64)
    return _final_check_of(stamps, drops, offset_ms), stamps


def _final_check_of(stamps, drops, offset_ms=0):
    """Feed these stamps with samples dropped; return the final request."""
    drops = {c: drops.get(c, set()) for c in ('flap', 'pitch', 'azimuth')}
    machine = _machine(auto_start='none', schedule=FitSchedule(update_every_rad=0.0))
    start = 100 + offset_ms                            # the test point's first flap sample
    for i, stamp in enumerate(stamps):
        if i == start:
            machine.arm()
        if i not in drops['flap']:
            machine.add_flap(int(stamp), np.zeros(4))
        if i not in drops['pitch']:
            machine.add_pitch(int(stamp), np.zeros(4))
        if i not in drops['azimuth']:
            machine.add_azimuth(int(stamp), (OMEGA * (stamp - BASE) / 1e9) % TWO_PI, OMEGA)
        request = machine.due()
        if request is not None:
            return request
    raise AssertionError('no final request')


@settings(max_examples=3000 if os.environ.get('ROTOR_ID_SLOW') else 150, deadline=None)
@given(data=st.data())
def test_no_sample_of_the_window_is_lost_unnoticed(data):
    """
    Property: a loss inside the window is never missed, one a period outside never counts.

    A loss inside the window is never taken for a complete window, and a loss more than one
    sampling period outside it never spoils one.

    Samples are dropped at random, in any channel, around and inside the window (its start and
    end included), with ±20 % stamp jitter: a lost sample's stamp is known only from its
    neighbours, so one within the jitter of a bound counts as possibly inside (never the
    reverse); one further out is outside.
    """
    offset = data.draw(st.integers(0, 30))
    first = 100 + offset + math.ceil(WINDOW[0] * 1000) - 3
    last = 100 + offset + math.floor(WINDOW[1] * 1000) + 3
    near = st.integers(first, last)
    drops = {c: set(data.draw(st.lists(near, max_size=3), label=c))
             for c in ('flap', 'pitch', 'azimuth')}
    request, stamps = _final_check(drops, data.draw(st.integers(0, 2**16)), offset)
    check = request.check
    lost = [stamps[i] for c in drops for i in drops[c] if c != 'flap' or i != 100 + offset]
    lost_inside = any(check.lo_ns <= stamp <= check.hi_ns for stamp in lost)
    lost_near = any(check.lo_ns - MS <= stamp <= check.hi_ns + MS for stamp in lost)
    if lost_inside:
        assert not check.complete, (drops, check.describe())
        assert outcome(check, True, True) != 'converged'
    elif not lost_near:
        assert check.complete, (drops, check.describe())
        assert outcome(check, True, True) == 'converged'


@pytest.mark.parametrize('channel', ['flap', 'pitch', 'azimuth'])
@pytest.mark.parametrize('where', ['first', 'last'])
@pytest.mark.parametrize('side', ['inside', 'outside'])
def test_a_sample_lost_at_a_window_bound_under_jitter(channel, where, side):
    """
    A sample lost at a window bound under jitter is missing when inside, not when outside.

    ±20 % jitter, the sample nearest a bound lost. Stamped 0.1 period inside the window, with
    neighbours that put the even-spacing guess 0.15 period outside, it is missing; a full
    period outside the window it is not. The final fit waits for every stream past the end.
    """
    start = 100                                        # the test point's first flap sample
    index = start + {'first': math.ceil(WINDOW[0] * 1000),
                     'last': math.floor(WINDOW[1] * 1000)}[where]
    _, stamps = _final_check({}, 0, 0)                 # the jittered stream
    stamps = stamps.copy()
    bound = int(stamps[start]) + int(round(WINDOW[0 if where == 'first' else 1] * 1e9))
    into = 1 if where == 'first' else -1               # the direction into the window
    if side == 'outside':                              # the sample before (after) the window
        index -= into
    lost = bound + into * (MS // 10 if side == 'inside' else -MS)
    # move the stream from 30 samples before the loss on, in 0.1-period steps, to put the
    # lost sample where wanted with its grid (no gap made by the move)
    ramp = np.clip((np.arange(stamps.size) - (index - 30)) / 10, 0.0, 1.0)
    stamps += np.round((lost - (BASE + index * MS)) * ramp).astype(np.int64)
    stamps[index] = lost
    if side == 'inside':                               # the guess lands 0.15 period outside
        stamps[index - into] = lost - into * (MS + MS // 4)
        stamps[index + into] = lost + into * (3 * MS // 4)
    assert np.all(np.diff(stamps) > 0)
    request = _final_check_of(stamps, {channel: {index}})
    check = request.check
    assert (check.lo_ns <= lost <= check.hi_ns) == (side == 'inside')
    assert check.complete == (side == 'outside'), check.describe()
    if side == 'inside':
        coverage = next(c for c in check.channels if c.name == channel)
        assert (coverage.missing_start if where == 'first' else coverage.missing_end) == 1


def test_a_new_window_applies_from_the_next_test_point_never_to_one_in_progress(stream):
    machine = _machine(auto_start='none', schedule=FitSchedule(update_every_rad=0.0))
    machine.arm()
    half = {k: v[:400] for k, v in stream.items()}
    assert not _feed(machine, half)
    shorter = (0.5, 0.6)
    text = machine.set_window(shorter)
    assert 'applies from the next test point' in text
    assert 'test point 1 (recording) keeps its window 0.8094-0.9367 s' in text
    assert machine.points[1].window_s == WINDOW and machine.window_s == shorter
    # test point 1 still ends at its own window's end (not at 0.6 s, which it has passed)
    rest = {k: v[400:LENGTH] for k, v in stream.items()}
    finals = _finals(_feed(machine, rest))
    assert [(r.test_point, r.window_s) for r in finals] == [(1, WINDOW)]
    assert finals[0].check.complete, finals[0].check.describe()
    machine.finish(1, 'converged')
    point, text = machine.arm()
    assert point.window_s == shorter and '0.5000-0.6000 s' in text
    finals = _finals(_feed(machine, {k: v[LENGTH:2 * LENGTH] for k, v in stream.items()}))
    assert [(r.test_point, r.window_s) for r in finals] == [(2, shorter)]
    assert finals[0].stamp0_ns == stream['stamps'][LENGTH]
    first, last = math.ceil(0.5 * RATE), math.floor(0.6 * RATE)
    assert finals[0].check.used_ns() == (stream['stamps'][LENGTH + first],
                                         stream['stamps'][LENGTH + last])
    for bad in ((0.6, 0.5), (-0.1, 0.2), (0.1, math.inf), (0.1,), 'ab'):
        with pytest.raises(ValueError, match='window_s'):
            machine.set_window(bad)
    assert machine.window_s == shorter


def test_buffers_keep_the_longer_of_the_current_and_the_next_window():
    machine = _machine(auto_start='none', schedule=FitSchedule(update_every_rad=0.0),
                       pre_trigger_s=0.0)
    machine.arm()
    machine.set_window((0.0, 0.05))         # the next one is short: the current one's data stay
    for i in range(1200):
        stamp = BASE + i * MS
        machine.add_flap(stamp, np.zeros(4))
        machine.add_pitch(stamp, np.zeros(4))
        machine.add_azimuth(stamp, (OMEGA * i / RATE) % TWO_PI, OMEGA)
        if i == 600:
            assert machine.flap.first_stamp == BASE     # the whole recording window so far
