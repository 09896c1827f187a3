"""trainer.bag (writer, reader, rosmsg) against independent readers/writers: the mcap library, rosbags, rerun's
MCAP checker, rclpy's serializer. Real files, a real killed writer process."""
from __future__ import annotations

import signal
from pathlib import Path

import numpy as np
import pytest
import yaml
from helpers import wait_until
from helpers.bags import rerun_check

from sim_bridge.contract import topics as T
from trainer.bag import rosmsg
from trainer.bag import writer as bag_writer
from trainer.bag.reader import BagReader, BagReadError, read_bag_metadata
from trainer.bag.rosmsg import TypeSupportError, decode, encode, message_definition, new_message, type_hash
from trainer.bag.writer import DEFAULT_OFFERED_QOS, BagWriteError, BagWriter, qos_profile
from trainer.bag.yamlcpp import yaml_cpp_dump

IMAGE, JOINT = "sensor_msgs/msg/Image", "sensor_msgs/msg/JointState"
CLOCK = "rosgraph_msgs/msg/Clock"
T0 = 1_700_000_000_000_000_000


def image(i: int, h: int = 64, w: int = 64) -> np.ndarray:
    return ((np.arange(h * w * 3).reshape(h, w, 3) + i * 7) % 256).astype(np.uint8)


def write_demo_bag(bag: Path, n: int = 60, **kw) -> BagWriter:
    """n steps of image + action (+ /clock every step); log = source + 50 us."""
    w = BagWriter(bag, **kw)
    w.add_topic("/protocad/image", IMAGE, DEFAULT_OFFERED_QOS)
    w.add_topic("/protocad/action", JOINT, [qos_profile(history="keep_last", depth=100)])
    w.add_topic("/clock", CLOCK)
    for i in range(n):
        stamp = i * 20_000_000
        src = T0 + i * 1_000_000
        w.write_message("/protocad/image", T.fill_image(new_message(IMAGE), image(i), stamp),
                        src + 50_000, src)
        w.write_message("/protocad/action",
                        T.fill_action(new_message(JOINT), [i / n, -i / n], ["a0", "a1"], stamp),
                        src + 60_000, src + 10_000)
        clock = new_message(CLOCK)
        T.set_stamp(clock.clock, stamp)
        w.write_message("/clock", clock, src + 70_000, src + 20_000)
    w.close()
    return w


# ------------------------------------------------------------------------------ type support

def test_message_definition_is_rosbag2s_concatenation():
    text = message_definition(IMAGE)
    share = Path(rosmsg._share_dir("sensor_msgs")).parent
    image_msg = (share / "sensor_msgs/msg/Image.msg").read_text()
    header_msg = (share / "std_msgs/msg/Header.msg").read_text()
    time_msg = (share / "builtin_interfaces/msg/Time.msg").read_text()
    sep = "\n" + "=" * 80 + "\n"
    assert text == (image_msg + sep + "MSG: std_msgs/Header\n" + header_msg
                    + sep + "MSG: builtin_interfaces/Time\n" + time_msg)
    assert message_definition("sensor_msgs/Image") == text  # short names accepted
    # every dependency once, depth-first, sorted (std::set) - DiagnosticArray has 3 levels
    diag = message_definition("diagnostic_msgs/msg/DiagnosticArray")
    heads = [ln for ln in diag.splitlines() if ln.startswith("MSG: ")]
    assert heads == ["MSG: diagnostic_msgs/DiagnosticStatus", "MSG: diagnostic_msgs/KeyValue",
                     "MSG: std_msgs/Header", "MSG: builtin_interfaces/Time"]


def test_type_hash_matches_rosbags_typestore():
    from rosbags.typesys import Stores, get_typestore
    ts = get_typestore(Stores.ROS2_JAZZY)
    for t in (IMAGE, JOINT, CLOCK, "diagnostic_msgs/msg/DiagnosticArray"):
        assert type_hash(t) == ts.hash_rihs01(t)
    with pytest.raises(TypeSupportError, match="no_such_pkg"):
        type_hash("no_such_pkg/msg/Foo")
    with pytest.raises(TypeSupportError, match="invalid message type"):
        new_message("not a type")


