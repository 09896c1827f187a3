"""Crafted MCAP files a stranger could hand over: a chunk bomb (a small file whose zstd chunk
inflates to 1 GiB, and says so) and a schema bomb (a JointState whose schema in the bag adds an
array of an empty struct, and a message whose length field asks for millions of them). Both are
built in pieces, so making them costs the test a few MB."""
from __future__ import annotations

import struct
from pathlib import Path

import zstandard

from trainer.bag.rosmsg import encode, message_definition, new_message
from trainer.bag.writer import MCAP_MAGIC

CHUNK_BOMB_BYTES = 1 << 30
EMPTY_ELEMENTS = 20_000_000
JOINT_STATE = "sensor_msgs/msg/JointState"


def _s(text: str) -> bytes:
    b = text.encode()
    return struct.pack("<I", len(b)) + b


def _record(opcode: int, body: bytes) -> bytes:
    return struct.pack("<BQ", opcode, len(body)) + body


def _schema(sid: int, name: str, text: str) -> bytes:
    data = text.encode()
    return _record(0x03, struct.pack("<H", sid) + _s(name) + _s("ros2msg") + struct.pack("<I", len(data)) + data)


def _channel(cid: int, sid: int, topic: str) -> bytes:
    return _record(0x04, struct.pack("<HH", cid, sid) + _s(topic) + _s("cdr") + struct.pack("<I", 0))


def _message_head(cid: int, t: int, data_len: int) -> bytes:
    return struct.pack("<BQHIQQ", 0x05, 2 + 4 + 8 + 8 + data_len, cid, 0, t, t)


def _chunk(records: bytes, declared: int, compression: str, t: int) -> bytes:
    body = struct.pack("<QQQI", t, t, declared, 0) + _s(compression) + struct.pack("<Q", len(records)) + records
    return _record(0x06, body)


def _header() -> bytes:
    return MCAP_MAGIC + _record(0x01, _s("ros2") + _s("hostile"))


def joint_state(names: list[str]) -> bytes:
    msg = new_message(JOINT_STATE)
    msg.name = names
    msg.position = [0.5] * len(names)
    return encode(JOINT_STATE, msg)


def write_chunk_bomb(path: Path, topic: str = "/protocad/action") -> Path:
    """MAGIC, Header, a zstd chunk holding one 1 GiB message (declared 1 GiB uncompressed),
    then a plain chunk with one real JointState on `topic`; no footer (a writer killed)."""
    head = _schema(1, JOINT_STATE, message_definition(JOINT_STATE)) + _channel(1, 1, topic)
    payload = CHUNK_BOMB_BYTES - len(head) - len(_message_head(1, 0, 0))
    comp = zstandard.ZstdCompressor(level=3).compressobj()
    parts = [comp.compress(head + _message_head(1, 1, payload))]
    zeros = bytes(1 << 24)
    left = payload
    while left:
        parts.append(comp.compress(zeros[:min(left, len(zeros))]))
        left -= min(left, len(zeros))
    parts.append(comp.flush())
    good = head + _message_head(1, 2, len(joint_state(["a"]))) + joint_state(["a"])
    path.write_bytes(_header() + _chunk(b"".join(parts), CHUNK_BOMB_BYTES, "zstd", 1) + _chunk(good, len(good), "", 2))
    return path


BOMB_SCHEMA = (message_definition(JOINT_STATE).replace("float64[] effort", "float64[] effort\nEmpty[] bomb", 1)
               + "\n" + "=" * 80 + "\nMSG: sensor_msgs/Empty\n")


def write_schema_bomb(path: Path, topic: str = "/protocad/action", msgtype: str = JOINT_STATE) -> Path:
    """One zstd chunk: `msgtype` with BOMB_SCHEMA as its schema, and a message that is a real
    JointState followed by a length of EMPTY_ELEMENTS and that many zero bytes (20 MB that
    zstd keeps in a few kB); no footer."""
    schema = BOMB_SCHEMA.replace("MSG: sensor_msgs/Empty", f"MSG: {msgtype.split('/')[0]}/Empty")
    js = joint_state([])
    data = js + bytes(-len(js) % 4) + struct.pack("<I", EMPTY_ELEMENTS) + bytes(EMPTY_ELEMENTS)
    records = _schema(1, msgtype, schema) + _channel(1, 1, topic) + _message_head(1, 1, len(data)) + data
    comp = zstandard.ZstdCompressor(level=3).compress(records)
    path.write_bytes(_header() + _chunk(comp, len(records), "zstd", 1))
    return path
