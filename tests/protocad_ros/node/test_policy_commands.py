"""The policy node's robot side as a real process over DDS (msgs_docs/policy.md#a-robots-command-interface,
#fail-safe): commands through a permuted, scaled joint map on a ros2_control topic, a bad map as a
configuration error, the watchdog, the enable switch and the rate limit, each acting within a
bound measured here. Observations are hand-made (helpers/policy.py Feeder), the agent random
(hopper_stand: 4 actions, so the map can permute them)."""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from helpers import wait_exit, wait_until
from helpers.policy import START, Feeder
from helpers.ros import Probe
from std_msgs.msg import Bool, Float64MultiArray
from std_srvs.srv import SetBool
from trajectory_msgs.msg import JointTrajectory

from protocad_ros.robot.command_output import command_qos
from sim_bridge.contract import qos, topics
from sim_bridge.contract.joint_map import load_joint_map

TASK = "hopper_stand"
ACTIONS = ["waist", "hip", "knee", "ankle"]
MAP = """joints:
  - {name: j_knee, action: knee, scale: 2.0, offset: 0.5}
  - {name: j_waist, action: waist, scale: -1.5}
  - {name: j_ankle, action: ankle, scale: 0.25, offset: -1.0}
  - {name: j_hip, action: hip, scale: 3.0, offset: 2.0}
"""
#: Safe-action and switch reaction bounds beyond the node's own period, on 2 busy cores: DDS
#: delivery, the executor's turn, the test's polling.
MARGIN_S = 0.4
SWITCH_BOUND_S = 5.0
#: Tests of other parts: the watchdog's safe commands would interleave with the answers' commands
#: (a Float64MultiArray has no stamp to tell them apart) whenever the test pauses.
QUIET_WATCHDOG = "input_timeout_s:=3600.0"


@pytest.fixture
def probe():
    p = Probe("policy_commands_probe")
    yield p
    p.close()


def args(*params: str) -> list[str]:
    out = ["-m", "protocad_ros.node.policy_node", "--ros-args", "-p", f"task:={TASK}",
           "-p", "diagnostics_period_s:=0.1", "-p", "num_threads:=1"]
    for p in params:
        out += ["-p", p]
    return out


def write_map(tmp_path, text: str = MAP):
    path = tmp_path / "robot.yaml"
    path.write_text(text)
    return path


class Commands:
    """What arrives on command_topic, each with the time it arrived."""

    def __init__(self, probe: Probe, msgtype=Float64MultiArray, topic: str = "commands"):
        self.lock = threading.Lock()
        self.got: list[tuple[float, object]] = []
        self.sub = probe.node.create_subscription(msgtype, probe.topic(topic), self._on, command_qos())

    def _on(self, msg) -> None:
        with self.lock:
            self.got.append((time.monotonic(), msg))

    def values(self, start: int = 0) -> list[np.ndarray]:
        with self.lock:
            return [np.asarray(m.data if hasattr(m, "data") else m.points[0].positions)
                    for _, m in self.got[start:]]

    def __len__(self) -> int:
        with self.lock:
            return len(self.got)


def start(spawn, probe, feeder: Feeder, commands: Commands, *params: str):
    policy = spawn("policy", *args(*params))
    def ready() -> bool:
        assert policy.alive(), policy.output()[-2000:]
        return feeder.ready() and commands.sub.get_publisher_count() >= 1

    wait_until(ready, START, "the policy's subscriptions and publishers to match")
    wait_until(lambda: probe.node_diag("policy").get("agent") == "random", 30, "diagnostics")
    return policy


def answer(feeder: Feeder, commands: Commands, stamp: int, step: int) -> tuple[np.ndarray, np.ndarray]:
    """One observation, waited for: (the contract's action, the command that went with it)."""
    n_act, n_cmd = len(feeder.actions), len(commands)
    feeder.obs(stamp, step, is_first=step == 0)
    wait_until(lambda: len(feeder.actions) > n_act and len(commands) > n_cmd, 30, f"the answer to {stamp}")
    return np.asarray(feeder.actions[-1].effort), commands.values()[-1]


