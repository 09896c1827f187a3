"""A loop run's directory: opening a new one or the one --resume continues (config.yaml,
run.json), with --init-policy's config (trainer/learn/init_policy.py), and the ledger of the phases the
bags on disk hold, which the counters, phases.json and a resume read. Its settings are
trainer.launch.loop.LoopSettings, declared beside their command."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

from protocad_ros.checkpoint.files import existing_checkpoint_file
from protocad_ros.model.config import plan_prototype_freeze
from sim_bridge.contract import topics as T
from trainer import runs, settings
from trainer.data.dataset import MCAPDataset, TopicMap
from trainer.launch.rosprocs import robot_namespaces
from trainer.learn.init_policy import policy_config
from trainer.learn.schedule import Schedule
from trainer.run_input import check_settings_section

#: trainer.launch.loop.LoopSettings, by name only: loop.py imports this module, so importing it
#: back would be a cycle.
LoopSettings = Any


def planned_updates(a: LoopSettings) -> int:
    """The updates a loop makes in all: C once after the prefill and per collected episode."""
    return Schedule(N=a.prefill_episodes, C=a.updates_per_episode).target_updates(a.cycles * a.episodes_per_cycle)


#: The loop's protocol, as run.json records it and a resume restores it.
PROTOCOL_KEYS = ("cycles", "episodes_per_cycle", "prefill_episodes", "updates_per_episode", "episode_length",
                 "exploration_noise", "eval_episodes", "robots")



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
            check_settings_section(run_dir / "run.json", "protocol", type(s),
                                   {k: v for k, v in (saved_protocol or {}).items() if k in PROTOCOL_KEYS})
        else:
            cfg = (policy_config(init_policy, model, config_args=config_args, prog=prog, other_model_allowed=s.demo)
                   if s.init_policy
                   else model.to_config(config_args, prog))
            cfg.train.device = device
            # a refused plan leaves no run directory behind
            plan_prototype_freeze(cfg, 0, planned_updates(s.resolved(cfg.train)))
            run_dir = runs.new_run_dir(s.run_dir, "loop", cfg.task, cfg.variant)
            run_dir.mkdir(parents=True, exist_ok=True)
            runs.save_run_config(run_dir, cfg)
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
