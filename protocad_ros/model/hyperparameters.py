"""The config's values, as data (pure Python, no ROS): the variants, each field's default, the
range each numeric field may take, and the settings tables make_config lays over the defaults.

Defaults are the paper's hyperparameter tables (ProtoCAD, ICLR 2023, appendix "Hyperparameters",
Tables `hyperpara` and `setting_k`).  Where the paper says "we use the default values suggested
in the config file in the official implementation of DreamerPro", the value is DreamerPro's
`dmc` config (DreamerV2 base, fdeng18/dreamer-pro DreamerPro/dreamerv2/configs.yaml) and the
comment next to the field says so ("DreamerPro dmc").  Each field's comment is also the help of
its command-line option (trainer.run_config).

make_config (protocad_ros.model.config, which builds, changes, checks and saves the tree) lays
over the defaults, in this order: the reference config (REFERENCE_SETTINGS), the settings a
baseline was published with (VARIANT_OWN_SETTINGS), the preset that sizes the run
(PRESET_OVERRIDES; MODEL_FREE_PRESET_OVERRIDES for drq), then the caller's overrides.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any


# ------------------------------------------------------------------------------------------------
# The variants: one row each. Agent code asks the row (what it trains, what x_t holds), never the
# name. Adding a variant = a row here (+ its own settings below if it was published with others).
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class VariantSpec:
    """What one variant is made of.

    family: 'world_model' (Dreamer's world model + actor-critic in imagination, protocad_ros.model.agent)
        or 'model_free' (DrQ: SAC on frame stacks, protocad_ros.model.drq).
    features: parts of x_t that the decoder / actor / critic read: 's' = RSSM state (h, z),
        'u' = projection embedding, 'e' = aggregated prototype, 'c' = the true context (read
        from the logs; it also enters the RSSM) (the reward head always reads s).
    representation: the extra representation loss: 'tc_swav' (ProtoCAD's context module),
        'swav' (the context module with in-place SwAV, no temporal consistency), 'dreamerpro'
        (DreamerPro's prototypes, reconstruction-free), 'none'.
    decoder: image reconstruction loss; augmentation: random-shift views of the observations.
    source: where the method comes from (msgs_docs/training.md, "Variants", lists these).
    """

    name: str
    family: str
    features: tuple[str, ...]
    representation: str
    decoder: bool
    augmentation: bool
    source: str

    @property
    def uses_context(self) -> bool:
        return self.representation in ("tc_swav", "swav")

    @property
    def reads_true_context(self) -> bool:
        return "c" in self.features


VARIANT_TABLE: dict[str, VariantSpec] = {v.name: v for v in (
    VariantSpec("protocad", "world_model", ("s", "u", "e"), "tc_swav", True, True,
                "ProtoCAD (Wang et al., ICLR 2023): x = (s, u, e), eq. 6"),
    VariantSpec("dreamer", "world_model", ("s",), "none", True, False,
                "Dreamer (Hafner et al., ICLR 2020), DreamerV2 world model as in DreamerPro's code"),
    VariantSpec("dreamerpro", "world_model", ("s",), "dreamerpro", False, True,
                "DreamerPro (Deng et al., ICML 2022): prototypes as a representation loss only"),
    VariantSpec("dreamer_context", "world_model", ("s", "u"), "tc_swav", True, True,
                "Dreamer + Context (ProtoCAD's baseline): TC-SwAV projection, no aggregation"),
    VariantSpec("no_projection", "world_model", ("s", "e"), "tc_swav", True, True,
                "ProtoCAD ablation 'w/o Projection': x = (s, e)"),
    VariantSpec("no_temporal_consistency", "world_model", ("s", "u", "e"), "swav", True, True,
                "ProtoCAD ablation 'w/o Temporal Consistency': in-place SwAV"),
    VariantSpec("dreamer_true_context", "world_model", ("s", "c"), "none", True, False,
                "Dreamer given the true context (normalized log m, log d into the RSSM and the "
                "decoder, as cRSSM): the ceiling of what a context can give; world model only"),
    VariantSpec("drq", "model_free", (), "none", False, True,
                "DrQ (Yarats, Kostrikov & Fergus, ICLR 2021): SAC + random-shift augmentation"),
)}
VARIANTS = tuple(VARIANT_TABLE)
WORLD_MODEL_VARIANTS = tuple(n for n, v in VARIANT_TABLE.items() if v.family == "world_model")


# ------------------------------------------------------------------------------------------------
# The sections of the config tree: one dataclass each, the paper's values as defaults
# ------------------------------------------------------------------------------------------------
@dataclass
class WorldModelConfig:
    # RSSM sizes: DreamerPro dmc (rssm: {hidden: 200, deter: 200, discrete: False}, stoch 32).
    deter: int = 200
    hidden: int = 200
    stoch: int = 32
    # 0 = continuous Gaussian latents (DreamerPro dmc); >0 = `stoch` categoricals with this many
    # classes each (DreamerV2 Atari / DreamerV3: 32 x 32), straight-through + unimix.
    discrete: int = 0
    unimix: float = 0.01           # DreamerV3: 1% uniform mix in categorical latents
    std_act: str = "sigmoid2"      # DreamerPro rssm.std_act
    min_std: float = 0.1           # DreamerPro rssm.min_std
    gru_norm: bool = True          # DreamerV2/DreamerPro GRUCell(norm=True), update bias -1
    # Conv encoder/decoder: DreamerPro encoder depth 48, kernels 4 (stride 2, 'valid'),
    # DreamerV2 decoder kernels 5, 5, 6, 6. 'dreamerv3' = stride-2 kernel-4 'same' convs down to
    # 4x4 (NM512/dreamerv3-torch, minres 4).
    cnn: str = "dreamerv2"
    cnn_depth: int = 48
    # Heads (reward, discount): DreamerPro reward_head {layers: 4, units: 400, act: elu}.
    mlp_layers: int = 4
    mlp_units: int = 400
    act: str = "elu"               # DreamerPro act: elu
    norm: str = "none"             # 'none' | 'layer' (LayerNorm in MLPs/CNN, DreamerV3 style)
    # KL: DreamerPro kl {balance: 0.8, free: 1.0 (dmc), free_avg: True, forward: False}.
    kl_balance: float = 0.8
    kl_free: float = 1.0
    kl_free_avg: bool = True
    kl_scale: float = 1.0          # DreamerPro loss_scales.kl (beta of eq. 2)
    image_scale: float = 1.0
    reward_scale: float = 1.0
    # DMC has no terminal states: DreamerPro dmc pred_discount False.
    discount_head: bool = False
    discount_scale: float = 1.0
    # Optimiser: paper lr 3e-4 (= DreamerPro model_opt {lr 3e-4, eps 1e-5, clip 100, wd 1e-6}).
    lr: float = 3e-4
    eps: float = 1e-5
    grad_clip: float = 100.0
    weight_decay: float = 1e-6


@dataclass
class ContextConfig:
    # Paper Table `hyperpara`: D = 32, T = 0.1, SK-itr 3, SK-eps 0.05, eta 0.05; K per task.
    # Five values below are not the paper's (reference=paper restores them all): at the paper's
    # the module collapses (projection cosine 0.91, prediction top 0.029 of 1/K = 0.01); with these
    # it stays alive (0.43, 0.151) and predicts unseen frames as well (the world-model study,
    # msgs_docs/results.md, issue 51).
    num_prototypes: int = 100      # K (Table setting_k; make_config sets it per task)
    proto_dim: int = 32
    temperature: float = 0.1
    sinkhorn_iters: int = 3
    # DreamerPro's DMC value (its rssm.sinkhorn_eps); the paper's table says 0.05.
    sinkhorn_eps: float = 0.0125
    ema: float = 0.05              # eta, target-projector momentum fraction (full copy first)
    # Prototypes get no gradient for their first updates, so that early, meaningless projections
    # do not drag them around (DreamerPro freeze_prototypes_iters: 10k of its ~100k updates).
    # -1 = auto: freeze_prototypes_fraction of the run's planned updates, resolved by the
    # trainer from the run's own schedule (resolve_prototype_freeze); a count = exactly that.
    freeze_prototypes_updates: int = -1
    freeze_prototypes_fraction: float = 0.1
    # A run whose prototypes would stay frozen for more than MAX_FREEZE_SHARE of its updates is
    # refused unless this says it is meant (e.g. to measure fixed random prototypes).
    allow_long_freeze: bool = False
    drop_first_steps: int = 1      # DreamerPro rssm.warm_up: first step out of the SwAV scores
    # What the projector f_theta reads: 's' = s_t = (z_t sampled, h_t), the paper's; 'h' = the
    # deterministic state h_t alone (the sampled z is most of s and is noise to a context code
    # that should hold over an episode; the trained projector suppresses it anyway).
    projector_input: str = "h"
    # What one Sinkhorn sample is: 'steps' (every time step, the paper's and DreamerPro's) or
    # 'half_means' (one per sequence half: with K prototypes and B sequences, per-step
    # equipartition forces each sequence onto >= K/B prototypes; per-half it can use one).
    sinkhorn_over: str = "half_means"
    # DreamerPro's same-time cross-view SwAV term (its `swav` loss: each step's prediction
    # against the other view's target at the same step), added beside TC-SwAV with this weight;
    # 0 = the paper's TC-SwAV alone.
    cross_view_scale: float = 1.0
    # Both augmented views train the world model (DreamerPro doubles the batch with them); false
    # = the paper's reading: view 2 only yields the targets.
    both_views_train: bool = True
    swav_scale: float = 1.0        # DreamerPro loss_scales.swav
    aug_pad: int = 3               # DreamerPro aug.max_delta: random shift +-3 px, bilinear
    # The reconstruction loss on x = (s, u, e) also trains projector and prototypes (Algorithm 1,
    # line 13: one gradient step of J_ProtoCAD on all world-model parameters). false = only
    # TC-SwAV trains them (how the Fig. 1 caption can be read); gradients still reach s.
    recon_trains_context: bool = True
    # DreamerPro baseline only (variant 'dreamerpro'): its own K and extra loss scales.
    dreamerpro_num_prototypes: int = 2500  # DreamerPro rssm.num_prototypes
    dreamerpro_temp_scale: float = 1.0     # DreamerPro loss_scales.temp
    dreamerpro_norm_scale: float = 1.0     # DreamerPro loss_scales.norm


@dataclass
class BehaviorConfig:
    horizon: int = 15              # paper H
    discount: float = 0.99         # paper gamma
    lambda_: float = 0.95          # DreamerPro discount_lambda
    # Actor: DreamerPro dmc, whose config the paper defers to: actor {dist: tanh_normal,
    # min_std: 0.1} (its dmc section does not override the default; DreamerV2's own dmc config
    # uses trunc_normal, kept as an option). Same parameterisation as DreamerPro's DistLayer
    # (mean 5 tanh(out / 5), std softplus(out + init) + min_std); its SampleDist takes mode and
    # entropy from 100 samples: ours the mode likewise, the entropy from one sample.
    actor_dist: str = "tanh_normal"
    actor_min_std: float = 0.1
    actor_init_std: float = 0.0
    actor_layers: int = 4          # DreamerPro actor {layers: 4, units: 400, act: elu}
    actor_units: int = 400
    critic_layers: int = 4         # DreamerPro critic {layers: 4, units: 400, act: elu}
    critic_units: int = 400
    act: str = "elu"
    norm: str = "none"
    actor_grad: str = "dynamics"   # DreamerPro dmc: backprop through the model
    actor_grad_mix: float = 0.1    # only for actor_grad='both'
    actor_entropy: float = 1e-4    # DreamerPro dmc actor_ent
    # Paper lr 8e-5 for actor and critic (= DreamerPro dmc); eps/clip/wd: DreamerPro *_opt.
    actor_lr: float = 8e-5
    critic_lr: float = 8e-5
    eps: float = 1e-5
    grad_clip: float = 100.0
    weight_decay: float = 1e-6
    slow_critic: bool = True       # DreamerPro slow_target
    slow_critic_update: int = 100  # DreamerPro slow_target_update (hard copy every 100 updates)
    slow_critic_fraction: float = 1.0


@dataclass
class DrQConfig:
    """DrQ (variant 'drq'): the authors' DMC settings, denisyarats/drq config.yaml (commit
    dd040f1) and the paper's Table of hyperparameters (batch 512, which the config file's
    comment asks for to reproduce the paper).  Not DrQ's: 64x64 frames (every variant here sees
    the bridge's 64x64 images; DrQ used 84x84, so the conv output is 25x25 instead of 35x35),
    the paper's action repeat A = 2 for every task (DrQ used PlaNet's per task), and C updates
    after each collected episode (train.collect_interval, one per agent step of that episode)
    instead of one after every agent step; the replay buffer is every logged episode (DrQ kept
    the last 100k transitions)."""

    frame_stack: int = 3           # frame_stack 3 (the observation is the last 3 frames)
    num_filters: int = 32          # Encoder: 4 conv 3x3 (stride 2, 1, 1, 1), 32 filters, ReLU
    num_conv_layers: int = 4
    feature_dim: int = 50          # encoder.feature_dim 50 (Linear -> LayerNorm -> tanh)
    hidden_dim: int = 1024         # actor / critic hidden_dim 1024
    hidden_depth: int = 2          # hidden_depth 2
    log_std_min: float = -10.0     # actor log_std_bounds [-10, 2]
    log_std_max: float = 2.0
    discount: float = 0.99         # agent.discount
    init_temperature: float = 0.1  # agent.init_temperature
    lr: float = 1e-3               # lr, for actor, critic and temperature (Adam)
    actor_update_frequency: int = 2
    critic_tau: float = 0.01       # soft update of the target critic (encoder included)
    critic_target_update_frequency: int = 2
    image_pad: int = 4             # image_pad: ReplicationPad2d(4) + RandomCrop, per sample
    target_augs: int = 2           # K: augmented next observations averaged in the Q target
    q_augs: int = 2                # M: augmented observations in the critic loss


@dataclass
class TrainConfig:
    batch_size: int = 16           # paper B (as in Dreamer)
    seq_len: int = 50              # paper M
    action_repeat: int = 2         # paper A
    prefill_episodes: int = 2      # paper N (random seed episodes)
    collect_interval: int = 100    # paper C (updates per collected episode)
    expl_noise: float = 0.0        # DreamerPro expl_noise (actions are sampled from the actor)
    eval_noise: float = 0.0
    time_limit: int = 1000         # env steps per episode (DreamerPro dmc time_limit)
    image_size: int = 64
    # How the envs this agent trains and is evaluated in render (sim_bridge.sim.envs): 'fast' = no
    # shadows, reflections or MSAA (4x cheaper on a CPU; what every run here used), 'default' =
    # dm_control's own settings (the look the paper's frames had).
    render_quality: str = "fast"
    # A request, resolved by each process on its own device (protocad_ros.model.precision):
    # 'float32', 'bfloat16' autocast (mixed precision; DreamerPro trains with precision 16,
    # DreamerV3 with bf16; float32 where the device would emulate bf16) or 'auto' (bfloat16
    # where the device has bf16 arithmetic). Losses, KL and distributions are always float32.
    precision: str = "float32"
    device: str = "cpu"
    seed: int = 0
    # What one training process may plan to allocate (estimate_train_memory), in GB; 0 = 90% of
    # this machine's memory. Training refuses a config estimated above it before building it.
    memory_limit_gb: float = 0.0
    # Train the world model only, no actor or critic (the world-model study on fixed logs,
    # msgs_docs/results.md): an update is the world model's step alone.
    world_model_only: bool = False


# ------------------------------------------------------------------------------------------------
# Value ranges: every numeric field, checked before anything is built
# ------------------------------------------------------------------------------------------------
_INF = float("inf")
#: context.freeze_prototypes_updates for "a fraction of the run's planned updates".
FREEZE_AUTO = -1
#: field -> (low, high, low inclusive): sizes positive and bounded by what one process can hold,
#: probabilities in [0, 1], learning rates in [0, 1] (0 freezes a part), eps and clips positive. Fields not listed only need to be finite.
RANGES: dict[str, tuple[float, float, bool]] = {
    **{f"world_model.{k}": (1, 16384, True) for k in ("deter", "hidden")},
    "world_model.stoch": (1, 1024, True), "world_model.discrete": (0, 1024, True),
    "world_model.cnn_depth": (1, 1024, True), "world_model.mlp_layers": (0, 64, True),
    "world_model.mlp_units": (1, 16384, True), "world_model.unimix": (0, 1, True),
    "world_model.min_std": (0, 100, False), "world_model.kl_balance": (0, 1, True),
    "world_model.kl_free": (0, 1e6, True), "world_model.kl_scale": (0, 1e6, True),
    "world_model.image_scale": (0, 1e6, True), "world_model.reward_scale": (0, 1e6, True),
    "world_model.discount_scale": (0, 1e6, True), "world_model.lr": (0, 1, True),
    "world_model.eps": (0, 1, False), "world_model.grad_clip": (0, _INF, False),
    "world_model.weight_decay": (0, 1, True),
    "context.num_prototypes": (1, 1_000_000, True), "context.proto_dim": (1, 16384, True),
    "context.temperature": (0, 1e6, False), "context.sinkhorn_iters": (1, 1000, True),
    "context.sinkhorn_eps": (0, 1e6, False), "context.ema": (0, 1, False),
    "context.cross_view_scale": (0, 1e6, True),
    "context.freeze_prototypes_updates": (FREEZE_AUTO, 1e12, True),
    "context.freeze_prototypes_fraction": (0, 1, True), "context.drop_first_steps": (0, 1000, True),
    "context.swav_scale": (0, 1e6, True), "context.aug_pad": (0, 32, True),
    "context.dreamerpro_num_prototypes": (1, 1_000_000, True),
    "context.dreamerpro_temp_scale": (0, 1e6, True), "context.dreamerpro_norm_scale": (0, 1e6, True),
    "behavior.horizon": (1, 1000, True), "behavior.discount": (0, 1, False),
    "behavior.lambda_": (0, 1, True), "behavior.actor_min_std": (0, 100, False),
    "behavior.actor_layers": (0, 64, True), "behavior.actor_units": (1, 16384, True),
    "behavior.critic_layers": (0, 64, True), "behavior.critic_units": (1, 16384, True),
    "behavior.actor_grad_mix": (0, 1, True), "behavior.actor_entropy": (0, 1e6, True),
    "behavior.actor_lr": (0, 1, True), "behavior.critic_lr": (0, 1, True),
    "behavior.eps": (0, 1, False), "behavior.grad_clip": (0, _INF, False),
    "behavior.weight_decay": (0, 1, True), "behavior.slow_critic_update": (1, 1e9, True),
    "behavior.slow_critic_fraction": (0, 1, False),
    "train.batch_size": (1, 65536, True), "train.seq_len": (2, 100_000, True),
    "train.action_repeat": (1, 1000, True), "train.prefill_episodes": (0, 1e6, True),
    "train.collect_interval": (0, 1e9, True), "train.expl_noise": (0, 100, True),
    "train.eval_noise": (0, 100, True), "train.time_limit": (1, 1e9, True),
    "train.memory_limit_gb": (0, 1e6, True),
    "drq.frame_stack": (1, 64, True), "drq.num_filters": (1, 4096, True),
    "drq.num_conv_layers": (1, 64, True), "drq.feature_dim": (1, 16384, True),
    "drq.hidden_dim": (1, 16384, True), "drq.hidden_depth": (0, 64, True),
    "drq.discount": (0, 1, False), "drq.lr": (0, 1, True),
}


# ------------------------------------------------------------------------------------------------
# Presets, reference configs and a baseline's own settings: overrides of the defaults above
# ------------------------------------------------------------------------------------------------
PRESETS = ("paper", "small", "dreamerv3_sizes")
#: The preset of a command line or a node that is given none: the CPU-sized one (a config built
#: in code, or read from a file without a preset, has the paper's).
DEFAULT_CLI_PRESET = "small"
PRESET_OVERRIDES: dict[str, dict[str, Any]] = {
    "paper": {},
    # CPU preset: ~1/4 of the paper's widths, 2-layer heads, batch 16 x 32, for runs and tests on a
    # CPU. Its time per update, measured: msgs_docs/benchmarks.md ("Training update").
    "small": {
        "world_model.deter": 128, "world_model.hidden": 128, "world_model.stoch": 16,
        "world_model.cnn_depth": 16, "world_model.mlp_layers": 2, "world_model.mlp_units": 128,
        "behavior.actor_layers": 2, "behavior.actor_units": 128,
        "behavior.critic_layers": 2, "behavior.critic_units": 128,
        "train.batch_size": 16, "train.seq_len": 32,
    },
    # NM512/dreamerv3-torch `dmc_vision` sizes (configs.yaml defaults): dyn_deter/dyn_hidden/units
    # 512, 32 x 32 discrete latents with 1% unimix, CNN depth 32 with minres 4, 2-layer heads,
    # SiLU + LayerNorm, batch 16 x 64, horizon 15. bfloat16 autocast: danijar/dreamerv3 computes
    # in bf16 by default (dreamerv3-torch in float32); on CPUs with AVX512-BF16 it is ~3x faster.
    "dreamerv3_sizes": {
        "train.precision": "bfloat16",
        "world_model.deter": 512, "world_model.hidden": 512, "world_model.stoch": 32,
        "world_model.discrete": 32, "world_model.unimix": 0.01, "world_model.cnn": "dreamerv3",
        "world_model.cnn_depth": 32, "world_model.mlp_layers": 2, "world_model.mlp_units": 512,
        "world_model.act": "silu", "world_model.norm": "layer",
        "behavior.actor_layers": 2, "behavior.actor_units": 512,
        "behavior.critic_layers": 2, "behavior.critic_units": 512,
        "behavior.act": "silu", "behavior.norm": "layer",
        "train.batch_size": 16, "train.seq_len": 64,
    },
}

# The model-free family's presets ('dreamerv3_sizes' sizes a world model: refused for drq).
# CPU preset: DrQ's config-file batch of 128 (its comment: "with a smaller batch size it still
# works well"), 16 conv filters and 256 hidden units.
MODEL_FREE_PRESET_OVERRIDES: dict[str, dict[str, Any]] = {
    "paper": {},
    "small": {"train.batch_size": 128, "drq.num_filters": 16, "drq.hidden_dim": 256},
}


#: context.projector_input: what f_theta reads (WorldModel.context_input).
PROJECTOR_INPUTS = ("s", "h")
#: context.sinkhorn_over: what one Sinkhorn sample is (ContextModule.targets).
SINKHORN_OVER = ("steps", "half_means")

#: The context module as the paper states it (Table `hyperpara`, sec. 4.2, Algorithm 1).
PAPER_CONTEXT_SETTINGS: dict[str, Any] = {
    "context.sinkhorn_eps": 0.05, "context.temperature": 0.1, "context.sinkhorn_iters": 3,
    "context.ema": 0.05, "context.proto_dim": 32, "context.projector_input": "s",
    "context.sinkhorn_over": "steps", "context.cross_view_scale": 0.0,
    "context.both_views_train": False,
}

#: The reference configs behind `Config.reference`, as overrides of the defaults above (which
#: are DreamerPro's dmc). DreamerV2: danijar/dreamerv2 dreamerv2/configs.yaml (commit 07d906e),
#: defaults + dmc_vision: rssm {stoch 32, discrete 32} (no unimix: a DreamerV3 addition),
#: actor dist 'auto' = trunc_normal for continuous actions; its other dmc_vision values (deter
#: and hidden 200, kl free 1.0, lr 3e-4 / 8e-5 / 8e-5, actor_ent 1e-4, CNN depth 48) are
#: DreamerPro's too. Applied first by make_config, so variant settings, presets and overrides
#: win.
REFERENCE_SETTINGS: dict[str, dict[str, Any]] = {
    "dreamerpro": {},
    # The paper's own settings, stated: DreamerPro's dmc reference with the context module as
    # the paper's text and tables define it (whatever the context defaults become).
    "paper": dict(PAPER_CONTEXT_SETTINGS),
    "dreamerv2": {
        "world_model.discrete": 32,
        "world_model.unimix": 0.0,
        "behavior.actor_dist": "trunc_normal",
    },
}

#: Settings a baseline was published with where they differ from ProtoCAD's, applied by
#: make_config before the preset (which sizes the run) and the overrides. DreamerPro:
#: fdeng18/dreamer-pro, DreamerPro/dreamerv2/configs.yaml (commit 033edd7), defaults + dmc.
VARIANT_OWN_SETTINGS: dict[str, dict[str, Any]] = {
    "dreamerpro": {
        "context.sinkhorn_eps": 0.0125,          # dmc: rssm.sinkhorn_eps 0.0125
        "train.batch_size": 50,                  # dataset.batch 50
        "train.seq_len": 51,                     # dataset.length 51
        # train_every 5 counts agent steps (its train.py divides prefill and time limit by
        # action_repeat, never train_every): 500 agent steps / 5 = 100 per 1000-step episode;
        # prefill 5000 env steps = 5 episodes (dmc time_limit 1000).
        "train.collect_interval": 100,
        "train.prefill_episodes": 5,
    },
    # The true-context ceiling has no policy that could act: it trains its world model only.
    "dreamer_true_context": {"train.world_model_only": True},
    # DrQ: denisyarats/drq config.yaml (dd040f1) and its paper: batch 512 transitions, one
    # update per agent step (500 per 1000-step episode at A = 2), 1000 seed steps of random
    # actions (= 2 episodes at A = 2, ProtoCAD's N as well).
    "drq": {
        "train.batch_size": 512,
        "train.collect_interval": 500,
        "train.prefill_episodes": 2,
    },
}
