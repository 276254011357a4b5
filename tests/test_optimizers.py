"""Optimizers on the physics-free toy environment: CMA-ES improves, every optimizer resumes
exactly, bad settings fail before any simulation, and `codesign eval` replays the best."""
import json
import shutil

import numpy as np
import pytest
import torch

from codesign import runner
from codesign.errors import CodesignError, RecipeError
from codesign.recipe import resolve_recipe

TOY_CMA = {
    "name": "toy-cma",
    "seed": 3,
    "environment": {"name": "toy", "horizon": 4, "target_range": 0.02},
    "representation": {"name": "constant"},
    "controller": {"name": "trajectory", "steps": 4, "init_std": 1.0},
    "optimizer": {"name": "cma_es", "generations": 12, "population": 8, "sigma0": 0.2},
}
TOY_NEAT = {**TOY_CMA, "name": "toy-neat", "representation": {"name": "neat_cppn"},
            "optimizer": {"name": "cppn_neat", "generations": 8, "population": 8, "sigma0": 0.2}}


def metrics(run_dir) -> list[dict]:
    return [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]


def test_cma_es_improves_on_its_first_generation(tmp_path):
    run_dir = runner.run(resolve_recipe(TOY_CMA), run_dir=tmp_path / "run", progress=False)
    rows = metrics(run_dir)
    assert len(rows) == 12
    first, last = rows[0]["mean_return"], np.mean([r["mean_return"] for r in rows[-3:]])
    assert last > first + 0.15 * abs(first), (first, last)  # measured: -0.324 -> -0.236
    assert rows[-1]["best_return"] >= max(r["episode_return"] for r in rows) - 1e-12


def test_eval_replays_the_best_design_and_controller(tmp_path, cli):
    run_dir = runner.run(resolve_recipe(TOY_CMA), run_dir=tmp_path / "run", progress=False)
    info = json.loads((run_dir / "best" / "info.json").read_text())
    assert (run_dir / "best" / "design.ply").stat().st_size > 0
    code, out, err = cli("eval", str(run_dir), "--episodes", "2")
    assert code == 0, err
    returns = [float(line.split("return ")[1].split(",")[0]) for line in out.splitlines() if line.startswith("episode")]
    assert len(returns) == 2
    # the toy's target is random per episode, so replays differ, but stay near the best found
    assert max(returns) > info["episode_return"] - 0.1


@pytest.mark.parametrize("recipe", [TOY_CMA, TOY_NEAT, {**TOY_CMA, "optimizer": {"name": "evaluate", "episodes": 6}}],
                         ids=["cma_es", "cppn_neat", "evaluate"])
def test_resumed_run_ends_with_the_numbers_of_an_uninterrupted_one(tmp_path, recipe):
    whole = runner.run(resolve_recipe(recipe), run_dir=tmp_path / "whole", progress=False)
    half = dict(recipe, optimizer={**recipe["optimizer"]})
    key = "episodes" if recipe["optimizer"]["name"] == "evaluate" else "generations"
    half["optimizer"][key] = 3
    part = runner.run(resolve_recipe(half), run_dir=tmp_path / "part", progress=False)
    config = part / "config.yaml"
    total = recipe["optimizer"][key]
    config.write_text(config.read_text().replace(f"{key}: 3", f"{key}: {total}"))  # the run goes on
    runner.resume(part, progress=False)
    drop = ("wall_time",)
    assert [{k: v for k, v in r.items() if k not in drop} for r in metrics(part)] == \
        [{k: v for k, v in r.items() if k not in drop} for r in metrics(whole)]


