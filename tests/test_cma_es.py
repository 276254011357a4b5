"""cma_es as pycma means it: on known functions it needs the evaluations pycma's own loop needs,
its parameters hold the bounded mean, it tells CMA only what was played, and it stops (or
restarts with a larger population) when pycma's termination criteria say so."""
import json
import math

import cma
import numpy as np
import pytest
import torch

from codesign import runner
from codesign.errors import DesignError
from codesign.interfaces import Controller, DesignFields, DesignSpace, Environment, Representation, StepResult
from codesign.recipe import resolve_recipe
from codesign_optimizers.cma_es import CMAES, coordinate_stds
from codesign_optimizers.config import CMAESConfig


def sphere(x: np.ndarray) -> float:
    return float(np.sum((x - 0.5) ** 2))  # bounded to [-0.2, 0.2]^n its optimum is the corner 0.2


def rosenbrock(x: np.ndarray) -> float:
    return float(np.sum(100 * (x[1:] - x[:-1] ** 2) ** 2 + (1 - x[:-1]) ** 2))


class Point(Representation):
    """The design is a free vector x (carried in the occupancy field)."""

    def __init__(self, start: float) -> None:
        self.start = start

    def setup(self, space: DesignSpace, rng: np.random.Generator) -> None:
        self.x = torch.full((len(space.points),), self.start, dtype=torch.float64, requires_grad=True)

    def parameters(self) -> list[torch.Tensor]:
        return [self.x]

    def __call__(self) -> DesignFields:
        n = len(self.x)
        return DesignFields(occupancy=self.x.detach().clone(), stiffness=np.ones(n), muscle=np.ones((n, 1)),
                            fiber=np.tile([1.0, 0.0, 0.0], (n, 1)))


class Still(Controller):
    open_loop = True

    def setup(self, action_dim, observation_dim, control_dt, rng) -> None:
        self.k = action_dim

    def __call__(self, observation, step):
        return np.zeros(self.k)


class Landscape(Environment):
    """One step whose reward is -f(x) for the design's x; designs with x[0] above `cliff` are refused."""

    def __init__(self, f, n: int, cliff: float = math.inf) -> None:
        self.f, self.cliff, self.played = f, cliff, 0
        self.design_space = DesignSpace(points=np.zeros((n, 3)), n_actuators=1, default_stiffness=1.0)
        self.action_dim, self.observation_dim, self.horizon, self.control_dt = 1, 1, 1, 0.01

    def reset(self, design=None, seed=None):
        self.x = np.asarray(design.occupancy, dtype=float)
        if self.x[0] > self.cliff:
            raise DesignError(f"x[0] = {self.x[0]:.3g} is past the cliff")
        self.played += 1
        return np.zeros(1)

    def step(self, action) -> StepResult:
        return StepResult(np.zeros(1), -self.f(self.x), True, {})

    def close(self) -> None:
        pass


def search(f, n: int, start: float = 0.0, cliff: float = math.inf, **config) -> CMAES:
    env = Landscape(f, n, cliff)
    representation, controller = Point(start), Still()
    representation.setup(env.design_space, np.random.default_rng(0))
    controller.setup(1, 1, 0.01, np.random.default_rng(0))
    optimizer = CMAES(CMAESConfig(optimize="design", **config))
    optimizer.setup(env, representation, controller, rng=np.random.default_rng(7), run_dir=None)
    return optimizer


def test_a_bounded_sphere_in_20_d_reaches_the_corner_as_pycmas_own_loop_does_and_never_leaves_the_bounds():
    optimizer = search(sphere, 20, sigma0=0.1, lower=-0.2, upper=0.2, generations=400)
    target = sphere(np.full(20, 0.2)) + 1e-8
    while optimizer.generation < 400 and -optimizer.best.best_return > target:
        optimizer.step()
        held = optimizer.representation.x.detach().numpy()
        assert held.min() >= -0.2 and held.max() <= 0.2  # es.mean (unbounded) would leave them
    evaluations = optimizer.es.countevals
    assert -optimizer.best.best_return <= target and optimizer.es.popsize == 4 + int(3 * math.log(20))

    es = cma.CMAEvolutionStrategy(np.zeros(20), 0.1, {"bounds": [-0.2, 0.2], "seed": 7, "verbose": -9})
    while es.best.f > target:
        candidates = es.ask()
        es.tell(candidates, [sphere(np.clip(x, -0.2, 0.2)) for x in candidates])
    assert evaluations <= 1.3 * es.countevals, (evaluations, es.countevals)  # measured: 2,460 and 2,280


