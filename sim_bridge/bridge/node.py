"""The sim-bridge node: a context-randomized DMC task as ROS 2 topics (msgs_docs/sim_bridge.md).

    ros2 run sim_bridge node --ros-args -p task:=pendulum_swingup -p mode:=lockstep
    ros2 run sim_bridge node --ros-args -p task:=walker_walk -p split:=test -r __ns:=/robot1

One stepping thread owns the environment (reset, step, render, publish); the executor thread
runs the callbacks (action, reset service, diagnostics timer) and hands actions over through a
condition variable (sim_bridge/bridge/handover.py), so a lock-step round trip costs no timer
period and no polling.

Lock-step: after publishing observation o_t (stamp t) the stepping thread waits for the action
stamped t. Actions stamped otherwise are rejected as stale. While no action publisher is
matched nothing times out (the bridge waits for a policy); while one is matched and no valid
answer comes within lockstep_timeout_s, the same observation is published again, unchanged
(same stamp and ids), and `lockstep_timeouts` is counted: the bridge never invents an action.
The answer to an is_last observation is recorded by others but not executed: the bridge resets
and publishes the next episode's is_first observation.

Real-time: the env steps at control_rate_hz with the latest valid action (zeros before the
first one of an episode); actions answering an older observation than the newest one are
counted late (and still used if newer than the held one).

Camera option and adapter mode (camera_out.py, command_adapter.py): the image topic may carry
a real camera's frame (any size, another encoding, or JPEG/PNG on image/compressed), and actions
may come as a robot's Float64MultiArray commands through a joint map, so the policy node's robot
path runs without a robot.
"""
from __future__ import annotations

import threading
from typing import Any, Callable

from diagnostic_msgs.msg import DiagnosticArray
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState

from sim_bridge.bridge.action_intake import ActionIntake
from sim_bridge.bridge.bridge_diagnostics import BridgeDiagnostics
from sim_bridge.bridge.camera_out import CameraOut
from sim_bridge.bridge.handover import BridgeShared, Handover
from sim_bridge.bridge.observation_publishing import PUBLISH_RETRY_S, ObservationPublishing, RCLError
from sim_bridge.bridge.params import COUNTERS, FLUSH_TIMEOUT_S, LOSSLESS_FLUSH_TIMEOUT_S, PARAMS, episode_contexts
from sim_bridge.bridge.stepping import Stepping, bridge_env
from sim_bridge.contract import qos, topics
from sim_bridge.nodekit.lifecycle import ManagedNode
from sim_bridge.nodekit.rosnode import (
    SHUTDOWN_BUDGET_S,
    KeyThrottle,
    declare_all,
    flush_publishers,
    install_parameter_guards,
    run_node,
)
from sim_bridge.nodekit.type_watch import TopicTypeWatch

NODE_NAME = "sim_bridge"
__all__ = ["COUNTERS", "PARAMS", "PUBLISH_RETRY_S", "RCLError", "SimBridgeNode", "episode_contexts", "main"]


