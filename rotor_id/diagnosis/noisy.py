"""
Deterministic effects under random inflow: the selection by the innovations likelihood (issue 16).

Random inflow (``process_noise``) is fitted by filter error; every deterministic candidate by
output error. A recording with turbulence *and* a sensor offset is then named one or the
other: the output-error likelihood of the offset is swamped by the turbulence, and once the
filter-error model wins nothing was added to it. Here the two are put together:

* **deterministic effects on top of random inflow** (:func:`add_deterministic`): forward
  selection with the filter-error (innovations) likelihood
  J = ½ Σ_j [ν_jᵀ B_j⁻¹ ν_j + log|B_j|] (Ch.1 eq. 26) as the criterion. Each candidate is the
  augmented model of the catalogue (the same stack as output error's,
  :func:`rotor_id.diagnosis.catalogue._build`), fitted with σ_V and the measurement σ's
  estimated (:func:`rotor_id.estimation.filter_error.fit_filter_error_ml`). The nested ones
  are first screened by the score test of the innovations likelihood at the current
  estimate, LM = gᵀ M⁻¹ g (g, M the gradient and Fisher information of J with the extra
  parameters at their neutral values): one filter pass with sensitivities instead of a fit.
  An effect is added when its likelihood-ratio test, 2ΔJ·ρ against the χ²_k quantile at a
  family-wise level over the step's alternatives, passes with a positive criterion
  (:func:`step_test`), and its one-step prediction of the unfitted half of the window
  (innovation RMS, both ways) beats the current model's. Candidates are ranked by the
  criterion 2ΔJ·ρ − k log(nρ) (as output error's). A backward check follows each addition,
  and at the end random inflow itself must still earn its place against the output-error
  fit of the same deterministic model.
* **random inflow on top of deterministic effects** (:func:`add_random_inflow`): after the
  output-error selection, the score test of σ_V² at 0 on the final model (one filter pass:
  at σ_V = 0 the filter is output error, so the model's own gradient vanishes and only σ_V²'s
  is left; one-sided, a cost that rises with σ_V² asks for none). Only when it could reach
  the threshold is the filter-error model fitted, and then it is added under the same
  criterion and held-out test.

Random inflow is one model in all of these fits and in the ``process_noise`` candidate itself
(:func:`fit_alone`): a pitch-like angle with a first-order spectrum, its σ_V and correlation
time τ_w estimated (:func:`_random_inflow_states`), so that "random inflow alone", "random
inflow + effect" and "effect + random inflow" are nested models compared under one noise
model. Models are held out by their log score with the parameters under test taken from the
other half of the window (:func:`cross_validate`); random inflow beside deterministic effects
with every parameter taken from the other three quarters, each quarter in turn.
"""

from dataclasses import dataclass
import math
import time
from types import SimpleNamespace
from typing import NamedTuple

import numpy as np

from rotor_id.diagnosis import augmentations as aug
from rotor_id.diagnosis import residuals as rs
from rotor_id.diagnosis.catalogue import (
    _at_catalogue_bound, _augment_runs, _block_runs, _build, _stop_at_bound, applicable,
    CandidateFit, effect_parameters, equivalent, fit_candidate, grid_starts, Job, n_choices,
    SCREENED)
from rotor_id.estimation import kalman
from rotor_id.estimation.filter_error import (
    _cost, _FilterProblem, _gradient_information, fit_filter_error_ml, measurement_noise_name,
    PROCESS_NOISE)
from rotor_id.estimation.output_error import _fit_initial_states, IdentificationError
from rotor_id.estimation.simulate import DEFAULT_MAX_STEP

NOISE = 'process_noise'
#: Most filter-error fits of one step cross-validated (the strongest by criterion).
MAX_VALIDATED = 2
#: Most screened effects fitted in one step, those of largest score statistic (a filter-error
#: fit of a time-varying model costs tens of score tests).
MAX_FITTED = 2
#: Gauss-Newton (scoring) iterations of a candidate's filter-error fit; it starts at the
#: current estimate with the extra parameters neutral, a few steps from its optimum.
MAX_ITER = 20
#: A filter-error fit here has converged when a further scoring step would gain less than
#: this in log-likelihood (the Newton decrement), beside the step test: the tests compare
#: likelihoods on a scale of χ² quantiles (≥ 3.8), and scoring zigzags about the optimum of
#: random inflow on the wake record with the cost flat to 0.01 (measured, inflow+noise seed
#: 1003: ΔJ final from iteration 6, the step test met at iteration 36).
LOGLIK_TOL = 1e-3
#: Most iterations of a held-out test's fits (a half-window's estimate, the refit on the
#: predicted part). Held-out scores are compared as optima: a refit stopped early scores the
#: model on where scoring happened to be (measured, inflow+blade+noise seed 1000: the wake
#: beside random inflow, refitted on the second half, had σ_V at 9e-5 after 10 iterations,
#: −log L 44 short of random inflow alone's; converged in 22, 29 ahead of it).
HELDOUT_MAX_ITER = 50
FAILURES = (IdentificationError, np.linalg.LinAlgError, FloatingPointError, ValueError)
#: Family-wise false-alarm level of one forward step beside random inflow. There the model
#: has the record's noise (its innovations are white, ρ ≈ 1) and an effect's 2ΔJ·ρ is a
#: likelihood-ratio statistic, χ²_k where the effect is absent; the step's alternatives are
#: Bonferroni-corrected (:func:`step_test`). The criterion's "very strong" margin (log n per
#: parameter plus 10, 2ΔJ ≈ 17.5 for one) is output error's guard against coloured residuals,
#: whose 2Δlog L is no χ² statistic; beside random inflow it cost the power to find an azimuth
#: offset of 0.03 rad at μ = 0.4 (expected 2ΔJ ≈ 17: half the records), and in the
#: turbulence-only records the step's candidates gained score tests of 0-2.3 (seeds
#: 1000-1009, bench/results/diagnosis_pairs_noise.md).
STEP_LEVEL = 0.01
#: ... and its criterion (BIC difference) must be positive: the approximate Bayes factor
#: favours it. The χ² quantile charges a parameter far less than log n, and a noise model
#: that is nearly but not exactly the record's lends a candidate of several parameters a
#: little of everything: at step 3 of periodic+noise seed 1002 a per-blade offset, per-blade
#: gains and the wake each passed χ²_3-4 (2ΔJ·ρ 20.8, 23.4, 19.9; criteria −0.8, −5.4, −8.9),
#: and the offsets predicted the held-out half 0.1 better: named, high confidence, without
#: being there. For one parameter the χ² test is the stricter of the two.
STEP_MIN_CRITERION = 0.0
#: random inflow's own parameters beside σ_V (its correlation time, a model without a wake)
SHAPE = tuple(par.name for par in aug.PitchLikeRandomInflow.extra_parameters)
SHAPE_START = {par.name: par.nominal for par in aug.PitchLikeRandomInflow.extra_parameters}


