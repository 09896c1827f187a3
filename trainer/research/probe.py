"""`protocad-probe`: does a checkpoint's context representation carry the physics, and how far
does its world model predict, on contexts it trained on and on unseen ones?

    protocad-probe protocad_ros/policies/walker_walk.pt --max-contexts 32 --json probe.json \\
        --plot probe.png --rrd probe.rrd
    protocad-probe runs/X --episodes 2 --steps 500          # a run directory: its latest.pt

It runs the checkpoint's policy on the training and the test contexts of its task (--episodes
each, --steps agent steps, actor mode as evaluation acts), then:

* probes (trainer/research/probe_fit.py): ridge regressions from the window means of u, w, e
  (ProtoCAD variants), the RSSM deterministic state h and a random projection of the pixels (the
  floor) to log m and log d, scored by R^2 and Spearman rank correlation within the test grid
  (grouped cross-validation by context), within each mass cluster of it (m < 1, m > 1), and from
  the training contexts to the test contexts;
* open-loop prediction (trainer/research/probe_collect.py): after 5 observed frames, the image
  MSE and reward error at each horizon 1..--horizon, on test and on training contexts;
* how far training moved the prototypes c_k from their seeded initial values (1.0: they never
  trained, as in every walker run before the freeze was scaled to the run).

Outputs: the tables on stdout; --json (schema protocad-probe/1, msgs_docs/results.md), --plot
(PNG), --rrd (rerun recording of the features coloured by context).
"""
from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from protocad_ros.atomic import file_sha256
from protocad_ros.checkpoint.agent_file import load_checkpoint, read_checkpoint, read_provenance
from protocad_ros.checkpoint.files import CheckpointError, existing_checkpoint_file
from protocad_ros.model.agent import make_agent
from protocad_ros.policy import Policy
from sim_bridge.contract.contexts import get_task
from trainer import settings, torch_setup
from trainer.learn.context_health import collapse_reason
from trainer.learn.evaluate import select_contexts
from trainer.provenance import code_version
from trainer.research import probe_report
from trainer.research.probe_collect import Collected, Plan, collect
from trainer.research.probe_fit import Windows, run_probes
from trainer.settings import arg


@dataclass
class ProbeSettings:
    """What protocad-probe runs: which checkpoint, on how much of each split, and what it writes."""

    checkpoint: str = arg("", "checkpoint", nargs="?", metavar="CHECKPOINT")
    """checkpoint file, or a run directory holding checkpoints/latest.pt"""
    episodes: int = 1
    """episodes per context"""
    steps: int = 300
    """agent steps (observations) per episode"""
    skip: int = 25
    """steps dropped at the start of each episode before the first window (the filter has not
    yet seen the dynamics)"""
    window: int = 25
    """steps per window; each window's mean is one probe sample"""
    horizon: int = 50
    """open-loop horizons 1..H predicted after the context frames"""
    context_frames: int = 5
    """observed frames before each open-loop prediction (the paper's figure: 5)"""
    max_contexts: int = 0
    """per split, the fixed stratified subset of K contexts (TaskSpec.stratified; 0 = all:
    walker_walk has 25 train and 64 test contexts)"""
    pixel_dim: int = 32
    """dimensions of the pixels' random projection (the floor)"""
    batch: int = 8
    """episodes run side by side"""
    seed: int = 0
    """seeds the envs, the policy's samples, the pixel projection and the folds"""
    drift_from: str | None = arg(None, metavar="POLICY_PT")
    """the policy file the checkpoint's run started from (its --init-policy): the prototypes'
    drift is measured from that file's prototypes, not from the config's seeded draw"""
    json: str | None = arg(None, metavar="FILE")
    """write the results as JSON (schema protocad-probe/1)"""
    plot: str | None = arg(None, metavar="FILE.png")
    """write a PNG: R^2 bars per feature and setting, open-loop error curves"""
    rrd: str | None = arg(None, metavar="FILE.rrd")
    """write a rerun recording: the window features in 2-D PCA, coloured by context"""
    device: str = "cpu"
    """cpu, cuda, cuda:N or auto"""
    threads: int = arg(0, help=settings.THREADS_HELP)
    """torch threads"""
    no_progress: bool = False
    """no progress bar"""
    summarize: list[str] = arg([], nargs="+", metavar="PROBE_JSON")
    """instead of probing: the tables of these probe JSONs together (a grid's seeds of each
    variant), as markdown: per variant the mean R^2 over them (min to max) and open-loop errors"""

    def plan(self) -> Plan:
        return Plan(episodes=self.episodes, steps=self.steps, skip=self.skip, window=self.window,
                    context_steps=self.context_frames, horizon=self.horizon, batch=self.batch,
                    pixel_dim=self.pixel_dim, seed=self.seed)


