#!/usr/bin/env python3
"""
Calibration of ``rotor-id diagnose``: does a stated probability mean what it says.

K random records (test/diagnosis/random_scenarios.py: rotor, noise, concealed effects and
their sizes from one seed each; the records from the independent truth generator) are
diagnosed and each verdict is scored right or not against the truth (random_scenarios.score).
The verdict's stated probability is ``explanation.probability``; an engine that gives none
is read by its label: 'high' as 0.95 (high confidence means at least 0.95) and
'low' as 0.5 (it claims no more than an even chance). Writes

- ``<out>.jsonl``: one line per record (resumable: a re-run skips the seeds it holds), with
  the verdict's candidate table (every term of each explanation's evidence);
- ``<out>.md``, ``<out>.json``: the reliability table (stated probability in bins against
  the observed accuracy, Wilson 95 % intervals), accuracy at high confidence, false alarms
  on the nulls, the breakdown per truth class and per rotor;
- ``<out>.png``: the reliability diagram.

    nice -n 10 python bench/calibration_study.py --records 300          # hours (see .md)
    python bench/calibration_study.py --records 40 --workers 2
    python bench/calibration_study.py --summary-only                    # tables from .jsonl
    python bench/calibration_study.py --kind null --first-seed 1001 --records 100 \
        --out bench/results/calibration_nulls                           # false alarms

Exit status 1 when the records reject a target at the 1 % level.
"""

import argparse
from dataclasses import replace
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

from common import machine_description, REPO_ROOT, RESULTS_DIR  # noqa: E402
import numpy as np  # noqa: E402
from run_all import NOTES_MARK, notes_of  # noqa: E402
from scipy import stats  # noqa: E402

sys.path.insert(0, str(REPO_ROOT / 'test' / 'diagnosis'))
import random_scenarios  # noqa: E402,I100
import truth_generator  # noqa: E402

#: Bins of the stated probability: below an even chance; "likely"; "probable"; and the
#: issue's high confidence (at least 0.95), the bin the targets are about.
BINS = (0.0, 0.5, 0.8, 0.95, 1.0)
#: A stated probability at or above this is "high confidence".
HIGH = 0.95
#: Targets: accuracy at high confidence, false alarms on the nulls.
TARGET_ACCURACY_HIGH = 0.95
TARGET_FALSE_ALARMS = 0.02
#: Two-sided 95 % normal quantile of the Wilson intervals.
Z95 = float(stats.norm.ppf(0.975))


def wilson(right, n, z=Z95):
    """Wilson score interval of a binomial proportion (lo, hi); (0, 1) when n = 0."""
    if n == 0:
        return 0.0, 1.0
    p = right / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return max(0.0, centre - half), min(1.0, centre + half)


def binomial_bound(n, rate, level=0.99):
    """Return the ``level`` quantile of Binomial(n, rate): the most events ``rate`` allows."""
    return int(stats.binom.ppf(level, n, rate)) if n else 0


def upper_tail(count, n, rate):
    """P(X ≥ count) for X ~ Binomial(n, rate): the p-value of ``count`` against ``rate``."""
    return float(stats.binom.sf(count - 1, n, rate)) if n else 1.0


def run_one(seed, kind=None, workers=1, tempering=None):
    """Draw, generate and diagnose one random record; return its scored line."""
    from rotor_id.diagnosis.diagnose import diagnose
    from rotor_id.diagnosis.policy import DEFAULT_POLICY
    scenario = random_scenarios.draw(seed, kind)
    c0, t0 = time.process_time(), time.perf_counter()
    try:
        record, description = scenario.record_and_description()
    except Exception as exc:  # noqa: B902 - a failed draw is a result of the study
        return {'seed': seed, 'error': f'generation: {exc!r}'}
    line = {'seed': seed, 'draw': scenario.as_dict(),
            'generate_cpu_s': time.process_time() - c0}
    c0, t0 = time.process_time(), time.perf_counter()
    try:
        policy = DEFAULT_POLICY if tempering is None else \
            replace(DEFAULT_POLICY, evidence_tempering=tempering)
        result = diagnose(record, description, workers=workers, policy=policy).as_json()
    except Exception as exc:  # noqa: B902
        line.update(error=f'diagnose: {exc!r}', cpu_s=time.process_time() - c0)
        return line
    line.update(random_scenarios.score(scenario, result),
                cpu_s=time.process_time() - c0, wall_s=time.perf_counter() - t0)
    # the candidate table with every term of its evidence and the fit's residual figures:
    # verdict rules can be re-scored on the recorded tables (bench/verdict_rules.py)
    line.update(candidates=result['candidates'], fit=result['fit'],
                tempering=result['policy']['evidence_tempering'])
    return line


