#!/usr/bin/env python3
"""
Full-statistics study of ``rotor-id diagnose`` on concealed-effect recordings.

For every scenario of test/diagnosis/diagnosis_scenarios.py and every seed, the independent
truth generator makes a recording, :func:`rotor_id.diagnosis.diagnose` diagnoses it, and the
outcome is checked: right effect named, baseline residual RMS excess over the noise floor
(≤ 10 % by design), augmented RMS excess (≤ 5 % wanted), extra parameters within 3σ of the
truth, original parameters' bias before/after (in their σ). Writes
bench/results/diagnosis.md (table) and bench/results/diagnosis.json (every run).

    python bench/diagnosis_stats.py                  # 10 seeds, all scenarios (hours)
    python bench/diagnosis_stats.py --seeds 3 --scenarios sensor_lag none_wake
    python bench/diagnosis_stats.py --pairs --out bench/results/diagnosis_pairs
"""

import argparse
import json
import math
import multiprocessing
import os
from pathlib import Path
import sys
import tempfile
import time

# one BLAS thread, as `rotor-id diagnose` runs (importing rotor_id sets it, but numpy is
# imported first here): the verdicts are those of the command, to the last bit
os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
os.environ.setdefault('OMP_NUM_THREADS', '1')

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / 'test' / 'diagnosis'))

from diagnosis_scenarios import BY_NAME, evaluate, PAIR_STUDY, SCENARIOS  # noqa: E402
import numpy as np  # noqa: E402
from rotor_id.diagnosis.diagnose import diagnose  # noqa: E402
import truth_generator  # noqa: E402
from run_all import NOTES_MARK, notes_of  # noqa: E402,I100

RESULTS = ROOT / 'bench' / 'results'


def run_one(args):
    """Diagnose one (scenario, seed); return the evaluation dict."""
    name, seed = args
    scenario = BY_NAME[name]
    t0, c0 = time.perf_counter(), time.process_time()
    record, description = scenario.record_and_description(seed)
    generated = {'generate_s': time.perf_counter() - t0,
                 'generate_cpu_s': time.process_time() - c0}
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        result = diagnose(record, description, workers=1).as_json()
    except Exception as exc:  # noqa: B902 - a failed run is a result of the study
        return {'scenario': name, 'seed': seed, 'effect': f'error: {exc}', 'right': False,
                'elapsed_s': time.perf_counter() - t0, **generated}
    out = evaluate(scenario, result)
    out.update(generated)
    out.update(seed=seed, elapsed_s=time.perf_counter() - t0, cpu_s=time.process_time() - c0,
               parameters=result['explanation']['parameters'],
               probability=result['explanation']['probability'],
               candidates=[{k: c.get(k) for k in ('effects', 'probability', 'two_delta_loglik',
                                                  'n_params', 'fitted')}
                           for c in result['candidates']])
    return out


def _fmt(x, spec='.3f'):
    return '–' if x is None else format(x, spec)


def summarize(runs, seeds):
    """Markdown table per scenario."""
    lines = ['# Diagnosis study (bench/diagnosis_stats.py)', '',
             f'{seeds} seeds per scenario; truth from test/diagnosis/truth_generator.py '
             '(independent blade-by-blade simulation), diagnosis by rotor_id.diagnosis. '
             '`excess` = baseline residual RMS / noise floor − 1, `aug excess` the same for the '
             'chosen model; `3σ` = extra parameters within 3σ of the truth; `orig z` = worst '
             '|estimate − truth|/σ of the original parameters, baseline → corrected. Pairs: '
             '`named right` counts an effect reported as confounded with a named one (the '
             'same physics to first order in that record), `both named` does not; '
             '`confounded` lists what was reported so. `s/run` wall (CPU) per run of the '
             "diagnosis alone (the truth's generation, or its read from the cache, is "
             '`generate_s` in the JSON).', '',
             '| scenario | truth effect | named right | both named | confounded | names given | '
             'wrong names (high conf.) | '
             'runs with an effect added beyond the truth | '
             'excess mean (max) | aug excess mean (max) | extra within 3σ | orig z before → '
             'after | s/run |',
             '|---|---|---|---|---|---|---|---|---|---|---|---|---|']
    # the study's scenarios in their order, then any other named one run (triples, ...)
    ran = dict.fromkeys(r['scenario'] for r in runs)
    for sc in [s for s in SCENARIOS if s.name in ran] + [
            BY_NAME[n] for n in ran if n not in {s.name for s in SCENARIOS}]:
        rs = [r for r in runs if r['scenario'] == sc.name]
        if not rs:
            continue
        right = sum(r['right'] for r in rs)
        wrong = [r for r in rs if not r['right']]
        names = {}
        for r in wrong:
            key = r['effect'] + (' (high)' if r.get('confidence') == 'high' else '')
            names[key] = names.get(key, 0) + 1
        wrong_txt = ', '.join(f'{k}×{v}' for k, v in sorted(names.items())) or '–'
        given = {}
        for r in rs:
            key = ' + '.join(r.get('named') or [r['effect']])
            given[key] = given.get(key, 0) + 1
        added = sum(bool(r.get('extra_names')) for r in rs)
        strict = f'{sum(r.get("right_named", r["right"]) for r in rs)}/{len(rs)}' \
            if sc.together else '–'
        conf = {}
        for r in rs:
            for c in r.get('confounded', []):
                conf[c] = conf.get(c, 0) + 1
        conf_txt = ', '.join(f'{k}×{v}' for k, v in sorted(conf.items())) or '–'
        given_txt = ', '.join(f'{k}×{v}' for k, v in sorted(given.items()))
        exc = [r['excess'] for r in rs if 'excess' in r]
        aug = [r['augmented_excess'] for r in rs if 'augmented_excess' in r]
        w3 = [r['within_3sigma'] for r in rs if r.get('within_3sigma') is not None]
        ob = [r['original_bias_before'] for r in rs if r.get('original_bias_before') is not None]
        oa = [r['original_bias_after'] for r in rs if r.get('original_bias_after') is not None]
        lines.append(
            f'| {sc.name} | {" + ".join(g[0] for g in sc.together) or sc.effect} | '
            f'{right}/{len(rs)} | {strict} | {conf_txt} | {given_txt} | {wrong_txt} | '
            f'{added}/{len(rs)} | '
            f'{_fmt(np.mean(exc) if exc else None)} ({_fmt(max(exc) if exc else None)}) | '
            f'{_fmt(np.mean(aug) if aug else None)} ({_fmt(max(aug) if aug else None)}) | '
            f'{sum(w3)}/{len(w3)} | {_fmt(np.mean(ob) if ob else None, ".1f")} → '
            f'{_fmt(np.mean(oa) if oa else None, ".1f")} | '
            f'{np.mean([r["elapsed_s"] for r in rs]):.0f} '
            f'({np.mean([r.get("cpu_s", math.nan) for r in rs]):.0f}) |')
    return '\n'.join(lines) + '\n'


