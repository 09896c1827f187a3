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

The recording carries its blueprint (layout) inside. The agent is used only through
Agent.embed_sequences, .reconstruct, .open_loop and .prototypes (protocad_ros/model/agent.py);
variants without a decoder skip the prediction views and variants without context features show
the RSSM state only.

The parts: trainer/viz/context_episodes.py (episodes per context, from a policy or from logs),
trainer/viz/context_view.py (features, projections, classes), trainer/viz/context_log.py (what
is logged: the entity paths), trainer/viz/context_blueprint.py (the layout),
trainer/viz/context_plot.py (the PNG); this module writes the recording and is the CLI.
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Sequence

import rerun as rr

from protocad_ros.checkpoint.files import existing_checkpoint_file
from protocad_ros.live_view import check_display
from sim_bridge.contract.contexts import context_label, get_task
from trainer.settings import arg, build, settings_parser
from trainer.viz.context_blueprint import context_blueprint, context_blueprint_parts
from trainer.viz.context_episodes import (
    DEFAULT_SKIP_STEPS,
    DEFAULT_STEPS_PER_CONTEXT,
    SPLIT_CLASS,
    Episode,
    collect_context_episodes,
    load_log_episodes,
    missing_contexts,
    pick_episodes,
    stack_batches,
)
from trainer.viz.context_log import log_context_view, log_open_loop, log_reconstructions
from trainer.viz.context_plot import render_context_png
from trainer.viz.context_view import (
    CLASS_COLORS,
    CLASS_NAMES,
    FEATURES,
    PROTOTYPE_CLASS,
    PROTOTYPE_FEATURES,
    ContextView,
    colormap,
    compute_context_view,
    embed_episodes,
    project,
)

__all__ = ["Episode", "ContextView", "RecordingResult", "ViewSettings", "VisualizeSettings", "collect_context_episodes",
           "load_log_episodes", "missing_contexts", "compute_context_view", "embed_episodes",
           "project", "log_context_view", "log_reconstructions", "log_open_loop",
           "context_blueprint", "context_blueprint_parts", "render_context_png",
           "write_context_recording", "load_agent", "context_label", "colormap", "stack_batches",
           "FEATURES", "PROTOTYPE_FEATURES", "CLASS_COLORS", "CLASS_NAMES", "PROTOTYPE_CLASS",
           "SPLIT_CLASS", "DEFAULT_STEPS_PER_CONTEXT", "DEFAULT_SKIP_STEPS", "pick_episodes", "main"]


# ============================================================================== top level
@dataclass
class RecordingResult:
    path: Path | None
    view: ContextView
    reconstruction_episodes: list[int]
    open_loop_episodes: list[int]
    png: Path | None = None


@dataclass
class ViewSettings:
    """What the context view shows and how it gets its episodes: write_context_recording's
    settings (a ViewSettings, or its fields by name) and protocad-visualize's options."""

    task: str | None = None
    """task whose contexts to collect (default: the checkpoint's task)"""
    log_steps: int | None = 100
    """first steps of each logged episode to use (default 100)"""
    steps_per_context: int = DEFAULT_STEPS_PER_CONTEXT
    """observations per collected episode"""
    random_policy: bool = False
    """collect with uniform random actions instead of the agent's policy"""
    projection: str = arg("pca", choices=("pca", "tsne"))
    """how the features are projected to 2D and 3D"""
    skip_steps: int = DEFAULT_SKIP_STEPS
    """first steps of each episode left out of the embedding points"""
    context_steps: int = 5
    """observed frames before the open-loop prediction"""
    horizon: int = 50
    """open-loop prediction length (0: no open-loop view)"""
    num_prediction_episodes: int = arg(4, "--episodes-shown")
    """episodes in the reconstruction / open-loop views"""
    seed: int = 0
    """seeds the collected episodes and the projection"""
    device: str = "cpu"
    """the agent's device"""
    cover_all_contexts: bool = arg(True, flag=False)
    """with logs: also collect the contexts they lack (all, or max_contexts per split's
    stratified subset); --logs-only turns it off"""
    max_contexts: int = arg(0, flag=False)
    """with logs and cover_all_contexts: at most this many contexts per split (0: all)"""
    progress: bool | None = arg(None, flag=False)
    """progress bars of the collection (None: where the terminal shows them); --no-progress"""


