"""
One rig description: topics, joint names, blade count, azimuth convention, read offline as live.

A rig unlike the built-in plant (hub joint ``hub``, its own topic and joint names, unwrapped
azimuth, recorded under a namespace) is read by the offline reader from the same run
description the nodes take, and gives the same record as the convention's bag of the same data.
"""

import warnings

from io_helpers import BLADES, make_record, record_streams, STAMP0, write_streams
import numpy as np
import pytest
from rotor_id.io.bag import read_record, read_run
from rotor_id.io.errors import BagError, RunDescriptionError
from rotor_id.io.run_description import (DEFAULT_NODE_TOPICS, parse_run_description,
                                         recorded_topic)

RIG = """\
rotor: {blades: 4, advance_ratio: 0.0, flap_frequency: 1.2, tip_loss: 0.97}
topics:
  blade_pitch: stand/pitch_angles
  blade_flap: stand/flap_angles
  azimuth: stand/shaft
  pitch_command: stand/pitch_setpoints
joint_names:
  azimuth: hub
  blade_flap: [flap_a, flap_b, flap_c, flap_d]
  blade_pitch: [pitch_a, pitch_b, pitch_c, pitch_d]
azimuth_convention: unwrapped
model: multiblade_wake
unknowns: [A, AL_over_tau, inv_tau]
window_s: [0.1, 0.9]
"""


def parse(text):
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        return parse_run_description(text, 'rig.yaml')


def test_rig_keys_parse():
    rig = parse(RIG)
    assert rig.azimuth_joint == 'hub' and rig.azimuth_convention == 'unwrapped'
    assert rig.topics == {'blade_pitch': 'stand/pitch_angles', 'blade_flap': 'stand/flap_angles',
                          'azimuth': 'stand/shaft'}
    assert rig.node_topics == {**DEFAULT_NODE_TOPICS, 'pitch_command': 'stand/pitch_setpoints'}
    assert rig.blade_joints('blade_flap') == ['flap_a', 'flap_b', 'flap_c', 'flap_d']
    assert rig.blade_joints('blade_pitch') == ['pitch_a', 'pitch_b', 'pitch_c', 'pitch_d']


def test_defaults_are_the_convention_relative():
    text = RIG.split('topics:')[0] + 'model: multiblade_wake\nunknowns: [A]\nwindow_s: [0, 1]\n'
    rig = parse(text)
    assert rig.topics == {'blade_pitch': 'rotor/blade_pitch', 'blade_flap': 'rotor/blade_flap',
                          'azimuth': 'rotor/azimuth'}
    assert rig.azimuth_joint == 'rotor' and rig.azimuth_convention == 'wrapped'
    assert rig.blade_joints('blade_flap') == BLADES


@pytest.mark.parametrize('edit, words', [
    (('azimuth_convention: unwrapped', 'azimuth_convention: degrees'),
     ["unknown azimuth_convention 'degrees'", 'wrapped, unwrapped']),
    (('  azimuth: hub', '  azimuth: [hub]'), ['joint_names.azimuth must be the joint name']),
    (('stand/shaft', 'stand shaft'), ['topics.azimuth must be a ROS topic name']),
    (('blade_flap: [flap_a, flap_b, flap_c, flap_d]', 'blade_flap: [flap_a, flap_b, flap_c]'),
     ['3 joint names for 4 blades']),
    (('flap_b, flap_c, flap_d]', 'flap_b, flap_a, flap_d]'), ['blade_flap: joint names repeat']),
    (('blade_pitch: [pitch_a, pitch_b, pitch_c, pitch_d]', 'blade_pitch: [pitch_a, pitch_b]'),
     ['blade_pitch: 2 joint names for 4 blades']),
    (('  azimuth: hub', '  azimuth: flap_c'),
     ["rig.yaml:8: joint_names.azimuth 'flap_c' is also the blade_flap joint of blade 3"]),
    (('  azimuth: hub', '  azimuth: pitch_a'),
     ["joint_names.azimuth 'pitch_a' is also the blade_pitch joint of blade 1"]),
    (('blade_flap: stand/flap_angles', 'blade_flap: stand/pitch_angles'),
     ["rig.yaml:4: topics.blade_flap and topics.blade_pitch are both 'stand/pitch_angles'",
      'every role needs its own topic']),
    (('pitch_command: stand/pitch_setpoints', 'pitch_command: /stand/pitch_angles'),
     ["topics.pitch_command and topics.blade_pitch are both '/stand/pitch_angles'"]),
    (('pitch_command: stand/pitch_setpoints', 'estimate: stand/shaft'),
     ["topics.estimate and topics.azimuth are both 'stand/shaft'"]),
])
def test_rig_errors(edit, words):
    with pytest.raises(RunDescriptionError) as err:
        parse(RIG.replace(*edit))
    for word in words:
        assert word in str(err.value)


