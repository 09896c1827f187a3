"""Rerun views of what the context module learned (``protocad-visualize``, ``ros2 run trainer
visualize``), and the library functions the trainer uses for the same views.

From a checkpoint and episodes (MCAP logs, or short episodes collected in-process for EVERY
context of both splits), it computes the context features with ``Agent.embed_sequences``,
projects them to 2D and 3D (PCA by default, t-SNE as an option), and writes one .rrd
recording with a blueprint (layout) inside:

* features per step: the learned feature ``u_e`` = concat(u, e) (the paper's t-SNE figure),
  ``u``, ``e`` and the RSSM state ``s`` (the paper's comparison), coloured by the true context
  value (one entity per context parameter) and by split (class ids + legend);
* the K prototypes in the same fitted projection (a prototype c_k sits at (c_k, c_k) in the
  u_e space, at c_k in the u and e spaces); per-context mean points, labelled;
* prototype assignment probabilities w over time for every episode, and the mean assignment
  per context (which prototypes fire for which dynamics);
* observations beside reconstructions, and open-loop predictions (a few context frames then
  ``horizon`` imagined frames) against the truth, with the per-frame error.

Entity paths (``<space>`` = ``<feature>/<method><dim>d``, e.g. ``u_e/pca3d``; ``<method>`` is
``pca`` or ``tsne``; ``<param>`` a context parameter of the task, e.g. ``m`` or ``d``):

================================== =========================================================
/embeddings                        AnnotationContext: class 0 train, 1 test, 2 prototype
/embeddings/legend                 TextDocument: features, colour scales, counts
/embeddings/<space>/by_split       Points: one per step (after ``skip_steps``), class = split,
                                   label = context
/embeddings/<space>/by_<param>     Points: same positions, coloured by the true value of
                                   <param> (viridis over both splits' range)
/embeddings/<space>/contexts       Points: one per context (mean of all its points), class =
                                   split, label = "train m=0.75 d=1" -- every context of both
                                   splits (collected in-process where no log has it)
/embeddings/<space>/prototypes     Points: the K prototypes (u_e, u, e spaces only), labels c<k>
/assignment/by_context             Tensor (episode x prototype): mean w per episode
/assignment/episodes               TextDocument: row index -> split, context, return
/episodes/<i>/assignment           Tensor (step x prototype): w over time for episode i
/episodes/<i>/top_prototype        Scalars on 'step': argmax_k w_t
/reconstruction/truth              Image on 'step': observations of a few episodes side by side
/reconstruction/model              Image on 'step': the decoder's reconstructions, same layout
/reconstruction/mse                Scalars on 'step': mean squared pixel error (0..1 scale)
/reconstruction/episodes           TextDocument: which episodes, left to right
/open_loop/truth                   Image on 'step': true frames (context + horizon)
/open_loop/prediction              Image on 'step': context frames (green border), then the
                                   open-loop prediction (red border)
/open_loop/mse                     Scalars on 'step': per-frame error of the prediction
/open_loop/montage                 Image: every 5th frame, truth row above prediction row
/open_loop/episodes                TextDocument: which episodes, left to right
/open_loop/note                    TextDocument: why there is no open-loop view (none long enough)
================================== =========================================================

Times: the embeddings, prototypes and tensors are static (or on 'update', see below); the
per-step entities are on the sequence timeline 'step'. The recording carries a blueprint with
tabs "Contexts" (u_e and RSSM state, 3D coloured by the first parameter and 2D by split, with
prototypes and context means, plus the legend), "Features u / e", "Assignments" and
"Predictions" (observations | reconstructions, open-loop truth | prediction, errors).

The agent is used only through Agent.embed_sequences, .reconstruct, .open_loop and
.prototypes (protocad_ros/agent.py); variants without a decoder skip the prediction views and
variants without context features show the RSSM state only.

With ``update`` set (``TrainingRecorder.log_context_view``) everything is logged on the
'update' timeline too, so the embeddings can be scrubbed through training.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

SPLIT_CLASS = {"train": 0, "test": 1}
PROTOTYPE_CLASS = 2
CLASS_COLORS = {0: (31, 119, 180), 1: (255, 127, 14), 2: (214, 39, 40)}
CLASS_NAMES = {0: "train", 1: "test", 2: "prototype"}
FEATURES = ("u_e", "u", "e", "rssm_state")
PROTOTYPE_FEATURES = ("u_e", "u", "e")
DEFAULT_STEPS_PER_CONTEXT = 30
DEFAULT_SKIP_STEPS = 5

# viridis, 9 anchors (matplotlib's table at 0, 1/8, ..., 1), interpolated linearly.
_VIRIDIS = np.array([(68, 1, 84), (71, 44, 122), (59, 81, 139), (44, 113, 142), (33, 144, 141),
                     (39, 173, 129), (92, 200, 99), (170, 220, 50), (253, 231, 37)], np.float64)


def colormap(values: np.ndarray, vmin: float | None = None, vmax: float | None = None) -> np.ndarray:
    """Viridis colours (N,3) uint8 for scalar ``values`` scaled to [vmin, vmax]."""
    v = np.asarray(values, np.float64)
    lo = float(np.nanmin(v)) if vmin is None else float(vmin)
    hi = float(np.nanmax(v)) if vmax is None else float(vmax)
    x = np.zeros_like(v) if hi <= lo else np.clip((v - lo) / (hi - lo), 0.0, 1.0)
    x = np.nan_to_num(x) * (len(_VIRIDIS) - 1)
    i = np.minimum(np.floor(x).astype(int), len(_VIRIDIS) - 2)
    f = (x - i)[..., None]
    return np.round(_VIRIDIS[i] * (1 - f) + _VIRIDIS[i + 1] * f).astype(np.uint8)


def context_label(context: Mapping[str, float], split: str | None = None) -> str:
    """'train m=0.75 d=1': the label of a context's points."""
    body = " ".join(f"{k}={float(v):g}" for k, v in context.items())
    return f"{split} {body}" if split else body


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
    from sim_bridge.contexts import get_task
    from sim_bridge.envs import ContextDMCEnv
    from trainer.runs import progress as progress_bar

    if steps < 2:
        raise ValueError(f"steps per context must be >= 2, got {steps}")
    spec = get_task(task)
    todo = [(split, dict(c)) for split in splits
            for c in (contexts[split] if contexts and split in contexts else spec.contexts(split))]
    if action_repeat is None:
        cfg = getattr(agent, "cfg", None)
        action_repeat = int(getattr(getattr(cfg, "train", None), "action_repeat", 2) or 2)
    policy = None
    if agent is not None and not random_policy:
        from protocad_ros.policy import Policy

        policy = Policy(agent, mode="deterministic", seed=seed)
    rng = np.random.default_rng(seed)
    episodes: list[Episode] = []
    bar = progress_bar(len(todo), desc=f"collect {task}", disable=None if progress is None
                       else not progress, unit="ctx")
    envs: dict[str, Any] = {}
    try:
        for split, context in todo:
            env = envs.get(split)
            if env is None:
                env = envs[split] = ContextDMCEnv(task, split=split, seed=seed,
                                                  action_repeat=action_repeat,
                                                  render_quality=render_quality)
            obs = env.reset(context)
            if policy is not None:
                policy.reset(1)
            images, actions, rewards, discounts, firsts = [], [], [], [], []
            prev = np.zeros(env.action_dim, np.float32)
            for t in range(steps):
                images.append(obs.image)
                actions.append(prev)
                rewards.append(obs.reward)
                discounts.append(obs.discount)
                firsts.append(obs.is_first)
                if t == steps - 1 or obs.is_last:
                    break
                if policy is not None:
                    act, _ = policy.act(obs.image, prev, obs.is_first)
                else:
                    act = rng.uniform(-1.0, 1.0, env.action_dim)
                prev = np.asarray(act, np.float32).reshape(env.action_dim)
                obs = env.step(prev)
            episodes.append(Episode(image=np.stack(images), action=np.stack(actions),
                                    reward=np.asarray(rewards), discount=np.asarray(discounts),
                                    is_first=np.asarray(firsts), context=obs.context,
                                    split=split, source="collected"))
            bar.update(1)
    finally:
        bar.close()
        for env in envs.values():
            env.close()
    return episodes


