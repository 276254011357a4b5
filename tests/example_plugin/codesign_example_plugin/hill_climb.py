"""An optimizer in a page: hill climbing on the controller's parameters. Each iteration plays the
current controller with Gaussian noise added to its parameters and keeps the change if the episode
scored better."""

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from codesign.artifacts import BestKeeper, play
from codesign.interfaces import Optimizer


@dataclass
class HillClimbConfig:
    iterations: int = field(default=10, metadata={"ge": 1})
    sigma: float = field(default=0.1, metadata={"gt": 0, "help": "standard deviation of each parameter's step"})


class HillClimb(Optimizer):
    def __init__(self, config: HillClimbConfig) -> None:
        self.config = config
        self.iterations = config.iterations

    def setup(self, environment, representation, controller, *, rng: np.random.Generator, run_dir: Path) -> None:
        self.environment, self.representation, self.controller = environment, representation, controller
        self.rng = rng
        self.keeper = BestKeeper(environment, controller, run_dir)  # best/ for `codesign eval`, render, view
        self.iteration = 0

    def step(self) -> dict[str, float]:
        import torch

        params = self.controller.parameters()
        before = [p.detach().clone() for p in params]
        if self.iteration > 0:  # the first iteration measures the start
            with torch.no_grad():
                for p in params:
                    p.add_(torch.as_tensor(self.rng.normal(0.0, self.config.sigma, tuple(p.shape)), dtype=p.dtype))
        design = self.representation()
        record = play(self.environment, design, self.controller, seed=int(self.rng.integers(2**31)))
        if not self.keeper.offer(record.episode_return, design, record, self.iteration):  # worse: step back
            with torch.no_grad():
                for p, old in zip(params, before):
                    p.copy_(old)
        self.iteration += 1
        return {"episode_return": record.episode_return, "best_return": self.keeper.best_return,
                **record.metrics}  # what the environment reports (e.g. the body's integrity)

    def state_dict(self) -> dict:
        """Everything a resumed run needs: the controller's parameters, the counters."""
        return {"iteration": self.iteration, "best_return": self.keeper.best_return,
                "params": [p.detach().clone() for p in self.controller.parameters()]}

    def load_state_dict(self, state: dict) -> None:
        import torch

        self.iteration, self.keeper.best_return = state["iteration"], state["best_return"]
        with torch.no_grad():
            for p, saved in zip(self.controller.parameters(), state["params"]):
                p.copy_(saved)
