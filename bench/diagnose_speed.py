#!/usr/bin/env python3
"""
Time ``rotor-id diagnose`` per recording against its full-search peer (issue 15, item 1).

For every dx_* practice recording (1-second, 4-blade, 1 kHz) the diagnosis is run two ways,
interleaved in one process so that both see the same load:

* ``screened``: the default; nested candidates are score-tested at the baseline estimate and
  only those that could reach the criterion are fitted, random inflow only when needed;
* ``full``: every candidate fitted (``diagnose(..., screen=False)``), the search as it was.

Both read the same in-memory record (bag reading and start-up are the CLI's and not the
diagnosis's). Reported per recording: the median wall and CPU time of each (workers = 1, so
CPU time counts the compiled kernels' and BLAS threads too, so it can exceed the wall time),
their ratio, and whether the verdicts agree; the target is ≤ 3 s wall per recording, judged
on the median wall time (the machine is shared: compare runs at a low load average).

    python bench/diagnose_speed.py [--repeat 3] [--no-write]
"""

import argparse
import sys
import time

from common import machine_description, REPO_ROOT, RESULTS_DIR, say
import numpy as np

RECORDINGS = REPO_ROOT.parent / 'shared' / 'recordings'
NAMES = ('dx_none_wake', 'dx_sensor_lag', 'dx_dynamic_inflow', 'dx_periodic_coefficients')
TARGET_S = 3.0


def _timed(function):
    wall, cpu = time.perf_counter(), time.process_time()
    out = function()
    return out, time.perf_counter() - wall, time.process_time() - cpu


def main(argv=None):
    """Run the comparison; exit 1 when a recording misses the target or a verdict changes."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument('--repeat', type=int, default=3)
    parser.add_argument('--no-write', action='store_true')
    args = parser.parse_args(argv)
    if not RECORDINGS.is_dir():
        say(f'no practice recordings at {RECORDINGS}: nothing to time')
        return 0
    from rotor_id.diagnosis.diagnose import diagnose
    from rotor_id.io.bag import read_run
    from rotor_id.io.run_description import load_run_description
    inputs = {}
    for name in NAMES:
        description = load_run_description(RECORDINGS / f'{name}.yaml')
        inputs[name] = (description, read_run(description))
    times = {(n, m): [] for n in NAMES for m in ('screened', 'full')}
    verdicts = {(n, m): set() for n in NAMES for m in ('screened', 'full')}
    for round_ in range(args.repeat):
        for name in NAMES:
            description, record = inputs[name]
            for mode in ('screened', 'full'):
                result, wall, cpu = _timed(lambda: diagnose(
                    record, description, workers=1, screen=mode == 'screened'))
                times[name, mode].append((wall, cpu))
                verdicts[name, mode].add(result.effect)
                say(f'round {round_ + 1}: {name} {mode}: {result.effect}, {wall:.2f} s wall, '
                    f'{cpu:.2f} s CPU')
    lines = ['# diagnose: score-test screening vs. fitting every candidate',
             '', 'Machine:', '']
    lines += [f'* {k}: {v}' for k, v in machine_description().items()]
    lines += ['', f'Median of {args.repeat} interleaved rounds, one worker, record in memory '
              '(the CLI adds start-up and bag reading). Target: ≤ 3 s per recording.', '',
              '| recording | verdict (screened / full) | screened wall s | screened CPU s | '
              'full wall s | full CPU s | full/screened (wall) | target |',
              '|---|---|---|---|---|---|---|---|']
    ok = True
    for name in NAMES:
        s = np.median(np.array(times[name, 'screened']), axis=0)
        f = np.median(np.array(times[name, 'full']), axis=0)
        vs, vf = verdicts[name, 'screened'], verdicts[name, 'full']
        same = vs == vf and len(vs) == 1
        met = s[0] <= TARGET_S
        ok &= same and met
        lines.append(f'| {name} | {"/".join(sorted(vs))} / {"/".join(sorted(vf))}'
                     f'{"" if same else " (DIFFER)"} | {s[0]:.2f} | {s[1]:.2f} | {f[0]:.2f} | '
                     f'{f[1]:.2f} | {f[0] / s[0]:.1f}× | {"met" if met else "MISSED"} |')
    lines += ['', 'Reproduce: `python bench/diagnose_speed.py --repeat 3`.']
    text = '\n'.join(lines) + '\n'
    print(text)
    if not args.no_write:
        RESULTS_DIR.mkdir(exist_ok=True)
        (RESULTS_DIR / 'diagnose_speed.md').write_text(text)
    return 0 if ok else 1


if __name__ == '__main__':
    sys.exit(main())