@dataclass
class _Setup:
    """What every filter-error fit of one diagnosis shares."""

    base_model: object
    experiments: list
    rows: list                  # process-noise rows (state names of the baseline model)
    noise_std: object           # fixed measurement σ per channel, or None (estimated)


def _setup(ctx):
    from rotor_id.pipeline import channel_noise, experiments_from_record, model_for
    description = ctx['description']
    base_model = model_for(description)
    experiments = experiments_from_record(ctx['record'], description, base_model,
                                          tuple(ctx['window_s']))
    rows = [base_model.state_names[i] for i in kalman.default_noise_rows(base_model)]
    noise = description.noise_std_rad
    fixed = None if noise is None else channel_noise(base_model, float(noise))
    return _Setup(base_model, experiments, rows, fixed)


def _say(ctx, text):
    if ctx.get('progress') is not None:
        ctx['progress'](f'{text} ({time.perf_counter() - ctx["t_start"]:.1f} s)')


def _job(ctx, effect, variant, kept, start):
    return Job(effect, variant, ctx['record'], ctx['description'], ctx['values'],
               ctx['unknowns'], ctx['known'], ctx['window_s'], prior=tuple(kept), start=start)


def _sigma_v(est):
    return float(est.value(PROCESS_NOISE)) if PROCESS_NOISE in est.names else 0.0


def _problem(runs, unknowns, guess, known, setup, sigma_v, max_step, start_est,
             process_sigma=None, rows=None, refit_states=False):
    """
    Filter problem of a candidate and its θ at the current estimate (extra parts neutral).

    Every θ entry the current estimate has (model unknowns, initial states, measurement σ's)
    is taken from it; the candidate's extra parameters stay at their neutral values and its
    extra initial states at their output-error fit. σ_V² is ``process_sigma``² if given.
    ``refit_states``: a fit's start away from the current estimate; its initial states are
    the current ones unless they make the start absurd, then all refitted there (a score
    test is at the current estimate, where they are already the current model's optimum).
    ``prob.start_cost`` is the filter's cost at the returned θ when it was evaluated here.
    """
    prob = _FilterProblem(runs, unknowns, guess, known, setup.noise_std, sigma_v, True,
                          setup.rows if rows is None else rows, 'white', 'auto', max_step)
    k = len(prob.names)
    base = prob.base
    theta = np.zeros(k)
    theta[:len(base.param_index)] = base.p_base[base.param_index]
    theta[:prob.n_base] = _fit_initial_states(base, theta[:prob.n_base].copy(), max_step)
    fitted_states = theta[:prob.n_base].copy()
    have = dict(zip(start_est.names, start_est.values))
    for i, name in enumerate(prob.names):
        if name == PROCESS_NOISE:
            theta[i] = (sigma_v if process_sigma is None else process_sigma)**2
        elif name in have and i >= len(base.param_index):
            theta[i] = have[name]
    if prob.i_meas is not None:
        for j, channel in enumerate(prob.model.output_names):
            name = measurement_noise_name(channel)
            if name not in have:
                theta[prob.i_meas][j] = float(np.asarray(start_est.noise_std)[j])
    y = np.concatenate([e.y for e in runs])
    scale_meas = float(np.mean(np.asarray(start_est.noise_std, dtype=float)))
    prob.scale = np.concatenate([np.maximum(np.abs(theta[:prob.n_base]),
                                            1e-3 * float(np.abs(y).max())),
                                 np.full(k - prob.n_base, scale_meas)])
    if prob.i_process is not None:
        prob.scale[prob.i_process] = scale_meas**2
    # the extra states' initial values: their output-error fit, or at rest, whichever the
    # filter finds more likely (a state the effect's neutral value leaves unobservable, as
    # a dissimilar blade's at ε = 0, gets an arbitrary output-error value)
    new = [i for i, n in enumerate(prob.names[:prob.n_base])
           if i >= len(base.param_index) and n not in have]
    tries = [theta]
    if new:
        rest = theta.copy()
        rest[new] = 0.0
        tries.append(rest)
    prob.start_cost = None
    if len(tries) > 1 or refit_states:
        costs = [_cost(prob.evaluate(th, sensitivities=False)) for th in tries]
        costs = np.where(np.isfinite(costs), costs, np.inf)
        best = int(np.argmin(costs))
        theta, prob.start_cost = tries[best], float(costs[best])
    if refit_states:
        # a filter-error fit can leave initial states far along a direction its own model
        # barely sees, which another model sees (measured, inflow+blade+noise seed 1000:
        # random inflow and the blade left β0(t0) = 64 rad, η(t0) = -256 rad; every start of
        # the wake beside them cost 1e8-1e9). Such a start, less likely by more than one unit
        # of log-likelihood per observation than with all initial states refitted there, is
        # absurd and takes the refitted ones; any other keeps the current estimate's, which
        # a nearer start can beat only by a start's transient (blade+noise seed 1001: taking
        # the likelier start there ended the blade's fit 10.5 lower in log-likelihood)
        refitted = theta.copy()
        refitted[len(base.param_index):prob.n_base] = fitted_states[len(base.param_index):]
        cost = _cost(prob.evaluate(refitted, sensitivities=False))
        if np.isfinite(cost) and prob.start_cost - cost > y.size:
            theta, prob.start_cost = refitted, float(cost)
    return prob, theta


def _score(prob, theta, one_sided=None):
    """
    Score statistic LM = gᵀ M⁻¹ g of the innovations likelihood at θ.

    Parameters on a lower bound that the gradient pushes against (σ_V² = 0 with a cost that
    rises with it) carry no evidence: their gradient is set to zero. ``one_sided`` names a θ
    index whose positive gradient (the cost rises) means LM = 0.
    """
    results = prob.evaluate(theta)
    g, M = _gradient_information(results, len(theta))
    if one_sided is not None and g[one_sided] >= 0.0:
        return 0.0
    at_lower = (theta <= prob.lo) & (g > 0)
    # a parameter the data carry no information on (a bilinear one at its neutral value,
    # e.g. a Lock-number change of a blade whose extra states start at rest) adds nothing
    informed = (np.diag(M) > 1e-12 * np.max(np.diag(M))) & ~at_lower
    g, M = g[informed], M[np.ix_(informed, informed)]
    d = np.sqrt(np.diag(M))
    gs = g / d
    return float(gs @ np.linalg.pinv(M / np.outer(d, d), rcond=1e-10) @ gs)


