"""DrQ, the paper's model-free baseline (Yarats, Kostrikov & Fergus, ICLR 2021), no ROS.

Soft actor-critic on stacks of the last k = 3 frames, with DrQ's image augmentation aug(o):
replicate-pad by 4 px and crop back at a random integer offset, a new offset per sample and per
draw.  Settings: protocad_ros.model.hyperparameters.DrQConfig (the authors' DMC values).  One update, as in
denisyarats/drq drq.py:

  critic (every update), with K target views o'_k = aug(o') and M critic views o_m = aug(o):
      a'_k ~ pi(. | o'_k)
      y = 1/K sum_k [ r + gamma d ( min(Qbar_1, Qbar_2)(o'_k, a'_k) - alpha log pi(a'_k | o'_k) ) ]
      J_Q = sum_m [ (Q_1(o_m, a) - y)^2 + (Q_2(o_m, a) - y)^2 ]      (means over the batch)
  actor and temperature (every `actor_update_frequency` updates), on o_1:
      a ~ pi(. | o_1)                    (encoder convs detached: only the critic trains them)
      J_pi    = alpha log pi(a | o_1) - min(Q_1, Q_2)(o_1, a)
      J_alpha = alpha (-log pi(a | o_1) - H_target),  H_target = -|A|,  alpha = exp(log_alpha)
  target (every `critic_target_update_frequency` updates):
      Qbar <- (1 - tau) Qbar + tau Q     (encoder convs and head included, tau = 0.01)

The conv layers are shared: the critic owns them, the actor reads their output detached and has
its own head (Linear -> LayerNorm -> tanh), as DrQ ties the actor's convs to the critic's.

Batches are the project's windows (agent_base.batch_to_device) of k + 1 steps: the first k
frames are the observation o, the last k the next observation o', action[k] / reward[k] /
discount[k] the transition between them.  Frames before an is_first inside a window are
replaced by that first frame (DrQ's FrameStack repeats the first frame at a reset), and a window
whose last step is_first is no transition (masked out).
"""
from __future__ import annotations

import copy
import math
from typing import Any, Mapping

import torch
import torch.nn as nn

from protocad_ros.model.agent_base import AgentBase, frozen
from protocad_ros.model.augment import random_crop
from protocad_ros.model.config import Config
from protocad_ros.model.hyperparameters import DrQConfig
from protocad_ros.model.networks import MLP, TanhNormal

__all__ = ["DrQAgent", "PixelEncoder", "DrQActor", "DrQCritic", "stack_frames", "transitions",
           "soft_update", "soft_q_target", "temperature_loss"]


def _orthogonal_init(m: nn.Module) -> None:
    """DrQ's weight_init: orthogonal weights (gain sqrt(2) for convs, ReLU), zero biases."""
    if isinstance(m, nn.Linear):
        nn.init.orthogonal_(m.weight)
        nn.init.zeros_(m.bias)
    elif isinstance(m, nn.Conv2d):
        nn.init.orthogonal_(m.weight, nn.init.calculate_gain("relu"))
        nn.init.zeros_(m.bias)


class PixelEncoder(nn.Module):
    """DrQ's conv trunk: conv 3x3 stride 2, then (layers - 1) x conv 3x3 stride 1, ReLU.
    (N, 3k, 64, 64) floats in [0, 1] -> (N, filters * 25 * 25) at 4 layers."""

    def __init__(self, in_channels: int, filters: int = 32, layers: int = 4, size: int = 64):
        super().__init__()
        convs = [nn.Conv2d(in_channels, filters, 3, stride=2)]
        convs += [nn.Conv2d(filters, filters, 3, stride=1) for _ in range(layers - 1)]
        self.convs = nn.ModuleList(convs)
        side = (size - 3) // 2 + 1 - 2 * (layers - 1)
        if side < 1:
            raise ValueError(f"{layers} conv layers leave nothing of a {size}x{size} image")
        self.out_dim = filters * side * side

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        h = obs
        for conv in self.convs:
            h = torch.relu(conv(h))
        return h.flatten(1)


class EncoderHead(nn.Module):
    """Linear -> LayerNorm -> tanh: DrQ's encoder output of `feature_dim` values."""

    def __init__(self, inp: int, feature_dim: int):
        super().__init__()
        self.fc, self.ln = nn.Linear(inp, feature_dim), nn.LayerNorm(feature_dim)

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        return torch.tanh(self.ln(self.fc(h)))


