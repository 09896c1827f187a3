"""What protocad-probe measures on a checkpoint's own episodes: the window means of its context
features and RSSM state beside a pixel floor (for the probes of trainer/research/probe_fit.py),
and its open-loop prediction errors.

Episodes: the policy acts as evaluation does (actor mode on a sampled posterior, seeded), one
wave of envs per split. Features: the posterior filtered over each recorded episode with its
mean, no augmentation (Agent.embed_sequences, what protocad-visualize shows): u, w, e (ProtoCAD
variants), h = the RSSM's deterministic state, and `pixels` = a fixed seeded Gaussian random
projection of the frames, the floor a learned feature has to clear. Each episode's first
`skip` steps are dropped (the filter has not yet seen the dynamics), the rest is cut into
windows of `window` steps and each window averaged.

Open loop (the paper's 5 context frames + 50 predicted ones): each episode is cut into
segments of context_steps + horizon steps; the posterior filters the first context_steps
frames of a segment from the initial state (as DreamerV2's openl does on a replayed chunk), then
the prior imagines the rest with the actions the policy took. Errors per horizon k = 1..H:
image MSE per pixel on the 0..1 scale, and |predicted - true reward|.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np

from sim_bridge.sim.rollout import Trajectory, rollout
from sim_bridge.sim.vector import VectorEnv
from trainer import console
from trainer.learn.context_health import health_of_states
from trainer.research.probe_fit import Windows

PIXELS = 64 * 64 * 3
CONTEXT_FEATURES = ("u", "w", "e")


@dataclass(frozen=True)
class Plan:
    """How many episodes of which length, and how they are cut."""

    episodes: int = 1
    steps: int = 300
    skip: int = 25
    window: int = 25
    context_steps: int = 5
    horizon: int = 50
    batch: int = 8
    pixel_dim: int = 32
    seed: int = 0

    def check(self) -> None:
        if self.episodes < 1 or self.window < 1 or self.skip < 0 or self.horizon < 1 or self.pixel_dim < 1:
            raise ValueError("--episodes, --window, --horizon and --pixel-dim must be >= 1, --skip >= 0")
        if self.steps < self.skip + self.window:
            raise ValueError(f"--steps {self.steps} leaves no window: it must be >= --skip + --window "
                             f"= {self.skip + self.window}")
        if self.steps < self.context_steps + self.horizon:
            raise ValueError(f"--steps {self.steps} leaves no open-loop segment: it must be >= "
                             f"{self.context_steps} context frames + --horizon {self.horizon}")


@dataclass
class OpenLoopSums:
    """Per-horizon error sums of one split over its segments."""

    image_se: np.ndarray | None
    reward_ae: np.ndarray
    segments: int = 0

    def mean(self) -> dict[str, Any]:
        n = max(self.segments, 1)
        return {"horizons": list(range(1, len(self.reward_ae) + 1)),
                "image_mse": None if self.image_se is None else [float(v) for v in self.image_se / n],
                "reward_abs_err": [float(v) for v in self.reward_ae / n], "n_segments": int(self.segments)}


@dataclass
class AssignmentSums:
    """How sharply the steps pick a prototype: sums of max_k w_k and of the entropy of w."""

    top: float = 0.0
    entropy: float = 0.0
    steps: int = 0
    prototypes: int = 0

    def add(self, w: np.ndarray) -> None:
        self.top += float(w.max(-1).sum())
        self.entropy += float(-(w * np.log(np.clip(w, 1e-12, None))).sum())
        self.steps += len(w)
        self.prototypes = w.shape[-1]

    def mean(self) -> dict[str, Any] | None:
        if not self.steps:
            return None
        return {"top_mean": self.top / self.steps, "entropy_mean": self.entropy / self.steps,
                "uniform_entropy": float(np.log(self.prototypes)), "prototypes": self.prototypes,
                "steps": self.steps}


@dataclass
class Collected:
    """Window features of both splits, the contexts they index, and open-loop errors."""

    contexts: list[tuple[str, dict[str, float]]] = field(default_factory=list)
    rows: dict[str, list[np.ndarray]] = field(default_factory=dict)
    context_ids: list[np.ndarray] = field(default_factory=list)
    open_loop: dict[str, OpenLoopSums] = field(default_factory=dict)
    assignment: AssignmentSums = field(default_factory=AssignmentSums)
    health: list[dict[str, float]] = field(default_factory=list)   # per wave of unseen contexts
    episodes: int = 0

    def windows(self, params: Sequence[str]) -> Windows:
        ctx = np.concatenate(self.context_ids)
        split = np.array([self.contexts[i][0] for i in ctx])
        value = {p: np.array([self.contexts[i][1][p] for i in ctx], np.float64) for p in params}
        return Windows({k: np.concatenate(v).astype(np.float64) for k, v in self.rows.items()},
                       {f"log_{p}": np.log(value[p]) for p in params}, ctx, split, value["m"])


def pixel_projection(dim: int, seed: int) -> np.ndarray:
    """(64*64*3, dim): a seeded Gaussian projection with unit-variance outputs for unit-variance
    pixels, the same for every checkpoint probed with the same seed."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x9E3779B9]))
    return (rng.standard_normal((PIXELS, dim)) / np.sqrt(PIXELS)).astype(np.float32)