def missing_contexts(task: str, episodes: Sequence[Episode],
                     splits: Sequence[str] = ("train", "test")) -> dict[str, list[dict[str, float]]]:
    """split -> the task's contexts that no episode in ``episodes`` has."""
    from sim_bridge.contexts import get_task

    def key(split: str, ctx: Mapping[str, float]) -> tuple:
        return (split, tuple(sorted((k, float(f"{float(v):.6g}")) for k, v in ctx.items())))

    have = {key(ep.split, ep.context) for ep in episodes}
    spec = get_task(task)
    return {s: [c for c in spec.contexts(s) if key(s, c) not in have] for s in splits}


def load_log_episodes(logs: Sequence[str | Path], *, max_steps: int | None = 100,
                      min_length: int = 2, progress: bool | None = None) -> list[Episode]:
    """Episodes of MCAP logs (bag directories, .mcap files, folders of bags) read with
    trainer.dataset.MCAPDataset; the first ``max_steps`` steps of each (None: all).
    Episodes without a recorded true context are skipped (their points could not be coloured);
    ValueError when none is left."""
    from trainer.dataset import MCAPDataset

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
def _np(x: Any) -> np.ndarray | None:
    if x is None:
        return None
    if hasattr(x, "detach"):
        x = x.detach().float().cpu().numpy() if x.dtype.is_floating_point else x.detach().cpu().numpy()
    return np.asarray(x)


def _no_grad():
    try:
        import torch

        return torch.no_grad()
    except ImportError:  # pragma: no cover
        import contextlib

        return contextlib.nullcontext()


def _groups_by_length(episodes: Sequence[Episode]) -> dict[int, list[int]]:
    groups: dict[int, list[int]] = {}
    for i, ep in enumerate(episodes):
        groups.setdefault(len(ep), []).append(i)
    return groups


def embed_episodes(agent: Any, episodes: Sequence[Episode], batch_size: int = 16
                   ) -> list[dict[str, np.ndarray | None]]:
    """``agent.embed_sequences`` per episode: dicts s (T,S), u (T,D), w (T,K), e (T,D)
    (u/w/e None for variants without context features). Episodes of equal length are batched."""
    out: list[dict | None] = [None] * len(episodes)
    with _no_grad():
        for _, idx in sorted(_groups_by_length(episodes).items()):
            for j in range(0, len(idx), batch_size):
                part = idx[j:j + batch_size]
                res = agent.embed_sequences(stack_batches([episodes[i].batch() for i in part]))
                arrays = {k: _np(res.get(k)) for k in ("s", "u", "w", "e")}
                for b, i in enumerate(part):
                    out[i] = {k: (None if v is None or v.size == 0 else v[b].astype(np.float32))
                              for k, v in arrays.items()}
    return out  # type: ignore[return-value]


def agent_prototypes(agent: Any) -> np.ndarray | None:
    protos = agent.prototypes() if hasattr(agent, "prototypes") else None
    protos = _np(protos)
    return None if protos is None or protos.size == 0 else protos.astype(np.float32)


# ============================================================================== projection
def project(X: np.ndarray, dim: int, method: str = "pca", extra: np.ndarray | None = None,
            seed: int = 0) -> tuple[np.ndarray, np.ndarray | None]:
    """Fit a ``dim``-D projection on X (N,F); returns (Y (N,dim), Y_extra (M,dim) or None).

    PCA: fitted on X, ``extra`` (e.g. prototypes) transformed by the same fit.
    t-SNE has no out-of-sample transform: it is fitted on X and extra together.
    Coordinates are centred and scaled so that the points (not the extra ones) span [-1, 1];
    prototypes far from every point land outside that frame.
    """
    X = np.asarray(X, np.float64)
    n = len(X)
    if n < 2 and method == "pca":  # nothing to fit: everything at the origin
        Ye = None if extra is None else np.zeros((len(extra), dim), np.float32)
        return np.zeros((n, dim), np.float32), Ye
    if method == "pca":
        from sklearn.decomposition import PCA

        k = max(1, min(dim, n, X.shape[1]))
        pca = PCA(n_components=k, random_state=seed).fit(X)
        Y = pca.transform(X)
        Ye = pca.transform(np.asarray(extra, np.float64)) if extra is not None else None
    elif method == "tsne":
        from sklearn.manifold import TSNE

        data = X if extra is None else np.concatenate([X, np.asarray(extra, np.float64)])
        if len(data) < 4:
            raise ValueError(f"t-SNE needs at least 4 points, got {len(data)}")
        perplexity = float(min(30.0, max(2.0, (len(data) - 1) / 3.0)))
        Z = TSNE(n_components=dim, perplexity=perplexity, init="pca", random_state=seed,
                 method="barnes_hut" if dim <= 3 else "exact").fit_transform(data)
        Y, Ye = Z[:n], (Z[n:] if extra is not None else None)
    else:
        raise ValueError(f"unknown projection {method!r}; valid: 'pca', 'tsne'")
    Y, Ye = _pad(Y, dim), (None if Ye is None else _pad(Ye, dim))
    center = Y.mean(0)
    scale = float(np.abs(Y - center).max()) or 1.0
    Y = (Y - center) / scale
    Ye = None if Ye is None else (Ye - center) / scale
    return Y.astype(np.float32), (None if Ye is None else Ye.astype(np.float32))


