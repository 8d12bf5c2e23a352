"""Run descriptions: the README schema, the optional keys, and errors that point at the line."""

import warnings

from io_helpers import make_record, RECORDING_NAMES
import pytest
from rotor_id.io.errors import RunDescriptionError, RunDescriptionWarning
from rotor_id.io.run_description import (
    load_run_description, normalize_joint_names, parse_run_description, validate_window,
)

BASE = """\
rotor:
  blades: 4
  advance_ratio: 0.0
  flap_frequency: 1.2
  tip_loss: 0.97
topics: {blade_pitch: /rotor/blade_pitch, blade_flap: /rotor/blade_flap, azimuth: /rotor/azimuth}
model: multiblade_wake
unknowns: [A, AL_over_tau, inv_tau]
window_s: [0.809, 0.937]
"""


def parse(text, path='run.yaml'):
    with warnings.catch_warnings():
        warnings.simplefilter('error')   # no warning unless a test expects one
        return parse_run_description(text, path)


def error_of(text):
    with pytest.raises(RunDescriptionError) as err:
        parse(text)
    return err.value


@pytest.mark.parametrize('name', RECORDING_NAMES)
def test_shared_run_descriptions_load(recordings, name):
    description = load_run_description(recordings / f'{name}.yaml')
    assert description.rotor.blades == 4
    assert description.rotor.tip_loss == 0.97 and description.rotor.flap_frequency == 1.2
    assert description.topics['blade_flap'] == '/rotor/blade_flap'
    assert description.model in ('multiblade', 'multiblade_constant', 'multiblade_wake')
    assert set(description.unknowns) <= set(description.parameters)
    assert description.window_s[1] > description.window_s[0] >= 0
    assert description.bag_path() == recordings / name
    assert description.initial_state == 'estimate' and description.method == 'output-error'
    assert description.warnings == ()


def test_readme_example_parses():
    description = parse(BASE)
    assert description.model == 'multiblade_wake'
    assert description.unknowns == ('A', 'AL_over_tau', 'inv_tau')
    assert description.window_s == (0.809, 0.937)
    assert description.known == {} and description.joint_names is None
    assert description.measurement is None and description.noise_std_rad is None


def test_optional_keys():
    description = parse(BASE.replace('unknowns: [A, AL_over_tau, inv_tau]',
                                     'unknowns: [AL_over_tau, inv_tau]') + """\
joint_names: {blade_1: b1, blade_2: b2, blade_3: b3, blade_4: b4}
known: {A: 0.49797745125}
initial_guess: {AL_over_tau: 0.2, inv_tau: 0.1}
initial_state: equilibrium
noise_std_rad: 0.0009
method: output-error
measurement: eq30
lock_number: 4.5
""")
    assert description.joint_names == {'blade_pitch': ('b1', 'b2', 'b3', 'b4'),
                                       'blade_flap': ('b1', 'b2', 'b3', 'b4')}
    assert description.known == {'A': 0.49797745125, 'gamma': 4.5}   # A = γB⁴/8
    assert description.lock_number == 4.5
    assert description.initial_guess == {'AL_over_tau': 0.2, 'inv_tau': 0.1}
    assert description.initial_state == 'equilibrium'
    assert description.noise_std_rad == 0.0009
    assert description.measurement == 'eq30'


def test_joint_names_forms():
    four = ['a', 'b', 'c', 'd']
    assert normalize_joint_names(four)['blade_flap'] == tuple(four)
    assert normalize_joint_names({1: 'a', 2: 'b', 3: 'c', 4: 'd'}, 4)['blade_pitch'] == tuple(four)
    per_role = normalize_joint_names({'blade_pitch': four, 'blade_flap': ['p', 'q', 'r', 's']})
    assert per_role['blade_flap'] == ('p', 'q', 'r', 's')
    assert per_role['blade_pitch'] == tuple(four)
    with pytest.raises(ValueError, match='3 joint names for 4 blades'):
        normalize_joint_names(['a', 'b', 'c'], 4)
    with pytest.raises(ValueError, match='not 1..3'):
        normalize_joint_names({'blade_1': 'a', 'blade_2': 'b', 'blade_4': 'c'})
    with pytest.raises(ValueError, match='repeat'):
        normalize_joint_names(['a', 'a'])


def test_unknown_keys_warn_but_load():
    with pytest.warns(RunDescriptionWarning, match=r"run.yaml:10: unknown key 'operator'"):
        description = parse_run_description(BASE + 'operator: jane\n', 'run.yaml')
    assert description.extra == {'operator': 'jane'}
    assert len(description.warnings) == 1


