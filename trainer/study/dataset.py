"""The study's dataset: the shipped walker policy with exploration noise on the 25 training
contexts (DATA/train, two whole episodes each) and its mode on all 64 unseen and 25 training
contexts (DATA/eval, one shorter episode each), written as the ROS path's bags; DATA/dataset.json
names the command, the seed, the policy's sha256 and every bag's, and one digest of them all."""
from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from protocad_ros.atomic import atomic_write_text, file_sha256
from protocad_ros.policy import Policy, shipped_policy
from sim_bridge.contract.contexts import get_task
from sim_bridge.sim.rollout import rollout
from sim_bridge.sim.vector import VectorEnv
from trainer.research.online_rundir import EpisodeBagWriter

TASK = "walker_walk"


def _write_episode(bag_dir: Path, names: Sequence[str], t: Any, split: str, full_length: int) -> None:
    a = t.arrays()
    n = len(a["image"])
    w = EpisodeBagWriter(bag_dir, names)
    try:
        for i in range(n):
            obs = type("Obs", (), dict(
                context=t.context, split=split, reward=float(a["reward"][i]), discount=float(a["discount"][i]),
                is_first=bool(a["is_first"][i]), is_last=i == n - 1 and n == full_length, is_terminal=False,
                episode=0, step=i, image=a["image"][i]))()
            stamp = (i + 1) * 10_000_000
            w.write_observation(obs, stamp)
            answer = a["action"][i + 1] if i + 1 < n else np.zeros_like(a["action"][0])
            w.write_action(answer, stamp)
    finally:
        w.close()


def record(data: Path, seed: int = 0, train_episodes: int = 2, noise: float = 0.3,
           eval_steps: int = 150) -> dict[str, Any]:
    """Record the study's dataset: DATA/train (noisy shipped policy, 25 training contexts) and
    DATA/eval (the policy's mode, 64 unseen + 25 training contexts), then DATA/dataset.json."""
    data, spec = Path(data), get_task(TASK)
    policy_file = shipped_policy(TASK)
    full = 1000 // 2 + 1
    jobs = [("train", "train", c, noise, full) for c in spec.contexts("train") for _ in range(train_episodes)]
    jobs += [("eval", split, c, 0.0, eval_steps) for split in ("test", "train") for c in spec.contexts(split)]
    t0 = time.monotonic()
    agent = Policy.from_checkpoint(policy_file).agent
    for k, (part, split, ctx, noise, steps) in enumerate(jobs):
        bag = data / part / f"{part}_{k:04d}"
        if (bag / "metadata.yaml").exists():
            continue   # written before an interruption
        policy = Policy(agent, mode="sample" if noise else "deterministic", exploration_noise=noise,
                        seed=seed * 100_003 + k)
        with VectorEnv(TASK, 1, split, seed=seed * 100_003 + k, in_process=True,
                       render_quality=policy.agent.cfg.train.render_quality) as pool:
            (traj,) = rollout(pool, policy, [ctx], max_steps=steps, record=True)
            _write_episode(bag, pool.action_names, traj, split, full)
        print(f"[study] {k + 1}/{len(jobs)} {bag.name} {split} {ctx} return {traj.ret:.1f} "
              f"({time.monotonic() - t0:.0f}s)", flush=True)
    bags = sorted(str(p.relative_to(data)) for p in data.glob("*/*/*.mcap"))
    doc = {"command": ["protocad-study", "record", "--data", str(data), "--seed", str(seed),
                       "--train-episodes", str(train_episodes), "--noise", str(noise),
                       "--eval-steps", str(eval_steps)],
           "task": TASK, "policy_sha256": file_sha256(policy_file),
           "bags": {b: file_sha256(data / b) for b in bags}}
    doc["sha256"] = _digest(doc["bags"])
    atomic_write_text(data / "dataset.json", json.dumps(doc, indent=1))
    print(f"[study] dataset {data}: {len(bags)} bags, sha256 {doc['sha256']}", flush=True)
    return doc


def _digest(bags: Mapping[str, str]) -> str:
    return hashlib.sha256("".join(f"{k} {v}\n" for k, v in sorted(bags.items())).encode()).hexdigest()


