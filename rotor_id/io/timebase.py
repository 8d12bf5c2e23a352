"""
Time base of a recording: rotor azimuth, nondimensional time, multiblade coordinates.

The report's nondimensional time is the rotor azimuth of blade 1, t = ψ (MODELS.md §0), so a
revolution is 2π. At constant rotor speed Ω this is t = Ω·(stamp − first stamp) + ψ(first
stamp); computed from the measured, unwrapped azimuth it stays right when Ω drifts.

Blade k (k = 1..N) sits at ψ_k = ψ + (k − 1)·2π/N, i.e. ψ + (k − 1)·π/2 for four blades.

Multiblade coordinates (MODELS.md §0, N blades, N ≥ 3)::

    β0  = (1/N) Σ β_k                       collective
    βI  = (2/N) Σ β_k cos ψ_k               cos   (forward tilt of the tip-path plane)
    βII = (2/N) Σ β_k sin ψ_k               sin   (left tilt)
    βd  = (1/N) Σ (−1)^k β_k   (N even)     differential (reactionless)

and for N = 4 exactly  β_k = β0 + βI cos ψ_k + βII sin ψ_k + (−1)^k βd.

For pitch, θ_k = θ0 − θI sin ψ_k + θII cos ψ_k, so the 'cos' coordinate of the blade pitches is
the lateral cyclic θII and the 'sin' coordinate is −θI.
"""

import numpy as np

# The transforms live with the physics; re-exported here for the readers of records.
from rotor_id.physics.multiblade import (  # noqa: F401
    blade_azimuths, blade_values, multiblade_coordinates)

TWO_PI = 2.0 * np.pi


def unwrap_azimuth(psi_wrapped, time_s, omega_rad_s=None):
    """
    Unwrap a measured azimuth into a continuous angle.

    Each step is taken as the wrapped increment plus the multiple of 2π that brings it closest
    to what the rotor speed predicts (Ω·Δt). With the speed known this stays right across gaps
    of any length; without it (``omega_rad_s`` None) the plain nearest-branch rule is used,
    which needs steps below half a revolution.

    Parameters
    ----------
    psi_wrapped
        (n,) azimuth in [0, 2π), rad.
    time_s
        (n,) increasing sample times, s.
    omega_rad_s
        (n,) rotor speed, rad/s, or None.

    Returns
    -------
    (n,) unwrapped azimuth, starting at ``psi_wrapped[0]``.

    """
    psi_wrapped = np.asarray(psi_wrapped, dtype=float)
    if omega_rad_s is None:
        return np.unwrap(psi_wrapped)
    omega = np.asarray(omega_rad_s, dtype=float)
    step = np.diff(psi_wrapped)
    expected = 0.5 * (omega[1:] + omega[:-1]) * np.diff(np.asarray(time_s, dtype=float))
    step += TWO_PI * np.round((expected - step) / TWO_PI)
    return np.concatenate([psi_wrapped[:1], psi_wrapped[0] + np.cumsum(step)])


def nondimensional_time(time_s, psi_wrapped=None, omega_rad_s=None):
    """
    Return the report's nondimensional time t = unwrapped azimuth of blade 1.

    Parameters
    ----------
    time_s
        (n,) seconds since the first stamp.
    psi_wrapped
        (n,) measured azimuth of blade 1 in [0, 2π), or None if not recorded.
    omega_rad_s
        (n,) rotor speed, or a scalar, or None.

    Returns
    -------
    (n,) t. Without azimuth, t = ∫Ω dt from 0 (trapezoidal), i.e. Ω·time at constant Ω.

    Raises
    ------
    ValueError
        Neither azimuth nor rotor speed given.

    """
    time_s = np.asarray(time_s, dtype=float)
    if psi_wrapped is not None:
        omega = None if omega_rad_s is None else np.broadcast_to(omega_rad_s, time_s.shape)
        return unwrap_azimuth(psi_wrapped, time_s, omega)
    if omega_rad_s is None:
        raise ValueError('nondimensional time needs the azimuth or the rotor speed')
    omega = np.broadcast_to(np.asarray(omega_rad_s, dtype=float), time_s.shape)
    increments = 0.5 * (omega[1:] + omega[:-1]) * np.diff(time_s)
    return np.concatenate([[0.0], np.cumsum(increments)])


def interpolate_columns(x_new, x, values):
    """Linearly interpolate every column of ``values`` (n, m) from ``x`` onto ``x_new``."""
    values = np.asarray(values, dtype=float)
    out = np.empty((len(x_new), values.shape[1]))
    for j in range(values.shape[1]):
        out[:, j] = np.interp(x_new, x, values[:, j])
    return out
