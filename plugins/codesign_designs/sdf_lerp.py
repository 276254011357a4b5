"""SDF-Lerp (SoftZoo appendix): geometry from a weighted sum of the primitives' signed distances."""

from __future__ import annotations

import numpy as np
import torch

from codesign.interfaces import DesignSpace
from codesign_designs.config import SdfLerpConfig
from codesign_designs.primitives import PrimitiveBlend

DISTANCE_CELLS = 64
"""Cells along the workspace's longest side of the lattice on which primitives' distances are
computed (`Body.signed_distance`: within about half a cell of the true distance)."""


class SdfLerpRepresentation(PrimitiveBlend):
    """occupancy = sigmoid(-sum_i alpha_i SDF_i(x) / T): the blended solid through a low-temperature
    sigmoid, so gradients reach the weights from particles near its surface. SDF_i are true signed
    distances (a distance transform), so no primitive's blend share is inflated by a loose bound.

    Stiffness and muscles are lerped, fibres averaged as rotations (Procrustes). With one weight
    at one, the design is that primitive. Parameters: 4 P for P primitives (20 for the default
    fish family), whatever the workspace's size or K.
    """

    config: SdfLerpConfig

    def _setup_geometry(self, space: DesignSpace) -> None:
        lo, hi = space.box()
        self.temperature = self.config.temperature * float((hi - lo).max())
        cell = float((hi - lo).max()) / DISTANCE_CELLS
        self._sdf = torch.tensor(np.stack([body.signed_distance(space.points, cell) for body in self.placed], 1),
                                 dtype=torch.get_default_dtype())  # (N, P)

    def _occupancy(self, weights: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(-(self._sdf @ weights) / self.temperature)
