"""
Input checks of `rotor-id identify`, `diagnose`, `plan` before any fitting (pins #12).

Every recording is made here: a test point of the μ = 0 wake rotor simulated by the library's
planning path (campaign_helpers.write_test_point), or a hand-made 3-blade record. Each bad
input must end in exit 2 with one line that names the key (and its line) or the path, before
any fitting; defaults the fit takes must be named in a warning and the JSON's
``defaults_used``; every warning is printed once.
"""

import errno
import json
import math
import os
from pathlib import Path
import shutil
import subprocess
import sys

import numpy as np
import pytest
from rotor_id import cli, pipeline
from rotor_id.commands import common
from rotor_id.estimation.output_error import IdentificationError
from rotor_id.io.bag import write_record_bag
from rotor_id.io.record import Record
from rotor_id.io.run_description import load_run_description
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from campaign_helpers import write_test_point  # noqa: E402,I100

REPO = Path(__file__).resolve().parents[2]
OMEGA = 94.24777960769379


@pytest.fixture(scope='module')
def point(tmp_path_factory):
    """Return (bag, run description) of one simulated 4-blade wake test point."""
    root = tmp_path_factory.mktemp('point')
    bag = write_test_point(root, 'tp', seed=3, noise_deg=0.05)
    return bag, root / 'tp.yaml'


def _edit(config, tmp_path, name='run.yaml', **changes):
    data = yaml.safe_load(Path(config).read_text())
    for key, value in changes.items():
        if value is None:
            data.pop(key, None)
        else:
            data[key] = value
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def _run(argv, capsys):
    rc = cli.main(argv)
    out = capsys.readouterr()
    return rc, out.out, out.err.strip().splitlines()


def _one_error_line(rc, err):
    assert rc == 2, err
    assert len(err) == 1, err
    assert 'iteration' not in err[0] and 'Traceback' not in err[0]
    return err[0]


# -------------------------------------------------------------------------- blade count

def test_blade_count_against_the_joints_in_the_bag(point, tmp_path, capsys):
    bag, config = point
    data = yaml.safe_load(config.read_text())
    data['rotor']['blades'] = 3
    bad = tmp_path / 'three.yaml'
    bad.write_text(yaml.safe_dump(data, sort_keys=False))
    line = _one_error_line(*_run(['identify', str(bag), '--config', str(bad)], capsys)[::2])
    assert 'rotor.blades = 3' in line and '4 blade joints' in line
    number = next(i for i, text in enumerate(bad.read_text().splitlines(), 1)
                  if text.strip().startswith('blades:'))
    assert f'three.yaml:{number}:' in line
    # diagnose reads its inputs by the same path
    line = _one_error_line(*_run(['diagnose', str(bag), '--config', str(bad)], capsys)[::2])
    assert 'rotor.blades = 3' in line


def test_three_of_four_joints_selected_is_said(point, tmp_path, capsys):
    """joint_names picking 3 of the 4 joints in the bag: allowed, with a warning that says so."""
    bag, config = point
    data = yaml.safe_load(config.read_text())
    data['rotor']['blades'] = 3
    data['model'] = 'multiblade'
    data['unknowns'] = ['gamma', 'theta0']
    data.pop('initial_guess')
    data['joint_names'] = ['blade_1', 'blade_2', 'blade_3']
    chosen = tmp_path / 'chosen.yaml'
    chosen.write_text(yaml.safe_dump(data, sort_keys=False))
    from rotor_id.commands.identify import load_inputs
    description, record = load_inputs(bag, chosen)
    said = [w for w in record.warnings if 'joint_names selects 3' in w]
    assert len(said) == 1 and '4 joints' in said[0] and 'rotor.blades = 3' in said[0]


