"""
Bare-LED point lamps end to end.

Detection, tone IDs and poses on simulated photos of the published five-LED rig
(``vlp_ros.sim.point_lamps``), for each look, with and without an IMU.

python -m vlp_ros.benchmarks.point_lamps [--photos N] [--camera 4k] [--seed S] [--looks NAME ...]

Per look, with and without an IMU: LEDs fully in view and detected (an observation
centred within 3 px of the true centre), IDs right / unknown / wrong, frames with a pose
and why the rest have none, the pose error's mean and p95, the mean NEES (6 DoF) and the
share of poses beyond its 99.9 % bound. Beside each look, on the same frames, the rig
authors' plain method: each LED's brightness centroid (the LED known, as their FFT reads
it) and a point-source pose from all five (``cv2.solvePnP``). Targets: every LED
detected; IDs right or unknown, never wrong; a mean error no larger than the plain
method's; mean NEES 3-10 with at most 1 % of poses beyond the bound.
"""
from __future__ import annotations

import argparse
from collections import Counter
from dataclasses import dataclass, field
import sys

import cv2
import numpy as np

from scipy.stats import chi2

from vlp_ros.core.pose import Pose
from vlp_ros.detection import detect_lamps
from vlp_ros.pipeline.config import settings_from_tree
from vlp_ros.pipeline.frame import Pipeline
from vlp_ros.sim.imu import specific_force
from vlp_ros.sim.point_lamps import bare_led_scenario, PointLampLook
from vlp_ros.sim.render import RenderedFrame
from vlp_ros.sim.sensor import encode_jpeg
from vlp_ros.solvers.point_lamps import pose_from_opencv

# An observation this close (px) to an LED's true centre is that LED's detection.
DETECTED_PX = 3.0
NEES_BOUND = float(chi2.ppf(0.999, 6))
TARGET_NEES = (3.0, 10.0)
TARGET_BEYOND = 0.01
# The plain method's lamp: the pixels above this share of the brightest (over the background), within
# this many core radii of it, their rows' gaps (dark stripes) closed.
PLAIN_LEVEL = 0.1


@dataclass(frozen=True)
class Setup:
    """How the photos look, how far off the locator's row time is, and JPEG quality (None: raw)."""

    look: PointLampLook
    row_time_error: float = 0.0
    jpeg_quality: int | None = None


SETUPS = {
    'rig (1 cm core, 40 % glow)': Setup(PointLampLook()),
    'rig, JPEG q90, row time 2 % off': Setup(PointLampLook(), 0.02, 90),
    'soft glow (2 cm core, 10 % glow)': Setup(PointLampLook(core_radius=0.02, glow_level=0.1)),
    'real lens (3x over, PSF tail 5 %, coma 0.3, rough core 15 %), JPEG q85': Setup(
        PointLampLook(overexposure=3.0, tail_level=0.05, coma=0.3, core_roughness=0.15), 0.02, 85),
    'harsh lens (6x over, 25 % glow, tail 10 % at 120 px, coma 0.5, rough 25 %), JPEG q80': Setup(
        PointLampLook(overexposure=6.0, glow_level=0.25, tail_level=0.1, tail_scale=120.0, coma=0.5,
                      core_roughness=0.25), 0.02, 80),
}


@dataclass
class Tally:
    in_view: int = 0
    detected: int = 0
    right: int = 0
    unknown: int = 0
    wrong: int = 0
    poses: int = 0
    outcomes: Counter = field(default_factory=Counter)
    errors: list[float] = field(default_factory=list)
    nees: list[float] = field(default_factory=list)
    plain_errors: list[float] = field(default_factory=list)


def run_setup(setup: Setup, imu: bool, camera: str, photos: int, seed: int) -> Tally:
    scenario = bare_led_scenario(camera, photos=photos, seed=seed, look=setup.look,
                                 row_time_error=setup.row_time_error, jpeg_quality=setup.jpeg_quality)
    pipeline = Pipeline(settings_from_tree(scenario.locator_parameters(imu=imu)))
    rng = np.random.default_rng([seed, 1])
    tally = Tally()
    positions = {sim.lamp.id: sim.lamp.position for sim in scenario.lamps}
    for index, pose in enumerate(scenario.poses):
        frame = scenario.render(index, rng)
        image = frame.image if setup.jpeg_quality is None else cv2.imdecode(
            encode_jpeg(frame.image, setup.jpeg_quality), cv2.IMREAD_COLOR)
        up = None
        if imu:
            force = specific_force(pose, None, scenario.imu_noise, rng)
            up = force / np.linalg.norm(force)
        result = pipeline.process(image, frame.camera, frame.start_time, up)
        truths = [t for t in frame.lamps if t.fully_inside]
        observations = detect_lamps(image)
        tally.in_view += len(truths)
        tally.detected += sum(any(np.linalg.norm(o.center - t.center_pixel) < DETECTED_PX for o in observations)
                              for t in truths)
        # Each ID against the LED at whose light it was read (the nearest to the observation's centre).
        read = [(seen.lamp_id, min(frame.lamps, key=lambda t: np.linalg.norm(seen.observation.center - t.center_pixel)))
                for seen in result.seen if seen.lamp_id is not None]
        right = sum(lamp_id == truth.lamp_id for lamp_id, truth in read)
        tally.right += right
        tally.wrong += len(read) - right
        tally.unknown += result.unknown_ids
        tally.outcomes[result.outcome] += 1
        if result.pose is not None:
            tally.poses += 1
            error = result.pose.error_vector(pose)
            tally.errors.append(float(np.linalg.norm(error[:3])))
            tally.nees.append(float(error @ np.linalg.solve(result.pose.covariance, error)))
        plain = plain_method_pose(image, frame, positions)
        if plain is not None:
            tally.plain_errors.append(plain.position_error(pose))
    return tally


