"""The particle-based design representation, and that the shipped recipes validate."""

from pathlib import Path

import numpy as np
import pytest
import torch

from codesign.errors import RecipeError
from codesign.interfaces import DesignSpace
from codesign.recipe import load_recipe
from codesign_designs.config import ParticleConfig
from codesign_designs.particle import ParticleRepresentation, near_cubic_grid

RECIPES = sorted((Path(__file__).resolve().parents[1] / "recipes").glob("*.yaml"))


def box_points(shape=(10, 4, 4), spacing=0.01) -> np.ndarray:
    axes = [np.arange(n) * spacing for n in shape]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


def particle(k=4, seed=0, points=None, **config) -> ParticleRepresentation:
    representation = ParticleRepresentation(ParticleConfig(**config))
    space = DesignSpace(points=box_points() if points is None else points, n_actuators=k, default_stiffness=2e4)
    representation.setup(space, np.random.default_rng(seed))
    return representation


def test_fields_have_the_design_space_shapes_and_ranges():
    design = particle(muscle_init="random")()
    n = len(box_points())
    assert design.occupancy.shape == (n,) and design.stiffness.shape == (n,)
    assert design.muscle.shape == (n, 4) and design.fiber.shape == (n, 3)
    assert (design.occupancy > 0.5).all() and (design.occupancy < 1).all()  # all present at first
    torch.testing.assert_close(design.stiffness, torch.full((n,), 2e4))  # logit 0: the default stiffness
    torch.testing.assert_close(design.muscle.sum(1), torch.ones(n))
    torch.testing.assert_close(design.fiber, torch.tensor([[1.0, 0.0, 0.0]]).expand(n, 3))


def test_stiffness_stays_between_its_ratios():
    representation = particle(min_stiffness_ratio=0.2, max_stiffness_ratio=3.0)
    with torch.no_grad():
        representation.stiffness.copy_(torch.linspace(-50, 50, len(representation.stiffness)))
    stiffness = representation().stiffness
    assert stiffness.min().item() == pytest.approx(0.2 * 2e4) and stiffness.max().item() == pytest.approx(3.0 * 2e4)


def test_gradients_reach_every_parameter():
    representation = particle(muscle_init="random")
    design = representation()
    weights = torch.rand(len(box_points()), 4, generator=torch.Generator().manual_seed(0))
    loss = design.occupancy.sum() + design.stiffness.sum() / 2e4 + (design.muscle * weights).sum()
    loss.backward()
    for tensor in representation.parameters():
        assert tensor.requires_grad and tensor.grad is not None and tensor.grad.abs().min() > 0


@pytest.mark.parametrize("k, grid", [(1, (1, 1, 1)), (2, (2, 1, 1)), (4, (2, 2, 1)), (6, (3, 2, 1)),
                                     (8, (2, 2, 2)), (12, (3, 2, 2)), (7, (7, 1, 1))])
def test_near_cubic_grid(k, grid):
    assert near_cubic_grid(k) == grid


def test_grid_init_gives_each_block_of_the_box_its_own_muscle():
    points = box_points()
    muscle = particle(k=4)().muscle.detach().numpy()
    owner = muscle.argmax(1)
    assert len(set(owner)) == 4 and (muscle.max(1) > 0.95).all()
    front, top = points[:, 0] > points[:, 0].mean(), points[:, 1] > points[:, 1].mean()
    for f in (False, True):
        for t in (False, True):
            block = owner[(front == f) & (top == t)]
            assert len(set(block)) == 1  # one muscle per x-half and y-half (2 x 2 x 1)


def test_random_init_comes_from_the_given_generator():
    torch.testing.assert_close(particle(seed=1, muscle_init="random").muscle,
                               particle(seed=1, muscle_init="random").muscle)
    assert not torch.equal(particle(seed=1, muscle_init="random").muscle,
                           particle(seed=2, muscle_init="random").muscle)


def test_inverted_stiffness_ratios_are_a_user_error():
    with pytest.raises(RecipeError, match="min_stiffness_ratio"):
        ParticleRepresentation(ParticleConfig(min_stiffness_ratio=2.0, max_stiffness_ratio=1.0))


@pytest.mark.parametrize("recipe", RECIPES, ids=[p.name for p in RECIPES])
def test_shipped_recipes_validate(recipe):
    resolved = load_recipe(recipe)
    assert resolved.sections["environment"].name in ("ground", "ice", "ocean")


@pytest.mark.parametrize("kind", ["particle", "voxel"])
def test_uniform_muscles_start_every_particle_in_every_muscle_alike_and_still_learn_placement(kind):
    """`muscle_init: uniform` (the released SoftZoo's start for Table 2): softmax of equal logits is
    1/K everywhere, and a loss that weighs the muscles differently still moves every logit."""
    from codesign_designs.config import VoxelConfig
    from codesign_designs.voxel import VoxelRepresentation

    space = DesignSpace(points=box_points(), n_actuators=4, default_stiffness=2e4)
    representation = (ParticleRepresentation(ParticleConfig(muscle_init="uniform")) if kind == "particle"
                      else VoxelRepresentation(VoxelConfig(muscle_init="uniform", resolution=4)))
    representation.setup(space, np.random.default_rng(0))
    design = representation()
    torch.testing.assert_close(design.muscle, torch.full_like(design.muscle, 0.25))
    weights = torch.rand(len(box_points()), 4, generator=torch.Generator().manual_seed(0))
    (design.muscle * weights).sum().backward()
    assert representation.muscle.grad.abs().min() > 0
