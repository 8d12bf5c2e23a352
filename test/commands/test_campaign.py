"""
`rotor-id campaign` (pins #17): a small simulated tunnel entry, in parallel and resumed.

Five test points of the wake rotor at five "tunnel speeds" (a condition of the run
descriptions), progressing and regressing stirring alternately; the one at 20 m/s has a
different rotor (A = 1 instead of .5) and must be flagged as the outlier of the A trend, and
nothing else. A sixth, at 35 m/s, has a flap sensor offset the model lacks: identify's adequacy
check calls its fit inadequate, and the report flags it and keeps it out of the trend. A seventh
bag's run description has a window outside its record: it fails in one line, is recorded, and
the others carry on.
"""

import csv
import json
import math
from pathlib import Path
import sys

import numpy as np
import pytest
from rotor_id import cli
from rotor_id.commands import campaign
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from campaign_helpers import write_test_point  # noqa: E402,I100

SPEEDS = (10, 15, 20, 25, 30)
OUTLIER = 'tp20'


@pytest.fixture(scope='module')
def entry(tmp_path_factory):
    """Return the campaign directory: five test points, one biased and one broken."""
    root = tmp_path_factory.mktemp('entry')
    for i, speed in enumerate(SPEEDS):
        write_test_point(root, f'tp{speed}', seed=i, noise_deg=0.05,
                         direction='progressing' if i % 2 == 0 else 'regressing',
                         truth={'A': 1.0} if f'tp{speed}' == OUTLIER else None,
                         conditions={'tunnel_speed_m_s': speed},
                         custom_data={'tunnel_run': '17'} if speed == 10 else None)
    write_test_point(root, 'biased', seed=7, noise_deg=0.05, conditions={'tunnel_speed_m_s': 35},
                     flap_bias_rad=[math.radians(0.3), 0.0, 0.0, 0.0])
    write_test_point(root, 'broken', seed=9)
    config = root / 'broken.yaml'
    data = yaml.safe_load(config.read_text())
    data['window_s'] = [5.0, 6.0]                       # the record is 0.94 s long
    config.write_text(yaml.safe_dump(data))
    return root


def _csv(path):
    with open(path, newline='') as f:
        return list(csv.DictReader(f))


def test_campaign_identifies_every_bag_flags_the_outlier_and_resumes(entry, tmp_path, capsys):
    out = tmp_path / 'out'
    rc = cli.main(['campaign', str(entry), '--out', str(out), '--jobs', '2'])
    captured = capsys.readouterr()
    assert rc == 1                                       # one bag failed
    err = captured.err.splitlines()
    failures = [line for line in err if 'failed:' in line]
    assert len(failures) == 1 and failures[0].startswith('campaign: broken failed: ')
    assert 'outside the record' in failures[0]
    assert 'campaign: 7/7 bags done (1 failed, 0 up to date)' in captured.err
    assert '~' in captured.err and 'left' in captured.err            # time left

    rows = _csv(out / 'campaign.csv')
    header = list(rows[0])
    assert header[:7] == ['bag', 'A', 'A_std', 'AL_over_tau', 'AL_over_tau_std', 'inv_tau',
                          'inv_tau_std']
    for column in ('status', 'converged', 'adequacy', 'diagnosis', 'noise_std_rad',
                   'window_start_s', 'window_end_s', 'tunnel_speed_m_s', 'stirring_direction',
                   'collective_rad', 'advance_ratio'):
        assert column in header
    by_bag = {r['bag']: r for r in rows}
    assert set(by_bag) == {'broken', 'biased'} | {f'tp{s}' for s in SPEEDS}
    assert by_bag['biased']['status'] == 'ok' and by_bag['biased']['adequacy'] == 'inadequate'
    assert by_bag['broken']['status'] == 'failed' and 'outside the record' in \
        by_bag['broken']['error']
    for speed, direction in zip(SPEEDS, ('progressing', 'regressing') * 3):
        row = by_bag[f'tp{speed}']
        assert row['status'] == 'ok' and row['converged'] == 'True'
        assert row['adequacy'] == 'adequate'
        assert row['stirring_direction'] == direction
        assert float(row['tunnel_speed_m_s']) == speed
        assert row['tunnel_run'] == ('17' if speed == 10 else '')     # the bag's custom_data
        assert float(row['noise_std_rad']) == pytest.approx(np.radians(0.05) / np.sqrt(2),
                                                            rel=0.15)
        truth = 1.0 if f'tp{speed}' == OUTLIER else 0.5
        assert abs(float(row['A']) - truth) < 3.5 * float(row['A_std'])

    report = (out / 'campaign.md').read_text()
    assert 'Trends against `tunnel_speed_m_s`' in report
    flagged = [line for line in report.splitlines() if line.startswith('- outlier')]
    assert len(flagged) == 1 and f'`{OUTLIER}` A' in flagged[0]
    inadequate = [line for line in report.splitlines() if line.startswith('- inadequate')]
    assert len(inadequate) == 1 and '`biased`' in inadequate[0]
    assert '`broken`: ' in report
    for name in ('A', 'AL_over_tau', 'inv_tau'):
        assert f'(trend_{name}.png)' in report
        assert (out / f'trend_{name}.png').stat().st_size > 20_000
    point = json.loads((out / 'points' / 'tp10' / 'result.json').read_text())
    assert (out / 'points' / 'tp10' / 'fit.png').is_file()
    assert json.loads((out / 'points' / 'tp10' / 'identify.json').read_text())['converged']

    # a second run redoes only what changed: nothing, then the one description edited
    stamp = (out / 'points' / 'tp10' / 'result.json').stat().st_mtime_ns
    rc = cli.main(['campaign', str(entry), '--out', str(out), '--jobs', '2'])
    captured = capsys.readouterr()
    assert rc == 1 and 'campaign: 7/7 bags done (1 failed, 6 up to date)' in captured.err
    assert (out / 'points' / 'tp10' / 'result.json').stat().st_mtime_ns == stamp
    config = entry / 'tp30.yaml'
    config.write_text(config.read_text() + '# edited\n')
    rc = cli.main(['campaign', str(entry), '--out', str(out), '--jobs', '2'])
    captured = capsys.readouterr()
    assert 'campaign: 7/7 bags done (1 failed, 5 up to date)' in captured.err
    assert (out / 'points' / 'tp10' / 'result.json').stat().st_mtime_ns == stamp
    assert json.loads((out / 'points' / 'tp10' / 'result.json').read_text()) == point


