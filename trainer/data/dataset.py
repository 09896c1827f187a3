"""MCAP dataset: recorded rosbag2-layout logs -> episodes -> B x M training sequences.

What it reads
    Bag directories (``NAME/`` with ``NAME_0.mcap``, ... and ``metadata.yaml``), single
    ``.mcap`` files, and folders of bags (every directory below that holds ``.mcap`` files is
    one bag). Logs written by this project (recorder, ``protocad-online``) and by other tools
    (``rosbags``, rosbag2) read the same as long as the message types match the topic
    contract (sim_bridge/contract/topics.py): step_info and action and context
    ``sensor_msgs/msg/JointState``; image ``sensor_msgs/msg/Image`` or, from a robot's camera,
    any size in a common encoding or ``sensor_msgs/msg/CompressedImage`` (JPEG/PNG): every
    frame becomes the model's image through ``sim_bridge.contract.camera.model_image`` (cropped,
    ``crop``, and area-resized to ``image_size``), the function the policy node runs on a robot;
    a frame already at the model's size passes bit-exact. Topic names are configurable
    (:class:`TopicMap`, CLI ``--topic image=/cam/rgb``); defaults are the contract topics in
    ``/protocad``.

How it rebuilds episodes (per bag; stamps are unique within one sim-bridge run)
    All messages of one step share ``header.stamp``; the action is stamped like the
    observation it answers. A *step* is a stamp that has both an image and a step_info
    (same stamp twice on a topic: the first is kept, the rest counted as duplicates).
    Steps are ordered by stamp; an episode starts at ``is_first`` or where the step_info
    episode id changes. A contiguous *segment* (what training windows are cut from) also
    ends at a gap (missing step ids), and where the answer to the previous observation is
    missing (the action that led to the next observation is unknown).

Training convention (Dreamer; msgs_docs/README.md, "Step convention"): ``action[t]`` is the
action that LED TO obs t (the answer to obs t-1), zeros at ``is_first`` and at a segment start
whose predecessor is unknown; ``reward[t]`` is the reward arriving with obs t. The answer to
``is_last`` is recorded but not executed, so it is unused.

Memory
    Each bag is streamed once into an on-disk store (``images.u8`` raw uint8 frames read
    back through ``np.memmap``, small per-step ``.npy`` arrays also memory-mapped, and an
    ``index.json``) in a cache directory keyed by the bag's files (path, size, mtime), the
    topic map and the image size and crop (when not the model's 64x64 center), so a second
    run (or the next loop cycle) reuses it. Only the segment index lives in RAM; frames stay
    uint8 on disk until a batch is sampled.

Nothing is hidden: :class:`DatasetReport` lists truncated files, read errors, foreign
(unused) topics, duplicates, gaps, incomplete steps, missing actions and skipped short
segments; ``print(dataset.report)`` shows it as a readable summary.

The parts: trainer/data/records.py (TopicMap, reports, errors), trainer/data/store.py
(sources, the cache, SourceStore, ingest); this module is the dataset and its CLI.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
from pathlib import Path
from typing import Any, Iterable, Iterator, Mapping, Sequence

import numpy as np

from protocad_ros.model.agent_base import BATCH_KEYS  # what an agent's train_step reads
from sim_bridge.contract.contexts import get_task, normalized_log_context
from trainer.data.records import (
    DEFAULT_CROP,
    DEFAULT_IMAGE_SIZE,
    CacheWriteError,
    DatasetError,
    DatasetReport,
    ImageSpec,
    SourceReport,
    TopicMap,
)
from trainer.data.sources import find_sources
from trainer.data.store import (
    SourceStore,
    cache_key,
    default_cache_budget_gb,
    default_cache_dir,
    entry_size,
    ingest_source,
    prune_cache,
)

__all__ = ["MCAPDataset", "TopicMap", "DatasetReport", "SourceReport", "DatasetError",
           "CacheWriteError", "find_sources", "cache_key", "default_cache_dir", "BATCH_KEYS"]

# ----------------------------------------------------------------------------- dataset


class MCAPDataset:
    """Episodes from MCAP logs, sampled as B x M windows uniformly over all valid windows.

    >>> ds = MCAPDataset(["runs/x/bags"], seq_len=50, seed=0)
    >>> print(ds.report)
    >>> batch = ds.sample(16)   # image uint8 (16,50,64,64,3), action (16,50,A), reward, ...

    `add(paths)` appends newly recorded bags (already-known bags are skipped).
    `state_dict()` / `load_state_dict()` carry the sampler RNG so a resumed run draws the
    same next batch.
    """

    def __init__(self, paths: Iterable[str | Path] = (), *, topics: TopicMap | None = None,
                 seq_len: int = 50, seed: int = 0, cache_dir: str | Path | None = None,
                 image_shape: Sequence[int] | None = None, action_dim: int | None = None,
                 verbose: bool = False, cache_budget_gb: float | None = None,
                 image_size: int | None = None, crop: str = DEFAULT_CROP):
        self.topics = topics or TopicMap()
        # Every frame becomes this (image_shape's size when given, else the model's 64).
        self.image = ImageSpec(int(image_size or (image_shape[0] if image_shape else DEFAULT_IMAGE_SIZE)),
                               crop)
        # LRU budget of the frame cache (entries this dataset uses are never evicted).
        self.cache_budget_gb = default_cache_budget_gb() if cache_budget_gb is None else float(cache_budget_gb)
        self.seq_len = int(seq_len)
        if self.seq_len < 1:
            raise ValueError("seq_len must be >= 1")
        self.cache_dir = Path(cache_dir) if cache_dir else default_cache_dir()
        self.rng = np.random.Generator(np.random.PCG64(seed))
        self.samples_drawn = 0
        self.stores: list[SourceStore] = []
        self._known: set[str] = set()
        self._warned_budget = False
        self.image_shape = tuple(image_shape) if image_shape else None
        self.action_dim = action_dim
        self.action_names: list[str] | None = None
        self.verbose = verbose
        self.report = DatasetReport(seq_len=self.seq_len)
        self._seg_store = np.zeros(0, np.int64)
        self._seg_start = np.zeros(0, np.int64)
        self._cum = np.zeros(0, np.int64)
        paths = list(paths)
        if paths:
            self.add(paths)

    # -- building
    def add(self, paths: Iterable[str | Path], topics: TopicMap | None = None) -> list[SourceReport]:
        """Index new bags (streamed once into the cache, or reused from it). `topics`: read
        these bags through another topic map than the dataset's (one bag that recorded several
        robots is added once per robot namespace)."""
        topics = topics or self.topics
        added = []
        for src in find_sources(paths):
            rid = f"{src.resolve()}|{topics.step_info}"
            if rid in self._known:
                continue
            key = cache_key(src, topics, self.image)
            entry = self.cache_dir / key
            cached = (entry / "index.json").exists()
            if cached:
                try:
                    store = SourceStore(entry)
                    # An entry from before frames were resized may hold a camera's own size.
                    if store.image_shape and tuple(store.image_shape) != (self.image.size, self.image.size, 3):
                        raise ValueError(f"frames of {store.image_shape}, not the model's")
                except Exception:  # noqa: BLE001 - corrupt or outdated cache entry: rebuild it
                    shutil.rmtree(entry, ignore_errors=True)
                    cached = False
            if not cached:
                if self.verbose:
                    print(f"[dataset] indexing {src} ...", file=sys.stderr, flush=True)
                entry.parent.mkdir(parents=True, exist_ok=True)
                ingest_source(src, topics, entry, self.image)
                store = SourceStore(entry)
            os.utime(entry)   # last use, for the LRU budget
            store.report.cached = cached
            store.report.path = str(src)
            self._check_compat(store)
            self._known.add(rid)
            self.stores.append(store)
            self.report.sources.append(store.report)
            added.append(store.report)
        self._reindex()
        if added and self.cache_budget_gb > 0:
            budget = int(self.cache_budget_gb * 1e9)
            evicted = prune_cache(self.cache_dir, budget, keep=[st.entry for st in self.stores])
            if evicted and self.verbose:
                print(f"[dataset] cache over its {self.cache_budget_gb:g} GB budget: evicted {len(evicted)} "
                      f"least recently used bag(s) (re-indexed from their logs if used again)",
                      file=sys.stderr, flush=True)
            used = sum(entry_size(st.entry) for st in self.stores)
            if used > budget and not self._warned_budget:
                self._warned_budget = True
                print(f"[dataset] this dataset alone holds {used / 1e9:.2f} GB of decoded frames, more than "
                      f"the cache budget ({self.cache_budget_gb:g} GB; --cache-budget-gb or "
                      f"PROTOCAD_CACHE_BUDGET_GB): nothing it uses is evicted", file=sys.stderr, flush=True)
        return added

    def _check_compat(self, store: SourceStore) -> None:
        rep = store.report
        if rep.rejected:
            return
        if self.image_shape is None:
            self.image_shape = tuple(rep.image_shape)
        elif tuple(rep.image_shape) != tuple(self.image_shape):
            rep.rejected = f"image shape {rep.image_shape} differs from the dataset's {list(self.image_shape)}"
            return
        if self.action_dim is None:
            self.action_dim = rep.action_dim
            self.action_names = rep.action_names
        elif rep.action_dim != self.action_dim:
            rep.rejected = f"action dim {rep.action_dim} differs from the dataset's {self.action_dim}"

    def _reindex(self) -> None:
        st, ss, ln = [], [], []
        short_n = short_steps = 0
        for i, store in enumerate(self.stores):
            if store.report.rejected or store.segments.size == 0:
                continue
            segs = store.segments
            ok = segs[:, 1] >= self.seq_len
            short_n += int((~ok).sum())
            short_steps += int(segs[~ok, 1].sum())
            st.append(np.full(int(ok.sum()), i, np.int64))
            ss.append(segs[ok, 0])
            ln.append(segs[ok, 1])
        self._seg_store = np.concatenate(st) if st else np.zeros(0, np.int64)
        self._seg_start = np.concatenate(ss) if ss else np.zeros(0, np.int64)
        lens = np.concatenate(ln) if ln else np.zeros(0, np.int64)
        self._cum = np.cumsum(lens - self.seq_len + 1)
        self.report.seq_len = self.seq_len
        self.report.windows = int(self._cum[-1]) if self._cum.size else 0
        self.report.short_segments_skipped = short_n
        self.report.short_steps_skipped = short_steps

    # -- info
    @property
    def num_windows(self) -> int:
        return self.report.windows

    @property
    def num_steps(self) -> int:
        return self.report.steps

    @property
    def num_episodes(self) -> int:
        return self.report.episodes

    def episodes(self) -> Iterator[dict]:
        """Per-episode info (source, start, length, return, context, split, has_first/last)."""
        for i, store in enumerate(self.stores):
            if store.report.rejected:
                continue
            for e in store.episodes:
                yield {**e, "source": store.report.path, "store": i}

    def episode_steps(self, store: int, start: int, length: int) -> dict[str, np.ndarray]:
        """Rows of one store (e.g. a whole episode from `episodes()`), images included."""
        return self.stores[store].rows(start, length)

    # -- sampling
    def _require(self) -> None:
        if self.num_windows == 0:
            raise DatasetError(
                f"no training window of length {self.seq_len}: {self.num_steps} steps in "
                f"{self.num_episodes} episodes, {self.report.short_segments_skipped} segment(s) "
                f"shorter than {self.seq_len}\n{self.report.summary()}")

    def sample_index(self, batch_size: int) -> list[tuple[int, int]]:
        """(store, first row) of B windows drawn uniformly over all valid windows."""
        self._require()
        w = self.rng.integers(0, int(self._cum[-1]), size=int(batch_size))
        seg = np.searchsorted(self._cum, w, side="right")
        before = np.where(seg > 0, self._cum[np.maximum(seg - 1, 0)], 0)
        off = w - before
        self.samples_drawn += int(batch_size)
        return [(int(self._seg_store[s]), int(self._seg_start[s] + o)) for s, o in zip(seg, off)]

    def sample(self, batch_size: int, seq_len: int | None = None) -> dict[str, np.ndarray]:
        """Batch dict: image uint8 (B,M,H,W,3), action float32 (B,M,A), reward/discount
        float32 (B,M), is_first/is_last/is_terminal bool (B,M); plus context float32
        (B,M,C) when every sampled store has one."""
        if seq_len is not None and int(seq_len) != self.seq_len:
            self.seq_len = int(seq_len)
            self._reindex()
        return self.gather(self.sample_index(batch_size))

    def gather(self, index: Sequence[tuple[int, int]]) -> dict[str, np.ndarray]:
        """The batch for (store, first row) pairs from `sample_index`."""
        parts = [self.stores[s].rows(r, self.seq_len) for s, r in index]
        keys = set.intersection(*(set(p) for p in parts))
        out = {k: np.stack([p[k] for p in parts]) for k in keys if k not in ("stamp", "episode", "step")}
        out["action"] = out["action"].astype(np.float32, copy=False)
        return out

    def check_true_context(self, task: str) -> None:
        """DatasetError (one line) unless every bag carries the true context of `task`'s
        parameters (the variant that reads it trains only from such logs)."""
        params = get_task(task).params
        for store in self.stores:
            if store.report.rejected:
                continue
            names = store.meta.get("context_names") or []
            if "context" not in store.arrays or not set(params) <= set(names):
                raise DatasetError(f"{store.report.path}: no true context of {task} ({', '.join(params)}) "
                                   "in this bag; the true-context variant reads it from the context topic")

    def true_context(self, index: Sequence[tuple[int, int]], task: str) -> np.ndarray:
        """The true context of the windows `index` names, as the true-context variant reads it:
        float32 (B, M, P), normalized log values of `task`'s parameters (normalized_log_context).
        Steps before a bag's first context message (NaN) read as the training grid's centre."""
        params = get_task(task).params
        rows = []
        for s, r in index:
            store = self.stores[s]
            cols = [store.meta["context_names"].index(p) for p in params]
            rows.append(store.rows(r, self.seq_len)["context"][:, cols])
        values = np.stack(rows).astype(np.float64)
        out = normalized_log_context(np.where(np.isfinite(values) & (values > 0), values, np.nan), task)
        return np.nan_to_num(out, nan=0.0).astype(np.float32)

    @staticmethod
    def training_batch(batch: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Only the keys Agent.train_step reads."""
        return {k: batch[k] for k in BATCH_KEYS}

    # -- state
    def state_dict(self) -> dict:
        return {"rng": self.rng.bit_generator.state, "samples_drawn": self.samples_drawn,
                "seq_len": self.seq_len, "sources": [s.report.path for s in self.stores]}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        self.rng.bit_generator.state = state["rng"]
        self.samples_drawn = int(state.get("samples_drawn", 0))


