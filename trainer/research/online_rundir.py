"""An online run's settings and its run directory: OnlineSettings (the command line's protocol
and run options, as run.json keeps them), opening a new run directory or the one --resume
continues (config.yaml, run.json), and the episode bags written into it: one MCAP bag per
episode and env with the ROS path's topics, types and stamps (so trainer.data reads both paths
alike and `protocad-train --logs RUN_DIR/bags` retrains from them), the counts a resume reads
back from them, and the leftovers a killed attempt leaves. No ROS."""
from __future__ import annotations

import argparse
import dataclasses
import os
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from protocad_ros.atomic import file_sha256, remove_stale_temporaries
from protocad_ros.checkpoint.files import existing_checkpoint_file
from protocad_ros.model.config import plan_prototype_freeze
from sim_bridge.contract import topics as T
from sim_bridge.contract.contexts import get_task
from trainer import cli_values, runs, settings
from trainer.bag.rosmsg import encode, new_message
from trainer.bag.writer import BagWriter, qos_profile
from trainer.data.dataset import MCAPDataset
from trainer.learn import distributed
from trainer.learn.evaluate import parse_context
from trainer.learn.init_policy import policy_config
from trainer.learn.schedule import RunCounters, Schedule
from trainer.provenance import code_version, stale_install
from trainer.run_input import check_settings_section
from trainer.settings import arg


def parse_context_arg(text: str) -> dict[str, float]:
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
    wall_budget: float | None = arg(None, type=cli_values.parse_duration, metavar="DURATION", group="protocol")
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
    init_policy: str | None = arg(None, metavar="POLICY_PT", group="run")
    """start from this policy file's weights (a shipped policy, a run's checkpoint) instead of
    fresh ones: its config is the run's, training options on top (--set, --seed, ...); fresh
    optimizers and update counter; the protocol is the same (the prefill's episodes are still
    random). Only context.projector_input may change its networks (the projector then starts
    fresh): trainer/learn/init_policy.py"""
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


@dataclass
class OnlineRunDir:
    """An opened run directory: the settings the run goes on with (a resume's old-style protocol
    and a checked --train-context applied), its config, run.json so far and its schedule."""

    s: OnlineSettings
    cfg: Any
    path: Path
    run_json: dict[str, Any]
    schedule: Schedule

    @property
    def bags_dir(self) -> Path:
        return self.path / "bags"

    @property
    def cache_dir(self) -> Path:
        return Path(self.s.cache_dir) if self.s.cache_dir else self.path / "cache"


def schedule_of(cfg, s: OnlineSettings) -> Schedule:
    tr = cfg.train
    return Schedule(N=tr.prefill_episodes, C=tr.collect_interval, eval_every=s.eval_every)


def open_run_dir(s: OnlineSettings, model: settings.ModelChoice, ctx: distributed.DistContext, device: str, *,
                 config_args: list[str], prog: str) -> OnlineRunDir:
    """A new run directory (rank 0's name for every rank), or the one --resume continues."""
    run_json: dict[str, Any] = {}
    if s.resume:
        # A run killed before its first checkpoint still resumes: from its config and its bags.
        run_dir, run_json = runs.resume_run_dir(s.run_dir, need_checkpoint=False)
        cfg = runs.load_run_config(run_dir)
        if "settings" not in run_json:   # a run from before settings were saved
            proto = run_json.get("protocol") or {}
            if not isinstance(proto, dict):
                raise ValueError(f"--resume: {run_dir / 'run.json'}: 'protocol' is not a mapping")
            check_settings_section(run_dir / "run.json", "protocol", OnlineSettings,
                                   {k: proto[k] for k in PROTOCOL_KEYS if k in proto})
            defaults = OnlineSettings()
            s = dataclasses.replace(s, **{k: proto[k] for k in PROTOCOL_KEYS if k in proto
                                          and getattr(s, k) == getattr(defaults, k)})
    else:
        if s.init_policy:   # the file itself (a run directory names its latest checkpoint), as run.json keeps it
            s = dataclasses.replace(s, init_policy=str(existing_checkpoint_file(s.init_policy)))
        cfg = (policy_config(Path(s.init_policy), model, config_args=config_args, prog=prog,
                             overrides=s.config_overrides()) if s.init_policy
               else model.to_config(config_args, prog, s.config_overrides()))
        cfg.train.device = device
        planned = schedule_of(cfg, s).planned_updates(s.env_steps, cfg.train.time_limit, s.num_envs * ctx.world_size)
        # before the run directory exists: a refused plan leaves nothing behind
        plan_prototype_freeze(cfg, 0, planned)
        run_dir = Path(distributed.gather_objects(   # rank 0's (the default name has a stamp)
            str(runs.new_run_dir(s.run_dir, "online", cfg.task, cfg.variant)) if ctx.is_main else None, ctx)[0])
        if ctx.is_main:
            run_dir.mkdir(parents=True, exist_ok=True)
            runs.save_run_config(run_dir, cfg)
        distributed.barrier_if(ctx)
    rd = OnlineRunDir(s, cfg, run_dir, run_json, schedule_of(cfg, s))
    rd.bags_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "eval").mkdir(exist_ok=True)
    if s.train_context is not None:
        rd.s = dataclasses.replace(s, train_context=get_task(cfg.task).validate(s.train_context, "train"))
    return rd


