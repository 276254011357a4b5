"""CPPN-NEAT co-design (the paper's evolution-strategy baseline): neat-python evolves the CPPN
genomes of the neat_cppn representation while CMA-ES evolves the controller, one population."""

from __future__ import annotations

import configparser
import math
import pickle
import random
from pathlib import Path

import cma
import numpy as np
import torch
from torch.nn.utils import parameters_to_vector, vector_to_parameters

from codesign.artifacts import BEST, play_population, rank_last
from codesign.errors import RecipeError
from codesign.interfaces import Controller, Environment, Optimizer, Representation
from codesign_optimizers.common import BestKeeper, candidate, parameter_groups
from codesign_optimizers.config import CPPNNEATConfig

NEAT_CONFIG_FILE = "neat.ini"
GENOME_FILE = "genome.pkl"


class CPPNNEAT(Optimizer):
    """One NEAT generation per iteration. As in the paper, NEAT and CMA-ES share one population
    (no inner loop): genome i plays with the controller of CMA-ES's candidate i, and the
    episode's return is the fitness of both. All pairs of a generation play with the same
    episode seed. A genome whose connected body is too small is not simulated and ranks below
    every valid one.

    neat-python reads its settings from an ini file; the run writes one (`neat.ini` in the run
    directory) from the representation's genome settings and this optimizer's population
    settings, so the recipe is the only place they live. neat-python draws from the `random`
    module and cma from numpy's global generator: both states are checkpointed, so a resumed
    run evolves exactly as an uninterrupted one.
    """

    def __init__(self, config: CPPNNEATConfig) -> None:
        if config.elitism >= config.population:
            raise RecipeError(f"invalid recipe: optimizer.elitism: {config.elitism!r} must be below "
                              f"optimizer.population ({config.population!r})")
        self.config = config
        self.iterations = config.generations

    def setup(self, environment: Environment, representation: Representation, controller: Controller, *,
              rng: np.random.Generator, run_dir: Path) -> None:
        import neat

        if not hasattr(representation, "set_genome"):
            raise RecipeError(f"invalid recipe: representation.name: cppn_neat evolves NEAT genomes and needs the "
                              f"neat_cppn representation; '{type(representation).__name__}' has no genome")
        self.environment, self.representation, self.controller, self.rng = environment, representation, controller, rng
        self.run_dir = Path(run_dir)
        self.params = parameter_groups("control", representation, controller)["control"] \
            if self.config.optimize == "both" else []
        path = self.run_dir / NEAT_CONFIG_FILE
        self._write_neat_config(path)
        neat_config = neat.Config(neat.DefaultGenome, neat.DefaultReproduction, neat.DefaultSpeciesSet,
                                  neat.DefaultStagnation, str(path))
        random.seed(int(rng.integers(2**31)))
        self.population = neat.Population(neat_config)
        self.es = None
        if self.params:
            x0 = parameters_to_vector(self.params).detach().double().numpy()
            self.es = cma.CMAEvolutionStrategy(x0, self.config.sigma0, {
                "popsize": self.config.population, "seed": int(rng.integers(1, 2**31)), "verbose": -9})
        self.best = BestKeeper(environment, controller, run_dir)

    def _write_neat_config(self, path: Path) -> None:
        c = self.config
        parser = configparser.ConfigParser()
        parser["NEAT"] = {"fitness_criterion": "max", "fitness_threshold": "inf", "no_fitness_termination": "True",
                          "pop_size": str(c.population), "reset_on_extinction": "True"}
        parser["DefaultGenome"] = self.representation.genome_section()
        parser["DefaultSpeciesSet"] = {"compatibility_threshold": str(c.compatibility_threshold)}
        parser["DefaultStagnation"] = {"species_fitness_func": "max", "max_stagnation": str(c.max_stagnation),
                                       "species_elitism": str(c.species_elitism)}
        parser["DefaultReproduction"] = {"elitism": str(c.elitism), "survival_threshold": str(c.survival_threshold)}
        path.parent.mkdir(parents=True, exist_ok=True)
        with path.open("w", encoding="utf-8") as f:
            f.write("# Written by the cppn_neat optimizer from the run's recipe; edit the recipe, not this file.\n")
            parser.write(f)

    def _evaluate_generation(self, genomes: list, neat_config) -> None:
        """neat-python's fitness function: play each (genome, controller candidate) pair once."""
        seed = int(self.rng.integers(2**31))
        candidates = self.es.ask(len(genomes)) if self.es is not None else None
        pairs = {}  # genome index -> (design, controller) of the valid bodies
        for i, (_, genome) in enumerate(genomes):
            self.representation.set_genome(genome, neat_config.genome_config)
            if self.representation.valid:
                pairs[i] = candidate(self.representation, self.controller, self.params,
                                     None if candidates is None else candidates[i])
        records = play_population(self.environment, [d for d, _ in pairs.values()], [c for _, c in pairs.values()],
                                  seed, self.config.batch)
        returns = [math.nan] * len(genomes)  # invalid or unplayable bodies rank below every played one
        for (i, (design, controller)), record in zip(pairs.items(), records):
            returns[i] = record.episode_return
            if self.best.offer(record.episode_return, design, record, self.population.generation, controller):
                (self.run_dir / BEST / GENOME_FILE).write_bytes(pickle.dumps(genomes[i][1]))
        played = [record for record in records if record.played]
        best_metrics = max(played, key=lambda record: record.episode_return).metrics if played else {}
        valid = [r for r in returns if not math.isnan(r)]
        fitness = rank_last(returns)
        for (_, genome), f in zip(genomes, fitness):
            genome.fitness = f
        if self.es is not None:
            self.es.tell(candidates, [-f for f in fitness])  # cma minimises
        self._generation_stats = {"returns": np.asarray(valid), "pairs": len(genomes), "metrics": best_metrics,
                                  "nodes": np.mean([len(g.nodes) for _, g in genomes]),
                                  "connections": np.mean([sum(c.enabled for c in g.connections.values())
                                                          for _, g in genomes])}

    def step(self) -> dict[str, float]:
        self.population.run(self._evaluate_generation, 1)
        if self.es is not None:
            with torch.no_grad():  # leave the controller at the distribution's mean
                vector_to_parameters(torch.as_tensor(self.es.mean, dtype=self.params[0].dtype), self.params)
        s = self._generation_stats
        r = s["returns"] if len(s["returns"]) else np.asarray([np.nan])
        metrics = {"episode_return": float(r.max()), "mean_return": float(r.mean()), "std_return": float(r.std()),
                   "best_return": self.best.best_return, "valid_fraction": len(s["returns"]) / s["pairs"],
                   "species": float(len(self.population.species.species)), "mean_nodes": float(s["nodes"]),
                   "mean_connections": float(s["connections"]),
                   "simulated_steps": float(len(s["returns"]) * self.environment.horizon), **s["metrics"]}
        if self.es is not None:
            metrics["sigma"] = float(self.es.sigma)
        return metrics

    def state_dict(self) -> dict:
        return {"population": self.population, "python_random": random.getstate(), "es": self.es,
                "numpy_random": np.random.get_state(), "best_return": self.best.best_return,
                "controller": parameters_to_vector(self.params).detach().clone() if self.params else None}

    def load_state_dict(self, state: dict) -> None:
        self.population, self.es = state["population"], state["es"]
        random.setstate(state["python_random"])
        np.random.set_state(state["numpy_random"])
        self.best.best_return = state["best_return"]
        if self.params:
            with torch.no_grad():
                vector_to_parameters(state["controller"], self.params)
