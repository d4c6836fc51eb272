"""ROS 1 bags (format v2.0), read one chunk at a time so that memory stays flat in log length.

A bag is a sequence of records, each a header (``name=value`` fields, ``op`` giving the kind)
and a data block: the bag header (where the index begins), chunks (compressed runs of
connection and message records) each followed by its index records, and at the end the index:
every connection, then one chunk-info record per chunk (its byte offset, first and last message
time and message count per connection). The index is read at open; messages are then read chunk
by chunk in log-time order, merged as the chunks overlap in time, without the per-message index
records (about 175 bytes a message in ``rosbags``' reader, which reads them all at open). A bag
without a usable index (a recording cut short, which ``rosbag reindex`` would repair) is scanned
from start to end at open instead, the records of the chunk it was still writing included, and
its messages read up to where the scan stopped.

Messages are decoded by ``rosbags``' ROS 1 type store, which learns the types it lacks from the
definitions the bag carries.
"""

from __future__ import annotations

import bz2
import heapq
import io
import logging
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any, BinaryIO

from ..errors import InputError, counted
from .messages import normalize_type
from .readers import _reason, _SkipsDamage, _widened, file_size, register_ros1_type, ros1_typestore

logger = logging.getLogger(__name__)

MAGIC = b"#ROSBAG V2.0\n"

_MESSAGE, _BAG_HEADER, _CHUNK, _CHUNK_INFO, _CONNECTION = 2, 3, 5, 6, 7  # record ops (4, index data, is not read)
_U32, _U64, _TIME = struct.Struct("<I"), struct.Struct("<Q"), struct.Struct("<II")


class BagError(Exception):
    """A record of the bag that does not parse (the reader turns it into :class:`InputError`)."""


@dataclass
class _Chunk:
    """A chunk as its chunk-info record (or a scan) describes it: byte offset, first and last
    message time (ns) and message count per connection id."""

    pos: int
    start_ns: int
    end_ns: int
    counts: dict[int, int] = field(default_factory=dict)
    end: int | None = None
    """Where the records of a chunk left open end (they start at ``pos``); None for a chunk record."""
    cut: bool = False
    """A chunk record that the file's end (at ``end``) cuts off, or still open with its records
    compressed: read as far as its complete records go (:func:`_cut_chunk_contents`)."""


def _fields(header: bytes) -> dict[str, bytes]:
    """A record header's ``name=value`` fields (each preceded by its uint32 length)."""
    fields, pos = {}, 0
    while pos < len(header):
        if pos + 4 > len(header):
            raise BagError("a header field's length is cut off")
        (size,) = _U32.unpack_from(header, pos)
        pos += 4
        name, sep, value = header[pos: pos + size].partition(b"=")
        if not sep or pos + size > len(header):
            raise BagError("a header field does not parse")
        fields[name.decode(errors="replace")] = value
        pos += size
    return fields


def _get(fields: dict[str, bytes], name: str, kind: struct.Struct) -> int:
    try:
        value = kind.unpack(fields[name])
    except (KeyError, struct.error):
        raise BagError(f"a record without a readable {name!r} field") from None
    return value[0] * 1_000_000_000 + value[1] if kind is _TIME else value[0]


def _text(fields: dict[str, bytes], name: str) -> str:
    try:
        return fields[name].decode()
    except (KeyError, UnicodeDecodeError):
        raise BagError(f"a record without a readable {name!r} field") from None


@dataclass
class _Connection:
    """A connection record: id, topic, message type (``pkg/msg/Type``) and its full definition."""

    id: int
    topic: str
    msgtype: str
    definition: str


def _connection(fields: dict[str, bytes], data: bytes) -> _Connection:
    """A connection record: its id and topic in the header, the type and definition in its data."""
    details = _fields(data)
    topic = _text(fields, "topic")  # as written, empty levels dropped (as rosbags and ROS's names do)
    topic = "/" * topic.startswith("/") + "/".join(level for level in topic.split("/") if level)
    return _Connection(_get(fields, "conn", _U32), topic, normalize_type(_text(details, "type")),
                       details.get("message_definition", b"").decode(errors="replace"))


