"""Where the dataset's steps live: sources (bag directories, .mcap files, folders of bags), the
on-disk cache of decoded steps (keyed by the bag's files and the topic map, with an LRU size
budget), the memory-mapped SourceStore of one source, and the ingest that streams a bag once
into a store (episodes, segments, gaps and losses as trainer/data/dataset.py describes; the
rebuilding itself is trainer/data/rebuild.py)."""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any, Iterable

import numpy as np
import yaml

from sim_bridge.contract import topics as T
from trainer.bag.reader import BagReader
from trainer.data.rebuild import BagColumns, assemble
from trainer.data.records import (
    EXPECTED_TYPES,
    KNOWN_UNUSED,
    MULTIPLE_PUBLISHERS_KEY,
    SMALL_STORE_STEPS,
    STORE_VERSION,
    CacheWriteError,
    ImageSpec,
    SourceReport,
    TopicMap,
)


def source_files(source: Path) -> list[Path]:
    source = Path(source)
    if source.is_file():
        return [source]
    return sorted(f for f in source.iterdir() if f.suffix == ".mcap" and f.is_file())


def source_identity(source: Path) -> list[tuple[str, int, int]]:
    ident = []
    for f in source_files(source):
        st = f.stat()
        ident.append((f.name, int(st.st_size), int(st.st_mtime_ns)))
    return ident


def cache_key(source: Path, topics: TopicMap, image: ImageSpec = ImageSpec()) -> str:
    h = hashlib.sha256()
    what = {"v": STORE_VERSION, "path": str(Path(source).resolve()),
            "files": source_identity(source), "topics": topics.as_dict()}
    if not image.is_default:   # the model's 64x64 center keeps the keys entries always had
        what["image"] = [image.size, image.crop]
    h.update(json.dumps(what, sort_keys=True).encode())
    return h.hexdigest()[:24]


DEFAULT_CACHE_BUDGET_GB = 4.0


def default_cache_budget_gb() -> float:
    """$PROTOCAD_CACHE_BUDGET_GB, else DEFAULT_CACHE_BUDGET_GB (0 = no limit)."""
    try:
        return float(os.environ.get("PROTOCAD_CACHE_BUDGET_GB", DEFAULT_CACHE_BUDGET_GB))
    except ValueError:
        return DEFAULT_CACHE_BUDGET_GB


def entry_size(entry: Path) -> int:
    return sum(f.stat().st_size for f in entry.rglob("*") if f.is_file())


def prune_cache(cache_dir: Path, budget_bytes: int, keep: Iterable[Path] = ()) -> list[Path]:
    """Evict least-recently-used cache entries (whole bags' decoded frames) until the cache
    fits `budget_bytes`; entries in `keep` (those a live dataset uses) are never evicted.
    An entry's last use is the mtime of its directory, touched each time a dataset opens it.
    Returns the evicted entries. Nothing is lost: an evicted bag is indexed again from its log."""
    cache_dir = Path(cache_dir)
    if budget_bytes <= 0 or not cache_dir.is_dir():
        return []
    keep = {Path(k).resolve() for k in keep}
    entries = [(e.stat().st_mtime, e, entry_size(e)) for e in cache_dir.iterdir()
               if e.is_dir() and (e / "index.json").exists()]
    total = sum(size for _, _, size in entries)
    evicted = []
    for _, entry, size in sorted(entries, key=lambda t: t[0]):
        if total <= budget_bytes:
            break
        if entry.resolve() in keep:
            continue
        shutil.rmtree(entry, ignore_errors=True)
        total -= size
        evicted.append(entry)
    return evicted


def default_cache_dir() -> Path:
    env = os.environ.get("PROTOCAD_CACHE_DIR")
    if env:
        return Path(env)
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "protocad-ros" / "dataset"


