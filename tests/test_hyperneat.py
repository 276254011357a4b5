"""The hyperneat controller: its weights are what neat-python's own network of the genome says at
the substrate's coordinates, its actions are bounded and closed-loop, and moving an actuator on
the substrate repaints only that actuator's weights. No simulator."""

import math
import random

import numpy as np
import pytest
import torch
from neat.genome import DefaultGenome
from neat.innovation import InnovationTracker
from neat.nn import FeedForwardNetwork

from codesign.plugins import get_registry

K, D, DT = 3, 5, 0.01  # actuators, observation entries, control step


def build(seed: int = 0, action_dim: int = K, **config):
    entry = get_registry().get("controller", "hyperneat")
    controller = entry.load_factory()(entry.load_config()(**config))
    controller.setup(action_dim, D, DT, np.random.default_rng(seed))
    return controller


class NeatConfigView:
    """What neat.nn.FeedForwardNetwork.create reads of a neat.Config."""

    def __init__(self, genome_config):
        self.genome_config = genome_config


def mutated_genomes(controller, count: int, seed: int = 3):
    config = DefaultGenome.parse_config(controller.genome_section())
    config.innovation_tracker = InnovationTracker()
    random.seed(seed)
    for key in range(count):
        genome = DefaultGenome(key)
        genome.configure_new(config)
        for _ in range(6):  # grow hidden nodes and connections, change activations and weights
            genome.mutate(config)
        yield genome, config


def expressed(w: float, threshold: float, max_weight: float) -> float:
    """HyperNEAT's expression of one CPPN weight output, written out per scalar."""
    w = min(max(w, -1.0), 1.0)
    return 0.0 if abs(w) < threshold else math.copysign((abs(w) - threshold) / (1 - threshold) * max_weight, w)


@pytest.mark.parametrize("hidden", [0, 5])
def test_weights_are_neat_pythons_network_at_the_substrate_coordinates(hidden):
    controller = build(hidden=hidden, weight_threshold=0.3, max_weight=2.0, node_add_prob=0.9, conn_add_prob=0.9)
    assert len(controller.substrate) == (3 if hidden else 2)
    zeros = expressed_count = 0
    for genome, config in mutated_genomes(controller, 4):
        controller.set_genome(genome, config)
        net = FeedForwardNetwork.create(genome, NeatConfigView(config))
        params = controller.parameters()
        for layer, (source, target) in enumerate(zip(controller.substrate[:-1], controller.substrate[1:])):
            weight = np.array([[expressed(np.subtract(*net.activate([*s, *t])[:2]), 0.3, 2.0) for s in source]
                               for t in target])
            bias = np.array([min(max(np.subtract(*net.activate([0.0, 0.0, 0.0, *t])[2:]), -1.0), 1.0) * 2.0
                             for t in target])
            np.testing.assert_allclose(params[2 * layer].detach().numpy(), weight, rtol=1e-6, atol=1e-6)
            np.testing.assert_allclose(params[2 * layer + 1].detach().numpy(), bias, rtol=1e-6, atol=1e-6)
            zeros += int((weight == 0).sum())
            expressed_count += int((weight != 0).sum())
    assert zeros and expressed_count  # the threshold both cut and kept connections


def test_substrate_layout_is_the_documented_one():
    controller = build(hidden=5, frequencies=[10.0, 20.0, 40.0], phases=4)
    inputs, hidden, outputs = controller.substrate
    basis, observation = inputs[:12], inputs[12:]
    assert len(observation) == D and (inputs[:, 2] == -1).all()
    radius = np.hypot(basis[:, 0], basis[:, 1])
    np.testing.assert_allclose(radius, np.repeat([1 / 3, 2 / 3, 1.0], 4))  # a ring per frequency
    np.testing.assert_allclose(np.arctan2(basis[:4, 1], basis[:4, 0]) % (2 * np.pi), np.arange(4) * np.pi / 2,
                               atol=1e-12)
    np.testing.assert_allclose(observation[:, :2], np.stack([np.linspace(-1, 1, D), np.full(D, -1.25)], axis=1))
    assert len(np.unique(inputs.round(9), axis=0)) == len(inputs)  # no two inputs share a point
    assert (hidden[:, 2] == 0).all() and np.abs(hidden[:, :2]).max() <= 1
    assert len(np.unique(hidden.round(9), axis=0)) == 5
    np.testing.assert_allclose(outputs, [[-1, 0, 1], [0, 0, 1], [1, 0, 1]])  # evenly on b = 0 until placed
    assert [tuple(p.shape) for p in controller.parameters()] == [(5, 12 + D), (5,), (K, 5), (K,)]