@pytest.mark.parametrize("optimizer, pattern", [
    ({"name": "diff_physics", "lr_control": -0.1}, r"optimizer.lr_control: -0.1 is out of range"),
    ({"name": "cma_es", "population": 1}, r"optimizer.population: 1 is out of range; must be >= 2"),
    ({"name": "cma_es", "optimize": "sideways"}, r"optimizer.optimize: 'sideways' is not a valid choice"),
    ({"name": "cma_es", "lower": 1.0, "upper": -1.0}, r"optimizer.lower/upper"),
    ({"name": "cppn_neat", "optimize": "body"}, r"optimizer.optimize: 'body' is not a valid choice"),
    ({"name": "cppn_neat", "elitism": 10}, r"optimizer.elitism: 10 must be below optimizer.population \(10\)"),
])
def test_bad_optimizer_settings_fail_with_the_key_and_what_is_allowed(tmp_path, optimizer, pattern):
    with pytest.raises(RecipeError, match=pattern):
        recipe = resolve_recipe({**TOY_CMA, "optimizer": optimizer})
        runner.run(recipe, run_dir=tmp_path / "run", progress=False)


@pytest.mark.parametrize("optimizer, pattern", [
    ({"name": "cma_es", "optimize": "design"}, r"trains the representation, but representation "
                                               r"'ConstantRepresentation' has no trainable parameters"),
    ({"name": "diff_physics"}, r"diff_physics needs an environment with differentiable episodes"),
    ({"name": "cppn_neat"}, r"representation.name: cppn_neat evolves NEAT genomes and needs the neat_cppn "
                            r"representation; 'ConstantRepresentation' has no genome"),
])
def test_a_mode_the_parts_cannot_do_fails_before_any_episode(tmp_path, optimizer, pattern):
    with pytest.raises(RecipeError, match=pattern):
        runner.run(resolve_recipe({**TOY_CMA, "optimizer": optimizer}), run_dir=tmp_path / "run", progress=False)
    assert not (tmp_path / "run" / "best").exists()


def test_a_fixed_body_trains_its_controller_alone_and_keeps_its_design(tmp_path):
    """The `fixed` representation's design is numpy and has no parameters: CMA-ES trains the controller
    (its default mode, control) and keeps the body as the environment gives it."""
    recipe = {**TOY_CMA, "representation": {"name": "fixed"}, "optimizer": {**TOY_CMA["optimizer"], "generations": 3}}
    run_dir = runner.run(resolve_recipe(recipe), run_dir=tmp_path / "run", progress=False)
    assert len(metrics(run_dir)) == 3
    design = np.load(run_dir / "best" / "design.npz")
    assert (design["occupancy"] == 1).all() and np.allclose(design["muscle"].sum(1), 1)  # the toy's grid muscles
    with pytest.raises(RecipeError, match=r"representation 'FixedRepresentation' has no trainable parameters"):
        runner.run(resolve_recipe({**recipe, "optimizer": {"name": "cma_es", "optimize": "both"}}),
                   run_dir=tmp_path / "both", progress=False)


def test_eval_of_a_run_without_a_best_says_so(tmp_path):
    run_dir = runner.run(resolve_recipe({**TOY_CMA, "optimizer": {"name": "evaluate"}}), run_dir=tmp_path / "r",
                         progress=False)
    shutil.rmtree(run_dir / "best")  # as a run stopped before its first episode ended
    with pytest.raises(CodesignError, match="saved no best design"):
        runner.evaluate_best(run_dir)


def test_trajectory_and_mlp_controllers_respect_their_bound_and_seed():
    from codesign_basics.config import MLPConfig, TrajectoryConfig
    from codesign_basics.mlp import MLPController
    from codesign_basics.trajectory import TrajectoryController

    for make in (lambda: TrajectoryController(TrajectoryConfig(steps=5, bound=0.2, init_std=10.0)),
                 lambda: MLPController(MLPConfig(bound=0.2, init_std=10.0)),
                 lambda: MLPController(MLPConfig(bound=0.2, init_std=10.0, output="sine_weights"))):
        a, b = make(), make()
        for c in (a, b):
            c.setup(3, 6, 0.01, np.random.default_rng(5))
        obs = np.random.default_rng(0).normal(size=6) * 10
        for t in range(5):
            u = a(obs, t).detach().numpy()
            assert np.abs(u).max() <= 0.2 and np.abs(u).max() > 0.1  # saturates towards the bound
            np.testing.assert_array_equal(u, b(obs, t).detach().numpy())


