"""
Build and fit the catalogue's candidates on the baseline's data.

A candidate is an id of the issue (``sensor_lag``, ``dynamic_inflow`` …), the augmented model
of :mod:`rotor_id.physics.augmented` for every run of the baseline, the unknowns (the
baseline's plus the augmentation's) and its starting values (the baseline estimate plus the
augmentation's neutral values). Fitting is the same output-error ML as the baseline
(:func:`rotor_id.estimation.output_error.fit_output_error`), so likelihoods, Cramér-Rao bounds
and residuals compare directly. ``process_noise`` (random inflow) is fitted by filter error
(:mod:`rotor_id.diagnosis.noisy`).
"""

from dataclasses import dataclass, field
from dataclasses import replace as _replace
import math
import sys
import time
import uuid

import numpy as np

from rotor_id.diagnosis.policy import DEFAULT_POLICY
from rotor_id.estimation.output_error import (
    augment_runs, evaluate, Experiment, ExtendedInput, FIT_FAILURES, fit_initial_states,
    fit_output_error, IdentificationError, Problem, split_values, STOP,
    weighted_products)
from rotor_id.estimation.simulate import DEFAULT_MAX_STEP
from rotor_id.estimation.validation import score_statistic
from rotor_id.physics import augmented as aug
from rotor_id.physics.aerodynamics import flap_damping
from rotor_id.pipeline import experiments_from_record, model_for

#: Every effect of the catalogue, in the order they are tried.
EFFECTS = ('dynamic_inflow', 'periodic_coefficients', 'sensor_lag', 'time_delay',
           'sensor_bias', 'blade_dissimilarity', 'process_noise', 'flap_frequency',
           'cubic_stiffness', 'pitch_flap_coupling', 'pitch_actuator_lag', 'sensor_gain',
           'azimuth_offset')
#: Random inflow: the one effect fitted by filter error.
NOISE = 'process_noise'

#: Effects that a recording cannot tell apart at small size (the same physics to first
#: order): a first-order sensor lag τ and a pure delay d = τ give the same flap to O(τ²); a
#: cubic spring κβ³ about the steady coning β0 is a flap-frequency change ΔP² = 3κβ0² to
#: first order in the flapping about trim.
#: A pitch-actuator lag τ_a is the same delay of the flap behind the pitch to first order,
#: and pitch-flap coupling (δ3) is a flap-stiffness change, exactly so at μ = 0 without a wake.
EQUIVALENT = {effect: tuple(e for e in group if e != effect)
              for group in (('time_delay', 'sensor_lag', 'pitch_actuator_lag'),
                            ('flap_frequency', 'cubic_stiffness', 'pitch_flap_coupling'))
              for effect in group}
#: Pairs of :data:`EQUIVALENT` that are one physics in hover only. In forward flight the
#: pitch moment coefficient is periodic, m_θ = (B⁴ + B²μ²)/4 + (2/3)B³μ sin ψ − (B²μ²/4) cos 2ψ:
#: δ3 adds a once-per-rev stiffness (2/3)B³μ / ((B⁴+B²μ²)/4) = 0.94 of its mean at μ = 0.4
#: (B = 0.97), which a flap-frequency change has not; a cubic spring linearised about the trim
#: flapping β0 + β1c cos ψ + β1s sin ψ adds 6κβ0(β1c cos ψ + β1s sin ψ) beside 3κβ0²; and
#: the rotor is time-varying, so a lag of the blade pitch no longer commutes with the rotor to
#: become a lag of the flap reading. Each differs at first order in μ: in a forward-flight
#: record they are separate candidates (the confound check, record by record, still says when
#: the data cannot tell them apart).
HOVER_ONLY = frozenset(frozenset(pair) for pair in (
    ('flap_frequency', 'pitch_flap_coupling'), ('flap_frequency', 'cubic_stiffness'),
    ('cubic_stiffness', 'pitch_flap_coupling'), ('pitch_actuator_lag', 'sensor_lag'),
    ('pitch_actuator_lag', 'time_delay')))


def equivalent(effect, advance_ratio=0.0):
    """
    Return the first-order equivalents of ``effect`` in a record at this advance ratio.

    :data:`EQUIVALENT` in hover; in forward flight without the :data:`HOVER_ONLY` pairs.
    """
    same = EQUIVALENT.get(effect, ())
    if advance_ratio > 0.0:
        same = tuple(e for e in same if frozenset((effect, e)) not in HOVER_ONLY)
    return same


