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
trainer.bag.writer.BagWriter with the contract topics, types and stamps of the ROS path (image,
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

This module is the command line and the run's loop over its parts: online_rundir.py (the settings,
the run directory, the episode bags), trainer/learn/resume.py (the trainer, fresh or resumed) and
trainer/learn/training_eval.py (the evaluations).
"""
from __future__ import annotations

import os
import sys
import time
from pathlib import Path
from typing import Sequence

from protocad_ros.checkpoint.files import CheckpointError
from protocad_ros.policy import Policy
from sim_bridge.sim.rollout import RandomPolicy, continuing_rollout
from sim_bridge.sim.vector import VectorEnv
from trainer import cli_values, console, runs, settings, torch_setup
from trainer.bag.writer import BagWriteError
from trainer.data.dataset import MCAPDataset, TopicMap
from trainer.data.records import CacheWriteError
from trainer.learn import distributed
from trainer.learn.evaluate import select_contexts
from trainer.learn.resume import TrainerOpening, open_trainer
from trainer.learn.schedule import RunCounters
from trainer.learn.trainer import CheckpointWriteError, RanksDiverged
from trainer.learn.training_eval import Evaluator
from trainer.research.online_rundir import (
    EnvBags,
    OnlineSettings,
    data_counts,
    feature_row,
    leftovers,
    open_run_dir,
    write_run_json,
)
from trainer.viz.metrics_rerun import metrics_callbacks


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
    try:
        return run(s, model, parsed.config_args, parsed.prog, parsed.argv)
    except (ValueError, CheckpointError) as exc:   # CheckpointError: the run's checkpoint is unusable
        print(f"protocad-online: error: {exc}", file=sys.stderr)
        return 2
    except (CheckpointWriteError, RanksDiverged, bag_write_errors(), cache_errors(), OSError) as exc:
        # a full disk (cache, bags, checkpoints, metrics) is one line with the path; the run
        # resumes once space is freed (protocad-online --resume)
        where = (f" ({exc.filename})" if isinstance(exc, OSError) and exc.filename
                 and str(exc.filename) not in str(exc) else "")
        print(f"protocad-online: error: {exc}{where}", file=sys.stderr)
        if s.run_dir:
            print(f"protocad-online: continue with: protocad-online --run-dir {s.run_dir} --resume",
                  file=sys.stderr)
        return 1


def bag_write_errors() -> type:
    return BagWriteError


def cache_errors() -> type:
    return CacheWriteError


# ---------------------------------------------------------------------- the run, in parts
def run(s: OnlineSettings, model: settings.ModelChoice, config_args: Sequence[str] = (),
        prog: str = "protocad-online", argv: Sequence[str] | None = None) -> int:
    """A whole online run (or its resume); under torchrun, this rank's share of it."""
    return distributed.run_entry_point(
        model.threads, model.device,
        lambda ctx, device: OnlineRun(s, model, ctx, device, config_args=list(config_args), prog=prog,
                                      argv=argv).run())


