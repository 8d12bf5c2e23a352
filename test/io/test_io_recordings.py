"""
The six shared test-stand recordings read into Records that agree with what is known of them.

Known facts (../shared/recordings/README.md, docs/models.md §0): 4 blades, 1 kHz, rotor at
900 rpm; the record starts in trim at collective pitch, the 1.5° lateral cyclic (θII) is stepped
on at t = 2π, and stirring starts t0 later (t0 = 12 at μ = 0.4, 70 at μ = 0).
"""

import math
import warnings

from io_helpers import OMEGA, RECORDING_NAMES
import numpy as np
import pytest
from rotor_id.io.bag import read_record, read_run
from rotor_id.io.run_description import load_run_description, validate_window

CYCLIC = math.radians(1.5)
MARGIN = 0.3  # t units kept clear of the step and the stirring start (transients, interp.)


def _run(recordings, name):
    description = load_run_description(recordings / f'{name}.yaml')
    with warnings.catch_warnings():
        warnings.simplefilter('error')  # a clean recording must read without any repair
        record = read_run(description)
    return description, record


@pytest.mark.parametrize('name', RECORDING_NAMES)
def test_recording_reads_as_four_blades_at_1khz(recordings, name):
    description, record = _run(recordings, name)
    assert record.n_blades == 4 == description.rotor.blades
    assert record.blade_names == ['blade_1', 'blade_2', 'blade_3', 'blade_4']
    assert record.warnings == []
    assert record.sample_period_s == pytest.approx(1e-3, rel=1e-6)
    assert record.omega_mean == pytest.approx(OMEGA, rel=1e-6)
    assert np.all(np.isfinite(record.blade_flap)) and np.all(np.isfinite(record.blade_pitch))
    # angles are radians: the flap stays within a few degrees
    assert np.abs(record.blade_flap).max() < 0.2
    assert record.time_s[0] == 0.0


@pytest.mark.parametrize('name', RECORDING_NAMES)
def test_t_is_the_unwrapped_blade1_azimuth_and_agrees_with_omega_time(recordings, name):
    _, record = _run(recordings, name)
    # starts at the first stamp's blade-1 azimuth (wrapped to [0, 2π))
    assert 0.0 <= record.t[0] < 2 * np.pi
    assert np.all(np.diff(record.t) > 0)
    # README: t = Ω·(stamp − first stamp) + ψ(first stamp)
    np.testing.assert_allclose(record.t, record.t[0] + record.rotor_speed_rad_s * record.time_s,
                               atol=1e-9)
    np.testing.assert_allclose(record.azimuths()[:, 1], record.t + np.pi / 2)


@pytest.mark.parametrize('name', RECORDING_NAMES)
def test_window_extraction_inside_the_record(recordings, name):
    description, record = _run(recordings, name)
    validate_window(description, record)
    t0_s, t1_s = description.window_s
    part = record.window(t0_s, t1_s)
    assert part.time_s[0] >= t0_s - 1e-9 and part.time_s[-1] <= t1_s + 1e-9
    # exactly the samples of the record inside the window, time origin kept
    inside = (record.time_s >= t0_s) & (record.time_s <= t1_s)
    np.testing.assert_array_equal(part.time_s, record.time_s[inside])
    np.testing.assert_array_equal(part.t, record.t[inside])
    np.testing.assert_array_equal(part.blade_flap, record.blade_flap[inside])
    np.testing.assert_array_equal(part.blade_pitch, record.blade_pitch[inside])
    assert part.time_s[0] - t0_s < record.sample_period_s


@pytest.mark.parametrize('name', RECORDING_NAMES)
def test_pitch_step_and_stirring_start(recordings, name):
    description, record = _run(recordings, name)
    t0 = 12.0 if description.rotor.advance_ratio > 0 else 70.0
    step, stir = 2 * np.pi, 2 * np.pi + t0
    pitch = record.multiblade('pitch')
    # 'cos' of the blade pitches is θII, 'sin' is −θI (docs/models.md §0)
    trim = record.t < step - MARGIN
    stepped = (record.t > step + MARGIN) & (record.t < stir - MARGIN)
    assert abs(pitch['cos'][trim].mean()) < 1e-4
    assert pitch['cos'][stepped].mean() == pytest.approx(CYCLIC, abs=2e-5)
    assert np.abs(pitch['cos'][stepped] - CYCLIC).max() < 5e-4   # pitch noise ~0.005°
    assert abs(pitch['sin'][stepped].mean()) < 2e-5
    assert pitch['collective'][stepped].mean() == pytest.approx(math.radians(2.0), abs=5e-5)
    # the step is on at the first sample after t = 2π
    first_on = record.t[np.argmax(pitch['cos'] > CYCLIC / 2)]
    assert step <= first_on < step + 0.1
    # stirring: the cyclic vector turns by φ = ω̇(t − t0)² with |ω̇| = 0.1/π
    late = record.t > stir + 8.0
    if late.any():
        phase = np.arctan2(-pitch['sin'][late], pitch['cos'][late])
        expected = np.angle(np.exp(-1j * 0.1 / np.pi * (record.t[late] - stir) ** 2))
        assert np.abs(np.angle(np.exp(1j * (phase - expected)))).max() < 0.05
        assert np.hypot(pitch['cos'][late], pitch['sin'][late]).mean() == pytest.approx(
            CYCLIC, rel=0.01)


@pytest.mark.parametrize('name', ['id_wake_progressing', 'id_multiblade_mu04'])
def test_identification_window_starts_at_stirring(recordings, name):
    description, record = _run(recordings, name)
    t0 = 12.0 if description.rotor.advance_ratio > 0 else 70.0
    first = record.window(*description.window_s)
    dt = np.median(np.diff(record.t))
    assert abs(record.t_at(description.window_s[0]) - (2 * np.pi + t0)) < dt
    assert abs(first.t[0] - (2 * np.pi + t0)) < dt
    # the window is the report's 12 units of t
    assert abs(first.t[-1] - first.t[0] - 12.0) < 2 * dt


def test_sqlite3_recording_reads_like_mcap(recordings):
    """id_multiblade_mu04 is the sqlite3 bag; its .db3 file and its directory give one Record."""
    bag = recordings / 'id_multiblade_mu04'
    assert (bag / 'id_multiblade_mu04.db3').is_file()
    from_dir = read_record(bag)
    from_file = read_record(bag / 'id_multiblade_mu04.db3')
    from_meta = read_record(bag / 'metadata.yaml')
    assert len(from_dir) == 449
    for other in (from_file, from_meta):
        np.testing.assert_array_equal(other.blade_flap, from_dir.blade_flap)
        np.testing.assert_array_equal(other.t, from_dir.t)
    assert 'sqlite3' in from_dir.source
