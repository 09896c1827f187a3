"""`protocad-stack FILE.yaml`: the sim bridge, the policy and the recorder from one file, in the
order that loses nothing, with one combined log and one Ctrl-C for all of them.

    protocad-stack stack.yaml
    protocad-stack stack.yaml --set bridge.task=walker_walk --set policy.checkpoint=runs/w/checkpoints/latest.pt

stack.yaml (every key but `namespace` and the three sections is refused; each section's keys
are that node's ROS parameters, as `-p key:=value`; `recorder: false` records nothing):

    namespace: /protocad
    bridge:   {task: pendulum_swingup, mode: lockstep, max_episodes: 2}
    policy:   {checkpoint: runs/X/checkpoints/latest.pt}
    recorder: {output: runs/X/bags/session1}

Order: the recorder starts first, then the policy; once the policy is active (its lifecycle
state) and the ROS graph shows the recorder subscribed to the policy's `action` topic, the
bridge starts with `min_subscribers` = the policy and the
recorder, so it publishes its first observation only when both read it: the bag holds every
step and every action from stamp 0. Each node logs to LOG_DIR/NAME.log (default beside the
bag, else runs/stack-STAMP/logs) and to this terminal with a `[name]` prefix. The stack ends
when the bridge finishes (`max_episodes`), a node fails, or on Ctrl-C; the nodes stop in that
order: bridge, policy, recorder (it drains and closes its bag). Exit 0 when every node exited 0.
A policy checkpoint whose task or image size differs from the bridge's, or a policy with a
checkpoint_topic but no trusted_keys (nor allow_unsigned: true), is refused before any node
starts (exit 2); a policy that refuses its bridge while running (its diagnostics at
ERROR, e.g. after reloading another task's checkpoint) stops the stack with exit 1.
The ROS domain is $ROS_DOMAIN_ID (or `--domain-id`); DDS stays on this machine.
"""
from __future__ import annotations

import argparse
import os
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import yaml

from protocad_ros.checkpoint.files import CheckpointError, checkpoint_file
from sim_bridge.bridge.params import PARAMS as BRIDGE_PARAMS
from sim_bridge.contract import topics as T
from trainer import console, run_config
from trainer.launch import discovery
from trainer.launch.rosprocs import NodeFailed, RosStack, recorder_endpoints
from trainer.settings import arg, build, settings_parser

SECTIONS = ("bridge", "policy", "recorder")
DIAG_ERROR = 2   # diagnostic_msgs/DiagnosticStatus.ERROR
MODULES = {"bridge": "sim_bridge.bridge.node", "policy": "protocad_ros.node.policy_node", "recorder": "trainer.nodes.recorder"}


def load_stack(path: str | Path, overrides: Sequence[str] = ()) -> dict[str, Any]:
    """The stack file with `section.key=value` overrides (values parsed as YAML); ValueError
    naming what is wrong."""
    try:
        doc = yaml.safe_load(Path(path).read_text()) or {}
    except (OSError, yaml.YAMLError) as exc:
        raise ValueError(f"{path}: {exc}") from None
    if not isinstance(doc, dict):
        raise ValueError(f"{path}: expected a mapping with {', '.join(SECTIONS)}")
    unknown = sorted(set(doc) - {"namespace", *SECTIONS})
    if unknown:
        raise ValueError(f"{path}: unknown key(s) {unknown}; valid: namespace, {', '.join(SECTIONS)}")
    for key, value in run_config.parse_set(overrides).items():
        section, _, name = key.partition(".")
        if section not in SECTIONS or not name:
            raise ValueError(f"--set {key}: expected bridge.NAME, policy.NAME or recorder.NAME")
        doc.setdefault(section, {})
        if doc[section] is False:
            doc[section] = {}
        doc[section][name] = value
    for section in ("bridge", "policy"):
        if not isinstance(doc.get(section, {}), dict):
            raise ValueError(f"{path}: {section} must be a mapping of ROS parameters")
    if doc.get("recorder", {}) not in (False, None) and not isinstance(doc.get("recorder", {}), dict):
        raise ValueError(f"{path}: recorder must be a mapping of its parameters, or false")
    return doc


