"""Policies acting in a `VectorEnv`, the two ways the project runs them: `rollout` (given
contexts, one episode per env, until every episode has ended: evaluation, online's periodic and
final evaluations, the context views) and `continuing_rollout` (every env on and on, a new
episode whenever one ends: online collection, which writes bags and trains between steps).
Both give a policy the same inputs (images, the previous actions, zero at is_first, is_first).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Iterator, Mapping, Sequence

import numpy as np


@dataclass
class Trajectory:
    """One env's episode: its context, return (rewards after the first observation), the
    number of observations, and with record=True the per-observation arrays. `action[t]` is
    the action that led to observation t (zeros at t = 0), as in the logs."""
    context: dict[str, float]
    ret: float = 0.0
    steps: int = 0
    frames: dict[str, list] = field(default_factory=dict)

    def arrays(self) -> dict[str, np.ndarray]:
        """The recorded frames as arrays: image (T, H, W, 3), action (T, A), reward, discount,
        is_first (T,)."""
        return {k: np.stack(v) if k in ("image", "action") else np.asarray(v) for k, v in self.frames.items()}


class RandomPolicy:
    """Uniform actions in [-1, 1]^A (the paper's prefill / a baseline), seeded."""

    def __init__(self, action_dim: int, seed: int = 0):
        self.action_dim = int(action_dim)
        self.rng = np.random.default_rng(seed)
        self._b = 1

    def reset(self, batch_size: int = 1) -> None:
        self._b = int(batch_size)

    def act(self, image, prev_action, is_first):
        b = np.asarray(image).shape[0] if np.asarray(image).ndim == 4 else None
        a = self.rng.uniform(-1.0, 1.0, size=(b, self.action_dim) if b else (self.action_dim,))
        return a.astype(np.float32), None


RECORDED = ("image", "action", "reward", "discount", "is_first")


def rollout(pool: Any, policy: Any, contexts: Sequence[Mapping[str, float]], *,
            max_steps: int | None = None, record: bool = False,
            on_step: Callable[[int], None] | None = None) -> list[Trajectory]:
    """One episode per context on the first len(contexts) envs of `pool` (a
    sim_bridge.sim.vector.VectorEnv), stepped together: `policy.act(images (n, H, W, 3), previous
    actions (n, A), is_first (n,))` -> (actions (n, A), features) for every env at once (a
    protocad_ros.policy.Policy, or RandomPolicy); an env stops at is_last or after
    `max_steps` observations. `on_step(k)` is told how many envs each step moved."""
    obs = pool.reset(contexts)
    n, A = len(obs), pool.action_dim
    policy.reset(n)
    trajectories = [Trajectory(dict(o.context), frames={k: [] for k in RECORDED} if record else {})
                    for o in obs]
    done = np.zeros(n, bool)
    prev = np.zeros((n, A), np.float32)

    def take(i: int, o: Any, action: np.ndarray) -> None:
        t = trajectories[i]
        t.steps += 1
        t.context = dict(o.context)
        if not o.is_first:
            t.ret += float(o.reward)
        if record:
            for key, value in zip(RECORDED, (o.image, action, o.reward, o.discount, o.is_first)):
                t.frames[key].append(value)
        done[i] = o.is_last or (max_steps is not None and t.steps >= max_steps)

    for i, o in enumerate(obs):
        take(i, o, prev[i])
    images = np.stack([o.image for o in obs])
    first = np.array([o.is_first for o in obs])
    while not done.all():
        action, _ = policy.act(images, prev, first)
        action = np.asarray(action, np.float32).reshape(n, A)
        live = np.flatnonzero(~done)
        for i, o in zip(live, pool.step(action[live], live)):
            images[i] = o.image
            take(i, o, action[i])
        prev, first = action, np.zeros(n, bool)
        if on_step is not None:
            on_step(len(live))
    return trajectories


def continuing_rollout(pool: Any, choose: Callable[[], Any]) -> Iterator[tuple[list, np.ndarray, Any]]:
    """Every env of `pool` stepped on and on (auto-reset at episode ends). Each item: the
    observations, the actions for them and the features of `choose()`, the policy asked before
    every step (a random one during the prefill, then the agent); the pool steps with those
    actions when the next item is asked for, so a consumer that stops leaves no step half done."""
    obs = pool.reset()
    n, A = len(obs), pool.action_dim
    prev = np.zeros((n, A), np.float32)
    while True:
        images = np.stack([o.image for o in obs])
        first = np.array([o.is_first for o in obs])
        prev[first] = 0.0
        actions, features = choose().act(images, prev, first)
        yield obs, actions, features
        prev = np.asarray(actions, np.float32)
        obs = pool.step(np.asarray(actions, np.float64))
