#!/usr/bin/env python3
"""The GPU campaign: one prepared script for a lent GPU machine (1 GPU, 16 cores, 15 minutes of
device time per task, start-up included; at most 8 files come back, 2 folders deep), so its
default deadline is 540 s and everything it writes is packed into $OUT/campaign.tar.gz beside
$OUT/campaign.json.

    OUT=/tmp/out python scripts/gpu_campaign.py --gl-debs .gl --site-archive .gpu/site.tar.xz \\
        --ament-prefix .gpu/prefix                           # on the GPU machine
    OUT=/tmp/out python scripts/gpu_campaign.py --tiny       # the same steps on CPU, minutes

Steps, each with its own time limit inside --deadline:
  1. preflight: the carried EGL libraries unpacked (--gl-debs: Debian .debs, as the device
     tool's notes say), then torch sees CUDA (not with --tiny) and MuJoCo renders one frame
     with MUJOCO_GL=egl. Anything missing stops the campaign here, with what was missing.
  2. s/update of protocad and dreamer at the small and paper presets, 1, 4 and 8 processes at
     once (scripts/bench_train.py --concurrent), and env steps/s with 16 env workers
     (scripts/bench_envs.py).
  3. As many paired walker_walk runs of the comparison's protocol (msgs_docs/results.md, issue
     42: small preset, fast look, reference=dreamerv2, 30k env steps, C = 100, prototypes
     trained, final evaluation on every unseen and training context) as the time left allows:
     protocad and dreamer x --seeds side by side on the GPU (protocad-compare), stopped by their
     wall budget, then results.json and the plot.
  4. campaign.tar.gz: every log, results.json, the plot and each run's run.json, eval/ and
     online.log (checkpoints, bags and caches left out unless --keep-runs).

The GPU machine has no ROS: this path imports no rclpy. Its Python packages come from the
working tree (--site-archive from scripts/gpu_pack.sh) and message definitions from
--ament-prefix (share/<pkg>/msg/*.msg); see msgs_docs/training.md.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: the comparison's protocol (msgs_docs/results.md, "ProtoCAD vs Dreamer, paired")
PAIRED_PROTOCOL = ["--preset", "small", "--seq-len", "50", "--precision", "auto", "--set", "reference=dreamerv2",
                   "--eval-every", "5000", "--eval-episodes", "2", "--eval-max-contexts", "8",
                   "--final-episodes", "5", "--final-train-contexts", "--checkpoint-every", "500"]
TINY_PROTOCOL = ["--preset", "small", "--time-limit", "200", "--prefill-episodes", "1",
                 "--updates-per-episode", "2", "--batch-size", "4", "--seq-len", "16", "--eval-every", "200",
                 "--eval-episodes", "1", "--eval-contexts", "m=0.2", "m=1.8", "--final-episodes", "1",
                 "--final-train-contexts"]
#: a frame through EGL: what the env workers need, checked before any minute is spent on them
RENDER_PROBE = ("from sim_bridge.sim.envs import ContextDMCEnv; e = ContextDMCEnv('walker_walk'); "
                "o = e.reset(); print('rendered', o.image.shape, 'mean', float(o.image.mean())); e.close()")
CUDA_PROBE = ("import os, torch; from protocad_ros.model.precision import cpu_capability; "
              "print('torch', torch.__version__, 'cuda', torch.version.cuda); "
              "print('cores', os.cpu_count(), 'CPU capability', cpu_capability()); "
              "[print('gpu', i, torch.cuda.get_device_name(i), "
              "round(torch.cuda.get_device_properties(i).total_memory / 2**30, 1), 'GiB') "
              "for i in range(torch.cuda.device_count())]; "
              "import sys; sys.exit(0 if torch.cuda.is_available() or os.environ.get('CAMPAIGN_CPU') else 3)")


def step(name: str, cmd: list[str], out: Path, timeout: float, env: dict) -> dict:
    """Run one step with a hard timeout, its output to OUT/logs/NAME.txt and its tail echoed."""
    t0 = time.monotonic()
    log = out / "logs" / f"{name}.txt"
    log.parent.mkdir(parents=True, exist_ok=True)
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
    return {"step": name, "rc": rc, "seconds": round(dt, 1), "log": f"logs/{log.name}"}


def unpack_gl(debs: Path) -> list[str]:
    """The carried EGL/GL .debs unpacked over / (the device tool's recipe), then ldconfig."""
    done = []
    for deb in sorted(debs.glob("*.deb")):
        subprocess.run(["dpkg", "-x", str(deb), "/"], check=True)
        done.append(deb.name)
    if done:
        subprocess.run(["ldconfig"], check=False)
    return done


def build_env(a: argparse.Namespace) -> dict:
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    env["PYOPENGL_PLATFORM"] = env.get("PYOPENGL_PLATFORM", env["MUJOCO_GL"])
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [a.site, str(ROOT), os.environ.get("PYTHONPATH")]))
    if a.ament_prefix:
        env["AMENT_PREFIX_PATH"] = os.pathsep.join(filter(None, [str(Path(a.ament_prefix).resolve()),
                                                                 os.environ.get("AMENT_PREFIX_PATH")]))
    if a.tiny:
        env["CAMPAIGN_CPU"] = "1"
    return env


