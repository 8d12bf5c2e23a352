"""
Validation of an identified model: prediction error, residual whiteness, input correlation.

For each run and output channel (:class:`ChannelValidation`):

* **prediction RMS** of the residual ε = y − ŷ, on the identification data (ŷ = the fit) and on
  held-out runs (ŷ simulated at the estimated parameters from the new run's initial state,
  fitted by linear least squares with the parameters held: y is linear in x(t0));
* **Theil inequality coefficient** U = rms(ε) / (rms(y) + rms(ŷ)), 0 for a perfect prediction,
  1 for no skill (ŷ = 0 or ŷ = −y);
* **whiteness**: the normalised autocorrelation r_k of ε for lags 1…L with the ±1.96/√N band
  of a white sequence, and the Ljung-Box portmanteau statistic
  Q = N(N+2) Σ_{k=1..L} r_k²/(N−k), χ²(L) under whiteness (p-value: the χ² upper tail);
* **cross-correlation with the input**: normalised correlation of ε with each varying input
  channel (θI, θII) at lags −L…L, with the same ±1.96/√N band. A model that explains the
  input-driven response leaves none.

Output error assumes white measurement noise (report Ch.2 eq. 14 ff.): coloured residuals or
residuals correlated with the input mean the model misses something (wrong structure,
periodic terms, wake, sensor lag) even when the fit looks good.
"""

from dataclasses import dataclass, field, replace
import math
from typing import Any, Sequence, TYPE_CHECKING

import numpy as np
import numpy.typing as npt
from rotor_id.estimation.output_error import evaluate, fit_initial_states, Problem
from rotor_id.estimation.simulate import DEFAULT_MAX_STEP
from rotor_id.physics.stirring import INPUT_NAMES

if TYPE_CHECKING:
    from rotor_id.estimation.output_error import Estimate, Experiment

#: Relative size of the last term (series) or correction (continued fraction) that ends the
#: evaluation of the incomplete gamma function Q(a, x).
_GAMMA_TOLERANCE = 1e-16
#: Iteration cap of that evaluation; both forms converge within ~√a + 10 steps at any x.
_GAMMA_MAX_TERMS = 10_000
#: Stand-in for a vanishing denominator of the modified Lentz recursion.
_LENTZ_TINY = 1e-300


def _gamma_q(a, x):
    """
    Regularized upper incomplete gamma function Q(a, x) = Γ(a, x)/Γ(a) for a > 0 (1 at x ≤ 0).

    The series of P = 1 − Q below x < a + 1 (Q is not small there), the continued fraction of
    Q above it (Q to its smallest values), each with the prefactor e^(−x) x^a / Γ(a) (Numerical
    Recipes 3rd ed. §6.2); relative error ~1e-13 up to x ~ 10³ against scipy.special.gammaincc.
    """
    if math.isnan(a) or math.isnan(x) or a <= 0.0:
        return math.nan
    if x <= 0.0 or math.isinf(a):
        return 1.0
    if math.isinf(x):
        return 0.0
    log_prefactor = -x + a * math.log(x) - math.lgamma(a)
    if x < a + 1.0:
        term = total = 1.0 / a
        denominator = a
        for _ in range(_GAMMA_MAX_TERMS):
            denominator += 1.0
            term *= x / denominator
            total += term
            if abs(term) < abs(total) * _GAMMA_TOLERANCE:
                break
        return max(0.0, 1.0 - total * math.exp(log_prefactor))
    b = x + 1.0 - a
    c = 1.0 / _LENTZ_TINY
    d = 1.0 / b
    h = d
    for i in range(1, _GAMMA_MAX_TERMS):
        an = -i * (i - a)
        b += 2.0
        d = an * d + b
        d = d if abs(d) >= _LENTZ_TINY else _LENTZ_TINY
        c = b + an / c
        c = c if abs(c) >= _LENTZ_TINY else _LENTZ_TINY
        d = 1.0 / d
        step = d * c
        h *= step
        if abs(step - 1.0) < _GAMMA_TOLERANCE:
            break
    return math.exp(log_prefactor) * h


# The χ² and normal tails are evaluated here, not by scipy: scipy.special alone is most of the
# import time of ``rotor-id identify``, whose adequacy check needs only these two tails
# (bench/results/startup.md); test/estimation/test_validation.py holds them to scipy.stats.
_chi2_tail = np.frompyfunc(lambda q, dof: _gamma_q(0.5 * dof, 0.5 * q), 2, 1)
_normal_tail = np.frompyfunc(lambda z: 0.5 * math.erfc(z / math.sqrt(2.0)), 1, 1)


