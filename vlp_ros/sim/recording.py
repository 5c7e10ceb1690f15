"""Render a scenario frame by frame into a rosbag2 recording plus the locator's params file."""
from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from vlp_ros.sim.bag_writer import SimBagWriter
from vlp_ros.sim.imu import specific_force
from vlp_ros.sim.render import RenderedFrame
from vlp_ros.sim.scenarios import Scenario

import yaml

# Recording start: a plausible wall-clock stamp, since a zero stamp often means "unset" in ROS.
EPOCH_NS = 1_700_000_000 * 1_000_000_000
LOCATOR_NODE = 'vlp_locator'


def write_params(path: Path | str, scenario: Scenario, imu: bool) -> None:
    """Write a params file (``--params-file``) configuring the locator for ``scenario`` to ``path``."""
    document = {LOCATOR_NODE: {'ros__parameters': scenario.locator_parameters(imu)}}
    Path(path).write_text(yaml.safe_dump(document, sort_keys=False, default_flow_style=None))


def record(scenario: Scenario, bag_path: Path | str, storage: str, imu: bool, rng: np.random.Generator,
           progress: Callable[[int, int], None] | None = None,
           on_frame: Callable[[RenderedFrame], None] | None = None) -> int:
    """
    Render every frame of ``scenario`` into a new bag; return how many frames were written.

    ``on_frame`` sees each rendered frame with its ground truth (which lamps it shows).
    """
    times = scenario.frame_times()
    with SimBagWriter(bag_path, storage, imu, scenario.jpeg_quality) as writer:
        for index, (pose, t) in enumerate(zip(scenario.poses, times)):
            frame = scenario.render(index, rng)
            force = None
            if imu:
                force = specific_force(pose, scenario.accelerations[index], scenario.imu_noise, rng)
            writer.write_frame(frame, EPOCH_NS + int(round(t * 1e9)), force, scenario.imu_noise)
            if on_frame is not None:
                on_frame(frame)
            if progress is not None:
                progress(index + 1, len(times))
        return writer.frames
