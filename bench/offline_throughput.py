"""
``rotor-id identify`` on a 10-minute, 1 kHz, 4-blade bag.

The bag is made once (and reused from ``--workdir``): the dynamic-wake model (μ = 0, true
A = 0.5, AL/τ = 0.25, 1/τ = 0.125) is simulated with the library simulator over 10 minutes at
Ω = 2π·15 rad/s, sampled at 1 kHz; the rotor is trimmed at collective pitch, the 1.5° lateral
cyclic is stepped on after one revolution, stirring starts 70 units of t later (report law for
12 units, then a constant stirring rate, :class:`common.SustainedStirring`); per-blade flap
(:mod:`rotor_id.physics.blades`, 0.1° noise) and pitch (0.01° noise) are written with
:func:`rotor_id.io.bag.write_record_bag` (MCAP), 3 topics × 600 000 JointState messages. The run
description identifies (A, AL/τ, 1/τ) over the report's window t0 … t0 + 12 (like
shared/recordings/id_wake_progressing.yaml).

Measured: wall time of the complete command in a child process (interpreter start, imports,
bag reading, the multi-start grid and the fit, JSON), as a multiple of the 600 s recorded
(target ≥ 200×); peak memory as ``ru_maxrss`` of that child alone (a small wrapper process runs
it, so no other child of this script counts). Where the time goes: the same command run
in-process, split into reading the bag and identifying, and a cProfile of the whole.

Run: ``python bench/offline_throughput.py [--repeat N] [--workdir DIR]``.
"""

import argparse
import cProfile
import io
import json
import math
from pathlib import Path
import pstats
import struct
import subprocess
import sys
import time

from common import (fmt_time, markdown_table, REPO_ROOT, run_in_workdir, say,
                    SustainedStirring, write_results)
import numpy as np

from rotor_id.estimation.simulate import simulate
from rotor_id.io.bag import DEFAULT_TOPICS
from rotor_id.physics.blades import blade_flap_from_multiblade_state
from rotor_id.physics.models import MultibladeWake, RotorConstants
from rotor_id.physics.stirring import blade_pitch_from_multiblade, StirringSchedule

DURATION_S = 600.0
RATE_HZ = 1000.0
OMEGA = 2.0 * math.pi * 15.0
TRUTH = {'A': 0.5, 'AL_over_tau': 0.25, 'inv_tau': 0.125}
FLAP_NOISE_DEG = 0.1
PITCH_NOISE_DEG = 0.01
T_STEP = 2.0 * math.pi           # lateral cyclic one revolution after the start
T0 = T_STEP + 70.0               # stirring start (report: 70 at μ = 0)
TARGET = 200.0

RUN_DESCRIPTION = f"""\
# 10-minute 1 kHz benchmark record (bench/offline_throughput.py)
rotor:
  blades: 4
  advance_ratio: 0.0
  flap_frequency: 1.2
  tip_loss: 0.97
topics:
  blade_pitch: /rotor/blade_pitch
  blade_flap: /rotor/blade_flap
  azimuth: /rotor/azimuth
model: multiblade_wake
unknowns: [A, AL_over_tau, inv_tau]
window_s: [{T0 / OMEGA:.6f}, {(T0 + 12.0) / OMEGA:.6f}]
"""

#: Runs the command given as arguments; prints ru_maxrss (kB), user and system CPU s of it last.
_MAXRSS_WRAPPER = ('import resource, subprocess, sys\n'
                   'code = subprocess.run(sys.argv[1:]).returncode\n'
                   'r = resource.getrusage(resource.RUSAGE_CHILDREN)\n'
                   'print(r.ru_maxrss, r.ru_utime, r.ru_stime)\n'
                   'sys.exit(code)\n')


