"""`ros2 run trainer checkpoint_publisher`: a learner's checkpoint file, delivered over ROS.

    protocad-checkpoint-publisher --ros-args -p checkpoint:=runs/x/checkpoints/latest.pt

A policy node on another machine cannot watch the learner's file. This node watches it (the
trainer replaces it atomically with os.replace) and, for each new version (new bytes: the
version is its sha256), announces it on `<topic>` (std_msgs/String, JSON: sha256, size, the
sha256 of every chunk, what it is, a growing sequence number) and publishes its bytes in chunks
on `<topic>/chunks`, both reliable + transient local, so a policy that starts or reconnects
later still gets the newest version. With `signing_key` the announcement carries the learner's
Ed25519 signature (msgs_docs/security.md), which policies with `trusted_keys` require.
Contract: msgs_docs/checkpoint_publisher.md.
"""
from __future__ import annotations

import dataclasses
import hashlib
import os
import time
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from std_msgs.msg import String, UInt8MultiArray

from protocad_ros.atomic import file_signature
from protocad_ros.checkpoint.files import read_checkpoint_file
from protocad_ros.checkpoint.signing import (
    SigningError,
    key_id,
    load_private_key,
    next_seq,
    sign_manifest,
    write_signature_file,
)
from protocad_ros.node.checkpoint_receiver import manifest_of
from sim_bridge.contract import qos, topics
from sim_bridge.nodekit.param_table import ConfigError, Param, executor_param, strict_param
from sim_bridge.nodekit.rosbase import ProtocadNode
from sim_bridge.nodekit.rosnode import declare_all, install_parameter_guards, make_status, run_node

NODE_NAME = "checkpoint_publisher"

PARAMS: tuple[Param, ...] = (
    Param("checkpoint", "", "The learner's checkpoint file to watch (protocad_ros.checkpoint "
          "format; it need not exist yet). Required."),
    Param("topic", topics.CHECKPOINT, "Announcement topic; the bytes go on <topic>/chunks. "
          "Relative names resolve in the node's namespace (default /protocad)."),
    Param("chunk_size", topics.DEFAULT_CHUNK_SIZE, "Bytes per chunk message (at most "
          f"{topics.MAX_CHUNKS} chunks per version).",
          range=(topics.MIN_CHUNK_SIZE, topics.MAX_CHUNK_SIZE), units="bytes"),
    Param("signing_key", "", "Ed25519 private key file (protocad-keygen NAME writes NAME.key): "
          "every announcement is signed with it, for policies with trusted_keys. Empty: "
          "unsigned announcements (a WARNING at start)."),
    Param("write_signature_file", False, "With signing_key: also write CHECKPOINT.sig beside "
          "the checkpoint file for each announced version (for policies on this machine that "
          "watch the file itself with trusted_keys)."),
    Param("poll_s", 1.0, "How often the file is checked for a new version (mtime/inode/size).",
          range=(0.01, 3600.0), units="s"),
    Param("diagnostics_period_s", 1.0, "Period of /diagnostics.", range=(0.05, 3600.0), units="s"),
    strict_param(),
    executor_param(),
)
COUNTERS = ("versions_announced", "unchanged_rewrites", "read_errors", "bytes_published",
            "unknown_parameters", "parameters_rejected")