def main(argv: Sequence[str] | None = None) -> int:
    """`python -m trainer.data.dataset LOGS... [--topic k=/t]`: index logs and print the report."""
    ap = argparse.ArgumentParser(prog="python -m trainer.data.dataset", description=main.__doc__)
    ap.add_argument("logs", nargs="+", help="bag directories, .mcap files or folders of bags")
    ap.add_argument("--topic", action="append", default=[], metavar="KEY=/TOPIC",
                    help="topic mapping for foreign logs (image, step_info, action, context)")
    ap.add_argument("--namespace", default=None, help="namespace of the contract topics (default /protocad)")
    ap.add_argument("--seq-len", type=int, default=50)
    ap.add_argument("--cache-dir", default=None)
    ap.add_argument("--json", default=None, help="also write the report as JSON here")
    ap.add_argument("--image-size", type=int, default=DEFAULT_IMAGE_SIZE,
                    help="every frame is cropped and resized to this square (the model's)")
    ap.add_argument("--crop", default=DEFAULT_CROP, help="the part of each frame the model sees: "
                    "center (the largest centered square), full, or x,y,w,h in pixels")
    a = ap.parse_args(argv)
    ds = MCAPDataset(a.logs, topics=TopicMap.parse(a.topic, a.namespace), seq_len=a.seq_len,
                     cache_dir=a.cache_dir, verbose=True, image_size=a.image_size, crop=a.crop)
    print(ds.report.summary(verbose=True))
    if a.json:
        Path(a.json).write_text(json.dumps(ds.report.to_dict(), indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
