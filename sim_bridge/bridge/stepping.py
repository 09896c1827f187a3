"""The sim bridge's stepping thread: it builds and owns the env (the renderer's GL context is
bound to the thread that creates it), waits to be active and for its readers, then steps in
lock-step (each observation waits for the action stamped with it; msgs_docs/sim_bridge.md) or in
real time (at control_rate_hz with the latest valid action) until cleanup or max_episodes.

Stepping (the node's `stepping`) owns the thread, the env and what the env fixes at configure
(action_dim, action_names, dt_ns, the real-time control rate), and the episode-context schedule.
It is handed BridgeShared (sim_bridge/bridge/handover.py: the node, for its logger and the ROS
graph; the parameters; the Handover through which ActionIntake's accepted actions and reset
requests arrive; the counters, the log throttle and the mode), the episode contexts, the env
factory, ObservationPublishing (its publishers, to see who reads them, and its `publish` and
`next_stamp`), ActionIntake's `action_publishers` and the node's `finished(exit_code)` (the
process is done)."""
from __future__ import annotations

import threading
import time
import traceback
from typing import Any, Callable

import numpy as np

from sim_bridge.bridge.handover import BridgeShared
from sim_bridge.bridge.observation_publishing import ObservationPublishing
from sim_bridge.bridge.params import READY_GRACE_S
from sim_bridge.contract import topics
from sim_bridge.nodekit.param_table import ConfigError
from sim_bridge.sim.envs import ContextDMCEnv


def bridge_env(p: dict[str, Any], render_size: tuple[int, int] | None) -> ContextDMCEnv:
    """The env the parameters describe (render_size: CameraOut's, None for the square image)."""
    return ContextDMCEnv(p["task"], split=p["split"], seed=p["seed"],
                         action_repeat=p["action_repeat"], image_size=p["image_size"],
                         render_quality=p["render_quality"],
                         time_limit=p["episode_length"] * p["action_repeat"],
                         camera_size=render_size)