def test_rosenbrock_in_10_d_reaches_its_optimum_within_pycmas_usual_evaluations():
    optimizer = search(rosenbrock, 10, sigma0=0.5, generations=2000)
    while optimizer.generation < 2000 and -optimizer.best.best_return > 1e-8:
        optimizer.step()
    assert -optimizer.best.best_return <= 1e-8
    assert optimizer.es.countevals < 10_000, optimizer.es.countevals  # measured 4,970; pycma's own fmin2: 4,871
    np.testing.assert_allclose(optimizer.es.result.xbest, np.ones(10), atol=1e-3)


def test_cma_is_told_only_the_candidates_that_were_played():
    """At a cliff up to half of the candidates are refused: none of them is told to CMA, whose
    update counts only played episodes, and the search still closes in on the edge."""
    optimizer = search(lambda x: float((x[0] - 1.2) ** 2 + np.sum(x[1:] ** 2)), 6, start=0.5, cliff=1.0,
                       sigma0=0.2, population=12, generations=60)
    rows = [optimizer.step() for _ in range(60)]
    assert sum(row["unplayable"] for row in rows) > 60  # many refusals, never told
    assert optimizer.es.countevals == optimizer.environment.played
    assert all(math.isfinite(row["mean_return"]) for row in rows)
    assert optimizer.representation.x.detach().numpy()[0] <= 1.0 and -optimizer.best.best_return < 0.05


def test_a_search_that_never_plays_enough_candidates_says_what_to_change():
    optimizer = search(sphere, 4, start=2.0, cliff=1.0, sigma0=0.1)  # every candidate past the cliff
    with pytest.raises(DesignError, match=r"only 0 of \d+ candidates had a design the environment could play, "
                                          r"CMA needs \d+; lower optimizer.sigma0"):
        optimizer.step()


def test_pycmas_termination_ends_the_search_or_restarts_it_with_twice_the_population():
    """A flat landscape: pycma's criteria stop it; one IPOP restart doubles the population and
    starts again from the initial parameters; with no restart left, the search is over."""
    optimizer = search(lambda x: 0.0, 5, start=0.3, restarts=1, generations=100)
    first = optimizer.es.popsize
    rows = []
    while not optimizer.stopped and len(rows) < 100:
        rows.append(optimizer.step())
    assert [row["restart"] for row in rows].count(1.0) > 0 and optimizer.es.popsize == 2 * first
    assert rows[-1]["population"] == 2 * first and optimizer.stopped.startswith("pycma's termination criteria: ")
    assert len(rows) < 30  # measured: 2 generations (pycma stops a flat search at once)


def test_both_groups_step_at_their_own_scale():
    control = [torch.full((4,), 0.1), torch.zeros(4)]  # rms 0.1 / sqrt(2)
    design = [torch.full((3,), 2.0)]
    stds = coordinate_stds({"control": control, "design": design}, None)
    np.testing.assert_allclose(stds, [1.0] * 8 + [2.0 / (0.1 / math.sqrt(2))] * 3)
    np.testing.assert_allclose(coordinate_stds({"control": control, "design": design}, 5.0), [1.0] * 8 + [5.0] * 3)
    assert coordinate_stds({"design": design}, None) is None


def test_above_the_stated_dimension_the_covariance_is_diagonal():
    assert search(sphere, 30, diagonal_above=20).es.opts["CMA_diagonal"] is True
    assert search(sphere, 10, diagonal_above=20).es.opts["CMA_diagonal"] is False


def test_the_runner_ends_a_stopped_search_and_says_why(tmp_path):
    recipe = {"name": "toy-flat", "seed": 1, "environment": {"name": "toy", "horizon": 1, "target_range": 0.0},
              "representation": {"name": "constant"}, "controller": {"name": "trajectory", "steps": 1,
                                                                    "init_std": 0.0, "bound": 1e-9},
              "optimizer": {"name": "cma_es", "generations": 200, "sigma0": 0.1}}
    run_dir = runner.run(resolve_recipe(recipe), run_dir=tmp_path / "run", progress=False)
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["status"] == "completed" and summary["iterations_completed"] < 200
    assert "pycma's termination criteria" in summary["stopped"]
    runner.resume(run_dir, progress=False)  # nothing left to do
    assert json.loads((run_dir / "summary.json").read_text())["iterations_completed"] == \
        summary["iterations_completed"]