def test_evaluate_writes_each_episodes_return_and_trajectory_and_keeps_the_best(tmp_path):
    recipe = {**TOY_CMA, "optimizer": {"name": "evaluate", "episodes": 2}}
    run_dir = runner.run(resolve_recipe(recipe), run_dir=tmp_path / "run", progress=False)
    rows = metrics(run_dir)
    for i, row in enumerate(rows):
        data = np.load(run_dir / f"trajectory-{i}.npz")
        assert data["actions"].shape == (4, 2) and data["com"].shape == (4, 3)
        assert float(data["episode_return"]) == pytest.approx(row["episode_return"])
    best = max(row["episode_return"] for row in rows)
    assert runner.load_best_info(run_dir)["episode_return"] == pytest.approx(best)
    assert float(np.load(run_dir / "best" / "trajectory.npz")["episode_return"]) == pytest.approx(best)
    assert len(runner.evaluate_best(run_dir)) == 1  # its run replays as any optimizer's (the toy is random)


class Knob:
    """A one-parameter representation: the design is the parameter."""

    def __init__(self, value):
        self.x = torch.tensor([value], requires_grad=True)

    def parameters(self):
        return [self.x]

    def __call__(self):
        return self.x


class Cliff:
    """The return grows with the design x, but x above 1 is unplayable (as a design thinner than the grid is)."""

    horizon = 1

    def __init__(self):
        from types import SimpleNamespace

        self.design_space = SimpleNamespace(points=np.zeros((1, 3)))

    def differentiable_episode(self, design, controller, checkpoint_every):
        from types import SimpleNamespace

        from codesign.errors import DesignError

        if design.item() > 1.0:
            raise DesignError(f"design {design.item():.3g} is past the cliff")
        return SimpleNamespace(loss=-design.sum(), episode_return=design.item(), com=torch.zeros(2, 3),
                               actions=np.zeros((1, 0)), metrics={})


def cliff_climber(start: float, iterations: int = 12):
    from types import SimpleNamespace

    from codesign_optimizers.config import DiffPhysicsConfig
    from codesign_optimizers.diff_physics import DiffPhysics

    optimizer = DiffPhysics(DiffPhysicsConfig(optimize="design", iterations=iterations, lr_design=0.3))
    optimizer.setup(Cliff(), Knob(start), SimpleNamespace(parameters=lambda: []), rng=np.random.default_rng(0),
                    run_dir=None)
    return optimizer


def test_diff_physics_takes_back_a_step_that_leaves_the_design_unplayable():
    """A refused design: the step is undone, parameters and Adam's moments alike, the design's
    learning rate halved, and the run goes on from the last playable design; a refused first
    design is an error that says so."""
    from codesign.errors import DesignError

    optimizer = cliff_climber(0.5)

    def adam_state():
        return {k: v.clone() for k, v in optimizer.adam.state[optimizer.representation.x].items()}

    rows, adam = [], [{}]  # adam[i]: Adam's state when step i starts
    for _ in range(12):
        rows.append(optimizer.step())
        adam.append(adam_state())
    refused = [i for i, row in enumerate(rows) if row.get("unplayable")]
    assert refused and rows[refused[0]]["lr_design"] == pytest.approx(0.15)
    for i in refused:  # step i-1 made the refused design: Adam is back where it was before that step
        assert adam[i + 1].keys() == adam[i - 1].keys() == {"step", "exp_avg", "exp_avg_sq"}
        assert all(torch.equal(adam[i + 1][key], adam[i - 1][key]) for key in adam[i + 1])
    played = [row["episode_return"] for row in rows if "episode_return" in row]
    assert max(played) <= 1.0 and optimizer.best.best_return > 0.9  # it crept up to the cliff's edge
    with pytest.raises(DesignError, match=r"the first design \(iteration 0\) is unplayable: design 2 is past"):
        cliff_climber(2.0, iterations=2).step()


