"""ament_python package rotor_id: nodes, library and the rotor-id command line."""

from glob import glob

from setuptools import find_packages
from setuptools import setup

package_name = 'rotor_id'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', sorted(glob('config/*.yaml'))),
        ('share/' + package_name + '/launch', sorted(glob('launch/*.launch.py'))),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='rotor_id maintainers',
    maintainer_email='rotor-id@example.org',
    description='Identification of rotor blade flapping dynamics from stirring experiments.',
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [
            'stirring_input = rotor_id.nodes.stirring_input:main',
            'rotor_plant = rotor_id.nodes.rotor_plant:main',
            'state_estimator = rotor_id.nodes.state_estimator:main',
            'identifier = rotor_id.nodes.identifier:main',
            'recorder = rotor_id.nodes.recorder:main',
            'rotor-id = rotor_id.cli:entry',
        ],
    },
)
