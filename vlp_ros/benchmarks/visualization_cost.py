"""
What vlp/debug_image and vlp/lamps cost per frame.

    python -m vlp_ros.benchmarks.visualization_cost [--poses N] [--repeats N]

On the frames of the pipeline speed benchmark (``pipeline_speed.cases``), with a
subscriber present on both topics (a second node in this process: the messages
still go through DDS), times in turn: ``Pipeline.process``; the debug image as the
locator makes it (``debug_view`` + the sensor_msgs/Image + publish); and the lamp
map as MarkerArray (built + published; the locator sends it only when the lamps
used in the latest pose change). Medians in ms and as a ratio to ``process``. With
no subscriber the locator draws nothing: the debug image then costs one
subscriber count.
"""
from __future__ import annotations

import argparse
import itertools

import cv2
import numpy as np
import rclpy
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Image
from std_msgs.msg import Header
from visualization_msgs.msg import MarkerArray

from vlp_ros.benchmarks.pipeline_speed import BURST, Case, cases, interleaved_times
from vlp_ros.evaluation.metrics import format_table
from vlp_ros.nodes.visualization import bgr8_image, lamp_markers
from vlp_ros.pipeline.config import settings_from_tree
from vlp_ros.pipeline.debug_view import debug_view
from vlp_ros.pipeline.frame import Pipeline
from vlp_ros.sim.render import render_frame

RUNS = ('process', 'debug image', 'lamps')
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)


def case_times(case: Case, publishers, repeats: int, rng: np.random.Generator) -> dict[str, list[float]]:
    settings = settings_from_tree(case.scenario.locator_parameters(imu=True))
    scenario = case.scenario
    image_pub, lamps_pub = publishers
    times: dict[str, list[float]] = {name: [] for name in RUNS}
    for index in case.indices:
        images = [render_frame(scenario.camera, scenario.poses[index], scenario.lamps, scenario.sensor,
                               k / scenario.frame_rate, rng).image for k in range(BURST)]
        pipeline, stamps, results = Pipeline(settings), itertools.count(), []

        def process(r: int) -> None:
            results.append(pipeline.process(images[r % BURST], scenario.camera, next(stamps) / scenario.frame_rate))

        def publish_debug_image(r: int) -> None:
            image_pub.publish(bgr8_image(debug_view(images[r % BURST], results[-1]), Header(frame_id='camera')))

        def publish_lamps(r: int) -> None:
            used = {seen.lamp_id for seen in results[-1].seen if seen.lamp_id is not None}
            lamps_pub.publish(lamp_markers(settings.lamps, settings.map_frame, used))

        runs = {'process': process, 'debug image': publish_debug_image, 'lamps': publish_lamps}
        for name, values in interleaved_times(runs, repeats, warmup=BURST).items():
            times[name] += values
    return times


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog='python -m vlp_ros.benchmarks.visualization_cost',
                                     description=__doc__.strip().splitlines()[0])
    parser.add_argument('--poses', type=int, default=3, help='camera poses per case')
    parser.add_argument('--repeats', type=int, default=20, help='timed repetitions per camera pose')
    parser.add_argument('--seed', type=int, default=3)
    args = parser.parse_args(argv)
    cv2.setNumThreads(1)
    rclpy.init()
    try:
        node, viewer = rclpy.create_node('vlp_visualization_cost'), rclpy.create_node('vlp_visualization_viewer')
        publishers = (node.create_publisher(Image, 'vlp/debug_image', 1),
                      node.create_publisher(MarkerArray, 'vlp/lamps', LATCHED))
        viewer.create_subscription(Image, 'vlp/debug_image', lambda msg: None, 1)
        viewer.create_subscription(MarkerArray, 'vlp/lamps', lambda msg: None, LATCHED)
        while publishers[0].get_subscription_count() == 0 or publishers[1].get_subscription_count() == 0:
            rclpy.spin_once(viewer, timeout_sec=0.05)
        rng = np.random.default_rng(args.seed)
        rows = []
        for case in cases(args.poses, args.seed):
            median = {name: float(np.median(values))
                      for name, values in case_times(case, publishers, args.repeats, rng).items()}
            camera = case.scenario.camera
            rows.append([case.name, f'{camera.width}x{camera.height}',
                         *(f'{1e3 * median[name]:.2f}' for name in RUNS),
                         f'{median["debug image"] / median["process"]:.2f}',
                         f'{median["lamps"] / median["process"]:.3f}'])
    finally:
        rclpy.try_shutdown()
    print(f'Visualization cost per frame with a subscriber, median ms (cv2 threads 1; '
          f'{args.poses} camera poses x {args.repeats} repeats per case)')
    print(format_table(rows, ('case', 'size', 'process', 'debug image', 'lamps', 'debug/process', 'lamps/process')))


if __name__ == '__main__':
    main()
