import copy
import os
import sys
from pathlib import Path

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


def _module_is_slow(item: pytest.Item) -> bool:
    marks = getattr(getattr(item, "module", None), "pytestmark", [])
    return any(mark.name == "slow" for mark in (marks if isinstance(marks, list) else [marks]))


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Modules marked slow as a whole (the gradient checks compile minutes of backward kernels on a
    cold cache) go first. xdist hands test files to its workers in this order (addopts:
    --no-loadscope-reorder; by default it sorts files by their number of tests, which put these
    few-test files last), so their compiles overlap the rest of the suite instead of ending it."""
    items.sort(key=lambda item: not _module_is_slow(item))  # stable: collection order otherwise


@pytest.fixture(autouse=True)
def private_caches(monkeypatch, tmp_path):
    """Each test keeps codesign's own caches (relaxed starts) to itself, not the user's."""
    monkeypatch.setenv("CODESIGN_CACHE", str(tmp_path / "codesign-cache"))


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


TINY_MPM_HORIZON = 5
TINY_MPM_RECIPE = {
    "name": "tiny-mpm", "seed": 0,
    "environment": {"name": "ground", "dx": 1 / 24, "horizon": TINY_MPM_HORIZON, "terrain": {"height": 0.13}},
    "representation": {"name": "particle"},
    "controller": {"name": "sine"},
    "optimizer": {"name": "cma_es", "generations": 1, "population": 2},
}
"""A real MPM run in seconds: a small box on ground, 5 control steps, one CMA-ES generation of 2."""


@pytest.fixture(scope="module")
def tiny_mpm_run(tmp_path_factory):
    """A finished run of TINY_MPM_RECIPE, with a best/ design and controller (about 10 s)."""
    from codesign import runner
    from codesign.recipe import resolve_recipe

    return runner.run(resolve_recipe(copy.deepcopy(TINY_MPM_RECIPE)), run_dir=tmp_path_factory.mktemp("tiny") / "run",
                      progress=False)


@pytest.fixture
def wandb_offline(tmp_path, monkeypatch):
    """W&B in offline mode, quiet, with its config, cache and data kept inside the test's tmp_path."""
    for var, value in {
        "WANDB_SILENT": "true",
        "WANDB_DISABLE_GIT": "true",
        "WANDB_CONFIG_DIR": str(tmp_path / "wandb-config"),
        "WANDB_CACHE_DIR": str(tmp_path / "wandb-cache"),
        "WANDB_DATA_DIR": str(tmp_path / "wandb-data"),
    }.items():
        monkeypatch.setenv(var, value)
    monkeypatch.delenv("WANDB_API_KEY", raising=False)
    monkeypatch.delenv("WANDB_MODE", raising=False)


@pytest.fixture
def local_ray(monkeypatch):
    """A local Ray instance with two worker CPUs; its workers find the toy plugin like this process."""
    import ray

    tests = str(Path(__file__).resolve().parent)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(filter(None, [tests, os.environ.get("PYTHONPATH")])))
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield ray
    ray.shutdown()


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