def make_record(seed=6):
    """Simulate the 10-minute 4-blade record (rotor_id.io.record.Record, radians)."""
    from rotor_id.io.record import Record
    n = int(round(DURATION_S * RATE_HZ))
    time_s = np.arange(n) / RATE_HZ
    t = OMEGA * time_s
    model = MultibladeWake(RotorConstants(advance_ratio=0.0))
    p = model.parameter_vector(TRUTH)
    schedule = StirringSchedule(collective=math.radians(2.0), amplitude=math.radians(1.5),
                                t0=T0, t_step=T_STEP)
    inputs = SustainedStirring(schedule, T0 + 12.0)
    sim = simulate(model, p, inputs, t, np.zeros(model.n_states))
    coning = model.coning(p, schedule.collective)                      # hover, no inflow
    rng = np.random.default_rng(seed)
    flap = blade_flap_from_multiblade_state(model, t, sim.x, coning=coning)
    flap = flap + math.radians(FLAP_NOISE_DEG) * rng.standard_normal(flap.shape)
    pitch = blade_pitch_from_multiblade(t, inputs(t), 4)
    pitch = pitch + math.radians(PITCH_NOISE_DEG) * rng.standard_normal(pitch.shape)
    return Record(time_s=time_s, t=t, rotor_speed_rad_s=np.full(n, OMEGA), blade_flap=flap,
                  blade_pitch=pitch, blade_names=[f'blade_{k}' for k in range(1, 5)],
                  source='bench/offline_throughput.py', stamp0_ns=1_700_000_000_000_000_000)


def ensure_bag(workdir):
    """Bag directory and run description in ``workdir``, made when missing; their paths."""
    from rotor_id.io.bag import write_record_bag
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    bag = workdir / 'wake_10min_1khz'
    config = workdir / 'wake_10min_1khz.yaml'
    config.write_text(RUN_DESCRIPTION)
    if (bag / 'metadata.yaml').exists():
        say(f'reusing {bag}')
        return bag, config
    say('simulating the 10-minute record (600 000 samples, 4 blades)')
    started = time.perf_counter()
    record = make_record()
    say(f'  simulated in {time.perf_counter() - started:.1f} s; writing the MCAP bag')
    started = time.perf_counter()
    write_record_bag(bag, record, storage='mcap')
    say(f'  wrote {bag} in {time.perf_counter() - started:.1f} s')
    return bag, config


def bag_size_mb(bag):
    """Total size of the bag directory, MB."""
    return sum(f.stat().st_size for f in Path(bag).rglob('*') if f.is_file()) / 1e6


def run_measured(command):
    """Run ``command`` in a child; return (wall s, peak RSS MB, CPU s, exit code, stdout)."""
    started = time.perf_counter()
    proc = subprocess.run([sys.executable, '-c', _MAXRSS_WRAPPER] + command,
                          capture_output=True, text=True)
    wall = time.perf_counter() - started
    lines = proc.stdout.strip().splitlines()
    if proc.returncode not in (0, 1) or not lines:
        raise RuntimeError(f'{" ".join(command)} failed ({proc.returncode}):\n{proc.stderr}')
    rss_kb, utime, stime = lines[-1].split()
    return wall, int(rss_kb) / 1024.0, float(utime) + float(stime), proc.returncode, lines


def run_child(bag, config, json_out):
    """Run ``rotor-id identify`` in a child; return (wall s, peak RSS MB, CPU s, exit code)."""
    wall, rss, cpu, code, _ = run_measured(
        [str(REPO_ROOT / 'rotor-id'), 'identify', str(bag), '--config', str(config),
         '--json', str(json_out), '--quiet'])
    return wall, rss, cpu, code


def import_costs():
    """Start-up of ``rotor-id identify --help`` and of importing the identify command alone."""
    cli = run_measured([str(REPO_ROOT / 'rotor-id'), 'identify', '--help'])
    alone = run_measured([sys.executable, '-c', 'import rotor_id.commands.identify'])
    return {'cli': cli[:3], 'identify_module': alone[:3]}


