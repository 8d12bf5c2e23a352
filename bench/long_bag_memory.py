"""
Memory follows the window: ``rotor-id identify`` on a one-hour 1 kHz bag.

The bag: one hour at 1 kHz of a four-bladed rotor (Ω = 2π·15 rad/s), 3 topics × 3 600 000
JointState messages in one MCAP (about 1.5 GB, uncompressed 1 MB chunks with a message index,
as ``ros2 bag record`` writes them). For 59 min 30 s the rotor is trimmed at collective pitch
(flap = coning + 0.1° noise, pitch + 0.01° noise); in the last 30 s the lateral cyclic is
stepped on and the report's pitch stirring follows, simulated with the library simulator on
the dynamic-wake model (μ = 0, A = 0.5, AL/τ = 0.25, 1/τ = 0.125), like
bench/offline_throughput.py. The run description identifies (A, AL/τ, 1/τ) over the report's
window t0 … t0 + 12 near the end of the hour.

The bag is written chunk by chunk from numpy arrays (CDR rows from
:func:`rotor_id.io.jointstate_cdr.encode_rows`, MCAP records assembled as byte matrices), so
making it takes well under a minute and little memory; it is kept in ``--workdir`` if given.

Measured, each in a child process (peak memory as ``ru_maxrss`` of that child alone):
the complete ``rotor-id identify`` (target: within 500 MB), reading the window alone
(``load_inputs``), and reading the whole bag (``read_record`` without a window, the
reader's behaviour before the window read) for the ratio.

Run: ``python bench/long_bag_memory.py [--workdir DIR] [--skip-whole]``.
"""

import argparse
import json
import math
from pathlib import Path
import struct
import sys
import time

from common import (markdown_table, REPO_ROOT, run_in_workdir, say, SustainedStirring,
                    write_results)
import numpy as np
from offline_throughput import run_measured

from rotor_id.estimation.simulate import simulate
from rotor_id.io.bag import DEFAULT_TOPICS, write_record_bag
from rotor_id.io.jointstate_cdr import encode_rows
from rotor_id.physics.blades import blade_flap_from_multiblade_state
from rotor_id.physics.models import MultibladeWake, RotorConstants
from rotor_id.physics.stirring import blade_pitch_from_multiblade, StirringSchedule
import yaml

DURATION_S = 3600.0
TRANSIENT_S = 30.0               # the simulated part at the end of the hour
RATE_HZ = 1000.0
OMEGA = 2.0 * math.pi * 15.0
TRUTH = {'A': 0.5, 'AL_over_tau': 0.25, 'inv_tau': 0.125}
FLAP_NOISE_DEG = 0.1
PITCH_NOISE_DEG = 0.01
COLLECTIVE_DEG = 2.0
T_STEP = 2.0 * math.pi           # lateral cyclic one revolution after the transient starts
T0 = T_STEP + 70.0               # stirring start (report: 70 at μ = 0)
CHUNK_SAMPLES = 1000             # samples per MCAP chunk (3 messages each, ~0.45 MB)
LATENCY_NS = 300_000             # receive time = stamp + 0.3 ms
STAMP0 = 1_700_000_000_000_000_000
TARGET_MB = 500.0
BLADES = [f'blade_{k}' for k in range(1, 5)]

_MAGIC = b'\x89MCAP0\r\n'


def transient_start_s():
    """Second of the hour at which the simulated transient starts."""
    return DURATION_S - TRANSIENT_S


def run_description():
    """Return the run description: the report's window, in seconds after the first flap stamp."""
    start = transient_start_s()
    return (
        '# one-hour 1 kHz benchmark record (bench/long_bag_memory.py)\n'
        'rotor: {blades: 4, advance_ratio: 0.0, flap_frequency: 1.2, tip_loss: 0.97}\n'
        'model: multiblade_wake\n'
        'unknowns: [A, AL_over_tau, inv_tau]\n'
        f'window_s: [{start + T0 / OMEGA:.6f}, {start + (T0 + 12.0) / OMEGA:.6f}]\n')


