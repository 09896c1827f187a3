"""The topic contract shared by every node, the recorder, the dataset and the in-process writer.

Only common_interfaces types exist here (no custom message build), so stamped named vectors
travel as ``sensor_msgs/JointState``: ``name[i]`` labels ``position[i]`` (or ``effort[i]`` for
actions). msgs_docs/topics.md is the human-readable version of this module.

The helpers below are duck-typed: they fill or read rclpy messages and rosbags dataclasses
alike (same field names), so the ROS path and the ROS-free path write identical bytes.
No rclpy import at module level.
"""
from __future__ import annotations

import functools
import hashlib
import json
import math
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np

DEFAULT_NAMESPACE = "/protocad"

# Relative names (resolved in the node's namespace, default /protocad).
IMAGE = "image"                    # sensor_msgs/msg/Image, rgb8, 64x64
STEP_INFO = "step_info"            # sensor_msgs/msg/JointState, fields STEP_INFO_FIELDS
CONTEXT = "context"                # sensor_msgs/msg/JointState, the true context (eval/plots only)
ACTION = "action"                  # sensor_msgs/msg/JointState, effort = action
CONTEXT_FEATURES = "context_features"  # sensor_msgs/msg/JointState, u/w/e from the policy
BRIDGE_INFO = "bridge_info"        # sensor_msgs/msg/JointState, transient local: what the bridge runs
RESET_SERVICE = "reset"            # std_srvs/srv/Trigger on the sim bridge
# Not in TYPES (the loop's topics, which every bag of a run holds): checkpoints over ROS.
CHECKPOINT = "checkpoint"          # std_msgs/msg/String, JSON announcement, transient local
CHUNKS_SUFFIX = "/chunks"          # <announcement topic>/chunks: std_msgs/msg/UInt8MultiArray
CLOCK = "/clock"                   # rosgraph_msgs/msg/Clock (sim time)
DIAGNOSTICS = "/diagnostics"       # diagnostic_msgs/msg/DiagnosticArray

TYPES = {
    IMAGE: "sensor_msgs/msg/Image",
    STEP_INFO: "sensor_msgs/msg/JointState",
    CONTEXT: "sensor_msgs/msg/JointState",
    ACTION: "sensor_msgs/msg/JointState",
    CONTEXT_FEATURES: "sensor_msgs/msg/JointState",
    BRIDGE_INFO: "sensor_msgs/msg/JointState",
    CLOCK: "rosgraph_msgs/msg/Clock",
    DIAGNOSTICS: "diagnostic_msgs/msg/DiagnosticArray",
}

IMAGE_FRAME_ID = "camera"
STEP_INFO_FIELDS = ("reward", "discount", "is_first", "is_last", "is_terminal", "episode", "step")
#: Sent by the sim bridge after the fields above, read when present: the episode's return so far
#: (on the is_last step, the episode's return). Other publishers may leave it out.
STEP_INFO_RETURN = "episode_return"
SPLIT_FIELD = "split"  # in CONTEXT: 0.0 = train split, 1.0 = test split
SPLITS = ("train", "test")


def clock_topic(namespace: str) -> str:
    """Where a sim bridge in `namespace` publishes sim time (its clock_topic left empty):
    /clock in the default namespace, NS/clock elsewhere, so bridges in two namespaces never
    interleave two sim times on one topic. Recorders and launchers look for it here too."""
    ns = "/" + namespace.strip("/")
    return CLOCK if ns in ("/", DEFAULT_NAMESPACE) else topic_name(ns, "clock")


def contract_topic_type(topic: str, namespace: str = DEFAULT_NAMESPACE, *, nested: bool = False) -> str | None:
    """The type the contract gives `topic` as seen from `namespace` (None: not a contract topic):
    /diagnostics, /clock or the namespace's clock topic, or a relative contract name (image,
    step_info, ...) in the namespace; nested=True also in any namespace below it (a recorder of
    a fleet's robots)."""
    if topic in (CLOCK, clock_topic(namespace)):
        return TYPES[CLOCK]
    if topic == DIAGNOSTICS:
        return TYPES[DIAGNOSTICS]
    parent, _, name = topic.rpartition("/")
    ns = "/" + namespace.strip("/") if namespace.strip("/") else ""
    if parent == ns or (nested and parent.startswith(ns + "/")):
        return TYPES[CLOCK] if name == "clock" else TYPES.get(name)
    return None


def topic_name(namespace: str, relative: str) -> str:
    """Fully qualified topic name, e.g. ('/protocad', 'image') -> '/protocad/image'."""
    if relative.startswith("/"):
        return relative
    ns = "/" + namespace.strip("/") if namespace.strip("/") else ""
    return f"{ns}/{relative}"


