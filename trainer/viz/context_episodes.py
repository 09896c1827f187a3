"""Episodes for the context views (trainer/viz/visualize.py): rolled out per context with a policy
(`collect_context_episodes`) or read back from logs (`load_log_episodes`), in the batch layout
the agent wants (Dreamer's step convention)."""
from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from sim_bridge.contract.contexts import context_label, get_task, task_actuators
from sim_bridge.sim.rollout import RandomPolicy, rollout
from sim_bridge.sim.vector import VectorEnv
from trainer.console import progress as progress_bar

SPLIT_CLASS = {"train": 0, "test": 1}   # class ids of the points (the prototypes are 2)
DEFAULT_STEPS_PER_CONTEXT = 30
DEFAULT_SKIP_STEPS = 5


# ============================================================================== episodes
@dataclass
class Episode:
    """One episode as the agent's batches want it (Dreamer step convention).

    image (T,H,W,3) uint8; action (T,A) float32 = the action that LED TO obs t (zeros at t=0);
    reward (T,) float32 (arriving with obs t); discount (T,); is_first (T,) bool;
    context: the true context dict; split 'train' | 'test'.
    """

    image: np.ndarray
    action: np.ndarray
    context: dict[str, float]
    split: str
    reward: np.ndarray | None = None
    discount: np.ndarray | None = None
    is_first: np.ndarray | None = None
    source: str = ""

    def __post_init__(self) -> None:
        self.image = np.asarray(self.image)
        if self.image.dtype != np.uint8 or self.image.ndim != 4 or self.image.shape[-1] != 3:
            raise ValueError(f"episode image must be (T,H,W,3) uint8, got {self.image.dtype} "
                             f"{self.image.shape}")
        T = len(self.image)
        if T < 1:
            raise ValueError("episode has no steps")
        self.action = np.asarray(self.action, np.float32).reshape(T, -1)
        self.reward = (np.zeros(T, np.float32) if self.reward is None
                       else np.asarray(self.reward, np.float32).reshape(T))
        self.discount = (np.ones(T, np.float32) if self.discount is None
                         else np.asarray(self.discount, np.float32).reshape(T))
        if self.is_first is None:
            self.is_first = np.zeros(T, bool)
            self.is_first[0] = True
        self.is_first = np.asarray(self.is_first, bool).reshape(T)
        if self.split not in SPLIT_CLASS:
            raise ValueError(f"episode split must be 'train' or 'test', got {self.split!r}")
        # 6 significant digits: undoes float32 round trips through messages (0.2000000029 -> 0.2)
        self.context = {str(k): float(f"{float(v):.6g}") for k, v in dict(self.context).items()}

    def __len__(self) -> int:
        return len(self.image)

    @property
    def label(self) -> str:
        return context_label(self.context, self.split)

    @classmethod
    def from_any(cls, ep: Any) -> "Episode":
        """From an Episode, a mapping with keys image, action, context, split (+ optional reward,
        discount, is_first), or an object with those attributes."""
        if isinstance(ep, Episode):
            return ep
        get = ep.get if isinstance(ep, Mapping) else (lambda k, d=None: getattr(ep, k, d))
        missing = [k for k in ("image", "action") if get(k) is None]
        if missing:
            raise ValueError(f"episode lacks {missing} (needs image, action, context, split)")
        context, split = get("context"), get("split")
        if context is None or split is None:
            raise ValueError("episode lacks its true context / split (needed to colour points)")
        return cls(image=get("image"), action=get("action"), context=dict(context),
                   split=str(split), reward=get("reward"), discount=get("discount"),
                   is_first=get("is_first"), source=str(get("source", "") or ""))

    def batch(self, start: int = 0, stop: int | None = None) -> dict[str, np.ndarray]:
        sl = slice(start, stop)
        is_first = self.is_first[sl].copy()
        is_first[0] = True
        action = self.action[sl].copy()
        action[is_first] = 0.0
        return {"image": self.image[sl], "action": action, "reward": self.reward[sl],
                "discount": self.discount[sl], "is_first": is_first}


def stack_batches(batches: Sequence[Mapping[str, np.ndarray]]) -> dict[str, np.ndarray]:
    return {k: np.stack([b[k] for b in batches]) for k in batches[0]}


