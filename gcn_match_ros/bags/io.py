"""rosbag2 files (mcap or sqlite3; a single ``.mcap`` or a bag directory) read and written
with the pure-Python ``rosbags``, no rclpy: every failure becomes a :class:`BagError`
naming the file, a bag appears only once complete (written aside, then renamed), and
:func:`restamp_cdr` shifts stamps of raw messages for replay.
"""
from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path
from typing import Dict, Iterator, NamedTuple, Optional, Sequence, Tuple

import numpy as np
from rosbags.interfaces import MessageDefinitionFormat
from rosbags.rosbag2 import CompressionFormat, CompressionMode, Reader, StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from .typesys import BagError, ensure_type, typestore

__all__ = ["STORAGES", "BagError", "BagInfo", "BagWriter", "BagReader", "bag_info", "iter_raw", "restamp_cdr"]

STORAGES = ("mcap", "sqlite3")


def _open_writer(path: Path, storage: str, compress: bool):
    if storage not in STORAGES:
        raise ValueError(f"storage must be one of {STORAGES}, got {storage!r}")
    writer = Writer(path, version=Writer.VERSION_LATEST,
                    storage_plugin=StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3)
    if compress and storage == "mcap":
        # zstd chunk compression inside the mcap file (what rosbag2's own mcap plugin
        # writes); readable with or without metadata.yaml.
        writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    return writer


class BagWriter:
    """Writes a rosbag2 bag; ``path`` ending in ``.mcap`` gives a single mcap file,
    anything else a rosbag2 directory (metadata.yaml + storage file)."""

    def __init__(self, path, storage: str = "mcap", compress: bool = True) -> None:
        self.path = Path(path)
        if self.path.exists():
            raise BagError(f"{self.path}: exists already, not overwriting")
        self.single = self.path.suffix == ".mcap"
        if self.single and storage != "mcap":
            raise ValueError(f"{self.path}: a .mcap path needs storage='mcap'")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._tmp = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.", dir=self.path.parent))
        self._bag_dir = self._tmp / self.path.stem
        self.writer = _open_writer(self._bag_dir, storage, compress)
        self.store = typestore()
        self.connections: Dict[str, object] = {}
        self.writer.open()

    def connection(self, topic: str, msgtype: str):
        conn = self.connections.get(topic)
        if conn is None:
            ensure_type(self.store, msgtype)
            conn = self.writer.add_connection(topic, msgtype, typestore=self.store)
            self.connections[topic] = conn
        elif conn.msgtype != msgtype:
            raise BagError(f"{self.path}: topic {topic} has type {conn.msgtype}, not {msgtype}")
        return conn

    def write_raw(self, topic: str, msgtype: str, log_ns: int, raw: bytes) -> None:
        self.writer.write(self.connection(topic, msgtype), int(log_ns), raw)

    def write(self, topic: str, msgtype: str, log_ns: int, msg) -> None:
        self.write_raw(topic, msgtype, log_ns, bytes(self.store.serialize_cdr(msg, msgtype)))

    def close(self) -> Path:
        """Finalise (index, metadata) and move the result into place atomically."""
        self.writer.close()
        try:
            if self.single:
                os.replace(self._bag_dir / f"{self.path.stem}.mcap", self.path)
            else:
                os.replace(self._bag_dir, self.path)
        finally:
            shutil.rmtree(self._tmp, ignore_errors=True)
        return self.path

    def abort(self) -> None:
        try:
            self.writer.abort()
        finally:
            shutil.rmtree(self._tmp, ignore_errors=True)

    def __enter__(self) -> "BagWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()



class BagInfo(NamedTuple):
    """Summary of a bag: topic -> type, topic -> message count, first and last log time (ns)."""

    path: Path
    topics: Dict[str, str]
    counts: Dict[str, int]
    start_ns: int
    end_ns: int
    message_count: int


def _wrap(path, exc: BaseException) -> BagError:
    text = str(exc).strip() or type(exc).__name__
    if isinstance(exc, FileNotFoundError):
        return BagError(f"{path}: no such bag ({text})")
    return BagError(f"{path}: unreadable bag, truncated or corrupt? ({type(exc).__name__}: {text})")


