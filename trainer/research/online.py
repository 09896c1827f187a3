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

Under torchrun (`torchrun --nproc_per_node N --no-python protocad-online ...`, see
trainer/learn/distributed.py) every rank collects with its own envs (seeded by rank) into its own bags
(`..._rankR`) and replays them, the ranks step in lock-step (same time limit, so their episodes
end together) and average gradients; counters are global (env steps and episodes of all ranks,
so --env-steps is the budget of the whole run and C updates follow each collected episode of
any rank); rank 0 evaluates (the others wait), writes the metrics, run.json and checkpoints.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from sim_bridge.contract import topics as T
from trainer.learn import distributed
from trainer import runs
from trainer.data.dataset import MCAPDataset, TopicMap
from trainer.learn.train import Trainer, add_common_model_args, config_from_args

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


# ---------------------------------------------------------------------- CLI
def parse_context_arg(text: str) -> dict[str, float]:
    from trainer.learn.evaluate import parse_context

    try:
        return parse_context(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="protocad-online",
        description="In-process training (no ROS): vectorized envs on the training contexts -> "
                    "agent -> trainer, with the paper's protocol (prefill N random episodes, C "
                    "updates per collected episode, evaluation on the test contexts every "
                    "--eval-every env steps) and the same MCAP bags as the ROS path.",
        formatter_class=runs.HelpFormatter)
    add_common_model_args(ap)
    # The research path uses a GPU when there is one, and bf16 where the hardware has it.
    ap.set_defaults(device="auto", precision="auto")
    g = ap.add_argument_group("protocol")
    g.add_argument("--env-steps", type=int, default=2_000_000,
                   help="budget in env steps (agent steps x action repeat); paper: 2M")
    g.add_argument("--num-envs", type=int, default=1, help="training envs (worker processes)")
    g.add_argument("--prefill-episodes", type=int, default=None, help="N (default train.prefill_episodes = 2)")
    g.add_argument("--updates-per-episode", type=int, default=None,
                   help="C (default train.collect_interval = 100)")
    g.add_argument("--time-limit", type=int, default=None,
                   help="env steps per episode (default train.time_limit = 1000)")
    g.add_argument("--eval-every", type=int, default=10_000, help="env steps between evaluations (0: only at the end)")
    g.add_argument("--eval-episodes", type=int, default=2,
                   help="episodes per context of the periodic evaluations")
    g.add_argument("--final-episodes", type=int, default=5,
                   help="episodes per context of the final evaluation and --random-baseline "
                        "(the paper's 5)")
    g.add_argument("--eval-max-contexts", type=int, default=8,
                   help="periodic evaluations use a fixed subset of K contexts, stratified over the "
                        "parameters (every m and every d equally often; sim_bridge.contract.contexts."
                        "TaskSpec.stratified); 0: all. 8 contexts x 2 episodes = 1.6x the training "
                        "interaction every 10k env steps, where all 64 x 5 of walker were 32x")
    g.add_argument("--final-max-contexts", type=int, default=0,
                   help="the final evaluation (and --random-baseline): 0 = every context of the "
                        "split, the paper protocol; K = the stratified subset of K")
    g.add_argument("--wall-budget", type=runs.parse_duration, default=None, metavar="DURATION",
                   help="also stop once the run's training wall time (carried across resumes) reaches "
                        "this, e.g. 5400, 90m, 1h30m; then the final evaluation, checkpoint and curves "
                        "are written as at the env-step budget")
    g.add_argument("--train-context", type=parse_context_arg, default=None, metavar="K=V[,K=V]",
                   help="train on this one context of the train split instead of a draw per episode "
                        "(e.g. m=1: the standard, unrandomized task)")
    g.add_argument("--eval-split", choices=("test", "train"), default="test",
                   help="split of the evaluation contexts (paper: test = unseen)")
    g.add_argument("--eval-contexts", type=parse_context_arg, nargs="+", default=None, metavar="K=V[,K=V]",
                   help="evaluate on exactly these contexts of --eval-split (default: the split's grid)")
    g.add_argument("--eval-workers", type=int, default=-1,
                   help="evaluation env processes (0: in this process; -1: auto)")
    g.add_argument("--random-baseline", action="store_true",
                   help="also evaluate the uniform random policy once (same contexts and episodes)")
    g = ap.add_argument_group("run")
    g.add_argument("--run-dir", default=None, help="output directory (default runs/online-TASK-VARIANT-TIME)")
    g.add_argument("--resume", action="store_true", help="continue RUN_DIR from its checkpoint")
    g.add_argument("--checkpoint-every", type=int, default=1000,
                   help="updates between checkpoints (also after every evaluation and at the end)")
    g.add_argument("--log-every", type=int, default=10, help="updates per metrics line")
    g.add_argument("--cache-dir", default=None, help="dataset cache (default RUN_DIR/cache)")
    g.add_argument("--rerun", nargs="?", const="", default=None, metavar="RRD",
                   help="log scalars and evaluations to a rerun recording (default RUN_DIR/metrics.rrd)")
    g.add_argument("--no-progress", action="store_true")
    return ap


