"""protocad-probe: the probes score what they should on windows of known content, and the
command on a tiny checkpoint writes JSON of its schema with finite R^2, open-loop errors of both
splits at every horizon, a PNG and a rerun recording of the features by context."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
from helpers.agents import tiny_checkpoint


def synthetic_windows(seed: int = 0):
    """Pendulum-like splits: 11 train and 8 test masses (two clusters), 6 windows each; feature
    `signal` = log m + noise, `noise` = noise only."""
    from trainer.research.probe_fit import Windows

    rng = np.random.default_rng(seed)
    train_m = np.linspace(0.75, 1.25, 11)
    test_m = np.array([0.2, 0.4, 0.5, 0.7, 1.3, 1.5, 1.6, 1.8])
    masses = np.concatenate([train_m, test_m])
    ctx = np.repeat(np.arange(len(masses)), 6)
    m = masses[ctx]
    signal = np.stack([np.log(m), rng.normal(size=len(m))], 1) + 0.02 * rng.normal(size=(len(m), 2))
    return Windows({"signal": signal, "noise": rng.normal(size=(len(m), 3))}, {"log_m": np.log(m)},
                   ctx, np.where(ctx < len(train_m), "train", "test"), m)


def test_probes_find_the_signal_and_not_the_noise():
    from trainer.research.probe_fit import run_probes

    probes, skipped = run_probes(synthetic_windows())
    assert set(probes) == {"test_grid", "test_light", "test_heavy", "train_to_test"} and skipped == {}
    for setting, targets in probes.items():
        sig, noise = targets["log_m"]["signal"], targets["log_m"]["noise"]
        # 2 contexts in a fold of a cluster: 6 tied targets each cap the ranks' agreement at 0.87
        assert sig["r2"] > 0.9 and sig["spearman"] > 0.85, setting
        assert noise["r2"] < 0.3, setting
        assert sig["n_windows"] == (48 if setting in ("test_grid", "train_to_test") else 24)
    # the reference that knows only light / heavy scores well on the whole grid: why the clusters
    assert probes["test_grid"]["log_m"]["mass_cluster"]["r2"] > 0.5
    assert "mass_cluster" not in probes["test_light"]["log_m"]


def test_folds_keep_each_context_whole():
    from trainer.research.probe_fit import group_folds

    groups = np.repeat(np.arange(7), 4)
    folds = group_folds(groups, 5, seed=3)
    assert len(folds) == 5 and np.array_equal(np.sum(folds, 0), np.ones(len(groups)))
    for scored in folds:
        assert all(scored[groups == g].all() or not scored[groups == g].any() for g in range(7))
    # dealt in the order of the target: each fold spans its range, so a probe that learned
    # nothing is not scored against the complement's mean (a rank correlation out of nothing)
    y = np.repeat([0.0, 0.0, 1.0, 1.0, 2.0, 2.0], 3)
    folds = group_folds(np.repeat(np.arange(6), 3), 2, y=y)
    assert [sorted(set(y[f])) for f in folds] == [[0.0, 1.0, 2.0]] * 2


def test_an_unreadable_target_gets_no_rank_correlation_from_the_folds():
    from trainer.research.probe_fit import fold_spearman, grouped_cv_predict, spearman

    rng = np.random.default_rng(1)
    groups = np.repeat(np.arange(32), 8)
    y = np.log(np.repeat(np.tile([0.2, 0.3, 0.4, 0.5, 1.5, 1.6, 1.7, 1.8], 4), 8))
    pooled, within = [], []
    for seed in range(6):
        pred, fold = grouped_cv_predict(rng.normal(size=(len(y), 8)), y, groups, seed)
        pooled.append(spearman(y, pred))
        within.append(fold_spearman(y, pred, fold))
    assert abs(np.mean(within)) < 0.1
    assert np.mean(pooled) < -0.05      # why within: pooled ranks the folds' intercepts too


def test_too_few_contexts_are_skipped_with_a_reason():
    from trainer.research.probe_fit import run_probes

    w = synthetic_windows()
    keep = np.isin(w.context, [0, 5, 10, 11, 12, 17])    # 3 train, 2 light, 1 heavy test masses
    probes, skipped = run_probes(w.select(keep))
    assert "test_heavy" not in probes and "need" in skipped["test_heavy"]["log_m"]
    assert "test_light" not in probes and "test_grid" in probes and "train_to_test" in probes


@pytest.fixture(scope="module")
def probed(tmp_path_factory):
    """The command on a tiny untrained pendulum checkpoint: 6 contexts per split, 30 steps."""
    from trainer.research import probe

    tmp = tmp_path_factory.mktemp("probe")
    ck = tiny_checkpoint(tmp / "ck.pt")
    out = {"json": tmp / "probe.json", "plot": tmp / "probe.png", "rrd": tmp / "probe.rrd"}
    rc = probe.main([str(ck), "--steps", "30", "--skip", "5", "--window", "5", "--horizon", "10",
                     "--max-contexts", "6", "--threads", "1", "--no-progress",
                     *(x for k, p in out.items() for x in (f"--{k}", str(p)))])
    assert rc == 0
    return out


def test_the_json_matches_its_schema_with_finite_scores(probed):
    import jsonschema

    from trainer.research.probe_report import PROBE_SCHEMA

    doc = json.loads(probed["json"].read_text())
    jsonschema.validate(doc, PROBE_SCHEMA)
    assert doc["task"] == "pendulum_swingup" and doc["variant"] == "protocad" and doc["updates"] == 0
    assert doc["features"] == {"u": 8, "w": 8, "e": 8, "h": 32, "pixels": 32}
    assert [c["split"] for c in doc["contexts"]] == ["train"] * 6 + ["test"] * 6
    assert all(c["windows"] == 5 for c in doc["contexts"])     # (30 - 5) // 5
    assert set(doc["probes"]) == {"test_grid", "test_light", "test_heavy", "train_to_test"}
    for setting, targets in doc["probes"].items():
        assert list(targets) == ["log_m"]                     # pendulum has no damping
        for feature, s in targets["log_m"].items():
            assert math.isfinite(s["r2"]), (setting, feature)
            assert s["spearman"] is None or -1 <= s["spearman"] <= 1
    assert set(doc["probes"]["test_grid"]["log_m"]) == {"u", "w", "e", "h", "pixels", "mass_cluster"}
    for split in ("test", "train"):
        ol = doc["open_loop"][split]
        assert ol["horizons"] == list(range(1, 11))
        assert len(ol["image_mse"]) == len(ol["reward_abs_err"]) == 10
        assert all(math.isfinite(v) and v >= 0 for v in ol["image_mse"] + ol["reward_abs_err"])
        assert ol["n_segments"] == 6 * 2                          # 30 steps: two 15-step segments
    a = doc["assignment"]
    assert a["prototypes"] == 8 and 1 / 8 <= a["top_mean"] <= 1 and 0 <= a["entropy_mean"] <= a["uniform_entropy"]
    assert a["steps"] == 12 * 25
    c = doc["prototypes"]                                       # untrained: where they started
    assert c["parameter"] == "wm.context.prototypes" and c["count"] == 8 and c["prototype_freeze"] is None
    assert c["cos_to_initial_mean"] == pytest.approx(1.0, abs=1e-5)
    h = doc["health"]                                           # the module's health on the unseen contexts
    assert h["proto_init_cosine"] == pytest.approx(1.0, abs=1e-5)
    assert 1 / 8 <= h["swav_pred_top"] <= 1 and 1 / 8 <= h["swav_target_top"] <= 1
    assert -1 <= h["proj_cosine"] <= 1 and 0 <= h["modal_share"] <= 1
    from trainer.research.probe_report import report_text
    assert "context health on the unseen contexts" in report_text(doc)   # what the command prints


def test_the_probe_tells_prototypes_that_trained_from_frozen_ones(tmp_path):
    """The cosine to the initial prototypes stays 1 inside the freeze and drops once they
    train, read back from a saved checkpoint as protocad-probe loads it (the initial values are
    redrawn from the checkpoint's config); a variant without prototypes has none."""
    from helpers.agents import TINY_OVERRIDES, render_batch

    from protocad_ros.checkpoint.agent_file import load_checkpoint, save_checkpoint
    from protocad_ros.model.agent import Agent
    from protocad_ros.model.config import make_config
    from trainer.research.probe import prototype_drift
    from trainer.research.probe_report import prototypes_line

    batch = render_batch(batch=4, length=8)
    cfg = make_config("pendulum_swingup", "small", "protocad", **TINY_OVERRIDES,
                      **{"train.seed": 3, "context.freeze_prototypes_updates": 1,
                         "world_model.lr": 0.03})   # Adam moves each value ~lr a step: make 3 steps show
    agent = Agent(cfg, 1)
    agent.train_step(batch)                                    # update 0: inside the freeze
    assert prototype_drift(agent)["cos_to_initial_mean"] == pytest.approx(1.0, abs=1e-6)
    for _ in range(3):
        agent.train_step(batch)
    save_checkpoint(tmp_path / "ck.pt", agent, {"prototype_freeze": 1})
    loaded, counters = load_checkpoint(tmp_path / "ck.pt", restore_rng=False, optimizer_states=False)
    moved = prototype_drift(loaded, counters["prototype_freeze"])
    assert moved["cos_to_initial_min"] <= moved["cos_to_initial_mean"] < 0.999
    assert moved["cos_to_initial_mean"] == pytest.approx(prototype_drift(agent)["cos_to_initial_mean"], abs=1e-6)
    assert "frozen for the first 1 of its 4 updates" in prototypes_line(moved, 4)
    # a run that started from a policy file (--init-policy) started from that file's
    # prototypes: measured from it, the file named by its content, said in the line
    assert prototype_drift(loaded, 1, tmp_path / "ck.pt")["cos_to_initial_mean"] == pytest.approx(1.0, abs=1e-6)
    fresh = Agent(cfg, 1)                                      # the seeded draw, untrained
    from_policy = prototype_drift(fresh, None, tmp_path / "ck.pt")
    assert from_policy["cos_to_initial_mean"] == pytest.approx(moved["cos_to_initial_mean"], abs=1e-6)
    assert from_policy["start"]["policy"] == str(tmp_path / "ck.pt") and len(from_policy["start"]["sha256"]) == 64
    assert "those of ck.pt, where the run started" in prototypes_line(from_policy, 4)
    dreamer = Agent(make_config("pendulum_swingup", "small", "dreamer", **TINY_OVERRIDES), 1)
    assert prototype_drift(dreamer) is None
    save_checkpoint(tmp_path / "dreamer.pt", dreamer, {})   # not where a ProtoCAD run started: one clear error
    with pytest.raises(ValueError, match="prototypes is missing: not the policy this run started from"):
        prototype_drift(loaded, 1, tmp_path / "dreamer.pt")
    # a shipped policy file has no counters of its own: the run's come from its provenance
    from protocad_ros.checkpoint.agent_file import save_policy
    from trainer.research.probe import load

    save_policy(tmp_path / "policy.pt", agent, {"counters": {"prototype_freeze": 1, "env_steps": 40}})
    _, counters, _ = load(str(tmp_path / "policy.pt"), "cpu")
    assert counters["prototype_freeze"] == 1 and counters["env_steps"] == 40
    # provenance is the file's word: counters that are no numbers are left out, not trusted
    save_policy(tmp_path / "odd.pt", agent, {"counters": {"prototype_freeze": "many", "env_steps": 40}})
    assert load(str(tmp_path / "odd.pt"), "cpu")[1] == {"env_steps": 40}
    save_policy(tmp_path / "odd.pt", agent, {"counters": ["not", "a", "mapping"]})
    assert load(str(tmp_path / "odd.pt"), "cpu")[1] == {}


def test_the_plot_and_the_recording_are_written(probed):
    from trainer.viz.rerun_log import read_recording

    assert probed["plot"].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    rec = read_recording(probed["rrd"])
    for feature in ("u", "w", "e", "h", "pixels"):
        assert rec[f"/probe/{feature}/pca2d/test"]["rows"] >= 1
        assert rec[f"/probe/{feature}/pca2d/contexts"]["rows"] >= 1
    assert "horizon" in rec["/open_loop/test/image_mse"]["timelines"]
    assert rec["__blueprints"]["rows"] >= 1          # its layout travels with it


def test_probes_of_several_seeds_summarize_per_variant(probed, tmp_path, capsys):
    """--summarize: a grid's probe JSONs together, per variant the mean R^2 over its checkpoints
    with their range, and the open-loop errors averaged; a file that is not a probe JSON is one
    error line."""
    from trainer.research import probe

    doc = json.loads(probed["json"].read_text())
    better = json.loads(json.dumps(doc))
    for targets in better["probes"].values():
        for scores in targets.values():
            for score in scores.values():
                score["r2"] += 0.2
    better["open_loop"]["test"]["reward_abs_err"] = [2 * x for x in doc["open_loop"]["test"]["reward_abs_err"]]
    other = {**doc, "variant": "dreamer"}
    paths = []
    for name, d in (("a", doc), ("b", better), ("c", other)):
        paths.append(tmp_path / f"{name}.json")
        paths[-1].write_text(json.dumps(d))
    assert probe.main(["--summarize", *map(str, paths)]) == 0
    text = capsys.readouterr().out
    r = doc["probes"]["test_grid"]["log_m"]["u"]["r2"]
    mine = text[text.index("| log_m: protocad (2) |"):]
    row = next(line for line in mine.splitlines() if line.startswith("| test_grid |"))
    assert row.split(" | ")[1] == f"{np.mean([r, r + 0.2]):.2f} ({r:.2f} to {r + 0.2:.2f})", row
    theirs = text[text.index("| log_m: dreamer (1) |"):]
    assert next(x for x in theirs.splitlines() if x.startswith("| test_grid |")).split(" | ")[1] == f"{r:.2f}"
    e = doc["open_loop"]["test"]["reward_abs_err"][0]
    loop = next(x for x in text.splitlines() if x.startswith("| protocad (2) | test |"))
    assert loop.split(" | ")[2].endswith(f"/ {1.5 * e:.3f}"), loop
    protos = next(x for x in text.splitlines() if x.startswith("| protocad (2) |") and "/" not in x)
    assert protos.split(" | ")[1] == "1.000 (1.000 to 1.000)", protos   # untrained: at their initial values
    (tmp_path / "bad.json").write_text(json.dumps({"schema": "protocad-probe/1"}))
    assert probe.main(["--summarize", str(paths[0]), str(tmp_path / "bad.json")]) == 2
    assert "bad.json" in capsys.readouterr().err


def test_help_and_bad_input(capsys, tmp_path):
    from trainer.research import probe

    with pytest.raises(SystemExit) as exit_:
        probe.main(["--help"])
    assert exit_.value.code == 0
    text = capsys.readouterr().out
    assert "protocad-probe" in text and "--horizon" in text and "--max-contexts" in text
    assert probe.main([str(tmp_path / "nothing.pt")]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert probe.main([str(tmp_path / "nothing.pt"), "--steps", "20"]) == 2
    assert "leaves no window" in capsys.readouterr().err
    assert probe.main([str(tmp_path / "nothing.pt"), "--steps", "40", "--skip", "0", "--window", "10"]) == 2
    assert "leaves no open-loop segment" in capsys.readouterr().err


def test_the_committed_probe_of_the_shipped_policy_matches_its_schema_and_results_md():
    from helpers import ROOT

    from trainer.research.probe_report import read_json

    doc = read_json(ROOT / "msgs_docs" / "results" / "walker_shipped_probe.json")   # checked as any probe is read
    u = doc["probes"]["test_grid"]["log_m"]["u"]
    row = f"| log m, within the unseen grid | {u['r2']:.2f} ({u['spearman']:.2f}) |"
    assert row in (ROOT / "msgs_docs" / "results.md").read_text()


@pytest.mark.parametrize("variant", ["dreamer", "dreamerpro"])
def test_variants_without_context_features_get_h_and_the_floor(variant):
    from helpers.agents import TINY_OVERRIDES

    from protocad_ros.model.agent import Agent
    from protocad_ros.model.config import make_config
    from trainer.research.probe_collect import Plan, feature_windows, open_loop_errors, pixel_projection

    agent = Agent(make_config("pendulum_swingup", "small", variant, **TINY_OVERRIDES), 1)
    rng = np.random.default_rng(0)
    B, T = 2, 20
    batch = {"image": rng.integers(0, 256, (B, T, 64, 64, 3), dtype=np.uint8),
             "action": rng.uniform(-1, 1, (B, T, 1)).astype(np.float32), "reward": np.zeros((B, T), np.float32),
             "discount": np.ones((B, T), np.float32), "is_first": np.eye(1, T, dtype=bool).repeat(B, 0)}
    plan = Plan(steps=T, skip=4, window=4, horizon=5, pixel_dim=6)
    windows, w = feature_windows(agent, batch, pixel_projection(6, 0), plan)
    assert w is None and [sorted(x) for x in windows] == [["h", "pixels"]] * B
    assert windows[0]["h"].shape == (4, 32) and windows[0]["pixels"].shape == (4, 6)
    image, reward = open_loop_errors(agent, batch, plan)
    assert reward.shape == (B * 2, 5)                     # two 10-step segments per episode
    assert (image is None) == (variant == "dreamerpro")   # DreamerPro has no decoder


def test_a_probe_json_written_before_the_freeze_had_one_name_reads_as_prototype_freeze():
    """The committed probes (msgs_docs/results/walker_paired_probes) say `frozen_updates`; read
    back they say `prototype_freeze`, as run.json and results.json do, and still validate."""
    from helpers import ROOT

    from trainer.research import probe_report

    old = ROOT / "msgs_docs" / "results" / "walker_paired_probes" / "protocad_seed0.json"
    assert "frozen_updates" in json.loads(old.read_text())["prototypes"]
    doc = probe_report.read_json(old)
    assert doc["prototypes"]["prototype_freeze"] == 290 and "frozen_updates" not in doc["prototypes"]
    assert "frozen for the first 290" in probe_report.report_text(doc)
