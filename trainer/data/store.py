"""Where the dataset's steps live: sources (bag directories, .mcap files, folders of bags), the
on-disk cache of decoded steps (keyed by the bag's files and the topic map, with an LRU size
budget), the memory-mapped SourceStore of one source, and the ingest that streams a bag once
into a store (episodes, segments, gaps and losses as trainer/data/dataset.py describes)."""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
from array import array
from dataclasses import asdict
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from sim_bridge.contract import topics as T
from trainer.data.sources import MAX_SEARCH_DEPTH, find_sources  # noqa: F401 - also imported from here
from trainer.data.records import (EXPECTED_TYPES, KNOWN_UNUSED, MULTIPLE_PUBLISHERS_KEY, REQUIRED_KEYS,
                                   SMALL_STORE_STEPS, STORE_VERSION, CacheWriteError, SourceReport, TopicMap)


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


def cache_key(source: Path, topics: TopicMap) -> str:
    h = hashlib.sha256()
    h.update(json.dumps({"v": STORE_VERSION, "path": str(Path(source).resolve()),
                         "files": source_identity(source), "topics": topics.as_dict()},
                        sort_keys=True).encode())
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


def ingest_source(source: Path, topics: TopicMap, entry: Path) -> None:
    """Stream one bag once into ENTRY (written under a temp name, renamed when complete; a
    failure or Ctrl-C leaves no partial entry behind)."""
    tmp = entry.with_name(entry.name + f".tmp-{os.getpid()}")
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    try:
        try:
            _ingest_into(source, topics, tmp)
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
    import json

    import yaml

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
    import json

    value = recorder_losses(source, used=used).get(MULTIPLE_PUBLISHERS_KEY)
    try:
        marked = json.loads(value) if value else {}
    except json.JSONDecodeError:
        return {}
    return {str(t): int(n) for t, n in marked.items()} if isinstance(marked, dict) else {}


def _ingest_into(source: Path, topics: TopicMap, tmp: Path) -> None:
    from trainer.bag import mcap_io

    t0 = time.monotonic()
    rep = SourceReport(path=str(source), files=[str(f) for f in source_files(source)])
    by_key = {k: v for k, v in topics.as_dict().items() if v}
    key_of = {v: k for k, v in by_key.items()}

    img_stamps, seen_img = array("q"), set()
    si_stamps, si_vals = array("q"), array("d")
    act_stamps, act_vals = array("q"), array("d")
    ctx_stamps, ctx_vals = array("q"), array("d")
    bad_type: set[str] = set()
    dup: dict[str, int] = {}
    dec_err: dict[str, int] = {}
    act_dim = ctx_names = None
    hw = None

    def err(topic: str, msg: str) -> None:
        dec_err[topic] = dec_err.get(topic, 0) + 1
        if len(rep.decode_error_examples) < 10:
            rep.decode_error_examples.append(f"{topic}: {msg}")

    reader = mcap_io.BagReader(str(source))
    img_f = open(tmp / "images.u8", "wb")
    n_img = 0
    try:
        try:
            for m in reader.messages(topics=list(key_of)):
                topic = m.topic
                key = key_of.get(topic)
                if key is None or topic in bad_type:
                    continue
                if m.msgtype != EXPECTED_TYPES[key]:
                    bad_type.add(topic)
                    rep.type_errors.append(f"{topic} (mapped as {key}) has type {m.msgtype}, "
                                           f"expected {EXPECTED_TYPES[key]}")
                    continue
                try:
                    msg = reader.decode(m)
                    stamp = T.stamp_to_ns(msg.header.stamp)
                    if key == "image":
                        if stamp in seen_img:
                            dup[topic] = dup.get(topic, 0) + 1
                            continue
                        img = T.read_image(msg, expected_hw=hw)
                        if hw is None:
                            hw = (img.shape[0], img.shape[1])
                        img_f.write(np.ascontiguousarray(img).tobytes())
                        seen_img.add(stamp)
                        img_stamps.append(stamp)
                        n_img += 1
                    elif key == "step_info":
                        info = T.read_step_info(msg)
                        si_stamps.append(stamp)
                        si_vals.extend([float(info.reward), float(info.discount), float(info.is_first),
                                        float(info.is_last), float(info.is_terminal), float(info.episode),
                                        float(info.step)])
                    elif key == "action":
                        a = T.read_action(msg)
                        if not np.all(np.isfinite(a)):
                            raise ValueError("non-finite action")
                        if act_dim is None:
                            act_dim = int(a.size)
                            rep.action_names = [str(n) for n in msg.name]
                        if a.size != act_dim:
                            raise ValueError(f"action has {a.size} values, earlier ones {act_dim}")
                        act_stamps.append(stamp)
                        act_vals.extend(a.tolist())
                    elif key == "context":
                        names = [str(n) for n in msg.name]
                        if ctx_names is None:
                            ctx_names = names
                        if names != ctx_names:
                            raise ValueError(f"context names {names} differ from earlier {ctx_names}")
                        ctx_stamps.append(stamp)
                        ctx_vals.extend(float(v) for v in msg.position)
                except OSError as exc:   # the cache, not the message: stop (below), never skip
                    raise CacheWriteError(tmp, exc) from exc
                except Exception as exc:  # noqa: BLE001 - count, report, keep going
                    err(topic, f"{type(exc).__name__}: {exc}")
        except CacheWriteError:
            raise
        except Exception as exc:  # noqa: BLE001 - a reader failure mid-stream: keep what we have
            rep.read_errors.append(f"{type(exc).__name__}: {exc}")
    finally:
        img_f.close()

    _report_reading(rep, reader.report, source, by_key)
    rep.decode_errors = dec_err
    rep.context_names = [n for n in (ctx_names or []) if n != T.SPLIT_FIELD] or None
    rep.action_dim = act_dim
    rep.image_shape = [hw[0], hw[1], 3] if hw else None

    arrays, meta = _assemble(rep, img_stamps, si_stamps, si_vals, act_stamps, act_vals, act_dim,
                             ctx_stamps, ctx_vals, ctx_names, dup, by_key)
    for name, arr in arrays.items():
        np.save(tmp / f"{name}.npy", arr)
    rep.ingest_seconds = round(time.monotonic() - t0, 3)
    meta.update(version=STORE_VERSION, source=str(source), identity=source_identity(source),
                topics=topics.as_dict(), num_images=n_img, image_shape=rep.image_shape,
                report=asdict(rep))
    (tmp / "index.json").write_text(json.dumps(meta))


