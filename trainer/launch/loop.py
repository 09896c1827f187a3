"""`protocad-loop` (`ros2 run trainer loop`): the collect-train-reload loop through the ROS nodes.

    protocad-loop --demo                         # README main command (a shipped policy, else Pendulum Swingup)
    protocad-loop --init-policy protocad_ros/policies/walker_walk.pt --cycles 20   # train on from it
    protocad-loop --task walker_walk --preset paper --cycles 100 --run-dir runs/ww
    protocad-loop --run-dir runs/ww --resume     # continue after Ctrl-C / a crash
    protocad-loop --robots 2 --start-discovery-server   # a Fast DDS Discovery Server, no multicast

Processes (trainer/launch/rosprocs.py; logs in RUN_DIR/logs/, one ROS_DOMAIN_ID per run, a fresh
one unless --domain-id):

1. prefill: sim bridge (lock-step, training contexts, max_episodes=N) + trainer.nodes.random_actor
   (uniform random actions) + recorder -> RUN_DIR/bags/00_prefill/;
2. train C updates (Algorithm 1: before the first collected episode) from every bag so far,
   checkpoint RUN_DIR/checkpoints/latest.pt (atomic);
3. the policy node starts on that checkpoint (mode sample: DreamerV2 collects with sampled
   actions) and stays up; each cycle: recorder -> bags/NN_collect/, a sim bridge run of
   E episodes, then C x E updates and a new checkpoint, which the policy node reloads (its
   file watcher loads it in the background and serves it from the next is_first); the loop
   waits until the node has loaded the newest checkpoint before the next cycle starts, and
   reads from the node's /diagnostics which checkpoint (update counter) served each cycle
   (readiness and these reads are ROS state, lifecycle and diagnostics, never log text);
4. the end: an evaluation table on the test contexts (in-process, deterministic), JSON in
   RUN_DIR/eval/, and a rerun recording of the context view (trainer.viz.visualize).

The recorder also records /diagnostics, so every bag says which checkpoint the policy node
served (its `checkpoint_updates` value). Ctrl-C stops the nodes in order (the recorder last:
its bag is closed cleanly) or saves a checkpoint when it comes during training; exit code 0.
`--resume` rebuilds the state from the run directory: the bags (prefill / collect phases,
episodes, env steps) and the checkpoint (weights, optimizers, counters, sampler state).
"""
from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path
from dataclasses import dataclass
from typing import Any, Sequence

from protocad_ros.model.config import plan_prototype_freeze
from sim_bridge.contract import topics as T
from protocad_ros.checkpoint_signing import load_private_key, sign_file
from trainer.launch import discovery, run_key
from trainer import runs, settings
from trainer.data.dataset import MCAPDataset, TopicMap
from trainer.learn.schedule import Schedule
from trainer.learn.resume import open_trainer
from trainer.settings import arg
from trainer.runs import check_settings_section

#: The demo's protocol. C=15: its 60 updates are most of its wall time, and on a CPU without bf16
#: arithmetic (float32, about 4.7 s an update of 16 x 50 on one AVX2 core) 100 updates alone took
#: 8 of the 10 minutes the demo may take there (issue 41); a demo shows the loop, not learning.
DEMO = dict(task="pendulum_swingup", preset="small", cycles=3, episodes_per_cycle=1, prefill=2,
            updates_per_episode=15, eval_episodes=1, eval_max_contexts=8)