def checkpoint_mismatch(doc: dict[str, Any]) -> str | None:
    """Why the policy's checkpoint cannot drive the bridge of this stack file (its task or image
    size differ), or None. Read before any node starts: a mismatched stack would otherwise run
    with a policy that refuses every observation."""
    # torch comes with the checkpoint module: the stack's --help and its nodes do without it here.
    from protocad_ros.checkpoint.agent_file import read_checkpoint

    path = (doc.get("policy") or {}).get("checkpoint")
    if not path or not Path(path).exists():
        return None   # a random agent, or wait_for_checkpoint: the node checks what arrives
    path = checkpoint_file(path)
    if not path.is_file():
        return None   # a run directory without a checkpoint yet: the node waits or says why
    try:
        cfg = read_checkpoint(path)["config"]
    except CheckpointError as exc:
        return str(exc)
    defaults = {p.name: p.default for p in BRIDGE_PARAMS}
    bridge = {**defaults, **(doc.get("bridge") or {})}
    why = []
    if cfg.get("task") != bridge["task"]:
        why.append(f"it was trained on {cfg.get('task')} but bridge.task is {bridge['task']}")
    size = (cfg.get("train") or {}).get("image_size", 64)
    if int(size) != int(bridge["image_size"]):
        why.append(f"it sees {size}x{size} images but bridge.image_size is {bridge['image_size']}")
    if not why:
        return None
    return (f"policy.checkpoint {path} ({cfg.get('variant')}) does not fit this bridge: "
            + "; ".join(why) + f". Set bridge.task: {cfg.get('task')} or give a checkpoint of "
            f"{bridge['task']}.")


def unsigned_topic(doc: dict[str, Any]) -> str | None:
    """Why the policy of this stack file would refuse to start: it receives checkpoints over ROS
    (checkpoint_topic) but trusts no key and does not allow unsigned ones; None if it is fine."""
    policy = doc.get("policy") or {}
    if not policy.get("checkpoint_topic") or policy.get("trusted_keys") or policy.get("allow_unsigned") is True:
        return None
    return (f"policy.checkpoint_topic {policy['checkpoint_topic']} without policy.trusted_keys: set "
            "policy.trusted_keys to the learner's public key (protocad-keygen; its publisher signs with "
            "the private key), or policy.allow_unsigned: true to serve unsigned checkpoints")


def ros_params(params: dict[str, Any]) -> list[str]:
    out = []
    for k, v in params.items():
        v = ("true" if v else "false") if isinstance(v, bool) else v
        out += ["-p", f"{k}:={v}"]
    return out


class LogFollower(threading.Thread):
    """Prints the new lines of each node's log file with a `[name]` prefix."""

    def __init__(self, procs: dict, out=sys.stdout):
        super().__init__(daemon=True)
        self.procs, self.out, self.stop = procs, out, threading.Event()
        self._pos: dict[str, int] = {}

    def run(self) -> None:
        while not self.stop.is_set():
            self.flush()
            time.sleep(0.1)

    def flush(self) -> None:
        for name, proc in list(self.procs.items()):
            try:
                with open(proc.log_path, "rb") as f:
                    f.seek(self._pos.get(name, 0))
                    data = f.read()
            except OSError:
                continue
            end = data.rfind(b"\n") + 1
            if end:
                self._pos[name] = self._pos.get(name, 0) + end
                for line in data[:end].decode(errors="replace").splitlines():
                    print(f"[{name}] {line}", file=self.out, flush=True)


