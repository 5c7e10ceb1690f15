"""
Pose covariance by first-order propagation of the measurement noise.

The pose is perturbed as in ``Pose``'s covariance convention: ``delta`` =
(position offset in the map, rotation vector about the map axes applied on the
left). With residuals already divided by their sigmas, the covariance of
``delta`` at the least-squares solution is (J^T J)^-1, J = d residuals / d delta.
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from typing import NamedTuple

import numpy as np

from vlp_ros.compiled import kernel
from vlp_ros.core.pose import Pose
from vlp_ros.solvers.fit_kernels import information_matrix, perturb

# Beyond this condition number of J^T J scaled to unit diagonal (units cancel)
# some pose direction is not observed to first order (e.g. an exactly frontal
# view of one lamp), and no first-order covariance exists.
_MAX_CONDITION = 1e12


def perturbed(pose: Pose, delta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rotation, position) of ``pose`` moved by ``delta`` = (dx, dy, dz, rotation vector)."""
    rotation, position = np.empty((3, 3)), np.empty(3)
    perturb(np.ascontiguousarray(pose.rotation), np.ascontiguousarray(pose.position),
            np.ascontiguousarray(delta, dtype=float), rotation, position)
    return rotation, position


def covariance_from_jacobian(jacobian: np.ndarray) -> np.ndarray:
    """(J^T J)^-1 of a whitened residual Jacobian; ValueError if the pose is not fully observed."""
    covariance = _covariance(np.ascontiguousarray(jacobian, dtype=float), _MAX_CONDITION)
    if covariance is None:
        raise ValueError('the measurements do not determine all six pose degrees of freedom')
    return covariance


@kernel
def _covariance(jacobian, max_condition):
    """
    Return the symmetrised (J^T J)^-1, or None if J^T J is not finite or is ill-conditioned.

    None also if it has an unobserved direction or a condition number (scaled to unit diagonal) over
    ``max_condition``.
    """
    information = np.empty((6, 6))
    information_matrix(jacobian, information)
    if not np.all(np.isfinite(information)):
        return None
    scaled = np.empty((6, 6))
    for i in range(6):
        if not information[i, i] > 0.0:
            return None
    for i in range(6):
        for j in range(6):
            scaled[i, j] = information[i, j] / math.sqrt(information[i, i] * information[j, j])
    if np.linalg.cond(scaled) > max_condition:
        return None
    covariance = np.linalg.inv(information)
    return 0.5 * (covariance + covariance.T)


def with_lamp_position_uncertainty(covariance: np.ndarray, lamp_jacobians: list[np.ndarray],
                                   other_information: np.ndarray, position_sigmas: list[np.ndarray | None]
                                   ) -> np.ndarray:
    """
    Return the pose ``covariance`` widened by how uncertain the lamps' map positions are.

    ``lamp_jacobians`` are each lamp's whitened residual Jacobians (M_l, 6) at the pose, ``other_information``
    the information (6, 6) of the fit's other measurements (up directions), ``position_sigmas`` each lamp's
    standard deviations (m) along the map axes (None: exact). A lamp moved by ``d`` in the map moves its
    residuals as the camera moved by ``-d`` would (only their difference is seen), so the least-squares pose
    moves by ``A_l d``, ``A_l = (J^T J)^-1 J_l^T J_l[:, :3]``; independent lamps add ``A_l diag(sigma_l^2) A_l^T``.
    One lamp alone carries the camera along: ``A = [I; 0]``.
    """
    information = other_information + sum(j.T @ j for j in lamp_jacobians)
    try:
        fit_covariance = np.linalg.inv(information)
    except np.linalg.LinAlgError:
        return covariance
    widened = np.array(covariance, dtype=float)
    for jacobian, sigma in zip(lamp_jacobians, position_sigmas):
        if sigma is None:
            continue
        shift = fit_covariance @ (jacobian.T @ jacobian[:, :3])
        widened += (shift * np.square(sigma)) @ shift.T
    return 0.5 * (widened + widened.T)


def nees(estimate: Pose, truth: Pose) -> float:
    """Normalised estimation error squared of ``estimate`` under its own covariance (mean 6 if honest)."""
    if estimate.covariance is None:
        raise ValueError('the estimate has no covariance')
    error = estimate.error_vector(truth)
    return float(error @ np.linalg.solve(estimate.covariance, error))


