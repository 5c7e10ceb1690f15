"""Bag reading and playback planning for the replay, without ROS: formats, versions, errors, schedule."""
from __future__ import annotations

import os
from pathlib import Path
import struct

import pytest
from replay_bags import (chatter, copy_bag, edit_metadata, IMAGE, image_data, offer, overlapping_recording, Recorded,
                         set_metadata_version, SHARED_BAGS, sqlite3_topic_data, storage_file, STRING, T0_NS, write_bag,
                         write_overlapping_split_bag, write_split_bag)
from rosbags.interfaces import QosDurability, QosReliability

from vlp_ros.bags.playback_plan import (parse_remaps, playback_origin, PlaybackOptions, PlaybackTally, seconds_played,
                                        select_topics, Timeline)
from vlp_ros.bags.reader import adapt_offers, Bag, BagError, BagMessage, header_stamp, OfferedQos

import yaml

TALKER_DB = SHARED_BAGS / 'talker_sqlite3' / 'talker.db3'


def played(path: Path, topics: list[str] | None = None) -> list[Recorded]:
    with Bag(path) as bag:
        return [Recorded(m.topic, m.msgtype, m.timestamp_ns, m.data) for m in bag.messages(topics or list(bag.topics))]


@pytest.mark.parametrize('name', ['talker_sqlite3', 'talker_mcap'])
def test_real_ros2_bag_recordings_yield_their_recorded_bytes(name: str) -> None:
    with Bag(SHARED_BAGS / name) as bag:
        assert {t.name: (t.msgtype, t.message_count) for t in bag.topics.values()} == {
            '/topic': (STRING, 10), '/rosout': ('rcl_interfaces/msg/Log', 10),
            '/parameter_events': ('rcl_interfaces/msg/ParameterEvent', 0)}
        assert bag.topics['/rosout'].qos == OfferedQos('RELIABLE', 'TRANSIENT_LOCAL')
        messages = list(bag.messages(['/topic', '/rosout']))
    assert [m.data for m in messages if m.topic == '/topic'] == sqlite3_topic_data(TALKER_DB, '/topic')
    assert len(messages) == 20
    stamps = [m.timestamp_ns for m in messages]
    assert stamps == sorted(stamps)


@pytest.mark.parametrize('version', [4, 5, 6, 7, 8, 9])
def test_metadata_versions_4_to_9_are_played(tmp_path: Path, version: int) -> None:
    messages = chatter(3, 0.1)
    bag = write_bag(tmp_path / 'bag', messages, version=9 if version == 9 else 8)
    if version < 8:  # rosbags writes 8 and 9 only; older ones differ in fields the reader does not need
        set_metadata_version(bag, version)
    assert played(bag) == messages


def test_a_newer_metadata_version_is_refused_clearly(tmp_path: Path) -> None:
    bag = set_metadata_version(write_bag(tmp_path / 'bag', chatter(2, 0.1)), 10)
    with pytest.raises(BagError, match='version 10 not supported'):
        Bag(bag)


@pytest.mark.parametrize('storage', ['sqlite3', 'mcap'])
def test_a_bag_split_over_several_files_plays_all_files_in_order(tmp_path: Path, storage: str) -> None:
    messages = chatter(9, 0.1)
    bag = write_split_bag(tmp_path / 'split', messages, parts=3, storage=storage)
    assert len(list(bag.glob('split_*'))) == 3
    assert played(bag) == messages


@pytest.mark.parametrize('storage, compression', [('sqlite3', 'file'), ('sqlite3', 'message'),
                                                  ('mcap', 'file'), ('mcap', 'message'), ('mcap', 'storage')])
def test_zstd_compressed_bags_play_their_original_bytes(tmp_path: Path, storage: str, compression: str) -> None:
    messages = chatter(4, 0.1)
    bag = write_bag(tmp_path / 'bag', messages, storage=storage, compression=compression)
    assert played(bag) == messages