def test_new_message_encode_matches_rclpy_and_decode_is_lenient():
    from rclpy.serialization import deserialize_message, serialize_message
    from sensor_msgs.msg import Image, JointState
    msg = T.fill_image(new_message(IMAGE), image(3), 1_500_000_123)
    data = encode(IMAGE, msg)
    ros = deserialize_message(data, Image)
    assert (ros.height, ros.width, ros.encoding, ros.step) == (64, 64, "rgb8", 192)
    assert bytes(ros.data) == image(3).tobytes() and ros.header.frame_id == "camera"
    assert T.stamp_to_ns(ros.header.stamp) == 1_500_000_123
    assert (T.read_image(decode(IMAGE, data)) == image(3)).all()
    # numpy arrays assigned by hand are accepted
    js = new_message(JOINT)
    js.name, js.effort = ["x", "y"], np.array([0.5, -0.25])
    assert list(deserialize_message(encode(JOINT, js), JointState).effort) == [0.5, -0.25]
    # rclpy/FastCDR writes trailing padding after an empty float64[]: decode must accept it
    ros_js = JointState()
    T.fill_step_info(ros_js, T.StepInfo(1.5, 1.0, False, True, False, 2, 9), 42)
    ros_js.velocity = []
    decoded = decode(JOINT, serialize_message(ros_js))
    assert T.read_step_info(decoded) == T.StepInfo(1.5, 1.0, False, True, False, 2, 9)
    assert encode(JOINT, decoded) == encode(JOINT, ros_js)  # decoded objects re-encode
    with pytest.raises(ValueError, match="cannot decode"):
        decode(IMAGE, b"\x00\x01\x00\x00\xff")


def test_yaml_matches_a_real_jazzy_metadata_yaml():
    """Byte-for-byte the layout `ros2 bag record` (Jazzy, yaml-cpp) writes."""
    expected = """rosbag2_bagfile_information:
  version: 9
  storage_identifier: mcap
  duration:
    nanoseconds: 28000217976
  starting_time:
    nanoseconds_since_epoch: 1791340443504644767
  message_count: 29
  topics_with_message_count:
    - topic_metadata:
        name: /number_count
        type: example_interfaces/msg/Int64
        serialization_format: cdr
        offered_qos_profiles:
          - history: unknown
            depth: 0
            reliability: reliable
            durability: volatile
            deadline:
              sec: 9223372036
              nsec: 854775807
            lifespan:
              sec: 9223372036
              nsec: 854775807
            liveliness: automatic
            liveliness_lease_duration:
              sec: 9223372036
              nsec: 854775807
            avoid_ros_namespace_conventions: false
        type_description_hash: RIHS01_1b3b9a6502f560d079520c73c685a9550e5a1838d2cefd537fe0aba75a3639a0
      message_count: 29
  compression_format: ""
  compression_mode: ""
  relative_file_paths:
    - rosbag2_2026_10_07-10_34_02_0.mcap
  files:
    - path: rosbag2_2026_10_07-10_34_02_0.mcap
      starting_time:
        nanoseconds_since_epoch: 1791340443504644767
      duration:
        nanoseconds: 28000217976
      message_count: 29
  custom_data: ~
  ros_distro: jazzy"""
    f = "rosbag2_2026_10_07-10_34_02_0.mcap"
    info = {
        "version": 9, "storage_identifier": "mcap", "duration": {"nanoseconds": 28000217976},
        "starting_time": {"nanoseconds_since_epoch": 1791340443504644767}, "message_count": 29,
        "topics_with_message_count": [{"topic_metadata": {
            "name": "/number_count", "type": "example_interfaces/msg/Int64",
            "serialization_format": "cdr", "offered_qos_profiles": list(DEFAULT_OFFERED_QOS),
            "type_description_hash": "RIHS01_1b3b9a6502f560d079520c73c685a9550e5a1838d2cefd537"
                                     "fe0aba75a3639a0"}, "message_count": 29}],
        "compression_format": "", "compression_mode": "", "relative_file_paths": [f],
        "files": [{"path": f, "starting_time": {"nanoseconds_since_epoch": 1791340443504644767},
                   "duration": {"nanoseconds": 28000217976}, "message_count": 29}],
        "custom_data": None, "ros_distro": "jazzy"}
    assert yaml_cpp_dump({"rosbag2_bagfile_information": info}) == expected


# ------------------------------------------------------------------------------ writer

