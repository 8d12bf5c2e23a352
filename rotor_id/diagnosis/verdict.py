"""
The verdict from the selection's table: probabilities, shares, detection limits, adequacy.

The rules (the most probable fitted explanation, first-order equivalents as one physics, the
0.95 confidence line, detection limits from the noncentral χ², ``unexplained`` when the
verdict's residuals are not noise) are docs/diagnosis.md's §4.
"""

import math

from rotor_id.diagnosis.catalogue import EFFECTS, equivalent
from rotor_id.diagnosis.result import Alternative, DetectionLimit, Effect, Explanation, Share
from rotor_id.diagnosis.selection import posterior, same_physics, shared_rho, tests_at
from rotor_id.estimation.validation import noncentrality_for_power


def alternatives(ranked, baseline, misfit=None, prior=None):
    """Return :class:`Alternative` rows of [(candidate, probability)]."""
    rho = shared_rho([cand for cand, _ in ranked])
    out = []
    for cand, prob in ranked:
        res = cand.result
        out.append(Alternative(
            effects=cand.names, probability=prob, fitted=cand.fitted,
            two_delta_loglik=2.0 * (cand.loglik - baseline.loglik), n_params=cand.n_params,
            likelihood=res.likelihood if res is not None else cand.parent.likelihood,
            misfit_explained=None if misfit is None or res is None else misfit(res),
            log_prior=prior.log(cand.effects) if prior is not None else math.nan,
            n_obs=cand.n_obs, rho=rho))
    return out


def _swapped(top, cand):
    """Return (effect of ``top``, effect of ``cand``) when they differ by one swap, else None."""
    mine, theirs = set(top.names), set(cand.names)
    if len(mine) != len(theirs) or len(mine - theirs) != 1:
        return None
    return next(iter(mine - theirs)), next(iter(theirs - mine))


def _shares(top, effect, ranked, policy):
    """Effects that stand in for ``effect`` in the top explanation, with their shares."""
    same = [(effect[0], p) for cand, p in ranked if cand is top]
    for cand, p in ranked:
        swap = _swapped(top, cand)
        if swap is not None and swap[0] == effect[0] and p >= policy.alternative_share:
            same.append((swap[1], p))
    total = sum(p for _, p in same)
    return [Share(e, p / total) for e, p in same]


def physics_of(top, ranked, policy, mu):
    """
    Return (the explanation to name, the probability of its physics).

    Explanations that differ from ``top`` only by first-order equivalents are one physics:
    their probabilities add. Of those holding more than 1 − high_confidence of it, the one of
    the catalogue's established effects (first in :data:`EFFECTS`) is named.
    """
    group = [(c, p) for c, p in ranked if c.fitted and same_physics(top.names, c.names, mu)]
    total = sum(p for _, p in group)
    plausible = [c for c, p in group if p >= (1.0 - policy.high_confidence) * total]
    named = min(plausible, key=lambda c: sorted(EFFECTS.index(e) for e in c.names))
    return named, total


def _effect(top, effect, ranked, candidates, policy):
    name, variant = effect
    rest = tuple(ev for ev in top.effects if ev != effect)
    without = candidates.get(rest)
    gain = None
    if without is not None and without.fitted:
        gain = 2.0 * (top.result.loglik - without.result.loglik)
    fit = top.result.fit
    params = fit.effect_parameters.get(name, {})
    layer_bound = [n for n in top.result.at_bound if n in params]
    return Effect(effect=name, variant=variant, parameters=params,
                  inclusion_probability=sum(p for c, p in ranked if name in c.names),
                  two_delta_loglik=gain, shares=_shares(top, effect, ranked, policy),
                  at_bound=layer_bound)


