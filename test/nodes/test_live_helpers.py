"""
The ROS-free parts of the nodes (rotor_id/nodes/live.py, rotor_id/physics/blades.py).

What they prove: the plant's stepping is the library simulator (sample by sample equals one
simulate() call), its noise does not depend on real-time batching, trim is the analytic
equilibrium; the identifier's Record equals the bag reader's; the sample checks reject each
kind of bad message; the streaming Kalman adapter equals the library's batch filter; the data
length verdict extrapolates an exact 1/T law exactly.
"""

import math

import numpy as np
import pytest
from rotor_id.estimation.kalman import discretize, kalman_filter
from rotor_id.estimation.simulate import simulate
from rotor_id.io.bag import read_record, write_record_bag
from rotor_id.io.timebase import nondimensional_time
from rotor_id.nodes.live import (AzimuthTracker, BadSample, check_azimuth_batch,
                                 check_azimuth_sample, check_joint_batch,
                                 check_joint_sample, data_length_verdict, PlantStepper,
                                 record_from_series, rotor_constants, StampedSeries,
                                 StreamingKalman)
from rotor_id.nodes.test_points import channel_coverage
from rotor_id.physics.blades import blade_flap_from_multiblade_state
from rotor_id.physics.models import build_model, multiblade_from_blade_flap, RotorConstants
from rotor_id.physics.stirring import SampledInput, StirringSchedule

OMEGA = 2 * math.pi * 15
WAKE = {'A': 0.5, 'AL_over_tau': 0.25, 'inv_tau': 0.125}
THETA0 = math.radians(2.0)


def _wake_stepper(**kw):
    rotor = rotor_constants(4, 0.0, 1.2, 0.97)
    args = {'flap_noise_std': 0.0, 'pitch_noise_std': 0.0, 'seed': 3}
    args.update(kw)
    return PlantStepper('multiblade_wake', rotor, WAKE, OMEGA, 1000.0, THETA0, **args)


def _drive(stepper, schedule, batches, every=5, knots=None):
    """Advance in batches, commanding the schedule at every ``every``-th sample (one ahead)."""
    out = []
    for n in batches:
        for j in range(n + every):
            if (stepper.samples + j) % every == 0:
                tc = stepper.t + stepper.step * (j + 1)
                if stepper.command(tc, schedule([tc])[0]) and knots is not None:
                    knots.append((tc, schedule([tc])[0]))
        out.append(stepper.advance(n))
    return [np.concatenate(parts) for parts in zip(*out)]


def test_trim_is_the_equilibrium_at_collective_only():
    stepper = _wake_stepper()
    t, flap, pitch = stepper.advance(200)
    # at mu = 0 the tilt modes see no collective: only the quasi-static coning A θ0 / P² remains
    assert np.allclose(flap, WAKE['A'] * THETA0 / 1.2**2, atol=1e-13)
    assert np.allclose(pitch, THETA0, atol=1e-15)


def test_stepping_equals_one_simulation_and_noise_ignores_batching():
    schedule = StirringSchedule(THETA0, math.radians(1.5), -0.1 / math.pi, 2 * math.pi + 3.0,
                                2 * math.pi)
    knots = [(0.0, np.array([THETA0, 0.0, 0.0]))]
    t, flap, _ = _drive(_wake_stepper(), schedule, [7, 1, 50, 13, 29, 100], knots=knots)
    # the same input (linear between the commands) through simulate() in one call
    kt = np.array([k[0] for k in knots])
    ku = np.array([k[1] for k in knots])

    def inputs(tt):
        return np.column_stack([np.interp(tt, kt, ku[:, j]) for j in range(3)])

    model = build_model('multiblade_wake', RotorConstants(advance_ratio=0.0))
    p = model.parameter_vector(WAKE)
    grid = np.concatenate([[0.0], t])
    sim = simulate(model, p, inputs, grid, model.equilibrium([0.0], p, [[THETA0, 0, 0]]))
    expected = blade_flap_from_multiblade_state(model, t, sim.x[1:], WAKE['A'] * THETA0 / 1.44)
    assert np.max(np.abs(flap - expected)) < 1e-12
    noisy = [_drive(_wake_stepper(flap_noise_std=1e-3), schedule, batches)[1]
             for batches in ([200], [3, 97, 1, 99])]
    assert np.max(np.abs(noisy[0] - noisy[1])) < 1e-13     # same draws, whatever the batches
    assert np.std(noisy[0] - flap[:200]) == pytest.approx(1e-3, rel=0.1)


