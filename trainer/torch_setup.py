"""Torch set-up of the trainer CLIs: seeds, the device, threads, and how freed memory is kept.
Imported where a command starts to compute, not by the command lines (trainer.settings), so that
--help and the torch-free commands never load torch."""
from __future__ import annotations

import ctypes
import os
import random

import numpy as np
import torch


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % (2 ** 32))
    torch.manual_seed(seed)


def resolve_device(name: str | None) -> str:
    """'cpu' (default), 'cuda', 'cuda:N' or 'auto' (cuda when available)."""
    name = (name or "cpu").lower()
    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise SystemExit(f"--device {name}: CUDA is not available on this machine (use cpu or auto)")
    if name != "cpu" and not name.startswith("cuda"):
        raise SystemExit(f"--device {name!r}: expected cpu, cuda, cuda:N or auto")
    return name


_TORCH_DEFAULT_THREADS: int | None = None


def retain_freed_memory() -> bool:
    """Keep memory that torch frees inside this process for its next allocation (glibc only).

    glibc hands every block of 128 KiB or more straight back to the kernel (mmap / munmap) and
    trims the heap top as soon as it is free, so each update's large activations (a 16 x 50
    batch of 64x64 images is 39 MB per float32 copy) are paid again as fresh zeroed pages:
    page faults, measured at 8-20% of a CPU update (more with two runs on the cores). Raising
    the mmap threshold to glibc's largest (32 MiB) and never trimming keeps them in the heap;
    the process holds its peak memory instead of returning it between updates. Returns
    whether glibc took both settings (False elsewhere: nothing changes)."""
    m_trim_threshold, m_mmap_threshold = -1, -3   # <malloc.h>
    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):
        return False
    return bool(mallopt(m_mmap_threshold, 32 << 20) and mallopt(m_trim_threshold, 2**31 - 1))


def setup_torch(n: int | None) -> int:
    """This process's CPU runtime for training: the allocator (retain_freed_memory) and torch's
    intra-op threads: n > 0 as given; 0/None = auto: one per core (torch's default),
    shared out among the ranks torchrun started on this machine (LOCAL_WORLD_SIZE). The CLIs
    compute in turn with their envs and nodes, never beside them (collect, then update; a
    lock-step loop; the loop's nodes wait while it trains), so each has the cores while it
    computes; jobs that do run side by side (protocad-compare's) are given --threads. Returns
    the number of threads in use."""
    global _TORCH_DEFAULT_THREADS
    retain_freed_memory()
    if _TORCH_DEFAULT_THREADS is None:   # before anything set it: torch's own, one per core
        _TORCH_DEFAULT_THREADS = torch.get_num_threads()
    if n:
        torch.set_num_threads(int(n))
    else:
        ranks = max(1, int(os.environ.get("LOCAL_WORLD_SIZE", "1")))
        torch.set_num_threads(max(1, _TORCH_DEFAULT_THREADS // ranks))
    return torch.get_num_threads()


def torch_threads() -> int:
    return torch.get_num_threads()
