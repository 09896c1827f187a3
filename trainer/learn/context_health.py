"""When ProtoCAD's context module counts as collapsed, and its health on given states.

The figures are protocad_ros.model.prototypes.context_health's; msgs_docs/training.md ("Context
health") says what each one means and why these thresholds.
"""
from __future__ import annotations

import math
from typing import Any, Mapping

import torch

#: Target projections in a cone: their mean pairwise cosine at least this (the collapsed walker
#: policy of 2026-12 read 0.83; a module that codes B contexts in B directions reads ~1/B).
COLLAPSE_PROJ_COSINE = 0.8
#: Predictions and targets both near uniform: entropy at least this share of ln K, i.e. each
#: step spread over K^0.8 prototypes or more (40 of 100), where a code needs one or a few.
COLLAPSE_ENTROPY_SHARE = 0.8
#: ... and either for this many updates in a row: every setting passes through a cone while
#: its projector and prototypes find their way (updates 25-125 of the walker A/B, results.md);
#: the paper's settings stay there, the healthy ones leave it within 100 updates.
COLLAPSE_PERSIST_UPDATES = 150


def collapse_reason(metrics: Mapping[str, float], num_prototypes: int) -> str | None:
    """Why the health figures say the module has collapsed to the trivial solution of its SwAV
    loss, or None. Figures missing from `metrics` count as healthy."""
    reasons = []
    cos = metrics.get("proj_cosine")
    if cos is not None and cos >= COLLAPSE_PROJ_COSINE:
        reasons.append(f"projections in a cone (mean pairwise cosine {cos:.2f} >= {COLLAPSE_PROJ_COSINE})")
    ln_k = math.log(max(int(num_prototypes), 2))
    pred, target = metrics.get("swav_pred_entropy"), metrics.get("swav_target_entropy")
    if pred is not None and target is not None and min(pred, target) >= COLLAPSE_ENTROPY_SHARE * ln_k:
        reasons.append(f"predictions and targets near uniform (entropy {pred:.2f} and {target:.2f} "
                       f"of ln K = {ln_k:.2f})")
    return "; ".join(reasons) or None


class CollapseWatch:
    """Reads the logged rows of a run and says once when its context module has collapsed: the
    collapse_reason condition held on every row for COLLAPSE_PERSIST_UPDATES updates."""

    def __init__(self, num_prototypes: int, persist_updates: int = COLLAPSE_PERSIST_UPDATES):
        self.num_prototypes, self.persist_updates = int(num_prototypes), int(persist_updates)
        self.since: int | None = None   # first logged update of the current collapse
        self.warned = False

    def update(self, update: int, metrics: Mapping[str, float]) -> str | None:
        """The warning line (once per run), or None; rows without the figures are left alone."""
        if self.warned or "proj_cosine" not in metrics:
            return None
        reason = collapse_reason(metrics, self.num_prototypes)
        if not reason:
            self.since = None
            return None
        self.since = update if self.since is None else self.since
        if update - self.since < self.persist_updates:
            return None
        self.warned = True
        return (f"WARNING: the context module has collapsed (since update {self.since}, now {update}): "
                f"{reason}; its features carry no context (msgs_docs/training.md#context-health)")


def health_of_states(agent: Any, s: Any) -> dict[str, float] | None:
    """The context module's health on posterior states s (B, M, S; numpy or torch) without
    augmentation: the online and target projections of the same states, Sinkhorn targets as
    training computes them (None for a variant without the module)."""
    ctx = agent.wm.context
    if ctx is None:
        return None
    s = torch.as_tensor(s)
    keep = ctx.kept_steps(s.shape[1])
    first, second = ctx.tc_pairs(keep.stop)
    with torch.no_grad(), torch.autocast(device_type=s.device.type, enabled=False):
        x = agent.wm.context_input(s[:, keep].float().to(agent.device))
        u = ctx.project(x)
        w = torch.softmax(ctx.logits(u), dim=-1)
        ubar = ctx.target_projections(x)
        wbar = ctx.targets(ubar, (first - keep.start, second - keep.start))
        return {k: float(v) for k, v in ctx.health(u, w, ubar, wbar).items()}