def _report_reading(rep: SourceReport, br: Any, source: Path, by_key: dict[str, str]) -> None:
    """What the bag reader saw, into the source's report: cut files, read errors, every topic
    (used, an unused contract topic, or foreign), the mapped topics missing, recorder losses."""
    key_of = {v: k for k, v in by_key.items()}
    rep.truncated = [f"{f}: {why}" for f, why in br.truncated.items()]
    rep.read_errors += [f"{f}: {why}" for f, why in br.errors.items()]
    rep.read_errors += [f"refused: {line}" for line in br.refused]
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


def _dedup(stamps: array, name: str, dup: dict) -> tuple[np.ndarray, np.ndarray]:
    """Sorted unique stamps and the index of each one's FIRST occurrence in stream order."""
    s = np.frombuffer(stamps, dtype=np.int64) if len(stamps) else np.zeros(0, np.int64)
    u, first = np.unique(s, return_index=True)
    if s.size - u.size:
        dup[name] = dup.get(name, 0) + int(s.size - u.size)
    return u, first


def _assemble(rep: SourceReport, img_stamps, si_stamps, si_vals, act_stamps, act_vals, act_dim,
              ctx_stamps, ctx_vals, ctx_names, dup, by_key) -> tuple[dict[str, np.ndarray], dict]:
    empty_meta = {"num_steps": 0, "segments": [], "episodes": []}
    # images: already deduplicated while streaming (row = arrival order)
    img_s = np.frombuffer(img_stamps, dtype=np.int64) if len(img_stamps) else np.zeros(0, np.int64)
    img_order = np.argsort(img_s, kind="stable")
    img_sorted, img_rows = img_s[img_order], img_order.astype(np.int64)
    si_u, si_first = _dedup(si_stamps, by_key["step_info"], dup)
    si = (np.frombuffer(si_vals, dtype=np.float64).reshape(-1, 7)[si_first] if len(si_vals)
          else np.zeros((0, 7)))
    rep.duplicates = {t: n for t, n in dup.items() if n}

    missing = [k for k in REQUIRED_KEYS if not (len(img_stamps) if k == "image" else
                                              len(si_stamps) if k == "step_info" else len(act_stamps))]
    if missing:
        rep.rejected = ("no usable messages for " + ", ".join(f"{k} ({by_key[k]})" for k in missing)
                        + "; map topics with --topic KEY=/name")
        return {}, empty_meta

    stamps, i_img, i_si = np.intersect1d(img_sorted, si_u, assume_unique=True, return_indices=True)
    rep.images_without_step_info = int(img_sorted.size - stamps.size)
    rep.step_info_without_image = int(si_u.size - stamps.size)
    n = int(stamps.size)
    if n == 0:
        rep.rejected = "no step has both an image and a step_info with the same header.stamp"
        return {}, empty_meta
    rep.steps = n
    img_row = img_rows[i_img]
    si = si[i_si]
    reward, discount = si[:, 0].astype(np.float32), si[:, 1].astype(np.float32)
    is_first, is_last, is_term = si[:, 2] > 0.5, si[:, 3] > 0.5, si[:, 4] > 0.5
    episode, step = si[:, 5].astype(np.int64), si[:, 6].astype(np.int64)

    # actions answering each observation (same stamp)
    act_u, act_first = _dedup(act_stamps, by_key["action"], dup)
    rep.duplicates = {t: k for t, k in dup.items() if k}
    acts = np.frombuffer(act_vals, dtype=np.float64).reshape(-1, act_dim)[act_first]
    pos = np.searchsorted(act_u, stamps)
    pos_c = np.minimum(pos, max(act_u.size - 1, 0))
    has_act = (act_u.size > 0) & (act_u[pos_c] == stamps)
    answer = np.zeros((n, act_dim), np.float32)
    answer[has_act] = acts[pos_c[has_act]]
    rep.orphan_actions = int(act_u.size - np.count_nonzero(has_act))

    # context at (or last before) each observation
    ctx = None
    if ctx_names is not None and len(ctx_stamps):
        ctx_u, ctx_first = _dedup(ctx_stamps, by_key.get("context", "context"), dup)
        rep.duplicates = {t: k for t, k in dup.items() if k}
        cv = np.frombuffer(ctx_vals, dtype=np.float64).reshape(-1, len(ctx_names))[ctx_first]
        cpos = np.searchsorted(ctx_u, stamps, side="right") - 1
        ctx = np.full((n, len(ctx_names)), np.nan, np.float32)
        ok = cpos >= 0
        ctx[ok] = cv[cpos[ok]]

    # episode and segment boundaries
    prev_ep = np.r_[np.int64(-(2 ** 62)), episode[:-1]]
    new_ep = is_first | (episode != prev_ep)
    new_ep[0] = True
    dstep = np.r_[1, np.diff(step)]
    gap = (~new_ep) & (dstep > 1)
    ooo = (~new_ep) & (dstep < 1)
    prev_has_act = np.r_[False, has_act[:-1]]
    miss_prev = (~new_ep) & (~gap) & (~ooo) & (~prev_has_act)
    seg_start = new_ep | gap | ooo | miss_prev
    rep.gaps = int(gap.sum())
    rep.missing_step_ids = int((dstep[gap] - 1).sum())
    for i in np.flatnonzero(gap)[:20]:
        a, b = step[i - 1] + 1, step[i] - 1
        rep.gap_examples.append(f"episode {episode[i]} steps {a}" + (f"..{b}" if b > a else ""))
    rep.out_of_order = int(ooo.sum())
    rep.missing_actions = int(miss_prev.sum())
    last = n - 1
    rep.unanswered_final = int(not has_act[last] and not is_last[last])
    rep.unanswered_is_last = int(np.count_nonzero(is_last & ~has_act))

    # training convention: action[t] = answer to obs t-1 within a segment, zeros at its start
    action = np.zeros((n, act_dim), np.float32)
    cont = ~seg_start
    action[1:][cont[1:]] = answer[:-1][cont[1:]]

    starts = np.flatnonzero(seg_start)
    lengths = np.diff(np.r_[starts, n])
    segments = np.stack([starts, lengths], 1)
    rep.segments = int(starts.size)

    ep_starts = np.flatnonzero(new_ep)
    ep_lens = np.diff(np.r_[ep_starts, n])
    episodes = []
    split_idx = ctx_names.index(T.SPLIT_FIELD) if ctx_names and T.SPLIT_FIELD in ctx_names else None
    for s0, ln in zip(ep_starts.tolist(), ep_lens.tolist()):
        sl = slice(s0, s0 + ln)
        e = {"start": s0, "length": ln, "episode": int(episode[s0]), "has_first": bool(is_first[s0]),
             "has_last": bool(is_last[s0 + ln - 1]),
             "gaps": int(gap[sl].sum() + ooo[sl].sum() + miss_prev[sl].sum()),
             "return": float(reward[sl][~is_first[sl]].sum()), "context": None, "split": None}
        if ctx is not None:
            row = ctx[s0]
            if np.all(np.isfinite(row)):
                e["context"] = {k: float(v) for k, v in zip(ctx_names, row) if k != T.SPLIT_FIELD}
                if split_idx is not None:
                    e["split"] = T.SPLITS[int(row[split_idx])] if int(row[split_idx]) in (0, 1) else None
        episodes.append(e)
    rep.episodes = len(episodes)
    rep.episodes_without_first = sum(not e["has_first"] for e in episodes)
    rep.complete_episodes = sum(e["has_first"] and e["has_last"] and not e["gaps"] for e in episodes)

    arrays = {"stamp": stamps.astype(np.int64), "img_row": img_row.astype(np.int64), "action": action,
              "reward": reward, "discount": discount, "is_first": is_first, "is_last": is_last,
              "is_terminal": is_term, "episode": episode, "step": step}
    if ctx is not None:
        arrays["context"] = ctx
    meta = {"num_steps": n, "segments": segments.tolist(), "episodes": episodes, "context_names": ctx_names}
    return arrays, meta
