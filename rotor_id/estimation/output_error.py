"""
Output-error maximum likelihood (report Ch.2 steps 1-8, Ch.1 eq. 25; docs/models.md §0.1).

For measurement noise only, the negative log-likelihood of samples y_j is

    J(θ) = ½ Σ_j ν_jᵀ R⁻¹ ν_j + (N/2) log det R,     ν_j = y_j − H x̂_j(θ)

It is minimised by Gauss-Newton with the information matrix M = Σ (∂ŷ/∂θ)ᵀ R⁻¹ (∂ŷ/∂θ) from the
analytic sensitivities of :func:`rotor_id.estimation.simulate.simulate`. Safeguards: step halving
and a Levenberg-Marquardt damping when a step does not lower the cost, and the parameters'
physical bounds. R is diagonal (one variance per channel); when not given it is re-estimated
from the residuals after every accepted step (the usual relaxation of the maximum-likelihood
equations, Maine & Iliff). Initial states are unknowns when asked for; several experiments
(runs) can share one parameter vector, each with its own initial state and, when their
``noise_group`` differ, its own R (separate recordings); a Gaussian prior adds Ch.1 eq. 25's
a-priori term.

The Cramér-Rao bound M⁻¹ is evaluated at the estimate with the estimated R. Where the report is
silent (starting initial states, convergence test, noise estimation) the choices are documented
on the functions below.
"""

from dataclasses import dataclass, field
import math
import time
from typing import Any, Callable, Mapping, Sequence, TYPE_CHECKING
import weakref

import numpy as np
import numpy.typing as npt

from rotor_id.estimation.simulate import (DEFAULT_MAX_STEP, simulate, Simulation,
                                          TimeInvariantPlan)

if TYPE_CHECKING:
    from rotor_id.physics.models import LinearModel

INITIAL_STATE_MODES = ('estimate', 'positions', 'equilibrium', 'zero')

#: Returned by a ``progress`` callback: stop after this iteration and return the estimate so far.
STOP = 'stop after this iteration'
#: Parameter values by name (a guess, known values).
ParameterValues = Mapping[str, float]
#: A fit's progress callback: called with each iteration's dict; :data:`STOP` ends the fit.
Progress = Callable[[dict[str, Any]], Any]


class IdentificationError(ValueError):
    """The identification problem is malformed (message says what to change)."""


@dataclass
class Experiment:
    """
    One run: a model, its input, the sample times and the measured outputs.

    Attributes
    ----------
    model : LinearModel
    inputs : callable
        ``u = inputs(t)`` (e.g. StirringSchedule or SampledInput).
    t : ndarray, shape (T,)
        Sample times (nondimensional).
    y : ndarray, shape (T, m) or None
        Measurements in the model's output channels (None: only for information predictions).
    initial_state : str or array_like
        'estimate' (all states at t[0] unknown), 'positions' (deflections unknown, rates zero;
        report multiblade case c and the 7-parameter wake case), 'equilibrium' (steady state at
        the current parameters for the input held at t[0]), 'zero', or a fixed state vector.
    x0_guess : array_like, optional
        Start for estimated initial states. Default: the exact linear least-squares fit of the
        initial state to the data at the starting parameters.
    name : str
    noise_group : hashable
        Runs with the same group share one measurement-noise covariance R (the blades of one
        recording); different groups (different recordings) each get their own R.

    """

    model: 'LinearModel'
    inputs: Callable[[np.ndarray], np.ndarray]
    t: np.ndarray
    y: np.ndarray | None = None
    initial_state: object = 'estimate'
    x0_guess: object = None
    name: str = 'run'
    noise_group: object = 0

    def free_states(self) -> list[int]:
        """Return the indices of the states whose initial value is estimated."""
        mode = self.initial_state
        if isinstance(mode, str):
            if mode == 'estimate':
                return list(range(self.model.n_states))
            if mode == 'positions':
                return [i for i, s in enumerate(self.model.state_names)
                        if not s.endswith('_dot')]
            if mode in ('equilibrium', 'zero'):
                return []
            raise IdentificationError(f'unknown initial_state {mode!r}; use one of '
                                      f'{", ".join(INITIAL_STATE_MODES)} or a state vector')
        return []


#: The exceptions of a fit, or of a test at a fit, that fails on its data: a caller that tries
#: many models reports them for the model concerned and goes on.
FIT_FAILURES = (IdentificationError, np.linalg.LinAlgError, FloatingPointError, ValueError)


@dataclass
class AugmentedExperiment(Experiment):
    """An Experiment whose estimated initial states are given explicitly (``free``)."""

    free: list | None = None

    def free_states(self) -> list[int]:
        """Return the baseline's free states plus the augmentation's free ones."""
        if self.free is not None:
            return list(self.free)
        return super().free_states()


