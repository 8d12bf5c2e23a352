"""Record: shapes, windows, azimuths."""

from io_helpers import make_record
import numpy as np
import pytest
from rotor_id.io.record import Record


def test_window_is_inclusive_and_keeps_the_time_origin():
    record = make_record(n=100)
    part = record.window(0.010, 0.020)
    np.testing.assert_allclose(part.time_s, np.arange(10, 21) / 1000.0)
    np.testing.assert_array_equal(part.t, record.t[10:21])
    np.testing.assert_array_equal(part.blade_pitch, record.blade_pitch[10:21])
    assert part.stamp0_ns == record.stamp0_ns
    assert 'window' in part.source
    # a window of a window is the same as the window
    np.testing.assert_array_equal(part.window(0.012, 0.013).t, record.t[12:14])


def test_window_errors_name_the_span():
    record = make_record(n=100)
    with pytest.raises(ValueError, match='holds no sample.*spans'):
        record.window(5.0, 6.0)
    with pytest.raises(ValueError, match='before its start'):
        record.window(0.02, 0.01)


def test_azimuths_and_omega_mean():
    record = make_record(n=50)
    azimuths = record.azimuths()
    assert azimuths.shape == (50, 4)
    np.testing.assert_allclose(azimuths[:, 2] - azimuths[:, 0], np.pi)
    assert record.omega_mean == pytest.approx(np.mean(record.rotor_speed_rad_s))
    assert record.n_blades == 4 and len(record) == 50


def test_shape_mismatch_is_refused():
    record = make_record(n=10)
    with pytest.raises(ValueError, match='blade_pitch has shape'):
        Record(record.time_s, record.t, record.rotor_speed_rad_s, record.blade_flap,
               record.blade_pitch[:, :3], record.blade_names)
    with pytest.raises(ValueError, match='blade names'):
        Record(record.time_s, record.t, record.rotor_speed_rad_s, record.blade_flap,
               record.blade_pitch, ['blade_1'])
    with pytest.raises(ValueError, match='Record.t has shape'):
        Record(record.time_s, record.t[:5], record.rotor_speed_rad_s, record.blade_flap,
               record.blade_pitch, record.blade_names)
