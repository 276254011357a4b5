"""An optimizer that changes nothing: it measures the current design and controller."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from codesign.interfaces import Controller, Environment, Optimizer, Representation
from codesign_basics.config import EvaluateConfig


def _to_numpy(value: Any) -> Any:
    return value.detach().cpu().numpy() if isinstance(value, torch.Tensor) else np.asarray(value)


class Evaluate(Optimizer):
    """Runs ``episodes`` episodes, one per iteration, and reports their returns.

    Each episode resets the environment with a seed drawn from the run's
    generator, so repeated episodes differ only where the environment is random.
    """

    def __init__(self, config: EvaluateConfig) -> None:
        self.config = config
        self.iterations = config.episodes

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

    @torch.no_grad()  # nothing is trained, so keep no autograd graph over the episode
    def step(self) -> dict[str, float]:
        env = self.environment
        observation = env.reset(design=self.representation(), seed=int(self.rng.integers(2**31)))
        self.controller.reset()
        episode_return, length = 0.0, 0
        for t in range(env.horizon):
            result = env.step(_to_numpy(self.controller(observation, t)))
            episode_return += float(result.reward)
            length += 1
            observation = result.observation
            if result.done:
                break
        return {
            "episode_return": episode_return,
            "mean_reward": episode_return / max(length, 1),
            "episode_length": float(length),
        }