def write_run_json(rd: OnlineRunDir, model: settings.ModelChoice, ctx: distributed.DistContext, *,
                   argv: list[str], device: str) -> None:
    """run.json as this invocation starts: what runs (kind, task, settings, the protocol), the
    code of every invocation and its command line; rank 0 writes it."""
    if ctx.is_main and (warning := stale_install()):
        print(f"[online] warning: {warning}", file=sys.stderr, flush=True)
    s, cfg, rj = rd.s, rd.cfg, rd.run_json
    tr = cfg.train
    versions, version = list(rj.get("code_versions", [])), code_version()
    if version not in versions:   # every invocation's code, resumes included
        versions.append(version)
    runs.record_invocation(rj, s.resume, argv)
    rj.update(kind="online", code_versions=versions, task=cfg.task, variant=cfg.variant,
              preset=cfg.preset, seed=tr.seed, device=device,
              settings={"online": settings.as_data(s), "model": settings.as_data(model)},
              protocol={"env_steps": s.env_steps, "num_envs": s.num_envs, "prefill_episodes": tr.prefill_episodes,
                        "updates_per_episode": tr.collect_interval, "action_repeat": tr.action_repeat,
                        "time_limit": tr.time_limit, "eval_every": s.eval_every,
                        "eval_episodes": s.eval_episodes, "eval_max_contexts": s.eval_max_contexts,
                        "final_max_contexts": s.final_max_contexts, "final_episodes": s.final_episodes,
                        "wall_budget": s.wall_budget, "train_context": s.train_context,
                        "eval_split": s.eval_split, "eval_contexts": s.eval_contexts, "world_size": ctx.world_size,
                        "env_draws": "per_episode"})
    if s.init_policy and "init_policy" not in rj:   # the file by its content: a shipped one is replaced later
        rj["init_policy"] = {"path": s.init_policy, "sha256": file_sha256(s.init_policy)}
    if ctx.is_main:
        runs.atomic_write_json(rd.path / "run.json", rj)


# ---------------------------------------------------------------------- the episode bags
BAG_QOS = dict(history="keep_last", depth=100, reliability="reliable", durability="volatile")


class EpisodeBagWriter:
    """Writes one env's steps as the ROS path records them: one bag per episode.

    write_observation(obs, stamp) then write_action(action, stamp, features) for every step;
    close() after the answer to is_last (or on shutdown: a partial episode is still valid).
    """

    def __init__(self, bag_dir: Path, action_names: Sequence[str], namespace: str = T.DEFAULT_NAMESPACE,
                 compression: str = "zstd"):
        self.bag_dir = Path(bag_dir)
        self.names = list(action_names)
        self.w = BagWriter(self.bag_dir, compression=compression)
        self.t = {k: T.topic_name(namespace, k) for k in (T.IMAGE, T.STEP_INFO, T.CONTEXT, T.ACTION,
                                                           T.CONTEXT_FEATURES)}
        self.t[T.CLOCK] = T.CLOCK
        for rel, name in self.t.items():
            depth = 10 if rel == T.CLOCK else 100
            self.w.add_topic(name, T.TYPES[rel], [qos_profile(**{**BAG_QOS, "depth": depth})])
        self.steps = 0

    def _put(self, rel: str, msg: Any, stamp: int) -> None:
        now = time.time_ns()
        self.w.write(self.t[rel], encode(T.TYPES[rel], msg), now, now)

    def write_observation(self, obs: Any, stamp: int) -> None:
        new = new_message
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
        new = new_message
        self._put(T.ACTION, T.fill_action(new(T.TYPES[T.ACTION]), np.asarray(action, np.float64),
                                          self.names, stamp), stamp)
        if features is not None and getattr(features, "u", None) is not None and np.size(features.u):
            self._put(T.CONTEXT_FEATURES, T.fill_context_features(
                new(T.TYPES[T.CONTEXT_FEATURES]), np.asarray(features.u), np.asarray(features.w),
                np.asarray(features.e), stamp), stamp)

    def close(self) -> None:
        self.w.close()


def feature_row(features: Any, i: int) -> Any:
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


class EnvBags:
    """One bag per episode for each env, named by bag_name; the run's counters advance as
    steps and episodes are recorded (global under torchrun: each rank adds world_size)."""

    def __init__(self, bags_dir: Path, n: int, action_names: Sequence[str], *, dt_ns: int, attempt: int,
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
