"""`codesign sweep`: a recipe's sweep: section run offline (Optuna proposes, the runner runs), on the
physics-free toy plugin: run directories, the summary over seeds, W&B groups, resume, Ray, errors."""
import csv
import json
import math
import statistics
import struct
from pathlib import Path

import pytest
import yaml

from codesign import CodesignError, RecipeError, sweep
from codesign.plots import mean_and_std
from codesign.recipe import resolve_recipe
from codesign.sweep import plan_sweep, run_sweep

from toy_plugin import CountingOptimizer

GRID = {
    "method": "grid",
    "parameters": {
        "controller.bound": {"values": [0.1, 0.3]},
        "environment.target_range": {"values": [0.05, 0.2]},
        "seed": {"values": [0, 1]},
    },
}


@pytest.fixture
def sweep_recipe(toy_recipe) -> dict:
    """The toy recipe (3 episodes of `evaluate`) swept over a 2 x 2 grid and 2 seeds; W&B off."""
    return {**toy_recipe, "name": "toysweep", "tracking": {"wandb_mode": "disabled"}, "sweep": GRID}


def read_csv(path: Path) -> list[dict]:
    with path.open() as f:
        return list(csv.DictReader(f))


def summary_of(run_dir: Path) -> dict:
    return json.loads((run_dir / "summary.json").read_text())


def wandb_run_record(path: Path):
    """The run record of an offline W&B run file (a LevelDB-style log of protobuf records)."""
    from wandb.proto import wandb_internal_pb2 as pb

    data, pos, chunk, block = path.read_bytes(), 7, b"", 32768  # 7: the file's ':W&B' header
    while pos + 7 <= len(data):
        if block - pos % block < 7:  # a block's tail too short for a header is padding
            pos += block - pos % block
            continue
        _, length, kind = struct.unpack("<IHB", data[pos:pos + 7])
        chunk, pos = chunk + data[pos + 7:pos + 7 + length], pos + 7 + length
        if kind in (1, 4):  # full, or last piece
            record = pb.Record()
            record.ParseFromString(chunk)
            chunk = b""
            if record.WhichOneof("record_type") == "run":
                return record.run
    raise AssertionError(f"no run record in {path}")


def test_a_2x2_grid_with_2_seeds_makes_8_runs_in_one_wandb_group_and_a_summary_over_seeds(
    tmp_path, sweep_recipe, cli, wandb_offline
):
    sweep_recipe["tracking"] = {"project": "codesign-tests"}  # W&B offline, the default mode
    recipe = tmp_path / "sweep.yaml"
    recipe.write_text(yaml.safe_dump(sweep_recipe))
    code, out, err = cli("sweep", str(recipe), "--sweep-dir", str(tmp_path / "sw"), "--no-progress")
    assert code == 0 and out.strip() == str(tmp_path / "sw")
    directory = tmp_path / "sw"

    run_dirs = sorted(p for p in directory.iterdir() if (p / "config.yaml").is_file())
    assert len(run_dirs) == 8 and all(summary_of(d)["status"] == "completed" for d in run_dirs)
    configs = [yaml.safe_load((d / "config.yaml").read_text()) for d in run_dirs]
    swept = {(c["controller"]["bound"], c["environment"]["target_range"], c["seed"]) for c in configs}
    assert swept == {(b, r, s) for b in (0.1, 0.3) for r in (0.05, 0.2) for s in (0, 1)}
    assert all(c["sweep"] is None and c["tracking"]["group"] == "toysweep" for c in configs)

    by_configuration: dict[tuple, list[float]] = {}
    for d, c in zip(run_dirs, configs):
        key = (c["controller"]["bound"], c["environment"]["target_range"])
        by_configuration.setdefault(key, []).append(summary_of(d)["best"]["episode_return"])
    rows = read_csv(directory / "summary.csv")
    assert len(rows) == 4
    for row in rows:
        values = by_configuration[(float(row["controller.bound"]), float(row["environment.target_range"]))]
        assert int(row["n"]) == 2
        assert float(row["mean"]) == pytest.approx(statistics.mean(values))
        assert float(row["std"]) == pytest.approx(statistics.stdev(values))
    means = [float(r["mean"]) for r in rows]
    assert means == sorted(means, reverse=True)  # best first (maximize)
    markdown = (directory / "summary.md").read_text()
    assert markdown.count("\n| ") == 2 + 4  # header, rule, 4 configurations
    assert "| controller.bound | environment.target_range | mean | std | n |" in markdown
    assert "| controller.bound |" in err  # the table is shown when the sweep ends
    assert (directory / "learning_curves.png").stat().st_size > 0

    records = [wandb_run_record(f) for d in run_dirs for f in (d / "wandb").glob("offline-run-*/run-*.wandb")]
    assert len(records) == 8
    assert {r.run_group for r in records} == {"toysweep"} and {r.project for r in records} == {"codesign-tests"}
    summary_run = [wandb_run_record(f) for f in (directory / "wandb").glob("offline-run-*/run-*.wandb")]
    assert [(r.run_group, r.job_type) for r in summary_run] == [("toysweep", "sweep-summary")]


