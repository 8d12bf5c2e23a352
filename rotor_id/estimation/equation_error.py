"""
Equation-error estimators (report Ch.2 eqs 7-13) and their iterated form.

The iterated form uses an updated Kalman filter (Ch.2, "Iterative equation error estimation
with updated Kalman filter"). The state equation x′ = F(t,p) x + g(t,p,u) is affine in p for
the report's models in (γ, δ) and in (A, AL/τ, 1/τ). Around the current p₀ it is written as
the report's "measurement equation" (eq. 8)

    ζ = h(ξ, θ) + v,     ζ = x′ − F(p₀)x − g(p₀) + A p₀,     h = A θ,
    A = [∂F/∂p_k x + ∂g/∂p_k]_k                       (the regressors, from system_jacobian)

which is exact for affine models (and a Gauss-Newton linearisation for θ0 = δ/γ). Only the rows
that depend on the parameters are used (the kinematic rows x₁′ = x₂ carry no information:
Ch.1's "row independence").

* :func:`sequential_estimate` integrates eqs 10-11 sample by sample (information form of the
  Kalman update with measurement ζ_j, "H" = A_j, weight W Δt_j) and returns θ̂(t) and P_θ(t).
* :func:`global_estimate` is eqs 12-13 (P_θ(0)⁻¹ = 0 unless a prior is given).
* :func:`fit_equation_error` is the iterated method: a Kalman filter and RTS smoother built with
  the current parameters (and process noise on the parameter-dependent rows, so the smoothed
  trajectory may leave the wrong model and follow the data) reconstruct x and x′ from the
  measured outputs, the global estimate re-estimates p, the filter is updated, and so on.
  An optional zero-phase low-pass prefilter (scipy.signal.filtfilt, the report's digital
  filter) can be applied to the measurements first.

The report found this method cheaper per iteration but less accurate than maximum likelihood,
and its covariance "does not properly reflect the actual errors": the regressors and x′ come
from the same smoothed, serially correlated reconstruction, so P_θ (the regression covariance,
first factor of eq. 12) is far smaller than the actual scatter of θ̂. It is reported as
computed, with a warning, and must not be read as a confidence measure.
"""

from dataclasses import dataclass, field, replace
import math
import time
from typing import Any, Callable, Mapping, Sequence, TYPE_CHECKING

import numpy as np
import numpy.typing as npt
from rotor_id.estimation import kalman
from rotor_id.estimation.filter_error import difference_noise_std, filter_batch
from rotor_id.estimation.output_error import (
    Estimate, Experiment, fit_initial_states, IdentificationError, Problem)
from rotor_id.estimation.simulate import DEFAULT_MAX_STEP

if TYPE_CHECKING:
    from rotor_id.physics.models import LinearModel

#: the process-noise σ's tried when none is given, in multiples of the outputs' RMS: a
#: half-decade grid from a filter that follows the model to one that follows the data
PROCESS_NOISE_LEVELS = (1e-3, 3e-3, 1e-2, 3e-2, 0.1, 0.3, 1.0)
COVARIANCE_WARNING = ('equation-error covariance: the regression covariance P_θ (report Ch.2 eq. '
                      '13) is computed from smoothed, correlated states and is NOT a confidence '
                      'measure (it understates the actual scatter); use output or filter error '
                      'for bounds')


@dataclass
class Regression:
    """
    The equation-error regression ζ = A θ + v on the parameter-dependent rows.

    Attributes
    ----------
    zeta : ndarray, shape (T, r)
        Parameter-free left-hand side of eq. 8 on the r used rows.
    A : ndarray, shape (T, r, k)
        Regressors ∂h/∂θ for the k unknowns.
    rows : list of int
        State rows used.
    weights : ndarray, shape (T,)
        Integration weights (trapezoidal Δt) of ∫ … dt.

    """

    zeta: np.ndarray
    A: np.ndarray
    rows: list
    weights: np.ndarray


