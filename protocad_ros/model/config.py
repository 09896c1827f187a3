"""The ProtoCAD agent's configuration: one typed tree, built, changed, checked and saved (pure
Python, no ROS). Its values (the variants, each field's default from the paper, the value ranges,
the presets) are data in protocad_ros.model.hyperparameters; this module is what is done with them.

    cfg = make_config("walker_walk", preset="paper", variant="protocad",
                      **{"train.batch_size": 8, "world_model.deter": 128})
    cfg.save("run/config.yaml"); cfg2 = Config.load("run/config.yaml")

Presets: 'paper' (the paper/DreamerPro sizes), 'small' (CPU-sized, for quick runs and tests),
'dreamerv3_sizes' (NM512/dreamerv3-torch dmc_vision sizes: 512 units, 32x32 discrete latents,
CNN depth 32, batch 16 x 64; used by scripts/bench_train.py --dreamerv3-sizes).
Unknown keys are rejected everywhere (overrides, from_dict, load) with the list of valid keys.
Before a run builds its agent: check_train_memory (against this machine's memory) and
plan_prototype_freeze (the prototype freeze scaled to the run's planned updates).
"""
from __future__ import annotations

import dataclasses
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import yaml

from protocad_ros.atomic import atomic_write_text
from protocad_ros.model.hyperparameters import (
    FREEZE_AUTO,
    MODEL_FREE_PRESET_OVERRIDES,
    PAPER_CONTEXT_SETTINGS,
    PRESET_OVERRIDES,
    PRESETS,
    PROJECTOR_INPUTS,
    RANGES,
    REFERENCE_SETTINGS,
    SINKHORN_OVER,
    VARIANT_OWN_SETTINGS,
    VARIANT_TABLE,
    VARIANTS,
    BehaviorConfig,
    ContextConfig,
    DrQConfig,
    TrainConfig,
    VariantSpec,
    WorldModelConfig,
)
from protocad_ros.model.precision import PRECISIONS
from sim_bridge.contract.contexts import TASKS  # pure data (no ROS): the contract's task table


class ConfigError(ValueError):
    """A configuration key or value that does not fit the tree (message lists valid keys)."""


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
    # paper's appendix comparison on standard DMC keeps DreamerV2's settings) or 'paper'
    # (DreamerPro's, with the context module exactly as the paper states it, whatever the
    # context defaults are). REFERENCE_SETTINGS.
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

    def save(self, path: str | os.PathLike, ran: str | None = None) -> Path:
        """Write YAML atomically (tmp file in the same directory + fsync + os.replace): every
        config.yaml is written here. ran: what ran (PrecisionChoice.ran_here()), a comment on
        the train.precision line ('# ran in float32 here (cpu, CPU capability AVX2)')."""
        path = Path(path)
        text = yaml.safe_dump(self.to_dict(), sort_keys=False)
        if ran:
            text = re.sub(r"^(  precision: .*)$", lambda m: f"{m.group(1)}  # {ran}", text, count=1, flags=re.MULTILINE)
        atomic_write_text(path, text)
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
        check(tr.precision in PRECISIONS,
              f"train.precision must be 'auto'|'float32'|'bfloat16', got {tr.precision!r}")
        check(tr.image_size == 64, "only 64x64 images are supported (train.image_size=64)")
        check(tr.render_quality in ("fast", "default"),
              f"train.render_quality must be 'fast'|'default', got {tr.render_quality!r}")
        check(tr.batch_size >= 1 and tr.seq_len >= 2, "train.batch_size >= 1, seq_len >= 2")
        if self.spec.reads_true_context:
            check(tr.world_model_only, f"variant {self.variant!r} reads the true context from the "
                  "logs and has no policy to act with it: set train.world_model_only=true")
        if self.spec.representation != "none":
            # SwAV scores drop the first steps and TC-SwAV needs two halves of >= 1 step.
            check(tr.seq_len - ctx.drop_first_steps >= 2,
                  f"train.seq_len={tr.seq_len} too short for the SwAV loss "
                  f"(drop_first_steps={ctx.drop_first_steps})")
            check(ctx.num_prototypes >= 1 and ctx.proto_dim >= 1, "context sizes must be >= 1")
            check(0.0 < ctx.ema <= 1.0, "context.ema must be in (0, 1]")
            check(ctx.projector_input in PROJECTOR_INPUTS, f"context.projector_input must be one of "
                  f"{PROJECTOR_INPUTS}, got {ctx.projector_input!r}")
            check(ctx.sinkhorn_over in SINKHORN_OVER, f"context.sinkhorn_over must be one of "
                  f"{SINKHORN_OVER}, got {ctx.sinkhorn_over!r}")


# ------------------------------------------------------------------------------------------------
# Checked before anything is built: value ranges (RANGES), the memory a config may plan
# ------------------------------------------------------------------------------------------------
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
            lo, hi, lo_in = RANGES.get(key, (-math.inf, math.inf, True))
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
    default, not a choice (no run here was that long): read it as auto. A saved config from
    before the context settings of 2026-12-07 (its context section whole, without
    projector_input) trained the paper's context module: it reads as that, whatever the
    defaults are now."""
    ctx = d.get("context")
    if not isinstance(ctx, Mapping):
        return d
    if "freeze_prototypes_fraction" not in ctx and ctx.get("freeze_prototypes_updates") == 10000:
        ctx = {**ctx, "freeze_prototypes_updates": FREEZE_AUTO}
    if "drop_first_steps" in ctx and "projector_input" not in ctx:
        ctx = {**{k.split(".", 1)[1]: v for k, v in PAPER_CONTEXT_SETTINGS.items()
                  if k.split(".", 1)[1] not in ctx}, **ctx}
    return {**d, "context": ctx}

# ------------------------------------------------------------------------------------------------
# Construction
# ------------------------------------------------------------------------------------------------
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
    presets = MODEL_FREE_PRESET_OVERRIDES if model_free else PRESET_OVERRIDES
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