@dataclass
class CandidateFit:
    """The outcome of fitting one candidate."""

    effect: str
    variant: str = ''
    available: bool = True
    reason: str = ''
    estimate: object = None
    model: object = None
    unknowns: list = field(default_factory=list)
    n_extra: int = 0
    parameters: dict = field(default_factory=dict)
    elapsed_s: float = 0.0
    #: {effect: its parameters {name: (value, std)}} of every effect in the fitted model
    effect_parameters: dict = field(default_factory=dict)
    #: effects fitted together with this one [(effect, variant)]
    prior: tuple = ()
    #: the catalogue ranges the fit ended with (widened where a fit stopped at one)
    bounds: dict = field(default_factory=dict)
    #: extra parameters still at a catalogue bound after widening: the likelihood is capped,
    #: so the candidate is reported but not compared
    bound_limited: list = field(default_factory=list)


def record_step(ident, tolerance):
    """
    Return the RK4 step of the diagnosis's fits: one step per sample where that is accurate.

    The baseline model at its estimate, integrated with one RK4 step per sample interval,
    must stay within ``tolerance`` of each channel's residual RMS (its noise) of the same
    model integrated at the default step; else the default step. A layer with a fast mode
    (a lag) still takes its own shorter step (:func:`build`).
    """
    longest = max(float(np.max(np.diff(exp.t))) for exp in ident.experiments)
    if longest <= DEFAULT_MAX_STEP:
        return DEFAULT_MAX_STEP
    values, known = split_values(ident.estimate, ident.unknowns)
    problem = Problem(ident.experiments, list(ident.unknowns), values, known)
    theta = _states_fitted(problem, DEFAULT_MAX_STEP)
    fine = evaluate(problem, theta, DEFAULT_MAX_STEP, sensitivities=False)
    coarse = evaluate(problem, theta, longest, sensitivities=False)
    for (residual, _, _), (other, _, _) in zip(fine, coarse):
        if residual is None:
            continue
        noise = np.sqrt(np.nanmean(residual**2, axis=0))
        if not np.all(np.nanmax(np.abs(other - residual), axis=0) <= tolerance * noise):
            return DEFAULT_MAX_STEP
    return longest


@dataclass(frozen=True)
class Setting:
    """What every candidate fit of one diagnosis shares: the record, the run and the values."""

    record: object
    description: object
    #: the baseline's estimate of the unknowns, and the known parameters
    values: dict
    unknowns: list
    known: dict
    window_s: tuple
    verbose: bool = False
    #: convergence of every candidate fit (the policy's ``fit_tolerance``)
    fit_tolerance: float = DEFAULT_POLICY.fit_tolerance
    #: the RK4 step of every fit where no layer needs a shorter one (:func:`record_step`)
    max_step: float = DEFAULT_MAX_STEP
    #: names this setting in every process it is sent to (:meth:`prepared`)
    token: str = field(default_factory=lambda: uuid.uuid4().hex, compare=False)

    @classmethod
    def of(cls, record, ident, **options):
        """Return the setting of a baseline fit (an :class:`~rotor_id.pipeline.Identification`)."""
        values, known = split_values(ident.estimate, ident.unknowns)
        return cls(record, ident.description, values, list(ident.unknowns), known,
                   tuple(ident.window_s), **options)

    def experiments(self, base_model):
        """Return the baseline model's experiments over the record's window."""
        return experiments_from_record(self.record, self.description, base_model,
                                       self.window_s)

    def prepared(self):
        """
        Return (the baseline model, its experiments), built once per process for this setting.

        Every job arrives as a copy of the setting; a model built per job computed its
        parameter-free blocks (per time grid) again each time. No fit changes them: each
        candidate wraps them in layers of its own.
        """
        key = (self.token, self.window_s)
        if _PREPARED.get('key') != key:
            base_model = model_for(self.description)
            _PREPARED.update(key=key, value=(base_model, self.experiments(base_model)))
        return _PREPARED['value']


#: this process's :meth:`Setting.prepared` (the one setting of the diagnosis under way)
_PREPARED: dict = {}


@dataclass
class Job:
    """One candidate fit on a :class:`Setting`: what a worker process needs (all picklable)."""

    setting: Setting
    effect: str
    variant: str = ''
    #: starting values of the augmented model (a bigger or smaller model's estimate)
    start: dict = None
    #: the baseline's −log L (a fit at a bound that does not beat it is not widened)
    baseline_nll: float = math.inf
    #: widened catalogue ranges {extra parameter: (lower, upper)} (see :func:`fit_candidate`)
    bounds: dict = None
    #: effects already kept, [(effect, variant)], fitted together with this one
    prior: tuple = ()


