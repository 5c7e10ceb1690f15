"""
The marker's compiled kernels against their numpy formulation.

``fit_marker``, ``find_seed`` and ``redness_and_peaks`` run as numba kernels
(vlp_ros.detection.marker). The reference here is the same fit written in numpy:
the blurred-disc model with its amplitudes eliminated (variable
projection, Kaufman's Jacobian), the Levenberg-Marquardt loop on it and the consider
covariance of the centre. The kernels must give the same fits, to rounding error, on
the markers detect_lamps meets in simulated frames.
"""
import cv2
import numpy as np
import pytest
from scipy.special import ndtr

from vlp_ros.core.ellipse import geometric_distances
from vlp_ros.detection import detect_lamps
from vlp_ros.detection import marker
import vlp_ros.detection.detector as detector
from vlp_ros.detection.marker import find_seed, fit_marker, MarkerSeed, redness_and_peaks
from vlp_ros.sim.render import render_frame
from vlp_ros.sim.scenarios import paper_scenario, robot_scenario

# ---------------------------------------------------------------------------------------------
# The numpy formulation.
# ---------------------------------------------------------------------------------------------


def reference_redness(bgr):
    red = 2 * bgr[..., 2].astype(np.int16)
    red -= bgr[..., 1]
    red -= bgr[..., 0]
    return red


def reference_seed(red, search_radius, min_redness):
    y, x = divmod(int(np.argmax(red)), red.shape[1])
    peak = float(red[y, x])
    if peak < min_redness:
        return None
    r = int(np.ceil(search_radius))
    y0, x0 = max(y - r, 0), max(x - r, 0)
    ys, xs = np.nonzero(red[y0:y + r + 1, x0:x + r + 1] > 0.4 * peak)
    centre = np.array([x0 + 0.5 * (xs.min() + xs.max()), y0 + 0.5 * (ys.min() + ys.max())])
    return MarkerSeed(centre, float(0.5 * max(xs.max() - xs.min() + 1, ys.max() - ys.min() + 1)))


def _shape_root(ellipse):
    _, _, a, b, theta = (float(v) for v in ellipse)
    c, s = np.cos(theta), np.sin(theta)
    along, across = np.sqrt(b / a), np.sqrt(a / b)
    off = c * s * (along - across)
    return np.array([[c * c * along + s * s * across, off], [off, s * s * along + c * c * across]])


class _Model:

    def __init__(self, data, pixels, lamp_disc, root, row_level):
        self.data = data.ravel()
        self.rows = pixels.shape[0]
        self.root = root
        self.rounded = pixels.reshape(-1, 2) @ root
        self.level = np.broadcast_to(row_level[:, None], data.shape).ravel()
        self.disc_term = (row_level[:, None] * lamp_disc).ravel()
        self.disc_norm2 = float(self.disc_term @ self.disc_term)

    def evaluate(self, params, with_consider=False):
        cx, cy, s, blur = params
        u = self.rounded - np.array([cx, cy]) @ self.root
        gradient = u @ self.root
        norm = np.maximum(np.sqrt(gradient[:, 0] ** 2 + gradient[:, 1] ** 2), 1e-9)
        rho = np.sqrt(u[:, 0] ** 2 + u[:, 1] ** 2)
        gain = rho / norm
        z = (s - rho) * gain / blur
        basis = np.array([self.level * ndtr(z), self.disc_term])
        a, b, d = float(basis[0] @ basis[0]) + 1e-9, float(basis[0] @ basis[1]), self.disc_norm2 + 1e-9
        gram_inverse = np.array([[d, -b], [-b, a]]) / (a * d - b * b)
        coef = gram_inverse @ (basis @ self.data)
        residual = self.data - coef @ basis
        density = coef[0] * self.level * np.exp(-0.5 * z * z) / (np.sqrt(2.0 * np.pi) * blur)
        columns = [density * gradient[:, 0] / norm, density * gradient[:, 1] / norm, density * gain, -density * z]
        if with_consider:
            stretch = density * gain / np.maximum(rho, 1e-9)
            columns += [-0.5 * stretch * (u[:, 0] ** 2 - u[:, 1] ** 2), -stretch * u[:, 0] * u[:, 1]]
        jac = np.array(columns)
        jac -= (jac @ basis.T) @ gram_inverse @ basis
        cost = float(residual @ residual)
        if not with_consider:
            return cost, residual, jac.T
        row_terms = (jac[:4] * (coef[0] * basis[0])).reshape(4, self.rows, -1).sum(axis=2).T
        return cost, residual, jac.T, row_terms