def chi2_sf(q: npt.ArrayLike, dof: npt.ArrayLike) -> Any:
    """Return P(χ²(dof) > q), the upper tail of the χ² distribution (dof > 0, real)."""
    return _as_float(_chi2_tail(np.asarray(q, dtype=float), np.asarray(dof, dtype=float)))


def _higher_dof_tails(q, dof, count):
    """P(χ²(dof + 2j) > q) for j = 0 … count−1: Q(a+1, x) = Q(a, x) + xᵃ e⁻ˣ / Γ(a+1)."""
    a, x = 0.5 * dof, 0.5 * q
    steps = a + np.arange(count - 1)                     # a, a+1, …: the term of each step
    log_terms = steps * math.log(x) - x - np.array([math.lgamma(b + 1.0) for b in steps])
    tails = _gamma_q(a, x) + np.concatenate([[0.0], np.cumsum(np.exp(log_terms))])
    return np.minimum(tails, 1.0)


def _poisson_terms(mean):
    """Return terms of a Poisson mixture past which its weight is below 1e-30 (of any mean)."""
    return int(math.ceil(mean + 12.0 * math.sqrt(mean) + 30.0))


def _noncentral_tail(q, dof, largest):
    """
    Return the function λ ↦ P(χ²_dof(λ) > q) for 0 ≤ λ ≤ ``largest``.

    The Poisson(λ/2) mixture of the central tails with dof + 2j degrees of freedom (computed
    once), summed until the Poisson weight left is below 1e-30.
    """
    tails = _higher_dof_tails(q, dof, _poisson_terms(0.5 * largest))
    j = np.arange(tails.size)
    log_factorial = np.array([math.lgamma(i + 1.0) for i in j])

    def tail(noncentrality):
        if noncentrality <= 0.0:
            return float(tails[0])
        half = 0.5 * noncentrality
        weights = np.exp(-half + j * math.log(half) - log_factorial)
        return float(min(1.0, weights @ tails))
    return tail


def noncentral_chi2_sf(q: float, dof: float, noncentrality: float) -> float:
    """Return P(χ²_dof(λ) > q), the upper tail of the noncentral χ² distribution (q > 0)."""
    return _noncentral_tail(q, dof, max(noncentrality, 0.0))(noncentrality)


def noncentrality_for_power(q: float, dof: float, power: float) -> float:
    """
    Return λ with P(χ²_dof(λ) > q) = power: a test at the threshold q detects it with power.

    0 when the central tail already reaches ``power``. The tail rises with λ: λ is bracketed
    by doubling and bisected to 1e-12 of itself.
    """
    if chi2_sf(q, dof) >= power:
        return 0.0
    high = max(1.0, q)
    while noncentral_chi2_sf(q, dof, high) < power:
        high *= 2.0
    tail = _noncentral_tail(q, dof, high)
    return _bisect(lambda lam: tail(lam) < power, 0.0, high, 1e-12)


#: Directions of a scaled information matrix whose eigenvalue is below this fraction of the
#: largest carry no information: M = JᵀJ squares J's condition, and its small eigenvalues
#: are rounding of the large ones (relative accuracy ~ k·ε·cond) well before this.
INFORMATION_CUTOFF = 1e-10


def score_statistic(gradient: np.ndarray, information: np.ndarray
                    ) -> tuple[float, np.ndarray]:
    """
    Return Rao's score statistic LM = gᵀ M⁻¹ g and the diagonal of M⁻¹ (each parameter's variance).

    g and M are the gradient and the information of −log L at the restricted estimate: LM is
    χ²_k where the restriction holds. M is inverted on its informed directions (eigenvalues of
    M scaled to a unit diagonal above :data:`INFORMATION_CUTOFF` of the largest); a parameter
    along an uninformed one has no finite variance (inf), not the zero a truncated inverse
    would give it.
    """
    d = np.sqrt(np.maximum(np.diag(information), 1e-300))
    s, V = np.linalg.eigh(information / np.outer(d, d))
    kept = s > INFORMATION_CUTOFF * s.max()
    cov = (V[:, kept] / s[kept]) @ V[:, kept].T / np.outer(d, d)
    unseen = np.sum(V[:, ~kept]**2, axis=1) > 1e-6
    return float(gradient @ cov @ gradient), np.where(unseen, np.inf, np.diag(cov))


