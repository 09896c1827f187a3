"""The loop's evaluations: at the start, the --init-policy policy against the random one on
unseen contexts through the ROS nodes; at the end, the trained checkpoint against the random
policy on the test contexts (in-process, deterministic) and the rerun recording of the context
view."""
from __future__ import annotations

import dataclasses
import os
from pathlib import Path

from trainer import console, runs
from trainer.launch.loop_rundir import LoopRunDir
from trainer.launch.ros_evaluate import evaluate_through_ros
from trainer.learn.evaluate import EvalPlan, RosPlan, evaluate_checkpoint, format_table


def policy_vs_random(rundir: LoopRunDir, domain_id: int, device: str, stop: console.StopFlag) -> None:
    """The starting policy and the random one on the same unseen contexts, through ROS."""
    n, cfg = rundir.a.start_eval_episodes, rundir.cfg
    print(f"[loop] {rundir.init_policy} against the random policy on {n} unseen-context episode(s), "
          "through the ROS nodes (sim bridge + policy node / random actor + recorder)", flush=True)
    plan = RosPlan(split="test", total_episodes=n, seed=cfg.train.seed + 11, domain_id=domain_id,
                   episode_length=rundir.a.episode_length)
    out_dir = rundir.path / "eval_start"
    res = evaluate_through_ros(str(rundir.init_policy), dataclasses.replace(plan, device=device), task=cfg.task,
                               out_dir=out_dir)
    if stop.stop:
        return
    rnd = evaluate_through_ros(None, plan, task=cfg.task, out_dir=out_dir)
    print(format_table(res, rnd), flush=True)
    runs.atomic_write_json(rundir.path / "eval" / "start.json", {**res.to_dict(), "random": rnd.to_dict()})


def final_evaluation(rundir: LoopRunDir, updates: int, device: str, stop: console.StopFlag) -> Path | None:
    """The trained checkpoint and the random policy on the test contexts (in-process): the table,
    and eval/test_UPDATES.json; None when stopped."""
    a = rundir.a
    ckpt = runs.checkpoint_path(rundir.path)
    print(f"[loop] evaluating {ckpt} on the test contexts ({a.eval_episodes} episode(s) each, "
          "in-process, deterministic)", flush=True)
    plan = EvalPlan(episodes=a.eval_episodes, max_contexts=a.eval_max_contexts, seed=rundir.cfg.train.seed + 7,
                    device=device, time_limit=a.episode_length * rundir.cfg.train.action_repeat,
                    progress=False if a.no_progress else None)
    res = evaluate_checkpoint(ckpt, plan, stop=stop)
    if stop.stop:
        return None
    # The uniform random policy on the same contexts, episodes and seeds: the reference
    # point a score needs (the demo's few hundred updates stay close to it).
    same = dataclasses.replace(plan, contexts=[r.context for r in res.per_context], max_contexts=0)
    rnd = evaluate_checkpoint(None, dataclasses.replace(same, device="cpu"), task=rundir.cfg.task, stop=stop)
    if stop.stop:
        return None
    # The policy the run started from (--init-policy, the demo's shipped one) on the same
    # contexts, episodes and seeds: whether training helped, side by side.
    start = None
    if rundir.init_policy:
        start = evaluate_checkpoint(rundir.init_policy, same, stop=stop)
        if stop.stop:
            return None
    print(format_table(res, start, rnd), flush=True)
    if a.demo and not rundir.init_policy:
        print("[loop] what to expect: the demo trains a few hundred updates, far from the "
              "~6k Pendulum Swingup needs before DreamerV2's own seeds show learning, so its "
              "policy scores near the random one; a policy that learned: README 'Results'.",
              flush=True)
    out = rundir.path / "eval" / f"test_{updates:06d}.json"
    runs.atomic_write_json(out, {**res.to_dict(), "random": rnd.to_dict(),
                                 **({"start_policy": start.to_dict()} if start is not None else {})})
    return out


def context_recording(rundir: LoopRunDir, device: str) -> Path | None:
    """The rerun recording of the context view (trainer.viz.visualize), RUN_DIR/contexts.rrd;
    None when it cannot be written (the run's results stand without it)."""
    out = rundir.path / "contexts.rrd"
    try:
        from trainer.viz.visualize import write_context_recording
    except ImportError as exc:
        print(f"[loop] no rerun context recording: trainer.viz.visualize is not available ({exc})", flush=True)
        return None
    old_cache = os.environ.get("PROTOCAD_CACHE_DIR")
    os.environ["PROTOCAD_CACHE_DIR"] = str(rundir.ledger.ds.cache_dir)  # reuse this run's dataset cache
    print(f"[loop] writing the rerun context recording {out}", flush=True)
    try:
        # The contexts the bags lack, as many per split as the final evaluation had (the
        # demo: 8 of walker's 25 + 64 instead of all: each is an env built and run in-process).
        write_context_recording(runs.checkpoint_path(rundir.path), logs=[rundir.bags_dir], out_rrd=out,
                                device=device, progress=False, max_contexts=rundir.a.eval_max_contexts)
    except Exception as exc:  # noqa: BLE001 - the run's results stand without the picture
        print(f"[loop] rerun context recording failed: {type(exc).__name__}: {exc}", flush=True)
        return None
    finally:
        if old_cache is None:
            os.environ.pop("PROTOCAD_CACHE_DIR", None)
        else:
            os.environ["PROTOCAD_CACHE_DIR"] = old_cache
    return out
