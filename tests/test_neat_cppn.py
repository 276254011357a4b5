"""The neat_cppn representation: its vectorised network is neat-python's, its body is connected,
its first genome comes from the run's generator. (Evolution itself: tests/test_optimizers.py on
the toy environment, tests/mpm/test_cppn_neat.py on a crawler.)"""

import random

import numpy as np
import pytest
from neat.genome import DefaultGenome
from neat.innovation import InnovationTracker
from neat.nn import FeedForwardNetwork

from codesign.bodies import lattice
from codesign.interfaces import DesignSpace
from codesign.plugins import get_registry
from codesign_designs.common import coordinate_features

SPACE = DesignSpace(points=lattice(np.zeros(3), np.array([0.2, 0.08, 0.08]), 0.02), n_actuators=3,
                    default_stiffness=2e4)


def build(seed: int = 0, **config):
    entry = get_registry().get("representation", "neat_cppn")
    representation = entry.load_factory()(entry.load_config()(**config))
    representation.setup(SPACE, np.random.default_rng(seed))
    return representation


class NeatConfigView:
    """What neat.nn.FeedForwardNetwork.create reads of a neat.Config."""

    def __init__(self, genome_config):
        self.genome_config = genome_config


def test_vectorised_network_equals_neat_pythons_network_on_evolved_genomes():
    representation = build(activations=["sigmoid", "tanh", "sin", "gauss", "selu", "abs", "log", "exp"],
                           num_hidden=2, initial_connection="full_nodirect", node_add_prob=0.9, conn_add_prob=0.9)
    config = DefaultGenome.parse_config(representation.genome_section())
    config.innovation_tracker = InnovationTracker()
    random.seed(5)
    features = coordinate_features(SPACE)
    from codesign_designs.neat_cppn import evaluate_cppn

    used = set()
    for key in range(6):
        genome = DefaultGenome(key)
        genome.configure_new(config)
        for _ in range(8):  # grow hidden nodes and connections, change activations and weights
            genome.mutate(config)
        used |= {node.activation for node in genome.nodes.values()}
        expected = np.array([FeedForwardNetwork.create(genome, NeatConfigView(config)).activate(row)
                             for row in features])
        np.testing.assert_allclose(evaluate_cppn(genome, config, features), expected, rtol=1e-12, atol=1e-12)
    assert len(used) >= 6  # the comparison covered most activations


def test_only_the_largest_connected_piece_of_the_body_is_kept():
    representation = build()
    x = SPACE.points[:, 0]
    two_blobs = (x < 0.05) | (x > 0.12)  # 0.05 .. 0.12 empty: two pieces, the right one larger
    kept = representation.connected_body(two_blobs)
    assert kept.any() and np.array_equal(kept, x > 0.12)
    assert np.array_equal(representation.connected_body(x < 0.2), x < 0.2)  # one piece stays whole


def test_fields_are_a_design_over_the_space_and_come_from_the_generator():
    first, again, other = build(1), build(1), build(2)
    design = first()
    n = len(SPACE.points)
    assert set(np.unique(design.occupancy)) <= {0.0, 1.0}
    assert design.stiffness.shape == (n,) and (design.stiffness > 0).all()
    np.testing.assert_array_equal(design.muscle.sum(1), np.ones(n))  # one muscle per particle
    assert np.array_equal(again().stiffness, design.stiffness)
    assert not np.array_equal(other().stiffness, design.stiffness)


def test_a_body_under_the_minimum_fraction_is_invalid():
    representation = build(min_body_fraction=0.5)
    genome = representation.genome
    for conn in genome.connections.values():  # every output a lone bias neuron
        conn.enabled = False
    occupied, empty = representation.genome_config.output_keys[:2]
    for key, bias in ((occupied, -1.0), (empty, 1.0)):  # the empty score wins everywhere
        genome.nodes[key].activation, genome.nodes[key].bias = "identity", bias
    representation.set_genome(genome, representation.genome_config)
    assert not representation.raw_occupancy.any()
    assert not representation.valid and representation().occupancy.sum() == 0


def test_fresh_genomes_are_seldom_empty_or_full(capsys):
    # One output's sign (the former rule) filled the whole workspace for about half of them: an
    # output's activation may be sigmoid, gauss, exp or abs, never negative.
    representation = build()
    config = DefaultGenome.parse_config(representation.genome_section())
    config.innovation_tracker = InnovationTracker()
    random.seed(0)
    raw, kept = [], []
    for key in range(400):
        genome = DefaultGenome(key)
        genome.configure_new(config)
        representation.set_genome(genome, config)
        raw.append(representation.raw_occupancy.mean())
        kept.append(representation().occupancy.mean())
    raw, kept = np.array(raw), np.array(kept)
    with capsys.disabled():
        print(f"\n400 fresh genomes: raw mask full {np.mean(raw == 1):.1%}, empty {np.mean(raw == 0):.1%}; "
              f"connected body full {np.mean(kept == 1):.1%}, empty {np.mean(kept == 0):.1%}, "
              f"under min_body_fraction {np.mean(kept < 0.05):.1%}")
    assert np.mean(raw == 1) <= 0.25 and np.mean(raw == 0) <= 0.25


def test_bad_configs_are_recipe_errors():
    from codesign.errors import RecipeError
    from codesign.recipe import resolve_recipe

    with pytest.raises(RecipeError, match=r"representation.activations\[0\]: 'swish' is not a valid choice"):
        resolve_recipe({"environment": {"name": "toy"}, "representation": {"name": "neat_cppn", "activations": ["swish"]},
                        "controller": {"name": "trajectory"}, "optimizer": {"name": "evaluate"}})
    entry = get_registry().get("representation", "neat_cppn")
    with pytest.raises(RecipeError, match="representation.min_stiffness_ratio"):
        entry.load_factory()(entry.load_config()(min_stiffness_ratio=2.0, max_stiffness_ratio=1.0))
