"""
Bench of ``rotor-id campaign``: a simulated tunnel entry of 120 bags.

The bench makes the recordings itself: test points of the μ = 0 wake rotor
(test/commands/campaign_helpers.py: the planning module's simulation in the test-stand
convention, 0.94 s at 1 kHz each, stirring 2 revolutions, 0.1° flap noise), at tunnel speeds
10-40 m/s, progressing and regressing stirring alternately, each an MCAP bag with its run
description beside it (no initial_guess: identify searches its start-value grid, as for a user
who gives none). Then the whole command (a fresh Python process, start-up included) runs over
them with ``--jobs 1`` and ``--jobs 2``, interleaved (1, 2, 1, 2, ...) into fresh output
directories, and once more over up-to-date results (the resume path). Wall time, CPU time of
the command and its workers, peak memory of a process, and the load average before and after
each run are recorded, since the machine is shared.

Run: ``python bench/campaign.py [--bags 120] [--repeat 2] [--no-write]``.
"""

import argparse
import json
import os
from pathlib import Path
import resource
import shutil
import subprocess
import sys
import tempfile
import time

from common import (fmt_time, machine_description, markdown_table, REPO_ROOT, RESULTS_DIR,
                    say, write_results)

sys.path.insert(0, str(REPO_ROOT / 'test' / 'commands'))
from campaign_helpers import write_test_point  # noqa: E402,I100

#: What a campaign must fit into to stay on one machine: a night between tunnel days.
OVERNIGHT_S = 12 * 3600.0


def make_campaign(directory, n_bags):
    """Write ``n_bags`` test points into ``directory``; return the seconds it took."""
    started = time.perf_counter()
    for i in range(n_bags):
        speed = 10.0 + 30.0 * i / max(n_bags - 1, 1)
        write_test_point(directory, f'tp{i:03d}', seed=1000 + i, guess=False,
                         direction='progressing' if i % 2 == 0 else 'regressing',
                         conditions={'tunnel_speed_m_s': round(speed, 2)})
        if (i + 1) % 20 == 0:
            say(f'made {i + 1}/{n_bags} bags')
    return time.perf_counter() - started


def run_campaign(directory, out, jobs, extra=()):
    """Run the command once; return wall, CPU (command + workers), peak RSS, load before/after."""
    load_before = os.getloadavg()
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    started = time.perf_counter()
    proc = subprocess.run([sys.executable, '-m', 'rotor_id.cli', 'campaign', str(directory),
                           '--out', str(out), '--jobs', str(jobs), *extra],
                          capture_output=True, text=True, cwd=REPO_ROOT)
    wall = time.perf_counter() - started
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise RuntimeError(f'campaign --jobs {jobs} exited {proc.returncode}: '
                           f'{proc.stderr.strip().splitlines()[-3:]}')
    return {'jobs': jobs, 'wall_s': wall,
            'cpu_s': (after.ru_utime - usage.ru_utime) + (after.ru_stime - usage.ru_stime),
            'peak_rss_mb': after.ru_maxrss / 1024.0,
            'load_before': [round(v, 2) for v in load_before],
            'load_after': [round(v, 2) for v in os.getloadavg()],
            'last_line': proc.stderr.strip().splitlines()[-1]}


def per_bag_seconds(out):
    """Worker seconds per bag from the results (identify + figure, inside the worker)."""
    times = [json.loads(p.read_text())['elapsed_s']
             for p in sorted(Path(out, 'points').glob('*/result.json'))]
    return sorted(times)