def test_blade_flap_inverts_to_the_multiblade_state():
    model = build_model('multiblade', RotorConstants(advance_ratio=0.4))
    rng = np.random.default_rng(0)
    t = np.linspace(0, 7, 40)
    x = rng.normal(size=(40, 8))
    flap = blade_flap_from_multiblade_state(model, t, x)
    assert np.allclose(multiblade_from_blade_flap(t, flap), x[:, :4], atol=1e-12)


@pytest.mark.parametrize('names, position, stamp, last, kind', [
    (['blade_1', 'blade_2', 'blade_3', 'blade_4'], [0.0, np.nan, 0.0, 0.0], 2, 1, 'non_finite'),
    (['b1', 'b2', 'b3', 'b4'], [0.0] * 4, 2, 1, 'wrong_names'),
    (['blade_1', 'blade_2', 'blade_3'], [0.0] * 3, 2, 1, 'wrong_count'),
    (['blade_1', 'blade_2', 'blade_3', 'blade_4'], [0.0] * 3, 2, 1, 'wrong_count'),
    (['blade_1', 'blade_2', 'blade_3', 'blade_4'], [2.0, 3.5, 2.0, 0.5], 2, 1, 'degrees'),
    (['blade_1', 'blade_2', 'blade_3', 'blade_4'], [0.0] * 4, 1, 2, 'out_of_order'),
    (['blade_1', 'blade_2', 'blade_3', 'blade_4'], [0.0] * 4, 2, 2, 'duplicate'),
])
def test_bad_joint_samples_are_named(names, position, stamp, last, kind):
    expected = [f'blade_{k}' for k in range(1, 5)]
    with pytest.raises(BadSample) as info:
        check_joint_sample(names, position, expected, stamp, last, max_abs_rad=0.7)
    assert info.value.kind == kind


def test_joint_sample_is_reordered_by_name():
    values = check_joint_sample(['blade_3', 'blade_1', 'blade_4', 'blade_2'], [3, 1, 4, 2],
                                [f'blade_{k}' for k in range(1, 5)], 5, 4, max_abs_rad=10)
    assert values.tolist() == [1, 2, 3, 4]


def test_a_sensor_topic_may_carry_other_joints_a_command_may_not():
    # a rig's joint_states: every joint of the stand in one message (velocity one per joint)
    names = ['hub', 'pitch_2', 'flap_2', 'pitch_1', 'flap_1', 'tail']
    position = [5.0, 0.02, 0.05, 0.01, 0.04, 0.3]
    velocity = [94.0, 0.0, 0.1, 0.0, 0.2, 7.0]
    assert check_joint_sample(names, position, ['flap_1', 'flap_2'], 2, 1, max_abs_rad=0.7,
                              extra_joints=True).tolist() == [0.04, 0.05]
    assert check_azimuth_sample(names, position, velocity, 'hub', 2, 1) == (5.0, 94.0)
    with pytest.raises(BadSample) as info:              # a command names exactly its joints
        check_joint_sample(names, position, ['pitch_1', 'pitch_2'], 2, 1)
    assert info.value.kind == 'wrong_count'
    with pytest.raises(BadSample) as info:              # one velocity for six joints
        check_azimuth_sample(names, position, [94.0], 'hub', 2, 1)
    assert info.value.kind == 'bad_speed'
    with pytest.raises(BadSample) as info:              # a wanted joint missing
        check_joint_sample(names, position, ['flap_1', 'flap_3'], 2, 1, extra_joints=True)
    assert info.value.kind == 'wrong_names'
    # the batch checks of the identifier take the same samples
    stamps = np.array([2, 3, 4])
    values, accepted = check_joint_batch(names, np.tile(position, (3, 1)), ['flap_1', 'flap_2'],
                                         stamps, 1, 0.7, extra_joints=True)
    assert accepted.all() and values.tolist() == [[0.04, 0.05]] * 3
    psi, omega, accepted = check_azimuth_batch(names, np.tile(position, (3, 1)),
                                               np.tile(velocity, (3, 1)), 'hub', stamps, 1)
    assert accepted.all() and psi.tolist() == [5.0] * 3 and omega.tolist() == [94.0] * 3
    _, accepted = check_joint_batch(names, np.tile(position, (3, 1)), ['pitch_1', 'pitch_2'],
                                    stamps, 1)
    assert not accepted.any()


