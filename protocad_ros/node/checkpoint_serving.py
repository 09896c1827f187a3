"""`CheckpointServing`: how the policy node loads the model it serves and replaces it while it
runs (a part of protocad_ros.node.policy_node.PolicyNode, as its observation pairing, action
publishing and diagnostics are: each in a file of its own).

The node configures with one checkpoint (or a random agent); afterwards one background thread
(`_watch`) is the only place checkpoints are loaded: the file when it changed, polled every
`reload_poll_s`, and versions the CheckpointReceiver got over ROS. A loaded model is handed over
(`_hand_over`) and swapped in by the executor thread at the next is_first (`_swap_if_pending`),
so no step waits for a load and no episode is served by two models.

With `trusted_keys` nothing is served that a trusted key did not sign: the file needs its
detached signature FILE.sig (protocad_ros.checkpoint.signing), received versions a signed
announcement (the receiver checks it), and each new version a sequence number above the newest
one held, which the node also keeps apart from the served file (rollback_floor.py), so that
losing FILE.sig does not lower it. A file is read once: those bytes are verified and loaded,
never a second read of the path. With `checkpoint_topic` and no trusted keys the node refuses
to start unless `allow_unsigned`. Whatever the source, a checkpoint is checked against what the
node serves (task, action and image size, variant and architecture: the random agent's too)
before anything is built. Refusals are counted, their lines rate-limited (refusal_log.py).

It works on the node's own state: `params`, `counters`, `_lock` (guards `_pending_policy` and
the counters), `_stop` / `_wake` (events), `receiver`, `policy`, `ckpt_counters`, `ckpt_sha`,
`ckpt_seq`, `trusted`, `agent_kind`, `task`, `action_dim`, `image_hw`, `_loaded_sig` /
`_failed_sig` (watch keys), and its logger and `_publish_diagnostics`.
"""
from __future__ import annotations

import hashlib
import time
from typing import Any

from protocad_ros.atomic import file_signature
from protocad_ros.checkpoint.files import CheckpointMismatch, architecture_differences, read_checkpoint_file
from protocad_ros.checkpoint.signing import (
    SignatureRejected,
    SigningError,
    load_trusted_keys,
    parse_key_list,
    read_signature_file,
    signature_path,
    verify_file,
)
from protocad_ros.model.config import make_config
from protocad_ros.node.checkpoint_receiver import CheckpointReceiver
from protocad_ros.node.rollback_floor import RollbackFloor, RollbackStateError, default_state_path
from sim_bridge.contract.contexts import task_actuators
from sim_bridge.nodekit.rosnode import ConfigError

#: How long a changed checkpoint file may wait for its FILE.sig (a signer writes it after the
#: file) before it counts as unsigned.
SIGNATURE_GRACE_S = 5.0


class RollbackRejected(SignatureRejected):
    """A validly signed version that is not newer than the one served."""


