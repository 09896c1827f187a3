"""Prototypical context module and augmentation: the equations of ProtoCAD sec. 4.2, checked.

Small tensors, CPU, a few seconds in all.  Each test compares against an independent
reference (explicit loops / closed forms), so a wrong axis, pairing or update fails it.
"""
from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from protocad_ros.model.augment import random_shift, sample_shifts, shift_images
from protocad_ros.model.prototypes import (
    ContextModule,
    same_episode_pairs,
    sinkhorn_knopp,
    swav_cross_entropy,
    swav_loss,
    tc_swav_loss,
)


def _gen(seed=0):
    return torch.Generator().manual_seed(seed)


# --------------------------------------------------------------------------------------------
# Sinkhorn-Knopp
# --------------------------------------------------------------------------------------------
def test_sinkhorn_rows_are_distributions_and_clusters_equipartitioned():
    g = _gen(0)
    N, K = 60, 7
    # Unbalanced scores: every sample prefers prototype 0, so a plain softmax is far from uniform.
    u = F.normalize(torch.randn(N, 5, generator=g), dim=-1)
    c = F.normalize(torch.randn(K, 5, generator=g), dim=-1)
    scores = u @ c.t() + 0.5 * F.one_hot(torch.zeros(N, dtype=torch.long), K)
    scores = scores.requires_grad_(True)

    q = sinkhorn_knopp(scores, num_iters=3, eps=0.05)
    assert q.shape == (N, K) and not q.requires_grad  # targets: no graph
    assert (q >= 0).all()
    torch.testing.assert_close(q.sum(1), torch.ones(N), atol=1e-5, rtol=0)  # rows: distributions

    naive = torch.softmax(scores.detach() / 0.05, dim=1).sum(0)  # cluster mass without SK
    col = q.sum(0)
    uniform = torch.full((K,), N / K)
    # 3 iterations: marginals far closer to uniform N/K than the plain softmax...
    assert (col - uniform).abs().max() < 0.25 * (naive - uniform).abs().max()
    # ...and converged: exactly uniform up to tolerance, rows still exact.
    q_conv = sinkhorn_knopp(scores.double(), num_iters=300, eps=0.05)
    torch.testing.assert_close(q_conv.sum(0), uniform.double(), atol=1e-6, rtol=0)
    torch.testing.assert_close(q_conv.sum(1), torch.ones(N).double(), atol=1e-9, rtol=0)


def test_sinkhorn_matches_plain_space_reference_and_is_stable():
    g = _gen(1)
    N, K, eps = 12, 4, 0.05
    scores = torch.rand(N, K, generator=g, dtype=torch.float64) * 2 - 1
    # Plain-space reference (SwAV's loop; DreamerPro's order: clusters first, then samples).
    Q = torch.exp(scores / eps)
    Q = Q / Q.sum()
    for _ in range(3):
        Q = Q / Q.sum(0, keepdim=True) / K
        Q = Q / Q.sum(1, keepdim=True) / N
    Q = Q * N
    torch.testing.assert_close(sinkhorn_knopp(scores, 3, eps), Q, rtol=1e-9, atol=1e-12)
    # Log space: a tiny eps that overflows exp() in plain space stays finite here.
    q = sinkhorn_knopp(scores.float(), 3, 1e-3)
    assert torch.isfinite(q).all()
    torch.testing.assert_close(q.sum(1), torch.ones(N), atol=1e-5, rtol=0)


# --------------------------------------------------------------------------------------------
# TC-SwAV vs. in-place SwAV
# --------------------------------------------------------------------------------------------
def _random_probs(shape, g):
    return torch.softmax(torch.randn(*shape, generator=g, dtype=torch.float64) * 2, dim=-1)


def _tc_reference(log_w, wbar):
    """Eq. 5 with explicit loops: 1/2 sum_k (wbar_tau,k log w_tau+M/2,k + wbar_tau+M/2,k log
    w_tau,k), negated, averaged over sequences and the M/2 pairs."""
    B, M, K = log_w.shape
    h = M // 2
    total = 0.0
    for b in range(B):
        for j in range(h):  # tau = j in the first half, tau + M/2 in the second
            first_to_second = sum(wbar[b, j, k].item() * log_w[b, j + h, k].item()
                                  for k in range(K))
            second_to_first = sum(wbar[b, j + h, k].item() * log_w[b, j, k].item()
                                  for k in range(K))
            total += -0.5 * (first_to_second + second_to_first)
    return total / (B * h)