def collect_context_episodes(task: str, agent: Any = None, *, steps: int = DEFAULT_STEPS_PER_CONTEXT,
                             splits: Sequence[str] = ("train", "test"), seed: int = 0,
                             render_quality: str = "fast", action_repeat: int | None = None,
                             random_policy: bool = False, progress: bool | None = None,
                             contexts: Mapping[str, Sequence[Mapping[str, float]]] | None = None
                             ) -> list[Episode]:
    """One short episode (``steps`` observations) per context of each split, in-process.

    Contexts: ``TaskSpec.contexts(split)`` for every split (for (m, d) grids 25 + 64), unless
    ``contexts`` maps split -> list of contexts. Actions from ``agent`` (a
    protocad_ros.policy.Policy in deterministic mode) or uniform random when no agent is given
    or ``random_policy``.
    """
    if steps < 2:
        raise ValueError(f"steps per context must be >= 2, got {steps}")
    spec = get_task(task)
    if action_repeat is None:
        cfg = getattr(agent, "cfg", None)
        action_repeat = int(getattr(getattr(cfg, "train", None), "action_repeat", 2) or 2)
    if agent is not None and not random_policy:
        from protocad_ros.policy import Policy

        policy = Policy(agent, mode="deterministic", seed=seed)
    else:
        policy = RandomPolicy(len(task_actuators(task)), seed)
    todo = [(split, [dict(c) for c in (contexts[split] if contexts and split in contexts
                                       else spec.contexts(split))]) for split in splits]
    episodes: list[Episode] = []
    bar = progress_bar(sum(len(c) for _, c in todo), desc=f"collect {task}",
                       disable=None if progress is None else not progress, unit="ctx")
    try:
        for split, split_contexts in todo:
            if not split_contexts:
                continue
            # One env per split, its contexts one after the other: the seed fixes every frame.
            with VectorEnv(task, 1, split, in_process=True, env_seeds=[seed], action_repeat=action_repeat,
                           render_quality=render_quality) as pool:
                for context in split_contexts:
                    t = rollout(pool, policy, [context], max_steps=steps, record=True)[0]
                    episodes.append(Episode(**t.arrays(), context=t.context, split=split, source="collected"))
                    bar.update(1)
    finally:
        bar.close()
    return episodes


def missing_contexts(task: str, episodes: Sequence[Episode], splits: Sequence[str] = ("train", "test"),
                     max_contexts: int = 0) -> dict[str, list[dict[str, float]]]:
    """split -> the task's contexts that no episode in ``episodes`` has; with max_contexts, only
    those of the split's fixed stratified subset of that many (TaskSpec.stratified, the one
    the evaluations use), so a view of a run covers a few contexts of each split, not 25 + 64."""
    def key(split: str, ctx: Mapping[str, float]) -> tuple:
        return (split, tuple(sorted((k, float(f"{float(v):.6g}")) for k, v in ctx.items())))

    have = {key(ep.split, ep.context) for ep in episodes}
    spec = get_task(task)
    return {s: [c for c in spec.stratified(s, max_contexts) if key(s, c) not in have] for s in splits}


def load_log_episodes(logs: Sequence[str | Path], *, max_steps: int | None = 100,
                      min_length: int = 2, progress: bool | None = None) -> list[Episode]:
    """Episodes of MCAP logs (bag directories, .mcap files, folders of bags) read with
    trainer.data.dataset.MCAPDataset; the first ``max_steps`` steps of each (None: all).
    Episodes without a recorded true context are skipped (their points could not be coloured);
    ValueError when none is left."""
    from trainer.data.dataset import MCAPDataset

    ds = MCAPDataset([str(p) for p in logs], seq_len=1)
    out, no_context = [], 0
    for info in ds.episodes():
        if not info.get("context") or info.get("split") not in SPLIT_CLASS:
            no_context += 1
            continue
        length = int(info["length"]) if max_steps is None else min(int(info["length"]), max_steps)
        if length < min_length:
            continue
        rows = ds.episode_steps(info["store"], info["start"], length)
        out.append(Episode(image=rows["image"], action=rows["action"], reward=rows["reward"],
                           discount=rows["discount"], is_first=rows["is_first"],
                           context=info["context"], split=info["split"],
                           source=str(info.get("source", ""))))
    if not out:
        why = (f"; {no_context} episode(s) have no true context topic" if no_context else "")
        raise ValueError(f"no usable episodes in {', '.join(map(str, logs))}{why}\n"
                         f"{ds.report.summary()}")
    if no_context:
        print(f"[visualize] skipped {no_context} episode(s) without a recorded context",
              file=sys.stderr)
    return out


# ============================================================================== agent calls
def pick_episodes(episodes: Sequence[Episode], n: int, min_length: int = 1) -> list[int]:
    """Up to n episode indices, alternating train and test, spread over each split's contexts."""
    by_split = {s: [i for i, ep in enumerate(episodes) if ep.split == s and len(ep) >= min_length]
                for s in ("train", "test")}
    picks: list[int] = []
    spread = {s: [idx[j] for j in np.linspace(0, len(idx) - 1, min(len(idx), n)).round().astype(int)]
              for s, idx in by_split.items() if idx}
    while len(picks) < n and any(spread.values()):
        for s in ("train", "test"):
            if spread.get(s) and len(picks) < n:
                i = spread[s].pop(0)
                if i not in picks:
                    picks.append(i)
    return picks


