"""What the dataset reads and what it reports (trainer/data/dataset.py): the topic map, the errors, and
the per-source and whole-dataset reports."""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Iterable

from sim_bridge.contract import topics as T
from sim_bridge.contract.camera import Crop

STORE_VERSION = 1
#: metadata.yaml custom_data key the recorder writes: {topic: most publishers matched at once}
#: for every recorded topic that had more than one (protocad-train refuses such bags).
MULTIPLE_PUBLISHERS_KEY = "protocad_multiple_publishers"
SMALL_STORE_STEPS = 200_000    # stores with more steps keep even their per-step arrays on disk
REQUIRED_KEYS = ("image", "step_info", "action")
TOPIC_KEYS = ("image", "step_info", "action", "context")
#: The types taken per key, the contract's first: a camera's frames may come compressed (any
#: size and common encoding: every frame goes through sim_bridge.contract.camera.model_image).
EXPECTED_TYPES = {
    "image": (T.TYPES[T.IMAGE], "sensor_msgs/msg/CompressedImage"),
    "step_info": (T.TYPES[T.STEP_INFO],),
    "action": (T.TYPES[T.ACTION],),
    "context": (T.TYPES[T.CONTEXT],),
}
#: The model's image size (protocad_ros.model.config: train.image_size) and the part of a
#: camera's frame it sees, unless a dataset is told otherwise.
DEFAULT_IMAGE_SIZE = 64
DEFAULT_CROP = "center"


@dataclass(frozen=True)
class ImageSpec:
    """What every frame becomes in the store: `camera.model_image(msg, size, crop)`, so a bag of
    a robot's camera (any size, encoding, JPEG/PNG) trains on what its policy will see."""

    size: int = DEFAULT_IMAGE_SIZE
    crop: str = DEFAULT_CROP

    def __post_init__(self):
        if not isinstance(self.size, int) or isinstance(self.size, bool) or self.size < 1:
            raise ValueError(f"image size must be a positive integer, got {self.size!r}")
        object.__setattr__(self, "crop", str(Crop.parse(self.crop)))   # ValueError naming it

    @property
    def is_default(self) -> bool:
        return (self.size, self.crop) == (DEFAULT_IMAGE_SIZE, DEFAULT_CROP)
# Contract topics that a training dataset does not need (listed as unused, not as foreign).
KNOWN_UNUSED = (T.CONTEXT_FEATURES, T.BRIDGE_INFO, T.CLOCK, T.DIAGNOSTICS, "/rosout", "/parameter_events",
                "/tf", "/tf_static")

#: Bags (or files) with one and the same problem that a report lists by name; the rest are counted.
SAME_PROBLEM_SHOWN = 3


def summarise_repeats(kind: str, entries: Iterable[str]) -> list[str]:
    """'KIND: PATH: reason' lines, those sharing a reason folded into one line beyond
    SAME_PROBLEM_SHOWN of them ('read error: empty file (0 bytes) in 1000 files, e.g. ...')."""
    by_reason: dict[str, list[str]] = {}
    for e in entries:
        path, sep, reason = e.partition(": ")
        by_reason.setdefault(reason if sep else e, []).append(path if sep else "")
    out = []
    for reason, paths in by_reason.items():
        if len(paths) <= SAME_PROBLEM_SHOWN or not all(paths):
            out += [f"{kind}: {p}: {reason}" if p else f"{kind}: {reason}" for p in paths]
        else:
            names = ", ".join(Path(p).name for p in paths[:SAME_PROBLEM_SHOWN])
            out.append(f"{kind}: {reason} in {len(paths)} files, e.g. {names}, ...")
    return out


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
        p += summarise_repeats("read error", self.read_errors)
        p += summarise_repeats("warning", self.read_warnings)
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
        # Bags rejected for the same reason are listed SAME_PROBLEM_SHOWN times, then counted:
        # 1,000 empty files are three lines and a count, not 2,000 lines.
        same: dict[tuple[str, ...], int] = {}
        hidden: dict[tuple[str, ...], int] = {}
        for s in self.sources:
            if s.rejected:
                key = tuple(s.problems())
                same[key] = same.get(key, 0) + 1
                if same[key] > SAME_PROBLEM_SHOWN:
                    hidden[key] = hidden.get(key, 0) + 1
                    continue
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
        for key, n in hidden.items():
            lines.append(f"  ... and {n} more bag(s) rejected for the same reason"
                         + (f": {key[0]}" if key else ""))
        if self.short_segments_skipped:
            lines.append(f"  skipped {self.short_segments_skipped} episode segment(s) shorter than {self.seq_len} "
                         f"steps ({self.short_steps_skipped} steps)")
        probs = self.problems()
        lines.append(f"  {'no problems found' if not probs else str(len(probs)) + ' problem line(s) above'}")
        return "\n".join(lines)

    __str__ = summary
