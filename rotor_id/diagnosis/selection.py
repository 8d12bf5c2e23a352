"""
Model selection over explanations: score-test-guided forward steps, a backward check, posterior.

One algorithm over the likelihood interface (:class:`rotor_id.diagnosis.likelihood.Likelihood`):
it never asks whether a model is fitted by output error or by filter error. The evidence
(:func:`log_evidence`), the prior (:class:`Prior`), the search (:func:`search`) and the
posterior over every explanation fitted or score-tested are stated in docs/diagnosis.md.
"""

from dataclasses import dataclass, field
import math

from rotor_id.diagnosis.catalogue import (
    equivalent, FIRST_ORDER_START, LAG_PARAMETER, n_choices, NOISE, parameter_range, SCREENED)
from rotor_id.diagnosis.likelihood import canonical, FitResult, ScoreTest


@dataclass
class Candidate:
    """One explanation of the table: fitted, or approximated by a score test at a parent."""

    effects: tuple
    result: FitResult = None
    #: score-test approximation: the model it was tested at, and the test
    parent: FitResult = None
    test: ScoreTest = None

    @property
    def fitted(self):
        """Return whether the explanation was fitted, not only score-tested."""
        return self.result is not None

    @property
    def names(self):
        """Return the effect ids."""
        return tuple(e for e, _ in self.effects)

    @property
    def loglik(self):
        """Return the fitted log-likelihood, or the score test's prediction of it."""
        if self.result is not None:
            return self.result.loglik
        return self.parent.loglik + 0.5 * self.test.statistic

    @property
    def n_params(self):
        """Return the parameters beyond the baseline."""
        if self.result is not None:
            return self.result.n_params
        return self.parent.n_params + self.test.k

    @property
    def n_obs(self):
        """Return the observations (samples × channels) of the fit or of the tested parent."""
        return (self.result if self.result is not None else self.parent).n_obs

    def log_evidence(self, rho):
        """Return log p(data | explanation) up to a shared constant, at the shared ρ."""
        return log_evidence(self.loglik, self.n_params, self.n_obs, rho)


def log_evidence(loglik, n_params, n_obs, rho):
    """
    Return the BIC approximation of log p(data | explanation), up to a shared constant.

    ρ·log L − ½ k log(Nρ): the log-likelihood tempered by the residuals' effective fraction ρ
    (a quasi-likelihood for correlated residuals) and the Laplace/BIC charge per parameter at
    the effective sample size Nρ (docs/diagnosis.md).
    """
    return rho * loglik - 0.5 * n_params * math.log(n_obs * rho)


@dataclass
class Step:
    """One move of the search: an effect added or dropped, with the log posterior odds."""

    action: str                 # 'add', 'drop' or 'exchange'
    effect: str
    variant: str
    #: log posterior odds of the model after the move against the one before
    log_odds: float
    #: 2Δlog L of the move (after − before)
    two_delta_loglik: float
    #: the explanation after the move
    effects: tuple


@dataclass
class Selection:
    """What the search fitted and tested, and where it stopped."""

    candidates: dict
    steps: list
    final: FitResult
    #: {explanation: {effect: ScoreTest}} of the score tests made at each fitted explanation
    tests: dict = field(default_factory=dict)
    #: catalogue effects the search could use (the prior's m), and the advance ratio
    effects: tuple = ()
    mu: float = 0.0


class Prior:
    """
    Uniform over sizes 0 … K, then over the sets of physics of a size, then over the forms.

    First-order equivalents in this record (:func:`~rotor_id.diagnosis.catalogue.equivalent`)
    are one physics, their forms sharing its weight, as an effect's variants do.
    """

    def __init__(self, effects, max_effects, n_blades, mu=0.0):
        groups = {}
        for e in effects:
            groups[e] = {e} | {o for o in equivalent(e, mu) if o in effects}
        for e in effects:                   # close the groups (equivalence is transitive)
            for o in list(groups[e]):
                groups[e] |= groups[o]
        self.forms = {e: len(g) for e, g in groups.items()}
        self.m = max(len({frozenset(g) for g in groups.values()}), 1)
        self.k_max, self.n_blades = max_effects, n_blades

    def log(self, effects):
        """Return log P(S) of an explanation [(effect, variant)]."""
        size = len(effects)
        if size > self.k_max:
            return -math.inf
        return (-math.log(self.k_max + 1) - math.log(math.comb(self.m, min(size, self.m)))
                - sum(math.log(n_choices(e, self.n_blades) * self.forms.get(e, 1))
                      for e, _ in effects))