def regression(model: 'LinearModel', p: np.ndarray, inputs: Callable[[np.ndarray], np.ndarray],
               t: npt.ArrayLike, x: np.ndarray, xdot: np.ndarray,
               unknown_index: Sequence[int]) -> 'Regression':
    """Build the eq.-8 regression from states ``x`` and derivatives ``xdot``, both (T, n)."""
    t = np.asarray(t, dtype=float)
    u = inputs(t)
    F, g = model.system(t, p, u)
    dF, dg = model.system_jacobian(t, p, u)
    idx = list(unknown_index)
    A = np.einsum('tkij,tj->tik', dF[:, idx], x) + np.swapaxes(dg[:, idx], 1, 2)
    zeta = xdot - np.einsum('tij,tj->ti', F, x) - g + A @ np.asarray(p, dtype=float)[idx]
    rows = [i for i in range(model.n_states) if np.any(A[:, i, :] != 0.0)]
    if not rows:
        raise IdentificationError('none of the unknowns appears in the state equations; '
                                  'equation error cannot estimate them')
    weights = np.zeros(t.size)
    dt = np.diff(t)
    weights[:-1] += 0.5 * dt
    weights[1:] += 0.5 * dt
    return Regression(zeta[:, rows], A[:, rows, :], rows, weights)


def _row_weight(W, r):
    W = np.ones(r) if W is None else np.asarray(W, dtype=float)
    return np.diag(W) if W.ndim == 1 else W


def global_estimate(reg: 'Regression', W: npt.ArrayLike | None = None,
                    prior_mean: npt.ArrayLike | None = None,
                    prior_cov: npt.ArrayLike | None = None) -> tuple[np.ndarray, np.ndarray]:
    """
    Global estimate, report Ch.2 eqs 12-13.

    θ̂ = [P_θ(0)⁻¹ + ∫AᵀWA dt]⁻¹ [P_θ(0)⁻¹θ(0) + ∫AᵀWζ dt],   P_θ(T) = the first factor.

    Parameters
    ----------
    reg : Regression
        The regression (:func:`regression`).
    W : array_like, shape (r,) or (r, r), optional
        Weighting R⁻¹ of the rows (default I, the report's R = I).
    prior_mean : array_like, shape (k,), optional
        θ(0) of eq. 12 (with ``prior_cov``).
    prior_cov : array_like, shape (k, k), optional
        P_θ(0); omitted = infinite (P_θ(0)⁻¹ = 0).

    Returns
    -------
    theta : ndarray, shape (k,)
    P : ndarray, shape (k, k)

    """
    Wm = _row_weight(W, reg.zeta.shape[1])
    info = np.einsum('t,tri,rs,tsk->ik', reg.weights, reg.A, Wm, reg.A)
    rhs = np.einsum('t,tri,rs,ts->i', reg.weights, reg.A, Wm, reg.zeta)
    if prior_cov is not None:
        prior_info = np.linalg.inv(np.asarray(prior_cov, dtype=float))
        info = info + prior_info
        rhs = rhs + prior_info @ np.asarray(prior_mean, dtype=float)
    P = np.linalg.inv(info)
    return P @ rhs, P


@dataclass
class SequentialResult:
    """θ̂(t) and P_θ(t) of the sequential linear estimator (eqs 10-11)."""

    t: np.ndarray
    theta: np.ndarray
    P: np.ndarray


def sequential_estimate(reg: 'Regression', t: npt.ArrayLike, theta0: npt.ArrayLike,
                        P0: npt.ArrayLike, W: npt.ArrayLike | None = None) -> 'SequentialResult':
    """
    Sequential linear estimator, report Ch.2 eqs 10-11 (Ch.1 eqs 43-46).

    Discretised sample by sample in information form, which integrates eq. 11 exactly for the
    trapezoidal quadrature of eq. 13:

        P_θ(t_j)⁻¹ = P_θ(t_{j−1})⁻¹ + A_jᵀ W A_j w_j
        θ̂(t_j)    = P_θ(t_j) [P_θ(t_{j−1})⁻¹ θ̂(t_{j−1}) + A_jᵀ W ζ_j w_j]

    With a very large P0 the final θ̂ equals :func:`global_estimate` (report Fig. 3: 5.05).

    Parameters
    ----------
    reg : Regression
        The regression (:func:`regression`).
    t : array_like, shape (T,)
        Sample times (nondimensional), strictly increasing.
    theta0 : array_like, shape (k,)
        A-priori estimate θ(0).
    P0 : array_like, shape (k, k)
        A-priori covariance P_θ(0) (large: little prior information).
    W : array_like, optional
        Weighting R⁻¹ of the rows (default I).

    Returns
    -------
    SequentialResult
        ``theta`` (T, k) and the P_θ history ``P`` (T, k, k).

    """
    Wm = _row_weight(W, reg.zeta.shape[1])
    T, _, k = reg.A.shape
    theta = np.asarray(theta0, dtype=float).copy()
    info = np.linalg.inv(np.asarray(P0, dtype=float))
    thetas = np.empty((T, k))
    Ps = np.empty((T, k, k))
    for j in range(T):
        Aj, wj = reg.A[j], reg.weights[j]
        # eq. 11: the information grows by the row regressors of this sample
        rhs = info @ theta + wj * Aj.T @ Wm @ reg.zeta[j]
        info = info + wj * Aj.T @ Wm @ Aj
        # eq. 10: the estimate moves towards what this sample's equation error says
        P = np.linalg.inv(info)
        theta = P @ rhs
        thetas[j], Ps[j] = theta, P
    return SequentialResult(np.asarray(t, dtype=float), thetas, Ps)


