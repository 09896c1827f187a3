"""The recorder's disk is a budget (trainer/nodes/recorder.py applies it; no ROS import here).

Any participant on the domain can publish on a recorded topic, so a flood (a stranger's
/diagnostics at 10 kHz, images at 100 MB/s) would otherwise fill the disk. Per message:
- a per-message size limit: a larger message is dropped and counted;
- a per-topic rate limit (token bucket, HZ with two seconds of burst) and byte-rate limit (bytes
  per second, the same way): messages above them are dropped and counted;
- a per-topic byte budget and a budget for the whole bag: a topic past its budget is no longer
  recorded (counted); the bag past its budget ends the recording (the recorder closes a valid
  bag and says so in one line);
- flood detection: a topic whose rate or byte rate in the last second is `flood_factor` times its
  recent figure (an average of the seconds before) and above a floor (FLOOD_MIN_HZ or
  FLOOD_MIN_BYTES_PER_S) is flagged once: in the bag's metadata and on /diagnostics; so is one
  offered more in a second than its bounds let through (or, without bounds, more than
  FLOOD_ABS_HZ / FLOOD_ABS_BYTES_PER_S), history or not.
The contract's topics are bounded by default (`contract_bounds`, declared once here: the CLI,
the node's parameters, the launch file's recorder and the launchers' take them from here); a
value of 0 given for a topic turns that bound off (the recorder says so in a WARNING).
The free-disk floor is the recorder's (DiskFloor): below it recording stops with a closed bag.
"""
from __future__ import annotations

import json
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping

from sim_bridge.contract import topics as T

#: Default free-disk floor (bytes): below it the recorder closes the bag and stops.
DEFAULT_MIN_FREE_DISK = 1 << 30
#: Default flood factor: a second this many times above the topic's recent rate is a flood.
DEFAULT_FLOOD_FACTOR = 10.0
#: A flood must also be above one of these (a topic going from 1 Hz to 10 Hz is no flood).
FLOOD_MIN_HZ = 100.0
FLOOD_MIN_BYTES_PER_S = 10 << 20
#: Seconds of history a recent figure needs before a jump from it counts.
FLOOD_WARMUP_S = 3
#: Seconds of burst a rate limit allows.
RATE_BURST_S = 2.0
#: A topic without bounds is flagged from its first second above these, history or not.
FLOOD_ABS_HZ = 5000.0
FLOOD_ABS_BYTES_PER_S = 64 << 20


@dataclass(frozen=True)
class TopicBounds:
    """One topic's default bounds (0: none): messages/s, bytes/s, bytes per message, bytes in
    the bag, and the seconds of burst the two rates allow."""
    rate_hz: float = 0.0
    bytes_per_s: float = 0.0
    message_bytes: int = 0
    budget_bytes: int = 0
    burst_s: float = RATE_BURST_S


#: The contract topics carry one message per agent step: twice the bridge's highest control
#: rate (control_rate_hz <= 1000 Hz) and above what lock-step reaches (933 env steps/s stepped
#: directly on the 2-core machine, msgs_docs/benchmarks.md).
STEP_TOPIC_RATE_HZ = 2000.0
#: Their burst: the backlog a stalled recorder receives at once (a KEEP_ALL reader's history
#: holds up to 5,000 samples per topic in Fast DDS, the writer as many): 10,000 messages.
STEP_TOPIC_BURST_S = 5.0
#: The model's image (64 x 64 rgb8, 12,288 bytes) and 4 KiB for the header and the CDR framing.
MODEL_IMAGE_BYTES = 64 * 64 * 3
IMAGE_MESSAGE_BYTES = MODEL_IMAGE_BYTES + (4 << 10)
#: 2.6 times a lock-step image stream at 1,000 steps/s (12.4 MB/s).
IMAGE_BYTES_PER_S = 32 << 20
#: step_info, context, action, bridge_info: a JointState of a handful of named values (~300 B).
STATUS_MESSAGE_BYTES = 16 << 10
STATUS_BYTES_PER_S = 4 << 20
#: context_features: u, w, e over the K prototypes (float64; room for K in the thousands).
FEATURES_MESSAGE_BYTES = 256 << 10
FEATURES_BYTES_PER_S = 32 << 20
#: /clock: a Clock is 12 bytes.
CLOCK_MESSAGE_BYTES = 1 << 10
#: /diagnostics is open to every participant and each of our nodes reports about once a
#: second: a rate-limited copy within a byte budget (what the launchers recorded before these
#: were the recorder's defaults), statuses of a few KiB each.
DIAGNOSTICS_RATE_LIMIT_HZ = 20.0
DIAGNOSTICS_BYTE_BUDGET = 64 << 20
DIAGNOSTICS_MESSAGE_BYTES = 32 << 10

