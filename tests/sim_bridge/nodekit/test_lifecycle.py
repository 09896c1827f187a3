"""The sim bridge and the policy as managed (lifecycle) nodes, driven from this (separate)
process through the standard lifecycle services, as `ros2 lifecycle set` does.

Started with autostart:=false, each node goes configure -> activate -> deactivate -> activate
-> deactivate -> cleanup; after each transition get_state says where it is, the bridge
publishes observations only while active and the policy answers only while active, and
transitions the state has not (activate from unconfigured) are refused with the node alive.
"""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from helpers import wait_until
from helpers.ros import Probe, Responder
from lifecycle_msgs.msg import Transition, TransitionEvent
from lifecycle_msgs.srv import ChangeState, GetAvailableStates, GetAvailableTransitions, GetState
from sensor_msgs.msg import Image, JointState

from sim_bridge.contract import qos, topics

pytestmark = pytest.mark.ros

TASK = "pendulum_swingup"
START = 120.0   # first start on a loaded 2-core machine (imports, EGL / torch, discovery)
NS = topics.DEFAULT_NAMESPACE
#: Per request: an answer not back by then counts as lost (see Lifecycle._call).
ATTEMPT_S = 10.0


class Lifecycle:
    """Client of one node's standard lifecycle services (from the probe's own process)."""

    def __init__(self, probe: Probe, node: str):
        self.probe, self.fqn = probe, f"{NS}/{node}"
        n = probe.node
        self.change = n.create_client(ChangeState, f"{self.fqn}/change_state")
        self.get = n.create_client(GetState, f"{self.fqn}/get_state")
        self.states = n.create_client(GetAvailableStates, f"{self.fqn}/get_available_states")
        self.transitions = n.create_client(GetAvailableTransitions,
                                           f"{self.fqn}/get_available_transitions")
        self.graph = n.create_client(GetAvailableTransitions, f"{self.fqn}/get_transition_graph")
        self.events: list[tuple[str, str]] = []
        self.lost_answer = False
        self._lock = threading.Lock()
        self._sub = n.create_subscription(TransitionEvent, f"{self.fqn}/transition_event",
                                          self._on_event, 10)

    def _on_event(self, msg) -> None:
        with self._lock:
            self.events.append((msg.start_state.label, msg.goal_state.label))

    def wait_services(self, timeout: float = START) -> None:
        for c in (self.change, self.get, self.states, self.transitions, self.graph):
            assert c.wait_for_service(timeout_sec=timeout), f"{c.srv_name} not available"

    def _ask(self, client, request, timeout: float):
        """One request; its answer, or None when none came within `timeout`."""
        future = client.call_async(request)
        done = threading.Event()
        future.add_done_callback(lambda _f: done.set())
        if done.wait(timeout):
            return future.result()
        client.remove_pending_request(future)
        return None

    def _call(self, client, request, timeout: float = 60.0):
        """The answer to an idempotent query, asked again when an answer is lost.

        Fast DDS drops a service answer when the server has not matched the caller's response
        reader within 100 ms of the request ("client will not receive response",
        ros2/rmw_fastrtps#467), which a loaded machine hits right after discovery, as
        `ros2 lifecycle` users meet it too; an honest client asks again."""
        deadline = time.monotonic() + timeout
        while True:
            answer = self._ask(client, request, min(ATTEMPT_S, max(0.1, deadline - time.monotonic())))
            if answer is not None:
                return answer
            assert time.monotonic() < deadline, f"no answer from {client.srv_name} within {timeout}s"

    def state(self) -> str:
        return self._call(self.get, GetState.Request()).current_state.label

    def set(self, label: str) -> bool:
        """The node's answer to the transition `label`. A lost answer is asked again (see
        `_call`); `self.lost_answer` then says the first attempt may have run."""
        self.lost_answer = False
        request = ChangeState.Request(transition=Transition(label=label))
        deadline = time.monotonic() + 60.0
        while (answer := self._ask(self.change, request, ATTEMPT_S)) is None:
            self.lost_answer = True
            assert time.monotonic() < deadline, f"no answer from {self.change.srv_name} within 60s"
        return answer.success

    def available(self) -> set[str]:
        return {t.transition.label for t in
                self._call(self.transitions, GetAvailableTransitions.Request()).available_transitions}

    def go(self, label: str, expect: str) -> None:
        ok = self.set(label)
        # A repeat of a transition whose first answer was lost is refused (the state moved on).
        assert ok or self.lost_answer, f"{label} refused"
        assert self.state() == expect


