"""
Does the identified model explain the data? The residual check after every identification.

A maximum-likelihood fit with Cramér-Rao bounds is only right when its residuals are the
measurement noise it assumes (report Ch.1 "Validation"; MATLAB's ``resid``, SIDPAC's residual
checks). After each fit :func:`check` tests, for every run and output channel:

* **whiteness**: Ljung-Box Q over 20 lags (:func:`rotor_id.estimation.validation.ljung_box`
  via the diagnosis's channel statistics). Q is χ²(20) for white noise, but the residuals of a
  fit are white noise with the fitted directions (the output sensitivities to the parameters
  and initial states, all smooth) projected out, which leaves a small negative autocorrelation
  at every short lag: at 133 samples and 9 fitted values Q averages 25, not 20, and p < 0.00125
  comes 14 times too often. The null distribution is therefore that of the projected noise:
  :func:`whiteness_null` draws it through the fit's own sensitivities and matches a scaled
  a·χ²(b) to its mean and variance (Satterthwaite);
* **input correlation**: the largest |normalised cross-correlation| of the residual with the
  stirring inputs θI, θII over ± one revolution of lags; for a white residual each value is
  N(0, 1/N) whatever the input, so its p-value is the two-sided normal tail, Bonferroni over the
  lags and inputs tried;
* **zero mean**: z = mean·√N / s of the residual, N(0, 1) for zero-mean white residuals. A
  constant misfit in a channel the model cannot hold constant (per-blade calibration offsets in
  the eq.-30 differences, which the wake model can only half absorb by a wrong A) shows here
  first;
* **noise level** (output and equation error): the residual mean square against the model-free
  noise floor of the flap sensors (their third differences,
  :func:`rotor_id.residuals.blade_noise_floor`), one-sided z with the standard error
  of both mean squares. Filter error's residuals are innovations, whose variance legitimately
  exceeds the sensor noise (the state prediction's own uncertainty), so for it only the two
  tests above apply: innovations of an adequate model are white even when process noise colours
  output-error residuals.

The family of K tests is corrected by Bonferroni: a test fails when its p-value is below α/K,
so a recording the model explains raises the warning with probability at most α
(:data:`FAMILY_ALPHA`) whatever the correlation between the tests. The verdict is a value
(:class:`Verdict`); a misfit also says where it is (channels, band per rev, time span) and
suggests ``rotor-id diagnose``, which locates and explains it. The exit code of a converged fit
stays 0: the estimate is still the best the model can do, but its bounds no longer describe its
error.
"""

from dataclasses import dataclass, field
import enum
import math
from typing import Any, Sequence, TYPE_CHECKING

import numpy as np
from rotor_id import residuals as rs
from rotor_id.estimation.validation import chi2_sf, normal_sf

if TYPE_CHECKING:
    from rotor_id.estimation.output_error import Estimate, Experiment
    from rotor_id.physics.models import LinearModel

#: Family-wise false-alarm probability of the adequacy check on a recording the model explains.
FAMILY_ALPHA = 0.01
#: Fewest samples per channel the tests need (the noise floor and 20 Ljung-Box lags).
MIN_SAMPLES = 80
#: Draws of the projected noise that calibrate the whiteness test (:func:`whiteness_null`).
NULL_DRAWS = 300
WHITENESS = 'whiteness'
INPUT_CORRELATION = 'input_correlation'
ZERO_MEAN = 'zero_mean'
NOISE_LEVEL = 'noise_level'


class Verdict(enum.Enum):
    """Outcome of the adequacy check."""

    ADEQUATE = 'adequate'           # every test passed: the residuals are noise
    INADEQUATE = 'inadequate'       # at least one test failed at the family-wise level
    NOT_TESTED = 'not_tested'       # too few samples (the note says why)


@dataclass
class ResidualTest:
    """One test of one channel of one run."""

    test: str
    run: str
    channel: str
    statistic: float
    p_value: float
    detail: dict = field(default_factory=dict)

    def as_json(self, limit: float) -> dict[str, Any]:
        """JSON-ready, with whether it passed at the per-test level ``limit``."""
        return {'test': self.test, 'run': self.run, 'channel': self.channel,
                'statistic': float(self.statistic), 'p_value': float(self.p_value),
                'passed': bool(self.p_value >= limit),
                **{k: (float(v) if isinstance(v, (float, np.floating)) else v)
                   for k, v in self.detail.items()}}


