"""
A rotor model's F and g over a long record from one revolution of samples.

Every coefficient of a rotor model is a function of the azimuth ψ = t (nondimensional time)
alone, of period 2π, and a trigonometric polynomial in it: the blade aerodynamics are
polynomials in μ sin ψ and cos ψ, the multiblade transforms first harmonics of the blade
azimuths, and every layer of :mod:`rotor_id.physics.augmented` turns, shifts or adds such
blocks. The forcing is affine in the inputs, g = b(ψ) + Σ_j B_j(ψ) u_j. So F, b and each B_j
(and their parameter derivatives) sampled at R points of one revolution are, by their
discrete Fourier series, the functions themselves at every ψ, as long as their highest
harmonic is below R/2. Evaluating the model on R·(1 + inputs) points and summing a few
harmonics over the record replaces evaluating it at every stage time of the record, which
for a periodic model of a one-second record is most of a fit's cost. :func:`series_at` is
the summation, also used for the filter's per-interval matrices
(:mod:`rotor_id.estimation.filter_error`).

The series is a shortcut, never a change of the answer: each evaluation is compared with the
model itself at a few of the record's own times and inputs, and where they differ by more than
rounding (a model not periodic in ψ, a forcing not affine in its inputs, a harmonic above the
samples) the model is evaluated directly, as it always could be.
"""

import numpy as np
import numpy.typing as npt

from rotor_id.physics.models import compact, LinearModel

#: samples per revolution of the probe that finds a model's highest harmonic
PROBE_SAMPLES = 64
#: a harmonic is present when its amplitude exceeds this fraction of the largest coefficient
#: (rounding of the probe's sums is ~1e-16 of it)
PRESENT = 1e-12
#: the series agrees with the model when they differ by no more than this fraction of the
#: largest entry (rounding of a sum of a few dozen terms; a missing harmonic is ~1e-3 or more)
AGREE = 1e-9
#: a harmonic below this fraction of every entry's largest coefficient is not summed (its
#: share of the value is below rounding)
NEGLIGIBLE = 1e-15
#: record times (spread over it, the last included) at which every evaluation is checked
#: against the model itself
CHECKED_TIMES = 4


def _samples(model: LinearModel) -> int | None:
    """Return the samples per revolution of the model's series (None: not probed, 0: none)."""
    return model.__dict__.get('_revolution_samples')


def series_at(values: np.ndarray, t0: float, t: np.ndarray,
              weights: np.ndarray | None = None) -> np.ndarray:
    """
    Values sampled at R equally spaced phases t0 + 2πr/R, summed as their Fourier series at t.

    ``values`` (R, …); returns (t.size, …). Exact for a trigonometric polynomial of degree
    below R/2 (the harmonics 0 … R/2 − 1 are summed; the Nyquist term is left out). Entries
    that are zero at every phase stay exactly zero, and harmonics below :data:`NEGLIGIBLE` of
    every entry's largest coefficient are not summed.

    ``weights`` (t.size, J): ``values`` (R, …, J) are J functions, and the result (t.size, …)
    is Σ_j values_j(t) weights_j(t) (an input matrix times the inputs), formed without the
    (t.size, …, J) array of the functions themselves.
    """
    samples = values.shape[0]
    t = np.asarray(t, dtype=float)
    n_weights = 1 if weights is None else weights.shape[1]
    shape = values.shape[1:] if weights is None else values.shape[1:-1]
    flat = values.reshape(samples, -1, n_weights)
    out = np.zeros((t.size, flat.shape[1]))
    varying = np.flatnonzero(np.any(flat != 0.0, axis=(0, 2)))
    if varying.size == 0:
        return out.reshape((t.size,) + shape)
    spectrum = np.fft.rfft(flat[:, varying], axis=0) / samples     # (R/2+1, columns, J)
    order = samples // 2 - 1
    size = np.abs(spectrum).max(axis=0)
    relative = np.abs(spectrum[:order + 1]) / np.where(size > 0.0, size, 1.0)
    present = np.flatnonzero(relative.reshape(order + 1, -1).max(axis=1) > NEGLIGIBLE)
    order = int(present[-1]) if present.size else 0
    rows = [spectrum[0].real]
    for h in range(1, order + 1):             # x = c0 + Σ 2 Re c_h cos hψ − 2 Im c_h sin hψ
        rows += [2.0 * spectrum[h].real, -2.0 * spectrum[h].imag]
    harmonic = np.multiply.outer(t - t0, np.arange(1, order + 1))
    basis = np.empty((t.size, 2 * order + 1))
    basis[:, 0] = 1.0
    basis[:, 1::2], basis[:, 2::2] = np.cos(harmonic), np.sin(harmonic)
    coefficients = np.moveaxis(np.array(rows), 2, 1)          # (harmonics, J, columns)
    if weights is not None:                                   # Σ_h Σ_j basis_h w_j c_hj
        basis = (basis[:, :, None] * weights[:, None, :]).reshape(t.size, -1)
    out[:, varying] = basis @ coefficients.reshape(-1, varying.size)
    return out.reshape((t.size,) + shape)


