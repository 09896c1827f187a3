"""Algorithm 1's schedule and the run counters (trainer/learn/schedule.py): what online and
loop runs train and evaluate when, and what a checkpoint carries of a run's progress."""
from __future__ import annotations

from trainer.learn.schedule import RunCounters, Schedule


def test_updates_follow_algorithm_1():
    s = Schedule(N=2, C=100)
    assert [s.prefilled(e) for e in (0, 1, 2, 3)] == [False, False, True, True]
    # C after the prefill, then C per collected episode: C (k + 1) in all
    assert [s.target_updates(k) for k in (0, 1, 5)] == [100, 200, 600]
    assert s.target_updates(-1) == 100   # nothing collected yet counts as none


def test_evaluation_points_every_eval_every_env_steps():
    s = Schedule(N=2, C=100, eval_every=5000)
    assert s.first_eval() == 5000
    assert not s.eval_due(4999, 5000) and s.eval_due(5000, 5000)
    assert s.next_eval_after(5000, 5000) == 10000
    assert s.next_eval_after(17000, 5000) == 20000        # points a long episode skipped are not caught up
    assert not Schedule(N=2, C=100).eval_due(10**9, 0)   # eval_every 0: only the final evaluation


def test_counters_round_trip_through_a_checkpoints_dict():
    c = RunCounters(env_steps=30000, agent_steps=15000, episodes=30, prefill_done=1, next_eval=35000,
                    evals=6, resumes=2, last_return=123.5, bags=31)
    # a checkpoint's counters also hold the trainer's own keys, and numbers come back as JSON gives them
    saved = {**c.as_dict(), "updates": 2900, "dataset_state": "{}", "env_steps": 30000.0}
    back = RunCounters.from_dict(saved)
    assert back == c and isinstance(back.env_steps, int) and isinstance(back.last_return, float)
    assert RunCounters.from_dict({}) == RunCounters()
