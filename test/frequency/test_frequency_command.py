"""``rotor-id frequency-response`` and ``identify --method frequency-response`` on bags."""

from dataclasses import replace
import json
import math
from pathlib import Path
import sys

import pytest
from rotor_id.cli import main
from rotor_id.io.bag import write_record_bag
from rotor_id.physics.models import build_model, RotorConstants

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'diagnosis'))
from frequency_helpers import sweep_record  # noqa: E402,I100
from truth_generator import generate, run_description_text, wake_case  # noqa: E402,I100

STAMP0 = 1_763_700_000_000_000_000
KEYS = ('frequency_per_rev', 'frequency_hz', 'magnitude', 'phase_deg', 'coherence',
        'random_error')


@pytest.fixture(scope='module')
def bags(tmp_path_factory):
    """Write a progressing and a regressing recording of the generator, and a description."""
    root = tmp_path_factory.mktemp('frequency_bags')
    out = {}
    for name, omegadot in (('progressing', -0.1 / math.pi), ('regressing', 0.1 / math.pi)):
        cfg = wake_case(seed=7, omegadot=omegadot)
        bag = write_record_bag(root / name, replace(generate(cfg), stamp0_ns=STAMP0))
        config = root / f'{name}.yaml'
        config.write_text(run_description_text(
            cfg, 'multiblade_wake', ['A', 'AL_over_tau', 'inv_tau'], window_s=(0.8094, 0.9367)))
        out[name] = (str(bag), str(config))
    return out


def test_command_writes_the_json_keys_and_the_figure(bags, tmp_path, capsys):
    (bag_p, config), (bag_r, _) = bags['progressing'], bags['regressing']
    assert main(['frequency-response', bag_p, bag_r, '--config', config,
                 '--out', str(tmp_path)]) == 0
    data = json.loads((tmp_path / 'frequency_response.json').read_text())
    lengths = {len(data[k]) for k in KEYS}
    assert len(lengths) == 1 and lengths.pop() >= 30
    f = data['frequency_per_rev']
    assert min(f) < -1.0 and max(f) > 1.0                 # both directions on one axis
    assert all(abs(hz - rev * 94.24777960769379 / (2 * math.pi)) < 1e-9
               for hz, rev in zip(data['frequency_hz'], f))
    assert all(0.0 <= c <= 1.0 for c in data['coherence'])
    assert data['model']['cost_J'] < 100.0
    assert (tmp_path / 'frequency_response.png').stat().st_size > 10_000
    assert 'J over all usable points' in capsys.readouterr().out


def test_model_json_of_identify_is_drawn(bags, tmp_path):
    bag, config = bags['regressing']
    ident = tmp_path / 'identify.json'
    assert main(['identify', bag, '--config', config, '--method', 'frequency-response',
                 '--json', str(ident), '--quiet']) == 0
    data = json.loads(ident.read_text())
    assert data['method'] == 'frequency-response'
    assert data['frequency_response']['cost_J'] < 100.0
    assert main(['frequency-response', bag, '--config', config, '--model-json', str(ident),
                 '--out', str(tmp_path / 'out'), '--quiet']) == 0
    drawn = json.loads((tmp_path / 'out' / 'frequency_response.json').read_text())['model']
    for name, entry in data['parameters'].items():
        assert drawn['parameters'][name] == pytest.approx(entry['value'])
    assert drawn['parameters_from'] == str(ident)


def test_a_record_without_stirring_is_one_line_before_any_spectrum(tmp_path, capsys):
    model = build_model('multiblade_wake', RotorConstants(advance_ratio=0.0))
    record = sweep_record(model, model.nominal(), -0.1 / math.pi, t_end=60.0, stirring=1.0,
                          t0=50.0)
    still = replace(record.window(0.0, 0.5), stamp0_ns=STAMP0)
    bag = write_record_bag(tmp_path / 'still', still)
    config = tmp_path / 'still.yaml'
    config.write_text(run_description_text(wake_case(), 'multiblade_wake', ['A'],
                                           window_s=(0.1, 0.3)))
    assert main(['frequency-response', str(bag), '--config', str(config),
                 '--out', str(tmp_path / 'out')]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and 'no pitch stirring' in err[0]


@pytest.mark.parametrize('words, says', [(['A'], 'NAME=VALUE'), (['A=x'], 'NAME=VALUE'),
                                         (['gamma=5'], 'not parameters of')])
def test_bad_parameters_are_one_line(bags, tmp_path, capsys, words, says):
    bag, config = bags['progressing']
    assert main(['frequency-response', bag, '--config', config, '--out', str(tmp_path),
                 '--parameters', *words]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and says in err[0], err
