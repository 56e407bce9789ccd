"""Tutorial "Your own robot from a URDF": the Franka Panda's URDF as a torque-controlled problem, fingers locked,
LinearMPC in closed loop. ``python urdf_robot.py [DURATION]`` (default 2 s)."""

import sys

import numpy as np

from ocpkit import LinearMPC, Problem, simulate
from ocpkit.problems.panda import urdf_path  # the shipped Franka Panda URDF

duration = float(sys.argv[1]) if len(sys.argv) > 1 else 2.0
arm = Problem.from_urdf(
    urdf_path(),  # 7 arm joints, 2 prismatic fingers (problem "panda")
    locked_joints=["panda_finger_joint1", "panda_finger_joint2"],
)
x0, goal = arm.sample(seed=0)  # at rest; goal: a step of up to ±0.5 rad per joint
traj = simulate(arm.plant(), LinearMPC(arm.ocp(knots=5)), x0, goal, duration=duration)
print(np.abs(traj.x[-1] - goal)[:7].max())  # final joint error, rad