@pytest.mark.parametrize('position, velocity, kind', [
    ([400.0], [94.0], 'degrees'), ([1.0], [-94.0], 'bad_speed'), ([1.0], [], 'bad_speed'),
    ([1.0], [np.inf], 'bad_speed'), ([np.nan], [94.0], 'non_finite')])
def test_bad_azimuth_samples_are_named(position, velocity, kind):
    with pytest.raises(BadSample) as info:
        check_azimuth_sample(['rotor'], position, velocity, 'rotor', 2, 1)
    assert info.value.kind == kind


def test_live_record_equals_the_bag_reader(tmp_path):
    stepper = _wake_stepper(flap_noise_std=1e-3, pitch_noise_std=1e-4)
    schedule = StirringSchedule(THETA0, math.radians(1.5), -0.1 / math.pi, 9.0, 2 * math.pi)
    t, flap, pitch = _drive(stepper, schedule, [300])
    stamps = 10**9 + np.arange(1, 301) * 1_000_000
    series = [StampedSeries(4), StampedSeries(4), StampedSeries(2)]
    tracker = AzimuthTracker()
    for i, stamp in enumerate(stamps):
        psi = math.fmod(t[i], 2 * math.pi)
        series[0].append(stamp, flap[i])
        series[1].append(stamp, pitch[i])
        series[2].append(stamp, (psi, OMEGA))
        tracker.add(stamp, psi, OMEGA)
    names = [f'blade_{k}' for k in range(1, 5)]
    live = record_from_series(*series, names, stamps[0])
    write_record_bag(tmp_path / 'bag', live)
    from_bag = read_record(tmp_path / 'bag')
    for field in ('time_s', 't', 'rotor_speed_rad_s', 'blade_flap', 'blade_pitch'):
        assert np.allclose(getattr(live, field), getattr(from_bag, field), atol=1e-9), field
    assert np.allclose(live.t, t, atol=1e-9)
    assert np.allclose(tracker.t_at(stamps), t, atol=1e-9)
    later = stamps[-1] + 5_000_000
    assert tracker.t_at([later])[0] == pytest.approx(t[-1] + OMEGA * 0.005)


