"""`protocad-train` (`ros2 run trainer train`): train an agent from MCAP logs.

    protocad-train --logs runs/loop/bags --task pendulum_swingup --variant protocad \\
        --preset small --updates 5000 --run-dir runs/offline-1
    protocad-train --logs foreign_bag/ --topic image=/robot/camera --topic action=/robot/cmd ...
    protocad-train --run-dir runs/offline-1 --resume            # continue exactly
    torchrun --nproc_per_node 2 --no-python protocad-train --bags runs/loop/bags ...  # 2 ranks

The training itself is the :class:`Trainer`'s (trainer/learn/trainer.py); this module reads the
logs, opens or resumes the run directory and trains to the asked update count.
"""
from __future__ import annotations

import dataclasses
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

from protocad_ros.checkpoint.files import CheckpointError
from protocad_ros.model.config import plan_prototype_freeze
from sim_bridge.contract.contexts import task_actuators
from trainer import cli_values, console, runs, settings
from trainer.data.dataset import DatasetError, MCAPDataset, TopicMap, default_cache_dir
from trainer.data.records import DEFAULT_CROP
from trainer.data.sources import find_sources
from trainer.data.store import multiple_publishers
from trainer.learn import distributed
from trainer.learn.resume import TrainerOpening, open_trainer
from trainer.learn.trainer import DEFAULT_LOG_EVERY, CheckpointWriteError, RanksDiverged, Trainer
from trainer.run_input import check_logs, check_settings_section
from trainer.settings import arg
from trainer.viz.metrics_rerun import metrics_callbacks


# ---------------------------------------------------------------------- settings and CLI
@dataclass
class TrainSettings:
    """protocad-train's logs and run options."""

    logs: list[str] | None = arg(None, "--logs", "--bags", metavar="PATH")
    """bag directories / .mcap files / folders of bags (with --resume: default = the run's
    logs). Under torchrun write --bags: torchrun takes --logs as its own --logs-specs"""
    topic: list[str] = arg([], action="append", metavar="KEY=/TOPIC", group="logs")
    """read KEY (image, step_info, action, context) from /TOPIC, for logs recorded under other
    names (e.g. --topic image=/cam/rgb; context=none)"""
    namespace: list[str] | None = arg(None, metavar="NS", group="logs")
    """namespace(s) of the contract topics in the logs (default /protocad); several = one robot
    each, e.g. the bags of `protocad-loop --robots 2`: --namespace /protocad/robot0 /protocad/robot1"""
    crop: str | None = arg(None, metavar="center|full|X,Y,W,H", group="logs")
    """the part of each camera frame the model sees before it is resized to train.image_size
    (sim_bridge.contract.camera, what the policy node does on a robot; default center: the
    largest centered square). Frames already at the model's size are taken whole"""
    cache_dir: str | None = arg(None, group="logs")
    """dataset cache (default $PROTOCAD_CACHE_DIR or ~/.cache/protocad-ros/dataset)"""
    cache_budget_gb: float | None = arg(None, group="logs")
    """size budget of the dataset cache: least recently used bags are evicted (and re-indexed
    from their logs if used again); bags in use never are; 0 = no limit (default
    $PROTOCAD_CACHE_BUDGET_GB or 4)"""
    updates: int | None = arg(None, group="run")
    """train until the update counter reaches N (a total; default 1000, or the resumed run's target)"""
    run_dir: str | None = arg(None, group="run")
    """output directory (default runs/train-TASK-VARIANT-TIME)"""
    checkpoint_every: int | None = arg(None, group="run")
    """updates between checkpoints (default 500, or the resumed run's)"""
    log_every: int | None = arg(None, group="run")
    """updates per metrics line (default 10, or the resumed run's)"""
    resume: bool = arg(False, group="run")
    """continue RUN_DIR from its checkpoint (config, counters, sampler state)"""
    rerun: str | None = arg(None, nargs="?", const="", metavar="RRD", group="run")
    """also log the scalars to a rerun recording (default RUN_DIR/metrics.rrd)"""
    no_progress: bool = arg(False, group="run")
    """no progress bar"""
    accept_test_split: bool = arg(False, group="run")
    """train on episodes recorded on the test split's contexts (refused by default: the
    evaluation keeps them unseen)"""
    accept_multiple_publishers: bool = arg(False, group="run")
    """train on bags whose recorder saw several publishers on a topic read here (a second bridge
    or an impostor interleaved its messages); refused by default, naming the bag and topic"""

    def resumed_from(self, run_json: dict[str, Any], path: Path = Path("run.json")) -> "TrainSettings":
        """Options the run was started with (run.json at `path`), where not given again
        (ValueError naming the first one whose type is not its option's)."""
        saved = {"logs": run_json.get("logs"), "topic": run_json.get("topics_args") or [],
                 "namespace": run_json.get("namespace"), "cache_dir": run_json.get("cache_dir"),
                 "crop": run_json.get("crop"),
                 "updates": run_json.get("updates"), "checkpoint_every": run_json.get("checkpoint_every"),
                 "log_every": run_json.get("log_every"), "rerun": run_json.get("rerun"),
                 "accept_test_split": bool(run_json.get("accept_test_split")),
                 "accept_multiple_publishers": bool(run_json.get("accept_multiple_publishers"))}
        if isinstance(saved["namespace"], str):   # older run.json: one
            saved["namespace"] = [saved["namespace"]]
        check_settings_section(path, "train", TrainSettings, {k: v for k, v in saved.items() if v is not None})
        mine = dataclasses.asdict(self)
        return dataclasses.replace(self, **{k: v for k, v in saved.items()
                                            if mine[k] in (None, [], False) and v not in (None, [])})