_STEP = {"rate_hz": STEP_TOPIC_RATE_HZ, "burst_s": STEP_TOPIC_BURST_S}
#: Per contract topic (relative name; "clock" for the bridge's clock topic): its default bounds.
CONTRACT_BOUNDS: Mapping[str, TopicBounds] = {
    T.IMAGE: TopicBounds(bytes_per_s=IMAGE_BYTES_PER_S, message_bytes=IMAGE_MESSAGE_BYTES, **_STEP),
    **{name: TopicBounds(bytes_per_s=STATUS_BYTES_PER_S, message_bytes=STATUS_MESSAGE_BYTES, **_STEP)
       for name in (T.STEP_INFO, T.CONTEXT, T.ACTION, T.BRIDGE_INFO)},
    T.CONTEXT_FEATURES: TopicBounds(bytes_per_s=FEATURES_BYTES_PER_S, message_bytes=FEATURES_MESSAGE_BYTES, **_STEP),
    "clock": TopicBounds(bytes_per_s=STEP_TOPIC_RATE_HZ * CLOCK_MESSAGE_BYTES, message_bytes=CLOCK_MESSAGE_BYTES,
                         **_STEP),
}
DIAGNOSTICS_BOUNDS = TopicBounds(rate_hz=DIAGNOSTICS_RATE_LIMIT_HZ, message_bytes=DIAGNOSTICS_MESSAGE_BYTES,
                                 budget_bytes=DIAGNOSTICS_BYTE_BUDGET)


def contract_name(topic: str, namespace: str = T.DEFAULT_NAMESPACE) -> str | None:
    """The contract's name for `topic` (None: not a contract topic): /diagnostics, /clock, or a
    relative contract name (image, step_info, ..., clock) of a topic in `namespace` or a
    namespace below it (a fleet's robots)."""
    if topic in (T.DIAGNOSTICS, T.CLOCK):
        return topic
    parent, _, name = topic.rpartition("/")
    ns = "/" + namespace.strip("/") if namespace.strip("/") else ""
    if name in CONTRACT_BOUNDS and (parent == ns or parent.startswith(ns + "/")):
        return name
    return None


def contract_bounds(topic: str, namespace: str = T.DEFAULT_NAMESPACE) -> TopicBounds | None:
    """The default bounds of `topic` (None: none), a contract topic (contract_name)."""
    name = contract_name(topic, namespace)
    if name is None:
        return None
    return DIAGNOSTICS_BOUNDS if name == T.DIAGNOSTICS else CONTRACT_BOUNDS["clock" if name == T.CLOCK else name]


#: What the recorder writes into metadata.yaml custom_data.
DROPPED_KEY, FLOOD_KEY, BUDGET_KEY = "protocad_dropped_messages", "protocad_floods", "protocad_budget_stop"


def parse_topic_values(items: list[str] | tuple[str, ...], what: str) -> dict[str, float]:
    """['/diagnostics=5', ...] -> {'/diagnostics': 5.0} (ValueError naming a bad item)."""
    out: dict[str, float] = {}
    for item in items:
        topic, sep, value = str(item).rpartition("=")
        try:
            number = float(value)
        except ValueError:
            number = -1.0
        if not sep or not topic or number < 0:
            raise ValueError(f"{what} expects TOPIC=NUMBER (>= 0), got {item!r}")
        out[topic] = number
    return out


