"""The implicit-function representation (SoftZoo, after Occupancy Networks): an MLP on coordinates."""

from __future__ import annotations

import numpy as np
import torch

from codesign.interfaces import DesignFields, DesignSpace, Representation
from codesign_designs.common import (Mirror, centre_output_head, check_fiber, check_stiffness_ratios,
                                     coordinate_features, fields_from_logits, fixed_fibers, linear_layer, mirrored)
from codesign_designs.config import ImplicitConfig

ACTIVATION = {"tanh": torch.tanh, "sin": torch.sin, "softplus": torch.nn.functional.softplus}
N_FEATURES = 7


class ImplicitRepresentation(Representation):
    """One shared MLP maps each particle's coordinate features to its design.

    Inputs (7): standardized x, y, z, their distances to the workspace's mid-planes and the
    radius from its centre. Outputs (2 + K): occupancy logit (sigmoid), stiffness logit (as the
    particle representation) and K muscle logits (softmax); the fibre is fixed. The design is
    smooth in space by construction. The muscle logits start centred over the workspace (their
    output biases cancel their mean) and `muscle_scale` times larger, so that each muscle starts
    with a region of its own instead of one muscle winning everywhere.

    Parameters: sum over layers of (fan_in + 1) fan_out, i.e. (7 + 1) h1 + (h1 + 1) h2 +
    (h2 + 1)(2 + K); 1378 + 33 K for the default two layers of 32.
    """

    def __init__(self, config: ImplicitConfig) -> None:
        check_stiffness_ratios(config)
        check_fiber(config.fiber)
        self.config = config
        self.layers: list[tuple[torch.Tensor, torch.Tensor]] = []

    def setup(self, space: DesignSpace, rng: np.random.Generator) -> None:
        cfg = self.config
        dtype = torch.get_default_dtype()
        widths = [N_FEATURES, *cfg.hidden, 2 + space.n_actuators]
        self.layers = [linear_layer(rng, a, b, cfg.init_scale, dtype) for a, b in zip(widths[:-1], widths[1:])]
        self.features = torch.tensor(coordinate_features(space), dtype=dtype)
        with torch.no_grad():
            centre_output_head(*self.layers[-1], self._hidden(), cfg.muscle_scale, cfg.init_occupancy_logit)
        self._fiber = torch.tensor(fixed_fibers(space, cfg.fiber), dtype=dtype)
        self._mirror = Mirror(space) if cfg.symmetric else None
        self._default_stiffness = space.default_stiffness

    def parameters(self) -> list[torch.Tensor]:
        return [t for layer in self.layers for t in layer]

    def _hidden(self) -> torch.Tensor:
        """(N, last hidden width) activations of the hidden layers."""
        h = self.features
        for w, b in self.layers[:-1]:
            h = ACTIVATION[self.config.activation](h @ w + b)
        return h

    def __call__(self) -> DesignFields:
        if not self.layers:
            raise RuntimeError("ImplicitRepresentation.setup() must be called before use")
        logits = self._hidden() @ self.layers[-1][0] + self.layers[-1][1]
        return mirrored(fields_from_logits(logits, self._default_stiffness, self.config, self._fiber), self._mirror)
