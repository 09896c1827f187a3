"""Baselines at the settings they were published with, and ProtoCAD's where the paper defers.

DreamerPro's values are those of its released config, fdeng18/dreamer-pro
DreamerPro/dreamerv2/configs.yaml at commit 033edd7 (the `defaults` section with the `dmc`
section applied), read from that file when these numbers were written down.
"""
from __future__ import annotations

import pytest

from protocad_ros.model.config import make_config

DREAMERPRO_DMC = {
    # dataset: {batch: 50, length: 51}
    ("train", "batch_size"): 50, ("train", "seq_len"): 51,
    # dmc: rssm {hidden: 200, deter: 200, discrete: False, sinkhorn_eps: 0.0125}; defaults: stoch 32,
    # warm_up 1, num_prototypes 2500, proto 32, temperature 0.1, sinkhorn_iters 3
    ("world_model", "hidden"): 200, ("world_model", "deter"): 200, ("world_model", "stoch"): 32,
    ("world_model", "discrete"): 0, ("context", "sinkhorn_eps"): 0.0125,
    ("context", "drop_first_steps"): 1, ("context", "dreamerpro_num_prototypes"): 2500,
    ("context", "proto_dim"): 32, ("context", "temperature"): 0.1, ("context", "sinkhorn_iters"): 3,
    # freeze_prototypes_iters 10000 of its 100k updates (1M env steps / A 2 / train_every 5): a
    # tenth of the run, here auto (-1) at 0.1; ema_update_fraction 0.05, aug.max_delta 3
    ("context", "freeze_prototypes_updates"): -1, ("context", "freeze_prototypes_fraction"): 0.1, ("context", "ema"): 0.05, ("context", "aug_pad"): 3,
    # loss_scales {swav 1, temp 1, norm 1, kl 1, reward 1}; dmc kl.free 1.0; kl balance 0.8, free_avg
    ("context", "swav_scale"): 1.0, ("context", "dreamerpro_temp_scale"): 1.0,
    ("context", "dreamerpro_norm_scale"): 1.0, ("world_model", "kl_scale"): 1.0,
    ("world_model", "kl_free"): 1.0, ("world_model", "kl_balance"): 0.8, ("world_model", "kl_free_avg"): True,
    # encoder depth 48; heads 4 x 400 elu; model_opt lr 3e-4 eps 1e-5 clip 100 wd 1e-6
    ("world_model", "cnn_depth"): 48, ("world_model", "mlp_layers"): 4, ("world_model", "mlp_units"): 400,
    ("world_model", "lr"): 3e-4, ("world_model", "eps"): 1e-5, ("world_model", "grad_clip"): 100.0,
    ("world_model", "weight_decay"): 1e-6, ("world_model", "discount_head"): False,   # dmc pred_discount
    # actor {layers 4, units 400, dist tanh_normal, min_std 0.1}; dmc actor/critic lr 8e-5, actor_ent 1e-4,
    # actor_grad dynamics; discount 0.99, discount_lambda 0.95, imag_horizon 15; slow_target every 100
    ("behavior", "actor_dist"): "tanh_normal", ("behavior", "actor_min_std"): 0.1,
    ("behavior", "actor_layers"): 4, ("behavior", "actor_units"): 400, ("behavior", "critic_layers"): 4,
    ("behavior", "actor_lr"): 8e-5, ("behavior", "critic_lr"): 8e-5, ("behavior", "actor_entropy"): 1e-4,
    ("behavior", "actor_grad"): "dynamics", ("behavior", "discount"): 0.99, ("behavior", "lambda_"): 0.95,
    ("behavior", "horizon"): 15, ("behavior", "slow_critic"): True, ("behavior", "slow_critic_update"): 100,
    # dmc: action_repeat 2, time_limit 1000, train_every 5 agent steps (train.py divides prefill
    # and time_limit by action_repeat, never train_every): 500 / 5 = 100 updates per 1000-step
    # episode; prefill 5000 env steps (5 episodes), expl_noise 0
    ("train", "action_repeat"): 2, ("train", "time_limit"): 1000, ("train", "collect_interval"): 100,
    ("train", "prefill_episodes"): 5, ("train", "expl_noise"): 0.0,
}