@dataclass
class VisualizeSettings(ViewSettings):
    """protocad-visualize's options: the checkpoint, where the episodes come from, the view's
    settings and where it goes."""

    checkpoint_arg: str | None = arg(None, "checkpoint_arg", nargs="?", metavar="CHECKPOINT")
    """checkpoint file or run directory, as protocad-evaluate takes it"""
    checkpoint: str | None = None
    """the same, as an option (either form)"""
    logs: list[str] | None = arg(None, metavar="BAG")
    """MCAP logs (bag directories or .mcap files) to take episodes from"""
    logs_only: bool = False
    """with --logs: show only the logged episodes (default: contexts the logs lack, e.g. the test
    contexts of a training run, are collected in-process so every context of both splits shows)"""
    collect: bool = False
    """collect one short episode per context of both splits in-process (the default when no
    --logs are given)"""
    out: str | None = None
    """output .rrd (default: RUN_DIR/contexts.rrd)"""
    png: str | None = None
    """also render a static scatter PNG of the 2D view"""
    spawn: bool = False
    """also open a rerun viewer"""
    no_progress: bool = False
    """no progress bar"""

    def view(self, task: str | None) -> ViewSettings:
        """The view's settings these options ask for, on `task`."""
        view = build(ViewSettings, dataclasses.asdict(self))
        return dataclasses.replace(view, task=task, cover_all_contexts=not self.logs_only,
                                   progress=False if self.no_progress else None)


def load_agent(source: Any, device: str = "cpu") -> Any:
    """An Agent from a checkpoint path, or ``source`` itself when it is already one."""
    if isinstance(source, (str, Path)):
        from protocad_ros.checkpoint.agent_file import load_checkpoint

        agent, _ = load_checkpoint(str(source), device=device, optimizer_states=False)
        if not hasattr(agent, "embed_sequences"):
            raise ValueError(f"{source}: variant {agent.cfg.variant!r} is model-free: it has no "
                             "latent state or context to show (the world-model variants do)")
        return agent
    if not hasattr(source, "embed_sequences"):
        raise TypeError(f"expected a checkpoint path or an Agent, got {type(source).__name__}")
    return source


def _check_destination(out_rrd: str | Path | None, recording: Any, spawn: bool) -> None:
    if out_rrd is not None and Path(out_rrd).suffix != ".rrd":
        raise ValueError(f"output must be an .rrd file, got {str(out_rrd)!r}")
    if recording is None and out_rrd is None and not spawn:
        raise ValueError("nowhere to write: give out_rrd or spawn=True")
    if spawn:
        check_display()


def _episodes_to_show(agent: Any, logs: Sequence[str | Path] | None, view: ViewSettings,
                      episodes: Iterable[Any] | None) -> list[Episode]:
    """The episodes of the view: those given, else those of the logs (plus the contexts they
    lack), else collected for every context of ``view.task``."""
    task, collect = view.task, dict(steps=view.steps_per_context, seed=view.seed,
                                    random_policy=view.random_policy, progress=view.progress)
    if episodes is not None:
        eps = [Episode.from_any(e) for e in episodes]
    elif logs:
        eps = load_log_episodes(logs, max_steps=view.log_steps)
        missing = missing_contexts(task, eps, max_contexts=view.max_contexts) \
            if (task and view.cover_all_contexts) else {}
        if any(missing.values()):
            # Logs of a training run hold only training contexts: the rest is collected, so the
            # view shows every context of both splits.
            eps += collect_context_episodes(task, agent, contexts=missing, **collect)
    elif task:
        eps = collect_context_episodes(task, agent, **collect)
    else:
        raise ValueError("give episodes, logs or a task to collect episodes for")
    if not eps:
        raise ValueError("no episodes to visualize")
    return eps


def _open_loop_episodes(agent: Any, view: ViewSettings, eps: list[Episode],
                        given: Iterable[Any] | None) -> list[Episode]:
    """Episodes long enough for the open-loop view: those given, else the view's own, else one
    collected in the first and last context of each split."""
    length = view.context_steps + view.horizon
    if given is not None:
        return [Episode.from_any(e) for e in given]
    if any(len(e) >= length for e in eps):
        return eps
    if view.task and view.horizon > 0:
        spec = get_task(view.task)
        pick = {s: [spec.contexts(s)[0], spec.contexts(s)[-1]] for s in ("train", "test")}
        return collect_context_episodes(view.task, agent, steps=length, seed=view.seed + 1, contexts=pick,
                                        random_policy=view.random_policy, progress=view.progress)
    return []


def _new_stream(blueprint: Any, out_rrd: Path | None, spawn: bool) -> tuple[Any, Path | None]:
    """A RecordingStream to a temporary file beside ``out_rrd`` (and a spawned viewer), and
    that file's path: the caller renames it at the end, so an earlier recording is never
    replaced by a partial one."""
    rec = rr.RecordingStream("protocad_contexts")
    sinks, tmp_rrd = [], None
    if out_rrd is not None:
        out_rrd.parent.mkdir(parents=True, exist_ok=True)
        tmp_rrd = out_rrd.parent / f".{out_rrd.name}.{os.getpid()}.tmp"
        sinks.append(rr.FileSink(str(tmp_rrd)))
    if spawn:
        rr.spawn(connect=False)
        sinks.append(rr.GrpcSink())
    rec.set_sinks(*sinks, default_blueprint=blueprint)
    return rec, tmp_rrd


