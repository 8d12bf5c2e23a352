"""
launch/rotor_id.launch.py as Jazzy's launch and launch_ros evaluate it.

The file is evaluated twice, and both must give the same nodes with the same command lines:

* against stand-ins of the launch classes it uses, as strict as Jazzy's (launch 3.4, launch_ros
  0.26): a substitution is a str, a Substitution or a flat iterable of those (a nested list is a
  TypeError there, so here), a default outside ``choices`` is refused, a condition is
  true/false/1/0, an action takes only the keywords the real one takes;
* against the real launch and launch_ros, when they are importable (a ROS 2 Jazzy install; the
  pinned wheels here have none, so those tests skip saying so): the description is visited with
  a LaunchContext, as ``ros2 launch`` does, without starting processes; and once it is really
  launched under a namespace with a LaunchService, the five nodes appear in that namespace and
  all stop on one SIGINT.

What is checked of each launch: every Node names a console_scripts entry of setup.py; every
case's parameter file exists in config/ (installed to share/rotor_id/config), holds a section
for each node, and the one run description they name loads; ``use_namespace:=true
namespace:=<ns>`` puts every node into /<ns>; ``log_level`` reaches every node as
``--ros-args --log-level``; a node switched off is not launched.
"""

import ast
import importlib.util
import os
from pathlib import Path
import re
import signal
import subprocess
import sys
import time
import types

import pytest
import yaml

REPO = Path(__file__).resolve().parents[2]
LAUNCH_FILE = REPO / 'launch' / 'rotor_id.launch.py'
NODES = {'rotor_plant': 'plant', 'stirring_input': 'stirring', 'identifier': 'identifier',
         'state_estimator': 'state_estimator', 'recorder': 'recorder'}


# ------------------------------------------------------------------------- strict stand-ins
class Substitution:
    """Stand-in of launch.Substitution."""


class TextSubstitution(Substitution):
    """Stand-in: a literal text."""

    def __init__(self, *, text):
        self.text = text

    def perform(self, context):
        return self.text


def normalize(subs):
    """launch.utilities.normalize_to_list_of_substitutions, as in Jazzy: no nested lists."""
    def one(x):
        if isinstance(x, Substitution):
            return x
        if isinstance(x, str):
            return TextSubstitution(text=x)
        raise TypeError(f"Failed to normalize given item of type '{type(x)}', when only 'str' "
                        "or 'launch.Substitution' were expected.")
    if isinstance(subs, str):
        return [TextSubstitution(text=subs)]
    if isinstance(subs, Substitution):
        return [subs]
    return [one(x) for x in subs]


def perform(subs, context):
    """launch.utilities.perform_substitutions: the performed parts concatenated."""
    return ''.join(s.perform(context) for s in subs)


class LaunchConfiguration(Substitution):
    """Stand-in: the value of a launch argument (KeyError-like failure when undeclared)."""

    def __init__(self, variable_name, *, default=None):
        self.variable_name = normalize(variable_name)
        self.default = None if default is None else normalize(default)

    def perform(self, context):
        name = perform(self.variable_name, context)
        if name in context.configurations:
            return context.configurations[name]
        if self.default is not None:
            return perform(self.default, context)
        raise LookupError(f"launch configuration '{name}' does not exist")


class PathJoinSubstitution(Substitution):
    """Stand-in: os.path.join of a flat iterable of str / Substitution."""

    def __init__(self, substitutions):
        self.parts = normalize(substitutions)

    def perform(self, context):
        return os.path.join(*(s.perform(context) for s in self.parts))


class IfCondition:
    """Stand-in of launch.conditions.IfCondition: 'true'/'false'/'1'/'0', any case."""

    def __init__(self, predicate_expression):
        self.expression = normalize(predicate_expression)

    def evaluate(self, context):
        value = perform(self.expression, context).lower()
        if value in ('true', '1'):
            return True
        if value in ('false', '0'):
            return False
        raise RuntimeError(f"Unknown value '{value}' for a condition (true/false/1/0)")


class Action:
    """Stand-in of launch.Action: only ``condition`` as keyword."""

    def __init__(self, *, condition=None):
        self.condition = condition


