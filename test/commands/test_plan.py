"""
`rotor-id plan` (pins #8): table, stable JSON, figure, exit codes, one-line errors.

The science (prediction vs Monte Carlo, the report's findings) is tested in test_planning.py;
here the command's contract: the JSON keys of the issue, a recommendation consistent with the
table, σ vs record length in the figure, and errors a user can act on.
"""

import json
from pathlib import Path

from rotor_id import cli

REPO = Path(__file__).resolve().parents[2]
WAKE = REPO / 'config' / 'plan_wake.yaml'
CANDIDATE_KEYS = {'direction', 'omegadot', 'amplitude_rad', 't0', 'duration_rev', 'std',
                  'meets_target'}


def test_plan_writes_json_table_and_figure(tmp_path, capsys):
    out = tmp_path / 'plan.json'
    figure = tmp_path / 'plan.png'
    rc = cli.main(['plan', '--config', str(WAKE), '--json', str(out), '--figure', str(figure)])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    data = json.loads(out.read_text())
    assert len(data['candidates']) == 12
    for cand in data['candidates']:
        assert CANDIDATE_KEYS <= set(cand)
        assert cand['direction'] in ('progressing', 'regressing')
        assert (cand['omegadot'] < 0) == (cand['direction'] == 'progressing')
        assert set(cand['std']) == {'A', 'AL_over_tau', 'inv_tau'}
        assert all(v > 0 for v in cand['std'].values())
        assert isinstance(cand['meets_target'], bool)
        assert cand['meets_target'] == all(cand['std'][n] <= s
                                           for n, s in data['target_std'].items())
    best = data['candidates'][data['recommended']]
    assert best['meets_target']
    assert best['duration_rev'] == min(c['duration_rev'] for c in data['candidates']
                                       if c['meets_target'])
    # σ fall with record length along each transient
    by_transient = {}
    for cand in data['candidates']:
        key = (cand['omegadot'], cand['amplitude_rad'], cand['t0'])
        by_transient.setdefault(key, []).append((cand['duration_rev'], cand['std']['A']))
    for rows in by_transient.values():
        stds = [s for _, s in sorted(rows)]
        assert stds == sorted(stds, reverse=True)
    assert figure.stat().st_size > 20_000
    table = captured.out
    assert f'*{data["recommended"]:>4}' in table and 'recommended: #' in table
    assert 'window_s' in table
    assert 'M⁻¹(t_f) 4/4' in captured.err          # progress per transient


def test_plan_exit_code_1_when_no_candidate_meets_the_targets(tmp_path, capsys):
    config = tmp_path / 'hard.yaml'
    config.write_text(WAKE.read_text().replace('A: 0.02,', 'A: 0.0001,'))
    rc = cli.main(['plan', '--config', str(config), '--quiet'])
    captured = capsys.readouterr()
    assert rc == 1
    assert 'no candidate meets target_std' in captured.err
    assert 'meets no target' in captured.out


def test_plan_errors_are_one_line(tmp_path, capsys):
    rc = cli.main(['plan', '--config', str(tmp_path / 'missing.yaml')])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and 'cannot read the plan' in err[0]
    bad = tmp_path / 'bad.yaml'
    bad.write_text(WAKE.read_text().replace('amplitude_rad: [0.0262]', 'amplitude_rad: [1.5]'))
    rc = cli.main(['plan', '--config', str(bad)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1
    assert 'bad.yaml:' in err[0] and 'radians, not degrees' in err[0]
