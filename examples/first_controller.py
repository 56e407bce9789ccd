"""Getting started: LinearMPC on the pendulum, 5 knots over T = 50 steps, in closed loop for one second."""

from ocpkit import LinearMPC, make, simulate  # the public API: OCP, LinearMPC, NonlinearMPC, EvolutionaryMPC, …
from ocpkit.sim.metrics import actual_cost

problem = make("pendulum")  # m l² q̈ + b q̇ + m g l sin q = τ
ocp = problem.ocp(knots=5, error=1.2)  # 5 knots over T = 50 steps; controller's model 20 % heavy
controller = LinearMPC(ocp, form="condensed")  # re-linearized each step, DAQP (dense active set)
x0, goal = problem.sample(seed=0)
traj = simulate(problem.plant(), controller, x0, goal, duration=1.0)
print(actual_cost(traj, ocp), traj.solutions[0].times)
