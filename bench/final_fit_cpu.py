"""
CPU of the live final fit (``fit_window``) on the final windows of a recorded live run.

For every final estimate in the bag (written by ``bench/live_latency.py``), the window is
fitted as the identifier does it: warm-started at that test point's last growing-window
estimate (the node starts from its latest iterate, which may be a later one), the live
tolerance, no residual-adequacy test, with the data-length verdict. Interleaved in one run:

* *kept*: the model kept per run-description structure (``fit_process.live_model``, the live
  path as it is);
* *fresh*: the same with that cache emptied before each fit (the model rebuilt per fit, as
  before it was kept).

CPU is this thread's (``time.thread_time``), medians of ``--repeat`` fits each. The estimate
is compared with a cold offline ``identify`` of the same window (default tolerance).
"""

import argparse
from dataclasses import replace
from pathlib import Path
import time

from common import markdown_table, REPO_ROOT, say, write_results
import numpy as np


def _estimates(bag):
    """Return the ParameterEstimate messages recorded in a bag, in order."""
    from rclpy.serialization import deserialize_message
    from rosbags.rosbag2 import Reader
    from rotor_id_msgs.msg import ParameterEstimate
    with Reader(bag) as reader:
        wanted = [c for c in reader.connections if c.topic == '/rotor_id/estimate']
        return [deserialize_message(bytes(data), ParameterEstimate)
                for _, _, data in reader.messages(connections=wanted)]


def _newest_bag():
    # either fit mode records the same run (directories are named by start time, then mode)
    bags = sorted([*(REPO_ROOT / 'out' / 'bench_live').glob('*-process/bag'),
                   *(REPO_ROOT / 'out' / 'bench_live').glob('*-thread/bag')],
                  key=lambda bag: bag.parent.name)
    return bags[-1] if bags else None


def main():
    """Time the final fits of a recorded live run; write bench/results/final_fit_cpu.md."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--bag', default=None, help='a bag of bench/live_latency.py (default: '
                        'the newest out/bench_live/*-process/bag or *-thread/bag)')
    parser.add_argument('--repeat', type=int, default=15)
    args = parser.parse_args()
    bag = Path(args.bag) if args.bag else _newest_bag()
    if bag is None or not bag.exists():
        say('no recorded live run: run `python bench/live_latency.py` first, or give --bag')
        return 2
    from rotor_id.commands.demo import case_files
    from rotor_id.io.bag import read_record
    from rotor_id.io.run_description import load_run_description
    from rotor_id.nodes import fit_process
    from rotor_id.nodes.test_points import FitRequest
    from rotor_id.pipeline import identify
    import yaml
    fit_process.warm_up()
    params_file, description_file, _ = case_files('wake')
    params = yaml.safe_load(Path(params_file).read_text())['/**/identifier']['ros__parameters']
    description = load_run_description(description_file)
    record = read_record(bag)
    estimates = _estimates(bag)
    finals = [e for e in estimates if e.kind == e.KIND_FINAL]
    if not finals:
        say(f'{bag}: no final estimate recorded')
        return 2
    options = fit_process.FitOptions(max_iter=50, multi_start=True, step_tol=1e-3,
                                     targets=tuple(params['target_std']))
    rows, kept_all, fresh_all = [], [], []
    for final in finals:
        say(f'test point {final.test_point}: {args.repeat} x 2 fits')
        provisional = [e for e in estimates if e.kind == e.KIND_PROVISIONAL
                       and e.test_point == final.test_point]
        start = provisional[-1] if provisional else final
        stamp0 = final.test_point_start.sec * 10**9 + final.test_point_start.nanosec
        shift = (stamp0 - record.stamp0_ns) / 1e9
        window = (final.window_requested_start_s + shift, final.window_requested_end_s + shift)
        warm = replace(description, initial_guess={**description.initial_guess,
                                                   **dict(zip(start.names, start.values))})
        request = FitRequest(final.test_point, True, window, record.stamp0_ns, record, None)
        times = {'kept': [], 'fresh': []}
        for _ in range(args.repeat):
            for key in ('kept', 'fresh'):
                if key == 'fresh':
                    fit_process._LIVE_MODELS.clear()
                cpu = time.thread_time()
                ident, verdict, timing = fit_process.fit_window(request, warm, options)
                times[key].append((time.thread_time() - cpu) * 1e3)
        offline = identify(record, description, window_s=window).estimate
        est = ident.estimate
        sigma = max(abs(v - offline.values[offline.names.index(n)]) / est.std_of(n)
                    for n, v in zip(ident.unknowns, est.values))
        kept, fresh = np.median(times['kept']), np.median(times['fresh'])
        kept_all.append(kept)
        fresh_all.append(fresh)
        rows.append([final.test_point, f'{window[1] - window[0]:.4f}',
                     'yes' if provisional else 'no (final values)', est.iterations,
                     'yes' if verdict[0] else 'no', f'{kept:.2f}', f'{fresh:.2f}',
                     f'{kept / fresh:.2f}', f'{sigma:.1e}'])
    body = (f'Bag: `{bag.relative_to(REPO_ROOT) if bag.is_relative_to(REPO_ROOT) else bag}` '
            f'({len(finals)} final windows); {args.repeat} fits per variant, interleaved.\n\n'
            f'* final fit CPU median over the windows: **{np.median(kept_all):.2f} ms** with the '
            f'kept model, {np.median(fresh_all):.2f} ms rebuilding it per fit (ratio '
            f'{np.median(kept_all) / np.median(fresh_all):.2f})\n\n'
            + markdown_table(['test point', 'window (s)', 'warm from a growing window',
                              'iterations', 'target met', 'kept model CPU (ms)',
                              'fresh model CPU (ms)', 'kept / fresh',
                              'live - cold offline (max σ)'], rows))
    command = 'python bench/final_fit_cpu.py' + (f' --bag {args.bag}' if args.bag else '')
    write_results('final_fit_cpu', 'Live final fit: CPU with the model kept per description',
                  body, command)
    print(body)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
