"""The Trainer: one agent, its dataset sampler, metrics log and checkpoints, shared by
protocad-train (trainer/learn/train.py), the loop (trainer/launch/loop.py) and the in-process
path (trainer/research/online.py).

A checkpoint (protocad_ros.checkpoint, written atomically) carries the weights, optimizer
states, the torch RNG state, the agent's update counter and the trainer's counters, including
the dataset sampler's RNG state, so a resume continues from the last checkpoint with the same
counters and draws the same next batch an uninterrupted run would have drawn.

Under torchrun (trainer/learn/distributed.py) every rank trains on its share of the global batch
(train.batch_size / N sequences, drawn by its own sampler seeded by its rank) and gradients are
averaged; rank 0 writes the metrics and the checkpoint, which carries every rank's sampler and
RNG state, so a resume with the same N continues exactly, and one with another N continues
with fresh per-rank seeds.
"""
from __future__ import annotations

import json
import time
import zlib
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping

import numpy as np
import torch

from protocad_ros.atomic import remove_stale_temporaries
from protocad_ros.checkpoint.agent_file import load_checkpoint, save_checkpoint
from protocad_ros.model.agent import make_agent
from protocad_ros.model.config import plan_prototype_freeze
from trainer import console, metrics_log, runs, torch_setup
from trainer.data.dataset import MCAPDataset
from trainer.learn import distributed
from trainer.learn.context_health import CollapseWatch
from trainer.learn.schedule import RunCounters

DEFAULT_LOG_EVERY = 10


