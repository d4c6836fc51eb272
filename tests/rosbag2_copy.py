"""Copies of logs as rosbag2 bags in other storage and compression, made by ``rosbags``' own writer."""

from __future__ import annotations

from pathlib import Path


def rewrite_rosbag2(src: Path, dst: Path, *, storage: str = "sqlite3", compression: str = "none") -> Path:
    """``src`` (an MCAP log or rosbag2) copied message by message into a new rosbag2 by ``rosbags``'
    own writer (not terrainmap's), in ``storage`` and with rosbag2's zstd ``compression`` (none,
    file or message). Topics of types the standard ROS 2 messages lack (a simulated log's truth) stay out."""
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, Reader, StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    typestore = get_typestore(Stores.ROS2_HUMBLE)
    writer = Writer(dst, version=8, storage_plugin=StoragePlugin[storage.upper()])
    writer.set_compression(CompressionMode[compression.upper()], CompressionFormat.ZSTD)
    with Reader(src) as reader, writer:
        out = {c.id: writer.add_connection(c.topic, c.msgtype, typestore=typestore)
               for c in reader.connections if c.msgtype in typestore.fielddefs}
        for connection, stamp, data in reader.messages([c for c in reader.connections if c.id in out]):
            writer.write(out[connection.id], stamp, data)
    return dst
