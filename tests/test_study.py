"""`codesign study`: a study's arms run as sweeps over seeds, its table in the paper's unit (per-step
return), the verdict on the paper's ordering, resume, docs; every shipped study file resolves."""
import csv
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml

from codesign import RecipeError
from codesign.recipe import RECIPES_DIR, resolve_recipe
from codesign.study import (DOCS_DATA, DOCS_PAGE, Arm, Row, arm_recipe, best_along, data_path, docs_links, load_study, publish,
                            Study, published_section, read_records, rows_from, section, verdict)

SHIPPED = sorted((RECIPES_DIR / "studies").glob("*.yaml"))
REPO = RECIPES_DIR.parent
COMMITTED = sorted(p for p in (REPO / DOCS_DATA).glob("*.jsonl") if not p.name.endswith(".points.jsonl"))  # tables


@pytest.fixture
def toy_study(tmp_path, toy_recipe) -> Path:
    """Two arms of the physics-free toy recipe (the action bound), two seeds, with paper numbers."""
    study = {
        "study": {"title": "Toy bound", "paper": "none", "seeds": [0, 1],
                  "arms": [{"label": "Loose bound", "paper": 0.5, "set": {"controller.bound": 0.3}},
                           {"label": "Tight bound", "paper": 0.2, "set": {"controller.bound": 0.01}}],
                  "scales": {"tiny": {"seeds": [3], "optimizer.episodes": 1}}},
        "recipe": {**toy_recipe, "tracking": {"wandb_mode": "disabled"}},
    }
    path = tmp_path / "toy_bound.yaml"
    path.write_text(yaml.safe_dump(study))
    return path


def test_each_arm_runs_once_per_seed_and_the_table_holds_each_best_return_per_step(tmp_path, toy_study, cli):
    code, out, err = cli("study", str(toy_study), "--dir", str(tmp_path / "s"), "--no-progress")
    assert code == 0, err
    root = Path(out.strip())
    rows = {r["arm"]: r for r in csv.DictReader((root / "table.csv").open())}
    assert set(rows) == {"Loose bound", "Tight bound"}
    for arm in ("loose_bound", "tight_bound"):
        runs = sorted((root / arm).glob("t*-seed*"))
        assert [yaml.safe_load((r / "config.yaml").read_text())["seed"] for r in runs] == [0, 1]
        horizon = yaml.safe_load((runs[0] / "config.yaml").read_text())["environment"]["horizon"]
        expected = [json.loads((r / "summary.json").read_text())["best"]["episode_return"] / horizon for r in runs]
        label = "Loose bound" if arm == "loose_bound" else "Tight bound"
        assert json.loads(rows[label]["per_step"]) == pytest.approx(expected)
        assert float(rows[label]["mean"]) == pytest.approx(sum(expected) / 2)
    assert (root / "toy_bound.png").stat().st_size > 1000
    assert "Kendall's tau" in (root / "section.md").read_text()


def test_each_arm_also_plays_its_starting_design_without_any_action(tmp_path, toy_study, cli):
    """The table's "no action" column: what the arm's body scores by itself (first seed, every action
    0), from a run beside the arm's seeds, played once for arms whose still episodes are the same (the
    toy's arms differ only in the controller); `study.still: false` leaves it out."""
    spec = yaml.safe_load(toy_study.read_text())
    spec["study"]["arms"].append({"label": "Far targets", "set": {"environment.target_range": 0.3}})
    three = tmp_path / "three.yaml"
    three.write_text(yaml.safe_dump(spec))
    code, out, err = cli("study", str(three), "--dir", str(tmp_path / "s"), "--no-progress")
    assert code == 0, err
    root = Path(out.strip())
    rows = {r["arm"]: r for r in csv.DictReader((root / "table.csv").open())}
    for arm, label, played in (("loose_bound", "Loose bound", "loose_bound"), ("tight_bound", "Tight bound", "loose_bound"),
                               ("far_targets", "Far targets", "far_targets")):
        still = root / played / "still"
        config = yaml.safe_load((still / "config.yaml").read_text())
        assert config["seed"] == 0 and config["optimizer"]["name"] == "evaluate"
        assert not np.load(still / "trajectory-0.npz")["actions"].any()
        episode_return = json.loads((still / "summary.json").read_text())["best"]["episode_return"]
        assert float(rows[label]["still"]) == pytest.approx(episode_return / config["environment"]["horizon"])
    assert not (root / "tight_bound" / "still").exists()
    assert rows["Far targets"]["still"] != rows["Loose bound"]["still"]
    assert "| no action |" in (root / "table.md").read_text()

    spec["study"]["still"] = False
    quiet = tmp_path / "quiet.yaml"
    quiet.write_text(yaml.safe_dump(spec))
    code, out, err = cli("study", str(quiet), "--dir", str(tmp_path / "q"), "--no-progress")
    assert code == 0, err
    assert not list(Path(out.strip()).glob("*/still"))


