"""`protocad-online`: the in-process research path (no ROS): vectorized envs -> the same agent
(Policy, batched) -> the same trainer, writing the same MCAP bags as the ROS path.

    protocad-online --task pendulum_swingup --preset small --env-steps 60000 --run-dir runs/pend
    protocad-online --task walker_walk --preset paper --device auto --num-envs 4   # paper protocol
    protocad-online --run-dir runs/pend --resume

Protocol (ProtoCAD Algorithm 1 + "Evaluation protocol"): N random-action prefill episodes
(train.prefill_episodes, paper 2), then C updates (train.collect_interval, paper 100) once
after the prefill and C per collected episode thereafter; evaluation on the test contexts
every --eval-every env steps (paper: 10k, 5 episodes per context); a budget of --env-steps
env steps (paper: 2M; env steps = agent steps x action repeat). Collection samples from the
actor (DreamerPro/DreamerV2: sampled actions, expl_noise 0).

Logs: every env writes each episode to its own bag RUN_DIR/bags/epNNNNNN_envI/ through
trainer.bag.mcap_io.BagWriter with the contract topics, types and stamps of the ROS path (image,
step_info, context, /clock at the observation's sim-time stamp; action and context_features
stamped like the observation they answer, the answer to is_last included), so
trainer.data.dataset reads both paths identically and `protocad-train --logs RUN_DIR/bags` retrains
from them. The replay buffer IS that dataset (disk-backed uint8 store, see trainer/data/dataset.py).

Resume (`--resume`): weights, optimizers, RNG, sampler state and counters come from the last
checkpoint; bags on disk are re-indexed (from the cache). Environments restart with fresh
episodes (a simulator mid-episode is not checkpointed), seeded differently from the first run.
Before the first new episode the resume makes what the interruption cut short: the updates the
episodes on disk are owed and an evaluation that was due (at the env step it was due), so an
interrupted run follows the same schedule as one that never was.

Under torchrun (`torchrun --nproc_per_node N --no-python protocad-online ...`, see
trainer/learn/distributed.py) every rank collects with its own envs (seeded by rank) into its own bags
(`..._rankR`) and replays them, the ranks step in lock-step (same time limit, so their episodes
end together) and average gradients; counters are global (env steps and episodes of all ranks,
so --env-steps is the budget of the whole run and C updates follow each collected episode of
any rank); rank 0 evaluates (the others wait), writes the metrics, run.json and checkpoints.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from protocad_ros.model.config import plan_prototype_freeze
from sim_bridge.contract import topics as T
from trainer import runs, settings
from trainer.data.dataset import MCAPDataset, TopicMap
from trainer.learn import distributed
from trainer.learn.schedule import RunCounters, Schedule
from trainer.learn.resume import open_trainer
from trainer.learn.train import Trainer
from trainer.runs import check_settings_section
from trainer.settings import arg

BAG_QOS = dict(history="keep_last", depth=100, reliability="reliable", durability="volatile")


class EpisodeBagWriter:
    """Writes one env's steps as the ROS path records them: one bag per episode.

    write_observation(obs, stamp) then write_action(action, stamp, features) for every step;
    close() after the answer to is_last (or on shutdown: a partial episode is still valid).
    """

    def __init__(self, bag_dir: Path, action_names: Sequence[str], namespace: str = T.DEFAULT_NAMESPACE,
                 compression: str = "zstd"):
        from trainer.bag import mcap_io

        self._io = mcap_io
        self.bag_dir = Path(bag_dir)
        self.names = list(action_names)
        self.w = mcap_io.BagWriter(self.bag_dir, compression=compression)
        self.t = {k: T.topic_name(namespace, k) for k in (T.IMAGE, T.STEP_INFO, T.CONTEXT, T.ACTION,
                                                           T.CONTEXT_FEATURES)}
        self.t[T.CLOCK] = T.CLOCK
        for rel, name in self.t.items():
            depth = 10 if rel == T.CLOCK else 100
            self.w.add_topic(name, T.TYPES[rel], [mcap_io.qos_profile(**{**BAG_QOS, "depth": depth})])
        self.steps = 0

    def _put(self, rel: str, msg: Any, stamp: int) -> None:
        now = time.time_ns()
        self.w.write(self.t[rel], self._io.encode(T.TYPES[rel], msg), now, now)

    def write_observation(self, obs: Any, stamp: int) -> None:
        new = self._io.new_message
        clock = new(T.TYPES[T.CLOCK])
        T.set_stamp(clock.clock, stamp)
        self._put(T.CLOCK, clock, stamp)
        self._put(T.CONTEXT, T.fill_context(new(T.TYPES[T.CONTEXT]), obs.context, obs.split, stamp), stamp)
        self._put(T.STEP_INFO, T.fill_step_info(new(T.TYPES[T.STEP_INFO]), T.StepInfo(
            float(obs.reward), float(obs.discount), bool(obs.is_first), bool(obs.is_last),
            bool(obs.is_terminal), int(obs.episode), int(obs.step)), stamp), stamp)
        self._put(T.IMAGE, T.fill_image(new(T.TYPES[T.IMAGE]), obs.image, stamp), stamp)
        self.steps += 1

    def write_action(self, action: np.ndarray, stamp: int, features: Any = None) -> None:
        new = self._io.new_message
        self._put(T.ACTION, T.fill_action(new(T.TYPES[T.ACTION]), np.asarray(action, np.float64),
                                          self.names, stamp), stamp)
        if features is not None and getattr(features, "u", None) is not None and np.size(features.u):
            self._put(T.CONTEXT_FEATURES, T.fill_context_features(
                new(T.TYPES[T.CONTEXT_FEATURES]), np.asarray(features.u), np.asarray(features.w),
                np.asarray(features.e), stamp), stamp)

    def close(self) -> None:
        self.w.close()


def _feature_row(features: Any, i: int) -> Any:
    if features is None:
        return None

    class _F:
        pass

    f = _F()
    f.u, f.w, f.e = features.u[i], features.w[i], features.e[i]
    return f


def bag_name(bags_dir: Path, index: int, env: int, attempt: int, rank_tag: str = "") -> str:
    """A new episode's bag directory name: its index, env, and the attempt (invocation) that
    writes it, so an attempt killed before its checkpoint never collides with the next one;
    a name already on disk gets a suffix (a bag is never overwritten)."""
    name = f"ep{index:06d}_env{env}_a{attempt}{rank_tag}"
    k = 1
    while (bags_dir / name).exists():
        name, k = f"ep{index:06d}_env{env}_a{attempt}{rank_tag}_{k}", k + 1
    return name


def data_counts(ds: MCAPDataset) -> tuple[int, int]:
    """(agent steps, complete episodes) in the replayed bags: the counters a resume continues
    from. A step is a row after an episode's first observation; an episode counts once it has
    its last one (a bag cut by a kill counts its steps, not as an episode)."""
    steps = episodes = 0
    for e in ds.episodes():
        steps += int(e["length"]) - (1 if e["has_first"] else 0)
        episodes += int(e["has_last"])
    return steps, episodes


def leftovers(run_dir: Path, cache_dir: Path) -> list[Path]:
    """Remove what killed attempts leave behind: temporaries of atomic writes in the run
    directory, half-built dataset cache entries, and the disk reserves of bags that were never
    closed. Returns what was removed."""
    import shutil

    from protocad_ros.atomic import remove_stale_temporaries

    removed = list(remove_stale_temporaries(run_dir / "metrics.jsonl"))
    removed += remove_stale_temporaries(run_dir / "run.json")
    for tmp in sorted(Path(cache_dir).glob("*.tmp-*")) if Path(cache_dir).is_dir() else []:
        pid = tmp.name.rsplit(".tmp-", 1)[-1]
        if pid.isdigit() and int(pid) != os.getpid():
            shutil.rmtree(tmp, ignore_errors=True) if tmp.is_dir() else tmp.unlink(missing_ok=True)
            removed.append(tmp)
    for reserve in sorted((run_dir / "bags").glob("*/.protocad-reserve")):
        reserve.unlink(missing_ok=True)
        removed.append(reserve)
    for bag in sorted(p for p in (run_dir / "bags").glob("*") if p.is_dir()):
        if not any(bag.glob("*.mcap")):   # killed before its first byte: it holds nothing
            shutil.rmtree(bag, ignore_errors=True)
            removed.append(bag)
    return removed


def close_quietly(steps) -> list[tuple[str, Exception]]:
    """Run every (what, clean-up step), each even if another failed (a full disk fails them
    all); the (what, error) pairs, for the caller to report without losing the error that
    stopped the run."""
    errors = []
    for what, step in steps:
        try:
            step()
        except Exception as exc:  # noqa: BLE001 - reported by the caller, one line each
            errors.append((what, exc))
    return errors


# ---------------------------------------------------------------------- settings
def parse_context_arg(text: str) -> dict[str, float]:
    from trainer.learn.evaluate import parse_context

    try:
        return parse_context(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


@dataclass
class OnlineSettings:
    """protocad-online's protocol (Algorithm 1 and the evaluation protocol) and run options."""

    env_steps: int = arg(2_000_000, group="protocol")
    """budget in env steps (agent steps x action repeat); paper: 2M"""
    num_envs: int = arg(1, group="protocol")
    """training envs (worker processes)"""
    prefill_episodes: int | None = arg(None, group="protocol")
    """N (default train.prefill_episodes = 2)"""
    updates_per_episode: int | None = arg(None, group="protocol")
    """C (default train.collect_interval = 100)"""
    time_limit: int | None = arg(None, group="protocol")
    """env steps per episode (default train.time_limit = 1000)"""
    eval_every: int = arg(10_000, group="protocol")
    """env steps between evaluations (0: only at the end)"""
    eval_episodes: int = arg(2, group="protocol")
    """episodes per context of the periodic evaluations"""
    final_episodes: int = arg(5, group="protocol")
    """episodes per context of the final evaluation and --random-baseline (the paper's 5)"""
    eval_max_contexts: int = arg(8, group="protocol")
    """periodic evaluations use a fixed subset of K contexts, stratified over the parameters
    (every m and every d equally often; sim_bridge.contract.contexts.TaskSpec.stratified); 0: all.
    8 contexts x 2 episodes = 1.6x the training interaction every 10k env steps, where all
    64 x 5 of walker were 32x"""
    final_train_contexts: bool = arg(False, group="protocol")
    """also evaluate the final agent on every training context (--final-episodes each, into
    eval/final_train.json): the other half of the unseen/train ratio"""
    final_max_contexts: int = arg(0, group="protocol")
    """the final evaluation (and --random-baseline): 0 = every context of the split, the paper
    protocol; K = the stratified subset of K"""
    wall_budget: float | None = arg(None, type=runs.parse_duration, metavar="DURATION", group="protocol")
    """also stop once the run's training wall time (carried across resumes) reaches this, e.g.
    5400, 90m, 1h30m; then the final evaluation, checkpoint and curves are written as at the
    env-step budget"""
    train_context: dict | None = arg(None, type=parse_context_arg, metavar="K=V[,K=V]", group="protocol")
    """train on this one context of the train split instead of a draw per episode (e.g. m=1:
    the standard, unrandomized task)"""
    eval_split: str = arg("test", choices=("test", "train"), group="protocol")
    """split of the evaluation contexts (paper: test = unseen)"""
    eval_contexts: list[dict] | None = arg(None, type=parse_context_arg, nargs="+", metavar="K=V[,K=V]",
                                           group="protocol")
    """evaluate on exactly these contexts of --eval-split (default: the split's grid)"""
    eval_workers: int = arg(-1, group="protocol")
    """evaluation env processes (0: in this process; -1: auto)"""
    random_baseline: bool = arg(False, group="protocol")
    """also evaluate the uniform random policy once (same contexts and episodes)"""
    run_dir: str | None = arg(None, group="run")
    """output directory (default runs/online-TASK-VARIANT-TIME)"""
    resume: bool = arg(False, group="run")
    """continue RUN_DIR from its checkpoint"""
    checkpoint_every: int = arg(1000, group="run")
    """updates between checkpoints (also after every evaluation and at the end)"""
    log_every: int = arg(10, group="run")
    """updates per metrics line"""
    cache_dir: str | None = arg(None, group="run")
    """dataset cache (default RUN_DIR/cache)"""
    rerun: str | None = arg(None, nargs="?", const="", metavar="RRD", group="run")
    """log scalars and evaluations to a rerun recording (default RUN_DIR/metrics.rrd)"""
    no_progress: bool = arg(False, group="run")
    """no progress bar"""

    def config_overrides(self) -> dict[str, Any]:
        """The protocol's shortcut flags, as config settings."""
        pairs = (("train.prefill_episodes", self.prefill_episodes),
                 ("train.collect_interval", self.updates_per_episode), ("train.time_limit", self.time_limit))
        return {k: v for k, v in pairs if v is not None}


