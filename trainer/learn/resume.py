"""A run's trainer, opened the one way protocad-train, protocad-loop and protocad-online open it: resumed from
the run's checkpoint when there is one, else fresh; then the prototype freeze planned for the
whole run, the precision resolved on this machine, and config.yaml saved saying what it ran in.
No ROS."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable

from protocad_ros.atomic import file_sha256
from protocad_ros.checkpoint.agent_file import read_checkpoint
from protocad_ros.model.precision import PrecisionChoice
from sim_bridge.contract.contexts import task_actuators
from trainer import metrics_log, runs
from trainer.data.dataset import MCAPDataset
from trainer.learn import distributed
from trainer.learn.init_policy import agent_from_policy, measure_drift_from_policy
from trainer.learn.trainer import Trainer


@dataclass
class OpenedTrainer:
    trainer: Trainer
    resumed: bool
    """restored from the run's checkpoint (False: fresh, also on a resume of a run that was
    stopped before its first checkpoint)"""
    prototype_freeze: int | None
    """updates the prototypes stay frozen for (None: the agent has none)"""
    precision: PrecisionChoice


@dataclass(frozen=True)
class TrainerOpening:
    """How a command opens its run's trainer (the same for protocad-train, -loop and -online)."""

    resume: bool
    """restore the checkpoint if the run has one (weights, optimizers, counters, sampler state);
    without one (stopped before it was written) the trainer starts fresh like a new run"""
    device: str
    end_updates: int
    """the agent's update count at the end of the run's plan (the freeze is a share of it; once
    resolved, the checkpoint keeps it)"""
    precision: str | None
    """the command line's --precision (None: the config's request)"""
    log_every: int
    callbacks: Iterable[metrics_log.MetricsCallback] = ()
    dist_ctx: distributed.DistContext | None = None
    init_policy: Path | None = None
    """the policy file the run started from (--init-policy): a fresh trainer's agent holds its
    weights; a resumed one measures its prototypes' drift from that policy's"""
    init_policy_sha256: str | None = None
    """that file's sha256 when the run started (run.json): a file replaced since is not used"""
    say: Callable[..., None] = print
    restart_metrics: bool = False
    """a trainer that starts fresh (a new run, or a resume of one stopped before its first
    checkpoint) drops the metrics lines an earlier attempt logged, as its updates start from 0"""


def open_trainer(cfg, run_dir: Path, dataset: MCAPDataset, how: TrainerOpening) -> OpenedTrainer:
    """The trainer of the run in `run_dir` with the run's config `cfg`, opened as `how` says."""
    ctx = how.dist_ctx or distributed.DistContext()
    ckpt = runs.checkpoint_path(run_dir)
    resumed = how.resume and ckpt.exists()
    # What the trainer runs on and reports to, whether it is rebuilt or new.
    process = {"device": how.device, "callbacks": how.callbacks, "log_every": how.log_every, "dist_ctx": how.dist_ctx}
    if resumed:
        trainer = Trainer.from_checkpoint(ckpt, run_dir, dataset, **process)
        if how.init_policy is not None and (why := _same_file(how)):
            how.say(f"[resume] {why}: the prototypes' drift is measured from their seeded draw", flush=True)
        elif how.init_policy is not None:
            measure_drift_from_policy(trainer.agent, read_checkpoint(how.init_policy)["modules"])
    else:
        if how.init_policy is not None and (why := _same_file(how)):
            raise ValueError(f"{why}: the run cannot start from it again")
        if how.restart_metrics and ctx.is_main:
            metrics_log.truncate_metrics(Path(run_dir) / "metrics.jsonl", 0)
        trainer = Trainer(cfg, run_dir, dataset, action_dim=len(task_actuators(cfg.task)),
                          agent=None if how.init_policy is None else
                          agent_from_policy(how.init_policy, cfg, how.device, say=how.say), **process)
    freeze = trainer.plan_prototype_freeze(how.end_updates)
    # Resolved here, on this rank's device: a config from another machine asks, never forces.
    chosen = trainer.agent.use_precision(how.precision)
    if ctx.is_main:
        runs.save_run_config(run_dir, cfg, ran=chosen.ran_here())
    return OpenedTrainer(trainer, resumed, freeze, chosen)


def _same_file(how: TrainerOpening) -> str | None:
    """Why the --init-policy file is not the one the run started from (None: it is)."""
    path = Path(how.init_policy)
    if not path.is_file():
        return f"--init-policy {path} is gone since the run started"
    if how.init_policy_sha256 and file_sha256(path) != how.init_policy_sha256:
        return (f"--init-policy {path} changed since the run started (sha256 {how.init_policy_sha256[:12]}..., "
                f"now {file_sha256(path)[:12]}...)")
    return None
