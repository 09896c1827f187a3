"""A fleet through the Fast DDS Discovery Server (trainer/launch/discovery.py): protocad-loop starts the
server on 127.0.0.1 as its first process, every node discovers through it (no multicast, no
peer list), and training uses both actor groups' logs."""
from __future__ import annotations

import json
import os

import pytest
from helpers import wait_until
from helpers.bags import TINY, check_robot_episodes, check_robots_recorded_and_trained, loop_failure, run_cli

from trainer.launch.discovery import free_port

ROBOTS = ["/protocad/robot0", "/protocad/robot1"]


def _seen(proc) -> dict:
    proc.stop()
    lines = [ln for ln in proc.output().splitlines() if ln.startswith("{")]
    assert lines, proc.output()
    return json.loads(lines[-1])


@pytest.mark.ros
@pytest.mark.process
def test_two_actor_groups_through_a_discovery_server(tmp_path, spawn):
    port = free_port()
    server = f"127.0.0.1:{port}"
    # Two onlookers in the loop's domain: one discovering the usual way, one a super client of
    # the fleet's server (both up before the server: a client keeps asking for it).
    plain = spawn("watch_plain", "tests/helpers/graph_watch.py")
    super_client = spawn("watch_super", "tests/helpers/graph_watch.py", "--server", server)
    control = spawn("watch_control", "tests/helpers/graph_watch.py", "--name", "control")   # plain, seen by plain
    for w in (plain, super_client, control):
        wait_until(lambda w=w: "watching" in w.output() or not w.alive(), 60, f"{w.args} to start")
    run = tmp_path / "run"
    r = run_cli("trainer.launch.loop", "--task", "pendulum_swingup", *TINY, "--episode-length", "12", "--robots", "2",
                "--prefill-episodes", "2", "--cycles", "1", "--updates-per-episode", "2",
                "--eval-episodes", "0", "--no-visualize", "--run-dir", run, "--start-discovery-server", server,
                "--domain-id", os.environ["ROS_DOMAIN_ID"], "--no-progress", timeout=300)
    assert r.returncode == 0, loop_failure(r, run)
    assert f"discovery through the Fast DDS Discovery Server {server} (started here" in r.stdout, r.stdout
    # the server was the loop's child, stopped after every node
    assert "Server is running" in (run / "logs" / "discovery_server.log").read_text()
    check_robots_recorded_and_trained(run, ROBOTS, episode_length=12,
                                      phases=[("00_prefill", 2), ("01_collect", 2)], episodes=4,
                                      updates=2 + 2 * 2, cache_dir=tmp_path / "cache")
    # Through the server the fleet was visible to a super client; a participant in the same
    # domain without the server saw none of it (the fleet's nodes did not answer the usual
    # discovery, so it is all the server's doing).
    sup, pl = _seen(super_client), _seen(plain)
    assert "/control" in pl["nodes"] and "/control" not in sup["nodes"], (pl, sup)
    for ns in ROBOTS:
        assert {f"{ns}/image", f"{ns}/action", f"{ns}/step_info"} <= set(sup["topics"]), sup
        assert f"{ns}/sim_bridge" in sup["nodes"] and f"{ns}/policy" in sup["nodes"], sup
    assert not [t for t in pl["topics"] if t.startswith("/protocad")], pl
    assert not [n for n in pl["nodes"] if n.startswith("/protocad")], pl


def test_bad_discovery_server_addresses_are_one_clear_line(capsys):
    from trainer.launch.loop import build_parser

    for args in (["--discovery-server", "localhost"], ["--discovery-server", "127.0.0.1:0"],
                 ["--discovery-server", ";"], ["--start-discovery-server", "somehost:11811"],
                 ["--start-discovery-server", "70000"]):
        with pytest.raises(SystemExit) as exc:
            build_parser().parse_args(args)
        err = capsys.readouterr().err.splitlines()
        assert exc.value.code == 2 and args[0] in err[-1] and "expected" in err[-1], err
    a = build_parser().parse_args(["--start-discovery-server"])
    assert a.start_discovery_server == ("127.0.0.1", 11811) and a.discovery_server is None
    assert build_parser().parse_args(["--start-discovery-server", "0.0.0.0:7000"]).start_discovery_server == ("0.0.0.0", 7000)
    assert build_parser().parse_args(["--discovery-server", ";10.0.0.2:11811"]).discovery_server == ";10.0.0.2:11811"