def reading_memory(bag, config):
    """
    Peak RSS (MB) of children that only read the bag.

    The product reading the window (as the command does), the product reading every message
    (``window_s`` None), and the floor (every message).
    """
    product = run_measured([sys.executable, '-c',
                            'from rotor_id.commands.identify import load_inputs; '
                            f'load_inputs({str(bag)!r}, {str(config)!r})'])
    whole = run_measured([sys.executable, '-c',
                          'from rotor_id.io.bag import read_record; '
                          'from rotor_id.io.run_description import load_run_description; '
                          f'd = load_run_description({str(config)!r}); '
                          f'read_record({str(bag)!r}, **dict(d.record_options(), '
                          'window_s=None))'])
    mcap = next(Path(bag).glob('*.mcap'))
    floor = run_measured([sys.executable, '-c',
                          f'import sys; sys.path.insert(0, {str(Path(__file__).parent)!r}); '
                          'from offline_throughput import vectorised_read_floor; '
                          f'vectorised_read_floor({str(mcap)!r}, '
                          f'{set(DEFAULT_TOPICS.values())!r})'])
    return product[1], whole[1], floor[1]


def vectorised_read_floor(mcap_file, topics):
    """
    Read the three topics of a healthy MCAP without a per-message Python step (a floor).

    A measurement prototype, not the product's reader (that is :func:`rotor_id.io.bag.
    read_record`): it walks the file's records (chunks and their MessageIndex records, MCAP
    spec), decompresses each chunk, gathers the message bodies of each channel through the
    index offsets as one (n, size) byte matrix, and decodes it with the project's CDR layout
    functions. It assumes equal-size messages per channel (true here) and skips every check
    the real reader makes. Returns {topic: (stamps_ns, position)} and the seconds it took.
    """
    from backports import zstd
    import lz4.frame
    from rotor_id.io.jointstate_cdr import _stamps, _values, parse_layout
    started = time.perf_counter()
    data = Path(mcap_file).read_bytes()
    head = struct.Struct('<BQ')
    pos, chunk, channels, rows = 8, None, {}, {}
    while pos + 9 <= len(data):
        op, length = head.unpack_from(data, pos)
        body = pos + 9
        if op == 0x04:                                   # Channel: id, schema, topic
            cid, _ = struct.unpack_from('<HH', data, body)
            n = struct.unpack_from('<I', data, body + 4)[0]
            channels[cid] = data[body + 8:body + 8 + n].decode()
        elif op == 0x06:                                 # Chunk: decompress its records
            n = struct.unpack_from('<I', data, body + 28)[0]
            compression = data[body + 32:body + 32 + n].decode()
            size = struct.unpack_from('<Q', data, body + 32 + n)[0]
            payload = data[body + 40 + n:body + 40 + n + size]
            if compression == 'zstd':
                payload = zstd.decompress(payload)
            elif compression == 'lz4':
                payload = lz4.frame.decompress(payload)
            chunk = np.frombuffer(payload, dtype=np.uint8)
        elif op == 0x07 and chunk is not None:           # MessageIndex of the last chunk
            cid = struct.unpack_from('<H', data, body)[0]
            n = struct.unpack_from('<I', data, body + 2)[0] // 16
            offsets = np.frombuffer(data, dtype='<u8', count=2 * n,
                                    offset=body + 6).reshape(n, 2)[:, 1].astype(np.int64)
            record = chunk[(offsets[:1] + 1)[:, None] + np.arange(8)].view('<u8')[0, 0]
            start = offsets + 9 + 22                     # opcode, length, message header
            width = int(record) - 22
            steps = np.diff(start)
            if n > 1 and np.all(steps == steps[0]):     # evenly interleaved: a strided view
                part = np.lib.stride_tricks.as_strided(
                    chunk[start[0]:], shape=(n, width), strides=(int(steps[0]), 1))
            else:
                part = chunk[start[:, None] + np.arange(width)]
            rows.setdefault(cid, []).append(part)
        elif op == 0x0F:                                 # DataEnd: summary follows
            pass
        pos = body + length
    out = {}
    for cid, parts in rows.items():
        topic = channels.get(cid)
        if topic not in topics:
            continue
        matrix = np.concatenate(parts)
        layout = parse_layout(matrix[0].tobytes())
        out[topic] = (_stamps(matrix, layout.little), _values(matrix, layout, 'position'))
    return out, time.perf_counter() - started


