"""
The pose fit's compiled numerics.

Every measurement's residuals and Jacobian, and the Levenberg-Marquardt loop over
them.

A fit is a few iterations on a few hundred residuals, where each numpy or OpenCV call
costs more in argument handling than in arithmetic: the loop runs whole in one kernel.
The measurements enter as ``Terms``, flat arrays of every kind at once (rim points of
any number of lamps, markers, up directions), residuals in that order. The small
solves and inverses come from ``vlp_ros.compiled.linalg``.

Formulas (derived in ``measurement`` and ``up_measurement``): rim residual s = v / (2|P|)
with v = h^T C h for the rim conic C = H^-T diag(1, 1, -r^2) H^-1, H = R^T [e_x, e_y,
centre - position], and P = G^T (C h)_xy; marker residual the projected marker (pinhole
and plumb_bob, as ``cv2.projectPoints``) minus its pixel; up residual 2 T u / (1 + g.u)
over sigma with u = R^T e_z.
"""
from __future__ import annotations

from collections.abc import Sequence
import math
from typing import NamedTuple

import numpy as np

from vlp_ros.compiled import kernel
from vlp_ros.compiled.linalg import inverse3_into, lu_solve, Solved

# Stop when the best step can lower the chi-square by less than this fraction of it, or
# by less than the floor: the pose is then within sqrt(floor) = 0.03 sigma of the minimum
# before its last step, far below the ~1 unit that noise moves the chi-square (this saves
# the last one or two iterations of a quadratically converging fit).
_COST_TOLERANCE = 1e-9
_DECREMENT_FLOOR = 1e-3
_MIN_DAMPING = 1e-12
# ``iterate``'s outcomes.
CONVERGED = 0
PAUSED = 1
SINGULAR = 2


class Terms(NamedTuple):
    """
    Measurements as flat arrays, passed to the kernels whole; a kind left out has none.

    The arrays are C-contiguous float64, writable: numba compiles once per array type.

    Rim points: ``rays`` (N, 3) homogeneous normalised, ``lens`` (N, 4) d(normalised)/d(pixel)
    as (g00, g01, g10, g11), ``rim_sigma`` (N,), ``lamp_of_point`` (N,) into ``centres`` (L, 3)
    and ``radii_squared`` (L,). Markers: map positions (K, 3), pixels (K, 2), whitening
    matrices (K, 2, 2) W with W^T W the inverse of the pixel's covariance, seen through
    ``intrinsics`` (3, 3) and plumb_bob ``distortion`` (5,). Up directions:
    unit ``up_directions`` (U, 3), tangent axes ``up_tangents`` (U, 2, 3), ``up_sigma`` (U,).
    """

    rays: np.ndarray = np.empty((0, 3))
    lens: np.ndarray = np.empty((0, 4))
    rim_sigma: np.ndarray = np.empty(0)
    lamp_of_point: np.ndarray = np.empty(0, dtype=np.int64)
    centres: np.ndarray = np.empty((0, 3))
    radii_squared: np.ndarray = np.empty(0)
    marker_maps: np.ndarray = np.empty((0, 3))
    marker_pixels: np.ndarray = np.empty((0, 2))
    marker_whitening: np.ndarray = np.empty((0, 2, 2))
    intrinsics: np.ndarray = np.eye(3)
    distortion: np.ndarray = np.zeros(5)
    up_directions: np.ndarray = np.empty((0, 3))
    up_tangents: np.ndarray = np.empty((0, 2, 3))
    up_sigma: np.ndarray = np.empty(0)

    @property
    def residual_count(self) -> int:
        return len(self.rays) + 2 * len(self.marker_maps) + 2 * len(self.up_directions)


class Linearization(NamedTuple):
    """
    A pose and the whitened residuals of ``Terms`` at it, which the kernels write in place.

    ``rotation`` (3, 3) camera to map, ``position`` (3,), ``residuals`` (M,) and their ``jacobian``
    (M, 6) in the pose perturbation of ``covariance.perturbed``: C-contiguous float64 arrays.
    """

    rotation: np.ndarray
    position: np.ndarray
    residuals: np.ndarray
    jacobian: np.ndarray


class Descent(NamedTuple):
    """``iterate``'s result: how it ended (CONVERGED, PAUSED or SINGULAR), the chi-square and the damping it left."""

    outcome: int
    cost: float
    damping: float


