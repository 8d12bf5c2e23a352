"""
From a recorded run to an estimate: the one path shared by CLI, nodes, diagnosis and plan.

record (rad, s)  →  window  →  model of the run description  →  Experiment(s) in the report's
nondimensional time  →  estimator  →  :class:`Identification` (estimate + what it was fitted to).

No ROS here: records come from :mod:`rotor_id.io.bag` or from the identifier node's buffers.
"""

from dataclasses import dataclass, field, replace
import itertools
import math
from typing import Any, Callable, Iterable, Mapping, Sequence, TYPE_CHECKING

import numpy as np

from rotor_id.estimation.output_error import (
    Estimate, Experiment, fit_output_error, IdentificationError)
from rotor_id.physics.models import (
    build_model, DirectionalResponse, LinearModel, lock_number_from_known, RotorConstants,
    RotorModel)
from rotor_id.physics.stirring import SampledInput

if TYPE_CHECKING:   # (scipy behind some of them: imported where used)
    from rotor_id.adequacy import Adequacy
    from rotor_id.estimation.frequency_response import (
        BandCost, FrequencyFit, FrequencyResponse, Sweep)
    from rotor_id.io.record import Record
    from rotor_id.io.run_description import RunDescription

#: Called with a dict per iteration of an estimator; returns None or STOP.
Progress = Callable[[dict], object]
#: Recordings fitted together: (record, its run description, a name for messages).
Runs = Sequence[tuple['Record', 'RunDescription', str]]

#: Default output channels per model when the run description does not say.
DEFAULT_MEASUREMENT = {
    'single_blade': 'blades',
    'multiblade': 'multiblade',
    'multiblade_constant': 'multiblade',
    'multiblade_wake': 'eq30',
}


@dataclass
class Identification:
    """An estimate with the model, runs and window it came from."""

    estimate: Estimate
    model: LinearModel
    experiments: list[Experiment]
    description: 'RunDescription'
    window_s: tuple
    omega_rad_s: float
    unknowns: list[str]
    #: Several recordings fitted together (:func:`identify_runs`): one :class:`Run` each.
    runs: list['Run'] = field(default_factory=list)
    #: parameters neither identified nor given in ``known``: name -> value the fit used
    defaults_used: dict = field(default_factory=dict)
    #: the residual check (None only when the caller skipped it)
    adequacy: 'Adequacy | None' = None
    #: remarks on the inputs (defaults taken), before the estimator's own warnings
    notes: list = field(default_factory=list)
    #: ``--method frequency-response``: the :class:`FrequencyIdentification` behind the estimate
    frequency_response: 'FrequencyIdentification | None' = None

    @property
    def warnings(self) -> list[str]:
        """Every warning of this identification: inputs, estimator, adequacy."""
        out = list(self.notes) + list(self.estimate.warnings)
        if self.adequacy is not None and self.adequacy.warning():
            out.append(self.adequacy.warning())
        return out

    def as_json(self) -> dict[str, Any]:
        """
        Return the JSON of ``rotor-id identify`` (its keys are stable; more may be added).

        With several recordings, ``window_s`` and ``omega_rad_s`` are the first run's,
        ``noise_std`` is pooled over the runs (sample-weighted variances), and ``runs`` holds
        every run's own window, noise, residual RMS and initial states.
        """
        est = self.estimate
        idx = [est.names.index(n) for n in self.unknowns]
        cov = est.covariance[np.ix_(idx, idx)]
        out = {
            'model': self.model.name,
            'method': est.method,
            'parameters': {n: {'value': float(est.values[i]), 'std': float(est.std[i])}
                           for n, i in zip(self.unknowns, idx)},
            'covariance': {'names': list(self.unknowns),
                           'matrix': [[float(c) for c in row] for row in cov]},
            'correlation': [[float(c) for c in row] for row in est.correlation[np.ix_(idx, idx)]],
            'noise_std': [float(s) for s in est.noise_std],
            'channels': list(est.channel_names),
            'iterations': int(est.iterations),
            'converged': bool(est.converged),
            'message': est.message,
            'window_s': [float(self.window_s[0]), float(self.window_s[1])],
            'omega_rad_s': float(self.omega_rad_s),
            'n_samples': int(est.n_samples),
            'neg_log_likelihood': float(est.neg_log_likelihood),
            'initial_states': {n: {'value': float(v), 'std': float(s)}
                               for n, v, s in zip(est.names, est.values, est.std)
                               if n not in self.unknowns and '(t0)' in n},
            'warnings': self.warnings,
            'defaults_used': {k: float(v) for k, v in self.defaults_used.items()},
        }
        if self.adequacy is not None:
            out['adequacy'] = self.adequacy.as_json()
        # filter error also estimates noise σ's (process_noise_std, noise_std_<channel>)
        noise = {n: {'value': float(v), 'std': float(s)}
                 for n, v, s in zip(est.names, est.values, est.std)
                 if n not in self.unknowns and '(t0)' not in n}
        if noise:
            out['noise_parameters'] = noise
        if self.runs:
            out['runs'] = [run.as_json(est) for run in self.runs]
        if self.frequency_response is not None:
            out['frequency_response'] = self.frequency_response.as_json()
        return out


