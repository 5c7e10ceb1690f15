"""Replay a recording through the locator: ros2 launch vlp_ros vlp.launch.py bag:=DIR params:=FILE."""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, SetEnvironmentVariable
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare


def generate_launch_description() -> LaunchDescription:
    bag = LaunchConfiguration('bag')
    params = LaunchConfiguration('params')
    return LaunchDescription([
        DeclareLaunchArgument('bag', description='rosbag2 directory to play'),
        DeclareLaunchArgument(
            'params', description='locator params file',
            default_value=PathJoinSubstitution([FindPackageShare('vlp_ros'), 'config', 'locator.example.yaml'])),
        DeclareLaunchArgument('rate', default_value='1.0', description='playback rate'),
        # Camera images exceed what Fast DDS's default transports deliver best effort.
        SetEnvironmentVariable('FASTDDS_BUILTIN_TRANSPORTS', 'LARGE_DATA'),
        Node(package='vlp_ros', executable='locator', name='vlp_locator', output='screen',
             parameters=[params]),
        Node(package='vlp_ros', executable='replay', name='vlp_replay', output='screen',
             arguments=[bag, '--rate', LaunchConfiguration('rate')]),
    ])