def test_record_of_a_span_equals_the_whole_record_cut():
    """The identifier's window records equal the whole buffer's Record cut to the window."""
    rng = np.random.default_rng(5)
    n = 3000
    stamps = 10**18 + np.cumsum(rng.integers(900_000, 1_100_000, n))     # jittered 1 kHz
    omega = OMEGA * (1 + 0.05 * np.sin(np.arange(n) / 300))
    psi = np.concatenate([[0.3], 0.3 + np.cumsum(omega[1:] * np.diff(stamps) / 1e9)])
    series = [StampedSeries(4), StampedSeries(4), StampedSeries(2)]
    tracker = AzimuthTracker()                    # the azimuth unwrapped as it arrives
    for i, stamp in enumerate(stamps):
        if i % 7:                                 # pitch and azimuth on every sample but some
            series[1].append(stamp + 300_000, rng.normal(size=4))
        series[0].append(stamp, rng.normal(size=4))
        series[2].append(stamp - 200_000, (math.fmod(psi[i], 2 * math.pi), omega[i]))
        tracker.add(stamp - 200_000, math.fmod(psi[i], 2 * math.pi), omega[i])
    az = series[2]
    np.testing.assert_array_equal(tracker.series.values[:, 2], nondimensional_time(
        (az.stamps - stamps[0]) / 1e9, az.values[:, 0], az.values[:, 1]))
    names = [f'blade_{k}' for k in range(1, 5)]
    whole = record_from_series(*series, names, stamps[0])     # unwrapped here, from the start
    for lo, hi in ((stamps[1200], stamps[1500] + 1), (0, stamps[40]), (stamps[2990], 2 * 10**18)):
        part = record_from_series(series[0], series[1], tracker.series, names, stamps[0],
                                  span_ns=(lo, hi))
        keep = (whole.time_s >= (lo - stamps[0]) / 1e9) & (whole.time_s <= (hi - stamps[0]) / 1e9)
        for field in ('time_s', 't', 'rotor_speed_rad_s', 'blade_flap', 'blade_pitch'):
            np.testing.assert_array_equal(getattr(part, field), getattr(whole, field)[keep])
    with pytest.raises(ValueError, match='unwrapped'):
        record_from_series(*series, names, stamps[0], span_ns=(0, stamps[5]))
    gappy = np.delete(stamps, [100, 101, 2000])
    assert channel_coverage('x', gappy, stamps[50], stamps[150]).gaps == 1
    assert channel_coverage('x', gappy, stamps[150], stamps[1900]).complete


def test_streaming_kalman_equals_the_batch_filter():
    model = build_model('multiblade_wake', RotorConstants(advance_ratio=0.0))
    p = model.parameter_vector(WAKE)
    schedule = StirringSchedule(0.0, 0.03, -0.1 / math.pi, 2.0, 0.0)
    t = np.arange(0.0, 20.0, 0.094)
    sim = simulate(model, p, schedule, t, np.zeros(6))
    y = sim.y + np.random.default_rng(1).normal(0, 1e-3, sim.y.shape)
    x0, P0 = np.zeros(6), np.eye(6) * 1e-4
    dm = discretize(model, p, schedule, t, [4, 5], 0.01)
    batch = kalman_filter(dm, y, x0, P0, np.full(2, 1e-6))
    stream = StreamingKalman(model, p, np.full(2, 1e-3), x0, P0, process_noise_std=0.01)
    xs = []
    for chunk in np.array_split(np.arange(t.size), [1, 8, 9, 60, 150]):
        xs.append(stream.update(t[chunk], schedule, y[chunk])[0])
    assert np.max(np.abs(np.concatenate(xs) - batch.x_filt)) < 1e-12
    assert np.allclose(stream.P, batch.P_filt[-1], atol=1e-15)


@pytest.mark.parametrize('name, mu', [('multiblade_wake', 0.0), ('multiblade', 0.4)])
def test_streaming_kalman_compiled_batches_equal_the_library_filter(name, mu):
    """advance() (one compiled scan per batch, the node's path) gives update()'s last states."""
    from rotor_id.estimation import kernels
    assert kernels.prefer() is not None, kernels.status()['error']
    model = build_model(name, RotorConstants(advance_ratio=mu))
    p = model.nominal()
    schedule = StirringSchedule(THETA0, math.radians(1.5), -0.1 / math.pi, 2.0, 1.0)
    t = np.arange(0.0, 30.0, OMEGA / 1000.0)            # 1 kHz at 15 Hz: 318 samples
    sim = simulate(model, p, schedule, t, np.zeros(model.n_states))
    y = sim.y + np.random.default_rng(2).normal(0, 1e-3, sim.y.shape)
    x0, P0 = np.zeros(model.n_states), np.eye(model.n_states) * 4e-4
    library = StreamingKalman(model, p, np.full(model.n_outputs, 1e-3), x0, P0, 0.01)
    compiled = StreamingKalman(model, p, np.full(model.n_outputs, 1e-3), x0, P0, 0.01)
    for k, chunk in enumerate(np.array_split(np.arange(t.size), [20, 21, 40, 60, 150, 250])):
        if k == 4:                      # new parameters from the identifier between batches
            library.p = compiled.p = p * 1.1
        xs, Ps = library.update(t[chunk], schedule, y[chunk])
        x, P = compiled.advance(t[chunk], schedule, y[chunk])
        std = np.sqrt(np.diag(Ps[-1]))
        np.testing.assert_allclose(x, xs[-1], rtol=1e-9, atol=1e-9 * std.min())
        np.testing.assert_allclose(P, Ps[-1], rtol=1e-9, atol=1e-9 * np.outer(std, std).min())
        assert np.max(np.abs(x - xs[-1]) / std) < 1e-9
    assert compiled.t == library.t