@dataclass
class Run:
    """One recording of a multi-run estimate and the experiments it contributed."""

    name: str
    source: str
    description: 'RunDescription'
    window_s: tuple
    omega_rad_s: float
    experiments: list[int]  # indices into Identification.experiments

    def as_json(self, estimate: Estimate) -> dict[str, Any]:
        """Return this run's section of the JSON: window, noise, residuals, initial states."""
        idx = self.experiments
        residuals = np.concatenate([estimate.residuals[i] for i in idx], axis=0)
        suffixes = [f'[{i + 1}]' for i in idx] if len(estimate.residuals) > 1 else ['']
        states = {n: {'value': float(v), 'std': float(s)}
                  for n, v, s in zip(estimate.names, estimate.values, estimate.std)
                  if '(t0)' in n and any(n.endswith(x) for x in suffixes)}
        noise = (estimate.run_noise_std[idx[0]] if estimate.run_noise_std
                 else estimate.noise_std)
        return {
            'name': self.name,
            'bag': self.source,
            'config': self.description.path,
            'window_s': [float(self.window_s[0]), float(self.window_s[1])],
            'omega_rad_s': float(self.omega_rad_s),
            'n_samples': int(residuals.shape[0]),
            'noise_std': [float(v) for v in noise],
            'residual_rms': [float(v) for v in np.sqrt(np.mean(residuals**2, axis=0))],
            'initial_states': states,
        }


def rotor_constants(description: 'RunDescription') -> RotorConstants:
    """Return the RotorConstants of a run description's ``rotor`` block."""
    rotor = description.rotor
    return RotorConstants(n_blades=int(rotor.blades), advance_ratio=float(rotor.advance_ratio),
                          flap_frequency=float(rotor.flap_frequency),
                          tip_loss=float(rotor.tip_loss),
                          pitch_flap_coupling=float(getattr(rotor, 'pitch_flap_coupling', 0.0)))


def model_for(description: 'RunDescription', **options: Any) -> RotorModel:
    """Return the identification model a run description names, in radians."""
    rotor = rotor_constants(description)
    measurement = description.measurement or DEFAULT_MEASUREMENT[description.model]
    if description.model != 'single_blade':
        options.setdefault('outputs', measurement)
    if description.model == 'multiblade_wake':
        options.setdefault('inflow', getattr(description, 'inflow', None) or 'cyclic')
    elif getattr(description, 'inflow', None):
        raise IdentificationError('inflow applies to the wake model only, not '
                                  f'{description.model}')
    collective = ('delta' if 'delta' in description.unknowns or 'delta' in description.known
                  else 'theta0')
    try:
        return build_model(description.model, rotor, collective=collective, angle_unit='rad',
                           **options)
    except ValueError as err:
        raise IdentificationError(f'{description.model} for this rotor: {err}') from None


def given_values(description: 'RunDescription', model: RotorModel) -> dict[str, float]:
    """Return the description's ``known`` values as the model's parameters (γ → A: wake)."""
    known = lock_number_from_known(description.known, model)
    return {k: v for k, v in known.items() if k in model.parameter_names}


def parameter_defaults(description: 'RunDescription', model: RotorModel,
                       collective: float | None = None,
                       collective_source: str = 'the mean measured collective pitch',
                       given: Iterable[str] = ()) -> tuple[dict[str, float], dict[str, str]]:
    """
    Model parameters neither identified nor given in ``known``, with the value used for them.

    Returns (values, sources): name -> value and name -> where the value comes from. θ0 is
    ``collective`` when given (identify: the measured mean collective pitch), else the model's
    nominal value, as is every other parameter. ``given`` names further parameters the caller
    has values for (the plan's ``guess``). These values change the answer, so every consumer
    names them (a warning and the JSON key ``defaults_used``).
    """
    known = set(given_values(description, model)) | set(given)
    values, sources = {}, {}
    for par in model.parameters:
        if par.name in known or par.name in description.unknowns:
            continue
        if par.name == 'theta0' and collective is not None:
            values[par.name] = float(collective)
            sources[par.name] = collective_source
        else:
            values[par.name] = float(par.nominal)
            sources[par.name] = "the library's nominal value"
    return values, sources


def defaults_warning(values: Mapping[str, float], sources: Mapping[str, str]) -> str | None:
    """One warning naming every default taken, or None."""
    if not values:
        return None
    listed = ', '.join(f'{name} = {values[name]:.6g} ({sources[name]})' for name in values)
    return (f'not identified and not given in known: {listed}; the estimates depend on '
            f'{"this value" if len(values) == 1 else "these values"}: give the true '
            f'{"value" if len(values) == 1 else "values"} under known: in the run description, '
            'or list them among the unknowns')


def _known_values(description, model, record):
    """Known values plus the defaults taken (name -> value), and those defaults' sources."""
    collective = float(np.mean(_pitch_input(record)(record.t)[:, 0]))
    defaults, sources = parameter_defaults(description, model, collective=collective)
    return {**given_values(description, model), **defaults}, defaults, sources