def screen(effect, kept, current, ctx, setup):
    """
    Score-test one effect on top of ``current`` (filter error): [(variant, LM, k)].

    A sensor lag (not nested, τ > 0) is tested by its first-order equivalent, the delay
    nested at d = 0, as output error's screening does; a blade dissimilarity blade by blade.
    """
    test = 'time_delay' if effect in ('sensor_lag', 'pitch_actuator_lag') else effect
    blades = list(setup.base_model.blades) if effect == 'blade_dissimilarity' else [None]
    est = current.estimate
    start = {n: est.model_parameters[n] for n in current.unknowns}
    out = []
    for blade in blades:
        variant = '' if blade is None else f'blade_{blade}'
        job = _job(ctx, test, variant, kept, start)
        runs, model, unknowns, extra, guess, max_step = _build(job, setup.base_model,
                                                               setup.experiments)
        runs, rows, unknowns = _with_inflow_states(runs, unknowns, guess, est, ctx, setup)
        prob, theta = _problem(runs, unknowns, guess, job.known, setup, _sigma_v(est),
                               max_step or DEFAULT_MAX_STEP, est, rows=rows)
        k = len(prob.names) - len(est.names)
        out.append((variant, _score(prob, theta), k))
    return out


def fit_filter(effect, variant, kept, start_fit, ctx, setup, max_iter=MAX_ITER):
    """
    Filter-error fit of the stack ``kept`` + ``effect`` with σ_V estimated: CandidateFit.

    Started from ``start_fit``'s estimate (a filter-error one: its σ_V and measurement σ's
    too). ``effect`` None fits ``kept`` alone (the backward check).
    """
    t0 = time.perf_counter()
    est0 = start_fit.estimate
    start = {n: est0.model_parameters[n] for n in start_fit.unknowns
             if n in est0.model_parameters}
    if effect is None:
        effect, variant = kept[-1]
        kept = kept[:-1]
    out = CandidateFit(effect=effect, variant=variant, prior=tuple(kept))
    try:
        job = _job(ctx, effect, variant, kept, start)
        runs, model, unknowns, extra, guess, max_step = _build(job, setup.base_model,
                                                               setup.experiments)
        max_step = max_step or DEFAULT_MAX_STEP
        runs, rows, unknowns = _with_inflow_states(runs, unknowns, guess, est0, ctx, setup)
        model = runs[0].model
        guess, prob, theta = _best_filter_start(
            effect, job, model, runs, unknowns, guess, setup, max_step, est0, rows,
            earlier=_earlier_fit(ctx, effect, variant, kept))
        begin = {n: v for n, v in zip(prob.names, theta)
                 if n != PROCESS_NOISE and n not in unknowns}
        # two iterations at a catalogue bound end the fit: it is reported bound-limited
        est = fit_filter_error_ml(runs, unknowns, guess=guess, known=job.known,
                                  noise_std=setup.noise_std, max_iter=max_iter,
                                  process_noise_std=math.sqrt(theta[prob.i_process]),
                                  rows=rows, max_step=max_step,
                                  label=f'{effect} + random inflow', _start=begin,
                                  loglik_tol=LOGLIK_TOL,
                                  progress=_stop_at_bound(model, extra, None))
    except FAILURES as exc:
        out.available, out.reason = False, f'filter-error fit failed: {exc}'
        return out
    _fill(out, est, model, unknowns, extra, ctx)
    out.bound_limited = [n for n, _ in _at_catalogue_bound(est, model, extra)]
    out.elapsed_s = time.perf_counter() - t0
    out.experiments, out.max_step, out.noise_rows = runs, max_step, rows
    ctx.setdefault('filter_fits', []).append(out)
    return out


def _earlier_fit(ctx, effect, variant, kept):
    """
    Return this effect's fit of an earlier step (beside fewer kept effects), or None.

    The latest one, its stack a part of ``kept``: the model now fitted is that fit's with the
    effects added since, so its estimate is a start from the other side of the same model.
    """
    stack = set(kept)
    for fit in reversed(ctx.get('filter_fits', [])):
        if (fit.effect, fit.variant) == (effect, variant) and fit.available \
                and set(fit.prior) < stack:
            return fit
    return None


def _best_filter_start(effect, job, model, runs, unknowns, guess, setup, max_step, est0,
                       rows, earlier=None):
    """
    Return (start, its filter problem, its θ): the most likely of output error's grid starts.

    Effects whose likelihood has several valleys (the wake's gain and time constant, a lag's
    τ, :func:`~rotor_id.diagnosis.catalogue.grid_starts`) are started where the filter, at the
    current σ_V, finds them most likely: from the neutral values the first scoring steps
    beside random inflow swing far (γ to twice its value, σ_V to its bound) and the fit ends,
    within its iterations, in whichever valley the path found.

    ``earlier``: the effect's fit beside fewer of the kept effects (:func:`_earlier_fit`).
    Its estimate, the effects added since at the current one's values, is one more start, at
    its own σ_V: the same model approached from the other side. The current model's
    parameters can sit in another valley than the effect needs (measured, inflow+blade+noise
    seed 1000: beside random inflow and the blade the wake gained ΔJ 10.2 from the current
    γ = 3.2, σ_V = 1.8e-3; the same three effects, the blade added to the wake's fit at
    γ = 3.9, reached 120 more).
    """
    sigma0 = max(_sigma_v(est0), 1e-12)
    starts = [(g, sigma0) for g in [guess] + (grid_starts(job, model, guess, unknowns) or [])]
    if effect == 'dynamic_inflow':
        # and no wake gain (L = 0, the current model's likelihood): a fit from there never
        # ends below the model it extends, where the grid's starts are all less likely
        starts.insert(1, ({**guess, 'AL_over_tau': 0.0}, sigma0))
    if earlier is not None:
        before = earlier.estimate.model_parameters
        starts.append(({**guess, **{n: before[n] for n in unknowns if n in before}},
                       max(_sigma_v(earlier.estimate), 1e-12)))
    best, best_cost = None, math.inf
    for start, sigma in starts:
        try:
            prob, theta = _problem(runs, unknowns, start, job.known, setup, sigma,
                                   max_step, est0, process_sigma=sigma, rows=rows,
                                   refit_states=True)
        except FAILURES:
            continue
        if len(starts) == 1:
            return start, prob, theta
        try:
            cost = prob.start_cost
            if cost is None:
                cost = _cost(prob.evaluate(theta, sensitivities=False))
        except FAILURES:
            continue
        if math.isfinite(cost) and (best is None or cost < best_cost):
            best, best_cost = (start, prob, theta), cost
    if best is None:           # no start evaluates: the neutral one fails as it did before
        prob, theta = _problem(runs, unknowns, guess, job.known, setup, _sigma_v(est0),
                               max_step, est0, process_sigma=max(_sigma_v(est0), 1e-12),
                               rows=rows)
        return guess, prob, theta
    return best


