"""A deflate-bombed checkpoint, as a stranger could hand one over: a valid checkpoint plus a
zero tensor whose storage entry inflates to 1 GiB, the archive re-zipped with deflate (what
torch.load would read without a size check). Built in pieces: a few MB for the test."""
from __future__ import annotations

import io
import struct
import zipfile
from pathlib import Path

import torch

from protocad_ros.model.agent import Agent
from protocad_ros.model.config import make_config

#: Elements of the marker tensor: a 4-byte pickle int (BININT), patched to BOMB_NUMEL.
MARKER_NUMEL = 70_001
BOMB_NUMEL = 1 << 28          # 1 GiB of float32 zeros once inflated
TINY = {"world_model.deter": 32, "world_model.hidden": 32, "world_model.stoch": 8,
        "world_model.cnn_depth": 8, "world_model.mlp_layers": 1, "world_model.mlp_units": 32,
        "behavior.actor_layers": 1, "behavior.actor_units": 32, "behavior.critic_layers": 1,
        "behavior.critic_units": 32, "context.num_prototypes": 8}


def tiny_agent() -> Agent:
    return Agent(make_config("cheetah_run", "small", "protocad", **TINY), action_dim=6)


def write_deflate_bomb(good: Path, out: Path, key: str = "padding") -> Path:
    """`good`'s payload plus `key`: a zero tensor whose storage entry inflates to 1 GiB, the
    archive re-zipped with deflate (what torch.load reads without a size check). Written in
    pieces: building it costs the test a few MB."""
    payload = torch.load(good, weights_only=True)
    payload[key] = torch.zeros(MARKER_NUMEL)
    buf = io.BytesIO()
    torch.save(payload, buf)
    src = zipfile.ZipFile(io.BytesIO(buf.getvalue()))
    marker, bomb = b"J" + struct.pack("<i", MARKER_NUMEL), b"J" + struct.pack("<i", BOMB_NUMEL)
    pkl_name = next(n for n in src.namelist() if n.endswith("/data.pkl"))
    pkl = src.read(pkl_name)
    assert pkl.count(marker) == 2, "storage numel and shape"   # the patch below needs both
    big = next(i.filename for i in src.infolist() if i.file_size == 4 * MARKER_NUMEL)
    with zipfile.ZipFile(out, "w", compression=zipfile.ZIP_DEFLATED) as dst:
        for info in src.infolist():
            if info.filename == pkl_name:
                dst.writestr(info.filename, pkl.replace(marker, bomb))
            elif info.filename == big:
                zeros = bytes(1 << 24)
                with dst.open(info.filename, "w", force_zip64=True) as f:
                    for _ in range(4 * BOMB_NUMEL // len(zeros)):
                        f.write(zeros)
            else:
                dst.writestr(info.filename, src.read(info.filename))
    return out