def defaults_for(record: 'Record', description: 'RunDescription',
                 window_s: Sequence[float] | None = None
                 ) -> tuple[dict[str, float], dict[str, str]]:
    """
    Return the defaults (name -> value, name -> source) an identification of ``record`` takes.

    The same values :func:`identify` fits with (θ0 from the mean pitch over the window ± one
    revolution), for commands that report them without running identify themselves (diagnose).
    """
    window_s = tuple(window_s or description.window_s)
    model = model_for(description)
    _, defaults, sources = _known_values(description, model, _near_window(record, window_s))
    return defaults, sources


def check_values(description: 'RunDescription', model: RotorModel, values: Mapping[str, float],
                 what: str) -> None:
    """
    Check parameter values against the model's physical ranges before any fitting.

    A value outside them (a known γ of 1e300, a guess in degrees) would overflow the simulation
    or pull the fit to nonsense; the error names the key and its line.
    """
    for name, value in values.items():
        par = model.parameter(name)
        if not (math.isfinite(value) and par.lower <= value <= par.upper):
            line = description.lines.get((what, name)) if hasattr(description, 'lines') else None
            where = f'{description.path}:{line}: ' if line else f'{description.path}: '
            raise IdentificationError(
                f'{where}{what}.{name} = {value:g} is outside the physical range '
                f'[{par.lower:g}, {par.upper:g}] {par.unit} of {model.name}; check its value '
                'and unit')


def _pitch_input(record):
    return SampledInput.from_blade_pitch(record.t, record.blade_pitch)


def _near_window(record, window_s):
    """Return the record cut to the window plus one revolution either side."""
    margin = 2.0 * math.pi / max(record.omega_mean, 1e-9)
    return record.window(max(window_s[0] - margin, float(record.time_s[0])),
                         min(window_s[1] + margin, float(record.time_s[-1])))


def experiments_from_record(record: 'Record', description: 'RunDescription',
                            model: RotorModel | None = None,
                            window_s: Sequence[float] | None = None) -> list[Experiment]:
    """Experiments (one per modelled blade for single_blade, else one) over the window."""
    model = model or model_for(description)
    window_s = tuple(window_s or description.window_s)
    part = record.window(*window_s)
    if len(part) < 3:
        raise IdentificationError(
            f'the window {window_s[0]:.4g}-{window_s[1]:.4g} s holds {len(part)} samples; '
            'identification needs a window of at least a few samples (widen window_s)')
    inputs = _pitch_input(_near_window(record, window_s))
    initial_state = description.initial_state
    if model.name == 'single_blade':
        rotor = model.rotor
        collective = model.collective
        runs = []
        for blade in range(1, record.n_blades + 1):
            blade_model = build_model('single_blade', rotor, collective=collective,
                                      angle_unit='rad', blade=blade)
            runs.append(Experiment(blade_model, inputs, part.t,
                                   blade_model.observe_blades(part.t, part.blade_flap),
                                   initial_state=initial_state, name=f'blade_{blade}'))
        return runs
    return [Experiment(model, inputs, part.t, model.observe_blades(part.t, part.blade_flap),
                       initial_state=initial_state, name='run')]


def _start_candidates(model, unknowns, guess):
    """Yield starting points: the guess, and each unknown scaled by 1/2 and 2 (a grid)."""
    base = {n: guess[n] for n in unknowns}
    scales = (0.5, 1.0, 2.0)
    for combo in itertools.product(scales, repeat=len(unknowns)):
        yield {n: base[n] * s for n, s in zip(unknowns, combo)}


def starting_values(record: 'Record', description: 'RunDescription', model: RotorModel,
                    experiments: Sequence[Experiment], known: Mapping[str, float] | None,
                    multi_start: bool = True) -> dict[str, float]:
    """
    Return starting values: the description's guess, or the best of a grid of starts.

    The report starts from guesses 20-50 % off. A test stand's rotor may be further off the
    nominal values, so unless the description gives ``initial_guess`` for every unknown the
    cost (with initial states fitted by linear least squares) is evaluated on a 3^k grid around
    the nominal values and the best point starts Gauss-Newton.
    """
    unknowns = list(description.unknowns)
    guess = {n: model.parameter(n).nominal for n in unknowns}
    if 'theta0' in unknowns:
        guess['theta0'] = float(np.mean(_pitch_input(record)(record.t)[:, 0])) or guess['theta0']
    guess.update({k: v for k, v in description.initial_guess.items() if k in guess})
    if not multi_start or all(n in description.initial_guess for n in unknowns):
        return guess
    best, best_cost = guess, math.inf
    for cand in _start_candidates(model, unknowns, guess):
        try:
            est = fit_output_error(experiments, unknowns, guess=cand, known=known, max_iter=0)
        except (IdentificationError, np.linalg.LinAlgError, FloatingPointError):
            continue
        if est.neg_log_likelihood < best_cost:
            best, best_cost = cand, est.neg_log_likelihood
    return best


