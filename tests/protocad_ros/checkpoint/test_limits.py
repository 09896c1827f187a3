"""Hostile checkpoint archives are refused from their zip directory, before torch expands them:
a deflate bomb (a valid checkpoint plus a 1 GiB zero tensor re-zipped with deflate), an unknown
top-level key, a file above max_bytes. Every loader refuses them (read, load, restore, the
evaluate and loop CLIs), and the peak RSS of a refusal stays within 200 MB of a normal load."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
import torch
from helpers import ROOT
from helpers.hostile_checkpoints import BOMB_NUMEL, tiny_agent, write_deflate_bomb

from protocad_ros.checkpoint.agent_file import load_checkpoint, read_checkpoint, restore_checkpoint, save_checkpoint
from protocad_ros.checkpoint.files import CheckpointError
from protocad_ros.checkpoint.limits import TOP_LEVEL_KEYS

pytestmark = pytest.mark.usefixtures("one_torch_thread")

@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("ckpt")
    good = save_checkpoint(d / "run" / "checkpoints" / "latest.pt", tiny_agent())
    stored = d / "unknown_key.pt"
    torch.save({**torch.load(good, weights_only=True), "padding": torch.zeros(8)}, stored)
    return {"good": good, "bomb": write_deflate_bomb(good, d / "bomb.pt"), "unknown": stored}


def test_the_bomb_is_small_on_disk_and_what_torch_would_inflate(files):
    assert files["bomb"].stat().st_size < 8 << 20
    info = {i.filename: i for i in zipfile.ZipFile(files["bomb"]).infolist()}
    assert max(i.file_size for i in info.values()) == 4 * BOMB_NUMEL
    assert any(i.compress_type == zipfile.ZIP_DEFLATED for i in info.values())


@pytest.mark.parametrize("loader", ["read", "load", "restore"])
def test_every_library_loader_refuses_the_bomb_and_the_unknown_key(files, loader):
    call = {"read": read_checkpoint, "load": load_checkpoint,
            "restore": lambda p: restore_checkpoint(p, tiny_agent())}[loader]
    with pytest.raises(CheckpointError, match=r"bomb\.pt: archive entry .* is compressed"):
        call(files["bomb"])
    with pytest.raises(CheckpointError, match=r"unknown top-level key\(s\) \['padding'\]"):
        call(files["unknown"])
    call(files["good"])   # the real one still loads


def test_max_bytes_refuses_a_larger_file_before_reading_it(files):
    size = files["good"].stat().st_size
    with pytest.raises(CheckpointError, match=f"{size} bytes, more than the limit of 4096"):
        load_checkpoint(files["good"], max_bytes=4096)
    load_checkpoint(files["good"], max_bytes=size)


def test_the_clis_default_comes_from_the_environment(files, monkeypatch):
    monkeypatch.setenv("PROTOCAD_MAX_CHECKPOINT_BYTES", "4096")
    with pytest.raises(CheckpointError, match="more than the limit of 4096"):
        read_checkpoint(files["good"])
    monkeypatch.setenv("PROTOCAD_MAX_CHECKPOINT_BYTES", "lots")
    with pytest.raises(CheckpointError, match="PROTOCAD_MAX_CHECKPOINT_BYTES='lots'"):
        read_checkpoint(files["good"])


def test_tensor_bytes_beyond_what_the_architecture_implies_are_refused(tmp_path, files):
    """Stored (not compressed), under max_bytes, known keys: but 64 MiB of optimizer state
    for a network of a few hundred kB."""
    payload = torch.load(files["good"], weights_only=True)
    payload["optimizers"]["world_model"]["state"][10**6] = {"exp_avg": torch.zeros(16 << 20)}
    torch.save(payload, tmp_path / "fat.pt")
    with pytest.raises(CheckpointError, match="more than the .* its config's architecture implies"):
        load_checkpoint(tmp_path / "fat.pt")


def test_format_keys_are_the_ones_save_writes(files):
    assert set(read_checkpoint(files["good"])) <= TOP_LEVEL_KEYS


PEAK_RSS = """
import resource, sys
from protocad_ros.checkpoint.files import CheckpointError
from protocad_ros.checkpoint.agent_file import load_checkpoint
load_checkpoint(sys.argv[1])
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
try:
    load_checkpoint(sys.argv[2])
    print("LOADED")
except CheckpointError as err:
    print("REFUSED", err)
print("GROWTH_KB", resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - base)
"""


def test_refusing_the_bomb_costs_under_200_mb_over_a_normal_load(files):
    out = subprocess.run([sys.executable, "-c", PEAK_RSS, str(files["good"]), str(files["bomb"])],
                         capture_output=True, text=True, cwd=ROOT, timeout=300,
                         env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert "REFUSED" in out.stdout, out.stdout + out.stderr
    growth_kb = int(out.stdout.split("GROWTH_KB")[1])
    assert growth_kb < 200_000, growth_kb


@pytest.mark.parametrize("cli", ["protocad-evaluate", "protocad-loop"])
def test_the_clis_refuse_it_in_one_line_with_exit_2(files, cli, tmp_path):
    bin_dir = Path(sys.executable).parent
    args = {"protocad-evaluate": [str(files["bomb"]), "--episodes", "1", "--json", str(tmp_path / "e.json")],
            "protocad-loop": ["--init-policy", str(files["bomb"]), "--run-dir", str(tmp_path / "loop"),
                              "--episodes-per-cycle", "1"]}[cli]
    out = subprocess.run([str(bin_dir / cli), *args], capture_output=True, text=True, cwd=ROOT,
                         timeout=300, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert out.returncode == 2, out.stdout + out.stderr
    lines = [x for x in out.stderr.splitlines() if x.strip()]
    assert len(lines) == 1 and "is compressed" in lines[0], out.stderr
    assert not (tmp_path / "e.json").exists()
    json.dumps(lines)   # plain text
