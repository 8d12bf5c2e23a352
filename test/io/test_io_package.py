"""The input layer's public names: each one where it is defined, loaded on first use."""

import subprocess
import sys

import pytest
import rotor_id.io


@pytest.mark.parametrize('name', rotor_id.io.__all__)
def test_every_public_name_is_the_one_its_module_defines(name):
    value = getattr(rotor_id.io, name)
    module = sys.modules[f'rotor_id.io.{rotor_id.io._DEFINED_IN[name]}']
    assert value is getattr(module, name)


def test_the_public_names_are_the_ones_it_maps_and_no_others():
    assert set(rotor_id.io.__all__) == set(rotor_id.io._DEFINED_IN)
    with pytest.raises(AttributeError, match='no attribute'):
        rotor_id.io.read_bag          # noqa: B018 - a name it does not have


def test_the_run_description_does_not_load_the_bag_reader():
    # a fresh process: this one has loaded rosbags for other tests
    code = ('import sys\n'
            'from rotor_id.io import load_run_description, blade_values\n'
            'from rotor_id.io.timebase import wrap_azimuth\n'
            'print("rosbags" in sys.modules)\n'
            'from rotor_id.io import read_run\n'
            'print("rosbags" in sys.modules)\n')
    done = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                          check=True)
    assert done.stdout.split() == ['False', 'True']
