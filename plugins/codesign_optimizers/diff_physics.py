"""Differentiable-physics optimisation: Adam through the simulator (SoftZoo appendix "Optimization")."""

from __future__ import annotations

import copy
import math
from pathlib import Path

import numpy as np
import torch

from codesign.artifacts import BestKeeper, EpisodeRecord
from codesign.errors import CodesignError, DesignError, RecipeError
from codesign.interfaces import Controller, Environment, Optimizer, Representation
from codesign_optimizers.common import parameter_groups
from codesign_optimizers.config import DiffPhysicsConfig


class DiffPhysics(Optimizer):
    """One Adam step per iteration on the loss of a differentiable episode (minus its return).

    Each parameter group (control, design) has its own learning rate and optional gradient
    clipping. With `restarts` > 1 the parts are re-initialised from the run's generator after
    every `iterations` steps (the paper's "several random seeds, keep the best"); the best
    episode over all restarts is what `best/` keeps. A non-finite gradient stops the run with
    an error naming the iteration and the group, never a silent zero.
    """

    maximize = {"loss": False}

    def __init__(self, config: DiffPhysicsConfig) -> None:
        self.config = config
        self.iterations = config.iterations * config.restarts
        self.iteration = 0

    def setup(self, environment: Environment, representation: Representation, controller: Controller, *,
              rng: np.random.Generator, run_dir: Path) -> None:
        if not hasattr(environment, "differentiable_episode"):
            raise RecipeError(f"invalid recipe: optimizer.name: diff_physics needs an environment with "
                              f"differentiable episodes; {type(environment).__name__} has none")
        self.environment, self.representation, self.controller, self.rng = environment, representation, controller, rng
        self.groups = parameter_groups(self.config.optimize, representation, controller)
        self.best = BestKeeper(environment, controller, run_dir)
        self._before: tuple[list[torch.Tensor], dict] | None = None  # parameters and Adam before the last step
        self._new_adam()

    def _parameters(self) -> list[torch.Tensor]:
        return [p for params in self.groups.values() for p in params]

    def _take_back(self, error: DesignError) -> dict[str, float]:
        """Undo the last Adam step, whose design the environment refused (parameters and Adam's
        state), and halve the design's rate."""
        if self._before is None:
            raise DesignError(f"diff_physics: the first design (iteration {self.iteration}) is unplayable: {error}; "
                              "use a finer environment.dx, a larger robot.size or another representation") from error
        parameters, adam = self._before
        with torch.no_grad():
            for p, saved in zip(self._parameters(), parameters):
                p.copy_(saved)
        self.adam.load_state_dict(adam)  # Adam's moments and step count as before the refused step
        self._before = None  # two refusals in a row go back no further than the last playable design
        metrics = {"unplayable": 1.0, "best_return": self.best.best_return,
                   "restart": float(self.iteration // self.config.iterations)}
        for group in self.adam.param_groups:
            if group["name"] == "design":
                group["lr"] /= 2
                metrics["lr_design"] = group["lr"]
        self.iteration += 1
        return metrics

    def _new_adam(self) -> None:
        lr = {"control": self.config.lr_control, "design": self.config.lr_design}
        self.adam = torch.optim.Adam([{"params": params, "lr": lr[name], "name": name}
                                      for name, params in self.groups.items()])

    def _restart(self) -> None:
        """Fresh initial parameters for the next restart (same shapes, so Adam's groups stay valid)."""
        env = self.environment
        self.representation.setup(env.design_space, self.rng)
        self.controller.setup(env.action_dim, env.observation_dim, env.control_dt, self.rng)
        self.groups = parameter_groups(self.config.optimize, self.representation, self.controller)
        self._before = None
        self._new_adam()

    def step(self) -> dict[str, float]:
        if self.iteration and self.iteration % self.config.iterations == 0:
            self._restart()
        design = self.representation()
        try:
            episode = self.environment.differentiable_episode(design, self.controller, self.config.checkpoint_every)
        except DesignError as error:
            return self._take_back(error)
        self.adam.zero_grad()
        episode.loss.backward()
        metrics = {"loss": episode.loss.item(), "episode_return": episode.episode_return,
                   "restart": float(self.iteration // self.config.iterations),
                   "simulated_steps": float(self.environment.horizon), **episode.metrics}
        for name, params in self.groups.items():
            grads = [p.grad if p.grad is not None else torch.zeros_like(p) for p in params]
            norm = float(torch.linalg.vector_norm(torch.stack([torch.linalg.vector_norm(g) for g in grads])))
            if not math.isfinite(norm):
                raise CodesignError(f"diff_physics: non-finite gradient in the {name} group at iteration "
                                    f"{self.iteration} (loss {episode.loss.item():.6g}); lower the learning "
                                    f"rate or set optimizer.clip_grad_norm")
            metrics[f"grad_norm_{name}"] = norm
            if self.config.clip_grad_norm is not None:
                torch.nn.utils.clip_grad_norm_(params, self.config.clip_grad_norm)
        record = EpisodeRecord(episode.episode_return, self.environment.horizon, episode.com[1:], episode.actions,
                               episode.metrics)
        self.best.offer(episode.episode_return, design, record, self.iteration)  # before the update changes them
        metrics["best_return"] = self.best.best_return
        self._before = ([p.detach().clone() for p in self._parameters()], copy.deepcopy(self.adam.state_dict()))
        self.adam.step()
        self.iteration += 1
        return metrics

    def state_dict(self) -> dict:
        return {"iteration": self.iteration, "adam": self.adam.state_dict(), "best_return": self.best.best_return,
                "representation": [p.detach().clone() for p in self.representation.parameters()],
                "controller": [p.detach().clone() for p in self.controller.parameters()],
                "before": self._before}  # so a step refused right after a resume is undone too

    def load_state_dict(self, state: dict) -> None:
        self.iteration = state["iteration"]
        with torch.no_grad():
            for part, saved in ((self.representation, state["representation"]), (self.controller, state["controller"])):
                for p, s in zip(part.parameters(), saved):
                    p.copy_(s)
        self.adam.load_state_dict(state["adam"])
        self.best.best_return = state["best_return"]
        self._before = state.get("before")  # absent from checkpoints written before undo was checkpointed
