"""The Franka Emika Panda: a 7-DoF torque-controlled arm under gravity, its two fingers locked (a URDF robot).

The URDF is example-robot-data's ``panda_description`` (upstream franka_ros), meshes removed, in
``problems/data/panda/`` (Apache-2.0). Everything else is :class:`ocpkit.model.problem.URDFRobot`'s: the URDF's damping
and effort limits, gravity compensation of the goal, Q = diag(100 per angle, 1 per rate), R = 1e-3 I, and its
kinematics with the end effector ``panda_hand_tcp`` for task-space targets (:func:`ocpkit.model.task.reach`).
"""

from __future__ import annotations

from importlib import resources

from ocpkit.model.problem import URDFRobot

FINGERS = ("panda_finger_joint1", "panda_finger_joint2")


def urdf_path() -> str:
    """Path of the shipped Panda URDF (arm, hand and fingers)."""
    return str(resources.files("ocpkit.problems").joinpath("data/panda/panda.urdf"))


def _make(arg=None) -> URDFRobot:
    if arg is not None:
        raise ValueError(f"panda takes no argument, got {arg!r}")
    return URDFRobot(urdf_path(), locked_joints=FINGERS, name="panda")


REGISTRY = {"panda": _make}