def _fields(first: str, last: str) -> slice:
    """Return the positions of the fields of ``Terms`` from ``first`` to ``last``."""
    return slice(Terms._fields.index(first), Terms._fields.index(last) + 1)


# Fields that come and go together: a lamp's rim points (and the lamp), markers, up directions.
_KINDS = (_fields('rays', 'radii_squared'), _fields('marker_maps', 'marker_whitening'),
          _fields('up_directions', 'up_sigma'))
_CAMERA = _fields('intrinsics', 'distortion')
_LAMP_OF_POINT = Terms._fields.index('lamp_of_point')
_NONE = Terms()


def joined(parts: Sequence[Terms]) -> Terms:
    """
    All ``parts`` as one.

    Each kind's entries in the order of the parts (lamps renumbered), seen through the
    first camera that has lamps or projected points.
    """
    if len(parts) == 1:
        return parts[0]
    # By field position rather than name: this runs several times per solve, where getattr and
    # keyword construction cost more than the arrays' work.
    fields = list(_NONE)
    for kind in _KINDS:
        having = [t for t in parts if len(t[kind.start])]
        if len(having) == 1:
            # The common case (one lamp term, one up term): nothing to copy.
            fields[kind] = having[0][kind]
        elif having:
            fields[kind] = [np.concatenate([t[i] for t in having]) for i in range(kind.start, kind.stop)]
            if kind.start == 0:
                offsets = np.cumsum([0] + [len(t.centres) for t in having[:-1]])
                fields[_LAMP_OF_POINT] = np.concatenate([t.lamp_of_point + o for t, o in zip(having, offsets)])
    camera = next((t for t in parts if len(t.centres) or len(t.marker_maps)), parts[0])
    fields[_CAMERA] = camera[_CAMERA]
    return Terms._make(fields)