class DrQActor(nn.Module):
    """Head + ReLU MLP -> squashed Gaussian; log std squashed into [log_std_min, log_std_max]."""

    def __init__(self, conv_dim: int, action_dim: int, d: DrQConfig):
        super().__init__()
        self.head = EncoderHead(conv_dim, d.feature_dim)
        self.trunk = MLP(d.feature_dim, 2 * action_dim, d.hidden_depth, d.hidden_dim, "relu")
        self.log_std_min, self.log_std_max = d.log_std_min, d.log_std_max

    def dist(self, feature: torch.Tensor) -> TanhNormal:
        mu, log_std = self.trunk(feature).float().chunk(2, -1)
        log_std = self.log_std_min + 0.5 * (self.log_std_max - self.log_std_min) * (
            torch.tanh(log_std) + 1)
        return TanhNormal(mu, log_std.exp())

    def forward(self, conv_out: torch.Tensor) -> TanhNormal:
        return self.dist(self.head(conv_out))


class DrQCritic(nn.Module):
    """Head + two ReLU MLP Q-functions on (feature, action): double Q-learning."""

    def __init__(self, conv_dim: int, action_dim: int, d: DrQConfig):
        super().__init__()
        self.head = EncoderHead(conv_dim, d.feature_dim)
        inp = d.feature_dim + action_dim
        self.q1 = MLP(inp, 1, d.hidden_depth, d.hidden_dim, "relu")
        self.q2 = MLP(inp, 1, d.hidden_depth, d.hidden_dim, "relu")

    def forward(self, conv_out: torch.Tensor, action: torch.Tensor):
        x = torch.cat([self.head(conv_out), action.to(conv_out.dtype)], -1)
        return self.q1(x).squeeze(-1).float(), self.q2(x).squeeze(-1).float()


@torch.no_grad()
def soft_update(target: nn.Module, source: nn.Module, tau: float) -> None:
    """target <- (1 - tau) target + tau source, parameter by parameter."""
    for t, s in zip(target.parameters(), source.parameters()):
        t.lerp_(s, tau)


def stack_frames(frames: torch.Tensor) -> torch.Tensor:
    """uint8 (N, k, H, W, 3) -> float (N, 3k, H, W) in [0, 1], frames oldest first (DrQ's
    FrameStack concatenates channels-first frames)."""
    N, k, H, W, C = frames.shape
    return frames.permute(0, 1, 4, 2, 3).reshape(N, k * C, H, W).float().div_(255.0)


def transitions(batch: Mapping[str, torch.Tensor], k: int):
    """(o, a, r, d, o', valid) from windows of k + 1 steps (see the module docstring).

    o, o': uint8 (B, k, H, W, 3); a (B, A); r, d (B,); valid bool (B,).
    """
    image, first = batch["image"], batch["is_first"]
    B, T = first.shape
    if T != k + 1:
        raise ValueError(f"DrQ needs windows of frame_stack + 1 = {k + 1} steps, got {T}")
    pos = torch.arange(T, device=first.device).expand(B, T)
    # Latest episode start at or before each step (0 if none in the window).
    last_first = torch.where(first, pos, torch.zeros_like(pos)).cummax(1).values

    def stack(end: int) -> torch.Tensor:
        src = torch.maximum(pos[:, end - k + 1:end + 1], last_first[:, end:end + 1])  # (B, k)
        return image[torch.arange(B, device=image.device)[:, None], src]

    return (stack(k - 1), batch["action"][:, k], batch["reward"][:, k], batch["discount"][:, k],
            stack(k), ~first[:, k])


def soft_q_target(reward: torch.Tensor, discount: torch.Tensor, q1: torch.Tensor,
                  q2: torch.Tensor, log_prob: torch.Tensor, *, alpha: torch.Tensor | float,
                  gamma: float) -> torch.Tensor:
    """SAC's soft Bellman target y = r + gamma d (min(Qbar_1, Qbar_2)(o', a') - alpha log pi(a'|o'))
    for a' ~ pi(. | o'); d = 0 ends the bootstrap (a terminal state)."""
    return reward + gamma * discount * (torch.minimum(q1, q2) - alpha * log_prob)


