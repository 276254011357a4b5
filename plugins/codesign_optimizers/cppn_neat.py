"""CPPN-NEAT co-design (the paper's evolution-strategy baseline): neat-python evolves the CPPN
genomes of the neat_cppn representation while CMA-ES evolves the controller, one population;
with the hyperneat controller, NEAT evolves the brain's CPPN too (HyperNEAT)."""

from __future__ import annotations

import configparser
import copy
import math
import pickle
import random
from pathlib import Path

import cma
import numpy as np
import torch
from torch.nn.utils import parameters_to_vector, vector_to_parameters

from codesign.artifacts import BEST, BestKeeper, EpisodeRecord, play_population
from codesign.errors import RecipeError
from codesign.interfaces import Controller, DesignFields, DesignSpace, Environment, Optimizer, Representation
from codesign_optimizers.common import candidate, fewest_to_tell, frozen_design, parameter_groups
from codesign_optimizers.config import CPPNNEATConfig

GENOME_FILE = "genome.pkl"
BRAIN_GENOME_FILE = "brain_genome.pkl"
FLOOR_SHARE = 0.1
"""An unplayed genome's fitness lies this share of the played returns' spread below the worst."""


def neat_fitness(returns: list[float]) -> list[float]:
    """Fitness for neat-python: played returns as they are, unplayed ones (nan) FLOOR_SHARE of the
    played spread below the worst. neat-python shares offspring among species in proportion to
    their mean fitness minus the generation's minimum; a floor a fixed distance below (1.0,
    say) would dwarf returns whose spread is 0.2 and make those shares blind to return."""
    played = [r for r in returns if not math.isnan(r)]
    if not played:
        return [0.0] * len(returns)
    lo, hi = min(played), max(played)
    floor = lo - FLOOR_SHARE * (hi - lo) if hi > lo else lo - 1e-9
    return [floor if math.isnan(r) else r for r in returns]


def actuator_positions(design: DesignFields, space: DesignSpace) -> np.ndarray:
    """(K, 2) each muscle's centroid over the occupied particles, (x, z) mapped from the workspace
    box onto [-1, 1]^2 (a muscle without particles: the centre): where a HyperNEAT substrate puts
    the actuators, so the brain's wiring follows the body's layout."""
    lo, hi = space.box()
    kept = np.asarray(design.occupancy) >= 0.5
    points = (space.points[kept] - lo) / np.maximum(hi - lo, 1e-12) * 2.0 - 1.0
    muscle = np.asarray(design.muscle)[kept]
    mass = muscle.sum(0)
    centroid = muscle.T @ points[:, [0, 2]] / np.maximum(mass, 1e-12)[:, None]
    return np.clip(np.where(mass[:, None] > 0, centroid, 0.0), -1.0, 1.0)


class NEATPopulation:
    """One neat-python population over the genomes of `part` (the neat_cppn representation or the
    hyperneat controller). neat-python reads its settings from an ini file; the run writes it
    (`name`.ini in the run directory) from the part's genome settings and the optimizer's
    population settings, so the recipe is the only place they live."""

    def __init__(self, part, config: CPPNNEATConfig, path: Path) -> None:
        import neat

        parser = configparser.ConfigParser()
        parser["NEAT"] = {"fitness_criterion": "max", "fitness_threshold": "inf", "no_fitness_termination": "True",
                          "pop_size": str(config.population), "reset_on_extinction": "True"}
        parser["DefaultGenome"] = part.genome_section()
        parser["DefaultSpeciesSet"] = {"compatibility_threshold": str(config.compatibility_threshold)}
        parser["DefaultStagnation"] = {"species_fitness_func": "max", "max_stagnation": str(config.max_stagnation),
                                       "species_elitism": str(config.species_elitism)}
        parser["DefaultReproduction"] = {"elitism": str(config.elitism),
                                         "survival_threshold": str(config.survival_threshold)}
        path.parent.mkdir(parents=True, exist_ok=True)
        with path.open("w", encoding="utf-8") as f:
            f.write("# Written by the cppn_neat optimizer from the run's recipe; edit the recipe, not this file.\n")
            parser.write(f)
        self.config = neat.Config(neat.DefaultGenome, neat.DefaultReproduction, neat.DefaultSpeciesSet,
                                  neat.DefaultStagnation, str(path))
        self.population = neat.Population(self.config)

    def genomes(self) -> list:
        return list(self.population.population.values())

    def advance(self) -> None:
        """Reproduce from the fitness already written on the genomes (one neat-python generation)."""
        self.population.run(lambda genomes, config: None, 1)

    def stats(self, prefix: str) -> dict[str, float]:
        genomes = self.genomes()
        return {f"{prefix}species": float(len(self.population.species.species)),
                f"{prefix}mean_nodes": float(np.mean([len(g.nodes) for g in genomes])),
                f"{prefix}mean_connections": float(np.mean([sum(c.enabled for c in g.connections.values())
                                                            for g in genomes]))}