def build_parser():
    return settings.settings_parser(
        "protocad-probe",
        "Probe a checkpoint's context features: linear probes of log m and log d from u, w, e, the "
        "RSSM state h and a pixel floor (within the test grid, within its mass clusters, train -> "
        "test), and open-loop image and reward errors per horizon on test and training contexts.",
        [(None, ProbeSettings)])


def main(argv: Sequence[str] | None = None) -> int:
    parsed = settings.parse(build_parser(), argv, config_help=False)
    try:
        return run(parsed.get(ProbeSettings), command=["protocad-probe", *parsed.argv])
    except (ValueError, CheckpointError) as exc:
        print(f"protocad-probe: error: {exc}", file=sys.stderr)
        return 2


def load(checkpoint: str, device: str) -> tuple[Any, dict[str, Any], Path]:
    """The agent, its counters and the checkpoint file; ValueError for a variant without a
    world model (nothing to probe)."""
    if not checkpoint:
        raise ValueError("give a CHECKPOINT (file or run directory)")
    path = existing_checkpoint_file(checkpoint)
    agent, counters = load_checkpoint(path, device=device, restore_rng=False,
                                      optimizer_states=False)
    if not hasattr(agent, "wm"):
        raise ValueError(f"{path}: variant {agent.cfg.variant!r} has no world model to probe")
    if not counters:   # a policy file: its run's counters (env steps, freeze) are in its provenance
        kept = read_provenance(path).get("counters")
        counters = ({k: v for k, v in kept.items() if isinstance(v, (int, float))}
                    if isinstance(kept, dict) else {})
    return agent, dict(counters), path


def document(s: ProbeSettings, agent: Any, *, counters: dict[str, Any], path: Path, data: Collected,
             windows: Windows) -> dict[str, Any]:
    """The protocad-probe/1 JSON of one probed checkpoint (probes fitted here)."""
    cfg = agent.cfg
    probes, skipped = run_probes(windows, s.seed)
    health = ({k: float(np.mean([h[k] for h in data.health])) for k in data.health[0]}
              if data.health else None)
    counts = np.bincount(windows.context, minlength=len(data.contexts))
    env_steps = counters.get("env_steps")
    return {
        "schema": probe_report.SCHEMA_ID, "command": [], "code_version": code_version(),
        "checkpoint": str(path), "task": cfg.task, "variant": cfg.variant,
        "updates": int(agent.counters()["updates"]),
        "env_steps": int(env_steps) if env_steps is not None else None,
        "settings": {"episodes": s.episodes, "steps": s.steps, "skip": s.skip, "window": s.window,
                     "context_steps": s.context_frames, "horizon": s.horizon, "max_contexts": s.max_contexts,
                     "seed": s.seed, "pixel_dim": s.pixel_dim, "episodes_run": data.episodes},
        "features": {k: int(v.shape[1]) for k, v in windows.features.items()},
        "contexts": [{"split": sp, "context": c, "windows": int(n)} for (sp, c), n in zip(data.contexts, counts)],
        "probes": probes, "skipped": skipped,
        "open_loop": {split: data.open_loop[split].mean() for split in ("test", "train") if split in data.open_loop},
        "assignment": data.assignment.mean(),
        "health": health,
        "collapsed": collapse_reason(health, cfg.context.num_prototypes) if health else None,
        "prototypes": prototype_drift(agent, counters.get("prototype_freeze"),
                                      Path(s.drift_from) if s.drift_from else None),
        "seconds": 0.0,
    }


