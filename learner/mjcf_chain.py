"""The robot's serial chain read from its MJCF file, in numpy (:func:`read_chain`).

Body poses, hinge axes and anchors, lumped inertials, armature, damping and springs of the
chain joints, all constant and expressed in the robot base frame conventions of
:mod:`learner.kinematics`, which builds the CasADi model from them. Nothing from a running
simulation is used.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from flyknot.errors import ConfigError
from flyknot.geometry import quat_to_matrix


@dataclass(frozen=True)
class ChainLink:
    """One moving segment of the chain, all vectors in numpy, constant.

    The segment's body frame after the joint is ``R = R_prev S Rot(axis, q - ref)``,
    ``p = o - R c`` with the anchor ``o = p_prev + R_prev s + R_prev S c``.
    """

    s: np.ndarray  # (3,) position of the joint body before rotation, previous frame [m]
    S: np.ndarray  # (3, 3) orientation of the joint body before rotation, previous frame
    axis: np.ndarray  # (3,) unit hinge axis, joint body frame
    anchor: np.ndarray  # (3,) hinge anchor c, joint body frame [m]
    ref: float  # qpos0 of the joint [rad]
    mass: float  # lumped mass [kg]
    com: np.ndarray  # (3,) lumped centre of mass, joint body frame [m]
    inertia: np.ndarray  # (3, 3) lumped inertia about the com, joint body frame [kg m^2]


def _ancestors(model: mujoco.MjModel, body: int) -> list[int]:
    """Bodies from ``body`` up to (excluding) the world, nearest first."""
    out = []
    while body != 0:
        out.append(body)
        body = int(model.body_parentid[body])
    return out


def _static_pose(model: mujoco.MjModel, top: int, body: int) -> tuple[np.ndarray, np.ndarray]:
    """Pose of ``body`` in the frame of its ancestor ``top`` with joints at ``qpos0``.

    At ``qpos0`` every MuJoCo joint is the identity, so the pose composes ``body_pos`` and
    ``body_quat`` alone: ``p = p_parent + R_parent pos``, ``R = R_parent R(quat)``.

    Returns:
        Position (3,) [m] and rotation (3, 3).
    """
    chain = []
    b = body
    while b != top:
        if b == 0:
            raise ConfigError("mjcf", f"body {body} is not below body {top}")
        chain.append(b)
        b = int(model.body_parentid[b])
    p, R = np.zeros(3), np.eye(3)
    for b in reversed(chain):
        p = p + R @ model.body_pos[b]
        R = R @ quat_to_matrix(model.body_quat[b])
    return p, R


def _has_free_joint(model: mujoco.MjModel, body: int) -> bool:
    start, count = int(model.body_jntadr[body]), int(model.body_jntnum[body])
    return any(model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE for j in range(start, start + count))


def _body_name(model: mujoco.MjModel, body: int) -> str:
    return mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, body) or f"body#{body}"


def read_chain(
    model: mujoco.MjModel, joint_names: tuple[str, ...], site_name: str, base_body: str | None
) -> dict:
    """Extract the serial chain from base to site.

    The joints must be hinges, one per body, forming a serial path from the base body (fixed to
    the world) to the site's body in the listed order (see
    :meth:`learner.kinematics.RobotModel.from_mjcf`). Bodies below a chain body are lumped into
    it rigidly at their reference pose; a free joint below the chain cuts its subtree off.

    Returns:
        ``links`` (one :class:`ChainLink` per joint), the site pose in the last link's frame
        (``site_pos``, ``site_rot``), ``gravity`` in the base frame, the joints' ``armature``,
        ``damping``, ``stiffness``, ``springref`` and ``q_range``, and ``base_name``.

    Raises:
        ConfigError: names or chain structure do not fit.
    """
    jids, sid, base = _chain_ids(model, joint_names, site_name, base_body)
    site_body = int(model.site_bodyid[sid])
    path = _chain_path(model, jids, site_name, site_body, base)
    jbody = [int(model.jnt_bodyid[j]) for j in jids]
    links = _chain_links(model, jids, jbody, base, _lumped_masses(model, path, jbody))
    p_site_body, R_site_body = (
        (np.zeros(3), np.eye(3))
        if site_body == jbody[-1]
        else _static_pose(model, jbody[-1], site_body)
    )
    site_pos = p_site_body + R_site_body @ model.site_pos[sid]
    site_rot = R_site_body @ quat_to_matrix(model.site_quat[sid])
    _, R_wb = _static_pose(model, 0, base) if base != 0 else (None, np.eye(3))
    dofs = [int(model.jnt_dofadr[j]) for j in jids]
    return {
        "links": links,
        "site_pos": site_pos,
        "site_rot": site_rot,
        "gravity": R_wb.T @ np.asarray(model.opt.gravity, dtype=float),
        "armature": np.array([model.dof_armature[d] for d in dofs]),
        "damping": np.array([model.dof_damping[d] for d in dofs]),
        "stiffness": np.array([model.jnt_stiffness[j] for j in jids]),
        "springref": np.array([model.qpos_spring[model.jnt_qposadr[j]] for j in jids]),
        "base_name": _body_name(model, base) if base != 0 else "world",
        "q_range": np.array([model.jnt_range[j] for j in jids]),
    }


def _chain_ids(
    model: mujoco.MjModel, joint_names: tuple[str, ...], site_name: str, base_body: str | None
) -> tuple[list[int], int, int]:
    """The listed hinges' ids, the site's id and the base body's id (default: the first
    joint's body's parent), checked: every name exists, every joint is a hinge, the base is
    welded to the world (so that gravity has a fixed direction in it)."""
    jids = []
    for name in joint_names:
        j = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
        if j < 0:
            all_joints = [
                mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, i) for i in range(model.njnt)
            ]
            raise ConfigError("joint_names", f"joint {name!r} not in the MJCF", all_joints)
        if model.jnt_type[j] != mujoco.mjtJoint.mjJNT_HINGE:
            raise ConfigError("joint_names", f"joint {name!r} is not a hinge")
        jids.append(j)
    sid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, site_name)
    if sid < 0:
        sites = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_SITE, i) for i in range(model.nsite)]
        raise ConfigError("site", f"site {site_name!r} not in the MJCF", sites)
    if base_body is None:
        base = int(model.body_parentid[int(model.jnt_bodyid[jids[0]])])
    else:
        base = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, base_body)
        if base < 0:
            bodies = [_body_name(model, i) for i in range(model.nbody)]
            raise ConfigError("base_body", f"body {base_body!r} not in the MJCF", bodies)
    for b in [*_ancestors(model, base)]:
        if model.body_jntnum[b] > 0:
            raise ConfigError("base_body", f"{_body_name(model, base)!r} is not fixed to the world")
    return jids, sid, base


def _chain_path(
    model: mujoco.MjModel, jids: list[int], site_name: str, site_body: int, base: int
) -> list[int]:
    """The bodies from below the base down to the site's body, checked: the joints along
    them are exactly ``jids``, in order, at most one per body."""
    path = list(reversed(_ancestors(model, site_body)))  # world child ... site body
    if base != 0:
        if base not in path:
            raise ConfigError(
                "site", f"site {site_name!r} is not below {_body_name(model, base)!r}"
            )
        path = path[path.index(base) + 1 :]
    seen = []
    for b in path:
        nj = int(model.body_jntnum[b])
        ids = list(range(model.body_jntadr[b], model.body_jntadr[b] + nj))
        for j in ids:
            if j not in jids:
                name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j)
                raise ConfigError(
                    "joint_names", f"joint {name!r} lies on the chain but is not listed"
                )
        if nj > 1:
            raise ConfigError("mjcf", f"body {_body_name(model, b)!r} has {nj} joints (need <= 1)")
        seen.extend(ids)
    if seen != jids:
        raise ConfigError(
            "joint_names",
            "must list the hinges from base to site in chain order; the chain has "
            + ", ".join(repr(mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j)) for j in seen),
        )
    return path


_Mass = tuple[float, np.ndarray, np.ndarray]
"""A body lumped into a link: mass [kg], centre of mass (3,) [m] and inertia about it (3, 3)
[kg m^2], both in the link's joint body's frame."""


def _lumped_masses(model: mujoco.MjModel, path: list[int], jbody: list[int]) -> list[list[_Mass]]:
    """Every body below the base, lumped into the link of its nearest ancestor on ``path``
    (the last chain joint at or above it) at its reference pose; bodies fixed to the base
    and the subtrees below a free joint are left out."""
    seg_of_path = {}
    k = -1
    for b in path:
        if model.body_jntnum[b] == 1:
            k += 1
        seg_of_path[b] = k
    masses: list[list[_Mass]] = [[] for _ in jbody]
    for b in range(1, model.nbody):
        anc = _ancestors(model, b)
        on_path = next((a for a in anc if a in seg_of_path), None)
        if on_path is None or seg_of_path[on_path] < 0:
            continue
        between = anc[: anc.index(on_path)]  # b and its ancestors below the path body
        if any(_has_free_joint(model, a) for a in between):
            continue  # a free body is not carried by the arm
        k = seg_of_path[on_path]
        p, R = _static_pose(model, jbody[k], b) if b != jbody[k] else (np.zeros(3), np.eye(3))
        Ri = R @ quat_to_matrix(model.body_iquat[b])
        masses[k].append(
            (
                float(model.body_mass[b]),
                p + R @ model.body_ipos[b],
                Ri @ np.diag(model.body_inertia[b]) @ Ri.T,
            )
        )
    return masses


def _chain_links(
    model: mujoco.MjModel,
    jids: list[int],
    jbody: list[int],
    base: int,
    masses: list[list[_Mass]],
) -> list[ChainLink]:
    """One :class:`ChainLink` per joint: its body's pose in the previous joint's body (the
    base for the first), the joint's axis, anchor and reference angle, and the link's lumped
    mass, centre of mass and inertia about it (parallel-axis sum)."""
    links = []
    prev = base
    for k, (j, b) in enumerate(zip(jids, jbody, strict=True)):
        parent = int(model.body_parentid[b])
        p_par, R_par = (
            (np.zeros(3), np.eye(3)) if parent == prev else _static_pose(model, prev, parent)
        )
        s = p_par + R_par @ model.body_pos[b]
        S = R_par @ quat_to_matrix(model.body_quat[b])
        m_tot = sum(m for m, _, _ in masses[k])
        if m_tot > 0:
            com = sum(m * c for m, c, _ in masses[k]) / m_tot
            inertia = sum(
                inertia_b + m * (np.dot(c - com, c - com) * np.eye(3) - np.outer(c - com, c - com))
                for m, c, inertia_b in masses[k]
            )
        else:
            com, inertia = np.zeros(3), np.zeros((3, 3))
        axis = np.asarray(model.jnt_axis[j], dtype=float)
        links.append(
            ChainLink(
                s=s,
                S=S,
                axis=axis / np.linalg.norm(axis),
                anchor=np.array(model.jnt_pos[j], dtype=float),
                ref=float(model.qpos0[model.jnt_qposadr[j]]),
                mass=float(m_tot),
                com=com,
                inertia=np.asarray(inertia, dtype=float),
            )
        )
        prev = b
    return links


__all__ = ["ChainLink", "read_chain"]
