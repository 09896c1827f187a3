"""QoS profiles of the protocad topics (msgs_docs/topics.md explains each choice).

Kept apart from sim_bridge/contract/topics.py because it imports rclpy; topics.py stays ROS-free.

Every protocad publisher offers RELIABLE + VOLATILE:
- RELIABLE: a learning loop must not lose steps (every observation answered by exactly one
  action and recorded exactly once). A reliable writer also matches best-effort readers, so a
  visualiser may subscribe best-effort without breaking anything.
- VOLATILE: a node that joins late must not act on (or answer) old observations; the sim
  bridge instead waits for its readers to be matched before it publishes the first step.
- KEEP_LAST with a deep history (OBSERVATION_DEPTH): in lock-step only one step is in flight,
  the depth is slack for a slow reader (the recorder writing a chunk, a policy reloading a
  checkpoint) in real-time mode, where a reader that falls more than DEPTH steps behind loses
  the oldest ones (counted by the reader, never blocking the simulation).
"""
from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import QoSOverridingOptions

#: History depth of image, step_info, context, action and context_features (messages).
OBSERVATION_DEPTH = 100
#: History depth of /clock (only the newest time matters; a little slack for recorders).
CLOCK_DEPTH = 10
#: History depth of /diagnostics (as diagnostic_updater).
DIAGNOSTICS_DEPTH = 10


def _reliable(depth: int) -> QoSProfile:
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)


def observation_qos(lossless: bool = False) -> QoSProfile:
    """image, step_info, context (sim bridge -> policy, recorder).

    lossless (the bridge's writers in lock-step): KEEP_ALL, so a sample leaves the writer's
    history only once every reliable reader acknowledged it. A stalled reader then costs memory,
    not data, at no cost per step (measured in scripts/bench_ros_loop.py). Waiting for the
    acknowledgements of each step instead (Publisher.wait_for_all_acked) made lock-step
    3.6-6.7x slower here: Fast DDS readers acknowledge at the writer's heartbeat, 5 ms to 3 s later."""
    if lossless:
        return QoSProfile(history=HistoryPolicy.KEEP_ALL, depth=OBSERVATION_DEPTH,
                          reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
    return _reliable(OBSERVATION_DEPTH)


def announcement_qos() -> QoSProfile:
    """bridge_info: reliable + transient local, depth 1: a node that starts later still gets
    the announcement (latched, as /tf_static)."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)


def checkpoint_chunks_qos(depth: int | None = None) -> QoSProfile:
    """<checkpoint topic>/chunks: reliable + transient local, so a receiver that joins late (or
    reconnects) still gets every chunk of the newest version. Writer (depth = the version's
    chunk count, one writer per version): its history is exactly one checkpoint. Reader
    (depth None): KEEP_ALL, so no chunk is overwritten before the callback took it."""
    if depth is None:
        return QoSProfile(history=HistoryPolicy.KEEP_ALL, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.TRANSIENT_LOCAL)
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)


def action_qos() -> QoSProfile:
    """action and context_features (policy -> sim bridge, recorder): KEEP_ALL. A few hundred
    bytes a step, so keeping every sample a stalled reader (a frozen recorder) has not
    acknowledged costs little memory, and the bag of a lock-step run has every action."""
    return QoSProfile(history=HistoryPolicy.KEEP_ALL, depth=OBSERVATION_DEPTH,
                      reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)


def clock_qos(lossless: bool = False) -> QoSProfile:
    """/clock: reliable so that reliable recorders match; rclpy's TimeSource subscribes
    best-effort depth 1, which a reliable writer also serves. lossless (the bridge in
    lock-step): KEEP_ALL like the observations, so a recorder that falls behind for more than
    CLOCK_DEPTH steps still gets the sim time of every step (best-effort readers never hold a
    KEEP_ALL writer back)."""
    if lossless:
        return QoSProfile(history=HistoryPolicy.KEEP_ALL, depth=CLOCK_DEPTH,
                          reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
    return _reliable(CLOCK_DEPTH)


def diagnostics_qos() -> QoSProfile:
    return _reliable(DIAGNOSTICS_DEPTH)


def describe(qos: QoSProfile) -> str:
    """One-line summary, e.g. 'RELIABLE, VOLATILE, KEEP_LAST(100)' (for logs and docs)."""
    history = "KEEP_ALL" if qos.history == HistoryPolicy.KEEP_ALL else f"{qos.history.name}({qos.depth})"
    return f"{qos.reliability.name}, {qos.durability.name}, {history}"


def overridable():
    """rclpy's QoS overriding: `-p qos_overrides./NS/TOPIC.publisher.reliability:=best_effort`
    (also `.subscription.`, and durability, history, depth) at start, for the image and
    action topics (for a viewer on a lossy link; see msgs_docs/topics.md for what it costs)."""
    return QoSOverridingOptions.with_default_policies()
