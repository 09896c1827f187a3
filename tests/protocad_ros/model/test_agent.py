"""ProtoCAD agent: config tree, world-model learning on real rendered frames (every variant),
gradient routing between world model / context module / actor / critic, and the Policy API.

Sizes are the 'small' preset shrunk further so the whole file runs in well under a minute on
one core. Frames are real MuJoCo renders (pendulum swingup, EGL) from sim_bridge.sim.envs.
"""
from __future__ import annotations

import dataclasses
import functools

import numpy as np
import pytest
import torch
from helpers.agents import render_batch

from protocad_ros.model.agent import Agent
from protocad_ros.model.config import Config, ConfigError, make_config
from protocad_ros.model.hyperparameters import VARIANT_TABLE, WORLD_MODEL_VARIANTS
from protocad_ros.policy import ContextFeatures, Policy
from protocad_ros.policy import Policy as _Policy

#: The world-model variants with a policy (the true-context ceiling trains its world model only).
ACTING = [v for v in WORLD_MODEL_VARIANTS if not VARIANT_TABLE[v].reads_true_context]

B, T = 4, 16  # 4 real sequences of 16 agent steps


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def tiny(variant: str = "protocad", **kw) -> Config:
    over = {
        "world_model.deter": 32, "world_model.hidden": 32, "world_model.stoch": 8,
        "world_model.cnn_depth": 8, "world_model.mlp_layers": 1, "world_model.mlp_units": 32,
        "behavior.actor_layers": 1, "behavior.actor_units": 32, "behavior.critic_layers": 1,
        "behavior.critic_units": 32, "behavior.horizon": 5, "train.batch_size": B,
        "train.seq_len": T, "context.num_prototypes": 16, "context.dreamerpro_num_prototypes": 16,
    }
    over.update(kw)
    return make_config("pendulum_swingup", "small", variant, **over)


@pytest.fixture(scope="module")
def real_batch():
    batch = render_batch(batch=B, length=T)
    assert batch["image"].std() > 5  # real pixels, not a blank buffer
    return batch


# ---- config ---------------------------------------------------------------------------------------
def test_config_defaults_are_the_paper_tables():
    cfg = make_config("cheetah_run", reference="paper")
    tr, bh, wm, ctx = cfg.train, cfg.behavior, cfg.world_model, cfg.context
    # Paper Table `hyperpara`
    assert (tr.batch_size, tr.seq_len, tr.action_repeat) == (16, 50, 2)
    assert (tr.prefill_episodes, tr.collect_interval) == (2, 100)
    assert (bh.discount, bh.horizon, bh.actor_lr, bh.critic_lr) == (0.99, 15, 8e-5, 8e-5)
    assert wm.lr == 3e-4
    assert (ctx.proto_dim, ctx.temperature, ctx.sinkhorn_iters, ctx.sinkhorn_eps, ctx.ema) == \
        (32, 0.1, 3, 0.05, 0.05)
    # DreamerPro dmc config
    assert (wm.deter, wm.hidden, wm.stoch, wm.discrete, wm.cnn_depth) == (200, 200, 32, 0, 48)
    assert (wm.kl_balance, wm.kl_free) == (0.8, 1.0)
    # DreamerPro's 10,000 of its ~100k updates, as a share of the run (-1 = auto)
    assert (ctx.freeze_prototypes_updates, ctx.freeze_prototypes_fraction) == (-1, 0.1)
    assert (bh.actor_grad, bh.actor_entropy, bh.slow_critic_update, bh.lambda_) == \
        ("dynamics", 1e-4, 100, 0.95)
    assert wm.discount_head is False
    # The default context settings are the world-model study's pick (results.md, issue 51);
    # everything else is the paper's, as reference=paper has it.
    default = make_config("cheetah_run")
    assert (default.context.sinkhorn_eps, default.context.projector_input, default.context.sinkhorn_over,
            default.context.cross_view_scale, default.context.both_views_train) == (0.0125, "h", "half_means", 1.0, True)
    assert default.world_model == wm and default.behavior == bh and default.train == tr


