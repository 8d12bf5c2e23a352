"""
Optimal data utilization: the Cramér-Rao bound as the record grows (report Ch.3 eqs 16-23).

For output error the information matrix of samples t_0 … t_f is (Ch.3 eq. 19)

    M(t_f) = Σ_{t_j ≤ t_f} S_jᵀ R⁻¹ S_j,        S_j = ∂ŷ_j/∂θ   (output sensitivities, eq. 18)

and M⁻¹(t_f) bounds the covariance of any unbiased estimate from those samples. Because every
sample adds a positive semi-definite term, each diagonal element M⁻¹(t_f)(i, i) decreases
monotonically with t_f (eq. 22, dM⁻¹/dt_f = −(1/Δt) M⁻¹ SᵀR⁻¹S M⁻¹), so there is a shortest
record meeting stipulated standard deviations σ_i (eq. 23, M⁻¹(i, i) ≤ σ_i²).

Everything here is evaluated at given parameters, without fitting: the sensitivities come from
:func:`rotor_id.estimation.simulate.simulate` through the same bookkeeping the output-error
estimator uses (:mod:`rotor_id.estimation.output_error`), so θ may include initial states
exactly as in an identification ('beta(t0)' …).

Public functions
----------------
:func:`sensitivities`         S_j for an experiment at p (what everything below is built from)
:func:`cramer_rao_bound`      M and M⁻¹ of one or more experiments at p (no fitting)
:func:`information_history`   M⁻¹(t_f) for every record end t_f (Ch.3 figs 2-3)
:func:`continuous_bound`      Δt·[∫SᵀR⁻¹S dt]⁻¹, the continuous approximation (eq. 21)
:func:`shortest_record`       first t_f with M⁻¹(i, i) ≤ σ_i² for all i (eq. 23)
:func:`information_density`   which samples carry the information (per parameter, log det M)
:func:`inverse_or_nan`        M⁻¹ of an information matrix, NaN while it is singular
:func:`inverses_or_nan`       the same for a stack of them (one per record end)
"""

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np
import numpy.typing as npt

from rotor_id.estimation.output_error import (
    evaluate, Experiment, fit_initial_states, IdentificationError, Problem)
from rotor_id.estimation.simulate import DEFAULT_MAX_STEP
from rotor_id.numpy_compat import trapezoid


@dataclass
class Sensitivities:
    """
    Output sensitivities of one experiment at given parameters.

    Attributes
    ----------
    t : ndarray, shape (T,)
    names : list of str
        θ: the unknown model parameters, then the experiment's free initial states.
    values : ndarray, shape (k,)
        θ at which they were evaluated.
    dy : ndarray, shape (T, m, k)
        S_j = ∂ŷ_j/∂θ.
    y : ndarray, shape (T, m)
        Noise-free model output at θ.

    """

    t: np.ndarray
    names: list
    values: np.ndarray
    dy: np.ndarray
    y: np.ndarray


@dataclass
class Bound:
    """
    Information matrix and Cramér-Rao bound at given parameters.

    Attributes
    ----------
    names : list of str
    values : ndarray, shape (k,)
    information : ndarray, shape (k, k)
        M = Σ SᵀR⁻¹S.
    covariance : ndarray, shape (k, k)
        M⁻¹ (NaN when M is singular).

    """

    names: list
    values: np.ndarray
    information: np.ndarray
    covariance: np.ndarray

    @property
    def std(self) -> np.ndarray:
        """Cramér-Rao standard deviations √diag(M⁻¹)."""
        return np.sqrt(np.diag(self.covariance))

    def sub(self, names: Sequence[str]) -> np.ndarray:
        """Return the block of M⁻¹ for the named parameters, shape (len(names), len(names))."""
        idx = [self.names.index(n) for n in names]
        return self.covariance[np.ix_(idx, idx)]


