import copy
import sys

import pytest

from codesign import plugins
from codesign.cli import main

#: A small recipe that runs in well under a second with the test doubles.
TOY_RECIPE = {
    "name": "toy",
    "seed": 7,
    "environment": {"name": "toy"},
    "representation": {"name": "constant"},
    "controller": {"name": "sine", "frequencies": [6.0, 12.0]},
    "optimizer": {"name": "evaluate", "episodes": 3},
}


@pytest.fixture(autouse=True)
def fresh_plugins(monkeypatch):
    """Every test sees the installed plugins plus tests/toy_plugin.py, loaded afresh."""
    monkeypatch.setenv(plugins.EXPLICIT_ENV, "toy_plugin")
    monkeypatch.delenv(plugins.DISABLE_ENV, raising=False)
    monkeypatch.delenv(plugins.NO_AUTOLOAD_ENV, raising=False)
    plugins.reset()
    yield
    plugins.reset()


@pytest.fixture
def toy_recipe() -> dict:
    return copy.deepcopy(TOY_RECIPE)


@pytest.fixture
def cli(capsys):
    """Run the codesign CLI in-process: cli("run", ...) -> (exit code, stdout, stderr)."""

    def run(*args: str) -> tuple[int, str, str]:
        with pytest.raises(SystemExit) as info:
            main(list(args))
        out, err = capsys.readouterr()
        return info.value.code, out, err

    return run


@pytest.fixture(autouse=True, scope="module")
def fresh_taichi_program():
    """Each module that simulates starts from a fresh Taichi program, so its fields get the same
    ids whatever ran before, and Taichi's offline cache (keyed by them) hits whichever tests are
    selected (codesign_mpm.runtime.reset)."""
    runtime = sys.modules.get("codesign_mpm.runtime")
    if runtime is not None:
        runtime.reset()
    yield
