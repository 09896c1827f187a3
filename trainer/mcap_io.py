"""rosbag2-compatible MCAP logs without ROS: type support, BagWriter, BagReader.

No rclpy import here: the ROS-free research path (vectorized envs -> agent -> trainer) and the
recorder node (trainer/recorder.py) write the same bags through this module, and the trainer
reads them back. msgs_docs/mcap_layout.md describes the layout; in short it is what rosbag2's
MCAP storage plugin (ROS 2 Jazzy) writes:

* a bag directory ``NAME/`` with ``NAME_0.mcap``, ``NAME_1.mcap``, ... (split by size and/or
  duration) and ``metadata.yaml`` (``rosbag2_bagfile_information`` version 9) written at close;
* MCAP profile ``ros2``; one schema per type named ``pkg/msg/Type`` with encoding ``ros2msg``
  whose data is the .msg text followed by every dependency after a line of 80 ``=`` and
  ``MSG: pkg/Type`` (rosbag2's LocalMessageDefinitionSource, byte for byte);
* channels with message encoding ``cdr`` and metadata ``offered_qos_profiles`` (the YAML
  rosbag2 writes) and ``topic_type_hash`` (RIHS01);
* a metadata record ``rosbag2`` with ``serialized_metadata`` (the bag info YAML) written when a
  file is opened and again when it is closed, as rosbag2's SequentialWriter does;
* message ``log_time`` = receive time, ``publish_time`` = source (send) time;
* zstd (default), lz4 or uncompressed chunks with CRCs; a file whose writer was killed has no
  footer/summary and BagReader recovers every complete chunk.

Type support comes from the ament index (``share/<pkg>/msg/<Type>.msg`` and ``.json`` installed
by the ROS wheels): message_definition, type_hash, new_message, encode, decode.
"""
from __future__ import annotations

import heapq
import io
import json
import os
import re
import struct
import sys
import time
from dataclasses import dataclass, field
from functools import lru_cache
from importlib.metadata import PackageNotFoundError, version as _pkg_version
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Mapping, NamedTuple, Sequence

import numpy as np

__all__ = [
    "TypeSupportError", "BagWriteError", "BagReadError",
    "normalize_type", "message_definition", "message_definition_with_encoding", "type_hash",
    "new_message", "encode", "decode", "decoder_for", "encoder_for", "to_plain",
    "qos_profile", "qos_yaml", "yaml_cpp_dump", "DEFAULT_OFFERED_QOS",
    "BagWriter", "BagReader", "BagReport", "RawMessage", "read_bag_metadata",
    "METADATA_VERSION", "ROS_DISTRO_DEFAULT", "MIN_SPLIT_SIZE", "DEFAULT_CHUNK_SIZE",
]

METADATA_VERSION = 9            # rosbag2 Jazzy's rosbag2_bagfile_information version
ROS_DISTRO_DEFAULT = "jazzy"    # written when $ROS_DISTRO is unset (PyPI ROS has no setup.bash)
MIN_SPLIT_SIZE = 1024           # rosbag2 MCAPStorage::get_minimum_split_file_size()
DEFAULT_CHUNK_SIZE = 768 * 1024  # mcap C++ DefaultChunkSize, what rosbag2 uses
INT64_MAX = 2**63 - 1           # rosbag2's "no time yet" (std::chrono::nanoseconds::max())
MCAP_MAGIC = b"\x89MCAP0\r\n"
DELIMITER = "=" * 80 + "\n"


# ---------------------------------------------------------------------------------------------
# Errors
# ---------------------------------------------------------------------------------------------

class TypeSupportError(LookupError):
    """A message type could not be resolved in the ament index (or parsed)."""


class BagWriteError(RuntimeError):
    """Misuse of BagWriter (write after close, unknown topic, existing bag directory...)."""


class BagReadError(RuntimeError):
    """A bag could not be read (raised only with strict=True; otherwise see BagReport)."""


# ---------------------------------------------------------------------------------------------
# Type support from the ament index
# ---------------------------------------------------------------------------------------------