def shared_rho(candidates):
    """Return ρ* of the fitted explanation with the highest likelihood."""
    fitted = [c.result for c in candidates if c.fitted]
    return max(fitted, key=lambda r: r.loglik).rho


def log_posterior(candidate, rho, prior):
    """Return the unnormalised log posterior of one explanation at the shared ρ."""
    return candidate.log_evidence(rho) + prior.log(candidate.effects)


def posterior(candidates, prior, tempering=1.0):
    """
    Return [(candidate, probability)] over the table, most probable first.

    ``tempering`` η ≤ 1 scales every log posterior (p ∝ posterior^η: the ranking stays, the
    odds shrink; :attr:`SelectionPolicy.evidence_tempering`).
    """
    rows = list(candidates)
    rho = shared_rho(rows)
    logs = [tempering * log_posterior(c, rho, prior) for c in rows]
    top = max(logs)
    weights = [math.exp(v - top) for v in logs]
    total = sum(weights)
    return sorted(zip(rows, (w / total for w in weights)), key=lambda cp: -cp[1])


def _open_effects(current, effects, mu):
    """Return the effects that can be added to ``current``: not in it, nor its equivalents."""
    taken = set(current.names)
    for e in current.names:
        taken.update(equivalent(e, mu))
    return [e for e in effects if e not in taken]


def _screen_odds(test, current, key, rho, prior, allowance):
    """Return the log posterior odds of ``key`` against ``current`` at 2Δlog L = allowance·LM."""
    return (log_evidence(0.5 * allowance * test.statistic, test.k, current.n_obs, rho)
            + prior.log(key) - prior.log(current.effects))


def same_physics(a, b, mu):
    """Return whether two explanations differ only by first-order equivalents."""
    mine, theirs = set(a), set(b)
    if len(mine) != len(theirs):
        return False
    x, y = mine - theirs, theirs - mine
    return all(any(v in equivalent(u, mu) for v in y) for u in x) \
        and all(any(u in equivalent(v, mu) for u in x) for v in y)