class BagReader:
    """rosbags Reader with every failure turned into BagError naming the file, and types
    rebuilt from the definitions stored in the bag (falling back to ours)."""

    def __init__(self, path) -> None:
        self.path = Path(path)
        if not self.path.exists():
            raise BagError(f"{self.path}: no such bag")
        try:
            self.reader = Reader(self.path)
            self.reader.open()
        except Exception as exc:  # ReaderError, struct errors, yaml, ...
            raise _wrap(self.path, exc) from None
        self.store = self._store()

    def _store(self):
        """Standard Jazzy types, then the definitions stored in the bag (a bag written with an
        older Keypoints.msg decodes with its own definition), then ours for the rest."""
        store = get_typestore(Stores.ROS2_JAZZY)
        for conn in self.reader.connections:
            if conn.msgdef.format == MessageDefinitionFormat.MSG and conn.msgdef.data:
                try:
                    types = get_types_from_msg(conn.msgdef.data, conn.msgtype)
                except Exception:  # noqa: BLE001 - fall back to the installed definition
                    continue
                store.register({k: v for k, v in types.items() if k not in store.fielddefs})
        try:
            ours = typestore().fielddefs
        except BagError:  # our .msg files are not installed here: the bag's own definitions serve
            ours = {}
        store.register({k: v for k, v in ours.items() if k not in store.fielddefs})
        return store

    def info(self) -> BagInfo:
        r = self.reader
        topics = {c.topic: c.msgtype for c in r.connections}
        counts: Dict[str, int] = {}
        for c in r.connections:
            counts[c.topic] = counts.get(c.topic, 0) + c.msgcount
        count = r.message_count
        return BagInfo(self.path, topics, counts, r.start_time if count else 0,
                       r.end_time - 1 if count else 0, count)

    def messages(self, topics: Optional[Sequence[str]] = None) -> Iterator[Tuple[str, str, int, bytes]]:
        conns = [c for c in self.reader.connections if topics is None or c.topic in topics]
        if not conns:
            return
        try:
            for conn, ns, raw in self.reader.messages(connections=conns):
                yield conn.topic, conn.msgtype, ns, raw
        except BagError:
            raise
        except Exception as exc:
            raise _wrap(self.path, exc) from None

    def decode(self, raw: bytes, msgtype: str):
        try:
            return self.store.deserialize_cdr(raw, msgtype)
        except Exception as exc:
            raise BagError(f"{self.path}: cannot decode a {msgtype} message "
                           f"({type(exc).__name__}: {exc})") from None

    def close(self) -> None:
        try:
            self.reader.close()
        except Exception:  # noqa: BLE001
            pass

    def __enter__(self) -> "BagReader":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def bag_info(path) -> BagInfo:
    """Topics, types and counts of a bag (mcap/db3 file or rosbag2 directory).

    Raises:
        BagError: missing, truncated or corrupt bag.
    """
    with BagReader(path) as r:
        return r.info()


def iter_raw(path, topics: Optional[Sequence[str]] = None) -> Iterator[Tuple[str, str, int, bytes]]:
    """``(topic, msgtype, log_time_ns, cdr_bytes)`` in log-time order (what a player
    publishes). Raises :class:`BagError` (at open or mid-way) for truncated/corrupt bags."""
    with BagReader(path) as r:
        yield from r.messages(topics)



def restamp_cdr(raw: bytes, offset_ns: int) -> bytes:
    """Shift the header stamp of a CDR message whose first field is a std_msgs/Header
    by ``offset_ns`` (the stamp is the first 8 bytes after the 4-byte encapsulation).

    Raises:
        ValueError: too short, or a stamp that would become negative.
    """
    if len(raw) < 12:
        raise ValueError("CDR message too short to hold a header stamp")
    endian = "<" if raw[1] & 1 else ">"
    sec = int(np.frombuffer(raw, dtype=endian + "i4", count=1, offset=4)[0])
    nsec = int(np.frombuffer(raw, dtype=endian + "u4", count=1, offset=8)[0])
    total = sec * 10**9 + nsec + int(offset_ns)
    if total < 0:
        raise ValueError("restamped header stamp would be negative")
    sec, nsec = divmod(total, 10**9)
    out = bytearray(raw)
    out[4:8] = np.array([sec], dtype=endian + "i4").tobytes()
    out[8:12] = np.array([nsec], dtype=endian + "u4").tobytes()
    return bytes(out)

