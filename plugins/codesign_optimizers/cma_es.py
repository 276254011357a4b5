"""CMA-ES (the `cma` library) on the flattened controller and/or design parameters."""

from __future__ import annotations

from pathlib import Path

import cma
import numpy as np
import torch
from torch.nn.utils import parameters_to_vector, vector_to_parameters

from codesign.artifacts import BestKeeper, EpisodeRecord, play_population
from codesign.errors import DesignError, RecipeError
from codesign.interfaces import Controller, Environment, Optimizer, Representation
from codesign_optimizers.common import candidate, fewest_to_tell, parameter_groups
from codesign_optimizers.config import CMAESConfig

ASK_ROUNDS = 5
"""Populations asked at most per generation to collect CMA's mu playable candidates."""


def coordinate_stds(groups: dict[str, list[torch.Tensor]], design_scale: float | None) -> np.ndarray | None:
    """pycma's CMA_stds for the flattened groups (control first): 1 on the controller's
    parameters, `design_scale` on the design's (None: the ratio of the groups' RMS initial values,
    a group of zeros counting as 1). None when one group is searched: sigma0 alone sets the step."""
    if len(groups) < 2:
        return None
    if design_scale is None:
        rms = {}
        for name, params in groups.items():
            flat = torch.cat([p.detach().reshape(-1) for p in params]).double()
            rms[name] = float(flat.square().mean().sqrt()) or 1.0
        design_scale = rms["design"] / rms["control"]
    sizes = {name: sum(p.numel() for p in params) for name, params in groups.items()}
    return np.concatenate([np.ones(sizes["control"]), np.full(sizes["design"], design_scale)])


class CMAES(Optimizer):
    """One generation per iteration: ask a population, play one episode each (together, `batch`
    at a time, where the environment batches; else one after the other), tell CMA their returns.
    All candidates of a generation play with the same episode seed (common random numbers), so
    a random environment ranks them by their parameters, not by their luck.

    CMA is told only what was played: a candidate whose design the environment refuses is left
    out (pycma's update needs at least mu of them; fewer, and more candidates are asked). The
    parameters hold pycma's favourite, its mean repaired into the bounds (`xfavorite`), never
    its internal unbounded mean. pycma's termination criteria (`es.stop()`) end the search, or
    start an IPOP restart where `restarts` allows. The search starts from the current
    parameters. cma draws from numpy's global generator, whose state is part of the checkpoint
    so a resumed run draws the same candidates.
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
        groups = parameter_groups(self.config.optimize, representation, controller)
        self.params = [p for group in groups.values() for p in group]
        self.x0 = parameters_to_vector(self.params).detach().double().numpy()
        self.stds = coordinate_stds(groups, self.config.design_scale)
        self.es = self._search(self.config.population)
        self.best = BestKeeper(environment, controller, run_dir)
        self.generation, self.restart, self.stopped = 0, 0, None

    def _search(self, popsize: int | None) -> cma.CMAEvolutionStrategy:
        """A fresh search from the initial parameters (`popsize` None: pycma's default)."""
        n = len(self.x0)
        options = {"seed": int(self.rng.integers(1, 2**31)), "verbose": -9,
                   "CMA_diagonal": n > self.config.diagonal_above}
        if popsize is not None:
            options["popsize"] = popsize
        if self.stds is not None:
            options["CMA_stds"] = self.stds
        if self.config.lower is not None:
            options["bounds"] = [self.config.lower, self.config.upper]
        return cma.CMAEvolutionStrategy(self.x0, self.config.sigma0, options)

    def _play_generation(self) -> tuple[list[np.ndarray], list[EpisodeRecord], int]:
        """At least mu, at most a population of played candidates, their records, and how many were refused."""
        seed = int(self.rng.integers(2**31))  # one episode seed per generation: candidates compare on equal terms
        mu, popsize = fewest_to_tell(self.es), self.es.popsize
        solutions, records, asked, refused = [], [], 0, 0
        for _ in range(ASK_ROUNDS):
            candidates = self.es.ask(popsize - len(solutions))  # a first population, then what it lacks
            asked += len(candidates)
            pairs = [candidate(self.representation, self.controller, self.params, x) for x in candidates]
            for x, (design, controller), record in zip(candidates, pairs, play_population(
                    self.environment, [d for d, _ in pairs], [c for _, c in pairs], seed, self.config.batch)):
                refused += not record.played
                if record.played:
                    solutions.append(x)
                    records.append(record)
                    self.best.offer(record.episode_return, design, record, self.generation, controller)
            if len(solutions) >= mu:
                return solutions, records, refused
        raise DesignError(f"cma_es: generation {self.generation}: only {len(solutions)} of {asked} candidates "
                          f"had a design the environment could play, CMA needs {mu}; lower optimizer.sigma0 or "
                          "bound the parameters (optimizer.lower/upper)")

    def step(self) -> dict[str, float]:
        solutions, records, refused = self._play_generation()
        returns = np.array([record.episode_return for record in records])
        self.es.tell(solutions, list(-returns))  # cma minimises
        self.generation += 1
        metrics = {"episode_return": float(returns.max()), "mean_return": float(returns.mean()),
                   "std_return": float(returns.std()), "best_return": self.best.best_return,
                   "sigma": float(self.es.sigma), "population": float(self.es.popsize),
                   "unplayable": float(refused),
                   "restart": float(self.restart),
                   "simulated_steps": float(sum(record.length for record in records)),
                   **records[int(returns.argmax())].metrics}
        stop = self.es.stop()
        if stop and self.restart < self.config.restarts:
            self.restart += 1
            self.es = self._search(2 * self.es.popsize)
        elif stop:
            self.stopped = "pycma's termination criteria: " + ", ".join(f"{k}={v}" for k, v in stop.items())
        self._hold(self.es.result.xfavorite if self.es.countiter else self.x0)
        return metrics

    def _hold(self, x: np.ndarray) -> None:
        """Leave the parameters at `x` (the distribution's bounded mean), as `codesign eval` of the
        last iterate and a resumed run see them."""
        with torch.no_grad():
            vector_to_parameters(torch.as_tensor(x, dtype=self.params[0].dtype), self.params)

    def state_dict(self) -> dict:
        return {"es": self.es, "generation": self.generation, "restart": self.restart, "stopped": self.stopped,
                "best_return": self.best.best_return, "numpy_random": np.random.get_state(),
                "params": parameters_to_vector(self.params).detach().clone()}

    def load_state_dict(self, state: dict) -> None:
        self.es, self.generation, self.best.best_return = state["es"], state["generation"], state["best_return"]
        self.restart, self.stopped = state.get("restart", 0), state.get("stopped")
        np.random.set_state(state["numpy_random"])
        with torch.no_grad():
            vector_to_parameters(state["params"], self.params)