def main(argv=None):
    """Make the campaign, time it with 1 and 2 jobs, write bench/results/campaign.md."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    parser.add_argument('--bags', type=int, default=120)
    parser.add_argument('--repeat', type=int, default=2, help='timed runs per --jobs value')
    parser.add_argument('--diagnose-bags', type=int, default=10,
                        help='bags of a second, smaller campaign run with --diagnose')
    parser.add_argument('--no-write', action='store_true', help='print only')
    args = parser.parse_args(argv)
    root = Path(tempfile.mkdtemp(prefix='campaign_bench_'))
    try:
        entry = root / 'entry'
        entry.mkdir()
        make_s = make_campaign(entry, args.bags)
        size_mb = sum(p.stat().st_size for p in entry.rglob('*') if p.is_file()) / 1e6
        say(f'{args.bags} bags ({size_mb:.1f} MB) made in {make_s:.1f} s')
        runs = []
        for r in range(args.repeat):
            for jobs in (1, 2):
                out = root / f'out_{jobs}_{r}'
                runs.append(run_campaign(entry, out, jobs))
                say(f'--jobs {jobs}: {runs[-1]["wall_s"]:.1f} s wall, '
                    f'{runs[-1]["cpu_s"]:.1f} s CPU, load {runs[-1]["load_before"][0]:.1f} -> '
                    f'{runs[-1]["load_after"][0]:.1f}')
        resume = run_campaign(entry, root / 'out_2_0', 2)
        say(f'resume (all up to date): {resume["wall_s"]:.2f} s')
        worker = per_bag_seconds(root / 'out_1_0')
        small = root / 'small'
        small.mkdir()
        for path in sorted(entry.glob('tp*.yaml'))[:args.diagnose_bags]:
            shutil.copy(path, small / path.name)
            shutil.copytree(path.with_suffix(''), small / path.stem)
        diagnosed = run_campaign(small, root / 'out_diagnose', 2, ['--diagnose'])
        say(f'--diagnose on {args.diagnose_bags} bags: {diagnosed["wall_s"]:.1f} s')
    finally:
        shutil.rmtree(root, ignore_errors=True)
    body = report(args, make_s, size_mb, runs, resume, worker, diagnosed)
    print(body)
    if not args.no_write:
        write_results('campaign', f'rotor-id campaign over {args.bags} simulated bags', body,
                      f'python bench/campaign.py --bags {args.bags} --repeat {args.repeat}')
        (RESULTS_DIR / 'campaign.json').write_text(json.dumps(
            {'machine': machine_description(), 'bags': args.bags, 'make_s': make_s,
             'size_mb': size_mb, 'runs': runs,
             'resume': resume, 'worker_s_per_bag': worker, 'diagnose': diagnosed,
             'diagnose_bags': args.diagnose_bags}, indent=1))
    return 0


def _median(values):
    values = sorted(values)
    mid = len(values) // 2
    return values[mid] if len(values) % 2 else 0.5 * (values[mid - 1] + values[mid])


def report(args, make_s, size_mb, runs, resume, worker, diagnosed):
    """Return the Markdown of the results."""
    n = args.bags
    rows = [[r['jobs'], f'{r["wall_s"]:.1f} s', f'{r["wall_s"] / n * 1e3:.0f} ms',
             f'{r["cpu_s"]:.1f} s', f'{r["peak_rss_mb"]:.0f} MB',
             ' / '.join(f'{v:.2f}' for v in r['load_before']),
             ' / '.join(f'{v:.2f}' for v in r['load_after'])] for r in runs]
    rows.append(['2, resumed', f'{resume["wall_s"]:.2f} s', '', f'{resume["cpu_s"]:.1f} s',
                 f'{resume["peak_rss_mb"]:.0f} MB',
                 ' / '.join(f'{v:.2f}' for v in resume['load_before']),
                 ' / '.join(f'{v:.2f}' for v in resume['load_after'])])
    wall = {j: _median([r['wall_s'] for r in runs if r['jobs'] == j]) for j in (1, 2)}
    cpu = {j: _median([r['cpu_s'] for r in runs if r['jobs'] == j]) for j in (1, 2)}
    speedup = wall[1] / wall[2]
    rate = n / wall[2]                                  # bags per second on this machine
    overnight = rate * OVERNIGHT_S
    loads = [r['load_before'][0] for r in runs] + [r['load_after'][0] for r in runs]
    busy = min(loads) >= 2.0
    verdict = (f'The 1-minute load average was {min(loads):.1f}-{max(loads):.1f} during the '
               "runs on 2 cores (other engineers' tests), and the bench runs under `nice`: "
               'both cores were busy, so a second worker mostly competed for the CPU the '
               "first one had, and wall times are dominated by the others' load."
               if busy else
               f'The 1-minute load average was {min(loads):.1f}-{max(loads):.1f} during the '
               'runs on 2 cores.')
    return f"""