class ExtendedInput:
    """u = [θ0, θI, θII, extra…]: the baseline input with extra sampled columns."""

    def __init__(self, base_input: Callable[[np.ndarray], np.ndarray], t: npt.ArrayLike,
                 extra: npt.ArrayLike) -> None:
        self.base = base_input
        self.t = np.asarray(t, dtype=float)
        self.extra = np.asarray(extra, dtype=float)

    def __call__(self, t: npt.ArrayLike) -> np.ndarray:
        """Return u at times t, shape (len(t), 3 + k)."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        cols = [np.interp(t, self.t, self.extra[:, j]) for j in range(self.extra.shape[1])]
        return np.column_stack([self.base(t)] + cols)


def augment_runs(experiments: Sequence[Experiment], make: Callable[[Any], Any],
                 extra_inputs: Callable[[Experiment, Any], tuple] | None = None,
                 ) -> tuple[list[AugmentedExperiment], Any]:
    """
    One experiment per run with its model augmented (``make(model)``): (runs, model of run 1).

    An augmentation's extra inputs are sampled by ``extra_inputs(run, model)`` -> (t, columns);
    its extra states are free initial states where the run estimates its initial state.
    """
    runs = []
    for exp in experiments:
        model = make(exp.model)
        inputs = exp.inputs
        if getattr(model, 'extra_inputs', ()):
            assert extra_inputs is not None, 'an augmentation with extra inputs needs them'
            inputs = ExtendedInput(exp.inputs, *extra_inputs(exp, model))
        free = list(exp.free_states())
        if isinstance(exp.initial_state, str) and exp.initial_state == 'estimate':
            free += [model.state_names.index(s) for s in model.free_extra_states]
        runs.append(AugmentedExperiment(model, inputs, exp.t, exp.y,
                                        initial_state=exp.initial_state, name=exp.name,
                                        free=free))
    return runs, runs[0].model


@dataclass
class Estimate:
    """Result of an identification, with everything a user or a message needs."""

    names: list
    values: np.ndarray
    covariance: np.ndarray
    information: np.ndarray
    noise_std: np.ndarray
    channel_names: list
    cost: float
    neg_log_likelihood: float
    iterations: int
    converged: bool
    message: str
    n_samples: int
    history: list = field(default_factory=list)
    residuals: list = field(default_factory=list)
    fitted: list = field(default_factory=list)
    initial_states: list = field(default_factory=list)
    warnings: list = field(default_factory=list)
    model_parameters: dict = field(default_factory=dict)
    method: str = 'output-error'
    #: Noise σ per channel of every run (equal within a noise group); ``noise_std`` is their
    #: sample-weighted pooled value when the runs have separate noise groups.
    run_noise_std: list = field(default_factory=list)

    @property
    def std(self) -> np.ndarray:
        """Cramér-Rao standard deviations √diag(M⁻¹)."""
        return np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))

    @property
    def correlation(self) -> np.ndarray:
        """Correlation matrix of the Cramér-Rao bound."""
        s = self.std
        with np.errstate(invalid='ignore', divide='ignore'):
            corr = self.covariance / np.outer(s, s)
        return np.nan_to_num(corr)

    def value(self, name: str) -> float:
        """Estimated value of parameter ``name``."""
        return float(self.values[self.names.index(name)])

    def std_of(self, name: str) -> float:
        """Cramér-Rao σ of parameter ``name``."""
        return float(self.std[self.names.index(name)])

    def residual_rms(self) -> np.ndarray:
        """RMS of all residuals, per channel."""
        res = np.concatenate(self.residuals, axis=0)
        return np.sqrt(np.mean(res**2, axis=0))

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready dictionary with the stable keys of ``rotor-id identify``."""
        return {
            'method': self.method,
            'parameters': {n: {'value': float(v), 'std': float(s)}
                           for n, v, s in zip(self.names, self.values, self.std)},
            'covariance': {'names': list(self.names),
                           'matrix': [[float(c) for c in row] for row in self.covariance]},
            'correlation': [[float(c) for c in row] for row in self.correlation],
            'noise_std': [float(s) for s in self.noise_std],
            'channels': list(self.channel_names),
            'cost': float(self.cost),
            'neg_log_likelihood': float(self.neg_log_likelihood),
            'iterations': int(self.iterations),
            'converged': bool(self.converged),
            'message': self.message,
            'warnings': list(self.warnings),
            'n_samples': int(self.n_samples),
        }


def split_values(estimate: 'Estimate', unknowns: Sequence[str],
                 ) -> tuple[dict[str, float], dict[str, float]]:
    """Return an estimate's ({unknown: value}, {every other model parameter: value})."""
    have = estimate.model_parameters
    return {n: have[n] for n in unknowns}, {n: v for n, v in have.items() if n not in unknowns}


def _initial_state_name(state, run_index, n_runs):
    suffix = f'[{run_index + 1}]' if n_runs > 1 else ''
    return f'{state}(t0){suffix}'


#: θ's layouts (names, indices, start, bounds, free states) per model object, by unknowns,
#: guess, known values and the runs' free states (:func:`_layout`): id(model) -> (a weak
#: reference to the model, {key: layout}); at most this many models and layouts per model
LAYOUT_MODELS = 64
LAYOUTS_PER_MODEL = 8
_layouts: dict[int, tuple[weakref.ref, dict[tuple, dict[str, Any]]]] = {}


def _layout(experiments, unknowns, guess, known):
    """
    Return θ's layout for these runs as a dict of :class:`Problem`'s attributes (read only).

    Kept per model object (runs of one model), by the unknowns, the guess and known values,
    each run's free states and the model's parameter tuple (which ``with_bounds`` replaces):
    the refits of a record and the runs of a Monte Carlo study build it once. Where that
    key cannot be hashed or the runs have different models it is built every time.
    """
    model = experiments[0].model
    free = tuple(tuple(exp.free_states()) for exp in experiments)
    if any(exp.model is not model for exp in experiments):
        return _new_layout(experiments, unknowns, guess, known, free)
    entry = _layouts.get(id(model))
    try:
        if entry is None or entry[0]() is not model:
            if len(_layouts) >= LAYOUT_MODELS:
                _layouts.clear()
            entry = _layouts[id(model)] = (weakref.ref(model), {})
        kept = entry[1]
        key = (tuple(unknowns), tuple((guess or {}).items()), tuple((known or {}).items()),
               free)
        hit = kept.get(key)
    except TypeError:                   # values that cannot be hashed, or no weak reference
        return _new_layout(experiments, unknowns, guess, known, free)
    if hit is not None and hit['parameters'] is model.parameters:
        return hit
    layout = _new_layout(experiments, unknowns, guess, known, free)
    if len(kept) >= LAYOUTS_PER_MODEL:
        kept.clear()
    kept[key] = layout
    return layout


def _new_layout(experiments, unknowns, guess, known, free_states):
    """Build :func:`_layout`'s dict, checking the names (IdentificationError)."""
    model = experiments[0].model
    names = model.parameter_names
    for exp in experiments[1:]:
        if exp.model.parameter_names != names:
            raise IdentificationError('all runs combined in one estimate must share the '
                                      'same model parameters')
    for group in (unknowns, known or (), guess or ()):
        for name in group:
            if name not in names:
                raise IdentificationError(
                    f'unknown parameter {name!r} for model {model.name!r}; '
                    f'its parameters are {", ".join(names)}')
    param_index = [names.index(n) for n in unknowns]
    # model.parameter_vector(known), then the guess
    values = [par.nominal for par in model.parameters]
    for overrides in (known or {}, guess or {}):
        for name, value in overrides.items():
            values[names.index(name)] = float(value)
    parameters = model.parameters
    theta_names = list(unknowns)
    bounds_lo = [parameters[i].lower for i in param_index]
    bounds_hi = [parameters[i].upper for i in param_index]
    state_slices = []
    for r, (exp, free) in enumerate(zip(experiments, free_states)):
        start = len(theta_names)
        theta_names += [_initial_state_name(exp.model.state_names[i], r, len(experiments))
                        for i in free]
        bounds_lo += [-np.inf] * len(free)
        bounds_hi += [np.inf] * len(free)
        state_slices.append(slice(start, len(theta_names)))
    return {'parameters': parameters, 'param_index': tuple(param_index),
            'p_base': np.array(values, dtype=float), 'free_states': free_states,
            'names': tuple(theta_names), 'bounds_lo': tuple(bounds_lo),
            'bounds_hi': tuple(bounds_hi), 'state_slices': tuple(state_slices),
            'lo': np.array(bounds_lo), 'hi': np.array(bounds_hi)}


