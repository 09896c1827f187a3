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

A bag may come from elsewhere, so reading is bounded (trainer/bag/limits.py): a record or chunk
over `max_chunk_bytes` is refused before it is read or inflated, a chunk inflates to its declared
size at most, a message is decoded with the installed definition of its type when there is one
(a bag's own schema text otherwise, vetted), and each refusal is one line in report.refused
(file, byte offset, limit) while the rest of the bag is still read.
"""
from __future__ import annotations

import dataclasses
import heapq
import io
import os
import re
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Iterator, NamedTuple

import yaml

__all__ = ["BagReader", "BagReadError", "BagReport", "RawMessage", "read_bag_metadata"]

from mcap.opcode import Opcode
from mcap.reader import SeekingReader
from mcap.records import Channel, Chunk, DataEnd, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk

from trainer.bag.bag_report import BagReadError, BagReport, RawMessage
from trainer.bag.limits import BagLimitError, ClampedFile, ReadLimits, check_message_size, decompress, vet_definition
from trainer.bag.rosmsg import TypeSupportError, decode, message_definition_with_encoding
from trainer.bag.writer import MCAP_MAGIC

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
    refused: list[str] = field(default_factory=list)
    profile: str = ""
    library: str = ""


def _record_at(fh, pos: int, size: int, limits: ReadLimits | None = None) -> tuple[int, int, Any]:
    """(opcode, length, record) of the record at byte `pos`, parsed by mcap's StreamReader
    (record None for an opcode the library does not know). ValueError when the record is cut
    off: the library reads a short record without complaint, so its length is checked first;
    BagLimitError, before it is read, when it is longer than limits.max_chunk_bytes."""
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
    if limits is not None and length > limits.max_chunk_bytes:
        raise BagLimitError(f"{name} record at byte {pos} is {length} bytes, over the limit of "
                            f"{limits.max_chunk_bytes} (max_chunk_bytes)")
    fh.seek(pos)
    # Parsed from its own bytes: a length field inside the record (a string's, a map's) can
    # then ask for no more than the record holds (read from the file, it could ask for GBs).
    blob = io.BytesIO(fh.read(_RECORD_HEAD.size + length))
    try:
        return opcode, length, next(StreamReader(blob, skip_magic=True, emit_chunks=True).records)
    except Exception as exc:  # noqa: BLE001 - the library's errors (EndOfFile, ...): a corrupt record
        raise ValueError(f"corrupt {name} record at byte {pos}: its fields need more than its "
                         f"{length} bytes ({type(exc).__name__})") from None


_OPCODES = frozenset(int(o) for o in Opcode)


def _chunk_records(chunk: Chunk, limits: ReadLimits) -> list[Any]:
    """A chunk's inner records, its CRC checked (mcap's breakup_chunk, handed the records
    inflated here within the limits: the library would inflate to whatever the chunk declares)."""
    if chunk.compression not in ("", "zstd", "lz4"):
        raise ValueError(f"unsupported chunk compression {chunk.compression!r}")
    data = decompress(chunk.compression, chunk.data, chunk.uncompressed_size, limits)
    return breakup_chunk(dataclasses.replace(chunk, compression="", data=data), validate_crc=True)


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


def _scan(fh, idx: _FileIndex, size: int, limits: ReadLimits) -> None:
    """Every complete record of the data section, one after the other (a file without a
    usable summary: a killed writer's, a cut copy, a writer that writes none). A record over
    the limits is refused (idx.refused) and skipped: the records after it are still read."""
    pos, n_chunks, n_msgs, problem = len(MCAP_MAGIC), 0, 0, None
    complete = False
    while pos < size:
        try:
            opcode, length, record = _record_at(fh, pos, size, limits)
        except BagLimitError as exc:
            idx.refused.append(f"{idx.path}: {exc}; skipped")
            fh.seek(pos)
            pos += _RECORD_HEAD.size + _RECORD_HEAD.unpack(fh.read(_RECORD_HEAD.size))[1]
            continue
        except ValueError as exc:
            problem = str(exc)
            break
        if opcode == 0 or (0x0F < opcode < 0x80):
            problem = f"invalid record opcode 0x{opcode:02x} at byte {pos}"
            break
        try:
            if isinstance(record, Chunk):
                start = None
                try:
                    inner = _chunk_records(record, limits)
                except BagLimitError as exc:
                    idx.refused.append(f"{idx.path}: chunk at byte {pos}: {exc}; skipped")
                    pos += _RECORD_HEAD.size + length
                    continue
                for r in inner:
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


def _index_file(path: Path, limits: ReadLimits) -> _FileIndex:
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
        reader = SeekingReader(ClampedFile(fh, size), validate_crcs=True)
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
            _scan(fh, idx, size, limits)
            if intact and idx.truncated and idx.truncated.startswith("summary"):
                idx.truncated = None  # a valid file without summary (e.g. noSummary writers)
    idx.entries.sort()
    return idx


def _split_index(path: Path) -> tuple[int, str]:
    m = re.search(r"_(\d+)\.mcap$", path.name)
    return (int(m.group(1)) if m else -1, path.name)


def read_bag_metadata(bag_dir: str | os.PathLike) -> dict[str, Any]:
    """The rosbag2_bagfile_information dict of a bag directory's metadata.yaml."""
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
                 strict: bool = False, limits: ReadLimits | None = None):
        if isinstance(paths, (str, os.PathLike)):
            paths = [paths]
        self.strict = strict
        self.limits = limits if limits is not None else ReadLimits.from_env()
        self._decoding: dict[str, str | None] = {}
        self._definition_files: dict[str, str] = {}
        self._refused_schemas: dict[str, BagLimitError] = {}
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
            idx = _index_file(path, self.limits)
        except BagReadError as exc:
            self._error(path, str(exc))
            return
        except OSError as exc:
            self._error(path, f"cannot read: {exc}")
            return
        self._indexes.append(idx)
        self.report.files.append(str(path))
        for line in idx.refused:
            self._refuse(line)
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
                self._definition_files[msgtype] = str(path)

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

    def _refuse(self, line: str) -> None:
        """One refusal: a line naming the file, the offset and the limit (strict: raised)."""
        if self.strict:
            raise BagReadError(line)
        self.report.refused.append(line)

    def decode(self, raw: RawMessage) -> Any:
        """Decode with the installed definition of the type when there is one (a bag's schema
        that differs from it is not trusted to say how many objects to build: a warning says
        so), else with the schema stored in the bag, vetted (trainer/bag/limits.py). Messages
        over limits.max_message_bytes and refused schemas: BagLimitError (a ValueError)."""
        check_message_size(len(raw.data), self.limits)
        if raw.msgtype in self._refused_schemas:
            raise self._refused_schemas[raw.msgtype]
        if raw.msgtype not in self._decoding:
            self._decoding[raw.msgtype] = self._definition_to_decode(raw.msgtype)
        return decode(raw.msgtype, raw.data, self._decoding[raw.msgtype])

    def _definition_to_decode(self, msgtype: str) -> str | None:
        """The schema text to decode `msgtype` with (None: the installed one, by name)."""
        d = self._definitions.get(msgtype)
        try:
            installed = message_definition_with_encoding(msgtype)
        except (TypeSupportError, OSError):
            installed = None
        if installed is not None:
            if d is not None and d[1] and d[1].strip() != installed[1].strip():
                self.report.warnings.append(f"{msgtype}: the bag's schema differs from the installed "
                                            "definition; decoded with the installed one")
            return None
        if d is None or d[0] != "ros2msg" or not d[1]:
            return None
        try:
            vet_definition(msgtype, d[1])
        except BagLimitError as exc:
            self._refused_schemas[msgtype] = exc
            self._refuse(f"{self._definition_files.get(msgtype, '?')}: {exc}; its messages are not decoded")
            raise
        return d[1]

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
                        for m in self._entry_messages(fh, e, size, self.limits):
                            c = chans.get(m.channel_id)
                            if c is None:
                                continue
                            seq += 1
                            heapq.heappush(heap, (m.log_time, e.offset, seq,
                                                  RawMessage(c[0], c[1], m.data, m.log_time, m.publish_time)))
                    except BagLimitError as exc:
                        self._refuse(f"{idx.path}: {e.kind.name.lower()} at byte {e.offset}: {exc}; skipped")
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
    def _entry_messages(fh, e: _Entry, size: int, limits: ReadLimits) -> Iterator[Message]:
        opcode, _, record = _record_at(fh, e.offset, size, limits)
        if opcode != e.kind:
            raise ValueError(f"expected a {e.kind.name} record, found opcode 0x{opcode:02x}")
        if isinstance(record, Message):
            yield record
            return
        for r in _chunk_records(record, limits):
            if isinstance(r, Message):
                yield r
