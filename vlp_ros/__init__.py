"""
vlp_ros: camera-based visible light positioning.

The subpackages follow a frame through the locator: ``core`` (shared types),
``detection``, ``beacon``, ``solvers``, ``pipeline``, ``images`` and ``bags``
(I/O), then ``nodes``. Everything except ``vlp_ros.nodes`` is ROS-free: it takes
arrays and returns plain results, so it can be used and tested without a ROS
installation. ``sim``, ``evaluation`` and ``benchmarks`` are tools; the nodes
never import them.
"""
