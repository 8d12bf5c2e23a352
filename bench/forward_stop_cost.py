#!/usr/bin/env python3
"""
What the forward selection's last step costs: the selection as it is against an omnibus stop.

The omnibus stop ends the selection as soon as the residuals look like noise (white, at the
floor, no mean); the selection instead always runs the next step (score tests, and fits of what
passes them), because a lag under a sensor gain passes the omnibus tests and still gains a
criterion of ~100.
This times ``diagnose()`` (one worker, record in memory) both ways on the practice recordings
and on single-effect scenarios of the study, interleaved, and reports CPU time beside wall time
(the machine is shared) with the same-run ratio and both verdicts. Writes
bench/results/forward_stop_cost.md.

    python bench/forward_stop_cost.py --repeat 1
"""

import argparse
import os
from pathlib import Path
import sys
import time

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / 'bench'))
sys.path.insert(0, str(ROOT / 'test' / 'diagnosis'))

from common import machine_description, RESULTS_DIR, say  # noqa: E402
from diagnosis_scenarios import BY_NAME  # noqa: E402
import numpy as np  # noqa: E402
from rotor_id.diagnosis.diagnose import diagnose  # noqa: E402

SELECTION = sys.modules['rotor_id.diagnosis.diagnose']
RECORDINGS = ROOT.parent / 'shared' / 'recordings'
NAMES = ('dx_none_wake', 'dx_sensor_lag', 'dx_dynamic_inflow', 'dx_periodic_coefficients')
SCENARIOS = ('sensor_gain', 'sensor_bias', 'flap_frequency', 'gain+lag')


def _inputs():
    from rotor_id.io.bag import read_run
    from rotor_id.io.run_description import load_run_description
    out = {}
    if RECORDINGS.is_dir():
        for name in NAMES:
            description = load_run_description(RECORDINGS / f'{name}.yaml')
            out[name] = (read_run(description), description)
    for name in SCENARIOS:
        out[f'{name} (seed 1000)'] = BY_NAME[name].record_and_description(1000)
    return out


def _residuals_are_noise(fit, ctx):
    """Return the old rule's test: white residuals at the floor with a mean within noise."""
    from rotor_id.diagnosis import residuals as rs
    if not SELECTION._adequate(fit, ctx['floors'], ctx['u'], ctx['t']):
        return False
    res = SELECTION._residual_matrix(fit.estimate)
    for j, floor in enumerate(ctx['floors']):
        n_eff = res.shape[0] * rs.effective_fraction(res[:, j])
        if abs(float(np.mean(res[:, j]))) > 3.0 * floor / np.sqrt(n_eff):
            return False
    return True


def _omnibus_stop(step):
    """Return the forward step with the old rule: no step once the residuals look like noise."""
    def stopped(current, cur_val, kept, ctx):
        return None if _residuals_are_noise(current, ctx) else step(current, cur_val, kept, ctx)
    return stopped


def _run(record, description, omnibus):
    step = SELECTION._forward_step
    if omnibus:
        SELECTION._forward_step = _omnibus_stop(step)
    wall, cpu = time.perf_counter(), time.process_time()
    try:
        result = diagnose(record, description, workers=1)
    finally:
        SELECTION._forward_step = step
    names = ' + '.join(st['effect'] for st in result.steps) or result.effect
    return names, time.perf_counter() - wall, time.process_time() - cpu


def main(argv=None):
    """Time both rules, interleaved; write the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument('--repeat', type=int, default=1)
    args = parser.parse_args(argv)
    inputs = _inputs()
    load_start = ' / '.join(f'{v:.2f}' for v in os.getloadavg())
    times = {(n, m): [] for n in inputs for m in (False, True)}
    verdicts = {}
    for round_ in range(args.repeat):
        for name, (record, description) in inputs.items():
            for omnibus in ((True, False) if round_ % 2 == 0 else (False, True)):
                names, wall, cpu = _run(record, description, omnibus)
                times[name, omnibus].append((wall, cpu))
                verdicts[name, omnibus] = names
                say(f'round {round_ + 1}: {name} {"omnibus stop" if omnibus else "always a step"}'
                    f': {names}, {wall:.2f} s wall, {cpu:.2f} s CPU')
    lines = ['# Forward selection: always a last step vs. the omnibus stop', '', 'Machine:', '']
    lines += [f'* {k}: {v}' for k, v in machine_description().items()]
    lines += ['', f'Median of {args.repeat} interleaved round(s) (the order of the two rules '
              'alternates from round to round); `diagnose()` on the record in '
              'memory, one worker. CPU time is the figure that matters on this shared '
              'machine (wall time includes waiting for the CPU).', '',
              '| record | verdict, omnibus stop | verdict, always a step | omnibus CPU s | '
              'always CPU s | always/omnibus (CPU) | omnibus wall s | always wall s |',
              '|---|---|---|---|---|---|---|---|']
    for name in inputs:
        o = np.median(np.array(times[name, True]), axis=0)
        a = np.median(np.array(times[name, False]), axis=0)
        lines.append(f'| {name} | {verdicts[name, True]} | {verdicts[name, False]} | '
                     f'{o[1]:.2f} | {a[1]:.2f} | {a[1] / o[1]:.2f}× | {o[0]:.2f} | {a[0]:.2f} |')
    load_end = ' / '.join(f'{v:.2f}' for v in os.getloadavg())
    lines += ['', f'Load average (1/5/15 min): {load_start} at the start, {load_end} at the end.',
              '', f'Reproduce: `python bench/forward_stop_cost.py --repeat {args.repeat}`.']
    text = '\n'.join(lines) + '\n'
    print(text)
    RESULTS_DIR.mkdir(exist_ok=True)
    (RESULTS_DIR / 'forward_stop_cost.md').write_text(text)
    return 0


if __name__ == '__main__':
    sys.exit(main())