class Trainer:
    """Agent + dataset + run directory: updates, metrics (JSON lines + callbacks), checkpoints.

    counters: free-form numbers/strings saved with every checkpoint (the sampler state, wall
    time, the loop's phases); `updates` always mirrors the agent's own update counter.
    progress: a run's RunCounters (trainer.learn.schedule), saved with every checkpoint too.
    """

    def __init__(self, cfg, run_dir: str | Path, dataset: MCAPDataset | None, *, device: str = "cpu",
                 agent=None, counters: Mapping[str, Any] | None = None,
                 callbacks: Iterable[metrics_log.MetricsCallback] = (), log_every: int = DEFAULT_LOG_EVERY,
                 action_dim: int | None = None, resumed: bool = False,
                 dist_ctx: distributed.DistContext | None = None):
        self.cfg = cfg
        self.dist = dist_ctx or distributed.DistContext()
        if cfg.train.batch_size % self.dist.world_size:
            raise ValueError(f"train.batch_size={cfg.train.batch_size} (the global batch) does not "
                             f"split over {self.dist.world_size} ranks")
        self.local_batch = cfg.train.batch_size // self.dist.world_size
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        if self.dist.is_main:
            for path in (self.checkpoint_path, self.checkpoint_path.with_name("config.yaml"),
                         self.run_dir / "config.yaml", self.run_dir / "run.json"):
                for tmp in remove_stale_temporaries(path):
                    print(f"[train] removed {tmp}, left by an interrupted write", flush=True)
        self.dataset = dataset
        self.device = device
        if agent is None:
            adim = action_dim or (dataset.action_dim if dataset is not None else None)
            if not adim:
                raise ValueError("the action size is unknown: no dataset with actions and no action_dim")
            torch_setup.seed_everything(cfg.train.seed)
            agent = make_agent(cfg, int(adim), device=device)
            if self.dist.enabled:   # the same weights (rank 0's), each rank its own draws
                torch_setup.seed_everything(distributed.rank_seed(cfg.train.seed, self.dist.rank))
                if dataset is not None:
                    dataset.rng = np.random.default_rng(distributed.rank_seed(cfg.train.seed, self.dist.rank))
        distributed.attach(agent, self.dist)
        self.agent = agent
        self.counters: dict[str, Any] = dict(counters or {})
        for key in ("dataset_state", "rank_states", "world_size"):   # rewritten at every save
            self.counters.pop(key, None)
        self.rank_fingerprints: list[dict[str, str]] = []
        self.progress: RunCounters | None = None
        self.counters["updates"] = int(agent.counters()["updates"])
        if "prototype_freeze" in self.counters:   # resolved when the run started: kept on resume
            agent.set_prototype_freeze(int(self.counters["prototype_freeze"]))
        self._last_saved: int | None = None
        #: called with the path after each checkpoint is written (protocad-loop signs it)
        self.after_save: list = []
        self.log_every = max(1, int(log_every))
        if resumed and self.dist.is_main:  # lines logged after the checkpoint will be logged again
            metrics_log.truncate_metrics(self.run_dir / "metrics.jsonl", self.counters["updates"])
        self.metrics = metrics_log.MetricsLogger(self.run_dir / "metrics.jsonl" if self.dist.is_main else None,
                                          callbacks if self.dist.is_main else (),
                                          wall_offset=float(self.counters.get("wall_time", 0.0)))
        self._mean = metrics_log.RunningMean()
        self._last_log_t = time.monotonic()
        self._last_log_u = self.updates
        self.last_metrics: dict[str, float] = {}
        self._collapse = CollapseWatch(cfg.context.num_prototypes)

    # ------------------------------------------------------------------ construction helpers
    @classmethod
    def from_checkpoint(cls, path: str | Path, run_dir: str | Path, dataset: MCAPDataset | None, *,
                        device: str = "cpu", **kw) -> "Trainer":
        """Rebuild from a checkpoint: weights, optimizers, torch RNG, counters, sampler state."""
        agent, counters = load_checkpoint(path, device=device)
        ctx = kw.get("dist_ctx") or distributed.DistContext()
        ranks = json.loads(counters.get("rank_states") or "[]")
        state = counters.get("dataset_state")
        if len(ranks) == ctx.world_size and ctx.enabled:     # the same N: exactly where it was
            state = ranks[ctx.rank]["dataset"]
            torch.set_rng_state(distributed.unpack_rng(ranks[ctx.rank]["torch_rng"]))
        elif ctx.enabled:   # another N: fresh per-rank draws (rank 0's weights go everywhere)
            seed = distributed.rank_seed(agent.cfg.train.seed, ctx.rank, int(agent.updates))
            torch.manual_seed(seed)
            state = None
            if dataset is not None:
                dataset.rng = np.random.default_rng(seed)
        if dataset is not None and state:
            dataset.load_state_dict(json.loads(state) if isinstance(state, str) else state)
        return cls(agent.cfg, run_dir, dataset, device=device, agent=agent, counters=counters,
                   resumed=True, **kw)

    # ------------------------------------------------------------------ properties
    @property
    def updates(self) -> int:
        return int(self.agent.counters()["updates"])

    @property
    def checkpoint_path(self) -> Path:
        return runs.checkpoint_path(self.run_dir)

    @property
    def prototype_freeze(self) -> int | None:
        """The update count below which the prototypes get no gradient (None: no prototypes,
        or not planned yet)."""
        value = self.counters.get("prototype_freeze")
        return None if value is None else int(value)

    def plan_prototype_freeze(self, end_updates: int) -> int | None:
        """Resolve the prototype freeze from the run's plan: its agent's update counter goes
        from here to `end_updates`. Refuses (ConfigError) a plan that keeps the prototypes
        frozen for more than a quarter of it unless the config allows it. Once resolved the
        count travels in the checkpoints, so a resume with a longer plan never re-freezes
        prototypes that have started to train. None for agents without prototypes."""
        if not self.agent.set_prototype_freeze(0):
            return None
        freeze = self.prototype_freeze
        if freeze is None:
            freeze = plan_prototype_freeze(self.cfg, self.updates, end_updates) or 0
            self.counters["prototype_freeze"] = freeze
        self.agent.set_prototype_freeze(freeze)
        return freeze

    # ------------------------------------------------------------------ training
    def update(self) -> dict[str, float]:
        """One update on a freshly sampled batch."""
        if self.dataset is None:
            raise RuntimeError("no dataset to train on")
        index = self.dataset.sample_index(self.local_batch)
        batch = MCAPDataset.training_batch(self.dataset.gather(index))
        if self.cfg.spec.reads_true_context:
            batch["context"] = self.dataset.true_context(index, self.cfg.task)
        m = self.agent.train_step(batch)
        m["batch_crc"] = float(zlib.crc32(np.asarray(index, np.int64).tobytes()))
        self.counters["updates"] = self.updates
        self._mean.add({k: v for k, v in m.items() if k not in ("batch_crc", "updates")})
        self.last_metrics = m
        if self.updates % self.log_every == 0:
            self.log_now(batch_crc=int(m["batch_crc"]))
        return m

    def log_now(self, **extra: Any) -> dict | None:
        means = self._mean.pop()
        if not means and not extra:
            return None
        now = time.monotonic()
        du = self.updates - self._last_log_u
        rate = du / (now - self._last_log_t) if now > self._last_log_t and du > 0 else None
        self._last_log_t, self._last_log_u = now, self.updates
        row_extra = {k: v for k, v in extra.items()}
        if rate is not None:
            row_extra["updates_per_s"] = round(rate, 3)
        counters = {**self.counters, **(self.progress.as_dict() if self.progress else {})}
        for k in ("env_steps", "episodes"):
            if k in counters:
                row_extra.setdefault(k, counters[k])
        self._warn_if_collapsed(means)
        return self.metrics.log(self.updates, means, kind="train", **row_extra)

    def _warn_if_collapsed(self, means: Mapping[str, float]) -> None:
        """One warning line per run when the context module's health figures say it has
        collapsed (trainer/learn/context_health.py; msgs_docs/training.md)."""
        line = self._collapse.update(self.updates, means) if self.dist.is_main else None
        if line:
            print(f"[train] {line}", flush=True)

    def train(self, target_updates: int, *, stop: console.StopFlag | None = None, checkpoint_every: int = 0,
              bar=None, on_update: Callable[[int, dict], None] | None = None, save: bool = True) -> bool:
        """Update until the agent's counter reaches target_updates (a total, not a delta).
        Checkpoints every `checkpoint_every` updates and at the end (unless save=False and not
        stopped; a multiple of `checkpoint_every` that is the target is then still saved, else a
        driver with C a multiple of it would never checkpoint between its evaluations). Returns
        False when stopped early by `stop` (a checkpoint is written then)."""
        completed = True
        # The rate of the first line of this call counts from here: between two calls a loop
        # collects, and that time is not the trainer's (it read as slow first updates).
        self._last_log_t, self._last_log_u = time.monotonic(), self.updates
        while self.updates < target_updates:
            # Ranks stop together (one would wait forever for the others' gradients).
            if distributed.any_rank(stop is not None and stop.stop, self.dist):
                completed = False
                break
            m = self.update()
            if bar is not None:
                bar.update(1)
                if self.updates % 5 == 0:
                    bar.set_postfix({k: f"{m[k]:.3g}" for k in ("wm_loss", "image_loss", "reward_loss", "actor_loss")
                                     if k in m}, refresh=False)
            if on_update is not None:
                on_update(self.updates, m)
            if checkpoint_every and self.updates % checkpoint_every == 0 and (self.updates < target_updates
                                                                             or not save):
                self.save()
        if save or not completed:
            self.save()
        return completed

    # ------------------------------------------------------------------ checkpoints
    def save(self, path: str | Path | None = None) -> Path:
        """Atomic checkpoint (weights, optimizers, torch RNG, counters, sampler state)."""
        self.log_now()
        self.counters["updates"] = self.updates
        self.counters["wall_time"] = round(self.metrics.wall_time, 3)
        counters = {**self.counters, **(self.progress.as_dict() if self.progress else {})}
        if self.dataset is not None:
            counters["dataset_state"] = json.dumps(self.dataset.state_dict())
        if self.dist.enabled:   # collective: every rank's sampler and RNG, and a weight check
            mine = {"dataset": counters.get("dataset_state"),
                    "torch_rng": distributed.pack_rng(torch.get_rng_state()),
                    "fingerprints": distributed.fingerprints(self.agent)}
            ranks = distributed.gather_objects(mine, self.dist)
            if not self.dist.is_main:
                return Path(path or self.checkpoint_path)
            counters["rank_states"] = json.dumps([{k: r[k] for k in ("dataset", "torch_rng")}
                                                  for r in ranks])
            differ = sorted(k for k in ranks[0]["fingerprints"]
                            if len({r["fingerprints"][k] for r in ranks}) > 1)
            counters["world_size"] = self.dist.world_size
            self.rank_fingerprints = [r["fingerprints"] for r in ranks]
            counters["rank_fingerprints"] = json.dumps(self.rank_fingerprints)
            if differ:
                raise RanksDiverged(f"data-parallel ranks diverged at update {self.updates}: {differ} "
                                   "differ between ranks")
        target = Path(path or self.checkpoint_path)
        try:
            out = save_checkpoint(target, self.agent, counters, rng_state=True)
            self._last_saved = self.updates
            for fn in self.after_save:
                fn(out)
            return out
        except OSError as exc:   # disk full, quota, permission: the previous file is untouched
            if target.exists():
                state = "the last good checkpoint there is intact" + (
                    f" (update {self._last_saved})" if self._last_saved is not None else "")
            else:
                state = "there is no earlier checkpoint there (the run resumes from its bags)"
            raise CheckpointWriteError(
                f"writing the checkpoint {target} at update {self.updates} failed: "
                f"{exc.strerror or exc}; {state}") from exc

    def close(self) -> None:
        self.metrics.close()


class CheckpointWriteError(RuntimeError):
    """A checkpoint could not be written (the message says why and what is still on disk)."""


class RanksDiverged(RuntimeError):
    """Data-parallel ranks hold different weights (nothing is written: the last checkpoint stays)."""
