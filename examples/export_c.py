"""Tutorial "Export to C and call it from a C program": export the pendulum's MPC step, build its library, compile
``pendulum_loop.c`` against it and run it; then load the same library back into Python as a Controller and check
that both give the same first input. ``python export_c.py [OUT_DIR]`` (OUT_DIR must be new or empty)."""

import subprocess
import sys
from pathlib import Path

from ocpkit import make
from ocpkit.export import ExportedMPC, export
from ocpkit.export.build import build

out = Path(sys.argv[1] if len(sys.argv) > 1 else "pendulum_c").resolve()
problem = make("pendulum")
ocp = problem.ocp(knots=5)  # T = 50 steps of 10 ms, 5 knots
x0, goal = problem.sample(seed=2)  # a start whose first input is inside the bounds
exported = export(ocp, out, x0=x0, goal=goal)  # mpc.h, mpc.c, mpc_casadi.c, Makefile, main.c, README.md
build(out)  # `make lib` in the folder: libmpc.so

# Your own C program, compiled against the header and the library
source = Path(__file__).with_name("pendulum_loop.c")
program = out / "pendulum_loop"
compile_flags = ["-std=c99", "-O2", f"-I{out}", f"-L{out}", f"-Wl,-rpath,{out}"]
subprocess.run(["cc", *compile_flags, str(source), "-lmpc", "-lm", "-o", str(program)], check=True)
run = subprocess.run([str(program), str(x0[0]), str(x0[1]), str(goal[0])], capture_output=True, text=True)
print(run.stdout, end="")

# The same library as a Controller in Python (it refuses a library exported for another OCP)
with ExportedMPC(ocp, out) as controller:
    u0 = controller.solve(x0, goal).u
print(f"Python u0 {u0[0]:.6f} (exported {exported.nx} states, {exported.nu} input, {exported.knots} knots)")
