"""`protocad-evaluate` (`ros2 run trainer evaluate`): returns of a checkpoint on a split's contexts.

    protocad-evaluate runs/x/checkpoints/latest.pt                       # test contexts, 5 eps each
    protocad-evaluate runs/a/checkpoints/latest.pt runs/b/... --json out.json  # several tasks
    protocad-evaluate --random --task pendulum_swingup --episodes 5        # random-policy baseline
    protocad-evaluate CKPT --through-ros --episodes 2                      # via the ROS nodes

Paper protocol (ProtoCAD, ICLR 2023, "Evaluation protocol"): train on C_train, evaluate on
C_test; the return of each test context is averaged over its episodes, a task's score is the
mean over its test contexts, and several tasks are summarised by the mean and the median of
their scores. Episodes act with the actor's mode on a sampled posterior, as DreamerV2 and
DreamerPro evaluate (protocad_ros.policy; seeded, so a run repeats itself).

Contexts: every context of the split by default (pendulum, finger, hopper: 4-8; cheetah and
walker: the 8 x 8 = 64 (m, d) grid). `--max-contexts K` takes the fixed stratified subset of
K (every value of m and of d equally often: TaskSpec.stratified); `--context m=0.2,d=1.5`
(repeatable) picks exact ones.

In-process (default): ContextDMCEnv copies with the context fixed per episode, stepped in this
process (`--workers 0`) or in worker processes (`--workers N`), the policy batched over them.
Through ROS (`--through-ros`, trainer/launch/ros_evaluate.py): a sim-bridge node (lock-step, the split's contexts drawn at each
reset: the bridge has no parameter to fix a context), the policy node serving the checkpoint,
and a recorder; the returns are read back from the recorded bag and grouped by the recorded
true context, so the per-context episode counts follow the bridge's draws.
"""
from __future__ import annotations

import dataclasses
import math
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from protocad_ros.atomic import file_sha256
from protocad_ros.checkpoint.files import CheckpointError, existing_checkpoint_file
from sim_bridge.contract.contexts import context_label, get_task, task_actuators
from sim_bridge.sim.rollout import RandomPolicy, rollout
from sim_bridge.sim.vector import VectorEnv
from trainer import console, runs, settings
from trainer.settings import arg, settings_parser

DEFAULT_EPISODES = 5


# ----------------------------------------------------------------------------- results
@dataclass
class ContextResult:
    context: dict[str, float]
    split: str
    returns: list[float] = field(default_factory=list)

    @property
    def mean(self) -> float:
        return float(np.mean(self.returns)) if self.returns else float("nan")

    @property
    def std(self) -> float:
        return float(np.std(self.returns)) if self.returns else float("nan")

    def to_dict(self) -> dict:
        return {"context": self.context, "split": self.split, "episodes": len(self.returns),
                "returns": [round(r, 4) for r in self.returns], "mean_return": self.mean,
                "std_return": self.std}


@dataclass
class EvalResult:
    task: str
    split: str
    policy: str                       # checkpoint path or 'random'
    per_context: list[ContextResult]
    variant: str | None = None
    updates: int | None = None
    env_steps: int | None = None      # the checkpoint's training env steps, if known
    seconds: float = 0.0
    mode: str = "in-process"
    sha256: str | None = None         # the checkpoint file's, so a result names the exact file it measured

    @property
    def mean(self) -> float:
        vals = [c.mean for c in self.per_context if c.returns]
        return float(np.mean(vals)) if vals else float("nan")

    @property
    def median(self) -> float:
        vals = [c.mean for c in self.per_context if c.returns]
        return float(np.median(vals)) if vals else float("nan")

    def to_dict(self) -> dict:
        return {"task": self.task, "split": self.split, "policy": self.policy, "sha256": self.sha256,
                "variant": self.variant, "updates": self.updates, "env_steps": self.env_steps, "mode": self.mode,
                "seconds": round(self.seconds, 2), "mean_return": self.mean,
                "median_over_contexts": self.median,
                "episodes": sum(len(c.returns) for c in self.per_context),
                "per_context": [c.to_dict() for c in self.per_context]}