@dataclass
class InformationHistory:
    """
    M(t_f) and M⁻¹(t_f) for every sample time t_f of a record (Ch.3 eq. 19 partial sums).

    Attributes
    ----------
    t : ndarray, shape (T,)
        Record ends t_f (the sample times).
    names : list of str
    information : ndarray, shape (T, k, k)
        M(t_f) = Σ_{t_j ≤ t_f} S_jᵀR⁻¹S_j.
    covariance : ndarray, shape (T, k, k)
        M⁻¹(t_f); NaN while M(t_f) is still singular (too few samples).

    """

    t: np.ndarray
    names: list
    information: np.ndarray
    covariance: np.ndarray

    def variance(self, name: str) -> np.ndarray:
        """M⁻¹(t_f)(i, i) of parameter ``name`` for every t_f, shape (T,)."""
        i = self.names.index(name)
        return self.covariance[:, i, i]

    def std(self) -> np.ndarray:
        """Cramér-Rao σ of every parameter for every t_f, shape (T, k)."""
        return np.sqrt(np.einsum('tii->ti', self.covariance))

    def at(self, t_f: float) -> np.ndarray:
        """M⁻¹ of the record ending at the last sample not later than ``t_f``."""
        j = int(np.searchsorted(self.t, t_f + 1e-9 * max(1.0, abs(t_f)), side='right')) - 1
        if j < 0:
            raise ValueError(f't_f = {t_f} is before the first sample t = {self.t[0]}')
        return self.covariance[j]


@dataclass
class RecordLength:
    """
    Answer of :func:`shortest_record` (report Ch.3 eq. 23).

    Attributes
    ----------
    met : bool
        Whether the stipulated σ_i are reached within the record.
    t_f : float or None
        Shortest record end meeting every M⁻¹(i, i) ≤ σ_i² (None when not met).
    index : int or None
        Its sample index.
    duration : float or None
        t_f − t_0.
    std_at_end : ndarray, shape (k,)
        Cramér-Rao σ at t_f (or at the end of the record when not met).
    limiting : str
        The parameter that is met last (or that is furthest from its target when not met).

    """

    met: bool
    t_f: float | None
    index: int | None
    duration: float | None
    std_at_end: np.ndarray
    limiting: str


@dataclass
class InformationDensity:
    """
    Where in the record the information is (per sample j).

    Attributes
    ----------
    t : ndarray, shape (T,)
    names : list of str
    diagonal : ndarray, shape (T, k)
        diag(S_jᵀR⁻¹S_j): sample j's contribution to each parameter's own information M(i, i).
    variance_reduction : ndarray, shape (T, k)
        diag(M⁻¹(t_{j−1}) − M⁻¹(t_j)): how much sample j lowers each bound M⁻¹(i, i)
        (the discrete form of eq. 22); zero while M is still singular.
    log_det_increment : ndarray, shape (T,)
        log det M(t_j) − log det M(t_{j−1}): sample j's share of the D-optimality criterion;
        NaN while M is still singular.

    """

    t: np.ndarray
    names: list
    diagonal: np.ndarray
    variance_reduction: np.ndarray
    log_det_increment: np.ndarray


def _as_list(experiments):
    return list(experiments) if isinstance(experiments, (list, tuple)) else [experiments]


def _theta(problem, p_full, x0, max_step):
    """θ = [unknown parameters at p_full, free initial states] for every run."""
    p_full = np.asarray(p_full, dtype=float)
    problem.p_base = p_full.copy()
    k = len(problem.names)
    theta = np.concatenate([p_full[problem.param_index], np.zeros(k - len(problem.param_index))])
    for r, exp in enumerate(problem.experiments):
        free = problem.free_states[r]
        if not free:
            continue
        x0_r = x0[r] if x0 is not None else exp.x0_guess
        if x0_r is not None:
            theta[problem.state_slices[r]] = np.asarray(x0_r, dtype=float)[free]
        elif exp.y is None:
            raise IdentificationError(
                f'run {exp.name!r} estimates initial states ({exp.initial_state!r}) but has '
                'neither measurements nor x0_guess: give the initial state to evaluate at')
    missing = any(problem.free_states[r] and (x0 is None and exp.x0_guess is None)
                  for r, exp in enumerate(problem.experiments))
    if missing:
        theta = fit_initial_states(problem, theta, max_step)
    return theta


