"""
``rotor-id identify BAG --test-point K|all``: the test points of a multi-point bag, offline.

What it proves, on a bag of three test points of the wake plant recorded straight through (the
plant's own stepper at 1 kHz, the stirring node's phases on ``rotor/stirring`` received 20 ms
after the samples they refer to, as the live recorder writes them): the test points are found
where the live identifier's state machine starts them (each at its schedule's first flap sample),
and each test point's offline estimate is the estimate of exactly the window the live identifier
fits (its FitRequest from the same TestPointSequence) to 0.001σ, with ``window_s`` counted from
that test point's start, not the bag's; ``all`` gives a JSON list and CSV rows in order; without
phases the estimates' test_point tags are used; a schedule cut short is reported as not
identified (an error when asked for by number); a bag with neither signal, an unknown number and
a bad ``--test-point`` are one line and exit 2.
"""

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
from rotor_id.cli import main
from rotor_id.io.bag import (message_with_defaults, typestore_with_custom_types,
                             write_record_bag)
from rotor_id.io.record import Record
from rotor_id.io.run_description import load_run_description
from rotor_id.nodes.test_points import Excitation, FitSchedule, TestPointSequence
from rotor_id.pipeline import identify
from test_test_points import _stream, BASE, BLADES, LENGTH, MS, OMEGA, WAKE

CONFIG = Path(__file__).resolve().parents[2] / 'config' / 'demo_wake.yaml'
LATE = 20                                   # samples a phase arrives after its stamp


def _schedules(points, done_at=960):
    phases = []
    for k in range(points):
        phases += [(k * LENGTH, Excitation.TRIM), (k * LENGTH + 67, Excitation.CYCLIC_STEP),
                   (k * LENGTH + 810, Excitation.STIRRING), (k * LENGTH + done_at,
                                                             Excitation.DONE)]
    return phases


def _time(store, ns):
    return store.types['builtin_interfaces/msg/Time'](sec=int(ns) // 10**9,
                                                      nanosec=int(ns) % 10**9)


@pytest.fixture(scope='module')
def recording(tmp_path_factory):
    """Return the stream of three test points as a Record, and a bag writer for it."""
    data = _stream(points=3)
    record = Record(time_s=(data['stamps'] - BASE) / 1e9, t=data['t'],
                    rotor_speed_rad_s=np.full(data['t'].size, OMEGA),
                    blade_flap=data['flap'], blade_pitch=data['pitch'], blade_names=BLADES,
                    stamp0_ns=BASE)
    store = typestore_with_custom_types()
    tmp = tmp_path_factory.mktemp('multi_point')

    def bag(name, phases=(), estimates=(), storage='mcap', written=record):
        extra = []
        for index, phase in phases:
            stamp = int(data['stamps'][index])
            header = store.types['std_msgs/msg/Header'](stamp=_time(store, stamp),
                                                        frame_id='rotor')
            extra.append(('/rotor/stirring', stamp + LATE * MS, message_with_defaults(
                store, 'rotor_id_msgs/msg/StirringCommand', header=header, phase=int(phase))))
        for number, start_index, status in estimates:
            start = int(data['stamps'][start_index])
            extra.append(('/rotor_id/estimate', start + LENGTH * MS, message_with_defaults(
                store, 'rotor_id_msgs/msg/ParameterEstimate', test_point=number, kind=1,
                status=status, test_point_start=_time(store, start))))
        extra.sort(key=lambda e: e[1])
        topics = {e[0] for e in extra}
        path = tmp / name
        if not path.exists():
            write_record_bag(path, written, extra=extra, typestore=store, storage=storage)
        return path, topics

    return {'data': data, 'record': record, 'bag': bag, 'tmp': tmp}


def _live_fits(data, phases):
    """Identify what the live identifier fits: the final FitRequest of each test point."""
    machine = TestPointSequence(4, load_run_description(CONFIG).window_s, BLADES,
                                FitSchedule(update_every_rad=0.0))
    events = {index + LATE: (phase, int(data['stamps'][index])) for index, phase in phases}
    fits = {}
    description = load_run_description(CONFIG)
    for i, stamp in enumerate(data['stamps']):
        machine.add_flap(int(stamp), data['flap'][i])
        machine.add_pitch(int(stamp), data['pitch'][i])
        machine.add_azimuth(int(stamp), data['psi'][i], OMEGA)
        if i in events:
            machine.on_excitation(*events[i])
        request = machine.due()
        if request is not None:
            estimate = identify(request.record, description, window_s=request.window_s).estimate
            fits[request.test_point] = (request.stamp0_ns, {
                n: (estimate.values[estimate.names.index(n)], estimate.std_of(n))
                for n in WAKE})
    return fits


