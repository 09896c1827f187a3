#!/usr/bin/env python3
"""Benchmark of the in-process research path (protocad-online's loop), by part: env steps/s
of collection (the env alone, and env + Policy.act + the MCAP bag writer), and seconds per
training update split into sampling the batch from the dataset, the world model and the
behaviour (imagination + actor-critic; DrQ's update is one piece: critic, actor, temperature),
each configuration in its own fresh process, side by side in one run on one machine.  The last
column is what 1000 env steps cost at the variant's own schedule: collection plus its C updates
per 1000-step episode (Dreamer-family 100, DreamerPro 200, DrQ 500).

    python scripts/bench_online.py                              # small preset, float32 vs auto
    python scripts/bench_online.py --precision float32 bfloat16 --preset paper --updates 5
    python scripts/bench_online.py --variants protocad dreamer drq --precision auto

"float32" is how this path trained before precision was chosen from the hardware; "auto" is
what `protocad-online` does now (bfloat16 where the CPU has AVX512-BF16/AMX, else float32),
so the two rows are the before and after of that change on this machine. The CPU capability
line says which one auto picks here.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

# Measure the working tree this script belongs to, not an installed copy of the packages.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from protocad_ros.model.config import make_config
from protocad_ros.model.precision import cpu_capability, resolve_precision
from protocad_ros.policy import Policy
from sim_bridge.sim.envs import ContextDMCEnv
from trainer.data.dataset import MCAPDataset, TopicMap
from trainer.learn.trainer import Trainer
from trainer.research.online_rundir import EpisodeBagWriter

ROOT = Path(__file__).resolve().parents[1]


def worker(spec: dict) -> dict:
    torch.set_num_threads(spec["threads"])
    prec = resolve_precision(spec["precision"], "cpu", explicit=True).precision
    cfg = make_config(spec["task"], spec["preset"], spec["variant"], **{"train.precision": prec})
    work = Path(tempfile.mkdtemp(prefix="bench_online_"))
    env = ContextDMCEnv(spec["task"], "train", seed=0, time_limit=2 * spec["steps"])
    rng = np.random.default_rng(0)
    # 1. the env alone, random actions
    env.reset()
    t0 = time.perf_counter()
    for _ in range(spec["steps"]):
        obs = env.step(rng.uniform(-1, 1, env.action_dim))
    env_only = spec["steps"] / (time.perf_counter() - t0)
    # 2. collection as protocad-online does it: env + Policy.act + the bag writer
    trainer = Trainer(cfg, work / "run", None, action_dim=env.action_dim)
    trainer.agent.use_precision(prec)   # as the bench's command line asked, even where emulated
    policy = Policy(trainer.agent, mode="sample")
    policy.reset(1)
    writer = EpisodeBagWriter(work / "bags" / "ep0", env.action_names)
    obs = env.reset()
    prev = np.zeros((1, env.action_dim), np.float32)
    t0 = time.perf_counter()
    act_s = 0.0
    for i in range(spec["steps"]):
        ta = time.perf_counter()
        action, feats = policy.act(obs.image[None], prev, np.array([obs.is_first]))
        act_s += time.perf_counter() - ta
        writer.write_observation(obs, i * 40_000_000)
        writer.write_action(action[0], i * 40_000_000)
        prev = np.asarray(action, np.float32)
        obs = env.step(action[0])
    writer.close()
    collect = spec["steps"] / (time.perf_counter() - t0)
    env.close()
    # 3. updates on what was collected
    ds = MCAPDataset([work / "bags" / "ep0"], topics=TopicMap(), seq_len=cfg.train.seq_len, seed=0,
                     cache_dir=work / "cache")
    trainer.dataset = ds
    B = cfg.train.batch_size
    for _ in range(spec["warmup"]):
        trainer.update()
    world_model = cfg.spec.family == "world_model"
    sample_t, wm_t, beh_t, total_t = [], [], [], []
    for _ in range(spec["updates"]):
        t0 = time.perf_counter()
        batch = MCAPDataset.training_batch(ds.gather(ds.sample_index(B)))
        t1 = time.perf_counter()
        if world_model:
            start, _ = trainer.agent.train_world_model(batch)
            t2 = time.perf_counter()
            trainer.agent.train_behavior(start)
            trainer.agent.updates += 1
        else:   # one piece (critic, actor, temperature): reported as 'wm', beh 0
            trainer.agent.train_step(batch)
            t2 = time.perf_counter()
        t3 = time.perf_counter()
        sample_t.append(t1 - t0)
        wm_t.append(t2 - t1)
        beh_t.append(t3 - t2)
        total_t.append(t3 - t0)
    trainer.close()
    R = cfg.train.action_repeat
    sec_update = float(np.mean(total_t))
    per_1k = 1000 / (R * collect) + cfg.train.collect_interval * 1000 / cfg.train.time_limit * sec_update
    return {"precision": prec, "env_steps_per_s_env_only": R * env_only,
            "env_steps_per_s_collect": R * collect, "act_ms": 1e3 * act_s / spec["steps"],
            "sec_update": sec_update, "updates_per_s": 1.0 / sec_update,
            "sec_sample": float(np.mean(sample_t)), "sec_wm": float(np.mean(wm_t)),
            "sec_beh": float(np.mean(beh_t)), "updates_per_episode": cfg.train.collect_interval,
            "batch": f"{B}x{cfg.train.seq_len}", "sec_per_1k_env_steps": per_1k}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog=__doc__.split("\n\n", 1)[1])
    ap.add_argument("--task", default="pendulum_swingup")
    ap.add_argument("--preset", default="small")
    ap.add_argument("--variants", nargs="+", default=["protocad"],
                    help="variants, each timed in its own process (e.g. protocad dreamer drq)")
    ap.add_argument("--precision", nargs="+", default=["float32", "auto"],
                    choices=["float32", "bfloat16", "auto"])
    ap.add_argument("--steps", type=int, default=300, help="agent steps per collection measurement")
    ap.add_argument("--updates", type=int, default=10, help="timed updates")
    ap.add_argument("--warmup", type=int, default=2, help="untimed updates first")
    ap.add_argument("--threads", type=int, default=1, help="torch threads")
    ap.add_argument("--json", type=Path, default=None, help="also write the rows here")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.worker:
        print(json.dumps(worker(json.loads(a.worker))))
        return 0
    print(f"machine: {os.cpu_count()} cores, torch {torch.__version__}, {a.threads} torch thread(s); "
          f"CPU capability {cpu_capability()}; load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    print(f"{a.task} / {a.preset}; collection {a.steps} agent steps (env steps = action repeat x), "
          f"{a.updates} timed updates")
    head = (f"{'variant':10} {'precision':18} {'batch':>7} {'env only':>9} {'collect':>8} {'act ms':>7} "
            f"{'s/update':>9} {'upd/s':>6} {'sample':>7} {'wm':>6} {'beh':>6} {'C':>4} {'s/1k env':>9}")
    print(head + "\n" + "-" * len(head))
    rows = []
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    for variant in a.variants:
        for prec in a.precision:
            spec = {"task": a.task, "preset": a.preset, "variant": variant, "precision": prec,
                    "steps": a.steps, "updates": a.updates, "warmup": a.warmup, "threads": a.threads}
            p = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--worker", json.dumps(spec)],
                               capture_output=True, text=True, env=env)
            if p.returncode != 0:
                print(f"{variant:10} {prec:18} ERROR: {(p.stderr.strip().splitlines() or ['?'])[-1]}")
                continue
            r = json.loads(p.stdout.strip().splitlines()[-1])
            rows.append({**spec, **r})
            label = prec if prec == r["precision"] else f"{prec} -> {r['precision']}"
            print(f"{variant:10} {label:18} {r['batch']:>7} {r['env_steps_per_s_env_only']:9.0f} "
                  f"{r['env_steps_per_s_collect']:8.0f} {r['act_ms']:7.2f} {r['sec_update']:9.3f} "
                  f"{r['updates_per_s']:6.2f} {r['sec_sample']:7.3f} {r['sec_wm']:6.3f} {r['sec_beh']:6.3f} "
                  f"{r['updates_per_episode']:4d} {r['sec_per_1k_env_steps']:9.1f}", flush=True)
    print("env only / collect: env steps per second (collect = env + Policy.act + bag writer); "
          "s/update = sample + wm (world model; DrQ: its whole update) + beh (behaviour); "
          "s/1k env = collecting 1000 env steps + the variant's C updates per 1000-step episode")
    if a.json:
        a.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
