"""
The lamp map a survey starts from and the one it writes: a locator params file with some positions missing.

Lamps with a ``position`` are anchors (their ``marker_angle`` too, when given); the others are
surveyed. The surveyed file is the same document with every determined lamp's ``position``,
``marker_angle`` and ``position_sigma`` filled in, so the locator loads it as it is.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from vlp_ros.core.lamp_map import Lamp
from vlp_ros.pipeline.config import ConfigError, LocatorSettings, parameters_tree, settings_from_tree

import yaml

NODE = 'vlp_locator'
MIN_ANCHORS = 2
# Decimals written: 0.01 mm, 1 microradian and sigmas to 0.1 micrometre, below what any survey achieves.
POSITION_DECIMALS = 5
ANGLE_DECIMALS = 6
SIGMA_DECIMALS = 7


@dataclass(frozen=True)
class Anchor:
    """A lamp whose map position is given; ``marker_angle`` None when the file leaves it to the survey."""

    position: np.ndarray
    marker_angle: float | None


@dataclass(frozen=True)
class SurveyedLamp:
    """A lamp's estimated map position (m), marker angle (rad), and their uncertainty."""

    position: np.ndarray
    marker_angle: float
    position_covariance: np.ndarray
    marker_angle_sigma: float

    @property
    def position_sigma(self) -> np.ndarray:
        return np.sqrt(np.diag(self.position_covariance))


@dataclass(frozen=True)
class PartialMap:
    """
    A params file to survey.

    ``settings`` are the locator's, with surveyed lamps at the map origin (their positions are not used
    to identify lamps); ``anchors`` by lamp name; ``surveyed`` the names of the lamps without a position.
    """

    document: dict[str, Any]
    settings: LocatorSettings
    anchors: dict[str, Anchor]
    surveyed: list[str]

    @property
    def lamps(self) -> list[Lamp]:
        return list(self.settings.lamps)


def load_partial_map(path: Path | str) -> PartialMap:
    """Read and validate a partial params file; ConfigError names the first bad parameter."""
    try:
        document = yaml.safe_load(Path(path).read_text()) or {}
    except yaml.YAMLError as err:
        raise ConfigError('params file', f'{path} is not YAML: {str(err).splitlines()[0]}') from err
    tree = copy.deepcopy(parameters_tree(document, NODE, path))
    leds = tree.get('leds') or {}
    names = leds.get('names') or []
    anchors, surveyed = {}, []
    for name in names:
        entry = leds.get(name)
        if not isinstance(entry, dict):
            raise ConfigError(f'leds.{name}', 'missing: every lamp in leds.names needs id, radius and marker_distance')
        if entry.get('position') is None:
            surveyed.append(name)
            entry['position'] = [0.0, 0.0, 0.0]
        else:
            anchors[name] = entry.get('marker_angle') is not None
    settings = settings_from_tree(tree)
    by_name = {lamp.name: lamp for lamp in settings.lamps}
    if len(anchors) < MIN_ANCHORS:
        raise ConfigError('leds', f'{len(anchors)} lamp(s) with a position: a survey needs at least {MIN_ANCHORS} '
                                  'anchors (lamps with a measured position)')
    return PartialMap(document, settings,
                      {name: Anchor(by_name[name].position, by_name[name].marker_angle if given else None)
                       for name, given in anchors.items()},
                      surveyed)


def surveyed_document(partial: PartialMap, lamps: dict[str, SurveyedLamp]) -> dict[str, Any]:
    """
    Return the partial file's document with the ``lamps`` estimated filled in.

    Anchors keep their position, with a ``position_sigma`` of zeros unless they have one: the survey held them
    exact, so every lamp of the file says how well it is known.
    """
    document = copy.deepcopy(partial.document)
    leds = parameters_tree(document, NODE, 'the partial map')['leds']
    for name in partial.anchors:
        leds[name].setdefault('position_sigma', [0.0, 0.0, 0.0])
    for name, lamp in lamps.items():
        entry = leds[name]
        if name not in partial.anchors:
            entry['position'] = [round(float(v), POSITION_DECIMALS) for v in lamp.position]
            entry['position_sigma'] = [round(float(v), SIGMA_DECIMALS) for v in lamp.position_sigma]
        entry['marker_angle'] = round(float(lamp.marker_angle), ANGLE_DECIMALS)
    return document


def write_surveyed(partial: PartialMap, lamps: dict[str, SurveyedLamp], path: Path | str) -> None:
    """Write the surveyed params file (see ``surveyed_document``)."""
    Path(path).write_text(yaml.safe_dump(surveyed_document(partial, lamps), sort_keys=False))