def test_a_rerun_continues_the_study_and_reruns_no_finished_run(tmp_path, toy_study, cli):
    cli("study", str(toy_study), "--dir", str(tmp_path / "s"), "--no-progress")
    summary = next((tmp_path / "s" / "loose_bound").glob("t*-seed0")) / "summary.json"
    before = summary.stat().st_mtime_ns
    table = (tmp_path / "s" / "table.md").read_text()
    code, _, err = cli("study", str(toy_study), "--dir", str(tmp_path / "s"), "--no-progress")
    assert code == 0, err
    assert summary.stat().st_mtime_ns == before and (tmp_path / "s" / "table.md").read_text() == table


def test_arm_runs_the_arms_chosen_first_and_a_later_run_the_rest(tmp_path, toy_study, cli):
    root = tmp_path / "s"
    code, _, err = cli("study", str(toy_study), "--dir", str(root), "--arm", "Tight bound", "--no-progress")
    assert code == 0, err
    assert len(list((root / "tight_bound").glob("t*-seed*/summary.json"))) == 2
    assert not list(root.glob("loose_bound/t*-seed*"))
    assert "**Under way**: 2 of 4 runs finished" in (root / "section.md").read_text()
    first = next((root / "tight_bound").glob("t*-seed0")) / "summary.json"
    before = first.stat().st_mtime_ns
    code, _, err = cli("study", str(toy_study), "--dir", str(root), "--no-progress")
    assert code == 0, err
    assert first.stat().st_mtime_ns == before and len(list(root.glob("loose_bound/t*-seed*/summary.json"))) == 2
    code, _, err = cli("study", str(toy_study), "--dir", str(root), "--arm", "Medium bound")
    assert code != 0 and "--arm 'Medium bound': no arm of study toy_bound has it; its arms' parts: Loose bound, " \
                         "Tight bound" in err


def test_a_scale_changes_seeds_and_settings_and_an_unknown_scale_names_the_allowed_ones(toy_study):
    tiny = load_study(str(toy_study), "tiny")
    assert tiny.seeds == (3,) and tiny.recipe["optimizer"]["episodes"] == 1
    with pytest.raises(RecipeError, match="'huge' is not a scale of this study; allowed: cpu, tiny"):
        load_study(str(toy_study), "huge")


def test_an_arm_with_an_unknown_key_is_an_error_naming_it(tmp_path, toy_study):
    data = yaml.safe_load(toy_study.read_text())
    data["study"]["arms"][0]["sett"] = {}
    toy_study.write_text(yaml.safe_dump(data))
    with pytest.raises(RecipeError, match=r"study.arms\[0\]: .*unknown sett"):
        load_study(str(toy_study))


def test_an_arm_whose_runs_do_not_depend_on_the_seed_can_run_one(tmp_path, toy_study, cli):
    """`seeds` on an arm: its own seeds (those the scale runs; else the scale's first), the table
    counting its runs; a bad value names the key."""
    data = yaml.safe_load(toy_study.read_text())
    data["study"]["arms"][1]["seeds"] = [1]
    toy_study.write_text(yaml.safe_dump(data))
    assert [arm.seeds for arm in load_study(str(toy_study)).arms] == [None, (1,)]
    assert load_study(str(toy_study), "tiny").arms[1].seeds == (3,)  # the tiny scale runs seed 3 alone
    code, out, err = cli("study", str(toy_study), "--dir", str(tmp_path / "s"), "--no-progress")
    assert code == 0, err
    root = Path(out.strip())
    assert [p.name for p in sorted((root / "tight_bound").glob("t*-seed*"))] == ["t000-seed1"]
    rows = {r["arm"]: r for r in csv.DictReader((root / "table.csv").open())}
    assert (rows["Loose bound"]["seeds"], rows["Tight bound"]["seeds"]) == ("2", "1")
    section = (root / "section.md").read_text()
    assert "Under way" not in section and "(1 for the arms whose runs do not depend on the seed)" in section
    data["study"]["arms"][1]["seeds"] = "one"
    toy_study.write_text(yaml.safe_dump(data))
    with pytest.raises(RecipeError, match=r"study.arms\[1\].seeds: 'one'; give a non-empty list of integers"):
        load_study(str(toy_study))


