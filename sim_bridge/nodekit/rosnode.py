"""rclpy plumbing shared by the protocad nodes (sim bridge, policy, recorder, ...): imports ROS
at its top; the parameter tables themselves (`Param`, `ConfigError`, the shared rows) are in
sim_bridge.nodekit.param_table, which imports without ROS.

- `declare_all`: declares a table with clear errors (`ConfigError`) for wrong types, values out
  of range, values outside a choice list; integers given for float parameters are accepted
  (`-p control_rate_hz:=10`), and so are true/false for a string parameter whose choices are
  those words; unknown `-p` overrides are reported with a warning.
- `install_parameter_guards`: run-time `set_parameters` handling of a declared table.
- `run_node`: the `main()` of a node: argparse (`--help` lists the ROS parameters; everything
  after `--ros-args` goes to ROS), spin, clean shutdown on Ctrl-C / SIGTERM (exit 0, no
  traceback), exit 2 on a configuration error.
- `Percentiles`, `make_status`, `KeyThrottle`: diagnostics and logging helpers.
"""
from __future__ import annotations

import argparse
import collections
import os
import signal
import sys
import threading
import time
import traceback
from typing import Any, Callable, Iterable, Sequence

import numpy as np
import rclpy
import rclpy.logging
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    ParameterType,
    SetParametersResult,
)
from rclpy.duration import Duration
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.experimental import EventsExecutor
from rclpy.parameter import Parameter
from rclpy.signals import SignalHandlerOptions
from rclpy.utilities import remove_ros_args

from sim_bridge.nodekit.param_table import (
    ConfigError,
    Param,
    help_epilog,
    is_builtin_param,
)

__all__ = ["SHUTDOWN_BUDGET_S", "KeyThrottle", "Percentiles", "arm_shutdown_watchdog", "declare_all",
           "descriptor", "flush_publishers", "install_parameter_guards", "make_executor", "make_status",
           "run_node"]


def descriptor(p: Param) -> ParameterDescriptor:
    """The row as rclpy declares it (description, range, read_only, choices as a constraint)."""
    types = {bool: ParameterType.PARAMETER_BOOL, int: ParameterType.PARAMETER_INTEGER,
             float: ParameterType.PARAMETER_DOUBLE, str: ParameterType.PARAMETER_STRING,
             tuple: ParameterType.PARAMETER_STRING_ARRAY}   # the type an empty list cannot say
    d = ParameterDescriptor(name=p.name, type=types[type(p.default)],
                            description=p.description, read_only=p.read_only)
    if p.choices:
        d.additional_constraints = "one of: " + ", ".join(p.choices)
    if p.range is not None:
        lo, hi = p.range
        if isinstance(p.default, float):
            d.floating_point_range = [
                FloatingPointRange(from_value=float(lo), to_value=float(hi), step=0.0)]
        else:
            d.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=1)]
    return d


def declare_all(node, params: Sequence[Param]) -> dict[str, Any]:
    """Declare every parameter of the table; returns {name: value}. Raises ConfigError."""
    overrides = getattr(node, "_parameter_overrides", None)  # rclpy keeps -p values here
    node.unknown_parameters = []
    values: dict[str, Any] = {}
    for p in params:
        if isinstance(overrides, dict) and isinstance(p.default, float) and p.name in overrides:
            given = overrides[p.name].value
            if isinstance(given, int) and not isinstance(given, bool):
                overrides[p.name] = Parameter(p.name, Parameter.Type.DOUBLE, float(given))
        if isinstance(overrides, dict) and p.choices and p.name in overrides:
            # `-p x:=true` reaches rclpy as a bool; a string parameter whose choices are the
            # words true and false (enabled_at_start: auto, true, false) takes the word.
            given = overrides[p.name].value
            if isinstance(given, bool) and str(given).lower() in p.choices:
                overrides[p.name] = Parameter(p.name, Parameter.Type.STRING, str(given).lower())
        # An empty list says no type: rclpy would declare a byte array, which refuses a `-p`
        # list of strings. Declared by its type instead, then given its empty value.
        untyped = p.default == ()
        try:
            value = node.declare_parameter(p.name, Parameter.Type.STRING_ARRAY if untyped else p.ros_default,
                                           descriptor(p)).value
            if untyped and value is None and not p.read_only:
                node.set_parameters([Parameter(p.name, Parameter.Type.STRING_ARRAY, [])])
        except ParameterException as e:
            raise ConfigError(f"parameter {p.name}: {e}".replace("\n", " ")) from None
        if isinstance(p.default, tuple):
            value = list(value or [])
        reason = p.check(value)
        if reason:
            raise ConfigError(reason)
        values[p.name] = value
    if isinstance(overrides, dict):
        known = {p.name for p in params}
        unknown = sorted(n for n in overrides if n not in known and not is_builtin_param(n))
        node.unknown_parameters = unknown
        if unknown and values.get("strict"):
            raise ConfigError(f"unknown parameter(s) {unknown} (strict:=true); valid: "
                              f"{', '.join(sorted(known))}")
        for name in unknown:
            node.get_logger().warning(
                f"unknown parameter {name!r} ignored (valid: {', '.join(sorted(known))})")
    return values