class Problem:
    """Bookkeeping of θ = [free model parameters, free initial states of each run]."""

    def __init__(self, experiments: Sequence[Experiment], unknowns: Sequence[str],
                 guess: ParameterValues | None, known: ParameterValues | None) -> None:
        if not experiments:
            raise IdentificationError('no experiment (run) to identify from')
        self.experiments = experiments
        self.model = experiments[0].model
        self.unknowns = list(unknowns)
        layout = _layout(experiments, self.unknowns, guess, known)
        self.param_index = list(layout['param_index'])
        self.p_base = layout['p_base'].copy()
        self.free_states = [list(free) for free in layout['free_states']]
        self.names = list(layout['names'])
        self.bounds_lo = list(layout['bounds_lo'])
        self.bounds_hi = list(layout['bounds_hi'])
        self.state_slices = list(layout['state_slices'])
        self.lo, self.hi = layout['lo'], layout['hi']
        #: per run: a TimeInvariantPlan (or None) once :meth:`prepare` ran; None before
        self.plans: list[TimeInvariantPlan | None] | None = None
        self.max_step: float | None = None

    def prepare(self, max_step: float) -> 'Problem':
        """
        Prepare every run's record for repeated simulation (:class:`TimeInvariantPlan`).

        Runs of models that do not qualify, or without the compiled kernels, keep None and are
        simulated by :func:`simulate` as before.
        """
        p = self.p_base
        self.plans = [TimeInvariantPlan.prepare(exp.model, exp.inputs, exp.t, max_step, p)
                      for exp in self.experiments]
        self.max_step = max_step
        return self

    def run_columns(self, r: int) -> np.ndarray | None:
        """Columns of θ of run r's sensitivities (None: all of θ, in order)."""
        k_par = len(self.param_index)
        sl = self.state_slices[r]
        if k_par + (sl.stop - sl.start) == len(self.names):
            return None
        return np.concatenate([np.arange(k_par), np.arange(sl.start, sl.stop)])

    def full_parameters(self, theta: np.ndarray) -> np.ndarray:
        p = self.p_base.copy()
        p[self.param_index] = theta[:len(self.param_index)]
        return p

    def initial_state(self, r: int, theta: np.ndarray, p: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
        """x0 of run r and ∂x0/∂θ_r (columns: model unknowns, then this run's free states)."""
        exp = self.experiments[r]
        n = exp.model.n_states
        k_par = len(self.param_index)
        free = self.free_states[r]
        jac = np.zeros((n, k_par + len(free)))
        mode = exp.initial_state
        if isinstance(mode, str) and mode == 'equilibrium':
            u0 = exp.inputs(exp.t[:1])
            x0 = exp.model.equilibrium(exp.t[:1], p, u0)
            jac[:, :k_par] = exp.model.equilibrium_jacobian(exp.t[:1], p, u0)[:, self.param_index]
            return x0, jac
        x0 = self.fixed_initial_state(r)
        x0[free] = theta[self.state_slices[r]]
        jac[free, k_par + np.arange(len(free))] = 1.0
        return x0, jac

    def fixed_initial_state(self, r: int) -> np.ndarray:
        """x0 of run r before its free states are set (not for 'equilibrium'): a new array."""
        exp = self.experiments[r]
        n = exp.model.n_states
        if isinstance(exp.initial_state, str):
            return np.zeros(n)
        x0 = np.array(exp.initial_state, dtype=float)
        if x0.shape != (n,):
            raise IdentificationError(f'initial state of run {exp.name!r} needs {n} values '
                                      f'({", ".join(exp.model.state_names)})')
        return x0


def fit_initial_states(problem: Problem, theta: np.ndarray, max_step: float) -> np.ndarray:
    """Least-squares initial states at fixed model parameters (y is linear in x0)."""
    p = None                            # the model parameters, once a run needs them
    for r, exp in enumerate(problem.experiments):
        free = problem.free_states[r]
        if not free or exp.y is None:
            continue
        if exp.x0_guess is not None:
            theta[problem.state_slices[r]] = np.asarray(exp.x0_guess, dtype=float)[free]
            continue
        if p is None:
            p = problem.full_parameters(theta)
        x0, _ = problem.initial_state(r, theta, p)
        x0[free] = 0.0
        jac = np.zeros((exp.model.n_states, len(free)))
        jac[free, np.arange(len(free))] = 1.0
        plan = _plan(problem, r, max_step)
        if plan is not None:
            sim = plan.run(p, x0, (), jac)
        else:
            sim = simulate(exp.model, p, exp.inputs, exp.t, x0, param_index=(),
                           x0_jacobian=jac, max_step=max_step)
        A = sim.dy.reshape(-1, len(free))  # type: ignore[union-attr]  # with x0_jacobian
        b = (exp.y - sim.y).ravel()
        ok = np.isfinite(b)
        theta[problem.state_slices[r]] = np.linalg.lstsq(A[ok], b[ok], rcond=None)[0]
    return theta


def _plan(problem, r, max_step):
    """Run r's prepared plan, if the problem was prepared for this ``max_step``."""
    if problem.plans is None or problem.max_step != max_step:
        return None
    return problem.plans[r]


def evaluate(problem: Problem, theta: np.ndarray, max_step: float = DEFAULT_MAX_STEP,
             sensitivities: bool = True, columns: Sequence[int] | None = None
             ) -> list[tuple[Any, Any, Simulation]]:
    """
    Residuals and output sensitivities of every run at θ.

    Returns a list of (residual (T, m), dy/dθ (T, m, len(θ)) or None, simulation) per run
    (residual None for a run without measurements, dy/dθ None without ``sensitivities``).
    Runs with a prepared plan (:meth:`Problem.prepare`) also carry the residuals' sums in
    ``simulation.residual_sums`` (run-local columns, :meth:`Problem.run_columns`).
    ``columns`` (positions in θ, its model parameters first): only those sensitivities are
    integrated, and dy/dθ has those columns alone (another run's initial state: zero).
    """
    p = problem.full_parameters(theta)
    k_par = len(problem.param_index)
    index = problem.param_index if columns is None else \
        [problem.param_index[c] for c in columns if c < k_par]
    if columns is not None and list(columns[:len(index)]) != [c for c in columns if c < k_par]:
        raise ValueError('columns: the model parameters come before the initial states')
    out = []
    for r, exp in enumerate(problem.experiments):
        x0, jac = problem.initial_state(r, theta, p)
        if columns is not None:
            mine = problem.state_slices[r]
            picked = np.zeros((jac.shape[0], len(columns)))
            for j, c in enumerate(columns):
                if c < k_par:
                    picked[:, j] = jac[:, c]
                elif mine.start <= c < mine.stop:
                    picked[:, j] = jac[:, k_par + c - mine.start]
            jac = picked
        # as integrated: every column of θ of this run, or the ``columns`` alone
        whole = columns is not None or problem.run_columns(r) is None
        plan = _plan(problem, r, max_step)
        if plan is not None:
            sim = plan.run(p, x0, index if sensitivities else (),
                           jac if sensitivities else None, exp.y)
            res = sim.residual
        else:
            sim = simulate(exp.model, p, exp.inputs, exp.t, x0,
                           param_index=index if sensitivities else (),
                           x0_jacobian=jac if sensitivities else None, max_step=max_step)
            res = None if exp.y is None else exp.y - sim.y
        if sensitivities and not whole:
            dy = np.zeros(sim.y.shape + (len(theta),))
            # (a simulation with sensitivities has dy)
            dy[:, :, :k_par] = sim.dy[:, :, :k_par]  # type: ignore[index]
            dy[:, :, problem.state_slices[r]] = sim.dy[:, :, k_par:]  # type: ignore[index]
        else:
            dy = sim.dy if sensitivities else None
        out.append((res, dy, sim))
    return out


def _squares(result):
    """Σ residual² per channel of one run's (res, dy, sim)."""
    res, _, sim = result
    if sim.residual_sums is not None:
        return sim.residual_sums[0]
    return np.sum(res**2, axis=0)


def _weighted_sums(problem, results, noise_var):
    """
    Return the information matrix M and the gradient of ½Σ νᵀR⁻¹ν over all runs (no prior).

    From each run's per-channel sums where its plan formed them, else from its residuals and
    sensitivities.
    """
    k = len(problem.names)
    M = np.zeros((k, k))
    grad = np.zeros(k)
    for r, ((res, dy, sim), var) in enumerate(zip(results, noise_var)):
        w = 1.0 / np.asarray(var, dtype=float)
        sums = sim.residual_sums
        if sums is None or sums[2].shape[-1] == 0:
            Mr, gr = weighted_products(dy, w, res)
            M += Mr
            grad -= gr
            continue
        _, gc, Mc = sums
        cols = problem.run_columns(r)
        Mr = (w @ Mc.reshape(w.size, -1)).reshape(Mc.shape[1:])
        if cols is None:
            M += Mr
            grad -= w @ gc
        else:
            M[np.ix_(cols, cols)] += Mr
            grad[cols] -= w @ gc
    return M, grad


def information_matrix(dys: Sequence[np.ndarray],
                       noise_var: npt.ArrayLike | list[npt.ArrayLike]) -> np.ndarray:
    """
    M = Σ_j (∂ŷ_j/∂θ)ᵀ R⁻¹ (∂ŷ_j/∂θ) over all runs (R = diag(noise_var)).

    ``noise_var`` is one variance per channel for all runs, or a list with one such per run.
    """
    k = dys[0].shape[-1]
    M = np.zeros((k, k))
    per_run = _per_run(noise_var, len(dys))
    for dy, var in zip(dys, per_run):
        M += weighted_products(dy, 1.0 / np.asarray(var, dtype=float))[0]
    return M


def weighted_products(dy: np.ndarray, weights: np.ndarray, res: np.ndarray | None = None
                      ) -> tuple[np.ndarray, np.ndarray | None]:
    """
    Return (Σ_t dy_tᵀ W dy_t, Σ_t dy_tᵀ W res_t) of one run, W = diag(weights) (None: no res).

    dy (T, m, k), res (T, m). As one product of (T·m, k) matrices (BLAS), not a loop over t.
    """
    k = dy.shape[-1]
    scaled = (dy * np.sqrt(weights)[:, None]).reshape(-1, k)
    gram = scaled.T @ scaled
    if res is None:
        return gram, None
    return gram, (res * weights).reshape(-1) @ dy.reshape(-1, k)


def _per_run(noise_var, n_runs):
    """One variance vector per run from either one shared vector or a list per run."""
    if isinstance(noise_var, list):
        if len(noise_var) != n_runs:
            raise ValueError(f'{len(noise_var)} noise variances for {n_runs} runs')
        return noise_var
    return [noise_var] * n_runs


#: Scaled-information eigenvalue ratio below which parameters are reported near-dependent.
DEPENDENCE_THRESHOLD = 1e-7


def dependence_warnings(names: Sequence[str], M: np.ndarray,
                        threshold: float = DEPENDENCE_THRESHOLD
                        ) -> tuple[list[str], np.ndarray | None]:
    """
    Eigen-analysis of the scaled information matrix: name near-dependent combinations.

    Returns (warnings, eigenvalues of the scaled matrix, or None when none can be small).
    A Cholesky factorisation of Ms − threshold·k·I first: where it succeeds, every eigenvalue
    of Ms exceeds threshold·k ≥ threshold·λmax (its diagonal is one, so λmax ≤ trace = k), no
    ratio falls below the threshold, and the eigen-analysis is not needed.
    """
    diag = M.diagonal()
    d = np.sqrt(np.clip(diag, 1e-300, None))
    Ms = M / np.outer(d, d)
    if diag.min() > 0:                          # (False with a NaN on the diagonal)
        shifted = Ms.copy()
        shifted.flat[::len(diag) + 1] -= threshold * len(diag)
        try:
            np.linalg.cholesky(shifted)
            return [], None
        except np.linalg.LinAlgError:
            pass
    vals, vecs = np.linalg.eigh(Ms)
    warnings = []
    if np.any(diag <= 0):
        zero = [n for n, v in zip(names, np.diag(M)) if v <= 0]
        warnings.append('no information at all on ' + ', '.join(zero)
                        + ': the data do not depend on them; fix them or change the input')
    ratios = vals / vals[-1] if vals[-1] > 0 else np.zeros_like(vals)
    if ratios[0] < threshold:
        # every direction of the near-null space: where it has more than one dimension, which
        # basis vector eigh returns first is decided by rounding, so one alone names too few
        combinations = []
        for c in np.flatnonzero(ratios < threshold):
            vec = vecs[:, c]
            order = np.argsort(-np.abs(vec))
            combinations.append(' '.join(f'{vec[i]:+.3f}·{names[i]}' for i in order
                                         if abs(vec[i]) > 0.1))
        what = (f'the combination {combinations[0]} is' if len(combinations) == 1 else
                f'the {len(combinations)} combinations {"; ".join(combinations)} are')
        warnings.append('near-dependent parameters (scaled information eigenvalue ratio '
                        f'{ratios[0]:.1e}): {what} not identifiable from these data; '
                        'fix one of them or add a prior')
    return warnings, vals


def damped_gauss_newton_step(theta: np.ndarray, grad: np.ndarray, M: np.ndarray,
                             lo: npt.ArrayLike, hi: npt.ArrayLike, cost: float,
                             trial_cost: Callable[[np.ndarray], tuple[float, Any]], lm: float,
                             free: npt.ArrayLike | None = None, attempts: int = 12,
                             halvings: int = 6) -> tuple[bool, np.ndarray, float, Any, float]:
    """
    One accepted step of scaled Gauss-Newton (Fisher scoring) with damping and step halving.

    The step solves (M̃ + λI) s̃ = −g̃ in the coordinates scaled by √diag(M), is clipped to the
    bounds [lo, hi] and halved until the cost does not rise; when ``halvings`` halvings fail,
    the Levenberg-Marquardt λ grows tenfold (from 1e-3) and the step is recomputed. Output
    error and filter error share this (one copy of the step logic).

    Parameters
    ----------
    theta, grad : ndarray, shape (k,)
        Current point and the gradient of the cost there.
    M : ndarray, shape (k, k)
        Gauss-Newton / expected information matrix.
    lo, hi : ndarray, shape (k,)
        Bounds.
    cost : float
        Cost at ``theta``.
    trial_cost : callable
        ``trial_cost(trial) -> (cost, payload)``; the payload of the accepted trial is returned.
    lm : float
        Current damping λ (0 = pure Gauss-Newton).
    free : ndarray of int, optional
        Indices allowed to move (an active set); default all.
    attempts, halvings : int
        Most damping increases, and most halvings per damping.

    Returns
    -------
    (accepted, trial, trial's cost, payload, λ for the next iteration)

    """
    k = theta.size
    fi = np.arange(k) if free is None else np.asarray(free)
    scale = np.sqrt(np.clip(np.diag(M)[fi], 1e-300, None))
    Ms = M[np.ix_(fi, fi)] / np.outer(scale, scale)
    for _attempt in range(attempts):
        A = Ms + lm * np.eye(fi.size)
        step = np.zeros(k)
        try:
            step[fi] = -np.linalg.solve(A, grad[fi] / scale) / scale
        except np.linalg.LinAlgError:
            step[fi] = -np.linalg.lstsq(A, grad[fi] / scale, rcond=None)[0] / scale
        for _halving in range(halvings):
            trial = np.clip(theta + step, lo, hi)
            # a trial far out may make the model blow up: numpy's overflow is no news to the
            # user, the trial's non-finite cost rejects it and the step is halved
            with np.errstate(over='ignore', invalid='ignore', divide='ignore'):
                new_cost, payload = trial_cost(trial)
            if math.isfinite(new_cost) and new_cost <= cost + 1e-12 * abs(cost):
                return True, trial, new_cost, payload, (lm / 10.0 if lm > 1e-6 else 0.0)
            step = 0.5 * step
        lm = max(1e-3, 10.0 * lm)
    return False, theta, cost, None, lm


def fit_output_error(experiments: Sequence[Experiment], unknowns: Sequence[str],
                     guess: ParameterValues | None = None,
                     known: ParameterValues | None = None,
                     noise_std: npt.ArrayLike | Sequence[npt.ArrayLike | None] | None = None,
                     prior: Mapping[str, Mapping[str, float]] | None = None, max_iter: int = 50,
                     step_tol: float = 1e-6, max_step: float = DEFAULT_MAX_STEP,
                     progress: Progress | None = None,
                     label: str = 'output-error ML') -> Estimate:
    """
    Output-error maximum likelihood over one or more runs.

    Parameters
    ----------
    experiments : list of Experiment
        The runs; they share the model parameters, each has its own initial state.
    unknowns : list of str
        Model parameters to identify (the initial states follow from each run's
        ``initial_state``).
    guess : dict, optional
        Starting values (default: the model's nominal values).
    known : dict, optional
        Values of the parameters held fixed (default: nominal).
    noise_std : float or array_like or list, optional
        Measurement noise σ per output channel. When None, R is estimated from the residuals
        (one R per ``noise_group`` of the experiments). A list gives one entry per experiment
        (each None, a scalar or one σ per channel): runs with an entry are held at it, the
        others' R is estimated per noise group.
    prior : dict, optional
        ``{'mean': {name: value}, 'std': {name: σ}}``: independent Gaussian a-priori information
        on model parameters (Ch.1 eq. 25); it adds ½Σ((θ−θp)/σp)² to J and 1/σp² to M.
    max_iter : int
        Most Gauss-Newton iterations.
    step_tol : float
        Converged when every step component is below ``step_tol`` times its Cramér-Rao σ
        (after taking that step) or below 1e-12 relative to the parameter.
    progress : callable, optional
        Called as ``progress(info)`` with a dict (iteration, cost, values, names, elapsed,
        message) after every iteration. If it returns :data:`STOP`, the fit ends after this
        iteration (unless it converged with it) and returns that iterate, not converged (a live
        caller that must publish something now).
    max_step : float
        Longest RK4 step of the simulation.
    label : str
        What is being fitted, passed on to ``progress``.

    Returns
    -------
    Estimate

    """
    problem = Problem(experiments, unknowns, guess, known)
    names = problem.names
    k = len(names)
    p_base = problem.p_base.tolist()
    theta = np.array([p_base[i] for i in problem.param_index]
                     + [0.0] * (k - len(problem.param_index)))
    m = experiments[0].model.n_outputs
    largest = 1.0
    for exp in experiments:
        if exp.y is None:
            raise IdentificationError(f'run {exp.name!r} has no measurements to fit')
        if exp.y.shape != (exp.t.size, exp.model.n_outputs):
            raise IdentificationError(
                f'run {exp.name!r}: measurements have shape {exp.y.shape}, the model needs '
                f'({exp.t.size}, {exp.model.n_outputs}) = samples x '
                f'({", ".join(exp.model.output_names)})')
        # the largest |y| is NaN or inf where any value is; it also sets the noise floor
        peak = float(np.abs(exp.y).max()) if exp.y.size else 0.0
        if not math.isfinite(peak):
            raise IdentificationError(f'run {exp.name!r}: measurements contain NaN or inf; '
                                      'drop those samples before identifying')
        largest = max(largest, peak)
    problem.prepare(max_step)
    theta = fit_initial_states(problem, theta, max_step)
    n_total = sum(exp.t.size for exp in experiments)
    prior_mean = np.zeros(k)
    prior_info = np.zeros(k)
    if prior:
        for name, sigma in prior.get('std', {}).items():
            if name not in names:
                raise IdentificationError(f'prior on unknown parameter {name!r}')
            i = names.index(name)
            prior_info[i] = 1.0 / float(sigma)**2
            prior_mean[i] = float(prior['mean'][name])
    noise_var, estimated_runs = _fixed_noise(noise_std, experiments, m)
    fixed_noise = not estimated_runs
    t_start = time.perf_counter()
    history = []
    warnings = []

    def cost_of(results, var):
        data = sum(0.5 * float(_squares(result) @ (1.0 / v)) for result, v in zip(results, var))
        return data + 0.5 * np.sum(prior_info * (theta_eval - prior_mean)**2)

    floor = 1e-24 * largest**2

    def estimate_var(results):
        # one R per noise group, from the residuals of its runs whose noise is not given
        var = list(noise_var)
        for members in estimated_runs:
            sq = sum(_squares(results[r]) for r in members)
            group_var = np.maximum(sq / sum(experiments[r].t.size for r in members), floor)
            for r in members:
                var[r] = group_var
        return var

    theta_eval = theta
    # the compiled iteration, or None once (or where) the fit runs in Python; the results of
    # either path (the compiled one's stay in its buffers: None until read)
    compiled: Any                       # (an iteration status ≥ 0 means it is not None)
    results: Any
    compiled = _CompiledIteration.for_problem(problem, floor, prior_info, prior_mean, step_tol,
                                              not fixed_noise)
    if compiled is not None and progress is None:     # the whole fit in one compiled call
        estimate = compiled.whole_fit(theta, noise_var[0], max_iter, t_start, label)
        if estimate is not None:
            return estimate
        # singular step equations on the way: the same fit again, an iteration at a time
    if compiled is not None:        # the first simulation already through its buffers
        results = [compiled.first(theta)]
    else:
        results = evaluate(problem, theta, max_step)
    if not fixed_noise:
        noise_var = estimate_var(results)
    cost = cost_of(results, noise_var)
    if not math.isfinite(cost):
        raise IdentificationError(NOT_FINITE_AT_START)
    converged = False
    message = 'maximum iterations reached'
    lm = 0.0
    iteration = 0

    def trial_cost(trial):
        # a plain simulation: most trials of a step are rejected, and the accepted one's
        # sensitivities are simulated once it is (the states are the same either way)
        nonlocal theta_eval
        theta_eval = trial              # the prior term of cost_of is taken at the trial
        return cost_of(evaluate(problem, trial, max_step, sensitivities=False), noise_var), None

    for iteration in range(1, max_iter + 1):
        status = -1 if compiled is None else compiled.iterate(theta, cost, lm, noise_var[0])
        if status >= 0:             # the compiled iteration: the same steps as below
            accepted, M, grad, lm = status == 1, compiled.M, compiled.grad, compiled.lm
            if accepted:            # its results stay in its buffers until they are read
                trial, trial_results = compiled.theta.copy(), None
        else:
            if compiled is not None:
                results = [compiled.result()]
            compiled = None         # singular step equations: Python from here on
            M, grad = _weighted_sums(problem, results, noise_var)
            M += np.diag(prior_info)
            grad = grad + prior_info * (theta - prior_mean)
            accepted, trial, _, trial_results, lm = damped_gauss_newton_step(
                theta, grad, M, problem.lo, problem.hi, cost, trial_cost, lm)
        if not accepted:
            theta_eval = theta
            message = NO_STEP_MESSAGE
            converged = _gradient_small(grad, M, cost)
            break
        applied: Any = None if compiled is not None else trial - theta
        theta = trial
        results = trial_results if compiled is not None else evaluate(problem, theta, max_step)
        if compiled is not None:
            theta_eval = theta
            noise_var = [compiled.var.copy()]
            cost = compiled.cost
            all_small = compiled.all_small
            rms = math.sqrt(compiled.squares / compiled.y.size)
        else:
            if not fixed_noise:
                noise_var = estimate_var(results)
                theta_eval = theta
            cost = cost_of(results, noise_var)
            sigma = np.sqrt(np.clip(np.diag(np.linalg.pinv(M)), 0.0, None))
            small = np.abs(applied) <= np.maximum(step_tol * sigma, 1e-12 * np.abs(theta))
            all_small = bool(np.all(small))
            n_res = sum(res.size for res, _, _ in results)
            rms = math.sqrt(sum(float(np.sum(_squares(result))) for result in results) / n_res)
        info = {'iteration': iteration, 'cost': float(cost), 'rms': rms, 'names': names,
                'values': theta.copy(), 'elapsed': time.perf_counter() - t_start,
                'label': label, 'noise_std': _pooled_std(noise_var, experiments)}
        history.append(info)
        stop = progress is not None and progress(info) is STOP
        any_bound = (compiled.at_bound if compiled is not None else
                     bool(np.any(theta <= problem.lo) or np.any(theta >= problem.hi)))
        if any_bound:
            at_bound = (theta <= problem.lo) | (theta >= problem.hi)
            bound_names = [n for n, b in zip(names, at_bound) if b]
            message = 'parameter at a physical bound: ' + ', '.join(bound_names)
        if all_small:
            converged = True
            message = 'converged' if not any_bound else message
            break
        if stop:
            if 'bound' not in message:
                message = 'stopped by the caller before convergence'
            break
    theta_eval = theta
    if compiled is not None:
        results = [compiled.result()]
    M, _ = _weighted_sums(problem, results, noise_var)
    M.flat[::k + 1] += prior_info
    dep, _ = dependence_warnings(names, M)
    warnings += dep
    try:
        cov = np.linalg.inv(M)
        if not np.isfinite(cov).all() or (cov.diagonal() < 0).any():
            raise np.linalg.LinAlgError
    except np.linalg.LinAlgError:
        cov = np.linalg.pinv(M)
        warnings.append(SINGULAR_WARNING)
    warnings += _stop_warnings(converged, message)
    data_cost = sum(0.5 * float(_squares(result) @ (1.0 / var))
                    for result, var in zip(results, noise_var))
    nll = data_cost + 0.5 * sum(exp.t.size * (float(np.log(var).sum()) + m * math.log(2 * math.pi))
                                for exp, var in zip(experiments, noise_var))
    p_final = problem.full_parameters(theta)
    init_states = [problem.initial_state(r, theta, p_final)[0] for r in range(len(experiments))]
    return Estimate(
        names=names, values=theta, covariance=cov, information=M,
        noise_std=_pooled_std(noise_var, experiments),
        channel_names=list(experiments[0].model.output_names),
        cost=float(cost), neg_log_likelihood=float(nll), iterations=iteration,
        converged=converged, message=message, n_samples=n_total, history=history,
        residuals=[res for res, _, _ in results], fitted=[sim.y for _, _, sim in results],
        initial_states=init_states, warnings=warnings,
        model_parameters=dict(zip(problem.model.parameter_names, p_final)),
        run_noise_std=[np.sqrt(var) for var in noise_var])


def _perf_counter_clock_id():
    """
    clock_gettime's id of time.perf_counter's clock, for gn_fit's per-iteration times; else -1.

    Only where perf_counter is that clock (Linux: CLOCK_MONOTONIC), so the compiled times and
    the start taken here in Python are on one clock.
    """
    clock = getattr(time, 'CLOCK_MONOTONIC', None)
    if clock is None or time.get_clock_info('perf_counter').implementation != \
            'clock_gettime(CLOCK_MONOTONIC)':
        return -1
    return int(clock)


PERF_COUNTER_CLOCK_ID = _perf_counter_clock_id()

NOT_FINITE_AT_START = ('the model response at the starting values is not finite; check the '
                       'starting values and the run description')
NO_STEP_MESSAGE = ('no step lowers the cost any more (stopped at a minimum or a bound; the '
                   'bound-limited parameters are reported)')
SINGULAR_WARNING = ('information matrix is singular: the Cramér-Rao bound is a pseudo-inverse '
                    'and meaningless for the dependent combination')


def _gradient_small(grad, M, cost):
    """Converged after all when no step lowers the cost: |g|·σ below 1e-3 of the cost."""
    return bool(np.all(np.abs(grad) * np.sqrt(np.clip(np.diag(np.linalg.pinv(M)), 0, None))
                       < 1e-3 * max(1.0, cost)))


def _stop_warnings(converged, message):
    """Warnings of how the iterations stopped (not converged, or at a physical bound)."""
    if 'bound' in message:
        return [message + ': the estimate is limited by the bound, not by the data (missing '
                'physics in the model, or a poor start); do not use it as is']
    return [] if converged else [message]


class _CompiledIteration:
    """
    The Gauss-Newton fit of a single prepared run: whole in one compiled call, or by iteration.

    Used where the run has a :class:`~rotor_id.estimation.simulate.TimeInvariantPlan` whose
    reference point covers every unknown model parameter (so no trial needs the model), no
    output offset, and an initial state that does not depend on the parameters (not
    'equilibrium'). :meth:`iterate` runs ``_kernels_numba.gn_iteration``: the same M,
    gradient, damped step, trials, noise estimate, cost and convergence test as the Python
    loop of :func:`fit_output_error` (test_kernels.py compares the two to 1e-9);
    :meth:`whole_fit` runs all iterations and the final M, dependence pre-test and M⁻¹ in
    ``_kernels_numba.gn_fit`` (callers without a progress callback).
    """

    def __init__(self, problem, plan, reference, index, floor, prior_info, prior_mean,
                 step_tol, estimate_noise):
        """Hold the arrays of the compiled call (see :meth:`for_problem`)."""
        exp = problem.experiments[0]
        self.plan = plan
        self.exp = exp
        p_ref, self.F, self.g, self.dF, self.dg, _ = reference
        self.p_ref = p_ref
        self.p_base = problem.p_base
        self.index = index
        # x0(θ) = x0_base + S0 θ: Problem.initial_state of a run whose x0 is not 'equilibrium'
        self.free, self.x0_base, self.S0 = self._initial_state_map(problem, plan, index.size)
        self.y = np.ascontiguousarray(exp.y, dtype=float)
        self.lo, self.hi = problem.lo, problem.hi
        self.floor = float(floor)
        self.prior_info, self.prior_mean = prior_info, prior_mean
        self.step_tol = float(step_tol)
        self.estimate_noise = bool(estimate_noise)
        self.problem = problem
        self.current = None             # the buffers of the iteration at a time (_buffers)

    @staticmethod
    def _initial_state_map(problem, plan, k_par):
        """
        (free states, x0_base, S0) of the run, kept on the plan for a named initial state.

        An initial state given by name ('estimate', 'zero', ...) makes them depend on the
        model's states and θ's layout only, so a refit of the record reuses them (six numpy
        calls less, in a refit's Python that runs cold between other work); a given vector
        is data, and they are built each time.
        """
        exp = problem.experiments[0]
        free_list = problem.free_states[0]
        key = None
        if isinstance(exp.initial_state, str):
            key = (exp.initial_state, tuple(free_list), k_par, len(problem.names))
            kept = plan.initial_state_maps.get(key)
            if kept is not None:
                return kept
        free = np.asarray(free_list, dtype=np.int64)
        x0 = problem.fixed_initial_state(0)
        x0[free] = 0.0
        S0 = np.zeros((exp.model.n_states, len(problem.names)))
        S0[free, k_par + np.arange(free.size)] = 1.0
        out = (free, x0, S0)
        if key is not None:             # writable (numba compiles read-only arrays anew):
            if len(plan.initial_state_maps) >= 8:       # nothing here writes them
                plan.initial_state_maps.clear()
            plan.initial_state_maps[key] = out
        return out

    def _buffers(self):
        """Allocate the buffers of :meth:`first` and :meth:`iterate` (not :meth:`whole_fit`)."""
        exp = self.exp
        k, m = len(self.problem.names), exp.model.n_outputs
        n, T = exp.model.n_states, exp.t.size
        shapes = ((T, n), (T, n, k), (T, m), (T, m, k), (T, m), (m,), (m, k), (m, k, k))
        # buffers (xs, Ss, ŷ, ∂ŷ, res, Σres², Σ∂ŷᵀres, Σ∂ŷᵀ∂ŷ) of the current point and a trial
        self.current = tuple(np.empty(shape) for shape in shapes)
        self.spare = tuple(np.empty(shape) for shape in shapes)
        self.theta, self.var = np.empty(k), np.empty(m)
        self.M, self.grad, self.sigma = np.empty((k, k)), np.empty(k), np.empty(k)
        self.scalars = np.empty(5)

    @classmethod
    def for_problem(cls, problem, floor, prior_info, prior_mean, step_tol, estimate_noise):
        """Return the compiled iteration of this problem, or None where it does not apply."""
        if problem.plans is None or len(problem.experiments) != 1:
            return None
        plan = problem.plans[0]
        mode = problem.experiments[0].initial_state
        if (plan is None or plan.has_offset or problem.experiments[0].y is None
                or (isinstance(mode, str) and mode == 'equilibrium')
                or not problem.param_index):
            return None
        # one read: a plan kept for its record may get a new reference from another fit
        index = np.asarray(problem.param_index, dtype=np.int64)
        reference = plan.reference_at(problem.p_base, index)
        # reference_at's point equals p_base along every parameter that is not affine
        if not plan.affine_along(reference, problem.param_index):
            return None
        return cls(problem, plan, reference, index, floor, prior_info, prior_mean, step_tol,
                   estimate_noise)

    def first(self, theta):
        """Simulate at the starting θ into the current buffers; return it as :meth:`result`."""
        if self.current is None:
            self._buffers()
        k_par = self.index.size
        shift = self.p_base - self.p_ref
        shift[self.index] = theta[:k_par] - self.p_ref[self.index]
        x0 = self.x0_base.copy()
        x0[self.free] = theta[k_par:]
        m = self.y.shape[1]
        plan = self.plan
        plan.kernels.affine_run(self.F, self.g, self.dF, self.dg, shift, self.index, plan.step,
                                plan.substeps, plan.U, x0, self.S0, plan.H, np.zeros((0, m)),
                                np.zeros((0, m, k_par)), self.y, *self.current)
        return self.result()

    def iterate(self, theta, cost, lm, var):
        """Run one iteration from θ; return 1 (step accepted), 0 (none lowers the cost), −1."""
        plan = self.plan
        xs, Ss, yhat, dyhat, res, sq, gc, Mc = self.spare
        status = plan.kernels.gn_iteration(
            self.F, self.g, self.dF, self.dg, self.p_ref, self.p_base, self.index, plan.step,
            plan.substeps, plan.U, self.x0_base, self.free, self.S0, plan.H, self.y,
            theta, float(cost), float(lm), var, self.estimate_noise, self.floor, self.prior_info,
            self.prior_mean, self.lo, self.hi, self.step_tol, self.current[5],
            self.current[6], self.current[7], xs, Ss, yhat, dyhat, res, sq, gc, Mc,
            self.theta, self.var, self.M, self.grad, self.sigma, self.scalars)
        self.cost, self.lm = float(self.scalars[0]), float(self.scalars[1])
        self.all_small = bool(self.scalars[2])
        self.squares = float(self.scalars[3])
        self.at_bound = bool(self.scalars[4])
        if status == 1:
            self.current, self.spare = self.spare, self.current
        return int(status)

    def whole_fit(self, theta, noise_var, max_iter, t_start, label):
        """
        Run the whole fit in one compiled call (``_kernels_numba.gn_fit``); return its Estimate.

        The same iterations, stops, messages, warnings and bound as fit_output_error's loop
        (test_kernels.py compares them to 1e-9), for a caller without a progress callback.
        Returns None when the step equations became singular on the way (the caller fits again
        an iteration at a time). Each iteration's ``elapsed`` is read in the compiled loop from
        perf_counter's clock (clock_gettime); where that clock is not available there, every
        history entry's ``elapsed`` is the time of the whole fit, as its ``elapsed_of`` says.
        """
        problem, exp, plan = self.problem, self.exp, self.plan
        names = problem.names
        k, m, T = theta.size, self.y.shape[1], self.y.shape[0]
        hist_theta, hist_var = np.empty((max(max_iter, 0), k)), np.empty((max(max_iter, 0), m))
        hist_scalars = np.empty((max(max_iter, 0), 4))
        res, yhat = np.empty((T, m)), np.empty((T, m))
        sq, gc, Mc = np.empty(m), np.empty((m, k)), np.empty((m, k, k))
        values, var, M, grad, cov = (np.empty(k), np.empty(m), np.empty((k, k)), np.empty(k),
                                     np.empty((k, k)))
        scalars = np.empty(7)
        reason = plan.kernels.gn_fit(
            self.F, self.g, self.dF, self.dg, self.p_ref, self.p_base, self.index, plan.step,
            plan.substeps, plan.U, self.x0_base, self.free, self.S0, plan.H, self.y, theta,
            np.ones(m) if noise_var is None else noise_var, self.estimate_noise, self.floor,
            self.prior_info, self.prior_mean, self.lo, self.hi, self.step_tol, int(max_iter),
            DEPENDENCE_THRESHOLD, PERF_COUNTER_CLOCK_ID, res, yhat, sq, gc, Mc, hist_theta,
            hist_var, hist_scalars, values, var, M, grad, cov, scalars)
        elapsed = time.perf_counter() - t_start
        if reason == -2:
            raise IdentificationError(NOT_FINITE_AT_START)
        if reason == -1:
            return None
        cost, data_cost, accepted, _, iterations, pretest_passed, inverse_valid = \
            scalars.tolist()
        accepted, iterations = int(accepted), int(iterations)
        # per accepted iteration [cost, rms, on a bound, clock ns] as Python floats
        rows = hist_scalars[:accepted].tolist()
        history = [{'iteration': i + 1, 'cost': cost_i, 'rms': rms_i, 'names': names,
                    'values': values_i, 'elapsed': clock_i * 1e-9 - t_start, 'label': label,
                    'noise_std': std_i}
                   for i, ((cost_i, rms_i, _, clock_i), values_i, std_i) in enumerate(
                       zip(rows, hist_theta[:accepted], np.sqrt(hist_var[:accepted])))]
        if PERF_COUNTER_CLOCK_ID < 0:           # no clock in the compiled loop: say so
            for info in history:
                info.update(elapsed=elapsed, elapsed_of='the whole fit (one compiled call)')
        message = 'maximum iterations reached'
        bounded = [i for i, row in enumerate(rows) if row[2]]
        if bounded:                 # the last iterate on a bound names it (as the loop does)
            last = hist_theta[bounded[-1]]
            at_bound = (last <= problem.lo) | (last >= problem.hi)
            message = 'parameter at a physical bound: ' + ', '.join(
                n for n, b in zip(names, at_bound) if b)
        converged = reason == 2
        if reason == 1:
            message = NO_STEP_MESSAGE
            converged = _gradient_small(grad, M, cost)
        elif converged and not (bounded and bounded[-1] == accepted - 1):
            message = 'converged'
        warnings = [] if pretest_passed else dependence_warnings(names, M)[0]
        if not inverse_valid:
            cov = np.linalg.pinv(M)
            warnings.append(SINGULAR_WARNING)
        warnings += _stop_warnings(converged, message)
        nll = data_cost + 0.5 * T * (float(np.log(var).sum()) + m * math.log(2 * math.pi))
        p_final = problem.full_parameters(values)
        x0 = self.x0_base.copy()
        x0[self.free] = values[self.index.size:]
        return Estimate(
            names=names, values=values, covariance=cov, information=M, noise_std=np.sqrt(var),
            channel_names=list(exp.model.output_names), cost=cost, neg_log_likelihood=nll,
            iterations=iterations, converged=converged, message=message, n_samples=T,
            history=history, residuals=[res], fitted=[yhat], initial_states=[x0],
            warnings=warnings, model_parameters=dict(zip(problem.model.parameter_names,
                                                         p_final)),
            run_noise_std=[np.sqrt(var)])

    def result(self):
        """Return the accepted point's (residual, dy/dθ, Simulation), as :func:`evaluate` does."""
        xs, Ss, yhat, dyhat, res, sq, gc, Mc = self.current
        sim = Simulation(self.plan.t, xs, yhat, Ss, dyhat, residual=res,
                         residual_sums=(sq, gc, Mc))
        return res, dyhat, sim


def _fixed_noise(noise_std, experiments, m):
    """
    Per-run variances of the given noise, and the noise groups to estimate.

    Returns ``(variances, groups)``: a list with one variance vector (or None, to be estimated)
    per run, and a list of run-index lists, one per noise group whose R is estimated.
    """
    n_runs = len(experiments)
    if isinstance(noise_std, (int, float, np.floating)):      # one σ for every channel and run
        return [np.full(m, float(noise_std)**2) for _ in range(n_runs)], []
    if isinstance(noise_std, list):
        if len(noise_std) != n_runs:
            raise IdentificationError(f'{len(noise_std)} noise σ entries for {n_runs} runs; '
                                      'give one per run (None where it is to be estimated)')
        given = noise_std
    else:
        given = [noise_std] * n_runs
    variances = [None if s is None else np.full(m, float(s)**2) if np.ndim(s) == 0 else
                 np.broadcast_to(np.asarray(s, dtype=float)**2, (m,)).copy() for s in given]
    groups = {}
    for r, exp in enumerate(experiments):
        if variances[r] is None:
            groups.setdefault(exp.noise_group, []).append(r)
    return variances, list(groups.values())


def _pooled_std(noise_var, experiments):
    """Noise σ per channel over all runs: the runs' own when equal, else sample-weighted."""
    if len(noise_var) == 1:
        return np.sqrt(noise_var[0])
    if all(np.array_equal(v, noise_var[0]) for v in noise_var[1:]):
        return np.sqrt(noise_var[0]).copy()
    n = np.array([exp.t.size for exp in experiments], dtype=float)
    return np.sqrt(np.einsum('r,rm->m', n, np.array(noise_var)) / n.sum())