def _row(label: str, paper: float, values: tuple[float, ...]) -> Row:
    return Row(Arm(label, paper=paper), values, (0.0,) * len(values), (1.0,) * len(values))


def test_the_verdict_says_whether_the_paper_ordering_holds_and_which_arms_the_seeds_do_not_separate():
    held = verdict([_row("A", 0.1, (1.0, 1.1)), _row("B", 0.3, (3.0, 3.1))])
    assert "(B > A) **holds**" in held and "tau 1.00" in held and "not separated" not in held
    reversed_ = verdict([_row("A", 0.1, (3.0, 3.1)), _row("B", 0.3, (1.0, 1.1))])
    assert "**does not hold** here: ours is A > B" in reversed_
    close = verdict([_row("A", 0.1, (1.0, 2.0)), _row("B", 0.3, (1.2, 2.2))])
    assert "**holds**" in close and "not separated at this scale): B / A" in close


def test_an_arm_reports_the_best_of_its_seeds_or_their_mean_and_its_gain_over_iteration_0(toy_study):
    """The paper reports diff-physics as the best of 8 seeds and PPO as the mean of 5: the verdict
    compares what the study (or the arm) says it reports; the gain is over each run's own start."""
    best = Row(Arm("A", paper=0.3), (1.0, 5.0), (0.0, 0.0), (1.0, 1.0), first=(0.5, 1.0))
    steady = Row(Arm("B", paper=0.1), (3.0, 3.2), (0.0, 0.0), (1.0, 1.0), first=(3.0, 3.0))
    assert (best.value, best.gain, steady.gain) == (5.0, 2.25, pytest.approx(0.1))
    assert "(A > B) **holds**" in verdict([best, steady])
    mean = Row(Arm("A", paper=0.3), (1.0, 5.0), (0.0, 0.0), (1.0, 1.0), reported="mean")
    assert "**does not hold** here: ours is B > A" in verdict([mean, steady])
    data = yaml.safe_load(toy_study.read_text())
    data["study"]["arms"][1]["reported"] = "mean"
    toy_study.write_text(yaml.safe_dump(data))
    assert [arm.reported for arm in load_study(str(toy_study)).arms] == [None, "mean"]
    data["study"]["reported"] = "median"
    toy_study.write_text(yaml.safe_dump(data))
    with pytest.raises(RecipeError, match=r"study.reported: 'median'; allowed: best, mean"):
        load_study(str(toy_study))


def test_a_cell_whose_every_arm_does_no_better_than_no_action_is_said_and_not_ranked():
    """Table 1's turning cells score within noise of a body left alone: ranking them ranks noise."""
    def row(cell, method, paper, values, still):
        return Row(Arm(f"{cell} / {method}", paper=paper, cell=cell), values, (0.0,) * 2, (1.0,) * 2, still)

    rows = [row("Turn", "diff", 0.2, (0.010, 0.012), 0.0115), row("Turn", "ppo", 0.1, (0.009, 0.0095), 0.0115),
            row("Walk", "diff", 0.4, (0.5, 0.6), 0.01), row("Walk", "ppo", 0.3, (0.3, 0.35), 0.01)]
    text = verdict(rows)
    assert "(Walk / diff > Walk / ppo) **holds**" in text and "Turn / diff" not in text.split("Not ranked")[0]
    assert "Not ranked, no better than no action (by more than their spread over seeds): Turn / diff, Turn / ppo" in text
    rows[1] = row("Turn", "ppo", 0.1, (0.5, 0.51), 0.0115)  # one arm of the cell moves: the cell is ranked
    assert "Not ranked" not in verdict(rows)
    # an arm no better than no action in a ranked cell is named, with whether its budget ended it still improving
    rows[0] = replace(rows[0], best_at_end=(True, False))
    assert ("ranked with the rest of their cell: Turn / diff (best at its last iteration in 1 of 2 seeds)."
            in verdict(rows))


