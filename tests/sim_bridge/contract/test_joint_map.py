"""The joint map (sim_bridge/contract/joint_map.py): a robot's joint order and units from the
policy's actions and back, rate limits, and every way a map can fail to fit, one line each."""
from __future__ import annotations

import numpy as np
import pytest
import yaml

from sim_bridge.contract.contexts import task_actuators
from sim_bridge.contract.joint_map import JointMapError, identity_map, load_joint_map, parse_joint_map

WALKER = task_actuators("walker_walk")


def _permuted_doc() -> dict:
    """The walker's six actions on an arm in another order and in other units."""
    order = [3, 0, 5, 1, 4, 2]
    return {"joints": [{"name": f"joint_{i}", "action": WALKER[a], "scale": 0.5 + i, "offset": -0.25 * i,
                        "max_rate": 2.0} for i, a in enumerate(order)]}


def test_a_permuted_scaled_map_round_trips_and_writes_the_robots_order_and_units(tmp_path):
    path = tmp_path / "arm.yaml"
    path.write_text(yaml.safe_dump(_permuted_doc()))
    jm = load_joint_map(path, WALKER)
    action = np.linspace(-1, 1, 6)
    command = jm.to_robot(action)
    assert jm.joint_names == tuple(f"joint_{i}" for i in range(6))
    assert command[0] == pytest.approx(0.5 * action[3]) and command[1] == pytest.approx(1.5 * action[0] - 0.25)
    assert np.allclose(jm.to_action(command), action)
    ident = identity_map(WALKER)
    assert np.array_equal(ident.to_robot(action), action) and ident.joint_names == tuple(WALKER)


def test_the_rate_limit_moves_each_joint_by_at_most_max_rate_times_dt():
    jm = parse_joint_map(_permuted_doc(), WALKER)
    prev = np.zeros(6)
    out = jm.rate_limit(np.array([5.0, -5.0, 0.01, 0.0, 1.0, -1.0]), prev, 0.1)
    assert np.allclose(out, [0.2, -0.2, 0.01, 0.0, 0.2, -0.2])
    assert np.array_equal(jm.rate_limit(np.ones(6), None, 0.1), np.ones(6))   # nothing to limit from


@pytest.mark.parametrize("change,match", [
    (lambda d: d["joints"][0].update(action="left_wrist"), "not one of the policy's actions"),
    (lambda d: d["joints"].pop(), "5 joint\\(s\\) for the policy's 6 actions"),
    (lambda d: d["joints"][1].update(action=d["joints"][0]["action"]), "drives two joints"),
    (lambda d: d["joints"][1].update(name="joint_0"), "named twice"),
    (lambda d: d["joints"][2].update(scale=0), "scale is 0"),
    (lambda d: d["joints"][2].update(offset="up"), "offset must be a finite number"),
    (lambda d: d["joints"][2].update(max_rate=-1.0), "max_rate must be above 0"),
    (lambda d: d["joints"][2].update(gain=3), "unknown key"),
    (lambda d: d.pop("joints"), "non-empty list `joints`"),
])
def test_a_map_that_does_not_fit_is_one_line_naming_what(change, match):
    doc = _permuted_doc()
    change(doc)
    with pytest.raises(JointMapError, match=match) as err:
        parse_joint_map(doc, WALKER, "joint map arm.yaml")
    assert "\n" not in str(err.value) and str(err.value).startswith("joint map arm.yaml")


def test_an_unreadable_or_non_yaml_file_is_a_joint_map_error(tmp_path):
    with pytest.raises(JointMapError, match="No such file"):
        load_joint_map(tmp_path / "missing.yaml", WALKER)
    bad = tmp_path / "bad.yaml"
    bad.write_text("joints: [unclosed")
    with pytest.raises(JointMapError, match="not YAML"):
        load_joint_map(bad, WALKER)
