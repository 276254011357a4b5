"""The spring contact (`terrain.contact: spring`, engine/contact.py) against known answers: Coulomb's
statics and sliding on an incline at two steps, a resting body's sink under its weight, no
propulsion on a frictionless floor, a population equal to its members. Its gradients:
tests/mpm/test_gradients_elastic_and_water.py (on a slope, all stuck, all slipping)."""
import math
from dataclasses import replace

import numpy as np
import pytest

from codesign_mpm import BodySpec, MaterialSpec, Scene, ShapeSpec, TerrainSpec, build_particles
from codesign_mpm.engine import Simulator
from test_engine_physics import downhill_travel, gait_distance, incline_scene

DX = 1 / 32
PIC_TIME = 0.265  # flip 0.99 at the quick start's 2.7 ms step, as a time


def block_scene(terrain: TerrainSpec, center: list[float]) -> Scene:
    """The incline tests' block, lying on flat terrain."""
    return Scene(size=[1.0, 1.0, 0.5], dx=DX, flip=0.99, pic_time=PIC_TIME, terrain=terrain,
                 bodies=[BodySpec(shape=ShapeSpec(size=[0.16, 0.08, 0.08]), center=center,
                                  material=MaterialSpec(youngs_modulus=1e5))])


@pytest.mark.parametrize("cfl", [0.4, 0.1])
@pytest.mark.parametrize("theta_deg", [20.0, 35.0])
def test_a_block_holds_below_the_friction_angle_and_slides_at_coulombs_rate_above(theta_deg, cfl):
    """mu 0.5 (friction angle 26.6 degrees). At 20: after settling (frame 20) it creeps under a tenth of
    a cell in the next second (measured 0.0005 and 0.006 cells at cfl 0.4 and 0.1); at 35 it slides
    with g (sin - mu cos) within 5% (measured: 0.6232 and 0.6231 against 0.6232)."""
    mu, g = 0.5, 3.8
    theta = math.radians(theta_deg)
    scene = incline_scene(theta_deg, mu, "spring", cfl=cfl, flip=0.99, pic_time=PIC_TIME)
    travel = downhill_travel(scene, 145 if math.tan(theta) <= mu else 60)
    if math.tan(theta) <= mu:
        assert abs(travel[19]) < DX / 4 and abs(travel[144] - travel[19]) < 0.1 * DX
    else:
        t = np.arange(1, 61) * scene.frame_dt
        accel = 2 * np.polyfit(t[20:], travel[20:], 2)[0]
        assert accel == pytest.approx(g * (math.sin(theta) - mu * math.cos(theta)), rel=0.05)


@pytest.mark.parametrize("stiffness", [3e4, 2e6])
def test_a_resting_body_sinks_by_its_weight_over_area_and_stiffness(stiffness):
    """The contact's stiffness is a pressure per metre of depth: a block of weight W on its footprint A
    rests W / (A stiffness) deep (measured: 10.13 and 0.152 mm, as predicted to 3 digits). The terrain
    lies 6 cells up: a bottom layer sunk near the wall band would lean on its held nodes."""
    h0 = 0.2
    scene = block_scene(TerrainSpec(height=h0, friction=0.5, contact="spring", contact_stiffness=stiffness),
                        [0.5, h0 + 0.04, 0.25])
    particles = build_particles(scene)
    sim = Simulator(scene, particles)
    try:
        for _ in range(150):
            sim.step()
        y = sim.particles_state()[0][:, 1]
    finally:
        sim.close()
    bottom = particles.x[:, 1] < particles.x[:, 1].min() + 1e-6
    spacing = particles.volume[bottom] ** (1 / 3)
    depth = np.mean(h0 + 0.5 * spacing - y[bottom])
    weight = float((particles.volume * particles.density).sum()) * 3.8
    area = float(spacing.sum() * spacing.mean())  # the bottom layer's particles tile the footprint
    assert depth == pytest.approx(weight / (area * stiffness), rel=0.10)


def test_a_frictionless_floor_gives_no_propulsion():
    """The travelling gait of docs/accuracy.md moves the box about 25 mm in a second with mu 0.5; on a
    frictionless floor the spring contact pushes only along the normal (measured: under 1 um)."""
    assert abs(gait_distance(contact="spring", pic_time=PIC_TIME, friction=0.0)) < 1e-4 * DX


def test_a_population_plays_as_its_members_do():
    """Springs are particle state: a batch of two designs (one sitting out substeps, being stiffer)
    carries each member's springs as the member alone does."""
    from codesign_mpm.engine.batch import BatchSimulator

    scene = block_scene(TerrainSpec(height=0.1, friction=0.5, contact="spring"), [0.5, 0.14 + DX / 8, 0.25])
    particles = build_particles(scene)
    stiff = replace(particles, youngs_modulus=particles.youngs_modulus * 4)
    alone = []
    for member in (particles, stiff):
        sim = Simulator(scene, member)
        for _ in range(20):
            sim.step()
        alone.append((sim.particles_state()[0], sim.contact_springs()))
        sim.close()
    batch = BatchSimulator(scene, [particles, stiff])
    try:
        for _ in range(20):
            batch.step()
        x, springs = batch.particles_state()[0], batch.contact_springs()
    finally:
        batch.close()
    for b, (x_alone, u_alone) in enumerate(alone):
        part = slice(b * particles.n, (b + 1) * particles.n)
        scale = np.abs(u_alone).max()
        assert scale > 0  # something stuck
        np.testing.assert_allclose(x[part], x_alone, atol=1e-5)
        # float32 sums in another order: a contact at the stick-slip edge may tip either way
        assert np.abs(springs[part] - u_alone).max() < 0.1 * scale