# ----------------------------------------------------------------------------- store
class SourceStore:
    """One ingested bag: memory-mapped per-step arrays + segment index."""

    ARRAYS = ("stamp", "img_row", "action", "reward", "discount", "is_first", "is_last", "is_terminal",
              "episode", "step", "context")

    def __init__(self, entry: Path):
        self.entry = Path(entry)
        meta = json.loads((self.entry / "index.json").read_text())
        self.meta = meta
        self.report = SourceReport(**meta["report"])
        self.num_steps = int(meta["num_steps"])
        self.num_images = int(meta["num_images"])
        self.image_shape = tuple(meta["image_shape"]) if meta["image_shape"] else None
        self.segments = np.asarray(meta["segments"], dtype=np.int64).reshape(-1, 2)   # (start, length)
        self.episodes = meta["episodes"]   # list of dicts: start, length, episode, context, split, return
        self.arrays: dict[str, np.ndarray] = {}
        # Per-step arrays are small (tens of bytes a step): in RAM for ordinary bags, memory-
        # mapped for huge ones. Frames always stay on disk (memory-mapped uint8).
        mmap = "r" if self.num_steps > SMALL_STORE_STEPS else None
        for name in self.ARRAYS:
            f = self.entry / f"{name}.npy"
            if f.exists():
                self.arrays[name] = np.load(f, mmap_mode=mmap)
        self._images: np.memmap | None = None

    @property
    def images(self) -> np.ndarray:
        if self._images is None:
            if self.num_images == 0:
                return np.zeros((0, *(self.image_shape or (64, 64, 3))), np.uint8)
            self._images = np.memmap(self.entry / "images.u8", dtype=np.uint8, mode="r",
                                     shape=(self.num_images, *self.image_shape))
        return self._images

    def rows(self, start: int, length: int) -> dict[str, np.ndarray]:
        sl = slice(start, start + length)
        out = {k: np.asarray(v[sl]) for k, v in self.arrays.items() if k not in ("img_row",)}
        out["image"] = np.asarray(self.images[np.asarray(self.arrays["img_row"][sl])])
        return out


def ingest_source(source: Path, topics: TopicMap, entry: Path, image: ImageSpec = ImageSpec()) -> None:
    """Stream one bag once into ENTRY (written under a temp name, renamed when complete; a
    failure or Ctrl-C leaves no partial entry behind)."""
    tmp = entry.with_name(entry.name + f".tmp-{os.getpid()}")
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    try:
        try:
            _ingest_into(source, topics, tmp, image)
        except OSError as exc:    # np.save / index.json on a full disk
            raise CacheWriteError(tmp, exc) from exc
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    try:
        os.replace(tmp, entry) if not entry.exists() else shutil.rmtree(tmp)
    except OSError:  # another process created it first
        shutil.rmtree(tmp, ignore_errors=True)


def recorder_losses(source: Path, used: Iterable[str] | None = None) -> dict[str, str]:
    """The protocad_* custom_data of the bag's metadata.yaml (none for foreign bags), per-topic
    counts kept for the `used` topics only (what the dataset trains on: a missed /diagnostics
    status is no problem)."""
    meta = Path(source) / "metadata.yaml" if Path(source).is_dir() else Path(source).parent / "metadata.yaml"
    try:
        info = (yaml.safe_load(meta.read_text()) or {}).get("rosbag2_bagfile_information") or {}
    except (OSError, ValueError, yaml.YAMLError, AttributeError):   # ValueError: not UTF-8
        return {}   # the reader reports an unreadable metadata.yaml with the bag's path
    custom = info.get("custom_data") or {}
    if not isinstance(custom, dict):
        return {}
    used = set(used) if used is not None else None
    out = {}
    for k, v in custom.items():
        k, v = str(k), str(v)
        if not k.startswith("protocad_"):
            continue
        if used is not None and k in ("protocad_lost_messages", "protocad_missed_before_subscribing",
                                      "protocad_loss_untracked_topics", MULTIPLE_PUBLISHERS_KEY):
            try:
                per = json.loads(v)
            except json.JSONDecodeError:
                per = None
            if isinstance(per, dict):
                per = {t: n for t, n in per.items() if t in used}
            elif isinstance(per, list):
                per = [t for t in per if t in used]
            if not per:
                continue
            v = json.dumps(per, sort_keys=True)
        out[k] = v
    return out


def multiple_publishers(source: Path, used: Iterable[str]) -> dict[str, int]:
    """{topic: publishers} for the `used` topics the bag's recorder saw several publishers on
    (the bag's metadata; empty for unmarked and foreign bags)."""
    value = recorder_losses(source, used=used).get(MULTIPLE_PUBLISHERS_KEY)
    try:
        marked = json.loads(value) if value else {}
    except json.JSONDecodeError:
        return {}
    return {str(t): int(n) for t, n in marked.items()} if isinstance(marked, dict) else {}


