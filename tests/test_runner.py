import json
import pickle
from pathlib import Path

import pytest
import yaml

from codesign import CodesignError, runner
from codesign.recipe import resolve_recipe

import toy_plugin
from toy_plugin import CountingOptimizer


def read_metrics(run_dir) -> list[dict]:
    return [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]


def read_summary(run_dir) -> dict:
    return json.loads((run_dir / "summary.json").read_text())


def test_best_metrics_take_the_best_episodes_own_figures_not_every_episodes_extreme():
    """summary.json's best: the highest return, the lowest loss, and the body figures of the best
    episode: a later episode that tore must not make the best one look torn."""
    rows = [{"loss": -1.0, "episode_return": 1.0, "torn_fraction": 0.0, "iteration": 0},
            {"loss": 5.0, "episode_return": -5.0, "torn_fraction": 0.4, "iteration": 1}]
    best = runner.best_metrics(rows, {"loss": False}, {"iteration": 0, "episode_return": 1.0, "torn_fraction": 0.0})
    assert best == {"loss": -1.0, "episode_return": 1.0, "torn_fraction": 0.0}


def test_run_writes_config_metrics_summary_and_checkpoint(tmp_path, toy_recipe):
    run_dir = runner.run(resolve_recipe(toy_recipe), run_dir=tmp_path / "run", progress=False)

    config = yaml.safe_load((run_dir / "config.yaml").read_text())
    assert config["run_dir"] == str(tmp_path / "run")
    assert config["controller"] == {"name": "sine", "frequencies": [6.0, 12.0], "phases": 4, "bound": 0.3, "init_std": 0.1,
                                    "bias": "per_basis"}
    assert resolve_recipe(config).data == config  # the saved config is itself a valid, complete recipe

    rows = read_metrics(run_dir)
    assert [r["iteration"] for r in rows] == [0, 1, 2]
    assert all({"episode_return", "mean_reward", "episode_length", "wall_time"} <= r.keys() for r in rows)
    assert rows[0]["wall_time"] <= rows[-1]["wall_time"]

    summary = read_summary(run_dir)
    assert summary["status"] == "completed"
    assert (summary["recipe"], summary["seed"], summary["iterations_completed"]) == ("toy", 7, 3)
    assert summary["final"]["episode_return"] == rows[-1]["episode_return"]
    assert summary["best"]["episode_return"] == max(r["episode_return"] for r in rows)
    assert {"python", "codesign", "numpy"} <= summary["versions"].keys()
    assert summary["wall_time"] >= rows[-1]["wall_time"]

    checkpoint = pickle.loads((run_dir / "checkpoint.pkl").read_bytes())
    assert checkpoint["completed"] == 3


def test_same_seed_gives_same_metrics_and_seeds_plugins(tmp_path, toy_recipe):
    toy_plugin.seeds.clear()
    a = runner.run(resolve_recipe(toy_recipe), run_dir=tmp_path / "a", progress=False)
    b = runner.run(resolve_recipe(toy_recipe), run_dir=tmp_path / "b", progress=False)
    strip = lambda rows: [{k: v for k, v in r.items() if k != "wall_time"} for r in rows]  # noqa: E731
    assert strip(read_metrics(a)) == strip(read_metrics(b))
    assert toy_plugin.seeds == [7, 7]


def test_best_respects_the_optimizers_direction(tmp_path, toy_recipe):
    toy_recipe["optimizer"] = {"name": "counting", "iterations": 3}
    summary = read_summary(runner.run(resolve_recipe(toy_recipe), run_dir=tmp_path / "r", progress=False))
    assert summary["best"]["count"] == 3  # maximised by default
    assert summary["best"]["loss"] == pytest.approx(1 / 3)  # declared lower-is-better


def test_failure_is_recorded_then_raised_and_resume_continues_exactly(tmp_path, toy_recipe, monkeypatch):
    toy_recipe["optimizer"] = {"name": "counting", "iterations": 4}
    reference = runner.run(resolve_recipe(toy_recipe), run_dir=tmp_path / "reference", progress=False)

    monkeypatch.setattr(CountingOptimizer, "fail_at", 3)
    with pytest.raises(RuntimeError, match="planned failure"):
        runner.run(resolve_recipe(toy_recipe), run_dir=tmp_path / "broken", progress=False)
    broken = tmp_path / "broken"
    summary = read_summary(broken)
    assert summary["status"] == "failed"
    assert summary["error"] == "RuntimeError: planned failure"
    assert summary["iterations_completed"] == 2
    assert len(read_metrics(broken)) == 2

    monkeypatch.setattr(CountingOptimizer, "fail_at", None)
    assert runner.resume(broken, progress=False) == broken
    rows = read_metrics(broken)
    assert [r["count"] for r in rows] == [1, 2, 3, 4]  # optimizer state restored
    expected = [r["draw"] for r in read_metrics(reference)]
    assert [r["draw"] for r in rows] == expected  # generator state restored
    assert read_summary(broken)["status"] == "completed"


def test_resume_drops_metrics_logged_after_the_last_checkpoint(tmp_path, toy_recipe):
    toy_recipe["optimizer"] = {"name": "counting", "iterations": 3}
    run_dir = runner.run(resolve_recipe(toy_recipe), run_dir=tmp_path / "r", progress=False)
    checkpoint = pickle.loads((run_dir / "checkpoint.pkl").read_bytes())
    # Pretend the process died after logging iteration 2 but before checkpointing it.
    checkpoint.update(completed=2, optimizer={"count": 2})
    (run_dir / "checkpoint.pkl").write_bytes(pickle.dumps(checkpoint))
    runner.resume(run_dir, progress=False)
    assert [r["iteration"] for r in read_metrics(run_dir)] == [0, 1, 2]


