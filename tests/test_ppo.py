"""The `ppo` optimizer on the physics-free toy environment: it runs end to end, `codesign eval`
replays exactly the logged deterministic episode, a resumed run equals an uninterrupted one,
and settings it cannot honour fail before any simulation."""
import json

import numpy as np
import pytest

from codesign import runner
from codesign.errors import RecipeError
from codesign.recipe import resolve_recipe

TOY_PPO = {
    "name": "toy-ppo",
    "seed": 3,
    "environment": {"name": "toy", "horizon": 4, "target_range": 0.02},
    "representation": {"name": "constant"},
    "controller": {"name": "mlp", "hidden": [8]},
    "optimizer": {"name": "ppo", "total_timesteps": 192, "timesteps_per_iteration": 64, "n_steps": 32,
                  "batch_size": 16, "n_epochs": 2, "learning_rate": 3e-3},
}
TOY_SINE = {**TOY_PPO, "controller": {"name": "sine", "frequencies": [6.0, 12.0], "phases": 2},
            "optimizer": {**TOY_PPO["optimizer"], "policy": "sine"}}


def metrics(run_dir) -> list[dict]:
    return [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]


@pytest.mark.parametrize("recipe", [TOY_PPO, TOY_SINE], ids=["mlp", "sine"])
def test_ppo_runs_and_eval_replays_the_best_deterministic_episode(tmp_path, recipe):
    run_dir = runner.run(resolve_recipe(recipe), run_dir=tmp_path / "run", progress=False)
    rows = metrics(run_dir)
    assert len(rows) == 3
    assert [r["timesteps"] for r in rows] == [64, 128, 192]
    assert all(r["train_episodes"] == 16 and np.isfinite(r["train_return"]) for r in rows)  # 64 steps / horizon 4
    assert all("value_loss" in r and "approx_kl" in r for r in rows)
    info = json.loads((run_dir / "best" / "info.json").read_text())
    assert info["episode_return"] == max(r["episode_return"] for r in rows) == rows[-1]["best_return"]
    assert runner.evaluate_best(run_dir) == [info["episode_return"]]  # same seed, same controller: exact


def test_the_controller_is_the_policy_mean(tmp_path):
    """After an iteration, SB3's deterministic action squashed by bound*tanh equals the controller's."""
    from codesign.plugins import get_registry
    from codesign_basics.config import MLPConfig
    from codesign_basics.mlp import MLPController
    from codesign_optimizers.config import PPOConfig
    from codesign_optimizers.ppo import PPO

    env = get_registry().get("environment", "toy").load_factory()(
        resolve_recipe(TOY_PPO).sections["environment"].config)
    rep = get_registry().get("representation", "constant").load_factory()(
        resolve_recipe(TOY_PPO).sections["representation"].config)
    rng = np.random.default_rng(0)
    rep.setup(env.design_space, rng)
    controller = MLPController(MLPConfig(hidden=[8], activation="elu", bound=0.2))
    controller.setup(env.action_dim, env.observation_dim, env.control_dt, rng)
    ppo = PPO(PPOConfig(total_timesteps=32, timesteps_per_iteration=32, n_steps=32, batch_size=16, n_epochs=1))
    ppo.setup(env, rep, controller, rng=rng, run_dir=tmp_path)
    ppo.step()
    for obs in (np.zeros(3), np.array([1.0, 2.0, 3.0])):
        mean, _ = ppo.model.predict(obs.astype(np.float32), deterministic=True)
        np.testing.assert_allclose(0.2 * np.tanh(mean), controller(obs, 0).detach().numpy(), atol=1e-6)


def test_resumed_run_ends_with_the_numbers_of_an_uninterrupted_one(tmp_path):
    whole = runner.run(resolve_recipe(TOY_PPO), run_dir=tmp_path / "whole", progress=False)
    half = {**TOY_PPO, "optimizer": {**TOY_PPO["optimizer"], "total_timesteps": 64}}
    part = runner.run(resolve_recipe(half), run_dir=tmp_path / "part", progress=False)
    config = part / "config.yaml"
    config.write_text(config.read_text().replace("total_timesteps: 64", "total_timesteps: 192"))  # the run goes on
    runner.resume(part, progress=False)
    drop = ("wall_time",)
    assert [{k: v for k, v in r.items() if k not in drop} for r in metrics(part)] == \
        [{k: v for k, v in r.items() if k not in drop} for r in metrics(whole)]


