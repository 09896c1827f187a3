"""One typed configuration tree for the ProtoCAD agent and its baselines (pure Python, no ROS).

Defaults are the paper's hyperparameter tables (ProtoCAD, ICLR 2023, appendix "Hyperparameters",
Tables `hyperpara` and `setting_k`).  Where the paper says "we use the default values suggested
in the config file in the official implementation of DreamerPro", the value is DreamerPro's
`dmc` config (DreamerV2 base, fdeng18/dreamer-pro DreamerPro/dreamerv2/configs.yaml) and the
comment next to the field says so ("DreamerPro dmc").

    cfg = make_config("walker_walk", preset="paper", variant="protocad",
                      **{"train.batch_size": 8, "world_model.deter": 128})
    cfg.save("run/config.yaml"); cfg2 = Config.load("run/config.yaml")

Presets: 'paper' (the paper/DreamerPro sizes), 'small' (CPU-sized, for quick runs and tests),
'dreamerv3_sizes' (NM512/dreamerv3-torch dmc_vision sizes: 512 units, 32x32 discrete latents,
CNN depth 32, batch 16 x 64; used by scripts/bench_train.py --dreamerv3-sizes).
Unknown keys are rejected everywhere (overrides, from_dict, load) with the list of valid keys.
"""
from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import yaml

from protocad_ros.atomic import atomic_write_text
from sim_bridge.contract.contexts import TASKS  # pure data (no ROS): the contract's task table


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
        'u' = projection embedding, 'e' = aggregated prototype (the reward head always reads s).
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
    VariantSpec("drq", "model_free", (), "none", False, True,
                "DrQ (Yarats, Kostrikov & Fergus, ICLR 2021): SAC + random-shift augmentation"),
)}
VARIANTS = tuple(VARIANT_TABLE)
WORLD_MODEL_VARIANTS = tuple(n for n, v in VARIANT_TABLE.items() if v.family == "world_model")
PRESETS = ("paper", "small", "dreamerv3_sizes")
#: The preset of a command line or a node that is given none: the CPU-sized one (a config built
#: in code, or read from a file without a preset, has the paper's).
DEFAULT_CLI_PRESET = "small"

class ConfigError(ValueError):
    """A configuration key or value that does not fit the tree (message lists valid keys)."""


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
    num_prototypes: int = 100      # K (Table setting_k; make_config sets it per task)
    proto_dim: int = 32
    temperature: float = 0.1
    sinkhorn_iters: int = 3
    # Paper value. DreamerPro overrides this to 0.0125 for DMC; keep configurable.
    sinkhorn_eps: float = 0.05
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