def reference_inflation(residual, rows):
    """
    Return the product of (1 + rho) / (1 - rho) per axis, rho the residuals' lag-one correlation.

    The axes are along rows and between adjacent used rows; rho is clipped to [0, 0.8].
    """
    factor = 1.0
    adjacent = np.flatnonzero(np.diff(rows) == 1)
    pairs = ((residual[:, :-1], residual[:, 1:]), (residual[adjacent], residual[adjacent + 1]))
    for first, second in pairs:
        norm = 0.5 * float(np.sum(first ** 2) + np.sum(second ** 2))
        rho = float(np.clip(np.sum(first * second) / norm, 0.0, 0.8)) if norm > 0.0 else 0.0
        factor *= (1.0 + rho) / (1.0 - rho)
    return factor


def reference_row_spread(blur, rows, level_gradient):
    """Each row's relative level error: 5 %, and blur's mixing beyond the linear part, s^2 / 2 (L'/L)' + (L'/L)^2."""
    padded = np.concatenate(([0.0], level_gradient, [0.0]))
    change = 0.5 * (padded[rows + 2] - padded[rows])
    inside = (rows > 0) & (rows < level_gradient.size - 1)
    curvature = np.where(inside, change, 0.0) + level_gradient[rows] ** 2
    return np.hypot(0.05, 0.5 * blur ** 2 * curvature)


def reference_fit(red, seed, lamp_ellipse, blur_guess, margin, row_level, rows_used, level_gradient, shape_spread):
    """(centre, covariance, radius, blur, shape) or None, as fit_marker computed them in numpy."""
    half = seed.radius + margin
    x0 = max(int(np.floor(seed.center[0] - half)), 0)
    y0 = max(int(np.floor(seed.center[1] - half)), 0)
    x1 = min(int(np.ceil(seed.center[0] + half)) + 1, red.shape[1])
    y1 = min(int(np.ceil(seed.center[1] + half)) + 1, red.shape[0])
    rows = np.arange(y0, y1)[rows_used[y0:y1]]
    if rows.size < 3 or x1 - x0 < 5:
        return None
    data = red[rows, x0:x1].astype(float)
    pixels = np.empty((len(rows), x1 - x0, 2))
    pixels[..., 0] = np.arange(x0, x1, dtype=float)
    pixels[..., 1] = rows[:, None]
    lamp_disc = ndtr(-geometric_distances(lamp_ellipse, pixels.reshape(-1, 2)).reshape(data.shape) / blur_guess)
    root = _shape_root(lamp_ellipse)
    model = _Model(data, pixels, lamp_disc, root, row_level[rows])
    params = np.array([seed.center[0], seed.center[1], seed.radius, blur_guess])
    cost, residual, jac = model.evaluate(params)
    damping = 1e-3
    for _ in range(12):
        jtj = jac.T @ jac
        damped = jtj + np.diag(damping * (np.diagonal(jtj) + 1e-12))
        _, step = cv2.solve(damped, (jac.T @ residual)[:, None], flags=cv2.DECOMP_LU)
        trial = params + step.ravel()
        trial[2] = max(trial[2], 0.5)
        trial[3] = min(max(trial[3], 0.3), 4.0)
        trial_cost, trial_residual, trial_jac = model.evaluate(trial)
        moved = np.linalg.norm(trial[:2] - params[:2])
        if trial_cost < cost:
            params, cost, residual, jac = trial, trial_cost, trial_residual, trial_jac
            damping = max(damping * 0.3, 1e-6)
        else:
            damping *= 10.0
        if moved < 3e-3 or damping > 1e6:
            break
    centre, radius, blur = params[:2], params[2], params[3]
    if not (x0 <= centre[0] < x1 and y0 <= centre[1] < y1) or radius > half or not 0.3 < blur < 4.0:
        return None
    if np.count_nonzero(np.abs(rows - centre[1]) < np.hypot(radius, blur)) < 3:
        return None
    dof = data.size - 6
    if dof <= 0:
        return None
    _, _, jac, row_terms = model.evaluate(params, with_consider=True)
    fitted, shape = jac[:, :4], jac[:, 4:]
    _, inverse = cv2.invert(fitted.T @ fitted, flags=cv2.DECOMP_SVD)
    shape_effect = inverse @ fitted.T @ shape
    level_effect = inverse @ row_terms.T
    covariance = (reference_inflation(residual.reshape(len(rows), -1), rows) * cost / dof * inverse
                  + shape_spread ** 2 * shape_effect @ shape_effect.T
                  + (level_effect * reference_row_spread(blur, rows, level_gradient) ** 2) @ level_effect.T)
    # Blur mixing rows whose level changes by L' shifts the fit by (J^T J)^-1 J^T (-blur^2 L'/L J_cy),
    # if all of the blur came after the shutter: half of it is undone, half counted along the shift.
    gradient = np.repeat(level_gradient[rows], data.shape[1])
    shift = -blur ** 2 * (inverse @ fitted.T @ (gradient * fitted[:, 1]))[:2]
    centre = centre - 0.5 * shift
    return centre, covariance[:2, :2] + 0.25 * np.outer(shift, shift), float(radius), float(blur), root @ root


