"""The sim-bridge node: a context-randomized DMC task as ROS 2 topics (msgs_docs/sim_bridge.md).

    ros2 run sim_bridge node --ros-args -p task:=pendulum_swingup -p mode:=lockstep
    ros2 run sim_bridge node --ros-args -p task:=walker_walk -p split:=test -r __ns:=/robot1

One stepping thread owns the environment (reset, step, render, publish); the executor thread
runs the callbacks (action, reset service, diagnostics timer) and hands actions over through a
condition variable, so a lock-step round trip costs no timer period and no polling.

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

Camera option and adapter mode (camera_out.py, commands.py): the image topic may carry a real
camera's frame (any size, another encoding, or JPEG/PNG on image/compressed), and actions may
come as a robot's Float64MultiArray commands through a joint map, so the policy node's robot
path runs without a robot.
"""
from __future__ import annotations

import collections
import threading
import time
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger

from sim_bridge.bridge.action_intake import ActionIntake
from sim_bridge.bridge.camera_out import CameraOut
from sim_bridge.bridge.commands import CommandAdapter
from sim_bridge.bridge.diagnostics import BridgeDiagnostics
from sim_bridge.bridge.params import COUNTERS, FLUSH_TIMEOUT_S, LOSSLESS_FLUSH_TIMEOUT_S, PARAMS, episode_contexts
from sim_bridge.bridge.publishing import PUBLISH_RETRY_S, ObservationPublishing, RCLError
from sim_bridge.bridge.stepping import Stepping
from sim_bridge.contract import qos, topics
from sim_bridge.contract.contexts import task_actuators
from sim_bridge.nodekit.lifecycle import ManagedNode
from sim_bridge.nodekit.publisher_watch import FirstPublisherLock, PublisherWatch
from sim_bridge.nodekit.rosnode import (
    SHUTDOWN_BUDGET_S,
    ConfigError,
    KeyThrottle,
    Percentiles,
    declare_all,
    flush_publishers,
    install_parameter_guards,
    run_node,
)
from sim_bridge.nodekit.type_watch import TopicTypeWatch

NODE_NAME = "sim_bridge"
__all__ = ["COUNTERS", "PARAMS", "PUBLISH_RETRY_S", "RCLError", "SimBridgeNode", "episode_contexts", "main"]


