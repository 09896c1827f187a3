"""What a context view logs to rerun: the embeddings, prototypes and assignments of a
ContextView, and reconstructions and open-loop predictions of a few episodes. A standalone
recording (trainer/viz/visualize.py) and a training recording at chosen updates
(trainer/viz/rerun_log.py) log the same entities.

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
per-step entities are on the sequence timeline 'step'.

With ``update`` set (``TrainingRecorder.log_context_view``) everything is logged on the
'update' timeline too, so the embeddings can be scrubbed through training.
"""
from __future__ import annotations

from typing import Any, Sequence

import numpy as np
import rerun as rr

from sim_bridge.contract.contexts import context_label
from trainer.viz.context_episodes import SPLIT_CLASS, Episode, pick_episodes, stack_batches
from trainer.viz.context_view import (
    CLASS_COLORS,
    CLASS_NAMES,
    PROTOTYPE_CLASS,
    ContextView,
    colormap,
    no_grad,
    to_numpy,
)


def annotation_context():
    return rr.AnnotationContext([rr.AnnotationInfo(id=i, label=CLASS_NAMES[i], color=CLASS_COLORS[i])
                                 for i in sorted(CLASS_NAMES)])


def log_context_view(rec: Any, view: ContextView, *, update: int | None = None) -> None:
    """Log the embeddings, prototypes and assignments of ``view`` to the RecordingStream ``rec``.

    update=None: static data (one snapshot); an int: on the 'update' timeline.
    """
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


def log_reconstructions(rec: Any, agent: Any, episodes: Sequence[Episode], *, num_episodes: int = 4,
                        update: int | None = None) -> list[int]:
    """Observations beside reconstructions of a few episodes (side by side), on 'step'."""
    picks = pick_episodes(episodes, num_episodes, min_length=2)
    if not picks or not getattr(agent, "has_decoder", True):
        return []  # e.g. DreamerPro: reconstruction-free, nothing to show
    if update is not None:
        rec.set_time("update", sequence=int(update))
    T = min(len(episodes[i]) for i in picks)
    with no_grad():
        model = to_numpy(agent.reconstruct(stack_batches([episodes[i].batch(0, T) for i in picks])))
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
    with no_grad():
        out = agent.open_loop(batch, context_steps=context_steps, horizon=horizon)
    pred = np.asarray(to_numpy(out["prediction"])).astype(np.uint8)
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
