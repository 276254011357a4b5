"""docs/cli-reference.md, generated from the command line itself: every command, argument and
option of the core and the first-party plugins, with its help and default, so the reference cannot
fall behind the code. `python -m codesign.clidoc > docs/cli-reference.md` rewrites it; a test checks
that the committed page is what this prints."""

from __future__ import annotations

import typer.main

from codesign.cli import build_app
from codesign.plugins import create_plugin_manager

FIRST_PARTY = ("basics", "mpm", "designs", "optimizers")
"""The plugins this repository ships (pyproject's entry points); others installed beside them are
left out of the page."""

HEADER = """# Command line reference

Every command and option, generated from the command line itself by `python -m codesign.clidoc >
docs/cli-reference.md` (a test checks this page is current). What the commands are for, with
examples: [cli.md](cli.md). `codesign COMMAND --help` prints the same in a terminal.
"""


def reference() -> str:
    """The reference page as Markdown."""
    others = [name for name, _ in create_plugin_manager().list_name_plugin() if name not in FIRST_PARTY]
    root = typer.main.get_command(build_app(create_plugin_manager(others)))
    parts = [HEADER]
    _describe(root, "codesign", parts)
    return "\n".join(parts)


def _describe(command, path: str, parts: list[str], parent=None) -> None:
    from typer import _click as click  # the click that typer carries

    ctx = click.Context(command, info_name=path.split()[-1], parent=parent)
    if parent is not None:
        parts.append(f"## `{path}`\n")
        if command.help:
            parts.append(_paragraphs(command.help) + "\n")
    parts.append(f"```\n{path} {' '.join(command.collect_usage_pieces(ctx))}\n```\n")
    rows = [_row(param, ctx) for param in command.params if not getattr(param, "hidden", False)]
    if rows:
        parts.append("| argument or option | meaning |\n| --- | --- |")
        parts.extend(rows)
        parts.append("")
    for name in getattr(command, "list_commands", lambda _: [])(ctx):
        _describe(command.get_command(ctx, name), f"{path} {name}", parts, ctx)


def _row(param, ctx) -> str:
    """A table row: the argument's or option's declaration, and its help with typer's [default: ...]
    and [required]."""
    declaration, meaning = param.get_help_record(ctx) or (param.name, "")
    cells = [f"`{declaration}`", " ".join(meaning.split())]
    return "| " + " | ".join(cell.replace("|", "\\|") for cell in cells) + " |"


def _paragraphs(text: str) -> str:
    """A docstring's paragraphs, each on one line (click keeps the source's line breaks)."""
    return "\n\n".join(" ".join(block.split()) for block in text.strip().split("\n\n"))


if __name__ == "__main__":
    print(reference(), end="")
