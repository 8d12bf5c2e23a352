"""
Model-mismatch diagnosis of one recording (issue 4): fit, locate, explain, choose, show.

1. Fit the run description's model (:func:`rotor_id.pipeline.identify`, output-error ML).
2. Locate (:mod:`rotor_id.diagnosis.residuals`): per channel RMS against a model-free noise
   floor, whiteness, correlation with the pitch input, spectrum per rev, energy over time.
3. Explain (:mod:`rotor_id.diagnosis.catalogue`): fit every applicable candidate of the
   catalogue, each an augmented model fitted by the same ML (worker processes in parallel).
4. Choose with statistics that do not reward extra parameters:

       criterion = 2 Δlog L · ρ − k log(n ρ)   (BIC difference, n = samples × channels)

   where k counts the candidate's extra parameters and estimated initial states and
   ρ = N_eff/N corrects the sample size for the autocorrelation left in the candidate's
   residuals (a candidate that leaves coloured residuals gets less credit for its Δlog L).
   An effect is named when its criterion exceeds :data:`CRITERION_THRESHOLD` ("very strong"
   evidence on the Kass-Raftery scale) and its prediction of the half of the window it was not
   fitted to beats the baseline's (cross-validation both ways). Otherwise the answer is
   ``unexplained`` if the residual tests find a mismatch, ``none`` if they do not.
5. Show: :meth:`Diagnosis.as_json` (stable keys of issue 4) and :mod:`rotor_id.diagnosis.figures`.
"""

from dataclasses import dataclass, field, replace as _replace
import math
import multiprocessing
import time

import numpy as np

from rotor_id.diagnosis import residuals as rs
from rotor_id.diagnosis.augmentations import BladeView
from rotor_id.diagnosis.catalogue import (
    applicable, CandidateFit, combine_halves, EFFECTS, equivalent, fit_candidate, Job,
    n_choices, screen_candidate, SCREENED, validate_candidate, validation_halves, variants)
from rotor_id.estimation import kernels
from rotor_id.estimation.output_error import IdentificationError
from rotor_id.estimation.simulate import simulate
from rotor_id.physics.multiblade import coordinate_names, multiblade_from_blade_matrix
from rotor_id.pipeline import identify

#: ΔBIC above which a candidate counts as an explanation ("very strong": > 10).
CRITERION_THRESHOLD = 10.0
#: Criterion gap to the best non-equivalent rival for a "high" confidence.
CONFIDENCE_GAP = 10.0
#: Strongest candidates cross-validated (the others cannot be chosen anyway).
MAX_VALIDATED = 3
#: Most effects named together.
MAX_EFFECTS = 3
#: Rig physics added to the catalogue after the others (issue 16); each has a first-order
#: equivalent among them in hover (:data:`rotor_id.diagnosis.catalogue.EQUIVALENT`).
RIG_EFFECTS = ('pitch_flap_coupling', 'pitch_actuator_lag')
#: A rig effect ahead of its established first-order equivalent by less than this criterion
#: (a likelihood ratio below e) ties with it, and the established effect is named.
EQUIVALENT_TIE = 2.0
#: A score test's LM may underpredict the full fit's 2Δlog L where the effect is not small;
#: screening credits the fit with this multiple of LM before ruling it out.
SCREEN_SAFETY = 2.0
#: Random inflow is fitted when the baseline residuals' combined whiteness p is below this
#: or their RMS is 2 standard errors above the floor (and no deterministic effect is adequate).
PROCESS_NOISE_WHITENESS = 0.05


@dataclass
class Channel:
    """A residual series of the baseline fit, with its noise floor."""

    name: str
    residual: np.ndarray
    measured: np.ndarray
    fitted: np.ndarray
    floor: float
    n_blades: int
    model_channel: bool


@dataclass
class Diagnosis:
    """Everything the diagnosis found (``as_json`` gives the issue's stable keys)."""

    mismatch: bool
    effect: str
    confidence: str
    location: dict
    explanation_parameters: dict
    fit: dict
    candidates: list
    parameters: dict
    baseline: object
    chosen: object
    channels: list
    stats_baseline: list
    stats_augmented: list
    blade_floor: np.ndarray
    record_window: object
    elapsed_s: float
    notes: list = field(default_factory=list)
    fits: list = field(default_factory=list)
    #: the effects added one at a time (forward selection), each with what it adds
    steps: list = field(default_factory=list)
    #: out of catalogue (verdict ``unexplained``): the proposal of rotor_id.diagnosis.proposal
    proposal: dict = None

    def as_json(self):
        """JSON of ``rotor-id diagnose`` (issue 4 keys; more allowed)."""
        from rotor_id.diagnosis import noisy
        return {
            'mismatch': bool(self.mismatch),
            'location': self.location,
            'explanation': {'effect': self.effect, 'confidence': self.confidence,
                            'parameters': self.explanation_parameters,
                            'effects': [_effect_json(st) for st in self.steps],
                            **({} if self.proposal is None else {'proposal': self.proposal})},
            'fit': self.fit,
            'candidates': self.candidates,
            'parameters': self.parameters,
            'baseline': {'model': self.baseline.model.name,
                         'unknowns': list(self.baseline.unknowns),
                         'window_s': [float(v) for v in self.baseline.window_s],
                         'neg_log_likelihood': float(self.baseline.estimate.neg_log_likelihood)},
            'channels_baseline': [s.as_dict() for s in self.stats_baseline],
            'channels_augmented': [s.as_dict() for s in self.stats_augmented],
            'noise_floor_blades_rad': [float(s) for s in self.blade_floor],
            'criterion': {'name': 'BIC difference with autocorrelation-corrected sample size',
                          'threshold': CRITERION_THRESHOLD,
                          'beside_random_inflow': {
                              'name': 'likelihood-ratio test, Bonferroni over the step',
                              'family_level': noisy.STEP_LEVEL}},
            'notes': list(self.notes),
            'elapsed_s': float(self.elapsed_s),
        }


def _effect_json(step):
    """One entry of ``explanation.effects``."""
    return {'effect': step['effect'], 'variant': step['variant'],
            'parameters': {n: {'value': v, 'std': s}
                           for n, (v, s) in step.get('parameters', {}).items()},
            'delta_loglik': step['delta_loglik'], 'criterion': step['criterion'],
            'validation_rms': step['validation_rms'], 'residual_rms': step['residual_rms'],
            'excess_over_floor': step['excess_over_floor'],
            'residuals_are_noise': bool(step['adequate']),
            'confounded_with': [c['effect'] for c in step.get('confounds', [])],
            'confounds': [dict(c) for c in step.get('confounds', [])],
            'equivalents': [dict(e) for e in step.get('equivalents', [])],
            **({'test': dict(step['test'])} if 'test' in step else {})}


def _say(progress, text):
    if progress is not None:
        progress(text)


# ------------------------------------------------------------------------------------------------
# Baseline channels
# ------------------------------------------------------------------------------------------------

def baseline_channels(ident, part, blade_sigma):
    """
    Return the residual channels of the baseline.

    The model's own, plus the multiblade coordinates it predicts and, when it predicts all
    four, each blade.
    """
    est = ident.estimate
    channels = []
    runs = ident.experiments
    for r, exp in enumerate(runs):
        view = BladeView(exp.model)
        floors = rs.channel_floor(view.channels(exp.t),
                                  blade_sigma[[b - 1 for b in view.blades]])
        for j, name in enumerate(exp.model.output_names):
            label = name if len(runs) == 1 or name.startswith('beta_') and len(runs) > 1 \
                else f'{name}[{exp.name}]'
            channels.append(Channel(label, est.residuals[r][:, j], exp.y[:, j],
                                    est.fitted[r][:, j], float(floors[j]),
                                    len(view.blades), True))
    model = ident.model
    if model.name == 'single_blade':
        return channels
    exp = runs[0]
    p = np.array([est.model_parameters[n] for n in model.parameter_names])
    sim = simulate(model, p, exp.inputs, exp.t, est.initial_states[0])
    view = BladeView(model)
    pred_blades = np.einsum('tkn,tn->tk', view.flap(exp.t), sim.x)
    meas_blades = part.blade_flap
    n_blades = model.rotor.n_blades
    coordinates = coordinate_names(n_blades)
    to_mbc = multiblade_from_blade_matrix(exp.t, n_blades)         # the one transform, any N
    pred_mbc = np.einsum('tij,tj->ti', to_mbc, pred_blades)
    meas_mbc = np.einsum('tij,tj->ti', to_mbc, meas_blades)
    predicted = [s for s in coordinates if s in model.state_names]
    have = {c.name for c in channels}
    for i, name in enumerate(coordinates):
        if name in predicted and name not in have:
            floor = rs.channel_floor(to_mbc[:, i:i + 1, :], blade_sigma)[0]
            channels.append(Channel(name, meas_mbc[:, i] - pred_mbc[:, i], meas_mbc[:, i],
                                    pred_mbc[:, i], float(floor), n_blades, False))
    if len(predicted) == n_blades:
        for k in range(n_blades):
            name = f'beta_{k + 1}'
            if name not in have:
                channels.append(Channel(name, meas_blades[:, k] - pred_blades[:, k],
                                        meas_blades[:, k], pred_blades[:, k],
                                        float(blade_sigma[k]), 1, False))
    return channels


def _stats(channels, t, u):
    return [rs.channel_stats(c.name, c.residual, c.floor, u, c.n_blades, t) for c in channels]


def _overall(values):
    return float(math.sqrt(np.mean(np.square(values))))


# ------------------------------------------------------------------------------------------------
# Candidates
# ------------------------------------------------------------------------------------------------

def _run_jobs(function, jobs, workers, on_done):
    results = []
    if workers <= 1 or len(jobs) <= 1:
        for job in jobs:
            res = function(job)
            on_done(res)
            results.append(res)
        return results
    # load the compiled kernel once, here, so that the forked workers inherit it: each would
    # otherwise run numpy until the auto switch and load it again (a noticeable part of a short
    # diagnosis' CPU, per worker and pool)
    kernels.prefer()
    ctx = multiprocessing.get_context('fork')
    with ctx.Pool(processes=workers) as pool:
        for res in pool.imap_unordered(function, jobs):
            on_done(res)
            results.append(res)
    return results