def linearize(terms: Terms, rotation: np.ndarray, position: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """
    Return the whitened residuals (M,) of ``terms`` at the pose and their Jacobian (M, 6).

    The pose is ``rotation`` camera to map and ``position``; the Jacobian is in the pose perturbation
    of ``covariance.perturbed``.
    """
    count = terms.residual_count
    fit = Linearization(np.ascontiguousarray(rotation, dtype=float), np.ascontiguousarray(position, dtype=float),
                        np.empty(count), np.empty((count, 6)))
    linearize_into(fit, terms)
    return fit.residuals, fit.jacobian


@kernel
def project_point(point, intrinsics, distortion, jacobian):
    """
    Return the pixel (u, v) of a camera-frame point as ``cv2.projectPoints`` does, and its Jacobian.

    K's skew is ignored, as there; d pixel / d point is written into ``jacobian`` (2, 3).
    """
    z = 1.0 / point[2] if point[2] != 0.0 else 1.0
    x, y = point[0] * z, point[1] * z
    k1, k2, p1, p2, k3 = distortion[0], distortion[1], distortion[2], distortion[3], distortion[4]
    fx, fy = intrinsics[0, 0], intrinsics[1, 1]
    r2 = x * x + y * y
    r4 = r2 * r2
    radial = 1.0 + k1 * r2 + k2 * r4 + k3 * r4 * r2
    xd = x * radial + p1 * (2.0 * x * y) + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + p2 * (2.0 * x * y)
    # d radial / d r2, then the distorted coordinates' derivatives in the normalised ones.
    slope = k1 + 2.0 * k2 * r2 + 3.0 * k3 * r4
    dxd_dx = radial + 2.0 * x * x * slope + 2.0 * p1 * y + 6.0 * p2 * x
    dxd_dy = 2.0 * x * y * slope + 2.0 * p1 * x + 2.0 * p2 * y
    dyd_dx = 2.0 * x * y * slope + 2.0 * p1 * x + 2.0 * p2 * y
    dyd_dy = radial + 2.0 * y * y * slope + 6.0 * p1 * y + 2.0 * p2 * x
    # x = X / Z, y = Y / Z.
    jacobian[0, 0] = fx * dxd_dx * z
    jacobian[0, 1] = fx * dxd_dy * z
    jacobian[0, 2] = -fx * (dxd_dx * x + dxd_dy * y) * z
    jacobian[1, 0] = fy * dyd_dx * z
    jacobian[1, 1] = fy * dyd_dy * z
    jacobian[1, 2] = -fy * (dyd_dx * x + dyd_dy * y) * z
    return fx * xd + intrinsics[0, 2], fy * yd + intrinsics[1, 2]


@kernel
def rim_terms(normalized, intrinsics, distortion, distorted, pinhole_inverse):
    """
    Rim rays (N, 3): undistorted normalised points (N, 2) made homogeneous.

    And d(normalised)/d(pixel) (N, 2, 2) at each: ``pinhole_inverse`` (K's upper-left block
    inverted) unless ``distorted``, else the inverse of ``project_point``'s Jacobian, whose x
    and y columns at z = 1 are d pixel / d normalised.
    """
    count = normalized.shape[0]
    rays = np.empty((count, 3))
    inverses = np.empty((count, 2, 2))
    point = np.ones(3)
    forward = np.empty((2, 3))
    for n in range(count):
        rays[n, 0], rays[n, 1], rays[n, 2] = normalized[n, 0], normalized[n, 1], 1.0
        if not distorted:
            inverses[n, :, :] = pinhole_inverse
            continue
        point[0], point[1] = normalized[n, 0], normalized[n, 1]
        project_point(point, intrinsics, distortion, forward)
        inverse_det = 1.0 / (forward[0, 0] * forward[1, 1] - forward[0, 1] * forward[1, 0])
        inverses[n, 0, 0] = forward[1, 1] * inverse_det
        inverses[n, 0, 1] = -forward[0, 1] * inverse_det
        inverses[n, 1, 0] = -forward[1, 0] * inverse_det
        inverses[n, 1, 1] = forward[0, 0] * inverse_det
    return rays, inverses


@kernel
def perturb(rotation, position, delta, rotation_out, position_out):
    """
    Write the pose moved by ``delta`` = (dx, dy, dz, rotation vector on the left) into the outputs.

    The outputs are ``rotation_out`` and ``position_out``; the rotation vector's matrix is formed as
    ``cv2.Rodrigues`` forms it.
    """
    rx, ry, rz = delta[3], delta[4], delta[5]
    theta = math.sqrt(rx * rx + ry * ry + rz * rz)
    left = np.eye(3)
    if theta >= 2.220446049250313e-16:
        c, s = math.cos(theta), math.sin(theta)
        c1 = 1.0 - c
        rx, ry, rz = rx / theta, ry / theta, rz / theta
        left[0, 0] = c + c1 * rx * rx
        left[0, 1] = c1 * rx * ry - s * rz
        left[0, 2] = c1 * rx * rz + s * ry
        left[1, 0] = c1 * rx * ry + s * rz
        left[1, 1] = c + c1 * ry * ry
        left[1, 2] = c1 * ry * rz - s * rx
        left[2, 0] = c1 * rx * rz - s * ry
        left[2, 1] = c1 * ry * rz + s * rx
        left[2, 2] = c + c1 * rz * rz
    for i in range(3):
        for j in range(3):
            rotation_out[i, j] = left[i, 0] * rotation[0, j] + left[i, 1] * rotation[1, j] + left[i, 2] * rotation[2, j]
        position_out[i] = position[i] + delta[i]


@kernel
def _conic_derivatives(rotation, position, centre, radius_squared, conic, d_conic):
    """
    Write the lamp's rim conic C (3, 3) and its derivatives dC_k (6, 3, 3) along the six pose perturbations.

    They go into ``conic`` and ``d_conic``. dH_k of H, then dC = -(M + M^T) with M = C dH H^-1.
    """
    plane = np.empty((3, 3))
    offset = np.empty(3)
    for m in range(3):
        offset[m] = centre[m] - position[m]
    for i in range(3):
        plane[i, 0] = rotation[0, i]
        plane[i, 1] = rotation[1, i]
        plane[i, 2] = rotation[0, i] * offset[0] + rotation[1, i] * offset[1] + rotation[2, i] * offset[2]
    inverse = np.empty((3, 3))
    inverse3_into(plane, inverse)
    for i in range(3):
        for j in range(3):
            conic[i, j] = (inverse[0, i] * inverse[0, j] + inverse[1, i] * inverse[1, j]
                           - radius_squared * inverse[2, i] * inverse[2, j])
    d_plane = np.zeros((3, 3))
    skew_r = np.zeros((3, 3))  # R^T [e_j]x
    m_matrix = np.empty((3, 3))
    c_dh = np.empty((3, 3))
    for k in range(6):
        if k < 3:
            # Position: only the column of the centre moves, by -R^T e_k.
            for i in range(3):
                d_plane[i, 0] = 0.0
                d_plane[i, 1] = 0.0
                d_plane[i, 2] = -rotation[k, i]
        else:
            # Rotation about map axis j: dH = -R^T [e_j]x A, A = [e_x, e_y, offset].
            j = k - 3
            skew_r[:, :] = 0.0
            for i in range(3):
                if j == 0:
                    skew_r[i, 1] = rotation[2, i]
                    skew_r[i, 2] = -rotation[1, i]
                elif j == 1:
                    skew_r[i, 0] = -rotation[2, i]
                    skew_r[i, 2] = rotation[0, i]
                else:
                    skew_r[i, 0] = rotation[1, i]
                    skew_r[i, 1] = -rotation[0, i]
            for i in range(3):
                d_plane[i, 0] = -skew_r[i, 0]
                d_plane[i, 1] = -skew_r[i, 1]
                d_plane[i, 2] = -(skew_r[i, 0] * offset[0] + skew_r[i, 1] * offset[1] + skew_r[i, 2] * offset[2])
        for i in range(3):
            for j in range(3):
                c_dh[i, j] = conic[i, 0] * d_plane[0, j] + conic[i, 1] * d_plane[1, j] + conic[i, 2] * d_plane[2, j]
        for i in range(3):
            for j in range(3):
                m_matrix[i, j] = c_dh[i, 0] * inverse[0, j] + c_dh[i, 1] * inverse[1, j] + c_dh[i, 2] * inverse[2, j]
        for i in range(3):
            for j in range(3):
                d_conic[k, i, j] = -(m_matrix[i, j] + m_matrix[j, i])


@kernel
def linearize_into(fit: Linearization, terms: Terms) -> float:
    """Write the whitened residuals and Jacobian of ``terms`` at ``fit``'s pose into ``fit``; return the chi-square."""
    row = _linearize_rim_points(fit, terms)
    row = _linearize_markers(fit, terms, row)
    _linearize_up_directions(fit, terms, row)
    return _chi_square(fit.residuals)


@kernel
def _linearize_rim_points(fit: Linearization, terms: Terms) -> int:
    """Write the rim points' rows, the first ones; return the row after them."""
    rotation, position, residuals, jacobian = fit.rotation, fit.position, fit.residuals, fit.jacobian
    lamps = terms.centres.shape[0]
    conics = np.empty((lamps, 3, 3))
    d_conics = np.empty((lamps, 6, 3, 3))
    for lamp in range(lamps):
        _conic_derivatives(rotation, position, terms.centres[lamp], terms.radii_squared[lamp], conics[lamp],
                           d_conics[lamp])
    rays, lens, lamp_of_point = terms.rays, terms.lens, terms.lamp_of_point
    a = np.empty(3)
    for n in range(rays.shape[0]):
        conic, d_conic, h = conics[lamp_of_point[n]], d_conics[lamp_of_point[n]], rays[n]
        c_h0 = conic[0, 0] * h[0] + conic[0, 1] * h[1] + conic[0, 2] * h[2]
        c_h1 = conic[1, 0] * h[0] + conic[1, 1] * h[1] + conic[1, 2] * h[2]
        c_h2 = conic[2, 0] * h[0] + conic[2, 1] * h[1] + conic[2, 2] * h[2]
        g00, g01, g10, g11 = lens[n, 0], lens[n, 1], lens[n, 2], lens[n, 3]
        value = h[0] * c_h0 + h[1] * c_h1 + h[2] * c_h2
        p0 = c_h0 * g00 + c_h1 * g10
        p1 = c_h0 * g01 + c_h1 * g11
        norm2 = p0 * p0 + p1 * p1
        norm = math.sqrt(norm2)
        residual = 0.5 * value / norm
        # ds = a^T dC h exactly (it matters far from the minimum, where v is large).
        pull = residual / norm2
        half = 0.5 / norm
        a[0] = h[0] * half - pull * (g00 * p0 + g01 * p1)
        a[1] = h[1] * half - pull * (g10 * p0 + g11 * p1)
        a[2] = h[2] * half
        sigma = terms.rim_sigma[n]
        residuals[n] = residual / sigma
        for k in range(6):
            total = 0.0
            for i in range(3):
                total += a[i] * (d_conic[k, i, 0] * h[0] + d_conic[k, i, 1] * h[1] + d_conic[k, i, 2] * h[2])
            jacobian[n, k] = total / sigma
    return rays.shape[0]


@kernel
def _linearize_markers(fit: Linearization, terms: Terms, row: int) -> int:
    """Write the markers' rows from ``row`` on, two per marker (u, v whitened); return the row after them."""
    rotation, position, residuals, jacobian = fit.rotation, fit.position, fit.residuals, fit.jacobian
    point = np.empty(3)
    offset = np.empty(3)
    lens_jacobian = np.empty((2, 3))
    to_pixel = np.empty((2, 3))
    w = np.empty(3)
    for marker in range(terms.marker_maps.shape[0]):
        # Camera-frame point R^T (m - p); its change is R^T (offset x dtheta - dp).
        for m in range(3):
            offset[m] = terms.marker_maps[marker, m] - position[m]
        for i in range(3):
            point[i] = rotation[0, i] * offset[0] + rotation[1, i] * offset[1] + rotation[2, i] * offset[2]
        u, v = project_point(point, terms.intrinsics, terms.distortion, lens_jacobian)
        whitening = terms.marker_whitening[marker]
        du, dv = u - terms.marker_pixels[marker, 0], v - terms.marker_pixels[marker, 1]
        for i in range(2):
            for m in range(3):
                to_pixel[i, m] = (lens_jacobian[i, 0] * rotation[m, 0] + lens_jacobian[i, 1] * rotation[m, 1]
                                  + lens_jacobian[i, 2] * rotation[m, 2])
        for i in range(2):
            w0, w1 = whitening[i, 0], whitening[i, 1]
            r = row + i
            residuals[r] = w0 * du + w1 * dv
            for m in range(3):
                w[m] = w0 * to_pixel[0, m] + w1 * to_pixel[1, m]
            jacobian[r, 0] = -w[0]
            jacobian[r, 1] = -w[1]
            jacobian[r, 2] = -w[2]
            jacobian[r, 3] = w[1] * offset[2] - w[2] * offset[1]
            jacobian[r, 4] = w[2] * offset[0] - w[0] * offset[2]
            jacobian[r, 5] = w[0] * offset[1] - w[1] * offset[0]
        row += 2
    return row


@kernel
def _linearize_up_directions(fit: Linearization, terms: Terms, row: int) -> None:
    """Write the up directions' rows from ``row`` on, two per direction (along its tangent axes)."""
    rotation, residuals, jacobian = fit.rotation, fit.residuals, fit.jacobian
    w = np.empty(3)
    for k in range(terms.up_directions.shape[0]):
        g, tangents, sigma = terms.up_directions[k], terms.up_tangents[k], terms.up_sigma[k]
        # u = R^T e_z, the pose's map up in the camera.
        scale = 2.0 / (sigma * (1.0 + g[0] * rotation[2, 0] + g[1] * rotation[2, 1] + g[2] * rotation[2, 2]))
        for i in range(2):
            residual = scale * (tangents[i, 0] * rotation[2, 0] + tangents[i, 1] * rotation[2, 1]
                                + tangents[i, 2] * rotation[2, 2])
            residuals[row + i] = residual
            # d residual / d u, then d u / d rotation vector = R^T [e_z]x.
            pull = 0.5 * sigma * scale * residual
            for m in range(3):
                w[m] = 0.0
                for j in range(3):
                    w[m] += (scale * tangents[i, j] - pull * g[j]) * rotation[m, j]
            jacobian[row + i, 0] = 0.0
            jacobian[row + i, 1] = 0.0
            jacobian[row + i, 2] = 0.0
            jacobian[row + i, 3] = w[1]
            jacobian[row + i, 4] = -w[0]
            jacobian[row + i, 5] = 0.0
        row += 2


@kernel
def _chi_square(residuals: np.ndarray) -> float:
    """Return the sum of the squared (whitened) residuals, in their order."""
    cost = 0.0
    for r in range(residuals.shape[0]):
        cost += residuals[r] * residuals[r]
    return cost


def inverse_form(matrix: np.ndarray, vector: np.ndarray) -> float:
    """v^T M^-1 v for a 6x6 ``matrix`` M; LinAlgError if M is singular (as ``np.linalg.solve``)."""
    vector = np.ascontiguousarray(vector, dtype=float)
    solved = lu_solve(np.ascontiguousarray(matrix, dtype=float), vector, 0.0)
    if not solved.ok:
        raise np.linalg.LinAlgError('singular matrix')
    return float(vector @ solved.solution)


@kernel
def forecast(residuals, jacobian):
    """
    Return the chi-square that the Gauss-Newton model of (residuals, jacobian) forecasts at its minimum.

    That is r^T r - g^T (J^T J)^-1 g with g = J^T r; 0 if J^T J is singular.
    """
    information, gradient = np.empty((6, 6)), np.empty(6)
    _normal_equations(residuals, jacobian, information, gradient)
    solved = lu_solve(information, gradient, 0.0)
    if not solved.ok:
        return 0.0
    step = solved.solution
    cost = _chi_square(residuals)
    for i in range(6):
        cost -= gradient[i] * step[i]
    return cost


@kernel
def information_matrix(jacobian, information):
    """J^T J (6x6) of a whitened residual Jacobian (M, 6), into ``information``."""
    for i in range(6):
        for j in range(i, 6):
            total = 0.0
            for n in range(jacobian.shape[0]):
                total += jacobian[n, i] * jacobian[n, j]
            information[i, j] = total
            information[j, i] = total


@kernel
def _normal_equations(residuals, jacobian, information, gradient):
    for i in range(6):
        total = 0.0
        for n in range(residuals.shape[0]):
            total += jacobian[n, i] * residuals[n]
        gradient[i] = total
    information_matrix(jacobian, information)


@kernel
def iterate(fit: Linearization, terms: Terms, cost: float, damping: float, iterations: int) -> Descent:
    """
    Run up to ``iterations`` Levenberg-Marquardt iterations from ``fit``, linearised, of chi-square ``cost``.

    The iterations update ``fit`` in place. CONVERGED when even the undamped Gauss-Newton step promises
    no real decrease: that last step is still taken, its residuals (lower by under the floor) not
    evaluated, since near the minimum it lands quadratically close to it. PAUSED when the iterations
    are spent; SINGULAR when the normal equations are.
    """
    information = np.empty((6, 6))
    damped = np.empty((6, 6))
    gradient = np.empty(6)
    trial = Linearization(np.empty((3, 3)), np.empty(3), np.empty_like(fit.residuals), np.empty_like(fit.jacobian))
    for _ in range(iterations):
        _normal_equations(fit.residuals, fit.jacobian, information, gradient)
        for i in range(6):
            gradient[i] = -gradient[i]
        solved = lu_solve(information, gradient, 0.0)
        if not solved.ok:
            return Descent(SINGULAR, cost, damping)
        if _decrease(gradient, solved.solution) < max(_COST_TOLERANCE * cost, _DECREMENT_FLOOR):
            perturb(fit.rotation, fit.position, solved.solution, trial.rotation, trial.position)
            _take_pose(trial, fit)
            return Descent(CONVERGED, cost, damping)
        solved = _damped_solve(information, gradient, damping, damped)
        if not solved.ok:
            return Descent(SINGULAR, cost, damping)
        perturb(fit.rotation, fit.position, solved.solution, trial.rotation, trial.position)
        trial_cost = linearize_into(trial, terms)
        if not np.isfinite(trial_cost) or trial_cost > cost:
            damping *= 10.0
            continue
        _take_pose(trial, fit)
        fit.residuals[:] = trial.residuals
        fit.jacobian[:, :] = trial.jacobian
        cost = trial_cost
        damping = max(damping / 10.0, _MIN_DAMPING)
    return Descent(PAUSED, cost, damping)


@kernel
def _decrease(gradient: np.ndarray, step: np.ndarray) -> float:
    """Return the chi-square's decrease that the Gauss-Newton model forecasts for ``step`` (``gradient`` = -J^T r)."""
    decrease = 0.0
    for i in range(6):
        decrease += gradient[i] * step[i]
    return decrease


@kernel
def _damped_solve(information: np.ndarray, gradient: np.ndarray, damping: float, damped: np.ndarray) -> Solved:
    """Solve the normal equations with each diagonal entry raised by ``damping`` times itself (in ``damped``)."""
    damped[:, :] = information
    for i in range(6):
        damped[i, i] += damping * information[i, i]
    return lu_solve(damped, gradient, 0.0)


@kernel
def _take_pose(source: Linearization, target: Linearization) -> None:
    """Copy ``source``'s pose into ``target``."""
    target.rotation[:, :] = source.rotation
    target.position[:] = source.position
