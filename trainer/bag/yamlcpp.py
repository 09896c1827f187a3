"""YAML the way rosbag2 writes it (yaml-cpp's block style), so that metadata.yaml and the
channels' offered_qos_profiles are byte for byte what a ROS 2 install writes. PyYAML cannot be
told to emit yaml-cpp's quoting and indentation rules; this small emitter does.
"""
from __future__ import annotations

import json
import re
from typing import Any, Mapping

import numpy as np

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