def _fit_selection_jobs(jobs, ctx):
    """
    :func:`fit_candidate` of the selection's jobs, each model fitted once per diagnosis.

    The forward steps, the exchanges and the two-for-one search revisit kept sets (an
    exchange that ends where it started, a two-for-one whose selection drops the stand-in
    again). The same augmented model on the same data within the same catalogue bounds is
    the same fit, so one already made is reused (``ctx['fitted']``) instead of repeated:
    the wake, fitted again beside an azimuth offset after a two-for-one that came back to
    it, dominated a single-effect record's time. Returns the fits in the jobs' order.
    """
    memo = ctx.setdefault('fitted', {})

    def key(job):
        return (job.effect, job.variant, frozenset(job.prior),
                tuple(sorted((job.bounds or {}).items())))
    todo = list({key(j): j for j in jobs if key(j) not in memo}.values())
    if ctx['workers'] <= 1 or len(todo) <= 1:
        fits = [fit_candidate(job) for job in todo]
    else:
        kernels.prefer()
        with multiprocessing.get_context('fork').Pool(processes=ctx['workers']) as pool:
            fits = pool.map(fit_candidate, todo)        # in the jobs' order
    memo.update(zip(map(key, todo), fits))
    return [memo[key(j)] for j in jobs]


def _fit_once(ctx, job):
    """Return :func:`fit_candidate` of one job of the selection (:func:`_fit_selection_jobs`)."""
    return _fit_selection_jobs([job], ctx)[0]


def _run_validation(jobs, workers, on_done):
    """
    :func:`validate_candidate` of every job: [(effect, variant, RMS)], in completion order.

    With workers, each job's two directions (fit the first half, predict the second, and the
    reverse) are jobs of their own, so both cores are busy while the slowest candidate is
    validated; their RMS are joined by :func:`combine_halves`.
    """
    if workers <= 1:
        return _run_jobs(validate_candidate, jobs, workers, on_done)
    parts, results = {}, []

    def half_done(res):
        effect, variant, rms = res
        seen = parts.setdefault((effect, variant), [])
        seen.append(rms)
        if len(seen) == 2:
            results.append((effect, variant, combine_halves(*seen)))
            on_done(results[-1])
    _run_jobs(validate_candidate, [h for job in jobs for h in validation_halves(job)],
              workers, half_done)
    return results


def _score(fit, baseline_est, n_obs, n_variants):
    est = fit.estimate
    dll = float(baseline_est.neg_log_likelihood - est.neg_log_likelihood)
    res = np.concatenate(est.residuals, axis=0)
    # random inflow's fit is by filter error: its residuals are innovations
    rho = rs.channels_effective_fraction(res, innovations=fit.effect == 'process_noise')
    k = max(fit.n_extra, 0)
    criterion = 2.0 * dll * rho - k * math.log(n_obs * rho)
    if n_variants > 1:
        criterion -= 2.0 * math.log(n_variants)       # which blade: a choice among N
    return dll, rho, criterion


def _screen(job, noise_var, n_obs, n_blades):
    """
    Score-test one effect at the baseline: {'effect', 'variant', 'lm', 'k', 'fit'}.

    ``fit`` is False only when even the most generous criterion the full fit could reach,
    2Δlog L·1 − k log(n ρ_min) − 2 log(choices) with 2Δlog L = SCREEN_SAFETY·LM, stays below
    :data:`CRITERION_THRESHOLD` (ρ_min = 1/50 is the smallest autocorrelation correction
    :func:`rotor_id.diagnosis.residuals.effective_fraction` gives).
    """
    try:
        tests = screen_candidate(job, noise_var)
    except (IdentificationError, np.linalg.LinAlgError, FloatingPointError):
        return {'effect': job.effect, 'variant': job.variant, 'lm': math.nan, 'k': 0,
                'fit': True}
    variant, lm, k = max(tests, key=lambda v: v[1])
    reach = SCREEN_SAFETY * lm - k * math.log(n_obs / 50.0) \
        - 2.0 * math.log(n_choices(job.effect, n_blades))
    return {'effect': job.effect, 'variant': variant, 'lm': lm, 'k': k,
            'fit': bool(reach > CRITERION_THRESHOLD or not math.isfinite(lm))}


def _process_noise_not_needed(fits, est, n_obs, n_blades, channels, u, t, model_stats, screen):
    """
    Return why random inflow need not be fitted, or '' when it must be.

    It is the explanation of last resort (:func:`_choose`): not needed when a deterministic
    candidate is eligible by its criterion and leaves white residuals at the floor, nor when
    the baseline's residuals show no structure at all (white, at the floor) for it to explain.
    """
    if not screen:
        return ''
    floors = [c.floor for c in channels if c.model_channel]
    for fit in fits:
        if not fit.available or fit.bound_limited:
            continue
        _, _, crit = _score(fit, est, n_obs, n_choices(fit.effect, n_blades))
        if crit > CRITERION_THRESHOLD and _adequate(fit, floors, u, t):
            return (f'{fit.effect} leaves white residuals at the noise floor and random '
                    'inflow is the explanation of last resort')
    white = rs.combined_whiteness_p(model_stats)
    if white > PROCESS_NOISE_WHITENESS and max(s.z_excess for s in model_stats) < 2.0:
        return (f'the baseline residuals are white (p = {white:.2g}) at the noise floor: '
                'nothing for random inflow to explain')
    return ''


