"""
Time the shared small linear algebra (``vlp_ros.compiled.linalg``) against numba's own np.linalg.

Each routine runs in a compiled loop on the sizes the kernels use (2x2 to 6x6), so the
times are what a kernel pays per call. ``python -m vlp_ros.benchmarks.linalg_speed``.
"""
from __future__ import annotations

import time

import numpy as np

from vlp_ros.compiled import kernel
from vlp_ros.compiled.linalg import inverse3_into, lu_solve, pseudo_inverse, svd_cutoff, symmetric_eigen


@kernel
def _lu_solve_loop(matrix, rhs, repeats):
    total = 0.0
    for _ in range(repeats):
        total += lu_solve(matrix, rhs, 0.0).solution[0]
    return total


@kernel
def _numpy_solve_loop(matrix, rhs, repeats):
    total = 0.0
    for _ in range(repeats):
        total += np.linalg.solve(matrix, rhs)[0]
    return total


@kernel
def _inverse3_loop(matrix, repeats):
    out = np.empty((3, 3))
    total = 0.0
    for _ in range(repeats):
        inverse3_into(matrix, out)
        total += out[0, 0]
    return total


@kernel
def _numpy_inverse_loop(matrix, repeats):
    total = 0.0
    for _ in range(repeats):
        total += np.linalg.inv(matrix)[0, 0]
    return total


@kernel
def _pseudo_inverse_loop(matrix, repeats):
    total = 0.0
    for _ in range(repeats):
        eigen = symmetric_eigen(matrix)
        total += pseudo_inverse(eigen, svd_cutoff(eigen))[0, 0]
    return total


@kernel
def _numpy_pseudo_inverse_loop(matrix, repeats):
    total = 0.0
    for _ in range(repeats):
        total += np.linalg.pinv(matrix)[0, 0]
    return total


def _microseconds(loop, *args, repeats: int = 20000, runs: int = 7) -> float:
    """Return the median time (us) of one call in ``loop``."""
    loop(*args, 10)
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        loop(*args, repeats)
        times.append((time.perf_counter() - start) / repeats * 1e6)
    return float(np.median(times))


def main() -> None:
    """Print the time of each routine here against numba's np.linalg on the sizes the kernels use."""
    rng = np.random.default_rng(0)
    print('us per call (median of 7 runs), inside a kernel loop')
    print(f'{"routine":40s} {"size":>4s} {"here":>7s} {"np.linalg":>9s} {"ratio":>6s}')
    rows = []
    for size in (2, 3, 4, 6):
        root = rng.normal(size=(size, size))
        matrix, rhs = root @ root.T + np.eye(size), rng.normal(size=size)
        rows.append(('lu_solve / np.linalg.solve', size, _microseconds(_lu_solve_loop, matrix, rhs),
                     _microseconds(_numpy_solve_loop, matrix, rhs)))
        rows.append(('pseudo_inverse(symmetric_eigen) / pinv', size, _microseconds(_pseudo_inverse_loop, matrix),
                     _microseconds(_numpy_pseudo_inverse_loop, matrix)))
        if size == 3:
            rows.append(('inverse3_into / np.linalg.inv', size, _microseconds(_inverse3_loop, matrix),
                         _microseconds(_numpy_inverse_loop, matrix)))
    for name, size, here, numpy_time in rows:
        print(f'{name:40s} {size:4d} {here:7.2f} {numpy_time:9.2f} {numpy_time / here:6.1f}')


if __name__ == '__main__':
    main()
