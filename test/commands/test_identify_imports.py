"""
`rotor-id identify` imports what it uses, when it uses it.

A fit of a short record and its adequacy check need numpy, the bag reader and the estimation
library; scipy (its import is most of a short command's start-up, bench/results/startup.md) and
matplotlib (only for ``--figure``) stay unloaded.
"""

import json
import os
from pathlib import Path
import subprocess
import sys

sys.path.insert(0, str(Path(__file__).resolve().parent))
from campaign_helpers import write_test_point  # noqa: E402,I100

REPO = Path(__file__).resolve().parents[2]
NOT_NEEDED = ('scipy', 'matplotlib')
#: The child runs the command in-process and prints its exit code and every loaded module.
_CHILD = ('import json, sys\nfrom rotor_id import cli\nrc = cli.main(sys.argv[1:])\n'
          'print(json.dumps([rc, sorted(sys.modules)]))\n')


def test_identify_loads_neither_scipy_nor_matplotlib(tmp_path):
    bag = write_test_point(tmp_path, 'tp', seed=3, noise_deg=0.05)
    env = dict(os.environ, ROTOR_ID_KERNELS='numpy', PYTHONPATH=os.pathsep.join(
        [str(REPO)] + [p for p in os.environ.get('PYTHONPATH', '').split(os.pathsep) if p]))
    out = subprocess.run(
        [sys.executable, '-c', _CHILD, 'identify', str(bag), '--config', str(tmp_path / 'tp.yaml'),
         '--quiet', '--json', str(tmp_path / 'fit.json')],
        capture_output=True, text=True, env=env, cwd=tmp_path, timeout=300)
    rc, modules = json.loads(out.stdout.strip().splitlines()[-1])
    assert rc == 0, out.stderr
    assert json.loads((tmp_path / 'fit.json').read_text())['adequacy'] is not None
    packages = {name.split('.')[0] for name in modules}
    assert {'numpy', 'rosbags'} <= packages            # the listing sees what was imported
    assert 'rotor_id.adequacy' in modules              # the check ran
    assert not packages & set(NOT_NEEDED), sorted(packages & set(NOT_NEEDED))
    # the adequacy check reads the residuals without the diagnosis (it never imports upward)
    assert not [name for name in modules if name.startswith('rotor_id.diagnosis')]


def test_diagnose_starts_without_scipy_special_or_matplotlib():
    # the diagnosis's detection limits take the noncentral χ² and its proposal Student's t from
    # rotor_id.estimation.validation, not scipy.special (whose import was a third of
    # `rotor-id diagnose`'s start-up, ~0.13 s); the proposal's equation error needs no
    # scipy.signal (0.6 s), which only its optional prefilter imports
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [str(REPO)] + [p for p in os.environ.get('PYTHONPATH', '').split(os.pathsep) if p]))
    out = subprocess.run(
        [sys.executable, '-c', 'import json, sys\nimport rotor_id.commands.diagnose\n'
         'import rotor_id.estimation.term_search\n'
         'print(json.dumps(sorted(sys.modules)))\n'],
        capture_output=True, text=True, env=env, timeout=120)
    modules = json.loads(out.stdout.strip().splitlines()[-1])
    assert 'rotor_id.diagnosis.verdict' in modules      # the listing sees the diagnosis
    assert not [m for m in modules if m.startswith(('scipy.special', 'scipy.signal',
                                                    'matplotlib'))]
