#!/usr/bin/env python3
"""Agent steps per second of the context-randomized DMC tasks, and what 'fast' rendering costs.

For each task: one process (ContextDMCEnv) and a VectorEnv (--workers processes), each with
'default' (suite look: shadows, reflections, 4x MSAA, 640x480 offscreen buffer) and 'fast'
(none of these, image-sized buffer) rendering; random actions, auto-reset at episode ends.
The pixel difference is the mean absolute difference (0-255 scale, over pixels and channels)
between the two qualities' frames of the same states (same seed and actions in one process).
Run with MUJOCO_GL=egl (scripts/env.sh sets it).
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

# Measure the working tree this script belongs to, not an installed copy of the packages.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from sim_bridge.contract.contexts import TASKS
from sim_bridge.sim.envs import RENDER_QUALITIES, ContextDMCEnv
from sim_bridge.sim.vector import VectorEnv


def single(task: str, quality: str, actions: np.ndarray, seed: int, split: str
           ) -> tuple[float, np.ndarray]:
    """(agent steps/s, frames) over len(actions) steps after a short warm-up."""
    with ContextDMCEnv(task, split, seed, render_quality=quality) as env:
        env.reset()
        for a in actions[:5]:  # first frames pay for shader compilation and uploads
            env.step(a)
        env.reset()
        frames = []
        start = time.perf_counter()
        for a in actions:
            obs = env.step(a)
            frames.append(obs.image)
            if obs.is_last:
                env.reset()
        return len(actions) / (time.perf_counter() - start), np.stack(frames)


def vector(task: str, quality: str, workers: int, steps: int, seed: int, split: str) -> float:
    """Total agent steps/s of all workers together."""
    rng = np.random.default_rng(seed)
    with VectorEnv(task, workers, split, seed, render_quality=quality) as venv:
        venv.reset()
        for _ in range(5):
            venv.step(rng.uniform(-1, 1, (workers, venv.action_dim)))
        actions = rng.uniform(-1, 1, (steps, workers, venv.action_dim))
        start = time.perf_counter()
        for a in actions:
            venv.step(a)
        return steps * workers / (time.perf_counter() - start)


def cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tasks", nargs="+", default=sorted(TASKS), choices=sorted(TASKS),
                        metavar="TASK", help="tasks to measure (default: all eight)")
    parser.add_argument("--steps", type=int, default=500,
                        help="timed agent steps per measurement (default 500 = one episode)")
    parser.add_argument("--workers", type=int, default=2,
                        help="VectorEnv worker processes; 0 skips the VectorEnv runs (default 2)")
    parser.add_argument("--split", default="train", choices=("train", "test"))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--frames", type=Path, metavar="PNG",
                        help="also save four frames of the same states in both looks, per task two rows "
                             "(fast above default), 3x enlarged")
    args = parser.parse_args()

    print(f"# {cpu_model()}, nproc={os.cpu_count()}, MUJOCO_GL={os.environ.get('MUJOCO_GL')}, "
          f"action_repeat=2, 64x64, {args.steps} timed agent steps, random actions")
    vec = f"vec{args.workers}"
    header = (f"{'task':18} {'1proc default':>14} {'1proc fast':>11}"
              + (f" {vec + ' default':>13} {vec + ' fast':>10}" if args.workers else "")
              + f" {'speed-up':>8} {'pixel diff':>10}")
    print(header)
    print("-" * len(header))
    strips = []
    for task in args.tasks:
        rng = np.random.default_rng(args.seed)
        probe = ContextDMCEnv(task, args.split, args.seed)
        actions = rng.uniform(-1, 1, (args.steps, probe.action_dim))
        probe.close()
        rate, frames = {}, {}
        for quality in RENDER_QUALITIES:
            rate[quality], frames[quality] = single(task, quality, actions, args.seed, args.split)
        vrate = {q: vector(task, q, args.workers, args.steps, args.seed, args.split)
                 for q in RENDER_QUALITIES} if args.workers else {}
        diff = np.abs(frames["default"].astype(np.int16) - frames["fast"]).mean()
        row = f"{task:18} {rate['default']:14.1f} {rate['fast']:11.1f}"
        if vrate:
            row += f" {vrate['default']:13.1f} {vrate['fast']:10.1f}"
        print(row + f" {rate['fast'] / rate['default']:7.1f}x {diff:10.2f}", flush=True)
        picks = np.linspace(len(actions) // 10, len(actions) - 1, 4).astype(int)
        strips += [np.concatenate(list(frames[q][picks]), axis=1) for q in ("fast", "default")]
    print("# steps/s = agent steps per second (x2 env steps); vecN = all N workers together; "
          "pixel diff = mean |default - fast| on the same states, 0-255")
    if args.frames:
        from PIL import Image

        grid = np.concatenate(strips, axis=0)
        Image.fromarray(grid).resize((grid.shape[1] * 3, grid.shape[0] * 3), Image.NEAREST).save(args.frames)
        print(f"# frames: {args.frames}")


if __name__ == "__main__":
    main()
