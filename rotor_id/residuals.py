"""
Residual analysis: where do the recording and the model disagree.

All tests compare the residuals with a **noise floor estimated without the model**: at 1 kHz
the flap signal is smooth from sample to sample, so the k-th differences of a measured flap
signal hold only its white measurement noise, with variance C(2k, k) σ² (k = 3 here; the
signal's third difference is ~1e-4 of the noise at Δt ≈ 0.1 rad). The floor of a model channel
y = C(t)·[β_1..β_N] follows as σ_y² = mean_t Σ_k C_jk(t)² σ_k².

Per channel: RMS against the floor, whiteness (Ljung-Box portmanteau over ``LAGS`` lags),
cross-correlation with the pitch input (θI, θII), the periodogram in per-rev frequency against
the floor's flat level, and the energy over one-revolution time windows. :func:`locate`
condenses these into the channels, the band (per rev) and the time span of the mismatch.
"""

from dataclasses import dataclass
import math
from typing import Any, Sequence

import numpy as np
import numpy.typing as npt

from rotor_id.estimation import validation
from rotor_id.estimation.validation import autocorrelation

#: Lags of the Ljung-Box whiteness test.
LAGS = 20
#: Family-wise whiteness level at which a filter's innovations count every sample.
WHITE_LEVEL = 0.05
#: Order of the differences used for the noise floor.
DIFF_ORDER = 3
#: Variance of the differencing filter's noise relative to its autocorrelation (for the floor's
#: own uncertainty): Σ_lag ρ² of the 3rd-difference filter [1, −3, 3, −1].
_DIFF_RHO2 = 1.0 + 2.0 * (0.75**2 + 0.3**2 + 0.05**2)


def blade_noise_floor(blade_flap: npt.ArrayLike, order: int = DIFF_ORDER) -> np.ndarray:
    """
    White-noise σ of each flap sensor from its k-th differences (T, N) → (N,).

    Outliers (a pitch step puts a kink into the flap) are trimmed at 5 robust σ first.
    """
    x = np.asarray(blade_flap, dtype=float)
    if x.shape[0] < order + 10:
        raise ValueError(f'{x.shape[0]} samples are too few to estimate the noise floor')
    d = np.diff(x, n=order, axis=0)
    scale = math.sqrt(math.comb(2 * order, order))
    robust = 1.4826 * np.median(np.abs(d - np.median(d, axis=0)), axis=0)
    sigma = np.empty(x.shape[1])
    for k in range(x.shape[1]):
        dk = d[:, k]
        keep = np.abs(dk) <= 5.0 * max(robust[k], 1e-300)
        sigma[k] = math.sqrt(np.mean(dk[keep]**2)) / scale
    return sigma


def channel_floor(C: npt.ArrayLike, blade_sigma: npt.ArrayLike) -> np.ndarray:
    """σ of each model channel from blade σ: √(mean_t Σ_k C_jk² σ_k²); C is (T, m, N)."""
    return np.sqrt(np.mean(np.einsum('tmk,k->tm', np.asarray(C)**2,
                                     np.asarray(blade_sigma)**2), axis=0))


