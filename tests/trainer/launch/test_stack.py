"""protocad-stack: bridge, policy and recorder from one file, one Ctrl-C for all."""
from __future__ import annotations

import signal
import sys

import pytest
from helpers import wait_until

from sim_bridge.contract import topics as T
from trainer.bag.reader import BagReader

pytestmark = pytest.mark.process


@pytest.mark.ros
def test_one_ctrl_c_three_clean_exits_and_every_step_has_its_action_from_stamp_0(spawn, tmp_path):
    bag = tmp_path / "bag"
    (tmp_path / "stack.yaml").write_text(
        "bridge: {task: pendulum_swingup, episode_length: 50}\n"
        "policy: {num_threads: 1}\n"
        f"recorder: {{output: {bag}}}\n")
    stack = spawn("stack", "-m", "trainer.launch.stack", str(tmp_path / "stack.yaml"))
    wait_until(lambda: "episode 3 " in stack.output(), 240, "three episodes through the stack")
    assert stack.stop(signal.SIGINT, timeout=60) == 0, stack.output()[-3000:]
    out = stack.output()
    assert "[stack] exit codes: bridge 0, policy 0, recorder 0" in out, out[-3000:]
    assert "[bridge]" in out and "[policy]" in out and "[recorder]" in out   # one combined log

    reader = BagReader(bag)
    info_stamps, action_stamps = [], set()
    for m in reader.messages(topics=[T.topic_name(T.DEFAULT_NAMESPACE, T.STEP_INFO),
                                     T.topic_name(T.DEFAULT_NAMESPACE, T.ACTION)]):
        stamp = T.stamp_to_ns(reader.decode(m).header.stamp)
        (info_stamps.append if m.topic.endswith(T.STEP_INFO) else action_stamps.add)(stamp)
    assert info_stamps and info_stamps[0] == 0
    dt = info_stamps[1] - info_stamps[0]
    assert info_stamps == [i * dt for i in range(len(info_stamps))]       # no gap at the start or later
    assert set(info_stamps) <= action_stamps                              # every step answered, in the bag


def test_stack_file_mistakes_are_refused_with_the_reason(tmp_path):
    import subprocess

    bad = tmp_path / "bad.yaml"
    bad.write_text("brigde: {task: walker_walk}\n")
    r = subprocess.run([sys.executable, "-m", "trainer.launch.stack", str(bad)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "unknown key(s) ['brigde']" in r.stderr


def test_a_checkpoint_of_another_task_is_refused_before_any_node_starts(tmp_path):
    import subprocess

    from protocad_ros.checkpoint.agent_file import save_checkpoint
    from protocad_ros.model.agent import Agent
    from protocad_ros.model.config import make_config

    cfg = make_config("pendulum_swingup", "small", "dreamer", **{
        "world_model.deter": 16, "world_model.hidden": 16, "world_model.stoch": 4,
        "world_model.cnn_depth": 4, "world_model.mlp_units": 16, "behavior.actor_units": 16,
        "behavior.critic_units": 16})
    save_checkpoint(tmp_path / "run" / "checkpoints" / "latest.pt", Agent(cfg, 1), {"env_steps": 0})
    stack = tmp_path / "stack.yaml"
    # the README's example: a walker bridge, and the only checkpoint a newcomer has (pendulum)
    stack.write_text(f"bridge: {{task: walker_walk}}\npolicy: {{checkpoint: {tmp_path / 'run'}}}\nrecorder: false\n")
    r = subprocess.run([sys.executable, "-m", "trainer.launch.stack", str(stack), "--log-dir", str(tmp_path / "logs")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stdout + r.stderr
    assert "trained on pendulum_swingup but bridge.task is walker_walk" in r.stderr, r.stderr
    assert not (tmp_path / "logs").exists()             # nothing started
    # the same checkpoint with its own task passes the check
    from trainer.launch.stack import checkpoint_mismatch
    assert checkpoint_mismatch({"bridge": {"task": "pendulum_swingup"},
                                "policy": {"checkpoint": str(tmp_path / "run")}}) is None
