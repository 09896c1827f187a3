"""Agent checkpoints, the part that needs torch: one file, versioned, written atomically, loaded
without pickle code.

    save_checkpoint("runs/x/agent.pt", agent, counters={"env_steps": 12000})
    agent, counters = load_checkpoint("runs/x/agent.pt", device="cpu")

File = torch.save of one dict (tensors, numbers, strings, lists and dicts only, so it loads with
torch.load(weights_only=True)):
    format "protocad-ros/agent-checkpoint", version 1, config (Config.to_dict()), action_dim,
    modules (agent.state_dict(): world model, context module, actor, critic, slow critic,
    update counter), optimizers (world_model / actor / critic state dicts), agent_counters,
    counters (the caller's: env steps, episodes, ...), torch_rng (optional).
A `config.yaml` with the same config is written beside the file (for humans and tools).

A policy file (`save_policy`) is the same format without optimizer states and RNG, its weights
stored in bfloat16 (a quarter of a training checkpoint), with a `provenance` mapping (where it
was trained, with what, how it scored): what the project ships. It loads like any checkpoint
(weights back in float32, fresh optimizers), so it is served, evaluated and trained on from.

A file may come from elsewhere (a policy node receives them over ROS), so loading checks before
it allocates: the weights' shapes against the config's, on torch's meta device (a config that
asks for huge networks costs nothing there), and, with `fits`, the caller's own conditions (a
policy node: the task and architecture it serves). Only the trainer's resume takes the file's
torch RNG state (`restore_rng`); a served checkpoint never changes its process's RNG.

Writes go to a temporary file in the same directory, are flushed and fsync'ed, and replace the
target with os.replace: a crash leaves either the old or the new checkpoint, never half of one.
Every failure to read (truncated/corrupt, not ours, other version, config or action size that
does not fit) is a CheckpointError that says which file and what is wrong.
"""
from __future__ import annotations

import io
import json
import os
import time
import zipfile
from pathlib import Path
from typing import Any, Callable, Mapping

import torch

from protocad_ros.atomic import atomic_open, atomic_write_text
from protocad_ros.checkpoint.files import (
    CONFIG_NAME,
    FORMAT,
    VERSION,
    CheckpointError,
    architecture_differences,
    read_bounded,
)
from protocad_ros.checkpoint.limits import (
    CheckpointLimitError,
    check_archive,
    check_implied_size,
    check_top_level_keys,
    max_checkpoint_bytes,
)
from protocad_ros.model.agent import make_agent
from protocad_ros.model.agent_base import AgentBase
from protocad_ros.model.config import Config, ConfigError

__all__ = ["save_checkpoint", "save_policy", "read_provenance", "load_checkpoint", "restore_checkpoint",
           "read_checkpoint"]

def save_checkpoint(path: str | os.PathLike, agent: AgentBase, counters: Mapping[str, Any] | None = None,
                    rng_state: bool = False) -> Path:
    """Write the agent (config, weights, optimizer states, counters) to `path` atomically,
    and its config to `config.yaml` beside it. Returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    counters = dict(counters or {})
    for k, v in counters.items():
        if not isinstance(v, (int, float, str, bool)):
            raise TypeError(f"counter {k!r} must be a number or string, got {type(v).__name__}")
    payload = {
        "format": FORMAT,
        "version": VERSION,
        "created_unix": time.time(),
        "config": agent.cfg.to_dict(),
        "action_dim": agent.action_dim,
        "modules": agent.state_dict(),
        "optimizers": {k: opt.state_dict() for k, opt in agent.optimizers().items()},
        "agent_counters": agent.counters(),
        "counters": counters,
    }
    if rng_state:
        payload["torch_rng"] = torch.get_rng_state()
    _write(path, payload)
    agent.cfg.save(path.parent / CONFIG_NAME, ran=agent.precision.ran_here())
    return path


def save_policy(path: str | os.PathLike, agent: AgentBase, provenance: Mapping[str, Any],
                dtype: torch.dtype = torch.bfloat16) -> Path:
    """Write the agent's weights alone (floating tensors in `dtype`; no optimizer states, no
    RNG) with `provenance` (strings, numbers, lists and mappings of them), atomically, and the
    same provenance and config as JSON beside it (PATH with .json: a policy directory may hold
    several, so no shared config.yaml)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    modules = {k: v.detach().to("cpu", dtype) if v.is_floating_point() else v.detach().cpu()
               for k, v in agent.state_dict().items()}
    payload = {"format": FORMAT, "version": VERSION, "created_unix": time.time(),
               "config": agent.cfg.to_dict(), "action_dim": agent.action_dim, "modules": modules,
               "agent_counters": agent.counters(), "counters": {},
               "provenance": dict(provenance)}
    _write(path, payload)
    atomic_write_text(path.with_suffix(".json"), json.dumps(
        {"provenance": payload["provenance"], "config": payload["config"]}, indent=1) + "\n")
    return path


