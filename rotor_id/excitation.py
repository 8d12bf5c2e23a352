"""
A stirring test point as a rig runs it: bounded, finite, and abortable (no ROS here).

The report's schedule (:class:`rotor_id.physics.stirring.StirringSchedule`, Ch.2 eqs 1-5) is
trim, a lateral cyclic step, then stirring with phase φ = ω̇ (t − t0)², whose rate 2 ω̇ (t − t0)
grows without bound. On a test stand the stirring must end: :class:`StirringTestPoint` ends it
after ``duration_rad`` of azimuth or when the stirring rate reaches ``max_stirring_rate_rad_s``,
whichever comes first, and then ramps the cyclic back to trim over ``ramp_s``; an abort starts
the same ramp at once. The cyclic vector is frozen at the ramp's start and shrinks linearly to
zero (no further rotation), so the blade pitch moves monotonically back to the collective. Then
the test point is done: collective only.

Time ``t`` is the report's nondimensional time (azimuth of blade 1, rad); the rotor speed Ω
(rad/s) converts the limits given in SI.
"""

import math
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

if TYPE_CHECKING:
    from rotor_id.physics.stirring import StirringSchedule

# Phases: the values of rotor_id_msgs/StirringCommand's PHASE_* constants.
PHASE_TRIM = 0
PHASE_CYCLIC_STEP = 1
PHASE_STIRRING = 2
PHASE_DONE = 3
PHASE_RAMP_DOWN = 4
PHASE_NAMES = {PHASE_TRIM: 'trim', PHASE_CYCLIC_STEP: 'cyclic step', PHASE_STIRRING: 'stirring',
               PHASE_DONE: 'done', PHASE_RAMP_DOWN: 'ramp down'}


def check_excitation_limits(amplitude_rad: float, max_amplitude_rad: float, duration_rad: float,
                            max_stirring_rate_rad_s: float, ramp_s: float) -> str | None:
    """
    Return the reason the excitation settings are unsafe or meaningless, or None.

    Every value must be finite; the amplitude at most ``max_amplitude_rad``; the duration and
    the maximum rate positive; the ramp not negative.
    """
    values = {'amplitude_rad': amplitude_rad, 'max_amplitude_rad': max_amplitude_rad,
              'duration_rad': duration_rad, 'max_stirring_rate_rad_s': max_stirring_rate_rad_s,
              'ramp_s': ramp_s}
    for name, value in values.items():
        if not math.isfinite(value):
            return f'{name} = {value} is not a finite number'
    if amplitude_rad < 0 or amplitude_rad > max_amplitude_rad:
        return (f'amplitude_rad = {amplitude_rad:.4g} rad is outside [0, max_amplitude_rad = '
                f'{max_amplitude_rad:.4g}] (radians, not degrees?)')
    if duration_rad <= 0:
        return f'duration_rad = {duration_rad} must be positive (rad of azimuth of stirring)'
    if max_stirring_rate_rad_s <= 0:
        return f'max_stirring_rate_rad_s = {max_stirring_rate_rad_s} must be positive'
    if ramp_s < 0:
        return f'ramp_s = {ramp_s} must not be negative'
    return None


class StirringTestPoint:
    """
    One run of the stirring schedule with its end, its ramp back to trim and its abort.

    Parameters
    ----------
    schedule
        StirringSchedule (t_step, t0, amplitude, ω̇, collective).
    omega_rad_s
        Rotor speed Ω, rad/s: converts the rate limit and the ramp time to azimuth.
    duration_rad
        Longest stirring, rad of azimuth after t0.
    max_stirring_rate_rad_s
        The stirring ends when |dφ/dt| = |2 ω̇ (t − t0)| Ω reaches this.
    ramp_s
        Time to ramp the cyclic back to trim, s.
    max_amplitude_rad
        Largest cyclic amplitude allowed.

    Raises
    ------
    ValueError
        Unsafe or meaningless settings (the message names the value).

    """

    def __init__(self, schedule: 'StirringSchedule', omega_rad_s: float, duration_rad: float,
                 max_stirring_rate_rad_s: float, ramp_s: float,
                 max_amplitude_rad: float) -> None:
        reason = check_excitation_limits(schedule.amplitude, max_amplitude_rad, duration_rad,
                                         max_stirring_rate_rad_s, ramp_s)
        if reason is None and not omega_rad_s > 0:
            reason = f'rotor speed {omega_rad_s} rad/s is not positive'
        if reason:
            raise ValueError(reason)
        self.schedule = schedule
        self.omega_rad_s = float(omega_rad_s)
        # rate 2|ω̇|(t − t0) per unit t, times Ω in rad/s: reaches the limit after this much t
        slope = 2.0 * abs(schedule.omegadot) * self.omega_rad_s
        to_rate_limit = max_stirring_rate_rad_s / slope if slope > 0 else math.inf
        if to_rate_limit < duration_rad:
            self.end_reason = (f'stirring rate reached max_stirring_rate_rad_s '
                               f'{max_stirring_rate_rad_s:g} rad/s')
        else:
            self.end_reason = f'duration_rad {duration_rad:g} elapsed'
        self.t_end = schedule.t0 + min(duration_rad, to_rate_limit)   # stirring stops here
        self.ramp_rad = ramp_s * self.omega_rad_s
        self.t_ramp = self.t_end          # the ramp starts here (earlier after an abort)
        self.aborted: str | None = None   # reason of an abort, None if not aborted

    @property
    def t_done(self) -> float:
        """Return t from which the test point is done (collective only)."""
        return self.t_ramp + self.ramp_rad

    def abort(self, t: float, reason: str = 'abort requested') -> bool:
        """
        Start the ramp back to trim at ``t`` (no effect once ramping or done).

        Returns
        -------
        True if this abort changed the course of the test point.

        """
        if t >= self.t_ramp:
            return False
        self.aborted = reason
        self.t_ramp = t
        if t < self.schedule.t_step:             # before the cyclic step: nothing to ramp
            self.ramp_rad = 0.0
        return True

    def phase(self, t: float) -> int:
        """Return the PHASE_* at ``t``."""
        if t >= self.t_done:
            return PHASE_DONE
        if t >= self.t_ramp:
            return PHASE_RAMP_DOWN
        if t < self.schedule.t_step:
            return PHASE_TRIM
        return PHASE_CYCLIC_STEP if t <= self.schedule.t0 else PHASE_STIRRING

    def inputs(self, t: npt.ArrayLike) -> np.ndarray:
        """Return (n, 3) u = [θ0, θI, θII] at the times ``t`` (rad)."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        u = self.schedule.inputs(np.minimum(t, self.t_ramp))   # cyclic frozen from the ramp on
        if self.ramp_rad > 0:
            scale = np.clip(1.0 - (t - self.t_ramp) / self.ramp_rad, 0.0, 1.0)
            scale[t >= self.t_done] = 0.0                 # done: exactly trim
        else:
            scale = (t < self.t_ramp).astype(float)
        u[:, 1:] *= scale[:, None]
        return u

    def stirring_phase(self, t: float) -> float:
        """Return φ at ``t`` (frozen from the ramp on), rad."""
        return float(self.schedule.phase(min(t, self.t_ramp)))

    def stirring_rate(self, t: float) -> float:
        """Return dφ/dt at ``t``, rad/s (0 once ramping: the cyclic no longer rotates)."""
        if t >= self.t_ramp:
            return 0.0
        return float(self.schedule.stirring_rate(t)) * self.omega_rad_s
