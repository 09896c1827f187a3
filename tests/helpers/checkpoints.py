"""A stranger's checkpoint sender and signing helpers for the tests of checkpoints over ROS
(tests/protocad_ros/node/test_checkpoint_delivery.py, test_trusted_by_default.py)."""
from __future__ import annotations

import dataclasses

from std_msgs.msg import String, UInt8MultiArray

from helpers.ros import Probe
from protocad_ros.checkpoint.signing import next_seq, sign_manifest
from protocad_ros.node.checkpoint_receiver import manifest_of
from sim_bridge.contract import qos, topics


class FakeCheckpointPublisher:
    """A FAKE sender, named as such: a healthy DDS link neither corrupts nor drops a reliable
    chunk, so the faults a receiver must survive (a flipped byte, a short chunk, bytes that are
    no checkpoint, a sender that stops half-way) are made here. It speaks the publisher's
    protocol (sim_bridge.contract.topics helpers, the same QoS) but announces whatever it is told."""

    def __init__(self, probe: Probe):
        self.probe = probe
        self.announce = probe.publisher(topics.CHECKPOINT, String, qos.announcement_qos())
        self.chunk_pub = None

    def send(self, ann: topics.CheckpointAnnouncement, chunks: list[bytes],
             labels: list[tuple[int, int]] | None = None) -> None:
        """Chunks first (so receivers must read them again after the announcement), `labels`
        the (index, n_chunks) each one claims (default: as sent)."""
        node = self.probe.node
        if self.chunk_pub is not None:
            node.destroy_publisher(self.chunk_pub)
        self.chunk_pub = node.create_publisher(
            UInt8MultiArray, self.probe.topic(topics.chunks_topic(topics.CHECKPOINT)),
            qos.checkpoint_chunks_qos(len(chunks)))
        for i, piece in enumerate(chunks):
            index, n = labels[i] if labels else (i, ann.n_chunks)
            self.chunk_pub.publish(topics.fill_checkpoint_chunk(UInt8MultiArray(), ann.sha256, index,
                                                                n, piece))
        self.announce_only(ann)

    def announce_only(self, ann: topics.CheckpointAnnouncement | str) -> None:
        text = ann if isinstance(ann, str) else topics.checkpoint_announcement_json(ann)
        self.announce.publish(String(data=text))

    def close(self) -> None:
        for pub in (self.announce, self.chunk_pub):
            if pub is not None:
                self.probe.node.destroy_publisher(pub)


def chunks(data: bytes, size: int) -> list[bytes]:
    return [data[i:i + size] for i in range(0, len(data), size)]


def sign(ann: topics.CheckpointAnnouncement, key, seq: int | None = None) -> topics.CheckpointAnnouncement:
    """The announcement as a publisher with `key` signs it (seq: the next one by default)."""
    ann = dataclasses.replace(ann, seq=next_seq() if seq is None else seq)
    manifest, signature = sign_manifest(manifest_of(ann), key)
    return dataclasses.replace(ann, key_id=manifest.key_id, signature=signature)