def read_provenance(path: str | os.PathLike) -> dict[str, Any]:
    """A checkpoint's `provenance` ({} for a training checkpoint, which has none)."""
    return dict(read_checkpoint(Path(path)).get("provenance") or {})


def _write(path: Path, payload: Mapping[str, Any]) -> None:
    # Serialized in memory first: torch's zip writer reports a failed file write as a
    # RuntimeError ("unexpected pos"); written as one buffer, a full disk is an OSError.
    buf = io.BytesIO()
    torch.save(dict(payload), buf)
    with atomic_open(path, "wb") as f:
        f.write(buf.getbuffer())


def read_checkpoint(path: str | os.PathLike, data: bytes | None = None,
                    max_bytes: int | None = None) -> dict[str, Any]:
    """The raw checkpoint dict (tensors on CPU), after the archive's limits
    (limits.py: checked on its zip directory, before anything is expanded)
    and the format and version checks. `data`: the file's bytes as the caller read (and
    verified) them; then the file is not read again."""
    return _read(Path(path), max_bytes, data)[0]


def _read(path: Path, max_bytes: int | None, data: bytes | None = None) -> tuple[dict[str, Any], int]:
    """(payload, bytes of its tensor entries): every load path's one reader. max_bytes: None
    = $PROTOCAD_MAX_CHECKPOINT_BYTES or 512 MiB (limits.max_checkpoint_bytes)."""
    try:
        max_bytes = max_checkpoint_bytes(max_bytes)
    except CheckpointLimitError as err:
        raise CheckpointError(str(err)) from None
    if data is None:
        data = read_bounded(path, max_bytes)
    elif len(data) > max_bytes:
        raise CheckpointError(f"{path}: {len(data)} bytes, more than the limit of {max_bytes} (max_checkpoint_bytes)")
    if not data:
        raise CheckpointError(f"{path}: empty file (an interrupted write?)")
    if not zipfile.is_zipfile(io.BytesIO(data)):
        kind = "truncated or corrupt" if data[:4] == b"PK\x03\x04" else "not a checkpoint"
        raise CheckpointError(f"{path}: {kind}: not a complete torch.save archive")
    try:
        tensor_bytes = check_archive(path, data, max_bytes)
    except CheckpointLimitError as err:
        raise CheckpointError(str(err)) from None
    try:
        payload = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except Exception as err:  # noqa: BLE001 - any unpickling failure means an unusable file
        raise CheckpointError(f"{path}: corrupt or foreign checkpoint: cannot be loaded with "
                              f"weights_only=True ({type(err).__name__}: {err})") from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        what = payload.get("format") if isinstance(payload, dict) else type(payload).__name__
        raise CheckpointError(f"{path}: not a protocad-ros agent checkpoint (format {what!r}, "
                              f"expected {FORMAT!r})")
    version = payload.get("version")
    if version != VERSION:
        raise CheckpointError(f"{path}: checkpoint format version {version!r} is not supported "
                              f"by this code (version {VERSION})")
    for key in ("config", "action_dim", "modules"):   # optimizers: not in a policy file
        if key not in payload:
            raise CheckpointError(f"{path}: checkpoint is missing {key!r}")
    try:
        check_top_level_keys(path, payload)
    except CheckpointLimitError as err:
        raise CheckpointError(str(err)) from None
    return payload, tensor_bytes


def _config(path: Path, payload: Mapping[str, Any]) -> Config:
    try:
        return Config.from_dict(payload["config"])
    except ConfigError as err:
        raise CheckpointError(f"{path}: incompatible config in checkpoint: {err}") from None


def _load_into(path: Path, agent: AgentBase, payload: Mapping[str, Any],
               restore_rng: bool = True, optimizer_states: bool = True) -> dict[str, Any]:
    try:
        agent.load_state_dict(payload["modules"], strict=True)
    except (RuntimeError, KeyError) as err:
        raise CheckpointError(f"{path}: weights do not fit this agent (config "
                              f"{agent.cfg.variant}/{agent.cfg.preset}): {err}") from None
    if "optimizers" not in payload or not optimizer_states:
        return dict(payload.get("counters", {}))   # a policy file, or an agent that only acts
    opts = agent.optimizers()
    if set(payload["optimizers"]) != set(opts):
        raise CheckpointError(f"{path}: optimizer states {sorted(payload['optimizers'])} do not "
                              f"match {sorted(opts)}")
    for name, opt in opts.items():
        try:
            opt.load_state_dict(payload["optimizers"][name])
        except (ValueError, KeyError, RuntimeError) as err:
            raise CheckpointError(f"{path}: {name} optimizer state does not fit: {err}") from None
    if restore_rng and "torch_rng" in payload:
        torch.set_rng_state(payload["torch_rng"])
    return dict(payload.get("counters", {}))


def _action_dim(path: Path, payload: Mapping[str, Any]) -> int:
    dim = payload["action_dim"]
    if isinstance(dim, bool) or not isinstance(dim, int) or dim < 1:
        raise CheckpointError(f"{path}: action_dim must be a whole number >= 1, got {dim!r}")
    return dim


