"""
Model selection over explanations: score-test-guided forward steps, a backward check, posterior.

One algorithm over the likelihood interface (:class:`rotor_id.diagnosis.likelihood.Likelihood`):
it never asks whether a model is fitted by output error or by filter error.

* **Evidence.** Each fitted explanation S has log p(data | S) ≈ ρ*·log L_S − ½ k_S log(Nρ*)
  (:meth:`~rotor_id.diagnosis.likelihood.FitResult.log_evidence`), ρ* the effective fraction
  of the residuals of the most likely fit (a quasi-likelihood: correlated residuals carry
  less information per sample). Explanations only score-tested enter with log L ≈ log L_S +
  LM/2 (the Gauss-Newton prediction of the fit).
* **Prior.** Uniform over the sizes 0 … K, then uniform over the C(m, size) sets of a size,
  and uniform over an effect's variants (the odd blade: one of N).
* **Search.** At the current model every remaining effect is score-tested; those that could
  hold :attr:`~rotor_id.diagnosis.policy.SelectionPolicy.fit_share` of the posterior (and the
  effects without a score test) are fitted on top of it. The most probable is added when it
  is more probable than the current model; then every earlier effect must stay (backward
  check: the model without it is fitted and must be less probable). At most K effects. An
  explanation reached by a drop or an exchange is extended from in turn.
* **Posterior.** Normalised over every explanation fitted or score-tested on the way.
"""

from dataclasses import dataclass, field
import math

from rotor_id.diagnosis.catalogue import (
    equivalent, FIRST_ORDER_START, LAG_PARAMETER, n_choices, parameter_range)
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

    Effects that are the same physics to first order in this record (a sensor lag, a delay
    and a pitch-actuator lag; :func:`~rotor_id.diagnosis.catalogue.equivalent`) are one
    physics: m counts the physics, and each form of one shares its weight. An effect's
    variants (the odd blade: one of N) share it too.
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
    n_obs = candidate.result.n_obs if candidate.fitted else candidate.parent.n_obs
    return (rho * candidate.loglik - 0.5 * candidate.n_params * math.log(n_obs * rho)
            + prior.log(candidate.effects))


def posterior(candidates, prior, tempering=1.0):
    """
    Return [(candidate, probability)] over the table, most probable first.

    Score-test approximations enter the normalisation but are never ranked above a fit of
    the same size that explains more: they are predictions, not fits. ``tempering`` η ≤ 1
    scales every log posterior (temperature scaling, p ∝ posterior^η): the ranking stays,
    the odds shrink (see :attr:`SelectionPolicy.evidence_tempering`).
    """
    rows = list(candidates)
    rho = shared_rho(rows)
    logs = [tempering * log_posterior(c, rho, prior) for c in rows]
    top = max(logs)
    weights = [math.exp(v - top) for v in logs]
    total = sum(weights)
    out = sorted(zip(rows, (w / total for w in weights)), key=lambda cp: -cp[1])
    return out


def _log_post(result, candidates, prior):
    return log_posterior(Candidate(result.effects, result), shared_rho(candidates.values()),
                         prior)


def _open_effects(current, effects, mu):
    """Return the effects that can be added to ``current``: not in it, nor its equivalents."""
    taken = set(current.names)
    for e in current.names:
        taken.update(equivalent(e, mu))
    return [e for e in effects if e not in taken]