def test_topic_subset_and_start_time_filter_messages(tmp_path: Path) -> None:
    images = [Recorded('/image', IMAGE, T0_NS + k * 10**8 + 1, image_data(T0_NS + k)) for k in range(4)]
    messages = sorted(chatter(4, 0.1) + images, key=lambda m: m.timestamp_ns)
    bag = write_bag(tmp_path / 'bag', messages)
    assert played(bag, ['/image']) == images
    tally = PlaybackTally({'/chatter': 4, '/image': 4})
    with Bag(bag) as opened:
        from_origin = list(tally.from_origin(opened.messages(tally.promised), T0_NS + 2 * 10**8))
    assert [(m.topic, m.timestamp_ns, m.data) for m in from_origin] == [
        (m.topic, m.timestamp_ns, m.data) for m in messages[4:]]
    assert tally.before_start == {'/chatter': 2, '/image': 2} and tally.read == {'/chatter': 2, '/image': 2}


@pytest.mark.parametrize('storage', ['sqlite3', 'mcap'])
def test_files_overlapping_in_time_yield_every_message_in_timestamp_order(tmp_path: Path, storage: str) -> None:
    files = overlapping_recording()
    bag = write_overlapping_split_bag(tmp_path / 'bag', files, storage=storage)
    recorded = [message for chunk in files for message in chunk]
    with Bag(bag) as opened:
        # The first file starts 0.2 s after the earliest message, which metadata.yaml's starting_time misses.
        assert opened.start_ns == T0_NS
        assert {t.name: (t.message_count, t.stored_count) for t in opened.topics.values()} == {
            '/a': (60, 60), '/b': (40, 40), '/c': (60, 60)}
        messages = list(opened.messages(list(opened.topics)))
    assert [(m.topic, m.timestamp_ns, m.data) for m in messages] == [
        (m.topic, m.timestamp_ns, m.data) for m in sorted(recorded, key=lambda m: m.timestamp_ns)]


def test_topics_without_leading_slash_and_empty_qos_strings_are_read_as_ros2_bag_writes_them(tmp_path: Path) -> None:
    bag = write_bag(tmp_path / 'bag', chatter(3, 0.1, topic='chatter'),
                    qos={'chatter': [offer(QosReliability.BEST_EFFORT)]})

    def empty_qos(info: dict) -> None:
        for entry in info['topics_with_message_count']:
            entry['topic_metadata']['offered_qos_profiles'] = ''

    edit_metadata(bag, empty_qos)
    with Bag(bag) as opened:
        assert list(opened.topics) == ['/chatter']
        # metadata.yaml has no offer left: the storage's is used.
        assert opened.topics['/chatter'].qos == OfferedQos('BEST_EFFORT', 'VOLATILE')
        assert [m.data for m in opened.messages(['/chatter'])] == [m.data for m in chatter(3, 0.1)]


def test_a_topic_recorded_with_two_types_is_refused_by_name(tmp_path: Path) -> None:
    bag = write_bag(tmp_path / 'bag', chatter(2, 0.1, '/x') + [Recorded('/x', IMAGE, T0_NS + 10**9, image_data(T0_NS))])
    with Bag(bag) as opened:
        with pytest.raises(ValueError, match=r'topic /x was recorded with several message types'):
            select_topics(opened.topics, [])


BROKEN_BAGS = {
    'missing': (lambda d: d / 'nothing_here', 'does not exist'),
    'a file, not a directory': (lambda d: storage_file(write_bag(d / 'b', chatter(2, 0.1))), 'not a rosbag2 directory'),
    'no metadata.yaml': (lambda d: d, 'has no metadata.yaml'),
    'no messages': (lambda d: write_bag(d / 'b', []), 'empty'),
    'unknown storage': (lambda d: _edit_metadata(copy_bag(SHARED_BAGS / 'talker_sqlite3', d / 'b'),
                                                 'storage_identifier: sqlite3', 'storage_identifier: leveldb'),
                        "'leveldb' not supported"),
    'storage file missing': (lambda d: _unlink(storage_file(write_bag(d / 'b', chatter(2, 0.1)))),
                             'files are missing'),
    'metadata not YAML': (lambda d: _write(copy_bag(SHARED_BAGS / 'talker_mcap', d / 'b'), 'metadata.yaml',
                                           'rosbag2_bagfile_information: ['), 'Could not load YAML'),
    'random bytes as db3': (lambda d: _write(copy_bag(SHARED_BAGS / 'talker_sqlite3', d / 'b'), 'talker.db3',
                                             os.urandom(4096)), 'not a database'),
    'truncated mcap': (lambda d: _truncate(copy_bag(SHARED_BAGS / 'talker_mcap', d / 'b') / 'talker.mcap'),
                       'magic is invalid'),
    'corrupt mcap chunk': (lambda d: _corrupt_middle(copy_bag(SHARED_BAGS / 'talker_mcap', d / 'b')), 'corrupt'),
}


