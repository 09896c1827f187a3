"""The behaviour-learning equations: lambda-returns (paper eq. 8), action distributions,
slow critic schedule, actor/critic loss plumbing. Pure torch, no rendering, fast."""
from __future__ import annotations

import math

import pytest
import torch

from protocad_ros.model.behavior import ActorCritic, ImagineFns, lambda_return
from protocad_ros.model.hyperparameters import BehaviorConfig
from protocad_ros.model.networks import TanhNormal, TruncNormal

pytestmark = pytest.mark.usefixtures("one_torch_thread")


# ---- lambda-returns ---------------------------------------------------------------------------
def test_lambda_return_hand_computed():
    # H = 3 imagined transitions, gamma = 0.9, lambda = 0.5.
    # rewards r_1..r_3 = 1, 2, 3; values v(x_0..x_2) = 0.5, 1.0, 1.5 (v(x_0) is never used);
    # bootstrap v(x_3) = 2.0.
    #   R_2 = 3 + 0.9 * 2.0                                  = 4.8
    #   R_1 = 2 + 0.9 * (0.5 * 1.5 + 0.5 * 4.8) = 2 + 2.835   = 4.835
    #   R_0 = 1 + 0.9 * (0.5 * 1.0 + 0.5 * 4.835) = 1 + 2.62575 = 3.62575
    # Eq. 8 directly for x_0: V^1 = 1 + .9 * 1 = 1.9; V^2 = 1 + 1.8 + .81 * 1.5 = 4.015;
    #   V^3 = 1 + 1.8 + 2.43 + .729 * 2 = 6.688;
    #   V_lambda = .5 * 1.9 + .5 * .5 * 4.015 + .5^2 * 6.688 = .95 + 1.00375 + 1.672 = 3.62575
    reward = torch.tensor([1.0, 2.0, 3.0])
    value = torch.tensor([0.5, 1.0, 1.5])
    discount = torch.full((3,), 0.9)
    bootstrap = torch.tensor(2.0)
    ret = lambda_return(reward, value, discount, bootstrap, 0.5)
    assert torch.allclose(ret, torch.tensor([3.62575, 4.835, 4.8]), atol=1e-5), ret


def _eq8(reward, value, gamma, bootstrap, lam):
    """V_lambda(x_t) of eq. 8 written literally: (1 - l) sum_{n<H'} l^(n-1) V^n + l^(H'-1) V^H'
    with V^n the n-step return from t (H' = steps left)."""
    H = len(reward)
    values = list(value[1:]) + [bootstrap]  # v(x_{t+1}) ... v(x_H)
    out = []
    for t in range(H):
        left = H - t
        vn = []
        for n in range(1, left + 1):
            g = sum(gamma ** i * reward[t + i] for i in range(n))
            vn.append(g + gamma ** n * values[t + n - 1])
        out.append((1 - lam) * sum(lam ** (n - 1) * vn[n - 1] for n in range(1, left))
                   + lam ** (left - 1) * vn[-1])
    return torch.tensor(out)


@pytest.mark.parametrize("lam", [0.0, 0.5, 0.95, 1.0])
def test_lambda_return_matches_eq8(lam):
    g = torch.Generator().manual_seed(1)
    H, gamma = 6, 0.99
    reward, value = torch.randn(H, generator=g), torch.randn(H, generator=g)
    bootstrap = torch.randn((), generator=g)
    ret = lambda_return(reward, value, torch.full((H,), gamma), bootstrap, lam)
    want = _eq8(reward.tolist(), value.tolist(), gamma, float(bootstrap), lam)
    assert torch.allclose(ret, want.float(), atol=1e-5)
    if lam == 0.0:  # one-step TD targets
        nxt = torch.cat([value[1:], bootstrap[None]])
        assert torch.allclose(ret, reward + gamma * nxt, atol=1e-6)
    if lam == 1.0:  # discounted Monte-Carlo return + bootstrap
        mc = sum(gamma ** i * reward[i] for i in range(H)) + gamma ** H * bootstrap
        assert math.isclose(float(ret[0]), float(mc), rel_tol=1e-5)


def test_lambda_return_batched_and_shape_check():
    reward = torch.ones(4, 3, 2)
    ret = lambda_return(reward, torch.zeros(4, 3, 2), torch.ones(4, 3, 2), torch.zeros(3, 2), 1.0)
    assert ret.shape == (4, 3, 2)
    assert torch.allclose(ret[:, 0, 0], torch.tensor([4.0, 3.0, 2.0, 1.0]))
    with pytest.raises(ValueError, match="same"):
        lambda_return(torch.ones(3), torch.ones(2), torch.ones(3), torch.tensor(0.0), 0.9)


# ---- action distributions ----------------------------------------------------------------------
def _grid_integral(f, n=200001):
    x = torch.linspace(-1, 1, n, dtype=torch.float64)
    y = f(x)
    return float(torch.trapezoid(y, x))


