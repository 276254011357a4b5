import json
from pathlib import Path

import pytest
import yaml



def write_recipe(tmp_path, data) -> str:
    path = tmp_path / "toy.yaml"
    path.write_text(yaml.safe_dump(data))
    return str(path)


def test_run_prints_the_run_dir_and_resume_continues(tmp_path, cli, toy_recipe):
    recipe = write_recipe(tmp_path, toy_recipe)
    run_dir = tmp_path / "run"
    code, out, _ = cli("run", recipe, "optimizer.episodes=2", "--run-dir", str(run_dir), "--no-progress")
    assert code == 0
    assert out.strip() == str(run_dir)
    assert len((run_dir / "metrics.jsonl").read_text().splitlines()) == 2
    code, out, _ = cli("run", "--resume", str(run_dir), "--no-progress")
    assert (code, out.strip()) == (0, str(run_dir))


def test_user_errors_print_one_red_line_without_traceback(tmp_path, cli, toy_recipe):
    recipe = write_recipe(tmp_path, toy_recipe)
    code, out, err = cli("show", recipe, "controller.name=sinee")
    assert code == 1 and out == ""
    assert err.strip() == (
        "error: invalid recipe 'toy': controller.name: unknown controller 'sinee'; did you mean 'sine'? "
        "known: hyperneat, mlp, sine, trajectory (from override 'controller.name=sinee')"
    )
    assert "Traceback" not in err


def test_resume_rejects_a_recipe_argument(tmp_path, cli):
    code, _, err = cli("run", "x.yaml", "--resume", str(tmp_path))
    assert code == 1 and "--resume takes no recipe" in err


def test_show_prints_the_resolved_recipe(tmp_path, cli, toy_recipe):
    code, out, _ = cli("show", write_recipe(tmp_path, toy_recipe), "seed=9")
    assert code == 0
    shown = yaml.safe_load(out)
    assert shown["seed"] == 9
    assert shown["controller"]["bound"] == 0.3  # defaults are filled in
    assert shown["tracking"] == {"wandb": False, "wandb_mode": "offline", "project": "codesign", "group": None}


def test_plugins_json_lists_every_entry_with_its_source(cli):
    code, out, _ = cli("plugins", "--json")
    assert code == 0
    rows = json.loads(out)
    assert {"kind": "controller", "name": "sine", "plugin": "basics", "distribution": "codesign"}.items() <= next(
        r for r in rows if r["name"] == "sine"
    ).items()
    assert all(r["description"] for r in rows)


def test_plugins_table(cli):
    code, out, _ = cli("plugins")
    assert code == 0 and "evaluate" in out and "basics" in out


def test_disable_plugin_option_hides_its_entries(cli):
    code, out, _ = cli("--disable-plugin", "basics", "plugins", "--json")
    assert code == 0
    assert "sine" not in [r["name"] for r in json.loads(out)]


def test_plugins_add_commands(cli):
    code, out, _ = cli("toy-hello")
    assert (code, out) == (0, "hello from toy\n")
    code, out, _ = cli("--help")
    assert "toy-hello" in out and "--disable-plugin" in out


@pytest.mark.parametrize("command", ["run", "show", "plugins"])
def test_every_command_has_help(cli, command):
    code, out, _ = cli(command, "--help")
    assert code == 0 and "Usage" in out


def test_eval_lines_name_the_bodys_integrity_where_the_environment_measures_it():
    from codesign.cli import episode_line

    assert episode_line(0, 1.5, {}) == "episode 0: return 1.5"  # e.g. the toy environment: no body
    assert episode_line(1, 7.0123, {"torn_fraction": 0.0, "thinnest_cells": 2.5, "torn_at_frame": 0.0}) == \
        "episode 1: return 7.0123, torn off 0% of the robot's mass, thinnest part 2.5 cells"
    assert episode_line(2, 3.0, {"torn_fraction": 0.2345, "thinnest_cells": 1.0, "torn_at_frame": 34.0}) == \
        ("episode 2: return 3, torn off 23.4% of the robot's mass (first over the tolerance at frame 34), "
         "thinnest part 1 cells")
    assert episode_line(3, float("nan"), {"unplayable": 1.0}) == \
        "episode 3: return nan (the environment refused the design: not played)"


def test_the_reference_pages_are_what_the_code_generates():
    from codesign.reference import PAGES

    docs = Path(__file__).parents[1] / "docs"
    for name, build in PAGES.items():
        assert (docs / name).read_text(encoding="utf-8") == build(), f"docs/{name} is stale: python -m codesign.reference"
    cli = (docs / "cli-reference.md").read_text(encoding="utf-8")
    for command in ("run", "sweep", "study", "eval", "view", "show", "plugins", "simulate", "render", "annotate",
                    "bench engine", "bench accuracy", "bench stability", "bench compile", "bench environments"):
        assert f"## `codesign {command}`" in cli
    assert "`--report`" in cli and "`--scale <list[str]>`" in cli
    api = (docs / "api.md").read_text(encoding="utf-8")
    for contract in ("Environment", "Representation", "Controller", "Optimizer", "DesignSpace", "DesignFields"):
        assert f"## `{contract}`" in api
    assert "### `step(self) -> dict[str, float]` *required*" in api
