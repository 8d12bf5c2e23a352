#!/usr/bin/env python3
"""
Re-score the verdicts of a calibration study under other evidence rules, from its tables.

A study line (bench/calibration_study.py) holds the verdict's candidate table with every
term of each explanation's evidence: 2Δlog L, parameters k, observations n, the
autocorrelation factor ρ and the log prior. Here the stated probability is recomputed under
another rule, with the search's table unchanged:

    log evidence = η · (ρ Δlog L − k · penalty + log prior)

- ``bic``: penalty ½ log(nρ), the diagnosis's own (unit-information prior on each size);
- ``g=G``: penalty ½ log(1 + G), a Zellner-type prior whose width is G times a parameter's
  sampling variance (BIC is G = nρ): a prior that expects effects near the detection limit;
- ``aic``: penalty 1 (Akaike weights, Burnham & Anderson).

The verdict is the most probable fitted explanation, its first-order equivalents' shares
added (rotor_id.diagnosis.verdict.physics_of); a record whose verdict was ``unexplained`` stays
so (its residual test does not depend on the rule). Right is scored as the study does, from
the draw's accepted groups. Prints, per rule and η, the accuracy at a stated ≥ 0.95 with its
Wilson interval, the false alarms on the nulls, and the log score (all records, and the odd
and even seeds apart: the halves on which η is chosen and checked).

    python bench/verdict_rules.py STUDY.jsonl [--eta 0.6 0.7 0.8 1.0] [--g 10 100 1000]
"""

import argparse
import json
import math
from pathlib import Path
import sys

from calibration_study import HIGH, random_scenarios, wilson
from rotor_id.diagnosis.policy import DEFAULT_POLICY
from rotor_id.diagnosis.selection import same_physics

#: An explanation one swap from the verdict's is named beside it from this share on.
ALTERNATIVE_SHARE = DEFAULT_POLICY.alternative_share


def penalty_of(rule, cand):
    """Return the log-evidence penalty of one parameter under ``rule``."""
    if rule == 'bic':
        return 0.5 * math.log(cand['n_obs'] * cand['rho'])
    if rule == 'aic':
        return 1.0
    return 0.5 * math.log1p(float(rule.split('=')[1]))


def verdict(line, rule, eta):
    """Return (named effects or 'unexplained', stated probability) under ``rule``, ``eta``."""
    table = line['candidates']
    logs = [eta * (c['rho'] * c['two_delta_loglik'] / 2.0 - c['n_params'] * penalty_of(rule, c)
                   + c['log_prior']) for c in table]
    top = max(logs)
    weights = [math.exp(v - top) for v in logs]
    total = sum(weights)
    ranked = sorted(zip(table, (w / total for w in weights)), key=lambda cp: -cp[1])
    best = next(c for c, _ in ranked if c['fitted'])
    mu = line['draw']['mu']
    p_top = sum(p for c, p in ranked
                if c['fitted'] and same_physics(best['effects'], c['effects'], mu))
    if line['verdict'] == 'unexplained':
        return 'unexplained', p_top
    # confounded: an explanation one swap away holding ≥ ALTERNATIVE_SHARE (verdict._shares)
    named = {e: set() for e in best['effects']}
    mine = set(best['effects'])
    for cand, p in ranked:
        theirs = set(cand['effects'])
        if p >= ALTERNATIVE_SHARE and len(theirs) == len(mine) and len(mine - theirs) == 1:
            named[next(iter(mine - theirs))].add(next(iter(theirs - mine)))
    return named, p_top


class _Drawn:
    """The scenario of a study line as random_scenarios.score reads it: its accepted ids."""

    def __init__(self, line):
        self.groups = line['draw']['accepted']

    def accepted(self):
        return self.groups


def right(line, named):
    """Score a verdict ({effect: confounded with} or 'unexplained') as the study does."""
    if named == 'unexplained':
        explanation = {'effect': 'unexplained', 'effects': []}
    else:
        explanation = {'effect': next(iter(named), 'none'),
                       'effects': [{'effect': e, 'confounded_with': sorted(c)}
                                   for e, c in named.items()]}
    return random_scenarios.score(_Drawn(line), {'explanation': explanation})['right']


