"""
Memory of ``rotor-id identify BAG --test-point all`` on a long multi-point bag: slices, not all.

The bag is bench/long_bag_memory.py's (1 kHz, four blades, Ω = 2π·15 rad/s, trimmed with noise,
the simulated stirring transient of the dynamic-wake model in its last 30 s), made by its
``write_hour_bag`` with the stirring node's phases added on ``/rotor/stirring`` (received
20 ms after their stamps): every ``--spacing-s`` a schedule that starts (TRIM) and ends half a
second later (RAMP_DOWN, before its window's end: aborted, not identified), and at the start of
the transient the schedule of the report's excitation (TRIM, CYCLIC_STEP, STIRRING, DONE at the
end), whose window (the report's t0 … t0 + 12 after the test point's first flap sample) is fitted.

Measured, each in a child process (peak memory as ``ru_maxrss`` of that child alone), in the
same run: ``rotor-id identify BAG --config RUN.yaml --test-point all --json --csv --quiet`` as
it is (a long bag read ``MULTI_POINT_SLICE_S`` at a time), and the same with the bag read
whole (``MULTI_POINT_SLICE_S`` set beyond the bag, which makes the reader take it all: the
peer). Their JSON results are compared.

Run: ``python bench/multi_point_bag_memory.py [--duration-s S] [--workdir DIR]``.
"""

import argparse
import json
import math
from pathlib import Path
import sys
import time

from common import markdown_table, run_in_workdir, say, write_results
from long_bag_memory import (bag_size_mb, DURATION_S, OMEGA, RATE_HZ, STAMP0, T0, TRANSIENT_S,
                             write_hour_bag)
from offline_throughput import run_measured

from rotor_id.commands.identify import MULTI_POINT_SLICE_S
from rotor_id.excitation import (PHASE_CYCLIC_STEP, PHASE_DONE, PHASE_RAMP_DOWN,
                                 PHASE_STIRRING, PHASE_TRIM)
from rotor_id.io.bag import message_with_defaults, typestore_with_custom_types

STIRRING_TOPIC = '/rotor/stirring'
LATE_NS = 20_000_000             # a phase is received 20 ms after its stamp
SAMPLE_NS = int(1e9 / RATE_HZ)


def run_description():
    """Return the run description: the report's window, s after a test point's start."""
    return (
        '# multi-point bag benchmark record (bench/multi_point_bag_memory.py)\n'
        'rotor: {blades: 4, advance_ratio: 0.0, flap_frequency: 1.2, tip_loss: 0.97}\n'
        'model: multiblade_wake\n'
        'unknowns: [A, AL_over_tau, inv_tau]\n'
        f'window_s: [{T0 / OMEGA:.6f}, {(T0 + 12.0) / OMEGA:.6f}]\n')


def stirring_phases(duration_s, spacing_s):
    """(stamp ns, phase) of the bag: aborted schedules, then the transient's."""
    phases = []
    for start in range(int(spacing_s), int(duration_s - TRANSIENT_S - 2), int(spacing_s)):
        phases += [(start, PHASE_TRIM), (start + 0.5, PHASE_RAMP_DOWN)]
    start = duration_s - TRANSIENT_S
    phases += [(start, PHASE_TRIM), (start + 2 * math.pi / OMEGA, PHASE_CYCLIC_STEP),
               (start + T0 / OMEGA, PHASE_STIRRING), (duration_s - 0.01, PHASE_DONE)]
    return [(STAMP0 + int(round(s * RATE_HZ)) * SAMPLE_NS, phase) for s, phase in phases]


def stirring_messages(store, phases):
    """(topic, receive ns, StirringCommand) of the phases."""
    out = []
    for stamp, phase in phases:
        header = store.types['std_msgs/msg/Header'](
            stamp=store.types['builtin_interfaces/msg/Time'](sec=stamp // 10**9,
                                                             nanosec=stamp % 10**9),
            frame_id='rotor')
        out.append((STIRRING_TOPIC, stamp + LATE_NS, message_with_defaults(
            store, 'rotor_id_msgs/msg/StirringCommand', header=header, phase=int(phase))))
    return out


def ensure_bag(workdir, duration_s, spacing_s):
    """Multi-point bag and run description in ``workdir``, made when missing; their paths."""
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    bag = workdir / f'multi_point_{duration_s:.0f}s_every_{spacing_s:.0f}s'
    config = workdir / 'multi_point.yaml'
    config.write_text(run_description())
    if (bag / 'metadata.yaml').exists():
        say(f'reusing {bag}')
        return bag, config
    say(f'writing the {duration_s:.0f} s multi-point bag')
    started = time.perf_counter()
    store = typestore_with_custom_types()
    write_hour_bag(bag, workdir, duration_s=duration_s, typestore=store,
                   extra=stirring_messages(store, stirring_phases(duration_s, spacing_s)))
    say(f'  wrote {bag} ({bag_size_mb(bag):.0f} MB) in {time.perf_counter() - started:.1f} s')
    return bag, config