def _cli(*argv):
    return main(['identify', *map(str, argv), '--quiet'])


def test_each_test_point_agrees_with_the_live_fit_of_its_window(recording, capsys):
    phases = _schedules(3)
    bag, _ = recording['bag']('phases', phases)
    out = recording['tmp'] / 'all.json'
    table = recording['tmp'] / 'all.csv'
    assert _cli(bag, '--config', CONFIG, '--test-point', 'all', '--json', out,
                '--csv', table) == 0, capsys.readouterr().err
    results = json.loads(out.read_text())
    live = _live_fits(recording['data'], phases)
    assert [r['test_point'] for r in results] == [1, 2, 3] == sorted(live)
    rows = list(csv.DictReader(table.open()))
    assert [int(r['test_point']) for r in rows] == [1, 2, 3]
    for result, row in zip(results, rows):
        k = result['test_point']
        stamp0, live_values = live[k]
        # its start is its schedule's first flap sample, as live
        assert result['test_point_start_ns'] == stamp0 == recording['data']['stamps'][
            (k - 1) * LENGTH]
        assert result['window_s_test_point'] == [0.80939, 0.93671]
        shift = (k - 1) * LENGTH * MS / 1e9
        assert result['window_s'] == pytest.approx([0.80939 + shift, 0.93671 + shift],
                                                   abs=1e-9)
        assert result['converged'] and result['window_complete_in_bag']
        for name, (value, std) in live_values.items():
            offline = result['parameters'][name]
            assert abs(offline['value'] - value) < 1e-3 * std, (k, name, offline, value, std)
            assert abs(offline['value'] - WAKE[name]) < 3 * offline['std']
            assert float(row[name]) == pytest.approx(offline['value'])
            assert float(row[f'{name}_std']) == pytest.approx(offline['std'])
        assert row['status'] == 'converged' and row['found_from'].startswith('/rotor/stirring')


def test_one_test_point_by_number(recording, capsys):
    bag, _ = recording['bag']('phases', _schedules(3))
    out = recording['tmp'] / 'two.json'
    assert _cli(bag, '--config', CONFIG, '--test-point', '2', '--json', out) == 0
    result = json.loads(out.read_text())
    assert result['test_point'] == 2 and result['converged']
    assert result['test_point_start_s'] == pytest.approx(LENGTH * MS / 1e9)
    assert '-- test point 2 --' in capsys.readouterr().out


def test_without_phases_the_estimates_tags_give_the_test_points(recording):
    # the identifier numbered them 4, 5, 6 (it ran three before this recording started)
    bag, _ = recording['bag']('estimates', estimates=[(4 + k, k * LENGTH, 1) for k in range(3)])
    out = recording['tmp'] / 'tags.json'
    assert _cli(bag, '--config', CONFIG, '--test-point', 'all', '--json', out) == 0
    results = json.loads(out.read_text())
    assert [r['test_point'] for r in results] == [4, 5, 6]
    assert all(r['found_from'].startswith('/rotor_id/estimate') for r in results)
    assert [r['test_point_start_ns'] for r in results] == [
        recording['data']['stamps'][k * LENGTH] for k in range(3)]


def test_phases_take_the_live_numbers_where_the_estimates_give_them(recording, capsys):
    bag, _ = recording['bag']('both', _schedules(3),
                              estimates=[(7 + k, k * LENGTH, 1) for k in range(3)])
    out = recording['tmp'] / 'both.json'
    assert _cli(bag, '--config', CONFIG, '--test-point', '8', '--json', out) == 0
    assert json.loads(out.read_text())['test_point_start_ns'] == recording['data']['stamps'][
        LENGTH]
    assert "the live identifier's test point 8" in capsys.readouterr().err


def test_a_schedule_cut_short_is_not_identified(recording, capsys):
    # test point 2's schedule is done at 0.85 s, before its window's end (0.937 s)
    phases = [p for p in _schedules(3) if p[0] != LENGTH + 960] + [(LENGTH + 850,
                                                                   Excitation.DONE)]
    bag, _ = recording['bag']('cut', sorted(phases, key=lambda p: p[0]))
    table = recording['tmp'] / 'cut.csv'
    assert _cli(bag, '--config', CONFIG, '--test-point', 'all', '--csv', table) == 1
    rows = list(csv.DictReader(table.open()))
    assert [(r['test_point'], r['status']) for r in rows] == [
        ('1', 'converged'), ('2', 'not identified'), ('3', 'converged')]
    assert rows[1]['A'] == ''
    capsys.readouterr()
    assert _cli(bag, '--config', CONFIG, '--test-point', '2') == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and 'test point 2 (aborted: excitation ended)' in err[0], err
    assert 'this test point starts at 1.0000 s' in err[0]


