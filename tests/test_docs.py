"""The documents name only what exists, and the README's test command is the one CI runs."""

import functools
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).parents[1]
PAGES = [ROOT / "README.md", ROOT / "CHANGELOG.md", *sorted((ROOT / "docs").rglob("*.md"))]


def _fenced(text: str, after: str) -> str:
    """The first fenced block after the heading `after`."""
    return re.search(r"```\w*\n(.*?)```", text[text.index(after):], re.S).group(1).strip()


def test_ci_runs_the_readmes_test_command():
    command = _fenced((ROOT / "README.md").read_text(encoding="utf-8"), "## Tests")
    assert command.startswith("python3 -m venv") and command.endswith("python -m pytest -q")
    assert command in (ROOT / ".ci" / "run").read_text(encoding="utf-8").splitlines()


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_link_and_named_file_of_a_page_exists(page):
    text = page.read_text(encoding="utf-8")
    missing = []
    for target in re.findall(r"\]\(([^)\s]+)\)", text):  # Markdown links
        path = target.split("#")[0]
        if path and not re.match(r"[a-z]+:", path) and not (page.parent / path).exists():
            missing.append(target)
    for named in re.findall(r"`((?:recipes|benchmarks|docs|plugins|codesign|tests)/[\w./-]+\.(?:yaml|py|md|jsonl|json))",
                            text):  # a repository file named in code
        if not (ROOT / named).exists():
            missing.append(named)
    assert not missing, f"{page.relative_to(ROOT)} names files that do not exist: {missing}"


USER_PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]  # the dated logs keep their history


@functools.cache
def _commands() -> dict[str, set[str]]:
    """Every `codesign` command, with the subcommands of a group (built once for every page)."""
    import click
    import typer

    from codesign.cli import build_app
    from codesign.plugins import load_plugins

    root = typer.main.get_command(build_app(load_plugins()))
    ctx = click.Context(root)
    commands = {}
    for name in root.list_commands(ctx):
        command = root.get_command(ctx, name)
        commands[name] = set(command.list_commands(ctx)) if isinstance(command, click.Group) else set()
    return commands


@pytest.mark.parametrize("page", USER_PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_command_a_page_names_exists(page):
    commands = _commands()
    unknown = []
    for name, sub in re.findall(r"(?:^|`|\$ )codesign ([a-z][\w-]*)(?: ([a-z][\w-]*))?", page.read_text(encoding="utf-8"),
                                re.M):
        if name not in commands:
            unknown.append(name)
        elif commands[name] and sub and sub not in commands[name] and not sub.startswith("-"):
            unknown.append(f"{name} {sub}")
    assert not unknown, f"{page.relative_to(ROOT)} names commands that do not exist: {unknown}"


@pytest.mark.parametrize("page", USER_PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_module_or_name_a_page_gives_by_its_dotted_path_imports(page):
    import importlib

    missing = []
    for dotted in sorted(set(re.findall(r"\bcodesign(?:_[a-z]+)?(?:\.[A-Za-z_]\w*)+", page.read_text(encoding="utf-8")))):
        parts = dotted.split(".")
        for i in range(len(parts), 0, -1):  # the longest prefix that imports, then attributes
            try:
                obj = importlib.import_module(".".join(parts[:i]))
                break
            except ImportError:
                continue
        for attribute in parts[i:]:
            if not hasattr(obj, attribute):
                missing.append(dotted)
                break
            obj = getattr(obj, attribute)
    assert not missing, f"{page.relative_to(ROOT)} names modules or names that do not exist: {missing}"
