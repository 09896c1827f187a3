"""How the sim bridge's stepping thread publishes an observation: image, step_info, context and
clock stamped together, published whole or not at all (a deactivation waits for a started one),
and, lossless, waiting out a full history instead of losing a sample.

ObservationPublishing (the node's `observation_publishing`) owns the four reused messages, the
stamp clock (tick x dt_ns) and what the newest observation said (episode, step, return so far,
context). It is handed BridgeShared (sim_bridge/bridge/handover.py: the node, for its logger;
the Handover, with `go`, the published stamps and the stamp awaiting its answer; the counters,
the log throttle and the mode), the node's CameraOut, the three observation publishers and the
clock's."""
from __future__ import annotations

import time

from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.publisher import Publisher
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState

from sim_bridge.bridge.camera_out import CameraOut
from sim_bridge.bridge.handover import BridgeShared
from sim_bridge.contract import topics

#: What rclpy raises when the middleware refuses a sample (a full KEEP_ALL history).
RCLError = _rclpy.RCLError
#: Seconds between attempts to publish into a full lossless history.
PUBLISH_RETRY_S = 0.05


class ObservationPublishing:
    """One observation out, whole; see the module docstring."""

    def __init__(self, shared: BridgeShared, *, camera_out: CameraOut,
                 observation_pubs: tuple[Publisher, Publisher, Publisher], pub_clock: Publisher, lossless: bool):
        self.node, self.handover, self.counters = shared.node, shared.handover, shared.counters
        self.throttle, self.lockstep = shared.throttle, shared.lockstep
        self.camera_out = camera_out
        self.observation_pubs = observation_pubs   # image, step_info, context
        self.pub_image, self.pub_info, self.pub_context = observation_pubs
        self.pub_clock = pub_clock
        self.lossless = lossless
        self._img_msg, self._info_msg, self._ctx_msg, self._clock_msg = (
            camera_out.msg_type(), JointState(), JointState(), Clock())
        self.new_run(0)

    def new_run(self, dt_ns: int) -> None:
        """A configured run starts at tick -1 with the env's control period."""
        self.dt_ns = dt_ns
        self._tick = -1
        self._return = 0.0   # the current episode's return so far (step_info episode_return)
        self._episode = -1
        self._step = -1
        self._obs_context: dict[str, float] = {}

    def next_stamp(self) -> int:
        """The next observation's stamp (sim time, one control period on)."""
        self._tick += 1
        return self._tick * self.dt_ns

    def progress(self) -> tuple[int, int, dict[str, float], float]:
        """(episode, step, context, sim_time_s) of the newest observation, for /diagnostics."""
        with self.handover.cond:
            return (self._episode, self._step, dict(self._obs_context),
                    max(self._tick, 0) * self.dt_ns / 1e9)

    def publish(self, obs, stamp: int, republish: bool = False) -> bool:
        """Publish observation `obs` (stamp); False, and nothing sent, while not active."""
        img, info, ctx = self._img_msg, self._info_msg, self._ctx_msg
        if not republish:
            self._return = 0.0 if obs.is_first else self._return + float(obs.reward)
            self.camera_out.fill(img, obs.image, stamp)
            topics.fill_step_info(info, topics.StepInfo(
                float(obs.reward), float(obs.discount), bool(obs.is_first), bool(obs.is_last),
                bool(obs.is_terminal), int(obs.episode), int(obs.step), self._return), stamp)
            if obs.is_last:   # the score of the episode, where a ROS user looks: the log
                label = ", ".join(f"{k}={v:g}" for k, v in obs.context.items())
                self.node.get_logger().info(f"episode {obs.episode} finished: return {self._return:.1f} "
                                            f"over {obs.step} steps ({obs.split} context {label})")
            topics.fill_context(ctx, obs.context, obs.split, stamp)
            topics.set_stamp(self._clock_msg.clock, stamp)
            self._episode, self._step, self._obs_context = obs.episode, obs.step, obs.context
        h = self.handover
        # Under cond: a deactivation waits for a started observation to go out whole.
        with h.cond:
            if not h.go:
                return False
            h.published[stamp] = time.monotonic()
            while len(h.published) > 256:
                h.published.popitem(last=False)
            h.newest_stamp = stamp
            if self.lockstep:
                h.pending_stamp, h.answer = stamp, None
            self.counters["observations_republished" if republish
                          else "observations_published"] += 1
            # What the policy waits for first (it answers once image and step_info are in);
            # the true context and the clock follow while it computes.
            for pub, msg in ((self.pub_image, img), (self.pub_info, info), (self.pub_context, ctx),
                             (self.pub_clock, self._clock_msg)):
                self._send(pub, msg)
        return True

    def _send(self, pub, msg) -> None:
        """Publish, under cond. A lossless writer refuses a sample once its history holds
        Fast DDS's limit (5000) of samples some reliable reader has not acknowledged (a recorder
        stalled that many steps): then wait for the reader, so a stall costs time, not a sample.
        The wait releases cond: callbacks and diagnostics go on meanwhile."""
        while True:
            try:
                return pub.publish(msg)
            except RCLError as exc:
                if not self.lossless or self.handover.stop.is_set():
                    raise
                self.counters["publish_waits"] += 1
                self.throttle.warning("publish_waits", f"{pub.topic_name}: the writer's history is full of "
                                      f"samples a reader has not acknowledged (a stalled reader): waiting "
                                      f"for it ({self.counters['publish_waits']} waits so far; {exc})".replace("\n", " "))
                self.handover.cond.wait(PUBLISH_RETRY_S)
