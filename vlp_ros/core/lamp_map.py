"""The lamps of a building: where each one hangs and how it identifies itself."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Lamp:
    """
    A flat luminous disc facing down (-z) with a red marker just inside its rim, or a point lamp.

    A point lamp has ``radius`` 0 (a bare LED, or a lamp too small or soft for an ellipse): the
    solvers see only the centre of its light, and it shines down, so it is seen from below.

    ``marker_angle`` is measured in the map from +x toward +y; ``marker_distance``
    defaults to the radius. ``frequency`` (Hz) identifies the lamp in tone mode.
    ``position_sigma`` (m, per map axis) is how well the position is known (a surveyed map's);
    None: exactly.
    """

    name: str
    id: int  # noqa: A003 the lamp's beacon ID, a public field named as the map file's ``id`` key
    position: np.ndarray
    radius: float
    marker_angle: float = 0.0
    marker_distance: float | None = None
    frequency: float | None = None
    position_sigma: np.ndarray | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, 'position', np.asarray(self.position, dtype=float).reshape(3))
        if self.position_sigma is not None:
            object.__setattr__(self, 'position_sigma', np.asarray(self.position_sigma, dtype=float).reshape(3))
        if self.marker_distance is None:
            object.__setattr__(self, 'marker_distance', float(self.radius))

    @property
    def is_point(self) -> bool:
        return self.radius == 0.0

    def marker_position(self) -> np.ndarray:
        a = self.marker_angle
        return self.position + self.marker_distance * np.array([np.cos(a), np.sin(a), 0.0])

    def rim_points(self, count: int) -> np.ndarray:
        """``count`` points (N, 3) evenly spaced on the disc's edge, in the map frame."""
        phi = np.linspace(0.0, 2.0 * np.pi, count, endpoint=False)
        return self.position + self.radius * np.stack(
            [np.cos(phi), np.sin(phi), np.zeros_like(phi)], axis=1)


class LampMap:
    """Lamps indexed by beacon ID; construction checks that IDs and names are unique."""

    def __init__(self, lamps: list[Lamp]) -> None:
        self._by_id: dict[int, Lamp] = {}
        names: set[str] = set()
        for lamp in lamps:
            if lamp.id in self._by_id:
                raise ValueError(f'lamps {self._by_id[lamp.id].name!r} and {lamp.name!r} share id {lamp.id}')
            if lamp.name in names:
                raise ValueError(f'lamp name {lamp.name!r} appears twice')
            if not lamp.radius >= 0.0:
                raise ValueError(f'lamp {lamp.name!r} has negative radius {lamp.radius}')
            self._by_id[lamp.id] = lamp
            names.add(lamp.name)

    def __len__(self) -> int:
        return len(self._by_id)

    def __iter__(self):
        return iter(self._by_id.values())

    def __contains__(self, lamp_id: int) -> bool:
        return lamp_id in self._by_id

    def get(self, lamp_id: int) -> Lamp | None:
        return self._by_id.get(lamp_id)

    @property
    def ids(self) -> list[int]:
        return sorted(self._by_id)

    def frequencies(self) -> dict[int, float]:
        """Tone-mode frequency (Hz) of every lamp that has one, by ID."""
        return {i: l.frequency for i, l in self._by_id.items() if l.frequency is not None}