def lowpass(t: npt.ArrayLike, y: npt.ArrayLike, cutoff: float, order: int = 4) -> np.ndarray:
    """
    Zero-phase Butterworth low-pass (the report's digital prefilter), cutoff in rad per unit t.

    The report's cut-off "2.5 to 2.9" is in multiples of the rotor speed, i.e. rad per unit
    nondimensional time; ``cutoff`` uses the same unit. Needs uniform sampling.
    """
    t = np.asarray(t, dtype=float)
    dt = np.diff(t)
    if not np.allclose(dt, dt[0], rtol=1e-6):
        raise IdentificationError('the low-pass prefilter needs uniformly sampled data')
    nyquist = math.pi / dt[0]
    if not 0.0 < cutoff < nyquist:
        raise IdentificationError(f'prefilter cutoff {cutoff} must lie between 0 and the Nyquist '
                                  f'frequency {nyquist:.3g} (rad per unit nondimensional time)')
    import scipy.signal     # on use: its import takes longer than a diagnosis's proposal
    b, a = scipy.signal.butter(order, cutoff / nyquist)
    return scipy.signal.filtfilt(b, a, np.asarray(y, dtype=float), axis=0)


@dataclass
class EquationErrorResult:
    """Iterated equation-error result for one set of runs."""

    names: list
    values: np.ndarray
    covariance: np.ndarray
    process_noise_std: float
    history: list = field(default_factory=list)
    reconstructions: list = field(default_factory=list)
    regressions: list = field(default_factory=list)
    iterations: int = 0
    converged: bool = False


def _parameter_rows(model, p, inputs, t):
    """State rows whose equation depends on some parameter."""
    u = inputs(np.asarray(t[:3], dtype=float))
    dF, dg = model.system_jacobian(np.asarray(t[:3], dtype=float), p, u)
    dep = np.any(dF != 0.0, axis=(0, 1, 3)) | np.any(dg != 0.0, axis=(0, 1))
    return [i for i in range(model.n_states) if dep[i]]