def _inplace_reference(log_w, wbar):
    B, M, K = log_w.shape
    total = 0.0
    for b in range(B):
        for t in range(M):
            total += -sum(wbar[b, t, k].item() * log_w[b, t, k].item() for k in range(K))
    return total / (B * M)


def test_tc_swav_pairs_halves_crosswise_and_ablation_pairs_in_place():
    g = _gen(2)
    B, M, K = 2, 6, 3
    log_w = torch.log(_random_probs((B, M, K), g))
    wbar = _random_probs((B, M, K), g)

    tc = tc_swav_loss(log_w, wbar)
    inplace = swav_loss(log_w, wbar)
    assert tc.item() == pytest.approx(_tc_reference(log_w, wbar), rel=1e-12)
    assert inplace.item() == pytest.approx(_inplace_reference(log_w, wbar), rel=1e-12)
    # Non-symmetric example: the pairing matters.
    assert abs(tc.item() - inplace.item()) > 1e-3

    # Crossover direction: a target set equal to the OTHER half's predictions is the optimum
    # of TC (CE = entropy) but not of the in-place loss.
    h = M // 2
    w = log_w.exp()
    swapped = torch.cat([w[:, h:], w[:, :h]], dim=1)  # wbar_(1) = w_(2), wbar_(2) = w_(1)
    entropy = -(w * log_w).sum(-1).mean()
    assert tc_swav_loss(log_w, swapped).item() == pytest.approx(entropy.item(), rel=1e-12)
    assert swav_loss(log_w, w).item() == pytest.approx(entropy.item(), rel=1e-12)
    assert tc_swav_loss(log_w, w).item() > entropy.item() + 1e-3


def test_tc_swav_validates_length_and_masks_pairs():
    g = _gen(3)
    log_w = torch.log(_random_probs((2, 5, 3), g))
    with pytest.raises(ValueError, match="even"):
        tc_swav_loss(log_w, log_w.exp())
    log_w = torch.log(_random_probs((2, 4, 3), g))
    wbar = _random_probs((2, 4, 3), g)
    mask = torch.tensor([[True, False], [False, False]])
    # Only pair (0, 2) of sequence 0 counts.
    expected = 0.5 * (swav_cross_entropy(log_w[0, 2], wbar[0, 0])
                      + swav_cross_entropy(log_w[0, 0], wbar[0, 2]))
    torch.testing.assert_close(tc_swav_loss(log_w, wbar, mask), expected)
    assert tc_swav_loss(log_w, wbar, torch.zeros(2, 2, dtype=torch.bool)).item() == 0.0

    is_first = torch.tensor([[1, 0, 0, 0, 0, 0], [1, 0, 0, 1, 0, 0]], dtype=torch.bool)
    assert same_episode_pairs(is_first).tolist() == [[True, True, True], [False, False, False]]
    is_first = torch.tensor([[0, 0, 0, 1]], dtype=torch.bool)  # reset at step 3
    assert same_episode_pairs(is_first).tolist() == [[True, False]]  # (0,2) ok, (1,3) crosses


# --------------------------------------------------------------------------------------------
# ContextModule
# --------------------------------------------------------------------------------------------
def _module(**kw):
    torch.manual_seed(0)
    kw = {"state_dim": 10, "proj_dim": 4, "num_prototypes": 5, **kw}
    return ContextModule(**kw)


def test_features_unit_norm_and_e_is_probability_weighted_prototype_sum():
    ctx = _module()
    with torch.no_grad():
        ctx.prototypes.mul_(3.0)  # off the sphere, as after an optimizer step
    ctx.normalize_prototypes()
    torch.testing.assert_close(ctx.prototypes.norm(dim=-1), torch.ones(5))
    torch.testing.assert_close(ctx.unit_prototypes(), ctx.prototypes.detach())

    s = torch.randn(3, 7, 10, generator=_gen(4))  # any leading dims
    u, w, e = ctx.features(s)
    assert u.shape == (3, 7, 4) and w.shape == (3, 7, 5) and e.shape == (3, 7, 4)
    torch.testing.assert_close(u.norm(dim=-1), torch.ones(3, 7))
    torch.testing.assert_close(w.sum(-1), torch.ones(3, 7))
    c = ctx.prototypes.detach()
    for b in range(3):
        for t in range(7):
            dots = torch.stack([u[b, t].detach() @ c[k] for k in range(5)])
            w_ref = torch.exp(dots / 0.1) / torch.exp(dots / 0.1).sum()  # eq. 3, T = 0.1
            e_ref = sum(w_ref[k] * c[k] for k in range(5))
            torch.testing.assert_close(w[b, t], w_ref, atol=1e-5, rtol=1e-5)
            torch.testing.assert_close(e[b, t], e_ref, atol=1e-5, rtol=1e-5)