## Campaign

{n} bags made by the bench in {make_s:.1f} s ({size_mb:.1f} MB in all; each 0.94 s of
4-blade data at 1 kHz, window 2 revolutions of stirring = 134 samples). Each bag: read,
identify (start-value grid, then Gauss-Newton), write identify.json, the fit figure and
result.json. Diagnosis not run (`--diagnose` adds a diagnosis per bag; see bench/diagnosis).

{markdown_table(['--jobs', 'wall', 'per bag', 'CPU (all processes)', 'peak RSS of a process',
                 'load before (1/5/15 min)', 'load after'], rows)}

* Median wall: **{wall[1]:.1f} s** with one job, **{wall[2]:.1f} s** with two, a
  speed-up of **{speedup:.2f}x** from the second core (ideal 2x on an idle 2-core machine).
  {verdict}
* CPU time of the command and its workers: {cpu[1]:.1f} s with one job, {cpu[2]:.1f} s with two
  ({cpu[2] / cpu[1] - 1:+.0%}: the second worker's start-up and imports). On an idle machine the
  work would take at least {cpu[1]:.1f} s and {cpu[2] / 2:.1f} s of wall time, a speed-up of
  at most {2 * cpu[1] / cpu[2]:.2f}x (the CPU figures are steadier than wall time under load).
* Inside a worker a bag takes {fmt_time(_median(worker))} of wall time at this load (median;
  {fmt_time(worker[0])} to {fmt_time(worker[-1])}): read, identify with the adequacy check,
  and the fit figure; {cpu[1] / n * 1e3:.0f} ms of CPU per bag in all (one job).
* A second run over up-to-date results (every bag's key unchanged) takes
  {resume["wall_s"]:.2f} s: it hashes the bags' file stats and the descriptions, and redraws
  the report.

## When one machine is not enough

With `--diagnose` ({args.diagnose_bags} of the bags, two jobs) the campaign took
{diagnosed["wall_s"]:.1f} s, {diagnosed["wall_s"] / args.diagnose_bags:.1f} s per bag
(load {diagnosed["load_before"][0]:.1f} before, {diagnosed["load_after"][0]:.1f} after).

At the measured rates with two jobs this machine handles, in a 12-hour night:

{markdown_table(['campaign', 'rate (2 jobs)', 'bags per hour', 'bags per 12-hour night'], [
    ['identify, measured at this load', f'{rate:.2f} bags/s', f'{rate * 3600:,.0f}',
     f'{overnight:,.0f}'],
    ['identify, idle machine (bound from the CPU time: 2 cores busy)',
     f'{2 * n / cpu[2]:.2f} bags/s', f'{2 * n / cpu[2] * 3600:,.0f}',
     f'{2 * n / cpu[2] * OVERNIGHT_S:,.0f}'],
    ['identify + diagnose, measured at this load',
     f'{args.diagnose_bags / diagnosed["wall_s"]:.3f} bags/s',
     f'{args.diagnose_bags / diagnosed["wall_s"] * 3600:,.0f}',
     f'{args.diagnose_bags / diagnosed["wall_s"] * OVERNIGHT_S:,.0f}']])}

A tunnel entry (tens to hundreds of test points, one every few minutes) is far inside that:
each bag's results are ready seconds after it is recorded, with or without diagnosis. One
machine is outgrown by campaigns larger than the last column (for bags of this size; at the
load measured, or on the machine alone): beyond it the bags are independent, so DIR splits
over machines and their campaign.csv rows concatenate. Longer records cost more per bag
(reading and fitting grow with the bag and the window), so the limit scales down in
proportion to the time per bag.
"""


if __name__ == '__main__':
    sys.exit(main())
