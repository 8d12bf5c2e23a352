"""
Live benchmark of the five nodes: estimate latency and message loss (issue 3 / issue 7 item 3).

Runs plant (4 blades x 1 kHz), stirring input, identifier, state estimator and recorder as
separate processes on the wake case for ``--duration`` seconds of rotor time, and measures

* latency: from the moment the identifier takes the newest sample of each window it fits
  (growing windows and the final one) to the publication of that estimate (target <= 6.7 ms);
* loss: the recorder's message count per topic against what the plant, the stirring input and
  the state estimator published (their counts, printed when they stop).

Writes bench/results/live.md. The issue asks for a 10-minute run (``--duration 600``); on a
shared machine the simulated rotor runs slower than real time (it never runs ahead of the pitch
commands), so a long run takes correspondingly longer.

    python bench/live_latency.py --duration 20
"""

import argparse
import json
import os
from pathlib import Path
import time

from common import markdown_table, REPO_ROOT, say, write_results
import numpy as np
import yaml


def _counts(bag):
    meta = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    return {t['topic_metadata']['name']: t['message_count']
            for t in meta['topics_with_message_count']}


def run(duration, out):
    """Run the nodes; return a dict of measurements."""
    import rclpy
    from rclpy.signals import SignalHandlerOptions
    from rotor_id.commands.demo import case_files
    from rotor_id.nodes.common import SENSOR_QOS
    from rotor_id.nodes.processes import isolated_env, NodeProcesses
    from rotor_id.nodes.watch import RunWatcher
    from sensor_msgs.msg import JointState

    params_file, _, _ = case_files('wake')
    domain = 101 + int(time.time()) % 100
    env = isolated_env(domain, out / 'ros_log')
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    rclpy.init(domain_id=domain, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node('live_bench')
    estimates = []

    def on_message(kind, msg):
        if kind == 'estimate':
            estimates.append((time.monotonic(), msg))

    # this process subscribes to the azimuth only (the plant waits for 5 subscribers of it)
    watcher = RunWatcher(node, on_message=on_message)
    node.create_subscription(JointState, '/rotor/azimuth', lambda _: None, SENSOR_QOS)
    procs = NodeProcesses(env, out / 'logs')
    bag = out / 'bag'
    started = time.monotonic()
    try:
        procs.start('identifier', params_file)
        procs.start('state_estimator', params_file)
        procs.start('recorder', params_file, {'output': str(bag)})
        procs.start('stirring_input', params_file)
        procs.start('rotor_plant', params_file, {'duration_s': float(duration),
                                                 'wait_for_subscribers': 5})
        say(f'running {duration} s of rotor time (domain {domain})')
        done = watcher.spin_until(lambda: 'run complete' in procs.log('rotor_plant'),
                                  timeout=60.0 + 60.0 * duration, alive=lambda: not procs.dead())
        if not done:
            raise RuntimeError(f'the run did not complete: {procs.dead()}')
        # stop the last publisher of the run, then let the recorder catch up before stopping it
        procs.stop('stirring_input')
        recorded = []

        def settled():
            # the recorder's count grows only by /diagnostics (5 nodes, 1 Hz) once it caught up
            counts = [int(v.value) for s in watcher.diagnostics('recorder') for v in s.values
                      if v.key == 'messages']
            if counts and (not recorded or counts[-1] != recorded[-1]):
                recorded.append(counts[-1])
            steps = zip(recorded[-3:-1], recorded[-2:])
            return len(recorded) > 3 and all(b - a <= 10 for a, b in steps)
        watcher.spin_until(settled, 120.0)
    finally:
        wall = time.monotonic() - started
        codes = procs.stop_all()
        node.destroy_node()
        rclpy.try_shutdown()
    samples = int(procs.log('rotor_plant').split('run complete: ')[1].split()[0])
    commands = int(procs.log('stirring_input').split('published ')[1].split()[0])
    states = int(procs.log('state_estimator').split('published ')[1].split()[0])
    inside = procs.log('identifier').split('estimate latencies (ms): ')[1].splitlines()[0]
    latencies = [float(v) for v in inside.split()]
    log = procs.log('identifier')
    breakdown = json.loads(log.split('latency breakdown (ms): ')[1].splitlines()[0])
    threads = json.loads(log.split('thread times: ')[1].splitlines()[0])
    fits = [m.message for _, m in estimates]
    return {'samples': samples, 'bag': _counts(bag), 'codes': codes, 'wall_s': wall,
            'latency_ms': latencies, 'breakdown': breakdown, 'threads': threads,
            'load_after': os.getloadavg(), 'fits': fits, 'estimates': len(estimates),
            'commands_published': commands, 'states_published': states,
            'received': {k: len(v) for k, v in watcher.messages.items()}}


def main():
    """Run and write bench/results/live.md."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--duration', type=float, default=600.0,
                        help='rotor time to simulate (s); the issue asks for 600')
    parser.add_argument('--out', default=str(REPO_ROOT / 'out' / 'bench_live'))
    parser.add_argument('--results-name', default='live',
                        help='write bench/results/<name>.md (default: live)')
    args = parser.parse_args()
    out = Path(args.out) / time.strftime('%Y%m%d-%H%M%S')
    out.mkdir(parents=True)
    result = run(args.duration, out)
    bag = result['bag']
    rows = [
        ['/rotor/blade_flap', result['samples'], bag.get('/rotor/blade_flap', 0)],
        ['/rotor/blade_pitch', result['samples'], bag.get('/rotor/blade_pitch', 0)],
        ['/rotor/azimuth', result['samples'], bag.get('/rotor/azimuth', 0)],
        ['/rotor/pitch_command', result['commands_published'],
         bag.get('/rotor/pitch_command', 0)],
    ]
    rows.append(['/rotor_id/state', result['states_published'], bag.get('/rotor_id/state', 0)])
    lost = sum(max(0, int(r[1]) - int(r[2])) for r in rows)
    for topic, kind in (('/rotor_id/estimate', 'estimate'), ('/rotor_id/progress', 'progress'),
                        ('/rotor/stirring', 'stirring')):
        rows.append([f'{topic} (received by this process)', result['received'][kind],
                     bag.get(topic, 0)])
    lat = np.array(result['latency_ms'])
    lat_text = ('no estimate' if lat.size == 0 else
                f'{lat.size} estimates: median {np.median(lat):.1f} ms, max {lat.max():.1f} ms, '
                f'min {lat.min():.1f} ms (target <= 6.7 ms: '
                f'{"met" if lat.max() <= 6.7 else "NOT met"})')

    rate = result['samples'] / 1000.0 / result['wall_s']
    columns = ('total', 'queued', 'record', 'identify', 'gauss_newton', 'verdict', 'message',
               'publish', 'other', 'cpu', 'cpu_wait', 'gil_or_lock_wait')
    breakdown = [[b['kind'], f'{b["window_end_s"]:.4f}', b.get('iterations', '')]
                 + [f'{b.get(c, float("nan")):.1f}' for c in columns] + [b['samples_taken']]
                 for b in result['breakdown']]
    threads = result['threads']
    per_sample = threads['executor_cpu_s'] / max(threads['samples_taken'], 1) * 1e6
    body = (
        f'## Result\n\n'
        f'* rotor time simulated: {result["samples"] / 1000:.1f} s at 1 kHz x 4 blades '
        f'(requested {args.duration:g} s'
        f'{"" if args.duration >= 600 else "; the issue asks for 600 s: this is a shorter run"})\n'
        f'* wall time {result["wall_s"]:.1f} s: the rotor ran at {rate:.2f} x real time\n'
        f'* estimate latency in the identifier (newest sample of the window taken -> its '
        f'estimate published): {lat_text}\n'

        f'* estimates (window, convergence, fit time): {"; ".join(result["fits"])}\n'
        f'* messages lost by the recorder: {lost}\n'
        f'* exit codes: {result["codes"]}\n'
        f'* load average (1/5/15 min) at the end: '
        f'{" / ".join(f"{v:.2f}" for v in result["load_after"])}\n\n'
        + markdown_table(['topic', 'published', 'in the bag'], rows) + '\n'
        '\n## Where the latency goes\n\n'
        "Per published estimate, in ms (the identifier's own clocks). *total* runs from taking "
        'the newest sample of the window to publishing; *queued* is the wait for the worker '
        'thread (a running fit to finish or give way); *record* forms the Record under the '
        'buffer lock; *identify* is rotor_id.pipeline.identify, of which *Gauss-Newton* the '
        'iterations; *verdict* the data-length verdict (Cramér-Rao bound history when a target '
        'is not met); then the message and its publication; *other* is the rest (mostly '
        "taking the GIL back between stages). The worker's wall time from "
        'picking the request up to publishing splits into *on CPU*, *waiting for a CPU* (run '
        'queue: other processes) and *waiting for the GIL or the buffer lock* (the subscription '
        'callbacks of the same process); *samples* counts the sensor samples the node took '
        'meanwhile.\n\n'
        + markdown_table(['estimate', 'window end (s)', 'iterations', 'total', 'queued',
                          'record', 'identify', 'Gauss-Newton', 'verdict', 'message',
                          'publish', 'other', 'on CPU', 'waiting for a CPU',
                          'waiting for the GIL/lock', 'samples'], breakdown) + '\n\n'
        f'Identifier threads over the whole run ({threads["wall_s"]:.1f} s wall, '
        f'{threads["samples_taken"]} sensor samples taken): executor (subscriptions) '
        f'{threads["executor_cpu_s"]:.1f} s on CPU ({per_sample:.0f} µs per sample), '
        f'{threads["executor_cpu_wait_s"]:.1f} s waiting for a CPU; worker (fits) '
        f'{threads["worker_cpu_s"]:.2f} s on CPU, {threads["worker_cpu_wait_s"]:.2f} s waiting '
        f'for a CPU.\n')
    command = f'python bench/live_latency.py --duration {args.duration:g}'
    if args.results_name != 'live':
        command += f' --results-name {args.results_name}'
    path = write_results(args.results_name,
                         'Live nodes: estimate latency and recorder completeness', body, command)
    print(body)
    say(f'wrote {path}')
    return 0 if lost == 0 and all(c == 0 for c in result['codes'].values()) else 1


if __name__ == '__main__':
    raise SystemExit(main())