def _noise_var(noise_std, m):
    var = np.broadcast_to(np.asarray(noise_std, dtype=float) ** 2, (m,)).copy()
    if np.any(var <= 0) or not np.all(np.isfinite(var)):
        raise ValueError(f'noise standard deviations must be positive and finite, got {noise_std}')
    return var


def sensitivities(experiment: Experiment, p_full: npt.ArrayLike, unknown_names: Sequence[str],
                  x0: npt.ArrayLike | None = None,
                  max_step: float = DEFAULT_MAX_STEP) -> Sensitivities:
    """
    Output sensitivities S_j = ∂ŷ_j/∂θ of one experiment at the full parameter vector p.

    Parameters
    ----------
    experiment : Experiment
        Its ``initial_state`` decides which initial states join θ (as in an identification).
    p_full : array_like, shape (P,)
        Every model parameter (``model.parameter_vector({...})``).
    unknown_names : sequence of str
        Model parameters in θ.
    x0 : array_like, shape (n,), optional
        Initial state to evaluate at when initial states are free. Default: the experiment's
        ``x0_guess``, else the least-squares fit to its measurements at p.
    max_step : float
        Longest RK4 step of the simulation.

    Returns
    -------
    Sensitivities

    """
    problem = Problem([experiment], list(unknown_names), None, None)
    theta = _theta(problem, p_full, None if x0 is None else [x0], max_step)
    _, dy, sim = evaluate(problem, theta, max_step)[0]
    return Sensitivities(t=np.asarray(experiment.t, dtype=float), names=list(problem.names),
                         values=theta, dy=dy, y=sim.y)


def _information(dy, noise_var):
    """Per-sample S_jᵀR⁻¹S_j, shape (T, k, k)."""
    return np.einsum('tmi,m,tmj->tij', dy, 1.0 / noise_var, dy)


def inverse_or_nan(M: npt.ArrayLike) -> np.ndarray:
    """
    Return M⁻¹ of an information matrix, or all-NaN when M is (numerically) singular.

    Inverted after scaling to unit diagonal; singular means a zero diagonal element or a
    scaled condition number above 1e12 (too few samples, or a non-identifiable combination).
    """
    d = np.sqrt(np.clip(np.diag(M), 0.0, None))
    if np.any(d <= 0):
        return np.full_like(M, np.nan)
    Ms = M / np.outer(d, d)
    if np.linalg.cond(Ms) > 1e12:
        return np.full_like(M, np.nan)
    return np.linalg.inv(Ms) / np.outer(d, d)


_safe_inverse = inverse_or_nan       # the name rotor_id.planning imports


def inverses_or_nan(M: npt.ArrayLike) -> np.ndarray:
    """
    Apply :func:`inverse_or_nan` to a stack of information matrices M (T, k, k).

    The same arithmetic as the loop over the stack, in one batched SVD and one batched
    inversion, so the results are identical (the live verdict inverts one M per sample).
    """
    M = np.asarray(M, dtype=float)
    out = np.full_like(M, np.nan)
    if M.shape[0] == 0:
        return out
    d = np.sqrt(np.clip(np.einsum('tii->ti', M), 0.0, None))
    good = np.flatnonzero(np.all(d > 0, axis=1))
    if good.size == 0:
        return out
    scale = d[good, :, None] * d[good, None, :]
    Ms = M[good] / scale
    good_cond = np.linalg.cond(Ms) <= 1e12
    out[good[good_cond]] = np.linalg.inv(Ms[good_cond]) / scale[good_cond]
    return out


