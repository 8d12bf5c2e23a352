"""
Every node refuses a rig it cannot read right, at start, with the one line ``ros2 run`` prints.

What it proves: the identifier, state estimator, stirring input, rotor plant and recorder, each
constructed as ``ros2 run`` constructs it (its ``run_description`` parameter naming the file),
raise a ValueError (rotor_id.nodes.common.spin_node prints it as one line and exits 2) naming the
file, the line and the problem, before any subscription or fit: a blade joint list whose length
is not ``rotor.blades``, a joint name repeated, the azimuth joint also a blade's, an unknown
azimuth convention, the pitch command on the pitch sensor's topic; and the identifier and state
estimator a model the rotor cannot have (multiblade_wake of a 2-bladed rotor: it has no
cyclic modes to fit).
"""


import pytest
from ros_domains import next_domain

rclpy = pytest.importorskip('rclpy', reason='rclpy not importable')
pytest.importorskip('rotor_id_msgs.msg', reason='rotor_id_msgs not built')

GOOD = """\
rotor: {blades: 3, advance_ratio: 0.0, flap_frequency: 1.2, tip_loss: 0.97}
topics: {blade_pitch: s/pitch, blade_flap: s/flap, azimuth: s/azimuth, pitch_command: s/cmd}
joint_names: {azimuth: hub, blade_flap: [f1, f2, f3], blade_pitch: [p1, p2, p3]}
azimuth_convention: unwrapped
model: multiblade_wake
unknowns: [A, AL_over_tau, inv_tau]
window_s: [0.80939, 0.93671]
"""
BAD = {
    'count': (('blade_flap: [f1, f2, f3]', 'blade_flap: [f1, f2]'),
              'rig.yaml:3: blade_flap: 2 joint names for 3 blades'),
    'repeat': (('[p1, p2, p3]', '[p1, p2, p1]'), 'rig.yaml:3: blade_pitch: joint names repeat'),
    'azimuth_is_a_blade': (('azimuth: hub', 'azimuth: f2'),
                           "rig.yaml:3: joint_names.azimuth 'f2' is also the blade_flap joint "
                           'of blade 2'),
    'convention': (('unwrapped', 'encoder'), "rig.yaml:4: unknown azimuth_convention 'encoder'"),
    'command_on_sensor': (('pitch_command: s/cmd', 'pitch_command: /s/pitch'),
                          'rig.yaml:2: topics.pitch_command and topics.blade_pitch are both '
                          "'/s/pitch'"),
}
NODES = ('identifier', 'state_estimator', 'stirring_input', 'rotor_plant', 'recorder')


def _construct(name, path, tmp_path):
    from rclpy.parameter import Parameter
    from rclpy.signals import SignalHandlerOptions
    module = __import__(f'rotor_id.nodes.{name}', fromlist=['_'])
    cls = {'identifier': 'Identifier', 'state_estimator': 'StateEstimator',
           'stirring_input': 'StirringInput', 'rotor_plant': 'RotorPlant',
           'recorder': 'Recorder'}[name]
    context = rclpy.context.Context()
    rclpy.init(context=context, domain_id=next_domain(),   # Fast DDS: at most 232
               signal_handler_options=SignalHandlerOptions.NO)
    params = [Parameter('run_description', value=str(path))]
    if name == 'recorder':
        params.append(Parameter('output', value=str(tmp_path / 'bag')))
    node = None
    try:
        node = getattr(module, cls)(parameter_overrides=params, context=context)
    finally:
        if node is not None:
            getattr(node, 'close', lambda: None)()
            node.destroy_node()
        rclpy.try_shutdown(context=context)


@pytest.mark.parametrize('node', NODES)
@pytest.mark.parametrize('case', sorted(BAD))
def test_an_invalid_rig_is_refused_at_start(tmp_path, node, case):
    edit, words = BAD[case]
    path = tmp_path / 'rig.yaml'
    path.write_text(GOOD.replace(*edit))
    with pytest.raises(ValueError) as error:
        _construct(node, path, tmp_path)
    assert words in str(error.value) and '\n' not in str(error.value).strip(), error.value


@pytest.mark.parametrize('node', ['identifier', 'state_estimator'])
def test_a_model_the_rotor_cannot_have_is_refused_at_start(tmp_path, node):
    path = tmp_path / 'rig.yaml'
    path.write_text(GOOD.replace('blades: 3', 'blades: 2').replace(
        'blade_flap: [f1, f2, f3], blade_pitch: [p1, p2, p3]',
        'blade_flap: [f1, f2], blade_pitch: [p1, p2]'))
    with pytest.raises(ValueError, match='a 2-bladed rotor has no cyclic flap'):
        _construct(node, path, tmp_path)
