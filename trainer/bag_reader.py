"""Reading bags back: BagReader over rosbag2 bag directories and bare .mcap files, intact or cut
short (a file whose writer was killed has no footer/summary: every complete chunk and message is
recovered by scanning its records), with a BagReport of what was found.
"""
from __future__ import annotations

import heapq
import io
import os
import re
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Iterator, NamedTuple

from trainer.bag_writer import MCAP_MAGIC
from trainer.rosmsg import decode


class BagReadError(RuntimeError):
    """A bag could not be read (raised only with strict=True; otherwise see BagReport)."""


# ---------------------------------------------------------------------------------------------
# BagReader
# ---------------------------------------------------------------------------------------------

class RawMessage(NamedTuple):
    topic: str
    msgtype: str
    data: bytes
    log_time_ns: int
    publish_time_ns: int


@dataclass
class BagReport:
    """What BagReader found. files: the .mcap files in read order; truncated: file -> reason
    (no footer/summary: writer killed or file cut; every complete chunk is still read);
    errors: file -> reason (foreign, garbage, missing, corrupt chunk); warnings: other findings
    (unknown schema encodings, type conflicts, metadata.yaml problems); counts: topic ->
    messages available; topic_types: topic -> type; schema_encodings: topic -> schema encoding."""
    files: list[str] = field(default_factory=list)
    truncated: dict[str, str] = field(default_factory=dict)
    errors: dict[str, str] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    counts: dict[str, int] = field(default_factory=dict)
    topic_types: dict[str, str] = field(default_factory=dict)
    schema_encodings: dict[str, str] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return not self.errors

    @property
    def message_count(self) -> int:
        return sum(self.counts.values())

    def summary(self) -> str:
        lines = [f"{len(self.files)} file(s), {self.message_count} message(s)"]
        lines += [f"  {t} [{self.topic_types.get(t, '?')}]: {n}" for t, n in self.counts.items()]
        lines += [f"  TRUNCATED {p}: {r}" for p, r in self.truncated.items()]
        lines += [f"  ERROR {p}: {r}" for p, r in self.errors.items()]
        lines += [f"  warning: {w}" for w in self.warnings]
        return "\n".join(lines)


_OP_HEADER, _OP_FOOTER, _OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE, _OP_CHUNK = 1, 2, 3, 4, 5, 6
_OP_METADATA, _OP_DATA_END, _OP_CHUNK_INDEX, _OP_STATISTICS = 0x0C, 0x0F, 0x08, 0x0B
_OP_NAMES = {1: "Header", 2: "Footer", 3: "Schema", 4: "Channel", 5: "Message", 6: "Chunk",
             7: "MessageIndex", 8: "ChunkIndex", 9: "Attachment", 0x0A: "AttachmentIndex",
             0x0B: "Statistics", 0x0C: "Metadata", 0x0D: "MetadataIndex", 0x0E: "SummaryOffset",
             0x0F: "DataEnd"}
_KNOWN_SCHEMA_ENCODINGS = {"ros2msg", "ros2idl", "omgidl"}
_MSG_HEAD = struct.Struct("<HIQQ")


class _Entry(NamedTuple):
    start: int      # message_start_time
    offset: int     # record offset in the file
    length: int     # record length including opcode and length prefix
    kind: int       # _OP_CHUNK or _OP_MESSAGE


@dataclass
class _FileIndex:
    path: Path
    schemas: dict[int, Any] = field(default_factory=dict)
    channels: dict[int, Any] = field(default_factory=dict)
    entries: list[_Entry] = field(default_factory=list)
    counts: dict[int, int] = field(default_factory=dict)
    rosbag2_metadata: str | None = None
    truncated: str | None = None
    profile: str = ""
    library: str = ""


def _stream(data: bytes):
    from mcap.data_stream import ReadDataStream
    return ReadDataStream(io.BytesIO(data))


def _chunk_records(body: bytes) -> list[Any]:
    """Parse and validate (CRC, size) a Chunk record body -> inner records."""
    from mcap.records import Chunk
    from mcap.stream_reader import breakup_chunk
    chunk = Chunk.read(_stream(body))
    if chunk.compression not in ("", "zstd", "lz4"):
        raise ValueError(f"unsupported chunk compression {chunk.compression!r}")
    records = breakup_chunk(chunk, validate_crc=True)
    return records


