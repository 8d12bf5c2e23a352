"""
Start-up of ``rotor-id identify``: the time its imports take, against the interpreter's own.

The command is output error on the practice recording ``id_wake_progressing`` (its
description's 127-sample window, the repository's sibling ``shared/recordings``), run as a
fresh process with ``python -X importtime``, interleaved with its peer ``python -X importtime
-c pass`` (median of ``--repeat`` rounds). Figures per process:

* import time: the sum of the top-level entries of ``-X importtime`` (wall time, µs), every
  module the whole run imports (the lazy imports of the command included), the interpreter's
  own start (``site``, encodings) included, which the peer measures alone;
* import CPU: the CPU time of a fresh process that imports exactly the top-level modules the
  command imported, in its order (nothing else runs): the same cost without the waiting of a
  loaded machine; the peer is that process importing nothing;
* the whole command's wall and CPU time.

Target: the command's imports cost ≤ 0.25 s, judged on their CPU time (on a loaded machine
the wall time also counts the waits for a core; both are printed). The tables list the modules
that cost most and which of the heavy packages the command does not load at all.

The sources are byte-compiled first (as ``make build`` does): with PYTHONDONTWRITEBYTECODE set
and no .pyc, every start would compile them again.

Run: ``python bench/startup.py [--repeat N]``.
"""

import argparse
import os
from pathlib import Path
import statistics
import subprocess
import sys
import tempfile
import time

from command_speed import BAG, DESCRIPTION, RECORDINGS
from common import children_cpu, fmt_time, markdown_table, REPO_ROOT, say, write_results

TARGET_S = 0.25
#: Packages ``rotor-id identify`` needs not (diagnosis, statistics, figures, compiled kernels).
NOT_NEEDED = ('rotor_id.diagnosis', 'scipy', 'scipy.stats', 'matplotlib', 'numba')


def top_level_imports(stderr):
    """Return [(module, cumulative µs)]: the top-level entries of ``-X importtime``."""
    rows = []
    for line in stderr.splitlines():
        if not line.startswith('import time:') or 'cumulative' in line:
            continue
        _, cumulative, name = line.split('|')
        if len(name) - len(name.lstrip()) == 1:
            rows.append((name.strip(), int(cumulative)))
    return rows


def all_imports(stderr):
    """Return the names of every module in ``-X importtime`` output."""
    return {line.split('|')[2].strip() for line in stderr.splitlines()
            if line.startswith('import time:') and 'cumulative' not in line}


def run(argv, env):
    """Run a command; return (wall s, CPU s, stderr)."""
    cpu = children_cpu()
    start = time.perf_counter()
    out = subprocess.run(argv, capture_output=True, text=True, env=env, cwd=REPO_ROOT)
    wall = time.perf_counter() - start
    if out.returncode != 0:
        raise RuntimeError(f'{" ".join(map(str, argv))} failed:\n{out.stderr[-2000:]}')
    return wall, children_cpu() - cpu, out.stderr


def import_cpu(modules, env):
    """Return the CPU seconds of importing ``modules`` (in order) in a fresh process."""
    code = ('import time\nstart = time.process_time()\n'
            + ''.join(f'import {m}\n' for m in modules)
            + 'print(time.process_time() - start)\n')
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, env=env,
                         cwd=REPO_ROOT, check=True)
    return float(out.stdout)