def test_diff_physics_undoes_a_step_refused_right_after_a_resume():
    """The undo state is checkpointed: resumed just before a refused step, the run undoes it and
    ends with the numbers of an uninterrupted run."""
    import pickle

    whole = cliff_climber(0.5)
    rows = [whole.step() for _ in range(12)]
    first_refusal = next(i for i, row in enumerate(rows) if row.get("unplayable"))
    part = cliff_climber(0.5)
    for _ in range(first_refusal):
        part.step()
    resumed = cliff_climber(0.5)
    resumed.load_state_dict(pickle.loads(pickle.dumps(part.state_dict())))
    assert [resumed.step() for _ in range(first_refusal, 12)] == rows[first_refusal:]


def test_unplayed_genomes_rank_last_without_blinding_neats_shares_to_small_returns():
    """neat-python shares offspring in proportion to each species' mean fitness minus the
    generation's minimum. The floor of unplayed genomes sits a tenth of the played spread below
    the worst, so those differences, and the shares, are the same at any return scale."""
    from codesign_optimizers.cppn_neat import neat_fitness

    nan = float("nan")
    for scale in (0.01, 1.0, 100.0):
        fitness = neat_fitness([0.3 * scale, nan, 0.1 * scale, 0.2 * scale, nan])
        assert fitness[1] == fitness[4] < min(fitness[0], fitness[2], fitness[3])
        above = np.array(fitness) - min(fitness)
        np.testing.assert_allclose(above / above.sum(), [0.611, 0, 0.056, 0.333, 0], atol=0.001)
    assert neat_fitness([nan, nan]) == [0.0, 0.0]


def test_every_brain_candidate_is_played_when_bodies_are_invalid(tmp_path):
    """A body too small to play lends its brain candidate to the next valid body: CMA-ES is told
    only returns that were played, a full population of them every generation."""
    recipe = {**TOY_NEAT, "representation": {"name": "neat_cppn", "min_body_fraction": 0.5}}
    run_dir = runner.run(resolve_recipe(recipe), run_dir=tmp_path / "run", progress=False)
    rows = metrics(run_dir)
    assert min(row["valid_fraction"] for row in rows) < 1.0  # some bodies were invalid
    played = sum(row["simulated_steps"] for row in rows) / recipe["environment"]["horizon"]
    with (run_dir / "checkpoint.pkl").open("rb") as f:
        es = __import__("pickle").load(f)["optimizer"]["es"]
    assert es.countevals == played == 8 * len(rows)


@pytest.mark.parametrize("representation, optimize", [("constant", "control"), ("neat_cppn", "both")])
def test_hyperneat_brains_evolve_and_replay_without_their_genome(tmp_path, representation, optimize):
    """cppn_neat evolves a hyperneat controller's CPPN as a NEAT population, alone (it improves
    on its first generation: measured -0.596 -> -0.426) or beside the body's; the best network's
    weights replay through `codesign eval`."""
    recipe = {**TOY_NEAT, "environment": {"name": "toy", "horizon": 4, "target_range": 0.0},
              "representation": {"name": representation}, "controller": {"name": "hyperneat"},
              "optimizer": {"name": "cppn_neat", "optimize": optimize, "generations": 10, "population": 8}}
    run_dir = runner.run(resolve_recipe(recipe), run_dir=tmp_path / "run", progress=False)
    rows = metrics(run_dir)
    if optimize == "control":  # the toy's reward ignores the body: co-evolution has nothing to find there
        assert rows[-1]["best_return"] > rows[0]["episode_return"] + 0.1, [r["episode_return"] for r in rows]
    assert all(r["brain_species"] >= 1 for r in rows) and (run_dir / "best" / "brain_genome.pkl").exists()
    assert (run_dir / "best" / "genome.pkl").exists() == (optimize == "both")
    assert runner.evaluate_best(run_dir) == pytest.approx([rows[-1]["best_return"]], rel=1e-9)