@pytest.mark.slow
def test_a_closed_loop_episode_carries_the_springs_from_step_to_step():
    """A closed-loop episode is one autograd node per control step (bridge.step_frame): the springs
    are part of the state it hands on, so its loss is minus the return of the same episode stepped
    (a reset spring at every step would change it), and its gradient matches central differences."""
    import torch

    from codesign_basics.config import MLPConfig
    from codesign_basics.mlp import MLPController
    from codesign_mpm.environment.config import PRESET_CONFIGS, PRESETS, RobotConfig, TerrainConfig
    from codesign_mpm.environment.env import LocomotionEnv
    from test_episodes import parts, stepped_return

    config = PRESET_CONFIGS["ground"](dx=1 / 32, horizon=4, dtype="float64", pic_time=PIC_TIME,
                                      terrain=TerrainConfig(height=0.1, friction=0.5, contact="spring"),
                                      robot=RobotConfig(size=[0.16, 0.08, 0.08]))
    env = LocomotionEnv(config, PRESETS["ground"])
    torch.set_default_dtype(torch.float64)
    try:
        rep, controller = parts(env, MLPController(MLPConfig(hidden=[16], init_std=1.0)))
        episode = env.differentiable_episode(rep(), controller)
        assert float(episode.loss) == pytest.approx(-stepped_return(env, rep, controller), rel=1e-9, abs=1e-12)
        episode.loss.backward()
        weight = controller.parameters()[0]
        analytic = weight.grad[0, 0].item()
        values = []
        for eps in (1e-4, -1e-4):
            with torch.no_grad():
                weight[0, 0] += eps
                values.append(float(env.differentiable_episode(rep(), controller).loss))
                weight[0, 0] -= eps
        assert analytic == pytest.approx((values[0] - values[1]) / 2e-4, rel=1e-4, abs=1e-4 * weight.grad.abs().max().item())
    finally:
        torch.set_default_dtype(torch.float32)
        env.close()


@pytest.mark.slow
@pytest.mark.parametrize("mu, stretch", [(0.5, 1e-5), (0.02, 2e-4)], ids=["sticking", "slipping"])
def test_the_springs_initial_values_get_their_gradient(mu, stretch):
    """A block pressed 0.1 mm into the terrain, its bottom layer's springs stretched at the start: the
    gradient of where its particles end up with respect to a contact particle's initial spring
    matches central differences, stuck (mu 0.5: the spring's pull, about 5e-3 N, under Coulomb's
    0.02 N) and slipping (mu 0.02: a pull of 0.1 N against 7e-4 N, the spring at the cap)."""
    h0 = 0.2
    scene = Scene(size=[1.0, 1.0, 0.5], dx=DX, dtype="float64", flip=0.99, pic_time=PIC_TIME,
                  terrain=TerrainSpec(height=h0, friction=mu, contact="spring"),
                  bodies=[BodySpec(shape=ShapeSpec(size=[0.08, 0.04, 0.04]), center=[0.5, h0 + 0.03, 0.25],
                                   material=MaterialSpec(youngs_modulus=1e5))])
    particles = build_particles(scene)
    bottom = np.flatnonzero(particles.x[:, 1] < particles.x[:, 1].min() + 1e-6)
    depth = particles.x[bottom[0], 1] - h0 - particles.volume[bottom[0]] ** (1 / 3) / 2 + 1e-4
    particles = replace(particles, x=particles.x - [0.0, depth, 0.0])  # the bottom layer 0.1 mm deep
    springs = np.zeros((particles.n, 3))
    springs[bottom, 0] = stretch  # along +x: pulls the layer back towards -x
    weights = np.random.default_rng(0).normal(size=(particles.n, 3)) / particles.n
    sim = Simulator(scene, particles, requires_grad=True, max_frames=3, checkpoint_every=4)
    try:
        def loss(u) -> float:
            sim.set_initial_state(u=u)
            return float((weights * sim.rollout(np.zeros((3, 0)), checkpoint_every=4).x).sum())

        loss(springs)
        gradient = sim.backward(x=weights).u0
        p = bottom[len(bottom) // 2]
        assert np.abs(gradient[bottom]).max() > 0
        for axis in (0, 2):
            plus, minus = springs.copy(), springs.copy()
            plus[p, axis] += 1e-7
            minus[p, axis] -= 1e-7
            numeric = (loss(plus) - loss(minus)) / 2e-7
            assert gradient[p, axis] == pytest.approx(numeric, rel=1e-4, abs=1e-4 * np.abs(gradient).max())
    finally:
        sim.close()
