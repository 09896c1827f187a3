"""DrQ, the model-free baseline: its pieces against hand-computed examples, learning on real
frames, training from the MCAP logs of protocad-online, and the policy node serving it."""
from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest
import torch
from helpers.agents import render_batch

from protocad_ros.checkpoint.agent_file import load_checkpoint, save_checkpoint
from protocad_ros.model.agent import make_agent
from protocad_ros.model.augment import crop_images, random_crop
from protocad_ros.model.config import ConfigError, make_config
from protocad_ros.model.drq import DrQAgent, soft_q_target, soft_update, temperature_loss, transitions
from protocad_ros.policy import Policy

pytestmark = pytest.mark.usefixtures("one_torch_thread")

TASK = "pendulum_swingup"


def tiny_drq(**kw):
    over = {"drq.num_filters": 4, "drq.hidden_dim": 32, "drq.feature_dim": 8,
            "train.batch_size": 16}
    over.update(kw)
    return make_config(TASK, "small", "drq", **over)


# ---- config ---------------------------------------------------------------------------------------
def test_drq_settings_are_the_authors_dmc_values():
    """denisyarats/drq config.yaml @dd040f1 and the DrQ paper (batch 512)."""
    cfg = make_config("walker_walk", "paper", "drq")
    d = cfg.drq
    assert (d.frame_stack, d.num_filters, d.num_conv_layers, d.feature_dim) == (3, 32, 4, 50)
    assert (d.hidden_dim, d.hidden_depth, d.log_std_min, d.log_std_max) == (1024, 2, -10.0, 2.0)
    assert (d.discount, d.init_temperature, d.lr) == (0.99, 0.1, 1e-3)
    assert (d.actor_update_frequency, d.critic_tau, d.critic_target_update_frequency) == (2, 0.01, 2)
    assert (d.image_pad, d.target_augs, d.q_augs) == (4, 2, 2)
    assert (cfg.train.batch_size, cfg.train.seq_len) == (512, 4)
    assert cfg.train.collect_interval == 500      # one update per agent step of a 1000-step episode
    assert cfg.spec.family == "model_free" and not cfg.uses_context and not cfg.uses_decoder
    with pytest.raises(ConfigError, match="dreamerv3_sizes"):
        make_config("walker_walk", "dreamerv3_sizes", "drq")
    with pytest.raises(ConfigError, match="frame_stack"):
        make_config("walker_walk", "small", "drq", **{"train.seq_len": 8})
    assert make_config("walker_walk", "small", "drq", **{"drq.frame_stack": 2}).train.seq_len == 3


# ---- pieces against hand-computed examples ------------------------------------------------------
def test_pad_and_crop_per_sample():
    img = torch.tensor([[1.0, 2.0], [3.0, 4.0]]).reshape(1, 1, 2, 2)
    padded = torch.nn.functional.pad(img, (1, 1, 1, 1), mode="replicate")
    # replicate pad by 1: [[1,1,2,2],[1,1,2,2],[3,3,4,4],[3,3,4,4]]
    three = padded.expand(3, 1, 4, 4)
    offsets = torch.tensor([[1, 1], [2, 0], [0, 2]])     # (ox, oy) per sample
    out = crop_images(three, offsets, 2, 2)
    assert out[0, 0].tolist() == [[1, 2], [3, 4]]        # the centre: the original
    assert out[1, 0].tolist() == [[2, 2], [2, 2]]        # right edge, top rows
    assert out[2, 0].tolist() == [[3, 3], [3, 3]]        # left edge, bottom rows

    # random_crop: one offset per sample (a batch of one image gets many different crops),
    # each one of the (2 pad + 1)^2 integer crops of the padded image.
    pad = 2
    base = torch.arange(36.0).reshape(1, 1, 6, 6)
    crops = random_crop(base.expand(64, 1, 6, 6).contiguous(), pad,
                        torch.Generator().manual_seed(0))
    padded = torch.nn.functional.pad(base, (pad,) * 4, mode="replicate")[0, 0]
    allowed = {tuple(padded[oy:oy + 6, ox:ox + 6].flatten().tolist())
               for ox in range(2 * pad + 1) for oy in range(2 * pad + 1)}
    seen = {tuple(c[0].flatten().tolist()) for c in crops}
    assert seen <= allowed and len(seen) > 10
    again = random_crop(base.expand(64, 1, 6, 6).contiguous(), pad,
                        torch.Generator().manual_seed(0))
    assert torch.equal(crops, again)                     # seeded


def test_soft_q_target_with_the_entropy_term():
    r, d = torch.tensor([1.0, 1.0]), torch.tensor([1.0, 0.0])
    q1, q2, logp = torch.tensor([2.0, 2.0]), torch.tensor([3.0, 3.0]), torch.tensor([-1.0, -1.0])
    y = soft_q_target(r, d, q1, q2, logp, alpha=0.1, gamma=0.99)
    # 1 + 0.99 * (min(2, 3) - 0.1 * (-1)) = 1 + 0.99 * 2.1 = 3.079; a terminal step keeps r only
    assert torch.allclose(y, torch.tensor([3.079, 1.0]))


