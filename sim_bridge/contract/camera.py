"""What a camera's frame becomes before a model sees it: decoded (sensor_msgs/Image in a common
encoding, or sensor_msgs/CompressedImage as JPEG or PNG), cropped and resized with antialiasing
to the model's square size. The policy node (protocad_ros/node/observation_pairing.py) and the
dataset over bags (trainer/data/rebuild.py) both call `model_image`, so a policy sees on a robot
what it saw in training. A frame already at the model's size and uncropped passes unchanged: the
native path (the sim bridge's 64x64 rgb8) is bit-exact.

Decoding is Pillow's; every size is checked before a pixel is expanded, so a frame that claims
to be huge (or a compressed bomb) is refused with its reason instead of filling memory.
"""
from __future__ import annotations

import io
import re
from dataclasses import dataclass
from typing import Any

import numpy as np
from PIL import Image

from sim_bridge.contract import topics

#: Raw encodings taken (sensor_msgs/image_encodings names): channels, and the order that gives RGB.
ENCODINGS: dict[str, tuple[int, tuple[int, ...]]] = {
    "rgb8": (3, (0, 1, 2)),
    "bgr8": (3, (2, 1, 0)),
    "rgba8": (4, (0, 1, 2)),
    "bgra8": (4, (2, 1, 0)),
    "mono8": (1, (0, 0, 0)),
}
#: CompressedImage formats taken, as image_transport's compressed plugin writes them
#: ("jpeg", "png", or "rgb8; jpeg compressed bgr8").
COMPRESSED_FORMATS = ("jpeg", "png")
#: Largest frame decoded (pixels): a 4K camera fits; a claimed 100k x 100k frame does not.
MAX_PIXELS = 4096 * 4096
#: Largest compressed payload taken (bytes).
MAX_COMPRESSED_BYTES = 64 << 20
RESAMPLING = Image.Resampling.BOX   # area averaging: antialiased, and no ringing next to edges


class FrameError(ValueError):
    """A frame that cannot become a model image; `kind` names the counter it goes to."""

    def __init__(self, kind: str, why: str):
        super().__init__(why)
        self.kind = kind


@dataclass(frozen=True)
class Crop:
    """The part of a frame the model sees: `center` (the largest centered square: what a square
    render of the same camera shows), `full` (the whole frame, squashed to a square) or a region
    `x,y,w,h` in pixels (clipped to the frame)."""

    mode: str = "center"
    region: tuple[int, int, int, int] | None = None

    @classmethod
    def parse(cls, text: str) -> Crop:
        t = text.strip().lower()
        if t in ("center", "full"):
            return cls(t)
        m = re.fullmatch(r"\s*(\d+)\s*,\s*(\d+)\s*,\s*(\d+)\s*,\s*(\d+)\s*", t)
        if m is None:
            raise ValueError(f"crop {text!r}: expected center, full or x,y,w,h (pixels)")
        x, y, w, h = (int(g) for g in m.groups())
        if w < 1 or h < 1:
            raise ValueError(f"crop {text!r}: width and height must be at least 1")
        return cls("region", (x, y, w, h))

    def box(self, height: int, width: int) -> tuple[int, int, int, int]:
        """(left, top, right, bottom) in a height x width frame."""
        if self.mode == "full":
            return 0, 0, width, height
        if self.mode == "center":
            side = min(height, width)
            left, top = (width - side) // 2, (height - side) // 2
            return left, top, left + side, top + side
        x, y, w, h = self.region or (0, 0, width, height)
        left, top = min(x, width - 1), min(y, height - 1)
        return left, top, min(width, left + w), min(height, top + h)

    def __str__(self) -> str:
        return ",".join(map(str, self.region)) if self.mode == "region" and self.region else self.mode


def _payload(data: Any) -> np.ndarray:
    """A flat uint8 view of a message's data field (array.array, bytes, ndarray, list)."""
    try:
        return topics.uint8_view(data)
    except ValueError as exc:
        raise FrameError("rejected_image_data", str(exc)) from None


def decode_raw(encoding: str, height: int, width: int, step: int, data: Any) -> np.ndarray:
    """An HxWx3 uint8 RGB array (a view where it can be) from sensor_msgs/Image's fields."""
    if encoding not in ENCODINGS:
        raise FrameError("rejected_image_encoding", f"image encoding {encoding!r} is not taken "
                         f"(taken: {', '.join(ENCODINGS)}; or CompressedImage jpeg/png)")
    channels, order = ENCODINGS[encoding]
    h, w, step = int(height), int(width), int(step)
    if h < 1 or w < 1 or h * w > MAX_PIXELS:
        raise FrameError("rejected_image_size", f"image is {h}x{w}: outside 1 to {MAX_PIXELS} pixels")
    buf = _payload(data)
    if step < w * channels or buf.size != h * step:
        raise FrameError("rejected_image_data", f"image data has {buf.size} bytes, expected "
                         f"{h}x{step} (width {w}, {encoding})")
    pixels = buf.reshape(h, step)[:, : w * channels].reshape(h, w, channels)
    return pixels if order == (0, 1, 2) and channels == 3 else pixels[:, :, list(order)]


