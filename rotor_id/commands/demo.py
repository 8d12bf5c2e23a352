"""
``rotor-id demo [--case wake|multiblade|single_blade]``: the five nodes, live and offline.

Starts the installed nodes as separate processes on their own DDS domain (loopback only) with
config/nodes_<case>.yaml: the simulated rotor (plant), the stirring input, the identifier, the
Kalman state estimator and the recorder. Prints the estimates as they arrive (window length, each
parameter ± its Cramér-Rao σ), then a table of identified vs true values, the bag, and figures;
then identifies the recorded bag offline with the same pipeline and shows that both agree.
Ctrl-C stops the children (the recorder last, so the bag is complete) and nothing is left running.
"""

import argparse
import math
import os
from pathlib import Path
import signal
import sys
import time
from typing import Any, Mapping, TextIO, TYPE_CHECKING

import numpy as np
import yaml

if TYPE_CHECKING:
    from rotor_id.nodes.watch import RunWatcher

CASES = ('wake', 'multiblade', 'single_blade')
#: Rotor time simulated after the identification window (s).
MARGIN_S = 0.05
#: how long the demo waits to hear the nodes' publishers before it starts the rotor
DISCOVERY_TIMEOUT_S = 30.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``rotor-id demo``."""
    parser.add_argument('--case', choices=CASES, default='wake',
                        help='report case: mu = 0 dynamic wake (default), mu = 0.4 multiblade '
                             'or single blade')
    parser.add_argument('--out', default='out/demo', help='directory for bag, logs, figures')
    parser.add_argument('--storage', choices=('mcap', 'sqlite3'), default='mcap')
    parser.add_argument('--domain-id', type=int, default=None,
                        help='ROS_DOMAIN_ID of the run (default: 101 + pid mod 100)')
    parser.add_argument('--timeout', type=float, default=240.0,
                        help='give up if no final estimate after this many seconds')
    parser.add_argument('--seed', type=int, default=None, help='noise seed of the plant')


def case_files(case: str) -> tuple[Path, Path, dict[str, float]]:
    """(node parameter file, run description, true parameter values) of a demo case."""
    from rotor_id.nodes.common import resolve_config
    params_file = resolve_config(f'nodes_{case}.yaml')
    params = yaml.safe_load(params_file.read_text())
    plant = params['/**/rotor_plant']['ros__parameters']
    description = resolve_config(params['/**/identifier']['ros__parameters']['run_description'])
    if plant['model'] == 'multiblade_wake':
        truth = {k: plant[k] for k in ('A', 'AL_over_tau', 'inv_tau')}
    else:
        truth = {'gamma': plant['gamma'], 'theta0': plant['initial_collective_rad']}
    return params_file, description, truth


def _estimate_line(msg, t_start):
    values = '  '.join(f'{n} = {v:.4f} ± {s:.4f}'
                       for n, v, s in zip(msg.names, msg.values, msg.std))
    kind = {0: 'provisional', 1: 'final', 2: 'FAILED', 3: 'final (iteration limit)',
            4: 'INCOMPLETE window', 5: 'ABORTED'}[msg.status]
    verdict = ('targets met' if msg.target_met else
               'more data needed: unknown' if msg.additional_data_s < 0 else
               f'≈{msg.additional_data_s * 1e3:.0f} ms more data needed')
    if msg.status in (2, 5):
        return f'  [{time.monotonic() - t_start:6.1f} s] estimate {kind}: {msg.message}'
    return (f'  [{time.monotonic() - t_start:6.1f} s] window {msg.window_s * 1e3:5.1f} ms  '
            f'{values}  ({kind}; {verdict})')


def run_live(case: str, out: Path, storage: str, domain_id: int, timeout: float,
             seed: int | None = None, stream: TextIO = sys.stdout
             ) -> tuple[Any, 'RunWatcher', Path, dict[str, int | None]]:
    """Run the five nodes; return (final ParameterEstimate, all estimates, bag path, codes)."""
    import rclpy
    from rclpy.signals import SignalHandlerOptions
    from rotor_id.nodes.processes import isolated_env, NodeProcesses
    from rotor_id.nodes.watch import RESULT_KINDS, RunWatcher
    from rotor_id.io.run_description import load_run_description

    params_file, description_path, _ = case_files(case)
    description = load_run_description(description_path)
    bag = out / f'bag_{case}_{time.strftime("%Y%m%d-%H%M%S")}'
    env = isolated_env(domain_id, out / 'logs' / 'ros')
    os.environ.update({k: env[k] for k in ('ROS_DOMAIN_ID', 'ROS_AUTOMATIC_DISCOVERY_RANGE',
                                           'FASTRTPS_DEFAULT_PROFILES_FILE') if k in env})
    t_start = time.monotonic()
    phases = {}

    def show(kind, msg):
        if kind == 'estimate':
            print(_estimate_line(msg, t_start), file=stream, flush=True)
        elif kind == 'stirring' and msg.phase == 3 and 0 not in phases:
            if 'holding' not in phases:        # before the start: the trim held while active
                phases['holding'] = True
                print(f'  [{time.monotonic() - t_start:6.1f} s] stirring input active, holding '
                      'trim until ~/start', file=stream, flush=True)
        elif kind == 'stirring' and msg.phase not in phases:
            phases[msg.phase] = True
            label = {0: 'rotor in trim (collective only)', 1: 'lateral cyclic step',
                     2: 'stirring started', 3: 'stirring done, back at trim',
                     4: 'stirring ended: cyclic ramping back to trim'}.get(msg.phase, 'phase '
                                                                           f'{msg.phase}')
            print(f'  [{time.monotonic() - t_start:6.1f} s] {label}', file=stream, flush=True)

    # Ctrl-C sets a flag that the spin loop checks: a KeyboardInterrupt raised at an arbitrary
    # point can land inside rclpy's message conversion and come out as a RuntimeError
    interrupted = []
    previous = signal.signal(signal.SIGINT, lambda *_: interrupted.append(True))
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node('rotor_id_demo')
    watcher = RunWatcher(node, on_message=show)
    plant_params = {'duration_s': description.window_s[1] + MARGIN_S}
    if seed is not None:
        plant_params['seed'] = seed
    procs = NodeProcesses(env, out / 'logs')
    try:
        print(f'starting the five nodes (ROS_DOMAIN_ID {domain_id}, logs in {out / "logs"}) '
              f'with {params_file.name}', file=stream, flush=True)
        procs.start('identifier', params_file)
        procs.start('state_estimator', params_file)
        procs.start('recorder', params_file, {'output': str(bag), 'storage': storage})
        procs.start('stirring_input', params_file)
        # the rotor starts once this display hears the nodes' outputs: otherwise a slow
        # discovery can hide the first estimates (or the whole short run) from it
        late = watcher.wait_for_publishers(RESULT_KINDS, DISCOVERY_TIMEOUT_S,
                                           alive=lambda: not procs.dead() and not interrupted)
        if late and not procs.dead() and not interrupted:
            print(f'  note: no {", ".join(late)} publisher heard within '
                  f'{DISCOVERY_TIMEOUT_S:.0f} s; starting the rotor anyway (the recorder '
                  'records what it hears)', file=stream, flush=True)
        # the stirring node holds trim until asked: the test point starts with the rotor
        answer = watcher.trigger('/stirring_input/start', DISCOVERY_TIMEOUT_S,
                                 alive=lambda: not procs.dead() and not interrupted)
        if answer is not None and answer.success:
            print(f'  stirring_input: {answer.message}', file=stream, flush=True)
        elif not procs.dead() and not interrupted:
            print('  note: stirring_input did not accept ~/start ('
                  + (answer.message if answer is not None else 'no answer') + '): the rotor '
                  'will hold trim and nothing will be identified', file=stream, flush=True)
        procs.start('rotor_plant', params_file, plant_params)
        print(f'identifying {", ".join(description.unknowns)} ({description.model}) over the '
              f'window {description.window_s[0]:.4f}-{description.window_s[1]:.4f} s after the '
              'first flap sample:', file=stream, flush=True)
        ok = watcher.spin_until(lambda: watcher.final_estimate() is not None, timeout,
                                alive=lambda: not procs.dead() and not interrupted)
        if interrupted:
            raise KeyboardInterrupt
        if not ok:
            dead = procs.dead()
            reason = (f'{", ".join(dead)} exited ({dead}); see {out / "logs"}' if dead
                      else f'no final estimate within {timeout:.0f} s; see {out / "logs"}')
            raise RuntimeError(f'the live run failed: {reason}')
        # a few more state estimates after the final parameters (the iterated loop)
        n_states = len(watcher.messages['state'])
        watcher.spin_until(lambda: len(watcher.messages['state']) > n_states, 3.0,
                           alive=lambda: not interrupted)
        if interrupted:
            raise KeyboardInterrupt
    finally:
        print('stopping the nodes (the recorder last)...', file=stream, flush=True)
        codes = procs.stop_all()
        node.destroy_node()
        rclpy.try_shutdown()
        signal.signal(signal.SIGINT, previous)
    return watcher.final_estimate(), watcher, bag, codes


def convergence_figure(watcher: 'RunWatcher', truth: Mapping[str, float],
                       path: str | os.PathLike, title: str) -> None:
    """Estimates ± σ against the window length, with the true values."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    msgs = [m for m in watcher.messages['estimate'] if m.status not in (2, 5)]
    names = list(msgs[-1].names)
    fig, axes = plt.subplots(len(names), 1, figsize=(7, 1.9 * len(names)), sharex=True)
    for i, (ax, name) in enumerate(zip(np.atleast_1d(axes), names)):
        w = np.array([m.window_s * 1e3 for m in msgs])
        v = np.array([m.values[i] for m in msgs])
        s = np.array([m.std[i] for m in msgs])
        ax.errorbar(w, v, yerr=s, fmt='o', capsize=3, label='estimate ± σ (CRB)')
        ax.axhline(truth[name], color='k', lw=0.8, ls='--', label='true')
        ax.set_ylabel(name)
    np.atleast_1d(axes)[0].legend(fontsize=8)
    np.atleast_1d(axes)[-1].set_xlabel('window length [ms]')
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run(args: argparse.Namespace) -> int:
    """Run the demo; exit 0 when every estimate is within 3σ and live and offline agree."""
    from rotor_id import pipeline
    from rotor_id.commands.identify import format_table, load_inputs, plot_fit
    from rotor_id_msgs.msg import ParameterEstimate
    aborted, failed = ParameterEstimate.STATUS_ABORTED, ParameterEstimate.STATUS_FAILED

    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    domain_id = args.domain_id if args.domain_id is not None else 101 + os.getpid() % 100
    _, description_path, truth = case_files(args.case)
    started = time.monotonic()
    for attempt in (1, 2):
        try:
            final, watcher, bag, codes = run_live(args.case, out, args.storage, domain_id,
                                                  args.timeout, args.seed)
        except RuntimeError as exc:
            print(f'rotor-id demo: {exc}', file=sys.stderr)
            return 1
        print(f'nodes stopped (exit codes {codes}); bag: {bag}')
        if final.status != aborted or attempt == 2:
            break
        # the stirring node stops on a stale azimuth when the simulated rotor falls behind
        # the clock: a machine too busy for the five nodes at that moment
        print(f'rotor-id demo: {final.message}; the simulated rotor fell behind the clock '
              f'(load {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores): running the test '
              'point once more', file=sys.stderr)
    if final.status in (failed, aborted):   # no values
        hint = ('this machine could not run the five nodes in real time; run the demo again '
                'when it is quieter' if final.status == aborted else
                f'the node logs are in {out / "logs"}')
        print(f'rotor-id demo: the live identification gave no values: {final.message}; {hint}',
              file=sys.stderr)
        return 1

    description, record = load_inputs(bag, description_path)
    offline = pipeline.identify(record, description)
    off = offline.as_json()['parameters']
    print(f'\noffline identification of the recorded bag ({len(record)} samples):')
    print(format_table(offline))
    rows, ok_truth, ok_agree = [], True, True
    print(f'\n{"parameter":<12} {"true":>10} {"live":>10} {"± σ":>9} {"(live−true)/σ":>14} '
          f'{"offline":>10} {"± σ":>9} {"(live−offline)/σ":>17}')
    for name, value, std in zip(final.names, final.values, final.std):
        z_true = (value - truth[name]) / std
        z_off = (value - off[name]['value']) / std
        ok_truth &= abs(z_true) <= 3.0
        ok_agree &= abs(z_off) <= 0.2
        rows.append((name, z_true, z_off))
        print(f'{name:<12} {truth[name]:10.5f} {value:10.5f} {std:9.5f} {z_true:14.2f} '
              f'{off[name]["value"]:10.5f} {off[name]["std"]:9.5f} {z_off:17.4f}')
    fit_png = out / f'demo_{args.case}_fit.png'
    conv_png = out / f'demo_{args.case}_convergence.png'
    plot_fit(offline, record, fit_png, title=f'{bag.name}: measured vs fitted (offline)')
    convergence_figure(watcher, truth, conv_png,
                       f'{args.case}: live estimates as the window grows')
    n_states = len(watcher.messages['state'])
    print(f'\nlive: {len(watcher.messages["estimate"])} estimates, '
          f'{len(watcher.messages["progress"])} Gauss-Newton progress messages, {n_states} state '
          f'estimates; final: {final.message}')
    print(f'bag: {bag}\nfigures: {fit_png}\n         {conv_png}')
    print(f'every live estimate within 3σ of the truth: {"yes" if ok_truth else "NO"}; live and '
          f'offline agree (within 0.2σ): {"yes" if ok_agree else "NO"}  '
          f'({time.monotonic() - started:.0f} s)')
    return 0 if ok_truth and ok_agree and math.isfinite(final.std[0]) else 1
