"""The numbers behind every context view: the agent's features of each step (u, e, the RSSM
state), their 2-D/3-D projections (PCA, t-SNE, UMAP) with the prototypes beside them, and the
classes and colours the recording and the PNG share."""
from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
from typing import Any, Iterable, Sequence

import numpy as np

from sim_bridge.contract.contexts import context_label
from trainer.viz.context_episodes import DEFAULT_SKIP_STEPS, SPLIT_CLASS, Episode, stack_batches

PROTOTYPE_CLASS = 2
CLASS_COLORS = {0: (31, 119, 180), 1: (255, 127, 14), 2: (214, 39, 40)}
CLASS_NAMES = {0: "train", 1: "test", 2: "prototype"}
FEATURES = ("u_e", "u", "e", "rssm_state")
PROTOTYPE_FEATURES = ("u_e", "u", "e")


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


def to_numpy(x: Any) -> np.ndarray | None:
    if x is None:
        return None
    if hasattr(x, "detach"):
        x = x.detach().float().cpu().numpy() if x.dtype.is_floating_point else x.detach().cpu().numpy()
    return np.asarray(x)


def no_grad():
    try:
        import torch

        return torch.no_grad()
    except ImportError:  # pragma: no cover
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
    with no_grad():
        for _, idx in sorted(_groups_by_length(episodes).items()):
            for j in range(0, len(idx), batch_size):
                part = idx[j:j + batch_size]
                res = agent.embed_sequences(stack_batches([episodes[i].batch() for i in part]))
                arrays = {k: to_numpy(res.get(k)) for k in ("s", "u", "w", "e")}
                for b, i in enumerate(part):
                    out[i] = {k: (None if v is None or v.size == 0 else v[b].astype(np.float32))
                              for k, v in arrays.items()}
    return out  # type: ignore[return-value]


def agent_prototypes(agent: Any) -> np.ndarray | None:
    protos = agent.prototypes() if hasattr(agent, "prototypes") else None
    protos = to_numpy(protos)
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

    def space(self, feature: str, dim: int) -> str:
        return f"/embeddings/{feature}/{self.method}{dim}d"

    def contexts_per_split(self) -> dict[str, int]:
        return {s: sum(split == s for split, _ in self.contexts) for s in SPLIT_CLASS}

    @property
    def context_labels(self) -> list[str]:
        return [context_label(c, s) for s, c in self.contexts]


def _point_steps(eps: Sequence[Episode], skip_steps: int, max_points: int) -> list[np.ndarray]:
    """The steps of each episode that become points: the warm-up skipped, thinned evenly to
    stay under max_points."""
    steps_per_ep = []
    for ep in eps:
        first = min(skip_steps, len(ep) - 1)
        steps_per_ep.append(np.arange(first, len(ep)))
    total = sum(len(s) for s in steps_per_ep)
    if total > max_points:
        keep = max(1, max_points // len(eps))
        steps_per_ep = [s[np.linspace(0, len(s) - 1, min(keep, len(s))).round().astype(int)]
                        for s in steps_per_ep]
    return steps_per_ep


def _contexts_of(eps: Sequence[Episode]) -> tuple[list[tuple[str, dict[str, float]]], np.ndarray]:
    """The (split, context) pairs in order of first appearance, and each episode's index into
    them: several episodes of one context share its mean point."""
    contexts: list[tuple[str, dict[str, float]]] = []
    episode_context = np.zeros(len(eps), int)
    index: dict[tuple, int] = {}
    for i, ep in enumerate(eps):
        key = (ep.split, tuple(sorted(ep.context.items())))
        if key not in index:
            index[key] = len(contexts)
            contexts.append((ep.split, dict(ep.context)))
        episode_context[i] = index[key]
    return contexts, episode_context


def _feature_spaces(emb: Sequence[dict[str, np.ndarray | None]], steps_per_ep: Sequence[np.ndarray]
                    ) -> dict[str, np.ndarray]:
    """name -> (N, F) at the point steps: u_e, u and e where the agent has context features,
    and always the RSSM state."""
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
    return features


def _project_spaces(features: dict[str, np.ndarray], protos: np.ndarray | None, point_context: np.ndarray,
                    num_contexts: int, *, dims: Sequence[int], projection: str, seed: int) -> tuple[dict, dict, dict]:
    """(points, context means, prototypes), each (feature, dim) -> (n, dim), of every feature
    space in every dim."""
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
                                                for c in range(num_contexts)])
    return points, ctx_points, proto_points


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
    steps_per_ep = _point_steps(eps, skip_steps, max_points)
    point_episode = np.concatenate([np.full(len(s), i) for i, s in enumerate(steps_per_ep)])
    point_step = np.concatenate(steps_per_ep)
    contexts, episode_context = _contexts_of(eps)
    features = _feature_spaces(emb, steps_per_ep)
    protos = agent_prototypes(agent)
    points, ctx_points, proto_points = _project_spaces(
        features, protos, episode_context[point_episode], len(contexts), dims=dims,
        projection=projection, seed=seed)
    value_range = {}
    for p in params:
        vals = [ep.context[p] for ep in eps if p in ep.context]
        value_range[p] = (min(vals), max(vals))
    assignments = [None if x["w"] is None else x["w"] for x in emb]
    return ContextView(projection, tuple(params), eps, point_episode, point_step, features,
                       points, ctx_points, proto_points, assignments,
                       0 if protos is None else len(protos), contexts, episode_context,
                       value_range, skip_steps)
