"""
Shared helpers of the benchmarks: machine description, side-by-side timing, tables, results.

The machine is shared (2 cores, several engineers running tests), so single timings are noisy.
Every benchmark therefore times the things it compares *interleaved* (A, B, C, A, B, C, ...)
in one run and reports medians; ratios of medians taken that way are what the speed targets are
judged on.
"""

import datetime
import math
import os
from pathlib import Path
import platform
import subprocess
import sys
import tempfile
import time

BENCH_DIR = Path(__file__).resolve().parent
REPO_ROOT = BENCH_DIR.parent
RESULTS_DIR = BENCH_DIR / 'results'

if str(REPO_ROOT) not in sys.path:          # `python bench/x.py` from anywhere
    sys.path.insert(0, str(REPO_ROOT))

import rotor_id  # noqa: E402,F401,I100 - before numpy: one BLAS thread, as the CLI has
import numpy as np  # noqa: E402,I100
import scipy  # noqa: E402

_T_START = time.perf_counter()


def say(message):
    """Progress line on stderr with the elapsed time of this process."""
    print(f'[{time.perf_counter() - _T_START:7.1f} s] {message}', file=sys.stderr, flush=True)


def _cpu_model():
    try:
        for line in Path('/proc/cpuinfo').read_text().splitlines():
            if line.startswith('model name'):
                return line.split(':', 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or 'unknown CPU'


def _memory_gb():
    try:
        for line in Path('/proc/meminfo').read_text().splitlines():
            if line.startswith('MemTotal'):
                return int(line.split()[1]) / 1024**2
    except OSError:
        pass
    return float('nan')


def machine_description():
    """Describe the machine, software and load (a dict) for the results files."""
    load = os.getloadavg() if hasattr(os, 'getloadavg') else (float('nan'),) * 3
    return {
        'date (UTC)': datetime.datetime.now(datetime.timezone.utc).strftime('%Y-%m-%d %H:%M'),
        'cpu': _cpu_model(),
        'logical cores': os.cpu_count(),
        'memory': f'{_memory_gb():.1f} GB',
        'load average (1/5/15 min) at start': ' / '.join(f'{v:.2f}' for v in load),
        'os': platform.platform(),
        'python': platform.python_version(),
        'numpy': np.__version__,
        'scipy': scipy.__version__,
        'BLAS threads (OPENBLAS_NUM_THREADS)': os.environ.get('OPENBLAS_NUM_THREADS', 'default'),
        'Python speed (10⁷ additions in a loop, best of 3)': f'{_loop_seconds():.2f} s',
    }


def _loop_seconds():
    """Return the CPU seconds of 10⁷ additions in a Python loop (best of 3): the VM's pace."""
    best = math.inf
    for _ in range(3):
        start, total = time.process_time(), 0
        for i in range(10**7):
            total += i
        best = min(best, time.process_time() - start)
    return best


def warm_kernel_cache():
    """
    Fill the compiled kernels' cache, as ``make build`` does, before anything is timed.

    After a change to the kernels' source their cached machine code is stale and the first
    process to load them compiles (about 20 s of CPU): a timing that caught that would measure
    the compiler, once. Loading from the cache (0.4-1 s) stays inside the timings.
    """
    started = time.perf_counter()
    subprocess.run([sys.executable, '-m', 'rotor_id.estimation.kernels'], cwd=REPO_ROOT,
                   capture_output=True, check=False)
    say(f'compiled-kernel cache checked ({time.perf_counter() - started:.1f} s)')


def run_in_workdir(workdir, prefix, measure):
    """
    Return ``measure(directory)`` run in ``workdir``, or in a fresh temporary one.

    A given ``workdir`` keeps what the benchmark makes there (a large bag) for the next run;
    without one, a temporary directory named ``prefix``… is made and removed afterwards, so
    that a run from a clean clone starts from nothing.
    """
    if workdir is None:
        with tempfile.TemporaryDirectory(prefix=prefix) as directory:
            return measure(directory)
    return measure(workdir)


def children_cpu():
    """CPU time (user + system) of this process's waited-for children so far, s."""
    import resource
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def run_command(argv, env=None, ok_codes=(0,)):
    """Run a command from the repository root; return (wall s, CPU s of the child, stdout)."""
    cpu = children_cpu()
    start = time.perf_counter()
    out = subprocess.run(argv, capture_output=True, text=True, env=env, cwd=REPO_ROOT)
    wall = time.perf_counter() - start
    if out.returncode not in ok_codes:
        raise RuntimeError(f'{" ".join(map(str, argv))} failed:\n{out.stderr[-2000:]}')
    return wall, children_cpu() - cpu, out.stdout


def machine_markdown():
    """Machine description as a markdown list."""
    return '\n'.join(f'* {k}: {v}' for k, v in machine_description().items())


def time_once(fn):
    """Wall and CPU time (this process, all threads) of one call of ``fn``, and its result."""
    wall, cpu = time.perf_counter(), time.process_time()
    result = fn()
    return time.perf_counter() - wall, time.process_time() - cpu, result


def time_interleaved(functions, repeat, warmup=1):
    """
    Time several callables round-robin and return their median wall and CPU times.

    CPU time (``time.process_time``) leaves out the time the process waits while other
    processes run, so on a shared machine it is the steadier measure of a computation's cost;
    wall time is what a user waits.

    Parameters
    ----------
    functions : dict
        Name -> callable without arguments.
    repeat : int
        Timed rounds; in each round every callable runs once, in the given order.
    warmup : int
        Untimed rounds first (imports, caches).

    Returns
    -------
    dict
        Name -> dict(median, min, max, times (wall), cpu (median CPU time), cpu_times,
        result (of the last call)).

    """
    times = {name: [] for name in functions}
    cpu_times = {name: [] for name in functions}
    results = {}
    for _ in range(warmup):
        for name, fn in functions.items():
            results[name] = fn()
    for _ in range(repeat):
        for name, fn in functions.items():
            wall, cpu, results[name] = time_once(fn)
            times[name].append(wall)
            cpu_times[name].append(cpu)
    return {name: {'median': float(np.median(ts)), 'min': float(np.min(ts)),
                   'max': float(np.max(ts)), 'times': ts,
                   'cpu': float(np.median(cpu_times[name])), 'cpu_times': cpu_times[name],
                   'result': results[name]}
            for name, ts in times.items()}


def fmt_time(seconds):
    """Human-readable duration (µs/ms/s)."""
    if seconds < 1e-3:
        return f'{seconds * 1e6:.1f} µs'
    if seconds < 1.0:
        return f'{seconds * 1e3:.2f} ms'
    return f'{seconds:.2f} s'


def markdown_table(headers, rows):
    """Markdown table from a header list and rows of already formatted cells."""
    lines = ['| ' + ' | '.join(headers) + ' |',
             '|' + '|'.join('---' for _ in headers) + '|']
    lines += ['| ' + ' | '.join(str(c) for c in row) + ' |' for row in rows]
    return '\n'.join(lines)


def write_results(name, title, body, command):
    """
    Write ``bench/results/<name>.md``: title, how to reproduce, machine, then ``body``.

    Returns the path written.
    """
    RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    path = RESULTS_DIR / f'{name}.md'
    text = (f'# {title}\n\n'
            f'Reproduce: `{command}` (from the repository root, after `make build`; '
            '`make bench` runs every benchmark).\n\n'
            f'## Machine\n\n{machine_markdown()}\n\n'
            'The machine is shared with other engineers running tests, so absolute times are '
            'noisy; every comparison below was timed interleaved in one run (medians).\n\n'
            f'{body.rstrip()}\n')
    path.write_text(text)
    say(f'wrote {path.relative_to(REPO_ROOT)}')
    return path


class SustainedStirring:
    """
    The report's stirring (Ch.2 eqs 1-5) that stops accelerating at ``t_hold``.

    Up to ``t_hold`` the phase is the report's φ = ω̇ (t − t0)²; after it the stirring rate is
    held at 2 ω̇ (t_hold − t0), so long records keep a physical input instead of a stirring
    rate that grows without bound. ``u = [θ0, θI, θII]`` like
    :class:`rotor_id.physics.stirring.StirringSchedule`, which it wraps.
    """

    def __init__(self, schedule, t_hold):
        self.schedule = schedule
        self.t_hold = float(t_hold)

    def phase(self, t):
        """Stirring phase: the report's law, then constant rate after ``t_hold``."""
        t = np.asarray(t, dtype=float)
        late = t > self.t_hold
        phi = self.schedule.phase(np.where(late, self.t_hold, t))
        rate = self.schedule.stirring_rate(self.t_hold)
        return phi + np.where(late, rate * (t - self.t_hold), 0.0)

    def __call__(self, t):
        """Return ``u = [θ0, θI, θII]`` at times t, shape (len(t), 3)."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        on = (t >= self.schedule.t_step) * self.schedule.amplitude
        phi = self.phase(t)
        return np.column_stack([np.full_like(t, self.schedule.collective), on * np.sin(phi),
                                on * np.cos(phi)])


def figure_path(name):
    """Path of ``bench/results/<name>.png`` (directory created)."""
    RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    return RESULTS_DIR / f'{name}.png'


def pyplot():
    """matplotlib.pyplot on the Agg backend (no display needed)."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    return plt
