"""The sim-bridge node: a context-randomized DMC task as ROS 2 topics (msgs_docs/sim_bridge.md).

    python -m sim_bridge.node --ros-args -p task:=pendulum_swingup -p mode:=lockstep
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
from rclpy.duration import Duration
from rclpy.event_handler import SubscriptionEventCallbacks
from sim_bridge.rosbase import ProtocadNode
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Image, JointState
from std_srvs.srv import Trigger

from sim_bridge import qos, topics
from sim_bridge.contexts import TASKS
from sim_bridge.rosnode import (ConfigError, KeyThrottle, Param, Percentiles, declare_all,
                                executor_param, install_parameter_guards, make_status, strict_param)

NODE_NAME = "sim_bridge"


def episode_contexts(task: str, split: str, schedule: str, fixed: str) -> list[dict[str, float]]:
    """The contexts episodes cycle through: [] = a uniform draw per reset. ConfigError for a
    malformed or out-of-table fixed context, naming the allowed values."""
    spec = TASKS[task]
    if fixed.strip():
        try:
            pairs = [item.split("=", 1) for item in fixed.replace(" ", "").split(",") if item]
            context = {k: float(v) for k, v in pairs}
        except ValueError:
            raise ConfigError(f"parameter context: {fixed!r} is not like 'm=0.2,d=1.5'") from None
        try:
            return [spec.validate(context, split)]
        except ValueError as e:
            raise ConfigError(f"parameter context: {e}") from None
    return spec.contexts(split) if schedule == "cycle" else []
MODES = ("lockstep", "realtime")

PARAMS: tuple[Param, ...] = (
    Param("task", "pendulum_swingup", "Context-randomized DMC task (sim_bridge.contexts.TASKS).",
          choices=tuple(sorted(TASKS))),
    Param("split", "train", "Context split drawn at each reset: train (C_train) or test (C_test).",
          choices=("train", "test")),
    Param("context_schedule", "sample", "How each reset picks its context from the split: "
          "sample = uniform draw (training, the paper's protocol); cycle = the split's grid in "
          "order, episode i gets context i mod n (evaluation: max_episodes = E * n gives exactly "
          "E episodes per context).", choices=("sample", "cycle")),
    Param("context", "", "A fixed context for every episode, e.g. 'm=0.2,d=1.5' (values from "
          "the split's table); empty = context_schedule decides."),
    Param("seed", 0, "Seeds the context draws and dm_control's initial states: a lock-step run "
          "is reproducible given the seed.", range=(0, 2**31 - 1)),
    Param("mode", "lockstep", "lockstep: each step waits for the action answering it; "
          "realtime: steps at control_rate_hz holding the latest action.", choices=MODES),
    Param("control_rate_hz", 0.0, "Real-time mode: agent steps per wall-clock second; 0 = the "
          "task's own rate 1/control_dt (real-time factor 1). Unused in lock-step.",
          read_only=False, range=(0.0, 1000.0), units="Hz"),
    Param("render_quality", "fast", "fast: no shadows/reflections/MSAA, 64x64 framebuffer "
          "(about 4x faster); default: the suite's look.", choices=("fast", "default")),
    Param("image_size", 64, "Image height and width (the model expects 64).", range=(16, 512),
          units="px"),
    Param("action_repeat", 2, "Physics control steps per agent step (the action is repeated).",
          range=(1, 100)),
    Param("episode_length", 500, "Agent steps per episode before the time limit ends it "
          "(time_limit = episode_length * action_repeat env steps; 500 = DMC's 1000 env steps).",
          range=(1, 1_000_000), units="agent steps"),
    Param("lockstep_timeout_s", 5.0, "Lock-step: with a policy matched and no valid answer "
          "after this long, the same observation is published again (counted in "
          "lockstep_timeouts).", read_only=False, range=(0.01, 3600.0), units="s"),
    Param("max_episodes", 0, "Exit (code 0) after this many complete episodes (lock-step: once "
          "the answer to the last is_last has arrived); 0 = run until stopped.", read_only=False,
          range=(0, 1_000_000_000)),
    Param("min_subscribers", 1, "Readers that must be matched on image and on step_info before "
          "the first observation is published (e.g. 2 = policy + recorder); readers already "
          "visible in the graph on image/step_info/context are awaited too (up to 2 s).",
          range=(0, 1000)),
    Param("diagnostics_period_s", 1.0, "Period of /diagnostics.", range=(0.05, 3600.0),
          units="s"),
    strict_param(),
    executor_param(),
)

ACTION_LOW, ACTION_HIGH = -1.0, 1.0
#: Longest wait, once min_subscribers are matched, for readers already in the graph to match.
READY_GRACE_S = 2.0
#: Longest wait at shutdown for reliable readers to acknowledge the last observations.
FLUSH_TIMEOUT_S = 1.0
#: Counters reported on /diagnostics (all cumulative since start).
COUNTERS = ("steps", "episodes", "observations_published", "observations_republished",
            "actions_received", "actions_accepted", "actions_rejected", "rejected_malformed",
            "rejected_wrong_length", "rejected_nonfinite", "rejected_stale_stamp",
            "rejected_duplicate", "actions_clipped", "late_actions", "lockstep_timeouts",
            "realtime_overruns", "resets_requested", "unknown_parameters",
            "parameters_rejected")


class SimBridgeNode(ProtocadNode):
    """See the module docstring; parameters in PARAMS, counters in COUNTERS."""

    def __init__(self, *, namespace: str = topics.DEFAULT_NAMESPACE, env_factory=None, **kw: Any):
        super().__init__(NODE_NAME, namespace=namespace, **kw)
        self.done = threading.Event()
        self.exit_code = 0
        p = self.params = declare_all(self, PARAMS)
        self.executor_kind = p["executor"]
        self._contexts = episode_contexts(p["task"], p["split"], p["context_schedule"],
                                          p["context"])
        self._episodes_begun = 0
        self.lockstep = p["mode"] == "lockstep"
        # The GL context of the renderer is bound to the thread that creates it: the stepping
        # thread builds the env, __init__ waits for it (and reports a bad configuration).
        self._env_factory = env_factory or self._make_env
        self._go = threading.Event()
        self._stop = threading.Event()
        self._env_error: BaseException | None = None
        self._env_ready = threading.Event()
        self.env = None
        self._thread = threading.Thread(target=self._run, name="sim_bridge_stepper", daemon=True)
        self._thread.start()
        while not self._env_ready.wait(0.1):
            if not self._thread.is_alive():
                break
        if self._env_error is not None:
            if isinstance(self._env_error, (TypeError, ValueError)):
                raise ConfigError(str(self._env_error))
            raise self._env_error
        env = self.env
        self.action_dim = int(env.action_dim)
        self.action_names = list(env.action_names)
        self.dt_ns = int(round(env.control_dt * 1e9))

        # Shared state between the executor thread (callbacks) and the stepping thread.
        self._cond = threading.Condition()
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
        self.counters = dict.fromkeys(COUNTERS, 0)
        self.counters["unknown_parameters"] = len(self.unknown_parameters)
        self._throttle = KeyThrottle(self.get_logger())
        self.latency = Percentiles()             # observation published -> answer received
        self._late_at_last_diag = 0
        self._rate_window = collections.deque(maxlen=2)
        self._rate_window.append((time.monotonic(), 0))
        self._episode = -1
        self._step = -1
        self._obs_context: dict[str, float] = {}
        self._control_rate = p["control_rate_hz"] or 1e9 / self.dt_ns

        ns = self.get_namespace()
        self._img_msg, self._info_msg, self._ctx_msg, self._clock_msg = (
            Image(), JointState(), JointState(), Clock())
        obs_qos = qos.observation_qos()
        # A profile of its own: rclpy's QoS overriding changes the profile object it is given.
        self.pub_image = self.create_publisher(Image, topics.IMAGE, qos.observation_qos(),
                                               qos_overriding_options=qos.overridable())
        self.pub_info = self.create_publisher(JointState, topics.STEP_INFO, obs_qos)
        self.pub_context = self.create_publisher(JointState, topics.CONTEXT, obs_qos)
        self.pub_clock = self.create_publisher(Clock, topics.CLOCK, qos.clock_qos())
        self.pub_diag = self.create_publisher(DiagnosticArray, topics.DIAGNOSTICS,
                                              qos.diagnostics_qos())
        self.pub_bridge_info = self.create_publisher(JointState, topics.BRIDGE_INFO, qos.announcement_qos())
        self.pub_bridge_info.publish(topics.fill_bridge_info(JointState(), topics.BridgeInfo(
            p["task"], self.action_names, self.dt_ns / 1e9, p["image_size"])))
        self._others_warned: set[str] = set()
        self.sub_action = self.create_subscription(
            JointState, topics.ACTION, self._on_action, qos.action_qos(),
            qos_overriding_options=qos.overridable(),
            event_callbacks=SubscriptionEventCallbacks(matched=self._on_action_matched))
        self.srv_reset = self.create_service(Trigger, topics.RESET_SERVICE, self._on_reset)
        self.diag_timer = self.create_timer(p["diagnostics_period_s"], self._publish_diagnostics)
        install_parameter_guards(self, PARAMS, self._apply_param, self._parameter_rejected)
        self._obs_pubs = (self.pub_image, self.pub_info, self.pub_context)
        self._diag_name = self.get_fully_qualified_name()   # -r __node:=... renames it too
        self.get_logger().info(
            f"{p['task']} ({p['split']} contexts, seed {p['seed']}) in {p['mode']} mode: "
            f"{self.action_dim}-d actions {self.action_names}, control_dt "
            f"{self.dt_ns / 1e9:g} s, {p['episode_length']} steps/episode; topics under "
            f"{ns}; QoS {qos.describe(obs_qos)}")
        self._go.set()   # the stepping thread may start waiting for readers

    # ------------------------------------------------------------------ callbacks
    def _apply_param(self, name: str, value: Any) -> None:
        with self._cond:
            self.params[name] = value
            if name == "control_rate_hz":
                self._control_rate = value or 1e9 / self.dt_ns
            self._cond.notify_all()

    def _parameter_rejected(self, reason: str) -> None:
        with self._cond:
            self.counters["parameters_rejected"] += 1
        self.get_logger().warning(f"parameter change rejected: {reason}")

    def _on_action_matched(self, info) -> None:
        with self._cond:   # wake the stepping thread (it re-checks _policy_present)
            self._cond.notify_all()

    def _policy_present(self) -> bool:
        return self.sub_action.get_publisher_count() > 0

    def _reject(self, counter: str, why: str) -> None:
        self.counters["actions_rejected"] += 1
        self.counters[counter] += 1
        self._throttle.warning(
            counter, f"action rejected ({counter}, {self.counters[counter]} so far): {why}")

    def _on_action(self, msg) -> None:
        now = time.monotonic()
        stamp = topics.stamp_to_ns(msg.header.stamp)
        with self._cond:
            self.counters["actions_received"] += 1
            try:
                a = topics.read_action(msg)
            except (ValueError, TypeError) as e:
                return self._reject("rejected_malformed", f"{e} (stamp {stamp})")
            if a.shape != (self.action_dim,):
                return self._reject("rejected_wrong_length",
                                    f"{a.size} values, expected {self.action_dim} "
                                    f"{self.action_names} (stamp {stamp})")
            if not np.all(np.isfinite(a)):
                return self._reject("rejected_nonfinite", f"{a.tolist()} (stamp {stamp})")
            if self.lockstep:
                if stamp != self._pending_stamp:
                    if stamp in self._answered_stamps:
                        return self._reject("rejected_duplicate",
                                            f"stamp {stamp} was already answered")
                    return self._reject("rejected_stale_stamp",
                                        f"stamp {stamp} is not the observation awaiting an "
                                        f"answer ({self._pending_stamp})" if self._pending_stamp is not None
                                        else f"stamp {stamp} arrived while no observation awaits an answer")
            else:
                if stamp not in self._published:
                    return self._reject("rejected_stale_stamp",
                                        f"stamp {stamp} answers no recent observation")
                if stamp in self._answered_stamps:
                    return self._reject("rejected_duplicate",
                                        f"stamp {stamp} was already answered")
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
                        "late_actions", f"late action for stamp {stamp} (newest observation "
                        f"{self._newest_stamp}; {self.counters['late_actions']} late so far)")
                if stamp > self._held_stamp:
                    self._held, self._held_stamp = clipped, stamp

    def _on_reset(self, request, response):
        with self._cond:
            self.counters["resets_requested"] += 1
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
        from sim_bridge.envs import ContextDMCEnv

        p = self.params
        return ContextDMCEnv(p["task"], split=p["split"], seed=p["seed"],
                             action_repeat=p["action_repeat"], image_size=p["image_size"],
                             render_quality=p["render_quality"],
                             time_limit=p["episode_length"] * p["action_repeat"])

    def _run(self) -> None:
        try:
            try:
                self.env = self._env_factory()
            except BaseException as e:  # noqa: BLE001 (reported by __init__)
                self._env_error = e
                return
            finally:
                self._env_ready.set()
            while not self._go.wait(0.1):
                if self._stop.is_set():
                    return
            if not self._wait_ready():
                return
            (self._run_lockstep if self.lockstep else self._run_realtime)()
        except Exception as e:  # noqa: BLE001
            if not self._stop.is_set():
                import traceback

                self.get_logger().fatal(f"stepping thread failed: {e}\n{traceback.format_exc()}")
                self.exit_code = 1
        finally:
            self.done.set()
            env, self.env = self.env, None
            if env is not None and hasattr(env, "close"):
                try:
                    env.close()   # in the thread that owns the GL context
                except Exception:
                    pass

    def _readers_ready(self) -> bool:
        n = self.params["min_subscribers"]
        if min(self.pub_image.get_subscription_count(),
               self.pub_info.get_subscription_count()) < n:
            return False
        return (not self.lockstep) or self._policy_present()

    def _graph_readers_matched(self) -> bool:
        """Every reader of image/step_info/context already visible in the ROS graph (e.g. a
        recorder) is matched, so it gets the first observation too."""
        return all(pub.get_subscription_count() >= self.count_subscribers(pub.topic_name)
                   for pub in self._obs_pubs)

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

    def _publish(self, obs, stamp: int, republish: bool = False) -> None:
        img, info, ctx = self._img_msg, self._info_msg, self._ctx_msg
        if not republish:
            topics.fill_image(img, obs.image, stamp)
            topics.fill_step_info(info, topics.StepInfo(
                float(obs.reward), float(obs.discount), bool(obs.is_first), bool(obs.is_last),
                bool(obs.is_terminal), int(obs.episode), int(obs.step)), stamp)
            topics.fill_context(ctx, obs.context, obs.split, stamp)
            topics.set_stamp(self._clock_msg.clock, stamp)
            self._episode, self._step, self._obs_context = obs.episode, obs.step, obs.context
        with self._cond:
            self._published[stamp] = time.monotonic()
            while len(self._published) > 256:
                self._published.popitem(last=False)
            self._newest_stamp = stamp
            if self.lockstep:
                self._pending_stamp, self._answer = stamp, None
            self.counters["observations_republished" if republish
                          else "observations_published"] += 1
        self.pub_clock.publish(self._clock_msg)
        self.pub_context.publish(ctx)
        self.pub_info.publish(info)
        self.pub_image.publish(img)

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
        self._tick = -1
        with self._cond:
            self._started = True
        obs = self._begin_episode()
        stamp = self._stamp()
        self._publish(obs, stamp)
        while not self._stop.is_set():
            with self._cond:
                since = time.monotonic()   # the timeout may be changed while waiting
                rematched = False
                while not (self._stop.is_set() or self._answer is not None
                           or self._reset_requested):
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
                answer, reset = self._answer, self._reset_requested
            if self._stop.is_set():
                return
            if reset:
                obs = self._serve_reset(obs)
                stamp = self._stamp()
                self._publish(obs, stamp)
                continue
            if answer is None:   # timeout: publish the same observation again, unchanged
                if rematched:
                    self.get_logger().info(f"action publisher matched again: publishing stamp "
                                           f"{stamp} again")
                else:
                    with self._cond:
                        self.counters["lockstep_timeouts"] += 1
                    self._throttle.warning(
                        "lockstep_timeouts", f"no valid action for stamp {stamp} within "
                        f"{self.params['lockstep_timeout_s']} s: publishing it again "
                        f"({self.counters['lockstep_timeouts']} timeouts so far)")
                self._publish(obs, stamp, republish=True)
                continue
            if obs.is_last:
                if self._finish_episode():
                    return
                obs = self._begin_episode()
            else:
                obs = self.env.step(answer)
                self._count_step()
            stamp = self._stamp()
            self._publish(obs, stamp)

    def _run_realtime(self) -> None:
        self._tick = -1
        with self._cond:
            self._started = True
        obs = self._begin_episode()
        self._publish(obs, self._stamp())
        next_t = time.monotonic()
        while not self._stop.is_set():
            with self._cond:
                next_t += 1.0 / self._control_rate
                while not (self._stop.is_set() or self._reset_requested):
                    left = next_t - time.monotonic()
                    if left <= 0:
                        break
                    self._cond.wait(left)
                reset, action = self._reset_requested, self._held.copy()
            if self._stop.is_set():
                return
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
            self._publish(obs, self._stamp())

    # ------------------------------------------------------------------ diagnostics
    def _publish_diagnostics(self) -> None:
        now = time.monotonic()
        with self._cond:
            c = dict(self.counters)
            t0, s0 = self._rate_window[0]
            self._rate_window.append((now, c["steps"]))
            episode, step, context = self._episode, self._step, dict(self._obs_context)
            tick = getattr(self, "_tick", -1)
        rate = (c["steps"] - s0) / (now - t0) if now > t0 else 0.0
        values: dict[str, Any] = {
            "task": self.params["task"], "split": self.params["split"],
            "seed": self.params["seed"], "mode": self.params["mode"],
            "steps_per_s": rate,
            "action_latency_ms_p50": self.latency.percentile(50) * 1e3,
            "action_latency_ms_p99": self.latency.percentile(99) * 1e3,
            "episode": episode, "step": step,
            "sim_time_s": max(tick, 0) * self.dt_ns / 1e9,
            "action_publishers": self.sub_action.get_publisher_count(),
            "callback_errors": self.callback_errors,
            **{f"context/{k}": v for k, v in context.items()},
            **c,
        }
        if not self.lockstep:
            values["control_rate_hz"] = self._control_rate
        # Late actions are a rate, not a state: WARN only while new ones arrive (one late
        # action must not mark the rest of a run).
        others = self._other_publishers()
        late_now = c["late_actions"] - self._late_at_last_diag
        self._late_at_last_diag = c["late_actions"]
        warn = c["actions_rejected"] or c["lockstep_timeouts"] or late_now or self.callback_errors
        unknown = self.unknown_parameters
        values["other_publishers"] = ", ".join(others)
        status = make_status(self._diag_name, self.params["task"], values,
                             "ERROR" if others else "WARN" if warn or unknown else "OK",
                             f"another publisher on {', '.join(others)} (a second bridge in this "
                             "namespace?)" if others else
                             f"unknown parameters ignored: {unknown}" if unknown else
                             "rejected/late actions or timeouts" if warn else "running")
        arr = DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        arr.status = [status]
        try:
            self.pub_diag.publish(arr)
        except Exception:  # context shutting down
            pass

    def _other_publishers(self) -> list[str]:
        """The bridge's own topics that some other node publishes too: two bridges in one
        namespace (or a stray publisher) interleave observations and /clock, so both say so."""
        others = []
        for pub in (self.pub_image, self.pub_info, self.pub_context, self.pub_bridge_info):
            topic = pub.topic_name
            if self.count_publishers(topic) > 1:
                others.append(topic)
        for topic in others:
            if topic not in self._others_warned:
                self._others_warned.add(topic)
                self.get_logger().error(f"another node also publishes {topic} (a second sim bridge in "
                                        f"{self.get_namespace()}?): its observations interleave with "
                                        "ours; run each bridge in its own namespace and domain")
        return others

    # ------------------------------------------------------------------ shutdown
    def close(self) -> None:
        """Stop the stepping thread, flush the last messages to reliable readers."""
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        self._thread.join(timeout=10.0)
        try:
            self._publish_diagnostics()
            # Reliable readers acknowledge lazily (on the writer's next heartbeat): give the
            # last samples a bounded chance to be acknowledged (or repaired) before exiting.
            deadline = time.monotonic() + FLUSH_TIMEOUT_S
            for pub in (*self._obs_pubs, self.pub_clock):
                left = max(0.0, deadline - time.monotonic())
                pub.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9)))
        except Exception:
            pass
        c = self.counters
        self.get_logger().info(
            "stopped: " + (", ".join(f"{k}={c[k]}" for k in COUNTERS if c[k]) or "no steps"))


def main(argv: list[str] | None = None) -> None:
    from sim_bridge.rosnode import run_node

    raise SystemExit(run_node(
        SimBridgeNode, prog="sim_bridge", params=PARAMS, argv=argv,
        description="Sim-bridge node: a context-randomized DMC task as ROS 2 topics "
                    "(image, step_info, context, /clock; action in; reset service). "
                    "Contract: msgs_docs/sim_bridge.md.",
        example="python -m sim_bridge.node --ros-args -p task:=walker_walk -p mode:=lockstep "
                "-p max_episodes:=10 -r __ns:=/protocad"))


if __name__ == "__main__":
    main()