@dataclass
class BudgetLimits:
    """The limits (0: off). rates / topic_bytes / byte_rates / message_bytes: per-topic values
    (0 turns that bound off) over the contract's defaults in `namespace` (contract_bounds) and
    the values for every topic (max_topic_rate, max_topic_bytes: the stricter one applies)."""
    max_topic_rate: float = 0.0
    max_topic_bytes: int = 0
    max_total_bytes: int = 0
    flood_factor: float = DEFAULT_FLOOD_FACTOR
    rates: Mapping[str, float] = field(default_factory=dict)
    topic_bytes: Mapping[str, float] = field(default_factory=dict)
    byte_rates: Mapping[str, float] = field(default_factory=dict)
    message_bytes: Mapping[str, float] = field(default_factory=dict)
    namespace: str = T.DEFAULT_NAMESPACE

    def _value(self, topic: str, given: Mapping[str, float], field_name: str, everywhere: float = 0.0) -> float:
        if topic in given:
            return float(given[topic])
        bounds = contract_bounds(topic, self.namespace)
        default = float(getattr(bounds, field_name)) if bounds is not None else 0.0
        return min(v for v in (default, everywhere) if v > 0) if default > 0 or everywhere > 0 else 0.0

    def rate(self, topic: str) -> float:
        return self._value(topic, self.rates, "rate_hz", self.max_topic_rate)

    def bytes_for(self, topic: str) -> int:
        return int(self._value(topic, self.topic_bytes, "budget_bytes", self.max_topic_bytes))

    def byte_rate(self, topic: str) -> float:
        return self._value(topic, self.byte_rates, "bytes_per_s")

    def message_limit(self, topic: str) -> int:
        return int(self._value(topic, self.message_bytes, "message_bytes"))

    def burst_s(self, topic: str) -> float:
        bounds = contract_bounds(topic, self.namespace)
        return bounds.burst_s if bounds is not None else RATE_BURST_S

    def turned_off(self) -> list[str]:
        """'TOPIC: NAME' of each bound a given 0 turns off (the recorder warns about each)."""
        return [f"{t}: {name}" for name, given in (("rate limit", self.rates), ("byte budget", self.topic_bytes),
                                                  ("byte-rate limit", self.byte_rates),
                                                  ("message size limit", self.message_bytes))
                for t, v in sorted(given.items()) if v == 0]


@dataclass
class _Topic:
    tokens: float = 0.0
    last: float | None = None
    byte_tokens: float = 0.0
    byte_last: float | None = None
    recorded_bytes: int = 0
    window_start: float | None = None
    window_msgs: int = 0
    window_bytes: int = 0
    seconds: int = 0            # full windows seen
    recent_hz: float = 0.0      # running average of the windows before
    recent_bps: float = 0.0