def format_table(result: EvalResult, *baselines: EvalResult | None) -> str:
    """Plain aligned text: one row per context with episodes, mean, std, and for each baseline
    (another policy on the same contexts) its mean and the difference to it."""
    others = [b for b in baselines if b is not None]
    head = ["context", "episodes", "mean return", "std"]
    for b in others:
        head += [f"{_short(b.policy)} mean", "diff"]
    base = [{context_label(c.context): c for c in b.per_context} for b in others]
    rows = []
    for c in result.per_context:
        r = [context_label(c.context), str(len(c.returns)), f"{c.mean:.1f}", f"{c.std:.1f}"]
        for table in base:
            b = table.get(context_label(c.context))
            r += [f"{b.mean:.1f}" if b else "-", f"{c.mean - b.mean:+.1f}" if b else "-"]
        rows.append(r)
    total = ["mean over contexts", str(sum(len(c.returns) for c in result.per_context)),
             f"{result.mean:.1f}", ""]
    for b in others:
        total += [f"{b.mean:.1f}", f"{result.mean - b.mean:+.1f}"]
    rows.append(total)
    title = (f"{result.task} on {result.split} contexts: {result.policy}"
             + (f" ({result.variant}, {result.updates} updates" if result.variant else "")
             + (f", {result.env_steps} env steps" if result.env_steps is not None and result.variant else "")
             + (")" if result.variant else "") + f" [{result.mode}, {result.seconds:.0f}s]")
    return title + "\n" + _align(head, rows)


def _short(policy: str) -> str:
    """A column name for a policy: 'random', or its file's name."""
    return Path(policy).name if policy not in ("random", "agent") else policy


def format_summary(results: Sequence[EvalResult]) -> str:
    """Per-task scores (mean over its contexts; several checkpoints of a task averaged) and the
    mean / median over tasks."""
    by_task: dict[str, list[EvalResult]] = {}
    for r in results:
        by_task.setdefault(r.task, []).append(r)
    rows, scores = [], []
    for task, rs in by_task.items():
        s = float(np.mean([r.mean for r in rs]))
        scores.append(s)
        rows.append([task, str(len(rs)), ", ".join(r.variant or r.policy for r in rs), f"{s:.1f}"])
    rows.append(["mean over tasks", "", "", f"{np.mean(scores):.1f}"])
    rows.append(["median over tasks", "", "", f"{np.median(scores):.1f}"])
    return "Summary (score = mean return over the split's contexts)\n" + _align(
        ["task", "runs", "policies", "score"], rows)


def summary_dict(results: Sequence[EvalResult]) -> dict:
    by_task: dict[str, list[float]] = {}
    for r in results:
        by_task.setdefault(r.task, []).append(r.mean)
    scores = {t: float(np.mean(v)) for t, v in by_task.items()}
    return {"per_task": scores, "mean_over_tasks": float(np.mean(list(scores.values()))),
            "median_over_tasks": float(np.median(list(scores.values())))}


def _align(head: list[str], rows: list[list[str]]) -> str:
    widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(head)]
    line = lambda r: "  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(r, widths)))  # noqa: E731
    sep = "  ".join("-" * w for w in widths)
    out = [line(head), sep] + [line(r) for r in rows[:-1]] + [sep, line(rows[-1])]
    return "\n".join(out)


# ----------------------------------------------------------------------------- contexts
def parse_context(text: str) -> dict[str, float]:
    out = {}
    for part in text.replace(";", ",").split(","):
        if not part.strip():
            continue
        k, sep, v = part.partition("=")
        if not sep:
            raise ValueError(f"--context expects k=v[,k=v], e.g. m=0.2,d=1.5; got {text!r}")
        out[k.strip()] = float(v)
    return out


def select_contexts(task: str, split: str = "test", contexts: Sequence[Mapping[str, float]] | None = None,
                    max_contexts: int = 0) -> list[dict[str, float]]:
    """The split's contexts (validated), a given subset, or the fixed stratified subset of
    K (TaskSpec.stratified: every value of m and of d equally often; 0 = all)."""
    spec = get_task(task)
    if contexts:
        return [spec.validate(c, split) for c in contexts]
    return spec.stratified(split, max_contexts)


