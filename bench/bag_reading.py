"""
What stays hand-written in the bag reader, and why: measured against the libraries.

A 60 s, 1 kHz, 4-blade bag (3 JointState topics, 180 000 messages, MCAP) is written with
:func:`rotor_id.io.bag.write_record_bag`. Measured, timed interleaved (CPU time, medians):

* reading a 10 s window of receive time from the MCAP index: rosbags' Reader (what
  :mod:`rotor_id.io.bag` uses for every read) against the ``mcap`` package's reader;
* decoding the window's 10 000 flap messages into arrays: the vectorised JointState codec
  (:func:`rotor_id.io.jointstate_cdr.decode_batch`) against rosbags' ``deserialize_cdr`` per
  message (the library's way), the arrays built from its messages;
* a copy of the MCAP cut at 60 % of its bytes (a recording cut short): the messages rosbags'
  Reader returns against those the salvage scan (:func:`rotor_id.io.mcap_recover.scan_mcap`)
  recovers.

Run: ``python bench/bag_reading.py [--repeat N] [--workdir DIR]``.
"""

import argparse
import os
from pathlib import Path
import shutil

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
os.environ.setdefault('OMP_NUM_THREADS', '1')

from common import (fmt_time, markdown_table, run_in_workdir, say,  # noqa: E402
                    time_interleaved, write_results)
import numpy as np  # noqa: E402

from rotor_id.io.bag import write_record_bag  # noqa: E402
from rotor_id.io.jointstate_cdr import decode_batch, JOINT_STATE  # noqa: E402
from rotor_id.io.mcap_recover import scan_mcap  # noqa: E402
from rotor_id.io.record import Record  # noqa: E402

SECONDS, RATE_HZ, OMEGA = 60.0, 1000.0, 2 * np.pi * 15
WINDOW_S = (30.0, 40.0)
CUT_FRACTION = 0.6
FLAP = '/rotor/blade_flap'
STAMP0 = 1_700_000_000_000_000_000


def make_bag(workdir):
    """Write the 60 s bag (once) and return its directory."""
    bag = Path(workdir) / 'bag_60s'
    if bag.exists():
        return bag
    rng = np.random.default_rng(1)
    time_s = np.arange(int(SECONDS * RATE_HZ)) / RATE_HZ
    t = OMEGA * time_s
    psi = t[:, None] + np.arange(4) * np.pi / 2
    pitch = 0.035 + 0.026 * np.cos(psi) + 1e-4 * rng.standard_normal(psi.shape)
    flap = 0.01 + 0.008 * np.sin(psi - 0.4) + 1e-3 * rng.standard_normal(psi.shape)
    record = Record(time_s=time_s, t=t, rotor_speed_rad_s=np.full(time_s.size, OMEGA),
                    blade_flap=flap, blade_pitch=pitch,
                    blade_names=[f'blade_{k}' for k in range(1, 5)], stamp0_ns=STAMP0)
    return write_record_bag(bag, record)


def rosbags_window(bag):
    """Return the receive times and CDR bytes of the flap topic in the window (rosbags)."""
    from rosbags.rosbag2 import Reader
    first, last = (STAMP0 + int(s * 1e9) for s in WINDOW_S)
    with Reader(bag) as reader:
        connections = [c for c in reader.connections if c.topic == FLAP]
        return [(ns, data) for _, ns, data in reader.messages(connections, first, last)]


def mcap_window(bag):
    """Return the same messages through the mcap package's indexed reader."""
    from mcap.reader import make_reader
    first, last = (STAMP0 + int(s * 1e9) for s in WINDOW_S)
    with open(next(bag.glob('*.mcap')), 'rb') as stream:
        return [(m.log_time, m.data) for _, _, m in make_reader(stream).iter_messages(
            topics=[FLAP], starting_at=first, ending_before=last, log_time_order=True)]


def decode_vectorised(messages):
    """Return stamps and flap positions decoded with the vectorised codec."""
    batch = decode_batch([data for _, data in messages])
    return batch.stamps_ns, batch.position


