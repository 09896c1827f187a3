"""What the sim bridge's camera publishes (msgs_docs/sim_bridge.md, "Camera option"): by default
the contract's square rgb8 Image; with the camera option a real camera's frame, any size, in
another raw encoding on `image`, or JPEG/PNG as sensor_msgs/CompressedImage on `image/compressed`
(image_transport's naming), so the policy node's camera input runs without a robot."""
from __future__ import annotations

from typing import Any, Mapping

import numpy as np
from sensor_msgs.msg import CompressedImage, Image

from sim_bridge.contract import camera, topics

#: Where image_transport's compressed plugin publishes a camera's `image`.
COMPRESSED_TOPIC = topics.IMAGE + "/compressed"


class CameraOut:
    """The image topic's type, name and message filling, from the camera_* parameters."""

    def __init__(self, params: Mapping[str, Any]):
        size = int(params["image_size"])
        self.height = int(params["camera_height"]) or size
        self.width = int(params["camera_width"]) or size
        self.encoding = str(params["camera_encoding"])
        self.compressed = params["camera_transport"] == "compressed"
        self.format = str(params["camera_format"])
        self.quality = int(params["jpeg_quality"])
        # The contract's path: fill_image as ever, no re-encoding, no other render size.
        self.native = (not self.compressed and self.encoding == "rgb8"
                       and (self.height, self.width) == (size, size))

    @property
    def msg_type(self) -> type:
        return CompressedImage if self.compressed else Image

    @property
    def topic(self) -> str:
        return COMPRESSED_TOPIC if self.compressed else topics.IMAGE

    @property
    def render_size(self) -> tuple[int, int] | None:
        """The env's camera_size: None for the square image_size render."""
        return None if self.native else (self.height, self.width)

    def describe(self) -> str:
        what = (f"{self.format}" + (f" quality {self.quality}" if self.format == "jpeg" else "")
                if self.compressed else self.encoding)
        return f"{self.height}x{self.width} {what} on {self.topic}"

    def fill(self, msg: Any, rgb: np.ndarray, t_ns: int) -> Any:
        """msg (of msg_type) carrying the HxWx3 RGB frame, stamped t_ns."""
        if self.native:
            return topics.fill_image(msg, rgb, t_ns)
        topics.set_stamp(msg.header.stamp, t_ns)
        msg.header.frame_id = topics.IMAGE_FRAME_ID
        if self.compressed:
            msg.format = self.format
            msg.data = camera.encode_compressed(rgb, self.format, self.quality)
            return msg
        msg.data, msg.step = camera.raw_payload(rgb, self.encoding)
        msg.height, msg.width = int(rgb.shape[0]), int(rgb.shape[1])
        msg.encoding, msg.is_bigendian = self.encoding, 0
        return msg