_NAME = r"[a-zA-Z][a-zA-Z0-9_]*"
_NO_NS = re.compile(rf"^({_NAME})/({_NAME})$")
_WITH_NS = re.compile(rf"^({_NAME})/({_NAME})/({_NAME})$")
# rosbag2_cpp LocalMessageDefinitionSource: field types at line starts / #include in .idl
_MSG_FIELD_TYPE = re.compile(r"(?:^|\n)\s*([a-zA-Z0-9_/]+)(?:\[[^\]]*\])?\s+")
_IDL_FIELD_TYPE = re.compile(r"(?:^|\n)#include\s+(?:\"|<)([a-zA-Z0-9_/]+)\.idl(?:\"|>)")
_PRIMITIVES = frozenset({"bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16",
                         "uint16", "int32", "uint32", "int64", "uint64", "string"})


def _split_type(msgtype: str) -> tuple[str, str, str]:
    """'pkg/msg/Type' or 'pkg/Type' -> (pkg, 'msg', 'Type')."""
    m = _WITH_NS.match(msgtype)
    if m:
        return m.group(1), m.group(2), m.group(3)
    m = _NO_NS.match(msgtype)
    if m:
        return m.group(1), "msg", m.group(2)
    raise TypeSupportError(f"invalid message type name {msgtype!r}; expected 'pkg/msg/Type'")


def normalize_type(msgtype: str) -> str:
    """'sensor_msgs/Image' or 'sensor_msgs/msg/Image' -> 'sensor_msgs/msg/Image'."""
    pkg, ns, name = _split_type(msgtype)
    return f"{pkg}/{ns}/{name}"


