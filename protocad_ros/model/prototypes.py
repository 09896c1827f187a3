"""ProtoCAD's prototypical context module (paper sec. 4.2, Algorithm 1), pure PyTorch.

No ROS imports: the agent, the trainer and the policy node all use this file.

Notation (paper -> code), shapes in comments:
    s^(1), s^(2)   posterior RSSM states of the two augmented views       s1, s2  (B, M, S)
    f_theta        linear projector (trained)                            self.projector
    f_thetabar     EMA copy of the projector (never trained)             self.target_projector
    u, ubar        l2-normalized projections                             (B, M, D)
    {c_k}          K trainable, l2-normalized prototypes                 self.prototypes (K, D)
    w              softmax(u . c / T), eq. 3                              (B, M, K)
    wbar           Sinkhorn-Knopp(ubar . c), the targets                  (B, M, K)
    e_t            sum_k w_t,k c_k, aggregated prototype                  (..., D)
    x_t            (s_t, u_t, e_t), the context feature (built by the agent)

Training objective (eq. 5, written as a loss to minimise, i.e. the negative of J_TC-SwAV):
    L = -1/2 [ sum_k wbar_(1),k log w_(2),k + sum_k wbar_(2),k log w_(1),k ]
averaged over sequences and time, where (1)/(2) are the first/second half of the sequence.
The "w/o temporal consistency" ablation pairs each step with itself: -sum_k wbar_t,k log w_t,k.

Call order inside one world-model update (see ContextModule's docstring).
"""
from __future__ import annotations

import copy
import math

import torch
import torch.nn as nn
import torch.nn.functional as F

from protocad_ros.model.augment import random_shift  # (re-export: the two views of Algorithm 1)
from protocad_ros.model.hyperparameters import SINKHORN_OVER

__all__ = [
    "SINKHORN_OVER",
    "sinkhorn_knopp",
    "swav_cross_entropy",
    "tc_swav_loss",
    "swav_loss",
    "same_episode_pairs",
    "context_health",
    "random_unit_prototypes",
    "ContextModule",
    "random_shift",
]


def random_unit_prototypes(num_prototypes: int, dim: int) -> torch.Tensor:
    """(K, D) random directions on the unit sphere, from torch's global RNG (the values
    torch.randn would draw).

    On the meta device (a checkpoint's shapes checked without allocating them) there are no
    values to draw: random and norm ops there run Python references that import sympy and
    torch's compiler (~1.5 CPU-s at every policy-node start), so the empty tensor is returned."""
    c = torch.empty(num_prototypes, dim)
    return c if c.is_meta else F.normalize(c.normal_(), dim=-1)


# ---- Sinkhorn-Knopp (online equipartition clustering, SwAV / DreamerPro) -------------
@torch.no_grad()
def sinkhorn_knopp(scores: torch.Tensor, num_iters: int = 3, eps: float = 0.05) -> torch.Tensor:
    """Soft cluster assignments with equal cluster sizes, computed in log space (no grad).

    scores: (N, K) similarities ubar_n . c_k (N samples = all B*M time steps flattened,
            K prototypes).
    returns Q: (N, K), Q = N * diag(a) exp(scores / eps) diag(b) with a, b chosen by
            alternating normalisation so that every row is a distribution over prototypes
            (rows sum to 1, exactly) and every prototype gets the same total mass
            (column sums N/K, up to the tolerance `num_iters` iterations reach).

    Each iteration is DreamerPro's (there the matrix is (K, N): "rows to 1/K, columns to 1/N"):
        prototype marginals:  Q[:, k] <- Q[:, k] / sum_n Q[n, k] / K     (each cluster 1/K)
        sample marginals:     Q[n, :] <- Q[n, :] / sum_k Q[n, k] / N     (each sample 1/N)
    and finally Q <- N * Q so that each sample's row is a probability vector.  Ending on the
    sample step is what makes the rows exact distributions (they are used as cross-entropy
    targets); the equipartition constraint is the one left approximate.  Log space keeps
    exp(scores / eps) from overflowing (|scores| <= 1, 1 / eps = 20 in the paper, but a
    smaller eps such as DreamerPro's 0.0125 gives exp(80)).
    """
    if scores.dim() != 2:
        raise ValueError(f"sinkhorn_knopp expects scores (N, K), got {tuple(scores.shape)}")
    if num_iters < 1:
        raise ValueError(f"num_iters must be >= 1, got {num_iters}")
    if eps <= 0:
        raise ValueError(f"eps must be > 0, got {eps}")
    N, K = scores.shape
    # (N, K) log of exp(scores / eps); at least float32 (half inputs), float64 kept.
    log_q = scores.detach().to(torch.promote_types(scores.dtype, torch.float32)) / eps
    log_q = log_q - torch.logsumexp(log_q.reshape(-1), dim=0)  # total mass 1 (conditioning)
    for _ in range(num_iters):
        # columns = prototypes: each cluster's total mass -> 1/K (equipartition).
        log_q = log_q - torch.logsumexp(log_q, dim=0, keepdim=True) - math.log(K)
        # rows = samples: each sample's total mass -> 1/N.
        log_q = log_q - torch.logsumexp(log_q, dim=1, keepdim=True) - math.log(N)
    return torch.exp(log_q + math.log(N)).to(scores.dtype)  # (N, K), rows sum to 1