def diagnose(record, description, progress=None, workers=2, effects=EFFECTS, window_s=None,
             verbose_fits=False, screen=True):
    """
    Diagnose the mismatch between a recording and the run description's model.

    Parameters
    ----------
    record : rotor_id.io.record.Record
        The recording (rad, s), e.g. from :func:`rotor_id.io.bag.read_run` or a live buffer.
    description : rotor_id.io.run_description.RunDescription
        The run description: model, unknowns, window, rotor data.
    progress : callable, optional
        Called with one line of text per step (what is being fitted, iteration, elapsed).
    workers : int
        Worker processes for the candidate fits (1: all in this process).
    effects : sequence of str
        Catalogue ids to try (default: all).
    window_s : (float, float), optional
        Overrides the description's window.
    verbose_fits : bool
        Worker processes print every Gauss-Newton iteration to stderr.
    screen : bool
        Score-test the nested candidates at the baseline and fit only those that could reach
        the criterion; fit random inflow only when needed (False: fit everything, as a
        reference for the benchmark).

    Returns
    -------
    Diagnosis

    """
    t_start = time.perf_counter()
    window_s = tuple(window_s or description.window_s)
    unknowns = list(description.unknowns)
    _say(progress, f'baseline: fitting {description.model} ({", ".join(unknowns)}) by '
                   f'output-error ML over {window_s[0]:.3f}-{window_s[1]:.3f} s')

    def base_progress(info):
        rms = math.sqrt(float(np.mean(np.square(info['noise_std']))))
        _say(progress, f'baseline: iteration {info["iteration"]}, residual RMS {rms:.5g} rad, '
                       f'{time.perf_counter() - t_start:.1f} s')

    ident = identify(record, description, progress=base_progress, window_s=window_s)
    est = ident.estimate
    part = record.window(*window_s)
    blade_sigma = rs.blade_noise_floor(part.blade_flap)
    exp0 = ident.experiments[0]
    u = exp0.inputs(exp0.t)
    channels = baseline_channels(ident, part, blade_sigma)
    stats_base = _stats(channels, exp0.t, u)
    model_stats = [s for s, c in zip(stats_base, channels) if c.model_channel]
    n_ch = len(stats_base)
    residual_flag = any(s.flagged(n_ch) for s in stats_base)
    white_p_base = rs.combined_whiteness_p(model_stats)
    _say(progress, 'baseline: residual RMS {:.4g} rad against a noise floor of {:.4g} rad, '
                   'whiteness p = {:.2g} ({:.1f} s)'.format(
                       _overall([s.rms for s in model_stats]),
                       _overall([s.floor for s in model_stats]), white_p_base,
                       time.perf_counter() - t_start))

    # ---- candidates (phase 1: fits) ----
    values = {n: est.model_parameters[n] for n in unknowns}
    known = {n: v for n, v in est.model_parameters.items() if n not in unknowns}
    n_blades = record.n_blades
    n_obs = sum(e.t.size * e.model.n_outputs for e in ident.experiments)
    noise_var = np.asarray(est.noise_std, dtype=float)**2
    jobs, screened_out = [], []
    deterministic = [e for e in effects if e != 'process_noise']
    for effect in deterministic:
        for variant in variants(effect, ident.model.name, n_blades):
            job = Job(effect, variant, record, description, values, unknowns, known,
                      window_s, verbose=verbose_fits, baseline_nll=est.neg_log_likelihood)
            if screen and effect in SCREENED and not applicable(
                    effect, ident.model.name, ident.model.rotor, unknowns):
                verdict = _screen(job, noise_var, n_obs, n_blades)
                if verdict['fit']:
                    job = _replace(job, variant=verdict['variant'])
                else:
                    screened_out.append(verdict)
                    _say(progress, f'candidate {effect}: screened out, score test '
                                   f'2Δlog L ≈ {verdict["lm"]:.1f} with {verdict["k"]} '
                                   'extra at the baseline')
                    continue
            jobs.append(job)
    _say(progress, f'candidates: fitting {len(jobs)} augmented models '
                   f'({", ".join(j.effect for j in jobs)}) in {max(1, workers)} process(es) '
                   f'({time.perf_counter() - t_start:.1f} s)')

    def done(fit):
        label = fit.effect + (f' {fit.variant}' if fit.variant else '')
        if not fit.available:
            _say(progress, f'candidate {label}: not tried ({fit.reason})')
            return
        dll = est.neg_log_likelihood - fit.estimate.neg_log_likelihood
        _say(progress, f'candidate {label}: Δlog L = {dll:.1f} with {fit.n_extra} extra, '
                       f'{fit.estimate.iterations} iterations, {fit.elapsed_s:.1f} s '
                       f'(total {time.perf_counter() - t_start:.1f} s)')

    fits = _run_jobs(fit_candidate, jobs, workers, done)
    if 'process_noise' in effects:
        why_not = _process_noise_not_needed(fits, est, n_obs, n_blades, channels, u, exp0.t,
                                            model_stats, screen)
        if why_not:
            fits.append(CandidateFit(effect='process_noise', available=False,
                                     reason=f'not fitted: {why_not}'))
        else:
            fits += _run_jobs(fit_candidate, [
                Job('process_noise', '', record, description, values, unknowns, known,
                    window_s, verbose=verbose_fits, baseline_nll=est.neg_log_likelihood)],
                1, done)
    fits.sort(key=lambda f: (EFFECTS.index(f.effect), f.variant))
    scored = {}
    for fit in fits:
        if not fit.available or fit.bound_limited:
            continue
        n_var = n_choices(fit.effect, n_blades)
        dll, rho, crit = _score(fit, est, n_obs, n_var)
        prev = scored.get(fit.effect)
        if prev is None or crit > prev['criterion']:
            scored[fit.effect] = {'fit': fit, 'delta_loglik': dll, 'rho': rho,
                                  'criterion': crit}

    # ---- phase 2: cross-validation of the strong ones and of the baseline ----
    strong = sorted([e for e, s in scored.items() if s['criterion'] > CRITERION_THRESHOLD],
                    key=lambda e: -scored[e]['criterion'])[:MAX_VALIDATED]
    val_jobs = [Job('baseline', '', record, description, values, unknowns, known, window_s)]
    for effect in strong:
        fit = scored[effect]['fit']
        start = {n: fit.estimate.model_parameters[n] for n in fit.unknowns} \
            if effect != 'process_noise' else None
        val_jobs.append(Job(effect, fit.variant, record, description, values, unknowns, known,
                            window_s, start=start, bounds=fit.bounds))
    _say(progress, f'validation: fitting {len(val_jobs)} model(s) on one half of the window '
                   'and predicting the other, both ways')
    validation = {}

    def vdone(res):
        effect, variant, v = res
        validation[effect] = v
        shown = 'n/a' if v is None else f'{v:.4g} rad'
        _say(progress, f'validation {effect}: prediction RMS {shown} '
                       f'({time.perf_counter() - t_start:.1f} s)')

    _run_validation(val_jobs, workers, vdone)
    base_val = validation.get('baseline')

    # ---- choose ----
    table = []
    for fit in fits:
        if fit.effect in scored and scored[fit.effect]['fit'] is fit:
            s = scored[fit.effect]
            v = validation.get(fit.effect)
            validated = v is None or base_val is None or v < base_val
            eligible = s['criterion'] > CRITERION_THRESHOLD and validated
            table.append({'effect': fit.effect, 'variant': fit.variant,
                          'delta_loglik': s['delta_loglik'], 'criterion': s['criterion'],
                          'validation_rms': v, 'n_extra': fit.n_extra,
                          'n_eff_fraction': s['rho'], 'eligible': eligible,
                          'available': True, 'converged': bool(fit.estimate.converged),
                          'fit': fit})
        elif fit.available and fit.bound_limited:
            # a likelihood capped by a catalogue range is not compared (issue 16, item 3)
            names = ', '.join(fit.bound_limited)
            table.append({'effect': fit.effect, 'variant': fit.variant,
                          'delta_loglik': float(est.neg_log_likelihood
                                                - fit.estimate.neg_log_likelihood),
                          'criterion': None, 'validation_rms': None,
                          'n_extra': fit.n_extra, 'eligible': False, 'available': True,
                          'bound_limited': list(fit.bound_limited),
                          'reason': f'bound-limited: {names} at the catalogue bound '
                                    f'{_bound_text(fit)} (the data ask for less of it than '
                                    'the range allows; not compared on a capped likelihood)',
                          'fit': fit})
        elif not fit.available and not any(t['effect'] == fit.effect for t in table):
            table.append({'effect': fit.effect, 'variant': fit.variant,
                          'delta_loglik': None, 'criterion': None, 'validation_rms': None,
                          'n_extra': 0, 'eligible': False, 'available': False,
                          'reason': fit.reason, 'fit': fit})
    for v in screened_out:
        table.append({'effect': v['effect'], 'variant': v['variant'],
                      'delta_loglik': 0.5 * v['lm'], 'criterion': None,
                      'validation_rms': None, 'n_extra': v['k'], 'eligible': False,
                      'available': True, 'score_test': True,
                      'reason': 'screened out: the score test at the baseline predicts '
                                f'2Δlog L ≈ {v["lm"]:.1f} with {v["k"]} extra, no criterion '
                                f'can reach {CRITERION_THRESHOLD:g}', 'fit': None})
    table.sort(key=lambda t: EFFECTS.index(t['effect']))
    ranked = sorted([t for t in table if t['criterion'] is not None],
                    key=lambda t: -t['criterion'])
    eligible = [t for t in ranked if t['eligible']]
    floors = [c.floor for c in channels if c.model_channel]
    for t in eligible:
        t['adequate'] = _adequate(t['fit'], floors, u, exp0.t)
    mu = ident.model.rotor.advance_ratio
    chosen, passed_over = _choose(eligible, mu)
    notes, confound_notes = [], []
    noise_row = None
    if chosen is not None and chosen['effect'] == 'process_noise':
        deterministic_rows = [t for t in eligible if t['effect'] != 'process_noise']
        if deterministic_rows:
            # several deterministic effects may explain together what none explains alone:
            # try them first; random inflow stays the explanation of last resort
            noise_row = chosen
            chosen, _ = _choose(deterministic_rows, mu)
    # ---- more effects: forward selection with refits and a backward check ----
    steps = []
    chosen_fit = chosen['fit'] if chosen else None
    if chosen is not None:
        steps.append(_step_row(chosen['fit'], chosen['delta_loglik'], chosen['criterion'],
                               validation.get(chosen['effect']), floors, u, exp0.t))
        context = {'record': record, 'description': description, 'values': values,
                   'unknowns': unknowns, 'known': known, 'window_s': window_s,
                   'n_obs': n_obs, 'n_blades': n_blades, 'floors': floors, 'u': u,
                   't': exp0.t, 'workers': workers, 'screen': screen,
                   'effects': deterministic, 'model_name': ident.model.name,
                   'rotor': ident.model.rotor, 'progress': progress, 't_start': t_start,
                   'verbose': verbose_fits, 'mu': mu,
                   'trace': [_standalone_gains(scored, screened_out, n_obs, n_blades)]}
        if chosen['effect'] != 'process_noise':
            chosen_fit, steps, dropped = _forward_selection(chosen['fit'], steps, context)
            confound_notes = [_confound_text(effect_row['effect'], c) for effect_row in steps
                              for c in effect_row.get('confounds', [])]
            confound_notes += [_confound_text(t['winner'], t)
                               for t in context['two_for_one_ties']]
            notes += list(dict.fromkeys(confound_notes))   # a two-for-one tie: one note
            notes += context['replaced']
            for old in dropped:
                notes.append(f'{old} was dropped by the backward check: with the effects added '
                             'after it, it no longer earns its place')
            if len(steps) > 1:
                mismatch = True
    last_resort = ''
    if noise_row is not None:
        if steps and steps[-1]['adequate']:
            passed_over = True
        else:
            tried = ' + '.join(st['effect'] for st in steps)
            chosen, chosen_fit = noise_row, noise_row['fit']
            steps = [_step_row(chosen_fit, noise_row['delta_loglik'], noise_row['criterion'],
                               validation.get('process_noise'), floors, u, exp0.t)]
            steps[0]['parameters'] = chosen_fit.parameters
            # random inflow as the last resort over eligible deterministic effects: a filter
            # tracks any unmodelled dynamics, so the verdict is weak by construction
            last_resort = tried
            notes = [n for n in notes if n not in confound_notes]     # of the effects dropped
            notes.append(f'random inflow is the explanation of last resort: {tried} raise(s) '
                         'the likelihood past the criterion but leave(s) structured residuals; '
                         'a deterministic effect the catalogue cannot represent in this record '
                         'is as likely (low confidence)')
    if chosen is not None and 'process_noise' in effects:
        chosen_fit, steps, last_resort, passed_over = _with_random_inflow(
            chosen, chosen_fit, steps, context, notes, last_resort, passed_over)
    if passed_over:
        notes.append('process_noise also raises the likelihood (a Kalman filter tracks any '
                     f'unmodelled dynamics), but {" + ".join(st["effect"] for st in steps)} '
                     'leave(s) white residuals at '
                     'the noise floor: random inflow is the explanation of last resort')
    if chosen is not None:
        effect = chosen['effect']
        named = {st['effect'] for st in steps} | {effect}
        named |= {eq for e in list(named) for eq in equivalent(e, mu)}
        rivals = [t for t in ranked if t['effect'] not in named
                  and not (passed_over and t['effect'] == 'process_noise')]
        gap = chosen['criterion'] - (rivals[0]['criterion'] if rivals else 0.0)
        confidence = 'high' if gap > CONFIDENCE_GAP and not last_resort else 'low'
        if context.get('doubts'):
            confidence = 'low'
        # a rival whose fit did not converge has a likelihood that is only a lower bound
        from rotor_id.diagnosis import noisy
        unsettled = noisy.unconverged(table, named,
                                      at_floor=bool(steps and steps[-1]['adequate']))
        if unsettled:
            confidence = 'low'
            notes += unsettled
        dominant = max(steps, key=lambda st: st['criterion'])['effect'] if steps else effect
        if any(c.get('how_given') == 'exchange' and st['effect'] == dominant
               or c.get('how_given') == 'two_for_one'
               for st in steps for c in st.get('confounds', [])) \
                or context.get('two_for_one_ties'):
            # another description of the record fits as well: not a confident name
            confidence = 'low'
        for st in steps or [{'effect': effect}]:
            one = st['effect']
            same = _equivalents_here(one, eligible, context['trace'], mu)
            st['equivalents'] = [dict(e) for e in same]
            for e in same:
                against = '' if e['criterion_named'] is None \
                    else f' against {e["criterion_named"]:.1f}'
                notes.append(f'{one} and {e["effect"]} are the same physics to first order at '
                             f'this size; both explain the data ({e["how"]}: criterion '
                             f'{e["criterion"]:.1f}{against})')
        if effect == 'blade_dissimilarity' and ident.model.name == 'multiblade_wake':
            notes.append('the (β1−β3)/2, (β2−β4)/2 channels see blade j and blade j+2 alike '
                         '(the mirror blade with the opposite static offset dtheta_static); '
                         'measure every blade to tell them apart')
        if rivals and gap <= CONFIDENCE_GAP:
            notes.append(f'{rivals[0]["effect"]} is about as strong by the criterion '
                         f'({rivals[0]["criterion"]:.1f} against {chosen["criterion"]:.1f}); '
                         'the prediction of the unfitted half-window decided')
        mismatch = True
    else:
        mismatch = residual_flag
        effect = 'unexplained' if mismatch else 'none'
        confidence = 'high' if not ranked or ranked[0]['criterion'] < 0 else 'low'
        # turbulence likely but not established, or a candidate whose fit did not converge
        from rotor_id.diagnosis import noisy
        doubts = (noisy.unconverged(table, set(), at_floor=not mismatch)
                  + noisy.noise_alone_doubt(table))
        if doubts:
            confidence = 'low'
            notes += doubts
    proposal, out_of_catalogue = None, False
    # out of catalogue: a term the data want, as a proposal. Random inflow is asked too: it is
    # the explanation of last resort, and a Kalman filter tracks unmodelled dynamics as well
    if effect in ('unexplained', 'process_noise') and not any(
            st['effect'] != 'process_noise' for st in steps):
        from rotor_id.diagnosis.proposal import propose
        _say(progress, 'proposal: stepwise regression of the equation error on a library of '
                       'flap-equation terms, validated on held-out time blocks')
        proposal = propose(ident.experiments, unknowns, values, known)
        _say(progress, proposal.text())
        if effect == 'process_noise' and proposal.terms:
            # a deterministic term that predicts held-out blocks is not random inflow: the
            # Kalman filter tracks any unmodelled dynamics, so the verdict is out of catalogue
            effect, confidence, out_of_catalogue = 'unexplained', 'low', True
            notes.append(f'random inflow (process_noise) raises the likelihood, but it is the '
                         f'explanation of last resort, and a deterministic term '
                         f'({proposal.terms[0]["term"]}) lowers the held-out equation error by '
                         f'{proposal.terms[0]["heldout_improvement"]:.0%} beyond chance: '
                         'unexplained, unmodelled dynamics likely (see explanation.proposal, '
                         'a proposal, not a catalogue verdict)')

    # ---- show ----
    if chosen_fit is not None:
        aug_est = chosen_fit.estimate
        aug_res = np.concatenate(aug_est.residuals, axis=0)
        names = list(aug_est.channel_names)
        if len(ident.experiments) > 1:
            names = [c.name for c in channels if c.model_channel]
            aug_res = np.column_stack([r[:, 0] for r in aug_est.residuals])
        floors = [c.floor for c in channels if c.model_channel]
        stats_aug = [rs.channel_stats(n, aug_res[:, j], floors[j], u,
                                      channels[j].n_blades, exp0.t)
                     for j, n in enumerate(names)]
    else:
        stats_aug = model_stats
    location = _location(channels, stats_base, exp0.t, part, mismatch, n_ch)
    fit_block = {
        'noise_floor': _overall([s.floor for s in model_stats]),
        'baseline_rms': _overall([s.rms for s in model_stats]),
        'augmented_rms': _overall([s.rms for s in stats_aug]),
        'whiteness_p_baseline': white_p_base,
        'whiteness_p_augmented': rs.combined_whiteness_p(stats_aug),
        'channels': [s.name for s in model_stats],
        'noise_floor_per_channel': [s.floor for s in model_stats],
        'baseline_rms_per_channel': [s.rms for s in model_stats],
        'augmented_rms_per_channel': [s.rms for s in stats_aug],
        'validation_rms_baseline': base_val,
    }
    explanation = {}
    if steps and not out_of_catalogue:
        effect = max(steps, key=lambda st: st['criterion'])['effect']
    if chosen_fit is not None and not out_of_catalogue:
        own = chosen_fit.effect_parameters.get(effect, chosen_fit.parameters)
        explanation = {n: {'value': v, 'std': s} for n, (v, s) in own.items()}
        if effect == 'time_delay' and 'delay_rad' in explanation:
            omega = ident.omega_rad_s
            explanation['delay_s'] = {'value': explanation['delay_rad']['value'] / omega,
                                      'std': explanation['delay_rad']['std'] / omega}
    parameters = {}
    for n in unknowns:
        entry = {'baseline_value': est.value(n), 'baseline_std': est.std_of(n)}
        if chosen_fit is not None and n in chosen_fit.estimate.names:
            entry.update(value=chosen_fit.estimate.value(n), std=chosen_fit.estimate.std_of(n))
        else:
            entry.update(value=entry['baseline_value'], std=entry['baseline_std'])
        parameters[n] = entry
    candidates = []
    for t in table:
        row = {k: v for k, v in t.items() if k != 'fit'}
        if t['available'] and t['fit'] is not None and t['fit'].parameters:
            row['parameters'] = {n: {'value': v, 'std': s}
                                 for n, (v, s) in t['fit'].parameters.items()}
        candidates.append(row)
    elapsed = time.perf_counter() - t_start
    _say(progress, f'diagnosis: {effect} ({confidence} confidence), {elapsed:.1f} s')
    return Diagnosis(mismatch=mismatch, effect=effect, confidence=confidence, location=location,
                     explanation_parameters=explanation, fit=fit_block, candidates=candidates,
                     parameters=parameters, baseline=ident, chosen=chosen_fit,
                     channels=channels, stats_baseline=stats_base, stats_augmented=stats_aug,
                     blade_floor=blade_sigma, record_window=part, elapsed_s=elapsed,
                     notes=notes, fits=fits, steps=steps,
                     proposal=None if proposal is None else proposal.as_json())


