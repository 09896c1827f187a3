"""sim_bridge.sim.vector.VectorEnv with real worker processes (spawn), real physics and rendering."""
from __future__ import annotations

import os
import signal
import subprocess
import sys

import numpy as np
import pytest
from helpers import ROOT

from sim_bridge.contract.contexts import get_task
from sim_bridge.sim.envs import ContextDMCEnv
from sim_bridge.sim.vector import VectorEnv, WorkerError

pytestmark = pytest.mark.process


def reaped(pids: list[int]) -> bool:
    """No process left, not even a zombie waiting for its parent's wait()."""
    return not any(os.path.exists(f"/proc/{pid}") for pid in pids)


def test_auto_reset_seeding_and_close():
    allowed = get_task("pendulum_swingup").contexts("train")
    with VectorEnv("pendulum_swingup", 2, seed=3, time_limit=4) as venv:  # 2 agent steps
        assert (venv.num_envs, venv.action_dim, venv.action_names) == (2, 1, ["torque"])
        first = venv.reset()
        assert all(o.is_first and o.episode == 0 and o.context in allowed for o in first)
        assert not np.array_equal(first[0].image, first[1].image)  # workers seeded apart
        mid = venv.step(np.zeros((2, 1)))
        last = venv.step(np.ones((2, 1)))
        assert [o.is_last for o in mid + last] == [False, False, True, True]
        # The action after is_last is ignored (any finite value) and a new episode starts.
        nxt = venv.step(np.full((2, 1), 1e9))
        assert all(o.is_first and o.episode == 1 and o.step == 0 and o.reward == 0.0
                   for o in nxt)
        assert all(not o.is_first and o.step == 1 for o in venv.step(np.zeros((2, 1))))
        pids = venv.pids
    assert reaped(pids)
    venv.close()  # idempotent
    with pytest.raises(RuntimeError, match="closed"):
        venv.reset()

    # Worker i is ContextDMCEnv(seed=SeedSequence(seed).spawn(n)[i]): reproducible alone.
    seeds = np.random.SeedSequence(3).spawn(2)
    with ContextDMCEnv("pendulum_swingup", seed=seeds[1], time_limit=4) as env:
        alone = env.reset()
    assert alone.context == first[1].context
    np.testing.assert_array_equal(alone.image, first[1].image)


def test_bad_arguments_and_actions_fail_in_the_parent():
    with pytest.raises(ValueError, match="valid tasks"):
        VectorEnv("pendulum_swing", 2)
    with pytest.raises(ValueError, match="num_envs"):
        VectorEnv("pendulum_swingup", 0)
    with pytest.raises(TypeError):
        VectorEnv("pendulum_swingup", 1, render_qualty="fast")
    with pytest.raises(ValueError, match="allowed m values"):
        VectorEnv("pendulum_swingup", 1, context={"m": 0.2})

    with VectorEnv("hopper_stand", 2, seed=0) as venv:
        with pytest.raises(RuntimeError, match="reset"):
            venv.step(np.zeros((2, 4)))
        venv.reset()
        with pytest.raises(ValueError, match=r"shape \(2, 3\), expected \(2, 4\)"):
            venv.step(np.zeros((2, 3)))
        with pytest.raises(ValueError, match=r"envs \[1\] contain NaN"):
            venv.step(np.array([[0, 0, 0, 0], [0, np.nan, 0, 0]]))
        assert [o.step for o in venv.step(np.zeros((2, 4)))] == [1, 1]  # still usable

        # A worker that dies is reported by index and exit code; everything is reaped.
        pids = venv.pids
        os.kill(pids[1], signal.SIGKILL)
        with pytest.raises(WorkerError, match=r"worker 1 \(pid \d+\) died during step "
                                              r"with exit code -9"):
            venv.step(np.zeros((2, 4)))
        assert reaped(pids)
        with pytest.raises(RuntimeError, match="closed"):
            venv.step(np.zeros((2, 4)))


def test_worker_exception_reaches_the_parent_with_its_traceback(monkeypatch):
    # A real failure inside the workers: dm_control refuses an unknown GL backend at import.
    monkeypatch.setenv("MUJOCO_GL", "no-such-backend")
    with pytest.raises(WorkerError) as info:
        VectorEnv("pendulum_swingup", 2)
    message = str(info.value)
    assert "worker 0" in message and "worker 1" in message and "during start" in message
    assert "Traceback" in message and "no-such-backend" in message


def test_given_contexts_subsets_and_in_process_match_workers():
    """Evaluation's use: the first k envs reset with given contexts, only the live ones
    stepped; the same seeds give the same frames in worker processes and in this process."""
    contexts = [dict(c) for c in get_task("pendulum_swingup").contexts("test")[:2]]
    frames = []
    for in_process in (True, False):
        with VectorEnv("pendulum_swingup", 3, "test", seed=5, in_process=in_process, time_limit=6) as venv:
            first = venv.reset(contexts)
            assert [o.context for o in first] == contexts and all(o.is_first for o in first)
            both = venv.step(np.full((2, 1), 0.5), which=[0, 1])
            assert [o.step for o in both] == [1, 1]
            one = venv.step(np.full((1, 1), -0.5), which=[1])
            assert [o.step for o in one] == [2]
            with pytest.raises(ValueError, match=r"shape \(2, 1\), expected \(1, 1\)"):
                venv.step(np.zeros((2, 1)), which=[0])
            with pytest.raises(ValueError, match="4 contexts for 3 envs"):
                venv.reset(contexts * 2)
            frames.append([o.image for o in first + both + one])
    for in_parent, in_worker in zip(*frames):
        np.testing.assert_array_equal(in_parent, in_worker)


def test_workers_do_not_import_the_parents_main_module(tmp_path):
    """'spawn' would re-import the parent's __main__ in each worker: for protocad-online that is
    torch and the trainer (about 1.5 CPU-s and 300 MB per worker). A main module that counts
    its imports, started the way protocad-online is (python -m), is imported once."""
    (tmp_path / "heavy_main.py").write_text(
        "import os, sys\n"
        f"open({str(tmp_path / 'imports')!r}, 'a').write(f'{{os.getpid()}}\\n')\n"
        "if __name__ == '__main__':\n"
        "    from sim_bridge.sim.vector import VectorEnv\n"
        "    with VectorEnv('pendulum_swingup', 2, time_limit=4) as venv:\n"
        "        venv.reset()\n"
        "        print(os.getpid(), *venv.pids)\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), str(ROOT)])}
    p = subprocess.run([sys.executable, "-m", "heavy_main"], cwd=tmp_path, env=env, capture_output=True,
                       text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    parent, *workers = p.stdout.split()
    assert len(workers) == 2
    assert (tmp_path / "imports").read_text().split() == [parent]