# ---------------------------------------------------------------------------------------------
# What detect_lamps hands the marker fit on simulated frames.
# ---------------------------------------------------------------------------------------------


@pytest.fixture(scope='module')
def recorded_fits():
    """fit_marker's arguments from detect_lamps on 1080p, 4K and robot frames (colour)."""
    calls = []
    original = detector.fit_marker

    def recording(*args):
        calls.append(tuple(np.copy(a) if isinstance(a, np.ndarray) else a for a in args))
        return original(*args)

    scenarios = [(paper_scenario('1080p', points=3, postures=1), 1), (paper_scenario('4k', points=2, postures=1), 1),
                 (robot_scenario(), 10)]
    detector.fit_marker = recording
    try:
        for number, (scenario, stride) in enumerate(scenarios):
            rng = np.random.default_rng(number)
            for index in range(0, min(len(scenario.poses), 12 * stride), stride):
                frame = render_frame(scenario.camera, scenario.poses[index], scenario.lamps, scenario.sensor,
                                     index / scenario.frame_rate, rng)
                detect_lamps(frame.image)
    finally:
        detector.fit_marker = original
    return calls


def test_fit_marker_matches_the_numpy_formulation(recorded_fits):
    assert len(recorded_fits) >= 25
    found = 0
    for args in recorded_fits:
        expected = reference_fit(*args)
        fit = fit_marker(*args)
        assert (fit is None) == (expected is None)
        if fit is None:
            continue
        found += 1
        centre, covariance, radius, blur, shape = expected
        # A micro-pixel: far below the marker's noise, far above rounding (which differs between CPUs).
        np.testing.assert_allclose(fit.center, centre, rtol=0.0, atol=1e-6)
        np.testing.assert_allclose(fit.covariance, covariance, rtol=1e-6, atol=1e-6 * np.trace(covariance))
        assert fit.radius == pytest.approx(radius, abs=1e-6)
        assert fit.blur == pytest.approx(blur, abs=1e-6)
        np.testing.assert_allclose(fit.shape, shape, rtol=0.0, atol=1e-9)  # dimensionless, of order 1
        assert isinstance(fit.sigma, float) and fit.center.shape == (2,)
    assert found >= 0.8 * len(recorded_fits)