def _published_toy(tmp_path, toy_study, cli) -> tuple[Path, Study]:
    """The toy study run in tmp_path/s and published into a repository of its own, tmp_path/repo."""
    code, _, err = cli("study", str(toy_study), "--dir", str(tmp_path / "s"), "--no-progress")
    assert code == 0, err
    repo = tmp_path / "repo"
    (repo / "docs").mkdir(parents=True)
    study = load_study(str(toy_study))
    publish(study, tmp_path / "s", repo)
    return repo, study


def test_the_committed_records_alone_rebuild_a_published_section(tmp_path, toy_study, cli, monkeypatch):
    """A fresh clone has no runs: `--report` then builds the table from docs/data/studies/, and
    what it writes is what `--docs` published (every number traceable to the committed records)."""
    repo, study = _published_toy(tmp_path, toy_study, cli)
    header, records = read_records(data_path(study, repo))
    assert header == {"study": "toy_bound", "scale": "cpu"}
    runs = [r for r in records if "best" in r]
    assert len(runs) == 4 and all(len(r["returns"]) == 3 for r in runs)  # the toy evaluates 3 episodes
    monkeypatch.chdir(repo)
    code, out, err = cli("study", str(toy_study), "--dir", str(tmp_path / "none"), "--report")
    assert code == 0, err
    assert "reporting the committed" in err
    published = published_section(repo / DOCS_PAGE, "toy_bound")
    assert docs_links((tmp_path / "none" / "section.md").read_text(), ["toy_bound.png"]) == published


def test_a_study_continued_elsewhere_keeps_the_committed_arms_it_has_not_rerun(tmp_path, toy_study, cli,
                                                                            monkeypatch):
    """A study longer than one machine's session: the next machine runs the arms left (`--arm`), and
    its table holds those runs and, for every arm it has no run (or no no-action episode) of, the
    committed records."""
    repo, study = _published_toy(tmp_path, toy_study, cli)
    _, committed = read_records(data_path(study, repo))
    # the committed loose-bound arm, marked so that its rows can be told from a rerun's
    data_path(study, repo).write_text("".join(json.dumps(r) + "\n" for r in [
        {"study": "toy_bound", "scale": "cpu"},
        *({**r, "best": 1e3 * r["horizon"]} if "best" in r and r["arm"] == "Loose bound" else r for r in committed)]))
    monkeypatch.chdir(repo)
    code, _, err = cli("study", str(toy_study), "--dir", str(tmp_path / "next"), "--arm", "Tight bound",
                       "--no-progress")
    assert code == 0, err
    assert "1 arm(s) with no finished run in" in err and not list((tmp_path / "next").glob("loose_bound/t*"))
    rows = {r["arm"]: r for r in csv.DictReader((tmp_path / "next" / "table.csv").open())}
    assert json.loads(rows["Loose bound"]["per_step"]) == [1e3, 1e3]  # the committed runs
    ran = [json.loads((run / "summary.json").read_text())["best"]["episode_return"]
           for run in sorted((tmp_path / "next" / "tight_bound").glob("t*-seed*"))]
    assert json.loads(rows["Tight bound"]["per_step"]) == pytest.approx([r / committed[0]["horizon"] for r in ran])
    assert "Under way" not in (tmp_path / "next" / "section.md").read_text()
    # the arms share one no-action episode, played in the loose bound's directory: committed, not rerun
    assert not list((tmp_path / "next").rglob("still"))
    stills = {r["arm"]: r["still"] for r in committed if "still" in r}
    assert {arm: float(rows[arm]["still"]) for arm in rows} == pytest.approx(stills) and len(stills) == 2


def test_publish_replaces_the_study_section_in_docs(tmp_path, toy_study, cli):
    cli("study", str(toy_study), "--dir", str(tmp_path / "s"), "--no-progress")
    repo = tmp_path / "repo"
    (repo / "docs").mkdir(parents=True)
    (repo / "docs" / "studies.md").write_text("# Studies\n\nintro\n")
    study = load_study(str(toy_study))
    publish(study, tmp_path / "s", repo)
    publish(study, tmp_path / "s", repo)  # a second publish replaces, not appends
    page = (repo / "docs" / "studies.md").read_text()
    assert page.startswith("# Studies\n\nintro\n") and page.count("<!-- study:toy_bound -->") == 1
    assert "## Toy bound" in page and (repo / "docs" / "images" / "studies" / "toy_bound.png").is_file()