#: Settings a resume takes from run.json's `protocol` when the run predates `settings`.
PROTOCOL_KEYS = ("env_steps", "num_envs", "eval_every", "eval_episodes", "eval_max_contexts",
                 "final_max_contexts", "final_episodes", "wall_budget", "train_context", "eval_split",
                 "eval_contexts")


def build_parser():
    return settings.settings_parser(
        "protocad-online",
        "In-process training (no ROS): vectorized envs on the training contexts -> agent -> "
        "trainer, with the paper's protocol (prefill N random episodes, C updates per collected "
        "episode, evaluation on the test contexts every --eval-every env steps) and the same "
        "MCAP bags as the ROS path.",
        [("model / config", settings.ModelChoice), (None, OnlineSettings)],
        # the research path uses a GPU when there is one, and bf16 where the hardware has it
        defaults={"device": "auto", "precision": "auto"})


def parse_args(argv: Sequence[str] | None = None) -> tuple[OnlineSettings, settings.ModelChoice, settings.Parsed]:
    """The command line as (protocol, model choice); with --resume, the run's saved settings
    replaced by the flags given."""
    parser = build_parser()
    parsed = settings.parse(parser, argv)
    s = parsed.get(OnlineSettings)
    model = parsed.get(settings.ModelChoice)
    if s.resume and s.run_dir:
        got = settings.resumed_from_run(s.run_dir, parsed, parser,
                                        {"online": OnlineSettings, "model": settings.ModelChoice})
        s, model = got["online"], got["model"]
    return s, model, parsed


