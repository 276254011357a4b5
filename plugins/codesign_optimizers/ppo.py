"""PPO (stable-baselines3) on the controller of a fixed design (SoftZoo appendix "Reinforcement Learning").

SB3 trains a Gaussian policy whose *mean* is, by construction, exactly the recipe's controller:

- ``policy: mlp`` needs the ``mlp`` controller (``output: action``). SB3's actor has the same widths
  and activation, and a :class:`TanhSquash` wrapper maps its sample ``a`` to ``bound * tanh(a)``,
  the controller's output layer, so the deterministic policy is ``bound * tanh(MLP(obs))``.
- ``policy: sine`` needs the ``sine`` controller. The policy sees the time ``t = step * control_dt``
  only; its features extractor computes the controller's basis ``sin(omega_i t + phi_j)`` and a
  linear head (no hidden layer) holds ``alpha`` (weights) and ``sum_ij beta`` (bias).

PPO starts from the controller's (seeded) initial weights and, after every iteration, the actor's
weights are copied back into the controller, so `best/controller.pt` and ``codesign eval`` replay
the deterministic policy PPO learned, not an approximation of it.
"""

from __future__ import annotations

import copy
import math
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
import torch
from stable_baselines3 import PPO as SB3PPO
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from stable_baselines3.common.vec_env import DummyVecEnv

from codesign.artifacts import play
from codesign.errors import RecipeError
from codesign.interfaces import Controller, DesignFields, Environment, Optimizer, Representation
from codesign_optimizers.common import BestKeeper, parameter_groups
from codesign_optimizers.config import PPOConfig

LOSSES = ("policy_gradient_loss", "value_loss", "entropy_loss", "approx_kl", "clip_fraction", "explained_variance",
          "std")
PRE_TANH_LIMIT = 100.0


def action_bound(controller: Controller, environment: Environment) -> float:
    """The controller config's `bound`, else the scene's `max_action`, else 1."""
    bound = getattr(getattr(controller, "config", None), "bound", None)
    if bound is None:
        bound = getattr(getattr(environment, "scene", None), "max_action", None)
    return float(bound if bound is not None else 1.0)


class FixedDesignEnv(gymnasium.Env):
    """Any codesign `Environment` with a fixed design as a Gymnasium environment (float32 observations).

    Episode seeds come from the wrapper's own generator (``episode_seed``), not from Gymnasium's
    reset seed, so episodes are reproducible, checkpointable (``episodes.bit_generator.state``)
    and unaffected by SB3 re-seeding its vectorised env. Reaching the horizon is a truncation;
    an earlier `done` a termination. Returns of finished episodes accumulate in ``returns``.
    With ``time_observation`` the observation is the time ``[step * control_dt]`` (open-loop policies).
    """

    metadata: dict[str, Any] = {"render_modes": []}

    def __init__(self, environment: Environment, design: DesignFields | None, bound: float, episode_seed: int = 0,
                 time_observation: bool = False) -> None:
        self.env, self.design, self.time_observation = environment, design, time_observation
        self.episodes = np.random.default_rng(episode_seed)
        self.action_space = gymnasium.spaces.Box(-bound, bound, (environment.action_dim,), dtype=np.float32)
        if time_observation:
            self.observation_space = gymnasium.spaces.Box(0.0, np.inf, (1,), dtype=np.float32)
        elif getattr(environment, "observation_space", None) is not None:
            self.observation_space = environment.observation_space
        else:
            self.observation_space = gymnasium.spaces.Box(-np.inf, np.inf, (environment.observation_dim,),
                                                          dtype=np.float32)
        self.returns: list[float] = []
        self.t, self.total = 0, 0.0

    def _observe(self, observation: np.ndarray) -> np.ndarray:
        if self.time_observation:
            return np.array([self.t * self.env.control_dt], dtype=np.float32)
        return np.asarray(observation, dtype=np.float32)

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        self.t, self.total = 0, 0.0
        observation = self.env.reset(self.design, seed=int(self.episodes.integers(2**31)))
        return self._observe(observation), {}

    def step(self, action) -> tuple[np.ndarray, float, bool, bool, dict]:
        result = self.env.step(np.asarray(action, dtype=np.float64))
        self.t += 1
        self.total += float(result.reward)
        truncated = self.t >= self.env.horizon
        terminated = bool(result.done) and not truncated
        if truncated or terminated:
            self.returns.append(self.total)
        return self._observe(result.observation), float(result.reward), terminated, truncated, result.info