@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
def test_writer_output_passes_rerun_and_is_read_by_mcap_and_rosbags(tmp_path, compression):
    from mcap.reader import make_reader
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    bag = tmp_path / "demo"
    n = 40
    write_demo_bag(bag, n, compression=compression, chunk_size=32 * 1024,
                   custom_data={"task": "pendulum_swingup"})
    assert sorted(p.name for p in bag.iterdir()) == ["demo_0.mcap", "metadata.yaml"]
    res = rerun_check(bag / "demo_0.mcap")
    assert res.returncode == 0, res.stdout + res.stderr

    # -- the mcap library: profile, schemas, channels, metadata records, times
    with open(bag / "demo_0.mcap", "rb") as fh:
        reader = make_reader(fh)
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        schemas = {s.name: s for s in summary.schemas.values()}
        assert set(schemas) == {IMAGE, JOINT, CLOCK}
        assert all(s.encoding == "ros2msg" for s in schemas.values())
        assert schemas[IMAGE].data.decode() == message_definition(IMAGE)
        chans = {c.topic: c for c in summary.channels.values()}
        assert all(c.message_encoding == "cdr" for c in chans.values())
        assert chans["/protocad/image"].metadata["topic_type_hash"] == type_hash(IMAGE)
        qos = yaml.safe_load(chans["/protocad/action"].metadata["offered_qos_profiles"])
        assert qos[0]["history"] == "keep_last" and qos[0]["depth"] == 100
        assert chans["/clock"].metadata["offered_qos_profiles"] == "[]"
        chunk_comp = {ci.compression for ci in summary.chunk_indexes}
        assert chunk_comp == {"" if compression == "none" else compression}
        records = [m for m in reader.iter_metadata() if m.name == "rosbag2"]
        assert len(records) == 2  # at open and at close, as rosbag2's SequentialWriter
        final = yaml.safe_load(records[-1].metadata["serialized_metadata"])
        assert final["version"] == 9 and final["message_count"] == 3 * n
        got = [(ch.topic, m.log_time, m.publish_time) for _s, ch, m in reader.iter_messages()]
    assert got[:3] == [("/protocad/image", T0 + 50_000, T0), ("/protocad/action", T0 + 60_000,
                       T0 + 10_000), ("/clock", T0 + 70_000, T0 + 20_000)]

    # -- metadata.yaml
    info = read_bag_metadata(bag)
    assert info["version"] == 9 and info["storage_identifier"] == "mcap"
    assert info["relative_file_paths"] == ["demo_0.mcap"] and info["ros_distro"] == "jazzy"
    assert info["message_count"] == 3 * n and info["compression_mode"] == ""
    assert info["starting_time"]["nanoseconds_since_epoch"] == T0 + 50_000
    assert info["duration"]["nanoseconds"] == (n - 1) * 1_000_000 + 20_000
    assert info["files"][0]["message_count"] == 3 * n
    assert info["custom_data"] == {"task": "pendulum_swingup"}
    tm = {t["topic_metadata"]["name"]: t for t in info["topics_with_message_count"]}
    assert tm["/protocad/image"]["message_count"] == n
    assert tm["/protocad/image"]["topic_metadata"]["type_description_hash"] == type_hash(IMAGE)
    assert tm["/protocad/image"]["topic_metadata"]["offered_qos_profiles"][0]["reliability"] \
        == "reliable"

    # -- rosbags (independent reader) on the bag directory
    ts = get_typestore(Stores.ROS2_JAZZY)
    with Reader(bag) as rb:
        assert rb.message_count == 3 * n
        conns = {c.topic: c for c in rb.connections}
        assert conns["/protocad/image"].msgtype == IMAGE
        assert conns["/protocad/action"].digest == type_hash(JOINT)
        assert conns["/protocad/image"].ext.offered_qos_profiles[0].depth == 0
        imgs = [ts.deserialize_cdr(raw, IMAGE) for c, _t, raw in
                rb.messages(connections=[conns["/protocad/image"]])]
        acts = [ts.deserialize_cdr(raw, JOINT) for c, _t, raw in
                rb.messages(connections=[conns["/protocad/action"]])]
    assert len(imgs) == n and (T.read_image(imgs[7]) == image(7)).all()
    assert T.stamp_to_ns(imgs[7].header.stamp) == 7 * 20_000_000
    assert list(acts[5].effort) == pytest.approx([5 / n, -5 / n]) and acts[5].name == ["a0", "a1"]