def _footer(fh, size: int) -> tuple[int, int] | None:
    """(summary_start, footer offset) if the file ends with a valid Footer + magic."""
    if size < 8 + 9 + 20 + 8:
        return None
    fh.seek(size - 37)
    tail = fh.read(37)
    if tail[-8:] != MCAP_MAGIC or tail[:9] != b"\x02\x14\x00\x00\x00\x00\x00\x00\x00":
        return None
    summary_start, _summary_offset_start, _crc = struct.unpack("<QQI", tail[9:29])
    if summary_start > size - 37:
        return None
    return summary_start, size - 37


def _read_record(fh, offset: int, size: int) -> tuple[int, bytes]:
    fh.seek(offset)
    head = fh.read(9)
    if len(head) < 9:
        raise ValueError(f"record header at byte {offset} is cut off")
    opcode, length = struct.unpack("<BQ", head)
    if offset + 9 + length > size:
        raise ValueError(f"{_OP_NAMES.get(opcode, hex(opcode))} record at byte {offset} needs "
                         f"{length} bytes, only {size - offset - 9} present")
    return opcode, fh.read(length)


def _index_from_summary(fh, idx: _FileIndex, summary_start: int, footer_at: int) -> bool:
    """Fill idx from the summary section; False if it is unusable (then scan the file)."""
    from mcap.records import Channel, ChunkIndex, Schema, Statistics, MetadataIndex, Metadata
    fh.seek(summary_start)
    data = fh.read(footer_at - summary_start)
    pos, stats, meta_offsets = 0, None, []
    while pos < len(data):
        opcode, length = struct.unpack_from("<BQ", data, pos)
        body = data[pos + 9: pos + 9 + length]
        if len(body) != length:
            return False
        if opcode == _OP_SCHEMA:
            s = Schema.read(_stream(body))
            idx.schemas[s.id] = s
        elif opcode == _OP_CHANNEL:
            c = Channel.read(_stream(body))
            idx.channels[c.id] = c
        elif opcode == _OP_CHUNK_INDEX:
            ci = ChunkIndex.read(_stream(body))
            idx.entries.append(_Entry(ci.message_start_time, ci.chunk_start_offset,
                                      ci.chunk_length, _OP_CHUNK))
        elif opcode == _OP_STATISTICS:
            stats = Statistics.read(_stream(body))
        elif opcode == 0x0D:
            mi = MetadataIndex.read(_stream(body))
            if mi.name == "rosbag2":
                meta_offsets.append(mi.offset)
        pos += 9 + length
    if stats is None or (stats.message_count and not idx.entries):
        return False  # unchunked file or no statistics: scan for loose messages
    if len(idx.channels) < stats.channel_count or len(idx.schemas) < stats.schema_count:
        return False  # channels/schemas not repeated in the summary: scan for them
    idx.counts = {int(k): int(v) for k, v in stats.channel_message_counts.items()}
    for off in meta_offsets[-1:]:
        try:
            op, body = _read_record(fh, off, footer_at)
            if op == _OP_METADATA:
                meta = Metadata.read(_stream(body)).metadata
                idx.rosbag2_metadata = meta.get("serialized_metadata")
        except Exception:
            pass
    return True


