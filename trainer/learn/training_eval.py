"""Evaluating the agent while it trains (protocad-online's periodic, final and train-context
evaluations, its random baseline): rank 0 evaluates, the other ranks wait for it, and each result
is logged as eval/TAG.json, a line of eval.jsonl, the metrics' eval row and the rerun hooks. No ROS."""
from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

from trainer import console, runs
from trainer.learn import distributed
from trainer.learn.evaluate import EvalPlan, evaluate_checkpoint, format_table, select_contexts
from trainer.learn.schedule import RunCounters
from trainer.learn.trainer import Trainer


class Evaluator:
    """Rank 0 evaluates the current agent (the others wait) and logs the result: eval/TAG.json,
    a line of eval.jsonl, the metrics' eval row and the rerun hooks."""

    def __init__(self, trainer: Trainer, run_dir: Path, ctx: distributed.DistContext, counters: RunCounters, *,
                 task: str, variant: str, split: str, seed: int, device: str, workers: int,
                 progress: bool | None):
        self.trainer, self.task, self.variant, self.split, self.seed = trainer, task, variant, split, seed
        self.device, self.workers, self.c, self.ctx, self.progress = device, workers, counters, ctx, progress
        self.run_dir, self.eval_dir = run_dir, run_dir / "eval"

    def __call__(self, tag: str, contexts, episodes: int, stop: console.StopFlag) -> Any:
        if not self.ctx.is_main:   # rank 0 evaluates; the others wait for it
            distributed.barrier_if(self.ctx)
            return None
        plan = EvalPlan(episodes=episodes, contexts=contexts, split=self.split, seed=self.seed, device=self.device,
                        workers=self.workers, progress=self.progress)
        res = evaluate_checkpoint(None, plan, agent=self.trainer.agent, task=self.task, counters=self.c.as_dict(),
                                  stop=stop)
        res.policy = f"{self.variant}@{self.c.env_steps}"
        distributed.barrier_if(self.ctx)
        if stop.stop:
            return res
        self.log(res, tag)
        print(format_table(res), flush=True)
        return res

    def random_baseline(self, contexts, episodes: int, time_limit: int, stop: console.StopFlag) -> None:
        """The uniform random policy once per run (eval/random.json)."""
        if not self.ctx.is_main or (self.eval_dir / "random.json").exists():
            return
        plan = EvalPlan(episodes=episodes, contexts=contexts, split=self.split, seed=self.seed,
                        workers=self.workers, time_limit=time_limit, progress=self.progress)
        rnd = evaluate_checkpoint(None, plan, task=self.task, stop=stop)
        if not stop.stop:
            runs.atomic_write_json(self.eval_dir / "random.json", rnd.to_dict())
            print(format_table(rnd), flush=True)

    def on_train_contexts(self, episodes: int, stop: console.StopFlag) -> Any:
        """The final agent on every context of the training split: eval/final_train.json
        (outside eval.jsonl, whose rows are the test curve)."""
        if not self.ctx.is_main:
            distributed.barrier_if(self.ctx)
            return None
        plan = EvalPlan(episodes=episodes, contexts=select_contexts(self.task, "train", None, 0), split="train",
                        seed=self.seed, device=self.device, workers=self.workers, progress=self.progress)
        res = evaluate_checkpoint(None, plan, agent=self.trainer.agent, task=self.task, counters=self.c.as_dict(),
                                  stop=stop)
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