def test_temperature_loss_and_its_direction():
    log_alpha = torch.tensor(math.log(0.1), requires_grad=True)
    logp = torch.tensor([-1.0, 1.0])        # entropies 1 and -1
    loss = temperature_loss(log_alpha, logp, target_entropy=-2.0)
    # 0.1 * mean(1 + 2, -1 + 2) = 0.1 * 2 = 0.2; d/dlog_alpha = alpha * 2 = 0.2
    assert loss.item() == pytest.approx(0.2)
    loss.backward()
    assert log_alpha.grad.item() == pytest.approx(0.2)   # entropy above target: alpha shrinks


def test_target_network_ema():
    src, tgt = torch.nn.Linear(1, 1), torch.nn.Linear(1, 1)
    torch.nn.init.ones_(src.weight), torch.nn.init.zeros_(tgt.weight)
    soft_update(tgt, src, 0.01)
    assert tgt.weight.item() == pytest.approx(0.01)
    soft_update(tgt, src, 0.01)
    assert tgt.weight.item() == pytest.approx(0.01 + 0.99 * 0.01)   # 0.0199

    # In the agent: every 2nd update (0, 2, ...) the targets move tau of the way.
    agent = DrQAgent(tiny_drq(), 1)
    batch = render_batch(TASK, batch=4, length=4)
    before = [p.detach().clone() for p in agent.critic_target.parameters()]
    agent.train_step(batch)                                    # update 0: soft update
    online = [p.detach().clone() for p in agent.critic.parameters()]
    for b, t, o in zip(before, agent.critic_target.parameters(), online):
        assert torch.allclose(t, 0.99 * b + 0.01 * o, atol=1e-6)
    after0 = [p.detach().clone() for p in agent.critic_target.parameters()]
    agent.train_step(batch)                                    # update 1: none
    assert all(torch.equal(a, t) for a, t in zip(after0, agent.critic_target.parameters()))


def test_frame_stacks_from_windows_repeat_the_first_frame():
    B, T = 1, 4
    image = torch.arange(T, dtype=torch.uint8).reshape(1, T, 1, 1, 1).expand(B, T, 64, 64, 3)
    first = torch.tensor([[False, False, True, False]])
    batch = {"image": image, "is_first": first, "action": torch.arange(4.0).reshape(1, 4, 1),
             "reward": torch.arange(4.0).reshape(1, 4), "discount": torch.ones(1, 4)}
    obs, a, r, d, nxt, valid = transitions(batch, 3)
    frame = lambda x: x[0, :, 0, 0, 0].tolist()  # noqa: E731
    assert frame(obs) == [2, 2, 2]       # the episode starts at step 2: earlier frames replaced
    assert frame(nxt) == [2, 2, 3]
    assert a.tolist() == [[3.0]] and r.tolist() == [3.0] and valid.tolist() == [True]
    first = torch.tensor([[False, False, False, True]])
    assert transitions({**batch, "is_first": first}, 3)[-1].tolist() == [False]  # no transition


def test_a_batch_without_transitions_changes_nothing_and_stays_finite():
    """Windows that end where an episode starts are no transitions: masked out, not NaN."""
    agent = DrQAgent(tiny_drq(), 1)
    batch = render_batch(TASK, batch=4, length=4)
    batch["is_first"][:, -1] = True
    before = {k: v.detach().clone() for k, v in agent.state_dict().items() if "target" not in k}
    m = agent.train_step(batch)
    assert all(np.isfinite(v) for v in m.values()) and m["valid_transitions"] == 0
    after = agent.state_dict()
    assert all(torch.equal(before[k], after[k]) for k in before if k != "updates")


# ---- learning ------------------------------------------------------------------------------------
def test_critic_loss_falls_on_real_frames():
    torch.manual_seed(0)
    batch = render_batch("walker_walk", batch=16, length=4, seed=1)
    assert batch["image"].std() > 5 and np.abs(batch["reward"][:, -1]).sum() > 0
    agent = make_agent(tiny_drq(), 6)
    losses = [agent.train_step(batch)["critic_loss"] for _ in range(40)]
    assert all(np.isfinite(losses))
    assert np.mean(losses[-5:]) < 0.5 * np.mean(losses[:5]), losses


