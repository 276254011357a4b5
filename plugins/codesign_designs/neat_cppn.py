"""CPPN-NEAT (Stanley 2007; the paper's evolution-strategy baseline): a NEAT genome's CPPN,
queried at every particle of the workspace, gives occupancy, stiffness and muscle membership.

The genome is evolved by the `cppn_neat` optimizer (neat-python); this representation only
turns one genome into a design. neat-python evaluates a network point by point in Python;
here the network's nodes are evaluated in topological order on all particles at once with
numpy, using neat-python's own activation definitions (its scaled sigmoid, sin, ... ; a test
checks both agree).
"""

from __future__ import annotations

import random

import numpy as np
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from codesign.interfaces import DesignFields, DesignSpace, Representation
from codesign_designs.common import (check_fiber, check_stiffness_ratios, coordinate_features, fixed_fibers,
                                     stiffness_map)
from codesign_designs.config import NeatCPPNConfig

_SELU_LAMBDA, _SELU_ALPHA = 1.0507009873554804934193349852946, 1.6732632423543772848170429916717

ACTIVATIONS = {  # neat.activations, vectorised (same clamps and scales)
    "sigmoid": lambda z: 1.0 / (1.0 + np.exp(-np.clip(5.0 * z, -60.0, 60.0))),
    "tanh": lambda z: np.tanh(np.clip(2.5 * z, -60.0, 60.0)),
    "sin": lambda z: np.sin(np.clip(5.0 * z, -60.0, 60.0)),
    "gauss": lambda z: np.exp(-5.0 * np.clip(z, -3.4, 3.4) ** 2),
    "selu": lambda z: np.where(z > 0.0, _SELU_LAMBDA * z, _SELU_LAMBDA * _SELU_ALPHA * (np.exp(np.minimum(z, 0.0)) - 1)),
    "abs": np.abs,
    "log": lambda z: np.log(np.maximum(z, 1e-7)),
    "exp": lambda z: np.exp(np.clip(z, -60.0, 60.0)),
    "identity": lambda z: z,
}
N_INPUTS = 7  # x, y, z, their distances to the mid-planes, radius (codesign_designs.common.coordinate_features)


def genome_section(config: NeatCPPNConfig, n_outputs: int) -> dict[str, str]:
    """neat-python's [DefaultGenome] settings for `n_outputs` CPPN outputs (sum aggregation only;
    unit response, so a node computes act(bias + sum w_i x_i))."""
    weight = {"init_mean": 0.0, "init_stdev": config.weight_init_stdev, "max_value": 30.0, "min_value": -30.0,
              "mutate_power": config.weight_mutate_power, "mutate_rate": config.weight_mutate_rate,
              "replace_rate": 0.1}
    bias = {**weight, "init_stdev": 1.0, "mutate_rate": config.bias_mutate_rate}
    response = {"init_mean": 1.0, "init_stdev": 0.0, "max_value": 1.0, "min_value": 1.0, "mutate_power": 0.0,
                "mutate_rate": 0.0, "replace_rate": 0.0}
    section = {
        "num_inputs": N_INPUTS, "num_outputs": n_outputs, "num_hidden": config.num_hidden, "feed_forward": True,
        "initial_connection": config.initial_connection,
        "compatibility_disjoint_coefficient": 1.0, "compatibility_weight_coefficient": 0.5,
        "conn_add_prob": config.conn_add_prob, "conn_delete_prob": config.conn_delete_prob,
        "node_add_prob": config.node_add_prob, "node_delete_prob": config.node_delete_prob,
        "activation_default": "random", "activation_options": " ".join(config.activations),
        "activation_mutate_rate": config.activation_mutate_rate,
        "aggregation_default": "sum", "aggregation_options": "sum", "aggregation_mutate_rate": 0.0,
        "enabled_default": True, "enabled_mutate_rate": 0.01,
        **{f"weight_{k}": v for k, v in weight.items()},
        **{f"bias_{k}": v for k, v in bias.items()},
        **{f"response_{k}": v for k, v in response.items()},
    }
    return {k: str(v) for k, v in section.items()}


