"""Golden test of the exported folder: the files ocpkit renders from its templates (``mpc.c``, ``mpc.h``, ``main.c``,
``Makefile``, ``README.md``) equal the stored ones for nlink:3, nlink:13, puma560, the Panda (a URDF arm) and two
variants (the real-time iteration; the Panda with reach's task terms). Text compares exactly; the numbers in it to
1e-12 relative (a constant computed through BLAS may round differently on another CPU), and the CasADi folder the
Makefile names is the installed one. CasADi's own ``mpc_casadi.c`` depends on its version and is not compared, nor
are the hashes of the OCP's digest (``mpc_ocp_digest``: the model's is of its CasADi serialization) and the CasADi
version there; tests/test_export.py checks what the digest tells apart.

After an intended change, ``OCPKIT_UPDATE_GOLDEN=1 pytest tests/test_export_golden.py`` rewrites the stored files;
review their diff before committing it. The stored files are named ``<file>.golden`` (data, not sources)."""

import os
import re
from pathlib import Path

import numpy as np
import pytest

from ocpkit.export import export
from ocpkit.problems import make
from ocpkit.model.task import reach

GOLDEN = Path(__file__).parent / "golden" / "export"
RENDERED = ("mpc.c", "mpc.h", "main.c", "Makefile", "README.md")
CASES = {
    "nlink3": ("nlink:3", False, {}),
    "nlink13": ("nlink:13", False, {}),
    "puma560": ("puma560", False, {}),
    "puma560_rti": ("puma560", False, {"linearization": "trajectory", "iterations": 2, "tol": 1e-6}),
    "panda": ("panda", False, {}),
    "panda_reach": ("panda", True, {}),
}
NUMBER = re.compile(r"(?<![\w.])-?\d+\.\d*(?:e[-+]?\d+)?|(?<![\w.])-?\d+e[-+]?\d+")
CASADI_DIR = re.compile(r"^CASADI_DIR \?= .*$", re.M)
DIGEST = re.compile(r'^(\s+"\w+ (?:\w+:)?)[0-9a-f]{16}(?=(?:; )?";?$)', re.M)
CASADI_VERSION = re.compile(r'^(\s+"casadi )[^;"]*', re.M)


def _masked(text: str) -> str:
    """``text`` with the installed CasADi's folder and version and the digest's hashes replaced by placeholders."""
    text = CASADI_DIR.sub("CASADI_DIR ?= <casadi>", text)
    return CASADI_VERSION.sub(r"\1<version>", DIGEST.sub(r"\1<hash>", text))


def _split(text: str) -> tuple[str, np.ndarray]:
    """(text with every decimal number replaced by #, the numbers) of a rendered file."""
    text = _masked(text)
    return NUMBER.sub("#", text), np.array([float(v) for v in NUMBER.findall(text)])


@pytest.mark.parametrize("case", list(CASES))
def test_rendered_files_equal_the_stored_ones(case, tmp_path):
    name, task, options = CASES[case]
    problem = make(name)
    ocp = reach(problem, knots=5, compiled=False) if task else problem.ocp(knots=5)
    x0, goal = problem.sample(0)
    out = export(ocp, tmp_path / case, x0=x0, goal=None if task else goal, **options).out_dir
    stored = GOLDEN / case
    if os.environ.get("OCPKIT_UPDATE_GOLDEN"):
        stored.mkdir(parents=True, exist_ok=True)
        for file in RENDERED:
            (stored / f"{file}.golden").write_text(_masked((out / file).read_text()))
    for file in RENDERED:
        text, numbers = _split((out / file).read_text())
        want_text, want_numbers = _split((stored / f"{file}.golden").read_text())
        assert text.splitlines() == want_text.splitlines(), f"{case}/{file} differs from tests/golden/export"
        np.testing.assert_allclose(numbers, want_numbers, rtol=1e-12, atol=0, err_msg=f"{case}/{file}")