@pytest.mark.parametrize("path", SHIPPED, ids=[p.stem for p in SHIPPED])
def test_every_shipped_study_resolves_every_arm_at_every_scale(path):
    scales = ["cpu", *(yaml.safe_load(path.read_text())["study"].get("scales") or {})]
    assert "tiny" in scales, "a shipped study needs a tiny scale for its smoke test"
    for scale in scales:
        study = load_study(str(path), scale)
        assert len(study.seeds) >= (1 if scale == "tiny" else 3)
        for arm in study.arms:
            resolve_recipe(arm_recipe(study, arm), default_name=arm.slug)


def test_init_controller_starts_the_controller_from_a_run_best_controller(tmp_path, toy_recipe, cli):
    """A zero sine controller acts 0, which the toy rewards with exactly 0 when every target is 0;
    the controller's own random start does worse. Parameters of another shape are an error."""
    import torch

    saved = tmp_path / "pretrained"
    (saved / "best").mkdir(parents=True)
    torch.save([torch.zeros(2, 2, 4), torch.zeros(2, 2, 4)], saved / "best" / "controller.pt")
    recipe = {**toy_recipe, "environment": {"name": "toy", "target_range": 0.0}, "tracking": {"wandb_mode": "disabled"}}
    for name, start, expected in (("own", None, "negative"), ("loaded", str(saved), "zero")):
        path = tmp_path / f"{name}.yaml"
        path.write_text(yaml.safe_dump({**recipe, "init_controller": start}))
        code, out, err = cli("run", str(path), "--run-dir", str(tmp_path / name), "--no-progress")
        assert code == 0, err
        best = json.loads((tmp_path / name / "summary.json").read_text())["best"]["episode_return"]
        assert (best == 0.0) if expected == "zero" else (best < 0.0)
    torch.save([torch.zeros(3)], saved / "best" / "controller.pt")
    code, _, err = cli("run", str(tmp_path / "loaded.yaml"), "--run-dir", str(tmp_path / "bad"), "--no-progress")
    assert code != 0 and "holds parameters of shapes [(3,)]" in err


def test_a_study_with_a_preparatory_run_starts_every_arm_from_its_controller():
    study = load_study("representations")
    assert study.prepare is not None
    for arm in study.arms:
        assert arm_recipe(study, arm, Path("out"))["init_controller"] == str(Path("out") / "prepare")


def test_a_preparatory_run_can_start_only_the_arms_it_names(tmp_path, toy_study):
    """Table 3's design-only arm starts from a gait trained beforehand (as the paper's does); its
    control-only and co-design arms start from scratch."""
    study = load_study("what_to_optimise")
    starts = {arm.label: arm_recipe(study, arm, Path("out")).get("init_controller") for arm in study.arms}
    assert starts == {"Controller": None, "Design": str(Path("out") / "prepare"), "Design + Control": None}
    data = yaml.safe_load(toy_study.read_text())
    data["study"]["prepare"] = {"label": "gait", "set": {}, "arms": ["Loose", "Tight bound"]}
    toy_study.write_text(yaml.safe_dump(data))
    with pytest.raises(RecipeError, match=r"study.prepare.arms: \['Loose', 'Tight bound'\]; give a list of arm "
                                          r"labels \(the arms that start from its controller\): Loose bound, Tight bound"):
        load_study(str(toy_study))


