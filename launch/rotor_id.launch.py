"""
Launch the five rotor_id nodes on the simulated rotor (for a full ROS 2 Jazzy install).

    ros2 launch rotor_id rotor_id.launch.py                       # mu = 0 dynamic-wake case
    ros2 launch rotor_id rotor_id.launch.py case:=multiblade      # or single_blade
    ros2 launch rotor_id rotor_id.launch.py params_file:=/path/my_stand.yaml bag:=run_42
    ros2 launch rotor_id rotor_id.launch.py use_namespace:=true namespace:=rig2 log_level:=debug

On a test stand whose sensors publish themselves, give ``plant:=false`` (and ``stirring:=false``
if the rig has its own excitation) and a params_file whose sections all name your run
description (``run_description``: the rig's topics, joint names, blade count and azimuth
convention; docs/run_description.md). Topic names are relative: ``use_namespace:=true
namespace:=<ns>`` pushes every node into ``<ns>`` and so moves the whole rig (the nav2
convention; the parameter files' ``/**/<node>`` sections match in any namespace). The
arguments, topics and QoS are tabulated in docs/ros_interfaces.md. The parameter files are
config/nodes_<case>.yaml (installed to share/rotor_id/config); ``rotor-id demo`` runs the same
nodes without ros2 launch.

Only what Jazzy's launch 3.4 and launch_ros 0.26 accept is used: a substitution is a str, a
Substitution or a flat list of those (concatenated), never a nested list.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, GroupAction
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node, PushROSNamespace
from launch_ros.parameter_descriptions import ParameterValue

CASES = ('wake', 'multiblade', 'single_blade')
#: node executable -> the launch argument that switches it on or off
NODES = {'rotor_plant': 'plant', 'stirring_input': 'stirring', 'identifier': 'identifier',
         'state_estimator': 'state_estimator', 'recorder': 'recorder'}
LOG_LEVELS = ('debug', 'info', 'warn', 'error', 'fatal')


def generate_launch_description():
    """Nodes of one case, with its parameter file, each switchable off, in a namespace."""
    config = os.path.join(get_package_share_directory('rotor_id'), 'config')
    arguments = [
        DeclareLaunchArgument('case', default_value='wake', choices=list(CASES),
                              description="the report's case: selects config/nodes_<case>.yaml"),
        # a flat list of substitutions is concatenated: <share>/config/nodes_<case>.yaml
        DeclareLaunchArgument('params_file', default_value=[
            os.path.join(config, 'nodes_'), LaunchConfiguration('case'), '.yaml'],
            description='node parameter file (ROS 2 YAML); default by case'),
        DeclareLaunchArgument('namespace', default_value='',
                              description='namespace of every node (with use_namespace:=true)'),
        DeclareLaunchArgument('use_namespace', default_value='false',
                              description='push the nodes into `namespace` (true/false)'),
        DeclareLaunchArgument('log_level', default_value='info',
                              description='log level of every node (--ros-args --log-level): '
                              + ', '.join(LOG_LEVELS)),
        DeclareLaunchArgument('bag', default_value='',
                              description='bag directory for the recorder (empty: dated name)'),
        DeclareLaunchArgument('use_sim_time', default_value='false',
                              description='follow /clock (true/false)'),
    ]
    arguments += [DeclareLaunchArgument(switch, default_value='true',
                                        description=f'start {name} (true/false)')
                  for name, switch in NODES.items()]
    nodes = []
    for name, switch in NODES.items():
        parameters = [LaunchConfiguration('params_file'),
                      {'use_sim_time': LaunchConfiguration('use_sim_time')}]
        if name == 'recorder':
            # a string even when the name reads as a number or is empty
            parameters.append({'output': ParameterValue(LaunchConfiguration('bag'),
                                                        value_type=str)})
        nodes.append(Node(package='rotor_id', executable=name, name=name,
                          parameters=parameters, output='screen',
                          arguments=['--ros-args', '--log-level',
                                     LaunchConfiguration('log_level')],
                          condition=IfCondition(LaunchConfiguration(switch))))
    rig = GroupAction([PushROSNamespace(namespace=LaunchConfiguration('namespace'),
                                        condition=IfCondition(LaunchConfiguration(
                                            'use_namespace'))),
                       *nodes])
    return LaunchDescription([*arguments, rig])
