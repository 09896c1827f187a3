"""Bounds a bag from elsewhere must keep while it is read (trainer/bag/reader.py applies them).

A chunk declares its uncompressed size and zstd/lz4 inflate to whatever a stream says: a 66 KB
chunk can ask for 4 GB. So a chunk (and any record) larger than `max_chunk_bytes` is refused
before it is read or inflated, decompression stops at the declared size, and a stream that
inflates to more or less than it declared is an error. A message's schema is text from the bag:
`vet_definition` refuses one whose decoding is not bounded by the message's bytes (an array of
a type that reads no bytes, a fixed array of millions of structs, a recursive or very deep
type), and a message larger than `max_message_bytes` is not decoded. Each refusal is a
BagLimitError whose message names the limit; the reader adds the file and offset.
"""
from __future__ import annotations

import io
import os
from dataclasses import dataclass
from functools import lru_cache

from mcap_ros2._dynamic import _for_each_msgdef  # the decoder's own split of a definition text

#: Default largest chunk (declared uncompressed size, and its record in the file). rosbag2
#: writes chunks of 768 KiB by default, this project 1 MiB; one raw 4K image is 25 MB.
DEFAULT_MAX_CHUNK_BYTES = 256 << 20
#: Default largest message the reader decodes (the CDR bytes, before Python objects exist).
DEFAULT_MAX_MESSAGE_BYTES = 32 << 20
#: Fewest checked bytes an element of an array of structs must read: each element is a Python
#: object (about 60 bytes), so a message of N bytes makes at most N/4 of them.
MIN_STRUCT_ELEMENT_BYTES = 4
#: Largest fixed-size array of structs in a schema (each element is decoded into an object).
MAX_FIXED_STRUCT_ARRAY = 1 << 16
#: Deepest nesting of message types in a schema (each level is a Python call when decoding).
MAX_TYPE_DEPTH = 32

_ENV = {"max_chunk_bytes": "PROTOCAD_BAG_MAX_CHUNK_BYTES", "max_message_bytes": "PROTOCAD_BAG_MAX_MESSAGE_BYTES"}

#: Bytes every CDR read of a primitive checks against the end of the data (mcap_ros2's reader
#: slices uint8/byte arrays without a check: they count 0 here).
_PRIMITIVE_BYTES = {"bool": 1, "byte": 1, "char": 1, "int8": 1, "uint8": 1, "int16": 2, "uint16": 2,
                    "int32": 4, "uint32": 4, "float32": 4, "int64": 8, "uint64": 8, "float64": 8,
                    "string": 4, "wstring": 4}
_SLICED = {"uint8", "byte"}


class BagLimitError(ValueError):
    """A record, chunk, message or schema over one of the reader's limits (the message says
    which limit and its value)."""


@dataclass(frozen=True)
class ReadLimits:
    """The reader's limits. Defaults: the constants above, or the environment variables
    PROTOCAD_BAG_MAX_CHUNK_BYTES / PROTOCAD_BAG_MAX_MESSAGE_BYTES (every tool that reads bags:
    protocad-train, ros2 bag info, ...)."""
    max_chunk_bytes: int = DEFAULT_MAX_CHUNK_BYTES
    max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES

    @classmethod
    def from_env(cls) -> "ReadLimits":
        out = {}
        for key, var in _ENV.items():
            text = os.environ.get(var, "").strip()
            if text:
                try:
                    out[key] = int(text)
                except ValueError:
                    raise BagLimitError(f"{var}={text!r} is not a whole number of bytes") from None
                if out[key] < 1:
                    raise BagLimitError(f"{var}={text!r} must be at least 1")
        return cls(**out)


def check_chunk_size(declared: int, limits: ReadLimits) -> None:
    if declared > limits.max_chunk_bytes:
        raise BagLimitError(f"chunk declares {declared} bytes uncompressed, over the limit of "
                            f"{limits.max_chunk_bytes} (max_chunk_bytes)")


