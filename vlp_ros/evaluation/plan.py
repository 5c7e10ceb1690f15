"""
Plan a lamp deployment: expected pose error and ID decodability over a room's floor, as a PNG.

    python -m vlp_ros.evaluation.plan --room 6 4 --spacing 2 --ceiling 2.5 --camera 1080p-wide --out plan.png

The camera moves over the floor with one orientation (straight up, optionally tilted);
see ``floor_plan`` for the model and its assumptions.
"""
from __future__ import annotations

import argparse
from pathlib import Path
import sys
import time
from typing import NoReturn

import matplotlib

matplotlib.use('Agg')  # files only; no display on robots or CI
from matplotlib.colors import ListedColormap, LogNorm  # noqa: E402
from matplotlib.patches import Patch  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.ticker import FuncFormatter  # noqa: E402
import numpy as np  # noqa: E402

from vlp_ros.core.camera import CameraModel  # noqa: E402
from vlp_ros.evaluation.floor_plan import (BeaconPlan, ceiling_lamp, Decodability, Deployment,  # noqa: E402
                                           FloorPlan, grid_positions, looking_up, MeasurementNoise,
                                           plan_floor)
from vlp_ros.sim.scenarios import paper_camera  # noqa: E402

WIDE_HFOV_DEG = 100.0
CAMERA_PRESETS = ('4k-lumia', '1080p-lumia', '1080p-wide')
NO_FIX_COLOR = 'lightgrey'
DECODABILITY_STYLE = {Decodability.NONE: ('not decodable', '#d7301f'),
                      Decodability.FEW_FRAMES: ('decodable over a few frames', '#fdae61'),
                      Decodability.ONE_FRAME: ('decodable in one frame', '#1a9850')}
_LEGEND_BELOW = {'loc': 'upper center', 'bbox_to_anchor': (0.5, -0.12), 'fontsize': 'small', 'frameon': False}


def preset_camera(name: str) -> CameraModel:
    """Return the Lumia 1020 of the seed paper at 4K or 1080p, or a 1080p camera with a 100 deg HFOV."""
    if name == '1080p-wide':
        return CameraModel.from_horizontal_fov(1920, 1080, np.radians(WIDE_HFOV_DEG))
    if name in ('4k-lumia', '1080p-lumia'):
        return paper_camera(name.split('-')[0])
    raise ValueError(f'camera must be one of {", ".join(CAMERA_PRESETS)}, got {name!r}')


def error_map_figure(plan: FloorPlan, deployment: Deployment, beacon: BeaconPlan, path: Path, title: str) -> Path:
    """Draw the expected 3D error and decodability over the floor into ``path``, side by side, lamps marked."""
    width, depth = deployment.room
    x_edges = np.linspace(0.0, width, len(plan.xs) + 1)
    y_edges = np.linspace(0.0, depth, len(plan.ys) + 1)
    fig, (ax_error, ax_id) = plt.subplots(1, 2, figsize=(12.0, 5.6), layout='constrained')
    cmap = plt.get_cmap('viridis').with_extremes(bad=NO_FIX_COLOR)
    covered = plan.error_cm[np.isfinite(plan.error_cm)]
    norm = None
    if covered.size:
        low, high = float(covered.min()), float(covered.max())
        norm = LogNorm(low, high if high > low else 1.01 * low)
    mesh = ax_error.pcolormesh(x_edges, y_edges, np.ma.masked_invalid(plan.error_cm), cmap=cmap, norm=norm)
    if covered.size:
        bar = fig.colorbar(mesh, ax=ax_error, label='expected 3D error (cm)')
        bar.ax.yaxis.set_major_formatter(FuncFormatter(lambda value, _: f'{value:g}'))
        bar.ax.yaxis.set_minor_formatter(FuncFormatter(_two_and_five))
    ax_error.set_title('expected 3D position error')
    ax_error.legend(handles=[Patch(color=NO_FIX_COLOR, label='no fix')], **_LEGEND_BELOW)
    levels = [Decodability.ONE_FRAME, Decodability.NONE] if beacon.mode == 'tone' else list(Decodability)
    colors = ListedColormap([DECODABILITY_STYLE[level][1] for level in Decodability])
    ax_id.pcolormesh(x_edges, y_edges, plan.decodability, cmap=colors, vmin=-0.5, vmax=len(Decodability) - 0.5)
    ax_id.set_title('lamp ID from the best-placed lamp')
    ax_id.legend(handles=[Patch(color=DECODABILITY_STYLE[level][1], label=DECODABILITY_STYLE[level][0])
                          for level in sorted(levels, reverse=True)], ncol=len(levels), **_LEGEND_BELOW)
    lamps = np.array([lamp.position[:2] for lamp in deployment.lamps])
    for ax in (ax_error, ax_id):
        ax.scatter(lamps[:, 0], lamps[:, 1], s=40, c='white', edgecolors='black', zorder=3, label='lamp')
        ax.set_xlim(0.0, width)
        ax.set_ylim(0.0, depth)
        ax.set_xlabel('x (m)')
        ax.set_ylabel('y (m)')
        ax.set_aspect('equal')
    fig.suptitle(title, fontsize='medium')
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _two_and_five(value: float, _position: int) -> str:
    """Log-axis minor tick labels at 2 and 5 times a power of ten only (the rest crowd)."""
    leading = value / 10.0 ** np.floor(np.log10(value))
    return f'{value:g}' if np.isclose(leading, 2.0) or np.isclose(leading, 5.0) else ''


