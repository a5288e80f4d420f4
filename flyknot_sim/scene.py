"""Composition of the simulated lab's scene: floor, pedestal, xArm 7, fingertip rope.

Two tools, each for what it does well on MuJoCo 4:

* dm_control's PyMJCF composes the rigid part (floor, pedestal, the robot MJCF attached to
  the pedestal's top site with the ``xarm7/`` name scope) and exports XML.
* ``mujoco.MjSpec`` takes that XML and adds the rope (a 1D flex or body chain, see
  :mod:`flyknot_sim.rope`), whose elements PyMJCF's schema does not fully know, then compiles.
  (PyMJCF's ``Physics`` wrapper cannot load MuJoCo 4 flex models, so it is not used.)
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import mujoco
import numpy as np

from flyknot.constants import XARM7_XML
from flyknot.errors import check_positive

os.environ.setdefault("MUJOCO_GL", "disable")  # PyMJCF only builds XML; no rendering here.
from dm_control import mjcf

ROBOT_PREFIX = "xarm7/"


@dataclass(frozen=True)
class SceneParams:
    """Geometry of the lab around the robot.

    Attributes:
        pedestal_height: Height of the robot's base above the floor [m]; high enough that
            the 1.1 m rope hangs clear of the floor with the fingertip above 1.2 m (the
            paper gives z_min only). Its bracket up to 1.31 m, where the initial guess puts
            the base above the demonstration's floor: docs/measuring-sticks.md.
        pedestal_half_width: Half the pedestal's side [m].
        floor_size: Half-extent of the floor plane [m].
    """

    pedestal_height: float = 1.0
    pedestal_half_width: float = 0.15
    floor_size: float = 4.0

    def __post_init__(self) -> None:
        check_positive("pedestal_height", self.pedestal_height)
        check_positive("pedestal_half_width", self.pedestal_half_width)
        check_positive("floor_size", self.floor_size)


def rigid_scene_mjcf(params: SceneParams = SceneParams()) -> mjcf.RootElement:
    """Floor, lights, a pedestal and the xArm 7 on it, composed with PyMJCF."""
    root = mjcf.RootElement(model="flyknot_lab")
    root.visual.headlight.ambient = [0.4, 0.4, 0.4]
    root.asset.add(
        "texture",
        name="grid",
        type="2d",
        builtin="checker",
        width=512,
        height=512,
        rgb1=[0.82, 0.84, 0.86],
        rgb2=[0.72, 0.74, 0.77],
    )
    root.asset.add("material", name="floor", texture="grid", texrepeat=[8, 8])
    # Floor: contype 1 so the rope (conaffinity 1) lands on it.
    root.worldbody.add(
        "geom",
        name="floor",
        type="plane",
        size=[params.floor_size, params.floor_size, 0.1],
        material="floor",
        contype=1,
        conaffinity=1,
    )
    root.worldbody.add("light", name="key", pos=[1.5, -1.5, 3.5], dir=[-0.4, 0.4, -1])
    h = params.pedestal_height
    ped = root.worldbody.add("body", name="pedestal", pos=[0, 0, h / 2])
    ped.add(
        "geom",
        name="pedestal",
        type="box",
        size=[params.pedestal_half_width, params.pedestal_half_width, h / 2],
        rgba=[0.35, 0.36, 0.4, 1],
        contype=1,
        conaffinity=1,
    )
    top = ped.add("site", name="robot_mount", pos=[0, 0, h / 2])
    robot = mjcf.from_path(str(XARM7_XML))
    robot.model = ROBOT_PREFIX.rstrip("/")
    top.attach(robot)
    return root


def robot_base_pose(params: SceneParams = SceneParams()) -> np.ndarray:
    """Robot base pose in the world (= mocap) frame, (x, y, z, qw, qx, qy, qz)."""
    return np.array([0.0, 0.0, params.pedestal_height, 1.0, 0.0, 0.0, 0.0])


def scene_spec(params: SceneParams = SceneParams()) -> mujoco.MjSpec:
    """The rigid scene as an editable ``MjSpec`` (the rope is added by the caller)."""
    xml = rigid_scene_mjcf(params).to_xml_string()
    return mujoco.MjSpec.from_string(xml)