def _ingest_into(source: Path, topics: TopicMap, tmp: Path, image: ImageSpec) -> None:
    t0 = time.monotonic()
    rep = SourceReport(path=str(source), files=[str(f) for f in source_files(source)])
    by_key = {k: v for k, v in topics.as_dict().items() if v}
    reader = BagReader(str(source))
    st = _stream_bag(reader, by_key, rep, tmp, image)

    _report_reading(rep, reader.report, source, by_key)
    rep.decode_errors = st.decode_errors
    rep.action_names = st.action_names
    rep.context_names = [n for n in (st.ctx_names or []) if n != T.SPLIT_FIELD] or None
    rep.action_dim = st.act_dim
    rep.image_shape = [st.hw[0], st.hw[1], 3] if st.hw else None

    arrays, meta = assemble(rep, st, by_key)
    for name, arr in arrays.items():
        np.save(tmp / f"{name}.npy", arr)
    rep.ingest_seconds = round(time.monotonic() - t0, 3)
    meta.update(version=STORE_VERSION, source=str(source), identity=source_identity(source),
                topics=topics.as_dict(), num_images=st.n_img, image_shape=rep.image_shape,
                image_crop=image.crop,
                report=asdict(rep))
    (tmp / "index.json").write_text(json.dumps(meta))


def _stream_bag(reader: Any, by_key: dict[str, str], rep: SourceReport, tmp: Path, image: ImageSpec) -> BagColumns:
    """One pass over the mapped topics. A message of the wrong type condemns its topic; one that
    does not decode is counted and skipped; a reader failure mid-stream keeps what came before;
    a write error on the cache stops the ingest (CacheWriteError)."""
    key_of = {v: k for k, v in by_key.items()}
    st = BagColumns(image=image)
    bad_type: set[str] = set()
    with open(tmp / "images.u8", "wb") as img_f:
        try:
            for m in reader.messages(topics=list(key_of)):
                topic = m.topic
                key = key_of.get(topic)
                if key is None or topic in bad_type:
                    continue
                if m.msgtype not in EXPECTED_TYPES[key]:
                    bad_type.add(topic)
                    rep.type_errors.append(f"{topic} (mapped as {key}) has type {m.msgtype}, "
                                           f"expected {' or '.join(EXPECTED_TYPES[key])}")
                    continue
                try:
                    st.take(key, topic, reader.decode(m), img_f)
                except OSError as exc:   # the cache, not the message: stop (below), never skip
                    raise CacheWriteError(tmp, exc) from exc
                except Exception as exc:  # noqa: BLE001 - count, report, keep going
                    st.decode_errors[topic] = st.decode_errors.get(topic, 0) + 1
                    if len(rep.decode_error_examples) < 10:
                        rep.decode_error_examples.append(f"{topic}: {type(exc).__name__}: {exc}")
        except CacheWriteError:
            raise
        except Exception as exc:  # noqa: BLE001 - a reader failure mid-stream: keep what we have
            rep.read_errors.append(f"{type(exc).__name__}: {exc}")
    return st


def _report_reading(rep: SourceReport, br: Any, source: Path, by_key: dict[str, str]) -> None:
    """What the bag reader saw, into the source's report: cut files, read errors, every topic
    (used, an unused contract topic, or foreign), the mapped topics missing, recorder losses."""
    key_of = {v: k for k, v in by_key.items()}
    rep.truncated = [f"{f}: {why}" for f, why in br.truncated.items()]
    rep.read_errors += [f"{f}: {why}" for f, why in br.errors.items()]
    rep.read_errors += [f"refused: {line}" for line in br.refused]
    rep.read_warnings = list(br.warnings)
    for t, n in br.counts.items():
        rep.topics[t] = {"type": br.topic_types.get(t, "?"), "count": n, "used_as": key_of.get(t)}
        if t in key_of:
            continue
        rel = t[len(T.DEFAULT_NAMESPACE):].lstrip("/") if t.startswith(T.DEFAULT_NAMESPACE + "/") else t
        if t in KNOWN_UNUSED or rel in KNOWN_UNUSED or t.rsplit("/", 1)[-1] in KNOWN_UNUSED:
            rep.unused_contract_topics[t] = n
        else:
            rep.foreign_topics[t] = {"type": br.topic_types.get(t, "?"), "count": n}
    rep.missing_topics = [f"{k}={v}" for k, v in by_key.items() if v not in br.counts]
    rep.recording_losses = recorder_losses(source, used=key_of)