def ljung_box(x: np.ndarray, lags: int = LAGS) -> tuple[float, float]:
    """Ljung-Box portmanteau test of whiteness of a residual series: (Q, p-value)."""
    n = len(x)
    lags = min(lags, n // 4)
    q, _, p = validation.ljung_box(autocorrelation(x, lags), n)
    return q, p


def effective_fraction(x: np.ndarray, max_lag: int = 200) -> float:
    """
    Return N_eff/N for the mean square of a correlated series.

    1/(1 + 2 Σ ρ_k), the sum taken over the initial positive run of ρ (Geyer); 1 for white
    residuals.
    """
    n = len(x)
    rho = autocorrelation(x, min(max_lag, n // 4))
    total = 0.0
    for r in rho:
        if r <= 0:
            break
        total += r
    return float(min(1.0, max(1.0 / (1.0 + 2.0 * total), 1.0 / 50.0)))


def channels_effective_fraction(residuals: npt.ArrayLike, innovations: bool = False,
                                white_level: float = WHITE_LEVEL) -> float:
    """
    N_eff/N of a likelihood gain over several channels (T, m): what a criterion counts.

    The smallest channel's :func:`effective_fraction`. For the ``innovations`` of a filter
    that models the process noise, whiteness is what the model predicts, and a channel that
    passes the Ljung-Box test at ``white_level``/m (Bonferroni over the m channels) counts
    every sample: without that gate the fraction of white innovations is biased low (the
    initial positive run stops at the first negative ρ_k and keeps sampling noise of one
    sign; the smallest of four white channels of 449 samples averages 0.85). Output-error
    residuals get no gate: weak correlation over many lags (unmodelled turbulence) can pass
    the test and still leave few effective samples.
    """
    res = np.asarray(residuals, dtype=float)
    m = res.shape[1]
    fractions = []
    for j in range(m):
        if innovations and ljung_box(res[:, j])[1] >= white_level / m:
            fractions.append(1.0)
        else:
            fractions.append(effective_fraction(res[:, j]))
    return min(fractions)


def periodogram(x: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Periodogram |X|²/N (white noise of variance σ² has mean level σ²); frequency per rev."""
    x = np.asarray(x, dtype=float) - np.mean(x)
    n = len(x)
    spec = np.abs(np.fft.rfft(x))**2 / n
    freq = np.fft.rfftfreq(n, d=dt) * 2.0 * math.pi        # cycles per rad × 2π = per rev
    return freq, spec


def windowed_energy(x: npt.ArrayLike, t: npt.ArrayLike, window: float = 2.0 * math.pi
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Mean square of x over consecutive windows of ``window`` (rad): (centres, ms)."""
    t = np.asarray(t, dtype=float)
    edges = np.arange(t[0], t[-1] + window, window)
    centres, ms = [], []
    for a, b in zip(edges[:-1], edges[1:]):
        sel = (t >= a) & (t < b)
        if np.count_nonzero(sel) >= 3:
            centres.append(0.5 * (a + b))
            ms.append(float(np.mean(np.asarray(x)[sel]**2)))
    return np.array(centres), np.array(ms)


def input_cross_correlation(x: np.ndarray, u: np.ndarray, max_lag: int
                            ) -> tuple[float, int, str]:
    """Largest |normalised cross-correlation| of x with θI and θII over ±max_lag samples."""
    x = np.asarray(x, dtype=float) - np.mean(x)
    best, best_lag, best_input = 0.0, 0, ''
    for j, name in ((1, 'theta_I'), (2, 'theta_II')):
        v = np.asarray(u[:, j], dtype=float) - np.mean(u[:, j])
        denom = math.sqrt(float(np.dot(x, x)) * float(np.dot(v, v)))
        if denom <= 0:
            continue
        for lag in range(-max_lag, max_lag + 1):
            if lag >= 0:
                r = np.dot(x[lag:], v[:len(v) - lag]) / denom
            else:
                r = np.dot(x[:lag], v[-lag:]) / denom
            if abs(r) > abs(best):
                best, best_lag, best_input = float(r), lag, name
    return best, best_lag, best_input


@dataclass
class ChannelStats:
    """Residual statistics of one channel."""

    name: str
    rms: float
    floor: float
    excess: float             # rms / floor − 1
    z_excess: float           # (rms²/floor² − 1) in standard errors
    whiteness_q: float
    whiteness_p: float
    n_eff_fraction: float
    xcorr: float
    xcorr_lag: int
    xcorr_input: str
    xcorr_threshold: float

    def flagged(self, n_channels: int) -> bool:
        """Significant departure from white noise at the floor (Bonferroni over channels)."""
        return bool(self.whiteness_p * n_channels < 1e-3 or self.z_excess > 4.0)

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready."""
        return {k: (float(v) if isinstance(v, (float, np.floating)) else v)
                for k, v in self.__dict__.items()}


def channel_stats(name: str, res: npt.ArrayLike, floor: float, u: np.ndarray,
                  n_blades_in_floor: int, t: np.ndarray) -> ChannelStats:
    """All per-channel statistics of one residual series."""
    res = np.asarray(res, dtype=float)
    n = len(res)
    rms = float(math.sqrt(np.mean(res**2)))
    ratio = rms**2 / floor**2
    se = math.sqrt(2.0 / n + 2.0 * _DIFF_RHO2 / (n * max(n_blades_in_floor, 1)))
    q, p = ljung_box(res)
    dt = float(np.median(np.diff(t)))
    max_lag = max(1, int(round(2.0 * math.pi / dt)))
    r, lag, which = input_cross_correlation(res, u, max_lag)
    return ChannelStats(name=name, rms=rms, floor=float(floor), excess=rms / floor - 1.0,
                        z_excess=(ratio - 1.0) / se, whiteness_q=q, whiteness_p=p,
                        n_eff_fraction=effective_fraction(res), xcorr=r, xcorr_lag=lag,
                        xcorr_input=which, xcorr_threshold=4.0 / math.sqrt(n))


def combined_whiteness_p(stats_list: Sequence[ChannelStats]) -> float:
    """Bonferroni-combined whiteness p-value over channels."""
    if not stats_list:
        return 1.0
    return float(min(1.0, len(stats_list) * min(s.whiteness_p for s in stats_list)))


def _span(x, w, lo=0.05, hi=0.95):
    """Return the range of x holding the central part of the positive weights w."""
    w = np.clip(np.asarray(w, dtype=float), 0.0, None)
    if w.sum() <= 0:
        return None
    c = np.cumsum(w) / w.sum()
    return float(x[np.searchsorted(c, lo)]), float(x[min(np.searchsorted(c, hi), len(x) - 1)])


def band_of_excess(residuals: Sequence[np.ndarray], floors: Sequence[float], dt: float,
                   smooth: int = 31) -> tuple[float, float]:
    """
    Band (per rev) holding 5-95 % of the significant residual power above the floor.

    The periodogram over all channels, relative to each floor, is averaged over ``smooth``
    bins; only bins more than 3 standard errors above the floor's level count.
    """
    total: Any                          # the channels' summed ratios (None before the first)
    total, count = None, 0
    for res, floor in zip(residuals, floors):
        freq, spec = periodogram(res, dt)
        ratio = spec / floor**2
        total = ratio if total is None else total + ratio
        count += 1
    kernel = np.ones(smooth) / smooth
    mean_ratio = np.convolve(total / count, kernel, mode='same')
    threshold = 1.0 + 3.0 / math.sqrt(smooth * count)
    excess = np.where(mean_ratio > threshold, mean_ratio - 1.0, 0.0)
    span = _span(freq, excess)
    return span or (0.0, float(freq[-1]))


def span_of_excess(residuals: Sequence[np.ndarray], floors: Sequence[float], t: np.ndarray
                   ) -> tuple[float, float]:
    """
    Return the time span holding 5-95 % of the significant residual energy above the floor.

    Nondimensional; one-revolution windows, a window counts when 3 standard errors above.
    """
    total: Any                          # the channels' summed ratios (None before the first)
    total, count, centres, n_win = None, 0, None, 1
    dt = float(np.median(np.diff(t)))
    for res, floor in zip(residuals, floors):
        centres, ms = windowed_energy(res, t)
        ratio = ms / floor**2
        total = ratio if total is None else total + ratio
        count += 1
    n_win = max(3, int(round(2.0 * math.pi / dt)))
    mean_ratio = total / count
    threshold = 1.0 + 3.0 * math.sqrt(2.0 / (n_win * count))
    excess = np.where(mean_ratio > threshold, mean_ratio - 1.0, 0.0)
    span = _span(centres, excess)
    if span is None:
        return float(t[0]), float(t[-1])
    half = math.pi
    return max(float(t[0]), span[0] - half), min(float(t[-1]), span[1] + half)