def _fill(out, est, model, unknowns, extra, ctx):
    """Estimate, model and every effect's parameters ± σ (random inflow's σ's included)."""
    out.estimate, out.model, out.unknowns, out.extra_names = est, model, unknowns, extra
    out.effect_parameters.update(effect_parameters(est, model))
    out.effect_parameters[NOISE] = {n: (est.value(n), est.std_of(n)) for n in est.names
                                    if n in (PROCESS_NOISE,) + SHAPE
                                    or n.startswith('noise_std_')}
    out.parameters = out.effect_parameters.get(out.effect, {})


class Heldout(NamedTuple):
    """Held-out one-step prediction of a filter-error model (both halves of the window)."""

    rms: float      # RMS over channels of the mean-square innovation, rad
    nll: float      # −log L of the innovations, Σ ½[νᵀB⁻¹ν + log|B|] + const (the log score)
    converged: bool = True  # every fit of the test met its convergence test


def cross_validate(fit, ctx, setup, under_test, without_noise=False, folds=2,
                   hold_all=False):
    """
    Held-out test of the parameters ``under_test`` of a filter-error model: :class:`Heldout`.

    Those parameters are fitted on one half of the window; on the other half every other
    parameter (the model's shared with the nested model it is compared with, initial states,
    the noise levels) is refitted with them held, both ways (None if a fit fails). The
    nested model, whose ``under_test`` is empty, is simply fitted on each half. So the
    held-out log score ``nll`` (−log L of the innovations, Σ ½[νᵀB⁻¹ν + log|B|] + const,
    which weighs each innovation by the covariance B the model predicts) asks whether the
    values one half gives the tested parameters predict the other half better than their
    neutral values, with the same number of parameters refitted on both sides. Holding the
    shared parameters too would test half-record estimates of the baseline and of σ_V
    instead: under turbulence they scatter between the halves more than a concealed effect
    gains (measured on lag+noise seed 1004: σ_V 0.98e-4 against 3.4e-4, the wake's
    AL_over_tau 0.31 against 0.25; the true lag then lost 31 in held-out log score, and its
    innovation RMS, the former measure, was 1 % worse). ``without_noise``: σ_V held at 0,
    where the filter is output error (innovations = simulation residuals). ``folds``: the
    window cut into that many equal blocks, the tested parameters fitted on all but one and
    the others refitted on that one, each block in turn (2: the halves, both ways).
    ``hold_all``: every parameter (the nested model's too) is fitted on the other blocks and
    held on the predicted one, its initial states alone refitted: the test of a noise level
    (σ_V, τ_w), which the measurement σ's and a baseline refitted on the predicted block
    absorb (measured: lag+noise 1007, held-out −log L short by 0.8 with the halves, by 0.4
    with four blocks, by 1.7 and 2.6 with the measurement σ's held too; ahead by 1.6 with
    four blocks and everything held; noise+gain 1003 still behind by 27.4, 34.6 of it on the
    last quarter, whose filter-error fit on the other three moved the wake's A from 0.461 to
    0.446).
    """
    est = fit.estimate
    runs = fit.experiments
    max_step = getattr(fit, 'max_step', DEFAULT_MAX_STEP)
    rows = getattr(fit, 'noise_rows', None) or setup.rows
    unknowns = list(fit.unknowns)
    tested = [n for n in under_test if n != PROCESS_NOISE]
    sigma_tested = PROCESS_NOISE in under_test
    ms, nll, converged = [], 0.0, True
    try:
        for fold in range(folds):
            rest = [b for b in range(folds) if b != fold]
            held, noise_std = {}, setup.noise_std
            sigma_v = 0.0 if without_noise else max(_sigma_v(est), 1e-12)
            if under_test or hold_all:
                part = fit_filter_error_ml(
                    _block_runs(runs, rest, folds), unknowns,
                    guess={n: est.model_parameters[n] for n in unknowns},
                    known=ctx['known'], noise_std=setup.noise_std,
                    max_iter=HELDOUT_MAX_ITER, process_noise_std=sigma_v,
                    estimate_process_noise=not without_noise,
                    rows=rows, max_step=max_step, label='held-out half',
                    loglik_tol=LOGLIK_TOL)
                held = {n: part.model_parameters[n]
                        for n in (unknowns if hold_all else tested)}
                if sigma_tested:
                    sigma_v = _sigma_v(part)
                if hold_all:
                    noise_std = np.asarray(part.noise_std, dtype=float)
                converged &= bool(part.converged)
            free = [n for n in unknowns if n not in held]
            pred = fit_filter_error_ml(
                _block_runs(runs, [fold], folds), free,
                guess={n: est.model_parameters[n] for n in free},
                known={**ctx['known'], **held}, noise_std=noise_std,
                max_iter=HELDOUT_MAX_ITER, process_noise_std=sigma_v,
                estimate_process_noise=not (without_noise or sigma_tested),
                rows=rows, max_step=max_step, label='held-out prediction',
                loglik_tol=LOGLIK_TOL)
            res = np.concatenate(pred.residuals, axis=0)
            ms.append(np.mean(res**2, axis=0))
            nll += pred.neg_log_likelihood
            converged &= bool(pred.converged)
    except FAILURES:
        return None
    return Heldout(float(math.sqrt(np.mean(ms))), float(nll), converged)


def _heldout_text(val, cur_val):
    def one(v):
        if v is None:
            return 'n/a'
        unconverged = '' if v.converged else \
            f', a refit unconverged in {HELDOUT_MAX_ITER} iterations'
        return f'{v.nll:.1f} (innovation RMS {v.rms:.4g} rad{unconverged})'
    return f'held-out −log L {one(val)} against {one(cur_val)}'


def _effective_fraction(fit):
    res = np.concatenate(fit.estimate.residuals, axis=0)
    return rs.channels_effective_fraction(res, innovations=True)


def _criterion(dll, fit, k, ctx):
    rho = _effective_fraction(fit)
    crit = 2.0 * dll * rho - max(k, 0) * math.log(ctx['n_obs'] * rho)
    if n_choices(fit.effect, ctx['n_blades']) > 1:
        crit -= 2.0 * math.log(n_choices(fit.effect, ctx['n_blades']))
    return crit