def test_a_grid_makes_an_arm_per_combination_with_the_paper_number_and_only_its_scales(tmp_path, toy_recipe):
    study = {
        "study": {"title": "grid", "seeds": [0],
                  "grid": [[{"label": "A", "set": {"controller.bound": 0.1}},
                            {"label": "B", "set": {"controller.bound": 0.2}, "only": ["paper"]}],
                           [{"label": "x", "set": {"optimizer.episodes": 1}},
                            {"label": "y", "set": {"optimizer.episodes": 2}, "scales": {"paper": {"optimizer.episodes": 9}}}]],
                  "paper_table": {"A": [0.1, 0.2], "B": {"x": 0.3}},
                  "scales": {"paper": {}}},
        "recipe": toy_recipe,
    }
    path = tmp_path / "grid.yaml"
    path.write_text(yaml.safe_dump(study))
    cpu = load_study(str(path))
    assert [(a.label, a.paper) for a in cpu.arms] == [("A / x", 0.1), ("A / y", 0.2)]
    paper = load_study(str(path), "paper")
    assert [(a.label, a.paper) for a in paper.arms] == [("A / x", 0.1), ("A / y", 0.2), ("B / x", 0.3), ("B / y", None)]
    assert arm_recipe(paper, paper.arms[3])["optimizer"]["episodes"] == 9
    assert arm_recipe(paper, paper.arms[3])["controller"]["bound"] == 0.2



def test_arms_sharing_a_section_value_do_not_change_each_other(tmp_path, toy_recipe):
    """A section given whole (a dict) and a dotted key into it, as a grid's scales give them."""
    shared = {"name": "evaluate", "episodes": 1}
    study = {"study": {"title": "t", "seeds": [0],
                       "grid": [[{"label": "A", "scales": {"paper": {"optimizer.episodes": 7}}}, {"label": "B"}],
                                [{"label": "x", "set": {"optimizer": shared}}]],
                       "scales": {"paper": {}}},
             "recipe": toy_recipe}
    path = tmp_path / "shared.yaml"
    path.write_text(yaml.safe_dump(study))
    paper = load_study(str(path), "paper")
    assert arm_recipe(paper, paper.arms[0])["optimizer"]["episodes"] == 7
    assert arm_recipe(paper, paper.arms[1])["optimizer"]["episodes"] == 1


def test_a_study_under_way_reports_its_finished_arms(tmp_path, toy_study, cli):
    cli("study", str(toy_study), "--dir", str(tmp_path / "s"), "--no-progress")
    for run in (tmp_path / "s" / "tight_bound").glob("t*-seed*"):
        (run / "summary.json").unlink()  # as if never finished
    code, _, err = cli("study", str(toy_study), "--dir", str(tmp_path / "s"), "--report")
    assert code == 0, err
    section = (tmp_path / "s" / "section.md").read_text()
    assert "**Under way**: 2 of 4 runs finished (1 of 2 arms" in section and "Tight bound" not in section


def test_a_grid_is_also_read_along_one_dimension_as_the_paper_reads_it():
    """Table 1's finding is which animal suits which environment: per task, environment and method,
    the best animal of ours against the paper's, and whether the seeds separate ours."""
    def row(label, paper, values):
        return Row(Arm(label, paper=paper, cell=label.rsplit(" / ", 1)[0]), values, (0.0,) * 2, (1.0,) * 2)

    rows = [row("Walk / Seal / Ground / diff", 0.12, (0.5, 0.52)), row("Walk / Worm / Ground / diff", 0.08, (0.2, 0.21)),
            row("Walk / Seal / Sea / diff", 0.03, (0.30, 0.40)), row("Walk / Worm / Sea / diff", 0.13, (0.35, 0.36)),
            row("Walk / Seal / Sand / diff", 0.06, (0.1, 0.1))]  # no caterpillar in the sand: nothing to compare
    text = best_along(rows, 1, "animal")
    assert "ours is the paper's in 1 of 2 comparisons, and the seeds separate our best" in text
    assert "in 1 of the 2." in text
    assert "Where they differ: Walk / Sea / diff: ours Seal (0.4000, not separated), the paper's Worm (0.130)." in text
    assert "No two animals" in best_along(rows[4:], 1, "animal")


def test_best_along_names_a_grid_dimension_before_the_methods(tmp_path):
    study = tmp_path / "grid.yaml"
    spec = {"study": {"title": "t", "grid": [[{"label": "a"}], [{"label": "x"}], [{"label": "m"}]],
                      "best_along": {"dimension": 2, "name": "method"}},
            "recipe": {"environment": {"name": "toy"}}}
    study.write_text(yaml.safe_dump(spec))
    with pytest.raises(RecipeError, match=r"study.best_along: .*a grid dimension before the methods' \(0 to 1\)"):
        load_study(str(study))
    spec["study"]["best_along"]["dimension"] = 1
    study.write_text(yaml.safe_dump(spec))
    assert load_study(str(study)).best_along == (1, "method")