@dataclass
class Adequacy:
    """The adequacy check of one identification (see the module docstring)."""

    verdict: Verdict
    family_alpha: float
    tests: list
    residuals: str                  # 'output error' | 'innovations'
    location: dict | None = None    # channels, tests, band_per_rev, window_s of the misfit
    note: str = ''
    timing: dict | None = None      # :func:`timing_sensitivity` (output and equation error)

    @property
    def per_test_alpha(self) -> float:
        """Bonferroni level of each test, α/K."""
        return self.family_alpha / max(len(self.tests), 1)

    @property
    def failed(self) -> list[ResidualTest]:
        """Return the tests below the per-test level."""
        return [t for t in self.tests if t.p_value < self.per_test_alpha]

    @property
    def adequate(self) -> bool:
        """Return True unless the check found a misfit (NOT_TESTED counts as adequate)."""
        return self.verdict is not Verdict.INADEQUATE

    def as_json(self) -> dict[str, Any]:
        """JSON-ready: the ``adequacy`` key of ``rotor-id identify --json``."""
        limit = self.per_test_alpha
        return {'verdict': self.verdict.value, 'family_alpha': self.family_alpha,
                'per_test_alpha': limit, 'n_tests': len(self.tests),
                'residuals': self.residuals,
                'tests': [t.as_json(limit) for t in self.tests],
                'misfit': self.location, 'note': self.note, 'timing': self.timing,
                'suggestion': ('rotor-id diagnose' if self.verdict is Verdict.INADEQUATE
                               else None)}

    def warning(self) -> str | None:
        """One-line warning for an inadequate or an unchecked fit, else None."""
        if self.verdict is Verdict.NOT_TESTED:
            # (too few samples: a misfit, a sensor fault included, would pass unnoticed)
            return (f'the fit\'s adequacy was not checked ({self.note.split(";")[0]}): a '
                    'misfit or a sensor fault would go unnoticed, and the σ assume the model '
                    f'and the sensors are right; lengthen window_s to at least {MIN_SAMPLES} '
                    'samples')
        if self.verdict is not Verdict.INADEQUATE:
            return None
        figures = '; '.join(_describe(t) for t in sorted(self.failed, key=lambda t: t.p_value)[:3])
        loc = self.location or {}
        where = (f'channel(s) {", ".join(loc.get("channels", []))}, '
                 f'{loc["band_per_rev"][0]:.2f}-{loc["band_per_rev"][1]:.2f} per rev, '
                 f'{loc["window_s"][0]:.3f}-{loc["window_s"][1]:.3f} s') if loc else 'unknown'
        return (f'the {self.residuals} residuals are not noise ({figures}; {len(self.failed)} '
                f'of {len(self.tests)} tests fail at the family-wise level '
                f'{self.family_alpha:g}): the model does not explain the data there ({where}), '
                'so the estimates may be biased and their σ too small; run `rotor-id diagnose` '
                'with the same bag and run description to locate and explain the misfit')


def _describe(test):
    if test.test == WHITENESS:
        return (f'{test.channel}: not white, Ljung-Box Q = {test.statistic:.1f}, '
                f'p = {test.p_value:.2g}')
    if test.test == ZERO_MEAN:
        return (f'{test.channel}: mean {test.detail.get("mean", float("nan")):.3g} rad, '
                f'z = {test.statistic:.1f}, p = {test.p_value:.2g}')
    if test.test == INPUT_CORRELATION:
        return (f'{test.channel}: correlated with {test.detail.get("input")}, '
                f'|ρ| = {test.statistic:.3f}, p = {test.p_value:.2g}')
    return (f'{test.channel}: residual RMS {test.detail.get("rms", float("nan")):.3g} rad vs '
            f'noise floor {test.detail.get("floor", float("nan")):.3g} rad '
            f'(z = {test.statistic:.1f}, p = {test.p_value:.2g})')


def channel_matrix(model: 'LinearModel', t: np.ndarray, n_blades: int) -> np.ndarray:
    """C (T, m, N): the model's output channels as linear combinations of the blade flaps."""
    t = np.asarray(t, dtype=float)
    columns = []
    for k in range(n_blades):
        unit = np.zeros((t.size, n_blades))
        unit[:, k] = 1.0
        columns.append(model.observe_blades(t, unit))
    return np.stack(columns, axis=-1)


