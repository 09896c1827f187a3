"""Recurrent state-space model (RSSM; Hafner et al. 2019, DreamerV2 variant), pure PyTorch.

    recurrent   h_t = f(h_{t-1}, z_{t-1}, a_{t-1})              GRU
    posterior   z_t ~ q(z_t | h_t, o_t)                          representation
    prior       z^_t ~ p(z^_t | h_t)                              transition
    state       s_t = (h_t, z_t), feature = concat(z_t, h_t)     (DreamerV2 order)

A state is a dict of tensors: 'deter' (..., deter), 'stoch' (..., stoch_dim) and the
distribution's statistics: 'mean', 'std' (Gaussian latents) or 'logit' (..., stoch, classes)
(categorical latents; log of the unimix-ed probabilities). Statistics are always float32.

Latents: continuous diagonal Gaussian with std = 2 sigmoid(x / 2) + min_std (DreamerPro dmc),
or `stoch` categoricals of `discrete` classes with 1% unimix and straight-through one-hot
samples (DreamerV2 Atari / DreamerV3).

Speed: observe() runs the posterior filter step by step but takes everything that does not
depend on the recurrence out of the loop: the embedding half of the posterior layer is one
batched matmul over all B*T steps, and the prior statistics (only needed for the KL) are
computed after the loop from the stacked h_t.
"""
from __future__ import annotations

import torch
import torch.nn as nn

from protocad_ros.model.hyperparameters import WorldModelConfig
from protocad_ros.model.networks import GRUCell, activation

State = dict[str, torch.Tensor]

__all__ = ["RSSM", "State", "stack_states", "flatten_state", "detach_state"]


def _dense(inp: int, out: int, act: str, norm: str) -> nn.Sequential:
    mods: list[nn.Module] = [nn.Linear(inp, out, bias=norm == "none")]
    if norm == "layer":
        mods.append(nn.LayerNorm(out))
    mods.append(activation(act))
    return nn.Sequential(*mods)


