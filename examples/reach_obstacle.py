"""Tutorial "Reach around obstacles": the Panda's hand to a point past a ball in the way of the straight path.
``python reach_obstacle.py [DURATION]`` (default 2 s)."""

import sys

import numpy as np

from ocpkit import problems
from ocpkit.model.task import Sphere, reach
from ocpkit.sim.simulate import simulate
from ocpkit.solvers.qp import LinearMPC

duration = float(sys.argv[1]) if len(sys.argv) > 1 else 2.0
arm = problems.make("panda")  # Problem.from_urdf(path, locked_joints=...) for yours
ball = Sphere(center=(0.4, -0.25, 0.35), radius=0.08)  # m, world frame
target = np.array([0.4, 0.0, 0.3])  # for arm.end_effector, "panda_hand_tcp"
ocp = reach(arm, [ball], knots=5)  # other keywords as problem.ocp's
x0, _ = arm.sample(seed=0)  # at rest, the hand at (0.36, -0.46, 0.36)
goal = ocp.goal(x0, position=target)  # joint velocities to zero, the hand to target
traj = simulate(arm.plant(), LinearMPC(ocp), x0, goal, duration=duration)

progress = traj.progress(arm.kinematics, arm.end_effector, target)  # the loop's verdict and the hand's distance
clearance = traj.clearances(ocp).min()  # m between robot and obstacle spheres; < 0: a collision
print(f"{progress.verdict}: final distance {progress.final:.4f} m, min clearance {clearance:.4f} m")