def _with_random_inflow(chosen, chosen_fit, steps, ctx, notes, last_resort, passed_over):
    """
    Random inflow together with deterministic effects (:mod:`rotor_id.diagnosis.noisy`).

    Random inflow chosen: deterministic effects are added to it by the innovations
    likelihood. Deterministic effects chosen: random inflow is added to them when its score
    test, fit and held-out prediction say so. Returns (fit, steps, last_resort, passed_over).
    """
    from rotor_id.diagnosis import noisy
    if chosen['effect'] == 'process_noise':
        fit, found, more = noisy.add_deterministic(chosen_fit, steps[0], ctx)
        notes += more + [_confound_text(st['effect'], c) for st in found
                         for c in st.get('confounds', [])]
        notes += ctx.get('doubts', [])         # an effect likely beside it: not confident
        deterministic = [st['effect'] for st in found if st['effect'] != 'process_noise']
        if deterministic:
            # a last resort stays one (low confidence): the output-error fits of these effects
            # left structured residuals, and a filter tracks any unmodelled dynamics
            notes.append(f'{" + ".join(deterministic)} found by the innovations (filter-error) '
                         'likelihood with random inflow in the model: the output-error '
                         'likelihood of a deterministic effect is swamped by the turbulence')
        return fit, found, last_resort, passed_over
    added = noisy.add_random_inflow(chosen_fit, steps, ctx)
    if added is None:
        notes += ctx.get('doubts', [])         # turbulence likely beside it: not confident
        return chosen_fit, steps, last_resort, passed_over
    fit, row = added
    steps = steps + [row]
    for st in steps:
        st['parameters'] = fit.effect_parameters.get(st['effect'], st.get('parameters', {}))
        st.setdefault('confounds', [])
    notes.append('random inflow (process_noise) added to '
                 f'{" + ".join(st["effect"] for st in steps[:-1])}: its innovations '
                 f'likelihood gains a criterion {row["criterion"]:.1f} and the filter '
                 'predicts each quarter of the window better from the other three')
    return fit, steps, last_resort, False


def _residual_matrix(est):
    """Return the residuals of an estimate as (T, channels) (several runs: a column each)."""
    if len(est.residuals) > 1:
        return np.column_stack([r[:, 0] for r in est.residuals])
    return est.residuals[0]


def _step_row(fit, dll, criterion, validation_rms, floors, u, t):
    """One effect added: what it adds (Δlog L, criterion, held-out RMS, residual RMS after)."""
    res = _residual_matrix(fit.estimate)
    rms = [float(math.sqrt(np.mean(res[:, j]**2))) for j in range(res.shape[1])]
    return {'effect': fit.effect, 'variant': fit.variant, 'delta_loglik': float(dll),
            'criterion': float(criterion), 'validation_rms': validation_rms,
            'residual_rms': _overall(rms),
            'excess_over_floor': _overall(rms) / _overall(floors) - 1.0,
            'adequate': _adequate(fit, floors, u, t), 'fit': fit}


def _say_t(ctx, text):
    _say(ctx['progress'], f'{text} ({time.perf_counter() - ctx["t_start"]:.1f} s)')


def _prefer_established(near, mu=0.0):
    """
    Drop rig effects from near-tied candidates that tie with their first-order equivalent.

    A pitch actuator lag and a sensor lag (or δ3 and a flap-frequency change) fit alike at
    these sizes; the effect that is the same physics and was in the catalogue first is named,
    and the note names both. ``mu``: the record's advance ratio (in forward flight δ3 and a
    pitch-actuator lag are physics of their own, :func:`~rotor_id.diagnosis.catalogue.equivalent`).
    A tie is a criterion within :data:`EQUIVALENT_TIE`: the two are one physics exactly (δ3
    and P at μ = 0 without a wake fit to the same likelihood), or nearly so. Where the record
    tells them apart, the one with the higher likelihood is kept and the other dropped: with
    a wake δ3 also drives the inflow, and beside a sensor lag δ3 led the flap-frequency
    change by 5 (the held-out RMS, which decides between other near-tied candidates, 0.15 %
    the other way); naming P left the wake's parameters 3.3σ off, naming δ3 1.6σ, with
    K_P = 0.097 ± 0.011 against 0.1.
    """
    def effect_of(t):
        return t[2].effect if isinstance(t, tuple) else t['effect']

    def criterion_of(t):
        return t[0] if isinstance(t, tuple) else t['criterion']

    def set_aside(t, o):
        """Whether t gives way to its equivalent o (rig effects to established ones in a tie)."""
        if effect_of(o) not in equivalent(effect_of(t), mu) \
                or (effect_of(t) in RIG_EFFECTS) == (effect_of(o) in RIG_EFFECTS):
            return False
        if effect_of(t) in RIG_EFFECTS:
            return criterion_of(o) >= criterion_of(t) - EQUIVALENT_TIE
        return criterion_of(o) > criterion_of(t) + EQUIVALENT_TIE
    keep = [t for t in near if not any(set_aside(t, o) for o in near)]
    return keep or near


def _ctx_job(ctx, effect, variant, **options):
    """Return a candidate :class:`Job` on the diagnosis's record, description and values."""
    return Job(effect, variant, ctx['record'], ctx['description'], ctx['values'],
               ctx['unknowns'], ctx['known'], ctx['window_s'], **options)