def _scan(fh, idx: _FileIndex, size: int) -> None:
    """Linear scan of the data section (file without usable summary)."""
    from mcap.records import Channel, Metadata, Schema
    pos, n_chunks, n_msgs, problem = 8, 0, 0, None
    complete = False
    while pos < size:
        try:
            opcode, body = _read_record(fh, pos, size)
        except ValueError as exc:
            problem = str(exc)
            break
        if opcode == 0 or (0x0F < opcode < 0x80):
            problem = f"invalid record opcode 0x{opcode:02x} at byte {pos}"
            break
        try:
            if opcode == _OP_CHUNK:
                records = _chunk_records(body)
                start = None
                for r in records:
                    name = type(r).__name__
                    if name == "Schema":
                        idx.schemas.setdefault(r.id, r)
                    elif name == "Channel":
                        idx.channels.setdefault(r.id, r)
                    elif name == "Message":
                        idx.counts[r.channel_id] = idx.counts.get(r.channel_id, 0) + 1
                        start = r.log_time if start is None else min(start, r.log_time)
                        n_msgs += 1
                if start is not None:
                    idx.entries.append(_Entry(start, pos, 9 + len(body), _OP_CHUNK))
                    n_chunks += 1
            elif opcode == _OP_SCHEMA:
                s = Schema.read(_stream(body))
                idx.schemas.setdefault(s.id, s)
            elif opcode == _OP_CHANNEL:
                c = Channel.read(_stream(body))
                idx.channels.setdefault(c.id, c)
            elif opcode == _OP_MESSAGE:
                cid, _seq, log_time, _pub = _MSG_HEAD.unpack_from(body)
                idx.counts[cid] = idx.counts.get(cid, 0) + 1
                idx.entries.append(_Entry(log_time, pos, 9 + len(body), _OP_MESSAGE))
                n_msgs += 1
            elif opcode == _OP_METADATA:
                m = Metadata.read(_stream(body))
                if m.name == "rosbag2":
                    idx.rosbag2_metadata = m.metadata.get("serialized_metadata")
            elif opcode in (_OP_DATA_END, _OP_FOOTER):
                complete = True
                break
        except Exception as exc:  # corrupt record: stop, keep what came before
            problem = (f"corrupt {_OP_NAMES.get(opcode, hex(opcode))} record at byte {pos} "
                       f"({type(exc).__name__}: {exc})")
            break
        pos += 9 + len(body)
    if complete:
        idx.truncated = ("summary/footer missing or damaged; data section complete "
                         f"({n_chunks} chunks, {n_msgs} messages recovered by a linear scan)")
    else:
        tail = (f"{size - pos} byte(s) from byte {pos} on are unreadable ({problem})" if problem
                else "the file ends after the last complete record")
        idx.truncated = (f"no MCAP footer/summary (writer killed or file cut): recovered "
                         f"{n_chunks} complete chunk(s) with {n_msgs} message(s); {tail}")


def _index_file(path: Path) -> _FileIndex:
    from mcap.records import Header
    idx = _FileIndex(path)
    size = path.stat().st_size
    with open(path, "rb") as fh:
        head = fh.read(8)
        if not head:
            raise BagReadError("empty file (0 bytes)")
        if head != MCAP_MAGIC:
            raise BagReadError(f"not an MCAP file: starts with {head[:8]!r}, expected MCAP magic "
                               f"{MCAP_MAGIC!r}")
        try:
            opcode, body = _read_record(fh, 8, size)
            if opcode != _OP_HEADER:
                name = _OP_NAMES.get(opcode, hex(opcode))
                raise ValueError(f"first record is {name}, not Header")
            header = Header.read(_stream(body))
        except Exception as exc:
            raise BagReadError(f"MCAP magic present but no valid Header record: {exc}") from None
        idx.profile, idx.library = header.profile, header.library
        footer = _footer(fh, size)
        ok = False
        if footer is not None and footer[0] != 0:
            try:
                ok = _index_from_summary(fh, idx, *footer)
            except Exception:
                ok = False
        if not ok:
            idx.schemas.clear(); idx.channels.clear(); idx.entries.clear(); idx.counts.clear()
            _scan(fh, idx, size)
            if footer is not None and idx.truncated and idx.truncated.startswith("summary"):
                idx.truncated = None  # a valid file without summary (e.g. noSummary writers)
    idx.entries.sort()
    return idx


def _split_index(path: Path) -> tuple[int, str]:
    m = re.search(r"_(\d+)\.mcap$", path.name)
    return (int(m.group(1)) if m else -1, path.name)


def read_bag_metadata(bag_dir: str | os.PathLike) -> dict[str, Any]:
    """The rosbag2_bagfile_information dict of a bag directory's metadata.yaml."""
    import yaml
    with open(Path(bag_dir) / "metadata.yaml") as fh:
        data = yaml.safe_load(fh)
    if not isinstance(data, dict) or "rosbag2_bagfile_information" not in data:
        raise ValueError("metadata.yaml has no rosbag2_bagfile_information mapping")
    return data["rosbag2_bagfile_information"]


