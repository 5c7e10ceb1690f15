"""
Command line: python -m vlp_ros.sim --scenario paper|robot|drive|tone|bare_leds --out DIR [--look NAME] [options].

Writes DIR/<scenario> (a rosbag2 recording) and DIR/params.yaml (the locator's
parameters for it), shows a progress bar on a terminal and prints a one-line summary.
"""
from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path
import sys
import time

import numpy as np
from tqdm import tqdm

from vlp_ros.sim.bag_writer import STORAGES
from vlp_ros.sim.looks import apply_look, Look, LOOKS
from vlp_ros.sim.point_lamps import BARE_LED_CAMERAS, bare_led_scenario, PointLampLook
from vlp_ros.sim.recording import record, write_params
from vlp_ros.sim.scenarios import (as_stills, PAPER_CAMERAS, paper_scenario, robot_drive_scenario, robot_scenario,
                                   robot_tone_scenario, Scenario, with_rim_markers)
from vlp_ros.sim.sensor import BAYER_PATTERNS, encoding

PAPER_ONLY = ('points', 'postures', 'still_interval')
BARE_LEDS_ONLY = ('photos', 'led_core_radius', 'led_glow')
DEFAULT_DEPTH = 0.75
# Options that change one effect of the chosen --look: (option, Look field, type, help).
LOOK_OPTIONS = (
    ('--blur', 'blur_sigma', float, 'blur sigma (px) of the recorded image, stripes included (up to 2 px is '
                                    'ordinary; realistic 1.6)'),
    ('--glare', 'glare', float, "lens-glare halo peak as a fraction of the disc's level (realistic 0.2)"),
    ('--glare-width', 'glare_width', float, "halo sigma as a fraction of the lamp's image diameter (0.35)"),
    ('--falloff', 'falloff', float, 'diffuser emission 1 - a (r/R)^2: a (realistic 0.3)'),
    ('--brightness', 'brightness', float, "scale of the lamps' light; above 1 saturates them"),
    ('--bloom', 'bloom', float, 'fraction of the charge beyond the full well that spills to neighbours'),
    ('--clutter', 'clutter', int, 'unmodulated lamps, not in the map, among the mapped ones (realistic 2)'),
    ('--jpeg', 'jpeg_quality', int, 'send the images as JPEG of this quality on /image_raw/compressed'),
    ('--row-time-error', 'row_time_error', float,
     'true row time = (1 + this) x the nominal one written to params.yaml (e.g. 0.02)'),
)


class UsageError(Exception):
    """A bad option or an output that would be overwritten: reported in one line, exit status 2."""


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog='python -m vlp_ros.sim',
        description='Simulate a rolling-shutter VLP recording: DIR/<scenario> (rosbag2) and DIR/params.yaml.')
    parser.add_argument('--scenario', required=True, choices=('paper', 'robot', 'drive', 'tone', 'bare_leds'),
                        help='paper: hand-held stills of one lamp; robot: under a row of lamps; drive: a robot '
                             'driving and turning under packet lamps 2.4 m apart; tone: robot stills under 12 tone '
                             'lamps; bare_leds: hand-held photos of the five-LED rig')
    parser.add_argument('--out', required=True, type=Path, help='output directory')
    parser.add_argument('--storage', default='sqlite3', choices=tuple(STORAGES))
    parser.add_argument('--frames', type=int, help='write only the first N frames')
    parser.add_argument('--points', type=int, help='paper: grid points per side (default 7)')
    parser.add_argument('--postures', type=int, help='paper: photos per grid point (default 3)')
    parser.add_argument('--camera', choices=tuple(dict.fromkeys((*PAPER_CAMERAS, *BARE_LED_CAMERAS))),
                        help='paper: output resolution (4k, 1080p; default 4k); bare_leds: the 7712x4352 sensor '
                             'binned (full, 4k = 3856x2176, 1080p = 1928x1088; default 4k)')
    parser.add_argument('--photos', type=int, help='bare_leds: hand-held photos of the five-LED rig (default 12)')
    parser.add_argument('--led-core-radius', type=float,
                        help="bare_leds: radius (m) of each LED's bright core (default 0.01: 46 px wide at 2.46 m)")
    parser.add_argument('--led-glow', type=float, help="bare_leds: the glow's level next to the core (default 0.4)")
    parser.add_argument('--height', type=float, help='lamp height above the camera in m (paper 2.0, robot 2.15)')
    parser.add_argument('--depth', type=float, help="beacon modulation depth (0..1], default 0.75 or the look's "
                                                    '(realistic 0.6)')
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--bayer', choices=BAYER_PATTERNS, help='record a raw Bayer mosaic instead of bgr8')
    parser.add_argument('--imu', action='store_true', help='record /imu and enable it in params.yaml')
    parser.add_argument('--still-interval', type=float,
                        help='paper: stamp the photos this many s apart with continuity on (e.g. 0.1 or 2)')
    parser.add_argument('--marker-distance', type=float,
                        help='marker centre as a fraction of the lamp radius, 0.5-1 (given alone or with '
                             "--marker-radius: the paper's marginal point, 0.9 and 0.1, for the other)")
    parser.add_argument('--marker-radius', type=float, help='marker radius as a fraction of the lamp radius')
    looks = parser.add_argument_group('looks', 'how real lamps and cameras look (docs/simulator.md)')
    looks.add_argument('--look', default='clean', choices=tuple(LOOKS), help='a named set of effects (default clean)')
    for option, _, kind, text in LOOK_OPTIONS:
        looks.add_argument(option, type=kind, help=f'{text}; overrides --look')
    return parser.parse_args(argv)


