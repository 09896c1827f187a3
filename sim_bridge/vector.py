"""ContextDMCEnv copies in worker processes, stepped in lockstep.

Workers are started with the 'spawn' method: importing dm_control under MUJOCO_GL=egl opens an
EGL display, and a forked copy of a process holding GL/EGL state is undefined behaviour. The
parent never imports dm_control. Worker i is seeded with the i-th child of
``np.random.SeedSequence(seed)``, so a seed reproduces every worker and workers differ.
"""
from __future__ import annotations

import multiprocessing as mp
import signal
import traceback
from multiprocessing.connection import Connection, wait
from typing import Any, Mapping

import numpy as np

from sim_bridge.envs import ContextDMCEnv, Observation, check_env_args


class WorkerError(RuntimeError):
    """A worker raised (its traceback is in the message) or died; the VectorEnv is closed."""


def _worker(conn: Connection, task: str, split: str, seed: np.random.SeedSequence,
            env_kwargs: Mapping[str, Any]) -> None:
    # Ctrl-C goes to the whole process group; the parent decides when workers stop.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    env = None
    try:  # dm_control is imported (and EGL opened) by the constructor: its errors go back too
        env = ContextDMCEnv(task, split, seed, **env_kwargs)
        conn.send(("ok", (env.action_dim, env.action_names, env.control_dt)))
        episode_over = True
        while True:
            try:
                cmd, arg = conn.recv()
            except EOFError:  # parent gone
                break
            if cmd == "close":
                break
            try:
                obs = env.reset() if cmd == "reset" or episode_over else env.step(arg)
                episode_over = obs.is_last
                conn.send(("ok", obs))
            except Exception:  # noqa: BLE001 (forwarded to the parent verbatim)
                conn.send(("error", traceback.format_exc()))
    except Exception:  # noqa: BLE001
        try:
            conn.send(("error", traceback.format_exc()))
        except OSError:
            pass
    finally:
        if env is not None:
            env.close()
        conn.close()


class VectorEnv:
    """``num_envs`` ContextDMCEnv(task, split, seed_i, **env_kwargs) in worker processes.

    reset() resets every env. step(actions (N, A)) steps each env; an env whose previous
    observation was is_last ignores its action and returns the next episode's is_first
    observation instead (auto-reset). Bad arguments and bad actions raise ValueError/TypeError
    in the parent before anything is sent; a worker that raises or dies raises WorkerError and
    closes the VectorEnv. close() is idempotent and reaps every worker; use it as a context
    manager.
    """

    action_dim: int
    action_names: list[str]
    control_dt: float

    def __init__(self, task: str, num_envs: int, split: str = "train", seed: int = 0,
                 **env_kwargs: Any):
        if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)) \
                or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
        self.spec, _ = check_env_args(task, split, seed, **env_kwargs)
        self.num_envs, self.split = int(num_envs), split
        self._closed, self._started = False, False
        self._conns: list[Connection] = []
        self._procs: list[mp.process.BaseProcess] = []
        ctx = mp.get_context("spawn")
        try:
            for i, worker_seed in enumerate(np.random.SeedSequence(seed).spawn(self.num_envs)):
                parent, child = ctx.Pipe()
                proc = ctx.Process(target=_worker, name=f"ContextDMCEnv-{task}-{i}", daemon=True,
                                   args=(child, task, split, worker_seed, dict(env_kwargs)))
                proc.start()
                child.close()
                self._conns.append(parent)
                self._procs.append(proc)
            self.action_dim, self.action_names, self.control_dt = self._gather("start")[0]
        except BaseException:
            self.close()
            raise

    @property
    def pids(self) -> list[int]:
        """Worker process ids (for monitoring)."""
        return [p.pid for p in self._procs if p.pid is not None]

    def reset(self) -> list[Observation]:
        """Reset every env; returns their is_first observations."""
        self._send([("reset", None)] * self.num_envs)
        self._started = True
        return self._gather("reset")

    def step(self, actions: np.ndarray) -> list[Observation]:
        """One agent step of every env (auto-resetting the ones that just returned is_last)."""
        if not self._started:
            raise RuntimeError("call reset() before step()")
        try:
            a = np.asarray(actions, dtype=np.float64)
        except (TypeError, ValueError) as err:
            raise ValueError(f"actions must be numbers of shape ({self.num_envs}, "
                             f"{self.action_dim})") from err
        if a.shape != (self.num_envs, self.action_dim):
            raise ValueError(f"actions have shape {a.shape}, expected "
                             f"({self.num_envs}, {self.action_dim})")
        bad = np.flatnonzero(~np.isfinite(a).all(axis=1))
        if bad.size:
            raise ValueError(f"actions of envs {bad.tolist()} contain NaN or inf")
        self._send([("step", row) for row in a])
        return self._gather("step")

    def close(self) -> None:
        """Stop and reap every worker (idempotent)."""
        if getattr(self, "_closed", True):
            return
        self._closed = True
        for conn in self._conns:
            try:
                conn.send(("close", None))
            except OSError:
                pass
        for proc in self._procs:
            proc.join(timeout=10)
            if proc.is_alive():
                proc.terminate()
                proc.join(timeout=5)
            if proc.is_alive():
                proc.kill()
                proc.join()
        for conn in self._conns:
            conn.close()

    def __enter__(self) -> VectorEnv:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # noqa: BLE001 (interpreter shutdown: modules may be gone)
            pass

    def _send(self, messages: list[tuple[str, Any]]) -> None:
        if self._closed:
            raise RuntimeError("the VectorEnv is closed")
        for i, (conn, msg) in enumerate(zip(self._conns, messages)):
            try:
                conn.send(msg)
            except OSError as err:
                self._fail(f"worker {i} cannot be reached ({err}); exit code "
                           f"{self._procs[i].exitcode}")

    def _gather(self, what: str) -> list[Any]:
        """Every worker's answer; raises WorkerError (after reading all) if one failed."""
        results, errors = [], []
        for i, (conn, proc) in enumerate(zip(self._conns, self._procs)):
            # Waiting on the process sentinel too: a dead worker never answers.
            ready = wait([conn, proc.sentinel])
            try:
                status, payload = conn.recv() if conn in ready or conn.poll() else (None, None)
            except (EOFError, OSError):
                status, payload = None, None
            if status is None:
                proc.join(timeout=1)
                errors.append(f"worker {i} (pid {proc.pid}) died during {what} "
                              f"with exit code {proc.exitcode}")
            elif status == "error":
                errors.append(f"worker {i} (pid {proc.pid}) failed during {what}:\n{payload}")
            results.append(payload)
        if errors:
            self._fail("\n".join(errors))
        return results

    def _fail(self, message: str) -> None:
        self.close()
        raise WorkerError(message)