def stamp_to_ns(stamp: Any) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def format_stamp(t_ns: int | None) -> str:
    """A stamp (sim time in ns) for log lines: 2480000000 -> '2.48 s', exact to the ns."""
    if t_ns is None:
        return "none"
    sec, ns = divmod(int(t_ns), 1_000_000_000)
    return f"{sec}.{(f'{ns:09d}'.rstrip('0') or '0')} s"


def set_stamp(stamp: Any, t_ns: int) -> None:
    stamp.sec, stamp.nanosec = divmod(int(t_ns), 1_000_000_000)


@dataclass
class StepInfo:
    reward: float
    discount: float
    is_first: bool
    is_last: bool
    is_terminal: bool
    episode: int
    step: int
    episode_return: float | None = None   # STEP_INFO_RETURN: optional


def fill_image(msg: Any, image: np.ndarray, t_ns: int) -> Any:
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"expected an HxWx3 uint8 RGB image, got {image.dtype} {image.shape}")
    set_stamp(msg.header.stamp, t_ns)
    msg.header.frame_id = IMAGE_FRAME_ID
    msg.height, msg.width = int(image.shape[0]), int(image.shape[1])
    msg.encoding = "rgb8"
    msg.is_bigendian = 0
    msg.step = int(image.shape[1]) * 3
    data = np.ascontiguousarray(image).reshape(-1)
    msg.data = data if isinstance(getattr(msg, "data", None), np.ndarray) else data.tobytes()
    return msg


def read_image(msg: Any, expected_hw: tuple[int, int] | None = None) -> np.ndarray:
    """HxWx3 uint8 array from an Image message; ValueError with the reason if it is not rgb8."""
    if msg.encoding != "rgb8":
        raise ValueError(f"image encoding {msg.encoding!r}, expected 'rgb8'")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    # Sizes first: an oversized or lying payload is refused before a byte of it is copied.
    size = _payload_size(msg.data)
    if step < w * 3 or size != h * step:
        raise ValueError(f"image data has {size} bytes, expected {h}x{step} (width {w}, rgb8)")
    if expected_hw is not None and (h, w) != tuple(expected_hw):
        raise ValueError(f"image is {h}x{w}, expected {expected_hw[0]}x{expected_hw[1]}")
    return uint8_view(msg.data).reshape(h, step)[:, : w * 3].reshape(h, w, 3)


def _payload_size(data: Any) -> int:
    """Bytes in a uint8[] field (rclpy's array.array, bytes, an ndarray, a list), uncopied."""
    return int(data.nbytes) if isinstance(data, np.ndarray) else len(data)


def uint8_view(data: Any) -> np.ndarray:
    """A flat uint8 array over the payload: no copy where it exposes a buffer (rclpy's
    array.array, bytes, ndarrays); a list (some decoders) is converted."""
    if isinstance(data, np.ndarray):
        return data.reshape(-1).view(np.uint8)
    try:
        return np.frombuffer(data, np.uint8)
    except TypeError:
        try:
            return np.asarray(data, np.uint8).reshape(-1)
        except (OverflowError, TypeError) as exc:
            raise ValueError(f"image data is not bytes: {exc}") from None


def fill_named(msg: Any, names: Sequence[str], values: Sequence[float], t_ns: int,
               field: str = "position", frame_id: str = "") -> Any:
    """Fill a JointState used as a stamped named vector (values in `position` or `effort`)."""
    if len(names) != len(values):
        raise ValueError(f"{len(names)} names for {len(values)} values")
    set_stamp(msg.header.stamp, t_ns)
    msg.header.frame_id = frame_id
    msg.name = list(names)
    arr = np.asarray(values, dtype=np.float64).reshape(-1)
    empty = np.zeros(0, np.float64)
    for f in ("position", "velocity", "effort"):
        val = arr if f == field else empty
        setattr(msg, f, val if isinstance(getattr(msg, f, None), np.ndarray) else val.tolist())
    return msg


def read_named(msg: Any, field: str = "position") -> dict[str, float]:
    """{name: value} of a JointState used as a named vector; ValueError if the lengths differ
    or a name repeats (values may be any float: each reader says which it accepts)."""
    values = list(getattr(msg, field))
    if len(values) != len(msg.name):
        raise ValueError(f"JointState has {len(msg.name)} names but {len(values)} {field} values")
    out = {str(n): float(v) for n, v in zip(msg.name, values)}
    if len(out) != len(values):
        raise ValueError(f"JointState names repeat: {sorted(n for n in out if list(msg.name).count(n) > 1)}")
    return out