def build_parser():
    return settings.settings_parser(
        "protocad-train",
        "Train a ProtoCAD agent (or a baseline/ablation variant) from MCAP logs (rosbag2 layout; "
        "bag directories, .mcap files or folders of bags). Writes RUN_DIR/config.yaml, "
        "metrics.jsonl, checkpoints/latest.pt (atomic, every --checkpoint-every updates and at the "
        "end). Ctrl-C saves a final checkpoint and exits 0; --resume continues exactly from the last one.",
        [(None, TrainSettings), ("model / config", settings.ModelChoice)])


def refuse_test_split(ds: MCAPDataset, accept: bool, say: Callable[..., None] = print) -> None:
    """ValueError (one line) when the logs hold episodes of the test split: contexts the
    evaluation keeps unseen (the paper's protocol), which training would then have seen. With
    `accept`, a warning instead."""
    test = {}
    for e in ds.episodes():
        if e.get("split") == "test":
            test[e["source"]] = test.get(e["source"], 0) + 1
    if not test:
        return
    n, bags = sum(test.values()), sorted(test)
    where = f"{bags[0]}" + (f" and {len(bags) - 1} more bag(s)" if len(bags) > 1 else "")
    text = (f"the logs hold {n} episode(s) of the test split (unseen contexts) in {where}: training "
            "on them leaks the evaluation")
    if not accept:
        raise ValueError(f"{text}; record training data with split:=train, or pass "
                         "--accept-test-split to train on them anyway")
    say(f"[train] WARNING: {text} (--accept-test-split)", flush=True)


def refuse_multiple_publishers(logs: Sequence[str | Path], topic_maps: Sequence[TopicMap]) -> None:
    """ValueError (one line, naming the bag and topic) when a bag's recorder marked a topic these
    maps read as having had several publishers: their messages interleave in it (an impostor's
    actions, a second bridge's observations) and nothing in the bag tells whose is whose."""
    used = {t for m in topic_maps for t in m.as_dict().values() if t}
    marked = [(src, found) for src in find_sources(logs) if (found := multiple_publishers(src, used))]
    if not marked:
        return
    src, found = marked[0]
    more = f" (and {len(marked) - 1} more bag(s))" if len(marked) > 1 else ""
    raise ValueError(f"bag {src}: " + ", ".join(f"{t} had {n} publishers" for t, n in sorted(found.items()))
                     + f" while it was recorded (a second bridge or an impostor: their messages interleave)"
                     f"{more}; refusing it (--accept-multiple-publishers trains on it anyway)")


def main(argv: Sequence[str] | None = None) -> int:
    parsed = settings.parse(build_parser(), argv)
    s, model = parsed.get(TrainSettings), parsed.get(settings.ModelChoice)
    try:
        return run(s, model, parsed.config_args, parsed.prog)
    except (DatasetError, ValueError) as exc:
        print(f"protocad-train: error: {exc}", file=sys.stderr)
        return 2
    except (CheckpointWriteError, RanksDiverged) as exc:
        print(f"protocad-train: error: {exc}", file=sys.stderr)
        return 1