@pytest.mark.parametrize('path', ['update', 'advance'])
def test_streaming_kalman_takes_a_gap_at_the_cost_of_its_own_substeps(path, monkeypatch):
    """
    A batch with lost samples (100 periods missing) filters as the library does over that grid.

    Every RK4 substep count along a grid is that of its longest interval; a gap in a batch
    would give it to every interval of the batch (seen live: one such batch held a state
    estimator for > 30 s). The discretisation fills the gap instead
    (:func:`rotor_id.estimation.simulate.gap_refinement`), so the batch costs its regular
    intervals' substeps plus the gap's.
    """
    from rotor_id.estimation import kalman, simulate as simulation
    model = build_model('multiblade_wake', RotorConstants(advance_ratio=0.0))
    p = model.parameter_vector(WAKE)
    schedule = StirringSchedule(0.0, 0.03, -0.1 / math.pi, 2.0, 0.0)
    t = np.delete(np.arange(0.0, 50.0, 0.094), np.arange(200, 300))
    sim = simulate(model, p, schedule, t, np.zeros(6))
    y = sim.y + np.random.default_rng(3).normal(0, 1e-3, sim.y.shape)
    x0, P0 = np.zeros(6), np.eye(6) * 1e-4
    batch = kalman_filter(discretize(model, p, schedule, t, [4, 5], 0.01), y, x0, P0,
                          np.full(2, 1e-6))
    cost = []
    grid = kalman.fine_grid
    monkeypatch.setattr(kalman, 'fine_grid',
                        lambda ts, m: cost.append((len(ts) - 1) * m) or grid(ts, m))
    stream = StreamingKalman(model, p, np.full(2, 1e-3), x0, P0, process_noise_std=0.01)
    split = [150] if path == 'update' else [1, 150]
    for chunk in np.array_split(np.arange(t.size), split):
        x, P = getattr(stream, path)(t[chunk], schedule, y[chunk])
    x, P = (x[-1], P[-1]) if path == 'update' else (x, P)
    std = np.sqrt(np.diag(batch.P_filt[-1]))
    assert np.max(np.abs(x - batch.x_filt[-1]) / std) < 1e-6
    assert np.max(np.abs(P - batch.P_filt[-1]) / np.outer(std, std)) < 1e-6
    regular, gap = simulation.substeps_for(t[:2]), simulation.substeps_for(t[199:201])
    assert gap > 50 * regular
    assert sum(cost) <= (t.size - 1) * regular + 2 * gap, cost


def test_batches_into_the_buffers_keep_what_sample_by_sample_keeps():
    """extend() / add_batch() (the state estimator's intake) hold append() / add()'s samples."""
    rng = np.random.default_rng(4)
    stamps = np.cumsum(rng.integers(900_000, 1_100_000, 5000))       # ~1 kHz, jittered
    values = rng.normal(size=(stamps.size, 4))
    omega = 94.0 + rng.normal(0, 0.1, stamps.size)
    psi = np.mod(np.cumsum(omega * np.diff(stamps, prepend=0) / 1e9), 2 * math.pi)
    keep_ns = 300_000_000                                 # a 0.3 s buffer
    one, batched = StampedSeries(4, capacity=64), StampedSeries(4, capacity=64)
    tracker, batch_tracker = AzimuthTracker(), AzimuthTracker()
    for chunk in np.array_split(np.arange(stamps.size), np.arange(7, stamps.size, 23)):
        for i in chunk:
            one.append(int(stamps[i]), values[i], int(stamps[i]) - keep_ns)
            tracker.add(int(stamps[i]), psi[i], omega[i], int(stamps[i]) - keep_ns)
        first = int(stamps[chunk[0]]) - keep_ns
        batched.extend(stamps[chunk], values[chunk], first)
        batch_tracker.add_batch(stamps[chunk], psi[chunk], omega[chunk], first)
        # the batch may keep older samples a little longer; the newest ones are the same
        tail = min(one.size, batched.size)
        np.testing.assert_array_equal(batched.stamps[-tail:], one.stamps[-tail:])
        np.testing.assert_array_equal(batched.values[-tail:], one.values[-tail:])
        tail = min(tracker.series.size, batch_tracker.series.size)
        np.testing.assert_array_equal(batch_tracker.series.values[-tail:],
                                      tracker.series.values[-tail:])
    need = stamps.size - int(np.searchsorted(stamps, stamps[-1] - keep_ns))
    for series, reference in ((batched, one), (batch_tracker.series, tracker.series)):
        assert need <= series.size <= series.capacity <= 4 * need    # bounded by the span
        assert series.capacity <= reference.capacity