def start_values(fit):
    """Return a fit's estimated model parameters (a start for a bigger or smaller model)."""
    est = fit.estimate
    return {n: est.model_parameters[n] for n in fit.unknowns if n in est.model_parameters}


def _pitch_rates(exp, model):
    base = exp.inputs
    while isinstance(base, ExtendedInput):
        base = base.base
    rate = np.gradient(base.u, base.t, axis=0)
    return base.t, rate


def _measured_flap_cubed(record):
    def columns(exp, model):
        blades = list(model.view.blades)
        return record.t, record.blade_flap[:, [b - 1 for b in blades]] ** 3
    return columns


def applicable(effect, model_name, rotor, unknowns):
    """'' when the effect can be tried on this baseline, else the reason why not."""
    has_gamma = 'gamma' in unknowns
    if effect == 'dynamic_inflow':
        if model_name == 'multiblade_wake':
            return 'the baseline already has the dynamic wake'
        if model_name == 'single_blade':
            return 'the wake couples the blades: use a multiblade model to test it'
        if not has_gamma:
            return 'needs gamma among the unknowns (A = γB⁴/8 sets the wake forcing)'
    if effect == 'periodic_coefficients':
        if model_name != 'multiblade_constant':
            return 'the baseline already has the periodic terms (or has none at this μ)'
        if rotor.advance_ratio == 0.0:
            return 'at μ = 0 the periodic terms vanish'
    if effect == 'azimuth_offset' and rotor.advance_ratio == 0.0:
        return ('at μ = 0 the rotor is axisymmetric: an azimuth offset turns flap and pitch '
                'alike and neither the fit nor the estimates can see it')
    if effect == 'pitch_actuator_lag' and model_name == 'single_blade':
        return 'needs the blades in one model (the pitch lag acts in multiblade pitch)'
    if effect in ('sensor_bias', 'blade_dissimilarity') and model_name == 'single_blade':
        return 'needs the blades in one model (multiblade with measurement: blades)'
    if effect == 'blade_dissimilarity' and model_name != 'multiblade_wake' and not has_gamma:
        return 'needs gamma among the unknowns'
    return ''


def n_choices(effect, n_blades):
    """How many alternatives the fit chose among (the odd blade: N), for the criterion."""
    return n_blades if effect == 'blade_dissimilarity' else 1


#: The order in which effects are stacked on the rotor model when several are fitted together
#: (innermost first): the flap frequency replaces a coefficient of the rotor model itself, the
#: wake and the blade's dynamics add states to the rotor, the delay shifts the pitch seen by
#: all of them, and the sensor effects act on what the rotor's flap becomes on the way to the
#: recording.
COMPOSE_ORDER = ('periodic_coefficients', 'flap_frequency', 'pitch_flap_coupling',
                 'dynamic_inflow', 'cubic_stiffness', 'blade_dissimilarity',
                 'pitch_actuator_lag', 'pitch_delay', 'time_delay', 'sensor_lag', 'sensor_gain',
                 'sensor_bias', 'azimuth_offset')


#: The augmentation of each effect that wraps the model alone, and of each that is fed the
#: measured pitch rates θ′ as extra inputs (the delays and the actuator lag).
WRAPS = {'sensor_lag': aug.SensorLag, 'flap_frequency': aug.FlapFrequency,
         'dynamic_inflow': aug.DynamicInflow, 'pitch_flap_coupling': aug.PitchFlapCoupling,
         'azimuth_offset': aug.AzimuthOffset}
FED_PITCH_RATES = {'time_delay': aug.TimeDelay, 'pitch_delay': aug.PitchDelay,
                   'pitch_actuator_lag': aug.PitchActuatorLag}


