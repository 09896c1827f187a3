#!/usr/bin/env python3
"""What one actor puts on the wire and on disk: the CDR size of each contract message of a step,
and how many steps per second one bag writer (one core, the recorder's writer) stores, with
zstd chunk compression and without, on real rendered frames (random actions, no repeats).

    python scripts/bench_wire.py                   # walker_walk, 2000 steps
    python scripts/bench_wire.py --task pendulum_swingup --steps 4000

msgs_docs/scaling.md turns these figures into bandwidth and recorder counts for 10-1000 actors.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

# Measure the working tree this script belongs to, not an installed copy of the packages.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from protocad_ros.model.precision import cpu_capability
from sim_bridge.contract import topics as T
from sim_bridge.sim.envs import ContextDMCEnv
from trainer.bag.rosmsg import encode, new_message
from trainer.research.online_rundir import EpisodeBagWriter


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog=__doc__.split("\n\n", 1)[1])
    ap.add_argument("--task", default="walker_walk")
    ap.add_argument("--steps", type=int, default=2000)
    a = ap.parse_args(argv)
    print(f"machine: {os.cpu_count()} cores, CPU capability {cpu_capability()}; load average "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    env = ContextDMCEnv(a.task, "train", seed=0, time_limit=2 * a.steps + 2)
    rng = np.random.default_rng(0)
    obs = [env.reset()]
    obs += [env.step(rng.uniform(-1, 1, env.action_dim)) for _ in range(a.steps - 1)]
    names, dt = list(env.action_names), env.control_dt
    env.close()
    new, o = new_message, obs[1]
    sizes = {
        "image": encode(T.TYPES[T.IMAGE], T.fill_image(new(T.TYPES[T.IMAGE]), o.image, 0)),
        "step_info": encode(T.TYPES[T.STEP_INFO], T.fill_step_info(
            new(T.TYPES[T.STEP_INFO]), T.StepInfo(0.0, 1.0, False, False, False, 0, 1), 0)),
        "context": encode(T.TYPES[T.CONTEXT], T.fill_context(
            new(T.TYPES[T.CONTEXT]), o.context, o.split, 0)),
        "action": encode(T.TYPES[T.ACTION], T.fill_action(
            new(T.TYPES[T.ACTION]), np.zeros(len(names)), names, 0)),
    }
    total = sum(len(v) for v in sizes.values())
    print(f"{a.task}: control period {dt * 1000:.0f} ms ({1 / dt:.0f} steps/s in real time); CDR bytes "
          "per step: " + ", ".join(f"{k} {len(v):,}" for k, v in sizes.items()) + f"; total {total:,}")
    for comp in ("zstd", "none"):
        with tempfile.TemporaryDirectory() as tmp:
            w = EpisodeBagWriter(Path(tmp) / "bag", names, compression=comp)
            t0 = time.perf_counter()
            for i, ob in enumerate(obs):
                stamp = i * int(round(dt * 1e9))
                w.write_observation(ob, stamp)
                w.write_action(np.zeros(len(names)), stamp)
            w.close()
            rate = len(obs) / (time.perf_counter() - t0)
            size = sum(f.stat().st_size for f in (Path(tmp) / "bag").glob("*.mcap"))
        print(f"bag writer, {comp:4}: {rate:,.0f} steps/s ({len(obs)} steps, 5 messages each), "
              f"{size / len(obs):,.0f} bytes/step on disk")
    return 0


if __name__ == "__main__":
    sys.exit(main())
