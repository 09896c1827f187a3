"""Algorithm 1's schedule, in the paper's notation, for every driver (protocad-online in one
process, protocad-loop through the ROS nodes):

    collect N episodes with random actions (the prefill)
    train C updates
    repeat: collect an episode with the agent, then train C updates

So after the prefill and k collected episodes the agent is due C (k + 1) updates in all. The
target is a total, not a step: a phase cut short (Ctrl-C, a kill) is made up after a resume,
which counts episodes from the data on disk. Evaluations come every `eval_every` env steps.

`RunCounters` are a run's progress; they travel in every checkpoint (Trainer.save) beside the
agent's own update counter.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Any, Mapping


@dataclass(frozen=True)
class Schedule:
    """When to train and when to evaluate."""

    N: int
    """prefill episodes (random actions) before the first update (paper: 2)"""
    C: int
    """updates once after the prefill and then per collected episode (paper: 100)"""
    eval_every: int = 0
    """env steps between periodic evaluations (0: only the final one)"""

    def prefilled(self, episodes: int) -> bool:
        """Whether `episodes` complete episodes finish the prefill."""
        return episodes >= self.N

    def target_updates(self, collected_episodes: int) -> int:
        """The total updates due once the prefill is done and `collected_episodes` episodes were
        collected with the agent after it: C (k + 1)."""
        return self.C * (max(collected_episodes, 0) + 1)

    def planned_updates(self, env_steps: int, time_limit: int, episodes_per_round: int = 1) -> int:
        """The updates due at an `env_steps` budget of episodes of `time_limit` env steps that
        end `episodes_per_round` at a time (vectorized envs x ranks): what a whole run makes."""
        rounds = -(-max(env_steps, 0) // max(time_limit * episodes_per_round, 1))
        return self.target_updates(rounds * episodes_per_round - self.N) if rounds * episodes_per_round >= self.N else 0

    def first_eval(self) -> int:
        return self.eval_every

    def eval_due(self, env_steps: int, next_eval: int) -> bool:
        return bool(self.eval_every) and env_steps >= next_eval

    def next_eval_after(self, env_steps: int, next_eval: int) -> int:
        """The next evaluation point past `env_steps` (points skipped by a long episode are
        skipped, not caught up)."""
        while next_eval <= env_steps:
            next_eval += self.eval_every
        return next_eval


@dataclass
class RunCounters:
    """A run's progress, saved in its checkpoints. Counters are global under torchrun (every
    rank's env steps and episodes)."""

    env_steps: int = 0
    """agent steps x action repeat"""
    agent_steps: int = 0
    episodes: int = 0
    """complete episodes, the prefill's included"""
    prefill_done: int = 0
    next_eval: int = 0
    """env steps of the next periodic evaluation"""
    evals: int = 0
    resumes: int = 0
    last_return: float = 0.0
    bags: int = 0
    """bags started (numbers the next bag's name)"""

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "RunCounters":
        """From a checkpoint's counters (which hold the trainer's own keys too)."""
        known = {f.name: f.type for f in fields(cls)}
        return cls(**{k: (float if known[k] == "float" else int)(v) for k, v in d.items() if k in known})

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)