def test_writer_rules(tmp_path):
    bag = tmp_path / "rules"
    w = BagWriter(bag)
    with pytest.raises(BagWriteError, match="add_topic"):
        w.write("/nope", b"\x00\x01\x00\x00", 1)
    w.add_topic("/a", JOINT)
    w.add_topic("/a", "sensor_msgs/JointState")  # same type again: fine
    with pytest.raises(BagWriteError, match="already added"):
        w.add_topic("/a", IMAGE)
    w.write_message("/a", new_message(JOINT), 5)
    w.close()
    w.close()  # idempotent
    assert w.closed and (bag / "metadata.yaml").exists()
    with pytest.raises(BagWriteError, match="closed"):
        w.write("/a", b"", 6)
    with pytest.raises(BagWriteError, match="already exists"):
        BagWriter(bag)
    with pytest.raises(ValueError, match="greater than 1024"):
        BagWriter(tmp_path / "x", max_bagfile_size=100)
    with pytest.raises(ValueError, match="compression"):
        BagWriter(tmp_path / "y", compression="gzip")


def test_read_order_is_log_time_per_file(tmp_path):
    """Out-of-order log times (within and across overlapping chunks) come back sorted."""
    bag = tmp_path / "order"
    rng = np.random.default_rng(0)
    times = rng.permutation(300) * 1000 + T0
    with BagWriter(bag, chunk_size=2048) as w:
        w.add_topic("/x", JOINT)
        for k, t in enumerate(times):
            w.write_message("/x", T.fill_named(new_message(JOINT), ["k"], [k], 0), int(t))
    got = [m.log_time_ns for m in BagReader(bag).messages()]
    assert got == sorted(times.tolist())


def test_split_by_size_and_duration(tmp_path):
    from rosbags.rosbag2 import Reader
    bag = tmp_path / "split"
    rng = np.random.default_rng(1)
    n = 120
    with BagWriter(bag, compression="none", chunk_size=4096, max_bagfile_size=20_000) as w:
        w.add_topic("/protocad/image", IMAGE, DEFAULT_OFFERED_QOS)
        for i in range(n):
            img = rng.integers(0, 256, (16, 16, 3), dtype=np.uint8)
            w.write_message("/protocad/image", T.fill_image(new_message(IMAGE), img, i),
                            T0 + i * 1000)
    files = sorted(p.name for p in bag.glob("*.mcap"))
    assert len(files) >= 3
    info = read_bag_metadata(bag)
    expected = [f"split_{k}.mcap" for k in range(len(files))]
    assert info["relative_file_paths"] == expected == [f["path"] for f in info["files"]]
    assert sum(f["message_count"] for f in info["files"]) == n == info["message_count"]
    for name in expected:
        assert (bag / name).stat().st_size < 20_000 + 8 * 1024  # split near the limit
        res = rerun_check(bag / name)
        assert res.returncode == 0, res.stdout + res.stderr
    r = BagReader(bag)
    assert r.report.ok and not r.report.truncated and r.files == [str(bag / f) for f in expected]
    stamps = [T.stamp_to_ns(r.decode(m).header.stamp) for m in r.messages()]
    assert stamps == list(range(n))
    with Reader(bag) as rb:
        assert rb.message_count == n
        assert sum(1 for _ in rb.messages()) == n

    bag2 = tmp_path / "dur"
    with BagWriter(bag2, max_bagfile_duration_s=1.0) as w:
        w.add_topic("/clock", CLOCK)
        for i in range(50):  # 4.9 s of log time
            w.write_message("/clock", new_message(CLOCK), T0 + i * 100_000_000)
    info = read_bag_metadata(bag2)
    assert len(info["files"]) == 5
    assert all(f["duration"]["nanoseconds"] <= 1_000_000_000 for f in info["files"])
    assert [m.log_time_ns for m in BagReader(bag2).messages()] == \
        [T0 + i * 100_000_000 for i in range(50)]


# ------------------------------------------------------------------------------ reader