def test_four_blade_description_of_a_three_blade_recording(point, tmp_path, capsys):
    n = 400
    time_s = np.arange(n) / 1000.0
    t = OMEGA * time_s
    rng = np.random.default_rng(0)
    record = Record(time_s=time_s, t=t, rotor_speed_rad_s=np.full(n, OMEGA),
                    blade_flap=0.01 + 1e-3 * rng.standard_normal((n, 3)),
                    blade_pitch=np.full((n, 3), 0.035),
                    blade_names=['blade_1', 'blade_2', 'blade_3'],
                    stamp0_ns=1_763_700_000_000_000_000)
    write_record_bag(tmp_path / 'three', record)
    config = _edit(point[1], tmp_path, window_s=[0.05, 0.35])
    line = _one_error_line(*_run(['identify', str(tmp_path / 'three'), '--config',
                                  str(config)], capsys)[::2])
    assert 'rotor.blades = 4' in line and '3 blade joints' in line


# -------------------------------------------------------------------------- keys and defaults

def test_typo_of_a_known_key_is_an_error_with_the_suggestion(point, tmp_path, capsys):
    bag, config = point
    text = config.read_text() + 'knwon: {gamma: 5.0}\n'
    bad = tmp_path / 'typo.yaml'
    bad.write_text(text)
    line = _one_error_line(*_run(['identify', str(bag), '--config', str(bad)], capsys)[::2])
    assert f'typo.yaml:{len(text.splitlines())}:' in line
    assert "'knwon'" in line and 'did you mean `known`?' in line
    # in a plan too: its own keys are known keys, their typos are caught as well
    plan = tmp_path / 'plan.yaml'
    plan.write_text((REPO / 'config' / 'plan_wake.yaml').read_text()
                    .replace('target_std:', 'target_sdt:'))
    line = _one_error_line(*_run(['plan', '--config', str(plan), '--quiet'], capsys)[::2])
    assert 'did you mean `target_std`?' in line


def test_unrelated_unknown_key_warns_once(point, tmp_path, capsys):
    bag, config = point
    extra = tmp_path / 'extra.yaml'
    extra.write_text(config.read_text() + 'operator: J. Smith\n')
    rc, _, err = _run(['identify', str(bag), '--config', str(extra), '--quiet'], capsys)
    assert rc == 0, err
    mentions = [line for line in err if 'operator' in line]
    assert len(mentions) == 1 and mentions[0].startswith('warning: ')
    assert all(line.startswith('warning: ') for line in err)


def test_parameter_neither_identified_nor_known_is_named(point, tmp_path, capsys):
    bag, config = point
    partial = _edit(config, tmp_path, unknowns=['AL_over_tau', 'inv_tau'],
                    initial_guess={'AL_over_tau': 0.25, 'inv_tau': 0.125})
    out = tmp_path / 'r.json'
    rc, _, err = _run(['identify', str(bag), '--config', str(partial), '--json', str(out),
                       '--quiet'], capsys)
    assert rc == 0, err
    data = json.loads(out.read_text())
    assert data['defaults_used'] == {'A': 0.5}
    named = [line for line in err if 'A = 0.5' in line]
    assert len(named) == 1 and named[0].startswith('warning: ') and 'known:' in named[0]
    assert any('A = 0.5' in w for w in data['warnings'])
    # with A known nothing is a default
    given = _edit(config, tmp_path, name='given.yaml', unknowns=['AL_over_tau', 'inv_tau'],
                  known={'A': 0.5}, initial_guess={'AL_over_tau': 0.25, 'inv_tau': 0.125})
    rc, _, err = _run(['identify', str(bag), '--config', str(given), '--json', str(out),
                       '--quiet'], capsys)
    assert rc == 0 and json.loads(out.read_text())['defaults_used'] == {}


def test_diagnose_names_the_same_defaults(point, tmp_path, capsys):
    bag, config = point
    partial = _edit(config, tmp_path, unknowns=['AL_over_tau', 'inv_tau'],
                    initial_guess={'AL_over_tau': 0.25, 'inv_tau': 0.125})
    out = tmp_path / 'd.json'
    rc, _, err = _run(['diagnose', str(bag), '--config', str(partial), '--json', str(out),
                       '--quiet', '--workers', '1', '--effects', 'sensor_bias'], capsys)
    assert rc == 0, err
    assert json.loads(out.read_text())['defaults_used'] == {'A': 0.5}
    assert len([line for line in err if 'A = 0.5' in line]) == 1