def _bisect(below, low, high, relative):
    """Return the root in [low, high] of a monotone test: ``below(x)`` while x is under it."""
    while high - low > relative * high:
        middle = 0.5 * (low + high)
        if below(middle):
            low = middle
        else:
            high = middle
    return 0.5 * (low + high)


def normal_sf(z: npt.ArrayLike) -> Any:
    """Return P(N(0, 1) > z), the upper tail of the standard normal."""
    return _as_float(_normal_tail(np.asarray(z, dtype=float)))


def _as_float(values):
    """Float array of a frompyfunc result, or a float for a scalar one."""
    return float(values) if np.ndim(values) == 0 else np.asarray(values, dtype=float)


def normal_isf(p: npt.ArrayLike) -> Any:
    """Return z with P(N(0, 1) > z) = p, the inverse upper tail of the standard normal."""
    from scipy.special import ndtri        # here, not at import: see chi2_sf
    return -ndtri(np.asarray(p, dtype=float))


def student_t_sf(t: float, dof: int) -> float:
    """
    Return P(T > t) for Student's t with an integer number of degrees of freedom.

    The finite series of Abramowitz & Stegun 26.7.3-4 in θ = atan(t/√ν): for odd ν,
    P(|T| < t) = (2/π)[θ + sin θ (cos θ + ⅔ cos³θ + … )], for even ν,
    P(|T| < t) = sin θ (1 + ½ cos²θ + ⅜ cos⁴θ + … ), each to the power ν − 2.
    """
    if dof < 1 or dof != int(dof):
        raise ValueError(f'degrees of freedom must be a positive integer, not {dof}')
    theta = math.atan(abs(t) / math.sqrt(dof))
    cos2 = math.cos(theta)**2
    if dof % 2:
        term, total = math.cos(theta), 0.0
        for j in range(1, (dof - 1) // 2 + 1):
            total += term
            term *= cos2 * 2 * j / (2 * j + 1)
        inside = 2.0 / math.pi * (theta + math.sin(theta) * total)
    else:
        term, total = 1.0, 0.0
        for j in range(1, dof // 2 + 1):
            total += term
            term *= cos2 * (2 * j - 1) / (2 * j)
        inside = math.sin(theta) * total
    tail = 0.5 * (1.0 - inside)
    return tail if t >= 0.0 else 1.0 - tail


def student_t_isf(p: float, dof: int) -> float:
    """Return t with P(T > t) = p for Student's t with integer ``dof`` (bisection, 1e-13)."""
    if not 0.0 < p < 1.0:
        raise ValueError(f'a tail probability lies strictly between 0 and 1, not {p}')
    if p > 0.5:
        return -student_t_isf(1.0 - p, dof)
    low, high = 0.0, 1.0
    while student_t_sf(high, dof) > p:
        low, high = high, 2.0 * high
    return _bisect(lambda t: student_t_sf(t, dof) > p, low, high, 1e-13)


#: Two-sided 95 % quantile of the standard normal: the band ±1.96/√N of a white sequence.
Z95 = 1.959963984540054


@dataclass
class ChannelValidation:
    """
    Residual statistics of one output channel of one run.

    Attributes
    ----------
    channel : str
    n_samples : int
    rms : float
        Root mean square of the residual (prediction error), in the output's unit.
    mean : float
        Mean residual.
    theil : float
        Theil inequality coefficient U (0 perfect, 1 no skill).
    lags : ndarray, shape (L,)
        1 … L.
    autocorrelation : ndarray, shape (L,)
        r_k of the residual.
    band : float
        1.96/√N.
    outside_band : float
        Fraction of lags with |r_k| > band (≈ 5 % for white residuals).
    ljung_box_q : float
    ljung_box_dof : int
    ljung_box_p : float
        Probability of a Q this large for white residuals.
    input_names : list of str
        Input channels correlated with the residual (those that vary in the run).
    cross_lags : ndarray, shape (2L+1,)
        −L … L (positive: residual lags the input).
    cross_correlation : ndarray, shape (len(input_names), 2L+1)
    max_cross_correlation : float
        Largest |cross-correlation| over inputs and lags.

    """

    channel: str
    n_samples: int
    rms: float
    mean: float
    theil: float
    lags: np.ndarray
    autocorrelation: np.ndarray
    band: float
    outside_band: float
    ljung_box_q: float
    ljung_box_dof: int
    ljung_box_p: float
    input_names: list = field(default_factory=list)
    cross_lags: np.ndarray | None = None
    cross_correlation: np.ndarray | None = None
    max_cross_correlation: float = float('nan')

    def white(self, alpha: float = 0.05) -> bool:
        """Whether the Ljung-Box test accepts whiteness at level ``alpha``."""
        return bool(self.ljung_box_p >= alpha)

    def cross_correlation_limit(self, alpha: float = 0.05) -> float:
        """
        Return the limit of |cross-correlation| for a residual independent of the input.

        With 2L+1 lags per input the ±1.96/√N band is widened to the two-sided
        ``alpha/((2L+1)·n_inputs)`` normal quantile (Bonferroni), so a white residual
        independent of the input stays inside with probability ≈ 1 − α.
        """
        count = max(1, 0 if self.cross_correlation is None else self.cross_correlation.size)
        return float(normal_isf(alpha / (2.0 * count)) / math.sqrt(self.n_samples))

    def uncorrelated_with_input(self, alpha: float = 0.05) -> bool:
        """Whether every input cross-correlation stays inside :meth:`cross_correlation_limit`."""
        if self.cross_correlation is None or self.cross_correlation.size == 0:
            return True
        return bool(self.max_cross_correlation <= self.cross_correlation_limit(alpha))

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready summary (without the full correlation functions)."""
        return {'channel': self.channel, 'n_samples': self.n_samples, 'rms': self.rms,
                'mean': self.mean, 'theil': self.theil, 'band': self.band,
                'outside_band': self.outside_band, 'ljung_box_q': self.ljung_box_q,
                'ljung_box_dof': self.ljung_box_dof, 'ljung_box_p': self.ljung_box_p,
                'max_cross_correlation': self.max_cross_correlation,
                'cross_correlation_limit': self.cross_correlation_limit(),
                'white': self.white(), 'uncorrelated_with_input': self.uncorrelated_with_input()}


@dataclass
class RunValidation:
    """
    Validation of one run: the prediction and per-channel statistics.

    Attributes
    ----------
    name : str
    held_out : bool
        True when the run was not used for the estimate.
    t : ndarray, shape (T,)
    measured, predicted, residuals : ndarray, shape (T, m)
    initial_state : ndarray, shape (n,)
        x(t0) used for the prediction (fitted for held-out runs).
    channels : list of ChannelValidation

    """

    name: str
    held_out: bool
    t: np.ndarray
    measured: np.ndarray
    predicted: np.ndarray
    residuals: np.ndarray
    initial_state: np.ndarray
    channels: list

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready summary."""
        return {'name': self.name, 'held_out': self.held_out,
                'initial_state': [float(v) for v in self.initial_state],
                'channels': [c.as_dict() for c in self.channels]}


def autocorrelation(x: np.ndarray, max_lag: int) -> np.ndarray:
    """
    Normalised autocorrelation r_k = c_k / c_0 of a sequence for lags 1 … max_lag.

    c_k = (1/N) Σ_{t=k}^{N−1} (x_t − x̄)(x_{t−k} − x̄), the biased estimate Ljung-Box uses.
    """
    x = np.asarray(x, dtype=float) - np.mean(x)
    n = x.size
    c0 = float(np.dot(x, x)) / n
    if c0 == 0.0:
        return np.zeros(max_lag)
    return np.array([np.dot(x[k:], x[:n - k]) / n / c0 for k in range(1, max_lag + 1)])


def ljung_box(r: npt.ArrayLike, n: int) -> tuple[float, int, float]:
    """Ljung-Box Q = N(N+2) Σ r_k²/(N−k) for autocorrelations r_1…r_L, its dof L and p-value."""
    r = np.asarray(r, dtype=float)
    k = np.arange(1, r.size + 1)
    q = float(n * (n + 2) * np.sum(r**2 / (n - k)))
    return q, int(r.size), float(chi2_sf(q, r.size))


def cross_correlation(residual: np.ndarray, signal: np.ndarray, max_lag: int) -> np.ndarray:
    """
    Normalised cross-correlation ρ_k of residual ε and input u for lags k = −L … L.

    ρ_k = Σ_t (ε_t − ε̄)(u_{t−k} − ū) / (N s_ε s_u): k > 0 means ε lags u.
    """
    e = np.asarray(residual, dtype=float) - np.mean(residual)
    u = np.asarray(signal, dtype=float) - np.mean(signal)
    n = e.size
    scale = n * np.std(e) * np.std(u)
    out = np.zeros(2 * max_lag + 1)
    if scale == 0.0:
        return out
    for i, k in enumerate(range(-max_lag, max_lag + 1)):
        if k >= 0:
            out[i] = np.dot(e[k:], u[:n - k]) / scale
        else:
            out[i] = np.dot(e[:n + k], u[-k:]) / scale
    return out


def theil_inequality(measured: npt.ArrayLike, predicted: npt.ArrayLike) -> float:
    """Theil's U = rms(y − ŷ) / (rms(y) + rms(ŷ)); 0 for ŷ = y, 1 for ŷ = 0 or ŷ = −y."""
    y = np.asarray(measured, dtype=float)
    yh = np.asarray(predicted, dtype=float)
    den = math.sqrt(np.mean(y**2)) + math.sqrt(np.mean(yh**2))
    return float(math.sqrt(np.mean((y - yh)**2)) / den) if den > 0 else 0.0


def default_max_lag(n_samples: int) -> int:
    """Lags tested: min(20, N/4), at least 1 (Ljung-Box needs L well below N)."""
    return max(1, min(20, n_samples // 4))


def channel_statistics(measured: npt.ArrayLike, predicted: npt.ArrayLike, channel: str = 'y',
                       inputs: npt.ArrayLike | None = None,
                       input_names: Sequence[str] | None = None,
                       max_lag: int | None = None) -> 'ChannelValidation':
    """
    Residual statistics of one channel (see the module docstring).

    Parameters
    ----------
    measured : array_like, shape (N,)
        Measured output y.
    predicted : array_like, shape (N,)
        Model output ŷ.
    channel : str
        Channel name for reports.
    inputs : array_like, shape (N, q), optional
        Input channels to correlate with the residual; constant ones are skipped.
    input_names : sequence of str, optional
        Names of the input channels.
    max_lag : int, optional
        Largest lag L (default :func:`default_max_lag`).

    Returns
    -------
    ChannelValidation

    """
    y = np.asarray(measured, dtype=float)
    yh = np.asarray(predicted, dtype=float)
    if y.shape != yh.shape or y.ndim != 1:
        raise ValueError(f'measured and predicted must be 1-D of equal length, got {y.shape} '
                         f'and {yh.shape}')
    n = y.size
    if n < 8:
        raise ValueError(f'residual statistics need at least 8 samples, got {n}; '
                         'validate on a longer record')
    lag = default_max_lag(n) if max_lag is None else int(max_lag)
    if not 1 <= lag < n // 2:
        raise ValueError(f'max_lag must be between 1 and N/2 = {n // 2}, got {lag}')
    res = y - yh
    r = autocorrelation(res, lag)
    band = Z95 / math.sqrt(n)
    q, dof, p = ljung_box(r, n)
    names, cross = [], np.zeros((0, 2 * lag + 1))
    if inputs is not None:
        inputs = np.asarray(inputs, dtype=float)
        input_names = list(input_names or [f'u{i}' for i in range(inputs.shape[1])])
        keep = [i for i in range(inputs.shape[1]) if np.std(inputs[:, i]) > 1e-12]
        names = [input_names[i] for i in keep]
        cross = np.array([cross_correlation(res, inputs[:, i], lag) for i in keep]) \
            if keep else cross
    return ChannelValidation(
        channel=channel, n_samples=n, rms=float(np.sqrt(np.mean(res**2))),
        mean=float(np.mean(res)), theil=theil_inequality(y, yh),
        lags=np.arange(1, lag + 1), autocorrelation=r, band=band,
        outside_band=float(np.mean(np.abs(r) > band)), ljung_box_q=q, ljung_box_dof=dof,
        ljung_box_p=p, input_names=names, cross_lags=np.arange(-lag, lag + 1),
        cross_correlation=cross,
        max_cross_correlation=float(np.max(np.abs(cross))) if cross.size else float('nan'))


def predict(experiment: 'Experiment', p_full: npt.ArrayLike, x0: npt.ArrayLike | None = None,
            max_step: float = DEFAULT_MAX_STEP) -> tuple[np.ndarray, np.ndarray]:
    """
    Simulate a run at fixed parameters; its free initial states fitted by least squares.

    Parameters
    ----------
    experiment : Experiment
        A run with measurements. Its ``initial_state`` says which states at t0 are free
        ('estimate': all, 'positions': deflections) and are fitted to its data with the model
        parameters held (y is linear in x(t0), so the fit is exact linear least squares).
    p_full : array_like, shape (P,)
        Every model parameter (e.g. ``Estimate.model_parameters`` as a vector).
    x0 : array_like, shape (n,), optional
        Use this initial state instead of fitting one.
    max_step : float
        Longest RK4 step.

    Returns
    -------
    (x0, predicted outputs of shape (T, m))

    """
    if experiment.y is None and x0 is None:
        raise ValueError(f'run {experiment.name!r} has no measurements: give x0 to predict')
    # x0_guess is a starting value for identification, not a fit: always solve for x(t0)
    exp = replace(experiment, x0_guess=None)
    if x0 is not None:
        exp = replace(exp, initial_state=np.asarray(x0, dtype=float))
    problem = Problem([exp], [], None, None)
    problem.p_base = np.asarray(p_full, dtype=float).copy()
    theta = np.zeros(len(problem.names))
    if theta.size:
        theta = fit_initial_states(problem, theta, max_step)
    _, _, sim = evaluate(problem, theta, max_step, sensitivities=False)[0]
    x_start = problem.initial_state(0, theta, problem.p_base)[0]
    return x_start, sim.y


def validate_run(experiment: 'Experiment', p_full: npt.ArrayLike, held_out: bool = True,
                 x0: npt.ArrayLike | None = None, predicted: npt.ArrayLike | None = None,
                 max_lag: int | None = None,
                 max_step: float = DEFAULT_MAX_STEP) -> 'RunValidation':
    """
    Validate one run: predict it (unless ``predicted`` is given) and compute the statistics.

    Parameters
    ----------
    experiment : Experiment
        Run with measurements ``y``.
    p_full : array_like, shape (P,)
        Parameters to predict with.
    held_out : bool
        Label only: whether the run was left out of the estimate.
    x0 : array_like, optional
        Initial state (default: fitted by least squares, see :func:`predict`).
    predicted : array_like, shape (T, m), optional
        Model output already computed (e.g. ``Estimate.fitted``).
    max_lag : int, optional
        Largest lag of the correlation tests.
    max_step : float
        Longest RK4 step.

    Returns
    -------
    RunValidation

    """
    if experiment.y is None:
        raise ValueError(f'run {experiment.name!r} has no measurements to validate against')
    if predicted is None:
        x_start, predicted = predict(experiment, p_full, x0, max_step)
    else:
        x_start = np.asarray(x0 if x0 is not None else [], dtype=float)
        predicted = np.asarray(predicted, dtype=float)
    y = np.asarray(experiment.y, dtype=float)
    if predicted.shape != y.shape:
        raise ValueError(f'run {experiment.name!r}: prediction has shape {predicted.shape}, '
                         f'measurements {y.shape}')
    u = experiment.inputs(experiment.t)
    channels = [channel_statistics(y[:, j], predicted[:, j], name, u, INPUT_NAMES, max_lag)
                for j, name in enumerate(experiment.model.output_names)]
    return RunValidation(name=experiment.name, held_out=held_out, t=np.asarray(experiment.t),
                         measured=y, predicted=predicted, residuals=y - predicted,
                         initial_state=x_start, channels=channels)


def validate(estimate: 'Estimate', experiments: Sequence['Experiment'],
             held_out: Sequence['Experiment'] = (), max_lag: int | None = None,
             max_step: float = DEFAULT_MAX_STEP) -> 'list[RunValidation]':
    """
    Validate an estimate on its identification runs and on held-out runs.

    Parameters
    ----------
    estimate : Estimate
        From :func:`~rotor_id.estimation.output_error.fit_output_error` (its fitted outputs
        and initial states are used for the identification runs).
    experiments : list of Experiment
        The runs the estimate was fitted to, in the same order.
    held_out : list of Experiment
        New runs of the same model: predicted at the estimated parameters from their own
        least-squares initial state.
    max_lag : int, optional
        Largest lag of the correlation tests.
    max_step : float
        Longest RK4 step.

    Returns
    -------
    list of RunValidation
        Identification runs first, then the held-out runs.

    """
    model = experiments[0].model
    p = model.parameter_vector(estimate.model_parameters)
    out = []
    for r, exp in enumerate(experiments):
        fitted = estimate.fitted[r] if r < len(estimate.fitted) else None
        x0 = estimate.initial_states[r] if r < len(estimate.initial_states) else None
        out.append(validate_run(exp, p, held_out=False, x0=x0, predicted=fitted,
                                max_lag=max_lag, max_step=max_step))
    for exp in held_out:
        if exp.model.parameter_names != model.parameter_names:
            raise ValueError(f'held-out run {exp.name!r} uses model {exp.model.name!r}, whose '
                             f'parameters differ from those of the estimate ({model.name!r})')
        out.append(validate_run(exp, p, held_out=True, max_lag=max_lag, max_step=max_step))
    return out
