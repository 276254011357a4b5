"""A NEAT genome's CPPN (neat-python 2.0), evaluated on many input rows at once: the machinery the
neat_cppn representation (a CPPN queried at particles gives a body) and the hyperneat controller
(a CPPN queried on a substrate gives a network's weights) share.

neat-python evaluates a network point by point in Python; here the network's nodes are
evaluated in topological order on all rows at once with numpy, using neat-python's own
activation definitions (its scaled sigmoid, sin, ...; tests check both agree).
"""

from __future__ import annotations

import random

import numpy as np

from codesign_basics.config import NeatGenomeSettings

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


def genome_section(settings: NeatGenomeSettings, n_inputs: int, n_outputs: int) -> dict[str, str]:
    """neat-python's [DefaultGenome] settings of a CPPN with `n_inputs` inputs and `n_outputs`
    outputs (sum aggregation only; unit response, so a node computes act(bias + sum w_i x_i))."""
    weight = {"init_mean": 0.0, "init_stdev": settings.weight_init_stdev, "max_value": 30.0, "min_value": -30.0,
              "mutate_power": settings.weight_mutate_power, "mutate_rate": settings.weight_mutate_rate,
              "replace_rate": 0.1}
    bias = {**weight, "init_stdev": 1.0, "mutate_rate": settings.bias_mutate_rate}
    response = {"init_mean": 1.0, "init_stdev": 0.0, "max_value": 1.0, "min_value": 1.0, "mutate_power": 0.0,
                "mutate_rate": 0.0, "replace_rate": 0.0}
    section = {
        "num_inputs": n_inputs, "num_outputs": n_outputs, "num_hidden": settings.num_hidden, "feed_forward": True,
        "initial_connection": settings.initial_connection,
        "compatibility_disjoint_coefficient": 1.0, "compatibility_weight_coefficient": 0.5,
        "conn_add_prob": settings.conn_add_prob, "conn_delete_prob": settings.conn_delete_prob,
        "node_add_prob": settings.node_add_prob, "node_delete_prob": settings.node_delete_prob,
        "activation_default": "random", "activation_options": " ".join(settings.activations),
        "activation_mutate_rate": settings.activation_mutate_rate,
        "aggregation_default": "sum", "aggregation_options": "sum", "aggregation_mutate_rate": 0.0,
        "enabled_default": True, "enabled_mutate_rate": 0.01,
        **{f"weight_{k}": v for k, v in weight.items()},
        **{f"bias_{k}": v for k, v in bias.items()},
        **{f"response_{k}": v for k, v in response.items()},
    }
    return {k: str(v) for k, v in section.items()}


def random_genome(section: dict[str, str], rng: np.random.Generator):
    """A fresh genome of the [DefaultGenome] `section` and its genome config, drawn from `rng`.

    neat-python draws from the `random` module: it is seeded from `rng` for the draw and left
    as it was, so a part's first genome follows the run's seed and disturbs no one else's draws.
    """
    from neat.genome import DefaultGenome
    from neat.innovation import InnovationTracker

    genome_config = DefaultGenome.parse_config(section)
    genome_config.innovation_tracker = InnovationTracker()
    state = random.getstate()
    random.seed(int(rng.integers(2**31)))
    genome = DefaultGenome(0)
    genome.configure_new(genome_config)
    random.setstate(state)
    return genome, genome_config


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
