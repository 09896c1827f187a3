"""The agents (no ROS): Agent, the world-model variants' (ProtoCAD, its ablations, Dreamer,
DreamerPro: world model + actor-critic, their optimisers and update counter), and make_agent,
the agent of any variant's family (DrQ's in protocad_ros.model.drq).

    agent = make_agent(make_config("pendulum_swingup", "small"), action_dim=1)
    metrics = agent.train_step(batch)      # one world-model + behaviour update (Algorithm 1)

batch (numpy or torch): image uint8 (B, T, 64, 64, 3); action float32 (B, T, A) = the action
that LED TO o_t (zeros where is_first); reward float32 (B, T) = reward arriving with o_t;
discount float32 (B, T); is_first bool (B, T).

One update of the world-model variants:
  1. the world-model loss of the batch (protocad_ros.model.world_model: two augmented views,
     RSSM posteriors, x = (s, u, e), J_ProtoCAD) -> one Adam step on encoder, RSSM, decoder,
     reward head, projector and prototypes (the prototypes get no gradient while they are
     frozen: context.freeze_prototypes_updates); then the EMA target projector update and
     prototype re-normalisation
  2. imagination from every posterior state of view 1 (detached), actor and critic losses with
     the world model frozen (protocad_ros.model.behavior); separate Adam steps; slow-critic
     refresh.
"""
from __future__ import annotations

from typing import Any, Mapping

import numpy as np
import torch
import torch.nn as nn

from protocad_ros.model.agent_base import AgentBase, frozen
from protocad_ros.model.behavior import ActorCritic, ImagineFns
from protocad_ros.model.config import Config
from protocad_ros.model.drq import DrQAgent
from protocad_ros.model.networks import init_weights
from protocad_ros.model.rssm import State, detach_state, flatten_state
from protocad_ros.model.world_model import WorldModel

__all__ = ["Agent", "make_agent", "AGENT_FAMILIES"]


