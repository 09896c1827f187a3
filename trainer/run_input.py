"""A run directory read back is input: `--resume` and the tools that read runs take run.json,
config.yaml and the settings in them as a stranger could have written them. Each is checked for
size, type, nesting depth and paths before anything uses it, and every problem is one
ValueError line naming the file (the CLIs print it and exit 2):

- run.json must be a JSON object of at most MAX_RUN_FILE_BYTES, nested at most MAX_DEPTH deep;
  config.yaml a YAML mapping (safe-loaded: an unsafe tag is refused, not constructed) within the
  same bounds;
- `settings` sections must be mappings whose values have their fields' types;
- `logs` must be a list of paths inside the run directory (bags elsewhere are given again on
  the command line: a run.json must not make a trainer walk /proc).
"""
from __future__ import annotations

import json
import os
import types
import typing
from pathlib import Path
from typing import Any, Mapping

import yaml

#: Largest run.json / config.yaml read back (a real one is a few kB).
MAX_RUN_FILE_BYTES = 16 << 20
#: Deepest nesting of lists and mappings in them (a real one: 4).
MAX_DEPTH = 32


def _read_text(path: Path) -> str:
    try:
        size = path.stat().st_size
        if size > MAX_RUN_FILE_BYTES:
            raise ValueError(f"{path}: {size} bytes, more than the limit of {MAX_RUN_FILE_BYTES}")
        return path.read_text()
    except OSError as exc:
        raise ValueError(f"{path}: cannot read: {exc.strerror or exc}") from None
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not UTF-8 text") from None


def depth(value: Any, limit: int = MAX_DEPTH) -> int:
    """Nesting depth of lists/tuples/mappings in value, counted without recursion (a value
    nested deeper than `limit` is reported as limit + 1)."""
    deepest, stack = 0, [(value, 1)]
    while stack:
        v, d = stack.pop()
        if isinstance(v, Mapping):
            children = list(v.values())
        elif isinstance(v, (list, tuple)):
            children = list(v)
        else:
            continue
        deepest = max(deepest, d)
        if d > limit:
            return limit + 1
        stack.extend((c, d + 1) for c in children)
    return deepest


def _bounded(path: Path, value: Any) -> Any:
    if depth(value) > MAX_DEPTH:
        raise ValueError(f"{path}: nested more than {MAX_DEPTH} levels deep")
    return value


def load_json_object(path: str | os.PathLike) -> dict[str, Any]:
    """A JSON object from `path`, or one ValueError line (not JSON, nested too deep, not an
    object, too large)."""
    path = Path(path)
    text = _read_text(path)
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON ({exc})") from None
    except RecursionError:
        raise ValueError(f"{path}: nested too deeply to read (more than {MAX_DEPTH} levels)") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: holds a JSON {type(data).__name__}, not an object")
    return _bounded(path, data)


def load_yaml_mapping(path: str | os.PathLike) -> dict[str, Any]:
    """A YAML mapping from `path` (safe_load), or one ValueError line (not YAML, an unsafe or
    unknown tag, nested too deep, not a mapping, too large)."""
    path = Path(path)
    text = _read_text(path)
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        where = getattr(exc, "problem_mark", None)
        line = f" (line {where.line + 1})" if where is not None else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ValueError(f"{path}: not YAML this tool reads{line}: {problem}") from None
    except RecursionError:
        raise ValueError(f"{path}: nested too deeply to read (more than {MAX_DEPTH} levels)") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ValueError(f"{path}: holds a YAML {type(data).__name__}, not a mapping")
    return _bounded(path, data)


def matches(value: Any, hint: Any) -> bool:
    """Whether a JSON value fits a settings field's type hint (int, float, str, bool, None,
    unions, list[X], dict, Literal; other hints: accepted)."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if hint is Any:
        return True
    if origin in (typing.Union, types.UnionType):
        return any(matches(value, a) for a in args)
    if hint is type(None):
        return value is None
    if hint is bool:
        return isinstance(value, bool)
    if hint is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if hint is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if hint is str:
        return isinstance(value, str)
    if origin is list or hint is list:
        return isinstance(value, list) and (not args or all(matches(v, args[0]) for v in value))
    if origin is dict or hint is dict:
        return isinstance(value, dict)
    if origin is typing.Literal:
        return value in args
    return True


def check_settings_section(path: Path, key: str, cls: type, saved: Mapping[str, Any]) -> None:
    """ValueError naming the first field of `saved` whose value does not fit its type in
    `cls` (a settings dataclass); fields `cls` does not have are left to the caller."""
    hints = typing.get_type_hints(cls)
    for name, value in saved.items():
        if name in hints and not matches(value, hints[name]):
            raise ValueError(f"{path}: settings.{key}.{name} is {value!r} ({type(value).__name__}), "
                             f"not a {hints[name]}")


def check_logs(path: Path, run_dir: Path, logs: Any) -> list[str]:
    """run.json's `logs`: a list of paths, each inside `run_dir` (ValueError otherwise)."""
    if logs is None:
        return []
    if not isinstance(logs, list) or not all(isinstance(x, str) for x in logs):
        raise ValueError(f"{path}: 'logs' is not a list of paths")
    root = run_dir.resolve()
    for entry in logs:
        where = (run_dir / entry).resolve()
        if where != root and root not in where.parents:
            raise ValueError(f"{path}: logs entry {entry!r} lies outside the run directory; give "
                             "the bags on the command line (--logs) to train on them")
    return list(logs)
