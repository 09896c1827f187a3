"""The study's runs: every arm x seed, RUN = GRID/ARM/seed_S, a world model trained on DATA/train
(checkpoints every 100 updates; a killed run resumes from its last), then evaluated on DATA/eval
into RUN/eval.json: open-loop image and reward error at each horizon after 5 observed frames, per
split; linear probes of log m and log d (protocad-probe's, on the same windows); the context
module's health (trainer.learn.context_health.health_of_states) on the unseen contexts."""
from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from protocad_ros.atomic import atomic_write_text
from protocad_ros.model.config import Config, make_config
from sim_bridge.contract.contexts import get_task, normalized_log_context
from trainer import runs
from trainer.data.dataset import MCAPDataset
from trainer.learn.context_health import health_of_states
from trainer.learn.trainer import Trainer
from trainer.research.probe_collect import (
    Collected,
    Plan,
    add_open_loop,
    feature_windows,
    open_loop_errors,
    pixel_projection,
)
from trainer.research.probe_fit import run_probes
from trainer.study.dataset import TASK

_PAPER = {"variant": "protocad", "reference": "paper"}
_EPS = {**_PAPER, "context.sinkhorn_eps": 0.0125}
#: Every fix together: the A/B's pick (results.md: the best health among the arms no worse than
#: the paper's on unseen image error, 3 seeds x 400 updates).
CHOSEN = {**_EPS, "context.projector_input": "h", "context.sinkhorn_over": "half_means",
          "context.cross_view_scale": 1.0, "context.both_views_train": True}
#: The study's arms (a variant and its config overrides over the small preset, world model only),
#: then the A/B's: the paper's settings with one fix at a time over DreamerPro's eps, and all.
ARMS: dict[str, dict[str, Any]] = {
    "dreamer": {"variant": "dreamer"},
    "protocad_paper": _PAPER,
    "protocad_chosen": CHOSEN,
    "true_context": {"variant": "dreamer_true_context"},
    "eps0125": _EPS,
    "eps0125_h": {**_EPS, "context.projector_input": "h"},
    "eps0125_halves": {**_EPS, "context.sinkhorn_over": "half_means"},
    "eps0125_views": {**_EPS, "context.cross_view_scale": 1.0, "context.both_views_train": True},
    "all_fixes": CHOSEN,
}
PLAN = dict(skip=25, window=25, context_steps=5, horizon=50, pixel_dim=32, seed=0)


def plan_runs(arms: Sequence[str], seeds: Sequence[int], shard: tuple[int, int] = (0, 1)) -> list[tuple[str, int]]:
    """(arm, seed) of every run, seed-major (a stopped grid has every arm's first seeds), the
    ones of shard (i, n): index i modulo n."""
    unknown = [a for a in arms if a not in ARMS]
    if unknown:
        raise ValueError(f"unknown arm(s) {unknown}; known: {list(ARMS)}")
    i, n = shard
    if not 0 <= i < n:
        raise ValueError(f"shard {i}/{n}: I must be in [0, N)")
    runs = [(a, int(seed)) for seed in seeds for a in arms]
    return [r for k, r in enumerate(runs) if k % n == i]


def arm_config(arm: str, seed: int) -> Config:
    """The arm's config: the small preset, world model only, the arm's variant and settings."""
    over = dict(ARMS[arm])
    variant, reference = over.pop("variant"), over.pop("reference", "dreamerpro")
    return make_config(TASK, preset="small", variant=variant, reference=reference,
                       **{"train.seed": seed, "train.world_model_only": True, **over})


def run_grid(data: Path, grid: Path, runs: Sequence[tuple[str, int]], updates: int) -> None:
    """Train and evaluate each (arm, seed) whose RUN/eval.json is not written yet."""
    for arm, seed in runs:
        out = Path(grid) / arm / f"seed_{seed}"
        if (out / "eval.json").exists():
            continue
        agent = train_one(Path(data), arm, seed, out, updates)
        doc = evaluate(agent, Path(data) / "eval")
        doc.update(arm=arm, seed=seed, updates=int(agent.counters()["updates"]), settings=ARMS[arm])
        atomic_write_text(out / "eval.json", json.dumps(doc, indent=1))
        print(f"[study] {arm} seed {seed}: {_one_line(doc)}", flush=True)


