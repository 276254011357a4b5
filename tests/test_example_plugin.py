"""End to end: a third-party plugin installed with pip is found through its entry point."""

import json
import os
import shutil
import subprocess
import venv
from importlib import metadata
from pathlib import Path

import pytest
import yaml

from codesign import plugins

HERE = Path(__file__).parent


@pytest.fixture(scope="module")
def venv_python(tmp_path_factory) -> Path:
    """A throwaway virtualenv that sees the system site (and its codesign) plus the example plugin."""
    try:
        metadata.distribution("codesign")
    except metadata.PackageNotFoundError:
        pytest.skip("codesign is not installed (pip install -e .) so a virtualenv cannot see it")
    root = tmp_path_factory.mktemp("example-plugin")
    source = shutil.copytree(HERE / "example_plugin", root / "src")  # keep build files out of the repo
    venv.EnvBuilder(system_site_packages=True, with_pip=False).create(root / "venv")
    python = root / "venv" / "bin" / "python"
    subprocess.run(
        [python, "-m", "pip", "install", "--quiet", "--no-deps", "--no-build-isolation", "--no-index", str(source)],
        check=True,
        capture_output=True,
    )
    return python


def codesign(python: Path, *args: str, **env: str) -> subprocess.CompletedProcess:
    clean = {k: v for k, v in os.environ.items() if not k.startswith("CODESIGN_")}
    clean.update(PYTHONPATH=str(HERE), **{plugins.EXPLICIT_ENV: "toy_plugin"}, **env)
    return subprocess.run([python, "-m", "codesign", *args], capture_output=True, text=True, env=clean)


def listed(result: subprocess.CompletedProcess) -> dict[str, dict]:
    assert result.returncode == 0, result.stderr
    return {row["name"]: row for row in json.loads(result.stdout)}


def test_installed_plugin_is_listed_with_its_distribution(venv_python):
    rows = listed(codesign(venv_python, "plugins", "--json"))
    assert rows["square_wave"]["distribution"] == "codesign-example-plugin"
    assert rows["square_wave"]["plugin"] == "example"
    assert rows["square_wave"]["kind"] == "controller"
    assert rows["sine"]["distribution"] == "codesign"  # first-party plugins are found the same way


def test_recipe_using_the_plugin_runs(venv_python, tmp_path, toy_recipe):
    toy_recipe["controller"] = {"name": "square_wave", "frequency": 2.0}
    recipe = tmp_path / "square.yaml"
    recipe.write_text(yaml.safe_dump(toy_recipe))
    result = codesign(venv_python, "run", str(recipe), "--run-dir", str(tmp_path / "run"), "--no-progress")
    assert result.returncode == 0, result.stderr
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["status"] == "completed" and summary["iterations_completed"] == 3


def test_plugin_can_be_disabled_by_option_or_by_turning_off_autoload(venv_python):
    assert "square_wave" not in listed(codesign(venv_python, "--disable-plugin", "example", "plugins", "--json"))
    rows = listed(codesign(venv_python, "plugins", "--json", **{plugins.NO_AUTOLOAD_ENV: "1"}))
    assert "square_wave" not in rows and "sine" not in rows
    assert "toy" in rows  # explicitly named modules still load


def test_plugin_is_not_visible_outside_its_virtualenv():
    assert "square_wave" not in [e.name for e in plugins.get_registry().entries("controller")]

