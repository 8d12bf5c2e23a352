#!/usr/bin/env python3
"""
Time ``rotor-id diagnose`` per recording against its full-search peer.

Two sets of 1-second 4-blade records at 1 kHz:

* the dx_* practice recordings (hover, one effect or none; dx_periodic_coefficients is the
  report's μ = 0.4 case, 0.45 s);
* forward flight (μ = 0.35, periodic baseline), made by the independent blade-by-blade truth
  generator of test/diagnosis and written as bags: no effect, a flap-sensor delay, a sensor
  lag, a blade Lock-number difference beside a delay, and random inflow (turbulence), the
  kinds of record that took longest.

Every record is diagnosed three ways, interleaved round by round so that all see the same
load:

* ``command``: what a user waits for, ``./rotor-id diagnose REC --config REC.yaml`` end to
  end in a child process (start-up, bag reading, the default two worker processes); its CPU
  time is the children's (resource.getrusage), summed over the command and its workers;
* ``in_process``: ``diagnose()`` on the record in memory, one worker (so wall ≈ CPU on a quiet
  machine);
* ``identify``: the peer, :func:`rotor_id.pipeline.identify` of the same record (the baseline
  fit alone, which every diagnosis starts with), timed in the same rounds.

Reported per recording: the median wall and CPU time of each, in_process/identify, and
whether the verdicts of the command and in-process agree. The targets: the command ≤ 3 s
wall on every recording and ≤ 1.5 s median over them (medians of the rounds; the machine is
shared, so read it beside the load average, the CPU time and the ratio to the peer).

    python bench/diagnose_speed.py [--repeat 3] [--no-write] [--output NAME.md]
"""

import argparse
import dataclasses
import json
import os
from pathlib import Path
import resource
import subprocess
import sys
import tempfile
import time

from common import machine_description, REPO_ROOT, RESULTS_DIR, say, warm_kernel_cache
import numpy as np

RECORDINGS = REPO_ROOT.parent / 'shared' / 'recordings'
NAMES = ('dx_none_wake', 'dx_sensor_lag', 'dx_dynamic_inflow', 'dx_periodic_coefficients')
#: forward flight at μ = 0.35 (the truth generator's knobs; a delay in seconds, a lag in rad
#: of azimuth, the Lock number of blade 2 scaled, turbulence σ in rad of pitch)
FORWARD = {'ff_none': {},
           'ff_delay': {'time_delay_s': 0.0003},
           'ff_sensor_lag': {'sensor_lag': 0.028},
           'ff_blade_delay': {'gamma_scale': [1.0, 1.06, 1.0, 1.0], 'time_delay_s': 0.00025},
           'ff_turbulence': {'turbulence': 0.0004, 'turbulence_corr': 2.0}}
FORWARD_MU = 0.35
STAMP0_NS = 1_764_000_000 * 10**9
TARGET_S = 3.0
TARGET_MEDIAN_S = 1.5


def _timed(function):
    wall, cpu = time.perf_counter(), time.process_time()
    out = function()
    return out, time.perf_counter() - wall, time.process_time() - cpu


def _children_cpu():
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def _forward_flight(workdir):
    """Write the forward-flight records as bags with run descriptions: {name: directory}."""
    sys.path.insert(0, str(REPO_ROOT / 'test' / 'diagnosis'))
    import truth_generator as truth
    from rotor_id.io.bag import write_record_bag
    out = {}
    for seed, (name, knobs) in enumerate(FORWARD.items(), start=1):
        cfg = truth.mu04_case(seed=seed, mu=FORWARD_MU, t0=truth.TruthConfig.t0, **knobs)
        # stamped from a nonzero clock, as a recorder's messages are (a zero stamp is unfilled)
        record = dataclasses.replace(truth.generate(cfg), stamp0_ns=STAMP0_NS)
        write_record_bag(Path(workdir) / name, record)
        (Path(workdir) / f'{name}.yaml').write_text(
            truth.run_description_text(cfg, 'multiblade', ('gamma', 'theta0')))
        out[name] = Path(workdir)
    return out


def _command(name, folder, workdir):
    """Run ``rotor-id diagnose`` on one recording: (verdict, wall s, CPU s of the children)."""
    out = Path(workdir) / f'{name}.json'
    cmd = [str(REPO_ROOT / 'rotor-id'), 'diagnose', str(folder / name), '--config',
           str(folder / f'{name}.yaml'), '--quiet', '--json', str(out)]
    wall, cpu = time.perf_counter(), _children_cpu()
    done = subprocess.run(cmd, capture_output=True, text=True)
    wall, cpu = time.perf_counter() - wall, _children_cpu() - cpu
    if done.returncode != 0:
        raise SystemExit(f'rotor-id diagnose {name} failed (exit {done.returncode}): '
                         f'{done.stderr.strip().splitlines()[-1:]}')
    return json.loads(out.read_text())['explanation']['effect'], wall, cpu


