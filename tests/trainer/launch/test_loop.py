"""protocad-loop through real ROS processes (sim bridge, policy node, random actor, recorder):
prefill + two collect-train-reload cycles, and the policy node serving the second checkpoint."""
from __future__ import annotations

import json
import os
import re

import pytest
from helpers.bags import TINY, check_robots_recorded_and_trained, loop_failure, run_cli

pytestmark = [pytest.mark.ros, pytest.mark.process]


def test_two_collect_train_reload_cycles_through_ros(tmp_path):
    run = tmp_path / "run"
    C = 3
    r = run_cli("trainer.launch.loop", "--task", "pendulum_swingup", *TINY, "--episode-length", "16",
                "--prefill-episodes", "2", "--cycles", "2", "--updates-per-episode", str(C),
                "--eval-episodes", "1", "--eval-max-contexts", "2", "--no-visualize", "--run-dir", run,
                "--domain-id", os.environ["ROS_DOMAIN_ID"], "--log-every", "1", "--no-progress", timeout=400)
    assert r.returncode == 0, loop_failure(r, run)
    # after the first training phase the loop says what the rest takes at its measured rate
    assert re.search(r"\[loop\] training runs at [\d.]+ updates/s on this machine \(float32, 1 torch thread\(s\)\): "
                     rf"the {2 * C} updates left take about .* with 2 collection cycle\(s\) the loop ends in about", r.stdout), r.stdout
    phases = json.loads((run / "phases.json").read_text())
    assert [p["bag"] for p in phases] == ["00_prefill", "01_collect", "02_collect"]
    assert [p["episodes"] for p in phases] == [2, 1, 1]
    # cycle 1 was served by the checkpoint trained after the prefill (C updates), cycle 2 by the
    # one trained after cycle 1 (2C updates): the policy node picked up the new checkpoint
    assert [p.get("served_updates") for p in phases[1:]] == [C, 2 * C]
    # ... one policy node process, which reloaded it (no restart): started on the first
    # checkpoint, then loaded the second one and served it from the next episode
    log = (run / "logs" / "policy.log").read_text()
    assert log.count("$ ") == 1 and f"serving checkpoint {run}/checkpoints/latest.pt (updates={C})" in log
    assert f"now serving checkpoint {run}/checkpoints/latest.pt (updates={2 * C})" in log
    # the recorded /diagnostics of the second cycle's bag say the same (the node's own report)
    from trainer.bag.reader import BagReader
    from trainer.bag.rosmsg import decode

    served = set()
    for m in BagReader(run / "bags" / "02_collect").messages(["/diagnostics"]):
        for status in decode(m.msgtype, m.data).status:
            kv = {v.key: v.value for v in status.values}
            if "checkpoint_updates" in kv and int(kv.get("observations_answered", 0)) > 0:
                served.add(int(kv["checkpoint_updates"]))
    assert 2 * C in served, served
    # final checkpoint: C after the prefill + C per collected episode
    from protocad_ros.checkpoint.agent_file import read_checkpoint

    ck = read_checkpoint(run / "checkpoints" / "latest.pt")
    assert int(ck["modules"]["updates"]) == 3 * C
    assert ck["counters"]["episodes"] == 4 and ck["counters"]["collect_phases"] == 2
    assert "mean over contexts" in r.stdout and list((run / "eval").glob("test_*.json"))
    # the final table sets the random policy beside the trained one, on the same contexts
    assert "random mean" in r.stdout and "diff" in r.stdout
    final = json.loads(next((run / "eval").glob("test_*.json")).read_text())
    assert [c["context"] for c in final["random"]["per_context"]] == [c["context"] for c in final["per_context"]]
    # every bag is a complete, cleanly closed rosbag2 bag without any problem to report
    for p in phases:
        assert (run / "bags" / p["bag"] / "metadata.yaml").exists() and not p["problems"], p
    signed_by_default(run, r.stdout, log)

    continue_from_a_policy_file(run, tmp_path)


