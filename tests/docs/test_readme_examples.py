"""The README's quick examples of "Running it as ROS 2 nodes", copied from README.md and run as
written, in a directory laid out as the README assumes (`.venv`, a walker checkpoint at
`runs/X/checkpoints/latest.pt`): the one-command stack, the three-terminal start, and the
everyday `ros2` verbs (from msgs_docs/ros2cli.md, the page the README links for them). A block
that runs until Ctrl-C gets one once the ROS graph shows it working.
"""
from __future__ import annotations

import os
import re
import signal
import subprocess
from pathlib import Path

import pytest
from helpers import ROOT, wait_until
from helpers.agents import tiny_checkpoint
from helpers.ros import Probe
from sensor_msgs.msg import JointState

from sim_bridge.contract import qos
from sim_bridge.contract import topics as T
from trainer.bag.reader import BagReader

pytestmark = [pytest.mark.ros, pytest.mark.process]

START = 240.0   # three nodes importing torch and EGL on 2 loaded cores
NS = T.DEFAULT_NAMESPACE


def readme_block(marker: str, doc: str = "README.md") -> str:
    blocks = [b for b in re.findall(r"```bash\n(.*?)```", (ROOT / doc).read_text(), re.S) if marker in b]
    assert len(blocks) == 1, f"expected one {doc} bash block containing {marker!r}, found {len(blocks)}"
    return blocks[0]


@pytest.fixture
def workdir(tmp_path):
    (tmp_path / ".venv").symlink_to(Path(os.sys.prefix))
    ckpt = tmp_path / "runs" / "X" / "checkpoints"
    ckpt.mkdir(parents=True)
    tiny_checkpoint(ckpt / "latest.pt", task="walker_walk", action_dim=6)
    return tmp_path


@pytest.fixture
def probe():
    p = Probe("readme_probe")
    yield p
    p.close()


def terminal(workdir: Path, line: str, log: Path) -> subprocess.Popen:
    """`line` typed into a fresh terminal in which the venv was activated."""
    return subprocess.Popen(["bash", "-c", f"source .venv/bin/activate && {line}"], cwd=workdir,
                            stdout=open(log, "wb"), stderr=subprocess.STDOUT, start_new_session=True)


def ctrl_c(p: subprocess.Popen, timeout: float = 60) -> int:
    os.killpg(p.pid, signal.SIGINT)
    try:
        return p.wait(timeout)
    except subprocess.TimeoutExpired:
        os.killpg(p.pid, signal.SIGKILL)
        raise


def assert_every_step_answered_from_stamp_0(bag: Path) -> int:
    reader = BagReader(bag)
    steps, actions = [], set()
    for m in reader.messages(topics=[T.topic_name(NS, T.STEP_INFO), T.topic_name(NS, T.ACTION)]):
        stamp = T.stamp_to_ns(reader.decode(m).header.stamp)
        (steps.append if m.topic.endswith(T.STEP_INFO) else actions.add)(stamp)
    assert steps and steps[0] == 0
    dt = steps[1] - steps[0]
    assert steps == [i * dt for i in range(len(steps))]
    assert set(steps) <= actions
    return len(steps)


def steps_seen(probe) -> list:
    """The actions the policy publishes, one per step. Not step_info: a reader of step_info is
    one of the readers the lock-step bridge waits for, and could stand in for the recorder's
    (the bridge would then start before the recorder's reader is matched, and step_info would
    be missing from the bag)."""
    return probe.record(T.ACTION, JointState, qos.action_qos())


def test_the_one_command_stack_as_written(workdir, probe):
    script = workdir / "stack_block.sh"
    script.write_text(readme_block("protocad-stack stack.yaml"))
    seen = steps_seen(probe)
    p = subprocess.Popen(["bash", "-e", str(script)], cwd=workdir, stdout=open(workdir / "stack.log", "wb"),
                         stderr=subprocess.STDOUT, start_new_session=True)
    try:
        wait_until(lambda: len(seen) >= 30 or p.poll() is not None, START, "30 steps through the stack")
    finally:
        rc = ctrl_c(p)
    out = (workdir / "stack.log").read_text(errors="replace")
    assert rc == 0 and "[stack] exit codes: bridge 0, policy 0, recorder 0" in out, out[-3000:]
    assert assert_every_step_answered_from_stamp_0(workdir / "runs/X/bags/session1") >= 30


def test_three_terminals_then_the_everyday_ros2_verbs_as_written(workdir, probe):
    record, policy, bridge = [ln for ln in readme_block("ros2 run trainer record").splitlines() if ln.strip()]
    seen = steps_seen(probe)
    node = probe.node
    action = T.topic_name(NS, T.ACTION)
    procs = [terminal(workdir, record, workdir / "record.log")]
    try:
        wait_until(lambda: "recorder" in [n for n, _ in node.get_node_names_and_namespaces()], START,
                   "the recorder in the graph")
        procs.append(terminal(workdir, policy, workdir / "policy.log"))
        # The recorder subscribes to each topic once it appears: the policy's action topic first.
        wait_until(lambda: node.count_publishers(action) >= 1 and node.count_subscribers(action) >= 1, START,
                   "the policy publishing actions and the recorder reading them")
        procs.append(terminal(workdir, bridge, workdir / "bridge.log"))
        wait_until(lambda: len(seen) >= 30, START, "30 steps")
    finally:
        codes = [ctrl_c(p) for p in reversed(procs)]       # bridge, policy, then the recorder
    logs = {n: (workdir / f"{n}.log").read_text(errors="replace") for n in ("record", "policy", "bridge")}
    assert codes == [0, 0, 0], {k: v[-2000:] for k, v in logs.items()}
    assert assert_every_step_answered_from_stamp_0(workdir / "runs/X/bags/session1") >= 30

    assert "(msgs_docs/ros2cli.md)" in (ROOT / "README.md").read_text()
    lines = [ln for ln in readme_block("ros2 node list", "msgs_docs/ros2cli.md").splitlines() if ln.strip()]
    first, rest = lines[0], lines[1:]
    sim = terminal(workdir, first, workdir / "ros2_bridge.log")
    try:
        wait_until(lambda: node.count_publishers(T.topic_name(NS, T.IMAGE)) >= 1, START, "the documented bridge")
        for line in rest:
            res = subprocess.run(["bash", "-c", f"source .venv/bin/activate && {line}"], cwd=workdir,
                                 capture_output=True, text=True, timeout=120)
            assert res.returncode == 0 and res.stdout.strip(), (line, res.stdout, res.stderr)
            assert "Traceback" not in res.stderr and "not supported" not in res.stderr, (line, res.stderr)
    finally:
        assert ctrl_c(sim) == 0