def in_process_phases(bag, config):
    """
    Time the command's two phases in this process, and profile the whole.

    Also times identify on the record cut to the window ± 0.5 s: the same fit without the
    full-length pitch table behind the input interpolation.
    """
    from rotor_id import pipeline
    from rotor_id.commands.identify import load_inputs
    from rotor_id.io.bag import read_record
    started = time.perf_counter()
    description, record = load_inputs(bag, config)
    t_read = time.perf_counter() - started
    started = time.perf_counter()
    read_record(bag, **dict(description.record_options(), window_s=None))
    t_read_all = time.perf_counter() - started
    started = time.perf_counter()
    result = pipeline.identify(record, description)
    t_fit = time.perf_counter() - started
    w0, w1 = description.window_s
    short = record.window(max(w0 - 0.5, 0.0), w1 + 0.5)
    started = time.perf_counter()
    pipeline.identify(short, description)
    t_fit_short = time.perf_counter() - started
    profiler = cProfile.Profile()
    profiler.enable()
    description, record = load_inputs(bag, config)
    pipeline.identify(record, description)
    profiler.disable()
    stream = io.StringIO()
    pstats.Stats(profiler, stream=stream).sort_stats('cumulative').print_stats(18)
    return t_read, t_read_all, t_fit, t_fit_short, result, stream.getvalue()


