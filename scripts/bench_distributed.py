#!/usr/bin/env python3
"""Learner updates/s on 1 process and on N data-parallel ranks (torchrun, gloo on CPU or NCCL on
GPUs), side by side in one run on one machine, with the same global batch.

    python scripts/bench_distributed.py                      # small preset, 1 vs 2 ranks on CPU
    python scripts/bench_distributed.py --preset paper --updates 6 --ranks 1 2
    python scripts/bench_distributed.py --device cuda --ranks 1   # a GPU machine

It records a few episodes of real frames (random actions) into bags first, then runs
`protocad-train` on them: the 1-rank row gets every torch thread, the N-rank rows share them out
(threads // N each), so on a CPU the rows compare ways of spending the same cores.
"""
from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

# Measure the working tree this script belongs to, not an installed copy of the packages.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from protocad_ros.model.precision import cpu_capability
from sim_bridge.sim.envs import ContextDMCEnv
from trainer.research.online_rundir import EpisodeBagWriter

ROOT = Path(__file__).resolve().parents[1]


def record_bags(out: Path, task: str, episodes: int, steps: int) -> None:
    env = ContextDMCEnv(task, "train", seed=0, time_limit=2 * steps)
    rng = np.random.default_rng(0)
    dt = int(round(env.control_dt * 1e9))
    for e in range(episodes):
        writer = EpisodeBagWriter(out / f"ep{e}", env.action_names)
        obs = env.reset()
        for i in range(steps + 1):
            action = rng.uniform(-1, 1, env.action_dim)
            writer.write_observation(obs, i * dt)
            writer.write_action(action, i * dt)
            if obs.is_last:
                break
            obs = env.step(action)
        writer.close()
    env.close()


def run_row(ranks: int, threads: int, a: argparse.Namespace, bags: Path, work: Path) -> str:
    train = [sys.executable, "-m", "trainer.learn.train", "--bags", str(bags), "--task", a.task,
             "--preset", a.preset, "--variant", a.variant, "--updates", str(a.updates),
             "--run-dir", str(work / f"run{ranks}"), "--no-progress", "--device", a.device,
             "--threads", str(threads), "--cache-dir", str(work / "cache"),
             "--precision", a.precision, "--checkpoint-every", str(10 ** 9)]
    if a.batch_size:
        train += ["--batch-size", str(a.batch_size)]
    cmd = train if ranks == 1 else [sys.executable, "-m", "torch.distributed.run", "--standalone",
                                    "--nproc_per_node", str(ranks), "--no-python", *train]
    env = {**os.environ, "GLOO_SOCKET_IFNAME": "lo", "OMP_NUM_THREADS": str(threads),
           "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    p = subprocess.run(cmd, capture_output=True, text=True, env=env)
    m = re.search(r"finished at update \d+ \((\d+) updates in ([^,]+), ([0-9.]+)/s\)", p.stdout)
    if p.returncode != 0 or not m:
        return f"ERROR: {(p.stderr.strip().splitlines() or p.stdout.strip().splitlines() or ['?'])[-1]}"
    batch = re.search(r"batch (\d+ x \d+)", p.stdout)
    return f"{m.group(3):>9} updates/s   ({m.group(1)} updates in {m.group(2)}; global batch {batch.group(1)})"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog=__doc__.split("\n\n", 1)[1])
    ap.add_argument("--task", default="pendulum_swingup")
    ap.add_argument("--preset", default="small")
    ap.add_argument("--variant", default="protocad")
    ap.add_argument("--ranks", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--updates", type=int, default=20, help="updates per row (one run each)")
    ap.add_argument("--batch-size", type=int, default=None, help="global batch (default the preset's)")
    ap.add_argument("--threads", type=int, default=os.cpu_count(), help="torch threads in all")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--precision", default="auto", choices=["auto", "float32", "bfloat16"])
    a = ap.parse_args(argv)
    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "no GPU"
    print(f"machine: {os.cpu_count()} cores, CPU capability {cpu_capability()}, {gpu}, torch "
          f"{torch.__version__}; load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    print(f"{a.task} / {a.variant} / {a.preset} on {a.device}, precision {a.precision}, "
          f"{a.threads} torch thread(s) in all")
    with tempfile.TemporaryDirectory(prefix="bench_dist_") as tmp:
        work = Path(tmp)
        record_bags(work / "bags", a.task, episodes=3, steps=150)
        for n in a.ranks:
            threads = max(1, a.threads // n)
            print(f"{n} rank(s) x {threads} thread(s): {run_row(n, threads, a, work / 'bags', work)}",
                  flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