def test_num_prototypes_per_task():
    assert make_config("hopper_hop").context.num_prototypes == 50
    assert make_config("walker_run").context.num_prototypes == 50
    assert make_config("walker_walk").context.num_prototypes == 100
    with pytest.raises(ConfigError, match="unknown task"):
        make_config("cartpole_balance")


def test_config_overrides_unknown_keys_and_yaml_roundtrip(tmp_path):
    cfg = make_config("pendulum_swingup", "small", "dreamer", **{"train.batch_size": 8,
                                                                 "world_model.kl_free": 0.5})
    assert cfg.train.batch_size == 8 and cfg.world_model.kl_free == 0.5
    assert cfg.world_model.deter == 128  # small preset
    with pytest.raises(ConfigError, match="train.batchsize"):
        make_config(**{"train.batchsize": 8})
    with pytest.raises(ConfigError, match="expects int"):
        make_config(**{"train.batch_size": "many"})
    with pytest.raises(ConfigError, match="unknown variant"):
        make_config(variant="dreamerv9")
    path = cfg.save(tmp_path / "config.yaml")
    back = Config.load(path)
    assert back == cfg
    d = cfg.to_dict()
    d["world_model"]["deterministic"] = 3
    with pytest.raises(ConfigError, match="deterministic"):
        Config.from_dict(d)
    assert cfg.replace(**{"behavior.horizon": 3}).behavior.horizon == 3


@pytest.mark.parametrize("variant,parts", [("protocad", "sue"), ("dreamer", "s"),
                                           ("dreamerpro", "s"), ("dreamer_context", "su"),
                                           ("no_projection", "se"),
                                           ("no_temporal_consistency", "sue")])
def test_variant_features_and_modules(variant, parts):
    agent = Agent(tiny(variant), action_dim=1)
    S, D = agent.wm.state_dim, agent.cfg.context.proto_dim
    assert S == 8 + 32
    assert agent.wm.feat_dim == S + D * (len(parts) - 1)
    assert (agent.wm.context is not None) == (variant not in ("dreamer", "dreamerpro"))
    assert agent.has_decoder == (variant != "dreamerpro")
    if agent.wm.context is not None:
        assert agent.wm.context.temporal_consistency == (variant != "no_temporal_consistency")
    protos = agent.prototypes()
    assert (protos is None) == (variant == "dreamer")
    if protos is not None:
        assert torch.allclose(protos.norm(dim=-1), torch.ones(len(protos)), atol=1e-5)


# ---- learning on real frames -------------------------------------------------------------------
@pytest.mark.parametrize("variant", ACTING)
def test_world_model_loss_decreases_on_real_frames(real_batch, variant):
    torch.manual_seed(0)
    agent = Agent(tiny(variant, **{"world_model.lr": 1e-3}), action_dim=1)
    losses = []
    for _ in range(24):
        m = agent.train_step(real_batch)
        assert all(np.isfinite(v) for v in m.values()), m
        losses.append(m["wm_loss"])
    first, last = np.mean(losses[:3]), np.mean(losses[-3:])
    assert last < 0.85 * first, (variant, losses)
    assert m["updates"] == 24 and int(agent.updates) == 24
    for key in ("kl", "reward_loss", "actor_loss", "critic_loss", "entropy", "wm_grad_norm"):
        assert key in m
    if variant != "dreamer":
        assert "swav_loss" in m
    if variant != "dreamerpro":
        assert "image_loss" in m


