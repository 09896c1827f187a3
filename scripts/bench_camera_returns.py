"""Returns of a policy when its 64x64 input comes from a camera-sized render (the sim bridge's
camera option, then `sim_bridge.contract.camera` as the policy node does it) against the native
64x64 render, on the same unseen contexts and seeds, in process (no DDS): how much a policy
trained on the native renders loses to the camera path (msgs_docs/robot.md).

    python scripts/bench_camera_returns.py --every 2 --count 32 --steps 150 --ways native,box
"""
from __future__ import annotations

import argparse
import itertools
import time

import numpy as np
import torch
from PIL import Image

from protocad_ros.policy import Policy
from sim_bridge.contract import camera
from sim_bridge.contract.contexts import get_task
from sim_bridge.sim.envs import ContextDMCEnv

WAYS = ("native", "box", "nearest", "bilinear", "swap", "full")


def model_input(frame: np.ndarray, way: str) -> np.ndarray:
    """native: the 64x64 render as is; box: what the policy node does (center crop, area
    averaging); nearest/bilinear: other filters; swap: box with the colour channels reversed (a
    bgr/rgb mix-up); full: the whole 4:3 frame squashed (a wrong crop)."""
    if way == "native":
        return frame
    if way == "swap":
        return camera.resize(frame, 64)[:, :, ::-1].copy()
    if way == "full":
        return camera.resize(frame, 64, camera.Crop("full"))
    if way == "box":
        return camera.resize(frame, 64)
    f = {"nearest": Image.Resampling.NEAREST, "bilinear": Image.Resampling.BILINEAR}[way]
    box = camera.Crop().box(*frame.shape[:2])
    return np.asarray(Image.fromarray(frame).resize((64, 64), f, box=box))


def episode(policy: Policy, task: str, context: dict, seed: int, way: str, steps: int,
            camera_hw: tuple[int, int]) -> float:
    env = ContextDMCEnv(task, "test", seed=seed, context=context, time_limit=2 * steps,
                        camera_size=None if way == "native" else camera_hw)
    try:
        obs, ret = env.reset(), 0.0
        policy.reset()
        prev = np.zeros(policy.agent.action_dim, np.float32)
        while not obs.is_last:
            action, _ = policy.act(model_input(obs.image, way), prev, bool(obs.is_first))
            prev = np.asarray(action, np.float32).reshape(-1)
            obs = env.step(prev)
            ret += float(obs.reward)
        return ret
    finally:
        env.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--policy", default="protocad_ros/policies/walker_walk.pt")
    ap.add_argument("--every", type=int, default=2, help="every N-th unseen context of the grid")
    ap.add_argument("--count", type=int, default=32, help="at most this many contexts")
    ap.add_argument("--steps", type=int, default=150, help="agent steps per episode")
    ap.add_argument("--ways", default="native,box", help=f"comma-separated, of {', '.join(WAYS)}")
    ap.add_argument("--camera", default="480x640", help="camera frame HxW")
    ap.add_argument("--threads", type=int, default=1)
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    policy = Policy.from_checkpoint(a.policy)
    task = policy.agent.cfg.task
    spec = get_task(task)
    grid = [dict(zip(spec.test, v)) for v in itertools.product(*spec.test.values())]
    contexts = grid[:: a.every][: a.count]
    camera_hw = tuple(int(v) for v in a.camera.lower().split("x"))
    print(f"{a.policy} ({task}), {len(contexts)} unseen contexts x {a.steps} steps, camera {a.camera}; "
          f"CPU capability {torch.backends.cpu.get_cpu_capability()}", flush=True)
    results: dict[str, np.ndarray] = {}
    for way in a.ways.split(","):
        t0 = time.monotonic()
        results[way] = np.array([episode(policy, task, c, 7 + i, way, a.steps, camera_hw)
                                 for i, c in enumerate(contexts)])
        line = f"{way:9s} mean {results[way].mean():6.1f}"
        if way != "native" and "native" in results:
            d = results[way] - results["native"]
            se = d.std(ddof=1) / np.sqrt(d.size)
            line += f"  paired difference {d.mean():+.1f} (SD {d.std(ddof=1):.1f}, SE {se:.1f})"
        print(f"{line}  [{time.monotonic() - t0:.0f} s]", flush=True)


if __name__ == "__main__":
    main()
