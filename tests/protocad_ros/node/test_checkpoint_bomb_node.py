"""A policy node handed a deflate-bombed checkpoint file refuses it from the zip directory
(configure fails, exit 2, the log naming the entry); the checkpoint publisher's reader refuses it before announcing it. Both go through the
one reader every load path uses (protocad_ros.checkpoint._read)."""
from __future__ import annotations

import pytest

from helpers import wait_exit
from helpers.hostile_checkpoints import tiny_agent, write_deflate_bomb
from helpers.policy import START, policy_args
from protocad_ros.checkpoint import CheckpointError, save_checkpoint


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
