"""MkDocs hooks for ocpkit's site: the API reference reads ocpkit's sources as installed, the tutorials include the
scripts of examples/, and the command-line reference is written from the argparse parser at build time (never
copied by hand)."""

from __future__ import annotations

import argparse
import atexit
import importlib.util
import re
import shutil
import tempfile
from pathlib import Path

import griffe
from mkdocs.plugins import event_priority

CLI_MARKER = "<!-- ocpkit-cli -->"
# ocpkit.problems, ocpkit.solvers and ocpkit.studies live in their own top-level folders of the checkout
# (setuptools package-dir): one tree that holds them under ocpkit/ lets mkdocstrings find them statically.
SUBPACKAGES = ("problems", "solvers", "studies")
# A Sphinx cross-reference in a docstring, :class:`~ocpkit.x.Name` or :func:`text <target>` (mkdocstrings reads
# Markdown: it would show the role's markup).
SPHINX_ROLE = re.compile(r":(?:py:)?(?:class|func|meth|attr|mod|data|exc|obj|const):`(~?)([^`<]+?)(?:\s*<[^>]+>)?`")


class SphinxRoles(griffe.Extension):
    """Docstrings' Sphinx roles as code spans: ``:class:`~a.B``` as ```B```, ``:mod:`a.b``` as ```a.b```."""

    def on_object(self, *, obj, **kwargs):
        if obj.docstring is not None:
            obj.docstring.value = SPHINX_ROLE.sub(_code_span, obj.docstring.value)


def _code_span(match) -> str:
    tilde, target = match.groups()
    return f"`{target.rsplit('.', 1)[-1] if tilde else target}`"


def _source_tree() -> Path:
    """A temporary ``ocpkit/`` of links to the installed package's files and its mapped subpackages."""
    root = Path(tempfile.mkdtemp(prefix="ocpkit-docs-"))
    atexit.register(shutil.rmtree, root, ignore_errors=True)
    tree = root / "ocpkit"
    tree.mkdir()
    package = Path(importlib.util.find_spec("ocpkit").submodule_search_locations[0])
    for entry in package.iterdir():
        if entry.name not in SUBPACKAGES and entry.name != "__pycache__":
            (tree / entry.name).symlink_to(entry)
    for name in SUBPACKAGES:
        (tree / name).symlink_to(Path(importlib.util.find_spec(f"ocpkit.{name}").submodule_search_locations[0]))
    return root


@event_priority(100)  # before mkdocstrings reads its handlers' configuration
def on_config(config):
    python = config["plugins"]["mkdocstrings"].config["handlers"].setdefault("python", {})
    python["paths"] = [str(_source_tree())]
    python.setdefault("options", {})["extensions"] = [f"{__file__}:SphinxRoles"]
    # the tutorials include examples/*.py wherever mkdocs is run from
    config["mdx_configs"]["pymdownx.snippets"]["base_path"] = [
        str(Path(config["config_file_path"]).parent / "examples")
    ]
    return config


def on_page_markdown(markdown, page, config, files):
    if CLI_MARKER not in markdown:
        return markdown
    from ocpkit.cli import _parser

    return markdown.replace(CLI_MARKER, cli_reference(_parser()))


def _subcommands(parser):
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {choice.dest: choice.help for choice in action._choices_actions}
            return [(name, sub, helps.get(name, "")) for name, sub in action.choices.items()]
    return []


def _escape(text: str) -> str:
    return text.replace("|", "\\|").replace("<", "&lt;").replace(">", "&gt;")


def _option_row(parser, action) -> str:
    names = ", ".join(f"`{s}`" for s in action.option_strings) or f"`{action.metavar or action.dest}`"
    if action.option_strings and action.nargs != 0:
        names += f" `{action.metavar or action.dest.upper()}`"
    parts = [parser._get_formatter()._expand_help(action) if action.help else ""]
    if action.choices is not None and not isinstance(action.choices, dict):
        parts.append("one of " + ", ".join(f"`{c}`" for c in action.choices))
    if action.default not in (None, False, argparse.SUPPRESS) and action.nargs != 0:
        parts.append(f"default `{action.default}`")
    return f"| {names} | {_escape('; '.join(p for p in parts if p))} |"


def cli_reference(parser) -> str:
    """Markdown for ``ocpkit`` and each subcommand: usage, description and a table of its arguments."""
    out = [f"```\n{parser.format_usage().strip()}\n```", ""]
    for name, sub, summary in _subcommands(parser):
        out += [f"## ocpkit {name}", "", _escape(summary or ""), "", f"```\n{sub.format_usage().strip()}\n```", ""]
        rows = [_option_row(sub, a) for a in sub._actions if not isinstance(a, argparse._HelpAction)]
        if rows:
            out += ["| argument | meaning |", "|---|---|", *rows, ""]
    return "\n".join(out)
