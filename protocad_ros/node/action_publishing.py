"""`ActionPublishing`: how the policy node answers a paired observation: one filter step of the
served model (its RSSM state reset at is_first, when a pending checkpoint is also swapped in),
then the action and the inferred context features u, w, e published on action and
context_features with the observation's stamp, and the act callbacks (add_act_callback; the
live view's when enabled) told with an ActEvent. A part of the policy node
(protocad_ros/node/policy_node.py), on its executor thread.

It owns the per-episode state of the answers (`_prev_action`, episode, step, return), the
latency and model-time percentiles, the act callbacks and the live view (built at configure).
It is handed the node (its logger), the parameter dict, the node's `count(key, why, n)`, the
action and context_features publishers, and callables: `policy()` (the served Policy),
`swap_if_pending()` (a newer checkpoint serves from this episode on), `checkpoint_updates()`
(for the ActEvent) and `command(action, stamp)` (the robot's output: the action that answers).
Which observations are answered, and when, is ObservationPairing's (observation_pairing.py).
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
from sensor_msgs.msg import JointState

from protocad_ros.live_view import LiveView
from sim_bridge.contract import topics
from sim_bridge.nodekit.param_table import ConfigError
from sim_bridge.nodekit.rosnode import Percentiles


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
    """The model step and what goes out; see the module docstring."""

    def __init__(self, *, node: Any, params: dict[str, Any], count: Callable[..., None],
                 publishers: tuple[Any, Any], policy: Callable[[], Any], swap_if_pending: Callable[[], None],
                 checkpoint_updates: Callable[[], int], command: Callable[[np.ndarray, int], np.ndarray]):
        self._log, self._params, self._count = node.get_logger(), params, count
        self._pub_action, self._pub_features = publishers
        self._policy, self._swap_if_pending = policy, swap_if_pending
        self._checkpoint_updates, self._command = checkpoint_updates, command
        self.latency = Percentiles()             # completing message -> action published
        self.act_time = Percentiles()            # model time (Policy.act)
        self._act_callbacks: list[Callable[[ActEvent], None]] = []
        self.live_view: LiveView | None = None
        self._action_names: list[str] = []
        self.reset(0)

    def add_act_callback(self, fn: Callable[[ActEvent], None]) -> None:
        """Call fn(ActEvent) after each answered observation (in the executor thread: keep it
        quick, e.g. hand over to a queue)."""
        self._act_callbacks.append(fn)

    # ------------------------------------------------------------------ lifecycle
    def reset(self, action_dim: int) -> None:
        """A blank filter: no previous action, no episode (the RSSM state itself lives in the
        served policy)."""
        self._prev_action = np.zeros(action_dim, np.float32)
        self.episode, self.step = -1, -1
        self._episode_return: float | None = None

    def configure(self, action_dim: int, action_names: list[str]) -> None:
        """A blank filter for the configured model, and the live view (rerun_* parameters; a
        ConfigError for settings that do not go together)."""
        self.reset(action_dim)
        self._action_names = action_names
        p = self._params
        try:
            self.live_view = LiveView.from_params(p["rerun_mode"], p["rerun_url"], p["rerun_path"],
                                                  action_names=action_names)
        except ValueError as e:
            raise ConfigError(f"rerun: {e}") from None

    def cleanup(self) -> None:
        """The live view's recording completed; a blank filter."""
        if self.live_view is not None:
            self.live_view.close()
        self.live_view, self._action_names = None, []
        self.reset(0)

    # ------------------------------------------------------------------ the answer
    def answer(self, stamp: int, image: np.ndarray, info: topics.StepInfo, t_recv: float,
               first: bool) -> tuple[Any, Any]:
        """Answer one observation (`first`: none answered since the filter was blank); returns
        the (action, context_features) messages published."""
        self._track_episode(info, first)
        t0 = time.monotonic()
        action, feats = self._policy().act(image, self._prev_action, bool(info.is_first))
        self.act_time.add(time.monotonic() - t0)
        # The model's action, or the safe action while disabled; its command out to a robot first.
        action = self._command(np.asarray(action, np.float32).reshape(-1), stamp)
        amsg = topics.fill_action(JointState(), action, self._action_names, stamp)
        u, w, e = (np.asarray(getattr(feats, k, ()), np.float32).reshape(-1) for k in "uwe")
        fmsg = topics.fill_context_features(JointState(), u, w, e, stamp)
        self._pub_action.publish(amsg)
        self._pub_features.publish(fmsg)
        latency = time.monotonic() - t_recv
        self.latency.add(latency)
        self._prev_action = action.copy()
        self.episode, self.step = info.episode, info.step
        self._episode_return = info.episode_return   # the bridge's running return (optional)
        self._count("observations_answered")
        callbacks = self._act_callbacks + (
            [self.live_view.on_act] if self.live_view is not None and self.live_view.enabled else [])
        if callbacks:
            event = ActEvent(stamp, info, image, action, feats, latency, self._checkpoint_updates())
            for fn in callbacks:
                try:
                    fn(event)
                except Exception as exc:  # noqa: BLE001
                    self._count("act_callback_errors", f"act callback {fn!r} failed: {exc}")
        return amsg, fmsg

    def _track_episode(self, info: topics.StepInfo, first: bool) -> None:
        """Before the model step: an episode's end reported and a pending checkpoint swapped in
        at is_first, or the observations that never arrived whole counted."""
        if info.is_first:
            if not first:   # the latency while running, not only at exit
                score = (f"return {self._episode_return:.1f}, " if self._episode_return is not None else "")
                self._log.info(
                    f"episode {self.episode} answered ({self.step + 1} steps); {score}latency obs -> action "
                    f"p50 {self.latency.percentile(50) * 1e3:.2f} ms, p99 {self.latency.percentile(99) * 1e3:.2f} ms "
                    f"(model p50 {self.act_time.percentile(50) * 1e3:.2f} ms)")
            self._swap_if_pending()
            self._prev_action[:] = 0.0
            self._count("episodes")
        elif first:
            self._log.info(f"joined in the middle of episode {info.episode} (step "
                           f"{info.step}): filtering from a blank state")
        else:
            # Observations that never reached us whole (a DDS queue overwritten under load, a
            # flood): the contract numbers the steps of an episode 0, 1, 2, ... A later episode
            # shows its lost head; the lost tail of an earlier one is not knowable.
            lost = info.step - self.step - 1 if info.episode == self.episode else info.step
            if lost > 0 and self._params["latest_only"]:   # skipped on purpose: the newest wins
                self._count("observations_skipped", None, lost)
            elif lost > 0:
                self._count("observations_lost", f"{lost} observation(s) before episode "
                            f"{info.episode} step {info.step} never arrived whole", lost)
