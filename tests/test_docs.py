"""The docs site builds with ``mkdocs build --strict`` (no broken link, anchor, reference or snippet) and holds the
API reference built from the docstrings and the command line's reference built from the argparse parser."""

import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MISSING = [
    name for name in ("mkdocs", "material", "mkdocstrings_handlers.python") if not importlib.util.find_spec(name)
]
pytestmark = pytest.mark.skipif(bool(MISSING), reason='the docs tools are not installed: pip install ".[docs]"')
# the public API's pages: (page under site/reference/api/, the anchor mkdocstrings gives the object)
API = [
    ("controllers", "ocpkit.solvers.qp.LinearMPC"),
    ("controllers", "ocpkit.solvers.nlp.NonlinearMPC"),
    ("controllers", "ocpkit.solvers.empc.EvolutionaryMPC"),
    ("controllers", "ocpkit.solvers.rti.RealTimeIteration"),
    ("controllers", "ocpkit.solvers.cem.CrossEntropyMPC"),
    ("controllers", "ocpkit.solvers.mppi.MPPI"),
    ("simulation", "ocpkit.sim.simulate.simulate"),
    ("export", "ocpkit.export.generate.export"),
    ("export", "ocpkit.export.library.ExportedMPC"),
    ("tasks", "ocpkit.model.reference.Reference"),
    ("tasks", "ocpkit.model.task.Task"),
]


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    out = tmp_path_factory.mktemp("site")
    proc = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(ROOT / "mkdocs.yml"), "-d", str(out)],
        cwd=out,
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "NO_MKDOCS_2_WARNING": "1"},
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "WARNING" not in proc.stderr, proc.stderr
    return out


@pytest.mark.parametrize("page, anchor", API, ids=[a.rsplit(".", 1)[1] for _, a in API])
def test_api_page_documents(site, page, anchor):
    html = (site / "reference" / "api" / page / "index.html").read_text()
    assert f'id="{anchor}"' in html
    body = html.split(f'id="{anchor}"', 1)[1][:4000]
    assert "doc-contents" in body  # its docstring rendered below the heading


def test_cli_reference_is_the_parser(site):
    """Every subcommand and every one of its options is on the command-line page."""
    from ocpkit.cli import _parser

    html = (site / "reference" / "cli" / "index.html").read_text()
    sub = next(a for a in _parser()._actions if a.__class__.__name__ == "_SubParsersAction")
    for name, parser in sub.choices.items():
        assert f'id="ocpkit-{name}"' in html
        section = html.split(f'id="ocpkit-{name}"', 1)[1].split("<h2", 1)[0]
        for action in parser._actions:
            for option in action.option_strings or [action.metavar or action.dest]:
                assert f"<code>{option}</code>" in section or option in ("-h", "--help"), (name, option)


def test_tutorials_include_their_scripts(site):
    """The snippets are resolved: each tutorial shows its example script's code, not the include line."""
    for page in (site / "tutorials").rglob("index.html"):
        html = page.read_text()
        assert "--8&lt;--" not in html and "--8<--" not in html, page
    assert "simulate(arm.plant(), LinearMPC(ocp), x0, goal" in re.sub(
        r"<[^>]+>", "", (site / "tutorials" / "obstacles" / "index.html").read_text()
    )
