"""The README is the landing page (issue 50): at most 150 lines; its example runs as printed and is the docs' first
controller; its two set-up commands are the getting-started page's; its picture is a committed file made by the
command under it (the gallery's script); it says how to build the docs; every file and heading it links to exists."""

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
README = (ROOT / "README.md").read_text()
FENCES = re.findall(r"```(\w*)\n(.*?)```", README, re.S)  # (language, code) of each fenced block


def test_readme_is_a_landing_page():
    assert len(README.splitlines()) <= 150
    assert 'pip install ".[docs]" && mkdocs build --strict' in README and "mkdocs serve" in README


def test_readme_example_runs_as_printed(tmp_path, monkeypatch, capsys):
    """Every Python block of the README runs; the one example is at most 10 lines, printing the closed loop's actual
    cost and the first step's times, and is the getting-started page's script (examples/first_controller.py)."""
    (code,) = [code for language, code in FENCES if language == "python"]
    assert len(code.strip().splitlines()) <= 10
    monkeypatch.chdir(tmp_path)
    exec(compile(code, "README.md", "exec"), {})
    cost, times = capsys.readouterr().out.strip().split(" ", 1)
    assert float(cost) > 0 and set(ast.literal_eval(times)) == {"model", "build", "solve", "total"}
    assert code.strip() in (ROOT / "examples" / "first_controller.py").read_text()


def test_readme_set_up_commands_are_the_docs():
    """The main job (the paper at its quick size) and the tests, word for word as on the getting-started page."""
    setup = [code for _, code in FENCES if code.startswith("python3 -m venv")]
    assert len(setup) == 2, setup
    assert setup[0].strip().endswith("ocpkit reproduce --quick") and setup[1].strip().endswith('".[test]" && pytest')
    started = (DOCS / "getting-started.md").read_text()
    assert all(f"```\n{code}```" in started for code in setup)


def test_readme_picture_is_made_by_the_command_under_it():
    image = re.search(r"!\[[^\]]*\]\(([^)]+)\)", README).group(1)
    assert image.startswith("docs/gallery/") and (ROOT / image).is_file()
    after = README.split(image, 1)[1]
    command = re.search(r"```\n(.*?)```", after, re.S).group(1).replace("\\\n", "").split()
    assert command[:2] == ["ocpkit", "simulate"] and f"--animate {Path(image).name}" in " ".join(command)
    script = (DOCS / "gallery" / "make_gallery.sh").read_text().replace("\\\n", "")
    assert command in [line.split() for line in script.splitlines()]


def _slug(heading: str) -> str:
    """The anchor MkDocs' toc gives a heading."""
    return re.sub(r"[\s-]+", "-", re.sub(r"[^\w\s-]", "", heading.strip().lower()))


def test_readme_links_exist():
    links = re.findall(r"\]\(([^)\s]+)\)", README)
    assert sum(link.startswith("docs/") for link in links) >= 10  # links into the docs
    for link in links:
        if link.startswith("http"):
            continue
        path, _, anchor = link.partition("#")
        assert (ROOT / path).exists(), link
        if anchor:
            headings = re.findall(r"^#+ (.+)$", (ROOT / path).read_text(), re.M)
            assert anchor in map(_slug, headings), link
