"""Message readers under :class:`~terrainmap.sources.log.LogSource`: MCAP files (a single file or
a rosbag2 directory of them), and through ``rosbags`` the rosbag2 directories the mcap reader
cannot read (sqlite3 storage, zstd-compressed files or messages); ROS 1 bags are read by
:mod:`~terrainmap.sources.ros1bag`.

A reader knows its files (``paths``), its topics (``types``: topic → message type, ``counts``:
topic → number of messages), ``damage`` (what is damaged in the file as a whole, or None) and ``skipped`` (the
damaged chunks of indexed MCAP files passed over so far, one line each), and streams decoded
messages of chosen topics in log-time order, one file at a time. Other read errors (truncated or
corrupt files) become :class:`InputError` naming the file, raised after the messages that could
be read.
"""

from __future__ import annotations

import heapq
import io
import logging
import os
import sqlite3
import struct
import zlib
from collections import Counter
from collections.abc import Iterator
from contextlib import redirect_stderr
from functools import lru_cache, partial
from pathlib import Path
from typing import Any

import yaml

from ..errors import InputError, counted
from .base import natural_key
from .messages import normalize_type

logger = logging.getLogger(__name__)


def _reason(exc: Exception) -> str:
    """``Type: message`` of an exception, first line only ("Type" when the message is empty)."""
    return f"{type(exc).__name__}: {exc}".rstrip(": ").splitlines()[0][:200]


MCAP_MAGIC = b"\x89MCAP0\r\n"
"""The 8 bytes an MCAP file begins (and ends) with."""

_FOOTER = struct.Struct("<BQQQI")
"""An MCAP footer record: opcode 0x02, record length, summary start, summary offset start, summary CRC."""

_MAX_UNDECODABLE = 20
"""Messages in a row of one channel that cannot be decoded before the log is refused (damage
does not do that: the channel's schema does not describe its data)."""


def summary_section(stream) -> tuple[int | None, bool]:
    """Where an MCAP file's summary section begins, by its footer (None without a footer or a
    summary), and whether it holds the CRC the footer gives (true when it gives none). The CRC
    covers the summary start to the footer's CRC field."""
    end = stream.seek(0, 2) - 8  # the closing magic
    if end < _FOOTER.size:
        return None, True
    stream.seek(end - _FOOTER.size)
    opcode, _, summary_start, _, crc = _FOOTER.unpack(stream.read(_FOOTER.size))
    if opcode != 0x02 or not 0 < summary_start < end:
        return None, True
    if crc == 0:
        return summary_start, True
    stream.seek(summary_start)
    return summary_start, zlib.crc32(stream.read(end - 4 - summary_start)) == crc


class _Until:
    """A binary stream read up to byte ``end`` only (a file's data section, before a damaged summary)."""

    def __init__(self, stream, end: int):
        self._stream, self._left = stream, end - stream.tell()

    def read(self, size: int = -1) -> bytes:
        data = self._stream.read(self._left if size is None or size < 0 else min(size, self._left))
        self._left -= len(data)
        return data

    @property
    def at_end(self) -> bool:
        return self._left <= 0


def _decoder_factories() -> list:
    from mcap_protobuf.decoder import DecoderFactory as ProtobufDecoderFactory
    from mcap_ros2.decoder import DecoderFactory as Ros2DecoderFactory

    return [Ros2DecoderFactory(), ProtobufDecoderFactory(), Ros1DecoderFactory()]


class Ros1DecoderFactory:
    """Decoders of ROS 1 messages in MCAP (message encoding ``ros1``, as ``mcap convert`` writes a
    ROS 1 bag), through ``rosbags``' ROS 1 type store; a type it lacks is registered from the
    channel's schema (the ``ros1msg`` definition a bag carries)."""

    def __init__(self):
        self._typestore = None

    def decoder_for(self, message_encoding: str, schema) -> Any:
        if message_encoding != "ros1" or schema is None:
            return None
        if self._typestore is None:
            self._typestore = ros1_typestore()
        name = normalize_type(schema.name)
        register_ros1_type(self._typestore, name, schema.data.decode())
        return partial(self._typestore.deserialize_ros1, typename=name)


