"""Module structure of the MPM plugin: its rooms import downwards only, and the environment and
its episodes do not import each other."""
import ast
from pathlib import Path

import pytest

import codesign_mpm

PACKAGE = Path(codesign_mpm.__file__).parent
LAYERS = {"materials": 0, "scene": 1, "engine": 2, "environment": 3, "reports": 4, "viewing": 4}
"""Each room's rank: a room imports its own modules and those of lower rank only (docs/engine.md)."""


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


@pytest.mark.parametrize("room", list(LAYERS))
def test_each_room_imports_only_the_rooms_below_it(room):
    wrong = {}
    for path in sorted((PACKAGE / room).glob("*.py")):
        above = {name for name in imported_modules(path) if name.startswith("codesign_mpm.")
                 and LAYERS.get(name.split(".")[1], -1) >= LAYERS[room] and name.split(".")[1] != room}
        if above:
            wrong[path.name] = sorted(above)
    assert not wrong, f"{room}/ imports rooms at or above its own: {wrong}"


def test_the_rooms_are_every_package_of_the_plugin():
    packages = {p.parent.name for p in PACKAGE.glob("*/__init__.py")}
    assert packages == set(LAYERS)


def test_env_and_episode_do_not_import_each_other():
    episode = imported_modules(PACKAGE / "environment" / "episode.py")
    assert "codesign_mpm.environment.env" not in episode, "episode runs against environment.protocols.EpisodeEnvironment"
    assert "codesign_mpm.environment.episode" in imported_modules(PACKAGE / "environment" / "env.py")  # one way only
