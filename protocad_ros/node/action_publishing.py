"""How the policy node answers a paired observation: one filter step of the served model (its
RSSM state reset at is_first, when a pending checkpoint is also swapped in), then the action and
the inferred context features u, w, e published on action and context_features with the
observation's stamp, and the act callbacks (add_act_callback; the live view's when enabled)
told with an ActEvent. A part of PolicyNode, on its executor thread: it keeps the node's
per-episode state (`_prev_action`, `_last_stamp`, `_last_answer`, `_episode`, `_step`) and the
latency percentiles, and drops the unpaired pieces the answered stamp has made stale."""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
from sensor_msgs.msg import JointState

from sim_bridge.contract import topics


@dataclass
class ActEvent:
    """What an act callback receives after each answered observation."""

    stamp_ns: int
    info: topics.StepInfo
    image: np.ndarray          # (H, W, 3) uint8
    action: np.ndarray         # (A,) float32 in [-1, 1]
    features: Any              # protocad_ros.policy.ContextFeatures (u, w, e)
    latency_s: float           # completing message received -> action published
    checkpoint_updates: int    # -1 for a random agent


class ActionPublishing:
    def add_act_callback(self, fn: Callable[[ActEvent], None]) -> None:
        """Call fn(ActEvent) after each answered observation (in the executor thread: keep it
        quick, e.g. hand over to a queue)."""
        self._act_callbacks.append(fn)

    def _answer(self, stamp: int, image: np.ndarray, info: topics.StepInfo, t_recv: float) -> None:
        self._track_episode(info)
        t0 = time.monotonic()
        action, feats = self.policy.act(image, self._prev_action, bool(info.is_first))
        self.act_time.add(time.monotonic() - t0)
        # The model's action, or the safe action while disabled; its command out to a robot first.
        action = self.robot.answer(np.asarray(action, np.float32).reshape(-1), stamp)
        amsg = topics.fill_action(JointState(), action, self.action_names, stamp)
        u, w, e = (np.asarray(getattr(feats, k, ()), np.float32).reshape(-1) for k in "uwe")
        fmsg = topics.fill_context_features(JointState(), u, w, e, stamp)
        self.pub_action.publish(amsg)
        self.pub_features.publish(fmsg)
        latency = time.monotonic() - t_recv
        self.latency.add(latency)
        self._prev_action = action.copy()
        self._last_stamp, self._last_answer = stamp, (amsg, fmsg)
        self._episode, self._step = info.episode, info.step
        self._episode_return = info.episode_return   # the bridge's running return (optional)
        stale = [s for s in self._unpaired if s < stamp]   # pieces that can no longer pair
        for s in stale:
            del self._unpaired[s]
        if stale:
            with self._lock:
                self.counters["fragments_discarded"] += len(stale)
        self._count("observations_answered")
        callbacks = self._act_callbacks + (
            [self.live_view.on_act] if self.live_view is not None and self.live_view.enabled else [])
        if callbacks:
            event = ActEvent(stamp, info, image, action, feats, latency, self.checkpoint_updates)
            for fn in callbacks:
                try:
                    fn(event)
                except Exception as exc:  # noqa: BLE001
                    self._count("act_callback_errors", f"act callback {fn!r} failed: {exc}")

    def _track_episode(self, info: topics.StepInfo) -> None:
        """Before the model step: an episode's end reported and a pending checkpoint swapped in
        at is_first, or the observations that never arrived whole counted."""
        if info.is_first:
            if self._last_stamp is not None:   # the latency while running, not only at exit
                score = (f"return {self._episode_return:.1f}, " if self._episode_return is not None else "")
                self.get_logger().info(
                    f"episode {self._episode} answered ({self._step + 1} steps); {score}latency obs -> action "
                    f"p50 {self.latency.percentile(50) * 1e3:.2f} ms, p99 {self.latency.percentile(99) * 1e3:.2f} ms "
                    f"(model p50 {self.act_time.percentile(50) * 1e3:.2f} ms)")
            self._swap_if_pending()
            self._prev_action[:] = 0.0
            self._count("episodes")
        elif self._last_stamp is None:
            self.get_logger().info(f"joined in the middle of episode {info.episode} (step "
                                   f"{info.step}): filtering from a blank state")
        else:
            # Observations that never reached us whole (a DDS queue overwritten under load, a
            # flood): the contract numbers the steps of an episode 0, 1, 2, ... A later episode
            # shows its lost head; the lost tail of an earlier one is not knowable.
            lost = info.step - self._step - 1 if info.episode == self._episode else info.step
            if lost > 0 and self.params["latest_only"]:   # skipped on purpose: the newest wins
                with self._lock:
                    self.counters["observations_skipped"] += lost
            elif lost > 0:
                with self._lock:
                    self.counters["observations_lost"] += lost
                    n = self.counters["observations_lost"]
                self._throttle.warning("observations_lost", f"{lost} observation(s) before episode "
                                       f"{info.episode} step {info.step} never arrived whole "
                                       f"(observations_lost: {n} so far)")
