"""The beacon decoder's entry points, one lamp in one frame (docs/beacon.md).

``row_profile`` turns a detected lamp into brightness per row; ``decode_packet``
and ``decode_tone`` turn that into a ``BeaconReading``; ``EvidenceTracker``
(vlp_ros.beacon.evidence) adds readings up across frames.
"""
from vlp_ros.beacon.packet import decode_packet
from vlp_ros.beacon.profile import RowProfile, row_profile
from vlp_ros.beacon.reading import UNMAPPED, BeaconReading
from vlp_ros.beacon.tone import decode_tone

__all__ = ['BeaconReading', 'RowProfile', 'UNMAPPED', 'decode_packet', 'decode_tone', 'row_profile']