def _prefixes() -> list[Path]:
    out = [Path(p) for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    if Path(sys.prefix) not in out:
        out.append(Path(sys.prefix))
    return out


@lru_cache(maxsize=None)
def _share_dir(pkg: str) -> Path:
    try:
        from ament_index_python.packages import get_package_share_directory
        return Path(get_package_share_directory(pkg))
    except Exception:  # not installed, or not in the resource index: look at the prefixes
        for prefix in _prefixes():
            if (prefix / "share" / pkg).is_dir():
                return prefix / "share" / pkg
    raise TypeSupportError(
        f"package {pkg!r} not found in the ament index (AMENT_PREFIX_PATH="
        f"{os.environ.get('AMENT_PREFIX_PATH', '')!r}); source scripts/env.sh or install it")


def _interface_file(msgtype: str, ext: str) -> Path:
    pkg, ns, name = _split_type(msgtype)
    return _share_dir(pkg) / ns / f"{name}{ext}"


@lru_cache(maxsize=None)
def _read_interface(msgtype: str, ext: str) -> str:
    path = _interface_file(msgtype, ext)
    try:
        return path.read_text()
    except FileNotFoundError:
        raise TypeSupportError(f"no {ext} file for {msgtype!r} ({path} does not exist)") from None


def _dependencies(fmt: str, text: str, package: str) -> list[str]:
    deps: set[str] = set()
    if fmt == "msg":
        for m in _MSG_FIELD_TYPE.finditer(text):
            t = m.group(1)
            if t in _PRIMITIVES:
                continue
            deps.add(t if "/" in t else f"{package}/{t}")
    else:
        deps.update(m.group(1) for m in _IDL_FIELD_TYPE.finditer(text))
    return sorted(deps)  # std::set<std::string> order


def _full_text(root: str, fmt: str) -> str:
    seen: set[str] = set()
    tag = "MSG: " if fmt == "msg" else "IDL: "

    def rec(name: str, depth: int) -> str:
        if depth <= 0:
            raise TypeSupportError(f"max recursion depth resolving definition of {root}")
        text = _read_interface(name, f".{fmt}")
        out = text
        for dep in _dependencies(fmt, text, _split_type(name)[0]):
            if dep not in seen:
                seen.add(dep)
                out += "\n" + DELIMITER + tag + dep + "\n" + rec(dep, depth - 1)
        return out

    text = rec(root, 50)
    return text if fmt == "msg" else DELIMITER + tag + root + "\n" + text


@lru_cache(maxsize=None)
def message_definition_with_encoding(msgtype: str) -> tuple[str, str]:
    """(schema encoding, text) exactly as rosbag2 Jazzy stores it: ('ros2msg', .msg text and
    dependencies) or, for types installed only as .idl, ('ros2idl', ...)."""
    msgtype = normalize_type(msgtype)
    try:
        return "ros2msg", _full_text(msgtype, "msg")
    except TypeSupportError as msg_err:
        if _interface_file(msgtype, ".msg").exists():
            raise  # a dependency is missing: do not silently switch format
        try:
            return "ros2idl", _full_text(msgtype, "idl")
        except TypeSupportError:
            raise msg_err from None


def message_definition(msgtype: str) -> str:
    """The rosbag2 schema text: the .msg text, then each dependency (depth-first, sorted, each
    once) after a newline, 80 '=' and 'MSG: pkg/Type' (the name as written in the .msg)."""
    return message_definition_with_encoding(msgtype)[1]


@lru_cache(maxsize=None)
def type_hash(msgtype: str) -> str:
    """'RIHS01_<sha256 hex>' from share/<pkg>/msg/<Type>.json (REP 2011 type hash)."""
    msgtype = normalize_type(msgtype)
    path = _interface_file(msgtype, ".json")
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise TypeSupportError(f"no type description for {msgtype!r} ({path} missing)") from None
    for entry in data.get("type_hashes", []):
        if entry.get("type_name") == msgtype:
            return str(entry["hash_string"])
    raise TypeSupportError(f"{path} has no type hash for {msgtype!r}")


def _try_type_hash(msgtype: str) -> str:
    try:
        return type_hash(msgtype)
    except TypeSupportError:
        return ""


# ---- message objects -------------------------------------------------------------------------

class RosMessage:
    """Base of the attribute objects made by new_message (fields with ROS default values)."""

    __slots__ = ()
    _type = ""
    _fields: tuple[str, ...] = ()

    def __repr__(self) -> str:
        inner = ", ".join(f"{f}={getattr(self, f)!r}" for f in self._fields)
        return f"{self._type}({inner})"

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, RosMessage) or other._type != self._type:
            return NotImplemented
        for f in self._fields:
            a, b = getattr(self, f), getattr(other, f)
            if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
                if not np.array_equal(np.asarray(a), np.asarray(b)):
                    return False
            elif a != b:
                return False
        return True

    def get_fields_and_field_types(self) -> dict[str, str]:  # rclpy-like introspection
        return dict(_specs(self._type)[1])

    def to_dict(self) -> dict[str, Any]:
        return {f: to_plain(getattr(self, f)) for f in self._fields}


@lru_cache(maxsize=None)
def _specs(msgtype: str):
    """(parsed MessageSpecification, [(field, type str)]) of one type's .msg."""
    from mcap_ros2._vendor.rosidl_adapter.parser import parse_message_string
    pkg, _, name = _split_type(msgtype)
    try:
        spec = parse_message_string(pkg, name, _read_interface(normalize_type(msgtype), ".msg"))
    except TypeSupportError:
        raise
    except Exception as exc:
        raise TypeSupportError(f"cannot parse {msgtype}.msg: {exc}") from exc
    return spec, [(f.name, str(f.type)) for f in spec.fields]


@lru_cache(maxsize=None)
def _message_class(msgtype: str) -> type:
    spec, _ = _specs(msgtype)
    names = tuple(f.name for f in spec.fields)
    cls = type(spec.base_type.type, (RosMessage,),
               {"__slots__": names, "_type": normalize_type(msgtype), "_fields": names})
    for c in spec.constants:  # constants as class attributes, as rclpy does
        setattr(cls, c.name, c.value)
    return cls


_ZERO = {"bool": False, "string": "", "wstring": "", "float32": 0.0, "float64": 0.0}


