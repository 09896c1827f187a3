"""trainer.data.dataset on real MCAP bags: episode rebuild, the reported problems, the step convention,
window sampling, the on-disk store and its reuse, truncated files."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from helpers.bags import DT_NS, answer, make_steps, write_bag

from trainer.data.dataset import DatasetError, MCAPDataset, TopicMap, find_sources


def test_episode_rebuild_reports_gaps_duplicates_foreign_topics_and_unanswered(tmp_path):
    steps = make_steps(3, 12)                          # episodes 0, 1, 2 of 12 steps
    dropped = [s for s in steps if s["episode"] == 1 and s["step"] in (4, 5)]
    steps = [s for s in steps if s not in dropped]     # a gap: episode 1 misses step ids 4..5
    no_answer = next(s for s in steps if s["episode"] == 2 and s["step"] == 6)
    no_answer["action"] = None                         # an observation nobody answered (mid-episode)
    steps[-1]["action"] = None                         # the log ends before the last answer
    dup = {steps[3]["stamp"], steps[20]["stamp"]}      # two stamps published twice
    bag = write_bag(tmp_path / "bag", steps, duplicate_stamps=dup,
                    extra_topics={"/some/foreign_topic": 5})
    ds = MCAPDataset([bag], seq_len=4, seed=0, cache_dir=tmp_path / "cache")
    rep = ds.report.sources[0]
    assert rep.rejected is None
    assert rep.steps == len(steps) and rep.episodes == 3
    assert rep.gaps == 1 and rep.missing_step_ids == 2
    assert rep.gap_examples == ["episode 1 steps 4..5"]
    # duplicates: every topic written twice at those stamps (image, step_info, context)
    assert rep.duplicates["/protocad/image"] == 2 and rep.duplicates["/protocad/step_info"] == 2
    assert rep.foreign_topics == {"/some/foreign_topic": {"type": "std_msgs/msg/String", "count": 5}}
    assert rep.missing_actions == 1          # episode 2 step 7 has no known incoming action
    assert rep.unanswered_final == 0         # the final obs is is_last: its answer is not needed...
    assert rep.unanswered_is_last == 1       # ...and is reported as such
    # segments: ep0, ep1 split at the gap (2), ep2 split at the missing answer (2)
    assert rep.segments == 5
    text = str(ds.report)
    for needle in ("1 gap(s) within episodes, 2 step id(s) missing", "episode 1 steps 4..5",
                   "duplicate message(s) on /protocad/image", "foreign topics (present, unused): "
                   "/some/foreign_topic [std_msgs/msg/String] x5",
                   "1 observation(s) without an action answering them"):
        assert needle in text, text


def test_action_shift_convention_and_windows_stay_inside_episodes(tmp_path):
    steps = make_steps(4, 10) + make_steps(1, 3, first_episode=4, t0_ns=40 * DT_NS)  # last one too short
    bag = write_bag(tmp_path / "bag", steps)
    ds = MCAPDataset([bag], seq_len=5, seed=3, cache_dir=tmp_path / "cache")
    assert ds.report.short_segments_skipped == 1 and ds.report.short_steps_skipped == 3
    assert "skipped 1 episode segment(s) shorter than 5 steps (3 steps)" in str(ds.report)
    assert ds.num_windows == 4 * (10 - 5 + 1)
    seen = set()
    for _ in range(40):
        b = ds.sample(6)
        assert b["image"].dtype == np.uint8 and b["image"].shape == (6, 5, 64, 64, 3)
        assert b["action"].dtype == np.float32 and b["action"].shape == (6, 5, 1)
        for i in range(6):
            step_ids = b["image"][i, :, 0, 0, 0].astype(int)
            eps = b["image"][i, :, 0, 0, 1].astype(int)
            assert len(set(eps)) == 1, "a window crossed an episode boundary"
            assert np.all(np.diff(step_ids) == 1)
            seen.add((eps[0], step_ids[0]))
            for t, s in enumerate(step_ids):
                # action[t] = the answer to the previous observation; zeros at is_first
                want = 0.0 if s == 0 else answer(s - 1, eps[0])[0]
                assert b["action"][i, t, 0] == pytest.approx(want)
                assert b["is_first"][i, t] == (s == 0)
                assert b["reward"][i, t] == pytest.approx(0.0 if s == 0 else s / 10)
    assert len(seen) == ds.num_windows   # uniform over all windows: every one drawn
    # seeded: the same seed draws the same batches; the state resumes the stream
    a, b = (MCAPDataset([bag], seq_len=5, seed=11, cache_dir=tmp_path / "cache") for _ in range(2))
    assert a.sample_index(8) == b.sample_index(8)
    state = a.state_dict()
    nxt = a.sample_index(8)
    b.load_state_dict(json.loads(json.dumps(state)))
    assert b.sample_index(8) == nxt


def test_store_is_on_disk_uint8_reused_and_appendable(tmp_path):
    cache = tmp_path / "cache"
    bag1 = write_bag(tmp_path / "bags" / "b1", make_steps(2, 12))
    ds = MCAPDataset([tmp_path / "bags"], seq_len=4, cache_dir=cache)
    assert [s.cached for s in ds.report.sources] == [False]
    entries = [p for p in cache.iterdir() if p.is_dir()]
    assert len(entries) == 1
    store = ds.stores[0]
    assert isinstance(store.images, np.memmap) and store.images.dtype == np.uint8
    assert (entries[0] / "images.u8").stat().st_size == 24 * 64 * 64 * 3
    index_mtime = (entries[0] / "index.json").stat().st_mtime_ns
    # a second run reuses the store (same bag files: path, size, mtime)
    ds2 = MCAPDataset([bag1], seq_len=4, cache_dir=cache)
    assert ds2.report.sources[0].cached and ds2.num_steps == 24
    assert (entries[0] / "index.json").stat().st_mtime_ns == index_mtime
    # appending a newly recorded bag (the loop does this after every collection phase)
    write_bag(tmp_path / "bags" / "b2", make_steps(1, 12, first_episode=5))
    added = ds2.add([tmp_path / "bags"])          # b1 known, only b2 indexed
    assert len(added) == 1 and ds2.num_steps == 36 and ds2.num_episodes == 3
    assert ds2.num_windows == 3 * (12 - 4 + 1)
    # a changed bag (new mtime/size) gets a new store, never a stale one
    shutil.rmtree(bag1)
    write_bag(bag1, make_steps(1, 12))
    ds3 = MCAPDataset([bag1], seq_len=4, cache_dir=cache)
    assert not ds3.report.sources[0].cached and ds3.num_steps == 12


def test_truncated_log_yields_every_complete_message_and_a_clear_report(tmp_path):
    from trainer.bag.reader import BagReader

    steps = make_steps(3, 40)
    bag = write_bag(tmp_path / "bag", steps, chunk_size=64 * 1024, compression="none")
    f = next(bag.glob("*.mcap"))
    data = f.read_bytes()
    cut = tmp_path / "cut"
    cut.mkdir()
    (cut / f.name).write_bytes(data[: int(len(data) * 0.6)])   # writer killed: no footer, no metadata
    # reference: what a reader recovers from the cut file (every complete chunk)
    recovered = {}
    for m in BagReader(cut).messages():
        recovered.setdefault(m.topic, set()).add(m.log_time_ns)
    both = {t - 3 for t in recovered["/protocad/image"]} & {t - 2 for t in recovered["/protocad/step_info"]}
    assert 0 < len(both) < len(steps)
    ds = MCAPDataset([cut], seq_len=4, cache_dir=tmp_path / "cache")
    rep = ds.report.sources[0]
    assert rep.rejected is None and rep.truncated
    assert rep.steps == len(both)                         # every complete step, nothing invented
    stamps = set(np.asarray(ds.stores[0].arrays["stamp"]).tolist())
    assert stamps == both
    text = str(ds.report)
    assert "TRUNCATED" in text and f.name in text and "no metadata.yaml" in text
    ds.sample(2)                                          # and it trains on what is there


def test_foreign_topic_names_and_clear_errors(tmp_path):
    bag = write_bag(tmp_path / "bag", make_steps(1, 10), namespace="/robot")
    # default topics find nothing: rejected with the reason, and sampling explains itself
    ds = MCAPDataset([bag], seq_len=4, cache_dir=tmp_path / "cache")
    assert "no usable messages for image (/protocad/image)" in ds.report.sources[0].rejected
    assert set(ds.report.sources[0].foreign_topics) == {"/robot/image", "/robot/step_info",
                                                        "/robot/context", "/robot/action"}
    with pytest.raises(DatasetError, match="no training window"):
        ds.sample(1)
    ok = MCAPDataset([bag], seq_len=4, topics=TopicMap.parse(["image=/robot/image", "step_info=/robot/step_info",
                                                             "action=/robot/action", "context=/robot/context"]),
                     cache_dir=tmp_path / "cache")
    assert ok.num_steps == 10 and not ok.report.problems()
    assert TopicMap.parse([], namespace="/robot") == ok.topics
    # a topic with the wrong type is named
    wrong = MCAPDataset([bag], seq_len=4, topics=TopicMap.parse(["image=/robot/context", "context=none"], "/robot"),
                        cache_dir=tmp_path / "cache")
    assert any("has type sensor_msgs/msg/JointState, expected sensor_msgs/msg/Image" in p
               for p in wrong.report.problems())
    with pytest.raises(ValueError, match="KEY=/topic"):
        TopicMap.parse(["camera=/x"])
    with pytest.raises(DatasetError, match="does not exist"):
        find_sources([tmp_path / "nope"])


@pytest.mark.process
def test_dataset_cli_prints_the_report(tmp_path):
    from helpers.bags import run_cli

    bag = write_bag(tmp_path / "bag", make_steps(2, 6), extra_topics={"/x": 1})
    r = run_cli("trainer.data.dataset", bag, "--seq-len", "4", "--cache-dir", tmp_path / "c", "--json", tmp_path / "r.json")
    assert r.returncode == 0, r.stderr
    assert "2 episodes" in r.stdout and "foreign topics" in r.stdout
    assert json.loads((tmp_path / "r.json").read_text())["steps"] == 12


def test_a_full_cache_disk_is_a_clear_error_and_skips_nothing(tmp_path):
    """Frames that cannot be cached are not 'bad messages': indexing stops with the reason,
    the partial cache entry is removed, and the bag is untouched."""
    import subprocess

    from trainer.data.dataset import CacheWriteError, MCAPDataset

    bag = write_bag(tmp_path / "bag", make_steps(2, 60))
    mnt = tmp_path / "cache_disk"
    mnt.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(mnt)]).returncode != 0:
        pytest.skip("cannot mount a tmpfs here")
    try:
        with pytest.raises(CacheWriteError, match="No space left on device.*logs are untouched"):
            MCAPDataset([bag], seq_len=8, cache_dir=mnt)
        leftovers = [p for p in mnt.rglob("*") if p.is_file()]
        assert not [p for p in leftovers if ".tmp-" in str(p)], leftovers
        ds = MCAPDataset([bag], seq_len=8, cache_dir=tmp_path / "roomy")   # the bag still reads whole
        assert ds.num_steps == 2 * 60
    finally:
        subprocess.run(["umount", "-l", str(mnt)])


def test_cache_budget_evicts_least_recently_used_bags_never_those_in_use(tmp_path):
    import os

    from trainer.data.dataset import MCAPDataset, TopicMap, cache_key

    bags = [write_bag(tmp_path / f"bag{i}", make_steps(1, 40, first_episode=i)) for i in range(3)]
    cache = tmp_path / "cache"
    entry = lambda b: cache / cache_key(b, TopicMap())   # noqa: E731
    MCAPDataset([bags[0]], seq_len=8, cache_dir=cache, cache_budget_gb=0)
    size = sum(f.stat().st_size for f in entry(bags[0]).rglob("*") if f.is_file())
    budget_gb = 2.5 * size / 1e9                      # room for two bags
    MCAPDataset([bags[1]], seq_len=8, cache_dir=cache, cache_budget_gb=budget_gb)
    assert entry(bags[0]).exists() and entry(bags[1]).exists()
    # Last uses set explicitly (file-time resolution varies): bag0 used after bag1.
    os.utime(entry(bags[1]), (1_000_000, 1_000_000))
    os.utime(entry(bags[0]), (2_000_000, 2_000_000))
    ds = MCAPDataset([bags[2]], seq_len=8, cache_dir=cache, cache_budget_gb=budget_gb)
    assert not entry(bags[1]).exists() and entry(bags[0]).exists() and entry(bags[2]).exists()
    # A dataset using more than the budget keeps all of its own entries.
    big = MCAPDataset(bags, seq_len=8, cache_dir=cache, cache_budget_gb=size / 1e9)
    assert all(entry(b).exists() for b in bags) and big.num_steps == ds.num_steps * 3


def test_unreadable_metadata_skips_that_bag_and_repeated_problems_are_one_line(tmp_path):
    logs = tmp_path / "logs"
    write_bag(logs / "good", make_steps(2, 20))
    bad = write_bag(logs / "bad", make_steps(2, 20, first_episode=2))
    (bad / "metadata.yaml").write_bytes(b"\xff\xfe not utf-8 \xff")
    ds = MCAPDataset([logs], seq_len=4, cache_dir=tmp_path / "cache")
    assert ds.num_episodes >= 2                                # the good bag trains
    text = str(ds.report)
    assert "bad" in text and "metadata.yaml" in text           # the bad one named, not fatal
    empty = tmp_path / "empty"
    empty.mkdir()
    for i in range(50):
        (empty / f"f{i}.mcap").write_bytes(b"")
    rep = MCAPDataset([empty, logs / "good"], seq_len=4, cache_dir=tmp_path / "cache3").report
    lines = [p for p in rep.problems() if "empty file" in p]
    assert len(lines) == 1 and "in 50 files" in lines[0], rep.problems()
