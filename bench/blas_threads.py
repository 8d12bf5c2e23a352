#!/usr/bin/env python3
"""
One BLAS thread against OpenBLAS's default (one per core): why rotor_id sets one.

``import rotor_id`` sets OPENBLAS_NUM_THREADS=1 unless the user set it. This benchmark shows
what that buys on this machine. Each setting runs in its own child process (OpenBLAS reads the
variable when numpy loads it), interleaved round by round so both see the same load, and times

* ``lstsq``: the initial-state least squares of the wake candidate of dx_dynamic_inflow, a
  4260 x 10 problem (``output_error.fit_initial_states``; a random matrix of that shape);
* ``diagnose``: ``diagnose()`` of the dx_dynamic_inflow practice recording, one worker, record
  in memory (skipped without /work/shared recordings).

Reported: median wall and CPU time (all threads of the child) per setting, and their ratio.

    python bench/blas_threads.py [--repeat 3] [--no-write]
"""

import argparse
import json
import os
import subprocess
import sys
import time

from common import markdown_table, REPO_ROOT, say, write_results
import numpy as np

RECORDING = REPO_ROOT.parent / 'shared' / 'recordings' / 'dx_dynamic_inflow'
SETTINGS = {'one thread (rotor_id default)': '1', 'OpenBLAS default (one per core)': None}


def _child(repeat_lstsq):
    """Time the workloads in this process; print one JSON line."""
    out = {}
    rng = np.random.default_rng(0)
    a, b = rng.standard_normal((4260, 10)), rng.standard_normal(4260)
    np.linalg.lstsq(a, b, rcond=None)
    wall, cpu = time.perf_counter(), time.process_time()
    for _ in range(repeat_lstsq):
        np.linalg.lstsq(a, b, rcond=None)
    out['lstsq'] = ((time.perf_counter() - wall) / repeat_lstsq,
                    (time.process_time() - cpu) / repeat_lstsq)
    if RECORDING.is_dir():
        from rotor_id.diagnosis.diagnose import diagnose
        from rotor_id.io.bag import read_run
        from rotor_id.io.run_description import load_run_description
        description = load_run_description(RECORDING.with_suffix('.yaml'))
        record = read_run(description)
        wall, cpu = time.perf_counter(), time.process_time()
        result = diagnose(record, description, workers=1)
        out['diagnose'] = (time.perf_counter() - wall, time.process_time() - cpu)
        out['verdict'] = result.effect
    print(json.dumps(out))
    return 0


def main(argv=None):
    """Run both settings interleaved in child processes and tabulate the medians."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument('--repeat', type=int, default=3)
    parser.add_argument('--no-write', action='store_true')
    parser.add_argument('--child', action='store_true', help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        return _child(50)
    runs = {name: [] for name in SETTINGS}
    for round_ in range(args.repeat):
        for name, threads in SETTINGS.items():
            env = dict(os.environ)
            env.pop('OPENBLAS_NUM_THREADS', None)
            if threads is not None:
                env['OPENBLAS_NUM_THREADS'] = threads
            else:
                env['OPENBLAS_NUM_THREADS'] = str(os.cpu_count())
            done = subprocess.run([sys.executable, __file__, '--child'], env=env,
                                  capture_output=True, text=True, check=True)
            runs[name].append(json.loads(done.stdout.strip().splitlines()[-1]))
            say(f'round {round_ + 1}/{args.repeat}: {name}: {runs[name][-1]}')
    rows = []
    base = {}
    for name, results in runs.items():
        for work in ('lstsq', 'diagnose'):
            if work not in results[0]:
                continue
            wall, cpu = np.median(np.array([r[work] for r in results]), axis=0)
            base.setdefault(work, wall)
            unit, scale = ('ms', 1e3) if work == 'lstsq' else ('s', 1.0)
            verdicts = ', '.join(sorted({r.get('verdict', '') for r in results})) \
                if work == 'diagnose' else ''
            rows.append([work, name, f'{wall * scale:.2f} {unit}', f'{cpu * scale:.2f} {unit}',
                         f'{wall / base[work]:.1f}×', verdicts])
    body = ('Median of {} interleaved rounds, each setting in its own child process.\n\n'
            .format(args.repeat)
            + markdown_table(['work', 'BLAS threads', 'wall', 'CPU (all threads)',
                              'wall / one thread', 'verdict'], rows) + '\n')
    print(body)
    if not args.no_write:
        write_results('blas_threads', 'One BLAS thread against one per core', body,
                      'python bench/blas_threads.py --repeat 3')
    return 0


if __name__ == '__main__':
    sys.exit(main())