class _Search:
    """One search: the table of explanations, the score tests and the moves made so far."""

    def __init__(self, space, effects, prior, policy, mu, say, adequate, on_fit):
        self.space, self.effects, self.prior, self.policy = space, effects, prior, policy
        self.mu, self.say, self.adequate, self.on_fit = mu, say, adequate, on_fit
        self.candidates, self.steps, self.tests = {}, [], {}
        #: the first step's fits begun before its score tests: (their keys, a call that waits)
        self.early = None

    def log_post(self, result):
        """Return a fit's unnormalised log posterior at the table's shared ρ now."""
        return log_posterior(Candidate(result.effects, result),
                             shared_rho(self.candidates.values()), self.prior)

    def fit(self, requests, label, later=False):
        """
        Fit [(effects, start)] and enter the fits into the table; return them (None: failed).

        ``later``: the fits run beside what the search does next; a call is returned that
        waits for them, enters and returns them.
        """
        self.say(label + ', '.join(' + '.join(e for e, _ in k) for k, _ in requests))
        self.on_fit([key for key, _ in requests])
        if later:
            wait = self.space.fit_later(requests)
            return lambda: self._enter(wait())
        return self._enter(self.space.fit_many(requests))

    def begin_unscored(self, baseline):
        """
        Begin the first step's fits of the effects without a score test (always requested).

        They are the costliest (the wake's grid of starts) and need no test: they run beside
        the score tests at the baseline, and the first step takes them (:meth:`fit_step`).
        """
        keys = [canonical(((e, ''),)) for e in _open_effects(baseline, self.effects, self.mu)
                if e not in SCREENED and e != NOISE]
        if keys:
            self.early = set(keys), self.fit([(k, baseline) for k in keys], '  fitting ',
                                             later=True)

    def _enter(self, fitted):
        base = self.candidates[()].result
        for res in fitted:
            if res is not None:
                self.candidates[res.effects] = Candidate(res.effects, res)
                self.say(f'  {" + ".join(res.names)}: 2Δlog L '
                         f'{2.0 * (res.loglik - base.loglik):.1f} with {res.n_params} '
                         f'({res.likelihood}, {res.elapsed_s:.1f} s)')
        return fitted

    def screen(self, current):
        """Score-test every open effect at ``current``; return the requests worth fitting."""
        candidates, policy = self.candidates, self.policy
        rho = shared_rho(candidates.values())
        here = tests_at(self.space, self, current)
        scored, unscored = [], []
        open_effects = _open_effects(current, self.effects, self.mu)
        for effect in open_effects:
            test = here.get(effect)
            if test is None:
                unscored.append(effect)
                continue
            key = canonical(current.effects + ((effect, test.variant),))
            if key not in candidates:
                candidates[key] = Candidate(key, parent=current, test=test)
            odds = _screen_odds(test, current, key, rho, self.prior, policy.score_allowance)
            if effect in LAG_PARAMETER and 'time_delay' in open_effects \
                    and _screen_odds(test, current, key, rho, self.prior, 1.0) < 0.0:
                # tested through the delay d = τ (one statistic): a lag is fitted beside the
                # delay only where the delay would be added, so that they compete for the name
                odds = -math.inf
            if odds >= math.log(policy.fit_share) and not candidates[key].fitted:
                scored.append((odds, key))
        if here:
            ranked = sorted(here.items(), key=lambda et: -et[1].statistic)
            self.say(f'score tests at {" + ".join(current.names) or "the baseline"}: '
                     + ', '.join(f'{e} {t.statistic:.1f}' for e, t in ranked))
        # the effects without a score test first: they are the costliest fits (the wake's grid
        # of starts, a periodic model), and a batch's jobs are queued in this order
        requests = []
        for effect in unscored:
            key = canonical(current.effects + ((effect, ''),))
            alone = candidates.get(canonical(((effect, ''),)))
            earned = alone is not None and alone.fitted and (
                self.log_post(alone.result) - self.log_post(candidates[()].result)
                >= math.log(policy.fit_share))
            if (not current.effects or earned) and not (key in candidates
                                                        and candidates[key].fitted):
                requests.append((math.inf, key, current))
        base = self.log_post(current)
        scored.sort(reverse=True)
        return requests + [(base + odds, key, current)
                           for odds, key in scored[:policy.max_fits_per_step]]

    def bound(self, key):
        """Return the upper bound of a request's log posterior at the table's shared ρ now."""
        cand = self.candidates.get(key)
        if cand is None or cand.test is None:
            return math.inf                      # no score test: always a contender
        rho = shared_rho(self.candidates.values())
        loglik = cand.parent.loglik + 0.5 * self.policy.score_allowance * cand.test.statistic
        return (log_evidence(loglik, cand.parent.n_params + cand.test.k, cand.parent.n_obs, rho)
                + self.prior.log(key))

    def swap_bound(self, rest, new):
        """
        Return the bound of the unfitted ``rest`` + ``new`` by a score test (cached).

        ``new``'s test at ``rest`` enters the table where the explanation is not in it yet.
        """
        smaller = self.candidates.get(rest)
        if smaller is None or not smaller.fitted:
            return math.inf
        test = tests_at(self.space, self, smaller.result, [new[0]]).get(new[0])
        if test is None:
            return math.inf
        key = canonical(rest + (new,))
        self.candidates.setdefault(key, Candidate(key, parent=smaller.result, test=test))
        return self.bound(key)

    def fit_step(self, requests):
        """Fit a step's requests [(bound, key, start)] by branch and bound; return the fits."""
        share = math.log(self.policy.fit_share)
        bounds = {key: self.bound(key) for _, key, _ in requests}
        top = max((b for b in bounds.values() if math.isfinite(b)), default=-math.inf)
        begun, wait = self.early or (set(), list)
        self.early = None
        first = [(key, start) for _, key, start in requests
                 if bounds[key] >= top + share and key not in begun]
        rest = [(key, start) for _, key, start in requests if bounds[key] < top + share]
        # the rest begin ahead where the first leave a worker idle; those the first's fits
        # bound out are given up (never entered)
        keep = self.space.fit_ahead(rest)
        fitted = (self.fit(first, '  fitting ') if first else []) + wait()
        size = len(requests[0][1])
        best = max((self.log_post(c.result) for c in self.candidates.values()
                    if c.fitted and len(c.effects) == size), default=-math.inf)
        rest = [(key, start) for key, start in rest if self.bound(key) >= best + share]
        keep(rest)
        if rest:
            fitted += self.fit(rest, '  then ')
        return fitted

    def restart_equivalents(self, fitted):
        """Refit a lag or delay that ended below its equivalent's likelihood from its estimate."""
        candidates = self.candidates
        by_key = {r.effects: r for r in fitted if r is not None}
        for res in list(by_key.values()):
            for effect, variant in res.effects:
                for other, (theirs, mine) in FIRST_ORDER_START.get(effect, {}).items():
                    twin = canonical(tuple(ev for ev in res.effects if ev[0] != effect)
                                     + ((other, ''),))
                    rival = candidates.get(twin)
                    if rival is None or not rival.fitted \
                            or rival.result.loglik - res.loglik <= self.policy.restart_margin:
                        continue
                    values = rival.result.start_values()
                    if theirs not in values:
                        continue
                    values[mine] = abs(values.pop(theirs))
                    lower, upper = (-math.inf, math.inf) if res.fit.model is None else \
                        parameter_range(res.fit.model, mine)
                    if not lower < values[mine] < upper:
                        continue        # the equivalent's value is outside this effect's range
                    better = self.space.refit_from(res.effects, values)
                    if better is not None and better.loglik > candidates[res.effects].loglik:
                        candidates[res.effects] = Candidate(res.effects, better)

    def backward(self, current, added):
        """Drop every effect before ``added`` whose removal makes the model more probable."""
        for effect, variant in [ev for ev in current.effects if ev != added]:
            rest = tuple(ev for ev in current.effects if ev != (effect, variant))
            smaller = self.candidates.get(rest)
            res = smaller.result if smaller is not None and smaller.fitted else \
                self.space.fit(rest, current)
            if res is None:
                continue
            self.candidates[rest] = Candidate(rest, res)
            odds = self.log_post(res) - self.log_post(current)
            if odds > 0.0:
                self.steps.append(Step('drop', effect, variant, float(odds),
                                       2.0 * (res.loglik - current.loglik), rest))
                current = res
        return current

    def exchange(self, best):
        """
        Swap each effect of ``best`` for each deterministic effect that would be named alone.

        Forward steps cannot undo an effect that stands in for another (per-blade gains for
        per-blade offsets beside a lag); random inflow is not swapped in (a filter tracks any
        unmodelled dynamics). A more probable swap is kept and the exchange repeated.
        """
        candidates, log_post = self.candidates, self.log_post
        baseline = candidates[()].result
        for _ in range(self.policy.max_effects):
            rho = shared_rho(candidates.values())
            base = log_posterior(candidates[()], rho, self.prior)
            # fitted alone, or score-tested at the baseline only (a branch-and-bound step may
            # fit the effect that stands in and never the one it stands in for)
            singles = [c.effects[0] for c in candidates.values() if len(c.effects) == 1
                       and (c.result.likelihood == baseline.likelihood if c.fitted
                            else c.parent is baseline and c.names[0] != NOISE)
                       and log_posterior(c, rho, self.prior) - base
                       >= -math.log(self.policy.fit_share)]
            requests, beat = {}, log_post(best) + math.log(self.policy.fit_share)
            for out in best.effects:
                rest = tuple(ev for ev in best.effects if ev != out)
                news = [new for new in singles if new[0] not in best.names
                        and not any(new[0] in equivalent(e, self.mu) for e, _ in rest)]
                smaller = self.candidates.get(rest)
                if news and smaller is not None and smaller.fitted:  # their tests, one batch
                    tests_at(self.space, self, smaller.result, [e for e, _ in news])
                for new in news:
                    key = canonical(rest + (new,))
                    # branch and bound at the model the swap extends, as in a forward step
                    if (key not in candidates or not candidates[key].fitted) \
                            and self.swap_bound(rest, new) >= beat:
                        requests.setdefault(key, (key, best))
            if not requests:
                return best
            self.fit(list(requests.values()), 'exchange: fitting ')
            rival = max((candidates[k].result for k in requests if candidates.get(k) is not None
                         and candidates[k].fitted), key=log_post, default=None)
            if rival is None or log_post(rival) <= log_post(best):
                return best
            added = next(ev for ev in rival.effects if ev not in best.effects)
            self.steps.append(Step('exchange', added[0], added[1],
                                   log_post(rival) - log_post(best),
                                   2.0 * (rival.loglik - best.loglik), rival.effects))
            best = rival
        return best

    def beam(self, ranked):
        """
        Return the explanations of one size to extend: the most probable ones, one per physics.

        However improbable the second is, it is extended (a stand-in can hide the pair it
        stands in for by any margin), if of the best one's likelihood (a filter-error fit
        costs tens of output-error ones) and the best one's residuals are not noise.
        """
        if self.adequate(ranked[0]):
            return ranked[:1]
        beam = []
        for res in ranked:
            if len(beam) == self.policy.beam_width:
                break
            if res.likelihood == ranked[0].likelihood \
                    and not any(same_physics(res.names, b.names, self.mu) for b in beam):
                beam.append(res)
        return beam

    def forward(self, best, frontier):
        """Step forward from ``frontier`` while the next size's best beats ``best``; the best."""
        for size in range(len(frontier[0].effects) + 1, self.policy.max_effects + 1):
            requests = {}
            for current in frontier:
                for ub, key, start in self.screen(current):
                    if ub > requests.get(key, (-math.inf,))[0]:
                        requests[key] = (ub, key, start)
            if not requests:
                break
            self.say(f'step {size}:')
            fitted = self.fit_step(list(requests.values()))
            self.restart_equivalents(fitted)
            ranked = sorted((c.result for c in self.candidates.values()
                             if c.fitted and len(c.effects) == size),
                            key=lambda r: -self.log_post(r))
            if not ranked:
                break
            odds = self.log_post(ranked[0]) - self.log_post(best)
            self.say(f'step {size}: best {" + ".join(ranked[0].names)}, '
                     f'log posterior odds {odds:.1f}')
            if odds <= 0.0:
                break
            parent = next((f for f in frontier if set(f.effects) < set(ranked[0].effects)),
                          best)
            added = next(ev for ev in ranked[0].effects if ev not in parent.effects)
            self.steps.append(Step('add', added[0], added[1], float(odds),
                                   2.0 * (ranked[0].loglik - best.loglik), ranked[0].effects))
            best = self.backward(ranked[0], added)
            frontier = self.beam(ranked)
        return best