class SimBridgeNode(ManagedNode):
    """See the module docstring; parameters in PARAMS, counters in COUNTERS. A managed node
    (sim_bridge/nodekit/lifecycle.py): configure builds the env and its stepping thread, activate
    lets it step, deactivate pauses it, cleanup closes the env. This class creates the node's
    publishers and wires its parts, one file each, built with what they need: action_intake
    (ActionIntake: the action subscription and the reset service, on the executor thread),
    stepping (Stepping: the stepping thread, its loops and the env), observation_publishing
    (ObservationPublishing: one observation out, whole), bridge_diagnostics (BridgeDiagnostics:
    /diagnostics) and camera_out (CameraOut: what the image topic carries). It keeps the
    node-wide state: parameters, counters, the log throttle, `done` and `exit_code`, and the
    Handover (handover.py) the executor thread and the stepping thread share."""

    def __init__(self, *, namespace: str = topics.DEFAULT_NAMESPACE,
                 env_factory: Callable[[], Any] | None = None, **kw: Any):
        super().__init__(NODE_NAME, namespace=namespace, **kw)
        self.done = threading.Event()
        self.exit_code = 0
        p = self.params = declare_all(self, PARAMS)
        self.executor_kind = p["executor"]
        if p["first_action_publisher_only"] and self.executor_kind == "events":
            # rclpy's EventsExecutor (7.1) hands a callback the message only, never its info.
            self.executor_kind = "single"
            self.get_logger().info("first_action_publisher_only:=true needs each action's sequence "
                                   "number, which the events executor does not pass: executor single")
        contexts = episode_contexts(p["task"], p["split"], p["context_schedule"], p["context"])
        self.lockstep = p["mode"] == "lockstep"
        self.handover = Handover()
        self.counters = dict.fromkeys(COUNTERS, 0)
        self.counters["unknown_parameters"] = len(self.unknown_parameters)
        if not self.params["remote_lifecycle"]:
            self.refuse_remote_transitions()
        self._throttle = KeyThrottle(self.get_logger())

        # Every ROS interface exists in every state (the graph shows the node's topics even
        # while unconfigured); observations go out only while active (lifecycle publishers,
        # and publish checks the handover's go), actions are taken only while active.
        self.camera_out = CameraOut(p)
        lossless = p["mode"] == "lockstep" and p["lossless"]
        obs_qos = self._obs_qos = qos.observation_qos(lossless)
        # A profile of its own: rclpy's QoS overriding changes the profile object it is given.
        self.pub_image = self.create_lifecycle_publisher(self.camera_out.msg_type, self.camera_out.topic,
                                                         qos.observation_qos(lossless),
                                                         qos_overriding_options=qos.overridable())
        self.pub_info = self.create_lifecycle_publisher(JointState, topics.STEP_INFO, obs_qos)
        self.pub_context = self.create_lifecycle_publisher(JointState, topics.CONTEXT, obs_qos)
        self.pub_clock = self.create_lifecycle_publisher(Clock, self._clock_topic(), qos.clock_qos(lossless))
        self.pub_diag = self.create_publisher(DiagnosticArray, topics.DIAGNOSTICS,
                                              qos.diagnostics_qos())
        # Not a lifecycle publisher: the announcement goes out at configure, so a policy can
        # check that it fits before the bridge steps.
        self.pub_bridge_info = self.create_publisher(JointState, topics.BRIDGE_INFO, qos.announcement_qos())
        self._obs_pubs = (self.pub_image, self.pub_info, self.pub_context)
        shared = BridgeShared(node=self, params=p, handover=self.handover, counters=self.counters,
                              throttle=self._throttle, lockstep=self.lockstep)
        self.observation_publishing = ObservationPublishing(
            shared, camera_out=self.camera_out, observation_pubs=self._obs_pubs, pub_clock=self.pub_clock,
            lossless=lossless)
        self.action_intake = ActionIntake(shared, done=self.done)
        render_size = self.camera_out.render_size
        self.stepping = Stepping(
            shared, contexts=contexts, env_factory=env_factory or (lambda: bridge_env(p, render_size)),
            publishing=self.observation_publishing, action_publishers=self.action_intake.action_publishers,
            finished=self._finished)
        # A contract topic claimed by a stranger with another type never matches: said, not a hang.
        self.type_watch = TopicTypeWatch(self)
        self.bridge_diagnostics = BridgeDiagnostics(
            shared, pub_diag=self.pub_diag, own_pubs=(*self._obs_pubs, self.pub_bridge_info),
            type_watch=self.type_watch, intake=self.action_intake, progress=self.observation_publishing.progress,
            control_rate=lambda: self.stepping.control_rate)
        self.diag_timer = self.create_timer(p["diagnostics_period_s"], self.bridge_diagnostics.publish)
        install_parameter_guards(self, PARAMS, self._apply_param, self._parameter_rejected)
        if p["autostart"]:
            self.autostart()
        else:
            self.get_logger().info("autostart:=false: unconfigured, waiting for lifecycle "
                                   f"transitions on {self.bridge_diagnostics.name}/change_state")

    def _finished(self, exit_code: int) -> None:
        """The stepping thread ended on its own (max_episodes, or failed: 1): the process exits."""
        self.exit_code = exit_code
        self.done.set()

    # ------------------------------------------------------------------ lifecycle
    def configure_node(self) -> None:
        """Load the command map (adapter mode), build the env in the stepping thread and start a
        run; announce it. A bad configuration is a ConfigError."""
        p = self.params
        self.action_intake.configure()   # a bad map: before anything starts
        self.stepping.configure()
        s = self.stepping
        with self.handover.cond:
            self.handover.new_run(s.action_dim)
            self.action_intake.new_run(s.action_dim, s.action_names)
            self.observation_publishing.new_run(s.dt_ns)
        self.pub_bridge_info.publish(topics.fill_bridge_info(JointState(), topics.BridgeInfo(
            p["task"], s.action_names, s.dt_ns / 1e9, p["image_size"])))
        self.get_logger().info(
            f"{p['task']} ({p['split']} contexts, seed {p['seed']}) in {p['mode']} mode: "
            f"{s.action_dim}-d actions {s.action_names}, control_dt "
            f"{s.dt_ns / 1e9:g} s, {p['episode_length']} steps/episode; topics under "
            f"{self.get_namespace()}; QoS {qos.describe(self._obs_qos)}"
            + ("" if self.camera_out.native else f"; camera {self.camera_out.describe()}")
            + self.action_intake.describe())

    def activate_node(self) -> None:
        self.handover.set_go(True)    # the stepping thread starts (or resumes) once it sees this

    def deactivate_node(self) -> None:
        self.handover.set_go(False)   # under cond: an observation goes out whole or not at all

    def cleanup_node(self) -> None:
        self.stepping.cleanup()

    # ------------------------------------------------------------------ callbacks
    def _apply_param(self, name: str, value: Any) -> None:
        with self.handover.cond:
            self.params[name] = value
            if name == "control_rate_hz":
                self.stepping.set_control_rate(value)
            self.handover.cond.notify_all()

    def _parameter_rejected(self, reason: str) -> None:
        with self.handover.cond:
            self.counters["parameters_rejected"] += 1
        self.get_logger().warning(f"parameter change rejected: {reason}")

    # ------------------------------------------------------------------ shutdown
    def _clock_topic(self) -> str:
        """clock_topic, or automatic: /clock in the default namespace, NS/clock elsewhere (a
        global /clock from bridges in two namespaces would interleave two sim times)."""
        return self.params["clock_topic"] or topics.clock_topic(self.get_namespace())

    @property
    def shutdown_budget_s(self) -> float:
        """What run_node's watchdog allows the close (lossless: the flush's own wait, and more)."""
        lossless = getattr(self, "lockstep", False) and self.params["lossless"]
        return (LOSSLESS_FLUSH_TIMEOUT_S if lossless else FLUSH_TIMEOUT_S) + SHUTDOWN_BUDGET_S

    def close(self) -> None:
        """The shutdown transition (ends the stepping thread), then flush the last messages to
        reliable readers."""
        self.shutdown_lifecycle()
        try:
            self.bridge_diagnostics.publish()
            # Reliable readers acknowledge lazily (on the writer's next heartbeat): give the
            # last samples a bounded chance to be acknowledged (or repaired) before exiting;
            # lossless, the backlog of a reader that was stalled too (what exiting would lose).
            lossless = self.lockstep and self.params["lossless"]
            wait_s = LOSSLESS_FLUSH_TIMEOUT_S if lossless else FLUSH_TIMEOUT_S
            for topic in flush_publishers((*self._obs_pubs, self.pub_clock), wait_s):
                self.get_logger().warning(
                    f"{topic}: exiting with samples a reader has not acknowledged after "
                    f"{wait_s:g} s (a reader stalled or gone): it does not get them")
        except Exception:  # noqa: BLE001 - exiting: the counters below are printed regardless
            pass
        c = self.counters
        self.get_logger().info(
            "stopped: " + (", ".join(f"{k}={c[k]}" for k in COUNTERS if c[k]) or "no steps"))


def main(argv: list[str] | None = None) -> None:
    raise SystemExit(run_node(
        SimBridgeNode, prog="sim_bridge", params=PARAMS, argv=argv,
        description="Sim-bridge node: a context-randomized DMC task as ROS 2 topics "
                    "(image, step_info, context, /clock; action in; reset service). "
                    "Contract: msgs_docs/sim_bridge.md.",
        example="ros2 run sim_bridge node --ros-args -p task:=walker_walk -p mode:=lockstep "
                "-p max_episodes:=10 -r __ns:=/protocad"))


if __name__ == "__main__":
    main()
