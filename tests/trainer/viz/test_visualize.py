"""Rerun views of the latent contexts (trainer/viz/visualize.py, trainer/viz/rerun_log.py).

Real parts throughout: a real (tiny, random-weight) ProtoCAD agent, episodes rendered by the
context-randomized DMC envs, a real MCAP bag, and the produced .rrd files read back with
rerun's own reader (rerun.chunk.RrdReader) and `rerun rrd verify` / `rerun mcap convert`.
"""
from __future__ import annotations

import os
import subprocess
import sys

import helpers
import numpy as np
import pytest

from sim_bridge.contract.contexts import get_task
from trainer.viz import visualize as V
from trainer.viz.rerun_log import TrainingRecorder, normalize_eval, read_recording

ROOT = str(helpers.ROOT)
K = 6  # configured number of prototypes of the tiny agents (the paper's is 50/100)


def tiny_agent(task: str, action_dim: int, variant: str = "protocad"):
    import torch

    from protocad_ros.model.agent import Agent
    from protocad_ros.model.config import make_config

    torch.set_num_threads(1)
    cfg = make_config(task, "small", variant, **{
        "world_model.deter": 32, "world_model.hidden": 32, "world_model.stoch": 8,
        "world_model.cnn_depth": 4, "world_model.mlp_units": 32, "behavior.actor_units": 32,
        "behavior.critic_units": 32, "context.num_prototypes": K, "context.proto_dim": 8})
    return Agent(cfg, action_dim)


@pytest.fixture(scope="module")
def pendulum_agent():
    return tiny_agent("pendulum_swingup", 1)


def _rerun(tmp_path, *args, timeout=60):
    cfg = tmp_path / "xdg" / "rerun"   # private rerun config: analytics off
    cfg.mkdir(parents=True, exist_ok=True)
    (cfg / "analytics.json").write_text('{"analytics_enabled": false}')
    exe = os.path.join(os.path.dirname(sys.executable), "rerun")
    return subprocess.run([exe, *args], capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, "XDG_CONFIG_HOME": str(tmp_path / "xdg")})


def _n_points(rec, path):
    cols = rec[path]["columns"]
    key = next(k for k in cols if k.endswith(":positions"))
    return len(cols[key][-1])


def _all_contexts(task):
    spec = get_task(task)
    return {V.context_label(c, s) for s in ("train", "test") for c in spec.contexts(s)}


def _check_context_view(rec, task, method="pca", params=("m",)):
    """Every documented entity of the context view, every context of both splits, K prototypes."""
    want = _all_contexts(task)
    assert "/embeddings" in rec and "/embeddings/legend" in rec
    for feature in V.FEATURES:
        for dim in (2, 3):
            space = f"/embeddings/{feature}/{method}{dim}d"
            for leaf in ["by_split", "contexts"] + [f"by_{p}" for p in params]:
                assert f"{space}/{leaf}" in rec, f"{space}/{leaf} missing"
            labels = rec[f"{space}/contexts"]["columns"]
            labels = labels[next(k for k in labels if k.endswith(":labels"))][-1]
            assert set(labels) == want, f"{space}: contexts {sorted(want - set(labels))} missing"
            assert _n_points(rec, f"{space}/contexts") == len(want)
            ids = rec[f"{space}/by_split"]["columns"]
            ids = ids[next(k for k in ids if k.endswith(":class_ids"))][-1]
            assert set(ids) == {0, 1}   # train and test points
            if feature in V.PROTOTYPE_FEATURES:
                assert _n_points(rec, f"{space}/prototypes") == K
            else:
                assert f"{space}/prototypes" not in rec   # RSSM state: no prototypes there
    tensor = rec["/assignment/by_context"]["columns"]["Tensor:data"][-1][0]
    assert tensor["shape"] == [len(want), K]
    for i in range(len(want)):
        assert f"/episodes/{i}/assignment" in rec and f"/episodes/{i}/top_prototype" in rec
    assert rec["__blueprints"]["rows"] >= 1


