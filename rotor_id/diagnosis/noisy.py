"""
Filter-error (random-inflow) fits and score tests of the catalogue's models.

A model with random inflow (``process_noise``, :func:`random_inflow_states`) is fitted by the
innovations likelihood J = ½ Σ_j [ν_jᵀ B_j⁻¹ ν_j + log|B_j|] (Ch.1 eq. 26) with σ_V, τ_w and
the measurement σ's estimated; the deterministic effects are stacked as output error's
(:func:`rotor_id.diagnosis.catalogue.build`). :class:`rotor_id.diagnosis.likelihood.FilterError`
wraps these functions in the likelihood interface of the selection.
"""

from dataclasses import dataclass
import math
import time

import numpy as np

from rotor_id.diagnosis.catalogue import (
    bound_sides, build, CandidateFit, CurrentColumns, effect_parameters, grid_starts, Job,
    kept_current, NOISE, start_values, stop_at_bound)
from rotor_id.estimation.filter_error import (
    FilterProblem, fit_filter_error_ml, gradient_information, innovations_cost,
    measurement_noise_name, PROCESS_NOISE)
from rotor_id.estimation.output_error import augment_runs, FIT_FAILURES, fit_initial_states
from rotor_id.estimation.validation import score_statistic
from rotor_id.physics import augmented as aug
from rotor_id.pipeline import channel_noise

#: Gauss-Newton (scoring) iterations of a candidate's filter-error fit; it starts at the
#: current estimate with the extra parameters neutral, a few steps from its optimum.
MAX_ITER = 20
#: random inflow's states (their initial values are the noise model's, no extra parameters)
INFLOW_STATES = tuple(aug.PitchLikeRandomInflow.extra_states)
#: random inflow's own parameters beside σ_V (its correlation time, a model without a wake)
SHAPE = tuple(par.name for par in aug.PitchLikeRandomInflow.extra_parameters)
SHAPE_START = {par.name: par.nominal for par in aug.PitchLikeRandomInflow.extra_parameters}


@dataclass
class Setup:
    """What every filter-error fit of one diagnosis shares."""

    base_model: object
    experiments: list
    noise_std: object           # fixed measurement σ per channel, or None (estimated)


def setup_for(ctx):
    """Return what every filter-error fit of one diagnosis shares (built once per process)."""
    base_model, experiments = ctx.prepared()
    noise = ctx.description.noise_std_rad
    fixed = None if noise is None else channel_noise(base_model, float(noise))
    return Setup(base_model, experiments, fixed)


def _sigma_v(est):
    return float(est.value(PROCESS_NOISE)) if PROCESS_NOISE in est.names else 0.0


def _problem(runs, unknowns, guess, known, setup, sigma_v, max_step, start_est, rows,
             process_sigma=None, refit_states=False, at_rest=False):
    """
    Filter problem of a candidate and its θ at the current estimate (extra parts neutral).

    θ takes every entry the current estimate has; the extra parameters are neutral, the extra
    initial states at rest (``at_rest``: a score test's null) or at their output-error fit or
    at rest, whichever the filter finds more likely (a fit's start). σ_V² is
    ``process_sigma``² if given. ``refit_states``: a fit's start, whose initial states are
    refitted where the current ones make it absurd. ``prob.start_cost``: the filter's cost at
    θ when evaluated here.
    """
    prob = FilterProblem(runs, unknowns, guess, known, setup.noise_std, sigma_v, True, rows,
                         'white', 'auto', max_step)
    k = len(prob.names)
    base = prob.base
    theta = np.zeros(k)
    theta[:len(base.param_index)] = base.p_base[base.param_index]
    have = dict(zip(start_est.names, start_est.values))
    if refit_states or not at_rest and any(
            name not in have for name in prob.names[len(base.param_index):prob.n_base]):
        # (the initial states the current estimate has are taken from it below)
        theta[:prob.n_base] = fit_initial_states(base, theta[:prob.n_base].copy(), max_step)
    fitted_states = theta[:prob.n_base].copy()
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
    # the extra states' initial values: at rest for a score test (the null: the current
    # model's innovations); a fit starts at their output-error fit or at rest, whichever the
    # filter finds more likely (a state the effect's neutral value leaves unobservable, as
    # a dissimilar blade's at ε = 0, gets an arbitrary output-error value)
    new = [i for i, n in enumerate(prob.names[:prob.n_base])
           if i >= len(base.param_index) and n not in have]
    tries = [theta]
    if new and at_rest:
        theta[new] = 0.0
    elif new:
        rest = theta.copy()
        rest[new] = 0.0
        tries.append(rest)
    prob.start_cost = None
    if len(tries) > 1 or refit_states:
        costs = [innovations_cost(prob.evaluate(th, sensitivities=False)) for th in tries]
        costs = np.where(np.isfinite(costs), costs, np.inf)
        best = int(np.argmin(costs))
        theta, prob.start_cost = tries[best], float(costs[best])
    if refit_states:
        # a filter-error fit can leave initial states far along a direction only another model
        # sees (β0(t0) at tens of radians beside a blade difference, every wake start beside
        # them at a cost of 1e8-1e9). A start worse by more than one unit of log-likelihood
        # per observation than with them refitted is absurd and takes the refitted ones; any
        # other keeps the current estimate's (a nearer start gains only a transient)
        refitted = theta.copy()
        refitted[len(base.param_index):prob.n_base] = fitted_states[len(base.param_index):]
        cost = innovations_cost(prob.evaluate(refitted, sensitivities=False))
        if np.isfinite(cost) and prob.start_cost - cost > y.size:
            theta, prob.start_cost = refitted, float(cost)
    return prob, theta