def _augment_one(effect, variant, record, experiments, unknowns=()):
    """
    Wrap every run's model in one effect's augmentation: (runs, model).

    ``unknowns``: the fitted parameters of the baseline (a sensor bias asks whether its
    collective pitch is one). ``pitch_delay`` is the actuator lag's score test (SCREENED_AS).
    """
    if effect in WRAPS:
        return augment_runs(experiments, WRAPS[effect])
    if effect in FED_PITCH_RATES:
        return augment_runs(experiments, FED_PITCH_RATES[effect], _pitch_rates)
    if effect == 'sensor_bias':
        t_all = np.concatenate([e.t for e in experiments])
        return augment_runs(experiments, lambda m: aug.SensorBias(
            m, t_all, collective_fitted=aug.BladeView(m).model.collective in unknowns))
    if effect == 'cubic_stiffness':
        return augment_runs(experiments, aug.CubicStiffness, _measured_flap_cubed(record))
    if effect == 'blade_dissimilarity':
        blade = int((variant or 'blade_1').split('_')[1])
        return augment_runs(experiments, lambda m: aug.BladeDissimilarity(m, blade))
    if effect == 'sensor_gain':
        def gain(m):
            blades = [b - 1 for b in aug.BladeView(m).blades]
            return aug.SensorGain(m, record.t, record.blade_flap[:, blades])
        return augment_runs(experiments, gain)
    if effect == 'periodic_coefficients':
        if any(isinstance(e.model, aug.Augmented) for e in experiments):
            raise IdentificationError('periodic_coefficients replaces the rotor model and is '
                                      'stacked first')
        runs = [Experiment(aug.periodic_coefficients(exp.model), exp.inputs, exp.t, exp.y,
                           initial_state=exp.initial_state, name=exp.name)
                for exp in experiments]
        return runs, runs[0].model
    raise IdentificationError(f'unknown effect {effect!r}')


def layers(model):
    """Return the augmentation layers of a model, outermost first."""
    out = []
    while isinstance(model, aug.Augmented):
        out.append(model)
        model = model.base
    return out


def build(job, experiments):
    """
    Return (experiments, model, unknowns, extra, guess, RK4 step) of a candidate.

    The candidate is ``job.effect`` on top of the effects already kept (``job.prior``), all
    stacked in :data:`COMPOSE_ORDER` on the one rotor model. ``extra`` names the candidate's
    own extra parameters; the unknowns are the baseline's and every effect's.
    """
    setting = job.setting
    guess = dict(setting.values)
    # (no effect of its own: the model the prior effects make, e.g. a score test's)
    own = [(job.effect, job.variant)] if job.effect else []
    unknown = [e for e, _ in list(job.prior) + own if e not in COMPOSE_ORDER]
    if unknown:
        raise IdentificationError(f'{unknown[0]!r} is not an augmented model of the rotor')
    stack = sorted(list(job.prior) + own, key=lambda ev: COMPOSE_ORDER.index(ev[0]))
    runs, model = experiments, None
    for effect, variant in stack:
        runs, model = _augment_one(effect, variant, setting.record, runs, setting.unknowns)
        if job.bounds and isinstance(model, aug.Augmented):
            for exp in runs:
                exp.model.with_bounds(job.bounds)
    max_step = None
    all_extra, extra = [], []
    for layer in reversed(layers(model)):
        names = [par.name for par in layer.extra_parameters]
        all_extra += names
        if layer.effect == job.effect:
            extra = names
        for par in layer.extra_parameters:
            guess[par.name] = par.nominal
        if layer.effect in ('sensor_lag', 'pitch_actuator_lag'):
            max_step = min(layer.step(), max_step or math.inf)
    unknowns = list(setting.unknowns) + all_extra
    # a start taken from a bigger model (the backward check's refit without an effect, an
    # exchange) carries parameters this model does not have: the fit refused them, so the
    # backward check never ran
    guess.update({n: v for n, v in (job.start or {}).items() if n in unknowns})
    return runs, model, unknowns, extra, guess, max_step or setting.max_step


#: Most times a catalogue range is widened when a fit stops at it.
MAX_WIDENINGS = 2


def bound_sides(values, model, extra):
    """[(name, 'lower'|'upper')] of the extra parameters in ``values`` at a catalogue bound."""
    out = []
    for name in extra:
        layer = _layer_of(model, name)
        par = layer.parameter(name)
        value = values[name]
        tol = 1e-9 * max(1.0, abs(par.lower), abs(par.upper))
        for side, bound in (('lower', par.lower), ('upper', par.upper)):
            if abs(value - bound) <= tol and side not in layer.physical_bounds.get(name, ()):
                out.append((name, side))
    return out


def parameter_range(model, name):
    """Return (lower, upper) of an augmentation's extra parameter in a fitted model."""
    par = _layer_of(model, name).parameter(name)
    return par.lower, par.upper


def _layer_of(model, name):
    """Return the augmentation layer that owns extra parameter ``name``."""
    for layer in layers(model):
        if name in [par.name for par in layer.extra_parameters]:
            return layer
    raise KeyError(name)


