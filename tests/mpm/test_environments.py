"""The eight environment presets at test resolution (dx = 1/32): construction, forward, and
how robots interact with each ground cover (their gradients: test_gradients_*.py)."""
import numpy as np
import pytest

from codesign_mpm.environment.config import PRESET_CONFIGS, PRESETS, CoverConfig, RobotConfig, TerrainConfig
from codesign_mpm.environment.env import LocomotionEnv

ENVIRONMENTS = ["ground", "ice", "desert", "snow", "clay", "wetland", "shallow_water", "ocean"]
DX = 1 / 32
NARROW = [0.6, 0.5, 0.5]
"""A domain narrower than the presets' 1 m for what needs no room to travel: the robot (x from 0.15 to
0.35) keeps cover on every side, on about half the cover particles and 60% of the grid."""


def make_env(name: str, dtype: str = "float32", horizon: int = 50, **overrides) -> LocomotionEnv:
    """The registered preset at test resolution; the terrain is raised above the wall band."""
    terrain = overrides.pop("terrain", TerrainConfig(height=0.1, friction=PRESETS[name].friction))
    config = PRESET_CONFIGS[name](dx=DX, horizon=horizon, dtype=dtype, terrain=terrain, **overrides)
    return LocomotionEnv(config, PRESETS[name])


def test_every_paper_environment_is_registered_with_its_cover_in_the_config():
    assert sorted(PRESETS) == sorted(ENVIRONMENTS)
    kinds = {name: PRESET_CONFIGS[name]().cover.kind for name in ENVIRONMENTS}
    assert kinds == {"ground": "none", "ice": "none", "desert": "sand", "snow": "snow", "clay": "clay",
                     "wetland": "mud", "shallow_water": "water", "ocean": "water"}
    assert PRESET_CONFIGS["ocean"]().terrain.friction == 0.0
    assert PRESET_CONFIGS["ocean"]().robot.youngs_modulus == 1e5
    assert PRESET_CONFIGS["ice"]().terrain.friction == 0.05


@pytest.mark.parametrize("name", ["desert", "ocean"])
def test_the_cover_is_laid_around_the_robot_without_overlap(name):
    env = make_env(name)
    robot, cover = env.base_particles, env.cover_particles
    assert cover.n > 0 and not cover.robot.any()
    # no cover inside the robot's box (its particles' extent and half a spacing), nor under it: it
    # stands on the terrain (rest_on: terrain), not on cover particles
    half = env.spacing / 2 - 1e-9
    lo, hi = robot.x.min(0) - half, robot.x.max(0) + half
    assert not np.all((cover.x > lo) & (cover.x < hi), axis=1).any()
    footprint = np.all((cover.x[:, [0, 2]] > lo[[0, 2]]) & (cover.x[:, [0, 2]] < hi[[0, 2]]), axis=1)
    assert (cover.x[footprint, 1] > robot.x[:, 1].min()).all()
    thickness = PRESET_CONFIGS[name]().cover.thickness
    assert cover.x[:, 1].min() > 0.1 and cover.x[:, 1].max() < 0.1 + thickness
    if name == "ocean":  # water covers the robot
        assert cover.x[:, 1].max() > robot.x[:, 1].max()


def test_the_robot_and_the_cover_are_the_environments_particles_without_a_copy():
    """A terrain may hold millions of particles: the robot's and the cover's are views of one sampling,
    robot first, and the cover has no muscles."""
    env = make_env("desert")
    robot, cover, both = env.base_particles, env.cover_particles, env.particles
    assert np.shares_memory(robot.x, both.x) and np.shares_memory(cover.x, both.x)
    np.testing.assert_array_equal(np.concatenate([robot.x, cover.x]), both.x)
    assert cover.n_actuators == 0 and both.n_actuators == robot.n_actuators > 0
    assert not both.muscle[robot.n:].any() and both.robot[:robot.n].all() and not both.robot[robot.n:].any()


def random_actions(env, steps: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-0.3, 0.3, size=(steps, env.action_dim))


@pytest.mark.parametrize("name", ENVIRONMENTS)
def test_fifty_control_steps_with_random_actions_stay_finite_and_move_the_robot(name):
    env = make_env(name)
    try:
        start = env.reset()[:3]
        for action in random_actions(env, 50):
            result = env.step(action)
        x, v, _, F = env.sim.particles_state()
        assert np.isfinite(x).all() and np.isfinite(v).all() and np.isfinite(F).all()
        assert np.linalg.norm(result.observation[:3] - start) > 3e-4  # a hundredth of a cell (mud, water: 6e-4)
    finally:
        env.close()


def sink_depth(name: str, frames: int = 60) -> float:
    """How far a robot (twice water's density) set on top of a deep (0.1) layer sinks, without acting."""
    env = make_env(name, size=NARROW, robot=RobotConfig(rest_on="cover", density=2e3),
                   cover=CoverConfig(**{**vars(PRESET_CONFIGS[name]().cover), "thickness": 0.1}))
    try:
        start = env.reset()[1]
        for _ in range(frames):
            result = env.step(np.zeros(env.action_dim))
        return start - result.observation[1]
    finally:
        env.close()