@pytest.mark.process
def test_context_recording_covers_every_context_of_both_splits(tmp_path, pendulum_agent):
    """Collected in-process with the agent's own policy: one episode per context (11 + 8)."""
    out = tmp_path / "ctx.rrd"
    png = tmp_path / "ctx.png"
    res = V.write_context_recording(pendulum_agent, out_rrd=out, task="pendulum_swingup",
                                    steps_per_context=8, skip_steps=2, context_steps=3,
                                    horizon=6, png=png, progress=False)
    assert res.path == out and out.stat().st_size > 0
    rec = read_recording(out)
    _check_context_view(rec, "pendulum_swingup")
    # observations beside reconstructions, open loop (3 context + 6 predicted frames)
    for p in ("/reconstruction/truth", "/reconstruction/model", "/reconstruction/mse",
              "/open_loop/truth", "/open_loop/prediction", "/open_loop/mse", "/open_loop/montage"):
        assert p in rec, p
    assert rec["/reconstruction/truth"]["rows"] == rec["/reconstruction/model"]["rows"] == 8
    assert "step" in rec["/open_loop/prediction"]["timelines"]
    assert rec["/open_loop/truth"]["rows"] == 9 and rec["/open_loop/mse"]["rows"] == 6
    fmt = rec["/open_loop/prediction"]["columns"]["Image:format"][0][0]
    n_shown = len(res.open_loop_episodes)
    assert n_shown == 4 and fmt["height"] == 64 and fmt["width"] == 64 * n_shown + 2 * (n_shown - 1)
    # the PNG is a real image of the same projection
    from PIL import Image

    with Image.open(png) as im:
        assert im.size[0] > 600 and im.size[1] > 600
        # the prototypes are drawn (red crosses) in the panels, above the legend rows
        panels = np.asarray(im.convert("RGB"))[:-60].reshape(-1, 3)
        cross = np.array(V.CLASS_COLORS[V.PROTOTYPE_CLASS], np.uint8)
        assert (panels == cross).all(axis=1).sum() > 100
    verify = _rerun(tmp_path, "rrd", "verify", str(out))
    assert verify.returncode == 0, verify.stderr


def test_cheetah_md_grid_every_context_colour_per_parameter(tmp_path):
    """(m, d) grid: 25 train + 64 test contexts, one point colouring per parameter."""
    agent = tiny_agent("cheetah_run", 6)
    eps = V.collect_context_episodes("cheetah_run", agent, steps=3, random_policy=True,
                                     progress=False)
    assert len(eps) == 25 + 64
    out = tmp_path / "cheetah.rrd"
    V.write_context_recording(agent, episodes=eps, out_rrd=out, skip_steps=1, horizon=0,
                              num_prediction_episodes=2)
    rec = read_recording(out)
    _check_context_view(rec, "cheetah_run", params=("m", "d"))
    colors = rec["/embeddings/u_e/pca3d/by_d"]["columns"]["Points3D:colors"][-1]
    assert len(set(colors)) > 5   # a colour scale, not one colour


def _write_bag(bag_dir, episodes):
    """A rosbag2/MCAP bag with the topic contract's messages (as the recorder writes them)."""
    from sim_bridge.contract import topics as T
    from trainer.bag.rosmsg import new_message
    from trainer.bag.writer import BagWriter

    ns = T.DEFAULT_NAMESPACE
    with BagWriter(bag_dir) as w:
        for rel in (T.IMAGE, T.STEP_INFO, T.ACTION, T.CONTEXT):
            w.add_topic(T.topic_name(ns, rel), T.TYPES[rel])
        t = 0
        for ep_id, ep in enumerate(episodes):
            for i in range(len(ep)):
                t += 20_000_000
                for rel, fill, args in (
                        (T.IMAGE, T.fill_image, (ep.image[i],)),
                        (T.STEP_INFO, T.fill_step_info, (T.StepInfo(
                            float(ep.reward[i]), 1.0, i == 0, i == len(ep) - 1, False, ep_id, i),)),
                        (T.CONTEXT, T.fill_context, (ep.context, ep.split)),
                        (T.ACTION, T.fill_action, (ep.action[i + 1] if i + 1 < len(ep)
                                                   else np.zeros(1), ["a0"]))):
                    msg = new_message(T.TYPES[rel])
                    fill(msg, *args, t)
                    w.write_message(T.topic_name(ns, rel), msg, t)
    return sorted(bag_dir.glob("*.mcap"))