def _read(stream: BinaryIO, size: int) -> bytes:
    """``size`` bytes of ``stream`` (a file, or a chunk's records in memory), checked against
    what is left of it first: a damaged length must not have ``read`` set aside gigabytes."""
    here = stream.tell()
    left = stream.seek(0, 2) - here
    stream.seek(here)
    if size > left:
        raise BagError(f"cut off: {max(left, 0)} of {size} bytes")
    return stream.read(size)


def _record(stream: BinaryIO) -> tuple[dict[str, bytes], int, bytes]:
    """The next record of ``stream``: its header fields, its op and its data."""
    fields = _fields(_read(stream, _U32.unpack(_read(stream, 4))[0]))
    data = _read(stream, _U32.unpack(_read(stream, 4))[0])
    op = fields.get("op", b"")
    if len(op) != 1:
        raise BagError("a record without its op")
    return fields, op[0], data


def _contents(stream: BinaryIO, end: int) -> tuple[list[_Connection], list[tuple[int, int, bytes]]]:
    """The connections and the messages (connection id, log time in ns, data) of the records
    from ``stream``'s position to byte ``end``: a chunk's records, or those of a chunk still open
    when the recording stopped, which C++ rosbag writes uncompressed after the chunk's header."""
    connections, messages = [], []
    while stream.tell() < end:
        fields, op, data = _record(stream)
        if op == _CONNECTION:
            connections.append(_connection(fields, data))
        elif op == _MESSAGE:
            messages.append((_get(fields, "conn", _U32), _get(fields, "time", _TIME), data))
    return connections, messages


def _chunk_contents(fields: dict[str, bytes], data: bytes) -> tuple[list[_Connection], list[tuple[int, int, bytes]]]:
    """:func:`_contents` of a chunk record (its header ``fields`` and data)."""
    records = _decompress(_text(fields, "compression"), data, _get(fields, "size", _U32))
    return _contents(io.BytesIO(records), len(records))


def _cut_chunk_contents(stream: BinaryIO, end: int) -> tuple[list[_Connection], list[tuple[int, int, bytes]]]:
    """:func:`_contents` of the complete records of the chunk record at ``stream``'s position that
    byte ``end`` cuts off: a file cut short in it, or a recording killed while C++ rosbag wrote it
    compressed (its size and length still 0, the compressed stream up to ``end``). Reads what
    ``end`` leaves of its length, or of 64 MB where its length is still 0."""
    fields = _fields(_read(stream, _U32.unpack(_read(stream, 4))[0]))
    if fields.get("op") != bytes([_CHUNK]):
        raise BagError("no chunk record")
    length, left = _U32.unpack(_read(stream, 4))[0], end - stream.tell()
    if 0 < length <= left:
        raise BagError("a chunk that is not cut off")  # damaged otherwise: nothing of it is trusted
    data = stream.read(min(left, length or _CUT_READ))
    records = io.BytesIO(_decompress(_text(fields, "compression"), data, 0, cut=True))
    connections, messages = [], []
    try:
        while True:
            fields, op, data = _record(records)
            if op == _CONNECTION:
                connections.append(_connection(fields, data))
            elif op == _MESSAGE:
                messages.append((_get(fields, "conn", _U32), _get(fields, "time", _TIME), data))
    except BagError:  # the record the cut falls in (or the end of the records)
        return connections, messages


_STEP = 1 << 22
"""Bytes a chunk is decompressed by at a time (lz4 sets its output limit aside at once: a 4 GB size
field read as the limit took 4 GB; 4 MB costs a 24 MB chunk 9 ms more than decompressing it whole)."""

_CUT_READ = 64 << 20
"""Bytes read at most of a chunk still open (its length unknown, :func:`_cut_chunk_contents`), and
decompressed at most from a chunk cut off."""

_MAX_RATIO = 1000
"""A compressed chunk may say it holds at most this many times its compressed bytes (or 64 MB,
whichever is more): bz2 turns 1.4 KB of a crafted file into 3 GB of zeros. Real chunks hold about
768 KB; images and point clouds compress far less than this."""