def _candidate_jobs(current, kept, ctx):
    """
    Jobs of every effect that can still be added to the kept ones (screened first).

    Every score test is recorded in the step's trace (``ctx['trace'][-1]``). Effects that
    have no score test are always fitted, also when the current residuals look like noise.
    """
    est = current.estimate
    start = {n: est.model_parameters[n] for n in current.unknowns}
    names = {e for e, _ in kept}
    excluded = set(names)
    for e in names:
        excluded.update(equivalent(e, ctx['mu']))
    noise_var = np.asarray(est.noise_std, dtype=float)**2
    jobs = []
    for effect in ctx['effects']:
        if effect in excluded or applicable(effect, ctx['model_name'], ctx['rotor'],
                                            ctx['unknowns']):
            continue
        job = _ctx_job(ctx, effect, '', verbose=ctx['verbose'],
                       baseline_nll=est.neg_log_likelihood, start=start, prior=tuple(kept))
        if ctx['screen'] and effect in SCREENED:
            verdict = _screen(job, noise_var, ctx['n_obs'], ctx['n_blades'])
            if not verdict['fit']:
                _say_t(ctx, f'  + {effect}: screened out, score test 2Δlog L ≈ '
                            f'{verdict["lm"]:.1f}')
                ctx['trace'][-1]['gains'][effect] = _score_test_gain(
                    verdict, ctx['n_obs'], ctx['n_blades'])
                continue
            job = _replace(job, variant=verdict['variant'])
        jobs.append(job)
    return jobs


def _score_test_gain(verdict, n_obs, n_blades):
    """Return what a screened-out effect would gain: 2Δlog L ≈ LM, criterion with ρ = 1."""
    lm = float(verdict['lm'])
    crit = lm - verdict['k'] * math.log(n_obs)
    if n_choices(verdict['effect'], n_blades) > 1:
        crit -= 2.0 * math.log(n_choices(verdict['effect'], n_blades))
    return {'two_delta_loglik': lm, 'criterion': crit, 'how': 'score test'}


def _standalone_gains(scored, screened_out, n_obs, n_blades):
    """Return the first row of the trace: what each effect gains alone at the baseline."""
    gains = {e: {'two_delta_loglik': 2.0 * s['delta_loglik'], 'criterion': s['criterion'],
                 'how': 'fit'} for e, s in scored.items() if e != 'process_noise'}
    for v in screened_out:
        if math.isfinite(v['lm']):
            gains[v['effect']] = _score_test_gain(v, n_obs, n_blades)
    return {'after': (), 'gains': gains}


def _confounds(kept_names, ctx):
    """
    Return {kept effect: [confound]}: effects the kept ones reproduce in this record.

    An effect C is confounded with a kept effect K when C passed the criterion at some step
    of the selection (alone at the baseline, first row of ``ctx['trace']``, or on top of the
    effects kept by then: a second effect can hide C at the baseline, as a flap-frequency
    error hides an azimuth offset at μ = 0.4) but, with all the kept effects in the model,
    gains less than the criterion's threshold (last row, the selection's final step): in
    this record K does what C would do, to within the noise, so the data can neither confirm
    nor exclude C beside K. K is the kept effect whose addition after that step took the most
    of C's likelihood gain away. First-order equivalents of kept effects in this record are
    said apart (:func:`rotor_id.diagnosis.catalogue.equivalent`).
    """
    trace = ctx['trace']
    out = {k: [] for k in kept_names}
    if len(trace) < 2 or tuple(trace[-1]['after']) != tuple(kept_names):
        return out              # the final model's step was not run (MAX_EFFECTS reached)
    covered = _covered(kept_names, ctx)
    for effect in dict.fromkeys(e for row in trace[:-1] for e in row['gains']):
        given = trace[-1]['gains'].get(effect)
        # the first step at which C passed the criterion (its gain given the effects kept then)
        first = next((i for i, row in enumerate(trace[:-1])
                      if effect in row['gains'] and _passed(row['gains'][effect])), None)
        if effect in covered or given is None or first is None or _passed(given):
            continue
        alone = trace[first]['gains'][effect]
        culprit, largest, previous = kept_names[min(first, len(kept_names) - 1)], -math.inf, \
            alone
        for row in trace[first + 1:]:
            now = row['gains'].get(effect)
            if now is None:
                continue
            drop = previous['two_delta_loglik'] - now['two_delta_loglik']
            if row['after'][-1] in kept_names and drop > largest:
                culprit, largest = row['after'][-1], drop
            previous = now
        out[culprit].append({
            'effect': effect, 'given': list(kept_names),
            'passed_after': list(trace[first]['after']),
            'two_delta_loglik_alone': float(alone['two_delta_loglik']),
            'criterion_alone': float(alone['criterion']),
            'two_delta_loglik_given': float(given['two_delta_loglik']),
            'criterion_given': float(given['criterion']), 'how_given': given['how'],
            'reproduced_fraction': _reproduced(alone, given)})
    return out


def _equivalents_here(one, eligible, trace, mu):
    """
    First-order equivalents of the named effect ``one`` that explain this record as well.

    An equivalent counts where it is eligible alone (the first table), or at a step of the
    selection where ``one`` is compared too, when it passes the criterion there within
    :data:`CONFIDENCE_GAP` of ``one`` (or above it): the catalogue names one of the two, and
    the other is the same physics in this record. A δ3 beside a sensor lag in hover gained
    more than the flap-frequency change named for it at step 2 and appeared in no note.
    Returns [{'effect', 'criterion', 'criterion_named', 'how'}], one per equivalent.
    """
    out = {}
    table = {t['effect']: t['criterion'] for t in eligible}
    for eq in equivalent(one, mu):
        if eq in table:
            out[eq] = {'effect': eq, 'criterion': float(table[eq]),
                       'criterion_named': (float(table[one]) if one in table else None),
                       'how': 'alone at the baseline'}
            continue
        for row in trace:
            mine, theirs = row['gains'].get(one), row['gains'].get(eq)
            if mine is None or theirs is None or theirs['how'] != 'fit' \
                    or not _passed(theirs) \
                    or theirs['criterion'] < mine['criterion'] - CONFIDENCE_GAP:
                continue
            after = ' + '.join(row['after'])
            out[eq] = {'effect': eq, 'criterion': float(theirs['criterion']),
                       'criterion_named': float(mine['criterion']),
                       'how': f'on top of {after}' if after else 'alone at the baseline'}
            break
    return list(out.values())


def _passed(gain):
    """
    Whether an effect's gain at a step of the selection passed that step's test.

    The criterion's threshold; beside random inflow the step's likelihood-ratio test
    (``passes``, :func:`rotor_id.diagnosis.noisy.step_test`).
    """
    return bool(gain.get('passes', gain['criterion'] > CRITERION_THRESHOLD))


def _covered(kept_names, ctx):
    """Return the kept effects and their first-order equivalents in this record."""
    covered = set(kept_names)
    for k in kept_names:
        covered.update(equivalent(k, ctx.get('mu', 0.0)))
    return covered


def _reproduced(alone, given):
    """Return the share of an effect's gain alone that the kept effects take away."""
    return float(1.0 - max(given['two_delta_loglik'], 0.0) / alone['two_delta_loglik'])


def _confound_text(kept, c):
    """One note of a confounded pair, with the figures behind it."""
    if c.get('how_given') == 'two_for_one':
        return (f'{" + ".join(c["alternative"])} fits this record within '
                f'{c["criterion_difference"]:.1f} of {" + ".join(c["given"])} by the criterion '
                f'(2Δlog L {c["two_delta_loglik_difference"]:.1f}, extra parameters charged; a '
                f'confident difference is {CONFIDENCE_GAP:g}): the two descriptions cannot be '
                f'told apart, so {" + ".join(c["alternative"])} may be present instead of '
                f'{kept}; all are named')
    if c.get('how_given') == 'exchange':
        others = [e for e in c['given'] if e != c['effect'] and e != kept]
        with_ = f' (with {" + ".join(others)})' if others else ''
        return (f'{c["effect"]} cannot be told apart from {kept} in this record: the model '
                f'with {c["effect"]} in place of {kept}{with_} fits within '
                f'{c["criterion_difference"]:.1f} of it by the criterion (2Δlog L '
                f'{c["two_delta_loglik_difference"]:.1f}; a confident difference is '
                f'{CONFIDENCE_GAP:g}), so {c["effect"]} may be present instead; both are named')
    before = ' + '.join(c.get('passed_after', ()))
    return (f'{c["effect"]} cannot be told apart from {kept} in this record: '
            f'{"with " + before + " in the model" if before else "alone"} it gains '
            f'2Δlog L = {c["two_delta_loglik_alone"]:.1f} (criterion '
            f'{c["criterion_alone"]:.1f}), with {" + ".join(c["given"])} in the model '
            f'{c["two_delta_loglik_given"]:.1f} (criterion {c["criterion_given"]:.1f}, '
            f'{c["how_given"]}; threshold {CRITERION_THRESHOLD:g}): '
            f'{" + ".join(c["given"])} '
            f'{"reproduce" if len(c["given"]) > 1 else "reproduces"} '
            f'{c["reproduced_fraction"]:.0%} of what '
            f'{c["effect"]} does here ({kept} took most of it), so '
            f'{c["effect"]} may be present too; both are named')


def _step_gain(fit, current, ctx):
    """
    Return what ``fit`` gains on top of ``current`` as a trace entry, or None.

    {'two_delta_loglik', 'criterion', 'how'}: 'fit' for a fit that is compared; a fit at a
    catalogue bound is not (issue 16, item 3), unless it is no better than ``current``:
    then it asks for none of the effect beside the kept ones (the current model is the limit
    beyond the bound, e.g. a lag → 0), so it gains nothing here. That entry is for the
    confounds, never for a choice: a pitch-actuator lag that passed alone (criterion 49) and
    ran to τ_a's bound beside a sensor lag was otherwise left out of every note while the
    sensor lag was named with high confidence.
    """
    if not fit.available:
        return None
    cur = current.estimate
    k = max(fit.n_extra - current.n_extra, 0)
    choices = 2.0 * math.log(n_choices(fit.effect, ctx['n_blades']))
    if fit.bound_limited:
        if fit.estimate.neg_log_likelihood < cur.neg_log_likelihood:
            return None
        _say_t(ctx, f'  + {fit.effect}: at its catalogue bound and no better than without '
                    'it, no gain')
        return {'two_delta_loglik': 0.0, 'criterion': -k * math.log(ctx['n_obs']) - choices,
                'how': 'fit, at its catalogue bound: no gain'}
    dll = float(cur.neg_log_likelihood - fit.estimate.neg_log_likelihood)
    res = np.concatenate(fit.estimate.residuals, axis=0)
    rho = rs.channels_effective_fraction(res)
    crit = 2.0 * dll * rho - k * math.log(ctx['n_obs'] * rho) - choices
    _say_t(ctx, f'  + {fit.effect}: Δlog L = {dll:.1f}, criterion {crit:.1f}')
    return {'two_delta_loglik': 2.0 * dll, 'criterion': crit, 'how': 'fit'}