def main(argv: Sequence[str] | None = None) -> int:
    try:
        s, model, parsed = parse_args(argv)
    except ValueError as exc:   # a run.json edited out of shape
        print(f"protocad-online: error: {exc}", file=sys.stderr)
        return 2
    from protocad_ros.checkpoint import CheckpointError
    from trainer.learn.train import CheckpointWriteError, RanksDiverged

    try:
        return run(s, model, parsed.config_args, parsed.prog, parsed.argv)
    except (ValueError, CheckpointError) as exc:   # CheckpointError: the run's checkpoint is unusable
        print(f"protocad-online: error: {exc}", file=sys.stderr)
        return 2
    except (CheckpointWriteError, RanksDiverged, mcap_io_errors(), cache_errors(), OSError) as exc:
        # a full disk (cache, bags, checkpoints, metrics) is one line with the path; the run
        # resumes once space is freed (protocad-online --resume)
        where = (f" ({exc.filename})" if isinstance(exc, OSError) and exc.filename
                 and str(exc.filename) not in str(exc) else "")
        print(f"protocad-online: error: {exc}{where}", file=sys.stderr)
        if s.run_dir:
            print(f"protocad-online: continue with: protocad-online --run-dir {s.run_dir} --resume",
                  file=sys.stderr)
        return 1


