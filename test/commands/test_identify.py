"""
`rotor-id identify` on the shared test-stand recordings (pins #3).

Each id_* recording has an answer (shared/recordings/answers.json); the identified parameters
must lie within 3σ of it, where σ is our own Cramér-Rao bound — so a biased estimator or a
bound too small by more than a factor ~3 fails.
"""

import json
from pathlib import Path
import re
import subprocess

from practice import RECORDINGS, require_practice
import pytest

from rotor_id import cli

REPO = Path(__file__).resolve().parents[2]
ID_RECORDINGS = sorted(p.stem for p in RECORDINGS.glob('id_*.yaml'))
JSON_KEYS = {'model', 'parameters', 'covariance', 'noise_std', 'iterations', 'converged',
             'window_s'}


def _need_recordings():
    require_practice()


@pytest.mark.parametrize('name', ID_RECORDINGS or ['none'])
def test_identify_recording_within_3_sigma(name, tmp_path, capsys):
    _need_recordings()
    answers = json.loads((RECORDINGS / 'answers.json').read_text())[name]['answer']
    out = tmp_path / 'result.json'
    figure = tmp_path / 'fit.png'
    rc = cli.main(['identify', str(RECORDINGS / name), '--config',
                   str(RECORDINGS / f'{name}.yaml'), '--json', str(out),
                   '--figure', str(figure), '--quiet'])
    assert rc == 0, capsys.readouterr()
    data = json.loads(out.read_text())
    assert JSON_KEYS <= set(data)
    assert data['converged'] is True
    assert set(data['parameters']) == set(answers['parameters'])
    for pname, truth in answers['parameters'].items():
        value = data['parameters'][pname]['value']
        std = data['parameters'][pname]['std']
        assert std > 0
        assert abs(value - truth) < 3 * std, f'{pname}: {value} ± {std}, truth {truth}'
    names = data['covariance']['names']
    matrix = data['covariance']['matrix']
    assert names == list(data['parameters'])
    for i, pname in enumerate(names):
        assert matrix[i][i] == pytest.approx(data['parameters'][pname]['std'] ** 2)
    assert figure.stat().st_size > 10_000
    table = capsys.readouterr().out
    for pname in answers['parameters']:
        assert pname in table


def test_identify_errors_are_one_line(tmp_path, capsys):
    _need_recordings()
    rc = cli.main(['identify', str(tmp_path / 'missing'), '--config',
                   str(RECORDINGS / 'id_wake_progressing.yaml')])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2
    assert len(err) == 1 and 'does not exist' in err[0]
    bad = tmp_path / 'bad.yaml'
    bad.write_text((RECORDINGS / 'id_wake_progressing.yaml').read_text()
                   .replace('multiblade_wake', 'multiblade_wakes'))
    rc = cli.main(['identify', str(RECORDINGS / 'id_wake_progressing'), '--config', str(bad)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1
    assert 'multiblade_wakes' in err[0]
    assert re.search(r'bad\.yaml:\d+:', err[0]), 'the line of the bad key is named'


def test_rotor_id_wrapper_runs_from_the_repository_root(tmp_path):
    """`./rotor-id` finds the environment itself (needs the built workspace)."""
    _need_recordings()
    if not (REPO / 'install' / 'local_setup.sh').is_file():
        pytest.skip('workspace not built (run make test)')
    out = tmp_path / 'r.json'
    proc = subprocess.run(
        [str(REPO / 'rotor-id'), 'identify', str(RECORDINGS / 'id_multiblade_mu04'),
         '--config', str(RECORDINGS / 'id_multiblade_mu04.yaml'), '--json', str(out)],
        capture_output=True, text=True, timeout=120, env={'PATH': '/usr/bin:/bin',
                                                          'HOME': str(tmp_path)})
    assert proc.returncode == 0, proc.stderr
    assert 'iteration' in proc.stderr            # progress lines
    assert json.loads(out.read_text())['model'] == 'multiblade'
