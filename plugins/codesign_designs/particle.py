"""The particle-based representation (PBR) of the SoftZoo appendix: free parameters per base particle."""

from __future__ import annotations

import numpy as np
import torch

from codesign.geometry import grid_partition
from codesign.interfaces import DesignFields, DesignSpace, Representation
from codesign_designs.common import (Mirror, check_fiber, check_stiffness_ratios, environment_muscle, fixed_fibers,
                                     mirrored, near_cubic_grid)
from codesign_designs.config import ParticleConfig


class ParticleRepresentation(Representation):
    """occupancy = sigmoid(g_p); stiffness = E0 (lo + (hi - lo) sigmoid(s_p)); muscle = softmax(r_p).

    Every base particle has its own logits, so this is the most expressive and least smooth
    representation; the fibres are fixed (the environment's own unless `fiber` is given). All three
    logit tensors require grad.
    """

    def __init__(self, config: ParticleConfig) -> None:
        check_stiffness_ratios(config)
        check_fiber(config.fiber)
        self.config = config
        self.geometry: torch.Tensor | None = None
        self.stiffness: torch.Tensor | None = None
        self.muscle: torch.Tensor | None = None

    def setup(self, space: DesignSpace, rng: np.random.Generator) -> None:
        cfg = self.config
        n, k = len(space.points), space.n_actuators
        if cfg.muscle_init == "grid":
            muscle = np.zeros((n, k))
            muscle[np.arange(n), grid_partition(space.points, near_cubic_grid(k))] = cfg.muscle_sharpness
        elif cfg.muscle_init == "environment":
            muscle = cfg.muscle_sharpness * environment_muscle(space)
        elif cfg.muscle_init == "uniform":
            muscle = np.zeros((n, k))
        else:
            muscle = rng.normal(0.0, 1.0, (n, k))
        dtype = torch.get_default_dtype()
        self.geometry = torch.full((n,), cfg.init_occupancy_logit, dtype=dtype, requires_grad=True)
        self.stiffness = torch.zeros(n, dtype=dtype, requires_grad=True)
        self.muscle = torch.tensor(muscle, dtype=dtype, requires_grad=True)
        self._fiber = torch.tensor(fixed_fibers(space, cfg.fiber), dtype=dtype)
        self._mirror = Mirror(space) if cfg.symmetric else None
        self._default_stiffness = space.default_stiffness

    def parameters(self) -> list[torch.Tensor]:
        return [self.geometry, self.stiffness, self.muscle]

    def __call__(self) -> DesignFields:
        if self.geometry is None:
            raise RuntimeError("ParticleRepresentation.setup() must be called before use")
        lo, hi = self.config.min_stiffness_ratio, self.config.max_stiffness_ratio
        return mirrored(DesignFields(
            occupancy=torch.sigmoid(self.geometry),
            stiffness=self._default_stiffness * (lo + (hi - lo) * torch.sigmoid(self.stiffness)),
            muscle=torch.softmax(self.muscle, dim=1),
            fiber=self._fiber,
        ), self._mirror)