@dataclass
class Config:
    task: str = "pendulum_swingup"
    variant: str = "protocad"
    preset: str = "paper"
    # A baseline with the settings it was published with (VARIANT_OWN_SETTINGS: DreamerPro's
    # DMC config for 'dreamerpro'), as the paper ran it; false = ProtoCAD's settings for every
    # variant (an ablation-style comparison on one schedule).
    own_settings: bool = True
    # Which reference config fills what the paper leaves to "the official implementation":
    # 'dreamerpro' (DreamerPro dmc, what the paper used) or 'dreamerv2' (DreamerV2 dmc_vision:
    # 32 x 32 discrete latents without unimix, trunc_normal actor; the anchor's, and the
    # paper's appendix comparison on standard DMC keeps DreamerV2's settings). REFERENCE_SETTINGS.
    reference: str = "dreamerpro"
    # Weight initialisation: 'glorot' (uniform fan-average, zero biases: the Keras default both
    # references use) or 'torch' (PyTorch's layer defaults, what runs before 2026-12 used).
    weight_init: str = "glorot"
    world_model: WorldModelConfig = field(default_factory=WorldModelConfig)
    context: ContextConfig = field(default_factory=ContextConfig)
    behavior: BehaviorConfig = field(default_factory=BehaviorConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    drq: DrQConfig = field(default_factory=DrQConfig)

    # ---- derived ------------------------------------------------------------------------------
    @property
    def spec(self) -> VariantSpec:
        """This variant's row of VARIANT_TABLE."""
        return VARIANT_TABLE[self.variant]

    @property
    def features(self) -> tuple[str, ...]:
        """Parts of x_t for this variant, e.g. ('s', 'u', 'e')."""
        return self.spec.features

    @property
    def uses_context(self) -> bool:
        """True for variants with ProtoCAD's ContextModule (projector + prototypes + TC-SwAV)."""
        return self.spec.uses_context

    @property
    def uses_augmentation(self) -> bool:
        return self.spec.augmentation

    @property
    def uses_decoder(self) -> bool:
        return self.spec.decoder

    # ---- serialisation -------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "Config":
        """Inverse of to_dict. Missing keys take defaults; unknown keys raise ConfigError."""
        if not isinstance(d, Mapping):
            raise ConfigError(f"config must be a mapping, got {type(d).__name__}")
        cfg = _build(cls, _migrate(d), "")
        cfg.validate()
        return cfg

    def save(self, path: str | os.PathLike) -> Path:
        """Write YAML atomically (tmp file in the same directory + fsync + os.replace)."""
        path = Path(path)
        atomic_write_text(path, yaml.safe_dump(self.to_dict(), sort_keys=False))
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> "Config":
        with open(path) as f:
            d = yaml.safe_load(f)
        try:
            return cls.from_dict(d or {})
        except ConfigError as err:
            raise ConfigError(f"{path}: {err}") from None

    def replace(self, **overrides: Any) -> "Config":
        """A copy with dotted-key overrides applied ('train.batch_size'=8)."""
        cfg = Config.from_dict(self.to_dict())
        apply_overrides(cfg, overrides)
        return cfg

    def validate(self) -> None:
        def check(ok: bool, msg: str) -> None:
            if not ok:
                raise ConfigError(msg)
        _check_ranges(self)
        check(self.variant in VARIANTS, f"unknown variant {self.variant!r}; valid: {VARIANTS}")
        check(self.preset in PRESETS, f"unknown preset {self.preset!r}; valid: {PRESETS}")
        wm, ctx, bh, tr = self.world_model, self.context, self.behavior, self.train
        if self.spec.family == "model_free":
            d = self.drq
            check(self.preset != "dreamerv3_sizes", "preset 'dreamerv3_sizes' sizes a world model; "
                  "drq has 'paper' (its authors' sizes) and 'small'")
            check(tr.seq_len == d.frame_stack + 1,
                  f"drq trains on windows of frame_stack + 1 = {d.frame_stack + 1} steps (a frame "
                  f"stack and the next one), got train.seq_len={tr.seq_len}")
            check(d.frame_stack >= 1 and d.num_conv_layers >= 1 and d.num_filters >= 1
                  and d.feature_dim >= 1 and d.hidden_dim >= 1 and d.hidden_depth >= 0,
                  "drq sizes must be positive (hidden_depth >= 0)")
            check(d.log_std_min < d.log_std_max, "drq.log_std_min must be < drq.log_std_max")
            check(d.init_temperature > 0, "drq.init_temperature must be > 0")
            check(0.0 < d.critic_tau <= 1.0, "drq.critic_tau must be in (0, 1]")
            check(d.actor_update_frequency >= 1 and d.critic_target_update_frequency >= 1,
                  "drq update frequencies must be >= 1")
            check(d.image_pad >= 0 and d.target_augs >= 1 and d.q_augs >= 1,
                  "drq.image_pad >= 0, drq.target_augs >= 1, drq.q_augs >= 1")
        check(self.reference in REFERENCE_SETTINGS, f"unknown reference {self.reference!r}; "
              f"valid: {sorted(REFERENCE_SETTINGS)}")
        check(self.weight_init in ("glorot", "torch"),
              f"weight_init must be 'glorot'|'torch', got {self.weight_init!r}")
        check(wm.cnn in ("dreamerv2", "dreamerv3"), f"world_model.cnn must be 'dreamerv2' or "
              f"'dreamerv3', got {wm.cnn!r}")
        check(wm.norm in ("none", "layer"), f"world_model.norm must be 'none'|'layer', got {wm.norm!r}")
        check(bh.norm in ("none", "layer"), f"behavior.norm must be 'none'|'layer', got {bh.norm!r}")
        check(wm.discrete >= 0 and wm.stoch > 0 and wm.deter > 0 and wm.hidden > 0,
              "world_model sizes must be positive (discrete >= 0)")
        check(0.0 <= wm.kl_balance <= 1.0, "world_model.kl_balance must be in [0, 1]")
        check(bh.actor_dist in ("trunc_normal", "tanh_normal"),
              f"behavior.actor_dist must be 'trunc_normal'|'tanh_normal', got {bh.actor_dist!r}")
        check(bh.actor_grad in ("dynamics", "reinforce", "both"),
              f"behavior.actor_grad must be 'dynamics'|'reinforce'|'both', got {bh.actor_grad!r}")
        check(bh.horizon >= 1, "behavior.horizon must be >= 1")
        check(tr.precision in ("auto", "float32", "bfloat16"),
              f"train.precision must be 'auto'|'float32'|'bfloat16', got {tr.precision!r}")
        check(tr.image_size == 64, "only 64x64 images are supported (train.image_size=64)")
        check(tr.render_quality in ("fast", "default"),
              f"train.render_quality must be 'fast'|'default', got {tr.render_quality!r}")
        check(tr.batch_size >= 1 and tr.seq_len >= 2, "train.batch_size >= 1, seq_len >= 2")
        if self.spec.representation != "none":
            # SwAV scores drop the first steps and TC-SwAV needs two halves of >= 1 step.
            check(tr.seq_len - ctx.drop_first_steps >= 2,
                  f"train.seq_len={tr.seq_len} too short for the SwAV loss "
                  f"(drop_first_steps={ctx.drop_first_steps})")
            check(ctx.num_prototypes >= 1 and ctx.proto_dim >= 1, "context sizes must be >= 1")
            check(0.0 < ctx.ema <= 1.0, "context.ema must be in (0, 1]")


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


def _check_ranges(cfg: "Config") -> None:
    """ConfigError naming the first numeric field that is not finite or out of its range."""
    for section in dataclasses.fields(cfg):
        sub = getattr(cfg, section.name)
        if not dataclasses.is_dataclass(sub):
            continue
        for f in dataclasses.fields(sub):
            v = getattr(sub, f.name)
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                continue
            key = f"{section.name}.{f.name}"
            if not math.isfinite(v):
                raise ConfigError(f"{key} must be a finite number, got {v!r}")
            lo, hi, lo_in = RANGES.get(key, (-_INF, _INF, True))
            if not ((v >= lo if lo_in else v > lo) and v <= hi):
                low = f"[{lo:g}" if lo_in else f"({lo:g}"
                raise ConfigError(f"{key}={v!r} is out of range: it must be in {low}, {hi:g}]")


def estimate_train_memory(cfg: "Config", action_dim: int = 6) -> int:
    """A rough upper estimate, in bytes, of what training a world-model config allocates:
    weights with their gradients and Adam moments, and the activations one update keeps for
    its backward pass (the observed sequences through the CNNs, the imagined rollout through
    the heads). It errs high so that only configs far beyond a machine are refused."""
    wm, bh, tr, ctx = cfg.world_model, cfg.behavior, cfg.train, cfg.context
    stoch = wm.stoch * (wm.discrete or 1)
    feat = wm.deter + stoch + 2 * ctx.proto_dim
    d = wm.cnn_depth
    mlp = lambda inp, layers, units: inp * units + max(0, layers - 1) * units * units  # noqa: E731
    params = (3 * (wm.hidden + wm.deter) * wm.deter + 4 * wm.hidden * (stoch + action_dim + wm.deter)
              + 2 * 16 * 42 * d * d + 8 * d * 16 * feat
              + mlp(feat, wm.mlp_layers, wm.mlp_units) + mlp(feat, bh.actor_layers, bh.actor_units)
              + 2 * mlp(feat, bh.critic_layers, bh.critic_units)
              + ctx.num_prototypes * ctx.proto_dim + ctx.dreamerpro_num_prototypes * ctx.proto_dim)
    steps = tr.batch_size * tr.seq_len
    observe = steps * (4 * 2000 * d + 8 * (wm.deter + wm.hidden + stoch) + mlp(1, wm.mlp_layers, wm.mlp_units))
    widest = max(wm.mlp_units * wm.mlp_layers, bh.actor_units * bh.actor_layers,
                 bh.critic_units * bh.critic_layers, 1)
    imagine = steps * (bh.horizon + 1) * (4 * feat + 8 * wm.deter + 6 * widest)
    swav = steps * 2 * ctx.num_prototypes
    return int(4 * (4 * params + observe + imagine + swav))


def machine_memory_bytes() -> int:
    """Physical memory of this machine (0 where the OS does not say)."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return 0


def check_train_memory(cfg: "Config") -> None:
    """ConfigError when training `cfg` is estimated to need more memory than the limit
    (train.memory_limit_gb, else 90% of this machine's), before anything is allocated."""
    if cfg.spec.family != "world_model":
        return
    need = estimate_train_memory(cfg)
    limit = cfg.train.memory_limit_gb * 2**30 or 0.9 * machine_memory_bytes()
    if limit and need > limit:
        raise ConfigError(f"this config needs about {need / 2**30:,.1f} GB to train (estimate: "
                          f"weights, optimiser state and one update's activations) and the limit is "
                          f"{limit / 2**30:,.1f} GB; make it smaller (batch_size, seq_len, "
                          f"behavior.horizon, sizes) or raise --set train.memory_limit_gb=N")


# ------------------------------------------------------------------------------------------------
# The prototype freeze, scaled to the run
# ------------------------------------------------------------------------------------------------
#: The largest share of a run's updates its prototypes may stay frozen for without
#: context.allow_long_freeze: past it the run mostly measures fixed random prototypes.
MAX_FREEZE_SHARE = 0.25


def resolve_prototype_freeze(ctx: ContextConfig, end_updates: int) -> int:
    """The update count below which the prototypes get no gradient, for a run whose agent's
    update counter ends at `end_updates`: the configured count, or (auto) its fraction of them."""
    if ctx.freeze_prototypes_updates == FREEZE_AUTO:
        return int(round(ctx.freeze_prototypes_fraction * max(end_updates, 0)))
    return int(ctx.freeze_prototypes_updates)


def check_prototype_freeze(ctx: ContextConfig, freeze: int, start: int, end: int) -> None:
    """ConfigError when the updates start..end would keep the prototypes frozen (below
    `freeze`) for more than MAX_FREEZE_SHARE of them, unless context.allow_long_freeze."""
    planned = end - start
    frozen = max(0, min(freeze, end) - start)
    if planned > 0 and frozen > MAX_FREEZE_SHARE * planned and not ctx.allow_long_freeze:
        raise ConfigError(
            f"the prototypes would stay frozen for {frozen:,} of this run's {planned:,} updates "
            f"(context.freeze_prototypes_updates={freeze:,}): set it to -1 (auto, "
            f"{ctx.freeze_prototypes_fraction:.0%} of the run) or a smaller count, or "
            f"context.allow_long_freeze=true if that is meant")


def plan_prototype_freeze(cfg: "Config", start: int, end: int) -> int | None:
    """The resolved and checked freeze of a run whose update counter goes from `start` to
    `end`; None for variants without prototypes."""
    if cfg.spec.representation == "none" or cfg.spec.family != "world_model":
        return None
    freeze = resolve_prototype_freeze(cfg.context, end)
    check_prototype_freeze(cfg.context, freeze, start, end)
    return freeze


def _migrate(d: Mapping[str, Any]) -> Mapping[str, Any]:
    """Configs written before the freeze scaled to the run recorded DreamerPro's 10,000 as a
    default, not a choice (no run here was that long): read it as auto."""
    ctx = d.get("context")
    if (isinstance(ctx, Mapping) and "freeze_prototypes_fraction" not in ctx
            and ctx.get("freeze_prototypes_updates") == 10000):
        return {**d, "context": {**ctx, "freeze_prototypes_updates": FREEZE_AUTO}}
    return d


# ------------------------------------------------------------------------------------------------
# Presets and construction
# ------------------------------------------------------------------------------------------------
_PRESET_OVERRIDES: dict[str, dict[str, Any]] = {
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
_MODEL_FREE_PRESET_OVERRIDES: dict[str, dict[str, Any]] = {
    "paper": {},
    "small": {"train.batch_size": 128, "drq.num_filters": 16, "drq.hidden_dim": 256},
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
    # DrQ: denisyarats/drq config.yaml (dd040f1) and its paper: batch 512 transitions, one
    # update per agent step (500 per 1000-step episode at A = 2), 1000 seed steps of random
    # actions (= 2 episodes at A = 2, ProtoCAD's N as well).
    "drq": {
        "train.batch_size": 512,
        "train.collect_interval": 500,
        "train.prefill_episodes": 2,
    },
}


def task_num_prototypes(task: str) -> int:
    """K for a task (paper Table `setting_k`), from the task table sim_bridge.contract.contexts.TASKS."""
    if task not in TASKS:
        raise ConfigError(f"unknown task {task!r}; valid tasks: {sorted(TASKS)}")
    return int(TASKS[task].num_prototypes)


def make_config(task: str = "pendulum_swingup", preset: str = "paper",
                variant: str = "protocad", **overrides: Any) -> Config:
    """The config for (task, preset, variant) with dotted-key overrides applied last.

    make_config("cheetah_run", "small", "dreamer", **{"train.batch_size": 8})
    K (context.num_prototypes) comes from the task table unless overridden.
    """
    if preset not in PRESETS:
        raise ConfigError(f"unknown preset {preset!r}; valid: {PRESETS}")
    if variant not in VARIANTS:
        raise ConfigError(f"unknown variant {variant!r}; valid: {VARIANTS}")
    own = _coerce(overrides.get("own_settings", True), "bool", "own_settings", True)
    reference = _coerce(overrides.get("reference", "dreamerpro"), "str", "reference", "")
    if reference not in REFERENCE_SETTINGS:
        raise ConfigError(f"unknown reference {reference!r}; valid: {sorted(REFERENCE_SETTINGS)}")
    cfg = Config(task=task, variant=variant, preset=preset, own_settings=own, reference=reference)
    cfg.context.num_prototypes = task_num_prototypes(task)
    model_free = cfg.spec.family == "model_free"
    presets = _MODEL_FREE_PRESET_OVERRIDES if model_free else _PRESET_OVERRIDES
    if preset not in presets:
        raise ConfigError(f"preset {preset!r} does not apply to variant {variant!r}; valid: "
                          f"{sorted(presets)}")
    if not model_free:
        apply_overrides(cfg, REFERENCE_SETTINGS[reference], validate=False)
    if own:
        apply_overrides(cfg, VARIANT_OWN_SETTINGS.get(variant, {}), validate=False)
    apply_overrides(cfg, presets[preset], validate=False)
    apply_overrides(cfg, overrides, validate=False)
    if model_free and "train.seq_len" not in overrides:
        cfg.train.seq_len = cfg.drq.frame_stack + 1  # structural: a stack and the next one
    cfg.validate()
    return cfg


def resolve_key(cfg: Config, key: str) -> str:
    """'lr' -> 'world_model.lr' when exactly one section has the field (a top-level field or a
    dotted key is returned as it is); an ambiguous bare key is a ConfigError naming the choices."""
    if "." in key or key in {f.name for f in dataclasses.fields(cfg)}:
        return key
    hits = [f.name for f in dataclasses.fields(cfg) if dataclasses.is_dataclass(getattr(cfg, f.name))
            and key in {g.name for g in dataclasses.fields(getattr(cfg, f.name))}]
    if len(hits) > 1:
        raise ConfigError(f"config key {key!r} is ambiguous: use one of "
                          + ", ".join(f"{h}.{key}" for h in hits))
    return f"{hits[0]}.{key}" if hits else key


def apply_overrides(cfg: Config, overrides: Mapping[str, Any], validate: bool = True) -> Config:
    """Set 'section.field' (or top-level 'field', or a bare field name that only one section
    has) keys in place, with type checks (and the whole config's checks after the last one
    unless validate=False). The one way every entry point (make_config, --set, a config file)
    changes a config."""
    for key, value in overrides.items():
        if isinstance(cfg, Config):
            key = resolve_key(cfg, key)
        parts = key.split(".")
        obj: Any = cfg
        for i, name in enumerate(parts):
            fields = {f.name: f for f in dataclasses.fields(obj)}
            if name not in fields:
                prefix = ".".join(parts[:i])
                valid = sorted(fields) if not prefix else [f"{prefix}.{n}" for n in sorted(fields)]
                raise ConfigError(f"unknown config key {key!r}; valid keys here: {valid}")
            if i == len(parts) - 1:
                f = fields[name]
                if dataclasses.is_dataclass(getattr(obj, name)):
                    if not isinstance(value, Mapping):
                        raise ConfigError(f"{key!r} is a section; give 'section.field' keys")
                    apply_overrides(getattr(obj, name), value, validate=False)
                else:
                    setattr(obj, name, _coerce(value, f.type, key, getattr(obj, name)))
            else:
                obj = getattr(obj, name)
                if not dataclasses.is_dataclass(obj):
                    raise ConfigError(f"unknown config key {key!r}: {name!r} is not a section")
    if validate and isinstance(cfg, Config):
        cfg.validate()
    return cfg


def _coerce(value: Any, type_name: Any, key: str, current: Any) -> Any:
    """Check/convert a leaf value to the field's type (annotations are strings here)."""
    t = type_name if isinstance(type_name, str) else getattr(type_name, "__name__", str(type_name))
    try:
        if t == "bool":
            if isinstance(value, bool):
                return value
            if isinstance(value, str) and value.lower() in ("true", "false", "1", "0"):
                return value.lower() in ("true", "1")
            if isinstance(value, int) and value in (0, 1):
                return bool(value)
            raise TypeError
        if t == "int":
            if isinstance(value, bool):
                raise TypeError
            if isinstance(value, float) and not value.is_integer():
                raise TypeError
            return int(value)
        if t == "float":
            if isinstance(value, bool):
                raise TypeError
            return float(value)
        if t == "str":
            if not isinstance(value, str):
                raise TypeError
            return value
    except (TypeError, ValueError):
        raise ConfigError(f"config key {key!r} expects {t}, got {value!r}") from None
    return value


def _build(cls: type, d: Mapping[str, Any], prefix: str) -> Any:
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(d) - set(fields))
    if unknown:
        where = f" in section {prefix.rstrip('.')!r}" if prefix else ""
        raise ConfigError(f"unknown config key(s) {[prefix + k for k in unknown]}{where}; "
                          f"valid: {sorted(fields)}")
    kwargs = {}
    default = cls()
    for name, f in fields.items():
        if name not in d:
            continue
        value = d[name]
        sub = getattr(default, name)
        if dataclasses.is_dataclass(sub):
            if not isinstance(value, Mapping):
                raise ConfigError(f"config section {prefix + name!r} must be a mapping")
            kwargs[name] = _build(type(sub), value, f"{prefix}{name}.")
        else:
            kwargs[name] = _coerce(value, f.type, prefix + name, sub)
    return cls(**kwargs)