def main(argv=None):
    """Run the comparison; exit 1 when a recording misses the target or a verdict changes."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument('--repeat', type=int, default=3)
    parser.add_argument('--no-write', action='store_true')
    parser.add_argument('--output', default='diagnose_speed.md',
                        help='results file under bench/results/ (another machine: its own name)')
    args = parser.parse_args(argv)
    if not RECORDINGS.is_dir():
        say(f'no practice recordings at {RECORDINGS}: nothing to time')
        return 0
    warm_kernel_cache()
    from rotor_id.diagnosis.diagnose import diagnose
    from rotor_id.io.bag import read_run
    from rotor_id.io.run_description import load_run_description
    from rotor_id.pipeline import identify
    modes = ('command', 'in_process', 'identify')
    with tempfile.TemporaryDirectory(prefix='rotor_id_diagnose_speed_') as workdir:
        folders = {**{name: RECORDINGS for name in NAMES}, **_forward_flight(workdir)}
        names = tuple(folders)
        inputs = {}
        for name, folder in folders.items():
            description = load_run_description(folder / f'{name}.yaml')
            inputs[name] = (description, read_run(description))
        times = {(n, m): [] for n in names for m in modes}
        verdicts = {(n, m): set() for n in names for m in modes}
        for round_ in range(args.repeat):
            for name in names:
                description, record = inputs[name]
                for mode in modes:
                    if mode == 'command':
                        effect, wall, cpu = _command(name, folders[name], workdir)
                    elif mode == 'in_process':
                        result, wall, cpu = _timed(lambda: diagnose(record, description,
                                                                    workers=1))
                        effect = result.effect
                    else:
                        _, wall, cpu = _timed(lambda: identify(record, description))
                        effect = 'n/a'
                    times[name, mode].append((wall, cpu))
                    verdicts[name, mode].add(effect)
                    say(f'round {round_ + 1}/{args.repeat}: {name} {mode}: {effect}, '
                        f'{wall:.2f} s wall, {cpu:.2f} s CPU')
    lines = ['# diagnose: the command, in process, and the baseline fit as the peer',
             '', 'Machine:', '']
    lines += [f'* {k}: {v}' for k, v in machine_description().items()]
    lines += ['', 'Records: the dx_* practice recordings, and forward flight at '
              f'μ = {FORWARD_MU} (ff_*: 1-second 4-blade records of the independent truth '
              'generator, test/diagnosis/truth_generator.py, written as bags; '
              + '; '.join(f'{n}: {", ".join(f"{k} {v}" for k, v in knobs.items()) or "none"}'
                          for n, knobs in FORWARD.items()) + ').']
    lines += ['', f'Median of {args.repeat} interleaved rounds. `command`: `./rotor-id diagnose` '
              'end to end (start-up, bag reading, two workers; CPU summed over the command and '
              'its workers). `in process`: `diagnose()` on the record in memory, one worker. '
              '`identify`: the baseline fit alone (the peer). Targets: the command ≤ 3 s wall '
              'per recording and ≤ 1.5 s median over them.', '',
              '| recording | verdict (command / in process) | command wall s | command CPU s | '
              'in-process wall s | in-process CPU s | identify wall s | in process / '
              'identify (CPU) | ≤ 3 s |',
              '|---|---|---|---|---|---|---|---|---|']
    ok = True
    walls = []
    for name in names:
        c, s_, f = (np.median(np.array(times[name, m]), axis=0) for m in modes)
        seen = [verdicts[name, m] for m in modes[:2]]
        same = seen[0] == seen[1] and len(seen[0]) == 1
        met = c[0] <= TARGET_S
        walls.append(c[0])
        ok &= same and met
        lines.append(f'| {name} | {" / ".join("/".join(sorted(v)) for v in seen)}'
                     f'{"" if same else " (DIFFER)"} | {c[0]:.2f} | {c[1]:.2f} | {s_[0]:.2f} | '
                     f'{s_[1]:.2f} | {f[0]:.2f} | {s_[1] / f[1]:.1f}× | '
                     f'{"met" if met else "MISSED"} |')
    median = float(np.median(walls))
    ok &= median <= TARGET_MEDIAN_S
    lines += ['', f'Median command wall over the recordings: {median:.2f} s '
              f'({"met" if median <= TARGET_MEDIAN_S else "MISSED"}: ≤ {TARGET_MEDIAN_S} s).']
    load = ' / '.join(f'{v:.2f}' for v in os.getloadavg())
    lines += ['', f'Load average (1/5/15 min) at the end: {load}.']
    output = '' if args.output == 'diagnose_speed.md' else f' --output {args.output}'
    lines += ['', f'Reproduce: `python bench/diagnose_speed.py --repeat {args.repeat}{output}`.']
    text = '\n'.join(lines) + '\n'
    print(text)
    if not args.no_write:
        RESULTS_DIR.mkdir(exist_ok=True)
        (RESULTS_DIR / args.output).write_text(text)
    return 0 if ok else 1


if __name__ == '__main__':
    sys.exit(main())