def ros1_typestore():
    """``rosbags``' type store of ROS 1 Noetic's standard messages."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS1_NOETIC)


def register_ros1_type(typestore, name: str, definition: str) -> None:
    """Teach ``typestore`` the ROS 1 message type ``name`` (``pkg/msg/Type``) from its full
    definition (the ``MSG:``-separated text a bag carries) unless it knows it: the Noetic store
    lacks some common ones, tf2_msgs/TFMessage among them."""
    from rosbags.typesys import get_types_from_msg

    if name not in typestore.fielddefs:
        typestore.register(get_types_from_msg(definition, name))


def file_size(path: Path) -> int | None:
    """The size of ``path`` in bytes; None where it cannot be read."""
    try:
        return path.stat().st_size
    except OSError:
        return None


class _SkipsDamage:
    """A reader that skips what is damaged and notes it: ``skipped_parts`` maps a key (a chunk's
    byte offset, a message's topic and time) to one line naming the file and what was skipped."""

    path: Path
    skipped_parts: dict
    opened_size: int | None = None
    """The file's size in bytes when it was opened."""

    @property
    def skipped(self) -> list[str]:
        """The damaged parts skipped so far, one line each."""
        return list(self.skipped_parts.values())

    def _skip(self, key, what: str, exc: Exception) -> None:
        """Note a damaged part in :attr:`skipped_parts` (once) and warn about it; but where the file
        is no longer the one opened (cut short or written over while being read, a copy still
        under way: its size is not the one it had), :class:`InputError`: what follows is no damage to
        skip."""
        if self.opened_size is not None and (now := file_size(self.path)) != self.opened_size:
            size = f"{now} bytes, was {self.opened_size}" if now is not None else "removed"
            raise InputError(f"{self.path}: changed while it was being read ({size}; {what}: {_reason(exc)})") from exc
        if key not in self.skipped_parts:
            self.skipped_parts[key] = f"{self.path}: {what} ({_reason(exc)})"
            logger.warning("%s: damaged, skipped", self.skipped_parts[key])

    def _decoded(self, records: Iterator, topics: list[str], what: str) -> Iterator[tuple[str, int, Any]]:
        """(topic, log time, message) from ``records`` of (topic, log time, kind, decode), the
        message being ``decode()``: one that cannot be decoded is skipped (:meth:`_undecodable`); a
        read that fails ends the messages with :class:`InputError` (``what``: "log", "bag")."""
        count, failing = 0, Counter()
        try:
            for topic, log_time, kind, decode in records:
                try:
                    message = decode()
                except Exception as exc:  # one bad message (its chunk's CRC held): skipped, reading goes on
                    self._undecodable(failing, topic, kind, log_time, exc)
                    continue
                failing.pop(topic, None)
                yield topic, log_time, message
                count += 1
        except InputError:
            raise
        except Exception as exc:
            raise InputError(f"{self.path}: {what} is truncated or corrupt after {counted(count, 'message')} of "
                             f"{', '.join(topics)} ({_reason(exc)})") from exc

    def _undecodable(self, failing: Counter, topic: str, kind: str, log_time: int, exc: Exception) -> None:
        """A message of ``topic`` that cannot be decoded as ``kind``: skipped, unless it is the
        :data:`_MAX_UNDECODABLE`-th in a row of its topic (``failing`` counts them; then
        :class:`InputError`: the topic's type is wrong, which is no damage)."""
        failing[topic] += 1
        if failing[topic] >= _MAX_UNDECODABLE:
            raise InputError(f"{self.path}: topic {topic}: {_MAX_UNDECODABLE} messages in a row are not a "
                             f"readable {kind} ({_reason(exc)})") from exc
        self._skip(("message", topic, log_time), f"{topic} message at log time {log_time / 1e9:.3f} s, not a "
                   f"readable {kind}", exc)


class McapFile(_SkipsDamage):
    """One MCAP file: its channels from the summary, or from a linear scan when it has none."""

    def __init__(self, path: Path):
        from mcap.reader import make_reader

        self.path = path
        self.types: dict[str, str] = {}
        self.counts: dict[str, int | None] = {}
        self.span_ns: tuple[int, int] | None = None  # log times of the first and the last message
        self.indexed = False
        self._data_end: int | None = None  # where a summary that cannot be used begins: reading stops there
        self._index = None  # the summary of an indexed file (its channels, schemas and chunk indexes)
        self.damage: str | None = None
        """What is damaged in the file as a whole (None: nothing found at open): where a scan of a
        file without a summary stopped early, or a summary that fails its CRC (its messages are
        then all read, from start to end)."""
        self.skipped_parts: dict[int | tuple, str] = {}
        """Damaged chunks of an indexed file (byte offset → what) and messages that could not be
        decoded (("message", topic, log time) → what), met while reading messages."""
        self.opened_size = file_size(path)
        try:
            with open(path, "rb") as stream:
                if (head := stream.read(len(MCAP_MAGIC))) != MCAP_MAGIC:
                    why = ("it is empty" if not head else "it ends within MCAP's 8 magic bytes"
                           if MCAP_MAGIC.startswith(head) else "it does not begin with MCAP's magic bytes")
                    raise InputError(f"{path}: not an MCAP file ({why})")
                stream.seek(0)
                reader = make_reader(stream)
                summary = self._summary(reader, stream)
                if summary is not None:
                    self._from_summary(summary)
                    self._index = summary if self.indexed else None  # read once, for every messages() call
                else:
                    stream.seek(0)
                    self._scan(stream)
        except OSError as exc:
            raise InputError(f"{path}: cannot read the log ({exc.strerror or exc})") from None
        except InputError:
            raise
        except Exception as exc:  # mcap raises many kinds on a file that is not MCAP
            raise InputError(f"{path}: not a readable MCAP file ({_reason(exc)})") from exc

    def _summary(self, reader, stream):
        start, holds = summary_section(stream)  # mcap does not check the summary's CRC
        try:
            summary, unreadable = reader.get_summary(), None
        except Exception as exc:  # no footer (a truncated or still-recording file), or a broken summary
            summary, unreadable = None, _reason(exc)
        if not holds:  # damaged, whether mcap could still parse it or not
            self._data_end = start
            self.damage = f"{self.path}: its summary (the index) is damaged (CRC mismatch); reading the file from start to end"
            logger.warning("%s", self.damage)
            return None
        if unreadable is not None:
            self._data_end = start
            logger.info("%s: no readable summary (%s); scanning the file", self.path, unreadable)
        return summary

    def _linear(self, stream, topics: list[str] | None = None) -> Iterator[tuple[Any, Any, Any]]:
        """(schema, channel, message) read from start to end, chunk CRCs checked, ending quietly
        where an unusable summary begins (the records there are not read)."""
        from mcap.reader import NonSeekingReader

        bounded = None if self._data_end is None else _Until(stream, self._data_end)
        try:
            yield from NonSeekingReader(bounded or stream, validate_crcs=True).iter_messages(
                topics=topics, log_time_order=False)
        except Exception:
            if bounded is None or not bounded.at_end:  # damage, not the data section's end
                raise

    def _from_summary(self, summary) -> None:
        self.indexed = bool(summary.chunk_indexes)
        stats = summary.statistics  # optional in MCAP: without it the counts are unknown (None)
        if stats and stats.message_count:
            self.span_ns = (stats.message_start_time, stats.message_end_time)
        elif not stats and summary.chunk_indexes:
            self.span_ns = (min(c.message_start_time for c in summary.chunk_indexes),
                            max(c.message_end_time for c in summary.chunk_indexes))
        for channel in summary.channels.values():
            schema = summary.schemas.get(channel.schema_id)
            self.types[channel.topic] = normalize_type(schema.name if schema else "")
            self.counts[channel.topic] = (self.counts.get(channel.topic, 0) + stats.channel_message_counts.get(channel.id, 0)
                                          if stats else None)

    def _scan(self, stream) -> None:
        try:
            for schema, channel, message in self._linear(stream):
                self.types[channel.topic] = normalize_type(schema.name if schema else "")
                self.counts[channel.topic] = self.counts.get(channel.topic, 0) + 1
                self.span_ns = _widened(self.span_ns, message.log_time, message.log_time)
        except Exception as exc:
            # Not a warning: ``info`` shows it, and reading the messages raises it as the error.
            self.damage = f"{self.path}: truncated or corrupt after {counted(sum(self.counts.values()), 'message')} ({_reason(exc)})"
            logger.info("%s", self.damage)

    def messages(self, topics: list[str]) -> Iterator[tuple[str, int, Any]]:
        """(topic, log_time_ns, decoded message) of ``topics`` in log-time order.

        Chunk CRCs are checked (0.6 ms a 640×480 frame), so that damaged image data never goes
        through as a wrong frame. In an indexed file a damaged chunk is skipped with a warning
        (and noted in :attr:`skipped`): the messages of the other chunks are read all the same.
        A message that cannot be decoded is skipped likewise, in any file.
        Damage that a linear read meets (a file without a summary) ends the messages there."""
        return self._decoded(self._records(topics), topics, "log")

    def _records(self, topics: list[str]) -> Iterator[tuple[str, int, str, Any]]:
        """(topic, log time, kind, decode) of ``topics`` (:meth:`_SkipsDamage._decoded`)."""
        factories, decoders = _decoder_factories(), {}
        with open(self.path, "rb") as stream:
            if self.indexed:
                records = self._indexed_messages(stream, set(topics))
            else:
                records = self._linear(stream, topics)
            for schema, channel, message in records:
                if channel.id not in decoders:
                    decoders[channel.id] = self._decoder(factories, channel, schema)
                if decoders[channel.id] is None:
                    schema_encoding = schema.encoding if schema is not None else "none"
                    raise InputError(f"{self.path}: no decoder for topic {channel.topic} (message encoding "
                                     f"{channel.message_encoding!r}, schema encoding {schema_encoding!r}; "
                                     "terrainmap reads cdr with ros2msg, ros1 with ros1msg and protobuf)")
                kind = schema.name if schema is not None else channel.message_encoding
                yield channel.topic, message.log_time, kind, partial(decoders[channel.id], message.data)

    def _indexed_messages(self, stream, topics: set[str]) -> Iterator[tuple[Any, Any, Any]]:
        """(schema, channel, message) of ``topics`` from the chunks of an indexed file, merged in
        log-time order as ``SeekingReader.iter_messages`` does, skipping chunks that fail to read."""
        from mcap.data_stream import ReadDataStream
        from mcap.reader import breakup_chunk
        from mcap.records import Chunk, Message

        summary = self._index
        wanted = {cid for cid, channel in summary.channels.items() if channel.topic in topics}
        # A heap of chunks (keyed by their first message's time) and of the messages of the chunks
        # opened so far: a chunk opens before any message at or after its start time is yielded.
        heap = [(c.message_start_time, 0, c.chunk_start_offset, -1, c) for c in summary.chunk_indexes
                if not c.message_index_offsets or wanted & c.message_index_offsets.keys()]
        heapq.heapify(heap)
        while heap:
            *_, offset, index, item = heapq.heappop(heap)
            if index >= 0:
                yield item
                continue
            try:
                stream.seek(offset + 1 + 8)  # past the opcode and the record length
                records = list(breakup_chunk(Chunk.read(ReadDataStream(stream)), validate_crc=True))
            except Exception as exc:
                self._skip(offset, f"chunk at byte {offset}, log time {item.message_start_time / 1e9:.3f}–"
                                   f"{item.message_end_time / 1e9:.3f} s", exc)
                continue
            for i, record in enumerate(records):
                if isinstance(record, Message) and record.channel_id in wanted:
                    channel = summary.channels[record.channel_id]
                    schema = summary.schemas.get(channel.schema_id)
                    heapq.heappush(heap, (record.log_time, 1, offset, i, (schema, channel, record)))

    def _decoder(self, factories, channel, schema):
        """The first decoder the factories offer for ``channel`` (None if none does), or
        :class:`InputError` naming the topic when its schema cannot be parsed."""
        try:
            # mcap_ros2's message-definition parser prints the bad line to stderr before raising
            with redirect_stderr(io.StringIO()):
                return next((d for f in factories if (d := f.decoder_for(channel.message_encoding, schema))), None)
        except Exception as exc:
            name = schema.name if schema else "none"
            raise InputError(f"{self.path}: topic {channel.topic}: unreadable schema {name} ({_reason(exc)})") from exc


def bag_metadata(path: Path) -> dict:
    """``rosbag2_bagfile_information`` of a rosbag2 directory's ``metadata.yaml``; {} when it is
    missing, or unreadable (which is logged)."""
    metadata = path / "metadata.yaml"
    if not metadata.is_file():
        return {}
    try:
        stat = metadata.stat()
        return _metadata_info(metadata, stat.st_mtime_ns, stat.st_size)
    except (OSError, ValueError, yaml.YAMLError, RecursionError) as exc:  # RecursionError: nested thousands deep
        if metadata not in _WARNED:  # once per file: several readers look at it
            _WARNED.add(metadata)
            logger.warning("%s: unreadable (%s)", metadata, _reason(exc))
        return {}


@lru_cache(maxsize=8)
def _metadata_info(metadata: Path, mtime_ns: int, size: int) -> dict:
    """The parsed ``rosbag2_bagfile_information`` of ``metadata`` (read-only; several readers ask
    for it while a log opens, so it is parsed once for each version of the file)."""
    data = yaml.safe_load(metadata.read_text())
    info = data.get("rosbag2_bagfile_information") if isinstance(data, dict) else None
    if not isinstance(info, dict):
        raise ValueError("no rosbag2_bagfile_information mapping in it")
    return info


_WARNED: set[Path] = set()
"""The unreadable ``metadata.yaml`` files (:func:`bag_metadata`) and the folders whose
``relative_file_paths`` is no list of file names (:func:`_listed`) warned about so far."""


def bag_files(path: Path) -> list[Path]:
    """The files a rosbag2 directory's ``metadata.yaml`` lists, in its order and once each, that
    exist inside the directory ([] without readable metadata)."""
    inside = path.resolve()
    return [path / n for n in _listed(path) if (path / n).is_file() and inside in (path / n).resolve().parents]


def missing_bag_files(path: Path) -> list[str]:
    """The files a rosbag2 directory's ``metadata.yaml`` lists that are not in it."""
    return [n for n in _listed(path) if not (path / n).is_file()]


def _listed(path: Path) -> list[str]:
    names = bag_metadata(path).get("relative_file_paths") or []
    if not _file_names(names):
        if path not in _WARNED:
            _WARNED.add(path)
            logger.warning("%s: relative_file_paths is no list of file names; using the files in the folder",
                           path / "metadata.yaml")
        names = []
    return list(dict.fromkeys(names))


def _file_names(names) -> bool:
    """Whether ``relative_file_paths`` is what rosbag2 writes: a list of file names."""
    return isinstance(names, list) and all(isinstance(name, str) for name in names)


def mcap_files(path: Path) -> list[Path]:
    """The MCAP files of a log: the file itself, or a rosbag2 directory's files in metadata order."""
    if path.is_file():
        return [path]
    return [f for f in bag_files(path) if f.suffix == ".mcap"] or sorted(path.glob("*.mcap"), key=lambda f: natural_key(f.name))


class SplitLog:
    """A log of one or more files read one after the other (``files``: readers with ``path``,
    ``types``, ``counts``, ``span_ns``, ``damage``, ``skipped`` and ``messages``): a rosbag2's
    MCAP files, or the bags ``rosbag record --split`` writes."""

    def __init__(self, path: Path, files: list):
        self.files = files
        self.types: dict[str, str] = {}
        self.counts: dict[str, int | None] = {}
        self.span_ns: tuple[int, int] | None = None  # of all its files' messages
        self.damage = next((f.damage for f in self.files if f.damage), None)
        if path.is_dir() and (missing := missing_bag_files(path)):  # a recording's file lost: its messages are too
            self.damage = f"{path / 'metadata.yaml'} lists {', '.join(missing)}, not in the folder"
            logger.warning("%s: their messages are lost", self.damage)
        elif path.is_dir() and (path / "metadata.yaml").is_file() and not bag_metadata(path):  # (said as it was read)
            self.damage = f"{path / 'metadata.yaml'} is unreadable; the folder's files are read in name order"
        self.paths = [f.path for f in self.files]
        where: dict[str, Path] = {}
        for f in self.files:
            for topic, kind in f.types.items():
                if self.types.setdefault(topic, kind) != kind:
                    raise InputError(f"{path}: topic {topic} is {self.types[topic]} in {where[topic].name} but {kind} "
                                     f"in {f.path.name}: these files are not one log; give one of them")
                where.setdefault(topic, f.path)
            for topic, n in f.counts.items():  # unknown (None) in one file: unknown in all
                known = n is not None and (topic not in self.counts or self.counts[topic] is not None)
                self.counts[topic] = self.counts.get(topic, 0) + n if known else None
            if f.span_ns is not None:
                self.span_ns = _widened(self.span_ns, *f.span_ns)

    @property
    def skipped(self) -> list[str]:
        """The damaged chunks and messages skipped so far (:attr:`McapFile.skipped`), one line each."""
        return [line for f in self.files for line in f.skipped]

    def messages(self, topics: list[str]) -> Iterator[tuple[str, int, Any]]:
        for f in self.files:
            yield from f.messages(topics)


class McapLog(SplitLog):
    """An MCAP file or a rosbag2 directory of MCAP files, read one file at a time."""

    format = "mcap"

    def __init__(self, path: Path):
        files = [McapFile(f) for f in mcap_files(path)]
        if not files:
            raise InputError(f"{path}: no .mcap files in this folder")
        super().__init__(path, files)


def _widened(span: tuple[int, int] | None, start_ns: int, end_ns: int) -> tuple[int, int]:
    """The span ``(first, last)`` log time, ns, that also covers ``start_ns`` to ``end_ns``."""
    return (start_ns, end_ns) if span is None else (min(span[0], start_ns), max(span[1], end_ns))


def _rosbags_span(bag, counts: dict[str, int]) -> tuple[int, int] | None:
    """Log times of a ``rosbags`` reader's first and last message (None: no message); its
    ``end_time`` is 1 ns after the last."""
    return (bag.start_time, max(bag.start_time, bag.end_time - 1)) if sum(counts.values()) else None


def _topics(connections) -> tuple[dict[str, str], dict[str, int]]:
    """Topic → message type and topic → message count of ``rosbags`` connections."""
    counts: dict[str, int] = {}
    for c in connections:
        counts[c.topic] = counts.get(c.topic, 0) + c.msgcount
    return {c.topic: normalize_type(c.msgtype) for c in connections}, counts


class _OpenWhileRead:
    """A ``rosbags`` storage reader of one file of a rosbag2 (``plugin``: sqlite3's or MCAP's),
    open only while it is being read: ``rosbags`` opens every file of a split bag at once and
    keeps them all open (memory, and the open-file limit). A file is reread only if it is still
    the one checked when the bag opened; errors name the file."""

    plugin: type
    is_sqlite3: bool
    """Whether the plugin is sqlite3's (whose files are read with :class:`_Sqlite3File`)."""
    compressed: dict[str, Path]
    """The bag's zstd-compressed files by the name of the copy ``rosbags`` decompresses each into,
    in a temporary folder: errors name the bag's file."""

    def __init__(self, path: Path):
        self.path = Path(os.path.abspath(path))  # reopened later: whatever the working folder is then
        original = self.compressed.get(self.path.name)
        self.shown = original if original is not None and original.parent != self.path.parent else None
        """The bag's compressed file this is the decompressed copy of (None: this is the bag's file)."""
        self.connections: list = []
        self.metadata = None
        self._identity = None
        self._reading: list = []  # the readers now open in :meth:`messages`

    def open(self) -> None:
        """Check the file and take its connections and metadata (rosbags asks as the bag opens)."""
        storage = self.plugin(self.path)
        try:
            storage.open()
        except Exception as exc:
            raise _named(self.shown or self.path, exc) from exc
        self.connections, self.metadata = list(storage.connections), storage.metadata  # copies: close empties them
        self._identity = _identity(self.path)
        storage.close()

    def close(self) -> None:
        while self._reading:
            self._reading.pop().close()

    def messages(self, connections, start=None, stop=None) -> Iterator:
        if _identity(self.path) != self._identity:
            copy = "" if self.shown is None else f" (the decompressed copy of {self.shown})"
            raise InputError(f"{self.path}{copy}: changed or removed since the bag was opened")
        reader = None  # one per call: two reads may be under way in one file
        try:
            if self.is_sqlite3:
                reader = _Sqlite3File(self.path, self.connections)
            else:
                reader = self.plugin(self.path)
                reader.open()
            self._reading.append(reader)
            yield from reader.messages(connections, start, stop)
        except Exception as exc:
            raise _named(self.shown or self.path, exc) from exc
        finally:
            if reader in self._reading:  # not yet closed by close()
                self._reading.remove(reader)
                reader.close()


class _Sqlite3File:
    """The messages of one rosbag2 sqlite3 file, as ``rosbags``' reader gives them (its query),
    without the statistics it gathers over the whole file each time it opens one (a second per
    million messages; opening a log reads a few messages of several topics in turn)."""

    def __init__(self, path: Path, connections: list):
        self._db = sqlite3.connect(f"{path.as_uri()}?immutable=1&mode=ro", uri=True, check_same_thread=False)
        self._cursor = None
        self._connections = {c.id: c for c in connections}

    def messages(self, connections, start: int | None = None, stop: int | None = None) -> Iterator:
        args = [c.id for c in connections]
        query = ("SELECT topics.id, messages.timestamp, messages.data FROM messages JOIN topics ON "
                 f"messages.topic_id=topics.id WHERE topics.id IN ({', '.join('?' * len(args))})")
        for clause, value in ((" AND messages.timestamp >= ?", start), (" AND messages.timestamp < ?", stop)):
            if value is not None:
                query += clause
                args.append(value)
        self._cursor = self._db.execute(query + " ORDER BY timestamp", args)
        for topic_id, stamp, data in self._cursor:
            yield self._connections[topic_id], stamp, data

    def close(self) -> None:
        if self._cursor is not None:  # a connection closed under an open cursor keeps its file
            self._cursor.close()
        self._db.close()


def _identity(path: Path) -> tuple | None:
    """What tells a file from another put in its place: size and modification time (None if gone;
    not the inode, which some network file systems number anew on each lookup)."""
    try:
        st = path.stat()
    except OSError:
        return None
    return st.st_size, st.st_mtime_ns


def _named(path: Path, exc: Exception) -> Exception:
    """``exc``, as a ``rosbags`` ReaderError whose message starts with the name of the file it came from."""
    from rosbags.rosbag2 import ReaderError

    return ReaderError(f"{path.name}: {exc}")


def _rosbags_reader(path: Path, files: list[Path]):
    """``rosbags``' reader of the rosbag2 directory ``path`` of storage ``files``, with the files
    opened one at a time (:class:`_OpenWhileRead`; ``rosbags`` is pinned to the minor version
    this is written for)."""
    from rosbags.rosbag2.reader import DirectoryReader, Reader

    compressed = {f.name.removesuffix(".zstd"): Path(os.path.abspath(f)) for f in files if f.name.endswith(".zstd")}

    class Directory(DirectoryReader):
        STORAGE_PLUGINS = {name: type(f"{plugin.__name__}OpenWhileRead", (_OpenWhileRead,),
                                      {"plugin": plugin, "is_sqlite3": name == "sqlite3", "compressed": compressed})
                           for name, plugin in DirectoryReader.STORAGE_PLUGINS.items()}

    class OneFileAtATime(Reader):
        STORAGE_PLUGINS = {**Reader.STORAGE_PLUGINS, "dir": Directory}

    return OneFileAtATime(path)


class Rosbag2Bag(_SkipsDamage):
    """A rosbag2 directory in sqlite3 storage (``.db3``, the default before ROS 2 Iron), or one whose
    files or messages rosbag2 compressed (zstd), opened with ``rosbags`` (which checks every file
    and gathers its topics) and read one file at a time (:class:`_OpenWhileRead`); CDR messages
    are decoded with its type store of standard ROS 2 messages, and one that cannot be decoded is
    skipped. A compressed file is decompressed once, into a temporary folder, when the bag opens;
    the folder goes at :meth:`close`."""

    format = "rosbag2"
    damage: str | None = None  # rosbags reads the storage's index at open and fails there

    def __init__(self, path: Path):
        from rosbags.typesys import Stores, get_typestore

        self.path = path
        self.skipped_parts: dict[tuple, str] = {}
        if not _file_names(bag_metadata(path).get("relative_file_paths", [])):  # rosbags would read a text's letters
            raise InputError(f"{path / 'metadata.yaml'}: relative_file_paths must be a list of file names")
        self.paths = bag_files(path)
        self._typestore = get_typestore(Stores.LATEST)
        try:
            self._bag = _rosbags_reader(path, self.paths)
            self._bag.open()
        except Exception as exc:  # ReaderError, but also sqlite3, YAML and zstd errors on damaged files
            raise InputError(f"{path}: not a readable rosbag2 ({_reason(exc)})") from exc
        self.types, self.counts = _topics(self._bag.connections)
        self.span_ns = _rosbags_span(self._bag, self.counts)

    def close(self) -> None:
        if self._bag.is_open:
            self._bag.close()

    def messages(self, topics: list[str]) -> Iterator[tuple[str, int, Any]]:
        """(topic, log time, message) of ``topics`` in log-time order (:meth:`_SkipsDamage._decoded`)."""
        def records():  # a generator, so that rosbags' errors too are met inside _decoded
            connections = [c for c in self._bag.connections if c.topic in topics]
            for c, log_time, raw in self._bag.messages(connections=connections):
                yield c.topic, log_time, c.msgtype, partial(self._typestore.deserialize_cdr, raw, c.msgtype)

        return self._decoded(records(), topics, "bag")

