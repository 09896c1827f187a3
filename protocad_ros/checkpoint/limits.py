"""Limits a checkpoint file must keep before torch expands it (a file may come from a stranger:
over ROS, or handed over as a file).

A `.pt` is a zip archive. torch.load inflates a deflate-compressed entry without looking at its
size, so a 8 MB file can hold 2 GiB of zeros. torch.save writes every entry *stored*
(uncompressed), so here the zip directory is read first and a file is refused, before anything
is unpickled, when:
- the file, or the sum of its entries' declared sizes, is larger than `max_bytes`;
- an entry is compressed (torch never writes one so: a stored entry costs what the file holds);
- it has more entries than `MAX_ENTRIES`, an entry name torch does not write, or a pickle
  larger than `MAX_PICKLE_BYTES` (the pickle is what builds Python objects).
After loading, the top-level keys must be the format's (`check_top_level_keys`), and the tensor
bytes must fit what the file's own architecture implies (`check_implied_size`).

No ROS import, no torch: every reader of a checkpoint (files.py, agent_file.py) calls it.
"""
from __future__ import annotations

import io
import os
import re
import zipfile
from pathlib import Path
from typing import Iterable, Mapping

#: Default largest checkpoint file (and sum of its declared entry sizes), in bytes: the policy
#: node's `max_checkpoint_bytes` default. The paper-sized training checkpoint is far below it.
DEFAULT_MAX_CHECKPOINT_BYTES = 512 << 20
#: The environment variable that sets the default for the CLIs (protocad-evaluate, protocad-loop
#: --init-policy, protocad-train --resume, ...); the policy node has its parameter.
MAX_BYTES_ENV = "PROTOCAD_MAX_CHECKPOINT_BYTES"
#: Most entries a checkpoint archive may have (one per tensor storage plus a handful).
MAX_ENTRIES = 20_000
#: Largest data.pkl (the object structure; tensors are separate entries).
MAX_PICKLE_BYTES = 16 << 20
#: Tensor bytes allowed beyond what the architecture implies (RNG state, counters, slack).
IMPLIED_SLACK_BYTES = 16 << 20
#: Tensor bytes allowed per byte of float32 weights: weights + Adam's two moments + slack.
IMPLIED_FACTOR = 4

#: The top-level keys of the format (agent_file.py); anything else is refused.
TOP_LEVEL_KEYS = frozenset({"format", "version", "created_unix", "config", "action_dim", "modules",
                            "optimizers", "agent_counters", "counters", "torch_rng", "provenance"})

# What torch.save writes under its one top-level folder (archive/ for a buffer).
_ENTRY = re.compile(r"^[^/]+/(data\.pkl|version|byteorder|\.format_version|\.storage_alignment|"
                    r"data/\d+|\.data/serialization_id|\.data/version)$")


class CheckpointLimitError(ValueError):
    """The archive breaks a limit; the message names the file, the entry and the limit."""


def max_checkpoint_bytes(given: int | None = None) -> int:
    """`given`, else $PROTOCAD_MAX_CHECKPOINT_BYTES, else DEFAULT_MAX_CHECKPOINT_BYTES
    (CheckpointLimitError for a value that is not a whole number >= 1)."""
    if given is not None:
        return int(given)
    text = os.environ.get(MAX_BYTES_ENV, "").strip()
    if not text:
        return DEFAULT_MAX_CHECKPOINT_BYTES
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise CheckpointLimitError(f"{MAX_BYTES_ENV}={text!r} is not a whole number of bytes >= 1")
    return value


def check_archive(path: Path, data: bytes, max_bytes: int = DEFAULT_MAX_CHECKPOINT_BYTES) -> int:
    """Refuse (CheckpointLimitError) an archive that would expand beyond what it holds or
    beyond `max_bytes`, reading only its zip directory. Returns the sum of the tensor entries'
    sizes (data/N), for `check_implied_size`."""
    if len(data) > max_bytes:
        raise CheckpointLimitError(f"{path}: {len(data)} bytes, more than the limit of {max_bytes} "
                                   "(max_checkpoint_bytes)")
    try:
        infos = zipfile.ZipFile(io.BytesIO(data)).infolist()
    except (zipfile.BadZipFile, ValueError, OSError) as err:
        raise CheckpointLimitError(f"{path}: unreadable zip directory: {err}") from None
    if len(infos) > MAX_ENTRIES:
        raise CheckpointLimitError(f"{path}: {len(infos)} archive entries, more than {MAX_ENTRIES}")
    declared = tensors = 0
    prefixes = set()
    for info in infos:
        name = info.filename
        if not _ENTRY.match(name):
            raise CheckpointLimitError(f"{path}: archive entry {name!r} is not one torch.save writes")
        prefixes.add(name.split("/", 1)[0])
        if info.compress_type != zipfile.ZIP_STORED or info.compress_size != info.file_size:
            raise CheckpointLimitError(
                f"{path}: archive entry {name!r} is compressed ({info.compress_size} bytes declaring "
                f"{info.file_size}); torch writes entries stored, so it is refused unexpanded")
        if name.endswith("/data.pkl") and info.file_size > MAX_PICKLE_BYTES:
            raise CheckpointLimitError(f"{path}: {name!r} is {info.file_size} bytes, more than "
                                       f"the limit of {MAX_PICKLE_BYTES}")
        declared += info.file_size
        if "/data/" in name:
            tensors += info.file_size
    if len(prefixes) > 1:
        raise CheckpointLimitError(f"{path}: archive entries under {len(prefixes)} top-level "
                                   "folders; torch.save writes one")
    if declared > max_bytes:
        raise CheckpointLimitError(f"{path}: entries declare {declared} bytes, more than the limit "
                                   f"of {max_bytes} (max_checkpoint_bytes)")
    return tensors


def check_top_level_keys(path: Path, keys: Iterable[object]) -> None:
    """Refuse a payload with keys the format does not have."""
    unknown = sorted(str(k) for k in keys if k not in TOP_LEVEL_KEYS)
    if unknown:
        raise CheckpointLimitError(f"{path}: unknown top-level key(s) {unknown[:5]}: not a "
                                   "protocad-ros checkpoint key")


def implied_bytes(shapes: Mapping[str, tuple[int, ...]]) -> int:
    """Tensor bytes a checkpoint of these weight shapes may hold: float32 weights, Adam's two
    moments and the slack (the file's weights may be bfloat16: smaller, never larger)."""
    numel = 0
    for shape in shapes.values():
        n = 1
        for d in shape:
            n *= int(d)
        numel += n
    return IMPLIED_FACTOR * 4 * numel + IMPLIED_SLACK_BYTES


def check_implied_size(path: Path, tensor_bytes: int, shapes: Mapping[str, tuple[int, ...]]) -> None:
    """Refuse a file whose tensor entries hold more than its architecture implies."""
    limit = implied_bytes(shapes)
    if tensor_bytes > limit:
        raise CheckpointLimitError(f"{path}: tensor entries hold {tensor_bytes} bytes, more than "
                                   f"the {limit} its config's architecture implies")