def with_rotation_curvature(covariance: np.ndarray, lever: np.ndarray) -> np.ndarray:
    """
    Return ``covariance`` widened by the second-order position error of a pose turning about a sharp bearing.

    The pose turns about a point whose bearing it sees sharply: the lamp centre, at map offset ``lever``
    from the camera.

    With the bearing pinned, a rotation error d moves the camera by
    -(exp([d]x) - I) lever = -d x lever + q / 2, q = d x (d x lever). Along the lever
    the fitted range absorbs q; across it, q_i = (d . lever)(p_i . d), p_i the i-th row
    of the projector across the lever (the twist about the line of sight times the tilt
    across it): quadratic in d, so outside any first-order covariance. With d ~ N(0, P),
    q_i = d^T B_i d, B_i = sym(p_i lever^T): E q_i = tr(B_i P), Cov(q_i, q_j) =
    2 tr(B_i P B_j P); the second moment of q / 2 is added to the position block. It
    matters only when rotations are uncertain by degrees (one lamp seen near-frontally,
    its tilt from gravity), and is then many sigma of the bearing.
    """
    widened = np.array(covariance, dtype=float)
    _add_rotation_curvature(widened, np.ascontiguousarray(lever, dtype=float))
    return widened


@kernel
def _add_rotation_curvature(covariance, lever):
    """``with_rotation_curvature`` in place: B_i = sym(p_i lever^T) against the rotation block P."""
    length = math.sqrt(lever[0] * lever[0] + lever[1] * lever[1] + lever[2] * lever[2])
    b = np.empty((3, 3, 3))
    for i in range(3):
        for j in range(3):
            for k in range(3):
                across_ij = (1.0 if i == j else 0.0) - lever[i] * lever[j] / (length * length)
                across_ik = (1.0 if i == k else 0.0) - lever[i] * lever[k] / (length * length)
                b[i, j, k] = 0.5 * (across_ij * lever[k] + lever[j] * across_ik)
    b_p = np.zeros((3, 3, 3))
    for i in range(3):
        for j in range(3):
            for k in range(3):
                for m in range(3):
                    b_p[i, j, k] += b[i, j, m] * covariance[3 + m, 3 + k]
    mean = np.empty(3)
    for i in range(3):
        mean[i] = 0.5 * (b_p[i, 0, 0] + b_p[i, 1, 1] + b_p[i, 2, 2])
    for i in range(3):
        for m in range(3):
            total = 0.0
            for j in range(3):
                for k in range(3):
                    total += b_p[i, j, k] * b_p[m, k, j]
            covariance[i, m] += 0.5 * total + mean[i] * mean[m]


