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

Its settings are LoopSettings, below. The parts, which `Loop.run` opens and drives in this
order: loop_rundir.py (the run directory and its ledger of phases), trainer/learn/resume.py
(the trainer, fresh or resumed), loop_collect.py (prefill and collection through the ROS
nodes), the training phase below, and loop_eval.py (the start and final evaluations, the rerun
recording).
"""
from __future__ import annotations

import dataclasses
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

from protocad_ros.checkpoint.signing import load_private_key, sign_file
from protocad_ros.policy import shipped_policy
from trainer import cli_values, console, runs, settings, torch_setup
from trainer.launch import discovery, run_key
from trainer.launch.loop_collect import Collection
from trainer.launch.loop_eval import context_recording, final_evaluation, policy_vs_random
from trainer.launch.loop_rundir import PROTOCOL_KEYS, LoopRunDir, planned_updates
from trainer.launch.rosprocs import NodeFailed, RosStack
from trainer.learn.resume import TrainerOpening, open_trainer
from trainer.learn.trainer import Trainer
from trainer.settings import arg
from trainer.viz.metrics_rerun import metrics_callbacks

#: The demo's protocol. C=15: its 60 updates are most of its wall time, and on a CPU without bf16
#: arithmetic (float32, about 4.7 s an update of 16 x 50 on one AVX2 core) 100 updates alone took
#: 8 of the 10 minutes the demo may take there (issue 41); a demo shows the loop, not learning.
DEMO = dict(task="pendulum_swingup", preset="small", cycles=3, episodes_per_cycle=1, prefill=2,
            updates_per_episode=15, eval_episodes=1, eval_max_contexts=8)


@dataclass
class LoopSettings(discovery.DiscoverySettings):
    """protocad-loop's protocol (Algorithm 1 through the ROS nodes), run options and how its
    nodes discover. Unset values come from the config (train.*) or the demo, once, in `resolved`."""

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


def with_shipped_policy(s: LoopSettings, model: settings.ModelChoice) -> LoopSettings:
    """The demo: start from a shipped policy (of --task if given, else the first of
    DEMO_POLICY_TASKS the package ships) unless --init-policy names one."""
    if s.init_policy or s.resume:
        return s
    for task in [model.task] if model.task else DEMO_POLICY_TASKS:
        if path := shipped_policy(task):
            return dataclasses.replace(s, init_policy=str(path))
    return s


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


class TrainingPhase:
    """C updates after the prefill and per collected episode, from every bag so far: the
    trainer brought up to the schedule's target, its rate said once."""

    def __init__(self, trainer: Trainer, rundir: LoopRunDir):
        self.trainer, self.rundir = trainer, rundir
        self._eta_said = False   # the expected time is said once, after the first training phase

    def __call__(self, stop: console.StopFlag) -> bool:
        """Train up to the schedule's target; False when stopped before it."""
        a, ledger, trainer = self.rundir.a, self.rundir.ledger, self.trainer
        target = self.rundir.schedule.target_updates(ledger.collected_episodes)
        if trainer.updates >= target or not ledger.ds.num_windows:
            if not ledger.ds.num_windows:
                print(f"[loop] no training window of {self.rundir.cfg.train.seq_len} steps yet:\n{ledger.ds.report}", flush=True)
            return True
        ledger.update_counters(trainer.counters)
        n = target - trainer.updates
        print(f"[loop] training {n} updates ({trainer.updates} -> {target}) on {ledger.ds.num_steps} steps "
              f"from {len(ledger.ds.stores)} bag(s)", flush=True)
        t0 = time.monotonic()
        bar = console.progress(target, initial=trainer.updates, desc="train",
                            disable=True if a.no_progress else None, unit="upd")
        try:
            done = trainer.train(target, stop=stop, checkpoint_every=a.checkpoint_every, bar=bar)
        finally:
            bar.close()
        m = trainer.last_metrics
        self._say_expected_time(n - (target - trainer.updates), time.monotonic() - t0)
        print(f"[loop] trained to update {trainer.updates} in {cli_values.format_duration(time.monotonic() - t0)}"
              + (f" (wm_loss {m.get('wm_loss', float('nan')):.3g}, reward_loss {m.get('reward_loss', float('nan')):.3g})" if m else "")
              + f"; checkpoint {trainer.checkpoint_path}", flush=True)
        return done

    def _say_expected_time(self, n: int, seconds: float) -> None:
        """Once, after the first training phase: how long the rest takes at the rate measured on
        this machine (CPUs differ many times over), so a slow machine says so early."""
        if self._eta_said or n <= 0 or seconds <= 0:
            return
        self._eta_said = True
        a, ledger, trainer, rate = self.rundir.a, self.rundir.ledger, self.trainer, n / seconds
        final = self.rundir.schedule.target_updates(a.cycles * a.episodes_per_cycle * a.robots)
        left = max(final - trainer.updates, 0)
        cycles_left = max(a.cycles - ledger.collect_phases, 0)
        per_episode = [p["seconds"] / max(p["episodes"] + p["partial_episodes"], 1) for p in ledger.phases if "seconds" in p]
        collect = cycles_left * a.episodes_per_cycle * (max(per_episode) if per_episode else 0.0)
        print(f"[loop] training runs at {rate:.2f} updates/s on this machine ({trainer.agent.precision.precision}, "
              f"{torch_setup.torch_threads()} torch thread(s)): the {left} updates left take about "
              f"{cli_values.format_duration(left / rate)}; with {cycles_left} collection cycle(s) the loop ends in about "
              f"{cli_values.format_duration(left / rate + collect)}, then the final evaluation", flush=True)