def window_means(x: np.ndarray, skip: int, window: int) -> np.ndarray:
    """(T, F) -> (n, F): the means of the complete windows after the first `skip` steps."""
    n = (len(x) - skip) // window
    return x[skip:skip + n * window].reshape(n, window, -1).mean(1)


def stack_trajectories(trajectories: Sequence[Trajectory]) -> dict[str, np.ndarray]:
    """One batch (B, T, ...) of the wave's episodes, cut to the shortest."""
    arrays = [t.arrays() for t in trajectories]
    T = min(len(a["image"]) for a in arrays)
    batch = {k: np.stack([a[k][:T] for a in arrays]) for k in ("image", "action", "reward", "discount", "is_first")}
    batch["action"] = batch["action"].astype(np.float32)
    batch["reward"] = batch["reward"].astype(np.float32)
    batch["discount"] = batch["discount"].astype(np.float32)
    batch["is_first"] = batch["is_first"].astype(bool)
    return batch


def feature_windows(agent: Any, batch: Mapping[str, np.ndarray], projection: np.ndarray,
                    plan: Plan) -> tuple[list[dict[str, np.ndarray]], np.ndarray | None]:
    """Per episode of the batch: {feature: (n_windows, F)} for u, w, e (where the variant has
    them), h and pixels; and the prototype probabilities w of every step after `skip`, (N, K)
    (None without a context module)."""
    emb = agent.embed_sequences(batch)
    deter = agent.wm.rssm.deter_dim
    frames = batch["image"].reshape(*batch["image"].shape[:2], PIXELS).astype(np.float32) / 255.0 - 0.5
    per_step = {k: emb[k] for k in CONTEXT_FEATURES if emb.get(k) is not None}
    per_step["h"] = emb["s"][..., -deter:]
    per_step["pixels"] = frames @ projection
    windows = [{k: window_means(v[b], plan.skip, plan.window) for k, v in per_step.items()}
               for b in range(len(batch["image"]))]
    w = emb.get("w")
    return windows, None if w is None else w[:, plan.skip:].reshape(-1, w.shape[-1])


def segments(batch: Mapping[str, np.ndarray], length: int) -> dict[str, np.ndarray]:
    """The batch's episodes cut into consecutive segments of `length` steps, each starting as
    an episode does (is_first, no previous action): (B * n, length, ...)."""
    T = batch["image"].shape[1]
    starts = range(0, T - length + 1, length)
    out = {k: np.concatenate([v[:, s:s + length] for s in starts]) for k, v in batch.items()}
    out["is_first"] = out["is_first"].copy()
    out["is_first"][:, 0] = True
    out["action"] = out["action"].copy()
    out["action"][:, 0] = 0.0
    return out