def fit_equation_error_experiments(experiments: Sequence[Experiment], unknowns: Sequence[str],
                                   guess: Mapping[str, float] | None = None,
                                   known: Mapping[str, float] | None = None,
                                   progress: Callable[..., Any] | None = None,
                                   max_iter: int = 10, noise_std: npt.ArrayLike | None = None,
                                   process_noise_std: float | None = None,
                                   prefilter_cutoff: float | None = None, step_tol: float = 1e-3,
                                   max_step: float = DEFAULT_MAX_STEP) -> Estimate:
    """
    Estimate by iterated equation error with an updated Kalman filter (report Ch.2).

    Parameters
    ----------
    experiments : list of Experiment
        Runs sharing one parameter vector (their regressions are stacked).
    unknowns : list of str
        Model parameters to estimate; the others are held at ``known`` (default nominal).
    guess : dict, optional
        Parameters of the first Kalman filter (the report used 20 % errors).
    known : dict, optional
        Values of the parameters held fixed (default nominal).
    progress : callable, optional
        ``progress(info)`` after every iteration.
    max_iter : int
        Filter-regression passes (the report shows 4).
    noise_std : float or array_like, optional
        Measurement σ per channel for the filter; default from second differences.
    process_noise_std : float, optional
        √(white-noise intensity) on the parameter-dependent rows of the reconstruction filter.
        Default: the maximum-likelihood value on a coarse grid at the starting parameters,
        then held (at the converged parameters the likelihood would push it to zero, where the
        smoothed trajectory *is* the model and the regression can only return its input).
    prefilter_cutoff : float, optional
        Zero-phase low-pass of the measurements first (rad per unit nondimensional time).
    step_tol : float
        Stop when every parameter changes by less than ``step_tol`` relative.
    max_step : float
        Longest RK4 step of the filter discretisation.

    Returns
    -------
    Estimate
        ``method='equation-error'``; its covariance is the regression's P_θ and carries the
        warning :data:`COVARIANCE_WARNING`.

    """
    result = fit_equation_error(experiments, unknowns, guess, known, progress, max_iter,
                                noise_std, process_noise_std, prefilter_cutoff, step_tol,
                                max_step)
    model = experiments[0].model
    p_final = model.parameter_vector({**(known or {}),
                                      **dict(zip(result.names, result.values))})
    residuals, fitted, x_init = [], [], []
    nll = 0.0
    for exp, rec in zip(experiments, result.reconstructions):
        H = exp.model.output_matrix(exp.t)
        y_hat = np.einsum('tij,tj->ti', H, rec.x_smoothed)
        y_hat = y_hat + exp.model.output_offset(exp.t, p_final)
        fitted.append(y_hat)
        residuals.append(exp.y - y_hat)
        x_init.append(rec.x_smoothed[0])
        nll -= rec.filtered.log_likelihood
    res_all = np.concatenate(residuals)
    noise = np.sqrt(np.mean(res_all**2, axis=0))
    info = np.linalg.inv(result.covariance)
    warnings = [COVARIANCE_WARNING]
    if not result.converged:
        warnings.append(f'equation error did not settle in {result.iterations} iterations '
                        '(the report saw overshoot too); the last iterate is reported')
    return Estimate(
        names=list(result.names), values=result.values, covariance=result.covariance,
        information=info, noise_std=noise, channel_names=list(model.output_names),
        cost=float(result.history[-1]['cost']), neg_log_likelihood=float(nll),
        iterations=result.iterations, converged=result.converged,
        message='converged' if result.converged else 'maximum iterations reached',
        n_samples=int(sum(exp.t.size for exp in experiments)), history=result.history,
        residuals=residuals, fitted=fitted, initial_states=x_init, warnings=warnings,
        model_parameters=dict(zip(model.parameter_names, p_final)), method='equation-error')