@dataclass
class FittedDirections:
    """The output sensitivities of every fitted value at the estimate, per run and weighted."""

    names: list                 # the fitted values: unknowns and free initial states
    sensitivities: list         # per run, ∂ŷ/∂θ of shape (T, m, P)
    noise_std: list             # per run, σ of each channel (m,)
    weighted: np.ndarray        # all runs stacked, ∂ŷ/∂θ / σ of shape (Σ T·m, P)


def fitted_directions(estimate: 'Estimate', experiments: Sequence['Experiment']
                      ) -> FittedDirections | None:
    """
    Return the :class:`FittedDirections` of a fit, or None when they cannot be formed.

    A filter-error fit's noise parameters are not model parameters: then the unknowns and
    initial states it shares with output error are used.
    """
    from rotor_id.estimation.output_error import Problem, evaluate
    model = experiments[0].model
    values = dict(zip(estimate.names, estimate.values))
    unknowns = [n for n in estimate.names if n in model.parameter_names]
    try:
        problem = Problem(experiments, unknowns, None, dict(estimate.model_parameters))
        if any(n not in values for n in problem.names):
            return None
        theta = np.array([values[n] for n in problem.names], dtype=float)
        dys = [dy for _, dy, _ in evaluate(problem, theta, sensitivities=True)]
    except (ValueError, np.linalg.LinAlgError, FloatingPointError):
        return None
    sigmas = (estimate.run_noise_std if getattr(estimate, 'run_noise_std', None)
              else [estimate.noise_std] * len(experiments))
    sigmas = [np.broadcast_to(np.asarray(sigma, dtype=float), (dy.shape[1],))
              for dy, sigma in zip(dys, sigmas)]
    J = np.concatenate([(dy / sigma[None, :, None]).reshape(-1, dy.shape[-1])
                        for dy, sigma in zip(dys, sigmas)], axis=0)
    if not np.all(np.isfinite(J)):
        return None
    return FittedDirections(list(problem.names), dys, sigmas, J)


def timing_sensitivity(estimate: 'Estimate', experiments: Sequence['Experiment'],
                       directions: FittedDirections, sample_period_s: float
                       ) -> dict[str, Any] | None:
    """
    How far one sample of flap-sensor delay would move each unknown, in its own σ.

    A sensor read d late measures y(t − d) ≈ y(t) − d·ẏ(t). Over a short window the direction
    −ẏ lies almost in the span of the fitted directions (a delay is a phase lag, and so is a
    change of damping or inflow lag), so the fit absorbs the delay into the parameters and its
    residuals stay white: no residual test can see it. The least-squares projection of −ẏ on
    the fitted directions gives the shift of every fitted value per unit delay; per sample
    period and divided by the Cramér-Rao σ it says how much the estimate depends on the
    sensor timing being right. ``delay_score_z`` is the score (Lagrange-multiplier) test of a
    common delay, N(0, 1) when there is none: what the residuals do show of it.
    """
    unknowns = [n for n in directions.names if n in estimate.names
                and '(t0)' not in n and n in experiments[0].model.parameter_names]
    rates = [-np.gradient(np.asarray(fitted, dtype=float), np.asarray(exp.t, dtype=float),
                          axis=0) / sigma
             for fitted, exp, sigma in zip(estimate.fitted, experiments, directions.noise_std)]
    delay = np.concatenate([rate.reshape(-1) for rate in rates])
    residual = np.concatenate([(np.asarray(res, dtype=float) / sigma).reshape(-1)
                               for res, sigma in zip(estimate.residuals, directions.noise_std)])
    J = directions.weighted
    if delay.size != J.shape[0] or residual.size != J.shape[0]:
        return None
    coefficients, *_ = np.linalg.lstsq(J, delay, rcond=None)
    unseen = delay - J @ coefficients                  # the part of a delay the fit cannot take
    size = float(np.linalg.norm(unseen))
    dt = float(np.median(np.diff(experiments[0].t)))   # one sample, nondimensional time
    shifts = {}
    for name in unknowns:
        k = directions.names.index(name)
        std = float(estimate.std[list(estimate.names).index(name)])
        if std > 0:
            shifts[name] = float(coefficients[k] * dt / std)
    return {'sample_period_s': float(sample_period_s),
            'shift_sigma_per_sample': shifts,
            'delay_score_z': float(unseen @ residual / size) if size > 0 else 0.0}


