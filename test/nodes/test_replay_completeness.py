"""
The `replay` executable delivers every recorded message of the selection, or says which it did not.

Each test subscribes to every played topic and wants, per topic, exactly the
recorded messages in timestamp order; bags whose files overlap in time and
topics with several connections are what real split recordings look like.
"""
from __future__ import annotations

from pathlib import Path

import pytest
from replay_bags import (by_topic, chatter, edit_metadata, overlapping_recording, Recorded, string_data, T0_NS,
                         write_bag, write_overlapping_split_bag)
from test_replay_node import deserialized, run_to_end, subscribe

pytestmark = pytest.mark.dds


def strings(data: list[bytes]) -> list[str]:
    from std_msgs.msg import String
    return [message.data for message in deserialized(data, String)]


def subscribe_strings(node, topics) -> dict:
    from std_msgs.msg import String
    return {topic: subscribe(node, topic, String) for topic in topics}


def arrived(received: dict) -> dict[str, list[str]]:
    return {topic: [message.data for message in messages.messages()] for topic, messages in received.items()}


def expected_strings(recorded: list[Recorded]) -> dict[str, list[str]]:
    return {topic: strings(data) for topic, data in by_topic(recorded).items()}


def recorded_messages() -> list[Recorded]:
    return [message for chunk in overlapping_recording() for message in chunk]


@pytest.mark.parametrize('storage', ['sqlite3', 'mcap'])
def test_a_split_bag_whose_files_overlap_in_time_arrives_complete_and_in_order(start_process, test_node,
                                                                               tmp_path: Path, storage: str) -> None:
    bag = write_overlapping_split_bag(tmp_path / 'bag', overlapping_recording(), storage=storage)
    expected = expected_strings(recorded_messages())
    received = subscribe_strings(test_node, expected)
    replay = start_process('replay', bag)
    assert run_to_end(test_node, replay, lambda: arrived(received) == expected) == 0
    assert arrived(received) == expected
    assert 'replay: done: published 160 messages' in replay.stderr()


def test_a_start_offset_into_an_overlapping_split_bag_plays_everything_after_it(start_process, test_node,
                                                                                tmp_path: Path) -> None:
    bag = write_overlapping_split_bag(tmp_path / 'bag', overlapping_recording())
    # 0.255 s: /a's first file starts at 0.2 s, /a and /b and /c each go on past it.
    origin_ns = T0_NS + 255_000_000
    expected = expected_strings([m for m in recorded_messages() if m.timestamp_ns >= origin_ns])
    assert {topic: len(texts) for topic, texts in expected.items()} == {'/a': 34, '/b': 14, '/c': 34}
    received = subscribe_strings(test_node, expected)
    replay = start_process('replay', bag, '--start-offset', '0.255')
    assert run_to_end(test_node, replay, lambda: arrived(received) == expected) == 0
    assert arrived(received) == expected
    assert 'replay: done: published 82 messages' in replay.stderr()


def test_topics_selects_every_connection_of_a_topic(start_process, test_node, tmp_path: Path) -> None:
    bag = write_overlapping_split_bag(tmp_path / 'bag', overlapping_recording(), storage='mcap')
    expected = expected_strings([m for m in recorded_messages() if m.topic == '/c'])
    received = subscribe_strings(test_node, ['/a', '/b', '/c'])
    replay = start_process('replay', bag, '--topics', 'c')
    assert run_to_end(test_node, replay, lambda: arrived(received)['/c'] == expected['/c']) == 0
    assert arrived(received) == {'/a': [], '/b': [], **expected}
    assert 'replay: done: published 60 messages' in replay.stderr()


def test_messages_metadata_promises_but_the_storage_lacks_end_with_one_line_and_status_1(
        start_process, test_node, tmp_path: Path) -> None:
    recorded = chatter(4, 0.05, '/a') + chatter(3, 0.05, '/b')
    bag = write_bag(tmp_path / 'bag', sorted(recorded, key=lambda m: m.timestamp_ns))

    def promise_two_more_on_b(info: dict) -> None:
        for entry in info['topics_with_message_count']:
            if entry['topic_metadata']['name'] == '/b':
                entry['message_count'] += 2

    edit_metadata(bag, promise_two_more_on_b)
    expected = expected_strings(recorded)
    received = subscribe_strings(test_node, expected)
    replay = start_process('replay', bag)
    assert run_to_end(test_node, replay, lambda: arrived(received) == expected) == 1
    assert arrived(received) == expected
    errors = [line for line in replay.stderr().splitlines() if line.startswith('replay: error:')]
    assert errors == ['replay: error: incomplete: 3 of the 5 messages that metadata.yaml promises '
                      'for the selection were played on /b 3 of 5'], replay.stderr()


def test_messages_metadata_does_not_announce_are_played_with_a_warning(start_process, test_node,
                                                                       tmp_path: Path) -> None:
    recorded = chatter(4, 0.05, '/a')
    bag = write_bag(tmp_path / 'bag', recorded)
    edit_metadata(bag, lambda info: info['topics_with_message_count'][0].update(message_count=1))
    expected = expected_strings(recorded)
    received = subscribe_strings(test_node, expected)
    replay = start_process('replay', bag)
    assert run_to_end(test_node, replay, lambda: arrived(received) == expected) == 0
    assert arrived(received) == expected
    assert '/a: the storage held 4 messages where metadata.yaml announces 1; all were played' in replay.stderr()


def test_skipped_types_are_counted_in_the_summary(start_process, test_node, tmp_path: Path) -> None:
    exotic = [Recorded('/exotic', 'foo_msgs/msg/Bar', T0_NS + k * 10**7 + 1, string_data('x')) for k in range(3)]
    recorded = chatter(2, 0.01, '/a')
    bag = write_bag(tmp_path / 'bag', sorted(recorded + exotic, key=lambda m: m.timestamp_ns))
    expected = expected_strings(recorded)
    received = subscribe_strings(test_node, expected)
    replay = start_process('replay', bag)
    assert run_to_end(test_node, replay, lambda: arrived(received) == expected) == 0
    assert 'published 2 messages' in replay.stderr()
    assert 'skipped 3 messages: /exotic 3 (foo_msgs/msg/Bar not installed)' in replay.stderr()