class OnlineRun:
    """Algorithm 1 in one process: prepare the run directory, replay and trainer, then collect,
    train on schedule and evaluate until the budget; every part resumable."""

    def __init__(self, s: OnlineSettings, model: settings.ModelChoice, ctx: distributed.DistContext,
                 device: str, *, config_args: list[str], prog: str, argv: Sequence[str] | None):
        self.s, self.model, self.ctx, self.device = s, model, ctx, device
        self.config_args, self.prog = config_args, prog
        self.argv = list(sys.argv[1:] if argv is None else argv)
        self.main_rank, self.world = ctx.is_main, ctx.world_size
        self.say = print if self.main_rank else (lambda *args, **kw: None)

    # ------------------------------------------------------------------ preparation
    def _open_run_dir(self) -> None:
        rd = open_run_dir(self.s, self.model, self.ctx, self.device, config_args=self.config_args, prog=self.prog)
        self.s, self.cfg, self.run_dir, self.run_json, self.schedule = rd.s, rd.cfg, rd.path, rd.run_json, rd.schedule
        self.bags_dir, self.cache_dir = rd.bags_dir, rd.cache_dir
        write_run_json(rd, self.model, self.ctx, argv=self.argv, device=self.device)

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
        callbacks = metrics_callbacks(s.rerun, self.run_dir, "protocad-online")
        opened = open_trainer(self.cfg, self.run_dir, self.ds, TrainerOpening(
            resume=s.resume, device=self.device,
            end_updates=self.schedule.planned_updates(s.env_steps, tr.time_limit, s.num_envs * self.world),
            precision=self.model.precision, log_every=s.log_every, callbacks=callbacks, dist_ctx=ctx,
            restart_metrics=True, init_policy=Path(s.init_policy) if s.init_policy else None,
            init_policy_sha256=(self.run_json.get("init_policy") or {}).get("sha256"), say=self.say))
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
        s, task = self.s, self.cfg.task
        workers = s.eval_workers if s.eval_workers >= 0 else (0 if (os.cpu_count() or 1) <= 2 else
                                                              min(16, (os.cpu_count() or 2) - 1))
        self.periodic_contexts = select_contexts(task, s.eval_split, s.eval_contexts, s.eval_max_contexts)
        self.final_contexts = select_contexts(task, s.eval_split, s.eval_contexts, s.final_max_contexts)
        self.evaluate = Evaluator(self.trainer, self.run_dir, self.ctx, self.c, task=task, variant=self.cfg.variant,
                                  split=s.eval_split, seed=self.cfg.train.seed + 7, device=self.device,
                                  workers=workers, progress=False if s.no_progress else None)

    def _start_envs(self):
        """The training envs and the rollout that asks, before every step, who acts: the
        prefill's random policy, then the agent (sampling, as DreamerV2 collects)."""
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
        self.bags = EnvBags(self.bags_dir, s.num_envs, self.venv.action_names,
                            dt_ns=int(round(self.venv.control_dt * 1e9)), attempt=attempt,
                            rank_tag=f"_rank{self.ctx.rank}" if self.ctx.enabled else "", counters=c,
                            action_repeat=tr.action_repeat, world=self.world)
        return continuing_rollout(self.venv, lambda: random_policy if self.prefilling() else agent_policy)

    def _announce(self) -> None:
        s, cfg, tr, ctx = self.s, self.cfg, self.cfg.train, self.ctx
        wall = f", wall budget {cli_values.format_duration(s.wall_budget)}" if s.wall_budget else ""
        self.say(f"[online] {cfg.task} / {cfg.variant} / {cfg.preset} on {self.device}: {s.num_envs} env(s)"
                 + (f" on each of {self.world} ranks ({ctx.backend})" if ctx.enabled else "") + ", "
                 f"budget {s.env_steps} env steps{wall}, prefill {tr.prefill_episodes} episodes, "
                 f"C={tr.collect_interval}, eval every {s.eval_every} env steps on {len(self.periodic_contexts)} "
                 f"{s.eval_split} contexts; {torch_setup.torch_threads()} torch thread(s); run dir {self.run_dir}",
                 flush=True)
        self.say(f"[online] {self.trainer.agent.precision.describe()}", flush=True)

    # ------------------------------------------------------------------ Algorithm 1
    def prefilling(self) -> bool:
        return not self.schedule.prefilled(self.c.episodes) and not self.c.prefill_done

    def _stopped(self, stop: console.StopFlag) -> bool:   # collective under torchrun: every rank decides the same
        return distributed.any_rank(stop.stop, self.ctx)

    def _keep_going(self, stop: console.StopFlag) -> bool:
        out_of_time = bool(self.s.wall_budget) and self.trainer.metrics.wall_time >= self.s.wall_budget
        return self.c.env_steps < self.s.env_steps and not distributed.any_rank(stop.stop or out_of_time, self.ctx)

    def _after_episodes(self, finished: list[Path], stop: console.StopFlag, bar) -> None:
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

    def _collect_and_train(self, stream, stop: console.StopFlag) -> str:
        """The loop: step every env, record, and after each finished episode train and evaluate
        on schedule. Returns how it ended: interrupted, finished (env steps) or wall_budget."""
        c, s = self.c, self.s
        bar = console.progress(s.env_steps, initial=c.env_steps, desc="env steps",
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
                        if (bag := self.bags.record(i, o, actions[i], feature_row(feats, i))) is not None]
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
        self._open_replay()
        self._evaluation()
        t_start = time.monotonic()
        self.venv, self.bags = None, None
        status, cause = "failed", None   # until the loop ends normally or is stopped
        with console.StopFlag() as stop:
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
                 f"updates in {cli_values.format_duration(seconds)}", flush=True)
        self.say(f"[online] run dir:    {run_dir}\n[online] checkpoint: {self.trainer.checkpoint_path}\n"
                 f"[online] bags:       {self.bags_dir} ({len(self.ds.stores)} episodes)\n"
                 f"[online] metrics:    {run_dir / 'metrics.jsonl'}\n"
                 f"[online] eval:       {run_dir / 'eval.jsonl'}, {run_dir / 'eval'}", flush=True)
        if status == "interrupted":
            self.say(f"[online] resume with: protocad-online --run-dir {run_dir} --resume", flush=True)


if __name__ == "__main__":
    sys.exit(main())
