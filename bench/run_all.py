"""
Regenerate every results file and figure in bench/results (``make bench``).

Every ``bench/results/<name>.md`` says how it was made on its ``Reproduce:`` line; this script
runs exactly that command for each (so a results file and its regeneration cannot drift
apart), with the few corrections in :data:`KNOWN` (a command whose line leaves out an output
path, and which runs are long). Each benchmark runs in its own process (timings and peak
memory do not leak between them) and writes its results file with the machine, load and
date. A line per benchmark shows progress; the summary gives each one's verdict and time.

    python bench/run_all.py                    # everything (the long studies take hours)
    python bench/run_all.py --skip-long        # the short benchmarks only (~10-20 min)
    python bench/run_all.py --only diagnose_speed command_speed
    python bench/run_all.py --list             # what would run, and how
    python bench/run_all.py --quick            # smoke run: small sizes, nothing written
    nice -n 19 python bench/run_all.py --only adequacy --workers 1   # on a shared machine

Exit status 1 if a benchmark missed its target or failed.
"""

import argparse
from dataclasses import dataclass
import os
from pathlib import Path
import re
import resource
import shlex
import subprocess
import sys
import tempfile
import time

BENCH_DIR = Path(__file__).resolve().parent
REPO_ROOT = BENCH_DIR.parent
RESULTS_DIR = BENCH_DIR / 'results'


@dataclass
class Benchmark:
    """One results file and the command that regenerates it."""

    name: str
    args: list            # arguments after ``python``: bench/<script>.py ...
    what: str = ''
    long: bool = True     # hours or the live nodes: skipped by --skip-long
    quick: list = None    # smoke-run arguments (``{tmp}`` is a scratch directory), None: skip
    target: bool = True   # exit 1 means a missed target (else the script has no target)
    source: str = 'results file'
    workers: bool = False  # takes ``--workers N`` and its figures do not depend on N

    def command(self, quick=False, tmp='', workers=None):
        """Return the command line of a full (or smoke) run (``workers``: override N)."""
        args = [a.replace('{tmp}', tmp) for a in (self.quick if quick else self.args)]
        if workers is not None and self.workers:
            if '--workers' in args:
                at = args.index('--workers') + 1
                args = args[:at] + [str(workers)] + args[at + 1:]
            else:
                args = args + ['--workers', str(workers)]
        return [sys.executable] + args


