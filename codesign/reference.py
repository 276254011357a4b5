"""The reference pages, generated from the code so they cannot fall behind it:
docs/cli-reference.md from the command line (every command, argument and option of the core and
the first-party plugins, with its help and default) and docs/api.md from `codesign.interfaces`
(the four component contracts, their attributes and methods, from their docstrings).
`python -m codesign.reference` rewrites both; a test checks the committed pages are what it writes."""

from __future__ import annotations

import ast
import inspect
from pathlib import Path

import typer.main

from codesign.cli import build_app
from codesign.plugins import create_plugin_manager

FIRST_PARTY = ("basics", "mpm", "designs", "optimizers")
"""The plugins this repository ships (pyproject's entry points); others installed beside them are
left out of the page."""

CLI_HEADER = """# Command line reference

Every command and option, generated from the command line itself by `python -m codesign.reference`
(a test checks this page is current). What the commands are for, with examples: [cli.md](cli.md).
`codesign COMMAND --help` prints the same in a terminal.
"""

API_HEADER = """# The component interfaces

`codesign.interfaces`, generated from its docstrings by `python -m codesign.reference` (a test
checks this page is current). A plugin implements one of the four contracts and registers it with a
config dataclass ([plugins.md](plugins.md)); the runner builds each part as `Factory(config)`.
Methods marked *required* are abstract; the others have the default described.
"""


def cli_reference() -> str:
    """docs/cli-reference.md as Markdown."""
    others = [name for name, _ in create_plugin_manager().list_name_plugin() if name not in FIRST_PARTY]
    root = typer.main.get_command(build_app(create_plugin_manager(others)))
    parts = [CLI_HEADER]
    _describe(root, "codesign", parts)
    return "\n".join(parts)


def api_reference() -> str:
    """docs/api.md as Markdown: the module's docstring, then per class its docstring, attributes
    (with the docstrings written under them) and methods (signature and docstring)."""
    from codesign import interfaces

    tree = ast.parse(inspect.getsource(interfaces))
    parts = [API_HEADER, _paragraphs(ast.get_docstring(tree)) + "\n"]
    for node in (n for n in tree.body if isinstance(n, ast.ClassDef)):
        parts.append(f"## `{node.name}`\n\n{_paragraphs(ast.get_docstring(node) or '')}\n")
        attributes, methods = [], []
        body = node.body
        for i, item in enumerate(body):
            if isinstance(item, ast.AnnAssign):
                following = body[i + 1] if i + 1 < len(body) else None
                doc = (following.value.value if isinstance(following, ast.Expr)
                       and isinstance(following.value, ast.Constant) else "")
                default = "" if item.value is None else f" = {ast.unparse(item.value)}"
                declaration = f"{ast.unparse(item.target)}: {ast.unparse(item.annotation)}{default}"
                attributes.append(_table_row([f"`{declaration}`", " ".join(doc.split())]))
            elif isinstance(item, ast.FunctionDef):
                required = any(ast.unparse(d) == "abstractmethod" for d in item.decorator_list)
                signature = f"{item.name}({ast.unparse(item.args)})" + (
                    f" -> {ast.unparse(item.returns)}" if item.returns else "")
                methods.append(f"### `{signature}`" + (" *required*" if required else "") + "\n\n"
                               + _paragraphs(ast.get_docstring(item) or "") + "\n")
        if attributes:
            parts.append("| attribute | meaning |\n| --- | --- |\n" + "\n".join(attributes) + "\n")
        parts.extend(methods)
    return "\n".join(parts)


PAGES = {"cli-reference.md": cli_reference, "api.md": api_reference}


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
    return _table_row([f"`{declaration}`", " ".join(meaning.split())])


def _table_row(cells: list[str]) -> str:
    """A Markdown table row, the pipes inside its cells escaped."""
    return "| " + " | ".join(cell.replace("|", "\\|") for cell in cells) + " |"


def _paragraphs(text: str) -> str:
    """A docstring's paragraphs, each on one line (click keeps the source's line breaks)."""
    return "\n\n".join(" ".join(block.split()) for block in text.strip().split("\n\n"))


def write(docs: Path = Path(__file__).parents[1] / "docs") -> None:
    """Rewrite the generated pages in `docs`."""
    for name, build in PAGES.items():
        (docs / name).write_text(build(), encoding="utf-8")


if __name__ == "__main__":
    write()
