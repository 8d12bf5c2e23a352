#!/usr/bin/env python3
"""
Out-of-catalogue proposals: right term, coefficient within 3σ, false proposals.

For every seed, the independent truth generator makes a recording, the baseline is fitted
(:func:`rotor_id.pipeline.identify`) and :func:`rotor_id.estimation.term_search.propose` is asked
directly, whatever the diagnosis would say, on

* ``flap_stiffness_1c``, ``flap_damping_1s``: a once-per-rev flap stiffness (damping) no
  candidate models (the term to find is ``beta*cos(psi)`` with coefficient −K_1c,
  ``beta_dot*sin(psi)`` with −D_1s);
* null records (no effect) of three kinds: their false-proposal rate;
* in-catalogue records: what a proposal says there if asked (diagnose asks only when the verdict
  is ``unexplained`` or ``process_noise``).

The in-catalogue records and the second out-of-catalogue term get fewer seeds (:data:`FEWER`),
so that one command regenerates the whole file. Writes bench/results/proposal.md and .json.

    python bench/proposal_stats.py --seeds 20
"""

import argparse
import json
import math
from pathlib import Path
import sys
import time

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / 'test' / 'diagnosis'))

from common import machine_markdown  # noqa: E402 (bench/ is on sys.path as a script's dir)
from diagnosis_scenarios import BY_NAME  # noqa: E402
from rotor_id.estimation.term_search import propose  # noqa: E402
from rotor_id.pipeline import identify  # noqa: E402

RESULTS = ROOT / 'bench' / 'results'
DEFAULT = ['flap_stiffness_1c', 'flap_damping_1s', 'none_multiblade', 'none_mu04', 'none_wake',
           'process_noise', 'dynamic_inflow', 'sensor_lag', 'azimuth_offset']
#: scenarios run on at most this many seeds (what a proposal says where it is not asked for)
FEWER = {'flap_damping_1s': 10, 'process_noise': 5, 'dynamic_inflow': 5, 'sensor_lag': 5,
         'azimuth_offset': 5}


def run_one(name, seed):
    """Propose on one (scenario, seed); return what was proposed and how long it took."""
    scenario = BY_NAME[name]
    record, description = scenario.record_and_description(seed)
    cpu0, wall0 = time.process_time(), time.perf_counter()
    proposal = propose(identify(record, description))
    out = {'scenario': name, 'seed': seed, 'terms': proposal.terms, 'steps': proposal.steps,
           'reason': proposal.reason, 'cpu_s': time.process_time() - cpu0,
           'wall_s': time.perf_counter() - wall0}
    truth = scenario.extra_truth if scenario.effect == 'unexplained' else {}
    if truth:
        (term, value), = truth.items()
        found = [t for t in proposal.terms if t['term'] == term]
        out['right_term'] = bool(found) and proposal.terms[0]['term'] == term
        out['z'] = abs(found[0]['coefficient'] - value) / found[0]['std'] if found else None
        out['z_equation_error'] = (abs(found[0]['equation_error_coefficient'] - value)
                                   / found[0]['equation_error_std'] if found else None)
    return out


def summarize(runs, seeds, command='python bench/proposal_stats.py'):
    """Return the Markdown file: how to reproduce, the machine, the table."""
    lines = ['# Out-of-catalogue proposals (bench/proposal_stats.py)', '',
             f'Reproduce: `{command}` (from the repository root, after `make build`).', '',
             machine_markdown(), '',
             f'{seeds} seeds per scenario (fewer where the runs column says); propose() asked '
             'directly on every record; CPU s/run is `time.process_time` of identify + '
             "propose, the generator's time excluded.", '',
             '| scenario | runs | runs with a proposal | terms proposed | right term first | '
             'coefficient within 3σ (ML) | within 3σ (equation error) | largest t of a '
             'rejected first step | CPU s/run |', '|---|---|---|---|---|---|---|---|---|']
    for name in dict.fromkeys(r['scenario'] for r in runs):
        rs = [r for r in runs if r['scenario'] == name]
        with_terms = [r for r in rs if r['terms']]
        terms = {}
        for r in with_terms:
            key = ' + '.join(t['term'] for t in r['terms'])
            terms[key] = terms.get(key, 0) + 1
        right = [r for r in rs if 'right_term' in r]
        z = [r['z'] for r in right if r.get('z') is not None]
        ze = [r['z_equation_error'] for r in right if r.get('z_equation_error') is not None]
        rejected = [r['steps'][0]['t_statistic'] for r in rs
                    if r['steps'] and not r['steps'][0]['kept']]
        lines.append(
            f'| {name} | {len(rs)} | {len(with_terms)} | '
            f'{", ".join(f"{k}×{v}" for k, v in sorted(terms.items())) or "–"} | '
            f'{sum(r["right_term"] for r in right) if right else "–"} | '
            f'{sum(v <= 3 for v in z) if right else "–"}/{len(z) if right else "–"} | '
            f'{sum(v <= 3 for v in ze) if right else "–"}/{len(ze) if right else "–"} | '
            f'{max(rejected):.2f} |' if rejected else
            f'| {name} | {len(rs)} | {len(with_terms)} | '
            f'{", ".join(f"{k}×{v}" for k, v in sorted(terms.items())) or "–"} | '
            f'{sum(r["right_term"] for r in right) if right else "–"} | '
            f'{sum(v <= 3 for v in z) if right else "–"}/{len(z) if right else "–"} | '
            f'{sum(v <= 3 for v in ze) if right else "–"}/{len(ze) if right else "–"} | – |')
        lines[-1] += f' {sum(r["cpu_s"] for r in rs) / len(rs):.1f} |'
    return '\n'.join(lines) + '\n'


def main(argv=None):
    """Run the study and write the results."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument('--seeds', type=int, default=20)
    parser.add_argument('--first-seed', type=int, default=2000)
    parser.add_argument('--scenarios', nargs='*', default=DEFAULT)
    parser.add_argument('--out', default=str(RESULTS / 'proposal'))
    args = parser.parse_args(argv)
    unknown = [n for n in args.scenarios if n not in BY_NAME]
    if unknown:
        parser.error(f'unknown scenario(s) {unknown}; choose from {list(BY_NAME)}')
    out = Path(args.out)
    command = f'python bench/proposal_stats.py --seeds {args.seeds}'
    if args.first_seed != 2000:
        command += f' --first-seed {args.first_seed}'
    if args.scenarios != DEFAULT:
        command += ' --scenarios ' + ' '.join(args.scenarios)
    if out != Path(RESULTS / 'proposal'):
        command += f' --out {args.out}'
    runs = []
    t0 = time.perf_counter()
    tasks = [(n, args.first_seed + k) for k in range(args.seeds) for n in args.scenarios
             if k < FEWER.get(n, args.seeds)]
    for i, (name, seed) in enumerate(tasks, 1):
        res = run_one(name, seed)
        runs.append(res)
        said = ' + '.join(f"{t['term']} {t['coefficient']:.4g}±{t['std']:.2g}"
                          for t in res['terms']) or 'nothing'
        print(f'[{i}/{len(tasks)}] {name} seed {seed}: {said} ({res["cpu_s"]:.1f} s CPU, '
              f'total {time.perf_counter() - t0:.0f} s)', flush=True)
        out.with_suffix('.json').write_text(json.dumps(runs, indent=1, default=float))
        out.with_suffix('.md').write_text(summarize(runs, args.seeds, command))
    print(out.with_suffix('.md').read_text())
    return 0 if all(math.isfinite(r['cpu_s']) for r in runs) else 1


if __name__ == '__main__':
    sys.exit(main())