# Model error. A lamp that is not the model's uniform disc with a sharp edge (a diffuser
# brighter in the middle, glare, soft edges, a rolling-shutter lamp's rows read apart from
# its columns) moves its half-level crossings by a smooth pattern round the rim: measured on
# an independent renderer's frames with blur 1.6 px, 30 % falloff and glare, at the true pose,
# 0.3-0.4 px inward and 0.6 px in the second harmonic, where clean frames are within 0.05 px.
# Such a pattern's offset and first two harmonics (``measurement.rim_error_modes``) are what
# an ellipse absorbs: one lamp's residuals cannot show them, while the fit turns them into
# range and tilt (1-2 degrees near frontal views) and claims hundredths of a pixel for them
# from the rim's hundreds of points. So each lamp's modes are parameters of the fit, with a
# common prior sigma that the frame's redundancy estimates (restricted maximum likelihood
# over ``_MODE_SIGMA_GRID_PX``, the pose marginalised): the disagreement of the lamps with
# one another, with an up direction, with the marker. Where the modes are consistent with
# noise (clean frames), the sigma comes out near 0 and nothing changes; where they are not,
# the rim's shape counts for what the disagreement shows and the pose moves toward the
# measurements that disagree with it. Where that estimate rests on little redundancy (two lamps:
# 0-0.2 px on the simulator's realistic robot row, whose modes at the true pose were 0.3-0.6 px),
# a lamp's own prior (``mode_prior_sigma``, from its edge) bounds what the fit may claim: the
# covariance is that of the fit's estimate with the lamp's modes spread by that prior (the sandwich
# of ``_add_mode_prior_excess``), and the pose stays where the estimated sigma put it (a floor on
# the sigma itself moved the independent renderer's robot poses, doubling their errors). A lamp's prior
# can overstate its patterns (the independent renderer's tone lamps showed 0.21 of theirs at the true
# pose): with ``MIN_BOUNDING_LAMPS`` or more lamps, no lamp's prior counts beyond the largest sigma the
# frame's restricted likelihood leaves plausible (within ``MODE_SIGMA_BOUND_DEVIANCE`` of its best; on
# synthetic frames of 3-6 lamps whose priors were four times their patterns, the mean NEES went from
# 0.8-0.9 to 3.2-4.9, and one lamp eight times worse than the others, stated right, stayed covered).
# Two lamps' estimate is too loose to bound by (0-0.2 px on the simulator's realistic robot row, whose
# modes were 0.3-0.6 px). Besides,
# a common rim offset (all lamps alike) is a parameter with a prior of ``RIM_OFFSET_FLOOR_PX``
# (or ``RIM_OFFSET_PRIOR`` times the rim's scatter, if more); with several lamps, which fix the
# scale, it moves the pose where the data determine it (its variance below ``OFFSET_DETERMINED``
# of the prior's). One lamp's marker would fix the scale too, but too noisily and with a bias near
# frontal views (measured: 2 mm at 0.3 m, 5 standard errors): there it only widens the covariance
# along range by ``RIM_OFFSET_PRIOR`` times the rim's scatter, or by the lamp's own measured prior
# if that is less. With an up direction, one lamp's pose (its modes marginalised under that prior)
# and the up direction's tilt are weighed by what each knows (``_up_fused_step``).
# The rim points' scatter beyond their stated sigma, and a marker that the pose cannot place within
# ``MARKER_CONSISTENT`` sigmas, widen their own information by what their residuals show.
RIM_OFFSET_PRIOR = 1.5
RIM_OFFSET_FLOOR_PX = 0.5
MIN_OFFSET_SIGMA_PX = 1e-3
OFFSET_DETERMINED = 0.25
MARKER_CONSISTENT = 2.0
_REWEIGHTINGS = 2
_MODE_REWEIGHTINGS = 1
# The modes of ``measurement.rim_error_modes`` (first, past the last) that trade with the tilt: cos 2t, sin 2t.
_TILT_MODES = (3, 5)
# The deviance (twice the log-likelihood) by which the modes' sigma bound lies off the likeliest: 99 % for
# one parameter (95 %, 3.84, left 1 pose of 30-39 beyond the bound on each of three synthetic several-lamp
# cases that 99 % keeps within it).
MODE_SIGMA_BOUND_DEVIANCE = 6.63
MIN_BOUNDING_LAMPS = 3
# Candidate prior sigmas (px) of the rim modes: none, then 0.005 to 5 px a factor sqrt(2) apart
# (a likelihood this flat near its maximum costs nothing at that spacing).
_MODE_SIGMA_GRID_PX = np.concatenate([[1e-4], 0.005 * 2.0 ** (np.arange(21) / 2.0)])


@dataclass(frozen=True)
class ModelErrorFit:
    """
    The pose fit allowing for model error.

    The pose ``step`` (as ``perturbed``'s delta), its ``covariance``, the chi-square ``cost``
    of the fit with only the common rim offset (its prior included; the measure candidates are
    compared and gated by), the common rim offset ``rim_offset`` (px, outward positive; 0 where
    not determined), the rim modes' estimated prior sigma ``mode_sigma`` (px), and
    ``fit_covariance``: the covariance before the modes were marginalised with their given
    prior, or before the lamps' priors widened the several-lamp fit's (None where neither was
    done).
    """

    step: np.ndarray
    covariance: np.ndarray
    cost: float
    rim_offset: float
    mode_sigma: float
    fit_covariance: np.ndarray | None = None


