"""What every agent family shares (no ROS): the batch contract, optimisers, precision, counters.

Two families implement it: the world-model agents (protocad_ros.model.agent: ProtoCAD, Dreamer,
DreamerPro, ...) and the model-free DrQ (protocad_ros.model.drq). Trainers, the checkpoint code and
the Policy only use this surface:

    agent.train_step(batch) -> metrics        agent.optimizers() -> {name: optimizer}
    agent.initial_state(B)                    agent.observe_step(state, image, a_prev, first)
    agent.act(x, sample, generator)           agent.counters(), agent.context_dims
"""
from __future__ import annotations

import contextlib
from typing import Any, Callable, Iterator, Mapping

import numpy as np
import torch
import torch.nn as nn

from protocad_ros.model.config import Config
from protocad_ros.model.precision import PrecisionChoice, resolve_precision

__all__ = ["AgentBase", "BATCH_KEYS", "frozen", "batch_to_device"]

BATCH_KEYS = ("image", "action", "reward", "discount", "is_first")


@contextlib.contextmanager
def frozen(*modules: nn.Module) -> Iterator[None]:
    """requires_grad=False on every parameter of `modules` inside the block (then restored).

    Gradients still flow *through* the modules to their inputs (dynamics backprop), but no
    weight gradient is computed or stored, and autograd saves fewer tensors.
    """
    params = [p for m in modules for p in m.parameters() if p.requires_grad]
    for p in params:
        p.requires_grad_(False)
    try:
        yield
    finally:
        for p in params:
            p.requires_grad_(True)


def batch_to_device(batch: Mapping[str, Any], action_dim: int,
                    device: torch.device) -> dict[str, torch.Tensor]:
    """Validate a training batch (numpy or torch) and move it to the device.

    image uint8 (B, T, 64, 64, 3); action float32 (B, T, A) = the action that LED TO o_t (zeros
    where is_first); reward float32 (B, T) = reward arriving with o_t; discount float32 (B, T)
    (ones if absent); is_first bool (B, T).
    """
    missing = [k for k in ("image", "action", "reward", "is_first") if k not in batch]
    if missing:
        raise ValueError(f"batch is missing {missing}; expected keys {BATCH_KEYS}")
    t = {k: torch.as_tensor(np.asarray(v) if not torch.is_tensor(v) else v)
         for k, v in batch.items() if k in BATCH_KEYS}
    img = t["image"]
    if img.dim() != 5 or tuple(img.shape[2:]) != (64, 64, 3) or img.dtype != torch.uint8:
        raise ValueError(f"batch['image'] must be uint8 (B, T, 64, 64, 3), got "
                         f"{img.dtype} {tuple(img.shape)}")
    B, T = img.shape[:2]
    if tuple(t["action"].shape) != (B, T, action_dim):
        raise ValueError(f"batch['action'] must be (B, T, A)=({B}, {T}, {action_dim}), "
                         f"got {tuple(t['action'].shape)}")
    for k in ("reward", "is_first") + (("discount",) if "discount" in t else ()):
        if tuple(t[k].shape) != (B, T):
            raise ValueError(f"batch[{k!r}] must be (B, T)=({B}, {T}), got {tuple(t[k].shape)}")
    if "discount" not in t:
        t["discount"] = torch.ones(B, T)
    nb = device.type == "cuda"
    out = {"image": img.to(device, non_blocking=nb)}
    for k in ("action", "reward", "discount"):
        out[k] = t[k].to(device, torch.float32, non_blocking=nb)
    out["is_first"] = t["is_first"].to(device, torch.bool, non_blocking=nb)
    if "context" in batch:   # the true context (B, T, P), for the variant that reads it
        ctx = torch.as_tensor(np.asarray(batch["context"], np.float32)
                              if not torch.is_tensor(batch["context"]) else batch["context"])
        if ctx.dim() != 3 or tuple(ctx.shape[:2]) != (B, T) or not torch.isfinite(ctx).all():
            raise ValueError(f"batch['context'] must be finite (B, T, P)=({B}, {T}, P), got "
                             f"{tuple(ctx.shape)}")
        out["context"] = ctx.to(device, torch.float32, non_blocking=nb)
    if not torch.isfinite(out["action"]).all() or not torch.isfinite(out["reward"]).all():
        raise ValueError("batch['action'] / batch['reward'] contain NaN or inf")
    return out


