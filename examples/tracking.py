"""Tutorial "Follow a moving reference": the 3-link arm's joints on sinusoids, previewed over the horizon or held;
then MPC at 100 Hz with the plant at 1 kHz under a disturbance, u₀ held or followed with the feedback gain K.
``python tracking.py [DURATION]`` (default 2 s)."""

import sys

import numpy as np

from ocpkit import LinearMPC, problems, simulate
from ocpkit.model.reference import Reference

duration = float(sys.argv[1]) if len(sys.argv) > 1 else 2.0
robot = problems.make("nlink:3")
ocp = robot.ocp(knots=5, horizon=30)

# Each joint on a 0.3 rad sinusoid at 0.5 Hz, with its rates: x_ref = [q, q̇]
t = np.linspace(0.0, 4.0, 401)
phase = np.array([0.0, 1.0, 2.0])
reference = Reference(
    t, np.hstack([0.3 * np.sin(np.pi * t[:, None] + phase), 0.3 * np.pi * np.cos(np.pi * t[:, None] + phase)])
)


def rms(errors):
    return float(np.sqrt(np.mean(np.square(errors))))


x0 = reference.at(0.0)
for name, goal in (("the preview", reference), ("g(t) held", reference.without_preview())):
    traj = simulate(robot.plant(), LinearMPC(ocp), x0, goal, duration)
    print(f"{name}: RMS error {rms([np.abs(x - reference.at(s))[:3].max() for s, x in zip(traj.t, traj.x)]):.4f} rad")

# MPC at 100 Hz, the plant at 1 kHz under a 12 Hz disturbance torque the MPC does not know of: hold u₀ for the
# 10 ms, or follow the plan with feedback, u = u_k + K (x − x̂(t)) (x̂ the prediction, linear between stages)
mpc, step = LinearMPC(ocp, gains=True), robot.plant().rk4(0.001, 1)
for feedback in (False, True):
    mpc.reset()
    x, errors = x0.copy(), []
    for k in range(round(duration * 1000)):
        if k % 10 == 0:
            sol, start = mpc.solve(x, reference.window(k * 1e-3, ocp.dt, ocp.horizon)), k
        s = (k - start) * 1e-3 / ocp.dt  # stages since the solve (0 … 1)
        x_hat = sol.x_pred[0] + s * (sol.x_pred[1] - sol.x_pred[0])
        u = sol.u + sol.gains @ (x - x_hat) if feedback else sol.u
        disturbance = 0.5 * np.sin(2 * np.pi * 12 * k * 1e-3 + phase)
        x = np.asarray(step(x, np.clip(u, ocp.u_min, ocp.u_max) + disturbance)).ravel()
        errors.append(np.abs(x - reference.at((k + 1) * 1e-3))[:3].max())
    print(f"1 kHz {'u₀ + K (x − x̂)' if feedback else 'u₀ held'}: RMS error {rms(errors):.4f} rad")
