"""
Detection accuracy and speed: python -m vlp_ros.benchmarks.detection [--frames N] [--repeats N].

Renders the paper scenario's photos (one lamp, hand-held postures) at 1080p and
4K, in colour and saturated, and in the simulator's looks of real lamps and cameras
(vlp_ros.sim.looks: blur 2 px, glare halo, diffuser falloff, saturation with blooming,
JPEG q90, and all of them with clutter lamps), and prints per case: how often the
lamp and its marker were found, the bias and standard deviation (px) of the ellipse
centre, of the semi-axes and of the marker centroid against the simulator's ground
truth, the RMS of marker error over reported marker_sigma, and the median detection
time with its ratio to one plain copy of the same frame timed in the same run.
"""
from __future__ import annotations

import argparse
from dataclasses import dataclass, field, replace

import numpy as np

from vlp_ros.benchmarks.timing import median_seconds
from vlp_ros.detection import detect_lamps
from vlp_ros.sim.looks import apply_look, LOOKS, transported
from vlp_ros.sim.scenarios import paper_scenario


LOOKS_SHOWN = ('blur', 'glare', 'falloff', 'saturated', 'jpeg', 'realistic', 'realistic_jpeg')


@dataclass
class CaseResult:
    frames: int = 0
    found: int = 0
    centre_errors: list[np.ndarray] = field(default_factory=list)
    axis_errors: list[np.ndarray] = field(default_factory=list)
    marker_errors: list[np.ndarray] = field(default_factory=list)
    marker_z: list[np.ndarray] = field(default_factory=list)
    detect_seconds: list[float] = field(default_factory=list)
    copy_seconds: list[float] = field(default_factory=list)


def run_case(camera_kind: str, peak_dn: float, look: str, frames: int, repeats: int, seed: int) -> CaseResult:
    scenario = paper_scenario(camera_kind, points=max(2, int(np.ceil(np.sqrt(frames)))), postures=1, seed=seed)
    scenario = replace(scenario, lamps=[replace(s, peak_dn=peak_dn) for s in scenario.lamps])
    scenario = apply_look(scenario, LOOKS[look], seed)
    rng = np.random.default_rng(seed)
    result = CaseResult()
    for k in range(min(frames, len(scenario.poses))):
        frame = scenario.render(k, rng)
        image = transported(scenario, frame.image)
        truth = frame.lamps[0]
        result.frames += 1
        observations = detect_lamps(image)
        result.detect_seconds.append(median_seconds(lambda: detect_lamps(image), repeats))
        result.copy_seconds.append(median_seconds(image.copy, repeats))
        # Clutter lamps are observed too: the mapped lamp is the one at its true centre.
        matches = [o for o in observations if np.linalg.norm(o.center - truth.ellipse[:2]) < 2.0]
        if len(matches) != 1 or not matches[0].rim_usable:
            continue
        lamp = matches[0]
        result.found += 1
        result.centre_errors.append(lamp.center - truth.ellipse[:2])
        result.axis_errors.append(lamp.ellipse[2:4] - truth.ellipse[2:4])
        if lamp.marker is not None:
            error = lamp.marker - truth.marker_pixel
            result.marker_errors.append(error)
            result.marker_z.append(error / lamp.marker_sigma)
    return result


def _stats(values: list[np.ndarray]) -> str:
    if not values:
        return f'{"-":>27}'
    v = np.asarray(values)
    bias, std = v.mean(axis=0), v.std(axis=0)
    return f'{bias[0]:+6.3f} {bias[1]:+6.3f} {std[0]:6.3f} {std[1]:6.3f}'


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog='python -m vlp_ros.benchmarks.detection',
                                     description=__doc__.strip().splitlines()[0])
    parser.add_argument('--frames', type=int, default=16, help='photos per case')
    parser.add_argument('--repeats', type=int, default=5, help='timed detections per photo')
    parser.add_argument('--seed', type=int, default=1)
    parser.add_argument('--looks', nargs='*', default=list(LOOKS_SHOWN), choices=sorted(LOOKS),
                        help='looks of vlp_ros.sim.looks measured after the clean cases')
    args = parser.parse_args(argv)
    cases = [('1080p', 210.0, 'clean'), ('4k', 210.0, 'clean'), ('1080p', 500.0, 'clean'), ('4k', 500.0, 'clean')]
    cases += [(kind, 210.0, look) for look in args.looks for kind in ('1080p', '4k')]
    print('bias x, bias y, std x, std y in px; axes: (a, b); z: RMS of marker error / marker_sigma per axis')
    print(f'{"case":<22} {"found":>6} {"marker":>6}  {"centre bias / std":>27}  {"axes bias / std":>27}  '
          f'{"marker bias / std":>27}  {"z x":>5} {"z y":>5}  {"detect ms":>9} {"copy ms":>7} {"ratio":>6}')
    for kind, peak, look in cases:
        r = run_case(kind, peak, look, args.frames, args.repeats, args.seed)
        z = np.sqrt(np.mean(np.square(r.marker_z), axis=0)) if r.marker_z else np.full(2, np.nan)
        detect, copy = float(np.median(r.detect_seconds)), float(np.median(r.copy_seconds))
        name = f'{kind} {"sat" if peak > 255 else "ok"}' if look == 'clean' else f'{kind} {look}'
        print(f'{name:<22} {r.found:>3}/{r.frames:<2} {len(r.marker_errors):>6}  {_stats(r.centre_errors)}  '
              f'{_stats(r.axis_errors)}  {_stats(r.marker_errors)}  {z[0]:5.2f} {z[1]:5.2f}  '
              f'{1e3 * detect:9.2f} {1e3 * copy:7.2f} {detect / copy:6.1f}')


if __name__ == '__main__':
    main()