def _score(prob, theta, extra=(), one_sided=None, current=None):
    """
    Score statistic LM = gᵀ M⁻¹ g of the innovations likelihood at θ, and {name: (M⁻¹)_jj}.

    Parameters on a lower bound that the gradient pushes against (σ_V² = 0 with a cost that
    rises with it) carry no evidence: their gradient is set to zero. ``one_sided`` names a θ
    index whose positive gradient (the cost rises) carries none either. The variances are of
    the ``extra`` parameters (names of ``prob``), their information taken as it is there.
    ``current``: the current model's :class:`~rotor_id.diagnosis.catalogue.CurrentColumns`.
    """
    new = None if current is None else \
        current.new_columns(prob.names, theta, extra, prob.n_base, prob.max_step)
    if new is None:
        results = prob.evaluate(theta)
    else:                                   # only the new columns integrated
        some = prob.evaluate(theta, columns=new)
        results = [(nu, B, dnu, dB, cost) for (nu, B, _, _, cost), (dnu, dB) in zip(
            some, current.filled(prob.names, new, [(dnu, dB) for _, _, dnu, dB, _ in some]))]
    g, M = gradient_information(results, len(theta))
    if one_sided is not None and g[one_sided] >= 0.0:
        g = g.copy()
        g[one_sided] = 0.0
    at_lower = (theta <= prob.lo) & (g > 0)
    # a parameter the data carry no information on (a bilinear one at its neutral value,
    # e.g. a Lock-number change of a blade whose extra states start at rest) adds nothing
    informed = (np.diag(M) > 1e-12 * np.max(np.diag(M))) & ~at_lower
    names = [n for n, keep in zip(prob.names, informed) if keep]
    lm, variance = score_statistic(g[informed], M[np.ix_(informed, informed)])
    return lm, {n: float(variance[names.index(n)]) for n in extra if n in names}


def current_innovations(kept, current, ctx, setup):
    """
    Return the :class:`~rotor_id.diagnosis.catalogue.CurrentColumns` (∂ν, ∂B) of ``current``.

    ``kept``: its deterministic effects. Kept per process for the next score test at it.
    """
    est = current.estimate

    def compute():
        _, runs, unknowns, _, guess, max_step, rows = _stack(ctx, setup, list(kept), est,
                                                             start_values(current))
        prob, theta = _problem(runs, unknowns, guess, ctx.known, setup, _sigma_v(est),
                               max_step, est, rows)
        return CurrentColumns(tuple(prob.names), theta,
                              [(dnu, dB) for _, _, dnu, dB, _ in prob.evaluate(theta)],
                              prob.max_step)
    return kept_current(('filter error', ctx.token, tuple(kept),
                         tuple(np.asarray(est.values, dtype=float).tolist())), compute)


