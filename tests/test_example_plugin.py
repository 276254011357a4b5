"""End to end: a third-party plugin installed with pip is found through its entry point."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from codesign import plugins

HERE = Path(__file__).parent


@pytest.fixture(scope="module")
def plugin_dir(tmp_path_factory) -> Path:
    """The example plugin pip-installed into a private folder (its code and entry-point metadata).

    The running interpreter does the install and the runs below, with that folder on
    PYTHONPATH: this works however codesign was installed (a virtualenv, the base interpreter,
    conda), and nothing outside the folder sees the plugin. The build needs setuptools >= 68
    in this environment (the `dev` extra brings it); nothing is downloaded.
    """
    root = tmp_path_factory.mktemp("example-plugin")
    source = shutil.copytree(HERE / "example_plugin", root / "src")  # keep build files out of the repo
    result = subprocess.run(
        [sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-build-isolation", "--no-index",
         "--target", str(root / "site"), str(source)],
        capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    return root / "site"


def codesign(site: Path, *args: str, cwd: str | None = None, **env: str) -> subprocess.CompletedProcess:
    clean = {k: v for k, v in os.environ.items() if not k.startswith("CODESIGN_") or k == "CODESIGN_TAICHI_CACHE"}
    clean.update(PYTHONPATH=os.pathsep.join([str(site), str(HERE), *_python_path()]),
                 **{plugins.EXPLICIT_ENV: "toy_plugin"}, **env)
    return subprocess.run([sys.executable, "-m", "codesign", *args], capture_output=True, text=True, env=clean,
                          cwd=cwd)


def _python_path() -> list[str]:
    """This process's own PYTHONPATH (a checkout run without installing it), after the plugin's folder."""
    return [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]


def listed(result: subprocess.CompletedProcess) -> dict[str, dict]:
    assert result.returncode == 0, result.stderr
    return {row["name"]: row for row in json.loads(result.stdout)}


def test_installed_plugin_is_listed_with_its_distribution(plugin_dir):
    rows = listed(codesign(plugin_dir, "plugins", "--json"))
    assert rows["square_wave"]["distribution"] == "codesign-example-plugin"
    assert rows["square_wave"]["plugin"] == "example"
    assert rows["square_wave"]["kind"] == "controller"
    assert rows["sine"]["distribution"] == "codesign"  # first-party plugins are found the same way


def test_recipe_using_the_plugin_runs(plugin_dir, tmp_path, toy_recipe):
    toy_recipe["controller"] = {"name": "square_wave", "frequency": 2.0}
    recipe = tmp_path / "square.yaml"
    recipe.write_text(yaml.safe_dump(toy_recipe))
    result = codesign(plugin_dir, "run", str(recipe), "--run-dir", str(tmp_path / "run"), "--no-progress")
    assert result.returncode == 0, result.stderr
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["status"] == "completed" and summary["iterations_completed"] == 3


def test_the_plugins_environment_representation_and_optimizer_run_and_replay(plugin_dir, tmp_path):
    """One component of each kind from the plugin in one MPM run (its `gravel` environment, added with
    `codesign_mpm.plugin.register_environment`, the `wedge` design, `hill_climb`): its defaults are
    the preset's, the run keeps its best, and `codesign eval` replays that best to the same return."""
    shown = codesign(plugin_dir, "show", "recipes/quickstart.yaml", "environment.name=gravel",
                     cwd=str(HERE.parent))
    assert shown.returncode == 0, shown.stderr
    environment = yaml.safe_load(shown.stdout)["environment"]
    assert environment["terrain"]["friction"] == 0.8 and environment["cover"]["friction_angle"] == 55.0
    recipe = tmp_path / "gravel.yaml"
    recipe.write_text(yaml.safe_dump({"name": "gravel-wedge", "environment": {"name": "gravel", "horizon": 3},
                                      "representation": {"name": "wedge", "slope": 0.4}, "controller": {"name": "sine"},
                                      "optimizer": {"name": "hill_climb", "iterations": 3}}))
    result = codesign(plugin_dir, "run", str(recipe), "--run-dir", str(tmp_path / "run"), "--no-progress")
    assert result.returncode == 0, result.stderr
    assert result.stdout == f"{tmp_path / 'run'}\n"  # Taichi's banners go elsewhere: `dir=$(codesign run ...)` works
    rows = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    best = [row["best_return"] for row in rows]
    assert best == sorted(best) and best[-1] == max(row["episode_return"] for row in rows)
    assert all(row["torn_fraction"] == 0.0 for row in rows)  # the environment's integrity, passed on
    replay = codesign(plugin_dir, "eval", str(tmp_path / "run"))
    assert replay.returncode == 0, replay.stderr
    assert float(replay.stdout.split("return")[1].split()[0].strip(":=,")) == pytest.approx(best[-1], rel=1e-5)


def test_plugin_can_be_disabled_by_option_or_by_turning_off_autoload(plugin_dir):
    assert "square_wave" not in listed(codesign(plugin_dir, "--disable-plugin", "example", "plugins", "--json"))
    rows = listed(codesign(plugin_dir, "plugins", "--json", **{plugins.NO_AUTOLOAD_ENV: "1"}))
    assert "square_wave" not in rows and "sine" not in rows
    assert "toy" in rows  # explicitly named modules still load


def test_plugin_is_not_visible_outside_its_virtualenv():
    assert "square_wave" not in [e.name for e in plugins.get_registry().entries("controller")]



def test_the_plugins_material_is_listed_with_the_engines_own(plugin_dir):
    rows = listed(codesign(plugin_dir, "plugins", "--json"))
    assert rows["mooney_rivlin"]["kind"] == "material"
    assert rows["mooney_rivlin"]["distribution"] == "codesign-example-plugin"
    assert rows["sand"]["kind"] == "material" and rows["sand"]["distribution"] == "codesign"


@pytest.mark.slow
def test_the_plugins_material_runs_in_a_scene_and_its_gradients_match_finite_differences(plugin_dir):
    """tests/example_material_check.py in a process that sees the plugin: forward in float32, then every
    kind of input's gradient (actions, Young's modulus, x0, v0) against central differences in float64."""
    env = {k: v for k, v in os.environ.items() if k != plugins.EXPLICIT_ENV}  # keep CODESIGN_TAICHI_CACHE
    env["PYTHONPATH"] = os.pathsep.join([str(plugin_dir), *_python_path()])
    result = subprocess.run([sys.executable, str(HERE / "example_material_check.py")], capture_output=True,
                            text=True, env=env)
    assert result.returncode == 0, result.stderr[-3000:]
    report = json.loads(result.stdout.strip().splitlines()[-1])
    assert report["id"] >= 8 and report["kind"] == "elastic"  # after the engine's own models
    forward = report["forward"]
    assert forward["finite"] and forward["moved"] > 0.01 and 0.5 < forward["min_J"] < 1.0 < forward["max_J"] < 1.5
    for row in report["gradients"]:
        assert row["analytic"] == pytest.approx(row["numeric"], rel=1e-4, abs=1e-4 * row["scale"]), row