@dataclass
class LoopSettings:
    """protocad-loop's protocol (Algorithm 1 through the ROS nodes) and run options. Unset
    values come from the config (train.*) or the demo, once, in `resolved`."""

    demo: bool = False
    """the README's main command: 3 cycles of 1 episode, C=15, then the test-context table and a
    rerun recording: from the shipped policy of the first of walker_walk, cheetah_run the
    package ships (--init-policy), else pendulum_swingup from scratch at the small preset (a few
    minutes on 2 CPU cores)"""
    cycles: int | None = arg(None, group="loop")
    """collection cycles after the prefill (default 10; demo 3)"""
    episodes_per_cycle: int | None = arg(None, group="loop")
    """E episodes recorded per cycle (default 1)"""
    prefill_episodes: int | None = arg(None, group="loop")
    """N random episodes (default train.prefill_episodes = 2)"""
    updates_per_episode: int | None = arg(None, group="loop")
    """C updates per collected episode, also done once after the prefill (default
    train.collect_interval = 100, the paper's; demo 15)"""
    episode_length: int | None = arg(None, group="loop")
    """agent steps per episode (default train.time_limit / action_repeat = 500)"""
    exploration_noise: float | None = arg(None, group="loop")
    """policy node exploration noise (default train.expl_noise)"""
    eval_episodes: int | None = arg(None, group="loop")
    """final evaluation: episodes per test context (0: none; default 5, demo 1)"""
    eval_max_contexts: int = arg(0, group="loop")
    """final evaluation: at most K test contexts, the fixed stratified subset (0: all; demo 8)"""
    init_policy: str | None = arg(None, metavar="POLICY_PT", group="loop")
    """start from this policy file's (or checkpoint's) weights: its config (task, variant,
    sizes) is the run's, optimizers and the update count start afresh; first its return on unseen
    contexts is printed beside the random policy's, both through the ROS nodes (the demo: the
    shipped policy of its task, protocad_ros/policies/TASK.pt, when there is one)"""
    start_eval_episodes: int = arg(4, group="loop")
    """with --init-policy: episodes on unseen contexts (drawn by the bridge, the same for both
    policies) before training; 0: none"""
    no_visualize: bool = arg(False, group="loop")
    """skip the rerun context recording at the end"""
    robots: int | None = arg(None, type=runs.positive_int, group="loop")
    """N robots collecting at once: a bridge and a policy node each in /protocad/robotI (own
    /clock), one recorder recording all of them, training on every robot's episodes; each
    records --episodes-per-cycle episodes per cycle (default 1)"""
    run_dir: str | None = arg(None, group="run")
    """output directory (default runs/loop-TASK-VARIANT-TIME)"""
    resume: bool = arg(False, group="run")
    """continue RUN_DIR (bags + checkpoint + counters)"""
    domain_id: int | None = arg(None, group="run")
    """ROS_DOMAIN_ID of the nodes (default: a fresh one)"""
    discovery_server: str | None = arg(None, type=discovery.server_list_arg, metavar="HOST:PORT",
                                       group="run", exclusive="discovery")
    """discover through this running Fast DDS Discovery Server instead of multicast (sets
    ROS_DISCOVERY_SERVER for every node; default: $ROS_DISCOVERY_SERVER if set)"""
    start_discovery_server: tuple | None = arg(None, type=discovery.listen_arg, nargs="?",
                                               const=discovery.DEFAULT_LISTEN, metavar="[HOST:]PORT",
                                               group="run", exclusive="discovery")
    """start a Discovery Server (fast-discovery-server, default 127.0.0.1:11811) before the
    nodes, stop it after them, and discover through it; listen on this machine's fleet-facing
    address to let actor groups on other machines join (0.0.0.0 works but exposes it everywhere)"""
    checkpoint_every: int = arg(500, group="run")
    """updates between checkpoints within a training phase"""
    log_every: int = arg(10, group="run")
    """updates per metrics line"""
    cache_dir: str | None = arg(None, group="run")
    """dataset cache (default RUN_DIR/cache)"""
    rerun: str | None = arg(None, nargs="?", const="", metavar="RRD", group="run")
    """log training scalars to a rerun recording (default RUN_DIR/metrics.rrd)"""
    phase_timeout: float = arg(3600.0, group="run")
    """seconds a collection phase may take"""
    no_progress: bool = arg(False, group="run")
    """no progress bar"""

    def with_demo(self) -> "LoopSettings":
        """The demo's values where none were given."""
        if not self.demo:
            return self
        pick = {k: DEMO[d] for k, d in (("cycles", "cycles"), ("episodes_per_cycle", "episodes_per_cycle"),
                                          ("prefill_episodes", "prefill"), ("updates_per_episode", "updates_per_episode"),
                                          ("eval_episodes", "eval_episodes")) if getattr(self, k) is None}
        if self.eval_max_contexts == 0:   # all 8 of Pendulum; 8 of the 64 of walker / cheetah
            pick["eval_max_contexts"] = DEMO["eval_max_contexts"]
        return dataclasses.replace(self, **pick)

    def resolved(self, tr, saved_protocol: dict[str, Any] | None = None) -> "LoopSettings":
        """Every unset protocol value: from the resumed run's protocol, else the config's train
        section (tr), else the defaults."""
        saved = {k: v for k, v in (saved_protocol or {}).items()
                 if k in PROTOCOL_KEYS and getattr(self, k) is None and v is not None}
        s = dataclasses.replace(self, **saved)
        return dataclasses.replace(
            s, cycles=10 if s.cycles is None else s.cycles, episodes_per_cycle=s.episodes_per_cycle or 1,
            prefill_episodes=tr.prefill_episodes if s.prefill_episodes is None else s.prefill_episodes,
            updates_per_episode=tr.collect_interval if s.updates_per_episode is None else s.updates_per_episode,
            episode_length=s.episode_length or max(1, tr.time_limit // tr.action_repeat),
            exploration_noise=tr.expl_noise if s.exploration_noise is None else s.exploration_noise,
            eval_episodes=5 if s.eval_episodes is None else s.eval_episodes, robots=s.robots or 1)


#: The loop's protocol, as run.json records it and a resume restores it.
#: Tasks whose shipped policy the demo starts from, in this order, when the package has one.
DEMO_POLICY_TASKS = ("walker_walk", "cheetah_run")


def planned_updates(a: LoopSettings) -> int:
    """The updates a loop makes in all: C once after the prefill and per collected episode."""
    return Schedule(N=a.prefill_episodes, C=a.updates_per_episode).target_updates(a.cycles * a.episodes_per_cycle)


def with_shipped_policy(s: LoopSettings, model: settings.ModelChoice) -> LoopSettings:
    """The demo: start from a shipped policy (of --task if given, else the first of
    DEMO_POLICY_TASKS the package ships) unless --init-policy names one."""
    from protocad_ros.policy import shipped_policy

    if s.init_policy or s.resume:
        return s
    for task in [model.task] if model.task else DEMO_POLICY_TASKS:
        if path := shipped_policy(task):
            return dataclasses.replace(s, init_policy=str(path))
    return s


PROTOCOL_KEYS = ("cycles", "episodes_per_cycle", "prefill_episodes", "updates_per_episode", "episode_length",
                 "exploration_noise", "eval_episodes", "robots")


def build_parser():
    return settings.settings_parser(
        "protocad-loop",
        "Collect-train-reload loop through the ROS 2 nodes: prefill with random actions on the "
        "training contexts, then alternate collection (policy node -> sim bridge, recorded to a "
        "new MCAP bag per cycle) and training (C updates per collected episode from all bags); "
        "the policy node reloads each new checkpoint. Ends with an evaluation table on the test contexts.",
        [(None, LoopSettings), ("model / config", settings.ModelChoice)])


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    parsed = settings.parse(parser, argv)
    s, model = parsed.get(LoopSettings), parsed.get(settings.ModelChoice)
    from trainer.launch.rosprocs import NodeFailed

    try:
        if s.resume and s.run_dir:   # the original command's options, unless given again
            got = settings.resumed_from_run(s.run_dir, parsed, parser,
                                            {"loop": LoopSettings, "model": settings.ModelChoice})
            s, model = got["loop"], got["model"]
        return Loop(s, model, parsed.config_args, parsed.prog, parsed.argv).run()
    except NodeFailed as exc:
        print(f"protocad-loop: a node failed: {exc}", file=sys.stderr)
        return 1
    except ValueError as exc:
        print(f"protocad-loop: error: {exc}", file=sys.stderr)
        return 2


class Loop:
    def __init__(self, s: LoopSettings, model: settings.ModelChoice, config_args: Sequence[str] = (),
                 prog: str = "protocad-loop", argv: Sequence[str] | None = None):
        if s.demo:
            s = with_shipped_policy(s, model)
            if not s.init_policy:
                model = dataclasses.replace(model, task=model.task or DEMO["task"], preset=model.preset or DEMO["preset"])
        self.a, self.model = s.with_demo(), model
        self.config_args, self.prog = list(config_args), prog
        self.argv = list(sys.argv[1:] if argv is None else argv)
        self.device = runs.resolve_device(model.device)
        runs.setup_torch(model.threads)
        self._eta_said = False   # the expected time is said once, after the first training phase

    # ------------------------------------------------------------------ setup
    def _setup(self) -> None:
        a = self.a
        saved_protocol = None
        self.init_policy = None
        if a.init_policy:
            from protocad_ros.checkpoint import existing_checkpoint_file

            self.init_policy = existing_checkpoint_file(a.init_policy)
        if a.resume:
            # A loop stopped during its prefill has bags but no checkpoint yet: still resumable.
            self.run_dir, self.run_json = runs.resume_run_dir(a.run_dir, need_checkpoint=False)
            self.cfg = runs.load_run_config(self.run_dir)
            saved_protocol = self.run_json.get("protocol")
            if saved_protocol is not None and not isinstance(saved_protocol, dict):
                raise ValueError(f"--resume: {self.run_dir / 'run.json'}: 'protocol' is not a mapping")
            check_settings_section(self.run_dir / "run.json", "protocol", LoopSettings,
                                   {k: v for k, v in (saved_protocol or {}).items() if k in PROTOCOL_KEYS})
        else:
            self.cfg = self._policy_config() if a.init_policy else self.model.to_config(self.config_args, self.prog)
            self.cfg.train.device = self.device
            # a refused plan leaves no run directory behind
            plan_prototype_freeze(self.cfg, 0, planned_updates(a.resolved(self.cfg.train)))
            self.run_dir = runs.new_run_dir(a.run_dir, "loop", self.cfg.task, self.cfg.variant)
            self.run_dir.mkdir(parents=True, exist_ok=True)
            self.cfg.save(self.run_dir / "config.yaml")
            self.run_json = {}
        tr = self.cfg.train
        self.a = a = a.resolved(tr, saved_protocol)
        self.schedule = Schedule(N=a.prefill_episodes, C=a.updates_per_episode)
        from trainer.launch.rosprocs import robot_namespaces

        self.namespaces = robot_namespaces(T.DEFAULT_NAMESPACE, a.robots)
        runs.record_invocation(self.run_json, a.resume, self.argv)
        self.run_json.update(kind="loop", task=self.cfg.task, variant=self.cfg.variant,
                             preset=self.cfg.preset, seed=tr.seed, device=self.device,
                             protocol={k: getattr(a, k) for k in PROTOCOL_KEYS},
                             settings={"loop": settings.as_data(a), "model": settings.as_data(self.model)})
        runs.atomic_write_json(self.run_dir / "run.json", self.run_json)
        self.bags_dir = self.run_dir / "bags"
        self.bags_dir.mkdir(exist_ok=True)
        self.ds = MCAPDataset([], topics=TopicMap(), seq_len=tr.seq_len, seed=tr.seed,
                              cache_dir=a.cache_dir or self.run_dir / "cache")
        self.phases: list[dict[str, Any]] = []
        for bag in sorted(p for p in self.bags_dir.iterdir() if p.is_dir()):
            self._add_bag(bag, resumed=True)

    def _policy_config(self):
        """--init-policy: the policy file's config (its networks) with this run's training
        options on top (--set, --batch-size, --seq-len, --seed, --precision, config flags); an
        option that would change the networks is refused (ValueError)."""
        import copy

        from protocad_ros.checkpoint import CheckpointError, architecture_differences, read_checkpoint
        from protocad_ros.model.config import Config, apply_overrides

        try:
            policy_cfg = Config.from_dict(read_checkpoint(self.init_policy)["config"])
        except CheckpointError as err:
            raise ValueError(f"--init-policy: {err}") from None
        m = self.model
        asked = {"task": m.task, "variant": m.variant, "preset": m.preset}
        other = [f"--{k} {v} (the policy's: {getattr(policy_cfg, k)})" for k, v in asked.items()
                 if v is not None and v != getattr(policy_cfg, k)]
        if other and not self.a.demo:
            raise ValueError(f"--init-policy {self.a.init_policy} is another model than "
                             + ", ".join(other) + ": leave them out, the policy's config is the run's")
        train = {"train.seed": m.seed, **({"train.batch_size": m.batch_size} if m.batch_size else {}),
                 **({"train.seq_len": m.seq_len} if m.seq_len else {})}
        if m.precision:   # the request; the policy's own (a shipped bf16 one) is a request too
            train["train.precision"] = m.precision
        cfg = apply_overrides(copy.deepcopy(policy_cfg), {**runs.parse_set(m.set), **train})
        if self.config_args:
            cfg = runs.apply_config_flags(cfg, self.config_args, self.prog)
        diffs = architecture_differences(policy_cfg, cfg)
        if diffs:
            raise ValueError(f"--init-policy {self.a.init_policy}: these options change its networks: "
                             + "; ".join(diffs))
        return cfg

    def _agent_from_policy(self):
        """An agent of the run's config (its optimizers from the run's learning rates) holding
        the policy's weights, update counter 0 (this run's schedule counts its own updates)."""
        from protocad_ros.checkpoint import CheckpointError, read_checkpoint
        from protocad_ros.model.agents import make_agent

        try:
            payload = read_checkpoint(self.init_policy)
            agent = make_agent(self.cfg, int(payload["action_dim"]), device=self.device)
            agent.load_state_dict(payload["modules"], strict=True)
        except (CheckpointError, RuntimeError, KeyError) as err:
            raise ValueError(f"--init-policy {self.init_policy}: its weights do not load: {err}") from None
        agent.updates.zero_()
        return agent

    def _policy_vs_random(self, stop) -> None:
        """The starting policy and the random one on the same unseen contexts, through ROS."""
        from trainer.learn.evaluate import evaluate_through_ros, format_table

        n, cfg = self.a.start_eval_episodes, self.cfg
        print(f"[loop] {self.init_policy} against the random policy on {n} unseen-context episode(s), "
              "through the ROS nodes (sim bridge + policy node / random actor + recorder)", flush=True)
        common = dict(task=cfg.task, split="test", total_episodes=n, seed=cfg.train.seed + 11,
                      out_dir=self.run_dir / "eval_start", domain_id=self.stack.domain_id,
                      episode_length=self.a.episode_length)
        res = evaluate_through_ros(str(self.init_policy), device=self.device, **common)
        if stop.stop:
            return
        rnd = evaluate_through_ros(None, **common)
        print(format_table(res, rnd), flush=True)
        runs.atomic_write_json(self.run_dir / "eval" / "start.json", {**res.to_dict(), "random": rnd.to_dict()})

    def _bag_stats(self, bag: Path) -> dict[str, Any]:
        """The bag's episodes, over every robot namespace it recorded."""
        stores = [s for s in self.ds.stores if Path(s.report.path).resolve() == bag.resolve()]
        eps = [e for s in stores for e in s.episodes]
        complete = [e for e in eps if e["has_first"] and e["has_last"]]
        R = self.cfg.train.action_repeat
        steps = sum(max(e["length"] - 1, 0) for e in eps)
        return {"bag": bag.name, "kind": "prefill" if bag.name.endswith("prefill") else "collect",
                "episodes": len(complete), "partial_episodes": len(eps) - len(complete),
                "env_steps": steps * R, "returns": [round(e["return"], 2) for e in complete],
                "contexts": [e["context"] for e in complete],
                "problems": [p for s in stores for p in s.report.problems()]}

    def _add_bag(self, bag: Path, resumed: bool = False) -> dict[str, Any]:
        for ns in self.namespaces:   # a bag of several robots: each namespace's episodes
            self.ds.add([bag], topics=TopicMap.for_namespace(ns))
        st = self._bag_stats(bag)
        self.phases.append(st)
        if resumed:
            print(f"[loop] found {bag.name}: {st['episodes']} complete episode(s)"
                  + (f", {st['partial_episodes']} partial" if st["partial_episodes"] else ""), flush=True)
        return st

    # ------------------------------------------------------------------ counters
    @property
    def prefill_episodes_done(self) -> int:
        return sum(p["episodes"] for p in self.phases if p["kind"] == "prefill")

    @property
    def collect_phases(self) -> int:
        return sum(p["kind"] == "collect" for p in self.phases)

    @property
    def collected_episodes(self) -> int:
        return sum(p["episodes"] for p in self.phases if p["kind"] == "collect")

    def target_updates(self) -> int:
        return self.schedule.target_updates(self.collected_episodes)

    def _counters(self) -> None:
        c = self.trainer.counters
        c.update(env_steps=sum(p["env_steps"] for p in self.phases),
                 episodes=sum(p["episodes"] for p in self.phases),
                 collect_phases=self.collect_phases, prefill_episodes=self.prefill_episodes_done)

    # ------------------------------------------------------------------ phases
    def _next_bag(self, kind: str) -> Path:
        return self.bags_dir / f"{len(self.phases):02d}_{kind}"

    def _collect(self, kind: str, episodes: int, stop: runs.StopFlag) -> dict[str, Any] | None:
        """One recorded run of every robot's bridge, `episodes` episodes each; returns the phase
        stats (None when interrupted before the bag holds anything)."""
        a, tr = self.a, self.cfg.train
        bag = self._next_bag(kind)
        stack = self.stack
        actor = "actor" if kind == "prefill" else "policy"
        stack.start_recorder(bag, log_name=f"recorder_{bag.name}", namespaces=self.namespaces,
                             wait_topics=[T.topic_name(ns, T.ACTION) for ns in self.namespaces])
        t0 = time.monotonic()
        bridges = []
        for i, ns in enumerate(self.namespaces):
            seed = tr.seed * 1000 + len(self.phases) * len(self.namespaces) + i
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
        st = self._add_bag(bag)
        st["seconds"] = round(time.monotonic() - t0, 1)
        st["interrupted"] = code != 0
        if kind == "collect":
            st["served_updates"] = self._served_updates()
        rets = ", ".join(f"{r:.0f}" for r in st["returns"])
        print(f"[loop] {bag.name}: {st['episodes']} episode(s) in {st['seconds']}s, returns [{rets}]"
              + (f", policy node served checkpoint updates={st.get('served_updates')}" if kind == "collect" else ""),
              flush=True)
        return st

    def _start_policies(self) -> None:
        a, cfg = self.a, self.cfg
        for i, ns in enumerate(self.namespaces):
            proc = self.stack.procs.get(self.stack.key("policy", ns))
            if proc is None or not proc.alive():
                self.stack.start_policy(checkpoint=runs.checkpoint_path(self.run_dir), task=cfg.task,
                                        trusted_keys=self.key.public,
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

    def _wait_policy_loaded(self, updates: int, stop, timeout: float = 120.0) -> None:
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

    def _train(self, stop: runs.StopFlag) -> bool:
        target = self.target_updates()
        if self.trainer.updates >= target or not self.ds.num_windows:
            if not self.ds.num_windows:
                print(f"[loop] no training window of {self.cfg.train.seq_len} steps yet:\n{self.ds.report}", flush=True)
            return True
        self._counters()
        n = target - self.trainer.updates
        print(f"[loop] training {n} updates ({self.trainer.updates} -> {target}) on {self.ds.num_steps} steps "
              f"from {len(self.ds.stores)} bag(s)", flush=True)
        t0 = time.monotonic()
        bar = runs.progress(target, initial=self.trainer.updates, desc="train",
                            disable=True if self.a.no_progress else None, unit="upd")
        try:
            done = self.trainer.train(target, stop=stop, checkpoint_every=self.a.checkpoint_every, bar=bar)
        finally:
            bar.close()
        m = self.trainer.last_metrics
        self._say_expected_time(n - (target - self.trainer.updates), time.monotonic() - t0)
        print(f"[loop] trained to update {self.trainer.updates} in {runs.fmt_seconds(time.monotonic() - t0)}"
              + (f" (wm_loss {m.get('wm_loss', float('nan')):.3g}, reward_loss {m.get('reward_loss', float('nan')):.3g})" if m else "")
              + f"; checkpoint {self.trainer.checkpoint_path}", flush=True)
        return done

    def _say_expected_time(self, n: int, seconds: float) -> None:
        """Once, after the first training phase: how long the rest takes at the rate measured on
        this machine (CPUs differ many times over), so a slow machine says so early."""
        if self._eta_said or n <= 0 or seconds <= 0:
            return
        self._eta_said = True
        a, rate = self.a, n / seconds
        final = self.schedule.target_updates(a.cycles * a.episodes_per_cycle * a.robots)
        left = max(final - self.trainer.updates, 0)
        cycles_left = max(a.cycles - self.collect_phases, 0)
        per_episode = [p["seconds"] / max(p["episodes"] + p["partial_episodes"], 1) for p in self.phases if "seconds" in p]
        collect = cycles_left * a.episodes_per_cycle * (max(per_episode) if per_episode else 0.0)
        print(f"[loop] training runs at {rate:.2f} updates/s on this machine ({self.trainer.agent.precision.precision}, "
              f"{runs.torch_threads()} torch thread(s)): the {left} updates left take about "
              f"{runs.fmt_seconds(left / rate)}; with {cycles_left} collection cycle(s) the loop ends in about "
              f"{runs.fmt_seconds(left / rate + collect)}, then the final evaluation", flush=True)

    # ------------------------------------------------------------------ main
    def _open_trainer(self, callbacks=()) -> None:
        """The trainer: from the run's checkpoint on a resume, else fresh (the --init-policy
        weights); its precision resolved on this machine, said in one line and kept in run.json."""
        a = self.a
        opened = open_trainer(self.cfg, self.run_dir, self.ds, resume=a.resume, device=self.device,
                              end_updates=planned_updates(a), precision=self.model.precision,
                              log_every=a.log_every, callbacks=callbacks,
                              initial_agent=self._agent_from_policy if a.init_policy else None)
        self.trainer = opened.trainer
        if opened.prototype_freeze is not None:
            print(f"[loop] prototypes frozen for the first {opened.prototype_freeze:,} updates", flush=True)
            self.run_json["prototype_freeze"] = opened.prototype_freeze
        print(f"[loop] {opened.precision.describe()}", flush=True)
        self.run_json["precision"] = opened.precision.to_dict()
        runs.atomic_write_json(self.run_dir / "run.json", self.run_json)

    def run(self) -> int:
        from trainer.launch.rosprocs import RosStack

        self._setup()
        a, cfg = self.a, self.cfg
        t_start = time.monotonic()
        from trainer.viz.rerun_log import metrics_callbacks

        self._open_trainer(metrics_callbacks(a.rerun, self.run_dir, "protocad-loop"))
        ckpt = runs.checkpoint_path(self.run_dir)
        # Signed by default: every checkpoint this run writes gets FILE.sig from the run key, and
        # its policy nodes serve only what that key signed (trainer/launch/run_key.py).
        self.key = run_key.run_key(self.run_dir)
        signer = load_private_key(self.key.private)
        self.trainer.after_save.append(lambda path: sign_file(path, signer))
        if ckpt.exists():   # resumed: signed anew (its FILE.sig may be missing, or another key's)
            sign_file(ckpt, signer)
        server, start_server = discovery.from_args(a)
        self.stack = RosStack(self.run_dir / "logs", domain_id=a.domain_id, discovery_server=server,
                              start_discovery_server=start_server)
        print(f"[loop] {cfg.task} / {cfg.variant} / {cfg.preset} on {self.device}; run dir {self.run_dir}; "
              f"ROS_DOMAIN_ID={self.stack.domain_id}; {self.stack.describe_discovery()}; "
              f"node logs in {self.stack.log_dir}; {run_key.describe(self.key)}", flush=True)
        print(f"[loop] plan: prefill {a.prefill_episodes} random episode(s), then {a.cycles} cycle(s) of "
              f"{a.episodes_per_cycle} episode(s) with C={a.updates_per_episode} updates per episode"
              + (f" (resuming: {self.collect_phases} cycle(s), {self.trainer.updates} updates done)" if a.resume else ""),
              flush=True)
        status = "finished"
        with runs.StopFlag() as stop:
            try:
                if a.init_policy and a.start_eval_episodes and not a.resume:
                    self._policy_vs_random(stop)
                # 1. prefill
                while self.prefill_episodes_done < a.prefill_episodes and not stop.stop:
                    for i, ns in enumerate(self.namespaces):
                        self.stack.start_random_actor(task=cfg.task, seed=cfg.train.seed + len(self.phases) + 100 * i,
                                                      ns=ns)
                    left = a.prefill_episodes - self.prefill_episodes_done
                    st = self._collect("prefill", -(-left // len(self.namespaces)), stop)
                    if st is None or (st["episodes"] == 0 and not stop.stop):
                        raise RuntimeError("the prefill phase recorded no complete episode; see "
                                           f"{self.stack.log_dir}")
                # 2. train + collect cycles
                while not stop.stop:
                    if not self._train(stop):
                        break
                    if not ckpt.exists() or self.trainer.counters.get("updates") != self.trainer.updates:
                        self._counters()
                        self.trainer.save()
                    if self.collect_phases >= a.cycles or stop.stop:
                        break
                    self._start_policies()
                    self._wait_policy_loaded(self.trainer.updates, stop)
                    if stop.stop:
                        break
                    st = self._collect("collect", a.episodes_per_cycle, stop)
                    if st is None:
                        break
                    self.trainer.metrics.log(self.trainer.updates, {
                        "collect_return": (sum(st["returns"]) / len(st["returns"])) if st["returns"] else float("nan")},
                        kind="collect", bag=st["bag"], env_steps=sum(p["env_steps"] for p in self.phases),
                        served_updates=st.get("served_updates"))
                if stop.stop:
                    status = "interrupted"
            finally:
                self.stack.stop_all()
                if self.stack.forged_note():
                    print(f"[loop] {self.stack.forged_note()}", file=sys.stderr, flush=True)
                self._counters()
                if self.trainer.updates:
                    self.trainer.save()
                self.trainer.close()
                runs.atomic_write_json(self.run_dir / "phases.json", self.phases)
            eval_json = rrd = None
            if status == "finished" and a.eval_episodes and self.trainer.updates and not stop.stop:
                eval_json = self._final_eval(stop)
                if not a.no_visualize and not stop.stop:
                    rrd = self._visualize()
        self._report(status, t_start, eval_json, rrd)
        return 0

    def _final_eval(self, stop) -> Path | None:
        from trainer.learn.evaluate import evaluate_checkpoint, format_table

        ckpt = runs.checkpoint_path(self.run_dir)
        print(f"[loop] evaluating {ckpt} on the test contexts ({self.a.eval_episodes} episode(s) each, "
              "in-process, deterministic)", flush=True)
        res = evaluate_checkpoint(ckpt, episodes=self.a.eval_episodes, max_contexts=self.a.eval_max_contexts,
                                  seed=self.cfg.train.seed + 7, device=self.device,
                                  time_limit=self.a.episode_length * self.cfg.train.action_repeat,
                                  progress=False if self.a.no_progress else None, stop=stop)
        if stop.stop:
            return None
        # The uniform random policy on the same contexts, episodes and seeds: the reference
        # point a score needs (the demo's few hundred updates stay close to it).
        rnd = evaluate_checkpoint(None, task=self.cfg.task, episodes=self.a.eval_episodes,
                                  contexts=[r.context for r in res.per_context],
                                  seed=self.cfg.train.seed + 7,
                                  time_limit=self.a.episode_length * self.cfg.train.action_repeat,
                                  progress=False if self.a.no_progress else None, stop=stop)
        if stop.stop:
            return None
        print(format_table(res, rnd), flush=True)
        if self.a.demo and not self.init_policy:
            print("[loop] what to expect: the demo trains a few hundred updates, far from the "
                  "~6k Pendulum Swingup needs before DreamerV2's own seeds show learning, so its "
                  "policy scores near the random one; a policy that learned: README 'Results'.",
                  flush=True)
        out = self.run_dir / "eval" / f"test_{self.trainer.updates:06d}.json"
        runs.atomic_write_json(out, {**res.to_dict(), "random": rnd.to_dict()})
        return out

    def _visualize(self) -> Path | None:
        out = self.run_dir / "contexts.rrd"
        try:
            from trainer.viz.visualize import write_context_recording
        except ImportError as exc:
            print(f"[loop] no rerun context recording: trainer.viz.visualize is not available ({exc})", flush=True)
            return None
        import os

        old_cache = os.environ.get("PROTOCAD_CACHE_DIR")
        os.environ["PROTOCAD_CACHE_DIR"] = str(self.ds.cache_dir)  # reuse this run's dataset cache
        print(f"[loop] writing the rerun context recording {out}", flush=True)
        try:
            # The contexts the bags lack, as many per split as the final evaluation had (the
            # demo: 8 of walker's 25 + 64 instead of all: each is an env built and run in-process).
            write_context_recording(runs.checkpoint_path(self.run_dir), logs=[self.bags_dir], out_rrd=out,
                                    device=self.device, progress=False, max_contexts=self.a.eval_max_contexts)
        except Exception as exc:  # noqa: BLE001 - the run's results stand without the picture
            print(f"[loop] rerun context recording failed: {type(exc).__name__}: {exc}", flush=True)
            return None
        finally:
            if old_cache is None:
                os.environ.pop("PROTOCAD_CACHE_DIR", None)
            else:
                os.environ["PROTOCAD_CACHE_DIR"] = old_cache
        return out

    def _report(self, status: str, t_start: float, eval_json: Path | None, rrd: Path | None) -> None:
        c = self.trainer.counters
        print(f"[loop] {status} in {runs.fmt_seconds(time.monotonic() - t_start)}: "
              f"{c.get('episodes', 0)} episodes ({c.get('env_steps', 0)} env steps) in {len(self.phases)} bag(s), "
              f"{self.trainer.updates} updates", flush=True)
        lines = [("run dir", self.run_dir), ("bags (MCAP)", self.bags_dir), ("checkpoint", runs.checkpoint_path(self.run_dir)),
                 ("config", self.run_dir / "config.yaml"), ("metrics", self.run_dir / "metrics.jsonl"),
                 ("phases", self.run_dir / "phases.json"), ("node logs", self.run_dir / "logs")]
        if eval_json:
            lines.append(("evaluation", eval_json))
        if rrd:
            lines.append(("rerun recording", f"{rrd}   (view: rerun {rrd})"))
        for k, v in lines:
            print(f"[loop]   {k + ':':<17}{v}", flush=True)
        if status != "finished":
            print(f"[loop] resume with: protocad-loop --run-dir {self.run_dir} --resume", flush=True)


if __name__ == "__main__":
    sys.exit(main())
