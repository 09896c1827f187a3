"""A loop run's settings and its run directory: LoopSettings (protocad-loop's protocol and run
options; unset values resolved once from the demo, a resumed run's protocol and the config),
opening a new run directory or the one --resume continues (config.yaml, run.json), the config
and weights --init-policy starts from, and the ledger of the phases the bags on disk hold, which
the counters, phases.json and a resume read."""
from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

from protocad_ros.checkpoint import CheckpointError, architecture_differences, existing_checkpoint_file, read_checkpoint
from protocad_ros.model.agent import make_agent
from protocad_ros.model.config import Config, apply_overrides, plan_prototype_freeze
from protocad_ros.policy import shipped_policy
from sim_bridge.contract import topics as T
from trainer import cli_values, run_config, runs, settings
from trainer.data.dataset import MCAPDataset, TopicMap
from trainer.launch import discovery
from trainer.launch.rosprocs import robot_namespaces
from trainer.learn.schedule import Schedule
from trainer.runs import check_settings_section
from trainer.settings import arg

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
    robots: int | None = arg(None, type=cli_values.positive_int, group="loop")
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


#: Tasks whose shipped policy the demo starts from, in this order, when the package has one.
DEMO_POLICY_TASKS = ("walker_walk", "cheetah_run")


def planned_updates(a: LoopSettings) -> int:
    """The updates a loop makes in all: C once after the prefill and per collected episode."""
    return Schedule(N=a.prefill_episodes, C=a.updates_per_episode).target_updates(a.cycles * a.episodes_per_cycle)


def with_shipped_policy(s: LoopSettings, model: settings.ModelChoice) -> LoopSettings:
    """The demo: start from a shipped policy (of --task if given, else the first of
    DEMO_POLICY_TASKS the package ships) unless --init-policy names one."""
    if s.init_policy or s.resume:
        return s
    for task in [model.task] if model.task else DEMO_POLICY_TASKS:
        if path := shipped_policy(task):
            return dataclasses.replace(s, init_policy=str(path))
    return s


#: The loop's protocol, as run.json records it and a resume restores it.
PROTOCOL_KEYS = ("cycles", "episodes_per_cycle", "prefill_episodes", "updates_per_episode", "episode_length",
                 "exploration_noise", "eval_episodes", "robots")



def policy_config(init_policy: Path, s: LoopSettings, model: settings.ModelChoice, *,
                  config_args: Sequence[str], prog: str):
    """--init-policy: the policy file's config (its networks) with this run's training
    options on top (--set, --batch-size, --seq-len, --seed, --precision, config flags); an
    option that would change the networks is refused (ValueError)."""
    try:
        policy_cfg = Config.from_dict(read_checkpoint(init_policy)["config"])
    except CheckpointError as err:
        raise ValueError(f"--init-policy: {err}") from None
    m = model
    asked = {"task": m.task, "variant": m.variant, "preset": m.preset}
    other = [f"--{k} {v} (the policy's: {getattr(policy_cfg, k)})" for k, v in asked.items()
             if v is not None and v != getattr(policy_cfg, k)]
    if other and not s.demo:
        raise ValueError(f"--init-policy {s.init_policy} is another model than "
                         + ", ".join(other) + ": leave them out, the policy's config is the run's")
    train = {"train.seed": m.seed, **({"train.batch_size": m.batch_size} if m.batch_size else {}),
             **({"train.seq_len": m.seq_len} if m.seq_len else {})}
    if m.precision:   # the request; the policy's own (a shipped bf16 one) is a request too
        train["train.precision"] = m.precision
    cfg = apply_overrides(copy.deepcopy(policy_cfg), {**run_config.parse_set(m.set), **train})
    if config_args:
        cfg = run_config.apply_config_flags(cfg, list(config_args), prog)
    diffs = architecture_differences(policy_cfg, cfg)
    if diffs:
        raise ValueError(f"--init-policy {s.init_policy}: these options change its networks: "
                         + "; ".join(diffs))
    return cfg


def agent_from_policy(init_policy: Path, cfg, device: str):
    """An agent of the run's config (its optimizers from the run's learning rates) holding
    the policy's weights, update counter 0 (this run's schedule counts its own updates)."""
    try:
        payload = read_checkpoint(init_policy)
        agent = make_agent(cfg, int(payload["action_dim"]), device=device)
        agent.load_state_dict(payload["modules"], strict=True)
    except (CheckpointError, RuntimeError, KeyError) as err:
        raise ValueError(f"--init-policy {init_policy}: its weights do not load: {err}") from None
    agent.updates.zero_()
    return agent