def test_checkpoint_round_trip_and_policy(tmp_path):
    agent = make_agent(tiny_drq(), 1)
    batch = render_batch(TASK, batch=4, length=4)
    agent.train_step(batch)
    path = save_checkpoint(tmp_path / "drq.pt", agent, {"env_steps": 10})
    loaded, counters = load_checkpoint(path)
    assert isinstance(loaded, DrQAgent) and counters["env_steps"] == 10
    assert int(loaded.updates) == 1
    for a, b in zip(agent.state_dict().values(), loaded.state_dict().values()):
        assert torch.equal(a, b)
    p1, p2 = Policy(agent), Policy(loaded)
    prev, first_run = np.zeros(1, np.float32), []
    for t in range(4):
        a1, f1 = p1.act(batch["image"][0, t], prev, t == 0)
        a2, _ = p2.act(batch["image"][0, t], prev, t == 0)
        np.testing.assert_array_equal(a1, a2)
        assert a1.shape == (1,) and f1.u.shape == (0,)
        first_run.append(a1)
        prev = a1
    # The frame stack is the policy's state: after a reset the same frames give the same actions.
    p1.reset()
    prev = np.zeros(1, np.float32)
    for t in range(4):
        a1, _ = p1.act(batch["image"][0, t], prev, t == 0)
        np.testing.assert_array_equal(a1, first_run[t])
        prev = a1


@pytest.mark.process
def test_compare_runs_drq_online_and_protocad_train_learns_from_its_logs(tmp_path):
    """protocad-compare runs DrQ as an ordinary protocad-online run, which collects into MCAP bags
    and trains from them; protocad-train then continues from the same logs offline (DrQ is
    off-policy)."""
    out_dir = tmp_path / "grid"
    cmd = [sys.executable, "-m", "trainer.research.compare", "--tasks", TASK, "--variants", "drq",
           "--seeds", "0", "--env-steps", "800", "--jobs", "1", "--out", str(out_dir), "--",
           "--preset", "small", "--time-limit", "200", "--prefill-episodes", "2",
           "--updates-per-episode", "20", "--eval-every", "0", "--eval-episodes", "1", "--final-episodes", "1",
           "--final-max-contexts", "1", "--log-every", "10", "--set", "train.batch_size=32"]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stdout + out.stderr
    results = json.loads((out_dir / "results.json").read_text())
    assert [r["variant"] for r in results["runs"]] == ["drq"]
    run = out_dir / TASK / "drq" / "seed0"
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    train = [r for r in rows if r.get("kind") == "train"]
    assert train and all("critic_loss" in r and "actor_loss" in r for r in train)
    assert len(list((run / "bags").iterdir())) == 4
    assert json.loads((run / "run.json").read_text())["result"]["status"] == "finished"

    offline = tmp_path / "offline"
    cmd = [sys.executable, "-m", "trainer.learn.train", "--logs", str(run / "bags"), "--task", TASK,
           "--variant", "drq", "--preset", "small", "--updates", "6", "--run-dir", str(offline),
           "--no-progress", "--set", "train.batch_size=32", "--cache-dir", str(tmp_path / "c")]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stdout + out.stderr
    agent, _ = load_checkpoint(offline / "checkpoints" / "latest.pt")
    assert isinstance(agent, DrQAgent) and int(agent.updates) == 6


# ---- the policy node serves DrQ -----------------------------------------------------------------
@pytest.mark.ros
@pytest.mark.process
def test_policy_node_serves_a_drq_checkpoint(spawn, tmp_path):
    from helpers import wait_until
    from helpers.policy import START, Feeder, policy_args
    from helpers.ros import Probe

    agent = make_agent(make_config(TASK, "small", "drq", **{"train.seed": 3}), 1)
    agent.updates.fill_(11)
    ckpt = save_checkpoint(tmp_path / "drq.pt", agent, {"env_steps": 1100})
    probe = Probe("drq_probe")
    try:
        f = Feeder(probe)
        policy = spawn("policy", *policy_args(f"checkpoint:={ckpt}"))
        wait_until(f.ready, START, "the policy to match")
        wait_until(lambda: probe.node_diag("policy").get("checkpoint_updates") == "11", 30,
                   "the DrQ checkpoint to be served")
        steps = [(10, 0, 0, True), (20, 1, 0, False), (30, 2, 0, False), (40, 3, 0, False),
                 (50, 0, 1, True), (60, 1, 1, False)]
        for i, (stamp, step, episode, first) in enumerate(steps):
            f.obs(stamp, step, episode=episode, is_first=first)
            f.wait_answers(i + 1, f"the answer to {stamp}")
        assert f.stamps() == [s[0] for s in steps]
        ref = Policy(agent, mode="deterministic")   # the node's default mode
        prev = np.zeros(1, np.float32)
        for (stamp, _, _, first), msg in zip(steps, list(f.actions)):
            a, _ = ref.act(f.images[stamp], prev, first)
            np.testing.assert_allclose(np.asarray(msg.effort), a, atol=1e-5)
            prev = a
        assert policy.alive() and policy.stop() == 0
        assert "Traceback" not in policy.log_path.read_text()
    finally:
        probe.close()