def identify(record: 'Record', description: 'RunDescription', method: str | None = None,
             progress: Progress | None = None, window_s: Sequence[float] | None = None,
             multi_start: bool = True, max_iter: int = 50, filter_bounds: str = 'marginal',
             step_tol: float | None = None, check_adequacy: bool = True,
             model: RotorModel | None = None) -> Identification:
    """
    Identify the run description's unknowns from a record.

    Parameters
    ----------
    record : rotor_id.io.record.Record
        The recorded run (radians, seconds).
    description : rotor_id.io.run_description.RunDescription
        What to identify: model, unknowns, window.
    method : str, optional
        'output-error' (default) | 'filter-error' | 'equation-error'.
    progress : callable, optional
        Called with a dict per iteration (see fit_output_error).
    window_s : tuple, optional
        Window (s after the first sample) overriding the description's.
    multi_start : bool
        Search a coarse grid of starting values unless the description gives them all.
    max_iter : int
        Most iterations of the estimator.
    filter_bounds : {'marginal', 'conditional'}
        Filter error only: bounds integrated over the process-noise σ (default) or the
        Cramér-Rao bound at the joint ML optimum (see
        :func:`rotor_id.estimation.filter_error.fit_filter_error`).
    step_tol : float, optional
        Output error only: converged when every step is below this many Cramér-Rao σ
        (default: :func:`~rotor_id.estimation.output_error.fit_output_error`'s 1e-6).
    check_adequacy : bool
        Test the residuals (:mod:`rotor_id.adequacy`, a few ms to tens of ms). Only a caller
        that fits the same data again at once (a live growing window) may skip it.
    model : optional
        ``model_for(description)`` kept by a caller that fits the same description again and
        again (the live fits); it must not be changed by anyone while in use.

    Returns
    -------
    Identification

    """
    method = method or description.method or 'output-error'
    if method == 'frequency-response':
        return identify_frequency_response([(record, description, 'run')], progress=progress,
                                           max_iter=max_iter)
    model = model if model is not None else model_for(description)
    window_s = tuple(window_s or description.window_s)
    record = _near_window(record, window_s)
    experiments = experiments_from_record(record, description, model, window_s)
    known, defaults, sources = _known_values(description, model, record)
    unknowns = list(description.unknowns)
    if model.name == 'multiblade_wake' and 'gamma' in unknowns:
        raise IdentificationError('the wake model is identified in A = γB⁴/8 (Ch.2 eq. 27); '
                                  'list A instead of gamma among the unknowns')
    check_values(description, model, given_values(description, model), 'known')
    check_values(description, model, {k: v for k, v in description.initial_guess.items()
                                      if k in model.parameter_names}, 'initial_guess')
    with np.errstate(over='ignore', invalid='ignore', divide='ignore'):
        guess = starting_values(record, description, model, experiments, known, multi_start)
        estimate = _fit_guarded(method, experiments, unknowns, guess, known, description,
                                model, progress, max_iter, filter_bounds, step_tol)
    part = record.window(*window_s)
    notes = [w for w in [defaults_warning(defaults, sources)] if w]
    ident = Identification(estimate=estimate, model=experiments[0].model, experiments=experiments,
                           description=description, window_s=window_s,
                           omega_rad_s=part.omega_mean, unknowns=unknowns,
                           defaults_used=defaults, notes=notes)
    if check_adequacy:
        ident.adequacy = adequacy_of(ident, record)
    return ident


def adequacy_of(ident: Identification, record: 'Record') -> 'Adequacy':
    """
    Return the residual-adequacy check (:mod:`rotor_id.adequacy`) of a one-record identification.

    ``identify`` runs it unless told not to; the live identifier runs it on its final estimate
    after publishing it, off the latency path.
    """
    from rotor_id import adequacy as adequacy_check   # scipy.fft: loaded when checked
    part = record.window(*ident.window_s)
    return adequacy_check.check(ident.estimate, ident.experiments,
                                [(part.blade_flap, part.time_s)] * len(ident.experiments))


def _fit_guarded(method, experiments, unknowns, guess, known, description, model, progress,
                 max_iter, filter_bounds, step_tol, noise_std=None):
    """Run the estimator; a non-finite simulation or iterate becomes an error naming its cause."""
    last = {}

    def watch(info):
        last.update(zip(info['names'], info['values']))
        # the caller's answer (STOP: end after this iteration) goes back to the estimator
        return progress(info) if progress is not None else None
    try:
        estimate = _fit(method, experiments, unknowns, guess, known, description, model,
                        watch, max_iter, filter_bounds, step_tol, noise_std)
    except (OverflowError, FloatingPointError, np.linalg.LinAlgError) as err:
        raise IdentificationError(_divergence_message(err, unknowns, last or guess, model,
                                                      description)) from None
    values = dict(zip(estimate.names, estimate.values))
    if not all(math.isfinite(values[n]) for n in unknowns) or \
            not np.all(np.isfinite(np.concatenate([np.ravel(f) for f in estimate.fitted]))):
        raise IdentificationError(_divergence_message(None, unknowns, values, model,
                                                      description))
    return estimate


def _divergence_message(err, unknowns, values, model, description):
    rotor = description.rotor
    shown = ', '.join(f'{n} = {float(values[n]):.4g}' for n in unknowns if n in values)
    cause = f' ({type(err).__name__}: {err})' if err is not None else ''
    return (f'the simulation of {model.name} became non-finite{cause} at {shown or "the start"} '
            f'with rotor.flap_frequency = {rotor.flap_frequency:g}, advance_ratio = '
            f'{rotor.advance_ratio:g}, tip_loss = {rotor.tip_loss:g}: the iterate of '
            f'{", ".join(unknowns)} diverged; give initial_guess values near the truth, fix '
            'known values, or shorten window_s')


