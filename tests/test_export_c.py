"""The exported step's C checked as C (issue 33, item 2).

- The C that ocpkit writes (``mpc.c``, ``main.c``, with ``mpc.h``) compiles as C99 with
  ``-Wall -Wextra -Wpedantic -Werror``: the LTI step, the RTI step, qrqp, the task's Gauss–Newton terms and its
  obstacles' clearance rows. CasADi's
  generated ``mpc_casadi.c`` and the QP libraries are not held to it (qrqp's runtime has unused parameters).
- The example closed loop runs clean under AddressSanitizer (leaks included) and UndefinedBehaviorSanitizer, and
  under valgrind where it is installed (one small problem in the default run, the others marked slow).
- The step allocates nothing after init with qrqp and OSQP; DAQP's set-up, which CasADi's generated call runs inside
  every step, allocates (16 blocks a step at nlink:3, about 1 µs of a 10 µs step measured here): its count is
  checked so that a change in CasADi's code shows up here and in the README's note.
"""

import os
import re
import shutil
import subprocess
from pathlib import Path

import pytest

from ocpkit.export import export
from ocpkit.problems import make
from ocpkit.model.task import reach

pytestmark = pytest.mark.skipif(
    shutil.which("cc") is None or shutil.which("make") is None, reason="needs a C compiler and make"
)

STRICT = ["-std=c99", "-Wall", "-Wextra", "-Wpedantic", "-Werror", "-fsyntax-only"]
# (problem, task: None or reach's obstacles, export options); the obstacle case starts 1.2 cm from its ball, whose
# rows are in the example's QPs from its first step
CASES = {
    "nlink:3 LTI, DAQP": ("nlink:3", None, {}),
    "puma560 RTI, 2 iterations": ("puma560", None, {"linearization": "trajectory", "iterations": 2}),
    "nlink:3 qrqp": ("nlink:3", None, {"qp": "qrqp"}),
    "nlink:3 osqp": ("nlink:3", None, {"qp": "osqp"}),
    "panda reach terms": ("panda", (), {}),
    "nlink:3 reach past a ball": ("nlink:3", ("0.58,-0.02,0,0.06",), {"linearization": "plan"}),
}
SLOW = pytest.mark.slow
SANITIZED = [
    "nlink:3 LTI, DAQP",
    pytest.param("nlink:3 qrqp", marks=SLOW),
    pytest.param("nlink:3 osqp", marks=SLOW),
    pytest.param("puma560 RTI, 2 iterations", marks=SLOW),
    pytest.param("panda reach terms", marks=SLOW),
    "nlink:3 reach past a ball",
]
SANITIZERS = "-fsanitize=address,undefined -fno-sanitize-recover=all -fno-omit-frame-pointer -g"
WRAPPED = ("malloc", "calloc", "realloc", "free", "mpc_step")


def _export(case: str, out: Path) -> Path:
    name, obstacles, options = CASES[case]
    problem = make(name)
    ocp = problem.ocp(knots=5) if obstacles is None else reach(problem, obstacles, knots=5, compiled=False)
    x0, goal = problem.sample(0)
    return export(ocp, out, x0=x0, goal=goal if obstacles is None else None, steps=30, **options).out_dir


def _make(out: Path, *variables: str) -> None:
    result = subprocess.run(["make", "-s", "-C", str(out), "example", *variables], capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr


@pytest.mark.parametrize("case", list(CASES))
def test_ocpkits_c_compiles_without_a_warning(case, tmp_path):
    out = _export(case, tmp_path / "export")
    for source in ("mpc.c", "main.c"):
        result = subprocess.run(["cc", *STRICT, "-I", str(out), str(out / source)], capture_output=True, text=True)
        assert result.returncode == 0, f"{source} ({case}):\n{result.stderr}"


@pytest.mark.parametrize("case", SANITIZED)
def test_example_runs_clean_under_address_and_undefined_behaviour_sanitizers(case, tmp_path):
    out = _export(case, tmp_path / "export")
    _make(out, "OPT=-O1", "OPT_STEP=-O1", f"CFLAGS=-fPIC {SANITIZERS}")
    env = dict(os.environ, ASAN_OPTIONS="detect_leaks=1:halt_on_error=1", UBSAN_OPTIONS="print_stacktrace=1")
    result = subprocess.run([str(out / "example")], capture_output=True, text=True, env=env, cwd=out)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "runtime error" not in result.stderr and "Sanitizer" not in result.stderr, result.stderr


@SLOW
@pytest.mark.skipif(shutil.which("valgrind") is None, reason="valgrind is not installed")
@pytest.mark.parametrize("case", ["nlink:3 LTI, DAQP", "nlink:3 reach past a ball"])
def test_example_runs_clean_under_valgrind(case, tmp_path):
    """Also no use of uninitialized memory: DAQP leaves the unused obstacle rows (zero) out of its work."""
    out = _export(case, tmp_path / "export")
    _make(out, "CFLAGS=-fPIC -g")
    result = subprocess.run(
        ["valgrind", "--error-exitcode=99", "--leak-check=full", "--errors-for-leak-kinds=all", str(out / "example")],
        capture_output=True,
        text=True,
        cwd=out,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert "ERROR SUMMARY: 0 errors" in result.stderr


@pytest.mark.parametrize("case, per_step", [("nlink:3 qrqp", 0), ("nlink:3 osqp", 0), ("nlink:3 LTI, DAQP", 16)])
def test_step_allocations_after_init(case, per_step, tmp_path):
    """Allocator calls inside ``mpc_step`` (tests/c/alloc_count.c wraps malloc, calloc, realloc, free and the step
    at link time): none with qrqp and OSQP, DAQP's set-up blocks with DAQP."""
    out = _export(case, tmp_path / "export")
    shutil.copy(Path(__file__).parent / "c" / "alloc_count.c", out)
    _make(out, "OBJ=mpc.o mpc_casadi.o alloc_count.o", "CFLAGS=-fPIC -Wl," + ",".join(f"--wrap={s}" for s in WRAPPED))
    result = subprocess.run([str(out / "example")], capture_output=True, text=True, cwd=out)
    assert result.returncode == 0, result.stdout + result.stderr
    counts = dict(re.findall(r"(\w+) (\d+)", result.stderr.splitlines()[-1]))
    steps, allocations, frees = (int(counts[k]) for k in ("steps", "allocations", "frees"))
    assert steps == 31  # the warm-up step and the loop's 30
    assert allocations == frees == per_step * steps, result.stderr


@pytest.mark.parametrize("case", ["nlink:3 LTI, DAQP", "puma560 RTI, 2 iterations", "nlink:3 osqp"])
def test_ocpkits_c_names_its_codes_and_casts_nothing_away(case, tmp_path):
    """Issue 45, item 5: the Γ schedule's operations and the solver's returns by name (from the Python tables), no
    (void) casts of unused variables, no function-like macros (the GEMM and the sensitivities are functions)."""
    from ocpkit.export.constants import GRAM_CODES

    text = (_export(case, tmp_path / "export") / "mpc.c").read_text()
    assert not re.search(r"\(void\) *\w+;", text)
    assert not re.search(r"^\s*#\s*define \w+\(", text, re.M)
    assert "enum { " + ", ".join(f"GRAM_{name} = {code}" for name, code in GRAM_CODES.items()) + " };" in text
    assert not re.search(r"\bcode (==|-) \d", text) and not re.search(r"\brc == -?\d", text)
