"""Time base and multiblade coordinates (docs/models.md §0)."""

from hypothesis import given, settings, strategies as st
from hypothesis.extra.numpy import arrays
from io_helpers import make_record
import numpy as np
import pytest
from rotor_id.io.timebase import (
    blade_azimuths, blade_values, multiblade_coordinates, nondimensional_time, unwrap_azimuth,
)

finite = st.floats(-1.0, 1.0, allow_nan=False)


@settings(max_examples=40)
@given(values=arrays(float, (7, 4), elements=finite), psi=arrays(float, 7, elements=st.floats(
    -50.0, 50.0, allow_nan=False)))
def test_multiblade_round_trip_is_exact_for_four_blades(values, psi):
    coords = multiblade_coordinates(values, psi)
    assert set(coords) == {'collective', 'cos', 'sin', 'differential'}
    np.testing.assert_allclose(blade_values(coords, psi, 4), values, atol=1e-12)


def test_multiblade_round_trip_three_blades_has_no_differential():
    rng = np.random.default_rng(3)
    values, psi = rng.normal(size=(20, 3)), rng.uniform(0, 7, 20)
    coords = multiblade_coordinates(values, psi)
    assert 'differential' not in coords
    np.testing.assert_allclose(blade_values(coords, psi, 3), values, atol=1e-12)


def test_multiblade_definitions_of_models_section_0():
    """β0 = ¼Σβ_k, βI = ½Σβ_k cos ψ_k, βII = ½Σβ_k sin ψ_k, βd = ¼Σ(−1)^k β_k, ψ_k = ψ+(k−1)π/2."""
    psi = np.array([0.0, 0.7, 2.0])
    beta = np.array([[1.0, 2.0, 3.0, 5.0], [0.1, -0.2, 0.4, 0.0], [0.0, 0.0, 1.0, 0.0]])
    coords = multiblade_coordinates(beta, psi)
    for i, p in enumerate(psi):
        azim = p + np.arange(4) * np.pi / 2
        assert coords['collective'][i] == pytest.approx(beta[i].sum() / 4)
        assert coords['cos'][i] == pytest.approx(0.5 * np.sum(beta[i] * np.cos(azim)))
        assert coords['sin'][i] == pytest.approx(0.5 * np.sum(beta[i] * np.sin(azim)))
        assert coords['differential'][i] == pytest.approx(
            0.25 * (-beta[i, 0] + beta[i, 1] - beta[i, 2] + beta[i, 3]))


def test_pitch_law_maps_to_lateral_and_forward_cyclic():
    """θ_k = θ0 − θI sin ψ_k + θII cos ψ_k: 'cos' = θII and 'sin' = −θI."""
    psi = np.linspace(0, 20, 200)
    theta0, theta_i, theta_ii = 0.035, 0.01, 0.026
    azim = blade_azimuths(psi, 4)
    pitch = theta0 - theta_i * np.sin(azim) + theta_ii * np.cos(azim)
    coords = multiblade_coordinates(pitch, psi)
    np.testing.assert_allclose(coords['collective'], theta0)
    np.testing.assert_allclose(coords['cos'], theta_ii)
    np.testing.assert_allclose(coords['sin'], -theta_i)
    np.testing.assert_allclose(coords['differential'], 0.0, atol=1e-15)


def test_multiblade_rejects_bad_shapes():
    with pytest.raises(ValueError, match='at least 2 blades'):
        multiblade_coordinates(np.zeros((5, 1)), np.zeros(5))
    with pytest.raises(ValueError, match='values must be'):
        multiblade_coordinates(np.zeros((5, 4)), np.zeros(4))


def test_blade_azimuths_four_blades_quarter_turns():
    np.testing.assert_allclose(blade_azimuths(np.array([1.0]), 4),
                               [[1.0, 1.0 + np.pi / 2, 1.0 + np.pi, 1.0 + 1.5 * np.pi]])


def test_unwrap_with_speed_survives_gaps_longer_than_half_a_revolution():
    record = make_record(n=3000)
    keep = np.ones(len(record), dtype=bool)
    keep[1000:1050] = False           # 50 ms gap: 0.75 rev, beyond np.unwrap's reach
    time_s, t = record.time_s[keep], record.t[keep]
    wrapped = np.mod(t, 2 * np.pi)
    unwrapped = unwrap_azimuth(wrapped, time_s, record.rotor_speed_rad_s[keep])
    np.testing.assert_allclose(unwrapped, t, atol=1e-9)
    assert np.abs(np.unwrap(wrapped) - t).max() > 1.0   # the plain rule fails there


def test_nondimensional_time_from_speed_when_no_azimuth():
    time_s = np.linspace(0, 1, 11)
    np.testing.assert_allclose(nondimensional_time(time_s, None, 90.0), 90.0 * time_s)
    with pytest.raises(ValueError, match='azimuth or the rotor speed'):
        nondimensional_time(time_s)