class Stepping:
    """The stepping thread and its env; see the module docstring."""

    def __init__(self, shared: BridgeShared, *, contexts: list[dict[str, float]],
                 env_factory: Callable[[], Any], publishing: ObservationPublishing,
                 action_publishers: Callable[[], int], finished: Callable[[int], None]):
        self.node, self.params, self.handover = shared.node, shared.params, shared.handover
        self.counters, self.throttle, self.lockstep = shared.counters, shared.throttle, shared.lockstep
        self._contexts = contexts
        self._env_factory = env_factory
        # ObservationPublishing's publishers (whose readers it waits for) and its one way out.
        self._obs_pubs = publishing.observation_pubs   # image, step_info, context
        self.pub_image, self.pub_info, self.pub_context = publishing.observation_pubs
        self.pub_clock = publishing.pub_clock
        self._publish, self._stamp = publishing.publish, publishing.next_stamp
        self._action_publishers = action_publishers   # ActionIntake's count of action writers
        self._finished = finished
        self._thread: threading.Thread | None = None
        self._env_ready = threading.Event()   # per configure: the thread built the env, or failed
        self._env_error: BaseException | None = None
        self.env = None
        self.action_dim, self.action_names, self.dt_ns = 0, [], 0
        self.control_rate = self.params["control_rate_hz"]   # the task's rate once configured
        self._episodes_begun = 0

    # ------------------------------------------------------------------ the node's lifecycle
    def configure(self) -> None:
        """Build the env in a new stepping thread (the renderer's GL context is bound to the
        thread that creates it) and wait for it; a bad configuration is a ConfigError."""
        if self._thread is not None and self._thread.is_alive():
            raise RuntimeError("the previous stepping thread has not ended")
        self.handover.stop.clear()
        self._env_error = None
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
        with self.handover.cond:
            self.action_dim = int(env.action_dim)
            self.action_names = list(env.action_names)
            self.dt_ns = int(round(env.control_dt * 1e9))
            self.control_rate = self.params["control_rate_hz"] or 1e9 / self.dt_ns
            self._episodes_begun = 0

    def cleanup(self) -> None:
        """End the stepping thread; it closes the env (in the thread that owns the GL context)."""
        self.handover.stop.set()
        self.handover.set_go(False)
        if self._thread is not None:
            self._thread.join(timeout=10.0)
            if self._thread.is_alive():
                raise RuntimeError("the stepping thread did not end within 10 s")
        self._thread = None

    def set_control_rate(self, hz: float) -> None:
        """control_rate_hz changed (0: the task's rate). Called under the handover's cond."""
        if self.dt_ns:
            self.control_rate = hz or 1e9 / self.dt_ns

    # ------------------------------------------------------------------ the thread
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
            if not self.handover.stop.is_set():
                self._finished(0)   # max_episodes reached: the process exits
        except Exception as e:  # noqa: BLE001
            if not self.handover.stop.is_set():
                self.node.get_logger().fatal(f"stepping thread failed: {e}\n{traceback.format_exc()}")
                self._finished(1)
        finally:
            env, self.env = self.env, None
            if env is not None and hasattr(env, "close"):
                try:
                    env.close()   # in the thread that owns the GL context
                except Exception:  # noqa: BLE001 - on the way out: nothing left to tell
                    pass

    def _wait_active(self) -> bool:
        """Block while not active; False once the thread is to end."""
        h = self.handover
        with h.cond:
            h.cond.wait_for(lambda: h.go or h.stop.is_set())
        return not h.stop.is_set()

    def _policy_present(self) -> bool:
        return self._action_publishers() > 0

    def _readers_ready(self) -> bool:
        if not self.handover.go:
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
        if not all(pub.get_subscription_count() >= self.node.count_subscribers(pub.topic_name)
                   for pub in self._obs_pubs):
            return False
        silent = self.pub_image.get_subscription_count() - self._action_publishers()
        return min(self.pub_context.get_subscription_count(),
                   self.pub_clock.get_subscription_count()) >= silent

    def _wait_ready(self) -> bool:
        """Block until min_subscribers readers of image and step_info (and, in lock-step, an
        action publisher) are matched; then up to READY_GRACE_S more until every reader the
        ROS graph shows on image/step_info/context is matched as well."""
        self.node.get_logger().info(
            f"waiting for {self.params['min_subscribers']} reader(s) of image and step_info"
            + (" and an action publisher" if self.lockstep else ""))
        since = None
        while not self.handover.stop.is_set():
            if not self._readers_ready():
                since = None
            else:
                since = since or time.monotonic()
                if self._graph_readers_matched() or time.monotonic() - since > READY_GRACE_S:
                    counts = {pub.topic_name: pub.get_subscription_count()
                              for pub in self._obs_pubs}
                    self.node.get_logger().info(f"readers matched {counts}: starting")
                    return True
            self.handover.stop.wait(0.01)
        return False

    def _resume(self, stamp: int) -> bool:
        """Deactivated: hold the episode until active again (False: the thread is to end)."""
        self.node.get_logger().info(f"inactive: holding observation {topics.format_stamp(stamp)} until activated again")
        return self._wait_active()

    def _begin_episode(self):
        # None: the env draws uniformly from the split; else the schedule's next context.
        ctx = self._contexts[self._episodes_begun % len(self._contexts)] if self._contexts else None
        self._episodes_begun += 1
        obs = self.env.reset(context=ctx)
        h = self.handover
        with h.cond:
            h.held, h.held_stamp = np.zeros(self.action_dim), -1
        ctx = ", ".join(f"{k}={v:g}" for k, v in obs.context.items())
        self.node.get_logger().info(f"episode {obs.episode} ({obs.split} context {ctx})")
        return obs

    def _count_step(self) -> None:
        with self.handover.cond:
            self.counters["steps"] += 1

    def _finish_episode(self) -> bool:
        """Count a finished episode; True when max_episodes is reached."""
        with self.handover.cond:
            self.counters["episodes"] += 1
            n, limit = self.counters["episodes"], self.params["max_episodes"]
        if limit and n >= limit:
            self.node.get_logger().info(f"max_episodes={limit} reached: "
                                        f"{self.counters['steps']} steps; exiting")
            return True
        return False

    def _serve_reset(self, obs_before) -> Any:
        """Start a new episode at once (the current one ends without is_last)."""
        obs = self._begin_episode()
        h = self.handover
        with h.cond:
            h.reset_requested = False
            h.reset_note = (f"episode {obs_before.episode} ended at step "
                            f"{obs_before.step}; episode {obs.episode} started")
            h.reset_served += 1
            h.cond.notify_all()
        return obs

    def _run_lockstep(self) -> None:
        h = self.handover
        with h.cond:
            h.started = True
        obs = self._begin_episode()
        stamp = self._stamp()
        sent = self._publish(obs, stamp)
        while not h.stop.is_set():
            with h.cond:
                since = time.monotonic()   # the timeout may be changed while waiting
                rematched = False
                while not (h.stop.is_set() or h.answer is not None
                           or h.reset_requested or not h.go):
                    if not self._policy_present():
                        # Nobody can answer: wait without timing out; when a policy appears
                        # again the observation is published again at once.
                        h.cond.wait(0.1)
                        rematched = self._policy_present()
                        if rematched:
                            break
                        continue
                    left = since + self.params["lockstep_timeout_s"] - time.monotonic()
                    if left <= 0:
                        break
                    h.cond.wait(left)
                answer, reset, go = h.answer, h.reset_requested, h.go
            if h.stop.is_set():
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
                    self.node.get_logger().info(f"action publisher matched again: publishing stamp "
                                                f"{topics.format_stamp(stamp)} again")
                elif sent:
                    with h.cond:
                        self.counters["lockstep_timeouts"] += 1
                    self.throttle.warning(
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
        h = self.handover
        with h.cond:
            h.started = True
        obs = self._begin_episode()
        stamp = self._stamp()
        sent = self._publish(obs, stamp)
        next_t = time.monotonic()
        while not h.stop.is_set():
            with h.cond:
                next_t += 1.0 / self.control_rate
                while not (h.stop.is_set() or h.reset_requested or not h.go):
                    left = next_t - time.monotonic()
                    if left <= 0:
                        break
                    h.cond.wait(left)
                reset, action, go = h.reset_requested, h.held.copy(), h.go
            if h.stop.is_set():
                return
            if not go:   # paused: the sim holds still; it goes on at the rate once active
                if not self._resume(stamp):
                    return
                next_t = time.monotonic()
                if not sent:
                    sent = self._publish(obs, stamp)
                continue
            now = time.monotonic()
            if now - next_t > 1.0 / self.control_rate:   # fell behind: don't catch up
                with h.cond:
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