class RSSM(nn.Module):
    def __init__(self, action_dim: int, embed_dim: int, cfg: WorldModelConfig):
        super().__init__()
        self.cfg = cfg
        self.action_dim, self.embed_dim = action_dim, embed_dim
        self.deter_dim, self.stoch, self.classes = cfg.deter, cfg.stoch, cfg.discrete
        self.stoch_dim = cfg.stoch * cfg.discrete if cfg.discrete else cfg.stoch
        stats_dim = self.stoch_dim if cfg.discrete else 2 * cfg.stoch
        self.feat_dim = self.stoch_dim + cfg.deter
        # prior / recurrent path: img_in -> GRU -> img_out -> img_stat (DreamerV2 img_step)
        self.img_in = _dense(self.stoch_dim + action_dim, cfg.hidden, cfg.act, cfg.norm)
        self.gru = GRUCell(cfg.hidden, cfg.deter, norm=cfg.gru_norm)
        self.img_out = _dense(cfg.deter, cfg.hidden, cfg.act, cfg.norm)
        self.img_stat = nn.Linear(cfg.hidden, stats_dim)
        # posterior: obs_out(concat(h, embed)) written as W_h h + W_e embed (the same layer),
        # so the W_e embed half can be batched over all time steps.
        self.obs_deter = nn.Linear(cfg.deter, cfg.hidden, bias=False)
        self.obs_embed = nn.Linear(embed_dim, cfg.hidden, bias=True)
        self.obs_post = nn.Sequential(
            *([nn.LayerNorm(cfg.hidden)] if cfg.norm == "layer" else []), activation(cfg.act))
        self.obs_stat = nn.Linear(cfg.hidden, stats_dim)

    # ---- states ---------------------------------------------------------------------------------
    def initial(self, batch_size: int, device: torch.device | str | None = None) -> State:
        """The zero state (DreamerV2); used at t=0 and wherever is_first is set."""
        device = device if device is not None else self.img_stat.weight.device
        z = lambda *s: torch.zeros(batch_size, *s, device=device)  # noqa: E731
        state = {"deter": z(self.deter_dim), "stoch": z(self.stoch_dim)}
        if self.classes:
            state["logit"] = z(self.stoch, self.classes)
        else:
            state["mean"], state["std"] = z(self.stoch), z(self.stoch)
        return state

    def get_feat(self, state: State) -> torch.Tensor:
        """s_t = concat(z_t, h_t): (..., stoch_dim + deter)."""
        return torch.cat([state["stoch"], state["deter"]], -1)

    # ---- distributions --------------------------------------------------------------------------
    def _stats(self, x: torch.Tensor) -> State:
        x = x.float()
        if self.classes:
            logit = x.reshape(*x.shape[:-1], self.stoch, self.classes)
            if self.cfg.unimix > 0:  # DreamerV3: probs = (1 - mix) softmax + mix / classes
                probs = torch.softmax(logit, -1)
                probs = (1 - self.cfg.unimix) * probs + self.cfg.unimix / self.classes
                return {"logit": probs.log()}
            # Normalized: `kl` reads these as log-probabilities (raw network outputs would make
            # sum(exp(lp) * (lp - rp)) any number, negative too, and the KL loss would sit at
            # its free nats with no gradient); softmax, argmax and sampling are unchanged.
            return {"logit": torch.log_softmax(logit, -1)}
        mean, std = x.chunk(2, -1)
        std = 2 * torch.sigmoid(std / 2) + self.cfg.min_std  # DreamerPro std_act 'sigmoid2'
        return {"mean": mean, "std": std}

    def _sample(self, stats: State, sample: bool,
                generator: torch.Generator | None = None) -> torch.Tensor:
        if self.classes:
            probs = stats["logit"].exp()  # the statistics are normalized log-probabilities
            if sample:
                # Inverse CDF: one uniform per latent, index = #{k : cdf_k <= u * total}. The
                # same Categorical(p) as Gumbel-max with 1/classes of the random numbers and no
                # argmax; these were 40% of imagination's forward at 32 classes on a CPU. Zero-
                # probability classes have empty intervals and are never drawn.
                cdf = probs.detach().cumsum(-1)
                u = torch.rand((*probs.shape[:-1], 1), generator=generator, device=probs.device)
                index = (cdf <= u * cdf[..., -1:]).sum(-1).clamp_max(self.classes - 1)
            else:
                index = probs.argmax(-1)
            onehot = torch.zeros_like(probs).scatter_(-1, index.unsqueeze(-1), 1.0)
            onehot = onehot + probs - probs.detach()  # straight-through gradient
            return onehot.reshape(*onehot.shape[:-2], self.stoch_dim)
        if not sample:
            return stats["mean"]
        eps = torch.randn(stats["mean"].shape, generator=generator, device=stats["mean"].device)
        return stats["mean"] + stats["std"] * eps

    # ---- steps ----------------------------------------------------------------------------------
    def _recurrent(self, prev: State, action: torch.Tensor) -> torch.Tensor:
        x = self.img_in(torch.cat([prev["stoch"], action], -1))
        return self.gru(x, prev["deter"])

    def img_step(self, prev: State, action: torch.Tensor, sample: bool = True,
                 generator: torch.Generator | None = None) -> State:
        """Prior step: h_t = f(h, z, a), z^_t ~ p(. | h_t). Used by imagination."""
        deter = self._recurrent(prev, action)
        stats = self._stats(self.img_stat(self.img_out(deter)))
        return {"deter": deter, "stoch": self._sample(stats, sample, generator), **stats}

    def _reset(self, prev: State, action: torch.Tensor, is_first: torch.Tensor | None):
        """Zero h, z and the action where a new episode starts (is_first): the zero state is
        the initial state, so a reset is a multiplication by (1 - is_first)."""
        if is_first is None:
            return prev, action
        keep = (~is_first.bool()).to(action.dtype).unsqueeze(-1)  # (B, 1)
        return {"deter": prev["deter"] * keep, "stoch": prev["stoch"] * keep}, action * keep

    def obs_step(self, prev: State, action: torch.Tensor, embed: torch.Tensor,
                 is_first: torch.Tensor | None = None, *, sample: bool = True,
                 generator: torch.Generator | None = None,
                 with_prior: bool = True) -> tuple[State, State | None]:
        """One filter step: (posterior, prior) of s_t given s_{t-1}, a_{t-1}, o_t's embedding.

        prev: (B, ...) state; action (B, A) = a_{t-1}; embed (B, E); is_first (B,) bool.
        with_prior=False skips the prior (the policy does not need it) and returns None for it.
        """
        prev, action = self._reset(prev, action, is_first)
        deter = self._recurrent(prev, action)
        prior = None
        if with_prior:
            prior_stats = self._stats(self.img_stat(self.img_out(deter)))
            prior = {"deter": deter, "stoch": self._sample(prior_stats, sample, generator),
                     **prior_stats}
        h = self.obs_post(self.obs_deter(deter) + self.obs_embed(embed))
        stats = self._stats(self.obs_stat(h))
        post = {"deter": deter, "stoch": self._sample(stats, sample, generator), **stats}
        return post, prior

    def observe(self, embed: torch.Tensor, action: torch.Tensor, is_first: torch.Tensor,
                state: State | None = None, sample: bool = True,
                with_prior: bool = True) -> tuple[State, State | None]:
        """Filter a batch of sequences.

        embed (B, T, E); action (B, T, A) = a_{t-1} (the action that led to o_t);
        is_first (B, T) bool. Returns posterior and prior states with (B, T, ...) tensors
        (the prior holds statistics and deter only: the KL needs nothing else; None if
        with_prior=False).
        """
        B, T = embed.shape[:2]
        state = self.initial(B, embed.device) if state is None else state
        emb_h = self.obs_embed(embed)  # (B, T, hidden): batched half of the posterior layer
        deters, stochs, stats_seq = [], [], []
        for t in range(T):
            prev, act = self._reset(state, action[:, t], is_first[:, t])
            deter = self._recurrent(prev, act)
            h = self.obs_post(self.obs_deter(deter) + emb_h[:, t])
            stats = self._stats(self.obs_stat(h))
            stoch = self._sample(stats, sample)
            state = {"deter": deter, "stoch": stoch}
            deters.append(deter)
            stochs.append(stoch)
            stats_seq.append(stats)
        deter = torch.stack(deters, 1)  # (B, T, deter)
        post = {"deter": deter, "stoch": torch.stack(stochs, 1)}
        for k in stats_seq[0]:
            post[k] = torch.stack([s[k] for s in stats_seq], 1)
        prior = None
        if with_prior:  # p(z_t | h_t) for all steps at once, outside the recurrence
            prior = {"deter": deter, **self._stats(self.img_stat(self.img_out(deter)))}
        return post, prior

    # ---- KL ---------------------------------------------------------------------------------------
    def kl(self, lhs: State, rhs: State) -> torch.Tensor:
        """KL(lhs || rhs) per state, summed over latent dims: (...)."""
        if self.classes:
            lp, rp = lhs["logit"], rhs["logit"]  # log-probabilities (unimix-ed)
            return (lp.exp() * (lp - rp)).sum((-2, -1))
        m1, s1, m2, s2 = lhs["mean"], lhs["std"], rhs["mean"], rhs["std"]
        return (torch.log(s2 / s1) + (s1 ** 2 + (m1 - m2) ** 2) / (2 * s2 ** 2) - 0.5).sum(-1)

    def kl_loss(self, post: State, prior: State, balance: float = 0.8, free: float = 1.0,
                free_avg: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
        """KL balancing (DreamerV2): balance * KL(sg(post) || prior) + (1 - balance) *
        KL(post || sg(prior)), each clipped below at `free` nats (after averaging if free_avg).

        Returns (loss scalar, KL value per state (B, T) detached).
        """
        keys = ("logit",) if self.classes else ("mean", "std")
        sg = lambda s: {k: s[k].detach() for k in keys}  # noqa: E731
        post_s, prior_s = {k: post[k] for k in keys}, {k: prior[k] for k in keys}
        value_lhs = self.kl(post_s, sg(prior_s))  # trains the posterior (representation)
        value_rhs = self.kl(sg(post_s), prior_s)  # trains the prior (dynamics)
        if free_avg:
            loss_lhs = value_lhs.mean().clamp_min(free)
            loss_rhs = value_rhs.mean().clamp_min(free)
        else:
            loss_lhs = value_lhs.clamp_min(free).mean()
            loss_rhs = value_rhs.clamp_min(free).mean()
        loss = (1 - balance) * loss_lhs + balance * loss_rhs
        return loss, value_lhs.detach()


# ---- state helpers --------------------------------------------------------------------------------
def stack_states(states: list[State], dim: int = 0) -> State:
    return {k: torch.stack([s[k] for s in states], dim) for k in states[0]}


def flatten_state(state: State, lead: int = 2) -> State:
    """Merge the first `lead` dims: (B, T, ...) -> (B*T, ...)."""
    return {k: v.reshape(-1, *v.shape[lead:]) for k, v in state.items()}


def detach_state(state: State) -> State:
    return {k: v.detach() for k, v in state.items()}