def _pad(Y: np.ndarray, dim: int) -> np.ndarray:
    if Y.shape[1] >= dim:
        return Y[:, :dim]
    return np.concatenate([Y, np.zeros((len(Y), dim - Y.shape[1]))], axis=1)


# ============================================================================== the view data
@dataclass
class ContextView:
    """Everything the context view shows, computed once (rrd and PNG use the same numbers)."""

    method: str
    params: tuple[str, ...]
    episodes: list[Episode]
    point_episode: np.ndarray                  # (N,) episode index of every point
    point_step: np.ndarray                     # (N,) step within the episode
    features: dict[str, np.ndarray]            # name -> (N, F)
    points: dict[tuple[str, int], np.ndarray]  # (feature, dim) -> (N, dim)
    context_points: dict[tuple[str, int], np.ndarray]    # (feature, dim) -> (E, dim)
    prototype_points: dict[tuple[str, int], np.ndarray]  # (feature, dim) -> (K, dim)
    assignments: list[np.ndarray | None]       # per episode (T, K) or None
    num_prototypes: int
    contexts: list[tuple[str, dict[str, float]]]  # (split, context) of each context point
    episode_context: np.ndarray                # (E,) index into contexts
    value_range: dict[str, tuple[float, float]] = field(default_factory=dict)
    skip_steps: int = 0

    @property
    def feature_names(self) -> list[str]:
        return [f for f in FEATURES if f in self.features]

    def space(self, feature: str, dim: int) -> str:
        return f"/embeddings/{feature}/{self.method}{dim}d"

    def contexts_per_split(self) -> dict[str, int]:
        return {s: sum(split == s for split, _ in self.contexts) for s in SPLIT_CLASS}

    @property
    def context_labels(self) -> list[str]:
        return [context_label(c, s) for s, c in self.contexts]