def benchmarks(a: argparse.Namespace, out: Path, env: dict, left) -> list[dict]:
    """s/update at both presets and 1/4/8 processes at once, then env steps/s at 16 workers."""
    py, device = sys.executable, "cpu" if a.tiny else "cuda"
    steps = []
    for n in ([1] if a.tiny else [1, 4, 8]):
        bench = [py, "scripts/bench_train.py", "--device", device, "--variants", "protocad", "dreamer",
                 "--concurrent", str(n), "--json", str(out / "logs" / f"bench_train_x{n}.json")]
        # tiny: that each step runs, not what it measures (a 4 x 16 batch: seconds on any CPU)
        bench += (["--presets", "small", "--updates", "1", "--warmup", "0", "--threads", "1",
                   "--set", "train.batch_size=4", "--set", "train.seq_len=16"] if a.tiny else
                  ["--presets", "small", "paper", "--updates", "3", "--warmup", "1", "--precision", "auto",
                   "--threads", str(max(1, 16 // n))])
        steps.append(step(f"bench_train_x{n}", bench, out, min(120 if a.tiny else 75, left() - 60), env))
    envs = [py, "scripts/bench_envs.py", "--tasks", "walker_walk", "--steps", "100" if a.tiny else "400",
            "--workers", "0" if a.tiny else "16"]
    steps.append(step("bench_envs", envs, out, min(90, left() - 60), env))
    return steps


def paired_runs(a: argparse.Namespace, out: Path, env: dict, left) -> dict:
    budget = max(30.0, left() - a.final_reserve)
    task = "pendulum_swingup" if a.tiny else "walker_walk"
    compare = [sys.executable, "-m", "trainer.research.compare", "--tasks", task, "--variants", "protocad",
               "dreamer", "--seeds", *map(str, a.seeds), "--env-steps", "400" if a.tiny else "30000",
               "--wall-budget", f"{budget:.0f}", "--jobs", str(a.jobs), "--threads", "1",
               "--devices", "cpu" if a.tiny else "cuda", "--out", str(out / "compare"), "--status-every", "60",
               "--random-baseline", "--", *(TINY_PROTOCOL if a.tiny else PAIRED_PROTOCOL),
               # the final evaluations render on the CPU cores: share them out between the runs
               "--eval-workers", "0" if a.tiny else str(max(1, 15 // (2 * len(a.seeds))))]
    return step("compare", compare, out, left() - 20, env)


def pack(out: Path, keep_runs: bool) -> Path:
    """Everything but checkpoints, bags and caches (unless keep_runs) into one tar in `out`, and
    nothing else left there: the device returns few files, and only 2 folders deep."""
    skip = set() if keep_runs else {"checkpoints", "bags", "cache"}
    target = out / "campaign.tar.gz"
    with tarfile.open(target, "w:gz") as tar:
        for path in sorted(out.rglob("*")):
            rel = path.relative_to(out)
            if path.is_file() and path != target and not skip & set(rel.parts):
                tar.add(path, arcname=str(rel))
    for path in out.iterdir():
        if path != target:
            shutil.rmtree(path) if path.is_dir() else path.unlink()
    return target


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog=__doc__.split("\n\n", 1)[1])
    ap.add_argument("--out", default=os.environ.get("OUT"), help="output directory (default $OUT)")
    ap.add_argument("--deadline", type=float, default=540.0, help="seconds for everything")
    ap.add_argument("--seeds", nargs="+", type=int, default=[5],
                    help="paired seeds to run (default one pair, seed 5: the CPU grid has 0-4). A "
                         "run's final evaluation is 89 contexts x 5 episodes, about 220k agent steps "
                         "rendered on the CPU cores, so by estimate one pair fits the window; give the "
                         "next seeds to the next window")
    ap.add_argument("--jobs", type=int, default=16, help="runs at once (all of them by default)")
    ap.add_argument("--final-reserve", type=float, default=120.0,
                    help="seconds kept for the final evaluations, the report and the tar")
    ap.add_argument("--tiny", action="store_true",
                    help="CPU dry run: pendulum_swingup, small preset, a few hundred env steps, one "
                         "seed pair, no CUDA needed")
    ap.add_argument("--gl-debs", type=Path, default=None,
                    help="folder of carried EGL/GL .debs to unpack over / first (the device tool's .gl)")
    ap.add_argument("--site-archive", default=None,
                    help="a .tar.xz made by scripts/gpu_pack.sh: extracted and put first on sys.path")
    ap.add_argument("--ament-prefix", default=None, help="prefix holding share/<pkg>/msg/*.msg")
    ap.add_argument("--keep-runs", action="store_true", help="pack checkpoints, bags and caches too")
    a = ap.parse_args(argv)
    if not a.out:
        ap.error("--out (or $OUT) is required")
    a.site = None
    if a.site_archive:
        tmp = Path(tempfile.mkdtemp(prefix="protocad-site-"))
        with tarfile.open(a.site_archive) as tar:
            tar.extractall(tmp, filter="data")
        a.site = str(tmp / "site")
    if a.tiny:
        a.seeds = a.seeds[:1]
    return a


def main(argv=None) -> int:
    a = parse_args(argv)
    t_start = time.monotonic()
    left = lambda: a.deadline - (time.monotonic() - t_start)  # noqa: E731
    out = Path(a.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    unpacked = unpack_gl(a.gl_debs) if a.gl_debs else []
    env = build_env(a)
    steps = [step("preflight_cuda", [sys.executable, "-c", CUDA_PROBE], out, min(60, left()), env),
             step("preflight_egl", [sys.executable, "-c", RENDER_PROBE], out, min(60, left()), env)]
    ready = all(s["rc"] == 0 for s in steps)
    if ready:
        steps += benchmarks(a, out, env, left)
        steps.append(paired_runs(a, out, env, left))
    else:
        print("[gpu-campaign] preflight failed: " + ", ".join(s["step"] for s in steps if s["rc"])
              + f" (see {out / 'logs'}); nothing else was run", flush=True)
    summary = {"steps": steps, "seconds": round(time.monotonic() - t_start, 1), "tiny": a.tiny,
               "deadline": a.deadline, "gl_debs_unpacked": unpacked, "preflight_ok": ready}
    summary["tar"] = pack(out, a.keep_runs).name
    (out / "campaign.json").write_text(json.dumps(summary, indent=1) + "\n")
    print(f"[gpu-campaign] done in {summary['seconds']:.0f} s; {out / summary['tar']} and campaign.json",
          flush=True)
    return 0 if ready and all(s["rc"] == 0 for s in steps) else 1


if __name__ == "__main__":
    sys.exit(main())
