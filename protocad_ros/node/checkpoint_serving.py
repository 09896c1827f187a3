"""`CheckpointServing`: the part of the policy node (protocad_ros/node/policy_node.py) that owns
the model it serves: loading it at configure (a checkpoint file or run directory, or a random
agent), verifying every version, watching the file, receiving versions over ROS and swapping a
newer one in at the next is_first.

After configure one background thread (`_watch`) is the only place checkpoints are loaded: the
file when it changed, polled every `reload_poll_s`, and versions the CheckpointReceiver it owns
(checkpoint_receiver.py) got over ROS. A loaded model is handed over (`_hand_over`) and swapped
in by the executor thread at the next is_first (`swap_if_pending`), so no step waits for a load
and no episode is served by two models.

With `trusted_keys` nothing is served that a trusted key did not sign: the file needs its
detached signature FILE.sig, received versions a signed announcement (the receiver checks it),
and each new version a sequence number above the newest one held; CheckpointTrust
(checkpoint_trust.py) keeps the keys and the rollback floor. A file is read once: those bytes
are verified and loaded, never a second read of the path. With `checkpoint_topic` and no
trusted keys the node refuses to start unless `allow_unsigned`. Whatever the source, a
checkpoint is checked against what the node serves (task, action and image size, variant and
architecture: the random agent's too) before anything is built. Refusals are counted, their
lines rate-limited (refusal_log.py).

It owns the served Policy, its ModelFacts (fixed from configure to cleanup: every version
swapped in fits them), the checkpoint's counters, sha256 and sequence number, the version
pending for the next episode (under its own lock), the watcher thread and the receiver. It is
handed the node (its logger; the receiver's subscriptions), the parameter dict, the node's
`count(key, why)` and `publish_diagnostics()`, called at each hand-over and swap.
"""
from __future__ import annotations

import hashlib
import threading
from dataclasses import dataclass, field
from typing import Any, Callable

from protocad_ros.atomic import file_signature, remove_stale_temporaries
from protocad_ros.checkpoint.files import (
    CheckpointError,
    CheckpointMismatch,
    architecture_differences,
    checkpoint_file,
    read_checkpoint_file,
)
from protocad_ros.checkpoint.signing import SignatureRejected
from protocad_ros.model.config import make_config
from protocad_ros.node.checkpoint_receiver import CheckpointReceiver, ReceiverSettings
from protocad_ros.node.checkpoint_trust import CheckpointTrust, RollbackRejected
from protocad_ros.node.refusal_log import RefusalLog
from sim_bridge.contract.contexts import task_actuators
from sim_bridge.nodekit.param_table import ConfigError


@dataclass(frozen=True)
class ModelFacts:
    """What the served model is for (unconfigured: the `task` parameter and no sizes)."""

    task: str
    action_dim: int = 0
    image_hw: tuple[int, int] = (0, 0)
    action_names: list[str] = field(default_factory=list)


def read_once(path: str, max_bytes: int) -> tuple[bytes, str]:
    """The file's bytes and their sha256: the one read that is verified and loaded (a file over
    max_bytes is refused before it is read: CheckpointError)."""
    data = read_checkpoint_file(path, max_bytes)
    return data, hashlib.sha256(data).hexdigest()


def _policy_kwargs(p: dict[str, Any]) -> dict[str, Any]:
    return dict(device=p["device"], mode=p["mode"], exploration_noise=p["exploration_noise"],
                seed=p["seed"], state_mean=p["state_mean"])


def load_policy(path: str, p: dict[str, Any], fits=None, data: bytes | None = None):
    """(Policy, counters) from `data`, the bytes of `path` as read (and verified) once; `fits`
    refuses a config that does not fit before anything is built."""
    from protocad_ros.checkpoint.agent_file import load_checkpoint
    from protocad_ros.policy import Policy

    # Never the file's RNG state: a served checkpoint must not reseed this process.
    agent, counters = load_checkpoint(path, device=p["device"], fits=fits, restore_rng=False,
                                      optimizer_states=False, data=data, max_bytes=p["max_checkpoint_bytes"])
    # `updates` = the agent's own update counter (restored with the weights); the other
    # counters are the trainer's (env steps, episodes, ...), reported as checkpoint/<key>.
    counters = {**dict(counters or {}), "updates": int(agent.counters()["updates"])}
    return Policy(agent, **_policy_kwargs(p)), counters


