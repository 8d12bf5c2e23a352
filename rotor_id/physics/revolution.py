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

from dataclasses import dataclass

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


@dataclass(frozen=True)
class Series:
    """
    The Fourier series of the entries of a function of ψ that are non-zero at some phase.

    ``index``: those entries' flat positions in one value of ``shape``; ``coefficients``
    (2H+1, J, entries): the constant, then the cosine and sine of each harmonic 1 … H, for each
    of J weights (J = 1 without weights); the series are in ψ − ``t0``.
    """

    shape: tuple[int, ...]
    index: np.ndarray
    coefficients: np.ndarray
    t0: float

    @classmethod
    def of(cls, values: np.ndarray, t0: float, weighted: bool = False) -> 'Series':
        """
        Return the series of ``values`` sampled at R equally spaced phases t0 + 2πr/R.

        ``values`` (R, …), or (R, …, J) when ``weighted``. Exact for a trigonometric polynomial
        of degree below R/2 (the harmonics 0 … R/2 − 1; the Nyquist term is left out); the
        harmonics above the last one that reaches :data:`NEGLIGIBLE` of some entry's largest
        coefficient are left out.
        """
        samples = values.shape[0]
        n_weights = values.shape[-1] if weighted else 1
        shape = values.shape[1:-1] if weighted else values.shape[1:]
        flat = values.reshape(samples, -1, n_weights)
        index = np.flatnonzero(np.any(flat != 0.0, axis=(0, 2)))
        spectrum = np.fft.rfft(flat[:, index], axis=0) / samples    # (R/2+1, entries, J)
        order = samples // 2 - 1
        size = np.abs(spectrum).max(axis=0) if index.size else np.ones((0, n_weights))
        relative = np.abs(spectrum[:order + 1]) / np.where(size > 0.0, size, 1.0)
        present = np.flatnonzero(relative.reshape(order + 1, -1).max(axis=1, initial=0.0)
                                 > NEGLIGIBLE)
        order = int(present[-1]) if present.size else 0
        rows = [spectrum[0].real]
        for h in range(1, order + 1):         # x = c0 + Σ 2 Re c_h cos hψ − 2 Im c_h sin hψ
            rows += [2.0 * spectrum[h].real, -2.0 * spectrum[h].imag]
        return cls(tuple(shape), index, np.moveaxis(np.array(rows), 2, 1), float(t0))

    @property
    def constant(self) -> bool:
        """Tell whether the function does not vary with ψ (no harmonic, no weights)."""
        return self.coefficients.shape[0] == 1 and self.coefficients.shape[1] == 1

    def entries(self, t: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
        """
        Return the entries at the times t: (t.size, entries); (1, entries) if :attr:`constant`.

        ``weights`` (t.size, J) for a weighted series: Σ_j values_j(t) weights_j(t) (an input
        matrix times the inputs), formed without the (t.size, …, J) array of the functions.
        """
        harmonics, n_weights, n_entries = self.coefficients.shape
        if weights is None and self.constant:
            return self.coefficients[0].copy()
        basis = _basis(np.asarray(t, dtype=float), self.t0, harmonics, weights)
        return basis @ self.coefficients.reshape(harmonics * n_weights, n_entries)

    def values(self, t: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
        """Return the full values at the times t: (t.size, …) (entries that are zero stay zero)."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        out = np.zeros((t.size, int(np.prod(self.shape))))
        out[:, self.index] = self.entries(t, weights)
        return out.reshape((t.size,) + self.shape)


#: the last trigonometric bases (a simulation sums F, g and their derivatives on one grid):
#: [(t, t0, harmonics, weights, basis)], newest last
_bases: list[tuple] = []
BASES_KEPT = 8
#: grids shorter than this (the check times) are summed without keeping their basis
SAMPLES_KEPT = 64


def _basis(t, t0, harmonics, weights):
    """
    Return the (t.size, harmonics·J) basis of :meth:`Series.entries` (read only).

    1, cos hψ, sin hψ (h = 1 … harmonics//2, ψ = t − t0), each times every weight w_j(t)
    (Σ_h Σ_j basis_h w_j c_hj); the last few are kept, found by their t and weights' values.
    """
    for kept_t, kept_t0, kept_h, kept_w, basis in _bases:
        if kept_t0 == t0 and kept_h == harmonics and kept_t.shape == t.shape \
                and np.array_equal(kept_t, t) and (
                    kept_w is None if weights is None else
                    kept_w is not None and kept_w.shape == weights.shape
                    and np.array_equal(kept_w, weights)):
            return basis
    angle = np.multiply.outer(t - t0, np.arange(1, harmonics // 2 + 1))
    basis = np.empty((t.size, harmonics))
    basis[:, 0] = 1.0
    basis[:, 1::2], basis[:, 2::2] = np.cos(angle), np.sin(angle)
    if weights is not None:
        basis = (basis[:, :, None] * weights[:, None, :]).reshape(t.size, -1)
    if t.size >= SAMPLES_KEPT:
        basis.flags.writeable = False
        _bases.append((t.copy(), t0, harmonics, None if weights is None else weights.copy(),
                       basis))
        del _bases[:-BASES_KEPT]
    return basis


def series_at(values: np.ndarray, t0: float, t: np.ndarray,
              weights: np.ndarray | None = None) -> np.ndarray:
    """
    Values sampled at R equally spaced phases t0 + 2πr/R, summed as their Fourier series at t.

    ``values`` (R, …); returns (t.size, …): :meth:`Series.values` of :meth:`Series.of`.
    ``weights`` (t.size, J): ``values`` (R, …, J) are J functions, and the result is
    Σ_j values_j(t) weights_j(t).
    """
    return Series.of(values, t0, weights is not None).values(t, weights)


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


def _on_revolution(model, method, t0, samples, p, n_inputs, also_t, also_u):
    """
    Return the method on one revolution from t0: F, b and B, sampled (R, …) each; then F, g.

    The model is evaluated once on the revolution repeated 1 + n_inputs times: at zero input
    and at each unit input; B_j is the difference (the forcing is affine in u). In the same
    call it is evaluated at the times ``also_t`` and inputs ``also_u`` (possibly none), whose F
    and g are returned after B (F of length 1 where the model gives it constant).
    """
    psi = t0 + 2.0 * np.pi * np.arange(samples) / samples
    grid = np.tile(psi, n_inputs + 1)
    units = np.zeros((grid.size, n_inputs))
    for j in range(n_inputs):
        units[(j + 1) * samples:(j + 2) * samples, j] = 1.0
    n_rev = grid.size
    grid, units = np.concatenate([grid, also_t]), np.concatenate([units, also_u])
    F, g = compact(model, method, grid, p, units)
    F_also = F if F.shape[0] == 1 else F[n_rev:]
    g_also = g[n_rev:]
    F = F[:samples] if F.shape[0] > 1 else F
    g = g[:n_rev].reshape((n_inputs + 1, samples) + g.shape[1:])
    return F, g[0], np.moveaxis(g[1:] - g[0], 0, -1), F_also, g_also   # B: (R, …, n_inputs)


def on_record(model: LinearModel, method: str, t: npt.ArrayLike, p: npt.ArrayLike,
              u: npt.ArrayLike, columns: list[int] | None = None
              ) -> tuple[np.ndarray, np.ndarray]:
    """
    Return :func:`~rotor_id.physics.models.compact` (``model.system`` or ``system_jacobian``).

    From one revolution's samples where that pays (a long grid, a model that varies with ψ)
    and holds (the model itself agrees at the checked times); else the model evaluated on t.
    ``columns``: the parameters of ``system_jacobian`` wanted (all when None).
    """
    t = np.atleast_1d(np.asarray(t, dtype=float))
    F, g = system_on_record(model, method, t, p, u, columns)
    return values_on(F, t), g


def values_on(F: 'Series | np.ndarray', t: np.ndarray) -> np.ndarray:
    """Return :func:`system_on_record`'s F on its own times t: the series summed, or the array."""
    return F if isinstance(F, np.ndarray) else F.values(t)


def entries_on_record(model: LinearModel, method: str, t: npt.ArrayLike, p: npt.ArrayLike,
                      u: npt.ArrayLike, columns: list[int] | None = None
                      ) -> tuple[tuple[np.ndarray, tuple[np.ndarray, ...]], np.ndarray]:
    """
    :func:`on_record` with F (∂F/∂p) as its non-zero entries, as :func:`nonzero_entries` gives.

    The entries come straight from the series where it holds, without the (T, …) array of F.
    """
    t = np.atleast_1d(np.asarray(t, dtype=float))
    F, g = system_on_record(model, method, t, p, u, columns)
    if isinstance(F, np.ndarray):
        return nonzero_entries(F), g
    index = tuple(i.astype(np.int64) for i in np.unravel_index(F.index, F.shape))
    return (np.ascontiguousarray(F.entries(t)), index), g


#: the last results of :func:`system_on_record`, newest last: [(model, method, columns, p, t,
#: u, (F, g))]. A fit asks for the same ones again (its initial states are fitted by one
#: simulation and its residuals and sensitivities come from the next, at the same parameters;
#: the screening's score test repeats the evaluation its fit starts from): a third of a
#: diagnosis's calls. The model is held, so another never takes its place; the arrays are
#: returned as they are, which no caller writes into (the compiled kernels read them).
_results: list[tuple] = []
RESULTS_KEPT = 6
#: ... each where its forcing array is at most this large (a short record's; a long record's
#: chunk of sensitivities is not held)
RESULT_BYTES_KEPT = 8 * 2**20


def system_on_record(model: LinearModel, method: str, t: np.ndarray, p: npt.ArrayLike,
                     u: npt.ArrayLike, columns: list[int] | None = None
                     ) -> tuple['Series | np.ndarray', np.ndarray]:
    """
    Return :func:`on_record`'s F as its :class:`Series` where that holds (else an array), and g.

    The series gives F at any other time too (``F.values(times)``), as the model would, to the
    rounding :func:`on_record` checks.
    """
    p, u = np.asarray(p, dtype=float), np.asarray(u, dtype=float)
    wanted = None if columns is None else [int(c) for c in columns]
    for kept_model, kept_method, kept_columns, kept_p, kept_t, kept_u, result in _results:
        if kept_model is model and kept_method == method and kept_columns == wanted \
                and kept_t.shape == t.shape and kept_u.shape == u.shape \
                and np.array_equal(kept_p, p) and np.array_equal(kept_t, t) \
                and np.array_equal(kept_u, u):
            return result
    series = _series(model, method, t, p, u, columns)
    if series is not None:
        F, b, B = series
        result = F, b.values(t) + B.values(t, u)
    else:
        F, g = compact(model, method, t, p, u)
        result = (F, g) if columns is None else (F[:, columns], g[:, columns])
    if result[1].nbytes <= RESULT_BYTES_KEPT:
        _results.append((model, method, wanted, p.copy(), t.copy(), u.copy(), result))
        del _results[:-RESULTS_KEPT]
    return result


def nonzero_entries(A: np.ndarray) -> tuple[np.ndarray, tuple[np.ndarray, ...]]:
    """
    Entries of the stacked arrays A (T, ...) that are non-zero at any t: (values, indices).

    values (T, nnz), or (1, nnz) when they are the same at every t; indices one int64 array
    per axis of A[0], as np.nonzero gives them.
    """
    index = np.nonzero(A[0] if A.shape[0] == 1 else np.any(A != 0.0, axis=0))
    values = A[(slice(None),) + index]
    if values.shape[0] > 1 and np.all(values == values[:1]):
        values = values[:1]
    return (np.ascontiguousarray(values, dtype=float),
            tuple(i.astype(np.int64) for i in index))


def _series(model, method, t, p, u, columns):
    """
    F, b and B of the method as series, checked at the record's times; or None.

    F is the revolution's (1, …) array where the model gives it constant; ``columns`` selects
    the parameters of ``system_jacobian``.
    """
    if getattr(model, 'time_invariant', True) or _samples(model) == 0:
        return None
    n_inputs = u.shape[1]
    samples = _samples(model) or PROBE_SAMPLES
    if t.size < 2 * samples * (n_inputs + 1):
        return None
    t0 = float(t[0])
    # the series is checked against the model at these record times, evaluated in the same call
    check = np.unique(np.linspace(0, t.size - 1, CHECKED_TIMES + 1).astype(int)[1:])
    probing = _samples(model) is None
    if probing:                             # the probe: the fewest samples that resolve it
        F_rev, b_rev, B_rev, _, _ = _on_revolution(model, method, t0, samples, p, n_inputs,
                                                   t[:0], u[:0])
        order = max(_highest_harmonic(part) for part in (F_rev, b_rev, B_rev))
        if order >= samples // 2 - 1:
            model.__dict__['_revolution_samples'] = 0
            return None
        samples = model.__dict__['_revolution_samples'] = 2 * order + 4
        # summed from those samples, as every later call is: a model's values do not depend
        # on which call probed it (the two sums differ by rounding)
    F_rev, b_rev, B_rev, F_at, g_at = _on_revolution(model, method, t0, samples, p, n_inputs,
                                                     t[check], u[check])
    if columns is not None:
        F_rev, b_rev, B_rev = F_rev[:, columns], b_rev[:, columns], B_rev[:, columns]
    F = F_rev if F_rev.shape[0] == 1 else Series.of(F_rev, t0)
    b, B = Series.of(b_rev, t0), Series.of(B_rev, t0, weighted=True)
    if columns is not None:
        F_at, g_at = F_at[:, columns], g_at[:, columns]
    F_series = F if isinstance(F, np.ndarray) else F.values(t[check])
    g_series = b.values(t[check]) + B.values(t[check], u[check])
    same = F_at.shape[0] == F_series.shape[0] and agree(F_series, F_at, AGREE) \
        and agree(g_series, g_at, AGREE)
    if not same:
        # a later call: a harmonic the probe's parameters left out, probe again at these; the
        # probing call itself (every harmonic its samples resolve summed): the series does not
        # hold for this model
        model.__dict__['_revolution_samples'] = 0 if probing else None
        return None
    return F, b, B
