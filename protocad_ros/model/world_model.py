"""The world model and its loss (no ROS): encoder, RSSM, reward head on s, image decoder on x,
and the variant's representation loss (ProtoCAD's context module, or DreamerPro's prototypes).

WorldModel.loss for variant 'protocad' (the others switch parts off, as their VariantSpec says):
  1. two views o^(1), o^(2) = random_shift(o) (one shift per sequence, bilinear)
  2. s^(1) = RSSM posterior of view 1 (with grad); s^(2) of view 2 (no grad: it only feeds the
     EMA target projector, whose Sinkhorn targets carry no gradient anyway; with
     context.both_views_train its own predictions learn view 1's targets, with grad)
  3. u, w, e = ContextModule.features(s^(1)); x = (s, u, e)
  4. J_ProtoCAD = KL(post || prior) + image NLL(decoder(x)) + reward NLL(reward(s)) + TC-SwAV
Its optimiser step, and the target and prototype updates after it, are the Agent's
(protocad_ros.model.agent); the posterior states it returns start the imagination there.
"""
from __future__ import annotations

import copy
from typing import Mapping

import torch
import torch.nn as nn
import torch.nn.functional as F

from protocad_ros.model.augment import random_shift
from protocad_ros.model.config import Config
from protocad_ros.model.networks import MLP, ConvDecoder, ConvEncoder
from protocad_ros.model.prototypes import ContextModule, random_unit_prototypes, sinkhorn_knopp
from protocad_ros.model.rssm import RSSM
from sim_bridge.contract.contexts import get_task  # pure data (no ROS): the task's context params

__all__ = ["WorldModel", "DreamerProPrototypes"]


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
        self.prototypes = nn.Parameter(random_unit_prototypes(self.num_prototypes, c.proto_dim))
        self.ema_encoder = copy.deepcopy(encoder).requires_grad_(False)
        self.ema_obs_proj = copy.deepcopy(self.obs_proj).requires_grad_(False)
        self.register_buffer("ema_updates", torch.zeros((), dtype=torch.long))
        self.prototype_freeze = max(0, c.freeze_prototypes_updates)   # -1 (auto) unresolved: 0

    @torch.no_grad()
    def normalize_prototypes(self) -> None:
        self.prototypes.copy_(F.normalize(self.prototypes, dim=-1))

    def unit_prototypes(self) -> torch.Tensor:
        return F.normalize(self.prototypes.detach(), dim=-1)

    def mask_frozen_prototype_grad(self, step: int) -> bool:
        if step < self.prototype_freeze:
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
        c = self.prototypes.detach() if step < self.prototype_freeze else self.prototypes
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
        # The true context (variant dreamer_true_context) enters the RSSM beside the action.
        self.true_context_dim = len(get_task(cfg.task).params) if cfg.spec.reads_true_context else 0
        self.rssm = RSSM(action_dim + self.true_context_dim, self.encoder.out_dim, wm)
        S = self.rssm.feat_dim
        self.context: ContextModule | None = None
        self.dreamerpro: DreamerProPrototypes | None = None
        if cfg.uses_context:
            self.context = ContextModule.from_config(
                ctx, state_dim=self.rssm.deter_dim if ctx.projector_input == "h" else S,
                temporal_consistency=cfg.spec.representation == "tc_swav")
        elif cfg.spec.representation == "dreamerpro":
            self.dreamerpro = DreamerProPrototypes(self.encoder, S, cfg)
        parts = cfg.features
        self.state_dim = S
        self.feat_dim = S + ctx.proto_dim * (("u" in parts) + ("e" in parts)) + self.true_context_dim
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

    def context_input(self, s: torch.Tensor) -> torch.Tensor:
        """What the projector reads of s = (z, h) (..., S): all of it, or h (context.projector_input)."""
        return s[..., self.rssm.stoch_dim:] if self.cfg.context.projector_input == "h" else s

    def context_features(self, s: torch.Tensor):
        """u, w, e of states s (..., S), or (None, None, None) without a context module."""
        if self.context is None:
            return None, None, None
        return self.context.features(self.context_input(s))

    def rssm_action(self, action: torch.Tensor, context: torch.Tensor | None) -> torch.Tensor:
        """The RSSM's action input: a_{t-1}, and the true context beside it for the variant
        that reads one (ValueError without it)."""
        if not self.true_context_dim:
            return action
        if context is None or context.shape[-1] != self.true_context_dim:
            raise ValueError(f"variant {self.variant!r} reads the true context ({self.true_context_dim} "
                             f"values per step) and the batch has " + (
                                 "none" if context is None else f"{context.shape[-1]}"))
        return torch.cat([action, context.to(action.dtype)], -1)

    def features(self, s: torch.Tensor, ctx=None, true_context: torch.Tensor | None = None) -> torch.Tensor:
        """x_t for the decoder / actor / critic: s plus the variant's context parts."""
        parts = self.cfg.features
        if len(parts) == 1:
            return s
        x = [s]
        if "u" in parts or "e" in parts:
            u, _, e = ctx if ctx is not None else self.context_features(s)
            if "u" in parts:
                x.append(u.to(s.dtype))
            if "e" in parts:
                x.append(e.to(s.dtype))
        if "c" in parts:
            if true_context is None:
                raise ValueError(f"variant {self.variant!r} reads the true context; none was given")
            x.append(true_context.to(s.dtype).expand(*s.shape[:-1], self.true_context_dim))
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
        true_context = batch.get("context")
        action, is_first = self.rssm_action(batch["action"], true_context), batch["is_first"]
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
            # View 2 yields the targets only (the paper), or trains the world model too
            # through its own predictions (context.both_views_train, as DreamerPro does).
            with torch.set_grad_enabled(cfg.context.both_views_train and torch.is_grad_enabled()):
                s2 = self.rssm.get_feat(self.rssm.observe(
                    self.encoder(view2), action, is_first, with_prior=False)[0])
            terms["swav"], swav_metrics = self.context.loss(
                self.context_input(s), self.context_input(s2), step, is_first)
            metrics.update(swav_metrics)
            ctx = self.context.features(self.context_input(s),
                                        train_module=cfg.context.recon_trains_context)
        elif self.dreamerpro is not None:
            terms["swav"], pro_metrics = self.dreamerpro.loss(embed, s, image, step)
            metrics.update(pro_metrics)

        if self.decoder is not None:
            x = self.features(s, ctx, true_context)  # decoder reads x: gradients reach u, e -> projector, c_k
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