def _screen(space, current, effects, candidates, prior, policy, tests, mu, say):
    """
    Score-test every open effect at ``current``; return the requests worth fitting.

    An effect is fitted when allowance·LM could give its explanation ``fit_share`` of the
    posterior against ``current``; an effect without a score test, when it was fitted alone
    and held that share against the baseline, or at the first step.
    """
    rho = shared_rho(candidates.values())
    here = tests.setdefault(current.effects, {})
    scored, unscored = [], []
    open_effects = _open_effects(current, effects, mu)
    asked = [e for e in open_effects if e not in here]
    fresh = space.score_many(current, asked) if asked else {}
    for effect in open_effects:
        test = here.get(effect) or fresh.get(effect)
        if test is None:
            unscored.append(effect)
            continue
        here[effect] = test
        key = canonical(current.effects + ((effect, test.variant),))
        if key not in candidates:
            candidates[key] = Candidate(key, parent=current, test=test)
        odds = (0.5 * (policy.score_allowance * test.statistic * rho
                       - test.k * math.log(current.n_obs * rho))
                + prior.log(key) - prior.log(current.effects))
        if effect in LAG_PARAMETER and 'time_delay' in open_effects:
            # tested through the delay d = τ (one statistic): a lag is fitted beside the delay
            # only where the delay would be added, so that they compete for the name
            expected = (0.5 * (test.statistic * rho - test.k * math.log(current.n_obs * rho))
                        + prior.log(key) - prior.log(current.effects))
            odds = odds if expected >= 0.0 else -math.inf
        if odds >= math.log(policy.fit_share) and not candidates[key].fitted:
            scored.append((odds, key))
    if here:
        ranked = sorted(here.items(), key=lambda et: -et[1].statistic)
        say(f'score tests at {" + ".join(current.names) or "the baseline"}: '
            + ', '.join(f'{e} {t.statistic:.1f}' for e, t in ranked))
    base = _log_post(current, candidates, prior)
    scored.sort(reverse=True)
    requests = [(base + odds, key, current) for odds, key in scored[:policy.max_fits_per_step]]
    for effect in unscored:
        key = canonical(current.effects + ((effect, ''),))
        alone = candidates.get(canonical(((effect, ''),)))
        earned = alone is not None and alone.fitted and (
            _log_post(alone.result, candidates, prior)
            - _log_post(candidates[()].result, candidates, prior) >= math.log(policy.fit_share))
        if (not current.effects or earned) and not (key in candidates
                                                    and candidates[key].fitted):
            requests.append((math.inf, key, current))
    return requests


def _bound(request, candidates, prior, policy):
    """Return the upper bound of a request's log posterior at the table's shared ρ now."""
    _, key, _ = request
    cand = candidates.get(key)
    if cand is None or cand.test is None:
        return math.inf                      # no score test: always a contender
    rho = shared_rho(candidates.values())
    loglik = cand.parent.loglik + 0.5 * policy.score_allowance * cand.test.statistic
    k = cand.parent.n_params + cand.test.k
    return rho * loglik - 0.5 * k * math.log(cand.parent.n_obs * rho) + prior.log(key)


def _fit_step(space, requests, candidates, prior, policy, say):
    """
    Fit a step's requests [(bound, key, start)]; return the fits.

    Branch and bound on the score tests' bound of the posterior (:func:`_bound`, evaluated
    at the shared ρ as it stands): the requests that could be the step's best (bound within
    ``fit_share`` of the highest, and those without a score test) first; then each other
    whose bound still reaches ``fit_share`` of the best fit.
    """
    bounds = {r[1]: _bound(r, candidates, prior, policy) for r in requests}
    top = max((b for b in bounds.values() if math.isfinite(b)), default=-math.inf)
    first = [r for r in requests if bounds[r[1]] >= top + math.log(policy.fit_share)]
    rest = [r for r in requests if bounds[r[1]] < top + math.log(policy.fit_share)]
    say('  fitting ' + ', '.join(' + '.join(e for e, _ in k) for _, k, _ in first))
    fitted = space.fit_many([(k, start) for _, k, start in first])
    _record(fitted, candidates, say)
    size = len(requests[0][1])
    best = max((_log_post(c.result, candidates, prior) for c in candidates.values()
                if c.fitted and len(c.effects) == size), default=-math.inf)
    rest = [r for r in rest
            if _bound(r, candidates, prior, policy) >= best + math.log(policy.fit_share)]
    if rest:
        say('  then ' + ', '.join(' + '.join(e for e, _ in k) for _, k, _ in rest))
        more = space.fit_many([(k, start) for _, k, start in rest])
        _record(more, candidates, say)
        fitted += more
    return fitted


def _restart_equivalents(space, fitted, candidates, policy):
    """
    Refit a lag or delay that ended below its first-order equivalent's likelihood.

    Started from the equivalent's estimate (a lag τ is a delay d = τ to first order); the
    better of the two fits is kept.
    """
    by_key = {r.effects: r for r in fitted if r is not None}
    for res in list(by_key.values()):
        for effect, variant in res.effects:
            for other, (theirs, mine) in FIRST_ORDER_START.get(effect, {}).items():
                twin = canonical(tuple(ev for ev in res.effects if ev[0] != effect)
                                 + ((other, ''),))
                rival = candidates.get(twin)
                if rival is None or not rival.fitted \
                        or rival.result.loglik - res.loglik <= policy.restart_margin:
                    continue
                values = rival.result.start_values()
                if theirs not in values:
                    continue
                values[mine] = abs(values.pop(theirs))
                lower, upper = (-math.inf, math.inf) if res.fit.model is None else \
                    parameter_range(res.fit.model, mine)
                if not lower < values[mine] < upper:
                    continue            # the equivalent's value is outside this effect's range
                better = space.refit_from(res.effects, values)
                if better is not None and better.loglik > candidates[res.effects].loglik:
                    candidates[res.effects] = Candidate(res.effects, better)


