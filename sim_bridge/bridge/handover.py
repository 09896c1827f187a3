"""What the sim bridge's two threads share: one condition variable and the state it guards.

The executor thread (action and reset callbacks, lifecycle transitions, diagnostics) and the
stepping thread meet here, so a lock-step round trip costs no timer period and no polling: an
accepted action is handed over under `cond` and wakes the stepping thread at once.

The node owns it (SimBridgeNode.handover), builds it before its parts and hands the same object
to each: ActionIntake answers the pending observation and requests resets, Stepping waits on it,
ObservationPublishing sets the stamp awaiting an answer, BridgeDiagnostics reads under it. No
part owns it because none is its only writer: the node's lifecycle hooks flip `go` (Stepping's
cleanup sets `stop`), and the node takes the same lock for its parameter changes and counters.
One lock for the node's cross-thread state, so a deactivation waits for an observation being
published to go out whole.
"""
from __future__ import annotations

import collections
import threading
from dataclasses import dataclass
from typing import Any

import numpy as np

from sim_bridge.nodekit.rosnode import KeyThrottle


@dataclass(frozen=True)
class BridgeShared:
    """What the node hands every part of the bridge: itself (logger, ROS graph, create_*), its
    parameters, the Handover, its counters (changed under the handover's lock), its log throttle
    and whether it steps in lock-step. One object, so a part's constructor lists only what is
    its own."""

    node: Any            # SimBridgeNode (a ManagedNode)
    params: dict[str, Any]
    handover: "Handover"
    counters: dict[str, int]
    throttle: KeyThrottle
    lockstep: bool


class Handover:
    """The lock (`cond`, reentrant) and the fields both threads read or write under it."""

    def __init__(self) -> None:
        self.cond = threading.Condition()
        self.stop = threading.Event()   # set: the stepping thread ends (cleanup)
        self.go = False                 # active: the stepping thread may step
        self.new_run(0)

    def new_run(self, action_dim: int) -> None:
        """The state of one configured run. Called under `cond` (or before any thread runs)."""
        self.pending_stamp: int | None = None   # lock-step: stamp awaiting its answer
        self.answer: np.ndarray | None = None   # lock-step: valid answer to pending_stamp
        #: stamp -> monotonic time published, the newest 256 (what an action may answer).
        self.published: collections.OrderedDict[int, float] = collections.OrderedDict()
        self.newest_stamp: int | None = None    # newest observation published
        self.held = np.zeros(action_dim)        # real-time: action applied at each tick
        self.held_stamp = -1
        self.reset_requested = False
        self.reset_served = 0                   # incremented by the stepping thread
        self.reset_note = ""
        self.started = False                    # the stepping thread began its first episode

    def set_go(self, go: bool) -> None:
        """Let the stepping thread step (True) or pause it; under `cond`, so an observation is
        published whole or not at all (ObservationPublishing.publish)."""
        with self.cond:
            self.go = go
            self.cond.notify_all()

    def hand_answer(self, action: np.ndarray) -> None:
        """Lock-step: the action answers the pending observation; the stepping thread goes on.
        Called under `cond`."""
        self.answer = action
        self.pending_stamp = None
        self.cond.notify_all()