class Agent(AgentBase):
    """World model + actor-critic + their optimizers and update counter.

    Agent(cfg, action_dim, device=None): device defaults to cfg.train.device ('cpu').
    Module initialisation is seeded by cfg.train.seed without touching the global RNG.
    """

    def __init__(self, cfg: Config, action_dim: int, device: str | torch.device | None = None):
        super().__init__(cfg, action_dim)
        if cfg.spec.family != "world_model":
            raise ValueError(f"variant {cfg.variant!r} is not a world-model agent; build it with "
                             "make_agent")
        device = torch.device(device if device is not None else cfg.train.device)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(cfg.train.seed)
            self.wm = init_weights(WorldModel(cfg, self.action_dim), cfg.weight_init)
            self.ac = init_weights(ActorCritic(self.wm.feat_dim, self.action_dim, cfg.behavior),
                                   cfg.weight_init)
            self.ac.slow_critic.load_state_dict(self.ac.critic.state_dict())
        self.to(device)

    @property
    def context_dims(self) -> tuple[int, int, int]:
        return self.wm.context_dims

    def _make_optimizers(self) -> dict[str, torch.optim.Optimizer]:
        wm, bh = self.cfg.world_model, self.cfg.behavior
        return {"world_model": self._adam(self.wm.parameters(), wm.lr, wm.eps, wm.weight_decay),
                "actor": self._adam(self.ac.actor.parameters(), bh.actor_lr, bh.eps, bh.weight_decay),
                "critic": self._adam(self.ac.critic.parameters(), bh.critic_lr, bh.eps,
                                     bh.weight_decay)}

    @property
    def has_decoder(self) -> bool:
        return self.wm.decoder is not None

    # ---- training -----------------------------------------------------------------------------------
    def train_world_model(self, batch: Mapping[str, Any]) -> tuple[State, dict[str, torch.Tensor]]:
        """One world-model update. Returns (detached posterior starts (N, ...), metrics)."""
        batch = self.to_batch(batch)
        step = int(self.updates)
        wm, opt = self.wm, self.optimizers()["world_model"]
        with self._autocast():
            total, _, post, metrics = wm.loss(batch, step)
        opt.zero_grad(set_to_none=True)
        total.backward()
        del total  # the graph is freed by backward; drop the last reference early
        self._sync_grads(opt)
        if wm.context is not None:
            wm.context.mask_frozen_prototype_grad(step)
        if wm.dreamerpro is not None:
            wm.dreamerpro.mask_frozen_prototype_grad(step)
        metrics["wm_grad_norm"] = nn.utils.clip_grad_norm_(
            opt.param_groups[0]["params"], self.cfg.world_model.grad_clip)
        opt.step()
        opt.zero_grad(set_to_none=True)  # free the gradients before imagination
        if wm.context is not None:
            wm.context.update_target()  # EMA of the projector after the optimizer step
            wm.context.normalize_prototypes()
        if wm.dreamerpro is not None:
            wm.dreamerpro.update_target(wm.encoder)
            wm.dreamerpro.normalize_prototypes()
        start = detach_state(flatten_state({k: post[k] for k in ("deter", "stoch")}))
        return start, metrics

    def imagine_fns(self) -> ImagineFns:
        wm = self.wm
        return ImagineFns(
            step=lambda state, a: wm.rssm.img_step(state, a),
            state_feat=wm.rssm.get_feat,
            features=wm.features,
            reward=wm.reward,
            discount=wm.discount_prob if wm.discount_head is not None else None)

    def train_behavior(self, start: State) -> dict[str, torch.Tensor]:
        """One actor + critic update from imagined rollouts of the (detached) start states.

        The world model (incl. projector and prototypes) is frozen: no weight gradients there.
        """
        bh, opts = self.cfg.behavior, self.optimizers()
        actor_opt, critic_opt = opts["actor"], opts["critic"]
        with frozen(self.wm), self._autocast():
            actor_loss, critic_loss, metrics = self.ac.loss(self.imagine_fns(), start)
        actor_opt.zero_grad(set_to_none=True)
        critic_opt.zero_grad(set_to_none=True)
        # Disjoint parameter sets (critic input detached): one backward serves both.
        (actor_loss + critic_loss).backward()
        del actor_loss, critic_loss
        self._sync_grads(actor_opt, critic_opt)
        metrics["actor_grad_norm"] = nn.utils.clip_grad_norm_(
            actor_opt.param_groups[0]["params"], bh.grad_clip)
        metrics["critic_grad_norm"] = nn.utils.clip_grad_norm_(
            critic_opt.param_groups[0]["params"], bh.grad_clip)
        actor_opt.step()
        critic_opt.step()
        actor_opt.zero_grad(set_to_none=True)
        critic_opt.zero_grad(set_to_none=True)
        self.ac.update_slow_critic()
        return metrics

    def train_step(self, batch: Mapping[str, Any]) -> dict[str, float]:
        """One world-model + behaviour update (incl. EMA / prototype / slow-critic updates).

        Returns metrics as floats: kl, image_loss, reward_loss, swav_loss, kl_loss, wm_loss,
        actor_loss, critic_loss, entropy, grad norms, ... (keys present per variant).
        """
        self.train()
        start, metrics = self.train_world_model(batch)
        if not self.cfg.train.world_model_only:
            metrics.update(self.train_behavior(start))
        self.updates += 1
        out = self.metrics_to_floats(metrics, self.device)
        out["updates"] = float(int(self.updates))
        return out

    # ---- acting (single-step filter, used by Policy) ----------------------------------------------
    def initial_state(self, batch_size: int) -> State:
        s = self.wm.rssm.initial(batch_size, self.device)
        return {"deter": s["deter"], "stoch": s["stoch"]}

    @torch.no_grad()
    def observe_step(self, state: State | None, image: torch.Tensor, prev_action: torch.Tensor,
                     is_first: torch.Tensor, sample: bool = False,
                     generator: torch.Generator | None = None):
        """Filter one step: (state, image uint8 (B, 64, 64, 3), a_{t-1} (B, A), is_first (B,))
        -> (new state, x (B, X), (u, w, e) or (None, None, None)). sample=False takes the
        posterior mean / mode (deterministic)."""
        if self.wm.true_context_dim:
            raise ValueError(f"variant {self.cfg.variant!r} reads the true context and trains no "
                             "policy: it is the world-model study's ceiling, it does not act")
        B = image.shape[0]
        if state is None:
            state = self.initial_state(B)
        with self._autocast():
            embed = self.wm.encoder(self.wm.preprocess(image.to(self.device)))
            post, _ = self.wm.rssm.obs_step(state, prev_action.to(self.device, torch.float32),
                                            embed, is_first.to(self.device), sample=sample,
                                            generator=generator, with_prior=False)
            s = self.wm.rssm.get_feat(post)
            ctx = self.wm.context_features(s)
            x = self.wm.features(s, ctx if ctx[0] is not None else None)
        ctx = tuple(c.float() if c is not None else None for c in ctx)
        return {"deter": post["deter"], "stoch": post["stoch"]}, x.float(), ctx

    @torch.no_grad()
    def act(self, x: torch.Tensor, sample: bool = False,
            generator: torch.Generator | None = None) -> torch.Tensor:
        """Actor output in [-1, 1] for features x (B, X): mode, or a sample."""
        with self._autocast():
            dist = self.ac.actor(x)
        return (dist.sample(generator) if sample else dist.mode(generator)).float().clamp(-1, 1)

    # ---- inspection (no grad, no augmentation) -------------------------------------------------
    @torch.no_grad()
    def _posterior(self, batch: Mapping[str, Any], sample: bool = False):
        b = self.to_batch(batch)
        with self._autocast():
            embed = self.wm.encoder(self.wm.preprocess(b["image"]))
            post, _ = self.wm.rssm.observe(embed, self.wm.rssm_action(b["action"], b.get("context")),
                                           b["is_first"], sample=sample, with_prior=False)
        return b, post

    @torch.no_grad()
    def embed_sequences(self, batch: Mapping[str, Any]) -> dict[str, np.ndarray | None]:
        """Posterior features of a batch: s (B, T, S), u (B, T, D), w (B, T, K), e (B, T, D) as
        float32 numpy arrays (posterior means, no augmentation); u/w/e None without a context
        module ('dreamer', 'dreamerpro')."""
        self.eval()
        _, post = self._posterior(batch)
        s = self.wm.rssm.get_feat(post).float()
        u, w, e = self.wm.context_features(s)
        np_ = lambda t: None if t is None else t.float().cpu().numpy()  # noqa: E731
        return {"s": np_(s), "u": np_(u), "w": np_(w), "e": np_(e)}

    def _decode(self, s: torch.Tensor, true_context: torch.Tensor | None = None) -> torch.Tensor:
        if self.wm.decoder is None:
            raise ValueError(f"variant {self.cfg.variant!r} has no image decoder "
                             "(DreamerPro is reconstruction-free); check agent.has_decoder")
        with self._autocast():
            ctx = self.wm.context_features(s)
            mean = self.wm.decoder(self.wm.features(s, ctx if ctx[0] is not None else None, true_context))
        img = ((mean.float() + 0.5).clamp(0, 1) * 255).round().to(torch.uint8)
        return img.movedim(-3, -1).cpu()

    @torch.no_grad()
    def reconstruct(self, batch: Mapping[str, Any]) -> np.ndarray:
        """Decoder reconstructions of the posterior: uint8 (B, T, 64, 64, 3)."""
        self.eval()
        b, post = self._posterior(batch)
        return self._decode(self.wm.rssm.get_feat(post), b.get("context")).numpy()

    @torch.no_grad()
    def open_loop(self, batch: Mapping[str, Any], context_steps: int = 5,
                  horizon: int = 50, images: bool = True) -> dict[str, np.ndarray]:
        """Observe `context_steps` frames, then predict the next frames from the prior with
        the batch's actions (the paper's Figure of 5 context + 50 predicted frames).

        Returns truth and prediction, uint8 (B, H, 64, 64, 3), H = min(horizon, T - context),
        and the rewards that arrived with those frames beside the reward head's prediction,
        reward_truth and reward_prediction float32 (B, H). images=False leaves the frames out
        (the only way to ask a variant without a decoder, DreamerPro, for its rewards).
        """
        self.eval()
        b = self.to_batch(batch)
        T = b["image"].shape[1]
        if not 1 <= context_steps < T:
            raise ValueError(f"context_steps must be in [1, T-1] = [1, {T - 1}], got "
                             f"{context_steps}")
        H = min(horizon, T - context_steps)
        action = self.wm.rssm_action(b["action"], b.get("context"))
        with self._autocast():
            embed = self.wm.encoder(self.wm.preprocess(b["image"][:, :context_steps]))
            post, _ = self.wm.rssm.observe(embed, action[:, :context_steps],
                                           b["is_first"][:, :context_steps], sample=False,
                                           with_prior=False)
            state = {"deter": post["deter"][:, -1], "stoch": post["stoch"][:, -1]}
            feats = []
            for t in range(context_steps, context_steps + H):
                state = self.wm.rssm.img_step(state, action[:, t], sample=False)
                feats.append(self.wm.rssm.get_feat(state))
            s = torch.stack(feats, 1).float()
            reward = self.wm.reward(s)
        window = slice(context_steps, context_steps + H)
        out = {"reward_truth": b["reward"][:, window].float().cpu().numpy(),
               "reward_prediction": reward.float().cpu().numpy()}
        if images:
            true_context = b.get("context")
            out["prediction"] = self._decode(
                s, None if true_context is None else true_context[:, window]).numpy()
            out["truth"] = b["image"][:, window].cpu().numpy()
        return out

    def set_prototype_freeze(self, prototype_freeze: int) -> bool:
        mods = [m for m in (self.wm.context, self.wm.dreamerpro) if m is not None]
        for m in mods:
            m.prototype_freeze = max(0, int(prototype_freeze))
        return bool(mods)

    def prototypes(self) -> torch.Tensor | None:
        """(K, D) unit-norm prototypes (ProtoCAD variants and DreamerPro), else None."""
        if self.wm.context is not None:
            return self.wm.context.unit_prototypes().cpu()
        if self.wm.dreamerpro is not None:
            return self.wm.dreamerpro.unit_prototypes().cpu()
        return None


# ------------------------------------------------------------------------------------------------
# Any variant's agent
# ------------------------------------------------------------------------------------------------
#: VariantSpec.family -> the class that implements it.
AGENT_FAMILIES: dict[str, type[AgentBase]] = {"world_model": Agent, "model_free": DrQAgent}


def make_agent(cfg: Config, action_dim: int,
               device: str | torch.device | None = None) -> AgentBase:
    """A fresh agent for cfg (seeded by cfg.train.seed) with `action_dim` actions."""
    return AGENT_FAMILIES[cfg.spec.family](cfg, action_dim, device=device)