def random_policy(p: dict[str, Any]):
    """A randomly initialised agent of the `variant` and `preset` parameters for `task`."""
    from protocad_ros.model.agent import make_agent
    from protocad_ros.policy import Policy

    cfg = make_config(p["task"], p["preset"], p["variant"], **{"train.seed": p["seed"]})
    agent = make_agent(cfg, len(task_actuators(p["task"])), device=p["device"])
    return Policy(agent, **_policy_kwargs(p))


def model_facts(policy, task: str) -> ModelFacts:
    """The facts of a loaded policy (`task` where its config names none); generic action names
    where the task's actuators are not the policy's."""
    cfg = policy.agent.cfg
    task = getattr(cfg, "task", task)
    action_dim = int(policy.agent.action_dim)
    try:
        names = task_actuators(task)
    except Exception:  # noqa: BLE001 - no actuator names for this task: generic ones below
        names = []
    return ModelFacts(task, action_dim, (int(cfg.train.image_size),) * 2,
                      names if len(names) == action_dim else [f"a{i}" for i in range(action_dim)])


class CheckpointServing:
    """Loading, verifying, watching and swapping the served checkpoint; see the module docstring."""

    def __init__(self, *, node: Any, params: dict[str, Any], count: Callable[..., None],
                 publish_diagnostics: Callable[[], None]):
        self._node, self._params, self._count = node, params, count
        self._log = node.get_logger()
        self._publish_diagnostics = publish_diagnostics
        self.trust = CheckpointTrust(params=params, logger=self._log)
        self.refusals = RefusalLog(self._log.error)   # refused checkpoints' lines
        self._lock = threading.Lock()            # guards _pending_policy
        self._stop = threading.Event()           # set: the checkpoint watcher ends (cleanup)
        self._wake = threading.Event()           # set: the watcher looks now (a received version)
        self.receiver: CheckpointReceiver | None = None
        self.release()

    def release(self) -> None:
        """No model (unconfigured)."""
        self.policy = None
        self.facts = ModelFacts(self._params["task"])
        self.ckpt_counters: dict[str, Any] = {}
        self.agent_kind = "none"
        self._watcher: threading.Thread | None = None
        self._loaded_sig: tuple | None = None     # watch keys (CheckpointTrust.watch_key)
        self._failed_sig: tuple | None = None
        self.ckpt_sha: str | None = None          # sha256 of the served checkpoint file
        self.ckpt_seq = -1                        # its signed sequence number (-1: unsigned)
        self.trust.release()
        with self._lock:
            self._pending_policy: tuple | None = None   # (policy, counters, key, sha, seq) to swap in

    # ------------------------------------------------------------------ lifecycle
    def configure(self) -> None:
        """Load the checkpoint (or build the random agent); a missing or unloadable checkpoint,
        or trust settings that do not go together, are a ConfigError."""
        p = self._params
        if p["checkpoint"]:   # a file or a run directory, as everywhere else
            p["checkpoint"] = str(checkpoint_file(p["checkpoint"]))
        path, topic = p["checkpoint"], p["checkpoint_topic"]
        if topic and not path:
            raise ConfigError(f"checkpoint_topic:={topic} needs checkpoint:=FILE: where received "
                              "versions are written (and served from after a restart)")
        self.trust.load()
        sig = file_signature(path) if path else None
        if sig is not None:
            try:
                data, self.ckpt_sha = read_once(path, p["max_checkpoint_bytes"])   # verified and loaded, read once
            except (OSError, CheckpointError) as e:   # CheckpointError: over max_checkpoint_bytes
                raise ConfigError(f"cannot read checkpoint {path}: {e}") from None
            self.ckpt_seq = self.trust.configured_seq(path, self.ckpt_sha, len(data))
            try:
                self.policy, self.ckpt_counters = load_policy(path, p, data=data)
            except Exception as e:  # noqa: BLE001 - CheckpointError and friends: a clear message, exit 2
                raise ConfigError(f"cannot load checkpoint {path}: {e}") from None
            self._loaded_sig = self.trust.watch_key(path)
            self.agent_kind = "checkpoint"
        elif path and not (p["wait_for_checkpoint"] or topic):
            raise ConfigError(f"checkpoint {path} does not exist (set wait_for_checkpoint:=true "
                              "to serve a random agent until it appears)")
        elif path and p["reload_poll_s"] <= 0 and not topic:
            raise ConfigError(f"checkpoint {path} does not exist and reload_poll_s is 0: it "
                              "would never be loaded")
        else:
            self.policy, self.ckpt_counters = random_policy(p), {}
            self.agent_kind = "random"
            self._log.warning(
                ("checkpoint %s does not exist yet: " % path if path else "no checkpoint given: ")
                + f"serving a RANDOMLY INITIALISED {p['variant']} agent ({p['preset']} preset, "
                f"task {p['task']}); its actions are meaningless")
        self.facts = model_facts(self.policy, p["task"])
        self.policy.reset()

    def start(self) -> None:
        """After configure: the receiver (with checkpoint_topic) and the watcher thread."""
        p = self._params
        path, topic = p["checkpoint"], p["checkpoint_topic"]
        self._stop.clear()
        if topic:
            remove_stale_temporaries(path)   # what an install interrupted by a kill left
            self.receiver = CheckpointReceiver(self._node, topic, ReceiverSettings(
                timeout_s=p["checkpoint_transfer_timeout_s"], wake=self._wake.set,
                next_sha=self._next_sha, serving=self.describe_agent, count=self._count,
                max_bytes=p["max_checkpoint_bytes"], trusted=self.trust.trusted,
                newest_seq=self._newest_seq, fits=self._announced_fits, refusals=self.refusals))
        if path and (p["reload_poll_s"] > 0 or topic):
            self._watcher = threading.Thread(target=self._watch, name="checkpoint_watcher",
                                             daemon=True)
            self._watcher.start()

    def stop(self) -> None:
        """Cleanup: the receiver goes and the watcher ends (a RuntimeError when it does not
        within 10 s); on a half-configured node too."""
        self._stop.set()
        self._wake.set()
        if self.receiver is not None:
            self.receiver.destroy()
            self.receiver = None
        if self._watcher is not None:
            self._watcher.join(timeout=10.0)
            if self._watcher.is_alive():
                raise RuntimeError("the checkpoint watcher did not end within 10 s")

    # ------------------------------------------------------------------ what is served
    @property
    def checkpoint_updates(self) -> int:
        return int(self.ckpt_counters.get("updates", -1)) if self.agent_kind == "checkpoint" else -1

    def describe_agent(self) -> str:
        if self.agent_kind == "random":
            return "a random agent"
        return f"checkpoint {self._params['checkpoint']} (updates={self.checkpoint_updates})"

    @property
    def unsigned_topic(self) -> bool:
        """Unsigned checkpoints over ROS are accepted (allow_unsigned): shown in /diagnostics."""
        return self.trust.unsigned_topic

    def diagnostics(self) -> dict[str, Any]:
        """This part's keys on the node's /diagnostics."""
        with self._lock:
            pending = self._pending_policy
        receiver = self.receiver
        return {
            "agent": self.agent_kind, "checkpoint": self._params["checkpoint"],
            "checkpoint_updates": self.checkpoint_updates,
            "pending_checkpoint_updates": (pending[1].get("updates", -1) if pending else -1),
            "checkpoint_sha256": self.ckpt_sha or "",
            "checkpoint_announced": receiver.last_announced if receiver is not None else "",
            "checkpoint_transfer": receiver.progress() if receiver is not None else "",
            "checkpoint_buffered_bytes": receiver.buffered_bytes() if receiver is not None else 0,
            "checkpoint_seq": self.ckpt_seq,
            **self.trust.diagnostics(),
            "unsigned_checkpoints_allowed": self.unsigned_topic,
            # The trainer's scalar counters only (env steps, episodes, ...): its sampler state
            # and bag list would be kilobytes on every diagnostics message.
            **{f"checkpoint/{k}": v for k, v in self.ckpt_counters.items()
               if k != "updates" and isinstance(v, (int, float)) and not isinstance(v, bool)},
        }

    # ------------------------------------------------------------------ the watcher thread
    def _watch(self) -> None:
        """Background: the one place checkpoints are loaded after configure: the file when it
        changed (polled every reload_poll_s) and versions received over ROS (woken at once).
        A loaded one goes to the executor thread, which swaps it in at the next is_first."""
        path, poll = self._params["checkpoint"], self._params["reload_poll_s"]
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
                    self._hand_over(policy, counters, self.trust.watch_key(path), sha, what, seq)
            if poll > 0:
                self._check_file(path)
            self.refusals.flush()

    def _load_checked(self, path: str, data: bytes):
        """A checkpoint that replaces the served one, from its verified bytes: refused
        (CheckpointMismatch) before it is built unless it fits what this node serves."""
        return load_policy(path, self._params, fits=self._fits_served, data=data)

    def _fits_served(self, cfg, action_dim: int) -> None:
        why = []
        facts = self.facts
        if cfg.task != facts.task:
            why.append(f"it is for {cfg.task}, this node serves {facts.task}")
        if action_dim != facts.action_dim or (int(cfg.train.image_size),) * 2 != facts.image_hw:
            why.append(f"{action_dim}-d actions / {cfg.train.image_size}px images, but this node "
                       f"serves {facts.action_dim}-d / {facts.image_hw[0]}px")
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
        task = self.facts.task
        if ann.task and ann.task != task:
            return f"it is for {ann.task}, this node serves {task}"
        policy = self.policy
        if policy is not None and ann.variant and ann.variant != policy.agent.cfg.variant:
            return f"it is a {ann.variant} agent, this node serves {policy.agent.cfg.variant}"
        return None

    def _check_file(self, path: str) -> None:
        key = self.trust.watch_key(path)
        if key is None or key == self._loaded_sig or key == self._failed_sig:
            return
        with self._lock:
            pending = self._pending_policy
        if pending is not None and pending[2] == key:
            return
        counter = None
        try:
            data, sha = read_once(path, self._params["max_checkpoint_bytes"])   # verified and loaded: never read again
            if sha == (pending[3] if pending is not None else self.ckpt_sha):
                self._loaded_sig = key
                return   # the same bytes again (rewritten, or re-signed): nothing new to serve
            if self.trust.awaiting_signature(path, sha, key):
                return
            seq = self.trust.verified_seq(path, sha, len(data), self._newest_seq())
            policy, counters = self._load_checked(path, data)
            if self.trust.watch_key(path) != key:
                return   # replaced while we read it: take the newer one next poll
        except Exception as e:  # noqa: BLE001 (unsigned, corrupt, foreign, incompatible)
            counter = (CheckpointReceiver.ROLLBACK if isinstance(e, RollbackRejected) else
                       CheckpointReceiver.SIGNATURE if isinstance(e, SignatureRejected) else
                       CheckpointReceiver.MISMATCH if isinstance(e, CheckpointMismatch) else None)
            self._failed_sig = key
            self._count("checkpoint_load_errors")
            if counter is not None:
                self._count(counter)
            self.refusals.refuse(f"file: {counter or type(e).__name__}",
                                 f"cannot load checkpoint {path}: {e}; still serving {self.describe_agent()}")
            return
        self._hand_over(policy, counters, key, sha, path, seq)

    def _hand_over(self, policy, counters: dict, key: tuple | None, sha: str, what: str,
                   seq: int) -> None:
        self.trust.hold(seq)
        with self._lock:
            self._pending_policy = (policy, counters, key, sha, seq)
        self._log.info(f"loaded checkpoint {what} (updates={counters.get('updates', '?')}); "
                       "serving it from the next episode")
        # At once, not at the next period: launchers wait for pending_checkpoint_updates.
        self._publish_diagnostics()

    # ------------------------------------------------------------------ versions held
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
        return max(self.ckpt_seq, self.trust.floor, pending[4] if pending is not None else -1,
                   self._params["min_checkpoint_seq"] - 1)

    def swap_if_pending(self) -> None:
        """Executor thread, at is_first: the version handed over (if any) serves from now on."""
        with self._lock:
            pending, self._pending_policy = self._pending_policy, None
        if pending is None:
            return
        self.policy, self.ckpt_counters, self._loaded_sig, self.ckpt_sha, self.ckpt_seq = pending
        self.agent_kind = "checkpoint"
        self.policy.reset()
        self._count("checkpoint_reloads")
        self._log.info(f"now serving {self.describe_agent()}")
        # At once too: an episode can end (and its recording with it) before the next period,
        # and the bag's /diagnostics would then name only the checkpoint served before.
        self._publish_diagnostics()