@pytest.mark.slow
def test_a_robot_sinks_into_deep_snow_and_mud_more_than_into_packed_sand():
    sand, snow, mud = (sink_depth(name) for name in ("desert", "snow", "wetland"))
    # measured (dx 1/32, NARROW): sand 0.0019 (settling into contact), snow 0.0116, mud 0.0267 (1 m wide: 0.0020,
    # 0.012, 0.027)
    assert sand < 0.3 * DX
    assert snow > sand + 0.25 * DX and mud > snow + 0.25 * DX, (sand, snow, mud)


def test_a_body_lighter_than_water_floats_and_a_heavier_one_sinks():
    """Dropped onto the ocean's surface, a robot of half water's density stays up; one of three
    times water's density goes under, more than a cell deep within 100 steps (then slowly: at dx
    1/32 the water must flow around a body only 2.5 cells thick, which makes the drag large)."""
    surface = 0.1 + PRESET_CONFIGS["ocean"]().cover.thickness
    final = {}
    for density in (500.0, 3000.0):
        env = make_env("ocean", robot=RobotConfig(density=density, youngs_modulus=1e5, rest_on="cover"))
        try:
            env.reset()
            for _ in range(100):
                result = env.step(np.zeros(env.action_dim))
            final[density] = result.observation
        finally:
            env.close()
    assert final[500.0][1] > surface  # measured 0.278 (surface 0.25)
    assert final[3000.0][1] < surface - DX  # measured 0.212 (0.209 after 160 steps, still sinking)


def test_a_design_smaller_than_its_workspace_sits_in_water_not_in_a_hole_that_carries_it_away():
    """The cover is laid around the whole workspace; what a design leaves empty of it is filled with
    the cover's material. A corner of a box of water's density, at rest in the ocean, then stays where it
    is: it moves 0.008 cells in 0.4 s (measured; without the fill the water fell into the empty part
    and pushed it 0.062 cells, and the ocean studies' fish, which fills a tenth of its workspace,
    drifted back 0.065 in 0.4 s, more than the swimming it was trained for)."""
    from codesign.interfaces import DesignFields

    env = make_env("ocean", robot=RobotConfig(size=[0.3, 0.15, 0.15], density=1e3, youngs_modulus=1e5))
    try:
        base = env.base_particles
        front = ((base.x[:, 0] < np.quantile(base.x[:, 0], 0.35))
                 & (base.x[:, 1] < np.quantile(base.x[:, 1], 0.5))).astype(float)  # a lower front corner
        design = DesignFields(front, np.full(base.n, 1e5), base.muscle, base.fiber)
        start = env.reset(design)[:3]
        particles = env.particles
        water = ~particles.robot
        assert particles.robot.sum() == front.sum()
        assert water.sum() == env.cover_particles.n + base.n - front.sum()  # the rest of the workspace is water
        assert (particles.material[water] == env.cover_particles.material[0]).all()
        for _ in range(50):
            result = env.step(np.zeros(env.action_dim))
        assert np.linalg.norm(result.observation[:3] - start) < 0.025 * DX
    finally:
        env.close()


def test_a_differentiable_episode_of_a_design_smaller_than_its_workspace_takes_the_fill_as_constants():
    """The gradient path gets the fill too (it once built its inputs from the cover alone), and the
    design's gradient reaches the occupancy of the particles it keeps."""
    import torch

    from codesign.interfaces import DesignFields
    from codesign_basics.config import SineConfig
    from codesign_basics.sine import SineController
    from codesign_mpm.environment.episode import run_episode

    env = make_env("ocean", horizon=3, robot=RobotConfig(size=[0.3, 0.15, 0.15], youngs_modulus=1e5))
    try:
        base = env.base_particles
        corner = (base.x[:, 0] < np.quantile(base.x[:, 0], 0.35)) & (base.x[:, 1] < np.quantile(base.x[:, 1], 0.5))
        occupancy = torch.tensor(np.where(corner, 0.9, 0.1), requires_grad=True)
        design = DesignFields(occupancy, np.full(base.n, 1e5), base.muscle, base.fiber)
        controller = SineController(SineConfig())
        controller.setup(env.action_dim, env.observation_dim, env.control_dt, np.random.default_rng(0))
        episode = run_episode(env, design, controller)
        (-episode.rewards.sum()).backward()
        grad = occupancy.grad.numpy()
        assert np.isfinite(grad).all() and np.abs(grad[corner]).max() > 0 and (grad[~corner] == 0).all()
    finally:
        env.close()


def test_a_recipe_setting_part_of_the_robot_or_cover_keeps_the_environments_own_defaults():
    """Giving `environment.robot.size` once replaced the ocean's robot (E 1e5) by the generic one
    (E 1e4), and `environment.cover.thickness` the ocean's water by no cover at all."""
    from codesign.recipe import resolve_recipe

    data = {"environment": {"name": "ocean", "robot": {"size": [0.3, 0.15, 0.15]}, "cover": {"thickness": 0.2}},
            "representation": {"name": "particle"}, "controller": {"name": "sine"}, "optimizer": {"name": "evaluate"}}
    config = resolve_recipe(data).sections["environment"].config
    assert config.robot.youngs_modulus == 1e5 and config.robot.size == [0.3, 0.15, 0.15]
    assert config.cover.kind == "water" and config.cover.thickness == 0.2
    data["environment"]["robot"]["youngs_modulus"] = 3e4  # what is given still wins
    assert resolve_recipe(data).sections["environment"].config.robot.youngs_modulus == 3e4
