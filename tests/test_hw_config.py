"""The lab file: parsed into frozen, validated dataclasses; every error names its field."""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest

from flyknot.constants import ASSETS_DIR
from flyknot.errors import ConfigError, FlyknotError
from flyknot_hw.config import (
    LabConfig,
    Margins,
    RobotConfig,
    Workspace,
    load_lab_config,
    parse_lab_config,
)

EXAMPLE = ASSETS_DIR / "lab_example.toml"

GOOD = {
    "robot": {"address": "192.168.1.185"},
    "mocap": {"kind": "live", "system": "vicon", "address": "192.168.1.20:801"},
    "rope": {"id": 3},
    "base": {"pose": [0.5, 0.0, 0.8, 1.0, 0.0, 0.0, 0.0]},
    "safety": {"margin": 0.05, "workspace": {"min": [-0.8, -0.8, -0.3], "max": [0.8, 0.8, 1.2]}},
}


def _doc(**changes):
    """GOOD with ``section__key=value`` changes (value None deletes the key)."""
    doc = copy.deepcopy(GOOD)
    for path, value in changes.items():
        *parents, key = path.split("__")
        table = doc
        for p in parents:
            table = table.setdefault(p, {})
        if value is None:
            table.pop(key, None)
        else:
            table[key] = value
    return doc


def test_example_lab_file_parses_and_is_documented():
    cfg = load_lab_config(EXAMPLE)
    assert isinstance(cfg, LabConfig)
    assert cfg.robot.port == 502 and cfg.robot.report_port == 30000
    assert cfg.robot.servo_rate_hz == 250.0
    assert cfg.mocap.kind in ("live", "file")
    assert cfg.base_pose.shape == (7,)
    assert cfg.source == str(EXAMPLE)
    text = EXAMPLE.read_text()
    fields = [f.name for f in dataclasses.fields(RobotConfig)]
    fields += ["kind", "system", "marker_set", "pose", "margin", "workspace", "mode", "after_s"]
    for name in fields:
        assert f"{name} =" in text or f"{name}]" in text, f"{name} is not documented"


def test_defaults_and_normalised_quaternion():
    with pytest.raises(ConfigError, match=r"base\.pose: quaternion"):
        parse_lab_config(_doc(base__pose=[0, 0, 1, 2.0, 0, 0, 0.0]))
    cfg = parse_lab_config(_doc(base__pose=[0, 0, 1, 0.7072, 0, 0, 0.7071]))
    assert np.isclose(np.linalg.norm(cfg.base_pose[3:]), 1.0)
    assert cfg.robot.joint_source == "auto"
    assert cfg.settle.mode == "seconds"
    assert cfg.safety.margins == Margins(0.05, 0.05, 0.05, 0.05)
    assert cfg.rope.key == 3


def test_margin_table_and_allowed_use():
    cfg = parse_lab_config(_doc(safety__margin={"position": 0.02, "torque": 0.1}))
    m = cfg.safety.margins
    assert (m.position, m.velocity, m.torque) == (0.02, 0.05, 0.1)
    assert m.allowed("torque") == pytest.approx(0.9)
    with pytest.raises(ConfigError, match="valid choices: position"):
        m.allowed("jerk")


def test_dataclasses_are_frozen():
    cfg = parse_lab_config(GOOD)
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.robot.address = "10.0.0.1"  # type: ignore[misc]
    with pytest.raises(ValueError):
        cfg.base_pose[0] = 1.0


@pytest.mark.parametrize(
    ("changes", "field", "extra"),
    [
        ({"robot__address": "xarm.local"}, "robot.address", "IPv4"),
        ({"robot__address": None}, "robot.address", "required"),
        ({"robot__port": 70000}, "robot.port", "1..65535"),
        ({"robot__report_port": 502}, "robot.report_port", "differ"),
        ({"robot__start_speed": 2.0}, "robot.start_speed", "at most 1.0"),
        ({"robot__start_acc": -1}, "robot.start_acc", "> 0"),
        ({"robot__servo_rate_hz": 0}, "robot.servo_rate_hz", "> 0"),
        ({"robot__joint_source": "udp"}, "robot.joint_source", "valid choices: auto, report"),
        ({"robot__adress": "1.2.3.4"}, "robot.adress", "valid choices: address"),
        ({"mocap__kind": "stream"}, "mocap.kind", "valid choices: live, file"),
        ({"mocap__address": None}, "mocap.address", "required"),
        ({"mocap__kind": "file"}, "mocap.file", "required"),
        ({"mocap__system": ""}, "mocap.system", "non-empty"),
        ({"rope__name": "climbing cord"}, "rope", "exactly one"),
        ({"rope__id": 9}, "rope.id", "valid choices: 1"),
        ({"rope__id": True}, "rope.id", "valid choices"),
        ({"base__pose": [0, 0, 1, 1, 0, 0]}, "base.pose", "7 numbers"),
        ({"base__pose": [0, 0, "up", 1, 0, 0, 0]}, "base.pose[2]", "finite number"),
        ({"base__pose": None}, "base.pose", "required"),
        ({"safety__margin": 1.5}, "safety.margin.position", "[0, 1)"),
        ({"safety__margin": {"speed": 0.1}}, "safety.margin.speed", "valid choices: position"),
        ({"safety__workspace__max": [0.8, -0.9, 1.2]}, "safety.workspace.max", "y has"),
        ({"safety__workspace__min": None}, "safety.workspace.min", "required"),
        ({"safety__workspace": None}, "safety.workspace", "missing"),
        ({"settle__mode": "wait"}, "settle.mode", "valid choices: seconds, markers"),
        ({"settle__after_s": -1}, "settle.after_s", ">= 0"),
        ({"robots": {}}, "robots", "valid choices: robot, mocap"),
    ],
)
def test_errors_name_the_field(changes, field, extra):
    with pytest.raises(ConfigError) as e:
        parse_lab_config(_doc(**changes))
    msg = str(e.value)
    assert msg.startswith(f"{field}:"), msg
    assert extra in msg, msg
    assert isinstance(e.value, FlyknotError)


def test_workspace_equality_and_shape():
    a = Workspace([-1, -1, 0], [1, 1, 2])
    assert a == Workspace(np.array([-1, -1, 0]), np.array([1, 1, 2]))
    assert a.lo.dtype == float
    with pytest.raises(ConfigError, match=r"safety\.workspace\.min: must be a list of 3"):
        Workspace([0, 0], [1, 1, 1])


def test_load_errors(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        load_lab_config(tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[robot\naddress = 1")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_lab_config(bad)
