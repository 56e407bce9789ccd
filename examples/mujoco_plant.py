"""Tutorial "MuJoCo as the plant": the same LinearMPC loop on ocpkit's plant and on MuJoCo (pip install
"ocpkit[mujoco]"), then on MuJoCo with what ocpkit's model leaves out. ``python mujoco_plant.py [DURATION]``."""

import sys

import numpy as np

from ocpkit.problems import make
from ocpkit.sim.mujoco_plant import MuJoCoPlant
from ocpkit.sim.simulate import simulate
from ocpkit.solvers.qp import LinearMPC

duration = float(sys.argv[1]) if len(sys.argv) > 1 else 1.0
pb = make("puma560")
x0, goal = pb.sample(0)
ctrl = LinearMPC(pb.ocp())
ours = simulate(pb.plant(), ctrl, x0, goal, duration)
theirs = simulate(MuJoCoPlant(pb), ctrl, x0, goal, duration)  # the same run to about 1e-12
rough = simulate(MuJoCoPlant(pb, frictionloss=5.0, armature=0.2, floor=-0.5), ctrl, x0, goal, duration)
print(f"ocpkit vs MuJoCo: max |x difference| {np.abs(ours.x - theirs.x).max():.1e}")
print(
    f"final error, max |x - goal|: exact plant {np.abs(ours.x[-1] - goal).max():.3f}, "
    f"with friction, armature and floor {np.abs(rough.x[-1] - goal).max():.3f}"
)
