"""Locomotion environments on the real engine (forward only, dx = 1/32 to stay fast)."""

import json
import warnings
from pathlib import Path

import numpy as np
import pytest

from codesign.cli import main
from codesign.errors import RecipeError
from codesign.interfaces import DesignFields
from codesign_mpm.environment.config import PRESET_CONFIGS, PRESETS, LocomotionConfig, RobotConfig, TaskConfig, TerrainConfig
from codesign_mpm.environment.env import LocomotionEnv

GRAVITY = 3.8
QUICKSTART = Path(__file__).resolve().parents[2] / "recipes" / "quickstart.yaml"


def make_env(preset: str = "ground", task: str = "movement_speed", direction=(1.0, 0.0, 0.0),
             horizon: int = 25) -> LocomotionEnv:
    config = LocomotionConfig(dx=1 / 32, horizon=horizon, terrain=TerrainConfig(height=0.1),
                              task=TaskConfig(name=task, direction=list(direction)))
    return LocomotionEnv(config, PRESETS[preset])


def full_design(env: LocomotionEnv, occupancy=None) -> DesignFields:
    base = env.base_particles
    return DesignFields(occupancy=np.ones(base.n) if occupancy is None else occupancy,
                        stiffness=base.youngs_modulus.copy(), muscle=base.muscle.copy(), fiber=base.fiber.copy())


def rollout(env: LocomotionEnv, actions) -> tuple[np.ndarray, list]:
    """COM displacement over an episode and its step results."""
    start = env.reset()[:3]
    results = [env.step(a) for a in actions]
    return results[-1].observation[:3] - start, results


@pytest.fixture
def env():
    environment = make_env()
    yield environment
    environment.close()


def test_spaces_observation_and_episode_end(env):
    n = env.base_particles.n
    assert env.design_space.points.shape == (n, 3) and env.design_space.n_actuators == 4
    assert (env.action_dim, env.observation_dim, env.control_dt) == (4, 9, 8e-3)
    obs = env.reset(full_design(env))
    assert obs.shape == (9,)
    np.testing.assert_allclose(obs[:3], env.base_particles.x.mean(0), atol=1e-5)  # uniform mass
    np.testing.assert_array_equal(obs[6:], [1.0, 0.0, 0.0])
    for t in range(env.horizon):
        result = env.step(np.zeros(4))
        assert result.done == (t == env.horizon - 1)
    np.testing.assert_array_equal(result.info["com"], result.observation[:3])


def test_robot_rests_without_action_and_moves_with_a_gait(env):
    steps = range(env.horizon)
    still, _ = rollout(env, [np.zeros(4) for _ in steps])
    gait, _ = rollout(env, [0.3 * np.sin(0.6 * t + np.arange(4) * np.pi / 2) for t in steps])
    assert np.abs(still[[0, 2]]).max() < 1e-4
    assert abs(gait[0]) > 20 * max(abs(still[0]), 1e-5)


def test_a_pushed_robot_decelerates_at_mu_g_on_ground_and_on_ice():
    """Launched at 1 unit/s, a sliding body's velocity falls linearly at mu g: 1.9 on ground, 0.19 on
    ice (a frictionless floor would give 0, so the bound on ice tells the two apart)."""
    for name in ("ground", "ice"):
        env = make_env(name, horizon=40)
        env.base_particles.v[:, 0] = 1.0
        try:
            _, results = rollout(env, [np.zeros(4)] * env.horizon)
        finally:
            env.close()
        velocity = np.array([r.reward for r in results])  # movement_speed: COM velocity along x
        assert velocity.min() > 0.2, "still sliding at the end, or the fit below means nothing"
        t = env.control_dt * np.arange(1, env.horizon + 1)
        slope = np.polyfit(t[5:], velocity[5:], 1)[0]  # after the first frames of landing on the ground
        assert -slope == pytest.approx(PRESETS[name].friction * GRAVITY, rel=0.25), name


@pytest.mark.parametrize("omega, sign", [(2.0, 1), (-2.0, -1)])
def test_turning_rewards_counter_clockwise_spin_about_up(omega, sign):
    env = make_env(task="turning")
    x = env.base_particles.x
    env.base_particles.v[:] = np.cross([0.0, omega, 0.0], x - x.mean(0))  # rigid spin about +y
    try:
        env.reset()
        reward = env.step(np.zeros(4)).reward
    finally:
        env.close()
    assert sign * reward > 0.05  # ~ |omega| * mean distance from the axis, minus friction losses


def test_low_occupancy_removes_particles_and_scales_mass(env):
    env.reset(full_design(env))
    first = env.sim
    n = env.base_particles.n
    occupancy = np.where(env.base_particles.x[:, 0] < np.median(env.base_particles.x[:, 0]), 0.3, 0.8)
    env.reset(full_design(env, occupancy))
    kept = occupancy >= 0.5
    assert env.sim is not first and env.sim.n == kept.sum() < n
    np.testing.assert_allclose(env.particles.volume, env.base_particles.volume[kept] * 0.8)
    np.testing.assert_allclose(env.particles.x, env.base_particles.x[kept])
    assert np.isfinite(env.step(np.zeros(4)).observation).all()
    same = env.sim
    env.reset(full_design(env, np.where(kept, 0.6, 0.1)))  # same count: the simulator is reused
    assert env.sim is same


