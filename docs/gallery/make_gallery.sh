#!/usr/bin/env bash
# The gallery's pictures, each made by the command beside it in gallery.md (run from this folder: bash make_gallery.sh).
set -euo pipefail
cd "$(dirname "$0")"
ocpkit simulate pendulum --out pendulum.png --animate pendulum.gif
ocpkit simulate pendulum --seed 1 --duration 2 --animate pendulum_swing_up.gif
ocpkit simulate nlink:3 --target 0.3,0.5,0 --obstacle 0.55,0.2,0,0.08 --duration 2 --animate nlink3_reach.gif
ocpkit simulate panda --target 0.4,0,0.3 --obstacle 0.4,-0.25,0.35,0.08 --duration 2 --out panda_reach.png \
  --animate panda_reach.gif
ocpkit simulate baxter --duration 2 --animate baxter.gif
# the tracking tutorial's reference: each joint on a 0.3 rad sinusoid at 0.5 Hz, with its rates
python -c "import numpy as np; t = np.linspace(0, 4, 401)[:, None]; p = np.array([0.0, 1.0, 2.0]); \
np.savetxt('nlink3_sinusoids.csv', np.hstack([t, 0.3 * np.sin(np.pi * t + p), 0.3 * np.pi * np.cos(np.pi * t + p)]), \
delimiter=',', header='t,q1,q2,q3,qd1,qd2,qd3', comments='')"
ocpkit simulate nlink:3 --reference nlink3_sinusoids.csv --duration 4 --animate nlink3_tracking.gif
rm nlink3_sinusoids.csv
ocpkit demo --out demo
# a study's figure: the robustness study on the cart-pole of examples/cartpole.py (its results stay in a temp folder)
study=$(mktemp -d)
ocpkit study robustness --problem ../../examples/cartpole.py:CartPole --size quick --out "$study"
cp "$study"/robustness_*.png robustness_cartpole.png
rm -r "$study"
