"""
The package as ROS users meet it: executables, interfaces, and a colcon build.

* every console script of setup.py is found the way ``ros2 run rotor_id <exe>`` finds it;
* the rotor_id_msgs messages import, serialize and carry the documented fields, and rosbags
  (our bag library) reads the same definitions with the same type hash as rosidl;
* a fresh workspace with the repository under ``src/`` builds with the documented command
  (the interface package compiled there too with ROTOR_ID_SLOW=1, else copied from make build);
* package.xml declares every ROS package and every rosdep key of a Python library that the code
  of rotor_id/ and launch/ imports, and no ROS package it does not use; the LICENSE is the
  declared one.
"""

import ast
import functools
import json
import os
from pathlib import Path
import re
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ElementTree

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
MSG_DIR = REPO_ROOT / 'msg_defs' / 'msg'
SRV_DIR = REPO_ROOT / 'msg_defs' / 'srv'

# The contract other parts of rotor_id (nodes, io, estimation) are written against.
EXPECTED_FIELDS = {
    'ParameterEstimate': [
        'header', 'computed_at', 'model', 'names', 'units', 'values', 'std', 'covariance',
        'correlation', 'noise_std', 'channel_names', 'cost', 'iteration', 'status', 'message',
        'window_start', 'window_end', 'window_s', 'test_point', 'kind', 'test_point_start',
        'window_requested_start_s', 'window_requested_end_s', 'time_base_consistent',
        'missing_channels', 'missing_samples', 'target_met', 'additional_data_s'],
    'StateEstimate': [
        'header', 'names', 'units', 'values', 'covariance', 'azimuth', 'rotor_speed'],
    'StirringCommand': [
        'header', 'collective', 'cyclic_forward', 'cyclic_left', 'stirring_phase',
        'stirring_rate', 'phase'],
    'IdentificationProgress': [
        'header', 'iteration', 'cost', 'values', 'names', 'elapsed', 'message'],
}
EXPECTED_CONSTANTS = {
    'ParameterEstimate': {'STATUS_ITERATING': 0, 'STATUS_CONVERGED': 1, 'STATUS_FAILED': 2,
                          'STATUS_MAX_ITERATIONS': 3, 'STATUS_INCOMPLETE': 4,
                          'STATUS_ABORTED': 5, 'KIND_PROVISIONAL': 0, 'KIND_FINAL': 1,
                          'KIND_ON_DEMAND': 2},
    'StirringCommand': {'PHASE_TRIM': 0, 'PHASE_CYCLIC_STEP': 1, 'PHASE_STIRRING': 2,
                        'PHASE_DONE': 3, 'PHASE_RAMP_DOWN': 4},
}


def console_scripts():
    """Return the console_scripts names declared in setup.py (read, not executed)."""
    tree = ast.parse((REPO_ROOT / 'setup.py').read_text(encoding='utf-8'))
    for node in ast.walk(tree):
        if isinstance(node, ast.keyword) and node.arg == 'entry_points':
            entry_points = ast.literal_eval(node.value)
            return [spec.split('=')[0].strip() for spec in entry_points['console_scripts']]
    raise AssertionError('setup.py declares no entry_points')


def ros2_run_lookup(package, executable):
    """
    Resolve ``ros2 run <package> <executable>`` like ros2run does; return the paths.

    The package prefix is the first AMENT_PREFIX_PATH entry whose ament index lists the
    package; the candidates are the executable files below ``<prefix>/lib/<package>/``
    (dot-directories skipped) whose basename is ``executable``.
    """
    from ament_index_python.packages import get_package_prefix
    base = Path(get_package_prefix(package)) / 'lib' / package
    found = []
    for dirpath, dirnames, filenames in os.walk(base):
        dirnames[:] = sorted(d for d in dirnames if not d.startswith('.'))
        for name in sorted(filenames):
            path = Path(dirpath, name)
            if name == executable and os.access(path, os.X_OK):
                found.append(path)
    return found