def plain_method_pose(image: np.ndarray, frame: RenderedFrame, positions: dict[int, np.ndarray]) -> Pose | None:
    """
    Return the pose by the rig authors' plain method on one photo: brightness centroids and a point-source PnP.

    Each LED in view (map ``positions`` by ID) is the blob of light at its true image (its ID given,
    as their FFT reads it); its centre is the blob's brightness centroid over the background; the pose
    is ``cv2.solvePnP`` on those centres. None with fewer than four LEDs.
    """
    brightness = (image.max(axis=2) if image.ndim == 3 else image).astype(np.float32)
    light = np.maximum(brightness - float(np.median(brightness)), 0.0)
    mask = (light > PLAIN_LEVEL * light.max()).astype(np.uint8)
    # The dark stripes split a lamp into bands: closed over a few stripe periods' rows.
    mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, np.ones((41, 3), np.uint8))
    _, labels = cv2.connectedComponents(mask)
    centres, points = [], []
    for truth in frame.lamps:
        x, y = np.rint(truth.center_pixel).astype(int) if truth.fully_inside else (-1, -1)
        if x < 0 or labels[y, x] == 0:
            continue
        ys, xs = np.nonzero(labels == labels[y, x])
        weights = light[ys, xs]
        centres.append([np.sum(weights * xs), np.sum(weights * ys)] / np.sum(weights))
        points.append(positions[truth.lamp_id])
    if len(centres) < 4:
        return None
    ok, rvec, tvec = cv2.solvePnP(np.array(points, dtype=float), np.array(centres, dtype=float),
                                  frame.camera.K, frame.camera.D, flags=cv2.SOLVEPNP_SQPNP)
    if not ok:
        return None
    ok, rvec, tvec = cv2.solvePnP(np.array(points, dtype=float), np.array(centres, dtype=float), frame.camera.K,
                                  frame.camera.D, rvec, tvec, useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
    return pose_from_opencv(rvec, tvec) if ok else None


def table(rows: list[tuple[str, Tally]], photos: int) -> str:
    lines = ['| look | IMU | LEDs detected | IDs right / unknown / wrong | poses | error mean / p95 / max (cm) | '
             'plain method mean / p95 (cm) | mean NEES | beyond 99.9 % | target | no pose |',
             '| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |']
    for label, t in rows:
        errors, plain = 100 * np.array(t.errors), 100 * np.array(t.plain_errors)
        error = f'{errors.mean():.2f} / {np.percentile(errors, 95):.2f} / {errors.max():.2f}' if len(errors) else '-'
        reference = f'{plain.mean():.2f} / {np.percentile(plain, 95):.2f}' if len(plain) else '-'
        nees = np.array(t.nees)
        beyond = float(np.mean(nees > NEES_BOUND)) if len(nees) else 0.0
        held = (len(errors) > 0 and t.wrong == 0 and t.detected == t.in_view
                and (not len(plain) or errors.mean() <= plain.mean())
                and TARGET_NEES[0] <= nees.mean() <= TARGET_NEES[1] and beyond <= TARGET_BEYOND)
        reasons = ', '.join(f'{k} {v}' for k, v in sorted(t.outcomes.items()) if k != 'pose') or '-'
        lines.append(f'| {label} | {t.detected}/{t.in_view} | {t.right} / {t.unknown} / {t.wrong} | '
                     f'{t.poses}/{photos} | {error} | {reference} | {f"{nees.mean():.1f}" if len(nees) else "-"} | '
                     f'{100 * beyond:.0f} % | {"holds" if held else "missed"} | {reasons} |')
    lines.append("Target: every LED detected, 0 wrong IDs, mean error <= the plain method's, mean NEES "
                 f'{TARGET_NEES[0]:g}-{TARGET_NEES[1]:g}, <= {100 * TARGET_BEYOND:g} % beyond the 99.9 % bound '
                 f'({NEES_BOUND:.1f}).')
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='python -m vlp_ros.benchmarks.point_lamps',
                                     description=__doc__.strip().splitlines()[0])
    parser.add_argument('--photos', type=int, default=24)
    parser.add_argument('--camera', default='4k', choices=('full', '4k', '1080p'))
    parser.add_argument('--seed', type=int, default=1)
    parser.add_argument('--looks', nargs='+', type=int, metavar='N',
                        help=f'only these looks, by number 1-{len(SETUPS)} in the order of the table')
    args = parser.parse_args(argv)
    chosen = list(SETUPS.items())
    if args.looks:
        if not all(1 <= n <= len(chosen) for n in args.looks):
            parser.error(f'--looks: numbers 1-{len(chosen)}')
        chosen = [chosen[n - 1] for n in args.looks]
    rows = []
    for name, setup in chosen:
        for imu in (False, True):
            tally = run_setup(setup, imu, args.camera, args.photos, args.seed)
            rows.append((f'{name} | {"yes" if imu else "no"}', tally))
    print(f'bare-LED rig, {args.camera}, {args.photos} photos per look, seed {args.seed}')
    print(table(rows, args.photos))
    return 0


if __name__ == '__main__':
    sys.exit(main())
