"""A body's joints in the scene's Pinocchio model, found by the names a scene gives them ("<body>/<joint>",
bodies.py): the one lookup of [[drives]] (drive.py), [[actuators]] (actuation.py) and MJCF actuators
(mjcf_actuators.py)."""

from __future__ import annotations


def find_joint(pm, body: str, joint: str) -> int | None:
    """The id in pm of `joint` of `body`, or None where the body has no joint of that name."""
    full = f"{body}/{joint}"
    return pm.getJointId(full) if pm.existJointName(full) else None


def one_dof(pm, j: int) -> bool:
    """Joint j of pm is a 1-dof revolute or prismatic joint (one q, one u)."""
    return pm.joints[j].nq == 1 and pm.joints[j].nv == 1