def _forward_step(current, cur_val, kept, ctx):
    """
    Return the best effect to add to ``current`` as (row, fit), or None.

    The same tests as for the first effect, relative to the current model: criterion above
    :data:`CRITERION_THRESHOLD` and a better prediction of the unfitted half of the window.
    What every candidate gains is recorded in a new row of ``ctx['trace']``.
    """
    ctx['trace'].append({'after': tuple(e for e, _ in kept), 'gains': {}})
    jobs = _candidate_jobs(current, kept, ctx)
    if not jobs:
        return None
    _say_t(ctx, f'step {len(kept) + 1}: fitting {len(jobs)} effect(s) on top of '
                f'{" + ".join(e for e, _ in kept)}')
    fits = _fit_selection_jobs(jobs, ctx)
    scored = []
    for fit in fits:
        gain = _step_gain(fit, current, ctx)
        if gain is None:
            continue
        ctx['trace'][-1]['gains'][fit.effect] = gain
        if gain['how'] == 'fit' and gain['criterion'] > CRITERION_THRESHOLD:
            scored.append((gain['criterion'], 0.5 * gain['two_delta_loglik'], fit))
    scored.sort(key=lambda c: -c[0])
    scored = scored[:MAX_VALIDATED]
    if not scored:
        return None
    val_jobs = [_ctx_job(ctx, f.effect, f.variant, prior=tuple(kept),
                         start={n: f.estimate.model_parameters[n] for n in f.unknowns},
                         bounds=f.bounds) for _, _, f in scored]
    vals = {e: v for e, _, v in _run_validation(val_jobs, ctx['workers'], lambda r: None)}
    ok = [(c, d, f) for c, d, f in scored
          if vals.get(f.effect) is not None and (cur_val is None or vals[f.effect] < cur_val)]
    if not ok:
        return None
    best = ok[0]
    near = _prefer_established([c for c in ok if best[0] - c[0] <= CONFIDENCE_GAP],
                               ctx['mu'])
    best = near[0]
    if len(near) > 1:
        best = min(near, key=lambda c: vals[c[2].effect])
    crit, dll, fit = best
    row = _step_row(fit, dll, crit, vals[fit.effect], ctx['floors'], ctx['u'], ctx['t'])
    return row, fit


def _without(effect, fit, kept, ctx):
    """Refit ``fit``'s model without ``effect`` (backward check): the fit, or None."""
    rest = [(e, v) for e, v in kept if e != effect]
    new = (fit.effect, fit.variant)
    others = [ev for ev in rest if ev != new]
    start = {n: fit.estimate.model_parameters[n] for n in fit.unknowns}
    job = _ctx_job(ctx, new[0], new[1], prior=tuple(others), start=start)
    out = _fit_once(ctx, job)
    return out if out.available else None


def _criterion_over(fit, other, n_obs, rival=False):
    """
    (2Δlog L, criterion) of ``fit`` over ``other``, with ρ of ``fit``'s residuals.

    ``other`` is nested in ``fit`` (k ≥ 0 extra parameters), or with ``rival`` a model that
    is not (an exchange: k may be negative, fewer parameters earn credit).
    """
    dll = float(other.estimate.neg_log_likelihood - fit.estimate.neg_log_likelihood)
    res = np.concatenate(fit.estimate.residuals, axis=0)
    rho = rs.channels_effective_fraction(res)
    k = fit.n_extra - other.n_extra
    if not rival:
        k = max(k, 0)
    return 2.0 * dll, 2.0 * dll * rho - k * math.log(n_obs * rho)


def _add_effects(current, cur_val, kept, steps, dropped, ctx):
    """
    Forward steps with a backward check after each: (current, cur_val, kept, steps).

    After each addition every effect kept before is tested by refitting without it: it
    stays only if its criterion, given the others, still exceeds the threshold.
    """
    # Residuals that pass the omnibus tests (white, at the floor, no mean) do not stop the
    # selection: a directed test (one effect's likelihood ratio) has far more power than the
    # omnibus one; a lag hidden under a per-blade gain passes whiteness and RMS and still
    # gains a criterion of ~100. Nor do they spare the fits without a score test: the
    # periodic coefficients under a large flap-frequency error (residuals white, 6 % above
    # the floor) gain 2Δlog L ≈ 120, and skipping them named the frequency alone, γ 5σ off.
    while len(kept) < MAX_EFFECTS:
        found = _forward_step(current, cur_val, kept, ctx)
        if found is None:
            break
        row, fit = found
        kept.append((fit.effect, fit.variant))
        steps.append(row)
        _say_t(ctx, f'step {len(kept)}: + {fit.effect} (criterion {row["criterion"]:.1f}, '
                    f'residual RMS {row["residual_rms"]:.4g} rad)')
        current, cur_val = fit, row['validation_rms']
        for old, variant in list(kept[:-1]):
            without = _without(old, current, kept, ctx)
            if without is None:
                continue
            _, crit = _criterion_over(current, without, ctx['n_obs'])
            if crit > CRITERION_THRESHOLD:
                continue
            _say_t(ctx, f'backward check: {old} no longer earns its place '
                        f'(criterion {crit:.1f} given the others); dropped')
            kept.remove((old, variant))
            dropped.append(old)
            steps = [st for st in steps if st['effect'] != old]
            current = without
            steps[-1]['fit'] = current
    return current, cur_val, kept, steps


def _forward_selection(first, steps, ctx):
    """
    Add effects one at a time until the residuals are noise or no effect earns its place.

    Returns (the fit of the final model, the step rows, the effects dropped by the backward
    check or an exchange). When two or more effects are kept, one exchange round follows
    (:func:`_exchange`): greedy selection can keep first an effect that stands in for parts
    of two concealed ones; the effects are added again after a swap.
    """
    current, kept, dropped = first, [(first.effect, first.variant)], []
    ctx['two_for_one_ties'], ctx['replaced'] = [], []
    cur_val = steps[0]['validation_rms']
    current, cur_val, kept, steps = _add_effects(current, cur_val, kept, steps, dropped, ctx)
    ahead = _look_ahead(current, kept, steps, ctx)
    if ahead is not None:
        current, kept, steps, gone = ahead
        dropped += gone
        cur_val = None
        current, cur_val, kept, steps = _add_effects(current, cur_val, kept, steps, dropped,
                                                     ctx)
    current, cur_val, kept, steps, ties = _exchange_round(current, cur_val, kept, steps,
                                                          dropped, ctx)
    if len(kept) < MAX_EFFECTS and ctx['mu'] > 0.0:
        # forward flight only: there the 1/rev terms make two effects look like a third that
        # is not their first-order equivalent (P + azimuth offset as δ3). In hover the
        # catalogue's equivalences already name what can stand in for what; there the
        # exchange changed no verdict in 15 pair runs and cost 5x on a sensor-lag record
        alt = _two_for_one(current, kept, steps, ctx)
        ties += alt['ties']
        if alt['fit'] is not None:
            names = [e for e, _ in kept]
            _say_t(ctx, f'two-for-one: {" + ".join(e for e, _ in alt["kept"])} replaces '
                        f'{" + ".join(names)} (criterion {alt["criterion"]:.1f})')
            gone = [e for e in names if e not in {a for a, _ in alt['kept']}]
            ctx['replaced'].append(
                f'{" + ".join(gone)} replaced by {" + ".join(e for e, _ in alt["kept"])}, '
                f'which fit(s) better by a criterion of {alt["criterion"]:.1f} (2Δlog L '
                f'{alt["two_delta_loglik"]:.1f}, the extra parameters charged): the greedy '
                f'selection had kept {" + ".join(gone)}, a stand-in for effects found '
                'together')
            current, kept, steps = alt['fit'], alt['kept'], alt['steps']
    names = [e for e, _ in kept]
    confounds = _with_ties(_confounds(names, ctx), ties, names, ctx)
    for st in steps:
        st['parameters'] = current.effect_parameters.get(st['effect'], {})
        st['confounds'] = confounds.get(st['effect'], [])
    return current, steps, dropped


def _with_ties(confounds, ties, names, ctx):
    """
    Add the near ties of the exchanges to the kept effects' confounds; return the confounds.

    ``confounds``: kept effect -> its confounds (:func:`_confounds`); ``names``: the kept
    effects. A two-for-one tie whose loser is a confound already goes to
    ``ctx['two_for_one_ties']`` (its note, and the confidence it takes away).
    """
    for tie in ties:
        if tie['winner'] not in confounds or tie['effect'] in names:
            continue
        if tie['how_given'] == 'exchange':
            # a whole model with the loser in the winner's place fits within the gap: closer
            # evidence than what the loser gains beside the kept effects, so it replaces that
            # (and takes the confidence away). Kept with the step's figures instead, the wake
            # that lost an exchange by a criterion of 1.3 left sensor offsets named with high
            # confidence and γ 17σ off (inflow+periodic, seed 1001)
            for winner in confounds:
                confounds[winner] = [c for c in confounds[winner]
                                     if c['effect'] != tie['effect']]
            confounds[tie['winner']].append(tie)
        elif not any(c['effect'] == tie['effect'] for cs in confounds.values() for c in cs):
            confounds[tie['winner']].append(tie)
        elif tie['how_given'] == 'two_for_one':
            # already a confound of a kept effect: the two-effect alternative still gets its
            # note and still takes the confidence away
            ctx['two_for_one_ties'].append(tie)
    return confounds


def _exchange_round(current, cur_val, kept, steps, dropped, ctx):
    """
    Run one exchange round (:func:`_exchange`) and, after a swap, the selection again.

    After a swap: the backward check and the forward steps. Returns (current, cur_val, kept,
    steps, ties).
    """
    if len(kept) < 2:
        return current, cur_val, kept, steps, []
    swap = _exchange(current, kept, ctx)
    if swap['fit'] is not None:
        fit = swap['fit']
        _say_t(ctx, f'exchange: {swap["out"]} replaced by {fit.effect} (criterion '
                    f'{swap["criterion"]:.1f} over the model with {swap["out"]})')
        kept = [ev for ev in kept if ev[0] != swap['out']] + [(fit.effect, fit.variant)]
        steps = [st for st in steps if st['effect'] != swap['out']] + [swap['row']]
        dropped.append(swap['out'])
        current, cur_val = fit, swap['row']['validation_rms']
        current, kept, steps = _backward(current, kept, steps, dropped, ctx)
        current, cur_val, kept, steps = _add_effects(current, cur_val, kept, steps, dropped,
                                                     ctx)
    return current, cur_val, kept, steps, swap['ties']


