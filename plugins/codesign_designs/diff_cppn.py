"""Diff-CPPN (SoftZoo, after Fernando et al. 2016): a fixed-topology CPPN with softened connections."""

from __future__ import annotations

import numpy as np
import torch

from codesign.interfaces import DesignFields, DesignSpace, Representation
from codesign_designs.common import (Mirror, centre_output_head, check_fiber, check_stiffness_ratios,
                                     coordinate_features, fields_from_logits, fixed_fibers, linear_layer, mirrored)
from codesign_designs.config import DiffCPPNConfig
from codesign_designs.implicit import N_FEATURES

ACTIVATIONS = {
    "sin": torch.sin,
    "sigmoid": torch.sigmoid,
    "gaussian": lambda x: torch.exp(-x * x),
    "abs": torch.abs,
    "tanh": torch.tanh,
    "selu": torch.nn.functional.selu,
    "identity": lambda x: x,
}


class DiffCPPNRepresentation(Representation):
    """A CPPN whose graph is a meta-graph of `hidden_layers` x `nodes`, every edge present but gated.

    Node j of layer l applies activations[(j + l) % len] to sum_i w_ij sigmoid(c_ij) h_i + b_j:
    each NEAT edge (on or off) is softened to a trainable weight w times a trainable gate
    sigmoid(c), which starts on (c = +gate_logit) for a random `connection_density` of the edges
    and off (c = -gate_logit) for the rest. Inputs are the implicit representation's seven
    coordinate features; a linear head gives occupancy, stiffness and K muscle logits; the
    fibre is fixed. Node biases start random like the weights (a zero bias would put the abs
    nodes on their kink at the workspace's centre, where every input is zero); muscle logits
    start centred and scaled as in the implicit representation.

    Parameters: 2 (7 n + (L - 1) n^2) + L n (weights and gates of the hidden edges, node
    biases) + (n + 1)(2 + K); with n = 20 nodes in L = 3 layers, 1982 + 21 K.
    """

    def __init__(self, config: DiffCPPNConfig) -> None:
        check_stiffness_ratios(config)
        check_fiber(config.fiber)
        self.config = config
        self.layers: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = []

    def setup(self, space: DesignSpace, rng: np.random.Generator) -> None:
        cfg = self.config
        dtype = torch.get_default_dtype()
        widths = [N_FEATURES] + [cfg.nodes] * cfg.hidden_layers
        self.layers = []
        for fan_in, fan_out in zip(widths[:-1], widths[1:]):
            w, b = linear_layer(rng, fan_in, fan_out, cfg.weight_scale, dtype, random_bias=True)
            on = rng.random((fan_in, fan_out)) < cfg.connection_density
            gate = torch.tensor(np.where(on, cfg.gate_logit, -cfg.gate_logit), dtype=dtype, requires_grad=True)
            self.layers.append((w, gate, b))
        self.head = linear_layer(rng, cfg.nodes, 2 + space.n_actuators, 1.0, dtype)
        # per layer: the nodes of each activation, and the order that puts them back in place
        self._groups = []
        for layer in range(cfg.hidden_layers):
            names = [cfg.activations[(j + layer) % len(cfg.activations)] for j in range(cfg.nodes)]
            groups = [(name, torch.tensor([j for j, n in enumerate(names) if n == name]))
                      for name in dict.fromkeys(names)]
            order = torch.cat([nodes for _, nodes in groups])
            self._groups.append((groups, torch.argsort(order)))
        self.features = torch.tensor(coordinate_features(space), dtype=dtype)
        with torch.no_grad():
            centre_output_head(*self.head, self._hidden(), cfg.muscle_scale, cfg.init_occupancy_logit)
        self._fiber = torch.tensor(fixed_fibers(space, cfg.fiber), dtype=dtype)
        self._mirror = Mirror(space) if cfg.symmetric else None
        self._default_stiffness = space.default_stiffness

    def parameters(self) -> list[torch.Tensor]:
        return [t for layer in self.layers for t in layer] + list(self.head)

    def _hidden(self) -> torch.Tensor:
        """(N, nodes) activations of the last layer of graph nodes."""
        h = self.features
        for (w, gate, b), (groups, back) in zip(self.layers, self._groups):
            z = h @ (w * torch.sigmoid(gate)) + b
            h = torch.cat([ACTIVATIONS[name](z[:, nodes]) for name, nodes in groups], dim=1)[:, back]
        return h

    def __call__(self) -> DesignFields:
        if not self.layers:
            raise RuntimeError("DiffCPPNRepresentation.setup() must be called before use")
        logits = self._hidden() @ self.head[0] + self.head[1]
        return mirrored(fields_from_logits(logits, self._default_stiffness, self.config, self._fiber), self._mirror)