def screen(test, variant, kept, current, ctx, setup):
    """
    Score-test one variant of a tested effect on top of ``current`` (filter error).

    Returns (variant, LM, k, {name: variance}). A lag is tested through its first-order
    equivalent, a delay nested at d = 0 (:data:`~rotor_id.diagnosis.catalogue.SCREENED_AS`),
    as output error's screening does; a blade dissimilarity blade by blade
    (:func:`~rotor_id.diagnosis.catalogue.tested_variants`).
    """
    est = current.estimate
    _, runs, unknowns, extra, guess, max_step, rows = _stack(
        ctx, setup, list(kept) + [(test, variant)], est, start_values(current))
    prob, theta = _problem(runs, unknowns, guess, ctx.known, setup, _sigma_v(est),
                           max_step, est, rows, at_rest=True)
    lm, var = _score(prob, theta, extra, current=current_innovations(kept, current, ctx, setup))
    return variant, lm, len(prob.names) - len(est.names), var


def fit_filter(effect, variant, kept, start_fit, ctx, setup, earlier=None):
    """
    Filter-error fit of the stack ``kept`` + ``effect`` with σ_V estimated: CandidateFit.

    Started from ``start_fit``'s estimate (a filter-error one: its σ_V and measurement σ's
    too) and, where given, from ``earlier``, this effect's fit beside fewer effects
    (:func:`earlier_fit`). ``effect`` None fits ``kept`` alone (the backward check).
    """
    t0 = time.perf_counter()
    est0 = start_fit.estimate
    if effect is None:
        effect, variant = kept[-1]
        kept = kept[:-1]
    out = CandidateFit(effect=effect, variant=variant, prior=tuple(kept))
    try:
        job, runs, unknowns, extra, guess, max_step, rows = _stack(
            ctx, setup, list(kept) + [(effect, variant)], est0, start_values(start_fit))
        model = runs[0].model
        guess, prob, theta = _best_filter_start(job, model, runs, unknowns, guess, setup,
                                                max_step, est0, rows, earlier)
        begin = {n: v for n, v in zip(prob.names, theta)
                 if n != PROCESS_NOISE and n not in unknowns}
        # two iterations at a catalogue bound end the fit: it is reported bound-limited
        est = fit_filter_error_ml(runs, unknowns, guess=guess, known=ctx.known,
                                  noise_std=setup.noise_std, max_iter=MAX_ITER,
                                  process_noise_std=math.sqrt(theta[prob.i_process]),
                                  rows=rows, max_step=max_step,
                                  label=f'{effect} + random inflow', start_values=begin,
                                  loglik_tol=ctx.fit_tolerance, step_tol=ctx.fit_tolerance,
                                  progress=stop_at_bound(model, extra, None))
    except FIT_FAILURES as exc:
        out.available, out.reason = False, f'filter-error fit failed: {exc}'
        return out
    _fill(out, est, model, unknowns)
    out.bound_limited = [n for n, _ in bound_sides(est.model_parameters, model, extra)]
    out.elapsed_s = time.perf_counter() - t0
    return out


def earlier_fit(fits, effect, variant, kept):
    """
    Return this effect's fit among earlier ``fits`` (beside fewer kept effects), or None.

    The latest one, its stack a part of ``kept``: the model now fitted is that fit's with the
    effects added since, so its estimate is a start from the other side of the same model.
    """
    stack = set(kept)
    for fit in reversed(fits):
        if (fit.effect, fit.variant) == (effect, variant) and fit.available \
                and set(fit.prior) < stack:
            return fit
    return None


def _best_filter_start(job, model, runs, unknowns, guess, setup, max_step, est0, rows,
                       earlier):
    """
    Return (start, its filter problem, its θ): the most likely of output error's grid starts.

    Effects whose likelihood has several valleys (:func:`~rotor_id.diagnosis.catalogue.
    grid_starts`) start where the filter, at the current σ_V, finds them most likely: from the
    neutral values the first scoring steps beside random inflow swing far (γ to twice its
    value, σ_V to its bound). ``earlier`` (:func:`earlier_fit`), the same model approached
    from the other side, is one more start at its own σ_V: the current model's parameters can
    sit in another valley than the effect needs.
    """
    sigma0 = max(_sigma_v(est0), 1e-12)
    starts = [(g, sigma0) for g in [guess] + (grid_starts(job, model, guess) or [])]
    if job.effect == 'dynamic_inflow':
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
            prob, theta = _problem(runs, unknowns, start, job.setting.known, setup, sigma,
                                   max_step, est0, rows, process_sigma=sigma,
                                   refit_states=True)
        except FIT_FAILURES:
            continue
        if len(starts) == 1:
            return start, prob, theta
        if math.isfinite(prob.start_cost) and prob.start_cost < best_cost:
            best, best_cost = (start, prob, theta), prob.start_cost
    if best is None:           # no start evaluates: the neutral one fails as it did before
        prob, theta = _problem(runs, unknowns, guess, job.setting.known, setup, _sigma_v(est0),
                               max_step, est0, rows, process_sigma=max(_sigma_v(est0), 1e-12))
        return guess, prob, theta
    return best


