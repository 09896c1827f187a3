#!/usr/bin/env python3
"""Benchmark: seconds per training update (world model + behaviour) and peak memory.

Every configuration runs in a fresh subprocess, so its peak RSS (resource.getrusage
ru_maxrss, which includes the Python/torch baseline) is its own; on CUDA the table also shows
torch.cuda.max_memory_allocated. Batches are random uint8 frames of the configured size (the
cost of an update does not depend on pixel values); the first `--warmup` updates (oneDNN/cuDNN
kernel selection, allocator growth) are not timed but do count for peak memory.

    python scripts/bench_train.py                       # paper + small presets, CPU
    python scripts/bench_train.py --dreamerv3-sizes     # + dreamer at dreamerv3-torch sizes
    python scripts/bench_train.py --device cuda --dreamerv3-sizes
    python scripts/bench_train.py --only-dreamerv3 --profile   # + top ops from torch.profiler
    python scripts/bench_train.py --only-dreamerv3 --precision float32 --flops   # + FLOPs, roof
    python scripts/bench_train.py --presets small --variants dreamer --baseline 3ee8463
                                   # before (that commit) and after (this tree), row by row

Precision: `--precision auto` (default) times bfloat16 autocast only where the device has bf16
arithmetic (protocad_ros/model/precision.py) and float32 elsewhere; `--precision float32` runs float32
only, for every row (the --dreamerv3-sizes rows included). The CPU capability is printed first.

Before and after: `--baseline REV` times every configuration twice, interleaved, once with the
code of git revision REV (exported to a temporary directory) and once with this tree, and prints
the speed-up of each pair; the worker is this script either way, so only the code under test
differs (a baseline without trainer.torch_setup.retain_freed_memory runs glibc's default allocator).

Peer reference: NM512/dreamerv3-torch dmc_vision, timed side by side on the same machine
(`--peer-sec`, `--peer-gb`; the defaults are the quiet 2-core AVX2-only machine's 18.1 s and
5.37 GB). The target is half the peer's time and memory.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
PEER_V3 = {"sec": 18.1, "rss_gb": 5.37}  # dreamerv3-torch dmc_vision, quiet 2-core AVX2 machine


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


# ---- worker (one configuration, in its own process) ---------------------------------------------
def retain_freed_memory() -> bool:
    """What every training command does first: trainer.torch_setup's retain_freed_memory
    (trainer.runs' before that module was split; a baseline revision may predate both)."""
    try:
        from trainer import torch_setup as setup
    except ImportError:
        from trainer import runs as setup
    return getattr(setup, "retain_freed_memory", lambda: False)()


def worker(spec: dict) -> dict:
    # torch in the worker (--list and --help answer without it); the project's modules from
    # spec["root"], this tree or the --baseline revision's, so none of them at the top.
    import torch

    torch.set_num_threads(spec["threads"])
    sys.path.insert(0, spec.get("root", str(ROOT)))
    from protocad_ros.model.agent import Agent
    from protocad_ros.model.config import make_config

    retained = retain_freed_memory()

    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    overrides = dict(spec["overrides"])
    if spec.get("precision"):
        overrides["train.precision"] = spec["precision"]
    cfg = make_config(spec["task"], spec["preset"], spec["variant"], **overrides)
    A = 6
    agent = Agent(cfg, A, device=spec["device"])
    if spec.get("precision") and hasattr(agent, "use_precision"):   # the bench's own command line:
        agent.use_precision(spec["precision"])                    # kept even where bf16 is emulated
    B, T = cfg.train.batch_size, cfg.train.seq_len
    rng = np.random.default_rng(0)
    batch = {"image": rng.integers(0, 256, (B, T, 64, 64, 3), dtype=np.uint8),
             "action": rng.uniform(-1, 1, (B, T, A)).astype(np.float32),
             "reward": rng.uniform(0, 1, (B, T)).astype(np.float32),
             "discount": np.ones((B, T), np.float32), "is_first": np.zeros((B, T), bool)}
    batch["is_first"][:, 0] = True
    cuda = agent.device.type == "cuda"
    sync = torch.cuda.synchronize if cuda else (lambda: None)
    if cuda:
        torch.cuda.reset_peak_memory_stats()
    for _ in range(spec["warmup"]):
        agent.train_step(batch)
    sync()
    wm_t, beh_t, tot_t = [], [], []
    for _ in range(spec["updates"]):
        t0 = time.perf_counter()
        start, _ = agent.train_world_model(batch)
        sync()
        t1 = time.perf_counter()
        agent.train_behavior(start)
        agent.updates += 1
        del start
        sync()
        t2 = time.perf_counter()
        wm_t.append(t1 - t0)
        beh_t.append(t2 - t1)
        tot_t.append(t2 - t0)
    out = {
        "sec": float(np.mean(tot_t)), "sec_min": float(np.min(tot_t)),
        "wm_sec": float(np.mean(wm_t)), "beh_sec": float(np.mean(beh_t)),
        "rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e9,
        "rss_base_gb": rss0 * 1024 / 1e9,
        "params_m": sum(p.numel() for p in agent.parameters()) / 1e6,
        "batch": f"{B}x{T}", "horizon": cfg.behavior.horizon,
        "allocator": "retained" if retained else "default",
    }
    if cuda:
        out["cuda_gb"] = torch.cuda.max_memory_allocated() / 1e9
    if spec.get("flops"):
        out.update(count_flops(agent, batch))
        out["roof_gflops"] = gemm_roof(torch.float32 if spec.get("precision") != "bfloat16"
                                       else torch.bfloat16)
    if spec.get("profile"):
        from torch.profiler import ProfilerActivity, profile

        acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
        with profile(activities=acts) as prof:
            t0 = time.perf_counter()
            start, _ = agent.train_world_model(batch)
            sync()
            t1 = time.perf_counter()
            agent.train_behavior(start)
            sync()
            t2 = time.perf_counter()
        sort = "self_cuda_time_total" if cuda else "self_cpu_time_total"
        out["profile"] = (f"profiled update: world model {t1 - t0:.2f} s, behaviour "
                          f"{t2 - t1:.2f} s\n" + prof.key_averages().table(sort_by=sort,
                                                                            row_limit=20))
    return out


def count_flops(agent, batch) -> dict:
    """Matmul + convolution FLOPs of one update, forward and backward (torch's FlopCounterMode
    counts the ops that dominate: mm/addmm/bmm/convolution and their gradients)."""
    from torch.utils.flop_counter import FlopCounterMode

    wm = FlopCounterMode(display=False)
    with wm:
        start, _ = agent.train_world_model(batch)
    beh = FlopCounterMode(display=False)
    with beh:
        agent.train_behavior(start)
    return {"wm_gflop": wm.get_total_flops() / 1e9, "beh_gflop": beh.get_total_flops() / 1e9}


def gemm_roof(dtype, seconds: float = 2.0) -> float:
    """GFLOP/s of a large square matmul with this process's threads: the most these cores do
    with the library's best kernel, a roof no update of the same FLOPs can beat."""
    import torch

    a, b = torch.randn(2048, 2048, dtype=dtype), torch.randn(2048, 2048, dtype=dtype)
    for _ in range(2):
        a @ b
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        a @ b
        n += 1
    return 2 * 2048 ** 3 * n / (time.perf_counter() - t0) / 1e9


# ---- driver -------------------------------------------------------------------------------------
def run_spec(spec: dict, timeout: float, copies: int = 1) -> dict:
    """Time one configuration in `copies` worker processes at once (a grid's runs share the
    cores like this); the figures are the mean over the copies."""
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", json.dumps(spec)]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [spec.get("root", str(ROOT)),
                                                                      os.environ.get("PYTHONPATH")]))}
    procs = [subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
             for _ in range(copies)]
    outs = []
    try:
        for p in procs:
            out, err = p.communicate(timeout=timeout)
            if p.returncode != 0:
                return {"error": (err.strip().splitlines() or ["?"])[-1]}
            outs.append(json.loads(out.strip().splitlines()[-1]))
    except subprocess.TimeoutExpired:
        return {"error": f"timed out after {timeout:.0f} s"}
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    numbers = [k for k, v in outs[0].items() if isinstance(v, float)]
    return {**outs[0], **{k: sum(o[k] for o in outs) / len(outs) for k in numbers}}


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog=__doc__.split("\n\n", 1)[1])
    ap.add_argument("--device", default="cpu", help="cpu or cuda (default cpu)")
    ap.add_argument("--presets", nargs="+", default=["paper", "small"],
                    choices=["paper", "small"], help="presets to time (default both)")
    ap.add_argument("--variants", nargs="+", default=["protocad", "dreamer"],
                    help="variants to time at each preset (default protocad dreamer)")
    ap.add_argument("--precision", nargs="+", default=["auto"],
                    choices=["auto", "float32", "bfloat16"],
                    help="precisions of every row (auto: bfloat16 where the device has bf16 "
                         "arithmetic, else float32)")
    ap.add_argument("--peer-sec", type=float, default=None,
                    help="dreamerv3-torch s/update measured on this machine (default: the quiet "
                         "2-core AVX2 machine's 18.1, labelled as such)")
    ap.add_argument("--peer-gb", type=float, default=None,
                    help="dreamerv3-torch peak RSS (GB) measured on this machine (default 5.37, "
                         "the same other machine's)")
    ap.add_argument("--dreamerv3-sizes", action="store_true",
                    help="also time the dreamer variant at NM512/dreamerv3-torch dmc_vision "
                         "sizes (512 units, 32x32 discrete, CNN depth 32, batch 16x64, H 15), "
                         "in float32 and bfloat16 autocast")
    ap.add_argument("--only-dreamerv3", action="store_true",
                    help="only the --dreamerv3-sizes rows")
    ap.add_argument("--updates", type=int, default=3, help="timed updates per config")
    ap.add_argument("--warmup", type=int, default=1, help="untimed updates first")
    ap.add_argument("--threads", type=int, default=os.cpu_count(),
                    help="torch threads (default: all cores)")
    ap.add_argument("--task", default="cheetah_run", help="task (sets K; default cheetah_run)")
    ap.add_argument("--profile", action="store_true",
                    help="print the top ops of one profiled update per config")
    ap.add_argument("--flops", action="store_true",
                    help="also count one update's matmul/conv FLOPs (torch FlopCounterMode) and time a "
                         "2048^2 matmul: prints GFLOP/s reached and the fastest an update of those "
                         "FLOPs could be on these cores")
    ap.add_argument("--timeout", type=float, default=1800, help="seconds per config")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="config override for every row, as protocad-online's --set "
                         "(e.g. --set train.seq_len=50 --set reference=dreamerv2)")
    ap.add_argument("--concurrent", type=int, default=1, metavar="N",
                    help="time N copies of each configuration at once, as protocad-compare's "
                         "--jobs N runs share the cores (default 1)")
    ap.add_argument("--baseline", metavar="REV",
                    help="also time every configuration with the code of git revision REV, "
                         "interleaved with this tree's, and print each speed-up")
    ap.add_argument("--json", type=Path, help="also write the results here")
    ap.add_argument("--list", action="store_true", help="print the configurations it would time and exit")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    return ap


