"""The rosbag2 (Jazzy) MCAP writer: BagWriter.

Written by hand, on the mcap library's record layer: the mcap Writer cannot write a bag that
stays valid when the disk fills or the process is killed mid-way (checked writes with a kept
reserve, a cut to the last complete chunk and index, DataEnd + footer: trainer/bag/disk_safety.py),
split files by size/duration, nor the metadata record and ``metadata.yaml`` rosbag2 writes
(trainer/bag/bag_info.py). Layout: msgs_docs/mcap_layout.md.
"""
from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any, Mapping

import mcap.writer as mw

from protocad_ros.atomic import atomic_write_text, remove_stale_temporaries
from trainer.bag.bag_info import (
    DEFAULT_OFFERED_QOS,
    INT64_MAX,
    METADATA_VERSION,
    FileInfo,
    TopicInfo,
    bag_metadata,
    library_string,
    plain_type,
    qos_profile,
    qos_yaml,
    topic_info,
)
from trainer.bag.disk_safety import CheckedFile as _CheckedFile
from trainer.bag.disk_safety import FailureRecovery
from trainer.bag.rosmsg import encode
from trainer.bag.yamlcpp import yaml_cpp_dump

__all__ = ["BagWriter", "BagWriteError", "DEFAULT_CHUNK_SIZE", "DEFAULT_OFFERED_QOS", "MCAP_MAGIC",
           "METADATA_VERSION", "MIN_SPLIT_SIZE", "ROS_DISTRO_DEFAULT", "qos_profile", "qos_yaml"]

ROS_DISTRO_DEFAULT = "jazzy"    # written when $ROS_DISTRO is unset (PyPI ROS has no setup.bash)
MIN_SPLIT_SIZE = 1024           # rosbag2 MCAPStorage::get_minimum_split_file_size()
DEFAULT_CHUNK_SIZE = 768 * 1024  # mcap C++ DefaultChunkSize, what rosbag2 uses
MCAP_MAGIC = b"\x89MCAP0\r\n"
_COMPRESSION = {"zstd": "ZSTD", "lz4": "LZ4", "none": "NONE", "": "NONE", None: "NONE"}


class BagWriteError(RuntimeError):
    """Misuse of BagWriter (write after close, unknown topic, existing bag directory...)."""


def check_options(compression: str | None, chunk_size: int, max_bagfile_size: int,
                  max_bagfile_duration_s: float, flush_interval_s: float,
                  custom_data: Mapping[str, str] | None) -> None:
    """ValueError for options rosbag2 would refuse (its own message for a too small split)."""
    if compression not in _COMPRESSION:
        raise ValueError(f"compression {compression!r}; valid: 'zstd', 'lz4', 'none'")
    if chunk_size <= 0:
        raise ValueError(f"chunk_size must be > 0, got {chunk_size}")
    if max_bagfile_size and max_bagfile_size < MIN_SPLIT_SIZE:
        raise ValueError(f"Invalid bag splitting size given. Please provide a value greater "
                         f"than {MIN_SPLIT_SIZE}. Specified value of {max_bagfile_size}")
    if max_bagfile_size < 0 or max_bagfile_duration_s < 0 or flush_interval_s < 0:
        raise ValueError("split sizes, durations and flush interval must be >= 0")
    for k, v in (custom_data or {}).items():
        if not isinstance(k, str) or not isinstance(v, str):
            raise ValueError(f"custom_data must map str to str, got {k!r}: {v!r}")


