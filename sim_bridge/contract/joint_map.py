"""How the policy's actions (one value in [-1, 1] per DMC actuator) become a robot's joint
commands, and back: a YAML file (msgs_docs/robot.md) lists the robot's joints in its controller's
order, each driven by one named action through an affine map, with an optional rate limit.

    joints:                      # the order a forward command controller expects
      - {name: arm_shoulder, action: right_hip, scale: 1.2, offset: 0.1, max_rate: 3.0}
      - {name: arm_elbow,    action: right_knee, scale: -2.0}
      ...

    command = offset + scale * action           (robot units: rad, m, N m, ...)
    max_rate: the most a command may change per second, in robot units (absent: no limit)

The policy node loads it to publish std_msgs/Float64MultiArray or trajectory_msgs/JointTrajectory;
the sim bridge's adapter mode loads the same file to turn such commands back into actions, so the
whole path runs without a robot. Every action is used exactly once: a missing, repeated or
unknown name is a JointMapError with one line saying which.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import yaml

MAX_MAP_BYTES = 1 << 20
JOINT_KEYS = ("name", "action", "scale", "offset", "max_rate")


class JointMapError(ValueError):
    """A joint map that does not fit the policy's actions (one line, naming the file and joint)."""


@dataclass(frozen=True)
class JointMap:
    """The robot's joints in its order; per joint, the index of the action that drives it."""

    joint_names: tuple[str, ...]
    action_index: np.ndarray   # (J,) int: joint j is driven by action[action_index[j]]
    scale: np.ndarray          # (J,) float64, never 0
    offset: np.ndarray         # (J,) float64
    max_rate: np.ndarray       # (J,) float64 robot units per second; inf: no limit

    def to_robot(self, action: np.ndarray) -> np.ndarray:
        """Robot commands (J,) in the robot's order and units from actions in [-1, 1]."""
        a = np.asarray(action, np.float64).reshape(-1)
        return self.offset + self.scale * a[self.action_index]

    def to_action(self, command: Sequence[float] | np.ndarray) -> np.ndarray:
        """Actions (A,) in the policy's order from robot commands (J,): to_robot's inverse."""
        c = np.asarray(command, np.float64).reshape(-1)
        if c.size != len(self.joint_names):
            raise ValueError(f"{c.size} command value(s), the map has {len(self.joint_names)} joints")
        action = np.empty(c.size, np.float64)
        action[self.action_index] = (c - self.offset) / self.scale
        return action

    def rate_limit(self, command: np.ndarray, previous: np.ndarray | None, dt_s: float) -> np.ndarray:
        """command moved towards from `previous` by at most max_rate * dt_s per joint."""
        if previous is None or not np.isfinite(self.max_rate).any():
            return command
        step = self.max_rate * max(float(dt_s), 0.0)
        return previous + np.clip(command - previous, -step, step)


def identity_map(action_names: Sequence[str]) -> JointMap:
    """Each action to a joint of its own name, unscaled (what the JointState contract carries)."""
    n = len(action_names)
    return JointMap(tuple(action_names), np.arange(n), np.ones(n), np.zeros(n), np.full(n, np.inf))


def _finite(entry: dict, key: str, default: float, where: str) -> float:
    value = entry.get(key, default)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise JointMapError(f"{where}: {key} must be a finite number, not {value!r}")
    return float(value)


def parse_joint_map(doc: Any, action_names: Sequence[str], source: str = "joint map") -> JointMap:
    """A JointMap from a parsed YAML document, checked against the policy's action names."""
    action_names = [str(a) for a in action_names]
    entries = doc.get("joints") if isinstance(doc, dict) else None
    if not isinstance(entries, list) or not entries:
        raise JointMapError(f"{source}: expected a mapping with a non-empty list `joints`")
    names, index, scale, offset, rate = [], [], [], [], []
    for i, entry in enumerate(entries):
        where = f"{source}: joint {i}"
        if not isinstance(entry, dict):
            raise JointMapError(f"{where}: expected a mapping with name and action, not {entry!r}")
        unknown = sorted(set(map(str, entry)) - set(JOINT_KEYS))
        if unknown:
            raise JointMapError(f"{where}: unknown key(s) {unknown} (known: {', '.join(JOINT_KEYS)})")
        name, action = entry.get("name"), entry.get("action")
        if not isinstance(name, str) or not name:
            raise JointMapError(f"{where}: name must be a non-empty string")
        where = f"{source}: joint {name!r}"
        if name in names:
            raise JointMapError(f"{where}: named twice")
        if action not in action_names:
            raise JointMapError(f"{where}: action {action!r} is not one of the policy's actions "
                                f"{list(action_names)}")
        if action_names.index(action) in index:
            raise JointMapError(f"{where}: action {action!r} drives two joints")
        s = _finite(entry, "scale", 1.0, where)
        if s == 0.0:
            raise JointMapError(f"{where}: scale is 0 (the joint would never move)")
        r = _finite(entry, "max_rate", math.inf, where) if "max_rate" in entry else math.inf
        if r <= 0.0:
            raise JointMapError(f"{where}: max_rate must be above 0, not {r}")
        names.append(name)
        index.append(action_names.index(action))
        scale.append(s)
        offset.append(_finite(entry, "offset", 0.0, where))
        rate.append(r)
    if len(names) != len(action_names):
        unused = [a for i, a in enumerate(action_names) if i not in index]
        raise JointMapError(f"{source}: {len(names)} joint(s) for the policy's {len(action_names)} "
                            f"actions; not driving any joint: {unused}")
    return JointMap(tuple(names), np.asarray(index), np.asarray(scale), np.asarray(offset), np.asarray(rate))


def load_joint_map(path: str | Path, action_names: Sequence[str]) -> JointMap:
    """parse_joint_map of a YAML file (at most MAX_MAP_BYTES); JointMapError says what is wrong."""
    p = Path(path)
    try:
        with p.open("rb") as f:
            raw = f.read(MAX_MAP_BYTES + 1)
    except OSError as exc:
        raise JointMapError(f"joint map {p}: {exc.strerror or exc}") from None
    if len(raw) > MAX_MAP_BYTES:
        raise JointMapError(f"joint map {p}: over {MAX_MAP_BYTES} bytes")
    try:
        doc = yaml.safe_load(raw)
    except yaml.YAMLError as exc:
        raise JointMapError(f"joint map {p}: not YAML ({str(exc).splitlines()[0]})") from None
    return parse_joint_map(doc, action_names, f"joint map {p}")
