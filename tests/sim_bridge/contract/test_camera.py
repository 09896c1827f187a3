"""The camera path (sim_bridge/contract/camera.py): every taken encoding, raw or compressed,
decodes to the same RGB frame; crops and resizing give the model's square; what cannot be a
frame is refused with the counter it belongs to."""
from __future__ import annotations

import io
from types import SimpleNamespace

import numpy as np
import pytest
from PIL import Image

from sim_bridge.contract import camera
from sim_bridge.contract.camera import Crop, FrameError


def _frame(h: int = 48, w: int = 64, seed: int = 0) -> np.ndarray:
    """Smooth content with edges, like a render (JPEG's error on pure noise says nothing)."""
    y, x = np.mgrid[0:h, 0:w]
    rng = np.random.default_rng(seed)
    img = np.stack([(x * 255 // w), (y * 255 // h), ((x // 8 + y // 8) % 2) * 200], axis=2)
    return np.clip(img + rng.integers(0, 8, img.shape), 0, 255).astype(np.uint8)


def _raw(rgb: np.ndarray, encoding: str) -> SimpleNamespace:
    data, step = camera.raw_payload(rgb, encoding)
    return SimpleNamespace(encoding=encoding, height=rgb.shape[0], width=rgb.shape[1], step=step, data=data)


@pytest.mark.parametrize("encoding", ["rgb8", "bgr8", "rgba8", "bgra8"])
def test_colour_encodings_decode_to_the_same_rgb_frame(encoding):
    rgb = _frame()
    assert np.array_equal(camera.frame_rgb(_raw(rgb, encoding)), rgb)


def test_mono8_becomes_three_equal_channels_of_the_frames_luma():
    rgb = _frame()
    out = camera.frame_rgb(_raw(rgb, "mono8"))
    luma = np.asarray(Image.fromarray(rgb).convert("L"))
    assert out.shape == rgb.shape and all(np.array_equal(out[:, :, c], luma) for c in range(3))


def test_a_padded_row_step_is_honoured():
    rgb = _frame()
    data, step = camera.raw_payload(rgb, "bgr8")
    rows = np.frombuffer(data, np.uint8).reshape(rgb.shape[0], step)
    padded = np.concatenate([rows, np.zeros((rgb.shape[0], 16), np.uint8)], axis=1)
    msg = SimpleNamespace(encoding="bgr8", height=rgb.shape[0], width=rgb.shape[1], step=step + 16,
                          data=padded.tobytes())
    assert np.array_equal(camera.frame_rgb(msg), rgb)


@pytest.fixture(scope="module")
def render() -> np.ndarray:
    """A real walker frame at 128x128 (JPEG's error depends on the content)."""
    from sim_bridge.sim.envs import ContextDMCEnv

    with ContextDMCEnv("walker_walk", image_size=128) as env:
        env.reset()
        for _ in range(5):
            env.step(np.zeros(6))
        return env.render()


def test_png_is_lossless_and_jpeg_stays_within_its_tolerance(render):
    rgb = render
    png = SimpleNamespace(format="png", data=camera.encode_compressed(rgb, "png"))
    assert np.array_equal(camera.frame_rgb(png), rgb)
    # image_transport's compressed plugin names the format this way
    jpeg = SimpleNamespace(format="bgr8; jpeg compressed bgr8", data=camera.encode_compressed(rgb, "jpeg", 90))
    err = np.abs(camera.model_image(jpeg, 64).astype(int) - camera.resize(rgb, 64).astype(int))
    # JPEG at quality 90, then area-averaged to 64x64: measured mean 1.4, p99 13 of 255
    assert err.mean() < 2.5 and np.percentile(err, 99) < 20


def test_a_frame_at_the_models_size_passes_unchanged_and_others_are_cropped_and_resized():
    rgb = _frame(64, 64)
    assert np.array_equal(camera.model_image(_raw(rgb, "rgb8"), 64), rgb)
    big = np.kron(rgb, np.ones((8, 8, 1), np.uint8))          # each pixel an 8x8 block
    assert np.array_equal(camera.resize(big, 64), rgb)        # area averaging undoes it exactly
    wide = np.zeros((480, 640, 3), np.uint8)
    wide[:, 80:560] = 255
    assert camera.resize(wide, 64).min() == 255               # center: the middle 480x480
    assert camera.resize(wide, 64, Crop.parse("full")).min() == 0   # full: the black borders too
    assert camera.resize(wide, 64, Crop.parse("0,0,80,480")).max() == 0


def test_crop_strings_parse_and_bad_ones_say_what_is_expected():
    assert Crop.parse("center").box(480, 640) == (80, 0, 560, 480)
    assert Crop.parse("full").box(480, 640) == (0, 0, 640, 480)
    assert Crop.parse(" 10, 20, 100, 50 ").box(480, 640) == (10, 20, 110, 70)
    assert Crop.parse("600,400,100,100").box(480, 640) == (600, 400, 640, 480)   # clipped
    for bad in ("middle", "1,2,3", "0,0,0,10"):
        with pytest.raises(ValueError, match="crop"):
            Crop.parse(bad)


@pytest.mark.parametrize("msg,kind", [
    (SimpleNamespace(encoding="yuv422", height=4, width=4, step=8, data=bytes(32)), "rejected_image_encoding"),
    (SimpleNamespace(encoding="16UC1", height=4, width=4, step=8, data=bytes(32)), "rejected_image_encoding"),
    (SimpleNamespace(encoding="rgb8", height=4, width=4, step=12, data=bytes(47)), "rejected_image_data"),
    (SimpleNamespace(encoding="rgb8", height=100000, width=100000, step=300000, data=b""), "rejected_image_size"),
    (SimpleNamespace(format="tiff", data=b"II*\0"), "rejected_image_encoding"),
    (SimpleNamespace(format="jpeg", data=b"\xff\xd8 not a jpeg"), "rejected_image_data"),
])
def test_what_cannot_be_a_frame_is_refused_with_its_counter(msg, kind):
    with pytest.raises(FrameError) as err:
        camera.model_image(msg, 64)
    assert err.value.kind == kind and str(err.value)


def test_a_compressed_frame_that_claims_too_many_pixels_is_refused_before_it_is_expanded():
    # A PNG header claiming 5000 x 5000 (25 M pixels) over a tiny body: refused from the header.
    out = io.BytesIO()
    Image.new("L", (5000, 5000)).save(out, "PNG")
    with pytest.raises(FrameError) as err:
        camera.model_image(SimpleNamespace(format="png", data=out.getvalue()), 64)
    assert err.value.kind == "rejected_image_size"
