"""
Bare-LED point lamps end to end.

Detection, tone IDs and poses on simulated photos of the published five-LED rig
(``vlp_ros.sim.point_lamps``), for each look, with and without an IMU.

python -m vlp_ros.benchmarks.point_lamps [--photos N] [--camera 4k] [--seed S]

Per setup: LEDs fully in view and detected (an observation centred within 3 px of the
true centre), IDs right / unknown / wrong, frames with a pose and why the rest have none,
the pose error and the mean NEES, for each look, raw and as JPEG with the row time 2 % off.
Targets (issue 14): every LED detected; IDs right or unknown, never wrong; with 3 or more
identified, a pose within 5 cm.
"""
from __future__ import annotations

import argparse
from collections import Counter
from dataclasses import dataclass, field
import sys

import cv2
import numpy as np

from vlp_ros.detection import detect_lamps
from vlp_ros.pipeline.config import settings_from_tree
from vlp_ros.pipeline.frame import Pipeline
from vlp_ros.sim.imu import specific_force
from vlp_ros.sim.point_lamps import bare_led_scenario, PointLampLook
from vlp_ros.sim.sensor import encode_jpeg

# An observation this close (px) to an LED's true centre is that LED's detection.
DETECTED_PX = 3.0
TARGET_M = 0.05


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
}


@dataclass
class Tally:
    in_view: int = 0
    detected: int = 0
    right: int = 0
    unknown: int = 0
    wrong: int = 0
    poses: int = 0
    frames_with_three: int = 0
    poses_with_three: int = 0
    outcomes: Counter = field(default_factory=Counter)
    errors: list[float] = field(default_factory=list)
    nees: list[float] = field(default_factory=list)


def run_setup(setup: Setup, imu: bool, camera: str, photos: int, seed: int) -> Tally:
    scenario = bare_led_scenario(camera, photos=photos, seed=seed, look=setup.look,
                                 row_time_error=setup.row_time_error, jpeg_quality=setup.jpeg_quality)
    pipeline = Pipeline(settings_from_tree(scenario.locator_parameters(imu=imu)))
    rng = np.random.default_rng([seed, 1])
    tally = Tally()
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
        tally.frames_with_three += right >= 3
        if result.pose is not None:
            tally.poses += 1
            tally.poses_with_three += right >= 3
            error = result.pose.error_vector(pose)
            tally.errors.append(float(np.linalg.norm(error[:3])))
            tally.nees.append(float(error @ np.linalg.solve(result.pose.covariance, error)))
    return tally


def table(rows: list[tuple[str, Tally]], photos: int) -> str:
    lines = ['| look | IMU | LEDs detected | IDs right / unknown / wrong | frames with >= 3 IDs | poses | '
             'error mean / max (cm) | within 5 cm | mean NEES | no pose |',
             '| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |']
    for label, t in rows:
        errors = np.array(t.errors)
        within = int(np.sum(errors < TARGET_M))
        error = f'{100 * errors.mean():.2f} / {100 * errors.max():.2f}' if len(errors) else '-'
        nees = f'{np.mean(t.nees):.1f}' if t.nees else '-'
        reasons = ', '.join(f'{k} {v}' for k, v in sorted(t.outcomes.items()) if k != 'pose') or '-'
        lines.append(f'| {label} | {t.detected}/{t.in_view} | {t.right} / {t.unknown} / {t.wrong} | '
                     f'{t.frames_with_three}/{photos} | {t.poses}/{photos} | {error} | {within}/{t.poses} | '
                     f'{nees} | {reasons} |')
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='python -m vlp_ros.benchmarks.point_lamps',
                                     description=__doc__.strip().splitlines()[0])
    parser.add_argument('--photos', type=int, default=24)
    parser.add_argument('--camera', default='4k', choices=('full', '4k', '1080p'))
    parser.add_argument('--seed', type=int, default=1)
    args = parser.parse_args(argv)
    rows = []
    for name, setup in SETUPS.items():
        for imu in (False, True):
            tally = run_setup(setup, imu, args.camera, args.photos, args.seed)
            rows.append((f'{name} | {"yes" if imu else "no"}', tally))
    print(f'bare-LED rig, {args.camera}, {args.photos} photos per setup, seed {args.seed}')
    print(table(rows, args.photos))
    return 0


if __name__ == '__main__':
    sys.exit(main())
