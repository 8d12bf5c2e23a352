"""
Directional frequency responses from stirring sweeps, CIFER's cost and a frequency-domain fit.

In complex fixed-frame coordinates the cyclic pitch θ_c = θI + iθII and the cyclic flap
β_c = βI + iβII (docs/models.md §0, §8) turn a progressing stirring into positive and a
regressing one into negative frequencies; their ratio is the directional frequency response
(dFRF) of :func:`rotor_id.physics.models.directional_frequency_response`. Frequencies are in
per rev (the nondimensional time t is the azimuth), so a record whose rotor speed drifts keeps
its frequency axis.

The estimate (docs/frequency_response.md gives the reasons)
-------------------------------------------------------------
Each run's transform window starts with the rotor steady (the recording convention starts in
trim) and its spectra are those of the time derivatives of θ_c and β_c,

    Θ(ω) = Σ_j (θ_c,j − θ_c,j−1) e^{−iω t_j−½},      B(ω) likewise,

which is the Fourier transform of the whole transient with the end-point terms included: a
record that starts steady needs no taper at its start and no detrending. At each frequency of
the grid (spacing 2π/T, independent for white noise) the runs whose stirring swept it are
pooled (n_d = their number):

    H = Σ Θ* B / Σ |Θ|²,   γ² = |H|² Σ|Θ|² / (|H|² Σ|Θ|² + Σ σ²),
    ε_r = √(1 − γ²) / (|γ| √(2 n_d))          (Bendat & Piersol, random error of |H| and ∠H)

with σ² the flap-noise power at that frequency, estimated from the residual of a response
linear across the ``NOISE_BINS`` neighbouring frequencies (Pintelon & Schoukens' local
method). γ² is then the ordinary coherence Σ|Θ* B|²/(Σ|Θ|² Σ|B|²) in expectation, without
the bias a smoothing over neighbouring frequencies has near a lightly damped mode.

The estimate is linear in the flap record, so the same operator applied to a model's simulated
flap gives the model's response exactly as this estimate sees it (:meth:`Spectra.of`): the
transient of a stirring that is cut off at the end of the record is then in both, which the
fit (:func:`fit_frequency_response`) relies on.

CIFER's cost (Tischler & Remple, eq. 11.x)
------------------------------------------
    J = (20/n_ω) Σ W_γ [W_g (|T_c| − |T_m|)² + W_p (∠T_c − ∠T_m)²]
    W_γ = [1.58 (1 − exp(−γ²))]²,  W_g = 1,  W_p = 0.01745,  |·| in dB, ∠ in degrees

over the points with γ² ≥ 0.6; J ≤ 100 is an acceptable fit.
"""

from dataclasses import dataclass, field
import math
import time
from typing import Any, Protocol, Sequence, TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from rotor_id.estimation.output_error import (dependence_warnings, Estimate,
                                              IdentificationError, ParameterValues, Progress)
from rotor_id.estimation.simulate import simulate
from rotor_id.physics.multiblade import multiblade_coordinates
from rotor_id.physics.stirring import multiblade_from_blade_pitch, SampledInput

if TYPE_CHECKING:
    from rotor_id.physics.models import RotorModel

#: Independent neighbouring frequencies (spacing 2π/T) over which the flap noise of a point is
#: estimated: seven give three degrees of freedom after the local response and transient.
NOISE_BINS = 7
#: Largest (frequencies × samples) of the estimator (complex, 16 bytes each): 160 MB, a
#: stirring test of a minute at 1 kHz; a longer window spans several tests.
OPERATOR_LIMIT = 10_000_000
#: CIFER's coherence threshold for a point to enter the cost and the fit.
COHERENCE_MIN = 0.6
#: CIFER's weights: magnitude (dB) and phase (deg), W_p/W_g = 1 dB per 7.57 deg.
MAGNITUDE_WEIGHT = 1.0
PHASE_WEIGHT = 0.01745
#: CIFER's rule: an average J up to 100 is an acceptable fit.
ACCEPTABLE_COST = 100.0
DB = 20.0 / math.log(10.0)          # dB per neper
DEG = 180.0 / math.pi


class StirringRecord(Protocol):
    """What :func:`sweep_from_record` reads of a record (a rotor_id.io Record has it)."""

    time_s: np.ndarray
    t: np.ndarray
    rotor_speed_rad_s: np.ndarray
    blade_flap: np.ndarray
    blade_pitch: np.ndarray