def summary(lines, rule, eta):
    """Return the figures of one rule."""
    high = right_high = nulls = alarms = 0
    log_score = 0.0
    for line in lines:
        named, p = verdict(line, rule, eta)
        ok = right(line, named)
        if named != 'unexplained':
            log_score += math.log(max(p if ok else 1.0 - p, 1e-12))
        if p >= HIGH and named != 'unexplained':
            high += 1
            right_high += ok
        if not line['draw']['accepted']:
            nulls += 1
            alarms += named not in ('unexplained',) and bool(named)
    lo, hi = wilson(right_high, high)
    return {'rule': rule, 'eta': eta, 'high': high, 'right_high': right_high,
            'accuracy_high': right_high / high if high else math.nan, 'wilson95': (lo, hi),
            'nulls': nulls, 'false_alarms': alarms, 'log_score': log_score}


def main(argv=None):
    """Print the table of rules."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument('study', type=Path)
    parser.add_argument('--eta', type=float, nargs='+', default=[0.6, 0.7, 0.75, 0.8, 1.0])
    parser.add_argument('--g', type=float, nargs='+', default=[10.0, 100.0, 1000.0])
    parser.add_argument('--out', default=None,
                        help='also write the table to OUT.md (e.g. bench/results/verdict_rules)')
    args = parser.parse_args(argv)
    lines = [json.loads(s) for s in args.study.read_text().splitlines() if s.strip()]
    lines = [s for s in lines if 'candidates' in s]
    if not lines:
        print(f'{args.study}: no line with a candidate table', file=sys.stderr)
        return 2
    own = [s for s in lines if s['verdict'] != 'unexplained']
    same_p = sum(abs(verdict(s, 'bic', s['tempering'])[1] - s['probability']) < 1e-6
                 for s in own)
    same_right = sum(right(s, verdict(s, 'bic', s['tempering'])[0]) == s['right'] for s in own)
    out = [f'{len(lines)} records of {args.study.name}; on the {len(own)} not unexplained the '
           f"diagnosis's own rule reproduces {same_p} stated probabilities and {same_right} "
           'scores.', '',
           '| rule | η | stated ≥ 0.95 | right | accuracy (Wilson 95 %) | false alarms on nulls '
           '| log score | odd seeds | even seeds |', '|---|---|---|---|---|---|---|---|---|']
    for rule in ['bic', 'aic'] + [f'g={g:g}' for g in args.g]:
        for eta in args.eta:
            s = summary(lines, rule, eta)
            odd, even = (summary([x for x in lines if x['seed'] % 2 == parity], rule, eta)
                         for parity in (1, 0))
            lo, hi = s['wilson95']
            out.append(f'| {rule} | {eta:g} | {s["high"]} | {s["right_high"]} | '
                       f'{s["accuracy_high"]:.0%} ({lo:.0%}–{hi:.0%}) | '
                       f'{s["false_alarms"]}/{s["nulls"]} | {s["log_score"]:.1f} | '
                       f'{odd["log_score"]:.1f} | {even["log_score"]:.1f} |')
    print('\n'.join(out))
    if args.out:
        command = ' '.join(['python', 'bench/verdict_rules.py', str(args.study), '--eta',
                            *map(str, args.eta), '--g', *(f'{g:g}' for g in args.g),
                            '--out', args.out])
        Path(args.out).with_suffix('.md').write_text(
            '# Verdict rules re-scored on recorded candidate tables\n\n'
            f'Reproduce: `{command}` (from the repository root; about a second).\n\n'
            + __doc__.split('\n\n', 1)[1].rsplit('\n\n', 1)[0] + '\n\n' + '\n'.join(out)
            + '\n')
    return 0


if __name__ == '__main__':
    sys.exit(main())