class DeclareLaunchArgument(Action):
    """Stand-in: Jazzy's checks of the default against ``choices``."""

    def __init__(self, name, *, default_value=None, description=None, choices=None, **kwargs):
        super().__init__(**kwargs)
        if not isinstance(name, str):
            raise TypeError('name must be a str')
        self.name = name
        self.default_value = None if default_value is None else normalize(default_value)
        if choices is not None and not choices:
            raise RuntimeError('Provided choices arg is empty.')
        if (choices is not None and default_value is not None
                and not isinstance(default_value, (Substitution, list))
                and default_value not in choices):
            raise RuntimeError(f'Provided default_value "{default_value}" is not in provided '
                               f'choices "{choices}".')
        self.choices = choices
        self.description = description

    def execute(self, context):
        if self.name not in context.configurations:
            if self.default_value is None:
                raise RuntimeError(f"Required launch argument '{self.name}' was not provided")
            context.configurations[self.name] = perform(self.default_value, context)
        value = context.configurations[self.name]
        if self.choices is not None and value not in self.choices:
            raise RuntimeError(f"Argument '{self.name}' provided value '{value}' is not valid. "
                               f'Valid options are: {self.choices}')
        return []


class GroupAction(Action):
    """Stand-in: a scoped group (launch configurations restored after it)."""

    def __init__(self, actions, *, scoped=True, forwarding=True, launch_configurations=None,
                 **kwargs):
        super().__init__(**kwargs)
        self.actions = list(actions)
        if not all(isinstance(a, Action) for a in self.actions):
            raise TypeError('GroupAction takes actions')
        self.scoped = scoped

    def execute(self, context):
        saved = dict(context.configurations)
        nodes = visit(self.actions, context)
        if self.scoped:
            context.configurations.clear()
            context.configurations.update(saved)
        return nodes


def _prefix_namespace(base, namespace):
    """launch_ros.utilities.prefix_namespace + make_namespace_absolute."""
    if namespace is None:
        return base
    if not namespace.startswith('/') and base:
        namespace = base.rstrip('/') + '/' + namespace
    return '/' + namespace.lstrip('/') if namespace else namespace


class PushROSNamespace(Action):
    """Stand-in of launch_ros.actions.PushROSNamespace."""

    def __init__(self, namespace, **kwargs):
        super().__init__(**kwargs)
        self.namespace = normalize(namespace)

    def execute(self, context):
        context.configurations['ros_namespace'] = _prefix_namespace(
            context.configurations.get('ros_namespace'), perform(self.namespace, context))
        return []


class ParameterValue:
    """Stand-in of launch_ros.parameter_descriptions.ParameterValue."""

    def __init__(self, value, *, value_type=None):
        self.value = normalize(value) if isinstance(value, (str, Substitution)) else value
        self.value_type = value_type

    def evaluate(self, context):
        text = perform(self.value, context)
        return text if self.value_type is str else yaml.safe_load(text or "''")


#: keywords launch_ros 0.26's Node takes besides its own (ExecuteProcess's and Action's)
PROCESS_KEYWORDS = {'condition', 'output', 'cwd', 'env', 'additional_env', 'shell',
                    'sigterm_timeout', 'sigkill_timeout', 'emulate_tty', 'prefix', 'respawn',
                    'respawn_delay', 'on_exit', 'log_cmd', 'output_format', 'cached_output'}