@pytest.mark.parametrize("mean,std", [(0.0, 0.3), (0.8, 0.5), (-0.95, 0.1), (0.3, 2.0)])
def test_trunc_normal_density_and_entropy(mean, std):
    d = TruncNormal(torch.tensor([mean], dtype=torch.float64), torch.tensor([std],
                                                                            dtype=torch.float64))
    logp = lambda x: d.log_prob(x[:, None])  # noqa: E731
    assert _grid_integral(lambda x: logp(x).exp()) == pytest.approx(1.0, abs=1e-4)
    ent = -_grid_integral(lambda x: logp(x).exp() * logp(x))
    assert float(d.entropy()) == pytest.approx(ent, abs=1e-3)
    x = TruncNormal(torch.full((20000, 1), mean), torch.full((20000, 1), std)).sample()
    assert x.min() >= -1 and x.max() <= 1
    # sample mean matches the density's mean
    m = _grid_integral(lambda x: x * logp(x).exp())
    assert float(x.mean()) == pytest.approx(m, abs=0.02)


def test_trunc_normal_sample_is_reparameterised():
    mean = torch.zeros(64, 2, requires_grad=True)
    std = torch.full((64, 2), 0.5, requires_grad=True)
    TruncNormal(torch.tanh(mean), std).sample().sum().backward()
    assert torch.isfinite(mean.grad).all() and mean.grad.abs().sum() > 0
    assert torch.isfinite(std.grad).all()


def test_tanh_normal_bounds_and_log_prob():
    d = TanhNormal(torch.zeros(5000, 1), torch.ones(5000, 1))
    x = d.sample()
    assert x.abs().max() < 1
    one = TanhNormal(torch.tensor([[0.2]], dtype=torch.float64), torch.tensor([[0.7]],
                                                                               dtype=torch.float64))
    total = _grid_integral(lambda t: one.log_prob(t.clamp(-1 + 1e-9, 1 - 1e-9)[:, None]).exp())
    assert total == pytest.approx(1.0, abs=2e-3)


# ---- actor-critic plumbing ---------------------------------------------------------------------
def _toy_fns(state_dim=4, action_dim=2):
    """A linear 'world model' s' = A s + B a with reward = sum(s): enough to test the plumbing."""
    g = torch.Generator().manual_seed(0)
    A = torch.randn(state_dim, state_dim, generator=g) * 0.3
    Bm = torch.randn(action_dim, state_dim, generator=g)
    return ImagineFns(step=lambda st, a: {"x": st["x"] @ A + a @ Bm},
                      state_feat=lambda st: st["x"], features=lambda s: s,
                      reward=lambda s: s.sum(-1))


def test_actor_and_critic_losses_reach_only_their_networks():
    cfg = BehaviorConfig(actor_layers=1, actor_units=16, critic_layers=1, critic_units=16,
                         horizon=4)
    ac = ActorCritic(4, 2, cfg)
    fns = _toy_fns()
    start = {"x": torch.randn(8, 4)}
    actor_loss, critic_loss, metrics = ac.loss(fns, start)
    actor_p, critic_p = list(ac.actor.parameters()), list(ac.critic.parameters())
    g_critic_from_actor = torch.autograd.grad(actor_loss, critic_p, retain_graph=True,
                                              allow_unused=True)
    assert all(g is None or g.abs().max() == 0 for g in g_critic_from_actor)
    g_actor_from_critic = torch.autograd.grad(critic_loss, actor_p, retain_graph=True,
                                              allow_unused=True)
    assert all(g is None or g.abs().max() == 0 for g in g_actor_from_critic)
    g_actor = torch.autograd.grad(actor_loss, actor_p, retain_graph=True)
    assert sum(float(g.abs().sum()) for g in g_actor) > 0  # dynamics backprop reaches the actor
    assert all(not p.requires_grad for p in ac.slow_critic.parameters())
    assert set(metrics) >= {"actor_loss", "critic_loss", "entropy", "imag_return"}


def test_slow_critic_schedule():
    cfg = BehaviorConfig(critic_layers=1, critic_units=8, slow_critic_update=3)
    ac = ActorCritic(4, 1, cfg)
    w = lambda m: next(m.parameters()).detach().clone()  # noqa: E731

    def bump():
        with torch.no_grad():
            for p in ac.critic.parameters():
                p.add_(1.0)

    bump()
    ac.update_slow_critic()  # update 0: full copy
    assert torch.equal(w(ac.slow_critic), w(ac.critic))
    for _ in range(2):  # updates 1, 2: no copy
        bump()
        ac.update_slow_critic()
        assert not torch.equal(w(ac.slow_critic), w(ac.critic))
    bump()
    ac.update_slow_critic()  # update 3: copy
    assert torch.equal(w(ac.slow_critic), w(ac.critic))


