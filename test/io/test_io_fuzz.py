"""Property-based fuzzing: bad input gives the documented error type and nothing else."""

from pathlib import Path
import tempfile
import warnings

from hypothesis import example, given, HealthCheck, settings, strategies as st
from io_helpers import make_record
import pytest
from rotor_id.io.bag import BagError, read_record, write_record_bag
from rotor_id.io.errors import RunDescriptionError
from rotor_id.io.record import Record
from rotor_id.io.run_description import parse_run_description, RunDescription
import yaml

KEYS = ['rotor', 'topics', 'model', 'unknowns', 'window_s', 'joint_names', 'known',
        'initial_guess', 'initial_state', 'noise_std_rad', 'method', 'measurement',
        'lock_number', 'blades', 'advance_ratio', 'flap_frequency', 'tip_loss', 'blade_pitch',
        'blade_flap', 'azimuth', 'gamma', 'theta0', 'A', 'inv_tau', 'blade_1', 'multiblade']
scalars = (st.none() | st.booleans() | st.integers(-10**30, 10**30)
           | st.floats(allow_nan=True, allow_infinity=True) | st.sampled_from(KEYS)
           | st.text(max_size=8))
values = st.recursive(scalars, lambda inner: st.lists(inner, max_size=4)
                      | st.dictionaries(st.sampled_from(KEYS) | scalars, inner, max_size=5),
                      max_leaves=12)
documents = st.dictionaries(st.sampled_from(KEYS) | st.text(max_size=6), values, max_size=9)

VALID = {
    'rotor': {'blades': 4, 'advance_ratio': 0.4, 'flap_frequency': 1.2, 'tip_loss': 0.97},
    'model': 'multiblade', 'unknowns': ['gamma', 'theta0'], 'window_s': [0.19, 0.32],
}


def parse_or_error(text):
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')
        try:
            return parse_run_description(text, 'fuzz.yaml')
        except RunDescriptionError as err:
            assert str(err).startswith('fuzz.yaml')
            return err


@settings(max_examples=80)
@given(document=documents)
def test_random_mappings_parse_or_raise_run_description_error(document):
    text = yaml.safe_dump(document, allow_unicode=True)
    assert isinstance(parse_or_error(text), (RunDescription, RunDescriptionError))


@settings(max_examples=80)
@given(changes=st.dictionaries(st.sampled_from(KEYS), values, max_size=3),
       drop=st.sets(st.sampled_from(sorted(VALID))))
def test_mutated_valid_descriptions_parse_or_raise(changes, drop):
    document = {k: v for k, v in VALID.items() if k not in drop}
    document.update(changes)
    result = parse_or_error(yaml.safe_dump(document, allow_unicode=True))
    assert isinstance(result, (RunDescription, RunDescriptionError))
    if not drop and not changes:
        assert isinstance(result, RunDescription)


@settings(max_examples=150)
@given(text=st.text(max_size=200))
@example(text='a: &x [*x]')
@example(text='[' * 200)
@example(text='rotor: {blades: 99999999999999999999999999999999999999999999999999999}')
def test_random_text_parses_or_raises(text):
    assert isinstance(parse_or_error(text), (RunDescription, RunDescriptionError))


_BAGS = {}


def clean_bag(storage):
    """Bytes of a small valid bag's storage file (written once per test run)."""
    if storage not in _BAGS:
        with tempfile.TemporaryDirectory() as tmp:
            bag = write_record_bag(Path(tmp) / 'bag', make_record(n=60), storage=storage)
            suffix = {'mcap': '.mcap', 'sqlite3': '.db3'}[storage]
            _BAGS[storage] = ((bag / f'bag{suffix}').read_bytes(), suffix)
    return _BAGS[storage]


def corrupt(data, edits, cut):
    data = bytearray(data)
    for position, value in edits:
        data[position % len(data)] = value
    return bytes(data[:max(1, int(len(data) * cut))])


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
@settings(max_examples=40, suppress_health_check=[HealthCheck.too_slow])
@given(edits=st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 255)), max_size=12),
       cut=st.sampled_from([1.0, 1.0, 0.9, 0.5, 0.25, 0.01]))
# a byte of a message's receive time set to 0x80: a time beyond the 64-bit range (found by
# hypothesis; it raised OverflowError instead of reading the rest)
@example(edits=[(1181, 128)], cut=0.9)
# a sqlite3 row whose timestamp reads NULL (found by hypothesis; it raised TypeError)
@example(edits=[(26884, 0)], cut=1.0)
def test_corrupted_bags_read_or_raise_bag_error(storage, edits, cut):
    data, suffix = clean_bag(storage)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f'corrupt{suffix}'
        path.write_bytes(corrupt(data, edits, cut))
        with warnings.catch_warnings():
            warnings.simplefilter('ignore')
            try:
                record = read_record(path)
            except BagError:
                return
    assert isinstance(record, Record) and len(record) >= 1