def test_reads_bag_written_by_rosbags(tmp_path):
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore
    ts = get_typestore(Stores.ROS2_JAZZY)
    Twist, Vector3 = ts.types["geometry_msgs/msg/Twist"], ts.types["geometry_msgs/msg/Vector3"]
    String = ts.types["std_msgs/msg/String"]
    bag = tmp_path / "foreign_names"
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        c1 = w.add_connection("/robot/cmd_vel", "geometry_msgs/msg/Twist", typestore=ts)
        c2 = w.add_connection("/robot/status", "std_msgs/msg/String", typestore=ts)
        for i in range(25):
            w.write(c1, 1000 + 2 * i, ts.serialize_cdr(
                Twist(linear=Vector3(x=float(i), y=0.0, z=0.0),
                      angular=Vector3(x=0.0, y=0.0, z=-float(i))), c1.msgtype))
            w.write(c2, 1001 + 2 * i, ts.serialize_cdr(String(data=f"s{i}"), c2.msgtype))
    r = BagReader(bag)
    assert r.report.ok and not r.report.truncated, r.report.summary()
    assert r.report.topic_types == {"/robot/cmd_vel": "geometry_msgs/msg/Twist",
                                    "/robot/status": "std_msgs/msg/String"}
    assert r.report.counts == {"/robot/cmd_vel": 25, "/robot/status": 25}
    msgs = list(r.messages())
    assert [m.log_time_ns for m in msgs] == list(range(1000, 1050))
    assert [r.decode(m).angular.z for m in msgs if m.topic == "/robot/cmd_vel"] == \
        [-float(i) for i in range(25)]
    assert [r.decode(m).data for m in r.messages(topics=["/robot/status"])] == \
        [f"s{i}" for i in range(25)]


def _expected_chunks(path: Path) -> list[tuple[int, int, int]]:
    """(chunk start offset, end offset, messages in it) from the summary (mcap library)."""
    from mcap.reader import make_reader
    from mcap.records import Chunk, Message
    from mcap.stream_reader import breakup_chunk
    with open(path, "rb") as fh:
        summary = make_reader(fh).get_summary()
        out = []
        for ci in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
            fh.seek(ci.chunk_start_offset + 9)
            from mcap.data_stream import ReadDataStream
            chunk = Chunk.read(ReadDataStream(fh))
            n = sum(isinstance(r, Message) for r in breakup_chunk(chunk))
            out.append((ci.chunk_start_offset, ci.chunk_start_offset + ci.chunk_length, n))
    return out


