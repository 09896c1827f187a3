"""The context module's health in a run, the collapse warning, the world-model-only mode and the
true-context arm (issue 51), through protocad-train as a process on real bags; and the
study's report over crafted run files."""
from __future__ import annotations

import json
import os
import signal
from pathlib import Path

import pytest
from helpers import wait_until
from helpers.bags import TINY, make_steps, run_cli, write_bag, write_rosbags_bag
from helpers.training import ckpt_counters, metrics, train_proc

HEALTH = ("proj_cosine", "swav_pred_top", "swav_target_top", "swav_pred_entropy", "swav_target_entropy",
          "swav_pred_perplexity", "swav_target_perplexity", "proj_between_share", "modal_share",
          "proto_init_cosine")
COLLAPSING = ["--set", "context.sinkhorn_eps=100", "--set", "context.temperature=100"]


def _train(tmp_path: Path, bag: Path, name: str, *extra: str):
    return run_cli("trainer.learn.train", "--logs", bag, "--task", "pendulum_swingup", *TINY,
                   "--run-dir", tmp_path / name, "--cache-dir", tmp_path / "cache", "--log-every", "1", *extra)


@pytest.mark.process
def test_health_is_logged_and_the_collapse_warning_fires_only_on_a_collapsing_setting(tmp_path):
    bag = write_bag(tmp_path / "bag", make_steps(3, 20))
    r = _train(tmp_path, bag, "healthy", "--updates", "3")
    assert r.returncode == 0, r.stdout + r.stderr
    rows = metrics(tmp_path / "healthy")
    assert [m["update"] for m in rows] == [1, 2, 3]
    for key in HEALTH:
        assert all(key in m for m in rows), key
    assert 0.0 < rows[-1]["swav_pred_top"] <= 1.0 and -1.0 <= rows[-1]["proj_cosine"] <= 1.0
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    events = EventAccumulator(str(tmp_path / "healthy" / "tensorboard"))
    events.Reload()
    assert [e.step for e in events.Scalars("train/proj_cosine")] == [1, 2, 3]
    assert [e.step for e in events.Scalars("train/modal_share")] == [1, 2, 3]
    assert "collapsed" not in r.stdout + r.stderr

    # Sinkhorn and softmax temperatures so high that targets and predictions are uniform: the
    # trivial solution of the SwAV loss, from the first update on. One line, once, when it has
    # lasted COLLAPSE_PERSIST_UPDATES.
    r = _train(tmp_path, bag, "collapsing", "--updates", "180", "--log-every", "10", *COLLAPSING)
    assert r.returncode == 0, r.stdout + r.stderr
    lines = [x for x in r.stdout.splitlines() if "context module has collapsed" in x]
    assert len(lines) == 1 and "WARNING" in lines[0] and "near uniform" in lines[0], r.stdout
    assert "(since update 10, now 160)" in lines[0] and "training.md#context-health" in lines[0]
    assert metrics(tmp_path / "collapsing")[-1]["swav_pred_entropy"] == pytest.approx(2.079, abs=0.01)


def test_the_collapse_warning_waits_out_the_cone_every_setting_passes_through():
    """The walker A/B's shapes (results.md): every setting's projections sit in a cone for a
    while early on; the healthy ones leave it within 100 updates, the paper's stays."""
    from trainer.learn.context_health import COLLAPSE_PERSIST_UPDATES, CollapseWatch

    cone, spread = {"proj_cosine": 0.9, "swav_pred_entropy": 3.0, "swav_target_entropy": 2.0}, \
        {"proj_cosine": 0.4, "swav_pred_entropy": 3.0, "swav_target_entropy": 2.0}
    healthy = CollapseWatch(100)
    rows = [(u, cone if 50 <= u <= 125 else spread) for u in range(25, 801, 25)]
    assert [healthy.update(u, m) for u, m in rows] == [None] * len(rows)
    collapsed = CollapseWatch(100)
    lines = [(u, line) for u in range(25, 801, 25) if (line := collapsed.update(u, cone if u >= 50 else spread))]
    assert [u for u, _ in lines] == [50 + COLLAPSE_PERSIST_UPDATES]   # once, after it lasted
    assert "since update 50" in lines[0][1] and "cone" in lines[0][1]
    assert CollapseWatch(100).update(25, {"wm_loss": 1.0}) is None      # a variant without the module


@pytest.mark.process
def test_world_model_only_trains_no_policy_and_resumes_after_a_kill(tmp_path):
    bag = write_bag(tmp_path / "bag", make_steps(3, 20))
    run_dir = tmp_path / "killed"
    p = train_proc(tmp_path, bag, run_dir, "--updates", "1000", "--checkpoint-every", "2",
                    "--train.world_model_only")
    ck = run_dir / "checkpoints" / "latest.pt"
    wait_until(ck.exists, 240, "the first checkpoint")
    os.killpg(p.pid, signal.SIGKILL)
    p.wait(30)
    k = ckpt_counters(ck)["agent_updates"]
    assert k >= 2
    r = run_cli("trainer.learn.train", "--run-dir", run_dir, "--resume", "--updates", str(k + 3), "--logs", bag)
    assert r.returncode == 0, r.stdout + r.stderr
    assert f"resuming {run_dir} at update {k}" in r.stdout
    rows = metrics(run_dir)
    assert [m["update"] for m in rows] == list(range(1, k + 4))
    assert all("wm_loss" in m and "actor_loss" not in m and "critic_loss" not in m for m in rows)
    assert ckpt_counters(ck)["agent_updates"] == k + 3