def transient(rng):
    """Simulate the last TRANSIENT_S seconds: (flap (n, 4), pitch (n, 4)), radians."""
    n = int(round(TRANSIENT_S * RATE_HZ))
    t = OMEGA * np.arange(n) / RATE_HZ
    model = MultibladeWake(RotorConstants(advance_ratio=0.0))
    p = model.parameter_vector(TRUTH)
    schedule = StirringSchedule(collective=math.radians(COLLECTIVE_DEG),
                                amplitude=math.radians(1.5), t0=T0, t_step=T_STEP)
    inputs = SustainedStirring(schedule, T0 + 12.0)
    sim = simulate(model, p, inputs, t, np.zeros(model.n_states))
    flap = blade_flap_from_multiblade_state(model, t, sim.x, coning=coning(model, p))
    pitch = blade_pitch_from_multiblade(t, inputs(t), 4)
    return (flap + math.radians(FLAP_NOISE_DEG) * rng.standard_normal(flap.shape),
            pitch + math.radians(PITCH_NOISE_DEG) * rng.standard_normal(pitch.shape))


def coning(model, p):
    """Trim coning at the collective pitch (hover, no inflow), rad."""
    return p[0] * math.radians(COLLECTIVE_DEG) / model.rotor.flap_frequency ** 2


def _record(op, body):
    return struct.pack('<BQ', op, len(body)) + body


def _string(text):
    data = text.encode()
    return struct.pack('<I', len(data)) + data


def _message_records(channel, log_ns, rows):
    """(k, 31 + size) uint8: MCAP Message records (op 0x05) of CDR ``rows``."""
    k, size = rows.shape
    out = np.empty((k, 31 + size), dtype=np.uint8)
    out[:, 0] = 0x05
    out[:, 1:9] = np.frombuffer(struct.pack('<Q', 22 + size), np.uint8)
    out[:, 9:11] = np.frombuffer(struct.pack('<H', channel), np.uint8)
    out[:, 11:15] = 0                                         # sequence: unused
    times = np.ascontiguousarray(log_ns.astype('<u8')).view(np.uint8).reshape(k, 8)
    out[:, 15:23] = times
    out[:, 23:31] = times                                     # publish time = log time
    out[:, 31:] = rows
    return out


def template_records(workdir, extra=(), typestore=None):
    """
    Return the Schema and Channel records and metadata that rosbags writes for the 3 topics.

    With ``extra`` ((topic, receive ns, message) of ``typestore``), also for their topics.
    """
    from rotor_id.io.record import Record
    tiny = Path(workdir) / ('template_bag' if not extra else 'template_bag_extra')
    if not tiny.exists():
        n = 3
        write_record_bag(tiny, Record(
            time_s=np.arange(n) / RATE_HZ, t=OMEGA * np.arange(n) / RATE_HZ,
            rotor_speed_rad_s=np.full(n, OMEGA), blade_flap=np.zeros((n, 4)),
            blade_pitch=np.zeros((n, 4)), blade_names=BLADES, stamp0_ns=STAMP0),
            extra=[(topic, STAMP0, message) for topic, _, message in extra],
            typestore=typestore)
    data = next(tiny.glob('*.mcap')).read_bytes()
    summary_start = struct.unpack_from('<Q', data, len(data) - 8 - 20)[0]
    pos, schemas, channels = summary_start, [], {}
    while pos < len(data) - 8 - 29:
        op, length = struct.unpack_from('<BQ', data, pos)
        body = data[pos + 9:pos + 9 + length]
        if op == 0x03:
            schemas.append(_record(op, body))
        elif op == 0x04:
            cid = struct.unpack_from('<H', body, 0)[0]
            topic_len = struct.unpack_from('<I', body, 4)[0]
            channels[body[8:8 + topic_len].decode()] = (cid, _record(op, body))
        pos += 9 + length
    meta = yaml.safe_load((tiny / 'metadata.yaml').read_text())
    return schemas, channels, meta