class CheckpointServing:
    """Loading, watching and swapping the served checkpoint; see the module docstring."""

    def _policy_kwargs(self) -> dict[str, Any]:
        p = self.params
        return dict(device=p["device"], mode=p["mode"], exploration_noise=p["exploration_noise"],
                    seed=p["seed"], state_mean=p["state_mean"])

    def _load(self, path: str, fits=None, data: bytes | None = None):
        """The policy from `data`, the bytes of `path` as read (and verified) once."""
        from protocad_ros.checkpoint.agent_file import load_checkpoint
        from protocad_ros.policy import Policy

        # Never the file's RNG state: a served checkpoint must not reseed this process.
        agent, counters = load_checkpoint(path, device=self.params["device"], fits=fits,
                                          restore_rng=False, optimizer_states=False, data=data,
                                          max_bytes=self.params["max_checkpoint_bytes"])
        # `updates` = the agent's own update counter (restored with the weights); the other
        # counters are the trainer's (env steps, episodes, ...), reported as checkpoint/<key>.
        counters = {**dict(counters or {}), "updates": int(agent.counters()["updates"])}
        return Policy(agent, **self._policy_kwargs()), counters

    def _random_policy(self):
        from protocad_ros.model.agent import make_agent
        from protocad_ros.policy import Policy

        p = self.params
        cfg = make_config(p["task"], p["preset"], p["variant"], **{"train.seed": p["seed"]})
        agent = make_agent(cfg, len(task_actuators(p["task"])), device=p["device"])
        return Policy(agent, **self._policy_kwargs())

    @property
    def checkpoint_updates(self) -> int:
        return int(self.ckpt_counters.get("updates", -1)) if self.agent_kind == "checkpoint" else -1

    def _describe_agent(self) -> str:
        if self.agent_kind == "random":
            return "a random agent"
        return f"checkpoint {self.params['checkpoint']} (updates={self.checkpoint_updates})"

    def _watch(self) -> None:
        """Background: the one place checkpoints are loaded after configure: the file when it
        changed (polled every reload_poll_s) and versions received over ROS (woken at once).
        A loaded one goes to the executor thread, which swaps it in at the next is_first."""
        path, poll = self.params["checkpoint"], self.params["reload_poll_s"]
        while not self._stop.is_set():
            self._wake.wait(poll if poll > 0 else None)
            self._wake.clear()
            if self._stop.is_set():
                return
            receiver = self.receiver   # None once cleanup began
            if receiver is not None:
                got = receiver.install_received(path, self._load_checked)
                if got is not None:
                    policy, counters, sha, what, seq = got
                    self._hand_over(policy, counters, self._watch_key(path), sha, what, seq)
            if poll > 0:
                self._check_file(path)
            self.refusals.flush()

    def _load_checked(self, path: str, data: bytes):
        """A checkpoint that replaces the served one, from its verified bytes: refused
        (CheckpointMismatch) before it is built unless it fits what this node serves."""
        return self._load(path, fits=self._fits_served, data=data)

    def _fits_served(self, cfg, action_dim: int) -> None:
        why = []
        if cfg.task != self.task:
            why.append(f"it is for {cfg.task}, this node serves {self.task}")
        if action_dim != self.action_dim or (int(cfg.train.image_size),) * 2 != self.image_hw:
            why.append(f"{action_dim}-d actions / {cfg.train.image_size}px images, but this node "
                       f"serves {self.action_dim}-d / {self.image_hw[0]}px")
        policy = self.policy
        # The random agent's too: its variant and preset (parameters) are what this node serves.
        if policy is not None:
            why += architecture_differences(policy.agent.cfg, cfg)
        if why:
            kind = "" if self.agent_kind == "checkpoint" else (
                " (this node serves a random agent of its variant and preset parameters)")
            raise CheckpointMismatch("; ".join(why) + kind)

    def _announced_fits(self, ann) -> str | None:
        """Why an announced version is not for this node (checked again on the file itself)."""
        if ann.task and ann.task != self.task:
            return f"it is for {ann.task}, this node serves {self.task}"
        policy = self.policy
        if policy is not None and ann.variant and ann.variant != policy.agent.cfg.variant:
            return f"it is a {ann.variant} agent, this node serves {policy.agent.cfg.variant}"
        return None

    # ------------------------------------------------------------------ trust
    def _load_trust(self) -> None:
        """trusted_keys -> self.trusted and the rollback floor (None: unsigned checkpoints are
        accepted: from the file said loudly, over checkpoint_topic only with allow_unsigned)."""
        p = self.params
        paths = parse_key_list(p["trusted_keys"])
        self.trusted, self.rollback = None, None
        if paths:
            try:
                self.trusted = load_trusted_keys(paths)
            except SigningError as e:
                raise ConfigError(f"trusted_keys: {e}") from None
            state = p["rollback_state"] or default_state_path(paths[0], p["checkpoint"] or "none")
            try:
                self.rollback = RollbackFloor(state, p["checkpoint"])
            except RollbackStateError as e:
                raise ConfigError(str(e)) from None
            minimum = (f"; no version signed below min_checkpoint_seq {p['min_checkpoint_seq']}"
                       if p["min_checkpoint_seq"] else "")
            self.get_logger().info(f"serving only checkpoints signed by trusted key(s) "
                                   f"{', '.join(sorted(self.trusted))}; rollback floor "
                                   f"{self.rollback.seq} ({self.rollback.path}){minimum}")
        elif p["min_checkpoint_seq"]:
            raise ConfigError(f"min_checkpoint_seq:={p['min_checkpoint_seq']} without trusted_keys: only "
                              "signed versions carry a sequence number; give -p trusted_keys:=LEARNER.pub")
        elif p["checkpoint_topic"] and not p["allow_unsigned"]:
            raise ConfigError(f"checkpoint_topic:={p['checkpoint_topic']} without trusted_keys: anyone on "
                              "this DDS domain could replace the served model; give -p trusted_keys:="
                              "LEARNER.pub (protocad-keygen makes the pair; the learner signs with it), "
                              "or -p allow_unsigned:=true to accept unsigned checkpoints")
        elif p["checkpoint"] or p["checkpoint_topic"]:
            source = (f"over {p['checkpoint_topic']} (allow_unsigned:=true): anyone on this DDS "
                      "domain can replace the served model" if p["checkpoint_topic"] else "from its file")
            self.get_logger().warning(f"no trusted_keys: this node accepts UNSIGNED checkpoints {source} "
                                      "(protocad-keygen makes a key pair; msgs_docs/security.md)")

    @property
    def unsigned_topic(self) -> bool:
        """Unsigned checkpoints over ROS are accepted (allow_unsigned): shown in /diagnostics."""
        return bool(self.params["checkpoint_topic"]) and self.trusted is None

    def _verified_seq(self, path: str, sha: str, size: int) -> int:
        """The sequence number FILE.sig vouches for (-1 without trusted keys); SignatureRejected
        when it does not verify, RollbackRejected when it is not above the newest one held."""
        if self.trusted is None:
            return -1
        manifest = verify_file(path, sha, size, self.trusted)
        newest = self._newest_seq()
        if manifest.seq <= newest:
            raise RollbackRejected(f"rollback: sequence number {manifest.seq} is not above {newest}, "
                                   "the newest version this node holds (or min_checkpoint_seq - 1)")
        return manifest.seq

    def _configure_seq(self, path: str, sha: str, size: int) -> None:
        """At configure: the file must verify (a ConfigError otherwise) and not be below the
        rollback floor kept apart from it; its number is the floor from now on."""
        self.ckpt_seq = -1
        if self.trusted is None:
            return
        try:
            self.ckpt_seq = verify_file(path, sha, size, self.trusted).seq
            self.rollback.check_served(self.ckpt_seq, f"checkpoint {path}")
            self.rollback.raise_to(self.ckpt_seq)
        except SignatureRejected as e:
            raise ConfigError(f"checkpoint {path} is not signed by a trusted key: {e}") from None
        except RollbackStateError as e:
            raise ConfigError(str(e)) from None

    def _read_once(self, path: str) -> tuple[bytes, str]:
        """The file's bytes and their sha256: the one read that is verified and loaded (a file
        over max_checkpoint_bytes is refused before it is read: CheckpointError)."""
        data = read_checkpoint_file(path, self.params["max_checkpoint_bytes"])
        return data, hashlib.sha256(data).hexdigest()

    def _watch_key(self, path: str) -> tuple | None:
        """What makes the poll look again: the file, and with trusted keys its FILE.sig."""
        sig = file_signature(path)
        if sig is None:
            return None
        return (sig, file_signature(signature_path(path)) if self.trusted is not None else None)

    def _awaiting_signature(self, path: str, sha: str, key: tuple) -> bool:
        """A changed file without its FILE.sig yet (or with the previous version's): its signer
        writes it after the file, so it is waited for SIGNATURE_GRACE_S before it counts."""
        try:
            manifest, _ = read_signature_file(path)
            if manifest.sha256 == sha:
                return False
        except SignatureRejected:
            pass
        now = time.monotonic()
        since = self._unsigned_since if self._unsigned_since[0] == key else (key, now)
        self._unsigned_since = since
        return now - since[1] < SIGNATURE_GRACE_S

    def _check_file(self, path: str) -> None:
        key = self._watch_key(path)
        if key is None or key == self._loaded_sig or key == self._failed_sig:
            return
        with self._lock:
            pending = self._pending_policy
        if pending is not None and pending[2] == key:
            return
        counter = None
        try:
            data, sha = self._read_once(path)   # verified and loaded: never read again
            if sha == (pending[3] if pending is not None else self.ckpt_sha):
                self._loaded_sig = key
                return   # the same bytes again (rewritten, or re-signed): nothing new to serve
            if self.trusted is not None and self._awaiting_signature(path, sha, key):
                return
            seq = self._verified_seq(path, sha, len(data))
            policy, counters = self._load_checked(path, data)
            if self._watch_key(path) != key:
                return   # replaced while we read it: take the newer one next poll
        except Exception as e:  # noqa: BLE001 (unsigned, corrupt, foreign, incompatible)
            counter = (CheckpointReceiver.ROLLBACK if isinstance(e, RollbackRejected) else
                       CheckpointReceiver.SIGNATURE if isinstance(e, SignatureRejected) else
                       CheckpointReceiver.MISMATCH if isinstance(e, CheckpointMismatch) else None)
            self._failed_sig = key
            with self._lock:
                self.counters["checkpoint_load_errors"] += 1
                if counter is not None:
                    self.counters[counter] += 1
            self.refusals.refuse(f"file: {counter or type(e).__name__}",
                                 f"cannot load checkpoint {path}: {e}; still serving {self._describe_agent()}")
            return
        self._hand_over(policy, counters, key, sha, path, seq)

    def _hand_over(self, policy, counters: dict, key: tuple | None, sha: str, what: str,
                   seq: int) -> None:
        if self.rollback is not None and seq >= 0:
            try:   # held from now on (installed on disk): the floor survives losing FILE.sig
                self.rollback.raise_to(seq)
            except RollbackStateError as e:
                self.get_logger().error(str(e))
        with self._lock:
            self._pending_policy = (policy, counters, key, sha, seq)
        self.get_logger().info(f"loaded checkpoint {what} (updates={counters.get('updates', '?')}); "
                               "serving it from the next episode")
        # At once, not at the next period: launchers wait for pending_checkpoint_updates.
        self._publish_diagnostics()

    # ------------------------------------------------------------------ checkpoints over ROS
    def _next_sha(self) -> str | None:
        """The version that serves from the next episode on (the receiver skips it)."""
        with self._lock:
            pending = self._pending_policy
        return pending[3] if pending is not None else self.ckpt_sha

    def _newest_seq(self) -> int:
        """Sequence number of the newest signed version held (served or pending), or the one
        below min_checkpoint_seq when that is higher: no new version at or below it is taken;
        -1: none."""
        with self._lock:
            pending = self._pending_policy
        floor = self.rollback.seq if self.rollback is not None else -1
        return max(self.ckpt_seq, floor, pending[4] if pending is not None else -1,
                   self.params["min_checkpoint_seq"] - 1)

    def _swap_if_pending(self) -> None:
        with self._lock:
            pending, self._pending_policy = self._pending_policy, None
        if pending is None:
            return
        self.policy, self.ckpt_counters, self._loaded_sig, self.ckpt_sha, self.ckpt_seq = pending
        self.agent_kind = "checkpoint"
        self.policy.reset()
        with self._lock:
            self.counters["checkpoint_reloads"] += 1
        self.get_logger().info(f"now serving {self._describe_agent()}")
        # At once too: an episode can end (and its recording with it) before the next period,
        # and the bag's /diagnostics would then name only the checkpoint served before.
        self._publish_diagnostics()
