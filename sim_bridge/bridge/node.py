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
"""
from __future__ import annotations

import collections
import threading
import time
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Image, JointState
from std_srvs.srv import Trigger

from sim_bridge.contract import qos, topics
from sim_bridge.bridge.diagnostics import BridgeDiagnostics
from sim_bridge.bridge.params import (ACTION_HIGH, ACTION_LOW, COUNTERS, FLUSH_TIMEOUT_S, LOSSLESS_FLUSH_TIMEOUT_S,
                                      PARAMS, READY_GRACE_S, episode_contexts)
from sim_bridge.nodekit.lifecycle import ManagedNode
from sim_bridge.nodekit.publisher_watch import FirstPublisherLock, PublisherWatch
from sim_bridge.nodekit.rosnode import (SHUTDOWN_BUDGET_S, ConfigError, KeyThrottle, Percentiles,
                                declare_all, flush_publishers, install_parameter_guards)

NODE_NAME = "sim_bridge"
#: What rclpy raises when the middleware refuses a sample (a full KEEP_ALL history).
RCLError = _rclpy.RCLError
#: Seconds between attempts to publish into a full lossless history.
PUBLISH_RETRY_S = 0.05
__all__ = ["COUNTERS", "PARAMS", "SimBridgeNode", "episode_contexts", "main"]


class SimBridgeNode(BridgeDiagnostics, ManagedNode):
    """See the module docstring; parameters in PARAMS, counters in COUNTERS. A managed node
    (sim_bridge/nodekit/lifecycle.py): configure builds the env and its stepping thread, activate
    lets it step, deactivate pauses it, cleanup closes the env."""

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
        self._img_msg, self._info_msg, self._ctx_msg, self._clock_msg = (
            Image(), JointState(), JointState(), Clock())
        lossless = self._obs_lossless = p["mode"] == "lockstep" and p["lossless"]
        obs_qos = self._obs_qos = qos.observation_qos(lossless)
        # A profile of its own: rclpy's QoS overriding changes the profile object it is given.
        self.pub_image = self.create_lifecycle_publisher(Image, topics.IMAGE, qos.observation_qos(lossless),
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
        self.sub_action = self.create_subscription(
            JointState, topics.ACTION,
            self._on_action if self._action_lock is None else self._on_attributed_action, qos.action_qos(),
            qos_overriding_options=qos.overridable(),
            event_callbacks=self.publisher_watch.callbacks(self.resolve_topic_name(topics.ACTION),
                                                           also=self._on_action_matched))
        self.srv_reset = (self.create_service(Trigger, topics.RESET_SERVICE, self._on_reset)
                          if p["reset_service"] else None)
        self.diag_timer = self.create_timer(p["diagnostics_period_s"], self._publish_diagnostics)
        install_parameter_guards(self, PARAMS, self._apply_param, self._parameter_rejected)
        self._obs_pubs = (self.pub_image, self.pub_info, self.pub_context)
        self._diag_name = self.get_fully_qualified_name()   # -r __node:=... renames it too
        if p["autostart"]:
            self.autostart()
        else:
            self.get_logger().info("autostart:=false: unconfigured, waiting for lifecycle "
                                   f"transitions on {self._diag_name}/change_state")

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
            f"{self.get_namespace()}; QoS {qos.describe(self._obs_qos)}")

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

    def _on_action_matched(self, info) -> None:
        with self._cond:   # wake the stepping thread (it re-checks _policy_present)
            if self._action_lock is not None and info.current_count == 0:
                self._action_lock.release()   # nobody left: the next publisher alone takes it
            self._cond.notify_all()

    def _on_new_publisher(self, topic: str, publishers: int, first_time: bool) -> None:
        with self._cond:
            self.counters["multiple_publishers_detected"] += 1
        if first_time:
            what = ("only the first one's actions are taken" if self._action_lock is not None
                    else "every one's actions are taken (first_action_publisher_only:=true takes "
                         "the first one's only)")
            self.get_logger().warning(
                f"{publishers} publishers on {topic}: another node publishes actions to this bridge "
                f"(an impostor, a second policy, a stray `ros2 topic pub`?); {what}")

    def _policy_present(self) -> bool:
        return self.sub_action.get_publisher_count() > 0

    def _other_publisher(self, info: Any) -> str | None:
        """Why the action comes from another publisher than the first (first_action_publisher_only),
        or None. Called under _cond."""
        if self._action_lock is None:
            return None
        seq = info.get("publication_sequence_number", 0) if isinstance(info, dict) else \
            getattr(info, "publication_sequence_number", 0)
        return self._action_lock.admit(int(seq or 0), self.sub_action.get_publisher_count())

    def _reject(self, counter: str, why: str) -> None:
        self.counters["actions_rejected"] += 1
        self.counters[counter] += 1
        self._throttle.warning(
            counter, f"action rejected ({counter}, {self.counters[counter]} so far): {why}")

    def _on_attributed_action(self, msg, info) -> None:
        """first_action_publisher_only: rclpy passes the message info (its sequence number) to
        a two-argument callback."""
        self._on_action(msg, info)

    def _on_action(self, msg, info=None) -> None:
        now = time.monotonic()
        stamp = topics.stamp_to_ns(msg.header.stamp)
        with self._cond:
            # Attribution first: the locked publisher's every sample advances its numbers.
            other = self._other_publisher(info)
            if not self._go:   # not active: no observation awaits an answer (dropped, counted)
                self.counters["actions_while_inactive"] += 1
                return
            self.counters["actions_received"] += 1
            if other is not None:
                return self._reject("rejected_other_publisher", f"stamp {topics.format_stamp(stamp)}: {other}")
            try:
                a = topics.read_action(msg)
            except (ValueError, TypeError) as e:
                return self._reject("rejected_malformed", f"{e} (stamp {topics.format_stamp(stamp)})")
            if a.shape != (self.action_dim,):
                return self._reject("rejected_wrong_length",
                                    f"{a.size} values, expected {self.action_dim} "
                                    f"{self.action_names} (stamp {topics.format_stamp(stamp)})")
            if not np.all(np.isfinite(a)):
                return self._reject("rejected_nonfinite", f"{a.tolist()} (stamp {topics.format_stamp(stamp)})")
            if self.lockstep:
                if stamp != self._pending_stamp:
                    if stamp in self._answered_stamps:
                        return self._reject("rejected_duplicate",
                                            f"stamp {topics.format_stamp(stamp)} was already answered")
                    return self._reject("rejected_stale_stamp",
                                        f"stamp {topics.format_stamp(stamp)} is not the observation awaiting an "
                                        f"answer ({topics.format_stamp(self._pending_stamp)})" if self._pending_stamp is not None
                                        else f"stamp {topics.format_stamp(stamp)} arrived while no observation awaits an answer")
            else:
                if stamp not in self._published:
                    return self._reject("rejected_stale_stamp",
                                        f"stamp {topics.format_stamp(stamp)} answers no recent observation")
                if stamp in self._answered_stamps:
                    return self._reject("rejected_duplicate",
                                        f"stamp {topics.format_stamp(stamp)} was already answered")
            clipped = np.clip(a, ACTION_LOW, ACTION_HIGH)
            if np.any(clipped != a):
                self.counters["actions_clipped"] += 1
                self._throttle.warning(
                    "actions_clipped", f"action {a.tolist()} clipped to [{ACTION_LOW}, "
                    f"{ACTION_HIGH}] ({self.counters['actions_clipped']} so far)")
            self.counters["actions_accepted"] += 1
            self._answered_stamps.append(stamp)
            sent = self._published.get(stamp)
            if sent is not None:
                self.latency.add(now - sent)
            if self.lockstep:
                self._answer = clipped
                self._pending_stamp = None
                self._cond.notify_all()
            else:
                if stamp != self._newest_stamp:
                    self.counters["late_actions"] += 1
                    self._throttle.warning(
                        "late_actions", f"late action for stamp {topics.format_stamp(stamp)} (newest observation "
                        f"{topics.format_stamp(self._newest_stamp)}; {self.counters['late_actions']} late so far)")
                if stamp > self._held_stamp:
                    self._held, self._held_stamp = clipped, stamp

    def _on_reset(self, request, response):
        with self._cond:
            self.counters["resets_requested"] += 1
            if not self._go:
                response.success = False
                response.message = f"not active (lifecycle state {self.lifecycle_state})"
                return response
            if not self._started:
                response.success = False
                response.message = "no episode running yet (waiting for subscribers)"
                return response
            served = self._reset_served
            self._reset_requested = True
            self._cond.notify_all()
            ok = self._cond.wait_for(lambda: (self._reset_served > served or self._stop.is_set()
                                              or self.done.is_set()), timeout=10.0)
            response.success = bool(ok and self._reset_served > served)
            response.message = self._reset_note if response.success else "reset not served"
        return response

    # ------------------------------------------------------------------ stepping thread
    def _make_env(self):
        from sim_bridge.sim.envs import ContextDMCEnv

        p = self.params
        return ContextDMCEnv(p["task"], split=p["split"], seed=p["seed"],
                             action_repeat=p["action_repeat"], image_size=p["image_size"],
                             render_quality=p["render_quality"],
                             time_limit=p["episode_length"] * p["action_repeat"])

    def _run(self) -> None:
        """The stepping thread of one configured run: build the env, wait for activation and
        for the readers, step until cleanup (_stop) or max_episodes; close the env."""
        try:
            try:
                self.env = self._env_factory()
            except BaseException as e:  # noqa: BLE001 (reported by configure_node)
                self._env_error = e
                return
            finally:
                self._env_ready.set()
            if not self._wait_active() or not self._wait_ready():
                return
            (self._run_lockstep if self.lockstep else self._run_realtime)()
            if not self._stop.is_set():
                self.done.set()   # max_episodes reached: the process exits
        except Exception as e:  # noqa: BLE001
            if not self._stop.is_set():
                import traceback

                self.get_logger().fatal(f"stepping thread failed: {e}\n{traceback.format_exc()}")
                self.exit_code = 1
                self.done.set()
        finally:
            env, self.env = self.env, None
            if env is not None and hasattr(env, "close"):
                try:
                    env.close()   # in the thread that owns the GL context
                except Exception:  # noqa: BLE001 - on the way out: nothing left to tell
                    pass

    def _wait_active(self) -> bool:
        """Block while not active; False once the thread is to end."""
        with self._cond:
            self._cond.wait_for(lambda: self._go or self._stop.is_set())
        return not self._stop.is_set()

    def _readers_ready(self) -> bool:
        if not self._go:
            return False
        n = self.params["min_subscribers"]
        if min(self.pub_image.get_subscription_count(),
               self.pub_info.get_subscription_count()) < n:
            return False
        return (not self.lockstep) or self._policy_present()

    def _graph_readers_matched(self) -> bool:
        """Every reader of image/step_info/context already visible in the ROS graph (e.g. a
        recorder) is matched, so it gets the first observation too; and the image readers that
        answer nothing (recorders, unlike policies) are matched on context and clock as well:
        through a Discovery Server each topic is matched on its own, and a recorder's image
        reader can be matched before its context and clock readers are."""
        if not all(pub.get_subscription_count() >= self.count_subscribers(pub.topic_name)
                   for pub in self._obs_pubs):
            return False
        silent = self.pub_image.get_subscription_count() - self.sub_action.get_publisher_count()
        return min(self.pub_context.get_subscription_count(),
                   self.pub_clock.get_subscription_count()) >= silent

    def _wait_ready(self) -> bool:
        """Block until min_subscribers readers of image and step_info (and, in lock-step, an
        action publisher) are matched; then up to READY_GRACE_S more until every reader the
        ROS graph shows on image/step_info/context is matched as well."""
        self.get_logger().info(
            f"waiting for {self.params['min_subscribers']} reader(s) of image and step_info"
            + (" and an action publisher" if self.lockstep else ""))
        since = None
        while not self._stop.is_set():
            if not self._readers_ready():
                since = None
            else:
                since = since or time.monotonic()
                if self._graph_readers_matched() or time.monotonic() - since > READY_GRACE_S:
                    counts = {pub.topic_name: pub.get_subscription_count()
                              for pub in self._obs_pubs}
                    self.get_logger().info(f"readers matched {counts}: starting")
                    return True
            self._stop.wait(0.01)
        return False

    def _stamp(self) -> int:
        self._tick += 1
        return self._tick * self.dt_ns

    def _publish(self, obs, stamp: int, republish: bool = False) -> bool:
        """Publish observation `obs` (stamp); False, and nothing sent, while not active."""
        img, info, ctx = self._img_msg, self._info_msg, self._ctx_msg
        if not republish:
            self._return = 0.0 if obs.is_first else self._return + float(obs.reward)
            topics.fill_image(img, obs.image, stamp)
            topics.fill_step_info(info, topics.StepInfo(
                float(obs.reward), float(obs.discount), bool(obs.is_first), bool(obs.is_last),
                bool(obs.is_terminal), int(obs.episode), int(obs.step), self._return), stamp)
            if obs.is_last:   # the score of the episode, where a ROS user looks: the log
                label = ", ".join(f"{k}={v:g}" for k, v in obs.context.items())
                self.get_logger().info(f"episode {obs.episode} finished: return {self._return:.1f} "
                                       f"over {obs.step} steps ({obs.split} context {label})")
            topics.fill_context(ctx, obs.context, obs.split, stamp)
            topics.set_stamp(self._clock_msg.clock, stamp)
            self._episode, self._step, self._obs_context = obs.episode, obs.step, obs.context
        # Under _cond: a deactivation waits for a started observation to go out whole.
        with self._cond:
            if not self._go:
                return False
            self._published[stamp] = time.monotonic()
            while len(self._published) > 256:
                self._published.popitem(last=False)
            self._newest_stamp = stamp
            if self.lockstep:
                self._pending_stamp, self._answer = stamp, None
            self.counters["observations_republished" if republish
                          else "observations_published"] += 1
            # What the policy waits for first (it answers once image and step_info are in);
            # the true context and the clock follow while it computes.
            for pub, msg in ((self.pub_image, img), (self.pub_info, info), (self.pub_context, ctx),
                             (self.pub_clock, self._clock_msg)):
                self._send(pub, msg)
        return True

    def _send(self, pub, msg) -> None:
        """Publish, under _cond. A lossless writer refuses a sample once its history holds
        Fast DDS's limit (5000) of samples some reliable reader has not acknowledged (a recorder
        stalled that many steps): then wait for the reader, so a stall costs time, not a sample.
        The wait releases _cond: callbacks and diagnostics go on meanwhile."""
        while True:
            try:
                return pub.publish(msg)
            except RCLError as exc:
                if not self._obs_lossless or self._stop.is_set():
                    raise
                self.counters["publish_waits"] += 1
                self._throttle.warning("publish_waits", f"{pub.topic_name}: the writer's history is full of "
                                       f"samples a reader has not acknowledged (a stalled reader): waiting "
                                       f"for it ({self.counters['publish_waits']} waits so far; {exc})".replace("\n", " "))
                self._cond.wait(PUBLISH_RETRY_S)

    def _resume(self, stamp: int) -> bool:
        """Deactivated: hold the episode until active again (False: the thread is to end)."""
        self.get_logger().info(f"inactive: holding observation {topics.format_stamp(stamp)} until activated again")
        return self._wait_active()

    def _begin_episode(self):
        # None: the env draws uniformly from the split; else the schedule's next context.
        ctx = self._contexts[self._episodes_begun % len(self._contexts)] if self._contexts else None
        self._episodes_begun += 1
        obs = self.env.reset(context=ctx)
        with self._cond:
            self._held, self._held_stamp = np.zeros(self.action_dim), -1
        ctx = ", ".join(f"{k}={v:g}" for k, v in obs.context.items())
        self.get_logger().info(f"episode {obs.episode} ({obs.split} context {ctx})")
        return obs

    def _count_step(self) -> None:
        with self._cond:
            self.counters["steps"] += 1

    def _finish_episode(self) -> bool:
        """Count a finished episode; True when max_episodes is reached."""
        with self._cond:
            self.counters["episodes"] += 1
            n, limit = self.counters["episodes"], self.params["max_episodes"]
        if limit and n >= limit:
            self.get_logger().info(f"max_episodes={limit} reached: "
                                   f"{self.counters['steps']} steps; exiting")
            return True
        return False

    def _serve_reset(self, obs_before) -> Any:
        """Start a new episode at once (the current one ends without is_last)."""
        obs = self._begin_episode()
        with self._cond:
            self._reset_requested = False
            self._reset_note = (f"episode {obs_before.episode} ended at step "
                                f"{obs_before.step}; episode {obs.episode} started")
            self._reset_served += 1
            self._cond.notify_all()
        return obs

    def _run_lockstep(self) -> None:
        with self._cond:
            self._started = True
        obs = self._begin_episode()
        stamp = self._stamp()
        sent = self._publish(obs, stamp)
        while not self._stop.is_set():
            with self._cond:
                since = time.monotonic()   # the timeout may be changed while waiting
                rematched = False
                while not (self._stop.is_set() or self._answer is not None
                           or self._reset_requested or not self._go):
                    if not self._policy_present():
                        # Nobody can answer: wait without timing out; when a policy appears
                        # again the observation is published again at once.
                        self._cond.wait(0.1)
                        rematched = self._policy_present()
                        if rematched:
                            break
                        continue
                    left = since + self.params["lockstep_timeout_s"] - time.monotonic()
                    if left <= 0:
                        break
                    self._cond.wait(left)
                answer, reset, go = self._answer, self._reset_requested, self._go
            if self._stop.is_set():
                return
            if not go:   # paused: once active again the same observation goes out again
                if not self._resume(stamp):
                    return
                sent = self._publish(obs, stamp, republish=sent)
                continue
            if reset:
                obs = self._serve_reset(obs)
                stamp = self._stamp()
                sent = self._publish(obs, stamp)
                continue
            if answer is None:   # timeout: publish the same observation again, unchanged
                if rematched:
                    self.get_logger().info(f"action publisher matched again: publishing stamp "
                                           f"{topics.format_stamp(stamp)} again")
                elif sent:
                    with self._cond:
                        self.counters["lockstep_timeouts"] += 1
                    self._throttle.warning(
                        "lockstep_timeouts", f"no valid action for stamp {topics.format_stamp(stamp)} within "
                        f"{self.params['lockstep_timeout_s']} s: publishing it again "
                        f"({self.counters['lockstep_timeouts']} timeouts so far)")
                sent = self._publish(obs, stamp, republish=sent)
                continue
            if obs.is_last:
                if self._finish_episode():
                    return
                obs = self._begin_episode()
            else:
                obs = self.env.step(answer)
                self._count_step()
            stamp = self._stamp()
            sent = self._publish(obs, stamp)

    def _run_realtime(self) -> None:
        with self._cond:
            self._started = True
        obs = self._begin_episode()
        stamp = self._stamp()
        sent = self._publish(obs, stamp)
        next_t = time.monotonic()
        while not self._stop.is_set():
            with self._cond:
                next_t += 1.0 / self._control_rate
                while not (self._stop.is_set() or self._reset_requested or not self._go):
                    left = next_t - time.monotonic()
                    if left <= 0:
                        break
                    self._cond.wait(left)
                reset, action, go = self._reset_requested, self._held.copy(), self._go
            if self._stop.is_set():
                return
            if not go:   # paused: the sim holds still; it goes on at the rate once active
                if not self._resume(stamp):
                    return
                next_t = time.monotonic()
                if not sent:
                    sent = self._publish(obs, stamp)
                continue
            now = time.monotonic()
            if now - next_t > 1.0 / self._control_rate:   # fell behind: don't catch up
                with self._cond:
                    self.counters["realtime_overruns"] += 1
                next_t = now
            if reset:
                obs = self._serve_reset(obs)
                next_t = time.monotonic()
            elif obs.is_last:
                if self._finish_episode():
                    return
                obs = self._begin_episode()
            else:
                obs = self.env.step(action)
                self._count_step()
            stamp = self._stamp()
            sent = self._publish(obs, stamp)

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
            left_over = flush_publishers((*self._obs_pubs, self.pub_clock),
                                         LOSSLESS_FLUSH_TIMEOUT_S if lossless else FLUSH_TIMEOUT_S)
            for topic in left_over if lossless else ():
                self.get_logger().warning(
                    f"{topic}: exiting with samples a reader has not acknowledged after "
                    f"{LOSSLESS_FLUSH_TIMEOUT_S:g} s (a reader stalled or gone)")
        except Exception:  # noqa: BLE001 - exiting: the counters below are printed regardless
            pass
        c = self.counters
        self.get_logger().info(
            "stopped: " + (", ".join(f"{k}={c[k]}" for k in COUNTERS if c[k]) or "no steps"))


def main(argv: list[str] | None = None) -> None:
    from sim_bridge.nodekit.rosnode import run_node

    raise SystemExit(run_node(
        SimBridgeNode, prog="sim_bridge", params=PARAMS, argv=argv,
        description="Sim-bridge node: a context-randomized DMC task as ROS 2 topics "
                    "(image, step_info, context, /clock; action in; reset service). "
                    "Contract: msgs_docs/sim_bridge.md.",
        example="ros2 run sim_bridge node --ros-args -p task:=walker_walk -p mode:=lockstep "
                "-p max_episodes:=10 -r __ns:=/protocad"))


if __name__ == "__main__":
    main()