def test_recorded_topic_resolution():
    available = {'/rig2/stand/shaft': 'x', '/stand/flap_angles': 'x',
                 '/rig2/stand/flap_angles': 'x', '/a/stand/pitch_angles': 'x',
                 '/b/stand/pitch_angles': 'x'}
    assert recorded_topic('stand/shaft', available) == '/rig2/stand/shaft'     # one namespace
    assert recorded_topic('stand/flap_angles', available) == '/stand/flap_angles'   # root first
    assert recorded_topic('stand/pitch_angles', available) is None             # ambiguous
    assert recorded_topic('/stand/shaft', available) == '/stand/shaft'         # absolute
    assert recorded_topic('stand/none', available) is None


def _rig_bag(path, record, namespace='/rig2'):
    """Write the rig's bag of ``record``: own names, hub joint, unwrapped azimuth far from 0."""
    stamps = STAMP0 + np.round(record.time_s * 1e9).astype(np.int64)
    unwrapped = (record.t + 2 * np.pi * 1000)[:, None]      # an encoder after 1000 turns
    pitch_joints = ['pitch_a', 'pitch_b', 'pitch_c', 'pitch_d']
    flap_joints = ['flap_a', 'flap_b', 'flap_c', 'flap_d']
    return write_streams(path, {
        f'{namespace}/stand/pitch_angles': (stamps, pitch_joints, record.blade_pitch, None),
        f'{namespace}/stand/flap_angles': (stamps, flap_joints, record.blade_flap, None),
        f'{namespace}/stand/shaft': (stamps, ['hub'], unwrapped,
                                     record.rotor_speed_rad_s[:, None]),
    })


def test_offline_reads_the_rig_as_described(tmp_path):
    record = make_record(n=1000)
    rig = parse(RIG)
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')
        got = read_record(_rig_bag(tmp_path / 'rig', record), **rig.record_options())
        reference = read_record(write_streams(tmp_path / 'ref', record_streams(record)))
    np.testing.assert_array_equal(got.blade_flap, reference.blade_flap)
    np.testing.assert_array_equal(got.blade_pitch, reference.blade_pitch)
    # the same nondimensional time up to whole revolutions (the origin is ψ of the first sample)
    np.testing.assert_allclose(got.t - reference.t, 0.0, atol=1e-9)
    assert '/rig2/stand/flap_angles' in got.source
    (tmp_path / 'rig.yaml').write_text(RIG)
    described = read_run(parse_run_description(RIG, tmp_path / 'rig.yaml'), tmp_path / 'rig')
    np.testing.assert_array_equal(described.blade_flap, got.blade_flap)


def test_offline_wrong_azimuth_joint_is_one_clear_error(tmp_path):
    record = make_record(n=200)
    bag = _rig_bag(tmp_path / 'rig', record)
    options = parse(RIG.replace('azimuth: hub', 'azimuth: rotor')).record_options()
    with pytest.raises(BagError, match=r"expected the azimuth joint 'rotor', got \['hub'\]; set "
                                       'joint_names.azimuth'):
        read_record(bag, **options)


def test_unwrapped_read_as_wrapped_is_refused(tmp_path):
    """Refuse an encoder's continuous azimuth declared wrapped, as the live nodes do."""
    bag = _rig_bag(tmp_path / 'rig', make_record(n=200))
    options = parse(RIG.replace('azimuth_convention: unwrapped',
                                'azimuth_convention: wrapped')).record_options()
    with pytest.raises(BagError, match='set azimuth_convention: unwrapped'):
        read_record(bag, **options)