@pytest.mark.parametrize('edit, words, line', [
    (('model: multiblade_wake', 'model: wake'),
     ["unknown model 'wake'", 'single_blade', 'multiblade_wake'], 7),
    (('unknowns: [A, AL_over_tau, inv_tau]', 'unknowns: [A, gamma_x]'),
     ["unknown parameter 'gamma_x' for model multiblade_wake", 'inv_tau'], 8),
    (('model: multiblade_wake', 'model: multiblade'),
     ["unknown parameter 'A' for model multiblade", 'gamma, theta0, delta'], 8),
    (('window_s: [0.809, 0.937]', 'window_s: [0.9, 0.8]'), ['window_s', 'increasing'], 9),
    (('window_s: [0.809, 0.937]', 'window_s: [0.9]'), ['window_s must be two numbers'], 9),
    (('window_s: [0.809, 0.937]', 'window_s: [-0.1, 0.8]'), ['window_s.0', 'at least 0'], 9),
    (('window_s: [0.809, 0.937]', 'window_s: [a, 0.8]'), ['window_s.0 must be a number'], 9),
    (('  blades: 4', '  blades: 0'), ['rotor.blades', 'at least 1'], 2),
    (('  blades: 4', '  blades: 2.5'), ['rotor.blades must be an integer'], 2),
    (('  advance_ratio: 0.0', '  advance_ratio: -0.4'), ['rotor.advance_ratio', 'negative'], 3),
    (('  tip_loss: 0.97', '  tip_loss: 1.5'), ['tip_loss must be in (0, 1]'], 5),
    (('  flap_frequency: 1.2\n', ''), ["missing required key 'rotor.flap_frequency'"], 1),
    (('blade_flap: /rotor/blade_flap', 'blade_flap: rotor//flap'),
     ['topics.blade_flap must be a ROS topic name', 'relative'], 6),
    (('blade_flap: /rotor/blade_flap', 'blade_flap: 2rotor'),
     ['topics.blade_flap must be a ROS topic name'], 6),
])
def test_errors_name_file_line_and_fix(edit, words, line):
    text = BASE.replace(*edit)
    assert text != BASE
    error = error_of(text)
    message = str(error)
    assert message.startswith(f'run.yaml:{line}: ')
    assert error.line == line and error.path == 'run.yaml'
    for word in words:
        assert word in message


@pytest.mark.parametrize('extra, words', [
    ('known: {gamma: -5}', ['known.gamma must be positive']),
    ('known: {delta: 1}', ["unknown parameter 'delta' for model multiblade_wake"]),
    ('known: {A: 0.5}', ["['A'] are both unknown and known"]),
    ('initial_state: steady', ["unknown initial_state 'steady'", 'equilibrium']),
    ('measurement: flap', ["unknown measurement 'flap'", 'eq30']),
    ('method: magic', ["unknown method 'magic'", 'output-error']),
    ('noise_std_rad: 0', ['noise_std_rad must be positive']),
    ('noise_std_rad: 5', ['radians']),
    ('lock_number: 5\nknown: {gamma: 4}', ['contradicts known.gamma']),
    ('joint_names: [a, b]', ['2 joint names for 4 blades']),
    ('lock_number: 4.5', ['A is unknown but fixed by the known γ', 'run.yaml:10:']),
    ('model: multiblade', ["key 'model' is given twice (lines 7 and 10)"]),
])
def test_errors_of_optional_keys(extra, words):
    message = str(error_of(BASE + extra + '\n'))
    assert message.startswith('run.yaml:')
    for word in words:
        assert word in message


def test_wake_gain_and_lock_number_are_one_parameter():
    fixed = BASE.replace('[A, AL_over_tau, inv_tau]', '[AL_over_tau, inv_tau]')
    message = str(error_of(fixed + 'known: {gamma: 4.5, A: 0.3}\n'))
    assert 'contradicts γ = 4.5' in message and 'A = γB⁴/8 = 0.49' in message
    message = str(error_of(BASE.replace('[A, AL_over_tau, inv_tau]', '[A, gamma]')))
    assert 'both A and gamma' in message
    assert parse(fixed + 'lock_number: 4.5\n').known == {'gamma': 4.5}


def test_theta0_in_degrees_is_caught():
    text = BASE.replace('multiblade_wake', 'multiblade').replace(
        '[A, AL_over_tau, inv_tau]', '[gamma]') + 'known: {theta0: 2.0}\n'
    assert 'looks like degrees' in str(error_of(text))


@pytest.mark.parametrize('text, words', [
    ('rotor: [1, 2\n', ['malformed YAML']),
    ('', ['the document must be a mapping']),
    ('- a\n- b\n', ['the document must be a mapping']),
    ('rotor: !!python/object:os.system x\n', ['malformed YAML']),
])
def test_malformed_yaml(text, words):
    message = str(error_of(text))
    for word in words:
        assert word in message


def test_load_missing_file(tmp_path):
    with pytest.raises(RunDescriptionError, match='cannot read the run description'):
        load_run_description(tmp_path / 'none.yaml')


def test_validate_window_names_the_record_span():
    record = make_record(n=500)                     # spans 0 .. 0.499 s
    validate_window(parse(BASE.replace('[0.809, 0.937]', '[0.1, 0.4995]')), record)
    with pytest.raises(RunDescriptionError, match=r'outside the record.*\[0.000000, 0.499000\]'):
        validate_window(parse(BASE), record)
    with pytest.raises(RunDescriptionError, match='outside the record'):
        validate_window(parse(BASE.replace('[0.809, 0.937]', '[0.1, 0.501]')), record)