@pytest.mark.process
def test_mcap_logs_view_and_rerun_reads_the_mcap(tmp_path, pendulum_agent):
    contexts = {"train": [{"m": 0.75}, {"m": 1.25}], "test": [{"m": 0.2}]}
    eps = V.collect_context_episodes("pendulum_swingup", None, steps=10, contexts=contexts,
                                     progress=False)
    files = _write_bag(tmp_path / "bag", eps)
    # rerun reads the MCAP itself: images become an Image entity (what `rerun LOG.mcap` shows)
    info = _rerun(tmp_path, "mcap", "info", str(files[0]))
    assert info.returncode == 0 and "/protocad/image" in info.stdout, info.stdout + info.stderr
    conv = _rerun(tmp_path, "mcap", "convert", str(files[0]), "-o", str(tmp_path / "bag.rrd"))
    assert conv.returncode == 0, conv.stderr
    bag_rec = read_recording(tmp_path / "bag.rrd")
    assert len(bag_rec["/protocad/image"]["columns"]["Image:buffer"]) == 30
    # the context view from the logs (read with trainer.data.dataset)
    logged = V.load_log_episodes([tmp_path / "bag"])
    assert [(e.split, e.context) for e in logged] == [(e.split, e.context) for e in eps]
    np.testing.assert_array_equal(logged[0].image, eps[0].image)
    np.testing.assert_allclose(logged[1].action, eps[1].action, atol=1e-6)
    only = tmp_path / "logs_only.rrd"
    V.write_context_recording(pendulum_agent, logs=[tmp_path / "bag"], out_rrd=only,
                              context_steps=2, horizon=5, skip_steps=2, cover_all_contexts=False)
    rec = read_recording(only)
    labels = rec["/embeddings/u_e/pca3d/contexts"]["columns"]["Points3D:labels"][-1]
    assert labels == ["train m=0.75", "train m=1.25", "test m=0.2"]
    assert rec["/open_loop/truth"]["rows"] == 7
    # by default the contexts the logs lack are collected: every context of both splits shows
    out = tmp_path / "logs.rrd"
    res = V.write_context_recording(pendulum_agent, logs=[tmp_path / "bag"], out_rrd=out,
                                    steps_per_context=4, horizon=0, skip_steps=1)
    assert [e.source for e in res.view.episodes[:3]] == [str(tmp_path / "bag")] * 3
    assert {e.source for e in res.view.episodes[3:]} == {"collected"}
    _check_context_view(read_recording(out), "pendulum_swingup")


def test_tsne_projection_keeps_prototypes_in_the_same_space(tmp_path, pendulum_agent):
    eps = V.collect_context_episodes("pendulum_swingup", None, steps=5, progress=False)
    out = tmp_path / "tsne.rrd"
    res = V.write_context_recording(pendulum_agent, episodes=eps, out_rrd=out, projection="tsne",
                                    skip_steps=2, horizon=0)
    rec = read_recording(out)
    _check_context_view(rec, "pendulum_swingup", method="tsne")
    assert res.view.method == "tsne"


def test_bad_input_is_a_clear_error(tmp_path, pendulum_agent):
    eps = V.collect_context_episodes("pendulum_swingup", None, steps=3, progress=False,
                                     contexts={"train": [{"m": 1.0}], "test": []})
    with pytest.raises(ValueError, match="projection"):
        V.write_context_recording(pendulum_agent, episodes=eps, out_rrd=tmp_path / "a.rrd",
                                  projection="umap")
    with pytest.raises(ValueError, match=r"\.rrd"):
        V.write_context_recording(pendulum_agent, episodes=eps, out_rrd=tmp_path / "a.txt",
                                  horizon=0)
    with pytest.raises(ValueError, match="context"):
        V.Episode.from_any({"image": eps[0].image, "action": eps[0].action})
    with pytest.raises(ValueError, match="uint8"):
        V.Episode(image=eps[0].image.astype(np.float32), action=eps[0].action,
                  context={"m": 1.0}, split="train")
    with pytest.raises(ValueError, match="split"):
        V.Episode(image=eps[0].image, action=eps[0].action, context={"m": 1.0}, split="val")
    with pytest.raises(ValueError, match="no episodes"):
        V.write_context_recording(pendulum_agent, episodes=[], out_rrd=tmp_path / "b.rrd")
    with pytest.raises(ValueError, match="unknown task"):
        V.collect_context_episodes("cartpole_swingup", None, steps=3)


@pytest.mark.process
def test_cli_writes_the_run_dirs_recording(tmp_path, pendulum_agent):
    from protocad_ros.checkpoint.agent_file import save_checkpoint

    ckpt = save_checkpoint(tmp_path / "run" / "checkpoints" / "latest.pt", pendulum_agent,
                           {"updates": 0})
    env = {**os.environ, "PYTHONPATH": ROOT}
    cmd = [sys.executable, "-m", "trainer.viz.visualize", "--checkpoint", str(tmp_path / "run"),
           "--steps-per-context", "3", "--skip-steps", "1", "--horizon", "0",
           "--png", str(tmp_path / "ctx.png"), "--no-progress"]
    out = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stdout + out.stderr
    rrd = tmp_path / "run" / "contexts.rrd"
    assert f"wrote {rrd}" in out.stdout and f"rerun {rrd}" in out.stdout
    assert "19 episodes of 11 train and 8 test contexts" in out.stdout
    _check_context_view(read_recording(rrd), "pendulum_swingup")
    assert (tmp_path / "ctx.png").stat().st_size > 0
    assert ckpt.exists()
    # errors: one clear line and a non-zero exit (SystemExit with the message)
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(SystemExit, match="cannot load"):
        V.main(["--checkpoint", str(bad)])
    with pytest.raises(SystemExit, match="does not exist"):
        V.main(["--checkpoint", str(tmp_path / "missing.pt")])
    with pytest.raises(SystemExit, match="unknown task"):
        V.main(["--checkpoint", str(ckpt), "--task", "cartpole_swingup"])
    helped = subprocess.run([sys.executable, "-m", "trainer.viz.visualize", "--help"], cwd=ROOT,
                            env=env, capture_output=True, text=True, timeout=60)
    assert helped.returncode == 0 and "--projection" in helped.stdout