def acceptance_noncentrality(result, test, prior, policy, rho):
    """
    Return λ such that an effect of that noncentrality is added with the policy's power.

    λ solves P(χ²_k(λ) > c) = power, c = (k log(Nρ) − 2 log(prior odds))/ρ the search's
    acceptance point of 2Δlog L (docs/diagnosis.md §4).
    """
    key = result.effects + ((test.effect, test.variant),)
    c = (test.k * math.log(result.n_obs * rho)
         - 2.0 * (prior.log(key) - prior.log(result.effects))) / rho
    k = max(test.k, 1)
    if not math.isfinite(c):            # the model is as large as the policy allows
        return math.inf
    if c <= 0.0:
        return 0.0
    return noncentrality_for_power(c, k, policy.detection_power)


def _tested_at(selection, top):
    """
    Return the fit whose score tests give the detection limits: the verdict's model.

    Where the search score-tested at a first-order equivalent of it instead (it stopped at a
    delay, a lag is named), that fit: the same information to first order, and the same open
    effects (equivalence is symmetric).
    """
    if top.effects in selection.tests:
        return top.result
    return next((c.result for c in selection.candidates.values()
                 if c.fitted and c.effects in selection.tests
                 and c.result.likelihood == top.result.likelihood
                 and same_physics(top.names, c.names, selection.mu)), top.result)


def detection_limits(space, selection, top, prior, policy):
    """Return :class:`DetectionLimit` of every open effect at the verdict's model."""
    rho = shared_rho(selection.candidates.values())
    out = []
    tested = _tested_at(selection, top)
    for effect, test in sorted(tests_at(space, selection, tested).items()):
        lam = acceptance_noncentrality(top.result, test, prior, policy, rho)
        if not math.isfinite(lam):
            continue
        limits = {n: math.sqrt(lam * v) for n, v in test.variance.items()
                  if v >= 0.0 and not math.isnan(v)}
        if effect == 'process_noise':          # the test is of σ_V², the limit of σ_V
            limits = {'process_noise_std': math.sqrt(v) for v in limits.values()}
        out.append(DetectionLimit(effect, limits, lam, test.statistic, 'score test'))
    named = set(top.names) | {e for n in top.names for e in equivalent(n, selection.mu)}
    for effect in selection.effects:
        if effect in named or any(d.effect == effect for d in out):
            continue
        alone = [c for c in selection.candidates.values() if c.names == (effect,)]
        if alone and alone[0].fitted:
            gain = 2.0 * (alone[0].loglik - selection.candidates[()].loglik)
            out.append(DetectionLimit(effect, {}, math.nan, gain,
                                      'not nested: fitted alone, 2Δlog L given'))
    return out


def explain(space, selection, prior, policy, adequate, misfit):
    """
    Return (Explanation, the verdict's Candidate, every alternative) from the search.

    ``adequate(result)``: whether a fit's residuals are noise; ``misfit(result)``: the share
    of the baseline's excess over the noise floor it removes.
    """
    ranked = posterior(selection.candidates.values(), prior, policy.evidence_tempering)
    baseline = selection.candidates[()]
    top = next(c for c, p in ranked if c.fitted)
    top, p_top = physics_of(top, ranked, policy, selection.mu)
    table = alternatives(ranked, baseline, misfit, prior)
    shown = [a for a, (c, p) in zip(table, ranked)
             if c is not top and p >= policy.alternative_share]
    limits = detection_limits(space, selection, top, prior, policy)
    if not adequate(top.result):
        why = ('the most probable explanation' + (f' ({" + ".join(top.names)})'
                                                  if top.effects else ' (none)')
               + ' leaves residuals that are not noise')
        return Explanation('unexplained', 'low', p_top, [], shown, limits, False, why), \
            top, table
    effects = [_effect(top, ev, ranked, selection.candidates, policy) for ev in top.effects]
    main = 'none'
    if effects:
        main = max(effects, key=lambda e: e.two_delta_loglik
                   if e.two_delta_loglik is not None else -math.inf).effect
    confidence = 'high' if p_top >= policy.high_confidence else 'low'
    return Explanation(main, confidence, p_top, effects, shown, limits, True), top, table
