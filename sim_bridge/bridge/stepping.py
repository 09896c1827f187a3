"""The sim bridge's stepping thread: it builds and owns the env (the renderer's GL context is
bound to the thread that creates it), waits to be active and for its readers, then steps in
lock-step (each observation waits for the action stamped with it; msgs_docs/sim_bridge.md) or in
real time (at control_rate_hz with the latest valid action) until cleanup or max_episodes. A
part of SimBridgeNode: it publishes through ObservationPublishing and takes the actions
ActionIntake accepted, both under the node's condition variable."""
from __future__ import annotations

import time
import traceback
from typing import Any

import numpy as np

from sim_bridge.bridge.params import READY_GRACE_S
from sim_bridge.contract import topics
from sim_bridge.sim.envs import ContextDMCEnv


class Stepping:
    def _make_env(self):
        p = self.params
        return ContextDMCEnv(p["task"], split=p["split"], seed=p["seed"],
                             action_repeat=p["action_repeat"], image_size=p["image_size"],
                             render_quality=p["render_quality"],
                             time_limit=p["episode_length"] * p["action_repeat"],
                             camera_size=self.camera.render_size)

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
