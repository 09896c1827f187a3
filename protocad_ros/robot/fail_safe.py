"""What holds a robot when the policy's input stops or a supervisor says stop
(msgs_docs/policy.md#fail-safe): `Watchdog` (no fresh observation answered for input_timeout_s:
the safe action, repeated, and /diagnostics at ERROR) and `EnableSwitch` (std_srvs/SetBool on
`~/enable` and a latched std_msgs/Bool on `enable`). Each owns its state and its ROS entities;
what they do to the commands is the caller's (protocad_ros/robot/robot_output.py)."""
from __future__ import annotations

import time
from typing import Callable

from std_msgs.msg import Bool
from std_srvs.srv import SetBool

from sim_bridge.contract import qos

#: Checks per input_timeout_s: the watchdog trips at most timeout/CHECKS_PER_TIMEOUT late.
CHECKS_PER_TIMEOUT = 10


class Watchdog:
    """Armed by the first answered observation after start, activation or enable (before it,
    silence is a robot not started yet, not a stall); tripped when none followed for timeout_s.
    While tripped, `on_trip()` runs at once and then every timeout_s (a controller with a
    timeout of its own keeps hearing the safe action); `fed()` by the next answered observation
    clears it."""

    def __init__(self, node, timeout_s: float, on_trip: Callable[[], None], count: Callable[..., None]):
        self.timeout_s = float(timeout_s)
        self._on_trip = on_trip
        self._count = count
        self._log = node.get_logger()
        self._last_fed: float | None = None   # None: disarmed
        self._last_trip_sent = 0.0
        self.tripped_since: float | None = None
        # A periodic check rather than a timer reset per observation: the events executor's
        # timers follow a reset only in newer rclpy; this costs 10 wake-ups per timeout.
        self._timer = node.create_timer(self.timeout_s / CHECKS_PER_TIMEOUT, self.check)

    @property
    def tripped(self) -> bool:
        return self.tripped_since is not None

    def disarm(self) -> None:
        """Until the next observation: deactivated, or enabled again."""
        self._last_fed, self.tripped_since = None, None

    def fed(self) -> None:
        """A fresh observation was answered."""
        now = time.monotonic()
        if self.tripped_since is not None:
            self._count("watchdog_clears")
            self._log.info(f"input back after {now - self.tripped_since:.2f} s: watchdog cleared, "
                           "the model's commands go out again")
            self.tripped_since = None
        self._last_fed = now

    def check(self) -> None:
        if self._last_fed is None:
            return
        now = time.monotonic()
        if self.tripped_since is None:
            if now - self._last_fed < self.timeout_s:
                return
            self.tripped_since = now
            self._count("watchdog_trips", self.reason())
        elif now - self._last_trip_sent < self.timeout_s:
            return
        self._last_trip_sent = now
        self._on_trip()

    def reason(self) -> str:
        if self.tripped_since is None:
            return ""
        silent = time.monotonic() - self._last_fed
        return (f"watchdog: no fresh observation answered for {silent:.2f} s (input_timeout_s "
                f"{self.timeout_s:g}): sending the safe action")

    def destroy(self, node) -> None:
        node.destroy_timer(self._timer)


class EnableSwitch:
    """Enabled or not, switched by the service `~/enable` (node-private, answered with what
    changed) or by the latched topic `enable` (reliable + transient local, depth 1: a
    supervisor's last word reaches a node started after it). `on_change(enabled)` runs on
    each real switch (each one counted as enable_switches); a repeated word changes nothing."""

    def __init__(self, node, enabled: bool, on_change: Callable[[bool], None], count: Callable[..., None]):
        self.enabled = bool(enabled)
        self._on_change = on_change
        self._count = count
        self._log = node.get_logger()
        self.srv = node.create_service(SetBool, "~/enable", self._on_service)
        self.sub = node.create_subscription(Bool, "enable", self._on_topic, qos.announcement_qos())

    def set(self, enabled: bool, source: str) -> str:
        enabled = bool(enabled)
        word = "enabled" if enabled else "disabled"
        if enabled == self.enabled:
            return f"already {word}"
        self.enabled = enabled
        self._count("enable_switches")
        self._log.warning(f"{word} by {source}: " + (
            "the model's commands go out" if enabled else "the safe action goes out instead of the model's"))
        self._on_change(enabled)
        return word

    def _on_service(self, request, response):
        response.message = self.set(request.data, "the ~/enable service")
        response.success = True
        return response

    def _on_topic(self, msg) -> None:
        self.set(msg.data, f"{self.sub.topic_name}")