class RecordBudget:
    """admit(topic, nbytes, now) per message: None (record it) or the reason it is not
    ('rate', 'topic_bytes', 'total_bytes'). `floods` and `dropped` say what happened;
    `new_floods` what admit flagged since the last call of take_new_floods."""

    def __init__(self, limits: BudgetLimits):
        self.limits = limits
        self.topics: dict[str, _Topic] = {}
        self.total_bytes = 0
        self.dropped: dict[str, dict[str, int]] = {}
        self.floods: dict[str, dict[str, float]] = {}
        self.stopped: str | None = None
        self._new: list[str] = []

    def admit(self, topic: str, nbytes: int, now: float) -> str | None:
        t = self.topics.setdefault(topic, _Topic())
        self._watch_flood(topic, t, nbytes, now)
        reason = self._limit(topic, t, nbytes, now)
        if reason is None:
            t.recorded_bytes += nbytes
            self.total_bytes += nbytes
        else:
            counts = self.dropped.setdefault(topic, {})
            counts[reason] = counts.get(reason, 0) + 1
        return reason

    def _limit(self, topic: str, t: _Topic, nbytes: int, now: float) -> str | None:
        lim = self.limits
        if self.stopped is not None:
            return "total_bytes"
        if lim.max_total_bytes and self.total_bytes + nbytes > lim.max_total_bytes:
            self.stopped = (f"the bag reached its budget of {lim.max_total_bytes} bytes "
                            f"(max_total_bytes) at a message on {topic}")
            return "total_bytes"
        size = lim.message_limit(topic)
        if size and nbytes > size:
            return "message_bytes"
        budget = lim.bytes_for(topic)
        if budget and t.recorded_bytes + nbytes > budget:
            return "topic_bytes"
        hz, bps, burst = lim.rate(topic), lim.byte_rate(topic), lim.burst_s(topic)
        if hz > 0:
            cap = max(1.0, hz * burst)
            t.tokens = cap if t.last is None else min(cap, t.tokens + (now - t.last) * hz)
            t.last = now
            if t.tokens < 1.0:
                return "rate"
        if bps > 0:
            cap = max(float(nbytes), bps * burst)
            t.byte_tokens = cap if t.byte_last is None else min(cap, t.byte_tokens + (now - t.byte_last) * bps)
            t.byte_last = now
            if t.byte_tokens < nbytes:
                return "byte_rate"
            t.byte_tokens -= nbytes
        if hz > 0:
            t.tokens -= 1.0
        return None

    def _watch_flood(self, topic: str, t: _Topic, nbytes: int, now: float) -> None:
        if t.window_start is None:
            t.window_start = now
        elif now - t.window_start >= 1.0:
            span = now - t.window_start
            hz, bps = t.window_msgs / span, t.window_bytes / span
            factor = self.limits.flood_factor
            if factor > 0 and topic not in self.floods and (self._over_bounds(topic, hz, bps) or (
                    t.seconds >= FLOOD_WARMUP_S and (
                        (hz >= FLOOD_MIN_HZ and hz > factor * max(t.recent_hz, 1e-9))
                        or (bps >= FLOOD_MIN_BYTES_PER_S and bps > factor * max(t.recent_bps, 1e-9))))):
                self.floods[topic] = {"rate_hz": round(hz, 1), "recent_hz": round(t.recent_hz, 1),
                                      "bytes_per_s": round(bps), "recent_bytes_per_s": round(t.recent_bps)}
                self._new.append(topic)
            if topic not in self.floods:   # a flood does not become the topic's normal
                w = 1.0 / (t.seconds + 1) if t.seconds < 10 else 0.1
                t.recent_hz += w * (hz - t.recent_hz)
                t.recent_bps += w * (bps - t.recent_bps)
            t.seconds += 1
            t.window_start, t.window_msgs, t.window_bytes = now, 0, 0
        t.window_msgs += 1
        t.window_bytes += nbytes

    def _over_bounds(self, topic: str, hz: float, bps: float) -> bool:
        """A second offering more than the topic's bounds let through (a topic without history
        included): its rate limit, its byte rate (else rate x message size), or, unbounded,
        FLOOD_ABS_HZ / FLOOD_ABS_BYTES_PER_S."""
        lim = self.limits
        rate = lim.rate(topic) or FLOOD_ABS_HZ
        byte_rate = (lim.byte_rate(topic) or lim.rate(topic) * lim.message_limit(topic)
                     or FLOOD_ABS_BYTES_PER_S)
        return hz > rate or bps > byte_rate

    def take_new_floods(self) -> list[str]:
        out, self._new = self._new, []
        return out

    def metadata(self) -> dict[str, str]:
        """What the budget did, as metadata.yaml custom_data (str -> str)."""
        out = {}
        if self.dropped:
            out[DROPPED_KEY] = json.dumps(self.dropped, sort_keys=True)
        if self.floods:
            out[FLOOD_KEY] = json.dumps(self.floods, sort_keys=True)
        if self.stopped:
            out[BUDGET_KEY] = self.stopped
        return out


class DiskFloor:
    """Free disk under the bag, checked at most every `every_bytes` written or `every_s`
    seconds (statvfs is cheap, but not free at 10 kHz)."""

    def __init__(self, path: Path, min_free: int, every_bytes: int = 1 << 20, every_s: float = 0.5):
        self.path, self.min_free = Path(path), int(min_free)
        self.every_bytes, self.every_s = every_bytes, every_s
        self._bytes, self._at = 0, float("-inf")

    def below(self, nbytes: int, now: float) -> str | None:
        """A one-line reason when free space is under the floor, else None."""
        if self.min_free <= 0:
            return None
        self._bytes += nbytes
        if self._bytes < self.every_bytes and now - self._at < self.every_s:
            return None
        self._bytes, self._at = 0, now
        free = self.free()
        if free < self.min_free:
            return (f"{free} bytes free under {self.path}, below the floor of {self.min_free} "
                    "(min_free_disk)")
        return None

    def free(self) -> int:
        probe = self.path
        while not probe.exists() and probe != probe.parent:
            probe = probe.parent
        return shutil.disk_usage(probe).free