# ---- RSSM pieces used by imagination ----------------------------------------------------------
def test_categorical_latent_sampling_and_straight_through():
    from protocad_ros.model.hyperparameters import WorldModelConfig
    from protocad_ros.model.rssm import RSSM

    rssm = RSSM(1, 8, WorldModelConfig(stoch=2, discrete=4, unimix=0.0))
    p = torch.tensor([0.1, 0.2, 0.3, 0.4])
    logit = p.log().expand(100000, 2, 4).clone().requires_grad_(True)
    s = rssm._sample({"logit": logit}, True)  # (N, 8) one-hot samples
    freq = s.detach().reshape(-1, 2, 4).mean(0)
    assert torch.allclose(freq, p.expand(2, 4), atol=0.01)
    (s * torch.arange(8.0)).sum().backward()  # straight-through: gradient reaches the logits
    assert logit.grad.abs().sum() > 0


def test_categorical_samples_are_one_hot_and_never_a_zero_probability_class():
    """Classes of probability 0 (first and last included) are never drawn, each latent draws
    exactly one class, and the mode is the most likely class."""
    from protocad_ros.model.hyperparameters import WorldModelConfig
    from protocad_ros.model.rssm import RSSM

    rssm = RSSM(1, 8, WorldModelConfig(stoch=2, discrete=5, unimix=0.0))
    p = torch.tensor([0.0, 0.7, 0.0, 0.3, 0.0])
    logit = torch.log_softmax(p.log(), -1).expand(50000, 2, 5)
    s = rssm._sample({"logit": logit}, True).reshape(-1, 2, 5)
    assert torch.equal(s.sum(-1), torch.ones(50000, 2))
    assert s[..., [0, 2, 4]].sum() == 0
    assert torch.allclose(s.mean(0), p.expand(2, 5), atol=0.01)
    mode = rssm._sample({"logit": logit[:3]}, False).reshape(3, 2, 5)
    assert torch.equal(mode.argmax(-1), torch.ones(3, 2, dtype=torch.long))


@pytest.mark.parametrize("unimix", [0.0, 0.01])
def test_categorical_kl_is_the_kl_of_the_networks_distributions(unimix):
    """From raw network outputs (any offset, as a linear layer gives them), with and without
    unimix: the KL of the distributions the latents are sampled from, never negative."""
    from protocad_ros.model.hyperparameters import WorldModelConfig
    from protocad_ros.model.rssm import RSSM

    rssm = RSSM(1, 8, WorldModelConfig(stoch=3, discrete=5, unimix=unimix))
    g = torch.Generator().manual_seed(0)
    raw_post, raw_prior = torch.randn(4, 15, generator=g) * 3 + 7, torch.randn(4, 15, generator=g) * 3 - 2
    post, prior = rssm._stats(raw_post), rssm._stats(raw_prior)

    def dist(raw):
        probs = torch.softmax(raw.reshape(4, 3, 5), -1)
        probs = (1 - unimix) * probs + unimix / 5
        return torch.distributions.Categorical(probs=probs)

    expected = torch.distributions.kl_divergence(dist(raw_post), dist(raw_prior)).sum(-1)
    assert torch.allclose(rssm.kl(post, prior), expected, atol=1e-5)
    assert (rssm.kl(post, prior) >= 0).all() and torch.allclose(rssm.kl(post, post), torch.zeros(4), atol=1e-6)


def test_kl_balancing_and_free_nats():
    from protocad_ros.model.hyperparameters import WorldModelConfig
    from protocad_ros.model.rssm import RSSM

    rssm = RSSM(1, 8, WorldModelConfig(stoch=3))
    post = {"mean": torch.zeros(4, 3, requires_grad=True), "std": torch.ones(4, 3)}
    prior = {"mean": torch.full((4, 3), 2.0, requires_grad=True), "std": torch.ones(4, 3)}
    # KL(N(0,1) || N(2,1)) = 2 per dim -> 6 per state, above free nats 1.
    loss, value = rssm.kl_loss(post, prior, balance=0.8, free=1.0)
    assert torch.allclose(value, torch.full((4,), 6.0)) and float(loss.detach()) == pytest.approx(6.0)
    g_post, g_prior = torch.autograd.grad(loss, [post["mean"], prior["mean"]])
    # d KL / d mean = -(prior - post) for the posterior, weighted 1 - balance = 0.2,
    # and +(prior - post) for the prior, weighted balance = 0.8 (averaged over 4 states).
    assert torch.allclose(g_post, torch.full((4, 3), -2.0 * 0.2 / 4))
    assert torch.allclose(g_prior, torch.full((4, 3), 2.0 * 0.8 / 4))
    # Below the free nats: no gradient at all.
    loss, _ = rssm.kl_loss(post, prior, balance=0.8, free=10.0)
    assert float(loss.detach()) == 10.0
    assert all(g.abs().sum() == 0 for g in torch.autograd.grad(loss, [post["mean"],
                                                                      prior["mean"]]))
