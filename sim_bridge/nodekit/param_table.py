"""A node's parameter table, without ROS: what --help, the docs, the launchers and the trainer's
command lines read (rclpy is not needed to import it; sim_bridge.nodekit.rosnode declares a table
on a node).

- `Param`: one row of a node's parameter table. The same table declares the ROS parameters
  (rosnode.declare_all: ParameterDescriptor with description, range, read_only), prints `--help`
  (`help_epilog`; or generates a node's own command line: trainer.settings.table_settings), and
  is what msgs_docs documents. `with_defaults`: the table with a command line's values as the
  declared defaults.
- `ConfigError`: a node cannot start with the given parameters.
- The rows every node shares: `strict_param`, `autostart_param`, `remote_lifecycle_param`,
  `executor_param`.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Sequence

#: Parameters every rclpy node has (never reported as unknown).
_BUILTIN_PARAMS = ("use_sim_time", "start_type_description_service")
_BUILTIN_PREFIXES = ("qos_overrides.",)


def is_builtin_param(name: str) -> bool:
    """A parameter every rclpy node has (never reported as unknown)."""
    return name in _BUILTIN_PARAMS or name.startswith(_BUILTIN_PREFIXES)


class ConfigError(Exception):
    """A node cannot start with the given parameters (message says why and what is valid)."""


@dataclass(frozen=True)
class Param:
    name: str
    default: bool | int | float | str | tuple[str, ...]   # a tuple: a string array
    description: str
    read_only: bool = True
    range: tuple[float, float] | None = None   # inclusive, for int and float parameters
    choices: tuple[str, ...] | None = None     # for string parameters
    units: str = ""

    @property
    def type_name(self) -> str:
        return {bool: "bool", int: "int", float: "double", str: "string", tuple: "string[]"}[type(self.default)]

    @property
    def ros_default(self) -> Any:
        """The default as declare_parameter takes it (a list for a string array)."""
        return list(self.default) if isinstance(self.default, tuple) else self.default

    def check(self, value: Any) -> str | None:
        """Reason why `value` is invalid (choices; ranges are also enforced by rclpy), or None."""
        if self.choices and value not in self.choices:
            return f"{self.name}={value!r} is not one of {', '.join(self.choices)}"
        if self.range is not None and not (self.range[0] <= value <= self.range[1]):
            return f"{self.name}={value!r} is out of range [{self.range[0]}, {self.range[1]}]"
        return None

    def help_line(self) -> str:
        extra = []
        if self.choices:
            extra.append("{" + "|".join(self.choices) + "}")
        if self.range is not None:
            lo, hi = self.range
            if isinstance(self.default, float):
                def fmt(v):
                    return f"{v:g}"
            else:
                def fmt(v):
                    return str(int(v))
            extra.append(f"range [{fmt(lo)}, {fmt(hi)}]")
        if self.units:
            extra.append(self.units)
        extra.append("read-only" if self.read_only else "settable at run time")
        default = repr(self.default) if isinstance(self.default, str) else self.ros_default
        return (f"  {self.name} ({self.type_name}, default {default}; {', '.join(extra)})\n"
                f"      {self.description}")

    def is_of_type(self, value: Any) -> bool:
        """Whether `value` is of this row's type (a run-time change rclpy would refuse otherwise)."""
        if isinstance(self.default, tuple):
            return isinstance(value, (list, tuple)) and all(isinstance(x, str) for x in value)
        if isinstance(self.default, bool):
            return isinstance(value, bool)
        if isinstance(self.default, int):
            return isinstance(value, int) and not isinstance(value, bool)
        if isinstance(self.default, float):
            return isinstance(value, float)
        return isinstance(value, str)


def help_epilog(params: Sequence[Param], example: str) -> str:
    return ("ROS parameters (set with --ros-args -p NAME:=VALUE):\n"
            + "\n".join(p.help_line() for p in params)
            + "\n\nROS arguments: everything after --ros-args, e.g. -r __ns:=/robot1 (namespace,"
            " default /protocad),\n  --log-level debug.\n\nExample:\n  " + example)


def with_defaults(params: Sequence[Param], values: dict[str, Any]) -> tuple[Param, ...]:
    """The table with `values` (a node's own command line's) as the declared defaults, each
    of its row's type: a `-p` override still wins over them."""
    def typed(p: Param, v: Any) -> Any:
        return tuple(str(x) for x in v) if isinstance(p.default, tuple) else type(p.default)(v)

    return tuple(dataclasses.replace(p, default=typed(p, values[p.name])) if p.name in values else p
                 for p in params)


EXECUTORS = ("events", "single")


def strict_param() -> Param:
    return Param("strict", False, "Refuse to start (exit 2) on an unknown -p parameter, e.g. a "
                 "typo like tsk:=walker_walk; without it the node starts, warns and reports "
                 "WARN on /diagnostics (unknown_parameters).", read_only=True)


def autostart_param() -> Param:
    return Param("autostart", True, "Configure and activate at start (one command runs the "
                 "node); false: the node starts unconfigured and waits for lifecycle "
                 "transitions (ros2 lifecycle set NODE configure, then activate).")


def remote_lifecycle_param() -> Param:
    return Param("remote_lifecycle", True, "Accept lifecycle transitions from other processes "
                 "(the change_state service, what `ros2 lifecycle set` calls). false: every "
                 "request is refused and counted (remote_transitions_refused); the node still "
                 "runs its own autostart and shutdown. Off in protocad-fleet: anyone on the "
                 "domain could otherwise stop a fleet's nodes.", read_only=True)


def executor_param(default: str = "events") -> Param:
    return Param("executor", default, "rclpy executor spinning the node's callbacks: events = "
                 "rclpy.experimental.EventsExecutor (lower latency per callback), single = "
                 "SingleThreadedExecutor (the classic wait-set executor).", choices=EXECUTORS)