def _job(args):
    return run_one(*args)


def read_runs(path):
    """Return the lines of a study's .jsonl (empty if absent)."""
    path = Path(path)
    if not path.is_file():
        return []
    return [json.loads(s) for s in path.read_text().splitlines() if s.strip()]


def _rate(right, n):
    lo, hi = wilson(right, n)
    return {'n': n, 'right': right, 'accuracy': right / n if n else None,
            'wilson95': [lo, hi]}


def named_right(line):
    """
    Return whether the named effects alone are the concealed set (equivalents allowed).

    Stricter than ``right``: no credit for an effect reported only as confounded with a
    named one.
    """
    groups = [set(g) for g in line['draw']['accepted']]
    if line['verdict'] in ('none', 'unexplained') or not line['named']:
        return line['verdict'] == 'none' and not groups
    union = set().union(*groups) if groups else set()
    named = set(line['named'])
    return bool(groups) and all(named & g for g in groups) and named <= union


def summarize(runs):
    """Return the study's statistics (a JSON-ready dict) from its scored lines."""
    done = [r for r in runs if 'error' not in r]
    judged = [r for r in done if r['verdict'] != 'unexplained']
    table = []
    for lo, hi in zip(BINS[:-1], BINS[1:]):
        inside = [r for r in judged if lo <= r['probability'] < hi
                  or (hi == 1.0 and r['probability'] == 1.0)]
        row = _rate(sum(r['right'] for r in inside), len(inside))
        row.update(bin=[lo, hi], mean_stated=float(np.mean([r['probability'] for r in inside]))
                   if inside else None, named_right=sum(named_right(r) for r in inside))
        table.append(row)
    high = [r for r in judged if r['probability'] >= HIGH]
    wrong_high = sum(not r['right'] for r in high)
    strict_high = sum(named_right(r) for r in high)
    nulls = [r for r in done if r['draw']['kind'] == 'null']
    alarms = [r for r in nulls if r['verdict'] not in ('none', 'unexplained')]
    alarms_high = [r for r in alarms if r['probability'] >= HIGH]
    classes = {}
    for r in done:
        keys = [r['draw']['kind']] + [f'{r["draw"]["kind"]}: {c["effect"]}'
                                      for c in r['draw']['concealed']]
        for key in keys:
            classes.setdefault(key, []).append(r)
    rotor = {}
    for r in done:
        d = r['draw']
        for key in (f'N = {d["n_blades"]}', 'hover' if d['mu'] == 0 else 'forward flight',
                    'wake' if d['wake'] else 'no wake'):
            rotor.setdefault(key, []).append(r)

    def breakdown(groups):
        out = {}
        for key in sorted(groups):
            rs = groups[key]
            hi = [r for r in rs if r['verdict'] != 'unexplained' and r['probability'] >= HIGH]
            out[key] = {**_rate(sum(r['right'] for r in rs), len(rs)),
                        'high': len(hi), 'high_right': sum(r['right'] for r in hi),
                        'unexplained': sum(r['verdict'] == 'unexplained' for r in rs),
                        'excess_mean': _mean([r.get('excess') for r in rs]),
                        'verdicts': _counts(r['named_text'] for r in rs if not r['right'])}
        return out

    cpu = [r['cpu_s'] for r in done if 'cpu_s' in r]
    sources = _counts(r['probability_source'] for r in done)
    return {
        'records': len(runs), 'diagnosed': len(done), 'errors': len(runs) - len(done),
        'probability_source': sources,
        'overall': _rate(sum(r['right'] for r in done), len(done)),
        'overall_named_right': _rate(sum(named_right(r) for r in done), len(done)),
        'unexplained': len(done) - len(judged),
        'reliability': table,
        'high_confidence': {**_rate(len(high) - wrong_high, len(high)),
                            'confidently_wrong': wrong_high, 'named_right': strict_high,
                            'allowed_at_target_99': binomial_bound(len(high),
                                                                   1 - TARGET_ACCURACY_HIGH),
                            'p_value_at_target': upper_tail(wrong_high, len(high),
                                                            1 - TARGET_ACCURACY_HIGH)},
        'nulls': {'n': len(nulls), 'false_alarms': len(alarms),
                  'false_alarms_high': len(alarms_high),
                  'wilson95': list(wilson(len(alarms), len(nulls))),
                  'allowed_at_target_99': binomial_bound(len(nulls), TARGET_FALSE_ALARMS),
                  'p_value_at_target': upper_tail(len(alarms), len(nulls),
                                                  TARGET_FALSE_ALARMS)},
        'per_class': breakdown(classes),
        'per_rotor': breakdown(rotor),
        'excess_target_vs_achieved': _excess_pairs(done),
        'cpu_s': {'total': float(np.sum(cpu)) if cpu else 0.0,
                  'median': _median(cpu), 'max': float(np.max(cpu)) if cpu else None,
                  'generate_total': float(np.sum([r.get('generate_cpu_s', 0.0)
                                                  for r in runs]))},
    }