MAX_COUNT = 2 ** 53   # episode and step counters: exact in the float64 they travel as


def _flag(d: Mapping[str, float], name: str) -> bool:
    v = d[name]
    if v not in (0.0, 1.0):   # NaN included: a flag that is neither 0 nor 1 means nothing
        raise ValueError(f"step_info {name} must be 0 or 1, got {v!r}")
    return v == 1.0


def _count(d: Mapping[str, float], name: str) -> int:
    v = d[name]
    if not (math.isfinite(v) and v == int(v) and 0 <= v < MAX_COUNT):
        raise ValueError(f"step_info {name} must be a whole number in [0, 2^53), got {v!r}")
    return int(v)


def fill_step_info(msg: Any, info: StepInfo, t_ns: int) -> Any:
    names, values = list(STEP_INFO_FIELDS), [float(getattr(info, f)) for f in STEP_INFO_FIELDS]
    if info.episode_return is not None:
        names.append(STEP_INFO_RETURN)
        values.append(float(info.episode_return))
    return fill_named(msg, names, values, t_ns)


def read_step_info(msg: Any) -> StepInfo:
    d = read_named(msg)
    missing = [f for f in STEP_INFO_FIELDS if f not in d]
    if missing:
        raise ValueError(f"step_info lacks fields {missing}")
    if not math.isfinite(d["reward"]):
        raise ValueError(f"step_info reward is not finite: {d['reward']!r}")
    if not (math.isfinite(d["discount"]) and 0.0 <= d["discount"] <= 1.0):
        raise ValueError(f"step_info discount must be in [0, 1], got {d['discount']!r}")
    ret = d.get(STEP_INFO_RETURN)
    return StepInfo(reward=d["reward"], discount=d["discount"], is_first=_flag(d, "is_first"),
                    is_last=_flag(d, "is_last"), is_terminal=_flag(d, "is_terminal"),
                    episode=_count(d, "episode"), step=_count(d, "step"),
                    episode_return=float(ret) if ret is not None and math.isfinite(ret) else None)


def fill_context(msg: Any, context: Mapping[str, float], split: str, t_ns: int) -> Any:
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r}; valid: {SPLITS}")
    names = list(context) + [SPLIT_FIELD]
    return fill_named(msg, names, [float(context[k]) for k in context] + [float(SPLITS.index(split))], t_ns)


def read_context(msg: Any) -> tuple[dict[str, float], str]:
    """(context, split); ValueError for a split code other than 0/1 or a non-finite value."""
    d = read_named(msg)
    code = d.pop(SPLIT_FIELD, 0.0)
    if code not in (0.0, 1.0):
        raise ValueError(f"context {SPLIT_FIELD} must be 0 (train) or 1 (test), got {code!r}")
    bad = {k: v for k, v in d.items() if not math.isfinite(v)}
    if bad:
        raise ValueError(f"context values are not finite: {bad}")
    return d, SPLITS[int(code)]


def fill_action(msg: Any, action: Sequence[float], names: Sequence[str], t_ns: int) -> Any:
    """`t_ns` is the stamp of the observation this action answers."""
    return fill_named(msg, names, action, t_ns, field="effort")


def read_action(msg: Any) -> np.ndarray:
    if len(msg.effort) != len(msg.name):
        raise ValueError(f"action has {len(msg.name)} names but {len(msg.effort)} effort values")
    return np.asarray(msg.effort, dtype=np.float64)


@dataclass
class BridgeInfo:
    """What a sim bridge runs, announced once (transient local) so that a policy can refuse a
    bridge its checkpoint does not fit before answering anything."""

    task: str
    action_names: list[str]
    control_dt: float
    image_size: int


def fill_bridge_info(msg: Any, info: BridgeInfo, t_ns: int = 0) -> Any:
    """header.frame_id = task, name = the action names in order, position = [control_dt,
    image_size] under the names '@control_dt', '@image_size' appended after the actions."""
    fill_named(msg, list(info.action_names) + ["@control_dt", "@image_size"],
               [0.0] * len(info.action_names) + [float(info.control_dt), float(info.image_size)], t_ns,
               frame_id=info.task)
    return msg


def read_bridge_info(msg: Any) -> BridgeInfo:
    d = read_named(msg)
    if "@control_dt" not in d or "@image_size" not in d or not msg.header.frame_id:
        raise ValueError("bridge_info lacks the task (frame_id), @control_dt or @image_size")
    names = [n for n in msg.name if not str(n).startswith("@")]
    size = d["@image_size"]
    if not (math.isfinite(d["@control_dt"]) and math.isfinite(size) and size == int(size) and size > 0):
        raise ValueError(f"bridge_info values are not usable: {d}")
    return BridgeInfo(str(msg.header.frame_id), [str(n) for n in names], d["@control_dt"], int(size))