def test_verdict_extrapolates_a_one_over_t_law_exactly():
    t = np.linspace(70.0, 82.0, 121)
    span = t - t[0]
    std = np.column_stack([np.sqrt(0.04 / np.maximum(span, 1e-9)),
                           np.sqrt(0.01 / np.maximum(span, 1e-9))])
    std[0] = np.nan
    # targets: the first needs span = 0.04/0.02² = 100 rad, the second is already met
    met, more_s = data_length_verdict(std[-1], [0.02, 0.1], t, std, OMEGA)
    assert not met
    assert more_s == pytest.approx((100.0 - 12.0) / OMEGA, rel=1e-9)
    assert data_length_verdict(std[-1], [0.1, 0.1], t, std, OMEGA) == (True, 0.0)
    assert data_length_verdict(std[-1], [0.0, 0.0]) == (True, 0.0)
    assert data_length_verdict(std[-1], [0.02, 0.0]) == (False, -1.0)


def test_sampled_input_of_the_plant_pitch_recovers_the_commands():
    stepper = _wake_stepper()
    schedule = StirringSchedule(THETA0, math.radians(1.5), -0.1 / math.pi, 8.0, 2 * math.pi)
    knots = []
    t, _, pitch = _drive(stepper, schedule, [400], every=1, knots=knots)
    u = SampledInput.from_blade_pitch(t, pitch)(t)
    assert np.allclose(u, np.array([k[1] for k in knots])[:400], atol=1e-12)


def test_window_coverage_counts_the_missing_samples():
    stamps = np.array([k * 1_000_000 for k in list(range(0, 100)) + list(range(110, 200))])
    assert channel_coverage('flap', stamps, 0, 50_000_000).complete
    coverage = channel_coverage('flap', stamps, 50_000_000, 150_000_000)
    assert (coverage.missing_inside, coverage.gaps, coverage.missing) == (10, 1, 10)
    assert coverage.describe() == 'flap: 10 sample(s) missing (10 in 1 gap(s) inside)'


def test_window_coverage_reports_heavy_scattered_loss():
    """
    A loaded identifier losing a quarter of the samples, one here and there, must say so.

    Isolated losses (steps of two periods) are gaps too: a threshold of 2.5 periods would
    never report them, and under overload the identifier would publish fits on thinned
    windows without a warning.
    """
    rng = np.random.default_rng(3)
    kept = np.flatnonzero(rng.random(3000) > 0.25)
    lo, hi = 1000, 1127
    coverage = channel_coverage('flap', kept * 1_000_000, lo * 1_000_000, hi * 1_000_000)
    lost = (hi - lo + 1) - np.count_nonzero((kept >= lo) & (kept <= hi))
    assert coverage.missing == lost and not coverage.complete
    jitter = np.arange(3000) * 1_000_000 + rng.uniform(-2e5, 2e5, 3000).astype(np.int64)
    assert channel_coverage('flap', jitter, lo * 1_000_000, hi * 1_000_000).complete