def decode_per_message(messages):
    """Return stamps and flap positions from rosbags' deserializer, one message at a time."""
    from rosbags.typesys import get_typestore, Stores
    store = get_typestore(Stores.ROS2_JAZZY)
    decoded = [store.deserialize_cdr(data, JOINT_STATE) for _, data in messages]
    stamps = np.array([m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec
                       for m in decoded], dtype=np.int64)
    return stamps, np.array([m.position for m in decoded])


def damaged_counts(bag, workdir):
    """Count the messages read from the cut copy: (rosbags, its error, salvage scan, why)."""
    from rosbags.rosbag2 import Reader
    cut = Path(workdir) / 'cut.mcap'
    source = next(bag.glob('*.mcap'))
    data = source.read_bytes()
    cut.write_bytes(data[:int(len(data) * CUT_FRACTION)])
    count, error = 0, ''
    try:
        with Reader(cut) as reader:
            for _ in reader.messages():
                count += 1
    except Exception as err:  # noqa: B902 - what rosbags says about the damage
        error = f'{type(err).__name__}: {err}'
    scan = scan_mcap(cut)
    total = sum(len(v) for v in scan.messages.values())
    return count, error, total, scan.problem


def main(argv=None):
    """Measure and write bench/results/bag_reading.md."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--repeat', type=int, default=5)
    parser.add_argument('--workdir', default=None)
    args = parser.parse_args(argv)
    return run_in_workdir(args.workdir, 'rotor_id_bag_reading_',
                          lambda workdir: _measure(args, workdir))


def _measure(args, workdir):
    bag = make_bag(workdir)
    say(f'bag {bag}')
    reads = time_interleaved({'rosbags': lambda: rosbags_window(bag),
                              'mcap': lambda: mcap_window(bag)}, args.repeat)
    messages = reads['rosbags']['result']
    assert [d for _, d in messages] == [d for _, d in reads['mcap']['result']]
    decodes = time_interleaved({'vectorised': lambda: decode_vectorised(messages),
                                'per message': lambda: decode_per_message(messages)},
                               args.repeat)
    (s1, p1), (s2, p2) = decodes['vectorised']['result'], decodes['per message']['result']
    assert np.array_equal(s1, s2) and np.array_equal(p1, p2)
    rosbags_count, error, salvaged, problem = damaged_counts(bag, workdir)
    n = len(messages)
    rows = [
        [f'read the {WINDOW_S[1] - WINDOW_S[0]:g} s window ({n} flap messages) from the MCAP '
         'index: rosbags Reader', fmt_time(reads['rosbags']['cpu']), '1 (peer)'],
        ['the same with the `mcap` package reader', fmt_time(reads['mcap']['cpu']),
         f'{reads["mcap"]["cpu"] / reads["rosbags"]["cpu"]:.1f}×'],
        [f'decode the {n} messages to arrays: `decode_batch` (vectorised, kept)',
         fmt_time(decodes['vectorised']['cpu']), '1 (peer)'],
        ['the same with rosbags `deserialize_cdr` per message',
         fmt_time(decodes['per message']['cpu']),
         f'{decodes["per message"]["cpu"] / decodes["vectorised"]["cpu"]:.0f}×'],
    ]
    body = (f'## Result ({args.repeat} interleaved rounds, CPU time medians)\n\n'
            + markdown_table(['step', 'CPU time', 'ratio'], rows) + '\n\n'
            f'## A recording cut short\n\n'
            f'The MCAP cut at {CUT_FRACTION:.0%} of its bytes (no summary, no footer, the last '
            'chunk cut):\n\n'
            + markdown_table(['reader', 'messages read', 'says'], [
                ['rosbags Reader', str(rosbags_count), error or '–'],
                ['`scan_mcap` (salvage, kept)', str(salvaged), problem or '–']]) + '\n')
    write_results('bag_reading', 'Bag reading: the libraries against what stays hand-written',
                  body, 'python bench/bag_reading.py')
    shutil.rmtree(Path(workdir) / 'cut.mcap', ignore_errors=True)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