def main(argv: Sequence[str] | None = None) -> int:
    a = runs.parse_cli(build_parser(), argv)
    if a.resume:   # the original command's options, unless given again
        a = runs.resumed_cli(build_parser, a)
    from trainer.learn.train import CheckpointWriteError, RanksDiverged

    try:
        return run(a)
    except ValueError as exc:
        print(f"protocad-online: error: {exc}", file=sys.stderr)
        return 2
    except (CheckpointWriteError, RanksDiverged, mcap_io_errors(), cache_errors(), OSError) as exc:
        # a full disk (cache, bags, checkpoints, metrics) is one line with the path; the run
        # resumes once space is freed (protocad-online --resume)
        where = (f" ({exc.filename})" if isinstance(exc, OSError) and exc.filename
                 and str(exc.filename) not in str(exc) else "")
        print(f"protocad-online: error: {exc}{where}", file=sys.stderr)
        if a.run_dir:
            print(f"protocad-online: continue with: protocad-online --run-dir {a.run_dir} --resume",
                  file=sys.stderr)
        return 1


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


def mcap_io_errors() -> type:
    from trainer.bag.mcap_io import BagWriteError

    return BagWriteError


def cache_errors() -> type:
    from trainer.data.records import CacheWriteError

    return CacheWriteError


def run(a: argparse.Namespace) -> int:
    return distributed.run_entry_point(a, _run)