def test_an_interrupted_sweep_resumes_skipping_finished_runs_and_continuing_the_half_finished_one(
    tmp_path, sweep_recipe, monkeypatch
):
    sweep_recipe["optimizer"] = {"name": "counting", "iterations": 3}
    sweep_recipe["sweep"] = {**GRID, "metric": {"name": "best.draw"}}
    recipe = resolve_recipe(sweep_recipe)
    calls: list[str] = []
    execute = sweep.execute

    def fifth_fails(data: dict) -> str:
        calls.append(Path(data["run_dir"]).name)
        monkeypatch.setattr(CountingOptimizer, "fail_at", 2 if len(calls) == 5 else None)
        return execute(data)

    monkeypatch.setattr(sweep, "execute", fifth_fails)
    directory = tmp_path / "sw"
    with pytest.raises(CodesignError, match=r"1 run\(s\) of the sweep failed .* --resume --sweep-dir"):
        run_sweep(recipe, sweep_dir=directory, progress=False)
    half = directory / calls[4]
    assert summary_of(half)["status"] == "failed" and summary_of(half)["iterations_completed"] == 1
    finished = {name: (directory / name / "metrics.jsonl").stat().st_mtime_ns
                for name in calls if name != half.name}
    assert len(finished) == 5  # the other seed of the failing configuration still ran
    assert len(read_csv(directory / "summary.csv")) == 2  # configurations with every seed finished

    with pytest.raises(CodesignError, match="not empty; continue it with --resume"):
        run_sweep(recipe, sweep_dir=directory, progress=False)
    changed = resolve_recipe({**sweep_recipe, "sweep": {**sweep_recipe["sweep"], "seed": 5}})
    with pytest.raises(CodesignError, match="the recipe differs"):
        run_sweep(changed, sweep_dir=directory, resume=True, progress=False)

    # a sweep run before a field existed (its sweep.yaml lacks it) resumes if the default is what it ran
    ran = yaml.safe_load((directory / "sweep.yaml").read_text())
    del ran["environment"]["n_points"]
    (directory / "sweep.yaml").write_text(yaml.safe_dump({**ran, "environment": {**ran["environment"], "horizon": 6}}))
    with pytest.raises(CodesignError, match="the recipe differs"):
        run_sweep(recipe, sweep_dir=directory, resume=True, progress=False)
    (directory / "sweep.yaml").write_text(yaml.safe_dump(ran))

    calls.clear()
    run_sweep(recipe, sweep_dir=directory, resume=True, progress=False)
    assert calls[0] == half.name and len(calls) == 3  # the half-finished run, then the last configuration
    assert {name: (directory / name / "metrics.jsonl").stat().st_mtime_ns for name in finished} == finished
    rows = [json.loads(line) for line in (half / "metrics.jsonl").read_text().splitlines()]
    assert [r["count"] for r in rows] == [1, 2, 3]  # continued from its checkpoint, not rerun
    assert summary_of(half)["status"] == "completed"
    assert len(read_csv(directory / "summary.csv")) == 4


def test_random_and_bayes_draw_their_trials_from_the_distributions(tmp_path, sweep_recipe):
    for method in ("random", "bayes"):
        sweep_recipe["sweep"] = {
            "method": method,
            "trials": 3,
            "parameters": {
                "controller.bound": {"distribution": "log_uniform_values", "min": 0.05, "max": 0.5},
                "optimizer.episodes": {"min": 1, "max": 3},  # integers: int_uniform, as W&B infers
                "controller.frequencies": {"values": [[6.0, 12.0], [3.0]]},  # any YAML value
            },
        }
        directory = run_sweep(resolve_recipe(sweep_recipe), sweep_dir=tmp_path / method, progress=False)
        configs = [yaml.safe_load(p.read_text()) for p in sorted(directory.glob("t*-seed7/config.yaml"))]
        assert len(configs) == 3 and len(read_csv(directory / "summary.csv")) == 3
        assert all(0.05 <= c["controller"]["bound"] <= 0.5 for c in configs)
        assert all(type(c["optimizer"]["episodes"]) is int and 1 <= c["optimizer"]["episodes"] <= 3 for c in configs)
        assert all(c["controller"]["frequencies"] in ([6.0, 12.0], [3.0]) for c in configs)


