"""
Launch the five rotor_id nodes on the simulated rotor (for a full ROS 2 Jazzy install).

    ros2 launch rotor_id rotor_id.launch.py                       # mu = 0 dynamic-wake case
    ros2 launch rotor_id rotor_id.launch.py case:=multiblade      # or single_blade
    ros2 launch rotor_id rotor_id.launch.py params_file:=/path/my_stand.yaml bag:=run_42

On a test stand whose sensors publish themselves, give ``plant:=false`` (and ``stirring:=false``
if the rig has its own excitation) and a params_file whose sections all name your run
description (``run_description``: the rig's topics, joint names, blade count and azimuth
convention; README "On your own test stand"). Topic names are relative: pushing the nodes into
a namespace moves the whole rig. The parameter files are config/nodes_<case>.yaml (installed to
share/rotor_id/config); ``rotor-id demo`` runs the same nodes without ros2 launch.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node

CASES = ('wake', 'multiblade', 'single_blade')
NODES = ('rotor_plant', 'stirring_input', 'identifier', 'state_estimator', 'recorder')


def generate_launch_description():
    """Nodes of one case, with its parameter file, each switchable off."""
    config = os.path.join(get_package_share_directory('rotor_id'), 'config')
    arguments = [
        DeclareLaunchArgument('case', default_value='wake', choices=list(CASES),
                              description="the report's case: selects config/nodes_<case>.yaml"),
        DeclareLaunchArgument('params_file', default_value=PathJoinSubstitution(
            [config, ['nodes_', LaunchConfiguration('case'), '.yaml']]),
            description='node parameter file (ROS 2 YAML); default by case'),
        DeclareLaunchArgument('bag', default_value='',
                              description='bag directory for the recorder (empty: dated name)'),
        DeclareLaunchArgument('use_sim_time', default_value='false',
                              description='follow /clock'),
    ]
    arguments += [DeclareLaunchArgument(name, default_value='true',
                                        description=f'start {name}')
                  for name in ('plant', 'stirring', 'identifier', 'state_estimator',
                               'recorder')]
    switch = {'rotor_plant': 'plant', 'stirring_input': 'stirring', 'identifier': 'identifier',
              'state_estimator': 'state_estimator', 'recorder': 'recorder'}
    nodes = []
    for name in NODES:
        parameters = [LaunchConfiguration('params_file'),
                      {'use_sim_time': LaunchConfiguration('use_sim_time')}]
        if name == 'recorder':
            parameters.append({'output': LaunchConfiguration('bag')})
        nodes.append(Node(package='rotor_id', executable=name, name=name,
                          parameters=parameters, output='screen',
                          condition=IfCondition(LaunchConfiguration(switch[name]))))
    return LaunchDescription(arguments + nodes)
