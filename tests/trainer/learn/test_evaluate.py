"""protocad-evaluate: per-context tables, JSON, the random baseline, several tasks, contexts
subsets, and one run through the ROS nodes."""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from helpers.agents import tiny_checkpoint
from helpers.bags import run_cli

from protocad_ros.atomic import file_sha256
from sim_bridge.contract.contexts import TASKS


def test_select_contexts_subsets():
    from trainer.learn.evaluate import parse_context, select_contexts

    assert len(select_contexts("walker_walk")) == 64
    sub = select_contexts("walker_walk", max_contexts=5)   # the stratified subset: 5 m, 5 d values
    assert len(sub) == 5 and len({c["m"] for c in sub}) == 5 and len({c["d"] for c in sub}) == 5
    assert select_contexts("pendulum_swingup", contexts=[parse_context("m=0.4")]) == [{"m": 0.4}]
    with pytest.raises(ValueError, match="belongs to the train split"):
        select_contexts("pendulum_swingup", contexts=[{"m": 1.0}])


@pytest.mark.process
def test_checkpoints_of_two_tasks_with_random_baseline(tmp_path):
    tiny_checkpoint(tmp_path / "pend" / "checkpoints" / "latest.pt")
    b = tiny_checkpoint(tmp_path / "hop.pt", task="hopper_stand", action_dim=4)
    out = tmp_path / "eval.json"
    r = run_cli("trainer.learn.evaluate", tmp_path / "pend", b, "--random", "--episodes", "2", "--max-contexts", "2",
                "--time-limit", "10", "--workers", "0", "--json", out)
    assert r.returncode == 0, r.stdout + r.stderr
    txt = r.stdout
    assert "pendulum_swingup on test contexts" in txt and "hopper_stand on test contexts" in txt
    assert "m=0.2 " in txt and "m=1.8 " in txt and "m=0.25 " in txt and "m=2 " in txt
    assert "random mean" in txt                          # the baseline column beside each context
    assert "mean over tasks" in txt and "median over tasks" in txt
    d = json.loads(out.read_text())
    assert [x["task"] for x in d["results"]] == ["pendulum_swingup", "hopper_stand"]
    pend = d["results"][0]
    assert [c["episodes"] for c in pend["per_context"]] == [2, 2]
    assert pend["mean_return"] == pytest.approx(np.mean([c["mean_return"] for c in pend["per_context"]]))
    assert pend["env_steps"] == 1234 and pend["updates"] == 0
    # each result names the exact file it measured
    assert pend["sha256"] == file_sha256(tmp_path / "pend" / "checkpoints" / "latest.pt")
    assert d["results"][1]["sha256"] == file_sha256(b) and d["random"][0]["sha256"] is None
    assert {x["task"] for x in d["random"]} == {"pendulum_swingup", "hopper_stand"}
    s = d["summary"]
    assert s["mean_over_tasks"] == pytest.approx(np.mean(list(s["per_task"].values())))
    # bad input: a clear error, exit code 2
    r = run_cli("trainer.learn.evaluate", tmp_path / "nothing.pt")
    assert r.returncode == 2 and "does not exist" in r.stderr
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    r = run_cli("trainer.learn.evaluate", tmp_path / "junk.pt", "--episodes", "1")
    assert r.returncode == 2 and "junk.pt" in r.stderr


@pytest.mark.process
def test_random_baseline_in_worker_processes_matches_in_process(tmp_path):
    from trainer.learn.evaluate import EvalPlan, evaluate_checkpoint

    plan = EvalPlan(episodes=1, contexts=[{"m": 0.5}, {"m": 1.5}], seed=3, time_limit=30)
    a = evaluate_checkpoint(None, dataclasses.replace(plan, workers=0), task="pendulum_swingup")
    b = evaluate_checkpoint(None, dataclasses.replace(plan, workers=2), task="pendulum_swingup")
    assert [c.returns for c in a.per_context] == [c.returns for c in b.per_context]


@pytest.mark.ros
@pytest.mark.process
@pytest.mark.slow
def test_through_ros_nodes(tmp_path):
    ck = tiny_checkpoint(tmp_path / "ck.pt")
    out = tmp_path / "ros.json"
    r = run_cli("trainer.launch.ros_evaluate", ck, "--through-ros", "--ros-episodes", "2", "--episode-length", "10",
                "--ros-dir", tmp_path / "ros", "--json", out, timeout=240)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "through ROS" in r.stdout
    assert r.stdout.count("[evaluate] episode ") == 2 and "return " in r.stdout   # a line per episode
    d = json.loads(out.read_text())["results"][0]
    assert d["mode"] == "through ROS" and d["episodes"] == 2
    assert all(c["split"] == "test" for c in d["per_context"])
    assert list((tmp_path / "ros").glob("eval_test_*/*.mcap"))   # the recorded bag stays

    # Without a total the bridge cycles through the split: every test context exactly once.
    out = tmp_path / "cycle.json"
    r = run_cli("trainer.launch.ros_evaluate", ck, "--through-ros", "--episodes", "1", "--episode-length", "5",
                "--ros-dir", tmp_path / "ros_cycle", "--json", out, timeout=240)
    assert r.returncode == 0, r.stdout + r.stderr
    d = json.loads(out.read_text())["results"][0]
    got = sorted(c["context"]["m"] for c in d["per_context"])
    assert got == pytest.approx(sorted(TASKS["pendulum_swingup"].test["m"]), abs=1e-6)
    assert all(len(c["returns"]) == 1 for c in d["per_context"])