def test_ema_first_update_copies_then_moves_by_eta():
    ctx = _module(ema=0.05)
    with torch.no_grad():  # online and target differ before the first update
        ctx.projector.weight.add_(1.0)
        ctx.projector.bias.add_(-2.0)
    ctx.update_target()
    for tgt, src in zip(ctx.target_projector.parameters(), ctx.projector.parameters()):
        assert torch.equal(tgt, src)  # full copy
    with torch.no_grad():
        ctx.projector.weight.mul_(-1.5).add_(0.3)
        ctx.projector.bias.add_(4.0)
    before = [p.clone() for p in ctx.target_projector.parameters()]
    ctx.update_target()
    for old, tgt, src in zip(before, ctx.target_projector.parameters(), ctx.projector.parameters()):
        torch.testing.assert_close(tgt - old, 0.05 * (src - old), atol=1e-6, rtol=1e-6)
        assert not torch.allclose(tgt, src)
    assert int(ctx.ema_updates) == 2
    # The counter is state: a restored module does not re-copy.
    restored = _module(ema=0.05)
    restored.load_state_dict(ctx.state_dict())
    assert int(restored.ema_updates) == 2


def test_tc_swav_pairs_are_exactly_m_over_2_apart():
    ctx = _module()                                  # drop_first_steps = 1 (DreamerPro warm_up)
    first, second = ctx.tc_pairs(50)                 # the paper's M = 50
    assert first.tolist() == list(range(1, 25)) and ((second - first) == 25).all()
    first, second = ctx.tc_pairs(51)                 # DreamerPro's length 51
    assert first.tolist() == list(range(1, 26)) and second.tolist() == list(range(26, 51))
    first, second = _module(drop_first_steps=0).tc_pairs(50)
    assert first.tolist() == list(range(25)) and second.tolist() == list(range(25, 50))
    assert ctx.kept_steps(50) == slice(1, 50)        # the in-place ablation scores steps 1..49
    with pytest.raises(ValueError):
        ctx.tc_pairs(2)


def test_tc_swav_loss_at_m_50_uses_the_m_over_2_pairs():
    g = _gen(11)
    ctx = _module(prototype_freeze=0)
    s1, s2 = torch.randn(2, 50, 10, generator=g), torch.randn(2, 50, 10, generator=g)
    loss, _ = ctx.loss(s1, s2, step=0)
    c = ctx.prototypes.detach()
    log_w = torch.log_softmax(F.normalize(ctx.projector(s1[:, 1:]), dim=-1) @ c.t() / 0.1, -1)
    ubar = F.normalize(ctx.target_projector(s2[:, 1:]), dim=-1)
    wbar = sinkhorn_knopp((ubar @ c.t()).reshape(-1, 5), 3, 0.05).reshape(2, 49, 5)
    # kept index i is time step i + 1: pairs (1, 26) .. (24, 49) are kept (0, 25) .. (23, 48)
    idx = torch.cat([torch.arange(0, 24), torch.arange(25, 49)])
    assert loss.item() == pytest.approx(_tc_reference(log_w.detach()[:, idx], wbar[:, idx]), rel=1e-5)