def mcap_io_errors() -> type:
    from trainer.bag.mcap_io import BagWriteError

    return BagWriteError


def cache_errors() -> type:
    from trainer.data.records import CacheWriteError

    return CacheWriteError


# ---------------------------------------------------------------------- the run, in parts
class EnvBags:
    """One bag per episode for each env, named by bag_name; the run's counters advance as
    steps and episodes are recorded (global under torchrun: each rank adds world_size)."""

    def __init__(self, bags_dir: Path, n: int, action_names: Sequence[str], dt_ns: int, attempt: int,
                 rank_tag: str, counters: RunCounters, action_repeat: int, world: int):
        self.bags_dir, self.names, self.dt_ns = bags_dir, list(action_names), dt_ns
        self.attempt, self.rank_tag, self.c, self.R, self.world = attempt, rank_tag, counters, action_repeat, world
        self.writers: list[EpisodeBagWriter | None] = [None] * n
        self.ticks = [0] * n
        self.returns = np.zeros(n)

    def record(self, i: int, obs: Any, action: np.ndarray, features: Any) -> Path | None:
        """Write env i's observation and the action answering it; the bag's directory when
        this observation ended its episode."""
        c, w = self.c, self.writers
        stamp = self.ticks[i] * self.dt_ns
        if obs.is_first or w[i] is None:
            if w[i] is not None:
                w[i].close()
            w[i] = EpisodeBagWriter(self.bags_dir / bag_name(self.bags_dir, c.bags, i, self.attempt, self.rank_tag),
                                    self.names)
            c.bags += 1
            self.returns[i] = 0.0
        w[i].write_observation(obs, stamp)
        w[i].write_action(action, stamp, features)
        self.ticks[i] += 1
        if not obs.is_first:
            self.returns[i] += obs.reward
            c.agent_steps += self.world
            c.env_steps += self.R * self.world
        if not obs.is_last:
            return None
        w[i].close()
        done, w[i] = w[i].bag_dir, None
        c.episodes += self.world
        c.last_return = float(self.returns[i])
        return done

    def closers(self) -> list[tuple[str, Any]]:
        return [("closing the bag", w.close) for w in self.writers if w is not None]


class Evaluator:
    """Rank 0 evaluates the current agent (the others wait) and logs the result: eval/TAG.json,
    a line of eval.jsonl, the metrics' eval row and the rerun hooks."""

    def __init__(self, trainer: Trainer, task: str, variant: str, split: str, seed: int, device: str,
                 workers: int, counters: RunCounters, ctx: distributed.DistContext, run_dir: Path,
                 progress: bool | None):
        self.trainer, self.task, self.variant, self.split, self.seed = trainer, task, variant, split, seed
        self.device, self.workers, self.c, self.ctx, self.progress = device, workers, counters, ctx, progress
        self.run_dir, self.eval_dir = run_dir, run_dir / "eval"

    def __call__(self, tag: str, contexts, episodes: int, stop: runs.StopFlag) -> Any:
        from trainer.learn.evaluate import evaluate_checkpoint, format_table

        if not self.ctx.is_main:   # rank 0 evaluates; the others wait for it
            distributed.barrier_if(self.ctx)
            return None
        res = evaluate_checkpoint(None, agent=self.trainer.agent, task=self.task, episodes=episodes,
                                  contexts=contexts, split=self.split, seed=self.seed, device=self.device,
                                  workers=self.workers, counters=self.c.as_dict(), progress=self.progress,
                                  stop=stop)
        res.policy = f"{self.variant}@{self.c.env_steps}"
        distributed.barrier_if(self.ctx)
        if stop.stop:
            return res
        self.log(res, tag)
        print(format_table(res), flush=True)
        return res

    def random_baseline(self, contexts, episodes: int, time_limit: int, stop: runs.StopFlag) -> None:
        """The uniform random policy once per run (eval/random.json)."""
        from trainer.learn.evaluate import evaluate_checkpoint, format_table

        if not self.ctx.is_main or (self.eval_dir / "random.json").exists():
            return
        rnd = evaluate_checkpoint(None, task=self.task, episodes=episodes, contexts=contexts, split=self.split,
                                  seed=self.seed, workers=self.workers, time_limit=time_limit,
                                  progress=self.progress, stop=stop)
        if not stop.stop:
            runs.atomic_write_json(self.eval_dir / "random.json", rnd.to_dict())
            print(format_table(rnd), flush=True)

    def on_train_contexts(self, episodes: int, stop: runs.StopFlag) -> Any:
        """The final agent on every context of the training split: eval/final_train.json
        (outside eval.jsonl, whose rows are the test curve)."""
        from trainer.learn.evaluate import evaluate_checkpoint, format_table, select_contexts

        if not self.ctx.is_main:
            distributed.barrier_if(self.ctx)
            return None
        res = evaluate_checkpoint(None, agent=self.trainer.agent, task=self.task, episodes=episodes,
                                  contexts=select_contexts(self.task, "train", None, 0), split="train",
                                  seed=self.seed, device=self.device, workers=self.workers,
                                  counters=self.c.as_dict(), progress=self.progress, stop=stop)
        res.policy = f"{self.variant}@{self.c.env_steps}"
        distributed.barrier_if(self.ctx)
        if not stop.stop:
            d = res.to_dict()
            d.update(env_steps=self.c.env_steps, updates=self.trainer.updates, tag="final_train")
            runs.atomic_write_json(self.eval_dir / "final_train.json", d)
            print(format_table(res), flush=True)
        return res

    def log(self, result: Any, tag: str) -> None:
        t, env_steps = self.trainer, self.c.env_steps
        d = result.to_dict()
        d.update(env_steps=env_steps, updates=t.updates, tag=tag)
        runs.atomic_write_json(self.eval_dir / f"{tag}.json", d)
        per_context = {" ".join(f"{k}={v:g}" for k, v in pc["context"].items()): pc["mean_return"]
                       for pc in d["per_context"]}
        with open(self.run_dir / "eval.jsonl", "a") as f:
            f.write(json.dumps({"env_steps": env_steps, "updates": t.updates, "tag": tag, "policy": d["policy"],
                                "mean_return": d["mean_return"], "per_context": per_context}) + "\n")
        t.metrics.log(t.updates, {"eval_return": d["mean_return"]}, kind="eval", tag=tag, env_steps=env_steps)
        for hook in t.metrics.eval_hooks():
            try:
                hook.log_eval(t.updates, d)
            except Exception as exc:  # noqa: BLE001 - a viewer's failure never stops the run
                print(f"[online] rerun eval logging failed: {exc}", file=sys.stderr)


