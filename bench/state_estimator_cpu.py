"""
CPU of the state estimator node per second of a 1 kHz stream, without the rest of the graph.

Builds the node of the demo's wake case (``config/nodes_wake.yaml``: 4 blades, 1 kHz, the
multiblade wake model) in this process, and replays a simulated run (the plant's stepper under
the stirring schedule) through the node's own batch intake and timer tick: each tick is given
the serialized JointState messages of ``update_period_s`` of flap, pitch and azimuth, as its
sensor poller would take them. The CPU time of this process over the ticks, per second of
stream, is the node's share of one core at 1 kHz (the DDS reception itself excluded: it is the
same before and after a change of the filter), for the numpy filter (``ROTOR_ID_KERNELS=numpy``)
and the compiled one in the same run. ``--profile`` prints the cProfile of the ticks.

    python bench/state_estimator_cpu.py --seconds 10
"""

import argparse
import cProfile
import math
import os
import pstats
import time

from common import markdown_table, say, write_results
import numpy as np
import yaml

NS = 1_000_000_000


def stream(seconds, period_s, params):
    """Batches of serialized (flap, pitch, azimuth) JointStates, one per tick."""
    from rclpy.serialization import serialize_message
    from rotor_id.nodes.live import PlantStepper
    from rotor_id.physics.models import RotorConstants
    from rotor_id.physics.stirring import StirringSchedule
    from sensor_msgs.msg import JointState

    plant = params['/**/rotor_plant']['ros__parameters']
    stir = params['/**/stirring_input']['ros__parameters']
    omega, rate = plant['rotor_speed_rad_s'], plant['sample_rate_hz']
    stepper = PlantStepper('multiblade_wake', RotorConstants(advance_ratio=0.0),
                           {k: plant[k] for k in ('A', 'AL_over_tau', 'inv_tau')}, omega, rate,
                           plant['initial_collective_rad'], plant['flap_noise_std_rad'],
                           plant['pitch_noise_std_rad'], seed=1)
    # stirring from the start of the replay, so the filter sees a moving input throughout
    schedule = StirringSchedule(stir['collective_rad'], stir['amplitude_rad'], stir['omegadot'],
                                2.0, 1.0)
    per_tick = int(round(period_s * rate))
    blades = [f'blade_{k}' for k in range(1, 5)]

    def message(stamp, names, position, velocity=()):
        msg = JointState()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, NS)
        msg.name, msg.position, msg.velocity = names, position, list(velocity)
        return serialize_message(msg)

    sample = 0
    batches = []
    for _ in range(int(seconds / period_s)):
        for k in range(per_tick):       # commands at the sample rate (the stirring node's 200 Hz
            t_cmd = stepper.t + (k + 1) * stepper.step     # would do as well)
            stepper.command(t_cmd, schedule(np.array([t_cmd]))[0])
        t, flap, pitch = stepper.advance(per_tick)
        stamps = [(sample + k + 1) * NS // int(rate) for k in range(per_tick)]
        sample += per_tick
        batches.append((
            [message(s, blades, f.tolist()) for s, f in zip(stamps, flap)],
            [message(s, blades, p.tolist()) for s, p in zip(stamps, pitch)],
            [message(s, ['rotor'], [math.fmod(ti, 2 * math.pi)], [omega])
             for s, ti in zip(stamps, t)]))
    return batches


def run(seconds=10.0, profile=False, publish_to=None):
    """CPU s of the node's ticks over ``seconds`` of stream, and the messages it published."""
    import rclpy
    from rclpy.parameter import Parameter
    from rotor_id.nodes.common import resolve_config
    from rotor_id.nodes.state_estimator import StateEstimator

    params_file = resolve_config('nodes_wake.yaml')
    params = yaml.safe_load(params_file.read_text())
    own = params['/**/state_estimator']['ros__parameters']
    description = resolve_config(own['run_description'])
    owned_context = not rclpy.ok()
    if owned_context:
        rclpy.init()
    node = StateEstimator(parameter_overrides=[
        Parameter('run_description', value=str(description)),
        Parameter('flap_noise_std_rad', value=own['flap_noise_std_rad']),
        Parameter('process_noise_std', value=own['process_noise_std'])])
    try:
        period = node.d['update_period_s']
        batches = stream(seconds, period, params)
        published = []
        publish = node.pub_state.publish

        def keep(msg):
            published.append(msg)
            publish(msg)
        node.pub_state.publish = keep
        feed = iter(batches)

        def poll():
            flap, pitch, azimuth = next(feed)
            node._take_batch('azimuth', None, None, azimuth)
            node._take_batch('blade_pitch', node.pitch, node.pitch_joints, pitch)
            node._take_batch('blade_flap', node.flap, node.flap_joints, flap)
        node.poller.poll = poll
        profiler = cProfile.Profile() if profile else None
        cpu = time.process_time()
        if profiler:
            profiler.enable()
        for _ in batches:
            node.tick()
        if profiler:
            profiler.disable()
        cpu = time.process_time() - cpu
        if profiler:
            pstats.Stats(profiler).sort_stats('cumulative').print_stats(35)
        return cpu, published, len(batches) * period
    finally:
        node.destroy_node()
        if owned_context:
            rclpy.shutdown()


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--seconds', type=float, default=10.0, help='stream length (s)')
    parser.add_argument('--repeats', type=int, default=5, help='runs of each filter path')
    parser.add_argument('--profile', action='store_true', help='print the cProfile of the ticks')
    parser.add_argument('--no-write', action='store_true', help='print only (a smoke run)')
    args = parser.parse_args()
    from rotor_id.estimation import kernels
    # the numpy path first: once numba's kernels are loaded this process keeps them
    cpu = {}
    states = {}
    for mode in ('numpy', 'numba'):
        os.environ['ROTOR_ID_KERNELS'] = mode
        for _ in range(args.repeats):
            say(f'{mode}: {args.seconds:g} s of stream')
            used, published, span = run(args.seconds, args.profile)
            cpu.setdefault(mode, []).append(used / span)
            states[mode] = published
        if mode == 'numba' and not kernels.status()['loaded']:
            raise SystemExit(f'numba kernels not loaded: {kernels.status()["error"]}')
    load = os.getloadavg()
    x = {m: np.array([msg.values for msg in states[m]]) for m in states}
    P = {m: np.array([msg.covariance for msg in states[m]]) for m in states}
    n = x['numpy'].shape[1]
    std = np.sqrt(np.einsum('kii->ki', P['numpy'].reshape(-1, n, n)))
    dx = np.max(np.abs(x['numba'] - x['numpy']) / std)
    dP = np.max(np.abs(P['numba'] - P['numpy']).reshape(-1, n, n) /
                (std[:, :, None] * std[:, None, :]))
    rows = [[mode, f'{100 * min(cpu[mode]):.1f}', f'{100 * float(np.median(cpu[mode])):.1f}',
             f'{100 * max(cpu[mode]):.1f}'] for mode in ('numpy', 'numba')]
    ratio = float(np.median(cpu['numba']) / np.median(cpu['numpy']))
    body = (f"{args.seconds:g} s of the wake case (4 blades, 1 kHz) through the node's batch "
            f'intake and tick, {args.repeats} runs of each filter path, CPU time of this '
            'process over the ticks as % of one core (real time: one stream second per '
            'second). The numpy runs come first, then the compiled ones (not interleaved: '
            'once loaded, the kernels stay in the process).\n\n'
            + markdown_table(['filter path', 'min %', 'median %', 'max %'], rows)
            + f'\n\n* compiled / numpy median CPU: **{ratio:.2f}**\n'
            f'* {len(states["numba"])} states published per run; largest difference between '
            f'the paths: state {dx:.1e} of its σ, covariance {dP:.1e} of σ_i σ_j\n'
            f'* load average after: {load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f}\n')
    print(body)
    if not args.no_write:
        write_results('state_estimator_cpu', 'State estimator CPU per second of a 1 kHz stream',
                      body, 'python bench/state_estimator_cpu.py')


if __name__ == '__main__':
    main()