def identify_all(bag, config, out, whole):
    """Run identify --test-point all in a child; (wall, RSS MB, CPU s, exit, JSON)."""
    argv = ['identify', str(bag), '--config', str(config), '--test-point', 'all', '--json',
            str(out), '--csv', str(out.with_suffix('.csv')), '--quiet']
    code = ('import sys; import rotor_id.commands.identify as m; '
            + ('m.MULTI_POINT_SLICE_S = 1e12; ' if whole else '')
            + f'from rotor_id.cli import main; sys.exit(main({argv!r}))')
    wall, rss, cpu, status, _ = run_measured([sys.executable, '-c', code])
    return wall, rss, cpu, status, json.loads(out.read_text())


def largest_difference(sliced, whole):
    """Largest relative difference of the estimates and σ (inf when the outcomes differ)."""
    worst = 0.0
    for a, b in zip(sliced, whole):
        if [a.get(k) for k in ('test_point', 'status', 'test_point_start_ns', 'n_samples')] != \
                [b.get(k) for k in ('test_point', 'status', 'test_point_start_ns', 'n_samples')]:
            return math.inf
        for name, p in b.get('parameters', {}).items():
            for key in ('value', 'std'):
                worst = max(worst, abs(a['parameters'][name][key] - p[key]) / abs(p[key]))
    return worst if len(sliced) == len(whole) else math.inf


def main(argv=None):
    """Make the bag if needed, measure, write bench/results/multi_point_bag_memory.md."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    parser.add_argument('--duration-s', type=float, default=DURATION_S,
                        help='length of the bag (default an hour: the whole read needs '
                             '~4 GB)')
    parser.add_argument('--spacing-s', type=float, default=300.0,
                        help='an aborted schedule every this many seconds before the last')
    parser.add_argument('--workdir', default=None,
                        help='where the bag is made and kept for the next run (default: a '
                             'fresh temporary directory, removed at the end)')
    parser.add_argument('--no-write', action='store_true')
    args = parser.parse_args(argv)
    return run_in_workdir(args.workdir, 'rotor_id_multi_point_bag_',
                          lambda workdir: _measure(args, workdir))


def _measure(args, workdir):
    bag, config = ensure_bag(workdir, args.duration_s, args.spacing_s)
    runs = {}
    for name, whole in (('sliced', False), ('whole', True)):
        say(f'identify --test-point all, bag read {name}')
        runs[name] = identify_all(bag, config, Path(workdir) / f'{name}.json', whole)
        wall, rss, cpu, code, _ = runs[name]
        say(f'  {wall:.2f} s wall ({cpu:.2f} s CPU), peak RSS {rss:.0f} MB, exit {code}')
    sliced, whole = runs['sliced'], runs['whole']
    results = sliced[4]
    fitted = [r for r in results if 'parameters' in r]
    rows = [
        ['bag', f'{args.duration_s:.0f} s at {RATE_HZ:.0f} Hz, 4 blades, 3 topics × '
                f'{int(args.duration_s * RATE_HZ)} JointState messages, MCAP '
                f'{bag_size_mb(bag):.0f} MB; {len(results)} test points '
                f'({len(fitted)} fitted, the others aborted by their schedule)'],
        [f'read {MULTI_POINT_SLICE_S:.0f} s at a time (the command)',
         f'**{sliced[1]:.0f} MB** peak RSS, {sliced[0]:.1f} s wall, {sliced[2]:.1f} s CPU, '
         f'exit {sliced[3]}'],
        ['read whole (peer)', f'{whole[1]:.0f} MB peak RSS, {whole[0]:.1f} s wall, '
                              f'{whole[2]:.1f} s CPU, exit {whole[3]}'],
        ['whole / sliced: peak memory, CPU time',
         f'**{whole[1] / sliced[1]:.1f}×**, {whole[2] / sliced[2]:.2f}×'],
        ['largest relative difference of the estimates and σ (same test points, statuses, '
         'starts and sample counts)', f'{largest_difference(results, whole[4]):.1e}'],
    ]
    fit = [[r['test_point'], f'{r["test_point_start_s"]:.3f}',
            ', '.join(f'{n} {v["value"]:.4f} ± {v["std"]:.4f}'
                      for n, v in r['parameters'].items()),
            'converged' if r['converged'] else r['message']] for r in fitted]
    body = ('## Result\n\n' + markdown_table(['quantity', 'value'], rows)
            + '\n\n## Fitted test points (truth A 0.5, AL_over_tau 0.25, inv_tau 0.125)\n\n'
            + markdown_table(['test point', 'start [s]', 'estimate ± σ', 'status'], fit)
            + '\n')
    if not args.no_write:
        write_results('multi_point_bag_memory', 'Memory of identify --test-point all on a long '
                      'multi-point bag', body, 'python bench/multi_point_bag_memory.py'
                      + ('' if args.duration_s == DURATION_S else
                         f' --duration-s {args.duration_s:.0f}'))
    print(body)
    return 0 if sliced[3] == whole[3] and largest_difference(results, whole[4]) < 1e-9 else 1


if __name__ == '__main__':
    sys.exit(main())
