#!/usr/bin/env python3
"""Benchmark of trainer.data.dataset: indexing speed, sampling speed and memory on a synthetic log.

    python scripts/bench_dataset.py --steps 20000 --bags 4     # ~1 GB of raw frames

Writes BAGS bags (trainer.bag.writer.BagWriter, zstd, the contract topics) with STEPS steps in
total (episodes of 500 steps, noise images so compression cannot cheat), then reports:
- first indexing (stream every bag once into the on-disk uint8 store): steps/s, MB/s of frames;
- a second open (cache reuse): seconds;
- sampling B x M batches (16 x 50 by default): batches/s and frames/s;
- resident memory (RSS) before/after indexing and after sampling, against the size of the frames:
  the store keeps frames on disk (memory-mapped), so RSS must not grow with the log.
Prints figures only; never used in tests.
"""
from __future__ import annotations

import argparse
import os
import resource
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from sim_bridge.contract import topics as T
from trainer.bag.rosmsg import new_message
from trainer.bag.writer import BagWriter
from trainer.data.dataset import MCAPDataset


def rss_mb(kind: str = "RssAnon") -> float:
    """Resident memory in MB: RssAnon = the process's own memory (what a log larger than RAM
    must not grow); RssFile = pages of memory-mapped files (page cache, reclaimable)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(kind + ":"):
                return int(line.split()[1]) / 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def write_bags(root: Path, steps: int, bags: int, ep_len: int = 500) -> list[Path]:
    rng = np.random.default_rng(0)
    out, per_bag, dt = [], steps // bags, 40_000_000
    new = new_message
    for b in range(bags):
        d = root / f"bag{b}"
        with BagWriter(d) as w:
            names = {k: T.topic_name("/protocad", k) for k in (T.IMAGE, T.STEP_INFO, T.CONTEXT, T.ACTION)}
            for rel, t in names.items():
                w.add_topic(t, T.TYPES[rel])
            for i in range(per_bag):
                s, stamp = i % ep_len, i * dt
                img = rng.integers(0, 256, (64, 64, 3), dtype=np.uint8)
                w.write_message(names[T.CONTEXT], T.fill_context(new(T.TYPES[T.CONTEXT]), {"m": 1.0}, "train", stamp), stamp)
                w.write_message(names[T.STEP_INFO], T.fill_step_info(new(T.TYPES[T.STEP_INFO]), T.StepInfo(
                    0.0, 1.0, s == 0, s == ep_len - 1, False, i // ep_len, s), stamp), stamp)
                w.write_message(names[T.IMAGE], T.fill_image(new(T.TYPES[T.IMAGE]), img, stamp), stamp)
                w.write_message(names[T.ACTION], T.fill_action(new(T.TYPES[T.ACTION]), [0.1], ["a"], stamp), stamp)
        out.append(d)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=20000)
    ap.add_argument("--bags", type=int, default=4)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--seq-len", type=int, default=50)
    ap.add_argument("--batches", type=int, default=200)
    ap.add_argument("--dir", default=None, help="work directory (default: a temp dir, removed)")
    a = ap.parse_args()
    work = Path(a.dir) if a.dir else Path(tempfile.mkdtemp(prefix="bench_dataset_"))
    try:
        t = time.perf_counter()
        bags = write_bags(work / "bags", a.steps, a.bags)
        t_write = time.perf_counter() - t
        mb_bags = sum(f.stat().st_size for b in bags for f in b.glob("*.mcap")) / 2**20
        frames_mb = a.steps * 64 * 64 * 3 / 2**20
        print(f"log: {a.steps} steps in {a.bags} bags, {mb_bags:.0f} MB of MCAP (zstd), {frames_mb:.0f} MB of raw "
              f"frames; written in {t_write:.1f}s")
        r0 = rss_mb()
        t = time.perf_counter()
        ds = MCAPDataset(bags, seq_len=a.seq_len, cache_dir=work / "cache")
        t_index = time.perf_counter() - t
        r1 = rss_mb()
        print(f"first indexing: {t_index:.1f}s = {a.steps / t_index:.0f} steps/s, {frames_mb / t_index:.0f} MB/s of frames")
        t = time.perf_counter()
        MCAPDataset(bags, seq_len=a.seq_len, cache_dir=work / "cache")
        print(f"second open (cache reused): {time.perf_counter() - t:.2f}s")
        ds.sample(a.batch)
        t = time.perf_counter()
        for _ in range(a.batches):
            ds.sample(a.batch)
        dt = time.perf_counter() - t
        r2 = rss_mb()
        print(f"sampling {a.batch} x {a.seq_len}: {a.batches / dt:.1f} batches/s = "
              f"{a.batches * a.batch * a.seq_len / dt:.0f} frames/s")
        print(f"anonymous RSS: {r0:.0f} MB before, {r1:.0f} MB after indexing (+{r1 - r0:.0f}), {r2:.0f} MB after "
              f"sampling (+{r2 - r0:.0f}); mapped file pages after sampling {rss_mb('RssFile'):.0f} MB (page cache, "
              f"reclaimable); raw frames {frames_mb:.0f} MB (store on disk: "
              f"{sum(f.stat().st_size for f in (work / 'cache').rglob('*')) / 2**20:.0f} MB)")
        print(f"machine: {os.cpu_count()} cores")
    finally:
        if not a.dir:
            shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
