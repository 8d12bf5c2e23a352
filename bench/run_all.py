"""
Run every benchmark that writes bench/results (issues 6 and 15) and summarise the targets.

``make bench`` calls this. Each benchmark runs in its own process (so timings and peak memory
do not leak between them), prints its tables and writes ``bench/results/<name>.md`` with the
machine description and the date. Item 4 (live latency) is bench/live_latency.py, run
separately with the nodes.

Run: ``python bench/run_all.py [--quick] [--only NAME ...]``; ``--quick`` uses fewer repeats
and seeds (a smoke run; its numbers are not the committed results).
"""

import argparse
from pathlib import Path
import subprocess
import sys
import time

BENCH_DIR = Path(__file__).resolve().parent

#: name -> (script, full arguments, quick arguments, what it measures)
BENCHMARKS = {
    'ml_vs_peers': ('ml_vs_peers.py', ['--repeat', '9'], ['--repeat', '1', '--no-write'],
                    'ML vs least_squares peers (wake fit ≤ 1 ms, ≥ 500× (a), ≥ 3× (b))'),
    'iteration_cost': ('iteration_cost.py', ['--repeat', '15'], ['--repeat', '2', '--no-write'],
                       'GN iteration / (p+1) simulations (target ≤ 1.5)'),
    'scaling': ('scaling.py', ['--repeat', '7'], ['--repeat', '1', '--no-write'],
                'record length and parameter count (no numeric target)'),
    'offline_throughput': ('offline_throughput.py', ['--repeat', '3'],
                           ['--repeat', '1', '--no-write'],
                           '10-minute 1 kHz bag (target ≥ 200× real time)'),
    'command_speed': ('command_speed.py', ['--repeat', '3'], ['--repeat', '1', '--no-write'],
                      'whole identify commands (127-sample OE ≤ 0.5 s, 1065-sample FE ≤ 2 s)'),
    'process_noise': ('compare_process_noise.py', ['--seeds', '100'],
                      ['--seeds', '4', '--workers', '1', '--out', '/tmp/rotor_id_pn_quick.md'],
                      'OE / FE / EKF under system noise, σ_m .05 (coverage and RMS figures)'),
    'process_noise_sigma_m_0.1': (
        'compare_process_noise.py',
        ['--seeds', '100', '--sigma-m', '0.1', '--out',
         str(BENCH_DIR / 'results' / 'process_noise_sigma_m_0.1.md')],
        ['--seeds', '4', '--workers', '1', '--sigma-m', '0.1', '--out',
         '/tmp/rotor_id_pn01_quick.md'],
        'the same at σ_m .1'),
    'plan_vs_monte_carlo': ('plan_vs_monte_carlo.py', ['--seeds', '200'],
                            ['--seeds', '20', '--json', '/tmp/rotor_id_pvm.json', '--figure',
                             '/tmp/rotor_id_pvm.png', '--markdown', '/tmp/rotor_id_pvm.md'],
                            'planned bounds vs Monte Carlo scatter (within 15 %)'),
    'diagnose_speed': ('diagnose_speed.py', ['--repeat', '3'], ['--repeat', '1', '--no-write'],
                       'rotor-id diagnose per 1-second 4-blade recording (target ≤ 3 s)'),
    'campaign': ('campaign.py', ['--bags', '120', '--repeat', '2'],
                 ['--bags', '12', '--repeat', '1', '--diagnose-bags', '2', '--no-write'],
                 '100-bag campaign (no numeric target here)'),
    'monte_carlo_speed': ('monte_carlo_speed.py', ['--seeds', '1000'],
                          ['--seeds', '100', '--efficiency-seeds', '50', '--no-write'],
                          '1000-seed wake Monte Carlo on 2 cores (target ≤ 5 s, issue 15)'),
}


#: Benchmarks that measure without a pass/fail target.
NO_TARGET = ('scaling', 'process_noise', 'process_noise_sigma_m_0.1', 'campaign')


def main(argv=None):
    """Run the benchmarks in turn; exit 1 if any missed its target or failed."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    parser.add_argument('--quick', action='store_true', help='smoke run, nothing written')
    parser.add_argument('--only', nargs='*', choices=sorted(BENCHMARKS), default=None)
    args = parser.parse_args(argv)
    names = args.only or list(BENCHMARKS)
    summary = []
    for i, name in enumerate(names, 1):
        script, full, quick, what = BENCHMARKS[name]
        print(f'\n=== [{i}/{len(names)}] {name}: {what}', flush=True)
        started = time.perf_counter()
        code = subprocess.run([sys.executable, str(BENCH_DIR / script)]
                              + (quick if args.quick else full)).returncode
        elapsed = time.perf_counter() - started
        verdict = {0: 'target met', 1: 'TARGET MISSED'}.get(code, f'FAILED (exit {code})')
        if name in NO_TARGET and code == 0:
            verdict = 'done'
        summary.append((name, what, verdict, elapsed))
    print('\n=== summary')
    for name, what, verdict, elapsed in summary:
        print(f'  {name:20s} {verdict:16s} {elapsed:6.0f} s   {what}')
    if not args.quick:
        print(f'results: {BENCH_DIR / "results"}/*.md')
    return 0 if all(v in ('target met', 'done') for _, _, v, _ in summary) else 1


if __name__ == '__main__':
    sys.exit(main())