def _fit(method, experiments, unknowns, guess, known, description, model, progress,
         max_iter, filter_bounds, step_tol, noise_std=None):
    noise = description.noise_std_rad
    if noise_std is None and noise is not None:
        noise_std = channel_noise(model, float(noise))
    if method == 'output-error':
        tolerance = {} if step_tol is None else {'step_tol': step_tol}
        estimate = fit_output_error(experiments, unknowns, guess=guess, known=known,
                                    noise_std=noise_std, progress=progress, max_iter=max_iter,
                                    **tolerance)
    elif method == 'filter-error':
        from rotor_id.estimation.filter_error import fit_filter_error
        estimate = fit_filter_error(experiments, unknowns, guess=guess, known=known,
                                    noise_std=noise_std, progress=progress, max_iter=max_iter,
                                    bounds=filter_bounds)
    elif method == 'equation-error':
        from rotor_id.estimation.equation_error import fit_equation_error_experiments
        estimate = fit_equation_error_experiments(experiments, unknowns, guess=guess,
                                                  known=known, progress=progress)
    else:
        raise IdentificationError(f'unknown method {method!r}; use output-error, '
                                  'filter-error or equation-error')
    return estimate


#: What the runs of one multi-run estimate must agree on (they share the parameters).
SHARED_KEYS = ('model', 'rotor', 'unknowns', 'known', 'measurement')


def check_runs_agree(descriptions: Sequence['RunDescription'], names: Sequence[str]) -> None:
    """Raise IdentificationError unless the run descriptions agree on :data:`SHARED_KEYS`."""
    first = descriptions[0]
    for description, name in zip(descriptions[1:], names[1:]):
        for key in SHARED_KEYS:
            a, b = getattr(first, key), getattr(description, key)
            if a != b:
                raise IdentificationError(
                    f'runs {names[0]} and {name} disagree on {key} ({a} vs {b}): runs '
                    'identified together share the model and its parameters; give them the '
                    'same ' + key + ' or identify them separately')


def _shared_model(description):
    """Return the model and unknowns of runs identified together (A, not γ, for the wake)."""
    model = model_for(description)
    unknowns = list(description.unknowns)
    if model.name == 'multiblade_wake' and 'gamma' in unknowns:
        raise IdentificationError('the wake model is identified in A = γB⁴/8 (Ch.2 eq. 27); '
                                  'list A instead of gamma among the unknowns')
    return model, unknowns


def identify_runs(runs: Runs, method: str | None = None, progress: Progress | None = None,
                  multi_start: bool = True, max_iter: int = 50,
                  step_tol: float | None = None) -> Identification:
    """
    Identify shared parameters from several recordings at once (output error).

    Every recording keeps its own window, its own initial states and its own measurement-noise
    covariance (estimated from its residuals unless its description gives
    ``noise_std_rad``); the model parameters are one vector for all (report Ch.2, several
    transients in one estimate; the information of the runs adds, Ch.3).

    Parameters
    ----------
    runs : list of (record, description, name)
        The recordings with their run descriptions and a name for messages and the JSON.
    method, progress, multi_start, max_iter, step_tol
        As :func:`identify` (only 'output-error' estimates per-run noise).

    Returns
    -------
    Identification
        With ``runs`` describing each recording's part.

    """
    if not runs:
        raise IdentificationError('no recording to identify from')
    records, descriptions, names = (list(x) for x in zip(*runs))
    if len(set(names)) != len(names):
        names = [f'{n}#{i + 1}' for i, n in enumerate(names)]
    check_runs_agree(descriptions, names)
    methods = {method or d.method or 'output-error' for d in descriptions}
    if methods != {'output-error'}:
        raise IdentificationError(
            f'several recordings are identified together by output error only (asked: '
            f'{", ".join(sorted(methods))}); drop method from the run descriptions or use '
            '--method output-error')
    description = descriptions[0]
    model, unknowns = _shared_model(description)
    experiments: list[Experiment]
    parts: list[Run]
    experiments, parts, noise_std, known, measured = [], [], [], None, []
    for index, (record, desc, name) in enumerate(zip(records, descriptions, names)):
        window_s = tuple(desc.window_s)
        near = _near_window(record, window_s)
        run_known, run_defaults, sources = _known_values(desc, model, near)
        if known is None:
            known, defaults = run_known, run_defaults
        elif set(run_known) != set(known) or any(
                not math.isclose(run_known[k], known[k], rel_tol=1e-3, abs_tol=1e-5)
                for k in known):
            raise IdentificationError(
                f'runs {names[0]} and {name} hold different fixed values '
                f'({known} vs {run_known}; theta0 comes from the mean pitch when not given): '
                'runs identified together share every parameter; make it an unknown or '
                'identify them separately')
        first = len(experiments)
        for exp in experiments_from_record(near, desc, model, window_s):
            label = name if exp.name == 'run' else f'{name}/{exp.name}'
            experiments.append(replace(exp, name=label, noise_group=index))
            noise = desc.noise_std_rad
            noise_std.append(None if noise is None else channel_noise(model, float(noise)))
        parts.append(Run(name=name, source=record.source, description=desc, window_s=window_s,
                         omega_rad_s=near.window(*window_s).omega_mean,
                         experiments=list(range(first, len(experiments)))))
        windowed = near.window(*window_s)
        measured += [(windowed.blade_flap, windowed.time_s)] * (len(experiments) - first)
    check_values(description, model, given_values(description, model), 'known')
    with np.errstate(over='ignore', invalid='ignore', divide='ignore'):
        guess = starting_values(records[0], description, model, experiments, known,
                                multi_start)
        estimate = _fit_guarded('output-error', experiments, unknowns, guess, known,
                                description, model, progress, max_iter, 'marginal', step_tol,
                                noise_std=noise_std)
    from rotor_id import adequacy as adequacy_check   # scipy.fft: loaded when checked
    return Identification(estimate=estimate, model=experiments[0].model,
                          experiments=experiments, description=description,
                          window_s=parts[0].window_s, omega_rad_s=parts[0].omega_rad_s,
                          unknowns=unknowns, runs=parts, defaults_used=defaults,
                          notes=[w for w in [defaults_warning(defaults, sources)] if w],
                          adequacy=adequacy_check.check(estimate, experiments, measured))


