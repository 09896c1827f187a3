"""`CheckpointServing`: how the policy node loads the model it serves and replaces it while it
runs (a mixin of protocad_ros.policy_node.PolicyNode, kept apart so the node's file reads as
the ROS side: topics, pairing, answers).

The node configures with one checkpoint (or a random agent); afterwards one background thread
(`_watch`) is the only place checkpoints are loaded: the file when it changed, polled every
`reload_poll_s`, and versions the CheckpointReceiver got over ROS. A loaded model is handed over
(`_hand_over`) and swapped in by the executor thread at the next is_first (`_swap_if_pending`),
so no step waits for a load and no episode is served by two models.

It works on the node's own state: `params`, `counters`, `_lock` (guards `_pending_policy` and
the counters), `_stop` / `_wake` (events), `receiver`, `policy`, `ckpt_counters`, `ckpt_sha`,
`agent_kind`, `action_dim`, `image_hw`, `_loaded_sig` / `_failed_sig` (file signatures), and its
logger and `_publish_diagnostics`.
"""
from __future__ import annotations

from typing import Any

from protocad_ros.atomic import file_sha256, file_signature
from sim_bridge.contexts import task_actuators


class CheckpointServing:
    """Loading, watching and swapping the served checkpoint; see the module docstring."""

    def _policy_kwargs(self) -> dict[str, Any]:
        p = self.params
        return dict(device=p["device"], mode=p["mode"], exploration_noise=p["exploration_noise"],
                    seed=p["seed"], state_mean=p["state_mean"])

    def _load(self, path: str):
        from protocad_ros.checkpoint import load_checkpoint
        from protocad_ros.policy import Policy

        agent, counters = load_checkpoint(path, device=self.params["device"])
        # `updates` = the agent's own update counter (restored with the weights); the other
        # counters are the trainer's (env steps, episodes, ...), reported as checkpoint/<key>.
        counters = {**dict(counters or {}), "updates": int(agent.counters()["updates"])}
        return Policy(agent, **self._policy_kwargs()), counters

    def _random_policy(self):
        from protocad_ros.agents import make_agent
        from protocad_ros.config import make_config
        from protocad_ros.policy import Policy

        p = self.params
        cfg = make_config(p["task"], p["preset"], p["variant"], **{"train.seed": p["seed"]})
        agent = make_agent(cfg, len(task_actuators(p["task"])), device=p["device"])
        return Policy(agent, **self._policy_kwargs())

    @property
    def checkpoint_updates(self) -> int:
        return int(self.ckpt_counters.get("updates", -1)) if self.agent_kind == "checkpoint" else -1

    def _describe_agent(self) -> str:
        if self.agent_kind == "random":
            return "a random agent"
        return f"checkpoint {self.params['checkpoint']} (updates={self.checkpoint_updates})"

    def _watch(self) -> None:
        """Background: the one place checkpoints are loaded after configure: the file when it
        changed (polled every reload_poll_s) and versions received over ROS (woken at once).
        A loaded one goes to the executor thread, which swaps it in at the next is_first."""
        path, poll = self.params["checkpoint"], self.params["reload_poll_s"]
        while not self._stop.is_set():
            self._wake.wait(poll if poll > 0 else None)
            self._wake.clear()
            if self._stop.is_set():
                return
            receiver = self.receiver   # None once cleanup began
            if receiver is not None:
                got = receiver.install_received(path, self._load_checked)
                if got is not None:
                    self._hand_over(*got)
            if poll > 0:
                self._check_file(path)

    def _load_checked(self, path: str):
        policy, counters = self._load(path)
        cfg = policy.agent.cfg
        if int(policy.agent.action_dim) != self.action_dim or (
                (int(cfg.train.image_size),) * 2 != self.image_hw):
            raise ValueError(
                f"{policy.agent.action_dim}-d actions / {cfg.train.image_size}px images, "
                f"but this node serves {self.action_dim}-d / {self.image_hw[0]}px")
        return policy, counters

    def _check_file(self, path: str) -> None:
        sig = file_signature(path)
        if sig is None or sig == self._loaded_sig or sig == self._failed_sig:
            return
        with self._lock:
            if self._pending_policy is not None and self._pending_policy[2] == sig:
                return
        try:
            sha = file_sha256(path)
            policy, counters = self._load_checked(path)
            if file_signature(path) != sig:
                return   # replaced while we read it: take the newer one next poll
        except Exception as e:  # noqa: BLE001 (corrupt, foreign, incompatible)
            self._failed_sig = sig
            with self._lock:
                self.counters["checkpoint_load_errors"] += 1
            self.get_logger().error(f"cannot load checkpoint {path}: {e}; still serving "
                                    f"{self._describe_agent()}")
            return
        self._hand_over(policy, counters, sig, sha, path)

    def _hand_over(self, policy, counters: dict, sig: tuple | None, sha: str, what: str) -> None:
        with self._lock:
            self._pending_policy = (policy, counters, sig, sha)
        self.get_logger().info(f"loaded checkpoint {what} (updates={counters.get('updates', '?')}); "
                               "serving it from the next episode")
        # At once, not at the next period: launchers wait for pending_checkpoint_updates.
        self._publish_diagnostics()

    # ------------------------------------------------------------------ checkpoints over ROS
    def _next_sha(self) -> str | None:
        """The version that serves from the next episode on (the receiver skips it)."""
        with self._lock:
            pending = self._pending_policy
        return pending[3] if pending is not None else self.ckpt_sha

    def _swap_if_pending(self) -> None:
        with self._lock:
            pending, self._pending_policy = self._pending_policy, None
        if pending is None:
            return
        self.policy, self.ckpt_counters, self._loaded_sig, self.ckpt_sha = pending
        self.agent_kind = "checkpoint"
        self.policy.reset()
        with self._lock:
            self.counters["checkpoint_reloads"] += 1
        self.get_logger().info(f"now serving {self._describe_agent()}")
