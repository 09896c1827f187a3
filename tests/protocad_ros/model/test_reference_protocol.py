"""Evaluation and initialisation as the reference implementations do them (DreamerV1/DreamerPro
SampleDist mode, DreamerV2/DreamerPro `eval_state_mean: False`, Keras' glorot init), and the
fixed stratified subset that periodic evaluations use. No processes, no rendering."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn as nn

from protocad_ros.model.agent import Agent
from protocad_ros.model.config import make_config
from protocad_ros.model.networks import TanhNormal, TruncNormal
from protocad_ros.policy import Policy

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def reference_sample_mode(mean: float, std: float, seed: int, samples: int = 100) -> float:
    """DreamerPro's SampleDist.mode, written with torch.distributions (tanh-transformed Normal):
    the sample of highest log-probability among `samples`."""
    d = torch.distributions.TransformedDistribution(
        torch.distributions.Normal(torch.tensor([mean], dtype=torch.float64),
                                   torch.tensor([std], dtype=torch.float64)),
        [torch.distributions.TanhTransform(cache_size=1)])
    g = torch.Generator().manual_seed(seed)
    pre = mean + std * torch.randn(samples, 1, generator=g, dtype=torch.float64)
    x = torch.tanh(pre).clamp(-1 + 1e-12, 1 - 1e-12)
    return float(x[d.log_prob(x).sum(-1).argmax()])


@pytest.mark.parametrize("mean,std", [(0.5, 1.5), (-0.8, 2.0), (0.3, 0.1)])
def test_tanh_normal_mode_is_the_most_likely_of_100_samples(mean, std):
    dist = TanhNormal(torch.full((8, 1), mean), torch.full((8, 1), std))
    ours = dist.mode(torch.Generator().manual_seed(0))[:, 0]
    refs = [reference_sample_mode(mean, std, seed) for seed in range(8)]
    # both estimate the same mode from 100 draws: same place within the draws' spread
    tol = 0.01 if std > 1 else 0.05
    assert abs(float(ours.mean()) - float(np.mean(refs))) < tol
    if std > 1:
        # a wide tanh(Normal) piles up at the bound: the mode is there, not at tanh(mean)
        assert abs(float(ours.mean())) > 0.99 and math.copysign(1, float(ours.mean())) == math.copysign(1, mean)
        assert abs(math.tanh(mean)) < 0.7


def test_tanh_normal_mode_repeats_with_the_generator_and_picks_jointly():
    mean, std = torch.randn(5, 6), torch.rand(5, 6) + 0.5
    dist = TanhNormal(mean, std)
    a = dist.mode(torch.Generator().manual_seed(3))
    b = dist.mode(torch.Generator().manual_seed(3))
    assert torch.equal(a, b) and a.shape == (5, 6) and a.abs().max() < 1
    # the pick is one joint draw: its log-density is the best of the 100 draws of that generator
    g = torch.Generator().manual_seed(3)
    pre = mean + std * torch.randn((100, 5, 6), generator=g)
    best = dist._log_prob_pre(pre).max(0).values
    assert torch.allclose(dist.log_prob(a), best, atol=1e-3)


def test_trunc_normal_mode_is_its_mean():
    mean = torch.tensor([[0.5, -0.9]])
    assert torch.equal(TruncNormal(mean, torch.full_like(mean, 1.5)).mode(), mean)


def _agent(**kw) -> Agent:
    over = {"world_model.deter": 32, "world_model.hidden": 32, "world_model.stoch": 4,
            "world_model.cnn_depth": 8, "world_model.mlp_layers": 1, "world_model.mlp_units": 32,
            "behavior.actor_layers": 1, "behavior.actor_units": 32, "behavior.critic_layers": 1,
            "behavior.critic_units": 32}
    over.update(kw)
    return Agent(make_config("walker_walk", "small", "dreamer", **over), 6)


def _episode(policy: Policy, steps: int = 6) -> np.ndarray:
    rng = np.random.default_rng(0)
    images = rng.integers(0, 256, (steps, 64, 64, 3), dtype=np.uint8)
    policy.reset()
    prev, out = np.zeros(6, np.float32), []
    for t in range(steps):
        prev, _ = policy.act(images[t], prev, t == 0)
        out.append(prev)
    return np.stack(out)


@pytest.mark.parametrize("reference", ["dreamerv2", "dreamerpro"])
def test_evaluation_samples_the_posterior_and_repeats_itself(reference):
    agent = _agent(reference=reference)
    # the deterministic (evaluation) mode filters with a sampled posterior, seeded
    a0 = _episode(Policy(agent, mode="deterministic", seed=0))
    assert np.array_equal(a0, _episode(Policy(agent, mode="deterministic", seed=0)))
    assert not np.allclose(a0, _episode(Policy(agent, mode="deterministic", seed=1)))
    if reference == "dreamerv2":
        # trunc_normal's mode is its mean: with the posterior's mean nothing is random any more
        m0 = _episode(Policy(agent, mode="deterministic", seed=0, state_mean=True))
        assert np.array_equal(m0, _episode(Policy(agent, mode="deterministic", seed=1, state_mean=True)))
        assert not np.allclose(a0, m0)


def test_weights_start_glorot_uniform_with_zero_biases():
    agent = _agent()
    layers = [m for m in agent.modules() if isinstance(m, (nn.Linear, nn.Conv2d, nn.ConvTranspose2d))]
    assert layers
    for m in layers:
        if m.bias is not None:
            assert not m.bias.any()
        fan_in, fan_out = nn.init._calculate_fan_in_and_fan_out(m.weight)
        bound = math.sqrt(6.0 / (fan_in + fan_out))
        w = m.weight.detach()
        assert float(w.abs().max()) <= bound + 1e-6
        if m.weight.numel() >= 1000:   # uniform on [-b, b]: std b / sqrt(3)
            assert abs(float(w.std()) - bound / math.sqrt(3)) < 0.1 * bound
    assert all(torch.equal(a, b) for a, b in zip(agent.ac.critic.state_dict().values(),
                                                 agent.ac.slow_critic.state_dict().values()))
    # 'torch' keeps PyTorch's defaults (non-zero biases), as runs before the switch had
    torch_init = _agent(weight_init="torch")
    assert any(m.bias is not None and m.bias.any() for m in torch_init.modules() if isinstance(m, nn.Linear))


def test_periodic_evaluation_subset_is_fixed_and_stratified():
    from sim_bridge.contract.contexts import get_task
    from trainer.learn.evaluate import select_contexts
    from trainer.research.online import build_parser

    walker = get_task("walker_walk")
    for k in (8, 16):
        sub = select_contexts("walker_walk", "test", None, k)
        assert sub == select_contexts("walker_walk", "test", None, k)           # fixed
        pairs = {(c["m"], c["d"]) for c in sub}
        assert len(pairs) == k                                                  # no repeats
        for p in ("m", "d"):                                                    # stratified
            counts = {v: sum(c[p] == v for c in sub) for v in walker.test[p]}
            assert set(counts.values()) == {k // 8}, (p, counts)
    # m and d not tied together (a diagonal would pair the lightest with the least damped)
    sub8 = select_contexts("walker_walk", "test", None, 8)
    ms, ds = [c["m"] for c in sub8], [c["d"] for c in sub8]
    assert abs(np.corrcoef(ms, ds)[0, 1]) < 0.5
    # one parameter: evenly spaced over its list; 0 or more than the grid: all of it
    assert select_contexts("pendulum_swingup", "test", None, 4) == [{"m": 0.2}, {"m": 0.5}, {"m": 1.5}, {"m": 1.8}]
    assert len(select_contexts("walker_walk", "test", None, 0)) == 64
    # protocad-online: periodic = the stratified 8 with 2 episodes, final = every context with 5
    d = build_parser().parse_args([])
    assert (d.eval_max_contexts, d.eval_episodes, d.final_max_contexts, d.final_episodes) == (8, 2, 0, 5)
