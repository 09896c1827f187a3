#!/usr/bin/env python3
"""The GPU campaign: one prepared script for a borrowed GPU machine (1 GPU, 16 cores, about 9
minutes of it), everything it measures written under $OUT.

    OUT=/tmp/out python scripts/gpu_campaign.py                 # on the GPU machine
    OUT=/tmp/out python scripts/gpu_campaign.py --tiny          # the same steps on CPU, seconds

Steps, each with its own time limit so the whole stays inside --deadline (default 540 s):
  1. the machine: GPU name and memory, torch, CUDA, CPU capability, cores -> machine.txt
  2. s/update at paper sizes (scripts/bench_train.py, protocad and dreamer) -> bench_train.txt
  3. env steps/s of the suite (scripts/bench_envs.py, fast rendering) -> bench_envs.txt
  4. protocad-compare: protocad and dreamer x --seeds on --tasks (walker_walk and cheetah_run,
     the tasks that learn first on DreamerV2's published curves), with the anchor (dreamer on the
     unrandomized task, --anchor-seeds), paper preset, the protocol of the CPU grids (issue 25:
     reference=dreamerv2 for both variants, 100 updates of 50 x 50 per 1,000 env steps), all
     runs side by side on the GPU (--jobs), stopped by their wall budget (what is left of the
     deadline minus the final evaluations), then results.json, curves.png, curves.rrd -> compare/
The runs' logs travel back with them (compare/TASK/VARIANT/seedS/online.log, eval/, run.json);
checkpoints and bags are deleted at the end unless --keep-runs (they do not fit the way back).

The GPU machine has no ROS: this path imports no rclpy. Its Python packages come from the
working tree (`--site DIR` is put first on sys.path of every step; what to copy along:
scripts/gpu_pack.sh, msgs_docs/training.md) and message definitions from `--ament-prefix DIR` (share/<pkg>/msg/*.msg).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def step(name: str, cmd: list[str], out: Path, timeout: float, env: dict) -> dict:
    """Run one step with a hard timeout, its output to OUT/NAME.txt and echoed at the end."""
    t0 = time.monotonic()
    log = out / f"{name}.txt"
    print(f"[gpu-campaign] {name}: {' '.join(cmd)} (limit {timeout:.0f} s)", flush=True)
    with open(log, "w") as f:
        try:
            rc = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT, cwd=ROOT, env=env,
                                timeout=max(1.0, timeout)).returncode
        except subprocess.TimeoutExpired:
            rc = 124
    dt = time.monotonic() - t0
    tail = log.read_text(errors="replace").splitlines()[-25:]
    print("\n".join(f"  {line}" for line in tail), flush=True)
    print(f"[gpu-campaign] {name}: exit {rc} after {dt:.0f} s", flush=True)
    return {"step": name, "rc": rc, "seconds": round(dt, 1), "log": log.name}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog=__doc__.split("\n\n", 1)[1])
    ap.add_argument("--out", default=os.environ.get("OUT"), help="output directory (default $OUT)")
    ap.add_argument("--deadline", type=float, default=540.0, help="seconds for everything")
    ap.add_argument("--tasks", nargs="+", default=["walker_walk", "cheetah_run"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--anchor-seeds", nargs="*", type=int, default=[0, 1],
                    help="seeds of the anchor (dreamer on the unrandomized task) per task")
    ap.add_argument("--jobs", type=int, default=16, help="runs at once (all of them by default)")
    ap.add_argument("--final-reserve", type=float, default=90.0,
                    help="seconds kept for the final evaluations and the report")
    ap.add_argument("--tiny", action="store_true",
                    help="CPU dry run: pendulum_swingup, small preset, a few hundred env steps, one "
                         "seed pair, no anchor")
    ap.add_argument("--site", default=None, help="extra Python packages directory (first on sys.path)")
    ap.add_argument("--site-archive", default=None,
                    help="a .tar.xz made by scripts/gpu_pack.sh: extracted to a temporary directory "
                         "and used as --site")
    ap.add_argument("--ament-prefix", default=None, help="prefix holding share/<pkg>/msg/*.msg")
    ap.add_argument("--keep-runs", action="store_true", help="keep checkpoints, bags and caches")
    a = ap.parse_args(argv)
    if not a.out:
        ap.error("--out (or $OUT) is required")
    t_start = time.monotonic()
    if a.site_archive:
        import tarfile
        import tempfile

        tmp = Path(tempfile.mkdtemp(prefix="protocad-site-"))
        with tarfile.open(a.site_archive) as tar:
            tar.extractall(tmp, filter="data")
        a.site = str(tmp / "site")
    out = Path(a.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    env["PYOPENGL_PLATFORM"] = env.get("PYOPENGL_PLATFORM", env["MUJOCO_GL"])
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [a.site, str(ROOT), os.environ.get("PYTHONPATH")]))
    if a.ament_prefix:
        env["AMENT_PREFIX_PATH"] = os.pathsep.join(filter(None, [str(Path(a.ament_prefix).resolve()),
                                                                 os.environ.get("AMENT_PREFIX_PATH")]))
    py = sys.executable
    device = "cpu" if a.tiny else "cuda"
    left = lambda: a.deadline - (time.monotonic() - t_start)  # noqa: E731
    steps = []

    probe = ("import os, torch; from protocad_ros.model.precision import cpu_capability; "
             "print('torch', torch.__version__, 'cuda', torch.version.cuda); "
             "print('cores', os.cpu_count(), 'CPU capability', cpu_capability()); "
             "[print('gpu', i, torch.cuda.get_device_name(i), "
             "round(torch.cuda.get_device_properties(i).total_memory / 2**30, 1), 'GiB', "
             "'bf16' if torch.cuda.is_bf16_supported() else 'no bf16') "
             "for i in range(torch.cuda.device_count())]; "
             "print('no GPU' if not torch.cuda.is_available() else '')")
    steps.append(step("machine", [py, "-c", probe], out, min(60, left()), env))

    bench = [py, "scripts/bench_train.py", "--device", device, "--variants", "protocad", "dreamer",
             "--json", str(out / "bench_train.json")]
    bench += (["--presets", "small", "--updates", "1", "--warmup", "0", "--threads", "1"] if a.tiny else
              ["--presets", "paper", "--updates", "5", "--warmup", "2", "--precision", "auto", "float32"])
    steps.append(step("bench_train", bench, out, min(150 if not a.tiny else 120, left() - 60), env))

    if a.tiny:
        a.tasks, a.seeds, a.anchor_seeds = ["pendulum_swingup"], a.seeds[:1], []
    envs = [py, "scripts/bench_envs.py", "--tasks", *a.tasks, "--steps", "100" if a.tiny else "500",
            "--workers", "0" if a.tiny else "8"]
    steps.append(step("bench_envs", envs, out, min(90, left() - 60), env))

    budget = max(30.0, left() - a.final_reserve)
    compare = [py, "-m", "trainer.research.compare", "--tasks", *a.tasks, "--variants", "protocad", "dreamer",
               "--seeds", *map(str, a.seeds), "--anchor-seeds", *map(str, a.anchor_seeds),
               "--env-steps", "400" if a.tiny else "2000000",
               "--wall-budget", f"{budget:.0f}", "--jobs", str(a.jobs), "--threads", "1",
               "--devices", device, "--out", str(out / "compare"), "--status-every", "60", "--"]
    if a.tiny:
        compare += ["--preset", "small", "--time-limit", "200", "--prefill-episodes", "1",
                    "--updates-per-episode", "2", "--batch-size", "4", "--seq-len", "16",
                    "--eval-every", "200", "--eval-episodes", "1", "--eval-contexts", "m=0.2", "m=1.8",
                    "--set", "context.freeze_prototypes_updates=2"]
    else:
        # Paper protocol inside a few minutes: eval every 10k env steps on at most 8 test
        # contexts (2 episodes), the final one on all of them; prototypes frozen for the first
        # 5% of a 2M-step run's updates would be 10k, far beyond this budget: 200 here.
        compare += ["--preset", "paper", "--eval-every", "10000", "--eval-episodes", "2",
                    "--eval-max-contexts", "8", "--final-episodes", "2", "--checkpoint-every", "500",
                    "--set", "context.freeze_prototypes_updates=200", "--set", "reference=dreamerv2"]
    steps.append(step("compare", compare, out, left() - 15, env))

    if not a.keep_runs:
        for d in (out / "compare").glob("*/*/seed*"):
            for sub in ("checkpoints", "bags", "cache"):
                shutil.rmtree(d / sub, ignore_errors=True)
    summary = {"steps": steps, "seconds": round(time.monotonic() - t_start, 1), "tiny": a.tiny,
               "device": device, "deadline": a.deadline}
    (out / "campaign.json").write_text(json.dumps(summary, indent=1) + "\n")
    print(f"[gpu-campaign] done in {summary['seconds']:.0f} s; results under {out}", flush=True)
    return 0 if all(s["rc"] == 0 for s in steps) else 1


if __name__ == "__main__":
    sys.exit(main())
