"""A process's own Fast DDS participant lease: how long the others wait for it when it stalls.

Fast DDS drops a participant it has not heard from for that participant's announced lease (20 s
by default). For a recorder that is a silent loss: a lossless (KEEP_ALL, reliable) writer that
drops a stalled reader also drops every sample the reader had not acknowledged, and the woken
reader is matched again as a new, volatile reader that never gets them. A recorder stopped
longer than its lease (Ctrl-Z, a debugger, a swap storm, a machine so loaded that its threads do
not run) therefore lost its whole backlog. A longer lease announced by the recorder alone keeps
it matched through such a stall; everyone else keeps the default, so a dead bridge or policy
node still leaves the graph in 20 s.

The lease is part of the participant, created with the process's first node, and Fast DDS reads
it from the XML profile named by FASTRTPS_DEFAULT_PROFILES_FILE: the environment's profile
(sim_bridge/fastdds_discovery.xml, or the user's) is copied with the lease set, and the process
points the variable at the copy before its first node exists. `announced_lease` says which lease
a process so started announces, for a recorder that reports its own stalls past it.
"""
from __future__ import annotations

import contextlib
import math
import os
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Iterator

PROFILES_ENV = "FASTRTPS_DEFAULT_PROFILES_FILE"   # the only name Fast DDS 2.14 (Jazzy) reads
#: The element path, under the default participant profile, of the lease a participant announces.
LEASE_PATH = ("rtps", "builtin", "discovery_config", "leaseDuration")
FASTDDS_XMLNS = "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"
#: Fast DDS's lease when no profile sets one (s).
FASTDDS_DEFAULT_LEASE_S = 20.0


def _local(elem: ET.Element) -> str:
    return elem.tag.rsplit("}", 1)[-1]


def profile_with_lease(text: str | None, lease_s: float) -> str:
    """The Fast DDS XML profile `text` (None: no profile, Fast DDS's defaults) with its default
    participant announcing a lease of `lease_s` seconds; everything else is kept (transports,
    discovery periods). A profile without a default participant profile gets one."""
    if not 0 < lease_s < 2**31:
        raise ValueError(f"a lease duration is a positive number of seconds (< 2^31), got {lease_s}")
    root = ET.fromstring(text) if text and text.strip() else ET.Element("profiles")
    # Fast DDS matches element names literally (no namespace processing), so the namespace goes
    # back as a plain xmlns attribute on unqualified names, never as an ns0: prefix.
    uri = root.tag[1:root.tag.index("}")] if root.tag.startswith("{") else FASTDDS_XMLNS
    for e in root.iter():
        e.tag = _local(e)
    root.set("xmlns", uri)
    profiles = root if root.tag == "profiles" else next((e for e in root.iter() if e.tag == "profiles"), None)
    if profiles is None:
        profiles = ET.SubElement(root, "profiles")
    participant = next((e for e in profiles if e.tag == "participant"
                        and e.get("is_default_profile") == "true"), None)
    if participant is None:
        participant = ET.SubElement(profiles, "participant",
                                    {"profile_name": "protocad_lease", "is_default_profile": "true"})
    node = participant
    for name in LEASE_PATH:
        found = node.find(name)
        node = found if found is not None else ET.SubElement(node, name)
    sec = int(lease_s)
    for e in list(node):
        node.remove(e)
    ET.SubElement(node, "sec").text = str(sec)
    ET.SubElement(node, "nanosec").text = str(int(round((lease_s - sec) * 1e9)))
    return '<?xml version="1.0" encoding="UTF-8" ?>\n' + ET.tostring(root, encoding="unicode") + "\n"


def profile_lease(text: str | None) -> float | None:
    """The lease (s) the default participant profile of the Fast DDS XML profile `text`
    announces: inf for Fast DDS's DURATION_INFINITY keywords; None where it sets none (Fast
    DDS's default applies) or the value is not a number of seconds."""
    root = ET.fromstring(text) if text and text.strip() else None
    if root is None:
        return None
    for participant in (e for e in root.iter() if _local(e) == "participant"
                        and e.get("is_default_profile") == "true"):
        node: ET.Element | None = participant
        for name in LEASE_PATH:
            node = next((e for e in node if _local(e) == name), None) if node is not None else None
        if node is None:
            continue
        parts = {_local(e): (e.text or "").strip() for e in node}
        if any(v.startswith("DURATION_INFINI") for v in parts.values()):
            return math.inf
        try:
            return float(parts.get("sec") or 0) + float(parts.get("nanosec") or 0) / 1e9
        except ValueError:
            return None
    return None


def announced_lease(lease_s: float) -> float | None:
    """The lease (s) the participant of a process started with `participant_lease(lease_s)`
    announces: `lease_s` itself, or with 0 the environment's profile's or Fast DDS's default;
    None for another rmw (its lease is not read here) or a profile that cannot be read."""
    rmw = os.environ.get("RMW_IMPLEMENTATION") or "rmw_fastrtps_cpp"
    if not rmw.startswith("rmw_fastrtps"):
        return None
    if lease_s > 0:
        return float(lease_s)
    base = os.environ.get(PROFILES_ENV)
    try:
        found = profile_lease(Path(base).read_text()) if base else None
    except (OSError, ET.ParseError):
        return None
    return found if found is not None else FASTDDS_DEFAULT_LEASE_S


@contextlib.contextmanager
def participant_lease(lease_s: float) -> Iterator[Path | None]:
    """Within the block, a participant created (the process's first node) announces a `lease_s`
    lease: the environment's profile with that lease is written to a temporary file that
    FASTRTPS_DEFAULT_PROFILES_FILE names; both are undone on leaving, when Fast DDS has read it.
    Yields the file, or None when nothing is changed: lease_s <= 0, or an rmw that is not Fast
    DDS. ValueError when the environment's profile cannot be read or parsed, or lease_s is
    not a number of seconds."""
    rmw = os.environ.get("RMW_IMPLEMENTATION") or "rmw_fastrtps_cpp"   # Jazzy's default
    if lease_s <= 0 or not rmw.startswith("rmw_fastrtps"):
        yield None
        return
    base = os.environ.get(PROFILES_ENV)
    try:
        text = profile_with_lease(Path(base).read_text() if base else None, lease_s)
    except ET.ParseError as exc:
        raise ValueError(f"{PROFILES_ENV}={base}: not a Fast DDS XML profile ({exc})") from None
    except OSError as exc:
        raise ValueError(f"{PROFILES_ENV}={base}: cannot read it ({exc})") from None
    fd, name = tempfile.mkstemp(prefix="protocad-lease-", suffix=".xml")
    with os.fdopen(fd, "w") as f:
        f.write(text)
    os.environ[PROFILES_ENV] = name
    try:
        yield Path(name)
    finally:
        if base is None:
            os.environ.pop(PROFILES_ENV, None)
        else:
            os.environ[PROFILES_ENV] = base
        os.unlink(name)
