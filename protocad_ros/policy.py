"""Policy API for the nodes: filter the RSSM state over an episode and answer each observation.

    policy = Policy.from_checkpoint("runs/x/agent.pt", device="cpu", mode="deterministic")
    policy.reset()                                    # batch size 1
    action, feats = policy.act(image, prev_action, is_first)
    # single: image (64, 64, 3) uint8, prev_action (A,), is_first bool -> action (A,)
    # batched: (B, 64, 64, 3), (B, A), (B,) -> (B, A); feats.u (B, D), feats.w (B, K), feats.e

prev_action is a_{t-1}, the action that led to this observation (ignored where is_first: the
state of that batch entry restarts from the initial state). mode 'deterministic' takes the
actor's mode (for tanh_normal the most likely of 100 samples, as DreamerPro's SampleDist);
'sample' samples the actor. The posterior state is sampled in both modes, as DreamerV2 and
DreamerPro evaluate (their `eval_state_mean: False`); state_mean=True filters with its mean
instead. All sampling draws from a generator seeded by `seed` and re-seeded by reset(), so a
policy repeats itself exactly. exploration_noise adds N(0, noise^2) to the action, then clips
to [-1, 1] (Dreamer's exploration). No ROS import here.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from protocad_ros.checkpoint.agent_file import load_checkpoint
from protocad_ros.model.agent_base import AgentBase

__all__ = ["Policy", "ContextFeatures", "SHIPPED_POLICIES", "shipped_policy"]

#: Policies that ship with the package, one per task: TASK.pt (protocad-compare --ship) with
#: TASK.json beside it saying where it was trained and how it scored.
SHIPPED_POLICIES = Path(__file__).resolve().parent / "policies"


def shipped_policy(task: str) -> Path | None:
    """The shipped policy file of `task`, or None where none ships."""
    path = SHIPPED_POLICIES / f"{task}.pt"
    return path if path.is_file() else None


@dataclass
class ContextFeatures:
    """Context features of the current step: u (projection), w (prototype probabilities),
    e (aggregated prototype); float32, size-0 arrays for variants without a context module."""

    u: np.ndarray
    w: np.ndarray
    e: np.ndarray


class Policy:
    MODES = ("deterministic", "sample")

    def __init__(self, agent: AgentBase, device: str | torch.device = "cpu",
                 mode: str = "deterministic", exploration_noise: float = 0.0, seed: int = 0,
                 state_mean: bool = False):
        if mode not in self.MODES:
            raise ValueError(f"mode must be one of {self.MODES}, got {mode!r}")
        if not (np.isfinite(exploration_noise) and exploration_noise >= 0):
            raise ValueError(f"exploration_noise must be a finite number >= 0, got "
                             f"{exploration_noise!r}")
        self.device = torch.device(device)
        self.agent = agent.to(self.device).eval()
        self.mode, self.exploration_noise, self.seed = mode, float(exploration_noise), seed
        self.state_mean = bool(state_mean)
        self.action_dim = agent.action_dim
        self.context_dims = agent.context_dims  # (D, K, D) or (0, 0, 0)
        self._generator = torch.Generator(device=self.device)
        self._np_rng = np.random.default_rng(seed)
        self._state = None
        self._batch_size: int | None = None
        self.reset()

    @classmethod
    def from_checkpoint(cls, path, device: str | torch.device = "cpu", **kwargs: Any) -> "Policy":
        # Serving a file must not reseed this process (the trainer's resume alone takes its RNG).
        agent, _ = load_checkpoint(path, device=device, restore_rng=False, optimizer_states=False)
        return cls(agent, device=device, **kwargs)

    def reset(self, batch_size: int = 1) -> None:
        """Forget the episode(s): the next act() starts from the initial state. Re-seeds the
        sampling generators, so a reset policy repeats itself exactly."""
        if int(batch_size) < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        self._batch_size = int(batch_size)
        self._state = self.agent.initial_state(self._batch_size)
        self._generator.manual_seed(self.seed)
        self._np_rng = np.random.default_rng(self.seed)

    @property
    def batch_size(self) -> int:
        return self._batch_size

    def _inputs(self, image, prev_action, is_first):
        image = np.asarray(image)
        single = image.ndim == 3
        if image.ndim not in (3, 4) or image.shape[-3:] != (64, 64, 3):
            raise ValueError(f"image must be (64, 64, 3) or (B, 64, 64, 3), got {image.shape}")
        if image.dtype != np.uint8:
            raise ValueError(f"image must be uint8 rgb8, got dtype {image.dtype}")
        B = 1 if single else image.shape[0]
        act = np.asarray(prev_action, dtype=np.float32)
        want = (self.action_dim,) if single else (B, self.action_dim)
        if act.shape != want:
            raise ValueError(f"prev_action must have shape {want}, got {act.shape}")
        if not np.isfinite(act).all():
            raise ValueError("prev_action contains NaN or inf")
        first = np.asarray(is_first, dtype=bool)
        if first.shape != (() if single else (B,)):
            raise ValueError(f"is_first must be {'a bool' if single else f'shape ({B},)'}, "
                             f"got shape {first.shape}")
        if single:
            image, act, first = image[None], act[None], first.reshape(1)
        if B != self._batch_size:
            raise ValueError(f"got a batch of {B} but the policy was reset for batch size "
                             f"{self._batch_size}; call reset(batch_size={B}) first")
        return single, image, np.clip(act, -1.0, 1.0), first

    @torch.no_grad()
    def act(self, image, prev_action, is_first) -> tuple[np.ndarray, ContextFeatures]:
        """Answer one observation per batch entry. Returns (action float32 in [-1, 1],
        ContextFeatures) with the input's batching (single or batched)."""
        single, image, act, first = self._inputs(image, prev_action, is_first)
        dev = self.device
        self._state, x, (u, w, e) = self.agent.observe_step(
            self._state, torch.from_numpy(np.ascontiguousarray(image)).to(dev),
            torch.from_numpy(act).to(dev), torch.from_numpy(first).to(dev),
            sample=not self.state_mean, generator=self._generator)
        action = self.agent.act(x, sample=self.mode == "sample",
                                generator=self._generator).cpu().numpy()
        if self.exploration_noise > 0:
            action = action + self._np_rng.normal(0.0, self.exploration_noise, action.shape)
        action = np.clip(action, -1.0, 1.0).astype(np.float32)
        B = action.shape[0]
        to_np = lambda t, n: (t.cpu().numpy().astype(np.float32) if t is not None  # noqa: E731
                              else np.zeros((B, 0), np.float32))
        feats = [to_np(u, 0), to_np(w, 0), to_np(e, 0)]
        if single:
            return action[0], ContextFeatures(*(f[0] for f in feats))
        return action, ContextFeatures(*feats)