@pytest.mark.parametrize('argv, words', [
    (('--test-point', '9'), 'has no test point 9: found [1, 2, 3]'),
    (('--test-point', '0'), "give a test point number (1, 2, ...) or 'all'"),
    (('--test-point', 'first'), "give a test point number (1, 2, ...) or 'all'"),
    (('--csv', 'x.csv'), '--csv is written with --test-point'),
])
def test_bad_selections_are_one_line(recording, capsys, argv, words):
    bag, _ = recording['bag']('phases', _schedules(3))
    assert _cli(bag, '--config', CONFIG, *argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and words in err[0], err


def test_a_bag_without_test_points_says_how_to_select_a_window(recording, capsys):
    bag, _ = recording['bag']('plain')
    assert _cli(bag, '--config', CONFIG, '--test-point', '1') == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and 'holds no test points' in err[0], err
    assert 'drop --test-point and set window_s' in err[0]
    assert math.isfinite(len(err))


def test_a_long_bag_read_slice_by_slice_gives_the_whole_reads_results(recording, capsys,
                                                                      monkeypatch):
    """
    A long bag's test points are found from slices and fitted from windowed reads only.

    The bag's reader is told to read parts of this small bag (sqlite3: read by its timestamp
    index, where a small MCAP has too few chunks) as it does of a long one (no size limit,
    short margins) and the recording to go 0.3 s at a time, so that slice boundaries fall
    inside test points' windows; the whole reader is then never called, and every test point
    comes out as from the whole record: the same start, window check and CSV row, estimates
    equal to 1e-12 (the windowed records count the azimuth's revolutions from their own start).
    """
    from rotor_id.commands import identify as identify_command
    from rotor_id.io import bag as bag_module
    # test point 2's schedule is cut short: aborted in both
    phases = [p for p in _schedules(3) if p[0] != LENGTH + 960] + [(LENGTH + 850,
                                                                   Excitation.DONE)]
    bag, _ = recording['bag']('cut_sqlite3', sorted(phases, key=lambda p: p[0]), storage='sqlite3')

    def identify_all(name):
        out, table = recording['tmp'] / f'{name}.json', recording['tmp'] / f'{name}.csv'
        code = _cli(bag, '--config', CONFIG, '--test-point', 'all', '--json', out,
                    '--csv', table)
        err = capsys.readouterr().err
        assert out.exists(), err
        return code, json.loads(out.read_text()), list(csv.DictReader(table.open()))

    whole = identify_all('whole')
    _read_in_slices(monkeypatch, slice_s=0.3)
    reads = []
    part = bag_module.read_record

    def windowed_only(*args, **kwargs):
        record = part(*args, **kwargs)
        assert record.read_around_window, 'the whole bag was read'
        reads.append(kwargs['window_s'])
        return record

    monkeypatch.setattr(identify_command, 'read_record', windowed_only)
    sliced = identify_all('sliced')
    # ten slices to find the test points (the last holds the end; the first read once), the
    # other nine again for the replay's rows, then the windows of test points 1 and 3
    np.testing.assert_allclose(reads[:10], [(k * 0.3, (k + 1) * 0.3) for k in range(10)])
    assert len(reads) == 10 + 9 + 2 and reads[-1][0] == pytest.approx(2.80939)
    assert sliced[0] == whole[0] == 1
    assert [r['status'] for r in sliced[2]] == ['converged', 'not identified', 'converged']
    for got, want in zip(sliced[1], whole[1]):
        assert got.keys() == want.keys()
        for key in ('test_point', 'found_from', 'test_point_start_ns', 'status', 'reason',
                    'converged', 'n_samples', 'window_complete_in_bag', 'iterations'):
            assert got.get(key) == want.get(key), key
        for name, value in want.get('parameters', {}).items():
            assert got['parameters'][name]['value'] == pytest.approx(value['value'], rel=1e-12)
            assert got['parameters'][name]['std'] == pytest.approx(value['std'], rel=1e-12)
    for got, want in zip(sliced[2], whole[2]):
        assert got.keys() == want.keys()
        assert {k: v for k, v in got.items() if k not in WAKE and not k.endswith('_std')} == {
            k: v for k, v in want.items() if k not in WAKE and not k.endswith('_std')}


def _read_in_slices(monkeypatch, slice_s=0.3):
    """Make the bag reader read parts of small bags, and the recording go ``slice_s`` at a time."""
    from rotor_id.commands import identify as identify_command
    from rotor_id.io import bag as bag_module
    monkeypatch.setattr(bag_module, 'WINDOW_READ_MIN_BYTES', 0)
    monkeypatch.setattr(bag_module, 'WINDOW_READ_MARGIN_S', 0.2)
    monkeypatch.setattr(bag_module, 'WINDOW_READ_CLOCK_TOLERANCE_S', 0.01)
    monkeypatch.setattr(bag_module, 'WINDOW_READ_MAX_FRACTION', 10.0)
    monkeypatch.setattr(identify_command, 'MULTI_POINT_SLICE_S', slice_s)


def _dead_blade_bag(recording, name, first, last):
    """Write a multi-point bag whose blade 3 reads 0.0 from sample ``first`` to ``last``."""
    from dataclasses import replace
    dead = recording['record'].blade_flap.copy()
    dead[first:last, 2] = 0.0
    bag, _ = recording['bag'](name, _schedules(3), storage='sqlite3',
                              written=replace(recording['record'], blade_flap=dead))
    return bag


@pytest.mark.parametrize('sliced', [False, True])
def test_a_dead_flap_between_test_points_spoils_nothing(recording, capsys, monkeypatch, sliced):
    """
    Identify every test point when a blade reads one value only between them.

    A blade reading one value outside every window (sensors off between test points) is no
    fault: read whole or slice by slice, the recording's three test points are identified.
    """
    bag = _dead_blade_bag(recording, 'dead_between_sqlite3', 1300, 1700)   # 1.3-1.7 s
    if sliced:
        _read_in_slices(monkeypatch, slice_s=0.2)
    table = recording['tmp'] / f'dead_between_{sliced}.csv'
    assert _cli(bag, '--config', CONFIG, '--test-point', 'all', '--csv', table) == 0
    capsys.readouterr()
    assert [r['status'] for r in csv.DictReader(table.open())] == ['converged'] * 3


@pytest.mark.parametrize('sliced', [False, True])
def test_a_dead_flap_in_a_window_spoils_that_test_point_only(recording, capsys, monkeypatch,
                                                             sliced):
    """
    Leave out only the test point whose window holds a dead flap sensor.

    Blade 3 reads one value throughout test point 2's window (1.81-1.94 s): that test
    point is not identified, with the blade and the value; the others are; exit 1. Asked
    for alone, it is one line and exit 2.
    """
    bag = _dead_blade_bag(recording, 'dead_in_window_sqlite3', 1750, 2000)
    if sliced:
        _read_in_slices(monkeypatch, slice_s=0.2)
    table = recording['tmp'] / f'dead_in_window_{sliced}.csv'
    assert _cli(bag, '--config', CONFIG, '--test-point', 'all', '--csv', table) == 1
    out = capsys.readouterr().out
    assert [r['status'] for r in csv.DictReader(table.open())] == [
        'converged', 'not identified', 'converged']
    assert 'test point 2: not identified (dead flap sensor: blade_3 reads exactly 0 rad' in out
    assert _cli(bag, '--config', CONFIG, '--test-point', '2') == 2
    err = [line for line in capsys.readouterr().err.strip().splitlines()
           if not line.startswith('warning: ')]      # (the step to 0.0 may look like a spike)
    assert len(err) == 1 and 'dead flap sensor: blade_3 reads exactly 0 rad' in err[0], err


def test_estimates_tags_of_a_long_bag_need_only_its_first_slice(recording, capsys,
                                                                monkeypatch):
    from rotor_id.commands import identify as identify_command
    bag, _ = recording['bag']('estimates_sqlite3', storage='sqlite3',
                              estimates=[(4 + k, k * LENGTH, 1) for k in range(3)])
    whole_out = recording['tmp'] / 'tags_whole.json'
    sliced_out = recording['tmp'] / 'tags_sliced.json'
    assert _cli(bag, '--config', CONFIG, '--test-point', 'all', '--json', whole_out) == 0
    _read_in_slices(monkeypatch)
    reads = []
    part = identify_command.read_record

    def counted(*args, **kwargs):
        reads.append(kwargs['window_s'])
        return part(*args, **kwargs)

    monkeypatch.setattr(identify_command, 'read_record', counted)
    assert _cli(bag, '--config', CONFIG, '--test-point', 'all', '--json', sliced_out) == 0
    capsys.readouterr()
    assert len(reads) == 1 + 3 and reads[0] == (0.0, 0.3)     # the origin, then each window
    whole, sliced = json.loads(whole_out.read_text()), json.loads(sliced_out.read_text())
    assert [r['test_point_start_ns'] for r in sliced] == [r['test_point_start_ns']
                                                          for r in whole]
    for got, want in zip(sliced, whole):
        for name, value in want['parameters'].items():
            assert got['parameters'][name]['value'] == pytest.approx(value['value'], rel=1e-12)
