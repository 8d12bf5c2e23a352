"""
Time base of a recording: rotor azimuth, nondimensional time, multiblade coordinates.

The report's nondimensional time is the rotor azimuth of blade 1, t = ψ (docs/models.md §0), so a
revolution is 2π. At constant rotor speed Ω this is t = Ω·(stamp − first stamp) + ψ(first
stamp); computed from the measured, unwrapped azimuth it stays right when Ω drifts.

Blade k (k = 1..N) sits at ψ_k = ψ + (k − 1)·2π/N, i.e. ψ + (k − 1)·π/2 for four blades.

Multiblade coordinates (docs/models.md §0, N blades, N ≥ 3)::

    β0  = (1/N) Σ β_k                       collective
    βI  = (2/N) Σ β_k cos ψ_k               cos   (forward tilt of the tip-path plane)
    βII = (2/N) Σ β_k sin ψ_k               sin   (left tilt)
    βd  = (1/N) Σ (−1)^k β_k   (N even)     differential (reactionless)

and for N = 4 exactly  β_k = β0 + βI cos ψ_k + βII sin ψ_k + (−1)^k βd.

For pitch, θ_k = θ0 − θI sin ψ_k + θII cos ψ_k, so the 'cos' coordinate of the blade pitches is
the lateral cyclic θII and the 'sin' coordinate is −θI.
"""

import numpy as np
import numpy.typing as npt

# The transforms live with the physics; re-exported here for the readers of records.
from rotor_id.physics.multiblade import (  # noqa: F401
    blade_azimuths, blade_values, multiblade_coordinates)

TWO_PI = 2.0 * np.pi


def wrap_azimuth(psi: npt.ArrayLike) -> float | np.ndarray:
    """Return an azimuth (rad, scalar or array, any branch) wrapped to [0, 2π)."""
    wrapped = np.mod(psi, TWO_PI)
    return np.where(wrapped >= TWO_PI, 0.0, wrapped) if np.ndim(wrapped) else (
        0.0 if wrapped >= TWO_PI else float(wrapped))


def unwrap_azimuth(psi_wrapped: npt.ArrayLike, time_s: npt.ArrayLike,
                   omega_rad_s: npt.ArrayLike | None = None) -> np.ndarray:
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
    step = azimuth_step(np.diff(psi_wrapped), omega[:-1], omega[1:],
                        np.diff(np.asarray(time_s, dtype=float)))
    return np.concatenate([psi_wrapped[:1], psi_wrapped[0] + np.cumsum(step)])


def azimuth_step(wrapped_step: float | np.ndarray, omega_before: float | np.ndarray,
                 omega_after: float | np.ndarray, dt_s: float | np.ndarray
                 ) -> float | np.ndarray:
    """
    Unwrap one step: the wrapped increment plus the 2π multiple nearest to Ω·Δt.

    Ω·Δt is the trapezoidal prediction 0.5 (Ω_before + Ω_after) Δt, so the rule stays right
    across gaps of any length as long as the speed is measured. Scalars or arrays.
    """
    expected = predicted_azimuth_step(omega_before, omega_after, dt_s)
    return wrapped_step + TWO_PI * np.round((expected - wrapped_step) / TWO_PI)


def predicted_azimuth_step(omega_before: float | np.ndarray, omega_after: float | np.ndarray,
                           dt_s: float | np.ndarray) -> float | np.ndarray:
    """Return the azimuth step the measured rotor speed predicts: 0.5 (Ω_before + Ω_after) Δt."""
    return 0.5 * (omega_after + omega_before) * dt_s


class AzimuthUnwrapper:
    """
    :func:`unwrap_azimuth` sample by sample, for streams (the live nodes).

    The same rule (:func:`azimuth_step`) and the same sums in the same order, so the values
    equal ``unwrap_azimuth`` of the whole series from its first sample, bit for bit (with the
    stamps in integer ns converted per step). The first sample's wrapped ψ is the origin.
    """

    def __init__(self) -> None:
        self._first = 0.0  # ψ of the first sample, set by the first add()
        self._sum = 0.0
        self._last: tuple[int, float, float] | None = None

    def add(self, stamp_ns: int, psi: float, omega: float) -> float:
        """Add one sample (stamp in ns, ψ wrapped to [0, 2π), Ω in rad/s); return it unwrapped."""
        if self._last is None:
            self._first = float(psi)
            value = self._first
        else:
            stamp_prev, psi_prev, omega_prev = self._last
            self._sum += float(azimuth_step(psi - psi_prev, omega_prev, omega,
                                            (stamp_ns - stamp_prev) / 1e9))
            value = self._first + self._sum
        self._last = (stamp_ns, psi, omega)
        return value

    @property
    def started(self) -> bool:
        """Say whether a sample was added."""
        return self._last is not None


def nondimensional_time(time_s: npt.ArrayLike, psi_wrapped: npt.ArrayLike | None = None,
                        omega_rad_s: npt.ArrayLike | None = None) -> np.ndarray:
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


def interpolate_columns(x_new: np.ndarray, x: np.ndarray, values: npt.ArrayLike) -> np.ndarray:
    """Linearly interpolate every column of ``values`` (n, m) from ``x`` onto ``x_new``."""
    values = np.asarray(values, dtype=float)
    out = np.empty((len(x_new), values.shape[1]))
    for j in range(values.shape[1]):
        out[:, j] = np.interp(x_new, x, values[:, j])
    return out