def write_hour_bag(bag, workdir, seed=12, duration_s=DURATION_S, extra=(), typestore=None):
    """
    Write the one-hour bag chunk by chunk; return its path.

    ``duration_s`` shortens (or lengthens) the trimmed part; ``extra`` adds messages (topic,
    receive ns, message of ``typestore``), each in the chunk of its receive time.
    """
    rng = np.random.default_rng(seed)
    schemas, channels, meta = template_records(workdir, extra, typestore)
    n = int(round(duration_s * RATE_HZ))
    extra = sorted(((t, int(ns), typestore.serialize_cdr(m, m.__msgtype__))
                    for t, ns, m in extra), key=lambda e: e[1])
    extra_topics = sorted({t for t, _, _ in extra})
    extra_all = list(extra)
    n_transient = int(round(TRANSIENT_S * RATE_HZ))
    flap_end, pitch_end = transient(rng)
    model = MultibladeWake(RotorConstants(advance_ratio=0.0))
    trim_flap = coning(model, model.parameter_vector(TRUTH))
    topics = [DEFAULT_TOPICS['blade_pitch'], DEFAULT_TOPICS['blade_flap'],
              DEFAULT_TOPICS['azimuth']]
    ids = [channels[t][0] for t in topics]
    bag.mkdir(parents=True)
    path = bag / f'{bag.name}.mcap'
    chunk_index = []
    with open(path, 'wb') as out:
        out.write(_MAGIC)
        out.write(_record(0x01, _string('ros2') + _string('rotor_id bench')))
        for record in schemas + [channels[t][1] for t in topics + extra_topics]:
            out.write(record)
        for first in range(0, n, CHUNK_SAMPLES):
            index = np.arange(first, min(first + CHUNK_SAMPLES, n))
            k = index.size
            stamps = STAMP0 + index * int(1e9 / RATE_HZ)
            log_ns = stamps + LATENCY_NS
            psi = np.mod(OMEGA * index / RATE_HZ, 2 * np.pi)
            flap = trim_flap + math.radians(FLAP_NOISE_DEG) * rng.standard_normal((k, 4))
            pitch = math.radians(COLLECTIVE_DEG) \
                + math.radians(PITCH_NOISE_DEG) * rng.standard_normal((k, 4))
            late = index >= n - n_transient
            if late.any():
                at = index[late] - (n - n_transient)
                flap[late], pitch[late] = flap_end[at], pitch_end[at]
            rows = [encode_rows(stamps, BLADES, pitch, frame_id='rotor'),
                    encode_rows(stamps, BLADES, flap, frame_id='rotor'),
                    encode_rows(stamps, ['rotor'], psi[:, None], np.full((k, 1), OMEGA),
                                frame_id='rotor')]
            blocks = [_message_records(cid, log_ns, r) for cid, r in zip(ids, rows)]
            widths = [b.shape[1] for b in blocks]
            records = np.hstack(blocks).tobytes()                 # sample by sample
            last_chunk = first + CHUNK_SAMPLES >= n
            here = [e for e in extra if e[1] <= log_ns[-1] or last_chunk]
            extra = extra[len(here):]
            extra_at, extra_records = {}, b''
            for topic, ns, data in here:
                cid = channels[topic][0]
                extra_at.setdefault(cid, []).append((ns, len(records) + len(extra_records)))
                extra_records += _message_records(cid, np.array([ns]), np.frombuffer(
                    data, np.uint8)[None, :]).tobytes()
            records += extra_records
            chunk_start = min([int(log_ns[0])] + [ns for _, ns, _ in here])
            chunk_end = max([int(log_ns[-1])] + [ns for _, ns, _ in here])
            body = (struct.pack('<QQQI', chunk_start, chunk_end, len(records), 0)
                    + _string('') + struct.pack('<Q', len(records)) + records)
            chunk_at = out.tell()
            out.write(_record(0x06, body))
            offsets = {}
            index_at = out.tell()
            for j, cid in enumerate(ids):
                pairs = np.empty((k, 2), dtype='<u8')
                pairs[:, 0] = log_ns
                pairs[:, 1] = np.arange(k) * sum(widths) + sum(widths[:j])
                offsets[cid] = out.tell()
                out.write(_record(0x07, struct.pack('<HI', cid, pairs.nbytes) + pairs.tobytes()))
            for cid, pairs in extra_at.items():
                pairs = np.array(pairs, dtype='<u8')
                offsets[cid] = out.tell()
                out.write(_record(0x07, struct.pack('<HI', cid, pairs.nbytes) + pairs.tobytes()))
            chunk_index.append((chunk_start, chunk_end, chunk_at, index_at - chunk_at,
                                offsets, out.tell() - index_at, len(records)))
        out.write(_record(0x0F, struct.pack('<I', 0)))
        summary_start = out.tell()
        for record in schemas + [channels[t][1] for t in topics + extra_topics]:
            out.write(record)
        for start, end, at, length, offsets, index_length, size in chunk_index:
            entries = b''.join(struct.pack('<HQ', cid, o) for cid, o in offsets.items())
            out.write(_record(0x08, struct.pack('<QQQQ', start, end, at, length)
                              + struct.pack('<I', len(entries)) + entries
                              + struct.pack('<Q', index_length) + _string('')
                              + struct.pack('<QQ', size, size)))
        out.write(_record(0x02, struct.pack('<QQI', summary_start, 0, 0)))
        out.write(_MAGIC)
    info = meta['rosbag2_bagfile_information']
    duration = int(duration_s * 1e9) - int(1e9 / RATE_HZ)
    info['duration'] = {'nanoseconds': duration}
    info['starting_time'] = {'nanoseconds_since_epoch': STAMP0 + LATENCY_NS}
    info['message_count'] = 3 * n + len(extra_all)
    info['relative_file_paths'] = [path.name]
    info['files'] = [{'path': path.name, 'message_count': 3 * n + len(extra_all),
                      'duration': {'nanoseconds': duration},
                      'starting_time': {'nanoseconds_since_epoch': STAMP0 + LATENCY_NS}}]
    counts = {t: sum(1 for e in extra_all if e[0] == t) for t in extra_topics}
    for entry in info['topics_with_message_count']:
        entry['message_count'] = counts.get(entry['topic_metadata']['name'], n)
    (bag / 'metadata.yaml').write_text(yaml.safe_dump(meta, sort_keys=False))
    return bag