def allow_for_model_error(residuals: np.ndarray, jacobian: np.ndarray, rim_sigma: np.ndarray,
                          modes: np.ndarray, lamp_of_point: np.ndarray, lamp_count: int,
                          marker_count: int, mode_prior_sigma: np.ndarray | None = None) -> ModelErrorFit:
    """
    Return the linear update of a converged fit by a common rim offset, each lamp's rim modes and the scatter.

    The fit is given as whitened ``residuals`` and ``jacobian`` laid out as ``fit_kernels.Terms``: rim
    points, then 2 per marker, then 2 per up direction. The update is by a common rim offset, each
    lamp's rim ``modes`` (``measurement.rim_error_modes``, rows as the rim points, ``lamp_of_point``
    their lamp) and the residuals' own scatter; ValueError if the pose is not fully observed.
    ``mode_prior_sigma`` (px, per lamp; None: 0) is what each lamp's edge shows of its modes
    (``LampObservation.rim_model_sigma``): where the frame's lamps cannot estimate the modes' sigma (one
    lamp), the modes are marginalised with it, widening the covariance along what they trade with; the
    pose stays where the fit put it unless an up direction was fitted too, when the lamp's tilt and the up
    direction's are weighed by their covariances in the step (``_up_fused_step``); with several lamps, a
    lamp's prior over the estimated sigma (up to the sigma's plausible bound, with three or more) widens
    the covariance alike, the pose left in place.
    """
    covariance_from_jacobian(jacobian)  # raises where no first-order covariance exists
    rim_count = len(rim_sigma)
    offset_sigma = _rim_offset_sigma(residuals[:rim_count], rim_sigma)
    estimated = lamp_count >= 2
    if estimated:
        offset_sigma = max(offset_sigma, RIM_OFFSET_FLOOR_PX)
    elif mode_prior_sigma is not None and len(mode_prior_sigma) and mode_prior_sigma.max() > 0.0:
        # One lamp whose edge measured its modes: its own offset mode, marginalised with that prior, holds
        # what its size may be off by (a rim put at the profile model's edge: 0.003-0.15 px where its points
        # scatter by 0.03-0.2 px). The common offset is the same column of the fit: a prior on it as well
        # would count that doubt twice (range 1.4 times as uncertain: on the independent renderer's hand-held
        # stills the range was within 0.1-0.4 of its sigma even counted once), so it is held.
        offset_sigma = MIN_OFFSET_SIGMA_PX
    step, covariance, fit_covariance = np.empty(6), np.empty((6, 6)), np.empty((6, 6))
    fitted = _model_error_fit(
        np.ascontiguousarray(residuals, dtype=float), np.ascontiguousarray(jacobian, dtype=float),
        np.ascontiguousarray(rim_sigma, dtype=float), np.ascontiguousarray(modes, dtype=float),
        np.ascontiguousarray(lamp_of_point, dtype=np.int64), lamp_count, marker_count, offset_sigma, estimated,
        max(rim_count - 5 * lamp_count - 1, 1), _MODE_SIGMA_GRID_PX,
        np.zeros(lamp_count) if mode_prior_sigma is None else np.ascontiguousarray(mode_prior_sigma, dtype=float),
        step, covariance, fit_covariance)
    return ModelErrorFit(step=step, covariance=covariance, cost=fitted.cost, rim_offset=fitted.rim_offset,
                         mode_sigma=fitted.mode_sigma, fit_covariance=fit_covariance if fitted.marginalised else None)


def _rim_offset_sigma(rim_residuals: np.ndarray, rim_sigma: np.ndarray) -> float:
    """
    Return the rim offset's prior sigma (px) from the rims' scatter.

    Point lamps alone have no rim, and then the offset, which moves nothing, keeps the
    floor's prior.
    """
    if not len(rim_sigma):
        return RIM_OFFSET_FLOOR_PX
    scatter_px = float(np.sqrt(np.mean(np.square(rim_residuals * rim_sigma))))
    return RIM_OFFSET_PRIOR * max(scatter_px, float(np.mean(rim_sigma)))


class _ModelErrorScalars(NamedTuple):
    """
    ``_model_error_fit``'s result beside its arrays.

    The cost, the rim offset, the mode sigma, and whether ``fit_covariance`` was set (the modes
    marginalised with their given prior, or a lamp's prior over the estimated sigma).
    """

    cost: float
    rim_offset: float
    mode_sigma: float
    marginalised: bool