class CheckpointPublisherNode(ProtocadNode):
    """See the module docstring; parameters in PARAMS, counters in COUNTERS (/diagnostics)."""

    def __init__(self, *, namespace: str = topics.DEFAULT_NAMESPACE, **kw: Any):
        super().__init__(NODE_NAME, namespace=namespace, **kw)
        p = self.params = declare_all(self, PARAMS)
        if not p["checkpoint"]:
            raise ConfigError("checkpoint is required: the learner's checkpoint file to publish "
                              "(-p checkpoint:=runs/x/checkpoints/latest.pt)")
        self.executor_kind = p["executor"]
        self.counters = dict.fromkeys(COUNTERS, 0)
        self.counters["unknown_parameters"] = len(self.unknown_parameters)
        self.key = None
        if p["signing_key"]:
            try:
                self.key = load_private_key(p["signing_key"])
            except SigningError as e:
                raise ConfigError(str(e)) from None
        elif p["write_signature_file"]:
            raise ConfigError("write_signature_file:=true needs signing_key:=FILE (the private key to sign with)")
        self.key_id = key_id(self.key.public_key()) if self.key is not None else ""
        self.seq = 0   # of the newest announcement: grows across restarts too (next_seq)
        self.current: topics.CheckpointAnnouncement | None = None
        self.published_at = 0.0
        self._seen_sig: tuple | None = None
        self._failed_sig: tuple | None = None
        self._chunk_pub = None   # one writer per version: its history is that version's chunks
        self.pub_announce = self.create_publisher(String, p["topic"], qos.announcement_qos())
        self.chunk_topic = topics.chunks_topic(self.pub_announce.topic_name)
        self.pub_diag = self.create_publisher(DiagnosticArray, topics.DIAGNOSTICS, qos.diagnostics_qos())
        install_parameter_guards(self, PARAMS, lambda name, value: None, self._rejected_parameter)
        self.create_timer(p["poll_s"], self._poll)
        self.create_timer(p["diagnostics_period_s"], self._publish_diagnostics)
        self._diag_name = self.get_fully_qualified_name()
        where = "" if os.path.exists(p["checkpoint"]) else " (it does not exist yet: waiting for it)"
        self.get_logger().info(f"watching {p['checkpoint']}{where}; announcing on "
                               f"{self.pub_announce.topic_name}, bytes on {self.chunk_topic}"
                               + (f"; signing with key {self.key_id}" if self.key is not None else ""))
        if self.key is None:
            self.get_logger().warning("no signing_key: announcements are UNSIGNED; policies with "
                                      "trusted_keys refuse them (protocad-keygen makes a key pair; "
                                      "msgs_docs/security.md)")
        self._poll()

    def _rejected_parameter(self, reason: str) -> None:
        self.counters["parameters_rejected"] += 1
        self.get_logger().warning(f"parameter change rejected: {reason}")

    # ------------------------------------------------------------------ versions
    def _read(self, path: str) -> tuple[bytes, dict[str, Any]] | None:
        """The file's bytes and what the announcement says about them, or None if it was
        replaced while we read it (the next poll takes the newer one)."""
        from protocad_ros.checkpoint.agent_file import read_checkpoint

        sig = file_signature(path)
        data = read_checkpoint_file(path)   # a file over the limit is refused unread
        # format and version checks on the bytes announced (never announce junk), not a reread
        payload = read_checkpoint(path, data=data)
        if file_signature(path) != sig or len(data) != sig[2]:
            return None
        cfg = payload.get("config", {})
        counters = {k: v for k, v in dict(payload.get("counters", {})).items()
                    if isinstance(v, (int, float)) and not isinstance(v, bool)}
        updates = payload.get("agent_counters", {}).get("updates", -1)
        return data, dict(updates=int(updates), task=str(cfg.get("task", "")),
                          variant=str(cfg.get("variant", "")), preset=str(cfg.get("preset", "")),
                          counters=counters)

    def _poll(self) -> None:
        path = self.params["checkpoint"]
        sig = file_signature(path)
        if sig is None or sig == self._seen_sig or sig == self._failed_sig:
            return
        try:
            got = self._read(path)
        except Exception as e:  # noqa: BLE001 (CheckpointError, OSError: said once per version)
            self._failed_sig = sig
            self.counters["read_errors"] += 1
            self.get_logger().error(f"not announcing {path}: {e}; still announcing "
                                    f"{self._describe(self.current)}")
            return
        if got is None:
            return
        self._seen_sig = sig
        data, fields = got
        if self.current is not None and hashlib.sha256(data).hexdigest() == self.current.sha256:
            self.counters["unchanged_rewrites"] += 1   # same bytes written again: same version
            return
        n_chunks = -(-len(data) // self.params["chunk_size"])
        if n_chunks > topics.MAX_CHUNKS:
            self._failed_sig = sig
            self.counters["read_errors"] += 1
            self.get_logger().error(f"not announcing {path}: {len(data)} bytes are {n_chunks} chunks of "
                                    f"{self.params['chunk_size']}, more than {topics.MAX_CHUNKS} (raise chunk_size)")
            return
        self.seq = next_seq(self.seq)
        ann = self._sign(topics.describe_checkpoint(data, self.params["chunk_size"], seq=self.seq, **fields))
        if self.params["write_signature_file"]:
            try:
                write_signature_file(path, manifest_of(ann), ann.signature)
            except OSError as e:   # the announcement still goes out; the file's watchers wait
                self.get_logger().error(f"cannot write the signature file beside {path}: {e}")
        self._publish(ann, data)

    def _sign(self, ann: topics.CheckpointAnnouncement) -> topics.CheckpointAnnouncement:
        """The announcement with the learner's signature over its manifest (unsigned without a key)."""
        if self.key is None:
            return ann
        manifest, signature = sign_manifest(manifest_of(ann), self.key)
        return dataclasses.replace(ann, key_id=manifest.key_id, signature=signature)

    def _publish(self, ann: topics.CheckpointAnnouncement, data: bytes) -> None:
        t0 = time.monotonic()
        if self._chunk_pub is not None:
            self.destroy_publisher(self._chunk_pub)
        self._chunk_pub = self.create_publisher(UInt8MultiArray, self.chunk_topic,
                                                qos.checkpoint_chunks_qos(ann.n_chunks))
        # The announcement first: receivers buffer only chunks of a version they accepted, and a
        # running one hears it before the new chunk writer is even matched. The writer keeps
        # every chunk (transient local), so a receiver that got chunks first reads them again.
        self.pub_announce.publish(String(data=topics.checkpoint_announcement_json(ann)))
        for i in range(ann.n_chunks):
            piece = data[i * ann.chunk_size:(i + 1) * ann.chunk_size]
            self._chunk_pub.publish(topics.fill_checkpoint_chunk(UInt8MultiArray(), ann.sha256, i,
                                                                 ann.n_chunks, piece))
        self.current, self.published_at = ann, time.time()
        self.counters["versions_announced"] += 1
        self.counters["bytes_published"] += ann.size
        self.get_logger().info(f"announced {self._describe(ann)}: {ann.size} bytes in {ann.n_chunks} "
                               f"chunk(s) of {ann.chunk_size} ({(time.monotonic() - t0) * 1e3:.0f} ms)")
        self._publish_diagnostics()

    @staticmethod
    def _describe(ann: topics.CheckpointAnnouncement | None) -> str:
        if ann is None:
            return "nothing"
        return f"checkpoint version {ann.short_id} (updates={ann.updates}, {ann.task} {ann.variant})"

    # ------------------------------------------------------------------ diagnostics
    def _publish_diagnostics(self) -> None:
        a = self.current
        values = {"checkpoint": self.params["checkpoint"], "topic": self.pub_announce.topic_name,
                  "sha256": a.sha256 if a else "", "updates": a.updates if a else -1,
                  "size": a.size if a else 0, "n_chunks": a.n_chunks if a else 0,
                  "seq": a.seq if a else 0, "key_id": self.key_id,
                  "chunk_size": self.params["chunk_size"], "announced_unix": self.published_at,
                  "subscribers": self.pub_announce.get_subscription_count(),
                  "callback_errors": self.callback_errors, **self.counters}
        bad = self.counters["read_errors"] or self.unknown_parameters or self.callback_errors
        level = "WARN" if bad or a is None else "OK"
        message = ("no version announced yet" if a is None else
                   "read errors" if self.counters["read_errors"] else
                   f"unknown parameters ignored: {self.unknown_parameters}" if self.unknown_parameters
                   else f"announcing {a.short_id}")
        arr = DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        arr.status = [make_status(self._diag_name, a.task if a else "", values, level, message)]
        self.pub_diag.publish(arr)

    def close(self) -> None:
        try:
            self._publish_diagnostics()
        except Exception:  # noqa: BLE001 - exiting: the last diagnostics are best effort
            pass
        self.get_logger().info("stopped: " + ", ".join(f"{k}={v}" for k, v in self.counters.items() if v))


def main(argv: list[str] | None = None) -> int:
    return run_node(
        CheckpointPublisherNode, prog="checkpoint_publisher", params=PARAMS, argv=argv,
        description="Publishes each new version of a learner's checkpoint file over ROS: "
                    "a JSON announcement (sha256, size, per-chunk sha256, updates, task, variant, "
                    "sequence number; signed with -p signing_key:=FILE) on <topic>, then the bytes "
                    "in chunks on <topic>/chunks, both latched (reliable, transient local). Policy "
                    "nodes receive it with -p checkpoint_topic:=checkpoint. Contract: "
                    "msgs_docs/checkpoint_publisher.md, msgs_docs/security.md.",
        example="protocad-checkpoint-publisher --ros-args -p checkpoint:=runs/x/checkpoints/latest.pt")


if __name__ == "__main__":
    raise SystemExit(main())