def stop_at_bound(model, extra, show):
    """
    Progress callback: print, and stop a fit whose extra parameter stays at a catalogue bound.

    Two iterations there mean the data push beyond the range: the fit will either be widened
    and repeated from there or reported bound-limited, so crawling on along the bound (the
    other parameters creep, the bounded one cannot move) is wasted work.
    """
    streak = [0]

    def check(info):
        if show is not None:
            show(info)
        values = dict(zip(info['names'], info['values']))
        streak[0] = streak[0] + 1 if bound_sides(values, model, extra) else 0
        return STOP if streak[0] >= 2 else None
    return check


#: The time constant of each lag effect (not nested: τ > 0; started from several values).
LAG_PARAMETER = {'sensor_lag': 'lag_rad', 'pitch_actuator_lag': 'actuator_lag_rad'}
#: Starts of a lag or delay from its first-order equivalent's fit: {effect: {equivalent:
#: (its parameter, this effect's parameter)}}. A lag τ and a delay d = τ give the same flap to
#: O(τ²), so one's estimate is a start of the other's fit near its optimum.
_TIME = {'time_delay': 'delay_rad', **LAG_PARAMETER}
FIRST_ORDER_START = {effect: {other: (_TIME[other], mine) for other in EQUIVALENT[effect]}
                     for effect, mine in _TIME.items()}
#: The nested first-order equivalent each lag is score-tested through: the delay d = τ, at
#: d = 0, of what the lag delays: the flap reading (``time_delay``) or the blade pitch
#: (:class:`~rotor_id.physics.augmented.PitchDelay`). In hover the two delays are one model;
#: in forward flight they differ at first order in μ d, and so do the two lags.
SCREENED_AS = {'sensor_lag': 'time_delay', 'pitch_actuator_lag': 'pitch_delay'}
#: The delay parameter of each of them (distinct names: the pitch delay is tested beside a
#: fitted flap-reading delay)
DELAY_PARAMETER = {layer.effect: layer.extra_parameters[0].name
                   for layer in (aug.TimeDelay, aug.PitchDelay)}


def as_lag_variance(effect, variance):
    """Return a delay's score-test variances {name: var} under the lag ``effect``'s name."""
    delay = DELAY_PARAMETER[SCREENED_AS[effect]]
    return {LAG_PARAMETER[effect]: variance.get(delay, math.nan)}


def grid_starts(job, model, guess):
    """
    Return the starting points of an effect whose likelihood has several valleys, or None.

    The wake (gain and time constant) and a lag whose τ the job does not already start from:
    the fit starts from the most likely of them (output error :func:`_best_start`, filter
    error :func:`rotor_id.diagnosis.noisy.fit_filter`).
    """
    if job.effect == 'dynamic_inflow':
        return list(_wake_starts(model, guess))
    if job.effect in LAG_PARAMETER and LAG_PARAMETER[job.effect] not in (job.start or {}):
        # τ from the smallest admissible up
        name = LAG_PARAMETER[job.effect]
        return [{**guess, name: model.parameter(name).lower * factor}
                for factor in (1.0, 2.0, 4.0, 10.0, 30.0)]
    return None


#: The wake's neutral values: no wake (AL/τ = 0), the model it extends whatever τ (the
#: grid's middle τ = 2 to leave from).
NO_WAKE = {'AL_over_tau': 0.0, 'inv_tau': 0.5}


def _wake_starts(model, guess):
    """
    Yield starting points for the wake.

    Gains L and time constants τ; γ raised so that the quasi-steady damping γ/(1+AL) stays at
    the baseline's. (Not :data:`NO_WAKE`: the most likely start is fitted, and no wake, as
    likely as the model it extends, is often the most likely while its fit stalls where a
    wake exists; a fit that ends below that model is restarted there, :func:`fit_candidate`.)
    """
    a1 = flap_damping(1.0, model.rotor.tip_loss)           # A/γ, Ch.2 eq. 27
    gamma_b = guess['gamma']
    for L in (0.5, 1.5, 3.0):
        denominator = 1.0 - gamma_b * a1 * L
        if denominator <= 0.05:
            continue
        gamma = gamma_b / denominator
        for tau in (0.5, 2.0, 8.0):
            start = dict(guess)
            start.update(gamma=gamma, AL_over_tau=gamma * a1 * L / tau, inv_tau=1.0 / tau)
            yield start


def _states_fitted(problem, max_step):
    """Return θ at a problem's base values, the initial states fitted (y is linear in them)."""
    theta = np.concatenate([problem.p_base[problem.param_index],
                            np.zeros(len(problem.names) - len(problem.param_index))])
    return fit_initial_states(problem, theta, max_step)


