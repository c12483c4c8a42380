"""
Make an interrupted MCAP recording readable again.

A recorder killed with SIGKILL leaves `NAME.mcap` without its summary and footer (and the bag
without metadata.yaml); only the chunks completed before the kill are in the file. `repair_bag`
reads the file sequentially with the `mcap` library up to the first damaged record, writes the
recovered schemas, channels and messages (bytes, times and sequence numbers unchanged) into a new
MCAP file with the `mcap` writer, and rebuilds metadata.yaml. A complete file whose metadata.yaml
is missing or unreadable gets only a new metadata.yaml. A bag that is still being recorded (its
recorder holds a lock on the file) is refused. Nothing in the file is executed.
"""
from __future__ import annotations

import os
import struct
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from piezo_narx_ros.bag.writer import lock_recording, typestore
from piezo_narx_ros.errors import BagError
from piezo_narx_ros.files import write_atomic, write_text_atomic


@dataclass
class RepairReport:
    """What `repair_bag` recovered."""

    bag: Path
    mcap: Path
    backup: Path | None
    messages: int = 0
    topics: dict[str, int] = field(default_factory=dict)   # {topic: messages recovered}
    dropped_bytes: int = 0         # tail of the file that could not be parsed
    stop_reason: str = ''          # why reading stopped ('' when the file was complete)
    orphans: int = 0               # messages of a channel whose definition was lost
    intact: bool = False           # nothing was wrong; the bag was left untouched
    metadata_problem: str = ''     # what was wrong with metadata.yaml ('' when nothing)
    metadata_only: bool = False    # the MCAP file was complete: only metadata.yaml was rebuilt


def _locate(path: Path) -> tuple[Path, Path]:
    """(bag directory, its .mcap file) for a bag directory or a lone .mcap file."""
    if not path.exists():
        raise BagError(f'bag not found: {path}')
    if path.is_file():
        if path.suffix != '.mcap':
            raise BagError(f'{path}: only MCAP bags can be repaired')
        return path.parent, path
    files = sorted(path.glob('*.mcap'))
    if len(files) != 1:
        if list(path.glob('*.db3')):
            raise BagError(f'{path}: only MCAP bags can be repaired (this one is sqlite3)')
        raise BagError(f'{path}: expected exactly one .mcap file, found {len(files)}')
    return path, files[0]


def _scan(mcap_path: Path):
    """
    Read records until the end or the first damaged one.

    Returns (schemas {id: Schema}, channels {id: Channel}, messages [Message], rosbag2 metadata
    dict or None, bytes parsed, stop reason).
    """
    from mcap.exceptions import McapError
    from mcap.records import Channel, Footer, Message, Metadata, Schema
    from mcap.stream_reader import StreamReader

    schemas, channels, messages, meta = {}, {}, [], None
    good_end, reason = 0, ''
    with mcap_path.open('rb') as f:
        reader = StreamReader(f, validate_crcs=True)
        records = reader.records
        try:
            for rec in records:
                if isinstance(rec, Schema):
                    schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    channels[rec.id] = rec
                elif isinstance(rec, Message):
                    messages.append(rec)
                elif isinstance(rec, Metadata) and rec.name == 'rosbag2':
                    meta = rec.metadata
                elif isinstance(rec, Footer):
                    good_end = mcap_path.stat().st_size
                    break
                # The file offset after each complete top-level record (chunk contents are
                # yielded together after their chunk was read in full).
                good_end = max(good_end, f.tell())
            else:
                reason = 'no footer'
        except (McapError, struct.error, EOFError, ValueError, MemoryError) as exc:
            reason = ' '.join(str(exc).split()) or type(exc).__name__
    return schemas, channels, messages, meta, good_end, reason


def _qos_list(channel) -> list:
    text = channel.metadata.get('offered_qos_profiles', '')
    try:
        value = yaml.safe_load(text) if text else []
    except yaml.YAMLError:
        return []
    return value if isinstance(value, list) else []


def _type_hash(msgtype: str) -> str:
    store = typestore()
    return store.hash_rihs01(msgtype) if msgtype in store.fielddefs else ''


def _metadata_problem(bag_dir: Path) -> str:
    """
    Why metadata.yaml of a bag directory cannot be read as rosbag2 metadata ('' when it can).

    Missing, not UTF-8, not YAML, or without the rosbag2 keys a reader needs.
    """
    from rosbags.rosbag2 import Reader, ReaderError
    meta = bag_dir / 'metadata.yaml'
    if not meta.is_file():
        return 'metadata.yaml is missing'
    try:
        reader = Reader(bag_dir)   # the reader every tool here uses decides what is readable
        reader.open()
        reader.close()
    except (ReaderError, OSError, ValueError, KeyError, TypeError) as exc:
        return 'metadata.yaml is not valid rosbag2 metadata (' + ' '.join(str(exc).split()) + ')'
    return ''