def main(argv=None):
    """Time the command's imports against the peer, print the table, write the results."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    parser.add_argument('--repeat', type=int, default=11, help='interleaved rounds')
    parser.add_argument('--no-write', action='store_true')
    args = parser.parse_args(argv)
    if not BAG.exists():
        print(f'skipped: the practice recordings are not at {RECORDINGS}', file=sys.stderr)
        return 0
    subprocess.run([sys.executable, '-m', 'compileall', '-q', 'rotor_id'], cwd=REPO_ROOT,
                   capture_output=True, check=False)
    env = {k: v for k, v in os.environ.items() if k != 'ROTOR_ID_KERNELS'}
    tmp = Path(tempfile.mkdtemp(prefix='rotor_id_bench_'))
    command = [sys.executable, '-X', 'importtime', '-m', 'rotor_id.cli', 'identify', '--quiet',
               '--config', str(DESCRIPTION), str(BAG), '--json', str(tmp / 'oe.json')]
    peer = [sys.executable, '-X', 'importtime', '-c', 'pass']
    figures = {name: {'imports': [], 'import_cpu': [], 'wall': [], 'cpu': []}
               for name in ('identify', 'peer')}
    per_module = {}
    loaded = set()
    for round_ in range(args.repeat):
        for name, argv_ in (('peer', peer), ('identify', command)):
            wall, cpu, stderr = run(argv_, env)
            rows = top_level_imports(stderr)
            modules = [m for m, _ in rows if m not in sys.builtin_module_names]
            fig = figures[name]
            fig['imports'].append(sum(us for _, us in rows) * 1e-6)
            fig['import_cpu'].append(import_cpu(modules, env) if name == 'identify' else 0.0)
            fig['wall'].append(wall)
            fig['cpu'].append(cpu)
            if name == 'identify':
                loaded |= all_imports(stderr)
                for module, us in rows:
                    per_module.setdefault(module, []).append(us * 1e-6)
            say(f'round {round_ + 1}: {name}: imports {fmt_time(fig["imports"][-1])}, '
                f'import CPU {fmt_time(fig["import_cpu"][-1])}, whole {fmt_time(wall)}')
    med = {name: {k: statistics.median(v) for k, v in fig.items()}
           for name, fig in figures.items()}
    rows = [[label, f'**{fmt_time(med[name]["imports"])}**',
             fmt_time(med[name]['import_cpu']) if name == 'identify' else '–',
             fmt_time(med[name]['wall']), fmt_time(med[name]['cpu'])]
            for name, label in (('peer', '`python -c pass` (peer)'),
                                ('identify', '`rotor-id identify`, 127 samples'))]
    table = markdown_table(['process', 'import time (-X importtime)', 'import CPU',
                            'whole process, wall', 'whole process, CPU'], rows)
    slowest = sorted(per_module.items(), key=lambda item: -statistics.median(item[1]))[:10]
    module_table = markdown_table(['top-level module', 'import time (median, cumulative)'],
                                  [[m, fmt_time(statistics.median(v))] for m, v in slowest])
    absent = ', '.join(f'{m}: {"LOADED" if m in loaded else "not loaded"}' for m in NOT_NEEDED)
    imports = med['identify']['imports']
    cost = med['identify']['import_cpu']
    met = cost <= TARGET_S
    load = os.getloadavg()[0]
    verdict = (
        f'Imports of `rotor-id identify`: {fmt_time(cost)} of CPU (target ≤ {TARGET_S:g} s: '
        f'{"met" if met else "MISSED"}); {fmt_time(imports)} wall by `-X importtime`, '
        f'{imports / med["peer"]["imports"]:.1f}× the interpreter\'s own start imports '
        f'({fmt_time(med["peer"]["imports"])}) timed in the same rounds. The whole command '
        f'takes {fmt_time(med["identify"]["wall"])} wall, {fmt_time(med["identify"]["cpu"])} '
        'CPU.\n\n'
        f'Packages the command leaves alone: {absent}.\n\n'
        f'Load average at the end: {load:.1f} (2 cores; wall times above CPU times are '
        'waiting for a core).')
    body = (f'## Imports and the whole process (median of {args.repeat} interleaved rounds)\n\n'
            f'{table}\n\n{verdict}\n\n## Costliest top-level imports of the command\n\n'
            f'{module_table}\n')
    print(body)
    if not args.no_write:
        write_results('startup', 'Start-up of rotor-id identify', body,
                      'python bench/startup.py')
    return 0 if met else 1


if __name__ == '__main__':
    sys.exit(main())