def cramer_rao_bound(experiments: Experiment | Sequence[Experiment], p_full: npt.ArrayLike,
                     unknown_names: Sequence[str], noise_std: npt.ArrayLike = 1.0,
                     x0: npt.ArrayLike | None = None,
                     max_step: float = DEFAULT_MAX_STEP) -> Bound:
    """
    M and M⁻¹ of one or more experiments at p, without fitting (Ch.3 eq. 19).

    Parameters
    ----------
    experiments : Experiment or list of Experiment
        Runs sharing the model parameters; each adds its own free initial states.
    p_full : array_like, shape (P,)
        Every model parameter.
    unknown_names : sequence of str
        Model parameters in θ.
    noise_std : float or array_like, shape (m,)
        Measurement σ per output channel (R = diag σ²). The report prints M⁻¹ for R = I.
    x0 : list of array_like, optional
        Initial state per run when initial states are free (see :func:`sensitivities`).
    max_step : float
        Longest RK4 step of the simulation.

    Returns
    -------
    Bound

    """
    experiments = _as_list(experiments)
    problem = Problem(experiments, list(unknown_names), None, None)
    theta = _theta(problem, p_full, x0, max_step)
    var = _noise_var(noise_std, experiments[0].model.n_outputs)
    M = sum(_information(dy, var).sum(axis=0) for _, dy, _ in evaluate(problem, theta, max_step))
    return Bound(names=list(problem.names), values=theta, information=M,
                 covariance=inverse_or_nan(M))


def information_history(experiment: Experiment, p_full: npt.ArrayLike,
                        unknown_names: Sequence[str], noise_std: npt.ArrayLike = 1.0,
                        x0: npt.ArrayLike | None = None,
                        max_step: float = DEFAULT_MAX_STEP) -> InformationHistory:
    """
    M⁻¹(t_f) as the record grows, from the cumulative information (Ch.3 eqs 19-22).

    The record always starts at the experiment's first sample t_0; M(t_f) sums the samples
    t_0 … t_f (t_0 informs the initial states only). Shorter windows of a longer record give the
    same numbers as separate experiments over those windows, because the sensitivities of a
    causal system do not depend on later samples.

    Parameters
    ----------
    experiment : Experiment
        The record (its ``initial_state`` decides which initial states join θ).
    p_full : array_like, shape (P,)
        Every model parameter.
    unknown_names : sequence of str
        Model parameters in θ.
    noise_std : float or array_like, shape (m,)
        Measurement σ per output channel (R = diag σ²).
    x0 : array_like, optional
        Initial state when initial states are free (see :func:`sensitivities`).
    max_step : float
        Longest RK4 step of the simulation.

    Returns
    -------
    InformationHistory

    """
    sens = sensitivities(experiment, p_full, unknown_names, x0, max_step)
    var = _noise_var(noise_std, experiment.model.n_outputs)
    M = np.cumsum(_information(sens.dy, var), axis=0)
    return InformationHistory(t=sens.t, names=sens.names, information=M,
                              covariance=inverses_or_nan(M))


def continuous_bound(experiment: Experiment, p_full: npt.ArrayLike,
                     unknown_names: Sequence[str], noise_std: npt.ArrayLike = 1.0,
                     x0: npt.ArrayLike | None = None,
                     max_step: float = DEFAULT_MAX_STEP) -> Bound:
    """
    Continuous approximation M⁻¹ ≈ Δt·[∫ SᵀR⁻¹S dt]⁻¹ over the record (Ch.3 eq. 21).

    The integral is the trapezoidal rule on the samples, Δt their mean spacing. The discrete sum
    (:func:`cramer_rao_bound`) is the Cramér-Rao bound; this form is what eq. 22 differentiates.
    Returns a :class:`Bound`.
    """
    sens = sensitivities(experiment, p_full, unknown_names, x0, max_step)
    var = _noise_var(noise_std, experiment.model.n_outputs)
    dt = float(np.mean(np.diff(sens.t)))
    integral = trapezoid(_information(sens.dy, var), sens.t, axis=0)
    return Bound(names=sens.names, values=sens.values, information=integral / dt,
                 covariance=inverse_or_nan(integral / dt))


