"""A policy node handed a deflate-bombed checkpoint file refuses it from the zip directory
(configure fails, exit 2, the log naming the entry); the checkpoint publisher's reader refuses it before announcing it. Both go through the
one reader every load path uses (protocad_ros.checkpoint.agent_file._read)."""
from __future__ import annotations

import pytest
from helpers import wait_exit
from helpers.hostile_checkpoints import tiny_agent, write_deflate_bomb
from helpers.policy import START, policy_args

from protocad_ros.checkpoint.agent_file import save_checkpoint
from protocad_ros.checkpoint.files import CheckpointError


@pytest.fixture(scope="module")
def bomb(tmp_path_factory):
    d = tmp_path_factory.mktemp("node_bomb")
    return write_deflate_bomb(save_checkpoint(d / "good.pt", tiny_agent()), d / "bomb.pt")


@pytest.mark.ros
@pytest.mark.process
def test_the_policy_node_refuses_a_bombed_checkpoint_file(spawn, bomb):
    node = spawn("policy", *policy_args(f"checkpoint:={bomb}"))
    assert wait_exit(node, START) == 2
    out = node.log_path.read_text()
    assert "cannot load checkpoint" in out and "is compressed" in out, out
    assert "Traceback" not in out


def test_the_publishers_reader_refuses_it_before_announcing(bomb):
    from trainer.nodes.checkpoint_publisher import CheckpointPublisherNode

    with pytest.raises(CheckpointError, match="is compressed"):
        CheckpointPublisherNode._read(None, str(bomb))   # the reader it announces from


def test_a_file_over_the_limit_is_refused_before_it_is_read(bomb, monkeypatch):
    from protocad_ros.checkpoint.files import read_checkpoint_file
    from trainer.nodes.checkpoint_publisher import CheckpointPublisherNode

    with pytest.raises(CheckpointError, match="more than the limit of 4096"):
        read_checkpoint_file(bomb, 4096)
    monkeypatch.setenv("PROTOCAD_MAX_CHECKPOINT_BYTES", "4096")
    with pytest.raises(CheckpointError, match="more than the limit of 4096"):
        CheckpointPublisherNode._read(None, str(bomb))


@pytest.mark.ros
@pytest.mark.process
def test_the_policy_node_refuses_a_file_over_max_checkpoint_bytes_unread(spawn, bomb):
    node = spawn("policy", *policy_args(f"checkpoint:={bomb}", "max_checkpoint_bytes:=4096"))
    assert wait_exit(node, START) == 2
    out = node.log_path.read_text()
    assert "cannot read checkpoint" in out and "more than the limit of 4096" in out, out