def test_measured_collective_is_a_named_default(point):
    """θ0 taken from the mean measured pitch is a default too (multiblade model, γ unknown)."""
    from rotor_id.io.bag import read_record
    bag, config = point
    description = load_run_description(config)
    data = yaml.safe_load(config.read_text())
    data.update(model='multiblade', unknowns=['gamma'], initial_guess={'gamma': 5.0})
    from rotor_id.io.run_description import parse_run_description
    description = parse_run_description(yaml.safe_dump(data))
    record = read_record(bag, description.topics)
    result = pipeline.identify(record, description)
    collective = float(np.mean(record.blade_pitch))
    assert set(result.defaults_used) == {'theta0'}
    assert result.defaults_used['theta0'] == pytest.approx(collective, abs=2e-4)
    assert any('theta0' in w and 'mean measured collective pitch' in w
               for w in result.warnings)
    assert result.as_json()['defaults_used']['theta0'] == pytest.approx(collective, abs=2e-4)


def test_plan_names_its_defaults(tmp_path, capsys):
    plan = tmp_path / 'plan.yaml'
    data = yaml.safe_load((REPO / 'config' / 'plan_wake.yaml').read_text())
    data['unknowns'] = ['AL_over_tau', 'inv_tau']
    data['guess'] = {'AL_over_tau': 0.25, 'inv_tau': 0.125}
    data['target_std'] = {'inv_tau': 0.008}
    data['candidates'] = {'direction': 'progressing', 'duration_rev': 2.0}
    plan.write_text(yaml.safe_dump(data))
    out = tmp_path / 'plan.json'
    rc, _, err = _run(['plan', '--config', str(plan), '--json', str(out), '--quiet'], capsys)
    assert rc in (0, 1), err
    assert json.loads(out.read_text())['defaults_used'] == {'A': 0.5}
    assert len([line for line in err if 'A = 0.5' in line]) == 1


# -------------------------------------------------------------------------- output paths

@pytest.mark.parametrize('command', ['identify', 'diagnose', 'plan'])
def test_output_paths_checked_before_any_work(point, tmp_path, capsys, command):
    bag, config = point
    args = ({'plan': ['plan', '--config', str(REPO / 'config' / 'plan_wake.yaml')]}
            .get(command, [command, str(bag), '--config', str(config)]))
    directory = tmp_path / 'a_directory'
    directory.mkdir()
    line = _one_error_line(*_run(args + ['--json', str(directory)], capsys)[::2])
    assert '--json' in line and 'is a directory' in line and str(directory) in line
    regular = tmp_path / 'a_file'
    regular.write_text('x')
    line = _one_error_line(*_run(args + ['--json', str(regular / 'sub' / 'r.json')],
                                 capsys)[::2])
    assert 'is a regular file' in line and regular.read_text() == 'x'
    if command != 'diagnose':
        line = _one_error_line(*_run(args + ['--figure', str(directory)], capsys)[::2])
        assert '--figure' in line


def test_read_only_file_system_is_named(monkeypatch, tmp_path):
    """EROFS from the file system (the probe is the real open) becomes the one-line cause."""
    def refuse(path, *args, **kwargs):
        raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(path))
    monkeypatch.setattr('builtins.open', refuse)
    with pytest.raises(common.OutputPathError, match='read-only'):
        common.check_output_path('--json', tmp_path / 'r.json')


def test_read_only_mount_end_to_end(point, tmp_path):
    """A really read-only file system (a private mount namespace), when the machine allows it."""
    unshare = shutil.which('unshare')
    if unshare is None or os.geteuid() != 0:
        pytest.skip('needs unshare and root for a private read-only mount')
    probe = subprocess.run([unshare, '-m', 'true'], capture_output=True)
    if probe.returncode != 0:
        pytest.skip(f'unshare -m not permitted here: {probe.stderr.decode().strip()}')
    bag, config = point
    mount = tmp_path / 'ro'
    mount.mkdir()
    script = (f'mount -t tmpfs -o ro tmpfs {mount} && exec {sys.executable} -m rotor_id.cli '
              f'identify {bag} --config {config} --json {mount}/r.json')
    proc = subprocess.run([unshare, '-m', 'sh', '-c', script], capture_output=True, text=True,
                          timeout=120, cwd=REPO)
    if 'mount' in proc.stderr and proc.returncode != 2:
        pytest.skip(f'cannot mount here: {proc.stderr.strip()}')
    err = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(err) == 1, proc.stderr
    assert 'read-only' in err[0] and '--json' in err[0]


