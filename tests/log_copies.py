"""Copies of logs in other formats, made by other libraries than terrainmap: rosbag2 bags in other
storage and compression (``rosbags``' writer), ROS 1 bags (``rosbags``' converter) and ROS 1 MCAP
(the ``mcap`` writer, as ``mcap convert`` makes it from a bag)."""

from __future__ import annotations

from pathlib import Path


def rewrite_rosbag2(src: Path, dst: Path, *, storage: str = "sqlite3", compression: str = "none",
                    keep=lambda i: True) -> Path:
    """``src`` (an MCAP log or rosbag2) copied message by message into a new rosbag2 by ``rosbags``'
    own writer (not terrainmap's), in ``storage`` and with rosbag2's zstd ``compression`` (none,
    file or message); only the messages whose number in log-time order passes ``keep(i)``, but all
    the topics. Topics of types the standard ROS 2 messages lack (a simulated log's truth) stay out."""
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, Reader, StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    typestore = get_typestore(Stores.ROS2_HUMBLE)
    writer = Writer(dst, version=8, storage_plugin=StoragePlugin[storage.upper()])
    writer.set_compression(CompressionMode[compression.upper()], CompressionFormat.ZSTD)
    with Reader(src) as reader, writer:
        out = {c.id: writer.add_connection(c.topic, c.msgtype, typestore=typestore)
               for c in reader.connections if c.msgtype in typestore.fielddefs}
        messages = reader.messages([c for c in reader.connections if c.id in out])
        for i, (connection, stamp, data) in enumerate(messages):
            if keep(i):
                writer.write(out[connection.id], stamp, data)
    return dst


def split_rosbag2(src: Path, dst: Path, parts: int, *, storage: str = "sqlite3", compression: str = "none") -> Path:
    """``src`` copied by ``rosbags``' writer into a rosbag2 split into ``parts`` files of consecutive
    messages, as ``ros2 bag record --max-bag-size`` splits one: ``dst/{dst.name}_{k}`` files, and a
    ``metadata.yaml`` listing them in order with the whole bag's topics and message counts."""
    import shutil

    import yaml
    from rosbags.rosbag2 import Reader

    whole = rewrite_rosbag2(src, dst.parent / f"{dst.name}_whole", storage=storage, compression=compression)
    with Reader(whole) as reader:
        total = reader.message_count
    info = yaml.safe_load((whole / "metadata.yaml").read_text())
    per_file = -(-total // parts)
    names, files = [], []
    for k in range(parts):  # part k: the messages numbered k·per_file .. (k+1)·per_file − 1 of the whole
        part = rewrite_rosbag2(whole, dst.parent / f"{dst.name}_{k}", storage=storage, compression=compression,
                               keep=lambda i, k=k: k * per_file <= i < (k + 1) * per_file)
        entry = yaml.safe_load((part / "metadata.yaml").read_text())["rosbag2_bagfile_information"]["files"][0]
        names.append(entry["path"])
        files.append(entry)
        dst.mkdir(exist_ok=True)
        shutil.move(part / entry["path"], dst / entry["path"])
        shutil.rmtree(part)
    shutil.rmtree(whole)
    info["rosbag2_bagfile_information"].update(relative_file_paths=names, files=files)
    (dst / "metadata.yaml").write_text(yaml.safe_dump(info))
    return dst


def ros1_bag(src: Path, dst: Path) -> Path:
    """``src`` (a ROS 2 MCAP log or rosbag2) converted into a ROS 1 bag by ``rosbags``' converter."""
    from rosbags.convert import convert
    from rosbags.typesys import Stores, get_typestore

    convert([src], dst, "sqlite3", 8, None, "file", get_typestore(Stores.ROS2_HUMBLE), None, [], [], [], [])
    return dst


def ros1_mcap(bag: Path, dst: Path) -> Path:
    """A ROS 1 bag's messages, bytes unchanged, in an MCAP file of profile ``ros1`` (schemas ``ros1msg``,
    message encoding ``ros1``), as ``mcap convert x.bag x.mcap`` writes it."""
    from mcap.writer import Writer
    from rosbags.rosbag1 import Reader

    with Reader(bag) as reader, open(dst, "wb") as stream:
        writer = Writer(stream)
        writer.start(profile="ros1", library="tests")
        channels = {}
        for connection, stamp, data in reader.messages():
            if connection.id not in channels:
                schema = writer.register_schema(connection.msgtype.replace("/msg/", "/"), "ros1msg",
                                                connection.msgdef.data.encode())
                channels[connection.id] = writer.register_channel(connection.topic, "ros1", schema)
            writer.add_message(channels[connection.id], stamp, data, stamp)
        writer.finish()
    return dst


def rewrite_mcap(src: Path, dst: Path, edit=lambda topic, data: data, *, use_statistics: bool = True) -> Path:
    """``src`` (an MCAP file) copied message by message by the ``mcap`` writer, each message's
    bytes passed through ``edit(topic, data) -> data``; without the (optional) statistics record
    where ``use_statistics`` is false."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    with open(src, "rb") as f, open(dst, "wb") as g:
        reader, writer = make_reader(f), Writer(g, use_statistics=use_statistics)
        summary = reader.get_summary()
        writer.start(profile=reader.get_header().profile, library="tests")
        schemas = {i: writer.register_schema(s.name, s.encoding, s.data) for i, s in summary.schemas.items()}
        channels = {i: writer.register_channel(c.topic, c.message_encoding, schemas.get(c.schema_id, 0), c.metadata)
                    for i, c in summary.channels.items()}
        for _, channel, message in reader.iter_messages():
            data = edit(channel.topic, message.data)
            writer.add_message(channels[channel.id], message.log_time, data, message.publish_time)
        writer.finish()
    return dst


def _alias_bomb() -> str:
    lines = ["bomb:", "  a: &a [l, l, l, l, l, l, l, l, l]"]
    for prev, name in zip("abcdefgh", "bcdefghi"):
        lines.append(f"  {name}: &{name} [{', '.join(['*' + prev] * 9)}]")
    return "\n".join(lines) + "\n"


YAML_BOMB = _alias_bomb()
"""A YAML block ``bomb:`` whose anchor ``*i`` reads as 9⁹ items (nested lists of 'l'): a value a
message must not print in full (about 2 GB)."""