class DiagLog:
    """Every diagnostics report of one node (the probe keeps only the latest)."""

    def __init__(self, probe: Probe, node: str):
        self.name, self.reports, self._lock = f"{NS}/{node}", [], threading.Lock()
        self._sub = probe.node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, self._on,
                                                   qos.diagnostics_qos())

    def _on(self, msg) -> None:
        with self._lock:
            self.reports += [{kv.key: kv.value for kv in st.values} for st in msg.status
                             if st.name == self.name]

    def after(self, n: int, key: str, value: str | None = None, timeout: float = 30.0) -> dict:
        """Wait for the n-th report from now whose `key` is `value` (any value if None)."""
        with self._lock:
            start = len(self.reports)

        def hit():
            with self._lock:
                got = [r for r in self.reports[start:] if value is None or r.get(key) == value]
            return got[n - 1] if len(got) >= n else None

        return wait_until(hit, timeout, f"{n} diagnostics report(s) of {self.name} with {key}={value}")


@pytest.fixture
def probe():
    p = Probe("lifecycle_test_probe")
    yield p
    p.close()


@pytest.mark.process
def test_sim_bridge_steps_only_while_active(spawn, probe):
    life = Lifecycle(probe, "sim_bridge")
    diag = DiagLog(probe, "sim_bridge")
    responder = Responder(probe, lambda info: [0.5], names=["torque"])
    announced = probe.record(topics.BRIDGE_INFO, JointState, qos.announcement_qos())
    bridge = spawn("bridge", "-m", "sim_bridge.bridge.node", "--ros-args", "-p", f"task:={TASK}",
                   "-p", "autostart:=false", "-p", "diagnostics_period_s:=0.1",
                   "-p", "episode_length:=1000")
    life.wait_services()
    assert life.state() == "unconfigured"
    states = life._call(life.states, GetAvailableStates.Request()).available_states
    assert {"unconfigured", "inactive", "active", "finalized"} <= {s.label for s in states}
    assert life.available() == {"configure", "shutdown"}

    # A transition the state has not: refused, nothing changes, the node is still up.
    assert not life.set("activate") and life.state() == "unconfigured"
    assert bridge.alive()

    life.go("configure", "inactive")                     # the env is built now
    assert life.available() >= {"activate", "cleanup"} and "configure" not in life.available()
    wait_until(lambda: len(announced) >= 1, 30, "bridge_info announced at configure")
    wait_until(responder.ready, 30, "the responder to match the bridge")
    report = diag.after(3, "lifecycle_state", "inactive")
    assert report["observations_published"] == "0" and int(report["action_publishers"]) >= 1
    assert responder.steps == []                          # a reader and a policy, yet no step

    life.go("activate", "active")
    wait_until(lambda: len(responder.steps) >= 5, 60, "steps while active")

    life.go("deactivate", "inactive")
    published = int(diag.after(1, "lifecycle_state", "inactive")["observations_published"])
    wait_until(lambda: len(responder.received) >= 2 * published, 30, "every published message")
    held = len(responder.steps)
    assert held == published                              # one answered step per observation
    assert diag.after(3, "lifecycle_state", "inactive")["observations_published"] == str(published)
    assert len(responder.steps) == held                   # nothing while inactive

    # Active again: the episode goes on where it was held (the observation awaiting its answer
    # goes out again, or the next one for the first time): no step lost, none skipped.
    life.go("activate", "active")
    wait_until(lambda: len(responder.steps) >= held + 5, 60, "steps after re-activation")
    stamps = [s for s, _, _ in responder.steps]
    dt = stamps[1] - stamps[0]
    assert sorted(stamps) == stamps and sorted(set(stamps)) == [i * dt for i in range(len(set(stamps)))]
    assert [i.is_first for _, i, _ in responder.steps].count(True) == 1   # still episode 0

    life.go("deactivate", "inactive")
    life.go("cleanup", "unconfigured")                    # the env is closed
    assert diag.after(1, "lifecycle_state", "unconfigured")["transition_errors"] == "0"
    # configured and activated again: a new run (sim time from 0 again)
    life.go("configure", "inactive")
    n = len(responder.steps)
    life.go("activate", "active")
    wait_until(lambda: len(responder.steps) >= n + 2, 60, "steps of the second run")
    assert responder.steps[n][1].is_first and responder.steps[n][0] == 0

    with life._lock:
        events = list(life.events)
    for edge in (("configuring", "inactive"), ("activating", "active"),
                 ("deactivating", "inactive"), ("cleaningup", "unconfigured")):
        assert edge in events, (edge, events)

    assert life.set("shutdown")                           # finalized: the process ends, code 0
    wait_until(lambda: not bridge.alive(), 30, "the bridge to exit after shutdown")
    assert bridge.p.returncode == 0
    out = bridge.output()
    assert "Traceback" not in out


