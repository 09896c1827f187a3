"""The policy node's robot-facing parts alone (protocad_ros/robot/), each built on a real rclpy
node in this process and driven by calls, no executor: the watchdog's arming, trip, repeat and
clear; the enable switch's counting; what the safe action is (zero, hold) and that it goes through
the rate limit. The same parts inside a node process over DDS: tests/protocad_ros/node/test_policy_commands.py."""
from __future__ import annotations

import collections
import time

import numpy as np
import pytest
import rclpy
from rclpy.lifecycle import LifecycleNode

from protocad_ros.robot.command_output import CommandOutput
from protocad_ros.robot.fail_safe import Watchdog
from protocad_ros.robot.robot_output import RobotOutput, enabled_at_start
from sim_bridge.nodekit.param_table import ConfigError

ACTIONS = ["a", "b"]


@pytest.fixture
def node():
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    n = LifecycleNode("robot_parts_test", context=ctx)
    yield n
    n.destroy_node()
    rclpy.try_shutdown(context=ctx)


class Counts(collections.Counter):
    def __call__(self, key: str, why: str | None = None) -> None:
        self[key] += 1


def params(**kw):
    p = {"safe_action": "zero", "command_map": "", "command_output": "", "command_topic": "commands",
         "trajectory_time_from_start_s": 0.1, "latest_only": False, "input_timeout_s": 0.05,
         "enabled_at_start": "auto"}
    p.update(kw)
    return p


@pytest.mark.ros
def test_the_watchdog_arms_trips_repeats_and_clears(node):
    counts, trips = Counts(), []
    dog = Watchdog(node, 0.05, lambda: trips.append(time.monotonic()), counts)
    time.sleep(0.06)
    dog.check()
    assert trips == [] and not dog.tripped          # not armed before the first observation
    dog.fed()
    dog.check()
    assert trips == []
    time.sleep(0.06)
    dog.check()
    dog.check()                                      # once per timeout, not per check
    assert len(trips) == 1 and dog.tripped and counts["watchdog_trips"] == 1
    assert "no fresh observation" in dog.reason()
    time.sleep(0.06)
    dog.check()
    assert len(trips) == 2 and counts["watchdog_trips"] == 1   # repeated while tripped
    dog.fed()
    assert not dog.tripped and counts["watchdog_clears"] == 1
    dog.disarm()
    time.sleep(0.06)
    dog.check()
    assert len(trips) == 2


@pytest.mark.ros
def test_the_switch_counts_real_switches_only(node):
    counts = Counts()
    out = RobotOutput(node, params(), counts)
    assert out.switch.enabled and out.watchdog is None   # the simulator path: as before
    assert out.switch.set(True, "test") == "already enabled" and counts["enable_switches"] == 0
    assert out.switch.set(False, "test") == "disabled" and counts["enable_switches"] == 1
    assert (enabled_at_start("auto", "float64_multi_array"), enabled_at_start("auto", ""),
            enabled_at_start("true", "joint_trajectory"), enabled_at_start("false", "")) == (False, True, True, False)


@pytest.mark.ros
@pytest.mark.parametrize("safe", ["zero", "hold"])
def test_the_safe_action_while_disabled(node, tmp_path, safe):
    counts = Counts()
    path = tmp_path / "map.yaml"
    path.write_text("joints:\n  - {name: jb, action: b, scale: 2.0, offset: 1.0}\n"
                    "  - {name: ja, action: a, scale: -1.0, offset: 0.5}\n")
    out = RobotOutput(node, params(command_output="float64_multi_array", command_map=str(path),
                                   safe_action=safe, enabled_at_start="true"), counts)
    out.configure(ACTIONS)
    model = np.array([0.5, -0.25], np.float32)
    assert np.allclose(out.answer(model, 1), model)
    assert np.allclose(out.commands.last, [1.0 + 2.0 * -0.25, 0.5 - 0.5])
    out.switch.set(False, "test")
    sent = out.answer(np.array([0.9, 0.9], np.float32), 2)
    if safe == "zero":
        assert np.allclose(sent, 0.0) and np.allclose(out.commands.last, [1.0, 0.5])   # the offsets
    else:
        assert np.allclose(sent, model) and np.allclose(out.commands.last, [0.5, 0.0])  # held
    assert counts["commands_sent"] == 1 and counts["safe_commands_sent"] == 1
    values = {}
    assert out.report(values, "OK", "serving")[0] == "WARN" and values["enabled"] is False


@pytest.mark.ros
def test_the_safe_action_is_rate_limited(node, tmp_path):
    counts = Counts()
    path = tmp_path / "map.yaml"
    path.write_text("joints:\n  - {name: ja, action: a, scale: 1.0, max_rate: 1.0}\n"
                    "  - {name: jb, action: b, scale: 1.0}\n")
    out = CommandOutput(node, "float64_multi_array", "commands", 0.1, counts)
    out.configure(str(path), ACTIONS)
    t0 = time.monotonic()
    out.send(np.array([1.0, 1.0]), 1)
    sent = out.send(np.zeros(2), 2, safe=True)
    dt = time.monotonic() - t0   # at least the node's time between the two
    assert 1.0 - sent[0] <= 1.0 * dt + 1e-9 and sent[0] > 0.5   # moved at most max_rate * dt
    assert sent[1] == 0.0                                       # no limit on jb
    assert counts["commands_rate_limited"] == 1 and counts["safe_commands_sent"] == 1


@pytest.mark.ros
def test_a_map_without_command_output_is_refused(node, tmp_path):
    path = tmp_path / "map.yaml"
    path.write_text("joints:\n  - {name: ja, action: a}\n  - {name: jb, action: b}\n")
    out = CommandOutput(node, "", "commands", 0.1, Counts())
    with pytest.raises(ConfigError, match="without command_output"):
        out.configure(str(path), ACTIONS)
    with pytest.raises(ConfigError, match="joint 'jx'"):
        CommandOutput(node, "joint_trajectory", "commands", 0.1, Counts()).configure(
            _write(tmp_path, "joints:\n  - {name: jx, action: c}\n"), ACTIONS)


def _write(tmp_path, text: str) -> str:
    p = tmp_path / "bad.yaml"
    p.write_text(text)
    return str(p)