def test_the_true_context_world_model_learns_from_the_context_and_refuses_to_act(real_batch):
    torch.manual_seed(0)
    agent = Agent(tiny("dreamer_true_context", **{"world_model.lr": 1e-3, "train.world_model_only": True}),
                  action_dim=1)
    B, T = real_batch["image"].shape[:2]
    batch = {**real_batch, "context": np.full((B, T, 1), 0.5, np.float32)}
    losses = [agent.train_step(batch)["wm_loss"] for _ in range(24)]
    assert np.mean(losses[-3:]) < 0.85 * np.mean(losses[:3])
    assert agent.wm.rssm.action_dim == 2 and agent.wm.feat_dim == agent.wm.state_dim + 1
    out = agent.open_loop(batch, context_steps=2, horizon=3)
    assert out["prediction"].shape[1] == 3
    with pytest.raises(ValueError, match="true context"):
        agent.train_step(real_batch)            # the context is its input: no batch without it
    with pytest.raises(ValueError, match="does not act"):
        agent.observe_step(None, torch.as_tensor(real_batch["image"][:, 0]), torch.zeros(B, 1),
                           torch.ones(B, dtype=torch.bool))


def test_discrete_latents_layernorm_and_bf16_run(real_batch):
    cfg = tiny("protocad", **{"world_model.discrete": 4, "world_model.cnn": "dreamerv3",
                              "world_model.norm": "layer", "behavior.norm": "layer",
                              "world_model.act": "silu", "train.precision": "bfloat16"})
    agent = Agent(cfg, action_dim=1)
    agent.use_precision("bfloat16")   # as --precision asks: the bf16 path also where it is emulated
    assert agent.wm.state_dim == 8 * 4 + 32
    for _ in range(2):
        m = agent.train_step(real_batch)
    assert all(np.isfinite(v) for v in m.values())
    post_stoch = agent.embed_sequences(real_batch)["s"][..., :32]
    # straight-through one-hot samples: (posterior mode) each group of 4 sums to one
    assert np.allclose(post_stoch.reshape(B, T, 8, 4).sum(-1), 1.0, atol=1e-2)


# ---- gradient routing ------------------------------------------------------------------------------
def _params(module):
    return {n: p.detach().clone() for n, p in module.named_parameters()}


def _changed(before, module):
    return [n for n, p in module.named_parameters() if not torch.equal(before[n], p.detach())]


def test_behavior_update_never_touches_world_model(real_batch):
    agent = Agent(tiny("protocad"), action_dim=1)
    start, _ = agent.train_world_model(real_batch)
    wm_before, actor_before = _params(agent.wm), _params(agent.ac.actor)
    critic_before = _params(agent.ac.critic)
    agent.train_behavior(start)
    assert _changed(wm_before, agent.wm) == []  # incl. projector and prototypes
    assert all(p.grad is None for p in agent.wm.parameters())
    assert len(_changed(actor_before, agent.ac.actor)) > 0
    assert len(_changed(critic_before, agent.ac.critic)) > 0
    assert all(p.requires_grad for n, p in agent.wm.named_parameters()
               if "target_projector" not in n)  # frozen() restored the flags


def _grads(loss, params):
    gs = torch.autograd.grad(loss, params, retain_graph=True, allow_unused=True)
    return [0.0 if g is None else float(g.abs().sum()) for g in gs]


@pytest.mark.parametrize("variant", ["protocad", "no_projection", "dreamer_context"])
def test_losses_reach_projector_and_prototypes_only_as_the_paper_says(real_batch, variant):
    agent = Agent(tiny(variant), action_dim=1)
    ctx = agent.wm.context
    batch = agent.to_batch(real_batch)
    step = ctx.prototype_freeze  # past the freeze window
    _, terms, _, _ = agent.wm.loss(batch, step)
    proj, protos = ctx.projector.weight, ctx.prototypes
    # Reward head reads s only (eq. 7); KL involves only the RSSM.
    assert _grads(terms["reward"], [proj, protos]) == [0.0, 0.0]
    assert _grads(terms["kl"], [proj, protos]) == [0.0, 0.0]
    # Decoder reads x: u feeds it in protocad / dreamer_context, e in protocad / no_projection;
    # e = sum_k w_k c_k depends on the projector (through w) and the prototypes.
    g_proj, g_proto = _grads(terms["image"], [proj, protos])
    assert g_proj > 0
    assert (g_proto > 0) == (variant != "dreamer_context")
    # TC-SwAV trains the projector and the prototypes, never the EMA target projector.
    g = _grads(terms["swav"], [proj, protos])
    assert g[0] > 0 and g[1] > 0
    assert not any(p.requires_grad for p in ctx.target_projector.parameters())
    opt_ids = {id(p) for p in agent.optimizers()["world_model"].param_groups[0]["params"]}
    assert id(ctx.target_projector.weight) not in opt_ids and id(proj) in opt_ids


