#!/usr/bin/env python3
"""How far one bf16-autocast update is from the same update in float32, against sampling noise.

The walker anchor (dreamer, small preset, bf16 autocast on the CPU) scored 187 at 60k env steps,
below DreamerV2's five seeds (197-466), which trained in float16 mixed precision: 10 mantissa
bits where bfloat16 has 7. A value of 150 has a bfloat16 step of 1.0 (float16: 0.125), and the
critic's and reward head's last layers, the lambda-returns' inputs, run inside autocast.

From a trained checkpoint (default: the shipped walker policy), on one batch of its own
episodes, this takes the gradients of one world-model update and one actor-critic update three
times: in float32, in bfloat16 autocast with the same random draws, and in float32 with other
random draws (posterior samples, imagined actions). Per parameter group it prints the cosine
between each pair and the relative norm of their difference: if bf16 strays from float32 by
more than another set of random draws does, the precision is changing what the agent learns.
Nothing is stepped; the checkpoint is not modified.
"""
from __future__ import annotations

import argparse
import copy
import platform
import sys
from pathlib import Path

import numpy as np
import torch

# Measure the working tree this script belongs to, not an installed copy of the packages.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from protocad_ros.checkpoint.agent_file import load_checkpoint
from protocad_ros.model.precision import cpu_capability
from trainer.viz.context_episodes import collect_context_episodes, stack_batches

SHIPPED = Path(__file__).resolve().parents[1] / "protocad_ros" / "policies" / "walker_walk.pt"


def batch_from_episodes(task: str, agent, episodes: int, steps: int, batch: int, seq_len: int,
                        seed: int) -> dict[str, np.ndarray]:
    """`batch` windows of `seq_len` steps at random offsets of the agent's own episodes on the
    unrandomized task (m = d = 1), as the replay would sample them."""
    eps = collect_context_episodes(task, agent, steps=steps, splits=("train",), seed=seed,
                                   contexts={"train": [{"m": 1.0, "d": 1.0}] * episodes})
    rng = np.random.default_rng(seed)
    windows = []
    for _ in range(batch):
        ep = eps[int(rng.integers(len(eps)))]
        start = int(rng.integers(0, len(ep) - seq_len + 1))
        windows.append(ep.batch(start, start + seq_len))
    print(f"batch: {batch} x {seq_len} from {len(eps)} episodes of {steps} steps, returns "
          + ", ".join(f"{float(e.reward.sum()):.1f}" for e in eps))
    return stack_batches(windows)


def update_gradients(agent, batch: dict[str, np.ndarray], precision: str, seed: int
                     ) -> dict[str, torch.Tensor]:
    """Flat gradients of one train_step of a copy of `agent` ('world_model', 'actor', 'critic'),
    captured where data-parallel training would average them, so nothing differs but the
    precision and the seed."""
    a = copy.deepcopy(agent)
    a.use_precision("float32" if precision == "float32" else "bfloat16")   # as asked, even if emulated
    if precision == "float16":  # DreamerV2's precision; autocast only here (no loss scaling)
        a._autocast = lambda: torch.autocast(a.device.type, dtype=torch.float16)
    names = {id(p): "world_model" for p in a.optimizers()["world_model"].param_groups[0]["params"]}
    names.update({id(p): "actor" for p in a.optimizers()["actor"].param_groups[0]["params"]})
    names.update({id(p): "critic" for p in a.optimizers()["critic"].param_groups[0]["params"]})
    grads: dict[str, list[torch.Tensor]] = {}

    def capture(params):
        for p in params:
            g = torch.zeros(p.numel()) if p.grad is None else p.grad.detach().float().flatten().clone()
            grads.setdefault(names[id(p)], []).append(g)

    a.grad_sync = capture
    for opt in a.optimizers().values():  # no step may move the weights of the next group's pass
        for group in opt.param_groups:
            group["lr"] = 0.0
            group["weight_decay"] = 0.0
    torch.manual_seed(seed)
    metrics = a.train_step(batch)
    out = {k: torch.cat(v) for k, v in grads.items()}
    print(f"  {precision:9s} seed {seed}: " + ", ".join(
        f"{k} {metrics[k]:.4g}" for k in ("image_loss", "reward_loss", "kl", "actor_loss",
                                          "critic_loss") if k in metrics))
    return out


def compare(x: dict[str, torch.Tensor], y: dict[str, torch.Tensor]) -> dict[str, tuple[float, float]]:
    """group -> (cosine, |x - y| / |x|)."""
    out = {}
    for k in x:
        a, b = x[k], y[k]
        cos = float(torch.nn.functional.cosine_similarity(a, b, dim=0))
        out[k] = (cos, float((a - b).norm() / a.norm().clamp_min(1e-30)))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog=__doc__.split("\n\n", 1)[1])
    ap.add_argument("checkpoint", nargs="?", default=str(SHIPPED),
                    help="a world-model checkpoint (default: the shipped walker_walk policy)")
    ap.add_argument("--task", default="walker_walk")
    ap.add_argument("--episodes", type=int, default=2, help="episodes of the policy to sample from")
    ap.add_argument("--steps", type=int, default=500, help="agent steps per episode")
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--seq-len", type=int, default=50)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2],
                    help="draws to repeat the comparison with (each against the next)")
    ap.add_argument("--threads", type=int, default=None)
    a = ap.parse_args(argv)
    if a.threads:
        torch.set_num_threads(a.threads)
    print(f"machine: {platform.processor() or platform.machine()}, torch {torch.__version__}, "
          f"CPU capability {cpu_capability()}, threads {torch.get_num_threads()}")
    agent, counters = load_checkpoint(a.checkpoint, restore_rng=False)
    updates = f", {counters['updates']} updates" if counters.get("updates") else ""
    print(f"checkpoint: {a.checkpoint} ({agent.cfg.variant}, {agent.cfg.preset} preset{updates})")
    batch = batch_from_episodes(a.task, agent, a.episodes, a.steps, a.batch, a.seq_len, a.seeds[0])
    grads = {p: [update_gradients(agent, batch, p, seed) for seed in a.seeds]
             for p in ("float32", "bfloat16", "float16")}
    mean = {p: {k: torch.stack([g[k] for g in gs]).mean(0) for k in gs[0]} for p, gs in grads.items()}
    f32 = grads["float32"]
    rows = [(f"seed {s}", {"bfloat16": compare(f32[i], grads["bfloat16"][i]),
                           "float16": compare(f32[i], grads["float16"][i]),
                           "f32 other draws": compare(f32[i], f32[(i + 1) % len(f32)])})
            for i, s in enumerate(a.seeds)]
    # Rounding that is noise averages out over draws like sampling does; a bias does not.
    rows.append((f"mean of {len(a.seeds)}", {"bfloat16": compare(mean["float32"], mean["bfloat16"]),
                                            "float16": compare(mean["float32"], mean["float16"])}))
    cols = ("bfloat16", "float16", "f32 other draws")
    print("\ncosine to the float32 gradient (relative difference):")
    print(f"{'group':12s} {'draws':>10s}  " + "  ".join(f"{c:>22s}" for c in cols))
    for label, cmp in rows:
        for k in cmp["bfloat16"]:
            print(f"{k:12s} {label:>10s}  " + "  ".join(
                f"{cmp[c][k][0]:14.4f} ({cmp[c][k][1]:5.3f})" if c in cmp else f"{'':>22s}"
                for c in cols))
    return 0


if __name__ == "__main__":
    sys.exit(main())
