"""`RobotOutput`: the policy node's answer on its way to a robot. For each answered observation
it decides what goes out (the model's action, or the safe action while disabled), sends the
command (CommandOutput) and feeds the watchdog; it reports its state on /diagnostics. The
policy node constructs it with its parameters and calls it from its lifecycle hooks and its
answer (protocad_ros/node/action_publishing.py); it owns the robot-facing state.

The safe action: `zero` = action 0 through the map (each joint at its offset); `hold` = the last
command sent (zero before any). It goes through the rate limit like any command.

Without command_output (a real-time simulator: latest_only) the watchdog reports but sends
nothing: the contract's `action` answers observations one for one, stamped like them, and the
sim bridge takes an action only as the answer to an observation it published and that is not
answered yet (sim_bridge/bridge/action_intake.py); a safe action with no observation to answer
would be refused there (rejected_stale_stamp or rejected_duplicate) and recorded as an answer
that never was. A bridge whose observations stopped is not stepping either.
"""
from __future__ import annotations

import threading
from typing import Any, Callable

import numpy as np

from protocad_ros.robot.command_output import CommandOutput
from protocad_ros.robot.fail_safe import EnableSwitch, Watchdog

LEVELS = ("OK", "WARN", "ERROR")


def enabled_at_start(value: str, command_output: str) -> bool:
    """auto: disabled when commands go to a robot (a person enables it), enabled otherwise."""
    return {"true": True, "false": False}.get(value, not command_output)


class RobotOutput:
    def __init__(self, node, params: dict[str, Any], count: Callable[..., None]):
        self._node = node
        self._lock = threading.Lock()   # the answer, the watchdog's timer and the switch
        self.safe_kind = params["safe_action"]
        self.map_path = params["command_map"]
        self.commands = CommandOutput(node, params["command_output"], params["command_topic"],
                                      params["trajectory_time_from_start_s"], count)
        # Armed in real-time use only: in lock-step a bridge waits for this node, and silence
        # between episodes or while the bridge is paused is normal.
        realtime = bool(params["command_output"]) or bool(params["latest_only"])
        self.watchdog = (Watchdog(node, params["input_timeout_s"], self._on_watchdog, count)
                         if realtime else None)
        self.switch = EnableSwitch(node, enabled_at_start(params["enabled_at_start"], params["command_output"]),
                                   self._on_switch, count)

    # ------------------------------------------------------------------ lifecycle
    def configure(self, action_names) -> None:
        self.commands.configure(self.map_path, action_names)

    def activate(self) -> None:
        self._disarm()
        if self.commands.kind:
            self._node.get_logger().info(
                f"commands as {self.commands.kind} on {self.commands.topic} for joints "
                f"{list(self.commands.joint_map.joint_names)}; " + (
                    "enabled" if self.switch.enabled else
                    f"DISABLED (safe action {self.safe_kind}) until enabled on ~/enable or the enable topic")
                + (f"; watchdog {self.watchdog.timeout_s:g} s" if self.watchdog is not None else ""))

    def deactivate(self) -> None:
        self._disarm()

    def cleanup(self) -> None:
        self._disarm()
        self.commands.release()

    def _disarm(self) -> None:
        if self.watchdog is not None:
            with self._lock:
                self.watchdog.disarm()

    # ------------------------------------------------------------------ the answer
    def answer(self, action: np.ndarray, stamp_ns: int) -> np.ndarray:
        """The action that answers this observation on the contract topic (the model's, or the
        safe action while disabled); its command goes out on command_topic first."""
        with self._lock:
            if self.watchdog is not None:
                self.watchdog.fed()
            out = action if self.switch.enabled else self.safe_action(action.shape)
            self.commands.send(out, stamp_ns, safe=not self.switch.enabled)
        return np.asarray(out, np.float32)

    def safe_action(self, shape) -> np.ndarray:
        if self.safe_kind == "hold" and self.commands.last is not None:
            return self.commands.action_of(self.commands.last)
        return np.zeros(shape, np.float64)

    def _on_watchdog(self) -> None:
        """The watchdog's timer: the safe action again (the node's executor thread)."""
        with self._lock:
            if self.commands.pub is None or self.commands.joint_map is None:
                return
            # No observation to stamp it with: stamp 0, which a joint_trajectory_controller
            # reads as "start now".
            self.commands.send(self.safe_action(len(self.commands.joint_map.joint_names)), 0, safe=True)

    def _on_switch(self, enabled: bool) -> None:
        if enabled:
            # A fresh start: the filter's state is from before the pause, and the watchdog
            # waits for the first observation answered with the model's command.
            restart = getattr(self._node, "restart_episode", None)
            if restart is not None:
                restart()
            if self.watchdog is not None:
                self.watchdog.disarm()

    # ------------------------------------------------------------------ diagnostics
    def report(self, values: dict[str, Any], level: str, message: str) -> tuple[str, str]:
        """Adds this part's keys to the node's diagnostics `values`; returns the node's level
        and message, or this part's where it is as bad or worse: ERROR while the watchdog is
        tripped, WARN while disabled."""
        tripped = self.watchdog is not None and self.watchdog.tripped
        joint_map, last = self.commands.joint_map, self.commands.last
        values.update({
            "enabled": self.switch.enabled, "watchdog_armed": self.watchdog is not None,
            "watchdog_tripped": tripped, "command_output": self.commands.kind,
            "command_topic": self.commands.topic, "safe_action": self.safe_kind,
            "command_joints": ",".join(joint_map.joint_names) if joint_map is not None else "",
            "last_command": "" if last is None else ",".join(f"{v:.6g}" for v in last)})
        mine, why = (("ERROR", self.watchdog.reason()) if tripped else
                     ("WARN", "disabled: sending the safe action (enable with ~/enable or the enable topic)")
                     if not self.switch.enabled else ("OK", ""))
        if mine != "OK" and LEVELS.index(mine) >= LEVELS.index(level):
            return mine, why
        return level, message
