"""The documents name only what exists, and the README's test command is the one CI runs."""

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
