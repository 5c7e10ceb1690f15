"""Messages for what users look at: the lamp map as markers, and the debug view as an image."""
from __future__ import annotations

import array

from geometry_msgs.msg import Point
import numpy as np
from sensor_msgs.msg import Image
from std_msgs.msg import ColorRGBA, Header
from visualization_msgs.msg import Marker, MarkerArray

from vlp_ros.core.lamp_map import Lamp, LampMap

DISC_THICKNESS_M = 0.01
LAMP = ColorRGBA(r=0.85, g=0.85, b=0.85, a=0.9)
USED = ColorRGBA(r=0.2, g=0.9, b=0.2, a=1.0)
MARKER_ARROW = ColorRGBA(r=0.9, g=0.1, b=0.1, a=1.0)
LABEL = ColorRGBA(r=1.0, g=1.0, b=1.0, a=1.0)


def lamp_markers(lamps: LampMap, map_frame: str, used_ids: set[int]) -> MarkerArray:
    """
    Return the map's lamps as RViz markers, three per lamp.

    Per lamp: a disc (green when used in the latest pose), an arrow from its centre to its rim
    marker, and a label with its name and ID. Namespaces lamps, marker_direction, labels.
    """
    array = MarkerArray()
    for index, lamp in enumerate(lamps):
        header = Header(frame_id=map_frame)
        array.markers.append(_disc(header, index, lamp, lamp.id in used_ids))
        array.markers.append(_marker_arrow(header, index, lamp))
        array.markers.append(_label(header, index, lamp))
    return array


def _point(xyz: np.ndarray) -> Point:
    return Point(x=float(xyz[0]), y=float(xyz[1]), z=float(xyz[2]))


def _disc(header: Header, index: int, lamp: Lamp, used: bool) -> Marker:
    marker = Marker(header=header, ns='lamps', id=index, type=Marker.CYLINDER, action=Marker.ADD)
    marker.pose.position = _point(lamp.position)
    marker.pose.orientation.w = 1.0  # horizontal, as every lamp of the map is
    marker.scale.x = marker.scale.y = 2.0 * float(lamp.radius)
    marker.scale.z = DISC_THICKNESS_M
    marker.color = USED if used else LAMP
    return marker


def _marker_arrow(header: Header, index: int, lamp: Lamp) -> Marker:
    marker = Marker(header=header, ns='marker_direction', id=index, type=Marker.ARROW, action=Marker.ADD)
    # Just below the disc so that it shows from the floor, where the camera looks up from.
    below = np.array([0.0, 0.0, -DISC_THICKNESS_M])
    marker.points = [_point(lamp.position + below), _point(lamp.marker_position() + below)]
    marker.pose.orientation.w = 1.0
    marker.scale.x = 0.1 * float(lamp.radius)  # shaft diameter
    marker.scale.y = 0.25 * float(lamp.radius)  # head diameter
    marker.color = MARKER_ARROW
    return marker


def _label(header: Header, index: int, lamp: Lamp) -> Marker:
    marker = Marker(header=header, ns='labels', id=index, type=Marker.TEXT_VIEW_FACING, action=Marker.ADD)
    marker.pose.position = _point(lamp.position - np.array([0.0, 0.0, 2.0 * float(lamp.radius)]))
    marker.pose.orientation.w = 1.0
    marker.scale.z = max(0.05, float(lamp.radius))  # text height
    marker.text = f'{lamp.name} (ID {lamp.id})'
    marker.color = LABEL
    return marker


def bgr8_image(pixels: np.ndarray, header: Header) -> Image:
    height, width = pixels.shape[:2]
    msg = Image(header=header, height=height, width=width, encoding='bgr8', is_bigendian=0, step=3 * width)
    # An array.array('B') is taken as is; bytes would be checked value by value.
    data = array.array('B')
    data.frombytes(np.ascontiguousarray(pixels, dtype=np.uint8).tobytes())
    msg.data = data
    return msg
