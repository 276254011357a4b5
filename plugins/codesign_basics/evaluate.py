"""An optimizer that changes nothing: it measures the current design and controller."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from codesign.artifacts import BestKeeper, play
from codesign.interfaces import Controller, Environment, Optimizer, Representation
from codesign_basics.config import EvaluateConfig


class Evaluate(Optimizer):
    """Runs ``episodes`` episodes, one per iteration, and reports their returns.

    Each episode resets the environment with a seed drawn from the run's generator, so
    repeated episodes differ only where the environment is random. Each episode's centre of
    mass and actions per step go to ``trajectory-<i>.npz`` in the run directory, and the best
    one to ``best/`` as every optimizer's does, so `codesign eval`, `render` and `view` take the run.
    """

    def __init__(self, config: EvaluateConfig) -> None:
        self.config = config
        self.iterations = config.episodes
        self.episode = 0

    def setup(
        self,
        environment: Environment,
        representation: Representation,
        controller: Controller,
        *,
        rng: np.random.Generator,
        run_dir: Path,
    ) -> None:
        self.environment = environment
        self.representation = representation
        self.controller = controller
        self.rng = rng
        self.run_dir = run_dir
        self.best = BestKeeper(environment, controller, run_dir)

    def step(self) -> dict[str, float]:
        design = self.representation()
        record = play(self.environment, design, self.controller, seed=int(self.rng.integers(2**31)))
        if self.run_dir is not None:
            np.savez_compressed(Path(self.run_dir) / f"trajectory-{self.episode}.npz", com=record.com,
                                actions=record.actions, episode_return=record.episode_return)
        self.best.offer(record.episode_return, design, record, self.episode)
        self.episode += 1
        return {
            "episode_return": record.episode_return,
            "mean_reward": record.episode_return / max(record.length, 1),
            "episode_length": float(record.length),
            **record.metrics,  # what the environment reports of the episode (e.g. the body's integrity)
        }

    def state_dict(self) -> dict:
        return {"episode": self.episode, "best_return": self.best.best_return}

    def load_state_dict(self, state: dict) -> None:
        self.episode = state["episode"]
        self.best.best_return = state.get("best_return", -float("inf"))  # checkpoints before it kept none