def channel_noise(model: RotorModel, blade_noise: float) -> float | np.ndarray:
    """
    Noise σ of the model's channels for independent per-blade flap noise σ, any N.

    A channel y_i = Σ_k C_ik β_k (the model's :meth:`channel_matrix`: the blade itself, a
    multiblade coordinate or report eq. 30) has σ_i = σ·sqrt(Σ_k C_ik²), averaged over a
    revolution (for the coordinates and eq. 30 it does not depend on the azimuth).
    """
    t = 2.0 * math.pi * np.arange(64) / 64
    C = model.channel_matrix(t)
    sigma = blade_noise * np.sqrt(np.mean(np.sum(C * C, axis=2), axis=0))
    return float(sigma[0]) if np.allclose(sigma, sigma[0], rtol=1e-12) else sigma


# ------------------------------------------------------------------------------------------------
# Frequency responses (docs/frequency_response.md)
# ------------------------------------------------------------------------------------------------

#: A point's transient error is worth a warning when it exceeds this many random errors.
TRANSIENT_ERROR_RANDOM_ERRORS = 2.0


@dataclass
class ModelOverlay:
    """A model's dFRF beside an estimate: its transfer function and as the estimate sees it."""

    name: str
    parameters: dict
    source: str | None
    transfer_function: DirectionalResponse  # on a fine grid
    at_points: np.ndarray              # transfer function at the estimate's points
    as_estimated: np.ndarray           # the same estimator applied to the model's simulation
    bands: list['BandCost']            # against as_estimated
    cost: float
    bands_transfer_function: list['BandCost']  # against the transfer function
    cost_transfer_function: float

    @property
    def sideband_ratios(self) -> dict[int, float]:
        """{n: largest |H_n|/|H_0| over the band} of a periodic model's sidebands (n per rev)."""
        tf = self.transfer_function
        scale = np.maximum(np.abs(tf.principal), 1e-300)
        return {n: float(np.max(np.abs(h) / scale)) for n, h in sorted(tf.sidebands.items())
                if np.max(np.abs(h) / scale) > 1e-6}

    @property
    def transient_error(self) -> np.ndarray:
        """|as estimated / transfer function − 1|: the estimate's deterministic error here."""
        return np.abs(self.as_estimated / self.at_points - 1.0)

    def as_json(self) -> dict[str, Any]:
        """Return the overlay's JSON: parameters, J per band against both model curves."""
        return {
            'model': self.name, 'parameters': {k: float(v) for k, v in self.parameters.items()},
            'parameters_from': self.source,
            'cost_J': float(self.cost),
            'bands': [b.as_json() for b in self.bands],
            'cost_J_transfer_function': float(self.cost_transfer_function),
            'bands_transfer_function': [b.as_json() for b in self.bands_transfer_function],
            'transient_error': [float(v) for v in self.transient_error],
            'sidebands': {str(n): r for n, r in self.sideband_ratios.items()},
            'model_magnitude': [float(v) for v in np.abs(self.at_points)],
            'model_phase_deg': [float(v) for v in np.degrees(np.angle(self.at_points))],
        }


@dataclass
class FrequencyAnalysis:
    """The dFRF of one or more runs, and optionally a model's beside it."""

    estimate: 'FrequencyResponse'
    sweeps: list['Sweep']
    overlay: ModelOverlay | None = None
    warnings: list = field(default_factory=list)

    def as_json(self) -> dict[str, Any]:
        """Return the JSON of ``rotor-id frequency-response``."""
        out = self.estimate.as_json()
        out['windows_s'] = [list(s.window_s) for s in self.sweeps]
        out['stirring_band_per_rev'] = [list(s.band) for s in self.sweeps]
        if self.overlay is not None:
            out['model'] = self.overlay.as_json()
        out['warnings'] = list(self.warnings)
        return out


def _frequency_runs(runs, window_s=None):
    from rotor_id.estimation.frequency_response import sweep_from_record
    return [sweep_from_record(record, name, window_s) for record, _, name in runs]