# Config fields that count layers: each layer brings at least one tensor, so a config that asks
# for more than the file has tensors cannot fit it (and would take long to build, even on meta).
_LAYER_COUNTS = (("world_model", "mlp_layers"), ("behavior", "actor_layers"),
                 ("behavior", "critic_layers"), ("drq", "num_conv_layers"), ("drq", "hidden_depth"))


def _check_weights_fit(path: Path, cfg: Config, action_dim: int, payload: Mapping[str, Any],
                       tensor_bytes: int = 0) -> None:
    """CheckpointError unless the file's tensors have the shapes its own config builds, checked
    on the meta device: a config that claims huge sizes is refused without allocating them."""
    modules = payload["modules"]
    if not isinstance(modules, Mapping):
        raise CheckpointError(f"{path}: modules is a {type(modules).__name__}, not a state dict")
    for sec, key in _LAYER_COUNTS:
        n = getattr(getattr(cfg, sec), key)
        if n > len(modules):
            raise CheckpointError(f"{path}: config {sec}.{key}={n} asks for more layers than the "
                                  f"file has tensors ({len(modules)})")
    try:
        with torch.device("meta"):
            shapes = {k: tuple(v.shape) for k, v in make_agent(cfg, action_dim, device="meta").state_dict().items()}
    except Exception as err:  # noqa: BLE001 (a config no agent can be built from)
        raise CheckpointError(f"{path}: its config builds no agent: {type(err).__name__}: {err}") from None
    try:   # more tensor bytes than these weights and their optimizer states: not this file's
        check_implied_size(path, tensor_bytes, shapes)
    except CheckpointLimitError as err:
        raise CheckpointError(str(err)) from None
    theirs = {k: tuple(v.shape) if isinstance(v, torch.Tensor) else None for k, v in modules.items()}
    wrong = [f"{k}: {theirs.get(k, 'missing')} in the file, {shape} from its config"
             for k, shape in shapes.items() if theirs.get(k) != shape]
    wrong += [f"{k}: not built by its config" for k in theirs if k not in shapes]
    if wrong:
        raise CheckpointError(f"{path}: weights do not fit the file's own config "
                              f"({len(wrong)} tensor(s)): " + "; ".join(wrong[:3]))


def load_checkpoint(path: str | os.PathLike, device: str | torch.device = "cpu",
                    action_dim: int | None = None, *,
                    fits: Callable[[Config, int], None] | None = None,
                    restore_rng: bool = True, optimizer_states: bool = True,
                    data: bytes | None = None,
                    max_bytes: int | None = None) -> tuple[AgentBase, dict[str, Any]]:
    """Rebuild the agent from a checkpoint. Returns (agent, counters).

    action_dim, if given, must match the checkpoint's (e.g. the environment's). fits(config,
    action_dim), if given, is called before anything is built and raises (CheckpointMismatch)
    to refuse the file. restore_rng: set torch's global RNG from the file (the trainer's
    exact resume); False for anything that only serves or evaluates it. optimizer_states: load
    the file's optimizer states (training goes on); False for an agent that only acts, whose
    optimizers are then never built. data: the file's bytes,
    already read (and verified) by the caller: loaded from, the file is not read again.
    max_bytes: the largest file (and declared archive contents) accepted
    (limits.py).
    """
    path = Path(path)
    payload, tensor_bytes = _read(path, max_bytes, data)
    cfg = _config(path, payload)
    ckpt_dim = _action_dim(path, payload)
    if action_dim is not None and int(action_dim) != ckpt_dim:
        raise CheckpointError(f"{path}: checkpoint was trained with action_dim={ckpt_dim}, "
                              f"but action_dim={action_dim} was requested")
    if fits is not None:
        fits(cfg, ckpt_dim)
    _check_weights_fit(path, cfg, ckpt_dim, payload, tensor_bytes)
    agent = make_agent(cfg, ckpt_dim, device=device)
    counters = _load_into(path, agent, payload, restore_rng, optimizer_states)
    return agent, counters


def restore_checkpoint(path: str | os.PathLike, agent: AgentBase,
                       max_bytes: int | None = None) -> dict[str, Any]:
    """Load a checkpoint into an existing agent (e.g. a policy node reloading new weights).

    The checkpoint's config must describe the same networks (variant, sizes, action_dim);
    training-only fields (learning rates, batch size, ...) may differ.
    """
    path = Path(path)
    payload, tensor_bytes = _read(path, max_bytes)
    cfg = _config(path, payload)
    _check_weights_fit(path, cfg, _action_dim(path, payload), payload, tensor_bytes)
    if int(payload["action_dim"]) != agent.action_dim:
        raise CheckpointError(f"{path}: checkpoint action_dim={payload['action_dim']} but the "
                              f"agent has action_dim={agent.action_dim}")
    diffs = architecture_differences(agent.cfg, cfg)
    if diffs:
        raise CheckpointError(f"{path}: checkpoint does not fit this agent: " + "; ".join(diffs))
    return _load_into(path, agent, payload)


