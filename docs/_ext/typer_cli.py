"""Sphinx directive ``typer-cli``: the reference of a typer (click) command-line app.

Usage in a reStructuredText page::

    .. typer-cli:: derender.cli:app
       :prog: derender

The app is turned into its click command (``typer.main.get_command``) and walked: one
section per command and sub-command with its help text, its usage line and every
argument and option (names, type, default, help), as ``--help`` prints them. Only the
click API is used (``params``, ``get_help_record``, ``list_commands``, ``get_usage``), so it works
with typer's vendored click as well as with click itself; the texts are escaped, so a
help string cannot break the page.
"""

from __future__ import annotations

import importlib
import re

from docutils import nodes
from docutils.parsers.rst import directives
from docutils.statemachine import StringList
from sphinx.util.docutils import SphinxDirective
from sphinx.util.nodes import nested_parse_with_titles

__all__ = ["TyperCliDirective", "setup", "command_rst"]

_UNDERLINES = "-~^\"'"
_SPECIAL = re.compile(r"([\\`*_|\[\]<>:])")


def _escape(text: str) -> str:
    """``text`` as literal reStructuredText inline text."""
    return _SPECIAL.sub(r"\\\1", text)


def _paragraphs(text: str | None) -> list[str]:
    """Help text as escaped paragraphs (blank-line separated, lines joined)."""
    if not text:
        return []
    text = text.split("\f")[0]  # click: text after a form feed is not shown
    paras = [" ".join(line.strip() for line in block.splitlines()) for block in re.split(r"\n\s*\n", text.strip())]
    return [_escape(p) for p in paras if p]


def _param_rst(param, ctx) -> list[str]:
    """A definition-list item for one argument or option: its ``--help`` line, escaped.

    ``get_help_record`` is click's own formatter (typer's adds arguments, the metavar,
    ``[default: ...]`` and ``[required]``); an argument plain click does not describe gets
    its name only.
    """
    if getattr(param, "hidden", False):
        return []
    record = param.get_help_record(ctx)
    if record is None:
        record = (param.human_readable_name, "")
    term, help_text = record
    body = _paragraphs(help_text) or ["\\ "]
    lines = [f"``{term}``"]
    for i, para in enumerate(body):
        if i:
            lines.append("")
        lines.append(f"   {para}")
    lines.append("")
    return lines


def _context(command, name: str, parent):
    """A click context for ``command`` (for its usage line), built without parsing anything."""
    return command.context_class(command, info_name=name, parent=parent)


def command_rst(command, path: list[str], level: int = 0, parent=None) -> list[str]:
    """reStructuredText for ``command`` (called as ``path``) and, recursively, its sub-commands."""
    ctx = _context(command, path[-1], parent)
    title = " ".join(path)
    lines = [title, _UNDERLINES[level] * len(title), ""]
    for para in _paragraphs(command.help):
        lines += [para, ""]
    lines += [".. code-block:: text", "", f"   {command.get_usage(ctx)}", ""]
    arguments = [p for p in command.params if getattr(p, "param_type_name", "") == "argument"]
    options = [p for p in command.params if getattr(p, "param_type_name", "") != "argument"
               and not getattr(p, "hidden", False)]
    for heading, params in (("Arguments", arguments), ("Options", options)):
        if params:
            lines += [f".. rubric:: {heading}", ""]
            for p in params:
                lines += _param_rst(p, ctx)
    sub = getattr(command, "list_commands", None)
    if sub is not None:
        names = sub(ctx)
        if names:
            lines += [".. rubric:: Commands", ""]
            for name in names:
                cmd = command.get_command(ctx, name)
                short = (_paragraphs(cmd.short_help or cmd.help) or [""])[0]
                lines += [f"- :ref:`{' '.join([*path, name])} <{_ref(path + [name])}>` \u2014 {short}"]
            lines.append("")
            for name in names:
                cmd = command.get_command(ctx, name)
                if getattr(cmd, "hidden", False):
                    continue
                lines += [f".. _{_ref(path + [name])}:", ""]
                lines += command_rst(cmd, path + [name], level + 1, ctx)
    return lines


def _ref(path: list[str]) -> str:
    return "cli-" + "-".join(path)


class TyperCliDirective(SphinxDirective):
    """``.. typer-cli:: module:attribute`` with option ``:prog:`` (the program name)."""

    required_arguments = 1
    option_spec = {"prog": directives.unchanged}
    has_content = False

    def run(self) -> list[nodes.Node]:
        module_name, _, attr = self.arguments[0].partition(":")
        app = getattr(importlib.import_module(module_name), attr or "app")
        import typer.main

        command = typer.main.get_command(app)
        prog = self.options.get("prog") or module_name.rsplit(".", 1)[-1]
        text = command_rst(command, [prog])
        node = nodes.section()
        node.document = self.state.document
        nested_parse_with_titles(self.state, StringList(text, source=f"<typer-cli {self.arguments[0]}>"), node)
        return node.children


def setup(app):
    app.add_directive("typer-cli", TyperCliDirective)
    return {"version": "1", "parallel_read_safe": True, "parallel_write_safe": True}