class Loop:
    """One protocad-loop run: its parts opened in order (run directory, trainer, the signing key,
    the ROS stack), then the prefill, the train-collect cycles and the final evaluation."""

    def __init__(self, s: LoopSettings, model: settings.ModelChoice, config_args: Sequence[str] = (),
                 prog: str = "protocad-loop", argv: Sequence[str] | None = None):
        if s.demo:
            s = with_shipped_policy(s, model)
            if not s.init_policy:
                model = dataclasses.replace(model, task=model.task or DEMO["task"], preset=model.preset or DEMO["preset"])
        self.a, self.model = s.with_demo(), model
        self.config_args, self.prog = list(config_args), prog
        self.argv = list(sys.argv[1:] if argv is None else argv)
        self.device = torch_setup.resolve_device(model.device)
        torch_setup.setup_torch(model.threads)

    def _setup(self) -> None:
        self.rundir = LoopRunDir.open(self.a, self.model, device=self.device, config_args=self.config_args,
                                      prog=self.prog, argv=self.argv)
        self.a, self.cfg, self.run_dir = self.rundir.a, self.rundir.cfg, self.rundir.path

    def _open_trainer(self, callbacks=()) -> None:
        """The trainer: from the run's checkpoint on a resume, else fresh (the --init-policy
        weights); its precision resolved on this machine, said in one line and kept in run.json."""
        a, rd = self.a, self.rundir
        opened = open_trainer(self.cfg, self.run_dir, rd.ledger.ds, TrainerOpening(
            resume=a.resume, device=self.device, end_updates=planned_updates(a), precision=self.model.precision,
            log_every=a.log_every, callbacks=callbacks,
            init_policy=rd.init_policy if a.init_policy else None))
        self.trainer = opened.trainer
        if opened.prototype_freeze is not None:
            print(f"[loop] prototypes frozen for the first {opened.prototype_freeze:,} updates", flush=True)
            rd.run_json["prototype_freeze"] = opened.prototype_freeze
        print(f"[loop] {opened.precision.describe()}", flush=True)
        rd.run_json["precision"] = opened.precision.to_dict()
        rd.write_run_json()

    def _sign_checkpoints(self) -> None:
        """Signed by default: every checkpoint this run writes gets FILE.sig from the run key, and
        its policy nodes serve only what that key signed (trainer/launch/run_key.py)."""
        ckpt = runs.checkpoint_path(self.run_dir)
        self.key = run_key.run_key(self.run_dir)
        signer = load_private_key(self.key.private)
        self.trainer.after_save.append(lambda path: sign_file(path, signer))
        if ckpt.exists():   # resumed: signed anew (its FILE.sig may be missing, or another key's)
            sign_file(ckpt, signer)

    def _start_stack(self) -> None:
        a, cfg = self.a, self.cfg
        server, start_server = discovery.from_args(a)
        self.stack = RosStack(self.run_dir / "logs", domain_id=a.domain_id, discovery_server=server,
                              start_discovery_server=start_server)
        print(f"[loop] {cfg.task} / {cfg.variant} / {cfg.preset} on {self.device}; run dir {self.run_dir}; "
              f"ROS_DOMAIN_ID={self.stack.domain_id}; {self.stack.describe_discovery()}; "
              f"node logs in {self.stack.log_dir}; {run_key.describe(self.key)}", flush=True)
        print(f"[loop] plan: prefill {a.prefill_episodes} random episode(s), then {a.cycles} cycle(s) of "
              f"{a.episodes_per_cycle} episode(s) with C={a.updates_per_episode} updates per episode"
              + (f" (resuming: {self.rundir.ledger.collect_phases} cycle(s), {self.trainer.updates} updates done)"
                 if a.resume else ""), flush=True)

    def run(self) -> int:
        self._setup()
        a = self.a
        t_start = time.monotonic()
        self._open_trainer(metrics_callbacks(a.rerun, self.run_dir, "protocad-loop"))
        self._sign_checkpoints()
        self._start_stack()
        collection = Collection(self.stack, self.rundir, trusted_keys=self.key.public, device=self.device)
        training = TrainingPhase(self.trainer, self.rundir)
        status = "finished"
        with console.StopFlag() as stop:
            try:
                if a.init_policy and a.start_eval_episodes and not a.resume:
                    policy_vs_random(self.rundir, self.stack.domain_id, self.device, stop)
                collection.prefill(stop)
                self._train_and_collect(collection, training, stop)
                if stop.stop:
                    status = "interrupted"
            finally:
                self._stop()
            eval_json = rrd = None
            if status == "finished" and a.eval_episodes and self.trainer.updates and not stop.stop:
                eval_json = final_evaluation(self.rundir, self.trainer.updates, self.device, stop)
                if not a.no_visualize and not stop.stop:
                    rrd = context_recording(self.rundir, self.device)
        self._report(status, t_start, eval_json, rrd)
        return 0

    def _train_and_collect(self, collection: Collection, training: TrainingPhase, stop: console.StopFlag) -> None:
        """The cycles: train to the schedule's target and checkpoint, then, until the cycles are
        done, collect a cycle once every policy node has loaded that checkpoint."""
        a, trainer, ledger = self.a, self.trainer, self.rundir.ledger
        ckpt = runs.checkpoint_path(self.run_dir)
        while not stop.stop:
            if not training(stop):
                break
            if not ckpt.exists() or trainer.counters.get("updates") != trainer.updates:
                ledger.update_counters(trainer.counters)
                trainer.save()
            if ledger.collect_phases >= a.cycles or stop.stop:
                break
            collection.start_policies()
            collection.wait_policy_loaded(trainer.updates, stop)
            if stop.stop:
                break
            st = collection.collect("collect", a.episodes_per_cycle, stop)
            if st is None:
                break
            trainer.metrics.log(trainer.updates, {
                "collect_return": (sum(st["returns"]) / len(st["returns"])) if st["returns"] else float("nan")},
                kind="collect", bag=st["bag"], env_steps=ledger.env_steps,
                served_updates=st.get("served_updates"))

    def _stop(self) -> None:
        """The nodes stopped (the recorder last: its bag closes cleanly), the counters and a
        checkpoint saved, phases.json written: also after Ctrl-C or a failed node."""
        self.stack.stop_all()
        if self.stack.forged_note():
            print(f"[loop] {self.stack.forged_note()}", file=sys.stderr, flush=True)
        self.rundir.ledger.update_counters(self.trainer.counters)
        if self.trainer.updates:
            self.trainer.save()
        self.trainer.close()
        self.rundir.ledger.write(self.run_dir / "phases.json")

    def _report(self, status: str, t_start: float, eval_json: Path | None, rrd: Path | None) -> None:
        c = self.trainer.counters
        print(f"[loop] {status} in {cli_values.format_duration(time.monotonic() - t_start)}: "
              f"{c.get('episodes', 0)} episodes ({c.get('env_steps', 0)} env steps) in {len(self.rundir.ledger.phases)} bag(s), "
              f"{self.trainer.updates} updates", flush=True)
        lines = [("run dir", self.run_dir), ("bags (MCAP)", self.rundir.bags_dir), ("checkpoint", runs.checkpoint_path(self.run_dir)),
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