def test_run_refuses_a_non_empty_run_dir(tmp_path, toy_recipe):
    (tmp_path / "old").mkdir()
    (tmp_path / "old" / "something").write_text("x")
    with pytest.raises(CodesignError, match="not empty; continue it with --resume"):
        runner.run(resolve_recipe(toy_recipe), run_dir=tmp_path / "old", progress=False)


def test_resume_needs_a_run_directory(tmp_path):
    with pytest.raises(CodesignError, match="not a run directory"):
        runner.resume(tmp_path)


def test_default_run_dir_is_under_runs_named_after_the_recipe(tmp_path, toy_recipe, monkeypatch):
    monkeypatch.chdir(tmp_path)
    first = runner.run(resolve_recipe(toy_recipe), progress=False)
    second = runner.run(resolve_recipe(toy_recipe), progress=False)
    assert first.parent == Path("runs") and (tmp_path / first / "summary.json").is_file()
    assert first.name.startswith("toy-") and first != second  # never reuses a directory


def test_wandb_offline_run_is_written_inside_the_run_dir(tmp_path, toy_recipe, wandb_offline):
    toy_recipe["tracking"] = {"wandb": True, "project": "codesign-tests", "group": "g"}
    run_dir = runner.run(resolve_recipe(toy_recipe), run_dir=tmp_path / "run", progress=False)
    offline_runs = list((run_dir / "wandb").glob("offline-run-*"))
    assert len(offline_runs) == 1
    assert list(offline_runs[0].glob("*.wandb"))  # the run's data, ready for `wandb sync`
    assert len(read_metrics(run_dir)) == 3  # the JSON-lines log is kept alongside


@pytest.mark.parametrize("how", ["recipe", "environment"])
def test_wandb_disabled_is_not_started_and_the_run_keeps_its_own_log(tmp_path, toy_recipe, wandb_offline, monkeypatch,
                                                                      how):
    import wandb

    def refuse(*args, **kwargs):
        raise AssertionError("wandb.init called for a disabled run")

    monkeypatch.setattr(wandb, "init", refuse)
    toy_recipe["tracking"] = {"wandb": True, **({"wandb_mode": "disabled"} if how == "recipe" else {})}
    if how == "environment":
        monkeypatch.setenv("WANDB_MODE", "disabled")
    run_dir = runner.run(resolve_recipe(toy_recipe), run_dir=tmp_path / "run", progress=False)
    assert len(read_metrics(run_dir)) == 3 and not (run_dir / "wandb").exists()


def test_render_switch_renders_the_best_episode_through_a_plugin_and_logs_the_video(
    tmp_path, toy_recipe, wandb_offline
):
    toy_plugin.rendered.clear()
    toy_recipe["render"] = {"enabled": True, "camera": "side", "fps": 5}
    toy_recipe["tracking"] = {"wandb": True, "project": "codesign-tests"}
    run_dir = runner.run(resolve_recipe(toy_recipe), run_dir=tmp_path / "run", progress=False)
    assert toy_plugin.rendered == [(run_dir, "side", 5)]
    assert read_summary(run_dir)["status"] == "completed"
    logged = list((run_dir / "wandb").glob("offline-run-*/files/media/videos/best_episode_*.gif"))
    assert len(logged) == 1 and logged[0].stat().st_size > 0


def test_render_switch_off_renders_nothing(tmp_path, toy_recipe):
    toy_plugin.rendered.clear()
    runner.run(resolve_recipe(toy_recipe), run_dir=tmp_path / "run", progress=False)
    assert toy_plugin.rendered == [] and not (tmp_path / "run" / "best" / "episode.gif").exists()


def test_render_switch_fails_the_run_clearly_when_no_plugin_renders_its_environment(
    tmp_path, toy_recipe, monkeypatch
):
    monkeypatch.setattr(toy_plugin, "renders", False)
    toy_recipe["render"] = {"enabled": True}
    with pytest.raises(CodesignError, match="render.enabled: no plugin renders environment 'toy'"):
        runner.run(resolve_recipe(toy_recipe), run_dir=tmp_path / "run", progress=False)
    assert read_summary(tmp_path / "run")["status"] == "failed"


def test_non_finite_metrics_read_back_as_numbers_and_a_run_of_refused_designs_says_so(tmp_path):
    """metrics.jsonl stores nan and inf as strings (JSON has no such numbers); reading them back gives
    floats again, and the end-of-run line of a run whose every design was refused (return nan) says
    so instead of failing to format the strings."""
    import math

    from codesign.tracking import JsonlTracker

    tracker = JsonlTracker(tmp_path / runner.METRICS_FILE)
    for i, value in enumerate((math.nan, math.nan)):
        tracker.log({"episode_return": value, "best_return": -math.inf, "iteration": i}, step=i)
    tracker.close()
    rows = runner.read_metrics(tmp_path / runner.METRICS_FILE)
    assert math.isnan(rows[0]["episode_return"]) and rows[1]["best_return"] == -math.inf
    assert runner.progress_report(tmp_path) == ("episode return: none of the 2 episodes was playable "
                                                "(the environment refused every design)")
    tracker = JsonlTracker(tmp_path / runner.METRICS_FILE)
    tracker.log({"episode_return": 0.5, "iteration": 2}, step=2)
    tracker.close()
    assert runner.progress_report(tmp_path).startswith("episode return: first nan, best 0.5 (iteration 2), last 0.5")