def compute_context_view(agent: Any, episodes: Iterable[Any], *, projection: str = "pca",
                         skip_steps: int = DEFAULT_SKIP_STEPS, batch_size: int = 16,
                         dims: Sequence[int] = (2, 3), seed: int = 0,
                         max_points: int = 4000, embeddings: list | None = None) -> ContextView:
    """Embed ``episodes`` with ``agent`` and project every feature space to ``dims``.

    Points are the steps of every episode from ``skip_steps`` on (the posterior needs a few
    observations to infer the context); at most ``max_points`` (evenly thinned per episode).
    """
    if projection not in ("pca", "tsne"):
        raise ValueError(f"unknown projection {projection!r}; valid: 'pca', 'tsne'")
    eps = [Episode.from_any(e) for e in episodes]
    if not eps:
        raise ValueError("no episodes to visualize")
    params: list[str] = []
    for ep in eps:
        for p in ep.context:
            if p not in params:
                params.append(p)
    emb = embeddings if embeddings is not None else embed_episodes(agent, eps, batch_size)
    # Which steps become points: skip the warm-up, thin evenly to stay under max_points.
    steps_per_ep = []
    for ep in eps:
        first = min(skip_steps, len(ep) - 1)
        steps_per_ep.append(np.arange(first, len(ep)))
    total = sum(len(s) for s in steps_per_ep)
    if total > max_points:
        keep = max(1, max_points // len(eps))
        steps_per_ep = [s[np.linspace(0, len(s) - 1, min(keep, len(s))).round().astype(int)]
                        for s in steps_per_ep]
    point_episode = np.concatenate([np.full(len(s), i) for i, s in enumerate(steps_per_ep)])
    point_step = np.concatenate(steps_per_ep)
    # Contexts in order of first appearance; several episodes of one context share its mean.
    contexts: list[tuple[str, dict[str, float]]] = []
    episode_context = np.zeros(len(eps), int)
    index: dict[tuple, int] = {}
    for i, ep in enumerate(eps):
        key = (ep.split, tuple(sorted(ep.context.items())))
        if key not in index:
            index[key] = len(contexts)
            contexts.append((ep.split, dict(ep.context)))
        episode_context[i] = index[key]
    point_context = episode_context[point_episode]

    def gather(key: str) -> np.ndarray | None:
        if any(e[key] is None for e in emb):
            return None
        return np.concatenate([emb[i][key][s] for i, s in enumerate(steps_per_ep)])

    s, u, e = gather("s"), gather("u"), gather("e")
    features: dict[str, np.ndarray] = {}
    if u is not None and e is not None:
        features["u_e"] = np.concatenate([u, e], axis=1)
    if u is not None:
        features["u"] = u
    if e is not None:
        features["e"] = e
    if s is None:
        raise ValueError("agent.embed_sequences returned no RSSM state 's'")
    features["rssm_state"] = s

    protos = agent_prototypes(agent)
    proto_in = {}
    if protos is not None:
        proto_in = {"u": protos, "e": protos, "u_e": np.concatenate([protos, protos], axis=1)}
    points, ctx_points, proto_points = {}, {}, {}
    for name, X in features.items():
        extra = proto_in.get(name)
        if extra is not None and extra.shape[1] != X.shape[1]:
            extra = None  # e.g. prototypes of another dim than u: not in this space
        for dim in dims:
            Y, Ye = project(X, dim, projection, extra=extra, seed=seed)
            points[(name, dim)] = Y
            if Ye is not None:
                proto_points[(name, dim)] = Ye
            ctx_points[(name, dim)] = np.stack([Y[point_context == c].mean(0)
                                                for c in range(len(contexts))])
    value_range = {}
    for p in params:
        vals = [ep.context[p] for ep in eps if p in ep.context]
        value_range[p] = (min(vals), max(vals))
    assignments = [None if x["w"] is None else x["w"] for x in emb]
    return ContextView(projection, tuple(params), eps, point_episode, point_step, features,
                       points, ctx_points, proto_points, assignments,
                       0 if protos is None else len(protos), contexts, episode_context,
                       value_range, skip_steps)


# ============================================================================== logging
def annotation_context():
    import rerun as rr

    return rr.AnnotationContext([rr.AnnotationInfo(id=i, label=CLASS_NAMES[i], color=CLASS_COLORS[i])
                                 for i in sorted(CLASS_NAMES)])


def log_context_view(rec: Any, view: ContextView, *, update: int | None = None) -> None:
    """Log the embeddings, prototypes and assignments of ``view`` to the RecordingStream ``rec``.

    update=None: static data (one snapshot); an int: on the 'update' timeline.
    """
    import rerun as rr

    static = update is None
    if update is not None:
        rec.set_time("update", sequence=int(update))
    rec.log("/embeddings", annotation_context(), static=True)
    eps = view.episodes
    split_ids = np.array([SPLIT_CLASS[ep.split] for ep in eps])
    ctx_split_ids = np.array([SPLIT_CLASS[s] for s, _ in view.contexts])
    labels = [ep.label for ep in eps]
    # Points in a fixed shuffled order: no split or context is drawn over all the others.
    order = np.random.default_rng(0).permutation(len(view.point_episode))
    p_ep = view.point_episode[order]
    point_labels = [f"{labels[i]} t={t}" for i, t in zip(p_ep, view.point_step[order])]
    for (name, dim), Y in view.points.items():
        Y = Y[order]
        space = view.space(name, dim)
        Points = rr.Points3D if dim == 3 else rr.Points2D
        rec.log(f"{space}/by_split", Points(Y, class_ids=split_ids[p_ep], labels=point_labels,
                                           show_labels=False, radii=-2.0), static=static)
        for p in view.params:
            vals = np.array([eps[i].context.get(p, np.nan) for i in p_ep])
            lo, hi = view.value_range[p]
            rec.log(f"{space}/by_{p}", Points(Y, colors=colormap(vals, lo, hi),
                                              class_ids=split_ids[p_ep], labels=point_labels,
                                              show_labels=False, radii=-2.0), static=static)
        rec.log(f"{space}/contexts", Points(view.context_points[(name, dim)],
                                            class_ids=ctx_split_ids, labels=view.context_labels,
                                            show_labels=False, radii=-5.0), static=static)
        Yp = view.prototype_points.get((name, dim))
        if Yp is not None:
            rec.log(f"{space}/prototypes",
                    Points(Yp, class_ids=np.full(len(Yp), PROTOTYPE_CLASS),
                           labels=[f"c{k}" for k in range(len(Yp))], show_labels=False,
                           radii=-4.0), static=static)
    rec.log("/embeddings/legend", rr.TextDocument(legend_markdown(view), media_type="text/markdown"),
            static=static)
    # Assignments: mean w per episode (rows sorted as the episode table) and w over time.
    rows = []
    if any(w is not None for w in view.assignments):
        mean_w = np.stack([w.mean(0) if w is not None else np.zeros(view.num_prototypes)
                           for w in view.assignments])
        rec.log("/assignment/by_context", rr.Tensor(mean_w, dim_names=["episode", "prototype"]),
                static=static)
        for i, (ep, w) in enumerate(zip(eps, view.assignments)):
            if w is None:
                continue
            rec.log(f"/episodes/{i}/assignment", rr.Tensor(w, dim_names=["step", "prototype"]),
                    static=static)
            top = np.argmax(w, axis=1).astype(np.float64)
            index = [rr.TimeColumn("step", sequence=np.arange(len(top)))]
            if update is not None:
                index.append(rr.TimeColumn("update", sequence=np.full(len(top), int(update))))
            rec.send_columns(f"/episodes/{i}/top_prototype", indexes=index,
                             columns=rr.Scalars.columns(scalars=top))
    for i, ep in enumerate(eps):
        rows.append(f"| {i} | {ep.split} | {context_label(ep.context)} | {len(ep)} | "
                    f"{float(ep.reward.sum()):.1f} |")
    table = ("| episode | split | context | steps | return |\n|---|---|---|---|---|\n"
             + "\n".join(rows))
    rec.log("/assignment/episodes", rr.TextDocument(table, media_type="text/markdown"),
            static=static)


def legend_markdown(view: ContextView) -> str:
    n_ctx = view.contexts_per_split()
    lines = [
        f"# Context features ({view.method.upper()})",
        "",
        "Points: one per step (from step %d on) of every episode; big points: per-context mean;"
        % view.skip_steps,
        "red `c<k>`: the K prototypes in the same projection.",
        "",
        "* **u_e**: concat(u, e), the learned context feature (paper t-SNE figure); a prototype "
        "c_k sits at (c_k, c_k)",
        "* **u**: projection of the RSSM state; **e**: prototype-weighted aggregate "
        "e = sum_k softmax(u.c_k / T) c_k",
        "* **rssm_state**: the RSSM state s = (h, z), for comparison",
        "",
        "Colours: `by_split` blue = train, orange = test; "
        + "; ".join(f"`by_{p}` viridis from {lo:g} (purple) to {hi:g} (yellow)"
                    for p, (lo, hi) in view.value_range.items()),
        "",
        f"{len(view.episodes)} episodes of {n_ctx['train']} train and {n_ctx['test']} test "
        f"contexts, {len(view.point_episode)} points, K = {view.num_prototypes} prototypes.",
    ]
    return "\n".join(lines)


def _strip(frames: Sequence[np.ndarray], pad: int = 2) -> np.ndarray:
    """Frames (H,W,3) side by side with a white gap."""
    h = max(f.shape[0] for f in frames)
    parts = []
    for i, f in enumerate(frames):
        if i:
            parts.append(np.full((h, pad, 3), 255, np.uint8))
        parts.append(f)
    return np.concatenate(parts, axis=1)


def _border(frame: np.ndarray, color: Sequence[int], width: int = 2) -> np.ndarray:
    f = frame.copy()
    f[:width], f[-width:], f[:, :width], f[:, -width:] = color, color, color, color
    return f


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


def log_reconstructions(rec: Any, agent: Any, episodes: Sequence[Episode], *, num_episodes: int = 4,
                        update: int | None = None) -> list[int]:
    """Observations beside reconstructions of a few episodes (side by side), on 'step'."""
    import rerun as rr

    picks = pick_episodes(episodes, num_episodes, min_length=2)
    if not picks or not getattr(agent, "has_decoder", True):
        return []  # e.g. DreamerPro: reconstruction-free, nothing to show
    if update is not None:
        rec.set_time("update", sequence=int(update))
    T = min(len(episodes[i]) for i in picks)
    with _no_grad():
        model = _np(agent.reconstruct(stack_batches([episodes[i].batch(0, T) for i in picks])))
    truth = np.stack([episodes[i].image[:T] for i in picks])
    model = np.asarray(model).astype(np.uint8)
    labels = " | ".join(episodes[i].label for i in picks)
    rec.log("/reconstruction/episodes", rr.TextDocument(f"left to right: {labels}"),
            static=update is None)
    for t in range(T):
        rec.set_time("step", sequence=t)
        rec.log("/reconstruction/truth", rr.Image(_strip(truth[:, t])))
        rec.log("/reconstruction/model", rr.Image(_strip(model[:, t])))
        err = ((truth[:, t].astype(np.float32) - model[:, t]) / 255.0) ** 2
        rec.log("/reconstruction/mse", rr.Scalars(float(err.mean())))
    rec.disable_timeline("step")
    return picks


def log_open_loop(rec: Any, agent: Any, episodes: Sequence[Episode], *, context_steps: int = 5,
                  horizon: int = 50, num_episodes: int = 4, update: int | None = None) -> list[int]:
    """Open-loop predictions (``context_steps`` observed frames, then ``horizon`` imagined ones)
    against the truth, for a few episodes at least context_steps + horizon long."""
    import rerun as rr

    L = context_steps + horizon
    if not getattr(agent, "has_decoder", True):
        return []
    picks = pick_episodes(episodes, num_episodes, min_length=L)
    if update is not None:
        rec.set_time("update", sequence=int(update))
    if not picks:
        rec.log("/open_loop/note", rr.TextDocument(
            f"no episode has {L} steps (context {context_steps} + horizon {horizon}); "
            "collect longer episodes for open-loop predictions"), static=update is None)
        return []
    batch = stack_batches([episodes[i].batch(0, L) for i in picks])
    with _no_grad():
        out = agent.open_loop(batch, context_steps=context_steps, horizon=horizon)
    pred = np.asarray(_np(out["prediction"])).astype(np.uint8)
    truth = batch["image"]
    if pred.shape[1] < truth.shape[1]:  # predictions only: prepend the observed context frames
        pred = np.concatenate([truth[:, :context_steps], pred], axis=1)
    L = min(L, pred.shape[1])
    truth, pred = truth[:, :L], pred[:, :L]
    labels = " | ".join(episodes[i].label for i in picks)
    rec.log("/open_loop/episodes", rr.TextDocument(
        f"left to right: {labels}; green border = observed context frame, red = open-loop "
        f"prediction ({context_steps} context + {horizon} predicted frames)"), static=update is None)
    green, red = (0, 200, 0), (220, 0, 0)
    for t in range(L):
        rec.set_time("step", sequence=t)
        color = green if t < context_steps else red
        rec.log("/open_loop/truth", rr.Image(_strip(truth[:, t])))
        rec.log("/open_loop/prediction", rr.Image(_strip([_border(f, color) for f in pred[:, t]])))
        if t >= context_steps:
            err = ((truth[:, t].astype(np.float32) - pred[:, t]) / 255.0) ** 2
            rec.log("/open_loop/mse", rr.Scalars(float(err.mean())))
    rec.disable_timeline("step")
    cols = list(range(0, L, 5))
    rows = []
    for b in range(len(picks)):
        rows.append(_strip([truth[b, t] for t in cols]))
        rows.append(_strip([_border(pred[b, t], green if t < context_steps else red) for t in cols]))
        rows.append(np.full((4, rows[-1].shape[1], 3), 255, np.uint8))
    rec.log("/open_loop/montage", rr.Image(np.concatenate(rows[:-1], axis=0)), static=update is None)
    return picks


# ============================================================================== blueprint
def context_blueprint_parts(view: ContextView | None, method: str = "pca") -> list:
    """Tabs: 'Contexts' (u_e and RSSM state 3D + 2D), 'Features u / e', 'Assignments',
    'Predictions'."""
    import rerun.blueprint as rrb

    method = view.method if view is not None else method
    params = view.params if view is not None else ()
    color = f"by_{params[0]}" if params else "by_split"

    def space_view(feature: str, dim: int, by: str, name: str):
        origin = f"/embeddings/{feature}/{method}{dim}d"
        contents = [f"{origin}/{by}", f"{origin}/prototypes", f"{origin}/contexts"]
        # Frame the points (they span [-1, 1]); unused prototypes may lie further out.
        if dim == 3:
            return rrb.Spatial3DView(origin=origin, contents=contents, name=name,
                                     eye_controls=rrb.EyeControls3D(position=[1.3, -1.6, 1.1],
                                                                    look_target=[0, 0, 0],
                                                                    eye_up=[0, 0, 1]))
        return rrb.Spatial2DView(origin=origin, contents=contents, name=name,
                                 visual_bounds=rrb.VisualBounds2D(x_range=[-1.15, 1.15],
                                                                  y_range=[-1.15, 1.15]))

    ctx = rrb.Horizontal(
        rrb.Vertical(space_view("u_e", 3, color, f"learned feature u,e (3D, {color})"),
                     space_view("u_e", 2, "by_split", "learned feature u,e (2D, by split)")),
        rrb.Vertical(space_view("rssm_state", 3, color, f"RSSM state (3D, {color})"),
                     space_view("rssm_state", 2, "by_split", "RSSM state (2D, by split)")),
        rrb.TextDocumentView(origin="/embeddings/legend", name="legend"),
        column_shares=[3, 3, 1], name="Contexts")
    feats = rrb.Grid(*[space_view(f, 3, b, f"{f} ({b})") for f in ("u", "e")
                       for b in (color, "by_split")], name="Features u / e")
    assign = rrb.Horizontal(
        rrb.TensorView(origin="/assignment/by_context", name="mean assignment w per episode"),
        rrb.Vertical(rrb.TensorView(origin="/episodes/0/assignment", name="episode 0: w over time"),
                     rrb.TimeSeriesView(origin="/episodes", name="top prototype per step")),
        rrb.TextDocumentView(origin="/assignment/episodes", name="episodes"),
        name="Assignments")
    preds = rrb.Horizontal(
        rrb.Vertical(rrb.Spatial2DView(origin="/reconstruction/truth", name="observations"),
                     rrb.Spatial2DView(origin="/reconstruction/model", name="reconstructions"),
                     rrb.TimeSeriesView(origin="/reconstruction/mse", name="reconstruction MSE")),
        rrb.Vertical(rrb.Spatial2DView(origin="/open_loop/truth", name="open loop: truth"),
                     rrb.Spatial2DView(origin="/open_loop/prediction", name="open loop: prediction"),
                     rrb.TimeSeriesView(origin="/open_loop/mse", name="open-loop MSE")),
        rrb.Spatial2DView(origin="/open_loop/montage", name="open loop montage"),
        name="Predictions")
    return [ctx, feats, assign, preds]


def context_blueprint(view: ContextView | None = None, extra_tabs: Sequence[Any] = ()):
    import rerun.blueprint as rrb

    # Side panels start collapsed so the views get the room (the collapsed time panel keeps
    # its play bar for the 'step' timeline); every panel opens again from the top bar.
    return rrb.Blueprint(rrb.Tabs(*context_blueprint_parts(view), *extra_tabs),
                         rrb.BlueprintPanel(state="collapsed"),
                         rrb.SelectionPanel(state="collapsed"),
                         rrb.TimePanel(state="collapsed"))


# ============================================================================== static PNG
def render_context_png(view: ContextView, path: str | Path, *, dim: int = 2, panel: int = 380,
                       features: Sequence[str] = ("u_e", "rssm_state")) -> Path:
    """A static scatter image of the 2D projection (no viewer needed), from the same numbers as
    the recording: rows = features (learned u,e and the RSSM state), columns = coloured by each
    context parameter, then by split; prototypes as red crosses, context means as big dots."""
    from PIL import Image, ImageDraw, ImageFont

    feats = [f for f in features if (f, dim) in view.points]
    if not feats:
        raise ValueError(f"no {dim}D projection of {list(features)} in this view")
    cols = [f"by_{p}" for p in view.params] + ["by_split"]
    title_h, margin, bar_h = 28, 14, 34
    W = margin + len(cols) * (panel + margin)
    H = title_h + len(feats) * (panel + title_h + margin) + bar_h + margin
    img = Image.new("RGB", (W, H), "white")
    draw = ImageDraw.Draw(img)
    font = ImageFont.load_default(size=15)
    small = ImageFont.load_default(size=12)
    n_ctx = view.contexts_per_split()
    draw.text((margin, 6), f"Context features, {view.method.upper()} {dim}D: {len(view.episodes)} "
              f"episodes of {n_ctx['train']} train and {n_ctx['test']} test contexts, "
              f"K={view.num_prototypes} prototypes", fill="black", font=font)
    eps, p_ep = view.episodes, view.point_episode
    order = np.random.default_rng(0).permutation(len(p_ep))
    split_col = np.array([CLASS_COLORS[SPLIT_CLASS[ep.split]] for ep in eps], np.uint8)
    ctx_split_col = np.array([CLASS_COLORS[SPLIT_CLASS[s]] for s, _ in view.contexts], np.uint8)
    names = {"u_e": "learned feature (u, e)", "rssm_state": "RSSM state s", "u": "u", "e": "e"}
    for r, feat in enumerate(feats):
        Y = view.points[(feat, dim)]
        C = view.context_points[(feat, dim)]
        P = view.prototype_points.get((feat, dim))
        # Frame the points and the prototypes together: every prototype is drawn (a frame of
        # the points alone left all of them out in an early recording, hidden behind a note).
        framed = Y if P is None else np.concatenate([Y[:, :2], P[:, :2]])
        lo, hi = framed[:, :2].min(0), framed[:, :2].max(0)
        span = np.where(hi - lo > 1e-9, hi - lo, 1.0)
        y0 = title_h + r * (panel + title_h + margin)
        for c, col in enumerate(cols):
            x0 = margin + c * (panel + margin)
            top = y0 + title_h

            def px(Z: np.ndarray) -> np.ndarray:
                q = (Z[:, :2] - lo[:2]) / span[:2]
                return np.stack([x0 + 8 + q[:, 0] * (panel - 16),
                                 top + panel - 8 - q[:, 1] * (panel - 16)], axis=1)

            draw.rectangle([x0, top, x0 + panel, top + panel], outline=(180, 180, 180))
            draw.text((x0 + 4, y0 + 6), f"{names.get(feat, feat)}, coloured {col.replace('_', ' ')}",
                      fill="black", font=font)
            if col == "by_split":
                pcol, ccol = split_col[p_ep], ctx_split_col
            else:
                prm = col[3:]
                vlo, vhi = view.value_range[prm]
                pcol = colormap(np.array([ep.context.get(prm, np.nan) for ep in eps]), vlo, vhi)[p_ep]
                ccol = colormap(np.array([c.get(prm, np.nan) for _, c in view.contexts]), vlo, vhi)
            P_xy = px(Y)
            for j in order:  # shuffled, so neither split paints over the other
                x, y = P_xy[j]
                draw.ellipse([x - 2, y - 2, x + 2, y + 2], fill=tuple(int(v) for v in pcol[j]))
            for (x, y), rgb, (split, _) in zip(px(C), ccol, view.contexts):
                r = 6
                outline = (0, 0, 0) if split == "train" else (120, 120, 120)
                draw.ellipse([x - r, y - r, x + r, y + r], fill=tuple(int(v) for v in rgb),
                             outline=outline, width=2 if split == "test" else 1)
            if P is not None:
                for x, y in px(P):
                    draw.line([x - 4, y - 4, x + 4, y + 4], fill=CLASS_COLORS[PROTOTYPE_CLASS], width=2)
                    draw.line([x - 4, y + 4, x + 4, y - 4], fill=CLASS_COLORS[PROTOTYPE_CLASS], width=2)
    # Legends under the columns: colour bars for the parameters, swatches for the split.
    ly = H - bar_h - margin + 4
    for c, col in enumerate(cols):
        x0 = margin + c * (panel + margin)
        if col == "by_split":
            x = x0
            for cls in (0, 1, 2):
                rgb = CLASS_COLORS[cls]
                if cls == 2:
                    draw.line([x, ly + 2, x + 10, ly + 12], fill=rgb, width=2)
                    draw.line([x, ly + 12, x + 10, ly + 2], fill=rgb, width=2)
                else:
                    draw.ellipse([x, ly + 2, x + 10, ly + 12], fill=rgb)
                draw.text((x + 14, ly), CLASS_NAMES[cls], fill="black", font=small)
                x += 100
            draw.text((x0, ly + 16), "big dots: per-context mean", fill="black", font=small)
        else:
            prm = col[3:]
            vlo, vhi = view.value_range[prm]
            ramp = colormap(np.linspace(0, 1, panel - 120), 0, 1)
            for i, rgb in enumerate(ramp):
                draw.line([x0 + 60 + i, ly, x0 + 60 + i, ly + 12], fill=tuple(int(v) for v in rgb))
            draw.text((x0, ly), f"{prm}={vlo:g}", fill="black", font=small)
            draw.text((x0 + panel - 56, ly), f"{vhi:g}", fill="black", font=small)
            draw.text((x0, ly + 16), "crosses: prototypes; grey ring: test context", fill="black",
                      font=small)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    img.save(path)
    return path


# ============================================================================== top level
@dataclass
class RecordingResult:
    path: Path | None
    view: ContextView
    reconstruction_episodes: list[int]
    open_loop_episodes: list[int]
    png: Path | None = None


def load_agent(source: Any, device: str = "cpu") -> Any:
    """An Agent from a checkpoint path, or ``source`` itself when it is already one."""
    if isinstance(source, (str, Path)):
        from protocad_ros.checkpoint import load_checkpoint

        agent, _ = load_checkpoint(str(source), device=device)
        if not hasattr(agent, "embed_sequences"):
            raise ValueError(f"{source}: variant {agent.cfg.variant!r} is model-free: it has no "
                             "latent state or context to show (the world-model variants do)")
        return agent
    if not hasattr(source, "embed_sequences"):
        raise TypeError(f"expected a checkpoint path or an Agent, got {type(source).__name__}")
    return source


def write_context_recording(source: Any, logs: Sequence[str | Path] | None = None,
                            out_rrd: str | Path | None = None, projection: str = "pca", *,
                            episodes: Iterable[Any] | None = None, task: str | None = None,
                            steps_per_context: int = DEFAULT_STEPS_PER_CONTEXT,
                            open_loop_episodes: Iterable[Any] | None = None,
                            context_steps: int = 5, horizon: int = 50,
                            num_prediction_episodes: int = 4, skip_steps: int = DEFAULT_SKIP_STEPS,
                            random_policy: bool = False, seed: int = 0, device: str = "cpu",
                            png: str | Path | None = None, recording: Any = None,
                            spawn: bool = False, progress: bool | None = None,
                            cover_all_contexts: bool = True,
                            log_steps: int | None = 100) -> RecordingResult:
    """Write the context view of an agent to ``out_rrd`` (with its blueprint).

    source: a checkpoint path or an Agent. Episodes from (first that applies) ``episodes``
    (Episode objects or dicts: image, action, context, split, ...), ``logs`` (MCAP bag dirs /
    files, read with trainer.dataset), or collected in-process for every context of both splits
    of ``task`` (``steps_per_context`` steps each; ``task`` defaults to the agent's). With logs
    and ``cover_all_contexts``, contexts of the task the logs lack (e.g. every test context in
    a training run's bags) are collected in-process too. ``open_loop_episodes``: longer episodes for
    the open-loop view (default: those of the main episodes that are long enough, else, when
    collecting, one context_steps + horizon episode per split's first and last context).
    ``recording``: an existing rerun.RecordingStream to log into instead of a new file;
    ``spawn``: also stream to a spawned viewer. ``png``: also write a static scatter image.
    """
    import rerun as rr

    if projection not in ("pca", "tsne"):
        raise ValueError(f"unknown projection {projection!r}; valid: 'pca', 'tsne'")
    if out_rrd is not None and Path(out_rrd).suffix != ".rrd":
        raise ValueError(f"output must be an .rrd file, got {str(out_rrd)!r}")
    if recording is None and out_rrd is None and not spawn:
        raise ValueError("nowhere to write: give out_rrd or spawn=True")
    if spawn:
        from protocad_ros.live_view import check_display

        check_display()
    agent = load_agent(source, device)
    if hasattr(agent, "eval"):
        agent.eval()
    task = task or getattr(getattr(agent, "cfg", None), "task", None)
    if episodes is not None:
        eps = [Episode.from_any(e) for e in episodes]
    elif logs:
        eps = load_log_episodes(logs, max_steps=log_steps)
        missing = missing_contexts(task, eps) if (task and cover_all_contexts) else {}
        if any(missing.values()):
            # Logs of a training run hold only training contexts: the rest is collected, so the
            # view shows every context of both splits.
            eps += collect_context_episodes(task, agent, steps=steps_per_context, seed=seed,
                                            contexts=missing, random_policy=random_policy,
                                            progress=progress)
    elif task:
        eps = collect_context_episodes(task, agent, steps=steps_per_context, seed=seed,
                                       random_policy=random_policy, progress=progress)
    else:
        raise ValueError("give episodes, logs or a task to collect episodes for")
    if not eps:
        raise ValueError("no episodes to visualize")
    view = compute_context_view(agent, eps, projection=projection, skip_steps=skip_steps, seed=seed)
    L = context_steps + horizon
    if open_loop_episodes is not None:
        ol_eps = [Episode.from_any(e) for e in open_loop_episodes]
    elif any(len(e) >= L for e in eps):
        ol_eps = eps
    elif task and horizon > 0:
        from sim_bridge.contexts import get_task

        spec = get_task(task)
        pick = {s: [spec.contexts(s)[0], spec.contexts(s)[-1]] for s in ("train", "test")}
        ol_eps = collect_context_episodes(task, agent, steps=L, seed=seed + 1, contexts=pick,
                                          random_policy=random_policy, progress=progress)
    else:
        ol_eps = []
    bp = context_blueprint(view)
    if recording is not None:
        rec = recording
        rec.send_blueprint(bp)
    else:
        rec = rr.RecordingStream("protocad_contexts")
        sinks = []
        if out_rrd is not None:
            # Written beside the target and renamed at the end: an earlier recording is never
            # replaced by a partial one.
            out_rrd = Path(out_rrd)
            out_rrd.parent.mkdir(parents=True, exist_ok=True)
            tmp_rrd = out_rrd.parent / f".{out_rrd.name}.{os.getpid()}.tmp"
            sinks.append(rr.FileSink(str(tmp_rrd)))
        if spawn:
            rr.spawn(connect=False)
            sinks.append(rr.GrpcSink())
        rec.set_sinks(*sinks, default_blueprint=bp)
    try:
        log_context_view(rec, view)
        recon = log_reconstructions(rec, agent, eps, num_episodes=num_prediction_episodes)
        ol = log_open_loop(rec, agent, ol_eps, context_steps=context_steps, horizon=horizon,
                           num_episodes=num_prediction_episodes) if horizon > 0 else []
    finally:
        if recording is None:
            rec.flush()
            rec.disconnect()
            if out_rrd is not None and sys.exc_info()[0] is not None:
                tmp_rrd.unlink(missing_ok=True)
    if recording is None and out_rrd is not None:
        os.replace(tmp_rrd, out_rrd)
    png_path = None
    if png:
        png_path = render_context_png(view, png)
    return RecordingResult(Path(out_rrd) if out_rrd else None, view, recon, ol, png_path)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="protocad-visualize",
        description="Write a rerun recording (.rrd) of what a ProtoCAD agent's context module "
                    "learned: u/e/RSSM-state embeddings (PCA or t-SNE) of every context of both "
                    "splits, prototypes, assignments, reconstructions and open-loop predictions. "
                    "Open it with `rerun FILE.rrd`.",
        epilog="examples:\n  protocad-visualize --checkpoint runs/X/checkpoints/latest.pt "
               "--task cheetah_run\n  protocad-visualize --checkpoint CKPT --logs runs/X/bags/* "
               "--projection tsne --out ctx.rrd\n\nView an MCAP log's images directly: rerun LOG.mcap",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", required=True, help="checkpoint file (checkpoints/latest.pt) "
                   "or a run directory")
    p.add_argument("--logs", nargs="+", default=None, metavar="BAG",
                   help="MCAP logs (bag directories or .mcap files) to take episodes from")
    p.add_argument("--task", default=None, help="task whose contexts to collect (default: the "
                   "checkpoint's task)")
    p.add_argument("--logs-only", action="store_true", help="with --logs: show only the logged "
                   "episodes (default: contexts the logs lack, e.g. the test contexts of a "
                   "training run, are collected in-process so every context of both splits shows)")
    p.add_argument("--log-steps", type=int, default=100,
                   help="first steps of each logged episode to use (default 100)")
    p.add_argument("--collect", action="store_true", help="collect one short episode per context "
                   "of both splits in-process (the default when no --logs are given)")
    p.add_argument("--steps-per-context", type=int, default=DEFAULT_STEPS_PER_CONTEXT,
                   help=f"observations per collected episode (default {DEFAULT_STEPS_PER_CONTEXT})")
    p.add_argument("--random-policy", action="store_true",
                   help="collect with uniform random actions instead of the agent's policy")
    p.add_argument("--projection", choices=("pca", "tsne"), default="pca")
    p.add_argument("--skip-steps", type=int, default=DEFAULT_SKIP_STEPS,
                   help="first steps of each episode left out of the embedding points")
    p.add_argument("--context-steps", type=int, default=5, help="observed frames before the "
                   "open-loop prediction")
    p.add_argument("--horizon", type=int, default=50, help="open-loop prediction length "
                   "(0: no open-loop view)")
    p.add_argument("--episodes-shown", type=int, default=4,
                   help="episodes in the reconstruction / open-loop views")
    p.add_argument("--out", default=None, help="output .rrd (default: RUN_DIR/contexts.rrd)")
    p.add_argument("--png", default=None, help="also render a static scatter PNG of the 2D view")
    p.add_argument("--spawn", action="store_true", help="also open a rerun viewer")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="cpu")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def _resolve_checkpoint(path: str) -> Path:
    p = Path(path)
    if p.is_dir():
        for cand in (p / "checkpoints" / "latest.pt", p / "latest.pt"):
            if cand.is_file():
                return cand
        raise SystemExit(f"--checkpoint {path}: no checkpoints/latest.pt in this directory")
    if not p.is_file():
        raise SystemExit(f"--checkpoint {path}: no such file")
    return p