@functools.lru_cache(maxsize=16)
def _feature_names(proj_dim: int, num_prototypes: int, proto_dim: int) -> tuple[str, ...]:
    return tuple([f"u/{i}" for i in range(proj_dim)] + [f"w/{k}" for k in range(num_prototypes)]
                 + [f"e/{i}" for i in range(proto_dim)])


def context_feature_names(proj_dim: int, num_prototypes: int, proto_dim: int) -> list[str]:
    """u/0.., w/0.., e/0..: the same few hundred names every step, built once (they were a
    measurable share of the policy node's step)."""
    return list(_feature_names(proj_dim, num_prototypes, proto_dim))


def fill_context_features(msg: Any, u: np.ndarray, w: np.ndarray, e: np.ndarray, t_ns: int) -> Any:
    names = context_feature_names(len(u), len(w), len(e))
    return fill_named(msg, names, np.concatenate([u, w, e]).astype(np.float64), t_ns)


def read_context_features(msg: Any) -> dict[str, np.ndarray]:
    d = read_named(msg)
    out: dict[str, list[float]] = {"u": [], "w": [], "e": []}
    for name, v in d.items():
        key, _, _ = name.partition("/")
        if key in out:
            out[key].append(v)
    return {k: np.asarray(v, np.float32) for k, v in out.items()}


# ---------------------------------------------------------------------- checkpoint delivery
ANNOUNCEMENT_FORMAT = "protocad-ros/checkpoint-announcement"
DEFAULT_CHUNK_SIZE = 1 << 20
#: The chunk sizes a publisher may use (its chunk_size parameter's range); a receiver refuses others.
MIN_CHUNK_SIZE, MAX_CHUNK_SIZE = 4096, 64 << 20
#: At most this many chunks per version: the per-chunk hashes travel in the announcement.
MAX_CHUNKS = 16384
#: An announcement longer than this is not read (16384 chunk hashes take about 1.1 MB).
MAX_ANNOUNCEMENT_CHARS = 2 << 20


def chunks_topic(announcement_topic: str) -> str:
    """Where the bytes of the versions announced on `announcement_topic` travel."""
    return announcement_topic.rstrip("/") + CHUNKS_SUFFIX


@dataclass
class CheckpointAnnouncement:
    """One checkpoint version, announced (latched) before anyone fetches it. A version is
    its content: `sha256` of the file's bytes is its identity (logs show `short_id`).
    chunk_sha256: the sha256 of each chunk (empty from senders that do not send them), so a
    receiver checks every chunk on arrival; key_id + signature: the learner's Ed25519 signature
    (protocad_ros.checkpoint.signing.Manifest; empty: unsigned)."""

    sha256: str
    size: int
    chunk_size: int
    n_chunks: int
    updates: int = -1
    task: str = ""
    variant: str = ""
    preset: str = ""
    seq: int = 0                      # grows with every version (signed: no rollback)
    counters: dict = field(default_factory=dict)   # the trainer's (env steps, ...)
    chunk_sha256: tuple = ()
    key_id: str = ""
    signature: str = ""

    @property
    def short_id(self) -> str:
        return self.sha256[:12]

    def chunk_length(self, index: int) -> int:
        """Bytes chunk `index` must carry: chunk_size, the last one the remainder."""
        return self.chunk_size if index < self.n_chunks - 1 else self.size - self.chunk_size * (self.n_chunks - 1)


def checkpoint_announcement_json(a: CheckpointAnnouncement) -> str:
    return json.dumps({"format": ANNOUNCEMENT_FORMAT, "sha256": a.sha256, "size": a.size,
                       "chunk_size": a.chunk_size, "n_chunks": a.n_chunks, "updates": a.updates,
                       "task": a.task, "variant": a.variant, "preset": a.preset, "seq": a.seq,
                       "counters": dict(a.counters), "chunk_sha256": list(a.chunk_sha256),
                       "key_id": a.key_id, "signature": a.signature}, sort_keys=True)


def _whole(d: Mapping[str, Any], key: str, lo: int) -> int:
    v = d.get(key)
    if isinstance(v, bool) or not isinstance(v, int) or v < lo:
        raise ValueError(f"{key} must be a whole number >= {lo}, got {v!r}")
    return v


