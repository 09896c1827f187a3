"""The recorder's disk is a budget (trainer/nodes/recorder.py applies it; no ROS import here).

Any participant on the domain can publish on a recorded topic, so a flood (a stranger's
/diagnostics at 10 kHz, images at 100 MB/s) would otherwise fill the disk. Per message:
- a per-topic rate limit (token bucket, HZ with two seconds of burst): messages above it are
  dropped and counted;
- a per-topic byte budget and a budget for the whole bag: a topic past its budget is no longer
  recorded (counted); the bag past its budget ends the recording (the recorder closes a valid
  bag and says so in one line);
- flood detection: a topic whose rate or byte rate in the last second is `flood_factor` times its
  recent figure (an average of the seconds before) and above a floor (FLOOD_MIN_HZ or
  FLOOD_MIN_BYTES_PER_S) is flagged once: in the bag's metadata and on /diagnostics.
The free-disk floor is the recorder's (DiskFloor): below it recording stops with a closed bag.
"""
from __future__ import annotations

import json
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping

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
    """The limits (0: off). rates / topic_bytes: per-topic values over the defaults."""
    max_topic_rate: float = 0.0
    max_topic_bytes: int = 0
    max_total_bytes: int = 0
    flood_factor: float = DEFAULT_FLOOD_FACTOR
    rates: Mapping[str, float] = field(default_factory=dict)
    topic_bytes: Mapping[str, float] = field(default_factory=dict)

    def rate(self, topic: str) -> float:
        return float(self.rates.get(topic, self.max_topic_rate))

    def bytes_for(self, topic: str) -> int:
        return int(self.topic_bytes.get(topic, self.max_topic_bytes))


@dataclass
class _Topic:
    tokens: float = 0.0
    last: float | None = None
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
        budget = lim.bytes_for(topic)
        if budget and t.recorded_bytes + nbytes > budget:
            return "topic_bytes"
        hz = lim.rate(topic)
        if hz > 0:
            cap = max(1.0, hz * RATE_BURST_S)
            t.tokens = cap if t.last is None else min(cap, t.tokens + (now - t.last) * hz)
            t.last = now
            if t.tokens < 1.0:
                return "rate"
            t.tokens -= 1.0
        return None

    def _watch_flood(self, topic: str, t: _Topic, nbytes: int, now: float) -> None:
        if t.window_start is None:
            t.window_start = now
        elif now - t.window_start >= 1.0:
            span = now - t.window_start
            hz, bps = t.window_msgs / span, t.window_bytes / span
            factor = self.limits.flood_factor
            if factor > 0 and t.seconds >= FLOOD_WARMUP_S and topic not in self.floods and (
                    (hz >= FLOOD_MIN_HZ and hz > factor * max(t.recent_hz, 1e-9))
                    or (bps >= FLOOD_MIN_BYTES_PER_S and bps > factor * max(t.recent_bps, 1e-9))):
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