def _default(ftype, default) -> Any:
    if ftype.is_primitive_type():
        if ftype.is_array:
            if ftype.type in ("uint8", "byte"):
                if ftype.is_fixed_size_array():
                    return bytes(default) if default else bytes(ftype.array_size)
                return bytes(default) if default else b""
            if default is not None:
                return list(default)
            zero = _ZERO.get(ftype.type, 0)
            return [zero] * ftype.array_size if ftype.is_fixed_size_array() else []
        return default if default is not None else _ZERO.get(ftype.type, 0)
    nested = f"{ftype.pkg_name}/msg/{ftype.type}"
    if ftype.is_array:
        return [new_message(nested) for _ in range(ftype.array_size)] \
            if ftype.is_fixed_size_array() else []
    return new_message(nested)


def new_message(msgtype: str) -> RosMessage:
    """An attribute object of `msgtype` with ROS default values (nested messages included):
    uint8[]/byte[] -> bytes, other arrays -> list, strings '' , numbers 0. topics.fill_* work on
    it, and encode() serializes it (numpy arrays assigned to fields are accepted too)."""
    msgtype = normalize_type(msgtype)
    cls = _message_class(msgtype)
    obj = cls.__new__(cls)
    for f in _specs(msgtype)[0].fields:
        object.__setattr__(obj, f.name, _default(f.type, f.default_value))
    return obj


def to_plain(value: Any) -> Any:
    """Nested plain Python (dict/list/bytes/scalars) from a message object, numpy included."""
    if isinstance(value, np.ndarray):
        return value.tobytes() if value.dtype == np.uint8 else value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, (str, bytes, int, float, bool)) or value is None:
        return value
    if isinstance(value, (bytearray, memoryview)):
        return bytes(value)
    if isinstance(value, (list, tuple)):
        return [to_plain(v) for v in value]
    if isinstance(value, Mapping):
        return {k: to_plain(v) for k, v in value.items()}
    if isinstance(value, RosMessage):
        return {f: to_plain(getattr(value, f)) for f in value._fields}
    if hasattr(value, "get_fields_and_field_types"):  # rclpy message
        return {f: to_plain(getattr(value, f)) for f in value.get_fields_and_field_types()}
    slots = getattr(type(value), "__slots__", None)
    if slots and not isinstance(slots, str):  # mcap_ros2 decoded messages
        return {f: to_plain(getattr(value, f)) for f in slots if not f.startswith("_")}
    if hasattr(value, "__dict__"):
        return {k: to_plain(v) for k, v in vars(value).items() if not k.startswith("_")}
    if hasattr(value, "tolist"):  # array.array
        return value.tobytes() if getattr(value, "typecode", "") == "B" else value.tolist()
    return value


@lru_cache(maxsize=None)
def encoder_for(msgtype: str, definition: str | None = None) -> Callable[[Any], bytes]:
    """Cached CDR encoder (mcap_ros2.serialize_dynamic) for a type; definition defaults to the
    local ament index."""
    from mcap_ros2._dynamic import serialize_dynamic
    msgtype = normalize_type(msgtype)
    text = definition if definition is not None else message_definition(msgtype)
    try:
        return serialize_dynamic(msgtype, text)[msgtype]
    except Exception as exc:
        raise TypeSupportError(f"cannot build a CDR encoder for {msgtype}: {exc}") from exc


@lru_cache(maxsize=256)
def decoder_for(msgtype: str, definition: str | None = None) -> Callable[[bytes], Any]:
    """Cached lenient CDR decoder (mcap_ros2.generate_dynamic: tolerates the trailing padding
    rclpy/FastCDR writes) for a type; definition defaults to the local ament index."""
    from mcap_ros2._dynamic import generate_dynamic
    msgtype = normalize_type(msgtype)
    text = definition if definition is not None else message_definition(msgtype)
    try:
        return generate_dynamic(msgtype, text)[msgtype]
    except Exception as exc:
        raise TypeSupportError(f"cannot build a CDR decoder for {msgtype}: {exc}") from exc


def encode(msgtype: str, msg: Any) -> bytes:
    """CDR bytes (little endian, rosbag2 'cdr' serialization format) of a message object: a
    new_message object, an rclpy message, a decoded message or a dict."""
    if isinstance(msg, RosMessage) or not hasattr(msg, "get_fields_and_field_types"):
        msg = to_plain(msg)  # numpy arrays -> list/bytes; rclpy messages are used as they are
    try:
        return encoder_for(normalize_type(msgtype))(msg)
    except TypeSupportError:
        raise
    except Exception as exc:
        raise ValueError(f"cannot encode {msgtype}: {exc}") from exc