def search(space, effects, prior, policy, mu=0.0, say=None, adequate=None, on_fit=None):
    """
    Forward steps guided by score tests, a backward check after each: :class:`Selection`.

    ``space``: a :class:`~rotor_id.diagnosis.likelihood.Likelihood` with ``baseline()`` and
    ``refit_from``; ``effects``: the catalogue ids it may use; ``mu``: the advance ratio (which
    effects are first-order equivalents); ``adequate(result)``: whether a fit's residuals are
    noise; ``on_fit(explanations)`` is told each batch of fits before it begins. The steps are
    docs/diagnosis.md's §3.
    """
    run = _Search(space, effects, prior, policy, mu, say or (lambda text: None),
                  adequate or (lambda result: False), on_fit or (lambda keys: None))
    best = space.baseline()
    run.candidates[()] = Candidate((), best)
    run.begin_unscored(best)
    # then an explanation the forward steps did not extend (reached by a drop or a swap) is
    # extended from in turn: the selection ends where no score test asks for more
    for _ in range(policy.max_effects + 1):
        before = best
        best = run.exchange(run.forward(best, [best]))
        if best is before or best.effects in run.tests \
                or len(best.effects) >= policy.max_effects:
            break
    return Selection(candidates=run.candidates, steps=run.steps, final=best, tests=run.tests,
                     effects=tuple(effects), mu=mu)


def tests_at(space, table, result, only=None):
    """
    Return the score tests of every open effect (or of those in ``only``) at a fit (cached).

    ``table``: a :class:`Selection` or the search in progress (``tests``, ``effects``, ``mu``).
    """
    here = table.tests.setdefault(result.effects, {})
    asked = [e for e in _open_effects(result, table.effects, table.mu)
             if e not in here and (only is None or e in only)]
    for effect, test in (space.score_many(result, asked) if asked else {}).items():
        if test is not None:
            here[effect] = test
    return here
