"""The checkpoint surface that needs no torch: the format's names and version, the errors every
reader raises, where a checkpoint named by a file or a run directory is, its one bounded read,
and what makes two configs different networks. A node's --help, its parameter checks, the
signature checks and a checkpoint's receipt run on this before any model loads (agent_file.py,
which builds and saves agents, needs torch)."""
from __future__ import annotations

import io
import os
import stat
from pathlib import Path

from protocad_ros.checkpoint.limits import CheckpointLimitError, max_checkpoint_bytes
from protocad_ros.model.config import Config

FORMAT = "protocad-ros/agent-checkpoint"
VERSION = 1
CONFIG_NAME = "config.yaml"


class CheckpointError(RuntimeError):
    """A checkpoint that cannot be used: corrupt/truncated, foreign, or incompatible."""


class CheckpointMismatch(CheckpointError):
    """A sound checkpoint that is not what the caller serves (another task, variant or
    architecture): refused before anything is built."""


def checkpoint_file(path: str | os.PathLike) -> Path:
    """A checkpoint named as a file or as a run directory: the file. A directory means its
    checkpoints/latest.pt (or a latest.pt in it, a bare checkpoints/ directory); a path that
    does not exist yet is returned as it is (a node waiting for its first checkpoint). The one
    way every node and CLI reads the name."""
    p = Path(path)
    if not p.is_dir():
        return p
    for cand in (p / "checkpoints" / "latest.pt", p / "latest.pt"):
        if cand.is_file():
            return cand
    return p / "checkpoints" / "latest.pt"


def existing_checkpoint_file(path: str | os.PathLike) -> Path:
    """`checkpoint_file` for a reader: the file, which must exist (ValueError saying which is
    missing otherwise)."""
    c = checkpoint_file(path)
    if not c.is_file():
        raise ValueError(f"{path} is a directory without checkpoints/latest.pt" if Path(path).is_dir()
                         else f"checkpoint {path} does not exist")
    return c


def read_checkpoint_file(path: str | os.PathLike, max_bytes: int | None = None) -> bytes:
    """A checkpoint file's bytes, for a caller that verifies them before loading them
    (read_checkpoint(path, data=...)): refused (CheckpointError) when the file is larger than
    max_bytes (None: $PROTOCAD_MAX_CHECKPOINT_BYTES or 512 MiB), before it is read."""
    try:
        return read_bounded(Path(path), max_checkpoint_bytes(max_bytes))
    except CheckpointLimitError as err:
        raise CheckpointError(str(err)) from None


def read_bounded(path: Path, max_bytes: int) -> bytes:
    """One bounded read: the file is opened once, its size checked on that descriptor (fstat),
    and at most that size plus one byte (never more than max_bytes + 1) read from it; the path
    is never opened again. A file that grows after its size check (a writer still at it, or a
    stranger's file that becomes a sparse 4 GiB one) is refused, naming what was read."""
    try:   # O_NONBLOCK: a FIFO put in its place must not hang the opener (refused just below)
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        raise CheckpointError(f"{path}: no such checkpoint file") from None
    except OSError as err:
        raise CheckpointError(f"{path}: cannot open: {err.strerror or err}") from None
    with open(fd, "rb", buffering=0) as f:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise CheckpointError(f"{path}: not a regular file (no such checkpoint file)")
        size = st.st_size
        if size > max_bytes:   # before reading it: a huge file costs nothing
            raise CheckpointError(f"{path}: {size} bytes, more than the limit of {max_bytes} (max_checkpoint_bytes)")
        data = _read_at_most(f, size)
        extra = len(f.read(1) or b"")   # one byte more: the file is longer than it was checked
    if extra:
        raise CheckpointError(f"{path}: grew after its size check ({size} bytes): {len(data) + extra} bytes "
                              f"read, more than was checked; refused (the limit is {max_bytes} bytes, "
                              "max_checkpoint_bytes)")
    return data


def _read_at_most(f: io.RawIOBase, size: int) -> bytes:
    """Up to `size` bytes from a raw file: one read (one allocation) unless it comes back short."""
    first = f.read(size) or b""
    if len(first) >= size or not first:
        return first
    parts = [first]
    got = len(first)
    while got < size:
        more = f.read(size - got)
        if not more:
            break
        parts.append(more)
        got += len(more)
    return b"".join(parts)


def architecture_differences(mine: Config, theirs: Config) -> list[str]:
    """What makes `theirs` another network than `mine` (variant, shape-giving fields), as
    'section.key: mine != theirs'; training-only fields (learning rates, ...) may differ."""
    a, b = mine.to_dict(), theirs.to_dict()
    diffs = [f"variant: {a['variant']!r} != {b['variant']!r}"] if a["variant"] != b["variant"] else []
    return diffs + [f"{sec}.{k}: {a[sec][k]!r} != {b[sec][k]!r}"
                    for sec in ("world_model", "context", "behavior", "drq") for k in sorted(_ARCH_KEYS[sec])
                    if a[sec].get(k) != b[sec].get(k)]


# Config fields that change the networks' shapes (the rest may differ on restore).
_ARCH_KEYS = {
    "world_model": {"deter", "hidden", "stoch", "discrete", "cnn", "cnn_depth", "mlp_layers",
                    "mlp_units", "act", "norm", "gru_norm", "discount_head"},
    "context": {"num_prototypes", "proto_dim", "dreamerpro_num_prototypes", "projector_input"},
    "behavior": {"actor_layers", "actor_units", "critic_layers", "critic_units", "act", "norm",
                 "actor_dist"},
    "drq": {"frame_stack", "num_filters", "num_conv_layers", "feature_dim", "hidden_dim",
            "hidden_depth"},
}