def step_test(lr, k, alternatives, criterion=math.inf):
    """
    Test one effect in a forward step beside random inflow by its likelihood ratio.

    ``lr`` = 2ΔJ·ρ, ``k`` the effect's extra parameters, ``alternatives`` how many fits the
    step chose among (each effect, an odd blade counted once per blade), ``criterion`` its
    criterion. Returns {'name', 'statistic', 'parameters', 'critical', 'level', 'criterion',
    'passes'}: the χ²_k quantile at :data:`STEP_LEVEL` / ``alternatives``, and whether ``lr``
    exceeds it with the criterion above :data:`STEP_MIN_CRITERION`.
    """
    from scipy.stats import chi2
    level = STEP_LEVEL / max(int(alternatives), 1)
    critical = float(chi2.ppf(1.0 - level, max(int(k), 1)))
    return {'name': 'likelihood ratio beside random inflow', 'statistic': float(lr),
            'parameters': max(int(k), 1), 'critical': critical, 'level': level,
            'criterion': float(criterion),
            'passes': bool(lr > critical and criterion > STEP_MIN_CRITERION)}


def _test_text(test):
    word = 'above' if test['statistic'] > test['critical'] else 'short of'
    text = (f'likelihood-ratio test 2ΔJ·ρ = {test["statistic"]:.1f} {word} '
            f'χ²_{test["parameters"]} {test["critical"]:.1f} at {test["level"]:.2g}')
    if test['statistic'] > test['critical'] and not test['passes']:
        text += f', but its criterion {test["criterion"]:.1f} is not above ' \
                f'{STEP_MIN_CRITERION:g}'
    return text


def _step(current, cur_val, kept, ctx, setup):
    """
    One forward step under random inflow: (row, fit) of the effect added, or None.

    What every candidate gains (its fit, else its score test) is recorded in a new row of
    ``ctx['noisy_trace']``, for the confounds (:func:`rotor_id.diagnosis.diagnose._confounds`).
    """
    from rotor_id.diagnosis.diagnose import SCREEN_SAFETY, _score_test_gain, _step_row
    gains = {}
    ctx['noisy_trace'].append({'after': tuple(e for e, _ in kept), 'gains': gains})
    names = {e for e, _ in kept}
    excluded = set(names)
    for e in names:
        excluded.update(equivalent(e, ctx.get('mu', 0.0)))
    est = current.estimate
    scores = {}                 # effect: its score test LM at the current model
    todo = []                   # (reach, effect, variant): the unscreened ones first
    candidates = [e for e in ctx['effects']
                  if not (e == NOISE or e in excluded or applicable(
                      e, ctx['model_name'], ctx['rotor'], ctx['unknowns']))]
    alternatives = sum(n_choices(e, ctx['n_blades']) for e in candidates)
    ctx['step_alternatives'] = alternatives
    for effect in candidates:
        if not (ctx['screen'] and effect in SCREENED):
            todo.append((math.inf, effect, ''))
            continue
        try:
            tests = screen(effect, kept, current, ctx, setup)
        except FAILURES:
            tests = [('', math.nan, 0)]
        variant, lm, k = max(tests, key=lambda v: v[1] if math.isfinite(v[1]) else -1)
        if math.isfinite(lm):
            scores[effect] = lm
            gains[effect] = _score_test_gain({'effect': effect, 'lm': lm, 'k': k},
                                             ctx['n_obs'], ctx['n_blades'])
            gains[effect]['passes'] = step_test(lm, k, alternatives,
                                                gains[effect]['criterion'])['passes']
        # how far the full fit could clear the step's test (its 2ΔJ·ρ credited with
        # SCREEN_SAFETY times the score statistic; ρ no smaller than 1/50 in the criterion)
        reach = min(SCREEN_SAFETY * lm - step_test(lm, k, alternatives)['critical'],
                    SCREEN_SAFETY * lm - k * math.log(ctx['n_obs'] / 50.0)
                    - 2.0 * math.log(n_choices(effect, ctx['n_blades'])) - STEP_MIN_CRITERION)
        if not math.isfinite(lm):
            reach = math.inf
        if reach <= 0.0:
            _say(ctx, f'  + {effect} under random inflow: screened out, innovations '
                      f'score test 2ΔJ ≈ {lm:.1f}')
            continue
        _say(ctx, f'  + {effect} under random inflow: innovations score test 2ΔJ ≈ {lm:.1f}')
        todo.append((reach, effect, variant))
    todo.sort(key=lambda c: -c[0])
    # one fit per physics: first-order equivalents score alike (a lag is tested as a delay)
    group_seen, screened = set(), []
    for c in [c for c in todo if math.isfinite(c[0])]:
        group = frozenset((c[1],) + tuple(equivalent(c[1], ctx.get('mu', 0.0))))
        if group in group_seen:
            todo.remove(c)
            _say(ctx, f'  + {c[1]} under random inflow: not fitted (a first-order '
                      'equivalent with as large a score is)')
            continue
        group_seen.add(group)
        screened.append(c)
    for _, effect, _ in screened[MAX_FITTED:]:
        _say(ctx, f'  + {effect} under random inflow: not fitted ({MAX_FITTED} effects have a '
                  'larger score)')
    fits, near = [], []
    for _, effect, variant in [c for c in todo if c not in screened[MAX_FITTED:]]:
        fit = fit_filter(effect, variant, kept, current, ctx, setup)
        if not fit.available or fit.bound_limited:
            _say(ctx, f'  + {effect} under random inflow: '
                      f'{fit.reason or "bound-limited, not compared"}')
            continue
        dll = float(est.neg_log_likelihood - fit.estimate.neg_log_likelihood)
        k = len(fit.estimate.names) - len(est.names)
        crit = _criterion(dll, fit, k, ctx)
        lr = 2.0 * dll * _effective_fraction(fit)
        test = step_test(lr, k, alternatives, crit)
        _say(ctx, f'  + {effect} under random inflow: ΔJ = {dll:.1f}, criterion {crit:.1f}, '
                  f'{_test_text(test)} ({fit.elapsed_s:.1f} s)')
        gains[effect] = {'two_delta_loglik': 2.0 * dll, 'criterion': crit, 'how': 'fit',
                         'passes': test['passes']}
        if test['passes']:
            fits.append((crit, dll, fit, test))
        else:
            near.append((effect, f'gains 2ΔJ = {2 * dll:.1f} in the innovations likelihood '
                                 f'({_test_text(test)}; criterion {crit:.1f})',
                         lr, k, 2.0 * dll, fit.estimate.converged))
    fits.sort(key=lambda c: -c[0])
    for crit, dll, fit, test in fits[:MAX_VALIDATED]:
        val = cross_validate(fit, ctx, setup, fit.extra_names)
        _say(ctx, f'  {fit.effect} under random inflow: {_heldout_text(val, cur_val)}')
        if val is not None and (cur_val is None or val.nll < cur_val.nll):
            row = _step_row(fit, dll, crit, val.rms, ctx['floors'], ctx['u'], ctx['t'])
            row['validation_nll'] = val.nll
            row['test'] = {n: v for n, v in test.items() if n != 'passes'}
            return row, fit, val
        near.append((fit.effect, f'gains 2ΔJ = {2 * dll:.1f} ({_test_text(test)}) but '
                                 'does not predict the unfitted half-window better '
                                 f'({_heldout_text(val, cur_val)})',
                     2.0 * dll * _effective_fraction(fit),
                     len(fit.estimate.names) - len(est.names), 2.0 * dll,
                     fit.estimate.converged))
    # nothing added: an effect whose likelihood-ratio test passes is likely, not established
    for effect, text, lr, k, raw, converged in near:
        _doubt(ctx, kept, text, lr, k, what=effect, raw=raw, score=scores.get(effect),
               converged=converged)
    return None