def whiteness_null(estimate: 'Estimate', experiments: Sequence['Experiment'],
                   n_draws: int = NULL_DRAWS, seed: int = 0,
                   directions: FittedDirections | None = None
                   ) -> list[list[tuple[float, float] | None]] | None:
    """
    Null distribution of each channel's Ljung-Box Q for the residuals of this very fit.

    Under the model the residual is (I − P) e: the noise e (σ per channel) with the weighted
    projection P onto the output sensitivities ∂ŷ/∂θ of every fitted value (the unknowns and
    the free initial states) removed. ``n_draws`` such residuals are drawn, Q computed on each,
    and a·χ²(b) matched to Q's mean and variance.

    Returns
    -------
    list (per run) of list (per channel) of (a, b), or None when the sensitivities cannot be
    formed (e.g. a filter-error fit's noise parameters are not model parameters: then the
    unknowns and initial states it shares with output error are used).

    """
    directions = directions or fitted_directions(estimate, experiments)
    if directions is None:
        return None
    dys, J = directions.sensitivities, directions.weighted
    # orthonormal basis of the fitted directions from the small Gram matrix (einsum and a
    # k×k eigh: a threaded SVD of the tall J waits for its threads on a loaded machine)
    gram = np.einsum('ik,il->kl', J, J)
    eigval, eigvec = np.linalg.eigh(gram)
    keep = eigval > eigval[-1] * 1e-12 * J.shape[0]
    basis = np.einsum('ik,kl->il', J, eigvec[:, keep] / np.sqrt(eigval[keep]))
    rng = np.random.default_rng(seed)
    z = rng.standard_normal((J.shape[0], n_draws))
    # einsum, not BLAS: on a loaded machine a threaded GEMM this small waits for its threads
    # (bench/results/blas_threads.md)
    z -= np.einsum('ik,kj->ij', basis, np.einsum('ik,ij->kj', basis, z))
    out, start = [], 0
    for dy in dys:
        T, m = dy.shape[:2]
        run = z[start:start + T * m].reshape(T, m, n_draws)
        start += T * m
        run_out = []
        lags = min(rs.LAGS, T // 4)
        k = np.arange(1, lags + 1)
        size = 1 << (2 * T - 2).bit_length()   # a power of 2 ≥ 2T − 1: linear correlation
        for j in range(m):
            r = np.ascontiguousarray(run[:, j, :].T)
            r -= r.mean(axis=1, keepdims=True)
            spectrum = np.fft.rfft(r, n=size, axis=1)
            acov = np.fft.irfft(spectrum.real**2 + spectrum.imag**2, n=size, axis=1)
            rho = acov[:, 1:lags + 1] / acov[:, :1]     # validation.autocorrelation, all draws
            q = T * (T + 2) * np.sum(rho**2 / (T - k)[None, :], axis=1)
            mean, var = float(np.mean(q)), float(np.var(q, ddof=1))
            run_out.append((var / (2.0 * mean), 2.0 * mean**2 / var) if var > 0 else None)
        out.append(run_out)
    return out


def check(estimate: 'Estimate', experiments: Sequence['Experiment'],
          measured: Sequence[tuple[np.ndarray, np.ndarray]],
          family_alpha: float = FAMILY_ALPHA) -> Adequacy:
    """
    Test the residuals of an identification (see the module docstring).

    Parameters
    ----------
    estimate : Estimate
        The fit (its ``residuals``: output error for output/equation error, innovations for
        filter error, ``method`` says which).
    experiments : list of Experiment
        The runs it was fitted to (their inputs and times).
    measured : list of (blade_flap, time_s)
        Per experiment: the measured flap of every blade over its window, shape (T, N), for
        the model-free noise floor, and the seconds of its samples, to say where a misfit is.
    family_alpha : float
        Family-wise false-alarm probability.

    Returns
    -------
    Adequacy

    """
    innovations = estimate.method == 'filter-error'
    kind = 'innovations' if innovations else 'output error'
    n = min(len(r) for r in estimate.residuals) if estimate.residuals else 0
    if n < MIN_SAMPLES:
        return Adequacy(Verdict.NOT_TESTED, family_alpha, [], kind,
                        note=f'{n} samples per channel: the residual tests need at least '
                             f'{MIN_SAMPLES}; the fit was not checked')
    tests, series = [], {}
    floors_of = {}
    directions = fitted_directions(estimate, experiments)
    null = whiteness_null(estimate, experiments, directions=directions)
    timing = None
    if directions is not None and not innovations:
        timing = timing_sensitivity(estimate, experiments, directions,
                                    float(np.median(np.diff(measured[0][1]))))
    for r, exp in enumerate(experiments):
        blade_flap, time_s = measured[r]
        blade_flap = np.asarray(blade_flap, dtype=float)
        key = id(blade_flap)
        if key not in floors_of:
            floors_of[key] = rs.blade_noise_floor(blade_flap)
        blade_sigma = floors_of[key]
        res_run = np.asarray(estimate.residuals[r], dtype=float)
        t = np.asarray(exp.t, dtype=float)
        u = exp.inputs(t)
        C = channel_matrix(exp.model, t, blade_flap.shape[1])
        floors = rs.channel_floor(C, blade_sigma)
        used = np.count_nonzero(np.any(np.abs(C) > 0, axis=0), axis=-1)
        run = exp.name
        for j, name in enumerate(exp.model.output_names):
            res = res_run[:, j]
            label = name if len(experiments) == 1 else f'{name}[{run}]'
            floor = float(floors[j]) if not innovations else float(np.sqrt(np.mean(res**2)))
            stats = rs.channel_stats(label, res, floor, u, int(used[j]), t)
            series[label] = (res, floor, t, np.asarray(time_s, dtype=float))
            scale = null[r][j] if null is not None else None
            if scale is not None:
                a, b = scale
                p_white = float(chi2_sf(stats.whiteness_q / a, b))
                detail = {'lags': min(rs.LAGS, len(res) // 4), 'null_scale': a, 'null_dof': b}
            else:   # no sensitivities: the uncorrected χ²(L), which errs towards alarms
                p_white = stats.whiteness_p
                detail = {'lags': min(rs.LAGS, len(res) // 4)}
            tests.append(ResidualTest(WHITENESS, run, label, stats.whiteness_q, p_white,
                                      detail))
            lags = 2 * int(round(2.0 * math.pi / float(np.median(np.diff(t))))) + 1
            varying = sum(1 for i in (1, 2) if np.std(u[:, i]) > 1e-12)
            if varying:
                count = lags * varying
                p_x = min(1.0, count * 2.0 * normal_sf(abs(stats.xcorr) * math.sqrt(len(res))))
                tests.append(ResidualTest(INPUT_CORRELATION, run, label, abs(stats.xcorr), p_x,
                                          {'input': stats.xcorr_input,
                                           'lag_samples': int(stats.xcorr_lag),
                                           'correlations_tried': count}))
            z_mean = float(np.mean(res) * math.sqrt(len(res)) / max(np.std(res), 1e-300))
            tests.append(ResidualTest(ZERO_MEAN, run, label, z_mean,
                                      float(2.0 * normal_sf(abs(z_mean))),
                                      {'mean': float(np.mean(res))}))
            if not innovations:
                tests.append(ResidualTest(NOISE_LEVEL, run, label, stats.z_excess,
                                          float(normal_sf(stats.z_excess)),
                                          {'rms': stats.rms, 'floor': stats.floor,
                                           'excess': stats.excess}))
    result = Adequacy(Verdict.ADEQUATE, family_alpha, tests, kind, timing=timing)
    failed = result.failed
    if not failed:
        return result
    result.verdict = Verdict.INADEQUATE
    names = list(dict.fromkeys(t.channel for t in failed))
    # located on the run of the strongest failure (the runs' times differ)
    worst = min(failed, key=lambda t: t.p_value)
    use = [series[c] for c in names if failed and _run_of(failed, c) == worst.run]
    t, time_s = use[0][2], use[0][3]
    dt = float(np.median(np.diff(t)))
    band = rs.band_of_excess([s[0] for s in use], [s[1] for s in use], dt)
    t0, t1 = rs.span_of_excess([s[0] for s in use], [s[1] for s in use], t)
    window = [float(np.interp(t0, t, time_s)), float(np.interp(t1, t, time_s))]
    result.location = {'channels': names, 'tests': sorted({t.test for t in failed}),
                       'run': worst.run, 'band_per_rev': [float(band[0]), float(band[1])],
                       'window_s': window}
    return result


def _run_of(tests, channel):
    return next(t.run for t in tests if t.channel == channel)
