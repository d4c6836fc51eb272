"""The streaming ROS 1 bag reader, against ``rosbags``' reader and writer (an independent
implementation of the format)."""

import bz2
import random
import struct
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag1 import Reader, Writer
from rosbags.typesys import Stores, get_typestore

from terrainmap.errors import InputError
from terrainmap.sources.ros1bag import Ros1Bag

STORE = get_typestore(Stores.ROS1_NOETIC)
STRING = STORE.types["std_msgs/msg/String"]
TOPICS = ["/a", "/b"]


def _fields_bytes(**fields: bytes) -> bytes:
    """``name=value`` fields, each preceded by its length: a record's header, a connection's data."""
    return b"".join(struct.pack("<I", len(k) + 1 + len(v)) + k.encode() + b"=" + v for k, v in fields.items())


def _record(data: bytes = b"", **fields: bytes) -> bytes:
    """A record with these header fields and ``data``."""
    header = _fields_bytes(**fields)
    return struct.pack("<I", len(header)) + header + struct.pack("<I", len(data)) + data


def write_bag(path: Path, n: int, *, compression=None, chunk_bytes: int = 300, shuffle: int = 0, seed: int = 0) -> Path:
    """A bag of ``n`` std_msgs/String messages alternating between /a and /b, 1 ms apart, in
    chunks of about ``chunk_bytes``; ``shuffle``: each message's time moved by up to that many
    ms, so that chunks overlap in time and messages come out of order."""
    rng = random.Random(seed)
    writer = Writer(path)
    if compression is not None:
        writer.set_compression(compression)
    writer.chunk_threshold = chunk_bytes
    writer.open()
    connections = {t: writer.add_connection(t, "std_msgs/msg/String", typestore=STORE) for t in TOPICS}
    for k in range(n):
        t = 10**12 + (k + rng.randint(-shuffle, shuffle)) * 1_000_000
        writer.write(connections[TOPICS[k % 2]], t, STORE.serialize_ros1(STRING(data=f"m{k}"), STRING.__msgtype__))
    writer.close()
    return path


def read(bag: Ros1Bag, topics=TOPICS) -> list[tuple[str, int, str]]:
    """(topic, time, text) of the messages, in log-time order (checked), ties in file order
    (put into ``rosbags``' order, :func:`expected`, by a stable sort by time and topic)."""
    got = [(topic, t, msg.data) for topic, t, msg in bag.messages(topics)]
    assert [t for _, t, _ in got] == sorted(t for _, t, _ in got)
    return sorted(got, key=lambda m: m[1::-1])


def expected(path: Path, topics=TOPICS) -> list[tuple[str, int, str]]:
    """What ``rosbags``' reader reads, in its log-time order (ties: by topic, then in file order)."""
    with Reader(path) as reader:
        return [(c.topic, t, STORE.deserialize_ros1(raw, c.msgtype).data)
                for c, t, raw in reader.messages([c for c in reader.connections if c.topic in topics])]


def test_topics_are_named_as_written(tmp_path):
    """``a`` and ``/a`` are two topics (the old reader, rosbags', kept them apart too)."""
    path = tmp_path / "x.bag"
    writer = Writer(path)
    writer.open()
    connections = [writer.add_connection(t, "std_msgs/msg/String", typestore=STORE) for t in ("a", "/a", "//b/")]
    for k in range(6):
        writer.write(connections[k % 3], 10**12 + k, STORE.serialize_ros1(STRING(data=f"m{k}"), STRING.__msgtype__))
    writer.close()
    bag = Ros1Bag(path)
    assert bag.counts == {"a": 2, "/a": 2, "/b": 2}
    for topic in bag.counts:
        assert read(bag, [topic]) == expected(path, [topic])


@pytest.mark.parametrize("compression", [None, Writer.CompressionFormat.BZ2, Writer.CompressionFormat.LZ4])
def test_messages_types_counts_and_span_as_rosbags_reads_them(tmp_path, compression):
    path = write_bag(tmp_path / "x.bag", 400, compression=compression, shuffle=5)
    bag = Ros1Bag(path)
    assert len(bag._chunks) > 20  # overlapping in time: the merge is exercised
    ours = read(bag)
    assert ours == expected(path)
    assert read(bag, ["/b"]) == expected(path, ["/b"])
    with Reader(path) as reader:
        assert bag.counts == {"/a": 200, "/b": 200} == {c.topic: c.msgcount for c in reader.connections}
        assert bag.span_ns == (reader.start_time, reader.end_time - 1)
    assert bag.types == {"/a": "std_msgs/msg/String", "/b": "std_msgs/msg/String"}
    assert bag.damage is None and bag.skipped == []


