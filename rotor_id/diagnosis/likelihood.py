"""
The likelihood interface of the selection: fit a model, score-test an effect at it.

An explanation is a set of catalogue effects (possibly empty). :class:`OutputError` fits the
deterministic ones by output-error ML (:func:`rotor_id.diagnosis.catalogue.fit_candidate`, the
compiled Gauss-Newton path); :class:`FilterError` fits those with random inflow
(``process_noise``) by filter-error ML (:mod:`rotor_id.diagnosis.noisy`). Both give a
:class:`FitResult` whose criteria are properties, and a :class:`ScoreTest` of an effect at a
fitted model. :class:`ModelSpace` sends each explanation to the likelihood that owns it, so
the search (:mod:`rotor_id.diagnosis.selection`) never asks which one it has.
"""

from dataclasses import dataclass, field, replace
from functools import cached_property, partial
import math
from typing import Callable

import numpy as np

from rotor_id import residuals as rs
from rotor_id.diagnosis import noisy
from rotor_id.diagnosis.catalogue import (
    as_lag_variance, CandidateFit, COMPOSE_ORDER, EFFECTS, fit_candidate, fit_runs,
    Job, LAG_PARAMETER, NOISE, screen_candidate, SCREENED, SCREENED_AS, start_values,
    tested_variants)
from rotor_id.estimation.output_error import FIT_FAILURES
from rotor_id.estimation.simulate import DEFAULT_MAX_STEP
from rotor_id.estimation.workers import Workers


def canonical(effects):
    """Return an explanation's effects [(effect, variant)] in the catalogue's order."""
    return tuple(sorted(effects, key=lambda ev: (EFFECTS.index(ev[0]), ev[1])))


@dataclass
class FitResult:
    """A fitted explanation: likelihood, size, effective sample size, bounds (MLEResults-like)."""

    effects: tuple
    loglik: float
    #: parameters beyond the baseline's (extra parameters and estimated extra initial states)
    n_params: int
    #: observations (samples × channels) and the residuals' effective fraction ρ = N_eff/N
    n_obs: int
    rho: float
    converged: bool
    #: extra parameters at a limit of their range after widening (the fit is still compared)
    at_bound: tuple
    fit: object
    likelihood: str
    #: the fit's time, s (CPU where run in a worker)
    elapsed_s: float = 0.0

    @property
    def names(self):
        """Return the effect ids."""
        return tuple(e for e, _ in self.effects)

    @property
    def estimate(self):
        """Return the fit's estimate: residuals, covariance, parameters."""
        return self.fit.estimate

    def start_values(self):
        """Return the estimate's model parameters (a start for a bigger or smaller model)."""
        return start_values(self.fit)


@dataclass
class ScoreTest:
    """Rao's score test of one effect at a fitted model."""

    effect: str
    variant: str
    #: LM = gᵀ M⁻¹ g, the Gauss-Newton prediction of 2Δlog L (χ²_k where the effect is absent)
    statistic: float
    k: int
    #: {extra parameter: its variance at the fitted model} (M⁻¹)_jj, others profiled
    variance: dict = field(default_factory=dict)


class Likelihood:
    """
    What the search needs of a likelihood: fits of explanations and score tests.

    A likelihood gives ``fit_many([(effects, start)])`` (results, None where a fit failed) and
    ``score_many(current, effects)`` ({effect: ScoreTest, None where not nested}), each batch
    in worker processes; :meth:`fit` is one fit.
    """

    def fit(self, effects: tuple, start: FitResult | None) -> FitResult | None:
        """Fit the explanation ``effects`` started from ``start``'s values (None: failed)."""
        return self.fit_many([(effects, start)])[0]

    def fit_many(self, requests: list) -> list:
        """Fit [(effects, start)]: a result each, None where the fit failed."""
        raise NotImplementedError

    def fit_later(self, requests: list) -> Callable[[], list]:
        """Begin :meth:`fit_many` beside the batches that follow; return a call that waits."""
        return partial(self.fit_many, requests)

    def fit_ahead(self, requests: list) -> Callable[[list], None]:
        """
        Begin fits [(effects, start)] that may be asked for next, where workers would idle.

        Return a call that is passed the requests still wanted: it queues them and gives up
        the others. Until asked for by :meth:`fit_many`, a fit begun ahead is nowhere in the
        results: what the search sees never depends on what ran ahead. (Here: none is.)
        """
        return lambda wanted: None

    def score_many(self, current: FitResult, effects: list) -> dict:
        """Score-test several effects at ``current``: {effect: ScoreTest or None}."""
        raise NotImplementedError


