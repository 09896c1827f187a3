"""Starting a run from a policy file (`--init-policy` of protocad-loop and protocad-online): the
policy's config with the run's training options on top, and an agent holding its weights.

One change of the networks is allowed: context.projector_input (what the context projector
reads, s or h) sets only the projector's input width, so a policy trained at the paper's
projector can train on at another; the projector and its EMA target then start fresh (said in
one line), every other weight comes from the policy. Anything else that changes the networks
is refused. No ROS."""
from __future__ import annotations

import copy
from pathlib import Path
from typing import Any, Mapping, Sequence

from protocad_ros.checkpoint.agent_file import read_checkpoint
from protocad_ros.checkpoint.files import CheckpointError, architecture_differences
from protocad_ros.model.agent import make_agent
from protocad_ros.model.config import Config, apply_overrides
from trainer import run_config, settings

#: Network changes a run may make to the policy it starts from, and the weights each makes fresh.
FRESH_ON_CHANGE: dict[str, tuple[str, ...]] = {
    "context.projector_input": ("wm.context.projector.", "wm.context.target_projector."),
}


def policy_config(init_policy: Path, model: settings.ModelChoice, *, config_args: Sequence[str], prog: str,
                  overrides: Mapping[str, Any] | None = None, other_model_allowed: bool = False) -> Config:
    """The policy file's config (its networks) with the run's training options on top (--set,
    `overrides`, --batch-size, --seq-len, --seed, --precision, config flags). ValueError for
    --task/--variant/--preset naming another model (unless `other_model_allowed`: the demo's
    defaults) and for an option that changes the networks beyond FRESH_ON_CHANGE."""
    try:
        policy_cfg = Config.from_dict(read_checkpoint(init_policy)["config"])
    except CheckpointError as err:
        raise ValueError(f"--init-policy: {err}") from None
    m = model
    asked = {"task": m.task, "variant": m.variant, "preset": m.preset}
    other = [f"--{k} {v} (the policy's: {getattr(policy_cfg, k)})" for k, v in asked.items()
             if v is not None and v != getattr(policy_cfg, k)]
    if other and not other_model_allowed:
        raise ValueError(f"--init-policy {init_policy} is another model than "
                         + ", ".join(other) + ": leave them out, the policy's config is the run's")
    train = {"train.seed": m.seed, **({"train.batch_size": m.batch_size} if m.batch_size else {}),
             **({"train.seq_len": m.seq_len} if m.seq_len else {})}
    if m.precision:   # the request; the policy's own (a shipped bf16 one) is a request too
        train["train.precision"] = m.precision
    cfg = apply_overrides(copy.deepcopy(policy_cfg), {**run_config.parse_set(m.set), **(overrides or {}), **train})
    if config_args:
        cfg = run_config.apply_config_flags(cfg, list(config_args), prog)
    diffs = [d for d in architecture_differences(policy_cfg, cfg) if d.split(":")[0] not in FRESH_ON_CHANGE]
    if diffs:
        raise ValueError(f"--init-policy {init_policy}: these options change its networks: " + "; ".join(diffs))
    return cfg


def fresh_weights(policy_cfg: Config, cfg: Config) -> dict[str, tuple[str, ...]]:
    """The settings of FRESH_ON_CHANGE that `cfg` changes from `policy_cfg`, each with the
    state-dict prefixes it makes start fresh."""
    a, b = policy_cfg.to_dict(), cfg.to_dict()
    return {key: prefixes for key, prefixes in FRESH_ON_CHANGE.items()
            if a[key.split(".")[0]].get(key.split(".")[1]) != b[key.split(".")[0]].get(key.split(".")[1])}


def agent_from_policy(init_policy: Path, cfg: Config, device: str, say=print):
    """An agent of the run's config (its optimizers from the run's learning rates) holding the
    policy's weights (those FRESH_ON_CHANGE names fresh when their setting changed), update
    counter 0 (the run's schedule counts its own updates)."""
    try:
        payload = read_checkpoint(init_policy)
        changed = fresh_weights(Config.from_dict(payload["config"]), cfg)
        fresh = tuple(p for prefixes in changed.values() for p in prefixes)
        agent = make_agent(cfg, int(payload["action_dim"]), device=device)
        weights = {k: v for k, v in payload["modules"].items() if not (fresh and k.startswith(fresh))}
        missing, unexpected = agent.load_state_dict(weights, strict=not fresh)
        left = [k for k in missing if not k.startswith(fresh)] + list(unexpected)
        if left:
            raise RuntimeError("keys that do not match: " + ", ".join(left))
    except (CheckpointError, RuntimeError, KeyError) as err:
        raise ValueError(f"--init-policy {init_policy}: its weights do not load: {err}") from None
    if fresh:
        say(f"--init-policy {init_policy}: {', '.join(changed)} differs from the policy's: "
            f"{', '.join(p.rstrip('.') for p in fresh)} start fresh, every other weight is the policy's", flush=True)
    measure_drift_from_policy(agent, payload["modules"])
    agent.updates.zero_()
    return agent


def measure_drift_from_policy(agent, policy_modules: Mapping[str, Any]) -> None:
    """The health figure "prototypes' cosine to their start" measures from the policy's
    prototypes, where the run started, not from the seeded draw the agent was built with."""
    for name, start in agent.named_buffers():
        if name.endswith("initial_prototypes"):
            start.copy_(policy_modules[name.removesuffix("initial_prototypes") + "prototypes"])