def add_deterministic(noise_fit, noise_row, ctx):
    """
    Forward selection of deterministic effects on top of random inflow (filter error).

    Returns (final fit, step rows, notes). The rows start with random inflow's; when no
    deterministic effect earns its place the answer is ``noise_fit`` and ``[noise_row]``, and
    so it is when some do but random inflow then no longer earns its own place beside them
    (their output-error fit is as likely): a verdict without random inflow is the
    output-error selection's, which did not reach it, and random inflow alone is then a doubt
    (a note says what was found; the verdict is low confidence).
    """
    from rotor_id.diagnosis.diagnose import (_confounds, CRITERION_THRESHOLD, MAX_EFFECTS,
                                             _step_row)
    setup = _setup(ctx)
    notes = []
    ctx['noisy_trace'], ctx['filter_fits'] = [], []
    current = noise_fit
    current.experiments, current.noise_rows, shape = _random_inflow_states(
        setup.experiments, ctx['record'])
    current.max_step = DEFAULT_MAX_STEP
    cur_val = cross_validate(current, ctx, setup, [])
    if cur_val is not None:
        noise_row.update(validation_rms=cur_val.rms, validation_nll=cur_val.nll)
    steps, kept = [noise_row], []
    while len(kept) + 1 < MAX_EFFECTS:
        _say(ctx, f'random inflow step {len(kept) + 2}: deterministic effects on top of '
                  f'{" + ".join([NOISE] + [e for e, _ in kept])} (filter error)')
        found = _step(current, cur_val, kept, ctx, setup)
        if found is None:
            break
        row, fit, _ = found
        kept.append((fit.effect, fit.variant))
        steps.append(row)
        current = fit
        # the next effect is tested against this model fitted on each half
        cur_val = cross_validate(current, ctx, setup, [])
        for old in list(kept[:-1]):
            rest = [ev for ev in kept if ev != old]
            without = fit_filter(None, '', rest, current, ctx, setup)
            if not without.available:
                continue
            dll = float(without.estimate.neg_log_likelihood
                        - current.estimate.neg_log_likelihood)
            # the test it passed to enter, given the effects added after it
            k = len(current.estimate.names) - len(without.estimate.names)
            test = step_test(2.0 * dll * _effective_fraction(current), k,
                             ctx['step_alternatives'], _criterion(dll, current, k, ctx))
            if test['passes']:
                continue
            _say(ctx, f'backward check under random inflow: {old[0]} dropped (its '
                      f'{_test_text(test)} given the others)')
            kept.remove(old)
            steps = [st for st in steps if st['effect'] != old[0]]
            notes.append(f'{old[0]} was dropped by the backward check: with the effects '
                         'added after it, it no longer earns its place')
            current = without
    if not kept:
        noise_row.setdefault('parameters', noise_fit.parameters)
        return noise_fit, [noise_row], notes
    # random inflow must still earn its place beside the deterministic effects
    last, others = kept[-1], kept[:-1]
    start = {n: current.estimate.model_parameters[n] for n in current.unknowns
             if n in current.estimate.model_parameters}
    oe = fit_candidate(_job(ctx, last[0], last[1], others, start))
    if oe.available and not oe.bound_limited:
        dll = float(oe.estimate.neg_log_likelihood - current.estimate.neg_log_likelihood)
        crit = _criterion(dll, current, 1 + len(shape), ctx)     # σ_V (and τ_w)
        if crit <= CRITERION_THRESHOLD:
            # a verdict without random inflow is the output-error selection's to give (it
            # did not reach this one): this search only adds effects to random inflow
            # but they explain the record as well as random inflow with them does, and
            # better than random inflow alone: so random inflow alone is not confident
            det = ' + '.join(e for e, _ in kept)
            ctx.setdefault('doubts', []).append(
                f'{det} found beside random inflow, but then random inflow no longer earns '
                f'its place (the filter error gains 2ΔJ = {2 * dll:.1f} over their '
                f'output-error fit, criterion {crit:.1f}): not a verdict of the output-error '
                f'selection, so random inflow alone is kept, but {det} without it may be '
                'the explanation (low confidence)')
            noise_row.setdefault('parameters', noise_fit.parameters)
            return noise_fit, [noise_row], notes
        noise_row.update(delta_loglik=dll, criterion=crit)
    # an effect that passes alone (beside random inflow) but adds nothing once the kept ones
    # are in is named as confounded with them, as in the output-error selection
    confounds = _confounds([e for e, _ in kept], {'trace': ctx['noisy_trace'],
                                                  'mu': ctx.get('mu', 0.0)})
    for st in steps:
        st['parameters'] = current.effect_parameters.get(st['effect'], {})
        st['confounds'] = confounds.get(st['effect'], [])
        st['adequate'] = _step_row(current, 0.0, 0.0, None, ctx['floors'], ctx['u'],
                                   ctx['t'])['adequate'] if st['effect'] != NOISE else False
    current.experiments = []
    return current, steps, notes


