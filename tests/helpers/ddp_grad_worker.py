"""Run by tests/trainer/learn/test_distributed.py under torchrun: one update of a tiny agent on
this rank's half of a saved batch, with this rank's seed; saves the gradients as averaged over
the ranks."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

from protocad_ros.model.agent import make_agent
from protocad_ros.model.config import Config
from trainer.learn import distributed


def main(work: str) -> int:
    return distributed.run_entry_point(1, "cpu", lambda ctx, _device: one_update(Path(work), ctx))


def one_update(work_dir: Path, ctx: distributed.DistContext) -> int:
    cfg = Config.load(work_dir / "config.yaml")
    data = np.load(work_dir / "batch.npz")
    half = len(data["image"]) // ctx.world_size
    batch = {k: data[k][ctx.rank * half:(ctx.rank + 1) * half] for k in data.files}
    agent = make_agent(cfg, 1)
    distributed.attach(agent, ctx)
    synced: dict[str, torch.Tensor] = {}
    names = {id(p): n for n, p in agent.named_parameters()}
    average = agent.grad_sync

    def record(params):
        average(params)
        for p in params:
            if p.grad is not None:
                synced[names[id(p)]] = p.grad.detach().clone()

    agent.grad_sync = record
    torch.manual_seed(100 + ctx.rank)
    agent.train_step(batch)
    torch.save(synced, work_dir / f"grads_rank{ctx.rank}.pt")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