@dataclass
class Sweep:
    """
    One run's cyclic pitch and flap in complex fixed-frame coordinates over its window.

    ``t`` nondimensional time (rad of azimuth), ``pitch`` θ_c = θI + iθII, ``flap``
    β_c = βI + iβII over the transform window; ``omega_rad_s`` the mean rotor speed, ``band``
    the signed frequencies (per rev) the stirring swept. ``record_t`` and ``inputs`` (the
    measured [θ0, θI, θII]) cover the whole record from its first sample, where the rotor is in
    trim, so that a model is simulated from there; ``start`` is the window's first sample in it.
    """

    name: str
    t: np.ndarray
    pitch: np.ndarray
    flap: np.ndarray
    omega_rad_s: float
    band: tuple
    record_t: np.ndarray
    inputs: SampledInput
    start: int
    stirring_t: tuple
    window_s: tuple
    #: samples at the window's start and end over which the pitch is steady (≥ 1)
    ends: tuple = (1, 1)


def cyclic_signals(t: npt.ArrayLike, blade_pitch: np.ndarray, blade_flap: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return θ_c = θI + iθII and β_c = βI + iβII (docs/models.md §0, §8) from blade data."""
    u = multiblade_from_blade_pitch(t, blade_pitch)
    coords = multiblade_coordinates(blade_flap, t)
    if 'cos' not in coords:
        raise ValueError(f'a {np.shape(blade_flap)[1]}-bladed rotor has no fixed-frame cyclic '
                         'flap: its directional frequency response is not defined')
    return u[:, 1] + 1j * u[:, 2], coords['cos'] + 1j * coords['sin'], u


def stirring_frequency(t: np.ndarray, pitch: np.ndarray, smoothing: float = 1.0
                       ) -> tuple[np.ndarray, np.ndarray]:
    """
    Instantaneous stirring frequency (per rev, signed) of θ_c, and where the cyclic is on.

    θ_c = i a e^{−iφ} (docs/models.md §0): its phase advances at −dφ/dt, positive for
    progressing stirring. The derivative is a central difference over ``smoothing`` rad of
    azimuth; samples with less than half the largest cyclic amplitude count as off.
    """
    amplitude = np.abs(pitch)
    on = amplitude >= 0.5 * np.max(amplitude, initial=0.0)
    if np.count_nonzero(on) < 3 or not np.any(amplitude > 0):
        return np.zeros(t.size), on
    phase = np.interp(t, t[on], np.unwrap(np.angle(pitch[on])))
    ahead = np.interp(t + 0.5 * smoothing, t, phase)
    behind = np.interp(t - 0.5 * smoothing, t, phase)
    span = np.interp(t + 0.5 * smoothing, t, t) - np.interp(t - 0.5 * smoothing, t, t)
    rate = (ahead - behind) / np.maximum(span, 1e-12)
    return np.where(on, rate, 0.0), on


def sweep_from_record(record: StirringRecord, name: str = 'run',
                      window_s: Sequence[float] | None = None) -> 'Sweep':
    """
    Return the :class:`Sweep` of a record: its stirring band and its transform window.

    The stirring part is found in the measured pitch (:func:`stirring_frequency`): the samples
    where the cyclic turns faster than 5 % of its fastest rate; the frequencies it swept are
    the band of the estimate. The transform window defaults to the whole record, which starts
    in trim (the recording convention) and so needs no start taper, and whose length sets the
    frequency resolution 2π/T (a window of the stirring alone would resolve a quarter as much
    in the report's tests); ``window_s`` (seconds after the first sample) overrides it.
    Raises ValueError, before any spectrum, when the window holds no stirring.
    """
    t_all = np.asarray(record.t, dtype=float)
    pitch_all, flap_all, u = cyclic_signals(t_all, record.blade_pitch, record.blade_flap)
    rate, _ = stirring_frequency(t_all, pitch_all)
    fastest = float(np.max(np.abs(rate), initial=0.0))
    stirring = np.abs(rate) > 0.05 * fastest
    if window_s is not None:
        inside = ((record.time_s >= window_s[0] - 1e-9) & (record.time_s <= window_s[1] + 1e-9))
    else:
        inside = np.ones(t_all.size, dtype=bool)
    keep = np.flatnonzero(inside)
    if keep.size < 16:
        raise ValueError(f'{name}: the window holds {keep.size} samples; a frequency response '
                         'needs the stirring part of the record (widen --window-s)')
    window = slice(int(keep[0]), int(keep[-1]) + 1)
    swept = stirring[window]
    dt = np.gradient(t_all)[window]
    turned = float(np.sum(np.abs(rate[window][swept]) * dt[swept]))
    if fastest <= 0.0 or turned < math.pi:
        raise ValueError(f'{name}: no pitch stirring in the window (the cyclic pitch turns '
                         f'{turned:.2g} rad); give a record with a stirring sweep, or a '
                         '--window-s that holds it')
    idx = np.flatnonzero(swept) + window.start
    band = (float(np.min(rate[idx])), float(np.max(rate[idx])))
    return Sweep(name=name, t=t_all[window], pitch=pitch_all[window], flap=flap_all[window],
                 omega_rad_s=float(np.mean(record.rotor_speed_rad_s[window])), band=band,
                 record_t=t_all, inputs=SampledInput(t_all, u), start=window.start,
                 stirring_t=(float(t_all[idx[0]]), float(t_all[idx[-1]])),
                 window_s=(float(record.time_s[window.start]),
                           float(record.time_s[window.stop - 1])),
                 ends=steady_ends(t_all[window], pitch_all[window]))


def steady_ends(t: np.ndarray, pitch: np.ndarray, longest: float = 2.0 * math.pi,
                tolerance: float = 0.01) -> tuple[int, int]:
    """
    Count the samples at each end of the window where the cyclic pitch holds still (≥ 1).

    At most ``longest`` rad of azimuth, within ``tolerance`` of the largest cyclic amplitude.
    The end values of a transform of the derivative enter every frequency alike; taken as the
    mean over these samples, their noise does not swamp the lowest frequencies.
    """
    scale = tolerance * max(float(np.max(np.abs(pitch), initial=0.0)), 1e-300)
    out = []
    for order in (slice(None), slice(None, None, -1)):
        p, tt = pitch[order], t[order]
        moved = (np.abs(p - p[0]) > scale) | (np.abs(tt - tt[0]) > longest)
        out.append(int(np.argmax(moved)) if moved.any() else p.size)
    return max(out[0], 1), max(out[1], 1)


def _with_steady_ends(x, ends):
    """Return x with its first and last samples replaced by their steady means (linear)."""
    x = np.array(x, copy=True)
    head, tail = ends
    x[0] = x[:head].mean(axis=0)
    x[-1] = x[x.shape[0] - tail:].mean(axis=0)
    return x


def _derivative_transform_matrix(t, omega):
    """E (F, T−1): the transform of the first differences at the interval midpoints."""
    mid = 0.5 * (t[1:] + t[:-1])
    return np.exp(-1j * np.multiply.outer(omega, mid - t[0]))


@dataclass
class Spectra:
    """
    The spectra of one or more sweeps at the points of a frequency grid, and the estimator.

    ``frequency`` per rev (signed); ``guu`` = Σ_r |Θ_r|², ``gyy`` = Σ_r |B_r|², ``guy`` =
    Σ_r Θ_r* B_r over the runs r whose stirring swept the point (``averages`` of them);
    ``noise`` = Σ_r σ_r², the flap-noise power at the point (:func:`estimate_spectra`).
    :meth:`of` applies the same estimator H = Σ Θ* B / Σ|Θ|² to other flap signals (a model's
    simulation and its sensitivities).
    """

    frequency: np.ndarray
    guu: np.ndarray
    gyy: np.ndarray
    guy: np.ndarray
    noise: np.ndarray
    averages: np.ndarray
    operators: list = field(default_factory=list)    # per sweep: (F, T−1) weights on Δβ_c
    ends: list = field(default_factory=list)         # per sweep: its steady ends
    #: Σ_r |Θ_r(−ω)|² / Σ_r |Θ_r(ω)|²: the input a rotor that is not axisymmetric (μ > 0)
    #: turns into response at ω through its mirror response (physics DirectionalResponse)
    # (given by every estimate; the default keeps the field optional in the constructor)
    mirror_input: np.ndarray = None  # type: ignore[assignment]

    def of(self, flaps: Sequence[np.ndarray]) -> np.ndarray:
        """Return the estimator applied to one flap signal per sweep, (F,) or (F, k)."""
        out: Any = 0.0                  # the sum over the sweeps, an array from the first on
        for weights, ends, flap in zip(self.operators, self.ends, flaps):
            out = out + weights @ np.diff(_with_steady_ends(flap, ends), axis=0)
        return out

    def restricted(self, points: np.ndarray) -> 'Spectra':
        """Return the estimator at some of the points only (for a fit)."""
        return Spectra(frequency=self.frequency[points], guu=self.guu[points],
                       gyy=self.gyy[points], guy=self.guy[points], noise=self.noise[points],
                       averages=self.averages[points],
                       operators=[op[points] for op in self.operators], ends=self.ends,
                       mirror_input=self.mirror_input[points])


def _local_noise(U, Y):
    """
    σ² of the flap noise at each point from its neighbourhood (U, Y: (F, b) spectra).

    B = (a + b·δ) Θ + c + d·δ + noise is fitted over the b neighbouring independent
    frequencies δ: a response linear across them, and a transient term (the record's end
    values, a stirring cut off by its end) that is smooth in frequency whatever the input
    (Pintelon & Schoukens' local polynomial method). The residual power over b − 4 degrees of
    freedom estimates the noise power of one frequency.
    """
    F, b = U.shape
    delta = np.arange(b) - 0.5 * (b - 1)
    ones = np.ones((F, b))
    A = np.stack([U, U * delta[None, :], ones, ones * delta[None, :]], axis=2)   # (F, b, 4)
    noise = np.zeros(F)
    for f in range(F):
        coef, *_ = np.linalg.lstsq(A[f], Y[f], rcond=None)
        residual = Y[f] - A[f] @ coef
        noise[f] = float(np.sum(np.abs(residual) ** 2)) / (b - A.shape[2])
    return noise


def _end_noise(sweep, frequency, local):
    """
    Noise power the two end values add at every frequency, which the local model cannot see.

    The end values (means over ``sweep.ends`` samples) enter the transform of every frequency
    alike; the local model's transient term takes them for signal. Their variance is
    σ²(1/head + 1/tail), σ² the flap noise of one sample, found from the local noise powers:
    the differences of white noise have the power σ² (T − 1)·2(1 − cos ωΔt) at ω.
    """
    dt = float(np.mean(np.diff(sweep.t)))
    shape = (sweep.t.size - 1) * 2.0 * (1.0 - np.cos(frequency * dt))
    usable = (shape > 0) & (local > 0)
    if not np.any(usable):
        return np.zeros(frequency.size)
    sigma2 = float(np.median(local[usable] / shape[usable]))
    head, tail = sweep.ends
    return np.full(frequency.size, sigma2 * (1.0 / head + 1.0 / tail))


def estimate_spectra(sweeps: Sequence[Sweep], noise_bins: int = NOISE_BINS,
                     frequency: npt.ArrayLike | None = None) -> Spectra:
    """
    Return the :class:`Spectra` of ``sweeps`` at each point of the grid.

    The estimate at a point uses the point's own frequency only (no smoothing: its bias near a
    lightly damped mode would be that of the smoothing width); the flap noise there is
    estimated from ``noise_bins`` independent neighbouring frequencies (:func:`_local_noise`).
    The grid (``frequency``, per rev, signed) defaults to the finest spacing 2π/T of the runs
    over the union of the bands they swept; a run contributes to a point only when its
    stirring swept it, so a progressing run never enters the negative frequencies.
    """
    if not sweeps:
        raise ValueError('no sweep to estimate a frequency response from')
    if noise_bins < 3:
        raise ValueError(f'noise_bins must be at least 3, got {noise_bins}')
    spacing = [2.0 * math.pi / (s.t[-1] - s.t[0]) for s in sweeps]
    if frequency is None:
        step = min(spacing)
        points = []
        for s in sweeps:
            ks = np.arange(math.ceil(s.band[0] / step), math.floor(s.band[1] / step) + 1)
            points.append(ks[ks != 0])
        frequency = np.unique(np.concatenate(points)) * step
    frequency = np.asarray(frequency, dtype=float)
    size = sum(frequency.size * s.t.size for s in sweeps)
    if size > OPERATOR_LIMIT:
        longest = max(sweeps, key=lambda s: s.t.size)
        raise ValueError(
            f'{longest.name}: the window {longest.window_s[0]:.4g}-{longest.window_s[1]:.4g} s '
            f'holds {longest.t.size} samples and resolves {frequency.size} frequencies: too '
            'long for a frequency response of one stirring test; give --window-s around the '
            'test (from trim before the stirring to the end of its settling)')
    offsets = np.arange(noise_bins) - 0.5 * (noise_bins - 1)
    centre = noise_bins // 2
    guu = np.zeros(frequency.size)
    gyy = np.zeros(frequency.size)
    guy = np.zeros(frequency.size, dtype=complex)
    noise = np.zeros(frequency.size)
    mirror = np.zeros(frequency.size)
    averages = np.zeros(frequency.size, dtype=int)
    parts = []
    for s, d in zip(sweeps, spacing):
        inside = (frequency >= s.band[0] - 1e-12) & (frequency <= s.band[1] + 1e-12)
        du = np.diff(_with_steady_ends(s.pitch, s.ends))
        dy = np.diff(_with_steady_ends(s.flap, s.ends))
        U = np.empty((frequency.size, noise_bins), dtype=complex)
        Y = np.empty_like(U)
        centre_rows = np.empty((frequency.size, du.size), dtype=complex)
        chunk = max(1, OPERATOR_LIMIT // (10 * noise_bins * max(du.size, 1)))
        for first in range(0, frequency.size, chunk):       # bounded memory
            rows = slice(first, first + chunk)
            grid = (frequency[rows, None] + d * offsets[None, :]).ravel()
            E = _derivative_transform_matrix(s.t, grid).reshape(-1, noise_bins, du.size)
            U[rows], Y[rows] = E @ du, E @ dy
            centre_rows[rows] = E[:, centre]
        U0, Y0 = np.where(inside, U[:, centre], 0.0), np.where(inside, Y[:, centre], 0.0)
        guu += np.abs(U0) ** 2
        gyy += np.abs(Y0) ** 2
        guy += np.conj(U0) * Y0
        local = _local_noise(U, Y)
        noise += np.where(inside, local + _end_noise(s, frequency, local), 0.0)
        mirror += np.where(inside, np.abs(np.conj(centre_rows) @ du) ** 2, 0.0)   # Θ(−ω)
        averages += inside
        centre_rows *= np.conj(U0)[:, None]
        parts.append(centre_rows)
    keep = (averages > 0) & (guu > 0)
    operators = [part[keep] / guu[keep, None] for part in parts]
    return Spectra(frequency=frequency[keep], guu=guu[keep], gyy=gyy[keep], guy=guy[keep],
                   noise=noise[keep], averages=averages[keep], operators=operators,
                   ends=[s.ends for s in sweeps],
                   mirror_input=mirror[keep] / guu[keep])


@dataclass
class FrequencyResponse:
    """
    An estimated directional FRF β_c/θ_c with its coherence and random error per point.

    Frequencies per rev (signed: + progressing, − regressing) and in Hz at the runs' mean
    rotor speed; ``response`` complex (rad/rad); ``random_error`` ε_r of Bendat & Piersol
    (relative error of the magnitude, and the phase error in rad).
    """

    frequency_per_rev: np.ndarray
    response: np.ndarray
    coherence: np.ndarray
    random_error: np.ndarray
    averages: np.ndarray
    omega_rad_s: float
    noise_bins: int
    runs: list
    # (given by every estimate; the default keeps the field optional in the constructor)
    spectra: Spectra = None  # type: ignore[assignment]

    @property
    def frequency_hz(self) -> np.ndarray:
        """Frequencies in Hz at the mean rotor speed (the per-rev value times Ω/2π)."""
        return self.frequency_per_rev * self.omega_rad_s / (2.0 * math.pi)

    @property
    def magnitude(self) -> np.ndarray:
        """|H|, rad/rad."""
        return np.abs(self.response)

    @property
    def phase_deg(self) -> np.ndarray:
        """∠H in degrees, in (−180, 180]."""
        return np.degrees(np.angle(self.response))

    def usable(self, coherence_min: float = COHERENCE_MIN) -> np.ndarray:
        """Return the points with γ² at least ``coherence_min`` (CIFER: 0.6)."""
        return self.coherence >= coherence_min

    def as_json(self) -> dict[str, Any]:
        """Return the JSON of ``rotor-id frequency-response`` (other tools read its keys)."""
        return {
            'frequency_per_rev': [float(v) for v in self.frequency_per_rev],
            'frequency_hz': [float(v) for v in self.frequency_hz],
            'magnitude': [float(v) for v in self.magnitude],
            'phase_deg': [float(v) for v in self.phase_deg],
            'coherence': [float(v) for v in self.coherence],
            'random_error': [float(v) for v in self.random_error],
            'averages': [int(v) for v in self.averages],
            'mirror_input': [float(v) for v in self.spectra.mirror_input],
            'noise_bins': int(self.noise_bins),
            'omega_rad_s': float(self.omega_rad_s),
            'runs': list(self.runs),
        }


def random_error(coherence: npt.ArrayLike, averages: npt.ArrayLike) -> np.ndarray:
    """ε_r = √(1 − γ²)/(|γ| √(2 n_d)) (Bendat & Piersol), for |H| (relative) and ∠H (rad)."""
    gamma2 = np.clip(np.asarray(coherence, dtype=float), 1e-12, 1.0)
    return np.sqrt(1.0 - gamma2) / (np.sqrt(gamma2) * np.sqrt(2.0 * np.asarray(averages)))


def estimate_frequency_response(sweeps: Sequence[Sweep], noise_bins: int = NOISE_BINS,
                                frequency: npt.ArrayLike | None = None) -> FrequencyResponse:
    """Estimate the dFRF of one or more :class:`Sweep` (module docstring)."""
    spectra = estimate_spectra(sweeps, noise_bins, frequency)
    if spectra.frequency.size == 0:
        raise ValueError('the stirring swept no frequency the records resolve (each needs '
                         'a few revolutions of stirring); record a longer sweep')
    response = spectra.guy / spectra.guu
    signal = np.abs(response) ** 2 * spectra.guu             # the flap power explained
    with np.errstate(invalid='ignore', divide='ignore'):
        coherence = np.nan_to_num(signal / (signal + spectra.noise))
    return FrequencyResponse(
        frequency_per_rev=spectra.frequency, response=response, coherence=coherence,
        random_error=random_error(coherence, spectra.averages), averages=spectra.averages,
        omega_rad_s=float(np.mean([s.omega_rad_s for s in sweeps])),
        noise_bins=int(noise_bins), runs=[s.name for s in sweeps], spectra=spectra)


# ------------------------------------------------------------------------------ CIFER's cost
def coherence_weight(coherence: npt.ArrayLike) -> np.ndarray:
    """W_γ = [1.58 (1 − exp(−γ²))]² (Tischler & Remple)."""
    return (1.58 * (1.0 - np.exp(-np.asarray(coherence, dtype=float)))) ** 2


def response_errors(measured: npt.ArrayLike, model: npt.ArrayLike
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Return the magnitude (dB) and phase (deg, within ±180) errors of ``model``."""
    ratio = np.asarray(model) / np.asarray(measured)
    return DB * np.log(np.abs(ratio)), DEG * np.angle(ratio)


def cifer_cost(measured: npt.ArrayLike, model: npt.ArrayLike, coherence: npt.ArrayLike
               ) -> float:
    """J = (20/n) Σ W_γ [W_g Δ|H|dB² + W_p Δ∠H deg²] over the points given (NaN if none)."""
    if np.size(measured) == 0:
        return float('nan')
    mag, phase = response_errors(measured, model)
    terms = coherence_weight(coherence) * (MAGNITUDE_WEIGHT * mag ** 2
                                           + PHASE_WEIGHT * phase ** 2)
    return float(20.0 / np.size(measured) * np.sum(terms))


@dataclass
class BandCost:
    """CIFER's J over one band of frequencies (per rev, signed)."""

    low: float
    high: float
    points: int
    cost: float

    @property
    def acceptable(self) -> bool:
        """J ≤ 100 (CIFER)."""
        return bool(self.points) and self.cost <= ACCEPTABLE_COST

    def as_json(self) -> dict[str, Any]:
        """Band limits, points and J."""
        return {'frequency_per_rev': [float(self.low), float(self.high)],
                'points': int(self.points), 'cost': float(self.cost),
                'acceptable': self.acceptable}


def band_costs(estimate: FrequencyResponse, model_response: np.ndarray, bands_per_side: int = 3,
               coherence_min: float = COHERENCE_MIN) -> tuple[list[BandCost], float]:
    """
    J per band: each direction's usable points split into ``bands_per_side`` equal bands.

    Returns the list of :class:`BandCost` and the J over all usable points.
    """
    use = estimate.usable(coherence_min)
    f = estimate.frequency_per_rev
    out = []
    for side in (f < 0, f > 0):
        idx = np.flatnonzero(use & side)
        if idx.size == 0:
            continue
        for chunk in np.array_split(idx, min(bands_per_side, idx.size)):
            out.append(BandCost(low=float(f[chunk].min()), high=float(f[chunk].max()),
                                points=int(chunk.size),
                                cost=cifer_cost(estimate.response[chunk],
                                                model_response[chunk],
                                                estimate.coherence[chunk])))
    idx = np.flatnonzero(use)
    total = cifer_cost(estimate.response[idx], model_response[idx], estimate.coherence[idx])
    return out, total


# ------------------------------------------------------------------ the model as estimated
def model_start(model: 'RotorModel', p: np.ndarray, sweep: Sweep, collective: float
                ) -> np.ndarray:
    """State at the record's first sample: in trim at the held input (the convention)."""
    u0 = sweep.inputs(sweep.record_t[:1])
    if model.time_invariant:
        return model.equilibrium(sweep.record_t[:1], p, u0)
    return model.trim_state(p, collective, t=float(sweep.record_t[0]))


def _start_jacobian(model, p, sweep, collective, index):
    if model.time_invariant:
        u0 = sweep.inputs(sweep.record_t[:1])
        return model.equilibrium_jacobian(sweep.record_t[:1], p, u0)[:, index]
    columns = []
    for i in index:
        h = 1e-6 * max(1.0, abs(p[i]))
        up, down = p.copy(), p.copy()
        up[i] += h
        down[i] -= h
        columns.append((model_start(model, up, sweep, collective)
                        - model_start(model, down, sweep, collective)) / (2.0 * h))
    return np.column_stack(columns)


def model_flap(model: 'RotorModel', p: npt.ArrayLike, sweep: Sweep, collective: float,
               index: Sequence[int] = ()) -> tuple[np.ndarray, np.ndarray | None]:
    """
    Simulate β_c of ``model`` at ``p`` on the measured pitch; return it over the window.

    The simulation starts at the record's first sample (:func:`model_start`), so a window
    that starts before the rotor has settled is simulated alike. With ``index`` also
    ∂β_c/∂p_i (T, k).
    """
    p = np.asarray(p, dtype=float)
    x0 = model_start(model, p, sweep, collective)
    names = list(model.state_names)
    iI, iII = names.index('beta_I'), names.index('beta_II')
    index = list(index)
    jac = _start_jacobian(model, p, sweep, collective, index) if index else None
    t = sweep.record_t[:sweep.start + sweep.t.size]
    sim = simulate(model, p, sweep.inputs, t, x0, param_index=index, x0_jacobian=jac)
    part = slice(sweep.start, None)
    flap = sim.x[part, iI] + 1j * sim.x[part, iII]
    if not index:
        return flap, None
    # (simulated with sensitivities to index: dx is an array)
    return flap, sim.dx[part, iI, :] + 1j * sim.dx[part, iII, :]  # type: ignore[index]


def estimated_model_response(model: 'RotorModel', p: npt.ArrayLike, sweeps: Sequence[Sweep],
                             spectra: Spectra, collective: float, index: Sequence[int] = ()
                             ) -> tuple[np.ndarray, np.ndarray | None]:
    """Return the model's dFRF as the estimator sees it on these sweeps (and ∂/∂p_i)."""
    flaps, sens = [], []
    for sweep in sweeps:
        flap, dflap = model_flap(model, p, sweep, collective, index)
        flaps.append(flap)
        sens.append(dflap)
    response = spectra.of(flaps)
    # (with index, every sweep's sensitivities are arrays)
    return response, (spectra.of(sens) if index else None)  # type: ignore[arg-type]


# ------------------------------------------------------------------------------ the fit
@dataclass
class FrequencyFit:
    """A frequency-domain estimate: values, covariance, J, and the points it used."""

    names: list
    values: np.ndarray
    covariance: np.ndarray
    cost: float
    iterations: int
    converged: bool
    message: str
    points: int
    model_response: np.ndarray
    chi2_per_dof: float


def _residuals(measured, model, weights):
    mag, phase = response_errors(measured, model)
    return np.concatenate([weights[0] * mag, weights[1] * phase])


def fit_frequency_response(model: 'RotorModel', sweeps: Sequence[Sweep],
                           estimate: FrequencyResponse, unknowns: Sequence[str],
                           guess: ParameterValues, known: ParameterValues,
                           collective: float, coherence_min: float = COHERENCE_MIN,
                           max_iter: int = 40, step_tol: float = 1e-6,
                           progress: Progress | None = None
                           ) -> 'FrequencyFit':
    """
    Fit ``unknowns`` by minimising CIFER's J between the estimate and the model's estimate.

    The model side is the same estimator applied to the model's simulated flap on the
    measured pitch (:func:`estimated_model_response`), so the end of a stirring cut off by the
    record and the periodic terms of a μ > 0 model are in both sides alike. Points: γ² ≥
    ``coherence_min`` (independent for white noise: one frequency each). Bounds: the
    linearised covariance of the J minimiser with each point's magnitude and phase error
    ε_r (dB: 8.69 ε_r, deg: 57.3 ε_r), inflated by the residual χ²/dof when it exceeds 1.
    """
    p = model.parameter_vector({**known, **guess})
    index = [model.parameter_names.index(n) for n in unknowns]
    usable = np.flatnonzero(estimate.usable(coherence_min))
    chosen = usable
    if chosen.size * 2 < len(unknowns) + 1:
        raise IdentificationError(
            f'only {chosen.size} independent frequencies have coherence ≥ {coherence_min:g}: '
            f'too few to fit {len(unknowns)} parameters in the frequency domain; record a '
            'longer or slower stirring sweep, or use --method output-error')
    measured = estimate.response[chosen]
    gamma2 = estimate.coherence[chosen]
    w_gamma = coherence_weight(gamma2)
    weights = (np.sqrt(w_gamma * MAGNITUDE_WEIGHT), np.sqrt(w_gamma * PHASE_WEIGHT))
    scale = 20.0 / chosen.size
    sub = estimate.spectra.restricted(chosen)
    lower = np.array([model.parameter(n).lower for n in unknowns])
    upper = np.array([model.parameter(n).upper for n in unknowns])
    started = time.perf_counter()

    def evaluate(values, jacobian):
        q = p.copy()
        q[index] = values
        response, sens = estimated_model_response(model, q, sweeps, sub, collective,
                                                  index if jacobian else ())
        r = _residuals(measured, response, weights)
        if not jacobian:
            return r, response, None
        rel = sens / response[:, None]
        A = np.concatenate([weights[0][:, None] * DB * rel.real,
                            weights[1][:, None] * DEG * rel.imag])
        return r, response, A

    theta = p[index].copy()
    lm, converged, message, iteration = 1e-3, False, 'iteration limit reached', 0
    r, response, A = evaluate(theta, True)
    cost = scale * float(r @ r)
    for iteration in range(1, max_iter + 1):
        N = A.T @ A
        g = A.T @ r
        while True:
            step_vec = -np.linalg.solve(N + lm * np.diag(np.diag(N) + 1e-300), g)
            trial = np.clip(theta + step_vec, lower, upper)
            r_t, resp_t, _ = evaluate(trial, False)
            cost_t = scale * float(r_t @ r_t)
            if cost_t <= cost or lm > 1e8:
                break
            lm *= 10.0
        if cost_t > cost:
            message = 'no further decrease of J'
            converged = True
            break
        moved = trial - theta
        theta = trial
        lm = max(lm / 10.0, 1e-9)
        r, response, A = evaluate(theta, True)
        cost = scale * float(r @ r)
        if progress is not None:
            progress({'iteration': iteration, 'rms': math.sqrt(cost / 20.0),
                      'names': list(unknowns), 'values': theta.tolist(),
                      'elapsed': time.perf_counter() - started, 'label': 'frequency-response J'})
        try:
            spread = np.sqrt(np.clip(np.diag(np.linalg.inv(A.T @ A)), 0.0, None))
        except np.linalg.LinAlgError:
            spread = np.full(theta.size, np.inf)
        if np.all(np.abs(moved) <= step_tol * np.maximum(spread * math.sqrt(cost), 1e-12)
                  + 1e-12 * np.abs(theta)):
            converged, message = True, 'converged'
            break
    covariance, chi2 = _covariance(A, weights, estimate.random_error[chosen], r)
    return FrequencyFit(names=list(unknowns), values=theta, covariance=covariance, cost=cost,
                        iterations=iteration, converged=converged, message=message,
                        points=int(chosen.size), model_response=response,
                        chi2_per_dof=chi2)


def _covariance(A, weights, eps, r):
    """Sandwich covariance of the weighted least-squares minimiser, scaled by χ²/dof ≥ 1."""
    eps = np.maximum(eps, 1e-9)
    sigma = np.concatenate([weights[0] * DB * eps, weights[1] * DEG * eps])   # of each residual
    N = A.T @ A
    try:
        Ninv = np.linalg.inv(N)
    except np.linalg.LinAlgError:
        k = A.shape[1]
        return np.full((k, k), np.nan), float('nan')
    meat = (A * (sigma ** 2)[:, None]).T @ A
    covariance = Ninv @ meat @ Ninv
    dof = max(r.size - A.shape[1], 1)
    chi2 = float(np.sum((r / sigma) ** 2) / dof)
    return covariance * max(1.0, chi2), chi2


def as_estimate(fit: 'FrequencyFit', time_domain: Estimate, method: str = 'frequency-response'
                ) -> Estimate:
    """
    Return an output-error :class:`Estimate` carrying the frequency-domain values and bounds.

    ``time_domain`` is the output-error evaluation at the frequency-domain values (no
    iteration): its residuals, fitted outputs and noise verify the estimate in the time domain.
    """
    names = list(time_domain.names)
    values = np.array(time_domain.values, dtype=float)
    covariance = np.zeros((len(names), len(names)))
    where = [names.index(n) for n in fit.names]
    values[where] = fit.values
    covariance[np.ix_(where, where)] = fit.covariance
    rest = [i for i in range(len(names)) if i not in where]
    td_cov = np.asarray(time_domain.covariance)
    covariance[np.ix_(rest, rest)] = td_cov[np.ix_(rest, rest)]
    with np.errstate(divide='ignore', invalid='ignore'):
        information = np.linalg.pinv(covariance)
    # the time-domain evaluation stopped on purpose (no iteration): its stop warnings do not
    # apply; the frequency-domain fit says how its parameters are determined
    warnings, _ = dependence_warnings(list(fit.names), np.linalg.pinv(fit.covariance))
    spread = np.sqrt(np.clip(np.diag(fit.covariance), 0.0, None))
    for name, value, sigma in zip(fit.names, fit.values, spread):
        if sigma > abs(value):
            warnings.append(f'{name}: the frequency response holds almost no information on it '
                            f'(σ = {sigma:.3g} for {value:.4g}); identify it by output error '
                            'or hold it known')
    est = Estimate(names=names, values=values, covariance=covariance, information=information,
                   noise_std=time_domain.noise_std, channel_names=time_domain.channel_names,
                   cost=fit.cost, neg_log_likelihood=time_domain.neg_log_likelihood,
                   iterations=fit.iterations, converged=fit.converged, message=fit.message,
                   n_samples=time_domain.n_samples, residuals=time_domain.residuals,
                   fitted=time_domain.fitted, initial_states=time_domain.initial_states,
                   warnings=warnings, method=method,
                   model_parameters=time_domain.model_parameters,
                   run_noise_std=time_domain.run_noise_std)
    return est