@kernel
def _model_error_fit(residuals, jacobian, rim_sigma, modes, lamp_of_point, lamp_count, marker_count, offset_sigma,
                     estimated, rim_dof, mode_sigma_grid, mode_prior_sigma, step, covariance, fit_covariance):
    """
    Write ``allow_for_model_error`` into ``step``, ``covariance`` and ``fit_covariance``.

    It returns the rest (``_ModelErrorScalars``). Parameters: the pose (6), the common rim offset,
    ``RIM_MODES`` per lamp (several lamps, or one with a prior sigma of its modes).
    """
    count, rims = residuals.shape[0], rim_sigma.shape[0]
    per_lamp = modes.shape[1]
    marginalised = not estimated and rims > 0 and mode_prior_sigma.max() > 0.0
    width = 7 + (per_lamp * lamp_count if estimated or marginalised else 0)
    design = np.zeros((count, width))
    design[:, :6] = jacobian
    for i in range(rims):
        design[i, 6] = -modes[i, 0] / rim_sigma[i]
        if estimated or marginalised:
            first = 7 + per_lamp * lamp_of_point[i]
            for j in range(per_lamp):
                design[i, first + j] = -modes[i, j] / rim_sigma[i]
    offset_precision = 1.0 / (offset_sigma * offset_sigma)
    # The fit with the common offset alone: its chi-square is the cost.
    weights = np.ones(count)
    predicted = residuals.copy()
    for reweighting in range(_REWEIGHTINGS + 1):
        gram, gradient = _normal_equations_of(design, 7, count, residuals, weights, lamp_of_point)
        solution, inverse = _offset_rule_solution(gram, gradient, offset_precision, offset_sigma, estimated)
        _predict(design, residuals, solution, predicted)
        if reweighting < _REWEIGHTINGS:
            _reweight(predicted, weights, rims, marker_count, rim_dof)
    cost = float(np.sum(predicted * predicted)) + (solution[6] / offset_sigma) ** 2
    offset = solution[6]
    mode_sigma = 0.0
    if marginalised:
        for i in range(6):
            for j in range(6):
                fit_covariance[i, j] = 0.5 * (inverse[i, j] + inverse[j, i])
        inverse = _marginalised_modes(design, width, count, residuals, weights, lamp_of_point, per_lamp,
                                      mode_prior_sigma, offset_precision)
        if count > rims + 2 * marker_count:
            # An up direction measures the tilt that the rim's modes trade with: the pose goes where
            # both put it, each by what it knows (the lamp under its modes' prior, the up by its sigma).
            _up_fused_step(design, width, count, rims + 2 * marker_count, residuals, weights, lamp_of_point,
                           per_lamp, mode_prior_sigma, offset_precision, offset_sigma, solution)
    if estimated:
        # The fit with each lamp's modes, from the weights the fit without them ended with (the
        # modes take up part of that scatter), their prior sigma estimated at each reweighting.
        _reweight(predicted, weights, rims, marker_count, rim_dof)
        # From the lamps alone: an up direction that disagrees (an accelerating IMU) is no
        # evidence of model error, and the lamps' shapes must not yield to it.
        lamp_rows = rims + 2 * marker_count
        for reweighting in range(_MODE_REWEIGHTINGS + 1):
            upper, gradient = np.zeros((width, width)), np.zeros(width)
            _weighted_normal_equations(design, width, 0, lamp_rows, residuals, weights, lamp_of_point, per_lamp, upper,
                                       gradient)
            mode_sigma, bound = _likeliest_mode_sigma(_symmetric(upper), gradient, offset_precision, mode_sigma_grid)
            _weighted_normal_equations(design, width, lamp_rows, count, residuals, weights, lamp_of_point, per_lamp,
                                       upper, gradient)
            gram = _symmetric(upper)
            for k in range(7, width):
                gram[k, k] += 1.0 / (mode_sigma * mode_sigma)
            solution, inverse = _offset_rule_solution(gram, gradient, offset_precision, offset_sigma, estimated)
            _predict(design, residuals, solution, predicted)
            if reweighting < _MODE_REWEIGHTINGS:
                _reweight(predicted, weights, rims, marker_count, rim_dof)
        spread = np.minimum(mode_prior_sigma, max(bound, mode_sigma)) if lamp_count >= MIN_BOUNDING_LAMPS \
            else mode_prior_sigma
        if spread.max() > mode_sigma:
            # Candidates are told apart and up directions judged by the fit's own covariance, as for one lamp.
            for i in range(6):
                for j in range(6):
                    fit_covariance[i, j] = 0.5 * (inverse[i, j] + inverse[j, i])
            marginalised = True
            _add_mode_prior_excess(inverse, mode_sigma, spread, per_lamp)
    for i in range(6):
        step[i] = solution[i]
        for j in range(6):
            covariance[i, j] = 0.5 * (inverse[i, j] + inverse[j, i])
    return _ModelErrorScalars(cost, offset, mode_sigma, marginalised)