def ensure_bag(workdir):
    """Bag directory and run description in ``workdir``, made when missing; their paths."""
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    bag = workdir / 'wake_1h_1khz'
    config = workdir / 'wake_1h_1khz.yaml'
    config.write_text(run_description())
    if (bag / 'metadata.yaml').exists():
        say(f'reusing {bag}')
        return bag, config
    say('writing the one-hour bag (3 x 3 600 000 JointState messages)')
    started = time.perf_counter()
    write_hour_bag(bag, workdir)
    say(f'  wrote {bag} ({bag_size_mb(bag):.0f} MB) in {time.perf_counter() - started:.1f} s')
    return bag, config


def bag_size_mb(bag):
    """Total size of the bag directory, MB."""
    return sum(f.stat().st_size for f in Path(bag).rglob('*') if f.is_file()) / 1e6


def main(argv=None):
    """Make the bag if needed, measure, write bench/results/long_bag_memory.md."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    parser.add_argument('--workdir', default=None,
                        help='where the one-hour bag (1.7 GB) is made and kept for the next run '
                             '(default: a fresh temporary directory, removed at the end)')
    parser.add_argument('--skip-whole', action='store_true',
                        help='do not measure reading the whole bag (needs several GB)')
    parser.add_argument('--no-write', action='store_true')
    args = parser.parse_args(argv)
    return run_in_workdir(args.workdir, 'rotor_id_long_bag_',
                          lambda workdir: _measure(args, workdir))


def _measure(args, workdir):
    bag, config = ensure_bag(workdir)
    json_out = Path(workdir) / 'identify_1h.json'
    say('rotor-id identify on the window at the end of the hour')
    wall, rss, cpu, code, _ = run_measured(
        [str(REPO_ROOT / 'rotor-id'), 'identify', str(bag), '--config', str(config),
         '--json', str(json_out), '--quiet'])
    say(f'  {wall:.2f} s wall ({cpu:.2f} s CPU), peak RSS {rss:.0f} MB, exit {code}')
    data = json.loads(json_out.read_text())
    say('reading the window alone (load_inputs)')
    read_window = run_measured([sys.executable, '-c',
                                'from rotor_id.commands.identify import load_inputs; '
                                f'd, r = load_inputs({str(bag)!r}, {str(config)!r}); '
                                'print(len(r))'])
    say(f'  {read_window[0]:.2f} s wall, peak RSS {read_window[1]:.0f} MB, '
        f'{read_window[4][-2]} samples')
    whole = None
    if not args.skip_whole:
        say('reading the whole bag (read_record without a window)')
        whole = run_measured([sys.executable, '-c',
                              'import warnings; warnings.simplefilter("ignore"); '
                              'from rotor_id.io.bag import read_record; '
                              f'r = read_record({str(bag)!r}); print(len(r))'])
        say(f'  {whole[0]:.2f} s wall, peak RSS {whole[1]:.0f} MB, {whole[4][-2]} samples')
    verdict = 'met' if rss <= TARGET_MB else f'MISSED ({rss / TARGET_MB:.1f}x the target)'
    rows = [
        ['record', f'{DURATION_S:.0f} s at {RATE_HZ:.0f} Hz, 4 blades, 3 topics × '
                   f'{int(DURATION_S * RATE_HZ)} JointState messages, MCAP '
                   f'{bag_size_mb(bag):.0f} MB; window at {data["window_s"][0]:.1f}-'
                   f'{data["window_s"][1]:.1f} s'],
        ['`rotor-id identify BAG --config RUN.yaml --json OUT --quiet`',
         f'**{rss:.0f} MB** peak RSS (target ≤ {TARGET_MB:.0f} MB: {verdict}), {wall:.2f} s '
         f'wall, {cpu:.2f} s CPU, exit {code}'],
        ['reading the window alone (`load_inputs`)',
         f'{read_window[1]:.0f} MB, {read_window[0]:.2f} s wall, {read_window[2]:.2f} s CPU, '
         f'{read_window[4][-2]} samples'],
    ]
    if whole is not None:
        rows.append(['reading the whole bag (`read_record` without a window)',
                     f'{whole[1]:.0f} MB, {whole[0]:.2f} s wall, {whole[2]:.2f} s CPU, '
                     f'{whole[4][-2]} samples'])
        rows.append(['whole bag / window read: peak memory, CPU time',
                     f'**{whole[1] / read_window[1]:.1f}×**, {whole[2] / read_window[2]:.1f}×'])
    fit = [[name, f'{v["value"]:.5f}', f'{v["std"]:.5f}', f'{TRUTH[name]:.5f}',
            f'{(v["value"] - TRUTH[name]) / v["std"]:+.2f}']
           for name, v in data['parameters'].items()]
    body = ('## Result\n\n' + markdown_table(['quantity', 'value'], rows)
            + '\n\n## Estimate (true values of the simulation)\n\n'
            + markdown_table(['parameter', 'estimate', 'σ (CRB)', 'truth',
                              '(estimate − truth)/σ'], fit)
            + f'\n\n{data["n_samples"]} samples, {data["iterations"]} iterations, '
            + ('converged' if data['converged'] else data['message']) + '.\n')
    if not args.no_write:
        write_results('long_bag_memory', 'Memory follows the window: identify on a one-hour '
                      '1 kHz bag', body, 'python bench/long_bag_memory.py')
    print(body)
    return 0 if rss <= TARGET_MB and code == 0 else 1


if __name__ == '__main__':
    sys.exit(main())