def msg_fields(text):
    """Yield (type, name, comment) of the fields of a .msg text, constants excluded."""
    comment_above = False
    for line in text.splitlines():
        stripped = line.strip()
        if not stripped:
            comment_above = False
            continue
        if stripped.startswith('#'):
            comment_above = True
            continue
        body, _, comment = stripped.partition('#')
        typ, name = body.split()[:2]
        if '=' in name:  # constant
            continue
        yield typ, name, comment.strip() or (comment_above and 'above')
        comment_above = False


@pytest.fixture(scope='module')
def ament_index():
    """Skip unless both packages are on AMENT_PREFIX_PATH (a built, sourced workspace)."""
    pytest.importorskip('ament_index_python')
    from ament_index_python.packages import get_package_prefix
    from ament_index_python.packages import PackageNotFoundError
    try:
        return {pkg: Path(get_package_prefix(pkg)) for pkg in ('rotor_id', 'rotor_id_msgs')}
    except PackageNotFoundError as exc:
        pytest.skip(f'{exc}: the workspace is not built or not sourced (`make test` does both)')


# --- (a) ros2 run -----------------------------------------------------------------------

def test_setup_py_declares_the_nodes_and_the_cli():
    assert set(console_scripts()) >= {
        'stirring_input', 'rotor_plant', 'state_estimator', 'identifier', 'recorder',
        'rotor-id'}


@pytest.mark.parametrize('executable', console_scripts())
def test_ros2_run_finds_console_script(ament_index, executable):
    found = ros2_run_lookup('rotor_id', executable)
    assert len(found) == 1, \
        f'ros2 run rotor_id {executable}: found {found} under {ament_index["rotor_id"]}/lib'
    shebang = found[0].read_text(encoding='utf-8').splitlines()[0]
    interpreter = shebang[2:].split()[0]
    assert os.access(interpreter, os.X_OK), f'{found[0]}: interpreter {interpreter} missing'


def test_ros2_run_rejects_unknown_executable(ament_index):
    assert ros2_run_lookup('rotor_id', 'no_such_node') == []


