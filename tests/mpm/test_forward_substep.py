"""A forward substep in one launch (`_forward_substep`) runs the same arithmetic as the stages'
own kernels one after the other: the two give bitwise the same states."""

import numpy as np
import pytest

from codesign_mpm import BodySpec, MuscleSpec, Scene, ShapeSpec, TerrainSpec, build_particles
from codesign_mpm.engine import Simulator


def _scene(contact: str, grid_region: str) -> Scene:
    return Scene(size=[1.0, 0.5, 0.5], dx=1 / 32, grid_region=grid_region, pic_time=0.265,
                 terrain=TerrainSpec(height=0.1, friction=0.5, contact=contact),
                 bodies=[BodySpec(name="robot", robot=True, shape=ShapeSpec(size=[0.2, 0.08, 0.08]),
                                  center=[0.5, 0.0, 0.25], rest_on_terrain=True, muscles=MuscleSpec(groups=[2, 1, 1]))])


def _staged(sim: Simulator):
    """The substep as separate kernels, whatever the layout (the path differentiable layouts take)."""
    def substep(s, so, t, j=0, keep_grid=False):
        sim._grid_update(s, so, t, j)
        sim.k._g2p(s, so, sim.n, j)
    return substep


@pytest.mark.parametrize("contact, grid_region", [("spring", "bbox"), ("nodes", "full")])
def test_one_launch_per_substep_gives_the_staged_kernels_results_bit_for_bit(contact, grid_region):
    scene = _scene(contact, grid_region)
    fused, staged = Simulator(scene, build_particles(scene)), Simulator(scene, build_particles(scene))
    staged._substep = _staged(staged)
    actions = np.random.default_rng(0).uniform(-0.3, 0.3, (6, fused.n_actuators))
    for action in actions:
        fused.step(action)
        staged.step(action)
    assert fused.frame_substeps == staged.frame_substeps
    for a, b in zip(fused.particles_state(), staged.particles_state()):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(fused.contact_springs(), staged.contact_springs())
    moved = np.abs(fused.particles_state()[0] - build_particles(scene).x).max()
    assert moved > 1e-4  # the actions moved the body: the comparison is not of two bodies at rest