def print_row(spec: dict, r: dict, cuda: bool) -> None:
    """One configuration's line (and its FLOPs and profile, when measured)."""
    if "error" in r:
        print(f"{spec['name']:26} {spec['precision']:9} ERROR: {r['error']}")
        return
    line = (f"{spec['name']:26} {spec['precision']:9} {r['batch']:>6} {r['params_m']:6.1f}M "
            f"{r['sec']:9.3f} {r['sec_min']:6.2f} {r['wm_sec']:6.2f} {r['beh_sec']:6.2f} "
            f"{r['rss_gb']:7.2f}GB")
    if cuda:
        line += f" {r.get('cuda_gb', 0):7.2f}GB"
    print(line, flush=True)
    if "wm_gflop" in r:
        total = r["wm_gflop"] + r["beh_gflop"]
        print(f"{'':26} FLOPs per update {total:.0f} G (world model {r['wm_gflop']:.0f}, "
              f"behaviour {r['beh_gflop']:.0f}): {total / r['sec']:.0f} GFLOP/s reached; "
              f"matmul roof here {r['roof_gflops']:.0f} GFLOP/s -> no update of these FLOPs "
              f"under {total / r['roof_gflops']:.2f} s", flush=True)
    if r.get("profile"):
        print(r["profile"])


