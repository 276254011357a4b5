"""The batched simulator: B designs of one scene in one launch per substep give the trajectories
of B plain simulators (float64, so the only difference allowed is the order of atomic sums), with
members of different stiffness (so different CFL steps: a member sits out substeps it does not
need), with and without a plastic cover (two code paths hold a resting member's deformation)."""
from dataclasses import replace

import numpy as np
import pytest

from codesign.artifacts import play, play_population
from codesign.recipe import resolve_recipe
from codesign.runner import build_parts
from codesign_mpm import BodySpec, MaterialSpec, MuscleSpec, Scene, ShapeSpec, TerrainSpec, build_particles
from codesign_mpm.engine.batch import BatchSimulator
from codesign_mpm.engine import SimulationError, Simulator
from codesign_optimizers.common import candidate

FRAMES = 4


def scene(cover: str | None) -> Scene:
    bodies = [BodySpec(name="robot", robot=True, shape=ShapeSpec(size=[0.2, 0.1, 0.1]), center=[0.3, 0.0, 0.25],
                       rest_on_terrain=True, muscles=MuscleSpec(groups=[2, 1, 1]))]
    if cover:
        bodies.append(BodySpec(name="cover", shape=ShapeSpec(kind="layer", thickness=0.04),
                               material=MaterialSpec(kind=cover)))
    return Scene(size=[0.6, 0.4, 0.5], dx=1 / 24, dtype="float64", bodies=bodies,
                 terrain=TerrainSpec(kind="flat", height=0.1, friction=0.5))


def designs(base) -> list:
    """Three designs: the second three times stiffer (a smaller CFL step), each of its own mass."""
    return [replace(base, youngs_modulus=np.where(base.robot, stiffness, base.youngs_modulus),
                    volume=base.volume * (1 + 0.1 * b)) for b, stiffness in enumerate([1e4, 3e4, 1e4])]


@pytest.mark.parametrize("cover", [None, "sand"])
def test_a_batch_equals_its_members_simulated_one_at_a_time(cover):
    s = scene(cover)
    members = designs(build_particles(s))
    actions = np.random.default_rng(0).uniform(-0.3, 0.3, (FRAMES, len(members), members[0].n_actuators))
    batch = BatchSimulator(s, members)
    assert [t.substeps for t in batch.member_steps] == [2, 3, 2] and batch.timestep.substeps == 3
    for a in actions:
        batch.step(a)
    together = [batch.split(a) for a in batch.particles_state()]
    batch.close()
    for b, member in enumerate(members):
        alone = Simulator(s, member)
        for a in actions:
            alone.step(a[b])
        for name, value, batched in zip("xvCF", alone.particles_state(), together):
            np.testing.assert_allclose(batched[b], value, rtol=0, atol=1e-12, err_msg=f"member {b}: {name}")
        assert np.abs(alone.particles_state()[0] - member.x).max() > 1e-3  # it moved: the check is not vacuous
        alone.close()


def test_a_member_that_fails_is_named_and_actions_are_one_row_per_member():
    s = scene(None)
    members = designs(build_particles(s))
    batch = BatchSimulator(s, members)
    with pytest.raises(ValueError, match=r"actions must have shape \(3, 2\) \(one row per member\), got \(4,\)"):
        batch.step(np.zeros(4))
    x = np.concatenate([m.x for m in members])
    x[batch.starts[1] + 5] = np.nan  # member 1 goes non-finite in its first substep
    batch.set_initial_state(x=x)
    with pytest.raises(SimulationError, match="first: particle [0-9]+ of member 1 of body 'robot'"):
        batch.step()
    finite = [np.isfinite(part).all() for part in batch.split(batch.particles_state()[1])]
    assert finite == [True, False, True]  # members share no grid node
    batch.close()


def test_a_population_plays_together_as_each_pair_plays_alone():
    """play_population (one batch) and play (one episode at a time) give the same returns and
    trajectories for designs of different sizes and controllers, with a task that keeps state."""
    recipe = resolve_recipe({
        "environment": {"name": "ground", "dx": 1 / 32, "horizon": 3, "dtype": "float64",
                        "terrain": {"height": 0.1, "friction": 0.5}, "robot": {"size": [0.16, 0.08, 0.08]},
                        "task": {"name": "waypoint_following"}},
        "representation": {"name": "particle"}, "controller": {"name": "mlp"},
        "optimizer": {"name": "evaluate"}})
    parts = build_parts(recipe)
    env, representation, controller = parts.environment, parts.representation, parts.controller
    rng = np.random.default_rng(0)
    representation.setup(env.design_space, rng)
    controller.setup(env.action_dim, env.observation_dim, env.control_dt, rng)
    pairs = []
    for b in range(3):  # designs of their own size and stiffness, controllers of their own
        for p in controller.parameters():
            p.data += 0.5 * p.data.new_tensor(rng.standard_normal(tuple(p.shape)))
        design, ctrl = candidate(representation, controller, [], None)
        front = env.design_space.points[:, 0]
        design.occupancy[front > front.max() - 0.03 * b] = 0.0  # shorter bodies: fewer particles
        design.stiffness *= 1 + b
        pairs.append((design, ctrl))
    together = play_population(env, [d for d, _ in pairs], [c for _, c in pairs], seed=0)
    assert len({round(r.episode_return, 6) for r in together}) == 3  # three different episodes
    for (design, ctrl), record in zip(pairs, together):
        alone = play(env, design, ctrl, seed=0)
        assert record.episode_return == pytest.approx(alone.episode_return, rel=1e-9, abs=1e-12)
        np.testing.assert_allclose(record.com, alone.com, rtol=0, atol=1e-12)
        np.testing.assert_allclose(record.actions, alone.actions, rtol=0, atol=1e-12)
    env.close()