def test_prototypes_frozen_for_the_first_updates(real_batch):
    agent = Agent(tiny("protocad", **{"context.freeze_prototypes_updates": 2}), action_dim=1)
    ctx = agent.wm.context
    before = ctx.prototypes.detach().clone()
    proj_before = ctx.projector.weight.detach().clone()
    for _ in range(2):
        agent.train_step(real_batch)
    assert torch.allclose(ctx.prototypes, before, atol=1e-6)  # no gradient while frozen
    assert not torch.equal(ctx.projector.weight, proj_before)  # the projector does learn
    agent.train_step(real_batch)  # update 2: window over
    assert not torch.allclose(ctx.prototypes, before, atol=1e-4)
    assert torch.allclose(ctx.prototypes.norm(dim=-1), torch.ones(16), atol=1e-5)


def test_batch_validation(real_batch):
    agent = Agent(tiny("dreamer"), action_dim=1)
    bad = dict(real_batch, image=real_batch["image"].astype(np.float32))
    with pytest.raises(ValueError, match="uint8"):
        agent.train_step(bad)
    with pytest.raises(ValueError, match="action"):
        agent.train_step(dict(real_batch, action=np.zeros((B, T, 2), np.float32)))
    with pytest.raises(ValueError, match="missing"):
        agent.train_step({k: v for k, v in real_batch.items() if k != "reward"})
    nan = dict(real_batch, reward=np.full((B, T), np.nan, np.float32))
    with pytest.raises(ValueError, match="NaN"):
        agent.train_step(nan)


def test_inspection_api(real_batch):
    agent = Agent(tiny("protocad"), action_dim=1)
    emb = agent.embed_sequences(real_batch)
    assert emb["s"].shape == (B, T, 40) and emb["u"].shape == (B, T, 32)
    assert emb["w"].shape == (B, T, 16) and emb["e"].shape == (B, T, 32)
    assert np.allclose(emb["w"].sum(-1), 1, atol=1e-5)
    rec = agent.reconstruct(real_batch)
    assert rec.shape == (B, T, 64, 64, 3) and rec.dtype == np.uint8
    ol = agent.open_loop(real_batch, context_steps=5, horizon=50)
    assert ol["truth"].shape == ol["prediction"].shape == (B, T - 5, 64, 64, 3)
    assert np.array_equal(ol["truth"], real_batch["image"][:, 5:])
    assert ol["reward_prediction"].shape == (B, T - 5)           # the reward head on the prior
    assert np.array_equal(ol["reward_truth"], real_batch["reward"][:, 5:])
    dreamer = Agent(tiny("dreamer"), action_dim=1)
    assert dreamer.embed_sequences(real_batch)["u"] is None
    with pytest.raises(ValueError, match="no image decoder"):
        Agent(tiny("dreamerpro"), action_dim=1).reconstruct(real_batch)
    rewards_only = Agent(tiny("dreamerpro"), action_dim=1).open_loop(real_batch, horizon=3, images=False)
    assert set(rewards_only) == {"reward_truth", "reward_prediction"} and rewards_only["reward_prediction"].shape == (B, 3)