def compressed_kind(fmt: str) -> str:
    """jpeg or png from a CompressedImage format string ("jpeg", "png", "bgr8; jpeg compressed
    bgr8", "rgb8; png compressed rgb8"); FrameError for anything else."""
    words = re.findall(r"[a-z0-9]+", fmt.lower())
    for kind in COMPRESSED_FORMATS:
        if kind in words or (kind == "jpeg" and "jpg" in words):
            return kind
    raise FrameError("rejected_image_encoding", f"compressed format {fmt!r} is not taken "
                     f"(taken: {', '.join(COMPRESSED_FORMATS)})")


def decode_compressed(fmt: str, data: Any) -> np.ndarray:
    """An HxWx3 uint8 RGB array from sensor_msgs/CompressedImage's format and data."""
    kind = compressed_kind(fmt)
    buf = _payload(data)
    if buf.size > MAX_COMPRESSED_BYTES:
        raise FrameError("rejected_image_size", f"compressed image of {buf.size} bytes (at most "
                         f"{MAX_COMPRESSED_BYTES})")
    try:
        with Image.open(io.BytesIO(buf.tobytes()), formats=["JPEG" if kind == "jpeg" else "PNG"]) as im:
            w, h = im.size   # from the header: nothing expanded yet
            if h * w > MAX_PIXELS:
                raise FrameError("rejected_image_size", f"compressed image is {h}x{w}: over {MAX_PIXELS} pixels")
            return np.asarray(im.convert("RGB"))
    except FrameError:
        raise
    except (OSError, ValueError, SyntaxError, Image.DecompressionBombError) as exc:
        raise FrameError("rejected_image_data", f"{kind} image does not decode: {exc}") from None


def resize(rgb: np.ndarray, size: int, crop: Crop = Crop()) -> np.ndarray:
    """The crop of an HxWx3 uint8 frame, resized to size x size with area averaging; a frame
    already size x size that the crop keeps whole is returned unchanged."""
    h, w = rgb.shape[:2]
    box = crop.box(h, w)
    if box == (0, 0, w, h) and (h, w) == (size, size):
        return rgb
    image = Image.fromarray(np.ascontiguousarray(rgb), "RGB")
    return np.asarray(image.resize((size, size), RESAMPLING, box=box))


def frame_rgb(msg: Any) -> np.ndarray:
    """The RGB frame of a sensor_msgs/Image or CompressedImage (told apart by `format`)."""
    if hasattr(msg, "format") and not hasattr(msg, "encoding"):
        return decode_compressed(str(msg.format), msg.data)
    return decode_raw(str(msg.encoding), msg.height, msg.width, msg.step, msg.data)


def model_image(msg: Any, size: int, crop: Crop = Crop()) -> np.ndarray:
    """What the model sees of one camera message: size x size x 3 uint8 RGB. FrameError (a
    ValueError with `kind`) says why a frame cannot be used."""
    return resize(frame_rgb(msg), size, crop)


def encode_compressed(rgb: np.ndarray, kind: str = "jpeg", quality: int = 90) -> bytes:
    """JPEG or PNG bytes of an HxWx3 uint8 RGB frame (what a camera's compressed transport sends)."""
    out = io.BytesIO()
    image = Image.fromarray(np.ascontiguousarray(rgb), "RGB")
    if kind == "jpeg":
        image.save(out, "JPEG", quality=int(quality))
    elif kind == "png":
        image.save(out, "PNG")
    else:
        raise ValueError(f"compressed kind {kind!r}: expected one of {COMPRESSED_FORMATS}")
    return out.getvalue()


def raw_payload(rgb: np.ndarray, encoding: str) -> tuple[bytes, int]:
    """(data, step) of an HxWx3 uint8 RGB frame in a raw encoding (mono8: ITU-R 601 luma)."""
    if encoding not in ENCODINGS:
        raise ValueError(f"encoding {encoding!r}: expected one of {tuple(ENCODINGS)}")
    channels, order = ENCODINGS[encoding]
    if encoding == "mono8":
        px = np.asarray(Image.fromarray(np.ascontiguousarray(rgb), "RGB").convert("L"))[:, :, None]
    else:
        px = rgb[:, :, list(order)]
        if channels == 4:
            px = np.concatenate([px, np.full(rgb.shape[:2] + (1,), 255, np.uint8)], axis=2)
    px = np.ascontiguousarray(px, np.uint8)
    return px.tobytes(), int(rgb.shape[1]) * channels
