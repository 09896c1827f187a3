"""Rate-limited refusal lines: one line per cause per interval, with a count.

A refused checkpoint is always counted (diagnostics), but its log line must not be the lever of
a flood: announcements with ever new version ids once wrote 540 error lines in 2 s. So the first
refusal of a cause (a counter name: signature, rollback, limits, ...) is logged at once; those
of the same cause within `interval_s` are only counted, and said as one line when the interval
is over ("... and 57 more refusal(s) of this kind in the last 10 s, the last: ..."). Free of ROS.
"""
from __future__ import annotations

import threading
import time
from typing import Callable

#: Seconds between two lines of one cause.
DEFAULT_INTERVAL_S = 10.0


class RefusalLog:
    def __init__(self, log: Callable[[str], None], interval_s: float = DEFAULT_INTERVAL_S,
                 clock: Callable[[], float] = time.monotonic):
        self._log, self._interval, self._clock = log, interval_s, clock
        self._lock = threading.Lock()
        self._last: dict[str, float] = {}                 # cause -> time of its last line
        self._held: dict[str, tuple[int, str]] = {}       # cause -> (refusals not said, the last)

    def refuse(self, cause: str, line: str) -> None:
        """Log `line` now, or count it for the cause's next line (within the interval)."""
        now = self._clock()
        with self._lock:
            if now - self._last.get(cause, -1e18) < self._interval:
                n, _ = self._held.get(cause, (0, ""))
                self._held[cause] = (n + 1, line)
                return
            self._last[cause] = now
        self._log(line)

    def flush(self, force: bool = False) -> None:
        """Say the refusals held back whose interval is over (all of them with `force`)."""
        now = self._clock()
        out = []
        with self._lock:
            for cause, (n, last) in list(self._held.items()):
                if force or now - self._last.get(cause, -1e18) >= self._interval:
                    del self._held[cause]
                    self._last[cause] = now
                    out.append(f"{n} more refusal(s) of this kind ({cause}) in the last "
                               f"{self._interval:g} s, the last: {last}")
        for line in out:
            self._log(line)