def _fit_result(effects, fit, n_params, n_obs, likelihood, innovations=False):
    """Return the :class:`FitResult` of a CandidateFit (None for a failed one)."""
    if fit is None or not fit.available:
        return None
    est = fit.estimate
    res = np.concatenate(est.residuals, axis=0)
    return FitResult(effects=effects, loglik=-float(est.neg_log_likelihood),
                     n_params=n_params, n_obs=n_obs,
                     rho=rs.channels_effective_fraction(res, innovations),
                     converged=bool(est.converged), at_bound=tuple(fit.bound_limited),
                     fit=fit, likelihood=likelihood, elapsed_s=float(fit.elapsed_s))


def _best_variant(effect, tests):
    """
    Return the ScoreTest of the variant with the largest statistic [(variant, LM, k, var)].

    The variances are the largest over the variants: a detection limit that holds for each.
    """
    variant, lm, k, _ = max(tests, key=lambda v: v[1])
    var = {n: max(t[3].get(n, 0.0) for t in tests) for n in tests[0][3]}
    return ScoreTest(effect, variant, float(lm), int(k), var)


def _screen_job(job_and_variance):
    """Return screen_candidate of (job, noise variance), None where it fails (a worker)."""
    try:
        return screen_candidate(*job_and_variance)
    except FIT_FAILURES:
        return None


def _as_lag(effect, test):
    """Return a delay's score test as a lag's (d = τ to first order), its variance renamed."""
    if effect not in LAG_PARAMETER:
        return test
    return ScoreTest(effect, test.variant, test.statistic, test.k,
                     as_lag_variance(effect, test.variance))


def _tests_by_effect(effects, tested, found):
    """
    Return {effect: ScoreTest or None} of ``effects``.

    ``tested``: {effect: the effect its test is of}; ``found``: {tested effect: its variants'
    [(variant, LM, k, var)], empty or None where the test failed}.
    """
    out = dict.fromkeys(effects)
    for effect, test in tested.items():
        if found.get(test):
            out[effect] = _as_lag(effect, _best_variant(effect, found[test]))
    return out


class OutputError(Likelihood):
    """Deterministic explanations by output-error ML; the baseline is the run's own fit."""

    name = 'output error'

    def __init__(self, setting, ident, n_obs, workers=None):
        self.setting, self.ident, self.n_obs = setting, ident, n_obs
        self.workers = workers if workers is not None else Workers(1)
        self._memo = {}
        #: {explanation: its fit submitted ahead (:meth:`fit_ahead`), not asked for yet}
        self._ahead = {}
        self._baseline = None

    def baseline(self):
        """
        Return the run's own fit (the empty explanation), integrated as every candidate is.

        The run's estimate itself where the diagnosis takes the default RK4 step; else the
        run's model refitted from it at the diagnosis's step (:func:`record_step`), so that
        every likelihood of the table comes from one integration.
        """
        if self._baseline is None:
            ident, setting = self.ident, self.setting
            estimate = ident.estimate
            if setting.max_step != DEFAULT_MAX_STEP:
                estimate = fit_runs(setting, ident.experiments, list(setting.unknowns),
                                    setting.values, setting.max_step, 'baseline')
            fit = CandidateFit(effect='baseline', estimate=estimate, model=ident.model,
                               unknowns=list(setting.unknowns))
            self._baseline = self._result((), fit)
        return self._baseline

    def _result(self, effects, fit):
        n_params = 0 if fit is None else max(int(fit.n_extra), 0)
        return _fit_result(effects, fit, n_params, self.n_obs, self.name)

    def _job(self, effects, start):
        """Return the job of ``effects``: its own effect the one ``start`` lacks (last added)."""
        have = () if start is None else start.effects
        new = [ev for ev in effects if ev not in have] or \
            [max(effects, key=lambda ev: COMPOSE_ORDER.index(ev[0]))]
        last = new[-1]
        prior = tuple(ev for ev in effects if ev != last)
        return Job(self.setting, *last, prior=prior,
                   start=None if start is None else start.start_values(),
                   baseline_nll=-start.loglik if start is not None else math.inf)

    def fit_many(self, requests):
        """Fit [(effects, start)] (in worker processes); returns results, None where failed."""
        keys = [canonical(effects) for effects, _ in requests]
        todo = {k: self._job(k, start) for k, (_, start) in zip(keys, requests)
                if k and k not in self._memo and k not in self._ahead}
        fits = self.workers.apply(fit_candidate, todo.values(),
                                  [('fit', job.effect) for job in todo.values()])
        self._memo.update((key, self._result(key, fit)) for key, fit in zip(todo, fits))
        for key in keys:
            if key in self._ahead:
                self._memo[key] = self._result(key, self._ahead.pop(key)())
        return [self.baseline() if not k else self._memo[k] for k in keys]

    def fit_ahead(self, requests):
        """
        Submit fits that may be asked for next, to fill workers idle before a batch ends.

        A fit's job is the same whether it runs ahead or in the batch that asks for it, so
        its result is too. The call returned queues those still wanted and gives up the rest.
        """
        for effects, start in requests:
            key = canonical(effects)
            if key and key not in self._memo and key not in self._ahead:
                self._ahead[key] = self.workers.submit(fit_candidate, self._job(key, start),
                                                       filler=True)

        def keep(wanted):
            wanted = {canonical(effects) for effects, _ in wanted}
            for key in list(self._ahead):
                if key in wanted:
                    self._ahead[key].release()
                else:
                    self._ahead.pop(key).cancel()
        return keep

    def refit_from(self, effects, values):
        """Fit an explanation again from the start ``values``; return the better of the two."""
        key = canonical(effects)
        new = self._result(key, fit_candidate(replace(self._job(key, None), start=dict(values))))
        old = self._memo.get(key)
        if new is not None and (old is None or new.loglik > old.loglik):
            self._memo[key] = new
        return self._memo.get(key)

    def score_many(self, current, effects):
        """
        Score-test effects at an output-error fit: {effect: ScoreTest or None}.

        In worker processes; a lag is tested through its delay d = τ (:data:`SCREENED_AS`).
        """
        noise_var = np.asarray(current.estimate.noise_std, dtype=float)**2
        tested = {e: SCREENED_AS.get(e, e) for e in effects if e in SCREENED}
        start = current.start_values()
        # each variant its own job: a blade dissimilarity's, one per blade
        keys = [(t, v) for t in sorted(set(tested.values()))
                for v in tested_variants(t, self.ident.model)]
        jobs = [(Job(self.setting, t, v, prior=current.effects, start=start), noise_var)
                for t, v in keys]
        found = {}
        for (t, _), test in zip(keys, self.workers.apply(_screen_job, jobs, keys)):
            if test is not None:
                found.setdefault(t, []).append(test)
        return _tests_by_effect(effects, tested, found)