class Node(Action):
    """Stand-in of launch_ros.actions.Node (keyword-only, as in Jazzy)."""

    def __init__(self, *, executable, package=None, name=None, namespace=None, exec_name=None,
                 parameters=None, remappings=None, ros_arguments=None, arguments=None,
                 **kwargs):
        unknown = set(kwargs) - PROCESS_KEYWORDS
        if unknown:
            raise TypeError(f'Node got unexpected keyword arguments {sorted(unknown)}')
        super().__init__(condition=kwargs.get('condition'))
        self.executable, self.package = normalize(executable), normalize(package)
        self.name = None if name is None else normalize(name)
        self.namespace = None if namespace is None else normalize(namespace)
        self.arguments = [normalize(a) for a in arguments or ()]
        self.ros_arguments = [normalize(a) for a in ros_arguments or ()]
        self.parameters = []
        for item in parameters or ():
            if isinstance(item, dict):
                for key, value in item.items():
                    if not isinstance(key, str):
                        raise TypeError('parameter names are str')
                    if not isinstance(value, (bool, int, float, str, Substitution, list,
                                              ParameterValue)):
                        raise TypeError(f'parameter {key}: type {type(value)} not allowed')
                self.parameters.append(item)
            elif isinstance(item, Path):
                self.parameters.append(item)
            else:
                self.parameters.append(normalize(item))       # a parameter file

    def evaluate(self, context):
        """Return the launched node: executable, name, namespace, arguments, parameters."""
        def value(v):
            if isinstance(v, ParameterValue):
                return v.evaluate(context)
            if isinstance(v, Substitution):
                return yaml.safe_load(v.perform(context) or "''")
            return v
        files, overrides = [], {}
        for item in self.parameters:
            if isinstance(item, dict):
                overrides.update({k: value(v) for k, v in item.items()})
            else:
                files.append(str(item) if isinstance(item, Path) else perform(item, context))
        namespace = _prefix_namespace(
            context.configurations.get('ros_namespace'),
            None if self.namespace is None else perform(self.namespace, context))
        return {'executable': perform(self.executable, context),
                'package': perform(self.package, context),
                'name': perform(self.name, context), 'namespace': namespace or '/',
                'arguments': [perform(a, context) for a in self.arguments],
                'ros_arguments': [perform(a, context) for a in self.ros_arguments],
                'files': files, 'overrides': overrides}


class LaunchDescription:
    """Stand-in: a list of actions."""

    def __init__(self, initial_entities=None, *, deprecated_reason=None):
        self.entities = list(initial_entities or ())
        if not all(isinstance(e, Action) for e in self.entities):
            raise TypeError('a LaunchDescription holds actions')


class StandInContext:
    """The launch configurations, set from the command line's ``name:=value``."""

    def __init__(self, arguments):
        self.configurations = dict(arguments)


def visit(entities, context):
    """Run the actions in order, as the launch service does; return the nodes launched."""
    nodes = []
    for entity in entities:
        if entity.condition is not None and not entity.condition.evaluate(context):
            continue
        if isinstance(entity, Node):
            nodes.append(entity.evaluate(context))
        else:
            nodes += entity.execute(context) or []
    return nodes