def _mean(values):
    values = [v for v in values if v is not None]
    return float(np.mean(values)) if values else None


def _median(values):
    return float(np.median(values)) if len(values) else None


def _counts(items):
    out = {}
    for item in items:
        out[item] = out.get(item, 0) + 1
    return dict(sorted(out.items(), key=lambda kv: -kv[1]))


def _excess_pairs(done):
    """(sum of the concealed effects' target excesses, achieved baseline excess) per record."""
    return [[sum(c['target_excess'] for c in r['draw']['concealed']), r.get('excess')]
            for r in done]


def _pct(x):
    return '–' if x is None else f'{100 * x:.0f} %'


def _interval(row):
    lo, hi = row['wilson95']
    return f'{100 * lo:.0f}–{100 * hi:.0f} %'


def markdown(summary, command, load_at_start):
    """Return the results file."""
    s = summary
    src = ', '.join(f'{k} ×{v}' for k, v in s['probability_source'].items()) or '–'
    lines = [
        '# Calibration of the diagnosis (bench/calibration_study.py)', '',
        f'{s["diagnosed"]} random records diagnosed ({s["errors"]} failed); truth from '
        'test/diagnosis/random_scenarios.py (rotor N = 3-5, μ = 0 or 0.05-0.4, wake or not, '
        'noise 0.03-0.15°, 20 % nulls, else one effect or a pair, each sized for a baseline '
        'excess of 2-10 %), records by the independent truth generator. Right = the named '
        'effects are the concealed ones up to first-order equivalents (a null: `none`); '
        '`unexplained` is not right and is left out of the reliability table (it states no '
        f'probability of a catalogue explanation). Stated probability from: {src}.', '',
        '## Reliability', '',
        '| stated probability | records | mean stated | right | observed accuracy | '
        'Wilson 95 % | named right (no credit for a confound) |', '|---|---|---|---|---|---|---|']
    for row in s['reliability']:
        lo, hi = row['bin']
        close = ']' if hi == 1.0 else ')'
        lines.append(f'| [{lo:.2f}, {hi:.2f}{close} | {row["n"]} | '
                     f'{_fmt(row["mean_stated"])} | {row["right"]} | '
                     f'{_pct(row["accuracy"])} | {_interval(row)} | {row["named_right"]} |')
    h, n = s['high_confidence'], s['nulls']
    lines += [
        '', '## Targets', '',
        f'- Accuracy at high confidence (stated ≥ {HIGH}): {h["right"]}/{h["n"]} = '
        f'{_pct(h["accuracy"])} (Wilson 95 % {_interval(h)}; named right without credit '
        f'for a confound: {h["named_right"]}/{h["n"]}); target ≥ '
        f'{_pct(TARGET_ACCURACY_HIGH)}. Confidently wrong: {h["confidently_wrong"]}; a true '
        f'rate of 5 % allows at most {h["allowed_at_target_99"]} (binomial 99 % quantile); '
        f'P(≥ {h["confidently_wrong"]} | 5 %) = {h["p_value_at_target"]:.2g}.',
        f'- False alarms on nulls (a catalogue effect named on an effect-free record): '
        f'{n["false_alarms"]}/{n["n"]} ({n["false_alarms_high"]} at high confidence), '
        f'Wilson 95 % {100 * n["wilson95"][0]:.0f}–{100 * n["wilson95"][1]:.0f} %; target '
        f'≤ {_pct(TARGET_FALSE_ALARMS)}: a true 2 % allows at most '
        f'{n["allowed_at_target_99"]} (binomial 99 %); P(≥ {n["false_alarms"]} | 2 %) = '
        f'{n["p_value_at_target"]:.2g}.',
        f'- Overall right: {s["overall"]["right"]}/{s["overall"]["n"]} = '
        f'{_pct(s["overall"]["accuracy"])}; named right without credit for "confounded '
        f'with": {s["overall_named_right"]["right"]}/{s["overall_named_right"]["n"]}; '
        f'`unexplained`: {s["unexplained"]}.', '']
    for title, key in (('Per truth class', 'per_class'), ('Per rotor', 'per_rotor')):
        lines += [f'## {title}', '',
                  '| class | records | right | accuracy (Wilson 95 %) | high conf. right | '
                  'unexplained | excess mean | verdicts when not right |',
                  '|---|---|---|---|---|---|---|---|']
        for name, row in s[key].items():
            wrong = ', '.join(f'{k} ×{v}' for k, v in row['verdicts'].items()) or '–'
            lines.append(f'| {name} | {row["n"]} | {row["right"]} | {_pct(row["accuracy"])} '
                         f'({_interval(row)}) | {row["high_right"]}/{row["high"]} | '
                         f'{row["unexplained"]} | {_fmt(row["excess_mean"])} | {wrong} |')
        lines.append('')
    cpu = s['cpu_s']
    machine = machine_description()
    lines += [
        f'CPU per diagnosis (workers=1): median {_fmt(cpu["median"], ".1f")} s, max '
        f'{_fmt(cpu["max"], ".1f")} s, total {cpu["total"]:.0f} s; generating the records '
        f'(with the size checks) {cpu["generate_total"]:.0f} s.', '',
        f'Reproduce: `{command}` ('
        f'{machine["cpu"]}, {machine["logical cores"]} cores, {machine["date (UTC)"]} UTC; '
        'load average '
        f'{" / ".join(f"{x:.2f}" for x in load_at_start)} at the start, '
        f'{" / ".join(f"{x:.2f}" for x in os.getloadavg())} at the last write).', '']
    return '\n'.join(lines)