def temperature_loss(log_alpha: torch.Tensor, log_prob: torch.Tensor, target_entropy: float,
                     weights: torch.Tensor | None = None) -> torch.Tensor:
    """J_alpha = mean(alpha (-log pi(a|o) - H_target)) (weighted by `weights` if given): alpha
    grows while the policy's entropy -log pi is below the target, and shrinks while above."""
    per_sample = log_alpha.exp() * (-log_prob - target_entropy).detach()
    return per_sample.mean() if weights is None else _masked_mean(per_sample, weights)


def _masked_mean(x: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    return (x * w).sum() / w.sum().clamp(min=1.0)


class DrQAgent(AgentBase):
    """DrQ with the project's agent surface (train_step, observe_step/act, optimizers).

    Modules: conv (the critic's, shared), critic, actor, their targets conv_target and
    critic_target, log_alpha.  Optimisers (Adam, lr 1e-3): critic (conv + critic), actor, alpha.
    """

    def __init__(self, cfg: Config, action_dim: int, device: str | torch.device | None = None):
        super().__init__(cfg, action_dim)
        if cfg.spec.family != "model_free":
            raise ValueError(f"variant {cfg.variant!r} is not DrQ; use make_agent")
        d = self.drq = cfg.drq
        device = torch.device(device if device is not None else cfg.train.device)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(cfg.train.seed)
            self.conv = PixelEncoder(3 * d.frame_stack, d.num_filters, d.num_conv_layers,
                                     cfg.train.image_size)
            self.critic = DrQCritic(self.conv.out_dim, self.action_dim, d)
            self.actor = DrQActor(self.conv.out_dim, self.action_dim, d)
            for m in (self.conv, self.critic, self.actor):
                m.apply(_orthogonal_init)
        self.conv_target = copy.deepcopy(self.conv).requires_grad_(False)
        self.critic_target = copy.deepcopy(self.critic).requires_grad_(False)
        self.log_alpha = nn.Parameter(torch.tensor(math.log(d.init_temperature)))
        self.target_entropy = -float(self.action_dim)
        self.to(device)

    def _make_optimizers(self) -> dict[str, torch.optim.Optimizer]:
        lr = self.drq.lr
        return {"critic": self._adam(list(self.conv.parameters()) + list(self.critic.parameters()), lr),
                "actor": self._adam(self.actor.parameters(), lr),
                "alpha": self._adam([self.log_alpha], lr)}

    @property
    def alpha(self) -> torch.Tensor:
        return self.log_alpha.exp()

    def _aug_views(self, frames: torch.Tensor, n: int) -> list[torch.Tensor]:
        # The global torch RNG (as the world models' shifts): checkpoints carry its state.
        x = stack_frames(frames)
        return [random_crop(x, self.drq.image_pad) for _ in range(n)]

    # ---- training --------------------------------------------------------------------------------
    def critic_loss(self, obs_views, action, reward, discount, next_views, valid):
        """J_Q (sum over the M views and both Q heads of batch means), the target y and Q_1 of
        the first view (a metric)."""
        d = self.drq
        alpha = self.alpha.detach()
        with torch.no_grad(), self._autocast():
            ys = []
            for nxt in next_views:
                next_action, log_prob = self.actor(self.conv(nxt)).sample_log_prob()
                q1, q2 = self.critic_target(self.conv_target(nxt), next_action)
                ys.append(soft_q_target(reward, discount, q1, q2, log_prob, alpha=alpha, gamma=d.discount))
            target = torch.stack(ys).mean(0)
        terms, q1s = [], []
        with self._autocast():
            for obs in obs_views:
                q1, q2 = self.critic(self.conv(obs), action)
                terms += [_masked_mean((q1 - target) ** 2, valid), _masked_mean((q2 - target) ** 2, valid)]
                q1s.append(q1.detach())
        return torch.stack(terms).sum(), target, q1s[0]

    def actor_alpha_loss(self, obs: torch.Tensor, valid: torch.Tensor):
        """J_pi, J_alpha and the entropy estimate -log pi on one view (convs detached)."""
        with torch.no_grad(), self._autocast():
            h = self.conv(obs)
        with self._autocast(), frozen(self.critic):
            action, log_prob = self.actor(h).sample_log_prob()
            q1, q2 = self.critic(h, action)
        actor_loss = _masked_mean(self.alpha.detach() * log_prob - torch.min(q1, q2), valid)
        alpha_loss = temperature_loss(self.log_alpha, log_prob, self.target_entropy, valid)
        return actor_loss, alpha_loss, -log_prob.detach()

    def train_step(self, batch: Mapping[str, Any]) -> dict[str, float]:
        """One DrQ update (critic; actor + temperature and target every 2nd). Returns floats:
        critic_loss, q_target, q1, batch_reward (+ actor_loss, alpha_loss, alpha, entropy)."""
        self.train()
        d, opts = self.drq, self.optimizers()
        b = self.to_batch(batch)
        obs, action, reward, discount, nxt, valid = transitions(b, d.frame_stack)
        w = valid.float()
        obs_views = self._aug_views(obs, d.q_augs)
        critic_loss, target, q1 = self.critic_loss(obs_views, action, reward, discount,
                                                   self._aug_views(nxt, d.target_augs), w)
        opts["critic"].zero_grad(set_to_none=True)
        critic_loss.backward()
        self._sync_grads(opts["critic"])
        opts["critic"].step()
        metrics: dict[str, Any] = {"critic_loss": critic_loss.detach(), "q_target": target.mean(),
                                   "q1": q1.mean(), "batch_reward": reward.mean(),
                                   "valid_transitions": w.sum()}
        step = int(self.updates)
        if step % d.actor_update_frequency == 0:
            actor_loss, alpha_loss, entropy = self.actor_alpha_loss(obs_views[0], w)
            opts["actor"].zero_grad(set_to_none=True)
            actor_loss.backward()
            self._sync_grads(opts["actor"])
            opts["actor"].step()
            opts["alpha"].zero_grad(set_to_none=True)
            alpha_loss.backward()
            self._sync_grads(opts["alpha"])
            opts["alpha"].step()
            metrics.update(actor_loss=actor_loss.detach(), alpha_loss=alpha_loss.detach(),
                           entropy=entropy.mean())
        if step % d.critic_target_update_frequency == 0:
            soft_update(self.conv_target, self.conv, d.critic_tau)
            soft_update(self.critic_target, self.critic, d.critic_tau)
        metrics["alpha"] = self.alpha.detach()
        self.updates += 1
        out = self.metrics_to_floats(metrics, self.device)
        out["updates"] = float(int(self.updates))
        return out

    # ---- acting (used by Policy) ---------------------------------------------------------------
    def initial_state(self, batch_size: int) -> dict[str, torch.Tensor]:
        """The frame stack, empty: the next observation fills every slot."""
        k, size = self.drq.frame_stack, self.cfg.train.image_size
        return {"frames": torch.zeros(batch_size, k, size, size, 3, dtype=torch.uint8,
                                      device=self.device),
                "started": torch.zeros(batch_size, dtype=torch.bool, device=self.device)}

    @torch.no_grad()
    def observe_step(self, state, image: torch.Tensor, prev_action: torch.Tensor,
                     is_first: torch.Tensor, sample: bool = False,
                     generator: torch.Generator | None = None):
        """Push the frame (B, 64, 64, 3) uint8 into the stack (a new episode fills it with this
        frame, as DrQ's FrameStack at reset) -> (state, actor feature (B, feature_dim),
        (None, None, None)). prev_action is not used: DrQ's observation is the frames."""
        B = image.shape[0]
        if state is None:
            state = self.initial_state(B)
        image = image.to(self.device)
        restart = is_first.to(self.device) | ~state["started"]
        frames = torch.cat([state["frames"][:, 1:], image[:, None]], 1)
        frames = torch.where(restart[:, None, None, None, None],
                             image[:, None].expand_as(frames), frames)
        with self._autocast():
            x = self.actor.head(self.conv(stack_frames(frames)))
        state = {"frames": frames, "started": torch.ones_like(state["started"])}
        return state, x.float(), (None, None, None)

    @torch.no_grad()
    def act(self, x: torch.Tensor, sample: bool = False,
            generator: torch.Generator | None = None) -> torch.Tensor:
        """tanh(mu) (DrQ's evaluation action), or a sample of the squashed Gaussian."""
        with self._autocast():
            dist = self.actor.dist(x)
        # DrQ acts with SquashedNormal.mean = tanh(mu), not the most likely sample (its
        # reference differs from DreamerPro's here).
        return (dist.sample(generator) if sample else torch.tanh(dist.mean)).float().clamp(-1, 1)