def run(s: TrainSettings, model: settings.ModelChoice, config_args: Sequence[str] = (),
        prog: str = "protocad-train") -> int:
    """Train from logs (or resume); under torchrun, this rank's share."""
    return distributed.run_entry_point(model.threads, model.device,
                                       lambda ctx, device: _train(s, model, list(config_args), prog, ctx, device))


def open_logs(s: TrainSettings, cfg, ctx: distributed.DistContext, say: Callable[..., None]) -> MCAPDataset:
    """The dataset over the logs, one topic map per robot namespace; rank 0 fills the cache
    first, the others then reuse it. Refuses bags with several publishers on a topic read and
    logs of the wrong action size (ValueError)."""
    namespaces = list(s.namespace or [None])
    if not s.accept_multiple_publishers:
        refuse_multiple_publishers(s.logs, [TopicMap.parse(s.topic, ns) for ns in namespaces])
    say(f"[train] reading logs: {', '.join(map(str, s.logs))}", flush=True)
    where = "--cache-dir" if s.cache_dir else (
        "$PROTOCAD_CACHE_DIR" if os.environ.get("PROTOCAD_CACHE_DIR") else "default, outside the project")
    say(f"[train] dataset cache (decoded frames, reused across runs): "
        f"{Path(s.cache_dir) if s.cache_dir else default_cache_dir()} ({where}; LRU budget: --cache-budget-gb)",
        flush=True)
    if not ctx.is_main:
        distributed.barrier_if(ctx)
    ds = MCAPDataset(s.logs, topics=TopicMap.parse(s.topic, namespaces[0]), seq_len=cfg.train.seq_len,
                     seed=cfg.train.seed, cache_dir=s.cache_dir, verbose=ctx.is_main,
                     cache_budget_gb=s.cache_budget_gb, image_size=cfg.train.image_size,
                     crop=s.crop or DEFAULT_CROP)
    for ns in namespaces[1:]:   # the same logs, read once more per robot namespace
        ds.add(s.logs, topics=TopicMap.parse(s.topic, ns))
    if ctx.is_main:
        distributed.barrier_if(ctx)
    say(ds.report.summary(), flush=True)
    if ds.num_windows == 0:
        raise DatasetError(f"nothing to train on: no window of {cfg.train.seq_len} steps in the logs "
                           "(see the report above)")
    refuse_test_split(ds, s.accept_test_split, say)
    if cfg.spec.reads_true_context:
        ds.check_true_context(cfg.task)
    n_act = len(task_actuators(cfg.task))
    if ds.action_dim != n_act:
        raise ValueError(f"the logs carry {ds.action_dim}-d actions {ds.action_names} but {cfg.task} has "
                         f"{n_act} actuators: wrong --task, or the action topic maps something else")
    return ds