# ---- policy --------------------------------------------------------------------------------------
def test_policy_single_and_batched(real_batch):
    agent = Agent(tiny("protocad"), action_dim=1)
    policy = Policy(agent)
    img = real_batch["image"]
    action, feats = policy.act(img[0, 0], np.zeros(1), True)
    assert action.shape == (1,) and action.dtype == np.float32 and abs(action[0]) <= 1
    assert isinstance(feats, ContextFeatures)
    assert feats.u.shape == (32,) and feats.w.shape == (16,) and feats.e.shape == (32,)
    policy.reset(batch_size=B)
    actions, feats = policy.act(img[:, 0], np.zeros((B, 1)), np.ones(B, bool))
    assert actions.shape == (B, 1) and feats.w.shape == (B, 16)
    # the batched answer for entry 0 equals the single-stream answer (nothing sampled: the
    # posterior's mean and trunc_normal's mode, its mean; sampled draws depend on the batch)
    det = Agent(tiny("protocad", **{"behavior.actor_dist": "trunc_normal"}), action_dim=1)
    batched = Policy(det, state_mean=True)
    batched.reset(batch_size=B)
    actions, feats = batched.act(img[:, 0], np.zeros((B, 1)), np.ones(B, bool))
    single = Policy(det, state_mean=True)
    a0, f0 = single.act(img[0, 0], np.zeros(1), True)
    assert np.allclose(actions[0], a0, atol=1e-5) and np.allclose(feats.u[0], f0.u, atol=1e-5)
    # variants without a context module give size-0 features
    dpol = Policy(Agent(tiny("dreamer"), action_dim=1))
    _, f = dpol.act(img[0, 0], np.zeros(1), True)
    assert f.u.size == f.w.size == f.e.size == 0


def _run(policy, batch, b, steps):
    out = []
    for t in range(steps):
        a, f = policy.act(batch["image"][b, t], batch["action"][b, t], t == 0)
        out.append((a, f.u))
    return out


def test_policy_is_first_resets_state_and_is_reproducible(real_batch):
    # nothing sampled (posterior mean, trunc_normal's mode): answers depend on the state alone,
    # not on how far a policy's generator has advanced
    agent = Agent(tiny("protocad", **{"behavior.actor_dist": "trunc_normal"}), action_dim=1)
    Policy = functools.partial(_Policy, state_mean=True)
    p1, p2 = Policy(agent), Policy(agent)
    run1, run2 = _run(p1, real_batch, 0, 6), _run(p2, real_batch, 0, 6)
    for (a1, u1), (a2, u2) in zip(run1, run2):  # deterministic mode: identical
        assert np.array_equal(a1, a2) and np.array_equal(u1, u2)
    # The filtered state matters: the same frame mid-episode gives different features...
    img = real_batch["image"][1, 0]
    _, f_mid = p1.act(img, np.zeros(1), False)
    fresh = Policy(agent)
    _, f_fresh = fresh.act(img, np.zeros(1), True)
    assert not np.allclose(f_mid.u, f_fresh.u, atol=1e-4)
    # ...and is_first forgets the episode: same answer as a fresh policy.
    a_reset, f_reset = p1.act(img, np.zeros(1), True)
    fresh.reset()
    a_fresh, f_fresh = fresh.act(img, np.zeros(1), True)
    assert np.allclose(a_reset, a_fresh, atol=1e-6) and np.allclose(f_reset.u, f_fresh.u,
                                                                       atol=1e-6)
    # Batched: is_first resets only its own entry.
    pb = Policy(agent)
    pb.reset(2)
    imgs = real_batch["image"][:2]
    pb.act(imgs[:, 0], np.zeros((2, 1)), np.array([True, True]))
    a_b, f_b = pb.act(imgs[:, 1], real_batch["action"][:2, 1], np.array([False, True]))
    p_single = Policy(agent)
    p_single.act(imgs[0, 0], np.zeros(1), True)
    a_s, _ = p_single.act(imgs[0, 1], real_batch["action"][0, 1], False)
    fresh.reset()
    a_f, _ = fresh.act(imgs[1, 1], real_batch["action"][1, 1], True)
    assert np.allclose(a_b[0], a_s, atol=1e-5) and np.allclose(a_b[1], a_f, atol=1e-5)


