"""
Pitch-stirring inputs of CR-137965 (Ch.2 eqs 1-6, Ch.3 eq. 29, as corrected in docs/models.md §0).

Time ``t`` is the report's nondimensional time: the azimuth of blade 1 (2π per revolution).
Angles are in whatever unit the caller uses consistently (the report uses degrees; the ROS
boundary uses radians): every model is linear in the pitch, so flapping comes out in that unit.

Multiblade pitch follows the report's eq. 3:

    θ_k = θ0 − θI sin ψ_k + θII cos ψ_k,    ψ_k = t + (k − 1)·2π/N

θI is forward cyclic and θII left cyclic. The model input vector used throughout the library is
``u = [θ0, θI, θII]`` (:data:`INPUT_NAMES`).
"""

from dataclasses import dataclass
import math

import numpy as np
import numpy.typing as npt

from rotor_id.physics.multiblade import blade_azimuths, multiblade_coordinates

INPUT_NAMES = ('theta_0', 'theta_I', 'theta_II')
PROGRESSING_OMEGADOT = -0.1 / math.pi   # docs/models.md §1.3: Ch.2 eq. 6 corrected to -0.1/π


@dataclass(frozen=True)
class StirringSchedule:
    """
    Lateral-cyclic step, then constant-acceleration pitch stirring (Ch.2 eqs 1-5).

    Attributes
    ----------
    collective : float
        θ0, collective pitch (report: 2°).
    amplitude : float
        Cyclic amplitude (report: 1.5°).
    omegadot : float
        ω̇ of eq. 1; negative = progressing, positive = regressing stirring. The phase law is
        φ = ω̇ (t − t0)² exactly as printed, so the instantaneous stirring rate is 2 ω̇ (t − t0)
        (docs/models.md §0 and §5 item 3).
    t0 : float
        Stirring start (report: 12 at μ = 0.4, 70 at μ = 0).
    t_step : float
        Time of the lateral-cyclic step (report: 0). Before it the pitch is collective only.

    """

    collective: float = 2.0
    amplitude: float = 1.5
    omegadot: float = PROGRESSING_OMEGADOT
    t0: float = 12.0
    t_step: float = 0.0

    @property
    def direction(self) -> str:
        """'progressing' for ω̇ < 0, 'regressing' for ω̇ > 0."""
        return 'progressing' if self.omegadot < 0 else 'regressing'

    def phase(self, t: npt.ArrayLike) -> np.ndarray:
        """Stirring phase φ(t) = ω̇ (t − t0)² for t > t0, else 0 (eq. 2)."""
        t = np.asarray(t, dtype=float)
        tau = np.maximum(t - self.t0, 0.0)
        return self.omegadot * tau * tau

    def stirring_rate(self, t: npt.ArrayLike) -> np.ndarray:
        """dφ/dt = 2 ω̇ (t − t0) for t > t0 (per unit nondimensional time)."""
        t = np.asarray(t, dtype=float)
        return 2.0 * self.omegadot * np.maximum(t - self.t0, 0.0)

    def multiblade(self, t: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Return ``(θI, θII)`` at times t (eqs 4-5, step at ``t_step``)."""
        t = np.asarray(t, dtype=float)
        on = (t >= self.t_step).astype(float) * self.amplitude
        phi = self.phase(t)
        return on * np.sin(phi), on * np.cos(phi)

    def inputs(self, t: npt.ArrayLike) -> np.ndarray:
        """Model input ``u = [θ0, θI, θII]`` at times t, shape ``(len(t), 3)``."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        theta_i, theta_ii = self.multiblade(t)
        return np.column_stack([np.full_like(t, self.collective), theta_i, theta_ii])

    def blade_pitch(self, t: npt.ArrayLike, n_blades: int = 4) -> np.ndarray:
        """Per-blade pitch θ_k(t), shape ``(len(t), n_blades)`` (eq. 3)."""
        return blade_pitch_from_multiblade(np.atleast_1d(t), self.inputs(t), n_blades)

    def __call__(self, t: npt.ArrayLike) -> np.ndarray:
        """Alias of :meth:`inputs` so a schedule can be used wherever an input signal is."""
        return self.inputs(t)


def blade_pitch_from_multiblade(t: npt.ArrayLike, u: npt.ArrayLike, n_blades: int) -> np.ndarray:
    """θ_k = θ0 − θI sin ψ_k + θII cos ψ_k for the inputs ``u = [θ0, θI, θII]`` (eq. 3)."""
    psi = blade_azimuths(t, n_blades)
    u = np.asarray(u, dtype=float)
    return u[:, :1] - u[:, 1:2] * np.sin(psi) + u[:, 2:3] * np.cos(psi)


def multiblade_from_blade_pitch(t: npt.ArrayLike, blade_pitch: npt.ArrayLike) -> np.ndarray:
    """
    Invert eq. 3: ``u = [θ0, θI, θII]`` from per-blade pitch.

    For N ≥ 3 the multiblade transform (docs/models.md §8). Two blades carry only the
    differential pitch θ_c = (θ1 − θ2)/2 = −θI sin t + θII cos t, so one instant does not fix
    θI and θII; but a two-bladed rotor responds to θ_c alone, and θI = −θ_c sin t,
    θII = θ_c cos t reproduces both blades' pitch exactly (the smallest such pair).
    """
    t = np.atleast_1d(np.asarray(t, dtype=float))
    coords = multiblade_coordinates(blade_pitch, t)
    if 'cos' not in coords:                       # N = 2
        theta_c = -coords['differential']          # blade 1 has the sign (−1)^1
        return np.column_stack([coords['collective'], -theta_c * np.sin(t),
                                theta_c * np.cos(t)])
    return np.column_stack([coords['collective'], -coords['sin'], coords['cos']])


class SampledInput:
    """
    Model input interpolated linearly from samples (e.g. measured blade pitch).

    Parameters
    ----------
    t : array_like, shape (n,)
        Nondimensional sample times, increasing.
    u : array_like, shape (n, 3)
        ``[θ0, θI, θII]`` at those times.

    Outside the sampled span the end values are held (no extrapolation).

    """

    def __init__(self, t: npt.ArrayLike, u: npt.ArrayLike) -> None:
        self.t = np.asarray(t, dtype=float)
        self.u = np.asarray(u, dtype=float)
        if self.t.ndim != 1 or self.u.shape != (self.t.size, len(INPUT_NAMES)):
            raise ValueError(f'SampledInput needs t of shape (n,) and u of shape (n, 3); '
                             f'got {self.t.shape} and {self.u.shape}')
        if self.t.size < 2 or np.any(np.diff(self.t) <= 0):
            raise ValueError('SampledInput needs at least two strictly increasing sample times')

    @classmethod
    def from_blade_pitch(cls, t: npt.ArrayLike, blade_pitch: npt.ArrayLike) -> 'SampledInput':
        """Build from measured per-blade pitch (eq. 3 inverted at each sample)."""
        return cls(t, multiblade_from_blade_pitch(t, blade_pitch))

    def __call__(self, t: npt.ArrayLike) -> np.ndarray:
        """``u`` at times t, shape ``(len(t), 3)``."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        return np.column_stack([np.interp(t, self.t, self.u[:, j])
                                for j in range(self.u.shape[1])])


def measured_stirring(t: npt.ArrayLike, u: npt.ArrayLike,
                      min_turn: float = math.pi / 2) -> tuple[str, float]:
    """
    Direction and mean rate of the stirring in a measured input (eqs 4-5 inverted).

    The stirring phase is φ = atan2(θI, θII) (θI = a sin φ, θII = a cos φ); it falls for
    progressing stirring (ω̇ < 0) and rises for regressing (ω̇ > 0). Only samples with at
    least half the largest cyclic amplitude count.

    Parameters
    ----------
    t : array_like, shape (n,)
        Nondimensional times.
    u : array_like, shape (n, 3)
        ``[θ0, θI, θII]`` at those times (e.g. :func:`multiblade_from_blade_pitch`).
    min_turn : float
        Smallest phase change (rad) that counts as stirring.

    Returns
    -------
    (direction, rate)
        'progressing', 'regressing' or 'none' (the phase turns less than ``min_turn``), and the
        mean |dφ/dt| over the samples, per unit nondimensional time (= per rev of the rotor).

    """
    t = np.asarray(t, dtype=float)
    u = np.asarray(u, dtype=float)
    amplitude = np.hypot(u[:, 1], u[:, 2])
    keep = amplitude >= 0.5 * np.max(amplitude, initial=0.0)
    if np.count_nonzero(keep) < 2 or not np.any(amplitude > 0):
        return 'none', 0.0
    phase = np.unwrap(np.arctan2(u[keep, 1], u[keep, 2]))
    turn = float(phase[-1] - phase[0])
    rate = abs(turn) / max(float(t[keep][-1] - t[keep][0]), 1e-12)
    if abs(turn) < min_turn:
        return 'none', rate
    return ('progressing' if turn < 0 else 'regressing'), rate
