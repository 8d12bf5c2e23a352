"""
Wall time of a 1000-seed Monte Carlo of the dynamic-wake case on both cores.

The fitting per draw is the statistics study's own (:func:`rotor_id.report.monte_carlo.run_case`,
used by bench/monte_carlo.py): report σ, R known, output-error ML started at the reference
point. This script only measures its speed: 1000 seeds on a pool of ``--workers`` processes
(target ≤ 5 s), for the 3-parameter case and the 7-parameter case, and
the parallel efficiency from a smaller sample fitted serially and on the pool in the same run.
:func:`timed_monte_carlo` is the reusable entry point.

Run: ``python bench/monte_carlo_speed.py [--seeds 1000] [--workers 2]``.
"""

import argparse
import multiprocessing
import os
import resource
import sys
import time

from common import markdown_table, say, warm_kernel_cache, write_results
import numpy as np

from rotor_id.estimation import kernels
from rotor_id.report import monte_carlo as M

TARGET_S = 5.0             # 1000 seeds on two cores
CASES = ('wake_progressing', 'wake_7par')


def _cpu_seconds():
    """User + system CPU of this process and of its finished (waited-for) children."""
    own = resource.getrusage(resource.RUSAGE_SELF)
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def timed_monte_carlo(case_name, n_seeds, workers=2, progress=None):
    """
    Fit ``n_seeds`` noise draws of a report case on ``workers`` processes (1: in-process).

    Returns (MonteCarloResult, wall seconds, CPU seconds of this process and its workers), both
    including the pool's start-up and the reference fit.
    """
    started, cpu = time.perf_counter(), _cpu_seconds()
    kernels.prefer()                         # before the fork: the workers inherit it
    if workers <= 1:
        result = M.run_case(case_name, range(n_seeds), pool=None, progress=progress)
    else:
        with multiprocessing.get_context('fork').Pool(workers) as pool:
            result = M.run_case(case_name, range(n_seeds), pool=pool, progress=progress)
            pool.close()
            pool.join()                      # reap the workers so their CPU time counts
    return result, time.perf_counter() - started, _cpu_seconds() - cpu


def _progress(case, done, total, elapsed):
    if done % 250 == 0 or done == total:
        say(f'  {case}: {done}/{total} draws ({elapsed:.1f} s)')


def main(argv=None):
    """Run, print, write bench/results/monte_carlo_speed.md."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    parser.add_argument('--seeds', type=int, default=1000)
    parser.add_argument('--workers', type=int, default=2)
    parser.add_argument('--efficiency-seeds', type=int, default=200,
                        help='draws fitted serially and in parallel for the speed-up')
    parser.add_argument('--no-write', action='store_true')
    args = parser.parse_args(argv)
    warm_kernel_cache()
    rows = []
    worst = worst_cpu = 0.0
    for case in CASES:
        say(f'{case}: {args.seeds} seeds on {args.workers} workers')
        load = os.getloadavg()[0]
        result, wall, cpu = timed_monte_carlo(case, args.seeds, args.workers, _progress)
        if case == 'wake_progressing':
            worst, worst_cpu = wall, cpu
        n_eff = args.efficiency_seeds
        say(f'{case}: {n_eff} seeds serial vs {args.workers} workers (speed-up)')
        _, serial, _ = timed_monte_carlo(case, n_eff, 1)
        _, parallel, _ = timed_monte_carlo(case, n_eff, args.workers)
        ratio = result.std_ratio
        rows.append([case, len(result.reference.names), args.seeds, f'**{wall:.1f} s**',
                     f'{wall / args.seeds * 1e3:.1f} ms', f'{cpu:.1f} s',
                     f'{cpu / args.seeds * 1e3:.1f} ms', f'{cpu / wall:.2f}',
                     f'{np.mean(result.iterations):.1f}', f'{np.mean(result.converged):.1%}',
                     f'{serial / parallel:.2f}× ({serial:.1f} s → {parallel:.1f} s)',
                     f'{load:.1f}',
                     ', '.join(f'{r:.2f}' for r in ratio)])
        say(f'  {wall:.1f} s for {args.seeds} seeds; speed-up {serial / parallel:.2f}')
    table = markdown_table(
        ['case', 'unknowns', 'seeds', f'wall time ({args.workers} workers)', 'per seed',
         'CPU time (all processes)', 'CPU per seed', 'cores used (CPU / wall)',
         'mean iterations', 'converged', f'speed-up {args.workers} workers vs 1 '
         f'({args.efficiency_seeds} seeds)', 'load avg at start',
         'sample σ / σ_CRB (sanity)'], rows)
    verdict = (f'3-parameter wake case: {worst:.1f} s for {args.seeds} seeds '
               f'(target ≤ {TARGET_S:.0f} s: {"met" if worst <= TARGET_S else "MISSED"}). '
               f'The work itself is {worst_cpu:.1f} s of CPU, so on {args.workers} otherwise idle '
               f'cores it would take about {worst_cpu / args.workers:.1f} s (a projection from '
               'the CPU time, not a measurement).')
    body = (f'## Monte Carlo wall time\n\n{table}\n\n{verdict}\n\n'
            'Wall time includes loading the compiled simulator kernel (from the cache that '
            '`make build` fills; the script fills it first), the pool start-up, the '
            'noise-free reference fit and making '
            "each draw's data (truth simulation + noise). The statistics themselves are "
            "bench/monte_carlo.py's subject; the σ ratios are shown only as a check that "
            'the fast runs fit what they should.\n')
    print(body)
    if not args.no_write:
        write_results('monte_carlo_speed', 'Monte Carlo speed', body,
                      f'python bench/monte_carlo_speed.py --seeds {args.seeds} '
                      f'--workers {args.workers}')
    return 0 if worst <= TARGET_S else 1


if __name__ == '__main__':
    sys.exit(main())