def _train(s: TrainSettings, model: settings.ModelChoice, config_args: list[str], prog: str,
           ctx: distributed.DistContext, device: str) -> int:
    say = print if ctx.is_main else (lambda *args, **kw: None)
    run_json: dict[str, Any] = {}
    if s.resume:
        run_dir, run_json = runs.resume_run_dir(s.run_dir, need_state=False)
        if not s.logs:   # bags from run.json: only inside the run (others are given again)
            check_logs(run_dir / "run.json", run_dir, run_json.get("logs"))
        s = s.resumed_from(run_json, run_dir / "run.json")
        cfg = runs.load_run_config(run_dir)
    else:
        cfg = model.to_config(config_args, prog)
        plan_prototype_freeze(cfg, 0, s.updates or 1000)   # a refused plan leaves no run directory
        # One directory for every rank (the default name has a time stamp): rank 0's.
        run_dir = Path(distributed.gather_objects(
            str(runs.new_run_dir(s.run_dir, "train", cfg.task, cfg.variant)) if ctx.is_main else None, ctx)[0])
    s = dataclasses.replace(s, checkpoint_every=s.checkpoint_every or 500, log_every=s.log_every or DEFAULT_LOG_EVERY)
    if not s.logs:
        raise ValueError("give --logs PATH... (bag directories, .mcap files or folders of bags)")
    ds = open_logs(s, cfg, ctx, say)
    callbacks = metrics_callbacks(s.rerun, run_dir, "protocad-train")
    rrd = (s.rerun or str(run_dir / "metrics.rrd")) if s.rerun is not None else None
    target = s.updates or 1000
    if not s.resume:
        cfg.train.device = device
    try:   # the one way every trainer CLI opens its run's trainer (resume.py)
        opened = open_trainer(cfg, run_dir, ds, TrainerOpening(
            resume=s.resume, device=device, end_updates=target, precision=model.precision,
            log_every=s.log_every, callbacks=callbacks, dist_ctx=ctx, restart_metrics=True))
    except CheckpointError as exc:
        raise ValueError(str(exc)) from None
    trainer, precision, freeze = opened.trainer, opened.precision, opened.prototype_freeze
    if opened.resumed:
        say(f"[train] resuming {run_dir} at update {trainer.updates} (target {target})", flush=True)
    say(f"[train] {precision.describe()}", flush=True)
    if trainer.dataset.action_dim != trainer.agent.action_dim:
        raise ValueError(f"the logs have {trainer.dataset.action_dim}-d actions but the agent "
                         f"{trainer.agent.action_dim}-d")
    namespaces = [n for n in (s.namespace or []) if n] or None
    run_json.update(kind="train", argv=sys.argv, logs=[str(Path(p).resolve()) for p in s.logs],
                    topics_args=list(s.topic), namespace=namespaces, crop=s.crop,
                    cache_dir=str(Path(s.cache_dir).resolve()) if s.cache_dir else None, task=cfg.task,
                    variant=cfg.variant, preset=cfg.preset, seed=cfg.train.seed, device=device, updates=target,
                    checkpoint_every=s.checkpoint_every, log_every=s.log_every,
                    rerun=str(rrd) if rrd else None, prototype_freeze=freeze, topics=ds.topics.as_dict(), world_size=ctx.world_size,
                    accept_multiple_publishers=s.accept_multiple_publishers,
                    accept_test_split=s.accept_test_split, precision=precision.to_dict(),
                    settings={"train": settings.as_data(s), "model": settings.as_data(model)})
    if ctx.is_main:
        runs.atomic_write_json(run_dir / "run.json", run_json)
    return _train_to(trainer, target, s, cfg, ctx, say)


def _train_to(trainer: Trainer, target: int, s: TrainSettings, cfg, ctx: distributed.DistContext,
              say: Callable[..., None]) -> int:
    """Update to `target` with a progress bar (Ctrl-C: a checkpoint, then exit 0) and report."""
    run_dir = trainer.run_dir
    ranks = (f" ({ctx.world_size} ranks over {ctx.backend}, {trainer.local_batch} sequences each)"
             if ctx.enabled else "")
    say(f"[train] {cfg.task} / {cfg.variant} / {cfg.preset} on {trainer.device}: batch "
        f"{cfg.train.batch_size} x {cfg.train.seq_len}{ranks}, {trainer.updates} -> {target} updates; "
        f"run dir {run_dir}", flush=True)
    t0 = time.monotonic()
    start = trainer.updates
    with console.StopFlag() as stop:
        bar = console.progress(target, initial=trainer.updates, desc="train",
                            disable=True if s.no_progress or not ctx.is_main else None, unit="upd")
        try:
            done = trainer.train(target, stop=stop, checkpoint_every=s.checkpoint_every, bar=bar)
        finally:
            bar.close()
            trainer.close()
    dt = time.monotonic() - t0
    n = trainer.updates - start
    status = "finished" if done else "interrupted"
    say(f"[train] {status} at update {trainer.updates} ({n} updates in {cli_values.format_duration(dt)}"
        f"{f', {n / dt:.2f}/s' if dt > 0 and n else ''})", flush=True)
    say(f"[train] checkpoint: {trainer.checkpoint_path}", flush=True)
    say(f"[train] metrics:    {run_dir / 'metrics.jsonl'}", flush=True)
    say(f"[train] config:     {run_dir / 'config.yaml'}", flush=True)
    if trainer.rank_fingerprints:
        say(f"[train] {ctx.world_size} ranks hold identical weights at update {trainer.updates}: "
            + " ".join(f"{k}={v}" for k, v in trainer.rank_fingerprints[0].items()), flush=True)
    if not done:
        say(f"[train] resume with: protocad-train --run-dir {run_dir} --resume", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