def decode(msgtype: str, data: bytes, definition: str | None = None) -> Any:
    """Decode CDR bytes to an attribute object (fields as in the .msg; uint8[] -> bytes)."""
    try:
        return decoder_for(normalize_type(msgtype), definition)(bytes(data))
    except TypeSupportError:
        raise
    except Exception as exc:
        raise ValueError(f"cannot decode {len(data)} bytes as {msgtype}: {exc}") from exc


# ---------------------------------------------------------------------------------------------
# YAML the way rosbag2 writes it (yaml-cpp block style: YAML::Dump / operator<<)
# ---------------------------------------------------------------------------------------------

_YAML_SPECIAL = {"", "~", "null", "true", "false", "yes", "no", "on", "off", "y", "n"}
_PLAIN = re.compile(r"[A-Za-z0-9_/.][A-Za-z0-9_/.\-+ ]*")
_NUMBER = re.compile(r"[-+]?(\.?[0-9][0-9_]*(\.[0-9_]*)?([eE][-+]?[0-9]+)?|\.inf|\.nan"
                     r"|0x[0-9a-fA-F]+|0o[0-7]+)")


def _scalar(v: Any) -> str:
    if v is None:
        return "~"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, float):
        return repr(v)
    s = str(v)
    if (_PLAIN.fullmatch(s) and not s.endswith(" ") and s.lower() not in _YAML_SPECIAL
            and not _NUMBER.fullmatch(s.lower())):
        return s
    return json.dumps(s)  # a valid YAML double-quoted scalar


def _emit(node: Any, indent: int, lines: list[str]) -> None:
    pad = " " * indent
    if isinstance(node, Mapping):
        for k, v in node.items():
            if isinstance(v, Mapping) and v:
                lines.append(f"{pad}{k}:")
                _emit(v, indent + 2, lines)
            elif isinstance(v, (list, tuple)) and v:
                lines.append(f"{pad}{k}:")
                _emit(v, indent + 2, lines)
            elif isinstance(v, (list, tuple)):
                lines.append(f"{pad}{k}:")
                lines.append(f"{pad}  []")
            elif isinstance(v, Mapping):
                lines.append(f"{pad}{k}:")
                lines.append(f"{pad}  {{}}")
            else:
                lines.append(f"{pad}{k}: {_scalar(v)}")
    elif isinstance(node, (list, tuple)):
        for item in node:
            if isinstance(item, Mapping) and item:
                sub: list[str] = []
                _emit(item, indent + 2, sub)
                sub[0] = f"{pad}- " + sub[0][indent + 2:]
                lines.extend(sub)
            elif isinstance(item, (list, tuple)) and item:
                sub = []
                _emit(item, indent + 2, sub)
                sub[0] = f"{pad}- " + sub[0][indent + 2:]
                lines.extend(sub)
            elif isinstance(item, (list, tuple)):
                lines.append(f"{pad}- []")
            elif isinstance(item, Mapping):
                lines.append(f"{pad}- {{}}")
            else:
                lines.append(f"{pad}- {_scalar(item)}")
    else:
        lines.append(pad + _scalar(node))


def yaml_cpp_dump(node: Any) -> str:
    """YAML text as yaml-cpp's emitter writes it in rosbag2 (2-space indentation, sequences
    indented under their key, '""' for empty strings, '~' for null, no trailing newline)."""
    if isinstance(node, (list, tuple)) and not node:
        return "[]"
    if isinstance(node, Mapping) and not node:
        return "{}"
    lines: list[str] = []
    _emit(node, 0, lines)
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------
# QoS profiles as rosbag2 serializes them (metadata version 9: enum names, {sec, nsec})
# ---------------------------------------------------------------------------------------------

INFINITE_NS = INT64_MAX  # RMW_DURATION_INFINITE = {9223372036, 854775807}