def _is_sha256(v: Any) -> bool:
    return isinstance(v, str) and len(v) == 64 and all(c in "0123456789abcdef" for c in v)


def read_checkpoint_announcement(text: str) -> CheckpointAnnouncement:
    """Parse an announcement; ValueError saying what is wrong (too long, not JSON, another
    format, a field missing or impossible: n_chunks must be exactly what size and chunk_size
    give, chunk hashes one per chunk). Sizes are not bounded here: that is the receiver's
    choice (max_checkpoint_bytes)."""
    if len(text) > MAX_ANNOUNCEMENT_CHARS:
        raise ValueError(f"{len(text)} characters, more than {MAX_ANNOUNCEMENT_CHARS}")
    try:
        d = json.loads(text)
    except ValueError as e:
        raise ValueError(f"not JSON ({e})") from None
    if not isinstance(d, dict) or d.get("format") != ANNOUNCEMENT_FORMAT:
        raise ValueError(f"format is not {ANNOUNCEMENT_FORMAT!r}")
    sha = d.get("sha256")
    if not _is_sha256(sha):
        raise ValueError(f"sha256 must be 64 lower-case hex digits, got {sha!r}")
    size, chunk = _whole(d, "size", 1), _whole(d, "chunk_size", 1)
    n = _whole(d, "n_chunks", 1)
    if n != -(-size // chunk):
        raise ValueError(f"n_chunks={n} does not match size={size} in chunks of {chunk}")
    counters = d.get("counters") or {}
    if not isinstance(counters, dict):
        raise ValueError("counters must be an object")
    hashes = d.get("chunk_sha256") or []
    if not isinstance(hashes, list) or not all(_is_sha256(h) for h in hashes):
        raise ValueError("chunk_sha256 must be a list of sha256 hex digests")
    if hashes and len(hashes) != n:
        raise ValueError(f"{len(hashes)} chunk hashes for n_chunks={n}")
    key_id, signature = d.get("key_id") or "", d.get("signature") or ""
    if not (isinstance(key_id, str) and isinstance(signature, str)):
        raise ValueError("key_id and signature must be strings")
    updates, seq = d.get("updates", -1), d.get("seq", 0)
    # Informative fields: a sender may leave them out, never make a version unusable (signed
    # ones are checked by the signature, which covers what was read here).
    return CheckpointAnnouncement(sha, size, chunk, n, updates if type(updates) is int else -1,
                                  str(d.get("task", "")), str(d.get("variant", "")),
                                  str(d.get("preset", "")), seq if type(seq) is int else 0, counters,
                                  tuple(hashes), key_id, signature)


def describe_checkpoint(data: bytes, chunk_size: int, *, chunk_hashes: bool = True,
                        **fields: Any) -> CheckpointAnnouncement:
    """The announcement of a file's bytes (sha256, size, chunking, per-chunk sha256) plus
    `fields`."""
    view, chunk_size = memoryview(data), int(chunk_size)
    hashes = tuple(hashlib.sha256(view[i:i + chunk_size]).hexdigest()
                   for i in range(0, len(view), chunk_size)) if chunk_hashes else ()
    return CheckpointAnnouncement(hashlib.sha256(data).hexdigest(), len(data), chunk_size,
                                  -(-len(data) // chunk_size), chunk_sha256=hashes, **fields)


def fill_checkpoint_chunk(msg: Any, sha256: str, index: int, n_chunks: int, data: bytes) -> Any:
    """layout.dim[0]: label '<sha256>:<index>/<n_chunks>' (which version, which piece), size =
    stride = len(data) (a plain 1-D byte array, as MultiArrayLayout means it)."""
    from std_msgs.msg import MultiArrayDimension

    msg.layout.dim = [MultiArrayDimension(label=f"{sha256}:{index}/{n_chunks}", size=len(data),
                                          stride=len(data))]
    msg.layout.data_offset = 0
    msg.data = data
    return msg


def read_checkpoint_chunk_label(msg: Any) -> tuple[str, int, int]:
    """(sha256, index, n_chunks) of a chunk, without copying its bytes; ValueError if its
    label is not ours."""
    if len(msg.layout.dim) != 1:
        raise ValueError(f"chunk layout has {len(msg.layout.dim)} dimensions, expected 1")
    sha, _, where = str(msg.layout.dim[0].label).partition(":")
    index, _, n = where.partition("/")
    if len(sha) != 64 or not index.isdigit() or not n.isdigit() or int(index) >= int(n):
        raise ValueError(f"chunk label {msg.layout.dim[0].label!r} is not '<sha256>:<index>/<n>'")
    return sha, int(index), int(n)

