"""ROS messages to and from the YAML that ros2cli prints and reads.

rosidl_runtime_py (which ros2cli uses for this) is not among the pip-installable ROS wheels, so
the conversions `ros2 topic echo`, `ros2 service call` and `ros2 param dump` need are written
here, following its documented output: fields in declaration order, block style, arrays and
strings longer than the truncate length cut with a trailing '...', `bytes` as characters,
`--no-arr`/`--no-str` replacing values by a placeholder that names the type and length.
"""
from __future__ import annotations

import array
import importlib
import sys
from collections import OrderedDict
from typing import Any

import numpy as np
import yaml
from rosidl_parser import definition as D

from trainer.bag.rosmsg import TypeSupportError, interface_module

_SEQUENCES = (list, tuple, array.array, np.ndarray)


class _Dumper(yaml.SafeDumper):
    """Keeps field order (OrderedDict as a plain map) without touching PyYAML's global state."""


_Dumper.add_representer(OrderedDict, lambda d, data: d.represent_mapping(
    "tag:yaml.org,2002:map", data.items()))


def _type_name(t: Any) -> str:
    if isinstance(t, D.BasicType):
        return t.typename
    if isinstance(t, D.AbstractString):
        return "string"
    if isinstance(t, D.AbstractWString):
        return "wstring"
    if isinstance(t, D.NamespacedType):
        return "/".join(t.namespaced_name())
    if isinstance(t, D.NamedType):
        return t.name
    return "unknown"


def _array_placeholder(value: Any, field_type: Any) -> str:
    inner = _type_name(field_type.value_type)
    if isinstance(field_type, D.Array):
        return f"<array type: {inner}[{field_type.size}]>"
    if isinstance(field_type, D.BoundedSequence):
        return f"<sequence type: {inner}[{field_type.maximum_size}], length: {len(value)}>"
    if isinstance(field_type, D.UnboundedSequence):
        return f"<sequence type: {inner}, length: {len(value)}>"
    return "unknown"


def _value(v: Any, field_type: Any, truncate: int | None, no_arr: bool, no_str: bool) -> Any:
    if isinstance(v, bytes):
        cut = truncate is not None and len(v) > truncate
        text = "".join(map(chr, v[:truncate] if cut else v))
        return text + "..." if cut else text
    if isinstance(v, str):
        if no_str:
            return f"<string length: <{len(v)}>>"
        return v[:truncate] + "..." if truncate is not None and len(v) > truncate else v
    if isinstance(v, _SEQUENCES):
        if no_arr and field_type is not None:
            return _array_placeholder(v, field_type)
        cut = truncate is not None and len(v) > truncate
        items = [_value(x, None, truncate, no_arr, no_str) for x in (v[:truncate] if cut else v)]
        return items + ["..."] if cut else items
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, (bool, int, float)):
        return v
    return message_to_ordereddict(v, truncate_length=truncate, no_arr=no_arr, no_str=no_str)


def message_to_ordereddict(msg: Any, *, truncate_length: int | None = None, no_arr: bool = False,
                           no_str: bool = False) -> OrderedDict:
    """Field name -> plain Python value, in the message's declaration order."""
    return OrderedDict(
        (name, _value(getattr(msg, name, None), ftype, truncate_length, no_arr, no_str))
        for name, ftype in zip(msg.get_fields_and_field_types(), msg.SLOT_TYPES))


def message_to_yaml(msg: Any, *, truncate_length: int | None = None, no_arr: bool = False,
                    no_str: bool = False, flow_style: bool = False) -> str:
    """The block (or flow) YAML `ros2 topic echo` prints for one message."""
    return dump(message_to_ordereddict(msg, truncate_length=truncate_length, no_arr=no_arr,
                                       no_str=no_str), flow_style=flow_style)


def dump(data: Any, *, flow_style: bool = False) -> str:
    return yaml.dump(data, Dumper=_Dumper, allow_unicode=True, width=sys.maxsize,
                     default_flow_style=flow_style)


def message_to_csv(msg: Any, *, truncate_length: int | None = None, no_arr: bool = False,
                   no_str: bool = False) -> str:
    """Every leaf field, depth first, comma-separated (`ros2 topic echo --csv`)."""

    def leaf(v: Any, field_type: Any = None) -> str:
        if isinstance(v, _SEQUENCES):
            if no_arr and field_type is not None:
                return _array_placeholder(v, field_type)
            parts = [leaf(x) for x in (v[:truncate_length] if truncate_length is not None else v)]
            if truncate_length is not None and len(v) > truncate_length:
                parts.append("...")
            return ",".join(parts)
        if isinstance(v, (bool, bytes, float, int, str, np.number)):
            if no_str and isinstance(v, str):
                v = f"<string length: <{len(v)}>>"
            elif isinstance(v, (bytes, str)) and truncate_length is not None and len(v) > truncate_length:
                v = v[:truncate_length] + (b"..." if isinstance(v, bytes) else "...")
            return str(v)
        return message_to_csv(v, truncate_length=truncate_length, no_arr=no_arr, no_str=no_str)

    return ",".join(leaf(getattr(msg, n), t) for n, t in zip(msg.get_fields_and_field_types(), msg.SLOT_TYPES))


def set_message_fields(msg: Any, values: dict | None) -> None:
    """Fill `msg` from a YAML mapping (`ros2 service call ... '{a: 1}'`); unknown fields raise."""
    if not values:
        return
    if not isinstance(values, dict):
        raise TypeError(f"expected a mapping of field names to values, got {values!r}")
    fields = msg.get_fields_and_field_types()
    slot_types = dict(zip(fields, msg.SLOT_TYPES))
    for name, value in values.items():
        if name not in fields:
            raise AttributeError(f"'{type(msg).__name__}' has no field '{name}' "
                                 f"(fields: {', '.join(fields) or 'none'})")
        current = getattr(msg, name)
        ftype = slot_types[name]
        if hasattr(current, "get_fields_and_field_types"):
            set_message_fields(current, value)
            continue
        inner = getattr(ftype, "value_type", None)
        if isinstance(value, list) and inner is not None and hasattr(inner, "namespaced_name"):
            cls = interface_class("/".join(inner.namespaced_name()))
            items = []
            for v in value:
                item = cls()
                set_message_fields(item, v)
                items.append(item)
            value = items
        setattr(msg, name, value)


def interface_class(type_name: str, kind: str = "msg") -> Any:
    """`pkg/msg/Name` (or `pkg/Name`) -> the generated Python class; ValueError if unknown."""
    try:   # a name from the graph or the command line: checked before anything is imported
        module, name = interface_module(type_name, kind)
    except TypeSupportError as exc:
        raise ValueError(str(exc)) from None
    try:
        return getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError) as exc:
        raise ValueError(f"unknown interface type {type_name!r}: {exc}") from None