def _evaluated(problem, max_step, sensitivities=True):
    """Evaluate a problem at its base values, the initial states fitted."""
    return evaluate(problem, _states_fitted(problem, max_step), max_step,
                    sensitivities=sensitivities)


def _best_start(runs, unknowns, starts, known, max_step):
    """
    Return the start of lowest −log L up to a constant, or None if none evaluates.

    With the initial states fitted and R at its ML value, each channel's mean square residual,
    −log L = ½ Σ_runs T Σ_channels log(mean r²) + const: the same ranking as the likelihood of
    a fit stopped at the start, from plain simulations (no sensitivities).
    """
    best, best_cost = None, math.inf
    for start in starts:
        try:
            results = _evaluated(Problem(runs, unknowns, start, known), max_step,
                                 sensitivities=False)
            cost = 0.5 * sum(res.shape[0] * float(np.sum(np.log(np.mean(res**2, axis=0))))
                             for res, _, _ in results)
        except FIT_FAILURES:
            continue
        if math.isfinite(cost) and cost < best_cost:
            best, best_cost = start, cost
    return best


def _printer(label, verbose):
    if not verbose:
        return None

    def show(info):
        rms = math.sqrt(float(np.mean(np.square(info['noise_std']))))
        # one write per line, so that lines of parallel workers do not interleave
        sys.stderr.write(f'  [{label}] iteration {info["iteration"]}: residual RMS '
                         f'{rms:.5g} rad, {info["elapsed"]:.1f} s\n')
        sys.stderr.flush()
    return show


def fit_runs(setting, runs, unknowns, guess, max_step, label, progress=None):
    """Fit ``runs`` by output error as every explanation of the diagnosis is fitted."""
    return fit_output_error(runs, unknowns, guess=guess, known=setting.known, max_iter=40,
                            step_tol=setting.fit_tolerance, max_step=max_step, label=label,
                            progress=progress)


def fit_candidate(job):
    """Fit one candidate (runs in a worker process); never raises for a failed fit."""
    t_start = time.perf_counter()
    setting = job.setting
    label = job.effect + (f' {job.variant}' if job.variant else '')
    out = CandidateFit(effect=job.effect, variant=job.variant, prior=tuple(job.prior))
    base_model, experiments = setting.prepared()
    reason = applicable(job.effect, base_model.name, base_model.rotor, setting.unknowns)
    if reason:
        out.available, out.reason = False, reason
        return out
    try:
        if job.effect == 'blade_dissimilarity':
            job = _screen_blade(job, base_model, experiments)
            out.variant = job.variant
            label = f'{job.effect} {job.variant}'
        for widening in range(MAX_WIDENINGS + 1):
            runs, model, unknowns, extra, guess, max_step = build(job, experiments)
            starts = grid_starts(job, model, guess)

            def fit_from(start):
                # (a callback per fit: it counts that fit's iterations at a bound)
                return fit_runs(setting, runs, unknowns, start, max_step, label,
                                stop_at_bound(model, extra, _printer(label, setting.verbose)))
            start = guess
            if starts is not None:
                start = _best_start(runs, unknowns, starts, setting.known, max_step) or guess
            est = fit_from(start)
            if job.effect == 'dynamic_inflow' and est.neg_log_likelihood > job.baseline_nll:
                # ended below the model it extends: restarted from it (no wake), whence a
                # fit never ends below it
                est = fit_from({**guess, **NO_WAKE})
            at_bound = bound_sides(est.model_parameters, model, extra)
            out.bounds = dict(job.bounds or {})
            out.bound_limited = [name for name, _ in at_bound]
            wider = {name: _layer_of(model, name).widened(name, side)
                     for name, side in at_bound}
            if not at_bound or widening == MAX_WIDENINGS or None in wider.values():
                break
            # a fit that is no better than the baseline at the bound asks for no effect: the
            # baseline is the limit beyond the bound (e.g. τ_s → 0), nothing to widen for
            if est.neg_log_likelihood >= job.baseline_nll:
                break
            job = _replace(job, bounds={**(job.bounds or {}), **wider},
                           start={n: est.model_parameters[n] for n in unknowns})
    except (IdentificationError, np.linalg.LinAlgError, FloatingPointError) as exc:
        out.available, out.reason = False, f'fit failed: {exc}'
        out.elapsed_s = time.perf_counter() - t_start
        return out
    out.estimate, out.model, out.unknowns = est, model, unknowns
    out.n_extra = len(est.names) - len(setting.unknowns) - _n_initial(experiments)
    out.effect_parameters.update(effect_parameters(est, model))
    out.parameters = out.effect_parameters.get(job.effect, {})
    out.elapsed_s = time.perf_counter() - t_start
    if setting.verbose:
        sys.stderr.write(f'  [{label}] done in {out.elapsed_s:.1f} s\n')
        sys.stderr.flush()
    return out