@kernel
def _add_mode_prior_excess(inverse, mode_sigma, spread, per_lamp):
    """
    Turn ``inverse`` (in place) into the covariance of its fit's estimate where a lamp's modes spread by more.

    ``inverse`` is of the fit with every lamp's modes under the prior sigma ``mode_sigma``; the modes
    spread by ``spread`` (px, per lamp): the sandwich H^-1 (H - P + P S P) H^-1, which adds
    (spread^2 - sigma^2) g g^T per mode, g = H^-1 e_k / sigma^2 the estimate's pull by the mode. The
    pose stays where the fit put it.
    """
    variance = mode_sigma * mode_sigma
    pulls = inverse[:, 7:] / variance
    for lamp in range(spread.shape[0]):
        excess = spread[lamp] * spread[lamp] - variance
        if excess <= 0.0:
            continue
        for j in range(per_lamp):
            k = per_lamp * lamp + j
            for a in range(inverse.shape[0]):
                for b in range(inverse.shape[0]):
                    inverse[a, b] += excess * pulls[a, k] * pulls[b, k]


@kernel
def _marginalised_modes(design, width, count, residuals, weights, lamp_of_point, per_lamp, mode_prior_sigma,
                        offset_precision):
    """
    Return the inverse information of the pose, the offset and each lamp's modes under their prior sigmas.

    A lamp without one has its modes fixed at 0; the rim points are weighted as the fit left them.
    """
    upper, gradient = np.zeros((width, width)), np.zeros(width)
    _weighted_normal_equations(design, width, 0, count, residuals, weights, lamp_of_point, per_lamp, upper, gradient)
    information = _symmetric(upper)
    information[6, 6] += offset_precision
    for lamp in range(mode_prior_sigma.shape[0]):
        sigma = mode_prior_sigma[lamp]
        precision = 1.0 / (sigma * sigma) if sigma > 0.0 else 1e30
        for j in range(per_lamp):
            k = 7 + per_lamp * lamp + j
            information[k, k] += precision
    return np.linalg.inv(information)


@kernel
def _up_fused_step(design, width, count, lamp_rows, residuals, weights, lamp_of_point, per_lamp, mode_prior_sigma,
                   offset_precision, offset_sigma, solution):
    """
    Write into ``solution`` the pose step that weighs the lamp's tilt and the up directions' by what each knows.

    The tilt (the rotation about the map's x and y) is the lamp's own least-squares pose (rows before
    ``lamp_rows``: the rim points and marker), with the covariance of its modes marginalised under their
    prior, updated linearly by the up rows (Kalman: S = J P J^T + W^-1, step -P J^T S^-1 (r + J step)).
    The rest of the pose is then the lamp's at that tilt, its second harmonic (the ellipse's elongation
    and direction, which trade with the tilt: ``_TILT_MODES``) free under the prior.

    A rim whose shape the optics bend thus yields to a good up direction by what its modes' prior allows,
    and no more. Freeing the harmonics in one joint step with the up rows let the rest of the rim's
    shape and its marker pull the tilt (0.3 degrees off both the rim's and the IMU's tilt on a frame of
    the independent renderer's hand-held set); the linear update alone left the range and bearing where
    the lamp's own wrong tilt had put them (4 cm off on soft rims 2 degrees off).
    """
    gram, gradient = _normal_equations_of(design, 7, lamp_rows, residuals, weights, lamp_of_point)
    lamp_step, _ = _offset_rule_solution(gram, gradient, offset_precision, offset_sigma, False)
    lamp_covariance = np.ascontiguousarray(_marginalised_modes(design, width, lamp_rows, residuals, weights,
                                                               lamp_of_point, per_lamp, mode_prior_sigma,
                                                               offset_precision)[:6, :6])
    ups = count - lamp_rows
    jacobian = np.empty((ups, 6))
    innovation = np.empty(ups)
    for a in range(ups):
        root = math.sqrt(weights[lamp_rows + a])
        total = residuals[lamp_rows + a]
        for i in range(6):
            jacobian[a, i] = root * design[lamp_rows + a, i]
            total += design[lamp_rows + a, i] * lamp_step[i]
        innovation[a] = root * total
    projected = jacobian @ lamp_covariance
    gain = np.linalg.solve(projected @ jacobian.T + np.eye(ups), projected)
    correction = gain.T @ innovation
    tilt = (lamp_step[3] - correction[3], lamp_step[4] - correction[4])
    upper, gradient = np.zeros((width, width)), np.zeros(width)
    _weighted_normal_equations(design, width, 0, lamp_rows, residuals, weights, lamp_of_point, per_lamp, upper,
                               gradient)
    information = _symmetric(upper)
    free = [0, 1, 2, 5]
    for lamp in range(mode_prior_sigma.shape[0]):
        sigma = mode_prior_sigma[lamp]
        if not sigma > 0.0:
            continue
        for j in range(_TILT_MODES[0], _TILT_MODES[1]):
            k = 7 + per_lamp * lamp + j
            information[k, k] += 1.0 / (sigma * sigma)
            free.append(k)
    size = len(free)
    reduced, right = np.empty((size, size)), np.empty(size)
    for a in range(size):
        right[a] = -(gradient[free[a]] + information[free[a], 3] * tilt[0] + information[free[a], 4] * tilt[1])
        for b in range(size):
            reduced[a, b] = information[free[a], free[b]]
    stepped = np.linalg.solve(reduced, right)
    for k in range(solution.shape[0]):
        solution[k] = 0.0
    for a in range(size):
        if free[a] < solution.shape[0]:
            solution[free[a]] = stepped[a]
    solution[3], solution[4] = tilt


