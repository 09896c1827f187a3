"""One bounded read of a checkpoint file (issue 54, point 2): a file that passes the size check
small and then becomes a sparse 4 GiB file is refused by every reader of `.pt` files, which read
at most the size they checked plus one byte, never the path again; the refusal names the bytes
read, and the peak RSS of the reading process stays under 1 GB.

The growth is made where a stranger with write access to the directory would make it: when the
reader opens the file (`open`: the old path.stat() + path.read_bytes() read all 4 GiB, 4.5 GB
RSS), or right after the reader's size check (`fstat`), by a hook in a child process that
extends the file with truncate (a sparse file: no disk, no memory until it is read)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from helpers import ROOT
from helpers.hostile_checkpoints import tiny_agent

from protocad_ros.checkpoint.agent_file import save_checkpoint

pytestmark = pytest.mark.usefixtures("one_torch_thread")

GROWN = 4 << 30
RSS_LIMIT_KB = 1_000_000   # 1 GB

#: The child: hooks os.open / io.open (growth when opened) or os.fstat (growth after the size
#: check) for the one file, then reads it with READER and prints what happened and its peak RSS.
CHILD = r"""
import io, json, os, resource, sys, types
target, when, reader = sys.argv[1], sys.argv[2], sys.argv[3]
ino = os.stat(target).st_ino
GROWN = 4 << 30

def grow():
    os.truncate(target, GROWN)

real_os_open, real_io_open, real_fstat = os.open, io.open, os.fstat

def os_open(path, *a, **k):
    fd = real_os_open(path, *a, **k)
    if when == "open" and os.fspath(path) == target:
        grow()
    return fd

def io_open(file, *a, **k):
    f = real_io_open(file, *a, **k)
    if when == "open" and not isinstance(file, int) and os.fspath(file) == target:
        grow()
    return f

def fstat(fd):
    st = real_fstat(fd)
    if when == "fstat" and st.st_ino == ino:
        grow()   # after the size check: the stat result says small, the file is 4 GiB
    return st

os.open, io.open, os.fstat = os_open, io_open, fstat

from protocad_ros.checkpoint.files import read_checkpoint_file
from protocad_ros.checkpoint.agent_file import load_checkpoint, read_checkpoint
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
from protocad_ros.checkpoint.signing import sign_file

def policy_node(path):   # the policy node's one read (checkpoint_serving)
    from protocad_ros.node.checkpoint_serving import read_once
    return read_once(path, 512 << 20)

def publisher(path):     # the checkpoint publisher's
    from trainer.nodes.checkpoint_publisher import CheckpointPublisherNode
    return CheckpointPublisherNode._read(types.SimpleNamespace(), path)

READERS = {"read_checkpoint_file": read_checkpoint_file, "read_checkpoint": read_checkpoint,
           "load_checkpoint": load_checkpoint, "sign_file": lambda p: sign_file(p, Ed25519PrivateKey.generate()),
           "policy_node": policy_node, "publisher": publisher}
try:
    READERS[reader](target)
    outcome = "READ"
except Exception as err:
    outcome = f"{type(err).__name__}: {err}"
# The peak RSS of this program's own memory (VmHWM): getrusage's ru_maxrss keeps the peak of the
# process before its exec too, i.e. of the pytest worker that forked it.
hwm = next(int(x.split()[1]) for x in open("/proc/self/status") if x.startswith("VmHWM:"))
print("RESULT " + json.dumps({"outcome": outcome, "size": os.stat(target).st_size, "maxrss_kb": hwm}))
"""


def read_grown(tmp_path: Path, good: Path, when: str, reader: str) -> dict:
    target = tmp_path / "agent.pt"
    target.write_bytes(good.read_bytes())
    out = subprocess.run([sys.executable, "-c", CHILD, str(target), when, reader], capture_output=True,
                         text=True, cwd=ROOT, timeout=300, env={**os.environ, "OMP_NUM_THREADS": "1"})
    line = next((x for x in out.stdout.splitlines() if x.startswith("RESULT ")), None)
    assert line, out.stdout + out.stderr
    return json.loads(line[len("RESULT "):])


@pytest.fixture(scope="module")
def good(tmp_path_factory) -> Path:
    return save_checkpoint(tmp_path_factory.mktemp("ckpt") / "good.pt", tiny_agent())


@pytest.mark.parametrize("reader", ["read_checkpoint_file", "read_checkpoint", "load_checkpoint",
                                    "sign_file", "policy_node", "publisher"])
def test_a_file_grown_to_4_gib_after_its_size_check_is_refused_reading_one_byte_more(tmp_path, good, reader):
    got = read_grown(tmp_path, good, "fstat", reader)
    size = good.stat().st_size
    assert got["size"] == GROWN   # the hook did grow it, after the check
    assert "CheckpointError" in got["outcome"], got
    assert f"grew after its size check ({size} bytes): {size + 1} bytes read" in got["outcome"], got
    assert got["maxrss_kb"] < RSS_LIMIT_KB, got


@pytest.mark.parametrize("reader", ["read_checkpoint_file", "load_checkpoint", "policy_node"])
def test_a_file_that_becomes_4_gib_when_opened_is_refused_from_its_descriptor(tmp_path, good, reader):
    """The issue's attack: small at the path's stat, 4 GiB once opened. Checked on the open
    descriptor, it is refused by its size before a byte is read."""
    got = read_grown(tmp_path, good, "open", reader)
    assert got["size"] == GROWN
    assert f"{GROWN} bytes, more than the limit of {512 << 20}" in got["outcome"], got
    assert got["maxrss_kb"] < RSS_LIMIT_KB, got


def test_a_fifo_in_place_of_the_file_is_refused_without_hanging(tmp_path):
    from protocad_ros.checkpoint.files import CheckpointError, read_checkpoint_file

    fifo = tmp_path / "agent.pt"
    os.mkfifo(fifo)
    with pytest.raises(CheckpointError, match="not a regular file"):
        read_checkpoint_file(fifo)


def test_a_file_that_stays_as_checked_still_loads(tmp_path, good):
    got = read_grown(tmp_path, good, "never", "load_checkpoint")
    assert got["outcome"] == "READ", got
