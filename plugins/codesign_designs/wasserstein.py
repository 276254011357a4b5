"""Wasserstein barycenter of the primitives (SoftZoo appendix, after DiffAqua): geometry that moves
mass between primitives instead of fading one into another.

The barycenter is entropic optimal transport on a voxel grid over the workspace, solved by our own
convolutional Sinkhorn in torch (log domain, no POT: POT's convolutional barycenters are 2-D):
the Gibbs kernel of the squared distance is a Gaussian, separable into one small matrix per
axis, so applying it costs three matrix products. We use the debiased barycenter (Janati et al.
2020): the plain entropic barycenter is blurred by the kernel, so a primitive weighted one
would come back smoothed; the debiased one returns it. The iterations are unrolled, so autograd
gives the weights' gradient.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import torch
from torch.utils.checkpoint import checkpoint

from codesign.errors import RecipeError
from codesign.interfaces import DesignSpace
from codesign_designs.common import grid_counts, grid_weights
from codesign_designs.config import WassersteinConfig
from codesign_designs.primitives import PrimitiveBlend

FLOOR = 1e-12
"""Density added to every voxel of a primitive (relative to a full voxel), so logarithms stay finite."""
SUBSAMPLES = 3
"""Points per voxel edge whose share inside a primitive is its occupancy of the voxel: the same
for a library body and its annotated file (a distance bound would differ between them)."""
GRAPH_BYTES_PER_VOXEL_ITERATION = 264
"""What autograd keeps per primitive voxel per Sinkhorn iteration (measured: 3.7 GB for 60
iterations of 5 primitives on 36^3 voxels, about 33 float64 values)."""
GRAPH_MEMORY_BYTES = 256 * 1024**2
"""A barycenter whose graph would hold more is differentiated in checkpointed segments (slower:
the backward pass recomputes them; the default resolution 24 stays under it)."""


def log_convolve(f: torch.Tensor, kernels: list[torch.Tensor]) -> torch.Tensor:
    """log(K exp(f)) over the last three axes, K the product of the per-axis `kernels`.

    Each axis is a matrix product after subtracting the maximum along that axis (the shift is a
    constant of the result, so it carries no gradient); products that underflow are floored.
    """
    for axis, kernel in enumerate(kernels):
        dim = f.dim() - 3 + axis
        shift = f.amax(dim=dim, keepdim=True).detach()
        product = torch.movedim(torch.movedim(torch.exp(f - shift), dim, -1) @ kernel, -1, dim)
        f = shift + torch.log(product.clamp_min(torch.finfo(f.dtype).tiny))
    return f


def _sinkhorn_steps(log_b: torch.Tensor, log_d: torch.Tensor, log_densities: torch.Tensor, w: torch.Tensor,
                    kernels: list[torch.Tensor], steps: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """`steps` iterations of `debiased_barycenter` from (log_b, log_d); returns them and log_q."""
    for _ in range(steps):
        log_a = log_densities - log_convolve(log_b, kernels)
        log_ka = log_convolve(log_a, kernels)
        log_q = log_d + (w * log_ka).sum(0)
        log_b = log_q - log_ka
        log_d = 0.5 * (log_d + log_q - log_convolve(log_d, kernels))
    return log_b, log_d, log_q


def debiased_barycenter(log_densities: torch.Tensor, weights: torch.Tensor, kernels: list[torch.Tensor],
                        iterations: int) -> torch.Tensor:
    """Debiased Sinkhorn barycenter (Janati et al. 2020, Algorithm 1) of (P, nx, ny, nz) densities
    given by their logarithms, with (P,) weights summing to one; returns the density, summing to one.

    In the log domain: a_k = p_k / K b_k; q = d prod_k (K a_k)^w_k; b_k = q / K a_k;
    d = sqrt(d q / K d), K symmetric. Differentiated with a graph larger than GRAPH_MEMORY_BYTES,
    the iterations run in about sqrt(iterations) checkpointed segments, each recomputed in the
    backward pass: the graph then holds one segment's intermediates instead of every iteration's
    (docs/designs.md).
    """
    log_b = torch.zeros_like(log_densities)
    log_d = torch.zeros_like(log_densities[0])
    w = weights.reshape(-1, 1, 1, 1)
    graph_bytes = GRAPH_BYTES_PER_VOXEL_ITERATION * log_densities.numel() * iterations
    checkpointed = torch.is_grad_enabled() and w.requires_grad and graph_bytes > GRAPH_MEMORY_BYTES
    segment = max(1, round(math.sqrt(iterations))) if checkpointed else iterations
    done = 0
    while done < iterations:
        steps = min(segment, iterations - done)
        run = functools.partial(_sinkhorn_steps, kernels=kernels, steps=steps)
        if checkpointed:
            log_b, log_d, log_q = checkpoint(run, log_b, log_d, log_densities, w, use_reentrant=False)
        else:
            log_b, log_d, log_q = run(log_b, log_d, log_densities, w)
        done += steps
    return torch.softmax(log_q.reshape(-1), 0).reshape(log_q.shape)


class WassersteinRepresentation(PrimitiveBlend):
    """Occupancy from the Wasserstein barycenter of the primitives' occupancy with weights alpha.

    Each primitive's voxel occupancy o_i (the fraction of SUBSAMPLES^3 points of the voxel inside it) is
    normalised to a density; the barycenter's density times the blended volume sum_i alpha_i
    |o_i| is the design's mass per voxel (`mass()`, which keeps total mass for any weights),
    clipped to [0, 1] and read at the particles trilinearly. Stiffness, muscles and fibres as
    SDF-Lerp. Parameters: 4 P for P primitives (20 for the default fish family).
    """

    config: WassersteinConfig

    def _setup_geometry(self, space: DesignSpace) -> None:
        cfg, dtype = self.config, torch.get_default_dtype()
        lo, hi = space.box()
        self.counts = grid_counts(space, cfg.resolution)
        cell = (hi - lo) / self.counts
        axes = [lo[a] + (np.arange(self.counts[a]) + 0.5) * cell[a] for a in range(3)]
        centres = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        offsets = (np.stack(np.meshgrid(*[np.arange(SUBSAMPLES)] * 3, indexing="ij"), -1).reshape(-1, 3) + 0.5) \
            / SUBSAMPLES - 0.5  # sub-cell centres, in cells
        samples = (centres[:, None, :] + offsets[None] * cell).reshape(-1, 3)
        occupancy = np.stack([body.contains(samples).reshape(len(centres), -1).mean(1) for body in self.placed])
        volumes = occupancy.sum(1)
        for name, volume in zip(self.config.primitives, volumes):
            if volume == 0:
                raise RecipeError(f"invalid recipe: representation.primitives: {name!r} fills no voxel at "
                                  f"resolution {cfg.resolution}; raise representation.resolution")
        self.occupancy = torch.tensor(occupancy.reshape(-1, *self.counts), dtype=dtype)
        self.volumes = torch.tensor(volumes, dtype=dtype)
        density = (occupancy + FLOOR) / (occupancy + FLOOR).sum(1, keepdims=True)
        self._log_density = torch.tensor(np.log(density).reshape(-1, *self.counts), dtype=torch.float64)
        width = cfg.blur * cell.mean()  # the Gibbs kernel exp(-|x - y|^2 / eps) with eps = 2 width^2
        self._kernels = [torch.tensor(np.exp(-np.subtract.outer(x, x) ** 2 / (2 * width ** 2)), dtype=torch.float64)
                         for x in axes]
        index, weight = grid_weights(space.points, lo, hi, self.counts, "trilinear")
        self.index, self.weight = torch.as_tensor(index), torch.tensor(weight, dtype=dtype)

    def mass(self, weights: torch.Tensor | None = None) -> torch.Tensor:
        """(nx, ny, nz) the barycenter's occupied volume per voxel, in voxels (before clipping to 1)."""
        weights = self.weights()["geometry"] if weights is None else weights
        density = debiased_barycenter(self._log_density, weights.to(torch.float64), self._kernels,
                                      self.config.iterations)
        return (weights @ self.volumes) * density.to(weights.dtype)

    def _occupancy(self, weights: torch.Tensor) -> torch.Tensor:
        grid = self.mass(weights).clamp(max=1.0).reshape(-1)
        return (grid[self.index] * self.weight).sum(1)
