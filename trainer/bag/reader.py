"""Reading bags back: BagReader over rosbag2 bag directories and bare .mcap files, intact or cut
short (a file whose writer was killed has no footer/summary: every complete chunk and message is
recovered by scanning its records), with a BagReport of what was found.

Records are parsed by the mcap library's public readers: `SeekingReader` for an intact file's
header, summary and metadata, `StreamReader` for each record of a file read front to back and
for each chunk or message read later, `breakup_chunk` for a chunk's contents (CRC checked).
What the library lacks is here: a record's length is checked against the file before it is
parsed (the library reads a cut record short, without complaint); a corrupt chunk is skipped and
reported while the chunks after it are still read; chunks that overlap in time are merged into
log-time order holding only those in memory; rosbag2's directory layout (metadata.yaml, splits).
"""
from __future__ import annotations

import heapq
import os
import re
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Iterator, NamedTuple

from mcap.opcode import Opcode
from mcap.reader import SeekingReader
from mcap.records import Channel, Chunk, DataEnd, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk

from trainer.bag.writer import MCAP_MAGIC
from trainer.bag.rosmsg import decode


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


_KNOWN_SCHEMA_ENCODINGS = {"ros2msg", "ros2idl", "omgidl"}
_RECORD_HEAD = struct.Struct("<BQ")     # opcode, length: every MCAP record starts so
_FOOTER_RECORD = b"\x02\x14\x00\x00\x00\x00\x00\x00\x00"   # Footer opcode + its fixed length
_FOOTER_AT_END = len(_FOOTER_RECORD) + 20 + len(MCAP_MAGIC)      # footer record + magic


class _Entry(NamedTuple):
    start: int      # earliest log time inside
    offset: int     # record offset in the file
    kind: Opcode    # CHUNK or MESSAGE


@dataclass
class _FileIndex:
    path: Path
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    entries: list[_Entry] = field(default_factory=list)
    counts: dict[int, int] = field(default_factory=dict)
    rosbag2_metadata: str | None = None
    truncated: str | None = None
    profile: str = ""
    library: str = ""


def _record_at(fh, pos: int, size: int) -> tuple[int, int, Any]:
    """(opcode, length, record) of the record at byte `pos`, parsed by mcap's StreamReader
    (record None for an opcode the library does not know). ValueError when the record is cut
    off: the library reads a short record without complaint, so its length is checked first."""
    fh.seek(pos)
    head = fh.read(_RECORD_HEAD.size)
    if len(head) < _RECORD_HEAD.size:
        raise ValueError(f"record header at byte {pos} is cut off")
    opcode, length = _RECORD_HEAD.unpack(head)
    name = Opcode(opcode).name if opcode in _OPCODES else hex(opcode)
    if pos + _RECORD_HEAD.size + length > size:
        raise ValueError(f"{name} record at byte {pos} needs {length} bytes, only "
                         f"{size - pos - _RECORD_HEAD.size} present")
    if opcode not in _OPCODES:
        return opcode, length, None
    fh.seek(pos)
    return opcode, length, next(StreamReader(fh, skip_magic=True, emit_chunks=True).records)


_OPCODES = frozenset(int(o) for o in Opcode)


def _chunk_records(chunk: Chunk) -> list[Any]:
    """A chunk's inner records, its CRC checked (mcap's breakup_chunk)."""
    if chunk.compression not in ("", "zstd", "lz4"):
        raise ValueError(f"unsupported chunk compression {chunk.compression!r}")
    return breakup_chunk(chunk, validate_crc=True)


def _ends_with_footer(fh, size: int) -> bool:
    """The file ends with a Footer record and the magic (the library would parse any 37
    bytes as a footer; a file cut anywhere else does not end so)."""
    if size < len(MCAP_MAGIC) + _FOOTER_AT_END:
        return False
    fh.seek(size - _FOOTER_AT_END)
    tail = fh.read(_FOOTER_AT_END)
    return tail.startswith(_FOOTER_RECORD) and tail.endswith(MCAP_MAGIC)


def _index_from_summary(reader: SeekingReader, idx: _FileIndex) -> bool:
    """Fill idx from the summary section (mcap's SeekingReader); False if it is unusable
    (then the file is scanned)."""
    summary = reader.get_summary()
    if summary is None or summary.statistics is None:
        return False          # no summary, or no statistics to count with: scan
    stats = summary.statistics
    if stats.message_count and not summary.chunk_indexes:
        return False          # unchunked file: scan for its loose messages
    if len(summary.channels) < stats.channel_count or len(summary.schemas) < stats.schema_count:
        return False          # channels/schemas not repeated in the summary: scan for them
    idx.schemas, idx.channels = dict(summary.schemas), dict(summary.channels)
    idx.entries = [_Entry(ci.message_start_time, ci.chunk_start_offset, Opcode.CHUNK)
                   for ci in summary.chunk_indexes]
    idx.counts = {int(k): int(v) for k, v in stats.channel_message_counts.items()}
    try:
        idx.rosbag2_metadata = next((m.metadata.get("serialized_metadata") for m in reader.iter_metadata()
                                     if m.name == "rosbag2"), None)
    except Exception:         # noqa: BLE001 - a damaged metadata record costs the metadata, not the messages
        pass
    return True


