"""The `ppo` optimizer on the physics-free toy environment: it runs end to end, `codesign eval`
replays exactly the logged deterministic episode, a resumed run equals an uninterrupted one,
and settings it cannot honour fail before any simulation."""
import json
import random

import numpy as np
import pytest
import torch

from codesign import runner
from codesign.errors import RecipeError
from codesign.interfaces import StepResult
from codesign.recipe import resolve_recipe
from toy_plugin import ToyEnvConfig, ToyEnvironment

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
NORMALIZED = {**TOY_PPO, "optimizer": {**TOY_PPO["optimizer"], "normalize": "both"}}


class PopulationToy(ToyEnvironment):
    """The toy environment playing populations: episode b's target is drawn from its own seed."""

    batched = True

    def reset_population(self, designs, seed=None) -> list[np.ndarray]:
        seeds = seed if isinstance(seed, list) else [seed] * len(designs)
        self.members = [ToyEnvironment(self.config) for _ in designs]
        return [member.reset(design, s) for member, design, s in zip(self.members, designs, seeds)]

    def step_population(self, actions: np.ndarray) -> list[StepResult]:
        return [member.step(action) for member, action in zip(self.members, actions)]


def toy_parts(environment: type[ToyEnvironment] = ToyEnvironment):
    """The toy environment, its constant design and an mlp controller (bound 0.2), set up from one generator."""
    from codesign_basics.config import MLPConfig
    from codesign_basics.mlp import MLPController
    from toy_plugin import ConstantConfig, ConstantRepresentation

    env, rep = environment(ToyEnvConfig(horizon=4, target_range=0.02)), ConstantRepresentation(ConstantConfig())
    rng = np.random.default_rng(0)
    rep.setup(env.design_space, rng)
    controller = MLPController(MLPConfig(hidden=[8], activation="elu", bound=0.2))
    controller.setup(env.action_dim, env.observation_dim, env.control_dt, rng)
    return env, rep, controller, rng


def toy_ppo(tmp_path, parts, normalize: str = "none", total_timesteps: int = 32, n_envs: int = 1):
    """PPO set up on `toy_parts()`, one rollout of 32 steps in all per iteration."""
    from codesign_optimizers.config import PPOConfig
    from codesign_optimizers.ppo import PPO

    env, rep, controller, rng = parts
    ppo = PPO(PPOConfig(total_timesteps=total_timesteps, timesteps_per_iteration=32, n_steps=32 // n_envs,
                        n_envs=n_envs, batch_size=16, n_epochs=1, normalize=normalize))
    ppo.setup(env, rep, controller, rng=rng, run_dir=tmp_path)
    return ppo


def metrics(run_dir) -> list[dict]:
    return [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]


@pytest.mark.parametrize("recipe", [TOY_PPO, TOY_SINE, NORMALIZED,
                                    {**TOY_SINE, "optimizer": {**TOY_SINE["optimizer"], "normalize": "rewards"}}],
                         ids=["mlp", "sine", "mlp-normalized", "sine-normalized-rewards"])
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


@pytest.mark.parametrize("normalize", ["none", "both"])
def test_the_controller_is_the_policy_mean(tmp_path, normalize):
    """After some iterations, SB3's deterministic action on the observation as it sees it (normalised
    by VecNormalize's running statistics, when on) squashed by bound*tanh equals the controller's on
    the raw observation: the statistics are folded into the controller's first layer."""
    parts = toy_parts()
    ppo, controller = toy_ppo(tmp_path, parts, normalize, total_timesteps=64), parts[2]
    ppo.step()
    ppo.step()
    seen = (lambda o: o) if normalize == "none" else ppo.normalizer.normalize_obs
    if normalize == "both":
        rms = ppo.normalizer.obs_rms
        assert np.all(np.abs(rms.mean) > 0.5) and np.all(np.abs(rms.var - 1) > 0.1)  # far from the identity
        # 2 iterations x (a reset + 32 steps), one observation each: the evaluation episodes added none
        assert rms.count == pytest.approx(1e-4 + 2 * 33)
    for obs in (np.zeros(3), np.array([1.0, 2.0, 3.0]), np.array([4.0, -2.0, 7.5])):
        mean, _ = ppo.model.predict(seen(obs.astype(np.float32)), deterministic=True)
        np.testing.assert_allclose(0.2 * np.tanh(mean), controller(obs, 0).detach().numpy(), atol=1e-6)


def test_ppo_leaves_the_global_random_generators_alone(tmp_path):
    """SB3 draws from (and its seed= would reseed) python's, numpy's and torch's global generators:
    PPO runs it on its own states, so the caller's are the same after setup and an iteration."""
    parts = toy_parts()  # (torch.nn.Linear draws from torch's generator as the controller is set up)
    random.seed(11)
    np.random.seed(12)
    torch.manual_seed(13)
    before = random.getstate(), np.random.get_state()[1].copy(), torch.get_rng_state()
    ppo = toy_ppo(tmp_path, parts, "both")
    ppo.step()
    assert random.getstate() == before[0]
    np.testing.assert_array_equal(np.random.get_state()[1], before[1])
    assert torch.equal(torch.get_rng_state(), before[2])
    assert not np.array_equal(ppo.random["numpy"][1], before[1])  # its own states moved on instead


