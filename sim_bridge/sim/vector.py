"""ContextDMCEnv copies in worker processes, stepped in lockstep: the one env pool (online
collection, evaluation, the context views).

Workers are started with the 'spawn' method: importing dm_control under MUJOCO_GL=egl opens an
EGL display, and a forked copy of a process holding GL/EGL state is undefined behaviour. The
parent never imports dm_control. Worker i is seeded with the i-th child of
``np.random.SeedSequence(seed)``, so a seed reproduces every worker and workers differ.
"""
from __future__ import annotations

import multiprocessing as mp
import signal
import sys
import traceback
import types
from contextlib import contextmanager
from multiprocessing.connection import Connection, wait
from typing import Any, Iterator, Mapping, Sequence

import numpy as np

from sim_bridge.sim.envs import ContextDMCEnv, Observation, check_env_args


@contextmanager
def _workers_skip_the_main_module() -> Iterator[None]:
    """'spawn' re-imports the parent's __main__ in every child (as __mp_main__). For
    protocad-online that is the whole trainer with torch: about 1.5 CPU-s and 300 MB per worker,
    none of which a worker uses (its target lives here). A __main__ without __spec__ or __file__
    gives the children nothing to re-import; the real one is back as soon as they are started."""
    main = sys.modules["__main__"]
    sys.modules["__main__"] = types.ModuleType("__main__")
    try:
        yield
    finally:
        sys.modules["__main__"] = main


class WorkerError(RuntimeError):
    """A worker raised (its traceback is in the message) or died; the VectorEnv is closed."""


def _worker(conn: Connection, task: str, split: str, seed: int | np.random.SeedSequence,
            env_kwargs: Mapping[str, Any]) -> None:
    # Ctrl-C goes to the whole process group; the parent decides when workers stop.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    env = None
    try:  # dm_control is imported (and EGL opened) by the constructor: its errors go back too
        env = _AutoResetEnv(ContextDMCEnv(task, split, seed, **env_kwargs))
        conn.send(("ok", env.description))
        while True:
            try:
                cmd, arg = conn.recv()
            except EOFError:  # parent gone
                break
            if cmd == "close":
                break
            try:
                conn.send(("ok", env.reset(arg) if cmd == "reset" else env.step(arg)))
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


class _AutoResetEnv:
    """One ContextDMCEnv whose step after is_last starts the next episode (in a worker, or in
    the parent for in_process=True)."""

    def __init__(self, env: ContextDMCEnv):
        self.env, self.episode_over = env, True
        self.description = (env.action_dim, env.action_names, env.control_dt)

    def reset(self, context: Mapping[str, float] | None) -> Observation:
        obs = self.env.reset(context)
        self.episode_over = obs.is_last
        return obs

    def step(self, action: np.ndarray) -> Observation:
        if self.episode_over:
            return self.reset(None)
        obs = self.env.step(action)
        self.episode_over = obs.is_last
        return obs

    def close(self) -> None:
        self.env.close()