def fit_equation_error(experiments: Sequence[Experiment], unknowns: Sequence[str],
                       guess: Mapping[str, float] | None = None,
                       known: Mapping[str, float] | None = None,
                       progress: Callable[..., Any] | None = None, max_iter: int = 10,
                       noise_std: npt.ArrayLike | None = None,
                       process_noise_std: float | None = None,
                       prefilter_cutoff: float | None = None, step_tol: float = 1e-3,
                       max_step: float = DEFAULT_MAX_STEP) -> 'EquationErrorResult':
    """
    Run the iteration behind :func:`fit_equation_error_experiments` (same parameters).

    Returns
    -------
    EquationErrorResult
        With the per-iteration history (values, P_θ diagonal), the final reconstructions
        (:class:`rotor_id.estimation.kalman.Reconstruction`) and regressions.

    """
    if isinstance(experiments, Experiment):
        experiments = [experiments]
    problem = Problem([Experiment(e.model, e.inputs, e.t, e.y, 'estimate', None, e.name)
                       for e in experiments], unknowns, guess, known)
    model = problem.model
    idx = problem.param_index
    m = model.n_outputs
    data = []
    for exp in experiments:
        if exp.y is None or exp.y.shape != (exp.t.size, m):
            raise IdentificationError(f'run {exp.name!r}: equation error needs measurements of '
                                      f'shape ({exp.t.size}, {m})')
        if not np.all(np.isfinite(exp.y)):
            raise IdentificationError(f'run {exp.name!r}: measurements contain NaN or inf; '
                                      'drop those samples before identifying')
        y = exp.y if prefilter_cutoff is None else lowpass(exp.t, exp.y, prefilter_cutoff)
        sig = difference_noise_std(exp.y) if noise_std is None else \
            np.broadcast_to(np.asarray(noise_std, dtype=float), (m,))
        data.append((exp, y, np.diag(np.maximum(sig, 1e-12)**2)))
    p = problem.p_base.copy()
    rows = _parameter_rows(model, p, experiments[0].inputs, experiments[0].t)
    scale = max(float(np.sqrt(np.mean(np.concatenate([y for _, y, _ in data])**2))), 1e-12)

    def initial_covariance(R):
        return np.eye(model.n_states) * max(scale**2, float(np.max(np.diag(R))))

    def initial_states(p):
        theta = np.concatenate([p[idx], np.zeros(len(problem.names) - len(idx))])
        return fit_initial_states(problem, theta, max_step)

    def reconstruct(p, q_std, smooth=True, theta=None):
        recs = []
        if theta is None:
            theta = initial_states(p)
        for r, (exp, y, R) in enumerate(data):
            recs.append(kalman.reconstruct_states(
                exp.model, p, exp.inputs, exp.t, y, R, theta[problem.state_slices[r]],
                initial_covariance(R), rows, q_std, 'white', max_step, smooth))
        return recs

    if process_noise_std is None:
        # the level of most likelihood (the filter's: no smoothing needed to rank them), all
        # from the same initial states (they depend on p only), every level in one batch: Q
        # is σ² times the unit-intensity Q of one discretisation
        theta = initial_states(p)
        levels = scale * np.array(PROCESS_NOISE_LEVELS)
        cost = np.zeros(levels.size)
        for r, (exp, y, R) in enumerate(data):
            unit = kalman.discretize(exp.model, p, exp.inputs, exp.t, rows, 1.0, 'white',
                                     max_step)
            cost += filter_batch([replace(unit, Q=unit.Q * level**2) for level in levels], y,
                                 np.tile(theta[problem.state_slices[r]], (levels.size, 1)),
                                 np.tile(R, (levels.size, 1, 1)), 'time-varying',
                                 np.tile(initial_covariance(R), (levels.size, 1, 1)))[3]
        process_noise_std = float(levels[np.argmin(cost)])
    t_start = time.perf_counter()
    history = []
    converged = False
    iteration = 0
    for iteration in range(1, max_iter + 1):
        recs = reconstruct(p, process_noise_std)
        regs = [regression(exp.model, p, exp.inputs, exp.t, rec.x_smoothed, rec.derivatives, idx)
                for (exp, _, _), rec in zip(data, recs)]
        stacked = Regression(np.concatenate([g.zeta for g in regs]),
                             np.concatenate([g.A for g in regs]), regs[0].rows,
                             np.concatenate([g.weights for g in regs]))
        # ordinary, then row-weighted least squares (W = 1/residual variance per row)
        theta, _ = global_estimate(stacked)
        res = stacked.zeta - stacked.A @ theta
        row_var = np.maximum(np.sum(stacked.weights[:, None] * res**2, axis=0)
                             / np.sum(stacked.weights), 1e-300)
        # a white equation error of per-sample variance s² has the density R = s² Δt, so
        # W = R⁻¹ makes P_θ of eq. 13 the classical regression covariance (Σ AᵀA / s²)⁻¹
        dt_mean = float(np.sum(stacked.weights)) / stacked.weights.size
        theta, P = global_estimate(stacked, W=1.0 / (row_var * dt_mean))
        res = stacked.zeta - stacked.A @ theta
        cost = 0.5 * float(np.sum(stacked.weights[:, None] * res**2 / row_var))
        change = theta - p[idx]
        p = p.copy()
        p[idx] = theta
        out_res = [y - np.einsum('tij,tj->ti', exp.model.output_matrix(exp.t), rec.x_smoothed)
                   for (exp, y, _), rec in zip(data, recs)]
        rms = math.sqrt(float(np.mean(np.concatenate(out_res)**2)))
        info = {'iteration': iteration, 'cost': cost, 'rms': rms, 'names': list(unknowns),
                'values': theta.copy(), 'P_diag': np.diag(P).copy(),
                'elapsed': time.perf_counter() - t_start, 'label': 'equation error'}
        history.append(info)
        if progress is not None:
            progress(info)
        if np.all(np.abs(change) <= step_tol * np.maximum(np.abs(theta), 1e-12)):
            converged = True
            break
    recs = reconstruct(p, process_noise_std)
    return EquationErrorResult(names=list(unknowns), values=p[idx].copy(), covariance=P,
                               process_noise_std=float(process_noise_std),
                               history=history,
                               reconstructions=recs, regressions=regs, iterations=iteration,
                               converged=converged)