def _backward(space, current, added, candidates, prior, steps):
    """Drop every effect before ``added`` whose removal makes the model more probable."""
    for effect, variant in [ev for ev in current.effects if ev != added]:
        rest = tuple(ev for ev in current.effects if ev != (effect, variant))
        smaller = candidates.get(rest)
        res = smaller.result if smaller is not None and smaller.fitted else \
            space.fit(rest, current)
        if res is None:
            continue
        candidates[rest] = Candidate(rest, res)
        odds = _log_post(res, candidates, prior) - _log_post(current, candidates, prior)
        if odds > 0.0:
            steps.append(Step('drop', effect, variant, float(odds),
                              2.0 * (res.loglik - current.loglik), rest))
            current = res
    return current


def _record(fitted, candidates, say):
    """Enter fits into the table (None: a failed fit)."""
    base = candidates[()].result
    for res in fitted:
        if res is not None:
            candidates[res.effects] = Candidate(res.effects, res)
            say(f'  {" + ".join(res.names)}: 2Δlog L {2.0 * (res.loglik - base.loglik):.1f} '
                f'with {res.n_params} ({res.likelihood}, {res.elapsed_s:.1f} s)')


def _exchange(space, best, candidates, prior, policy, steps, mu, say):
    """
    Swap each effect of the final explanation for each strong single effect not in it.

    Strong: fitted alone, it beats the baseline by posterior odds of 1/fit_share or more (it
    would be named alone); random inflow is not swapped in (its own score test is asked at
    every step, and a filter tracks any unmodelled dynamics). Forward steps cannot undo an
    effect that stands in for another (per-blade gains for per-blade offsets beside a lag);
    the swap is kept when it is more probable, and the exchange repeated from there.
    """
    base = _log_post(candidates[()].result, candidates, prior)
    for _ in range(policy.max_effects):
        singles = [c.result for c in candidates.values() if c.fitted and len(c.effects) == 1
                   and c.result.likelihood == candidates[()].result.likelihood
                   and _log_post(c.result, candidates, prior) - base
                   >= -math.log(policy.fit_share)]
        requests = {}
        for out in best.effects:
            rest = tuple(ev for ev in best.effects if ev != out)
            for single in singles:
                new = single.effects[0]
                if new[0] in best.names or any(new[0] in equivalent(e, mu) for e, _ in rest):
                    continue
                key = canonical(rest + (new,))
                if key not in candidates or not candidates[key].fitted:
                    requests.setdefault(key, (key, best))
        if not requests:
            return best
        say(f'exchange: fitting {", ".join(" + ".join(e for e, _ in k) for k in requests)}')
        _record(space.fit_many(list(requests.values())), candidates, say)
        rival = max((candidates[k].result for k in requests if candidates.get(k) is not None
                     and candidates[k].fitted), key=lambda r: _log_post(r, candidates, prior),
                    default=None)
        if rival is None or _log_post(rival, candidates, prior) <= _log_post(best, candidates,
                                                                             prior):
            return best
        added = next(ev for ev in rival.effects if ev not in best.effects)
        steps.append(Step('exchange', added[0], added[1],
                          _log_post(rival, candidates, prior) - _log_post(best, candidates,
                                                                          prior),
                          2.0 * (rival.loglik - best.loglik), rival.effects))
        best = rival
    return best


def same_physics(a, b, mu):
    """Return whether two explanations differ only by first-order equivalents."""
    mine, theirs = set(a), set(b)
    if len(mine) != len(theirs):
        return False
    x, y = mine - theirs, theirs - mine
    return all(any(v in equivalent(u, mu) for v in y) for u in x) \
        and all(any(u in equivalent(v, mu) for u in x) for v in y)