def run(doc: dict[str, Any], *, log_dir: Path, domain_id: int | None, ready_timeout: float,
        discovery_server: str | None = None, start_discovery_server: tuple[str, int] | None = None) -> int:
    ns = doc.get("namespace") or T.DEFAULT_NAMESPACE
    try:
        stack = RosStack(log_dir, domain_id=domain_id, namespace=ns, discovery_server=discovery_server,
                         start_discovery_server=start_discovery_server)
    except NodeFailed as exc:
        print(f"[stack] {exc}", file=sys.stderr, flush=True)
        return 1
    follower = LogFollower(stack.procs)
    follower.start()
    record = doc.get("recorder", {}) is not False
    print(f"[stack] ROS_DOMAIN_ID={stack.domain_id}, namespace {ns}, {stack.describe_discovery()}, logs in {log_dir}",
          flush=True)
    codes: dict[str, int | None] = {}
    refused = None
    with console.StopFlag() as stop:
        try:
            if record:
                rec = dict(doc.get("recorder") or {})
                output = rec.pop("output", None) or str(log_dir.parent / "bag")
                up, reading = recorder_endpoints([]), recorder_endpoints([T.topic_name(ns, T.ACTION)])
                # Endpoints of another recorder on this domain (e.g. a previous stack's, going).
                old = stack.graph.snapshot("recorder", "/", up + reading)
                proc = stack._spawn("recorder", MODULES["recorder"], ["-o", str(output), "--namespace", ns,  # noqa: SLF001 - RosStack's generic start: a stack file picks the nodes
                                                                       "--ros-args", *ros_params(rec)],
                                    super_client=True)   # it reads topic types from the graph
                stack.wait_endpoints(proc, "recorder", "/", up, ready_timeout, stop=stop, old=old)
            policy = dict(doc.get("policy") or {})
            policy.setdefault("task", (doc.get("bridge") or {}).get("task", "pendulum_swingup"))
            proc = stack._spawn("policy", MODULES["policy"], ["--ros-args", *ros_params(policy), "-r", f"__ns:={ns}"])  # noqa: SLF001
            stack.wait_active(proc, "policy", ready_timeout, stop=stop)
            if record:   # the action topic exists now: wait until the recorder reads it
                stack.wait_endpoints(stack.procs["recorder"], "recorder", "/", reading, ready_timeout,
                                     stop=stop, old=old)
            bridge = dict(doc.get("bridge") or {})
            bridge.setdefault("min_subscribers", 2 if record else 1)
            stack._spawn("bridge", MODULES["bridge"], ["--ros-args", *ros_params(bridge), "-r", f"__ns:={ns}"])  # noqa: SLF001
            print("[stack] running: Ctrl-C stops every node", flush=True)
            policy_fqn = stack.node_fqn("policy")
            while not stop.stop:
                status = stack.graph.diagnostic_status(policy_fqn)
                if status and status[0] == DIAG_ERROR and status[1].startswith("not answering"):
                    # e.g. a reloaded checkpoint of another task: the bridge would wait forever
                    refused = f"the policy refuses the bridge: {status[1]}"
                    print(f"[stack] {refused}: stopping the stack", file=sys.stderr, flush=True)
                    break
                dead = [n for n, p in stack.procs.items() if not p.alive()]
                if dead:
                    if dead == ["bridge"] and stack.procs["bridge"].p.returncode == 0:
                        print("[stack] the bridge finished", flush=True)
                    else:
                        print(f"[stack] {', '.join(dead)} exited: stopping the stack", flush=True)
                    break
                time.sleep(0.2)
        except NodeFailed as exc:
            print(f"[stack] {exc}", file=sys.stderr, flush=True)
        finally:
            codes = stack.stop_all()
            time.sleep(0.3)
            follower.flush()
            follower.stop.set()
    if stack.forged_note():
        print(f"[stack] {stack.forged_note()}", file=sys.stderr, flush=True)
    print("[stack] exit codes: " + ", ".join(f"{n} {c}" for n, c in codes.items()), flush=True)
    if refused:
        print(f"[stack] failed: {refused}", file=sys.stderr, flush=True)
        return 1
    return 0 if codes and all(c == 0 for c in codes.values()) else 1


@dataclass
class StackSettings(discovery.DiscoverySettings):
    """protocad-stack's options: the stack file, overrides, and how its nodes discover."""

    file: str = arg(None, "file")
    """the stack file (YAML)"""
    set: list[str] = arg([], action="append", metavar="SECTION.KEY=VALUE")
    """override one parameter, e.g. --set bridge.task=walker_walk (repeatable)"""
    log_dir: str | None = None
    """node logs (default: beside the bag, or runs/stack-STAMP/logs)"""
    domain_id: int | None = None
    """ROS_DOMAIN_ID (default: the environment's)"""
    ready_timeout: float = 120.0
    """seconds each node may take to start"""


def build_parser() -> argparse.ArgumentParser:
    return settings_parser("protocad-stack", __doc__.split("\n\n")[0], [(None, StackSettings)],
                           epilog=__doc__.split("\n\n", 1)[1])


def main(argv: Sequence[str] | None = None) -> int:
    a = build(StackSettings, vars(build_parser().parse_args(argv)))
    try:
        doc = load_stack(a.file, a.set)
    except ValueError as exc:
        print(f"protocad-stack: error: {exc}", file=sys.stderr)
        return 2
    mismatch = checkpoint_mismatch(doc) or unsigned_topic(doc)
    if mismatch:
        print(f"protocad-stack: error: {mismatch}", file=sys.stderr)
        return 2
    out = (doc.get("recorder") or {}).get("output") if isinstance(doc.get("recorder"), dict) else None
    log_dir = Path(a.log_dir) if a.log_dir else (Path(out).parent / "logs" if out else
                                                 Path(time.strftime("runs/stack-%Y%m%d-%H%M%S")) / "logs")
    domain = a.domain_id if a.domain_id is not None else (int(os.environ["ROS_DOMAIN_ID"])
                                                          if os.environ.get("ROS_DOMAIN_ID", "").isdigit() else None)
    server, start_server = discovery.from_args(a)
    return run(doc, log_dir=log_dir, domain_id=domain, ready_timeout=a.ready_timeout,
               discovery_server=server, start_discovery_server=start_server)


if __name__ == "__main__":
    sys.exit(main())