def test_from_config_maps_config_names():
    from types import SimpleNamespace
    cfg = SimpleNamespace(proto_dim=6, num_prototypes=9, temperature=0.2, sinkhorn_iters=4,
                          sinkhorn_eps=0.0125, ema=0.1, freeze_prototypes_updates=7,
                          drop_first_steps=0, sinkhorn_over="half_means", cross_view_scale=0.5,
                          both_views_train=True)
    ctx = ContextModule.from_config(cfg, state_dim=11, temporal_consistency=False)
    assert ctx.prototypes.shape == (9, 6) and ctx.projector.in_features == 11
    assert (ctx.temperature, ctx.sinkhorn_iters, ctx.sinkhorn_eps, ctx.ema) == (0.2, 4, 0.0125, 0.1)
    assert ctx.prototype_freeze == 7 and ctx.drop_first_steps == 0
    assert not ctx.temporal_consistency
    assert (ctx.sinkhorn_over, ctx.cross_view_scale, ctx.both_views_train) == ("half_means", 0.5, True)


def test_loss_uses_target_projector_sinkhorn_and_crossover():
    g = _gen(5)
    ctx = _module(prototype_freeze=0)
    with torch.no_grad():  # make target and online projector differ
        ctx.target_projector.weight.add_(torch.randn(4, 10, generator=g))
    s1 = torch.randn(3, 9, 10, generator=g)
    s2 = torch.randn(3, 9, 10, generator=g)
    loss, metrics = ctx.loss(s1, s2, step=0)
    # Reference: steps 1..8 kept (M=9, drop 1), predictions from s1, targets from s2.
    k1, k2 = s1[:, 1:], s2[:, 1:]
    c = ctx.prototypes.detach()
    log_w = torch.log_softmax(F.normalize(ctx.projector(k1), dim=-1) @ c.t() / 0.1, -1)
    ubar = F.normalize(ctx.target_projector(k2), dim=-1)
    wbar = sinkhorn_knopp((ubar @ c.t()).reshape(-1, 5), 3, 0.05).reshape(3, 8, 5)
    assert loss.item() == pytest.approx(_tc_reference(log_w.detach(), wbar), rel=1e-5)
    assert float(metrics["swav_loss"]) == pytest.approx(loss.item())
    assert 1.0 <= float(metrics["swav_target_perplexity"]) <= 5.0 + 1e-4

    ablation = _module(prototype_freeze=0, temporal_consistency=False)
    ablation.load_state_dict(ctx.state_dict())
    loss_ab, _ = ablation.loss(s1, s2, step=0)
    assert loss_ab.item() == pytest.approx(_inplace_reference(log_w.detach(), wbar), rel=1e-5)
    assert abs(loss_ab.item() - loss.item()) > 1e-4

    # is_first: a reset in the middle removes the straddling pairs.
    is_first = torch.zeros(3, 9, dtype=torch.bool)
    is_first[0, 6] = True  # seq 0: kept steps 1..8, halves 1..4 / 5..8; reset at 6
    loss_m, _ = ctx.loss(s1, s2, step=0, is_first=is_first)
    mask = torch.ones(3, 4, dtype=torch.bool)
    mask[0] = torch.tensor([True, False, False, False])  # pair (1,5) ok; (2,6)..(4,8) cross
    assert loss_m.item() == pytest.approx(tc_swav_loss(log_w, wbar, mask).item(), rel=1e-5)


def _grads(module):
    return {name: (p.grad is not None and p.grad.abs().sum().item() > 0)
            for name, p in module.named_parameters()}