class VectorEnv:
    """``num_envs`` ContextDMCEnv(task, split, seed_i, **env_kwargs), one worker process each
    (or all in this process with ``in_process=True``: dm_control is then imported here).

    reset() resets every env, each with a context drawn from the split (or the fixed one);
    reset(contexts) resets the first len(contexts) envs with those contexts (evaluation's
    waves). step(actions (N, A)) steps each env; step(actions (k, A), which) only the k envs
    listed. An env whose previous observation was is_last ignores its action and returns the
    next episode's is_first observation instead (auto-reset). Bad arguments and bad actions
    raise ValueError/TypeError in the parent before anything is sent; a worker that raises or
    dies raises WorkerError and closes the VectorEnv. close() is idempotent and reaps every
    worker; use it as a context manager. ``env_seeds`` (one per env) replaces the default seeds,
    the children of ``np.random.SeedSequence(seed)``.
    """

    action_dim: int
    action_names: list[str]
    control_dt: float

    def __init__(self, task: str, num_envs: int, split: str = "train", seed: int = 0, *,
                 in_process: bool = False,
                 env_seeds: Sequence[int | np.random.SeedSequence] | None = None, **env_kwargs: Any):
        if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)) \
                or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
        self.spec, _ = check_env_args(task, split, seed, **env_kwargs)
        self.num_envs, self.split, self.in_process = int(num_envs), split, bool(in_process)
        seeds = list(np.random.SeedSequence(seed).spawn(self.num_envs) if env_seeds is None else env_seeds)
        if len(seeds) != self.num_envs:
            raise ValueError(f"env_seeds has {len(seeds)} seeds for {self.num_envs} envs")
        self._closed, self._started = False, False
        self._envs: list[_AutoResetEnv] = []
        self._conns: list[Connection] = []
        self._procs: list[mp.process.BaseProcess] = []
        try:
            if self.in_process:
                for s in seeds:
                    self._envs.append(_AutoResetEnv(ContextDMCEnv(task, split, s, **env_kwargs)))
                description = self._envs[0].description
            else:
                ctx = mp.get_context("spawn")
                for i, worker_seed in enumerate(seeds):
                    parent, child = ctx.Pipe()
                    proc = ctx.Process(target=_worker, name=f"ContextDMCEnv-{task}-{i}", daemon=True,
                                       args=(child, task, split, worker_seed, dict(env_kwargs)))
                    with _workers_skip_the_main_module():
                        proc.start()
                    child.close()
                    self._conns.append(parent)
                    self._procs.append(proc)
                description = self._gather("start", range(self.num_envs))[0]
            self.action_dim, self.action_names, self.control_dt = description
        except BaseException:
            self.close()
            raise

    @property
    def pids(self) -> list[int]:
        """Worker process ids (for monitoring)."""
        return [p.pid for p in self._procs if p.pid is not None]

    def reset(self, contexts: Sequence[Mapping[str, float]] | None = None) -> list[Observation]:
        """Reset every env (contexts None) or the first len(contexts) envs with those contexts;
        returns their is_first observations."""
        which = range(self.num_envs if contexts is None else len(contexts))
        if len(which) > self.num_envs:
            raise ValueError(f"{len(which)} contexts for {self.num_envs} envs")
        arg = [None] * len(which) if contexts is None else [dict(c) for c in contexts]
        out = self._call("reset", which, arg)
        self._started = True
        return out

    def step(self, actions: np.ndarray, which: Sequence[int] | None = None) -> list[Observation]:
        """One agent step of every env, or of the envs in `which` (actions: one row each);
        envs that just returned is_last start their next episode instead."""
        if not self._started:
            raise RuntimeError("call reset() before step()")
        which = range(self.num_envs) if which is None else [int(i) for i in which]
        try:
            a = np.asarray(actions, dtype=np.float64)
        except (TypeError, ValueError) as err:
            raise ValueError(f"actions must be numbers of shape ({len(which)}, "
                             f"{self.action_dim})") from err
        if a.shape != (len(which), self.action_dim):
            raise ValueError(f"actions have shape {a.shape}, expected "
                             f"({len(which)}, {self.action_dim})")
        bad = np.flatnonzero(~np.isfinite(a).all(axis=1))
        if bad.size:
            raise ValueError(f"actions of envs {[which[i] for i in bad]} contain NaN or inf")
        return self._call("step", which, list(a))

    def _call(self, cmd: str, which: Sequence[int], args: list[Any]) -> list[Observation]:
        if self._closed:
            raise RuntimeError("the VectorEnv is closed")
        if self.in_process:
            return [getattr(self._envs[i], cmd)(arg) for i, arg in zip(which, args)]
        self._send([(i, (cmd, arg)) for i, arg in zip(which, args)])
        return self._gather(cmd, which)

    def close(self) -> None:
        """Stop and reap every worker (idempotent)."""
        if getattr(self, "_closed", True):
            return
        self._closed = True
        for env in self._envs:
            env.close()
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

    def _send(self, messages: list[tuple[int, tuple[str, Any]]]) -> None:
        for i, msg in messages:
            try:
                self._conns[i].send(msg)
            except OSError as err:
                self._fail(f"worker {i} cannot be reached ({err}); exit code "
                           f"{self._procs[i].exitcode}")

    def _gather(self, what: str, which: Sequence[int]) -> list[Any]:
        """The answers of the workers in `which`; raises WorkerError (after reading all) if
        one failed."""
        results, errors = [], []
        for i in which:
            conn, proc = self._conns[i], self._procs[i]
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
