"""
launch/rotor_id.launch.py names only executables and parameter files that exist (CONVENTIONS §10).

launch and launch_ros are not installable here, so the file is executed against small stand-ins
of the classes it uses; every Node must name a console_scripts entry of setup.py, every case's
parameter file must exist in config/ (installed to share/rotor_id/config by setup.py), hold a
section for each launched node, and the run descriptions those sections name must load. With the
real launch_ros importable, the real generate_launch_description() is called as well.
"""

import ast
import importlib.util
from pathlib import Path
import sys
import types

import pytest
import yaml

REPO = Path(__file__).resolve().parents[2]
LAUNCH_FILE = REPO / 'launch' / 'rotor_id.launch.py'


class _Recorded:
    def __init__(self, *args, **kwargs):
        self.args = args
        self.kwargs = kwargs


class LaunchConfiguration(_Recorded):
    """Stand-in: remembers the argument name."""


class PathJoinSubstitution(_Recorded):
    """Stand-in: remembers the parts."""


def _resolve(value, arguments):
    """Evaluate a stand-in substitution tree with the given launch argument values."""
    if isinstance(value, LaunchConfiguration):
        return _resolve(arguments[value.args[0]], arguments)
    if isinstance(value, PathJoinSubstitution):
        parts = [_resolve(p, arguments) for p in value.args[0]]
        return str(Path(*parts))
    if isinstance(value, list):
        return ''.join(_resolve(p, arguments) for p in value)
    return value


def _stand_ins(monkeypatch):
    modules = {
        'launch': {'LaunchDescription': type('LaunchDescription', (_Recorded,), {})},
        'launch.actions': {'DeclareLaunchArgument': type('DeclareLaunchArgument', (_Recorded,),
                                                         {})},
        'launch.conditions': {'IfCondition': type('IfCondition', (_Recorded,), {})},
        'launch.substitutions': {'LaunchConfiguration': LaunchConfiguration,
                                 'PathJoinSubstitution': PathJoinSubstitution},
        'launch_ros': {},
        'launch_ros.actions': {'Node': type('Node', (_Recorded,), {})},
    }
    for name, attributes in modules.items():
        module = types.ModuleType(name)
        module.__dict__.update(attributes)
        monkeypatch.setitem(sys.modules, name, module)
    fake_index = types.ModuleType('ament_index_python.packages')
    fake_index.get_package_share_directory = lambda package: str(REPO)
    monkeypatch.setitem(sys.modules, 'ament_index_python.packages', fake_index)


def _load(module_name='rotor_id_launch_under_test'):
    spec = importlib.util.spec_from_file_location(module_name, LAUNCH_FILE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _console_scripts():
    tree = ast.parse((REPO / 'setup.py').read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Dict):
            for key, value in zip(node.keys, node.values):
                if isinstance(key, ast.Constant) and key.value == 'console_scripts':
                    return {ast.literal_eval(item).split('=')[0].strip() for item in value.elts}
    raise AssertionError('no console_scripts in setup.py')


def test_launch_file_names_existing_executables_and_parameter_files(monkeypatch):
    compile(LAUNCH_FILE.read_text(), str(LAUNCH_FILE), 'exec')
    _stand_ins(monkeypatch)
    description = _load().generate_launch_description()
    entities = description.args[0]
    arguments = {e.args[0]: e.kwargs.get('default_value') for e in entities
                 if type(e).__name__ == 'DeclareLaunchArgument'}
    nodes = [e for e in entities if type(e).__name__ == 'Node']
    scripts = _console_scripts()
    assert {n.kwargs['executable'] for n in nodes} == {
        'rotor_plant', 'stirring_input', 'identifier', 'state_estimator', 'recorder'}
    for node in nodes:
        assert node.kwargs['package'] == 'rotor_id'
        assert node.kwargs['executable'] in scripts, node.kwargs['executable']
        condition = node.kwargs['condition'].args[0]
        assert condition.args[0] in arguments, f'undeclared launch argument {condition.args[0]}'
    from rotor_id.io.run_description import load_run_description
    for case in ('wake', 'multiblade', 'single_blade'):
        params_file = Path(_resolve(arguments['params_file'], {**arguments, 'case': case}))
        assert params_file.is_file(), params_file
        params = yaml.safe_load(params_file.read_text())
        for node in nodes:
            assert f'/**/{node.kwargs["name"]}' in params, (params_file, node.kwargs['name'])
        # one rig description for every node, the same file
        runs = {params[f'/**/{node.kwargs["name"]}']['ros__parameters']['run_description']
                for node in nodes}
        assert len(runs) == 1, runs
        load_run_description(params_file.parent / runs.pop())
    # installed where the launch file looks: setup.py puts config/*.yaml into share/rotor_id
    setup = (REPO / 'setup.py').read_text()
    assert "'/config', sorted(glob('config/*.yaml'))" in setup
    assert "'/launch', sorted(glob('launch/*.launch.py'))" in setup


def test_real_launch_description():
    pytest.importorskip('launch_ros', reason='launch_ros is not installable here (TOOLCHAIN.md)')
    description = _load('rotor_id_launch_real').generate_launch_description()
    assert len(description.entities) >= 5