@kernel
def _weighted_normal_equations(design, columns, start, stop, residuals, weights, lamp_of_point, per_lamp, gram,
                               gradient):
    """
    Add (D^T W D, D^T W r) of the whitened ``design`` to ``gram`` (upper triangle) and ``gradient``.

    The sums are over the design's first ``columns`` and ``residuals`` over rows ``start`` to
    ``stop``, under ``weights``. A rim point moves only the pose, the offset and its own lamp's modes;
    other rows only the pose.
    """
    per_lamp = (design.shape[1] - 7) // max(lamp_of_point.shape[0] and (lamp_of_point.max() + 1), 1)
    used = np.empty(7 + per_lamp, dtype=np.int64)
    for n in range(start, stop):
        count = 7
        for k in range(7):
            used[k] = k
        if columns > 7 and n < lamp_of_point.shape[0]:
            first = 7 + per_lamp * lamp_of_point[n]
            for j in range(per_lamp):
                used[7 + j] = first + j
            count = 7 + per_lamp
        for a in range(count):
            i = used[a]
            weighted = weights[n] * design[n, i]
            if weighted == 0.0:
                continue
            gradient[i] += weighted * residuals[n]
            for b in range(a, count):
                gram[i, used[b]] += weighted * design[n, used[b]]


@kernel
def _normal_equations_of(design, columns, rows, residuals, weights, lamp_of_point):
    """``_weighted_normal_equations`` of the pose and offset over the first ``rows``, as a full matrix."""
    gram, gradient = np.zeros((columns, columns)), np.zeros(columns)
    _weighted_normal_equations(design, columns, 0, rows, residuals, weights, lamp_of_point, 0, gram, gradient)
    return _symmetric(gram), gradient


@kernel
def _symmetric(upper):
    """Return the symmetric matrix whose upper triangle is ``upper``'s."""
    full = upper.copy()
    for i in range(full.shape[0]):
        for j in range(i):
            full[i, j] = full[j, i]
    return full


@kernel
def _predict(design, residuals, solution, predicted):
    """Write the residuals after the step ``solution`` (over the design's first columns) into ``predicted``."""
    for n in range(residuals.shape[0]):
        total = residuals[n]
        for k in range(solution.shape[0]):
            total += design[n, k] * solution[k]
        predicted[n] = total


@kernel
def _offset_rule_solution(information, gradient, offset_precision, offset_sigma, estimated):
    """
    Return the Gauss-Newton step of all parameters of ``information``, and the inverse information.

    The step has their priors in, except the common offset's; the inverse information is with the
    offset's prior. The offset is left at 0 in the step unless ``estimated`` and the data determine it.
    """
    information = information.copy()
    information[6, 6] += offset_precision
    inverse = np.linalg.inv(information)
    if estimated and inverse[6, 6] < OFFSET_DETERMINED * offset_sigma * offset_sigma:
        return -(inverse @ gradient), inverse
    width = information.shape[0]
    stepped = np.array([k for k in range(width) if k != 6])
    reduced = np.empty((width - 1, width - 1))
    for a in range(width - 1):
        for b in range(width - 1):
            reduced[a, b] = information[stepped[a], stepped[b]]
    solved = np.linalg.solve(reduced, gradient[stepped])
    solution = np.zeros(width)
    for a in range(width - 1):
        solution[stepped[a]] = -solved[a]
    return solution, inverse