# -------------------------------------------------------------------------- overflow

def test_overflowing_rotor_constant_is_named(point, tmp_path, capsys):
    bag, config = point
    data = yaml.safe_load(config.read_text())
    data['rotor']['flap_frequency'] = 1.0e300
    bad = tmp_path / 'huge.yaml'
    bad.write_text(yaml.safe_dump(data))
    line = _one_error_line(*_run(['identify', str(bag), '--config', str(bad)], capsys)[::2])
    assert 'rotor.flap_frequency' in line and 'per rev' in line
    known = _edit(config, tmp_path, name='known.yaml', model='multiblade',
                  unknowns=['theta0'], known={'gamma': 1.0e300},
                  initial_guess=None)
    line = _one_error_line(*_run(['identify', str(bag), '--config', str(known), '--quiet'],
                                 capsys)[::2])
    assert 'known.gamma' in line and 'physical range' in line


def test_divergent_iterate_is_an_error_naming_the_unknowns(point, monkeypatch):
    """A non-finite simulation inside the estimator becomes IdentificationError, not exit 3."""
    from rotor_id.io.bag import read_record
    bag, config = point
    description = load_run_description(config)
    record = read_record(bag, description.topics)

    def overflow(*args, progress=None, **kwargs):
        progress({'names': ['A', 'AL_over_tau', 'inv_tau'], 'values': [1e200, 0.2, 0.1],
                  'iteration': 1, 'rms': math.inf, 'elapsed': 0.0})
        raise FloatingPointError('overflow encountered in matmul')
    monkeypatch.setattr(pipeline, 'fit_output_error', overflow)
    with pytest.raises(IdentificationError, match=r'non-finite.*A = 1e\+200'):
        pipeline.identify(record, description, multi_start=False)


# -------------------------------------------------------------------------- warnings once

def test_python_warnings_print_once_as_warning_lines(capsys):
    import warnings
    with common.capture_warnings():
        for _ in range(3):
            warnings.warn('the same remark', RuntimeWarning)
        common.print_warning('the same remark')
        common.print_warning('warning: another')
    err = capsys.readouterr().err.splitlines()
    assert err == ['warning: the same remark', 'warning: another']


def test_a_librarys_deprecation_notice_is_not_a_warning_line(capsys):
    import warnings
    with common.capture_warnings():
        warnings.warn("module 'sre_parse' is deprecated", DeprecationWarning)
        warnings.warn('going away', PendingDeprecationWarning)
        warnings.warn('the fit is doubtful', UserWarning)
    assert capsys.readouterr().err.splitlines() == ['warning: the fit is doubtful']


def test_output_piped_into_a_reader_that_leaves_is_quiet(tmp_path):
    """`rotor-id … | head -1`: the reader leaves; no "unexpected BrokenPipeError", SIGPIPE exit."""
    import os
    import sys
    script = ('import sys\n'
              'from rotor_id import cli\n'
              'from rotor_id.commands import demo\n'
              'demo.run = lambda args: [print("a result line") for _ in range(100000)]\n'
              'sys.exit(cli.main(["demo"]))\n')
    read, write = os.pipe()
    os.close(read)                                 # the reader has left before we write
    proc = subprocess.run([sys.executable, '-c', script], stdout=write, stderr=subprocess.PIPE,
                          text=True, timeout=60)
    os.close(write)
    assert 'unexpected' not in proc.stderr and 'Traceback' not in proc.stderr, proc.stderr
    assert proc.returncode == 128 + 13