def _edit_metadata(bag: Path, old: str, new: str) -> Path:
    path = bag / 'metadata.yaml'
    path.write_text(path.read_text().replace(old, new))
    return bag


def _unlink(path: Path) -> Path:
    path.unlink()
    return path.parent


def _write(bag: Path, name: str, content: str | bytes) -> Path:
    (bag / name).write_bytes(content.encode() if isinstance(content, str) else content)
    return bag


def _truncate(path: Path) -> Path:
    path.write_bytes(path.read_bytes()[:len(path.read_bytes()) // 2])
    return path.parent


def _corrupt_middle(bag: Path) -> Path:
    path = bag / 'talker.mcap'
    data = bytearray(path.read_bytes())
    data[len(data) // 3: len(data) // 3 + 64] = b'\xff' * 64
    path.write_bytes(bytes(data))
    return bag


@pytest.mark.parametrize('case', BROKEN_BAGS)
def test_unplayable_bags_raise_one_clear_bag_error(tmp_path: Path, case: str) -> None:
    make, message = BROKEN_BAGS[case]
    path = make(tmp_path)
    with pytest.raises(BagError, match=message):
        with Bag(path) as bag:
            list(bag.messages(list(bag.topics)))


def test_metadata_announcing_messages_the_storage_lacks_is_an_error(tmp_path: Path) -> None:
    bag = write_bag(tmp_path / 'b', chatter(1, 0.1, '/a') + chatter(3, 0.1, '/b'))
    only_a = write_bag(tmp_path / 'a', chatter(1, 0.1, '/a'))
    storage_file(only_a).replace(storage_file(bag))
    with Bag(bag) as opened, pytest.raises(BagError, match='no readable messages'):
        list(opened.messages(['/b']))


def test_consistent_recorded_offers_are_kept_mixed_ones_fall_back_to_the_default() -> None:
    best_effort = offer(QosReliability.BEST_EFFORT)
    latched = offer(durability=QosDurability.TRANSIENT_LOCAL)
    assert adapt_offers([best_effort, best_effort]) == (OfferedQos('BEST_EFFORT', 'VOLATILE'), True)
    assert adapt_offers([latched]) == (OfferedQos('RELIABLE', 'TRANSIENT_LOCAL'), True)
    assert adapt_offers([best_effort, latched]) == (OfferedQos(), False)
    assert adapt_offers([]) == (OfferedQos(), True)
    assert adapt_offers([offer(QosReliability.UNKNOWN, QosDurability.SYSTEM_DEFAULT)]) == (OfferedQos(), True)


def test_recorded_qos_reaches_the_topic_description(tmp_path: Path) -> None:
    bag = write_bag(tmp_path / 'b', chatter(2, 0.1), qos={'/chatter': [offer(QosReliability.BEST_EFFORT)]})
    with Bag(bag) as opened:
        assert opened.topics['/chatter'].qos == OfferedQos('BEST_EFFORT', 'VOLATILE')


@pytest.mark.parametrize('little_endian', [True, False])
def test_header_stamp_is_read_from_serialized_images(little_endian: bool) -> None:
    from replay_bags import TYPESTORE
    stamp_ns = T0_NS + 123_456_789
    image = TYPESTORE.deserialize_cdr(image_data(stamp_ns), IMAGE)
    data = bytes(TYPESTORE.serialize_cdr(image, IMAGE, little_endian=little_endian))
    assert header_stamp(data) == (stamp_ns // 10**9, 123_456_789)


def test_header_stamp_refuses_unknown_encapsulation_and_short_data() -> None:
    with pytest.raises(ValueError, match='encapsulation'):
        header_stamp(b'\x00\x0a\x00\x00' + struct.pack('<iI', 1, 2))
    with pytest.raises(ValueError, match='too short'):
        header_stamp(b'\x00\x01\x00\x00')


def test_topic_selection_accepts_names_without_slash_and_reports_unknown_ones() -> None:
    with Bag(SHARED_BAGS / 'talker_sqlite3') as bag:
        selected, missing = select_topics(bag.topics, ['topic', '/nope'])
        assert [t.name for t in selected] == ['/topic'] and missing == ['/nope']
        assert {t.name for t in select_topics(bag.topics, [])[0]} == set(bag.topics)
        with pytest.raises(ValueError, match='none of the topics'):
            select_topics(bag.topics, ['/nope'])
        with pytest.raises(ValueError, match='hold no messages'):
            select_topics(bag.topics, ['/parameter_events'])


def test_remap_rules_parse_and_malformed_ones_are_refused() -> None:
    assert parse_remaps(['topic:=/a', '/b:=c']) == {'/topic': '/a', '/b': 'c'}
    for rule in ['/a', '/a:=', ':=/b', '/a=/b']:
        with pytest.raises(ValueError, match='FROM:=TO'):
            parse_remaps([rule])


@pytest.mark.parametrize('field, value, message', [
    ('bag', '', 'no bag'), ('rate', 0.0, 'rate'), ('rate', float('nan'), 'rate'), ('delay', -1.0, 'delay'),
    ('start_offset', -0.5, 'start_offset'), ('clock', -1.0, 'clock'), ('answer_timeout', 0.0, 'answer_timeout'),
    ('remap', ('/a',), 'FROM:=TO')])
def test_invalid_options_are_refused(field: str, value: object, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        PlaybackOptions(**{'bag': '/bag', field: value})


def test_schedule_scales_bag_time_by_rate_from_the_start_offset() -> None:
    origin = playback_origin(T0_NS, T0_NS + 10 * 10**9, 2.0)
    assert origin == T0_NS + 2 * 10**9
    timeline = Timeline(origin, rate=4.0)
    assert timeline.due_s(origin + 8 * 10**9) == pytest.approx(2.0)
    assert timeline.due_s(origin - 10**9) == 0.0
    assert timeline.bag_time_ns(2.0) == origin + 8 * 10**9
    with pytest.raises(ValueError, match='past the end'):
        playback_origin(T0_NS, T0_NS + 10 * 10**9, 10.0)


def test_progress_counts_bag_time_from_the_start_offset_to_the_end() -> None:
    end = T0_NS + 4 * 10**9
    assert [seconds_played(T0_NS + k * 10**9, T0_NS, end) for k in (-1, 1, 5)] == [0.0, 1.0, 4.0]


def test_tally_compares_what_was_played_with_what_metadata_promises_from_the_start_offset() -> None:
    messages = [BagMessage(topic, STRING, T0_NS + k, b'') for k in range(6) for topic in ('/a', '/b', '/x')]
    tally = PlaybackTally({'/a': 6, '/b': 8, '/x': 6}, {'/x': 'foo_msgs/msg/Bar not installed'})
    for message in tally.from_origin(messages, T0_NS + 2):
        tally.published[message.topic] += 1
    assert tally.before_start == {'/a': 2, '/b': 2, '/x': 2} and tally.published == {'/a': 4, '/b': 4}
    assert tally.shortfall() == {'/b': (4, 6)}
    assert tally.shortfall_line() == ('replay: error: incomplete: 4 of the 6 messages that metadata.yaml '
                                      'promises for the selection were played on /b 4 of 6')
    assert tally.skipped_text() == 'skipped 4 messages: /x 4 (foo_msgs/msg/Bar not installed)'
    surplus = PlaybackTally({'/a': 3})
    list(surplus.from_origin(messages[::3], T0_NS))
    assert surplus.surplus() == {'/a': (6, 3)} and PlaybackTally({'/a': 1}).skipped_text() == ''


def test_several_connections_of_a_topic_are_summed_and_their_offers_adapted(tmp_path: Path) -> None:
    recorded = [Recorded('/c', STRING, T0_NS + k, m.data, connection=k % 2) for k, m in enumerate(chatter(6, 0.1))]
    bag = write_bag(tmp_path / 'bag', recorded, version=8)
    listed = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert len(listed['topics_with_message_count']) == 2  # /c once per connection
    with Bag(bag) as opened:
        assert opened.topics['/c'].message_count == opened.topics['/c'].stored_count == 6
        assert opened.topics['/c'].qos_consistent
        assert [m.data for m in opened.messages(['/c'])] == [m.data for m in recorded]