@pytest.mark.parametrize("change, pattern", [
    ({"optimizer": {"optimize": "design"}}, r"optimizer.optimize: 'design' is not supported by this optimizer; "
                                            r"allowed: control"),
    ({"optimizer": {"timesteps_per_iteration": 50}}, r"optimizer.timesteps_per_iteration: 50 is not a multiple "
                                                     r"of optimizer.n_steps \(32\)"),
    ({"controller": {"name": "mlp", "output": "sine_weights"}}, r"optimizer.policy 'mlp' needs the 'mlp' "
                                                                r"controller with output: action"),
    ({"controller": {"name": "sine"}}, r"optimizer.policy 'mlp' needs the 'mlp' controller.*got SineController"),
    ({"optimizer": {"policy": "sine"}}, r"optimizer.policy 'sine' needs the 'sine' controller"),
    ({"optimizer": {"n_envs": 2}}, r"optimizer.n_envs: 2 needs an environment that simulates populations.*"
                                   r"ToyEnvironment plays one at a time \(allowed here: 1\)"),
    ({"optimizer": {"n_envs": 3}}, r"optimizer.timesteps_per_iteration: 64 is not a multiple of optimizer.n_steps x "
                                   r"optimizer.n_envs \(32 x 3 = 96\)"),
])
def test_settings_ppo_cannot_honour_fail_before_any_episode(tmp_path, change, pattern):
    recipe = {**TOY_PPO, **{k: ({**TOY_PPO[k], **v} if k == "optimizer" else v) for k, v in change.items()}}
    with pytest.raises(RecipeError, match=pattern):
        runner.run(resolve_recipe(recipe), run_dir=tmp_path / "run", progress=False)
    assert not (tmp_path / "run" / "best").exists()


@pytest.mark.slow
def test_a_population_of_episodes_equals_episodes_one_at_a_time():
    """EpisodesVecEnv with n_envs = 2 on an MPM environment (one batched simulator): each member's
    rewards, observations and last observation are those of the same actions played alone, and
    the next episodes start at once."""
    from codesign.plugins import get_registry
    from codesign_optimizers.ppo import EpisodesVecEnv

    recipe = resolve_recipe({"name": "pop", "environment": {"name": "ground", "dx": 0.04166, "horizon": 3,
                                                            "terrain": {"height": 0.13}},
                             "representation": {"name": "particle"}, "controller": {"name": "mlp"},
                             "optimizer": {"name": "ppo"}})
    registry = get_registry()
    env = registry.get("environment", "ground").load_factory()(recipe.sections["environment"].config)
    rep = registry.get("representation", "particle").load_factory()(recipe.sections["representation"].config)
    rep.setup(env.design_space, np.random.default_rng(0))
    design = rep()
    try:
        actions = np.random.default_rng(1).normal(size=(env.horizon, 2, env.action_dim))
        together = EpisodesVecEnv(env, design, bound=0.3, n_envs=2)
        first = together.reset()
        steps = [together.step(a) for a in actions]
        for b in range(2):
            alone = EpisodesVecEnv(env, design, bound=0.3, n_envs=1)
            np.testing.assert_allclose(alone.reset()[0], first[b], rtol=1e-5, atol=1e-6)
            for t, a in enumerate(actions):
                observation, reward, done, info = alone.step(a[b:b + 1])
                expected = steps[t][3][b]["terminal_observation"] if t == env.horizon - 1 else steps[t][0][b]
                np.testing.assert_allclose(observation[0] if t < env.horizon - 1 else info[0]["terminal_observation"],
                                           expected, rtol=1e-4, atol=1e-5)
                np.testing.assert_allclose(reward[0], steps[t][1][b], rtol=1e-4, atol=1e-6)
                assert done[0] == steps[t][2][b] == (t == env.horizon - 1)
            assert alone.returns[0] == pytest.approx(together.returns[b], rel=1e-4, abs=1e-6)
        np.testing.assert_allclose(steps[-1][0], first, rtol=1e-5, atol=1e-6)  # the next episodes have started
    finally:
        env.close()


@pytest.mark.slow
@pytest.mark.parametrize("rollout", [{"n_steps": 50}, {"n_steps": 25, "n_envs": 4}], ids=["one", "population"])
def test_ppo_on_the_mpm_ground(tmp_path, rollout):
    recipe = {"name": "ground-ppo", "seed": 0,
              "environment": {"name": "ground", "dx": 0.04166, "horizon": 5, "terrain": {"height": 0.13}},
              "representation": {"name": "particle"}, "controller": {"name": "mlp", "hidden": [16]},
              "optimizer": {"name": "ppo", "total_timesteps": 200, "timesteps_per_iteration": 100, "batch_size": 25,
                            "n_epochs": 2, **rollout}}
    run_dir = runner.run(resolve_recipe(recipe), run_dir=tmp_path / "run", progress=False)
    rows = metrics(run_dir)
    assert [r["timesteps"] for r in rows] == [100, 200] and all(r["train_episodes"] == 20 for r in rows)
    assert runner.evaluate_best(run_dir) == [rows[-1]["best_return"]]
