"""Bags of a robot's camera (issue 53): 480x640 frames as JPEG sensor_msgs/CompressedImage, written
by this project's writer and by another tool (rosbags), train through the function the policy
node runs on a robot (sim_bridge.contract.camera.model_image): the dataset holds exactly what a
bag of the same frames already at 64x64 rgb8 holds, and protocad-train runs on them."""
from __future__ import annotations

import numpy as np
import pytest
from helpers.bags import COMPRESSED_IMAGE, TINY, fill_jpeg, make_steps, run_cli, write_bag, write_rosbags_bag
from helpers.training import ckpt_counters

from sim_bridge.contract import camera
from sim_bridge.contract import topics as T
from trainer.bag.rosmsg import new_message
from trainer.data.dataset import MCAPDataset, TopicMap
from trainer.data.records import ImageSpec
from trainer.data.store import cache_key, ingest_source

COMPRESSED_TOPIC = "/protocad/image/compressed"
ROBOT = {"image": "/robot/camera/image_raw/compressed", "step_info": "/robot/step", "action": "/robot/cmd",
         "context": "/robot/ctx"}


def camera_frame(step: int, episode: int) -> np.ndarray:
    """A 480x640 frame that moves with the step: a gradient and a block (JPEG's own kind of content)."""
    y, x = np.mgrid[0:480, 0:640]
    img = np.stack([(x * 255 // 639), (y * 255 // 479), np.full_like(x, 40 * episode)], -1).astype(np.uint8)
    top, left = 40 + 20 * step, 100 + 25 * step
    img[top:top + 120, left:left + 160] = (250, 30, 30 + 10 * step)
    return img


def camera_steps() -> tuple[list[dict], list[dict]]:
    """The same 2 episodes of 16 steps twice: 480x640 camera frames, and the model images of
    their JPEG messages (what the policy node makes of each)."""
    big, small = make_steps(2, 16), make_steps(2, 16)
    for b, s in zip(big, small):
        b["image"] = camera_frame(b["step"], b["episode"])
        msg = fill_jpeg(new_message(COMPRESSED_IMAGE), b["image"], b["stamp"])
        s["image"] = camera.model_image(msg, 64)
    return big, small


def same_store(a: MCAPDataset, b: MCAPDataset) -> None:
    sa, sb = a.stores[0], b.stores[0]
    assert sa.report.rejected is None and sb.report.rejected is None, (sa.report.rejected, sb.report.rejected)
    assert sa.image_shape == sb.image_shape == (64, 64, 3)
    assert np.array_equal(np.asarray(sa.images), np.asarray(sb.images))
    assert set(sa.arrays) == set(sb.arrays)
    for k in sa.arrays:
        assert np.array_equal(sa.arrays[k], sb.arrays[k]), k
    index = a.sample_index(6)   # the same windows from both: the batches the model trains on
    ba, bb = a.gather(index), b.gather(index)
    assert set(ba) == set(bb) and all(np.array_equal(ba[k], bb[k]) for k in ba)


def test_jpeg_camera_bags_give_the_tensors_of_the_same_frames_at_64x64(tmp_path):
    big, small = camera_steps()
    jpeg = write_bag(tmp_path / "jpeg", big, image_type=COMPRESSED_IMAGE, fill_image=fill_jpeg,
                     image_topic="image/compressed")
    native = write_bag(tmp_path / "native", small)
    foreign = write_rosbags_bag(tmp_path / "foreign", big, ROBOT, image_type=COMPRESSED_IMAGE, fill_image=fill_jpeg)
    cache = tmp_path / "cache"
    ds_native = MCAPDataset([native], seq_len=4, seed=5, cache_dir=cache)
    ds_jpeg = MCAPDataset([jpeg], topics=TopicMap.parse([f"image={COMPRESSED_TOPIC}"]), seq_len=4, seed=5,
                          cache_dir=cache)
    robot = TopicMap.parse([f"{k}={t}" for k, t in ROBOT.items()])
    ds_foreign = MCAPDataset([foreign], topics=robot, seq_len=4, seed=5, cache_dir=cache)
    assert ds_native.num_steps == 32 and ds_native.num_episodes == 2
    same_store(ds_jpeg, ds_native)
    same_store(ds_foreign, ds_native)
    assert np.array_equal(np.asarray(ds_native.stores[0].images), np.stack([s["image"] for s in small]))
    assert ds_jpeg.report.sources[0].topics[COMPRESSED_TOPIC]["type"] == COMPRESSED_IMAGE
    # From the cache the second time, the same frames.
    again = MCAPDataset([jpeg], topics=TopicMap.parse([f"image={COMPRESSED_TOPIC}"]), seq_len=4, seed=5,
                        cache_dir=cache)
    assert again.report.sources[0].cached
    same_store(again, ds_native)


def test_another_size_or_crop_is_its_own_cache_entry_and_an_outdated_entry_is_rebuilt(tmp_path):
    big, _ = camera_steps()
    jpeg = write_bag(tmp_path / "jpeg", big[:8], image_type=COMPRESSED_IMAGE, fill_image=fill_jpeg,
                     image_topic="image/compressed")
    topics = TopicMap.parse([f"image={COMPRESSED_TOPIC}"])
    cache = tmp_path / "cache"
    # What an entry made before frames were resized looks like: the default key, other frames.
    ingest_source(jpeg, topics, cache / cache_key(jpeg, topics), ImageSpec(32))
    ds = MCAPDataset([jpeg], topics=topics, seq_len=4, cache_dir=cache)
    assert not ds.report.sources[0].cached and ds.stores[0].image_shape == (64, 64, 3)
    full = MCAPDataset([jpeg], topics=topics, seq_len=4, cache_dir=cache, crop="full")
    assert not full.report.sources[0].cached
    msg = fill_jpeg(new_message(COMPRESSED_IMAGE), big[3]["image"], big[3]["stamp"])
    assert np.array_equal(np.asarray(full.stores[0].images[3]), camera.model_image(msg, 64, camera.Crop.parse("full")))
    assert not np.array_equal(np.asarray(full.stores[0].images[3]), np.asarray(ds.stores[0].images[3]))
    with pytest.raises(ValueError, match="crop"):
        MCAPDataset([], crop="middle")


@pytest.mark.process
def test_protocad_train_trains_from_a_jpeg_camera_bag(tmp_path):
    big, _ = camera_steps()
    bag = write_bag(tmp_path / "jpeg", big, image_type=COMPRESSED_IMAGE, fill_image=fill_jpeg,
                    image_topic="image/compressed")
    run_dir = tmp_path / "run"
    r = run_cli("trainer.learn.train", "--logs", bag, "--topic", f"image={COMPRESSED_TOPIC}", "--task",
                "pendulum_swingup", *TINY, "--updates", "2", "--run-dir", run_dir, "--cache-dir", tmp_path / "cache")
    assert r.returncode == 0, r.stdout + r.stderr
    assert f"{COMPRESSED_TOPIC} as image x32" in r.stdout and "finished at update 2" in r.stdout
    assert ckpt_counters(run_dir / "checkpoints" / "latest.pt")["agent_updates"] == 2
    assert T.topic_name("/protocad", "image/compressed") == COMPRESSED_TOPIC
