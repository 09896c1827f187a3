"""Data-parallel training over torch.distributed (no ROS): `torchrun --nproc_per_node N ...`.

    ctx = distributed.init(device)          # from torchrun's env; a no-op context without it
    distributed.attach(agent, ctx)          # same weights everywhere, gradients averaged

Every rank holds the whole agent, samples its own sequences (its sampler and torch RNG seeded by
its rank) and computes the gradients of its share of the global batch (train.batch_size / N
sequences); after each backward the gradients of the parameters about to be stepped are averaged
over the ranks with one all-reduce (SUM / N, one flat buffer per optimizer), so every rank takes
the same optimizer step and the weights stay identical; so do everything derived from them (the
EMA target projector, DreamerPro's EMA encoder, the slow critic, DrQ's target critic). Rank 0
writes checkpoints, metrics and rerun logs.

This is what DistributedDataParallel does for one module, done by hand: an update here steps three
optimisers over parts of one module and backpropagates the actor loss through a frozen world
model, which DDP's wrapper (every forward through the wrapper, every parameter used once per
backward) does not fit. Backend: gloo on CPU, NCCL on CUDA (torchrun sets RANK, WORLD_SIZE,
LOCAL_RANK, MASTER_ADDR/PORT).
"""
from __future__ import annotations

import base64
import ctypes
import hashlib
import os
import signal
import sys
from dataclasses import dataclass
from datetime import timedelta
from typing import Any, Callable, NoReturn, Sequence

import torch
import torch.distributed as dist
import torch.nn as nn

from trainer import torch_setup

__all__ = ["DistContext", "init", "attach", "average_gradients", "fingerprints", "any_rank",
           "gather_objects", "rank_seed", "pack_rng", "unpack_rng"]


@dataclass(frozen=True)
class DistContext:
    """Where this process stands: rank / world_size (1 and 0 without torchrun)."""

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    backend: str | None = None

    @property
    def enabled(self) -> bool:
        return self.world_size > 1

    @property
    def is_main(self) -> bool:
        return self.rank == 0


def init(device: str) -> tuple[DistContext, str]:
    """Join the process group torchrun describes in the environment, if it does.

    Returns (context, device): on CUDA each rank takes the GPU of its LOCAL_RANK. Without
    WORLD_SIZE > 1 nothing is initialised and the device is returned unchanged.
    """
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return DistContext(), device
    rank, local = int(os.environ["RANK"]), int(os.environ.get("LOCAL_RANK", "0"))
    _die_with_launcher()
    cuda = device.startswith("cuda")
    if cuda:
        device = f"cuda:{local}"
        torch.cuda.set_device(local)
    backend = "nccl" if cuda else "gloo"
    if not dist.is_initialized():
        # Ranks wait at a barrier while rank 0 evaluates (minutes to hours on a CPU for the
        # paper's 64 contexts): far longer than the 10-30 min default.
        hours = float(os.environ.get("PROTOCAD_DIST_TIMEOUT_H", "6"))
        dist.init_process_group(backend, timeout=timedelta(hours=hours))
    return DistContext(rank, world, local, backend), device


def _die_with_launcher() -> None:
    """SIGTERM (a clean, coordinated stop with a checkpoint) when torchrun's agent dies, instead
    of ranks training on as orphans (Linux prctl PR_SET_PDEATHSIG; elsewhere nothing)."""
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)
    except (OSError, AttributeError):
        pass


def barrier_if(ctx: DistContext) -> None:
    """Wait for every rank (nothing without torch.distributed)."""
    if ctx.enabled:
        dist.barrier()


def run_entry_point(threads: int, device: str, body: Callable[[DistContext, str], int]) -> int:
    """A command's body under torchrun or not: threads, join the ranks (device per rank), run
    body(ctx, device) and return its exit code.

    Under torchrun a rank whose body returned does not come back: it waits for every rank at a
    barrier and ends the process there (`leave`). A body that raised leaves the process group
    and the exception goes on to the command's error handling."""
    torch_setup.setup_torch(threads)
    ctx, device = init(torch_setup.resolve_device(device))
    try:
        code = body(ctx, device)
    except BaseException:
        shutdown(ctx)
        raise
    if ctx.enabled:
        # Only after a normal return: a peer that failed never reaches the barrier.
        barrier_if(ctx)
        leave(code)
    return code


