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
.prototypes (protocad_ros/model/agent.py); variants without a decoder skip the prediction views and
variants without context features show the RSSM state only.

With ``update`` set (``TrainingRecorder.log_context_view``) everything is logged on the
'update' timeline too, so the embeddings can be scrubbed through training.

The parts: trainer/viz/context_episodes.py (episodes per context, from a policy or from logs),
trainer/viz/context_view.py (features, projections, classes), trainer/viz/context_plot.py (the PNG);
this module logs them to rerun and is the CLI.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np


from sim_bridge.contract.contexts import context_label
from trainer.viz.context_episodes import (DEFAULT_SKIP_STEPS, DEFAULT_STEPS_PER_CONTEXT, SPLIT_CLASS,
                                      Episode, collect_context_episodes, load_log_episodes,
                                      missing_contexts, pick_episodes, stack_batches)
from trainer.viz.context_plot import render_context_png
from trainer.viz.context_view import (CLASS_COLORS, CLASS_NAMES, FEATURES, PROTOTYPE_CLASS,
                                  PROTOTYPE_FEATURES, ContextView, colormap,
                                  compute_context_view, embed_episodes, no_grad, project, to_numpy)

__all__ = ["Episode", "ContextView", "RecordingResult", "collect_context_episodes",
           "load_log_episodes", "missing_contexts", "compute_context_view", "embed_episodes",
           "project", "log_context_view", "log_reconstructions", "log_open_loop",
           "context_blueprint", "context_blueprint_parts", "render_context_png",
           "write_context_recording", "load_agent", "context_label", "colormap", "stack_batches",
           "FEATURES", "PROTOTYPE_FEATURES", "CLASS_COLORS", "CLASS_NAMES", "PROTOTYPE_CLASS",
           "SPLIT_CLASS", "DEFAULT_STEPS_PER_CONTEXT", "DEFAULT_SKIP_STEPS", "pick_episodes", "main"]


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
                            cover_all_contexts: bool = True, max_contexts: int = 0,
                            log_steps: int | None = 100) -> RecordingResult:
    """Write the context view of an agent to ``out_rrd`` (with its blueprint).

    source: a checkpoint path or an Agent. Episodes from (first that applies) ``episodes``
    (Episode objects or dicts: image, action, context, split, ...), ``logs`` (MCAP bag dirs /
    files, read with trainer.data.dataset), or collected in-process for every context of both splits
    of ``task`` (``steps_per_context`` steps each; ``task`` defaults to the agent's). With logs
    and ``cover_all_contexts``, contexts of the task the logs lack (e.g. every test context in
    a training run's bags) are collected in-process too: all of them, or with ``max_contexts``
    those of each split's stratified subset of that many. ``open_loop_episodes``: longer episodes for
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
        missing = missing_contexts(task, eps, max_contexts=max_contexts) if (task and cover_all_contexts) else {}
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
        from sim_bridge.contract.contexts import get_task

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
    p.add_argument("checkpoint_arg", nargs="?", metavar="CHECKPOINT",
                   help="checkpoint file or run directory, as protocad-evaluate takes it")
    p.add_argument("--checkpoint", default=None, help="the same, as an option (either form)")
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
    from protocad_ros.checkpoint import existing_checkpoint_file

    try:
        return existing_checkpoint_file(path)
    except ValueError as exc:
        raise SystemExit(f"protocad-visualize: {exc}") from None


def _default_out(ckpt: Path) -> Path:
    run_dir = ckpt.parent.parent if ckpt.parent.name == "checkpoints" else ckpt.parent
    return run_dir / "contexts.rrd"


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if bool(args.checkpoint) == bool(args.checkpoint_arg):
        raise SystemExit("protocad-visualize: give one checkpoint (file or run directory), "
                         "as CHECKPOINT or --checkpoint")
    ckpt = _resolve_checkpoint(args.checkpoint or args.checkpoint_arg)
    if args.logs and args.collect:
        raise SystemExit("give either --logs or --collect, not both")
    if args.steps_per_context < 2:
        raise SystemExit("--steps-per-context must be >= 2")
    t0 = time.monotonic()
    try:
        agent = load_agent(ckpt, args.device)
    except Exception as exc:  # noqa: BLE001 - CheckpointError and friends: one clear line
        raise SystemExit(f"cannot load {ckpt}: {exc}")
    task = args.task or getattr(getattr(agent, "cfg", None), "task", None)
    if not args.logs and not task:
        raise SystemExit("--task is needed (the checkpoint does not say which task it learned)")
    if task:
        from sim_bridge.contract.contexts import get_task

        try:
            get_task(task)
        except ValueError as exc:
            raise SystemExit(str(exc))
    out = Path(args.out) if args.out else _default_out(ckpt)
    if out.exists():
        print(f"[visualize] {out} exists: replacing it (--out PATH writes elsewhere)", flush=True)
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