@pytest.mark.ros
@pytest.mark.process
@pytest.mark.parametrize("kind", ["float64_multi_array", "joint_trajectory"])
def test_commands_follow_the_joint_map(spawn, probe, tmp_path, kind):
    jmap = load_joint_map(write_map(tmp_path), ACTIONS)
    f = Feeder(probe)
    cmds = Commands(probe, Float64MultiArray if kind == "float64_multi_array" else JointTrajectory)
    start(spawn, probe, f, cmds, f"command_output:={kind}", f"command_map:={write_map(tmp_path)}",
          "enabled_at_start:=true", "trajectory_time_from_start_s:=0.25", QUIET_WATCHDOG)
    for i in range(4):
        action, command = answer(f, cmds, 1_000 * (i + 1), i)
        assert list(f.actions[-1].name) == ACTIONS            # the contract is unchanged
        assert np.allclose(command, jmap.to_robot(action), rtol=0, atol=1e-9), (action, command)
        assert np.allclose(jmap.to_action(command), action, atol=1e-6)
    assert not np.allclose(action, 0.0)   # a map applied to something
    if kind == "joint_trajectory":
        with cmds.lock:
            msgs = [m for _, m in cmds.got]
        for i, m in enumerate(msgs):
            assert list(m.joint_names) == ["j_knee", "j_waist", "j_ankle", "j_hip"]
            assert topics.stamp_to_ns(m.header.stamp) == 1_000 * (i + 1)
            assert len(m.points) == 1
            assert (m.points[0].time_from_start.sec, m.points[0].time_from_start.nanosec) == (0, 250_000_000)
    wait_until(lambda: probe.counter("policy", "commands_sent") == 4, 5, "commands_sent counted")
    assert probe.node_diag("policy")["command_joints"] == "j_knee,j_waist,j_ankle,j_hip"


@pytest.mark.ros
@pytest.mark.process
def test_a_bad_map_is_a_configuration_error(spawn, tmp_path):
    bad = write_map(tmp_path, MAP.replace("action: ankle", "action: wrist"))
    policy = spawn("policy", *args("command_output:=float64_multi_array", f"command_map:={bad}"))
    assert wait_exit(policy, START) == 2
    lines = [line for line in policy.output().splitlines() if "configuration error" in line]
    assert len(lines) == 1 and "joint 'j_ankle'" in lines[0] and "'wrist'" in lines[0], lines


@pytest.mark.ros
@pytest.mark.process
def test_the_watchdog_sends_the_safe_action_when_input_stops(spawn, probe, tmp_path):
    timeout = 1.0   # headroom for the test's own round trips between observations
    jmap = load_joint_map(write_map(tmp_path), ACTIONS)
    f = Feeder(probe)
    cmds = Commands(probe)
    start(spawn, probe, f, cmds, "command_output:=float64_multi_array", f"command_map:={write_map(tmp_path)}",
          "enabled_at_start:=true", f"input_timeout_s:={timeout}")
    time.sleep(2 * timeout)   # armed by the first observation only: no trip before it
    assert len(cmds) == 0 and probe.node_diag("policy")["watchdog_trips"] == "0"
    for i in range(3):
        answer(f, cmds, 1_000 * (i + 1), i)
    last_model = len(cmds)
    safe = jmap.to_robot(np.zeros(4))   # zero: each joint at its offset
    wait_until(lambda: len(cmds) >= last_model + 2, 10 * timeout, "two safe commands")
    with cmds.lock:
        (t_model, _), (t1, m1), (t2, m2) = cmds.got[last_model - 1:last_model + 2]
    assert np.array_equal(m1.data, safe) and np.array_equal(m2.data, safe)
    reaction, repeat = t1 - t_model, t2 - t1
    print(f"watchdog: safe action {reaction:.3f} s after the last command, repeated after {repeat:.3f} s")
    assert timeout - 0.05 <= reaction <= timeout + MARGIN_S
    assert timeout - 0.1 <= repeat <= timeout + MARGIN_S
    wait_until(lambda: probe.node_diag("policy").get("_level") == 2, 5, "diagnostics at ERROR")
    d = probe.node_diag("policy")
    assert "no fresh observation" in d["_message"] and d["watchdog_tripped"] == "true", d
    assert d["watchdog_trips"] == "1" and d["safe_commands_sent"] != "0"

    action, command = answer(f, cmds, 4_000, 3)
    wait_until(lambda: any(np.allclose(c, jmap.to_robot(action)) for c in cmds.values(last_model)), 10,
               "the model's command again")
    wait_until(lambda: probe.node_diag("policy").get("watchdog_tripped") == "false", 5, "the watchdog cleared")
    d = probe.node_diag("policy")
    assert d["_level"] < 2 and d["watchdog_clears"] == "1" and d["watchdog_trips"] == "1", d


