"""What a long command does at the terminal: a progress bar, Ctrl-C as a flag to stop at the next
safe point, and waiting for something with a deadline."""
from __future__ import annotations

import os
import signal
import sys
import time
from dataclasses import dataclass, field
from typing import Callable


def progress(total: int | None, initial: int = 0, desc: str = "", disable: bool | None = None, unit: str = "it"):
    """A tqdm bar (to stderr; disabled automatically when stderr is not a terminal unless
    PROTOCAD_PROGRESS=1)."""
    from tqdm.auto import tqdm

    if disable is None:
        disable = not (sys.stderr.isatty() or os.environ.get("PROTOCAD_PROGRESS") == "1")
    return tqdm(total=total, initial=initial, desc=desc, disable=disable, unit=unit,
                dynamic_ncols=True, smoothing=0.05)


# ----------------------------------------------------------------------------- interrupts
@dataclass
class StopFlag:
    """Ctrl-C / SIGTERM turn into a flag the training loop checks between updates; a second
    Ctrl-C exits (130) without a traceback."""

    stop: bool = False
    signum: int | None = None
    _old: dict = field(default_factory=dict)

    def __enter__(self) -> "StopFlag":
        for sig in (signal.SIGINT, signal.SIGTERM):
            try:
                self._old[sig] = signal.signal(sig, self._handler)
            except ValueError:  # not the main thread
                pass
        return self

    def _handler(self, signum, frame):
        if self.stop and signum == signal.SIGINT:
            # A second Ctrl-C: leave now, without a traceback. The clean-up of `finally` blocks
            # still runs (bags closed); checkpoints and run.json are written atomically, so
            # what is on disk stays valid either way.
            print("\n[protocad] SIGINT again: aborting", file=sys.stderr, flush=True)
            raise SystemExit(130)
        self.stop, self.signum = True, signum
        print(f"\n[protocad] {signal.Signals(signum).name}: stopping: finishing the current step, "
              "saving, exiting (press Ctrl-C again to abort)", file=sys.stderr, flush=True)

    def __exit__(self, *exc) -> None:
        for sig, old in self._old.items():
            signal.signal(sig, old)


def wait_until(ready: Callable[[], bool], *, what: str, timeout: float,
               alive: Callable[[], str | None] = lambda: None, stop=None,
               pause: Callable[[], None] = lambda: time.sleep(0.05)) -> bool:
    """Poll `ready()` (calling `pause()` in between) until it is true; TimeoutError naming
    `what`; RuntimeError at once with what `alive()` says when the process watched is gone;
    False when `stop.stop` (a StopFlag) is raised."""
    deadline = time.monotonic() + timeout
    while True:
        if ready():
            return True
        if stop is not None and stop.stop:
            return False
        gone = alive()
        if gone:
            raise RuntimeError(gone)
        if time.monotonic() > deadline:
            raise TimeoutError(f"no {what} within {timeout:.0f}s")
        pause()