def leave(code: int) -> NoReturn:
    """End a rank whose work is done and saved: flush stdout and stderr, then os._exit(code).

    Tearing gloo down in-process is what fails: destroying the process group and then the
    interpreter while the peer rank does the same now and then aborts one of them in gloo's
    transport threads ("terminate called without an active exception", SIGABRT; about 1 run in
    500 on a loaded 2-core machine), and torchrun reports the whole finished run as failed.
    Past the barrier there is nothing left to save (checkpoints, metrics and run.json are
    written and closed by then), so the rank skips the teardown; the kernel closes its sockets.
    """
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):   # a closed or broken pipe: nothing more can reach it
            pass
    os._exit(code)


def shutdown(ctx: DistContext) -> None:
    if ctx.enabled and dist.is_initialized():
        dist.destroy_process_group()


@torch.no_grad()
def average_gradients(params: Sequence[nn.Parameter], world_size: int) -> None:
    """grad <- (sum over ranks of grad) / N for every parameter that has one.

    Parameters without a gradient are left out: every rank runs the same code path, so the same
    parameters lack one everywhere and the flat buffers line up.
    """
    have = [p for p in params if p.grad is not None]
    if not have:
        return
    flat = torch.cat([p.grad.reshape(-1) for p in have])
    dist.all_reduce(flat, op=dist.ReduceOp.SUM)
    flat.div_(world_size)
    offset = 0
    for p in have:
        n = p.grad.numel()
        p.grad.copy_(flat[offset:offset + n].view_as(p.grad))
        offset += n


@torch.no_grad()
def broadcast_state(module: nn.Module, src: int = 0) -> None:
    """Every parameter and buffer of `module` takes rank `src`'s values."""
    for t in list(module.state_dict(keep_vars=True).values()):
        data = t.data if isinstance(t, nn.Parameter) else t
        dist.broadcast(data, src)


def attach(agent: Any, ctx: DistContext) -> None:
    """Rank 0's weights everywhere, and gradient averaging after every backward."""
    if not ctx.enabled:
        return
    broadcast_state(agent)
    agent.grad_sync = lambda params: average_gradients(params, ctx.world_size)


def any_rank(flag: bool, ctx: DistContext) -> bool:
    """True on every rank if it is True on any (a stop request must stop them all together)."""
    if not ctx.enabled:
        return flag
    # NCCL reduces CUDA tensors only; gloo CPU ones.
    device = f"cuda:{ctx.local_rank}" if ctx.backend == "nccl" else "cpu"
    t = torch.tensor([1.0 if flag else 0.0], device=device)
    dist.all_reduce(t, op=dist.ReduceOp.MAX)
    return bool(t.item() > 0)


def gather_objects(obj: Any, ctx: DistContext) -> list[Any]:
    """[obj of rank 0, obj of rank 1, ...] on every rank ([obj] without torch.distributed)."""
    if not ctx.enabled:
        return [obj]
    out: list[Any] = [None] * ctx.world_size
    dist.all_gather_object(out, obj)
    return out


def rank_seed(seed: int, rank: int, updates: int = 0) -> int:
    """A seed for this rank's sampler and torch RNG (rank 0 of a fresh run: `seed` itself)."""
    return int(seed) + 1_000_003 * int(rank) + 7_919 * int(updates)


def pack_rng(state: torch.Tensor) -> str:
    return base64.b64encode(state.numpy().tobytes()).decode("ascii")


def unpack_rng(text: str) -> torch.Tensor:
    return torch.frombuffer(bytearray(base64.b64decode(text)), dtype=torch.uint8).clone()


def _digest(tensors: dict[str, torch.Tensor]) -> str:
    h = hashlib.sha256()
    for key, t in tensors.items():
        h.update(key.encode())
        h.update(t.detach().cpu().contiguous().reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()[:16]


def fingerprints(agent: nn.Module) -> dict[str, str]:
    """sha256 (16 hex digits) of the weights and buffers of every part two levels down (e.g.
    wm.context, ac.actor, ac.slow_critic, critic_target) and of the agent's own (DrQ's
    log_alpha, the update counter): equal on two ranks exactly when those are bit for bit."""
    out = {"agent": _digest({**dict(agent.named_parameters(recurse=False)),
                             **dict(agent.named_buffers(recurse=False))})}
    for name, child in agent.named_children():
        grandchildren = list(child.named_children())
        if not grandchildren:
            out[name] = _digest(child.state_dict())
        for sub, mod in grandchildren:
            out[f"{name}.{sub}"] = _digest(mod.state_dict())
    return out
