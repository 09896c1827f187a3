"""Messages with the GID of the writer that sent them (what rclpy's Jazzy message info leaves out).

rclpy's subscription callbacks get a message and, at most, its timestamps and sequence numbers;
rcl hands the publisher's GID to C callers (`rmw_message_info_t.publisher_gid`). A launcher that
must believe only the nodes it started (trainer/launch/rosgraph.py), or a policy only its bridge's
announcement (protocad_ros/node/bridge_pairing.py), needs that GID, so
`SenderSubscription` is an rcl subscription made through rclpy's own binding but taken from
here: `rcl_take_serialized_message` through ctypes, then rclpy's deserializer. It is not added
to any executor; `take()` drains it when its owner spins.

The layouts below are Jazzy's (rmw/types.h: RMW_GID_STORAGE_SIZE 16; rcutils/types/uint8_array.h).
With Fast DDS a GID is the writer's GUID: its bytes 0-1 are the vendor id, 2-3 the host, 4-5
the low 16 bits of the writing process's id (`gid_pid`), 12-15 the entity.
"""
from __future__ import annotations

import ctypes
import sys
from pathlib import Path
from typing import Any, Iterator

from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.serialization import deserialize_message
from rclpy.type_support import check_for_type_support

RCL_RET_OK = 0
GID_SIZE = 16
#: Bytes of a GID that name the writer's participant (the DDS GUID prefix).
PARTICIPANT_BYTES = 12
#: How often a node takes the announcements it holds with their writer (the policy's and the
#: recorder's bridge_info; also right when one arrives).
TAKE_PERIOD_S = 0.2


class _Allocator(ctypes.Structure):
    _fields_ = [("allocate", ctypes.c_void_p), ("deallocate", ctypes.c_void_p),
                ("reallocate", ctypes.c_void_p), ("zero_allocate", ctypes.c_void_p),
                ("state", ctypes.c_void_p)]


class _Uint8Array(ctypes.Structure):   # rcutils_uint8_array_t = rmw_serialized_message_t
    _fields_ = [("buffer", ctypes.POINTER(ctypes.c_uint8)), ("buffer_length", ctypes.c_size_t),
                ("buffer_capacity", ctypes.c_size_t), ("allocator", _Allocator)]


class _Gid(ctypes.Structure):
    _fields_ = [("implementation_identifier", ctypes.c_char_p), ("data", ctypes.c_uint8 * GID_SIZE)]


class _MessageInfo(ctypes.Structure):
    _fields_ = [("source_timestamp", ctypes.c_int64), ("received_timestamp", ctypes.c_int64),
                ("publication_sequence_number", ctypes.c_uint64),
                ("reception_sequence_number", ctypes.c_uint64),
                ("publisher_gid", _Gid), ("from_intra_process", ctypes.c_bool)]


_libs: tuple[Any, Any] | None = None


def _load() -> tuple[Any, Any]:
    global _libs
    if _libs is None:
        lib = Path(sys.prefix) / "lib"
        rcl = ctypes.CDLL(str(lib / "librcl.so"))
        rcutils = ctypes.CDLL(str(lib / "librcutils.so"))
        rcutils.rcutils_get_default_allocator.restype = _Allocator
        rcutils.rcutils_uint8_array_init.argtypes = [ctypes.POINTER(_Uint8Array), ctypes.c_size_t,
                                                     ctypes.POINTER(_Allocator)]
        rcutils.rcutils_uint8_array_fini.argtypes = [ctypes.POINTER(_Uint8Array)]
        rcl.rcl_take_serialized_message.argtypes = [ctypes.c_void_p, ctypes.POINTER(_Uint8Array),
                                                    ctypes.POINTER(_MessageInfo), ctypes.c_void_p]
        _libs = (rcl, rcutils)
    return _libs


def gid_pid(gid: tuple[int, ...]) -> int:
    """The low 16 bits of the writing process's id in a Fast DDS GID."""
    return gid[4] | (gid[5] << 8)


class SenderSubscription:
    """An rcl subscription on `node` whose messages come with their writer's GID."""

    def __init__(self, node, msg_type, topic: str, qos_profile):
        check_for_type_support(msg_type)
        self.msg_type = msg_type
        self._rcl, self._rcutils = _load()
        with node.handle:
            self._sub = _rclpy.Subscription(node.handle, msg_type, topic, qos_profile.get_c_qos_profile())
        self._buf = _Uint8Array()
        alloc = self._rcutils.rcutils_get_default_allocator()
        if self._rcutils.rcutils_uint8_array_init(ctypes.byref(self._buf), 0, ctypes.byref(alloc)) != RCL_RET_OK:
            raise MemoryError("rcutils_uint8_array_init failed")

    def take(self, limit: int = 1000) -> Iterator[tuple[Any, tuple[int, ...]]]:
        """(message, writer GID) of each message waiting, oldest first, at most `limit`."""
        for data, gid, _ in self.take_raw(limit):
            yield deserialize_message(data, self.msg_type), gid

    def take_raw(self, limit: int = 1000) -> Iterator[tuple[bytes, tuple[int, ...], dict[str, int]]]:
        """(CDR bytes, writer GID, message info as rclpy's dict names it: source_timestamp,
        received_timestamp, publication_sequence_number) of each message waiting, at most `limit`."""
        info = _MessageInfo()
        for _ in range(limit):
            with self._sub:
                rc = self._rcl.rcl_take_serialized_message(self._sub.pointer, ctypes.byref(self._buf),
                                                           ctypes.byref(info), None)
            if rc != RCL_RET_OK:   # RCL_RET_SUBSCRIPTION_TAKE_FAILED: nothing waiting
                return
            yield (ctypes.string_at(self._buf.buffer, self._buf.buffer_length), tuple(info.publisher_gid.data),
                   {"source_timestamp": int(info.source_timestamp), "received_timestamp": int(info.received_timestamp),
                    "publication_sequence_number": int(info.publication_sequence_number)})

    def destroy(self) -> None:
        self._sub.destroy_when_not_in_use()
        self._rcutils.rcutils_uint8_array_fini(ctypes.byref(self._buf))