def _filter_fit_job(item):
    """Return the filter-error fit of one request (in a worker), None where it fails."""
    new, rest, start_fit, earlier, setting = item
    setup = noisy.setup_for(setting)
    try:
        if start_fit is None:
            return noisy.fit_alone(setting, setup)
        effect, variant = new if new is not None else (None, None)
        return noisy.fit_filter(effect, variant, rest, start_fit, setting, setup,
                                earlier=earlier)
    except FIT_FAILURES:
        return None


def _filter_score_job(item):
    """Return the filter-error score test of one tested variant (in a worker), None: failed."""
    test, variant, kept, current_fit, setting = item
    setup = noisy.setup_for(setting)
    try:
        if test == NOISE:
            lm, var = noisy.noise_score(current_fit, kept, setting, setup)
            return '', float(lm), 1 + len(noisy.SHAPE), var
        return noisy.screen(test, variant, kept, current_fit, setting, setup)
    except FIT_FAILURES:
        return None


class FilterError(Likelihood):
    """Explanations with random inflow, by filter-error ML (innovations likelihood)."""

    name = 'filter error'

    def __init__(self, setting, n_obs, baseline_names, workers=None):
        self.setting, self.n_obs = setting, n_obs
        self.base_names = set(baseline_names)
        self.workers = workers if workers is not None else Workers(1)
        self._memo = {}
        #: the fits made so far (later ones start from an earlier one's values)
        self.fits = []

    @cached_property
    def setup(self):
        """Return the filter problem's shared parts (built on first use)."""
        return noisy.setup_for(self.setting)

    def _result(self, effects, fit):
        if fit is None or not fit.available:
            return None
        # not counted: the measurement σ's (output error's R alike), random inflow's states
        measured = {noisy.measurement_noise_name(c) for c in fit.model.output_names}
        k = len([n for n in fit.estimate.names if n not in self.base_names and n not in measured
                 and not n.startswith(noisy.INFLOW_STATES)])
        return _fit_result(effects, fit, k, self.n_obs, self.name, innovations=True)

    def _request(self, key, start):
        """
        Return a worker's item for fitting ``key`` from ``start``.

        Random inflow alone, or the effect ``start`` lacks added to its filter-error fit, or
        (from an output-error start) the stack fitted whole.
        """
        kept = [ev for ev in key if ev[0] != NOISE]
        if not kept:
            return None, [], None, None, self.setting
        if start is not None and start.likelihood == self.name:
            new = ([ev for ev in kept if ev not in start.effects] or kept[-1:])[0]
            rest = [ev for ev in kept if ev != new]
            effect, variant, stack = new[0], new[1], rest
        else:
            new, rest = None, kept
            (effect, variant), stack = kept[-1], kept[:-1]
        earlier = noisy.earlier_fit(self.fits, effect, variant, stack)
        return new, rest, start.fit, earlier, self.setting

    def fit_many(self, requests):
        """Fit [(effects, start)] with random inflow (in worker processes); None where failed."""
        keys = [canonical(effects) for effects, _ in requests]
        todo = {}
        for key, (_, start) in zip(keys, requests):
            if key not in self._memo and key not in todo:
                todo[key] = self._request(key, start)
        # named by the effect added (random inflow alone: '')
        names = [('filter fit', item[0][0] if item[0] else '') for item in todo.values()]
        for key, fit in zip(todo, self.workers.apply(_filter_fit_job, todo.values(), names)):
            self._memo[key] = self._result(key, fit)
            if self._memo[key] is not None:
                self.fits.append(fit)
        return [self._memo[k] for k in keys]

    def score_many(self, current, effects):
        """Score-test effects at a fitted model, in worker processes: {effect: ScoreTest}."""
        kept = [ev for ev in current.effects if ev[0] != NOISE]
        tested = {e: SCREENED_AS.get(e, e) for e in effects if e == NOISE or e in SCREENED}
        # each variant its own job: a blade dissimilarity's are the longest, one per blade
        keys = [(NOISE, t, v) for t in sorted(set(tested.values()))
                for v in tested_variants(t, self.setup.base_model)]
        items = [(t, v, kept, current.fit, self.setting) for _, t, v in keys]
        found = {}
        for item, test in zip(items, self.workers.apply(_filter_score_job, items, keys)):
            if test is not None:
                found.setdefault(item[0], []).append(test)
        return _tests_by_effect(effects, tested, found)