class AgentBase(nn.Module):
    """cfg, action_dim, an `updates` counter buffer, Adam(W) construction, bf16 autocast."""

    def __init__(self, cfg: Config, action_dim: int):
        super().__init__()
        cfg.validate()
        if int(action_dim) < 1:
            raise ValueError(f"action_dim must be >= 1, got {action_dim}")
        self.cfg, self.action_dim = cfg, int(action_dim)
        self.register_buffer("updates", torch.zeros((), dtype=torch.long))
        # Data-parallel training (trainer/learn/distributed.py) averages gradients across processes
        # here: called after every backward with the parameters about to be stepped.
        self.grad_sync: Callable[[list[nn.Parameter]], None] | None = None
        self._precision: PrecisionChoice | None = None   # resolved on first use (`precision`)
        self._optimizers: dict[str, torch.optim.Optimizer] | None = None   # built on first use

    @property
    def device(self) -> torch.device:
        """Where the agent lives (follows .to(...))."""
        return self.updates.device

    @property
    def context_dims(self) -> tuple[int, int, int]:
        """(D, K, D) of the context features u, w, e, or (0, 0, 0) without a context module."""
        return (0, 0, 0)

    @property
    def has_decoder(self) -> bool:
        return False

    def prototypes(self) -> torch.Tensor | None:
        """(K, D) unit-norm prototypes, or None for agents without any."""
        return None

    def set_prototype_freeze(self, updates: int) -> bool:
        """Prototypes get no gradient while the update counter is below `updates` (the run's
        resolved freeze); False for agents without prototypes."""
        return False

    def _adam(self, params, lr: float, eps: float = 1e-8, wd: float = 0.0,
              betas: tuple[float, float] = (0.9, 0.999)) -> torch.optim.Optimizer:
        # DreamerV2 applies decoupled decay var *= (1 - wd) per step, independent of lr;
        # AdamW decays by lr * weight_decay, hence weight_decay = wd / lr.
        params = [p for p in params if p.requires_grad]
        kw: dict[str, Any] = {"lr": lr, "eps": eps, "betas": betas,
                              "weight_decay": wd / lr if wd else 0.0}
        if self.device.type in ("cpu", "cuda"):
            kw["foreach"] = True
        return torch.optim.AdamW(params, **kw)

    @property
    def precision(self) -> PrecisionChoice:
        """What this agent computes in: cfg.train.precision resolved as a request on the agent's
        device, unless `use_precision` was given a command line's choice."""
        if self._precision is None:
            self.use_precision(None)
        return self._precision

    def use_precision(self, command_line: str | None) -> PrecisionChoice:
        """Resolve the precision on this agent's device: a command line's --precision (explicit:
        bfloat16 is kept even where emulated) or, without one, cfg.train.precision (a request:
        bfloat16 only where the device has bf16 arithmetic). Returns the choice (describe() it)."""
        explicit = command_line is not None
        self._precision = resolve_precision(command_line if explicit else self.cfg.train.precision,
                                            str(self.device), explicit)
        return self._precision

    def _autocast(self):
        return torch.autocast(self.device.type, dtype=torch.bfloat16,
                              enabled=self.precision.precision == "bfloat16")

    def to_batch(self, batch: Mapping[str, Any]) -> dict[str, torch.Tensor]:
        """Validate a training batch (numpy or torch) and move it to the device."""
        return batch_to_device(batch, self.action_dim, self.device)

    def optimizers(self) -> dict[str, torch.optim.Optimizer]:
        """{name: optimizer}, built on first use: an agent that only acts (a policy node, an
        evaluation) never builds them, and building one imports torch's compiler (~1 CPU-s)."""
        if self._optimizers is None:
            self._optimizers = self._make_optimizers()
        return self._optimizers

    def _make_optimizers(self) -> dict[str, torch.optim.Optimizer]:
        raise NotImplementedError

    def _sync_grads(self, *optimizers: torch.optim.Optimizer) -> None:
        if self.grad_sync is not None:
            self.grad_sync([p for opt in optimizers for g in opt.param_groups for p in g["params"]])

    def counters(self) -> dict[str, int]:
        return {"updates": int(self.updates)}

    @staticmethod
    def metrics_to_floats(metrics: Mapping[str, Any], device: torch.device) -> dict[str, float]:
        """One device sync for all metrics (tensors or numbers) -> floats."""
        keys = list(metrics)
        values = torch.stack([torch.as_tensor(metrics[k], dtype=torch.float32,
                                              device=device).reshape(()) for k in keys])
        return dict(zip(keys, values.tolist()))