def test_training_recorder_series_on_the_update_timeline(tmp_path, pendulum_agent):
    path = tmp_path / "metrics.rrd"
    rec = TrainingRecorder(path, config=pendulum_agent.cfg)
    for u in range(5):
        rec(u * 10, {"update": u * 10, "model_loss": 1.0 / (u + 1), "wm.kl": 2.0,
                     "note": "text is skipped", "time": 123.0})
    rows = rec.log_eval(40, [
        {"context": {"m": 0.2}, "split": "test", "returns": [100.0, 200.0]},
        {"context": {"m": 1.8}, "split": "test", "return": 50.0},
        {"context": {"m": 1.0}, "split": "train", "mean_return": 400.0}])
    assert ("test", "m0.2", 150.0) in rows
    rec.log_eval(50, {"test m=0.2": 160.0, "test/m1.8": [60.0], "train m=1": 410.0})
    from trainer.learn.evaluate import ContextResult, EvalResult  # what evaluate_checkpoint returns

    res = EvalResult("pendulum_swingup", "test", "x", [ContextResult({"m": 0.4}, "test", [1.0, 3.0])])
    assert rec.log_eval(60, res) == [("test", "m0.4", 2.0)]
    eps = V.collect_context_episodes("pendulum_swingup", None, steps=4, progress=False)
    view = rec.log_context_view(50, pendulum_agent, eps, skip_steps=1, horizon=0)
    rec.close()
    assert view.num_prototypes == K

    r = read_recording(path)
    loss = r["/train/model_loss"]
    assert loss["rows"] == 5 and "update" in loss["timelines"]
    assert sorted(loss["columns"]["update"]) == [0, 10, 20, 30, 40]
    assert "/train/wm/kl" in r and "/train/note" not in r and "/train/time" not in r
    assert "/train/config" in r
    ret = r["/eval/test/m0.2/return"]
    assert sorted(ret["columns"]["update"]) == [40, 50]
    assert sorted(v[0] for v in ret["columns"]["Scalars:scalars"]) == [150.0, 160.0]
    assert "/eval/test/m1.8/return" in r and "/eval/train/m1/return" in r
    cols = r["/eval/test/mean_return"]["columns"]
    means = sorted(zip(cols["update"], (v[0] for v in cols["Scalars:scalars"])))
    assert means == [(40, 100.0), (50, 110.0), (60, 2.0)]
    assert r["/eval/test/m0.4/return"]["columns"]["update"] == [60]
    assert "/eval/test/median_return" in r
    # the context view, on the same 'update' timeline
    ctx = r["/embeddings/u_e/pca3d/contexts"]
    assert ctx["columns"]["update"] == [50] and _n_points(r, "/embeddings/u_e/pca3d/prototypes") == K
    assert r["__blueprints"]["rows"] >= 1
    with pytest.raises(ValueError, match="context"):
        normalize_eval([{"split": "test", "return": 1.0}])


def test_metrics_callback_is_the_training_recorder(tmp_path):
    from trainer.metrics_log import MetricsLogger
    from trainer.viz.rerun_log import metrics_callback

    assert metrics_callback(None) is None
    cb = metrics_callback(tmp_path / "run" / "metrics.rrd")
    assert isinstance(cb, TrainingRecorder)
    logger = MetricsLogger(tmp_path / "run" / "metrics.jsonl", callbacks=[cb])
    for u in range(3):
        logger.log(u, {"actor_loss": float(u), "bad": float("nan")})
    logger.close()
    cb.close()
    r = read_recording(tmp_path / "run" / "metrics.rrd")
    assert r["/train/actor_loss"]["rows"] == 3
    assert sorted(r["/train/actor_loss"]["columns"]["update"]) == [0, 1, 2]


def test_the_contexts_a_run_lacks_can_be_a_stratified_few_per_split():
    """The loop's recording collects what its bags lack: for the demo the final evaluation's
    8 contexts per split, not walker's 25 + 64 (each an env built and run in-process)."""
    from types import SimpleNamespace

    from trainer.viz.context_episodes import missing_contexts

    spec = get_task("walker_walk")
    full = missing_contexts("walker_walk", [])
    assert (len(full["train"]), len(full["test"])) == (25, 64)
    seen = SimpleNamespace(split="train", context=spec.stratified("train", 8)[0])
    few = missing_contexts("walker_walk", [seen], max_contexts=8)
    assert few["test"] == spec.stratified("test", 8)
    assert few["train"] == spec.stratified("train", 8)[1:]   # the one the bags have is left out