def model_overlay(model: RotorModel, p: np.ndarray, sweeps: Sequence['Sweep'],
                  estimate: 'FrequencyResponse', collective: float, source: str | None,
                  points_per_side: int = 200) -> ModelOverlay:
    """Return the :class:`ModelOverlay` of ``model`` at the full parameter vector ``p``."""
    from rotor_id.estimation.frequency_response import band_costs, estimated_model_response
    from rotor_id.physics.models import directional_frequency_response
    f = estimate.frequency_per_rev
    # (hi is None only with lo, which the filter drops)
    sides = [np.linspace(lo, hi, points_per_side)  # type: ignore[arg-type]
             for lo, hi in
             ((f[f < 0].min(), f[f < 0].max()) if np.any(f < 0) else (None, None),
              (f[f > 0].min(), f[f > 0].max()) if np.any(f > 0) else (None, None))
             if lo is not None]
    fine = directional_frequency_response(model, p, np.concatenate(sides))
    at_points = directional_frequency_response(model, p, f).principal
    as_estimated, _ = estimated_model_response(model, p, sweeps, estimate.spectra, collective)
    bands, cost = band_costs(estimate, as_estimated)
    bands_tf, cost_tf = band_costs(estimate, at_points)
    return ModelOverlay(name=model.name, parameters=dict(zip(model.parameter_names, p)),
                        source=source, transfer_function=fine, at_points=at_points,
                        as_estimated=as_estimated, bands=bands, cost=cost,
                        bands_transfer_function=bands_tf, cost_transfer_function=cost_tf)


def overlay_warnings(estimate: 'FrequencyResponse', overlay: ModelOverlay) -> list[str]:
    """Say where the estimate's transient error exceeds its random error, with the figures."""
    from rotor_id.estimation.frequency_response import ACCEPTABLE_COST, COHERENCE_MIN
    out = []
    use = estimate.usable(COHERENCE_MIN)
    error = overlay.transient_error
    bad = use & (error > TRANSIENT_ERROR_RANDOM_ERRORS * estimate.random_error) & (error > 0.01)
    if np.any(bad):
        out.append(
            f'at {int(np.sum(bad))} of {int(np.sum(use))} usable points the estimate differs '
            f'from the transfer function of the model by up to {100 * error[bad].max():.0f} % '
            'for this record alone (the stirring is too short or is cut off by the end of the '
            'record, so the response has not died out): compare the data with the model '
            'through the same estimate (J = '
            f'{overlay.cost:.3g}), not with its transfer function (J = '
            f'{overlay.cost_transfer_function:.3g}); a longer sweep ending in trim removes it')
    if math.isfinite(overlay.cost) and overlay.cost > ACCEPTABLE_COST:
        worst = max(overlay.bands, key=lambda b: b.cost)
        out.append(f'the model departs from the data: J = {overlay.cost:.3g} > '
                   f'{ACCEPTABLE_COST:g} (CIFER), worst in {worst.low:+.3g}..{worst.high:+.3g} '
                   f'per rev (J = {worst.cost:.3g})')
    return out


def frequency_analysis(runs: Runs, window_s: Sequence[float] | None = None,
                       parameters: Mapping[str, float] | None = None,
                       source: str | None = None) -> FrequencyAnalysis:
    """
    Estimate the dFRF of ``runs`` [(record, description, name)], with the model overlaid.

    ``parameters`` (name -> value) are the model's values to draw (from an identify JSON or the
    command line); without them the run description's known values and guesses, else the
    nominal values (θ0: the mean measured collective pitch). None of the runs' models needs
    β_I, β_II to estimate; without them (a single blade, N = 2) no model is drawn.
    """
    from rotor_id.estimation.frequency_response import estimate_frequency_response
    sweeps = _frequency_runs(runs, window_s)
    estimate = estimate_frequency_response(sweeps)
    analysis = FrequencyAnalysis(estimate=estimate, sweeps=sweeps)
    record, description, _ = runs[0]
    model = model_for(description)
    if 'beta_I' not in model.state_names or 'beta_II' not in model.state_names:
        analysis.warnings.append(f'{model.name} has no fixed-frame cyclic flap states: no '
                                 'model drawn')
        return analysis
    known, defaults, sources = _known_values(description, model, record)
    values = {**known, **description.initial_guess}
    if parameters:
        unknown = [n for n in parameters if n not in model.parameter_names]
        if unknown:
            raise IdentificationError(f'{", ".join(unknown)}: not parameters of {model.name} '
                                      f'(its parameters: {", ".join(model.parameter_names)})')
        values.update(parameters)
    else:
        source = source or 'the run description (known, initial_guess; else nominal values)'
    check_values(description, model, {k: v for k, v in values.items()
                                      if k in model.parameter_names}, 'parameters')
    p = model.parameter_vector({k: v for k, v in values.items() if k in model.parameter_names})
    collective = float(np.mean(_pitch_input(record)(record.t)[:, 0]))
    analysis.overlay = model_overlay(model, p, sweeps, estimate, collective, source)
    analysis.warnings += overlay_warnings(estimate, analysis.overlay)
    return analysis