def test_gradients_follow_the_paper():
    g = _gen(6)
    ctx = _module(prototype_freeze=10)
    s1 = torch.randn(2, 7, 10, generator=g, requires_grad=True)
    s2 = torch.randn(2, 7, 10, generator=g, requires_grad=True)

    # After the freeze window: the SwAV loss trains projector + prototypes + the view-1 states,
    # never the target projector nor view-2 states (targets are constants).
    loss, _ = ctx.loss(s1, s2, step=10)
    loss.backward()
    grads = _grads(ctx)
    assert grads["projector.weight"] and grads["projector.bias"] and grads["prototypes"]
    assert all(p.grad is None for p in ctx.target_projector.parameters())
    assert not any(p.requires_grad for p in ctx.target_projector.parameters())
    assert s1.grad is not None and s1.grad.abs().sum() > 0
    assert s2.grad is None

    # Inside the freeze window: projector yes, prototypes no.
    ctx.zero_grad(set_to_none=True)
    loss, metrics = ctx.loss(s1, s2, step=9)
    loss.backward()
    grads = _grads(ctx)
    assert grads["projector.weight"] and not grads["prototypes"]
    assert float(metrics["prototypes_frozen"]) == 1.0

    # Context features feed downstream losses (decoder / actor / critic on x = (s, u, e)).
    ctx.zero_grad(set_to_none=True)
    u, w, e = ctx.features(s1)
    (e * torch.randn_like(e)).sum().backward()  # e: prototypes (directly and via w) + projector
    grads = _grads(ctx)
    assert grads["prototypes"] and grads["projector.weight"]
    # Exactly d/dc of sum_k softmax(u.c/T)_k c_k: both the direct c_k term and the one via w.
    ctx.zero_grad(set_to_none=True)
    v = torch.randn(2, 7, 4, generator=g)
    (ctx.features(s1)[2] * v).sum().backward()
    c = ctx.prototypes.detach().clone().requires_grad_(True)
    u_ref = F.normalize(s1.detach() @ ctx.projector.weight.detach().t()
                        + ctx.projector.bias.detach(), dim=-1)
    e_ref = torch.softmax(u_ref @ c.t() / 0.1, dim=-1) @ c
    (e_ref * v).sum().backward()
    torch.testing.assert_close(ctx.prototypes.grad, c.grad)
    ctx.zero_grad(set_to_none=True)
    u, w, e = ctx.features(s1)
    (u * torch.randn_like(u)).sum().backward()  # u: projector only
    grads = _grads(ctx)
    assert grads["projector.weight"] and not grads["prototypes"]

    # The freeze window also covers gradients arriving through e.
    ctx.zero_grad(set_to_none=True)
    u, w, e = ctx.features(s1)
    (e * torch.randn_like(e)).sum().backward()
    assert ctx.mask_frozen_prototype_grad(step=9) and ctx.prototypes.grad is None
    assert ctx.projector.weight.grad is not None
    ctx.features(s1)[2].sum().backward()
    assert not ctx.mask_frozen_prototype_grad(step=10) and ctx.prototypes.grad is not None


# --------------------------------------------------------------------------------------------
# Random shift
# --------------------------------------------------------------------------------------------
def test_random_shift_one_shift_per_sequence_and_deterministic():
    g = _gen(7)
    B, T, C, H, W = 4, 5, 3, 12, 12
    frame = torch.rand(B, 1, C, H, W, generator=g)
    images = frame.expand(B, T, C, H, W).contiguous()  # same frame at every t
    images[1] = images[0]  # two sequences with identical content
    out = random_shift(images, pad=3, generator=_gen(11))
    assert out.shape == images.shape
    # Same shift at every time step: identical input frames -> identical output frames.
    for t in range(1, T):
        torch.testing.assert_close(out[:, t], out[:, 0], atol=0, rtol=0)
    # Different shifts across the batch: identical content, different output.
    assert not torch.allclose(out[0], out[1])
    # Deterministic given the generator; a different seed gives different views.
    torch.testing.assert_close(random_shift(images, 3, _gen(11)), out, atol=0, rtol=0)
    assert not torch.allclose(random_shift(images, 3, _gen(12)), out)
    # Shifts are continuous and within +-pad.
    s = sample_shifts(1000, 3, _gen(13))
    assert s.abs().max() <= 3 and s.min() < -2.5 and s.max() > 2.5
    assert (s - s.round()).abs().max() > 0.1
    # And a real shift moves content with time-varying frames too.
    moving = torch.rand(B, T, C, H, W, generator=g)
    shifted = random_shift(moving, 3, _gen(14))
    shifts = sample_shifts(B, 3, _gen(14))
    torch.testing.assert_close(shifted, shift_images(moving, shifts, 3))