def main(argv=None):
    """Make the bag if needed, time the command, write bench/results/offline_throughput.md."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    parser.add_argument('--repeat', type=int, default=3, help='timed runs of the command')
    parser.add_argument('--workdir', default=None,
                        help='where the 10-minute bag is made and kept for the next run '
                             '(default: a fresh temporary directory, removed at the end)')
    parser.add_argument('--no-write', action='store_true')
    args = parser.parse_args(argv)
    return run_in_workdir(args.workdir, 'rotor_id_offline_',
                          lambda workdir: _measure(args, workdir))


def _measure(args, workdir):
    bag, config = ensure_bag(workdir)
    json_out = Path(workdir) / 'identify.json'
    runs = []
    for i in range(args.repeat):
        runs.append(run_child(bag, config, json_out))
        wall, rss, cpu, code = runs[-1]
        say(f'run {i + 1}/{args.repeat}: {wall:.2f} s wall ({cpu:.2f} s CPU) = '
            f'{DURATION_S / wall:.0f}x real time, peak RSS {rss:.0f} MB (exit {code})')
    data = json.loads(json_out.read_text())
    wall = float(np.median([r[0] for r in runs]))
    cpu = float(np.median([r[2] for r in runs]))
    rss = float(max(r[1] for r in runs))
    say('start-up cost of the command line')
    imports = import_costs()
    say('timing the phases in-process and profiling')
    t_read, t_read_all, t_fit, t_fit_short, _, profile = in_process_phases(bag, config)
    say('vectorised read floor')
    mcap = next(Path(bag).glob('*.mcap'))
    floor = min(vectorised_read_floor(mcap, set(DEFAULT_TOPICS.values()))[1] for _ in range(2))
    say('peak memory of reading alone')
    rss_read, rss_whole, rss_floor = reading_memory(bag, config)
    factor = DURATION_S / wall
    rows = [[name, f'{v["value"]:.5f}', f'{v["std"]:.5f}', f'{TRUTH[name]:.5f}',
             f'{(v["value"] - TRUTH[name]) / v["std"]:+.2f}']
            for name, v in data['parameters'].items()]
    missed = factor < TARGET
    verdict = f'MISSED by a factor {TARGET / factor:.1f}' if missed else 'met'
    body = (
        f'## Result (median of {args.repeat} runs)\n\n'
        + markdown_table(['quantity', 'value'], [
            ['record', f'{DURATION_S:.0f} s at {RATE_HZ:.0f} Hz, 4 blades, 3 topics × '
                       f'{int(DURATION_S * RATE_HZ)} JointState messages, MCAP '
                       f'{bag_size_mb(bag):.0f} MB'],
            ['command', '`rotor-id identify BAG --config RUN.yaml --json OUT --quiet`'],
            ['wall time (child process, everything)', f'{wall:.2f} s, {cpu:.2f} s CPU '
             f'(runs: {", ".join(f"{r[0]:.2f}" for r in runs)} s)'],
            ['throughput', f'**{factor:.0f}× real time** (target ≥ {TARGET:.0f}×: {verdict})'],
            ['throughput on CPU time (user + system of the child)',
             f'{DURATION_S / cpu:.0f}× (the machine is shared: wall/CPU = {wall / cpu:.1f})'],
            ['peak memory (ru_maxrss of the child)', f'**{rss:.0f} MB**'],
            ['fit', f'{data["n_samples"]} samples, {data["iterations"]} iterations, '
                    f'{"converged" if data["converged"] else data["message"]}'],
        ])
        + '\n\n## Where the time goes\n\n'
        + markdown_table(['part', 'measured', 'share of the in-process read + identify'], [
            ['`rotor-id identify --help` (interpreter + imports of every command)',
             f'{imports["cli"][0]:.2f} s wall, {imports["cli"][2]:.2f} s CPU', '–'],
            ['`import rotor_id.commands.identify` alone',
             f'{imports["identify_module"][0]:.2f} s wall, '
             f'{imports["identify_module"][2]:.2f} s CPU', '–'],
            ['reading the bag (`load_inputs`: the window ± 2 s through the MCAP chunk index, '
             'batched CDR decode, time base, checks)',
             fmt_time(t_read), f'{t_read / (t_read + t_fit):.0%}'],
            ['reading every message of the bag with the product reader (`window_s` None)',
             fmt_time(t_read_all), '–'],
            ['identify (27-point start grid + Gauss-Newton)', fmt_time(t_fit),
             f'{t_fit / (t_read + t_fit):.0%}'],
            ['identify on the record cut to the window ± 0.5 s', fmt_time(t_fit_short), '–'],
            ['vectorised MCAP read floor (prototype below, same 3 topics)', fmt_time(floor),
             '–'],
            ['peak memory of a child that only reads: the window (product) / every message '
             '(product) / every message (floor)',
             f'{rss_read:.0f} MB / {rss_whole:.0f} MB / {rss_floor:.0f} MB', '–'],
        ])
        + '\n\n'
        f'Like with like, every message of the bag: the product reader takes '
        f'{t_read_all / floor:.1f}× the time of the bare vectorised MCAP read (the floor), '
        'which checks nothing. The command reads only the window, '
        f"{fmt_time(t_read)} ({t_read / floor:.2f}× the floor's whole-bag read).\n"
        + '\n## Estimate (true values of the simulation)\n\n'
        + markdown_table(['parameter', 'estimate', 'σ (CRB)', 'truth', '(estimate − truth)/σ'],
                         rows)
        + '\n\n## Profile of the in-process run (cumulative, top entries)\n\n```\n'
        + '\n'.join(line for line in profile.splitlines() if line.strip())[:6000]
        + '\n```\n')
    print(body)
    if not args.no_write:
        write_results('offline_throughput', 'Offline identification of a 10-minute 1 kHz bag',
                      body, 'python bench/offline_throughput.py')
    return 0 if not missed else 1


if __name__ == '__main__':
    sys.exit(main())