def prototype_drift(agent: Any, freeze: int | None = None, start_policy: Path | None = None) -> dict[str, Any] | None:
    """The cosine of each prototype c_k to its initial direction, summarised (None for a
    variant without prototypes). Initialisation is seeded by the config alone (Agent), so
    rebuilding the agent from its config redraws exactly the values training started from;
    a run that started from a policy file started from that file's (`start_policy`).
    `freeze`: the run's effective prototype freeze (its counters), kept beside the figures."""
    mine = {n: p for n, p in agent.named_parameters() if n.endswith("prototypes")}
    if not mine:
        return None
    name, c = next(iter(mine.items()))
    if start_policy is None:
        initial = dict(make_agent(agent.cfg, agent.action_dim, device="cpu").named_parameters())[name]
    else:
        initial = read_checkpoint(existing_checkpoint_file(start_policy))["modules"].get(name)
        if not isinstance(initial, torch.Tensor) or initial.shape != c.shape:
            raise ValueError(f"--drift-from {start_policy}: its {name} "
                             + ("is missing" if not isinstance(initial, torch.Tensor) else
                                f"has shape {tuple(initial.shape)}, this checkpoint's {tuple(c.shape)}")
                             + ": not the policy this run started from")
    with torch.no_grad():
        cos = F.cosine_similarity(c.float().cpu(), initial.float(), dim=-1)
    return {"parameter": name, "cos_to_initial_mean": float(cos.mean()), "cos_to_initial_min": float(cos.min()),
            "count": int(cos.numel()), "prototype_freeze": None if freeze is None else int(freeze),
            "start": "seeded draw" if start_policy is None else {"policy": str(start_policy),
                                                                "sha256": file_sha256(start_policy)}}


def _params(task: str) -> tuple[str, ...]:
    return get_task(task).params


def run(s: ProbeSettings, command: Sequence[str] = ()) -> int:
    """Probe as the settings say: print the tables, write what was asked for (`command`: the
    argv the JSON records)."""
    if s.summarize:
        docs = [probe_report.read_json(p) for p in s.summarize]
        print(probe_report.summary_markdown(docs))
        return 0
    t0 = time.monotonic()
    s.plan().check()
    torch_setup.setup_torch(s.threads)
    device = torch_setup.resolve_device(s.device)
    agent, counters, path = load(s.checkpoint, device)
    if s.drift_from:   # checked before the episodes, not after them
        prototype_drift(agent, None, Path(s.drift_from))

    contexts = {split: select_contexts(agent.cfg.task, split, max_contexts=s.max_contexts)
                for split in ("train", "test")}
    policy = Policy(agent, device=device, mode="deterministic", seed=s.seed)
    data = collect(agent, policy, contexts, s.plan(), progress=False if s.no_progress else None)
    windows = data.windows(_params(agent.cfg.task))
    doc = document(s, agent, counters=counters, path=path, data=data, windows=windows)
    doc["command"] = [str(c) for c in command]
    doc["seconds"] = round(time.monotonic() - t0, 2)
    print(probe_report.report_text(doc))
    if s.json:
        probe_report.write_json(doc, Path(s.json))
        print(f"[probe] results: {s.json}")
    if s.plot:
        probe_report.write_png(doc, Path(s.plot))
        print(f"[probe] plot: {s.plot}")
    if s.rrd:
        probe_report.write_rrd(doc, windows, data.contexts, Path(s.rrd))
        print(f"[probe] rerun recording: {s.rrd} (open it with: rerun {s.rrd})")
    print(f"[probe] {data.episodes} episodes in {doc['seconds']:.0f}s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