@pytest.mark.process
def test_the_true_context_arm_reads_the_context_from_the_bag_and_refuses_a_bag_without_it(tmp_path):
    args = ("--variant", "dreamer_true_context", "--updates", "2")
    with_context = write_bag(tmp_path / "bag", make_steps(2, 20, context={"m": 1.5}))
    r = _train(tmp_path, with_context, "ceiling", *args)
    assert r.returncode == 0, r.stdout + r.stderr
    assert [m["update"] for m in metrics(tmp_path / "ceiling")] == [1, 2]

    topics = {"image": "/robot/camera", "step_info": "/robot/step", "action": "/robot/cmd"}
    without = write_rosbags_bag(tmp_path / "no_context", make_steps(2, 20), topics)
    topic_args = [x for k, t in topics.items() for x in ("--topic", f"{k}={t}")] + ["--topic", "context=none"]
    r = _train(tmp_path, without, "refused", *args, *topic_args)
    assert r.returncode == 2, r.stdout + r.stderr
    line = [x for x in r.stderr.splitlines() if "error" in x]
    assert len(line) == 1 and "no true context of pendulum_swingup (m)" in line[0] and str(without) in line[0], r.stderr

    # The variant trains its world model only by its own settings; asked for a policy, it refuses.
    r = _train(tmp_path, with_context, "no_policy", "--variant", "dreamer_true_context", "--updates", "1",
               "--train.no_world_model_only")
    assert r.returncode == 2 and "train.world_model_only=true" in r.stderr, r.stdout + r.stderr


def _eval_doc(arm: str, seed: int, mse: float, r2: float) -> dict:
    ol = {"horizons": list(range(1, 51)), "image_mse": [mse] * 50, "reward_abs_err": [0.1] * 50, "n_segments": 8}
    return {"arm": arm, "seed": seed, "updates": 10, "settings": {"variant": arm},
            "open_loop": {"test": ol, "train": ol},
            "probes": {"test_grid": {"log_m": {"h": {"r2": r2}}}}, "skipped": {}, "health": None}


def test_the_study_report_gives_each_arm_its_mean_and_t_interval_over_seeds(tmp_path):
    from trainer.study import cli as study

    for seed, (mse, r2) in enumerate([(0.010, 0.5), (0.012, 0.7), (0.014, 0.6)]):
        d = tmp_path / "grid" / "dreamer" / f"seed_{seed}"
        d.mkdir(parents=True)
        (d / "eval.json").write_text(json.dumps(_eval_doc("dreamer", seed, mse, r2)))
    out = tmp_path / "study.json"
    assert study.main(["report", "--grid", str(tmp_path / "grid"), "--json", str(out)]) == 0
    arm = json.loads(out.read_text())["arms"]["dreamer"]
    assert arm["seeds"] == [0, 1, 2]
    mse = arm["figures"]["test_image_mse_1_50"]
    # mean 0.012, SD 0.002, t(0.975, 2) = 4.303: half-width 0.002 * 4.303 / sqrt(3)
    assert mse["mean"] == pytest.approx(0.012)
    assert mse["hi"] - mse["mean"] == pytest.approx(0.002 * 4.3027 / 3 ** 0.5, rel=1e-3)
    assert arm["figures"]["r2_test_grid_log_m_h"]["mean"] == pytest.approx(0.6)
    # A second arm on the same seeds: its paired difference to Dreamer, the primary figure.
    for seed, mse in enumerate([0.009, 0.010, 0.012]):
        d = tmp_path / "grid" / "protocad_chosen" / f"seed_{seed}"
        d.mkdir(parents=True)
        (d / "eval.json").write_text(json.dumps(_eval_doc("protocad_chosen", seed, mse, 0.5)))
    assert study.main(["report", "--grid", str(tmp_path / "grid"), "--json", str(out)]) == 0
    (pair,) = json.loads(out.read_text())["paired"]
    assert pair["arm"] == "protocad_chosen" and pair["base"] == "dreamer" and pair["seeds"] == [0, 1, 2]
    assert pair["differences"] == pytest.approx([-0.001, -0.002, -0.002])
    assert pair["mean"] == pytest.approx(-0.005 / 3) and pair["verdict"] == "lower"
    assert study.main(["report", "--grid", str(tmp_path / "empty")]) == 2
    bad = tmp_path / "grid" / "dreamer" / "seed_9"
    bad.mkdir()
    (bad / "eval.json").write_text(json.dumps({"arm": "dreamer", "open_loop": []}))   # crafted, wrong shape
    assert study.main(["report", "--grid", str(tmp_path / "grid")]) == 2               # one line, no traceback


@pytest.mark.parametrize("name", ["study_ab.json", "study.json"])
def test_the_committed_study_tables_in_results_md_are_its_json_files(name):
    """results.md's tables of the world-model study are what `protocad-study report` makes of
    the committed JSON, and every arm ran every seed it names for the same updates."""
    from helpers import ROOT

    from trainer.study.report import markdown

    doc = json.loads((ROOT / "msgs_docs" / "results" / name).read_text())
    assert doc["schema"] == "protocad-study/1" and doc["task"] == "walker_walk"
    for arm in doc["arms"].values():
        assert len(arm["seeds"]) >= 3 and len(arm["updates"]) == 1 and set(arm["per_seed"]) == set(map(str, arm["seeds"]))
    page = (ROOT / "msgs_docs" / "results.md").read_text()
    assert markdown(doc["arms"]) in page
    if name == "study.json":   # the study proper: its four arms, 5 seeds each, and the primary figure
        assert set(doc["arms"]) == {"dreamer", "protocad_paper", "protocad_chosen", "true_context"}
        assert all(len(a["seeds"]) >= 5 for a in doc["arms"].values())
        (primary,) = [p for p in doc["paired"] if p["arm"] == "protocad_chosen"]
        assert f"{primary['mean']:+.5f} [95% t-interval {primary['lo']:+.5f}, {primary['hi']:+.5f}]" in page
