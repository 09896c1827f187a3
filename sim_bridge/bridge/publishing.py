"""How the sim bridge's stepping thread publishes an observation: image, step_info, context and
clock stamped together, published whole or not at all (a deactivation waits for a started one),
and, lossless, waiting out a full history instead of losing a sample. A part of SimBridgeNode."""
from __future__ import annotations

import time

from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy

from sim_bridge.contract import topics

#: What rclpy raises when the middleware refuses a sample (a full KEEP_ALL history).
RCLError = _rclpy.RCLError
#: Seconds between attempts to publish into a full lossless history.
PUBLISH_RETRY_S = 0.05


class ObservationPublishing:
    def _stamp(self) -> int:
        self._tick += 1
        return self._tick * self.dt_ns

    def _publish(self, obs, stamp: int, republish: bool = False) -> bool:
        """Publish observation `obs` (stamp); False, and nothing sent, while not active."""
        img, info, ctx = self._img_msg, self._info_msg, self._ctx_msg
        if not republish:
            self._return = 0.0 if obs.is_first else self._return + float(obs.reward)
            self.camera.fill(img, obs.image, stamp)
            topics.fill_step_info(info, topics.StepInfo(
                float(obs.reward), float(obs.discount), bool(obs.is_first), bool(obs.is_last),
                bool(obs.is_terminal), int(obs.episode), int(obs.step), self._return), stamp)
            if obs.is_last:   # the score of the episode, where a ROS user looks: the log
                label = ", ".join(f"{k}={v:g}" for k, v in obs.context.items())
                self.get_logger().info(f"episode {obs.episode} finished: return {self._return:.1f} "
                                       f"over {obs.step} steps ({obs.split} context {label})")
            topics.fill_context(ctx, obs.context, obs.split, stamp)
            topics.set_stamp(self._clock_msg.clock, stamp)
            self._episode, self._step, self._obs_context = obs.episode, obs.step, obs.context
        # Under _cond: a deactivation waits for a started observation to go out whole.
        with self._cond:
            if not self._go:
                return False
            self._published[stamp] = time.monotonic()
            while len(self._published) > 256:
                self._published.popitem(last=False)
            self._newest_stamp = stamp
            if self.lockstep:
                self._pending_stamp, self._answer = stamp, None
            self.counters["observations_republished" if republish
                          else "observations_published"] += 1
            # What the policy waits for first (it answers once image and step_info are in);
            # the true context and the clock follow while it computes.
            for pub, msg in ((self.pub_image, img), (self.pub_info, info), (self.pub_context, ctx),
                             (self.pub_clock, self._clock_msg)):
                self._send(pub, msg)
        return True

    def _send(self, pub, msg) -> None:
        """Publish, under _cond. A lossless writer refuses a sample once its history holds
        Fast DDS's limit (5000) of samples some reliable reader has not acknowledged (a recorder
        stalled that many steps): then wait for the reader, so a stall costs time, not a sample.
        The wait releases _cond: callbacks and diagnostics go on meanwhile."""
        while True:
            try:
                return pub.publish(msg)
            except RCLError as exc:
                if not self._obs_lossless or self._stop.is_set():
                    raise
                self.counters["publish_waits"] += 1
                self._throttle.warning("publish_waits", f"{pub.topic_name}: the writer's history is full of "
                                       f"samples a reader has not acknowledged (a stalled reader): waiting "
                                       f"for it ({self.counters['publish_waits']} waits so far; {exc})".replace("\n", " "))
                self._cond.wait(PUBLISH_RETRY_S)