def test_a_population_resets_each_episode_with_its_own_seed(tmp_path):
    """EpisodesVecEnv draws one seed per episode (the toy target is random per seed), so the members of
    a population play distinct episodes, and the next population others again; PPO trains on them."""
    from codesign_optimizers.ppo import EpisodesVecEnv

    env = PopulationToy(ToyEnvConfig(horizon=2, target_range=1.0))
    episodes = EpisodesVecEnv(env, None, bound=1.0, n_envs=3, episode_seed=5)
    episodes.reset()
    first = np.array([m.target for m in env.members])
    _, rewards, _, _ = episodes.step(np.zeros((3, env.action_dim)))
    assert len(np.unique(rewards)) == 3 and len(np.unique(first, axis=0)) == 3
    episodes.step(np.zeros((3, env.action_dim)))  # the horizon: the next episodes start at once
    assert not np.isin(np.array([m.target for m in env.members]), first).any()

    ppo = toy_ppo(tmp_path, toy_parts(PopulationToy), "both", n_envs=2)
    row = ppo.step()
    assert row["train_episodes"] == 8 and len(set(ppo.gym.returns)) == 8  # 2 x 16 steps / horizon 4


@pytest.mark.parametrize("bias", ["per_basis", "per_actuator"])
def test_the_sine_policy_head_is_the_sine_controller(bias):
    """SB3's linear head on the sine basis holds alpha and the bias: per_basis beta (K, I, J) acts by its
    sum, per_actuator beta (K,) one to one. Copied in and back, the pre-tanh output is the controller's."""
    from codesign_basics.config import SineConfig
    from codesign_basics.sine import SineController
    from codesign_optimizers.ppo import _policy

    controller = SineController(SineConfig(frequencies=[6.0, 12.0], phases=3, bias=bias))
    controller.setup(2, 3, 0.01, np.random.default_rng(0))
    with torch.no_grad():
        controller.beta.copy_(torch.randn(controller.beta.shape, generator=torch.Generator().manual_seed(0)))
        actor, _ = _policy("sine", controller)
        w, b = (p.clone() for p in actor.to_sb3())
        basis = torch.sin(torch.tensor([6.0, 12.0])[:, None] * 0.37 + torch.arange(3) * (2 * np.pi / 3))  # (I, J)
        alpha, beta = controller.alpha.clone(), controller.beta.clone()
        expected = (alpha * basis).sum(dim=(1, 2)) + (beta.sum(dim=(1, 2)) if bias == "per_basis" else beta)
        torch.testing.assert_close(w @ basis.flatten() + b, expected)
        actor.from_sb3([2 * w, b + 1])  # back: the new weights land in the controller's own shapes
        assert controller.beta.shape == beta.shape
        torch.testing.assert_close(controller.alpha, 2 * alpha)
        summed = controller.beta.sum(dim=(1, 2)) if bias == "per_basis" else controller.beta
        torch.testing.assert_close(summed, b + 1)


@pytest.mark.parametrize("recipe", [TOY_PPO, NORMALIZED], ids=["raw", "normalized"])
def test_resumed_run_ends_with_the_numbers_of_an_uninterrupted_one(tmp_path, recipe):
    whole = runner.run(resolve_recipe(recipe), run_dir=tmp_path / "whole", progress=False)
    half = {**recipe, "optimizer": {**recipe["optimizer"], "total_timesteps": 64}}
    part = runner.run(resolve_recipe(half), run_dir=tmp_path / "part", progress=False)
    config = part / "config.yaml"
    config.write_text(config.read_text().replace("total_timesteps: 64", "total_timesteps: 192"))  # the run goes on
    runner.resume(part, progress=False)
    drop = ("wall_time",)
    assert [{k: v for k, v in r.items() if k not in drop} for r in metrics(part)] == \
        [{k: v for k, v in r.items() if k not in drop} for r in metrics(whole)]


@pytest.mark.parametrize("optimize", ["design", "both"])
def test_ppo_refuses_to_optimize_the_design_when_the_recipe_is_validated(optimize):
    recipe = {**TOY_PPO, "optimizer": {**TOY_PPO["optimizer"], "optimize": optimize}}
    pattern = rf"optimizer.optimize: '{optimize}' is not a valid choice; .*allowed: control"
    with pytest.raises(RecipeError, match=pattern):
        resolve_recipe(recipe)


@pytest.mark.parametrize("change, pattern", [
    ({"optimizer": {"timesteps_per_iteration": 50}}, r"optimizer.timesteps_per_iteration: 50 is not a multiple "
                                                     r"of optimizer.n_steps \(32\)"),
    ({"controller": {"name": "mlp", "output": "sine_weights"}}, r"optimizer.policy 'mlp' needs the 'mlp' "
                                                                r"controller with output: action"),
    ({"controller": {"name": "sine"}}, r"optimizer.policy 'mlp' needs the 'mlp' controller.*got SineController"),
    ({"optimizer": {"policy": "sine"}}, r"optimizer.policy 'sine' needs the 'sine' controller"),
    ({"optimizer": {"policy": "sine", "normalize": "observations"}},
     r"optimizer.normalize: 'observations' normalises observations, but optimizer.policy 'sine' observes only the "
     r"time \(allowed with it: none, rewards\)"),
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