def _peak_bytes(path: Path) -> int:
    tracemalloc.start()
    try:
        bag = Ros1Bag(path)
        for _ in bag.messages(["/a"]):
            pass
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_memory_is_flat_in_the_number_of_messages(tmp_path):
    """No per-message index is held: 4 times the messages, not 4 times the memory (rosbags'
    reader holds about 175 bytes a message, 7 MB for the larger bag)."""
    small = _peak_bytes(write_bag(tmp_path / "small.bag", 10_000, chunk_bytes=65536))
    large = _peak_bytes(write_bag(tmp_path / "large.bag", 40_000, chunk_bytes=65536))
    assert large < small + 500_000 and large < 2_000_000, (small, large)


def _index_pos_field(data: bytes) -> int:
    """Where the bag header's 8-byte ``index_pos`` value lies in the file."""
    return data.index(b"index_pos=") + len(b"index_pos=")


def _index_records(data: bytes):
    """(header, where its data begins) of the records of the index, from ``index_pos`` to the end."""
    at = _index_pos_field(data)
    pos = int.from_bytes(data[at: at + 8], "little")
    while pos < len(data):
        (size,) = struct.unpack_from("<I", data, pos)
        header, data_at = bytes(data[pos + 4: pos + 4 + size]), pos + 4 + size + 4
        yield header, data_at
        pos = data_at + struct.unpack_from("<I", data, data_at - 4)[0]


def test_a_bag_without_its_index_is_scanned(tmp_path):
    """A recording cut off before its index was written (index_pos 0) is read from start to end."""
    path = write_bag(tmp_path / "x.bag", 200, shuffle=3)
    data = bytearray(path.read_bytes())
    at = _index_pos_field(data)
    data[at: at + 8] = bytes(8)
    (tmp_path / "noindex.bag").write_bytes(data)
    bag = Ros1Bag(tmp_path / "noindex.bag")
    assert read(bag) == expected(path) and bag.counts == {"/a": 100, "/b": 100} and bag.damage is None


def test_a_bag_whose_index_is_damaged_is_scanned_up_to_the_index(tmp_path, caplog):
    """Every chunk is whole: all messages are read, and the scan stops where the index begins."""
    path = write_bag(tmp_path / "x.bag", 200, shuffle=3)
    data = bytearray(path.read_bytes())
    at = _index_pos_field(data)
    index = int.from_bytes(data[at: at + 8], "little")
    data[index + 4: index + 40] = b"\xee" * 36  # the first connection record's header
    (tmp_path / "bad.bag").write_bytes(data)
    bag = Ros1Bag(tmp_path / "bad.bag")
    assert bag.damage.startswith(f"{tmp_path / 'bad.bag'}: its index is damaged (")
    assert bag.damage.endswith("reading the bag from start to end") and "its index is damaged" in caplog.text
    assert read(bag) == expected(path) and bag.counts == {"/a": 100, "/b": 100}


def _killed_recording(path: Path, closed: int, open_: int) -> Path:
    """A recording killed as C++ rosbag leaves it: index_pos 0, ``closed`` messages in a closed
    (uncompressed) chunk, then the open chunk: its header with size 0 and no data, and its
    records (a connection, ``open_`` messages) written raw after it."""
    definition = STORE.generate_msgdef("std_msgs/msg/String", ros_version=1)[0].encode()
    connection = _record(_fields_bytes(topic=b"/a", type=b"std_msgs/String", md5sum=b"0" * 32,
                                       message_definition=definition), op=b"\x07", conn=struct.pack("<I", 0), topic=b"/a")
    def message(k):
        data = STORE.serialize_ros1(STRING(data=f"m{k}"), STRING.__msgtype__)
        return _record(data, op=b"\x02", conn=struct.pack("<I", 0), time=struct.pack("<II", 1000, k * 1_000_000))
    closed_records = connection + b"".join(message(k) for k in range(closed))
    path.write_bytes(b"#ROSBAG V2.0\n" + _record(op=b"\x03", index_pos=bytes(8), conn_count=bytes(4), chunk_count=bytes(4))
                     + _record(closed_records, op=b"\x05", compression=b"none", size=struct.pack("<I", len(closed_records)))
                     + _record(op=b"\x05", compression=b"none", size=bytes(4))
                     + b"".join(message(k) for k in range(closed, closed + open_)))
    return path


