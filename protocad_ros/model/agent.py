"""The ProtoCAD agent and its baselines: world model + context module + actor-critic (no ROS).

    agent = Agent(make_config("pendulum_swingup", "small"), action_dim=1)
    metrics = agent.train_step(batch)      # one world-model + behaviour update (Algorithm 1)

batch (numpy or torch): image uint8 (B, T, 64, 64, 3); action float32 (B, T, A) = the action
that LED TO o_t (zeros where is_first); reward float32 (B, T) = reward arriving with o_t;
discount float32 (B, T); is_first bool (B, T).

One update (variant 'protocad'; the others switch parts off, see WorldModel):
  1. two views o^(1), o^(2) = random_shift(o) (one shift per sequence, bilinear)
  2. s^(1) = RSSM posterior of view 1 (with grad); s^(2) of view 2 (no grad: it only feeds the
     EMA target projector, whose Sinkhorn targets carry no gradient anyway)
  3. u, w, e = ContextModule.features(s^(1)); x = (s, u, e)
  4. J_ProtoCAD = KL(post || prior) + image NLL(decoder(x)) + reward NLL(reward(s)) + TC-SwAV
     -> one Adam step on encoder, RSSM, decoder, reward head, projector and prototypes
     (prototype gradient dropped for the first 10k updates); then the EMA target projector
     update and prototype re-normalisation
  5. imagination from every posterior state of view 1 (detached), actor and critic losses with
     the world model frozen; separate Adam steps; slow-critic refresh.
"""
from __future__ import annotations

import copy
from typing import Any, Mapping

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from protocad_ros.model.agent_base import BATCH_KEYS, AgentBase, frozen
from protocad_ros.model.augment import random_shift
from protocad_ros.model.behavior import ActorCritic, ImagineFns
from protocad_ros.model.config import Config
from protocad_ros.model.networks import MLP, ConvDecoder, ConvEncoder, init_weights
from protocad_ros.model.prototypes import ContextModule, sinkhorn_knopp
from protocad_ros.model.rssm import RSSM, State, detach_state, flatten_state

__all__ = ["Agent", "WorldModel", "DreamerProPrototypes", "BATCH_KEYS", "frozen"]