class LoopRunDir:
    """The run directory of a loop, opened: the settings it runs with (resolved), its config,
    run.json, the --init-policy file, the schedule, the robots' namespaces and the ledger of its
    bags. `open` makes a new one or continues one (--resume)."""

    def __init__(self, a: LoopSettings, cfg, path: Path, run_json: dict[str, Any], init_policy: Path | None):
        self.a, self.cfg, self.path, self.run_json, self.init_policy = a, cfg, path, run_json, init_policy
        self.schedule = Schedule(N=a.prefill_episodes, C=a.updates_per_episode)
        self.namespaces = robot_namespaces(T.DEFAULT_NAMESPACE, a.robots)
        self.bags_dir = path / "bags"
        tr = cfg.train
        self.ledger = PhaseLedger(MCAPDataset([], topics=TopicMap(), seq_len=tr.seq_len, seed=tr.seed,
                                              cache_dir=a.cache_dir or path / "cache"),
                                  self.namespaces, self.bags_dir, tr.action_repeat)

    @classmethod
    def open(cls, s: LoopSettings, model: settings.ModelChoice, *, device: str, config_args: Sequence[str],
             prog: str, argv: Sequence[str]) -> "LoopRunDir":
        """A new run directory (config.yaml written; nothing when the plan is refused), or the
        one --resume continues; its run.json written, its bags read into the ledger."""
        saved_protocol = None
        init_policy = None
        if s.init_policy:
            init_policy = existing_checkpoint_file(s.init_policy)
        if s.resume:
            # A loop stopped during its prefill has bags but no checkpoint yet: still resumable.
            run_dir, run_json = runs.resume_run_dir(s.run_dir, need_checkpoint=False)
            cfg = runs.load_run_config(run_dir)
            saved_protocol = run_json.get("protocol")
            if saved_protocol is not None and not isinstance(saved_protocol, dict):
                raise ValueError(f"--resume: {run_dir / 'run.json'}: 'protocol' is not a mapping")
            check_settings_section(run_dir / "run.json", "protocol", LoopSettings,
                                   {k: v for k, v in (saved_protocol or {}).items() if k in PROTOCOL_KEYS})
        else:
            cfg = (policy_config(init_policy, s, model, config_args=config_args, prog=prog) if s.init_policy
                   else model.to_config(config_args, prog))
            cfg.train.device = device
            # a refused plan leaves no run directory behind
            plan_prototype_freeze(cfg, 0, planned_updates(s.resolved(cfg.train)))
            run_dir = runs.new_run_dir(s.run_dir, "loop", cfg.task, cfg.variant)
            run_dir.mkdir(parents=True, exist_ok=True)
            cfg.save(run_dir / "config.yaml")
            run_json = {}
        tr = cfg.train
        a = s.resolved(tr, saved_protocol)
        rd = cls(a, cfg, run_dir, run_json, init_policy)
        runs.record_invocation(run_json, a.resume, list(argv))
        run_json.update(kind="loop", task=cfg.task, variant=cfg.variant, preset=cfg.preset, seed=tr.seed,
                        device=device, protocol={k: getattr(a, k) for k in PROTOCOL_KEYS},
                        settings={"loop": settings.as_data(a), "model": settings.as_data(model)})
        rd.write_run_json()
        rd.bags_dir.mkdir(exist_ok=True)
        for bag in sorted(p for p in rd.bags_dir.iterdir() if p.is_dir()):
            rd.ledger.add_bag(bag, resumed=True)
        return rd

    def write_run_json(self) -> None:
        runs.atomic_write_json(self.path / "run.json", self.run_json)


class PhaseLedger:
    """The run's phases, one per bag (prefill or collect): the episodes, env steps and returns
    each recorded, read into the dataset for every robot namespace; the counters and the
    schedule's target follow from them, so a resume counts from the bags on disk."""

    def __init__(self, ds: MCAPDataset, namespaces: Sequence[str], bags_dir: Path, action_repeat: int):
        self.ds, self.namespaces, self.bags_dir, self.action_repeat = ds, list(namespaces), bags_dir, action_repeat
        self.phases: list[dict[str, Any]] = []

    def _bag_stats(self, bag: Path) -> dict[str, Any]:
        """The bag's episodes, over every robot namespace it recorded."""
        stores = [s for s in self.ds.stores if Path(s.report.path).resolve() == bag.resolve()]
        eps = [e for s in stores for e in s.episodes]
        complete = [e for e in eps if e["has_first"] and e["has_last"]]
        R = self.action_repeat
        steps = sum(max(e["length"] - 1, 0) for e in eps)
        return {"bag": bag.name, "kind": "prefill" if bag.name.endswith("prefill") else "collect",
                "episodes": len(complete), "partial_episodes": len(eps) - len(complete),
                "env_steps": steps * R, "returns": [round(e["return"], 2) for e in complete],
                "contexts": [e["context"] for e in complete],
                "problems": [p for s in stores for p in s.report.problems()]}

    def add_bag(self, bag: Path, resumed: bool = False) -> dict[str, Any]:
        for ns in self.namespaces:   # a bag of several robots: each namespace's episodes
            self.ds.add([bag], topics=TopicMap.for_namespace(ns))
        st = self._bag_stats(bag)
        self.phases.append(st)
        if resumed:
            print(f"[loop] found {bag.name}: {st['episodes']} complete episode(s)"
                  + (f", {st['partial_episodes']} partial" if st["partial_episodes"] else ""), flush=True)
        return st

    def next_bag(self, kind: str) -> Path:
        return self.bags_dir / f"{len(self.phases):02d}_{kind}"

    @property
    def prefill_episodes_done(self) -> int:
        return sum(p["episodes"] for p in self.phases if p["kind"] == "prefill")

    @property
    def collect_phases(self) -> int:
        return sum(p["kind"] == "collect" for p in self.phases)

    @property
    def collected_episodes(self) -> int:
        return sum(p["episodes"] for p in self.phases if p["kind"] == "collect")

    @property
    def env_steps(self) -> int:
        return sum(p["env_steps"] for p in self.phases)

    def update_counters(self, counters: dict[str, Any]) -> None:
        """The trainer's counters (saved with every checkpoint) from the phases so far."""
        counters.update(env_steps=self.env_steps, episodes=sum(p["episodes"] for p in self.phases),
                        collect_phases=self.collect_phases, prefill_episodes=self.prefill_episodes_done)

    def write(self, path: Path) -> None:
        runs.atomic_write_json(path, self.phases)
