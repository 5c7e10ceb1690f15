"""vlp_ros: camera-based visible light positioning.

Everything directly below this package except ``vlp_ros.nodes`` is ROS-free:
it takes arrays and returns plain results, so it can be used and tested
without a ROS installation.
"""
