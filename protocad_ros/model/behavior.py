"""Actor-critic learned in imagination (Dreamer; paper sec. 4.3, eq. 8-9), pure PyTorch.

Imagination (Algorithm 1, lines 14-15): from every posterior state s_0 of the training batch
(detached: behaviour learning never trains the world model), roll the prior forward H steps
with actions from the actor,

    a_t ~ pi(a_t | sg(x_t)),   s_{t+1} = img_step(s_t, a_t),   x_t = features(s_t)

where x_t is the variant's latent feature ((s, u, e) for ProtoCAD).  Targets are lambda-returns
(eq. 8) bootstrapped with the slow critic:

    R_t = r_{t+1} + gamma_{t+1} ((1 - lambda) v(x_{t+1}) + lambda R_{t+1}),   R_{H-1} uses v(x_H)

r_{t+1} = reward head on s_{t+1} (the reward that arrives with the state reached by a_t, the
data's step convention).  DreamerV2 feeds r(s_t) instead; the two differ by a constant per
state that a_t cannot change.

    actor  loss = -mean_t w_t (R_t + eta H[pi(. | x_t)])     (dynamics backprop, DMC)
    critic loss =  mean_t w_t 1/2 (v(sg(x_t)) - sg(R_t))^2   (eq. 9)
    w_t = prod_{i<t} gamma_i (DreamerV2's discount weights)

Only the actor and the critic are trained here: the caller freezes the world model's
parameters (requires_grad=False) while imagining, so the actor's gradient flows *through* the
dynamics, the reward head and the context module to the actions without ever producing a
gradient for their weights.
"""
from __future__ import annotations

import copy
from typing import Callable

import torch
import torch.nn as nn

from protocad_ros.model.hyperparameters import BehaviorConfig
from protocad_ros.model.networks import MLP, ActionHead
from protocad_ros.model.rssm import State

__all__ = ["lambda_return", "ActorCritic", "ImagineFns"]


def lambda_return(reward: torch.Tensor, value: torch.Tensor, discount: torch.Tensor,
                  bootstrap: torch.Tensor, lambda_: float) -> torch.Tensor:
    """Dreamer's TD(lambda) return, time-major (H, ...), computed backwards in time.

    reward[t], discount[t]: reward and discount received when moving from step t to t+1;
    value[t] = v(x_t) (only value[1:] is used: the next values); bootstrap = v(x_H).

        next_value[t] = value[t+1] (t < H-1),  bootstrap (t = H-1)
        R[t] = reward[t] + discount[t] ((1 - lambda) next_value[t] + lambda R[t+1]),
        R[H] := bootstrap

    This is eq. 8's V_lambda: (1 - lambda) sum_n lambda^(n-1) V_N^n + lambda^(H-1) V_N^H.
    """
    if not (reward.shape == value.shape == discount.shape):
        raise ValueError(f"reward {tuple(reward.shape)}, value {tuple(value.shape)}, discount "
                         f"{tuple(discount.shape)} must have the same (H, ...) shape")
    next_value = torch.cat([value[1:], bootstrap[None]], 0)
    inputs = reward + discount * next_value * (1 - lambda_)
    returns = []
    last = bootstrap
    for t in reversed(range(reward.shape[0])):
        last = inputs[t] + discount[t] * lambda_ * last
        returns.append(last)
    return torch.stack(returns[::-1], 0)


class ImagineFns:
    """What imagination needs from the world model (kept apart so behavior.py stays small).

    step(state, action) -> next state (prior); state_feat(state) -> s (N, S) (the reward-head
    input); features(s) -> x (N, X) (the actor/critic input); reward(s) -> (...) and optional
    discount(s) -> (...) probabilities of continuing.
    """

    def __init__(self, step: Callable[[State, torch.Tensor], State],
                 features: Callable[[torch.Tensor], torch.Tensor],
                 state_feat: Callable[[State], torch.Tensor],
                 reward: Callable[[torch.Tensor], torch.Tensor],
                 discount: Callable[[torch.Tensor], torch.Tensor] | None = None):
        self.step, self.features, self.state_feat = step, features, state_feat
        self.reward, self.discount = reward, discount


