"""
Whole ``rotor-id identify`` commands, as a user waits for them.

Three commands on the practice recording ``id_wake_progressing`` (the repository's sibling
``shared/recordings``), each as a fresh process, timed interleaved (median of ``--repeat``):

* ``python -c pass`` in the same environment: the interpreter's own start, the floor;
* output error on the description's window (127 samples; target ≤ 0.5 s end to end), with
  the default kernel mode (numba is not loaded for so short a job);
* filter error on the whole record (1065 samples; target ≤ 2 s) with the default kernel mode
  (analytic sensitivities through the filter, compiled), with ``ROTOR_ID_KERNELS=numpy``
  (the same equations in numpy; the two must give the same estimates and bounds to 1e-9
  relative), and with finite-difference sensitivities (``gradients='finite-difference'``: the
  filter run 2k+1 times per iteration, compiled: the peer of the analytic sensitivities), whose
  optimum may differ by the convergence tolerance (printed in σ);
* filter error on the periodic practice record ``id_multiblade_mu04`` (its own window), with
  analytic and with finite-difference sensitivities.

A ``python -X importtime`` run of the short command lists the modules whose import costs the
most (start-up is most of that command).

Run: ``python bench/command_speed.py [--repeat N]``.
"""

import argparse
import json
import os
from pathlib import Path
import subprocess
import sys
import tempfile

from common import fmt_time, markdown_table, REPO_ROOT, run_command, say, write_results

RECORDINGS = REPO_ROOT.parent / 'shared' / 'recordings'
BAG = RECORDINGS / 'id_wake_progressing'
PERIODIC_BAG = RECORDINGS / 'id_multiblade_mu04'
DESCRIPTION = RECORDINGS / 'id_wake_progressing.yaml'
SHORT_TARGET_S = 0.5
FILTER_TARGET_S = 2.0
AGREEMENT = 1e-9


def whole_record_description(directory):
    """Write the practice description with the window widened to the whole 1065 samples."""
    lines = DESCRIPTION.read_text().splitlines()
    cut = next(i for i, line in enumerate(lines) if line.startswith('window_s'))
    kept = lines[:cut]
    rest = lines[cut + 1:]
    while rest and rest[0].startswith('-'):
        rest.pop(0)
    path = Path(directory) / 'whole_record.yaml'
    path.write_text('\n'.join(kept + rest + ['window_s: [0.0, 1.064]']) + '\n')
    return path


def slowest_imports(argv, count=8):
    """Top ``count`` modules by cumulative import time (µs) of one run with -X importtime."""
    out = subprocess.run([sys.executable, '-X', 'importtime'] + argv[1:], capture_output=True,
                         text=True, cwd=REPO_ROOT)
    rows = []
    for line in out.stderr.splitlines():
        if not line.startswith('import time:') or 'cumulative' in line:
            continue
        _, cumulative, name = line.split('|')
        if len(name) - len(name.lstrip()) == 1:             # imported at the top level
            rows.append((int(cumulative), name.strip()))
    rows.sort(reverse=True)
    return rows[:count]


def finite_difference_command(args):
    """Return the identify command with finite-difference filter-error sensitivities."""
    code = ('import functools, sys; from rotor_id.estimation import filter_error as fe; '
            'fe.fit_filter_error = functools.partial(fe.fit_filter_error, '
            "gradients='finite-difference'); from rotor_id import cli; "
            'sys.exit(cli.main(sys.argv[1:]))')
    return [sys.executable, '-c', code] + args


def shift_in_sigma(a, b):
    """Largest |value difference| / σ and relative σ difference of two identify JSON files."""
    pa = json.loads(Path(a).read_text())['parameters']
    pb = json.loads(Path(b).read_text())['parameters']
    shift = max(abs(pb[n]['value'] - pa[n]['value']) / pa[n]['std'] for n in pa)
    spread = max(abs(pb[n]['std'] / pa[n]['std'] - 1.0) for n in pa)
    return shift, spread


def compare(a, b):
    """Largest relative difference of parameter values and σ of two identify JSON files."""
    pa = json.loads(Path(a).read_text())['parameters']
    pb = json.loads(Path(b).read_text())['parameters']
    worst = 0.0
    for name, entry in pa.items():
        for key in ('value', 'std'):
            ref = entry[key]
            worst = max(worst, abs(pb[name][key] - ref) / max(abs(ref), 1e-300))
    return worst


