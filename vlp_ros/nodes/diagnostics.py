"""The locator's state as a diagnostic_msgs/DiagnosticArray."""
from __future__ import annotations

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from vlp_ros.pipeline.frame_stats import FrameStats

# Pipeline outcomes (solver Reason values) that mean candidates could not be told apart.
AMBIGUITY_OUTCOMES = ('ambiguous', 'conflicting_hints', 'no_candidate_agrees', 'inconsistent_lamps')


def diagnostic_array(stats: FrameStats, has_camera_info: bool, image_topic: str,
                     track_restarts: int = 0, kernels_ready: bool = True) -> DiagnosticArray:
    """
    Return the locator's state as one status.

    ``track_restarts``: poses published against continuity (``Pipeline.track_restarts``); ``kernels_ready``:
    whether the compiled kernels are ready (numba may still be compiling them, frames dropped meanwhile).
    """
    input_rate, processed_rate = stats.rates()
    latency_median, latency_max = stats.latency_ms()
    values = {
        'image topic': image_topic,
        'input rate (Hz)': f'{input_rate:.1f}',
        'processed rate (Hz)': f'{processed_rate:.1f}',
        'frames received': stats.received,
        'frames processed': stats.processed,
        'frames superseded by newer ones': stats.superseded,
        'poses published': stats.poses,
        'latency median (ms)': f'{latency_median:.1f}',
        'latency max (ms)': f'{latency_max:.1f}',
        'decoded ids': ' '.join(f'{i}:{n}' for i, n in sorted(stats.decoded_ids.items())) or 'none',
        'unknown ids': stats.unknown_ids,
        'ambiguity rejections': sum(n for r, n in stats.no_pose.items() if r in AMBIGUITY_OUTCOMES),
        'track restarts': track_restarts,
        'kernels ready': kernels_ready,
    }
    values.update({f'no pose: {reason}': n for reason, n in sorted(stats.no_pose.items())})
    values.update({f'dropped: {reason}': n for reason, n in sorted(stats.dropped.items())})
    status = DiagnosticStatus(name='vlp_ros: locator', hardware_id=image_topic)
    status.level, status.message = _level_and_message(stats, has_camera_info, input_rate, kernels_ready)
    status.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
    return DiagnosticArray(status=[status])


def _level_and_message(stats: FrameStats, has_camera_info: bool, input_rate: float,
                       kernels_ready: bool) -> tuple[bytes, str]:
    if not kernels_ready:
        return DiagnosticStatus.WARN, 'compiling the numba kernels: frames are dropped until they are ready'
    if stats.received and not has_camera_info:
        return DiagnosticStatus.WARN, 'waiting for a valid camera_info'
    if stats.received == 0:
        return DiagnosticStatus.WARN, 'no images received'
    if input_rate == 0.0:
        return DiagnosticStatus.WARN, 'images stopped arriving'
    if sum(stats.dropped.values()) and stats.processed == 0:
        return DiagnosticStatus.ERROR, 'every frame is dropped'
    return DiagnosticStatus.OK, f'{stats.poses} poses from {stats.processed} frames'
