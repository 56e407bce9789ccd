"""The exported step's C, the part ocpkit writes (``mpc.c``, ``main.c``, ``mpc.h``), compiles as C99 with
``-Wall -Wextra -Wpedantic -Werror`` (issue 33, item 2): the LTI step, the RTI step and the task's Gauss–Newton
terms. CasADi's generated ``mpc_casadi.c`` and the QP libraries are not held to it (qrqp's runtime has unused
parameters)."""
import shutil
import subprocess

import pytest

from ocpkit.export import export
from ocpkit.problems import make
from ocpkit.task import reach

STRICT = ["-std=c99", "-Wall", "-Wextra", "-Wpedantic", "-Werror", "-fsyntax-only"]
CASES = {"nlink:3 LTI, DAQP": ("nlink:3", False, {}),
         "puma560 RTI, 2 iterations": ("puma560", False, {"linearization": "trajectory", "iterations": 2}),
         "nlink:3 qrqp": ("nlink:3", False, {"qp": "qrqp"}),
         "panda reach terms": ("panda", True, {})}


@pytest.mark.skipif(shutil.which("cc") is None, reason="needs a C compiler")
@pytest.mark.parametrize("case", list(CASES))
def test_ocpkits_c_compiles_without_a_warning(case, tmp_path):
    name, task, options = CASES[case]
    problem = make(name)
    ocp = reach(problem, knots=5, compiled=False) if task else problem.ocp(knots=5)
    out = export(ocp, tmp_path / "export", **options).out_dir
    for source in ("mpc.c", "main.c"):
        result = subprocess.run(["cc", *STRICT, "-I", str(out), str(out / source)], capture_output=True, text=True)
        assert result.returncode == 0, f"{source} ({case}):\n{result.stderr}"