def export_revision(rev: str) -> Path:
    """The tree of git revision `rev` of this repository, in a fresh temporary directory."""
    out = Path(tempfile.mkdtemp(prefix="bench_train_baseline_"))
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", rev], capture_output=True)
    if archive.returncode != 0:
        shutil.rmtree(out, ignore_errors=True)
        raise SystemExit(f"--baseline {rev}: {archive.stderr.decode().strip()}")
    subprocess.run(["tar", "-x", "-C", str(out)], input=archive.stdout, check=True)
    return out


def print_speedups(results: list[dict]) -> None:
    """Each --baseline row against the row of this tree that follows it."""
    for base, new in zip(results, results[1:]):
        if base.get("baseline_of") != new["name"] or "error" in base or "error" in new:
            continue
        print(f"speed-up {new['name']} {new['precision']}: {base['sec'] / new['sec']:.2f}x "
              f"({base['sec']:.3f} -> {new['sec']:.3f} s/update; allocator {base['allocator']} "
              f"-> {new['allocator']})")


def compare_with_peer(results: list[dict], args) -> None:
    """The dreamerv3-sizes rows against dreamerv3-torch's time and memory (half of each: the target)."""
    v3 = [r for r in results if r.get("preset") == "dreamerv3_sizes" and "error" not in r]
    where = "measured on this machine"
    if args.peer_sec is None or args.peer_gb is None:
        where = "measured on another machine (quiet 2-core AVX2): time it here and pass --peer-sec/--peer-gb"
        args.peer_sec = args.peer_sec if args.peer_sec is not None else PEER_V3["sec"]
        args.peer_gb = args.peer_gb if args.peer_gb is not None else PEER_V3["rss_gb"]
    for r in v3:
        ok = r["sec"] <= args.peer_sec / 2 and r["rss_gb"] <= args.peer_gb / 2
        print(f"dreamerv3-sizes {r['precision']}: {r['sec'] / args.peer_sec:.2f}x the time, "
              f"{r['rss_gb'] / args.peer_gb:.2f}x the memory of dreamerv3-torch "
              f"({args.peer_sec} s, {args.peer_gb} GB, {where}): target "
              f"{'met' if ok else 'NOT met'} (<= {args.peer_sec / 2:.2f} s, "
              f"<= {args.peer_gb / 2:.2f} GB)")


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.worker:
        print(json.dumps(worker(json.loads(args.worker))))
        return 0

    def _interrupt(signum, frame):  # SIGTERM -> KeyboardInterrupt, so subprocess.run kills
        raise KeyboardInterrupt  # the running worker instead of orphaning it

    signal.signal(signal.SIGTERM, _interrupt)
    from protocad_ros.model.precision import cpu_capability, resolve_precision

    precisions = list(dict.fromkeys(resolve_precision(p, args.device, explicit=True).precision
                                    for p in args.precision))
    specs = []
    common = {"task": args.task, "device": args.device, "threads": args.threads,
              "updates": args.updates, "warmup": args.warmup, "profile": args.profile,
              "flops": args.flops}
    overrides = dict(kv.split("=", 1) for kv in args.set)
    if not args.only_dreamerv3:
        for preset in args.presets:
            for variant in args.variants:
                for prec in precisions:
                    specs.append({**common, "name": f"{preset}/{variant}", "preset": preset,
                                  "variant": variant, "precision": prec, "overrides": overrides})
    if args.dreamerv3_sizes or args.only_dreamerv3:
        for prec in precisions:
            specs.append({**common, "name": "dreamerv3-sizes/dreamer", "preset": "dreamerv3_sizes",
                          "variant": "dreamer", "precision": prec, "overrides": overrides})

    baseline_dir = None
    if args.baseline:
        baseline_dir = export_revision(args.baseline)
        specs = [row for spec in specs for row in (
            {**spec, "name": f"{spec['name']}@{args.baseline[:10]}", "root": str(baseline_dir),
             "baseline_of": spec["name"]}, spec)]
    if args.list:
        for spec in specs:
            print(f"{spec['name']} {spec['precision']}")
        return 0
    import torch
    print(f"machine: {_cpu_model()}, {os.cpu_count()} cores, torch {torch.__version__}, "
          f"threads {args.threads}, device {args.device}"
          + (f" ({torch.cuda.get_device_name()})" if args.device.startswith("cuda")
             and torch.cuda.is_available() else ""))
    print(f"CPU capability: {cpu_capability()}; precision(s): {', '.join(precisions)}"
          f" (asked: {' '.join(args.precision)})")
    load = os.getloadavg()
    if args.concurrent > 1:
        print(f"{args.concurrent} copies of each configuration at once; figures: their mean")
    print(f"load average before: {' '.join(f'{x:.2f}' for x in load)}")
    if args.device == "cpu" and load[0] + args.threads > (os.cpu_count() or 1) + 0.5:
        print(f"WARNING: the machine is busy (load {load[0]:.1f} on {os.cpu_count()} cores): the "
              f"figures below are slower than on an idle machine"
              + (f"; with {args.threads} threads, OpenMP barriers also wait for descheduled "
                 f"threads (often several times slower): compare with --threads 1."
                 if args.threads > 1 else "."))
    head = (f"{'config':26} {'precision':9} {'batch':>6} {'params':>7} {'s/update':>9} "
            f"{'min':>6} {'wm s':>6} {'beh s':>6} {'peak RSS':>9}")
    cuda = args.device.startswith("cuda")
    if cuda:
        head += f" {'CUDA peak':>9}"
    print(head)
    print("-" * len(head))
    results = []
    for spec in specs:
        r = run_spec(spec, args.timeout, args.concurrent)
        results.append({**spec, **r})
        print_row(spec, r, cuda)
    print(f"load average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    print_speedups(results)
    compare_with_peer(results, args)
    if baseline_dir is not None:
        shutil.rmtree(baseline_dir, ignore_errors=True)
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