def _look_ahead(current, kept, steps, ctx):
    """
    One step past the criterion when the selection ends with structured residuals.

    A stand-in kept first can leave the concealed effects below the criterion one at a time
    (μ = 0.4, periodic terms and a sensor lag: a flap-frequency change is kept first; the
    periodic terms then gain 2Δlog L = 93 but, on residuals still coloured by the lag, a
    criterion of 9, and the lag's score test is 5). The effect that gains most on top of the
    final model is added anyway, the next forward step is taken, and every kept effect must
    then earn its place given the others (backward check). The result is kept only if it
    beats the final model by the criterion. Returns (fit, kept, steps, dropped) or None.
    """
    if len(kept) >= MAX_EFFECTS - 1 or _adequate(current, ctx['floors'], ctx['u'], ctx['t']):
        return None
    names = [e for e, _ in kept]
    covered = _covered(names, ctx)
    gains = ctx['trace'][-1]['gains'] if ctx['trace'] else {}
    fitted = [e for e, g in gains.items() if e not in covered and g['how'] == 'fit'
              and g['two_delta_loglik'] > EXCHANGE_MIN_GAIN]
    if not fitted:
        return None
    best = max(fitted, key=lambda e: gains[e]['two_delta_loglik'])
    _say_t(ctx, f'look-ahead: the residuals are structured; {best} added past the criterion '
                f'(2Δlog L = {gains[best]["two_delta_loglik"]:.1f}) to see what follows')
    start = {n: current.estimate.model_parameters[n] for n in current.unknowns}
    fit = _fit_once(ctx, _ctx_job(ctx, best, '', verbose=ctx['verbose'], start=start,
                                  prior=tuple(kept),
                                  baseline_nll=current.estimate.neg_log_likelihood))
    if not fit.available or fit.bound_limited:
        return None
    two_dll, crit = _criterion_over(fit, current, ctx['n_obs'])
    row = _step_row(fit, 0.5 * two_dll, crit, None, ctx['floors'], ctx['u'], ctx['t'])
    trial_kept, trial_steps, gone = list(kept) + [(fit.effect, fit.variant)], steps + [row], []
    trial, _, trial_kept, trial_steps = _add_effects(fit, None, trial_kept, trial_steps, gone,
                                                     ctx)
    trial, trial_kept, trial_steps = _backward(trial, trial_kept, trial_steps, gone, ctx)
    _, gain = _criterion_over(trial, current, ctx['n_obs'])
    if gain <= CRITERION_THRESHOLD or [e for e, _ in trial_kept] == names:
        _say_t(ctx, f'look-ahead: {" + ".join(e for e, _ in trial_kept)} does not beat '
                    f'{" + ".join(names)} (criterion {gain:.1f}); kept the latter')
        ctx['trace'].append({'after': tuple(names), 'gains': dict(gains)})
        return None
    _say_t(ctx, f'look-ahead: {" + ".join(e for e, _ in trial_kept)} beats '
                f'{" + ".join(names)} by a criterion of {gain:.1f}')
    for st in trial_steps:
        st['fit'] = trial
    return trial, trial_kept, trial_steps, gone


def _backward(current, kept, steps, dropped, ctx):
    """Drop every kept effect that does not earn its place given all the others."""
    for old, variant in list(kept):
        if len(kept) < 2:
            break
        without = _refit([ev for ev in kept if ev != (old, variant)], ctx, current)
        if without is None:
            continue
        _, crit = _criterion_over(current, without, ctx['n_obs'])
        if crit <= CRITERION_THRESHOLD:
            _say_t(ctx, f'backward check: {old} does not earn its place given the others '
                        f'(criterion {crit:.1f}); dropped')
            kept.remove((old, variant))
            steps = [st for st in steps if st['effect'] != old]
            dropped.append(old)
            current = without
    for st in steps:
        st['fit'] = current
    return current, kept, steps


def _refit(kept, ctx, like):
    """Fit the model of the kept effects [(effect, variant)], started from ``like``."""
    start = {n: like.estimate.model_parameters[n] for n in like.unknowns}
    out = _fit_once(ctx, _ctx_job(ctx, kept[-1][0], kept[-1][1], prior=tuple(kept[:-1]),
                                  start=start))
    return out if out.available else None


#: Contenders tried by an exchange: the strongest effects not kept, by what they gain on top
#: of the final model.
EXCHANGE_CONTENDERS = 2
#: 2Δlog L a contender must gain on top of the final model to be tried in an exchange (the
#: 5 % point of χ² with one degree of freedom: a trace of the effect, not yet evidence).
EXCHANGE_MIN_GAIN = 3.84


def _exchange(current, kept, ctx):
    """
    Try replacing one kept effect by a contender (one exchange round of stepwise selection).

    Forward selection is greedy: an effect that reproduces parts of two concealed effects can
    be kept first, and then one of those no longer passes beside it. Contenders are the
    effects not kept that passed the criterion at some step or still gain 2Δlog L >
    :data:`EXCHANGE_MIN_GAIN` on the final model. At μ = 0.4 a flap read
    early (negative time delay) turns the steady 1/rev flapping as an azimuth offset does and
    as a flap-frequency error partly does; kept with δ3, it left the azimuth offset at a
    criterion of 3. Each contender (the strongest :data:`EXCHANGE_CONTENDERS` by their best
    2Δlog L) is fitted in place of each kept effect. The best swap is made when it beats the
    final model by the criterion and still earns its place given the others. A swap within
    :data:`CONFIDENCE_GAP` of the final model either way is a tie: the record cannot tell the
    two descriptions apart, and the loser is reported as confounded with the winner.

    Returns {'fit', 'out', 'criterion', 'row', 'ties'} ('fit' None: no swap).
    """
    names = [e for e, _ in kept]
    out = {'fit': None, 'ties': []}
    covered = _covered(names, ctx)
    # what each effect gained at its best: on the final model, or at any earlier step where
    # it passed the criterion (an effect a stand-in absorbed gains little at the end)
    best = {}
    for i, row in enumerate(ctx['trace']):
        for e, g in row['gains'].items():
            if e in covered or not (g['criterion'] > CRITERION_THRESHOLD or (
                    i == len(ctx['trace']) - 1 and g['two_delta_loglik'] > EXCHANGE_MIN_GAIN)):
                continue
            best[e] = max(best.get(e, -math.inf), g['two_delta_loglik'])
    contenders = sorted(best, key=lambda e: -best[e])[:EXCHANGE_CONTENDERS]
    start = {n: current.estimate.model_parameters[n] for n in current.unknowns}
    jobs = [_ctx_job(ctx, c, '', verbose=ctx['verbose'],
                     baseline_nll=current.estimate.neg_log_likelihood, start=start,
                     prior=tuple(ev for ev in kept if ev[0] != k))
            for c in contenders for k in names]
    if not jobs:
        return out
    _say_t(ctx, f'exchange: fitting {", ".join(contenders)} in place of each of '
                f'{" + ".join(names)}')
    scored = []
    for fit in _fit_selection_jobs(jobs, ctx):
        if not fit.available or fit.bound_limited:
            _say_t(ctx, f'  {fit.effect} after {" + ".join(p for p, _ in fit.prior)}: '
                        f'{fit.reason or "bound-limited"}, not compared')
            continue
        replaced = next(e for e in names if e not in {p for p, _ in fit.prior})
        two_dll, crit = _criterion_over(fit, current, ctx['n_obs'], rival=True)
        crit -= 2.0 * math.log(n_choices(fit.effect, ctx['n_blades']))
        _say_t(ctx, f'  {fit.effect} for {replaced}: 2Δlog L = {two_dll:.1f}, criterion '
                    f'{crit:.1f} over the final model')
        scored.append((crit, two_dll, replaced, fit))
    if not scored:
        return out
    scored.sort(key=lambda c: -c[0])
    crit, two_dll, replaced, fit = scored[0]
    tie = {'effect': fit.effect if crit <= 0 else replaced,
           'winner': replaced if crit <= 0 else fit.effect, 'given': list(names),
           'how_given': 'exchange', 'criterion_difference': float(abs(crit)),
           'two_delta_loglik_difference': float(abs(two_dll))}
    if abs(crit) <= CONFIDENCE_GAP:
        out['ties'] = [tie]
    if crit <= 0:
        return out
    kept_tie = [{**tie, 'effect': fit.effect, 'winner': replaced}] if out['ties'] else []
    # what the swapped-in effect adds to the others alone (its own backward check)
    others = [ev for ev in kept if ev[0] != replaced]
    rest = _ctx_job(ctx, others[-1][0], others[-1][1], prior=tuple(others[:-1]), start=start)
    base = _fit_once(ctx, rest)
    if not base.available:
        out['ties'] = kept_tie
        return out
    add_2dll, add_crit = _criterion_over(fit, base, ctx['n_obs'])
    if add_crit <= CRITERION_THRESHOLD:
        out['ties'] = kept_tie
        return out
    val = _run_validation([_ctx_job(ctx, fit.effect, fit.variant, prior=tuple(others),
                                    start={n: fit.estimate.model_parameters[n]
                                           for n in fit.unknowns}, bounds=fit.bounds)],
                          ctx['workers'], lambda r: None)
    row = _step_row(fit, 0.5 * add_2dll, add_crit, val[0][2] if val else None, ctx['floors'],
                    ctx['u'], ctx['t'])
    out.update(fit=fit, out=replaced, criterion=crit, row=row)
    return out


#: Share of a candidate's own gain that the kept effects must take away before the candidate
#: is tried as a partial stand-in (:func:`_partial_stand_ins`): most of what it explains
#: alone, the kept effects explain too.
PARTIAL_REPRODUCED = 0.5