def evaluate_cppn(genome, genome_config, inputs: np.ndarray) -> np.ndarray:
    """(N, num_outputs) outputs of the genome's network at each row of `inputs` (N, num_inputs);
    an output no enabled path reaches is 0, as in neat.nn.FeedForwardNetwork."""
    from neat.graphs import feed_forward_layers

    connections = [cg.key for cg in genome.connections.values() if cg.enabled]
    layers, _ = feed_forward_layers(genome_config.input_keys, genome_config.output_keys, connections)
    values = {key: inputs[:, i] for i, key in enumerate(genome_config.input_keys)}
    zero = np.zeros(len(inputs))
    for layer in layers:
        for node in sorted(layer):
            gene = genome.nodes[node]
            total = sum((values[i] * genome.connections[(i, o)].weight
                         for i, o in connections if o == node and i in values), zero)
            values[node] = ACTIVATIONS[gene.activation](gene.bias + gene.response * total)
    return np.stack([values.get(key, zero) for key in genome_config.output_keys], axis=1)


class NeatCPPNRepresentation(Representation):
    """A NEAT genome's CPPN: inputs the seven coordinate features (the paper's x, y, z, plane
    distances and radius); outputs occupancy (kept where positive), stiffness (as the other
    representations' logit) and K muscle scores (each particle joins its highest).

    The paper's connected-body constraint: only the largest connected piece of the occupied
    particles is kept (particles are neighbours within 1.5 times the median spacing), and of that
    what the environment simulates (`DesignSpace.keep`: parts thick enough for its grid). A genome
    whose body keeps under `min_body_fraction` of the workspace is `valid` False: the optimizer
    ranks it last without simulating it. Setup draws a first random genome, so the
    representation also plays alone (e.g. with the evaluate optimizer); it has no torch
    parameters: only the evolution changes it.
    """

    def __init__(self, config: NeatCPPNConfig) -> None:
        check_stiffness_ratios(config)
        check_fiber(config.fiber)
        self.config = config
        self.genome = None

    def setup(self, space: DesignSpace, rng: np.random.Generator) -> None:
        from neat.genome import DefaultGenome
        from neat.innovation import InnovationTracker

        self.space = space
        self.features = coordinate_features(space)
        self.n_outputs = 2 + space.n_actuators
        self._fiber = fixed_fibers(space, self.config.fiber)
        tree = cKDTree(space.points)
        spacing = float(np.median(tree.query(space.points, k=2)[0][:, 1])) if len(space.points) > 1 else 1.0
        self._pairs = tree.query_pairs(1.5 * spacing, output_type="ndarray")
        genome_config = DefaultGenome.parse_config(self.genome_section())
        genome_config.innovation_tracker = InnovationTracker()
        state = random.getstate()  # neat-python draws from the random module; leave it as it was
        random.seed(int(rng.integers(2**31)))
        genome = DefaultGenome(0)
        genome.configure_new(genome_config)
        random.setstate(state)
        self.set_genome(genome, genome_config)

    def genome_section(self) -> dict[str, str]:
        """neat-python's [DefaultGenome] settings of this representation (after setup)."""
        return genome_section(self.config, self.n_outputs)

    def set_genome(self, genome, genome_config) -> None:
        """Make `genome` (a neat DefaultGenome of `genome_config`) the current design."""
        self.genome, self.genome_config = genome, genome_config
        out = evaluate_cppn(genome, genome_config, self.features)
        occupied = self.connected_body(out[:, 0] > 0.0)
        if self.space.keep is not None:  # what the environment simulates of it (thick enough for its grid)
            occupied = self.space.keep(occupied)
        self.valid = occupied.mean() >= max(self.config.min_body_fraction, 1e-12)
        muscle = np.eye(self.space.n_actuators)[np.argmax(out[:, 2:], axis=1)]
        self._fields = DesignFields(
            occupancy=occupied.astype(float),
            stiffness=stiffness_map(torch.as_tensor(out[:, 1]), self.space.default_stiffness,
                                    self.config.min_stiffness_ratio, self.config.max_stiffness_ratio).numpy(),
            muscle=muscle, fiber=self._fiber)

    def connected_body(self, occupied: np.ndarray) -> np.ndarray:
        """The largest connected piece of `occupied` (a boolean mask over the workspace's particles)."""
        if not occupied.any():
            return occupied
        pairs = self._pairs[occupied[self._pairs[:, 0]] & occupied[self._pairs[:, 1]]]
        n = len(occupied)
        graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
        _, label = connected_components(graph, directed=False)
        largest = np.bincount(label[occupied]).argmax()
        return occupied & (label == largest)

    def __call__(self) -> DesignFields:
        if self.genome is None:
            raise RuntimeError("NeatCPPNRepresentation.setup() must be called before use")
        return self._fields
