"""make_agent: the agent of a config's variant family (no ROS).

    agent = make_agent(make_config("walker_walk", "small", "drq"), action_dim=6)
"""
from __future__ import annotations

import torch

from protocad_ros.model.agent import Agent
from protocad_ros.model.agent_base import AgentBase
from protocad_ros.model.config import Config
from protocad_ros.model.drq import DrQAgent

__all__ = ["make_agent", "AGENT_FAMILIES"]

#: VariantSpec.family -> the class that implements it.
AGENT_FAMILIES: dict[str, type[AgentBase]] = {"world_model": Agent, "model_free": DrQAgent}


def make_agent(cfg: Config, action_dim: int,
               device: str | torch.device | None = None) -> AgentBase:
    """A fresh agent for cfg (seeded by cfg.train.seed) with `action_dim` actions."""
    return AGENT_FAMILIES[cfg.spec.family](cfg, action_dim, device=device)