class ActorCritic(nn.Module):
    """Actor pi(a | x), critic v(x), slow (target) critic; losses from imagined rollouts."""

    def __init__(self, feat_dim: int, action_dim: int, cfg: BehaviorConfig):
        super().__init__()
        self.cfg = cfg
        self.actor = ActionHead(feat_dim, action_dim, cfg.actor_layers, cfg.actor_units, cfg.act,
                                cfg.norm, dist=cfg.actor_dist, min_std=cfg.actor_min_std,
                                init_std=cfg.actor_init_std)
        self.critic = MLP(feat_dim, 1, cfg.critic_layers, cfg.critic_units, cfg.act, cfg.norm)
        # DreamerPro slow_target: a copy used for the lambda-return bootstrap, refreshed every
        # slow_critic_update updates (hard copy with fraction 1). Never trained directly. With
        # slow_critic=False it is refreshed after every update, i.e. it equals the critic; the
        # copy keeps the actor's gradient (which flows through v(x)) off the critic's weights.
        self.slow_critic = copy.deepcopy(self.critic).requires_grad_(False)
        self.register_buffer("updates", torch.zeros((), dtype=torch.long))

    def value(self, x: torch.Tensor, slow: bool = False) -> torch.Tensor:
        return (self.slow_critic if slow else self.critic)(x).squeeze(-1).float()

    # ---- imagination ------------------------------------------------------------------------------
    def imagine(self, fns: ImagineFns, start: State, horizon: int):
        """Roll out `horizon` steps from each of the N start states (detached by the caller).

        Returns x (H+1, N, X) features with gradient through the dynamics, s (H+1, N, S) model
        states, actions (H, N, A), entropy (H, N) and (if needed) log-probs (H, N).
        """
        state = start
        xs, ss, actions, ents, logps = [], [], [], [], []
        need_logp = self.cfg.actor_grad != "dynamics"
        for t in range(horizon + 1):
            s = fns.state_feat(state)
            x = fns.features(s)
            ss.append(s)
            xs.append(x)
            if t == horizon:
                break
            # The actor sees sg(x_t): its gradient comes only through the chosen action.
            dist = self.actor(x.detach())
            action = dist.sample()
            ents.append(dist.entropy())
            if need_logp:
                logps.append(dist.log_prob(action.detach()))
            actions.append(action)
            state = fns.step(state, action)
        return (torch.stack(xs), torch.stack(ss), torch.stack(actions), torch.stack(ents),
                torch.stack(logps) if need_logp else None)

    def loss(self, fns: ImagineFns, start: State) -> tuple[torch.Tensor, torch.Tensor, dict]:
        """(actor loss, critic loss, metrics) from one imagined rollout of every start state.

        The critic loss only reaches the critic (its input is detached); the actor loss reaches
        the actor (through the actions and the frozen dynamics). One backward of their sum
        therefore gives each network exactly its own gradient.
        """
        cfg = self.cfg
        x, s, actions, ent, logp = self.imagine(fns, start, cfg.horizon)
        reward = fns.reward(s[1:]).float()  # (H, N): r_{t+1} = reward head on s_{t+1}
        if fns.discount is not None:
            discount = cfg.discount * fns.discount(s[1:]).float()
        else:
            discount = torch.full_like(reward, cfg.discount)
        value = self.value(x, slow=True)  # (H+1, N), gradient flows into x (dynamics backprop)
        target = lambda_return(reward, value[:-1], discount, value[-1], cfg.lambda_)  # (H, N)
        with torch.no_grad():  # w_t = prod_{i<t} gamma_i
            weight = torch.cumprod(torch.cat([torch.ones_like(discount[:1]), discount[:-1]]), 0)

        v = self.value(x[:-1].detach())  # (H, N) critic on the imagined states, once

        # Actor: maximise the lambda-return (+ entropy bonus).
        if cfg.actor_grad == "dynamics":
            objective = target
        else:
            advantage = (target - v).detach()
            reinforce = logp * advantage
            objective = reinforce if cfg.actor_grad == "reinforce" else \
                cfg.actor_grad_mix * target + (1 - cfg.actor_grad_mix) * reinforce
        actor_loss = -(weight * (objective + cfg.actor_entropy * ent)).mean()

        # Critic: 1/2 squared error to the (fixed) lambda-return targets, eq. 9.
        critic_loss = (weight * 0.5 * (v - target.detach()) ** 2).mean()

        with torch.no_grad():
            metrics = {
                "actor_loss": actor_loss.detach(), "critic_loss": critic_loss.detach(),
                "entropy": ent.mean(), "imag_reward": reward.mean(),
                "imag_return": target.mean(), "value": v.mean(),
                "slow_value": value.mean(), "imag_action_abs": actions.abs().mean(),
            }
        return actor_loss, critic_loss, metrics

    @torch.no_grad()
    def update_slow_critic(self) -> None:
        """Every slow_critic_update calls: slow <- mix * critic + (1 - mix) * slow; a full copy
        on the first call (DreamerPro update_slow_target)."""
        every = self.cfg.slow_critic_update if self.cfg.slow_critic else 1
        if int(self.updates) % every == 0:
            mix = 1.0 if (int(self.updates) == 0 or not self.cfg.slow_critic) \
                else self.cfg.slow_critic_fraction
            for d, s in zip(self.slow_critic.parameters(), self.critic.parameters()):
                d.mul_(1 - mix).add_(s, alpha=mix)
        self.updates += 1
