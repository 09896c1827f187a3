"""MCAP dataset: recorded rosbag2-layout logs -> episodes -> B x M training sequences.

What it reads
    Bag directories (``NAME/`` with ``NAME_0.mcap``, ... and ``metadata.yaml``), single
    ``.mcap`` files, and folders of bags (every directory below that holds ``.mcap`` files is
    one bag). Logs written by this project (recorder, ``protocad-online``) and by other tools
    (``rosbags``, rosbag2) read the same as long as the message types match the topic
    contract (sim_bridge/topics.py): image ``sensor_msgs/msg/Image`` rgb8, step_info and
    action and context ``sensor_msgs/msg/JointState``. Topic names are configurable
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

Training convention (API.md, Dreamer): ``action[t]`` is the action that LED TO obs t (the
answer to obs t-1), zeros at ``is_first`` and at a segment start whose predecessor is
unknown; ``reward[t]`` is the reward arriving with obs t. The answer to ``is_last`` is
recorded but not executed, so it is unused.

Memory
    Each bag is streamed once into an on-disk store (``images.u8`` raw uint8 frames read
    back through ``np.memmap``, small per-step ``.npy`` arrays also memory-mapped, and an
    ``index.json``) in a cache directory keyed by the bag's files (path, size, mtime) and
    the topic map, so a second run (or the next loop cycle) reuses it. Only the segment
    index lives in RAM; frames stay uint8 on disk until a batch is sampled.

Nothing is hidden: :class:`DatasetReport` lists truncated files, read errors, foreign
(unused) topics, duplicates, gaps, incomplete steps, missing actions and skipped short
segments; ``print(dataset.report)`` shows it as a readable summary.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import sys
import time
from array import array
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Iterable, Iterator, Mapping, Sequence

import numpy as np

from sim_bridge import topics as T

STORE_VERSION = 1
SMALL_STORE_STEPS = 200_000    # stores with more steps keep even their per-step arrays on disk
REQUIRED_KEYS = ("image", "step_info", "action")
TOPIC_KEYS = ("image", "step_info", "action", "context")
EXPECTED_TYPES = {
    "image": T.TYPES[T.IMAGE],
    "step_info": T.TYPES[T.STEP_INFO],
    "action": T.TYPES[T.ACTION],
    "context": T.TYPES[T.CONTEXT],
}
# Contract topics that a training dataset does not need (listed as unused, not as foreign).
KNOWN_UNUSED = (T.CONTEXT_FEATURES, T.BRIDGE_INFO, T.CLOCK, T.DIAGNOSTICS, "/rosout", "/parameter_events",
                "/tf", "/tf_static")


class DatasetError(RuntimeError):
    """No usable data, or a cache that cannot be written (with the reason)."""


class CacheWriteError(DatasetError):
    """Writing the on-disk frame cache failed (disk full, permission): nothing is skipped, the
    partial cache entry is removed and the logs themselves are untouched."""

    def __init__(self, where: Path, exc: OSError):
        super().__init__(f"writing the dataset cache under {where.parent} failed: {exc.strerror or exc}; "
                         "the partial entry was removed and the logs are untouched: free space or "
                         "point --cache-dir (PROTOCAD_CACHE_DIR) at a disk with room")


# ----------------------------------------------------------------------------- topic map
@dataclass(frozen=True)
class TopicMap:
    """Which topic carries what. ``context`` may be None (a log without the true context)."""

    image: str = T.topic_name(T.DEFAULT_NAMESPACE, T.IMAGE)
    step_info: str = T.topic_name(T.DEFAULT_NAMESPACE, T.STEP_INFO)
    action: str = T.topic_name(T.DEFAULT_NAMESPACE, T.ACTION)
    context: str | None = T.topic_name(T.DEFAULT_NAMESPACE, T.CONTEXT)

    @classmethod
    def for_namespace(cls, namespace: str = T.DEFAULT_NAMESPACE) -> "TopicMap":
        return cls(image=T.topic_name(namespace, T.IMAGE), step_info=T.topic_name(namespace, T.STEP_INFO),
                   action=T.topic_name(namespace, T.ACTION), context=T.topic_name(namespace, T.CONTEXT))

    @classmethod
    def parse(cls, mappings: Iterable[str] | None = None, namespace: str | None = None) -> "TopicMap":
        """From CLI strings ``KEY=/topic`` (KEY in image, step_info, action, context;
        ``context=none`` for logs without the true context)."""
        base = cls.for_namespace(namespace or T.DEFAULT_NAMESPACE)
        values = asdict(base)
        for item in mappings or []:
            key, sep, topic = item.partition("=")
            key = key.strip().replace("-", "_")
            if not sep or key not in TOPIC_KEYS:
                raise ValueError(f"--topic expects KEY=/topic with KEY one of {', '.join(TOPIC_KEYS)}; got {item!r}")
            topic = topic.strip()
            if topic.lower() in ("", "none", "-"):
                if key in REQUIRED_KEYS:
                    raise ValueError(f"--topic {key}: a {key} topic is required")
                values[key] = None
            else:
                values[key] = topic if topic.startswith("/") else "/" + topic
        return cls(**values)

    def as_dict(self) -> dict[str, str | None]:
        return asdict(self)

    def key_of(self, topic: str) -> str | None:
        for k, v in asdict(self).items():
            if v == topic:
                return k
        return None


# ----------------------------------------------------------------------------- sources
def find_sources(paths: Iterable[str | Path]) -> list[Path]:
    """Expand CLI paths into bags: a .mcap file, a directory with .mcap files in it (one bag),
    or a directory of such directories (searched recursively). Raises on paths with none."""
    out: list[Path] = []
    for p in paths:
        p = Path(p)
        if not p.exists():
            raise DatasetError(f"log path {p} does not exist")
        if p.is_file():
            if p.suffix != ".mcap":
                raise DatasetError(f"{p} is not an .mcap file (give a bag directory or .mcap files)")
            out.append(p)
            continue
        found = _bag_dirs(p)
        if not found:
            raise DatasetError(f"no .mcap files under {p}")
        out.extend(found)
    # unique, keep order
    seen, uniq = set(), []
    for s in out:
        r = s.resolve()
        if r not in seen:
            seen.add(r)
            uniq.append(s)
    return uniq


def _bag_dirs(d: Path) -> list[Path]:
    if any(f.suffix == ".mcap" and f.is_file() for f in d.iterdir()):
        return [d]
    out: list[Path] = []
    for sub in sorted(x for x in d.iterdir() if x.is_dir() and not x.name.startswith(".")):
        out.extend(_bag_dirs(sub))
    return out


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


def _entry_size(entry: Path) -> int:
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
    entries = [(e.stat().st_mtime, e, _entry_size(e)) for e in cache_dir.iterdir()
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


# ----------------------------------------------------------------------------- report
@dataclass
class SourceReport:
    """What one bag held and what was made of it."""

    path: str
    files: list[str] = field(default_factory=list)
    cached: bool = False
    ingest_seconds: float = 0.0
    truncated: list[str] = field(default_factory=list)
    read_errors: list[str] = field(default_factory=list)
    read_warnings: list[str] = field(default_factory=list)
    topics: dict[str, dict[str, Any]] = field(default_factory=dict)   # topic -> {type, count, used_as}
    foreign_topics: dict[str, dict[str, Any]] = field(default_factory=dict)  # present, unused, not contract
    unused_contract_topics: dict[str, int] = field(default_factory=dict)
    missing_topics: list[str] = field(default_factory=list)            # mapped but absent
    type_errors: list[str] = field(default_factory=list)
    decode_errors: dict[str, int] = field(default_factory=dict)
    decode_error_examples: list[str] = field(default_factory=list)
    duplicates: dict[str, int] = field(default_factory=dict)           # topic -> extra copies dropped
    steps: int = 0
    episodes: int = 0
    complete_episodes: int = 0          # is_first ... is_last all present without gaps
    episodes_without_first: int = 0     # recording started mid-episode
    segments: int = 0
    gaps: int = 0
    missing_step_ids: int = 0
    gap_examples: list[str] = field(default_factory=list)
    out_of_order: int = 0
    images_without_step_info: int = 0
    step_info_without_image: int = 0
    missing_actions: int = 0            # non-final observations whose answer is missing (break)
    unanswered_final: int = 0           # last observation of the log without an answer
    unanswered_is_last: int = 0         # is_last observations without an answer (harmless)
    orphan_actions: int = 0             # actions whose observation is not in the log
    image_shape: list[int] | None = None
    action_dim: int | None = None
    action_names: list[str] | None = None
    context_names: list[str] | None = None
    rejected: str | None = None         # why the whole bag is unusable (None = usable)
    # What the recorder reported in metadata.yaml custom_data (protocad_* keys): messages lost
    # before it took them, published before it subscribed, a write error that ended the bag.
    recording_losses: dict[str, str] = field(default_factory=dict)

    def problems(self) -> list[str]:
        p = []
        if self.rejected:
            p.append(f"REJECTED: {self.rejected}")
        for f in self.truncated:
            p.append(f"TRUNCATED {f} (every complete chunk before the cut was read)")
        p += [f"read error: {e}" for e in self.read_errors]
        p += [f"warning: {w}" for w in self.read_warnings]
        p += [f"type error: {e}" for e in self.type_errors]
        if self.missing_topics:
            p.append(f"mapped topics absent from the log: {', '.join(self.missing_topics)}")
        for t, n in self.decode_errors.items():
            p.append(f"{n} message(s) on {t} could not be decoded/used")
        p += [f"  e.g. {e}" for e in self.decode_error_examples[:3]]
        for t, n in self.duplicates.items():
            if n:
                p.append(f"{n} duplicate message(s) on {t} (same stamp again; first kept)")
        if self.gaps:
            p.append(f"{self.gaps} gap(s) within episodes, {self.missing_step_ids} step id(s) missing: "
                     + "; ".join(self.gap_examples[:5]) + (" ..." if len(self.gap_examples) > 5 else ""))
        if self.out_of_order:
            p.append(f"{self.out_of_order} step id(s) out of order within an episode (segment split)")
        if self.images_without_step_info:
            p.append(f"{self.images_without_step_info} image(s) without step_info at the same stamp (dropped)")
        if self.step_info_without_image:
            p.append(f"{self.step_info_without_image} step_info message(s) without an image (dropped)")
        if self.missing_actions:
            p.append(f"{self.missing_actions} observation(s) without an action answering them (segment split)")
        if self.orphan_actions:
            p.append(f"{self.orphan_actions} action(s) whose observation is not in the log")
        for key, value in self.recording_losses.items():
            # What a long-lived writer published before this bag's recorder started (the loop's
            # policy, whose earlier answers are in the previous bag) is no loss in this bag.
            if key != "protocad_missed_before_subscribing":
                p.append(f"the recorder reported {key[len('protocad_'):].replace('_', ' ')}: {value}")
        if self.foreign_topics:
            p.append("foreign topics (present, unused): " + ", ".join(
                f"{t} [{v['type']}] x{v['count']}" for t, v in self.foreign_topics.items()))
        return p


@dataclass
class DatasetReport:
    sources: list[SourceReport] = field(default_factory=list)
    seq_len: int = 0
    short_segments_skipped: int = 0
    short_steps_skipped: int = 0
    windows: int = 0

    @property
    def steps(self) -> int:
        return sum(s.steps for s in self.sources if not s.rejected)

    @property
    def episodes(self) -> int:
        return sum(s.episodes for s in self.sources if not s.rejected)

    @property
    def truncated(self) -> list[str]:
        return [f for s in self.sources for f in s.truncated]

    @property
    def duplicates(self) -> int:
        return sum(n for s in self.sources for n in s.duplicates.values())

    @property
    def gaps(self) -> int:
        return sum(s.gaps for s in self.sources)

    @property
    def foreign_topics(self) -> dict[str, dict]:
        out: dict[str, dict] = {}
        for s in self.sources:
            for t, v in s.foreign_topics.items():
                o = out.setdefault(t, {"type": v["type"], "count": 0})
                o["count"] += v["count"]
        return out

    def problems(self) -> list[str]:
        return [f"{Path(s.path).name}: {p}" for s in self.sources for p in s.problems()]

    def to_dict(self) -> dict:
        d = asdict(self)
        d.update(steps=self.steps, episodes=self.episodes)
        return d

    def summary(self, verbose: bool = False) -> str:
        lines = [f"MCAP dataset: {len(self.sources)} bag(s), {self.steps} steps, {self.episodes} episodes, "
                 f"{self.windows} training windows of length {self.seq_len}"]
        for s in self.sources:
            status = "REJECTED" if s.rejected else ("cached" if s.cached else f"indexed in {s.ingest_seconds:.1f}s")
            lines.append(f"  {s.path}  [{len(s.files)} file(s), {status}]")
            if not s.rejected:
                lines.append(f"    {s.steps} steps, {s.episodes} episodes ({s.complete_episodes} complete, "
                             f"{s.episodes_without_first} started mid-way), {s.segments} segments; "
                             f"image {s.image_shape}, action dim {s.action_dim}"
                             + (f", context {s.context_names}" if s.context_names else ", no context topic"))
            used = [f"{t} as {v['used_as']} x{v['count']}" for t, v in s.topics.items() if v.get("used_as")]
            if used:
                lines.append("    topics: " + ", ".join(used))
            if s.unused_contract_topics and verbose:
                lines.append("    unused contract topics: " + ", ".join(
                    f"{t} x{n}" for t, n in s.unused_contract_topics.items() if n))
            if s.unanswered_final or s.unanswered_is_last:
                lines.append(f"    unanswered observations: {s.unanswered_final} final (log ended), "
                             f"{s.unanswered_is_last} is_last (answer not needed)")
            for p in s.problems():
                lines.append(f"    ! {p}")
        if self.short_segments_skipped:
            lines.append(f"  skipped {self.short_segments_skipped} episode segment(s) shorter than {self.seq_len} "
                         f"steps ({self.short_steps_skipped} steps)")
        probs = self.problems()
        lines.append(f"  {'no problems found' if not probs else str(len(probs)) + ' problem line(s) above'}")
        return "\n".join(lines)

    __str__ = summary


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


def _ingest(source: Path, topics: TopicMap, entry: Path) -> None:
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
    except (OSError, yaml.YAMLError, AttributeError):
        return {}
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
                                      "protocad_loss_untracked_topics"):
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


def _ingest_into(source: Path, topics: TopicMap, tmp: Path) -> None:
    from trainer import mcap_io

    t0 = time.monotonic()
    rep = SourceReport(path=str(source), files=[str(f) for f in source_files(source)])
    by_key = {k: v for k, v in topics.as_dict().items() if v}
    key_of = {v: k for k, v in by_key.items()}

    img_stamps, seen_img = array("q"), set()
    si_stamps, si_vals = array("q"), array("d")
    act_stamps, act_vals = array("q"), array("d")
    ctx_stamps, ctx_vals = array("q"), array("d")
    counts: dict[str, int] = {}
    types: dict[str, str] = {}
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

    br = reader.report
    counts.update(br.counts)
    types.update(br.topic_types)
    rep.truncated = [f"{f}: {why}" for f, why in br.truncated.items()]
    rep.read_errors += [f"{f}: {why}" for f, why in br.errors.items()]
    rep.read_warnings = list(br.warnings)
    for t, n in counts.items():
        rep.topics[t] = {"type": types.get(t, "?"), "count": n, "used_as": key_of.get(t)}
        if t in key_of:
            continue
        rel = t[len(T.DEFAULT_NAMESPACE):].lstrip("/") if t.startswith(T.DEFAULT_NAMESPACE + "/") else t
        if t in KNOWN_UNUSED or rel in KNOWN_UNUSED or t.rsplit("/", 1)[-1] in KNOWN_UNUSED:
            rep.unused_contract_topics[t] = n
        else:
            rep.foreign_topics[t] = {"type": types.get(t, "?"), "count": n}
    rep.missing_topics = [f"{k}={v}" for k, v in by_key.items() if v not in counts]
    rep.decode_errors = dec_err
    rep.recording_losses = recorder_losses(source, used=key_of)
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


# ----------------------------------------------------------------------------- dataset
BATCH_KEYS = ("image", "action", "reward", "discount", "is_first")


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
                 verbose: bool = False, cache_budget_gb: float | None = None):
        self.topics = topics or TopicMap()
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
            key = cache_key(src, topics)
            entry = self.cache_dir / key
            cached = (entry / "index.json").exists()
            if cached:
                try:
                    store = SourceStore(entry)
                except Exception:  # noqa: BLE001 - corrupt cache entry: rebuild it
                    shutil.rmtree(entry, ignore_errors=True)
                    cached = False
            if not cached:
                if self.verbose:
                    print(f"[dataset] indexing {src} ...", file=sys.stderr, flush=True)
                entry.parent.mkdir(parents=True, exist_ok=True)
                _ingest(src, topics, entry)
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
            used = sum(_entry_size(st.entry) for st in self.stores)
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
    """`python -m trainer.dataset LOGS... [--topic k=/t]`: index logs and print the report."""
    import argparse

    ap = argparse.ArgumentParser(prog="python -m trainer.dataset", description=main.__doc__)
    ap.add_argument("logs", nargs="+", help="bag directories, .mcap files or folders of bags")
    ap.add_argument("--topic", action="append", default=[], metavar="KEY=/TOPIC",
                    help="topic mapping for foreign logs (image, step_info, action, context)")
    ap.add_argument("--namespace", default=None, help="namespace of the contract topics (default /protocad)")
    ap.add_argument("--seq-len", type=int, default=50)
    ap.add_argument("--cache-dir", default=None)
    ap.add_argument("--json", default=None, help="also write the report as JSON here")
    a = ap.parse_args(argv)
    ds = MCAPDataset(a.logs, topics=TopicMap.parse(a.topic, a.namespace), seq_len=a.seq_len,
                     cache_dir=a.cache_dir, verbose=True)
    print(ds.report.summary(verbose=True))
    if a.json:
        Path(a.json).write_text(json.dumps(ds.report.to_dict(), indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
