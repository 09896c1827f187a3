"""The policy's actions as a robot's commands (msgs_docs/policy.md#a-robots-command-interface):
through the joint map (sim_bridge/contract/joint_map.py) into the robot's joint order and units,
rate limited per joint, and published on `command_topic` as what a ros2_control controller
takes: std_msgs/Float64MultiArray (a forward command controller) or
trajectory_msgs/JointTrajectory (one point). Without `command_output` nothing is published, but
the commands are still tracked (identity map), so `hold` means the same thing on every path:
the last command sent."""
from __future__ import annotations

import time
from typing import Callable, Sequence

import numpy as np
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Float64MultiArray
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from sim_bridge.contract import topics
from sim_bridge.contract.joint_map import JointMap, JointMapError, identity_map, load_joint_map
from sim_bridge.nodekit.param_table import ConfigError

KINDS = ("", "float64_multi_array", "joint_trajectory")
#: History depth of command_topic (rclcpp's default, what the controllers subscribe with).
COMMAND_DEPTH = 10


def command_qos() -> QoSProfile:
    """ros2_control's forward_command_controller and joint_trajectory_controller subscribe with
    rclcpp's default profile (reliable, volatile, keep last 10): a reliable writer matches it
    (and best-effort readers too); volatile, because a controller that connects late must never
    get an old command; only the newest command matters, so keep last, no deeper than theirs."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=COMMAND_DEPTH,
                      reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)


class CommandOutput:
    """Owns the command publisher (a lifecycle one: nothing goes out unless the node is active),
    the joint map (loaded by configure) and the last command sent, with its time."""

    def __init__(self, node, kind: str, topic: str, time_from_start_s: float,
                 count: Callable[[str], None]):
        if kind not in KINDS:
            raise ConfigError(f"command_output={kind!r} is not one of {', '.join(repr(k) for k in KINDS)}")
        self.kind = kind
        self._time_from_start_ns = int(round(time_from_start_s * 1e9))
        self._count = count
        self.joint_map: JointMap | None = None
        self.last: np.ndarray | None = None   # the last command sent (robot units, robot order)
        self._last_t = 0.0
        self.pub = None
        self.topic = ""
        if kind:
            msgtype = Float64MultiArray if kind == "float64_multi_array" else JointTrajectory
            self.pub = node.create_lifecycle_publisher(msgtype, topic, command_qos())
            self.topic = self.pub.topic_name

    def configure(self, map_path: str, action_names: Sequence[str]) -> None:
        """Load and check the map against the served policy's actions (ConfigError, one line)."""
        if map_path and not self.kind:
            raise ConfigError(f"command_map:={map_path} without command_output: the map would not be "
                              "used (set command_output:=float64_multi_array or joint_trajectory)")
        try:
            self.joint_map = load_joint_map(map_path, action_names) if map_path else identity_map(action_names)
        except JointMapError as e:
            raise ConfigError(str(e)) from None
        self.last = None

    def release(self) -> None:
        self.joint_map, self.last = None, None

    def action_of(self, command: np.ndarray) -> np.ndarray:
        """The action (policy order, [-1, 1] scale) a command stands for."""
        return self.joint_map.to_action(command)

    def send(self, action: np.ndarray, stamp_ns: int, *, safe: bool = False) -> np.ndarray:
        """The command for `action`, rate limited from the last one (the safe action too: a jump
        to it can hurt a robot as much as any other), published; returns it."""
        now = time.monotonic()
        command = self.joint_map.to_robot(action)
        limited = self.joint_map.rate_limit(command, self.last, now - self._last_t)
        # Within the limit, the command itself (previous + (command - previous) may round).
        kept = np.abs(limited - command) <= 1e-9 * np.maximum(1.0, np.abs(command))
        if not kept.all():
            self._count("commands_rate_limited")
        limited = np.where(kept, command, limited)
        if self.pub is not None:
            self.pub.publish(self._message(limited, stamp_ns))
            self._count("safe_commands_sent" if safe else "commands_sent")
        self.last, self._last_t = limited, now
        return limited

    def _message(self, command: np.ndarray, stamp_ns: int):
        if self.kind == "float64_multi_array":
            return Float64MultiArray(data=command.tolist())
        msg = JointTrajectory()
        topics.set_stamp(msg.header.stamp, stamp_ns)
        msg.joint_names = list(self.joint_map.joint_names)
        point = JointTrajectoryPoint(positions=command.tolist())
        point.time_from_start.sec, point.time_from_start.nanosec = divmod(self._time_from_start_ns, 10**9)
        msg.points = [point]
        return msg
