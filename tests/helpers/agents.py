"""Agents for tests: real rendered training batches, tiny checkpoints, saved agents with known
update counts."""
from __future__ import annotations

import numpy as np

#: A model small enough for CPU tests, as config overrides (helpers.bags.TINY: as CLI options).
TINY_OVERRIDES = {"world_model.deter": 32, "world_model.hidden": 32, "world_model.stoch": 8,
                  "world_model.cnn_depth": 8, "world_model.mlp_units": 32, "behavior.actor_units": 32,
                  "behavior.critic_units": 32, "context.num_prototypes": 8, "context.proto_dim": 8,
                  "train.batch_size": 4, "train.seq_len": 8}


def render_batch(task: str = "pendulum_swingup", batch: int = 4, length: int = 16, seed: int = 0):
    """Real rendered frames with random actions, in the training-batch layout."""
    from sim_bridge.sim.envs import ContextDMCEnv

    rng = np.random.default_rng(seed)
    env = ContextDMCEnv(task, seed=seed)
    A = env.action_dim
    out = {"image": np.zeros((batch, length, 64, 64, 3), np.uint8),
           "action": np.zeros((batch, length, A), np.float32),
           "reward": np.zeros((batch, length), np.float32),
           "discount": np.ones((batch, length), np.float32),
           "is_first": np.zeros((batch, length), bool)}
    try:
        for b in range(batch):
            obs = env.reset()
            out["image"][b, 0], out["is_first"][b, 0] = obs.image, True
            for t in range(1, length):
                a = rng.uniform(-1, 1, A).astype(np.float32)
                obs = env.step(a)
                out["image"][b, t], out["action"][b, t], out["reward"][b, t] = obs.image, a, obs.reward
    finally:
        env.close()
    return out


def tiny_checkpoint(path, task="pendulum_swingup", action_dim=1):
    """A checkpoint of an untrained TINY_OVERRIDES agent (env_steps 1234); its path."""
    from protocad_ros.checkpoint.agent_file import save_checkpoint
    from protocad_ros.model.agent import Agent
    from protocad_ros.model.config import make_config

    cfg = make_config(task, "small", "protocad", **TINY_OVERRIDES)
    return save_checkpoint(path, Agent(cfg, action_dim), {"env_steps": 1234})


def save_agent(path, updates: int, seed: int = 0, task: str = "pendulum_swingup"):
    """A small-preset agent saved at `path` with `updates` updates (env_steps 100 per update),
    so a node's reload shows in the update count it reports; the agent."""
    from protocad_ros.checkpoint.agent_file import save_checkpoint
    from protocad_ros.model.agent import Agent
    from protocad_ros.model.config import make_config

    agent = Agent(make_config(task, "small", **{"train.seed": seed}), 1)
    agent.updates.fill_(updates)
    save_checkpoint(path, agent, counters={"env_steps": 100 * updates})
    return agent


def bf16_request_policy(dst):
    """The shipped walker policy as a machine with bf16 arithmetic writes it when its run asked
    for `--precision bfloat16`: the same bf16 weights, `train.precision: bfloat16` in its config
    (the shipped file itself says `auto`; the one shipped before 2026-12-06 said bfloat16).
    None where no walker policy ships."""
    import torch

    from protocad_ros.policy import shipped_policy

    src = shipped_policy("walker_walk")
    if src is None:
        return None
    payload = torch.load(src, map_location="cpu", weights_only=True)
    payload["config"]["train"]["precision"] = "bfloat16"
    torch.save(payload, dst)
    return dst