def open_loop_errors(agent: Any, batch: Mapping[str, np.ndarray], plan: Plan) -> tuple[np.ndarray | None, np.ndarray]:
    """Squared image error per pixel (0..1 scale; None without a decoder) and absolute reward
    error, each (n_segments, horizon)."""
    seg = segments(batch, plan.context_steps + plan.horizon)
    out = agent.open_loop(seg, context_steps=plan.context_steps, horizon=plan.horizon,
                          images=agent.has_decoder)
    reward = np.abs(out["reward_prediction"] - out["reward_truth"])
    if not agent.has_decoder:
        return None, reward
    diff = (out["prediction"].astype(np.float32) - out["truth"].astype(np.float32)) / 255.0
    return (diff ** 2).mean((-3, -2, -1)), reward


def add_open_loop(sums: dict[str, OpenLoopSums], split: str, errors: tuple[np.ndarray | None, np.ndarray]) -> None:
    image, reward = errors
    acc = sums.setdefault(split, OpenLoopSums(None if image is None else np.zeros(reward.shape[1]),
                                              np.zeros(reward.shape[1])))
    if image is not None:
        acc.image_se += image.sum(0)
    acc.reward_ae += reward.sum(0)
    acc.segments += len(reward)


def collect(agent: Any, policy: Any, contexts: Mapping[str, Sequence[Mapping[str, float]]], plan: Plan,
            progress: bool | None = None) -> Collected:
    """Roll `policy` out on every context of each split (`plan.episodes` episodes each) and
    measure the windows and open-loop errors of `agent` on those episodes."""
    cfg = agent.cfg
    projection = pixel_projection(plan.pixel_dim, plan.seed)
    out = Collected()
    out.contexts = [(split, dict(c)) for split, ctxs in contexts.items() for c in ctxs]
    jobs = [(split, ci) for ci, (split, _) in enumerate(out.contexts) for _ in range(plan.episodes)]
    # rollout counts the steps after each episode's first observation
    bar = console.progress(len(jobs) * (plan.steps - 1), desc=f"probe {cfg.task}", unit="step",
                        disable=True if progress is False else None)
    try:
        for split_index, split in enumerate(contexts):
            todo = [ci for s, ci in jobs if s == split]
            if not todo:
                continue
            n = min(len(todo), plan.batch)
            # Each split's envs seeded apart, so the train and test episodes are not the same draws.
            seeds = [int(s.generate_state(1)[0]) for s in np.random.SeedSequence([plan.seed, split_index]).spawn(n)]
            with VectorEnv(cfg.task, n, split, plan.seed, in_process=True, env_seeds=seeds,
                           action_repeat=cfg.train.action_repeat, time_limit=cfg.train.time_limit,
                           render_quality=cfg.train.render_quality) as pool:
                for w0 in range(0, len(todo), n):
                    wave = todo[w0:w0 + n]
                    done = rollout(pool, policy, [out.contexts[ci][1] for ci in wave], max_steps=plan.steps,
                                   record=True, on_step=bar.update)
                    _measure(agent, stack_trajectories(done), wave, split, out, projection=projection, plan=plan)
    finally:
        bar.close()
    return out


def _measure(agent: Any, batch: Mapping[str, np.ndarray], wave: Sequence[int], split: str, out: Collected, *,
             projection: np.ndarray, plan: Plan) -> None:
    windows, w = feature_windows(agent, batch, projection, plan)
    for ci, feats in zip(wave, windows):
        for k, v in feats.items():
            out.rows.setdefault(k, []).append(v)
        out.context_ids.append(np.full(len(feats["h"]), ci))
    if w is not None:
        out.assignment.add(w)
    if agent.wm.context is not None and split == "test":
        out.health.append(health_of_states(agent, agent.embed_sequences(batch)["s"][:, plan.skip:]))
    add_open_loop(out.open_loop, split, open_loop_errors(agent, batch, plan))
    out.episodes += len(wave)
