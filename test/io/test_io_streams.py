"""The stream-fault detectors on their own: runs, interleaving (false alarms and power), phase."""

import numpy as np
import pytest
from rotor_id.io.streams import (
    BLOCK, interleaved_streams, MIN_BLOCKS, phase_outliers, spikes, split_runs,
)

MS = 1_000_000


def test_split_runs_separates_resets_and_drops_glitches():
    run1 = np.arange(1000) * MS
    run2 = -50_000 * MS + np.arange(800) * MS          # clock restarted 50 s earlier
    stamps = np.concatenate([run1, run2])
    stamps[300] += 3_600_000 * MS                      # one stamp an hour off
    split = split_runs(stamps)
    assert split.n_runs == 2 and not split.interleaved()
    assert split.glitches().tolist() == [300]
    assert np.all(split.labels[:1000][np.arange(1000) != 300] == 0)
    assert np.all(split.labels[1000:] == 1)
    assert split.jumps.tolist() == [1000]


def test_split_runs_keeps_gaps_and_reordering_in_one_run():
    stamps = np.concatenate([np.arange(500), np.arange(2500, 3000)]) * MS   # 2 s gap
    stamps[[100, 101]] = stamps[[101, 100]]                                # swapped pair
    split = split_runs(stamps)
    assert split.n_runs == 1 and split.glitches().size == 0


def test_split_runs_takes_a_late_burst_for_reordering_not_a_reset():
    """A driver delivering 30 ms of samples 80 ms late: the samples fill their own gap."""
    stamps = np.arange(2000) * MS
    late = stamps[1000:1030]
    order = np.concatenate([stamps[:1000], stamps[1030:1110], late, stamps[1110:]])
    split = split_runs(order)
    assert split.n_runs == 1 and split.glitches().size == 0