class BagReader:
    """Read rosbag2 MCAP bags: bag directories, single .mcap files, or a list of them.

    A directory is read through its metadata.yaml (relative_file_paths, in order) when present,
    else every *.mcap in it sorted by split index (a recorder that was killed leaves none).
    Messages come in log-time order within each file, files in order. Files are streamed (one
    chunk in memory at a time, plus chunks overlapping in time); nothing is loaded whole.
    A file without footer/summary yields the messages of every complete chunk and is listed in
    report.truncated; a foreign or garbage file is listed in report.errors and skipped
    (strict=True raises BagReadError instead).
    """

    def __init__(self, paths: str | os.PathLike | Iterable[str | os.PathLike], *,
                 strict: bool = False):
        if isinstance(paths, (str, os.PathLike)):
            paths = [paths]
        self.strict = strict
        self.report = BagReport()
        self._indexes: list[_FileIndex] = []
        self._definitions: dict[str, tuple[str, str]] = {}
        for p in paths:
            for f in self._resolve(Path(p)):
                self._add_file(f)

    # -- resolution ----------------------------------------------------------------------------
    def _error(self, path: Path | str, reason: str) -> None:
        if self.strict:
            raise BagReadError(f"{path}: {reason}")
        self.report.errors[str(path)] = reason

    def _resolve(self, path: Path) -> list[Path]:
        if not path.exists():
            self._error(path, "no such file or directory")
            return []
        if path.is_file():
            return [path]
        globbed = sorted(path.glob("*.mcap"), key=_split_index)
        meta = path / "metadata.yaml"
        if not meta.exists():
            if not globbed:
                self._error(path, "directory has no metadata.yaml and no .mcap files")
            else:
                self.report.warnings.append(
                    f"{path}: no metadata.yaml (recorder killed?); reading {len(globbed)} .mcap "
                    "file(s) in split order")
            return globbed
        try:
            info = read_bag_metadata(path)
            storage = info.get("storage_identifier", "")
            if storage != "mcap":
                self._error(path, f"storage {storage!r} is not supported (only mcap)")
                return []
            if info.get("compression_mode"):
                self._error(path, f"file/message compression {info.get('compression_mode')!r} "
                            f"({info.get('compression_format')}) is not supported; decompress "
                            "the files first (chunk compression is supported)")
                return []
            files = [path / Path(str(x)).name for x in info["relative_file_paths"]]
        except BagReadError:
            raise
        except Exception as exc:
            self.report.warnings.append(f"{meta}: unreadable ({exc}); reading *.mcap instead")
            return globbed
        for extra in globbed:
            if extra not in files:
                self.report.warnings.append(f"{extra} is not listed in {meta}; read last")
                files.append(extra)
        return files

    def _add_file(self, path: Path) -> None:
        if not path.exists():
            self._error(path, "listed in metadata.yaml but missing")
            return
        try:
            idx = _index_file(path)
        except BagReadError as exc:
            self._error(path, str(exc))
            return
        except OSError as exc:
            self._error(path, f"cannot read: {exc}")
            return
        self._indexes.append(idx)
        self.report.files.append(str(path))
        if idx.truncated:
            self.report.truncated[str(path)] = idx.truncated
        if idx.profile != "ros2":
            self.report.warnings.append(f"{path}: MCAP profile {idx.profile!r}, not 'ros2'")
        for cid, ch in idx.channels.items():
            schema = idx.schemas.get(ch.schema_id)
            msgtype = schema.name if schema is not None else ""
            enc = schema.encoding if schema is not None else ""
            if schema is None:
                self.report.warnings.append(f"{path}: channel {ch.topic} has no schema")
            elif enc not in _KNOWN_SCHEMA_ENCODINGS:
                self.report.warnings.append(
                    f"{path}: unknown schema encoding {enc!r} for {ch.topic} [{msgtype}]")
            if ch.message_encoding != "cdr":
                self.report.warnings.append(
                    f"{path}: {ch.topic} has message encoding {ch.message_encoding!r}, not 'cdr'")
            old = self.report.topic_types.get(ch.topic)
            if old is not None and old != msgtype:
                self.report.warnings.append(f"{path}: {ch.topic} has type {msgtype}, "
                                            f"earlier files {old}")
            self.report.topic_types.setdefault(ch.topic, msgtype)
            self.report.schema_encodings.setdefault(ch.topic, enc)
            counts = self.report.counts
            counts[ch.topic] = counts.get(ch.topic, 0) + idx.counts.get(cid, 0)
            if schema is not None and msgtype not in self._definitions:
                data = schema.data.decode(errors="replace") if isinstance(schema.data, bytes) \
                    else str(schema.data)
                self._definitions[msgtype] = (enc, data)

    # -- access --------------------------------------------------------------------------------
    @property
    def files(self) -> list[str]:
        return list(self.report.files)

    @property
    def topics(self) -> dict[str, str]:
        return dict(self.report.topic_types)

    def definition(self, msgtype: str) -> tuple[str, str] | None:
        """(schema encoding, text) stored in the bag for a type."""
        return self._definitions.get(msgtype)

    def decode(self, raw: RawMessage) -> Any:
        """Decode with the schema stored in the bag (falls back to the local ament index)."""
        d = self._definitions.get(raw.msgtype)
        if d is not None and d[0] == "ros2msg" and d[1]:
            return decode(raw.msgtype, raw.data, d[1])
        return decode(raw.msgtype, raw.data)

    def messages(self, topics: Iterable[str] | None = None) -> Iterator[RawMessage]:
        """RawMessage(topic, msgtype, data, log_time_ns, publish_time_ns) in log-time order per
        file, files in order; `topics` restricts to those topic names."""
        wanted = None if topics is None else set(topics)
        for idx in self._indexes:
            yield from self._file_messages(idx, wanted)

    def __iter__(self) -> Iterator[RawMessage]:
        return self.messages()

    def _file_messages(self, idx: _FileIndex, wanted: set[str] | None) -> Iterator[RawMessage]:
        chans: dict[int, tuple[str, str]] = {}
        for cid, ch in idx.channels.items():
            if wanted is None or ch.topic in wanted:
                schema = idx.schemas.get(ch.schema_id)
                chans[cid] = (ch.topic, schema.name if schema is not None else "")
        if not chans:
            return
        size = idx.path.stat().st_size
        heap: list[tuple[int, int, int, RawMessage]] = []
        entries = idx.entries
        i, seq = 0, 0
        with open(idx.path, "rb") as fh:
            while i < len(entries) or heap:
                if i < len(entries) and (not heap or entries[i].start <= heap[0][0]):
                    e = entries[i]
                    i += 1
                    try:
                        for m in self._entry_messages(fh, e, size):
                            c = chans.get(m[0])
                            if c is None:
                                continue
                            seq += 1
                            heapq.heappush(heap, (m[1], e.offset, seq,
                                                  RawMessage(c[0], c[1], m[3], m[1], m[2])))
                    except Exception as exc:
                        msg = (f"corrupt {'chunk' if e.kind == _OP_CHUNK else 'message'} at byte "
                               f"{e.offset} skipped ({type(exc).__name__}: {exc})")
                        if self.strict:
                            raise BagReadError(f"{idx.path}: {msg}") from exc
                        prev = self.report.errors.get(str(idx.path))
                        self.report.errors[str(idx.path)] = f"{prev}; {msg}" if prev else msg
                    continue
                yield heapq.heappop(heap)[3]

    @staticmethod
    def _entry_messages(fh, e: _Entry, size: int) -> Iterator[tuple[int, int, int, bytes]]:
        opcode, body = _read_record(fh, e.offset, size)
        if opcode != e.kind:
            raise ValueError(f"expected {_OP_NAMES[e.kind]} record, found opcode 0x{opcode:02x}")
        if opcode == _OP_MESSAGE:
            cid, _s, log_time, pub = _MSG_HEAD.unpack_from(body)
            yield cid, log_time, pub, body[_MSG_HEAD.size:]
            return
        for r in _chunk_records(body):
            if type(r).__name__ == "Message":
                yield r.channel_id, r.log_time, r.publish_time, r.data