def _partial_stand_ins(kept_names, ctx):
    """
    Return candidates that explain part of what the kept effects explain, short of the criterion.

    A candidate C with positive evidence alone at the baseline (criterion above 0, below the
    threshold: not a confound, :func:`_confounds`) of which the kept effects take at least
    :data:`PARTIAL_REPRODUCED` of the gain away. Two concealed effects can each fall short
    alone while a third catalogue effect stands in for both: at μ = 0.25 per-blade sensor
    biases and an azimuth offset together look like per-blade sensor gains (the gains won
    by 2Δlog L 65 against 43 and 26 alone, each short of the criterion alone, and beside the
    gains neither passed), a confident wrong verdict with the original parameters 7.8σ off.
    Entries as :func:`_confounds`' (those the two-for-one search reads). Asked only when
    one effect is kept: the verdict then names one effect where two may be present; with two
    kept, each further search doubled the CPU of a μ = 0.4 pair diagnosis and changed no
    verdict in 40 pair runs.
    """
    trace = ctx['trace']
    if len(trace) < 2 or tuple(trace[-1]['after']) != tuple(kept_names):
        return []
    covered = _covered(kept_names, ctx)
    out = []
    for effect, alone in trace[0]['gains'].items():
        given = trace[-1]['gains'].get(effect)
        if effect in covered or given is None or alone['how'] != 'fit' \
                or not 0.0 < alone['criterion'] <= CRITERION_THRESHOLD \
                or given['criterion'] > CRITERION_THRESHOLD:
            continue
        reproduced = _reproduced(alone, given)
        if reproduced >= PARTIAL_REPRODUCED:
            out.append({'effect': effect, 'criterion_alone': float(alone['criterion']),
                        'two_delta_loglik_alone': float(alone['two_delta_loglik']),
                        'reproduced_fraction': reproduced})
    return out


#: Stand-ins of the dominant effect tried by :func:`_two_for_one` (the strongest by their
#: own gain): each costs a forward selection and an exchange round.
TWO_FOR_ONE_STAND_INS = 1


def _two_for_one(current, kept, steps, ctx):
    """
    Try the stand-in C of the dominant effect E, plus what C lets in, in place of E.

    Two concealed effects together can look like a third catalogue effect alone in forward
    flight: at μ = 0.4 a flap-frequency error and an azimuth offset together look like δ3
    (δ3 beats P alone by a criterion of 16, and beside δ3 the azimuth gains 2Δlog L ≈ 9), so
    δ3 is kept first and the selection stops. The one-for-one exchange needs two kept
    effects and swaps one name for one name; here one name stands for two. E is the kept
    effect with the largest criterion (the name the verdict gives); its stand-ins are the
    effects it reproduces in this record (its confounds: each passed the criterion at some
    step and no longer passes beside E, :func:`_confounds`) or, when it has none, the
    effects that explain part of it short of the criterion (:func:`_partial_stand_ins`). For
    each of the
    :data:`TWO_FOR_ONE_STAND_INS` strongest, C replaces E and the selection (forward steps
    with backward checks, then an exchange round) starts again from there, so the second
    effect must earn its place given C by the criterion and the held-out prediction as any
    other. The alternative is compared
    with the final model by the criterion, which charges the extra parameters
    (k log(n ρ)): it replaces it when it is better. Within :data:`CONFIDENCE_GAP` either way
    the record cannot tell the two descriptions apart: the loser is reported as a tie (the
    dominant name gets low confidence; the note gives both criteria).

    Returns {'fit', 'kept', 'steps', 'criterion', 'ties'} ('fit' None: no replacement).
    """
    out = {'fit': None, 'ties': []}
    names = [e for e, _ in kept]
    trace = ctx['trace']
    dominant = max(steps, key=lambda st: st['criterion'])['effect']
    stand_ins = [(dominant, c['effect'], c['criterion_alone'])
                 for c in sorted(_confounds(names, ctx).get(dominant, []) or
                                 (_partial_stand_ins(names, ctx) if len(names) == 1 else []),
                                 key=lambda c: -c['criterion_alone'])[:TWO_FOR_ONE_STAND_INS]]
    best = None
    for replaced, stand_in, _ in sorted(stand_ins, key=lambda s: -s[2]):
        others = [ev for ev in kept if ev[0] != replaced]
        start = {n: current.estimate.model_parameters[n] for n in current.unknowns}
        _say_t(ctx, f'two-for-one: {stand_in} in place of {replaced}, then the selection '
                    'again')
        fit = _fit_once(ctx, _ctx_job(ctx, stand_in, '', verbose=ctx['verbose'],
                                      start=start, prior=tuple(others),
                                      baseline_nll=current.estimate.neg_log_likelihood))
        if not fit.available or fit.bound_limited:
            continue
        # the stand-in's own row: what it adds to the effects kept beside it (the baseline's
        # candidate table when it stands alone)
        ctx['trace'] = trace[:1]
        base = _refit(others, ctx, current) if others else None
        if others and base is None:
            continue
        two_dll, crit = _criterion_over(fit, base, ctx['n_obs']) if base is not None else (
            trace[0]['gains'].get(stand_in, {}).get('two_delta_loglik', math.nan),
            trace[0]['gains'].get(stand_in, {}).get('criterion', math.nan))
        row = _step_row(fit, 0.5 * two_dll, crit, None, ctx['floors'], ctx['u'], ctx['t'])
        kept_rows = [st for st in steps if st['effect'] != replaced]
        alt_kept, alt_steps = list(others) + [(fit.effect, fit.variant)], kept_rows + [row]
        alt, alt_val, alt_kept, alt_steps = _add_effects(fit, None, alt_kept, alt_steps, [],
                                                         ctx)
        # the stand-in may leave a second effect's stand-in kept (a flap read early standing
        # in for the azimuth offset): the same exchange round as the greedy selection's
        alt, _, alt_kept, alt_steps, _ = _exchange_round(alt, alt_val, alt_kept, alt_steps,
                                                         [], ctx)
        alt_trace = ctx['trace']
        ctx['trace'] = trace
        alt_names = [e for e, _ in alt_kept]
        if set(alt_names) in (set(names), {e for e, _ in others} | {stand_in}):
            # back where it started, or a plain swap of one name for another: the choice
            # among near ties (held-out prediction) and the confidence gap judge that
            _say_t(ctx, f'two-for-one: from {stand_in} the selection finds '
                        f'{" + ".join(alt_names)}, no second effect')
            continue
        two_dll, crit = _criterion_over(alt, current, ctx['n_obs'], rival=True)
        _say_t(ctx, f'two-for-one: {" + ".join(alt_names)} against {" + ".join(names)}: '
                    f'2Δlog L = {two_dll:.1f}, criterion {crit:.1f}')
        if best is None or crit > best['criterion']:
            best = {'fit': alt, 'kept': alt_kept, 'steps': alt_steps, 'criterion': crit,
                    'two_delta_loglik': two_dll, 'trace': alt_trace, 'replaced': replaced,
                    'stand_in': stand_in}
    if best is None:
        return out
    crit = best['criterion']
    alt_names = [e for e, _ in best['kept']]
    new = [e for e in alt_names if e not in names]
    if abs(crit) <= CONFIDENCE_GAP:
        # the loser may be present instead: reported with the winner's dominant effect
        tie = {'how_given': 'two_for_one', 'criterion_difference': float(abs(crit)),
               'two_delta_loglik_difference': float(abs(best['two_delta_loglik']))}
        if crit > 0:
            out['ties'] = [{**tie, 'effect': best['replaced'], 'winner': best['stand_in'],
                            'given': alt_names, 'alternative': names}]
        else:
            out['ties'] = [{**tie, 'effect': e, 'winner': best['replaced'], 'given': names,
                            'alternative': alt_names} for e in new]
    if crit <= 0:
        return out
    ctx['trace'] = best['trace']
    for st in best['steps']:
        st['fit'] = best['fit']
    out.update(fit=best['fit'], kept=best['kept'], steps=best['steps'], criterion=crit,
               two_delta_loglik=best['two_delta_loglik'])
    return out


def _bound_text(fit):
    """Return 'name = value' of the bound-limited parameters."""
    return ', '.join(f'{n} = {fit.estimate.model_parameters[n]:.4g}'
                     for n in fit.bound_limited)


def _adequate(fit, floors, u, t):
    """Return whether a deterministic candidate leaves white residuals at the noise floor."""
    if fit.effect == 'process_noise':
        return False
    est = fit.estimate
    if len(est.residuals) > 1:
        res = np.column_stack([r[:, 0] for r in est.residuals])
    else:
        res = est.residuals[0]
    stats = [rs.channel_stats(str(j), res[:, j], floors[j], u, 1, t)
             for j in range(res.shape[1])]
    return bool(rs.combined_whiteness_p(stats) > 1e-3 and max(s.z_excess for s in stats) < 4.0)


def _choose(eligible, mu=0.0):
    """
    Return the explanation among the eligible candidates, and whether noise was passed over.

    ``eligible`` is ranked by criterion; the flag says whether process_noise ranked higher
    than the chosen, adequate deterministic candidate. Random inflow (filter-error
    likelihood) can absorb any unmodelled dynamics, so it is chosen only when no
    deterministic candidate leaves white residuals at the floor. Among candidates within
    :data:`CONFIDENCE_GAP` of the best criterion, the one that predicts the unfitted half of
    the window best wins (cross-validation decides what BIC cannot).
    """
    if not eligible:
        return None, False
    deterministic = [t for t in eligible if t['effect'] != 'process_noise' and t['adequate']]
    pool = deterministic or eligible
    best = pool[0]
    near = _prefer_established([t for t in pool
                                if best['criterion'] - t['criterion'] <= CONFIDENCE_GAP], mu)
    best = near[0]
    if len(near) > 1 and all(t['validation_rms'] is not None for t in near):
        best = min(near, key=lambda t: t['validation_rms'])
    passed_over = bool(deterministic) and any(
        t['effect'] == 'process_noise' and t['criterion'] > best['criterion'] for t in eligible)
    return best, passed_over


def _location(channels, stats_base, t, part, mismatch, n_ch):
    flagged = [c for c, s in zip(channels, stats_base) if s.flagged(n_ch)]
    if not flagged and mismatch:
        order = sorted(zip(channels, stats_base), key=lambda cs: -cs[1].z_excess)
        flagged = [c for c, s in order if s.z_excess > 2.0][:4] or [order[0][0]]
    use = flagged or [c for c in channels if c.model_channel]
    dt = float(np.median(np.diff(t)))
    band = rs.band_of_excess([c.residual for c in use], [c.floor for c in use], dt)
    t0, t1 = rs.span_of_excess([c.residual for c in use], [c.floor for c in use], t)
    window_s = [float(np.interp(t0, part.t, part.time_s)),
                float(np.interp(t1, part.t, part.time_s))]
    return {'channels': [c.name for c in flagged], 'band_per_rev': [band[0], band[1]],
            'window_s': window_s}
