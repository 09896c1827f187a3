"""The loop's collection through the ROS nodes: the prefill (random actors) and each cycle's
collection (policy nodes serving the newest checkpoint), every robot's sim bridge run for a
number of episodes while the recorder writes one bag; and what the policy nodes report on
/diagnostics: which checkpoint they loaded and which served a cycle."""
from __future__ import annotations

import time
from typing import Any

from sim_bridge.contract import topics as T
from trainer import console, runs
from trainer.launch.loop_rundir import LoopRunDir


class Collection:
    """Phases of recorded episodes on the run's ROS stack, each a new bag in the ledger."""

    def __init__(self, stack, rundir: LoopRunDir, *, trusted_keys, device: str):
        self.stack, self.rundir, self.trusted_keys, self.device = stack, rundir, trusted_keys, device
        self.a, self.cfg, self.ledger, self.namespaces = rundir.a, rundir.cfg, rundir.ledger, rundir.namespaces

    def prefill(self, stop: console.StopFlag) -> None:
        """Random actions until the prefill's episodes are recorded (those of a resumed run count)."""
        a, cfg, ledger = self.a, self.cfg, self.ledger
        while ledger.prefill_episodes_done < a.prefill_episodes and not stop.stop:
            for i, ns in enumerate(self.namespaces):
                self.stack.start_random_actor(task=cfg.task, seed=cfg.train.seed + len(ledger.phases) + 100 * i,
                                              ns=ns)
            left = a.prefill_episodes - ledger.prefill_episodes_done
            st = self.collect("prefill", -(-left // len(self.namespaces)), stop)
            if st is None or (st["episodes"] == 0 and not stop.stop):
                raise RuntimeError("the prefill phase recorded no complete episode; see "
                                   f"{self.stack.log_dir}")

    def collect(self, kind: str, episodes: int, stop: console.StopFlag) -> dict[str, Any] | None:
        """One recorded run of every robot's bridge, `episodes` episodes each; returns the phase
        stats (None when interrupted before the bag holds anything)."""
        a, tr = self.a, self.cfg.train
        bag = self.ledger.next_bag(kind)
        stack = self.stack
        actor = "actor" if kind == "prefill" else "policy"
        stack.start_recorder(bag, log_name=f"recorder_{bag.name}", namespaces=self.namespaces,
                             wait_topics=[T.topic_name(ns, T.ACTION) for ns in self.namespaces])
        t0 = time.monotonic()
        bridges = []
        for i, ns in enumerate(self.namespaces):
            seed = tr.seed * 1000 + len(self.ledger.phases) * len(self.namespaces) + i
            bridges.append(stack.start_bridge(
                task=self.cfg.task, split="train", seed=seed, max_episodes=episodes,
                episode_length=a.episode_length, action_repeat=tr.action_repeat, min_subscribers=2,
                log_name=f"bridge_{bag.name}" + (f"_robot{i}" if len(self.namespaces) > 1 else ""), ns=ns))
        print(f"[loop] {bag.name}: {episodes} episode(s) of {a.episode_length} steps on training contexts "
              f"({'random actions' if kind == 'prefill' else 'policy node'}"
              + (f"; {len(bridges)} robots" if len(bridges) > 1 else "")
              + f"; bridge pid {', '.join(str(b.pid) for b in bridges)})", flush=True)
        code = 0
        for b in bridges:
            code = stack.wait_exit(b, a.phase_timeout, watch=(actor, "recorder"), stop=stop) or code
        for ns in self.namespaces:
            stack.stop(stack.key("bridge", ns))
        stack.stop("recorder")
        if kind == "prefill":
            for ns in self.namespaces:
                stack.stop(stack.key("actor", ns))
        if not any(bag.glob("*.mcap")):
            return None
        st = self.ledger.add_bag(bag)
        st["seconds"] = round(time.monotonic() - t0, 1)
        st["interrupted"] = code != 0
        if kind == "collect":
            st["served_updates"] = self._served_updates()
        rets = ", ".join(f"{r:.0f}" for r in st["returns"])
        print(f"[loop] {bag.name}: {st['episodes']} episode(s) in {st['seconds']}s, returns [{rets}]"
              + (f", policy node served checkpoint updates={st.get('served_updates')}" if kind == "collect" else ""),
              flush=True)
        return st

    def start_policies(self) -> None:
        a, cfg = self.a, self.cfg
        for i, ns in enumerate(self.namespaces):
            proc = self.stack.procs.get(self.stack.key("policy", ns))
            if proc is None or not proc.alive():
                self.stack.start_policy(checkpoint=runs.checkpoint_path(self.rundir.path), task=cfg.task,
                                        trusted_keys=self.trusted_keys,
                                        wait_for_checkpoint=True, reload_poll_s=0.5, mode="sample",
                                        exploration_noise=a.exploration_noise, seed=cfg.train.seed + i,
                                        device=self.device, ns=ns)

    def _policy_diagnostics(self, newer_than: float | None = None, timeout: float = 5.0,
                            ns: str | None = None) -> dict[str, str]:
        """A policy node's latest /diagnostics values (stamped after `newer_than`, if given and
        one comes within `timeout`); the first robot's unless `ns`."""
        graph, fqn = self.stack.graph, self.stack.node_fqn("policy", ns or self.namespaces[0])
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            values = graph.diagnostics(fqn, newer_than)
            if values is not None:
                return values
            graph.spin(0.1)
        return graph.diagnostics(fqn) or {}

    def _served_updates(self) -> int | None:
        """The update counter of the checkpoint the (first) policy node serves now (its
        diagnostics' checkpoint_updates, from a report made after the phase ended)."""
        value = self._policy_diagnostics(newer_than=time.time()).get("checkpoint_updates")
        return int(value) if value is not None and int(value) >= 0 else None

    def wait_policy_loaded(self, updates: int, stop, timeout: float = 120.0) -> None:
        """Block until every policy node has loaded the checkpoint with this update counter:
        its diagnostics say checkpoint_updates=N (serving it) or pending_checkpoint_updates=N
        (its watcher loaded it; served from the next is_first)."""
        graph, want = self.stack.graph, str(updates)
        for ns in self.namespaces:
            fqn = self.stack.node_fqn("policy", ns)

            def loaded(fqn: str = fqn) -> bool:
                values = graph.diagnostics(fqn) or {}
                return want in (values.get("checkpoint_updates"), values.get("pending_checkpoint_updates"))

            self.stack.wait_until(self.stack.procs[self.stack.key("policy", ns)], loaded,
                                  f"{fqn} diagnostics with checkpoint updates={updates}", timeout, stop)