def test_shift_images_identity_integer_and_bilinear_half_pixel():
    g = _gen(8)
    B, T, C, H, W = 2, 3, 2, 8, 9
    x = torch.rand(B, T, C, H, W, generator=g, dtype=torch.float64)
    zero = torch.zeros(B, 2, dtype=torch.float64)
    torch.testing.assert_close(shift_images(x, zero, 3), x)  # zero shift = identity

    # Integer shift (dx=+2, dy=-1) for sequence 0, zero for sequence 1; replicate fill.
    shifts = torch.tensor([[2.0, -1.0], [0.0, 0.0]], dtype=torch.float64)
    out = shift_images(x, shifts, 3)
    for yy in range(H):
        for xx in range(W):
            sy, sx = min(max(yy - 1, 0), H - 1), min(max(xx + 2, 0), W - 1)
            torch.testing.assert_close(out[0, :, :, yy, xx], x[0, :, :, sy, sx])
    torch.testing.assert_close(out[1], x[1])

    # Half-pixel shift in x: bilinear average of horizontal neighbours (clamped at the edge).
    half = torch.tensor([[0.5, 0.0], [-0.5, 0.0]], dtype=torch.float64)
    out = shift_images(x, half, 3)
    right = torch.cat([x[..., 1:], x[..., -1:]], dim=-1)
    left = torch.cat([x[..., :1], x[..., :-1]], dim=-1)
    torch.testing.assert_close(out[0], 0.5 * (x[0] + right[0]))
    torch.testing.assert_close(out[1], 0.5 * (x[1] + left[1]))
    # Quarter-pixel in y: 3/4 own row + 1/4 the next row.
    quarter = torch.tensor([[0.0, 0.25], [0.0, 0.25]], dtype=torch.float64)
    down = torch.cat([x[..., 1:, :], x[..., -1:, :]], dim=-2)
    torch.testing.assert_close(shift_images(x, quarter, 3), 0.75 * x + 0.25 * down)

    # Single frames (B, C, H, W) and input validation.
    torch.testing.assert_close(shift_images(x[:, 0], half, 3), out[:, 0])
    with pytest.raises(TypeError):
        random_shift(torch.zeros(1, 1, 3, 4, 4, dtype=torch.uint8))
    with pytest.raises(ValueError):
        shift_images(x, torch.full((B, 2), 4.0, dtype=torch.float64), 3)


def test_reconstruction_trains_the_context_module_only_when_asked():
    """Algorithm 1 (default): a loss on x = (s, u, e) reaches projector and prototypes; the
    Fig. 1 reading (recon_trains_context = false): it reaches s only."""
    for train_module, reaches_module in ((True, True), (False, False)):
        ctx = _module(prototype_freeze=0)
        s = torch.randn(4, 10, generator=_gen(3), requires_grad=True)
        u, w, e = ctx.features(s, train_module=train_module)
        (u.sum() + e.pow(2).sum() + w[:, 0].sum()).backward()
        grads = _grads(ctx)
        assert grads["prototypes"] is reaches_module
        assert any(v for k, v in grads.items() if k.startswith("projector.")) is reaches_module
        assert s.grad is not None and s.grad.abs().sum() > 0
        # the features themselves do not depend on the switch
        u2, w2, e2 = ctx.features(s.detach(), train_module=not train_module)
        torch.testing.assert_close((u.detach(), w.detach(), e.detach()), (u2, w2, e2))


# --------------------------------------------------------------------------------------------
# The settings beside the paper's (issue 51) and the module's health
# --------------------------------------------------------------------------------------------
def test_half_means_sinkhorn_gives_each_half_one_target_from_its_mean_projection():
    g = _gen(11)
    ctx = _module(sinkhorn_over="half_means")
    s2 = torch.randn(3, 9, 10, generator=g)
    ubar = ctx.target_projections(s2[:, 1:])              # kept steps 1..8
    halves = (torch.arange(0, 4), torch.arange(4, 8))     # (1..4) and (5..8) among the kept
    wbar = ctx.targets(ubar, halves)
    means = torch.stack([F.normalize(ubar[:, h].mean(1), dim=-1) for h in halves], 1)
    ref = sinkhorn_knopp((means @ ctx.prototypes.detach().t()).reshape(6, 5), 3, 0.05).reshape(3, 2, 5)
    for i, h in enumerate(halves):
        assert torch.allclose(wbar[:, h], ref[:, i:i + 1].expand(3, 4, 5), atol=1e-6)
    assert torch.allclose(wbar.sum(-1), torch.ones(3, 8), atol=1e-5)
    # The loss pairs each half's target with the other half's predictions, as eq. 5.
    s1 = torch.randn(3, 9, 10, generator=g)
    loss, _ = ctx.loss(s1, s2, step=0)
    log_w = torch.log_softmax(ctx.project(s1[:, 1:]) @ ctx.prototypes.detach().t() / 0.1, -1)
    assert loss.item() == pytest.approx(_tc_reference(log_w.detach(), wbar), rel=1e-5)


