"""Bags from elsewhere are read within bounds: a chunk bomb (a 36 kB file whose chunk inflates to
1 GiB) and a schema bomb (a JointState whose schema in the bag adds an array of an empty struct,
20 M elements long) are refused or decoded with the installed definition, by BagReader, by
`ros2 bag info` and by protocad-train, with peak RSS within 200 MB of the same tool on a plain
bag; each refusal is one line naming the file, the offset and the limit, and the rest of the
bag is still read."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import zstandard
from helpers import ROOT
from helpers.hostile_bags import (
    JOINT_STATE,
    _channel,
    _chunk,
    _header,
    _message_head,
    _schema,
    joint_state,
    write_chunk_bomb,
    write_schema_bomb,
)

from trainer.bag.limits import BagLimitError, ReadLimits, vet_definition
from trainer.bag.reader import BagReader
from trainer.bag.rosmsg import message_definition

MEASURE = ("import resource, subprocess, sys\n"
           "r = subprocess.run(sys.argv[1:], capture_output=True, text=True)\n"
           "sys.stdout.write(r.stdout); sys.stderr.write(r.stderr)\n"
           "print('PEAK_KB', resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss, 'RC', r.returncode)")


def peak_kb(*cmd: str) -> tuple[int, int, str]:
    """(peak RSS of the command in kB, its exit code, its output)."""
    out = subprocess.run([sys.executable, "-c", MEASURE, *cmd], capture_output=True, text=True, cwd=ROOT,
                         timeout=600, env={**os.environ, "OMP_NUM_THREADS": "1"})
    tail = out.stdout.rsplit("PEAK_KB", 1)
    kb, rc = tail[1].split("RC")
    return int(kb), int(rc), tail[0] + out.stderr


def plain_bag(path: Path) -> Path:
    """What the bombs carry besides the bomb: one real JointState, no footer."""
    good = _schema(1, JOINT_STATE, message_definition(JOINT_STATE)) + _channel(1, 1, "/protocad/action")
    good += _message_head(1, 2, len(joint_state(["a"]))) + joint_state(["a"])
    path.write_bytes(_header() + _chunk(good, len(good), "", 2))
    return path


@pytest.fixture(scope="module")
def bags(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("hostile")
    return {"plain": plain_bag(d / "plain.mcap"), "chunk": write_chunk_bomb(d / "chunk_bomb.mcap"),
            "schema": write_schema_bomb(d / "schema_bomb.mcap")}


def test_the_chunk_bomb_is_refused_in_one_line_and_the_next_chunk_is_read(bags):
    assert bags["chunk"].stat().st_size < 100_000
    r = BagReader(bags["chunk"])
    msgs = list(r.messages())
    assert [r.decode(m).name for m in msgs] == [["a"]]   # the chunk after the bomb
    assert r.report.refused == [f"{bags['chunk']}: chunk at byte 36: chunk declares 1073741824 bytes "
                                "uncompressed, over the limit of 268435456 (max_chunk_bytes); skipped"]
    assert not r.report.ok


def test_a_record_over_the_limit_is_skipped_unread(bags):
    r = BagReader(bags["chunk"], limits=ReadLimits(max_chunk_bytes=5000))
    assert len(list(r.messages())) == 1
    assert len(r.report.refused) == 1 and "CHUNK record at byte 36 is" in r.report.refused[0]
    assert "over the limit of 5000 (max_chunk_bytes)" in r.report.refused[0]


@pytest.mark.parametrize("declared", [100, 10_000])
def test_a_chunk_that_inflates_to_another_size_than_it_declares_is_refused(tmp_path, declared):
    records = _schema(1, JOINT_STATE, message_definition(JOINT_STATE)) + _channel(1, 1, "/x")
    records += _message_head(1, 1, 4000) + bytes(4000)
    path = tmp_path / "liar.mcap"
    path.write_bytes(_header() + _chunk(zstandard.ZstdCompressor().compress(records), declared, "zstd", 1))
    r = BagReader(path)
    assert list(r.messages()) == []
    assert len(r.report.refused) == 1, r.report.summary()
    assert f"the {declared} bytes it declares" in r.report.refused[0]


def test_the_schema_bomb_is_decoded_with_the_installed_definition(bags):
    r = BagReader(bags["schema"])
    (m,) = list(r.messages())
    msg = r.decode(m)
    assert list(msg.name) == [] and not hasattr(msg, "bomb")
    assert any("differs from the installed definition" in w for w in r.report.warnings)


def test_a_foreign_type_with_the_bomb_schema_is_refused_not_expanded(tmp_path):
    path = write_schema_bomb(tmp_path / "foreign.mcap", msgtype="hostile_msgs/msg/Thing")
    r = BagReader(path)
    (m,) = list(r.messages())
    for _ in range(2):   # refused once, one line; every later message of it is refused too
        with pytest.raises(BagLimitError, match="field bomb is an array of Empty"):
            r.decode(m)
    assert len(r.report.refused) == 1
    assert r.report.refused[0].startswith(f"{path}: schema of hostile_msgs/msg/Thing: field bomb")
    assert "under the limit of 4" in r.report.refused[0]


@pytest.mark.parametrize("field, why", [("Empty[] e", "array of Empty"),
                                        ("Pad[] p", "array of Pad"),
                                        ("Big[100000] b", "fixed array of 100000 Big, over the limit of 65536"),
                                        ("Self s", "contains itself")])
def test_schemas_whose_decoding_the_bytes_do_not_bound_are_refused(field, why):
    deps = {"Empty": "", "Pad": "uint8[16] pad", "Big": "float64 x", "Self": "Self s"}
    name = field.split("[")[0].split()[0]
    text = f"{field}\n" + "=" * 80 + f"\nMSG: p/{name}\n{deps[name]}\n"
    with pytest.raises(BagLimitError, match=why):
        vet_definition("p/msg/T", text)


def test_real_schemas_pass_the_vetting():
    for t in ("sensor_msgs/msg/JointState", "sensor_msgs/msg/Image", "diagnostic_msgs/msg/DiagnosticArray",
              "geometry_msgs/msg/PoseArray", "rcl_interfaces/msg/ParameterEvent"):
        vet_definition(t, message_definition(t))


def test_a_message_over_max_message_bytes_is_not_decoded(bags):
    r = BagReader(bags["schema"], limits=ReadLimits(max_message_bytes=1 << 20))
    (m,) = list(r.messages())
    with pytest.raises(BagLimitError, match=r"message of 20000040 bytes, over the limit of 1048576"):
        r.decode(m)


def test_limits_come_from_the_environment(monkeypatch):
    monkeypatch.setenv("PROTOCAD_BAG_MAX_CHUNK_BYTES", "5000")
    assert ReadLimits.from_env().max_chunk_bytes == 5000
    monkeypatch.setenv("PROTOCAD_BAG_MAX_CHUNK_BYTES", "lots")
    with pytest.raises(BagLimitError, match="not a whole number"):
        ReadLimits.from_env()


@pytest.mark.parametrize("bomb", ["chunk", "schema"])
def test_ros2_bag_info_stays_bounded(bags, bomb):
    base, rc0, _ = peak_kb(sys.executable, "-m", "trainer.ros2cli", "bag", "info", str(bags["plain"]))
    peak, rc, out = peak_kb(sys.executable, "-m", "trainer.ros2cli", "bag", "info", str(bags[bomb]))
    assert rc0 == rc == 0, out
    assert "Count: 1" in out
    if bomb == "chunk":
        assert "refused: " in out and "max_chunk_bytes" in out
    assert peak - base < 200_000, (peak, base)


@pytest.mark.parametrize("bomb", ["chunk", "schema"])
def test_protocad_train_stays_bounded(bags, bomb, tmp_path):
    def train(bag: Path, name: str) -> tuple[int, int, str]:
        return peak_kb(str(Path(sys.executable).parent / "protocad-train"), "--logs", str(bag),
                       "--run-dir", str(tmp_path / name), "--cache-dir", str(tmp_path / f"cache-{name}"),
                       "--updates", "1", "--no-progress", "--threads", "1")
    base, rc0, out0 = train(bags["plain"], "plain")
    peak, rc, out = train(bags[bomb], "bomb")
    assert rc0 == rc == 2, out0 + out
    assert "nothing to train on" in out
    assert ("refused: " in out and "max_chunk_bytes" in out) if bomb == "chunk" \
        else "decoded with the installed one" in out
    assert out.count("refused: ") == (1 if bomb == "chunk" else 0), out   # one line per refusal
    assert peak - base < 200_000, (peak, base)