def run(s: OnlineSettings, model: settings.ModelChoice, config_args: Sequence[str] = (),
        prog: str = "protocad-online", argv: Sequence[str] | None = None) -> int:
    """A whole online run (or its resume); under torchrun, this rank's share of it."""
    return distributed.run_entry_point(
        model.threads, model.device,
        lambda ctx, device: OnlineRun(s, model, ctx, device, list(config_args), prog, argv).run())


class OnlineRun:
    """Algorithm 1 in one process: prepare the run directory, replay and trainer, then collect,
    train on schedule and evaluate until the budget; every part resumable."""

    def __init__(self, s: OnlineSettings, model: settings.ModelChoice, ctx: distributed.DistContext,
                 device: str, config_args: list[str], prog: str, argv: Sequence[str] | None):
        self.s, self.model, self.ctx, self.device = s, model, ctx, device
        self.config_args, self.prog = config_args, prog
        self.argv = list(sys.argv[1:] if argv is None else argv)
        self.main_rank, self.world = ctx.is_main, ctx.world_size
        self.say = print if self.main_rank else (lambda *args, **kw: None)

    # ------------------------------------------------------------------ preparation
    def _open_run_dir(self) -> None:
        s, ctx = self.s, self.ctx
        self.run_json: dict[str, Any] = {}
        if s.resume:
            # A run killed before its first checkpoint still resumes: from its config and its bags.
            self.run_dir, self.run_json = runs.resume_run_dir(s.run_dir, need_checkpoint=False)
            self.cfg = runs.load_run_config(self.run_dir)
            if "settings" not in self.run_json:   # a run from before settings were saved
                proto = self.run_json.get("protocol") or {}
                if not isinstance(proto, dict):
                    raise ValueError(f"--resume: {self.run_dir / 'run.json'}: 'protocol' is not a mapping")
                check_settings_section(self.run_dir / "run.json", "protocol", OnlineSettings,
                                       {k: proto[k] for k in PROTOCOL_KEYS if k in proto})
                defaults = OnlineSettings()
                self.s = s = dataclasses.replace(s, **{k: proto[k] for k in PROTOCOL_KEYS if k in proto
                                                       and getattr(s, k) == getattr(defaults, k)})
        else:
            self.cfg = self.model.to_config(self.config_args, self.prog, s.config_overrides())
            self.cfg.train.device = self.device
            planned = self._plan(self.cfg).planned_updates(s.env_steps, self.cfg.train.time_limit, s.num_envs * self.world)
            # before the run directory exists: a refused plan leaves nothing behind
            plan_prototype_freeze(self.cfg, 0, planned)
            self.run_dir = Path(distributed.gather_objects(   # rank 0's (the default name has a stamp)
                str(runs.new_run_dir(s.run_dir, "online", self.cfg.task, self.cfg.variant))
                if self.main_rank else None, ctx)[0])
            if self.main_rank:
                self.run_dir.mkdir(parents=True, exist_ok=True)
                self.cfg.save(self.run_dir / "config.yaml")
            distributed.barrier_if(ctx)
        self.schedule = self._plan(self.cfg)
        self.bags_dir = self.run_dir / "bags"
        self.bags_dir.mkdir(parents=True, exist_ok=True)
        self.cache_dir = Path(s.cache_dir) if s.cache_dir else self.run_dir / "cache"
        (self.run_dir / "eval").mkdir(exist_ok=True)
        if s.train_context is not None:
            from sim_bridge.contract.contexts import get_task

            self.s = dataclasses.replace(s, train_context=get_task(self.cfg.task).validate(s.train_context, "train"))

    def _plan(self, cfg) -> Schedule:
        tr = cfg.train
        return Schedule(N=tr.prefill_episodes, C=tr.collect_interval, eval_every=self.s.eval_every)

    def _write_run_json(self) -> None:
        from trainer.provenance import code_version, stale_install

        if self.main_rank and (warning := stale_install()):
            print(f"[online] warning: {warning}", file=sys.stderr, flush=True)
        s, tr, rj = self.s, self.cfg.train, self.run_json
        versions, version = list(rj.get("code_versions", [])), code_version()
        if version not in versions:   # every invocation's code, resumes included
            versions.append(version)
        runs.record_invocation(rj, s.resume, self.argv)
        rj.update(kind="online", code_versions=versions, task=self.cfg.task, variant=self.cfg.variant,
                  preset=self.cfg.preset, seed=tr.seed, device=self.device,
                  settings={"online": settings.as_data(s), "model": settings.as_data(self.model)},
                  protocol={"env_steps": s.env_steps, "num_envs": s.num_envs, "prefill_episodes": tr.prefill_episodes,
                            "updates_per_episode": tr.collect_interval, "action_repeat": tr.action_repeat,
                            "time_limit": tr.time_limit, "eval_every": s.eval_every,
                            "eval_episodes": s.eval_episodes, "eval_max_contexts": s.eval_max_contexts,
                            "final_max_contexts": s.final_max_contexts, "final_episodes": s.final_episodes,
                            "wall_budget": s.wall_budget, "train_context": s.train_context,
                            "eval_split": s.eval_split, "eval_contexts": s.eval_contexts, "world_size": self.world,
                            "env_draws": "per_episode"})
        if self.main_rank:
            runs.atomic_write_json(self.run_dir / "run.json", rj)

    def _open_replay(self) -> None:
        """The replay (the run's own bags, its cache as the buffer) and the trainer, restored
        from the checkpoint when there is one; the counters from the data on a resume."""
        s, ctx, tr = self.s, self.ctx, self.cfg.train
        # The run's own cache is its replay buffer: every entry is in use, no budget applies.
        self.ds = MCAPDataset([], topics=TopicMap(), seq_len=tr.seq_len, seed=tr.seed, cache_dir=self.cache_dir,
                              cache_budget_gb=None if s.cache_dir else 0)
        if self.main_rank and s.resume:
            for left in leftovers(self.run_dir, self.cache_dir):
                self.say(f"[online] removed {left}, left by an interrupted attempt", flush=True)
        distributed.barrier_if(ctx)
        all_bags = sorted(p for p in self.bags_dir.iterdir() if p.is_dir())
        if all_bags[ctx.rank::self.world]:   # each rank a share, whatever the ranks that wrote them
            self.ds.add(all_bags[ctx.rank::self.world])
        from trainer.viz.rerun_log import metrics_callbacks

        callbacks = metrics_callbacks(s.rerun, self.run_dir, "protocad-online")
        opened = open_trainer(self.cfg, self.run_dir, self.ds, resume=s.resume, device=self.device,
                              end_updates=self.schedule.planned_updates(s.env_steps, tr.time_limit,
                                                                        s.num_envs * self.world),
                              precision=self.model.precision, log_every=s.log_every, callbacks=callbacks,
                              dist_ctx=ctx, restart_metrics=True)
        self.trainer = opened.trainer
        self.c = (RunCounters.from_dict(self.trainer.counters) if opened.resumed
                  else RunCounters(next_eval=self.schedule.first_eval()))
        self.trainer.progress = self.c
        if opened.prototype_freeze is not None:
            self.say(f"[online] prototypes frozen for the first {opened.prototype_freeze:,} updates", flush=True)
        self.run_json["precision"] = opened.precision.to_dict()
        if s.resume:
            # The data is the truth: every bag on disk counts, also those written after the last
            # checkpoint (their updates are made up by the schedule, which counts from episodes).
            steps, episodes = (sum(x) for x in zip(*distributed.gather_objects(data_counts(self.ds), ctx)))
            c = self.c
            c.agent_steps, c.env_steps, c.episodes, c.bags = steps, steps * tr.action_repeat, episodes, len(all_bags)
            c.prefill_done, c.resumes = int(self.schedule.prefilled(episodes)), c.resumes + 1
            self.say(f"[online] resuming {self.run_dir}: {c.env_steps} env steps, {c.episodes} episodes "
                     f"in {len(all_bags)} bags, {self.trainer.updates} updates"
                     + ("" if opened.resumed else " (no checkpoint yet: from the bags)"), flush=True)

    def _evaluation(self) -> None:
        from trainer.learn.evaluate import select_contexts

        s, task = self.s, self.cfg.task
        workers = s.eval_workers if s.eval_workers >= 0 else (0 if (os.cpu_count() or 1) <= 2 else
                                                              min(16, (os.cpu_count() or 2) - 1))
        self.periodic_contexts = select_contexts(task, s.eval_split, s.eval_contexts, s.eval_max_contexts)
        self.final_contexts = select_contexts(task, s.eval_split, s.eval_contexts, s.final_max_contexts)
        self.evaluate = Evaluator(self.trainer, task, self.cfg.variant, s.eval_split, self.cfg.train.seed + 7,
                                  self.device, workers, self.c, self.ctx, self.run_dir,
                                  False if s.no_progress else None)

    def _start_envs(self):
        """The training envs and the rollout that asks, before every step, who acts: the
        prefill's random policy, then the agent (sampling, as DreamerV2 collects)."""
        from protocad_ros.policy import Policy
        from sim_bridge.sim.rollout import RandomPolicy, continuing_rollout
        from sim_bridge.sim.vector import VectorEnv

        s, tr, c = self.s, self.cfg.train, self.c
        # Episode-keyed draws: every run of a seed (each variant of a paired comparison, a
        # resumed run) meets the same contexts and initial states in the same episodes.
        seed = distributed.rank_seed(tr.seed * 1000, self.ctx.rank)
        self.venv = VectorEnv(self.cfg.task, s.num_envs, split="train", seed=seed, action_repeat=tr.action_repeat,
                              render_quality=tr.render_quality, time_limit=tr.time_limit,
                              image_size=tr.image_size, context=s.train_context,
                              first_episode=c.episodes // (s.num_envs * self.world))
        random_policy = RandomPolicy(self.venv.action_dim, seed=tr.seed * 1_000_003 + c.episodes)
        agent_policy = Policy(self.trainer.agent, device=self.device, mode="sample",
                              exploration_noise=tr.expl_noise, seed=tr.seed + c.episodes)
        agent_policy.reset(s.num_envs)
        attempt = len(self.run_json.get("resumes_argv", []))   # this invocation's number, unique per run
        self.bags = EnvBags(self.bags_dir, s.num_envs, self.venv.action_names, int(round(self.venv.control_dt * 1e9)),
                            attempt, f"_rank{self.ctx.rank}" if self.ctx.enabled else "", c, tr.action_repeat,
                            self.world)
        return continuing_rollout(self.venv, lambda: random_policy if self.prefilling() else agent_policy)

    def _announce(self) -> None:
        s, cfg, tr, ctx = self.s, self.cfg, self.cfg.train, self.ctx
        wall = f", wall budget {runs.fmt_seconds(s.wall_budget)}" if s.wall_budget else ""
        self.say(f"[online] {cfg.task} / {cfg.variant} / {cfg.preset} on {self.device}: {s.num_envs} env(s)"
                 + (f" on each of {self.world} ranks ({ctx.backend})" if ctx.enabled else "") + ", "
                 f"budget {s.env_steps} env steps{wall}, prefill {tr.prefill_episodes} episodes, "
                 f"C={tr.collect_interval}, eval every {s.eval_every} env steps on {len(self.periodic_contexts)} "
                 f"{s.eval_split} contexts; {runs.torch_threads()} torch thread(s); run dir {self.run_dir}",
                 flush=True)
        self.say(f"[online] {self.trainer.agent.precision.describe()}", flush=True)

    # ------------------------------------------------------------------ Algorithm 1
    def prefilling(self) -> bool:
        return not self.schedule.prefilled(self.c.episodes) and not self.c.prefill_done

    def _stopped(self, stop: runs.StopFlag) -> bool:   # collective under torchrun: every rank decides the same
        return distributed.any_rank(stop.stop, self.ctx)

    def _keep_going(self, stop: runs.StopFlag) -> bool:
        out_of_time = bool(self.s.wall_budget) and self.trainer.metrics.wall_time >= self.s.wall_budget
        return self.c.env_steps < self.s.env_steps and not distributed.any_rank(stop.stop or out_of_time, self.ctx)

    def _after_episodes(self, finished: list[Path], stop: runs.StopFlag, bar) -> None:
        """Episodes ended: replay them, train up to the schedule's target, evaluate when due."""
        s, c, sched, trainer = self.s, self.c, self.schedule, self.trainer
        self.ds.add(finished)
        if sched.prefilled(c.episodes):
            c.prefill_done = 1
        target = sched.target_updates(c.episodes - sched.N) if c.prefill_done else 0
        if target > trainer.updates and self.ds.num_windows:
            bar.set_description(f"train (ep {c.episodes}, return {c.last_return:.0f})")
            trainer.train(target, stop=stop, checkpoint_every=s.checkpoint_every, save=False)
            bar.set_description("env steps")
        # at the budget the final evaluation comes instead
        if sched.eval_due(c.env_steps, c.next_eval) and not self._stopped(stop) and c.env_steps < s.env_steps:
            self.evaluate(f"eval_{c.env_steps:08d}", self.periodic_contexts, s.eval_episodes, stop)
            if not self._stopped(stop):   # cut short, it stays due: the resume makes it
                c.next_eval = sched.next_eval_after(c.env_steps, c.next_eval)
                c.evals += 1
                trainer.save()

    def _collect_and_train(self, stream, stop: runs.StopFlag) -> str:
        """The loop: step every env, record, and after each finished episode train and evaluate
        on schedule. Returns how it ended: interrupted, finished (env steps) or wall_budget."""
        c, s = self.c, self.s
        bar = runs.progress(s.env_steps, initial=c.env_steps, desc="env steps",
                            disable=True if s.no_progress or not self.main_rank else None, unit="step")
        if s.resume:
            # What the interruption cut short comes first: the updates the episodes on disk are
            # owed and an evaluation still due, before the next episode is collected, so the
            # run's schedule is the one it would have had without the interruption. At the
            # budget too: the final evaluation is of the agent of all its updates.
            self._after_episodes([], stop, bar)
        while self._keep_going(stop):
            obs, actions, feats = next(stream)
            prefill, steps_before = self.prefilling(), c.env_steps
            finished = [bag for i, o in enumerate(obs)
                        if (bag := self.bags.record(i, o, actions[i], _feature_row(feats, i))) is not None]
            bar.update(c.env_steps - steps_before)
            for bag in finished:   # one training-return row per episode
                self.trainer.metrics.log(self.trainer.updates, {"train_return": c.last_return}, kind="episode",
                                         env_steps=c.env_steps, episodes=c.episodes, prefill=bool(prefill))
            if finished:
                self._after_episodes(finished, stop, bar)
            if self._stopped(stop):
                break
        bar.close()
        if self._stopped(stop):
            return "interrupted"
        return "finished" if c.env_steps >= s.env_steps else "wall_budget"

    def run(self) -> int:
        self._open_run_dir()
        self._write_run_json()
        self._open_replay()
        self._evaluation()
        t_start = time.monotonic()
        self.venv, self.bags = None, None
        status, cause = "failed", None   # until the loop ends normally or is stopped
        with runs.StopFlag() as stop:
            try:
                if self.s.random_baseline:
                    self.evaluate.random_baseline(self.final_contexts, self.s.final_episodes,
                                                  self.cfg.train.time_limit, stop)
                stream = self._start_envs()
                self._announce()
                status = self._collect_and_train(stream, stop)
                if status != "interrupted":
                    final = self.evaluate("final", self.final_contexts, self.s.final_episodes, stop)
                    if self.main_rank and not stop.stop:
                        print(f"[online] final mean return on {len(final.per_context)} test contexts: "
                              f"{final.mean:.1f}", flush=True)
                    if self.s.final_train_contexts and not stop.stop:
                        self.evaluate.on_train_contexts(self.s.final_episodes, stop)
                    if stop.stop:   # an evaluation cut short: the resume makes it
                        status = "interrupted"
            except BaseException as exc:
                cause = exc   # the real error: the clean-up below must neither hide nor replace it
                raise
            finally:
                self._close(status, cause)
        self._report(status, time.monotonic() - t_start)
        return 0

    # ------------------------------------------------------------------ the end
    def _close(self, status: str, cause: BaseException | None) -> None:
        """Close bags and envs, save, write run.json's result: each step even if another failed
        (a full disk fails them all); the error that stopped the run stays the one raised."""
        trainer, c = self.trainer, self.c
        errors = close_quietly([*(self.bags.closers() if self.bags else []),
                                *([("closing the envs", self.venv.close)] if self.venv is not None else [])])
        if trainer.updates or status == "interrupted":
            errors += close_quietly([("saving the checkpoint", trainer.save)])
        errors += close_quietly([("closing the metrics", trainer.close)])
        result = {"status": status, "env_steps": c.env_steps, "updates": trainer.updates, "episodes": c.episodes,
                  "wall_time": round(trainer.metrics.wall_time, 1), "precision": trainer.agent.precision.precision,
                  "resumes": c.resumes, "prototype_freeze": trainer.prototype_freeze}
        if cause is not None and not isinstance(cause, (KeyboardInterrupt, SystemExit)):
            result["error"] = f"{type(cause).__name__}: {cause}"
        self.run_json["result"] = result
        if self.main_rank:
            path = self.run_dir / "run.json"
            errors += close_quietly([(f"writing {path}", lambda: runs.atomic_write_json(path, self.run_json))])
        for what, err in errors:
            print(f"[online] while stopping, {what}: {err}", file=sys.stderr, flush=True)
        if errors and cause is None:
            raise errors[0][1]

    def _report(self, status: str, seconds: float) -> None:
        c, run_dir = self.c, self.run_dir
        self.say(f"[online] {status}: {c.env_steps} env steps, {c.episodes} episodes, {self.trainer.updates} "
                 f"updates in {runs.fmt_seconds(seconds)}", flush=True)
        self.say(f"[online] run dir:    {run_dir}\n[online] checkpoint: {self.trainer.checkpoint_path}\n"
                 f"[online] bags:       {self.bags_dir} ({len(self.ds.stores)} episodes)\n"
                 f"[online] metrics:    {run_dir / 'metrics.jsonl'}\n"
                 f"[online] eval:       {run_dir / 'eval.jsonl'}, {run_dir / 'eval'}", flush=True)
        if status == "interrupted":
            self.say(f"[online] resume with: protocad-online --run-dir {run_dir} --resume", flush=True)


if __name__ == "__main__":
    sys.exit(main())