def train_one(data: Path, arm: str, seed: int, out: Path, updates: int) -> Any:
    """The arm's world model trained to `updates` in `out` (resumed from its checkpoint)."""
    cfg = arm_config(arm, seed)
    ds = MCAPDataset([data / "train"], seq_len=cfg.train.seq_len, seed=seed, cache_dir=data / "cache")
    if cfg.spec.reads_true_context:
        ds.check_true_context(TASK)
    ckpt = out / "checkpoints" / "latest.pt"
    trainer = (Trainer.from_checkpoint(ckpt, out, ds) if ckpt.exists()
               else Trainer(cfg, out, ds, log_every=25))
    if not ckpt.exists():
        runs.save_run_config(out, cfg)
    trainer.plan_prototype_freeze(updates)
    t0 = time.monotonic()
    trainer.train(updates, checkpoint_every=100)
    trainer.close()
    print(f"[study] {arm} seed {seed}: {trainer.updates} updates ({time.monotonic() - t0:.0f}s here)", flush=True)
    return trainer.agent


# ---------------------------------------------------------------------- evaluation
def _eval_batches(eval_dir: Path, seq_len: int = 2):
    """The evaluation episodes, grouped by split into batches of 8 of equal length: (split,
    contexts, batch with the normalized true context)."""
    ds = MCAPDataset([eval_dir], seq_len=seq_len, cache_dir=eval_dir.parent / "cache")
    params = get_task(TASK).params
    eps = sorted(ds.episodes(), key=lambda e: (e["source"], e["start"]))
    for split in ("test", "train"):
        mine = [e for e in eps if e["split"] == split]
        for k in range(0, len(mine), 8):
            wave = mine[k:k + 8]
            T = min(int(e["length"]) for e in wave)
            rows = [ds.episode_steps(e["store"], e["start"], T) for e in wave]
            batch = {key: np.stack([r[key] for r in rows]) for key in ("image", "action", "reward", "discount", "is_first")}
            batch["action"] = batch["action"].astype(np.float32)
            ctx = [{p: float(e["context"][p]) for p in params} for e in wave]
            values = np.array([[c[p] for p in params] for c in ctx])
            batch["context"] = np.repeat(normalized_log_context(values, TASK)[:, None], T, 1).astype(np.float32)
            yield split, ctx, batch


def evaluate(agent: Any, eval_dir: Path) -> dict[str, Any]:
    """Open-loop errors, probes and the context module's health of `agent` on the evaluation set."""
    plan = Plan(steps=150, **PLAN)
    projection = pixel_projection(plan.pixel_dim, plan.seed)
    out = Collected()
    health: list[dict[str, float]] = []
    for split, ctxs, batch in _eval_batches(eval_dir):
        if not agent.wm.true_context_dim:
            batch.pop("context")
        windows, _ = feature_windows(agent, batch, projection, plan)
        for c, feats in zip(ctxs, windows):
            out.contexts.append((split, c))
            for k, v in feats.items():
                out.rows.setdefault(k, []).append(v)
            out.context_ids.append(np.full(len(feats["h"]), len(out.contexts) - 1))
        add_open_loop(out.open_loop, split, open_loop_errors(agent, batch, plan))
        if agent.wm.context is not None and split == "test":
            health.append(health_of_states(agent, agent.embed_sequences(batch)["s"][:, plan.skip:]))
    probes, skipped = run_probes(out.windows(get_task(TASK).params), plan.seed)
    ol = {split: out.open_loop[split].mean() for split in ("test", "train")}
    return {"open_loop": ol, "probes": probes, "skipped": skipped,
            "health": {k: float(np.mean([h[k] for h in health])) for k in health[0]} if health else None}


def _one_line(doc: Mapping[str, Any]) -> str:
    ol = doc["open_loop"]["test"]
    r2 = doc["probes"].get("test_grid", {}).get("log_m", {})
    best = max(((k, v["r2"]) for k, v in r2.items() if k not in ("pixels", "heavy")), key=lambda x: x[1], default=None)
    h = doc.get("health") or {}
    return (f"unseen image MSE (h 1-50) {np.mean(ol['image_mse']):.5f}, reward err {np.mean(ol['reward_abs_err']):.3f}; "
            f"log m R2 {best}; proj_cosine {h.get('proj_cosine', float('nan')):.2f}")


