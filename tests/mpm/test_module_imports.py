"""Module structure of the MPM plugin: no import cycle between the environment and its episodes."""
import ast
from pathlib import Path

import codesign_mpm

PACKAGE = Path(codesign_mpm.__file__).parent


def imported_modules(path: Path) -> set[str]:
    """Every module a file imports, at its top or inside functions (TYPE_CHECKING blocks too)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
            names.update(f"{node.module}.{alias.name}" for alias in node.names)
        elif isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
    return names


def test_env_and_episode_do_not_import_each_other():
    episode = imported_modules(PACKAGE / "episode.py")
    assert "codesign_mpm.environment.env" not in episode, "episode runs against codesign_mpm.environment.protocols.EpisodeEnvironment"
    assert "codesign_mpm.environment.episode" in imported_modules(PACKAGE / "env.py")  # one way only