def test_a_recording_killed_keeps_the_messages_of_its_open_chunk(tmp_path):
    bag = Ros1Bag(_killed_recording(tmp_path / "killed.bag", 5, 4))
    assert bag.damage is None and bag.counts == {"/a": 9}
    assert [m.data for _, _, m in bag.messages(["/a"])] == [f"m{k}" for k in range(9)]
    cut = tmp_path / "cut.bag"  # cut inside the open chunk's last message: the three before it are read
    cut.write_bytes((tmp_path / "killed.bag").read_bytes()[:-5])
    bag = Ros1Bag(cut)
    assert bag.counts == {"/a": 8} and "truncated or corrupt after 8 messages" in bag.damage
    got = []
    with pytest.raises(InputError, match="cut off"):
        for _, _, m in bag.messages(["/a"]):
            got.append(m.data)
    assert got == [f"m{k}" for k in range(8)]


@pytest.mark.parametrize("compression", ["none", "bz2", "lz4"])
def test_a_chunk_cut_off_keeps_its_complete_messages(tmp_path, compression):
    """C++ rosbag writes an open chunk through its compressor: the chunk's header (size and length
    still 0), then the compressed stream, which a killed recording cuts off; a closed chunk (its
    size and length written) can be cut off by the file's end too. Their complete messages are
    read (for bz2 and lz4, those of the compressed blocks that are whole), then the damage is named."""
    import lz4.frame

    open_header = _record(op=b"\x05", compression=b"none", size=bytes(4))
    killed = _killed_recording(tmp_path / "plain.bag", 5, 0).read_bytes()  # a closed chunk of m0..m4, then the open one
    closed_part = killed[: -len(open_header)]
    rng = random.Random(0)
    texts = [f"m{k}" for k in range(5)] + [f"m{k} " + "".join(rng.choices("abcdefgh", k=2000)) for k in range(5, 300)]
    records = b"".join(_record(STORE.serialize_ros1(STRING(data=texts[k]), STRING.__msgtype__), op=b"\x02",
                               conn=struct.pack("<I", 0), time=struct.pack("<II", 1000, k * 1_000_000))
                       for k in range(5, 300))  # 590 KB: blocks of 100 KB (bz2 -1), 64 KB (lz4) decompress whole
    stream = {"none": records, "bz2": bz2.compress(records, 1), "lz4": lz4.frame.compress(records)}[compression]
    open_chunk = _record(op=b"\x05", compression=compression.encode(), size=bytes(4)) + stream
    closed_chunk = _record(stream, op=b"\x05", compression=compression.encode(), size=struct.pack("<I", len(records)))
    for name, chunk in (("open", open_chunk), ("closed", closed_chunk)):
        path = tmp_path / f"{name}.bag"
        path.write_bytes(closed_part + chunk[: len(chunk) * 2 // 3])
        got = []
        with pytest.raises(InputError, match="truncated or corrupt"):
            for _, _, m in Ros1Bag(path).messages(["/a"]):
                got.append(m.data)
        assert got == texts[: len(got)] and 5 + 100 < len(got) < 300, name


def test_a_bag_cut_short_is_read_up_to_the_cut_then_named(tmp_path):
    path = write_bag(tmp_path / "x.bag", 200)
    cut = tmp_path / "cut.bag"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    bag = Ros1Bag(cut)
    assert bag.damage.startswith(f"{cut}: truncated or corrupt after ") and 0 < sum(bag.counts.values()) < 200
    got = []
    with pytest.raises(InputError, match=rf"^{cut}: bag is truncated or corrupt after \d+ messages of /a, /b \("):
        for topic, t, message in bag.messages(TOPICS):
            got.append((topic, t, message.data))
    assert got == expected(path)[: len(got)] and len(got) == sum(bag.counts.values())  # no shuffle: no ties


def test_a_damaged_chunk_of_an_indexed_bag_is_skipped(tmp_path, caplog):
    """bz2 checks its data: a chunk whose bytes changed is skipped with a warning, the others read."""
    path = write_bag(tmp_path / "x.bag", 200, compression=Writer.CompressionFormat.BZ2)
    bag = Ros1Bag(path)
    third = sorted(c.pos for c in bag._chunks)[3]
    data = bytearray(path.read_bytes())
    data[third + 120: third + 160] = b"\x55" * 40  # inside the compressed data
    (tmp_path / "bad.bag").write_bytes(data)
    bad = Ros1Bag(tmp_path / "bad.bag")
    got = read(bad)
    assert 0 < len(expected(path)) - len(got) < 20 and set(got) < set(expected(path))
    (line,) = bad.skipped
    assert line.startswith(f"{tmp_path / 'bad.bag'}: chunk at byte {third}, log time ") and "damaged, skipped" in caplog.text


def test_a_chunk_is_decompressed_no_further_than_its_header_says(tmp_path, caplog):
    """A chunk that holds more than its header's ``size`` (a crafted one could fill the memory)
    is damage: decompression stops one byte past it."""
    path = write_bag(tmp_path / "x.bag", 200, compression=Writer.CompressionFormat.BZ2, chunk_bytes=4096)
    data = bytearray(path.read_bytes())
    at = data.index(b"\x09\x00\x00\x00size=") + 9  # the first chunk's uncompressed size
    data[at: at + 4] = struct.pack("<I", 100)
    (tmp_path / "bad.bag").write_bytes(data)
    bad = Ros1Bag(tmp_path / "bad.bag")
    assert 0 < len(expected(path)) - len(read(bad)) < 200
    (line,) = bad.skipped
    assert "a chunk holds more than the 100 bytes its header says" in line


def test_a_damaged_length_allocates_nothing_like_it(tmp_path):
    """A record header's length of 4 GiB (4 bytes changed): named as cut off, without reading
    (``read(n)`` sets n bytes aside first)."""
    path = write_bag(tmp_path / "x.bag", 20)
    data = bytearray(path.read_bytes())
    data[13:17] = struct.pack("<I", 0xFFFFFFF0)  # the bag header record's header length
    (tmp_path / "bad.bag").write_bytes(data)
    tracemalloc.start()
    try:
        with pytest.raises(InputError, match=r"bad.bag: not a readable ROS 1 bag \(cut off: \d+ of 4294967280 bytes\)"):
            Ros1Bag(tmp_path / "bad.bag")
        assert tracemalloc.get_traced_memory()[1] < 1_000_000
    finally:
        tracemalloc.stop()


def _changed(path: Path, dst: Path, find: bytes, nth: int, at: int, value: int) -> Path:
    """``path`` with byte ``at`` after the ``nth`` occurrence of ``find`` set to ``value``."""
    data = bytearray(path.read_bytes())
    where = -1
    for _ in range(nth + 1):
        where = data.index(find, where + 1)
    data[where + at] = value
    dst.write_bytes(data)
    return dst


def test_a_bag_header_that_counts_too_few_chunks_does_not_hide_the_rest(tmp_path, caplog):
    """The index ends the file: records past those the header counts mean the header lost count,
    and the bag is read from start to end, every message found (not only the counted chunks')."""
    path = write_bag(tmp_path / "x.bag", 60)
    counted = Ros1Bag(path)
    assert len(counted._chunks) > 2
    short = Ros1Bag(_changed(path, tmp_path / "short.bag", b"chunk_count=", 0, 12, 1))  # its low byte: 1 chunk
    assert "holds more records than the bag header counts (2 connections, 1 chunks)" in short.damage
    assert read(short) == expected(path)


def test_a_message_record_without_its_fields_loses_its_chunk_only(tmp_path, caplog):
    path = write_bag(tmp_path / "x.bag", 60)
    bad = Ros1Bag(_changed(path, tmp_path / "bad.bag", b"conn=", 30, 1, ord("X")))  # 'cXnn=' in a message
    got = read(bad)
    assert 0 < len(expected(path)) - len(got) < 20 and set(got) < set(expected(path))
    (line,) = bad.skipped
    assert "chunk at byte" in line and "a record without a readable 'conn' field" in line


def test_a_message_stamped_outside_its_chunks_span_is_skipped(tmp_path, caplog):
    """Its time changed (1 s earlier): messages after it would have come out before it, so it is
    skipped, named, and the rest keep their log-time order (:func:`read` checks it)."""
    path = write_bag(tmp_path / "x.bag", 60)
    bad = Ros1Bag(_changed(path, tmp_path / "bad.bag", b"time=", 30, 5, 0xE7))  # its seconds' low byte: 1000 → 999
    got = read(bad)
    assert len(got) == 59 and set(got) < set(expected(path))
    (line,) = bad.skipped
    assert "message at log time 999." in line and "outside its chunk's span in the index" in line


def test_a_decompression_bomb_is_refused_before_it_is_decompressed(tmp_path):
    """A chunk of a few hundred bytes of bz2 that says (and holds) 128 MB of zeros."""
    size = 128 << 20
    compressor = bz2.BZ2Compressor(9)
    payload = b"".join(compressor.compress(bytes(16 << 20)) for _ in range(8)) + compressor.flush()
    path = tmp_path / "bomb.bag"
    path.write_bytes(b"#ROSBAG V2.0\n" + _record(op=b"\x03", index_pos=bytes(8), conn_count=bytes(4), chunk_count=bytes(4))
                     + _record(op=b"\x05", compression=b"bz2", size=struct.pack("<I", size), data=payload))
    tracemalloc.start()
    try:
        bag = Ros1Bag(path)
        assert tracemalloc.get_traced_memory()[1] < 10_000_000
    finally:
        tracemalloc.stop()
    assert f"a chunk of {len(payload)} compressed bytes says it holds {size}, more than 1000 times as many" in bag.damage


def test_an_index_that_names_an_unknown_connection_is_damage(tmp_path, caplog):
    """A chunk-info record whose data is garbage names connections the bag lacks: that chunk's
    counts would be lost without a word."""
    path = write_bag(tmp_path / "x.bag", 20)
    data = bytearray(path.read_bytes())
    data_at = next(at for header, at in _index_records(data) if b"op=\x06" in header)  # the first chunk info
    data[data_at: data_at + 4] = struct.pack("<I", 0xFFFFFFFF)  # its first (connection id, count) pair
    (tmp_path / "bad.bag").write_bytes(data)
    bag = Ros1Bag(tmp_path / "bad.bag")
    assert bag.damage.startswith(f"{tmp_path / 'bad.bag'}: the index of the chunk at byte ")
    assert "names connection 4294967295" in bag.damage and "messages of that chunk may be lost" in caplog.text


@pytest.mark.parametrize("data, why", [(b"", "an empty file"), (b"#ROSBAG V1.2\n", r"format 1.2, not 2.0"),
                                       (b"#ROSBAG V2\x8e0\n", r"format 2\\x8e0, not 2.0"),  # a damaged byte, shown
                                       (b"<html>\n", "no '#ROSBAG V2.0' line at its start"),
                                       (b"#ROSBAG V2.0\n\x10\x00\x00\x00abc", "cut off"),
                                       (b"#ROSBAG V2.0\n" + _record(op=b"\x03", encryptor=b"aes"), r"encrypted \(aes\)")])
def test_what_is_no_bag_is_named(tmp_path, data, why):
    path = tmp_path / "x.bag"
    path.write_bytes(data)
    with pytest.raises(InputError, match=rf"^{path}: not a readable ROS 1 bag \(.*{why}"):
        Ros1Bag(path)


def test_a_bag_of_ros1_tf_messages_places_the_cameras(tmp_path):
    """``tf/tfMessage`` (ROS 1's tf before tf2) on ``/tf``, as older bags and static_transform_publisher
    record the mount and the stereo pose: both are read, the stereo pose where the camera infos
    give no baseline (right Tx = 0), though the mount came first."""
    from rosbags.typesys import get_types_from_msg

    from terrainmap.sources import open_source

    store = get_typestore(Stores.ROS1_NOETIC)
    store.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf/msg/tfMessage"))
    t = store.types
    path, t0 = tmp_path / "old_tf.bag", 10**18

    def header(frame):
        return t["std_msgs/msg/Header"](seq=0, stamp=t["builtin_interfaces/msg/Time"](sec=t0 // 10**9, nanosec=0),
                                        frame_id=frame)

    def tf(parent, child, xyz, q):
        transform = t["geometry_msgs/msg/Transform"](translation=t["geometry_msgs/msg/Vector3"](*xyz),
                                                     rotation=t["geometry_msgs/msg/Quaternion"](*q))
        return t["tf/msg/tfMessage"](transforms=[t["geometry_msgs/msg/TransformStamped"](
            header=header(parent), child_frame_id=child, transform=transform)])

    def info(frame):
        roi = t["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        return t["sensor_msgs/msg/CameraInfo"](
            header=header(frame), height=6, width=8, distortion_model="plumb_bob", D=np.zeros(5),
            K=np.array([400.0, 0, 4, 0, 400, 3, 0, 0, 1]), R=np.eye(3).ravel(),
            P=np.array([400.0, 0, 4, 0, 0, 400, 3, 0, 0, 0, 1, 0]), binning_x=0, binning_y=0, roi=roi)

    def image(frame, seed):
        pixels = np.random.default_rng(seed).integers(0, 255, 48, dtype=np.uint8)
        return t["sensor_msgs/msg/Image"](header=header(frame), height=6, width=8, encoding="mono8", is_bigendian=0,
                                          step=8, data=pixels)

    optical = (-0.5, 0.5, -0.5, 0.5)
    messages = [("/tf", "tf/msg/tfMessage", tf("base_link", "left_optical", (0.0, 0.0, 1.65), optical)),
                ("/tf", "tf/msg/tfMessage", tf("left_optical", "right_optical", (0.3, 0.0, 0.0), (0, 0, 0, 1))),
                *[(f"/stereo/{side}/camera_info", "sensor_msgs/msg/CameraInfo", info(f"{side}_optical"))
                  for side in ("left", "right")],
                *[(f"/stereo/{side}/image_rect", "sensor_msgs/msg/Image", image(f"{side}_optical", k))
                  for k, side in enumerate(("left", "right"))]]
    writer = Writer(path)
    writer.open()
    connections = {}
    for topic, kind, message in messages:
        if topic not in connections:
            connections[topic] = writer.add_connection(topic, kind, typestore=store)
        writer.write(connections[topic], t0, store.serialize_ros1(message, kind))
    writer.close()
    with open_source(path) as source:
        frame = next(source.frames())
    assert frame.extrinsics.source == "tf" and frame.extrinsics.translation[2] == pytest.approx(1.65)
    assert frame.calibration.baseline_m == pytest.approx(0.3)


def test_a_folder_of_split_bags_is_one_log_read_in_name_order(tmp_path):
    """``rosbag record --split`` writes run_0.bag, run_1.bag, ...: read one after the other, numbers
    by value (2 before 10); a folder with an image layout stays an image folder."""
    from terrainmap.errors import NoStereoError
    from terrainmap.sources import open_source, source_class
    from terrainmap.sources.log import Ros1BagSource
    from terrainmap.sources.readers import SplitLog

    folder = tmp_path / "run"
    folder.mkdir()
    for k in (2, 10):  # 10 sorts before 2 as text
        write_bag(folder / f"run_{k}.bag", 4, seed=k)
    write_bag(folder / "run_11.bag.active", 4, seed=11)  # the one it was writing when the recording was killed
    (folder / "._run_2.bag").write_bytes(b"\x00\x05\x16\x07 macOS resource fork")
    assert source_class(folder) is Ros1BagSource
    with pytest.raises(NoStereoError) as exc:  # strings, no images: described all the same
        open_source(folder)
    names = ["run_2.bag", "run_10.bag", "run_11.bag.active"]
    assert exc.value.contents["files"] == [str(folder / name) for name in names]
    assert exc.value.contents["topics"] == [{"topic": t, "type": "std_msgs/msg/String", "count": 6} for t in TOPICS]
    parts = [Ros1Bag(folder / name) for name in names]
    assert [m.data for _, _, m in SplitLog(folder, parts).messages(TOPICS)] == [
        m.data for part in parts for _, _, m in part.messages(TOPICS)]
    images = tmp_path / "images"
    for side in ("left", "right"):
        (images / side).mkdir(parents=True)
    (images / "calibration.yaml").write_text("width: 8\n")
    write_bag(images / "stray.bag", 2)
    assert source_class(images) is not Ros1BagSource
    hidden = tmp_path / "hidden"  # resource forks alone are no bags
    hidden.mkdir()
    (hidden / "._run_0.bag").write_bytes(b"\x00\x05\x16\x07")
    with pytest.raises(InputError, match="not a known stereo source"):
        source_class(hidden)