@dataclass
class FrequencyIdentification:
    """What ``identify --method frequency-response`` fitted: the dFRF and the J fit."""

    analysis: FrequencyAnalysis
    fit: 'FrequencyFit'

    def as_json(self) -> dict[str, Any]:
        """Return J, points, χ²/dof and the windows of the frequency-domain fit."""
        return {'cost_J': float(self.fit.cost), 'points': int(self.fit.points),
                'chi2_per_dof': float(self.fit.chi2_per_dof),
                'windows_s': [list(s.window_s) for s in self.analysis.sweeps],
                'noise_bins': int(self.analysis.estimate.noise_bins)}


def identify_frequency_response(runs: Runs, progress: Progress | None = None, max_iter: int = 40,
                                window_s: Sequence[float] | None = None) -> Identification:
    """
    Identify the run description's unknowns by CIFER's J on the dFRF (docs/frequency_response.md).

    ``runs``: [(record, description, name)]. The dFRF uses each record's whole stirring test
    (``window_s`` overrides it); the result is verified in the time domain over each run
    description's ``window_s`` (output error evaluated at the frequency-domain values, no
    iteration), which gives the residuals, the fitted outputs and the noise of the JSON.
    """
    from rotor_id.estimation.frequency_response import as_estimate, fit_frequency_response
    records, descriptions, names = (list(x) for x in zip(*runs))
    check_runs_agree(descriptions, names)
    description = descriptions[0]
    model, unknowns = _shared_model(description)
    if 'beta_I' not in model.state_names or 'beta_II' not in model.state_names:
        raise IdentificationError(f'{model.name} has no fixed-frame cyclic flap (beta_I, '
                                  'beta_II): identify it with --method output-error')
    check_values(description, model, given_values(description, model), 'known')
    known, defaults, sources = _known_values(description, model, records[0])
    guess = {n: model.parameter(n).nominal for n in unknowns}
    if 'theta0' in unknowns:
        guess['theta0'] = known.get('theta0', float(np.mean(
            _pitch_input(records[0])(records[0].t)[:, 0])))
    guess.update({k: v for k, v in description.initial_guess.items() if k in guess})
    known = {k: v for k, v in known.items() if k not in unknowns}
    collective = float(np.mean(_pitch_input(records[0])(records[0].t)[:, 0]))
    from rotor_id.estimation.frequency_response import estimate_frequency_response
    sweeps = _frequency_runs(runs, window_s)
    estimate = estimate_frequency_response(sweeps)
    analysis = FrequencyAnalysis(estimate=estimate, sweeps=sweeps)
    # a constant input is not in a frequency response: θ0 is held at the measured collective
    # for the frequency-domain fit and fitted alone in the time domain afterwards
    fitted = [n for n in unknowns if n != 'theta0']
    held = {n: guess[n] for n in unknowns if n not in fitted}
    with np.errstate(over='ignore', invalid='ignore', divide='ignore'):
        fit = fit_frequency_response(model, sweeps, estimate, fitted,
                                     {n: guess[n] for n in fitted}, {**known, **held},
                                     collective, max_iter=max_iter, progress=progress)
    values = {**held, **dict(zip(fitted, fit.values))}
    analysis.overlay = model_overlay(model, model.parameter_vector({**known, **values}),
                                     sweeps, estimate, collective, 'the frequency-domain fit')
    experiments: list[Experiment]
    parts: list[Run]
    experiments, parts = [], []
    for index, (record, desc, name) in enumerate(runs):
        near = _near_window(record, tuple(desc.window_s))
        first = len(experiments)
        for exp in experiments_from_record(near, desc, model, tuple(desc.window_s)):
            experiments.append(replace(exp, noise_group=index))
        parts.append(Run(name=name, source=record.source, description=desc,
                         window_s=tuple(desc.window_s),
                         omega_rad_s=near.window(*desc.window_s).omega_mean,
                         experiments=list(range(first, len(experiments)))))
    notes = [w for w in [defaults_warning(defaults, sources)] if w]
    with np.errstate(over='ignore', invalid='ignore', divide='ignore'):
        if held:
            alone = fit_output_error(experiments, list(held), guess=held,
                                     known={**known, **values})
            values.update({n: alone.value(n) for n in held})
            notes.append(f'{", ".join(held)}: a constant input does not enter a frequency '
                         'response; fitted alone by output error over window_s with the other '
                         'parameters at their frequency-domain values (its σ is the joint '
                         'Cramér-Rao bound there)')
        time_domain = fit_output_error(experiments, unknowns, guess=values, known=known,
                                       max_iter=0)
    est = as_estimate(fit, time_domain)
    if fit.chi2_per_dof > 4.0:
        notes.append(f'the frequency-domain fit leaves χ²/dof = {fit.chi2_per_dof:.3g} of its '
                     'random errors: the bounds are widened by that; the model or the sweep '
                     'does not explain the data within the random error of the estimate')
    return Identification(estimate=est, model=model, experiments=experiments,
                          description=description, window_s=tuple(description.window_s),
                          omega_rad_s=parts[0].omega_rad_s, unknowns=unknowns,
                          runs=parts if len(runs) > 1 else [], defaults_used=defaults,
                          notes=notes, frequency_response=FrequencyIdentification(analysis, fit))