#: What the results files' own Reproduce lines do not say. ``args`` overrides the line (None:
#: use it); ``long`` marks runs of more than a few minutes on two idle cores.
KNOWN = {
    'ml_vs_peers': {
        'long': False,
        'what': 'wake fit vs least_squares peers (≤ 1 ms, ≥ 500×, ≥ 3×)',
        'quick': ['bench/ml_vs_peers.py', '--repeat', '1', '--no-write']},
    'iteration_cost': {
        'long': False, 'what': 'GN iteration / (p+1) simulations',
        'quick': ['bench/iteration_cost.py', '--repeat', '2', '--no-write']},
    'scaling': {
        'long': False, 'target': False,
        'what': 'record length and parameter count (no numeric target)',
        'quick': ['bench/scaling.py', '--repeat', '1', '--no-write']},
    'offline_throughput': {
        'long': False,
        'what': '10-minute 1 kHz bag (≥ 200× real time; the bag made in a fresh tmp dir)',
        'quick': ['bench/offline_throughput.py', '--repeat', '1', '--no-write',
                  '--workdir', '{tmp}/offline']},
    'command_speed': {
        'long': False,
        'what': 'whole identify commands (127-sample OE ≤ 0.5 s; 1065-sample FE ≤ 2 s)',
        'quick': ['bench/command_speed.py', '--repeat', '1', '--no-write']},
    'frequency_response_speed': {
        'long': False,
        'what': 'rotor-id frequency-response per 1-second 4-blade record (target ≤ 1 s)',
        'quick': ['bench/frequency_response_speed.py', '--repeat', '1', '--no-write']},
    'startup': {
        'long': False,
        'what': 'imports of rotor-id identify against python -c pass (≤ 0.25 s)',
        'quick': ['bench/startup.py', '--repeat', '1', '--no-write']},
    'diagnose_speed': {
        'long': False,
        'what': 'rotor-id diagnose per 1-second 4-blade recording (≤ 3 s)',
        'quick': ['bench/diagnose_speed.py', '--repeat', '1', '--no-write']},
    'monte_carlo_speed': {
        'long': False, 'what': '1000-seed wake Monte Carlo on 2 cores (≤ 5 s)',
        'quick': ['bench/monte_carlo_speed.py', '--seeds', '100', '--efficiency-seeds', '50',
                  '--no-write']},
    'blas_threads': {
        'long': False, 'target': False, 'what': 'one BLAS thread against one per core',
        'quick': ['bench/blas_threads.py', '--repeat', '1', '--no-write']},
    'campaign': {
        'target': False, 'what': '120-bag campaign, 1 and 2 jobs (no numeric target)',
        'quick': ['bench/campaign.py', '--bags', '12', '--repeat', '1', '--diagnose-bags', '2',
                  '--no-write']},
    'plan_vs_monte_carlo': {
        'long': False,              # 19 s at load 10 (make bench, 2026-11-24)
        'what': 'planned bounds vs Monte Carlo scatter (within 15 %)',
        'quick': ['bench/plan_vs_monte_carlo.py', '--seeds', '20', '--json', '{tmp}/pvm.json',
                  '--figure', '{tmp}/pvm.png', '--markdown', '{tmp}/pvm.md']},
    'monte_carlo': {'workers': True,
                    'what': "ML scatter vs Cramér-Rao bound, the report's cases (limits)"},
    'process_noise': {
        'target': False, 'workers': True,
        'what': 'OE / FE / EKF under system noise, σ_m .05 (coverage, RMS)',
        'args': ['bench/compare_process_noise.py', '--seeds', '100', '--workers', '2',
                 '--sigma-m', '0.05', '--out', str(RESULTS_DIR / 'process_noise.md')],
        'quick': ['bench/compare_process_noise.py', '--seeds', '4', '--workers', '1',
                  '--out', '{tmp}/pn.md']},
    'process_noise_sigma_m_0.1': {
        'target': False, 'workers': True, 'what': 'the same at σ_m .1',
        'args': ['bench/compare_process_noise.py', '--seeds', '100', '--workers', '2',
                 '--sigma-m', '0.1', '--out', str(RESULTS_DIR / 'process_noise_sigma_m_0.1.md')]},
    'diagnosis': {'target': False, 'workers': True,
                  'what': 'diagnosis study: verdicts over the scenario catalogue'},
    'diagnosis_azimuth': {'target': False, 'workers': True, 'what': 'diagnosis: azimuth offset'},
    'diagnosis_pairs': {'target': False, 'workers': True, 'what': 'diagnosis: pairs of effects'},
    'diagnosis_rig': {'target': False, 'workers': True, 'what': 'diagnosis: rig scenarios'},
    'calibration': {'workers': True,
                    'what': 'diagnosis calibration: stated probability vs accuracy on random '
                            'concealed effects (target ≥ 95 % at high confidence)',
                    'quick': ['bench/calibration_study.py', '--records', '2', '--out',
                              '{tmp}/calibration']},
    'adequacy': {'target': False, 'workers': True,
                 'what': 'adequacy check: false alarms and detection'},
    'long_bag_memory': {'what': 'one-hour 1 kHz bag: peak memory follows the window'},
    'live': {'what': '10 minutes of the live nodes: nothing lost, latency'},
    'live_60s': {'what': '60 s of the live nodes: latency'},
    'live_latency': {'what': 'live test points: latency of the final estimate'},
    'final_fit_cpu': {'target': False, 'what': 'live final fit CPU, kept vs rebuilt model, '
                      'on the newest recorded run of live_latency (run that first)'},
    'sensor_intake': {'what': 'live sensor topics: CPU per message, callbacks vs polled batches'},
    'state_estimator_cpu': {
        'long': False, 'target': False,     # 35 s at load 5
        'what': 'state estimator node: CPU per second of 1 kHz stream, numpy vs compiled filter',
        'quick': ['bench/state_estimator_cpu.py', '--seconds', '1', '--repeats', '1',
                  '--no-write']},
    'value_checks': {'long': False,  # 3 s
                     'what': 'live window value checks (spikes, dead flap) CPU vs the final fit'},
    'messy_sweep': {'long': False, 'target': False,  # 59 s, 9 s CPU at load 10
                    'what': 'identify on one injected recording fault at a time (8 seeds)'},
    'gap_cost': {'long': False, 'target': False,  # 20 s
                 'what': 'fit CPU with lost samples (a gap) over the same fit on the whole '
                         'record',
                 'quick': ['bench/gap_cost.py', '--repeat', '1', '--no-write']},
}