class BagWriter:
    """Write a rosbag2 (Jazzy, MCAP storage) bag directory.

    BagWriter(bag_dir, compression='zstd'|'lz4'|'none', chunk_size=768 KiB, max_bagfile_size=0
    (bytes, 0 = no split; >= 1024 like rosbag2), max_bagfile_duration_s=0 (0 = no split),
    flush_interval_s=0 (close the current chunk at least this often while writing; 0 = only by
    size), custom_data={str: str}, ros_distro=None ($ROS_DISTRO or 'jazzy')).

    add_topic(name, msgtype, qos_yaml=None, ...) then write(topic, data, log_time_ns,
    publish_time_ns). A chunk is written (and handed to the OS) whenever chunk_size bytes are
    buffered, on flush() and every flush_interval_s: after a SIGKILL, all of those survive.
    close() (idempotent; also on exiting a `with` block) writes the summary, footer and
    metadata.yaml. Writing after close raises BagWriteError. What a failed write needs (the
    space reserve, the counts on disk, the salvage) is its FailureRecovery (disk_safety.py).
    """

    def __init__(self, bag_dir: str | os.PathLike, *, compression: str | None = "zstd",
                 chunk_size: int = DEFAULT_CHUNK_SIZE, max_bagfile_size: int = 0,
                 max_bagfile_duration_s: float = 0, flush_interval_s: float = 0,
                 custom_data: Mapping[str, str] | None = None, ros_distro: str | None = None):
        check_options(compression, chunk_size, max_bagfile_size, max_bagfile_duration_s, flush_interval_s,
                      custom_data)
        self.bag_dir = Path(bag_dir)
        if self.bag_dir.exists() and (not self.bag_dir.is_dir() or any(self.bag_dir.iterdir())):
            raise BagWriteError(f"Bag directory already exists ({self.bag_dir}), "
                                "can't overwrite existing bag")
        self.bag_dir.mkdir(parents=True, exist_ok=True)
        self._mw = mw
        self._compression = getattr(mw.CompressionType, _COMPRESSION[compression])
        self.compression = (compression or "none").lower()
        self.chunk_size = int(chunk_size)
        self.max_bagfile_size = int(max_bagfile_size)
        self.max_bagfile_duration_ns = int(round(max_bagfile_duration_s * 1e9))
        self.flush_interval_s = float(flush_interval_s)
        self.custom_data = dict(custom_data) if custom_data else None
        self.ros_distro = ros_distro or os.environ.get("ROS_DISTRO") or ROS_DISTRO_DEFAULT
        self.library = library_string()
        self._topics: dict[str, TopicInfo] = {}
        self._files: list[FileInfo] = []
        self._start = INT64_MAX
        self._end = 0
        self._count = 0
        self._closed = False
        self._stream: Any = None
        self._mcap: Any = None
        self._channel_ids: dict[str, int] = {}
        self._schema_ids: dict[str, int] = {}
        self._pending = 0           # bytes buffered in the open chunk (estimate)
        self._last_flush = time.monotonic()
        #: Why writing stopped (an OSError: disk full, file too large, permission, removed),
        #: or None. After it, write() raises BagWriteError and close() salvages the bag.
        self.failure: str | None = None
        self.lost_after_failure = 0  # write() calls refused after the failure
        self.salvage_notes: list[str] = []
        remove_stale_temporaries(self.bag_dir / "metadata.yaml")
        self._recovery = FailureRecovery(bag_dir=self.bag_dir, topics=self._topics, files=self._files,
                                         notes=self.salvage_notes)
        try:
            self._open_file()
        except OSError as exc:
            self._recovery.drop_reserve()
            raise BagWriteError(f"cannot start a bag in {self.bag_dir}: {exc}") from exc

    # -- public API ----------------------------------------------------------------------------
    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def files(self) -> list[Path]:
        return [self.bag_dir / f.path for f in self._files]

    @property
    def message_count(self) -> int:
        return self._count

    @property
    def topic_counts(self) -> dict[str, int]:
        return {t.name: t.message_count for t in self._topics.values()}

    def add_topic(self, name: str, msgtype: str, qos_yaml: Any = None, *,
                  type_hash: str | None = None, serialization_format: str = "cdr",
                  definition: tuple[str, str] | None = None) -> None:
        """Declare a topic (channel) before writing to it.

        qos_yaml: offered QoS profiles, as rosbag2's YAML string, a list of qos_profile() dicts
        or None (no publisher known: '[]'). type_hash defaults to the local RIHS01 hash;
        definition = (encoding, text) defaults to the local ament index (as rosbag2 does;
        ('unknown', '') when the type is not installed).
        """
        self._check_open()
        if not name.startswith("/"):
            raise ValueError(f"topic name must be absolute, got {name!r}")
        norm = plain_type(msgtype)
        if name in self._topics:
            if self._topics[name].msgtype != norm:
                raise BagWriteError(f"topic {name} already added with type "
                                    f"{self._topics[name].msgtype}, not {norm}")
            return
        info = topic_info(name, norm, qos_yaml, type_hash=type_hash,
                          serialization_format=serialization_format, definition=definition)
        self._topics[name] = info
        self._register(info)

    def write(self, topic: str, data: bytes | bytearray | memoryview, log_time_ns: int,
              publish_time_ns: int | None = None, sequence: int = 0) -> None:
        """Write one serialized (CDR) message. log_time = receive time, publish_time = source
        time (defaults to log_time)."""
        if self.failure is not None:
            self.lost_after_failure += 1
            raise BagWriteError(f"the bag stopped recording after a write error: {self.failure}")
        self._check_open()
        info = self._topics.get(topic)
        if info is None:
            raise BagWriteError(f"Failed to write on topic '{topic}'. Call add_topic() before "
                                "first write.")
        counted = self._count
        try:
            self._write(topic, info, data, log_time_ns, publish_time_ns, sequence)
        except OSError as exc:
            if self._count == counted:   # the message in hand never got in
                self.lost_after_failure += 1
            self._fail(exc)
            raise BagWriteError(f"write to {self.bag_dir} failed: {exc}; the bag was closed with "
                                "what was written before") from exc

    def _write(self, topic: str, info: Any, data: Any, log_time_ns: int, publish_time_ns: int | None,
               sequence: int) -> None:
        log_time_ns = int(log_time_ns)
        if log_time_ns < 0:
            raise ValueError(f"log_time_ns must be >= 0, got {log_time_ns}")
        publish_time_ns = log_time_ns if publish_time_ns is None else int(publish_time_ns)
        if self._should_split(log_time_ns):
            self._split()
        data = bytes(data)
        before = self._stream.tell()
        self._mcap.add_message(channel_id=self._channel_ids[topic], log_time=log_time_ns,
                               data=data, publish_time=max(publish_time_ns, 0),
                               sequence=int(sequence) & 0xFFFFFFFF)
        committed = self._stream.tell() != before   # a chunk (this message included) is on disk
        if committed:
            self._pending = 0
            self._last_flush = time.monotonic()
        else:
            self._pending += len(data) + 31
        self._files[-1].count(log_time_ns)
        self._start = min(self._start, log_time_ns)
        self._end = max(self._end, log_time_ns)
        self._count += 1
        info.message_count += 1
        if committed:
            self._recovery.commit(self._stream, self._count)
        if self.flush_interval_s and time.monotonic() - self._last_flush >= self.flush_interval_s:
            self.flush()

    def write_message(self, topic: str, msg: Any, log_time_ns: int,
                      publish_time_ns: int | None = None) -> None:
        """encode() a message object with the topic's type, then write()."""
        info = self._topics.get(topic)
        if info is None:
            raise BagWriteError(f"Failed to write on topic '{topic}'. Call add_topic() before "
                                "first write.")
        self.write(topic, encode(info.msgtype, msg), log_time_ns, publish_time_ns)

    def flush(self) -> None:
        """Close the open chunk (if it holds messages) and hand everything to the OS."""
        if self._closed:
            return
        try:
            self._mcap.flush()
            self._recovery.commit(self._stream, self._count)
        except OSError as exc:
            self._fail(exc)
            raise BagWriteError(f"flushing {self.bag_dir} failed: {exc}") from exc
        self._pending = 0
        self._last_flush = time.monotonic()

    def flush_if_due(self) -> bool:
        if self._closed or not self.flush_interval_s or not self._pending:
            return False
        if time.monotonic() - self._last_flush >= self.flush_interval_s:
            self.flush()
            return True
        return False

    def close(self) -> None:
        """Finish the current file (summary + footer) and write metadata.yaml. Idempotent.

        After a write error (self.failure) it salvages instead: the reserve beside the bag is
        freed, the current file is cut back to the end of the last chunk whose index was
        written too (what the counts describe) and ended with a
        DataEnd and a footer without summary (valid MCAP: readers scan it), and metadata.yaml
        is written with the failure and the loss in custom_data (or salvage_notes says why it
        could not be). Never raises OSError."""
        if self._closed:
            return
        self._closed = True
        if self.failure is None:
            try:
                self._close_file()
            except OSError as exc:
                self._fail(exc)
        if self.failure is not None:
            total = self._recovery.salvage(self._stream)
            self.lost_after_failure += self._count - total
            self._count = total
        try:
            self._write_metadata_yaml()
        except OSError as exc:
            self.salvage_notes.append(f"metadata.yaml not written: {exc}")
            for tmp in self.bag_dir.glob(".metadata.yaml.*.tmp"):
                tmp.unlink(missing_ok=True)
        self._recovery.drop_reserve()

    def __enter__(self) -> "BagWriter":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def metadata(self) -> dict[str, Any]:
        """The bag info (the dict under rosbag2_bagfile_information)."""
        return bag_metadata(list(self._topics.values()), self._files, start=self._start, end=self._end,
                            count=self._count, custom_data=self.custom_data, ros_distro=self.ros_distro)

    # -- internals -----------------------------------------------------------------------------
    def _check_open(self) -> None:
        if self._closed:
            raise BagWriteError(f"BagWriter for {self.bag_dir} is closed; cannot write")

    def _should_split(self, t_ns: int) -> bool:
        f = self._files[-1]
        if not f.message_count:
            return False
        if self.max_bagfile_size and self._stream.tell() + self._pending >= self.max_bagfile_size:
            return True
        return bool(self.max_bagfile_duration_ns
                    and t_ns - f.starting_time > self.max_bagfile_duration_ns)

    def _open_file(self) -> None:
        name = f"{self.bag_dir.name}_{len(self._files)}.mcap"
        path = self.bag_dir / name
        self._stream = _CheckedFile(path)
        try:
            self._mcap = self._mw.Writer(self._stream, chunk_size=self.chunk_size,
                                         compression=self._compression, enable_crcs=True)
            self._mcap.start(profile="ros2", library=self.library)
            self._files.append(FileInfo(name))
            self._channel_ids, self._schema_ids = {}, {}
            self._pending = 0
            self._write_metadata_record()
            for info in self._topics.values():  # rosbag2 re-registers every topic after a split
                self._register(info)
            self._recovery.commit(self._stream, self._count)
        except OSError:
            # A file that could not even be started holds nothing: it goes, the bag ends with
            # the files before it (salvage sees no open stream).
            self._stream.close()
            self._stream = None
            path.unlink(missing_ok=True)
            if self._files and self._files[-1].path == name:
                self._files.pop()
            raise

    def _register(self, info: TopicInfo) -> None:
        sid = self._schema_ids.get(info.msgtype)
        if sid is None:
            sid = self._mcap.register_schema(name=info.msgtype, encoding=info.encoding,
                                             data=info.definition.encode())
            self._schema_ids[info.msgtype] = sid
        self._channel_ids[info.name] = self._mcap.register_channel(
            topic=info.name, message_encoding=info.serialization_format, schema_id=sid,
            metadata={"offered_qos_profiles": qos_yaml(info.qos),
                      "topic_type_hash": info.type_hash})

    def _write_metadata_record(self) -> None:
        self._mcap.add_metadata("rosbag2", {"serialized_metadata": yaml_cpp_dump(self.metadata())})

    def _close_file(self) -> None:
        self._write_metadata_record()
        self._mcap.finish()
        os.fsync(self._stream.fileno())
        self._stream.close()
        self._recovery.snapshot(self._stream, self._count)   # the file's last chunk is on disk now

    def _split(self) -> None:
        self._close_file()
        self._open_file()

    def _fail(self, exc: OSError) -> None:
        if self.failure is None:
            self.failure = f"{type(exc).__name__}: {exc}"

    def _write_metadata_yaml(self) -> None:
        info = self.metadata()
        if self.failure is not None:
            info["custom_data"] = {**(info["custom_data"] or {}), "protocad_write_error": self.failure,
                                   "protocad_messages_lost_after_error": str(self.lost_after_failure)}
        atomic_write_text(self.bag_dir / "metadata.yaml", yaml_cpp_dump({"rosbag2_bagfile_information": info}))