@pytest.mark.ros
@pytest.mark.process
def test_the_enable_switch(spawn, probe, tmp_path):
    jmap = load_joint_map(write_map(tmp_path), ACTIONS)
    f = Feeder(probe)
    cmds = Commands(probe)
    client = probe.node.create_client(SetBool, "/protocad/policy/enable")
    switch = probe.publisher("enable", Bool, qos.announcement_qos())
    start(spawn, probe, f, cmds, "command_output:=float64_multi_array", f"command_map:={write_map(tmp_path)}",
          QUIET_WATCHDOG)
    safe = jmap.to_robot(np.zeros(4))

    # auto with command_output: disabled at start; answers carry the safe action.
    for i in range(2):
        action, command = answer(f, cmds, 1_000 * (i + 1), i)
        assert np.array_equal(action, np.zeros(4)) and np.array_equal(command, safe)
    wait_until(lambda: probe.node_diag("policy").get("_message", "").startswith("disabled"), 5, "WARN: disabled")
    assert probe.node_diag("policy")["_level"] == 1

    assert client.wait_for_service(timeout_sec=30)
    t0 = time.monotonic()
    response = client.call_async(SetBool.Request(data=True))
    wait_until(response.done, SWITCH_BOUND_S, "the enable service's answer")
    enabled_after = time.monotonic() - t0
    assert response.result().success and response.result().message == "enabled"
    # The switch happened before the answer: the next observation gets the model's command.
    action, command = answer(f, cmds, 3_000, 2)
    assert not np.allclose(action, 0.0) and np.allclose(command, jmap.to_robot(action), atol=1e-9)
    wait_until(lambda: probe.node_diag("policy").get("enabled") == "true", 5, "diagnostics: enabled")

    # The latched topic, no answer to wait for: observations until the safe action comes back.
    wait_until(lambda: switch.get_subscription_count() >= 1, 10, "the enable topic to match")
    switch.publish(Bool(data=False))
    t0, step = time.monotonic(), 3
    while True:
        action, command = answer(f, cmds, 1_000 * (step + 1), step)
        if np.array_equal(command, safe):
            break
        assert time.monotonic() - t0 < SWITCH_BOUND_S, "the enable topic's false was not followed"
        step += 1
    disabled_after = time.monotonic() - t0
    print(f"enable switch: service answered in {enabled_after:.3f} s; topic false followed "
          f"within {disabled_after:.3f} s ({step - 2} observation(s))")
    assert np.array_equal(action, np.zeros(4))
    wait_until(lambda: probe.counter("policy", "enable_switches") == 2, 5, "enable_switches counted")