def test_fit_marker_rejects_what_the_numpy_formulation_rejects(recorded_fits):
    """Too few usable rows, and a window without any: None, as the numpy formulation gives."""
    red, seed, lamp_ellipse, blur_guess, margin, row_level, rows_used, gradient, spread = recorded_fits[0]
    for used in (np.zeros_like(rows_used), np.arange(rows_used.size) == int(seed.center[1])):
        assert reference_fit(red, seed, lamp_ellipse, blur_guess, margin, row_level, used, gradient, spread) is None
        assert fit_marker(red, seed, lamp_ellipse, blur_guess, margin, row_level, used, gradient, spread) is None


def test_redness_matches_numpy():
    rng = np.random.default_rng(1)
    image = rng.integers(0, 256, (60, 80, 3), dtype=np.uint8)
    for roi in (image, image[7:41, 13:70], image[7:41, 13:70] // 3):
        red, _ = redness_and_peaks(roi)
        assert red.dtype == np.int16 and red.flags.c_contiguous
        np.testing.assert_array_equal(red, reference_redness(roi))
        both, peaks = redness_and_peaks(roi)
        np.testing.assert_array_equal(both, red)
        assert peaks == tuple(int(roi[..., channel].max()) for channel in range(3))


def test_find_seed_matches_numpy():
    rng = np.random.default_rng(2)
    for trial in range(40):
        red = rng.integers(-30, 30, (rng.integers(20, 90), rng.integers(20, 90))).astype(np.int16)
        y, x = rng.integers(0, red.shape[0]), rng.integers(0, red.shape[1])
        red[max(y - 3, 0):y + 4, max(x - 2, 0):x + 3] += np.int16(rng.integers(20, 200))
        if trial % 3 == 0:
            red[rng.integers(0, red.shape[0]), rng.integers(0, red.shape[1])] = red.max()  # a tie: the first wins
        for search, min_redness in ((5.0, 40.0), (12.3, 10.0), (30.0, 400.0)):
            expected = reference_seed(red, search, min_redness)
            seed = find_seed(red, search, min_redness)
            assert (seed is None) == (expected is None)
            if seed is not None:
                np.testing.assert_array_equal(seed.center, expected.center)
                assert seed.radius == expected.radius


def test_blurred_step_is_scipys_ndtr():
    z = np.concatenate([np.linspace(-45.0, 45.0, 200_001), [-marker._TAIL, marker._TAIL, -1.4142135, 1.4142136]])
    expected = ndtr(z)
    direct = np.array([marker._ndtr(v) for v in z])
    stepped = np.array([marker._blurred_step(v, np.exp(-0.5 * v * v)) for v in z])
    assert np.max(np.abs(direct - expected)) <= 3e-16
    assert np.max(np.abs(stepped - expected)) <= 3e-16
    # Beyond the tail bound ndtr rounds to 1; before its negative, the series holds to 1e-6 of the value.
    assert np.all(expected[z > marker._TAIL] == 1.0)
    tail = (z < -marker._TAIL) & (expected > 0.0)
    assert np.max(np.abs(stepped[tail] / expected[tail] - 1.0)) < 1e-6


def test_pseudo_inverse_matches_numpy_and_opencv():
    rng = np.random.default_rng(3)
    for _ in range(50):
        a = rng.normal(size=(4, 4))
        spd = a @ a.T + 0.1 * np.eye(4)
        # Eight digits of a fit's covariance; these matrices' rounding stays below 1e-12.
        np.testing.assert_allclose(marker._pseudo_inverse(spd), np.linalg.inv(spd), rtol=1e-8, atol=1e-10)
    # Rank-deficient: the pseudo-inverse, as OpenCV's SVD gives it.
    v = rng.normal(size=(4, 2))
    singular = v @ v.T
    _, expected = cv2.invert(singular, flags=cv2.DECOMP_SVD)
    np.testing.assert_allclose(marker._pseudo_inverse(singular), expected, atol=1e-8 * np.abs(expected).max())