class CPPNNEAT(Optimizer):
    """One generation per iteration. As in the paper, the body's NEAT and the brain's search
    share one population (no inner loop): body genome i plays with brain candidate i, and the
    episode's return is the fitness of both. The brain is CMA-ES on the controller's parameters
    or, for a controller with a genome (`hyperneat`), a second NEAT population. All pairs of a
    generation play with the same episode seed.

    A body genome whose connected body is too small (`valid` False) is not simulated; its brain
    partner then plays with the next valid body in turn, so every brain candidate is played and
    CMA-ES is never told a return that was not played, and each valid body's fitness is the mean
    of its episodes. Unplayed genomes rank last by `neat_fitness`. With `optimize: design` the
    controller stays as it is and each valid body plays once; with `optimize: control` the
    representation's design stays and only the brain evolves.

    neat-python draws from the `random` module and cma from numpy's global generator: both
    states are checkpointed, so a resumed run evolves exactly as an uninterrupted one.
    """

    def __init__(self, config: CPPNNEATConfig) -> None:
        if config.elitism >= config.population:
            raise RecipeError(f"invalid recipe: optimizer.elitism: {config.elitism!r} must be below "
                              f"optimizer.population ({config.population!r})")
        self.config = config
        self.iterations = config.generations

    def setup(self, environment: Environment, representation: Representation, controller: Controller, *,
              rng: np.random.Generator, run_dir: Path) -> None:
        mode = self.config.optimize
        if mode != "control" and not hasattr(representation, "set_genome"):
            raise RecipeError(f"invalid recipe: representation.name: cppn_neat evolves NEAT genomes and needs the "
                              f"neat_cppn representation; '{type(representation).__name__}' has no genome")
        self.environment, self.representation, self.controller, self.rng = environment, representation, controller, rng
        self.run_dir = Path(run_dir)
        random.seed(int(rng.integers(2**31)))
        self.body = NEATPopulation(representation, self.config, self.run_dir / "neat.ini") \
            if mode != "control" else None
        self.brain = self.es = None
        self.params: list[torch.Tensor] = []
        if mode != "design" and hasattr(controller, "set_genome"):
            self.brain = NEATPopulation(controller, self.config, self.run_dir / "neat_brain.ini")
        elif mode != "design":
            self.params = parameter_groups("control", representation, controller)["control"]
            x0 = parameters_to_vector(self.params).detach().double().numpy()
            self.es = cma.CMAEvolutionStrategy(x0, self.config.sigma0, {
                "popsize": self.config.population, "seed": int(rng.integers(1, 2**31)), "verbose": -9})
        self.best = BestKeeper(environment, controller, run_dir)
        self.generation = 0

    def _bodies(self) -> tuple[list[DesignFields | None], list[float]]:
        """Each body genome's frozen design (None: invalid) and occupied fraction; without a body
        population, the representation's one design."""
        if self.body is None:
            design = frozen_design(self.representation)
            return [design], [float(np.mean(design.occupancy >= 0.5))]
        designs, fractions = [], []
        for genome in self.body.genomes():
            self.representation.set_genome(genome, self.body.config.genome_config)
            design = frozen_design(self.representation)
            designs.append(design if self.representation.valid else None)
            fractions.append(float(np.mean(design.occupancy >= 0.5)))
        return designs, fractions

    def _brain(self, j: int, design: DesignFields, x: np.ndarray | None) -> Controller:
        """A copy of the controller as brain candidate j: brain genome j painted for `design`'s
        muscles, or CMA's candidate `x`, or the controller as it is."""
        if self.brain is not None:
            self.controller.set_genome(self.brain.genomes()[j], self.brain.config.genome_config)
            self.controller.set_substrate(actuator_positions(design, self.environment.design_space))
            return copy.deepcopy(self.controller)
        return candidate(self.representation, self.controller, self.params, x)[1]

    def step(self) -> dict[str, float]:
        designs, fractions = self._bodies()
        valid = [i for i, d in enumerate(designs) if d is not None]
        evolves_brain = self.brain is not None or self.es is not None
        n = (self.config.population if evolves_brain else len(valid)) if valid else 0
        xs = self.es.ask(n) if self.es is not None and n else [None] * n
        pairs = [(valid[j % len(valid)], self._brain(j, designs[valid[j % len(valid)]], xs[j])) for j in range(n)]
        records = play_population(self.environment, [designs[i] for i, _ in pairs], [c for _, c in pairs],
                                  int(self.rng.integers(2**31)), self.config.batch)
        body_returns: list[list[float]] = [[] for _ in designs]
        for j, ((i, controller), record) in enumerate(zip(pairs, records)):
            if not record.played:
                continue
            body_returns[i].append(record.episode_return)
            if self.best.offer(record.episode_return, designs[i], record, self.generation, controller):
                self._keep_genomes(i, j)
        self._tell(records, xs, [float(np.mean(r)) if r else math.nan for r in body_returns])
        self.generation += 1
        return self._metrics(records, designs, fractions)

    def _keep_genomes(self, body: int, brain: int) -> None:
        """Pickle the best episode's genomes next to its design and controller."""
        for population, index, name in ((self.body, body, GENOME_FILE), (self.brain, brain, BRAIN_GENOME_FILE)):
            if population is not None:
                (self.run_dir / BEST / name).write_bytes(pickle.dumps(population.genomes()[index]))

    def _tell(self, records: list[EpisodeRecord], xs: list, body_returns: list[float]) -> None:
        """Write fitness on the genomes, tell CMA the played candidates, advance both populations."""
        brain_returns = [record.episode_return for record in records]
        if self.body is not None:
            for genome, f in zip(self.body.genomes(), neat_fitness(body_returns)):
                genome.fitness = f
        if self.brain is not None:
            brain_returns += [math.nan] * (self.config.population - len(records))  # no valid body to play with
            for genome, f in zip(self.brain.genomes(), neat_fitness(brain_returns)):
                genome.fitness = f
        played = [(x, r) for x, r in zip(xs, brain_returns) if not math.isnan(r)]
        if self.es is not None and len(played) >= fewest_to_tell(self.es):
            self.es.tell([x for x, _ in played], [-r for _, r in played])  # cma minimises
            with torch.no_grad():  # leave the controller at the distribution's bounded mean
                vector_to_parameters(torch.as_tensor(self.es.result.xfavorite, dtype=self.params[0].dtype),
                                     self.params)
        for population in (self.body, self.brain):
            if population is not None:
                population.advance()

    def _metrics(self, records: list[EpisodeRecord], designs: list, fractions: list[float]) -> dict[str, float]:
        played = [record for record in records if record.played]
        r = np.asarray([record.episode_return for record in played]) if played else np.asarray([np.nan])
        valid = [f for d, f in zip(designs, fractions) if d is not None]
        metrics = {"episode_return": float(r.max()), "mean_return": float(r.mean()), "std_return": float(r.std()),
                   "best_return": self.best.best_return,
                   "valid_fraction": len(valid) / len(designs),
                   "body_fraction": float(np.mean(valid)) if valid else 0.0,
                   "full_bodies": float(np.mean([f == 1.0 for f in fractions])),
                   "simulated_steps": float(sum(record.length for record in records)),
                   **(max(played, key=lambda record: record.episode_return).metrics if played else {})}
        if self.body is not None:
            metrics.update(self.body.stats(""))
        if self.brain is not None:
            metrics.update(self.brain.stats("brain_"))
        if self.es is not None:
            metrics["sigma"] = float(self.es.sigma)
        return metrics

    def state_dict(self) -> dict:
        return {"body": self.body and self.body.population, "brain": self.brain and self.brain.population,
                "python_random": random.getstate(), "es": self.es, "numpy_random": np.random.get_state(),
                "best_return": self.best.best_return, "generation": self.generation,
                "controller": parameters_to_vector(self.params).detach().clone() if self.params else None}

    def load_state_dict(self, state: dict) -> None:
        for population, saved in ((self.body, state["body"]), (self.brain, state["brain"])):
            if population is not None:
                population.population = saved
        self.es, self.generation = state["es"], state["generation"]
        random.setstate(state["python_random"])
        np.random.set_state(state["numpy_random"])
        self.best.best_return = state["best_return"]
        if self.params:
            with torch.no_grad():
                vector_to_parameters(state["controller"], self.params)