def _fill(out, est, model, unknowns):
    """Estimate, model and every effect's parameters ± σ (random inflow's σ's included)."""
    out.estimate, out.model, out.unknowns = est, model, unknowns
    out.effect_parameters.update(effect_parameters(est, model))
    out.effect_parameters[NOISE] = {n: (est.value(n), est.std_of(n)) for n in est.names
                                    if n in (PROCESS_NOISE,) + SHAPE
                                    or n.startswith('noise_std_')}
    out.parameters = out.effect_parameters.get(out.effect, {})


def random_inflow_states(runs):
    """
    Return (runs, process-noise rows, extra unknowns) of random inflow over a candidate's runs.

    The one noise model of every filter-error fit of a diagnosis, so that they are nested: a
    pitch-like angle with a first-order spectrum (:class:`~rotor_id.physics.augmented.
    PitchLikeRandomInflow`), on a wake model too. White noise on the flap-acceleration rows
    has neither turbulence's spectrum nor its direction; a wake's λ rows have its direction
    but the wake's time constant (bench/results/diagnosis_pairs.md).
    """
    runs, model = augment_runs(runs, aug.PitchLikeRandomInflow)
    return runs, list(model.extra_states), list(SHAPE)


def _stack(ctx, setup, kept, est, start):
    """
    Return the stack ``kept`` [(effect, variant)] with random inflow, τ_w at ``est``'s.

    Returns (job of the last effect or None, runs, unknowns, extra parameters of the last
    effect, guess, RK4 step, process-noise rows).
    """
    job, runs, unknowns, extra = None, setup.experiments, list(ctx.unknowns), []
    guess, max_step = dict(start), ctx.max_step
    if kept:
        job = Job(ctx, *kept[-1], prior=tuple(kept[:-1]), start=start)
        runs, _, unknowns, extra, guess, max_step = build(job, setup.experiments)
    runs, rows, shape = random_inflow_states(runs)
    have = {} if est is None else est.model_parameters
    guess.update({name: have.get(name, SHAPE_START[name]) for name in shape})
    return job, runs, list(unknowns) + shape, extra, guess, max_step, rows


def fit_alone(ctx, setup):
    """
    Fit random inflow alone (the ``process_noise`` explanation) by filter error: CandidateFit.

    With the noise model of every filter-error fit here (:func:`random_inflow_states`),
    started at the baseline's values and the nominal correlation time.
    """
    t0 = time.perf_counter()
    out = CandidateFit(effect=NOISE)
    _, runs, unknowns, _, guess, _, rows = _stack(ctx, setup, [], None, ctx.values)
    try:
        est = fit_filter_error_ml(runs, unknowns, guess=guess, known=ctx.known,
                                  noise_std=setup.noise_std, max_iter=MAX_ITER, rows=rows,
                                  label='process_noise (pitch-like random inflow)',
                                  loglik_tol=ctx.fit_tolerance, step_tol=ctx.fit_tolerance)
    except FIT_FAILURES as exc:
        out.available, out.reason = False, f'filter-error fit failed: {exc}'
        return out
    _fill(out, est, runs[0].model, unknowns)
    out.elapsed_s = time.perf_counter() - t0
    return out


def noise_score(current, kept, ctx, setup):
    """
    Score test of σ_V² = 0 on an output-error model: (LM, {'process_noise_std': var of σ_V²}).

    At σ_V = 0 the filter is output error, so the model's own gradient vanishes and only σ_V²'s
    (and τ_w's) is left; one-sided: a cost that rises with σ_V² asks for none.
    """
    est = current.estimate
    _, runs, unknowns, _, guess, max_step, rows = _stack(ctx, setup, kept, est,
                                                         start_values(current))
    prob, theta = _problem(runs, unknowns, guess, ctx.known, setup, 0.0, max_step, est, rows,
                           process_sigma=0.0)
    return _score(prob, theta, (PROCESS_NOISE,), one_sided=prob.i_process)