#: Hand-written notes on a results file's figures go after this line; a re-run keeps them.
NOTES_MARK = '<!-- notes below: kept by make bench when it rewrites the file above -->'

_REPRODUCE = re.compile(r'Reproduce:\s*`([^`]*)`', re.S)
#: Older results files name the command without ``Reproduce:``: the first one quoted.
_QUOTED = re.compile(r'`((?:nice -n \d+ )?python bench/[^`]*)`', re.S)


def reproduce_line(path):
    """Return the arguments after ``python`` of a results file's Reproduce line, or None."""
    text = Path(path).read_text()
    match = _REPRODUCE.search(text) or _QUOTED.search(text)
    if not match:
        return None
    words = shlex.split(' '.join(match.group(1).split()))
    while words and words[0] == 'nice':                  # nice -n 10 python ...
        words = words[3:] if len(words) > 2 and words[1] == '-n' else words[1:]
    if len(words) < 2 or not words[0].startswith('python') or \
            not words[1].startswith('bench/'):
        return None
    return words[1:]


def notes_of(path):
    """Return the hand-written notes of a results file (from :data:`NOTES_MARK` on), or ''."""
    text = Path(path).read_text() if Path(path).is_file() else ''
    return text[text.index(NOTES_MARK):] if NOTES_MARK in text else ''


def keep_notes(path, notes):
    """Append ``notes`` to a rewritten results file that lost them; True if it did."""
    path = Path(path)
    if not notes or not path.is_file() or NOTES_MARK in path.read_text():
        return False
    path.write_text(path.read_text().rstrip('\n') + '\n\n' + notes)
    return True


