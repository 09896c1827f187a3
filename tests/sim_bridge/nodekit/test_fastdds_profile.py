"""The recorder's own participant lease (sim_bridge.nodekit.fastdds_profile): the environment's
Fast DDS profile with only the lease changed. That Fast DDS applies it (a recorder frozen past
the default 20 s lease keeps its backlog) is tests/trainer/nodes/test_lossless.py."""
from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from sim_bridge.nodekit.fastdds_profile import (
    FASTDDS_DEFAULT_LEASE_S,
    PROFILES_ENV,
    announced_lease,
    participant_lease,
    profile_lease,
    profile_with_lease,
)

ROOT = Path(__file__).resolve().parents[3]
NS = "{http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles}"


def lease(text: str) -> tuple[int, int]:
    (node,) = ET.fromstring(text).iter(f"{NS}leaseDuration")
    return int(node.find(f"{NS}sec").text), int(node.find(f"{NS}nanosec").text)


def test_the_project_profile_keeps_its_loopback_transports_and_gets_the_lease():
    text = profile_with_lease((ROOT / "sim_bridge" / "fastdds_discovery.xml").read_text(), 120.5)
    root = ET.fromstring(text)
    assert lease(text) == (120, 500_000_000)
    assert [a.text for a in root.iter(f"{NS}address")] == ["127.0.0.1"]
    assert [t.text for t in root.iter(f"{NS}transport_id")].count("protocad_shm") == 2
    assert root.find(f".//{NS}useBuiltinTransports").text == "false"
    (announce,) = root.iter(f"{NS}leaseAnnouncement")
    assert announce.find(f"{NS}nanosec").text == "500000000"
    assert "ns0:" not in text            # Fast DDS reads element names literally


def test_a_lease_already_in_a_profile_is_replaced_and_a_missing_profile_gets_one():
    mine = ('<dds><profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">'
            '<participant profile_name="p" is_default_profile="true"><rtps><builtin><discovery_config>'
            '<leaseDuration><sec>3</sec></leaseDuration></discovery_config></builtin></rtps>'
            '</participant></profiles></dds>')
    text = profile_with_lease(mine, 60)
    assert text.count("leaseDuration>") == 2 and lease(text) == (60, 0)
    assert lease(profile_with_lease(None, 7)) == (7, 0)
    for bad in (0, -1, float("nan"), float("inf")):
        with pytest.raises(ValueError):
            profile_with_lease(None, bad)


def test_participant_lease_points_fast_dds_at_the_copy_only_while_the_node_is_made(tmp_path, monkeypatch):
    base = tmp_path / "mine.xml"
    base.write_text((ROOT / "sim_bridge" / "fastdds_discovery.xml").read_text())
    monkeypatch.setenv(PROFILES_ENV, str(base))
    monkeypatch.delenv("RMW_IMPLEMENTATION", raising=False)
    with participant_lease(90) as path:
        assert os.environ[PROFILES_ENV] == str(path) and lease(path.read_text()) == (90, 0)
    assert os.environ[PROFILES_ENV] == str(base) and not path.exists()
    with participant_lease(0) as nothing:
        assert nothing is None and os.environ[PROFILES_ENV] == str(base)
    monkeypatch.setenv("RMW_IMPLEMENTATION", "rmw_cyclonedds_cpp")
    with participant_lease(90) as nothing:
        assert nothing is None
    monkeypatch.delenv("RMW_IMPLEMENTATION")
    base.write_text("<profiles><participant")
    with pytest.raises(ValueError, match="not a Fast DDS XML profile"), participant_lease(90):
        pass
    monkeypatch.setenv(PROFILES_ENV, str(tmp_path / "missing.xml"))
    with pytest.raises(ValueError, match="cannot read"), participant_lease(90):
        pass


def test_the_lease_a_process_announces_is_read_back(tmp_path, monkeypatch):
    """What the recorder's stall watch measures against: the lease it asked for, or with 0 the
    environment profile's, or Fast DDS's 20 s; unknown under another rmw."""
    project = (ROOT / "sim_bridge" / "fastdds_discovery.xml").read_text()
    assert profile_lease(profile_with_lease(project, 42.25)) == 42.25
    assert profile_lease(project) is None and profile_lease(None) is None
    infinite = profile_with_lease(None, 5).replace("<sec>5</sec>", "<sec>DURATION_INFINITY</sec>")
    assert profile_lease(infinite) == float("inf")
    monkeypatch.delenv("RMW_IMPLEMENTATION", raising=False)
    mine = tmp_path / "mine.xml"
    mine.write_text(profile_with_lease(project, 7))
    monkeypatch.setenv(PROFILES_ENV, str(mine))
    assert announced_lease(30) == 30 and announced_lease(0) == 7
    monkeypatch.delenv(PROFILES_ENV)
    assert announced_lease(0) == FASTDDS_DEFAULT_LEASE_S
    with participant_lease(90):
        assert announced_lease(0) == 90
    monkeypatch.setenv("RMW_IMPLEMENTATION", "rmw_cyclonedds_cpp")
    assert announced_lease(30) is None