@pytest.mark.ros
@pytest.mark.process
def test_the_rate_limit_bounds_each_change(spawn, probe, tmp_path):
    rate = 0.5   # robot units per second: the map's scales make the model's changes bigger
    text = MAP.replace("}", f", max_rate: {rate}}}")
    jmap = load_joint_map(write_map(tmp_path, text), ACTIONS)
    f = Feeder(probe)
    cmds = Commands(probe)
    start(spawn, probe, f, cmds, "command_output:=float64_multi_array",
          f"command_map:={write_map(tmp_path, text)}", "enabled_at_start:=true", QUIET_WATCHDOG)
    client = probe.node.create_client(SetBool, "/protocad/policy/enable")
    wanted = []
    for i in range(12):
        action, _ = answer(f, cmds, 1_000 * (i + 1), i)
        wanted.append(jmap.to_robot(action))
        time.sleep(0.05)
    # Disabled: the safe action (each joint at its offset) goes through the limit too.
    assert client.wait_for_service(timeout_sec=30)
    done = client.call_async(SetBool.Request(data=False))
    wait_until(done.done, SWITCH_BOUND_S, "the enable service's answer")
    safe = jmap.to_robot(np.zeros(4))
    _, command = answer(f, cmds, 13_000, 12)
    wanted.append(safe)
    with cmds.lock:
        got = list(cmds.got)
    # Tolerance: the test's receive times jitter against the node's send times (DDS, the executor).
    jitter_s = 0.1
    ratios = []
    for (ta, a), (tb, b) in zip(got, got[1:]):
        change = np.abs(np.asarray(b.data) - a.data)
        assert np.all(change <= rate * (tb - ta + jitter_s) + 1e-9), (a.data, b.data, tb - ta)
        ratios.append(float(np.max(change / (rate * (tb - ta)))))
    limited = [not np.allclose(g.data, w, rtol=0, atol=1e-9) for (_, g), w in zip(got, wanted)]
    print(f"rate limit: {sum(limited)} of {len(got)} commands limited; largest change "
          f"{max(ratios):.3f} x max_rate * dt (dt from the arrival times)")
    assert any(limited) and not limited[0]   # the first command has nothing to be limited against
    far = np.max(np.abs(np.asarray(got[-2][1].data) - safe)) > rate * (got[-1][0] - got[-2][0] + jitter_s)
    print(f"rate limit: the safe pose {'beyond' if far else 'within'} one step's reach; the command after "
          f"disabling {'reached it' if np.allclose(command, safe) else 'moved towards it'}")
    assert not far or not np.allclose(command, safe), "the safe action jumped past the rate limit"
    wait_until(lambda: probe.counter("policy", "commands_rate_limited") == sum(limited), 5,
               "commands_rate_limited counted")


@pytest.mark.ros
@pytest.mark.process
def test_a_supervisors_latched_word_reaches_a_node_started_later(spawn, probe, tmp_path):
    jmap = load_joint_map(write_map(tmp_path), ACTIONS)
    f = Feeder(probe)
    cmds = Commands(probe)
    switch = probe.publisher("enable", Bool, qos.announcement_qos())
    switch.publish(Bool(data=True))   # before the node exists
    start(spawn, probe, f, cmds, "command_output:=float64_multi_array", f"command_map:={write_map(tmp_path)}",
          QUIET_WATCHDOG)
    wait_until(lambda: probe.node_diag("policy").get("enabled") == "true", 10, "the latched enable taken")
    action, command = answer(f, cmds, 1_000, 0)
    assert not np.allclose(action, 0.0) and np.allclose(command, jmap.to_robot(action), atol=1e-9)
    assert probe.node_diag("policy")["enable_switches"] == "1"


@pytest.mark.ros
@pytest.mark.process
def test_the_watchdog_without_command_output_reports_only(spawn, probe):
    """A real-time simulator (latest_only): the bridge takes an action only as the answer to an
    observation, so the watchdog says ERROR and sends nothing on action."""
    f = Feeder(probe)
    policy = spawn("policy", *args("latest_only:=true", "input_timeout_s:=0.5"))
    wait_until(lambda: f.ready() or not policy.alive(), START, "the policy's subscriptions and publishers to match")
    for i in range(2):
        f.obs(1_000 * (i + 1), i, is_first=i == 0)
        f.wait_answers(i + 1, "an answer")
    wait_until(lambda: probe.node_diag("policy").get("_level") == 2, 10, "diagnostics at ERROR")
    d = probe.node_diag("policy")
    assert d["watchdog_trips"] == "1" and d["safe_commands_sent"] == "0" and d["enabled"] == "true", d
    assert len(f.actions) == 2
    f.obs(3_000, 2)
    f.wait_answers(3, "the answer after the stall")
    wait_until(lambda: probe.counter("policy", "watchdog_clears") == 1, 10, "the watchdog cleared")
    assert len(f.actions) == 3 and probe.node_diag("policy")["_level"] < 2