def continue_from_a_policy_file(trained, tmp_path):
    """--init-policy: a policy file's networks and weights, fresh optimizers and counter; first
    the table of that policy against the random one through the ROS nodes."""
    import torch

    from protocad_ros.checkpoint.agent_file import load_checkpoint, read_checkpoint, save_policy

    agent, _ = load_checkpoint(trained / "checkpoints" / "latest.pt", restore_rng=False)
    policy = save_policy(tmp_path / "policies" / "pendulum_swingup.pt", agent, {"what": "a test policy"})
    run, C = tmp_path / "from_policy", 2
    r = run_cli("trainer.launch.loop", "--init-policy", policy, "--start-eval-episodes", "2", "--seed", "5",
                "--episode-length", "16", "--prefill-episodes", "1", "--cycles", "1",
                "--updates-per-episode", str(C), "--batch-size", "4", "--seq-len", "8", "--threads", "1",
                "--eval-episodes", "1", "--eval-max-contexts", "2", "--no-visualize", "--run-dir", run,
                "--domain-id", os.environ["ROS_DOMAIN_ID"], "--no-progress", timeout=400)
    assert r.returncode == 0, loop_failure(r, run)
    assert "against the random policy on 2 unseen-context episode(s)" in r.stdout
    # the closing table: the trained checkpoint beside the policy it started from and the random
    # one, on the same contexts
    final = json.loads(next((run / "eval").glob("test_*.json")).read_text())
    contexts = [c["context"] for c in final["per_context"]]
    assert len(contexts) == 2 and final["start_policy"]["policy"] == str(policy)
    assert [c["context"] for c in final["start_policy"]["per_context"]] == contexts
    assert [c["context"] for c in final["random"]["per_context"]] == contexts
    assert "pendulum_swingup.pt mean" in r.stdout and "random mean" in r.stdout
    start = json.loads((run / "eval" / "start.json").read_text())
    assert start["mode"] == "through ROS" and start["random"]["mode"] == "through ROS"
    assert sum(len(c["returns"]) for c in start["per_context"]) == 2
    assert [c["context"] for c in start["random"]["per_context"]] == [c["context"] for c in start["per_context"]]
    ck = read_checkpoint(run / "checkpoints" / "latest.pt")
    assert ck["config"]["world_model"] == read_checkpoint(policy)["config"]["world_model"]
    assert int(ck["modules"]["updates"]) == 2 * C         # its own count, from 0
    # trained on from the policy's weights (4 Adam steps away: each moves a weight by <= ~lr),
    # not from seed 5's fresh initialisation
    start_w = agent.state_dict()["wm.encoder.convs.0.weight"].to(torch.bfloat16).float()
    end_w = ck["modules"]["wm.encoder.convs.0.weight"]
    assert 0 < (end_w - start_w).abs().max() < 0.01
    # training options apply on top of the policy's config; one that changes its networks is refused
    assert ck["config"]["train"]["seed"] == 5 and ck["config"]["train"]["batch_size"] == 4
    bad = run_cli("trainer.launch.loop", "--init-policy", policy, "--set", "world_model.deter=64",
                  "--run-dir", tmp_path / "refused", "--no-progress", timeout=120)
    assert bad.returncode == 2 and "world_model.deter: 32 != 64" in bad.stderr, bad.stderr
    assert not (tmp_path / "refused" / "bags").exists()


def test_two_robots_in_one_loop(tmp_path):
    """--robots 2: two bridges and two policy nodes in /protocad/robot0 and /protocad/robot1
    (own /clock each), one recorder for both; the episodes of both are in the bags under their
    namespaces and are what training counts and samples."""
    run = tmp_path / "run"
    r = run_cli("trainer.launch.loop", "--task", "pendulum_swingup", *TINY, "--episode-length", "12", "--robots", "2",
                "--prefill-episodes", "2", "--cycles", "1", "--updates-per-episode", "2",
                "--eval-episodes", "0", "--no-visualize", "--run-dir", run,
                "--domain-id", os.environ["ROS_DOMAIN_ID"], "--no-progress", timeout=400)
    assert r.returncode == 0, loop_failure(r, run)
    check_robots_recorded_and_trained(run, ["/protocad/robot0", "/protocad/robot1"], episode_length=12,
                                      phases=[("00_prefill", 2), ("01_collect", 2)], episodes=4,
                                      updates=2 + 2 * 2, cache_dir=tmp_path / "cache")
    for i in (0, 1):
        assert (run / "logs" / f"policy_robot{i}.log").exists()
    # offline: protocad-train reads both robots of the same bags
    t = run_cli("trainer.learn.train", "--logs", run / "bags", "--namespace", "/protocad/robot0", "/protocad/robot1",
                "--task", "pendulum_swingup", *TINY, "--updates", "1", "--run-dir", tmp_path / "offline",
                "--cache-dir", tmp_path / "cache", timeout=300)
    assert t.returncode == 0, t.stdout + t.stderr
    assert "/protocad/robot0" in t.stdout and "/protocad/robot1" in t.stdout, t.stdout


def signed_by_default(run, stdout: str, policy_log: str) -> None:
    """The loop made its run key (0600), signed every checkpoint with it, and its policy node
    served only what that key signed (it trusted nothing else, and refused nothing)."""
    import hashlib
    import stat

    from protocad_ros.checkpoint.signing import load_trusted_keys, verify_file

    key, pub = run / "keys" / "checkpoint.key", run / "keys" / "checkpoint.pub"
    assert stat.S_IMODE(key.stat().st_mode) == 0o600 and "checkpoints signed with the run key" in stdout
    (kid,) = load_trusted_keys([pub])
    ckpt = run / "checkpoints" / "latest.pt"
    data = ckpt.read_bytes()
    assert verify_file(ckpt, hashlib.sha256(data).hexdigest(), len(data), load_trusted_keys([pub])).key_id == kid
    assert f"serving only checkpoints signed by trusted key(s) {kid}" in policy_log
    assert "cannot load checkpoint" not in policy_log, policy_log

