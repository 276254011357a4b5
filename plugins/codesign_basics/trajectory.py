"""Free actions per control step: trajectory optimisation."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from codesign.errors import RecipeError
from codesign.interfaces import Controller
from codesign_basics.config import TrajectoryConfig


class TrajectoryController(Controller):
    """u(t) = bound * tanh(logits[t]): one free action per step (the most expressive open-loop
    controller, and the least regular: nothing ties one step's action to the next)."""

    open_loop = True

    def __init__(self, config: TrajectoryConfig) -> None:
        self.config = config
        self.logits: torch.Tensor | None = None

    def setup(self, action_dim: int, observation_dim: int, control_dt: float, rng: np.random.Generator) -> None:
        shape = (self.config.steps, action_dim)
        self.logits = torch.tensor(rng.normal(0.0, self.config.init_std, shape), dtype=torch.get_default_dtype(),
                                   requires_grad=True)

    def parameters(self) -> list[torch.Tensor]:
        return [self.logits]

    def __call__(self, observation: Any, step: int) -> torch.Tensor:
        if self.logits is None:
            raise RuntimeError("TrajectoryController.setup() must be called before use")
        if step >= len(self.logits):
            raise RecipeError(f"invalid recipe: controller.steps: {len(self.logits)} is shorter than the episode "
                              f"(step {step} asked); set it to at least environment.horizon")
        return self.config.bound * torch.tanh(self.logits[step])
