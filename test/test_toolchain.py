"""The toolchain pieces: the CMake export patch, the pins, and the ./rotor-id launcher."""

import importlib.util
import os
from pathlib import Path
import re
import shutil
import subprocess
import sysconfig

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]

_spec = importlib.util.spec_from_file_location(
    'patch_cmake_exports', REPO_ROOT / 'tools' / 'patch_cmake_exports.py')
patch_cmake_exports = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(patch_cmake_exports)

# What the ros-* wheels ship (one line of share/std_msgs/cmake/export_..._pyExport.cmake).
WHEEL_LINE = (
    '  INTERFACE_INCLUDE_DIRECTORIES "/opt/python/cp311-cp311/include/python3.11;'
    '/opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/_core/include"\n')


def _fake_prefix(root):
    cmake = root / 'share' / 'std_msgs' / 'cmake'
    cmake.mkdir(parents=True)
    export = cmake / 'export_std_msgs__rosidl_generator_pyExport.cmake'
    export.write_text('set_target_properties(x PROPERTIES\n' + WHEEL_LINE + ')\n')
    (cmake / 'std_msgsConfig.cmake').write_text('# untouched\n')
    return export


def test_patch_rewrites_builder_paths_to_this_interpreter(tmp_path, capsys):
    np = pytest.importorskip('numpy')
    export = _fake_prefix(tmp_path)
    prefix = ['--prefix', str(tmp_path)]
    assert patch_cmake_exports.main(prefix + ['--check']) == 1
    assert patch_cmake_exports.main(prefix) == 0
    text = export.read_text()
    assert '/opt/python' not in text
    assert f'"{sysconfig.get_paths()["include"]};{np.get_include()}"' in text
    assert patch_cmake_exports.main(prefix + ['--check']) == 0
    # idempotent: a second run changes nothing
    assert patch_cmake_exports.main(prefix) == 0
    assert export.read_text() == text
    assert '0 of 2 CMake files patched' in capsys.readouterr().out


def test_patch_fixes_another_venvs_paths_without_touching_hard_links(tmp_path):
    """A file hard-linked into a package cache (uv) keeps the cache's content intact."""
    np = pytest.importorskip('numpy')
    export = _fake_prefix(tmp_path / 'venv')
    export.write_text('set_target_properties(x PROPERTIES\n  INTERFACE_INCLUDE_DIRECTORIES '
                      '"${_IMPORT_PREFIX}/include/std_msgs;/tmp/trial/v/include/python3.11;'
                      '/tmp/trial/v/lib/python3.11/site-packages/numpy/_core/include")\n')
    cache_copy = tmp_path / 'cache-file.cmake'
    os.link(export, cache_copy)
    before = cache_copy.read_text()
    prefix = ['--prefix', str(tmp_path / 'venv')]
    assert patch_cmake_exports.main(prefix + ['--check']) == 1
    assert patch_cmake_exports.main(prefix) == 0
    text = export.read_text()
    assert '/tmp/trial' not in text
    assert '${_IMPORT_PREFIX}/include/std_msgs' in text
    assert f'{sysconfig.get_paths()["include"]};{np.get_include()}' in text
    assert cache_copy.read_text() == before
    assert patch_cmake_exports.main(prefix + ['--check']) == 0


def test_patch_fails_on_a_prefix_without_cmake_files(tmp_path):
    assert patch_cmake_exports.main(['--prefix', str(tmp_path), '--check']) == 1


def test_venv_cmake_exports_are_patched(venv_prefix):
    if not (venv_prefix / 'share' / 'std_msgs' / 'cmake').is_dir():
        pytest.skip(f'no ros-* message wheels in {venv_prefix}')
    assert patch_cmake_exports.main(['--prefix', str(venv_prefix), '--check']) == 0


def _pins(path):
    pins = {}
    for line in path.read_text().splitlines():
        line = line.split('#')[0].strip()
        match = re.fullmatch(r'([A-Za-z0-9_.\-\[\]]+?)(\[[a-z,]+\])?\s*==\s*(\S+)', line)
        if match:
            pins[re.sub(r'[-_.]+', '-', match.group(1)).lower()] = match.group(3)
    return pins


def test_every_requirement_is_locked_and_numpy_stays_at_2_4_6():
    constraints = _pins(REPO_ROOT / 'constraints-jazzy.txt')
    for line in (REPO_ROOT / 'requirements-jazzy.in').read_text().splitlines():
        line = line.split('#')[0].strip()
        if not line:
            continue
        name = re.sub(r'[-_.]+', '-', re.split(r'[\[=<>~! ]', line)[0]).lower()
        assert name in constraints, f'{name} is not pinned in constraints-jazzy.txt'
    assert constraints['numpy'] == '2.4.6'