def write_context_recording(source: Any, logs: Sequence[str | Path] | None = None,
                            out_rrd: str | Path | None = None, view: ViewSettings | None = None, *,
                            episodes: Iterable[Any] | None = None, open_loop_episodes: Iterable[Any] | None = None,
                            png: str | Path | None = None, recording: Any = None, spawn: bool = False,
                            **view_fields: Any) -> RecordingResult:
    """Write the context view of an agent to ``out_rrd`` (with its blueprint).

    source: a checkpoint path or an Agent; ``view``: the ViewSettings (what it shows, how
    episodes are collected), replaced by the ``view_fields`` given by name. Episodes from (first
    that applies) ``episodes`` (Episode objects or dicts: image, action, context, split, ...),
    ``logs`` (MCAP bag dirs / files, read with trainer.data.dataset), or collected in-process for
    every context of both splits of ``view.task`` (``steps_per_context`` steps each; the task
    defaults to the agent's). With logs and ``cover_all_contexts``, contexts of the task the logs
    lack (e.g. every test context in a training run's bags) are collected in-process too: all of
    them, or with ``max_contexts`` those of each split's stratified subset of that many.
    ``open_loop_episodes``: longer episodes for the open-loop view (default: those of the main
    episodes that are long enough, else, when collecting, one context_steps + horizon episode per
    split's first and last context). ``recording``: an existing rerun.RecordingStream to log into
    instead of a new file; ``spawn``: also stream to a spawned viewer. ``png``: also write a
    static scatter image.
    """
    view = dataclasses.replace(view or ViewSettings(), **view_fields)
    if view.projection not in ("pca", "tsne"):
        raise ValueError(f"unknown projection {view.projection!r}; valid: 'pca', 'tsne'")
    _check_destination(out_rrd, recording, spawn)
    agent = load_agent(source, view.device)
    if hasattr(agent, "eval"):
        agent.eval()
    view = dataclasses.replace(view, task=view.task or getattr(getattr(agent, "cfg", None), "task", None))
    eps = _episodes_to_show(agent, logs, view, episodes)
    context_view = compute_context_view(agent, eps, projection=view.projection, skip_steps=view.skip_steps,
                                        seed=view.seed)
    ol_eps = _open_loop_episodes(agent, view, eps, open_loop_episodes)
    out_rrd = Path(out_rrd) if out_rrd is not None else None
    if recording is not None:
        rec, tmp_rrd = recording, None
        rec.send_blueprint(context_blueprint(context_view))
    else:
        rec, tmp_rrd = _new_stream(context_blueprint(context_view), out_rrd, spawn)
    try:
        log_context_view(rec, context_view)
        recon = log_reconstructions(rec, agent, eps, num_episodes=view.num_prediction_episodes)
        ol = log_open_loop(rec, agent, ol_eps, context_steps=view.context_steps, horizon=view.horizon,
                           num_episodes=view.num_prediction_episodes) if view.horizon > 0 else []
    finally:
        if recording is None:
            rec.flush()
            rec.disconnect()
            if tmp_rrd is not None and sys.exc_info()[0] is not None:
                tmp_rrd.unlink(missing_ok=True)
    if tmp_rrd is not None:
        os.replace(tmp_rrd, out_rrd)
    png_path = render_context_png(context_view, png) if png else None
    return RecordingResult(out_rrd, context_view, recon, ol, png_path)


def build_parser() -> argparse.ArgumentParser:
    return settings_parser(
        "protocad-visualize",
        "Write a rerun recording (.rrd) of what a ProtoCAD agent's context module "
        "learned: u/e/RSSM-state embeddings (PCA or t-SNE) of every context of both "
        "splits, prototypes, assignments, reconstructions and open-loop predictions. "
        "Open it with `rerun FILE.rrd`.",
        [(None, VisualizeSettings)],
        epilog="examples:\n  protocad-visualize --checkpoint runs/X/checkpoints/latest.pt "
               "--task cheetah_run\n  protocad-visualize --checkpoint CKPT --logs runs/X/bags/* "
               "--projection tsne --out ctx.rrd\n\nView an MCAP log's images directly: rerun LOG.mcap")


def _resolve_checkpoint(path: str) -> Path:
    try:
        return existing_checkpoint_file(path)
    except ValueError as exc:
        raise SystemExit(f"protocad-visualize: {exc}") from None


def _default_out(ckpt: Path) -> Path:
    run_dir = ckpt.parent.parent if ckpt.parent.name == "checkpoints" else ckpt.parent
    return run_dir / "contexts.rrd"


def main(argv: Sequence[str] | None = None) -> int:
    args = build(VisualizeSettings, vars(build_parser().parse_args(argv)))
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
        try:
            get_task(task)
        except ValueError as exc:
            raise SystemExit(str(exc))
    out = Path(args.out) if args.out else _default_out(ckpt)
    if out.exists():
        print(f"[visualize] {out} exists: replacing it (--out PATH writes elsewhere)", flush=True)
    try:
        res = write_context_recording(agent, logs=args.logs, out_rrd=out, view=args.view(task), png=args.png,
                                      spawn=args.spawn)
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