def build_scenario(args: argparse.Namespace) -> Scenario:
    if args.depth is not None and not 0.0 < args.depth <= 1.0:
        raise UsageError(f'--depth must be in (0, 1], got {args.depth}')
    if args.frames is not None and args.frames < 1:
        raise UsageError(f'--frames must be at least 1, got {args.frames}')
    if args.height is not None and not args.height > 0.0:
        raise UsageError(f'--height must be positive, got {args.height}')
    common = {'seed': args.seed, 'depth': DEFAULT_DEPTH if args.depth is None else args.depth, 'bayer': args.bayer}
    if args.height is not None:
        common['height'] = args.height
    try:
        if args.scenario == 'paper':
            for name in ('points', 'postures'):
                if getattr(args, name) is not None and getattr(args, name) < 1:
                    raise UsageError(f'--{name} must be at least 1, got {getattr(args, name)}')
            _reject_options(args, BARE_LEDS_ONLY, 'bare_leds')
            scenario = paper_scenario(camera_kind=args.camera or '4k', points=args.points or 7,
                                      postures=args.postures or 3, **common)
            if args.still_interval is not None:
                scenario = as_stills(scenario, args.still_interval)
        elif args.scenario == 'bare_leds':
            _reject_options(args, PAPER_ONLY, 'paper')
            return bare_leds_scenario(args, common)
        else:
            _reject_options(args, ('camera',), 'paper or bare_leds')
            _reject_options(args, PAPER_ONLY, 'paper')
            _reject_options(args, BARE_LEDS_ONLY, 'bare_leds')
            makers = {'robot': robot_scenario, 'drive': robot_drive_scenario, 'tone': robot_tone_scenario}
            scenario = makers[args.scenario](**common)
        marker = {name: getattr(args, f'marker_{name}') for name in ('distance', 'radius')
                  if getattr(args, f'marker_{name}') is not None}
        if marker:
            scenario = with_rim_markers(scenario, **marker)
        scenario = apply_look(scenario, chosen_look(args), args.seed)
    except ValueError as error:
        raise UsageError(str(error)) from error
    return scenario.truncated(args.frames) if args.frames is not None else scenario


def bare_leds_scenario(args: argparse.Namespace, common: dict) -> Scenario:
    """
    Return the five-LED rig's photos.

    Of the looks only the camera's JPEG and row-time error apply to its bare LEDs (their optics are the
    bare-LED look's).
    """
    if args.photos is not None and args.photos < 1:
        raise UsageError(f'--photos must be at least 1, got {args.photos}')
    if args.led_core_radius is not None and not args.led_core_radius > 0.0:
        raise UsageError(f'--led-core-radius must be positive, got {args.led_core_radius}')
    if args.led_glow is not None and not 0.0 <= args.led_glow < 1.0:
        raise UsageError(f'--led-glow must be in [0, 1), got {args.led_glow}')
    given = {'core_radius': args.led_core_radius, 'glow_level': args.led_glow}
    look = PointLampLook(**{name: value for name, value in given.items() if value is not None})
    camera = chosen_look(args)
    scenario = bare_led_scenario(camera_kind=args.camera or '4k', photos=args.photos or 12, look=look,
                                 row_time_error=camera.row_time_error, jpeg_quality=camera.jpeg_quality, **common)
    return scenario.truncated(args.frames) if args.frames is not None else scenario


def _reject_options(args: argparse.Namespace, names: tuple[str, ...], scenario: str) -> None:
    given = [f'--{name.replace("_", "-")}' for name in names if getattr(args, name) is not None]
    if given:
        raise UsageError(f'{", ".join(given)}: only valid with --scenario {scenario}')


def chosen_look(args: argparse.Namespace) -> Look:
    """Return the --look with every effect option given on the command line put in (--depth too)."""
    changes = {field: getattr(args, option[2:].replace('-', '_')) for option, field, _, _ in LOOK_OPTIONS
               if getattr(args, option[2:].replace('-', '_')) is not None}
    if args.depth is not None:
        changes['depth'] = args.depth
    return replace(LOOKS[args.look], **changes)


def beacon_summary(scenario: Scenario) -> str:
    beacon = scenario.locator_parameters(False)['beacon']
    if beacon['mode'] == 'tone':
        return 'tone lamps'
    return f'chip rate {beacon["chip_rate"]:.0f} Hz, {beacon["id_bits"]} id bits'


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        scenario = build_scenario(args)
        bag_path, params_path = args.out / scenario.name, args.out / 'params.yaml'
        for path in (bag_path, params_path):
            if path.exists():
                raise UsageError(f'{path} exists already; remove it or choose another --out')
        try:
            args.out.mkdir(parents=True, exist_ok=True)
        except OSError as error:
            raise UsageError(f'cannot create {args.out}: {error.strerror}') from error
    except UsageError as error:
        print(f'python -m vlp_ros.sim: error: {error}', file=sys.stderr)
        return 2
    started = time.perf_counter()
    with tqdm(desc='frames', total=len(scenario.poses), unit='frame', disable=None) as bar:
        frames = record(scenario, bag_path, args.storage, args.imu, np.random.default_rng([args.seed, 1]),
                        lambda done, total: bar.update(done - bar.n))
    write_params(params_path, scenario, args.imu)
    camera = scenario.camera
    print(f'wrote {bag_path} ({args.storage}): {frames} frames {camera.width}x{camera.height} '
          f'{encoding(scenario.sensor.bayer)}, {len(scenario.lamps)} lamps, {beacon_summary(scenario)}'
          f'{", imu" if args.imu else ""}, look {args.look}; params {params_path}; '
          f'{time.perf_counter() - started:.1f} s')
    return 0


if __name__ == '__main__':
    sys.exit(main())