def install_parameter_guards(node, params: Sequence[Param], apply: Callable[[str, Any], None],
                             on_reject: Callable[[str], None]) -> None:
    """Run-time `set_parameters` handling for a node declared with `declare_all`.

    A pre-set callback reports every change that will be refused (unknown name, read-only,
    wrong type, out of range, not one of the choices) through `on_reject(reason)` (a log line
    and a diagnostics count); rclpy itself refuses unknown names, read-only, type and range
    violations, the on-set callback below refuses choice violations. Accepted values are
    handed to `apply(name, value)`.
    """
    table = {p.name: p for p in params}

    def _pre(changes):
        try:
            _report(changes)
        except Exception as exc:  # noqa: BLE001  reporting must never block the change itself
            on_reject(f"could not check the change: {type(exc).__name__}: {exc}")
        return changes

    def _report(changes):
        for c in changes:
            p = table.get(c.name)
            if p is None:
                if not is_builtin_param(c.name):
                    on_reject(f"unknown parameter {c.name!r}")
            elif p.read_only:
                on_reject(f"parameter {c.name} is read-only")
            elif not p.is_of_type(c.value):
                on_reject(f"{c.name}={c.value!r} is not a {p.type_name}")
            else:
                reason = p.check(c.value)
                if reason:
                    on_reject(reason)

    def _on_set(changes):
        try:
            return _apply(changes)
        except Exception as exc:  # noqa: BLE001
            on_reject(f"applying {[c.name for c in changes]} failed: {type(exc).__name__}: {exc}")
            return SetParametersResult(successful=False, reason=f"internal error: {exc}")

    def _apply(changes):
        for c in changes:
            p = table.get(c.name)
            reason = p.check(c.value) if p is not None else None
            if reason:
                return SetParametersResult(successful=False, reason=reason)
        for c in changes:
            if c.name in table:
                apply(c.name, c.value)
        return SetParametersResult(successful=True)

    node.add_pre_set_parameters_callback(_pre)
    node.add_on_set_parameters_callback(_on_set)


class KeyThrottle:
    """Log at most once per `period_s` per key (rclpy's throttling is per call site, which
    would let one kind of bad input hide another)."""

    def __init__(self, logger, period_s: float = 1.0):
        self._logger, self._period = logger, period_s
        self._last: dict[str, float] = {}
        self._lock = threading.Lock()

    def warning(self, key: str, message: str) -> None:
        now = time.monotonic()
        with self._lock:
            if now - self._last.get(key, -1e9) < self._period:
                return
            self._last[key] = now
        self._logger.warning(message)


class Percentiles:
    """Rolling window of samples (e.g. latencies in seconds) with percentile read-out."""

    def __init__(self, window: int = 2000):
        self._buf: collections.deque[float] = collections.deque(maxlen=window)
        self._lock = threading.Lock()
        self.count = 0

    def add(self, x: float) -> None:
        with self._lock:
            self._buf.append(float(x))
            self.count += 1

    def values(self) -> np.ndarray:
        with self._lock:
            return np.asarray(self._buf, np.float64)

    def percentile(self, q: float) -> float:
        v = self.values()
        return float(np.percentile(v, q)) if v.size else float("nan")


def make_status(name: str, hardware_id: str, values: dict[str, Any], level: str = "OK",
                message: str = ""):
    """DiagnosticStatus with KeyValue strings (floats with 6 significant digits)."""
    def fmt(v: Any) -> str:
        if isinstance(v, bool):
            return str(v).lower()
        if isinstance(v, float):
            return f"{v:.6g}"
        return str(v)

    st = DiagnosticStatus()
    st.level = {"OK": DiagnosticStatus.OK, "WARN": DiagnosticStatus.WARN,
                "ERROR": DiagnosticStatus.ERROR, "STALE": DiagnosticStatus.STALE}[level]
    st.name, st.hardware_id, st.message = name, hardware_id, message or level
    st.values = [KeyValue(key=str(k), value=fmt(v)) for k, v in values.items()]
    return st


def flush_publishers(publishers: Iterable[Any], timeout_s: float) -> list[str]:
    """Give reliable readers up to `timeout_s` (in all) to acknowledge, or have repaired, every
    sample of `publishers` before the node exits: readers acknowledge lazily (at the writer's
    next heartbeat) and a reader that was stalled (a frozen recorder) still has a backlog that
    exiting would lose. Returns the topics with samples left unacknowledged."""
    deadline = time.monotonic() + float(timeout_s)
    left_over = []
    for pub in publishers:
        left = max(0.0, deadline - time.monotonic())
        if not pub.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9))):
            left_over.append(pub.topic_name)
    return left_over


def make_executor(kind: str):
    if kind == "events":
        return EventsExecutor()
    return SingleThreadedExecutor()


#: Seconds a node may take to close once asked to stop; then the process exits regardless. DDS
#: can hold a closing participant for its peers' lease (a peer that died without a clean
#: shutdown: 20 s seen), and a Ctrl-C must not wait for that. A node sets `shutdown_budget_s`
#: for a longer close of its own (the recorder drains its readers first).
SHUTDOWN_BUDGET_S = 5.0