@pytest.mark.parametrize(
    "section, message",
    [
        ({"method": "grdi", "parameters": {"seed": {"values": [0]}}},
         "sweep.method: 'grdi' is not a valid choice; did you mean 'grid'? allowed: grid, random, bayes"),
        ({"method": "grid", "parameters": {"controller.bonud": {"values": [0.1]}}},
         "sweep.parameters.controller.bonud: 'controller.bonud' is not a recipe key; did you mean "
         "'controller.bound' or"),
        ({"method": "grid", "parameters": {"controller.bound": {"values": []}}},
         "sweep.parameters.controller.bound.values: [] is empty or not a list; allowed: a non-empty list"),
        ({"method": "grid", "parameters": {}}, "sweep.parameters: empty"),
        ({"method": "random", "trials": 2, "parameters": {"controller.bound": {"distribution": "normal", "min": 0.1,
                                                                              "max": 0.2}}},
         "sweep.parameters.controller.bound.distribution: 'normal' is not supported; did you mean 'uniform'? "
         "allowed: uniform, log_uniform_values, int_uniform"),
        ({"method": "random", "trials": 2, "parameters": {"controller.bound": {"min": 0.3, "max": 0.1}}},
         "sweep.parameters.controller.bound: min 0.3 is not below max 0.1; allowed: min < max"),
        ({"method": "grid", "parameters": {"controller.bound": {"min": 0.1, "max": 0.3}}},
         "sweep.parameters.controller.bound: a grid needs discrete values; allowed: values or value"),
        ({"method": "bayes", "parameters": {"controller.bound": {"values": [0.1]}}},
         "sweep.trials: missing; method bayes needs the number of configurations to try"),
        ({"method": "grid", "parameters": {"seed": {"values": [0, "one"]}}},
         "sweep.parameters.seed.values: [0, 'one']; allowed: seeds, integers >= 0"),
        ({"method": "grid", "parameters": {"run_dir": {"values": ["a"]}}},
         "sweep.parameters.run_dir: 'run_dir' is set by the sweep itself"),
        ({"method": "grid", "parameters": {"controller.bound": {"values": [0.1, -1.0]}}},
         "sweep.parameters: the run with controller.bound=-1.0, seed=7 is invalid: controller.bound: -1.0 is out "
         "of range; must be > 0"),
    ],
)
def test_bad_sweep_sections_fail_clearly_before_any_run(tmp_path, sweep_recipe, section, message):
    sweep_recipe["sweep"] = section
    with pytest.raises(RecipeError) as info:
        run_sweep(resolve_recipe(sweep_recipe), sweep_dir=tmp_path / "sw", progress=False)
    assert str(info.value).startswith("invalid recipe 'toysweep': ")
    assert message in str(info.value)
    assert not (tmp_path / "sw").exists()


def test_a_recipe_without_a_sweep_section_is_refused(toy_recipe):
    with pytest.raises(RecipeError, match="sweep: missing; a sweep needs a 'sweep:' section"):
        plan_sweep(resolve_recipe(toy_recipe))


def test_the_sweep_prints_as_a_native_wandb_sweep_running_codesign_run(tmp_path, sweep_recipe, cli):
    sweep_recipe["sweep"] = {**GRID, "method": "random", "trials": 3}
    recipe = tmp_path / "sweep.yaml"
    recipe.write_text(yaml.safe_dump(sweep_recipe))
    code, out, _ = cli("sweep", str(recipe), "optimizer.episodes=2", "--print-wandb-config")
    assert code == 0 and not list(Path.cwd().glob("sweeps"))  # nothing ran
    config = yaml.safe_load(out)
    assert config["program"] == str(recipe) and config["method"] == "random"
    assert config["metric"] == {"name": "best.episode_return", "goal": "maximize"}
    assert config["parameters"] == GRID["parameters"]  # the seed is an ordinary W&B parameter there
    assert config["run_cap"] == 6  # 3 configurations x 2 seeds
    assert config["command"] == ["codesign", "run", "${program}", "optimizer.episodes=2", "tracking.wandb=true",
                                 "tracking.wandb_mode=online", "--no-progress", "${args_no_hyphens}"]


def test_mean_and_std_over_seeds_use_the_iterations_every_run_reached():
    runs = [[{"iteration": i, "r": v} for i, v in enumerate(values)] for values in ([1.0, 2.0, 3.0], [3.0, 4.0])]
    iterations, mean, std = mean_and_std(runs, "r")
    assert (iterations, mean) == ([0, 1], [2.0, 3.0])
    assert std == pytest.approx([math.sqrt(2), math.sqrt(2)])


def test_the_ray_backend_runs_the_same_sweep_to_the_same_runs_and_summary(tmp_path, sweep_recipe, local_ray):
    recipe = resolve_recipe(sweep_recipe)
    local = run_sweep(recipe, sweep_dir=tmp_path / "local", progress=False)
    on_ray = run_sweep(recipe, sweep_dir=tmp_path / "ray", backend="ray", progress=False)
    names = sorted(p.name for p in on_ray.iterdir() if p.is_dir())
    assert names == sorted(p.name for p in local.iterdir() if p.is_dir()) and len(names) == 8
    assert read_csv(on_ray / "summary.csv") == read_csv(local / "summary.csv")
    assert all(summary_of(on_ray / name)["status"] == "completed" for name in names)