#: Effects screened by a score test at the baseline estimate (nested at a neutral value and
#: close to linear in their extra parameters there). The others are always fitted:
#: ``periodic_coefficients`` is not nested by a parameter, ``dynamic_inflow``'s gain is far
#: from linear (its benefit comes at a wake gain where the local test says little), and
#: ``process_noise`` is the explanation of last resort (fitted only when needed).
SCREENED = tuple(e for e in EFFECTS
                 if e not in ('periodic_coefficients', 'dynamic_inflow', NOISE))


def output_error_score(runs, unknowns, guess, known, noise_var, current, max_step=None,
                       extra=()):
    """
    Score (Lagrange-multiplier) test of extra parameters at the current estimate: (LM, var).

    :func:`~rotor_id.estimation.validation.score_statistic` of the output-error cost ½Σ r²/σ²
    at the current model's estimate (``current``, its :class:`CurrentColumns`; its initial
    states included), the extra parameters neutral and the effect's new initial states at
    rest: there the output is the current model's (the null), and the new states' gradient is
    in the test as they are in its k. σ² the current model's; χ²(k) without the effect.
    ``var`` = {name: (M⁻¹)_jj} of the ``extra`` parameters, the others profiled (a detection
    limit follows from it).
    """
    max_step = max_step or DEFAULT_MAX_STEP
    problem = Problem(runs, unknowns, guess, known).prepare(max_step)
    theta = np.concatenate([problem.p_base[problem.param_index],
                            np.zeros(len(problem.names) - len(problem.param_index))])
    mine, theirs = current.shared(problem.names)
    theta[mine] = current.theta[theirs]
    new = current.new_columns(problem.names, theta, extra, len(theta), max_step)
    if new is None:                         # every column integrated
        results = evaluate(problem, theta, max_step)
        dys = [dy for _, dy, _ in results]
    else:
        results = evaluate(problem, theta, max_step, columns=new)
        dys = [dy for dy, in current.filled(problem.names, new,
                                            [(dy,) for _, dy, _ in results])]
    inv_var = 1.0 / np.asarray(noise_var, dtype=float)
    products = [weighted_products(dy, inv_var, res) for (res, _, _), dy in zip(results, dys)]
    names = problem.names
    lm, variance = score_statistic(-sum(g for _, g in products), sum(M for M, _ in products))
    return lm, {n: float(variance[names.index(n)]) for n in extra if n in names}


@dataclass
class CurrentColumns:
    """
    The current model's θ and its sensitivities per run, kept for the score tests at it.

    At a nested model's neutral extra parameters (and new initial states at rest) its output
    is the current model's, and so are its sensitivities along the current θ: a score test
    integrates only its new columns. ``parts``: per run, the arrays whose last axis is θ
    (output error's dy/dθ; filter error's ∂ν and ∂B).
    """

    names: tuple
    theta: np.ndarray
    parts: list
    max_step: float

    def shared(self, names):
        """Return (positions in a nested model's θ ``names``, in the current θ) of shared ones."""
        mine = [i for i, n in enumerate(names) if n in self.names]
        return mine, [self.names.index(names[i]) for i in mine]

    def new_columns(self, names, theta, extra, n_base, max_step):
        """
        Return the positions of a nested model's θ to integrate, or None: all of them.

        None where its output at ``theta`` is not the current model's: another RK4 step, an
        entry it shares at another value, or a new entry that is neither an ``extra``
        parameter nor an initial state at rest (zero, among θ's first ``n_base``).
        """
        mine, theirs = self.shared(names)
        new = [i for i, n in enumerate(names) if n not in self.names]
        if max_step != self.max_step or not np.array_equal(theta[mine], self.theta[theirs]) \
                or any(names[i] not in extra and not (i < n_base and theta[i] == 0)
                       for i in new):
            return None
        return new

    def filled(self, names, new, parts):
        """Return a nested model's arrays per run: ``parts`` in ``new`` columns, others current."""
        mine, theirs = self.shared(names)
        out = []
        for given, had in zip(parts, self.parts):
            arrays = []
            for part, current in zip(given, had):
                full = np.zeros(part.shape[:-1] + (len(names),))
                full[..., new], full[..., mine] = part, current[..., theirs]
                arrays.append(full)
            out.append(tuple(arrays))
        return out