def _default_out(ckpt: Path) -> Path:
    run_dir = ckpt.parent.parent if ckpt.parent.name == "checkpoints" else ckpt.parent
    return run_dir / "contexts.rrd"


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    ckpt = _resolve_checkpoint(args.checkpoint)
    if args.logs and args.collect:
        raise SystemExit("give either --logs or --collect, not both")
    if args.steps_per_context < 2:
        raise SystemExit("--steps-per-context must be >= 2")
    t0 = time.monotonic()
    try:
        agent = load_agent(ckpt, args.device)
    except Exception as exc:  # CheckpointError and friends: one clear line
        raise SystemExit(f"cannot load {ckpt}: {exc}")
    task = args.task or getattr(getattr(agent, "cfg", None), "task", None)
    if not args.logs and not task:
        raise SystemExit("--task is needed (the checkpoint does not say which task it learned)")
    if task:
        from sim_bridge.contexts import get_task

        try:
            get_task(task)
        except ValueError as exc:
            raise SystemExit(str(exc))
    out = Path(args.out) if args.out else _default_out(ckpt)
    progress = False if args.no_progress else None
    try:
        res = write_context_recording(
            agent, logs=args.logs, out_rrd=out, projection=args.projection,
            task=task, steps_per_context=args.steps_per_context, log_steps=args.log_steps,
            cover_all_contexts=not args.logs_only,
            context_steps=args.context_steps, horizon=args.horizon,
            num_prediction_episodes=args.episodes_shown, skip_steps=args.skip_steps,
            random_policy=args.random_policy, seed=args.seed, png=args.png, spawn=args.spawn,
            progress=progress)
    except (ValueError, FileNotFoundError, RuntimeError) as exc:
        raise SystemExit(f"protocad-visualize: {exc}")
    view = res.view
    n_ctx = view.contexts_per_split()
    print(f"wrote {res.path} ({res.path.stat().st_size / 1e6:.1f} MB) in "
          f"{time.monotonic() - t0:.1f}s: {len(view.episodes)} episodes of {n_ctx['train']} train "
          f"and {n_ctx['test']} test contexts, {len(view.point_episode)} points, "
          f"K={view.num_prototypes} prototypes, projection {view.method}; "
          f"reconstructions of {len(res.reconstruction_episodes)} and open-loop predictions of "
          f"{len(res.open_loop_episodes)} episodes")
    if res.png:
        print(f"wrote {res.png}")
    print(f"open it with: rerun {res.path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