def decompress(compression: str, data: bytes, declared: int, limits: ReadLimits) -> bytes:
    """A chunk's records, inflated to at most its declared size (+1 byte to tell a stream
    that holds more): a size other than the declared one is a BagLimitError."""
    check_chunk_size(declared, limits)
    if compression == "":
        out = data
    elif compression == "zstd":
        import zstandard
        # A stream reader never allocates what the frame header claims: it reads in pieces.
        with zstandard.ZstdDecompressor().stream_reader(io.BytesIO(data), read_across_frames=True) as r:
            out = r.read(declared + 1)
    elif compression == "lz4":
        import lz4.frame
        out = lz4.frame.LZ4FrameDecompressor().decompress(data, max_length=declared + 1)
    else:
        raise BagLimitError(f"unsupported chunk compression {compression!r}")
    if len(out) != declared:
        more = "more than" if len(out) > declared else f"{len(out)} bytes, not"
        raise BagLimitError(f"chunk inflates to {more} the {declared} bytes it declares")
    return out


def check_message_size(size: int, limits: ReadLimits) -> None:
    if size > limits.max_message_bytes:
        raise BagLimitError(f"message of {size} bytes, over the limit of {limits.max_message_bytes} "
                            "(max_message_bytes): not decoded")


@lru_cache(maxsize=256)
def vet_definition(msgtype: str, text: str) -> None:
    """BagLimitError unless decoding `text` (a ros2msg schema: the type, then its dependencies
    after lines of '=') reads at least MIN_STRUCT_ELEMENT_BYTES checked bytes per element of an
    array of structs: then no message expands beyond about one object per 4 bytes of its own.
    Refused: an array of a type that reads fewer (an empty struct reads one checked byte, a
    struct of only fixed byte arrays none), a fixed array of more than MAX_FIXED_STRUCT_ARRAY structs, a recursive type, nesting
    deeper than MAX_TYPE_DEPTH."""
    defs: dict[str, object] = {}

    def keep(name: str, short: str, msgdef: object) -> None:
        defs[name] = defs[short] = msgdef

    try:
        _for_each_msgdef(msgtype, text, keep)
    except Exception as exc:  # noqa: BLE001 - a schema the decoder cannot parse: refused here
        raise BagLimitError(f"schema of {msgtype} does not parse ({type(exc).__name__}: {exc})") from None
    memo: dict[str, int] = {}

    def min_bytes(name: str, stack: tuple[str, ...]) -> int:
        if name in memo:
            return memo[name]
        if name in stack:
            raise BagLimitError(f"schema of {msgtype}: type {name} contains itself")
        if len(stack) > MAX_TYPE_DEPTH:
            raise BagLimitError(f"schema of {msgtype}: types nested deeper than {MAX_TYPE_DEPTH}")
        spec = defs.get(name)
        if spec is None:   # builtin_interfaces/Time and Duration: two int32/uint32
            return 8 if name.startswith("builtin_interfaces/") else 0
        fields = getattr(spec, "fields")
        total = 0 if fields else 1   # an empty struct: one checked uint8
        for f in fields:
            t = f.type
            fixed = t.array_size if t.is_array and t.is_fixed_size_array() else None
            if t.is_primitive_type():
                each = 0 if t.type in _SLICED and t.is_array else _PRIMITIVE_BYTES.get(t.type, 0)
                total += each * fixed if fixed is not None else (4 if t.is_array else each)
                continue
            each = min_bytes(f"{t.pkg_name}/{t.type}", (*stack, name))
            if t.is_array and each < MIN_STRUCT_ELEMENT_BYTES:
                raise BagLimitError(f"schema of {msgtype}: field {f.name} is an array of {t.type}, "
                                    f"which reads {each} byte(s) per element, under the limit of "
                                    f"{MIN_STRUCT_ELEMENT_BYTES}: its length would set the work, not its bytes")
            if fixed is not None and fixed > MAX_FIXED_STRUCT_ARRAY:
                raise BagLimitError(f"schema of {msgtype}: field {f.name} is a fixed array of {fixed} "
                                    f"{t.type}, over the limit of {MAX_FIXED_STRUCT_ARRAY}")
            total += each * fixed if fixed is not None else (4 if t.is_array else each)
        memo[name] = total
        return total

    for name in list(defs):
        min_bytes(name, ())


class ClampedFile:
    """A file whose read(n) asks for no more than the file holds: mcap's SeekingReader reads
    lengths from the file and Python's read(n) reserves n bytes before it reads any."""

    def __init__(self, fh, size: int):
        self._fh, self._size = fh, size

    def read(self, n: int = -1) -> bytes:
        left = max(0, self._size - self._fh.tell())
        return self._fh.read(left if n is None or n < 0 else min(n, left))

    def seek(self, offset: int, whence: int = 0) -> int:
        return self._fh.seek(offset, whence)

    def tell(self) -> int:
        return self._fh.tell()