def _run(a: argparse.Namespace, ctx: distributed.DistContext, device: str) -> int:
    from protocad_ros.policy import Policy
    from sim_bridge.sim.vector import VectorEnv
    from trainer.learn.evaluate import evaluate_checkpoint, format_table, select_contexts
    from sim_bridge.sim.rollout import RandomPolicy, continuing_rollout

    main_rank, world = ctx.is_main, ctx.world_size
    say = print if main_rank else (lambda *args, **kw: None)
    run_json: dict[str, Any] = {}
    if a.resume:
        # A run killed before its first checkpoint still resumes: from its config and its bags.
        run_dir, run_json = runs.resume_run_dir(a.run_dir, need_checkpoint=False)
        from protocad_ros.model.config import Config

        cfg = Config.load(run_dir / "config.yaml")
        proto = run_json["protocol"]
        for k in ("env_steps", "num_envs", "eval_every", "eval_episodes", "eval_max_contexts",
                  "final_max_contexts", "final_episodes", "wall_budget", "train_context", "eval_split", "eval_contexts"):
            if getattr(a, k) == build_parser().get_default(k):
                setattr(a, k, proto.get(k, getattr(a, k)))
    else:
        overrides = {}
        if a.prefill_episodes is not None:
            overrides["train.prefill_episodes"] = a.prefill_episodes
        if a.updates_per_episode is not None:
            overrides["train.collect_interval"] = a.updates_per_episode
        if a.time_limit is not None:
            overrides["train.time_limit"] = a.time_limit
        a.set = list(a.set) + [f"{k}={v}" for k, v in overrides.items()]
        cfg = config_from_args(a)
        cfg.train.device = device
        run_dir = Path(distributed.gather_objects(   # rank 0's (the default name has a stamp)
            str(runs.new_run_dir(a.run_dir, "online", cfg.task, cfg.variant)) if main_rank else None, ctx)[0])
        if main_rank:
            run_dir.mkdir(parents=True, exist_ok=True)
            cfg.save(run_dir / "config.yaml")
        distributed.barrier_if(ctx)
    tr = cfg.train
    N, C, R = tr.prefill_episodes, tr.collect_interval, tr.action_repeat
    bags_dir = run_dir / "bags"
    bags_dir.mkdir(parents=True, exist_ok=True)
    rank_tag = f"_rank{ctx.rank}" if ctx.enabled else ""
    cache_dir = Path(a.cache_dir) if a.cache_dir else run_dir / "cache"
    eval_dir = run_dir / "eval"
    eval_dir.mkdir(exist_ok=True)
    from trainer.research.results import code_version

    versions = list(run_json.get("code_versions", []))
    if code_version() not in versions:   # every invocation's code, resumes included
        versions.append(code_version())
    runs.record_invocation(run_json, a)
    run_json.update(kind="online", code_versions=versions, task=cfg.task, variant=cfg.variant, preset=cfg.preset,
                    seed=tr.seed, device=device, protocol={
                        "env_steps": a.env_steps, "num_envs": a.num_envs, "prefill_episodes": N,
                        "updates_per_episode": C, "action_repeat": R, "time_limit": tr.time_limit,
                        "eval_every": a.eval_every, "eval_episodes": a.eval_episodes,
                        "eval_max_contexts": a.eval_max_contexts, "final_max_contexts": a.final_max_contexts,
                        "final_episodes": a.final_episodes,
                        "wall_budget": a.wall_budget, "train_context": a.train_context,
                        "eval_split": a.eval_split, "eval_contexts": a.eval_contexts, "world_size": world})
    if main_rank:
        runs.atomic_write_json(run_dir / "run.json", run_json)

    # The run's own cache is its replay buffer: every entry is in use, no budget applies.
    ds = MCAPDataset([], topics=TopicMap(), seq_len=tr.seq_len, seed=tr.seed, cache_dir=cache_dir,
                     cache_budget_gb=None if a.cache_dir else 0)
    # On resume each rank replays a share of the bags on disk (all of them on one process),
    # whatever the number of ranks that wrote them.
    if main_rank and a.resume:
        for left in leftovers(run_dir, cache_dir):
            say(f"[online] removed {left}, left by an interrupted attempt", flush=True)
    distributed.barrier_if(ctx)
    all_bags = sorted(p for p in bags_dir.iterdir() if p.is_dir())
    existing = all_bags[ctx.rank::world]
    if existing:
        ds.add(existing)
    callbacks = []
    if a.rerun is not None:
        from trainer.viz.rerun_log import metrics_callback

        callbacks.append(metrics_callback(a.rerun or run_dir / "metrics.rrd", application="protocad-online"))
    if a.resume and runs.checkpoint_path(run_dir).exists():
        trainer = Trainer.from_checkpoint(runs.checkpoint_path(run_dir), run_dir, ds, device=device,
                                          callbacks=callbacks, log_every=a.log_every, dist_ctx=ctx)
    else:
        from sim_bridge.contract.contexts import task_actuators

        if a.resume and main_rank:   # killed before its first checkpoint: updates start again
            runs.truncate_metrics(run_dir / "metrics.jsonl", 0)
        trainer = Trainer(cfg, run_dir, ds, device=device, callbacks=callbacks, log_every=a.log_every,
                          action_dim=len(task_actuators(cfg.task)), dist_ctx=ctx)
        trainer.counters.update(env_steps=0, agent_steps=0, episodes=0, prefill_done=0,
                                next_eval=a.eval_every, evals=0, resumes=0, last_return=0.0, bags=0)
    c = trainer.counters
    if a.resume:
        # The data is the truth: every bag on disk counts, also those written after the last
        # checkpoint (their updates are made up by the schedule, which counts from episodes).
        steps, episodes = (sum(x) for x in zip(*distributed.gather_objects(data_counts(ds), ctx)))
        c.update(agent_steps=steps, env_steps=steps * R, episodes=episodes, bags=len(all_bags),
                 prefill_done=int(episodes >= N), resumes=int(c.get("resumes", 0)) + 1)
        say(f"[online] resuming {run_dir}: {c['env_steps']} env steps, {c['episodes']} episodes "
            f"in {len(all_bags)} bags, {trainer.updates} updates"
            + ("" if runs.checkpoint_path(run_dir).exists() else " (no checkpoint yet: from the bags)"),
            flush=True)
    attempt = len(run_json.get("resumes_argv", []))   # this invocation's number, unique per run
    eval_workers = a.eval_workers if a.eval_workers >= 0 else (0 if (os.cpu_count() or 1) <= 2 else
                                                               min(16, (os.cpu_count() or 2) - 1))
    periodic_contexts = select_contexts(cfg.task, a.eval_split, a.eval_contexts, a.eval_max_contexts)
    final_contexts = select_contexts(cfg.task, a.eval_split, a.eval_contexts, a.final_max_contexts)
    if a.train_context is not None:
        from sim_bridge.contract.contexts import get_task

        a.train_context = get_task(cfg.task).validate(a.train_context, "train")

    def log_eval(result, tag: str) -> None:
        if not main_rank:
            return
        d = result.to_dict()
        d.update(env_steps=int(c["env_steps"]), updates=trainer.updates, tag=tag)
        runs.atomic_write_json(eval_dir / f"{tag}.json", d)
        with open(run_dir / "eval.jsonl", "a") as f:
            f.write(json.dumps({"env_steps": int(c["env_steps"]), "updates": trainer.updates, "tag": tag,
                                "policy": d["policy"], "mean_return": d["mean_return"],
                                "per_context": {" ".join(f"{k}={v:g}" for k, v in pc["context"].items()):
                                                pc["mean_return"] for pc in d["per_context"]}}) + "\n")
        trainer.metrics.log(trainer.updates, {"eval_return": d["mean_return"]}, kind="eval", tag=tag,
                            env_steps=int(c["env_steps"]))
        for hook in trainer.metrics.eval_hooks():
            try:
                hook.log_eval(trainer.updates, d)
            except Exception as exc:  # noqa: BLE001
                print(f"[online] rerun eval logging failed: {exc}", file=sys.stderr)

    final_episodes = a.final_episodes

    def evaluate(tag: str, contexts, stop, episodes: int) -> Any:
        if not main_rank:   # rank 0 evaluates; the others wait for it
            distributed.barrier_if(ctx)
            return None
        res = evaluate_checkpoint(None, agent=trainer.agent, task=cfg.task, episodes=episodes,
                                  contexts=contexts, split=a.eval_split, seed=tr.seed + 7, device=device, workers=eval_workers,
                                  counters=c, progress=False if a.no_progress else None, stop=stop)
        res.policy = f"{cfg.variant}@{int(c['env_steps'])}"
        distributed.barrier_if(ctx)
        if stop.stop:
            return res
        log_eval(res, tag)
        print(format_table(res), flush=True)
        return res

    venv = None
    writers: list[EpisodeBagWriter | None] = []
    t_start = time.monotonic()
    status = "failed"   # until the loop below ends normally or is stopped
    cause: BaseException | None = None
    with runs.StopFlag() as stop:
        try:
            if a.random_baseline and main_rank and not (eval_dir / "random.json").exists():
                from sim_bridge.contract.contexts import task_actuators

                rnd = evaluate_checkpoint(None, task=cfg.task, episodes=final_episodes, contexts=final_contexts,
                                          split=a.eval_split,
                                          seed=tr.seed + 7, workers=eval_workers,
                                          time_limit=tr.time_limit, progress=False if a.no_progress else None,
                                          stop=stop)
                if not stop.stop:
                    runs.atomic_write_json(eval_dir / "random.json", rnd.to_dict())
                    print(format_table(rnd), flush=True)
            seed = distributed.rank_seed(tr.seed * 1000 + int(c.get("resumes", 0)), ctx.rank)
            venv = VectorEnv(cfg.task, a.num_envs, split="train", seed=seed, action_repeat=R,
                             render_quality=tr.render_quality,
                             time_limit=tr.time_limit, image_size=tr.image_size, context=a.train_context)
            names = list(venv.action_names)
            dt_ns = int(round(venv.control_dt * 1e9))
            A = venv.action_dim
            rng_policy = RandomPolicy(A, seed=tr.seed + 1000 * int(c.get("resumes", 0)))
            agent_policy = Policy(trainer.agent, device=device, mode="sample",
                                  exploration_noise=tr.expl_noise, seed=tr.seed + int(c["episodes"]))
            n = a.num_envs
            agent_policy.reset(n)

            def prefilling() -> bool:
                return int(c["episodes"]) < N and not int(c["prefill_done"])

            # Asked before every step: the prefill's random policy, then the agent.
            stream = continuing_rollout(venv, lambda: rng_policy if prefilling() else agent_policy)
            ticks = [0] * n
            ep_return = np.zeros(n)
            writers = [None] * n
            bar = runs.progress(a.env_steps, initial=int(c["env_steps"]), desc="env steps",
                                disable=True if a.no_progress or not main_rank else None, unit="step")
            from protocad_ros.model.precision import cpu_capability

            wall = f", wall budget {runs.fmt_seconds(a.wall_budget)}" if a.wall_budget else ""
            say(f"[online] {cfg.task} / {cfg.variant} / {cfg.preset} on {device}: {n} env(s)"
                  + (f" on each of {world} ranks ({ctx.backend})" if ctx.enabled else "") + ", "
                  f"budget {a.env_steps} env steps{wall}, prefill {N} episodes, C={C}, eval every "
                  f"{a.eval_every} env steps on {len(periodic_contexts)} {a.eval_split} contexts; "
                  f"precision {tr.precision}, CPU capability {cpu_capability()}, "
                  f"{runs.torch_threads()} torch thread(s); run dir {run_dir}", flush=True)

            def out_of_wall_time() -> bool:
                return bool(a.wall_budget) and trainer.metrics.wall_time >= a.wall_budget

            def stopped() -> bool:   # collective under torchrun: every rank decides the same
                return distributed.any_rank(stop.stop, ctx)

            def keep_going() -> bool:
                halt = stop.stop or out_of_wall_time()
                return int(c["env_steps"]) < a.env_steps and not distributed.any_rank(halt, ctx)

            while keep_going():
                obs, actions, feats = next(stream)
                prefill = prefilling()
                finished = []
                for i, o in enumerate(obs):
                    stamp = ticks[i] * dt_ns
                    if o.is_first or writers[i] is None:
                        if writers[i] is not None:
                            writers[i].close()
                        name = bag_name(bags_dir, int(c["bags"]), i, attempt, rank_tag)
                        c["bags"] = int(c["bags"]) + 1
                        writers[i] = EpisodeBagWriter(bags_dir / name, names)
                        ep_return[i] = 0.0
                    writers[i].write_observation(o, stamp)
                    writers[i].write_action(actions[i], stamp, _feature_row(feats, i))
                    ticks[i] += 1
                    if not o.is_first:
                        ep_return[i] += o.reward
                        c["agent_steps"] = int(c["agent_steps"]) + world   # counters are global
                        c["env_steps"] = int(c["env_steps"]) + R * world
                        bar.update(R * world)
                    if o.is_last:
                        writers[i].close()
                        finished.append(writers[i].bag_dir)
                        writers[i] = None
                        c["episodes"] = int(c["episodes"]) + world
                        c["last_return"] = float(ep_return[i])
                        trainer.metrics.log(trainer.updates, {"train_return": float(ep_return[i])}, kind="episode",
                                            env_steps=int(c["env_steps"]), episodes=int(c["episodes"]),
                                            prefill=bool(prefill))
                if finished:
                    ds.add(finished)
                    if int(c["episodes"]) >= N and not int(c["prefill_done"]):
                        c["prefill_done"] = 1
                    target = 0
                    if int(c["prefill_done"]):
                        # Algorithm 1: C updates before the first collected episode, then C per
                        # collected episode (a total, so an interrupted phase is made up on resume)
                        target = C + C * max(int(c["episodes"]) - N, 0)
                    if target > trainer.updates and ds.num_windows:
                        bar.set_description(f"train (ep {c['episodes']}, return {c['last_return']:.0f})")
                        trainer.train(target, stop=stop, checkpoint_every=a.checkpoint_every, save=False)
                        bar.set_description("env steps")
                    if (a.eval_every and int(c["env_steps"]) >= int(c["next_eval"]) and not stopped()
                            and int(c["env_steps"]) < a.env_steps):   # at the budget: the final one
                        while int(c["next_eval"]) <= int(c["env_steps"]):
                            c["next_eval"] = int(c["next_eval"]) + a.eval_every
                        evaluate(f"eval_{int(c['env_steps']):08d}", periodic_contexts, stop, a.eval_episodes)
                        c["evals"] = int(c["evals"]) + 1
                        trainer.save()
                if stopped():
                    break
            bar.close()
            if stopped():
                status = "interrupted"
            else:
                status = "finished" if int(c["env_steps"]) >= a.env_steps else "wall_budget"
                final = evaluate("final", final_contexts, stop, final_episodes)
                if main_rank and not stop.stop:
                    print(f"[online] final mean return on {len(final.per_context)} test contexts: "
                          f"{final.mean:.1f}", flush=True)
        except BaseException as exc:
            cause = exc   # the real error: the clean-up below must neither hide nor replace it
            raise
        finally:
            cleanup_errors = close_quietly([*(("closing the bag", w.close) for w in writers if w is not None),
                                            *([("closing the envs", venv.close)] if venv is not None else [])])
            if trainer.updates or status == "interrupted":
                cleanup_errors += close_quietly([("saving the checkpoint", trainer.save)])
            cleanup_errors += close_quietly([("closing the metrics", trainer.close)])
            run_json["result"] = {"status": status, "env_steps": int(c["env_steps"]), "updates": trainer.updates,
                                  "episodes": int(c["episodes"]), "wall_time": round(trainer.metrics.wall_time, 1),
                                  "precision": tr.precision, "resumes": int(c.get("resumes", 0))}
            if cause is not None and not isinstance(cause, (KeyboardInterrupt, SystemExit)):
                run_json["result"]["error"] = f"{type(cause).__name__}: {cause}"
            if main_rank:
                cleanup_errors += close_quietly([(f"writing {run_dir / 'run.json'}",
                                                  lambda: runs.atomic_write_json(run_dir / "run.json", run_json))])
            for what, err in cleanup_errors:
                print(f"[online] while stopping, {what}: {err}", file=sys.stderr, flush=True)
            if cleanup_errors and cause is None:
                raise cleanup_errors[0][1]
    dt = time.monotonic() - t_start
    say(f"[online] {status}: {c['env_steps']} env steps, {c['episodes']} episodes, {trainer.updates} "
          f"updates in {runs.fmt_seconds(dt)}", flush=True)
    say(f"[online] run dir:    {run_dir}\n[online] checkpoint: {trainer.checkpoint_path}\n"
          f"[online] bags:       {bags_dir} ({len(ds.stores)} episodes)\n"
          f"[online] metrics:    {run_dir / 'metrics.jsonl'}\n[online] eval:       {run_dir / 'eval.jsonl'}, {eval_dir}",
          flush=True)
    if status == "interrupted":
        say(f"[online] resume with: protocad-online --run-dir {run_dir} --resume", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