def _scan(fh, idx: _FileIndex, size: int) -> None:
    """Every complete record of the data section, one after the other (a file without a
    usable summary: a killed writer's, a cut copy, a writer that writes none)."""
    pos, n_chunks, n_msgs, problem = len(MCAP_MAGIC), 0, 0, None
    complete = False
    while pos < size:
        try:
            opcode, length, record = _record_at(fh, pos, size)
        except ValueError as exc:
            problem = str(exc)
            break
        if opcode == 0 or (0x0F < opcode < 0x80):
            problem = f"invalid record opcode 0x{opcode:02x} at byte {pos}"
            break
        try:
            if isinstance(record, Chunk):
                start = None
                for r in _chunk_records(record):
                    if isinstance(r, Schema):
                        idx.schemas.setdefault(r.id, r)
                    elif isinstance(r, Channel):
                        idx.channels.setdefault(r.id, r)
                    elif isinstance(r, Message):
                        idx.counts[r.channel_id] = idx.counts.get(r.channel_id, 0) + 1
                        start = r.log_time if start is None else min(start, r.log_time)
                        n_msgs += 1
                if start is not None:
                    idx.entries.append(_Entry(start, pos, Opcode.CHUNK))
                    n_chunks += 1
            elif isinstance(record, (Schema, Channel)):
                (idx.schemas if isinstance(record, Schema) else idx.channels).setdefault(record.id, record)
            elif isinstance(record, Message):
                idx.counts[record.channel_id] = idx.counts.get(record.channel_id, 0) + 1
                idx.entries.append(_Entry(record.log_time, pos, Opcode.MESSAGE))
                n_msgs += 1
            elif isinstance(record, Metadata):
                if record.name == "rosbag2":
                    idx.rosbag2_metadata = record.metadata.get("serialized_metadata")
            elif isinstance(record, (DataEnd, Footer)):
                complete = True
                break
        except Exception as exc:  # noqa: BLE001 - corrupt record: stop, keep what came before
            name = Opcode(opcode).name if opcode in _OPCODES else hex(opcode)
            problem = f"corrupt {name} record at byte {pos} ({type(exc).__name__}: {exc})"
            break
        pos += _RECORD_HEAD.size + length
    if complete:
        idx.truncated = ("summary/footer missing or damaged; data section complete "
                         f"({n_chunks} chunks, {n_msgs} messages recovered by a linear scan)")
    else:
        tail = (f"{size - pos} byte(s) from byte {pos} on are unreadable ({problem})" if problem
                else "the file ends after the last complete record")
        idx.truncated = (f"no MCAP footer/summary (writer killed or file cut): recovered "
                         f"{n_chunks} complete chunk(s) with {n_msgs} message(s); {tail}")


def _index_file(path: Path) -> _FileIndex:
    idx = _FileIndex(path)
    size = path.stat().st_size
    with open(path, "rb") as fh:
        head = fh.read(len(MCAP_MAGIC))
        if not head:
            raise BagReadError("empty file (0 bytes)")
        if head != MCAP_MAGIC:
            raise BagReadError(f"not an MCAP file: starts with {head!r}, expected MCAP magic "
                               f"{MCAP_MAGIC!r}")
        fh.seek(0)
        reader = SeekingReader(fh, validate_crcs=True)
        try:
            _record_at(fh, len(MCAP_MAGIC), size)          # complete, or ValueError
            header = reader.get_header()
        except Exception as exc:  # noqa: BLE001 - whatever the mcap library raises: one BagReadError
            raise BagReadError(f"MCAP magic present but no valid Header record: {exc}") from None
        idx.profile, idx.library = header.profile, header.library
        intact = _ends_with_footer(fh, size)
        try:
            ok = intact and _index_from_summary(reader, idx)
        except Exception:  # noqa: BLE001 - a damaged summary: scan the records instead
            ok = False
        if not ok:
            idx.schemas, idx.channels, idx.entries, idx.counts = {}, {}, [], {}
            _scan(fh, idx, size)
            if intact and idx.truncated and idx.truncated.startswith("summary"):
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
        except Exception as exc:  # noqa: BLE001 - a broken metadata.yaml is reported, the files still read
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
                            c = chans.get(m.channel_id)
                            if c is None:
                                continue
                            seq += 1
                            heapq.heappush(heap, (m.log_time, e.offset, seq,
                                                  RawMessage(c[0], c[1], m.data, m.log_time, m.publish_time)))
                    except Exception as exc:
                        msg = (f"corrupt {'chunk' if e.kind == Opcode.CHUNK else 'message'} at byte "
                               f"{e.offset} skipped ({type(exc).__name__}: {exc})")
                        if self.strict:
                            raise BagReadError(f"{idx.path}: {msg}") from exc
                        prev = self.report.errors.get(str(idx.path))
                        self.report.errors[str(idx.path)] = f"{prev}; {msg}" if prev else msg
                    continue
                yield heapq.heappop(heap)[3]

    @staticmethod
    def _entry_messages(fh, e: _Entry, size: int) -> Iterator[Message]:
        opcode, _, record = _record_at(fh, e.offset, size)
        if opcode != e.kind:
            raise ValueError(f"expected a {e.kind.name} record, found opcode 0x{opcode:02x}")
        if isinstance(record, Message):
            yield record
            return
        for r in _chunk_records(record):
            if isinstance(r, Message):
                yield r