@dataclass(frozen=True)
class RosPlan:
    """What `--through-ros` plays through real nodes (trainer.launch.ros_evaluate): episodes per
    context of the split (the bridge cycles through its contexts), or `total_episodes` drawn
    uniformly; the seed; where the policy runs; the episode length (None: the checkpoint's); the
    ROS domain (None: a free one) and how long the episodes may take."""

    split: str = "test"
    episodes: int = 1
    total_episodes: int = 0
    seed: int = 0
    device: str = "cpu"
    episode_length: int | None = None
    domain_id: int | None = None
    timeout_s: float = 3600.0


@dataclass(frozen=True)
class EpisodePlan:
    """How `run_episodes` plays its episodes: how many per context, the split they are recorded
    under, the seeds, the envs (in worker processes or here; side by side), and each episode's
    length, action repeat and rendering, as the policy was trained with."""

    episodes: int = 1
    split: str = "test"
    seed: int = 0
    workers: int = 0
    batch: int = 0
    action_repeat: int = 2
    time_limit: int = 1000
    render_quality: str = "fast"
    progress: bool | None = None
    desc: str = "eval"


def run_episodes(task: str, policy: Any, contexts: Sequence[Mapping[str, float]], plan: EpisodePlan = EpisodePlan(),
                 stop: console.StopFlag | None = None) -> list[ContextResult]:
    """`plan.episodes` episodes of every context with `policy` (protocad_ros.policy.Policy or
    RandomPolicy; batched over up to `plan.batch` envs). plan.workers > 0: envs in worker
    processes."""
    p = plan
    jobs = [(ci, e) for ci in range(len(contexts)) for e in range(p.episodes)]
    results = [ContextResult(dict(c), p.split) for c in contexts]
    if not jobs:
        return results
    n = min(len(jobs), p.batch or (p.workers if p.workers > 0 else 8))   # one env per worker process
    steps_per_ep = math.ceil(p.time_limit / p.action_repeat)
    bar = console.progress(len(jobs) * steps_per_ep, desc=p.desc, disable=True if p.progress is False else None,
                           unit="step")
    # Seeds as evaluation always drew them (an int from each child of SeedSequence(seed)), so
    # earlier results reproduce.
    env_seeds = [int(s.generate_state(1)[0]) for s in np.random.SeedSequence(p.seed).spawn(n)]
    with VectorEnv(task, n, p.split, p.seed, in_process=p.workers <= 0, env_seeds=env_seeds,
                   action_repeat=p.action_repeat, time_limit=p.time_limit, render_quality=p.render_quality) as pool:
        for w0 in range(0, len(jobs), n):
            if stop is not None and stop.stop:
                break
            wave = jobs[w0:w0 + n]
            done = rollout(pool, policy, [contexts[ci] for ci, _ in wave], on_step=bar.update)
            for (ci, _), t in zip(wave, done):
                results[ci].returns.append(t.ret)
    bar.close()
    return results


@dataclass(frozen=True)
class EvalPlan:
    """What `evaluate_checkpoint` plays: the split's contexts (given ones, or the stratified
    subset of `max_contexts`, 0 = all), episodes per context, the seed of the episodes and of
    the policy's samples, where the model runs, the envs (worker processes, side by side) and
    the episode length (None: the checkpoint's train.time_limit, else 1000)."""

    split: str = "test"
    episodes: int = DEFAULT_EPISODES
    contexts: Sequence[Mapping[str, float]] | None = None
    max_contexts: int = 0
    seed: int = 0
    device: str = "cpu"
    workers: int = 0
    batch: int = 0
    time_limit: int | None = None
    progress: bool | None = None