def test_a_stiffer_design_gets_a_smaller_time_step(env):
    env.reset(full_design(env))
    substeps = env.sim.timestep.substeps
    stiff = full_design(env)
    stiff.stiffness *= 4  # wave speed doubles, so the CFL bound halves
    env.reset(stiff)
    assert env.sim.timestep.substeps >= 2 * substeps - 1
    assert np.isfinite(env.step(np.full(4, env.scene.max_action)).observation).all()


def test_torch_designs_are_accepted():
    torch = pytest.importorskip("torch")
    env = make_env()
    design = full_design(env)
    occupancy = torch.ones(env.base_particles.n, requires_grad=True)
    try:
        obs = env.reset(DesignFields(occupancy, torch.tensor(design.stiffness), torch.tensor(design.muscle),
                                     torch.tensor(design.fiber)))
    finally:
        env.close()
    assert np.isfinite(obs).all()


def test_terrain_inside_the_wall_band_is_rejected_when_the_recipe_is_read(cli):
    """Checked before anything is built (`codesign show` refuses it), at the quality preset's dx too,
    and again at build for a config changed after it was read."""
    with pytest.raises(RecipeError, match=r"environment.terrain.height: 0.05 is below the wall band"):
        LocomotionConfig(dx=1 / 32, terrain=TerrainConfig(height=0.05))
    code, _, err = cli("show", "quickstart", "environment.quality=draft", "environment.dx=null",
                       "environment.terrain.height=0.08")
    assert code != 0 and "environment.terrain.height: 0.08 is below the wall band; must be >= 3 dx" in err
    code, _, err = cli("show", "quickstart", "environment.robot.muscle_stiffness_ratio=1.0")
    assert code != 0 and "environment.robot.muscle_stiffness_ratio: 1.0 is too strong for the body" in err
    config = LocomotionConfig(dx=1 / 32, terrain=TerrainConfig(height=0.1))
    config.terrain.height = 0.05
    with pytest.raises(RecipeError, match=r"environment.terrain.height: 0.05 is below the wall band"):
        LocomotionEnv(config, PRESETS["ground"])


def test_a_robot_near_the_wall_in_water_is_warned_about():
    """Pushing the water against the wall moves a robot (docs/studies.md), so it is warned about in
    the ocean; on ground the same position is fine."""
    def build(name: str, x: float) -> None:
        config = PRESET_CONFIGS[name](dx=1 / 32, horizon=2, terrain=TerrainConfig(height=0.1),
                                      robot=RobotConfig(size=[0.3, 0.1, 0.1], position=[x, 0.25]))
        LocomotionEnv(config, PRESETS[name]).close()

    with pytest.warns(UserWarning, match=r"environment.robot.position: .* 0.00625 m from the wall band along x"):
        build("ocean", 0.25)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        build("ocean", 0.45)
        build("ground", 0.25)


def test_no_shipped_study_puts_a_robot_in_water_near_a_wall():
    """Table 1's ocean cells were once measured with the animals 0.04 m from the wall band, a push
    off the wall ranked as swimming (docs/studies.md); every arm of every shipped study, at every
    scale, keeps its robot clear."""
    import yaml

    from codesign.recipe import RECIPES_DIR, resolve_recipe
    from codesign.study import arm_recipe, load_study
    from codesign_mpm.environment.env import _warn_wall_push

    checked = 0
    for path in sorted((RECIPES_DIR / "studies").glob("*.yaml")):
        for scale in ["cpu", *(yaml.safe_load(path.read_text())["study"].get("scales") or {})]:
            study = load_study(str(path), scale)
            for arm in study.arms:
                section = resolve_recipe(arm_recipe(study, arm), default_name=arm.slug).sections["environment"]
                preset = PRESETS.get(section.name)
                if preset is not None and section.config.resolved_cover(preset).kind == "water":
                    with warnings.catch_warnings():
                        warnings.simplefilter("error")
                        _warn_wall_push(section.config, preset)
                    checked += 1
    assert checked > 0  # the ocean arms were found


@pytest.mark.slow
def test_quickstart_recipe_runs_through_the_cli(tmp_path, capsys):
    """The README's main command, shortened: a co-design run that prints its progress and run dir."""
    run_dir = tmp_path / "run"
    with pytest.raises(SystemExit) as info:
        main(["run", str(QUICKSTART), "environment.horizon=10", "optimizer.iterations=3", "--run-dir", str(run_dir),
              "--no-progress"])
    captured = capsys.readouterr()
    assert info.value.code == 0 and captured.out.strip() == str(run_dir)
    assert "episode return: first" in captured.err and "learning_curve.png" in captured.err
    rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    assert [row["iteration"] for row in rows] == [0, 1, 2]
    assert all(np.isfinite(row["episode_return"]) and row["grad_norm_design"] > 0 for row in rows)
    assert json.loads((run_dir / "summary.json").read_text())["status"] == "completed"
    assert (run_dir / "best" / "design.npz").is_file() and (run_dir / "learning_curve.png").is_file()