class TanhSquash(gymnasium.ActionWrapper):
    """Policy samples a -> bound * tanh(a): the controllers' own output layer, so the SB3 Gaussian
    mean passes through exactly the function the controller applies at evaluation. SB3 wants a
    finite Box and clips samples to it; at +-PRE_TANH_LIMIT tanh is 1 in float64, so clipping changes nothing."""

    def __init__(self, env: FixedDesignEnv) -> None:
        super().__init__(env)
        self.bound = float(env.action_space.high[0])
        self.action_space = gymnasium.spaces.Box(-PRE_TANH_LIMIT, PRE_TANH_LIMIT, env.action_space.shape,
                                                 dtype=np.float32)

    def action(self, action: np.ndarray) -> np.ndarray:
        return self.bound * np.tanh(np.asarray(action, dtype=np.float64))


class SineBasis(BaseFeaturesExtractor):
    """Time observation [t] -> sin(omega_i t + phi_j), flattened (I, J) as in `SineController`."""

    def __init__(self, observation_space: gymnasium.spaces.Box, frequencies: list[float], phases: int) -> None:
        super().__init__(observation_space, len(frequencies) * phases)
        self.register_buffer("omega", torch.tensor(frequencies, dtype=torch.float32))
        self.register_buffer("phi", torch.arange(phases, dtype=torch.float32) * (2 * math.pi / phases))

    def forward(self, observations: torch.Tensor) -> torch.Tensor:
        t = observations[:, :1, None]  # (B, 1, 1)
        return torch.sin(self.omega[None, :, None] * t + self.phi[None, None, :]).flatten(1)


class PPO(Optimizer):
    """One iteration = `timesteps_per_iteration` environment steps of SB3's PPO, then a deterministic
    evaluation episode through the recipe's controller (with the seed `codesign eval` uses first, the
    same every iteration so iterations compare on equal terms); the best one goes to `best/`.

    Every iteration starts a fresh episode and collects whole rollouts (`timesteps_per_iteration`
    must be a multiple of `n_steps`), so nothing lives between iterations except the policy, Adam,
    the counters and the random generators: a resumed run continues exactly.
    """

    def __init__(self, config: PPOConfig) -> None:
        if config.timesteps_per_iteration % config.n_steps:
            raise RecipeError(f"invalid recipe: optimizer.timesteps_per_iteration: {config.timesteps_per_iteration} "
                              f"is not a multiple of optimizer.n_steps ({config.n_steps}); iterations must end on "
                              "rollout boundaries so a resumed run continues exactly")
        self.config = config
        self.iterations = math.ceil(config.total_timesteps / config.timesteps_per_iteration)
        self.iteration = 0

    def setup(self, environment: Environment, representation: Representation, controller: Controller, *,
              rng: np.random.Generator, run_dir: Path) -> None:
        cfg = self.config  # checked before anything simulates: PPO trains the controller only
        parameter_groups(cfg.optimize, representation, controller, supported=("control",))
        self.environment, self.controller = environment, controller
        self.actor, policy_kwargs = _policy(cfg.policy, controller)
        self.eval_seed = int(rng.integers(2**31))  # first draw: the seed `codesign eval` plays its first episode with
        ppo_seed, episode_seed = (int(s) for s in rng.integers(2**31, size=2))
        self.design = representation()
        self.gym = FixedDesignEnv(environment, self.design, action_bound(controller, environment), episode_seed,
                                  time_observation=cfg.policy == "sine")
        self.model = SB3PPO("MlpPolicy", DummyVecEnv([lambda: TanhSquash(self.gym)]), n_steps=cfg.n_steps,
                            batch_size=cfg.batch_size, n_epochs=cfg.n_epochs, gamma=cfg.gamma,
                            gae_lambda=cfg.gae_lambda, ent_coef=cfg.ent_coef, learning_rate=cfg.learning_rate,
                            clip_range=cfg.clip_range, policy_kwargs=policy_kwargs, seed=ppo_seed, device="cpu",
                            verbose=0)
        self.model.set_logger(Logger(folder=None, output_formats=[]))
        with torch.no_grad():  # PPO starts from the controller's own (seeded) initialisation
            for dst, src in zip(self._sb3_params(), self.actor.to_sb3()):
                dst.copy_(src)
        self.best = BestKeeper(environment, controller, run_dir)

    def _sb3_params(self) -> list[torch.Tensor]:
        layers = [m for m in self.model.policy.mlp_extractor.policy_net if isinstance(m, torch.nn.Linear)]
        return [p for m in [*layers, self.model.policy.action_net] for p in (m.weight, m.bias)]

    def step(self) -> dict[str, float]:
        cfg, model = self.config, self.model
        self.gym.returns.clear()
        model._last_obs = None  # a fresh episode per iteration: nothing mid-episode outlives an iteration
        remaining = cfg.total_timesteps - model.num_timesteps
        model.learn(min(cfg.timesteps_per_iteration, remaining), reset_num_timesteps=False, log_interval=None)
        with torch.no_grad():
            self.actor.from_sb3([p.detach() for p in self._sb3_params()])
        record = play(self.environment, self.design, self.controller, seed=self.eval_seed)
        self.best.offer(record.episode_return, self.design, record, self.iteration)
        self.iteration += 1
        metrics = {"episode_return": record.episode_return, "best_return": self.best.best_return,
                   "timesteps": float(model.num_timesteps), "train_episodes": float(len(self.gym.returns))}
        if self.gym.returns:
            metrics["train_return"] = float(np.mean(self.gym.returns))
        logged = model.logger.name_to_value
        metrics.update({k: float(logged[f"train/{k}"]) for k in LOSSES if f"train/{k}" in logged})
        return metrics

    def state_dict(self) -> dict:
        model = self.model
        return copy.deepcopy({
            "iteration": self.iteration, "best_return": self.best.best_return, "policy": model.policy.state_dict(),
            "adam": model.policy.optimizer.state_dict(), "num_timesteps": model.num_timesteps,
            "n_updates": model._n_updates, "episode_num": model._episode_num,
            "episodes": self.gym.episodes.bit_generator.state, "numpy_random": np.random.get_state(),
            "torch_random": torch.get_rng_state()})

    def load_state_dict(self, state: dict) -> None:
        model = self.model
        self.iteration, self.best.best_return = state["iteration"], state["best_return"]
        model.policy.load_state_dict(state["policy"])
        model.policy.optimizer.load_state_dict(state["adam"])
        model.num_timesteps, model._n_updates, model._episode_num = (
            state["num_timesteps"], state["n_updates"], state["episode_num"])
        self.gym.episodes.bit_generator.state = state["episodes"]
        np.random.set_state(state["numpy_random"])
        torch.set_rng_state(state["torch_random"])
        with torch.no_grad():
            self.actor.from_sb3([p.detach() for p in self._sb3_params()])