def kept_current(key, compute):
    """Return this process's :class:`CurrentColumns` under ``key`` (``compute()`` for another)."""
    if _CURRENT.get('key') != key:
        _CURRENT.update(key=key, value=compute())
    return _CURRENT['value']


#: this process's current model of the score tests under way (:func:`kept_current`)
_CURRENT: dict = {}


def current_columns(job, experiments):
    """Return the :class:`CurrentColumns` of a job's current model (``prior`` at ``start``)."""
    here = _replace(job, effect='', variant='')

    def compute():
        runs, _, unknowns, _, guess, max_step = build(here, experiments)
        problem = Problem(runs, unknowns, guess, job.setting.known).prepare(max_step)
        theta = _states_fitted(problem, max_step)
        return CurrentColumns(tuple(problem.names), theta,
                              [(dy,) for _, dy, _ in evaluate(problem, theta, max_step)],
                              max_step)
    return kept_current(('output error', job.setting.token, here.prior,
                         tuple(sorted((here.start or {}).items()))), compute)


def tested_variants(effect, base_model):
    """Return the variants of a tested effect, each its own score test ('' for one)."""
    if effect == 'blade_dissimilarity':
        return [f'blade_{blade}' for blade in base_model.blades]
    return ['']


def screen_candidate(job, noise_var):
    """
    Return (variant, LM, k, var) of a screened effect's score test at the current model.

    k: the extra parameters and estimated extra initial states; var: {extra parameter: its
    variance here}. A blade dissimilarity is tested per blade (``job.variant``, one of
    :func:`tested_variants`); a lag (not nested: τ > 0) by its delay d = τ at d = 0
    (:data:`SCREENED_AS`; var under the lag's parameter name).
    """
    setting = job.setting
    _, experiments = setting.prepared()
    effect = job.effect
    if effect in LAG_PARAMETER:
        job = _replace(job, effect=SCREENED_AS[effect])
    runs, model, unknowns, extra, guess, max_step = build(job, experiments)
    lm, var = output_error_score(runs, unknowns, guess, setting.known, noise_var,
                                 current_columns(job, experiments), max_step, extra)
    if effect in LAG_PARAMETER:
        var = as_lag_variance(effect, var)
    return job.variant, lm, len(extra) + _n_initial(runs) - _n_initial(experiments), var


#: Starting Lock-number differences: the fit is bilinear (ε multiplies the state), and from
#: ε = 0 alone Gauss-Newton can stall where a static offset explains the trim shift.
DISSIMILARITY_STARTS = (-0.1, 0.0, 0.1)


def _screen_blade(job, base_model, experiments):
    """
    Return the job of the blade (and start) that lowers the cost most in two GN steps.

    The full fit starts there.
    """
    best, best_cost = None, math.inf
    blades = [int(job.variant.split('_')[1])] if job.variant else \
        aug.BladeView(base_model).blades
    for blade in blades:
        for eps in DISSIMILARITY_STARTS:
            trial = _replace(job, variant=f'blade_{blade}',
                             start={**(job.start or {}), 'dgamma_rel': eps})
            runs, _, unknowns, _, guess, max_step = build(trial, experiments)
            try:
                est = fit_output_error(runs, unknowns, guess=guess, known=job.setting.known,
                                       max_iter=2, max_step=max_step)
            except (IdentificationError, np.linalg.LinAlgError, FloatingPointError):
                continue
            if est.neg_log_likelihood < best_cost:
                best, best_cost = trial, est.neg_log_likelihood
    if best is None:
        raise IdentificationError('no blade-dissimilarity fit could be evaluated')
    return best


def _n_initial(experiments):
    return sum(len(e.free_states()) for e in experiments)


def effect_parameters(est, model):
    """Return {effect: its parameters ± σ as reported} for each augmentation layer of a fit."""
    if not layers(model):
        return {}
    names = model.parameter_names
    p_full = np.array([est.model_parameters[n] for n in names])
    # the covariance over the model's full parameter vector (zero rows for known ones)
    mine = [i for i, n in enumerate(names) if n in est.names]
    theirs = [est.names.index(names[i]) for i in mine]
    cov_full = np.zeros((len(names), len(names)))
    cov_full[np.ix_(mine, mine)] = np.asarray(est.covariance)[np.ix_(theirs, theirs)]
    found = {}
    for layer in layers(model):
        n = len(layer.parameters)          # its base's parameters, then its own
        found[layer.effect] = layer.report_parameters(p_full[:n], cov_full[:n, :n])
    return found