@pytest.mark.parametrize("task", ["walker_walk", "cheetah_run"])
def test_dreamerpro_runs_at_its_released_dmc_settings(task):
    cfg = make_config(task, "paper", "dreamerpro")
    got = {k: getattr(getattr(cfg, k[0]), k[1]) for k in DREAMERPRO_DMC}
    assert got == DREAMERPRO_DMC
    assert cfg.own_settings and cfg.uses_decoder is False       # reconstruction-free


def test_dreamerpro_at_protocad_settings_is_the_ablation_option():
    own, same = make_config("walker_walk", "paper", "dreamerpro", reference="paper"), make_config(
        "walker_walk", "paper", "dreamerpro", own_settings=False, reference="paper")
    ours = make_config("walker_walk", "paper", "protocad", reference="paper")
    assert not same.own_settings
    for section, key in (("train", "batch_size"), ("train", "seq_len"), ("context", "sinkhorn_eps"),
                         ("train", "prefill_episodes")):
        assert getattr(getattr(same, section), key) == getattr(getattr(ours, section), key)
        assert getattr(getattr(own, section), key) != getattr(getattr(ours, section), key)
    # DreamerPro's update rate is ProtoCAD's C = 100 (both 5 agent steps per update)
    assert own.train.collect_interval == same.train.collect_interval == 100


def test_protocad_defaults_are_the_paper_tables_and_dreamerpro_where_it_defers():
    cfg = make_config("walker_walk", "paper", "protocad", reference="paper")
    # Table hyperpara: D 32, T 0.1, SK-itr 3, SK-eps 0.05, eta 0.05; B 16, M 50, H 15; K (setting_k)
    assert (cfg.context.proto_dim, cfg.context.temperature, cfg.context.sinkhorn_iters,
            cfg.context.sinkhorn_eps, cfg.context.ema) == (32, 0.1, 3, 0.05, 0.05)
    assert (cfg.train.batch_size, cfg.train.seq_len, cfg.behavior.horizon) == (16, 50, 15)
    assert cfg.context.num_prototypes == 100
    assert cfg.behavior.actor_dist == "tanh_normal"              # DreamerPro dmc actor
    # the other variants have no published settings of their own here: own_settings changes nothing
    for variant in ("dreamer", "dreamer_context", "no_projection", "no_temporal_consistency"):
        assert make_config("walker_walk", "paper", variant).to_dict() | {"own_settings": False} == \
            make_config("walker_walk", "paper", variant, own_settings=False).to_dict()


# danijar/dreamerv2 dreamerv2/configs.yaml (commit 07d906e), defaults + dmc_vision: rssm {hidden 200,
# deter 200} with the defaults' stoch 32, discrete 32; actor dist auto (trunc_normal for
# continuous actions), min_std 0.1; kl.free 1.0, balance 0.8; model_opt lr 3e-4; actor/critic lr
# 8e-5; actor_ent 1e-4; dataset 16 x 50; action_repeat 2; train_every 5 agent steps.
DREAMERV2_DMC_VISION = {
    ("world_model", "hidden"): 200, ("world_model", "deter"): 200, ("world_model", "stoch"): 32,
    ("world_model", "discrete"): 32, ("world_model", "unimix"): 0.0, ("world_model", "cnn_depth"): 48,
    ("world_model", "kl_free"): 1.0, ("world_model", "kl_balance"): 0.8, ("world_model", "lr"): 3e-4,
    ("behavior", "actor_dist"): "trunc_normal", ("behavior", "actor_min_std"): 0.1,
    ("behavior", "actor_lr"): 8e-5, ("behavior", "critic_lr"): 8e-5, ("behavior", "actor_entropy"): 1e-4,
    ("train", "batch_size"): 16, ("train", "seq_len"): 50, ("train", "action_repeat"): 2,
    ("train", "collect_interval"): 100,
}