class _Actor:
    """Maps the controller's parameters to SB3's actor ([W, b] per layer) and back."""

    def __init__(self, params: list[torch.Tensor], to_sb3, from_sb3) -> None:
        self.params, self._to, self._from = params, to_sb3, from_sb3

    def to_sb3(self) -> list[torch.Tensor]:
        return self._to(self.params)

    def from_sb3(self, sb3: list[torch.Tensor]) -> None:
        for p, v in zip(self.params, self._from(sb3)):
            p.copy_(v.to(p.dtype))


def _policy(policy: str, controller: Controller) -> tuple[_Actor, dict]:
    """Check the recipe's controller fits `optimizer.policy`; return the weight mapping and SB3 policy kwargs."""
    from codesign_basics.mlp import ACTIVATIONS, MLPController
    from codesign_basics.sine import SineController

    if policy == "mlp":
        if not isinstance(controller, MLPController) or controller.config.output != "action":
            raise RecipeError(f"invalid recipe: controller.name: optimizer.policy 'mlp' needs the 'mlp' controller "
                              f"with output: action (so `codesign eval` replays the learned policy); got "
                              f"{type(controller).__name__}{_output(controller)}")
        cfg = controller.config
        kwargs = {"net_arch": {"pi": list(cfg.hidden), "vf": list(cfg.hidden)},
                  "activation_fn": ACTIVATIONS[cfg.activation]}
        same = lambda ps: [p.detach().float() for p in ps]  # noqa: E731 - Linear weights map one to one
        return _Actor(controller.parameters(), same, lambda ps: ps), kwargs
    if not isinstance(controller, SineController):
        raise RecipeError(f"invalid recipe: controller.name: optimizer.policy 'sine' needs the 'sine' controller "
                          f"(so `codesign eval` replays the learned policy); got {type(controller).__name__}")
    cfg, (alpha, beta) = controller.config, controller.parameters()
    n_basis = alpha.shape[1] * alpha.shape[2]
    kwargs = {"net_arch": {"pi": [], "vf": [64, 64]}, "features_extractor_class": SineBasis,
              "features_extractor_kwargs": {"frequencies": list(cfg.frequencies), "phases": cfg.phases}}

    def to_sb3(ps: list[torch.Tensor]) -> list[torch.Tensor]:
        return [ps[0].detach().reshape(len(ps[0]), -1).float(), ps[1].detach().sum(dim=(1, 2)).float()]

    def from_sb3(ps: list[torch.Tensor]) -> list[torch.Tensor]:  # the bias spread evenly over beta's entries
        return [ps[0].reshape(alpha.shape), (ps[1] / n_basis)[:, None, None].expand(beta.shape)]

    return _Actor([alpha, beta], to_sb3, from_sb3), kwargs


def _output(controller: Controller) -> str:
    output = getattr(getattr(controller, "config", None), "output", None)
    return f" (output: {output})" if output is not None else ""