def _fmt(x, spec='.3f'):
    return '–' if x is None else format(x, spec)


def figure(summary, path):
    """Write the reliability diagram: observed accuracy against stated probability."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    rows = [r for r in summary['reliability'] if r['n']]
    fig, (ax, bx) = plt.subplots(2, 1, figsize=(5.5, 6.5), sharex=True,
                                 gridspec_kw={'height_ratios': [3, 1]})
    ax.plot([0, 1], [0, 1], color='0.6', lw=1, label='calibrated')
    for lo, _ in [r['bin'] for r in summary['reliability']][1:]:
        ax.axvline(lo, color='0.9', lw=0.8)
    x = [r['mean_stated'] for r in rows]
    y = [r['accuracy'] for r in rows]
    # (clipped: at an accuracy of 0 or 1 the interval's end is that value up to rounding)
    err = [[max(a - r['wilson95'][0], 0.0) for a, r in zip(y, rows)],
           [max(r['wilson95'][1] - a, 0.0) for a, r in zip(y, rows)]]
    ax.errorbar(x, y, yerr=err, fmt='o', capsize=4, label='observed (Wilson 95 %)')
    for xi, yi, r in zip(x, y, rows):
        ax.annotate(f'{r["right"]}/{r["n"]}', (xi, yi), textcoords='offset points',
                    xytext=(6, -12), fontsize=8)
    ax.axhline(TARGET_ACCURACY_HIGH, color='C3', lw=0.8, ls='--', label='target at high conf.')
    ax.set_ylabel('observed accuracy')
    ax.set_ylim(0, 1.02)
    ax.set_title(f'Diagnosis reliability, {summary["diagnosed"]} random records')
    ax.legend(loc='upper left', fontsize=8)
    bx.bar([(r['bin'][0] + r['bin'][1]) / 2 for r in summary['reliability']],
           [r['n'] for r in summary['reliability']],
           width=[(r['bin'][1] - r['bin'][0]) * 0.9 for r in summary['reliability']],
           color='C0', alpha=0.6)
    bx.set_xlabel('stated probability of the verdict')
    bx.set_ylabel('records')
    bx.set_xlim(0, 1.02)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_results(runs, out, command, load_at_start):
    """Write <out>.md (keeping its notes below NOTES_MARK), .json, .png from the lines."""
    summary = summarize(runs)
    out = Path(out)
    out.with_suffix('.json').write_text(json.dumps(summary, indent=1, default=float) + '\n')
    md = out.with_suffix('.md')
    notes = notes_of(md) or NOTES_MARK + '\n'
    md.write_text(markdown(summary, command, load_at_start) + '\n' + notes)
    if summary['diagnosed']:
        figure(summary, out.with_suffix('.png'))
    return summary


def main(argv=None):
    """Run (or resume) the study and write the results."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument('--records', type=int, default=300, help='K: seeds first-seed..+K-1')
    parser.add_argument('--first-seed', type=int, default=1)
    parser.add_argument('--workers', type=int, default=1, help='records diagnosed at once')
    parser.add_argument('--kind', choices=('null', 'single', 'pair'),
                        help='conceal only this (a stratum: e.g. many cheap nulls for the '
                             'false-alarm rate); the rotor and noise are drawn as without it')
    parser.add_argument('--out', default=str(RESULTS_DIR / 'calibration'))
    parser.add_argument('--evidence-tempering', type=float, default=None,
                        help='η of the stated probabilities (default: the policy value)')
    parser.add_argument('--summary-only', action='store_true',
                        help='rewrite .md/.json/.png from the .jsonl, diagnose nothing')
    parser.add_argument('--truth-cache', default=str(Path(tempfile.gettempdir())
                                                     / 'rotor_id_truth_cache'),
                        help='directory of generated truth records ("" : none)')
    args = parser.parse_args(argv)
    if args.truth_cache:
        os.environ[truth_generator.CACHE_ENV] = args.truth_cache
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    lines_path = out.with_suffix('.jsonl')
    runs = read_runs(lines_path)
    command = ' '.join(['python', 'bench/calibration_study.py'] + list(
        sys.argv[1:] if argv is None else argv))
    load = os.getloadavg()
    if args.summary_only:
        seeds = sorted(r['seed'] for r in runs) or [args.first_seed]
        command = (f'python bench/calibration_study.py --records {seeds[-1] - seeds[0] + 1} '
                   f'--first-seed {seeds[0]} --out {args.out}'
                   + (f' --kind {args.kind}' if args.kind else ''))
        write_results(runs, out, command, load)
        print(out.with_suffix('.md').read_text())
        return 0 if targets_hold(summarize(runs)) else 1
    have = {r['seed'] for r in runs}
    seeds = [s for s in range(args.first_seed, args.first_seed + args.records) if s not in have]
    print(f'{len(have)} records in {lines_path}, {len(seeds)} to diagnose', flush=True)
    t0 = time.perf_counter()
    tasks = [(s, args.kind, 1, args.evidence_tempering) for s in seeds]
    pool = multiprocessing.get_context('fork').Pool(args.workers) if args.workers > 1 else None
    results = pool.imap_unordered(_job, tasks) if pool else map(_job, tasks)
    try:
        for i, line in enumerate(results, 1):
            runs.append(line)
            with lines_path.open('a') as f:
                f.write(json.dumps(line, default=float) + '\n')
            verdict = line.get('error') or (
                f'{line["named_text"]} p={line["probability"]:.2f} '
                f'{"right" if line["right"] else "NOT RIGHT"}')
            truth = line.get('draw', {}).get('truth', '?')
            print(f'[{i}/{len(seeds)}] seed {line["seed"]} truth {truth}: {verdict}, '
                  f'excess {_fmt(line.get("excess"))}, cpu {line.get("cpu_s", 0):.0f} s '
                  f'(elapsed {time.perf_counter() - t0:.0f} s)', flush=True)
            write_results(runs, out, command, load)
    finally:
        if pool:
            pool.terminate()
    print(out.with_suffix('.md').read_text())
    return 0 if targets_hold(summarize(runs)) else 1


def targets_hold(summary):
    """
    Return False when the records reject a target at the 1 % level.

    More confidently wrong verdicts than the binomial 99 % quantile at a 5 % error rate, or
    more false alarms on the nulls than that quantile at 2 %.
    """
    h, n = summary['high_confidence'], summary['nulls']
    return (h['confidently_wrong'] <= h['allowed_at_target_99']
            and n['false_alarms'] <= n['allowed_at_target_99'])


if __name__ == '__main__':
    sys.exit(main())