def test_a_large_table_verdict_counts_the_pairs_ordered_as_in_the_paper():
    rows = [_row(f"arm{i}", paper, (mean, mean + 0.01)) for i, (paper, mean) in
            enumerate([(0.1, 1.0), (0.2, 2.0), (0.3, 3.0), (0.4, 4.0), (0.5, 5.0), (0.6, 7.0), (0.7, 6.0)])]
    text = verdict(rows)
    assert "Over the 7 arms with a number in the paper, ours order 20 of 21 pairs as the paper's do" in text
    rows[0] = replace(rows[0], still=1.01)  # arm0 (best 1.01) does no better than doing nothing: named
    assert verdict(rows) == text + (" No better than no action by more than their spread over seeds, ranked with "
                                    "the rest of their cell: arm0.")


@pytest.mark.parametrize("path", COMMITTED, ids=[p.stem for p in COMMITTED])
def test_each_section_in_the_docs_is_what_its_committed_records_rebuild(path, monkeypatch):
    """docs/studies.md's tables come from docs/data/studies/ alone (`codesign study NAME --report --docs`)."""
    header, records = read_records(path)
    monkeypatch.chdir(REPO)
    study = load_study(header["study"], header["scale"])
    assert data_path(study) == path.relative_to(REPO)
    text = docs_links(section(study, rows_from(study, records)), [f"{study.name}.png"])
    assert published_section(REPO / DOCS_PAGE, study.name) == text


def test_an_analysis_reports_from_its_committed_points_where_its_directory_has_none(tmp_path, monkeypatch):
    """An analysis's section is rebuilt by running it on its points: from a fresh clone, the
    committed ones (docs/data/studies/NAME.points.jsonl), so it measures nothing they hold."""
    from codesign.study import POINTS_FILE, seed_points

    study = load_study("muscle_ambiguity")
    monkeypatch.chdir(tmp_path)
    assert data_path(study) == DOCS_DATA / "muscle_ambiguity.points.jsonl"
    assert not seed_points(study, tmp_path / "run")  # nothing committed: nothing to copy
    data_path(study).parent.mkdir(parents=True)
    data_path(study).write_text('{"key": ["stiffness", 2.0, 0], "emd": 1.0}\n')
    assert seed_points(study, tmp_path / "run")
    assert (tmp_path / "run" / POINTS_FILE).read_text() == data_path(study).read_text()
    (tmp_path / "run" / POINTS_FILE).write_text("{}\n")  # points of its own are kept
    assert not seed_points(study, tmp_path / "run") and (tmp_path / "run" / POINTS_FILE).read_text() == "{}\n"


def test_on_ray_a_study_runs_every_arm_at_once_to_the_same_runs_and_table(tmp_path, toy_study, local_ray, cli):
    """`--backend ray`: the preparatory run first, then every arm's seeds and the no-action episodes
    as Ray tasks; the records and the table are those of the same study run here, one run after another."""
    data = yaml.safe_load(toy_study.read_text())
    data["study"]["prepare"] = {"label": "a gait first", "set": {"optimizer.episodes": 2}, "arms": ["Tight bound"]}
    toy_study.write_text(yaml.safe_dump(data))
    here, there = tmp_path / "here", tmp_path / "ray"
    assert cli("study", str(toy_study), "--dir", str(here), "--no-progress")[0] == 0
    code, out, err = cli("study", str(toy_study), "--dir", str(there), "--backend", "ray", "--no-progress")
    assert code == 0, err

    def returns(root: Path) -> list:
        _, records = read_records(root / "runs.jsonl")
        return sorted((r["arm"], r.get("seed", -1), r.get("returns", r.get("still"))) for r in records)

    assert returns(there) == returns(here) and len(returns(here)) == 6  # 2 arms x 2 seeds, a no-action episode each
    assert (there / "prepare" / "summary.json").is_file()
    table = [{k: v for k, v in row.items() if k != "wall_time"} for row in csv.DictReader((there / "table.csv").open())]
    assert table == [{k: v for k, v in row.items() if k != "wall_time"} for row in csv.DictReader((here / "table.csv").open())]
    code, _, err = cli("study", str(toy_study), "--dir", str(there), "--backend", "slurm")
    assert code != 0 and "--backend 'slurm': choose from local, ray" in err