def main(argv=None):
    """Time the commands, print the table, write bench/results/command_speed.md."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    parser.add_argument('--repeat', type=int, default=3, help='interleaved rounds')
    parser.add_argument('--no-write', action='store_true')
    args = parser.parse_args(argv)
    if not BAG.exists():
        print(f'skipped: the practice recordings are not at {RECORDINGS}', file=sys.stderr)
        return 0
    tmp = Path(tempfile.mkdtemp(prefix='rotor_id_bench_'))
    whole = whole_record_description(tmp)
    cli = [sys.executable, '-m', 'rotor_id.cli', 'identify', '--quiet']
    default_env = {k: v for k, v in os.environ.items() if k != 'ROTOR_ID_KERNELS'}
    numpy_env = dict(default_env, ROTOR_ID_KERNELS='numpy')
    commands = {
        'python -c pass': ([sys.executable, '-c', 'pass'], default_env),
        'identify, output error, 127 samples': (
            cli + ['--config', str(DESCRIPTION), str(BAG), '--json', str(tmp / 'oe.json')],
            default_env),
        'identify, filter error, 1065 samples': (
            cli + ['--method', 'filter-error', '--config', str(whole), str(BAG),
                   '--json', str(tmp / 'fe.json')], default_env),
        'identify, filter error, 1065 samples, numpy only (reference)': (
            cli + ['--method', 'filter-error', '--config', str(whole), str(BAG),
                   '--json', str(tmp / 'fe_numpy.json')], numpy_env),
        'identify, filter error, 1065 samples, finite-difference sensitivities (reference)': (
            finite_difference_command(cli[3:] + ['--method', 'filter-error', '--config',
                                                 str(whole), str(BAG), '--json',
                                                 str(tmp / 'fe_fd.json')]), default_env),
        'identify, filter error, μ = .4 (periodic) practice record': (
            cli + ['--method', 'filter-error', '--config', f'{PERIODIC_BAG}.yaml',
                   str(PERIODIC_BAG), '--json', str(tmp / 'fe_mu04.json')], default_env),
        'identify, filter error, μ = .4, finite-difference sensitivities (reference)': (
            finite_difference_command(cli[3:] + [
                '--method', 'filter-error', '--config', f'{PERIODIC_BAG}.yaml',
                str(PERIODIC_BAG), '--json', str(tmp / 'fe_mu04_fd.json')]), default_env),
    }
    times = {name: [] for name in commands}
    cpus = {name: [] for name in commands}
    for round_ in range(args.repeat):
        for name, (command, env) in commands.items():
            wall, cpu, _ = run_command(command, env)
            times[name].append(wall)
            cpus[name].append(cpu)
            say(f'round {round_ + 1}: {name}: {fmt_time(wall)} wall, {fmt_time(cpu)} CPU')

    def median(values):
        return sorted(values)[len(values) // 2]

    load = os.getloadavg()[0]
    agreement = compare(tmp / 'fe_numpy.json', tmp / 'fe.json')
    short = median(times['identify, output error, 127 samples'])
    filt = median(times['identify, filter error, 1065 samples'])
    filt_cpu = median(cpus['identify, filter error, 1065 samples'])
    reference = median(times['identify, filter error, 1065 samples, numpy only (reference)'])
    reference_cpu = median(cpus['identify, filter error, 1065 samples, numpy only (reference)'])
    fd_name = 'identify, filter error, 1065 samples, finite-difference sensitivities (reference)'
    fd_cpu = median(cpus[fd_name])
    fd_shift, fd_spread = shift_in_sigma(tmp / 'fe_fd.json', tmp / 'fe.json')
    periodic_name = 'identify, filter error, μ = .4 (periodic) practice record'
    periodic_fd_name = ('identify, filter error, μ = .4, finite-difference sensitivities '
                        '(reference)')
    periodic_shift, periodic_spread = shift_in_sigma(tmp / 'fe_mu04_fd.json',
                                                     tmp / 'fe_mu04.json')
    rows = [[name, f'**{fmt_time(median(times[name]))}**', fmt_time(median(cpus[name])),
             f'{fmt_time(min(times[name]))} – {fmt_time(max(times[name]))}']
            for name in commands]
    table = markdown_table(['command', 'wall (median)', 'CPU (median)', 'wall range'], rows)
    imports = slowest_imports(commands['identify, output error, 127 samples'][0])
    import_table = markdown_table(['top-level module', 'import time (cumulative)'],
                                  [[name, fmt_time(us * 1e-6)] for us, name in imports])
    verdict = (
        f'Output error, 127 samples: {fmt_time(short)} end to end (target ≤ '
        f'{SHORT_TARGET_S:g} s: {"met" if short <= SHORT_TARGET_S else "MISSED"}).\n\n'
        f'Filter error, 1065 samples: {fmt_time(filt)} wall, {fmt_time(filt_cpu)} CPU (target '
        f'≤ {FILTER_TARGET_S:g} s on a quiet machine: '
        f'{"met" if filt <= FILTER_TARGET_S else "MISSED"} in wall time here, '
        f'{"met" if filt_cpu <= FILTER_TARGET_S else "MISSED"} in CPU time); '
        f'the numpy-only reference takes {fmt_time(reference)} wall, '
        f'{fmt_time(reference_cpu)} CPU ({reference_cpu / filt_cpu:.1f}× the CPU), '
        f'finite-difference sensitivities {fmt_time(median(times[fd_name]))} wall, '
        f'{fmt_time(fd_cpu)} CPU ({fd_cpu / filt_cpu:.1f}× the CPU). Estimates and bounds of the '
        f'compiled and numpy runs agree to {agreement:.1e} relative (required ≤ '
        f'{AGREEMENT:g}); the finite-difference optimum is {fd_shift:.1e} σ away, its bounds '
        f'{fd_spread:.1e} relative (both converge to 1e-3 σ steps).'
        f'\n\nFilter error on the periodic (μ = .4) practice record: '
        f'{fmt_time(median(cpus[periodic_name]))} CPU with analytic sensitivities, '
        f'{fmt_time(median(cpus[periodic_fd_name]))} CPU with finite differences '
        f'({median(cpus[periodic_fd_name]) / median(cpus[periodic_name]):.1f}×); optima '
        f'{periodic_shift:.1e} σ apart, bounds {periodic_spread:.1e} relative.'
        f'\n\nLoad average at the end: {load:.1f} (2 cores; wall times above CPU times are '
        'waiting for a core).')
    body = (f'## Whole commands (median of {args.repeat} interleaved rounds)\n\n{table}\n\n'
            f'{verdict}\n\n## Slowest imports of the short command (`-X importtime`)\n\n'
            f'{import_table}\n')
    print(body)
    if not args.no_write:
        write_results('command_speed', 'Whole identify commands', body,
                      'python bench/command_speed.py')
    if agreement > AGREEMENT:
        print(f'ERROR: compiled and numpy filter error differ by {agreement:.1e}',
              file=sys.stderr)
        return 2
    return 0 if short <= SHORT_TARGET_S and filt <= FILTER_TARGET_S else 1


if __name__ == '__main__':
    sys.exit(main())