def _decompress(compression: str, data: bytes, size: int, *, cut: bool = False) -> bytes | bytearray:
    """A chunk's records, decompressed (``size``: their length, as its header gives it). Output
    comes :data:`_STEP` bytes at a time and stops once past ``size``, and ``size`` is held to
    :data:`_MAX_RATIO`, so that neither a crafted chunk nor a damaged ``size`` fills the memory.
    ``cut``: ``data`` is cut off, its size unknown; what it decompresses to, up to :data:`_CUT_READ`
    bytes (a chunk as rosbag writes them holds about 768 KB)."""
    bound = max(64 << 20, _MAX_RATIO * len(data))
    if cut:
        size = _CUT_READ
    if compression == "none":
        out = data
    elif compression in ("bz2", "lz4"):
        if size > bound:
            raise BagError(f"a chunk of {len(data)} compressed bytes says it holds {size}, more than "
                           f"{_MAX_RATIO} times as many")
        if compression == "bz2":
            decompressor = bz2.BZ2Decompressor()
        else:
            import lz4.frame  # installed with rosbags

            decompressor = lz4.frame.LZ4FrameDecompressor()
        out, pending = bytearray(), data
        try:
            while not decompressor.eof and len(out) <= size:
                out += decompressor.decompress(pending, max_length=_STEP)
                if decompressor.needs_input and not decompressor.eof:
                    if cut:
                        return out
                    raise BagError("a chunk's compressed data is cut off")
                pending = b""
        except BagError:
            raise
        except Exception as exc:  # OSError from bz2, RuntimeError from lz4
            raise BagError(f"a chunk does not decompress ({_reason(exc)})") from None
    else:
        raise BagError(f"chunk compression {compression!r} is not bz2, lz4 or none")
    if cut:
        return out
    if len(out) > size:
        raise BagError(f"a chunk holds more than the {size} bytes its header says")
    if len(out) < size:
        raise BagError(f"a chunk holds {len(out)} bytes, its header says {size}")
    return out


