"""`ProtocadNode`: the rclpy Node every protocad node derives from, so that no message, service
request, parameter change or timer can kill a node.

- Every subscription, service and timer callback is guarded: an exception a callback did not
  handle itself is counted (`callback_errors`, per callback name in `callback_error_counts`,
  shown on /diagnostics by each node) and logged at most once a second per callback, and the
  node goes on. Callbacks still reject bad input themselves, with their own counters; the guard
  is the net under them (a bug, or an input class nobody thought of).
- A service whose callback failed answers with `success=False` and the reason (when its
  response has those fields) instead of no answer.
- A refused run-time parameter that was never declared names itself: rclpy's own reason is
  "Invalid access to undeclared parameter(s): []" (it consumes the generator it prints).
"""
from __future__ import annotations

import collections
import functools
import traceback
from typing import Any, Callable

from rclpy.exceptions import ParameterNotDeclaredException
from rclpy.node import Node

from sim_bridge.nodekit.rosnode import KeyThrottle


class ProtocadNode(Node):
    def __init__(self, node_name: str, **kw: Any):
        #: The node's counters on /diagnostics (each node fills its own keys in).
        self.counters: dict[str, int] = {}
        #: `-p` names no parameter table declares (rosnode.declare_all fills it in).
        self.unknown_parameters: list[str] = []
        self.callback_errors = 0
        self.callback_error_counts: collections.Counter[str] = collections.Counter()
        super().__init__(node_name, **kw)
        self._guard_throttle = KeyThrottle(self.get_logger())

    # ------------------------------------------------------------------ guards
    def guard(self, fn: Callable, name: str, on_error: Callable[[tuple, BaseException], Any] | None = None) -> Callable:
        """`fn` that never raises an Exception: it counts, logs (throttled) and returns
        `on_error(args, exc)` (default None). functools.wraps keeps fn's signature, which rclpy
        reads to decide whether a subscription callback also gets the MessageInfo."""

        @functools.wraps(fn)
        def guarded(*args: Any) -> Any:
            try:
                return fn(*args)
            except Exception as exc:  # noqa: BLE001  the point of the guard
                self.callback_errors += 1
                self.callback_error_counts[name] += 1
                where = traceback.extract_tb(exc.__traceback__)[-1]
                throttle = getattr(self, "_guard_throttle", None) or KeyThrottle(self.get_logger())
                throttle.warning(
                    f"guard:{name}", f"{name} failed and was skipped: {type(exc).__name__}: {exc} "
                    f"(at {where.filename.rsplit('/', 1)[-1]}:{where.lineno}; "
                    f"{self.callback_error_counts[name]} so far)")
                return on_error(args, exc) if on_error is not None else None

        return guarded

    def create_subscription(self, msg_type, topic, callback, qos_profile, **kw):
        return super().create_subscription(msg_type, topic, self.guard(callback, f"subscription {topic}"),
                                           qos_profile, **kw)

    def create_service(self, srv_type, srv_name, callback, **kw):
        def failed(args: tuple, exc: BaseException) -> Any:
            response = args[1] if len(args) > 1 else srv_type.Response()
            if hasattr(response, "success"):
                response.success = False
            if hasattr(response, "message"):
                response.message = f"internal error: {type(exc).__name__}: {exc}"
            return response

        return super().create_service(srv_type, srv_name, self.guard(callback, f"service {srv_name}", failed),
                                      **kw)

    def create_timer(self, timer_period_sec, callback, *args, **kw):
        name = getattr(callback, "__name__", "timer")
        return super().create_timer(timer_period_sec, self.guard(callback, f"timer {name}"), *args, **kw)

    # ------------------------------------------------------------------ parameters
    def set_parameters_atomically(self, parameter_list):
        unknown = [p.name for p in parameter_list if not self.has_parameter(p.name)]
        try:
            return super().set_parameters_atomically(parameter_list)
        except ParameterNotDeclaredException:
            raise ParameterNotDeclaredException(unknown) from None