def agree(series: np.ndarray, exact: np.ndarray, tolerance: float = 1e-9) -> bool:
    """Tell whether a series is within ``tolerance`` of the exact values' largest entry."""
    scale = max(float(np.max(np.abs(exact), initial=0.0)), 1e-300)
    return bool(np.max(np.abs(series - exact), initial=0.0) <= tolerance * scale)


def _highest_harmonic(values: np.ndarray) -> int:
    """Highest harmonic present in R samples over one revolution."""
    samples = values.shape[0]
    spectrum = np.abs(np.fft.rfft(values.reshape(samples, -1), axis=0)).max(axis=1)
    present = np.flatnonzero(spectrum > PRESENT * max(spectrum.max(), 1e-300))
    return int(present[-1]) if present.size else 0


def _on_revolution(model, method, t0, samples, p, n_inputs):
    """
    Return the method on one revolution from t0: F, b and B, sampled (R, …) each.

    The model is evaluated once on the revolution repeated 1 + n_inputs times: at zero input
    and at each unit input; B_j is the difference (the forcing is affine in u).
    """
    psi = t0 + 2.0 * np.pi * np.arange(samples) / samples
    grid = np.tile(psi, n_inputs + 1)
    units = np.zeros((grid.size, n_inputs))
    for j in range(n_inputs):
        units[(j + 1) * samples:(j + 2) * samples, j] = 1.0
    F, g = compact(model, method, grid, p, units)
    F = F[:samples] if F.shape[0] > 1 else F
    g = g.reshape((n_inputs + 1, samples) + g.shape[1:])
    return F, g[0], np.moveaxis(g[1:] - g[0], 0, -1)       # B: (R, …, n_inputs)


def on_record(model: LinearModel, method: str, t: npt.ArrayLike, p: npt.ArrayLike,
              u: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """
    Return :func:`~rotor_id.physics.models.compact` (``model.system`` or ``system_jacobian``).

    From one revolution's samples where that pays (a long grid, a model that varies with ψ)
    and holds (the model itself agrees at the checked times); else the model evaluated on t.
    """
    t = np.atleast_1d(np.asarray(t, dtype=float))
    p, u = np.asarray(p, dtype=float), np.asarray(u, dtype=float)
    series = _series(model, method, t, p, u)
    return compact(model, method, t, p, u) if series is None else series


def _series(model, method, t, p, u):
    if getattr(model, 'time_invariant', True) or _samples(model) == 0:
        return None
    n_inputs = u.shape[1]
    samples = _samples(model) or PROBE_SAMPLES
    if t.size < 2 * samples * (n_inputs + 1):
        return None
    t0 = float(t[0])
    F_rev, b_rev, B_rev = _on_revolution(model, method, t0, samples, p, n_inputs)
    if _samples(model) is None:             # the probe: the fewest samples that resolve it
        order = max(_highest_harmonic(part) for part in (F_rev, b_rev, B_rev))
        if order >= samples // 2 - 1:
            model.__dict__['_revolution_samples'] = 0
            return None
        model.__dict__['_revolution_samples'] = 2 * order + 4
    if F_rev.shape[0] == 1:
        F = F_rev
    else:
        F = series_at(F_rev, t0, t)
    g = series_at(b_rev, t0, t) + series_at(B_rev, t0, t, weights=u)
    check = np.unique(np.linspace(0, t.size - 1, CHECKED_TIMES + 1).astype(int)[1:])
    F_at, g_at = compact(model, method, t[check], p, u[check])
    F_series = F if F.shape[0] == 1 else F[check]
    same = F_at.shape[0] == F_series.shape[0] and agree(F_series, F_at, AGREE) \
        and agree(g[check], g_at, AGREE)
    if not same:
        # fewer samples than the probe's: a harmonic the probe's parameters left out, probe
        # again at these; at the probe's own count the series does not hold for this model
        model.__dict__['_revolution_samples'] = None if samples < PROBE_SAMPLES else 0
        return None
    return F, g
