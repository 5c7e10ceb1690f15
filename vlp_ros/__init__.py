"""
vlp_ros: camera-based visible light positioning.

The subpackages follow a frame through the locator: ``core`` (shared types),
``detection``, ``beacon``, ``solvers``, ``pipeline``, ``images`` and ``bags``
(I/O), then ``nodes``. Everything except ``vlp_ros.nodes`` is ROS-free: it takes
arrays and returns plain results, so it can be used and tested without a ROS
installation. ``sim``, ``evaluation`` and ``benchmarks`` are tools; the nodes
never import them.
"""
import os

# The pipeline works on one frame at a time, one core, small arrays: a BLAS thread pool only contends with
# the rest (the censored reading's (700, 24) x (24, 768) products took ~50 ms instead of ~1 ms a window in
# the locator on a busy 2-core machine). numpy sizes the pool when it loads, which the package's modules
# do after this; a value set by the user wins.
for _variable in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ.setdefault(_variable, '1')