def arm_shutdown_watchdog(budget_s: float, prog: str, code: Callable[[], int]) -> threading.Timer:
    """A daemon timer that ends the process (os._exit with code()) after budget_s: the bound
    on a node's shutdown. What it skips is the rest of a clean close; checkpoints and bags are
    written so that an abrupt end leaves them valid (atomic files, recoverable chunks)."""
    def expire() -> None:
        print(f"[{prog}] shutdown took longer than {budget_s:g} s (a peer that left DDS "
              "uncleanly?): exiting now", file=sys.stderr, flush=True)
        os._exit(code())

    timer = threading.Timer(budget_s, expire)
    timer.daemon = True
    timer.start()
    return timer


def _node_args(argv: Sequence[str], *, prog: str, description: str, params: Iterable[Param], example: str,
               parser: argparse.ArgumentParser | None) -> argparse.Namespace:
    """The node's own command line (ROS arguments removed); argparse exits here on --help or a
    bad plain argument."""
    if parser is None:
        parser = argparse.ArgumentParser(
            prog=prog, description=description, epilog=help_epilog(list(params), example),
            formatter_class=argparse.RawDescriptionHelpFormatter)
    return parser.parse_args(remove_ros_args(argv)[1:])


def _stop_on_signals(prog: str) -> threading.Event:
    """Our own SIGINT/SIGTERM handlers (not rclpy's, which would shut the context down at
    once): the node then closes with a live context, so its last diagnostics and log lines
    still go out, and reliable readers get the last samples. Returns the event they set."""
    stop = threading.Event()

    def _on_signal(signum, _frame):
        if stop.is_set() and signum == signal.SIGINT:
            raise KeyboardInterrupt   # a second Ctrl-C: stop waiting for a clean close
        stop.set()
        # said at once, so a user knows the first Ctrl-C was heard (the close may take a moment)
        print(f"[{prog}] {signal.Signals(signum).name}: stopping (Ctrl-C again to skip the "
              "clean close)", file=sys.stderr, flush=True)

    signal.signal(signal.SIGINT, _on_signal)
    signal.signal(signal.SIGTERM, _on_signal)
    return stop


def _spin_until_done(node: Any, stop: threading.Event) -> int:
    """Spins ``node`` until it is done, a signal stops it or ROS shuts down; its exit code."""
    executor = make_executor(getattr(node, "executor_kind", "single"))
    executor.add_node(node)
    done = getattr(node, "done", None) or threading.Event()
    while rclpy.ok() and not done.is_set() and not stop.is_set():
        executor.spin_once(timeout_sec=0.1)
    return int(getattr(node, "exit_code", 0))


def _close_node(node: Any, prog: str) -> None:
    try:
        close = getattr(node, "close", None)
        if close is not None:
            close()
    except (Exception, KeyboardInterrupt) as e:  # noqa: BLE001 - never a traceback on the way out
        print(f"[{prog}] error while shutting down: {e!r}", file=sys.stderr)
    try:
        node.destroy_node()
    except Exception:  # noqa: BLE001 - on the way out
        pass


def run_node(make_node: Callable[..., Any], *, prog: str, description: str = "",
             params: Iterable[Param] = (), example: str = "", argv: Sequence[str] | None = None,
             parser: argparse.ArgumentParser | None = None) -> int:
    """main() of a protocad node; returns the exit code.

    `make_node()` builds the node after rclpy.init (raise ConfigError for bad configuration);
    its settings are ROS parameters (`params`, listed by --help). A node with a command line of
    its own (the recorder, which speaks `ros2 bag record`'s) passes its `parser` instead and
    gets `make_node(args)`. The node may define `close()` (stop threads, flush) and `done`
    (threading.Event set when it finished on its own, e.g. after max_episodes) and `exit_code`.
    """
    argv = list(sys.argv if argv is None else argv)
    try:
        own_args = parser is not None
        args = _node_args(argv, prog=prog, description=description, params=params, example=example,
                          parser=parser)
        stop = _stop_on_signals(prog)
        rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    except KeyboardInterrupt:
        return 0
    log = rclpy.logging.get_logger(prog)
    node = None
    code = 0
    try:
        try:
            node = make_node(args) if own_args else make_node()
        except ConfigError as e:
            log.error(f"configuration error: {e}")
            return 2
        except (KeyboardInterrupt, ExternalShutdownException):
            return 0
        except Exception as e:  # noqa: BLE001 - any other start-up failure: logged with its traceback, exit 1
            log.error(f"could not start: {type(e).__name__}: {e}\n{traceback.format_exc()}")
            return 1
        code = _spin_until_done(node, stop)
    except (KeyboardInterrupt, ExternalShutdownException):
        code = 0
    finally:
        watchdog = arm_shutdown_watchdog(float(getattr(node, "shutdown_budget_s", SHUTDOWN_BUDGET_S)),
                                         prog, lambda: code)
        if node is not None:
            _close_node(node, prog)
        try:
            rclpy.try_shutdown()
        except Exception:  # noqa: BLE001 - on the way out
            pass
        watchdog.cancel()
    return code