def results_markdown(runs, seeds, command, notes, load_at_start):
    """
    Return the results file: the table, how it was made (command, load), ``notes``.

    ``notes`` are the hand-written notes of the file being replaced (from :data:`NOTES_MARK`
    on), so a re-run, or an interrupted one, keeps them; their figures are to be checked.
    """
    made = (f'Reproduce: `{command}` ({seeds} seed(s) per scenario; load average (1/5/15 min) '
            f'{" / ".join(f"{x:.2f}" for x in load_at_start)} at the start, '
            f'{" / ".join(f"{x:.2f}" for x in os.getloadavg())} at the last write).')
    text = summarize(runs, seeds) + '\n' + made + '\n'
    return text + '\n' + (notes or NOTES_MARK + '\n')


def rewrite_summary(path, seeds, command='python bench/diagnosis_stats.py'):
    """Regenerate the Markdown table from a study's JSON (e.g. after an interrupted run)."""
    path = Path(path)
    runs = json.loads(path.with_suffix('.json').read_text())
    md = path.with_suffix('.md')
    md.write_text(results_markdown(runs, seeds, command, notes_of(md), os.getloadavg()))
    return md


def main(argv=None):
    """Run the study and write the results."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--seeds', type=int, default=10)
    parser.add_argument('--first-seed', type=int, default=1000)
    parser.add_argument('--scenarios', nargs='*', default=[s.name for s in SCENARIOS])
    parser.add_argument('--pairs', action='store_true',
                        help='the catalogue pair study (every pair of effect groups a rig can '
                             'produce together) instead of --scenarios')
    parser.add_argument('--scenario-major', action='store_true',
                        help='all seeds of a scenario before the next (default: seed-major, '
                             'every scenario gets its first seed early)')
    parser.add_argument('--workers', type=int, default=2)
    parser.add_argument('--out', default=str(RESULTS / 'diagnosis'))
    parser.add_argument('--truth-cache', default=str(Path(tempfile.gettempdir())
                                                     / 'rotor_id_truth_cache'),
                        help='directory of generated truth records, looked up by a hash of the '
                             'generator source and the truth (a re-run reads them: a turbulent '
                             'record takes seconds to generate); "" generates every record')
    args = parser.parse_args(argv)
    if args.truth_cache:
        os.environ[truth_generator.CACHE_ENV] = args.truth_cache
    unknown = [n for n in args.scenarios if n not in BY_NAME]
    if unknown:
        parser.error(f'unknown scenario(s) {unknown}; choose from {list(BY_NAME)}')
    if args.pairs:
        args.scenarios = [s.name for s in PAIR_STUDY]
    if args.scenario_major:
        tasks = [(n, args.first_seed + k) for n in args.scenarios for k in range(args.seeds)]
    else:
        tasks = [(n, args.first_seed + k) for k in range(args.seeds) for n in args.scenarios]
    runs = []
    t0 = time.perf_counter()
    out = Path(args.out)
    notes = notes_of(out.with_suffix('.md'))
    load_at_start = os.getloadavg()
    command = ' '.join(['python', 'bench/diagnosis_stats.py'] + list(
        sys.argv[1:] if argv is None else argv))
    out.parent.mkdir(parents=True, exist_ok=True)
    ctx = multiprocessing.get_context('fork')
    with ctx.Pool(args.workers) as pool:
        for i, res in enumerate(pool.imap_unordered(run_one, tasks), 1):
            runs.append(res)
            print(f'[{i}/{len(tasks)}] {res["scenario"]} seed {res["seed"]}: {res["effect"]} '
                  f'({"right" if res["right"] else "WRONG"}), excess '
                  f'{_fmt(res.get("excess"))}, {res["elapsed_s"]:.0f} s '
                  f'(total {time.perf_counter() - t0:.0f} s)', flush=True)
            # written after every run, so an interrupted study still leaves its results
            out.with_suffix('.json').write_text(json.dumps(runs, indent=1, default=float))
            out.with_suffix('.md').write_text(
                results_markdown(runs, args.seeds, command, notes, load_at_start))
    print(out.with_suffix('.md').read_text())
    return 0


if __name__ == '__main__':
    sys.exit(main())