def _beam(ranked, policy, mu, adequate):
    """
    Return the explanations of one size to extend: the most probable ones, one per physics.

    At most ``beam_width``, each of another physics than those before it (extending a delay
    beside the lag it is equivalent to tests the same models again). However improbable the
    second is, it is extended: a stand-in can hide the pair it stands in for by any margin.
    Only explanations of the best one's likelihood are extended beside it (a compute budget:
    a filter-error fit costs tens of output-error ones; random inflow is score-tested on top
    of the best explanation at every step all the same), and only when the best one leaves
    residuals that are not noise (``adequate``): otherwise nothing is left that a pair
    could explain better than the effect standing in for it.
    """
    if adequate(ranked[0]):
        return ranked[:1]
    beam = []
    for res in ranked:
        if len(beam) == policy.beam_width:
            break
        if res.likelihood == ranked[0].likelihood \
                and not any(same_physics(res.names, b.names, mu) for b in beam):
            beam.append(res)
    return beam


def search(space, effects, prior, policy, mu=0.0, say=None, adequate=None):
    """
    Forward steps guided by score tests, a backward check after each: :class:`Selection`.

    ``space``: a :class:`~rotor_id.diagnosis.likelihood.Likelihood` with ``baseline()``,
    ``fit_many`` and ``refit_from``; ``effects``: the catalogue ids it may use; ``mu``: the
    advance ratio (which effects are first-order equivalents, never added together). Each
    step extends the :attr:`~SelectionPolicy.beam_width` most probable explanations of the
    last size (:func:`_beam`; ``adequate(result)``: whether a fit's residuals are noise);
    the search goes on while the best of the new size is the most probable yet.
    """
    say = say or (lambda text: None)
    adequate = adequate or (lambda result: False)
    best = space.baseline()
    candidates = {(): Candidate((), best)}
    steps, tests = [], {}
    table = (space, effects, candidates, prior, policy, tests, mu, say)
    best = _forward(table, best, [best], steps, adequate)
    best = _exchange(space, best, candidates, prior, policy, steps, mu, say)
    # a final explanation the forward steps did not extend (reached by a drop or a swap) is
    # extended from in turn: the selection ends where no score test asks for more
    for _ in range(policy.max_effects):
        if best.effects in tests or len(best.effects) >= policy.max_effects:
            break
        before = best
        best = _exchange(space, _forward(table, best, [best], steps, adequate), candidates,
                         prior, policy, steps, mu, say)
        if best is before:
            break
    return Selection(candidates=candidates, steps=steps, final=best, tests=tests,
                     effects=tuple(effects), mu=mu)


def _forward(table, best, frontier, steps, adequate):
    """
    Forward steps from ``frontier`` while the best of the next size is more probable: the best.

    Each step score-tests the open effects at each explanation of the frontier, fits the
    promising ones (:func:`_fit_step`), adds the most probable when it beats ``best``, checks
    backward, and extends the beam (:func:`_beam`) of that size next.
    """
    space, effects, candidates, prior, policy, tests, mu, say = table
    for size in range(len(frontier[0].effects) + 1, policy.max_effects + 1):
        requests = {}
        for current in frontier:
            for ub, key, start in _screen(space, current, effects, candidates, prior, policy,
                                          tests, mu, say):
                if ub > requests.get(key, (-math.inf,))[0]:
                    requests[key] = (ub, key, start)
        if not requests:
            break
        say(f'step {size}:')
        fitted = _fit_step(space, list(requests.values()), candidates, prior, policy, say)
        _restart_equivalents(space, fitted, candidates, policy)
        ranked = sorted((c.result for c in candidates.values()
                         if c.fitted and len(c.effects) == size),
                        key=lambda r: -_log_post(r, candidates, prior))
        if not ranked:
            break
        odds = _log_post(ranked[0], candidates, prior) - _log_post(best, candidates, prior)
        say(f'step {size}: best {" + ".join(ranked[0].names)}, log posterior odds {odds:.1f}')
        if odds <= 0.0:
            break
        parent = next((f for f in frontier if set(f.effects) < set(ranked[0].effects)), best)
        added = next(ev for ev in ranked[0].effects if ev not in parent.effects)
        steps.append(Step('add', added[0], added[1], float(odds),
                          2.0 * (ranked[0].loglik - best.loglik), ranked[0].effects))
        best = _backward(space, ranked[0], added, candidates, prior, steps)
        frontier = _beam(ranked, policy, mu, adequate)
    return best


def tests_at(space, selection, result):
    """Return the score tests of every open effect at a fitted explanation (cached)."""
    here = selection.tests.setdefault(result.effects, {})
    asked = [e for e in _open_effects(result, selection.effects, selection.mu) if e not in here]
    for effect, test in (space.score_many(result, asked) if asked else {}).items():
        if test is not None:
            here[effect] = test
    return here