def evaluate_checkpoint(checkpoint: str | Path | None, plan: EvalPlan = EvalPlan(), *, task: str | None = None,
                        agent: Any = None, counters: Mapping[str, Any] | None = None,
                        stop: console.StopFlag | None = None) -> EvalResult:
    """Evaluate a checkpoint (or an in-memory `agent`, or the random policy when both are None)
    as `plan` says."""
    from protocad_ros.policy import Policy

    t0 = time.monotonic()
    cfg = None
    if agent is None and checkpoint is not None:
        from protocad_ros.checkpoint.agent_file import load_checkpoint

        agent, counters = load_checkpoint(checkpoint, device=plan.device, optimizer_states=False)
    if agent is not None:
        cfg = agent.cfg
        task = task or cfg.task
        if task != cfg.task:
            raise ValueError(f"checkpoint is for {cfg.task}, not {task}")
        policy = Policy(agent, device=plan.device, mode="deterministic", seed=plan.seed)
        repeat, quality = cfg.train.action_repeat, cfg.train.render_quality
        limit = plan.time_limit or cfg.train.time_limit
    else:
        if not task:
            raise ValueError("--random needs --task")

        get_task(task)
        policy = None
        repeat, limit, quality = 2, plan.time_limit or 1000, "fast"
    ctxs = select_contexts(task, plan.split, plan.contexts, plan.max_contexts)
    if policy is None:
        policy = RandomPolicy(len(task_actuators(task)), plan.seed)
    episodes = EpisodePlan(episodes=plan.episodes, split=plan.split, seed=plan.seed, workers=plan.workers,
                           batch=plan.batch, action_repeat=repeat, time_limit=limit, render_quality=quality,
                           progress=plan.progress, desc=f"eval {task}")
    per = run_episodes(task, policy, ctxs, episodes, stop)
    counters = dict(counters or {})
    updates = int(agent.counters()["updates"]) if agent is not None else None
    env_steps = counters.get("env_steps")
    return EvalResult(task=task, split=plan.split, policy=str(checkpoint) if checkpoint else
                      ("agent" if agent is not None else "random"), per_context=per,
                      variant=cfg.variant if cfg else None, updates=updates,
                      env_steps=int(env_steps) if env_steps is not None else None,
                      seconds=time.monotonic() - t0)


# ----------------------------------------------------------------------------- CLI
@dataclass
class EvaluateSettings:
    """What protocad-evaluate runs: which policies, on which contexts, how many episodes."""

    checkpoints: list[str] = arg([], "checkpoints", nargs="*", metavar="CHECKPOINT")
    """checkpoint files (or run directories holding checkpoints/latest.pt)"""
    random: bool = False
    """evaluate the uniform random policy (needs --task; with checkpoints: also shown beside each
    as a baseline)"""
    task: list[str] = arg([], action="append")
    """task(s) for --random (default: the checkpoints' tasks)"""
    split: str = arg("test", choices=("train", "test"))
    """the contexts' split (paper: test = unseen)"""
    episodes: int = DEFAULT_EPISODES
    """episodes per context"""
    context: list[str] = arg([], action="append", metavar="k=v[,k=v]")
    """evaluate only these contexts (repeatable), e.g. --context m=0.2,d=1.5"""
    max_contexts: int = 0
    """the fixed stratified subset of K contexts (every m and d equally often; 0 = all; the
    (m, d) tasks have 64 test contexts)"""
    time_limit: int | None = None
    """env steps per episode (default: the checkpoint's train.time_limit, 1000)"""
    seed: int = 0
    """seeds the contexts' episodes and the policy's samples"""
    device: str = "cpu"
    """cpu, cuda, cuda:N or auto"""
    workers: int = -1
    """env worker processes (0: envs in this process; -1: auto = 0 on <= 2 cores, else cores - 1)"""
    batch: int = 0
    """episodes run side by side (0: auto)"""
    through_ros: bool = False
    """run through the ROS nodes (sim bridge + policy node + recorder): the bridge cycles
    through the split's contexts, --episodes each (or --ros-episodes in all, contexts drawn
    uniformly); each episode's return is in the bridge's log"""
    ros_episodes: int = 0
    """--through-ros: total episodes, contexts drawn uniformly (default: the bridge cycles
    through the split's contexts, --episodes each)"""
    episode_length: int | None = None
    """--through-ros: agent steps per episode (default: the checkpoint's time_limit / action_repeat)"""
    ros_dir: str | None = None
    """--through-ros: where bags and node logs go"""
    domain_id: int | None = None
    """--through-ros: ROS_DOMAIN_ID (default: a fresh one)"""
    json: str | None = arg(None, metavar="FILE")
    """write the results as JSON"""
    threads: int = arg(0, help=settings.THREADS_HELP)
    """torch threads"""
    no_progress: bool = False
    """no progress bar"""


def build_parser():
    return settings_parser(
        "protocad-evaluate",
        "Evaluate checkpoints (or the random policy) on a split's contexts: E episodes per "
        "context, a per-context table with the mean, and the mean / median over tasks when "
        "several are given. Paper protocol: test split, 5 episodes per context, deterministic actions.",
        [(None, EvaluateSettings)])