def _nll_image(mean: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """-log N(target; mean, 1) summed over pixels, up to the constant: (...)."""
    return 0.5 * (mean.float() - target.float()).pow(2).sum((-3, -2, -1))


# ------------------------------------------------------------------------------------------------
# DreamerPro baseline: prototypes as a representation loss only
# ------------------------------------------------------------------------------------------------
class DreamerProPrototypes(nn.Module):
    """DreamerPro's (Deng et al., ICML 2022) reconstruction-free prototypical representation.

    Both augmented views go through encoder + RSSM (concatenated on the batch axis). With a
    projection of the observation embedding (obs_proj), of the RSSM state (feat_proj), K
    prototypes, and Sinkhorn targets from an EMA copy of encoder + obs_proj (per view):
        swav = cross-view SwAV between the two views' observation projections
        temp = RSSM state of view i predicts the target of its own observation (temporal loss)
        norm = (||obs_proj|| - 1)^2 + (||feat_proj|| - 1)^2
    The first `drop_first_steps` steps are left out of the scores (DreamerPro warm_up).
    Nothing from here reaches the actor/critic: DreamerPro's policy reads x = s.
    """

    def __init__(self, encoder: ConvEncoder, feat_dim: int, cfg: Config):
        super().__init__()
        c = cfg.context
        self.cfg = c
        self.num_prototypes, self.proj_dim = c.dreamerpro_num_prototypes, c.proto_dim
        self.obs_proj = nn.Linear(encoder.out_dim, c.proto_dim)
        self.feat_proj = nn.Linear(feat_dim, c.proto_dim)
        self.prototypes = nn.Parameter(F.normalize(torch.randn(self.num_prototypes,
                                                               c.proto_dim), dim=-1))
        self.ema_encoder = copy.deepcopy(encoder).requires_grad_(False)
        self.ema_obs_proj = copy.deepcopy(self.obs_proj).requires_grad_(False)
        self.register_buffer("ema_updates", torch.zeros((), dtype=torch.long))
        self.freeze_prototypes_steps = max(0, c.freeze_prototypes_updates)   # -1 (auto) unresolved: 0

    @torch.no_grad()
    def normalize_prototypes(self) -> None:
        self.prototypes.copy_(F.normalize(self.prototypes, dim=-1))

    def unit_prototypes(self) -> torch.Tensor:
        return F.normalize(self.prototypes.detach(), dim=-1)

    def mask_frozen_prototype_grad(self, step: int) -> bool:
        if step < self.freeze_prototypes_steps:
            self.prototypes.grad = None
            return True
        return False

    @torch.no_grad()
    def update_target(self, encoder: ConvEncoder) -> None:
        mix = 1.0 if int(self.ema_updates) == 0 else self.cfg.ema
        for src_mod, dst_mod in ((encoder, self.ema_encoder), (self.obs_proj, self.ema_obs_proj)):
            for d, s in zip(dst_mod.parameters(), src_mod.parameters()):
                d.mul_(1 - mix).add_(s, alpha=mix)
        self.ema_updates += 1

    @torch.no_grad()
    def _targets(self, images: torch.Tensor, c: torch.Tensor, keep: slice) -> torch.Tensor:
        """Sinkhorn targets of the EMA projection, separately per view: (2B, T', K)."""
        ema = F.normalize(self.ema_obs_proj(self.ema_encoder(images)).float(), dim=-1)
        scores = ema[:, keep] @ c.t()  # (2B, T', K)
        out = []
        for view in scores.chunk(2, 0):
            B, T, K = view.shape
            out.append(sinkhorn_knopp(view.reshape(B * T, K), self.cfg.sinkhorn_iters,
                                      self.cfg.sinkhorn_eps).reshape(B, T, K))
        return torch.cat(out, 0)

    def loss(self, embed: torch.Tensor, feat: torch.Tensor, images: torch.Tensor,
             step: int) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """embed (2B, T, E), feat (2B, T, S), images (2B, T, 3, 64, 64) of the two views."""
        cfg = self.cfg
        c = self.prototypes.detach() if step < self.freeze_prototypes_steps else self.prototypes
        keep = slice(min(cfg.drop_first_steps, embed.shape[1] - 1), embed.shape[1])
        obs = self.obs_proj(embed).float()
        feat_p = self.feat_proj(feat).float()
        obs_logits = torch.log_softmax(F.normalize(obs, dim=-1)[:, keep] @ c.t()
                                       / cfg.temperature, -1)
        feat_logits = torch.log_softmax(F.normalize(feat_p, dim=-1)[:, keep] @ c.t()
                                        / cfg.temperature, -1)
        targets = self._targets(images, c.detach(), keep)
        t1, t2 = targets.chunk(2, 0)
        o1, o2 = obs_logits.chunk(2, 0)
        swav = -0.5 * (t2 * o1).sum(-1).mean() - 0.5 * (t1 * o2).sum(-1).mean()
        temp = -(targets * feat_logits).sum(-1).mean()
        norm = ((obs.norm(dim=-1) - 1) ** 2).mean() + ((feat_p.norm(dim=-1) - 1) ** 2).mean()
        total = cfg.swav_scale * swav + cfg.dreamerpro_temp_scale * temp \
            + cfg.dreamerpro_norm_scale * norm
        return total, {"swav_loss": swav.detach(), "temp_loss": temp.detach(),
                       "norm_loss": norm.detach()}


# ------------------------------------------------------------------------------------------------
# World model
# ------------------------------------------------------------------------------------------------
class WorldModel(nn.Module):
    """Encoder, RSSM, reward head on s, image decoder on x, context module (per variant).

    features(s) -> x is the variant's latent feature: (s, u, e) for ProtoCAD, s for Dreamer and
    DreamerPro, (s, u) for Dreamer+Context, (s, e) for the w/o-projection ablation.
    """

    def __init__(self, cfg: Config, action_dim: int):
        super().__init__()
        self.cfg, self.variant = cfg, cfg.variant
        wm, ctx = cfg.world_model, cfg.context
        self.encoder = ConvEncoder(wm.cnn_depth, wm.cnn, wm.act, wm.norm)
        self.rssm = RSSM(action_dim, self.encoder.out_dim, wm)
        S = self.rssm.feat_dim
        self.context: ContextModule | None = None
        self.dreamerpro: DreamerProPrototypes | None = None
        if cfg.uses_context:
            self.context = ContextModule.from_config(
                ctx, state_dim=S, temporal_consistency=cfg.spec.representation == "tc_swav")
        elif cfg.spec.representation == "dreamerpro":
            self.dreamerpro = DreamerProPrototypes(self.encoder, S, cfg)
        parts = cfg.features
        self.state_dim = S
        self.feat_dim = S + ctx.proto_dim * (("u" in parts) + ("e" in parts))
        self.context_dims = (ctx.proto_dim, ctx.num_prototypes, ctx.proto_dim) \
            if self.context is not None else (0, 0, 0)
        self.decoder = ConvDecoder(self.feat_dim, wm.cnn_depth, wm.cnn, wm.act, wm.norm) \
            if cfg.uses_decoder else None
        self.reward_head = MLP(S, 1, wm.mlp_layers, wm.mlp_units, wm.act, wm.norm)
        self.discount_head = MLP(S, 1, wm.mlp_layers, wm.mlp_units, wm.act, wm.norm) \
            if wm.discount_head else None

    # ---- features ---------------------------------------------------------------------------------
    @staticmethod
    def preprocess(image: torch.Tensor) -> torch.Tensor:
        """uint8 (..., 64, 64, 3) -> float (..., 3, 64, 64) in [-0.5, 0.5]."""
        return image.movedim(-1, -3).float().div_(255.0).sub_(0.5)

    def context_features(self, s: torch.Tensor):
        """u, w, e of states s (..., S), or (None, None, None) without a context module."""
        if self.context is None:
            return None, None, None
        return self.context.features(s)

    def features(self, s: torch.Tensor, ctx=None) -> torch.Tensor:
        """x_t for the decoder / actor / critic: s plus the variant's context parts."""
        parts = self.cfg.features
        if len(parts) == 1:
            return s
        u, _, e = ctx if ctx is not None else self.context.features(s)
        x = [s]
        if "u" in parts:
            x.append(u.to(s.dtype))
        if "e" in parts:
            x.append(e.to(s.dtype))
        return torch.cat(x, -1)

    def reward(self, s: torch.Tensor) -> torch.Tensor:
        return self.reward_head(s).squeeze(-1).float()

    def discount_prob(self, s: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(self.discount_head(s).squeeze(-1).float())

    # ---- loss ---------------------------------------------------------------------------------------
    def loss(self, batch: Mapping[str, torch.Tensor], step: int):
        """World-model loss of one batch.

        Returns (total loss, dict of the weighted-free loss terms (tensors with grad), posterior
        states (B', T, ...) used as imagination starts, metrics dict of detached tensors).
        """
        cfg, wm = self.cfg, self.cfg.world_model
        image = self.preprocess(batch["image"])  # (B, T, 3, 64, 64)
        action, is_first = batch["action"], batch["is_first"]
        reward = batch["reward"]
        terms: dict[str, torch.Tensor] = {}
        metrics: dict[str, torch.Tensor] = {}

        if self.context is not None:
            self.context.normalize_prototypes()  # unit c_k before any forward (idempotent)
        if self.dreamerpro is not None:
            self.dreamerpro.normalize_prototypes()

        if self.dreamerpro is not None:
            # DreamerPro: both views are training data (batch doubled), no decoder.
            pad = cfg.context.aug_pad
            image = torch.cat([random_shift(image, pad), random_shift(image, pad)], 0)
            action, is_first = torch.cat([action, action], 0), torch.cat([is_first, is_first], 0)
            reward = torch.cat([reward, reward], 0)
            batch = {**batch, "discount": torch.cat([batch["discount"]] * 2, 0)}
        elif cfg.uses_augmentation:
            view2 = random_shift(image, cfg.context.aug_pad)
            image = random_shift(image, cfg.context.aug_pad)  # view 1: the training view

        embed = self.encoder(image)
        post, prior = self.rssm.observe(embed, action, is_first)
        s = self.rssm.get_feat(post)  # (B, T, S)

        kl_loss, kl_value = self.rssm.kl_loss(post, prior, wm.kl_balance, wm.kl_free,
                                              wm.kl_free_avg)
        terms["kl"] = kl_loss
        metrics["kl"] = kl_value.mean()
        # Reward head reads s only (paper eq. 7: the reward is context-independent).
        terms["reward"] = 0.5 * (self.reward(s) - reward.float()).pow(2).mean()
        if self.discount_head is not None:
            terms["discount"] = F.binary_cross_entropy_with_logits(
                self.discount_head(s).squeeze(-1).float(), batch["discount"].float())

        ctx = None
        if self.context is not None:
            with torch.no_grad():  # view 2: targets only
                s2 = self.rssm.get_feat(self.rssm.observe(
                    self.encoder(view2), action, is_first, with_prior=False)[0])
            terms["swav"], swav_metrics = self.context.loss(s, s2, step, is_first)
            metrics.update(swav_metrics)
            ctx = self.context.features(s, train_module=cfg.context.recon_trains_context)
        elif self.dreamerpro is not None:
            terms["swav"], pro_metrics = self.dreamerpro.loss(embed, s, image, step)
            metrics.update(pro_metrics)

        if self.decoder is not None:
            x = self.features(s, ctx)  # decoder reads x: gradients reach u, e -> projector, c_k
            # Target: the view the states were inferred from (view 1).
            terms["image"] = _nll_image(self.decoder(x), image).mean()

        scales = {"kl": wm.kl_scale, "reward": wm.reward_scale, "image": wm.image_scale,
                  "discount": wm.discount_scale, "swav": 1.0 if self.dreamerpro is not None
                  else cfg.context.swav_scale}
        total = sum(scales[k] * v for k, v in terms.items())
        for k, v in terms.items():
            metrics[f"{k}_loss"] = v.detach()
        metrics["wm_loss"] = total.detach()
        with torch.no_grad():
            if self.rssm.classes:
                metrics["post_ent"] = -(post["logit"].exp() * post["logit"]).sum((-2, -1)).mean()
            else:
                metrics["post_std"] = post["std"].mean()
        return total, terms, post, metrics


# ------------------------------------------------------------------------------------------------
# Agent
# ------------------------------------------------------------------------------------------------
class Agent(AgentBase):
    """World model + actor-critic + their optimizers and update counter.

    Agent(cfg, action_dim, device=None): device defaults to cfg.train.device ('cpu').
    Module initialisation is seeded by cfg.train.seed without touching the global RNG.
    """

    def __init__(self, cfg: Config, action_dim: int, device: str | torch.device | None = None):
        super().__init__(cfg, action_dim)
        if cfg.spec.family != "world_model":
            raise ValueError(f"variant {cfg.variant!r} is not a world-model agent; build it with "
                             "protocad_ros.model.agents.make_agent")
        device = torch.device(device if device is not None else cfg.train.device)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(cfg.train.seed)
            self.wm = init_weights(WorldModel(cfg, self.action_dim), cfg.weight_init)
            self.ac = init_weights(ActorCritic(self.wm.feat_dim, self.action_dim, cfg.behavior),
                                   cfg.weight_init)
            self.ac.slow_critic.load_state_dict(self.ac.critic.state_dict())
        self.to(device)
        wm, bh = cfg.world_model, cfg.behavior
        self.wm_opt = self._adam(self.wm.parameters(), wm.lr, wm.eps, wm.weight_decay)
        self.actor_opt = self._adam(self.ac.actor.parameters(), bh.actor_lr, bh.eps,
                                    bh.weight_decay)
        self.critic_opt = self._adam(self.ac.critic.parameters(), bh.critic_lr, bh.eps,
                                     bh.weight_decay)

    @property
    def context_dims(self) -> tuple[int, int, int]:
        return self.wm.context_dims

    def optimizers(self) -> dict[str, torch.optim.Optimizer]:
        return {"world_model": self.wm_opt, "actor": self.actor_opt, "critic": self.critic_opt}

    @property
    def has_decoder(self) -> bool:
        return self.wm.decoder is not None

    # ---- training -----------------------------------------------------------------------------------
    def train_world_model(self, batch: Mapping[str, Any]) -> tuple[State, dict[str, torch.Tensor]]:
        """One world-model update. Returns (detached posterior starts (N, ...), metrics)."""
        batch = self.to_batch(batch)
        step = int(self.updates)
        wm = self.wm
        with self._autocast():
            total, _, post, metrics = wm.loss(batch, step)
        self.wm_opt.zero_grad(set_to_none=True)
        total.backward()
        del total  # the graph is freed by backward; drop the last reference early
        self._sync_grads(self.wm_opt)
        if wm.context is not None:
            wm.context.mask_frozen_prototype_grad(step)
        if wm.dreamerpro is not None:
            wm.dreamerpro.mask_frozen_prototype_grad(step)
        metrics["wm_grad_norm"] = nn.utils.clip_grad_norm_(
            self.wm_opt.param_groups[0]["params"], self.cfg.world_model.grad_clip)
        self.wm_opt.step()
        self.wm_opt.zero_grad(set_to_none=True)  # free the gradients before imagination
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
        bh = self.cfg.behavior
        with frozen(self.wm), self._autocast():
            actor_loss, critic_loss, metrics = self.ac.loss(self.imagine_fns(), start)
        self.actor_opt.zero_grad(set_to_none=True)
        self.critic_opt.zero_grad(set_to_none=True)
        # Disjoint parameter sets (critic input detached): one backward serves both.
        (actor_loss + critic_loss).backward()
        del actor_loss, critic_loss
        self._sync_grads(self.actor_opt, self.critic_opt)
        metrics["actor_grad_norm"] = nn.utils.clip_grad_norm_(
            self.actor_opt.param_groups[0]["params"], bh.grad_clip)
        metrics["critic_grad_norm"] = nn.utils.clip_grad_norm_(
            self.critic_opt.param_groups[0]["params"], bh.grad_clip)
        self.actor_opt.step()
        self.critic_opt.step()
        self.actor_opt.zero_grad(set_to_none=True)
        self.critic_opt.zero_grad(set_to_none=True)
        self.ac.update_slow_critic()
        return metrics

    def train_step(self, batch: Mapping[str, Any]) -> dict[str, float]:
        """One world-model + behaviour update (incl. EMA / prototype / slow-critic updates).

        Returns metrics as floats: kl, image_loss, reward_loss, swav_loss, kl_loss, wm_loss,
        actor_loss, critic_loss, entropy, grad norms, ... (keys present per variant).
        """
        self.train()
        start, metrics = self.train_world_model(batch)
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
            post, _ = self.wm.rssm.observe(embed, b["action"], b["is_first"], sample=sample,
                                           with_prior=False)
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

    def _decode(self, s: torch.Tensor) -> torch.Tensor:
        if self.wm.decoder is None:
            raise ValueError(f"variant {self.cfg.variant!r} has no image decoder "
                             "(DreamerPro is reconstruction-free); check agent.has_decoder")
        with self._autocast():
            ctx = self.wm.context_features(s)
            mean = self.wm.decoder(self.wm.features(s, ctx if ctx[0] is not None else None))
        img = ((mean.float() + 0.5).clamp(0, 1) * 255).round().to(torch.uint8)
        return img.movedim(-3, -1).cpu()

    @torch.no_grad()
    def reconstruct(self, batch: Mapping[str, Any]) -> np.ndarray:
        """Decoder reconstructions of the posterior: uint8 (B, T, 64, 64, 3)."""
        self.eval()
        _, post = self._posterior(batch)
        return self._decode(self.wm.rssm.get_feat(post)).numpy()

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
        ctx_batch = {k: v[:, :context_steps] for k, v in b.items()}
        with self._autocast():
            embed = self.wm.encoder(self.wm.preprocess(ctx_batch["image"]))
            post, _ = self.wm.rssm.observe(embed, ctx_batch["action"], ctx_batch["is_first"],
                                           sample=False, with_prior=False)
            state = {"deter": post["deter"][:, -1], "stoch": post["stoch"][:, -1]}
            feats = []
            for t in range(context_steps, context_steps + H):
                state = self.wm.rssm.img_step(state, b["action"][:, t], sample=False)
                feats.append(self.wm.rssm.get_feat(state))
            s = torch.stack(feats, 1).float()
            reward = self.wm.reward(s)
        window = slice(context_steps, context_steps + H)
        out = {"reward_truth": b["reward"][:, window].float().cpu().numpy(),
               "reward_prediction": reward.float().cpu().numpy()}
        if images:
            out["prediction"] = self._decode(s).numpy()
            out["truth"] = b["image"][:, window].cpu().numpy()
        return out

    def set_prototype_freeze(self, updates: int) -> bool:
        mods = [m for m in (self.wm.context, self.wm.dreamerpro) if m is not None]
        for m in mods:
            m.freeze_prototypes_steps = max(0, int(updates))
        return bool(mods)

    def prototypes(self) -> torch.Tensor | None:
        """(K, D) unit-norm prototypes (ProtoCAD variants and DreamerPro), else None."""
        if self.wm.context is not None:
            return self.wm.context.unit_prototypes().cpu()
        if self.wm.dreamerpro is not None:
            return self.wm.dreamerpro.unit_prototypes().cpu()
        return None