@pytest.mark.process
def test_sim_bridge_realtime_holds_still_while_inactive(spawn, probe):
    """Real time: deactivate pauses the clock-driven stepping, activate resumes it at the rate,
    the sim time going on from where it stopped (no step lost, none skipped)."""
    life = Lifecycle(probe, "sim_bridge")
    diag = DiagLog(probe, "sim_bridge")
    images = probe.record(topics.IMAGE, Image)
    infos = probe.record(topics.STEP_INFO, JointState)
    spawn("bridge", "-m", "sim_bridge.bridge.node", "--ros-args", "-p", f"task:={TASK}",
          "-p", "mode:=realtime", "-p", "control_rate_hz:=50", "-p", "autostart:=false",
          "-p", "diagnostics_period_s:=0.1", "-p", "episode_length:=100000")
    life.wait_services()
    life.go("configure", "inactive")
    life.go("activate", "active")
    wait_until(lambda: len(images) >= 10 and len(infos) >= 10, 60, "real-time steps")
    life.go("deactivate", "inactive")
    published = diag.after(1, "lifecycle_state", "inactive")["observations_published"]
    assert diag.after(5, "lifecycle_state", "inactive")["observations_published"] == published
    wait_until(lambda: len(images) >= int(published), 30, "every published image")
    assert len(images) == int(published)
    life.go("activate", "active")
    wait_until(lambda: len(images) >= int(published) + 10, 60, "steps after re-activation")
    stamps = [topics.stamp_to_ns(m.header.stamp) for m in list(images)]
    dt = stamps[1] - stamps[0]
    assert stamps == [i * dt for i in range(len(stamps))]

@pytest.mark.process
def test_policy_answers_only_while_active(spawn, probe, tmp_path):
    from helpers.agents import save_agent
    from helpers.policy import Feeder

    ckpt = tmp_path / "agent.pt"
    life = Lifecycle(probe, "policy")
    diag = DiagLog(probe, "policy")
    feed = Feeder(probe)
    policy = spawn("policy", "-m", "protocad_ros.node.policy_node", "--ros-args", "-p", f"task:={TASK}",
                   "-p", f"checkpoint:={ckpt}", "-p", "autostart:=false",
                   "-p", "diagnostics_period_s:=0.1", "-p", "num_threads:=1")
    life.wait_services()
    assert life.state() == "unconfigured"
    assert not life.set("activate") and life.state() == "unconfigured"

    # configure loads the checkpoint: missing, configure fails and the node stays unconfigured
    assert not life.set("configure") and life.state() == "unconfigured" and policy.alive()
    save_agent(ckpt, 4)
    life.go("configure", "inactive")
    report = diag.after(1, "lifecycle_state", "inactive")
    assert report["agent"] == "checkpoint" and report["checkpoint_updates"] == "4"

    wait_until(feed.ready, 60, "the feeder to match the policy")
    feed.obs(10, 0, is_first=True)                       # inactive: not answered
    diag.after(1, "observations_while_inactive", "2")
    assert len(feed.actions) == 0

    life.go("activate", "active")
    feed.obs(20, 0, is_first=True)
    feed.obs(30, 1)
    feed.wait_answers(2, "answers while active")
    assert feed.stamps() == [20, 30]

    life.go("deactivate", "inactive")
    feed.obs(40, 2)
    diag.after(1, "observations_while_inactive", "4")
    assert feed.stamps() == [20, 30]                      # nothing while inactive

    life.go("activate", "active")
    feed.obs(50, 3)
    feed.wait_answers(3, "answers after re-activation")
    assert feed.stamps() == [20, 30, 50]
    assert np.asarray(list(feed.actions)[-1].effort).shape == (1,)

    life.go("deactivate", "inactive")
    life.go("cleanup", "unconfigured")                    # the model is dropped
    report = diag.after(1, "lifecycle_state", "unconfigured")
    assert report["agent"] == "none" and report["checkpoint_updates"] == "-1"
    assert not life.set("deactivate") and life.state() == "unconfigured" and policy.alive()
    assert policy.stop() == 0
    out = policy.output()
    assert "Traceback" not in out and "configure failed: checkpoint" in out