def main(argv: Sequence[str] | None = None, ros_evaluator: Callable[..., EvalResult] | None = None) -> int:
    """protocad-evaluate; ros_evaluator: the evaluator --through-ros runs (the ROS side's
    trainer.launch.ros_evaluate, whose main passes it: this package does not start nodes)."""
    s = settings.parse(build_parser(), argv, config_help=False).get(EvaluateSettings)
    try:
        return run(s, ros_evaluator)
    except (ValueError, CheckpointError) as exc:
        print(f"protocad-evaluate: error: {exc}", file=sys.stderr)
        return 2


def run(a: EvaluateSettings, ros_evaluator: Callable[..., EvalResult] | None = None) -> int:
    """Evaluate as the settings say, print the tables (and write --json)."""
    if a.through_ros and ros_evaluator is None:
        raise ValueError("--through-ros starts ROS nodes: run it as protocad-evaluate (trainer.launch.ros_evaluate)")
    from trainer import torch_setup

    torch_setup.setup_torch(a.threads)
    device = torch_setup.resolve_device(a.device)
    if not a.checkpoints and not a.random:
        raise ValueError("give CHECKPOINT(s) or --random --task TASK")
    if a.episodes < 1:
        raise ValueError("--episodes must be >= 1")
    workers = a.workers if a.workers >= 0 else (0 if (os.cpu_count() or 1) <= 2 else (os.cpu_count() or 2) - 1)
    ckpts = [existing_checkpoint_file(c) for c in a.checkpoints]
    contexts = [parse_context(c) for c in a.context]
    plan = EvalPlan(split=a.split, episodes=a.episodes, contexts=contexts, max_contexts=a.max_contexts,
                    seed=a.seed, device=device, workers=workers, batch=a.batch, time_limit=a.time_limit,
                    progress=False if a.no_progress else None)
    ros_plan = RosPlan(split=a.split, episodes=a.episodes, total_episodes=a.ros_episodes, seed=a.seed,
                       episode_length=a.episode_length, domain_id=a.domain_id)
    results: list[EvalResult] = []
    baselines: dict[str, EvalResult] = {}
    out: dict[str, Any] = {"split": a.split, "episodes_per_context": a.episodes, "seed": a.seed, "results": []}
    with console.StopFlag() as stop:
        random_tasks = list(a.task)
        for ck in ckpts:
            sha = file_sha256(ck)   # the file as evaluation began (a live run may replace latest.pt)
            if a.through_ros:
                r = ros_evaluator(str(ck), dataclasses.replace(ros_plan, device=device), task=None,
                                  out_dir=Path(a.ros_dir or ck.parent.parent / "eval_ros"))
            else:
                r = evaluate_checkpoint(ck, plan, stop=stop)
            r.sha256 = sha
            results.append(r)
            if a.random and r.task not in random_tasks:
                random_tasks.append(r.task)
        if a.random:
            if not random_tasks:
                raise ValueError("--random needs --task TASK (or checkpoints to take tasks from)")
            for t in random_tasks:
                if a.through_ros:
                    r = ros_evaluator(None, ros_plan, task=t, out_dir=Path(a.ros_dir or "runs/eval_ros"))
                else:
                    r = evaluate_checkpoint(None, dataclasses.replace(plan, device="cpu"), task=t, stop=stop)
                baselines[t] = r
        interrupted = stop.stop
    for r in results:
        print(format_table(r, baselines.get(r.task)))
        print()
    if not results:
        for r in baselines.values():
            print(format_table(r))
            print()
    scored = results or list(baselines.values())
    if len({r.task for r in scored}) > 1 or len(scored) > 1:
        print(format_summary(scored))
        print()
    out["results"] = [r.to_dict() for r in results]
    out["random"] = [r.to_dict() for r in baselines.values()]
    out["summary"] = summary_dict(scored)
    if baselines:
        out["random_summary"] = summary_dict(list(baselines.values()))
    if a.json:
        runs.atomic_write_json(Path(a.json), out)
        print(f"[evaluate] results: {a.json}")
    if interrupted:
        print("[evaluate] interrupted: results cover the episodes finished before Ctrl-C", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