def test_policy_sample_mode_seeded_and_noise_clipped(real_batch):
    agent = Agent(tiny("protocad", **{"behavior.actor_init_std": 3.0}), action_dim=1)
    p = Policy(agent, mode="sample", seed=3)
    r1 = _run(p, real_batch, 0, 5)
    p.reset()
    r2 = _run(p, real_batch, 0, 5)
    assert all(np.array_equal(a, b) for (a, _), (b, _) in zip(r1, r2))
    other = _run(Policy(agent, mode="sample", seed=4), real_batch, 0, 5)
    assert any(not np.array_equal(a, b) for (a, _), (b, _) in zip(r1, other))
    noisy = Policy(agent, exploration_noise=5.0)
    acts = np.array([a for a, _ in _run(noisy, real_batch, 0, 8)])
    assert np.all(np.abs(acts) <= 1) and np.any(np.abs(acts) == 1.0)


def test_policy_rejects_bad_inputs(real_batch):
    policy = Policy(Agent(tiny("dreamer"), action_dim=1))
    img = real_batch["image"][0, 0]
    with pytest.raises(ValueError, match="64, 64, 3"):
        policy.act(np.zeros((32, 32, 3), np.uint8), np.zeros(1), True)
    with pytest.raises(ValueError, match="uint8"):
        policy.act(img.astype(np.float32), np.zeros(1), True)
    with pytest.raises(ValueError, match="prev_action"):
        policy.act(img, np.zeros(3), True)
    with pytest.raises(ValueError, match="NaN"):
        policy.act(img, np.array([np.nan]), True)
    with pytest.raises(ValueError, match="reset\\(batch_size=2\\)"):
        policy.act(np.stack([img, img]), np.zeros((2, 1)), np.ones(2, bool))
    with pytest.raises(ValueError, match="mode"):
        Policy(policy.agent, mode="greedy")


def test_agent_cuda_when_available(real_batch):
    if not torch.cuda.is_available():
        pytest.skip("no CUDA device on this machine")
    agent = Agent(tiny("protocad"), action_dim=1, device="cuda")
    m = agent.train_step(real_batch)
    assert np.isfinite(m["wm_loss"])
    policy = Policy(agent, device="cuda")
    a, f = policy.act(real_batch["image"][0, 0], np.zeros(1), True)
    assert a.shape == (1,) and f.u.shape == (32,)


def test_config_dataclasses_are_typed():
    for section in dataclasses.fields(Config):
        assert section.type  # every field annotated (YAML load coerces by annotation)


def test_one_override_path_for_make_config_files_and_set(tmp_path):
    """make_config, a config file and --set all go through config.apply_overrides: bare keys
    resolve to the one section that has them, ambiguous ones are refused with the choices."""
    from protocad_ros.model.config import apply_overrides
    from trainer.run_config import build_config

    cfg = make_config("pendulum_swingup", "small")
    assert apply_overrides(cfg, {"horizon": 3}).behavior.horizon == 3
    with pytest.raises(ConfigError, match="ambiguous: use one of world_model.lr, drq.lr"):
        apply_overrides(cfg, {"lr": 1e-3})
    (tmp_path / "c.yaml").write_text("behavior:\n  horizon: 7\ntrain:\n  batch_size: 8\n")
    built = build_config("pendulum_swingup", "dreamer", "small", tmp_path / "c.yaml",
                         {"train.batch_size": 4, "kl_scale": 0.5})
    assert (built.behavior.horizon, built.train.batch_size, built.world_model.kl_scale) == (7, 4, 0.5)
    with pytest.raises(ValueError, match="unknown config key"):
        build_config("pendulum_swingup", None, "small", None, {"train.bogus": 1})