def children_cpu_s():
    """CPU seconds (user + system) of the finished child processes, theirs included."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def registry():
    """Return (benchmarks by name, results files that say no runnable command)."""
    out, orphans = {}, []
    for path in sorted(RESULTS_DIR.glob('*.md')):
        name = path.stem
        known = dict(KNOWN.get(name, {}))
        args = known.pop('args', None)
        source = 'run_all.KNOWN' if args else 'results file'
        args = args or reproduce_line(path)
        if args is None:
            orphans.append(path.name)
            continue
        out[name] = Benchmark(name, args, source=source, **known)
    # short ones first, each group in name order
    return dict(sorted(out.items(), key=lambda kv: (kv[1].long, kv[0]))), orphans


def main(argv=None):
    """Run the selected benchmarks in turn and summarise."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    parser.add_argument('--only', nargs='+', metavar='NAME', default=None,
                        help='results names to regenerate (see --list)')
    parser.add_argument('--skip-long', action='store_true',
                        help='leave out the long studies and the live-node runs')
    parser.add_argument('--quick', action='store_true',
                        help='smoke run with small sizes; nothing in bench/results is written')
    parser.add_argument('--list', action='store_true', help='show what would run and exit')
    parser.add_argument('--workers', type=int, default=None, metavar='N',
                        help='worker processes of the statistical studies whose figures do not '
                             "depend on it (a shared machine: 1); default: each one's own")
    args = parser.parse_args(argv)
    benchmarks, orphans = registry()
    for name in orphans:
        print(f'warning: bench/results/{name} has no "Reproduce: `python bench/...`" line; '
              'it cannot be regenerated', file=sys.stderr)
    if args.only:
        unknown = [n for n in args.only if n not in benchmarks]
        if unknown:
            print(f'run_all: unknown benchmark(s) {", ".join(unknown)}; choose from '
                  f'{", ".join(benchmarks)}', file=sys.stderr)
            return 2
        selected = [benchmarks[n] for n in args.only]
    else:
        selected = [b for b in benchmarks.values() if not (args.skip_long and b.long)]
    if args.quick:
        skipped = [b.name for b in selected if b.quick is None]
        selected = [b for b in selected if b.quick is not None]
        if skipped:
            print(f'--quick: no smoke variant of {", ".join(skipped)} (left out)')
    if args.list:
        for b in selected:
            print(f'{b.name:28s} {"long " if b.long else "short"} '
                  f'{" ".join(b.command(args.quick, "TMP", args.workers)[1:])}   [{b.source}]')
        return 1 if orphans else 0
    summary = []
    started_all = time.perf_counter()
    if not args.quick:
        from common import warm_kernel_cache
        warm_kernel_cache()           # a stale cache would put a compile into a timing
    env = dict(os.environ, PYTHONUNBUFFERED='1')
    with tempfile.TemporaryDirectory(prefix='rotor_id_bench_') as tmp:
        for i, bench in enumerate(selected, 1):
            command = bench.command(args.quick, tmp, args.workers)
            print(f'\n=== [{i}/{len(selected)}] {bench.name} ({"long" if bench.long else "short"}'
                  f', {time.perf_counter() - started_all:.0f} s into the run): {bench.what}\n'
                  f'    {" ".join(command[1:])}', flush=True)
            results = RESULTS_DIR / f'{bench.name}.md'
            notes = '' if args.quick else notes_of(results)
            load_before = os.getloadavg()[0]
            started, cpu_before = time.perf_counter(), children_cpu_s()
            code = subprocess.run(command, cwd=REPO_ROOT, env=env).returncode
            elapsed, cpu = time.perf_counter() - started, children_cpu_s() - cpu_before
            load = f'{load_before:.1f}-{os.getloadavg()[0]:.1f}'
            verdict = {0: 'target met' if bench.target else 'done',
                       1: 'TARGET MISSED'}.get(code, f'FAILED (exit {code})')
            if code == 1 and not bench.target:
                verdict = 'FAILED (exit 1)'
            print(f'=== {bench.name}: {verdict} in {elapsed:.0f} s wall, {cpu:.0f} s CPU '
                  f'(load {load})', flush=True)
            if keep_notes(results, notes):
                print(f'=== {results.name}: hand-written notes kept below the new figures; '
                      'check the figures they quote', flush=True)
            summary.append((bench.name, verdict, elapsed, cpu, load, bench.what))
    print(f'\n=== summary ({time.perf_counter() - started_all:.0f} s; CPU of each benchmark '
          'with its child processes; 1-minute load average before-after)')
    for name, verdict, elapsed, cpu, load, what in summary:
        print(f'  {name:28s} {verdict:16s} {elapsed:6.0f} s {cpu:6.0f} s CPU  load {load:9s}  '
              f'{what}')
    if not args.quick:
        print(f'results: {RESULTS_DIR}/*.md')
    good = ('target met', 'done')
    return 0 if all(row[1] in good for row in summary) and not orphans else 1


if __name__ == '__main__':
    sys.exit(main())
