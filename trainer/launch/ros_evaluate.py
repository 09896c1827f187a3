"""`protocad-evaluate` (`ros2 run trainer evaluate`), whose --through-ros runs the episodes
through real ROS processes: a sim-bridge node (lock-step, the split's contexts drawn at each
reset), the policy node serving the checkpoint (or the random actor) and a recorder; the returns
are read back from the recorded bag and grouped by the recorded true context. The in-process
evaluation, the tables and the command line are trainer/learn/evaluate.py's; starting nodes is
this package's, so the evaluator is handed to it from here."""
from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Sequence

from protocad_ros.model.config import Config
from sim_bridge.contract.contexts import context_label, get_task
from trainer.launch import rosprocs
from trainer.learn import evaluate
from trainer.learn.evaluate import ContextResult, EvalResult, RosPlan


def main(argv: Sequence[str] | None = None) -> int:
    return evaluate.main(argv, ros_evaluator=evaluate_through_ros)


def evaluate_through_ros(checkpoint: str | None, plan: RosPlan = RosPlan(), *, task: str | None,
                         out_dir: Path) -> EvalResult:
    """Run the episodes `plan` asks for through real ROS processes (bridge + policy node or
    random actor + recorder), then read the returns from the recorded bag (grouped by the true
    context). Without `plan.total_episodes` the bridge cycles through the split's contexts, so
    each gets exactly `plan.episodes` episodes; with it, contexts are drawn uniformly."""
    split, seed, total_episodes = plan.split, plan.seed, plan.total_episodes
    from trainer.data.dataset import MCAPDataset

    t0 = time.monotonic()
    cfg = None
    updates = env_steps = None
    if checkpoint:
        from protocad_ros.checkpoint.agent_file import read_checkpoint

        payload = read_checkpoint(checkpoint)
        cfg = Config.from_dict(payload["config"])
        task = task or cfg.task
        updates = int(payload["modules"]["updates"]) if "updates" in payload["modules"] else None
        env_steps = payload.get("counters", {}).get("env_steps")
    if not task:
        raise ValueError("give a checkpoint or --task")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    bag = out_dir / f"eval_{split}_{time.strftime('%Y%m%d-%H%M%S')}"
    stack = rosprocs.RosStack(out_dir / "logs", domain_id=plan.domain_id)
    ep_len = plan.episode_length or ((cfg.train.time_limit // cfg.train.action_repeat) if cfg else 500)
    total = total_episodes or plan.episodes * len(get_task(task).contexts(split))
    try:
        if checkpoint:
            stack.start_policy(checkpoint=checkpoint, task=task, seed=seed, device=plan.device, mode="deterministic",
                               reload_poll_s=0.0)
        else:  # the random baseline: uniform random actions
            stack.start_random_actor(task=task, seed=seed)
        stack.start_recorder(bag, wait_topics=[f"{stack.namespace}/action"])
        bridge = stack.start_bridge(task=task, split=split, seed=seed, max_episodes=total,
                                    context_schedule="sample" if total_episodes else "cycle",
                                    episode_length=ep_len, action_repeat=cfg.train.action_repeat if cfg else 2)
        stack.wait_exit(bridge, plan.timeout_s)
    finally:
        stack.stop_all()
    ds = MCAPDataset([bag], seq_len=1, cache_dir=out_dir / "cache")
    per: dict[str, ContextResult] = {}
    for e in ds.episodes():
        if not (e["has_first"] and e["has_last"]) or e["context"] is None:
            continue
        key = context_label(e["context"])
        print(f"[evaluate] episode {e['episode']} ({e['split'] or split} context {key}): "
              f"return {e['return']:.1f} over {e['length'] - 1} steps", flush=True)
        per.setdefault(key, ContextResult(e["context"], e["split"] or split)).returns.append(e["return"])
    ordered = sorted(per.values(), key=lambda c: tuple(c.context.values()))
    return EvalResult(task=task, split=split, policy=str(checkpoint) if checkpoint else "random",
                      per_context=ordered, variant=cfg.variant if cfg else None, updates=updates,
                      env_steps=env_steps, seconds=time.monotonic() - t0, mode="through ROS")


if __name__ == "__main__":
    sys.exit(main())