def summary(plan: FloorPlan, beacon: BeaconPlan) -> str:
    """Coverage, error percentiles over the covered floor, and where IDs can be read."""
    one_lamp = np.mean(np.isfinite(plan.error_cm) & (plan.lamps_in_view == 1))
    lines = [f'fix on {100 * plan.coverage:.1f} % of the floor ({100 * one_lamp:.1f} % from a single lamp); '
             f'no lamp fully in view on {100 * np.mean(plan.lamps_in_view == 0):.1f} %']
    if plan.coverage > 0.0:
        lines.append(f'expected 3D error over the covered floor: median {plan.error_percentile(50):.2f} cm, '
                     f'95th percentile {plan.error_percentile(95):.2f} cm')
    one_frame = f'ID in one frame on {100 * plan.decodable_fraction(Decodability.ONE_FRAME):.1f} % of the floor'
    if beacon.mode == 'packet':
        one_frame += f', within a few frames on {100 * plan.decodable_fraction(Decodability.FEW_FRAMES):.1f} %'
    lines.append(one_frame)
    return '\n'.join(lines)


class _Parser(argparse.ArgumentParser):
    """Bad options end the run with one line and exit status 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f'{self.prog}: error: {message}\n')


def _arguments(argv: list[str] | None) -> argparse.Namespace:
    parser = _Parser(prog='python -m vlp_ros.evaluation.plan', description=__doc__.strip().splitlines()[0])
    parser.add_argument('--out', type=Path, required=True, help='PNG to write')
    parser.add_argument('--room', type=float, nargs=2, default=(6.0, 4.0), metavar=('WIDTH', 'DEPTH'),
                        help='floor size (m), x by y')
    layout = parser.add_mutually_exclusive_group()
    layout.add_argument('--spacing', type=float, default=2.0, help='lamps on a square grid this far apart (m)')
    layout.add_argument('--lamps', nargs='+', metavar='X,Y', help='explicit lamp positions (m) on the floor plan')
    parser.add_argument('--radius', type=float, default=0.075, help='lamp disc radius (m)')
    parser.add_argument('--ceiling', type=float, default=2.5, help='lamp height above the camera (m)')
    parser.add_argument('--camera', default='1080p-wide', choices=CAMERA_PRESETS)
    parser.add_argument('--fx', type=float, help='explicit camera: focal length (px); needs --width and --height')
    parser.add_argument('--width', type=int, help='explicit camera: image width (px)')
    parser.add_argument('--height', type=int, help='explicit camera: image height (px)')
    parser.add_argument('--tilt', type=float, default=0.0, help='optical axis from straight up (deg)')
    parser.add_argument('--tilt-azimuth', type=float, default=0.0, help='map direction of the tilt (deg from +x)')
    parser.add_argument('--yaw', type=float, default=0.0, help='map direction of image +x (deg from +x)')
    defaults = BeaconPlan()
    parser.add_argument('--beacon', choices=('packet', 'tone'), default=defaults.mode)
    parser.add_argument('--chip-rate', type=float, default=defaults.chip_rate, help='packet mode (Hz)')
    parser.add_argument('--id-bits', type=int, default=defaults.id_bits, help='packet mode')
    parser.add_argument('--row-time', type=float, default=defaults.row_time, help='time between row starts (s)')
    parser.add_argument('--tone-frequency', type=float, default=defaults.tone_frequency,
                        help='tone mode: lowest lamp frequency (Hz)')
    noise = MeasurementNoise()
    parser.add_argument('--rim-sigma', type=float, default=noise.rim_sigma, help='rim point noise (px)')
    parser.add_argument('--marker-sigma', type=float, default=noise.marker_sigma, help='marker noise (px per axis)')
    parser.add_argument('--imu-sigma', type=float, default=noise.imu_sigma, help='IMU up direction noise (rad)')
    parser.add_argument('--no-imu', action='store_true', help='no IMU: one lamp alone gives no fix')
    parser.add_argument('--points', type=int, default=40, help='floor grid points per side')
    args = parser.parse_args(argv)
    explicit = [args.fx, args.width, args.height]
    if any(v is not None for v in explicit) and any(v is None for v in explicit):
        parser.error('an explicit camera needs all of --fx, --width and --height')
    if not 0.0 <= args.tilt < 90.0:
        parser.error(f'--tilt must be in [0, 90) degrees, got {args.tilt}')
    return args


def _camera(args: argparse.Namespace) -> CameraModel:
    if args.fx is None:
        return preset_camera(args.camera)
    if not (args.fx > 0.0 and args.width > 0 and args.height > 0):
        raise ValueError('--fx, --width and --height must be positive')
    K = [[args.fx, 0.0, (args.width - 1) / 2], [0.0, args.fx, (args.height - 1) / 2], [0.0, 0.0, 1.0]]
    return CameraModel(args.width, args.height, K)


def _lamp_positions(args: argparse.Namespace) -> np.ndarray:
    room = tuple(args.room)
    if args.lamps is None:
        return grid_positions(room, args.spacing)
    positions = []
    for text in args.lamps:
        try:
            x, y = (float(v) for v in text.split(','))
        except ValueError:
            raise ValueError(f'--lamps: expected X,Y (m), got {text!r}') from None
        if not (0.0 <= x <= room[0] and 0.0 <= y <= room[1]):
            raise ValueError(f'--lamps: {text} lies outside the {room[0]} x {room[1]} m room')
        positions.append((x, y))
    return np.array(positions)


def _setup(args: argparse.Namespace) -> tuple[Deployment, BeaconPlan, MeasurementNoise]:
    if not args.ceiling > 0.0:
        raise ValueError(f'--ceiling must be positive, got {args.ceiling}')
    lamps = tuple(ceiling_lamp(f'lamp_{k}', k, x, y, args.ceiling, args.radius)
                  for k, (x, y) in enumerate(_lamp_positions(args)))
    rotation = looking_up(*np.radians([args.tilt, args.tilt_azimuth, args.yaw]))
    deployment = Deployment(tuple(args.room), lamps, _camera(args), rotation)
    beacon = BeaconPlan(args.beacon, args.chip_rate, args.id_bits, args.row_time, args.tone_frequency)
    noise = MeasurementNoise(args.rim_sigma, args.marker_sigma, None if args.no_imu else args.imu_sigma)
    return deployment, beacon, noise


def _title(args: argparse.Namespace, deployment: Deployment, beacon: BeaconPlan) -> str:
    camera = f'fx {args.fx:.0f} px {args.width}x{args.height}' if args.fx is not None else args.camera
    view = 'looking up' if args.tilt == 0.0 else f'tilted {args.tilt:g} deg toward {args.tilt_azimuth:g} deg'
    code = (f'packet {beacon.chip_rate:g} Hz, {beacon.id_bits} bits' if beacon.mode == 'packet'
            else f'tone from {beacon.tone_frequency:g} Hz')
    imu = 'no IMU' if args.no_imu else f'IMU {args.imu_sigma:g} rad'
    return (f'{len(deployment.lamps)} lamps of radius {100 * args.radius:g} cm, {args.ceiling:g} m above the '
            f'camera ({camera}, {view})\n{code}, row time {1e6 * beacon.row_time:g} us; '
            f'rim {args.rim_sigma:g} px, marker {args.marker_sigma:g} px, {imu}')


def main(argv: list[str] | None = None) -> int:
    try:
        args = _arguments(argv)
    except SystemExit as stop:  # --help, or bad options already reported in one line
        return int(stop.code or 0)
    prog = 'python -m vlp_ros.evaluation.plan'
    start = time.perf_counter()
    try:
        deployment, beacon, noise = _setup(args)
        plan = plan_floor(deployment, beacon, noise, args.points)
    except ValueError as err:
        print(f'{prog}: error: {err}', file=sys.stderr)
        return 2
    elapsed = time.perf_counter() - start
    try:
        error_map_figure(plan, deployment, beacon, args.out, _title(args, deployment, beacon))
    except OSError as err:
        print(f'{prog}: cannot write {args.out}: {err}', file=sys.stderr)
        return 1
    print(f'{len(deployment.lamps)} lamps over {args.room[0]:g} x {args.room[1]:g} m, '
          f'{args.points} x {args.points} floor points in {elapsed:.1f} s')
    print(summary(plan, beacon))
    print(f'plan: {args.out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