def test_a_transition_that_raises_is_an_error_transition_not_a_dead_node():
    """In-process: a configure that raises (not a ConfigError) ends in error processing, which
    releases what was built and returns the node to unconfigured; it can be configured again."""
    import rclpy

    from sim_bridge.nodekit.lifecycle import ERROR, SUCCESS, ManagedNode

    class Flaky(ManagedNode):
        def __init__(self, **kw):
            self.fail, self.released = True, 0
            super().__init__("flaky", **kw)

        def configure_node(self):
            if self.fail:
                raise RuntimeError("a bug in configure")

        def cleanup_node(self):
            self.released += 1

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    try:
        node = Flaky(context=ctx)
        assert node.trigger_configure() == ERROR
        assert node.lifecycle_state == "unconfigured" and node.released >= 1
        assert node.transition_errors == 1 and isinstance(node.last_transition_error, RuntimeError)
        node.fail = False
        assert node.trigger_configure() == SUCCESS and node.lifecycle_state == "inactive"
        assert node.trigger_activate() == SUCCESS and node.is_active
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)


@pytest.mark.process
def test_a_closed_control_plane_refuses_other_processes(spawn, probe):
    """remote_lifecycle:=false and reset_service:=false (what protocad-fleet gives its nodes):
    a transition asked from this process is refused and counted, the bridge keeps stepping, no
    reset service exists, and max_episodes cannot be changed while it runs."""
    from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
    from rcl_interfaces.srv import SetParameters
    from std_srvs.srv import Trigger

    life = Lifecycle(probe, "sim_bridge")
    diag = DiagLog(probe, "sim_bridge")
    responder = Responder(probe, lambda info: [0.5], names=["torque"])
    bridge = spawn("bridge", "-m", "sim_bridge.bridge.node", "--ros-args", "-p", f"task:={TASK}",
                   "-p", "remote_lifecycle:=false", "-p", "reset_service:=false",
                   "-p", "diagnostics_period_s:=0.1", "-p", "episode_length:=1000")
    life.wait_services()
    wait_until(lambda: life.state() == "active", START, "autostart (its own transitions run)")
    wait_until(lambda: len(responder.steps) >= 3, 60, "steps")
    assert not life.set("deactivate") and life.state() == "active"
    report = diag.after(1, "remote_transitions_refused", "1")
    assert report["lifecycle_state"] == "active"
    n = len(responder.steps)
    wait_until(lambda: len(responder.steps) > n + 3, 30, "steps after the refused transition")
    assert "refused (remote_lifecycle:=false)" in bridge.output()

    reset = probe.node.create_client(Trigger, f"{NS}/{topics.RESET_SERVICE}")
    assert not reset.wait_for_service(timeout_sec=2.0)            # not served at all
    params = probe.node.create_client(SetParameters, f"{NS}/sim_bridge/set_parameters")
    assert params.wait_for_service(timeout_sec=30.0)
    request = SetParameters.Request(parameters=[Parameter(name="max_episodes", value=ParameterValue(
        type=ParameterType.PARAMETER_INTEGER, integer_value=1))])
    answer = life._call(params, request)
    assert not answer.results[0].successful                        # read-only
    assert bridge.alive()


HANGING_NODE = """
import sys, time
from sim_bridge.nodekit.rosbase import ProtocadNode
from sim_bridge.nodekit.rosnode import run_node

class Hanging(ProtocadNode):
    # Stands in for a close that DDS holds up (a peer gone without a clean shutdown: a state
    # that cannot be produced on demand): the close never returns.
    shutdown_budget_s = 1.0

    def __init__(self):
        super().__init__("hanging")
        print("up", flush=True)

    def close(self):
        time.sleep(120)

sys.exit(run_node(Hanging, prog="hanging"))
"""


@pytest.mark.process
def test_a_node_whose_close_hangs_still_exits_on_ctrl_c(spawn):
    import signal

    proc = spawn("hanging", "-c", HANGING_NODE)
    wait_until(lambda: "up" in proc.output(), START, "the node to start")
    proc.stop(signal.SIGINT, timeout=60)       # exits long before the close would return
    out = proc.output()
    assert proc.p.returncode == 0, out
    assert "stopping" in out and "shutdown took longer than 1 s" in out and "exiting now" in out