class Ros1Bag(_SkipsDamage):
    """A ROS 1 bag (v2.0). Interface of the readers in :mod:`~terrainmap.sources.readers`: its
    ``paths``, ``types`` (topic → message type), ``counts`` (topic → messages), ``span_ns``,
    ``damage`` and ``skipped``, and :meth:`messages` in log-time order.

    With an index, a chunk that cannot be read or decompressed is skipped with a warning (and
    noted in :attr:`skipped`), as an indexed MCAP's is; without one, damage ends the messages
    where the scan at open stopped. A message that cannot be decoded is skipped, in any bag."""

    format = "ros1-bag"

    def __init__(self, path: Path):
        self.path = path
        self.paths = [path]
        self.skipped_parts: dict[Any, str] = {}
        self.damage: str | None = None
        self._connections: dict[int, _Connection] = {}
        self._chunks: list[_Chunk] = []
        self._scan_error: str | None = None  # why the scan of a bag without an index stopped
        self.opened_size = file_size(path)
        try:
            with open(path, "rb") as stream:
                if (magic := stream.readline(64)) != MAGIC:
                    version = magic[len(b"#ROSBAG V"):].strip().decode(errors="backslashreplace")  # (bytes shown)
                    raise BagError(f"format {version}, not 2.0" if magic.startswith(b"#ROSBAG V") else
                                   "an empty file" if not magic else "no '#ROSBAG V2.0' line at its start")
                fields, op, _ = _record(stream)  # its data: padding
                if op != _BAG_HEADER:
                    raise BagError("no bag header record after the version line")
                if encryptor := fields.get("encryptor", b"").decode(errors="replace"):
                    raise BagError(f"encrypted ({encryptor}); `rosbag decrypt` writes a plain copy")
                index_pos = _get(fields, "index_pos", _U64)
                data_start, end = stream.tell(), stream.seek(0, 2)
                indexed = 0 < index_pos < end
                if not indexed:
                    logger.info("%s: no index (the recording was cut short); scanning the bag", path)
                if not (indexed and self._read_index(stream, fields, index_pos)):
                    stream.seek(data_start)
                    self._scan(stream, index_pos if indexed else end)
        except OSError as exc:
            raise InputError(f"{path}: cannot read the bag ({exc.strerror or exc})") from None
        except BagError as exc:
            raise InputError(f"{path}: not a readable ROS 1 bag ({exc})") from None
        self._typestore = ros1_typestore()
        for c in self._connections.values():
            try:
                register_ros1_type(self._typestore, c.msgtype, c.definition)
            except Exception as exc:  # a definition rosbags cannot parse: only its topic is unreadable
                logger.info("%s: topic %s: cannot parse the definition of %s (%s)", path, c.topic, c.msgtype,
                            _reason(exc))
        self.types = {c.topic: c.msgtype for c in self._connections.values()}
        self.counts = dict.fromkeys(self.types, 0)
        self.span_ns: tuple[int, int] | None = None
        for chunk in self._chunks:
            for cid, n in chunk.counts.items():
                if cid in self._connections:  # a message of a connection the bag never defines cannot be read
                    self.counts[self._connections[cid].topic] += n
            if chunk.counts:
                self.span_ns = _widened(self.span_ns, chunk.start_ns, chunk.end_ns)

    def _read_index(self, stream: BinaryIO, header: dict[str, bytes], index_pos: int) -> bool:
        """Connections and chunk infos from the index at ``index_pos``; False (and a note in
        :attr:`damage`) when it does not parse, for :meth:`_scan` to take over."""
        try:
            stream.seek(index_pos)
            for _ in range(_get(header, "conn_count", _U32)):
                fields, op, data = _record(stream)
                if op != _CONNECTION:
                    raise BagError("the index holds a record other than a connection")
                c = _connection(fields, data)
                self._connections.setdefault(c.id, c)
            for _ in range(_get(header, "chunk_count", _U32)):
                fields, op, data = _record(stream)
                if op != _CHUNK_INFO or _get(fields, "ver", _U32) != 1:
                    raise BagError("the index holds a record other than a chunk info (version 1)")
                counts = dict(struct.iter_unpack("<II", data[: len(data) // 8 * 8]))
                self._chunks.append(_Chunk(_get(fields, "chunk_pos", _U64), _get(fields, "start_time", _TIME),
                                           _get(fields, "end_time", _TIME), counts))
            if stream.read(1):  # the index ends the file: more records than counted, a header that lost count
                raise BagError(f"it holds more records than the bag header counts ({_get(header, 'conn_count', _U32)} "
                               f"connections, {_get(header, 'chunk_count', _U32)} chunks)")
        except BagError as exc:
            self.damage = f"{self.path}: its index is damaged ({exc}); reading the bag from start to end"
            logger.warning("%s", self.damage)
            self._connections, self._chunks = {}, []
            return False
        for chunk in self._chunks:  # an index that names no connection of the bag lost the messages it held
            if unknown := sorted(set(chunk.counts) - self._connections.keys()):
                self.damage = (f"{self.path}: the index of the chunk at byte {chunk.pos} names connection "
                               f"{', '.join(map(str, unknown))}, which the bag does not define")
                logger.warning("%s: messages of that chunk may be lost", self.damage)
                for cid in unknown:
                    del chunk.counts[cid]
        return True

    def _scan(self, stream: BinaryIO, end: int) -> None:
        """Connections and chunks of a bag without a usable index, read from the first record
        after the bag header to byte ``end`` (where a damaged index begins, else the file's end)
        or to the first record that does not read (noted in :attr:`damage`; :meth:`messages`
        ends there). The records of a chunk still open when the recording stopped, which C++
        rosbag writes uncompressed after the chunk's header, make chunks of their own
        (``_Chunk.end``), of up to :data:`_STEP` bytes each."""
        messages, loose = 0, None
        try:
            while (pos := stream.tell()) < end:
                fields, op, data = _record(stream)
                if op == _CONNECTION:
                    c = _connection(fields, data)
                    self._connections.setdefault(c.id, c)
                    continue  # within an open chunk's records too
                if op == _MESSAGE:
                    if loose is None or stream.tell() - loose.pos > _STEP:
                        loose = _Chunk(pos, 0, 0)
                        self._chunks.append(loose)
                    loose.end = stream.tell()
                    contents = [(_get(fields, "conn", _U32), _get(fields, "time", _TIME), data)]
                else:
                    loose = None
                    if op != _CHUNK:
                        continue
                    connections, contents = _chunk_contents(fields, data)
                    for c in connections:
                        self._connections.setdefault(c.id, c)
                    if not contents:
                        continue
                    self._chunks.append(_Chunk(pos, 0, 0))
                chunk = self._chunks[-1]
                for cid, t, _ in contents:
                    chunk.start_ns, chunk.end_ns = _widened((chunk.start_ns, chunk.end_ns) if chunk.counts else None, t, t)
                    chunk.counts[cid] = chunk.counts.get(cid, 0) + 1
                messages += len(contents)
        except BagError as exc:
            messages += self._cut_chunk(stream, pos, end)
            self._scan_error = str(exc)
            self.damage = f"{self.path}: truncated or corrupt after {counted(messages, 'message')} ({exc})"
            logger.info("%s", self.damage)  # not a warning: ``info`` shows it, reading the messages raises it

    def _cut_chunk(self, stream: BinaryIO, pos: int, end: int) -> int:
        """The chunk record at ``pos`` where the scan failed, if it is one that ``end`` cuts off:
        its complete messages, as a chunk of their own; how many."""
        stream.seek(pos)
        try:
            connections, contents = _cut_chunk_contents(stream, end)
        except BagError:  # no chunk, or one whose header is cut off too
            return 0
        for c in connections:
            self._connections.setdefault(c.id, c)
        if contents:
            chunk = _Chunk(pos, min(t for _, t, _ in contents), max(t for _, t, _ in contents), end=end, cut=True)
            for cid, _, _ in contents:
                chunk.counts[cid] = chunk.counts.get(cid, 0) + 1
            self._chunks.append(chunk)
        return len(contents)

    def messages(self, topics: list[str]) -> Iterator[tuple[str, int, Any]]:
        """(topic, log_time_ns, decoded message) of ``topics`` in log-time order (:meth:`_SkipsDamage._decoded`)."""
        return self._decoded(self._records(topics), topics, "bag")

    def _records(self, topics: list[str]) -> Iterator[tuple[str, int, str, Any]]:
        """(topic, log time, type, decode) of ``topics``, from the chunks that hold them. A heap of
        chunks (keyed by their first message's time) and of the messages of the chunks opened so
        far: a chunk opens before any message at or after its start time is yielded, so only the
        chunks that overlap in time are held at once."""
        wanted = {cid for cid, c in self._connections.items() if c.topic in topics}
        heap: list[tuple] = [(c.start_ns, 0, c.pos, -1, c) for c in self._chunks if wanted & c.counts.keys()]
        heapq.heapify(heap)
        with open(self.path, "rb") as stream:
            while heap:
                *_, pos, index, item = heapq.heappop(heap)
                if index >= 0:
                    yield item
                    continue
                try:
                    stream.seek(pos)
                    if item.cut:
                        _, contents = _cut_chunk_contents(stream, item.end)
                    elif item.end is not None:  # the records of a chunk left open
                        _, contents = _contents(stream, item.end)
                    else:
                        fields, op, data = _record(stream)
                        if op != _CHUNK:
                            raise BagError("no chunk record where the index points")
                        _, contents = _chunk_contents(fields, data)
                except BagError as exc:
                    self._skip(pos, f"chunk at byte {pos}, log time {item.start_ns / 1e9:.3f}–{item.end_ns / 1e9:.3f} s", exc)
                    continue
                for i, (cid, t, body) in enumerate(contents):
                    if cid not in wanted:
                        continue
                    c = self._connections[cid]
                    if not item.start_ns <= t <= item.end_ns:  # messages before it have been yielded already
                        self._skip(("message", c.topic, t), f"{c.topic} message at log time {t / 1e9:.3f} s",
                                   BagError(f"outside its chunk's span in the index, {item.start_ns / 1e9:.3f}–"
                                            f"{item.end_ns / 1e9:.3f} s"))
                        continue
                    decode = partial(self._typestore.deserialize_ros1, body, c.msgtype)
                    heapq.heappush(heap, (t, 1, pos, i, (c.topic, t, c.msgtype, decode)))
        if self._scan_error is not None:
            raise BagError(self._scan_error)