def repair_bag(path: str | Path, backup: bool = True) -> RepairReport:
    """
    Rebuild an MCAP bag (directory or lone .mcap) whose recording was interrupted.

    Also one whose metadata.yaml is missing or unreadable.

    An intact bag (footer present, metadata.yaml readable) is left untouched (`intact`). A
    truncated file is replaced by the recovered messages; with `backup` the damaged original is
    kept beside it as `NAME.mcap.damaged`. metadata.yaml is (re)written for a bag directory (an
    unreadable one kept as metadata.yaml.damaged with `backup`); when only it was wrong, the MCAP
    file is not touched (`metadata_only`). Raises BagError while the bag is being recorded (a
    live recorder holds its lock), when the file is not MCAP, or holds no complete
    schema/channel record.
    """
    path = Path(path)
    bag_dir, mcap_path = _locate(path)
    with mcap_path.open('rb') as f:
        if f.read(8) != b'\x89MCAP0\r\n':
            raise BagError(f'{mcap_path}: not an MCAP file (bad magic)')
    lock = lock_recording(mcap_path)   # refuses a live recording; keeps a recorder out meanwhile
    try:
        return _repair(path, bag_dir, mcap_path, backup)
    finally:
        if lock is not None:
            lock.close()


def _repair(path: Path, bag_dir: Path, mcap_path: Path, backup: bool) -> RepairReport:
    schemas, channels, messages, meta, good_end, reason = _scan(mcap_path)
    if not channels:
        raise BagError(f'{mcap_path}: no complete chunk was written before the recording stopped;'
                       ' nothing to recover')
    report = RepairReport(bag_dir if path.is_dir() else path, mcap_path, None,
                          dropped_bytes=max(0, mcap_path.stat().st_size - good_end),
                          stop_reason=reason)
    report.metadata_problem = _metadata_problem(bag_dir) if path.is_dir() else ''
    if not reason and not report.metadata_problem:
        report.intact = True
        report.messages = len(messages)
        return report
    counts = dict.fromkeys(channels, 0)
    t_min, t_max = 2**63 - 1, 0
    for m in messages:
        if m.channel_id not in channels:
            report.orphans += 1
            continue
        counts[m.channel_id] += 1
        t_min, t_max = min(t_min, m.log_time), max(t_max, m.log_time)
    report.messages = sum(counts.values())
    report.topics = {channels[c].topic: n for c, n in counts.items()}
    types = {cid: schemas[c.schema_id].name if c.schema_id in schemas else ''
             for cid, c in channels.items()}
    info = _metadata(mcap_path.name, channels, types, counts, t_min, t_max, meta)
    if reason:
        _rewrite_mcap(mcap_path, schemas, channels, messages, info, report, backup)
    else:
        report.metadata_only = True
    if path.is_dir():
        old = bag_dir / 'metadata.yaml'
        if backup and old.is_file():
            os.replace(old, bag_dir / 'metadata.yaml.damaged')
        write_text_atomic(old, yaml.safe_dump({'rosbag2_bagfile_information': info},
                                              default_flow_style=False))
    return report


def _rewrite_mcap(mcap_path: Path, schemas: dict, channels: dict, messages: list, info: dict,
                  report: RepairReport, backup: bool) -> None:
    """
    Write the recovered records into a new complete MCAP file that replaces `mcap_path`.

    Bytes, times and sequence numbers are unchanged.
    """
    from mcap.writer import CompressionType, Writer
    with write_atomic(mcap_path) as out:
        writer = Writer(out, compression=CompressionType.NONE)
        writer.start(profile='ros2', library='piezo_narx_ros bag repair')
        schema_ids = {sid: writer.register_schema(s.name, s.encoding, s.data)
                      for sid, s in schemas.items()}
        chan_ids = {}
        for cid, c in channels.items():
            chan_ids[cid] = writer.register_channel(c.topic, c.message_encoding,
                                                    schema_ids.get(c.schema_id, 0), c.metadata)
        for m in messages:
            new = chan_ids.get(m.channel_id)
            if new is not None:
                writer.add_message(new, m.log_time, m.data, m.publish_time, m.sequence)
        writer.add_metadata('rosbag2', {'serialized_metadata': yaml.safe_dump(
            info, default_flow_style=False).strip()})
        writer.finish()
        if backup:      # before write_atomic renames the new file over it
            report.backup = mcap_path.with_name(mcap_path.name + '.damaged')
            os.replace(mcap_path, report.backup)


def _metadata(file_name: str, channels: dict, types: dict, counts: dict, t_min: int, t_max: int,
              old: dict | None) -> dict:
    """rosbag2 metadata (version 9) describing the repaired file."""
    count = int(sum(counts.values()))
    start = int(t_min) if count else 0
    duration = int(t_max - t_min) if count else 0
    distro = ''
    if old and 'serialized_metadata' in old:
        try:
            distro = str(yaml.safe_load(old['serialized_metadata']).get('ros_distro', ''))
        except (yaml.YAMLError, AttributeError):
            distro = ''
    return {
        'version': 9,
        'storage_identifier': 'mcap',
        'relative_file_paths': [file_name],
        'duration': {'nanoseconds': duration},
        'starting_time': {'nanoseconds_since_epoch': start},
        'message_count': count,
        'topics_with_message_count': [
            {'topic_metadata': {'name': c.topic, 'type': types[cid],
                                'serialization_format': c.message_encoding,
                                'offered_qos_profiles': _qos_list(c),
                                'type_description_hash': _type_hash(types[cid])},
             'message_count': int(counts[cid])}
            for cid, c in channels.items()],
        'compression_format': '',
        'compression_mode': '',
        'files': [{'path': file_name, 'starting_time': {'nanoseconds_since_epoch': start},
                   'duration': {'nanoseconds': duration}, 'message_count': count}],
        'custom_data': None,
        'ros_distro': distro or os.environ.get('ROS_DISTRO', ''),
    }