def test_cross_view_term_adds_the_same_time_swav_and_both_views_train_view_2():
    g = _gen(12)
    s1 = torch.randn(2, 9, 10, generator=g, requires_grad=True)
    s2 = torch.randn(2, 9, 10, generator=g, requires_grad=True)
    paper = _module()
    crossed = _module(cross_view_scale=0.5)
    tc, _ = paper.loss(s1, s2, step=0)
    both, _ = crossed.loss(s1, s2, step=0)
    log_w = torch.log_softmax(paper.project(s1[:, 1:]) @ paper.prototypes.detach().t() / 0.1, -1)
    wbar = paper.targets(paper.target_projections(s2[:, 1:]))
    assert both.item() == pytest.approx(tc.item() + 0.5 * _inplace_reference(log_w.detach(), wbar), rel=1e-5)
    tc.backward()
    assert s2.grad is None                                   # the paper: view 2 yields targets only
    views = _module(both_views_train=True)
    loss, _ = views.loss(s1, s2, step=0)
    loss.backward()
    assert s2.grad is not None and s2.grad.abs().sum() > 0   # view 2's predictions learn view 1's targets
    swapped, _ = _module().loss(s2, s1, step=0)
    assert loss.item() == pytest.approx(0.5 * (tc.item() + swapped.item()), rel=1e-5)


def test_swav_runs_in_float32_under_bfloat16_autocast():
    g = _gen(13)
    ctx = _module()
    s1, s2 = torch.randn(2, 9, 10, generator=g), torch.randn(2, 9, 10, generator=g)
    ref, _ = ctx.loss(s1, s2, step=0)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        loss, metrics = ctx.loss(s1.bfloat16(), s2.bfloat16(), step=0)
    assert loss.dtype == torch.float32 and metrics["swav_pred_entropy"].dtype == torch.float32
    # bf16 inputs round s itself; the SwAV arithmetic after that is float32 (no 1/32 steps).
    ref16, _ = ctx.loss(s1.bfloat16().float(), s2.bfloat16().float(), step=0)
    assert loss.item() == pytest.approx(ref16.item(), rel=1e-6)


def test_health_reads_a_collapsed_and_a_context_coding_batch():
    from trainer.learn.context_health import collapse_reason

    ctx = _module(num_prototypes=4, proj_dim=4)
    B, M, K = 4, 6, 4
    # Collapsed: every projection the same direction, predictions and targets uniform.
    one = F.normalize(torch.ones(B, M, 4), dim=-1)
    uniform = torch.full((B, M, K), 1 / K)
    h = ctx.health(one, uniform, one, uniform)
    assert float(h["proj_cosine"]) == pytest.approx(1.0, abs=1e-5)
    assert float(h["swav_pred_top"]) == pytest.approx(0.25) and float(h["swav_target_top"]) == pytest.approx(0.25)
    assert float(h["swav_pred_perplexity"]) == pytest.approx(4.0, rel=1e-4)
    reason = collapse_reason({k: float(v) for k, v in h.items()}, K)
    assert "cone" in reason and "near uniform" in reason
    # A code of the context: sequence b sits on prototype b at every step, u = c_b.
    eye = torch.eye(4)
    u = eye[:, None, :].expand(B, M, 4).clone()
    w = eye[:, None, :].expand(B, M, K).clone()
    h = ctx.health(u, w, u, w)
    # Pairs within a sequence have cosine 1, across sequences 0: (M - 1) / (BM - 1) of them.
    assert float(h["proj_cosine"]) == pytest.approx((M - 1) / (B * M - 1), abs=1e-5)
    assert float(h["modal_share"]) == 1.0 and float(h["proj_between_share"]) == pytest.approx(1.0)
    assert float(h["swav_pred_top"]) == 1.0 and float(h["swav_pred_perplexity"]) == pytest.approx(4.0, rel=1e-4)
    assert collapse_reason({k: float(v) for k, v in h.items()}, K) is None
    # The prototypes' cosine to their seeded start: 1 until they move.
    assert float(h["proto_init_cosine"]) == pytest.approx(1.0)
    with torch.no_grad():
        ctx.prototypes.mul_(-1)
    assert float(ctx.health(u, w, u, w)["proto_init_cosine"]) == pytest.approx(-1.0)