def test_installed_versions_match_the_lock(venv_prefix):
    from importlib import metadata
    constraints = _pins(REPO_ROOT / 'constraints-jazzy.txt')
    wrong = {}
    for dist in metadata.distributions():
        name = re.sub(r'[-_.]+', '-', dist.metadata['Name']).lower()
        if name in constraints and dist.version != constraints[name]:
            wrong[name] = (dist.version, constraints[name])
    assert not wrong, f'installed vs locked: {wrong} (run `make venv`)'


def test_launcher_without_environment_prints_one_hint_line(tmp_path):
    # A clone that was never built: no .venv, no install/.
    (tmp_path / 'tools').mkdir()
    shutil.copy2(REPO_ROOT / 'rotor-id', tmp_path / 'rotor-id')
    shutil.copy2(REPO_ROOT / 'tools' / 'env.sh', tmp_path / 'tools' / 'env.sh')
    result = subprocess.run([str(tmp_path / 'rotor-id'), '--help'], capture_output=True,
                            text=True, timeout=30, stdin=subprocess.DEVNULL)
    assert result.returncode == 1
    assert result.stdout == ''
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and 'make test' in lines[0] and 'make demo' in lines[0], lines


def test_launcher_runs_the_cli_from_anywhere(install_prefix, tmp_path):
    # No sourced environment, another working directory: rotor-id finds everything itself.
    env = {'HOME': str(tmp_path), 'PATH': '/usr/bin:/bin'}
    result = subprocess.run([str(REPO_ROOT / 'rotor-id'), '--help'], capture_output=True,
                            text=True, timeout=60, cwd=tmp_path, env=env,
                            stdin=subprocess.DEVNULL)
    assert result.returncode == 0, result.stderr
    assert 'usage: rotor-id' in result.stdout


def test_launcher_environment_imports_the_messages(install_prefix, tmp_path):
    script = '. "$1/tools/env.sh" && exec python -c "$2"'
    code = ('import rotor_id, rotor_id_msgs.msg as m; '
            'from rclpy.serialization import serialize_message as s; '
            'print(rotor_id.__file__); print(len(s(m.StirringCommand())))')
    result = subprocess.run(['bash', '-c', script, 'env.sh', str(REPO_ROOT), code],
                            capture_output=True, text=True, timeout=60, cwd=tmp_path,
                            env={'HOME': str(tmp_path), 'PATH': '/usr/bin:/bin'},
                            stdin=subprocess.DEVNULL)
    assert result.returncode == 0, result.stderr
    module_file, size = result.stdout.split()
    # the source tree comes first, so edits apply without a rebuild
    assert Path(module_file).parent == REPO_ROOT / 'rotor_id'
    assert int(size) > 0


def _environment(script, tmp_path):
    result = subprocess.run(['bash', '-c', script + ' && env -0', 'env.sh', str(REPO_ROOT)],
                            capture_output=True, text=True, timeout=60, cwd=tmp_path,
                            env={'HOME': str(tmp_path), 'PATH': '/usr/bin:/bin',
                                 'LD_LIBRARY_PATH': '/opt/inherited'},
                            stdin=subprocess.DEVNULL)
    assert result.returncode == 0, result.stderr
    return dict(line.split('=', 1) for line in result.stdout.split('\0') if '=' in line)


def test_kept_setup_commands_give_what_local_setup_gives(install_prefix, tmp_path):
    # env.sh keeps colcon's setup commands beside the install tree (made by the first source,
    # read by the second); the environment must be the one install/local_setup.sh sets itself
    _environment('. "$1/tools/env.sh"', tmp_path)
    assert (REPO_ROOT / 'install' / '.setup_commands.sh').is_file()
    ours = _environment('. "$1/tools/env.sh"', tmp_path)
    theirs = _environment('. "$1/tools/env.sh" --venv-only && COLCON_CURRENT_PREFIX="$1/install"'
                          ' && export COLCON_CURRENT_PREFIX && . "$1/install/local_setup.sh"',
                          tmp_path)

    def parts(env, name):
        return [p for p in env.get(name, '').split(':') if p]
    for name in ('AMENT_PREFIX_PATH', 'CMAKE_PREFIX_PATH', 'LD_LIBRARY_PATH',
                 'COLCON_PREFIX_PATH'):
        assert parts(ours, name) == parts(theirs, name), name
    assert parts(ours, 'PYTHONPATH') == [str(REPO_ROOT)] + parts(theirs, 'PYTHONPATH')
    assert str(REPO_ROOT / 'install' / 'rotor_id_msgs' / 'lib') in parts(ours, 'LD_LIBRARY_PATH')