def test_a_server_on_every_interface_is_warned_about():
    from trainer.launch.discovery import exposure_warning
    for host in ("0.0.0.0", "::"):
        w = exposure_warning(host)
        assert w and host in w and "msgs_docs/security.md" in w and "actions" in w
    assert exposure_warning("127.0.0.1") is None and exposure_warning("10.0.0.2") is None


@pytest.mark.ros
@pytest.mark.process
def test_actor_groups_placed_like_on_other_machines(tmp_path, spawn):
    """`protocad-fleet` as on three machines (here all on 127.0.0.1): A runs the server, one
    recorder for robot0 and robot1 and the checkpoint publisher on the learner's file; B and C
    one actor group each, whose policy receives that checkpoint over ROS into its own file
    (no access to the learner's directory) and serves it before its bridge steps; the bag holds
    both robots' episodes and protocad-train learns from both."""
    from protocad_ros.checkpoint.agent_file import save_checkpoint
    from protocad_ros.model.agent import make_agent
    from protocad_ros.model.config import make_config

    learner = tmp_path / "learner_ckpt" / "latest.pt"
    agent = make_agent(make_config("pendulum_swingup", "small"), 1)
    agent.updates.fill_(3)
    save_checkpoint(learner, agent)
    topic = "/protocad/checkpoint"
    port = free_port()
    dom = ["--domain-id", os.environ["ROS_DOMAIN_ID"]]
    bag = tmp_path / "bags" / "session1"
    a = spawn("machine_a", "-m", "trainer.launch.fleet", "--start-discovery-server", str(port), "--robots", "2",
              "--no-actors", "--record", str(bag), "--log-dir", str(tmp_path / "logs_a"),
              "--publish-checkpoint", str(learner), "--checkpoint-topic", topic, *dom)
    wait_until(lambda: f"publishing {learner} on {topic}" in a.output() or not a.alive(), 90,
             "machine A's recorder and checkpoint publisher")
    assert a.alive(), a.output()
    own = {m: tmp_path / f"machine_{m}" / "policy.pt" for m in "bc"}
    groups = [spawn(f"machine_{m}", "-m", "trainer.launch.fleet", "--discovery-server", f"127.0.0.1:{port}",
                    "--robots", "1", "--first-robot", str(i), "--episodes", "1", "--episode-length", "12",
                    "--checkpoint", str(own[m]), "--checkpoint-topic", topic, "--wait-for-checkpoint",
                    "--trusted-key", str(tmp_path / "keys" / "checkpoint.pub"),   # A's run key (RUN_DIR = tmp_path)
                    "--log-dir", str(tmp_path / f"logs_{m}"), *dom) for i, m in enumerate("bc")]
    for g in groups:
        wait_until(lambda g=g: not g.alive(), 180, f"{g.args} to finish")
        assert g.p.returncode == 0 and "every bridge finished" in g.output(), g.output()
    for m in "bc":   # each policy's own copy is the learner's checkpoint, byte for byte, served
        assert own[m].read_bytes() == learner.read_bytes()   # from the first episode on
        log = (tmp_path / f"logs_{m}" / f"policy_robot{'bc'.index(m)}.log").read_text()
        assert f"now serving checkpoint {own[m]} (updates=3)" in log, log
        assert "serving only checkpoints signed by trusted key(s)" in log, log   # signed by default
    assert a.stop() == 0, a.output()
    assert "exit codes: recorder 0, checkpoint_publisher 0, discovery_server 0" in a.output(), a.output()
    check_robot_episodes(bag, ROBOTS, episode_length=12)
    t = run_cli("trainer.learn.train", "--logs", bag.parent, "--namespace", *ROBOTS, "--task", "pendulum_swingup",
                *TINY, "--updates", "1", "--run-dir", tmp_path / "learner", "--cache-dir", tmp_path / "cache",
                timeout=300)
    assert t.returncode == 0, t.stdout + t.stderr


@pytest.mark.ros
@pytest.mark.process
def test_a_fleet_profile_allows_the_fleet_interface_beside_loopback(tmp_path):
    import subprocess
    import sys

    from trainer.launch.discovery import fleet_profile
    text = fleet_profile(["10.0.0.5"])
    assert "<address>127.0.0.1</address><address>10.0.0.5</address>" in text
    r = subprocess.run([sys.executable, "-m", "trainer.launch.discovery", "--print-profile", "10.0.0.5"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and r.stdout == text
    bad = subprocess.run([sys.executable, "-m", "trainer.launch.discovery", "--print-profile", "eth0"],
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1