def test_reference_dreamerv2_is_dreamerv2s_dmc_vision_config():
    cfg = make_config("walker_walk", "paper", "dreamer", reference="dreamerv2")
    got = {k: getattr(getattr(cfg, k[0]), k[1]) for k in DREAMERV2_DMC_VISION}
    assert got == DREAMERV2_DMC_VISION
    assert cfg.reference == "dreamerv2"
    # a preset sizes it, and an explicit override still wins over the reference
    small = make_config("walker_walk", "small", "dreamer", reference="dreamerv2",
                        **{"behavior.actor_dist": "tanh_normal"})
    assert (small.world_model.discrete, small.world_model.deter) == (32, 128)
    assert small.behavior.actor_dist == "tanh_normal"


def test_reference_and_weight_init_are_checked():
    from protocad_ros.model.config import ConfigError
    with pytest.raises(ConfigError, match="unknown reference"):
        make_config("walker_walk", "small", "dreamer", reference="dreamerv9")
    with pytest.raises(ConfigError, match="weight_init"):
        make_config("walker_walk", "small", "dreamer", weight_init="he")
    assert make_config("walker_walk").weight_init == "glorot"    # the references' Keras default


#: ProtoCAD's context module as the paper states it: Table `hyperpara` (D 32, T 0.1, SK-itr 3,
#: SK-eps 0.05, eta 0.05), sec. 4.2 (the projector reads s; one Sinkhorn sample per time step;
#: TC-SwAV alone; view 2 only yields the targets).
PAPER_CONTEXT = {"proto_dim": 32, "temperature": 0.1, "sinkhorn_iters": 3, "sinkhorn_eps": 0.05, "ema": 0.05,
                 "projector_input": "s", "sinkhorn_over": "steps", "cross_view_scale": 0.0,
                 "both_views_train": False}


@pytest.mark.parametrize("preset", ["paper", "small"])
def test_reference_paper_gives_the_papers_context_settings_whatever_the_defaults(preset):
    fixes = {"context.sinkhorn_eps": 0.0125, "context.projector_input": "h", "context.sinkhorn_over": "half_means",
             "context.cross_view_scale": 1.0, "context.both_views_train": True}
    cfg = make_config("walker_walk", preset, "protocad", reference="paper")
    assert {k: getattr(cfg.context, k) for k in PAPER_CONTEXT} == PAPER_CONTEXT
    assert cfg.context.num_prototypes == 100 and cfg.reference == "paper"   # K of the task table
    # The reference sits under the caller's overrides (as every reference does) ...
    tried = make_config("walker_walk", preset, "protocad", reference="paper", **fixes)
    assert {f"context.{k}": getattr(tried.context, k) for k in (n.split(".")[1] for n in fixes)} == fixes
    # ... and the Dreamer core under it is DreamerPro's, the paper's own.
    pro = make_config("walker_walk", preset, "protocad")
    assert tried.world_model == pro.world_model and tried.behavior == pro.behavior


#: The context section of the walker policy shipped until 2026-12-07 (4bb2ca1), as its file
#: saved it: trained before the context settings existed.
SAVED_BEFORE = {"num_prototypes": 100, "proto_dim": 32, "temperature": 0.1, "sinkhorn_iters": 3,
                "sinkhorn_eps": 0.05, "ema": 0.05, "freeze_prototypes_updates": -1,
                "freeze_prototypes_fraction": 0.1, "allow_long_freeze": False, "drop_first_steps": 1,
                "swav_scale": 1.0, "aug_pad": 3, "recon_trains_context": True, "dreamerpro_num_prototypes": 2500,
                "dreamerpro_temp_scale": 1.0, "dreamerpro_norm_scale": 1.0}


def test_a_config_saved_before_the_context_settings_reads_as_the_papers():
    from protocad_ros.model.config import Config

    saved = {**make_config("walker_walk", "small", "protocad").to_dict(), "context": dict(SAVED_BEFORE)}
    cfg = Config.from_dict(saved)
    assert {k: getattr(cfg.context, k) for k in PAPER_CONTEXT} == PAPER_CONTEXT
    # A whole context section with the settings keeps them; a partial one (a user's --config
    # file) takes the defaults for what it leaves out.
    now = make_config("walker_walk", "small", "protocad", **{"context.sinkhorn_over": "half_means"}).to_dict()
    assert Config.from_dict(now).context.sinkhorn_over == "half_means"
    partial = {"task": "walker_walk", "context": {"num_prototypes": 7}}
    assert Config.from_dict(partial).context.projector_input == make_config("walker_walk").context.projector_input
