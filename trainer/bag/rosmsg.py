"""ROS 2 message type support without rclpy: definitions, RIHS01 type hashes, message objects,
CDR encode/decode, read from the ament index the ROS wheels install (``share/<pkg>/msg/<Type>.msg``
and ``.json``).

What a library does not give here: rosbag2's message definition text (the .msg followed by every
dependency after a line of 80 ``=``, LocalMessageDefinitionSource byte for byte) and the type
hashes rosbag2 stores per channel; the CDR itself is mcap-ros2-support's. Decoding goes through
its public `mcap_ros2.decoder.DecoderFactory`. Encoding and the .msg parser are two private
pieces of it (`mcap_ros2._dynamic.serialize_dynamic`, the vendored rosidl parser): no public
library encodes CDR without a ROS installation, which protocad-online on a GPU box has not; the
version is pinned in setup.py for that reason.
"""
from __future__ import annotations

import json
import os
import re
import sys
from functools import lru_cache
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np
from mcap.records import Schema
from mcap_ros2._dynamic import serialize_dynamic
from mcap_ros2._vendor.rosidl_adapter.parser import parse_message_string
from mcap_ros2.decoder import DecoderFactory

DELIMITER = "=" * 80 + "\n"


class TypeSupportError(LookupError):
    """A message type could not be resolved in the ament index (or parsed)."""


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


#: The rosidl interface kinds a type name from the ROS graph may name (pkg/<kind>/Type).
INTERFACE_KINDS = ("msg", "srv", "action")


def interface_module(type_name: str, kind: str = "msg") -> tuple[str, str]:
    """('pkg.kind', 'Type'): the module to import for a type name that came from the ROS graph
    or a command line, and the class in it. Any participant can advertise any type string, and
    importing `pkg.kind` runs that module's code (`idlelib/idle/X` would start IDLE), so it is
    refused (TypeSupportError, nothing imported) unless it is `pkg/kind/Type` (or `pkg/Type`
    for `kind`) with every part an identifier (no dots), kind one of INTERFACE_KINDS, and pkg a
    package of the ament index (rosidl generates only those)."""
    parts = type_name.split("/")
    if len(parts) == 2:
        parts = [parts[0], kind, parts[1]]
    if len(parts) != 3 or not all(p.isidentifier() for p in parts):
        raise TypeSupportError(f"invalid interface type name {type_name!r}; expected 'pkg/{kind}/Type'")
    pkg, ns, name = parts
    if ns not in INTERFACE_KINDS:
        raise TypeSupportError(f"{type_name!r} is not an interface type ('{ns}' is not one of "
                               f"{', '.join(INTERFACE_KINDS)})")
    if not ament_package_exists(pkg):
        raise TypeSupportError(f"{type_name!r}: package {pkg!r} is not in the ament index "
                               "(not installed here): its types are not imported")
    return f"{pkg}.{ns}", name


def ament_package_exists(pkg: str) -> bool:
    """Whether `pkg` is registered in the ament resource index of a prefix (a marker file
    share/ament_index/resource_index/packages/<pkg>, what ament_index_python reads)."""
    if not pkg.isidentifier():
        return False
    return any((prefix / "share" / "ament_index" / "resource_index" / "packages" / pkg).is_file()
               for prefix in _prefixes())


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
    except Exception:  # noqa: BLE001 - not installed, or not in the resource index: look at the prefixes
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
    msgtype = normalize_type(msgtype)
    text = definition if definition is not None else message_definition(msgtype)
    try:
        return serialize_dynamic(msgtype, text)[msgtype]
    except Exception as exc:
        raise TypeSupportError(f"cannot build a CDR encoder for {msgtype}: {exc}") from exc


@lru_cache(maxsize=256)
def decoder_for(msgtype: str, definition: str | None = None) -> Callable[[bytes], Any]:
    """Cached lenient CDR decoder for a type (mcap_ros2's public DecoderFactory: it tolerates
    the trailing padding rclpy/FastCDR writes); definition defaults to the local ament index.
    The same decoder serves our own types and foreign ones, and needs no ROS installation
    (rclpy.serialization would, and only for types built here)."""
    msgtype = normalize_type(msgtype)
    text = definition if definition is not None else message_definition(msgtype)
    try:
        decoder = DecoderFactory().decoder_for("cdr", Schema(id=1, name=msgtype, encoding="ros2msg",
                                                             data=text.encode()))
    except Exception as exc:
        raise TypeSupportError(f"cannot build a CDR decoder for {msgtype}: {exc}") from exc
    if decoder is None:
        raise TypeSupportError(f"cannot build a CDR decoder for {msgtype}")
    return decoder


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


