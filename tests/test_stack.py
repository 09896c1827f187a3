"""protocad-stack: bridge, policy and recorder from one file, one Ctrl-C for all."""
from __future__ import annotations

import signal
import sys

from conftest import wait_for
from sim_bridge import topics as T
from trainer import mcap_io as M


def test_one_ctrl_c_three_clean_exits_and_every_step_has_its_action_from_stamp_0(spawn, tmp_path):
    bag = tmp_path / "bag"
    (tmp_path / "stack.yaml").write_text(
        "bridge: {task: pendulum_swingup, episode_length: 50}\n"
        "policy: {num_threads: 1}\n"
        f"recorder: {{output: {bag}}}\n")
    stack = spawn("stack", "-m", "trainer.stack", str(tmp_path / "stack.yaml"))
    wait_for(lambda: "episode 3 " in stack.output(), 240, "three episodes through the stack")
    assert stack.stop(signal.SIGINT, timeout=60) == 0, stack.output()[-3000:]
    out = stack.output()
    assert "[stack] exit codes: bridge 0, policy 0, recorder 0" in out, out[-3000:]
    assert "[bridge]" in out and "[policy]" in out and "[recorder]" in out   # one combined log

    reader = M.BagReader(bag)
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
    r = subprocess.run([sys.executable, "-m", "trainer.stack", str(bad)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "unknown key(s) ['brigde']" in r.stderr