@kernel
def _likeliest_mode_sigma(gram, gradient, offset_precision, grid):
    """
    Return the modes' prior sigma on ``grid`` that maximises the restricted likelihood of the weighted residuals.

    Also the largest on the grid within ``MODE_SIGMA_BOUND_DEVIANCE`` of its maximum (inf where that is
    the grid's last). The pose is flat and the offset at its prior: with the pose and offset profiled out
    (information M and gradient h of the modes), it minimises
    log det(I + sigma^2 M) - h^T (M + I / sigma^2)^-1 h.
    """
    width = gram.shape[0]
    information = gram.copy()
    information[6, 6] += offset_precision
    cross = np.ascontiguousarray(information[:7, 7:])
    solved = np.linalg.solve(np.ascontiguousarray(information[:7, :7]),
                             np.concatenate((cross, gradient[:7].reshape(7, 1)), axis=1))
    profiled = np.ascontiguousarray(information[7:, 7:]) - cross.T @ np.ascontiguousarray(solved[:, :width - 7])
    profiled_gradient = gradient[7:] - cross.T @ np.ascontiguousarray(solved[:, width - 7])
    values, vectors = np.linalg.eigh(0.5 * (profiled + profiled.T))
    projected = vectors.T @ profiled_gradient
    objectives = np.empty(grid.shape[0])
    for g in range(grid.shape[0]):
        variance = grid[g] * grid[g]
        objective = 0.0
        for k in range(values.shape[0]):
            value = max(values[k], 0.0)
            objective += math.log(1.0 + variance * value) - projected[k] ** 2 * variance / (1.0 + variance * value)
        objectives[g] = objective
    best = int(np.argmin(objectives))
    bound = best
    while bound + 1 < grid.shape[0] and objectives[bound + 1] - objectives[best] <= MODE_SIGMA_BOUND_DEVIANCE:
        bound += 1
    # Past the grid's end the bound is unknown: no bound.
    return grid[best], grid[bound] if bound + 1 < grid.shape[0] else np.inf


@kernel
def _reweight(predicted, weights, rims, marker_count, rim_dof):
    """
    Set ``weights``: rim points and markers that the pose does not explain count for less.

    Rim points count for less by their scatter beyond their sigma, a marker the pose cannot place
    within ``MARKER_CONSISTENT`` sigmas by its chi-square.
    """
    chi_square = 0.0
    for i in range(rims):
        chi_square += predicted[i] * predicted[i]
    rim_weight = 1.0 / max(1.0, chi_square / rim_dof)
    for i in range(rims):
        weights[i] = rim_weight
    for k in range(marker_count):
        a, b = rims + 2 * k, rims + 2 * k + 1
        marker_chi_square = predicted[a] * predicted[a] + predicted[b] * predicted[b]
        weight = 1.0 / marker_chi_square if marker_chi_square > MARKER_CONSISTENT ** 2 else 1.0
        weights[a] = weight
        weights[b] = weight


def widened_toward_up(pose: Pose, up_in_camera: np.ndarray, pivot: np.ndarray, share: float = 1.0) -> np.ndarray:
    """
    Return ``pose``'s covariance widened toward agreeing with a measured up direction.

    It is plus ``share`` of the outer product of the pose change that would make it agree with a
    measured up direction (unit, camera frame): the rotation turning its up onto it, the camera turning
    about the map point ``pivot`` whose bearing the image pins. Whether the up measurement (an
    accelerating IMU) or the lamps (a shape off the model) are wrong, the frame cannot tell: the
    covariance then spans both.
    """
    measured_in_map = pose.rotation @ up_in_camera
    axis = np.cross(measured_in_map, np.array([0.0, 0.0, 1.0]))
    rotation = math.atan2(float(np.linalg.norm(axis)), float(measured_in_map[2])) * axis / max(
        float(np.linalg.norm(axis)), 1e-300)
    widened = np.array(pose.covariance, dtype=float)
    # The tilt is in doubt by that angle about either horizontal axis, not only the one measured,
    # and the position by what it moves the camera; uncorrelated, as the true tilt error is neither
    # exactly the measured angle nor exactly pivoting about ``pivot``.
    for tilt in (rotation, np.array([-rotation[1], rotation[0], 0.0])):
        moved = -np.cross(tilt, pivot - pose.position)
        widened[:3, :3] += share * np.outer(moved, moved)
        widened[3:, 3:] += share * np.outer(tilt, tilt)
    return widened