class ModelSpace(Likelihood):
    """
    The explanations of one record, each fitted by the likelihood that owns it.

    Random inflow in an explanation: :class:`FilterError`; otherwise :class:`OutputError`.
    """

    def __init__(self, output_error, filter_error, effects):
        self.output_error, self.filter_error = output_error, filter_error
        self.effects = tuple(effects)

    def _longest_first(self):
        """
        Return the likelihoods, filter error first: its jobs are queued first in the workers.

        A filter-error job costs several output-error ones; queued last, it runs alone at
        the end of its batch while the other worker waits.
        """
        return (self.filter_error, self.output_error)

    def _owner(self, effects):
        return self.filter_error if any(e == NOISE for e, _ in effects) else self.output_error

    def baseline(self):
        """Return the fit of the empty explanation."""
        return self.output_error.baseline()

    def fit_many(self, requests):
        """Fit [(effects, start)], each by its likelihood, the batches at once in the workers."""
        out = [None] * len(requests)
        batches = []
        for owner in self._longest_first():
            mine = [i for i, (effects, _) in enumerate(requests)
                    if self._owner(effects) is owner]
            if mine and owner is not None:
                batches.append((mine, partial(owner.fit_many, [requests[i] for i in mine])))
        results = self.output_error.workers.together([call for _, call in batches])
        for (mine, _), fits in zip(batches, results):
            for i, res in zip(mine, fits):
                out[i] = res
        return out

    def fit_later(self, requests):
        """Begin fitting [(effects, start)] in the workers beside the next batches."""
        return self.output_error.workers.beside(partial(self.fit_many, requests))

    def fit_ahead(self, requests):
        """
        Begin the output-error fits among ``requests`` ahead (:meth:`Likelihood.fit_ahead`).

        A filter-error fit starts from the fits made before it, so it is made only when asked.
        """
        return self.output_error.fit_ahead(
            [(effects, start) for effects, start in requests
             if self._owner(effects) is self.output_error])

    def refit_from(self, effects, values):
        """Fit an explanation again from ``values``; the better of the two (output error)."""
        owner = self._owner(effects)
        return owner.refit_from(effects, values) if hasattr(owner, 'refit_from') else None

    def score_many(self, current, effects):
        """Score-test effects at ``current`` with the likelihood of ``current + effect``."""
        out = dict.fromkeys(effects)
        batches = []
        for owner in self._longest_first():
            mine = [e for e in effects if self._owner(current.effects + ((e, ''),)) is owner]
            if mine and owner is not None:
                batches.append(partial(owner.score_many, current, mine))
        for tests in self.output_error.workers.together(batches):
            out.update(tests)
        return out