def _random_inflow_states(runs, record):
    """
    Return (runs, process-noise rows, extra unknowns) of random inflow over a candidate's runs.

    The one noise model of every filter-error fit of a diagnosis (random inflow alone, with
    deterministic effects added to it, or added to them), so that they are nested: random
    inflow as a pitch-like angle with a first-order spectrum
    (:class:`~rotor_id.diagnosis.augmentations.PitchLikeRandomInflow`), its correlation time
    τ_w estimated, on a wake model too. White noise on the flap-acceleration rows (the
    default rows of a model without a wake) has neither the spectrum nor the direction of
    turbulence; a wake's λ rows have its direction but the wake's time constant. Measured
    (bench/results/diagnosis_pairs.md): a flap-frequency error beside turbulence in the wake
    record gains 2ΔJ = 18-25 with the pitch-like states against 15 with noise on λ
    (noise+flap_frequency seeds 1001, 1002).
    """
    runs, model = _augment_runs(runs, aug.PitchLikeRandomInflow, record)
    return runs, list(model.extra_states), list(SHAPE)


def _with_inflow_states(runs, unknowns, guess, est, ctx, setup):
    """Candidate runs with random inflow's states; τ_w (if any) started at ``est``'s."""
    runs, rows, shape = _random_inflow_states(runs, ctx['record'])
    for name in shape:
        guess[name] = est.model_parameters.get(name, SHAPE_START[name])
    return runs, rows, list(unknowns) + shape


def fit_alone(job):
    """
    Fit random inflow alone (the ``process_noise`` candidate) by filter error: the Estimate.

    With the noise model of every filter-error fit here (:func:`_random_inflow_states`),
    started at the baseline's values and the nominal correlation time. Returns (estimate,
    model, unknowns).
    """
    ctx = {'description': job.description, 'record': job.record, 'window_s': job.window_s}
    setup = _setup(ctx)
    runs, rows, shape = _random_inflow_states(setup.experiments, job.record)
    model = runs[0].model
    guess = {**job.baseline_values, **{n: SHAPE_START[n] for n in shape}}
    est = fit_filter_error_ml(runs, list(job.unknowns) + shape, guess=guess, known=job.known,
                              noise_std=setup.noise_std, max_iter=MAX_ITER, rows=rows,
                              label='process_noise (pitch-like random inflow)',
                              loglik_tol=LOGLIK_TOL)
    return est, model, list(job.unknowns) + shape


#: Blocks of the window in the held-out test of random inflow beside deterministic effects:
#: both models fitted on three quarters, every parameter held on the quarter left out (its
#: initial states refitted), each quarter in turn. With the halves and the baseline and the
#: measurement σ's refitted on the predicted half, these absorbed what a concealed
#: turbulence predicts (lag+noise 1007: criterion 33.6, held-out −log L short by 0.8).
NOISE_FOLDS = 4


#: Significance of random inflow's likelihood-ratio test (without the criterion's log n
#: per parameter) that makes a verdict without it doubtful: turbulence is then likely beside
#: the effects found although it does not earn its place by the criterion.
DOUBT_LEVEL = 0.05


def _doubt(ctx, kept, text, lr, k, what=NOISE, raw=None, score=None, converged=True):
    """
    Record a doubt (a note; the verdict is not confident) when ``what`` is not added.

    ``lr`` = 2ΔJ·ρ (ρ the residuals' effective fraction), ``k`` its parameters: a doubt when
    it passes the χ²_k test at :data:`DOUBT_LEVEL`; or when the uncorrected ``raw`` = 2ΔJ and
    the ``score`` test at its neutral value both pass it (innovations that stay correlated
    with it in the model, ρ small, are no sign that nothing is missing: inflow+noise seed
    1009, random inflow beside the wake 2ΔJ = 17.0, score test 14.2, ρ 0.1); or when its fit
    did not converge (``converged`` False: its gain is a lower bound). ``what``: random
    inflow beside the deterministic effects ``kept``, or a deterministic effect beside random
    inflow (+ kept).
    """
    from scipy.stats import chi2
    level = chi2.ppf(1.0 - DOUBT_LEVEL, k)
    both = raw is not None and score is not None and raw > level and score > level
    if not (lr > level or both or not converged):
        return
    shown = 'random inflow (process_noise)' if what == NOISE else what
    beside = ' + '.join(([] if what == NOISE else [NOISE]) + [e for e, _ in kept])
    if not converged:
        why = (f'its filter-error fit did not converge in {MAX_ITER} iterations (2ΔJ·ρ = '
               f'{lr:.1f} so far, a lower bound)')
    elif lr > level:
        why = (f'its likelihood-ratio test passes at the {DOUBT_LEVEL:.0%} level (2ΔJ·ρ = '
               f'{lr:.1f} > χ²_{k} {level:.1f})')
    else:
        why = (f'its likelihood-ratio test without the effective-sample fraction (2ΔJ = '
               f'{raw:.1f}) and its score test ({score:.1f}) pass at the {DOUBT_LEVEL:.0%} '
               f'level (χ²_{k} {level:.1f}; 2ΔJ·ρ = {lr:.1f}: the innovations stay '
               'correlated with it in the model)')
    ctx.setdefault('doubts', []).append(
        f'{shown} on top of {beside} {text}: not added, but {why}: the verdict may be '
        f'incomplete, {"turbulence" if what == NOISE else what} beside it is likely, not '
        'established')


def unconverged(table, named, at_floor=False):
    """
    Note the candidate fits that did not converge, other than the ``named`` effects.

    Their likelihood is a lower bound: such a candidate may explain the record better than
    the verdict, which is then not confident. ``table``: the diagnosis's candidate rows.
    ``at_floor``: the verdict's model (or the baseline, for ``none``) leaves white residuals
    at the model-free noise floor. A deterministic rival's output-error fit can then at best
    reach that floor too, so its unfinished fit is no doubt about the verdict; random inflow
    still is (white output-error residuals do not exclude it).
    """
    notes = []
    for row in table:
        fit = row.get('fit')
        est = getattr(fit, 'estimate', None)
        if (row['effect'] in named or est is None or est.converged or not fit.available
                or fit.bound_limited or (at_floor and row['effect'] != NOISE)):
            continue
        dll = row.get('delta_loglik')
        gain = '' if dll is None else f', 2Δlog L = {2.0 * dll:.1f} so far'
        crit = row.get('criterion')
        gain += '' if crit is None else f', criterion {crit:.1f}'
        notes.append(f'the fit of {row["effect"]} did not converge in {est.iterations} '
                     f'iterations{gain}: its likelihood is a lower bound, it may explain the '
                     'record better than the verdict (low confidence)')
    return notes


