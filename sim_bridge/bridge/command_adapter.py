"""The sim bridge's adapter mode (action_input:=float64_multi_array; msgs_docs/sim_bridge.md,
"Adapter mode"): std_msgs/Float64MultiArray commands in a robot's joint order and units, as a
ros2_control forward command controller takes them from the policy node, turned back into the
task's actions through the same joint map file (sim_bridge/contract/joint_map.py)."""
from __future__ import annotations

from typing import Sequence

import numpy as np

from sim_bridge.contract.joint_map import JointMap, JointMapError, identity_map, load_joint_map
from sim_bridge.nodekit.param_table import ConfigError


class CommandRejected(ValueError):
    """A command that is no action; `counter` names the bridge counter it goes to."""

    def __init__(self, counter: str, why: str):
        super().__init__(why)
        self.counter = counter


class CommandAdapter:
    """Float64MultiArray data -> the task's action (not yet clipped)."""

    def __init__(self, joint_map: JointMap):
        self.map = joint_map

    @classmethod
    def load(cls, path: str, action_names: Sequence[str]) -> CommandAdapter:
        """From command_map (empty: the actuators in order, unscaled); a map that does not fit
        the task is a ConfigError with the map's own one line."""
        if not path.strip():
            return cls(identity_map(action_names))
        try:
            return cls(load_joint_map(path, action_names))
        except JointMapError as e:
            raise ConfigError(f"parameter command_map: {e}") from None

    def action(self, data: Sequence[float]) -> np.ndarray:
        c = np.asarray(data, np.float64).reshape(-1)
        joints = self.map.joint_names
        if c.size != len(joints):
            raise CommandRejected("rejected_wrong_length", f"{c.size} command values, expected "
                                  f"{len(joints)} {list(joints)}")
        if not np.all(np.isfinite(c)):
            raise CommandRejected("rejected_nonfinite", f"command {c.tolist()}")
        return self.map.to_action(c)