def _duration(ns: int) -> dict[str, int]:
    sec, nsec = divmod(int(ns), 1_000_000_000)
    return {"sec": sec, "nsec": nsec}


def qos_profile(history: str = "unknown", depth: int = 0, reliability: str = "reliable",
                durability: str = "volatile", deadline_ns: int = INFINITE_NS,
                lifespan_ns: int = INFINITE_NS, liveliness: str = "automatic",
                liveliness_lease_duration_ns: int = INFINITE_NS,
                avoid_ros_namespace_conventions: bool = False) -> dict[str, Any]:
    """One offered QoS profile in rosbag2's v9 form. Defaults = what the ROS graph reports for a
    reliable, volatile publisher (DDS does not propagate history: 'unknown', depth 0)."""
    return {
        "history": history, "depth": int(depth), "reliability": reliability,
        "durability": durability, "deadline": _duration(deadline_ns),
        "lifespan": _duration(lifespan_ns), "liveliness": liveliness,
        "liveliness_lease_duration": _duration(liveliness_lease_duration_ns),
        "avoid_ros_namespace_conventions": bool(avoid_ros_namespace_conventions),
    }


DEFAULT_OFFERED_QOS = (qos_profile(),)


def qos_yaml(profiles: Sequence[Mapping[str, Any]]) -> str:
    """The channel metadata value rosbag2 writes (serialize_rclcpp_qos_vector)."""
    return yaml_cpp_dump(list(profiles))


def _parse_qos(qos: Any) -> list[dict[str, Any]]:
    if qos is None:
        return []
    if isinstance(qos, str):
        import yaml
        loaded = yaml.safe_load(qos) if qos.strip() else []
        if not isinstance(loaded, list):
            raise ValueError(f"offered_qos_profiles YAML must be a list, got {type(loaded)}")
        return [dict(x) for x in loaded]
    if isinstance(qos, Mapping):
        return [dict(qos)]
    return [dict(x) for x in qos]


# ---------------------------------------------------------------------------------------------
# BagWriter
# ---------------------------------------------------------------------------------------------

def _library_string() -> str:
    def ver(name: str) -> str:
        try:
            return _pkg_version(name)
        except PackageNotFoundError:
            return "unknown"
    return f"protocad-ros {ver('protocad-ros')} trainer.mcap_io; mcap-python {ver('mcap')}"


@dataclass
class _TopicInfo:
    name: str
    msgtype: str
    serialization_format: str
    qos: list[dict[str, Any]]
    type_hash: str
    encoding: str
    definition: str
    message_count: int = 0

    def metadata(self) -> dict[str, Any]:
        return {"topic_metadata": {
            "name": self.name, "type": self.msgtype,
            "serialization_format": self.serialization_format,
            "offered_qos_profiles": self.qos, "type_description_hash": self.type_hash},
            "message_count": self.message_count}


@dataclass
class _FileInfo:
    path: str
    starting_time: int = INT64_MAX
    end_time: int = 0
    message_count: int = 0

    def metadata(self) -> dict[str, Any]:
        dur = self.end_time - self.starting_time if self.message_count else 0
        return {"path": self.path, "starting_time": {"nanoseconds_since_epoch": self.starting_time},
                "duration": {"nanoseconds": dur}, "message_count": self.message_count}


_COMPRESSION = {"zstd": "ZSTD", "lz4": "LZ4", "none": "NONE", "": "NONE", None: "NONE"}


RESERVE_BYTES = 64 * 1024   # kept free beside the bag, to close it validly on a full disk
_DATA_END = b"\x0f" + (4).to_bytes(8, "little") + (0).to_bytes(4, "little")
_FOOTER = b"\x02" + (20).to_bytes(8, "little") + bytes(20) + b"\x89MCAP0\r\n"