def shortest_record(history: InformationHistory,
                    target_std: Mapping[str, float] | npt.ArrayLike) -> 'RecordLength':
    """
    Shortest record meeting stipulated standard deviations (Ch.3 eq. 23).

    Parameters
    ----------
    history : InformationHistory
        From :func:`information_history` (with the noise σ of the planned test).
    target_std : dict or array_like
        σ_i per parameter name (parameters left out are unconstrained) or one value per name.
        The report advises choosing them smaller than needed, since M⁻¹ is only a lower bound.

    Returns
    -------
    RecordLength

    """
    if isinstance(target_std, dict):
        unknown = [n for n in target_std if n not in history.names]
        if unknown:
            raise ValueError(f'no parameter {", ".join(unknown)} in this record; '
                             f'its parameters are {", ".join(history.names)}')
        idx = [history.names.index(n) for n in target_std]
        sig = np.array([float(v) for v in target_std.values()])
    else:
        sig = np.broadcast_to(np.asarray(target_std, dtype=float), (len(history.names),))
        idx = list(range(len(history.names)))
    if np.any(sig <= 0):
        raise ValueError('stipulated standard deviations must be positive')
    std = history.std()[:, idx]
    ok = np.all(std <= sig, axis=1) & np.all(np.isfinite(std), axis=1)
    ratio = std / sig
    if not np.any(ok):
        last = np.nan_to_num(ratio[-1], nan=np.inf)
        return RecordLength(met=False, t_f=None, index=None, duration=None,
                            std_at_end=history.std()[-1],
                            limiting=history.names[idx[int(np.argmax(last))]])
    j = int(np.argmax(ok))
    if j == 0:
        limiting = history.names[idx[int(np.argmax(ratio[0]))]]
    else:
        prev = np.nan_to_num(ratio[j - 1], nan=np.inf)
        limiting = history.names[idx[int(np.argmax(prev))]]
    return RecordLength(met=True, t_f=float(history.t[j]), index=j,
                        duration=float(history.t[j] - history.t[0]),
                        std_at_end=history.std()[j], limiting=limiting)


def information_density(experiment: Experiment, p_full: npt.ArrayLike,
                        unknown_names: Sequence[str], noise_std: npt.ArrayLike = 1.0,
                        x0: npt.ArrayLike | None = None,
                        max_step: float = DEFAULT_MAX_STEP) -> 'InformationDensity':
    """
    Which samples carry the information: per-sample contributions (Ch.3 eqs 19, 22).

    Returns
    -------
    InformationDensity

    """
    history = information_history(experiment, p_full, unknown_names, noise_std, x0, max_step)
    M = history.information
    per_sample = np.diff(np.concatenate([np.zeros((1,) + M.shape[1:]), M]), axis=0)
    diagonal = np.einsum('tii->ti', per_sample)
    var = np.einsum('tii->ti', history.covariance)
    reduction = np.zeros_like(var)
    reduction[1:] = np.nan_to_num(var[:-1] - var[1:], nan=0.0)
    logdet = np.full(M.shape[0], np.nan)
    for j, Mj in enumerate(M):
        sign, value = np.linalg.slogdet(Mj)
        if sign > 0 and np.all(np.isfinite(history.covariance[j])):
            logdet[j] = value
    increment = np.full_like(logdet, np.nan)
    increment[1:] = logdet[1:] - logdet[:-1]
    return InformationDensity(t=history.t, names=history.names, diagonal=diagonal,
                              variance_reduction=reduction, log_det_increment=increment)
