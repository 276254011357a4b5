"""What every optimizer here shares: parameter groups by mode, and keeping the best."""

from __future__ import annotations

import math
from pathlib import Path

import torch

from codesign.artifacts import EpisodeRecord, save_best
from codesign.errors import RecipeError
from codesign.interfaces import Controller, DesignFields, Environment, Representation


def parameter_groups(mode: str, representation: Representation, controller: Controller,
                     supported: tuple[str, ...] = ("control", "design", "both")) -> dict[str, list[torch.Tensor]]:
    """{"control": [...], "design": [...]} for `optimizer.optimize` = mode, each group non-empty."""
    if mode not in supported:
        raise RecipeError(f"invalid recipe: optimizer.optimize: {mode!r} is not supported by this optimizer; "
                          f"allowed: {', '.join(supported)}")
    groups = {}
    for name, part, kind in (("control", controller, "controller"), ("design", representation, "representation")):
        if mode in (name, "both"):
            params = list(part.parameters())
            if not params:
                raise RecipeError(f"invalid recipe: optimizer.optimize: {mode!r} trains the {kind}, but "
                                  f"{kind} '{type(part).__name__}' has no trainable parameters")
            groups[name] = params
    return groups


class BestKeeper:
    """Remembers the best return so far and writes its design and controller to run_dir/best."""

    def __init__(self, environment: Environment, controller: Controller, run_dir: Path | None) -> None:
        self.environment, self.controller, self.run_dir = environment, controller, run_dir
        self.best_return = -math.inf

    def offer(self, episode_return: float, design: DesignFields, record: EpisodeRecord | None, iteration: int) -> bool:
        """Keep this episode if it beats the best so far (call before the parameters change)."""
        if not episode_return > self.best_return:
            return False
        self.best_return = episode_return
        if self.run_dir is not None:
            save_best(Path(self.run_dir), design, self.environment.design_space.points, self.controller, record,
                      {"iteration": iteration, "episode_return": episode_return})
        return True