class SimBridgeNode(ActionIntake, Stepping, ObservationPublishing, BridgeDiagnostics, ManagedNode):
    """See the module docstring; parameters in PARAMS, counters in COUNTERS. A managed node
    (sim_bridge/nodekit/lifecycle.py): configure builds the env and its stepping thread, activate
    lets it step, deactivate pauses it, cleanup closes the env. This class wires the node's ROS
    interfaces and lifecycle; its parts, one file each: ActionIntake (actions and the reset
    service, on the executor thread), Stepping (the stepping thread's loops),
    ObservationPublishing (one observation out, whole) and BridgeDiagnostics (/diagnostics)."""

    def __init__(self, *, namespace: str = topics.DEFAULT_NAMESPACE, env_factory=None, **kw: Any):
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
        self._contexts = episode_contexts(p["task"], p["split"], p["context_schedule"],
                                          p["context"])
        self.lockstep = p["mode"] == "lockstep"
        self._env_factory = env_factory or self._make_env
        self._cond = threading.Condition()
        self._stop = threading.Event()           # set: the stepping thread ends (cleanup)
        self._thread: threading.Thread | None = None
        self._go = False                         # active: the stepping thread may step
        self._control_rate = p["control_rate_hz"]   # the task's rate once configured
        self.env = None
        self.action_dim, self.action_names, self.dt_ns = 0, [], 0
        self._reset_run_state()
        self.counters = dict.fromkeys(COUNTERS, 0)
        self.counters["unknown_parameters"] = len(self.unknown_parameters)
        if not self.params["remote_lifecycle"]:
            self.refuse_remote_transitions()
        self._throttle = KeyThrottle(self.get_logger())
        self.latency = Percentiles()             # observation published -> answer received
        self._late_at_last_diag = 0
        self._rate_window = collections.deque(maxlen=2)
        self._rate_window.append((time.monotonic(), 0))

        # Every ROS interface exists in every state (the graph shows the node's topics even
        # while unconfigured); observations go out only while active (lifecycle publishers,
        # and _publish checks _go), actions are taken only while active.
        self.camera = CameraOut(p)
        self.commands: CommandAdapter | None = None   # adapter mode, from configure
        self._img_msg, self._info_msg, self._ctx_msg, self._clock_msg = (
            self.camera.msg_type(), JointState(), JointState(), Clock())
        lossless = self._obs_lossless = p["mode"] == "lockstep" and p["lossless"]
        obs_qos = self._obs_qos = qos.observation_qos(lossless)
        # A profile of its own: rclpy's QoS overriding changes the profile object it is given.
        self.pub_image = self.create_lifecycle_publisher(self.camera.msg_type, self.camera.topic,
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
        self._others_warned: set[str] = set()
        self._others_now: set[str] = set()
        # A second action publisher (an impostor, a stray `ros2 topic pub`) is reported; with
        # first_action_publisher_only its actions are refused too.
        self.publisher_watch = PublisherWatch(self._on_new_publisher)
        self._action_lock = FirstPublisherLock() if p["first_action_publisher_only"] else None
        self.sub_action = self._subscribe_actions(p)
        self.srv_reset = (self.create_service(Trigger, topics.RESET_SERVICE, self._on_reset)
                          if p["reset_service"] else None)
        # A contract topic claimed by a stranger with another type never matches: said, not a hang.
        self.type_watch = TopicTypeWatch(self)
        self.diag_timer = self.create_timer(p["diagnostics_period_s"], self._publish_diagnostics)
        install_parameter_guards(self, PARAMS, self._apply_param, self._parameter_rejected)
        self._obs_pubs = (self.pub_image, self.pub_info, self.pub_context)
        self._diag_name = self.get_fully_qualified_name()   # -r __node:=... renames it too
        if p["autostart"]:
            self.autostart()
        else:
            self.get_logger().info("autostart:=false: unconfigured, waiting for lifecycle "
                                   f"transitions on {self._diag_name}/change_state")

    def _subscribe_actions(self, p: dict[str, Any]):
        """Actions on `action`, or in adapter mode a robot's commands instead (never both)."""
        adapter = p["action_input"] == "float64_multi_array"
        action_type, action_topic, on_action = ((Float64MultiArray, p["command_topic"], self._on_command)
                                                if adapter else (JointState, topics.ACTION, self._on_action))
        return self.create_subscription(
            action_type, action_topic,
            # first_action_publisher_only: rclpy passes the message info (its sequence number)
            # to a two-argument callback.
            on_action if self._action_lock is None else (lambda msg, info: on_action(msg, info)),
            qos.action_qos(), qos_overriding_options=qos.overridable(),
            event_callbacks=self.publisher_watch.callbacks(self.resolve_topic_name(action_topic),
                                                           also=self._on_action_matched))

    def _reset_run_state(self) -> None:
        """State of one configured run (stepping thread <-> executor thread, under _cond)."""
        self._episodes_begun = 0
        self._pending_stamp: int | None = None   # lock-step: stamp awaiting its answer
        self._answer: np.ndarray | None = None   # lock-step: valid answer to _pending_stamp
        self._answered_stamps: collections.deque[int] = collections.deque(maxlen=64)
        self._published: collections.OrderedDict[int, float] = collections.OrderedDict()
        self._newest_stamp: int | None = None    # newest observation published
        self._held = np.zeros(self.action_dim)   # real-time: action applied at each tick
        self._held_stamp = -1
        self._reset_requested = False
        self._reset_served = 0                   # incremented by the stepping thread
        self._reset_note = ""
        self._started = False
        self._episode = -1
        self._return = 0.0   # the current episode's return so far (step_info episode_return)
        self._step = -1
        self._tick = -1
        self._obs_context: dict[str, float] = {}

    # ------------------------------------------------------------------ lifecycle
    def configure_node(self) -> None:
        """Build the env in a new stepping thread (the renderer's GL context is bound to the
        thread that creates it) and wait for it; a bad configuration is a ConfigError."""
        if self._thread is not None and self._thread.is_alive():
            raise RuntimeError("the previous stepping thread has not ended")
        p = self.params
        if p["action_input"] == "float64_multi_array":   # a bad map: before anything starts
            self.commands = CommandAdapter.load(p["command_map"], task_actuators(p["task"]))
        self._stop.clear()
        self._env_error: BaseException | None = None
        self._env_ready = threading.Event()
        self._thread = threading.Thread(target=self._run, name="sim_bridge_stepper", daemon=True)
        self._thread.start()
        while not self._env_ready.wait(0.1):
            if not self._thread.is_alive():
                break
        if self._env_error is not None or self.env is None:
            err = self._env_error or RuntimeError("the stepping thread ended before the env was built")
            if isinstance(err, (TypeError, ValueError)):
                raise ConfigError(str(err))
            raise err
        env = self.env
        with self._cond:
            self.action_dim = int(env.action_dim)
            self.action_names = list(env.action_names)
            self.dt_ns = int(round(env.control_dt * 1e9))
            self._control_rate = p["control_rate_hz"] or 1e9 / self.dt_ns
            self._reset_run_state()
        self.pub_bridge_info.publish(topics.fill_bridge_info(JointState(), topics.BridgeInfo(
            p["task"], self.action_names, self.dt_ns / 1e9, p["image_size"])))
        self.get_logger().info(
            f"{p['task']} ({p['split']} contexts, seed {p['seed']}) in {p['mode']} mode: "
            f"{self.action_dim}-d actions {self.action_names}, control_dt "
            f"{self.dt_ns / 1e9:g} s, {p['episode_length']} steps/episode; topics under "
            f"{self.get_namespace()}; QoS {qos.describe(self._obs_qos)}"
            + ("" if self.camera.native else f"; camera {self.camera.describe()}")
            + (f"; commands on {self.sub_action.topic_name} for joints {list(self.commands.map.joint_names)}"
               if self.commands else ""))

    def activate_node(self) -> None:
        with self._cond:   # the stepping thread starts (or resumes) once it sees this
            self._go = True
            self._cond.notify_all()

    def deactivate_node(self) -> None:
        # Under _cond, so an observation is published whole or not at all (see _publish).
        with self._cond:
            self._go = False
            self._cond.notify_all()

    def cleanup_node(self) -> None:
        """End the stepping thread; it closes the env (in the thread that owns the GL context)."""
        self._stop.set()
        with self._cond:
            self._go = False
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join(timeout=10.0)
            if self._thread.is_alive():
                raise RuntimeError("the stepping thread did not end within 10 s")
        self._thread = None

    # ------------------------------------------------------------------ callbacks
    def _apply_param(self, name: str, value: Any) -> None:
        with self._cond:
            self.params[name] = value
            if name == "control_rate_hz" and self.dt_ns:
                self._control_rate = value or 1e9 / self.dt_ns
            self._cond.notify_all()

    def _parameter_rejected(self, reason: str) -> None:
        with self._cond:
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
            self._publish_diagnostics()
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