def noise_alone_doubt(table):
    """
    Note random inflow alone when its likelihood-ratio test passes but it was not chosen.

    The test: 2ΔJ·ρ against χ²_k at :data:`DOUBT_LEVEL`, k its extra parameters. A verdict
    without it (``none``) is then not confident (process_noise seed 1009: 2ΔJ = 12.0 with 4
    extra, criterion −12.9).
    """
    from scipy.stats import chi2
    for row in table:
        if row['effect'] != NOISE or row.get('delta_loglik') is None:
            continue
        k = max(int(row.get('n_extra') or 0), 1)
        rho = row.get('n_eff_fraction') or 1.0
        lr = 2.0 * row['delta_loglik'] * rho
        level = chi2.ppf(1.0 - DOUBT_LEVEL, k)
        if lr > level:
            return [f'random inflow (process_noise) alone gains 2ΔJ·ρ = {lr:.1f} (2ΔJ = '
                    f'{2.0 * row["delta_loglik"]:.1f}, ρ = {rho:.2f}) with {k} extra, past '
                    f'χ²_{k} {level:.1f} at the {DOUBT_LEVEL:.0%} level, but not its '
                    f'criterion ({row["criterion"]:.1f}): turbulence is likely, not '
                    'established (low confidence)']
    return []


def add_random_inflow(final_fit, steps, ctx):
    """
    Random inflow on top of the deterministic effects of the output-error selection.

    Returns (fit, row) when it earns its place (criterion and held-out one-step prediction),
    else None. Screened first: the score test of σ_V² at 0 on the final model.
    """
    from rotor_id.diagnosis.diagnose import CRITERION_THRESHOLD, SCREEN_SAFETY, _step_row
    kept = [(st['effect'], st['variant']) for st in steps]
    if not kept or any(e == NOISE for e, _ in kept):
        return None
    setup = _setup(ctx)
    est = final_fit.estimate
    start = {n: est.model_parameters[n] for n in final_fit.unknowns}
    job = _job(ctx, kept[-1][0], kept[-1][1], kept[:-1], start)
    try:
        runs, model, unknowns, extra, guess, max_step = _build(job, setup.base_model,
                                                               setup.experiments)
        max_step = max_step or DEFAULT_MAX_STEP
        oe_runs, oe_unknowns = runs, list(unknowns)
        runs, rows, shape = _random_inflow_states(runs, ctx['record'])
        model, unknowns = runs[0].model, unknowns + shape
        guess.update({n: SHAPE_START[n] for n in shape})
        prob, theta = _problem(runs, unknowns, guess, job.known, setup, 0.0, max_step, est,
                               process_sigma=0.0, rows=rows)
        lm = _score(prob, theta, one_sided=prob.i_process)
    except FAILURES as exc:
        _say(ctx, f'random inflow on top of {" + ".join(e for e, _ in kept)}: score test '
                  f'failed ({exc})')
        return None
    from scipy.stats import chi2
    reach = SCREEN_SAFETY * lm - math.log(ctx['n_obs'] / 50.0)
    # fitted also when it could only make the verdict doubtful (its likelihood-ratio test,
    # :func:`_doubt`): a screen on the criterion alone would pass over turbulence that is
    # likely and call the verdict confident
    doubt_level = chi2.ppf(1.0 - DOUBT_LEVEL, 1 + len(shape))
    if reach <= CRITERION_THRESHOLD and SCREEN_SAFETY * lm <= doubt_level:
        _say(ctx, f'random inflow on top of {" + ".join(e for e, _ in kept)}: screened out, '
                  f'innovations score test of σ_V² = 0 gives 2ΔJ ≈ {lm:.1f}')
        return None
    _say(ctx, f'random inflow on top of {" + ".join(e for e, _ in kept)}: score test '
              f'2ΔJ ≈ {lm:.1f}, fitting by filter error')
    t0 = time.perf_counter()
    fit = CandidateFit(effect=NOISE, prior=tuple(kept))
    try:
        begin = {n: v for n, v in zip(prob.names, theta)
                 if n != PROCESS_NOISE and n not in unknowns}
        fe = fit_filter_error_ml(runs, unknowns, guess=guess, known=job.known,
                                 noise_std=setup.noise_std, max_iter=MAX_ITER, rows=rows,
                                 max_step=max_step, label='random inflow on top',
                                 _start=begin, loglik_tol=LOGLIK_TOL)
    except FAILURES as exc:
        _say(ctx, f'random inflow on top: filter-error fit failed ({exc})')
        return None
    _fill(fit, fe, model, unknowns, extra, ctx)
    fit.parameters = fit.effect_parameters[NOISE]
    fit.experiments, fit.max_step, fit.noise_rows = runs, max_step, rows
    fit.elapsed_s = time.perf_counter() - t0
    dll = float(est.neg_log_likelihood - fe.neg_log_likelihood)
    crit = _criterion(dll, fit, 1 + len(shape), ctx)      # σ_V (and τ_w)
    shape_text = ''.join(f', τ_w = {fe.value(n):.2g} ± {fe.std_of(n):.1g} rad' for n in shape)
    _say(ctx, f'  + random inflow: ΔJ = {dll:.1f}, criterion {crit:.1f}{shape_text}')
    if crit <= CRITERION_THRESHOLD:
        _doubt(ctx, kept, f'gains 2ΔJ = {2 * dll:.1f} in the innovations likelihood '
               f'(criterion {crit:.1f}, threshold {CRITERION_THRESHOLD:g})',
               2.0 * dll * _effective_fraction(fit), 1 + len(shape), raw=2.0 * dll, score=lm,
               converged=fe.converged)
        return None
    held = cross_validate(fit, ctx, setup, [PROCESS_NOISE] + shape, folds=NOISE_FOLDS,
                          hold_all=True)
    # the deterministic model's held-out log score by the same filter with σ_V = 0
    cur = cross_validate(SimpleNamespace(estimate=est, experiments=oe_runs,
                                         unknowns=oe_unknowns, max_step=max_step,
                                         noise_rows=setup.rows), ctx, setup, [],
                         without_noise=True, folds=NOISE_FOLDS, hold_all=True)
    _say(ctx, f'  random inflow: {_heldout_text(held, cur)} (output error)')
    if held is None or (cur is not None and held.nll >= cur.nll):
        _doubt(ctx, kept, f'gains a criterion {crit:.1f} (2ΔJ = {2 * dll:.1f}) but does not '
               f'predict held-out quarters better ({_heldout_text(held, cur)})',
               2.0 * dll * _effective_fraction(fit), 1 + len(shape), raw=2.0 * dll, score=lm,
               converged=fe.converged)
        return None
    val = held.rms
    row = _step_row(fit, dll, crit, val, ctx['floors'], ctx['u'], ctx['t'])
    fit.experiments = []
    return fit, row
