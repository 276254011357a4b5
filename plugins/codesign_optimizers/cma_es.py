"""CMA-ES (the `cma` library) on the flattened controller and/or design parameters."""

from __future__ import annotations

from pathlib import Path

import cma
import numpy as np
import torch
from torch.nn.utils import parameters_to_vector, vector_to_parameters

from codesign.artifacts import play_population, rank_last
from codesign.errors import RecipeError
from codesign.interfaces import Controller, Environment, Optimizer, Representation
from codesign_optimizers.common import BestKeeper, candidate, parameter_groups
from codesign_optimizers.config import CMAESConfig


class CMAES(Optimizer):
    """One generation per iteration: ask `population` candidates, play one episode each (together,
    `batch` at a time, where the environment batches; else one after the other), tell CMA their returns.
    All candidates of a generation play with the same episode seed (common random numbers), so
    a random environment ranks them by their parameters, not by their luck.

    The search starts from the current parameters. cma draws from numpy's global generator,
    whose state is part of the checkpoint so a resumed run draws the same candidates.
    """

    def __init__(self, config: CMAESConfig) -> None:
        if (config.lower is None) != (config.upper is None) or (
                config.lower is not None and not config.lower < config.upper):
            raise RecipeError(f"invalid recipe: optimizer.lower/upper: ({config.lower!r}, {config.upper!r}) must "
                              "both be null or satisfy lower < upper")
        self.config = config
        self.iterations = config.generations

    def setup(self, environment: Environment, representation: Representation, controller: Controller, *,
              rng: np.random.Generator, run_dir: Path) -> None:
        self.environment, self.representation, self.controller, self.rng = environment, representation, controller, rng
        self.params = [p for group in parameter_groups(self.config.optimize, representation, controller).values()
                       for p in group]
        x0 = parameters_to_vector(self.params).detach().double().numpy()
        options = {"popsize": self.config.population, "seed": int(rng.integers(1, 2**31)), "verbose": -9}
        if self.config.lower is not None:
            options["bounds"] = [self.config.lower, self.config.upper]
        self.es = cma.CMAEvolutionStrategy(x0, self.config.sigma0, options)
        self.best = BestKeeper(environment, controller, run_dir)
        self.generation = 0

    def step(self) -> dict[str, float]:
        candidates = self.es.ask()
        seed = int(self.rng.integers(2**31))  # one episode seed per generation: candidates compare on equal terms
        pairs = [candidate(self.representation, self.controller, self.params, x) for x in candidates]
        records = play_population(self.environment, [d for d, _ in pairs], [c for _, c in pairs], seed,
                                  self.config.batch)
        returns = rank_last([record.episode_return for record in records])
        for (design, controller), record in zip(pairs, records):
            self.best.offer(record.episode_return, design, record, self.generation, controller)
        self.es.tell(candidates, [-r for r in returns])  # cma minimises
        with torch.no_grad():  # leave the parts at the distribution's mean
            vector_to_parameters(torch.as_tensor(self.es.mean, dtype=self.params[0].dtype), self.params)
        self.generation += 1
        r = np.asarray(returns)
        return {"episode_return": float(r.max()), "mean_return": float(r.mean()), "std_return": float(r.std()),
                "best_return": self.best.best_return, "sigma": float(self.es.sigma),
                "simulated_steps": float(sum(record.length for record in records)),
                **records[int(r.argmax())].metrics}

    def state_dict(self) -> dict:
        return {"es": self.es, "generation": self.generation, "best_return": self.best.best_return,
                "numpy_random": np.random.get_state(), "params": parameters_to_vector(self.params).detach().clone()}

    def load_state_dict(self, state: dict) -> None:
        self.es, self.generation = state["es"], state["generation"]
        self.best.best_return = state["best_return"]
        np.random.set_state(state["numpy_random"])
        with torch.no_grad():
            vector_to_parameters(state["params"], self.params)