@pytest.mark.parametrize('model, mu', [('multiblade_wake', 0.0), ('multiblade', 0.4),
                                       ('multiblade_constant', 0.4), ('single_blade', 0.4)])
def test_every_library_model_drives_the_plant_from_trim(model, mu):
    rotor = rotor_constants(4, mu, 1.2, 0.97)
    stepper = PlantStepper(model, rotor, {'gamma': 5.0, **WAKE}, OMEGA, 1000.0, THETA0)
    _, flap_trim, _ = stepper.advance(400)     # trim: 200 samples are exactly 3 revolutions
    assert np.max(np.abs(flap_trim[200:] - flap_trim[:200])) < 1e-7    # rad: settled
    schedule = StirringSchedule(THETA0, math.radians(1.5), -0.1 / math.pi, 60.0, 40.0)
    t, flap, pitch = _drive(stepper, schedule, [300])
    assert np.all(np.isfinite(flap)) and flap.shape == (300, 4)
    # the lateral cyclic step (t = 40) tilts the tip-path plane: blades 1 and 3 separate
    before = np.ptp(flap_trim[:, 0] - flap_trim[:, 2])
    assert np.ptp(flap[-100:, 0] - flap[-100:, 2]) > before + math.radians(0.3)


def test_an_encoder_wrapped_to_minus_pi_pi_is_read_as_wrapped(tmp_path):
    """ψ in [-π, π) (many encoders) is a wrapped azimuth, live and offline: the same record."""
    from rotor_id.io.bag import read_record, write_record_bag
    from rotor_id.io.record import Record
    psi = np.array([3.0, -3.0, -1.0, 0.5, 3.1])
    ok = [check_azimuth_sample(['rotor'], [p], [94.0], 'rotor', 2 + i, 1 + i)[0]
          for i, p in enumerate(psi)]
    assert ok == pytest.approx(np.mod(psi, 2 * np.pi).tolist())
    got, omega, accepted = check_azimuth_batch(['rotor'], psi[:, None], np.full((5, 1), 94.0),
                                               'rotor', np.arange(2, 7), 1)
    assert accepted.all() and got.tolist() == pytest.approx(np.mod(psi, 2 * np.pi).tolist())
    with pytest.raises(BadSample, match='outside'):       # degrees stay refused
        check_azimuth_sample(['rotor'], [-200.0], [94.0], 'rotor', 2, 1)
    # offline: a bag whose azimuth is written in [-π, π) reads as the one in [0, 2π)
    from rosbags.typesys import get_typestore, Stores
    store = get_typestore(Stores.ROS2_JAZZY)
    omega = 2 * np.pi * 15
    n = 60                 # 0.9 revolution from ψ = 3.3: most samples negative in [-π, π)
    time_s = np.arange(n) / 1000.0
    record = Record(time_s=time_s, t=omega * time_s + 3.3, rotor_speed_rad_s=np.full(n, omega),
                    blade_flap=np.zeros((n, 4)) + 0.01, blade_pitch=np.zeros((n, 4)),
                    blade_names=[f'blade_{k}' for k in range(1, 5)], stamp0_ns=10**18)
    write_record_bag(tmp_path / 'wrapped', record)
    types = store.types
    encoder = []
    for i in range(n):
        stamp = 10**18 + i * 1_000_000
        header = types['std_msgs/msg/Header'](stamp=types['builtin_interfaces/msg/Time'](
            sec=stamp // 10**9, nanosec=stamp % 10**9), frame_id='rotor')
        position = (record.t[i] + np.pi) % (2 * np.pi) - np.pi           # in [-π, π)
        encoder.append(('/rotor/azimuth', stamp, types['sensor_msgs/msg/JointState'](
            header=header, name=['rotor'], position=np.array([position]),
            velocity=np.array([omega]), effort=np.array([], dtype=float))))
    write_record_bag(tmp_path / 'encoder', record, topics={'azimuth': None}, extra=encoder)
    a, b = read_record(tmp_path / 'wrapped'), read_record(tmp_path / 'encoder')
    assert np.allclose(a.t, b.t, atol=1e-9) and np.allclose(a.t, record.t, atol=1e-9)
