"""The voxel-based representation (SoftZoo VBR): the particle representation's logits, per voxel."""

from __future__ import annotations

import numpy as np
import torch

from codesign.interfaces import DesignFields, DesignSpace, Representation
from codesign_designs.common import (Mirror, check_fiber, check_stiffness_ratios, environment_muscle, fixed_fibers,
                                     grid_counts, grid_weights, mirrored, stiffness_map)
from codesign_designs.config import VoxelConfig


class VoxelRepresentation(Representation):
    """Logits on a voxel grid of its own over the workspace, read by each particle.

    occupancy = sigmoid(g), stiffness = E0 (lo + (hi - lo) sigmoid(s)), muscle = softmax(r), with
    g, s and r interpolated (trilinear) or looked up (nearest) from the voxels at the particle;
    the fibre is fixed. Parameters: V (2 + K) for V = nx ny nz voxels (`resolution` along the
    longest side), far fewer than the particle representation's N (2 + K).
    """

    def __init__(self, config: VoxelConfig) -> None:
        check_stiffness_ratios(config)
        check_fiber(config.fiber)
        self.config = config
        self.geometry: torch.Tensor | None = None

    def setup(self, space: DesignSpace, rng: np.random.Generator) -> None:
        cfg = self.config
        self.counts = grid_counts(space, cfg.resolution)
        voxels, k = int(np.prod(self.counts)), space.n_actuators
        lo, hi = space.box()
        index, weight = grid_weights(space.points, lo, hi, self.counts, cfg.interpolation)
        if cfg.muscle_init == "environment":
            own, _ = grid_weights(space.points, lo, hi, self.counts, "nearest")
            total = np.zeros((voxels, k))
            np.add.at(total, own[:, 0], environment_muscle(space))
            count = np.bincount(own[:, 0], minlength=voxels)[:, None]
            muscle = cfg.muscle_sharpness * total / np.maximum(count, 1)
        elif cfg.muscle_init == "uniform":
            muscle = np.zeros((voxels, k))
        else:
            muscle = rng.normal(0.0, 1.0, (voxels, k))
        dtype = torch.get_default_dtype()
        self.index, self.weight = torch.as_tensor(index), torch.tensor(weight, dtype=dtype)
        self.geometry = torch.full((voxels,), cfg.init_occupancy_logit, dtype=dtype, requires_grad=True)
        self.stiffness = torch.zeros(voxels, dtype=dtype, requires_grad=True)
        self.muscle = torch.tensor(muscle, dtype=dtype, requires_grad=True)
        self._fiber = torch.tensor(fixed_fibers(space, cfg.fiber), dtype=dtype)
        self._mirror = Mirror(space) if cfg.symmetric else None
        self._default_stiffness = space.default_stiffness

    def parameters(self) -> list[torch.Tensor]:
        return [self.geometry, self.stiffness, self.muscle]

    def _read(self, voxels: torch.Tensor) -> torch.Tensor:
        """Voxel values at the particles: the weighted sum over each particle's cells."""
        gathered = voxels[self.index]  # (N, C) or (N, C, K)
        w = self.weight if voxels.dim() == 1 else self.weight[..., None]
        return (gathered * w).sum(1)

    def __call__(self) -> DesignFields:
        if self.geometry is None:
            raise RuntimeError("VoxelRepresentation.setup() must be called before use")
        cfg = self.config
        return mirrored(DesignFields(
            occupancy=torch.sigmoid(self._read(self.geometry)),
            stiffness=stiffness_map(self._read(self.stiffness), self._default_stiffness, cfg.min_stiffness_ratio,
                                    cfg.max_stiffness_ratio),
            muscle=torch.softmax(self._read(self.muscle), dim=1),
            fiber=self._fiber,
        ), self._mirror)