def test_split_runs_tells_two_clocks_interleaved():
    a = np.arange(600) * MS
    b = 7_000_000 * MS + np.arange(600) * MS
    stamps = np.empty(1200, dtype=np.int64)
    stamps[0::2], stamps[1::2] = a, b
    for first in (stamps, np.concatenate([stamps[1::2][:1], stamps])):   # either clock first
        split = split_runs(first, received_ns=np.arange(first.size) * MS // 2)
        assert split.n_runs == 2 and split.interleaved()


def smooth_signal(rng, n, rate_hz=1000.0):
    """Rotor-like signal: a few harmonics of 10-25 Hz, a step, white noise σ = 1."""
    t = np.arange(n) / rate_hz
    omega = 2 * np.pi * rng.uniform(10, 25)
    signal = sum(rng.uniform(0, 5) * np.sin(k * omega * t + rng.uniform(0, 6)) for k in (1, 2, 4))
    signal += rng.uniform(-20, 20) * (t > t[n // 2])
    return signal + rng.normal(size=n)


def test_interleaving_false_alarm_rate_on_one_sensor():
    """No alarm in 300 single-sensor records (the design rate is far below 1 in 300)."""
    rng = np.random.default_rng(7)
    alarms = 0
    for _ in range(300):
        n = int(rng.integers(MIN_BLOCKS * (BLOCK + 2) + 2, 20_000))
        values = smooth_signal(rng, n)[:, None]
        alarms += interleaved_streams(np.arange(n) * MS, values) is not None
    assert alarms == 0


@pytest.mark.parametrize('batch', [10, 12])
def test_a_noiseless_unwrapped_azimuth_is_one_stream(batch):
    """
    A simulated azimuth, unwrapped to hundreds of rad, computed batch by batch, is no alarm.

    rotor_plant at 2 kHz publishes ψ = t0 + step·k in batches of 10 samples (its 5 ms tick):
    the rounding left alternates with the parity of k (about 1e-14 rad), and was taken for
    two streams, refusing the bag of a 5-blade rig with an unwrapped azimuth.
    """
    step = 2.0 * np.pi * 15 / 2000
    t, out = 0.0, []
    while len(out) < 18_000:
        grid = t + step * np.arange(batch + 1)
        out.extend(grid[1:])
        t = float(grid[-1])
    psi = np.array(out)
    assert interleaved_streams(np.arange(psi.size) * MS // 2, psi[:, None]) is None
    # a second stream offset by 1e-9 rad (far above the rounding) is still found
    two = psi + np.where(np.arange(psi.size) % 2 == 0, 0.0, 1e-9)
    assert interleaved_streams(np.arange(psi.size) * MS // 2, two[:, None]) is not None


def test_quantised_sensor_and_held_command_are_one_stream():
    """A coarse ADC (most steps exactly 0) or a command held between updates is no alarm."""
    rng = np.random.default_rng(5)
    n = 20_000
    lsb = 0.5
    quantised = lsb * np.round((0.3 * np.sin(np.arange(n) / 400) + 0.3 * rng.normal(size=n))
                               / lsb)
    held = np.repeat(rng.normal(size=n // 10).cumsum(), 10)             # 100 Hz command
    for values in (quantised, held, held + quantised):
        assert interleaved_streams(np.arange(n) * MS, values[:, None]) is None


@pytest.mark.parametrize('offset', [1.0, 3.0])
def test_interleaving_is_found_at_an_offset_of_one_noise_sigma(offset):
    rng = np.random.default_rng(3)
    found = 0
    for _ in range(50):
        n = 4000
        values = smooth_signal(rng, n)
        values[1::2] += offset                         # second stream: calibration offset
        found += interleaved_streams(np.arange(n) * MS // 2, values[:, None]) is not None
    assert found == 50


def test_phase_outliers_repairs_glitches_and_reports_slips():
    rng = np.random.default_rng(0)
    phase = 0.001 * rng.normal(size=3000)
    phase[700] = -2.0                                  # glitch
    phase[1500:1502] += 0.8                            # two-sample glitch
    phase[2200:] += 0.5                                # slip
    steps = np.diff(phase)
    found = phase_outliers(steps, floor=0.02)
    assert found.repaired.tolist() == [700, 1500, 1501]
    assert len(found.slips) == 1 and found.slips[0][0] == 2200
    assert found.slips[0][1] == pytest.approx(0.5, abs=0.01)


def test_spikes_finds_isolated_speed_readings():
    rng = np.random.default_rng(1)
    speed = 94.0 + 0.5 * np.sin(np.arange(2000) / 300) + 0.01 * rng.normal(size=2000)
    speed[[10, 1200, 1201]] = [0.0, 180.0, 180.0]
    assert spikes(speed, floor=0.05 * 94).tolist() == [10, 1200, 1201]


def test_running_median_is_scipy_median_filter():
    """The spike detector's running median equals scipy.ndimage's, blocks or not."""
    from rotor_id.io.streams import _running_median, MEDIAN_SPAN
    from scipy.ndimage import median_filter
    rng = np.random.default_rng(4)
    for n in (MEDIAN_SPAN, MEDIAN_SPAN + 1, 1000, 70001):
        values = rng.standard_normal(n)
        values[::13] += 20.0                       # spikes
        want = median_filter(values, size=MEDIAN_SPAN, mode='nearest')
        assert np.array_equal(_running_median(values, MEDIAN_SPAN), want)
        assert np.array_equal(_running_median(values, MEDIAN_SPAN, block=997), want)


# ----------------------------------------------------------------------- value spikes (pins #36)

RATE_HZ, OMEGA = 1000.0, 2 * np.pi * 15.0
THETA0, CYCLIC = np.radians(2.0), np.radians(1.5)
PITCH_NOISE = np.radians(0.01)


def _blade_pitch(n_blades, event, noise=PITCH_NOISE, seconds=0.6, seed=0):
    """(n, N) blade pitch θ0 + θ1c cos ψk + θ1s sin ψk at 1 kHz, 15 rev/s, with ``event``."""
    time_s = np.arange(int(seconds * RATE_HZ)) / RATE_HZ
    psi = OMEGA * time_s[:, None] + 2 * np.pi * np.arange(n_blades) / n_blades
    collective, cosine, sine = event(time_s)
    pitch = (collective[:, None] + cosine[:, None] * np.cos(psi)
             + sine[:, None] * np.sin(psi))
    rng = np.random.default_rng(seed)
    return time_s, pitch + noise * rng.standard_normal(pitch.shape)


def _step_at(time_s, at_s, size):
    return np.where(time_s >= at_s, size, 0.0)


ONE_REV_S = 2 * np.pi / OMEGA          # 0.067 s: where the test steps the lateral cyclic
INPUTS = {
    # the test's lateral-cyclic step one revolution in (the 3-blade hover recording)
    'lateral step': lambda t: (THETA0 + 0 * t, 0 * t, _step_at(t, ONE_REV_S, CYCLIC)),
    'collective step': lambda t: (THETA0 + _step_at(t, 0.2, np.radians(0.5)), 0 * t, 0 * t),
    # a command that goes out for 3 samples and back, on every blade at once
    'cyclic pulse': lambda t: (THETA0 + 0 * t, 0 * t, CYCLIC * ((t >= ONE_REV_S)
                                                                & (t < ONE_REV_S + 0.003))),
    'collective ramp': lambda t: (THETA0 + np.radians(2.0) * np.clip((t - 0.2) / 0.05, 0, 1),
                                  0 * t, 0 * t),
    # stirring: the cyclic starts to turn at 7/rev (105 Hz: 9-10 samples a cycle)
    'stirring start': lambda t: (THETA0 + 0 * t,
                                 CYCLIC * np.cos(7 * OMEGA * t) * (t >= 0.2),
                                 CYCLIC * np.sin(7 * OMEGA * t) * (t >= 0.2)),
}


@pytest.mark.parametrize('n_blades', [2, 3, 4, 5, 6])
@pytest.mark.parametrize('name', sorted(INPUTS))
@pytest.mark.parametrize('noise', [PITCH_NOISE, 0.0])
def test_inputs_on_every_blade_are_never_repaired(n_blades, name, noise):
    """Steps, ramps, pulses and stirring starts of the pitch are real inputs: none repaired."""
    from rotor_id.io.streams import repair_value_spikes
    time_s, pitch = _blade_pitch(n_blades, INPUTS[name], noise)
    before = pitch.copy()
    assert repair_value_spikes(time_s, pitch) == []
    assert np.array_equal(pitch, before)


@pytest.mark.parametrize('n_blades', [2, 3, 4, 5, 6])
@pytest.mark.parametrize('name', sorted(INPUTS))
def test_single_sample_spikes_are_repaired_among_inputs(n_blades, name):
    """
    A bit flip of one blade's reading is found and replaced, whatever the input.

    One sample of the last blade +0.2 rad, away from the input's event; the replaced value is
    the interpolation, within the noise of the true reading.
    """
    from rotor_id.io.streams import repair_value_spikes
    time_s, pitch = _blade_pitch(n_blades, INPUTS[name])
    clean = pitch.copy()
    at = 450
    pitch[at, -1] += 0.2
    repairs = repair_value_spikes(time_s, pitch)
    assert [(r.column, r.indices.tolist()) for r in repairs] == [(n_blades - 1, [at])]
    assert repairs[0].old[0] == clean[at, -1] + 0.2
    assert abs(pitch[at, -1] - clean[at, -1]) < 10 * PITCH_NOISE
    unchanged = np.ones(pitch.shape, dtype=bool)
    unchanged[at, -1] = False
    assert np.array_equal(pitch[unchanged], clean[unchanged])


def test_spike_threshold_follows_the_noise_scale():
    """
    The threshold is VALUE_SPIKE_SIGMAS cubic prediction errors of the MAD noise σ.

    On white noise of σ (no signal), the MAD of second differences gives σ back within 3 %,
    a +15σ sample is repaired and a +6σ one (below 7 × 1.39σ) is not.
    """
    from rotor_id.io.streams import noise_scale, value_spikes
    rng = np.random.default_rng(7)
    sigma = 0.002
    values = sigma * rng.standard_normal((20000, 2))
    assert noise_scale(values) == pytest.approx([sigma, sigma], rel=0.03)
    values[5000, 0] += 15 * sigma
    values[9000, 1] += 6 * sigma
    found = value_spikes(values, groups=[[0], [1]])
    assert found[0].tolist() == [5000] and found[1].size == 0
