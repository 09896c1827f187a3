"""trainer/launch/rosprocs.py: the domain a launcher's nodes get."""
from __future__ import annotations

import os

import pytest

from trainer.launch.rosprocs import FRESH_DOMAINS, domains_in_use, fresh_domain_id


@pytest.mark.ros
def test_a_domain_with_a_participant_on_this_machine_is_seen_in_use():
    from helpers.ros import Probe

    mine = int(os.environ["ROS_DOMAIN_ID"])
    probe = Probe("domain_probe")      # a real participant in this test's domain
    try:
        assert mine in domains_in_use()
    finally:
        probe.close()


def test_a_fresh_domain_is_never_one_in_use(tmp_path):
    free = 42
    in_use = set(FRESH_DOMAINS) - {free}
    assert {fresh_domain_id(in_use) for _ in range(50)} == {free}
    # every one in use (a crowded machine): still a valid domain, not an error
    assert fresh_domain_id(set(FRESH_DOMAINS)) in FRESH_DOMAINS
    # the kernel's table read as it is written: port 7410 + 250 * 37 is domain 37's
    table = tmp_path / "udp"
    table.write_text("  sl  local_address rem_address   st\n"
                     f"   0: 0100007F:{7410 + 250 * 37:04X} 00000000:0000 07\n"
                     "   1: 00000000:0044 00000000:0000 07\n")
    assert domains_in_use([str(table), str(tmp_path / "absent")]) == {37}