# ---- SwAV-style losses on sequences --------------------------------------------------
def swav_cross_entropy(log_w: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """Cross-entropy of predictions against (Sinkhorn) targets, per sample.

    log_w: (..., K) log-probabilities log w; targets: (..., K) wbar (rows sum to 1).
    returns (...): -sum_k wbar_k log w_k.
    """
    return -(targets * log_w).sum(dim=-1)


def tc_swav_loss(log_w: torch.Tensor, targets: torch.Tensor,
                 pair_mask: torch.Tensor | None = None) -> torch.Tensor:
    """Temporal-crossover SwAV loss (eq. 5), negated to be minimised.

    log_w:   (B, M, K) log w from the online projector on view 1 (predictions).
    targets: (B, M, K) wbar from the target projector on view 2 + Sinkhorn (no grad).
    pair_mask: optional (B, M/2) bool; pair (j, j + M/2) counts only where True (e.g. both
             steps in the same episode, see same_episode_pairs).
    M must be even: the first half (1) = steps [0, M/2), the second half (2) = [M/2, M), and
    step j of one half is paired with step j of the other (tau <-> tau + M/2, eq. 5).

        L = mean_{b, j} 1/2 [ CE(wbar_(1)[b, j] -> log w_(2)[b, j])
                            + CE(wbar_(2)[b, j] -> log w_(1)[b, j]) ]

    i.e. the mean cross-entropy per prediction, on the same scale as swav_loss.
    """
    if log_w.shape != targets.shape or log_w.dim() != 3:
        raise ValueError(f"expected log_w and targets (B, M, K) of the same shape, got "
                         f"{tuple(log_w.shape)} and {tuple(targets.shape)}")
    B, M, K = log_w.shape
    if M % 2 != 0 or M == 0:
        raise ValueError(f"TC-SwAV needs an even, non-zero sequence length M, got M={M}")
    h = M // 2
    # wbar_(1) . log w_(2): targets of the first half predict the second half.   (B, h)
    ce_1_to_2 = swav_cross_entropy(log_w[:, h:], targets[:, :h])
    # wbar_(2) . log w_(1): targets of the second half predict the first half.   (B, h)
    ce_2_to_1 = swav_cross_entropy(log_w[:, :h], targets[:, h:])
    per_pair = 0.5 * (ce_1_to_2 + ce_2_to_1)  # (B, h)
    if pair_mask is None:
        return per_pair.mean()
    if pair_mask.shape != (B, h):
        raise ValueError(f"pair_mask must be (B, M/2)=({B}, {h}), got {tuple(pair_mask.shape)}")
    mask = pair_mask.to(per_pair.dtype)
    # Mean over valid pairs; no valid pair -> 0 (and zero gradient), never NaN.
    return (per_pair * mask).sum() / mask.sum().clamp(min=1.0)


def swav_loss(log_w: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """Ablation "w/o temporal consistency": each prediction against its own step's target.

    log_w, targets: (B, M, K).  L = mean_{b, t} -sum_k wbar[b, t, k] log w[b, t, k].
    """
    if log_w.shape != targets.shape:
        raise ValueError(f"log_w {tuple(log_w.shape)} and targets {tuple(targets.shape)} differ")
    return swav_cross_entropy(log_w, targets).mean()


def same_episode_pairs(is_first: torch.Tensor) -> torch.Tensor:
    """(B, M) bool is_first -> (B, M/2) bool: pair (j, j + M/2) lies within one episode.

    TC-SwAV assumes the context is constant over the sequence; a replay sequence that crosses
    an episode reset (a new context is sampled there) must not pair steps across it.  A reset
    at step t starts a new segment; steps j and j + M/2 are in one episode iff no reset in
    (j, j + M/2].
    """
    B, M = is_first.shape
    if M % 2 != 0:
        raise ValueError(f"is_first needs an even length, got M={M}")
    episode = torch.cumsum(is_first.long(), dim=1)  # (B, M) segment index per step
    h = M // 2
    return episode[:, :h] == episode[:, h:]


def _entropy(p: torch.Tensor) -> torch.Tensor:
    """(..., K) probabilities -> (...) entropy in nats."""
    return -(p * torch.log(p.clamp_min(1e-12))).sum(-1)


@torch.no_grad()
def context_health(u: torch.Tensor, w: torch.Tensor, ubar: torch.Tensor, wbar: torch.Tensor | None,
                   prototypes: torch.Tensor, initial: torch.Tensor) -> dict[str, torch.Tensor]:
    """Whether the context module codes anything: figures of one batch of sequences.

    u, ubar: (B, M, D) online / target projections; w, wbar: (B, M, K) predictions and
    Sinkhorn targets (wbar None: left out); prototypes and their seeded initial values (K, D).
    The trivial solution of the SwAV loss shows as projections in a cone (proj_cosine near 1),
    predictions and targets near uniform (entropies near ln K, top probabilities near 1/K) and
    swav_loss near ln K; a code of the context as sequences whose steps share one prototype
    (modal_share near 1) and projections that differ between sequences more than within
    (proj_between_share near 1). Thresholds: trainer/learn/context_health.py.
    """
    B, M, D = ubar.shape
    flat = ubar.reshape(-1, D).float()
    n = flat.shape[0]
    # mean over pairs i != j of ubar_i . ubar_j = (|sum ubar|^2 - n) / (n (n - 1))
    proj_cos = (flat.sum(0).pow(2).sum() - n) / max(n * (n - 1), 1)
    uf = u.float()
    centre = uf.reshape(-1, D).mean(0)
    total_var = (uf - centre).pow(2).sum(-1).mean()
    between = (uf.mean(1) - centre).pow(2).sum(-1).mean()
    modal = w.argmax(-1)  # (B, M)
    counts = torch.zeros(B, w.shape[-1], device=w.device).scatter_add_(
        1, modal, torch.ones_like(modal, dtype=torch.float32))
    out = {"swav_pred_entropy": _entropy(w).mean(), "swav_pred_top": w.max(-1).values.mean(),
           # exp(H(mean assignment)): how many prototypes are effectively in use (<= K).
           "swav_pred_perplexity": _entropy(w.reshape(-1, w.shape[-1]).mean(0)).exp(),
           "proj_cosine": proj_cos, "proj_between_share": between / total_var.clamp_min(1e-12),
           "modal_share": (counts.max(-1).values / M).mean(),
           "proto_init_cosine": F.cosine_similarity(prototypes.detach().float(), initial.float(), dim=-1).mean()}
    if wbar is not None:
        out.update({"swav_target_entropy": _entropy(wbar).mean(), "swav_target_top": wbar.max(-1).values.mean(),
                    "swav_target_perplexity": _entropy(wbar.reshape(-1, wbar.shape[-1]).mean(0)).exp()})
    return out


# ---- The module ----------------------------------------------------------------------
class ContextModule(nn.Module):
    """Projector f_theta, EMA target projector f_thetabar and K prototypes c_k (ProtoCAD).

    Args (paper table / DreamerPro defaults):
        state_dim: S, size of s = (h, z).
        proj_dim: D, prototype dimension (32).
        num_prototypes: K (task table: 100 or 50).
        temperature: T of the prediction softmax, eq. 3 (0.1).
        sinkhorn_iters / sinkhorn_eps: Sinkhorn-Knopp iterations / epsilon (3 / 0.05; the paper's
            eps, DreamerPro uses 0.0125 on DMC).
        ema: eta, fraction the target projector moves towards the online one per update (0.05).
        prototype_freeze: prototypes get zero gradient for the first this many updates, so
            the early, meaningless projections do not drag them around (DreamerPro: 10k of its
            ~100k). A trainer sets it from the run's plan (Agent.set_prototype_freeze); the
            config's -1 (auto, not yet resolved) builds with 0.
        temporal_consistency: True -> TC-SwAV (eq. 5); False -> in-place ablation.
        drop_first_steps: leading time steps left out of the SwAV loss (DreamerPro drops 1:
            the posterior at a sequence's first step has seen one frame and no transition, so
            it carries no dynamics/context information). TC-SwAV then pairs tau with
            tau + M/2 exactly (eq. 5, M = the sequence length), for every kept tau whose
            partner is inside the sequence: M=50 pairs (1, 26) ... (24, 49), 24 pairs (step 25
            has no partner); DreamerPro's M=51 pairs (1, 26) ... (25, 50). The ablation scores
            every kept step in place, so the two variants differ only in the pairing.

    Call order in one world-model update (the agent owns the optimizer):
        ctx.normalize_prototypes()            # unit-norm c_k before any forward (idempotent)
        u, w, e = ctx.features(s1)           # context features for the decoder (x = (s,u,e))
        loss, metrics = ctx.loss(s1, s2, step, is_first)   # add to the world-model loss
        total.backward()
        ctx.mask_frozen_prototype_grad(step) # zero every prototype grad inside the freeze window
        optimizer.step()
        ctx.update_target()                  # EMA of the projector, AFTER the optimizer step
        ctx.normalize_prototypes()           # so imagination / policy / checkpoints see unit c_k
    `step` = number of world-model updates done before this one (0 on the first update).
    """

    def __init__(self, state_dim: int, *, proj_dim: int = 32, num_prototypes: int = 100,
                 temperature: float = 0.1, sinkhorn_iters: int = 3, sinkhorn_eps: float = 0.05,
                 ema: float = 0.05, prototype_freeze: int = 0,
                 temporal_consistency: bool = True, drop_first_steps: int = 1,
                 sinkhorn_over: str = "steps", cross_view_scale: float = 0.0,
                 both_views_train: bool = False):
        super().__init__()
        if sinkhorn_over not in SINKHORN_OVER:
            raise ValueError(f"sinkhorn_over must be one of {SINKHORN_OVER}, got {sinkhorn_over!r}")
        if not 0.0 < ema <= 1.0:
            raise ValueError(f"ema must be in (0, 1], got {ema}")
        if temperature <= 0:
            raise ValueError(f"temperature must be > 0, got {temperature}")
        if drop_first_steps < 0:
            raise ValueError(f"drop_first_steps must be >= 0, got {drop_first_steps}")
        self.state_dim, self.proj_dim, self.num_prototypes = state_dim, proj_dim, num_prototypes
        self.temperature = temperature
        self.sinkhorn_iters, self.sinkhorn_eps = sinkhorn_iters, sinkhorn_eps
        self.ema = ema
        self.prototype_freeze = max(0, int(prototype_freeze))
        self.temporal_consistency = temporal_consistency
        self.drop_first_steps = drop_first_steps
        self.sinkhorn_over = sinkhorn_over
        self.cross_view_scale = float(cross_view_scale)
        self.both_views_train = bool(both_views_train)

        self.projector = nn.Linear(state_dim, proj_dim)  # f_theta
        # f_thetabar: Algorithm 1 "Initialize thetabar = theta"; never receives gradients.
        self.target_projector = copy.deepcopy(self.projector)
        self.target_projector.requires_grad_(False)
        # c_k: random directions on the unit sphere (K, D).
        self.prototypes = nn.Parameter(random_unit_prototypes(num_prototypes, proj_dim))
        # The starting directions, for the health metric "have the prototypes moved": the seeded
        # draw, redrawn on every load (not saved), or the policy's a run started from (init_policy).
        self.register_buffer("initial_prototypes", self.prototypes.detach().clone(), persistent=False)
        # EMA updates done so far; a buffer so a resumed checkpoint does not re-copy.
        self.register_buffer("ema_updates", torch.zeros((), dtype=torch.long))

    @classmethod
    def from_config(cls, ctx_cfg, state_dim: int, temporal_consistency: bool = True,
                    num_prototypes: int | None = None) -> "ContextModule":
        """Build from hyperparameters.ContextConfig (duck-typed: proto_dim, freeze_prototypes_updates...)."""
        return cls(state_dim=state_dim, proj_dim=ctx_cfg.proto_dim,
                   num_prototypes=ctx_cfg.num_prototypes if num_prototypes is None
                   else num_prototypes,
                   temperature=ctx_cfg.temperature, sinkhorn_iters=ctx_cfg.sinkhorn_iters,
                   sinkhorn_eps=ctx_cfg.sinkhorn_eps, ema=ctx_cfg.ema,
                   prototype_freeze=ctx_cfg.freeze_prototypes_updates,
                   temporal_consistency=temporal_consistency,
                   drop_first_steps=ctx_cfg.drop_first_steps,
                   sinkhorn_over=ctx_cfg.sinkhorn_over,
                   cross_view_scale=ctx_cfg.cross_view_scale,
                   both_views_train=ctx_cfg.both_views_train)

    def extra_repr(self) -> str:
        return (f"K={self.num_prototypes}, D={self.proj_dim}, T={self.temperature}, "
                f"sinkhorn=({self.sinkhorn_iters}, {self.sinkhorn_eps}), ema={self.ema}, "
                f"freeze={self.prototype_freeze}, tc={self.temporal_consistency}, "
                f"drop_first={self.drop_first_steps}, sinkhorn_over={self.sinkhorn_over}, "
                f"cross_view={self.cross_view_scale}, both_views={self.both_views_train}")

    # ---- prototypes -------------------------------------------------------------------------
    @torch.no_grad()
    def normalize_prototypes(self) -> None:
        """c_k <- c_k / ||c_k|| in place, outside autograd (DreamerPro does this every step).

        Gradients then act on the raw parameter; the next call projects it back onto the sphere.
        Must not be called between a forward that used the prototypes and its backward
        (autograd would raise: the saved tensor was modified in place).
        """
        self.prototypes.copy_(F.normalize(self.prototypes, dim=-1))

    def unit_prototypes(self) -> torch.Tensor:
        """(K, D) detached unit-norm copy, for plots / Agent.prototypes()."""
        return F.normalize(self.prototypes.detach(), dim=-1)

    def prototypes_frozen(self, step: int) -> bool:
        """True while `step` (updates done before this one) is inside the freeze window."""
        return step < self.prototype_freeze

    def mask_frozen_prototype_grad(self, step: int) -> bool:
        """Inside the freeze window drop every gradient on c_k (call after backward).

        Covers the gradients that reach c_k through e (decoder, actor/critic) as well, which
        loss() alone cannot see.  grad = None makes Adam skip the parameter entirely, so its
        moment estimates do not start from the frozen period.  Returns whether it masked.
        """
        if self.prototypes_frozen(step):
            self.prototypes.grad = None
            return True
        return False

    # ---- target projector -------------------------------------------------------------------
    @torch.no_grad()
    def update_target(self) -> None:
        """thetabar <- (1 - eta) thetabar + eta theta; a full copy on the first update."""
        if int(self.ema_updates) == 0:
            for tgt, src in zip(self.target_projector.parameters(), self.projector.parameters()):
                tgt.copy_(src)
        else:
            for tgt, src in zip(self.target_projector.parameters(), self.projector.parameters()):
                tgt.mul_(1.0 - self.ema).add_(src, alpha=self.ema)
        self.ema_updates += 1

    # ---- features ---------------------------------------------------------------------------
    def project(self, s: torch.Tensor) -> torch.Tensor:
        """u = f_theta(s) / ||f_theta(s)||: (..., S) -> (..., D)."""
        return F.normalize(self.projector(s), dim=-1)

    def logits(self, u: torch.Tensor, prototypes: torch.Tensor | None = None) -> torch.Tensor:
        """(u . c_k) / T: (..., D) -> (..., K)."""
        c = self.prototypes if prototypes is None else prototypes
        return u @ c.t() / self.temperature

    def features(self, s: torch.Tensor, train_module: bool = True
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Context features of states s (..., S) -> u (..., D), w (..., K), e (..., D).

        u = normalize(f_theta(s)); w = softmax(u . c / T) (eq. 3); e = sum_k w_k c_k.
        Differentiable: u in projector (and s), e in prototypes (directly and through w) and
        projector, so decoder / actor / critic losses on x = (s, u, e) train both (Algorithm 1,
        line 13). train_module=False: theta and c_k are constants here (gradients still reach
        s through them), so only TC-SwAV trains the context module (the Fig. 1 caption's reading).
        """
        if train_module:
            u, c = self.project(s), self.prototypes
        else:
            params = {k: v.detach() for k, v in self.projector.named_parameters()}
            u = F.normalize(torch.func.functional_call(self.projector, params, (s,)), dim=-1)
            c = self.prototypes.detach()
        w = torch.softmax(self.logits(u, c), dim=-1)  # (..., K)
        e = w @ c  # (..., D) = sum_k w_k c_k
        return u, w, e

    # ---- loss -------------------------------------------------------------------------------
    def kept_steps(self, seq_len: int) -> slice:
        """Time steps of a length-M sequence that enter the SwAV loss (see drop_first_steps)."""
        start = min(self.drop_first_steps, seq_len)
        if seq_len - start < 2:
            raise ValueError(f"sequence length {seq_len} leaves {seq_len - start} steps after "
                             f"dropping the first {self.drop_first_steps}; need >= 2")
        return slice(start, seq_len)

    def tc_pairs(self, seq_len: int) -> tuple[torch.Tensor, torch.Tensor]:
        """(tau, tau + M/2) time indices TC-SwAV pairs in a length-M sequence (eq. 5)."""
        h = seq_len // 2
        first = torch.arange(min(self.drop_first_steps, seq_len), seq_len - h)
        if first.numel() < 1:
            raise ValueError(f"sequence length {seq_len} has no pair (tau, tau + {h}) after dropping "
                             f"the first {self.drop_first_steps} step(s)")
        return first, first + h

    @torch.no_grad()
    def target_projections(self, s2: torch.Tensor) -> torch.Tensor:
        """ubar = normalize(f_thetabar(s)): (..., S) -> (..., D), float32."""
        return F.normalize(self.target_projector(s2.float()), dim=-1)

    @torch.no_grad()
    def targets(self, ubar: torch.Tensor, halves: tuple[torch.Tensor, torch.Tensor] | None = None
                ) -> torch.Tensor:
        """wbar = Sinkhorn-Knopp(ubar . c): target projections (B, M, D) -> (B, M, K).

        sinkhorn_over='steps' (the paper): every one of the B*M steps is a sample, so
        equipartition spreads each sequence over at least K/B prototypes. 'half_means': one
        sample per sequence half (the mean of its projections, renormalised; `halves` = the
        two halves' step indices), 2B samples, and every step of a half gets its half's
        target: the code can then be one prototype per context, and the halves still predict
        each other (eq. 5) when the context is constant. Steps in neither half get no target
        (zeros).
        """
        c = self.prototypes.detach().float()
        B, M, _ = ubar.shape
        K = c.shape[0]
        if self.sinkhorn_over == "steps" or halves is None:
            q = sinkhorn_knopp((ubar @ c.t()).reshape(B * M, K), self.sinkhorn_iters, self.sinkhorn_eps)
            return q.reshape(B, M, K)
        means = torch.stack([F.normalize(ubar[:, idx].mean(1), dim=-1) for idx in halves], 1)  # (B, 2, D)
        q = sinkhorn_knopp((means @ c.t()).reshape(B * 2, K), self.sinkhorn_iters,
                           self.sinkhorn_eps).reshape(B, 2, K)
        out = torch.zeros(B, M, K, device=ubar.device)
        for i, idx in enumerate(halves):
            out[:, idx] = q[:, i:i + 1].expand(B, len(idx), K)
        return out

    def _swav_terms(self, log_w: torch.Tensor, wbar: torch.Tensor, halves: tuple[torch.Tensor, torch.Tensor],
                    pair_mask: torch.Tensor | None) -> torch.Tensor:
        """The paper's term (TC-SwAV across halves, or in place for the ablation) plus, with
        cross_view_scale, DreamerPro's same-time term (each step's prediction against its own
        step's target of the other view) on the paired steps."""
        idx = torch.cat(halves).to(log_w.device)
        if self.temporal_consistency:
            loss = tc_swav_loss(log_w[:, idx], wbar[:, idx], pair_mask)
        else:
            loss = swav_loss(log_w, wbar)
        if self.cross_view_scale:
            loss = loss + self.cross_view_scale * swav_loss(log_w[:, idx], wbar[:, idx])
        return loss

    def loss(self, s1: torch.Tensor, s2: torch.Tensor, step: int,
             is_first: torch.Tensor | None = None) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """TC-SwAV (or the in-place ablation) between view-1 predictions and view-2 targets.

        s1, s2: (B, M, S) posterior states of views 1 and 2 (gradient flows into s1; into s2
            too with both_views_train, whose predictions then learn view 1's targets).
        step: world-model updates done before this one (freeze window for the prototypes).
        is_first: optional (B, M) bool; with TC, pairs that straddle an episode reset are
            left out (a new context starts there).
        returns (scalar loss to minimise, metrics: dict of detached 0-dim tensors: the loss and
            the module's health, context_health).
        Computed in float32 whatever the autocast around it: in bf16 the scores of nearby
        projections round together (SwAV figures came in multiples of 1/32).
        """
        if s1.shape != s2.shape or s1.dim() != 3:
            raise ValueError(f"expected s1, s2 (B, M, S) of the same shape, got "
                             f"{tuple(s1.shape)} and {tuple(s2.shape)}")
        keep = self.kept_steps(s1.shape[1])
        first, second = self.tc_pairs(keep.stop)
        halves = (first - keep.start, second - keep.start)  # indices among the kept steps
        pair_mask = None
        if self.temporal_consistency and is_first is not None:
            # Segment ids from the full sequence, so resets in dropped steps still count.
            episode = torch.cumsum(is_first.to(s1.device).long(), dim=1)
            pair_mask = episode[:, first.to(s1.device)] == episode[:, second.to(s1.device)]

        frozen = self.prototypes_frozen(step)
        with torch.autocast(device_type=s1.device.type, enabled=False):
            s1, s2 = s1[:, keep].float(), s2[:, keep].float()  # (B, M', S) after the warm-up
            # Frozen: the loss still trains the projector, but c_k gets no gradient from it.
            c = self.prototypes.detach() if frozen else self.prototypes  # (K, D)
            views = [(s1, s2), (s2, s1)] if self.both_views_train else [(s1, s2)]
            total, metrics = s1.new_zeros(()), {}
            for pred_s, tgt_s in views:
                u = self.project(pred_s)  # (B, M', D)
                log_w = torch.log_softmax(self.logits(u, c), dim=-1)  # (B, M', K)
                ubar = self.target_projections(tgt_s)
                wbar = self.targets(ubar, halves)  # (B, M', K), no grad
                total = total + self._swav_terms(log_w, wbar, halves, pair_mask)
                # Health of view 1's predictions against view 2's targets (the paper's pair).
                metrics = metrics or self.health(u.detach(), log_w.detach().exp(), ubar, wbar)
            loss = total / len(views)
        metrics["swav_loss"] = loss.detach()
        metrics["prototypes_frozen"] = torch.tensor(float(frozen), device=loss.device)
        return loss, metrics

    def health(self, u: torch.Tensor, w: torch.Tensor, ubar: torch.Tensor,
               wbar: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """context_health of these projections and assignments with this module's prototypes."""
        return context_health(u, w, ubar, wbar, self.prototypes, self.initial_prototypes)