class _CheckedFile:
    """An unbuffered file for the mcap Writer that never writes a record half-way silently:
    a short write is retried until complete or an OSError, and `good` is the end of the last
    complete write (the mcap Writer writes each chunk, index and summary record in one call),
    so that after a failure the file can be cut back to whole records."""

    def __init__(self, path: Path):
        self._f = open(path, "xb", buffering=0)
        self.good = 0
        self.data_end: int | None = None

    def write(self, data) -> int:
        view = memoryview(data).cast("B")
        done = 0
        while done < len(view):
            n = self._f.write(view[done:])
            if not n:
                raise OSError(28, "No space left on device (short write)")
            done += n
        self.good = self._f.tell()
        return done

    def tell(self) -> int:
        return self._f.tell()

    def flush(self) -> None:
        pass

    def fileno(self) -> int:
        return self._f.fileno()

    def close(self) -> None:
        self._f.close()

    @property
    def closed(self) -> bool:
        return self._f.closed


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
    metadata.yaml. Writing after close raises BagWriteError.
    """

    def __init__(self, bag_dir: str | os.PathLike, *, compression: str | None = "zstd",
                 chunk_size: int = DEFAULT_CHUNK_SIZE, max_bagfile_size: int = 0,
                 max_bagfile_duration_s: float = 0, flush_interval_s: float = 0,
                 custom_data: Mapping[str, str] | None = None, ros_distro: str | None = None):
        import mcap.writer as mw
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
        self.library = _library_string()
        self._topics: dict[str, _TopicInfo] = {}
        self._files: list[_FileInfo] = []
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
        from protocad_ros.atomic import remove_stale_temporaries

        remove_stale_temporaries(self.bag_dir / "metadata.yaml")
        self._reserve = self.bag_dir / ".protocad-reserve"
        self._make_reserve()
        try:
            self._open_file()
        except OSError as exc:
            self._drop_reserve()
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
        try:
            norm = normalize_type(msgtype)
        except TypeSupportError:
            norm = msgtype
        if name in self._topics:
            if self._topics[name].msgtype != norm:
                raise BagWriteError(f"topic {name} already added with type "
                                    f"{self._topics[name].msgtype}, not {norm}")
            return
        if definition is None:
            try:
                definition = message_definition_with_encoding(norm)
            except TypeSupportError:
                definition = ("unknown", "")  # MessageDefinition::empty_message_definition_for
        info = _TopicInfo(name=name, msgtype=norm, serialization_format=serialization_format,
                          qos=_parse_qos(qos_yaml),
                          type_hash=_try_type_hash(norm) if type_hash is None else type_hash,
                          encoding=definition[0], definition=definition[1])
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
        f = self._files[-1]
        f.starting_time = min(f.starting_time, log_time_ns)
        f.end_time = max(f.end_time, log_time_ns)
        f.message_count += 1
        self._start = min(self._start, log_time_ns)
        self._end = max(self._end, log_time_ns)
        self._count += 1
        info.message_count += 1
        if committed:
            self._commit()
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
            self._commit()
        except OSError as exc:
            self._fail(exc)
            raise BagWriteError(f"flushing {self.bag_dir} failed: {exc}") from exc
        self._pending = 0
        self._last_flush = time.monotonic()

    def _commit(self) -> None:
        """Remember the counts of what is on disk: a failure loses only the open chunk. A bag
        file deleted while recording takes writes without an error (its inode lives on), so
        that is checked here too and treated as a write failure."""
        if self._files and os.fstat(self._stream.fileno()).st_nlink == 0:
            raise OSError(2, f"{self.files[-1]} was removed while recording")
        self._snapshot()

    def _snapshot(self) -> None:
        self._committed = (self._count, {n: t.message_count for n, t in self._topics.items()},
                           self._files[-1].message_count)

    def _uncommit(self) -> None:
        """After a failure: the counts go back to what the file holds; the rest is lost."""
        total, per_topic, in_file = self._committed
        self.lost_after_failure += self._count - total
        self._count = total
        for n, t in self._topics.items():
            t.message_count = per_topic.get(n, 0)
        self._files[-1].message_count = in_file

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
        freed, the current file is cut back to its last complete record and ended with a
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
            self._salvage()
        try:
            self._write_metadata_yaml()
        except OSError as exc:
            self.salvage_notes.append(f"metadata.yaml not written: {exc}")
            for tmp in self.bag_dir.glob(".metadata.yaml.*.tmp"):
                tmp.unlink(missing_ok=True)
        self._drop_reserve()

    def __enter__(self) -> "BagWriter":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def metadata(self) -> dict[str, Any]:
        """The bag info (the dict under rosbag2_bagfile_information)."""
        return {
            "version": METADATA_VERSION,
            "storage_identifier": "mcap",
            "duration": {"nanoseconds": self._end - self._start if self._count else 0},
            "starting_time": {"nanoseconds_since_epoch": self._start},
            "message_count": self._count,
            "topics_with_message_count": [t.metadata() for t in self._topics.values()],
            "compression_format": "",  # chunk compression is internal to the MCAP storage
            "compression_mode": "",
            "relative_file_paths": [f.path for f in self._files],
            "files": [f.metadata() for f in self._files],
            "custom_data": self.custom_data,
            "ros_distro": self.ros_distro,
        }

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

    def _make_reserve(self) -> None:
        try:
            with open(self._reserve, "wb") as f:
                f.write(bytes(RESERVE_BYTES))
                f.flush()
                os.fsync(f.fileno())
        except OSError as exc:
            self._reserve.unlink(missing_ok=True)
            self.salvage_notes.append(f"no space reserve ({exc})")

    def _drop_reserve(self) -> None:
        try:
            self._reserve.unlink(missing_ok=True)
        except OSError:
            pass

    def _fail(self, exc: OSError) -> None:
        if self.failure is None:
            self.failure = f"{type(exc).__name__}: {exc}"

    def _salvage(self) -> None:
        self._drop_reserve()
        self._uncommit()
        stream = self._stream
        if stream is None or stream.closed:
            return
        try:
            fd = stream.fileno()
            cut = stream.data_end if stream.data_end is not None else stream.good
            os.ftruncate(fd, cut)
            os.lseek(fd, cut, os.SEEK_SET)
            os.write(fd, _DATA_END + _FOOTER)
            os.fsync(fd)
            self.salvage_notes.append(f"{self.files[-1].name} cut back to its last complete record "
                                      f"({cut} bytes) and ended without a summary")
        except OSError as exc:
            self.salvage_notes.append(f"{self.files[-1].name} could not be ended ({exc}): readers "
                                      "recover its complete chunks")
        finally:
            try:
                stream.close()
            except OSError:
                pass

    def _open_file(self) -> None:
        name = f"{self.bag_dir.name}_{len(self._files)}.mcap"
        path = self.bag_dir / name
        self._stream = _CheckedFile(path)
        try:
            self._mcap = self._mw.Writer(self._stream, chunk_size=self.chunk_size,
                                         compression=self._compression, enable_crcs=True)
            self._mcap.start(profile="ros2", library=self.library)
            self._files.append(_FileInfo(name))
            self._channel_ids, self._schema_ids = {}, {}
            self._pending = 0
            self._write_metadata_record()
            for info in self._topics.values():  # rosbag2 re-registers every topic after a split
                self._register(info)
            self._commit()
        except OSError:
            # A file that could not even be started holds nothing: it goes, the bag ends with
            # the files before it (salvage sees no open stream).
            self._stream.close()
            self._stream = None
            path.unlink(missing_ok=True)
            if self._files and self._files[-1].path == name:
                self._files.pop()
            raise

    def _register(self, info: _TopicInfo) -> None:
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
        self._stream.data_end = self._stream.good   # a failed finish() is cut back to here
        self._mcap.finish()
        os.fsync(self._stream.fileno())
        self._stream.close()
        self._snapshot()   # the file's last chunk is on disk now

    def _split(self) -> None:
        self._close_file()
        self._open_file()

    def _write_metadata_yaml(self) -> None:
        from protocad_ros.atomic import atomic_write_text

        info = self.metadata()
        if self.failure is not None:
            info["custom_data"] = {**(info["custom_data"] or {}), "protocad_write_error": self.failure,
                                   "protocad_messages_lost_after_error": str(self.lost_after_failure)}
        atomic_write_text(self.bag_dir / "metadata.yaml", yaml_cpp_dump({"rosbag2_bagfile_information": info}))


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