def test_campaign_input_errors_are_one_line_before_any_work(entry, tmp_path, capsys):
    rc = cli.main(['campaign', str(tmp_path / 'nothing'), '--out', str(tmp_path / 'o')])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and 'is not a directory' in err[0]
    rc = cli.main(['campaign', str(entry), '--out', str(tmp_path / 'o'),
                   '--trend-against', 'tunnel_sped'])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and 'tunnel_speed_m_s' in err[0]
    rc = cli.main(['campaign', str(entry), '--out', str(tmp_path / 'o'),
                   '--trend-against', 'stirring_direction'])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and 'is not a number' in err[0]
    assert not (tmp_path / 'o').exists()


def _summary(bag, x, value, std, adequacy='adequate', converged=True):
    return {'bag': bag, 'status': 'ok' if converged else 'not converged',
            'converged': converged, 'adequacy': adequacy,
            'parameters': {'gamma': {'value': value, 'std': std}},
            'conditions': {'collective_rad': x}}


def test_inadequate_fits_are_flagged_and_kept_out_of_the_trend():
    """A linear trend of 8 points; an inadequate fit far off is flagged, not an outlier."""
    x = np.linspace(0.0, 0.14, 8)
    summaries = [_summary(f'p{i}', xi, 5.0 + 10.0 * xi, 0.05) for i, xi in enumerate(x)]
    summaries.append(_summary('bad', 0.07, 9.0, 0.05, adequacy='inadequate'))
    summaries.append(_summary('off', 0.10, 6.0 + 0.5, 0.05))          # 10σ off the line
    assert campaign.trend_key(summaries) == 'collective_rad'
    analysis = campaign.analyse(summaries, 'collective_rad')['gamma']
    assert list(analysis['inadequate']) == [False] * 8 + [True, False]
    assert list(analysis['outlier']) == [False] * 9 + [True]
    usable = ~np.isnan(analysis['z'])
    assert np.all(np.abs(analysis['z'][usable][:8]) < 3.0)


def test_campaign_diagnoses_on_request(tmp_path, capsys):
    """One clean test point, one --config, --diagnose: the diagnosis finds nothing missing."""
    entry = tmp_path / 'entry'
    write_test_point(entry, 'clean', seed=3, noise_deg=0.05, conditions={'run': 1})
    config = (entry / 'clean.yaml').rename(tmp_path / 'one_for_all.yaml')   # --config instead
    out = tmp_path / 'out'
    rc = cli.main(['campaign', str(entry), '--out', str(out), '--diagnose', '--jobs', '1',
                   '--no-figures', '--config', str(config)])
    assert rc == 0, capsys.readouterr().err
    row = _csv(out / 'campaign.csv')[0]
    diagnosis = json.loads((out / 'points' / 'clean' / 'diagnose.json').read_text())
    assert row['diagnosis'] == diagnosis['explanation']['effect'] == 'none'
    assert not (out / 'points' / 'clean' / 'fit.png').exists()
    assert '| none | ok |' in (out / 'campaign.md').read_text()
