"""
Tone's small dense linear algebra, in closed form: the stripe model's 3x3 whitening and 2x2 / 3x3 inverse.

Both belong in ``vlp_ros.compiled.linalg`` (the one place for the small dense linear algebra that
kernels share). Numba's ``np.linalg`` in their place (``inv(cholesky(gram))``; ``det`` and ``inv``)
took 2 us per decode instead of 0.2 us (of about 400 us), moved the likelihoods of 117 of 400 test
profiles by rounding (no ID changed) and raises where these give nan (a Gram matrix that is not
positive definite, a singular normal matrix).
"""
from __future__ import annotations

import math

import numpy as np

from vlp_ros.compiled import kernel


@kernel
def inverse_cholesky_3x3(gram: np.ndarray) -> np.ndarray:
    """Return the inverse of the Cholesky factor of a 3x3 Gram matrix, in closed form."""
    a, b, c, d, e, f = gram[0, 0], gram[0, 1], gram[0, 2], gram[1, 1], gram[1, 2], gram[2, 2]
    l00 = math.sqrt(a)
    l10, l20 = b / l00, c / l00
    l11 = math.sqrt(d - l10 * l10)
    l21 = (e - l20 * l10) / l11
    l22 = math.sqrt(f - l20 * l20 - l21 * l21)
    m10 = -l10 / (l00 * l11)
    out = np.zeros((3, 3))
    out[0, 0], out[1, 0], out[1, 1] = 1.0 / l00, m10, 1.0 / l11
    out[2, 0], out[2, 1], out[2, 2] = -(l20 / l00 + l21 * m10) / l22, -l21 / (l11 * l22), 1.0 / l22
    return out


@kernel
def inverse_2x2_or_3x3(m: np.ndarray) -> tuple[bool, np.ndarray]:
    """Return whether a 2x2 or 3x3 matrix is invertible, and its inverse by cofactors."""
    n = len(m)
    cofactors = np.empty((n, n))
    if n == 2:
        cofactors[0, 0], cofactors[0, 1], cofactors[1, 0], cofactors[1, 1] = m[1, 1], -m[0, 1], -m[1, 0], m[0, 0]
        det = m[0, 0] * m[1, 1] - m[0, 1] * m[1, 0]
    else:
        for r in range(3):
            for c in range(3):
                # The cofactor of m[c, r]: rows and columns other than c and r, in cyclic order.
                r1, r2, c1, c2 = (c + 1) % 3, (c + 2) % 3, (r + 1) % 3, (r + 2) % 3
                cofactors[r, c] = m[r1, c1] * m[r2, c2] - m[r1, c2] * m[r2, c1]
        det = m[0, 0] * cofactors[0, 0] + m[0, 1] * cofactors[1, 0] + m[0, 2] * cofactors[2, 0]
    scale = np.abs(m).max() ** n
    return np.isfinite(det) and abs(det) > 1e-12 * scale, cofactors / det