def test_truncated_copy_recovers_every_complete_chunk(tmp_path):
    bag = tmp_path / "good"
    write_demo_bag(bag, 80, chunk_size=8 * 1024)
    good = bag / "good_0.mcap"
    data = good.read_bytes()
    chunks = _expected_chunks(good)
    assert len(chunks) >= 5
    all_msgs = list(BagReader(good).messages())
    for k in (1, 3, len(chunks) - 1):
        start, end, _ = chunks[k]
        for cut in (start + (end - start) // 2, end):  # inside chunk k, right after it
            cut_file = tmp_path / f"cut_{k}_{cut}.mcap"
            cut_file.write_bytes(data[:cut])
            r = BagReader(cut_file)
            want = sum(c[2] for c in chunks[:k + (cut == end)])
            got = list(r.messages())
            assert len(got) == want and r.report.message_count == want
            assert str(cut_file) in r.report.truncated and r.report.ok
            assert "no MCAP footer" in r.report.truncated[str(cut_file)]
            assert sorted(got, key=lambda m: m.log_time_ns) == got
            assert set(got) <= set(all_msgs)  # the same messages, not garbage
            assert [(m.log_time_ns, m.data) for m in got] == _streamed_until_it_fails(cut_file)


def _streamed_until_it_fails(path: Path) -> list[tuple[int, bytes]]:
    """(log time, data) of every message mcap's own StreamReader yields from a cut file before
    it stops (at the cut chunk: its CRC or its decompression fails), in log-time order."""
    from mcap.records import Message
    from mcap.stream_reader import StreamReader
    out = []
    with open(path, "rb") as fh:
        try:
            for record in StreamReader(fh, validate_crcs=True).records:
                if isinstance(record, Message):
                    out.append((record.log_time, record.data))
        except Exception:  # noqa: BLE001  what the cut chunk raises (CRC, zstd, EndOfFile) ends it
            pass
    return sorted(out)


def test_corrupt_chunk_is_reported_and_skipped(tmp_path):
    bag = tmp_path / "flip"
    write_demo_bag(bag, 60, chunk_size=8 * 1024, compression="none")
    path = bag / "flip_0.mcap"
    chunks = _expected_chunks(path)
    start, end, lost = chunks[2]
    data = bytearray(path.read_bytes())
    data[(start + end) // 2] ^= 0xFF  # one flipped byte inside chunk 2: its CRC fails
    path.write_bytes(bytes(data))
    r = BagReader(bag)
    got = list(r.messages())
    assert len(got) == 180 - lost
    assert "corrupt chunk" in r.report.errors[str(path)] and "CRC" in r.report.errors[str(path)]
    with pytest.raises(BagReadError, match="corrupt chunk"):
        list(BagReader(bag, strict=True).messages())


def test_foreign_and_garbage_files_are_reported(tmp_path):
    bag = tmp_path / "ok"
    write_demo_bag(bag, 5)
    text = tmp_path / "notes.mcap"
    text.write_text("this is not an mcap file\n")
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    png = tmp_path / "img.mcap"
    png.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(100))
    r = BagReader([text, bag, empty, png, tmp_path / "missing.mcap"])
    assert "not an MCAP file" in r.report.errors[str(text)]
    assert "empty" in r.report.errors[str(empty)]
    assert "MCAP magic" in r.report.errors[str(png)]
    assert "no such file" in r.report.errors[str(tmp_path / "missing.mcap")]
    assert r.report.counts["/protocad/image"] == 5 and len(list(r.messages())) == 15
    with pytest.raises(BagReadError, match="not an MCAP file"):
        BagReader([bag, text], strict=True)
    # a bag directory without metadata.yaml (killed recorder) is read in split order
    (bag / "metadata.yaml").unlink()
    r = BagReader(bag)
    assert r.report.ok and len(list(r.messages())) == 15
    assert any("no metadata.yaml" in w for w in r.report.warnings)


WRITER_SCRIPT = r"""
import sys, time
from trainer.bag.reader import BagReadError, BagReader, read_bag_metadata
from trainer.bag.rosmsg import TypeSupportError, decode, encode, message_definition, new_message, type_hash
from trainer.bag.writer import BagWriteError, BagWriter, DEFAULT_OFFERED_QOS, qos_profile
from trainer.bag.yamlcpp import yaml_cpp_dump
from sim_bridge.contract import topics as T
w = BagWriter(sys.argv[1], chunk_size=2048, compression="zstd")
w.add_topic("/x", "sensor_msgs/msg/JointState")
i = 0
while True:
    w.write_message("/x", T.fill_named(new_message("sensor_msgs/msg/JointState"), ["i"], [i], i),
                    1_000_000 + i)
    i += 1
    if i % 100 == 0:
        w.flush()
        print(f"flushed {i}", flush=True)
        time.sleep(0.01)
"""


@pytest.mark.process
def test_writer_killed_with_sigkill_leaves_readable_chunks(tmp_path, spawn):
    bag = tmp_path / "killed"
    proc = spawn("writer", "-c", WRITER_SCRIPT, str(bag))

    def flushed() -> int:
        lines = [ln for ln in proc.output().splitlines() if ln.startswith("flushed ")]
        return int(lines[-1].split()[1]) if lines else 0

    wait_until(lambda: flushed() >= 1500 or not proc.alive(), 60, "the writer to flush 1500")
    assert proc.alive(), proc.output()
    at_least = flushed()  # every message reported flushed is in a complete chunk on disk
    proc.stop(signal.SIGKILL)
    assert not (bag / "metadata.yaml").exists()
    r = BagReader(bag)
    f = str(bag / "killed_0.mcap")
    assert r.report.ok and f in r.report.truncated, r.report.summary()
    idx = [int(decode(JOINT, m.data).position[0]) for m in r.messages()]
    assert len(idx) >= at_least and idx == list(range(len(idx)))  # a gap-free prefix
    assert r.report.counts["/x"] == len(idx)
    assert rerun_check(bag / "killed_0.mcap").returncode != 0  # no footer: rerun refuses too


def test_a_bag_file_removed_while_recording_is_a_write_failure_not_silence(tmp_path):
    """Writes to a deleted file succeed at the OS level; the writer notices at its next chunk."""
    import pytest

    bag = tmp_path / "bag"
    w = BagWriter(bag, chunk_size=1024)
    w.add_topic("/x", "std_msgs/msg/String", [])
    w.write_message("/x", {"data": "a" * 100}, 1)
    (bag / "bag_0.mcap").unlink()
    with pytest.raises(BagWriteError, match="was removed while recording"):
        for t in range(2, 100):
            w.write_message("/x", {"data": "b" * 100}, t)
    w.close()
    assert "was removed while recording" in w.failure
    assert (bag / "metadata.yaml").exists() and not (bag / ".protocad-reserve").exists()


class _FailingFile:
    """Fault injection (named as such: a disk that fills exactly while a split starts its next
    file cannot be produced on demand): every write to files of the given name fails ENOSPC."""

    def __init__(self, real, name: str):
        self.real, self.name = real, name

    def __call__(self, path):
        f = self.real(path)
        if Path(path).name == self.name:
            def fail(data):
                raise OSError(28, "No space left on device")
            f.write = fail
        return f


def test_a_split_whose_next_file_cannot_start_ends_the_bag_with_the_files_before_it(tmp_path, monkeypatch):
    import pytest
    from mcap.reader import make_reader

    monkeypatch.setattr(bag_writer, "_CheckedFile", _FailingFile(bag_writer._CheckedFile, "bag_1.mcap"))
    bag = tmp_path / "bag"
    w = BagWriter(bag, chunk_size=2048, max_bagfile_size=4096)
    w.add_topic("/x", "std_msgs/msg/String", [])
    with pytest.raises(BagWriteError, match="No space left"):
        for t in range(1, 1000):
            w.write_message("/x", {"data": "y" * 200}, t)
    w.close()
    assert sorted(p.name for p in bag.iterdir()) == ["bag_0.mcap", "metadata.yaml"]
    with open(bag / "bag_0.mcap", "rb") as f:
        n = sum(1 for _ in make_reader(f).iter_messages())
    info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert info["message_count"] == n > 0 and info["relative_file_paths"] == ["bag_0.mcap"]
    assert int(info["custom_data"]["protocad_messages_lost_after_error"]) == t - n


class _DiskFullAfterChunk:
    """Fault injection (named as such: a disk that fills in the bytes between a chunk record and
    its message index, which a recording into a small tmpfs hit about once in 30 runs, cannot
    be produced on demand): the write after the `nth` chunk record fails ENOSPC."""

    def __init__(self, real, nth: int):
        self.real, self.nth, self.chunks = real, nth, 0

    def __call__(self, path):
        f = self.real(path)
        write = f.write

        def checked(data):
            if self.chunks >= self.nth:
                raise OSError(28, "No space left on device")
            n = write(data)
            self.chunks += bytes(memoryview(data)[:1]) == b"\x06"    # MCAP opcode 0x06: Chunk
            return n
        f.write = checked
        return f


@pytest.mark.parametrize("by", ["size", "flush"])
def test_a_disk_full_between_a_chunk_and_its_index_leaves_metadata_that_counts_the_file(tmp_path, monkeypatch, by):
    """metadata.yaml, the file and rosbags agree on every count after the cut: the salvage cuts
    back to where the counts were taken, not to a chunk whose index never got written."""
    from mcap.reader import make_reader
    from rosbags.rosbag2 import Reader

    monkeypatch.setattr(bag_writer, "_CheckedFile", _DiskFullAfterChunk(bag_writer._CheckedFile, 3))
    bag = tmp_path / "bag"
    w = BagWriter(bag, chunk_size=2048 if by == "size" else 10**6, compression="none")
    w.add_topic("/x", "std_msgs/msg/String", [])
    sent = 0
    with pytest.raises(BagWriteError, match="No space left"):
        for t in range(1, 1000):
            sent += 1
            w.write_message("/x", {"data": "y" * 200}, t)
            if by == "flush" and t % 7 == 0:
                w.flush()
    w.close()
    with open(bag / "bag_0.mcap", "rb") as f:
        n = sum(1 for _ in make_reader(f).iter_messages())
    info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert n > 0 and info["message_count"] == n == w.message_count == w.topic_counts["/x"]
    assert int(info["custom_data"]["protocad_messages_lost_after_error"]) == sent - n
    with Reader(bag) as reader:
        assert sum(1 for _ in reader.messages()) == reader.message_count == n


def test_a_bag_that_cannot_even_start_is_a_clear_error_leaving_nothing(tmp_path, monkeypatch):
    import pytest

    monkeypatch.setattr(bag_writer, "_CheckedFile", _FailingFile(bag_writer._CheckedFile, "bag_0.mcap"))
    with pytest.raises(BagWriteError, match="cannot start a bag"):
        BagWriter(tmp_path / "bag")
    assert list((tmp_path / "bag").iterdir()) == []