def test_installed_cli_starts(ament_index):
    # Loads the entry point through importlib.metadata: needs the egg-info on PYTHONPATH.
    exe = ros2_run_lookup('rotor_id', 'rotor-id')[0]
    result = subprocess.run([str(exe), '--help'], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert 'usage: rotor-id' in result.stdout


def test_share_directory_is_complete(ament_index):
    share = ament_index['rotor_id'] / 'share' / 'rotor_id'
    assert (share / 'package.xml').is_file()
    msgs = ament_index['rotor_id_msgs'] / 'share' / 'rotor_id_msgs'
    for name in EXPECTED_FIELDS:
        # rosbags builds its typestore from these installed definitions
        assert (msgs / 'msg' / f'{name}.msg').is_file()
    assert (msgs / 'srv' / 'Identify.srv').is_file()


# --- (b) interfaces ---------------------------------------------------------------------

def test_every_field_is_documented():
    for path in sorted(MSG_DIR.glob('*.msg')) + sorted(SRV_DIR.glob('*.srv')):
        lines = [ln for ln in path.read_text(encoding='utf-8').splitlines() if ln != '---']
        for typ, name, comment in msg_fields('\n'.join(lines)):
            assert comment, f'{path.name}: field `{typ} {name}` has no comment (units!)'


def test_messages_start_with_header():
    for name in EXPECTED_FIELDS:
        first = next(msg_fields((MSG_DIR / f'{name}.msg').read_text(encoding='utf-8')))
        assert first[:2] == ('std_msgs/Header', 'header'), name


def _sample_value(typ):
    """Return a non-default value for a field of rosidl type string ``typ``."""
    sequence = re.fullmatch(r'sequence<(.+)>', typ)
    if sequence:
        return [_sample_value(sequence.group(1)) for _ in range(3)]
    scalars = {'double': -1.25, 'float': 0.5, 'boolean': True, 'string': 'rotor_hub',
               'uint8': 3, 'uint32': 7, 'int32': -7, 'uint64': 9, 'int64': -9}
    if typ in scalars:
        return scalars[typ]
    package, name = typ.split('/')
    cls = getattr(__import__(f'{package}.msg', fromlist=[name]), name)
    return _filled(cls)


def _filled(cls):
    """Return a ``cls`` message with every field set to a non-default value."""
    msg = cls()
    for field, typ in cls.get_fields_and_field_types().items():
        setattr(msg, field, _sample_value(typ))
    return msg


@pytest.fixture(scope='module')
def interfaces(ament_index):
    msg = pytest.importorskip('rotor_id_msgs.msg')
    srv = pytest.importorskip('rotor_id_msgs.srv')
    return msg, srv


@pytest.mark.parametrize('name', sorted(EXPECTED_FIELDS))
def test_message_round_trips_through_cdr(interfaces, name):
    from rclpy.serialization import deserialize_message
    from rclpy.serialization import serialize_message
    msg_module, _ = interfaces
    cls = getattr(msg_module, name)
    assert list(cls.get_fields_and_field_types()) == EXPECTED_FIELDS[name]
    for constant, value in EXPECTED_CONSTANTS.get(name, {}).items():
        assert getattr(cls, constant) == value
    original = _filled(cls)
    assert original != cls()
    assert deserialize_message(serialize_message(original), cls) == original


def test_identify_service_round_trips(interfaces):
    from rclpy.serialization import deserialize_message
    from rclpy.serialization import serialize_message
    msg_module, srv_module = interfaces
    request = srv_module.Identify.Request(window_start_s=1.5, window_end_s=30.0)
    response = srv_module.Identify.Response(
        success=True, message='ok', estimate=_filled(msg_module.ParameterEstimate))
    for value in (request, response):
        assert deserialize_message(serialize_message(value), type(value)) == value


@pytest.mark.parametrize('name', sorted(EXPECTED_FIELDS))
def test_rosbags_type_hash_matches_rosidl(ament_index, name):
    # Bags written with rosbags must carry the type hash a ROS 2 Jazzy reader expects.
    typesys = pytest.importorskip('rosbags.typesys')
    store = typesys.get_typestore(typesys.Stores.ROS2_JAZZY)
    share = ament_index['rotor_id_msgs'] / 'share' / 'rotor_id_msgs' / 'msg'
    types = {}
    for path in sorted(share.glob('*.msg')):
        types.update(typesys.get_types_from_msg(
            path.read_text(encoding='utf-8'), f'rotor_id_msgs/msg/{path.stem}'))
    store.register(types)
    rosidl = json.loads((share / f'{name}.json').read_text(encoding='utf-8'))
    expected = rosidl['type_hashes'][0]
    assert expected['type_name'] == f'rotor_id_msgs/msg/{name}'
    assert store.hash_rihs01(f'rotor_id_msgs/msg/{name}') == expected['hash_string']


# --- (c) colcon -------------------------------------------------------------------------

def _colcon_env(venv_prefix, tmp_path):
    """Environment of a user with only the venv (no built workspace) active."""
    env = {k: v for k, v in os.environ.items()
           if k not in ('PYTHONPATH', 'COLCON_PREFIX_PATH', 'LD_LIBRARY_PATH',
                        'COLCON_DEFAULTS_FILE')}
    env['VIRTUAL_ENV'] = str(venv_prefix)
    env['PATH'] = f'{venv_prefix / "bin"}{os.pathsep}{env.get("PATH", "")}'
    env['AMENT_PREFIX_PATH'] = str(venv_prefix)
    env['CMAKE_PREFIX_PATH'] = str(venv_prefix)
    env['COLCON_HOME'] = str(tmp_path / 'colcon_home')  # no personal colcon defaults
    return env


def _colcon(args, cwd, env, timeout=60):
    colcon = Path(env['VIRTUAL_ENV'], 'bin', 'colcon')
    if not colcon.exists():
        pytest.skip(f'colcon is not installed in {env["VIRTUAL_ENV"]}')
    return subprocess.run([str(colcon), *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=timeout, stdin=subprocess.DEVNULL)


def _listed(result):
    assert result.returncode == 0, result.stderr
    return sorted(result.stdout.split())


def test_colcon_in_repo_root_finds_both_packages(venv_prefix, tmp_path):
    # colcon_defaults.yaml in the root adds msg_defs as a base path.
    env = _colcon_env(venv_prefix, tmp_path)
    assert _listed(_colcon(['list', '--names-only'], REPO_ROOT, env)) == \
        ['rotor_id', 'rotor_id_msgs']


def _copy_ignore(directory, names):
    generated = {'__pycache__', '.pytest_cache', '.hypothesis'}
    if Path(directory).resolve() == REPO_ROOT:
        generated |= {'.venv', 'build', 'install', 'log', 'out', '.git'}
    return [n for n in names if n in generated or n.endswith('.egg-info')]


@pytest.mark.slow
def test_fresh_workspace_builds_with_documented_command(venv_prefix, tmp_path):
    ws = tmp_path / 'ws'
    shutil.copytree(REPO_ROOT, ws / 'src' / 'rotor_id', ignore=_copy_ignore, symlinks=True)
    env = _colcon_env(venv_prefix, tmp_path)

    # What docs/install.md says: colcon's crawl stops at the root package ...
    assert _listed(_colcon(['list', '--names-only', '--base-paths', 'src'], ws, env)) == \
        ['rotor_id']
    # ... so msg_defs is named as a second base path.
    base_paths = ['--base-paths', 'src', 'src/rotor_id/msg_defs']
    assert _listed(_colcon(['list', '--names-only', *base_paths], ws, env)) == \
        ['rotor_id', 'rotor_id_msgs']

    # The interface package is the same CMake project from either base path, and `make build`
    # built it with this venv before the tests: copied from there, it is not compiled again (a
    # minute of a 2-core CI machine) unless ROTOR_ID_SLOW=1 or there is no such build.
    skip = []
    built = REPO_ROOT / 'install' / 'rotor_id_msgs'
    if not os.environ.get('ROTOR_ID_SLOW') and built.is_dir():
        shutil.copytree(built, ws / 'install' / 'rotor_id_msgs', symlinks=True)
        skip = ['--packages-skip', 'rotor_id_msgs']
    result = _colcon(
        ['build', *base_paths, *skip, '--event-handlers', 'status-', 'desktop_notification-',
         'terminal_title-'], ws, env, timeout=900)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    install = ws / 'install'
    for exe in console_scripts():
        assert os.access(install / 'rotor_id' / 'lib' / 'rotor_id' / exe, os.X_OK), exe
    site = install / 'rotor_id_msgs' / 'lib' / f'python{sys.version_info[0]}.' \
        f'{sys.version_info[1]}' / 'site-packages' / 'rotor_id_msgs'
    assert (site / 'msg' / '_parameter_estimate.py').is_file()
    assert (site / 'srv' / '_identify.py').is_file()


# --- (d) package.xml ---------------------------------------------------------------------

#: Python modules that are no ROS package, by the rosdep key that installs them.
ROSDEP_KEYS = {'numpy': 'python3-numpy', 'scipy': 'python3-scipy',
               'matplotlib': 'python3-matplotlib', 'yaml': 'python3-yaml',
               'rosbags': 'python3-rosbags-pip'}
#: Imported, but installed by a declared dependency or optional (each with its reason).
NOT_DECLARED = {
    'lz4': 'a dependency of rosbags',
    'backports': 'backports.zstd, a dependency of rosbags (before Python 3.14)',
    'compression': 'compression.zstd, the standard library from Python 3.14',
    'numba': 'optional: rotor_id.estimation.kernels falls back to numpy without it',
    'llvmlite': "numba's own dependency, used by the optional kernels",
}
#: ROS packages that ship Python modules under the package's own name.
ROS_PYTHON_PACKAGES = {'rclpy', 'launch', 'launch_ros', 'ament_index_python'}
#: Declared, though not imported by name (each with its reason).
DECLARED_NOT_IMPORTED = {
    'std_msgs': 'the Header type of every rotor_id message and of sensor_msgs/JointState',
    'ros2launch': '`ros2 launch rotor_id rotor_id.launch.py`',
}


@functools.lru_cache(maxsize=1)
def imported_modules():
    """Return {top-level module: [files]} imported by rotor_id/ and launch/ (stdlib left out)."""
    found = {}
    files = sorted((REPO_ROOT / 'rotor_id').rglob('*.py')) + \
        sorted((REPO_ROOT / 'launch').rglob('*.py'))
    for path in files:
        for node in ast.walk(ast.parse(path.read_text(encoding='utf-8'))):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0:
                names = [node.module]
            else:
                continue
            for name in names:
                top = name.split('.')[0]
                if top not in sys.stdlib_module_names and top != 'rotor_id':
                    found.setdefault(top, []).append(str(path.relative_to(REPO_ROOT)))
    return found


def is_ros_package(module):
    """Say whether a module is a ROS package of the same name (interfaces or Python)."""
    return (module in ROS_PYTHON_PACKAGES
            or re.fullmatch(r'[a-z0-9_]+_(msgs|srvs|interfaces)', module) is not None)


def declared_dependencies(kinds=('depend', 'exec_depend')):
    """Return the package names of package.xml's dependencies of the given kinds."""
    root = ElementTree.parse(REPO_ROOT / 'package.xml').getroot()
    assert root.get('format') == '3'
    return {element.text.strip() for kind in kinds for element in root.findall(kind)}


def test_package_xml_declares_every_imported_package():
    declared = declared_dependencies()
    modules = imported_modules()
    # the scan sees what it must: the nodes' and the launch file's imports
    assert {'rclpy', 'rcl_interfaces', 'ament_index_python', 'launch', 'launch_ros',
            'numpy'} <= set(modules)
    missing = []
    for module, files in sorted(modules.items()):
        if is_ros_package(module):
            key = module
        elif module in ROSDEP_KEYS:
            key = ROSDEP_KEYS[module]
        else:
            assert module in NOT_DECLARED, \
                f'{module} (imported by {files[0]}) is neither a ROS package nor mapped to a ' \
                'rosdep key here: declare it in package.xml and add it to ROSDEP_KEYS'
            continue
        if key not in declared:
            missing.append(f'{key} (imported by {files[0]})')
    assert not missing, f'package.xml does not declare: {", ".join(missing)}'
    for module in NOT_DECLARED:
        assert module in modules, f'{module} is no longer imported: drop it from NOT_DECLARED'


def test_package_xml_declares_no_unused_ros_package():
    imported = {m for m in imported_modules() if is_ros_package(m)}
    python_keys = set(ROSDEP_KEYS.values())
    unused = {d for d in declared_dependencies()
              if d not in imported and d not in python_keys and d not in DECLARED_NOT_IMPORTED}
    assert not unused, f'declared but never imported: {sorted(unused)}'


def test_license_file_is_the_declared_license():
    root = ElementTree.parse(REPO_ROOT / 'package.xml').getroot()
    assert root.findtext('license') == 'Apache-2.0'
    text = (REPO_ROOT / 'LICENSE').read_text(encoding='utf-8')
    assert 'Apache License' in text and 'Version 2.0, January 2004' in text
    assert 'END OF TERMS AND CONDITIONS' in text
    # the full text: its nine sections, not a pointer to it
    for section in range(1, 10):
        assert re.search(rf'^\s*{section}\. [A-Z]', text, re.MULTILINE), section
    setup = (REPO_ROOT / 'setup.py').read_text(encoding='utf-8')
    assert "license='Apache-2.0'" in setup or 'license="Apache-2.0"' in setup