def test_actions_are_bounded_and_closed_loop():
    controller = build(bound=0.25, max_weight=0.5)  # small weights: tanh far from saturation
    assert not controller.open_loop
    large = np.random.default_rng(0).normal(0.0, 30.0, (20, D))
    actions = np.stack([controller(obs, step).detach().numpy() for step, obs in enumerate(large)])
    assert actions.shape == (20, K) and np.abs(actions).max() <= 0.25
    observations = np.random.default_rng(1).normal(0.0, 0.3, (2, D))
    assert not np.allclose(controller(observations[0], 4).detach(), controller(observations[1], 4).detach())
    observation = torch.tensor(observations[0], requires_grad=True)  # torch observations: gradients reach them
    action = controller(observation, 4)
    np.testing.assert_allclose(action.detach(), controller(observations[0], 4).detach())
    action.sum().backward()
    assert observation.grad.abs().sum() > 0

    open_loop = build(observation=False)
    assert open_loop.open_loop and open_loop.parameters()[0].shape == (K, 8)
    assert torch.equal(open_loop(observations[0], 3), open_loop(None, 3))
    assert not torch.equal(open_loop(None, 3), open_loop(None, 4))  # the sine basis drives it


def test_moving_an_actuator_repaints_only_its_weights():
    for hidden in (0, 4):
        controller = build(hidden=hidden)
        before = [p.detach().clone() for p in controller.parameters()]
        positions = np.stack([np.linspace(-1, 1, K), np.zeros(K)], axis=1)
        positions[1] = [0.4, -0.8]
        controller.set_substrate(positions)
        after = controller.parameters()
        for old, new in zip(before[:-2], after[:-2]):  # the layers before the actuators stay
            assert torch.equal(old, new)
        (w_old, b_old), (w_new, b_new) = before[-2:], after[-2:]
        moved = np.arange(K) == 1
        assert torch.equal(w_old[~moved], w_new[~moved]) and torch.equal(b_old[~moved], b_new[~moved])
        assert not (torch.equal(w_old[moved], w_new[moved]) and torch.equal(b_old[moved], b_new[moved]))
        controller.set_substrate(None)
        assert all(torch.equal(old, new) for old, new in zip(before, controller.parameters()))
    with pytest.raises(ValueError, match=r"\(3, 2\) array"):
        controller.set_substrate(np.zeros((2, 2)))
    with pytest.raises(ValueError, match=r"in \[-1, 1\]\^2"):
        controller.set_substrate(np.full((K, 2), 1.5))


def test_first_genome_comes_from_the_generator_and_the_weights_replay_without_it():
    state = random.getstate()
    first, again, other = build(1), build(1), build(2)
    assert random.getstate() == state  # neat-python's draw left the random module as it was
    assert all(torch.equal(a, b) for a, b in zip(first.parameters(), again.parameters()))
    assert not torch.equal(first.parameters()[0], other.parameters()[0])
    with torch.no_grad():  # what `codesign eval` does with best/controller.pt: copy the tensors
        for mine, saved in zip(other.parameters(), first.parameters()):
            mine.copy_(saved)
    observation = np.linspace(-1, 1, D)
    assert torch.equal(other(observation, 7), first(observation, 7))
    assert all(p.requires_grad for p in first.parameters())  # a gradient optimizer may fine-tune them


def test_bad_values_are_recipe_errors():
    from codesign.errors import RecipeError
    from codesign.recipe import resolve_recipe

    def recipe(**controller):
        return {"environment": {"name": "toy"}, "representation": {"name": "particle"},
                "controller": {"name": "hyperneat", **controller}, "optimizer": {"name": "evaluate"}}

    resolve_recipe(recipe(hidden=9, observation=False))
    with pytest.raises(RecipeError, match=r"controller.weight_threshold: 1.5 is out of range; must be >= 0 and < 1"):
        resolve_recipe(recipe(weight_threshold=1.5))
    with pytest.raises(RecipeError, match=r"controller.activations\[1\]: 'swish' is not a valid choice"):
        resolve_recipe(recipe(activations=["sin", "swish"]))
    with pytest.raises(RecipeError, match="controller.max_weight"):
        resolve_recipe(recipe(max_weight=0))
