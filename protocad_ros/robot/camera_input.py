"""The policy node's camera (msgs_docs/policy.md, "Camera input"): a camera's frames, in any
encoding `sim_bridge.contract.camera` takes, raw (`sensor_msgs/Image` on `image`) or compressed
(`sensor_msgs/CompressedImage` on `<image>/compressed`, image_transport's name for it), cropped
and resized to the model's square by `camera.model_image`, the one function the dataset over
bags uses too, so the policy sees on a robot what it saw in training.

Each model image goes on in one of two ways (`observations`):

- `paired`: to the node's pairing with step_info by stamp (the sim bridge's contract);
- `image_only`: a real robot's camera alone, no step_info. Each frame is an observation of its
  own, with reward 0; the episode and step numbers are counted here. A frame starts an episode
  (is_first) when it is the first after activation or after `restart_episode()` (a watchdog
  that saw the input stop, an enable switch). A camera's stamps must grow: a frame not newer
  than the last one handed on is stale and not answered.

A frame that cannot be a model image is counted under its kind (`FrameError.kind`) with one
throttled line naming why; the next good frame is answered as usual.
"""
from __future__ import annotations

import time
from typing import Any, Callable

import numpy as np
from sensor_msgs.msg import CompressedImage, Image

from sim_bridge.contract import camera, topics
from sim_bridge.contract.camera import Crop, FrameError
from sim_bridge.contract.qos import overridable
from sim_bridge.nodekit.param_table import ConfigError

TRANSPORTS = ("raw", "compressed")
OBSERVATIONS = ("paired", "image_only")


def parse_crop(text: str) -> Crop:
    """The `image_crop` parameter; a ConfigError (one line) for a value that is no crop."""
    try:
        return Crop.parse(text)
    except ValueError as exc:
        raise ConfigError(f"image_crop: {exc}") from None


class CameraInput:
    """Owns the node's image subscription and turns each frame into a model image.

    `active()` says whether frames are taken now (counted and dropped otherwise, by the node),
    `size()` the model's square side (known from configure on), `count(key, why)` counts on the
    node's diagnostics; `image(stamp, rgb, t)` hands a model image to the pairing with
    step_info, `observation(stamp, entry, t)` a whole observation (image_only) to the node's
    answering path."""

    def __init__(self, node: Any, params: dict[str, Any], *, qos_profile: Any, event_callbacks: Callable,
                 active: Callable[[], bool], size: Callable[[], int], count: Callable[..., None],
                 image: Callable[[int, np.ndarray, float], None],
                 observation: Callable[[int, dict, float], None]):
        self.transport, self.mode = params["image_transport"], params["observations"]
        self.crop = parse_crop(params["image_crop"])
        self._active, self._size, self._count = active, size, count
        self._image, self._observation = image, observation
        self._restart = True          # image_only: the next frame starts an episode
        self._episode, self._step = -1, -1
        self._last_stamp: int | None = None
        base = node.resolve_topic_name(topics.IMAGE)
        if self.transport == "compressed":
            # image_transport's naming: the compressed stream of `image` is `image/compressed`.
            self.topic, msg_type = base + "/compressed", CompressedImage
        else:
            self.topic, msg_type = base, Image
        self.subscription = node.create_subscription(msg_type, self.topic, self._on_frame, qos_profile,
                                                     qos_overriding_options=overridable(),
                                                     event_callbacks=event_callbacks(self.topic))

    def describe(self) -> str:
        kind = "CompressedImage (jpeg, png)" if self.transport == "compressed" else (
            f"Image ({', '.join(camera.ENCODINGS)})")
        crop = "" if self.crop == Crop() else f", crop {self.crop}"
        alone = ", without step_info (image_only)" if self.mode == "image_only" else ""
        return f"{kind} on {self.topic}{crop}{alone}"

    def restart_episode(self) -> None:
        """image_only: the next frame starts a new episode (is_first: a blank filter). With
        paired observations the bridge's step_info says where episodes start, so this only
        counts."""
        self._restart = True
        self._count("episode_restarts")

    def activated(self) -> None:
        """image_only: the first frame after activation starts an episode (the time between
        is unknown, the filter's state is no longer the robot's)."""
        self._restart = True

    def _on_frame(self, msg: Any) -> None:
        if not self._active():
            return
        t = time.monotonic()
        stamp = topics.stamp_to_ns(msg.header.stamp)
        self._count("images_received")
        try:
            # A copy: the filter may keep the image (act callbacks, the live view) after the
            # message's buffer is gone.
            rgb = np.array(camera.model_image(msg, self._size(), self.crop))
        except FrameError as exc:
            self._count("images_rejected")
            return self._count(exc.kind, f"image rejected (stamp {topics.format_stamp(stamp)}): {exc}")
        if self.mode == "paired":
            return self._image(stamp, rgb, t)
        if self._last_stamp is not None and stamp <= self._last_stamp:
            return self._count("stale_observations", f"frame {topics.format_stamp(stamp)} is not newer than "
                               f"the last one ({topics.format_stamp(self._last_stamp)}): not answered")
        first, self._restart = self._restart, False
        self._episode, self._step = (self._episode + 1, 0) if first else (self._episode, self._step + 1)
        self._last_stamp = stamp
        info = topics.StepInfo(0.0, 1.0, first, False, False, max(self._episode, 0), self._step)
        self._observation(stamp, {"image": rgb, "info": info}, t)
