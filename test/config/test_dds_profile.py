"""The loopback DDS profile's shared memory: room for one raw 4K frame's fragments, and no more than it needs."""
from __future__ import annotations

import xml.etree.ElementTree as ElementTree

from conftest import LOOPBACK_PROFILE

NAMESPACE = {'dds': 'http://www.eprosima.com'}
RAW_4K_BGR8_BYTES = 3840 * 2160 * 3


def shared_memory_transport() -> ElementTree.Element:
    """Return the profile's SHM transport descriptor."""
    descriptors = ElementTree.parse(LOOPBACK_PROFILE).getroot().iterfind('.//dds:transport_descriptor', NAMESPACE)
    return next(d for d in descriptors if d.findtext('dds:type', namespaces=NAMESPACE) == 'SHM')


def test_the_segment_holds_one_raw_4k_frame_and_is_resident_for_no_second() -> None:
    transport = shared_memory_transport()
    segment = int(transport.findtext('dds:segment_size', namespaces=NAMESPACE))
    largest_message = int(transport.findtext('dds:maxMessageSize', namespaces=NAMESPACE))
    # A best-effort writer puts a frame's ~400 fragments in its segment at once.
    assert segment >= RAW_4K_BGR8_BYTES * 1.1
    # Every process under the profile keeps its own segment resident, whatever it sends.
    assert segment < 2 * RAW_4K_BGR8_BYTES
    assert largest_message <= segment