def _stand_ins(monkeypatch):
    modules = {
        'launch': {'LaunchDescription': LaunchDescription, 'Substitution': Substitution,
                   'Action': Action},
        'launch.actions': {'DeclareLaunchArgument': DeclareLaunchArgument,
                           'GroupAction': GroupAction},
        'launch.conditions': {'IfCondition': IfCondition},
        'launch.substitutions': {'LaunchConfiguration': LaunchConfiguration,
                                 'PathJoinSubstitution': PathJoinSubstitution,
                                 'TextSubstitution': TextSubstitution},
        'launch_ros': {},
        'launch_ros.actions': {'Node': Node, 'PushROSNamespace': PushROSNamespace,
                               'PushRosNamespace': PushROSNamespace},
        'launch_ros.parameter_descriptions': {'ParameterValue': ParameterValue},
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


def _launched_by_stand_ins(monkeypatch, arguments):
    _stand_ins(monkeypatch)
    description = _load().generate_launch_description()
    return visit(description.entities, StandInContext(arguments))


# ------------------------------------------------------------------------- what a launch gives
LAUNCHES = [
    ({}, 'wake', '/', 'info', set(NODES)),
    ({'case': 'multiblade', 'use_namespace': 'true', 'namespace': 'rigx', 'log_level': 'debug',
      'bag': '42'}, 'multiblade', '/rigx', 'debug', set(NODES)),
    ({'case': 'single_blade', 'namespace': 'ignored', 'plant': 'false', 'stirring': 'False'},
     'single_blade', '/', 'info', set(NODES) - {'rotor_plant', 'stirring_input'}),
]


def _check(nodes, arguments, case, namespace, log_level, expected):
    """Assert the launched nodes of one launch (a list of dicts, from either evaluation)."""
    assert {n['executable'] for n in nodes} == expected
    scripts = _console_scripts()
    for node in nodes:
        assert node['package'] == 'rotor_id'
        assert node['executable'] in scripts
        assert node['name'] == node['executable']
        assert node['namespace'] == namespace, node
        args = node['arguments'] + ['--ros-args'] + node['ros_arguments']
        assert any(args[i:i + 3] == ['--ros-args', '--log-level', log_level]
                   for i in range(len(args))), args
        params_file = Path(node['files'][0])
        assert params_file.name == f'nodes_{case}.yaml'
        assert params_file.is_file(), params_file
        assert node['overrides']['use_sim_time'] is False
        if node['executable'] == 'recorder':
            # a bag name that reads as a number stays a string parameter
            assert node['overrides']['output'] == arguments.get('bag', '')
    return nodes


@pytest.mark.parametrize('arguments, case, namespace, log_level, expected', LAUNCHES)
def test_stand_in_launch(monkeypatch, arguments, case, namespace, log_level, expected):
    nodes = _launched_by_stand_ins(monkeypatch, arguments)
    _check(nodes, arguments, case, namespace, log_level, expected)


def test_stand_ins_are_as_strict_as_jazzy(monkeypatch):
    # what the launch file once did: a nested list in PathJoinSubstitution (Jazzy: TypeError)
    with pytest.raises(TypeError, match="type '<class 'list'>'"):
        PathJoinSubstitution(['config', ['nodes_', LaunchConfiguration('case'), '.yaml']])
    with pytest.raises(RuntimeError, match='not valid'):
        _launched_by_stand_ins(monkeypatch, {'case': 'hover'})
    with pytest.raises(RuntimeError, match='Unknown value'):
        _launched_by_stand_ins(monkeypatch, {'use_namespace': 'yes'})
    with pytest.raises(TypeError, match='unexpected keyword'):
        Node(executable='x', package='rotor_id', node_namespace='/a')


def test_every_case_names_existing_parameter_files_and_one_rig(monkeypatch):
    from rotor_id.io.run_description import load_run_description
    for case in ('wake', 'multiblade', 'single_blade'):
        nodes = _launched_by_stand_ins(monkeypatch, {'case': case})
        params_file = Path(nodes[0]['files'][0])
        params = yaml.safe_load(params_file.read_text())
        for node in nodes:
            assert f'/**/{node["name"]}' in params, (params_file, node['name'])
        # one rig description for every node, the same file
        runs = {params[f'/**/{node["name"]}']['ros__parameters']['run_description']
                for node in nodes}
        assert len(runs) == 1, runs
        load_run_description(params_file.parent / runs.pop())
    # installed where the launch file looks: setup.py puts config/*.yaml into share/rotor_id
    setup = (REPO / 'setup.py').read_text()
    assert "'/config', sorted(glob('config/*.yaml'))" in setup
    assert "'/launch', sorted(glob('launch/*.launch.py'))" in setup


# ------------------------------------------------------------------------- the real launch
def _real_launch():
    """Skip unless Jazzy's launch and launch_ros are importable (not the repo's launch/ dir)."""
    launch = pytest.importorskip('launch', reason='launch is not installed (ROS 2 Jazzy)')
    if not hasattr(launch, 'LaunchDescription'):
        pytest.skip('launch is not installed (only the repository launch/ directory is found)')
    pytest.importorskip('launch_ros.actions', reason='launch_ros is not installed')
    try:
        from ament_index_python.packages import get_package_share_directory
        get_package_share_directory('rotor_id')
    except (ImportError, LookupError) as exc:
        pytest.skip(f'rotor_id is not installed in a sourced workspace ({exc})')
    return launch


def _visit_real(entities, context):
    """Visit as the launch service does, but evaluate a Node instead of starting it."""
    from launch.launch_context import LaunchContext  # noqa: F401
    from launch.utilities import perform_substitutions
    from launch_ros.actions import Node as RealNode
    nodes = []
    for entity in entities:
        if isinstance(entity, RealNode):
            if entity.condition is not None and not entity.condition.evaluate(context):
                continue
            entity._perform_substitutions(context)
            ros = {'name': f'__node:={entity.node_name.rsplit("/", 1)[-1]}'}
            if entity.expanded_node_namespace not in ('', entity.UNSPECIFIED_NODE_NAMESPACE):
                ros['ns'] = f'__ns:={entity.expanded_node_namespace}'
            context.extend_locals({'ros_specific_arguments': ros})
            cmd = [perform_substitutions(context, part) for part in entity.cmd]
            files = [cmd[i + 1] for i, a in enumerate(cmd) if a == '--params-file']
            overrides = {}
            for path in files[1:]:               # the dicts, written to files by launch_ros
                for section in yaml.safe_load(Path(path).read_text()).values():
                    overrides.update(section['ros__parameters'])
            first_ros = cmd.index('--ros-args')
            namespace = entity.expanded_node_namespace
            nodes.append({'executable': Path(cmd[0]).name, 'package': entity.node_package,
                          'name': entity.node_name.rsplit('/', 1)[-1],
                          'namespace': namespace if namespace.startswith('/') else '/',
                          'arguments': cmd[1:first_ros], 'ros_arguments': cmd[first_ros + 1:],
                          'files': files[:1], 'overrides': overrides})
            continue
        nodes += _visit_real(entity.visit(context) or [], context)
    return nodes


@pytest.mark.parametrize('arguments, case, namespace, log_level, expected', LAUNCHES)
def test_real_launch_description(arguments, case, namespace, log_level, expected):
    launch = _real_launch()
    description = _load('rotor_id_launch_real').generate_launch_description()
    context = launch.LaunchContext()
    context.launch_configurations.update(arguments)
    nodes = _visit_real([description], context)
    _check(nodes, arguments, case, namespace, log_level, expected)


LAUNCH_SCRIPT = """
import sys
from launch import LaunchService
from launch.actions import IncludeLaunchDescription
from launch.launch_description_sources import PythonLaunchDescriptionSource
service = LaunchService(argv=sys.argv[2:])
service.include_launch_description(IncludeLaunchDescription(
    PythonLaunchDescriptionSource(sys.argv[1]),
    launch_arguments=[a.split(':=', 1) for a in sys.argv[2:]]))
sys.exit(service.run())
"""


def test_real_launch_under_a_namespace(tmp_path):
    """What ``ros2 launch rotor_id rotor_id.launch.py use_namespace:=true ...`` does."""
    _real_launch()
    from live_helpers import domain_id, require_workspace, RosClient
    require_workspace()
    domain = domain_id()
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
               ROS_LOG_DIR=str(tmp_path / 'log'), PYTHONUNBUFFERED='1')
    log = (tmp_path / 'launch.out').open('w')
    process = subprocess.Popen(
        [sys.executable, '-c', LAUNCH_SCRIPT, str(LAUNCH_FILE), 'use_namespace:=true',
         'namespace:=rigx', 'log_level:=warn', f'bag:={tmp_path / "bag"}'],
        env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    ros = RosClient(domain, 'launch_watcher')
    expected = {(name, '/rigx') for name in NODES}
    seen = set()
    try:
        deadline = time.monotonic() + 120
        while not expected <= seen and time.monotonic() < deadline and process.poll() is None:
            time.sleep(0.5)
            seen = set(ros.node.get_node_names_and_namespaces())
        assert expected <= seen, (sorted(seen), (tmp_path / 'launch.out').read_text()[-3000:])
        started = time.monotonic() - (deadline - 120)
        os.killpg(process.pid, signal.SIGINT)       # Ctrl-C: the terminal's whole group
        code = process.wait(timeout=60)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
        ros.close()
        log.close()
    output = (tmp_path / 'launch.out').read_text()
    print(f'five nodes in /rigx after {started:.1f} s')
    assert code == 0, output[-3000:]
    # every node stopped on SIGINT itself: launch had to escalate to none
    assert "sending signal 'SIGTERM'" not in output and 'SIGKILL' not in output, output[-3000:]
    # log_level:=warn reached the nodes: none logged at INFO (at info the recorder logs where
    # it records, the identifier its test points)
    info = re.findall(r'\[INFO\] \[[0-9.]+\] \[rigx\.\w+\]: .*', output)
    assert not info, info[:3]
